//! The emergency stop end to end: the built binary drives an external
//! pseudo-terminal (the motor controller) while a WASM component drives;
//! each way of engaging stops it, STOP is the last thing on the wire and
//! nothing moves until a release (docs/estop.md).

use std::io::{BufRead, BufReader, Write};
use std::process::{Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use crate::support::{self, PASS_ENVELOPE, subsume};

const TOKEN: &str = "alice-token-0123456789";

struct Host {
    _process: support::HostProcess,
    teleop: String,
    websocket: Option<String>,
    _dir: tempfile::TempDir,
}

/// `subsume run` (no portal) on a robot whose WASM driver sends `VEL 0.25
/// 0` for ever, with the motors on `device`; `arbiter_extra` goes inside
/// the arbiter, `wiring_extra` after the connections.
fn start(device: &str, arbiter_extra: &str, wiring_extra: &str) -> Host {
    start_with_teleop(device, arbiter_extra, wiring_extra, "")
}

/// [`start`], with `teleop_extra` inside the network platform's teleop.
fn start_with_teleop(device: &str, arbiter_extra: &str, wiring_extra: &str, teleop_extra: &str) -> Host {
    support::guest_dir();
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("operators"), format!("alice {TOKEN}\n")).unwrap();
    let xml = format!(
        r#"<robot name="estop">
  <platform name="network">
    <component name="teleop" source="builtin:teleop" rate="100" timeout="300ms">
      <param name="listen" value="127.0.0.1:0"/>
      <param name="operators" value="operators"/>{teleop_extra}
    </component>
  </platform>
  <platform name="control">
    <component name="driver" source="{driver}" rate="20" timeout="200ms">
      <param name="command" value="VEL 0.25 0"/>
      <param name="ticks" value="100000000"/>
    </component>
    <component name="arbiter" source="builtin:arbiter" rate="20">{arbiter_extra}</component>
    <component name="motors" source="builtin:serial" rate="100"><param name="device" value="{device}"/></component>
    {PASS_ENVELOPE}
    <connect from="driver.cmd" to="arbiter.commands"/>
    <connect from="teleop.cmd" to="arbiter.commands"/>
    <connect from="arbiter.cmd" to="envelope.cmd"/>
    <connect from="envelope.cmd" to="motors.cmd"/>
    {wiring_extra}
  </platform>
</robot>"#,
        driver = support::guest("test-commander").display()
    );
    let robot = dir.path().join("robot.xml");
    std::fs::write(&robot, xml).unwrap();
    let mut command = subsume();
    command.args(["run", robot.to_str().unwrap(), "--duration", "60"]);
    let process = support::HostProcess::spawn(command);
    let teleop = process.word_after("teleoperation on tcp ", Duration::from_secs(60));
    // The whole ws:// URL the host announces.
    let websocket = (!teleop_extra.is_empty())
        .then(|| format!("ws://{}", process.word_after("teleoperation websocket on ws://", Duration::from_secs(60))));
    Host { _process: process, teleop, websocket, _dir: dir }
}

/// An authenticated operator on the line protocol (it never asks for a
/// mode: it does not drive, it only stops and releases).
fn operator(address: &str) -> support::Operator {
    let (mut operator, hello) = support::Operator::connect_to(address);
    assert!(hello.starts_with("HELLO "));
    assert!(operator.say(&format!("AUTH alice {TOKEN}")).starts_with("OK authenticated as alice"));
    operator
}

/// Reads the motors for `for_ms` and returns the lines read in that time.
fn watch(motors: &mut support::MotorRecorder, for_ms: u64) -> Vec<(Instant, String)> {
    let from = motors.lines.len();
    let until = Instant::now() + Duration::from_millis(for_ms);
    motors.read_while(|| Instant::now() < until);
    motors.lines[from..].to_vec()
}

const DRIVING: &str = "M 250 250";

/// The driver is driving: motion lines reach the motors.
fn assert_drives(motors: &mut support::MotorRecorder, what: &str) {
    let deadline = Instant::now() + Duration::from_secs(20);
    loop {
        let lines = watch(motors, 200);
        if lines.iter().any(|(_, l)| l == DRIVING) {
            return;
        }
        assert!(Instant::now() < deadline, "{what}: the driver never moved the robot: {lines:?}");
    }
}

