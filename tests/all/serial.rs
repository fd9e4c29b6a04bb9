//! The serial link over real pseudo-terminals. The link's control-loop side
//! is driven with controlled time (`tick(now)`); its I/O thread and the PTY
//! are real, so the tests wait (bounded) for bytes to cross.

use std::io::{Read, Write};
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use serialport::{SerialPort, TTYPort};
use subsume::contract::Value;
use subsume::contract::control::ControlCommand;
use subsume::robot::protocol::{Feedback, Profile};
use subsume::robot::serial::{LinkError, LinkSettings, SerialLink};
use subsume::robot::translator::{DriveGeometry, LinkPlan, ProfileTranslator, TranslateError, Translator};
use subsume::runtime::{Component, StopOutcome};

use crate::support;

const MS: u64 = 1_000_000;
const WAIT: Duration = Duration::from_secs(5);

/// A pseudo-terminal ([`support::pty`], so no child process another test
/// spawns holds it open): the master, with reads that wait 20 ms; the
/// slave; its path.
fn pty() -> (TTYPort, std::fs::File, PathBuf) {
    let (mut master, slave, path) = support::pty();
    master.set_timeout(Duration::from_millis(20)).unwrap();
    (master, slave, path)
}

fn settings(device: &Path, min_interval_ms: u64, watchdog_ms: u64, refresh_ms: u64) -> LinkSettings {
    LinkSettings {
        device: device.to_path_buf(),
        baud: 115_200,
        min_interval_ns: min_interval_ms * MS,
        watchdog_ns: watchdog_ms * MS,
        refresh_ns: refresh_ms * MS,
    }
}

const GEOMETRY: DriveGeometry = DriveGeometry { wheel_base: 0.3, max_wheel_speed: 1.0 };

fn link(device: &Path, min_interval_ms: u64, watchdog_ms: u64, refresh_ms: u64) -> SerialLink {
    let translator = ProfileTranslator::new(Profile::Ascii, GEOMETRY);
    SerialLink::start("motors", settings(device, min_interval_ms, watchdog_ms, refresh_ms), Box::new(translator))
        .unwrap()
}

