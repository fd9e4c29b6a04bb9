//! The stall watchdog: native components that block the control loop (they
//! sleep in a call) in a graph with a real serial link on a pseudo-terminal,
//! run by the real control loop. The watchdog must put STOP on the wire
//! while the loop is still stuck, fault the component with the call named,
//! and leave the others running.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use subsume::contract::Value;
use subsume::robot::protocol::Profile;
use subsume::robot::serial::{LinkSettings, SerialLink};
use subsume::robot::translator::{DriveGeometry, ProfileTranslator};
use subsume::runtime::control_loop::{self, Clock, CycleHook, NoHook, Shutdown};
use subsume::runtime::stall::Stall;
use subsume::runtime::{CallError, Component, ComponentState, Graph, Heartbeat, Outbox, Policy, StallWatchdog};

use crate::support::MotorRecorder;

const LIMIT: Duration = Duration::from_millis(100);
const MS: u64 = 1_000_000;

/// When a component started to block, shared with the test.
type Mark = Arc<Mutex<Option<Instant>>>;

/// Emits `VEL 0.2 0` on every tick; on tick `stall_on` it sleeps `sleep`
/// after emitting.
struct Driver {
    ticks: u64,
    stall_on: Option<u64>,
    sleep: Duration,
    slept_at: Mark,
}

impl Component for Driver {
    fn tick(&mut self, _now_ns: u64, out: &mut Outbox) -> Result<(), CallError> {
        self.ticks += 1;
        out.push((0, Value::Command("VEL 0.2 0".into())));
        if self.stall_on == Some(self.ticks) {
            *self.slept_at.lock().unwrap() = Some(Instant::now());
            std::thread::sleep(self.sleep);
        }
        Ok(())
    }
}

/// Emits a number on every tick.
struct Ticker;

impl Component for Ticker {
    fn tick(&mut self, now_ns: u64, out: &mut Outbox) -> Result<(), CallError> {
        out.push((0, Value::Scalar(now_ns as f64)));
        Ok(())
    }
}

/// Sleeps `sleep` in the `on-input` of its `stall_on`-th value.
struct Sleeper {
    inputs: u64,
    stall_on: u64,
    sleep: Duration,
    slept_at: Mark,
}

impl Component for Sleeper {
    fn on_input(&mut self, _: u32, _: &Value, _: usize, _: u64, _: &mut Outbox) -> Result<(), CallError> {
        self.inputs += 1;
        if self.inputs == self.stall_on {
            *self.slept_at.lock().unwrap() = Some(Instant::now());
            std::thread::sleep(self.sleep);
        }
        Ok(())
    }
}

fn new_driver(stall_on: Option<u64>, sleep: Duration) -> (Box<dyn Component>, Mark) {
    let mark = Mark::default();
    (Box::new(Driver { ticks: 0, stall_on, sleep, slept_at: mark.clone() }), mark)
}

/// A serial link on `device` (ascii), refreshing every 100 ms, with a
/// watchdog longer than any run here.
fn link(device: &str) -> Box<dyn Component> {
    let settings = LinkSettings {
        device: device.into(),
        baud: 115_200,
        min_interval_ns: MS,
        watchdog_ns: 10_000 * MS,
        refresh_ns: 100 * MS,
    };
    let translator = ProfileTranslator::new(Profile::Ascii, DriveGeometry { wheel_base: 0.3, max_wheel_speed: 1.0 });
    Box::new(SerialLink::start("motors", settings, Box::new(translator)).unwrap())
}

/// Records the motor controller's lines on a thread until `done`.
fn record(mut motors: MotorRecorder, done: Arc<AtomicBool>) -> JoinHandle<MotorRecorder> {
    std::thread::spawn(move || {
        motors.read_while(|| !done.load(Ordering::Relaxed));
        // What the link's final STOP left in the PTY.
        motors.read();
        motors
    })
}

/// Runs `graph` on the real control loop for `run_for` with a watchdog of
/// `LIMIT`; returns the graph and the stalls the watchdog reported.
fn run_watched(mut graph: Graph, run_for: Duration, hook: Box<dyn CycleHook + Send>) -> (Graph, Vec<Stall>) {
    let heartbeat = Heartbeat::new(LIMIT);
    let stalls = Arc::new(Mutex::new(Vec::new()));
    let seen = stalls.clone();
    let watchdog =
        StallWatchdog::start(heartbeat.clone(), Box::new(move |stall| seen.lock().unwrap().push(stall.clone())))
            .unwrap();
    let clock = Clock::new();
    let until = clock.now_ns() + run_for.as_nanos() as u64;
    let graph = std::thread::spawn(move || {
        let mut hook = hook;
        control_loop::run_watched(&mut graph, &clock, &Shutdown::new(), Some(until), &mut *hook, Some(&heartbeat));
        graph
    })
    .join()
    .unwrap();
    assert_eq!(watchdog.stalls(), stalls.lock().unwrap().len() as u64);
    drop(watchdog);
    let stalls = stalls.lock().unwrap().clone();
    (graph, stalls)
}

