//! The reset by driving (docs/lab.md, "Reset by driving"): before each
//! experiment, with the owner's `drive` reset policy, the owner's reset
//! set runs until the robot's pose (its serial link's odometry) is within
//! the tolerance of the start pose and stays there, at rest, for the
//! settle time; or until the timeout. Its outcome goes on the experiment's
//! record; a reset that fails takes the robot out of service
//! (`by: "reset"`), and the experiment waits in the queue.
//!
//! [`ResetProgress`] is the pure decision over time and poses (tested with
//! controlled time); [`Lab::drive_reset`] runs it against the live status.

use std::time::{Duration, Instant};

use super::{Book, LAB_AUDIT_USER, Lab};
use crate::notify::EventKind;
use crate::report::Report;
use crate::robot::serial::SerialStatus;
use crate::runtime::Locks;
use crate::store::Outcome;
use crate::store::experiments::{DriveReset, MAX_MAINTENANCE_REASON, Maintenance, Pose, PoseTolerance, ResetOutcome};
use crate::walltime::unix_now_ms;

/// The name a failed reset that takes the robot out of service goes by.
pub const RESET_USER: &str = "reset";

/// How often the reset looks at the robot's pose.
const LOOK: Duration = Duration::from_millis(50);

/// Whether `pose` is within `tolerance` of `target` (the heading's error
/// taken the short way round).
pub fn at_pose(pose: Pose, target: Pose, tolerance: PoseTolerance) -> bool {
    let distance = (pose.x - target.x).hypot(pose.y - target.y);
    distance <= tolerance.position_m && heading_error(pose.heading, target.heading).abs() <= tolerance.heading_rad
}

/// `heading - target` in (-pi, pi].
fn heading_error(heading: f64, target: f64) -> f64 {
    let tau = std::f64::consts::TAU;
    let error = (heading - target).rem_euclid(tau);
    if error > std::f64::consts::PI { error - tau } else { error }
}

/// The robot's pose in `report`: the odometry of serial link `link`, or of
/// the first link (by name) that reports one.
pub fn pose_in(report: &Report, link: Option<&str>) -> Option<Pose> {
    let mut links: Vec<(&str, &SerialStatus)> = report.sections.of::<SerialStatus>().collect();
    links.sort_by(|a, b| a.0.cmp(b.0));
    links
        .into_iter()
        .filter(|(name, _)| link.is_none_or(|wanted| wanted == *name))
        .find_map(|(_, status)| status.pose)
        .map(|[x, y, heading]| Pose { x, y, heading })
}

/// What the reset does next.
#[derive(Clone, Debug, PartialEq)]
pub enum Step {
    /// Go on driving (or settling).
    Drive,
    /// At the start pose, and still after the settle time.
    Passed,
    /// Not at the start pose in time: why.
    Failed(String),
}

/// A reset's progress over time (ms since it began).
#[derive(Clone, Debug)]
pub struct ResetProgress {
    settings: DriveReset,
    /// Since when the robot is at the pose (ms), if it is.
    settling_since_ms: Option<u64>,
    /// The pose when it began, and the last seen.
    pub from: Option<Pose>,
    pub last: Option<Pose>,
}

impl ResetProgress {
    pub fn new(settings: &DriveReset) -> ResetProgress {
        ResetProgress { settings: settings.clone(), settling_since_ms: None, from: None, last: None }
    }

    /// The decision at `now_ms` (since the reset began) with the robot at
    /// `pose` (`None`: no pose reported yet). The timeout bounds the
    /// driving; a settle begun before it runs to its end.
    pub fn step(&mut self, now_ms: u64, pose: Option<Pose>) -> Step {
        if self.from.is_none() {
            self.from = pose;
        }
        if pose.is_some() {
            self.last = pose;
        }
        let settings = &self.settings;
        let at = pose.is_some_and(|p| at_pose(p, settings.pose, settings.tolerance));
        let settle_ms = (settings.settle_s * 1000.0).round() as u64;
        if at {
            let since = *self.settling_since_ms.get_or_insert(now_ms);
            if now_ms.saturating_sub(since) >= settle_ms {
                return Step::Passed;
            }
            return Step::Drive;
        }
        let left_while_settling = self.settling_since_ms.take().is_some();
        if now_ms >= settings.timeout_s * 1000 {
            let target = settings.pose;
            let tolerance = settings.tolerance;
            let start = format!(
                "the start pose ({:.2}, {:.2}, {:.2} rad) within {:.2} m and {:.2} rad",
                target.x, target.y, target.heading, tolerance.position_m, tolerance.heading_rad
            );
            let why = match self.last {
                None => format!("no serial link reported the robot's pose in {} s", settings.timeout_s),
                Some(p) if left_while_settling => format!(
                    "the robot left {start} while it settled, at ({:.2}, {:.2}, {:.2} rad) after {} s",
                    p.x, p.y, p.heading, settings.timeout_s
                ),
                Some(p) => format!(
                    "the robot is at ({:.2}, {:.2}, {:.2} rad) after {} s, not at {start}",
                    p.x, p.y, p.heading, settings.timeout_s
                ),
            };
            return Step::Failed(why);
        }
        Step::Drive
    }
}

