//! The component graph and its scheduler (the paper's module runtime).
//!
//! Components (WASM guests and native built-ins alike, behind the
//! [`Component`] trait) are ticked at their rates; every value a component
//! emits is routed, in the same cycle, to the mailboxes of the connected
//! inputs, and each receiving component handles it in `on-input` (input is
//! passive). A mailbox keeps the latest value or a bounded queue whose oldest
//! value is dropped, and counted, when full.
//!
//! Invariants:
//! - time comes in as an argument ([`Graph::step`]): the graph never reads a
//!   clock, so tests drive it with controlled time;
//! - a faulted component is never called again and its pending input is
//!   discarded; the others keep running;
//! - no call into a component happens while a mailbox or route is borrowed.

use std::collections::VecDeque;
use std::sync::Arc;
use std::time::{Duration, Instant};

use super::clock;
use super::component::{CallError, Component, Outbox, RestartError, Restarter, Vacant};
use super::cpu_wait::CpuWait;
use super::histogram::Histogram;
use super::stall::{Activity, Heartbeat};
use super::status::StatusSection;
use super::tap::{Call, Tap};
use super::wiring::{Convert, MAX_RESTART_BACKOFF_NS, Mailbox, Policy, RestartPolicy};
use crate::contract::Value;

/// Most `on-input` deliveries in one cycle. A cycle in the wiring (a -> b ->
/// a) must not keep the control loop in one cycle forever: what is left waits
/// for the next cycle.
pub const MAX_DELIVERIES_PER_CYCLE: usize = 100_000;
/// Least time between two log lines about one component's reported errors:
/// a component failing at 1 kHz must not flood the log.
pub const ERROR_LOG_INTERVAL_NS: u64 = 1_000_000_000;

/// Whether a component still runs.
#[derive(Clone, Debug, PartialEq)]
pub enum ComponentState {
    Running,
    Faulted { reason: String, at_ns: u64 },
}

/// Counters of one component since it started.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ComponentStats {
    /// Calls of `tick` and `on-input`.
    pub calls: u64,
    pub ticks: u64,
    /// Ticks skipped because the loop fell behind the component's rate.
    pub missed_ticks: u64,
    /// Wall time spent in the component's calls, including the host's routing
    /// of what each call emitted.
    pub call_ns: u64,
    /// Values handed to `on-input`.
    pub messages_in: u64,
    /// Values emitted.
    pub messages_out: u64,
    /// Values dropped from full queues feeding this component.
    pub messages_dropped: u64,
    /// `err` results.
    pub errors: u64,
    pub last_error: Option<String>,
    /// Times the component was restarted after a fault.
    pub restarts: u64,
    /// Times it was faulted (trap, budget, stall, broken rule).
    pub faults: u64,
    /// The time of each call, as `call_ns` counts it.
    pub call_times: Histogram,
}

/// Counters of one connection.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ConnectionStats {
    /// Values put into the mailbox.
    pub routed: u64,
    /// Values handed to the receiver.
    pub delivered: u64,
    /// Values dropped because the queue was full.
    pub dropped: u64,
    /// Values overwritten in a latest-value mailbox before delivery.
    pub overwritten: u64,
}

struct Connection {
    from: usize,
    to: usize,
    to_port: u32,
    mailbox: Mailbox,
    stats: ConnectionStats,
    convert: Convert,
}

struct Node {
    name: Arc<str>,
    component: Box<dyn Component>,
    state: ComponentState,
    /// Nanoseconds between ticks; `None` when the component only reacts.
    period_ns: Option<u64>,
    next_tick_ns: u64,
    /// Connections into this component, in the order they were made.
    incoming: Vec<usize>,
    /// Whether the node waits in the delivery queue.
    queued: bool,
    stats: ComponentStats,
    last_error_log_ns: Option<u64>,
    restart: Option<(RestartPolicy, Restarter)>,
    /// When the next restart is due, if one is.
    restart_at_ns: Option<u64>,
}

