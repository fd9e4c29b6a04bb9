#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic)]
//! A 1 kHz control loop of 16 WASM components (issue 15, part 3), run by the
//! host's own loop (`control_loop::run_with`):
//!
//! - a chain: `test-counter` ticking at 1 kHz -> 10 `test-relay`s -> a sink;
//! - a fan-in: 5 `test-commander`s ticking at 1 kHz, each sending a control
//!   string every tick to the native arbiter (ticked at 1 kHz too).
//!
//! It reports, for the control thread:
//! - lateness: how long after its scheduled time each cycle started (p50,
//!   p99, max), and period jitter: how far each interval between two cycle
//!   starts was from 1 ms (p50, p99, max);
//! - missed cycles: ticks of the 1 kHz source the loop skipped because it was
//!   more than a period late (the graph's `missed_ticks`);
//! - CPU per cycle: the control thread's CPU time over the run / cycles (and
//!   the whole process's, which adds the epoch ticker and, under load, the
//!   compiles).
//!
//! Settings (environment):
//! - `KHZ_SECONDS` (default 60): how long to run; a few seconds for a smoke run;
//! - `KHZ_LOAD=1`: meanwhile, another thread compiles the Python obstacle
//!   avoider (18 MB, no compile cache) again and again, and after each
//!   compile builds a fresh set of the same 16 components and hands it to the
//!   loop, which swaps it in between two cycles (what activating a robot
//!   file from the portal does: build beside, swap at a cycle boundary);
//! - `KHZ_PIN=N`: pin the control thread to CPU N (`sched_setaffinity`);
//! - `KHZ_FIFO=P`: run the control thread under `SCHED_FIFO` at priority P;
//! - `KHZ_MLOCK=1`: `mlockall(MCL_CURRENT | MCL_FUTURE)` before the run;
//! - `KHZ_FLOOR=1`: native stand-ins instead of the WASM components (same
//!   emissions, same graph and loop): the machine's and the loop's own
//!   floor, against which the WASM run's missed cycles are read.
//!
//! A setting the kernel refuses is reported, and the run goes on without it.
//!
//! Run: `KHZ_SECONDS=60 cargo bench --bench kilohertz` (BENCHMARKS.md records
//! the figures).

#[path = "../../tests/all/support.rs"]
mod support;

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use subsume::arbiter::{ArbiterComponent, Source};
use subsume::config::Policy;
use subsume::contract::Param;
use subsume::contract::Value;
use subsume::runtime::control_loop::{Clock, CycleHook, Shutdown, run_with};
use subsume::runtime::cpu_wait::thread_run_delay_ns;
use subsume::runtime::scheduling::ControlThreadSettings;
use subsume::runtime::{CallError, Component, Graph, Outbox, PriorityCell, Vacant};
use subsume::sandbox::{GuestLimits, Sandbox, WasmArtifact, thread_cpu_time};

const PERIOD_NS: u64 = 1_000_000;
const RELAYS: usize = 10;
const COMMANDERS: usize = 5;

struct Artifacts {
    counter: Arc<WasmArtifact>,
    relay: Arc<WasmArtifact>,
    commander: Arc<WasmArtifact>,
}

fn limits() -> GuestLimits {
    GuestLimits { memory_bytes: 16 << 20, ..GuestLimits::default() }
}

fn param(name: &str, value: &str) -> Param {
    Param { name: name.into(), value: value.into() }
}

/// A native stand-in for one of the guests (the floor run, `KHZ_FLOOR=1`):
/// the same emissions without a sandbox.
enum Native {
    Counter(f64),
    Relay,
    Commander(subsume::contract::control::Command),
}

impl Component for Native {
    fn on_input(&mut self, port: u32, value: &Value, _: usize, _: u64, out: &mut Outbox) -> Result<(), CallError> {
        if let Native::Relay = self {
            out.push((port, value.clone()));
        }
        Ok(())
    }

    fn tick(&mut self, _: u64, out: &mut Outbox) -> Result<(), CallError> {
        match self {
            Native::Counter(count) => {
                *count += 1.0;
                out.push((0, Value::Scalar(*count)));
            }
            Native::Commander(command) => out.push((0, Value::Command(command.clone()))),
            Native::Relay => {}
        }
        Ok(())
    }
}

