//! The WebAssembly sandbox: the one wasmtime [`Engine`] of the process, the
//! linker that offers guests the `subsume:robot/host` interface and a minimal
//! WASI (no preopened directories, no sockets, no environment, no arguments;
//! stdout and stderr go to the log), a [`Store`] per component with memory
//! limits, an epoch deadline before every call, and an on-disk cache of
//! compiled components.
//!
//! Invariants:
//! - bytes that came from outside are only ever compiled (`Component::new`),
//!   never deserialized; only artifacts this host wrote to its own cache
//!   directory, named by the sha256 of their source, are deserialized;
//! - every call into a guest runs under an epoch deadline;
//! - a guest that traps, overruns its budget or breaks a host rule is
//!   reported as [`CallError::Fault`] and its store is never called again.

mod guest_output;

use std::hash::{Hash, Hasher};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::thread::JoinHandle;
use std::time::Duration;

use sha2::{Digest, Sha256};
use thiserror::Error;
use wasmtime::component::{HasSelf, Linker, ResourceTable};
use wasmtime::{
    Config, Engine, InstanceAllocationStrategy, PoolingAllocationConfig, Store, StoreLimits, StoreLimitsBuilder, Trap,
};
use wasmtime_wasi::{WasiCtx, WasiCtxBuilder, WasiCtxView, WasiView};

pub use guest_output::{GuestOutput, MAX_GUEST_LINE_BYTES};

use crate::config::limits::MAX_COMPONENTS;
use crate::contract::bindings::subsume::robot::types::Feedback as WitFeedback;
use crate::contract::bindings::{self, subsume::robot as wit};
use crate::contract::translator_bindings;
use crate::contract::{Description, LogLevel, Param, Value, ValueKind, check_description, kind_of};
use crate::fsutil::write_atomically;
use crate::robot::control::ControlCommand;
use crate::robot::protocol::Feedback;
use crate::robot::translator::{TranslateError, Translator};
use crate::runtime::{CallError, Component, Outbox};

/// How often the ticker thread advances the engine's epoch. A call is stopped
/// between its budget and its budget plus one tick after it starts (plus the
/// ticker thread's wake-up latency).
pub const EPOCH_TICK: Duration = Duration::from_millis(1);
/// Budget of `describe`: a component that loops there must not hang loading.
pub const DESCRIBE_BUDGET: Duration = Duration::from_millis(500);
/// Budget of instantiation plus `init`: a component that loops while
/// starting must not hang startup or activation.
pub const INIT_BUDGET: Duration = Duration::from_secs(1);
/// Memory given to the throwaway instance that answers `describe`.
pub const DESCRIBE_MEMORY_BYTES: u64 = 64 << 20;
/// Native stack a guest may use; deep recursion traps instead of crashing
/// the host.
pub const MAX_WASM_STACK_BYTES: usize = 512 << 10;
/// Core instances one component may create (componentize-py components
/// create about 38): bounds what one component takes from the pool.
pub const MAX_INSTANCES_PER_STORE: usize = 64;
/// Tables and memories one component may create.
pub const MAX_TABLES_PER_STORE: usize = 64;
pub const MAX_MEMORIES_PER_STORE: usize = 64;
/// Largest linear memory the instance pool reserves a slot for; per-component
/// limits from the robot file are at most this.
pub const POOL_MAX_MEMORY_BYTES: u64 = 1 << 30;
/// Core instances (and memories) the whole pool holds: enough for
/// [`MAX_COMPONENTS`] components plus throwaway `describe` instances.
pub const POOL_TOTAL_CORE_INSTANCES: u32 = 1000;
/// Entries a guest may hold in its WASI resource table (open streams,
/// pollables): a guest must not grow host-side tables without bound.
pub const MAX_RESOURCE_ENTRIES: usize = 1000;
/// Component-model handles alive at once in one store (`resource.new`).
pub const MAX_COMPONENT_HANDLES: usize = 1000;
/// Hostcall fuel beyond the component's `max-message`: room for the other
/// arguments of a host call.
pub const HOSTCALL_FUEL_SLACK: u64 = 64 << 10;
/// Longest message from a guest's `log` or `err` result kept in the log.
pub const MAX_GUEST_MESSAGE_BYTES: usize = 1024;

