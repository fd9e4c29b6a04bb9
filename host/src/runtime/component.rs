//! What the scheduler calls: the [`Component`] trait (the paper's
//! `Module`), implemented alike by WASM guests and native built-ins, the
//! values a call emits ([`Outbox`]) and why a call failed ([`CallError`]).

use std::sync::Arc;

use super::stall::MotorStop;
use crate::contract::Value;

/// Values a component emitted during one call: (output port index, value).
pub type Outbox = Vec<(u32, Value)>;

/// Why a call into a component did not succeed.
#[derive(Clone, Debug, PartialEq)]
pub enum CallError {
    /// The component returned `err`: logged and counted, it keeps running.
    Reported(String),
    /// The component trapped, overran its budget or broke a host rule: it is
    /// stopped for good.
    Fault(String),
}

/// What the scheduler calls: the paper's `Module`. WASM components and
/// native built-ins implement it alike.
pub trait Component: Send {
    /// A new value arrived on input `port`, sent by component `from` (its
    /// index in the graph). Emitted values go to `out`. Components without
    /// inputs are never called here; the default ignores the value.
    fn on_input(
        &mut self,
        port: u32,
        value: &Value,
        from: usize,
        now_ns: u64,
        out: &mut Outbox,
    ) -> Result<(), CallError> {
        let _ = (port, value, from, now_ns, out);
        Ok(())
    }
    /// The component's periodic call. Emitted values go to `out`. The
    /// default does nothing (components that only react to input).
    fn tick(&mut self, now_ns: u64, out: &mut Outbox) -> Result<(), CallError> {
        let _ = (now_ns, out);
        Ok(())
    }
    /// Called on every cycle (before delivery), for components fed from
    /// outside the graph (the network platform). Emitted values are routed.
    fn poll(&mut self, now_ns: u64, out: &mut Outbox) {
        let _ = (now_ns, out);
    }
    /// When the component next needs a cycle besides its ticks (a command
    /// due for release), on the graph's clock.
    fn next_wake(&self) -> Option<u64> {
        None
    }
    /// Component `component` has just faulted. Native components that track
    /// others (the arbiter) react here; emitted values are routed.
    fn peer_faulted(&mut self, component: usize, now_ns: u64, out: &mut Outbox) {
        let _ = (component, now_ns, out);
    }
    /// This component has just faulted and will not be called again (until
    /// a restart brings a fresh instance). A component that drives hardware
    /// leaves it safe here (the serial link sends its final STOP).
    fn faulted(&mut self) {}
    /// The handle that stops this component's motors from any thread,
    /// without the control loop (the stall watchdog uses it). Only
    /// components that own a motor device have one.
    fn motor_stop(&self) -> Option<Arc<dyn MotorStop>> {
        None
    }
    /// Component `component` has been restarted after a fault.
    fn peer_restarted(&mut self, component: usize, now_ns: u64) {
        let _ = (component, now_ns);
    }
    /// Its section of the run report and the live status.
    fn status(&self) -> Option<Box<dyn super::StatusSection>> {
        None
    }
}

/// Builds a fresh instance of a component (from its cached, pre-linked form).
pub type Restarter = Box<dyn FnMut() -> Result<Box<dyn Component>, RestartError> + Send>;

/// Why a restart did not bring a component back.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[error("{0}")]
pub struct RestartError(pub String);

/// A component that does nothing: it stands where one was moved out (an
/// activation carries it on), or ends a chain (benchmarks).
pub struct Vacant;

impl Component for Vacant {}
