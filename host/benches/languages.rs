#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic)]
//! What a component's language costs the host (a bench binary, not a timed
//! test). For each component, by default the obstacle avoider in Rust, C,
//! Python and JavaScript (`guest-components/*/avoider`, built first):
//!
//! - size of the .wasm file;
//! - compile: the first `Sandbox::load` with an empty cache (cranelift
//!   compile, cache write, pre-link, one `describe` instance);
//! - load from the compile cache (deserialize, pre-link, `describe`);
//! - instantiate + `init` from the loaded form;
//! - hop: a 9-ray scan with an obstacle ahead enters the component
//!   (`on-input`), its `tick` emits a command, the host routes it and
//!   delivers it to the next component (p50, p99).
//!
//! Run: `cargo bench --bench languages` (BENCHMARKS.md records the figures),
//! or `cargo bench --bench languages -- FILE.wasm ...` for other components
//! with a vector input 0 and one output (the avoider's ports).

#[path = "../../tests/all/support.rs"]
mod support;

use std::path::PathBuf;
use std::process::Command;
use std::time::{Duration, Instant};

use subsume::config::Policy;
use subsume::contract::{Param, Value};
use subsume::runtime::{Graph, Vacant};
use subsume::sandbox::{GuestLimits, Sandbox};

fn limits() -> GuestLimits {
    GuestLimits { budget: Duration::from_millis(100), ..GuestLimits::default() }
}

/// The four avoiders, built (incrementally) first.
fn avoiders() -> Vec<(String, PathBuf)> {
    let root = support::repo_root();
    let built = Command::new(root.join("guest-components/build-all"))
        .args(["c", "python", "js"])
        .env_remove("CARGO_TARGET_DIR")
        .status()
        .unwrap();
    assert!(built.success(), "guest-components/build-all failed (scripts/setup installs the toolchains)");
    let mut all = vec![("rust".to_string(), support::guest("avoider"))];
    for lang in ["c", "python", "js"] {
        all.push((lang.to_string(), root.join(format!("guest-components/{lang}/avoider/avoider.wasm"))));
    }
    all
}

fn percentile(sorted: &[u64], p: f64) -> u64 {
    sorted[((sorted.len() - 1) as f64 * p).round() as usize]
}

fn measure(label: &str, bytes: &[u8]) {
    let cache = tempfile::tempdir().unwrap();
    let sandbox = Sandbox::new(Some(cache.path().to_path_buf())).unwrap();
    let start = Instant::now();
    let artifact = sandbox.load(bytes).unwrap();
    let compile = start.elapsed();
    let rounds = 10;
    let start = Instant::now();
    for _ in 0..rounds {
        sandbox.load(bytes).unwrap();
    }
    let from_cache = start.elapsed() / rounds;
    // Every declared parameter at its default, as the host hands them over.
    let params: Vec<Param> = artifact
        .description
        .params
        .iter()
        .map(|p| Param { name: p.name.clone(), value: p.default_value.clone() })
        .collect();
    let start = Instant::now();
    for _ in 0..rounds {
        drop(sandbox.instantiate(&artifact, label, &limits(), &params).unwrap());
    }
    let instantiate = start.elapsed() / rounds;

    // source -> component (ticked on every step) -> sink.
    let mut graph = Graph::new();
    let source = graph.add("source", Box::new(Vacant), 1, 0.0, 0);
    let component = Box::new(sandbox.instantiate(&artifact, label, &limits(), &params).unwrap());
    let tested = graph.add(label, component, 1, 1000.0, 0);
    let sink = graph.add("sink", Box::new(Vacant), 0, 0.0, 0);
    graph.connect(source, 0, tested, 0, Policy::Latest);
    graph.connect(tested, 0, sink, 0, Policy::Latest);
    let scan = Value::Vector(vec![2.0, 2.0, 2.0, 0.3, 0.2, 0.3, 3.0, 3.0, 3.0]);
    let (warm_up, samples) = (2_000, 20_000);
    let mut times = Vec::with_capacity(samples);
    for i in 0..(warm_up + samples) {
        let now = (i as u64 + 1) * 1_000_000;
        let value = scan.clone();
        let start = Instant::now();
        graph.inject(source, 0, value, now);
        graph.step(now);
        let elapsed = start.elapsed().as_nanos() as u64;
        if i >= warm_up {
            times.push(elapsed);
        }
    }
    let stats = graph.stats(sink).unwrap();
    assert!(stats.messages_in >= samples as u64, "{label} emitted {} commands for {samples} scans", stats.messages_in);
    times.sort_unstable();
    println!(
        "{label:<8} {:>9} KB   compile {:>8.1} ms   load from cache {:>7.2} ms   instantiate + init {:>8.1} us   \
         hop (scan in, command delivered) p50 {:>6.1} us  p99 {:>6.1} us",
        bytes.len() / 1024,
        compile.as_secs_f64() * 1e3,
        from_cache.as_secs_f64() * 1e3,
        instantiate.as_secs_f64() * 1e6,
        percentile(&times, 0.50) as f64 / 1e3,
        percentile(&times, 0.99) as f64 / 1e3,
    );
}

fn main() {
    // `cargo bench` passes --bench; other arguments name components.
    let files: Vec<PathBuf> = std::env::args().skip(1).filter(|a| !a.starts_with("--")).map(PathBuf::from).collect();
    let components = if files.is_empty() {
        avoiders()
    } else {
        files.into_iter().map(|f| (f.file_stem().unwrap().to_string_lossy().into_owned(), f)).collect()
    };
    for (label, path) in components {
        measure(&label, &std::fs::read(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display())));
    }
}
