//! Locks: the host's emergency stops (docs/estop.md). A lock is a motion
//! source of a different kind: while it is engaged, every source below its
//! priority is suppressed and, unless a source at or above it drives, the
//! motors get STOP.
//!
//! [`Locks`] is one per host (provided through `builtin::Services`, like
//! `Standings`), so an engaged lock survives a set activation: the arbiter
//! of the new set reads the same board. Anyone may engage (the portal's
//! STOP button, the network platform's `ESTOP`, `subsume estop`, a
//! configured feed such as the bumper); a lock is released only by an
//! explicit release (never by a timeout, never by a feed). Who may release
//! is the callers' check (a role that may drive), not this board's.
//!
//! Every engage and release is kept in a bounded history (for the report
//! and the live view) and handed to an optional sink (the audit log's
//! writer, off the control loop); a change wakes the control loop so the
//! arbiter decides within the cycle.

use std::collections::{BTreeMap, VecDeque};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::mpsc::SyncSender;
use std::sync::{Arc, Mutex};

use serde::Serialize;

use super::control_loop::Waker;

/// The lock the portal, the network platform and the command line engage
/// when they name none. Unless the robot file declares it, it is above
/// every source.
pub const DEFAULT_LOCK: &str = "estop";

/// Engage and release events kept for the report and the live view (the
/// audit log keeps every one): a stuck button or a chattering feed cannot
/// grow the host's memory.
pub const MAX_LOCK_HISTORY: usize = 256;

/// Longest lock name, user name or "how" kept in an event: they come from
/// the robot file and from authenticated users, and are shown in the portal.
pub const MAX_LOCK_TEXT: usize = 64;

/// An engaged lock: who engaged it, how, and when (ms since the Unix epoch).
#[derive(Clone, Debug, PartialEq, Eq, Serialize, schemars::JsonSchema)]
pub struct Engagement {
    pub lock: String,
    pub by: String,
    pub how: String,
    pub since_ms: u64,
}

/// One engage or release.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, schemars::JsonSchema)]
pub struct LockEvent {
    pub lock: String,
    /// "engage" or "release".
    pub action: &'static str,
    pub by: String,
    pub how: String,
    /// When, in ms since the Unix epoch.
    pub at_ms: u64,
    /// On a release: how long the lock was engaged, and who engaged it.
    pub held_ms: Option<u64>,
    pub engaged_by: Option<String>,
}

#[derive(Debug, Default)]
struct Board {
    engaged: BTreeMap<String, Engagement>,
    history: VecDeque<LockEvent>,
    events: u64,
    sink: Option<SyncSender<LockEvent>>,
    waker: Option<Waker>,
}

impl Board {
    fn record(&mut self, event: LockEvent) {
        if self.history.len() == MAX_LOCK_HISTORY {
            self.history.pop_front();
        }
        self.events += 1;
        if let Some(sink) = &self.sink
            && sink.try_send(event.clone()).is_err()
        {
            tracing::error!("the audit log is behind: lock event '{} {}' is not in it", event.action, event.lock);
        }
        self.history.push_back(event);
    }
}

fn kept(text: &str) -> String {
    crate::contract::clip(text).chars().take(MAX_LOCK_TEXT).collect()
}

/// The host's locks: which are engaged, and what happened to them.
#[derive(Clone, Debug, Default)]
pub struct Locks {
    board: Arc<Mutex<Board>>,
    /// Bumped on every engage and release, so the arbiter checks for news
    /// with one load per cycle.
    generation: Arc<AtomicU64>,
}

impl Locks {
    /// A board that wakes the control loop on every change.
    pub fn with_waker(waker: Waker) -> Locks {
        let locks = Locks::default();
        if let Ok(mut board) = locks.board.lock() {
            board.waker = Some(waker);
        }
        locks
    }

    /// Hands every later event to `sink` as well (without waiting: a full
    /// sink loses the event there, with an error in the log).
    pub fn set_sink(&self, sink: SyncSender<LockEvent>) {
        if let Ok(mut board) = self.board.lock() {
            board.sink = Some(sink);
        }
    }

    /// Engages `lock` (by `by`, through `how`, at `at_ms`). Returns false
    /// when it was engaged already (nothing changes: the first engagement
    /// stands).
    pub fn engage(&self, lock: &str, by: &str, how: &str, at_ms: u64) -> bool {
        let Ok(mut board) = self.board.lock() else { return false };
        let lock = kept(lock);
        if board.engaged.contains_key(&lock) {
            return false;
        }
        let (by, how) = (kept(by), kept(how));
        board
            .engaged
            .insert(lock.clone(), Engagement { lock: lock.clone(), by: by.clone(), how: how.clone(), since_ms: at_ms });
        board.record(LockEvent { lock, action: "engage", by, how, at_ms, held_ms: None, engaged_by: None });
        self.generation.fetch_add(1, Ordering::Release);
        if let Some(waker) = &board.waker {
            waker.wake();
        }
        true
    }

