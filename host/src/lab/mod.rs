//! The remote lab (docs/lab.md): a researcher's experiment as a thing the
//! host knows. An experiment is a staged set, a duration and a label; it is
//! checked, run first in the simulator ([`preflight`]), queued fairly
//! ([`queue`]), run on the robot from a fresh start while recording, stopped
//! on time, and its results kept ([`bundle`]); between experiments the
//! robot runs the owner's baseline.
//!
//! [`Lab`] holds the use cases (submit, cancel, list, results, the owner's
//! settings, the baseline, pause and resume, reservations, the manual
//! reset's confirmation) and two threads: one checks and preflights
//! experiments one at a time, the other runs them on the robot
//! ([`runner`]). Each use case authorises, then changes the experiments'
//! records and `lab.json` under the lab's lock and the store's, and writes
//! one audit line, refused or not.
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

pub mod bundle;
pub mod materialize;
pub mod preflight;
pub mod queue;
pub mod robot_link;
mod runner;
pub mod server;
pub mod transfer;
pub mod verdict;
pub mod wire;

use std::collections::{BTreeMap, BTreeSet};
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::time::Duration;

use serde::Serialize;
use thiserror::Error;

use self::preflight::PreflightCommand;
use self::queue::{Charge, OverLimit, QueueView, Waiting};
use crate::contract::clip;
use crate::deploy::{DeployError, Deployer, Diagnostics, RunningExperiment, utc_time};
use crate::runtime::locks::unix_now_ms;
use crate::store::experiments::{
    AppliedSettings, ComponentHash, ExperimentRecord, ExperimentState, LAB_FORMAT, LabSettings, LabState,
    MAX_EXPERIMENT_RECORDS, MAX_LABEL_LEN, MAX_RESERVATIONS, Placement, Reservation, Target,
};
use crate::store::users::{Role, User};
use crate::store::{Outcome, Store, StoreError};

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
        matches!(self, LabError::Store(_) | LabError::Host(_))
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
}

/// An experiment as its submitter (or an admin) sees it.
#[derive(Clone, Debug, Serialize)]
pub struct ExperimentView {
    #[serde(flatten)]
    pub record: ExperimentRecord,
    /// Place in the queue (1: next), while queued.
    pub place: Option<usize>,
    /// When it is expected to start (ms since the Unix epoch), while queued.
    pub eta_unix_ms: Option<u64>,
    /// When it ends (ms since the Unix epoch), while it runs.
    pub ends_unix_ms: Option<u64>,
    /// It is next, and waits for an admin to confirm the robot was reset.
    pub awaiting_reset: bool,
}

/// The lab as a user sees it.
#[derive(Clone, Debug, Serialize)]
pub struct LabView {
    /// The experiment on the robot now, for every tab's banner.
    pub running: Option<RunningExperiment>,
    pub queued: usize,
    pub paused: bool,
    /// Why the head of the queue waits, when it does (a lock, a reset).
    pub held: Option<String>,
    pub awaiting_reset: Option<u64>,
    pub baseline: u64,
    pub reservations: Vec<Reservation>,
    /// The reservation in effect now.
    pub reserved_now: Option<Reservation>,
    /// On a lab server: every robot it knows.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub robots: Option<Vec<server::RobotView>>,
    /// The owner's settings (admins only).
    pub settings: Option<LabSettings>,
    /// The host's clock when this view was made (ms since the Unix epoch):
    /// a client whose own clock is off counts down to `running`'s end and
    /// to ETAs from it.
    pub now_unix_ms: u64,
}

/// The body of a submission.
#[derive(Clone, Debug, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Submission {
    pub set: u64,
    pub duration_s: f64,
    #[serde(default)]
    pub label: String,
    /// On a lab server: which robots may run it (`{"robot": NAME}`,
    /// `{"profile": ID}`); the first free robot when missing.
    #[serde(default)]
    pub target: Option<Target>,
}

fn visible(user: &User, record: &ExperimentRecord) -> bool {
    user.role == Role::Admin || record.submitter == user.name
}

fn not_found(id: u64) -> LabError {
    LabError::NotFound(format!("no experiment {id}"))
}

/// Seconds from `now_ms` to `at_ms`, rounded up.
fn seconds_until(at_ms: u64, now_ms: u64) -> u64 {
    at_ms.saturating_sub(now_ms).div_ceil(1000)
}

