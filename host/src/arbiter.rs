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
//! Locks (docs/estop.md): while a lock of the host's [`Locks`] is engaged,
//! every source below its priority is suppressed (a lock the robot file
//! does not declare in `locks` is above every source), so unless a source
//! at or above it drives, the motors get STOP. The arbiter checks the board
//! once per cycle (one atomic load) and decides at once when it changed; a
//! `true` on the `lock` input (a bumper) engages the `feed-lock`. Nothing
//! here releases a lock.
//!
//! [`Arbiter`] is the decision logic, driven with explicit time; the
//! `builtin:arbiter` component ([`ArbiterComponent`]) wires it into the graph:
//! every connection into its `commands` input is a source, with the sending
//! component's priority and timeout. [`ArbiterBuiltin`] declares it.

use serde::Serialize;

use crate::builtin::{
    self, BuildContext, Builtin, BuiltinError, CheckContext, ParamDecl, ParamType, Params, Ports, Registry, number_in,
};
use crate::config::{ParamProblem, RobotProblem, RobotView};
use crate::contract::control::{Command, ControlCommand};
use crate::contract::{Value, ValueKind};
use crate::runtime::locks::unix_now_ms;
use crate::runtime::{
    CallError, Component, Engagement, Family, LockEvent, Locks, NamedSection, Outbox, PriorityCell, Sample, Standing,
    Standings, StatusSection,
};

/// Most sources one arbiter may have.
pub const MAX_SOURCES: usize = 64;

/// Most locks one arbiter may declare (`locks`): the robot file is the
/// only writer, and a lock is a word in the status and the portal.
pub const MAX_DECLARED_LOCKS: usize = 16;

/// The priority of a lock the robot file does not declare: above every
/// source.
pub const UNDECLARED_LOCK_PRIORITY: i32 = i32::MAX;

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
    last: Option<(Command, u64)>,
    faulted: bool,
    held_ns: u64,
}

/// Who holds control and what goes to the motors.
#[derive(Clone, Debug, PartialEq)]
pub struct Decision {
    /// Index of the winning source, `None` when no source is active.
    pub holder: Option<usize>,
    /// The command for the motors: the holder's latest (as it entered), or
    /// STOP.
    pub command: Command,
}

/// What the rest of the host sees of the arbiter.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
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
    /// The highest engaged lock, if any: its name and priority (`None`:
    /// undeclared, above every source).
    pub lock: Option<LockView>,
    /// Every engaged lock.
    pub engaged: Vec<Engagement>,
    /// The latest lock events (at most `runtime::locks::MAX_LOCK_HISTORY`)
    /// and how many there were.
    pub lock_events: Vec<LockEvent>,
    pub lock_events_total: u64,
}

impl NamedSection for ArbiterStatus {
    const SECTION: &'static str = "arbiter";

    fn families(&self, component: &str) -> Vec<Family> {
        Family::each(
            ("arbiter", component),
            &[
                (
                    "subsume_arbiter_switches",
                    "changes of the source holding control (to and from none)",
                    Sample::Counter(self.switches),
                ),
                (
                    "subsume_arbiter_stops",
                    "STOP commands sent because no source was active",
                    Sample::Counter(self.stops_sent),
                ),
            ],
        )
    }
}

/// The lock that bounds the arbiter's sources now.
#[derive(Clone, Debug, PartialEq, Eq, Serialize)]
pub struct LockView {
    pub name: String,
    /// `None` when the robot file does not declare it (above everything).
    pub priority: Option<i32>,
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
    locks: Locks,
    /// Declared locks and their priorities.
    declared: Vec<(String, i32)>,
    /// The board's generation the floor was computed at.
    seen_locks: Option<u64>,
    /// The highest engaged lock: (name, priority); sources below it do not count.
    floor: Option<(String, i32)>,
}

