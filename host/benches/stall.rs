#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic)]
//! Stall benchmark (a bench binary): from a component blocking the control
//! loop to STOP arriving at the far end of a real pseudo-terminal.
//!
//! A native driver emits `VEL 0.2 0` at 50 Hz into a serial link (ascii) on
//! a PTY; every so often it blocks in `tick` for three stall limits. The
//! real control loop runs the graph with the stall watchdog beside it; the
//! driver is faulted by each stall, so each sample runs a fresh graph that
//! takes the link over (as an activation carries it). A sample runs from the moment the driver starts blocking to the
//! moment the `S` line has been read at the PTY's master end. p50 and p99,
//! and the same less the limit (what detection and the write add).
//!
//! Run: `cargo bench --bench stall` (BENCHMARKS.md records the figures).

use std::io::Read;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use serialport::{SerialPort, TTYPort};
use subsume::contract::Value;
use subsume::robot::protocol::Profile;
use subsume::robot::serial::{LinkSettings, SerialLink};
use subsume::robot::translator::{DriveGeometry, ProfileTranslator};
use subsume::runtime::control_loop::{self, Clock, NoHook, Shutdown};
use subsume::runtime::{CallError, Component, Graph, Heartbeat, Outbox, Policy, StallWatchdog};

const MS: u64 = 1_000_000;

/// Drives, and blocks for `sleep` on its `stall_on`-th tick.
struct Driver {
    ticks: u64,
    stall_on: u64,
    sleep: Duration,
    starts: Arc<Mutex<Vec<Instant>>>,
}

impl Component for Driver {
    fn tick(&mut self, _now_ns: u64, out: &mut Outbox) -> Result<(), CallError> {
        self.ticks += 1;
        out.push((0, Value::Command("VEL 0.2 0".into())));
        if self.ticks == self.stall_on {
            self.starts.lock().unwrap().push(Instant::now());
            std::thread::sleep(self.sleep);
        }
        Ok(())
    }
}

fn percentile(sorted: &[Duration], p: f64) -> Duration {
    sorted[((sorted.len() - 1) as f64 * p).round() as usize]
}

fn measure(limit: Duration, samples: usize) {
    let (mut master, slave) = TTYPort::pair().unwrap();
    master.set_timeout(Duration::from_millis(20)).unwrap();
    let settings = LinkSettings {
        device: slave.name().unwrap().into(),
        baud: 115_200,
        min_interval_ns: MS,
        watchdog_ns: 10_000 * MS,
        refresh_ns: 100 * MS,
    };
    let translator = ProfileTranslator::new(Profile::Ascii, DriveGeometry { wheel_base: 0.3, max_wheel_speed: 1.0 });
    let link = SerialLink::start("motors", settings, Box::new(translator)).unwrap();

    let starts = Arc::new(Mutex::new(Vec::new()));
    let sleep = limit * 3;

    // The master end: every line with its arrival time.
    let done = Arc::new(AtomicBool::new(false));
    let reading = done.clone();
    let reader = std::thread::spawn(move || {
        let mut lines = Vec::new();
        let mut pending = Vec::new();
        let mut buffer = [0u8; 256];
        while !reading.load(Ordering::Relaxed) {
            if let Ok(n) = master.read(&mut buffer) {
                let at = Instant::now();
                pending.extend_from_slice(&buffer[..n]);
                while let Some(end) = pending.iter().position(|&b| b == b'\n') {
                    let line: Vec<u8> = pending.drain(..=end).collect();
                    lines.push((at, line));
                }
            }
        }
        lines
    });

    // One watchdog for the whole run; each sample runs a fresh graph (the
    // stall faults its driver) on the real control loop, and the link moves
    // from graph to graph, as an activation carries it.
    let heartbeat = Heartbeat::new(limit);
    let watchdog = StallWatchdog::start(heartbeat.clone(), Box::new(|_| {})).unwrap();
    let mut link: Box<dyn Component> = Box::new(link);
    for sample in 0..=samples {
        let mut graph = Graph::new();
        // Drives for 0.1 s, then blocks.
        let driver = Driver { ticks: 0, stall_on: 5, sleep, starts: starts.clone() };
        let index = graph.add("driver", Box::new(driver), 1, 50.0, 0);
        let motors = graph.add("motors", link, 4, 100.0, 0);
        graph.connect(index, 0, motors, 0, Policy::Latest);
        let shutdown = Shutdown::new();
        let loop_shutdown = shutdown.clone();
        let loop_heartbeat = heartbeat.clone();
        let control = std::thread::spawn(move || {
            let clock = Clock::new();
            control_loop::run_watched(&mut graph, &clock, &loop_shutdown, None, &mut NoHook, Some(&loop_heartbeat));
            graph
        });
        while starts.lock().unwrap().len() <= sample {
            std::thread::sleep(Duration::from_millis(5));
        }
        // Past the stall, and the driver's fault.
        std::thread::sleep(sleep + Duration::from_millis(50));
        shutdown.request();
        let mut graph = control.join().unwrap();
        link = graph.take_component(motors).unwrap();
    }
    drop(link);
    drop(watchdog);
    done.store(true, Ordering::Relaxed);
    let lines = reader.join().unwrap();

    let starts = starts.lock().unwrap().clone();
    let mut times: Vec<Duration> = starts[1..=samples]
        .iter()
        .map(|&start| {
            let (at, _) = lines.iter().find(|(at, line)| *at >= start && line == b"S\n").expect("a STOP per stall");
            at.duration_since(start)
        })
        .collect();
    times.sort_unstable();
    let past: Vec<Duration> = times.iter().map(|t| t.saturating_sub(limit)).collect();
    println!(
        "stall limit {} ms: blocking call -> STOP read at the PTY: p50 {:.1} ms, p99 {:.1} ms, max {:.1} ms; past the limit: p50 {:.1} ms, p99 {:.1} ms ({samples} stalls)",
        limit.as_millis(),
        percentile(&times, 0.5).as_secs_f64() * 1e3,
        percentile(&times, 0.99).as_secs_f64() * 1e3,
        times[times.len() - 1].as_secs_f64() * 1e3,
        percentile(&past, 0.5).as_secs_f64() * 1e3,
        percentile(&past, 0.99).as_secs_f64() * 1e3,
    );
}

fn main() {
    // The default limit, and a tight one (the detection period is a quarter
    // of the limit, so the spread shrinks with it).
    measure(Duration::from_millis(100), 200);
    measure(Duration::from_millis(20), 300);
}
