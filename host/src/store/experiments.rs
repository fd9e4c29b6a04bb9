//! What the store keeps of the remote lab (docs/lab.md): each experiment's
//! record and results folder, and the lab's own state (the owner's
//! settings, the baseline, whether the queue is paused, the reservations,
//! the id counters).
//!
//! Layout under the store's root:
//! ```text
//! lab.json                        the lab's state (`LabState`)
//! experiments/<id>/experiment.json  one experiment (`ExperimentRecord`), rewritten at every change
//! experiments/<id>/...            its results (recordings, reports, log, robot file)
//! ```
//!
//! Invariants: experiment ids are never reused (the counter is written
//! before the record); every file is replaced atomically, so a kill -9
//! leaves each record as it was before or after a change; a record of a
//! newer format than this host knows is refused, never guessed at.

use std::collections::BTreeMap;
use std::path::PathBuf;

use serde::{Deserialize, Serialize};

/// Format of `lab.json` and `experiment.json`.
pub const LAB_FORMAT: u32 = 1;

/// Experiments the store keeps records of; the oldest finished ones are
/// forgotten beyond this (their results went first, by the retention cap):
/// a lab running for years must not grow the store's folder without bound.
pub const MAX_EXPERIMENT_RECORDS: usize = 5000;

/// Experiment records one user keeps: beyond it her own oldest finished
/// ones are forgotten, so a user submitting and cancelling in a loop
/// erases only her own records.
pub const MAX_EXPERIMENT_RECORDS_PER_USER: usize = 1000;

/// Reservations kept (past ones are dropped first): a user booking in a
/// loop cannot grow `lab.json` without bound.
pub const MAX_RESERVATIONS: usize = 500;

/// Longest label an experiment keeps (it is shown to every admin).
pub const MAX_LABEL_LEN: usize = 120;

/// Reasons kept per experiment (a preflight can find many collisions).
pub const MAX_REASONS: usize = 32;

/// Where an experiment is in its life.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(rename_all = "lowercase")]
pub enum ExperimentState {
    /// Submitted; its set is being validated again.
    Checking,
    /// Running in the simulator first.
    Preflight,
    /// Passed; waiting for its turn.
    Queued,
    /// On the robot.
    Running,
    /// Its time is up (or it was stopped): the baseline comes back and the
    /// results are written.
    Finishing,
    Done,
    /// A check or the preflight failed (the reasons say which).
    Refused,
    /// Its submitter or an admin cancelled it.
    Cancelled,
    /// An emergency stop, or the host stopping while it ran.
    Aborted,
    /// Something of the host's went wrong (the reasons say what).
    Failed,
}

impl ExperimentState {
    pub const ALL: [ExperimentState; 10] = [
        ExperimentState::Checking,
        ExperimentState::Preflight,
        ExperimentState::Queued,
        ExperimentState::Running,
        ExperimentState::Finishing,
        ExperimentState::Done,
        ExperimentState::Refused,
        ExperimentState::Cancelled,
        ExperimentState::Aborted,
        ExperimentState::Failed,
    ];

    pub fn name(self) -> &'static str {
        match self {
            ExperimentState::Checking => "checking",
            ExperimentState::Preflight => "preflight",
            ExperimentState::Queued => "queued",
            ExperimentState::Running => "running",
            ExperimentState::Finishing => "finishing",
            ExperimentState::Done => "done",
            ExperimentState::Refused => "refused",
            ExperimentState::Cancelled => "cancelled",
            ExperimentState::Aborted => "aborted",
            ExperimentState::Failed => "failed",
        }
    }

    /// Whether it has ended (no state follows).
    pub fn is_final(self) -> bool {
        matches!(
            self,
            ExperimentState::Done
                | ExperimentState::Refused
                | ExperimentState::Cancelled
                | ExperimentState::Aborted
                | ExperimentState::Failed
        )
    }

    /// Whether it waits to run (checked, in preflight or queued): what the
    /// per-user queued limit counts.
    pub fn is_waiting(self) -> bool {
        matches!(self, ExperimentState::Checking | ExperimentState::Preflight | ExperimentState::Queued)
    }
}

impl ExperimentState {
    /// Whether an experiment in this state may go to `next`: the life in
    /// docs/lab.md as a table. `queued -> queued` is a lab server's refused
    /// dispatch going back to the queue once; `preflight -> checking` a
    /// host that stopped during a preflight checking it again; `running`
    /// and `finishing` end in any final state but `refused` (a lab server
    /// learns a robot's ending from the robot); an ended experiment goes
    /// nowhere.
    pub fn may_enter(self, next: ExperimentState) -> bool {
        use ExperimentState::*;
        match self {
            Checking => matches!(next, Preflight | Refused | Cancelled | Failed),
            Preflight => matches!(next, Queued | Checking | Refused | Cancelled | Failed),
            Queued => matches!(next, Queued | Running | Refused | Cancelled | Failed),
            Running => matches!(next, Finishing | Done | Cancelled | Aborted | Failed),
            Finishing => matches!(next, Done | Cancelled | Aborted | Failed),
            Done | Refused | Cancelled | Aborted | Failed => false,
        }
    }
}

