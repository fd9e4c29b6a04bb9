//! A running WASM component: its store, its instance and the calls the
//! graph makes into it, each under an epoch deadline.

use std::sync::Arc;
use std::time::Duration;

use wasmtime::{Engine, Store};

use super::SandboxError;
use super::engine::{INIT_BUDGET, WasmArtifact};
use super::guest::{GuestLimits, GuestState, MAX_GUEST_MESSAGE_BYTES, budget_ticks, call_error, new_store, truncate};
use crate::contract::bindings;
use crate::contract::{Param, Value, ValueKind};
use crate::runtime::{CallError, Component, Outbox};

/// A running, initialised instance of `artifact` in a new store of `engine`.
pub(super) fn instantiate_component(
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
