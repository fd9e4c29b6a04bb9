//! The motors stop on every exit the host controls: the built binary drives
//! a pseudo-terminal playing the motor controller, a source keeps the robot
//! moving, and the run ends in each way it can (SIGINT, SIGTERM, the end of
//! `--duration`, a fatal error, a panic on the control thread and on another
//! thread, a second signal while the loop hangs, an activation that removes
//! or replaces the serial link). Each time, the last frame the link wrote
//! must be its translator's STOP; each way out is tried with the `ascii`
//! and `binary` profiles and the WASM translator
//! (`guest-components/rust/translator-ascii`).
//!
//! Panics and a hanging loop are caused with the test-only
//! `SUBSUME_FAULT_INJECTION` setting; the fatal error is a real one (the
//! portal's address is taken).

use std::net::TcpListener;
use std::path::Path;
use std::process::ExitStatus;
use std::time::{Duration, Instant};

use crate::support::{self, HostProcess, MotorRecorder, PASS_ENVELOPE, http, subsume};

/// Longest a test waits for the host to start moving or to exit.
const WAIT: Duration = Duration::from_secs(60);

/// How the link speaks to the motors.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Wire {
    Ascii,
    Binary,
    /// `translator-ascii.wasm`: the ascii bytes, from a WASM translator.
    Wasm,
}

const WIRES: [Wire; 3] = [Wire::Ascii, Wire::Binary, Wire::Wasm];

impl Wire {
    /// The `translator` parameter (the WASM file is copied beside the robot).
    fn translator(self) -> &'static str {
        match self {
            Wire::Ascii => "ascii",
            Wire::Binary => "binary",
            Wire::Wasm => "translator.wasm",
        }
    }

    /// The frame for `VEL 0.2 0` (both wheels at 200 mm/s; wheel base 0.3).
    fn moving(self) -> Vec<u8> {
        match self {
            Wire::Ascii | Wire::Wasm => b"M 200 200\n".to_vec(),
            Wire::Binary => vec![0xA5, 0x05, 0x01, 0xC8, 0x00, 0xC8, 0x00, 0x6F],
        }
    }

    fn stop(self) -> Vec<u8> {
        match self {
            Wire::Ascii | Wire::Wasm => b"S\n".to_vec(),
            Wire::Binary => vec![0xA5, 0x01, 0x02, 0xFE],
        }
    }

    /// The frames at the start of `bytes` in this wire's protocol (an
    /// independent splitter: lines, or `A5 LEN PAYLOAD CHECKSUM` frames),
    /// up to where another protocol's bytes begin.
    fn frames(self, bytes: &[u8]) -> Vec<Vec<u8>> {
        match self {
            Wire::Ascii | Wire::Wasm => {
                let end = bytes.iter().position(|&b| b == 0xA5).unwrap_or(bytes.len());
                bytes[..end].split_inclusive(|&b| b == b'\n').map(<[u8]>::to_vec).collect()
            }
            Wire::Binary => {
                let mut frames = Vec::new();
                let mut at = 0;
                while bytes.get(at) == Some(&0xA5) && at + 1 < bytes.len() {
                    let end = at + usize::from(bytes[at + 1]) + 3;
                    if end > bytes.len() {
                        break;
                    }
                    frames.push(bytes[at..end].to_vec());
                    at = end;
                }
                frames
            }
        }
    }
}

fn contains(haystack: &[u8], needle: &[u8]) -> bool {
    haystack.windows(needle.len()).any(|w| w == needle)
}

/// The robot: a source driving `command` for ever, the arbiter, the link on
/// `device`. `refresh` tells two links apart (a changed parameter makes an
/// activation build a new link rather than carry the old one).
fn robot(device: &str, wire: Wire, command: &str, refresh: &str) -> String {
    format!(
        r#"<robot name="stops">
  <platform name="control">
    <component name="driver" source="test-commander.wasm" rate="20" timeout="200ms">
      <param name="command" value="{command}"/>
      <param name="ticks" value="100000000"/>
    </component>
    <component name="arbiter" source="builtin:arbiter" rate="20"/>
    <component name="motors" source="builtin:serial" rate="100">
      <param name="device" value="{device}"/>
      <param name="translator" value="{}"/>
      <param name="refresh" value="{refresh}"/>
    </component>
    <connect from="driver.cmd" to="arbiter.commands"/>
    {PASS_ENVELOPE}
    <connect from="arbiter.cmd" to="envelope.cmd"/>
    <connect from="envelope.cmd" to="motors.cmd"/>
  </platform>
</robot>
"#,
        wire.translator()
    )
}

