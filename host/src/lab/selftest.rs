//! The self-test after every run (docs/lab.md, "Self-test"): once an
//! experiment has ended and the baseline is back, the robot is watched for
//! the owner's window, and checked: every serial link connected and giving
//! feedback, no component of the baseline faulted, no motor controller
//! reporting a fault where its protocol has a fault status, the battery
//! above the owner's threshold where a link reports one. The result goes into the
//! experiment's bundle (`selftest.json`) and the lab's history (the newest
//! [`MAX_SELF_TESTS`]); a failed one takes the robot out of service.
//!
//! [`judge`] is the pure decision over two live reports, a window apart;
//! [`Lab::self_test`] takes them from the running baseline.

use std::time::{Duration, Instant};

use super::{Book, LAB_AUDIT_USER, Lab, LabError};
use crate::notify::EventKind;
use crate::report::{ComponentRunState, Report};
use crate::robot::serial::SerialStatus;
use crate::store::Outcome;
use crate::store::experiments::{
    MAX_SELF_TESTS, MIN_JUDGED_MOTION_M, Maintenance, SelfTest, SelfTestCheck, SelfTestSettings,
};
use crate::walltime::unix_now_ms;

/// The name a self-test that takes the robot out of service goes by.
pub const SELF_TEST_USER: &str = "self-test";

/// How long the self-test waits for the running baseline's live status
/// (published every control cycle while watched): longer means the loop
/// is not running.
pub const LIVE_WAIT: Duration = Duration::from_secs(3);

/// The file of an experiment's bundle that holds the self-test after it.
pub const SELF_TEST_FILE: &str = "selftest.json";

/// The checks of `settings` over the robot's live reports `before` and
/// `after`, taken `window_s` apart.
pub fn judge(before: &Report, after: &Report, window_s: f64, settings: &SelfTestSettings) -> Vec<SelfTestCheck> {
    let check = |name: &str, failures: Vec<String>, passed: String| SelfTestCheck {
        check: name.to_string(),
        passed: failures.is_empty(),
        detail: if failures.is_empty() { passed } else { failures.join("; ") },
    };
    let faulted: Vec<String> = after
        .components
        .iter()
        .filter(|c| c.state == ComponentRunState::Faulted)
        .map(|c| format!("component '{}' faulted: {}", c.name, c.fault.as_deref().unwrap_or("no reason given")))
        .collect();
    let running = after.components.len();
    let mut checks = vec![check("components", faulted, format!("{running} components running, none faulted"))];
    let links: Vec<(&str, &SerialStatus)> = after.sections.of::<SerialStatus>().collect();
    let mut silent = Vec::new();
    let mut heard = Vec::new();
    for (name, link) in &links {
        let earlier = before.sections.of::<SerialStatus>().find(|(n, _)| n == name).map(|(_, s)| s.feedback_messages);
        let messages = link.feedback_messages.saturating_sub(earlier.unwrap_or(link.feedback_messages));
        if !link.connected {
            silent.push(format!("link '{name}' is not connected to {}", link.device));
        } else if messages == 0 {
            silent.push(format!("link '{name}' ({}) gave no feedback in {window_s:.1} s", link.device));
        } else {
            heard.push(format!("link '{name}': {messages} feedback messages in {window_s:.1} s"));
        }
    }
    let fresh = if links.is_empty() { "no serial link in the baseline".to_string() } else { heard.join("; ") };
    checks.push(check("feedback", silent, fresh));
    if settings.controller_faults {
        let reporting: Vec<&(&str, &SerialStatus)> = links.iter().filter(|(_, s)| s.fault_readings > 0).collect();
        let faults: Vec<String> = reporting
            .iter()
            .filter_map(|(n, s)| s.fault.as_ref().map(|f| format!("link '{n}': the motor controller reports {f}")))
            .collect();
        let fine = if reporting.is_empty() {
            "no link reports its controller's faults".to_string()
        } else {
            reporting.iter().map(|(n, _)| format!("link '{n}': no fault")).collect::<Vec<_>>().join("; ")
        };
        checks.push(check("controller", faults, fine));
    }
    if let Some(least) = settings.min_battery_v {
        let readings: Vec<(&str, f64)> = links.iter().filter_map(|(n, s)| s.battery_v.map(|v| (*n, v))).collect();
        let low: Vec<String> = readings
            .iter()
            .filter(|(_, v)| *v < least)
            .map(|(n, v)| format!("link '{n}': battery {v:.2} V is under {least:.2} V"))
            .collect();
        let fine = if readings.is_empty() {
            "no link reports a battery".to_string()
        } else {
            readings.iter().map(|(n, v)| format!("link '{n}': battery {v:.2} V")).collect::<Vec<_>>().join("; ")
        };
        checks.push(check("battery", low, fine));
    }
    if let Some(ratio) = settings.odometry_ratio {
        let (failures, fine) = judge_motion(before, &links, window_s, ratio);
        checks.push(check("motion", failures, fine));
    }
    checks
}

