//! The deploy side of the remote lab's experiments (docs/lab.md): an
//! experiment's set is checked against the baseline, swapped in from a
//! fresh start with its recording attached at the swap, and replaced by the
//! baseline when it ends; while one runs, [`ExperimentGate`] refuses every
//! other activation (an admin's cancels the experiment first).
//!
//! These are the lab's own steps, not a user's requests: the lab checks who
//! may submit and cancel, and writes the experiment's record; each step
//! here still takes the active set's lock, validates like an activation,
//! and writes its audit line under the store's lock.
//!
//! Invariants: an experiment never changes the envelope (its settings are
//! the owner's, whoever submits) nor a platform its submitter does not
//! hold; an experiment's activation is not recorded as the active set in
//! `state.json`, so a host that stops during one starts again on the
//! baseline; if the baseline cannot be built when an experiment ends, the
//! emergency stop is engaged before anything else, so the robot never goes
//! on under the experiment.

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::{Arc, Mutex, Weak};

use super::activate::Ready;
use super::{DeployError, Deployer, stage};
use crate::assemble::Loader;
use crate::config::{ComponentSource, RobotConfig};
use crate::record::Layout;
use crate::record::control::{Recordings, Stopped};
use crate::report::{ExperimentTag, Report};
use crate::runtime::Locks;
use crate::runtime::locks::unix_now_ms;
use crate::store::users::{Principal, Role};
use crate::store::{Outcome, SetRecord};

/// The user the lab's own activations are made as (in the audit log).
pub const LAB_USER: &str = "lab";

/// The lock the lab engages when the baseline cannot come back.
pub const LAB_LOCK: &str = "estop";

/// The experiment that runs now, as everyone else's requests see it.
#[derive(Clone, Debug, PartialEq, serde::Serialize, schemars::JsonSchema)]
pub struct RunningExperiment {
    pub id: u64,
    pub submitter: String,
    pub set: u64,
    pub label: String,
    pub started_unix_ms: u64,
    pub ends_unix_ms: u64,
}

/// Ends the running experiment for an admin's activation (the lab
/// implements it; see [`ExperimentGate::on_preempt`]).
pub trait Preempt: Send + Sync {
    /// Ends experiment `id` now (the baseline comes back, the results are
    /// written) because `by` is about to `what`; returns what it did, for
    /// the admin's answer.
    fn preempt(&self, id: u64, by: &str, what: &str) -> Result<String, PreemptError>;
}

/// Why the running experiment could not be ended for an admin.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[error("{0}")]
pub struct PreemptError(pub String);

/// Whether an experiment runs, and who ends it for an admin.
#[derive(Default)]
pub struct ExperimentGate {
    running: Mutex<Option<RunningExperiment>>,
    /// What ran before the running experiment (the set that comes back
    /// after it): what robot files are staged against meanwhile.
    before: Mutex<Option<(SetRecord, Arc<RobotConfig>)>>,
    preempt: Mutex<Option<Weak<dyn Preempt>>>,
    /// The experiment the lab's reset set drives the robot back for, while
    /// it does (`reset.rs`).
    resetting: Mutex<Option<u64>>,
}

impl ExperimentGate {
    /// The experiment that runs now, if any.
    pub fn running(&self) -> Option<RunningExperiment> {
        self.running.lock().ok().and_then(|r| r.clone())
    }

    fn set(&self, running: Option<RunningExperiment>) {
        if let Ok(mut slot) = self.running.lock() {
            *slot = running;
        }
    }

    pub(super) fn set_before(&self, before: Option<(SetRecord, Arc<RobotConfig>)>) {
        if let Ok(mut slot) = self.before.lock() {
            *slot = before;
        }
    }

    /// The experiment the lab's reset runs for, while one runs.
    pub fn resetting(&self) -> Option<u64> {
        self.resetting.lock().ok().and_then(|r| *r)
    }

    pub(super) fn set_resetting(&self, before: Option<u64>) {
        if let Ok(mut slot) = self.resetting.lock() {
            *slot = before;
        }
    }

    /// The set that ran before the running experiment, if one runs.
    pub fn before(&self) -> Option<(SetRecord, Arc<RobotConfig>)> {
        self.before.lock().ok().and_then(|b| b.clone())
    }

