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
//! Invariants: nothing but bytes on the PTY connects the host to the
//! simulated controller; the simulation's clock is its own (real time), not
//! the control loop's.

pub mod builtin;
pub mod create2;
pub mod physics;
pub mod world;

use std::io::{ErrorKind, Read, Write};
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use serialport::{SerialPort, TTYPort};

use self::create2::{OpenInterface, Readings, WheelCommand};
use self::physics::{Body, SimStatus, Simulation};
use self::world::World;
use crate::robot::protocol::{Decoder, Feedback, Message, MotorCommand, Profile};
use crate::runtime::Component;

/// Why a simulated robot did not start.
#[derive(Debug, thiserror::Error)]
pub enum SimError {
    #[error("the start ({x}, {y}) is within {radius} m of an obstacle")]
    StartBlocked { x: f64, y: f64, radius: f64 },
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

/// One side of the wire, as the simulated controller speaks it.
enum Wire {
    Profile { profile: Profile, decoder: Decoder, messages: Vec<Message> },
    Create2(OpenInterface),
}

/// What the simulated controller shares with the host.
#[derive(Debug)]
struct Shared {
    status: Mutex<SimStatus>,
    stop: AtomicBool,
    commands: std::sync::atomic::AtomicU64,
    malformed: std::sync::atomic::AtomicU64,
}

/// A running simulated robot: its thread and the path of the PTY end the
/// host opens.
pub struct SimulatedRobot {
    pty_path: PathBuf,
    shared: Arc<Shared>,
    thread: Option<JoinHandle<()>>,
}

impl SimulatedRobot {
    /// Creates the PTY pair and starts the controller thread.
    pub fn start(name: &str, settings: SimSettings) -> Result<SimulatedRobot, SimError> {
        let simulation = Simulation::new(settings.world.clone(), settings.body)?;
        let (mut master, slave) = TTYPort::pair().map_err(|e| SimError::Pty(e.to_string()))?;
        let pty_path = slave.name().map(PathBuf::from).ok_or_else(|| SimError::Pty("it has no name".into()))?;
        master.set_timeout(SIM_PERIOD).map_err(|e| SimError::Pty(e.to_string()))?;
        let shared = Arc::new(Shared {
            status: Mutex::new(simulation.status()),
            stop: AtomicBool::new(false),
            commands: Default::default(),
            malformed: Default::default(),
        });
        let thread_shared = shared.clone();
        let label = name.to_string();
        let thread = std::thread::Builder::new().name(format!("sim-{name}")).spawn(move || {
            // The slave end stays open here so the master never sees a
            // hang-up while the host's link reconnects.
            let _slave = slave;
            controller(&label, master, simulation, settings, &thread_shared);
        })?;
        tracing::info!(component = name, "simulated robot on {}", pty_path.display());
        Ok(SimulatedRobot { pty_path, shared, thread: Some(thread) })
    }

    /// The device path the host's serial link opens.
    pub fn pty_path(&self) -> &PathBuf {
        &self.pty_path
    }

    pub fn status(&self) -> Option<SimStatus> {
        self.shared.status.lock().ok().map(|s| s.clone())
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

/// The simulated motor controller's loop.
fn controller(name: &str, mut port: TTYPort, mut sim: Simulation, settings: SimSettings, shared: &Shared) {
    let mut wire = match settings.protocol {
        SimProtocol::Profile(profile) => {
            Wire::Profile { profile, decoder: Decoder::new(profile), messages: Vec::new() }
        }
        SimProtocol::Create2 => Wire::Create2(OpenInterface::new(settings.body.geometry.wheel_base)),
    };
    let mut commands = Vec::new();
    let mut buffer = [0u8; 1024];
    let mut out = Vec::new();
    let feedback_period = Duration::from_secs_f64(1.0 / settings.feedback_hz.max(0.1));
    let mut last_step = Instant::now();
    let mut last_command = Instant::now();
    let mut last_feedback = Instant::now();
    while !shared.stop.load(Ordering::Relaxed) {
        match port.read(&mut buffer) {
            Ok(n) if n > 0 => match &mut wire {
                Wire::Profile { decoder, messages, .. } => {
                    decoder.feed(&buffer[..n], messages);
                    for message in messages.drain(..) {
                        match message {
                            Message::Command(MotorCommand::Wheels { left, right }) => {
                                commands.push(WheelCommand::Wheels(left, right));
                            }
                            Message::Command(MotorCommand::Stop) => commands.push(WheelCommand::Stop),
                            Message::Feedback(_) => {
                                shared.malformed.fetch_add(1, Ordering::Relaxed);
                            }
                        }
                    }
                }
                Wire::Create2(oi) => {
                    let before = oi.malformed();
                    oi.feed(&buffer[..n], &mut commands);
                    shared.malformed.fetch_add(oi.malformed() - before, Ordering::Relaxed);
                }
            },
            Ok(_) => {}
            Err(e) if e.kind() == ErrorKind::TimedOut || e.kind() == ErrorKind::WouldBlock => {}
            Err(e) => {
                tracing::debug!(component = name, "pseudo-terminal read failed: {e}");
                std::thread::sleep(SIM_PERIOD);
            }
        }
        for command in commands.drain(..) {
            let (left, right) = match command {
                WheelCommand::Wheels(left, right) => (left, right),
                WheelCommand::Stop => (0.0, 0.0),
            };
            sim.set_wheels(left, right);
            last_command = Instant::now();
            shared.commands.fetch_add(1, Ordering::Relaxed);
        }
        if last_command.elapsed() > settings.controller_watchdog {
            sim.set_wheels(0.0, 0.0);
        }
        let now = Instant::now();
        sim.step(now.duration_since(last_step).min(MAX_CATCH_UP).as_secs_f64());
        last_step = now;
        if let Wire::Create2(oi) = &mut wire {
            oi.track(sim.pose());
        }
        if last_feedback.elapsed() >= feedback_period {
            last_feedback = Instant::now();
            let (x, y, heading) = sim.pose();
            out.clear();
            match &wire {
                Wire::Profile { profile, .. } => {
                    profile.encode_feedback(&Feedback::Odometry { x, y, heading }, &mut out);
                    profile.encode_feedback(&Feedback::Ranges(sim.ranges()), &mut out);
                    profile.encode_feedback(&Feedback::Bumper(sim.bumper()), &mut out);
                    profile.encode_feedback(&Feedback::Battery(BATTERY_VOLTS), &mut out);
                }
                Wire::Create2(oi) => {
                    let readings = Readings {
                        bumper: sim.bumper(),
                        volts: BATTERY_VOLTS,
                        ranges: sim.ranges(),
                        max_range: settings.body.max_range,
                    };
                    out.extend(oi.frame(&readings).unwrap_or_default());
                }
            }
            // Nobody may be listening (the host reconnecting): that is fine.
            let _ = port.write_all(&out);
            if let Ok(mut status) = shared.status.lock() {
                *status = sim.status();
            }
        }
    }
    if let Ok(mut status) = shared.status.lock() {
        *status = sim.status();
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
    fn status(&self) -> Option<(&'static str, serde_json::Value)> {
        let status = self.robot.status()?;
        let mut value = serde_json::to_value(status).ok()?;
        if let Some(object) = value.as_object_mut() {
            object.insert("commands_received".into(), self.robot.shared.commands.load(Ordering::Relaxed).into());
            object.insert("malformed_messages".into(), self.robot.shared.malformed.load(Ordering::Relaxed).into());
            object.insert("pty".into(), self.robot.pty_path.display().to_string().into());
        }
        Some(("sim", value))
    }
}
