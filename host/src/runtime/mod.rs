//! The runtime: components behind one trait ([`component`]), how they are
//! wired ([`wiring`]), the graph that schedules them ([`graph`]) and its
//! stopwatch ([`clock`]), the
//! control loop that drives it in real time ([`control_loop`]) and how long
//! it waited for a CPU ([`cpu_wait`]), how threads ask the kernel for the
//! CPU so the loop wins it ([`scheduling`]), the host's
//! emergency-stop locks ([`locks`]), the process's list of final stops for
//! exits that cannot wait for the loop ([`halt`]), the
//! watchdog outside it that stops the motors when it stalls ([`stall`]),
//! simulated time's lock-step between the loop, the simulated robots and
//! their links ([`lockstep`]), and what an observer such as the recorder
//! sees of it ([`tap`]).
//!
//! Import rule: nothing here imports `config` or any built-in; the robot
//! file's validator and the assembler feed the graph through the types of
//! [`wiring`].

pub mod clock;
pub mod component;
pub mod control_loop;
pub mod cpu_wait;
pub mod graph;
pub mod halt;
pub mod histogram;
pub mod locks;
pub mod lockstep;
pub mod scheduling;
pub mod stall;
pub mod standing;
pub mod status;
pub mod tap;
pub mod wiring;

pub use component::{CallError, Component, Outbox, Restarter, Vacant};
pub use graph::{ComponentState, ComponentStats, ConnectionStats, Graph};
pub use histogram::Histogram;
pub use locks::{DEFAULT_LOCK, Engagement, LockEvent, Locks};
pub use stall::{Heartbeat, MotorStop, StallWatchdog, StopOutcome};
pub use standing::{Standing, Standings};
pub use status::{Family, MetricKind, NamedSection, Sample, StatusSection};
pub use tap::{Call, Tap};
pub use wiring::{Convert, Policy, PriorityCell, RestartPolicy, RunningRobot};