impl Lab {
    /// The lab of `deployer`'s host: reads the experiments back (those the
    /// host stopped during are aborted, those in their checks are checked
    /// again) and starts its threads.
    pub fn start(deployer: Arc<Deployer>, options: LabOptions) -> Result<Arc<Lab>, LabError> {
        let store = deployer.store.clone();
        let mut experiments = store.experiments()?;
        let lab = store.lab_state()?;
        let now = unix_now_ms();
        let is_server = matches!(options.role, LabRole::Server(_));
        {
            let writer = store.lock()?;
            for record in experiments.values_mut() {
                // A lab server's experiments on robots ran on without it:
                // it learns what became of them from the robots.
                if is_server && matches!(record.state, ExperimentState::Running | ExperimentState::Finishing) {
                    continue;
                }
                let cause = match record.state {
                    ExperimentState::Running | ExperimentState::Finishing => "the host stopped while it ran",
                    ExperimentState::Preflight => "the host stopped during its preflight; it is checked again",
                    _ => continue,
                };
                if matches!(record.state, ExperimentState::Running | ExperimentState::Finishing) {
                    record.add_reason("aborted: host stopped".into());
                    bundle::salvage(&store, record);
                    record.enter(ExperimentState::Aborted, now, cause);
                } else {
                    record.enter(ExperimentState::Checking, now, cause);
                }
                writer.put_experiment(record)?;
                writer.record(LAB_AUDIT_USER, "experiment", &format!("experiment {}", record.id), Outcome::Ok(cause));
            }
        }
        let lab = Arc::new(Lab {
            deployer: deployer.clone(),
            options,
            book: Mutex::new(Book {
                experiments,
                lab,
                cancels: BTreeMap::new(),
                preempt: None,
                running: None,
                starting: None,
                dispatching: BTreeSet::new(),
                aborts: BTreeMap::new(),
                reset_confirmed: None,
                awaiting_reset: None,
                held: None,
                granted: None,
            }),
            changed: Condvar::new(),
            generation: tokio::sync::watch::channel(0).0,
            stopping: AtomicBool::new(false),
            threads: Mutex::new(Vec::new()),
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
        let record = book.experiments.get_mut(&id).ok_or_else(|| not_found(id))?;
        record.enter(state, unix_now_ms(), cause);
        for reason in reasons {
            record.add_reason(reason);
        }
        let record = record.clone();
        let writer = self.store().lock()?;
        writer.put_experiment(&record)?;
        writer.record(
            LAB_AUDIT_USER,
            &format!("experiment-{}", state.name()),
            &format!("experiment {id} by {}", record.submitter),
            Outcome::Ok(cause),
        );
        drop(writer);
        tracing::info!("experiment {id} ({}): {}: {cause}", record.submitter, state.name());
        self.notify();
        Ok(record)
    }

    /// Submits set `submission.set` as `user`'s experiment: checked at once
    /// (permission, duration, the set validates against the baseline, the
    /// limits), then preflighted and queued by the lab's threads.
    pub fn submit(&self, user: &User, submission: &Submission) -> Result<ExperimentRecord, LabError> {
        let target = format!("set {}", submission.set);
        let prepared = self.prepare_submit(user, submission);
        let result = prepared.and_then(|(settings, components, baseline)| {
            let mut book = self.lock()?;
            let now = unix_now_ms();
            let duration_ms = (submission.duration_s * 1000.0) as u64;
            self.admit(&book, user, duration_ms, now)?;
            let record = ExperimentRecord {
                format: LAB_FORMAT,
                id: 0,
                submitter: user.name.clone(),
                set: submission.set,
                label: submission.label.trim().to_string(),
                duration_s: submission.duration_s,
                submitted_ms: now,
                state: ExperimentState::Checking,
                history: Vec::new(),
                reasons: Vec::new(),
                settings: AppliedSettings::of(&settings, baseline),
                components,
                preflight: None,
                run: None,
                results: Vec::new(),
                recording_expired: false,
                origin: None,
                placement: self.fleet().map(|_| Placement {
                    target: submission.target.clone().unwrap_or_default(),
                    ..Placement::default()
                }),
            };
            let writer = self.store().lock()?;
            let mut record = writer.add_experiment(&mut book.lab, record)?;
            record.enter(ExperimentState::Checking, now, &format!("submitted by {}", user.name));
            writer.put_experiment(&record)?;
            writer.record(
                &user.name,
                "submit-experiment",
                &target,
                Outcome::Ok(&format!("experiment {} ({} s)", record.id, submission.duration_s)),
            );
            drop(writer);
            book.experiments.insert(record.id, record.clone());
            self.forget_oldest(&mut book);
            drop(book);
            tracing::info!("experiment {} submitted by {}: set {}", record.id, user.name, submission.set);
            self.notify();
            Ok(record)
        });
        if let Err(e) = &result {
            self.audit_refusal(&user.name, "submit-experiment", &target, e);
        }
        result
    }

    fn audit_refusal(&self, user: &str, action: &str, target: &str, e: &LabError) {
        let detail = e.to_string();
        let outcome = if e.is_failure() { Outcome::Failed(&detail) } else { Outcome::Refused(&detail) };
        match self.store().lock() {
            Ok(writer) => writer.record(user, action, target, outcome),
            Err(e) => tracing::error!("cannot lock the store to record {action} by {user}: {e}"),
        }
    }

    /// The checks a submission passes before the lab's lock: the slow
    /// ones (validating the set).
    #[allow(clippy::type_complexity)]
    fn prepare_submit(
        &self,
        user: &User,
        submission: &Submission,
    ) -> Result<(LabSettings, Vec<ComponentHash>, u64), LabError> {
        if !user.may_submit() {
            return Err(LabError::Forbidden(format!(
                "{} may not submit experiments (researchers, developers and admins may)",
                user.name
            )));
        }
        let label = submission.label.trim();
        if label.chars().count() > MAX_LABEL_LEN || label.chars().any(char::is_control) {
            return Err(LabError::BadRequest(format!(
                "the label must be at most {MAX_LABEL_LEN} characters, without control characters"
            )));
        }
        if let LabRole::Joined { lab } = &self.options.role {
            return Err(LabError::Conflict(format!(
                "this robot takes its experiments from lab '{lab}': submit them to the lab's server"
            )));
        }
        let (settings, mut baseline, baselines) = {
            let book = self.lock()?;
            (book.lab.settings.clone(), self.baseline(&book.lab), book.lab.baselines.clone())
        };
        match (self.fleet(), &submission.target) {
            (None, Some(_)) => {
                return Err(LabError::BadRequest(
                    "this host is one robot: a target is for a lab server (subsume lab serve)".into(),
                ));
            }
            (Some(fleet), target) => {
                let target = target.clone().unwrap_or_default();
                baseline = fleet.baseline_for(&target, &baselines, baseline)?;
                if baseline == 0 {
                    return Err(LabError::Conflict(
                        "the lab knows no robot yet: experiments are checked against a robot's baseline".into(),
                    ));
                }
            }
            (None, None) => {}
        }
        let duration = submission.duration_s;
        if !duration.is_finite() || duration < MIN_DURATION_S || duration > settings.max_duration_s {
            return Err(LabError::BadRequest(format!(
                "duration_s must be from {MIN_DURATION_S} to the robot's max-duration of {} s, got {}",
                settings.max_duration_s, duration
            )));
        }
        let checked = self.deployer.check_experiment_set(user, submission.set, baseline)?;
        let components = checked
            .components
            .into_iter()
            .map(|(name, source, sha256)| ComponentHash { name, source, sha256 })
            .collect();
        Ok((settings, components, baseline))
    }

    /// Whether `user` may have one more experiment of `duration_ms` now
    /// (the per-user limits), with the answer a 429 carries.
    fn admit(&self, book: &Book, user: &User, duration_ms: u64, now: u64) -> Result<(), LabError> {
        let charges: Vec<Charge> = book
            .experiments
            .values()
            .filter(|r| r.submitter == user.name)
            .map(|r| Charge { submitted_ms: r.submitted_ms, waiting: r.state.is_waiting(), robot_ms: r.robot_ms() })
            .collect();
        let first_start = self
            .etas(book, now)
            .into_iter()
            .filter(|(id, _)| book.experiments.get(id).is_some_and(|r| r.submitter == user.name))
            .filter_map(|(_, eta)| eta)
            .min();
        queue::admit(&book.lab.settings.limits, &charges, duration_ms, now, first_start).map_err(|over| {
            let frees = over.frees_ms();
            let when = match frees {
                Some(at) => format!("it frees at {} (in {} s)", utc_time(at), seconds_until(at, now)),
                None => "it frees when one of them ends or is cancelled".to_string(),
            };
            let message = match over {
                OverLimit::Queued { limit, .. } => {
                    format!("{} has {limit} experiments waiting, the most allowed; {when}", user.name)
                }
                OverLimit::RobotMinutes { limit, used, asked, frees_ms } => {
                    let when = match frees_ms {
                        Some(at) => format!("enough frees at {} (in {} s)", utc_time(at), seconds_until(at, now)),
                        None => format!("an experiment of {asked:.1} min never fits the daily limit"),
                    };
                    format!(
                        "{} has used {used:.1} of {limit} robot-minutes in the last 24 hours and this experiment needs {asked:.1}; {when}",
                        user.name
                    )
                }
            };
            LabError::OverLimit { message, retry_after_s: frees.map(|at| seconds_until(at, now).max(1)) }
        })
    }

    /// Forgets the oldest finished experiments beyond
    /// [`MAX_EXPERIMENT_RECORDS`].
    fn forget_oldest(&self, book: &mut Book) {
        let excess = book.experiments.len().saturating_sub(MAX_EXPERIMENT_RECORDS);
        let old: Vec<u64> =
            book.experiments.values().filter(|r| r.state.is_final()).map(|r| r.id).take(excess).collect();
        for id in old {
            match self.store().lock().and_then(|writer| writer.forget_experiment(id)) {
                Ok(()) => {
                    book.experiments.remove(&id);
                }
                Err(e) => tracing::warn!("cannot forget experiment {id}: {e}"),
            }
        }
    }

    /// The queue's ETAs now.
    fn etas(&self, book: &Book, now: u64) -> Vec<(u64, Option<u64>)> {
        let waiting = Self::waiting(book);
        let view = QueueView {
            now_ms: now,
            running_until_ms: book.running.as_ref().map(|r| r.ends_unix_ms),
            waiting: &waiting,
            reservations: &book.lab.reservations,
            paused: book.lab.paused,
            turnaround_ms: TURNAROUND.as_millis() as u64,
        };
        queue::etas(&view)
    }

    /// The queued experiments, in submission order.
    fn waiting(book: &Book) -> Vec<Waiting> {
        book.experiments
            .values()
            .filter(|r| r.state == ExperimentState::Queued)
            .map(|r| Waiting { id: r.id, user: r.submitter.clone(), duration_ms: (r.duration_s * 1000.0) as u64 })
            .collect()
    }

    fn view(&self, book: &Book, record: &ExperimentRecord, etas: &[(u64, Option<u64>)]) -> ExperimentView {
        let place = etas.iter().position(|(id, _)| *id == record.id).map(|i| i + 1);
        let eta = etas.iter().find(|(id, _)| *id == record.id).and_then(|(_, eta)| *eta);
        let ends = book.running.as_ref().filter(|r| r.id == record.id).map(|r| r.ends_unix_ms);
        ExperimentView {
            record: record.clone(),
            place,
            eta_unix_ms: eta,
            ends_unix_ms: ends,
            awaiting_reset: book.awaiting_reset == Some(record.id),
        }
    }

    /// `user`'s experiments (an admin's: every one), newest first.
    pub fn list(&self, user: &User) -> Result<Vec<ExperimentView>, LabError> {
        let book = self.lock()?;
        let etas = self.etas(&book, unix_now_ms());
        Ok(book.experiments.values().rev().filter(|r| visible(user, r)).map(|r| self.view(&book, r, &etas)).collect())
    }

    /// Experiment `id`, if `user` may see it.
    pub fn get(&self, user: &User, id: u64) -> Result<ExperimentView, LabError> {
        let book = self.lock()?;
        let record = book.experiments.get(&id).filter(|r| visible(user, r)).ok_or_else(|| not_found(id))?;
        let etas = self.etas(&book, unix_now_ms());
        Ok(self.view(&book, record, &etas))
    }

    /// The lab as `user` sees it (the owner's settings for admins only).
    pub fn overview(&self, user: &User) -> Result<LabView, LabError> {
        let book = self.lock()?;
        let now = unix_now_ms();
        Ok(LabView {
            running: self.deployer.experiments().running(),
            queued: book.experiments.values().filter(|r| r.state == ExperimentState::Queued).count(),
            paused: book.lab.paused,
            held: book.held.clone(),
            awaiting_reset: book.awaiting_reset,
            baseline: self.baseline(&book.lab),
            reservations: book.lab.reservations.iter().filter(|r| r.end_ms > now).cloned().collect(),
            reserved_now: queue::reservation_at(&book.lab.reservations, now).cloned(),
            settings: (user.role == Role::Admin).then(|| book.lab.settings.clone()),
            now_unix_ms: now,
            robots: self.fleet().map(|f| f.robots_with(now, &book.lab.baselines)),
        })
    }

    /// Cancels experiment `id` for `user` (its submitter or an admin):
    /// at once while it waits; while it runs, the robot goes back to the
    /// baseline first (this waits for that, at most [`END_WAIT`]).
    pub fn cancel(&self, user: &User, id: u64) -> Result<ExperimentRecord, LabError> {
        let target = format!("experiment {id}");
        let result = self.cancel_inner(user, id);
        match &result {
            Ok(record) => {
                if let Ok(writer) = self.store().lock() {
                    writer.record(&user.name, "cancel-experiment", &target, Outcome::Ok(record.state.name()));
                }
            }
            Err(e) => self.audit_refusal(&user.name, "cancel-experiment", &target, e),
        }
        result
    }

    fn cancel_inner(&self, user: &User, id: u64) -> Result<ExperimentRecord, LabError> {
        let mut book = self.lock()?;
        let record = book.experiments.get(&id).filter(|r| visible(user, r)).ok_or_else(|| not_found(id))?;
        let cause = format!("cancelled by {}", user.name);
        match record.state {
            s if s.is_final() => Err(LabError::Conflict(format!("experiment {id} has ended already ({})", s.name()))),
            ExperimentState::Queued if book.starting == Some(id) || book.dispatching.contains(&id) => {
                self.cancel_when_it_runs(book, id, &user.name)
            }
            ExperimentState::Checking | ExperimentState::Queued => {
                let record = self.transition(&mut book, id, ExperimentState::Cancelled, &cause, vec![cause.clone()])?;
                Ok(record)
            }
            // In preflight or on the robot: the thread that has it ends it.
            _ => self.cancel_when_it_runs(book, id, &user.name),
        }
    }

    /// Asks the thread that has experiment `id` to cancel it, and waits
    /// (at most [`END_WAIT`]) for it to end.
    fn cancel_when_it_runs(
        &self,
        mut book: MutexGuard<'_, Book>,
        id: u64,
        by: &str,
    ) -> Result<ExperimentRecord, LabError> {
        book.cancels.insert(id, by.to_string());
        self.notify();
        let (book, _) = self
            .changed
            .wait_timeout_while(book, END_WAIT, |b| b.experiments.get(&id).is_some_and(|r| !r.state.is_final()))
            .map_err(|_| LabError::Host("the lab's state is unusable".into()))?;
        book.experiments.get(&id).cloned().ok_or_else(|| not_found(id))
    }

    /// Changes the owner's settings (admins).
    pub fn set_settings(&self, user: &User, settings: LabSettings) -> Result<LabSettings, LabError> {
        self.admin_change(user, "lab-settings", "lab", |lab| {
            check_settings(&settings)?;
            lab.settings = settings.clone();
            Ok(format!(
                "max-duration {} s, {} queued and {} robot-minutes a day per user",
                settings.max_duration_s, settings.limits.max_queued, settings.limits.robot_minutes_per_day
            ))
        })
        .map(|lab| lab.settings)
    }

    /// Marks set `set` as the baseline (admins); it must validate.
    pub fn set_baseline(&self, user: &User, set: u64) -> Result<u64, LabError> {
        let checked = self.deployer.check_experiment_set(user, set, set);
        let reference = match (&checked, self.fleet()) {
            (Ok(_), Some(_)) if user.role == Role::Admin => self.deployer.set_reference(set).map_err(LabError::from),
            _ => Ok(()),
        };
        self.admin_change(user, "lab-baseline", &format!("set {set}"), |lab| {
            checked.map_err(LabError::from)?;
            reference?;
            lab.baseline = Some(set);
            Ok(format!("the baseline is set {set}"))
        })
        .map(|lab| self.baseline(&lab))
    }

    /// Pauses or resumes the queue (admins): a paused queue starts nothing
    /// new; what runs goes on.
    pub fn set_paused(&self, user: &User, paused: bool) -> Result<bool, LabError> {
        let action = if paused { "lab-pause" } else { "lab-resume" };
        self.admin_change(user, action, "queue", |lab| {
            lab.paused = paused;
            Ok(if paused { "the queue is paused".into() } else { "the queue runs".into() })
        })
        .map(|lab| lab.paused)
    }

    /// Confirms the robot was put back at its start for the experiment
    /// that waits for it (admins; the `manual` reset policy).
    pub fn confirm_reset(&self, user: &User) -> Result<u64, LabError> {
        let target = "reset".to_string();
        let result = (|| {
            if user.role != Role::Admin {
                return Err(LabError::Forbidden(format!("{} may not confirm resets (admins may)", user.name)));
            }
            let mut book = self.lock()?;
            let id = book
                .awaiting_reset
                .ok_or_else(|| LabError::Conflict("no experiment waits for the robot to be reset".into()))?;
            book.reset_confirmed = Some(id);
            drop(book);
            self.notify();
            Ok(id)
        })();
        match &result {
            Ok(id) => {
                if let Ok(writer) = self.store().lock() {
                    writer.record(&user.name, "lab-reset", &target, Outcome::Ok(&format!("for experiment {id}")));
                }
            }
            Err(e) => self.audit_refusal(&user.name, "lab-reset", &target, e),
        }
        result
    }

    /// Books `[start_ms, end_ms)` for `user` (researchers for themselves,
    /// admins for anyone).
    pub fn book(&self, user: &User, for_user: &str, start_ms: u64, end_ms: u64) -> Result<Reservation, LabError> {
        let target = format!("reservation for {for_user}");
        let result = (|| {
            if !user.may_submit() {
                return Err(LabError::Forbidden(format!("{} may not book the robot", user.name)));
            }
            if for_user != user.name && user.role != Role::Admin {
                return Err(LabError::Forbidden(format!("{} may book only for themselves", user.name)));
            }
            if self.fleet().is_some() {
                return Err(LabError::Conflict(
                    "reservations are for one robot: book on that robot's own portal".into(),
                ));
            }
            let mut book = self.lock()?;
            let now = unix_now_ms();
            if start_ms > now.saturating_add(MAX_BOOKING_AHEAD.as_millis() as u64) {
                return Err(LabError::BadRequest(format!(
                    "a reservation starts at most {} days ahead",
                    MAX_BOOKING_AHEAD.as_secs() / 86_400
                )));
            }
            let start_ms = start_ms.max(now);
            queue::check_booking(&book.lab.settings.limits, &book.lab.reservations, for_user, start_ms, end_ms, now)
                .map_err(|e| booking_error(e, for_user))?;
            let mut lab = book.lab.clone();
            if lab.reservations.len() >= MAX_RESERVATIONS {
                lab.reservations.retain(|r| r.end_ms > now);
            }
            if lab.reservations.len() >= MAX_RESERVATIONS {
                return Err(LabError::Conflict(format!("the lab holds {MAX_RESERVATIONS} reservations already")));
            }
            let reservation = Reservation { id: lab.next_reservation, user: for_user.to_string(), start_ms, end_ms };
            lab.next_reservation += 1;
            lab.reservations.push(reservation.clone());
            lab.reservations.sort_by_key(|r| r.start_ms);
            self.store().lock()?.put_lab_state(&lab)?;
            book.lab = lab;
            drop(book);
            self.notify();
            Ok(reservation)
        })();
        match &result {
            Ok(r) => {
                if let Ok(writer) = self.store().lock() {
                    let detail =
                        format!("reservation {} from {} to {}", r.id, utc_time(r.start_ms), utc_time(r.end_ms));
                    writer.record(&user.name, "book", &target, Outcome::Ok(&detail));
                }
            }
            Err(e) => self.audit_refusal(&user.name, "book", &target, e),
        }
        result
    }

    /// Cancels reservation `id` (its holder, or an admin: the owner).
    pub fn unbook(&self, user: &User, id: u64) -> Result<(), LabError> {
        let target = format!("reservation {id}");
        let result = (|| {
            let mut book = self.lock()?;
            let found = book.lab.reservations.iter().find(|r| r.id == id);
            let Some(found) = found.filter(|r| user.role == Role::Admin || r.user == user.name) else {
                return Err(LabError::NotFound(format!("no reservation {id}")));
            };
            let _ = found;
            let mut lab = book.lab.clone();
            lab.reservations.retain(|r| r.id != id);
            self.store().lock()?.put_lab_state(&lab)?;
            book.lab = lab;
            drop(book);
            self.notify();
            Ok(())
        })();
        match &result {
            Ok(()) => {
                if let Ok(writer) = self.store().lock() {
                    writer.record(&user.name, "unbook", &target, Outcome::Ok("cancelled"));
                }
            }
            Err(e) => self.audit_refusal(&user.name, "unbook", &target, e),
        }
        result
    }

    /// Whether `user` holds the reservation in effect now (a researcher
    /// may drive inside it).
    pub fn holds_reservation_now(&self, user: &str) -> bool {
        self.book
            .lock()
            .ok()
            .and_then(|b| queue::reservation_at(&b.lab.reservations, unix_now_ms()).map(|r| r.user == user))
            .unwrap_or(false)
    }

    fn admin_change(
        &self,
        user: &User,
        action: &str,
        target: &str,
        change: impl FnOnce(&mut LabState) -> Result<String, LabError>,
    ) -> Result<LabState, LabError> {
        let result = (|| {
            if user.role != Role::Admin {
                return Err(LabError::Forbidden(format!("{} may not change the lab (admins may)", user.name)));
            }
            let mut book = self.lock()?;
            let mut lab = book.lab.clone();
            let detail = change(&mut lab)?;
            self.store().lock()?.put_lab_state(&lab)?;
            book.lab = lab.clone();
            drop(book);
            self.notify();
            Ok((lab, detail))
        })();
        match result {
            Ok((lab, detail)) => {
                if let Ok(writer) = self.store().lock() {
                    writer.record(&user.name, action, target, Outcome::Ok(&detail));
                }
                Ok(lab)
            }
            Err(e) => {
                self.audit_refusal(&user.name, action, target, &e);
                Err(e)
            }
        }
    }

    /// The files of experiment `id`'s results bundle, if `user` may see
    /// it: see [`bundle::contents`].
    pub fn results(&self, user: &User, id: u64) -> Result<bundle::Contents, LabError> {
        let record = {
            let book = self.lock()?;
            book.experiments.get(&id).filter(|r| visible(user, r)).cloned().ok_or_else(|| not_found(id))?
        };
        if !record.state.is_final() {
            return Err(LabError::Conflict(format!(
                "experiment {id} is {}: its results come when it ends",
                record.state.name()
            )));
        }
        bundle::contents(self.store(), &record).map_err(LabError::from)
    }

    /// The lab kit (docs/lab.md): the baseline in its preflight form (the
    /// robot file, its components, its world), the criteria and a README,
    /// for `user` to run the lab's robot on their own machine; written into
    /// a temporary folder the caller keeps until the archive is sent.
    pub fn kit(&self, user: &User) -> Result<(tempfile::TempDir, bundle::Contents), LabError> {
        let (settings, baseline) = {
            let book = self.lock()?;
            (book.lab.settings.clone(), self.baseline(&book.lab))
        };
        if !user.may_submit() {
            return Err(LabError::Forbidden(format!("{} may not download the lab kit", user.name)));
        }
        if !settings.kit && user.role != Role::Admin {
            return Err(LabError::Forbidden("the robot's owner turned the lab kit off".into()));
        }
        let set = self.store().set(baseline)?;
        let world = match &settings.preflight_world {
            Some(name) => {
                let worlds = self.store().worlds()?;
                let stored = worlds
                    .get(name)
                    .ok_or_else(|| LabError::Host(format!("the preflight world '{name}' is not stored")))?;
                Some(materialize::PreflightWorld { name: name.clone(), sha256: stored.sha256.clone() })
            }
            None => None,
        };
        let dir = tempfile::tempdir().map_err(|e| LabError::Host(format!("cannot make the kit's folder: {e}")))?;
        let comment = format!("the lab's baseline (set {baseline}) in its preflight form: the lab kit (docs/lab.md)");
        let written = materialize::write_preflight_form(self.store(), &set, world.as_ref(), dir.path(), &comment)
            .map_err(|e| LabError::Host(e.to_string()))?;
        let criteria = serde_json::to_vec_pretty(&settings.criteria).map_err(|e| LabError::Host(e.to_string()))?;
        let readme = format!(
            "The lab's robot (set {baseline}), as the lab's preflight runs it.\n\n\
             Check an experiment's components the way the lab will, for up to {} s:\n\n    \
             subsume run robot.xml --http off --speed max --duration 60 --criteria criteria.json\n\n\
             It ends with the verdict the preflight would give. Replace a component's source in\n\
             robot.xml with your own .wasm to try yours. The envelope component's parameters are the\n\
             robot's safety settings: an experiment may not change them.\n",
            settings.max_duration_s
        );
        let mut entries = vec![
            ("criteria.json".to_string(), bundle::Source::Bytes(criteria)),
            ("README.txt".to_string(), bundle::Source::Bytes(readme.into_bytes())),
        ];
        for (name, _) in &written.files {
            entries.push((name.clone(), bundle::Source::File(dir.path().join(name))));
        }
        if let Ok(writer) = self.store().lock() {
            writer.record(&user.name, "lab-kit", &format!("set {baseline}"), Outcome::Ok("downloaded"));
        }
        Ok((dir, bundle::Contents { folder: "lab-kit".into(), entries }))
    }

    /// Counts of experiments by state, the queue's length, and the
    /// preflights' durations (for /metrics).
    pub fn metrics(&self) -> LabMetrics {
        let Ok(book) = self.book.lock() else { return LabMetrics::default() };
        let mut by_state = BTreeMap::new();
        for state in ExperimentState::ALL {
            by_state.insert(state.name(), 0);
        }
        let mut preflight_s = Vec::new();
        for record in book.experiments.values() {
            *by_state.entry(record.state.name()).or_default() += 1;
            if let Some(p) = &record.preflight {
                preflight_s.push(p.wall_s);
            }
        }
        let link = self.fleet().map(|fleet| fleet.link_figures());
        LabMetrics {
            by_state,
            queued: book.experiments.values().filter(|r| r.state == ExperimentState::Queued).count() as u64,
            preflight_wall_s: preflight_s,
            link,
        }
    }

    fn fleet_or_refuse(&self) -> Result<&Arc<server::Fleet>, LabError> {
        self.fleet().ok_or_else(|| {
            LabError::NotFound("this host is one robot, not a lab server: GET /api/v1/status shows it".into())
        })
    }

    /// The lab server's robots (any logged-in user).
    pub fn robots(&self) -> Result<Vec<server::RobotView>, LabError> {
        let fleet = self.fleet_or_refuse()?;
        let book = self.lock()?;
        Ok(fleet.robots_with(unix_now_ms(), &book.lab.baselines))
    }

    /// Robot `name`'s live status, asked of it now (any logged-in user).
    pub fn robot_live(&self, name: &str) -> Result<serde_json::Value, LabError> {
        self.fleet_or_refuse()?.live(name)
    }

    /// The lab's STOP: engages the emergency stop of robot `name`, or of
    /// every robot when `None` (any logged-in user); each robot's answer.
    pub fn stop_robots(&self, user: &User, name: Option<&str>) -> Result<Vec<RobotStop>, LabError> {
        let target = name.map_or_else(|| "every robot".to_string(), |n| format!("robot {}", clip(n)));
        let result = self.fleet_or_refuse().and_then(|fleet| fleet.estop(user, name));
        match &result {
            Ok(answers) => {
                if let Ok(writer) = self.store().lock() {
                    for (robot, answer) in answers {
                        let (detail, outcome) = match answer {
                            Ok(said) => (said.clone(), true),
                            Err(why) => (why.clone(), false),
                        };
                        let outcome = if outcome { Outcome::Ok(&detail) } else { Outcome::Failed(&detail) };
                        writer.record(&user.name, "lab-estop", &format!("robot {robot}"), outcome);
                    }
                }
            }
            Err(e) => self.audit_refusal(&user.name, "lab-estop", &target, e),
        }
        result.map(|answers| {
            answers
                .into_iter()
                .map(|(robot, answer)| match answer {
                    Ok(said) => RobotStop { robot, engaged: true, message: said },
                    Err(why) => RobotStop { robot, engaged: false, message: why },
                })
                .collect()
        })
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

impl crate::deploy::Preempt for Lab {
    fn preempt(&self, id: u64, by: &str, what: &str) -> Result<String, crate::deploy::PreemptError> {
        use crate::deploy::PreemptError;
        let mut book = self.book.lock().map_err(|_| PreemptError("the lab's state is unusable".into()))?;
        if book.running.as_ref().is_none_or(|r| r.id != id) {
            return Ok(String::new());
        }
        book.preempt = Some((id, by.to_string(), what.to_string()));
        self.notify();
        let (book, timeout) = self
            .changed
            .wait_timeout_while(book, END_WAIT, |b| b.running.as_ref().is_some_and(|r| r.id == id))
            .map_err(|_| PreemptError("the lab's state is unusable".into()))?;
        if timeout.timed_out() {
            return Err(PreemptError(format!("experiment {id} did not end within {} s", END_WAIT.as_secs())));
        }
        let submitter = book.experiments.get(&id).map(|r| r.submitter.clone()).unwrap_or_default();
        Ok(format!("it cancelled experiment {id} (by {submitter}) first; the queue is paused"))
    }
}

/// A robot's answer to the lab's STOP.
#[derive(Clone, Debug, Serialize)]
pub struct RobotStop {
    pub robot: String,
    pub engaged: bool,
    pub message: String,
}

/// What /metrics shows of the lab.
#[derive(Clone, Debug, Default)]
pub struct LabMetrics {
    pub by_state: BTreeMap<&'static str, u64>,
    pub queued: u64,
    pub preflight_wall_s: Vec<f64>,
    /// A lab server's link to its robots.
    pub link: Option<server::LinkFigures>,
}

/// The bounds (seconds) of the preflight-duration histogram's buckets.
pub const PREFLIGHT_BUCKETS_S: [f64; 10] = [0.5, 1.0, 2.0, 5.0, 10.0, 20.0, 30.0, 60.0, 120.0, 300.0];

impl LabMetrics {
    /// The lab's metric families: experiments by state, the queue's
    /// length, the preflights' wall-clock durations.
    pub fn families(&self) -> Vec<crate::runtime::Family> {
        use crate::runtime::{Family, MetricKind, Sample};
        let mut states =
            Family::new("subsume_experiments", "experiments the lab keeps, by state (docs/lab.md)", MetricKind::Gauge);
        for (state, count) in &self.by_state {
            states.samples.push((vec![("state", (*state).to_string())], Sample::Gauge(*count as f64)));
        }
        let mut queue =
            Family::new("subsume_experiment_queue_length", "experiments queued for the robot", MetricKind::Gauge);
        queue.samples.push((vec![], Sample::Gauge(self.queued as f64)));
        let mut preflight = Family::new(
            "subsume_preflight_seconds",
            "wall-clock time of each preflight (the experiment in the simulator)",
            MetricKind::Histogram,
        );
        let mut buckets: Vec<(f64, u64)> = PREFLIGHT_BUCKETS_S.iter().map(|b| (*b, 0)).collect();
        buckets.push((f64::INFINITY, 0));
        for seconds in &self.preflight_wall_s {
            if let Some(bucket) = buckets.iter_mut().find(|(bound, _)| seconds <= bound) {
                bucket.1 += 1;
            }
        }
        let sum = self.preflight_wall_s.iter().sum();
        let count = self.preflight_wall_s.len() as u64;
        preflight.samples.push((vec![], Sample::Buckets { buckets, sum, count }));
        let mut families = vec![states, queue, preflight];
        if let Some(link) = &self.link {
            families.push(
                Family::new(
                    "subsume_lab_robots",
                    "robots the lab server knows, by whether they are online (a token and fresh signed statuses)",
                    MetricKind::Gauge,
                )
                .gauge(vec![("online", "true".into())], link.online as f64)
                .gauge(vec![("online", "false".into())], (link.known - link.online) as f64),
            );
            families.push(
                Family::new(
                    "subsume_lab_statuses",
                    "robot statuses the lab server received and accepted",
                    MetricKind::Counter,
                )
                .counter(vec![], link.statuses),
            );
            families.push(
                Family::new(
                    "subsume_lab_tokens",
                    "robot token changes the lab server received and accepted",
                    MetricKind::Counter,
                )
                .counter(vec![], link.tokens),
            );
            families.push(
                Family::new(
                    "subsume_lab_foreign_messages",
                    "tokens and statuses not signed with this lab's key, ignored",
                    MetricKind::Counter,
                )
                .counter(vec![], link.foreign),
            );
            families.extend(link.refusal_families());
        }
        families
    }
}

/// The user the lab's own state changes are audited as.
pub const LAB_AUDIT_USER: &str = crate::deploy::LAB_USER;

fn check_settings(settings: &LabSettings) -> Result<(), LabError> {
    let bad = |why: String| Err(LabError::BadRequest(why));
    let d = settings.max_duration_s;
    if !d.is_finite() || !(MIN_DURATION_S..=MAX_DURATION_CAP_S).contains(&d) {
        return bad(format!("max_duration_s must be from {MIN_DURATION_S} to {MAX_DURATION_CAP_S}, got {d}"));
    }
    let limits = &settings.limits;
    let minutes = limits.robot_minutes_per_day;
    if !minutes.is_finite() || !(0.0..=24.0 * 60.0).contains(&minutes) {
        return bad(format!("limits.robot_minutes_per_day must be from 0 to 1440, got {minutes}"));
    }
    if limits.max_queued > 1000 {
        return bad(format!("limits.max_queued must be at most 1000, got {}", limits.max_queued));
    }
    if limits.max_reservation_s > 24 * 3600 || limits.reservation_per_day_s > 24 * 3600 {
        return bad("reservations last at most a day".into());
    }
    if let Some(name) = &settings.preflight_world
        && (name.is_empty() || name.len() > 64)
    {
        return bad(format!("preflight_world must name an uploaded world, got '{}'", clip(name)));
    }
    Ok(())
}

fn booking_error(e: queue::BookingError, user: &str) -> LabError {
    use queue::BookingError;
    match e {
        BookingError::Shape(why) => LabError::BadRequest(format!("the reservation: {why}")),
        BookingError::TooLong { limit_s } => {
            LabError::BadRequest(format!("a reservation lasts at most {} min", limit_s / 60))
        }
        BookingError::Overlaps(other) => LabError::Conflict(format!(
            "it overlaps reservation {} ({} to {})",
            other.id,
            utc_time(other.start_ms),
            utc_time(other.end_ms)
        )),
        BookingError::OverDay { limit_s, booked_s } => LabError::OverLimit {
            message: format!("{user} has {} min booked that day; at most {} min a day", booked_s / 60, limit_s / 60),
            retry_after_s: None,
        },
    }
}

/// Where experiment `id`'s run on the robot records to.
fn run_recording(store: &Store, id: u64) -> PathBuf {
    store.experiment_dir(id).join(bundle::RUN_RECORDING)
}
