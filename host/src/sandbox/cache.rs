//! The on-disk cache of compiled components. Invariant: only files this
//! host wrote to its own private folder, named by the sha256 of their source
//! and the engine's compatibility hash, are ever deserialized; bytes from
//! outside are only compiled.

use std::hash::{Hash, Hasher};
use std::path::{Path, PathBuf};
use std::sync::Arc;

use wasmtime::Engine;

use super::function_cache::{FunctionCache, FunctionCacheStats};
use super::{SandboxError, error_text};
use crate::fsutil::write_atomically;
use crate::runtime::scheduling;

fn create_private_dir(dir: &Path) -> std::io::Result<()> {
    use std::os::unix::fs::DirBuilderExt;
    std::fs::DirBuilder::new().recursive(true).mode(0o700).create(dir)
}

/// Where compiled components are kept, and the engine they were compiled by.
#[derive(Debug)]
pub(super) struct CompileCache {
    dir: Option<PathBuf>,
    engine_key: String,
    /// Cranelift's cache of compiled functions, which the engine was
    /// configured with: here for its counters and its bound.
    functions: Option<Arc<FunctionCache>>,
}

impl CompileCache {
    /// A cache in `dir` (created private when missing; no cache when it
    /// cannot be) for artifacts of `engine`.
    pub(super) fn new(engine: &Engine, dir: Option<PathBuf>, functions: Option<Arc<FunctionCache>>) -> CompileCache {
        let mut hasher = std::collections::hash_map::DefaultHasher::new();
        engine.precompile_compatibility_hash().hash(&mut hasher);
        let engine_key = format!("{:016x}", hasher.finish());
        let dir = dir.filter(|dir| match create_private_dir(dir) {
            Ok(()) => true,
            Err(err) => {
                tracing::warn!("cannot use cache directory {}: {err}; compiling without a cache", dir.display());
                false
            }
        });
        CompileCache { dir, engine_key, functions }
    }

    pub(super) fn function_stats(&self) -> Option<FunctionCacheStats> {
        self.functions.as_ref().map(|f| f.stats())
    }

    pub(super) fn dir(&self) -> Option<&Path> {
        self.dir.as_deref()
    }

    /// The compiled form of `bytes` (whose sha256 is `sha256`): from the
    /// cache when this host compiled it before, else compiled now (and
    /// cached).
    pub(super) fn compile(
        &self,
        engine: &Engine,
        sha256: &str,
        bytes: &[u8],
    ) -> Result<wasmtime::component::Component, SandboxError> {
        let cached = self.dir.as_ref().map(|dir| dir.join(format!("{sha256}-{}.cwasm", self.engine_key)));
        if let Some(path) = cached.as_ref().filter(|p| p.is_file()) {
            // SAFETY: the file is in this host's private cache directory and
            // was written by `compile_cached` below from `Component::serialize`
            // of a component whose source hashes to `sha256`, by an engine
            // with the same compatibility hash. User bytes never land here
            // without being compiled first.
            match unsafe { wasmtime::component::Component::deserialize_file(engine, path) } {
                Ok(component) => return Ok(component),
                Err(err) => {
                    tracing::warn!("ignoring unusable cache entry {}: {err}", path.display())
                }
            }
        }
        // Compiling a large component (a Python one) takes seconds: say so
        // before, and how long it took after.
        let short = sha256.get(..12).unwrap_or(sha256);
        tracing::info!("compiling component {short} ({} KiB; not in the cache yet)...", bytes.len().div_ceil(1024));
        let started = std::time::Instant::now();
        let before = self.function_stats();
        // On a background thread: the compile yields the CPU to the control
        // loop (its parallel workers are background threads too).
        let component = scheduling::in_background("subsume-compile", || {
            wasmtime::component::Component::new(engine, bytes).map_err(|e| SandboxError::Compile(error_text(&e)))
        });
        let seconds = started.elapsed().as_secs_f64();
        // What the function cache served (counters shared with concurrent
        // compiles, which the host serialises anyway).
        let reused = match (before, self.function_stats()) {
            (Some(before), Some(after)) => {
                let hits = after.hits.saturating_sub(before.hits);
                let looked_up = hits + after.misses.saturating_sub(before.misses);
                format!(" ({hits} of {looked_up} functions from the cache)")
            }
            _ => String::new(),
        };
        if let Some(functions) = &self.functions {
            functions.prune();
        }
        let component = component?;
        tracing::info!("compiled component {short} in {seconds:.2} s{reused}");
        if let Some(path) = cached {
            match component.serialize() {
                Ok(serialized) => {
                    if let Err(err) = write_atomically(&path, &serialized) {
                        tracing::warn!("cannot write cache entry {}: {err}", path.display());
                    }
                }
                Err(err) => tracing::warn!("cannot serialize compiled component: {err}"),
            }
        }
        Ok(component)
    }
}
