//! A dispatched experiment on a robot (docs/lab.md, "How an experiment
//! runs"): the robot's side of its lab server's dispatch. It is taken only
//! when it is fresh, not withdrawn, and within this robot's limits; its
//! sources come from the lab server by hash; it is checked again here and
//! queued in this host's own lab as one of its own, and the answer waits
//! (up to [`super::robot_link::START_WAIT`]) for it to start.

use std::time::Duration;

use super::LabError;
use super::robot_link::{RobotLink, START_WAIT, lab_user, live_local_id, lock, withdrawn_before};
use super::transfer::{self, Asker, TransferError};
use super::wire::{self, Dispatch, DispatchOutcome, FileSource, RobotState, SetManifest};
use crate::runtime::locks::unix_now_ms;
use crate::store::experiments::{
    AppliedSettings, ComponentHash, ExperimentRecord, ExperimentState, NewExperiment, Origin,
};
use crate::store::users::Principal;
use crate::store::{Outcome, SetRecord};

impl RobotLink {
    /// Takes the lab's experiment, checks it again, runs it through this
    /// host's lab, and says how it went (or why not).
    pub(super) fn dispatch(&self, dispatch: &Dispatch) -> DispatchOutcome {
        let target = format!("lab experiment {}", dispatch.lab_id);
        // Admitted (signed, for this robot, fresh, new): the lab is heard.
        self.heard_lab();
        let outcome = self.take(dispatch).and_then(|id| self.wait_start(id, dispatch.start_by_unix_ms));
        let outcome = match outcome {
            Ok(outcome) => outcome,
            Err(reasons) => DispatchOutcome::Refused { reasons },
        };
        let (text, result) = match &outcome {
            DispatchOutcome::Started { local_id, .. } => (format!("runs as experiment {local_id}"), true),
            DispatchOutcome::Refused { reasons } => (reasons.join("; "), false),
        };
        let outcome_line = if result { Outcome::Ok(&text) } else { Outcome::Refused(&text) };
        self.lab.deployer.audit(&lab_user(&self.options, &dispatch.submitter), "lab-dispatch", &target, outcome_line);
        outcome
    }

    /// Checks and queues `dispatch` here: the local experiment's id.
    pub(super) fn take(&self, dispatch: &Dispatch) -> Result<u64, Vec<String>> {
        let lab_name = self.options.key.lab().to_string();
        if let Some(id) = self.lab.lock().ok().and_then(|b| live_local_id(&b.experiments, &lab_name, dispatch.lab_id)) {
            return Ok(id);
        }
        if withdrawn_before(&lock(&self.withdrawn), dispatch.lab_id, dispatch.to.issued_unix_ms) {
            return Err(vec!["its lab withdrew this dispatch of it before it came here".into()]);
        }
        late(dispatch.start_by_unix_ms, unix_now_ms()).map_err(|why| vec![why])?;
        self.busy(dispatch.duration_s).map_err(|why| vec![why])?;
        let baseline_dir = lock(&self.package)
            .as_ref()
            .and_then(|p| self.lab.store().set(p.set).ok())
            .map(|s| s.base_dir)
            .ok_or_else(|| vec!["the robot has no baseline".to_string()])?;
        self.fetch_sources(&dispatch.set).map_err(|e| vec![format!("the set's files did not come: {e}")])?;
        let by = lab_user(&self.options, &dispatch.submitter);
        let set = self.lab.import_manifest(&dispatch.set, &by, &baseline_dir).map_err(|e| check_reasons(e.into()))?;
        let user =
            Principal { name: dispatch.submitter.clone(), role: dispatch.role, platforms: dispatch.platforms.clone() };
        let (baseline, settings) = {
            let book = self.lab.lock().map_err(|e| vec![e.to_string()])?;
            (self.lab.baseline(&book.lab), book.lab.settings.clone())
        };
        let checked =
            self.lab.deployer.check_experiment_set(&user, set.id, baseline).map_err(|e| check_reasons(e.into()))?;
        self.queue(dispatch, &set, baseline, settings, checked.components)
    }