#[derive(Debug, Error)]
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

/// State of one component's store.
pub struct GuestState {
    wasi: WasiCtx,
    table: ResourceTable,
    limits: StoreLimits,
    component: Arc<str>,
    /// Kinds of the declared outputs, by index: checked on every `emit`.
    outputs: Arc<[ValueKind]>,
    /// Values emitted during the current call.
    outbox: Outbox,
    /// The host clock at the start of the current call.
    now_ns: u64,
    /// Values emitted in the current call, against `max_emits`.
    emits: u32,
    max_emits: u32,
    max_message_bytes: u64,
    /// Log lines per second, shared with stdout and stderr.
    logs: LogBudget,
}

impl WasiView for GuestState {
    fn ctx(&mut self) -> WasiCtxView<'_> {
        WasiCtxView { ctx: &mut self.wasi, table: &mut self.table }
    }
}

impl wit::types::Host for GuestState {}

impl wit::host::Host for GuestState {
    fn emit(&mut self, port: u32, value: Value) -> wasmtime::Result<()> {
        self.emits += 1;
        if self.emits > self.max_emits {
            return Err(wasmtime::format_err!("emitted more than {} values in one call (max-emits)", self.max_emits));
        }
        let size = value_bytes(&value);
        if size > self.max_message_bytes {
            return Err(wasmtime::format_err!(
                "emitted a value of {size} bytes; at most {} are allowed (max-message)",
                self.max_message_bytes
            ));
        }
        let Some(kind) = self.outputs.get(port as usize) else {
            return Err(wasmtime::format_err!(
                "emitted on output port {port}, but the component declares {} output(s)",
                self.outputs.len()
            ));
        };
        if !kind.accepts(&value) {
            return Err(wasmtime::format_err!(
                "emitted a {} value on output port {port}, which carries {kind}",
                kind_of(&value)
            ));
        }
        self.outbox.push((port, value));
        Ok(())
    }

    fn log(&mut self, level: LogLevel, message: String) -> wasmtime::Result<()> {
        self.logs.take().map_err(wasmtime::Error::msg)?;
        let message = truncate(message, MAX_GUEST_MESSAGE_BYTES);
        let component = &*self.component;
        match level {
            LogLevel::Trace => tracing::trace!(component, "{message}"),
            LogLevel::Debug => tracing::debug!(component, "{message}"),
            LogLevel::Info => tracing::info!(component, "{message}"),
            LogLevel::Warn => tracing::warn!(component, "{message}"),
            LogLevel::Error => tracing::error!(component, "{message}"),
        }
        Ok(())
    }

    fn now_ns(&mut self) -> wasmtime::Result<u64> {
        Ok(self.now_ns)
    }
}

/// What one guest may use and push at the host; from its robot-file
/// settings (`memory`, `budget`, `max-emits`, `max-message`, `max-logs`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GuestLimits {
    pub memory_bytes: u64,
    pub budget: Duration,
    pub max_emits: u32,
    pub max_message_bytes: u64,
    pub max_logs_per_s: u32,
}

impl Default for GuestLimits {
    fn default() -> Self {
        use crate::config::limits;
        GuestLimits {
            memory_bytes: limits::DEFAULT_MEMORY_BYTES,
            budget: limits::DEFAULT_CALL_BUDGET,
            max_emits: limits::DEFAULT_EMITS_PER_CALL,
            max_message_bytes: limits::DEFAULT_MESSAGE_BYTES,
            max_logs_per_s: limits::DEFAULT_LOG_LINES_PER_S,
        }
    }
}

impl GuestLimits {
    /// The limits a component's configuration sets.
    pub fn of(config: &crate::config::ComponentConfig) -> GuestLimits {
        GuestLimits {
            memory_bytes: config.memory_bytes,
            budget: config.budget,
            max_emits: config.max_emits,
            max_message_bytes: config.max_message_bytes,
            max_logs_per_s: config.max_logs_per_s,
        }
    }
}

/// A guest's log lines this second, shared by `log`, stdout and stderr.
#[derive(Clone, Debug)]
pub struct LogBudget {
    max_per_s: u32,
    window: Arc<std::sync::Mutex<(std::time::Instant, u32)>>,
}

