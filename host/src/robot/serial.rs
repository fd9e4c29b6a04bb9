//! The serial link to the motor controller (`builtin:serial`).
//!
//! On the control loop (graph time, so tests control it): commands arrive on
//! `cmd`; a rate limit lets at most one frame out per `min-interval`,
//! coalescing to the latest command (a burst cannot hammer the motors); a
//! watchdog sends STOP when the command is not refreshed within `watchdog`;
//! the current command is re-sent every `refresh` so the controller's own
//! watchdog stays fed; feedback bytes are decoded by the translator and
//! emitted on `pose`, `ranges`, `bumper`, `battery` and `fault` (the
//! controller's fault status, where its protocol reports one: its text, or
//! empty when it reports none; the link's status keeps the last).
//!
//! On the link's I/O thread: the device (`serialport`) is opened, written and
//! read; when it disappears the link treats the motors as stopped, discards
//! queued frames (never replays stale commands), and reopens it with backoff.
//!
//! Stopping without the loop: the translator's STOP frame is encoded once,
//! when the link starts (a translator that cannot encode STOP is refused).
//! [`LinkStop`], shared with any thread, writes that frame straight to the
//! device, past the queue, and drains it (`tcdrain`): `stop_now` for the
//! stall watchdog (frames the loop made before it are never written; later
//! ones are), `halt` for the end of the link (nothing is written after it).
//! The link halts when it is dropped (every way the host ends a run, an
//! activation that removes or replaces it) and when it faults; the panic
//! hook and the second signal halt every live link (`runtime::halt`).
//!
//! The translator's link plan: its `opening` bytes are written each time the
//! device opens (and reopens), before any frame; its `poll` is called every
//! `poll-period` on the control loop and what it returns (a sensor request,
//! a keep-alive) is queued like a frame, past the rate limit; its `closing`
//! bytes follow the final STOP in the same write. Replies to polls reach the
//! translator's `decode` with the rest of the controller's bytes.
//!
//! Invariants: guest code never reaches the device: only this component
//! writes to it, and only translator output; the control loop never blocks
//! on the device (bounded channels, `try_send`); the last command a link
//! writes is its STOP, followed only by the translator's closing bytes.

use std::io::{ErrorKind, Read, Write};
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::mpsc::{Receiver, RecvTimeoutError, SyncSender, TrySendError};
use std::sync::{Arc, Mutex, MutexGuard, PoisonError, TryLockError, mpsc};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use serde::Serialize;

use super::protocol::Feedback;
use super::translator::{LinkPlan, TranslateError, Translator};
use crate::contract::control::ControlCommand;
use crate::contract::{Scan, Value};
use crate::runtime::lockstep::{Lockstep, LockstepLink, wait_until};
use crate::runtime::{
    CallError, Component, Family, MotorStop, NamedSection, Outbox, Sample, StatusSection, StopOutcome,
};

/// Frames waiting for the I/O thread; more means the device is stuck, and
/// further frames are dropped (and counted) rather than queued.
pub const TX_QUEUE_FRAMES: usize = 16;
/// Chunks of received bytes waiting for the control loop.
pub const RX_QUEUE_CHUNKS: usize = 256;
/// Read timeout on the device: how quickly the I/O threads notice a stop.
pub const READ_TIMEOUT: Duration = Duration::from_millis(50);
/// First and longest wait between attempts to reopen a lost device.
pub const RECONNECT_BACKOFF: (Duration, Duration) = (Duration::from_millis(50), Duration::from_secs(2));
/// Longest a link that is closing waits for its device to take the final
/// STOP: the writer holds the device for at most one frame, each write
/// bounded by `READ_TIMEOUT`.
pub const HALT_WAIT: Duration = Duration::from_millis(500);
/// How often a thread waiting for the device looks again.
const LOCK_POLL: Duration = Duration::from_micros(100);