/// The motion check: each link's odometry over the window against the
/// distance its commands asked for (failures, and the passed detail).
fn judge_motion(before: &Report, links: &[(&str, &SerialStatus)], window_s: f64, ratio: f64) -> (Vec<String>, String) {
    let mut failures = Vec::new();
    let mut fine = Vec::new();
    for (name, link) in links {
        let Some((_, earlier)) = before.sections.of::<SerialStatus>().find(|(n, _)| n == name) else { continue };
        if link.pose.is_none() {
            fine.push(format!("link '{name}' reports no odometry"));
            continue;
        }
        let commanded = link.commanded_m - earlier.commanded_m;
        let travelled = link.odometry_m - earlier.odometry_m;
        let said = format!(
            "link '{name}': {commanded:.2} m commanded, the odometry shows {travelled:.2} m in {window_s:.1} s"
        );
        if commanded < MIN_JUDGED_MOTION_M {
            fine.push(format!("{said}: too little motion to judge (at least {MIN_JUDGED_MOTION_M} m)"));
        } else if travelled < ratio * commanded || travelled > commanded / ratio {
            failures.push(format!("{said}, outside {ratio:.2} to {:.2} of it", 1.0 / ratio));
        } else {
            fine.push(said);
        }
    }
    let fine = if fine.is_empty() { "no serial link in the baseline".to_string() } else { fine.join("; ") };
    (failures, fine)
}

impl Lab {
    /// Runs the owner's self-test on the running baseline now (after
    /// experiment `experiment`, if any): two live reports `window_ms`
    /// apart, judged. Takes at least the window; holds no lock.
    pub(super) fn self_test(&self, experiment: Option<u64>, settings: &SelfTestSettings) -> SelfTest {
        let window = Duration::from_millis(settings.window_ms);
        let mut live = self.deployer.live().subscribe();
        let mut next_report = || {
            live.borrow_and_update();
            let deadline = Instant::now() + LIVE_WAIT;
            loop {
                if live.has_changed().unwrap_or(false) {
                    let status = live.borrow_and_update().clone();
                    if let Some(status) = status.as_ref().as_ref().filter(|s| s.experiment.is_none()) {
                        return Some(status.report.clone());
                    }
                }
                if Instant::now() >= deadline {
                    return None;
                }
                std::thread::sleep(Duration::from_millis(10));
            }
        };
        let before = next_report();
        std::thread::sleep(window);
        let after = next_report();
        let checks = match (before, after) {
            (Some(before), Some(after)) => judge(&before, &after, window.as_secs_f64(), settings),
            _ => vec![SelfTestCheck {
                check: "live".into(),
                passed: false,
                detail: format!("the baseline published no live status within {} s", LIVE_WAIT.as_secs()),
            }],
        };
        SelfTest { at_ms: unix_now_ms(), experiment, passed: checks.iter().all(|c| c.passed), checks }
    }

