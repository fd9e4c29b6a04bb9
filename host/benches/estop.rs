#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic)]
//! Emergency-stop benchmark (a bench binary): from an operator's `ESTOP`
//! line on the teleoperation TCP port to the `S` line read at the far end
//! of a real pseudo-terminal (the motor controller), with the real binary.
//!
//! `subsume run` (no portal) drives a WASM driver (`VEL 0.25 0` at 20 Hz)
//! through arbiter, envelope and serial link (ascii, 100 Hz) to a PTY this
//! bench holds. Each sample: wait until the motors move, write `ESTOP`,
//! read the PTY until `S`; then `RELEASE` and wait for motion again. p50,
//! p99 and max.
//!
//! With `FROM=browser`: the same robot with its portal, an operator in
//! headless Chromium (`tests/browser/estop-bench.mjs`) clicks STOP; a sample
//! runs from the page's clock when the click event reaches the document to
//! the `S` line read (wall clock on both sides, same machine). A second
//! figure starts when the mouse input is sent to Chromium, so it adds the
//! browser's input pipeline (and the DevTools protocol's hop) in front.
//!
//! Run: `taskset -c 1 cargo bench --bench estop` (BENCHMARKS.md records
//! the figures; `--profile dev` measures the debug binary). `SAMPLES`
//! sets the number of samples (default 200; 50 from the browser).

#[path = "../../tests/all/support.rs"]
mod support;

