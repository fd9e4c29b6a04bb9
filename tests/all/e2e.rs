//! End-to-end tests: the built `subsume` binary, driven from outside as a
//! user drives it (processes, files, signals, exit codes, stdout, reports).

use std::path::Path;
use std::process::{Output, Stdio};
use std::time::{Duration, Instant};

use serde_json::Value as Json;

use crate::support::{
    self, FREE_TELEOP_PORTS, PASS_ENVELOPE, component, read_report, robot_file, subsume, text, wait_for_exit,
};

fn run(args: &[&str]) -> Output {
    subsume().args(args).output().unwrap()
}

#[test]
fn the_demo_robot_reaches_its_goal_without_collisions() {
    // On simulated time, lock-step (`--speed max`): the outcome is the
    // demo's, not the machine's. In real time, with both cores kept busy
    // (scripts/test-under-load), the loop ran late and the robot was still
    // 0.5 m short of its goal at 50 s.
    let dir = tempfile::tempdir().unwrap();
    let report_path = dir.path().join("report.json");
    let mut args = vec!["run", "config/demo.xml", "--speed", "max", "--duration", "50"];
    args.extend(["--report", report_path.to_str().unwrap()]);
    args.extend(FREE_TELEOP_PORTS);
    let output = run(&args);
    let log = text(&output.stderr);
    assert!(output.status.success(), "{log}");

    let report = read_report(&report_path);
    assert_eq!(
        (report["format"].as_u64(), report["robot"].as_str(), report["stopped_by"].as_str()),
        (Some(2), Some("demo"), Some("duration"))
    );
    for c in report["components"].as_array().unwrap() {
        assert_eq!(c["state"], "running", "{c}");
        assert_eq!(c["errors"], 0, "{c}");
    }
    let sim = &report["sim"];
    assert_eq!(sim["goal_reached"], true, "{sim}");
    assert_eq!(sim["collisions"], 0, "{sim}");
    assert!(sim["goal_reached_at_s"].as_f64().unwrap() < 50.0);
    assert!(sim["distance_travelled_m"].as_f64().unwrap() > 9.0, "{sim}");
    // Both behaviours drove: the avoider took over near the box.
    let arbiter = &report["arbiter"];
    let held = |source: &str| {
        let entry = arbiter["held_s"].as_array().unwrap().iter().find(|h| h[0] == source);
        entry.and_then(|h| h[1].as_f64()).unwrap_or_default()
    };
    assert!(held("avoid") > 0.5 && held("planner") > 0.5, "{arbiter}");
    assert_eq!(held("teleop"), 0.0, "no operator connected: {arbiter}");
    assert!(arbiter["switches"].as_u64().unwrap() >= 3, "{arbiter}");
    assert!(log.contains("avoid (priority 3) suppresses planner (priority 1)"), "{log}");
    assert!(log.contains("planner (priority 1) holds control"), "{log}");
    // The commands crossed the PTY as bytes; the feedback came back clean.
    let serial = &report["serial"];
    assert!(serial["frames_written"].as_u64().unwrap() > 100, "{serial}");
    assert!(serial["bytes_written"].as_u64().unwrap() > 500, "{serial}");
    assert_eq!(serial["frames_written"], report["sim"]["commands_received"], "{serial}");
    assert_eq!((serial["malformed_feedback"].as_u64(), serial["reconnects"].as_u64()), (Some(0), Some(0)));
    assert!(serial["feedback_messages"].as_u64().unwrap() > 1000, "{serial}");
    // The distance the commands asked for and the one the odometry showed
    // (the self-test's motion check compares them) agree with the
    // simulated robot's path.
    let (commanded, odometry) = (serial["commanded_m"].as_f64().unwrap(), serial["odometry_m"].as_f64().unwrap());
    let travelled = sim["distance_travelled_m"].as_f64().unwrap();
    assert!((odometry - travelled).abs() < 0.05 * travelled, "odometry {odometry} m, travelled {travelled} m");
    assert!((commanded - odometry).abs() < 0.1 * odometry, "commanded {commanded} m, odometry {odometry} m");
}