    /// Keeps `test` in the lab's history; a failed one takes the robot out
    /// of service (unless it is already), audited and told to the owner.
    pub(super) fn keep_self_test(&self, book: &mut Book, test: SelfTest) {
        let mut lab = book.lab.clone();
        lab.self_tests.push(test.clone());
        let over = lab.self_tests.len().saturating_sub(MAX_SELF_TESTS);
        lab.self_tests.drain(..over);
        let failed: Vec<String> =
            test.checks.iter().filter(|c| !c.passed).map(|c| format!("{}: {}", c.check, c.detail)).collect();
        let after = test.experiment.map_or_else(String::new, |id| format!(" after experiment {id}"));
        let reason = crate::contract::clip_to(
            &format!("the self-test{after} failed: {}", failed.join("; ")),
            crate::store::experiments::MAX_MAINTENANCE_REASON,
        );
        let enters = !test.passed && lab.maintenance.is_none();
        if enters {
            // A low battery alone clears by itself once charged.
            let battery_alone = test.checks.iter().all(|c| c.passed || c.check == "battery");
            let resume = book.lab.settings.self_test.and_then(|s| s.resume_battery_v);
            lab.maintenance = Some(Maintenance {
                reason: reason.clone(),
                by: SELF_TEST_USER.into(),
                since_ms: test.at_ms,
                ends_at_battery_v: resume.filter(|_| battery_alone),
            });
        }
        let stored = self.store().lock().and_then(|writer| writer.put_lab_state(&lab));
        if let Err(e) = stored {
            // The robot still must not take work: kept in memory.
            tracing::error!("the self-test's result was not stored: {e}");
        }
        book.lab = lab;
        let outcome = if test.passed { "passed".to_string() } else { reason.clone() };
        self.audit(LAB_AUDIT_USER, "self-test", &format!("the robot{after}"), Outcome::Ok(&outcome));
        if enters {
            tracing::warn!("out of service: {reason}");
            self.tell_robot(EventKind::RobotMaintenanceStarted, &format!("{reason} (by {SELF_TEST_USER})"));
        }
        self.notify();
    }
}

impl Lab {
    /// Runs the owner's self-test now, asked by admin `user` (the robot
    /// idle: no experiment runs or starts meanwhile). Kept in the history
    /// as after a run; a failed one takes the robot out of service, and a
    /// passed one ends a maintenance the self-test began.
    pub fn run_self_test(&self, user: &crate::store::users::Principal) -> Result<SelfTest, LabError> {
        let use_case = || {
            if user.role != crate::store::users::Role::Admin {
                return Err(LabError::Forbidden(format!("{} may not run the self-test (admins may)", user.name)));
            }
            let settings = {
                let mut book = self.lock()?;
                let settings = book.lab.settings.self_test.ok_or_else(|| {
                    LabError::Conflict("the owner's settings have no self-test (self_test: null)".into())
                })?;
                if let Some(id) = book.running.as_ref().map(|r| r.id).or(book.starting) {
                    return Err(LabError::Conflict(format!(
                        "experiment {id} runs on the robot: the self-test runs on the baseline, after it"
                    )));
                }
                if book.self_testing {
                    return Err(LabError::Conflict("a self-test runs already".into()));
                }
                book.self_testing = true;
                settings
            };
            let test = self.self_test(None, &settings);
            // Cleared first: nothing after it leaves the queue held.
            let mut book = self.lock()?;
            book.self_testing = false;
            let ends = test.passed && book.lab.maintenance.as_ref().is_some_and(|m| m.by == SELF_TEST_USER);
            self.keep_self_test(&mut book, test.clone());
            if ends {
                self.end_self_test_maintenance(&mut book, &format!("the self-test {} ran passed", user.name))?;
            }
            Ok(test)
        };
        self.audited(&user.name, "self-test", "the robot", use_case, |test| {
            if test.passed { "passed".to_string() } else { "failed".to_string() }
        })
    }