fn fault_reason(graph: &Graph, index: usize) -> String {
    match graph.state(index).unwrap() {
        ComponentState::Faulted { reason, .. } => reason.clone(),
        ComponentState::Running => panic!("'{}' is still running", graph.name(index).unwrap()),
    }
}

/// The first STOP at or after `since`, and the lines from it on.
fn stop_after(lines: &[(Instant, String)], since: Instant) -> (Instant, Vec<String>) {
    let at = lines.iter().position(|(t, l)| *t >= since && l == "S").expect("STOP reached the wire");
    (lines[at].0, lines[at..].iter().map(|(_, l)| l.clone()).collect())
}

#[test]
fn a_driving_component_that_blocks_in_tick_gets_stop_on_the_wire_while_it_blocks_and_is_faulted() {
    let (motors, _slave, device) = MotorRecorder::new();
    let done = Arc::new(AtomicBool::new(false));
    let recorder = record(motors, done.clone());
    let sleep = Duration::from_secs(1);
    let mut graph = Graph::new();
    let (component, slept_at) = new_driver(Some(25), sleep);
    let driver = graph.add("driver", component, 1, 50.0, 0);
    let motors = graph.add("motors", link(&device), 4, 100.0, 0);
    graph.connect(driver, 0, motors, 0, Policy::Latest);

    let (graph, stalls) = run_watched(graph, Duration::from_millis(2500), Box::new(NoHook));
    let reason = fault_reason(&graph, driver);
    drop(graph);
    done.store(true, Ordering::Relaxed);
    let lines = recorder.join().unwrap().lines;

    let slept_at = slept_at.lock().unwrap().expect("the driver blocked");
    let (stop_at, after) = stop_after(&lines, slept_at);
    let waited = stop_at.duration_since(slept_at);
    assert!(waited >= LIMIT, "STOP came {waited:?} into the stall, before the limit");
    assert!(waited < sleep, "STOP came {waited:?} into a {sleep:?} stall: not while the loop was stuck");
    let before: Vec<&str> = lines.iter().filter(|(t, _)| *t < slept_at).map(|(_, l)| l.as_str()).collect();
    assert_eq!(before.last(), Some(&"M 200 200"), "the driver was driving");
    assert!(after.iter().all(|l| l == "S"), "only STOP after the stall (the refresh and the final STOP): {after:?}");
    assert!(after.len() >= 3, "{after:?}");

    assert_eq!(stalls.len(), 1, "{stalls:?}");
    let stall = &stalls[0];
    assert_eq!((stall.component.as_deref(), stall.call), (Some("driver"), "tick"));
    assert!(stall.held >= LIMIT && stall.held < sleep, "{stall:?}");
    assert_eq!(stall.stops, vec![("motors".to_string(), subsume::runtime::StopOutcome::Sent)]);
    assert!(reason.starts_with("tick stalled the control loop: it held it for "), "{reason}");
    assert!(reason.ends_with("ms (the stall limit is 100 ms)"), "{reason}");
}

#[test]
fn a_bystander_that_blocks_in_on_input_is_faulted_and_the_driver_drives_on() {
    let (motors, _slave, device) = MotorRecorder::new();
    let done = Arc::new(AtomicBool::new(false));
    let recorder = record(motors, done.clone());
    let sleep = Duration::from_millis(600);
    let mut graph = Graph::new();
    let (component, _) = new_driver(None, sleep);
    let driver = graph.add("driver", component, 1, 50.0, 0);
    let ticker = graph.add("ticker", Box::new(Ticker), 1, 20.0, 0);
    let slept_at = Mark::default();
    let sleeper = Sleeper { inputs: 0, stall_on: 10, sleep, slept_at: slept_at.clone() };
    let sleeper = graph.add("sleeper", Box::new(sleeper), 0, 0.0, 0);
    let motors = graph.add("motors", link(&device), 4, 100.0, 0);
    graph.connect(driver, 0, motors, 0, Policy::Latest);
    graph.connect(ticker, 0, sleeper, 0, Policy::Latest);

    let (graph, stalls) = run_watched(graph, Duration::from_millis(2000), Box::new(NoHook));
    let reason = fault_reason(&graph, sleeper);
    assert_eq!(graph.state(driver), Some(&ComponentState::Running));
    assert_eq!(graph.state(ticker), Some(&ComponentState::Running));
    let driver_ticks = graph.stats(driver).unwrap().ticks;
    drop(graph);
    done.store(true, Ordering::Relaxed);
    let lines = recorder.join().unwrap().lines;

    let slept_at = slept_at.lock().unwrap().expect("the sleeper blocked");
    let (stop_at, after) = stop_after(&lines, slept_at);
    let waited = stop_at.duration_since(slept_at);
    assert!(waited >= LIMIT && waited < sleep, "STOP came {waited:?} into a {sleep:?} stall");
    assert!(after.iter().any(|l| l == "M 200 200"), "the driver drives again after the stall: {after:?}");
    assert_eq!(after.last().map(String::as_str), Some("S"), "the link's final STOP is last");
    // 2 s at 50 Hz, less the stall's missed ticks (counted, not replayed).
    assert!(driver_ticks >= 60, "the driver kept its rate outside the stall: {driver_ticks} ticks");

    assert_eq!(stalls.len(), 1, "{stalls:?}");
    assert_eq!((stalls[0].component.as_deref(), stalls[0].call), (Some("sleeper"), "on-input"));
    assert!(reason.starts_with("on-input stalled the control loop"), "{reason}");
}