/// A robot whose only motion source drives straight at a wall, with or
/// without the obstacle avoider above it, through an envelope with or
/// without its collision monitor (the ranges wired in); returns the report.
fn drive_at_a_wall(with_avoider: bool, monitor: bool) -> Json {
    let dir = tempfile::tempdir().unwrap();
    let world = support::repo_root().join("tests/worlds/wall-ahead.world");
    let avoider = if with_avoider {
        r#"<component name="avoid" source="GUEST(avoider)" rate="20" timeout="400ms">
      <param name="creep-speed" value="0.05"/>
    </component>
    <connect from="filter.filtered" to="avoid.ranges"/>
    <connect from="avoid.cmd" to="arbiter.commands"/>"#
    } else {
        ""
    };
    let envelope = if monitor {
        // The owner's defaults, with the sensors wired in.
        r#"<component name="envelope" source="builtin:envelope" rate="20"/>
    <connect from="motors.ranges" to="envelope.ranges"/>
    <connect from="motors.pose" to="envelope.pose"/>"#
    } else {
        PASS_ENVELOPE
    };
    let body = format!(
        r#"<robot name="wall">
  <platform name="control">
    <component name="sim" source="builtin:sim"><param name="world" value="{}"/></component>
    <component name="motors" source="builtin:serial" rate="100"><param name="device" value="sim:sim"/></component>
    <component name="filter" source="GUEST(range-filter)" rate="0"/>
    <component name="driver" source="builtin:publish" rate="10" priority="{priority}">
      <param name="kind" value="command"/>
      <param name="value" value="VEL 0.4 0"/>
    </component>
    <component name="arbiter" source="builtin:arbiter" rate="20"/>
    <connect from="motors.ranges" to="filter.ranges"/>
    <connect from="driver.out" to="arbiter.commands"/>
    {envelope}
    <connect from="arbiter.cmd" to="envelope.cmd"/>
    <connect from="envelope.cmd" to="motors.cmd"/>
    {avoider}
  </platform>
</robot>"#,
        world.display(),
        priority = if with_avoider { 1 } else { 1000 },
    );
    let robot = robot_file(dir.path(), &body);
    let report_path = dir.path().join("report.json");
    // On simulated time (lock-step): in real time on a machine with both
    // cores busy, stale ranges made the envelope stop the robot again and
    // again and it had not finished its approach at 15 s.
    let robot = robot.to_str().unwrap();
    let output = run(&["run", robot, "--speed", "max", "--duration", "15", "--report", report_path.to_str().unwrap()]);
    assert!(output.status.success(), "{}", text(&output.stderr));
    read_report(&report_path)
}

#[test]
fn the_avoider_prevents_the_collision_a_blind_source_would_cause() {
    let blind = drive_at_a_wall(false, false);
    assert!(
        blind["sim"]["collisions"].as_u64().unwrap() >= 1,
        "without the avoider the robot hits the wall: {}",
        blind["sim"]
    );
    let guarded = drive_at_a_wall(true, false);
    assert_eq!(guarded["sim"]["collisions"], 0, "{}", guarded["sim"]);
    let held = &guarded["arbiter"]["held_s"];
    assert!(held[1][0] == "avoid" && held[1][1].as_f64().unwrap() > 0.5, "{held}");
    assert!(guarded["sim"]["distance_travelled_m"].as_f64().unwrap() > 3.0, "{}", guarded["sim"]);
}

#[test]
fn the_envelope_stops_a_blind_top_priority_driver_short_of_the_wall() {
    let report = drive_at_a_wall(false, true);
    let (sim, envelope) = (&report["sim"], &report["envelope"]);
    assert_eq!(sim["collisions"], 0, "{sim}");
    // The wall is at x = 5, the body a disc of 0.18 m, the stop zone 0.1 m:
    // the robot got close (it was not just frozen) and stopped outside the
    // stop zone (the slowdown zone's ramp ends at its edge). How close
    // depends on the reaction time the envelope budgeted (at 0.4 m/s, each
    // 0.1 s of it is 4 cm kept back): 0.05 s at its 20 Hz on an idle
    // machine, longer when a busy machine runs the loop late.
    let clearance = 5.0 - sim["x"].as_f64().unwrap() - 0.18;
    let reaction_s = envelope["reaction_max_s"].as_f64().unwrap();
    let farthest = 0.2 + 0.4 * (reaction_s - 0.05).max(0.0);
    assert!(
        clearance > 0.09 && clearance < farthest,
        "clearance {clearance} m, at most {farthest} m: {sim} {envelope}"
    );
    assert!(envelope["scaled"].as_u64().unwrap() > 0, "{envelope}");
    let causes = &envelope["causes"];
    assert!(
        causes["slowdown-zone"].as_u64().unwrap_or(0) + causes["time-to-collision"].as_u64().unwrap_or(0) > 0,
        "{envelope}"
    );
    let closest = envelope["closest_ever_m"].as_f64().unwrap();
    assert!(closest > 0.09, "closest approach {closest} m: {envelope}");
    // What it changed (the command as the driver wrote it), why, and the
    // reading behind it.
    let last = envelope["last"]["text"].as_str().unwrap();
    assert!(last.contains("VEL 0.4 0 to ") && last.contains("m ahead,") && last.contains("zone"), "{envelope}");
}