/// Why a link did not start.
#[derive(Debug, thiserror::Error)]
pub enum LinkError {
    /// Without its STOP frame a link could not stop the motors on its way
    /// out, so it does not start.
    #[error("the translator cannot encode STOP: {0}")]
    NoStopFrame(TranslateError),
    #[error("cannot start the serial thread: {0}")]
    Thread(#[source] std::io::Error),
}

/// A frame for the I/O thread, stamped with the stop generation it was
/// made in: a stop from outside the loop makes older frames stale.
struct Frame {
    generation: u64,
    bytes: Vec<u8>,
}

/// The part of a link any thread may use to stop its motors now, without
/// the control loop (see the module's docs).
pub struct LinkStop {
    name: String,
    device: PathBuf,
    baud: u32,
    /// The translator's STOP, encoded when the link started.
    stop_frame: Vec<u8>,
    /// Written each time the device opens, before any frame.
    opening: Vec<u8>,
    /// Written after the final STOP.
    closing: Vec<u8>,
    /// The device's write side while the I/O thread holds it open.
    port: Mutex<Option<serialport::TTYPort>>,
    /// Bumped by every stop from outside the loop; frames made before it are
    /// never written.
    generation: AtomicU64,
    /// Set by the final STOP: nothing is written after it.
    halted: AtomicBool,
    /// STOPs sent from outside the control loop (the stall watchdog).
    emergency_stops: AtomicU64,
    /// Every byte written to the device (frames, openings, STOPs), for the
    /// lock-step of a simulated clock.
    wire_out: AtomicU64,
}

/// Takes `mutex` if it comes free before `deadline`. A poisoned lock is
/// taken all the same: stopping the motors matters more than the panic
/// that poisoned it.
fn lock_within<T>(mutex: &Mutex<T>, deadline: Instant) -> Option<MutexGuard<'_, T>> {
    loop {
        match mutex.try_lock() {
            Ok(guard) => return Some(guard),
            Err(TryLockError::Poisoned(poisoned)) => return Some(poisoned.into_inner()),
            Err(TryLockError::WouldBlock) if Instant::now() < deadline => std::thread::sleep(LOCK_POLL),
            Err(TryLockError::WouldBlock) => return None,
        }
    }
}

impl LinkStop {
    /// The STOP frame this link sends.
    pub fn stop_frame(&self) -> &[u8] {
        &self.stop_frame
    }

    fn write_stop(&self, port: &mut serialport::TTYPort) -> StopOutcome {
        self.write_bytes(port, &self.stop_frame)
    }

    /// The final STOP and then the translator's closing bytes, in one write.
    fn write_final(&self, port: &mut serialport::TTYPort) -> StopOutcome {
        let mut bytes = self.stop_frame.clone();
        bytes.extend_from_slice(&self.closing);
        self.write_bytes(port, &bytes)
    }

    fn write_bytes(&self, port: &mut serialport::TTYPort, bytes: &[u8]) -> StopOutcome {
        match port.write_all(bytes).and_then(|()| port.flush()) {
            Ok(()) => {
                self.wire_out.fetch_add(bytes.len() as u64, Ordering::Release);
                StopOutcome::Sent
            }
            Err(e) => StopOutcome::Failed(format!("writing to {}: {e}", self.device.display())),
        }
    }

    fn busy(&self, wait: Duration) -> StopOutcome {
        StopOutcome::Failed(format!("{} stayed busy for {} ms", self.device.display(), wait.as_millis()))
    }

    /// Sends STOP now, ahead of the queue, and drains it to the device;
    /// commands the loop makes afterwards still go out.
    pub fn stop_now(&self, wait: Duration) -> StopOutcome {
        if self.halted.load(Ordering::Acquire) {
            return StopOutcome::Closed;
        }
        let Some(mut port) = lock_within(&self.port, Instant::now() + wait) else { return self.busy(wait) };
        if self.halted.load(Ordering::Acquire) {
            return StopOutcome::Closed;
        }
        self.generation.fetch_add(1, Ordering::AcqRel);
        self.emergency_stops.fetch_add(1, Ordering::Relaxed);
        match port.as_mut() {
            Some(port) => self.write_stop(port),
            None => StopOutcome::NotConnected,
        }
    }

    /// Sends the final STOP: nothing is written after it. When the I/O
    /// thread does not hold the device (still opening it, or in its
    /// reconnect backoff), the device is opened once for the STOP; the
    /// open fails while anyone else holds it (ports are opened exclusively),
    /// so a link never stops a device another link drives.
    pub fn halt(&self, wait: Duration) -> StopOutcome {
        let Some(mut port) = lock_within(&self.port, Instant::now() + wait) else {
            self.halted.store(true, Ordering::Release);
            return self.busy(wait);
        };
        if self.halted.swap(true, Ordering::AcqRel) {
            return StopOutcome::Closed;
        }
        self.generation.fetch_add(1, Ordering::AcqRel);
        if let Some(port) = port.as_mut() {
            return self.write_final(port);
        }
        match super::device::open(&self.device, self.baud, READ_TIMEOUT) {
            Ok(mut port) => self.write_final(&mut port),
            Err(_) => StopOutcome::NotConnected,
        }
    }

    /// Whether the final STOP was sent (or tried).
    pub fn is_halted(&self) -> bool {
        self.halted.load(Ordering::Acquire)
    }
}

impl MotorStop for LinkStop {
    fn name(&self) -> &str {
        &self.name
    }

    fn stop_now(&self, wait: Duration) -> StopOutcome {
        LinkStop::stop_now(self, wait)
    }
}

impl crate::runtime::halt::Halt for LinkStop {
    fn label(&self) -> String {
        format!("serial link '{}'", self.name)
    }