/// What has arrived at the master end by now (the PTY holds what was
/// written; one read timeout of 20 ms ends the read).
fn read_available(master: &mut TTYPort) -> Vec<u8> {
    let mut bytes = Vec::new();
    let mut buffer = [0u8; 256];
    while let Ok(n) = master.read(&mut buffer) {
        if n == 0 {
            break;
        }
        bytes.extend_from_slice(&buffer[..n]);
    }
    bytes
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
fn a_stop_held_by_the_rate_limit_goes_out_when_the_interval_ends_not_at_the_next_tick() {
    let (mut master, _slave, path) = pty();
    let mut link = link(&path, 100, 10_000, 10_000);
    wait_until("connected", || link.status().connected);
    command(&mut link, "VEL 0.1 0", 0);
    command(&mut link, "STOP", MS);
    assert_eq!(link.next_wake(), Some(100 * MS), "the link asks for a cycle when the interval ends");
    let mut out = Vec::new();
    link.poll(99 * MS, &mut out);
    assert_eq!(link.status().frames_sent, 1, "not before");
    link.poll(100 * MS, &mut out);
    assert_eq!(read_lines(&mut master, 2), vec!["M 100 100", "S"]);
    assert_eq!(link.next_wake(), None);
    // A held motion command still waits for the tick.
    command(&mut link, "VEL 0.2 0", 150 * MS);
    assert_eq!(link.next_wake(), None);
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

/// The bytes `profile` puts on the wire for `command`.
fn frame(profile: Profile, command: &str) -> Vec<u8> {
    let mut out = Vec::new();
    ProfileTranslator::new(profile, GEOMETRY).encode(&command.parse().unwrap(), &mut out).unwrap();
    out
}

#[test]
fn dropping_the_link_sends_stop_last_in_each_profile() {
    for profile in [Profile::Ascii, Profile::Binary] {
        let (mut master, _slave, path) = pty();
        let translator = ProfileTranslator::new(profile, GEOMETRY);
        let mut link = SerialLink::start("motors", settings(&path, 20, 10_000, 10_000), Box::new(translator)).unwrap();
        wait_until("connected", || link.status().connected);
        command(&mut link, "VEL 0.2 0", 0);
        let moving = frame(profile, "VEL 0.2 0");
        let mut wire = Vec::new();
        wait_until("the command arrives", || {
            wire.extend(read_available(&mut master));
            wire.len() >= moving.len()
        });
        assert_eq!(wire, moving, "{profile:?}");
        // The final STOP is written and drained before drop returns.
        drop(link);
        assert_eq!(read_available(&mut master), frame(profile, "STOP"), "{profile:?}");
    }
}

#[test]
fn stop_now_goes_out_at_once_and_the_link_then_holds_stop_until_a_new_command() {
    let (mut master, _slave, path) = pty();
    let mut link = link(&path, 20, 10_000, 100);
    wait_until("connected", || link.status().connected);
    command(&mut link, "VEL 0.2 0", 0);
    assert_eq!(read_lines(&mut master, 1), vec!["M 200 200"]);
    // From another thread, without a tick: the loop is not needed.
    let stop = link.link_stop().clone();
    let outcome = std::thread::spawn(move || stop.stop_now(Duration::from_millis(200))).join().unwrap();
    assert_eq!(outcome, StopOutcome::Sent);
    assert_eq!(read_available(&mut master), b"S\n");
    // The refresh repeats STOP (one period after the loop saw it), not the
    // command from before the stop.
    tick(&mut link, 150 * MS);
    tick(&mut link, 249 * MS);
    tick(&mut link, 250 * MS);
    assert_eq!(read_lines(&mut master, 1), vec!["S"]);
    assert_eq!(link.status().emergency_stops, 1);
    // A new command moves the motors again.
    command(&mut link, "VEL 0.1 0", 300 * MS);
    assert_eq!(read_lines(&mut master, 1), vec!["M 100 100"]);
}

#[test]
fn a_faulted_link_sends_its_final_stop_and_nothing_after() {
    let (mut master, _slave, path) = pty();
    let mut link = link(&path, 20, 10_000, 100);
    wait_until("connected", || link.status().connected);
    command(&mut link, "VEL 0.2 0", 0);
    assert_eq!(read_lines(&mut master, 1), vec!["M 200 200"]);
    link.faulted();
    assert_eq!(read_available(&mut master), b"S\n");
    assert!(link.link_stop().is_halted());
    assert_eq!(link.link_stop().stop_now(Duration::from_millis(200)), StopOutcome::Closed);
    command(&mut link, "VEL 0.3 0", 100 * MS);
    tick(&mut link, 200 * MS);
    wait_until("the link let go of the device", || !link.status().connected);
    assert_eq!(read_available(&mut master), b"", "nothing after the final STOP");
    drop(link);
    assert_eq!(read_available(&mut master), b"", "the final STOP goes out once");
}

#[test]
fn the_final_stop_reaches_a_device_the_link_had_not_opened_yet() {
    let dir = tempfile::tempdir().unwrap();
    let device = dir.path().join("motor-controller");
    let link = link(&device, 20, 10_000, 10_000);
    // The device appears while the link waits in its reconnect backoff.
    let (mut master, _slave, path) = pty();
    std::os::unix::fs::symlink(&path, &device).unwrap();
    drop(link);
    assert_eq!(read_available(&mut master), b"S\n");
}

#[test]
fn a_link_never_stops_a_device_another_link_holds() {
    let (mut master, _slave, path) = pty();
    let mut holder = link(&path, 20, 10_000, 10_000);
    wait_until("connected", || holder.status().connected);
    command(&mut holder, "VEL 0.2 0", 0);
    assert_eq!(read_lines(&mut master, 1), vec!["M 200 200"]);
    // A second link on the same device cannot open it (ports are opened
    // exclusively), so its end must not reach the first one's motors.
    let second = link(&path, 20, 10_000, 10_000);
    assert_eq!(second.link_stop().halt(Duration::from_millis(200)), StopOutcome::NotConnected);
    drop(second);
    assert_eq!(read_available(&mut master), b"");
    command(&mut holder, "VEL 0.1 0", 100 * MS);
    assert_eq!(read_lines(&mut master, 1), vec!["M 100 100"]);
}

/// A translator for hardware without a STOP.
struct NoStop;

impl Translator for NoStop {
    fn encode(&mut self, command: &ControlCommand, out: &mut Vec<u8>) -> Result<(), TranslateError> {
        match command {
            ControlCommand::Stop => Err(TranslateError::Refused("this controller has no stop".into())),
            _ => {
                out.extend_from_slice(b"go\n");
                Ok(())
            }
        }
    }
    fn decode(&mut self, _bytes: &[u8], _out: &mut Vec<Feedback>) -> Result<(), TranslateError> {
        Ok(())
    }
    fn malformed(&self) -> u64 {
        0
    }
}

#[test]
fn a_translator_that_cannot_encode_stop_is_refused_before_the_device_opens() {
    let (mut master, _slave, path) = pty();
    let refused = SerialLink::start("motors", settings(&path, 20, 10_000, 10_000), Box::new(NoStop));
    let Err(error @ LinkError::NoStopFrame(_)) = refused else { panic!("a link without STOP started") };
    assert_eq!(error.to_string(), "the translator cannot encode STOP: this controller has no stop");
    assert_eq!(read_available(&mut master), b"");
}

/// A translator with a link plan: ascii commands, an opening and closing
/// sequence, and a poll that asks for a reading; replies `V <n>` decode to a
/// battery voltage.
struct Planned {
    inner: ProfileTranslator,
    polls: Vec<u64>,
}

impl Translator for Planned {
    fn encode(&mut self, command: &ControlCommand, out: &mut Vec<u8>) -> Result<(), TranslateError> {
        self.inner.encode(command, out)
    }
    fn decode(&mut self, bytes: &[u8], out: &mut Vec<Feedback>) -> Result<(), TranslateError> {
        self.inner.decode(bytes, out)
    }
    fn malformed(&self) -> u64 {
        self.inner.malformed()
    }
    fn plan(&self) -> LinkPlan {
        LinkPlan { opening: b"HELLO\n".to_vec(), poll_period_ns: 100 * MS, closing: b"BYE\n".to_vec() }
    }
    fn poll(&mut self, now_ns: u64, out: &mut Vec<u8>) -> Result<(), TranslateError> {
        self.polls.push(now_ns);
        out.extend_from_slice(b"?\n");
        Ok(())
    }
}

fn planned() -> Box<Planned> {
    Box::new(Planned { inner: ProfileTranslator::new(Profile::Ascii, GEOMETRY), polls: Vec::new() })
}

#[test]
fn the_link_plan_opens_polls_feeds_replies_to_decode_and_closes_after_stop() {
    let (mut master, _slave, path) = pty();
    let mut link = SerialLink::start("motors", settings(&path, 20, 10_000, 10_000), planned()).unwrap();
    wait_until("connected", || link.status().connected);
    // The opening is on the wire before any command.
    assert_eq!(read_lines(&mut master, 1), vec!["HELLO"]);
    assert_eq!(link.status().openings_written, 1);
    command(&mut link, "VEL 0.2 0", 0);
    // Polls at their period on the loop's clock: 0, 100 and 200 ms.
    for ms in [0, 50, 99, 100, 150, 200] {
        tick(&mut link, ms * MS);
    }
    assert_eq!(read_lines(&mut master, 4), vec!["M 200 200", "?", "?", "?"]);
    assert_eq!(link.status().polls_sent, 3);
    // The controller's reply to a poll reaches decode.
    master.write_all(b"P 12600\n").unwrap();
    let mut outputs = Vec::new();
    let mut now = 200 * MS;
    wait_until("the reply is decoded", || {
        now += MS;
        outputs.extend(tick(&mut link, now));
        !outputs.is_empty()
    });
    assert_eq!(outputs[0], (3, Value::Scalar(12.6)));
    read_available(&mut master);
    // Closing: STOP, then the closing bytes, then nothing.
    drop(link);
    assert_eq!(read_available(&mut master), b"S\nBYE\n");
}

#[test]
fn the_opening_is_sent_again_on_every_reconnect_before_any_command() {
    let dir = tempfile::tempdir().unwrap();
    let device = dir.path().join("motor-controller");
    let (mut master, slave, first) = pty();
    std::os::unix::fs::symlink(&first, &device).unwrap();
    let mut link = SerialLink::start("motors", settings(&device, 20, 10_000, 10_000), planned()).unwrap();
    wait_until("connected", || link.status().connected);
    assert_eq!(read_lines(&mut master, 1), vec!["HELLO"]);
    drop(master);
    drop(slave);
    std::fs::remove_file(&device).unwrap();
    wait_until("the loss is noticed", || !link.status().connected);
    let (mut master, _slave, second) = pty();
    std::os::unix::fs::symlink(&second, &device).unwrap();
    wait_until("reconnected", || link.status().connected);
    command(&mut link, "STOP", 100 * MS);
    assert_eq!(read_lines(&mut master, 2), vec!["HELLO", "S"]);
    // The count is the status's: it may come a moment after the bytes (a
    // fresh-clone run on a loaded machine read 1 here). At least two: a
    // loaded machine may make the link reopen once more, and each reopening
    // counts its opening (a fresh-clone run timed out waiting for exactly 2,
    // the bytes above having come in order).
    // Unexplained once (a fresh-clone run, 2026-12-07): the bytes came but
    // the count stayed at 1; the message says what the link saw.
    let deadline = Instant::now() + WAIT;
    while link.status().openings_written < 2 {
        let status = link.status();
        assert!(
            Instant::now() < deadline,
            "timed out waiting until the second opening is counted: openings {}, reconnects {}, connected {}, \
             frames written {}, bytes written {}",
            status.openings_written,
            status.reconnects,
            status.connected,
            status.frames_written,
            status.bytes_written
        );
        std::thread::sleep(Duration::from_millis(5));
    }
}

/// Every module's tests share this process, and a child one of them spawns
/// inherits every descriptor that is not close-on-exec: a controller's
/// pseudo-terminal a child held open would never hang up, and a link would
/// never see its controller go (the reconnect tests above). The ends
/// [`support::pty`] opens are not inherited.
#[test]
fn a_child_process_does_not_keep_a_closed_controllers_terminal_open() {
    use std::os::fd::AsRawFd;
    let (master, slave, _path) = pty();
    let mut child = std::process::Command::new("sleep").arg("30").spawn().unwrap();
    drop(master);
    let mut poll = libc::pollfd { fd: slave.as_raw_fd(), events: libc::POLLIN, revents: 0 };
    // SAFETY: one pollfd for an open descriptor.
    let ready = unsafe { libc::poll(&mut poll, 1, 2000) };
    let _ = child.kill();
    let _ = child.wait();
    assert!(ready == 1 && poll.revents & libc::POLLHUP != 0, "no hang-up: poll {ready}, revents {}", poll.revents);
}
