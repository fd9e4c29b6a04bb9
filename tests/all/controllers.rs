//! Real motor controllers: the WASM translators in guest-components/rust
//! (translator-create2, translator-roboclaw, translator-odrive), checked
//! against implementations no one here wrote.
//!
//! - iRobot Create 2 and Basicmicro RoboClaw: the built `subsume` binary
//!   drives a pseudo-terminal whose far end is a Python peer
//!   (tests/python/create2_peer.py, roboclaw_peer.py) built on the PyPI
//!   packages pycreate2 0.8.0 and basicmicro 2.0.10: every byte the host
//!   sends must be what those packages write, and the sensor answers the
//!   peers build with them must come back as the right pose, bumper and
//!   battery.
//! - ODrive: the published ASCII protocol document (odriverobotics/ODrive,
//!   docs/ascii-protocol.md, firmware 0.5: https://docs.odriverobotics.com/
//!   v/0.5.6/ascii-protocol.html); the fixtures are its examples.
//! - The demo runs "as a Create 2" (config/demo-create2.xml).

use std::io::{BufRead, BufReader, Read};
use std::path::Path;
use std::process::{Child, ChildStdout, Command, Output, Stdio};
use std::time::Duration;

use serde_json::Value as Json;
use subsume::contract::Param;
use subsume::contract::control::ControlCommand;
use subsume::robot::protocol::Feedback;
use subsume::robot::translator::Translator;
use subsume::sandbox::{GuestLimits, Sandbox, WasmTranslator};

use crate::support::{self, FREE_TELEOP_PORTS, PASS_ENVELOPE, component, read_report, sandbox, subsume, text};

/// A Python peer on its pseudo-terminal: the device path it printed and
/// its process.
struct Peer {
    child: Child,
    stdout: BufReader<ChildStdout>,
    device: String,
}

impl Peer {
    fn start(script: &str, args: &[String]) -> Peer {
        let mut child = Command::new(support::python())
            .current_dir(support::repo_root().join("tests/python"))
            .arg(script)
            .args(args)
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .spawn()
            .unwrap();
        let mut stdout = BufReader::new(child.stdout.take().unwrap());
        let mut device = String::new();
        stdout.read_line(&mut device).unwrap();
        assert!(device.starts_with("/dev/"), "the peer printed no device: {device:?}");
        Peer { child, stdout, device: device.trim().to_string() }
    }

    /// Closes the peer's stdin (the run is over) and reads its summary.
    fn finish(mut self) -> Json {
        drop(self.child.stdin.take());
        let mut rest = String::new();
        self.stdout.read_to_string(&mut rest).unwrap();
        assert!(self.child.wait().unwrap().success(), "the peer failed: {rest}");
        serde_json::from_str(rest.lines().last().unwrap_or_default()).unwrap_or_else(|e| panic!("{e}: {rest}"))
    }
}

/// Runs `robot` (XML) for `seconds` with its report in `dir`.
fn run_robot(dir: &Path, robot: &str, seconds: &str) -> (Output, Json) {
    let path = dir.join("robot.xml");
    std::fs::write(&path, robot).unwrap();
    let report = dir.join("report.json");
    let output = subsume()
        .args(["run", path.to_str().unwrap(), "--duration", seconds, "--report", report.to_str().unwrap()])
        .output()
        .unwrap();
    assert!(output.status.success(), "{}", text(&output.stderr));
    let report = read_report(&report);
    (output, report)
}

/// A robot file: a serial link on `device` with `translator` and its
/// `options`, one source driving `command`, and log sinks on every output.
fn driving_robot(device: &str, translator: &str, options: &str, wheel_base: &str, command: &str) -> String {
    format!(
        r#"<robot name="controller">
  <platform name="control">
    <component name="motors" source="builtin:serial" rate="100">
      <param name="device" value="{device}"/>
      <param name="baud" value="115200"/>
      <param name="translator" value="{}"/>
      <param name="options" value="{options}"/>
      <param name="wheel-base" value="{wheel_base}"/>
      <param name="watchdog" value="0.5"/>
    </component>
    <component name="driver" source="builtin:publish" rate="10" priority="1">
      <param name="kind" value="command"/>
      <param name="value" value="{command}"/>
    </component>
    <component name="arbiter" source="builtin:arbiter" rate="20"/>
    {PASS_ENVELOPE}
    <component name="pose-log" source="builtin:log" rate="0"><param name="interval" value="0"/></component>
    <component name="ranges-log" source="builtin:log" rate="0"><param name="interval" value="0"/></component>
    <component name="bumper-log" source="builtin:log" rate="0"><param name="interval" value="0"/></component>
    <component name="battery-log" source="builtin:log" rate="0"><param name="interval" value="0"/></component>
    <component name="fault-log" source="builtin:log" rate="0"><param name="interval" value="0"/></component>
    <connect from="driver.out" to="arbiter.commands"/>
    <connect from="arbiter.cmd" to="envelope.cmd"/>
    <connect from="envelope.cmd" to="motors.cmd"/>
    <connect from="motors.pose" to="pose-log.in"/>
    <connect from="motors.ranges" to="ranges-log.in"/>
    <connect from="motors.bumper" to="bumper-log.in"/>
    <connect from="motors.battery" to="battery-log.in"/>
    <connect from="motors.fault" to="fault-log.in"/>
  </platform>
</robot>"#,
        support::guest(translator).display()
    )
}