    fn halt(&self, wait: Duration) -> StopOutcome {
        LinkStop::halt(self, wait)
    }
}

/// Puts `link` on the process's list of halt actions (the panic hook and
/// the second signal).
fn register(link: &Arc<LinkStop>) {
    let action: Arc<dyn crate::runtime::halt::Halt> = link.clone();
    crate::runtime::halt::register(&action);
}

/// Settings of one link.
#[derive(Clone, Debug, PartialEq)]
pub struct LinkSettings {
    pub device: PathBuf,
    pub baud: u32,
    /// Least time between two frames.
    pub min_interval_ns: u64,
    /// STOP when no command arrived for this long.
    pub watchdog_ns: u64,
    /// Re-send the current command after this long without a frame.
    pub refresh_ns: u64,
}

/// Counters shared with the I/O thread.
#[derive(Debug, Default)]
struct IoCounters {
    connected: AtomicBool,
    /// Open, with the translator's opening written: frames may go out.
    ready: AtomicBool,
    /// Frames handed to the I/O thread (for the lock-step).
    frames_queued: AtomicU64,
    frames_written: AtomicU64,
    bytes_written: AtomicU64,
    bytes_read: AtomicU64,
    reconnects: AtomicU64,
    frames_discarded: AtomicU64,
    rx_dropped: AtomicU64,
    openings_written: AtomicU64,
    stop: AtomicBool,
}

/// The report section of a link.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct SerialStatus {
    pub device: String,
    pub connected: bool,
    pub commands_in: u64,
    pub frames_sent: u64,
    pub frames_written: u64,
    pub bytes_written: u64,
    /// Commands replaced by a newer one before the rate limit let them out.
    pub frames_dropped_rate_limit: u64,
    /// Frames dropped because the device was gone or stuck.
    pub frames_dropped_link: u64,
    pub watchdog_stops: u64,
    pub reconnects: u64,
    pub bytes_read: u64,
    pub feedback_messages: u64,
    pub malformed_feedback: u64,
    /// Commands the translator refused (e.g. GOTO to the motors).
    pub rejected_commands: u64,
    /// STOPs sent from outside the control loop (the stall watchdog).
    pub emergency_stops: u64,
    /// Times the translator's opening bytes were written (each open).
    pub openings_written: u64,
    /// Polls that gave bytes to send (sensor requests, keep-alives).
    pub polls_sent: u64,
    /// The battery's voltage as the controller last reported it, where
    /// its protocol reports one (the lab's self-test reads it).
    pub battery_v: Option<f64>,
    /// The controller's fault as it last reported it (its text, naming
    /// what is wrong), `None` while it reports none; the lab's self-test
    /// reads it.
    pub fault: Option<String>,
    /// Fault statuses the controller reported (with a fault or without):
    /// 0 while it reported none (its protocol has no fault status, or the
    /// translator does not read it).
    pub fault_readings: u64,
    /// The pose `[x m, y m, heading rad]` the controller's odometry last
    /// reported (the lab's reset by driving reads it).
    pub pose: Option<[f64; 3]>,
    /// Distance the commands sent asked for (m): each VEL's speed over the
    /// time it was in force, until the next command, a STOP or a stop from
    /// outside the loop (the lab's self-test compares it with the
    /// odometry's).
    pub commanded_m: f64,
    /// Distance the controller's odometry reported (m): the path through
    /// its poses.
    pub odometry_m: f64,
}

impl NamedSection for SerialStatus {
    const SECTION: &'static str = "serial";

    fn families(&self, component: &str) -> Vec<Family> {
        Family::each(
            ("link", component),
            &[
                (
                    "subsume_serial_frames",
                    "frames written to the motor controller",
                    Sample::Counter(self.frames_written),
                ),
                (
                    "subsume_serial_malformed_feedback",
                    "feedback from the controller that did not parse",
                    Sample::Counter(self.malformed_feedback),
                ),
                (
                    "subsume_serial_reconnects",
                    "times the serial device was opened again",
                    Sample::Counter(self.reconnects),
                ),
                (
                    "subsume_serial_connected",
                    "1 while the serial device is open",
                    Sample::Gauge(if self.connected { 1.0 } else { 0.0 }),
                ),
                (
                    "subsume_serial_controller_fault",
                    "1 while the motor controller reports a fault",
                    Sample::Gauge(if self.fault.is_some() { 1.0 } else { 0.0 }),
                ),
                (
                    "subsume_serial_watchdog_stops",
                    "STOPs sent because commands stopped coming",
                    Sample::Counter(self.watchdog_stops),
                ),
            ],
        )
    }
}

