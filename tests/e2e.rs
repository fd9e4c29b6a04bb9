#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic)]
//! End-to-end tests: the built `subsume` binary, driven from outside as a
//! user drives it (processes, files, signals, exit codes, stdout, reports).

#[path = "../host/tests/support/mod.rs"]
mod support;

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use serde_json::Value as Json;

fn subsume() -> Command {
    support::guest_dir();
    let mut command = Command::new(env!("CARGO_BIN_EXE_subsume"));
    command
        .current_dir(support::repo_root())
        .arg("--cache-dir")
        .arg(support::cache_dir())
        .env("RUST_LOG", "info")
        .env("NO_COLOR", "1");
    command
}

fn run(args: &[&str]) -> Output {
    subsume().args(args).output().unwrap()
}

fn text(bytes: &[u8]) -> String {
    String::from_utf8_lossy(bytes).into_owned()
}

fn read_report(path: &Path) -> Json {
    serde_json::from_slice(&std::fs::read(path).unwrap()).unwrap()
}

fn component<'a>(report: &'a Json, name: &str) -> &'a Json {
    report["components"]
        .as_array()
        .unwrap()
        .iter()
        .find(|c| c["name"] == name)
        .unwrap_or_else(|| panic!("no component '{name}' in the report"))
}

/// Writes a robot file into `dir` whose `GUEST(name)` placeholders name the
/// built guests.
fn robot_file(dir: &Path, body: &str) -> PathBuf {
    let mut xml = body.to_string();
    for name in [
        "test-counter",
        "test-faulty",
        "test-relay",
        "avoider",
        "planner",
        "range-filter",
    ] {
        xml = xml.replace(
            &format!("GUEST({name})"),
            &support::guest(name).display().to_string(),
        );
    }
    let path = dir.join("robot.xml");
    std::fs::write(&path, xml).unwrap();
    path
}

#[test]
fn the_demo_runs_for_its_duration_and_reports() {
    let dir = tempfile::tempdir().unwrap();
    let report_path = dir.path().join("report.json");
    let started = Instant::now();
    let output = run(&[
        "run",
        "config/demo.xml",
        "--duration",
        "2",
        "--report",
        report_path.to_str().unwrap(),
    ]);
    let log = text(&output.stderr);
    assert!(output.status.success(), "{log}");
    assert!(started.elapsed() < Duration::from_secs(20));

    let report = read_report(&report_path);
    assert_eq!(report["format"], 1);
    assert_eq!(report["robot"], "demo");
    assert_eq!(report["stopped_by"], "duration");
    let seconds = report["duration_s"].as_f64().unwrap();
    assert!((2.0..3.0).contains(&seconds), "ran {seconds} s");
    let components = report["components"].as_array().unwrap();
    assert_eq!(components.len(), 7);
    for c in components {
        assert_eq!(c["state"], "running", "{c}");
        assert!(c["fault"].is_null());
    }
    // 20 Hz for 2 s: about 40 scans through the filter into the avoider,
    // which sees an obstacle and commands a turn on each of its ticks.
    let filter = component(&report, "filter");
    assert!(
        (36..=44).contains(&filter["messages_in"].as_u64().unwrap()),
        "{filter}"
    );
    assert_eq!(
        filter["messages_out"].as_u64().unwrap(),
        2 * filter["messages_in"].as_u64().unwrap()
    );
    let avoid = component(&report, "avoid");
    assert!(
        (36..=44).contains(&avoid["ticks"].as_u64().unwrap()),
        "{avoid}"
    );
    // Its first tick (t = 0) comes before the first scan reaches it.
    assert_eq!(
        avoid["messages_out"].as_u64().unwrap(),
        avoid["ticks"].as_u64().unwrap() - 1
    );
    assert!(avoid["call_time_ms"].as_f64().unwrap() > 0.0);
    let motion_log = component(&report, "motion-log");
    let planner = component(&report, "planner");
    // Like the avoider, the planner has no pose yet on its first tick.
    let planner_cmds = planner["ticks"].as_u64().unwrap() - 1;
    assert_eq!(
        motion_log["messages_in"].as_u64().unwrap(),
        avoid["messages_out"].as_u64().unwrap() + planner_cmds
    );
    assert!(report["messages"]["routed"].as_u64().unwrap() > 200);
    assert_eq!(report["messages"]["dropped"], 0);
    assert_eq!(report["connections"].as_array().unwrap().len(), 6);
    // The log shows the data moving.
    assert!(log.contains("received command 'VEL 0.000 1.200'"), "{log}");
    assert!(log.contains("received scalar 0.400"), "{log}");
}