impl Lab {
    /// Drives the robot back to the owner's start pose before experiment
    /// `before` (the baseline, set `baseline`, runs now and again after):
    /// the reset set is swapped in, the live status watched, the baseline
    /// swapped back. Holds no lock of the lab's; takes at most the timeout
    /// plus the settle time, and the two swaps.
    pub(super) fn drive_reset(&self, before: u64, baseline: u64, settings: &DriveReset) -> ResetOutcome {
        let at_ms = unix_now_ms();
        let began = Instant::now();
        let mut progress = ResetProgress::new(settings);
        let failed = |error: String, progress: &ResetProgress| ResetOutcome {
            at_ms,
            passed: false,
            took_s: began.elapsed().as_secs_f64(),
            from: progress.from,
            pose: progress.last,
            error: Some(error),
        };
        let mut live = self.deployer.live().subscribe();
        if let Err(e) = self.deployer.start_reset(settings.set, before) {
            return failed(format!("the reset set {} did not start: {e}", settings.set), &progress);
        }
        let locks = self.deployer.services.get::<Locks>();
        let driven = loop {
            if self.is_stopping() {
                break Err("the host is stopping".to_string());
            }
            if let Some(lock) = locks.as_ref().and_then(|l| l.engaged().into_iter().next()) {
                break Err(format!("the emergency stop was engaged (by {}: {})", lock.by, lock.how));
            }
            let status = live.borrow_and_update().clone();
            let pose = status
                .as_ref()
                .as_ref()
                .filter(|s| s.set == settings.set && s.experiment.is_none())
                .and_then(|s| pose_in(&s.report, settings.link.as_deref()));
            match progress.step(began.elapsed().as_millis() as u64, pose) {
                Step::Drive => std::thread::sleep(LOOK),
                Step::Passed => break Ok(()),
                Step::Failed(why) => break Err(why),
            }
        };
        let took_s = began.elapsed().as_secs_f64();
        let ended = match &driven {
            Ok(()) => "passed".to_string(),
            Err(why) => format!("failed: {why}"),
        };
        let back = self.deployer.end_reset(baseline, &ended);
        let error = match (driven, back) {
            (Ok(()), Ok(())) => None,
            (driven, back) => {
                let mut why: Vec<String> = driven.err().into_iter().collect();
                if let Err(e) = back {
                    why.push(format!("the baseline did not come back ({e}); the emergency stop is engaged"));
                }
                Some(why.join("; "))
            }
        };
        ResetOutcome { at_ms, passed: error.is_none(), took_s, from: progress.from, pose: progress.last, error }
    }