#[test]
fn a_loop_that_sleeps_between_ticks_is_not_stalled() {
    // One tick a second: the loop sleeps far longer than the limit.
    let mut graph = Graph::new();
    let ticker = graph.add("ticker", Box::new(Ticker), 1, 1.0, 0);
    let (graph, stalls) = run_watched(graph, Duration::from_millis(2500), Box::new(NoHook));
    assert_eq!(stalls, vec![]);
    assert_eq!(graph.state(ticker), Some(&ComponentState::Running));
    // Ticks at 0, 1 and 2 s; on a loaded machine the run may start late
    // and end before the third. What matters is that it ticked and was
    // never taken for a stall.
    let ticks = graph.stats(ticker).unwrap().ticks;
    assert!((2..=3).contains(&ticks), "{ticks} ticks in 2.5 s at 1 Hz");
}

/// Swaps in `next` at `at_ns`, as an activation does.
struct SwapAt {
    at_ns: u64,
    next: Option<Graph>,
    old: Arc<Mutex<Option<Graph>>>,
}

impl CycleHook for SwapAt {
    fn between_cycles(&mut self, graph: &mut Graph, now_ns: u64) {
        if now_ns >= self.at_ns
            && let Some(mut next) = self.next.take()
        {
            std::mem::swap(graph, &mut next);
            *self.old.lock().unwrap() = Some(next);
        }
    }
}

#[test]
fn a_graph_swapped_in_by_an_activation_is_watched_too() {
    let (first_motors, _first_slave, first_device) = MotorRecorder::new();
    let (second_motors, _second_slave, second_device) = MotorRecorder::new();
    let done = Arc::new(AtomicBool::new(false));
    let first_recorder = record(first_motors, done.clone());
    let second_recorder = record(second_motors, done.clone());
    let sleep = Duration::from_millis(800);

    let mut first = Graph::new();
    let (component, _) = new_driver(None, sleep);
    let driver = first.add("driver", component, 1, 50.0, 0);
    let motors = first.add("motors", link(&first_device), 4, 100.0, 0);
    first.connect(driver, 0, motors, 0, Policy::Latest);

    let mut second = Graph::new();
    let (component, slept_at) = new_driver(Some(10), sleep);
    let blocker = second.add("blocker", component, 1, 50.0, 0);
    let motors = second.add("motors", link(&second_device), 4, 100.0, 0);
    second.connect(blocker, 0, motors, 0, Policy::Latest);

    let old = Arc::new(Mutex::new(None));
    let hook = SwapAt { at_ns: 300 * MS, next: Some(second), old: old.clone() };
    let (graph, stalls) = run_watched(first, Duration::from_millis(2000), Box::new(hook));
    let reason = fault_reason(&graph, blocker);
    drop(graph);
    drop(old.lock().unwrap().take());
    done.store(true, Ordering::Relaxed);
    let second_lines = second_recorder.join().unwrap().lines;
    let first_lines = first_recorder.join().unwrap().lines;

    assert_eq!(first_lines.last().map(|(_, l)| l.as_str()), Some("S"), "the old graph's link stopped");
    let slept_at = slept_at.lock().unwrap().expect("the new graph's driver blocked");
    let (stop_at, after) = stop_after(&second_lines, slept_at);
    let waited = stop_at.duration_since(slept_at);
    assert!(waited >= LIMIT && waited < sleep, "STOP came {waited:?} into a {sleep:?} stall");
    assert!(after.iter().all(|l| l == "S"), "{after:?}");
    // Exactly one stall in the blocker. A loaded machine can hold the
    // loop itself off the CPU for longer than LIMIT (the watchdog then
    // rightly declares that too), so other stalls are not counted here.
    let in_blocker = stalls.iter().filter(|s| s.component.as_deref() == Some("blocker")).count();
    assert_eq!(in_blocker, 1, "{stalls:?}");
    assert!(reason.starts_with("tick stalled"), "{reason}");
}
