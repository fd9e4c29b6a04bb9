//! Cooperating hosts end to end: two `subsume run` processes on loopback,
//! joined by Zenoh (docs/distributed.md). Host A owns the motors (a
//! pseudo-terminal this test plays), publishes its ranges and takes host
//! B's commands as one more arbiter source (priority 3, timeout 300 ms)
//! above a local stand-in planner (priority 1). Host B runs the WASM
//! avoider on A's ranges. Killing B must hand the motors back to the
//! planner within B's timeout.

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use serde_json::Value as Json;

use crate::support::{self, PASS_ENVELOPE, free_port, read_report, subsume, wait_for_exit};

struct Host {
    child: Child,
    report: PathBuf,
    _dir: tempfile::TempDir,
}

impl Drop for Host {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn start(name: &str, body: &str) -> Host {
    let dir = tempfile::tempdir().unwrap();
    let robot = support::robot_file(dir.path(), &format!("<robot name=\"{name}\">\n{body}\n</robot>\n"));
    let report = dir.path().join("report.json");
    let mut child = subsume()
        .args(["run", robot.to_str().unwrap()])
        .args(["--duration", "60", "--report", report.to_str().unwrap()])
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let stderr = child.stderr.take().unwrap();
    let (tx, rx) = std::sync::mpsc::channel();
    let label = name.to_string();
    std::thread::spawn(move || {
        for line in BufReader::new(stderr).lines().map_while(Result::ok) {
            if line.contains("control loop") || line.contains("zenoh session open") {
                let _ = tx.send(());
            }
            if line.contains("ERROR") || line.contains("WARN") || line.contains("error:") {
                eprintln!("{label}: {line}");
            }
        }
    });
    let _ = rx.recv_timeout(Duration::from_secs(60));
    Host { child, report, _dir: dir }
}

fn stop(mut host: Host) -> Json {
    support::signal(host.child.id(), "TERM");
    wait_for_exit(&mut host.child, Duration::from_secs(20));
    read_report(&host.report)
}

/// The report section of the bridge on `key`.
fn bridge<'a>(report: &'a Json, key: &str) -> &'a Json {
    report
        .as_object()
        .unwrap()
        .iter()
        .find(|(name, v)| name.starts_with("zenoh") && v["key"] == key)
        .map(|(_, v)| v)
        .unwrap_or_else(|| panic!("no bridge on {key}: {report}"))
}

const PLANNER: &str = "M 200 200";

type Lines = [(Instant, String)];

/// Plays the motor controller until `until` or `done`: an obstacle 0.3 m
/// ahead on every ray, 20 times a second; records what the host writes.
fn feed_until(motors: &mut support::MotorRecorder, until: Instant, done: &dyn Fn(&Lines) -> bool) {
    let mut next = Instant::now();
    while Instant::now() < until && !done(&motors.lines) {
        if Instant::now() >= next {
            motors.write(b"R 300 300 300 300 300 300 300 300 300\n");
            next += Duration::from_millis(50);
        }
        motors.read();
    }
}

