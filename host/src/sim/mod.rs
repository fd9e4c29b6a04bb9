//! The simulated robot (`builtin:sim`): a differential-drive robot in a 2D
//! world, behind a real pseudo-terminal. Its thread plays the motor
//! controller: it reads command bytes from the PTY's master end, speaks the
//! same protocol as real firmware (`robot::protocol`), moves the robot and
//! writes odometry, range and bumper feedback back. With `protocol` set to
//! `create2` it speaks the iRobot Create 2 Open Interface instead
//! ([`create2`]): the demo then runs "as a Create 2", with the Create 2
//! WASM translator on the host's side. The host's serial link
//! opens the PTY's other end like any serial device, so the bytes cross a
//! real tty exactly as they would cross a cable.
//!
//! [`SimControl`] resets, poses, pauses and single-steps a robot (for tests
//! and the portal). On a simulated clock the robot has no thread: it joins
//! the clock's lock-step (`runtime::lockstep`) and the control loop steps it
//! to each cycle's simulated time.
//!
//! Invariants: nothing but bytes on the PTY connects the host to the
//! simulated controller; the simulation keeps its own time (real time, or
//! the simulated clock's in lock-step) and the controller's watchdog and
//! feedback follow it, so the same bytes at the same times give the same
//! feedback.

pub mod builtin;
pub mod create2;
pub mod perturb;
pub mod physics;
pub mod world;

