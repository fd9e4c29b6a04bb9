#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic)]
//! Hostile components: a guest that misbehaves in each way we know is
//! stopped alone, with its reason in the report, while a healthy component
//! beside it keeps its tick rate (within 5%), and where the offender held
//! control, the motors get STOP in time. Each case runs the built binary.

#[path = "../host/tests/support/mod.rs"]
mod support;

use std::path::Path;
use std::process::{Command, Output};
use std::time::{Duration, Instant};

use serde_json::Value as Json;

fn run_robot(dir: &Path, body: &str, args: &[&str]) -> (Output, Option<Json>) {
    let mut xml = body.to_string();
    for name in ["test-counter", "test-faulty", "test-loop-describe"] {
        xml = xml.replace(&format!("GUEST({name})"), &support::guest(name).display().to_string());
    }
    let robot = dir.join("robot.xml");
    std::fs::write(&robot, xml).unwrap();
    let report = dir.join("report.json");
    let output = Command::new(env!("CARGO_BIN_EXE_subsume"))
        .current_dir(support::repo_root())
        .env("SUBSUME_HTTP", "off")
        .args(["--cache-dir", support::cache_dir().to_str().unwrap()])
        .args(args)
        .arg(&robot)
        .args(if args.first() == Some(&"run") { vec!["--report", report.to_str().unwrap()] } else { vec![] })
        .env("NO_COLOR", "1")
        .output()
        .unwrap();
    let report = std::fs::read(&report).ok().and_then(|b| serde_json::from_slice(&b).ok());
    (output, report)
}

fn component<'a>(report: &'a Json, name: &str) -> &'a Json {
    report["components"].as_array().unwrap().iter().find(|c| c["name"] == name).unwrap()
}

/// Runs test-faulty in `mode` beside a 100 Hz counter for 2 s; checks the
/// offender is stopped with a reason starting with `reason`, and the counter
/// kept its rate.
fn hostile(mode: &str, reason: &str) {
    support::guest_dir();
    let dir = tempfile::tempdir().unwrap();
    let body = format!(
        r#"<robot name="hostile">
  <platform name="control">
    <component name="bad" source="GUEST(test-faulty)" rate="50" budget="5ms" memory="16MiB">
      <param name="mode" value="{mode}"/>
      <param name="after" value="3"/>
    </component>
    <component name="feeder" source="builtin:publish" rate="20"/>
    <component name="good" source="GUEST(test-counter)" rate="100"/>
    <component name="sink" source="builtin:log" rate="0"><param name="interval" value="10"/></component>
    <connect from="feeder.out" to="bad.in"/>
    <connect from="good.count" to="sink.in"/>
  </platform>
</robot>"#
    );
    let started = Instant::now();
    let (output, report) = run_robot(dir.path(), &body, &["run", "--duration", "2"]);
    let log = String::from_utf8_lossy(&output.stderr);
    assert!(output.status.success(), "{mode}: the host must keep running:\n{log}");
    assert!(started.elapsed() < Duration::from_secs(30), "{mode}: took {:?}", started.elapsed());
    let report = report.expect("a report");
    let bad = component(&report, "bad");
    assert_eq!(bad["state"], "faulted", "{mode}: {bad}");
    let fault = bad["fault"].as_str().unwrap_or_default();
    assert!(fault.starts_with(reason), "{mode}: fault {fault:?} should start with {reason:?}");
    assert!(log.contains(&format!("component faulted and is stopped: {fault}")), "{mode}: the log says why:\n{log}");
    let good = component(&report, "good");
    assert_eq!(good["state"], "running", "{mode}");
    // 100 Hz over the run's duration (ticks at 0, 10, ... ms), within 5%.
    let expected = report["duration_s"].as_f64().unwrap() * 100.0;
    let ticks = good["ticks"].as_f64().unwrap();
    assert!(
        (ticks - expected).abs() <= expected * 0.05,
        "{mode}: the healthy counter ticked {ticks} times, expected about {expected}"
    );
}

macro_rules! hostile_cases {
    ($($name:ident: $mode:literal => $reason:literal,)*) => {
        $(
            #[test]
            fn $name() {
                hostile($mode, $reason);
            }
        )*
    };
}

hostile_cases! {
    a_trap_in_tick: "trap-on-tick" => "tick: trapped: ",
    a_panic_in_tick: "panic-on-tick" => "tick: trapped: ",
    an_endless_loop_in_tick: "loop-on-tick" => "tick: exceeded its time budget of 5 ms",
    an_endless_loop_in_on_input: "loop-on-input" => "on-input: exceeded its time budget of 5 ms",
    // A Rust guest keeps its stack in linear memory: running off its end is
    // an out-of-bounds access (wasmtime's native stack limit catches the rest).
    endless_recursion: "recurse-on-tick" => "tick: trapped: wasm trap: out of bounds memory access",
    memory_growth_without_bound: "grow-memory" => "tick: exceeded its memory limit (growing memory to ",
    an_emit_flood: "emit-flood" => "tick: emitted more than 256 values in one call (max-emits)",
    one_giant_emit: "giant-emit" => "tick: passed more data to the host in one call than its max-message allows",
    a_log_flood: "log-flood" => "tick: wrote more than 100 log lines in one second (max-logs)",
    an_out_of_range_port: "bad-port-on-tick" => "tick: emitted on output port 99, but the component declares 4 output(s)",
}