/// The `builtin:serial` component.
pub struct SerialLink {
    name: String,
    settings: LinkSettings,
    translator: Box<dyn Translator>,
    /// How often the translator is polled; 0: never.
    poll_period_ns: u64,
    /// When the translator was last polled.
    last_poll: Option<u64>,
    tx: SyncSender<Frame>,
    rx: Receiver<Vec<u8>>,
    io: Arc<IoCounters>,
    stop: Arc<LinkStop>,
    /// The stop generation this side has seen: a newer one means a STOP went
    /// out past the loop.
    generation: u64,
    thread: Option<JoinHandle<()>>,
    /// The newest command and when it arrived.
    latest_at: Option<u64>,
    /// The command waiting for the rate limit.
    pending: Option<ControlCommand>,
    /// The last command handed to the I/O thread, and when.
    last_sent: Option<(ControlCommand, u64)>,
    /// When `stats.commanded_m` was last brought up to date.
    commanded_at: Option<u64>,
    watchdog_tripped: bool,
    feedback: Vec<Feedback>,
    frame: Vec<u8>,
    stats: SerialStatus,
    /// Held so a simulated clock's lock-step registry (which keeps a weak
    /// reference) keeps this link.
    lockstep: Option<Arc<dyn LockstepLink>>,
    /// The rays' geometry when the ranges are a scan (`with_scan`).
    scan: Option<ScanGeometry>,
}

/// Where the rays of a link's ranges point, when it is known (a simulated
/// robot's `fov` and `max-range`): the ranges go out as a `scan`, ray `i`
/// of `n` at `-fov/2 + i * fov/(n-1)` radians (right to left), as the
/// simulator casts them.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ScanGeometry {
    /// Angle covered by the rays, radians.
    pub fov: f64,
    /// Longest reading, metres ("nothing seen").
    pub max_range: f64,
}

impl ScanGeometry {
    /// `ranges` as a scan with this geometry (the increment follows the
    /// number of readings, so it always matches what arrived).
    pub fn scan(&self, ranges: Vec<f64>) -> Scan {
        let n = ranges.len();
        let (angle_min, angle_increment) =
            if n > 1 { (-self.fov / 2.0, self.fov / (n - 1) as f64) } else { (0.0, 0.0) };
        Scan { angle_min, angle_increment, range_min: 0.0, range_max: self.max_range, ranges }
    }
}

/// Output ports of `builtin:serial`, in order.
pub const OUTPUTS: [&str; 5] = ["pose", "ranges", "bumper", "battery", "fault"];

impl SerialLink {
    /// Encodes the translator's STOP and starts the link's I/O thread (which
    /// opens the device, retrying with backoff until it appears).
    pub fn start(
        name: &str,
        settings: LinkSettings,
        mut translator: Box<dyn Translator>,
    ) -> Result<SerialLink, LinkError> {
        let mut stop_frame = Vec::new();
        translator.encode(&ControlCommand::Stop, &mut stop_frame).map_err(LinkError::NoStopFrame)?;
        let LinkPlan { opening, poll_period_ns, closing } = translator.plan();
        let stop = Arc::new(LinkStop {
            name: name.to_string(),
            device: settings.device.clone(),
            baud: settings.baud,
            stop_frame,
            opening,
            closing,
            port: Mutex::new(None),
            generation: AtomicU64::new(0),
            halted: AtomicBool::new(false),
            emergency_stops: AtomicU64::new(0),
            wire_out: AtomicU64::new(0),
        });
        let (tx, tx_rx) = mpsc::sync_channel(TX_QUEUE_FRAMES);
        let (rx_tx, rx) = mpsc::sync_channel(RX_QUEUE_CHUNKS);
        let io = Arc::new(IoCounters::default());
        let thread_io = io.clone();
        let thread_stop = stop.clone();
        let thread_settings = settings.clone();
        let label = name.to_string();
        let thread = std::thread::Builder::new()
            .name(format!("serial-{name}"))
            .spawn(move || io_thread(&label, &thread_settings, &thread_stop, &tx_rx, &rx_tx, &thread_io))
            .map_err(LinkError::Thread)?;
        register(&stop);
        let stats = SerialStatus { device: settings.device.display().to_string(), ..SerialStatus::default() };
        Ok(SerialLink {
            name: name.to_string(),
            settings,
            translator,
            poll_period_ns,
            last_poll: None,
            tx,
            rx,
            io,
            stop,
            generation: 0,
            thread: Some(thread),
            latest_at: None,
            pending: None,
            last_sent: None,
            commanded_at: None,
            watchdog_tripped: false,
            feedback: Vec::new(),
            frame: Vec::new(),
            stats,
            lockstep: None,
            scan: None,
        })
    }

    /// Emits the ranges as a `scan` with `geometry` (the `ranges` port is
    /// then declared `scan`; see `builtin.rs`).
    pub fn with_scan(mut self, geometry: ScanGeometry) -> SerialLink {
        self.scan = Some(geometry);
        self
    }

