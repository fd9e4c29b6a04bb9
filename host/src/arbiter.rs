//! Subsumption (Brooks): every source of motion commands has a priority and a
//! timeout; a source is active while its last command is younger than its
//! timeout; the highest-priority active source wins and suppresses the rest;
//! when none is active, the motors get an explicit STOP.
//!
//! Ties: among active sources of the same (top) priority, a source that
//! answers to a person (the network platform, `builtin:teleop`) wins over
//! autonomous ones: an operator who asked for direct control (priority 1,
//! like the planner) drives, rather than being silently ignored. Otherwise
//! the current holder keeps control; if it is not among them, the source
//! listed first in the robot file wins. A faulted source stops counting at
//! once.
//!
//! Every decision also updates each source's [`Standing`] (holds,
//! suppressed by whom, idle) in the host's [`Standings`] when it changed, so
//! the network platform can tell its operator.
//!
//! [`Arbiter`] is the decision logic, driven with explicit time; the
//! `builtin:arbiter` component ([`ArbiterComponent`]) wires it into the graph:
//! every connection into its `commands` input is a source, with the sending
//! component's priority and timeout. [`ArbiterBuiltin`] declares it.

use serde::Serialize;

use crate::builtin::{self, BuildContext, Builtin, BuiltinError, ParamDecl, Params, Ports};
use crate::config::ComponentSource;
use crate::contract::{Value, ValueKind};
use crate::robot::control::{self, ControlCommand};
use crate::runtime::{CallError, Component, Outbox, PriorityCell, Standing, Standings};

/// The built-in kind whose sources answer to a person (they win ties).
const OPERATOR_KIND: &str = "teleop";

/// Most sources one arbiter may have.
pub const MAX_SOURCES: usize = 64;

/// One source of motion commands.
#[derive(Clone, Debug, PartialEq)]
pub struct Source {
    /// The sending component's index in the graph.
    pub component: usize,
    pub name: String,
    pub priority: PriorityCell,
    /// How long after its last command the source stays active.
    pub timeout_ns: u64,
    /// The source answers to a person (a remote operator): it wins ties
    /// against sources that do not.
    pub operator: bool,
}

#[derive(Clone, Debug)]
struct SourceState {
    source: Source,
    last: Option<(ControlCommand, u64)>,
    faulted: bool,
    held_ns: u64,
}

/// Who holds control and what goes to the motors.
#[derive(Clone, Debug, PartialEq)]
pub struct Decision {
    /// Index of the winning source, `None` when no source is active.
    pub holder: Option<usize>,
    /// The command for the motors: the holder's latest, or STOP.
    pub command: ControlCommand,
}

/// What the rest of the host sees of the arbiter.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct ArbiterStatus {
    /// The source holding control, if any.
    pub holder: Option<String>,
    /// Active sources suppressed by the holder.
    pub suppressed: Vec<String>,
    /// Changes of holder (including to and from "none").
    pub switches: u64,
    /// STOP commands sent because no source was active.
    pub stops_sent: u64,
    /// Seconds each source held control.
    pub held_s: Vec<(String, f64)>,
    /// Commands that were not valid control strings.
    pub rejected: u64,
}

/// The subsumption decision, with explicit time.
#[derive(Clone, Debug)]
pub struct Arbiter {
    sources: Vec<SourceState>,
    holder: Option<usize>,
    decided_at: Option<u64>,
    switches: u64,
    stops_sent: u64,
    rejected: u64,
}

impl Arbiter {
    /// An arbiter over `sources`, in robot-file order (the tie-break order).
    pub fn new(sources: Vec<Source>) -> Arbiter {
        let sources =
            sources.into_iter().map(|source| SourceState { source, last: None, faulted: false, held_ns: 0 }).collect();
        Arbiter { sources, holder: None, decided_at: None, switches: 0, stops_sent: 0, rejected: 0 }
    }