/// What log sink `name` received, in order (the text after "received ").
fn logged(stderr: &str, name: &str) -> Vec<String> {
    stderr
        .lines()
        .filter(|line| line.contains(&format!("component={name}")) || line.contains(&format!("{name}:")))
        .filter_map(|line| line.split("received ").nth(1))
        .map(|rest| rest.split(" component=").next().unwrap_or(rest).trim().to_string())
        .collect()
}

/// The numbers of a logged `vector [a, b, c]`.
fn vector(entry: &str) -> Vec<f64> {
    let inner = entry.trim_start_matches("vector [").trim_end_matches(']');
    inner.split(", ").map(|x| x.parse().unwrap()).collect()
}

fn hex(json: &Json) -> Vec<u8> {
    let text = json.as_str().unwrap();
    (0..text.len()).step_by(2).map(|i| u8::from_str_radix(&text[i..i + 2], 16).unwrap()).collect()
}

#[test]
fn a_create2_gets_pycreate2s_bytes_and_its_sensor_stream_comes_back_as_pose_bumper_battery_and_ranges() {
    // VEL 0.2 0.5 on a 0.235 m base: left 141 mm/s, right 259 mm/s.
    let peer = Peer::start("create2_peer.py", &["141".into(), "259".into()]);
    let dir = tempfile::tempdir().unwrap();
    let robot = driving_robot(&peer.device, "translator-create2", "light-bump-range=2.0", "0.235", "VEL 0.2 0.5");
    let (output, report) = run_robot(dir.path(), &robot, "2");
    let summary = peer.finish();
    let stderr = text(&output.stderr);
    let refs = &summary["references"];
    let received = hex(&summary["received"]);

    // Opening: pycreate2's Start and Safe, then Stream (148) of bumps (7),
    // voltage (22), encoder counts (43, 44) and light bumps (46-51).
    let mut opening = hex(&refs["start"]);
    opening.extend(hex(&refs["safe"]));
    opening.extend([148, 10, 7, 22, 43, 44, 46, 47, 48, 49, 50, 51]);
    assert!(received.starts_with(&opening), "{}", summary["received"]);
    // Closing: the final STOP (drive_direct(0, 0)), Pause Stream, pycreate2's Stop.
    let mut closing = hex(&refs["halt"]);
    closing.extend([150, 0]);
    closing.extend(hex(&refs["stop_oi"]));
    assert!(received.ends_with(&closing), "{}", summary["received"]);
    // In between, only pycreate2's drive_direct(259, 141) and (0, 0).
    let (drive, halt) = (hex(&refs["drive"]), hex(&refs["halt"]));
    let middle = &received[opening.len()..received.len() - closing.len()];
    assert_eq!(middle.len() % 5, 0, "{}", summary["received"]);
    let frames: Vec<&[u8]> = middle.chunks(5).collect();
    assert!(frames.iter().all(|f| *f == drive.as_slice() || *f == halt.as_slice()), "{frames:?}");
    assert!(frames.iter().filter(|f| **f == drive.as_slice()).count() >= 10, "{frames:?}");
    assert_eq!(summary["unparsed"], 0);

    // The stream decoded: the host's last pose is one the peer's own dead
    // reckoning reached (the log shows three decimals).
    let poses = logged(&stderr, "pose-log");
    let last = vector(poses.last().expect("no pose was logged"));
    let peer_poses = summary["poses"].as_array().unwrap();
    let close = |p: &Json| (0..3).all(|i| (p[i].as_f64().unwrap() - last[i]).abs() < 2e-3);
    assert!(peer_poses.iter().any(close), "host pose {last:?} is none of the peer's");
    assert!(last[0].hypot(last[1]) > 0.15 && last[2] > 0.3, "the robot hardly moved: {last:?}");
    // Pressed from 0.3 s to 0.6 s of the stream, released before and after.
    let bumper = logged(&stderr, "bumper-log");
    assert!(bumper.iter().any(|b| b == "flag true") && bumper.last().map(String::as_str) == Some("flag false"));
    assert!(logged(&stderr, "battery-log").iter().all(|b| b == "scalar 14.400"));
    // Light bumps, right to left, as 2.0 m * (1 - signal / 4095).
    let signals = summary["light_bumps"].as_array().unwrap();
    let expected: Vec<f64> = signals.iter().rev().map(|s| 2.0 * (1.0 - s.as_f64().unwrap() / 4095.0)).collect();
    let ranges = vector(logged(&stderr, "ranges-log").last().expect("no ranges were logged"));
    assert!(ranges.iter().zip(&expected).all(|(a, b)| (a - b).abs() < 1e-3), "{ranges:?} vs {expected:?}");

    let serial = &report["serial"];
    assert_eq!((serial["openings_written"].as_u64(), serial["malformed_feedback"].as_u64()), (Some(1), Some(0)));
    assert_eq!(component(&report, "motors")["errors"], 0);
}

