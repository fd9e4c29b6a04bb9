//! The one wasmtime engine of the process, its linker (WASI p2 without
//! preopens, sockets, environment or arguments, with the host's
//! non-blocking clocks and poll: `wasi.rs`; `subsume:robot/host`), the
//! epoch ticker, and loading components: compile (or take from the cache),
//! link against a world, describe.

use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::thread::JoinHandle;

use sha2::{Digest, Sha256};
use wasmtime::component::{HasSelf, Linker};
use wasmtime::{Config, Engine, InstanceAllocationStrategy, PoolingAllocationConfig, Store};

use super::artifact::{ComponentPre, Contract, TranslatorArtifact, TranslatorPre, WasmArtifact};
use super::cache::CompileCache;
use super::component::{WasmComponent, instantiate_component};
use super::function_cache::{FunctionCache, FunctionCacheStats};
use super::guest::{GuestLimits, GuestState, arm, call_error, new_store};
use super::limits::{
    DESCRIBE_BUDGET, DESCRIBE_MEMORY_BYTES, EPOCH_TICK, MAX_INSTANCES_PER_STORE, MAX_MEMORIES_PER_STORE,
    MAX_TABLES_PER_STORE, MAX_WASM_STACK_BYTES, POOL_MAX_MEMORY_BYTES, POOL_TOTAL_CORE_INSTANCES,
};
use super::translator::WasmTranslator;
use super::{SandboxError, error_text};
use crate::config::limits::MAX_COMPONENTS;
use crate::contract::{Description, Param, ValueKind, check_description};
use crate::contract::{bindings, translator_bindings, v1};
use crate::runtime::{Component, scheduling};

/// The per-process engine, linker, epoch ticker and compile cache.
pub struct Sandbox {
    engine: Engine,
    linker: Linker<GuestState>,
    cache: CompileCache,
    pooling: bool,
    /// Calls have no wall-clock cap ([`Sandbox::on_simulated_time`]).
    simulated_time: bool,
    _ticker: EpochTicker,
}

impl std::fmt::Debug for Sandbox {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Sandbox").field("cache_dir", &self.cache.dir()).field("pooling", &self.pooling).finish()
    }
}

impl Sandbox {
    /// Starts the engine and its epoch ticker. Compiled components are cached
    /// in `cache_dir` when given.
    pub fn new(cache_dir: Option<PathBuf>) -> Result<Sandbox, SandboxError> {
        Sandbox::with_epochs(cache_dir, true)
    }

    /// This sandbox's guests run on simulated time: their calls have no
    /// wall-clock cap, only their CPU budgets (the module doc of
    /// `sandbox::budget` says why).
    pub fn on_simulated_time(mut self) -> Sandbox {
        self.simulated_time = true;
        self
    }

    /// `limits` as this sandbox applies them.
    fn applied(&self, limits: &GuestLimits) -> GuestLimits {
        GuestLimits { wall_capped: limits.wall_capped && !self.simulated_time, ..*limits }
    }

    /// A sandbox whose engine has no epoch interruption: calls cannot be
    /// stopped, so budgets are not enforced. Only for measuring what the
    /// epoch checks cost (`benches/hop.rs`); never for running components.
    #[doc(hidden)]
    pub fn without_budgets_for_benchmarks(cache_dir: Option<PathBuf>) -> Result<Sandbox, SandboxError> {
        Sandbox::with_epochs(cache_dir, false)
    }

    fn with_epochs(cache_dir: Option<PathBuf>, epochs: bool) -> Result<Sandbox, SandboxError> {
        background_compile_workers();
        let functions = cache_dir.as_ref().and_then(|dir| match FunctionCache::open(dir.join("functions")) {
            Ok(cache) => Some(Arc::new(cache)),
            Err(err) => {
                tracing::warn!("cannot use the function cache in {}: {err}; compiling without it", dir.display());
                None
            }
        });
        let engine_config = |pooling| {
            let mut config = engine_config(pooling, epochs);
            if let Some(functions) = &functions {
                config
                    .enable_incremental_compilation(functions.clone())
                    .map_err(|e| SandboxError::Engine(e.to_string()))?;
            }
            Ok::<Config, SandboxError>(config)
        };
        let (engine, pooling) = match Engine::new(&engine_config(true)?) {
            Ok(engine) => (engine, true),
            Err(err) => {
                tracing::warn!("pooling allocator unavailable ({err}); instances are allocated on demand");
                let engine = Engine::new(&engine_config(false)?).map_err(|e| SandboxError::Engine(e.to_string()))?;
                (engine, false)
            }
        };
        let mut linker = Linker::new(&engine);
        super::wasi::add_to_linker(&mut linker).map_err(|e| SandboxError::Engine(e.to_string()))?;
        bindings::Component::add_to_linker::<GuestState, HasSelf<GuestState>>(&mut linker, |state| state)
            .map_err(|e| SandboxError::Engine(e.to_string()))?;
        v1::bindings::Component::add_to_linker::<GuestState, HasSelf<GuestState>>(&mut linker, |state| state)
            .map_err(|e| SandboxError::Engine(e.to_string()))?;
        let cache = CompileCache::new(&engine, cache_dir, functions);
        let ticker = EpochTicker::start(engine.clone());
        Ok(Sandbox { engine, linker, cache, pooling, simulated_time: false, _ticker: ticker })
    }