    /// Records `command` from the source whose component is `component`.
    /// Returns false when `component` is not a source or has faulted.
    pub fn offer(&mut self, component: usize, command: ControlCommand, now_ns: u64) -> bool {
        match self.sources.iter_mut().find(|s| s.source.component == component) {
            Some(state) if !state.faulted => {
                state.last = Some((command, now_ns));
                true
            }
            _ => false,
        }
    }

    /// Counts a command that was not a valid control string.
    pub fn reject(&mut self) {
        self.rejected += 1;
    }

    /// Counts the source of `component` again (it was restarted).
    pub fn restore(&mut self, component: usize) {
        for state in self.sources.iter_mut().filter(|s| s.source.component == component) {
            state.faulted = false;
        }
    }

    /// Stops counting the source of `component`, at once.
    pub fn fault(&mut self, component: usize) {
        for state in self.sources.iter_mut().filter(|s| s.source.component == component) {
            state.faulted = true;
            state.last = None;
        }
    }

    fn is_active(state: &SourceState, now_ns: u64) -> bool {
        !state.faulted && state.last.is_some_and(|(_, at)| now_ns.saturating_sub(at) <= state.source.timeout_ns)
    }

    /// Decides at `now_ns`; counts switches, held time and stops.
    pub fn decide(&mut self, now_ns: u64) -> Decision {
        if let (Some(holder), Some(at)) = (self.holder, self.decided_at) {
            self.sources[holder].held_ns += now_ns.saturating_sub(at);
        }
        self.decided_at = Some(now_ns);
        let top = self.sources.iter().filter(|s| Self::is_active(s, now_ns)).map(|s| s.source.priority.get()).max();
        let winner = top.and_then(|top| {
            let tied =
                |i: &usize| Self::is_active(&self.sources[*i], now_ns) && self.sources[*i].source.priority.get() == top;
            let operator_tied = (0..self.sources.len()).any(|i| tied(&i) && self.sources[i].source.operator);
            let candidate = |i: &usize| tied(i) && (!operator_tied || self.sources[*i].source.operator);
            self.holder.filter(candidate).or_else(|| (0..self.sources.len()).find(candidate))
        });
        if winner != self.holder {
            self.switches += 1;
            self.holder = winner;
        }
        let command = match winner.and_then(|w| self.sources[w].last) {
            Some((command, _)) => command,
            None => {
                self.stops_sent += 1;
                ControlCommand::Stop
            }
        };
        Decision { holder: winner, command }
    }

    /// The source at `index`.
    pub fn source(&self, index: usize) -> Option<&Source> {
        self.sources.get(index).map(|s| &s.source)
    }

    /// Active sources other than the holder, at `now_ns`.
    pub fn suppressed(&self, now_ns: u64) -> Vec<usize> {
        (0..self.sources.len())
            .filter(|&i| Some(i) != self.holder && Self::is_active(&self.sources[i], now_ns))
            .collect()
    }

    /// How source `index` stands after the last decision, at `now_ns`.
    pub fn standing(&self, index: usize, now_ns: u64) -> Standing {
        match (self.holder, self.sources.get(index)) {
            (_, None) => Standing::Idle,
            (Some(holder), _) if holder == index => Standing::Holds,
            (Some(holder), Some(state)) if Self::is_active(state, now_ns) => Standing::Suppressed {
                by: self.sources[holder].source.name.clone(),
                priority: self.sources[holder].source.priority.get(),
            },
            _ => Standing::Idle,
        }
    }

    /// The number of sources.
    pub fn len(&self) -> usize {
        self.sources.len()
    }

    /// Whether there are no sources.
    pub fn is_empty(&self) -> bool {
        self.sources.is_empty()
    }

    pub fn status(&self, now_ns: u64) -> ArbiterStatus {
        ArbiterStatus {
            holder: self.holder.map(|h| self.sources[h].source.name.clone()),
            suppressed: self.suppressed(now_ns).into_iter().map(|i| self.sources[i].source.name.clone()).collect(),
            switches: self.switches,
            stops_sent: self.stops_sent,
            held_s: self.sources.iter().map(|s| (s.source.name.clone(), s.held_ns as f64 / 1e9)).collect(),
            rejected: self.rejected,
        }
    }
}