impl LogBudget {
    pub fn new(max_per_s: u32) -> LogBudget {
        LogBudget { max_per_s, window: Arc::new(std::sync::Mutex::new((std::time::Instant::now(), 0))) }
    }

    /// Counts one line; `Err` when the guest is over its rate.
    pub fn take(&self) -> Result<(), String> {
        let Ok(mut window) = self.window.lock() else { return Ok(()) };
        if window.0.elapsed() >= Duration::from_secs(1) {
            *window = (std::time::Instant::now(), 0);
        }
        window.1 += 1;
        if window.1 > self.max_per_s {
            return Err(format!("wrote more than {} log lines in one second (max-logs)", self.max_per_s));
        }
        Ok(())
    }
}

/// The size a value takes on the host, for `max-message`.
fn value_bytes(value: &Value) -> u64 {
    match value {
        Value::Flag(_) => 1,
        Value::Scalar(_) => 8,
        Value::Vector(v) => 8 * v.len() as u64,
        Value::Text(t) | Value::Command(t) => t.len() as u64,
        Value::Bytes(b) => b.len() as u64,
    }
}

/// A compiled, linked component and what it says about itself.
pub struct WasmArtifact {
    /// Hex sha256 of the `.wasm` bytes.
    pub sha256: String,
    pub description: Description,
    pre: bindings::ComponentPre<GuestState>,
}

impl std::fmt::Debug for WasmArtifact {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("WasmArtifact").field("sha256", &self.sha256).field("name", &self.description.name).finish()
    }
}

/// A compiled, linked translator component.
pub struct TranslatorArtifact {
    pub sha256: String,
    pre: translator_bindings::TranslatorPre<GuestState>,
}

impl std::fmt::Debug for TranslatorArtifact {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("TranslatorArtifact").field("sha256", &self.sha256).finish()
    }
}

/// The per-process engine, linker, epoch ticker and compile cache.
pub struct Sandbox {
    engine: Engine,
    linker: Linker<GuestState>,
    cache_dir: Option<PathBuf>,
    engine_key: String,
    pooling: bool,
    _ticker: EpochTicker,
}

impl std::fmt::Debug for Sandbox {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Sandbox").field("cache_dir", &self.cache_dir).field("pooling", &self.pooling).finish()
    }
}

impl Sandbox {
    /// Starts the engine and its epoch ticker. Compiled components are cached
    /// in `cache_dir` when given.
    pub fn new(cache_dir: Option<PathBuf>) -> Result<Sandbox, SandboxError> {
        Sandbox::with_epochs(cache_dir, true)
    }

    /// A sandbox whose engine has no epoch interruption: calls cannot be
    /// stopped, so budgets are not enforced. Only for measuring what the
    /// epoch checks cost (`benches/hop.rs`); never for running components.
    #[doc(hidden)]
    pub fn without_budgets_for_benchmarks(cache_dir: Option<PathBuf>) -> Result<Sandbox, SandboxError> {
        Sandbox::with_epochs(cache_dir, false)
    }

    fn with_epochs(cache_dir: Option<PathBuf>, epochs: bool) -> Result<Sandbox, SandboxError> {
        let (engine, pooling) = match Engine::new(&engine_config(true, epochs)) {
            Ok(engine) => (engine, true),
            Err(err) => {
                tracing::warn!("pooling allocator unavailable ({err}); instances are allocated on demand");
                let engine =
                    Engine::new(&engine_config(false, epochs)).map_err(|e| SandboxError::Engine(e.to_string()))?;
                (engine, false)
            }
        };
        let mut linker = Linker::new(&engine);
        wasmtime_wasi::p2::add_to_linker_sync(&mut linker).map_err(|e| SandboxError::Engine(e.to_string()))?;
        bindings::Component::add_to_linker::<GuestState, HasSelf<GuestState>>(&mut linker, |state| state)
            .map_err(|e| SandboxError::Engine(e.to_string()))?;
        let mut hasher = std::collections::hash_map::DefaultHasher::new();
        engine.precompile_compatibility_hash().hash(&mut hasher);
        let engine_key = format!("{:016x}", hasher.finish());
        let cache_dir = cache_dir.filter(|dir| match create_private_dir(dir) {
            Ok(()) => true,
            Err(err) => {
                tracing::warn!("cannot use cache directory {}: {err}; compiling without a cache", dir.display());
                false
            }
        });
        let ticker = EpochTicker::start(engine.clone());
        Ok(Sandbox { engine, linker, cache_dir, engine_key, pooling, _ticker: ticker })
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
        let component = self.compile_cached(&sha256, bytes)?;
        let instance_pre = self.linker.instantiate_pre(&component).map_err(|e| SandboxError::World(error_text(&e)))?;
        let pre = bindings::ComponentPre::new(instance_pre).map_err(|e| SandboxError::World(error_text(&e)))?;
        let description = self.describe(&pre)?;
        check_description(&description).map_err(SandboxError::BadDescription)?;
        Ok(Arc::new(WasmArtifact { sha256, description, pre }))
    }

