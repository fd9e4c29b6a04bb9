//! What one guest's store holds and may do: its WASI context (stdout and
//! stderr to the log, stdin closed, seeded generators, nothing else), the
//! `subsume:robot/host` functions with their checks (`emit` kinds and caps,
//! `log` rate), its limits (the CPU-time budget of the running call:
//! `budget.rs`), and turning a failed call into a reason a human can act on.

use std::sync::Arc;
use std::time::Duration;

use wasmtime::component::ResourceTable;
use wasmtime::{Engine, Store, StoreLimits, StoreLimitsBuilder, Trap};
use wasmtime_wasi::{WasiCtx, WasiCtxBuilder, WasiCtxView, WasiView};

use rand::SeedableRng as _;
use rand::rngs::StdRng;
use sha2::{Digest, Sha256};

use super::SandboxError;
use super::budget::{self, CallBudget};
use super::guest_output::{GuestOutput, LastWords, LogBudget};
use super::limits::{
    HOSTCALL_FUEL_SLACK, MAX_COMPONENT_HANDLES, MAX_GUEST_MESSAGE_BYTES, MAX_INSTANCES_PER_STORE,
    MAX_MEMORIES_PER_STORE, MAX_RESOURCE_ENTRIES, MAX_TABLES_PER_STORE,
};
use crate::contract::bindings::subsume::robot as wit;
use crate::contract::v1;
use crate::contract::v1::bindings::subsume::robot as old;
use crate::contract::{GuestValue, LogLevel, Value, ValueKind, clip_to, kind_of};
use crate::runtime::Outbox;

/// State of one component's store.
pub struct GuestState {
    pub(super) wasi: WasiCtx,
    pub(super) table: ResourceTable,
    pub(super) limits: StoreLimits,
    pub(super) component: Arc<str>,
    /// Kinds of the declared outputs, by index: checked on every `emit`.
    pub(super) outputs: Arc<[ValueKind]>,
    /// Values emitted during the current call.
    pub(super) outbox: Outbox,
    /// The host clock at the start of the current call (the cycle's time).
    pub(super) now_ns: u64,
    /// The wall clock's anchor: the system's wall time when this instance
    /// first asked, and the cycle's time then. The wall clock a guest reads
    /// is the anchor moved on by the cycle's time since (`wasi.rs`).
    pub(super) wall_anchor: Option<(Duration, u64)>,
    /// The current call's time limits (the epoch callback's state).
    pub(super) call: CallBudget,
    /// Values emitted in the current call, against `max_emits`.
    pub(super) emits: u32,
    pub(super) max_emits: u32,
    pub(super) max_message_bytes: u64,
    /// Log lines per second, shared with stdout and stderr.
    pub(super) logs: LogBudget,
    /// What the current call reported with `host.report` (0.2.0).
    pub(super) reported: Option<String>,
    /// What the guest last wrote to stderr in the current call.
    pub(super) last_words: LastWords,
}

impl WasiView for GuestState {
    fn ctx(&mut self) -> WasiCtxView<'_> {
        WasiCtxView { ctx: &mut self.wasi, table: &mut self.table }
    }
}

impl wit::types::Host for GuestState {}

impl wit::host::Host for GuestState {
    fn emit(&mut self, port: u32, value: GuestValue) -> wasmtime::Result<()> {
        self.take_emit(port, Value::from_guest(value))
    }

    fn log(&mut self, level: LogLevel, message: String) -> wasmtime::Result<()> {
        self.write_log(level, message)
    }

    fn now_ns(&mut self) -> wasmtime::Result<u64> {
        Ok(self.now_ns)
    }

    fn report(&mut self, message: String) -> wasmtime::Result<()> {
        // Bounded like everything else a guest hands the host.
        self.reported = Some(clip_to(&message, MAX_GUEST_MESSAGE_BYTES));
        Ok(())
    }
}

/// The host side of `subsume:robot@0.1.0`: the same functions, on 0.1.0's
/// types.
impl old::types::Host for GuestState {}

impl old::host::Host for GuestState {
    fn emit(&mut self, port: u32, value: old::types::Value) -> wasmtime::Result<()> {
        self.take_emit(port, v1::value_from_v1(value))
    }

    fn log(&mut self, level: old::types::LogLevel, message: String) -> wasmtime::Result<()> {
        self.write_log(v1::log_level_from_v1(level), message)
    }

    fn now_ns(&mut self) -> wasmtime::Result<u64> {
        Ok(self.now_ns)
    }
}