/// The `builtin:arbiter` component: input `commands` (one connection per
/// source), output `cmd` (the winner's command, or STOP). It re-decides on
/// every command and every tick, emits at once when the output changes and
/// on every tick otherwise (so the serial link's watchdog stays fed).
pub struct ArbiterComponent {
    name: String,
    arbiter: Arbiter,
    last_sent: Option<(Option<usize>, ControlCommand)>,
    now_ns: u64,
    standings: Standings,
    /// Each source's standing as last written to `standings`.
    published: Vec<Standing>,
}

impl ArbiterComponent {
    pub fn new(name: &str, sources: Vec<Source>) -> ArbiterComponent {
        ArbiterComponent::with_standings(name, sources, Standings::default())
    }

    /// An arbiter that writes its sources' standings to `standings`.
    pub fn with_standings(name: &str, sources: Vec<Source>, standings: Standings) -> ArbiterComponent {
        let published = vec![Standing::Idle; sources.len()];
        ArbiterComponent {
            name: name.to_string(),
            arbiter: Arbiter::new(sources),
            last_sent: None,
            now_ns: 0,
            standings,
            published,
        }
    }

    /// Writes the standings that changed since the last decision. Most
    /// decisions change none: one comparison per source, no allocation.
    fn publish_standings(&mut self, now_ns: u64) {
        for index in 0..self.arbiter.len() {
            let unchanged = match (&self.published[index], self.arbiter.holder, self.arbiter.sources.get(index)) {
                (Standing::Holds, Some(holder), _) => holder == index,
                (Standing::Idle, holder, Some(state)) => holder != Some(index) && !Arbiter::is_active(state, now_ns),
                (Standing::Suppressed { by, priority }, Some(holder), Some(state)) => {
                    holder != index
                        && Arbiter::is_active(state, now_ns)
                        && self.arbiter.sources[holder].source.name == *by
                        && self.arbiter.sources[holder].source.priority.get() == *priority
                }
                _ => false,
            };
            if !unchanged {
                let standing = self.arbiter.standing(index, now_ns);
                if let Some(source) = self.arbiter.source(index) {
                    self.standings.set(&source.name, standing.clone());
                }
                self.published[index] = standing;
            }
        }
    }

    fn decide_and_emit(&mut self, now_ns: u64, always: bool, out: &mut Outbox) {
        self.now_ns = now_ns;
        let decision = self.arbiter.decide(now_ns);
        self.publish_standings(now_ns);
        let previous_holder = self.last_sent.map(|(h, _)| h);
        if previous_holder != Some(decision.holder) {
            self.log_change(decision.holder, now_ns);
        }
        let output = (decision.holder, decision.command);
        if always || self.last_sent != Some(output) {
            out.push((0, Value::Command(decision.command.to_string())));
        }
        self.last_sent = Some(output);
    }

    fn log_change(&self, holder: Option<usize>, now_ns: u64) {
        let label = |i: usize| {
            self.arbiter.source(i).map(|s| format!("{} (priority {})", s.name, s.priority.get())).unwrap_or_default()
        };
        let suppressed: Vec<String> = self.arbiter.suppressed(now_ns).into_iter().map(label).collect();
        match holder {
            None => tracing::info!(component = %self.name, "no source is active: STOP"),
            Some(h) if suppressed.is_empty() => tracing::info!(component = %self.name, "{} holds control", label(h)),
            Some(h) => tracing::info!(component = %self.name, "{} suppresses {}", label(h), suppressed.join(", ")),
        }
    }
}