/// The 16 components (native stand-ins when `floor`), their first ticks at
/// `start_ns`. Returns the graph and the index of the 1 kHz source.
fn build(sandbox: &Sandbox, artifacts: &Artifacts, start_ns: u64) -> (Graph, usize) {
    let floor = std::env::var("KHZ_FLOOR").is_ok_and(|v| v == "1");
    let wasm = |artifact: &WasmArtifact, name: &str, params: &[Param]| -> Box<dyn Component> {
        if floor {
            return Box::new(match name {
                "counter" => Native::Counter(0.0),
                "relay" => Native::Relay,
                _ => Native::Commander(params[0].value.as_str().into()),
            });
        }
        Box::new(sandbox.instantiate(artifact, name, &limits(), params).unwrap())
    };
    let mut graph = Graph::new();
    let counter_params = [param("start", "0"), param("step", "1")];
    let counter = graph.add("counter", wasm(&artifacts.counter, "counter", &counter_params), 1, 1000.0, start_ns);
    let mut previous = counter;
    for i in 0..RELAYS {
        let relay = graph.add(&format!("relay{i}"), wasm(&artifacts.relay, "relay", &[]), 2, 0.0, start_ns);
        graph.connect(previous, 0, relay, 0, Policy::Latest);
        previous = relay;
    }
    let sink = graph.add("sink", Box::new(Vacant), 0, 0.0, start_ns);
    graph.connect(previous, 0, sink, 0, Policy::Latest);
    let first_commander = graph.len();
    let arbiter_index = first_commander + COMMANDERS;
    let mut sources = Vec::new();
    for i in 0..COMMANDERS {
        let name = format!("commander{i}");
        let params = [param("command", &format!("VEL 0.{} 0", i + 1)), param("ticks", "1000000000")];
        let index = graph.add(&name, wasm(&artifacts.commander, &name, &params), 1, 1000.0, start_ns);
        graph.connect(index, 0, arbiter_index, 0, Policy::Latest);
        sources.push(Source {
            component: index,
            name,
            priority: PriorityCell::new(i as i32 + 1),
            timeout_ns: 100 * PERIOD_NS,
            operator: false,
        });
    }
    let arbiter = graph.add("arbiter", Box::new(ArbiterComponent::new("arbiter", sources)), 1, 1000.0, start_ns);
    assert_eq!(arbiter, arbiter_index);
    let motors = graph.add("motors", Box::new(Vacant), 0, 0.0, start_ns);
    graph.connect(arbiter, 0, motors, 0, Policy::Latest);
    (graph, counter)
}

/// Records each cycle's start and its lateness; swaps in graphs the loader
/// thread sends.
struct Recorder {
    lateness: Vec<u64>,
    starts: Vec<u64>,
    source: usize,
    missed: u64,
    swaps: u64,
    /// Built sets and when their first ticks are due.
    incoming: mpsc::Receiver<(Graph, u64)>,
    pending: Option<(Graph, u64)>,
    retired: mpsc::Sender<Graph>,
}

impl CycleHook for Recorder {
    fn between_cycles(&mut self, graph: &mut Graph, now_ns: u64) {
        if self.pending.is_none() {
            self.pending = self.incoming.try_recv().ok();
        }
        // A set is swapped in when its first tick is due, so its schedule
        // starts on time.
        if self.pending.as_ref().is_some_and(|(_, start)| *start <= now_ns + PERIOD_NS / 2)
            && let Some((mut next, _)) = self.pending.take()
        {
            std::mem::swap(graph, &mut next);
            self.missed += next.stats(self.source).map_or(0, |s| s.missed_ticks);
            self.swaps += 1;
            // Dropped on the loader thread, not in the loop.
            let _ = self.retired.send(next);
        }
        if let Some(due) = graph.next_due_ns().filter(|due| *due <= now_ns) {
            self.lateness.push(now_ns - due);
            self.starts.push(now_ns);
        }
    }
}

fn percentile(sorted: &[u64], p: f64) -> u64 {
    sorted.get(((sorted.len().saturating_sub(1)) as f64 * p).round() as usize).copied().unwrap_or(0)
}

fn summary(values: &mut [u64]) -> String {
    values.sort_unstable();
    let us = |ns: u64| ns as f64 / 1e3;
    format!(
        "p50 {:.1} us, p99 {:.1} us, max {:.1} us",
        us(percentile(values, 0.5)),
        us(percentile(values, 0.99)),
        us(values.last().copied().unwrap_or(0))
    )
}

/// (VmRSS, VmSize) of this process in KiB.
fn memory_kib() -> (u64, u64) {
    let status = std::fs::read_to_string("/proc/self/status").unwrap_or_default();
    let field = |name: &str| {
        status
            .lines()
            .find_map(|l| l.strip_prefix(name))
            .and_then(|rest| rest.split_whitespace().next())
            .and_then(|v| v.parse().ok())
            .unwrap_or(0)
    };
    (field("VmRSS:"), field("VmSize:"))
}