/// An experiment asked to go where its life does not lead
/// ([`ExperimentState::may_enter`]): the host's own bug, refused.
#[derive(Clone, Copy, Debug, PartialEq, Eq, thiserror::Error)]
#[error("experiment {id} cannot go from {from} to {to}")]
pub struct IllegalTransition {
    pub id: u64,
    pub from: ExperimentState,
    pub to: ExperimentState,
}

impl std::fmt::Display for ExperimentState {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// One state change: when (ms since the Unix epoch) and why.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
pub struct StateChange {
    pub state: ExperimentState,
    pub at_ms: u64,
    pub cause: String,
}

/// A component of the experiment's set, as it ran.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
pub struct ComponentHash {
    pub name: String,
    /// `builtin:KIND`, or the source as the robot file writes it.
    pub source: String,
    /// The WASM file's sha256; `None` for built-ins.
    pub sha256: Option<String>,
}

/// What the preflight found.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
pub struct PreflightResult {
    pub passed: bool,
    /// Every reason it did not pass, in the order they happened.
    pub reasons: Vec<String>,
    /// Simulated seconds it ran.
    pub simulated_s: f64,
    /// Wall-clock seconds it took.
    pub wall_s: f64,
    /// The replay against the owner's reference recording, when one is
    /// named: information, never a refusal.
    #[serde(default)]
    pub replay: Option<serde_json::Value>,
    /// Its score against the experiment's task, from its recording (in
    /// the bundle as `preflight-score.json`): the simulator's side of the
    /// run's score.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub score: Option<crate::store::task::Score>,
    /// Why its simulated run ended, with the task's end conditions
    /// applied as on the robot (`goal`, `collision`, `time-out`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ended_by: Option<crate::store::task::EpisodeEnd>,
}

/// What the run on the robot left.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
pub struct RunResult {
    pub started_ms: u64,
    pub ended_ms: u64,
    /// Seconds of graph time it ran.
    pub ran_s: f64,
    /// Control-loop cycles that started later than the serial link's
    /// watchdog margin (the host's own lateness, not the algorithm's).
    pub late_cycles: u64,
    /// The worst lateness of a cycle, ms.
    pub worst_lateness_ms: f64,
    /// How the algorithm did (the run's status is the experiment's state:
    /// `done` says it ran to its end, not that it did well).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub outcome: Option<RunOutcome>,
}

/// How an algorithm did in its run on the robot, from the run's report:
/// its components' faults, the collisions its simulated robots counted,
/// the envelope's interventions by kind, and the world's goal.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
pub struct RunOutcome {
    /// Each component that faulted, with when (seconds from the run's
    /// start) and why; at most [`MAX_OUTCOME_FAULTS`].
    pub faults: Vec<FaultSeen>,
    /// Collisions (simulated robots; a real robot counts none).
    pub collisions: u64,
    /// The envelope's interventions, by cause (`stop-zone`, `geofence`,
    /// ...): each cause that happened, with its count.
    pub interventions: BTreeMap<String, u64>,
    /// Whether the world's goal was reached (simulated robots only).
    pub goal_reached: Option<bool>,
    /// Why the run (the episode) ended, when it ran to its end (`done`):
    /// at the task's goal, at its first collision (the task's end
    /// conditions), or at its duration (`time-out`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ended_by: Option<crate::store::task::EpisodeEnd>,
}

/// Faults kept in an outcome: a component restarted on every fault must
/// not grow the record without end.
pub const MAX_OUTCOME_FAULTS: usize = 16;

/// A component's fault in a run.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
pub struct FaultSeen {
    pub component: String,
    pub at_s: Option<f64>,
    pub reason: String,
}

impl RunOutcome {
    /// One line, as `lab submit`, `lab show`, the portal and the mails say
    /// it: `goal reached, no collision, no fault, no intervention`.
    pub fn said(&self) -> String {
        let mut parts = Vec::new();
        if let Some(end) = self.ended_by {
            parts.push(format!("ended: {}", end.name()));
        }
        match self.goal_reached {
            Some(true) => parts.push("goal reached".to_string()),
            Some(false) => parts.push("goal not reached".to_string()),
            None => {}
        }
        parts.push(match self.collisions {
            0 => "no collision".to_string(),
            1 => "1 collision".to_string(),
            n => format!("{n} collisions"),
        });
        parts.push(match self.faults.as_slice() {
            [] => "no fault".to_string(),
            [f] => format!("component '{}' faulted{}: {}", f.component, at(f.at_s), f.reason),
            [f, rest @ ..] => {
                format!("{} faults (first: '{}'{}: {})", rest.len() + 1, f.component, at(f.at_s), f.reason)
            }
        });
        if self.interventions.is_empty() {
            parts.push("no intervention".to_string());
        } else {
            let kinds: Vec<String> = self.interventions.iter().map(|(cause, n)| format!("{cause} {n}")).collect();
            parts.push(format!("interventions: {}", kinds.join(", ")));
        }
        parts.join(", ")
    }
}

fn at(at_s: Option<f64>) -> String {
    at_s.map(|s| format!(" at {s:.1} s")).unwrap_or_default()
}

/// A file of an experiment's results.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
pub struct ResultFile {
    /// Its name inside the experiment's folder (and the bundle).
    pub name: String,
    pub bytes: u64,
}

/// The settings an experiment ran under, copied when it was submitted.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
pub struct AppliedSettings {
    pub max_duration_s: f64,
    pub limits: Limits,
    pub criteria: Criteria,
    pub reset: ResetPolicy,
    /// The preflight's world (an uploaded world's name); `None`: the
    /// set's own.
    pub preflight_world: Option<String>,
    pub baseline: Option<u64>,
    /// The owner's task its run is scored against (docs/lab.md, "Tasks
    /// and scores").
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub task: Option<crate::store::task::Task>,
}

/// One experiment.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
pub struct ExperimentRecord {
    pub format: u32,
    pub id: u64,
    pub submitter: String,
    /// The staged set it runs.
    pub set: u64,
    pub label: String,
    pub duration_s: f64,
    pub submitted_ms: u64,
    pub state: ExperimentState,
    /// Every state it was in, oldest first (the first is `checking`).
    pub history: Vec<StateChange>,
    /// Why it was refused, aborted, cancelled or failed (at most
    /// [`MAX_REASONS`]).
    pub reasons: Vec<String>,
    pub settings: AppliedSettings,
    /// The set's components with their hashes, once checked.
    #[serde(default)]
    pub components: Vec<ComponentHash>,
    #[serde(default)]
    pub preflight: Option<PreflightResult>,
    #[serde(default)]
    pub run: Option<RunResult>,
    /// Files in its results folder.
    #[serde(default)]
    pub results: Vec<ResultFile>,
    /// Its recordings were removed by the retention cap; the record stays.
    #[serde(default)]
    pub recording_expired: bool,
    /// How long its first ETA said it would wait, from when it was queued
    /// (ms): it is refused, never started, after twice that (or the
    /// owner's `stuck_after_min_s`, whichever is longer).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub first_wait_ms: Option<u64>,
    /// On a robot of a lab: the lab that dispatched it (docs/lab.md,
    /// "Several robots").
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub origin: Option<Origin>,
    /// On a lab server: which robots may run it, and which does.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub placement: Option<Placement>,
    /// The reset by driving before it ran (the `drive` policy).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub reset: Option<ResetOutcome>,
    /// Its run's score against its task (its outcome; `state` is its
    /// status): in its bundle as `score.json`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub score: Option<crate::store::task::Score>,
}

/// Where a robot's experiment came from: lab `lab`'s experiment `id`,
/// submitted by a user with these rights in the lab.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
pub struct Origin {
    pub lab: String,
    pub id: u64,
    pub role: crate::store::users::Role,
    pub platforms: Vec<String>,
    /// It starts only before this time (ms since the Unix epoch): the lab
    /// stopped waiting for the dispatch's answer then.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub start_by_unix_ms: Option<u64>,
}

/// Which robots may run an experiment of a lab server.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(rename_all = "lowercase")]
pub enum Target {
    /// The first free robot.
    #[default]
    Any,
    /// This robot.
    Robot(String),
    /// The first free robot of this profile (its id).
    Profile(String),
}

/// Where a lab server's experiment is, among its robots.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
pub struct Placement {
    pub target: Target,
    /// The robot it was given to (while it is dispatched, runs, or after).
    pub robot: Option<String>,
    /// Its id on that robot.
    pub local_id: Option<u64>,
    /// Times a robot refused it (a second refusal ends it).
    pub refusals: u32,
    /// What the robot recorded is still to be fetched (it was lost).
    pub fetch_pending: bool,
    /// Its dispatch to `robot` is unanswered (sent, or its answer lost);
    /// the robot starts it only before this time (ms since the Unix epoch,
    /// the lab server's clock). Stored before the dispatch is sent, so a
    /// lab server restarted meanwhile knows it too. Once its answer is
    /// lost, it stays placed there until the robot says it will not run
    /// it (a withdrawal), or runs it, or the time plus the largest clock
    /// skew has passed.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub unanswered_start_by_ms: Option<u64>,
}

impl AppliedSettings {
    /// The owner's `settings` as an experiment submitted now runs under,
    /// with the lab's `baseline`.
    pub fn of(settings: &LabSettings, baseline: u64) -> AppliedSettings {
        AppliedSettings {
            max_duration_s: settings.max_duration_s,
            limits: settings.limits,
            criteria: settings.criteria,
            reset: settings.reset,
            preflight_world: settings.preflight_world.clone(),
            baseline: Some(baseline),
            task: settings.task.clone(),
        }
    }
}

/// What a new experiment's record is made of (a submission here, or a
/// lab's dispatch on a robot).
#[derive(Clone, Debug)]
pub struct NewExperiment {
    pub submitter: String,
    pub set: u64,
    pub label: String,
    pub duration_s: f64,
    pub submitted_ms: u64,
    pub settings: AppliedSettings,
    pub components: Vec<ComponentHash>,
}

impl ExperimentRecord {
    /// Ended without ever running (cancelled or refused in its checks or
    /// its queue): nothing of it happened on the robot.
    pub fn ended_unrun(&self) -> bool {
        self.state.is_final() && self.entered(ExperimentState::Running).is_none()
    }