use std::io::{ErrorKind, Read, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use serialport::{SerialPort, TTYPort};

use self::create2::{OpenInterface, Readings, WheelCommand};
use self::physics::{Body, SimStatus, Simulation};
use self::world::World;
use crate::robot::protocol::{Decoder, Feedback, Message, MotorCommand, Profile};
use crate::runtime::lockstep::{Lockstep, LockstepSim};
use crate::runtime::{Component, NamedSection, StatusSection};

/// Why a simulated robot did not start.
#[derive(Debug, thiserror::Error)]
pub enum SimError {
    #[error("the start ({x}, {y}) {why}")]
    StartBlocked { x: f64, y: f64, why: String },
    #[error("{0}")]
    BadPose(String),
    #[error("{0}")]
    Control(String),
    #[error("cannot create a pseudo-terminal: {0}")]
    Pty(String),
    #[error("cannot start the simulation thread: {0}")]
    Thread(#[from] std::io::Error),
}
/// How often the simulated controller reads, steps and may send feedback.
pub const SIM_PERIOD: Duration = Duration::from_millis(5);
/// Longest time one step of the controller's loop catches up on. The
/// simulation runs in real time, so when its thread waited for a core (a
/// loaded machine) it steps the whole wait (in physics steps of
/// `physics::MAX_STEP_S`); only a longer stall loses time, which bounds the
/// physics steps one iteration computes (200).
pub const MAX_CATCH_UP: Duration = Duration::from_secs(1);
/// Simulated battery voltage reported in feedback.
pub const BATTERY_VOLTS: f64 = 12.6;

/// Settings of one simulated robot.
#[derive(Clone, Debug)]
pub struct SimSettings {
    pub world: World,
    pub body: Body,
    pub protocol: SimProtocol,
    /// Feedback messages (odometry, ranges, bumper) per second.
    pub feedback_hz: f64,
    /// The simulated controller stops the wheels when no command came for
    /// this long (real controllers have such a watchdog too).
    pub controller_watchdog: Duration,
    /// Seeded sensor latency, range noise and serial delay (`subsume run
    /// --perturb`); none: the lock-step's own timing.
    pub timing: Option<perturb::SimTiming>,
}

/// The wire protocol of a simulated controller.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SimProtocol {
    /// A built-in profile (docs/protocols.md).
    Profile(Profile),
    /// The iRobot Create 2 Open Interface ([`create2`]).
    Create2,
}

impl SimProtocol {
    pub fn parse(name: &str) -> Option<SimProtocol> {
        match name {
            "create2" => Some(SimProtocol::Create2),
            other => Profile::parse(other).map(SimProtocol::Profile),
        }
    }
}

/// Longest single step a caller may ask of a paused simulation: a longer
/// one would hold the simulation (and its controller) for long.
pub const MAX_SINGLE_STEP_S: f64 = 10.0;

/// One side of the wire, as the simulated controller speaks it.
enum Wire {
    Profile { profile: Profile, decoder: Decoder, messages: Vec<Message> },
    Create2(OpenInterface),
}

/// The simulated controller without its pseudo-terminal: takes the bytes
/// read, steps the physics by the time it is told, makes the feedback that
/// is due. Time is the simulation's own (`Simulation::time_s`), so the same
/// bytes and steps give the same feedback.
struct Core {
    sim: Simulation,
    wire: Wire,
    settings: SimSettings,
    commands: Vec<WheelCommand>,
    feedback_period_s: f64,
    /// Simulated time of the last command and of the last feedback.
    last_command_s: f64,
    last_feedback_s: Option<f64>,
    /// Paused: time stands still; commands are taken, not acted on.
    paused: bool,
    /// Send feedback now (after a reset, a new pose, a single step).
    feedback_now: bool,
    commands_received: u64,
    malformed: u64,
    /// Seeded delays and noise ([`SimSettings::timing`]).
    timing: Option<perturb::SimTiming>,
}

impl Core {
    fn new(sim: Simulation, mut settings: SimSettings) -> Core {
        let timing = settings.timing.take();
        let wire = match settings.protocol {
            SimProtocol::Profile(profile) => {
                Wire::Profile { profile, decoder: Decoder::new(profile), messages: Vec::new() }
            }
            SimProtocol::Create2 => Wire::Create2(OpenInterface::new(settings.body.geometry.wheel_base)),
        };
        let feedback_period_s = 1.0 / settings.feedback_hz.max(0.1);
        Core {
            sim,
            wire,
            settings,
            commands: Vec::new(),
            feedback_period_s,
            last_command_s: 0.0,
            last_feedback_s: None,
            paused: false,
            feedback_now: false,
            commands_received: 0,
            malformed: 0,
            timing,
        }
    }

    /// Takes bytes from the host and acts on the commands in them.
    fn feed(&mut self, bytes: &[u8]) {
        match &mut self.wire {
            Wire::Profile { decoder, messages, .. } => {
                decoder.feed(bytes, messages);
                for message in messages.drain(..) {
                    match message {
                        Message::Command(MotorCommand::Wheels { left, right }) => {
                            self.commands.push(WheelCommand::Wheels(left, right));
                        }
                        Message::Command(MotorCommand::Stop) => self.commands.push(WheelCommand::Stop),
                        Message::Feedback(_) => self.malformed += 1,
                    }
                }
            }
            Wire::Create2(oi) => {
                let before = oi.malformed();
                oi.feed(bytes, &mut self.commands);
                self.malformed += oi.malformed() - before;
            }
        }
        for command in self.commands.drain(..) {
            let (left, right) = match command {
                WheelCommand::Wheels(left, right) => (left, right),
                WheelCommand::Stop => (0.0, 0.0),
            };
            self.commands_received += 1;
            if self.paused {
                continue;
            }
            match &mut self.timing {
                Some(timing) if timing.holds_commands() => timing.hold_command(self.sim.time_s(), left, right),
                _ => {
                    self.sim.set_wheels(left, right);
                    self.last_command_s = self.sim.time_s();
                }
            }
        }
    }

    /// Advances the world by `dt` seconds unless paused; the controller's
    /// watchdog stops the wheels when no command came for its time.
    fn step(&mut self, dt: f64) {
        if self.paused {
            return;
        }
        self.advance(dt);
    }

    /// Advances the world by `dt` seconds, acting on each held command
    /// ([`SimSettings::timing`]) at its time within them.
    fn advance(&mut self, dt: f64) {
        let Some(timing) = &mut self.timing else { return self.run(dt) };
        let end = self.sim.time_s() + dt;
        let mut next = timing.next_command_by(end);
        while let Some((at, left, right)) = next {
            let before = at - self.sim.time_s();
            if before > 0.0 {
                self.run(before);
            }
            self.sim.set_wheels(left, right);
            self.last_command_s = self.sim.time_s();
            next = self.timing.as_mut().and_then(|t| t.next_command_by(end));
        }
        let rest = end - self.sim.time_s();
        if rest > 0.0 {
            self.run(rest);
        }
    }

    fn run(&mut self, dt: f64) {
        if self.sim.time_s() - self.last_command_s > self.settings.controller_watchdog.as_secs_f64() {
            self.sim.set_wheels(0.0, 0.0);
        }
        self.sim.step(dt);
        if let Wire::Create2(oi) = &mut self.wire {
            oi.track(self.sim.pose());
        }
    }

    /// The feedback bytes that are due now, appended to `out`.
    fn feedback(&mut self, out: &mut Vec<u8>) {
        let now = self.sim.time_s();
        let due = self.last_feedback_s.is_none_or(|last| now - last >= self.feedback_period_s - 1e-9);
        if due || self.feedback_now {
            self.feedback_now = false;
            self.last_feedback_s = Some(now);
            if self.timing.as_ref().is_some_and(perturb::SimTiming::holds_feedback) {
                let mut measured = Vec::new();
                self.measure(&mut measured);
                if let Some(timing) = &mut self.timing {
                    timing.hold_feedback(now, measured);
                }
            } else {
                self.measure(out);
            }
        }
        if let Some(timing) = &mut self.timing {
            timing.release_feedback(now, out);
        }
    }

    /// The feedback of this moment (ranges with their seeded noise, if
    /// any), appended to `out`.
    fn measure(&mut self, out: &mut Vec<u8>) {
        let sim = &self.sim;
        let max_range = self.settings.body.max_range;
        let mut ranges = sim.ranges();
        if let Some(timing) = &mut self.timing {
            timing.add_noise(&mut ranges, max_range);
        }
        match &self.wire {
            Wire::Profile { profile, .. } => {
                let (x, y, heading) = sim.pose();
                profile.encode_feedback(&Feedback::Odometry { x, y, heading }, out);
                profile.encode_feedback(&Feedback::Ranges(ranges), out);
                profile.encode_feedback(&Feedback::Bumper(sim.bumper()), out);
                profile.encode_feedback(&Feedback::Battery(BATTERY_VOLTS), out);
            }
            Wire::Create2(oi) => {
                let readings = Readings { bumper: sim.bumper(), volts: BATTERY_VOLTS, ranges, max_range };
                out.extend(oi.frame(&readings).unwrap_or_default());
            }
        }
    }

    /// Back to the start: the world's start pose, time 0, counters cleared.
    fn reset(&mut self) {
        self.sim.reset();
        self.last_command_s = 0.0;
        self.last_feedback_s = None;
        self.feedback_now = true;
        if let Wire::Create2(oi) = &mut self.wire {
            *oi = OpenInterface::new(self.settings.body.geometry.wheel_base);
        }
        if let Some(timing) = &mut self.timing {
            timing.clear();
        }
    }
}

/// What the simulated controller shares with the host.
struct Shared {
    core: Mutex<Core>,
    stop: AtomicBool,
}

impl std::fmt::Debug for Shared {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("simulated robot")
    }
}