use std::io::{BufRead, BufReader, Write};
use std::net::TcpStream;
use std::process::{Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

const TOKEN: &str = "bench-token-0123456789";

fn percentile(sorted: &[Duration], p: f64) -> Duration {
    sorted[((sorted.len() - 1) as f64 * p).round() as usize]
}

/// "N samples: p50 .., p90 .., p95 .., p99 .., max .." of sorted latencies, in ms.
fn summary(sorted: &[Duration]) -> String {
    let ms = |d: Duration| d.as_secs_f64() * 1e3;
    let mut text = format!("{} samples:", sorted.len());
    for (name, p) in [("p50", 0.5), ("p90", 0.9), ("p95", 0.95), ("p99", 0.99), ("max", 1.0)] {
        text += &format!(" {name} {:.2} ms", ms(percentile(sorted, p)));
    }
    text
}

fn robot_xml(device: &str, _extra: &str) -> String {
    format!(
        r#"<robot name="estop-bench">
  <platform name="network">
    <component name="teleop" source="builtin:teleop" rate="100" timeout="300ms">
      <param name="listen" value="127.0.0.1:0"/><param name="operators" value="operators"/>
    </component>
  </platform>
  <platform name="control">
    <component name="driver" source="{driver}" rate="20" timeout="200ms">
      <param name="command" value="VEL 0.25 0"/><param name="ticks" value="100000000"/>
    </component>
    <component name="arbiter" source="builtin:arbiter" rate="20"/>
    <component name="motors" source="builtin:serial" rate="100">
      <param name="device" value="{device}"/><param name="min-interval" value="0.001"/>
    </component>
    <component name="envelope" source="builtin:envelope" rate="20">
      <param name="max-speed" value="10"/><param name="max-reverse" value="10"/><param name="max-turn" value="20"/>
      <param name="max-accel" value="100"/><param name="max-turn-accel" value="100"/>
    </component>
    <connect from="driver.cmd" to="arbiter.commands"/>
    <connect from="teleop.cmd" to="arbiter.commands"/>
    <connect from="arbiter.cmd" to="envelope.cmd"/>
    <connect from="envelope.cmd" to="motors.cmd"/>
  </platform>
</robot>"#,
        driver = support::guest("test-commander").display()
    )
}

fn unix_ms_now() -> f64 {
    std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap().as_secs_f64() * 1e3
}

/// From the portal's STOP button: see the module's docs.
fn from_browser(samples: usize) {
    let (mut motors, _slave, device) = support::MotorRecorder::new();
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    let mut add = Command::new(env!("CARGO_BIN_EXE_subsume"))
        .args(["user", "add", "op", "--role", "operator", "--password-stdin", "--store"])
        .arg(&store)
        .stdin(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    add.stdin.take().unwrap().write_all(b"bench-password-123\n").unwrap();
    assert!(add.wait().unwrap().success());
    let xml = robot_xml(&device, "").replace(r#"<connect from="teleop.cmd" to="arbiter.commands"/>"#, "");
    let xml = xml[..xml.find("<platform name=\"network\">").unwrap()].to_string()
        + &xml[xml.find("<platform name=\"control\">").unwrap()..];
    let robot = dir.path().join("robot.xml");
    std::fs::write(&robot, xml).unwrap();
    let mut command = support::subsume();
    command.args(["--store", store.to_str().unwrap(), "run", robot.to_str().unwrap(), "--http", "127.0.0.1:0"]);
    let host = support::HostProcess::spawn(command);
    let url = host.word_after("portal on http://", Duration::from_secs(60));
    let address = url.split('/').next().unwrap_or_default().to_string();
    let mut node = Command::new("node")
        .current_dir(support::repo_root().join("tests/browser"))
        .arg("estop-bench.mjs")
        .arg(format!("http://{address}/"))
        .args(["op", "bench-password-123", &samples.to_string()])
        .stdout(Stdio::piped())
        .spawn()
        .unwrap();
    let stdout = node.stdout.take().unwrap();
    let (clicks_tx, clicks) = mpsc::channel();
    std::thread::spawn(move || {
        for line in BufReader::new(stdout).lines().map_while(Result::ok) {
            let _ = clicks_tx.send(line);
        }
    });
    let mut clicked: Vec<f64> = Vec::new();
    let mut asked: Vec<f64> = Vec::new();
    let mut stops: Vec<f64> = Vec::new();
    let mut done = false;
    let deadline = Instant::now() + Duration::from_secs(600);
    while !done && Instant::now() < deadline {
        let from = motors.lines.len();
        motors.read();
        let now = unix_ms_now();
        if motors.lines[from..].iter().any(|(_, l)| l == "S") {
            stops.push(now);
        }
        while let Ok(line) = clicks.try_recv() {
            if let Some(ms) = line.strip_prefix("clicked ") {
                clicked.push(ms.parse().unwrap());
            } else if let Some(ms) = line.strip_prefix("asked ") {
                asked.push(ms.parse().unwrap());
            } else {
                done = line == "done";
            }
        }
    }
    assert!(node.wait().unwrap().success(), "the browser failed");
    drop(host);
    let latencies = |starts: &[f64]| {
        let mut latencies: Vec<Duration> = starts
            .iter()
            .filter_map(|at| stops.iter().find(|s| *s >= at).map(|s| Duration::from_secs_f64((s - at) / 1e3)))
            .collect();
        latencies.sort();
        latencies
    };
    for (what, latencies) in [
        ("portal STOP click event -> S on the PTY", latencies(&clicked)),
        ("mouse input sent to Chromium -> S on the PTY", latencies(&asked)),
    ] {
        println!("estop: {what}, {}", summary(&latencies));
    }
}

fn main() {
    if std::env::var("FROM").as_deref() == Ok("browser") {
        let samples = std::env::var("SAMPLES").ok().and_then(|s| s.parse().ok()).unwrap_or(50);
        return from_browser(samples);
    }
    let samples: usize = std::env::var("SAMPLES").ok().and_then(|s| s.parse().ok()).unwrap_or(200);
    let (mut motors, _slave, device) = support::MotorRecorder::new();
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("operators"), format!("bench {TOKEN}\n")).unwrap();
    let xml = robot_xml(&device, "");
    let robot = dir.path().join("robot.xml");
    std::fs::write(&robot, xml).unwrap();
    let mut command = support::subsume();
    command.env("SUBSUME_HTTP", "off").args(["run", robot.to_str().unwrap()]);
    let host = support::HostProcess::spawn(command);
    let address = host.word_after("teleoperation on tcp ", Duration::from_secs(60));
    let stream = TcpStream::connect(&address).unwrap();
    stream.set_nodelay(true).unwrap();
    let mut writer = stream.try_clone().unwrap();
    // Replies (and pings) are read on their own thread, answered at once.
    let mut pong = stream.try_clone().unwrap();
    std::thread::spawn(move || {
        for line in BufReader::new(stream).lines().map_while(Result::ok) {
            if let Some(nonce) = line.strip_prefix("PING ") {
                let _ = pong.write_all(format!("PONG {nonce}\n").as_bytes());
            }
        }
    });
    writer.write_all(format!("AUTH bench {TOKEN}\n").as_bytes()).unwrap();
    let moving = |motors: &mut support::MotorRecorder| {
        let deadline = Instant::now() + Duration::from_secs(20);
        loop {
            let from = motors.lines.len();
            motors.read();
            if motors.lines[from..].iter().any(|(_, l)| l.starts_with("M ")) {
                return;
            }
            assert!(Instant::now() < deadline, "the driver never moved the robot");
        }
    };
    let mut latencies = Vec::with_capacity(samples);
    for _ in 0..samples {
        moving(&mut motors);
        // Let the sample start at a random phase of the loop's cycles.
        std::thread::sleep(Duration::from_millis(7 + (latencies.len() as u64 * 13) % 40));
        motors.read();
        let from = motors.lines.len();
        let start = Instant::now();
        writer.write_all(b"ESTOP\n").unwrap();
        let deadline = start + Duration::from_secs(5);
        let stopped = loop {
            motors.read();
            if let Some((at, _)) = motors.lines[from..].iter().find(|(_, l)| l == "S") {
                break *at;
            }
            assert!(Instant::now() < deadline, "no STOP within 5 s of ESTOP");
        };
        latencies.push(stopped.duration_since(start));
        writer.write_all(b"RELEASE\n").unwrap();
    }
    drop(host);
    latencies.sort();
    println!("estop: teleop ESTOP line -> S on the PTY, {}", summary(&latencies));
}
