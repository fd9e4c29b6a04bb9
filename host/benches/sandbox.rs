#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic)]
//! How fast a runaway guest is stopped (a bench binary): a guest that spins
//! for ever in `tick`, under a 5 ms budget. A sample is the wall time of that
//! `tick` call, from the host calling it to the host having the fault in
//! hand; the overshoot is that minus the budget. p50 and p99 over fresh
//! instances.
//!
//! Run: `cargo bench --bench sandbox` (BENCHMARKS.md records the figures).

#[path = "../tests/support/mod.rs"]
mod support;

use std::time::{Duration, Instant};

use subsume::contract::Param;
use subsume::runtime::{CallError, Component};
use subsume::sandbox::{GuestLimits, Sandbox};

fn percentile(sorted: &[u64], p: f64) -> u64 {
    sorted[((sorted.len() - 1) as f64 * p).round() as usize]
}

fn main() {
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
    for _ in 0..samples {
        let mut guest = sandbox.instantiate(&artifact, "runaway", &limits, &params).unwrap();
        let start = Instant::now();
        let result = guest.tick(0, &mut Vec::new());
        let took = start.elapsed();
        assert!(matches!(result, Err(CallError::Fault(ref r)) if r.contains("exceeded its time budget")), "{result:?}");
        overshoot.push(took.saturating_sub(budget).as_micros() as u64);
    }
    overshoot.sort_unstable();
    println!(
        "budget overrun -> stopped, 5 ms budget, 1 ms epoch tick: time past the budget p50 {} us   p99 {} us   max {} us   ({samples} samples)",
        percentile(&overshoot, 0.50),
        percentile(&overshoot, 0.99),
        overshoot.last().copied().unwrap_or_default()
    );
}