impl Arbiter {
    /// An arbiter over `sources`, in robot-file order (the tie-break order).
    pub fn new(sources: Vec<Source>) -> Arbiter {
        Arbiter::with_locks(sources, Locks::default(), Vec::new())
    }

    /// An arbiter over `sources` bounded by the host's `locks`, with the
    /// priorities the robot file `declared` for some of them.
    pub fn with_locks(sources: Vec<Source>, locks: Locks, declared: Vec<(String, i32)>) -> Arbiter {
        let sources =
            sources.into_iter().map(|source| SourceState { source, last: None, faulted: false, held_ns: 0 }).collect();
        Arbiter {
            sources,
            holder: None,
            decided_at: None,
            switches: 0,
            stops_sent: 0,
            rejected: 0,
            locks,
            declared,
            seen_locks: None,
            floor: None,
        }
    }

    /// The host's locks this arbiter obeys.
    pub fn locks(&self) -> &Locks {
        &self.locks
    }

    /// Whether the locks changed since the last decision.
    pub fn locks_changed(&self) -> bool {
        self.seen_locks != Some(self.locks.generation())
    }

    /// A lock's priority: declared, or above everything.
    fn lock_priority(&self, name: &str) -> i32 {
        self.declared.iter().find(|(n, _)| n == name).map_or(UNDECLARED_LOCK_PRIORITY, |(_, p)| *p)
    }

    fn refresh_floor(&mut self) {
        let generation = self.locks.generation();
        if self.seen_locks == Some(generation) {
            return;
        }
        self.seen_locks = Some(generation);
        self.floor = self
            .locks
            .engaged()
            .into_iter()
            .map(|e| {
                let priority = self.lock_priority(&e.lock);
                (e.lock, priority)
            })
            .max_by_key(|(_, p)| *p);
    }

    /// The highest engaged lock as of the last decision.
    pub fn lock(&self) -> Option<LockView> {
        self.floor.as_ref().map(|(name, priority)| LockView {
            name: name.clone(),
            priority: (*priority != UNDECLARED_LOCK_PRIORITY).then_some(*priority),
        })
    }

    /// Whether the engaged locks let `state` count.
    fn above_floor(&self, state: &SourceState) -> bool {
        self.floor.as_ref().is_none_or(|(_, p)| state.source.priority.get() >= *p)
    }