impl Component for ArbiterComponent {
    fn on_input(
        &mut self,
        _port: u32,
        value: &Value,
        from: usize,
        now_ns: u64,
        out: &mut Outbox,
    ) -> Result<(), CallError> {
        let Value::Command(text) = value else {
            self.arbiter.reject();
            return Err(CallError::Reported("commands: expected a control string".into()));
        };
        match control::parse(text) {
            Ok(command) => {
                if self.arbiter.offer(from, command, now_ns) {
                    self.decide_and_emit(now_ns, false, out);
                }
                Ok(())
            }
            Err(err) => {
                self.arbiter.reject();
                Err(CallError::Reported(format!("ignored an invalid control string: {err}")))
            }
        }
    }

    fn tick(&mut self, now_ns: u64, out: &mut Outbox) -> Result<(), CallError> {
        self.decide_and_emit(now_ns, true, out);
        Ok(())
    }

    fn peer_faulted(&mut self, component: usize, now_ns: u64, out: &mut Outbox) {
        self.arbiter.fault(component);
        self.decide_and_emit(now_ns, false, out);
    }

    fn peer_restarted(&mut self, component: usize, _now_ns: u64) {
        self.arbiter.restore(component);
    }

    fn status(&self) -> Option<(&'static str, serde_json::Value)> {
        serde_json::to_value(self.arbiter.status(self.now_ns)).ok().map(|v| ("arbiter", v))
    }
}

/// The `arbiter` kind: no parameters; its sources are the connections
/// into `commands`.
pub struct ArbiterBuiltin;