/// From `engaged` on: the first line after the (loose) one-cycle margin is
/// STOP, and nothing but STOP follows while it stays engaged.
fn assert_stopped(lines: &[(Instant, String)], engaged: Instant, what: &str) {
    let after: Vec<&(Instant, String)> = lines.iter().filter(|(at, _)| *at > engaged).collect();
    let first_stop = after.iter().position(|(_, l)| l == "S").unwrap_or_else(|| panic!("{what}: no STOP: {lines:?}"));
    let stop_at = after[first_stop].0;
    // A loaded machine: bound by a cycle of the slowest component (50 ms)
    // plus generous scheduling slack, not a tight wall-clock guess.
    assert!(stop_at.duration_since(engaged) < Duration::from_millis(500), "{what}: STOP after {:?}", stop_at - engaged);
    let moving: Vec<_> = after[first_stop..].iter().filter(|(_, l)| l != "S").collect();
    assert!(moving.is_empty(), "{what}: motion after STOP while engaged: {moving:?}");
    assert_eq!(lines.last().map(|(_, l)| l.as_str()), Some("S"), "{what}: STOP is the last thing on the wire");
}

#[test]
fn estop_and_release_over_the_teleop_line_stop_a_driving_component_until_released() {
    let (mut motors, _slave, device) = support::MotorRecorder::new();
    let host = start(&device, "", "");
    assert_drives(&mut motors, "before");
    let mut alice = operator(&host.teleop);
    let engaged = Instant::now();
    assert_eq!(alice.say("ESTOP"), "OK estop engaged: the motors are stopped");
    let lines = watch(&mut motors, 1500);
    assert_stopped(&lines, engaged, "ESTOP");
    assert!(alice.say("ESTOP").starts_with("OK estop is engaged already (by alice)"));
    assert_eq!(alice.say("RELEASE bumper"), "ERR lock 'bumper' is not engaged");
    // The driver kept sending all along: nothing moved. A release lets it.
    let reply = alice.say("RELEASE");
    assert!(reply.starts_with("OK released estop after "), "{reply}");
    assert_drives(&mut motors, "after the release");
    // A dropped connection releases nothing.
    let engaged = Instant::now();
    alice.say("ESTOP");
    drop(alice);
    let lines = watch(&mut motors, 1000);
    assert_stopped(&lines, engaged, "ESTOP, then the operator left");
}

#[test]
fn a_bumper_hit_from_the_controller_engages_a_lock_that_only_a_release_ends() {
    let (mut motors, _slave, device) = support::MotorRecorder::new();
    let host = start(
        &device,
        r#"<param name="locks" value="bumper=100"/>"#,
        r#"<connect from="motors.bumper" to="arbiter.lock"/>"#,
    );
    assert_drives(&mut motors, "before");
    let hit = Instant::now();
    motors.write(b"B 1\n");
    let lines = watch(&mut motors, 800);
    assert_stopped(&lines, hit, "bumper");
    // The bumper lets go: the lock stays.
    motors.write(b"B 0\n");
    let lines = watch(&mut motors, 800);
    assert!(lines.iter().all(|(_, l)| l == "S"), "released by the bumper's false: {lines:?}");
    let mut alice = operator(&host.teleop);
    let reply = alice.say("RELEASE bumper");
    assert!(reply.starts_with("OK released bumper after "), "{reply}");
    assert_drives(&mut motors, "after the release");
}