    /// Who ends the running experiment when an admin activates a set.
    pub fn on_preempt(&self, preempt: Weak<dyn Preempt>) {
        if let Ok(mut slot) = self.preempt.lock() {
            *slot = Some(preempt);
        }
    }

    /// Whether `user` may `what` (an activation, a rollback, ...) now: yes
    /// when no experiment runs; a 409 naming the experiment and when it
    /// ends for anyone but an admin; for an admin, the experiment is ended
    /// first and the answer says so.
    pub(super) fn admit(&self, user: &Principal, what: &str) -> Result<Option<String>, DeployError> {
        if let Some(before) = self.resetting() {
            return Err(DeployError::Conflict(format!(
                "the lab drives the robot back to its start before experiment {before}: nobody changes what runs until the reset ends"
            )));
        }
        let Some(running) = self.running() else { return Ok(None) };
        if user.role != Role::Admin {
            let left_s = running.ends_unix_ms.saturating_sub(unix_now_ms()).div_ceil(1000);
            return Err(DeployError::Conflict(format!(
                "experiment {} by {} runs until {} ({left_s} s from now): nobody else changes what runs until it ends",
                running.id,
                running.submitter,
                utc_time(running.ends_unix_ms)
            )));
        }
        let preempt = self.preempt.lock().ok().and_then(|p| p.as_ref().and_then(Weak::upgrade));
        let Some(preempt) = preempt else {
            return Err(DeployError::Host(format!("experiment {} runs and nothing can end it", running.id)));
        };
        preempt.preempt(running.id, &user.name, what).map(Some).map_err(|e| DeployError::Host(e.0))
    }
}

/// A time in ms since the Unix epoch as a person reads it: its time of
/// day, with its date when it is not today (`walltime::shown`).
pub fn utc_time(unix_ms: u64) -> String {
    crate::walltime::shown(unix_ms)
}

/// A set checked to run as an experiment.
#[derive(Clone, Debug)]
pub struct CheckedSet {
    pub set: SetRecord,
    pub config: Arc<RobotConfig>,
    /// Each component's name, source and, for WASM, its sha256.
    pub components: Vec<(String, String, Option<String>)>,
}

/// What an experiment left when it ended.
#[derive(Debug, Default)]
pub struct Ended {
    /// The experiment graph's report, taken on the control thread as it
    /// was swapped out.
    pub report: Option<Report>,
    /// Its recording, stopped.
    pub recording: Option<Stopped>,
}

/// The simulated robots of `config`.
fn simulated_robots(config: &RobotConfig) -> impl Iterator<Item = &crate::config::ComponentConfig> {
    let sim = crate::assemble::registry::kind_of(&crate::sim::builtin::SimBuiltin);
    config.components.iter().filter(move |c| matches!(c.source, ComponentSource::Builtin(k) if Some(k) == sim))
}

pub(super) fn lab_user() -> Principal {
    Principal::host(LAB_USER)
}

/// The components of `config` with their sha256 (the stored blob a WASM
/// source of `set` was pinned to).
fn component_hashes(set: &SetRecord, config: &RobotConfig) -> Vec<(String, String, Option<String>)> {
    config
        .components
        .iter()
        .map(|c| match &c.source {
            ComponentSource::Builtin(kind) => (c.name.clone(), format!("builtin:{kind}"), None),
            ComponentSource::Wasm(path) => {
                let sha = path.file_name().map(|n| n.to_string_lossy().into_owned());
                let written = sha
                    .as_ref()
                    .and_then(|sha| set.sources.iter().find(|(_, blob)| *blob == sha).map(|(source, _)| source.clone()))
                    .unwrap_or_else(|| path.display().to_string());
                (c.name.clone(), written, sha)
            }
        })
        .collect()
}

impl Deployer {
    /// The gate experiments pass through.
    pub fn experiments(&self) -> &ExperimentGate {
        &self.experiments
    }

    /// The set the host started with (the lab's default baseline).
    pub fn boot_set(&self) -> u64 {
        self.boot_set
    }