    /// While the robot is out of service for a low battery alone: ends it
    /// once every battery the live status reports reads at least its
    /// threshold (called by the runner at every look, under the book).
    pub(super) fn watch_battery(&self, book: &mut Book) {
        let Some(resume) = book.lab.maintenance.as_ref().and_then(|m| m.ends_at_battery_v) else {
            book.battery_watch = None;
            return;
        };
        let live = book.battery_watch.get_or_insert_with(|| self.deployer.live().subscribe());
        if !live.has_changed().unwrap_or(false) {
            return;
        }
        let status = live.borrow_and_update().clone();
        let Some(status) = status.as_ref().as_ref() else { return };
        let readings: Vec<(String, f64)> = status
            .report
            .sections
            .of::<SerialStatus>()
            .filter_map(|(name, link)| link.battery_v.map(|v| (name.to_string(), v)))
            .collect();
        if readings.is_empty() || readings.iter().any(|(_, v)| *v < resume) {
            return;
        }
        let said = readings.iter().map(|(n, v)| format!("link '{n}': {v:.2} V")).collect::<Vec<_>>().join("; ");
        let why = format!("the battery is charged ({said}, at least {resume:.2} V)");
        if let Err(e) = self.end_self_test_maintenance(book, &why) {
            tracing::error!("the robot stays out of service: its end was not stored: {e}");
        }
    }

