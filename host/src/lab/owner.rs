//! The owner's use cases (admins): the lab's settings, the baseline,
//! pausing and resuming the queue, and confirming a manual reset. Each is
//! one change of `lab.json` under the lab's lock, audited.

use super::{Lab, LabError, MAX_DURATION_CAP_S, MIN_DURATION_S};
use crate::contract::clip;
use crate::store::World;
use crate::store::experiments::{
    DriveReset, LabSettings, LabState, MAX_PREFLIGHT_RUNS, MAX_RESET_SETTLE_S, MAX_RESET_TIMEOUT_S, ResetPolicy,
};
use crate::store::task::{MAX_TASK_DESCRIPTION, MAX_TASK_NAME, Metric, Task};
use crate::store::users::{Principal, Role};

impl Lab {
    /// Changes the owner's settings (admins).
    pub fn set_settings(&self, user: &Principal, settings: LabSettings) -> Result<LabSettings, LabError> {
        let reset_set = self.check_reset_set(user, &settings);
        let scorer = settings.task.as_ref().map_or(Ok(()), |task| self.check_scorer(task));
        self.admin_change(user, "lab-settings", "lab", |lab| {
            check_settings(&settings)?;
            reset_set?;
            scorer?;
            lab.settings = settings.clone();
            Ok(format!(
                "max-duration {} s, {} queued and {} robot-minutes a day per user",
                settings.max_duration_s, settings.limits.max_queued, settings.limits.robot_minutes_per_day
            ))
        })
        .map(|lab| lab.settings)
    }

    /// With the `drive` reset policy: the reset set must be stored, run
    /// here (not on a lab server), validate, and keep the baseline's
    /// envelope (as an experiment's set must).
    fn check_reset_set(&self, user: &Principal, settings: &LabSettings) -> Result<(), LabError> {
        let Some(drive) = settings.drive_reset() else {
            return Ok(());
        };
        if self.fleet().is_some() {
            return Err(LabError::BadRequest(
                "reset: the lab server runs no robot: the drive reset is each robot's own lab setting".into(),
            ));
        }
        if user.role != Role::Admin {
            return Ok(());
        }
        let baseline = self.baseline(&self.lock()?.lab);
        self.deployer
            .check_experiment_set(user, drive.set, baseline)
            .map(|_| ())
            .map_err(|e| LabError::BadRequest(format!("drive_reset.set: {e}")))
    }

    /// A task scored by a component names a stored upload of the `scorer`
    /// world whose bytes are the sha256 it pins.
    fn check_scorer(&self, task: &Task) -> Result<(), LabError> {
        let Some(scorer) = &task.scorer else { return Ok(()) };
        let bad = |why: String| Err(LabError::BadRequest(format!("task.scorer: {why}")));
        let Some((owner, name)) = scorer.component.split_once('/') else {
            return bad(format!("component must name an upload as OWNER/NAME, got '{}'", clip(&scorer.component)));
        };
        let Some(record) = self.store().component(owner, name)? else {
            return bad(format!("no component '{}' in the store", clip(&scorer.component)));
        };
        if record.world != World::Scorer {
            return bad(format!(
                "'{}' is not a scoring component (it fits the {} world, not subsume:robot/scorer)",
                record.key(),
                record.world.name()
            ));
        }
        if record.sha256 != scorer.sha256 {
            return bad(format!(
                "'{}' is stored with sha256 {}, but the task pins {}: pin the bytes you mean",
                record.key(),
                record.sha256,
                crate::contract::clip_to(&scorer.sha256, 64)
            ));
        }
        Ok(())
    }