/// A pose by dead reckoning from encoder readings (left, right counts).
fn dead_reckon(readings: &[Json], counts_per_metre: f64, wheel_base: f64) -> Vec<[f64; 3]> {
    let mut pose = [0.0f64; 3];
    let mut poses = vec![pose];
    for pair in readings.windows(2) {
        let travel = |i: usize| {
            let diff = (pair[1][i].as_u64().unwrap() as u32).wrapping_sub(pair[0][i].as_u64().unwrap() as u32);
            f64::from(diff as i32) / counts_per_metre
        };
        let (left, right) = (travel(0), travel(1));
        let turn = (right - left) / wheel_base;
        let mid = pose[2] + turn / 2.0;
        pose = [pose[0] + (left + right) / 2.0 * mid.cos(), pose[1] + (left + right) / 2.0 * mid.sin(), pose[2] + turn];
        poses.push(pose);
    }
    poses
}

#[test]
fn a_roboclaw_that_answers_late_is_not_flooded_with_reads_and_no_answer_is_taken_for_garbage() {
    // Every answer leaves 0.4 s after its request: eight 50 ms polls would
    // be outstanding. The translator keeps at most four reads in flight
    // (it skips polls meanwhile), so every answer is expected when it comes.
    // Before, it kept polling and the answers past the fourth were counted
    // as malformed (seen on a busy machine with a prompt peer, too).
    let peer = Peer::start("roboclaw_peer.py", &["128".into(), "250".into(), "550".into(), "0.4".into()]);
    let dir = tempfile::tempdir().unwrap();
    let robot =
        driving_robot(&peer.device, "translator-roboclaw", "counts-per-metre=2000 poll-ms=50", "0.3", "VEL 0.2 0.5");
    let (_output, report) = run_robot(dir.path(), &robot, "3");
    let summary = peer.finish();
    let serial = &report["serial"];
    assert_eq!(serial["malformed_feedback"], 0, "{serial}");
    // Polling freely would send 60 reads in 3 s; four per 0.4 s round trip
    // is about 30.
    let (polls, reads) = (serial["polls_sent"].as_u64().unwrap(), summary["reads"].as_u64().unwrap());
    assert!(polls <= 40 && reads >= 8, "{polls} reads sent, {reads} received by the controller");
    assert!(serial["feedback_messages"].as_u64().unwrap() >= 8, "the odometry still flows: {serial}");
}

#[test]
fn a_roboclaw_gets_basicmicros_bytes_its_acks_are_taken_its_encoders_become_odometry_and_its_battery_is_read() {
    // VEL 0.2 0.5 on a 0.3 m base at 2000 counts/m: M1 (left) 250, M2 550.
    let peer = Peer::start("roboclaw_peer.py", &["128".into(), "250".into(), "550".into()]);
    let dir = tempfile::tempdir().unwrap();
    let robot =
        driving_robot(&peer.device, "translator-roboclaw", "counts-per-metre=2000 poll-ms=50", "0.3", "VEL 0.2 0.5");
    let (output, report) = run_robot(dir.path(), &robot, "2");
    let summary = peer.finish();
    let stderr = text(&output.stderr);
    let refs = &summary["references"];
    let received = hex(&summary["received"]);
    let (drive, halt, read) = (hex(&refs["drive"]), hex(&refs["halt"]), hex(&refs["read"]));
    let (battery, status) = (hex(&refs["battery"]), hex(&refs["status"]));

    // Every byte is one of basicmicro's SpeedM1M2(128, 250, 550),
    // SpeedM1M2(128, 0, 0), GetEncoders(128), ReadMainBatteryVoltage(128)
    // or ReadError(128); the last is the STOP.
    let mut rest = received.as_slice();
    let (mut drives, mut reads, mut battery_reads, mut status_reads) = (0, 0, 0, 0);
    while !rest.is_empty() {
        if rest.starts_with(&battery) {
            battery_reads += 1;
            rest = &rest[battery.len()..];
            continue;
        }
        if rest.starts_with(&status) {
            status_reads += 1;
            rest = &rest[status.len()..];
            continue;
        }
        if rest.starts_with(&drive) {
            drives += 1;
            rest = &rest[drive.len()..];
        } else if rest.starts_with(&halt) {
            rest = &rest[halt.len()..];
        } else if rest.starts_with(&read) {
            reads += 1;
            rest = &rest[read.len()..];
        } else {
            panic!("bytes basicmicro would not send: {rest:02x?}");
        }
    }
    assert!(received.ends_with(&halt), "{}", summary["received"]);
    assert!(drives >= 10 && reads >= 10, "{drives} drives, {reads} reads");
    assert_eq!((summary["bad_crc"].as_u64(), summary["unparsed"].as_u64()), (Some(0), Some(0)));
    assert_eq!(summary["reads"].as_u64(), Some(reads), "every read was answered");
    // One poll in ten reads the battery, the first among them.
    assert_eq!(summary["battery_reads"].as_u64(), Some(battery_reads), "every battery read was answered");
    assert!(battery_reads >= 1 && battery_reads <= reads / 8 + 1, "{battery_reads} battery reads, {reads} reads");
    // And one in ten its status (the sixth among them).
    assert_eq!(summary["status_reads"].as_u64(), Some(status_reads), "every status read was answered");
    assert!(status_reads >= 1 && status_reads <= reads / 8 + 1, "{status_reads} status reads, {reads} reads");
    assert!(summary["writes"].as_u64().unwrap() >= drives);

    // Every ACK, encoder and battery answer decoded cleanly; the battery
    // basicmicro reads as 124 tenths is 12.4 V on the host.
    let serial = &report["serial"];
    assert_eq!(serial["malformed_feedback"], 0, "{serial}");
    assert_eq!(serial["battery_v"].as_f64(), Some(12.4), "{serial}");
    assert!(serial["polls_sent"].as_u64().unwrap() >= 10, "{serial}");
    // Its status reads no error or warning: no fault, on the status and
    // the `fault` port.
    assert_eq!(serial["fault"], Json::Null, "{serial}");
    assert!(decoded_but_the_last(serial["fault_readings"].as_u64().unwrap(), status_reads), "{serial}");
    assert!(logged(&stderr, "fault-log").iter().all(|f| f == "text \"\""), "{stderr}");
    // The host's last pose is the dead reckoning of a prefix of the answers.
    let last = vector(logged(&stderr, "pose-log").last().expect("no pose was logged"));
    let readings = summary["readings"].as_array().unwrap();
    let expected = dead_reckon(readings, 2000.0, 0.3);
    let close = |p: &[f64; 3]| (0..3).all(|i| (p[i] - last[i]).abs() < 2e-3);
    assert!(expected.iter().any(close), "host pose {last:?} is none of {expected:?}");
    assert!(last[0].hypot(last[1]) > 0.15, "the robot hardly moved: {last:?}");
}

