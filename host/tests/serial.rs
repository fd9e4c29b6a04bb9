#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic)]
//! The serial link over real pseudo-terminals. The link's control-loop side
//! is driven with controlled time (`tick(now)`); its I/O thread and the PTY
//! are real, so the tests wait (bounded) for bytes to cross.

use std::io::{Read, Write};
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use serialport::{SerialPort, TTYPort};
use subsume::contract::Value;
use subsume::robot::protocol::Profile;
use subsume::robot::serial::{LinkSettings, SerialLink};
use subsume::robot::translator::{DriveGeometry, ProfileTranslator};
use subsume::runtime::Component;

const MS: u64 = 1_000_000;
const WAIT: Duration = Duration::from_secs(5);

fn pty() -> (TTYPort, TTYPort, PathBuf) {
    let (mut master, slave) = TTYPort::pair().unwrap();
    master.set_timeout(Duration::from_millis(20)).unwrap();
    let path = PathBuf::from(slave.name().unwrap());
    (master, slave, path)
}

fn link(device: &Path, min_interval_ms: u64, watchdog_ms: u64, refresh_ms: u64) -> SerialLink {
    let settings = LinkSettings {
        device: device.to_path_buf(),
        baud: 115_200,
        min_interval_ns: min_interval_ms * MS,
        watchdog_ns: watchdog_ms * MS,
        refresh_ns: refresh_ms * MS,
    };
    let translator = ProfileTranslator::new(Profile::Ascii, DriveGeometry { wheel_base: 0.3, max_wheel_speed: 1.0 });
    SerialLink::start("motors", settings, Box::new(translator)).unwrap()
}

fn wait_until(what: &str, mut condition: impl FnMut() -> bool) {
    let deadline = Instant::now() + WAIT;
    while !condition() {
        assert!(Instant::now() < deadline, "timed out waiting until {what}");
        std::thread::sleep(Duration::from_millis(5));
    }
}

/// Reads from the master end until `lines` whole lines arrived.
fn read_lines(master: &mut TTYPort, lines: usize) -> Vec<String> {
    let mut text = String::new();
    let mut buffer = [0u8; 256];
    let deadline = Instant::now() + WAIT;
    while text.matches('\n').count() < lines {
        assert!(Instant::now() < deadline, "timed out reading {lines} lines, got {text:?}");
        if let Ok(n) = master.read(&mut buffer) {
            text.push_str(&String::from_utf8_lossy(&buffer[..n]));
        }
    }
    text.lines().map(str::to_string).collect()
}

fn command(link: &mut SerialLink, text: &str, now_ns: u64) {
    let mut out = Vec::new();
    link.on_input(0, &Value::Command(text.into()), 0, now_ns, &mut out).unwrap();
}

fn tick(link: &mut SerialLink, now_ns: u64) -> Vec<(u32, Value)> {
    let mut out = Vec::new();
    link.tick(now_ns, &mut out).unwrap();
    out
}

#[test]
fn a_burst_is_rate_limited_to_the_latest_command() {
    let (mut master, _slave, path) = pty();
    let mut link = link(&path, 100, 10_000, 10_000);
    wait_until("connected", || link.status().connected);
    command(&mut link, "VEL 0.1 0", 0);
    for (i, speed) in ["0.2", "0.3", "0.4", "0.5"].iter().enumerate() {
        command(&mut link, &format!("VEL {speed} 0"), (i as u64 + 1) * MS);
    }
    tick(&mut link, 50 * MS);
    assert_eq!(link.status().frames_sent, 1, "the rate limit holds the burst back");
    tick(&mut link, 100 * MS);
    assert_eq!(read_lines(&mut master, 2), vec!["M 100 100", "M 500 500"]);
    let status = link.status();
    assert_eq!((status.frames_sent, status.frames_dropped_rate_limit, status.commands_in), (2, 3, 5));
    wait_until("both frames written", || link.status().frames_written == 2);
    assert_eq!(link.status().bytes_written, 20);
}

#[test]
fn the_watchdog_sends_stop_when_commands_stop_coming() {
    let (mut master, _slave, path) = pty();
    let mut link = link(&path, 20, 300, 10_000);
    wait_until("connected", || link.status().connected);
    command(&mut link, "VEL 0.2 0", 0);
    for ms in [100, 200, 300] {
        tick(&mut link, ms * MS);
    }
    assert_eq!(link.status().watchdog_stops, 0, "not stale yet at exactly the timeout");
    tick(&mut link, 301 * MS);
    assert_eq!(read_lines(&mut master, 2), vec!["M 200 200", "S"]);
    assert_eq!(link.status().watchdog_stops, 1);
    // A fresh command lifts the watchdog.
    command(&mut link, "VEL 0.1 0", 400 * MS);
    assert_eq!(read_lines(&mut master, 1), vec!["M 100 100"]);
}

#[test]
fn the_current_command_is_refreshed() {
    let (mut master, _slave, path) = pty();
    let mut link = link(&path, 20, 10_000, 100);
    wait_until("connected", || link.status().connected);
    command(&mut link, "VEL 0 1", 0);
    tick(&mut link, 99 * MS);
    tick(&mut link, 100 * MS);
    assert_eq!(read_lines(&mut master, 2), vec!["M -150 150", "M -150 150"]);
}

#[test]
fn garbage_from_the_controller_is_counted_and_skipped() {
    let (mut master, _slave, path) = pty();
    let mut link = link(&path, 20, 10_000, 10_000);
    wait_until("connected", || link.status().connected);
    master.write_all(b"garbage\nO 1000 2000 500\n\xff\xfe\x00\nR 500 600\nB 1\nP -4\n").unwrap();
    let mut outputs = Vec::new();
    let mut now = 0;
    wait_until("feedback arrives", || {
        now += MS;
        outputs.extend(tick(&mut link, now));
        outputs.len() >= 3
    });
    assert_eq!(
        outputs,
        vec![(0, Value::Vector(vec![1.0, 2.0, 0.5])), (1, Value::Vector(vec![0.5, 0.6])), (2, Value::Flag(true))]
    );
    wait_until("the last line is decoded", || {
        now += MS;
        tick(&mut link, now);
        link.status().malformed_feedback == 3
    });
}

#[test]
fn the_link_reconnects_when_the_far_end_closes_and_comes_back_and_replays_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let device = dir.path().join("motor-controller");
    let (master, slave, first) = pty();
    std::os::unix::fs::symlink(&first, &device).unwrap();
    let mut link = link(&device, 20, 10_000, 10_000);
    wait_until("connected", || link.status().connected);

    // The controller goes away.
    drop(master);
    drop(slave);
    std::fs::remove_file(&device).unwrap();
    wait_until("the loss is noticed", || !link.status().connected);
    // Commands sent meanwhile go nowhere: they must not reach the motors later.
    command(&mut link, "VEL 0.4 0", 0);
    command(&mut link, "VEL 0.4 0", 50 * MS);

    let (mut master, _slave, second) = pty();
    std::os::unix::fs::symlink(&second, &device).unwrap();
    wait_until("reconnected", || link.status().connected);
    assert_eq!(link.status().reconnects, 1);
    command(&mut link, "STOP", 100 * MS);
    assert_eq!(read_lines(&mut master, 1), vec!["S"], "stale frames were replayed");
    assert!(link.status().frames_dropped_link >= 1);
}