    /// Marks set `set` as the baseline (admins); it must validate.
    pub fn set_baseline(&self, user: &Principal, set: u64) -> Result<u64, LabError> {
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
    pub fn set_paused(&self, user: &Principal, paused: bool) -> Result<bool, LabError> {
        let action = if paused { "lab-pause" } else { "lab-resume" };
        self.admin_change(user, action, "queue", |lab| {
            lab.paused = paused;
            Ok(if paused { "the queue is paused".into() } else { "the queue runs".into() })
        })
        .map(|lab| lab.paused)
    }

    /// Confirms the robot was put back at its start for the experiment
    /// that waits for it (admins; the `manual` reset policy).
    pub fn confirm_reset(&self, user: &Principal) -> Result<u64, LabError> {
        let confirmed = || {
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
        };
        self.audited(&user.name, "lab-reset", "reset", confirmed, |id| format!("for experiment {id}"))
    }

    pub(super) fn admin_change(
        &self,
        user: &Principal,
        action: &str,
        target: &str,
        change: impl FnOnce(&mut LabState) -> Result<String, LabError>,
    ) -> Result<LabState, LabError> {
        let changed = || {
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
        };
        self.audited(&user.name, action, target, changed, |(_, detail)| detail.clone()).map(|(lab, _)| lab)
    }
}

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
    if let Some(duty) = settings.duty_cycle
        && !((1..=24 * 3600).contains(&duty.run_s) && (1..=24 * 3600).contains(&duty.rest_s))
    {
        return bad(format!(
            "duty_cycle.run_s and rest_s must be from 1 to 86400 (a day), got {} and {}",
            duty.run_s, duty.rest_s
        ));
    }
    if let Some(test) = settings.self_test {
        let window = crate::store::experiments::SELF_TEST_WINDOW_MS;
        if !window.contains(&test.window_ms) {
            return bad(format!(
                "self_test.window_ms must be from {} to {}, got {}",
                window.start(),
                window.end(),
                test.window_ms
            ));
        }
        if let Some(volts) = test.min_battery_v
            && !(volts.is_finite() && (0.0..=1000.0).contains(&volts))
        {
            return bad(format!("self_test.min_battery_v must be from 0 to 1000 volts, got {volts}"));
        }
        if let Some(ratio) = test.odometry_ratio
            && !(ratio.is_finite() && ratio > 0.0 && ratio <= 1.0)
        {
            return bad(format!("self_test.odometry_ratio must be above 0 and at most 1, got {ratio}"));
        }
        match (test.min_battery_v, test.resume_battery_v) {
            (_, None) => {}
            (Some(least), Some(resume)) if resume.is_finite() && resume > least && resume <= 1000.0 => {}
            (least, Some(resume)) => {
                return bad(format!(
                    "self_test.resume_battery_v must be above min_battery_v ({}) and at most 1000 volts, got {resume}",
                    least.map_or("none".to_string(), |v| v.to_string())
                ));
            }
        }
    }
    match (&settings.reset, &settings.drive_reset) {
        (ResetPolicy::Drive, None) => {
            return bad("reset: drive needs drive_reset (the reset set, the start pose and its tolerances)".into());
        }
        (_, Some(drive)) => check_drive_reset(drive)?,
        _ => {}
    }
    if let Some(task) = &settings.task {
        check_task(task)?;
    }
    let timing = &settings.preflight_timing;
    if !(1..=MAX_PREFLIGHT_RUNS).contains(&timing.runs) {
        return bad(format!("preflight_timing.runs must be from 1 to {MAX_PREFLIGHT_RUNS}, got {}", timing.runs));
    }
    if let Err(e) = timing.bounds().check() {
        return bad(format!("preflight_timing.{e}"));
    }
    if !(1..=7 * 24 * 3600).contains(&settings.stuck_after_min_s) {
        return bad(format!("stuck_after_min_s must be from 1 to 604800 (a week), got {}", settings.stuck_after_min_s));
    }
    Ok(())
}

fn check_drive_reset(drive: &DriveReset) -> Result<(), LabError> {
    let bad = |why: String| Err(LabError::BadRequest(format!("drive_reset.{why}")));
    let pose = drive.pose;
    if ![pose.x, pose.y, pose.heading].iter().all(|v| v.is_finite() && v.abs() <= 1e6) {
        return bad(format!("pose must be finite metres and radians, got ({}, {}, {})", pose.x, pose.y, pose.heading));
    }
    let tolerance = drive.tolerance;
    if !(tolerance.position_m.is_finite() && tolerance.position_m > 0.0 && tolerance.position_m <= 10.0) {
        return bad(format!("tolerance.position_m must be above 0 and at most 10 m, got {}", tolerance.position_m));
    }
    let pi = std::f64::consts::PI;
    if !(tolerance.heading_rad.is_finite() && tolerance.heading_rad > 0.0 && tolerance.heading_rad <= pi) {
        return bad(format!("tolerance.heading_rad must be above 0 and at most pi, got {}", tolerance.heading_rad));
    }
    if !(1..=MAX_RESET_TIMEOUT_S).contains(&drive.timeout_s) {
        return bad(format!("timeout_s must be from 1 to {MAX_RESET_TIMEOUT_S}, got {}", drive.timeout_s));
    }
    if !(drive.settle_s.is_finite() && (0.0..=MAX_RESET_SETTLE_S).contains(&drive.settle_s)) {
        return bad(format!("settle_s must be from 0 to {MAX_RESET_SETTLE_S}, got {}", drive.settle_s));
    }
    if let Some(link) = &drive.link
        && (link.is_empty() || link.len() > 64)
    {
        return bad(format!("link must name a serial link of the reset set, got '{}'", clip(link)));
    }
    Ok(())
}

