//! The lab's reset by driving, on the deploy side (docs/lab.md, "Reset by
//! driving"): the owner's reset set is swapped in between experiments
//! (built beside what runs, checked to keep the robot's envelope, no
//! recording, no experiment tag), and the baseline swapped back after it.
//!
//! Invariants: while a reset runs, [`ExperimentGate`](super::ExperimentGate)
//! refuses every activation, admins' too (the lab swaps the baseline back
//! itself); the reset set is never recorded as the active set in
//! `state.json`, so a host that stops during a reset starts again on the
//! baseline; if the baseline cannot be built after a reset, the emergency
//! stop is engaged before anything else, as after an experiment.

use super::activate::Ready;
use super::experiment::{LAB_USER, lab_user};
use super::{DeployError, Deployer, stage};

impl Deployer {
    /// Swaps the owner's reset set `set` in before experiment `before`:
    /// checked against what runs (the baseline: same envelope), built
    /// beside it, unchanged built-ins (the motors' link, a simulated
    /// robot) carried over. Activations are refused until
    /// [`Deployer::end_reset`].
    pub fn start_reset(&self, set: u64, before: u64) -> Result<(), DeployError> {
        let mut active = self.lock_active()?;
        let target = format!("set {set} (the reset before experiment {before})");
        let prepared = (|| {
            if let Some(other) = self.experiments.running() {
                return Err(DeployError::Conflict(format!("experiment {} runs", other.id)));
            }
            let record = self.store.set(set)?;
            let ready: Ready = self.build_beside(&lab_user(), record, &active)?;
            if let Some(change) = stage::envelope_change(&active.config, &ready.config) {
                return Err(DeployError::Forbidden(format!(
                    "the reset set {set} {change}: a reset runs with the robot's own envelope settings"
                )));
            }
            Ok(ready)
        })();
        self.commit(
            LAB_USER,
            "reset-start",
            &target,
            prepared,
            |_, ready: Ready| {
                // Robot files staged meanwhile are staged against the
                // baseline, never the reset set.
                let baseline = (active.set.clone(), active.config.clone());
                self.swap_in_reporting(ready, &mut active, None, None)?;
                self.experiments.set_before(Some(baseline));
                self.experiments.set_resetting(Some(before));
                tracing::info!("the reset set {set} drives the robot back before experiment {before}");
                Ok(())
            },
            |()| format!("the robot is driven back to its start before experiment {before}"),
        )
    }

    /// Swaps the baseline (set `baseline`) back in after a reset that
    /// `ended` (for the audit line). If it does not come back, the
    /// emergency stop is engaged and the error returned.
    pub fn end_reset(&self, baseline: u64, ended: &str) -> Result<(), DeployError> {
        let mut active = self.lock_active()?;
        let target = format!("set {baseline} (after the reset)");
        let prepared = self.build_baseline_or_stop(&active, baseline, "a reset");
        let done = self.commit(
            LAB_USER,
            "reset-end",
            &target,
            prepared,
            |writer, ready: Ready| {
                self.swap_in_reporting(ready, &mut active, None, None)?;
                if writer.state()?.active != Some(baseline) {
                    writer.mark_active(baseline)?;
                }
                Ok(())
            },
            |()| format!("the reset {ended}; the baseline (set {baseline}) runs"),
        );
        if let Err(e) = &done {
            // The reset set may still drive: nothing must go on under it.
            self.engage_lab_stop(&format!("the baseline did not come back after a reset: {e}"));
        }
        self.experiments.set_resetting(None);
        self.experiments.set_before(None);
        done
    }
}