    /// Ends the maintenance the self-test began (`why`: what brought the
    /// robot back): stored, audited as the self-test's, told to the owner.
    fn end_self_test_maintenance(&self, book: &mut Book, why: &str) -> Result<(), LabError> {
        let mut lab = book.lab.clone();
        let Some(ended) = lab.maintenance.take() else { return Ok(()) };
        self.store().lock()?.put_lab_state(&lab)?;
        book.lab = lab;
        book.battery_watch = None;
        let detail = format!("back in service: {why}; was: {}", ended.reason);
        tracing::info!("{detail}");
        self.audit(SELF_TEST_USER, "maintenance-end", "the robot", Outcome::Ok(&detail));
        self.tell_robot(EventKind::RobotMaintenanceEnded, &detail);
        self.notify();
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::report::{ComponentReport, LoopLateness, MessageTotals, Section, Sections, StoppedBy};

    fn component(name: &str, fault: Option<&str>) -> ComponentReport {
        ComponentReport {
            name: name.into(),
            platform: "control".into(),
            source: "builtin:x".into(),
            rate_hz: 10.0,
            priority: None,
            state: if fault.is_some() { ComponentRunState::Faulted } else { ComponentRunState::Running },
            fault: fault.map(String::from),
            faulted_at_s: None,
            calls: 0,
            ticks: 0,
            missed_ticks: 0,
            call_time_ms: 0.0,
            messages_in: 0,
            messages_out: 0,
            messages_dropped: 0,
            errors: 0,
            last_error: None,
            restarts: 0,
            faults: 0,
            call_times: Default::default(),
        }
    }

    fn report(components: Vec<ComponentReport>, links: Vec<(&str, SerialStatus)>) -> Report {
        Report {
            format: 1,
            robot: "lab".into(),
            config: "robot.xml".into(),
            stopped_by: StoppedBy::Running,
            duration_s: 1.0,
            cycles: 10,
            components,
            connections: Vec::new(),
            messages: MessageTotals { routed: 0, delivered: 0, dropped: 0 },
            loop_lateness: LoopLateness {
                cycles: 0,
                total_ms: 0.0,
                max_ms: 0.0,
                waited_for_cpu_ms: 0.0,
                histogram: Default::default(),
            },
            sections: Sections(
                links
                    .into_iter()
                    .map(|(name, status)| Section {
                        key: "serial".into(),
                        component: name.into(),
                        status: std::sync::Arc::new(status),
                    })
                    .collect(),
            ),
        }
    }

    fn link(connected: bool, feedback_messages: u64, battery_v: Option<f64>) -> SerialStatus {
        SerialStatus {
            device: "/dev/ttyUSB0".into(),
            connected,
            feedback_messages,
            battery_v,
            ..SerialStatus::default()
        }
    }

    /// `link` whose controller reported its fault status `readings` times,
    /// the last with `fault`.
    fn faulty(link: SerialStatus, readings: u64, fault: Option<&str>) -> SerialStatus {
        SerialStatus { fault_readings: readings, fault: fault.map(String::from), ..link }
    }

    #[test]
    fn each_check_passes_or_fails_with_what_it_saw() {
        let settings = SelfTestSettings {
            window_ms: 1000,
            min_battery_v: Some(11.0),
            resume_battery_v: None,
            controller_faults: true,
            odometry_ratio: None,
        };
        let healthy = || vec![component("motors", None), component("avoid", None)];
        // (case, before, after, expected (check, passed, words in its detail))
        type Expected = Vec<(&'static str, bool, &'static str)>;
        let cases: Vec<(&str, Report, Report, Expected)> = vec![
            (
                "all well",
                report(healthy(), vec![("motors", link(true, 10, Some(12.4)))]),
                report(healthy(), vec![("motors", link(true, 30, Some(12.3)))]),
                vec![
                    ("components", true, "2 components running"),
                    ("feedback", true, "link 'motors': 20 feedback messages in 1.0 s"),
                    ("controller", true, "no link reports its controller's faults"),
                    ("battery", true, "battery 12.30 V"),
                ],
            ),
            (
                "a controller that reads no fault",
                report(healthy(), vec![("motors", link(true, 10, None))]),
                report(healthy(), vec![("motors", faulty(link(true, 30, None), 4, None))]),
                vec![
                    ("components", true, ""),
                    ("feedback", true, ""),
                    ("controller", true, "link 'motors': no fault"),
                    ("battery", true, "no link reports a battery"),
                ],
            ),
            (
                "a controller in fault, beside one that is not",
                report(healthy(), vec![("left", link(true, 10, None)), ("right", link(true, 10, None))]),
                report(
                    healthy(),
                    vec![
                        ("left", faulty(link(true, 30, None), 2, Some("m1 over current warning"))),
                        ("right", faulty(link(true, 30, None), 2, None)),
                    ],
                ),
                vec![
                    ("components", true, ""),
                    ("feedback", true, ""),
                    ("controller", false, "link 'left': the motor controller reports m1 over current warning"),
                    ("battery", true, ""),
                ],
            ),
            (
                "a silent link and a low battery",
                report(healthy(), vec![("motors", link(true, 30, Some(10.2)))]),
                report(healthy(), vec![("motors", link(true, 30, Some(10.2)))]),
                vec![
                    ("components", true, ""),
                    ("feedback", false, "link 'motors' (/dev/ttyUSB0) gave no feedback in 1.0 s"),
                    ("controller", true, ""),
                    ("battery", false, "battery 10.20 V is under 11.00 V"),
                ],
            ),
            (
                "a link gone and a faulted component",
                report(healthy(), vec![("motors", link(true, 5, None))]),
                report(
                    vec![component("motors", None), component("avoid", Some("trapped"))],
                    vec![("motors", link(false, 9, None))],
                ),
                vec![
                    ("components", false, "component 'avoid' faulted: trapped"),
                    ("feedback", false, "link 'motors' is not connected to /dev/ttyUSB0"),
                    ("controller", true, ""),
                    ("battery", true, "no link reports a battery"),
                ],
            ),
            (
                "no serial link",
                report(healthy(), vec![]),
                report(healthy(), vec![]),
                vec![
                    ("components", true, ""),
                    ("feedback", true, "no serial link"),
                    ("controller", true, "no link reports"),
                    ("battery", true, "no link"),
                ],
            ),
        ];
        for (case, before, after, expected) in cases {
            let checks = judge(&before, &after, 1.0, &settings);
            assert_eq!(checks.len(), expected.len(), "{case}: {checks:#?}");
            for (check, (name, passed, words)) in checks.iter().zip(expected) {
                assert_eq!((check.check.as_str(), check.passed), (name, passed), "{case}: {check:#?}");
                assert!(check.detail.contains(words), "{case}: {check:#?}");
            }
        }
        // Without a battery threshold, no battery check; with the controller
        // check turned off, a controller's fault fails nothing.
        let quiet = SelfTestSettings { controller_faults: false, min_battery_v: None, ..settings };
        let same = report(healthy(), vec![("motors", link(true, 3, Some(1.0)))]);
        let faulted = faulty(link(true, 4, Some(1.0)), 1, Some("e-stop"));
        let checks = judge(&same, &report(healthy(), vec![("motors", faulted)]), 1.0, &quiet);
        assert_eq!(checks.iter().map(|c| c.check.as_str()).collect::<Vec<_>>(), ["components", "feedback"]);
        assert!(checks.iter().all(|c| c.passed), "{checks:#?}");
    }

    /// `link` at distance `commanded_m` commanded and `odometry_m` seen,
    /// with a pose (none: it reports no odometry).
    fn moving(commanded_m: f64, odometry_m: f64, pose: bool) -> SerialStatus {
        SerialStatus { commanded_m, odometry_m, pose: pose.then_some([1.0, 1.0, 0.0]), ..link(true, 30, None) }
    }

    /// The motion check: the odometry over the window against what the
    /// commands asked for, within the owner's ratio either way.
    #[test]
    fn the_motion_check_compares_each_links_odometry_with_its_commands() {
        let settings = SelfTestSettings {
            window_ms: 1000,
            min_battery_v: None,
            resume_battery_v: None,
            controller_faults: false,
            odometry_ratio: Some(0.5),
        };
        let healthy = || vec![component("motors", None)];
        let cases: [(&str, SerialStatus, SerialStatus, bool, &str); 6] = [
            (
                "it went where it was sent",
                moving(1.0, 1.0, true),
                moving(1.4, 1.38, true),
                true,
                "link 'motors': 0.40 m commanded, the odometry shows 0.38 m in 1.0 s",
            ),
            (
                "a motor that does not answer",
                moving(1.0, 1.0, true),
                moving(1.4, 1.0, true),
                false,
                "0.40 m commanded, the odometry shows 0.00 m in 1.0 s, outside 0.50 to 2.00 of it",
            ),
            ("half the way still passes", moving(0.0, 0.0, true), moving(0.4, 0.2, true), true, "shows 0.20 m"),
            ("a runaway", moving(0.0, 0.0, true), moving(0.1, 0.3, true), false, "outside 0.50 to 2.00"),
            (
                "standing still is not judged",
                moving(2.0, 2.0, true),
                moving(2.01, 2.0, true),
                true,
                "too little motion to judge (at least 0.05 m)",
            ),
            (
                "no odometry",
                moving(0.0, 0.0, false),
                moving(1.0, 0.0, false),
                true,
                "link 'motors' reports no odometry",
            ),
        ];
        for (case, before, after, passed, words) in cases {
            let checks = judge(
                &report(healthy(), vec![("motors", before)]),
                &report(healthy(), vec![("motors", after)]),
                1.0,
                &settings,
            );
            let motion = checks.iter().find(|c| c.check == "motion").unwrap_or_else(|| panic!("{case}: {checks:#?}"));
            assert_eq!(motion.passed, passed, "{case}: {motion:#?}");
            assert!(motion.detail.contains(words), "{case}: {motion:#?}");
        }
        let off = SelfTestSettings { odometry_ratio: None, ..settings };
        let checks = judge(&report(healthy(), vec![]), &report(healthy(), vec![]), 1.0, &off);
        assert!(checks.iter().all(|c| c.check != "motion"), "{checks:#?}");
    }
}