#[test]
fn host_b_avoids_for_host_a_and_when_b_dies_the_planner_takes_over_within_the_timeout() {
    support::guest_dir();
    let port = free_port();
    let (mut motors, _slave, device) = support::MotorRecorder::new();
    let a = start(
        "host-a",
        &format!(
            r#"<platform name="control">
    <component name="motors" source="builtin:serial" rate="100"><param name="device" value="{device}"/></component>
    <component name="planner" source="builtin:publish" rate="20" priority="1" timeout="300ms">
      <param name="kind" value="command"/><param name="value" value="VEL 0.2 0"/>
    </component>
    <component name="arbiter" source="builtin:arbiter" rate="50"/>
    {PASS_ENVELOPE}
    <connect from="planner.out" to="arbiter.commands"/>
    <connect from="arbiter.cmd" to="envelope.cmd"/>
    <connect from="envelope.cmd" to="motors.cmd"/>
  </platform>
  <platform name="network">
    <component name="zenoh" source="builtin:zenoh"><param name="listen" value="tcp/127.0.0.1:{port}"/></component>
    <component name="ranges-out" source="builtin:zenoh-publish"><param name="key" value="test/a/ranges"/></component>
    <component name="remote-avoid" source="builtin:zenoh-subscribe" priority="3" timeout="300ms">
      <param name="key" value="test/b/cmd"/><param name="kind" value="command"/>
    </component>
    <connect from="motors.ranges" to="ranges-out.in"/>
    <connect from="remote-avoid.out" to="arbiter.commands"/>
  </platform>"#
        ),
    );
    let b = start(
        "host-b",
        &format!(
            r#"<platform name="control">
    <component name="avoid" source="GUEST(avoider)" rate="20" budget="5ms" memory="16MiB">
      <param name="threshold" value="0.55"/><param name="creep-speed" value="0.1"/><param name="turn-rate" value="1.5"/>
    </component>
    <connect from="ranges-in.out" to="avoid.ranges"/>
    <connect from="avoid.cmd" to="cmd-out.in"/>
  </platform>
  <platform name="network">
    <component name="zenoh" source="builtin:zenoh"><param name="connect" value="tcp/127.0.0.1:{port}"/></component>
    <component name="ranges-in" source="builtin:zenoh-subscribe">
      <param name="key" value="test/a/ranges"/><param name="kind" value="vector"/>
    </component>
    <component name="cmd-out" source="builtin:zenoh-publish"><param name="key" value="test/b/cmd"/></component>
  </platform>"#
        ),
    );
    let turning = |l: &str| l.starts_with("M ") && l != PLANNER;
    let started = Instant::now();
    feed_until(&mut motors, started + Duration::from_secs(30), &|lines| lines.iter().any(|(_, l)| turning(l)));
    let first_turn =
        motors.lines.iter().position(|(_, l)| turning(l)).expect("host B's avoider never reached A's motors");
    // B holds control while it keeps answering.
    let held_from = Instant::now();
    feed_until(&mut motors, held_from + Duration::from_secs(1), &|_| false);
    let while_b: Vec<&String> = motors.lines.iter().filter(|(at, _)| *at > held_from).map(|(_, l)| l).collect();
    assert!(
        !while_b.is_empty() && while_b.iter().all(|l| turning(l)),
        "B's commands win over the planner: {while_b:?}"
    );
    assert!(motors.lines[..first_turn].iter().any(|(_, l)| l == PLANNER), "the planner drove before B answered");

    // B dies without a word.
    let killed = Instant::now();
    support::signal(b.child.id(), "KILL");
    feed_until(&mut motors, killed + Duration::from_millis(1500), &|_| false);
    drop(b);
    let back = motors.lines.iter().find(|(at, l)| *at > killed && l == PLANNER).expect("the planner took over");
    let after = back.0.duration_since(killed);
    // B's timeout is 300 ms from its last command (sent before the kill);
    // the arbiter ticks at 50 Hz, the link at 100 Hz; 300 ms of slack for a
    // loaded machine (quiet runs take over in about 300 ms).
    eprintln!("the planner took over {after:?} after the kill");
    assert!(after < Duration::from_millis(600), "the planner took over after {after:?}");
    let late: Vec<&String> =
        motors.lines.iter().filter(|(at, _)| *at > killed + Duration::from_millis(600)).map(|(_, l)| l).collect();
    assert!(late.iter().all(|l| l.as_str() == PLANNER), "after the timeout only the planner drives: {late:?}");

    let report = stop(a);
    let remote = bridge(&report, "test/b/cmd");
    assert!(remote["in"].as_u64().unwrap() > 10, "{remote}");
    assert_eq!(remote["malformed"], 0, "{remote}");
    let ranges = bridge(&report, "test/a/ranges");
    assert!(ranges["out"].as_u64().unwrap() > 10, "{ranges}");
    // The remote source held control (at the robot file's priority 3, over
    // the planner's 1), then the planner again.
    let held = report["arbiter"]["held_s"].as_array().unwrap();
    let held_by = |name: &str| held.iter().find(|h| h[0] == name).and_then(|h| h[1].as_f64()).unwrap_or(0.0);
    assert!(held_by("remote-avoid") > 0.9 && held_by("planner") > 0.5, "{}", report["arbiter"]);
    assert_eq!(report["arbiter"]["holder"], "planner");
}

/// A test CA, a certificate it signed for localhost and 127.0.0.1, and a
/// user/password dictionary, made with the openssl CLI in a fresh folder.
fn make_tls_pki() -> tempfile::TempDir {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    support::make_test_pki(d);
    std::fs::write(d.join("users.txt"), "robot-a:secret-a\nrobot-b:secret-b\n").unwrap();
    dir
}