/// A folder with the robot file and the WASM files it names.
fn robot_dir(device: &str, wire: Wire) -> tempfile::TempDir {
    let dir = tempfile::tempdir().unwrap();
    std::fs::copy(support::guest("test-commander"), dir.path().join("test-commander.wasm")).unwrap();
    std::fs::copy(support::guest("translator-ascii"), dir.path().join("translator.wasm")).unwrap();
    std::fs::write(dir.path().join("robot.xml"), robot(device, wire, "VEL 0.2 0", "0.1")).unwrap();
    dir
}

/// A running host (its log collected on a thread) and the far end of its
/// motor PTY.
struct Host {
    process: HostProcess,
    motors: MotorRecorder,
    wire: Wire,
}

impl Host {
    /// Starts `subsume run` on the robot in `dir` with `args` and `env`.
    fn start(dir: &Path, motors: MotorRecorder, wire: Wire, args: &[&str], env: &[(&str, &str)]) -> Host {
        let mut command = subsume();
        command.arg("run").arg(dir.join("robot.xml")).args(args).envs(env.iter().copied());
        Host { process: HostProcess::spawn(command), motors, wire }
    }

    fn log(&self) -> String {
        self.process.log()
    }

    /// Reads the PTY until the motors are being driven.
    fn wait_until_moving(&mut self) {
        let deadline = Instant::now() + WAIT;
        let moving = self.wire.moving();
        while !contains(&self.motors.bytes, &moving) {
            assert!(Instant::now() < deadline, "{:?}: the motors never moved; log:\n{}", self.wire, self.log());
            assert!(
                self.process.child.try_wait().unwrap().is_none(),
                "{:?}: the host exited; log:\n{}",
                self.wire,
                self.log()
            );
            self.motors.read();
        }
    }

    /// Reads the PTY until `text` is in the log.
    fn wait_for_log(&mut self, text: &str) {
        let mut deadline = Instant::now() + WAIT;
        let mut exited = false;
        while !self.log().contains(text) {
            assert!(Instant::now() < deadline, "{:?}: no '{text}' in the log:\n{}", self.wire, self.log());
            if !exited && self.process.child.try_wait().unwrap().is_some() {
                // Give the log thread a moment to read the rest.
                exited = true;
                deadline = deadline.min(Instant::now() + Duration::from_secs(2));
            }
            self.motors.read();
        }
    }

    fn signal(&self, signal: &str) {
        support::signal(self.process.child.id(), signal);
    }

    /// Reads the PTY until the host exits, then what is left.
    fn wait_for_exit(&mut self) -> ExitStatus {
        let deadline = Instant::now() + WAIT;
        loop {
            if let Some(status) = self.process.child.try_wait().unwrap() {
                self.motors.read();
                return status;
            }
            assert!(Instant::now() < deadline, "{:?}: the host did not exit; log:\n{}", self.wire, self.log());
            self.motors.read();
        }
    }

    /// The motors were driven, and the link's last frame is its STOP; with
    /// `alone`, no other link wrote after it.
    fn assert_stopped_last(&self, how: &str, alone: bool) {
        let frames = self.wire.frames(&self.motors.bytes);
        assert!(frames.contains(&self.wire.moving()), "{how}, {:?}: never moved: {frames:?}", self.wire);
        assert_eq!(frames.last(), Some(&self.wire.stop()), "{how}, {:?}: frames {frames:?}\n{}", self.wire, self.log());
        if alone {
            let all: usize = frames.iter().map(Vec::len).sum();
            assert_eq!(all, self.motors.bytes.len(), "{how}, {:?}: bytes beyond the frames", self.wire);
        }
    }
}