    /// The record of `new`, in its first `state` since it was submitted,
    /// for `cause` (the store gives it its id).
    pub fn new(new: NewExperiment, state: ExperimentState, cause: &str) -> ExperimentRecord {
        let NewExperiment { submitter, set, label, duration_s, submitted_ms, settings, components } = new;
        ExperimentRecord {
            format: LAB_FORMAT,
            id: 0,
            submitter,
            set,
            label,
            duration_s,
            submitted_ms,
            state,
            history: vec![StateChange { state, at_ms: submitted_ms, cause: cause.to_string() }],
            reasons: Vec::new(),
            settings,
            components,
            preflight: None,
            run: None,
            results: Vec::new(),
            recording_expired: false,
            first_wait_ms: None,
            origin: None,
            placement: None,
            reset: None,
            score: None,
        }
    }

    pub(super) fn parse(bytes: &[u8]) -> Result<ExperimentRecord, String> {
        check_format(bytes)?;
        serde_json::from_slice(bytes).map_err(|e| e.to_string())
    }

    /// Moves it to `state` at `at_ms` for `cause`, if its life leads there
    /// from where it is (else nothing changes).
    pub fn enter(&mut self, state: ExperimentState, at_ms: u64, cause: &str) -> Result<(), IllegalTransition> {
        if !self.state.may_enter(state) {
            return Err(IllegalTransition { id: self.id, from: self.state, to: state });
        }
        self.state = state;
        self.history.push(StateChange { state, at_ms, cause: cause.to_string() });
        Ok(())
    }