/// Components, their connections and the scheduler.
pub struct Graph {
    nodes: Vec<Node>,
    connections: Vec<Connection>,
    /// `routes[node][output port]` = connections fed by that output.
    routes: Vec<Vec<Vec<usize>>>,
    /// Nodes with values waiting in a mailbox.
    pending: VecDeque<usize>,
    scratch: Outbox,
    messages_routed: u64,
    messages_dropped: u64,
    cycles: u64,
    /// When the last call (and its routing) ended, within this cycle
    /// (`clock::now_ns`): the start of the next call's time, so a call
    /// costs one clock read.
    mark: Option<u64>,
    /// The stall watchdog's heartbeat, once the loop attached one.
    heartbeat: Option<Arc<Heartbeat>>,
    /// Numbers the heartbeat's words (wraps).
    beats: u32,
    /// How late the loop ran each cycle it had scheduled (`control_loop`).
    lateness: Histogram,
    /// How long the control thread waited for a CPU while running this
    /// graph (`control_loop`).
    cpu_wait: CpuWait,
    /// The observer of every call and emission (a recorder), if any.
    tap: Option<Box<dyn Tap>>,
    /// The time of the cycle (or injection) in progress, for the tap.
    now_ns: u64,
}

impl Drop for Graph {
    /// Components stop in reverse order: a serial link closes before the
    /// simulated robot it talks to.
    fn drop(&mut self) {
        while let Some(node) = self.nodes.pop() {
            drop(node);
        }
    }
}

impl Default for Graph {
    fn default() -> Self {
        Graph::new()
    }
}

impl Graph {
    pub fn new() -> Graph {
        clock::init();
        Graph {
            nodes: Vec::new(),
            connections: Vec::new(),
            routes: Vec::new(),
            pending: VecDeque::new(),
            scratch: Vec::new(),
            messages_routed: 0,
            messages_dropped: 0,
            cycles: 0,
            mark: None,
            heartbeat: None,
            beats: 0,
            lateness: Histogram::default(),
            cpu_wait: CpuWait::default(),
            tap: None,
            now_ns: 0,
        }
    }

    /// Lets `tap` observe every call, emission, fault and restart from now
    /// on (replacing the tap there was, which is returned).
    pub fn set_tap(&mut self, tap: Box<dyn Tap>) -> Option<Box<dyn Tap>> {
        self.tap.replace(tap)
    }

    /// Removes the tap, if there is one (an activation moves it to the next
    /// graph; stopping a recording drops it).
    pub fn take_tap(&mut self) -> Option<Box<dyn Tap>> {
        self.tap.take()
    }

    /// Whether a tap observes this graph.
    pub fn has_tap(&self) -> bool {
        self.tap.is_some()
    }

    /// Publishes this graph's pulse on `heartbeat` (and tells it the
    /// components' names and motor stops) unless it does already. The
    /// control loop calls it every cycle: after an activation swapped the
    /// graph, the new one is attached before its first call.
    pub fn attach(&mut self, heartbeat: &Arc<Heartbeat>) {
        if self.heartbeat.as_ref().is_some_and(|h| Arc::ptr_eq(h, heartbeat)) {
            return;
        }
        self.beats = heartbeat.last_seq();
        self.heartbeat = Some(heartbeat.clone());
        self.publish_components();
    }

    /// Tells the heartbeat the components' names and motor stops.
    fn publish_components(&self) {
        if let Some(heartbeat) = &self.heartbeat {
            let names = self.nodes.iter().map(|n| n.name.clone()).collect();
            let stops = self.nodes.iter().filter_map(|n| n.component.motor_stop()).collect();
            heartbeat.attach(names, stops);
        }
    }

    /// Publishes what the control thread does now; returns the word the
    /// watchdog would declare stalled (0 without a heartbeat).
    #[inline]
    pub(super) fn beat(&mut self, node: Option<usize>, activity: Activity) -> u64 {
        match &self.heartbeat {
            Some(heartbeat) => {
                self.beats = self.beats.wrapping_add(1);
                heartbeat.beat(self.beats, node, activity)
            }
            None => 0,
        }
    }

    /// Tells the stall watchdog that the control thread is about to wait
    /// (for the next tick, or for good): waiting is never a stall.
    pub fn asleep(&mut self) {
        self.beat(None, Activity::Asleep);
    }