impl Shared {
    fn core(&self) -> std::sync::MutexGuard<'_, Core> {
        self.core.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
    }
}

/// Controls a simulated robot from outside (tests, the portal): reset, set
/// the pose, pause, single-step. Each action takes effect at once, between
/// two steps of the simulated controller.
#[derive(Clone)]
pub struct SimControl {
    shared: Arc<Shared>,
}

impl std::fmt::Debug for SimControl {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("SimControl")
    }
}

impl SimControl {
    /// The robot back at the world's start, at rest, time 0.
    pub fn reset(&self) -> SimStatus {
        let mut core = self.shared.core();
        core.reset();
        core.sim.status()
    }

    /// The robot at (`x`, `y`), facing `heading` (rad), at rest.
    pub fn set_pose(&self, x: f64, y: f64, heading: f64) -> Result<SimStatus, SimError> {
        let mut core = self.shared.core();
        core.sim.set_pose(x, y, heading)?;
        core.feedback_now = true;
        Ok(core.sim.status())
    }

    /// Pauses (time stands still, the wheels stop) or resumes.
    pub fn pause(&self, paused: bool) -> SimStatus {
        let mut core = self.shared.core();
        if paused && !core.paused {
            core.sim.set_wheels(0.0, 0.0);
        }
        if !paused && core.paused {
            // The controller's watchdog counts from the resumption.
            core.last_command_s = core.sim.time_s();
        }
        core.paused = paused;
        core.feedback_now = true;
        core.sim.status()
    }