    /// Adds a reason (at most [`MAX_REASONS`]; the rest are counted).
    pub fn add_reason(&mut self, reason: String) {
        if self.reasons.len() + 1 < MAX_REASONS {
            self.reasons.push(reason);
        } else if self.reasons.len() + 1 == MAX_REASONS {
            self.reasons.push("... and more (the report lists every one)".into());
        }
    }

    /// When it entered `state` last, if it did.
    pub fn entered(&self, state: ExperimentState) -> Option<u64> {
        self.history.iter().rev().find(|c| c.state == state).map(|c| c.at_ms)
    }

    /// The robot time it holds, ms: its duration while it waits or runs,
    /// what it ran once it ended, 0 when it never ran.
    pub fn robot_ms(&self) -> u64 {
        let duration_ms = (self.duration_s * 1000.0) as u64;
        match self.state {
            s if s.is_waiting() => duration_ms,
            ExperimentState::Running | ExperimentState::Finishing => duration_ms,
            _ => match (self.entered(ExperimentState::Running), &self.run) {
                (_, Some(run)) => (run.ran_s * 1000.0) as u64,
                (Some(started), None) => {
                    let ended = self.history.last().map_or(started, |c| c.at_ms);
                    ended.saturating_sub(started).min(duration_ms)
                }
                (None, None) => 0,
            },
        }
    }
}

/// A booked window: only `user`'s experiments run in it, and `user` may
/// drive.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize, schemars::JsonSchema)]
pub struct Reservation {
    pub id: u64,
    pub user: String,
    pub start_ms: u64,
    pub end_ms: u64,
}

impl Reservation {
    pub fn contains(&self, at_ms: u64) -> bool {
        self.start_ms <= at_ms && at_ms < self.end_ms
    }

    pub fn overlaps(&self, start_ms: u64, end_ms: u64) -> bool {
        self.start_ms < end_ms && start_ms < self.end_ms
    }
}

/// The owner's limits on what one user may ask of the robot.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct Limits {
    /// Experiments a user may have waiting (checked, in preflight or
    /// queued): one user cannot fill the queue.
    pub max_queued: u32,
    /// Robot minutes a user may use in any 24 hours: one user cannot hold
    /// the robot all day.
    pub robot_minutes_per_day: f64,
    /// Longest reservation, seconds: one booking cannot take the robot for
    /// a day.
    pub max_reservation_s: u64,
    /// Reserved seconds a user may book per UTC day.
    pub reservation_per_day_s: u64,
}

impl Default for Limits {
    fn default() -> Limits {
        Limits {
            max_queued: 3,
            robot_minutes_per_day: 30.0,
            max_reservation_s: 30 * 60,
            reservation_per_day_s: 60 * 60,
        }
    }
}

/// What the preflight must see to pass (the owner's; by default nothing
/// of the kind may happen).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct Criteria {
    /// Collisions with obstacles allowed.
    pub max_collisions: u32,
    /// Whether a component may fault.
    pub allow_faults: bool,
    /// Whether the robot may reach or leave the geofence (the envelope
    /// holding it there counts).
    pub allow_geofence: bool,
    /// Whether the envelope's collision (stop) zone may stop it.
    pub allow_stop_zone: bool,
    /// On the robot too: a run that breaks these criteria (a fault, more
    /// collisions, the stop zone or the geofence) ends early, aborted with
    /// the breach named. Off by default: the criteria judge the preflight.
    #[serde(default)]
    pub end_run_on_breach: bool,
}

/// How the robot gets back to its start before each experiment.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(rename_all = "lowercase")]
pub enum ResetPolicy {
    /// The simulated world is reset.
    #[default]
    Sim,
    /// A person puts the robot back; an admin confirms in the portal.
    Manual,
    /// The owner's reset set drives the robot back to its start pose
    /// ([`DriveReset`]).
    Drive,
}