/// An operator on the WebSocket JSON protocol, played by the `websockets`
/// package from PyPI (an implementation no one here wrote): each JSON line
/// written to it is sent, and the next `ok` or `error` comes back as one
/// line (pings are answered on the way). It gives up after 120 s, so a
/// failing test cannot hang on it.
const WEBSOCKET_OPERATOR: &str = r#"
import asyncio, json, sys, threading, websockets
async def main():
    loop = asyncio.get_running_loop()
    lines = asyncio.Queue()
    def feed():
        for line in sys.stdin:
            loop.call_soon_threadsafe(lines.put_nowait, line)
        loop.call_soon_threadsafe(lines.put_nowait, "")
    threading.Thread(target=feed, daemon=True).start()
    async with asyncio.timeout(120), websockets.connect(sys.argv[1]) as ws:
        replies = asyncio.Queue()
        async def read():
            async for raw in ws:
                message = json.loads(raw)
                if message.get("type") == "ping":
                    await ws.send(json.dumps({"type": "pong", "nonce": message["nonce"]}))
                elif message.get("type") in ("hello", "ok", "error"):
                    await replies.put(message)
        reading = asyncio.create_task(read())
        print(json.dumps(await replies.get()), flush=True)
        while line := await lines.get():
            await ws.send(line.strip())
            print(json.dumps(await replies.get()), flush=True)
        reading.cancel()
asyncio.run(main())
"#;