    /// Checks that set `id` may run as `user`'s experiment on the robot
    /// whose baseline is set `baseline`: it validates (422 with the
    /// diagnostics `subsume check` prints), it changes only platforms
    /// `user` holds (403) and never the envelope (403, admins included).
    pub fn check_experiment_set(&self, user: &Principal, id: u64, baseline: u64) -> Result<CheckedSet, DeployError> {
        let set = self.store.set(id)?;
        if let Some(platform) = set.platform.as_deref()
            && let Ok(platform) = crate::config::Platform::parse(platform)
            && !user.may_change(platform)
        {
            return Err(DeployError::Forbidden(format!(
                "set {id} was staged for platform {}, which {} does not hold",
                platform.name(),
                user.name
            )));
        }
        let mut loader = Loader::new(&self.sandbox);
        let config = stage::validate_set(&self.store, &set, &mut loader, &self.overrides)?;
        let base = self.store.set(baseline)?;
        let base_config = stage::validate_set(&self.store, &base, &mut loader, &self.overrides)
            .map_err(|e| DeployError::Host(format!("the baseline (set {baseline}) does not validate: {e}")))?;
        if let Some(denied) = stage::platform_changes(&base_config, &config).iter().find(|p| !user.may_change(**p)) {
            return Err(DeployError::Forbidden(format!(
                "set {id} changes platform {} of the baseline, which {} does not hold",
                denied.name(),
                user.name
            )));
        }
        if let Some(change) = stage::envelope_change(&base_config, &config) {
            return Err(DeployError::Forbidden(format!(
                "set {id} {change}: an experiment runs with the robot's own envelope settings"
            )));
        }
        let components = component_hashes(&set, &config);
        Ok(CheckedSet { set, config: Arc::new(config), components })
    }

    fn recordings_service(&self) -> Result<Arc<Recordings>, DeployError> {
        self.services
            .get::<Recordings>()
            .ok_or_else(|| DeployError::Host("this host keeps no recordings (run it with the portal)".into()))
    }

    /// Starts experiment `tag` on the robot: set `tag.set`, checked again
    /// against what runs (the baseline) and built beside it as `user`, is
    /// swapped in from a fresh start with its recording into `recording`
    /// attached in the same cycle boundary, its time line starting there;
    /// with `reset_sim` its simulated robots, and the serial links on
    /// them, are built afresh (at their world's start, time 0) rather than
    /// carried over from the active set.
    /// A portal recording that runs is stopped first (the graph has one
    /// recording tap).
    pub fn start_experiment(
        &self,
        user: &Principal,
        tag: RunningExperiment,
        recording: PathBuf,
        about: BTreeMap<String, String>,
        reset_sim: bool,
    ) -> Result<(), DeployError> {
        let recordings = self.recordings_service()?;
        let mut active = self.lock_active()?;
        let target = format!("set {} (experiment {})", tag.set, tag.id);
        let tag_id = tag.id;
        let prepared = (|| {
            if let Some(other) = self.experiments.running() {
                return Err(DeployError::Conflict(format!("experiment {} runs already", other.id)));
            }
            let set = self.store.set(tag.set)?;
            // With the sim's reset, its simulated robots start afresh (and
            // the serial links on them): nothing of the baseline's run,
            // not a pose the link heard before the reset, is in the run.
            let ready: Ready = self.build_beside_carrying(user, set, &active, reset_sim)?;
            if let Some(change) = stage::envelope_change(&active.config, &ready.config) {
                return Err(DeployError::Forbidden(format!(
                    "set {} {change}: an experiment runs with the robot's own envelope settings",
                    tag.set
                )));
            }
            Ok(ready)
        })();
        self.commit(
            LAB_USER,
            "experiment-start",
            &target,
            prepared,
            |writer, ready: Ready| {
                if let Some(current) = recordings.current() {
                    match recordings.stop() {
                        Ok(stopped) => writer.record(
                            LAB_USER,
                            "stop-recording",
                            "recordings",
                            Outcome::Ok(&format!(
                                "{} (started by {}) stopped: experiment {} starts",
                                stopped.name, current.by, tag.id
                            )),
                        ),
                        Err(e) => return Err(DeployError::from(e)),
                    }
                }
                let mut layout = Layout::of(&ready.config);
                layout.about = about;
                recordings.start_after_swap_to(&tag.submitter, layout, self.slot.swaps(), recording)?;
                let shown = ExperimentTag {
                    id: tag_id,
                    submitter: tag.submitter.clone(),
                    label: tag.label.clone(),
                    sha256: ready
                        .config
                        .components
                        .iter()
                        .filter_map(|c| match &c.source {
                            ComponentSource::Wasm(path) => {
                                Some((c.name.clone(), path.file_name()?.to_string_lossy().into_owned()))
                            }
                            ComponentSource::Builtin(_) => None,
                        })
                        .collect(),
                };
                let before = (active.set.clone(), active.config.clone());
                if let Err(e) = self.swap_in_reporting(ready, &mut active, None, Some(Arc::new(shown))) {
                    if let Err(abandoned) = recordings.abandon() {
                        tracing::error!("experiment {}'s recording was not removed: {abandoned}", tag.id);
                    }
                    return Err(e);
                }
                self.experiments.set_before(Some(before));
                self.experiments.set(Some(tag.clone()));
                tracing::info!("experiment {} by {} runs set {} on the robot", tag.id, tag.submitter, tag.set);
                Ok(())
            },
            |()| format!("experiment {} by {} from a fresh start, recording", tag.id, tag.submitter),
        )
    }