#[test]
fn when_every_source_goes_silent_stop_bytes_reach_the_pty_within_the_watchdog_timeout() {
    let (mut motors, _slave, device) = support::MotorRecorder::new();
    let dir = tempfile::tempdir().unwrap();
    let robot = robot_file(
        dir.path(),
        &format!(
            r#"<robot name="silence">
  <platform name="control">
    <component name="motors" source="builtin:serial" rate="100">
      <param name="device" value="{device}"/>
      <param name="watchdog" value="0.3"/>
    </component>
    <component name="teleop" source="GUEST(test-commander)" rate="20" timeout="200ms">
      <param name="command" value="VEL 0.25 0"/>
      <param name="ticks" value="20"/>
    </component>
    <component name="arbiter" source="builtin:arbiter" rate="20"/>
    <connect from="teleop.cmd" to="arbiter.commands"/>
    {PASS_ENVELOPE}
    <connect from="arbiter.cmd" to="envelope.cmd"/>
    <connect from="envelope.cmd" to="motors.cmd"/>
  </platform>
</robot>"#
        ),
    );
    let mut child =
        subsume().args(["run", robot.to_str().unwrap(), "--duration", "4"]).stderr(Stdio::null()).spawn().unwrap();
    // Record every line the motor controller receives, with its arrival time.
    let deadline = Instant::now() + Duration::from_secs(30);
    motors.read_while(|| child.try_wait().unwrap().is_none() && Instant::now() < deadline);
    assert!(wait_for_exit(&mut child, Duration::from_secs(10)).success());
    let lines = motors.lines;
    let last_motion = lines.iter().rposition(|(_, l)| l == "M 250 250").expect("the source's commands reached the pty");
    let first_stop = lines[last_motion..].iter().find(|(_, l)| l == "S").expect("STOP reached the pty");
    let gap = first_stop.0.duration_since(lines[last_motion].0);
    assert!(gap <= Duration::from_millis(300), "STOP came {gap:?} after the last motion command");
    assert!(lines[last_motion + 1..].iter().all(|(_, l)| l == "S"), "only STOP after the silence: {lines:?}");
}

/// Starts `subsume run` without a duration and waits until the log shows a
/// value moving through the graph.
fn start_and_wait_until_running(report: &Path) -> support::HostProcess {
    let mut command = subsume();
    command.args(["run", "config/demo.xml", "--report", report.to_str().unwrap()]).args(FREE_TELEOP_PORTS);
    let host = support::HostProcess::spawn(command);
    host.word_after("received command", Duration::from_secs(30));
    host
}

#[test]
fn sigint_and_sigterm_stop_the_host_cleanly() {
    for signal in ["INT", "TERM"] {
        let dir = tempfile::tempdir().unwrap();
        let report_path = dir.path().join("report.json");
        let mut host = start_and_wait_until_running(&report_path);
        support::signal(host.child.id(), signal);
        let status = wait_for_exit(&mut host.child, Duration::from_secs(5));
        assert!(status.success(), "SIG{signal}: {status}");
        let report = read_report(&report_path);
        assert_eq!(report["stopped_by"], "shutdown", "SIG{signal}");
        assert!(report["messages"]["routed"].as_u64().unwrap() > 0);
    }
}

