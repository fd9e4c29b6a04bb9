//! The WebAssembly sandbox: the wasmtime [`Engine`] of the robot's guests, the
//! linker that offers guests the `subsume:robot/host` interface and a minimal
//! WASI (no preopened directories, no sockets, no environment, no arguments;
//! stdin closed; stdout and stderr go to the log; the cycle's clocks, seeded
//! generators, and a poll that never waits), a [`Store`] per component with
//! memory limits, a CPU-time budget and a wall-clock cap on every call, an
//! on-disk cache of compiled components and of compiled functions
//! (cranelift's incremental cache: a rebuilt component compiles only the
//! functions that changed), and a second engine for a task's scoring
//! components (`scorer.rs`), with the same WASI and limits, clocks at 0.
//!
//! Invariants:
//! - bytes that came from outside are only ever compiled (`Component::new`),
//!   never deserialized; only artifacts this host wrote to its own cache
//!   directory, named by the sha256 of their source, are deserialized;
//! - every call into a guest runs under its CPU-time budget and wall-clock
//!   cap (epoch checks, `budget.rs`);
//! - no WASI function a guest can reach waits for time or input (`wasi.rs`);
//! - a guest that traps, overruns its budget or breaks a host rule is
//!   reported as [`CallError::Fault`] and its store is never called again.

mod artifact;
mod budget;
mod cache;
mod component;
mod engine;
mod function_cache;
mod guest;
mod guest_output;
mod limits;
pub mod preamble;
mod scorer;
mod translator;
mod wasi;

use thiserror::Error;

pub use artifact::{Contract, TranslatorArtifact, WasmArtifact};
pub use budget::{OverBudget, WALL_CAP_FACTOR, thread_cpu_time, wall_cap};
pub use component::WasmComponent;
pub use engine::{Sandbox, check_component_header};
pub use function_cache::{
    FUNCTION_CACHE_PRUNE_TO, FunctionCacheStats, MAX_FUNCTION_CACHE_BYTES, MAX_FUNCTION_ENTRY_BYTES,
};
pub use guest::{GuestLimits, random_seed};
pub use guest_output::{GuestOutput, LogBudget, MAX_GUEST_LINE_BYTES};
pub use limits::{
    DESCRIBE_BUDGET, DESCRIBE_MEMORY_BYTES, EPOCH_TICK, HOSTCALL_FUEL_SLACK, INIT_BUDGET, MAX_COMPONENT_HANDLES,
    MAX_GUEST_MESSAGE_BYTES, MAX_INSTANCES_PER_STORE, MAX_RESOURCE_ENTRIES, MAX_TABLES_PER_STORE, MAX_WASM_STACK_BYTES,
    POOL_MAX_MEMORY_BYTES, POOL_TOTAL_CORE_INSTANCES,
};
pub use scorer::{
    MAX_COMPILED_SCORERS, MAX_SUB_SCORE_NAME, MAX_SUB_SCORES, SCORER_BUDGET, SCORER_MEMORY_BYTES, ScorerError,
    check_scorer, run_scorer,
};
pub use translator::{MAX_FEEDBACK_PER_DECODE, MAX_TRANSLATED_FRAME_BYTES, TranslatorCallError, WasmTranslator};
pub use wasi::BlockingCall;

#[derive(Clone, Debug, Error)]
pub enum SandboxError {
    #[error("failed to start the webassembly engine: {0}")]
    Engine(String),
    #[error("not a webassembly component: {0}")]
    NotAComponent(String),
    #[error("failed to compile: {0}")]
    Compile(String),
    #[error("does not fit the subsume:robot/component world: {0}")]
    World(String),
    #[error("{call} failed: {reason}")]
    Call { call: &'static str, reason: String },
    #[error("does not fit the subsume:robot/translator world: {0}")]
    TranslatorWorld(String),
    #[error("describe() returned an invalid description: {}", .0.join("; "))]
    BadDescription(Vec<String>),
}

/// Largest `.wasm` file loaded: big enough for Python and JavaScript
/// components (~20 MB), small enough that a bogus file cannot exhaust memory.
pub const MAX_COMPONENT_BYTES: u64 = 32 << 20;

/// Why a component file did not load.
#[derive(Clone, Debug, Error)]
pub enum LoadError {
    #[error("cannot read '{}': {reason}", .path.display())]
    Read { path: std::path::PathBuf, reason: String },
    #[error("'{}' is larger than {} MiB", .path.display(), MAX_COMPONENT_BYTES >> 20)]
    TooLarge { path: std::path::PathBuf },
    #[error("cannot load '{}': {source}", .path.display())]
    Component { path: std::path::PathBuf, source: SandboxError },
    #[error("cannot load translator '{}': {source}", .path.display())]
    Translator { path: std::path::PathBuf, source: SandboxError },
}

/// Reads a component file, refusing files over [`MAX_COMPONENT_BYTES`].
pub fn read_component_file(path: &std::path::Path) -> Result<Vec<u8>, LoadError> {
    use std::io::Read as _;
    let read = |e: std::io::Error| LoadError::Read { path: path.to_path_buf(), reason: e.to_string() };
    let file = std::fs::File::open(path).map_err(read)?;
    let mut bytes = Vec::new();
    file.take(MAX_COMPONENT_BYTES + 1).read_to_end(&mut bytes).map_err(read)?;
    if bytes.len() as u64 > MAX_COMPONENT_BYTES {
        return Err(LoadError::TooLarge { path: path.to_path_buf() });
    }
    Ok(bytes)
}

/// A wasmtime error and its root cause, as one line of text.
fn error_text(err: &wasmtime::Error) -> String {
    let mut text = err.to_string();
    let cause = err.root_cause().to_string();
    if cause != text {
        text = format!("{text}: {cause}");
    }
    text
}