    /// While paused: runs the world `seconds` forward with the wheels as
    /// they are (at rest unless set with [`SimControl::set_wheels`]).
    pub fn step(&self, seconds: f64) -> Result<SimStatus, SimError> {
        if !(seconds > 0.0 && seconds <= MAX_SINGLE_STEP_S) {
            return Err(SimError::Control(format!(
                "a step must be more than 0 and at most {MAX_SINGLE_STEP_S} s, got {seconds}"
            )));
        }
        let mut core = self.shared.core();
        if !core.paused {
            return Err(SimError::Control("the simulation is running: pause it before stepping".into()));
        }
        core.advance(seconds);
        core.last_command_s = core.sim.time_s();
        core.feedback_now = true;
        Ok(core.sim.status())
    }

    /// While paused: sets the wheel speeds (m/s) the next steps use.
    pub fn set_wheels(&self, left: f64, right: f64) -> Result<(), SimError> {
        let mut core = self.shared.core();
        if !core.paused {
            return Err(SimError::Control("the simulation is running: its controller drives the wheels".into()));
        }
        core.sim.set_wheels(left, right);
        // As a command would: the controller's watchdog counts from now.
        core.last_command_s = core.sim.time_s();
        Ok(())
    }

    /// The world and the robot's body it runs with (they never change
    /// while it runs): what a camera needs besides the status.
    pub fn world_and_body(&self) -> (World, Body) {
        let core = self.shared.core();
        (core.settings.world.clone(), core.settings.body)
    }

    pub fn is_paused(&self) -> bool {
        self.shared.core().paused
    }

    pub fn status(&self) -> SimStatus {
        self.shared.core().sim.status()
    }
}

/// The simulated robots this host runs, by component name, for the portal's
/// simulator controls: provided through `builtin::Services`, filled by
/// `builtin:sim` when it starts a robot.
#[derive(Debug, Default)]
pub struct SimRegistry {
    robots: Mutex<Vec<(String, std::sync::Weak<Shared>)>>,
}

impl SimRegistry {
    fn add(&self, name: &str, robot: &SimulatedRobot) {
        if let Ok(mut robots) = self.robots.lock() {
            // A robot built beside a running one of the same name (an
            // activation) takes its name; the running one has it back if
            // the new one goes (an activation that did not happen).
            robots.retain(|(_, r)| r.strong_count() > 0);
            robots.push((name.to_string(), Arc::downgrade(&robot.shared)));
        }
    }

    /// The control of the running robot named `name`, if it runs.
    pub fn get(&self, name: &str) -> Option<SimControl> {
        let robots = self.robots.lock().ok()?;
        robots
            .iter()
            .rev()
            .filter(|(n, _)| n == name)
            .find_map(|(_, r)| r.upgrade())
            .map(|shared| SimControl { shared })
    }
}

/// A running simulated robot: the path of the PTY end the host opens, and
/// either its controller thread (real time) or its part in the lock-step
/// of a simulated clock.
pub struct SimulatedRobot {
    pty_path: PathBuf,
    shared: Arc<Shared>,
    thread: Option<JoinHandle<()>>,
    /// Held so the lock-step registry (which keeps a weak reference) keeps it.
    _lockstep: Option<Arc<dyn LockstepSim>>,
}