/// `subsume run` of a robot that publishes 7.25 on test/tls/out and
/// subscribes to test/tls/in, its session from a JSON5 file connecting to
/// `endpoint` over TLS as robot-b with `password`. Zenoh's
/// `exit_on_failure` makes a refused session an error at start.
fn tls_host(dir: &Path, pki: &Path, endpoint: &str, password: &str) -> Child {
    let config = dir.join("zenoh.json5");
    std::fs::write(
        &config,
        format!(
            r#"{{
  mode: "peer",
  scouting: {{ multicast: {{ enabled: false }} }},
  connect: {{ endpoints: ["{endpoint}"], exit_on_failure: true, timeout_ms: 5000 }},
  transport: {{
    link: {{ tls: {{ root_ca_certificate: "{ca}" }} }},
    auth: {{ usrpwd: {{ user: "robot-b", password: "{password}" }} }},
  }},
}}"#,
            ca = pki.join("ca.pem").display()
        ),
    )
    .unwrap();
    let robot = dir.join("robot.xml");
    std::fs::write(
        &robot,
        r#"<robot name="tls-host">
  <platform name="control">
    <component name="value" source="builtin:publish" rate="20">
      <param name="kind" value="scalar"/><param name="value" value="7.25"/>
    </component>
  </platform>
  <platform name="network">
    <component name="zenoh" source="builtin:zenoh"><param name="zenoh-config" value="zenoh.json5"/></component>
    <component name="out" source="builtin:zenoh-publish"><param name="key" value="test/tls/out"/></component>
    <component name="in" source="builtin:zenoh-subscribe">
      <param name="key" value="test/tls/in"/><param name="kind" value="scalar"/>
    </component>
    <connect from="value.out" to="out.in"/>
  </platform>
</robot>
"#,
    )
    .unwrap();
    subsume()
        .args(["run", robot.to_str().unwrap()])
        .args(["--duration", "60", "--report", dir.join("report.json").to_str().unwrap()])
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap()
}

#[test]
fn a_host_and_an_eclipse_zenoh_peer_talk_over_tls_with_a_password_and_a_wrong_password_is_refused() {
    let pki = make_tls_pki();
    let endpoint = format!("tls/localhost:{}", free_port());
    let mut peer = Command::new(support::python())
        .arg(support::repo_root().join("tests/python/zenoh_tls_peer.py"))
        .args([&endpoint, pki.path().to_str().unwrap()])
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .spawn()
        .unwrap();
    let mut peer_out = BufReader::new(peer.stdout.take().unwrap());
    let mut line = String::new();
    peer_out.read_line(&mut line).unwrap();
    assert_eq!(line.trim(), "ready");

    // The right password: values cross both ways over TLS.
    let dir = tempfile::tempdir().unwrap();
    let host = tls_host(dir.path(), pki.path(), &endpoint, "secret-b");
    let mut host = Host { child: host, report: dir.path().join("report.json"), _dir: dir };
    std::thread::sleep(Duration::from_secs(4));
    assert!(host.child.try_wait().unwrap().is_none(), "the host exited early");
    host.child.stderr.take();
    let report = stop(host);
    let inbound = bridge(&report, "test/tls/in");
    assert!(inbound["in"].as_u64().unwrap() >= 10, "{inbound}");
    assert_eq!(inbound["malformed"], 0, "{inbound}");
    assert_eq!(inbound["peers"], 1, "{inbound}");
    assert!(bridge(&report, "test/tls/out")["out"].as_u64().unwrap() >= 10, "{report}");

    // A wrong password: the peer closes the handshake; the host says so and
    // does not run.
    let dir = tempfile::tempdir().unwrap();
    let mut refused = tls_host(dir.path(), pki.path(), &endpoint, "not-the-password");
    let mut stderr = String::new();
    std::io::Read::read_to_string(&mut refused.stderr.take().unwrap(), &mut stderr).unwrap();
    let status = refused.wait().unwrap();
    assert_eq!(status.code(), Some(1), "{stderr}");
    assert!(stderr.contains(&format!("no peer accepted the connection to {endpoint}")), "{stderr}");
    assert!(stderr.contains("user/password or the TLS certificate"), "{stderr}");

    drop(peer.stdin.take());
    line.clear();
    peer_out.read_line(&mut line).unwrap();
    let _ = peer.wait();
    let summary: Json = serde_json::from_str(&line).unwrap_or_else(|e| panic!("peer said {line:?}: {e}"));
    assert_eq!(summary["bad"], Json::Array(vec![]), "{summary}");
    let received = summary["received"].as_array().unwrap();
    assert!(received.len() >= 10 && received.iter().all(|x| x == 7.25), "{summary}");
}