    /// Records `command` from the source whose component is `component`.
    /// Returns false when `component` is not a source or has faulted.
    pub fn offer(&mut self, component: usize, command: impl Into<Command>, now_ns: u64) -> bool {
        match self.sources.iter_mut().find(|s| s.source.component == component) {
            Some(state) if !state.faulted => {
                state.last = Some((command.into(), now_ns));
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
        !state.faulted
            && state.last.as_ref().is_some_and(|(_, at)| now_ns.saturating_sub(*at) <= state.source.timeout_ns)
    }

    /// Decides at `now_ns`; counts switches, held time and stops.
    pub fn decide(&mut self, now_ns: u64) -> Decision {
        if let (Some(holder), Some(at)) = (self.holder, self.decided_at) {
            self.sources[holder].held_ns += now_ns.saturating_sub(at);
        }
        self.decided_at = Some(now_ns);
        self.refresh_floor();
        let counts = |s: &SourceState| Self::is_active(s, now_ns) && self.above_floor(s);
        let top = self.sources.iter().filter(|s| counts(s)).map(|s| s.source.priority.get()).max();
        let winner = top.and_then(|top| {
            let tied = |i: &usize| counts(&self.sources[*i]) && self.sources[*i].source.priority.get() == top;
            let operator_tied = (0..self.sources.len()).any(|i| tied(&i) && self.sources[i].source.operator);
            let candidate = |i: &usize| tied(i) && (!operator_tied || self.sources[*i].source.operator);
            self.holder.filter(candidate).or_else(|| (0..self.sources.len()).find(candidate))
        });
        if winner != self.holder {
            self.switches += 1;
            self.holder = winner;
        }
        let command = match winner.and_then(|w| self.sources[w].last.as_ref()) {
            Some((command, _)) => command.clone(),
            None => {
                self.stops_sent += 1;
                Command::from(ControlCommand::Stop)
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
            (_, Some(state)) if Self::is_active(state, now_ns) && !self.above_floor(state) => {
                let (name, priority) = self.floor.clone().unwrap_or_default();
                Standing::Suppressed { by: format!("lock {name}"), priority }
            }
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
        let (history, total) = self.locks.history();
        ArbiterStatus {
            holder: self.holder.map(|h| self.sources[h].source.name.clone()),
            suppressed: self.suppressed(now_ns).into_iter().map(|i| self.sources[i].source.name.clone()).collect(),
            switches: self.switches,
            stops_sent: self.stops_sent,
            held_s: self.sources.iter().map(|s| (s.source.name.clone(), s.held_ns as f64 / 1e9)).collect(),
            rejected: self.rejected,
            lock: self.lock(),
            engaged: self.locks.engaged(),
            lock_events: history,
            lock_events_total: total,
        }
    }
}

/// The `builtin:arbiter` component: input `commands` (one connection per
/// source), input `lock` (flags: `true` engages the feed lock), output
/// `cmd` (the winner's command, or STOP). It re-decides on every command,
/// every tick and every cycle the host's locks changed, emits at once when
/// the output changes and on every tick otherwise (so the serial link's
/// watchdog stays fed).
pub struct ArbiterComponent {
    name: String,
    arbiter: Arbiter,
    last_sent: Option<(Option<usize>, Option<ControlCommand>)>,
    now_ns: u64,
    standings: Standings,
    /// Each source's standing as last written to `standings`.
    published: Vec<Standing>,
    /// The lock the `lock` input engages, and its feeds.
    feed: LockFeed,
}

/// What feeds the `lock` input: which lock it engages, the feeding
/// components (index, name) with when each last sent (graph ns), and how
/// long a feed may stay silent before that engages the lock (0: forever).
#[derive(Clone, Debug, Default)]
pub struct LockFeed {
    pub lock: String,
    pub feeds: Vec<(usize, String)>,
    pub timeout_ns: u64,
    last: Vec<Option<u64>>,
    started_ns: Option<u64>,
}

impl LockFeed {
    pub fn new(lock: &str, feeds: Vec<(usize, String)>, timeout_ns: u64) -> LockFeed {
        let last = vec![None; feeds.len()];
        LockFeed { lock: lock.to_string(), feeds, timeout_ns, last, started_ns: None }
    }

    /// The feed that has been silent longer than the timeout at `now_ns`.
    fn silent(&self, now_ns: u64) -> Option<&str> {
        if self.timeout_ns == 0 {
            return None;
        }
        let started = self.started_ns.unwrap_or(now_ns);
        self.feeds
            .iter()
            .zip(&self.last)
            .find(|(_, last)| now_ns.saturating_sub(last.unwrap_or(started)) > self.timeout_ns)
            .map(|((_, name), _)| name.as_str())
    }
}

impl ArbiterComponent {
    pub fn new(name: &str, sources: Vec<Source>) -> ArbiterComponent {
        ArbiterComponent::with_standings(name, sources, Standings::default())
    }

    /// An arbiter that writes its sources' standings to `standings`.
    pub fn with_standings(name: &str, sources: Vec<Source>, standings: Standings) -> ArbiterComponent {
        ArbiterComponent::with_locks(name, Arbiter::new(sources), standings, LockFeed::default())
    }

    /// An arbiter component around `arbiter` (and the host's locks it
    /// obeys), fed by `feed` on its `lock` input.
    pub fn with_locks(name: &str, arbiter: Arbiter, standings: Standings, feed: LockFeed) -> ArbiterComponent {
        let published = vec![Standing::Idle; arbiter.len()];
        ArbiterComponent { name: name.to_string(), arbiter, last_sent: None, now_ns: 0, standings, published, feed }
    }

    /// Writes the standings that changed since the last decision. Most
    /// decisions change none: one comparison per source, no allocation.
    fn publish_standings(&mut self, now_ns: u64, locked: bool) {
        for index in 0..self.arbiter.len() {
            if locked {
                // While a lock is engaged (or just after): compare in full.
                let standing = self.arbiter.standing(index, now_ns);
                if standing != self.published[index] {
                    if let Some(source) = self.arbiter.source(index) {
                        self.standings.set(&source.name, standing.clone());
                    }
                    self.published[index] = standing;
                }
                continue;
            }
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
        let locks_changed = self.arbiter.locks_changed();
        let decision = self.arbiter.decide(now_ns);
        if locks_changed {
            self.log_locks();
        }
        self.publish_standings(now_ns, locks_changed || self.arbiter.floor.is_some());
        let previous_holder = self.last_sent.map(|(h, _)| h);
        if previous_holder != Some(decision.holder) {
            self.log_change(decision.holder, now_ns);
        }
        let output = (decision.holder, decision.command.motion());
        if always || self.last_sent != Some(output) {
            out.push((0, Value::Command(decision.command)));
        }
        self.last_sent = Some(output);
    }

    fn log_locks(&self) {
        match self.arbiter.lock() {
            Some(LockView { name, priority: None }) => {
                tracing::warn!(component = %self.name, "lock '{name}' is engaged: every source is suppressed, STOP")
            }
            Some(LockView { name, priority: Some(p) }) => {
                tracing::warn!(component = %self.name, "lock '{name}' is engaged: sources below priority {p} are suppressed")
            }
            None => tracing::info!(component = %self.name, "no lock is engaged"),
        }
    }

    /// A flag on the `lock` input from component `from`.
    fn on_lock_feed(&mut self, value: &Value, from: usize, now_ns: u64, out: &mut Outbox) -> Result<(), CallError> {
        let Value::Flag(engage) = value else {
            return Err(CallError::Reported("lock: expected a flag".into()));
        };
        let Some(slot) = self.feed.feeds.iter().position(|(c, _)| *c == from) else { return Ok(()) };
        self.feed.last[slot] = Some(now_ns);
        if *engage {
            let by = self.feed.feeds[slot].1.clone();
            if self.arbiter.locks().engage(&self.feed.lock, &by, "feedback", unix_now_ms()) {
                self.decide_and_emit(now_ns, false, out);
            }
        }
        Ok(())
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
        port: u32,
        value: &Value,
        from: usize,
        now_ns: u64,
        out: &mut Outbox,
    ) -> Result<(), CallError> {
        if port == LOCK_PORT {
            return self.on_lock_feed(value, from, now_ns, out);
        }
        let Value::Command(command) = value else {
            self.arbiter.reject();
            return Err(CallError::Reported("commands: expected a control string".into()));
        };
        match command.parsed() {
            Ok(_) => {
                if self.arbiter.offer(from, command.clone(), now_ns) {
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
        self.feed.started_ns.get_or_insert(now_ns);
        if let Some(silent) = self.feed.silent(now_ns) {
            let by = silent.to_string();
            self.arbiter.locks().engage(&self.feed.lock, &by, "feed silent", unix_now_ms());
        }
        self.decide_and_emit(now_ns, true, out);
        Ok(())
    }

    fn poll(&mut self, now_ns: u64, out: &mut Outbox) {
        // One load per cycle: a lock engaged or released elsewhere (the
        // portal, the network platform, the command line) is decided on in
        // the cycle it wakes.
        if self.arbiter.locks_changed() {
            self.decide_and_emit(now_ns, false, out);
        }
    }

    fn peer_faulted(&mut self, component: usize, now_ns: u64, out: &mut Outbox) {
        self.arbiter.fault(component);
        self.decide_and_emit(now_ns, false, out);
    }

    fn peer_restarted(&mut self, component: usize, _now_ns: u64) {
        self.arbiter.restore(component);
    }

    fn status(&self) -> Option<Box<dyn StatusSection>> {
        Some(Box::new(self.arbiter.status(self.now_ns)))
    }
}

/// The `commands` input's index: motion sources.
const COMMANDS_PORT: u32 = 0;
/// The `lock` input's index.
const LOCK_PORT: u32 = 1;

const PARAMS: &[ParamDecl] = &[
    ParamDecl {
        name: "locks",
        ty: ParamType::Text,
        default: "",
        unit: "",
        doc: "declared locks, name=priority pairs separated by spaces (estop=5); a lock not declared is above every source",
    },
    ParamDecl {
        name: "feed-lock",
        ty: ParamType::Required,
        default: "bumper",
        unit: "",
        doc: "the lock a true flag on the lock input engages (a bumper hit); it stays engaged until released",
    },
    ParamDecl {
        name: "feed-timeout",
        ty: number_in(0.0, 3600.0),
        default: "0",
        unit: "s",
        doc: "a wired lock feed silent this long engages feed-lock (0: never; for feeds that repeat their state)",
    },
];

/// The declared locks of `text`: `name=priority` pairs separated by spaces.
pub fn parse_locks(text: &str) -> Result<Vec<(String, i32)>, LockSpecError> {
    let mut locks: Vec<(String, i32)> = Vec::new();
    for pair in text.split_ascii_whitespace() {
        let (name, priority) =
            pair.split_once('=').ok_or_else(|| LockSpecError(format!("'{pair}' is not name=priority")))?;
        let valid = !name.is_empty()
            && name.len() <= 32
            && name.chars().all(|c| c.is_ascii_alphanumeric() || c == '-' || c == '_');
        if !valid {
            return Err(LockSpecError(format!("lock name '{name}' must be 1 to 32 letters, digits, '-' or '_'")));
        }
        let priority =
            priority.parse::<i32>().ok().filter(|p| *p < UNDECLARED_LOCK_PRIORITY).ok_or_else(|| {
                LockSpecError(format!("priority '{priority}' of lock '{name}' is not a whole number"))
            })?;
        if locks.iter().any(|(n, _)| n == name) {
            return Err(LockSpecError(format!("lock '{name}' is declared twice")));
        }
        locks.push((name.to_string(), priority));
    }
    if locks.len() > MAX_DECLARED_LOCKS {
        return Err(LockSpecError(format!("{} locks; at most {MAX_DECLARED_LOCKS} are allowed", locks.len())));
    }
    Ok(locks)
}

/// Why a `locks` parameter is refused (lowercase, names the pair).
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[error("{0}")]
pub struct LockSpecError(pub String);

/// The `arbiter` kind: its sources are the connections into `commands`,
/// its lock feeds the connections into `lock`.
pub struct ArbiterBuiltin;

impl Builtin for ArbiterBuiltin {
    fn kind(&self) -> &'static str {
        "arbiter"
    }

    fn summary(&self) -> &'static str {
        "Subsumption: the highest-priority active source drives; none active: STOP"
    }

    fn params(&self) -> &'static [ParamDecl] {
        PARAMS
    }

    fn arbitrates(&self) -> bool {
        true
    }

    /// Every motion source (a connection into `commands`; `lock` takes
    /// emergency stops) needs a priority.
    fn check_robot(&self, me: usize, _: &Params, view: &RobotView<'_>, _: Registry) -> Vec<RobotProblem> {
        let robot = view.robot;
        let into_commands = robot.connections.iter().filter(|c| c.to.component == me && c.to.port == COMMANDS_PORT);
        into_commands
            .filter_map(|c| {
                let source = robot.components.get(c.from.component)?;
                source.priority.is_none().then(|| RobotProblem {
                    offset: c.offset,
                    message: format!(
                        "'{}' feeds the arbiter, but component '{}' has no priority (set priority=\"N\" on it)",
                        robot.output_name(c.from),
                        source.name
                    ),
                })
            })
            .collect()
    }

    fn check(&self, params: &Params, _ctx: &mut CheckContext<'_>) -> Vec<ParamProblem> {
        match parse_locks(params.text("locks").unwrap_or_default()) {
            Ok(_) => Vec::new(),
            Err(e) => vec![ParamProblem::new("locks", e.0)],
        }
    }

    fn ports(&self, _params: &Params) -> Ports {
        Ports {
            inputs: vec![
                builtin::port(
                    "commands",
                    ValueKind::Command,
                    "control strings; every connection is a source with its sender's priority",
                ),
                builtin::port("lock", ValueKind::Flag, "true engages feed-lock (a bumper); false releases nothing"),
            ],
            outputs: vec![builtin::port("cmd", ValueKind::Command, "the winning command, or STOP")],
        }
    }

    fn build(&self, params: &Params, ctx: &mut BuildContext<'_>) -> Result<Box<dyn Component>, BuiltinError> {
        let declared = parse_locks(params.text("locks")?).map_err(|e| BuiltinError::Refused(e.0))?;
        let mut feeds: Vec<(usize, String)> = Vec::new();
        for connection in ctx.robot.connections.iter().filter(|c| c.to.component == ctx.index && c.to.port == LOCK_PORT)
        {
            let Some(from) = ctx.robot.components.get(connection.from.component) else { continue };
            if !feeds.iter().any(|(c, _)| *c == connection.from.component) {
                feeds.push((connection.from.component, from.name.clone()));
            }
        }
        let feed = LockFeed::new(params.text("feed-lock")?, feeds, params.seconds("feed-timeout")?.as_nanos() as u64);
        let mut sources: Vec<Source> = Vec::new();
        for connection in ctx.robot.connections.iter().filter(|c| c.to.component == ctx.index && c.to.port != LOCK_PORT)
        {
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
                operator: builtin::builtin_of(ctx.robot, connection.from.component, ctx.registry)
                    .is_some_and(|b| b.answers_to_a_person()),
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
        // The host's locks, so an engaged lock survives an activation; a
        // graph without a host gets a board of its own.
        let locks = ctx.services.get::<Locks>().map(|l| (*l).clone()).unwrap_or_default();
        let arbiter = Arbiter::with_locks(sources, locks, declared);
        Ok(Box::new(ArbiterComponent::with_locks(name, arbiter, standings, feed)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::runtime::DEFAULT_LOCK;

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
            assert_eq!((decision.holder, decision.command), (holder, Command::from(command)), "at {ms} ms");
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
        // The winner's command goes on as it came in, not reformatted.
        assert_eq!(out, vec![(0, Value::Command("VEL 0.2 0".into()))], "unchanged output is not re-sent on input");
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

    /// What happens at a step of a lock table.
    enum LockEvent_ {
        Offer(usize, f64),
        Engage(&'static str),
        Release(Option<&'static str>),
        Decide,
    }

    /// (time ms, event, the holder expected, the command expected).
    type LockStep = (u64, LockEvent_, Option<usize>, ControlCommand);

    fn run_lock_table(arbiter: &mut Arbiter, table: Vec<LockStep>) {
        for (ms, event, holder, command) in table {
            let now = ms * MS;
            match event {
                LockEvent_::Offer(component, v) => {
                    arbiter.offer(component, vel(v), now);
                }
                LockEvent_::Engage(lock) => {
                    arbiter.locks().engage(lock, "ann", "portal", ms);
                }
                LockEvent_::Release(lock) => {
                    arbiter.locks().release(lock, "bob", "teleop", ms);
                }
                LockEvent_::Decide => {}
            }
            let decision = arbiter.decide(now);
            assert_eq!((decision.holder, decision.command), (holder, Command::from(command)), "at {ms} ms");
        }
    }

    #[test]
    fn a_lock_stops_everything_below_it_until_an_explicit_release() {
        use LockEvent_::*;
        // 0: avoid (10, priority 3), 1: planner (20, 1), 2: dock (30, 6).
        // Declared: "soft" at 2; "estop" is not declared: above everything.
        let sources = vec![source(10, "avoid", 3), source(20, "planner", 1), source(30, "dock", 6)];
        let mut arbiter = Arbiter::with_locks(sources, Locks::default(), vec![("soft".into(), 2)]);
        let stop = ControlCommand::Stop;
        #[rustfmt::skip]
        let table: Vec<LockStep> = vec![
            (0,    Offer(20, 0.2), Some(1), vel(0.2)), // the planner drives
            (10,   Engage("estop"), None,   stop),     // engage: STOP at once
            (20,   Offer(20, 0.3), None,    stop),     // the planner is suppressed
            (30,   Offer(10, 0.1), None,    stop),     // so is avoid (3)
            (40,   Offer(30, 0.1), None,    stop),     // and dock (6): undeclared is above everything
            (5000, Decide,         None,    stop),     // no timeout releases it
            (5001, Release(Some("soft")), None, stop), // releasing another lock changes nothing
            (5002, Offer(20, 0.2), None,    stop),
            (5003, Release(None),  Some(1), vel(0.2)), // an explicit release: the planner again
            (5010, Engage("soft"), None,    stop),     // soft (2) suppresses the planner (1)...
            (5020, Offer(10, 0.1), Some(0), vel(0.1)), // ...but not avoid (3)
            (5030, Engage("estop"), None,   stop),     // a lock over a lock: the higher one bounds
            (5040, Release(Some("estop")), Some(0), vel(0.1)), // soft still engaged: avoid drives
            (5041, Offer(20, 0.2), Some(0), vel(0.1)),
            (5600, Offer(20, 0.2), None,    stop),     // avoid timed out; the planner is below soft
            (5601, Release(Some("soft")), Some(1), vel(0.2)),
        ];
        run_lock_table(&mut arbiter, table);
        let status = arbiter.status(5601 * MS);
        assert_eq!(status.lock, None);
        assert_eq!(status.lock_events_total, 6, "three engages, three releases");
        assert_eq!(status.lock_events[1].held_ms, Some(4993), "estop from 10 ms to 5003 ms");
    }

    #[test]
    fn a_lock_suppresses_an_operator_holding_control_and_says_so() {
        use LockEvent_::*;
        let standings = Standings::default();
        let sources = vec![source(10, "planner", 1), operator(20, "net", 2)];
        let locks = Locks::default();
        let arbiter = Arbiter::with_locks(sources, locks.clone(), Vec::new());
        let mut component = ArbiterComponent::with_locks("arbiter", arbiter, standings.clone(), LockFeed::default());
        let mut out = Vec::new();
        component.on_input(0, &Value::Command("VEL 0.4 0".into()), 20, 0, &mut out).ok();
        assert_eq!(standings.get("net"), Standing::Holds);
        locks.engage(DEFAULT_LOCK, "ann", "portal", 0);
        out.clear();
        component.poll(MS, &mut out);
        assert_eq!(out, vec![(0, Value::Command("STOP".into()))], "the cycle after the engage sends STOP");
        assert_eq!(
            standings.get("net"),
            Standing::Suppressed { by: "lock estop".into(), priority: UNDECLARED_LOCK_PRIORITY }
        );
        out.clear();
        component.poll(2 * MS, &mut out);
        assert!(out.is_empty(), "an unchanged board decides nothing new");
        component.on_input(0, &Value::Command("VEL 0.4 0".into()), 20, 3 * MS, &mut out).ok();
        component.tick(4 * MS, &mut out).ok();
        assert!(out.iter().all(|(_, v)| *v == Value::Command("STOP".into())), "nothing moves while engaged: {out:?}");
        // A table over the operator's later commands.
        let mut arbiter =
            Arbiter::with_locks(vec![source(10, "planner", 1), operator(20, "net", 2)], locks.clone(), Vec::new());
        #[rustfmt::skip]
        run_lock_table(&mut arbiter, vec![
            (10,  Offer(20, 0.4), None,    ControlCommand::Stop),
            (20,  Release(None),  Some(1), vel(0.4)),
            (30,  Engage("estop"), None,   ControlCommand::Stop),
        ]);
    }

    #[test]
    fn a_lock_survives_a_set_activation() {
        use LockEvent_::*;
        // The host's board, shared by the old set's arbiter and the new one.
        let locks = Locks::default();
        let mut old = Arbiter::with_locks(vec![source(10, "planner", 1)], locks.clone(), Vec::new());
        #[rustfmt::skip]
        run_lock_table(&mut old, vec![
            (0,  Offer(10, 0.2), Some(0), vel(0.2)),
            (10, Engage("estop"), None,   ControlCommand::Stop),
        ]);
        // The activation swaps in a new graph: a new arbiter, same board.
        drop(old);
        let mut new = Arbiter::with_locks(vec![source(11, "planner2", 1)], locks.clone(), Vec::new());
        #[rustfmt::skip]
        run_lock_table(&mut new, vec![
            (20, Offer(11, 0.3), None,    ControlCommand::Stop), // the first decision is locked
            (30, Release(None),  Some(0), vel(0.3)),
        ]);
    }

    #[test]
    fn a_feed_engages_but_never_releases_and_a_silent_feed_engages() {
        let locks = Locks::default();
        let arbiter = Arbiter::with_locks(vec![source(10, "planner", 1)], locks.clone(), Vec::new());
        let feed = LockFeed::new("bumper", vec![(40, "motors".into())], 100 * MS);
        let mut component = ArbiterComponent::with_locks("arbiter", arbiter, Standings::default(), feed);
        let mut out = Vec::new();
        component.tick(0, &mut out).ok();
        component.on_input(1, &Value::Flag(false), 40, MS, &mut out).ok();
        assert!(!locks.any_engaged());
        component.on_input(1, &Value::Flag(true), 40, 2 * MS, &mut out).ok();
        assert_eq!(locks.engaged()[0].lock, "bumper");
        assert_eq!(locks.engaged()[0].by, "motors");
        assert_eq!(out.last(), Some(&(0, Value::Command("STOP".into()))));
        component.on_input(1, &Value::Flag(false), 40, 3 * MS, &mut out).ok();
        assert!(locks.any_engaged(), "a feed's false releases nothing");
        assert!(component.on_input(1, &Value::Scalar(1.0), 40, 3 * MS, &mut out).is_err());
        locks.release(None, "bob", "portal", 0);
        component.tick(90 * MS, &mut out).ok();
        assert!(!locks.any_engaged(), "silent for 87 ms: within the timeout");
        component.tick(104 * MS, &mut out).ok();
        assert_eq!(locks.engaged()[0].how, "feed silent", "silent for 101 ms");
    }

    #[test]
    fn declared_locks_are_checked() {
        assert_eq!(parse_locks("estop=5  soft=-1").unwrap(), vec![("estop".into(), 5), ("soft".into(), -1)]);
        assert_eq!(parse_locks("").unwrap(), vec![]);
        for (text, why) in [
            ("estop", "is not name=priority"),
            ("estop=x", "is not a whole number"),
            ("a=1 a=2", "declared twice"),
            ("bad!=1", "lock name 'bad!'"),
        ] {
            let err = parse_locks(text).unwrap_err();
            assert!(err.0.contains(why), "{text}: {err}");
        }
    }
}