#[test]
fn estop_and_release_as_websocket_json_stop_a_driving_component_until_released() {
    let (mut motors, _slave, device) = support::MotorRecorder::new();
    let host = start_with_teleop(&device, "", "", r#"<param name="websocket" value="127.0.0.1:0"/>"#);
    assert_drives(&mut motors, "before");
    let url = host.websocket.clone().unwrap_or_default();
    let mut operator = Command::new(support::python())
        .args(["-c", WEBSOCKET_OPERATOR, &url])
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .spawn()
        .unwrap();
    let mut to_operator = operator.stdin.take().unwrap();
    let mut from_operator = BufReader::new(operator.stdout.take().unwrap()).lines();
    let mut next = move || -> serde_json::Value {
        let line = from_operator.next().and_then(Result::ok).unwrap_or_default();
        serde_json::from_str(&line).unwrap_or_else(|e| panic!("the websocket operator said {line:?}: {e}"))
    };
    let json = |text: &str| -> serde_json::Value { serde_json::from_str(text).unwrap() };
    assert_eq!(next()["type"], "hello");
    let mut say = move |text: &str| -> serde_json::Value {
        to_operator.write_all(format!("{text}\n").as_bytes()).unwrap();
        next()
    };
    let authenticated = say(r#"{"type": "auth", "name": "alice", "token": "alice-token-0123456789"}"#);
    assert!(
        authenticated["message"].as_str().unwrap_or_default().starts_with("authenticated as alice"),
        "{authenticated}"
    );
    let engaged = Instant::now();
    assert_eq!(
        say(r#"{"type": "estop"}"#),
        json(r#"{"type": "ok", "message": "estop engaged: the motors are stopped"}"#)
    );
    let lines = watch(&mut motors, 1500);
    assert_stopped(&lines, engaged, "websocket estop");
    assert_eq!(
        say(r#"{"type": "release", "lock": "bumper"}"#),
        json(r#"{"type": "error", "message": "lock 'bumper' is not engaged"}"#)
    );
    let released = say(r#"{"type": "release"}"#);
    assert!(released["message"].as_str().unwrap_or_default().starts_with("released estop after "), "{released}");
    assert_drives(&mut motors, "after the websocket release");
    drop(say);
    assert!(operator.wait().unwrap().success(), "the websocket operator failed");
}

const PASSWORD: &str = "estop-test-password";

/// `subsume user add NAME --role ROLE` with [`PASSWORD`].
fn add_user(store: &std::path::Path, name: &str, role: &str) {
    let platforms: &[&str] = if role == "developer" { &["control"] } else { &[] };
    support::add_user(store, name, role, platforms, PASSWORD);
}

/// `subsume run` with its portal on the robot of [`start`] (driver,
/// arbiter, envelope, motors on `device`); returns the host and the
/// portal's address.
fn start_with_portal(device: &str, dir: &std::path::Path) -> (support::HostProcess, String) {
    support::guest_dir();
    let store = dir.join("store");
    for (name, role) in [("viewer", "viewer"), ("dev", "developer"), ("operator", "operator")] {
        add_user(&store, name, role);
    }
    let xml = format!(
        r#"<robot name="estop">
  <platform name="control">
    <component name="driver" source="{driver}" rate="20" timeout="200ms">
      <param name="command" value="VEL 0.25 0"/>
      <param name="ticks" value="100000000"/>
    </component>
    <component name="arbiter" source="builtin:arbiter" rate="20"/>
    <component name="motors" source="builtin:serial" rate="100"><param name="device" value="{device}"/></component>
    {PASS_ENVELOPE}
    <connect from="driver.cmd" to="arbiter.commands"/>
    <connect from="arbiter.cmd" to="envelope.cmd"/>
    <connect from="envelope.cmd" to="motors.cmd"/>
  </platform>
</robot>"#,
        driver = support::guest("test-commander").display()
    );
    let robot = dir.join("robot.xml");
    std::fs::write(&robot, xml).unwrap();
    let mut command = subsume();
    command.args(["--store", store.to_str().unwrap(), "run", robot.to_str().unwrap()]);
    command.args(["--http", "127.0.0.1:0", "--duration", "90"]);
    let process = support::HostProcess::spawn(command);
    let address = process.portal_address();
    (process, address)
}

/// `subsume estop|release ADDRESS --user USER`: (success, stdout + stderr).
fn cli(action: &str, address: &str, user: &str) -> (bool, String) {
    let output = subsume().args([action, address, "--user", user]).env("SUBSUME_PASSWORD", PASSWORD).output().unwrap();
    let text = format!("{}{}", String::from_utf8_lossy(&output.stdout), String::from_utf8_lossy(&output.stderr));
    (output.status.success(), text)
}

#[test]
fn the_command_line_and_the_portal_button_stop_the_robot_and_only_a_driver_releases() {
    let (mut motors, _slave, device) = support::MotorRecorder::new();
    let dir = tempfile::tempdir().unwrap();
    let (_host, address) = start_with_portal(&device, dir.path());
    assert_drives(&mut motors, "before");
    // The command line, as a viewer (a button on a small computer).
    let engaged = Instant::now();
    let (ok, said) = cli("estop", &address, "viewer");
    assert!(ok, "{said}");
    assert!(said.contains("estop engaged: the motors are stopped"), "{said}");
    let lines = watch(&mut motors, 1000);
    assert_stopped(&lines, engaged, "subsume estop");
    // Neither a viewer nor a developer may release; nothing moves.
    for (user, role) in [("viewer", "viewer"), ("dev", "developer")] {
        let (ok, said) = cli("release", &address, user);
        assert!(!ok, "{user} released: {said}");
        // The portal's reason, whole.
        let reason = format!("403: {user} may not drive (role {role}): releasing a lock needs a role that may drive\n");
        assert!(said.contains(&reason), "{said}");
    }
    let lines = watch(&mut motors, 300);
    assert!(lines.iter().all(|(_, l)| l == "S"), "moved after a refused release: {lines:?}");
    let (ok, said) = cli("release", &address, "operator");
    assert!(ok && said.contains("released estop after"), "{said}");
    assert_drives(&mut motors, "after the release");
    // The portal's STOP button, clicked by a viewer in headless Chromium.
    let node = Command::new("node")
        .current_dir(support::browser_dir())
        .arg("estop.mjs")
        .arg(format!("http://{address}/"))
        .args(["viewer", PASSWORD])
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let clicked = Instant::now();
    let (tx, rx) = mpsc::channel();
    std::thread::spawn(move || {
        let _ = tx.send(node.wait_with_output());
    });
    let mut output = None;
    let deadline = Instant::now() + Duration::from_secs(60);
    while output.is_none() && Instant::now() < deadline {
        motors.read();
        output = rx.try_recv().ok();
    }
    let output = output.expect("the browser test finished").unwrap();
    let stdout = String::from_utf8_lossy(&output.stdout);
    assert!(output.status.success(), "browser: {stdout}{}", String::from_utf8_lossy(&output.stderr));
    let lines = watch(&mut motors, 500);
    let all: Vec<(Instant, String)> = motors.lines.iter().filter(|(at, _)| *at > clicked).cloned().collect();
    assert!(all.iter().any(|(_, l)| l == "S"), "no STOP after the click");
    assert!(lines.iter().all(|(_, l)| l == "S"), "moving after the portal STOP: {lines:?}");
    assert_eq!(motors.lines.last().map(|(_, l)| l.as_str()), Some("S"));
}