    /// Joins the lock-step of a simulated clock: the control loop then waits
    /// for this link's frames to be written and its feedback received.
    pub fn join_lockstep(&mut self, lockstep: &Lockstep) {
        let part: Arc<dyn LockstepLink> = Arc::new(LinkPart {
            device: self.settings.device.clone(),
            io: self.io.clone(),
            stop: self.stop.clone(),
            taken: AtomicU64::new(0),
            expected: AtomicU64::new(0),
        });
        lockstep.join_link(&part);
        self.lockstep = Some(part);
    }

    /// The handle that stops this link's motors from any thread.
    pub fn link_stop(&self) -> &Arc<LinkStop> {
        &self.stop
    }

    /// Takes in a STOP sent past the loop: the motors stand, so nothing
    /// older than it is sent, and the refresh repeats STOP until a new
    /// command arrives.
    fn follow_outside_stops(&mut self, now_ns: u64) {
        let generation = self.stop.generation.load(Ordering::Acquire);
        if generation != self.generation {
            self.count_commanded(now_ns);
            self.generation = generation;
            self.pending = None;
            self.last_sent = Some((ControlCommand::Stop, now_ns));
        }
    }

    /// Adds to `commanded_m` the distance the command in force asked for
    /// since the last count.
    fn count_commanded(&mut self, now_ns: u64) {
        let speed = match self.last_sent {
            Some((ControlCommand::Vel { linear, .. }, _)) if linear.is_finite() => linear.abs(),
            _ => 0.0,
        };
        if let Some(at) = self.commanded_at {
            self.stats.commanded_m += speed * now_ns.saturating_sub(at) as f64 / 1e9;
        }
        self.commanded_at = Some(now_ns);
    }

    /// Queues `command` for the rate limit.
    fn queue(&mut self, command: ControlCommand) {
        if self.pending.replace(command).is_some() {
            self.stats.frames_dropped_rate_limit += 1;
        }
    }

    /// Sends the pending command if the rate limit allows.
    fn flush(&mut self, now_ns: u64) -> Result<(), CallError> {
        let Some(command) = self.pending else { return Ok(()) };
        if self.last_sent.is_some_and(|(_, at)| now_ns.saturating_sub(at) < self.settings.min_interval_ns) {
            return Ok(());
        }
        self.pending = None;
        self.frame.clear();
        match self.translator.encode(&command, &mut self.frame) {
            Ok(()) => {}
            Err(TranslateError::Refused(why)) => {
                self.stats.rejected_commands += 1;
                return Err(CallError::Reported(format!("the translator refused '{command}': {why}")));
            }
            Err(fault @ TranslateError::Fault(_)) => return Err(CallError::Fault(fault.to_string())),
        }
        self.count_commanded(now_ns);
        self.last_sent = Some((command, now_ns));
        self.stats.frames_sent += 1;
        match self.tx.try_send(Frame { generation: self.generation, bytes: self.frame.clone() }) {
            Ok(()) => {
                self.io.frames_queued.fetch_add(1, Ordering::Release);
            }
            Err(TrySendError::Full(_) | TrySendError::Disconnected(_)) => self.stats.frames_dropped_link += 1,
        }
        Ok(())
    }

    /// Polls the translator when its period has passed and queues what it
    /// asks to send.
    fn poll(&mut self, now_ns: u64) -> Result<(), CallError> {
        if self.poll_period_ns == 0 || self.last_poll.is_some_and(|at| now_ns.saturating_sub(at) < self.poll_period_ns)
        {
            return Ok(());
        }
        self.last_poll = Some(now_ns);
        self.frame.clear();
        self.translator.poll(now_ns, &mut self.frame).map_err(|why| CallError::Fault(why.to_string()))?;
        if self.frame.is_empty() {
            return Ok(());
        }
        self.stats.polls_sent += 1;
        match self.tx.try_send(Frame { generation: self.generation, bytes: self.frame.clone() }) {
            Ok(()) => {
                self.io.frames_queued.fetch_add(1, Ordering::Release);
            }
            Err(TrySendError::Full(_) | TrySendError::Disconnected(_)) => self.stats.frames_dropped_link += 1,
        }
        Ok(())
    }

