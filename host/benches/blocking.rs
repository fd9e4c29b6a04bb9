#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic)]
//! From a guest's blocking call to STOP on the wire (a bench binary), end to
//! end: the built `subsume` binary runs a robot whose motion source
//! (test-faulty, `sleep-on-tick`) drives through the arbiter into a serial
//! link on a real pseudo-terminal, then calls `std::thread::sleep` in its
//! sixth tick while holding control. The host refuses the wait, faults the
//! source, and the arbiter's STOP goes out. A sample runs from the guest's
//! log line just before the sleep (the host log's timestamp) to the `S`
//! line read at the PTY's master end (the same wall clock). One run of the
//! binary per sample. p50 and p99.
//!
//! Run: `cargo bench --bench blocking` (BENCHMARKS.md records the figures).

#[path = "../../tests/all/support.rs"]
mod support;

use std::io::Read as _;
use std::process::Command;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use serialport::{SerialPort as _, TTYPort};

fn percentile(sorted: &[Duration], p: f64) -> Duration {
    sorted[((sorted.len() - 1) as f64 * p).round() as usize]
}

/// Seconds since the epoch of a log line's leading RFC 3339 UTC timestamp
/// (`2026-11-23T10:49:30.219726Z`), taken as the same day as `today`.
fn log_time(line: &str, today: Duration) -> Option<Duration> {
    let start = line.find('T')?;
    let clock = &line[start + 1..line[start..].find('Z')? + start];
    let mut parts = clock.split(':');
    let hours: f64 = parts.next()?.parse().ok()?;
    let minutes: f64 = parts.next()?.parse().ok()?;
    let seconds: f64 = parts.next()?.parse().ok()?;
    let midnight = today.as_secs() - today.as_secs() % 86_400;
    Some(Duration::from_secs(midnight) + Duration::from_secs_f64(hours * 3600.0 + minutes * 60.0 + seconds))
}

fn sample(dir: &std::path::Path) -> Duration {
    let (mut master, slave) = TTYPort::pair().unwrap();
    master.set_timeout(Duration::from_millis(10)).unwrap();
    let device = slave.name().unwrap();
    let robot = dir.join("robot.xml");
    std::fs::write(
        &robot,
        format!(
            r#"<robot name="blocking">
  <platform name="control">
    <component name="motors" source="builtin:serial" rate="100">
      <param name="device" value="{device}"/>
      <param name="watchdog" value="5"/>
    </component>
    <component name="sleeper" source="{}" rate="20" budget="5ms" timeout="5s">
      <param name="mode" value="sleep-on-tick"/>
      <param name="after" value="5"/>
      <param name="drive" value="yes"/>
    </component>
    <component name="arbiter" source="builtin:arbiter" rate="50"/>
    <connect from="sleeper.cmd" to="arbiter.commands"/>
    <connect from="arbiter.cmd" to="motors.cmd"/>
  </platform>
</robot>"#,
            support::guest("test-faulty").display()
        ),
    )
    .unwrap();
    let stops = Arc::new(Mutex::new(Vec::new()));
    let done = Arc::new(AtomicBool::new(false));
    let reader = {
        let (stops, done) = (stops.clone(), done.clone());
        std::thread::spawn(move || {
            let mut pending = Vec::new();
            let mut buffer = [0u8; 256];
            while !done.load(Ordering::Relaxed) {
                if let Ok(n) = master.read(&mut buffer) {
                    let at = SystemTime::now().duration_since(UNIX_EPOCH).unwrap();
                    pending.extend_from_slice(&buffer[..n]);
                    while let Some(end) = pending.iter().position(|&b| b == b'\n') {
                        let line: Vec<u8> = pending.drain(..=end).collect();
                        if line == b"S\n" {
                            stops.lock().unwrap().push(at);
                        }
                    }
                }
            }
        })
    };
    let output = Command::new(env!("CARGO_BIN_EXE_subsume"))
        .current_dir(support::repo_root())
        .env("SUBSUME_HTTP", "off")
        .env("NO_COLOR", "1")
        .args(["--cache-dir", support::cache_dir().to_str().unwrap(), "run", "--duration", "0.6"])
        .arg(&robot)
        .output()
        .unwrap();
    done.store(true, Ordering::Relaxed);
    reader.join().unwrap();
    let log = String::from_utf8_lossy(&output.stderr);
    assert!(output.status.success(), "{log}");
    let today = SystemTime::now().duration_since(UNIX_EPOCH).unwrap();
    let slept = log.lines().find(|l| l.contains("sleeping now")).and_then(|l| log_time(l, today)).expect("the mark");
    let stop = stops.lock().unwrap().iter().copied().find(|&at| at >= slept).expect("a STOP after the sleep");
    stop - slept
}

fn main() {
    support::guest_dir();
    let dir = tempfile::tempdir().unwrap();
    let samples = 60;
    let mut times: Vec<Duration> = (0..samples).map(|_| sample(dir.path())).collect();
    times.sort_unstable();
    println!(
        "guest blocking call (sleep) -> STOP read at the PTY: p50 {:.1} ms, p99 {:.1} ms, max {:.1} ms ({samples} runs)",
        percentile(&times, 0.5).as_secs_f64() * 1e3,
        percentile(&times, 0.99).as_secs_f64() * 1e3,
        times[times.len() - 1].as_secs_f64() * 1e3,
    );
}