    /// Keeps a failed reset's consequence: the robot out of service (unless
    /// it is already, or an emergency stop ended the reset: the stop holds
    /// the queue itself), audited and told to the owner.
    pub(super) fn keep_failed_reset(&self, book: &mut Book, before: u64, outcome: &ResetOutcome) {
        let error = outcome.error.as_deref().unwrap_or("no reason given");
        let reason = crate::contract::clip_to(
            &format!("the reset before experiment {before} failed: {error}"),
            MAX_MAINTENANCE_REASON,
        );
        self.audit(LAB_AUDIT_USER, "reset", &format!("before experiment {before}"), Outcome::Failed(&reason));
        let stopped = self.deployer.services.get::<Locks>().is_some_and(|l| l.any_engaged());
        if stopped || book.lab.maintenance.is_some() {
            return;
        }
        let mut lab = book.lab.clone();
        lab.maintenance = Some(Maintenance {
            reason: reason.clone(),
            by: RESET_USER.into(),
            since_ms: unix_now_ms(),
            ends_at_battery_v: None,
        });
        if let Err(e) = self.store().lock().and_then(|writer| writer.put_lab_state(&lab)) {
            // The robot still must not take work: kept in memory.
            tracing::error!("the failed reset's maintenance was not stored: {e}");
        }
        book.lab = lab;
        tracing::warn!("out of service: {reason}");
        self.tell_robot(EventKind::RobotMaintenanceStarted, &format!("{reason} (by {RESET_USER})"));
        self.notify();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn settings() -> DriveReset {
        DriveReset {
            set: 3,
            pose: Pose { x: 1.0, y: 1.0, heading: 0.0 },
            tolerance: PoseTolerance { position_m: 0.2, heading_rad: 0.3 },
            timeout_s: 10,
            settle_s: 1.0,
            link: None,
        }
    }

    fn pose(x: f64, y: f64, heading: f64) -> Option<Pose> {
        Some(Pose { x, y, heading })
    }

    #[test]
    fn a_pose_is_at_the_start_within_both_tolerances_the_heading_the_short_way_round() {
        let target = Pose { x: 1.0, y: 1.0, heading: 3.1 };
        let tolerance = PoseTolerance { position_m: 0.2, heading_rad: 0.3 };
        let cases = [
            ("exactly", 1.0, 1.0, 3.1, true),
            ("0.19 m off", 1.19, 1.0, 3.1, true),
            ("0.21 m off", 1.0, 1.21, 3.1, false),
            ("0.2 rad off across pi", 1.0, 1.0, -3.0833, true),
            ("0.4 rad off across pi", 1.0, 1.0, -2.88, false),
            ("a whole turn more", 1.0, 1.0, 3.1 + std::f64::consts::TAU, true),
            ("facing away", 1.0, 1.0, 0.0, false),
        ];
        for (case, x, y, heading, expected) in cases {
            assert_eq!(at_pose(Pose { x, y, heading }, target, tolerance), expected, "{case}");
        }
    }

    /// (ms since the reset began, pose, what the reset does then), in order.
    type Script = &'static [(u64, Option<(f64, f64, f64)>, &'static str)];

    #[test]
    fn a_reset_passes_once_the_pose_held_for_the_settle_time_and_fails_at_its_timeout() {
        let scripts: &[(&str, Script)] = &[
            (
                "arrives and settles",
                &[
                    (0, Some((5.0, 1.0, 3.1)), "drive"),
                    (4000, Some((1.1, 1.0, 0.1)), "drive"),
                    (4999, Some((1.0, 1.0, 0.0)), "drive"),
                    (5000, Some((1.0, 1.0, 0.0)), "passed"),
                ],
            ),
            (
                "leaves during the settle: the settle starts again",
                &[
                    (0, Some((1.0, 1.0, 0.0)), "drive"),
                    (900, Some((1.5, 1.0, 0.0)), "drive"),
                    (1000, Some((1.0, 1.0, 0.0)), "drive"),
                    (1999, Some((1.0, 1.0, 0.0)), "drive"),
                    (2000, Some((1.0, 1.0, 0.0)), "passed"),
                ],
            ),
            (
                "never there",
                &[
                    (0, Some((5.0, 1.0, 0.0)), "drive"),
                    (9999, Some((3.0, 1.0, 0.0)), "drive"),
                    (10_000, Some((2.0, 1.0, 0.0)), "failed: the robot is at (2.00, 1.00"),
                ],
            ),
            ("no pose at all", &[(0, None, "drive"), (10_000, None, "failed: no serial link reported")]),
            (
                "a settle begun before the timeout runs to its end",
                &[
                    (0, Some((5.0, 1.0, 0.0)), "drive"),
                    (9500, Some((1.0, 1.0, 0.0)), "drive"),
                    (10_200, Some((1.0, 1.0, 0.0)), "drive"),
                    (10_500, Some((1.0, 1.0, 0.0)), "passed"),
                ],
            ),
            (
                "leaving while settling past the timeout fails",
                &[
                    (0, Some((5.0, 1.0, 0.0)), "drive"),
                    (9500, Some((1.0, 1.0, 0.0)), "drive"),
                    (10_200, Some((1.5, 1.0, 0.0)), "failed: the robot left the start pose"),
                ],
            ),
        ];
        for (case, script) in scripts {
            let mut progress = ResetProgress::new(&settings());
            for (at, p, expected) in *script {
                let step = progress.step(*at, p.and_then(|(x, y, h)| pose(x, y, h)));
                let shown = match &step {
                    Step::Drive => "drive".to_string(),
                    Step::Passed => "passed".to_string(),
                    Step::Failed(why) => format!("failed: {why}"),
                };
                assert!(shown.starts_with(expected), "{case} at {at} ms: {shown}");
            }
        }
    }

    #[test]
    fn the_first_pose_seen_is_where_the_reset_began() {
        let mut progress = ResetProgress::new(&settings());
        progress.step(0, None);
        progress.step(50, pose(4.0, 2.0, 1.0));
        progress.step(100, pose(3.0, 2.0, 1.0));
        assert_eq!(progress.from, pose(4.0, 2.0, 1.0));
        assert_eq!(progress.last, pose(3.0, 2.0, 1.0));
    }
}
