//! The emergency stop's use cases (docs/estop.md): engage (any logged-in
//! user, viewers included: anyone watching may stop the robot) and release
//! (a deliberate action of a user who may drive), on the host's one
//! `Locks` board; and the audit of every engage and release, whoever made
//! it (the portal, the network platform, a feed), written off the control
//! loop by one thread.
//!
//! Engaging does not wait for the store: the lock is engaged first, its
//! audit line follows (through the board's sink). A refused release writes
//! its own line at once.

use std::sync::Arc;
use std::sync::mpsc::{Receiver, sync_channel};

use serde::Serialize;

use super::{DeployError, Deployer};
use crate::runtime::locks::unix_now_ms;
use crate::runtime::{DEFAULT_LOCK, Engagement, LockEvent, Locks};
use crate::store::users::Principal;
use crate::store::{Outcome, Store};

/// Lock events waiting for the audit log: engages and releases are
/// deliberate acts of people (or a bumper), so this only fills when the
/// store's disk stalls; past it an event is logged as lost, never waited on.
pub const AUDIT_QUEUE: usize = 1024;

/// What an engage did.
#[derive(Clone, Debug, Serialize, schemars::JsonSchema)]
pub struct Engaged {
    pub lock: String,
    /// False when the lock was engaged already (the first engagement stands).
    pub newly: bool,
    pub engaged: Vec<Engagement>,
}

/// One release: the lock and how long it was engaged.
#[derive(Clone, Debug, Serialize, schemars::JsonSchema)]
pub struct Released {
    pub lock: String,
    pub held_ms: u64,
}

/// The locks as the portal shows them.
#[derive(Clone, Debug, Serialize, schemars::JsonSchema)]
pub struct LocksView {
    pub engaged: Vec<Engagement>,
    pub events: Vec<LockEvent>,
    pub events_total: u64,
}

impl Deployer {
    /// The host's locks (one board for every set this host runs).
    fn locks(&self) -> Result<Arc<Locks>, DeployError> {
        self.services.get::<Locks>().ok_or_else(|| DeployError::Host("this host has no emergency stop board".into()))
    }

    /// Engages the emergency stop for `user`, through `how`.
    pub fn engage_lock(&self, user: &Principal, how: &str) -> Result<Engaged, DeployError> {
        let locks = self.locks()?;
        let newly = locks.engage(DEFAULT_LOCK, &user.name, how, unix_now_ms());
        if newly {
            tracing::warn!("{} engaged the emergency stop over {how}", user.name);
        }
        Ok(Engaged { lock: DEFAULT_LOCK.into(), newly, engaged: locks.engaged() })
    }

    /// Releases `lock` (or every engaged lock) for `user`, who must be
    /// allowed to drive.
    pub fn release_lock(&self, user: &Principal, lock: Option<&str>, how: &str) -> Result<Vec<Released>, DeployError> {
        let target = lock.unwrap_or("every lock");
        if let Err(refused) = self.authorise_drive(user) {
            let detail = format!("over {how}: {refused}");
            if let Ok(writer) = self.store.lock() {
                writer.record(&user.name, "release-lock", target, Outcome::Refused(&detail));
            }
            return Err(DeployError::Forbidden(format!("{refused}: releasing a lock needs a role that may drive")));
        }
        let locks = self.locks()?;
        let released = locks.release(lock, &user.name, how, unix_now_ms());
        if released.is_empty() {
            return Err(DeployError::Conflict(match lock {
                Some(name) => format!("lock '{}' is not engaged", crate::contract::clip(name)),
                None => "no lock is engaged".into(),
            }));
        }
        tracing::warn!("{} released {} over {how}", user.name, target);
        Ok(released.into_iter().map(|(lock, held_ms)| Released { lock, held_ms }).collect())
    }

    /// The engaged locks and the latest events.
    pub fn locks_view(&self) -> Result<LocksView, DeployError> {
        let locks = self.locks()?;
        let (events, events_total) = locks.history();
        Ok(LocksView { engaged: locks.engaged(), events, events_total })
    }
}

/// Hands every event of `locks` to a thread that writes it to `store`'s
/// audit log.
pub(super) fn audit_locks(locks: &Locks, store: Arc<Store>) -> Result<(), DeployError> {
    let (sink, events) = sync_channel(AUDIT_QUEUE);
    locks.set_sink(sink);
    std::thread::Builder::new()
        .name("lock-audit".into())
        .spawn(move || write_audit(&events, &store))
        .map(drop)
        .map_err(|e| DeployError::Host(format!("cannot start the lock audit: {e}")))
}

fn write_audit(events: &Receiver<LockEvent>, store: &Store) {
    for event in events {
        let detail = match (event.held_ms, &event.engaged_by) {
            (Some(ms), Some(by)) => {
                format!("over {}, after {:.1} s engaged (by {by})", event.how, ms as f64 / 1000.0)
            }
            _ => format!("over {}", event.how),
        };
        let action = format!("{}-lock", event.action);
        match store.lock() {
            Ok(writer) => writer.record(&event.by, &action, &event.lock, Outcome::Ok(&detail)),
            Err(e) => tracing::error!("cannot record '{action} {}' by {} in the audit log: {e}", event.lock, event.by),
        }
    }
}