/// Runs each wire: starts the host with `args` and `env`, waits until the
/// motors move, ends the run with `end`, and checks the exit status and that
/// STOP came last.
fn each_wire(how: &str, args: &[&str], env: &[(&str, &str)], end: impl Fn(&mut Host), exit_code: i32) {
    for wire in WIRES {
        let (motors, _slave, device) = MotorRecorder::new();
        let dir = robot_dir(&device, wire);
        let mut host = Host::start(dir.path(), motors, wire, args, env);
        host.wait_until_moving();
        end(&mut host);
        let status = host.wait_for_exit();
        assert_eq!(status.code(), Some(exit_code), "{how}, {wire:?}: {status}; log:\n{}", host.log());
        host.assert_stopped_last(how, true);
        assert!(host.log().contains("final STOP sent") || host.log().contains("'motors': STOP sent"), "{how}");
    }
}

#[test]
fn sigint_and_sigterm_leave_stop_last() {
    for signal in ["INT", "TERM"] {
        each_wire(&format!("SIG{signal}"), &[], &[], |host| host.signal(signal), 0);
    }
}

#[test]
fn the_end_of_the_duration_leaves_stop_last() {
    each_wire("--duration", &["--duration", "2"], &[], |_| {}, 0);
}

#[test]
fn a_panic_on_the_control_thread_leaves_stop_last() {
    // Without a backtrace to resolve, the panic hook is quick: it is the
    // hook's STOP on the wire, not the stall watchdog's.
    let env = [("SUBSUME_FAULT_INJECTION", "panic-control:1.5"), ("RUST_BACKTRACE", "0")];
    each_wire(
        "panic on the control thread",
        &[],
        &env,
        |host| {
            host.wait_for_log("fault injection: the control thread panics");
            host.wait_for_log("after the panic, serial link 'motors': STOP sent");
        },
        101,
    );
}

#[test]
fn a_panic_on_another_thread_leaves_stop_last() {
    let env = [("SUBSUME_FAULT_INJECTION", "panic-thread:1.5"), ("RUST_BACKTRACE", "0")];
    each_wire(
        "panic outside the loop",
        &[],
        &env,
        |host| {
            host.wait_for_log("a thread outside the control loop panics");
            host.wait_for_log("after the panic, serial link 'motors': STOP sent");
        },
        101,
    );
}

#[test]
fn a_second_signal_while_the_loop_hangs_stops_the_motors_then_exits() {
    let env = [("SUBSUME_FAULT_INJECTION", "hang-control:1.5")];
    each_wire(
        "second signal",
        &[],
        &env,
        |host| {
            // The stall watchdog stops the motors while the loop hangs ...
            host.wait_for_log("the control loop is stalled: the cycle between calls has not ended for");
            host.wait_for_log("motors: 'motors': STOP sent");
            // ... the first signal cannot end a hung loop, the second
            // sends the final STOP itself and exits.
            host.signal("INT");
            host.wait_for_log("signal 2 received: stopping");
            host.signal("INT");
            host.wait_for_log("second signal: serial link 'motors': STOP sent");
        },
        130,
    );
}

#[test]
fn a_fatal_error_after_the_link_started_sends_stop() {
    // A real fatal error: the portal's address is taken, found after the
    // robot (and its serial link) started.
    let taken = TcpListener::bind("127.0.0.1:0").unwrap();
    let address = taken.local_addr().unwrap().to_string();
    for wire in WIRES {
        let (motors, _slave, device) = MotorRecorder::new();
        let dir = robot_dir(&device, wire);
        let store = tempfile::tempdir().unwrap();
        let args = ["--http", &address, "--store", store.path().to_str().unwrap()];
        let mut host = Host::start(dir.path(), motors, wire, &args, &[]);
        let status = host.wait_for_exit();
        let log = host.log();
        assert_eq!(status.code(), Some(1), "{wire:?}: {log}");
        assert!(log.contains(&format!("error: the portal cannot listen on {address}")), "{wire:?}: {log}");
        // The robot never ran: the link's final STOP is all it wrote (the
        // I/O thread and the closing link may both have held the device
        // for it, one after the other).
        let frames = wire.frames(&host.motors.bytes);
        assert!(!frames.is_empty() && frames.iter().all(|f| *f == wire.stop()), "{wire:?}: {frames:?}\n{log}");
        assert_eq!(frames.iter().map(Vec::len).sum::<usize>(), host.motors.bytes.len(), "{wire:?}");
    }
}