    /// What the function cache (cranelift's incremental cache) served since
    /// the process started; `None` without a cache folder.
    pub fn function_cache_stats(&self) -> Option<FunctionCacheStats> {
        self.cache.function_stats()
    }

    /// The folder of the compile cache, if there is one.
    pub fn cache_dir(&self) -> Option<&std::path::Path> {
        self.cache.dir()
    }

    /// Whether instances come from the pooling allocator.
    pub fn is_pooling(&self) -> bool {
        self.pooling
    }

    /// Checks that `bytes` are a component of the `component` world, compiles
    /// them (or loads this host's cached compilation) and asks the component
    /// to describe itself.
    pub fn load(&self, bytes: &[u8]) -> Result<Arc<WasmArtifact>, SandboxError> {
        check_component_header(bytes)?;
        let sha256 = hex::encode(Sha256::digest(bytes));
        let component = self.cache.compile(&self.engine, &sha256, bytes)?;
        let instance_pre = self.linker.instantiate_pre(&component).map_err(|e| SandboxError::World(error_text(&e)))?;
        let pre = match bindings::ComponentPre::new(instance_pre.clone()) {
            Ok(pre) => ComponentPre::V2(pre),
            Err(as_v2) => match v1::bindings::ComponentPre::new(instance_pre) {
                Ok(pre) => ComponentPre::V1(pre),
                // Report against the current contract: that is what a new
                // component is meant to fit.
                Err(_) => return Err(SandboxError::World(error_text(&as_v2))),
            },
        };
        let description = self.describe(&pre)?;
        check_description(&description).map_err(SandboxError::BadDescription)?;
        let contract = match pre {
            ComponentPre::V2(_) => Contract::V0_2,
            ComponentPre::V1(_) => Contract::V0_1,
        };
        Ok(Arc::new(WasmArtifact { sha256, description, contract, pre }))
    }

    /// Checks that `bytes` are a component of the `translator` world and
    /// compiles them (or loads this host's cached compilation).
    pub fn load_translator(&self, bytes: &[u8]) -> Result<Arc<TranslatorArtifact>, SandboxError> {
        check_component_header(bytes)?;
        let sha256 = hex::encode(Sha256::digest(bytes));
        let component = self.cache.compile(&self.engine, &sha256, bytes)?;
        let instance_pre = self.linker.instantiate_pre(&component).map_err(|e| SandboxError::World(error_text(&e)))?;
        let (contract, pre) = match translator_bindings::TranslatorPre::new(instance_pre.clone()) {
            Ok(pre) => (Contract::V0_2, TranslatorPre::V2(pre)),
            Err(as_v2) => match v1::translator_bindings::TranslatorPre::new(instance_pre) {
                Ok(pre) => (Contract::V0_1, TranslatorPre::V1(pre)),
                Err(_) => return Err(SandboxError::TranslatorWorld(error_text(&as_v2))),
            },
        };
        Ok(Arc::new(TranslatorArtifact { sha256, contract, pre }))
    }

    /// A running translator named `name`, initialised with `params`.
    pub fn instantiate_translator(
        &self,
        artifact: &TranslatorArtifact,
        name: &str,
        limits: &GuestLimits,
        params: &[Param],
    ) -> Result<WasmTranslator, SandboxError> {
        let store = self.new_store(format!("{name}/translator").into(), &self.applied(limits), Arc::from([]));
        WasmTranslator::start(store, &artifact.pre, limits.budget, params)
    }

    fn describe(&self, pre: &ComponentPre) -> Result<Description, SandboxError> {
        let limits =
            GuestLimits { memory_bytes: DESCRIBE_MEMORY_BYTES, budget: DESCRIBE_BUDGET, ..GuestLimits::default() };
        let mut store = self.new_store("describe".into(), &limits, Arc::from([]));
        arm(&mut store, DESCRIBE_BUDGET);
        let call = "instantiation for describe()";
        let failed = |e| call_error("describe()", DESCRIBE_BUDGET, &e);
        match pre {
            ComponentPre::V2(pre) => {
                let instance = pre.instantiate(&mut store).map_err(|e| call_error(call, DESCRIBE_BUDGET, &e))?;
                instance.call_describe(&mut store).map_err(failed)
            }
            ComponentPre::V1(pre) => {
                let instance = pre.instantiate(&mut store).map_err(|e| call_error(call, DESCRIBE_BUDGET, &e))?;
                instance.call_describe(&mut store).map(v1::description_from_v1).map_err(failed)
            }
        }
    }