/// The owner's settings of the lab.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct LabSettings {
    /// Longest experiment, seconds.
    pub max_duration_s: f64,
    pub limits: Limits,
    pub criteria: Criteria,
    pub reset: ResetPolicy,
    /// The uploaded world the preflight runs in; `None`: each set's own.
    pub preflight_world: Option<String>,
    /// A recording in the host's recordings folder that each experiment's
    /// components are also replayed against (information only).
    pub reference_recording: Option<String>,
    /// Total bytes of experiments' results kept; the oldest finished
    /// experiments' recordings go first beyond it.
    pub retention_bytes: u64,
    /// Whether researchers may download the lab kit (the baseline's robot
    /// file and components).
    pub kit: bool,
    /// The least a queued experiment waits before, never started, it is
    /// refused (seconds): it is refused after twice its first ETA, or
    /// this, whichever is longer (docs/lab.md, "Nothing silently stuck").
    #[serde(default = "default_stuck_after_min_s")]
    pub stuck_after_min_s: u64,
    /// Motors and batteries that need rest: after `run_s` seconds of
    /// experiments the robot rests `rest_s` before the next starts. Off
    /// (`null`) by default.
    #[serde(default)]
    pub duty_cycle: Option<DutyCycle>,
    /// The checks run on the robot after every experiment, once its
    /// baseline is back (docs/lab.md, "Self-test"). Off (`null`) by
    /// default; a failed one takes the robot out of service.
    #[serde(default)]
    pub self_test: Option<SelfTestSettings>,
    /// With the `drive` reset policy: the set that drives the robot back,
    /// and where to (docs/lab.md, "Reset by driving").
    #[serde(default)]
    pub drive_reset: Option<DriveReset>,
    /// The task every run is scored against (docs/lab.md, "Tasks and
    /// scores"). Off (`null`) by default.
    #[serde(default)]
    pub task: Option<crate::store::task::Task>,
    /// How many times the preflight runs, and the timing a robot has that
    /// each run is seeded with (docs/lab.md, "Timing"). Settings from
    /// before it get the defaults.
    #[serde(default)]
    pub preflight_timing: PreflightTiming,
}

/// Runs of a preflight by default: a few, so that a set whose verdict
/// hangs on timing is likely seen both ways, and a 60 s experiment's
/// preflight still takes seconds.
pub const DEFAULT_PREFLIGHT_RUNS: u32 = 3;

/// Most runs of a preflight. Threat: each run is a whole preflight on the
/// lab's CPU; more would hold every experiment's checks that many times as
/// long.
pub const MAX_PREFLIGHT_RUNS: u32 = 10;

/// The preflight's runs and the bounds of each one's seeded timing
/// (`sim::perturb::PerturbBounds`, whose limits they keep).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct PreflightTiming {
    /// Runs, each with its own seed (1 to [`MAX_PREFLIGHT_RUNS`]).
    pub runs: u32,
    /// Offset each component's first tick by a seeded fraction of its period.
    pub tick_phase: bool,
    /// Most a sensor reading waits before it reaches the host (ms).
    pub sensor_latency_ms: f64,
    /// Most a range reading is off, either way (m).
    pub range_noise_m: f64,
    /// Most a command waits on the serial link before the motors act on it (ms).
    pub serial_delay_ms: f64,
}

impl PreflightTiming {
    /// The bounds of each run's perturbation.
    pub fn bounds(&self) -> crate::sim::perturb::PerturbBounds {
        crate::sim::perturb::PerturbBounds {
            tick_phase: self.tick_phase,
            sensor_latency_ms: self.sensor_latency_ms,
            range_noise_m: self.range_noise_m,
            serial_delay_ms: self.serial_delay_ms,
        }
    }
}

impl Default for PreflightTiming {
    /// [`DEFAULT_PREFLIGHT_RUNS`] runs within the default bounds
    /// (`PerturbBounds::DEFAULT`, with their reasons).
    fn default() -> PreflightTiming {
        let bounds = crate::sim::perturb::PerturbBounds::DEFAULT;
        PreflightTiming {
            runs: DEFAULT_PREFLIGHT_RUNS,
            tick_phase: bounds.tick_phase,
            sensor_latency_ms: bounds.sensor_latency_ms,
            range_noise_m: bounds.range_noise_m,
            serial_delay_ms: bounds.serial_delay_ms,
        }
    }
}

impl LabSettings {
    /// The start pose the reset by driving brings the robot to, with the
    /// `drive` policy (the preflight's simulated robot starts there too).
    pub fn start_pose(&self) -> Option<Pose> {
        self.drive_reset().map(|d| d.pose)
    }

    /// The reset by driving, when the policy is `drive` (settings kept
    /// under another policy do nothing).
    pub fn drive_reset(&self) -> Option<&DriveReset> {
        self.drive_reset.as_ref().filter(|_| self.reset == ResetPolicy::Drive)
    }
}

