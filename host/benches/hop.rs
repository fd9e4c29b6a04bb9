#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic)]
//! Runtime benchmarks (a bench binary, not a timed test):
//!
//! - hop latency: a value enters a guest's input, the guest emits it, the host
//!   routes it into the next component's mailbox and delivers it: one
//!   host -> guest -> host -> next component hop (p50, p99), for a scalar and
//!   a 100-element vector;
//! - chain throughput: values pushed through a chain of 8 relay guests,
//!   counted as deliveries per second;
//! - load from the compile cache, and instantiate + init from the loaded form;
//! - what the stall watchdog costs the hop: the same hop and chain with the
//!   graph attached to a heartbeat and the watchdog thread sampling it,
//!   interleaved with unwatched rounds in one run.
//!
//! Run: `cargo bench --bench hop` (BENCHMARKS.md records the figures).

#[path = "../../tests/all/support.rs"]
mod support;

use std::sync::Arc;
use std::time::{Duration, Instant};

use subsume::config::Policy;
use subsume::contract::Value;
use subsume::runtime::stall::DEFAULT_STALL_LIMIT;
use subsume::runtime::{Component, Graph, Heartbeat, StallWatchdog, Vacant};
use subsume::sandbox::{GuestLimits, Sandbox};

const BUDGET: Duration = Duration::from_millis(100);

fn limits() -> GuestLimits {
    GuestLimits { memory_bytes: 16 << 20, budget: BUDGET, ..GuestLimits::default() }
}

fn relay(sandbox: &Sandbox, bytes: &[u8]) -> Box<dyn Component> {
    let artifact = sandbox.load(bytes).unwrap();
    Box::new(sandbox.instantiate(&artifact, "relay", &limits(), &[]).unwrap())
}

/// source (native, only used to inject) -> `relays` relay guests -> sink.
/// `port` 0 carries scalars, 1 vectors.
fn chain(sandbox: &Sandbox, bytes: &[u8], relays: usize, port: u32) -> (Graph, usize) {
    let mut graph = Graph::new();
    let source = graph.add("source", Box::new(Vacant), 2, 0.0, 0);
    let mut previous = source;
    for _ in 0..relays {
        let next = graph.add("relay", relay(sandbox, bytes), 2, 0.0, 0);
        graph.connect(previous, port, next, port, Policy::Latest);
        previous = next;
    }
    let sink = graph.add("sink", Box::new(Vacant), 0, 0.0, 0);
    graph.connect(previous, port, sink, port, Policy::Latest);
    (graph, source)
}

/// What one `Instant::now()` + `elapsed()` pair costs here; subtracted from
/// every sample so the figures are the work, not the stopwatch.
fn timer_overhead() -> u64 {
    let mut times: Vec<u64> = (0..100_000)
        .map(|_| {
            let start = Instant::now();
            start.elapsed().as_nanos() as u64
        })
        .collect();
    times.sort_unstable();
    percentile(&times, 0.5)
}

fn percentile(sorted: &[u64], p: f64) -> u64 {
    sorted[((sorted.len() - 1) as f64 * p).round() as usize]
}

fn hop_latency(sandbox: &Sandbox, bytes: &[u8], label: &str, port: u32, value: Value, overhead: u64) {
    let (p50, p99, samples) = hop_samples(sandbox, bytes, port, &value, overhead, None);
    println!("hop latency, {label:<18} p50 {p50:>6} ns   p99 {p99:>6} ns   ({samples} samples)");
}

/// (p50, p99, samples) of the hop; with `watch`, the graph publishes its
/// heartbeat there.
fn hop_samples(
    sandbox: &Sandbox,
    bytes: &[u8],
    port: u32,
    value: &Value,
    overhead: u64,
    watch: Option<&Arc<Heartbeat>>,
) -> (u64, u64, usize) {
    let (mut graph, source) = chain(sandbox, bytes, 1, port);
    if let Some(heartbeat) = watch {
        graph.attach(heartbeat);
    }
    let samples = 200_000;
    for _ in 0..20_000 {
        graph.inject(source, port, value.clone(), 0);
    }
    let mut times = Vec::with_capacity(samples);
    for _ in 0..samples {
        let v = value.clone();
        let start = Instant::now();
        graph.inject(source, port, v, 0);
        times.push((start.elapsed().as_nanos() as u64).saturating_sub(overhead));
    }
    // Between rounds the bench, not a stuck call, holds the thread.
    graph.asleep();
    times.sort_unstable();
    (percentile(&times, 0.50), percentile(&times, 0.99), samples)
}

/// The hop and the chain with and without the stall watchdog (its
/// heartbeat attached, its thread sampling), in alternating rounds.
fn watchdog_cost(sandbox: &Sandbox, bytes: &[u8], overhead: u64) {
    let heartbeat = Heartbeat::new(DEFAULT_STALL_LIMIT);
    let watchdog = StallWatchdog::start(heartbeat.clone(), Box::new(|_| {})).unwrap();
    let value = Value::Scalar(1.5);
    let (mut plain, mut watched) = (Vec::new(), Vec::new());
    for round in 0..4 {
        let (p50, p99, _) = hop_samples(sandbox, bytes, 0, &value, overhead, None);
        let (wp50, wp99, _) = hop_samples(sandbox, bytes, 0, &value, overhead, Some(&heartbeat));
        println!(
            "round {round}: hop, scalar: unwatched p50 {p50} ns p99 {p99} ns; watched p50 {wp50} ns p99 {wp99} ns"
        );
        plain.push(p50 as f64);
        watched.push(wp50 as f64);
    }
    let (mut plain_rate, mut watched_rate) = (Vec::new(), Vec::new());
    for round in 0..4 {
        let rate = chain_rate(sandbox, bytes, None);
        let watched_chain = chain_rate(sandbox, bytes, Some(&heartbeat));
        println!("round {round}: chain of 8: unwatched {rate:.2} M/s; watched {watched_chain:.2} M/s");
        plain_rate.push(rate);
        watched_rate.push(watched_chain);
    }
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
    println!(
        "stall watchdog: hop p50 watched/unwatched = {:.3}, chain throughput watched/unwatched = {:.3} (means of 4 rounds); stalls seen: {}",
        mean(&watched) / mean(&plain),
        mean(&watched_rate) / mean(&plain_rate),
        watchdog.stalls()
    );
}

