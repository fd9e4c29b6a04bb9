//! The remote lab (docs/lab.md): a researcher's experiment as a thing the
//! host knows. An experiment is a staged set, a duration and a label; it is
//! checked, run first in the simulator ([`preflight`], a few times with
//! seeded timing: [`preflight_runs`]), queued fairly
//! ([`queue`]), run on the robot from a fresh start while recording, stopped
//! on time, and its results kept ([`bundle`]); between experiments the
//! robot runs the owner's baseline.
//!
//! This file is the core: [`Lab`], its in-memory book of records,
//! [`LabError`] and `transition` (every state change, stored and audited
//! before anyone is told, kept to `ExperimentState::may_enter`); `audit`
//! has `audited` (a use case's one audit line, refused or not), and
//! `visibility` who sees which experiments. Each use case
//! is an `impl Lab` in a file of its own, in `deploy`'s shape: `submit`,
//! `cancel`, `views` (list, get, overview, results), `owner` (settings,
//! baseline, pause, the manual reset), `reservations`, `kit`, `metrics`,
//! `robots` (a lab server's robots and STOP). Pure decisions: `queue`
//! (what starts next, ETAs, limits, reservations, a lab server's
//! placement), `verdict` (the preflight's verdict), `episode` (a task's
//! end conditions), and the preflight
//! outcome's state in `runner`, and a lab's Zenoh router config
//! (`router_config`). Two threads drive the lab: the checker,
//! and on a robot the runner ([`runner`]) or on a lab server the
//! dispatcher ([`server`]).
//!
//! Invariants:
//! - every state change is stored (time, cause) before anyone is told, and
//!   audit-logged;
//! - one experiment runs at a time; while it runs, nobody else changes what
//!   runs (`deploy::ExperimentGate`);
//! - a user sees only their own experiments (an admin sees every one): a
//!   request for someone else's gets the answer one that does not exist
//!   gets;
//! - the per-user limits are checked under the lab's lock, so concurrent
//!   submissions cannot pass them together;
//! - every path that ends a run on the robot brings the baseline back (or
//!   engages the emergency stop when it cannot);
//! - nothing queued or finished is lost on a restart: experiments that were
//!   running are marked `aborted: host stopped` with what they recorded,
//!   those in their checks are checked again.

mod audit;
pub mod bundle;
mod cancel;
pub mod episode;
mod kit;
pub mod kit_submission;
pub mod leaderboard;
mod mail;
mod maintenance;
pub mod materialize;
mod metrics;
mod owner;
pub mod preflight;
pub mod preflight_runs;
pub mod queue;
mod reservations;
pub mod reset;
mod robot_dispatch;
mod robot_files;
pub mod robot_link;
mod robots;
pub mod router_config;
mod runner;
pub mod selftest;
pub mod server;
mod submit;
pub mod transfer;
pub mod verdict;
mod views;
mod visibility;
pub mod wire;

pub use self::metrics::{LabMetrics, PREFLIGHT_BUCKETS_S};
pub use self::robots::RobotStop;
pub use self::submit::{MAX_SUBMISSIONS_PER_WINDOW, SUBMISSION_WINDOW_MS, Submission};
pub use self::views::{ExperimentView, LabView};
pub use self::visibility::{live_status_for, sees_experiments_of};
pub use crate::notify::mail::Subscription as MailSubscription;

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::time::Duration;

use thiserror::Error;

use self::preflight::PreflightCommand;
use self::visibility::visible;
use crate::deploy::{DeployError, Deployer, Diagnostics, SetImport};
use crate::notify::{self, ExperimentFacts, Notifier};
use crate::runtime::locks::unix_now_ms;
use crate::store::experiments::{ExperimentRecord, ExperimentState, IllegalTransition, LabState};
use crate::store::{Outcome, SetRecord, Store, StoreError};