impl SimulatedRobot {
    /// Creates the PTY pair and starts the controller thread, in real time;
    /// with `lockstep`, joins it instead: the control loop then steps the
    /// controller before each cycle.
    pub fn start(
        name: &str,
        settings: SimSettings,
        lockstep: Option<&Arc<Lockstep>>,
    ) -> Result<SimulatedRobot, SimError> {
        let simulation = Simulation::new(settings.world.clone(), settings.body)?;
        let (mut master, slave) = TTYPort::pair().map_err(|e| SimError::Pty(e.to_string()))?;
        let pty_path = slave.name().map(PathBuf::from).ok_or_else(|| SimError::Pty("it has no name".into()))?;
        let timeout = if lockstep.is_some() { LOCKSTEP_READ_TIMEOUT } else { SIM_PERIOD };
        master.set_timeout(timeout).map_err(|e| SimError::Pty(e.to_string()))?;
        let shared =
            Arc::new(Shared { core: Mutex::new(Core::new(simulation, settings)), stop: AtomicBool::new(false) });
        if let Some(lockstep) = lockstep {
            let part: Arc<dyn LockstepSim> = Arc::new(LockstepPart {
                device: pty_path.clone(),
                shared: shared.clone(),
                port: Mutex::new(PortSide { master, _slave: slave, bytes_in: 0, last_ns: None }),
            });
            lockstep.join_sim(&part);
            tracing::info!(component = name, "simulated robot on {} (simulated time)", pty_path.display());
            return Ok(SimulatedRobot { pty_path, shared, thread: None, _lockstep: Some(part) });
        }
        let thread_shared = shared.clone();
        let label = name.to_string();
        let thread = std::thread::Builder::new().name(format!("sim-{name}")).spawn(move || {
            // The slave end stays open here so the master never sees a
            // hang-up while the host's link reconnects.
            let _slave = slave;
            controller(&label, master, &thread_shared);
        })?;
        tracing::info!(component = name, "simulated robot on {}", pty_path.display());
        Ok(SimulatedRobot { pty_path, shared, thread: Some(thread), _lockstep: None })
    }

    /// The device path the host's serial link opens.
    pub fn pty_path(&self) -> &PathBuf {
        &self.pty_path
    }

    pub fn status(&self) -> SimStatus {
        self.shared.core().sim.status()
    }

    /// The handle that resets, poses, pauses and steps this robot.
    pub fn control(&self) -> SimControl {
        SimControl { shared: self.shared.clone() }
    }

    /// Lists this robot in `registry` under `name`.
    pub fn register(&self, name: &str, registry: &SimRegistry) {
        registry.add(name, self);
    }
}

impl Drop for SimulatedRobot {
    fn drop(&mut self) {
        self.shared.stop.store(true, Ordering::Relaxed);
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
    }
}

/// Read timeout on the PTY in lock-step: how long one read waits for bytes
/// the link has already written.
const LOCKSTEP_READ_TIMEOUT: Duration = Duration::from_millis(1);

/// The pseudo-terminal side of a robot in lock-step.
struct PortSide {
    master: TTYPort,
    _slave: TTYPort,
    bytes_in: u64,
    /// Simulated time of the last advance.
    last_ns: Option<u64>,
}

/// A simulated robot's part in the lock-step of a simulated clock.
struct LockstepPart {
    device: PathBuf,
    shared: Arc<Shared>,
    port: Mutex<PortSide>,
}

impl LockstepSim for LockstepPart {
    fn device(&self) -> &Path {
        &self.device
    }

    fn advance(&self, to_ns: u64, bytes_in: u64, deadline: Instant) -> u64 {
        let mut port = self.port.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
        let mut buffer = [0u8; 1024];
        let target = port.bytes_in + bytes_in;
        while port.bytes_in < target && Instant::now() < deadline {
            match port.master.read(&mut buffer) {
                Ok(n) if n > 0 => {
                    port.bytes_in += n as u64;
                    self.shared.core().feed(&buffer[..n]);
                }
                Ok(_) => {}
                Err(e) if e.kind() == ErrorKind::TimedOut || e.kind() == ErrorKind::WouldBlock => {}
                Err(e) => {
                    tracing::debug!("pseudo-terminal read failed: {e}");
                    break;
                }
            }
        }
        let mut out = Vec::new();
        {
            let mut core = self.shared.core();
            let dt = port.last_ns.map_or(0, |last| to_ns.saturating_sub(last));
            core.step(dt as f64 / 1e9);
            core.feedback(&mut out);
        }
        port.last_ns = Some(to_ns);
        if !out.is_empty() && port.master.write_all(&out).is_ok() {
            return out.len() as u64;
        }
        0
    }
}