    /// Checks that `bytes` are a component of the `translator` world and
    /// compiles them (or loads this host's cached compilation).
    pub fn load_translator(&self, bytes: &[u8]) -> Result<Arc<TranslatorArtifact>, SandboxError> {
        check_component_header(bytes)?;
        let sha256 = hex::encode(Sha256::digest(bytes));
        let component = self.compile_cached(&sha256, bytes)?;
        let instance_pre = self.linker.instantiate_pre(&component).map_err(|e| SandboxError::World(error_text(&e)))?;
        let pre = translator_bindings::TranslatorPre::new(instance_pre)
            .map_err(|e| SandboxError::TranslatorWorld(error_text(&e)))?;
        Ok(Arc::new(TranslatorArtifact { sha256, pre }))
    }

    /// A running translator named `name`, initialised with `params`.
    pub fn instantiate_translator(
        &self,
        artifact: &TranslatorArtifact,
        name: &str,
        limits: &GuestLimits,
        params: &[Param],
    ) -> Result<WasmTranslator, SandboxError> {
        let budget = limits.budget;
        let mut store = self.new_store(format!("{name}/translator").into(), limits, Arc::from([]));
        store.set_epoch_deadline(budget_ticks(INIT_BUDGET));
        let instance =
            artifact.pre.instantiate(&mut store).map_err(|e| call_error("instantiation", INIT_BUDGET, &e))?;
        match instance.call_init(&mut store, params) {
            Ok(Ok(())) => {}
            Ok(Err(message)) => {
                return Err(SandboxError::Call { call: "init()", reason: truncate(message, MAX_GUEST_MESSAGE_BYTES) });
            }
            Err(e) => return Err(call_error("init()", INIT_BUDGET, &e)),
        }
        Ok(WasmTranslator { store, instance, budget, budget_ticks: budget_ticks(budget), malformed: 0, broken: None })
    }

    fn describe(&self, pre: &bindings::ComponentPre<GuestState>) -> Result<Description, SandboxError> {
        let limits =
            GuestLimits { memory_bytes: DESCRIBE_MEMORY_BYTES, budget: DESCRIBE_BUDGET, ..GuestLimits::default() };
        let mut store = self.new_store("describe".into(), &limits, Arc::from([]));
        store.set_epoch_deadline(budget_ticks(DESCRIBE_BUDGET));
        let call = "instantiation for describe()";
        let instance = pre.instantiate(&mut store).map_err(|e| call_error(call, DESCRIBE_BUDGET, &e))?;
        instance.call_describe(&mut store).map_err(|e| call_error("describe()", DESCRIBE_BUDGET, &e))
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
        instantiate_component(&self.engine, artifact, name, limits, params)
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
        Box::new(move || {
            instantiate_component(&engine, &artifact, &name, &limits, &params)
                .map(|c| Box::new(c) as Box<dyn Component>)
                .map_err(|e| e.to_string())
        })
    }

    fn new_store(&self, component: Arc<str>, guest: &GuestLimits, outputs: Arc<[ValueKind]>) -> Store<GuestState> {
        new_store(&self.engine, component, guest, outputs)
    }