    fn emit_feedback(&mut self, out: &mut Outbox) -> Result<(), CallError> {
        while let Ok(bytes) = self.rx.try_recv() {
            self.translator.decode(&bytes, &mut self.feedback).map_err(|why| CallError::Fault(why.to_string()))?;
        }
        for feedback in self.feedback.drain(..) {
            self.stats.feedback_messages += 1;
            let item = match feedback {
                Feedback::Odometry { x, y, heading } => {
                    if let Some([was_x, was_y, _]) = self.stats.pose
                        && (x - was_x).hypot(y - was_y).is_finite()
                    {
                        self.stats.odometry_m += (x - was_x).hypot(y - was_y);
                    }
                    self.stats.pose = Some([x, y, heading]);
                    (0, Value::Vector(vec![x, y, heading]))
                }
                Feedback::Ranges(ranges) => match &self.scan {
                    Some(geometry) => (1, Value::Scan(geometry.scan(ranges))),
                    None => (1, Value::Vector(ranges)),
                },
                Feedback::Bumper(hit) => (2, Value::Flag(hit)),
                Feedback::Battery(volts) => {
                    self.stats.battery_v = Some(volts);
                    (3, Value::Scalar(volts))
                }
                Feedback::Fault(fault) => {
                    if fault != self.stats.fault {
                        match &fault {
                            Some(text) => {
                                tracing::warn!(component = %self.name, "the motor controller reports a fault: {text}")
                            }
                            None => tracing::info!(component = %self.name, "the motor controller reports no fault"),
                        }
                    }
                    self.stats.fault_readings += 1;
                    let text = fault.clone().unwrap_or_default();
                    self.stats.fault = fault;
                    (4, Value::Text(text))
                }
            };
            out.push(item);
        }
        Ok(())
    }

    /// Current counters.
    pub fn status(&self) -> SerialStatus {
        SerialStatus {
            connected: self.io.connected.load(Ordering::Relaxed),
            frames_written: self.io.frames_written.load(Ordering::Relaxed),
            bytes_written: self.io.bytes_written.load(Ordering::Relaxed),
            reconnects: self.io.reconnects.load(Ordering::Relaxed),
            bytes_read: self.io.bytes_read.load(Ordering::Relaxed),
            frames_dropped_link: self.stats.frames_dropped_link + self.io.frames_discarded.load(Ordering::Relaxed),
            malformed_feedback: self.translator.malformed(),
            emergency_stops: self.stop.emergency_stops.load(Ordering::Relaxed),
            openings_written: self.io.openings_written.load(Ordering::Relaxed),
            ..self.stats.clone()
        }
    }
}

impl Component for SerialLink {
    /// A STOP held back by the rate limit goes out as soon as the interval
    /// ends (an emergency stop must not wait for the link's next tick).
    fn next_wake(&self) -> Option<u64> {
        match (self.pending, self.last_sent) {
            (Some(ControlCommand::Stop), Some((_, at))) => Some(at.saturating_add(self.settings.min_interval_ns)),
            _ => None,
        }
    }

    fn poll(&mut self, now_ns: u64, _out: &mut Outbox) {
        if self.pending == Some(ControlCommand::Stop)
            && let Err(e) = self.flush(now_ns)
        {
            tracing::warn!(component = %self.name, "cannot send a held STOP: {e:?}");
        }
    }

    fn on_input(
        &mut self,
        _port: u32,
        value: &Value,
        _from: usize,
        now_ns: u64,
        _out: &mut Outbox,
    ) -> Result<(), CallError> {
        let Value::Command(command) = value else {
            return Err(CallError::Reported("cmd: expected a control string".into()));
        };
        let command =
            command.parsed().map_err(|e| CallError::Reported(format!("ignored an invalid control string: {e}")))?;
        self.follow_outside_stops(now_ns);
        self.stats.commands_in += 1;
        self.latest_at = Some(now_ns);
        if self.watchdog_tripped {
            self.watchdog_tripped = false;
            tracing::info!(component = %self.name, "commands are flowing again");
        }
        self.queue(command);
        self.flush(now_ns)
    }

    fn tick(&mut self, now_ns: u64, out: &mut Outbox) -> Result<(), CallError> {
        self.follow_outside_stops(now_ns);
        self.count_commanded(now_ns);
        self.emit_feedback(out)?;
        let stale = self.latest_at.is_none_or(|at| now_ns.saturating_sub(at) > self.settings.watchdog_ns);
        if stale && !self.watchdog_tripped && self.last_sent.is_some() {
            self.watchdog_tripped = true;
            self.stats.watchdog_stops += 1;
            tracing::warn!(component = %self.name, "watchdog: no command for {} ms: sending STOP", self.settings.watchdog_ns / 1_000_000);
            self.queue(ControlCommand::Stop);
        }
        let resend = self.last_sent.filter(|(_, at)| now_ns.saturating_sub(*at) >= self.settings.refresh_ns);
        if self.pending.is_none()
            && let Some((command, _)) = resend
        {
            self.pending = Some(if self.watchdog_tripped { ControlCommand::Stop } else { command });
        }
        self.flush(now_ns)?;
        self.poll(now_ns)
    }