/// Shortest experiment, seconds: a run must last long enough to record.
pub const MIN_DURATION_S: f64 = 1.0;
/// Longest any owner may allow, seconds (the owner's `max_duration_s` is
/// checked against it): a day.
pub const MAX_DURATION_CAP_S: f64 = 24.0 * 3600.0;
/// How long a cancel or an admin's activation waits for the running
/// experiment to end before it answers.
pub const END_WAIT: Duration = Duration::from_secs(30);
/// How far ahead a reservation may be booked: a user cannot hold the
/// calendar for years.
pub const MAX_BOOKING_AHEAD: Duration = Duration::from_secs(30 * 24 * 3600);
/// The time between one experiment's end and the next one's start that
/// ETAs count (the reset and two activations).
pub const TURNAROUND: Duration = Duration::from_secs(1);

/// Why a lab request was refused or failed.
#[derive(Debug, Error)]
pub enum LabError {
    #[error("{0}")]
    Forbidden(String),
    /// Nothing by that id (or not the user's).
    #[error("{0}")]
    NotFound(String),
    #[error("{0}")]
    BadRequest(String),
    #[error("{0}")]
    Conflict(String),
    /// Over a per-user limit; frees after this many seconds, when known.
    #[error("{message}")]
    OverLimit { message: String, retry_after_s: Option<u64> },
    /// The set does not validate (the diagnostics `subsume check` prints).
    #[error("{0}")]
    Invalid(Diagnostics),
    #[error(transparent)]
    Store(#[from] StoreError),
    /// A state change the experiment's life does not allow: the host's bug.
    #[error(transparent)]
    Illegal(#[from] IllegalTransition),
    #[error("{0}")]
    Host(String),
}

impl From<DeployError> for LabError {
    fn from(e: DeployError) -> LabError {
        match e {
            DeployError::Invalid(d) => LabError::Invalid(d),
            DeployError::Forbidden(m) => LabError::Forbidden(m),
            DeployError::NotFound(m) => LabError::NotFound(m),
            DeployError::Store(StoreError::NoSet(id)) => LabError::NotFound(format!("no set {id}")),
            DeployError::Conflict(m) => LabError::Conflict(m),
            DeployError::BadRequest(m) => LabError::BadRequest(m),
            DeployError::Store(e) => LabError::Store(e),
            other => LabError::Host(other.to_string()),
        }
    }
}

impl LabError {
    fn is_failure(&self) -> bool {
        matches!(self, LabError::Store(_) | LabError::Host(_) | LabError::Illegal(_))
    }
}

/// What starting the lab needs.
#[derive(Clone, Debug)]
pub struct LabOptions {
    pub preflight: PreflightCommand,
    /// What this host is in a lab of several robots.
    pub role: LabRole,
}

/// What a host is in a lab of several robots (docs/lab.md, "Several
/// robots").
#[derive(Clone, Debug, Default)]
pub enum LabRole {
    /// One robot, its own lab: experiments are submitted on its portal.
    #[default]
    Alone,
    /// A robot of lab `lab`: its experiments come from that lab's server
    /// only ([`robot_link`]).
    Joined { lab: String },
    /// The lab server: no robot; experiments are dispatched to the lab's
    /// robots ([`server`]).
    Server(Arc<server::Fleet>),
}

/// The lab's state in memory: the records as stored, and what only this
/// process knows (who asked to cancel, what runs on the robot).
#[derive(Default)]
struct Book {
    experiments: BTreeMap<u64, ExperimentRecord>,
    lab: LabState,
    /// Cancels asked for experiments in preflight or running: id -> by.
    cancels: BTreeMap<u64, String>,
    /// An admin's activation waits for the running experiment to end:
    /// (experiment, by, what the admin does).
    preempt: Option<(u64, String, String)>,
    running: Option<runner::OnRobot>,
    /// The queued experiment the runner is starting (its graph is being
    /// built): a cancel waits for it to run, then ends it.
    starting: Option<u64>,
    /// On a lab server: the experiments being handed to a robot (a cancel
    /// waits for the answer, then ends it).
    dispatching: BTreeSet<u64>,
    /// Experiments to abort (not cancel) on the robot: id -> cause (a lab
    /// that was lost).
    aborts: BTreeMap<u64, String>,
    /// The experiment an admin confirmed the robot was reset for.
    reset_confirmed: Option<u64>,
    /// The queued experiment waiting for a manual reset, if any.
    awaiting_reset: Option<u64>,
    /// Why the queue does not start its head now, when it could otherwise.
    held: Option<String>,
    /// Who may drive by reservation now, until when.
    granted: Option<(String, u64)>,
    /// The duty cycle: robot time run since the last rest (ms), and until
    /// when the robot rests (ms since the Unix epoch). Not kept over a
    /// restart: a restart starts a fresh cycle.
    duty_counted_ms: u64,
    resting_until_ms: Option<u64>,
    /// While the robot is out of service for a low battery alone: the live
    /// status, watched for the battery coming back (`selftest`).
    /// An admin's self-test runs now: nothing starts meanwhile.
    self_testing: bool,
    battery_watch: Option<tokio::sync::watch::Receiver<std::sync::Arc<Option<crate::report::LiveStatus>>>>,
}

/// The remote lab of one robot host.
pub struct Lab {
    deployer: Arc<Deployer>,
    options: LabOptions,
    book: Mutex<Book>,
    /// Wakes the threads (new work, a cancel) and the requests waiting for
    /// an experiment to end.
    changed: Condvar,
    /// Bumped at every change, for the portal's live view.
    generation: tokio::sync::watch::Sender<u64>,
    stopping: AtomicBool,
    threads: Mutex<Vec<std::thread::JoinHandle<()>>>,
    /// The owner's webhooks (`notify`), when the store's folder has any.
    notifier: Option<Arc<Notifier>>,
}

fn not_found(id: u64) -> LabError {
    LabError::NotFound(format!("no experiment {id}"))
}

/// Seconds from `now_ms` to `at_ms`, rounded up.
fn seconds_until(at_ms: u64, now_ms: u64) -> u64 {
    at_ms.saturating_sub(now_ms).div_ceil(1000)
}

impl Lab {
    /// Stores a set a lab sent (a dispatch's, or a robot's baseline) as one
    /// of this host's sets, recorded as made `by`; the files its built-ins
    /// name are in `base_dir`.
    fn import_manifest(&self, set: &wire::SetManifest, by: &str, base_dir: &Path) -> Result<SetRecord, DeployError> {
        let sources: BTreeMap<String, String> =
            set.sources.iter().map(|(k, b)| (k.clone(), b.sha256.clone())).collect();
        self.deployer.import_set(&SetImport {
            by,
            config_name: &set.config_name,
            config_text: &set.config_text,
            platform: set.platform.as_deref(),
            sources: &sources,
            base_dir,
        })
    }

    /// The lab of `deployer`'s host: reads the experiments back (those the
    /// host stopped during are aborted, those in their checks are checked
    /// again) and starts its threads.
    pub fn start(deployer: Arc<Deployer>, options: LabOptions) -> Result<Arc<Lab>, LabError> {
        let store = deployer.store.clone();
        let mut experiments = store.experiments()?;
        let lab = store.lab_state()?;
        runner::recover(&store, &mut experiments, matches!(options.role, LabRole::Server(_)))?;
        let notifier = Notifier::start(store.root()).map_err(|e| LabError::Host(e.to_string()))?;
        let lab = Arc::new(Lab {
            deployer: deployer.clone(),
            options,
            book: Mutex::new(Book { experiments, lab, ..Book::default() }),
            changed: Condvar::new(),
            generation: tokio::sync::watch::channel(0).0,
            stopping: AtomicBool::new(false),
            threads: Mutex::new(Vec::new()),
            notifier,
        });
        let preempt: Arc<dyn crate::deploy::Preempt> = lab.clone();
        deployer.experiments().on_preempt(Arc::downgrade(&preempt));
        match &lab.options.role {
            LabRole::Server(fleet) => server::spawn(&lab, fleet.clone())?,
            _ => runner::spawn(&lab)?,
        }
        Ok(lab)
    }

    fn store(&self) -> &Arc<Store> {
        &self.deployer.store
    }

    fn lock(&self) -> Result<MutexGuard<'_, Book>, LabError> {
        self.book.lock().map_err(|_| LabError::Host("the lab's state is unusable".into()))
    }

    /// Tells the threads and the live view that something changed.
    fn notify(&self) {
        self.changed.notify_all();
        self.generation.send_modify(|g| *g = g.wrapping_add(1));
    }

    /// A receiver that changes with the lab (the portal's live view).
    pub fn subscribe(&self) -> tokio::sync::watch::Receiver<u64> {
        self.generation.subscribe()
    }

    /// The baseline: the owner's choice, else the set the host started with
    /// (on a lab server: the reference, the first robot baseline it learned).
    fn baseline(&self, lab: &LabState) -> u64 {
        lab.baseline.unwrap_or_else(|| self.deployer.boot_set())
    }

    /// The lab server's fleet, if this is one.
    pub fn fleet(&self) -> Option<&Arc<server::Fleet>> {
        match &self.options.role {
            LabRole::Server(fleet) => Some(fleet),
            _ => None,
        }
    }

    /// Moves experiment `id` to `state` for `cause` (and `reasons`),
    /// stores it and tells everyone; returns the record.
    fn transition(
        &self,
        book: &mut Book,
        id: u64,
        state: ExperimentState,
        cause: &str,
        reasons: Vec<String>,
    ) -> Result<ExperimentRecord, LabError> {
        // Changed on a copy, stored, and only then in the book: a failed
        // write (a full disk) leaves the experiment what the store says.
        let mut record = book.experiments.get(&id).cloned().ok_or_else(|| not_found(id))?;
        record.enter(state, unix_now_ms(), cause)?;
        for reason in reasons {
            record.add_reason(reason);
        }
        let writer = self.store().lock()?;
        writer.put_experiment(&record)?;
        book.experiments.insert(id, record.clone());
        writer.record(
            LAB_AUDIT_USER,
            &format!("experiment-{}", state.name()),
            &format!("experiment {id} by {}", record.submitter),
            Outcome::Ok(cause),
        );
        drop(writer);
        tracing::info!("experiment {id} ({}): {}: {cause}", record.submitter, state.name());
        if let (Some(notifier), Some(kind)) = (&self.notifier, notify::experiment_event(state.name())) {
            let facts = ExperimentFacts {
                id,
                submitter: record.submitter.clone(),
                state: state.name().to_string(),
                reasons: record.reasons.clone(),
                outcome: record.run.as_ref().and_then(|r| r.outcome.clone()),
                score: record.score.clone(),
            };
            if let Err(e) = notifier.tell(kind, unix_now_ms(), Some(facts)) {
                tracing::error!("experiment {id}: its {} webhook event is lost: {e}", state.name());
            }
        }
        self.notify();
        Ok(record)
    }

    /// Stops the lab's threads as the host stops; an experiment that ran
    /// is aborted (`host stopped`) with what it recorded and `report`, the
    /// run's final report (the experiment's graph was the last one).
    pub fn shut_down(&self, report: Option<&crate::report::Report>) {
        self.stopping.store(true, Ordering::Release);
        self.notify();
        let threads = self.threads.lock().map(|mut t| std::mem::take(&mut *t)).unwrap_or_default();
        for thread in threads {
            let _ = thread.join();
        }
        runner::host_stopped(self, report);
    }

    fn is_stopping(&self) -> bool {
        self.stopping.load(Ordering::Acquire)
    }
}

/// The user the lab's own state changes are audited as.
pub const LAB_AUDIT_USER: &str = crate::deploy::LAB_USER;

/// Where experiment `id`'s run on the robot records to.
fn run_recording(store: &Store, id: u64) -> PathBuf {
    store.experiment_dir(id).join(bundle::RUN_RECORDING)
}