/// The owner's reset by driving: before each experiment, set `set` runs
/// until the robot's pose is within `tolerance` of `pose`, and still is
/// after `settle_s` at rest, or `timeout_s` has passed (a failure: the
/// robot goes out of service).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct DriveReset {
    /// The reset set (a staged set; it keeps the robot's envelope).
    pub set: u64,
    /// The start pose.
    pub pose: Pose,
    pub tolerance: PoseTolerance,
    /// Longest a reset drives (s, 1 to 600).
    pub timeout_s: u64,
    /// How long the robot must hold the pose at rest (s, 0 to 60).
    pub settle_s: f64,
    /// The serial link whose odometry is the robot's pose; `None`: the
    /// first (by name) that reports one.
    #[serde(default)]
    pub link: Option<String>,
}

/// A pose in the robot's odometry frame: metres, and radians
/// counter-clockwise from +x.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct Pose {
    pub x: f64,
    pub y: f64,
    /// Radians.
    pub heading: f64,
}

/// How far from the start pose still counts as at it.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct PoseTolerance {
    pub position_m: f64,
    pub heading_rad: f64,
}

/// Longest reset by driving (s): beyond it a robot that cannot get back
/// is better out of service than holding the queue.
pub const MAX_RESET_TIMEOUT_S: u64 = 600;
/// Longest settle time (s).
pub const MAX_RESET_SETTLE_S: f64 = 60.0;

/// How a reset by driving went (on the record of the experiment it was
/// for).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
pub struct ResetOutcome {
    /// When it began (ms since the Unix epoch).
    pub at_ms: u64,
    pub passed: bool,
    /// Seconds from the reset set's start to the end of the settle.
    pub took_s: f64,
    /// The pose when it began, and when it ended (`None`: none reported).
    pub from: Option<Pose>,
    pub pose: Option<Pose>,
    /// Why it failed.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub error: Option<String>,
}

/// The owner's self-test: what is checked after every run.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct SelfTestSettings {
    /// How long the robot is watched (ms, 200 to 10000): every serial
    /// link must give feedback within it.
    pub window_ms: u64,
    /// The least battery voltage, where a link reports one.
    #[serde(default)]
    pub min_battery_v: Option<f64>,
    /// A robot out of service for a low battery alone comes back by itself
    /// once every battery reads at least this (above `min_battery_v`:
    /// charged, not just over the line). `None`: an admin ends it.
    #[serde(default)]
    pub resume_battery_v: Option<f64>,
    /// The check "controller": no serial link's motor controller reports a
    /// fault (where its protocol has a fault status). On unless the owner
    /// turns it off.
    #[serde(default = "checked")]
    pub controller_faults: bool,
    /// The check "motion": over the window, each serial link's odometry
    /// shows at least this share of the distance its commands asked for,
    /// and at most its inverse (a motor that does not answer, a wheel off
    /// the floor, a runaway). Judged when the baseline commands at least
    /// [`MIN_JUDGED_MOTION_M`]; off (`None`) by default.
    #[serde(default)]
    pub odometry_ratio: Option<f64>,
}

/// The least distance a self-test's window must command before the
/// motion check judges it (m): less, and the odometry's own noise and the
/// commands' latency would decide it.
pub const MIN_JUDGED_MOTION_M: f64 = 0.05;

/// A check the owner has not turned off is on.
fn checked() -> bool {
    true
}

/// Shortest and longest self-test window: shorter, a link polled at 5 Hz
/// may look silent; longer, the robot idles that long after every run.
pub const SELF_TEST_WINDOW_MS: std::ops::RangeInclusive<u64> = 200..=10_000;

/// One self-test, as run after an experiment (or asked by an admin).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
pub struct SelfTest {
    pub at_ms: u64,
    /// The experiment it followed, if any.
    pub experiment: Option<u64>,
    pub passed: bool,
    pub checks: Vec<SelfTestCheck>,
}

/// One check of a self-test, and what it found.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
pub struct SelfTestCheck {
    /// `feedback`, `components` or `battery`.
    pub check: String,
    pub passed: bool,
    pub detail: String,
}

/// Most self-tests kept in the lab's state (the newest): the owner's
/// history, bounded so the state file stays small.
pub const MAX_SELF_TESTS: usize = 50;

/// Run at most `run_s` seconds of experiments, then rest `rest_s`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct DutyCycle {
    pub run_s: u64,
    pub rest_s: u64,
}

/// 15 minutes: a queue held that long (an emergency stop, maintenance) is
/// told to its submitters rather than left to wait without end.
pub const DEFAULT_STUCK_AFTER_MIN_S: u64 = 15 * 60;

fn default_stuck_after_min_s() -> u64 {
    DEFAULT_STUCK_AFTER_MIN_S
}

impl Default for LabSettings {
    fn default() -> LabSettings {
        LabSettings {
            max_duration_s: 120.0,
            limits: Limits::default(),
            criteria: Criteria::default(),
            reset: ResetPolicy::Sim,
            preflight_world: None,
            reference_recording: None,
            retention_bytes: 10 << 30,
            kit: true,
            stuck_after_min_s: DEFAULT_STUCK_AFTER_MIN_S,
            duty_cycle: None,
            self_test: None,
            drive_reset: None,
            task: None,
            preflight_timing: PreflightTiming::default(),
        }
    }
}