/// Starts `subsume run` without a duration and waits until the log shows a
/// value moving through the graph.
fn start_and_wait_until_running(report: &Path) -> Child {
    let mut child = subsume()
        .args([
            "run",
            "config/demo.xml",
            "--report",
            report.to_str().unwrap(),
        ])
        .stderr(Stdio::piped())
        .stdout(Stdio::null())
        .spawn()
        .unwrap();
    let stderr = child.stderr.take().unwrap();
    let (seen, wait) = mpsc::channel();
    std::thread::spawn(move || {
        let mut told = false;
        for line in BufReader::new(stderr).lines().map_while(Result::ok) {
            if !told && line.contains("received command") {
                told = true;
                let _ = seen.send(());
            }
        }
    });
    wait.recv_timeout(Duration::from_secs(30))
        .expect("the demo never logged a command");
    child
}

fn wait_for_exit(child: &mut Child, limit: Duration) -> std::process::ExitStatus {
    let deadline = Instant::now() + limit;
    loop {
        if let Some(status) = child.try_wait().unwrap() {
            return status;
        }
        if Instant::now() > deadline {
            let _ = child.kill();
            panic!("the host did not stop within {limit:?}");
        }
        std::thread::sleep(Duration::from_millis(20));
    }
}

#[test]
fn sigint_and_sigterm_stop_the_host_cleanly() {
    for signal in ["INT", "TERM"] {
        let dir = tempfile::tempdir().unwrap();
        let report_path = dir.path().join("report.json");
        let mut child = start_and_wait_until_running(&report_path);
        let sent = Command::new("kill")
            .arg(format!("-{signal}"))
            .arg(child.id().to_string())
            .status()
            .unwrap();
        assert!(sent.success());
        let status = wait_for_exit(&mut child, Duration::from_secs(5));
        assert!(status.success(), "SIG{signal}: {status}");
        let report = read_report(&report_path);
        assert_eq!(report["stopped_by"], "shutdown", "SIG{signal}");
        assert!(report["messages"]["routed"].as_u64().unwrap() > 0);
    }
}

#[test]
fn check_prints_every_error_one_per_line_and_exits_1() {
    let output = run(&["check", "host/tests/config/many-errors.xml"]);
    assert_eq!(output.status.code(), Some(1));
    let stdout = text(&output.stdout);
    let expected = std::fs::read_to_string(
        support::repo_root().join("host/tests/config/many-errors.expected"),
    )
    .unwrap();
    let expected: Vec<String> = expected
        .lines()
        .map(|l| format!("host/tests/config/{l}"))
        .collect();
    assert_eq!(stdout.lines().collect::<Vec<_>>(), expected);
}

#[test]
fn check_accepts_a_good_file_with_a_summary() {
    let output = run(&["check", "config/demo.xml"]);
    assert_eq!(output.status.code(), Some(0), "{}", text(&output.stdout));
    assert_eq!(
        text(&output.stdout),
        "config/demo.xml: ok: robot 'demo', 7 components, 6 connections\n"
    );
}

#[test]
fn run_refuses_a_bad_file_and_starts_nothing() {
    let output = run(&[
        "run",
        "host/tests/config/bad-connections.xml",
        "--duration",
        "1",
    ]);
    assert_eq!(output.status.code(), Some(1));
    assert_eq!(text(&output.stdout).lines().count(), 10);
    let stderr = text(&output.stderr);
    assert!(
        stderr.contains(
            "10 problem(s) in host/tests/config/bad-connections.xml; nothing was started"
        ),
        "{stderr}"
    );
    assert!(!stderr.contains("started range-filter"), "{stderr}");
}

#[test]
fn describe_prints_ports_params_and_priority() {
    let avoider = support::guest("avoider");
    let output = run(&["describe", avoider.to_str().unwrap()]);
    assert!(output.status.success());
    let stdout = text(&output.stdout);
    assert!(
        stdout.starts_with("avoider 0.1.0: Turns away from obstacles"),
        "{stdout}"
    );
    assert!(stdout.contains("default priority: 3\n"), "{stdout}");
    assert!(stdout.contains("inputs:\n  0: ranges (vector)"), "{stdout}");
    assert!(stdout.contains("outputs:\n  0: cmd (command)"), "{stdout}");
    assert!(
        stdout.contains("  threshold (number, default '0.5')"),
        "{stdout}"
    );

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
    assert!(
        stderr.contains("not a webassembly component: this is a core webassembly module"),
        "{stderr}"
    );
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
    let output = run(&[
        "run",
        robot.to_str().unwrap(),
        "--duration",
        "1",
        "--report",
        report_path.to_str().unwrap(),
    ]);
    let log = text(&output.stderr);
    assert!(output.status.success(), "{log}");
    assert!(
        log.contains("component faulted and is stopped: tick: exceeded its time budget of 5 ms"),
        "{log}"
    );
    let report = read_report(&report_path);
    let bad = component(&report, "bad");
    assert_eq!(bad["state"], "faulted");
    assert_eq!(bad["fault"], "tick: exceeded its time budget of 5 ms");
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
        stderr.contains(
            "failed to start component 'stubborn': init() failed: refusing to start, as asked"
        ),
        "{stderr}"
    );
}