/// Issue 40: a RoboClaw whose status (command 90, read as basicmicro's
/// ReadError reads it) has an error and a warning set is in fault: the
/// link's status names both bits as the RoboClaw manual does, the `fault`
/// port carries the same text, and the log says so once.
#[test]
fn a_roboclaw_whose_status_has_an_error_and_a_warning_set_reports_the_fault_by_name() {
    // M2 current error (0x2000) and M1 over current warning (0x10000).
    let args = ["128", "250", "550", "0", "0x00012000"].map(String::from);
    let peer = Peer::start("roboclaw_peer.py", &args);
    let dir = tempfile::tempdir().unwrap();
    let robot =
        driving_robot(&peer.device, "translator-roboclaw", "counts-per-metre=2000 poll-ms=50", "0.3", "VEL 0.2 0.5");
    let (output, report) = run_robot(dir.path(), &robot, "2");
    let summary = peer.finish();
    let stderr = text(&output.stderr);
    assert_eq!((summary["bad_crc"].as_u64(), summary["unparsed"].as_u64()), (Some(0), Some(0)), "{summary}");
    let status_reads = summary["status_reads"].as_u64().unwrap();
    assert!(status_reads >= 1, "{summary}");
    let serial = &report["serial"];
    assert_eq!(serial["malformed_feedback"], 0, "{serial}");
    let fault = "m2 current error, m1 over current warning";
    assert_eq!(serial["fault"], fault, "{serial}");
    let readings = serial["fault_readings"].as_u64().unwrap();
    assert!(decoded_but_the_last(readings, status_reads), "{status_reads} status reads: {serial}");
    let told = logged(&stderr, "fault-log");
    // (The log sink shortens long texts.)
    assert!(told.last().is_some_and(|t| t.starts_with("text \"m2 current error, m1 over current")), "{stderr}");
    assert!(decoded_but_the_last(told.len() as u64, readings), "{readings} readings: {told:?}");
    let warned = stderr.lines().filter(|l| l.contains("the motor controller reports a fault: ")).count();
    assert_eq!(warned, 1, "said once, not at every reading: {stderr}");
}

/// Whether the host got every one of `sent` (status replies the
/// controller sent, or readings the link decoded) but the last, which may
/// still have been on its way when the run ended (a fresh-clone run
/// decoded 3 of the 4 status replies the controller sent).
fn decoded_but_the_last(decoded: u64, sent: u64) -> bool {
    decoded == sent || decoded + 1 == sent
}

fn translator(sandbox: &Sandbox, name: &str, params: &[(&str, &str)]) -> WasmTranslator {
    let bytes = std::fs::read(support::guest(name)).unwrap();
    let artifact = sandbox.load_translator(&bytes).unwrap();
    let params: Vec<Param> =
        params.iter().map(|(name, value)| Param { name: name.to_string(), value: value.to_string() }).collect();
    let limits = GuestLimits { memory_bytes: 16 << 20, budget: Duration::from_millis(50), ..GuestLimits::default() };
    sandbox.instantiate_translator(&artifact, "motors", &limits, &params).unwrap()
}