/// Refuses a file of a newer format before reading its fields (a newer
/// host may have changed them; the refusal says so rather than naming a
/// missing field).
fn check_format(bytes: &[u8]) -> Result<(), String> {
    #[derive(Deserialize)]
    struct Format {
        format: u32,
    }
    let Format { format } = serde_json::from_slice(bytes).map_err(|e| e.to_string())?;
    if format > LAB_FORMAT {
        return Err(format!("format {format} is newer than this host's {LAB_FORMAT}"));
    }
    Ok(())
}

/// `lab.json`: the lab's own state.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
pub struct LabState {
    pub format: u32,
    pub next_experiment: u64,
    pub next_reservation: u64,
    pub settings: LabSettings,
    /// The set the robot runs between experiments; `None`: the set the
    /// host started with.
    pub baseline: Option<u64>,
    pub paused: bool,
    pub reservations: Vec<Reservation>,
    /// On a lab server: the robots' baselines it imported, by their hash
    /// (set ids in this store).
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub baselines: BTreeMap<String, u64>,
    /// The robot is out of service: no experiment starts until an admin
    /// ends it (docs/lab.md, "Maintenance").
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub maintenance: Option<Maintenance>,
    /// The newest self-tests, oldest first (at most [`MAX_SELF_TESTS`]).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub self_tests: Vec<SelfTest>,
}

/// Why and since when the robot is out of service, and who said so.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
pub struct Maintenance {
    pub reason: String,
    pub by: String,
    pub since_ms: u64,
    /// Entered by the self-test for a low battery alone: it ends by itself
    /// once every battery reads at least this (volts).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ends_at_battery_v: Option<f64>,
}

/// Longest reason for maintenance, characters: it is shown to every user
/// in the queue and sent in notifications.
pub const MAX_MAINTENANCE_REASON: usize = 500;

impl Default for LabState {
    fn default() -> LabState {
        LabState {
            format: LAB_FORMAT,
            next_experiment: 1,
            next_reservation: 1,
            settings: LabSettings::default(),
            baseline: None,
            paused: false,
            reservations: Vec::new(),
            baselines: BTreeMap::new(),
            maintenance: None,
            self_tests: Vec::new(),
        }
    }
}

impl LabState {
    pub(super) fn parse(bytes: &[u8]) -> Result<LabState, String> {
        check_format(bytes)?;
        let mut state: LabState = serde_json::from_slice(bytes).map_err(|e| e.to_string())?;
        state.next_experiment = state.next_experiment.max(1);
        state.next_reservation = state.next_reservation.max(1);
        Ok(state)
    }
}

/// The folder of experiment `id` under the store's root.
pub fn experiment_dir(root: &std::path::Path, id: u64) -> PathBuf {
    root.join("experiments").join(id.to_string())
}

/// Experiments by id.
pub type Experiments = BTreeMap<u64, ExperimentRecord>;

#[cfg(test)]
mod tests {
    use super::*;
    use crate::store::task::EpisodeEnd;

    #[test]
    fn the_life_of_an_experiment_is_a_table_checked_pair_by_pair() {
        use ExperimentState::*;
        // Row: from; the states it may enter, in ALL's order. The life in
        // docs/lab.md ("An experiment's life").
        let table: [(ExperimentState, &[ExperimentState]); 10] = [
            (Checking, &[Preflight, Refused, Cancelled, Failed]),
            (Preflight, &[Checking, Queued, Refused, Cancelled, Failed]),
            (Queued, &[Queued, Running, Refused, Cancelled, Failed]),
            (Running, &[Finishing, Done, Cancelled, Aborted, Failed]),
            (Finishing, &[Done, Cancelled, Aborted, Failed]),
            (Done, &[]),
            (Refused, &[]),
            (Cancelled, &[]),
            (Aborted, &[]),
            (Failed, &[]),
        ];
        for (from, allowed) in table {
            for to in ExperimentState::ALL {
                assert_eq!(from.may_enter(to), allowed.contains(&to), "{from} -> {to}");
            }
        }
        // `enter` keeps to it: a refused move changes nothing.
        let new = NewExperiment {
            submitter: "ana".into(),
            set: 3,
            label: String::new(),
            duration_s: 10.0,
            submitted_ms: 1,
            settings: AppliedSettings::of(&LabSettings::default(), 1),
            components: Vec::new(),
        };
        let mut record = ExperimentRecord::new(new, Checking, "submitted by ana");
        assert_eq!(
            record.enter(Queued, 2, "skips its preflight"),
            Err(IllegalTransition { id: 0, from: Checking, to: Queued })
        );
        assert_eq!((record.state, record.history.len()), (Checking, 1));
        for (to, at) in [(Preflight, 3), (Queued, 4), (Running, 5), (Finishing, 6), (Done, 7)] {
            record.enter(to, at, "on").unwrap();
        }
        assert!(record.enter(Failed, 8, "after the end").is_err());
        let states: Vec<_> = record.history.iter().map(|c| (c.state, c.at_ms)).collect();
        assert_eq!(states, [(Checking, 1), (Preflight, 3), (Queued, 4), (Running, 5), (Finishing, 6), (Done, 7)]);
    }