    fn status(&self) -> Option<Box<dyn StatusSection>> {
        Some(Box::new(SerialLink::status(self)))
    }

    fn faulted(&mut self) {
        self.halt();
    }

    fn motor_stop(&self) -> Option<Arc<dyn MotorStop>> {
        Some(self.stop.clone())
    }
}

impl SerialLink {
    /// Sends the final STOP (once) and logs what became of it.
    fn halt(&self) {
        if self.stop.is_halted() {
            return;
        }
        match self.stop.halt(HALT_WAIT) {
            StopOutcome::Sent => tracing::info!(component = %self.name, "final STOP sent to the motors"),
            StopOutcome::Closed => {}
            StopOutcome::NotConnected => tracing::info!(
                component = %self.name,
                "{} could not be opened for the final STOP (gone, or held by another link)",
                self.settings.device.display()
            ),
            StopOutcome::Failed(why) => tracing::error!(component = %self.name, "the final STOP failed: {why}"),
        }
    }
}

impl Drop for SerialLink {
    /// The final STOP goes out before the device closes.
    fn drop(&mut self) {
        self.halt();
        self.io.stop.store(true, Ordering::Relaxed);
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
    }
}

/// A link's part in the lock-step of a simulated clock.
struct LinkPart {
    device: PathBuf,
    io: Arc<IoCounters>,
    stop: Arc<LinkStop>,
    /// Bytes written that the robot has been told to read.
    taken: AtomicU64,
    /// Bytes the robot wrote to this link.
    expected: AtomicU64,
}

impl LockstepLink for LinkPart {
    fn device(&self) -> &std::path::Path {
        &self.device
    }

    fn settle(&self, deadline: Instant) -> bool {
        let io = &self.io;
        wait_until(deadline, || {
            io.ready.load(Ordering::Acquire)
                && io.frames_queued.load(Ordering::Acquire)
                    == io.frames_written.load(Ordering::Acquire) + io.frames_discarded.load(Ordering::Acquire)
        })
    }

    fn take_written(&self) -> u64 {
        let written = self.stop.wire_out.load(Ordering::Acquire);
        written.saturating_sub(self.taken.swap(written, Ordering::AcqRel))
    }

    fn expect(&self, bytes: u64) {
        self.expected.fetch_add(bytes, Ordering::AcqRel);
    }

    fn received(&self, deadline: Instant) -> bool {
        let expected = self.expected.load(Ordering::Acquire);
        wait_until(deadline, || self.io.bytes_read.load(Ordering::Acquire) >= expected)
    }
}

/// Opens, writes, reads and reopens the device until told to stop.
fn io_thread(
    name: &str,
    settings: &LinkSettings,
    stop: &LinkStop,
    frames: &Receiver<Frame>,
    received: &SyncSender<Vec<u8>>,
    io: &IoCounters,
) {
    let mut backoff = RECONNECT_BACKOFF.0;
    let mut ever_connected = false;
    let mut warned = false;
    // A halted link has sent its final STOP: it neither writes nor reopens.
    while !io.stop.load(Ordering::Relaxed) && !stop.is_halted() {
        let opened = super::device::open(&settings.device, settings.baud, READ_TIMEOUT);
        let port = match opened {
            Ok(port) => port,
            Err(err) => {
                if !warned {
                    tracing::warn!(component = name, "cannot open {}: {err}; retrying", settings.device.display());
                    warned = true;
                }
                sleep_unless_stopped(backoff, io);
                backoff = (backoff * 2).min(RECONNECT_BACKOFF.1);
                continue;
            }
        };
        // Frames queued while the device was gone are stale: never replay them.
        let stale = frames.try_iter().count() as u64;
        io.frames_discarded.fetch_add(stale, Ordering::Release);
        if ever_connected {
            io.reconnects.fetch_add(1, Ordering::Relaxed);
            tracing::info!(component = name, "reconnected to {}", settings.device.display());
        } else {
            tracing::info!(component = name, "connected to {} at {} baud", settings.device.display(), settings.baud);
        }
        ever_connected = true;
        warned = false;
        backoff = RECONNECT_BACKOFF.0;
        io.connected.store(true, Ordering::Relaxed);
        let failure = run_connection(port, stop, frames, received, io);
        io.connected.store(false, Ordering::Relaxed);
        if let Some(why) = failure {
            tracing::warn!(
                component = name,
                "lost {}: {why}; motors treated as stopped; reconnecting",
                settings.device.display()
            );
            sleep_unless_stopped(backoff, io);
        }
    }
}