    /// Whether the watchdog declared the call published as `word` stalled.
    #[inline]
    fn stalled(&self, word: u64) -> bool {
        word != 0 && self.heartbeat.as_ref().is_some_and(|h| h.stalled(word))
    }

    /// The fault reason of a call that held the loop for `held` (`None`: a
    /// call the graph does not time, held at least the limit).
    fn stall_reason(&self, activity: Activity, held: Option<std::time::Duration>) -> String {
        let limit = self.heartbeat.as_ref().map_or(0, |h| h.limit().as_millis());
        let held = held.map_or_else(|| format!("at least {limit} ms"), |held| format!("{} ms", held.as_millis()));
        format!("{} stalled the control loop: it held it for {held} (the stall limit is {limit} ms)", activity.name())
    }

    /// Adds a component with `outputs` output ports, ticked `rate_hz` times a
    /// second (0: never) from `start_ns` on. Returns its index.
    pub fn add(
        &mut self,
        name: &str,
        component: Box<dyn Component>,
        outputs: usize,
        rate_hz: f64,
        start_ns: u64,
    ) -> usize {
        let period_ns = (rate_hz > 0.0).then(|| ((1e9 / rate_hz).round() as u64).max(1));
        self.nodes.push(Node {
            name: name.into(),
            component,
            state: ComponentState::Running,
            period_ns,
            next_tick_ns: start_ns,
            incoming: Vec::new(),
            queued: false,
            stats: ComponentStats::default(),
            last_error_log_ns: None,
            restart: None,
            restart_at_ns: None,
        });
        self.routes.push(vec![Vec::new(); outputs]);
        self.nodes.len() - 1
    }

    /// The period of component `index`'s ticks (ns); `None` when it only
    /// reacts.
    pub fn period_ns(&self, index: usize) -> Option<u64> {
        self.nodes.get(index).and_then(|n| n.period_ns)
    }

    /// Puts component `index`'s next tick (and the grid after it) `by_ns`
    /// later: a seeded run's tick phase (`sim::perturb`).
    pub fn delay_next_tick(&mut self, index: usize, by_ns: u64) {
        if let Some(node) = self.nodes.get_mut(index) {
            node.next_tick_ns = node.next_tick_ns.saturating_add(by_ns);
        }
    }

    /// Lets component `index` be restarted by `restarter` after a fault,
    /// under `policy`.
    pub fn set_restart(&mut self, index: usize, policy: RestartPolicy, restarter: Restarter) {
        if let Some(node) = self.nodes.get_mut(index) {
            node.restart = Some((policy, restarter));
        }
    }

    /// Connects output `from_port` of `from` to input `to_port` of `to`.
    /// Indices come from a validated config; out-of-range ones are ignored.
    pub fn connect(&mut self, from: usize, from_port: u32, to: usize, to_port: u32, policy: Policy) {
        self.connect_converting(from, from_port, to, to_port, policy, Convert::Nothing);
    }

    /// As `connect`, with `convert` applied to every value on its way (a
    /// scan into a vector input arrives as its ranges).
    pub fn connect_converting(
        &mut self,
        from: usize,
        from_port: u32,
        to: usize,
        to_port: u32,
        policy: Policy,
        convert: Convert,
    ) {
        if to >= self.nodes.len() {
            return;
        }
        let Some(route) = self.routes.get_mut(from).and_then(|r| r.get_mut(from_port as usize)) else {
            return;
        };
        let mailbox = Mailbox::new(policy);
        route.push(self.connections.len());
        self.nodes[to].incoming.push(self.connections.len());
        self.connections.push(Connection { from, to, to_port, mailbox, stats: ConnectionStats::default(), convert });
    }