fn encode(translator: &mut WasmTranslator, command: &str) -> String {
    let mut out = Vec::new();
    Translator::encode(translator, &command.parse::<ControlCommand>().unwrap(), &mut out).unwrap();
    text(&out)
}

fn poll(translator: &mut WasmTranslator) -> String {
    let mut out = Vec::new();
    Translator::poll(translator, 0, &mut out).unwrap();
    text(&out)
}

fn decode(translator: &mut WasmTranslator, bytes: &[u8]) -> Vec<Feedback> {
    let mut out = Vec::new();
    Translator::decode(translator, bytes, &mut out).unwrap();
    out
}

#[test]
fn odrive_lines_follow_the_ascii_protocol_document() {
    let sandbox = sandbox();
    let params = [("wheel-base", "0.3"), ("max-wheel-speed", "2"), ("turns-per-metre", "1")];
    let mut odrive = translator(&sandbox, "translator-odrive", &params);
    // "Motor Velocity command: v motor velocity torque_ff ... Example: v 0 1 0"
    // (torque_ff is optional and omitted): 1 m/s is 1 turn/s on each wheel.
    assert_eq!(encode(&mut odrive, "VEL 1 0"), "v 0 1\nv 1 1\n");
    assert_eq!(encode(&mut odrive, "VEL -0.25 0"), "v 0 -0.25\nv 1 -0.25\n");
    // Turning on the spot at 1 rad/s: wheels -/+ 0.15 m/s.
    assert_eq!(encode(&mut odrive, "VEL 0 1"), "v 0 -0.15\nv 1 0.15\n");
    assert_eq!(encode(&mut odrive, "STOP"), "v 0 0\nv 1 0\n");
    // "Update motor watchdog: u motor"; "Request feedback: f motor";
    // parameter reading "r vbus_voltage" on the first poll.
    assert_eq!(poll(&mut odrive), "u 0\nu 1\nf 0\nf 1\nr vbus_voltage\n");
    assert_eq!(poll(&mut odrive), "u 0\nu 1\nf 0\nf 1\n");
    // "response: pos vel" per axis; "r vbus_voltage => response: 24.087744".
    let feedback = decode(&mut odrive, b"0 0\n0 0\n24.087744\n");
    assert_eq!(feedback[0], Feedback::Odometry { x: 0.0, y: 0.0, heading: 0.0 });
    assert_eq!(feedback[1], Feedback::Battery(24.087744));
    // The second poll's answers: both wheels 0.5 turns on: 0.5 m ahead.
    assert_eq!(decode(&mut odrive, b"0.5 1.2\n0.5 1.2\n"), vec![Feedback::Odometry { x: 0.5, y: 0.0, heading: 0.0 }]);
    // What the ODrive says to a bad line is not feedback.
    assert_eq!(decode(&mut odrive, b"invalid command format\n"), vec![]);
    assert_eq!(Translator::malformed(&odrive), 1);
    // Arming: closed-loop velocity control on opening, idle on closing.
    let plan = Translator::plan(&odrive);
    assert_eq!(
        text(&plan.opening),
        "w axis0.controller.config.control_mode 2\nw axis1.controller.config.control_mode 2\n\
         w axis0.requested_state 8\nw axis1.requested_state 8\n"
    );
    assert_eq!(text(&plan.closing), "w axis0.requested_state 1\nw axis1.requested_state 1\n");
    assert_eq!(plan.poll_period_ns, 100_000_000);
}

/// Issue 40: every tenth poll, from the sixth, reads both axes' errors
/// (`r axis0.error`, `r axis1.error`: "r property => response: value" in
/// the ASCII protocol document); a bit set is the controller's fault, named
/// as the firmware's AxisError names it, and both clear is no fault.
#[test]
fn odrive_axis_errors_are_read_and_a_set_bit_is_the_controllers_fault_by_name() {
    let sandbox = sandbox();
    let params = [("wheel-base", "0.3"), ("max-wheel-speed", "2"), ("turns-per-metre", "1")];
    let mut odrive = translator(&sandbox, "translator-odrive", &params);
    // One poll, answered as an ODrive standing still with these axis
    // errors answers it: the feedback and whether the poll read the errors.
    let step = |odrive: &mut WasmTranslator, errors: [&str; 2]| {
        let asked = poll(odrive);
        let answers: String = asked
            .lines()
            .filter_map(|line| match line {
                "f 0" | "f 1" => Some("0 0\n".to_string()),
                "r vbus_voltage" => Some("24\n".to_string()),
                "r axis0.error" => Some(format!("{}\n", errors[0])),
                "r axis1.error" => Some(format!("{}\n", errors[1])),
                _ => None,
            })
            .collect();
        (decode(odrive, answers.as_bytes()), asked.contains("r axis0.error\nr axis1.error\n"))
    };
    for _ in 0..5 {
        let (feedback, read) = step(&mut odrive, ["0", "0"]);
        assert!(!read && !feedback.iter().any(|f| matches!(f, Feedback::Fault(_))), "{feedback:?}");
    }
    // The sixth poll reads them: motor failed (0x40) and encoder failed
    // (0x100) on axis 0, a bit the firmware's list lacks on axis 1.
    let (feedback, read) = step(&mut odrive, ["320", "1073741824"]);
    assert!(read);
    let fault = "axis0: motor failed, encoder failed; axis1: error bits 0x40000000";
    assert_eq!(feedback.last(), Some(&Feedback::Fault(Some(fault.into()))), "{feedback:?}");
    // Ten polls on, read again: both clear is no fault.
    for _ in 0..9 {
        assert!(!step(&mut odrive, ["0", "0"]).1);
    }
    let (feedback, read) = step(&mut odrive, ["0", "0"]);
    assert!(read);
    assert_eq!(feedback.last(), Some(&Feedback::Fault(None)), "{feedback:?}");
    assert_eq!(Translator::malformed(&odrive), 0);
    // An error that is no bit mask is garbage, not a fault.
    for _ in 0..9 {
        step(&mut odrive, ["0", "0"]);
    }
    let (feedback, read) = step(&mut odrive, ["-1", "0"]);
    assert!(read);
    assert_eq!(Translator::malformed(&odrive), 1);
    assert_eq!(feedback.last(), Some(&Feedback::Fault(None)), "axis1's clear answer: {feedback:?}");
}