/// The simulated motor controller's loop, in real time.
fn controller(name: &str, mut port: TTYPort, shared: &Shared) {
    let mut buffer = [0u8; 1024];
    let mut out = Vec::new();
    let mut last_step = Instant::now();
    while !shared.stop.load(Ordering::Relaxed) {
        let read = match port.read(&mut buffer) {
            Ok(n) => n,
            Err(e) if e.kind() == ErrorKind::TimedOut || e.kind() == ErrorKind::WouldBlock => 0,
            Err(e) => {
                tracing::debug!(component = name, "pseudo-terminal read failed: {e}");
                std::thread::sleep(SIM_PERIOD);
                0
            }
        };
        out.clear();
        {
            let mut core = shared.core();
            core.feed(&buffer[..read]);
            let now = Instant::now();
            core.step(now.duration_since(last_step).min(MAX_CATCH_UP).as_secs_f64());
            last_step = now;
            core.feedback(&mut out);
        }
        if !out.is_empty() {
            // Nobody may be listening (the host reconnecting): that is fine.
            let _ = port.write_all(&out);
        }
    }
}

/// The `builtin:sim` component: owns a simulated robot; no ports. Its report
/// section is the simulation's status; `commands_received` and
/// `malformed_bytes` count what the controller got over the PTY.
pub struct SimComponent {
    robot: SimulatedRobot,
}

impl SimComponent {
    pub fn new(robot: SimulatedRobot) -> SimComponent {
        SimComponent { robot }
    }
}

impl Component for SimComponent {
    fn status(&self) -> Option<Box<dyn StatusSection>> {
        let core = self.robot.shared.core();
        Some(Box::new(SimSection {
            simulation: core.sim.status(),
            commands_received: core.commands_received,
            malformed_messages: core.malformed,
            paused: core.paused,
            pty: self.robot.pty_path.display().to_string(),
        }))
    }
}

/// The simulated robot's section of the report and the live status.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct SimSection {
    #[serde(flatten)]
    pub simulation: SimStatus,
    pub commands_received: u64,
    pub malformed_messages: u64,
    pub paused: bool,
    pub pty: String,
}