    /// One cycle at time `now_ns`: ticks every running component that is due,
    /// then delivers every routed value (and what its handling emits).
    pub fn step(&mut self, now_ns: u64) {
        self.now_ns = now_ns;
        self.cycles += 1;
        self.mark = None;
        self.restart_due(now_ns);
        for index in 0..self.nodes.len() {
            let node = &mut self.nodes[index];
            let Some(period) = node.period_ns else {
                continue;
            };
            if node.state != ComponentState::Running || now_ns < node.next_tick_ns {
                continue;
            }
            // Keep the schedule on its grid; skip (and count) missed ticks.
            let behind = (now_ns - node.next_tick_ns) / period;
            node.stats.missed_ticks += behind;
            node.next_tick_ns += (behind + 1) * period;
            node.stats.ticks += 1;
            self.call(index, now_ns, None);
        }
        for index in 0..self.nodes.len() {
            if self.nodes[index].state == ComponentState::Running {
                let word = self.beat(Some(index), Activity::Poll);
                let mut outbox = std::mem::take(&mut self.scratch);
                self.nodes[index].component.poll(now_ns, &mut outbox);
                if self.stalled(word) {
                    outbox.clear();
                    let reason = self.stall_reason(Activity::Poll, None);
                    self.fault(index, reason, now_ns);
                }
                self.route(index, &mut outbox);
                self.scratch = outbox;
            }
        }
        // Polls are not timed: the next call starts its own clock.
        self.mark = None;
        self.deliver(now_ns);
    }

    /// Routes `value` as if component `from` had emitted it on `port`, and
    /// delivers it at once. Lets native sources outside the loop feed the
    /// graph (and benchmarks inject values).
    pub fn inject(&mut self, from: usize, port: u32, value: Value, now_ns: u64) {
        self.now_ns = now_ns;
        self.mark = None;
        self.scratch.push((port, value));
        let mut outbox = std::mem::take(&mut self.scratch);
        self.route(from, &mut outbox);
        self.scratch = outbox;
        self.deliver(now_ns);
    }

    /// When the next cycle is due: the earliest tick of a running component,
    /// an earlier wake a component asked for, or a restart.
    pub fn next_due_ns(&self) -> Option<u64> {
        let running = self.nodes.iter().filter(|n| n.state == ComponentState::Running);
        let ticks = running.clone().filter(|n| n.period_ns.is_some()).map(|n| n.next_tick_ns);
        let wakes = running.filter_map(|n| n.component.next_wake());
        let restarts = self.nodes.iter().filter_map(|n| n.restart_at_ns);
        ticks.chain(wakes).chain(restarts).min()
    }

    /// Whether values wait for delivery (left over by the per-cycle cap).
    pub fn has_pending(&self) -> bool {
        !self.pending.is_empty()
    }

    fn deliver(&mut self, now_ns: u64) {
        let mut budget = MAX_DELIVERIES_PER_CYCLE;
        while let Some(index) = self.pending.pop_front() {
            self.nodes[index].queued = false;
            if self.nodes[index].state != ComponentState::Running {
                continue;
            }
            for slot in 0..self.nodes[index].incoming.len() {
                let connection = self.nodes[index].incoming[slot];
                loop {
                    if self.nodes[index].state != ComponentState::Running {
                        break;
                    }
                    let value = match &mut self.connections[connection].mailbox {
                        Mailbox::Latest(value) => value.take(),
                        Mailbox::Queue { values, .. } => values.pop_front(),
                    };
                    let Some(value) = value else { break };
                    if budget == 0 {
                        // Put it back and finish next cycle.
                        match &mut self.connections[connection].mailbox {
                            Mailbox::Latest(slot) => *slot = Some(value),
                            Mailbox::Queue { values, .. } => values.push_front(value),
                        }
                        self.nodes[index].queued = true;
                        self.pending.push_front(index);
                        return;
                    }
                    budget -= 1;
                    let port = self.connections[connection].to_port;
                    let from = self.connections[connection].from;
                    self.connections[connection].stats.delivered += 1;
                    self.nodes[index].stats.messages_in += 1;
                    self.call(index, now_ns, Some((port, value, from)));
                }
            }
        }
    }