/// Serves one open device until it fails (returns why) or a stop is asked:
/// a reader thread feeds received bytes to the control loop while this
/// thread writes frames. The port's write side lives in `stop` meanwhile, so
/// any thread can write the STOP frame.
fn run_connection(
    port: serialport::TTYPort,
    stop: &LinkStop,
    frames: &Receiver<Frame>,
    received: &SyncSender<Vec<u8>>,
    io: &IoCounters,
) -> Option<String> {
    let mut reader = match port.try_clone_native() {
        Ok(reader) => reader,
        Err(err) => return Some(format!("cannot clone the port for reading: {err}")),
    };
    {
        let mut slot = stop.port.lock().unwrap_or_else(PoisonError::into_inner);
        let mut port = port;
        if stop.halted.load(Ordering::Acquire) {
            // Halted while the device was opening: the final STOP is ours.
            let _ = stop.write_final(&mut port);
            return None;
        }
        // The opening goes first: no frame can reach the device before it,
        // since frames are written under this lock.
        if !stop.opening.is_empty() {
            if let StopOutcome::Failed(why) = stop.write_bytes(&mut port, &stop.opening) {
                return Some(format!("the opening sequence failed: {why}"));
            }
            io.openings_written.fetch_add(1, Ordering::Relaxed);
        }
        *slot = Some(port);
        io.ready.store(true, Ordering::Release);
    }
    let failed = Mutex::new(None::<String>);
    std::thread::scope(|scope| {
        scope.spawn(|| read_loop(&mut reader, stop, received, io, &failed));
        if let Some(why) = write_loop(stop, frames, io, &failed) {
            set_failed(&failed, why);
        }
    });
    io.ready.store(false, Ordering::Release);
    drop(stop.port.lock().unwrap_or_else(PoisonError::into_inner).take());
    failed.into_inner().ok().flatten()
}

fn set_failed(failed: &Mutex<Option<String>>, why: String) {
    if let Ok(mut slot) = failed.lock() {
        slot.get_or_insert(why);
    }
}

fn is_failed(failed: &Mutex<Option<String>>) -> bool {
    failed.lock().map(|f| f.is_some()).unwrap_or(true)
}

fn write_loop(
    stop: &LinkStop,
    frames: &Receiver<Frame>,
    io: &IoCounters,
    failed: &Mutex<Option<String>>,
) -> Option<String> {
    loop {
        if io.stop.load(Ordering::Relaxed) || stop.is_halted() || is_failed(failed) {
            return None;
        }
        match frames.recv_timeout(READ_TIMEOUT) {
            Ok(frame) => {
                let mut port = stop.port.lock().unwrap_or_else(PoisonError::into_inner);
                // Under the lock a STOP from outside cannot slip in between
                // this check and the write.
                if stop.halted.load(Ordering::Acquire) || frame.generation != stop.generation.load(Ordering::Acquire) {
                    io.frames_discarded.fetch_add(1, Ordering::Release);
                    continue;
                }
                let Some(port) = port.as_mut() else { return Some("the device was closed".into()) };
                if let Err(err) = port.write_all(&frame.bytes).and_then(|()| port.flush()) {
                    return Some(format!("write failed: {err}"));
                }
                stop.wire_out.fetch_add(frame.bytes.len() as u64, Ordering::Release);
                io.bytes_written.fetch_add(frame.bytes.len() as u64, Ordering::Relaxed);
                io.frames_written.fetch_add(1, Ordering::Release);
            }
            Err(RecvTimeoutError::Timeout) => {}
            Err(RecvTimeoutError::Disconnected) => return None,
        }
    }
}

fn read_loop(
    port: &mut serialport::TTYPort,
    stop: &LinkStop,
    received: &SyncSender<Vec<u8>>,
    io: &IoCounters,
    failed: &Mutex<Option<String>>,
) {
    let mut buffer = [0u8; 1024];
    while !io.stop.load(Ordering::Relaxed) && !stop.is_halted() && !is_failed(failed) {
        match port.read(&mut buffer) {
            Ok(0) => {
                set_failed(failed, "the device closed".into());
                return;
            }
            Ok(n) => {
                if received.try_send(buffer[..n].to_vec()).is_err() {
                    io.rx_dropped.fetch_add(1, Ordering::Relaxed);
                }
                // Counted once handed on: the lock-step waits for this.
                io.bytes_read.fetch_add(n as u64, Ordering::Release);
            }
            Err(e)
                if e.kind() == ErrorKind::TimedOut
                    || e.kind() == ErrorKind::WouldBlock
                    || e.kind() == ErrorKind::Interrupted => {}
            Err(e) => {
                set_failed(failed, format!("read failed: {e}"));
                return;
            }
        }
    }
}

fn sleep_unless_stopped(total: Duration, io: &IoCounters) {
    let step = Duration::from_millis(10);
    let mut slept = Duration::ZERO;
    while slept < total && !io.stop.load(Ordering::Relaxed) {
        std::thread::sleep(step);
        slept += step;
    }
}
