//! A running WASM component: its store, its instance and the calls the
//! graph makes into it, each under its CPU-time budget (`budget.rs`).

use std::sync::Arc;
use std::time::Duration;

use wasmtime::{Engine, Store};

use super::SandboxError;
use super::artifact::{ComponentPre, WasmArtifact};
use super::guest::{GuestLimits, GuestState, arm, call_error, new_store};
use super::limits::{INIT_BUDGET, MAX_GUEST_MESSAGE_BYTES};
use crate::contract::{GuestValue, Param, Value, ValueKind, clip_to};
use crate::contract::{bindings, v1};
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
    let inputs: Arc<[ValueKind]> = artifact.description.inputs.iter().map(|p| p.kind).collect();
    let mut store = new_store(engine, name.into(), limits, outputs);
    arm(&mut store, INIT_BUDGET);
    let instantiation = |e| call_error("instantiation", INIT_BUDGET, &e);
    let (instance, init) = match &artifact.pre {
        ComponentPre::V2(pre) => {
            let instance = pre.instantiate(&mut store).map_err(instantiation)?;
            let init = instance.call_init(&mut store, params);
            (Instance::V2(instance), init)
        }
        ComponentPre::V1(pre) => {
            let instance = pre.instantiate(&mut store).map_err(instantiation)?;
            let init = instance.call_init(&mut store, &v1::params_to_v1(params));
            (Instance::V1(instance), init)
        }
    };
    match init {
        Ok(Ok(())) => {}
        Ok(Err(message)) => {
            return Err(SandboxError::Call { call: "init()", reason: clip_to(&message, MAX_GUEST_MESSAGE_BYTES) });
        }
        Err(e) => return Err(call_error("init()", INIT_BUDGET, &e)),
    }
    // Values emitted (or errors reported) during init are dropped: nothing
    // is wired yet.
    store.data_mut().outbox.clear();
    store.data_mut().reported = None;
    Ok(WasmComponent { store, instance, inputs, budget })
}

/// An instance of the world its component was built against.
enum Instance {
    V2(bindings::Component),
    V1(v1::bindings::Component),
}

/// A running WASM component: its store and instance.
pub struct WasmComponent {
    store: Store<GuestState>,
    instance: Instance,
    /// Kinds of the declared inputs, by index: a scan reaches a `vector`
    /// input as its ranges.
    inputs: Arc<[ValueKind]>,
    budget: Duration,
}

impl WasmComponent {
    /// Prepares the store for a call at `now_ns`.
    fn begin(&mut self, now_ns: u64) {
        let state = self.store.data_mut();
        state.now_ns = now_ns;
        state.emits = 0;
        state.reported = None;
        arm(&mut self.store, self.budget);
    }

    /// Routes what the call emitted, or faults it; an error the component
    /// reported (an `err` result in 0.1.0, `report` in 0.2.0) is returned
    /// as [`CallError::Reported`] after routing.
    fn finish(
        &mut self,
        call: &'static str,
        result: wasmtime::Result<Result<(), String>>,
        out: &mut Outbox,
    ) -> Result<(), CallError> {
        match result {
            Ok(result) => {
                let state = self.store.data_mut();
                out.append(&mut state.outbox);
                let reported = result.err().or_else(|| state.reported.take());
                match reported {
                    Some(message) => Err(CallError::Reported(clip_to(&message, MAX_GUEST_MESSAGE_BYTES))),
                    None => Ok(()),
                }
            }
            Err(err) => {
                // The call did not complete: what it emitted is not routed.
                self.store.data_mut().outbox.clear();
                let mut reason = match call_error(call, self.budget, &err) {
                    SandboxError::Call { reason, .. } => format!("{call}: {reason}"),
                    other => other.to_string(),
                };
                // A trap after the guest explained itself on stderr (a Rust
                // panic, a Python exception, a JavaScript error): say what
                // it said, not only `unreachable`.
                if err.downcast_ref::<wasmtime::Trap>().is_some()
                    && let Some(words) = self.store.data().last_words.take()
                {
                    reason = format!("{reason} (the component said: {words})");
                }
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
        self.begin(now_ns);
        let result = match &self.instance {
            Instance::V2(instance) => match value {
                Value::Scan(scan) if self.inputs.get(port as usize) == Some(&ValueKind::Vector) => {
                    instance.call_on_input(&mut self.store, port, &GuestValue::Vector(scan.ranges.clone())).map(Ok)
                }
                _ => instance.call_on_input(&mut self.store, port, &value.to_guest()).map(Ok),
            },
            Instance::V1(instance) => instance.call_on_input(&mut self.store, port, &v1::value_to_v1(value)),
        };
        self.finish("on-input", result, out)
    }

    fn tick(&mut self, now_ns: u64, out: &mut Outbox) -> Result<(), CallError> {
        self.begin(now_ns);
        let result = match &self.instance {
            Instance::V2(instance) => instance.call_tick(&mut self.store, now_ns).map(Ok),
            Instance::V1(instance) => instance.call_tick(&mut self.store, now_ns),
        };
        self.finish("tick", result, out)
    }
}