    /// Calls `tick` (no input) or `on-input` on node `index`, then routes
    /// what it emitted or records its failure. The component is charged the
    /// time of its call and of routing what it emitted; when it faulted, not
    /// the time its peers take to hear of it.
    fn call(&mut self, index: usize, now_ns: u64, input: Option<(u32, Value, usize)>) {
        let started = self.mark.take().unwrap_or_else(clock::now_ns);
        let activity = if input.is_some() { Activity::OnInput } else { Activity::Tick };
        let word = self.beat(Some(index), activity);
        if let Some(tap) = &mut self.tap {
            let call = match &input {
                None => Call::Tick,
                Some((port, value, from)) => Call::Input { port: *port, value, from: *from },
            };
            tap.call(index, call, now_ns);
        }
        let mut outbox = std::mem::take(&mut self.scratch);
        let node = &mut self.nodes[index];
        let mut result = match &input {
            None => node.component.tick(now_ns, &mut outbox),
            Some((port, value, from)) => node.component.on_input(*port, value, *from, now_ns, &mut outbox),
        };
        node.stats.calls += 1;
        let stalled = self.stalled(word);
        if stalled {
            // The watchdog stopped the motors past this call: what it
            // emitted is stale, and the component is faulted.
            let held = Duration::from_nanos(clock::now_ns().saturating_sub(started));
            result = Err(CallError::Fault(self.stall_reason(activity, Some(held))));
        }
        let node = &mut self.nodes[index];
        let mut fault_began = None;
        match result {
            Ok(()) => {}
            Err(CallError::Reported(message)) => {
                node.stats.errors += 1;
                let quiet = node.last_error_log_ns.is_some_and(|t| now_ns.saturating_sub(t) < ERROR_LOG_INTERVAL_NS);
                if !quiet {
                    node.last_error_log_ns = Some(now_ns);
                    tracing::warn!(
                        component = &*node.name,
                        "{} returned an error: {message} ({} so far)",
                        activity.name(),
                        node.stats.errors
                    );
                }
                node.stats.last_error = Some(message);
            }
            Err(CallError::Fault(reason)) => {
                outbox.clear();
                // Charged up to here: what follows is the peers' work (each
                // told of the fault) and the recorder's, not this call's.
                fault_began = Some(clock::now_ns());
                self.fault(index, reason, now_ns);
            }
        }
        self.route(index, &mut outbox);
        self.scratch = outbox;
        let ended = clock::now_ns();
        let held_ns = fault_began.unwrap_or(ended).saturating_sub(started);
        let held = Duration::from_nanos(held_ns);
        let stats = &mut self.nodes[index].stats;
        stats.call_ns += held_ns;
        stats.call_times.record(held_ns);
        self.mark = Some(ended);
        // A call that held the loop past the limit is faulted even when the
        // watchdog's verdict came too late for it (or it slept through it).
        if !stalled && self.heartbeat.as_ref().is_some_and(|h| h.after_the_call(held)) {
            let reason = self.stall_reason(activity, Some(held));
            self.fault(index, reason, now_ns);
        }
    }

    /// Restarts the faulted components whose restart is due.
    fn restart_due(&mut self, now_ns: u64) {
        for index in 0..self.nodes.len() {
            let node = &mut self.nodes[index];
            if node.restart_at_ns.is_none_or(|at| at > now_ns) || node.restart.is_none() {
                continue;
            }
            node.restart_at_ns = None;
            node.stats.restarts += 1;
            let attempt = node.stats.restarts;
            let word = self.beat(Some(index), Activity::Restart);
            let started = Instant::now();
            let Some((policy, restarter)) = self.nodes[index].restart.as_mut() else { continue };
            let max_restarts = policy.max_restarts;
            let mut restarted = restarter();
            let held = started.elapsed();
            if self.stalled(word) || self.heartbeat.as_ref().is_some_and(|h| h.after_the_call(held)) {
                restarted = Err(RestartError(self.stall_reason(Activity::Restart, Some(held))));
            }
            let node = &mut self.nodes[index];
            match restarted {
                Ok(component) => {
                    tracing::info!(component = &*node.name, "restarted (restart {attempt} of {max_restarts})");
                    if let Some(tap) = &mut self.tap {
                        tap.restarted(index, attempt, now_ns);
                    }
                    node.component = component;
                    node.state = ComponentState::Running;
                    node.next_tick_ns = now_ns;
                    self.publish_components();
                    for other in 0..self.nodes.len() {
                        if other != index && self.nodes[other].state == ComponentState::Running {
                            self.beat(Some(other), Activity::PeerRestarted);
                            self.nodes[other].component.peer_restarted(index, now_ns);
                        }
                    }
                }
                Err(why) => {
                    tracing::error!(component = &*node.name, "restart {attempt} failed: {why}");
                    Self::schedule_restart(node, now_ns);
                }
            }
        }
    }