/// Issue 40, end to end: an ODrive played on a pseudo-terminal (answering
/// as the ASCII protocol document says: `pos vel` to `f`, a value to `r`)
/// whose axis 0 has "motor failed" set: the built binary's link reports the
/// fault by name in its status, and the `fault` port carries it.
#[test]
fn an_odrive_whose_axis_has_an_error_set_is_in_fault_on_the_links_status() {
    use std::sync::atomic::{AtomicBool, Ordering};
    let (mut odrive, _slave, device) = support::MotorRecorder::new();
    let going = std::sync::Arc::new(AtomicBool::new(true));
    let playing = going.clone();
    let player = std::thread::spawn(move || {
        let mut answered = 0;
        let mut asked = Vec::new();
        while playing.load(Ordering::Relaxed) {
            odrive.read();
            let new: Vec<String> = odrive.lines[answered..].iter().map(|(_, line)| line.clone()).collect();
            answered = odrive.lines.len();
            for line in new {
                asked.push(line.clone());
                let answer = match line.as_str() {
                    "f 0" | "f 1" => "0 0\n",
                    "r vbus_voltage" => "24.1\n",
                    "r axis0.error" => "64\n",
                    "r axis1.error" => "0\n",
                    _ => continue,
                };
                odrive.write(answer.as_bytes());
            }
        }
        asked
    });
    let dir = tempfile::tempdir().unwrap();
    let robot = driving_robot(&device, "translator-odrive", "turns-per-metre=1 poll-ms=20", "0.3", "VEL 0 0");
    let (output, report) = run_robot(dir.path(), &robot, "2");
    going.store(false, Ordering::Relaxed);
    let asked = player.join().unwrap();
    let stderr = text(&output.stderr);
    let reads = asked.iter().filter(|l| *l == "r axis0.error").count();
    assert!(reads >= 1, "the axes' errors were never read: {asked:?}");
    assert_eq!(asked.iter().filter(|l| *l == "r axis1.error").count(), reads, "{asked:?}");
    let serial = &report["serial"];
    assert_eq!(serial["fault"], "axis0: motor failed", "{serial}");
    assert!(serial["fault_readings"].as_u64().unwrap() >= 1, "{serial}");
    assert_eq!(serial["battery_v"].as_f64(), Some(24.1), "{serial}");
    let told = logged(&stderr, "fault-log");
    assert!(told.iter().any(|t| t == "text \"axis0: motor failed\""), "{stderr}");
}

/// Found by the `translator_odrive` fuzz target (fuzz/regressions/translator_odrive):
/// positions 2e308 turns apart made the travel infinite and every later
/// pose NaN. Such a step is now malformed and the pose stays a number.
#[test]
fn odrive_positions_too_far_apart_for_a_number_are_malformed_and_the_pose_stays_finite() {
    let sandbox = sandbox();
    let params = [("wheel-base", "0.3"), ("max-wheel-speed", "2"), ("turns-per-metre", "1")];
    let mut odrive = translator(&sandbox, "translator-odrive", &params);
    for _ in 0..3 {
        poll(&mut odrive);
    }
    assert_eq!(decode(&mut odrive, b"1e308 0\n1e308 0\n"), vec![Feedback::Odometry { x: 0.0, y: 0.0, heading: 0.0 }]);
    assert_eq!(decode(&mut odrive, b"-1e308 0\n-1e308 0\n"), vec![]);
    assert_eq!(Translator::malformed(&odrive), 1);
    // The next step starts from the refused positions, the pose from where
    // it was.
    assert_eq!(decode(&mut odrive, b"-1e308 0\n-1e308 0\n"), vec![Feedback::Odometry { x: 0.0, y: 0.0, heading: 0.0 }]);
}