/// The log is coloured only on a terminal: a redirected log (a pipe, a
/// file, the journal) gets plain text, and `NO_COLOR` turns colour off on
/// a terminal too.
#[test]
fn the_log_is_coloured_only_on_a_terminal_without_no_color() {
    let dir = tempfile::tempdir().unwrap();
    let robot = robot_file(
        dir.path(),
        r#"<robot name="colours"><platform name="control">
  <component name="source" source="builtin:publish" rate="20"><param name="value" value="1"/></component>
  <component name="sink" source="builtin:log" rate="0"/>
  <connect from="source.out" to="sink.in"/>
</platform></robot>"#,
    );
    let host = |no_color: Option<&str>| {
        let mut command = subsume();
        command.env_remove("NO_COLOR").args(["run", robot.to_str().unwrap(), "--duration", "0.3"]);
        if let Some(value) = no_color {
            command.env("NO_COLOR", value);
        }
        command
    };
    const ESCAPE: char = '\u{1b}';
    let piped = host(None).output().unwrap();
    let log = text(&piped.stderr);
    assert!(piped.status.success() && log.contains("robot 'colours'"), "{log}");
    assert!(!log.contains(ESCAPE), "colour in a redirected log: {log:?}");
    // On a terminal: colour, unless NO_COLOR is set (and not empty).
    for (no_color, coloured) in [(None, true), (Some(""), true), (Some("1"), false)] {
        let mut terminal = support::Pty::new();
        let mut child = host(no_color).stderr(terminal.stdio()).stdout(Stdio::null()).spawn().unwrap();
        let stopped = terminal.read_until(Duration::from_secs(30), |t| t.contains("messages routed"));
        assert!(child.wait().unwrap().success() && stopped, "{}", terminal.text);
        assert!(terminal.text.contains("robot 'colours'"), "{}", terminal.text);
        assert_eq!(terminal.text.contains(ESCAPE), coloured, "NO_COLOR {no_color:?}: {:?}", terminal.text);
    }
}

#[test]
fn check_prints_every_error_one_per_line_and_exits_1() {
    let output = run(&["check", "tests/config/many-errors.xml"]);
    assert_eq!(output.status.code(), Some(1));
    let stdout = text(&output.stdout);
    let expected = std::fs::read_to_string(support::repo_root().join("tests/config/many-errors.expected")).unwrap();
    let expected: Vec<String> = expected.lines().map(|l| format!("tests/config/{l}")).collect();
    assert_eq!(stdout.lines().collect::<Vec<_>>(), expected);
}

#[test]
fn check_accepts_a_good_file_with_a_summary() {
    let output = run(&["check", "config/demo.xml"]);
    assert_eq!(output.status.code(), Some(0), "{}", text(&output.stdout));
    assert_eq!(text(&output.stdout), "config/demo.xml: ok: robot 'demo', 9 components, 12 connections\n");
    // Parameters can be set from the command line; a bad one is reported.
    let output = run(&["check", "config/demo.xml", "--param", "avoid.threshold=near"]);
    assert_eq!(output.status.code(), Some(1));
    let stdout = text(&output.stdout);
    assert!(
        stdout.contains("parameter 'threshold' of component 'avoid' expects a finite number, got 'near'"),
        "{stdout}"
    );
    let output = run(&["check", "config/demo.xml", "--param", "ghost.x=1"]);
    assert_eq!(text(&output.stdout), "--param:1:1: no component 'ghost' in config/demo.xml to set 'x' on\n");
}

#[test]
fn run_refuses_a_bad_file_and_starts_nothing() {
    let output = run(&["run", "tests/config/bad-connections.xml", "--duration", "1"]);
    assert_eq!(output.status.code(), Some(1));
    assert_eq!(text(&output.stdout).lines().count(), 11);
    let stderr = text(&output.stderr);
    assert!(stderr.contains("11 problem(s) in tests/config/bad-connections.xml; nothing was started"), "{stderr}");
    assert!(!stderr.contains("started range-filter"), "{stderr}");
}

#[test]
fn describe_prints_ports_params_and_priority() {
    let avoider = support::guest("avoider");
    let output = run(&["describe", avoider.to_str().unwrap()]);
    assert!(output.status.success());
    let stdout = text(&output.stdout);
    assert!(stdout.starts_with("avoider 0.1.0: Turns away from obstacles"), "{stdout}");
    assert!(stdout.contains("default priority: 3\n"), "{stdout}");
    assert!(stdout.contains("inputs:\n  0: ranges (vector)"), "{stdout}");
    assert!(stdout.contains("outputs:\n  0: cmd (command)"), "{stdout}");
    assert!(stdout.contains("  threshold (number, default '0.5')"), "{stdout}");

    let output = run(&["describe", avoider.to_str().unwrap(), "--json"]);
    assert!(output.status.success());
    let json: Json = serde_json::from_slice(&output.stdout).unwrap();
    assert_eq!(json["name"], "avoider");
    assert_eq!(json["default_priority"], 3);
    assert_eq!(json["inputs"][0]["name"], "ranges");
    assert_eq!(json["inputs"][0]["kind"], "vector");
    assert_eq!(json["outputs"][0]["kind"], "command");
    assert_eq!(json["params"][0]["name"], "threshold");
    assert_eq!(json["params"][0]["default"], "0.5");
    assert_eq!(json["sha256"].as_str().unwrap().len(), 64);
}