    /// Schedules the next restart of `node` if its policy allows one.
    fn schedule_restart(node: &mut Node, now_ns: u64) {
        let Some((policy, _)) = &node.restart else { return };
        if node.stats.restarts >= u64::from(policy.max_restarts) {
            if policy.max_restarts > 0 {
                tracing::error!(
                    component = &*node.name,
                    "no restarts left ({} used): it stays stopped",
                    policy.max_restarts
                );
            }
            return;
        }
        let backoff = policy.backoff_ns.saturating_mul(1 << node.stats.restarts.min(20)).min(MAX_RESTART_BACKOFF_NS);
        node.restart_at_ns = Some(now_ns.saturating_add(backoff));
        tracing::info!(component = &*node.name, "restarting in {:.1} s", backoff as f64 / 1e9);
    }

    /// Stops node `index`: it is not called again (until a restart, if its
    /// policy allows one) and its pending input is discarded. The other
    /// components are told at once (the arbiter stops counting it as a
    /// source) and what they emit is routed.
    pub fn fault(&mut self, index: usize, reason: String, now_ns: u64) {
        self.now_ns = now_ns;
        let Some(node) = self.nodes.get_mut(index) else { return };
        if node.state != ComponentState::Running {
            return;
        }
        tracing::error!(component = &*node.name, "component faulted and is stopped: {reason}; the others keep running");
        if let Some(tap) = &mut self.tap {
            tap.faulted(index, &reason, now_ns);
        }
        node.component.faulted();
        node.stats.faults += 1;
        node.state = ComponentState::Faulted { reason, at_ns: now_ns };
        Self::schedule_restart(node, now_ns);
        for &connection in &node.incoming {
            match &mut self.connections[connection].mailbox {
                Mailbox::Latest(value) => *value = None,
                Mailbox::Queue { values, .. } => values.clear(),
            }
        }
        let mut outbox = Vec::new();
        for other in 0..self.nodes.len() {
            if other != index && self.nodes[other].state == ComponentState::Running {
                self.beat(Some(other), Activity::PeerFaulted);
                self.nodes[other].component.peer_faulted(index, now_ns, &mut outbox);
                self.route(other, &mut outbox);
            }
        }
    }

    fn route(&mut self, from: usize, outbox: &mut Outbox) {
        self.nodes[from].stats.messages_out += outbox.len() as u64;
        if let Some(tap) = &mut self.tap {
            for (port, value) in outbox.iter() {
                tap.emitted(from, *port, value, self.now_ns);
            }
        }
        for (port, value) in outbox.drain(..) {
            let Some(targets) = self.routes[from].get(port as usize) else {
                continue;
            };
            let Some((&last, rest)) = targets.split_last() else {
                continue;
            };
            for &connection in rest {
                Self::put(
                    &mut self.connections[connection],
                    &mut self.nodes,
                    &mut self.pending,
                    &mut self.messages_dropped,
                    value.clone(),
                );
            }
            Self::put(
                &mut self.connections[last],
                &mut self.nodes,
                &mut self.pending,
                &mut self.messages_dropped,
                value,
            );
            self.messages_routed += targets.len() as u64;
        }
    }

    fn put(
        connection: &mut Connection,
        nodes: &mut [Node],
        pending: &mut VecDeque<usize>,
        dropped: &mut u64,
        value: Value,
    ) {
        let target = &mut nodes[connection.to];
        if target.state != ComponentState::Running {
            return;
        }
        let value = connection.convert.apply(value);
        connection.stats.routed += 1;
        match &mut connection.mailbox {
            Mailbox::Latest(slot) => {
                if slot.replace(value).is_some() {
                    connection.stats.overwritten += 1;
                }
            }
            Mailbox::Queue { values, depth } => {
                if values.len() >= *depth {
                    values.pop_front();
                    connection.stats.dropped += 1;
                    target.stats.messages_dropped += 1;
                    *dropped += 1;
                }
                values.push_back(value);
            }
        }
        if !target.queued {
            target.queued = true;
            pending.push_back(connection.to);
        }
    }