    /// Whether the active set has a simulated robot (the `sim` reset
    /// policy needs one).
    pub fn has_simulated_robot(&self) -> Result<bool, DeployError> {
        let (_, config) = self.active()?;
        Ok(simulated_robots(&config).next().is_some())
    }

    /// Ends the running experiment: its recording stops, the baseline (set
    /// `baseline`) is built beside it and swapped in, and the experiment
    /// graph's report, `stopped_by` and `ran_ns` long, is taken on the
    /// control thread at the swap. If the baseline cannot be built, the
    /// emergency stop is engaged first and the error returned.
    pub fn end_experiment(&self, id: u64, baseline: u64, stopped_by: &str, ran_ns: u64) -> Result<Ended, DeployError> {
        let mut active = self.lock_active()?;
        let recordings = self.recordings_service()?;
        let target = format!("set {baseline} (after experiment {id})");
        let prepared = self.build_baseline_or_stop(&active, baseline, &format!("experiment {id}"));
        self.commit(
            LAB_USER,
            "experiment-end",
            &target,
            prepared,
            |writer, ready: Ready| {
                let recording = match recordings.current() {
                    Some(_) => Some(recordings.stop()?),
                    None => None,
                };
                let (sender, receiver) = std::sync::mpsc::sync_channel(1);
                self.swap_in_reporting(ready, &mut active, Some((ran_ns, sender)), None)?;
                self.experiments.set(None);
                self.experiments.set_before(None);
                if writer.state()?.active != Some(baseline) {
                    writer.mark_active(baseline)?;
                }
                Ok(Ended { report: receiver.try_recv().ok(), recording })
            },
            |_| format!("experiment {id} {stopped_by}; the baseline (set {baseline}) runs"),
        )
    }

    /// The baseline (set `baseline`) built beside what runs after `what`
    /// (an experiment, a reset). If it cannot be built, the emergency stop
    /// is engaged first: the robot never goes on under what ran.
    pub(super) fn build_baseline_or_stop(
        &self,
        active: &super::Deployment,
        baseline: u64,
        what: &str,
    ) -> Result<Ready, DeployError> {
        let built = self.store.set(baseline).map_err(DeployError::from).and_then(|set| {
            if active.set.id == baseline
                && self.experiments.running().is_none()
                && self.experiments.resetting().is_none()
            {
                return Err(DeployError::Conflict(format!("the baseline (set {baseline}) runs already")));
            }
            self.build_beside(&lab_user(), set, active)
        });
        if let Err(e) = &built {
            self.engage_lab_stop(&format!("the baseline did not start after {what}"));
            tracing::error!(
                "{what} ended, but the baseline (set {baseline}) did not start: {e}; the emergency stop is engaged"
            );
        }
        built
    }

    /// Engages the lab's emergency stop for `why`.
    pub(super) fn engage_lab_stop(&self, why: &str) {
        if let Some(locks) = self.services.get::<Locks>() {
            locks.engage(LAB_LOCK, LAB_USER, why, unix_now_ms());
        }
    }

    /// Forgets the running experiment without a swap: the host is
    /// stopping (the graph stops with it).
    pub fn forget_experiment(&self) {
        self.experiments.set(None);
        self.experiments.set_before(None);
    }
}