    fn compile_cached(&self, sha256: &str, bytes: &[u8]) -> Result<wasmtime::component::Component, SandboxError> {
        let cached = self.cache_dir.as_ref().map(|dir| dir.join(format!("{sha256}-{}.cwasm", self.engine_key)));
        if let Some(path) = cached.as_ref().filter(|p| p.is_file()) {
            // SAFETY: the file is in this host's private cache directory and
            // was written by `compile_cached` below from `Component::serialize`
            // of a component whose source hashes to `sha256`, by an engine
            // with the same compatibility hash. User bytes never land here
            // without being compiled first.
            match unsafe { wasmtime::component::Component::deserialize_file(&self.engine, path) } {
                Ok(component) => return Ok(component),
                Err(err) => {
                    tracing::warn!("ignoring unusable cache entry {}: {err}", path.display())
                }
            }
        }
        let component = wasmtime::component::Component::new(&self.engine, bytes)
            .map_err(|e| SandboxError::Compile(error_text(&e)))?;
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

/// A running, initialised instance of `artifact` in a new store of `engine`.
fn instantiate_component(
    engine: &Engine,
    artifact: &WasmArtifact,
    name: &str,
    limits: &GuestLimits,
    params: &[Param],
) -> Result<WasmComponent, SandboxError> {
    let budget = limits.budget;
    let outputs: Arc<[ValueKind]> = artifact.description.outputs.iter().map(|p| p.kind).collect();
    let mut store = new_store(engine, name.into(), limits, outputs);
    store.set_epoch_deadline(budget_ticks(INIT_BUDGET));
    let instance = artifact.pre.instantiate(&mut store).map_err(|e| call_error("instantiation", INIT_BUDGET, &e))?;
    match instance.call_init(&mut store, params) {
        Ok(Ok(())) => {}
        Ok(Err(message)) => {
            return Err(SandboxError::Call { call: "init()", reason: truncate(message, MAX_GUEST_MESSAGE_BYTES) });
        }
        Err(e) => return Err(call_error("init()", INIT_BUDGET, &e)),
    }
    // Values emitted during init are dropped: nothing is wired yet.
    store.data_mut().outbox.clear();
    Ok(WasmComponent { store, instance, budget, budget_ticks: budget_ticks(budget) })
}

fn new_store(
    engine: &Engine,
    component: Arc<str>,
    guest: &GuestLimits,
    outputs: Arc<[ValueKind]>,
) -> Store<GuestState> {
    let logs = LogBudget::new(guest.max_logs_per_s);
    let wasi = WasiCtxBuilder::new()
        .stdout(GuestOutput::new(component.clone(), "stdout", logs.clone()))
        .stderr(GuestOutput::new(component.clone(), "stderr", logs.clone()))
        .allow_tcp(false)
        .allow_udp(false)
        .allow_ip_name_lookup(false)
        .build();
    let limits = StoreLimitsBuilder::new()
        .memory_size(usize::try_from(guest.memory_bytes).unwrap_or(usize::MAX))
        .instances(MAX_INSTANCES_PER_STORE)
        .tables(MAX_TABLES_PER_STORE)
        .memories(MAX_MEMORIES_PER_STORE)
        .trap_on_grow_failure(true)
        .build();
    let mut table = ResourceTable::new();
    table.set_max_capacity(MAX_RESOURCE_ENTRIES);
    let state = GuestState {
        wasi,
        table,
        limits,
        component,
        outputs,
        outbox: Vec::new(),
        now_ns: 0,
        emits: 0,
        max_emits: guest.max_emits,
        max_message_bytes: guest.max_message_bytes,
        logs,
    };
    let mut store = Store::new(engine, state);
    store.limiter(|state| &mut state.limits);
    store.set_hostcall_fuel(usize::try_from(guest.max_message_bytes + HOSTCALL_FUEL_SLACK).unwrap_or(usize::MAX));
    store.set_max_component_handles(MAX_COMPONENT_HANDLES);
    store
}

/// A running WASM component: its store and instance.
pub struct WasmComponent {
    store: Store<GuestState>,
    instance: bindings::Component,
    budget: Duration,
    budget_ticks: u64,
}

impl WasmComponent {
    fn finish(
        &mut self,
        call: &'static str,
        result: wasmtime::Result<Result<(), String>>,
        out: &mut Outbox,
    ) -> Result<(), CallError> {
        match result {
            Ok(result) => {
                out.append(&mut self.store.data_mut().outbox);
                result.map_err(|message| CallError::Reported(truncate(message, MAX_GUEST_MESSAGE_BYTES)))
            }
            Err(err) => {
                // The call did not complete: what it emitted is not routed.
                self.store.data_mut().outbox.clear();
                let reason = match call_error(call, self.budget, &err) {
                    SandboxError::Call { reason, .. } => format!("{call}: {reason}"),
                    other => other.to_string(),
                };
                Err(CallError::Fault(reason))
            }
        }
    }
}

impl Component for WasmComponent {
    fn on_input(
        &mut self,
        port: u32,
        value: &Value,
        _from: usize,
        now_ns: u64,
        out: &mut Outbox,
    ) -> Result<(), CallError> {
        let state = self.store.data_mut();
        state.now_ns = now_ns;
        state.emits = 0;
        self.store.set_epoch_deadline(self.budget_ticks);
        let result = self.instance.call_on_input(&mut self.store, port, value);
        self.finish("on-input", result, out)
    }

    fn tick(&mut self, now_ns: u64, out: &mut Outbox) -> Result<(), CallError> {
        let state = self.store.data_mut();
        state.now_ns = now_ns;
        state.emits = 0;
        self.store.set_epoch_deadline(self.budget_ticks);
        let result = self.instance.call_tick(&mut self.store, now_ns);
        self.finish("tick", result, out)
    }
}

/// Most bytes one `encode` may return: a motor frame is a few dozen bytes.
pub const MAX_TRANSLATED_FRAME_BYTES: usize = 1024;
/// Most feedback messages one `decode` may return.
pub const MAX_FEEDBACK_PER_DECODE: usize = 1024;

/// A running WASM translator (the `translator` world).
pub struct WasmTranslator {
    store: Store<GuestState>,
    instance: translator_bindings::Translator,
    budget: Duration,
    budget_ticks: u64,
    malformed: u64,
    /// Why it broke, once it has: it is never called again.
    broken: Option<String>,
}

impl WasmTranslator {
    fn check(&self) -> Result<(), String> {
        self.broken.clone().map_or(Ok(()), Err)
    }

    fn break_with(&mut self, call: &'static str, err: &wasmtime::Error) -> String {
        let reason = match call_error(call, self.budget, err) {
            SandboxError::Call { reason, .. } => format!("{call}: {reason}"),
            other => other.to_string(),
        };
        self.broken = Some(reason.clone());
        reason
    }
}

impl Translator for WasmTranslator {
    fn encode(&mut self, command: &ControlCommand, out: &mut Vec<u8>) -> Result<(), TranslateError> {
        self.check().map_err(TranslateError::Fault)?;
        self.store.set_epoch_deadline(self.budget_ticks);
        match self.instance.call_encode(&mut self.store, &command.to_string()) {
            Ok(Ok(bytes)) if bytes.len() <= MAX_TRANSLATED_FRAME_BYTES => {
                out.extend_from_slice(&bytes);
                Ok(())
            }
            Ok(Ok(bytes)) => {
                let reason =
                    format!("encode: returned {} bytes; at most {MAX_TRANSLATED_FRAME_BYTES} are allowed", bytes.len());
                self.broken = Some(reason.clone());
                Err(TranslateError::Fault(reason))
            }
            Ok(Err(message)) => Err(TranslateError::Refused(truncate(message, MAX_GUEST_MESSAGE_BYTES))),
            Err(err) => Err(TranslateError::Fault(self.break_with("encode", &err))),
        }
    }

    fn decode(&mut self, bytes: &[u8], out: &mut Vec<Feedback>) -> Result<(), String> {
        self.check()?;
        self.store.set_epoch_deadline(self.budget_ticks);
        let decoded = match self.instance.call_decode(&mut self.store, bytes) {
            Ok(decoded) => decoded,
            Err(err) => return Err(self.break_with("decode", &err)),
        };
        if decoded.feedback.len() > MAX_FEEDBACK_PER_DECODE {
            let reason = format!(
                "decode: returned {} messages; at most {MAX_FEEDBACK_PER_DECODE} are allowed",
                decoded.feedback.len()
            );
            self.broken = Some(reason.clone());
            return Err(reason);
        }
        self.malformed += u64::from(decoded.malformed);
        out.extend(decoded.feedback.into_iter().map(|f| match f {
            WitFeedback::Odometry(p) => Feedback::Odometry { x: p.x, y: p.y, heading: p.heading },
            WitFeedback::Ranges(r) => Feedback::Ranges(r),
            WitFeedback::Bumper(b) => Feedback::Bumper(b),
            WitFeedback::Battery(v) => Feedback::Battery(v),
        }));
        Ok(())
    }

    fn malformed(&self) -> u64 {
        self.malformed
    }
}

/// Checks the preamble of `bytes`: a component, not a core module, a
/// precompiled artifact or anything else (`crate::preamble`).
pub fn check_component_header(bytes: &[u8]) -> Result<(), SandboxError> {
    crate::preamble::check_component_preamble(bytes).map_err(|why| SandboxError::NotAComponent(why.to_string()))
}

fn engine_config(pooling: bool, epochs: bool) -> Config {
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

/// Epoch ticks for `budget`: one extra because the current tick may end at
/// once, so the guest always gets at least its whole budget.
fn budget_ticks(budget: Duration) -> u64 {
    let tick = EPOCH_TICK.as_nanos().max(1);
    (budget.as_nanos().div_ceil(tick) as u64).saturating_add(1)
}

/// Turns a failed guest call into a reason a human can act on.
fn call_error(call: &'static str, budget: Duration, err: &wasmtime::Error) -> SandboxError {
    let reason = match err.downcast_ref::<Trap>() {
        Some(Trap::Interrupt) => format!("exceeded its time budget of {} ms", budget.as_millis().max(1)),
        Some(Trap::StackOverflow) => "overflowed its stack (recursion too deep?)".to_string(),
        Some(trap) => format!("trapped: {trap}"),
        None => {
            let cause = err.root_cause().to_string();
            // StoreLimits (trap_on_grow_failure) says this when a memory or
            // table would outgrow the component's limit.
            match cause.strip_prefix("forcing trap when growing memory to ") {
                Some(size) => format!("exceeded its memory limit (growing memory to {size})"),
                // The hostcall fuel is the component's max-message.
                None if cause.contains("fuel allocated for hostcalls has been exhausted") => {
                    "passed more data to the host in one call than its max-message allows".to_string()
                }
                None => cause,
            }
        }
    };
    SandboxError::Call { call, reason }
}

fn error_text(err: &wasmtime::Error) -> String {
    let mut text = err.to_string();
    let cause = err.root_cause().to_string();
    if cause != text {
        text = format!("{text}: {cause}");
    }
    text
}

fn truncate(mut text: String, max: usize) -> String {
    if text.len() > max {
        let mut end = max;
        while !text.is_char_boundary(end) {
            end -= 1;
        }
        text.truncate(end);
        text.push_str("...");
    }
    clip_control(text)
}

/// Replaces control characters so guest text cannot forge log lines.
fn clip_control(text: String) -> String {
    if text.chars().any(char::is_control) {
        text.chars().map(|c| if c.is_control() { ' ' } else { c }).collect()
    } else {
        text
    }
}

fn create_private_dir(dir: &Path) -> std::io::Result<()> {
    use std::os::unix::fs::DirBuilderExt;
    std::fs::DirBuilder::new().recursive(true).mode(0o700).create(dir)
}

/// Advances the engine's epoch every [`EPOCH_TICK`] until dropped.
struct EpochTicker {
    stop: Arc<AtomicBool>,
    thread: Option<JoinHandle<()>>,
}

impl EpochTicker {
    fn start(engine: Engine) -> EpochTicker {
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

    #[test]
    fn a_budget_always_gets_at_least_its_time() {
        assert_eq!(budget_ticks(Duration::from_millis(10)), 11);
        assert_eq!(budget_ticks(Duration::from_micros(1500)), 3);
    }

    #[test]
    fn guest_text_is_cut_and_cleaned() {
        assert_eq!(truncate("abcdef".into(), 3), "abc...");
        assert_eq!(truncate("a\nb".into(), 10), "a b");
        assert_eq!(truncate("ééé".into(), 3), "é...");
    }
}