    #[test]
    fn states_say_whether_they_wait_or_ended() {
        let waiting: Vec<&str> = ExperimentState::ALL.iter().filter(|s| s.is_waiting()).map(|s| s.name()).collect();
        let ended: Vec<&str> = ExperimentState::ALL.iter().filter(|s| s.is_final()).map(|s| s.name()).collect();
        assert_eq!(waiting, ["checking", "preflight", "queued"]);
        assert_eq!(ended, ["done", "refused", "cancelled", "aborted", "failed"]);
        for state in ExperimentState::ALL {
            let json = serde_json::to_string(&state).unwrap_or_default();
            assert_eq!(json, format!("\"{}\"", state.name()));
        }
    }

    /// Settings written before the preflight's timing existed load with
    /// its defaults; written back, they carry it.
    #[test]
    fn settings_from_before_the_preflights_timing_load_with_its_defaults() {
        let mut old = serde_json::to_value(LabSettings::default()).unwrap();
        old.as_object_mut().unwrap().remove("preflight_timing");
        let settings: LabSettings = serde_json::from_value(old).unwrap();
        assert_eq!(settings.preflight_timing, PreflightTiming::default());
        assert_eq!(settings.preflight_timing.runs, DEFAULT_PREFLIGHT_RUNS);
        assert_eq!(settings.preflight_timing.bounds(), crate::sim::perturb::PerturbBounds::DEFAULT);
        let written = serde_json::to_value(&settings).unwrap();
        assert_eq!(written["preflight_timing"]["runs"], 3, "{written:#}");
        let unknown = serde_json::json!({ "runs": 3, "tick_phase": true, "sensor_latency_ms": 1.0, "range_noise_m": 0.0,
            "serial_delay_ms": 0.0, "jitter": 1 });
        assert!(serde_json::from_value::<PreflightTiming>(unknown).is_err(), "an unknown bound is refused");
    }

    #[test]
    fn newer_formats_are_refused_and_counters_start_at_one() {
        let newer = format!(r#"{{"format": {}, "next_experiment": 1}}"#, LAB_FORMAT + 1);
        let refusal = format!("format {} is newer", LAB_FORMAT + 1);
        assert!(LabState::parse(newer.as_bytes()).is_err_and(|e| e.contains(&refusal)));
        let mut state = LabState { next_experiment: 0, ..LabState::default() };
        state.next_reservation = 0;
        let bytes = serde_json::to_vec(&state).unwrap_or_default();
        let read = LabState::parse(&bytes).unwrap_or_default();
        assert_eq!((read.next_experiment, read.next_reservation), (1, 1));
    }

    #[test]
    fn an_outcome_is_said_in_one_line_apart_from_the_status() {
        let fault = |c: &str, at: Option<f64>| FaultSeen { component: c.into(), at_s: at, reason: "trapped".into() };
        let kinds = |k: &[(&str, u64)]| k.iter().map(|(c, n)| (c.to_string(), *n)).collect::<BTreeMap<_, _>>();
        let cases = [
            (RunOutcome::default(), "no collision, no fault, no intervention"),
            (
                RunOutcome { goal_reached: Some(true), ..RunOutcome::default() },
                "goal reached, no collision, no fault, no intervention",
            ),
            (
                RunOutcome {
                    goal_reached: Some(false),
                    collisions: 2,
                    faults: vec![fault("planner", Some(3.26))],
                    interventions: kinds(&[("stop-zone", 4), ("geofence", 1)]),
                    ended_by: None,
                },
                "goal not reached, 2 collisions, component 'planner' faulted at 3.3 s: trapped, \
                 interventions: geofence 1, stop-zone 4",
            ),
            (
                RunOutcome {
                    collisions: 1,
                    faults: vec![fault("a", None), fault("b", Some(1.0))],
                    ..RunOutcome::default()
                },
                "1 collision, 2 faults (first: 'a': trapped), no intervention",
            ),
            (
                RunOutcome { ended_by: Some(EpisodeEnd::Goal), goal_reached: Some(true), ..RunOutcome::default() },
                "ended: goal, goal reached, no collision, no fault, no intervention",
            ),
            (
                RunOutcome { ended_by: Some(EpisodeEnd::TimeOut), ..RunOutcome::default() },
                "ended: time-out, no collision, no fault, no intervention",
            ),
            (
                RunOutcome { ended_by: Some(EpisodeEnd::Collision), collisions: 1, ..RunOutcome::default() },
                "ended: collision, 1 collision, no fault, no intervention",
            ),
        ];
        for (outcome, said) in cases {
            assert_eq!(outcome.said(), said);
            let json = serde_json::to_string(&outcome).unwrap_or_default();
            assert_eq!(serde_json::from_str::<RunOutcome>(&json).ok(), Some(outcome), "{json}");
        }
        // A record written before outcomes existed still reads.
        let old = r#"{"started_ms": 1, "ended_ms": 2, "ran_s": 1.0, "late_cycles": 0, "worst_lateness_ms": 0.1}"#;
        assert_eq!(serde_json::from_str::<RunResult>(old).ok().map(|r| r.outcome), Some(None));
        // Why the episode ended is spelt as the record keeps it.
        let ended = RunOutcome { ended_by: Some(EpisodeEnd::TimeOut), ..RunOutcome::default() };
        let json = serde_json::to_value(&ended).unwrap_or_default();
        assert_eq!(json["ended_by"], "time-out", "{json}");
    }
}