/// Deliveries per second (millions) through a chain of 8 relays.
fn chain_rate(sandbox: &Sandbox, bytes: &[u8], watch: Option<&Arc<Heartbeat>>) -> f64 {
    let relays = 8;
    let (mut graph, source) = chain(sandbox, bytes, relays, 0);
    if let Some(heartbeat) = watch {
        graph.attach(heartbeat);
    }
    let values = 200_000u64;
    for i in 0..10_000 {
        graph.inject(source, 0, Value::Scalar(i as f64), 0);
    }
    let start = Instant::now();
    for i in 0..values {
        graph.inject(source, 0, Value::Scalar(i as f64), 0);
    }
    let rate = (values * (relays as u64 + 1)) as f64 / start.elapsed().as_secs_f64() / 1e6;
    graph.asleep();
    rate
}

/// The floor under a hop: one `on-input` call of the relay guest (which
/// emits once) without the graph around it.
fn direct_call(sandbox: &Sandbox, bytes: &[u8], overhead: u64) {
    let mut relay = relay(sandbox, bytes);
    let value = Value::Scalar(1.5);
    let mut out = Vec::with_capacity(4);
    let samples = 200_000;
    let mut times = Vec::with_capacity(samples);
    for i in 0..(samples + 20_000) {
        let start = Instant::now();
        relay.on_input(0, &value, 0, 0, &mut out).unwrap();
        let elapsed = (start.elapsed().as_nanos() as u64).saturating_sub(overhead);
        out.clear();
        if i >= 20_000 {
            times.push(elapsed);
        }
    }
    times.sort_unstable();
    println!(
        "direct on-input call of the relay guest (emits once): p50 {:>6} ns   p99 {:>6} ns",
        percentile(&times, 0.50),
        percentile(&times, 0.99)
    );
}

fn throughput(sandbox: &Sandbox, bytes: &[u8]) {
    let relays = 8;
    let (mut graph, source) = chain(sandbox, bytes, relays, 0);
    let values = 200_000u64;
    for i in 0..10_000 {
        graph.inject(source, 0, Value::Scalar(i as f64), 0);
    }
    let before = graph.stats(1).unwrap().messages_in;
    let start = Instant::now();
    for i in 0..values {
        graph.inject(source, 0, Value::Scalar(i as f64), 0);
    }
    let elapsed = start.elapsed();
    assert_eq!(graph.stats(1).unwrap().messages_in - before, values);
    let deliveries = values * (relays as u64 + 1);
    println!(
        "chain throughput, {relays} relays: {:.2} M messages/s ({deliveries} deliveries in {:.3} s)",
        deliveries as f64 / elapsed.as_secs_f64() / 1e6,
        elapsed.as_secs_f64()
    );
}

fn load_and_instantiate(bytes: &[u8]) {
    let cache = tempfile::tempdir().unwrap();
    let sandbox = Sandbox::new(Some(cache.path().to_path_buf())).unwrap();
    let start = Instant::now();
    sandbox.load(bytes).unwrap();
    let compile = start.elapsed();
    let rounds = 50;
    let start = Instant::now();
    for _ in 0..rounds {
        sandbox.load(bytes).unwrap();
    }
    let from_cache = start.elapsed() / rounds;
    let artifact = sandbox.load(bytes).unwrap();
    let start = Instant::now();
    for _ in 0..rounds {
        let instance = sandbox.instantiate(&artifact, "relay", &limits(), &[]).unwrap();
        drop(instance);
    }
    let instantiate = start.elapsed() / rounds;
    println!(
        "test-relay ({} KB): compile {:.1} ms, load from cache {:.0} us, instantiate + init {:.0} us (pooling: {})",
        bytes.len() / 1024,
        compile.as_secs_f64() * 1e3,
        from_cache.as_secs_f64() * 1e6,
        instantiate.as_secs_f64() * 1e6,
        sandbox.is_pooling()
    );
}

fn main() {
    // `cargo bench` passes --bench; any other argument filters nothing here.
    let bytes = std::fs::read(support::guest("test-relay")).unwrap();
    let sandbox = Sandbox::new(Some(support::cache_dir())).unwrap();
    let overhead = timer_overhead();
    println!("timer overhead subtracted from each sample: {overhead} ns");
    hop_latency(&sandbox, &bytes, "scalar", 0, Value::Scalar(1.5), overhead);
    hop_latency(&sandbox, &bytes, "vector of 100 f64", 1, Value::Vector((0..100).map(f64::from).collect()), overhead);
    direct_call(&sandbox, &bytes, overhead);
    // The same hop on an engine without epoch interruption: what the epoch
    // checks (the per-call budget) cost.
    let unchecked = Sandbox::without_budgets_for_benchmarks(None).unwrap();
    hop_latency(&unchecked, &bytes, "scalar, no epochs", 0, Value::Scalar(1.5), overhead);
    throughput(&sandbox, &bytes);
    watchdog_cost(&sandbox, &bytes, overhead);
    load_and_instantiate(&bytes);
}