#[test]
fn odrive_checksums_are_the_documents_and_bad_ones_are_refused() {
    let sandbox = sandbox();
    let params = [("turns-per-metre", "2"), ("checksum", "on"), ("arm", "no"), ("left-sign", "-1")];
    let mut odrive = translator(&sandbox, "translator-odrive", &params);
    // "Example of a valid checksum: r vbus_voltage *93".
    assert!(poll(&mut odrive).ends_with("r vbus_voltage *93\n"));
    // The left motor is mirrored: its velocity is negated.
    let line = encode(&mut odrive, "VEL 0.5 0");
    assert_eq!(line, format!("v 0 -1 *{}\nv 1 1 *{}\n", xor("v 0 -1 "), xor("v 1 1 ")));
    // Answers carry a checksum too; a wrong one makes the line garbage.
    let good = format!("0 0 *{}\n", xor("0 0 "));
    assert_eq!(decode(&mut odrive, format!("{good}{good}").as_bytes()).len(), 1);
    assert_eq!(decode(&mut odrive, b"24.1 *0\n"), vec![]);
    assert_eq!(Translator::malformed(&odrive), 1);
    let plan = Translator::plan(&odrive);
    assert!(plan.opening.is_empty() && plan.closing.is_empty());
}

fn xor(text: &str) -> u8 {
    text.bytes().fold(0, |x, b| x ^ b)
}

/// A Create 2 stream frame of `packets` (id, data...), with its checksum.
fn create2_frame(packets: &[u8]) -> Vec<u8> {
    let mut frame = vec![19, packets.len() as u8];
    frame.extend_from_slice(packets);
    let sum = frame.iter().fold(0u8, |s, b| s.wrapping_add(*b));
    frame.push(0u8.wrapping_sub(sum));
    frame
}

#[test]
fn create2_counts_wrap_garbage_is_skipped_and_a_silent_stream_is_asked_for_again() {
    let sandbox = sandbox();
    let mut create2 = translator(&sandbox, "translator-create2", &[("wheel-base", "0.235"), ("origin-x", "1")]);
    let plan = Translator::plan(&create2);
    let opening = vec![128, 131, 148, 10, 7, 22, 43, 44, 46, 47, 48, 49, 50, 51];
    assert_eq!(
        (plan.opening.clone(), plan.closing.clone(), plan.poll_period_ns),
        (opening.clone(), vec![150, 0, 173], 1_000_000_000)
    );
    // Right 0.3 m/s then left -0.1 m/s, big-endian mm/s; STOP is zeros.
    assert_eq!(encode_bytes(&mut create2, "VEL 0.1 1.7021"), [145, 0x01, 0x2C, 0xFF, 0x9C]);
    assert_eq!(encode_bytes(&mut create2, "STOP"), [145, 0, 0, 0, 0]);
    // Counts just below the wrap, then 2 past it on both wheels: forward
    // 2 counts, from the origin option.
    let first = create2_frame(&[43, 0xFF, 0xFF, 44, 0xFF, 0xFF]);
    let second = create2_frame(&[43, 0x00, 0x01, 44, 0x00, 0x01]);
    let mut bytes = b"\x13garbage".to_vec();
    bytes.extend(&first);
    bytes.extend([19, 6, 43, 0, 0, 44, 0, 0, 0x99]); // a bad checksum
    bytes.extend(&second);
    let mut feedback = Vec::new();
    // In chunks of three bytes: frames straddle the calls.
    for chunk in bytes.chunks(3) {
        feedback.extend(decode(&mut create2, chunk));
    }
    let step = 2.0 * std::f64::consts::PI * 0.072 / 508.8;
    assert_eq!(feedback[0], Feedback::Odometry { x: 1.0, y: 0.0, heading: 0.0 });
    let Feedback::Odometry { x, y, heading } = feedback[1] else { panic!("{feedback:?}") };
    assert!((x - 1.0 - step).abs() < 1e-12 && y == 0.0 && heading == 0.0, "{feedback:?}");
    assert_eq!(feedback.len(), 2);
    assert!(Translator::malformed(&create2) >= 2);
    // The first poll arms; a frame since keeps the next quiet; silence
    // until the one after asks for the stream again.
    assert_eq!(poll_bytes(&mut create2), b"");
    decode(&mut create2, &first);
    assert_eq!(poll_bytes(&mut create2), b"");
    assert_eq!(poll_bytes(&mut create2), opening);
}