fn process_cpu() -> Duration {
    // SAFETY: getrusage writes only into the zeroed struct it is given.
    let mut usage: libc::rusage = unsafe { std::mem::zeroed() };
    let rc = unsafe { libc::getrusage(libc::RUSAGE_SELF, &mut usage) };
    if rc != 0 {
        return Duration::ZERO;
    }
    let tv = |t: libc::timeval| Duration::new(t.tv_sec as u64, t.tv_usec as u32 * 1000);
    tv(usage.ru_utime) + tv(usage.ru_stime)
}

/// Steal time of all the machine's CPUs so far (`/proc/stat`, in ms).
fn steal_ms() -> Option<u64> {
    let stat = std::fs::read_to_string("/proc/stat").ok()?;
    let ticks: u64 = stat.lines().next()?.split_whitespace().nth(8)?.parse().ok()?;
    // SAFETY: sysconf takes a constant only.
    let hz = unsafe { libc::sysconf(libc::_SC_CLK_TCK) }.max(1) as u64;
    Some(ticks * 1000 / hz)
}

/// Applies the real-time settings asked for; returns what was done.
fn apply_settings() -> Vec<String> {
    let mut applied = Vec::new();
    let os_error = || std::io::Error::last_os_error().to_string();
    // The host's own settings (`subsume run --control-cpu/--control-fifo`).
    let control = ControlThreadSettings {
        cpu: std::env::var("KHZ_PIN").ok().and_then(|v| v.parse::<usize>().ok()),
        fifo_priority: std::env::var("KHZ_FIFO").ok().and_then(|v| v.parse::<i32>().ok()),
    };
    let (done, refused) = control.apply();
    applied.extend(done);
    applied.extend(refused.iter().map(|err| format!("refused: {err}")));
    if std::env::var("KHZ_MLOCK").is_ok_and(|v| v == "1") {
        let started = Instant::now();
        // SAFETY: mlockall takes flags only.
        let rc = unsafe { libc::mlockall(libc::MCL_CURRENT | libc::MCL_FUTURE) };
        applied.push(if rc == 0 {
            format!("mlockall (took {:.2} s)", started.elapsed().as_secs_f64())
        } else {
            format!("mlockall refused: {}", os_error())
        });
    }
    applied
}