    /// Number of components.
    pub fn len(&self) -> usize {
        self.nodes.len()
    }

    pub fn is_empty(&self) -> bool {
        self.nodes.is_empty()
    }

    pub fn name(&self, index: usize) -> Option<&str> {
        self.nodes.get(index).map(|n| &*n.name)
    }

    pub fn state(&self, index: usize) -> Option<&ComponentState> {
        self.nodes.get(index).map(|n| &n.state)
    }

    pub fn stats(&self, index: usize) -> Option<&ComponentStats> {
        self.nodes.get(index).map(|n| &n.stats)
    }

    /// (component name, section) of the components that have a report
    /// section, in graph order.
    pub fn statuses(&self) -> Vec<(&str, Box<dyn StatusSection>)> {
        self.nodes.iter().filter_map(|n| n.component.status().map(|status| (&*n.name, status))).collect()
    }

    /// Component `index`'s (name, section), if it has a report section.
    pub fn component_status(&self, index: usize) -> Option<(&str, Box<dyn StatusSection>)> {
        let node = self.nodes.get(index)?;
        node.component.status().map(|status| (&*node.name, status))
    }

    /// Calls component `index` as a cycle would (`tick` without `input`,
    /// else `on-input`) at `now_ns`, routing and tapping what it emits:
    /// replay feeds a component its recorded calls one by one. A component
    /// that is not running is not called.
    pub fn drive(&mut self, index: usize, input: Option<(u32, Value, usize)>, now_ns: u64) {
        self.now_ns = now_ns;
        self.mark = None;
        let Some(node) = self.nodes.get_mut(index) else { return };
        if node.state != ComponentState::Running {
            return;
        }
        match input {
            None => node.stats.ticks += 1,
            Some(_) => node.stats.messages_in += 1,
        }
        self.call(index, now_ns, input);
    }

    /// Counters of connection `index` (in the order connections were made).
    pub fn connection_stats(&self, index: usize) -> Option<&ConnectionStats> {
        self.connections.get(index).map(|c| &c.stats)
    }

    /// Values put into mailboxes since the start.
    pub fn messages_routed(&self) -> u64 {
        self.messages_routed
    }

    /// Values dropped from full queues since the start.
    pub fn messages_dropped(&self) -> u64 {
        self.messages_dropped
    }

    /// How late the loop ran the cycles it had scheduled.
    pub fn lateness(&self) -> &Histogram {
        &self.lateness
    }

    /// Counts one scheduled cycle that ran `late_ns` after its time
    /// (called by the control loop).
    pub fn record_lateness(&mut self, late_ns: u64) {
        self.lateness.record(late_ns);
    }

    /// How long the control thread waited for a CPU while running this graph.
    pub fn cpu_wait(&self) -> &CpuWait {
        &self.cpu_wait
    }

    /// A reading of the control thread's run delay (`control_loop`).
    pub fn note_cpu_wait(&mut self, reading_ns: u64) {
        self.cpu_wait.note(reading_ns);
    }

    /// Cycles run since the start.
    pub fn cycles(&self) -> u64 {
        self.cycles
    }

    /// Moves component `index` out, leaving a component that does nothing
    /// in its place (activation carries built-ins that own a device or a
    /// socket into the next graph).
    pub fn take_component(&mut self, index: usize) -> Option<Box<dyn Component>> {
        let node = self.nodes.get_mut(index)?;
        Some(std::mem::replace(&mut node.component, Box::new(Vacant)))
    }

    /// Puts `component` in place of component `index`'s.
    pub fn replace_component(&mut self, index: usize, component: Box<dyn Component>) {
        if let Some(node) = self.nodes.get_mut(index) {
            node.component = component;
        }
        self.publish_components();
    }
}