    /// Why this robot cannot take an experiment of `duration_s` now.
    pub(super) fn busy(&self, duration_s: f64) -> Result<(), String> {
        let (state, _) = self.state();
        match state {
            RobotState::Idle => {}
            RobotState::Running { experiment } => {
                return Err(format!("busy: it runs the lab's experiment {experiment}"));
            }
            RobotState::Stopped { by } => return Err(format!("its emergency stop is engaged (by {by})")),
            RobotState::Maintenance => {
                return Err("it is in maintenance: its owner paused its queue or took it out of service".into());
            }
        }
        let book = self.lab.lock().map_err(|e| e.to_string())?;
        let other = book
            .running
            .as_ref()
            .map(|r| r.id)
            .or(book.starting)
            .or_else(|| book.experiments.values().find(|r| r.state.is_waiting()).map(|r| r.id));
        if let Some(other) = other.and_then(|id| book.experiments.get(&id)) {
            return Err(format!("busy: its experiment {} is {}", other.id, other.state.name()));
        }
        let max = book.lab.settings.max_duration_s;
        if duration_s > max {
            return Err(format!("its duration of {duration_s} s is over this robot's max-duration of {max} s"));
        }
        Ok(())
    }

    /// Fetches the blobs of `set` this robot does not hold yet from the
    /// lab server, each checked by its sha256.
    pub(super) fn fetch_sources(&self, set: &SetManifest) -> Result<(), TransferError> {
        let store = self.lab.store();
        for blob in set.sources.values() {
            if store.blob_path(&blob.sha256).is_file() {
                continue;
            }
            let source = FileSource::Blob { sha256: blob.sha256.clone() };
            let asker = Asker { shared: &self.shared, key: &self.options.key, skipped: &self.skipped };
            let at = (self.keys.blobs(), wire::SERVER_TARGET);
            let bytes = transfer::fetch_blob(asker, (&at.0, at.1), &source, blob)?;
            let writer = store.lock().map_err(|e| TransferError::Missing(e.to_string()))?;
            writer.put_blob(&bytes).map_err(|e| TransferError::Missing(e.to_string()))?;
        }
        Ok(())
    }

    /// Queues the checked experiment in this host's lab, as the lab's.
    pub(super) fn queue(
        &self,
        dispatch: &Dispatch,
        set: &SetRecord,
        baseline: u64,
        settings: crate::store::experiments::LabSettings,
        components: Vec<(String, String, Option<String>)>,
    ) -> Result<u64, Vec<String>> {
        // Checked again after the checks: nothing else came in meanwhile
        // (this thread is the only one that queues here).
        self.busy(dispatch.duration_s).map_err(|why| vec![why])?;
        let mut book = self.lab.lock().map_err(|e| vec![e.to_string()])?;
        let now = unix_now_ms();
        let new = NewExperiment {
            submitter: dispatch.submitter.clone(),
            set: set.id,
            label: dispatch.label.clone(),
            duration_s: dispatch.duration_s,
            submitted_ms: now,
            settings: AppliedSettings::of(&settings, baseline),
            components: components
                .into_iter()
                .map(|(name, source, sha256)| ComponentHash { name, source, sha256 })
                .collect(),
        };
        let cause = format!(
            "dispatched by lab '{}' as its experiment {} (its preflight ran there); checked again here",
            self.options.key.lab(),
            dispatch.lab_id
        );
        let mut record = ExperimentRecord::new(new, ExperimentState::Queued, &cause);
        record.origin = Some(Origin {
            lab: self.options.key.lab().to_string(),
            id: dispatch.lab_id,
            role: dispatch.role,
            platforms: dispatch.platforms.clone(),
            start_by_unix_ms: dispatch.start_by_unix_ms,
        });
        let stored = self.lab.store().lock().and_then(|writer| writer.add_experiment(&mut book.lab, record));
        let record = stored.map_err(|e| vec![format!("failed: {e}")])?;
        let id = record.id;
        book.experiments.insert(id, record);
        drop(book);
        tracing::info!("lab experiment {} by {} queued here as experiment {id}", dispatch.lab_id, dispatch.submitter);
        self.lab.notify();
        Ok(id)
    }