fn main() {
    let seconds: f64 = std::env::var("KHZ_SECONDS").ok().and_then(|v| v.parse().ok()).unwrap_or(60.0);
    let load = std::env::var("KHZ_LOAD").is_ok_and(|v| v == "1");
    let sandbox = Arc::new(Sandbox::new(Some(support::cache_dir())).unwrap());
    let read = |name: &str| std::fs::read(support::guest(name)).unwrap();
    let artifacts = Arc::new(Artifacts {
        counter: sandbox.load(&read("test-counter")).unwrap(),
        relay: sandbox.load(&read("test-relay")).unwrap(),
        commander: sandbox.load(&read("test-commander")).unwrap(),
    });
    let clock = Clock::new();
    // The loader starts before the settings: threads inherit their
    // creator's scheduling policy and affinity, and a compile at SCHED_FIFO
    // on the control thread's CPU would starve the loop.
    let (start_tx, start_rx) = mpsc::channel::<u64>();
    let (to_loop, incoming) = mpsc::channel();
    let (retired, from_loop) = mpsc::channel::<Graph>();
    let stop = Arc::new(AtomicBool::new(false));
    let compiles = Arc::new(AtomicU64::new(0));
    let loader = load.then(|| {
        let (sandbox, artifacts, stop, compiles) = (sandbox.clone(), artifacts.clone(), stop.clone(), compiles.clone());
        let clock = clock.clone();
        let python = std::fs::read(support::repo_root().join("guest-components/python/avoider/avoider.wasm")).unwrap();
        std::thread::spawn(move || {
            let Ok(start_ns) = start_rx.recv() else {
                return;
            };
            // No cache: every round really compiles.
            let cold = Sandbox::new(None).unwrap();
            while !stop.load(Ordering::Relaxed) {
                let started = Instant::now();
                let avoider = cold.load(&python).unwrap();
                drop(avoider);
                compiles.fetch_add(1, Ordering::Relaxed);
                eprintln!("compiled the Python avoider in {:.1} s", started.elapsed().as_secs_f64());
                // Due after the build (a few ms), on the old set's grid.
                let now = clock.now_ns();
                let first = (now / PERIOD_NS + 50) * PERIOD_NS + (start_ns % PERIOD_NS);
                let (next, _) = build(&sandbox, &artifacts, first);
                if to_loop.send((next, first)).is_err() {
                    break;
                }
                while let Ok(old) = from_loop.try_recv() {
                    drop(old);
                }
            }
        })
    });

    // The settings first, so mlockall's MCL_FUTURE covers the instances.
    let settings = apply_settings();
    let before = memory_kib();
    let (first, _) = build(&sandbox, &artifacts, 0);
    let after = memory_kib();
    // A second set, as an activation builds beside the running one.
    let (second, _) = build(&sandbox, &artifacts, 0);
    let after_second = memory_kib();
    drop((first, second));
    println!(
        "memory (pooling allocator: {}): RSS {:.1} MiB before the 16 components, {:.1} MiB after \
         ({:.0} KiB each), {:.1} MiB with a second set beside ({:.0} KiB per component); \
         address space {:.1} GiB reserved",
        sandbox.is_pooling(),
        before.0 as f64 / 1024.0,
        after.0 as f64 / 1024.0,
        after.0.saturating_sub(before.0) as f64 / 16.0,
        after_second.0 as f64 / 1024.0,
        after_second.0.saturating_sub(after.0) as f64 / 16.0,
        after.1 as f64 / (1024.0 * 1024.0)
    );
    let start_ns = clock.now_ns() + 10 * PERIOD_NS;
    let (mut graph, source) = build(&sandbox, &artifacts, start_ns);
    let _ = start_tx.send(start_ns);

    let mut recorder = Recorder {
        lateness: Vec::with_capacity((seconds * 1100.0) as usize),
        starts: Vec::with_capacity((seconds * 1100.0) as usize),
        source,
        missed: 0,
        swaps: 0,
        incoming,
        pending: None,
        retired,
    };
    let shutdown = Shutdown::new();
    let until = start_ns + (seconds * 1e9) as u64;
    let (cpu_before, process_before) = (thread_cpu_time(), process_cpu());
    let (waited_before, steal_before) = (thread_run_delay_ns(), steal_ms());
    run_with(&mut graph, &clock, &shutdown, Some(until), &mut recorder);
    let (waited, steal) = (thread_run_delay_ns(), steal_ms());
    let (cpu, process) = (thread_cpu_time() - cpu_before, process_cpu() - process_before);
    stop.store(true, Ordering::Relaxed);
    recorder.missed += graph.stats(source).map_or(0, |s| s.missed_ticks);
    let faults = (0..graph.len())
        .filter(|i| graph.state(*i).is_some_and(|s| *s != subsume::runtime::ComponentState::Running))
        .count();

    let cycles = recorder.lateness.len() as u64;
    let mut jitter: Vec<u64> = recorder.starts.windows(2).map(|w| (w[1] - w[0]).abs_diff(PERIOD_NS)).collect();
    let scenario = if load { "while compiling Python + activating" } else { "alone" };
    let settings = if settings.is_empty() { "none".to_string() } else { settings.join(", ") };
    let kind = if std::env::var("KHZ_FLOOR").is_ok_and(|v| v == "1") { "native stand-ins (floor)" } else { "WASM" };
    println!("1 kHz loop, 16 {kind} components, {seconds} s, {scenario}; settings: {settings}");
    println!(
        "cycles: {cycles}; swaps (activations): {}; compiles: {}",
        recorder.swaps,
        compiles.load(Ordering::Relaxed)
    );
    println!("lateness: {}", summary(&mut recorder.lateness));
    println!("period jitter: {}", summary(&mut jitter));
    println!("missed cycles (1 kHz source): {}; components not running at the end: {faults}", recorder.missed);
    // Where the late starts came from: the control thread waiting for a CPU
    // inside this machine (the kernel's run delay), or the machine itself
    // not running (steal time, counted by the hypervisor for every vCPU).
    println!(
        "control thread waited for a CPU: {:.1} ms; steal time of the machine over the run: {} ms",
        waited.zip(waited_before).map_or(f64::NAN, |(after, before)| (after - before) as f64 / 1e6),
        steal.zip(steal_before).map_or_else(|| "unknown".to_string(), |(after, before)| (after - before).to_string())
    );
    println!(
        "CPU per cycle: control thread {:.1} us; whole process {:.1} us",
        cpu.as_secs_f64() * 1e6 / cycles.max(1) as f64,
        process.as_secs_f64() * 1e6 / cycles.max(1) as f64
    );
    drop(recorder);
    if let Some(loader) = loader {
        let _ = loader.join();
    }
}
