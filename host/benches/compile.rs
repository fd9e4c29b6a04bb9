//! What a component's compile costs under the wasmtime settings that
//! matter (issue 18: the Python avoider took 14-19 s): cranelift's
//! optimisation level and parallel compilation, each on the same bytes,
//! with the engine settings the host uses otherwise left at their defaults.
//!
//!   cargo bench --profile dev --bench compile [-- FILE.wasm ...]
//!
//! Default files: the Rust, C, Python and JavaScript avoiders. Prints one
//! line per (file, setting): compile seconds, best of `ROUNDS`.

use std::sync::atomic::Ordering;
use std::time::Instant;

use wasmtime::{Config, Engine, OptLevel, component::Component};

const ROUNDS: usize = 2;

fn main() {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let mut files: Vec<std::path::PathBuf> =
        std::env::args().skip(1).filter(|a| a.ends_with(".wasm")).map(Into::into).collect();
    if files.is_empty() {
        files = [
            "guest-components/rust/target/wasm32-wasip2/release/avoider.wasm",
            "guest-components/c/avoider/avoider.wasm",
            "guest-components/python/avoider/avoider.wasm",
            "guest-components/js/avoider/avoider.wasm",
        ]
        .iter()
        .map(|f| root.join(f))
        .filter(|f| f.is_file())
        .collect();
    }
    if std::env::var_os("INCREMENTAL").is_some() {
        incremental(&files);
        return;
    }
    let settings: [(&str, OptLevel, bool); 4] = [
        ("speed, parallel (the host's)", OptLevel::Speed, true),
        ("speed, one thread", OptLevel::Speed, false),
        ("none, parallel", OptLevel::None, true),
        ("speed-and-size, parallel", OptLevel::SpeedAndSize, true),
    ];
    for file in &files {
        let Ok(bytes) = std::fs::read(file) else { continue };
        for (label, opt, parallel) in settings {
            let mut config = Config::new();
            config.wasm_component_model(true);
            config.epoch_interruption(true);
            config.parallel_compilation(parallel);
            config.cranelift_opt_level(opt);
            let Ok(engine) = Engine::new(&config) else { continue };
            let mut best = f64::INFINITY;
            for _ in 0..ROUNDS {
                let started = Instant::now();
                if Component::new(&engine, &bytes).is_err() {
                    break;
                }
                best = best.min(started.elapsed().as_secs_f64());
            }
            println!(
                "{} ({} KiB), {label}: {best:.2} s",
                file.file_name().map(|n| n.to_string_lossy()).unwrap_or_default(),
                bytes.len() / 1024
            );
        }
    }
}

/// An in-memory function cache that counts what it served.
#[derive(Debug, Default)]
struct MemoryStore {
    entries: std::sync::Mutex<std::collections::HashMap<Vec<u8>, Vec<u8>>>,
    hits: std::sync::atomic::AtomicUsize,
    misses: std::sync::atomic::AtomicUsize,
}

impl wasmtime::CacheStore for MemoryStore {
    fn get(&self, key: &[u8]) -> Option<std::borrow::Cow<'_, [u8]>> {
        let found = self.entries.lock().ok()?.get(key).cloned();
        let counter = if found.is_some() { &self.hits } else { &self.misses };
        counter.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        found.map(std::borrow::Cow::Owned)
    }
    fn insert(&self, key: &[u8], value: Vec<u8>) -> bool {
        self.entries.lock().map(|mut e| e.insert(key.to_vec(), value)).is_ok()
    }
}

/// `INCREMENTAL=1 cargo bench --profile dev --bench compile -- A.wasm B.wasm`:
/// each file compiled without a function cache (the baseline), then one
/// after another by one engine with cranelift's incremental cache (in
/// memory): the first cold, each next one served what its functions share
/// with the earlier ones (B = A rebuilt after a one-line edit).
fn incremental(files: &[std::path::PathBuf]) {
    // The baseline: the same files, the same settings, no function cache.
    let mut plain = Config::new();
    plain.wasm_component_model(true);
    plain.epoch_interruption(true);
    if let Ok(engine) = Engine::new(&plain) {
        for file in files {
            let Ok(bytes) = std::fs::read(file) else { continue };
            let started = Instant::now();
            let ok = Component::new(&engine, &bytes).is_ok();
            println!(
                "{} ({} KiB), no function cache: {:.2} s{}",
                file.display(),
                bytes.len() / 1024,
                started.elapsed().as_secs_f64(),
                if ok { "" } else { " (failed)" }
            );
        }
    }
    let store = std::sync::Arc::new(MemoryStore::default());
    let mut config = Config::new();
    config.wasm_component_model(true);
    config.epoch_interruption(true);
    let Ok(config) = config.enable_incremental_compilation(store.clone()) else { return };
    let Ok(engine) = Engine::new(config) else { return };
    for file in files {
        let Ok(bytes) = std::fs::read(file) else { continue };
        let (h0, m0) = (store.hits.load(Ordering::Relaxed), store.misses.load(Ordering::Relaxed));
        let started = Instant::now();
        let ok = Component::new(&engine, &bytes).is_ok();
        let took = started.elapsed().as_secs_f64();
        let (h1, m1) = (store.hits.load(Ordering::Relaxed), store.misses.load(Ordering::Relaxed));
        println!(
            "{} ({} KiB), incremental cache: {took:.2} s, {} functions from the cache, {} compiled{}",
            file.display(),
            bytes.len() / 1024,
            h1 - h0,
            m1 - m0,
            if ok { "" } else { " (failed)" }
        );
    }
}
