//! What a component's compile costs under the wasmtime settings that
//! matter (issue 18: the Python avoider took 14-19 s): cranelift's
//! optimisation level and parallel compilation, each on the same bytes,
//! with the engine settings the host uses otherwise left at their defaults.
//!
//!   cargo bench --profile dev --bench compile [-- FILE.wasm ...]
//!
//! Default files: the Rust, C, Python and JavaScript avoiders. Prints one
//! line per (file, setting): compile seconds, best of `ROUNDS`.

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