    /// Waits (at most [`START_WAIT`], and never past the lab's start-by
    /// time) for local experiment `id` to run. One that has not started
    /// by then is cancelled here: the lab gets a refusal, or nothing, and
    /// it must never start later behind the lab's back.
    pub(super) fn wait_start(&self, id: u64, start_by_unix_ms: Option<u64>) -> Result<DispatchOutcome, Vec<String>> {
        let wait = match start_by_unix_ms {
            Some(start_by) => START_WAIT.min(Duration::from_millis(start_by.saturating_sub(unix_now_ms()))),
            None => START_WAIT,
        };
        let book = self.lab.lock().map_err(|e| vec![e.to_string()])?;
        let (mut book, _) = self
            .lab
            .changed
            .wait_timeout_while(book, wait, |b| {
                b.running.as_ref().is_none_or(|r| r.id != id)
                    && b.experiments.get(&id).is_some_and(|r| !r.state.is_final())
            })
            .map_err(|_| vec!["the lab's state is unusable".to_string()])?;
        if let Some(running) = book.running.as_ref().filter(|r| r.id == id) {
            return Ok(DispatchOutcome::Started {
                local_id: id,
                started_unix_ms: running.started_unix_ms,
                ends_unix_ms: running.ends_unix_ms,
            });
        }
        match book.experiments.get(&id) {
            Some(record) if record.state.is_final() => {
                let mut reasons = record.reasons.clone();
                if reasons.is_empty() {
                    reasons.push(format!("it ended here as {}", record.state.name()));
                }
                Err(reasons)
            }
            Some(record) if record.state == ExperimentState::Queued && book.starting != Some(id) => {
                let why = format!("it did not start here within {:.1} s", wait.as_secs_f64());
                let cause = format!("cancelled: {why}, and its lab stops waiting for it");
                if let Err(e) =
                    self.lab.transition(&mut book, id, ExperimentState::Cancelled, &cause, vec![cause.clone()])
                {
                    return Err(vec![why, e.to_string()]);
                }
                Err(vec![why])
            }
            // Starting this instant: the lab learns it from the token.
            _ => Err(vec![format!("it did not start here within {:.1} s", wait.as_secs_f64())]),
        }
    }
}

/// Why a dispatch that must start by `start_by_unix_ms` is not taken at
/// `now_ms` (it came after its lab stopped waiting).
fn late(start_by_unix_ms: Option<u64>, now_ms: u64) -> Result<(), String> {
    match start_by_unix_ms {
        Some(start_by) if now_ms >= start_by => Err(format!(
            "it came {:.1} s after its lab stopped waiting for the answer",
            (now_ms - start_by) as f64 / 1000.0
        )),
        _ => Ok(()),
    }
}

/// A check's refusal as the reasons a dispatch answer carries.
fn check_reasons(e: LabError) -> Vec<String> {
    match e {
        LabError::Invalid(diagnostics) => diagnostics.0.iter().map(|d| format!("check: {d}")).collect(),
        other => vec![format!("check: {other}")],
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_dispatch_is_late_from_its_start_by_time_on() {
        // (start-by, now, late)
        let cases =
            [(None, 5_000, false), (Some(5_000), 4_999, false), (Some(5_000), 5_000, true), (Some(5_000), 9_000, true)];
        for (start_by, now, expected) in cases {
            let said = late(start_by, now);
            assert_eq!(said.is_err(), expected, "{start_by:?} at {now}: {said:?}");
        }
        assert_eq!(late(Some(5_000), 6_500).unwrap_err(), "it came 1.5 s after its lab stopped waiting for the answer");
    }
}