#[test]
fn files_sockets_and_the_environment_are_out_of_reach() {
    support::guest_dir();
    let dir = tempfile::tempdir().unwrap();
    let body = r#"<robot name="wasi">
  <platform name="control">
    <component name="probe" source="GUEST(test-faulty)" rate="10">
      <param name="mode" value="wasi-probe"/>
    </component>
  </platform>
</robot>"#;
    let (output, report) = run_robot(dir.path(), body, &["run", "--duration", "0.5"]);
    assert!(output.status.success());
    let probe = component(report.as_ref().unwrap(), "probe");
    assert_eq!(probe["state"], "running");
    let found = probe["last_error"].as_str().unwrap_or_default();
    assert!(found.starts_with("file: refused ("), "{found}");
    assert!(found.contains("; socket: refused ("), "{found}");
    assert!(found.ends_with("; environment: empty"), "{found}");
}

#[test]
fn endless_loops_in_describe_and_init_fail_loading_in_bounded_time() {
    support::guest_dir();
    let dir = tempfile::tempdir().unwrap();
    let describe = r#"<robot name="stuck"><platform name="control">
    <component name="stuck" source="GUEST(test-loop-describe)"/>
  </platform></robot>"#;
    let started = Instant::now();
    let (output, _) = run_robot(dir.path(), describe, &["check"]);
    assert_eq!(output.status.code(), Some(1));
    let stdout = String::from_utf8_lossy(&output.stdout);
    assert!(stdout.contains("component 'stuck': cannot load"), "{stdout}");
    assert!(stdout.contains("describe() failed: exceeded its time budget of 500 ms"), "{stdout}");
    assert!(started.elapsed() < Duration::from_secs(20));

    let init = r#"<robot name="stuck"><platform name="control">
    <component name="stuck" source="GUEST(test-faulty)"><param name="mode" value="loop-on-init"/></component>
  </platform></robot>"#;
    let started = Instant::now();
    let (output, _) = run_robot(dir.path(), init, &["run", "--duration", "1"]);
    assert_eq!(output.status.code(), Some(1));
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(
        stderr.contains("failed to start component 'stuck': init() failed: exceeded its time budget of 1000 ms"),
        "{stderr}"
    );
    assert!(started.elapsed() < Duration::from_secs(20));
}

#[test]
fn a_component_that_holds_control_and_then_loops_leaves_the_robot_stopped() {
    support::guest_dir();
    let (mut motors, _slave, device) = support::MotorRecorder::new();
    let dir = tempfile::tempdir().unwrap();
    let body = format!(
        r#"<robot name="grab">
  <platform name="control">
    <component name="motors" source="builtin:serial" rate="100">
      <param name="device" value="{device}"/>
      <param name="watchdog" value="0.3"/>
    </component>
    <component name="grabber" source="GUEST(test-faulty)" rate="20" budget="5ms" timeout="2s">
      <param name="mode" value="command-then-loop"/>
      <param name="after" value="20"/>
    </component>
    <component name="arbiter" source="builtin:arbiter" rate="50"/>
    <connect from="grabber.cmd" to="arbiter.commands"/>
    <component name="envelope" source="builtin:envelope" rate="20">
      <param name="max-speed" value="10"/><param name="max-reverse" value="10"/><param name="max-turn" value="20"/>
      <param name="max-accel" value="100"/><param name="max-turn-accel" value="100"/>
    </component>
    <connect from="arbiter.cmd" to="envelope.cmd"/>
    <connect from="envelope.cmd" to="motors.cmd"/>
  </platform>
</robot>"#
    );
    let dir_path = dir.path().to_path_buf();
    let host = std::thread::spawn(move || run_robot(&dir_path, &body, &["run", "--duration", "3"]));
    motors.read_while(|| !host.is_finished());
    let lines = motors.lines;
    let (output, report) = host.join().unwrap();
    assert!(output.status.success());
    let grabber = component(report.as_ref().unwrap(), "grabber");
    assert_eq!(grabber["fault"], "tick: exceeded its time budget of 5 ms");
    // It drove, then stopped answering while holding control (its timeout
    // is 2 s): the fault takes it out at once and STOP follows.
    let last_motion = lines.iter().rposition(|(_, l)| l == "M 300 300").expect("the grabber drove");
    let stop = lines[last_motion..].iter().find(|(_, l)| l == "S").expect("STOP reached the motors");
    let gap = stop.0.duration_since(lines[last_motion].0);
    assert!(gap < Duration::from_millis(300), "STOP {gap:?} after the last motion command");
}

#[test]
fn a_restart_policy_brings_a_faulted_component_back_until_its_restarts_run_out() {
    support::guest_dir();
    let dir = tempfile::tempdir().unwrap();
    let body = r#"<robot name="restarts">
  <platform name="control">
    <component name="flaky" source="GUEST(test-faulty)" rate="50" restart="on-failure" max-restarts="1">
      <param name="mode" value="trap-on-tick"/>
      <param name="after" value="3"/>
    </component>
  </platform>
</robot>"#;
    let (output, report) = run_robot(dir.path(), body, &["run", "--duration", "2.5"]);
    let log = String::from_utf8_lossy(&output.stderr);
    assert!(output.status.success(), "{log}");
    let flaky = component(report.as_ref().unwrap(), "flaky");
    // Fault at ~60 ms, restart after 1 s, fault again ~60 ms later; no more.
    assert_eq!(flaky["restarts"], 1, "{flaky}");
    assert_eq!(flaky["state"], "faulted", "{flaky}");
    assert_eq!(flaky["messages_out"], 6, "three good ticks in each life: {flaky}");
    assert!(log.contains("restarted (restart 1 of 1)"), "{log}");
    assert!(log.contains("no restarts left (1 used): it stays stopped"), "{log}");
}