impl GuestState {
    /// Checks an emitted value against the component's caps and declared
    /// outputs, and keeps it for routing; a broken rule traps the guest.
    fn take_emit(&mut self, port: u32, value: Value) -> wasmtime::Result<()> {
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

    fn write_log(&mut self, level: LogLevel, message: String) -> wasmtime::Result<()> {
        self.logs.take().map_err(wasmtime::Error::msg)?;
        let message = clip_to(&message, MAX_GUEST_MESSAGE_BYTES);
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
    /// Whether a call has a wall-clock cap besides its CPU budget
    /// ([`super::budget`]); not on simulated time.
    pub wall_capped: bool,
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
            wall_capped: true,
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
            wall_capped: true,
        }
    }
}

/// The seed of a component's WASI generators: the same for every instance
/// of the same name, so a run replays (a component that wants different
/// numbers per robot takes a seed parameter).
pub fn random_seed(component: &str) -> [u8; 32] {
    let mut hash = Sha256::new();
    hash.update(b"subsume guest random\0");
    hash.update(component.as_bytes());
    hash.finalize().into()
}

/// The size a value takes on the host, for `max-message`.
fn value_bytes(value: &Value) -> u64 {
    match value {
        Value::Flag(_) => 1,
        Value::Scalar(_) => 8,
        Value::Vector(v) => 8 * v.len() as u64,
        Value::Text(t) => t.len() as u64,
        Value::Command(c) => c.text().len() as u64,
        Value::Bytes(b) => b.len() as u64,
        Value::Scan(s) => 32 + 8 * s.ranges.len() as u64,
    }
}

pub(super) fn new_store(
    engine: &Engine,
    component: Arc<str>,
    guest: &GuestLimits,
    outputs: Arc<[ValueKind]>,
) -> Store<GuestState> {
    let logs = LogBudget::new(guest.max_logs_per_s);
    let last_words = LastWords::default();
    let seed = random_seed(&component);
    let mut insecure_seed = seed;
    insecure_seed[0] ^= 0xFF;
    let wasi = WasiCtxBuilder::new()
        .stdin(std::io::empty())
        .stdout(GuestOutput::new(component.clone(), "stdout", logs.clone()))
        .stderr(GuestOutput::new(component.clone(), "stderr", logs.clone()).keeping_last_words(last_words.clone()))
        .secure_random(StdRng::from_seed(seed))
        .insecure_random(StdRng::from_seed(insecure_seed))
        .insecure_random_seed(u128::from_le_bytes(seed[..16].try_into().unwrap_or_default()))
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
        wall_anchor: None,
        call: CallBudget::new(guest.budget, guest.wall_capped),
        emits: 0,
        max_emits: guest.max_emits,
        max_message_bytes: guest.max_message_bytes,
        logs,
        reported: None,
        last_words,
    };
    let mut store = Store::new(engine, state);
    store.limiter(|state| &mut state.limits);
    store.set_hostcall_fuel(usize::try_from(guest.max_message_bytes + HOSTCALL_FUEL_SLACK).unwrap_or(usize::MAX));
    store.set_max_component_handles(MAX_COMPONENT_HANDLES);
    store.epoch_deadline_callback(|mut store| budget::check(&mut store.data_mut().call));
    store
}

/// Prepares `store` for a call under `budget` (CPU time; the wall-clock cap
/// follows from it): the first epoch check comes at the next tick, and the
/// call's wall clock follows from its cycle's time.
pub(super) fn arm(store: &mut Store<GuestState>, budget: Duration) {
    let state = store.data_mut();
    state.call.reset(budget);
    state.last_words.clear();
    store.set_epoch_deadline(1);
}

/// Turns a failed guest call into a reason a human can act on.
pub(super) fn call_error(call: &'static str, budget: Duration, err: &wasmtime::Error) -> SandboxError {
    let reason = match err.downcast_ref::<Trap>() {
        // Budgets end calls with `budget::OverBudget` (its text, below);
        // an interrupt without one is still a budget.
        Some(Trap::Interrupt) => format!("exceeded its time budget of {} ms", budget.as_millis().max(1)),
        Some(Trap::StackOverflow) => "overflowed its stack (recursion too deep?)".to_string(),
        Some(trap) => format!("trapped: {trap}"),
        None if err.downcast_ref::<wasmtime_wasi::I32Exit>().is_some() => {
            let status = err.downcast_ref::<wasmtime_wasi::I32Exit>().map_or(0, |e| e.0);
            format!("called exit (status {status}): a component may not end the process")
        }
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