impl NamedSection for SimSection {
    const SECTION: &'static str = "sim";
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]

    use std::sync::atomic::AtomicU64;

    use super::*;
    use crate::robot::translator::DriveGeometry;

    fn settings() -> SimSettings {
        let world = world::parse(Path::new("t.world"), "bounds 0 0 10 10\nstart 1 5 0\ngoal 9 9 0.2\nwall 4 0 4 10\n");
        SimSettings {
            world: world.unwrap(),
            body: Body {
                radius: 0.2,
                geometry: DriveGeometry { wheel_base: 0.3, max_wheel_speed: 0.5 },
                rays: 3,
                fov: std::f64::consts::PI,
                max_range: 4.0,
            },
            protocol: SimProtocol::Profile(Profile::Ascii),
            feedback_hz: 10.0,
            controller_watchdog: Duration::from_secs(1),
            timing: None,
        }
    }

    /// The host's side of the wire, reduced to what the lock-step needs:
    /// writes command bytes, reads feedback bytes.
    struct TestLink {
        device: PathBuf,
        port: Mutex<TTYPort>,
        written: AtomicU64,
        taken: AtomicU64,
        expected: AtomicU64,
        received: Mutex<Vec<u8>>,
    }

    impl TestLink {
        fn send(&self, command: MotorCommand) {
            let mut bytes = Vec::new();
            Profile::Ascii.encode_command(&command, &mut bytes);
            self.port.lock().unwrap().write_all(&bytes).unwrap();
            self.written.fetch_add(bytes.len() as u64, Ordering::Relaxed);
        }

        /// The poses in the feedback received so far (and forgets them).
        fn poses(&self) -> Vec<(f64, f64, f64)> {
            self.feedback()
                .into_iter()
                .filter_map(|f| match f {
                    Feedback::Odometry { x, y, heading } => Some((x, y, heading)),
                    _ => None,
                })
                .collect()
        }

        /// The feedback received so far (and forgets it).
        fn feedback(&self) -> Vec<Feedback> {
            let mut decoder = Decoder::new(Profile::Ascii);
            let mut messages = Vec::new();
            decoder.feed(&std::mem::take(&mut *self.received.lock().unwrap()), &mut messages);
            messages
                .into_iter()
                .filter_map(|m| match m {
                    Message::Feedback(feedback) => Some(feedback),
                    Message::Command(_) => None,
                })
                .collect()
        }
    }

    impl LockstepLink for TestLink {
        fn device(&self) -> &Path {
            &self.device
        }
        fn settle(&self, _deadline: Instant) -> bool {
            true
        }
        fn take_written(&self) -> u64 {
            let written = self.written.load(Ordering::Relaxed);
            written - self.taken.swap(written, Ordering::Relaxed)
        }
        fn expect(&self, bytes: u64) {
            self.expected.fetch_add(bytes, Ordering::Relaxed);
        }
        fn received(&self, deadline: Instant) -> bool {
            let mut port = self.port.lock().unwrap();
            let mut received = self.received.lock().unwrap();
            let mut buffer = [0u8; 1024];
            let mut total = 0;
            while total < self.expected.swap(0, Ordering::Relaxed) as usize && Instant::now() < deadline {
                let n = port.read(&mut buffer).unwrap_or(0);
                received.extend_from_slice(&buffer[..n]);
                total += n;
            }
            true
        }
    }

    use crate::runtime::lockstep::LockstepLink;

    /// A robot in lock-step and the link that talks to it, the robot with
    /// `timing`.
    fn robot_and_link(timing: Option<perturb::SimTiming>) -> (Arc<Lockstep>, SimulatedRobot, Arc<TestLink>) {
        let lockstep = Arc::new(Lockstep::default());
        let robot = SimulatedRobot::start("t", SimSettings { timing, ..settings() }, Some(&lockstep)).unwrap();
        let port = serialport::new(robot.pty_path().to_string_lossy(), 115_200)
            .timeout(Duration::from_millis(20))
            .open_native()
            .unwrap();
        let link = Arc::new(TestLink {
            device: robot.pty_path().clone(),
            port: Mutex::new(port),
            written: AtomicU64::new(0),
            taken: AtomicU64::new(0),
            expected: AtomicU64::new(0),
            received: Mutex::new(Vec::new()),
        });
        let joined: Arc<dyn LockstepLink> = link.clone();
        lockstep.join_link(&joined);
        (lockstep, robot, link)
    }

    /// A seeded robot (`sim::perturb`): a command acts up to the serial
    /// delay late, a reading arrives up to the sensor latency late and in
    /// order, and ranges carry noise within their bound; without timing,
    /// none of it.
    #[test]
    fn seeded_timing_delays_commands_and_readings_and_adds_noise() {
        let bounds = perturb::PerturbBounds {
            tick_phase: false,
            sensor_latency_ms: 80.0,
            range_noise_m: 0.05,
            serial_delay_ms: 200.0,
        };
        let timing = perturb::Perturbation { seed: 11, bounds }.sim_timing("t");
        for timed in [false, true] {
            let (lockstep, robot, link) = robot_and_link(timed.then(|| timing.clone()));
            let at = |s: f64| lockstep.before_cycle((s * 1e9) as u64);
            at(0.0);
            // The reading of time 0 waits for its latency.
            assert_eq!(link.poses().len(), usize::from(!timed), "timed: {timed}");
            link.send(MotorCommand::Wheels { left: 0.2, right: 0.2 });
            at(1.0);
            let x = robot.control().status().x;
            if timed {
                // It started up to 200 ms late: up to 4 cm short.
                assert!((1.16 - 1e-9..1.2 - 1e-6).contains(&x), "{x}");
            } else {
                assert!((x - 1.2).abs() < 1e-9, "{x}");
            }
            // The reading of time 0 came; the one of time 1 (taken now)
            // comes within 80 ms.
            let poses = link.poses();
            assert_eq!(poses.len(), 1, "{poses:?}");
            assert!((poses[0].0 - if timed { 1.0 } else { 1.2 }).abs() < 1e-3, "{poses:?}");
            at(1.09);
            let feedback = link.feedback();
            let poses: Vec<f64> = feedback
                .iter()
                .filter_map(|f| if let Feedback::Odometry { x, .. } = f { Some(*x) } else { None })
                .collect();
            assert!(poses.len() == usize::from(timed) && (!timed || (poses[0] - x).abs() < 1e-3), "{poses:?}");
            // Ranges (the robot stands still now: its controller's
            // watchdog stopped it): off by up to 5 cm with timing, as
            // measured (to the wire's millimetre) without.
            at(1.5);
            at(1.6);
            let truth = robot.control().status().ranges;
            let read = link
                .feedback()
                .into_iter()
                .filter_map(|f| if let Feedback::Ranges(r) = f { Some(r) } else { None })
                .next()
                .unwrap();
            let off: Vec<f64> = read.iter().zip(&truth).map(|(r, t)| (r - t).abs()).collect();
            assert_eq!(read.len(), truth.len());
            if timed {
                assert!(off.iter().all(|o| *o <= 0.051) && off.iter().any(|o| *o > 0.002), "{off:?}");
            } else {
                assert!(off.iter().all(|o| *o <= 0.001), "{off:?}");
            }
        }
    }

    #[test]
    fn a_robot_in_lockstep_follows_controlled_time_and_is_reset_posed_paused_and_stepped() {
        let (lockstep, robot, link) = robot_and_link(None);
        let control = robot.control();
        let at = |s: f64| lockstep.before_cycle((s * 1e9) as u64);

        // Time is what the loop says; a command sent before a cycle is acted
        // on from that cycle; feedback goes out every 0.1 s of it.
        at(0.0);
        link.send(MotorCommand::Wheels { left: 0.2, right: 0.2 });
        at(1.0);
        let status = control.status();
        assert!((status.time_s - 1.0).abs() < 1e-9 && (status.x - 1.2).abs() < 1e-9, "{status:?}");
        let poses = link.poses();
        assert_eq!(poses.len(), 2, "at 0 s and at 1 s: {poses:?}");
        assert!((poses[1].0 - 1.2).abs() < 1e-3);
        assert!(control.set_wheels(0.1, 0.1).is_err(), "its controller drives the wheels while running");
        assert!(control.step(0.5).is_err(), "stepping needs a pause");

        // Paused: the loop's time moves on, the world's does not.
        control.pause(true);
        at(2.0);
        assert!((control.status().time_s - 1.0).abs() < 1e-9);
        assert!((control.status().x - 1.2).abs() < 1e-9);
        // Single steps, with wheels the caller sets.
        control.set_wheels(0.5, 0.5).unwrap();
        let stepped = control.step(0.5).unwrap();
        assert!((stepped.time_s - 1.5).abs() < 1e-9 && (stepped.x - 1.45).abs() < 1e-9, "{stepped:?}");
        for bad in [0.0, -1.0, f64::NAN, MAX_SINGLE_STEP_S + 1.0] {
            assert!(control.step(bad).is_err(), "{bad}");
        }
        // A pose inside the wall is refused; a free one is taken and reported at once.
        assert!(control.set_pose(3.9, 5.0, 0.0).is_err());
        control.set_pose(2.0, 3.0, 1.0).unwrap();
        at(2.1);
        assert_eq!(link.poses().last().map(|p| (p.0, p.1)), Some((2.0, 3.0)));

        // Reset: the start pose, time 0, nothing travelled; resumed, it goes on.
        let reset = control.reset();
        assert_eq!((reset.x, reset.y, reset.time_s, reset.distance_travelled_m), (1.0, 5.0, 0.0, 0.0));
        control.pause(false);
        at(2.6);
        assert!((control.status().time_s - 0.5).abs() < 1e-9);
        assert!(!control.is_paused());
    }
}