impl Builtin for ArbiterBuiltin {
    fn kind(&self) -> &'static str {
        "arbiter"
    }

    fn summary(&self) -> &'static str {
        "Subsumption: the highest-priority active source drives; none active: STOP"
    }

    fn params(&self) -> &'static [ParamDecl] {
        &[]
    }

    fn ports(&self, _params: &Params) -> Ports {
        Ports {
            inputs: vec![builtin::port(
                "commands",
                ValueKind::Command,
                "control strings; every connection is a source with its sender's priority",
            )],
            outputs: vec![builtin::port("cmd", ValueKind::Command, "the winning command, or STOP")],
        }
    }

    fn build(&self, _params: &Params, ctx: &mut BuildContext<'_>) -> Result<Box<dyn Component>, BuiltinError> {
        let mut sources: Vec<Source> = Vec::new();
        for connection in ctx.robot.connections.iter().filter(|c| c.to.component == ctx.index) {
            let Some(from) = ctx.robot.components.get(connection.from.component) else { continue };
            if sources.iter().any(|s| s.component == connection.from.component) {
                continue;
            }
            if from.priority.is_none() {
                return Err(BuiltinError::Refused(format!("source '{}' has no priority", from.name)));
            }
            let priority = ctx.priorities.get(connection.from.component).cloned().unwrap_or_default();
            sources.push(Source {
                component: connection.from.component,
                name: from.name.clone(),
                priority,
                timeout_ns: from.timeout.as_nanos() as u64,
                operator: from.source == ComponentSource::Builtin(OPERATOR_KIND.into()),
            });
        }
        if sources.len() > MAX_SOURCES {
            return Err(BuiltinError::Refused(format!("{} sources; at most {MAX_SOURCES} are allowed", sources.len())));
        }
        let name = &ctx.component()?.name;
        let listed: Vec<String> =
            sources.iter().map(|s| format!("{} (priority {})", s.name, s.priority.get())).collect();
        tracing::info!(
            component = %name,
            "motion sources: {}",
            if listed.is_empty() { "none".into() } else { listed.join(", ") }
        );
        let standings = ctx.services.get::<Standings>().map(|s| (*s).clone()).unwrap_or_default();
        Ok(Box::new(ArbiterComponent::with_standings(name, sources, standings)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const MS: u64 = 1_000_000;

    fn source(component: usize, name: &str, priority: i32) -> Source {
        Source {
            component,
            name: name.into(),
            priority: PriorityCell::new(priority),
            timeout_ns: 500 * MS,
            operator: false,
        }
    }

    fn vel(v: f64) -> ControlCommand {
        ControlCommand::Vel { linear: v, angular: 0.0 }
    }

    /// A table of (time ms, event) and the holder expected after it.
    enum Event {
        Offer(usize, f64),
        Fault(usize),
        Decide,
    }

    #[test]
    fn decisions_follow_priority_timeout_ties_and_faults() {
        use Event::*;
        // Sources 0: avoid (component 10, priority 3), 1: planner (20, 1),
        // 2: tracker (30, 1); every timeout is 500 ms.
        let sources = vec![source(10, "avoid", 3), source(20, "planner", 1), source(30, "tracker", 1)];
        let mut arbiter = Arbiter::new(sources);
        let stop = ControlCommand::Stop;
        #[rustfmt::skip]
        let table: Vec<(u64, Event, Option<usize>, ControlCommand)> = vec![
            (0,   Decide,         None,    stop),      // nobody active: explicit STOP
            (10,  Offer(20, 0.2), Some(1), vel(0.2)),  // the planner drives
            (20,  Offer(30, 0.3), Some(1), vel(0.2)),  // tie at priority 1: the holder keeps it
            (30,  Offer(10, 0.0), Some(0), vel(0.0)),  // avoid (3) suppresses both
            (400, Offer(20, 0.25), Some(0), vel(0.0)), // the planner stays suppressed
            (530, Decide,         Some(0), vel(0.0)),  // avoid is active up to 30 + 500 ms
            (531, Decide,         Some(1), vel(0.25)), // avoid timed out; tracker (20 ms) too
            (600, Offer(10, 0.1), Some(0), vel(0.1)),  // avoid is back
            (610, Fault(10),      Some(1), vel(0.25)), // avoid faults: out at once
            (650, Offer(10, 0.5), Some(1), vel(0.25)), // a faulted source is ignored
            (901, Decide,         None,    stop),      // the planner (400 ms) timed out
        ];
        for (ms, event, holder, command) in table {
            let now = ms * MS;
            match event {
                Offer(component, v) => {
                    arbiter.offer(component, vel(v), now);
                }
                Fault(component) => arbiter.fault(component),
                Decide => {}
            }
            let decision = arbiter.decide(now);
            assert_eq!((decision.holder, decision.command), (holder, command), "at {ms} ms");
        }
        let status = arbiter.status(901 * MS);
        assert_eq!(status.holder, None);
        assert_eq!(status.stops_sent, 2);
        assert_eq!(status.switches, 6);
        let held: Vec<f64> = status.held_s.iter().map(|(_, s)| (s * 1000.0).round()).collect();
        // avoid 30..531 and 600..610; planner 10..30, 531..600 and 610..901.
        assert_eq!(held, vec![511.0, 380.0, 0.0]);
    }

    #[test]
    fn a_restarted_source_counts_again() {
        let mut arbiter = Arbiter::new(vec![source(1, "a", 3), source(2, "b", 1)]);
        arbiter.offer(1, vel(0.1), 0);
        arbiter.offer(2, vel(0.2), 0);
        arbiter.fault(1);
        assert_eq!(arbiter.decide(0).holder, Some(1));
        assert!(!arbiter.offer(1, vel(0.1), MS), "a faulted source is ignored");
        arbiter.restore(1);
        assert!(arbiter.offer(1, vel(0.1), 2 * MS));
        assert_eq!(arbiter.decide(2 * MS).holder, Some(0));
    }

    #[test]
    fn a_tie_without_the_holder_goes_to_the_first_listed_source() {
        let mut arbiter = Arbiter::new(vec![source(1, "a", 1), source(2, "b", 1)]);
        arbiter.offer(2, vel(0.2), 0);
        arbiter.offer(1, vel(0.1), 0);
        assert_eq!(arbiter.decide(0).holder, Some(0));
    }

    #[test]
    fn the_component_logs_nothing_twice_and_emits_on_change_and_on_tick() {
        let mut component = ArbiterComponent::new("arbiter", vec![source(10, "avoid", 3), source(20, "planner", 1)]);
        let mut out = Vec::new();
        component.on_input(0, &Value::Command("VEL 0.2 0".into()), 20, 0, &mut out).ok();
        component.on_input(0, &Value::Command("VEL 0.2 0".into()), 20, MS, &mut out).ok();
        assert_eq!(out, vec![(0, Value::Command("VEL 0.2 0.0".into()))], "unchanged output is not re-sent on input");
        component.tick(2 * MS, &mut out).ok();
        assert_eq!(out.len(), 2, "a tick always re-sends");
        let err = component.on_input(0, &Value::Command("FLY".into()), 20, 3 * MS, &mut out);
        assert!(matches!(err, Err(CallError::Reported(m)) if m.contains("column 1")));
        component.peer_faulted(20, 4 * MS, &mut out);
        assert_eq!(out.last(), Some(&(0, Value::Command("STOP".into()))));
    }

    fn operator(component: usize, name: &str, priority: i32) -> Source {
        Source { operator: true, ..source(component, name, priority) }
    }

    /// (time ms, a component's offer, the operator's new priority, the
    /// holder expected).
    type Step = (u64, Option<(usize, f64)>, Option<i32>, Option<usize>);

    #[test]
    fn an_operator_wins_a_tie_against_autonomous_sources_but_not_a_higher_priority() {
        // 0: planner (10, priority 1), 1: operator (20, 1 in direct mode),
        // 2: avoid (30, 3).
        let op = operator(20, "net", 1);
        let cell = op.priority.clone();
        let mut arbiter = Arbiter::new(vec![source(10, "planner", 1), op, source(30, "avoid", 3)]);
        #[rustfmt::skip]
        let table: Vec<Step> = vec![
            (0,   Some((10, 0.2)), None,    Some(0)), // the planner drives alone
            (10,  Some((20, 0.5)), None,    Some(1)), // direct (1) = planner (1): the operator takes it at once
            (20,  Some((10, 0.2)), None,    Some(1)), // the planner does not take it back
            (30,  Some((30, 0.0)), None,    Some(2)), // avoid (3) outranks every mode
            (40,  None,            Some(2), Some(2)), // shared (2): still below avoid
            (590, Some((10, 0.2)), Some(0), Some(0)), // avoid and the operator timed out: the planner
            (600, Some((20, 0.5)), None,    Some(0)), // supervisory (0) loses to the planner
            (610, Some((20, 0.5)), Some(1), Some(1)), // back to direct: the operator again
        ];
        for (ms, offer, priority, holder) in table {
            let now = ms * MS;
            if let Some(p) = priority {
                cell.set(p);
            }
            if let Some((component, v)) = offer {
                arbiter.offer(component, vel(v), now);
            }
            assert_eq!(arbiter.decide(now).holder, holder, "at {ms} ms");
        }
    }

    #[test]
    fn standings_are_written_when_they_change_and_name_the_holder() {
        let standings = Standings::default();
        let sources = vec![source(10, "planner", 1), operator(20, "net", 0)];
        let mut component = ArbiterComponent::with_standings("arbiter", sources, standings.clone());
        let mut out = Vec::new();
        let command = Value::Command("VEL 0.2 0".into());
        assert_eq!(standings.get("net"), Standing::Idle);
        component.on_input(0, &command, 10, 0, &mut out).ok();
        assert_eq!(standings.get("planner"), Standing::Holds);
        assert_eq!(standings.get("net"), Standing::Idle, "a silent source is idle, not suppressed");
        component.on_input(0, &command, 20, MS, &mut out).ok();
        assert_eq!(standings.get("net"), Standing::Suppressed { by: "planner".into(), priority: 1 });
        let generation = standings.generation();
        component.tick(2 * MS, &mut out).ok();
        assert_eq!(standings.generation(), generation, "an unchanged decision writes nothing");
        component.peer_faulted(10, 3 * MS, &mut out);
        assert_eq!(standings.get("net"), Standing::Holds);
        assert_eq!(standings.get("planner"), Standing::Idle);
        component.tick(600 * MS, &mut out).ok();
        assert_eq!(standings.get("net"), Standing::Idle, "the operator's commands timed out");
    }
}