#[test]
fn describe_refuses_what_is_not_a_component() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("module.wasm");
    std::fs::write(&path, b"\0asm\x01\x00\x00\x00").unwrap();
    let output = run(&["describe", path.to_str().unwrap()]);
    assert_eq!(output.status.code(), Some(1));
    let stderr = text(&output.stderr);
    assert!(stderr.contains("not a webassembly component: this is a core webassembly module"), "{stderr}");
}

#[test]
fn a_faulting_guest_is_reported_and_the_others_keep_running() {
    let dir = tempfile::tempdir().unwrap();
    let robot = robot_file(
        dir.path(),
        r#"<robot name="faults">
  <platform name="control">
    <component name="bad" source="GUEST(test-faulty)" rate="50" budget="5ms">
      <param name="mode" value="loop-on-tick"/>
      <param name="after" value="5"/>
    </component>
    <component name="good" source="GUEST(test-counter)" rate="50"/>
    <component name="sink" source="builtin:log" rate="0"/>
    <connect from="good.count" to="sink.in"/>
    <connect from="bad.out" to="sink.in"/>
  </platform>
</robot>"#,
    );
    let report_path = dir.path().join("report.json");
    let output = run(&["run", robot.to_str().unwrap(), "--duration", "1", "--report", report_path.to_str().unwrap()]);
    let log = text(&output.stderr);
    assert!(output.status.success(), "{log}");
    assert!(
        log.contains("component faulted and is stopped: tick: exceeded its cpu-time budget of 5 ms (used "),
        "{log}"
    );
    let report = read_report(&report_path);
    let bad = component(&report, "bad");
    assert_eq!(bad["state"], "faulted");
    let fault = bad["fault"].as_str().unwrap_or_default();
    assert!(fault.starts_with("tick: exceeded its cpu-time budget of 5 ms (used "), "{fault}");
    assert_eq!(bad["messages_out"], 5);
    let good = component(&report, "good");
    assert_eq!(good["state"], "running");
    assert!(good["ticks"].as_u64().unwrap() >= 45, "{good}");
}

#[test]
fn a_component_that_refuses_to_start_stops_startup() {
    let dir = tempfile::tempdir().unwrap();
    let robot = robot_file(
        dir.path(),
        r#"<robot name="refusal">
  <platform name="control">
    <component name="stubborn" source="GUEST(test-faulty)">
      <param name="mode" value="error-on-init"/>
    </component>
  </platform>
</robot>"#,
    );
    let output = run(&["run", robot.to_str().unwrap(), "--duration", "1"]);
    assert_eq!(output.status.code(), Some(1));
    let stderr = text(&output.stderr);
    assert!(
        stderr.contains("failed to start component 'stubborn': init() failed: refusing to start, as asked"),
        "{stderr}"
    );
}

#[test]
fn compiling_a_component_says_so_and_how_long_it_took_and_a_cached_one_is_silent() {
    let cache = tempfile::tempdir().unwrap();
    let describe = || {
        let output =
            support::subsume_with_cache(cache.path()).arg("describe").arg(support::guest("avoider")).output().unwrap();
        assert!(output.status.success(), "{}", text(&output.stderr));
        text(&output.stderr)
    };
    let first = describe();
    let before = first.find("compiling component ").unwrap_or_else(|| panic!("no progress line:\n{first}"));
    let after = first.find("compiled component ").unwrap_or_else(|| panic!("no time line:\n{first}"));
    assert!(before < after && first.contains("KiB; not in the cache yet)..."), "{first}");
    let seconds = first[after..].split(" in ").nth(1).and_then(|t| t.split(" s").next()).unwrap_or("");
    assert!(seconds.parse::<f64>().is_ok_and(|s| s >= 0.0), "{first}");
    let second = describe();
    assert!(!second.contains("compil"), "the cached component was compiled again:\n{second}");
}