    /// A running instance of `artifact` named `name`, initialised with
    /// `params`, with its own limits.
    pub fn instantiate(
        &self,
        artifact: &WasmArtifact,
        name: &str,
        limits: &GuestLimits,
        params: &[Param],
    ) -> Result<WasmComponent, SandboxError> {
        instantiate_component(&self.engine, artifact, name, &self.applied(limits), params)
    }

    /// Builds fresh instances of `artifact` (its cached, pre-linked form)
    /// for restarts, after this loader is gone.
    pub fn restarter(
        &self,
        artifact: Arc<WasmArtifact>,
        name: &str,
        limits: GuestLimits,
        params: Vec<Param>,
    ) -> crate::runtime::Restarter {
        let engine = self.engine.clone();
        let name = name.to_string();
        let limits = self.applied(&limits);
        Box::new(move || {
            instantiate_component(&engine, &artifact, &name, &limits, &params)
                .map(|c| Box::new(c) as Box<dyn Component>)
                .map_err(|e| crate::runtime::component::RestartError(e.to_string()))
        })
    }

    fn new_store(&self, component: Arc<str>, guest: &GuestLimits, outputs: Arc<[ValueKind]>) -> Store<GuestState> {
        new_store(&self.engine, component, guest, outputs)
    }
}

/// Checks the preamble of `bytes`: a component, not a core module, a
/// precompiled artifact or anything else (`preamble`).
pub fn check_component_header(bytes: &[u8]) -> Result<(), SandboxError> {
    super::preamble::check_component_preamble(bytes).map_err(|why| SandboxError::NotAComponent(why.to_string()))
}

pub(super) fn engine_config(pooling: bool, epochs: bool) -> Config {
    let mut config = Config::new();
    // Measured: with concurrency support on, an empty call costs ~500 ns
    // instead of ~150 ns; the host calls guests synchronously.
    config.concurrency_support(false);
    config.wasm_component_model(true);
    config.epoch_interruption(epochs);
    config.max_wasm_stack(MAX_WASM_STACK_BYTES);
    config.parallel_compilation(true);
    if pooling {
        let mut pool = PoolingAllocationConfig::new();
        pool.total_component_instances(2 * MAX_COMPONENTS as u32 + 16)
            .total_core_instances(POOL_TOTAL_CORE_INSTANCES)
            .total_memories(POOL_TOTAL_CORE_INSTANCES)
            .total_tables(POOL_TOTAL_CORE_INSTANCES)
            .max_core_instances_per_component(MAX_INSTANCES_PER_STORE as u32)
            .max_memories_per_component(MAX_MEMORIES_PER_STORE as u32)
            .max_tables_per_component(MAX_TABLES_PER_STORE as u32)
            .max_memory_size(POOL_MAX_MEMORY_BYTES as usize);
        config.allocation_strategy(InstanceAllocationStrategy::Pooling(pool));
    }
    config
}

/// Makes the worker pool that compiles functions in parallel (rayon's global
/// pool, which wasmtime uses) run at the background priority
/// ([`scheduling::BACKGROUND_NICE`]): a compile must not take the CPU from
/// the control loop. Once per process, before any compile; if the pool was
/// made already (by another user of rayon), it is left as it is, and said.
fn background_compile_workers() {
    static ONCE: std::sync::Once = std::sync::Once::new();
    ONCE.call_once(|| {
        let built = rayon::ThreadPoolBuilder::new()
            .thread_name(|i| format!("compile-pool-{i}"))
            .start_handler(|_| {
                scheduling::lower_to_background();
            })
            .build_global();
        if let Err(err) = built {
            tracing::warn!("compile workers keep their priority: {err}");
        }
    });
}

/// Advances the engine's epoch every [`EPOCH_TICK`] until dropped.
pub(super) struct EpochTicker {
    stop: Arc<AtomicBool>,
    thread: Option<JoinHandle<()>>,
}

impl EpochTicker {
    pub(super) fn start(engine: Engine) -> EpochTicker {
        let stop = Arc::new(AtomicBool::new(false));
        let flag = stop.clone();
        let thread = std::thread::Builder::new()
            .name("subsume-epoch".into())
            .spawn(move || {
                while !flag.load(Ordering::Relaxed) {
                    std::thread::sleep(EPOCH_TICK);
                    engine.increment_epoch();
                }
            })
            .map_err(|err| tracing::error!("cannot start the epoch ticker thread: {err}"))
            .ok();
        EpochTicker { stop, thread }
    }
}

impl Drop for EpochTicker {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_preamble_tells_components_from_other_files() {
        let component = b"\0asm\x0d\x00\x01\x00";
        assert!(check_component_header(component).is_ok());
        let cases: [(&[u8], &str); 4] = [
            (b"\0asm\x01\x00\x00\x00", "core webassembly module"),
            (b"\x7fELF\x02\x01\x01\x00", "precompiled"),
            (b"hello world", "magic bytes"),
            (b"\0asm", "too short"),
        ];
        for (bytes, expected) in cases {
            let err = check_component_header(bytes).err().map(|e| e.to_string()).unwrap_or_default();
            assert!(err.contains(expected), "{err}");
        }
    }
}
