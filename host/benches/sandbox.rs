#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic)]
//! How fast a runaway guest is stopped (a bench binary): a guest that spins
//! for ever in `tick`, under a 5 ms budget of CPU time. A sample is that
//! `tick` call, from the host calling it to the host having the fault in
//! hand: the CPU time it used past the budget (what the budget counts), and
//! its wall time past the budget (what the control loop waited; on a loaded
//! machine it includes the time the thread was preempted). p50 and p99 over
//! fresh instances.
//!
//! Run: `cargo bench --bench sandbox`; loaded: `scripts/with-load cargo
//! bench --bench sandbox` (BENCHMARKS.md records the figures).

#[path = "../../tests/all/support.rs"]
mod support;

use std::time::{Duration, Instant};

use subsume::contract::Param;
use subsume::runtime::{CallError, Component};
use subsume::sandbox::{GuestLimits, Sandbox, thread_cpu_time};

fn percentile(sorted: &[u64], p: f64) -> u64 {
    sorted[((sorted.len() - 1) as f64 * p).round() as usize]
}

/// What one read of the thread's CPU clock costs: the budget reads it only
/// at epoch checks (a call shorter than a tick reads it never), so this is
/// a cost per check, not per call.
fn cpu_clock_read_cost() {
    let reads = 200_000u32;
    let start = Instant::now();
    let mut last = Duration::ZERO;
    for _ in 0..reads {
        last = std::hint::black_box(thread_cpu_time());
    }
    let per_read = start.elapsed() / reads;
    assert!(last > Duration::ZERO);
    println!("thread cpu clock (clock_gettime CLOCK_THREAD_CPUTIME_ID): {} ns per read", per_read.as_nanos());
}

fn main() {
    cpu_clock_read_cost();
    let bytes = std::fs::read(support::guest("test-faulty")).unwrap();
    let sandbox = Sandbox::new(Some(support::cache_dir())).unwrap();
    let artifact = sandbox.load(&bytes).unwrap();
    let budget = Duration::from_millis(5);
    let limits = GuestLimits { memory_bytes: 16 << 20, budget, ..GuestLimits::default() };
    let params = vec![
        Param { name: "mode".into(), value: "loop-on-tick".into() },
        Param { name: "after".into(), value: "0".into() },
    ];
    let samples = 300;
    let mut overshoot = Vec::with_capacity(samples);
    let mut cpu_overshoot = Vec::with_capacity(samples);
    for _ in 0..samples {
        let mut guest = sandbox.instantiate(&artifact, "runaway", &limits, &params).unwrap();
        let start = Instant::now();
        let cpu_start = thread_cpu_time();
        let result = guest.tick(0, &mut Vec::new());
        let cpu = thread_cpu_time() - cpu_start;
        let took = start.elapsed();
        cpu_overshoot.push(cpu.saturating_sub(budget).as_micros() as u64);
        assert!(
            matches!(result, Err(CallError::Fault(ref r)) if r.contains("exceeded its cpu-time budget")),
            "{result:?}"
        );
        overshoot.push(took.saturating_sub(budget).as_micros() as u64);
    }
    overshoot.sort_unstable();
    cpu_overshoot.sort_unstable();
    println!(
        "budget overrun -> stopped, 5 ms cpu budget, 1 ms epoch tick: wall time past the budget p50 {} us   p99 {} us   max {} us   ({samples} samples)",
        percentile(&overshoot, 0.50),
        percentile(&overshoot, 0.99),
        overshoot.last().copied().unwrap_or_default()
    );
    println!(
        "                                                          cpu time past the budget  p50 {} us   p99 {} us   max {} us",
        percentile(&cpu_overshoot, 0.50),
        percentile(&cpu_overshoot, 0.99),
        cpu_overshoot.last().copied().unwrap_or_default()
    );
}