const PASSWORD: &str = "stops-test-password";

/// Starts the host with the portal on the robot in `dir`, adds an admin and
/// logs in; returns the host, the portal's address and a session token.
fn start_with_portal(dir: &Path, store: &Path, motors: MotorRecorder, wire: Wire) -> (Host, String, String) {
    support::add_user(store, "admin", "admin", &[], PASSWORD);
    let args = ["--http", "127.0.0.1:0", "--store", store.to_str().unwrap()];
    let mut host = Host::start(dir, motors, wire, &args, &[]);
    host.wait_for_log("portal on http://");
    let address = host.process.portal_address();
    let token = support::login(&address, "admin", PASSWORD);
    (host, address, token)
}

/// Stages `robot` as `file` and activates it; returns once the portal says
/// it runs (the old graph, with its link, is dropped before the answer).
fn activate(address: &str, token: &str, file: &str, robot: &str) {
    let path = format!("/api/v1/platforms/control/configs/{file}");
    let (status, body) = http(address, "PUT", &path, Some(token), robot.as_bytes());
    assert_eq!(status, 201, "{body}");
    let id = body["set"]["id"].as_u64().unwrap_or_else(|| panic!("no set id in {body}"));
    let (status, body) = http(address, "POST", &format!("/api/v1/sets/{id}/activate"), Some(token), b"");
    assert_eq!(status, 200, "{body}");
}

#[test]
fn an_activation_that_removes_the_link_leaves_stop_last() {
    for wire in WIRES {
        let (motors, _slave, device) = MotorRecorder::new();
        let dir = robot_dir(&device, wire);
        let store = tempfile::tempdir().unwrap();
        let (mut host, address, token) = start_with_portal(dir.path(), store.path(), motors, wire);
        host.wait_until_moving();
        let without_link = r#"<robot name="stops">
  <platform name="control">
    <component name="driver" source="test-commander.wasm" rate="20"/>
    <component name="arbiter" source="builtin:arbiter" rate="20"/>
    <connect from="driver.cmd" to="arbiter.commands"/>
  </platform>
</robot>
"#;
        activate(&address, &token, "without-link.xml", without_link);
        // Had the link lived on, its refresh (0.1 s) would write again
        // within this wait.
        let quiet = Instant::now() + Duration::from_millis(500);
        host.motors.read_while(|| Instant::now() < quiet);
        host.assert_stopped_last("activation without the link", true);
        host.signal("TERM");
        assert!(host.wait_for_exit().success(), "{}", host.log());
        host.assert_stopped_last("activation without the link, then SIGTERM", true);
    }
}

#[test]
fn an_activation_that_replaces_the_link_sends_the_old_links_stop_before_the_new_link_writes() {
    // The new link speaks another protocol, so the wire shows where one
    // link's bytes end and the other's begin.
    for (old, new) in [(Wire::Ascii, Wire::Binary), (Wire::Binary, Wire::Ascii), (Wire::Wasm, Wire::Binary)] {
        let (motors, _slave, device) = MotorRecorder::new();
        let dir = robot_dir(&device, old);
        let store = tempfile::tempdir().unwrap();
        let (mut host, address, token) = start_with_portal(dir.path(), store.path(), motors, old);
        host.wait_until_moving();
        activate(&address, &token, "new-link.xml", &robot(&device, new, "VEL 0.2 0", "0.1"));
        // Until the new link's first frame arrives.
        let deadline = Instant::now() + WAIT;
        while old.frames(&host.motors.bytes).iter().map(Vec::len).sum::<usize>() == host.motors.bytes.len() {
            assert!(Instant::now() < deadline, "{old:?} -> {new:?}: the new link never wrote:\n{}", host.log());
            host.motors.read();
        }
        host.assert_stopped_last(&format!("replaced by a {new:?} link"), false);
        host.signal("TERM");
        assert!(host.wait_for_exit().success(), "{}", host.log());
        let rest = host.motors.bytes[old.frames(&host.motors.bytes).iter().map(Vec::len).sum::<usize>()..].to_vec();
        let frames = new.frames(&rest);
        assert_eq!(frames.last(), Some(&new.stop()), "{old:?} -> {new:?}: the new link's frames {frames:?}");
    }
}
