//! What the graph tells an observer outside the control loop (a recorder):
//! the [`Tap`] trait. The graph calls it after each call it makes, with
//! indices and borrowed values only; an implementation must not block (a
//! recorder hands events to its writer thread through a bounded channel and
//! counts what did not fit).
//!
//! Order: the graph tells the tap of a call ([`Tap::call`]) before it makes
//! it and of everything the call emitted ([`Tap::emitted`]) right after it
//! returns, before it makes any other call; a component emits outside its
//! calls only from `poll`, `peer_faulted` or an injection (built-ins, never
//! a WASM component). Replay relies on it: a recorded output belongs to its
//! component's last call before it.

use crate::contract::Value;

/// One call the graph made into a component, as a tap sees it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Call<'a> {
    /// `tick(now)`.
    Tick,
    /// `on-input(port, value)` with a value sent by component `from`.
    Input { port: u32, value: &'a Value, from: usize },
}

/// An observer of the graph (the recorder). Every method runs on the
/// control thread, between component calls: it must return at once.
pub trait Tap: Send {
    /// Component `index` is about to be called at `now_ns` (its inputs and
    /// the ticks it gets, in the order the graph makes them: what replay
    /// feeds it again).
    fn call(&mut self, index: usize, call: Call<'_>, now_ns: u64);
    /// Component `from` emitted `value` on output `port` at `now_ns`.
    fn emitted(&mut self, from: usize, port: u32, value: &Value, now_ns: u64);
    /// Component `index` was faulted for `reason`.
    fn faulted(&mut self, index: usize, reason: &str, now_ns: u64);
    /// Component `index` was restarted after a fault (`attempt` counts from 1).
    fn restarted(&mut self, index: usize, attempt: u64, now_ns: u64);
}