    /// Releases `lock`, or every engaged lock when `lock` is `None`.
    /// Returns the releases made: (lock, ms it was engaged).
    pub fn release(&self, lock: Option<&str>, by: &str, how: &str, at_ms: u64) -> Vec<(String, u64)> {
        let Ok(mut board) = self.board.lock() else { return Vec::new() };
        let names: Vec<String> = match lock {
            Some(name) => board.engaged.keys().filter(|k| **k == kept(name)).cloned().collect(),
            None => board.engaged.keys().cloned().collect(),
        };
        let mut released = Vec::new();
        for name in names {
            let Some(engagement) = board.engaged.remove(&name) else { continue };
            let held_ms = at_ms.saturating_sub(engagement.since_ms);
            board.record(LockEvent {
                lock: name.clone(),
                action: "release",
                by: kept(by),
                how: kept(how),
                at_ms,
                held_ms: Some(held_ms),
                engaged_by: Some(engagement.by),
            });
            released.push((name, held_ms));
        }
        if !released.is_empty() {
            self.generation.fetch_add(1, Ordering::Release);
            if let Some(waker) = &board.waker {
                waker.wake();
            }
        }
        released
    }

    /// The engaged locks, by name.
    pub fn engaged(&self) -> Vec<Engagement> {
        self.board.lock().map(|b| b.engaged.values().cloned().collect()).unwrap_or_default()
    }

    /// Whether any lock is engaged.
    pub fn any_engaged(&self) -> bool {
        self.board.lock().map(|b| !b.engaged.is_empty()).unwrap_or(true)
    }

    /// The latest events (at most [`MAX_LOCK_HISTORY`]), oldest first, and
    /// how many there were in all.
    pub fn history(&self) -> (Vec<LockEvent>, u64) {
        self.board.lock().map(|b| (b.history.iter().cloned().collect(), b.events)).unwrap_or_default()
    }

    /// Changes with every engage and release.
    pub fn generation(&self) -> u64 {
        self.generation.load(Ordering::Acquire)
    }
}

pub use crate::walltime::unix_now_ms;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn engage_is_idempotent_and_release_says_how_long() {
        let locks = Locks::default();
        let (tx, rx) = std::sync::mpsc::sync_channel(8);
        locks.set_sink(tx);
        let g0 = locks.generation();
        assert!(locks.engage("estop", "ann", "portal", 1_000));
        assert!(!locks.engage("estop", "bob", "teleop", 2_000), "the first engagement stands");
        assert_eq!(locks.engaged()[0].by, "ann");
        assert_ne!(locks.generation(), g0);
        assert!(locks.release(Some("other"), "bob", "teleop", 3_000).is_empty());
        assert_eq!(locks.release(None, "bob", "teleop", 3_500), vec![("estop".to_string(), 2_500)]);
        assert!(!locks.any_engaged());
        let events: Vec<LockEvent> = rx.try_iter().collect();
        assert_eq!(events.len(), 2);
        assert_eq!(events[1].engaged_by.as_deref(), Some("ann"));
        assert_eq!(locks.history().1, 2);
    }

    #[test]
    fn operators_engaging_and_releasing_at_once_lose_no_change() {
        // Eight threads (portal users, teleop sessions, a bumper) engage and
        // release the same two locks at once, many times. Every successful
        // engage is released exactly once, and every engage and release is
        // one event and one generation step: nothing lost, nothing doubled.
        let locks = Locks::default();
        let threads = 8;
        let rounds = 500;
        let (engaged, released): (u64, u64) = std::thread::scope(|s| {
            let handles: Vec<_> = (0..threads)
                .map(|t| {
                    let locks = locks.clone();
                    s.spawn(move || {
                        let lock = if t % 2 == 0 { "estop" } else { "dock" };
                        let (mut e, mut r) = (0u64, 0u64);
                        for i in 0..rounds {
                            if locks.engage(lock, &format!("user{t}"), "test", i) {
                                e += 1;
                            }
                            r += locks.release(Some(lock), &format!("user{t}"), "test", i + 1).len() as u64;
                        }
                        (e, r)
                    })
                })
                .collect();
            handles.into_iter().map(|h| h.join().unwrap()).fold((0, 0), |a, b| (a.0 + b.0, a.1 + b.1))
        });
        assert!(engaged > 0);
        assert_eq!(engaged, released, "every engagement was released exactly once");
        assert!(locks.engaged().is_empty());
        let (_, total) = locks.history();
        assert_eq!(total, engaged + released);
        assert_eq!(locks.generation(), engaged + released);
    }

    #[test]
    fn the_history_is_bounded() {
        let locks = Locks::default();
        for i in 0..(MAX_LOCK_HISTORY as u64) {
            locks.engage("estop", "a", "cli", i);
            locks.release(None, "a", "cli", i);
        }
        let (history, total) = locks.history();
        assert_eq!(history.len(), MAX_LOCK_HISTORY);
        assert_eq!(total, 2 * MAX_LOCK_HISTORY as u64);
    }
}