#[test]
fn roboclaw_acks_encoder_and_battery_answers_are_told_apart() {
    let sandbox = sandbox();
    let params = [("wheel-base", "0.3"), ("counts-per-metre", "1000"), ("address", "129")];
    let mut claw = translator(&sandbox, "translator-roboclaw", &params);
    // The first poll of ten reads the main battery: 12.4 V, byte by byte.
    assert_eq!(poll_bytes(&mut claw), [129, 24]);
    let mut volts = vec![129, 24, 0, 124];
    volts.extend(crc16(&volts).to_be_bytes());
    let mut feedback = Vec::new();
    for byte in &volts[2..] {
        feedback.extend(decode(&mut claw, std::slice::from_ref(byte)));
    }
    assert_eq!(feedback, vec![Feedback::Battery(12.4)]);
    assert_eq!(poll_bytes(&mut claw), [129, 78]);
    // An ACK, then the answer: counters -1 and -1 (they start with FF).
    let answer = |m1: i32, m2: i32| {
        let mut data = vec![129, 78];
        data.extend(m1.to_be_bytes());
        data.extend(m2.to_be_bytes());
        let crc = crc16(&data);
        data.extend(crc.to_be_bytes());
        data.split_off(2)
    };
    let mut bytes = vec![0xFF];
    bytes.extend(answer(-1, -1));
    // Byte by byte: the decoder waits for a whole answer before taking FF.
    let mut feedback = Vec::new();
    for byte in &bytes {
        feedback.extend(decode(&mut claw, std::slice::from_ref(byte)));
    }
    assert_eq!(feedback, vec![Feedback::Odometry { x: 0.0, y: 0.0, heading: 0.0 }]);
    // Backwards 100 counts on both: 0.1 m back; then an ACK alone.
    assert_eq!(poll_bytes(&mut claw), [129, 78]);
    let mut bytes = answer(-101, -101);
    bytes.push(0xFF);
    assert_eq!(decode(&mut claw, &bytes), vec![Feedback::Odometry { x: -0.1, y: 0.0, heading: 0.0 }]);
    // An answer with a bad CRC is garbage, not odometry.
    assert_eq!(poll_bytes(&mut claw), [129, 78]);
    let mut bad = answer(5, 5);
    bad[9] ^= 1;
    assert_eq!(decode(&mut claw, &bad), vec![]);
    assert_eq!(Translator::malformed(&claw), 1);
    // Mixed speed with the CRC basicmicro computes (the PTY test checks
    // the same bytes against basicmicro itself).
    let mut expected = vec![129, 37, 0, 0, 0, 100, 0, 0, 0, 100];
    expected.extend(crc16(&expected).to_be_bytes());
    assert_eq!(encode_bytes(&mut claw, "VEL 0.1 0"), expected);
}

/// CRC16-CCITT (XModem), as Basicmicro documents it.
fn crc16(bytes: &[u8]) -> u16 {
    bytes.iter().fold(0u16, |crc, byte| {
        (0..8).fold(crc ^ (u16::from(*byte) << 8), |c, _| if c & 0x8000 != 0 { (c << 1) ^ 0x1021 } else { c << 1 })
    })
}

fn encode_bytes(translator: &mut WasmTranslator, command: &str) -> Vec<u8> {
    let mut out = Vec::new();
    Translator::encode(translator, &command.parse::<ControlCommand>().unwrap(), &mut out).unwrap();
    out
}

fn poll_bytes(translator: &mut WasmTranslator) -> Vec<u8> {
    let mut out = Vec::new();
    Translator::poll(translator, 0, &mut out).unwrap();
    out
}

#[test]
fn translators_refuse_missing_or_bad_options_at_init() {
    let sandbox = sandbox();
    let bytes = std::fs::read(support::guest("translator-roboclaw")).unwrap();
    let artifact = sandbox.load_translator(&bytes).unwrap();
    let limits = GuestLimits { memory_bytes: 16 << 20, budget: Duration::from_millis(50), ..GuestLimits::default() };
    let start = |name: &str, value: &str| {
        let params = vec![Param { name: name.into(), value: value.into() }];
        sandbox.instantiate_translator(&artifact, "motors", &limits, &params).err().map(|e| e.to_string())
    };
    assert!(start("address", "128").unwrap().contains("counts-per-metre' is required"));
    assert!(start("counts-per-metre", "-3").unwrap().contains("must be positive"));
}

#[test]
fn the_demo_runs_as_a_create2_and_reaches_its_goal_without_collisions() {
    let dir = tempfile::tempdir().unwrap();
    let report_path = dir.path().join("report.json");
    let output = subsume()
        // Simulated time in lock-step: the outcome depends on the robot and its
        // protocol, not on how busy the machine is (in real time the goal came
        // at 40-45 s of 50 on this machine, and later on a loaded one).
        .args(["run", "config/demo-create2.xml", "--speed", "max", "--duration", "90"])
        .args(["--report", report_path.to_str().unwrap()])
        .args(FREE_TELEOP_PORTS)
        .output()
        .unwrap();
    let log = text(&output.stderr);
    assert!(output.status.success(), "{log}");
    let report: Json = read_report(&report_path);
    assert_eq!(report["robot"], "demo-create2");
    for c in report["components"].as_array().unwrap() {
        assert_eq!(c["errors"], 0, "{c}");
    }
    let sim = &report["sim"];
    assert_eq!(sim["goal_reached"], true, "{sim}");
    assert_eq!(sim["collisions"], 0, "{sim}");
    assert_eq!(sim["malformed_messages"], 0, "{sim}");
    let serial = &report["serial"];
    assert_eq!((serial["malformed_feedback"].as_u64(), serial["openings_written"].as_u64()), (Some(0), Some(1)));
    assert!(serial["feedback_messages"].as_u64().unwrap() > 1000, "{serial}");
}