fn check_task(task: &Task) -> Result<(), LabError> {
    let bad = |why: String| Err(LabError::BadRequest(format!("task.{why}")));
    let name_ok = |n: &str| {
        !n.is_empty()
            && n.len() <= MAX_TASK_NAME
            && n.bytes().all(|b| b.is_ascii_lowercase() || b.is_ascii_digit() || b == b'-')
    };
    if !name_ok(&task.name) {
        return bad(format!("name must be 1 to {MAX_TASK_NAME} of a-z, 0-9 and '-', got '{}'", clip(&task.name)));
    }
    if task.description.chars().count() > MAX_TASK_DESCRIPTION {
        return bad(format!("description is at most {MAX_TASK_DESCRIPTION} characters"));
    }
    let goal = task.goal;
    if ![goal.x, goal.y, goal.radius].iter().all(|v| v.is_finite() && v.abs() <= 1e6) || goal.radius <= 0.0 {
        return bad(format!(
            "goal must be finite metres with a positive radius, got ({}, {}, {})",
            goal.x, goal.y, goal.radius
        ));
    }
    if !(task.wheel_base_m.is_finite() && task.wheel_base_m > 0.0 && task.wheel_base_m <= 10.0) {
        return bad(format!("wheel_base_m must be above 0 and at most 10, got {}", task.wheel_base_m));
    }
    match (task.metric, &task.scorer) {
        (Metric::Scorer, None) => return bad("scorer must name the scoring component of the metric scorer".into()),
        (Metric::Scorer, Some(_)) | (_, None) => {}
        (metric, Some(_)) => {
            return bad(format!("scorer is only for the metric scorer, and the metric is {}", metric.name()));
        }
    }
    for (n, condition) in task.end_on.iter().enumerate() {
        if task.end_on[..n].contains(condition) {
            return bad(format!("end_on names {} twice", condition.name()));
        }
    }
    for (field, port) in [("pose", &task.pose), ("commands", &task.commands), ("ranges", &task.ranges)] {
        let shaped = port.split_once('.').is_some_and(|(c, p)| !c.is_empty() && !p.is_empty() && !p.contains('.'));
        if !shaped || port.len() > 128 || port.chars().any(|c| c.is_control() || c == '/') {
            return bad(format!("{field} must name an output port as COMPONENT.PORT, got '{}'", clip(port)));
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::store::experiments::PreflightTiming;

    /// (the preflight's timing, the start of the refusal, if any): each
    /// field out of its range is named.
    #[test]
    fn the_preflights_timing_is_checked_naming_the_field() {
        let with = |f: fn(&mut PreflightTiming)| {
            let mut timing = PreflightTiming::default();
            f(&mut timing);
            timing
        };
        let cases = [
            (PreflightTiming::default(), None),
            (with(|t| t.runs = 1), None),
            (with(|t| t.runs = MAX_PREFLIGHT_RUNS), None),
            (with(|t| t.runs = 0), Some("preflight_timing.runs must be from 1 to 10, got 0")),
            (with(|t| t.runs = 11), Some("preflight_timing.runs must be from 1 to 10, got 11")),
            (with(|t| t.sensor_latency_ms = -1.0), Some("preflight_timing.sensor_latency_ms must be from 0 to 1000")),
            (with(|t| t.range_noise_m = f64::NAN), Some("preflight_timing.range_noise_m must be from 0 to 1")),
            (with(|t| t.serial_delay_ms = 1001.0), Some("preflight_timing.serial_delay_ms must be from 0 to 1000")),
        ];
        for (timing, refused) in cases {
            let settings = LabSettings { preflight_timing: timing, ..LabSettings::default() };
            match (check_settings(&settings), refused) {
                (Ok(()), None) => {}
                (Err(LabError::BadRequest(why)), Some(start)) => assert!(why.starts_with(start), "{why}"),
                (other, _) => panic!("{timing:?}: {other:?}"),
            }
        }
    }
}
