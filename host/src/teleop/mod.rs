//! The network platform (`builtin:teleop`): remote operators connect over TCP
//! (a line protocol, docs/teleop.md) or WebSocket (the same messages as
//! JSON), authenticate, are measured (round-trip time and jitter, on connect
//! and every `probe-period`), get the control modes their link allows, and
//! send commands that pass through a constant-delay buffer into the graph as
//! one motion source whose priority is 1 + the mode's offset.
//!
//! Threads: sessions run on a small tokio runtime of their own; the control
//! loop side (`TeleopComponent`) owns the delay buffers and emits commands.
//! They talk only through bounded channels; a full channel drops (and tells
//! the operator), it never blocks the control loop.
//!
//! Invariants: a remote peer cannot exhaust the host (connection, line,
//! queue and authentication limits are named constants or settings); only an
//! authenticated operator holding a granted mode can move the robot, and only
//! one operator holds control at a time; commands never reach the arbiter
//! out of order, twice, or stale.

pub mod builtin;
pub mod client;
pub mod delay;
pub mod mode;
pub mod protocol;
pub mod session;

use std::collections::{HashMap, VecDeque};
use std::net::SocketAddr;
use std::path::Path;
use std::sync::mpsc::{Receiver, SyncSender, TrySendError};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use serde::Serialize;

use self::delay::{DelayBuffer, DelaySettings, DelayStats};
use self::mode::{Mode, ModePolicy};
use self::protocol::{ModeChange, ServerMessage};
use self::session::Measurement;
use crate::builtin::BuiltinError;
use crate::contract::{Value, is_valid_name};
use crate::robot::control::ControlCommand;
use crate::runtime::control_loop::{Clock, Waker};
use crate::runtime::{
    CallError, Component, Family, Locks, MetricKind, NamedSection, Outbox, PriorityCell, RunningRobot, Sample,
    Standing, Standings, StatusSection,
};
use crate::store::users::Directory;

/// Events from sessions waiting for the control loop; more are dropped and
/// the operator is told.
pub const EVENT_QUEUE: usize = 1024;
/// Shortest operator token accepted in the operators file: short tokens are
/// guessed.
pub const MIN_TOKEN_LEN: usize = 12;
/// Most operators in the operators file.
pub const MAX_OPERATORS_IN_FILE: usize = 1000;
/// Most ended sessions the status and the run report list one by one (the
/// newest; the older ones are counted in `earlier_sessions` and their
/// commands stay in the totals). A peer connecting in a loop, even one that
/// never logs in, would otherwise grow the host's memory, and the status the
/// control thread builds every second, without bound.
pub const MAX_ENDED_SESSIONS_LISTED: usize = 32;
/// Most mode changes listed per session (the newest; the older ones are
/// counted): an operator asking for modes in a loop would otherwise grow
/// its session's report without bound.
pub const MAX_MODE_CHANGES_LISTED: usize = 32;
/// Connections that have not logged in yet, on one network platform (its
/// line protocol, TLS or not, and both WebSockets together): each holds a
/// socket and a task until it logs in or its `auth-timeout` passes. They
/// take no operator's place; past this the newest is refused.
pub const MAX_UNAUTHENTICATED: usize = 64;
/// Of those, from one client address (one IPv6 /64): a peer opening
/// connections in a loop holds this many at most, and everyone else still
/// gets in.
pub const MAX_UNAUTHENTICATED_PER_ADDRESS: usize = 8;
/// Orders waiting for a session (close, lose control); a second one is
/// never needed before the first is read.
const ORDER_QUEUE: usize = 4;

/// Settings of the network platform.
#[derive(Clone, Debug)]
pub struct TeleopSettings {
    pub listen: SocketAddr,
    /// Where the WebSocket endpoint (`/teleop`) listens, if anywhere.
    pub websocket: Option<SocketAddr>,
    /// Operators and their tokens (the `operators` file).
    pub operators: Vec<(String, String)>,
    /// The portal's users (operators and admins drive with their password
    /// or a pad ticket), when the host runs the portal.
    pub directory: Option<Arc<Directory>>,
    pub probe_period: Duration,
    pub policy: ModePolicy,
    /// Operators logged in at once (`max-operators`); connections that
    /// have not logged in take no place (docs/teleop.md, "Who gets in").
    pub max_operators: usize,
    /// How long a connection may take to log in (`auth-timeout`), TLS
    /// handshake included.
    pub auth_timeout: Duration,
    /// How long a logged-in operator may send nothing but pongs before
    /// another operator may take their place or control (`idle-timeout`).
    pub idle_timeout: Duration,
    pub delay: DelaySettings,
    /// Serve TLS on both listeners with this identity (the `tls`
    /// parameter, resolved against the host's certificate).
    pub tls: Option<crate::tls::TlsIdentity>,
}

impl TeleopSettings {
    /// Whether `token` is `name`'s: in the operators file (constant time in
    /// the token's length), or a portal user's password or pad ticket. A
    /// password check costs an argon2id hash (~tens of ms) on the network
    /// runtime; logins are rare and rate-limited by the session.
    pub fn check_token(&self, name: &str, token: &str) -> bool {
        if self.directory.as_ref().is_some_and(|d| d.check_operator(name, token)) {
            return true;
        }
        let mut found = false;
        for (operator, expected) in &self.operators {
            let same_length = expected.len() == token.len();
            let difference = expected.bytes().zip(token.bytes()).fold(0u8, |acc, (a, b)| acc | (a ^ b));
            found |= operator == name && same_length && difference == 0;
        }
        found
    }

    /// Whether `name` drives only by a grant (a portal user whose role may
    /// not drive, and who is not in the operators file).
    pub fn drives_by_grant(&self, name: &str) -> bool {
        let Some(directory) = &self.directory else { return false };
        !self.operators.iter().any(|(operator, _)| operator == name)
            && directory.users.get(name).is_some_and(|user| !user.may_drive())
    }

    /// Whether `name`'s grant holds now.
    pub fn grant_holds(&self, name: &str) -> bool {
        self.directory.as_ref().is_some_and(|d| d.grants.allows(name, crate::runtime::locks::unix_now_ms()))
    }
}

/// Reads an operators file: one `NAME TOKEN` per line, `#` comments.
fn load_operators(path: &Path) -> Result<Vec<(String, String)>, String> {
    let text =
        std::fs::read_to_string(path).map_err(|e| format!("cannot read operators file {}: {e}", path.display()))?;
    let mut operators = Vec::new();
    for (i, line) in text.lines().enumerate() {
        let content = line.split('#').next().unwrap_or("").trim();
        if content.is_empty() {
            continue;
        }
        let at = format!("{}:{}", path.display(), i + 1);
        let (name, token) = match content.split_ascii_whitespace().collect::<Vec<_>>().as_slice() {
            [name, token] => (name.to_string(), token.to_string()),
            _ => return Err(format!("{at}: expected NAME TOKEN")),
        };
        if !is_valid_name(&name) {
            return Err(format!("{at}: operator name '{name}' is not [a-z][a-z0-9_-]*"));
        }
        if token.len() < MIN_TOKEN_LEN {
            return Err(format!("{at}: the token of '{name}' is shorter than {MIN_TOKEN_LEN} characters"));
        }
        if operators.iter().any(|(n, _)| *n == name) {
            return Err(format!("{at}: operator '{name}' is listed twice"));
        }
        operators.push((name, token));
        if operators.len() > MAX_OPERATORS_IN_FILE {
            return Err(format!("{at}: more than {MAX_OPERATORS_IN_FILE} operators"));
        }
    }
    Ok(operators)
}

/// What sessions tell the control loop.
#[derive(Debug)]
pub enum NetEvent {
    Connected { session: u64, notices: tokio::sync::mpsc::Sender<ServerMessage> },
    Command { session: u64, seq: u64, time_ms: u64, command: ControlCommand, arrival_ns: u64 },
    Mode { session: u64, mode: Option<Mode> },
    Disconnected { session: u64 },
}

/// One session as the report shows it.
#[derive(Clone, Debug, Default, Serialize)]
pub struct SessionReport {
    pub session: u64,
    pub operator: Option<String>,
    pub address: String,
    pub connected_at_s: f64,
    pub disconnected_at_s: Option<f64>,
    pub rtt_ms: Option<f64>,
    pub jitter_ms: Option<f64>,
    pub measurements: u64,
    pub mode: Option<Mode>,
    /// The newest [`MAX_MODE_CHANGES_LISTED`] changes, oldest first.
    pub mode_changes: Vec<ModeChange>,
    /// Changes no longer listed.
    pub earlier_mode_changes: u64,
    pub malformed_lines: u64,
    pub commands: DelayStats,
    pub playout_delay_ms: Option<f64>,
}

/// The network platform's section of the report and the live status.
#[derive(Clone, Debug, Default, Serialize)]
pub struct TeleopStatus {
    /// Where it listens.
    pub listen: String,
    /// Operators logged in now (each holds one of `max-operators` places).
    pub operators_served: usize,
    /// Connections that have not logged in yet (their own pool).
    pub unauthenticated: usize,
    /// Every open session and the newest ended ones.
    pub sessions: Vec<SessionReport>,
    /// Ended sessions no longer listed.
    pub earlier_sessions: u64,
    /// The commands of every session, listed or not.
    pub commands: DelayStats,
    /// The network source's priority now.
    pub priority: i32,
    /// The robot it belongs to (renamed by activations).
    pub robot: String,
}

impl TeleopStatus {
    /// The sessions still connected.
    pub fn open_sessions(&self) -> impl Iterator<Item = &SessionReport> {
        self.sessions.iter().filter(|s| s.disconnected_at_s.is_none())
    }
}

impl NamedSection for TeleopStatus {
    const SECTION: &'static str = "teleop";

    fn families(&self, component: &str) -> Vec<Family> {
        let network = || ("network", component.to_string());
        let mut rtt = Family::new(
            "subsume_teleop_rtt_seconds",
            "the last measured round-trip time of each connected operator session",
            MetricKind::Gauge,
        );
        for session in self.open_sessions() {
            if let Some(ms) = session.rtt_ms {
                let operator = session.operator.clone().unwrap_or_default();
                let labels = vec![network(), ("session", session.session.to_string()), ("operator", operator)];
                rtt = rtt.gauge(labels, ms / 1e3);
            }
        }
        let open = self.open_sessions().count();
        let c = &self.commands;
        let mut dropped = Family::new(
            "subsume_teleop_commands_dropped",
            "operator commands never released, by reason (stale, duplicate, full, superseded)",
            MetricKind::Counter,
        );
        for (reason, count) in [
            ("stale", c.dropped_stale),
            ("duplicate", c.dropped_duplicate),
            ("full", c.dropped_full),
            ("superseded", c.superseded),
        ] {
            dropped = dropped.counter(vec![network(), ("reason", reason.to_string())], count);
        }
        let mut families = vec![rtt];
        families.extend(Family::each(
            ("network", component),
            &[
                ("subsume_teleop_sessions", "operator connections open now", Sample::Gauge(open as f64)),
                (
                    "subsume_teleop_commands_released",
                    "operator commands released by the delay buffer",
                    Sample::Counter(c.released),
                ),
            ],
        ));
        families.push(dropped);
        families
    }
}

/// State shared by the sessions (network runtime) and the component.
pub struct ServerContext {
    /// The robot that runs now (renamed by activations).
    pub robot: Arc<RunningRobot>,
    pub settings: TeleopSettings,
    pub clock: Clock,
    events: SyncSender<NetEvent>,
    waker: Waker,
    /// The host's locks: sessions engage and release them directly (not
    /// through the control loop's queue, which a flood could fill).
    pub locks: Locks,
    controller: Mutex<Option<(u64, String)>>,
    reports: Mutex<SessionReports>,
    /// Sessions open (logged in or not), counted from `open_session` to
    /// `close_session`.
    open: std::sync::atomic::AtomicUsize,
    /// Connections that have not logged in (their own pool: they take no
    /// operator's place).
    pub unauthenticated: Arc<crate::admission::Pool>,
    /// The logged-in operators' places.
    operators: Mutex<Vec<OperatorPlace>>,
}

/// What the host can tell a session to do from outside it.
#[derive(Debug)]
pub enum SessionOrder {
    /// Close, saying why (its place went to another operator).
    Close(String),
    /// Control passed to another operator: drop the mode, saying why.
    LoseControl(String),
}

/// A logged-in operator's place among `max-operators`.
#[derive(Debug)]
struct OperatorPlace {
    session: u64,
    name: String,
    /// The last message other than a `PONG` (the client answers those by
    /// itself, so they say nothing of a person being there).
    last_active: tokio::time::Instant,
    orders: tokio::sync::mpsc::Sender<SessionOrder>,
}

/// Why a login got no operator's place.
#[derive(Debug, PartialEq, Eq)]
pub struct NoPlace {
    pub max: usize,
    pub idle_timeout: Duration,
}

impl std::fmt::Display for NoPlace {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "busy: at most {} operators are served at once, and none has been idle for {} s",
            self.max,
            self.idle_timeout.as_secs_f64()
        )
    }
}

/// The sessions the status lists: every open one, in the order they
/// connected, and the newest [`MAX_ENDED_SESSIONS_LISTED`] ended ones, in
/// the order they ended (the order the control loop hears of it, so its
/// command counts are dropped for the same sessions).
#[derive(Default)]
struct SessionReports {
    open: Vec<SessionReport>,
    ended: VecDeque<SessionReport>,
    /// Ended sessions no longer listed.
    earlier: u64,
}

impl SessionReports {
    fn find(&mut self, session: u64) -> Option<&mut SessionReport> {
        self.open.iter_mut().find(|r| r.session == session)
    }

    /// Moves `session` to the ended ones at `at_s`, dropping the oldest
    /// ended past the bound.
    fn end(&mut self, session: u64, at_s: f64) {
        if let Some(index) = self.open.iter().position(|r| r.session == session) {
            let mut report = self.open.remove(index);
            report.disconnected_at_s = Some(at_s);
            self.ended.push_back(report);
        }
        while self.ended.len() > MAX_ENDED_SESSIONS_LISTED {
            self.ended.pop_front();
            self.earlier += 1;
        }
    }

    /// Ended sessions first (oldest first), then the open ones, and how
    /// many ended ones are no longer listed.
    fn listed(&self) -> (Vec<SessionReport>, u64) {
        (self.ended.iter().chain(&self.open).cloned().collect(), self.earlier)
    }
}

impl ServerContext {
    /// Sends `event` to the control loop and wakes it.
    pub fn send(&self, event: NetEvent) -> Result<(), TrySendError<NetEvent>> {
        self.events.try_send(event)?;
        self.waker.wake();
        Ok(())
    }

    fn report<F: FnOnce(&mut SessionReport)>(&self, session: u64, update: F) {
        if let Ok(mut reports) = self.reports.lock()
            && let Some(report) = reports.find(session)
        {
            update(report);
        }
    }

    fn open_session(&self, session: u64, address: &str, notices: tokio::sync::mpsc::Sender<ServerMessage>) {
        self.open.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        if let Ok(mut reports) = self.reports.lock() {
            reports.open.push(SessionReport {
                session,
                address: address.to_string(),
                connected_at_s: self.clock.now_ns() as f64 / 1e9,
                ..SessionReport::default()
            });
        }
        let _ = self.send(NetEvent::Connected { session, notices });
    }

    fn authenticated(&self, session: u64, name: &str) {
        self.report(session, |r| r.operator = Some(name.to_string()));
    }

    fn measured(&self, session: u64, m: Measurement) {
        self.report(session, |r| {
            r.rtt_ms = Some(m.rtt.as_secs_f64() * 1e3);
            r.jitter_ms = Some(m.jitter.as_secs_f64() * 1e3);
            r.measurements += 1;
        });
    }

    fn mode_changed(&self, session: u64, change: ModeChange) {
        self.report(session, |r| {
            r.mode = change.to;
            if r.mode_changes.len() >= MAX_MODE_CHANGES_LISTED {
                r.mode_changes.remove(0);
                r.earlier_mode_changes += 1;
            }
            r.mode_changes.push(change);
        });
    }

    fn count_malformed(&self, session: u64) {
        self.report(session, |r| r.malformed_lines += 1);
    }

    /// Gives control to `session` unless another session holds it and
    /// has not been idle for `idle-timeout`; an idle holder loses control
    /// (and is told). `Err` names the holder.
    fn take_control(&self, session: u64, name: &str, now: tokio::time::Instant) -> Result<(), String> {
        let Ok(mut controller) = self.controller.lock() else { return Err("nobody (the host is failing)".into()) };
        if let Some((holder, holder_name)) = &*controller
            && *holder != session
        {
            let Ok(places) = self.operators.lock() else { return Err(holder_name.clone()) };
            let idle =
                places.iter().find(|p| p.session == *holder).map(|p| now.saturating_duration_since(p.last_active));
            // A holder with no place is on its way out: it holds nothing.
            if idle.is_some_and(|idle| idle < self.settings.idle_timeout) {
                return Err(holder_name.clone());
            }
            if let Some(place) = places.iter().find(|p| p.session == *holder) {
                let why = format!(
                    "control passed to {name}: you sent nothing for {} s (idle-timeout); ask with MODE to drive again",
                    self.settings.idle_timeout.as_secs_f64()
                );
                let _ = place.orders.try_send(SessionOrder::LoseControl(why));
            }
            tracing::info!(from = %holder_name, to = %name, "control passed from an idle operator");
        }
        *controller = Some((session, name.to_string()));
        Ok(())
    }

    /// An operator's place for `session`, which just logged in as `name`:
    /// a free one, else the place of the operator idle longest past
    /// `idle-timeout` (who is told, and closed), else none.
    fn claim_place(
        &self,
        session: u64,
        name: &str,
        orders: tokio::sync::mpsc::Sender<SessionOrder>,
        now: tokio::time::Instant,
    ) -> Result<(), NoPlace> {
        let settings = &self.settings;
        let no_place = NoPlace { max: settings.max_operators, idle_timeout: settings.idle_timeout };
        let evicted = {
            let Ok(mut places) = self.operators.lock() else { return Err(no_place) };
            let mut evicted = None;
            if places.len() >= settings.max_operators {
                let idlest = places
                    .iter()
                    .enumerate()
                    .filter(|(_, p)| now.saturating_duration_since(p.last_active) >= settings.idle_timeout)
                    .min_by_key(|(_, p)| p.last_active)
                    .map(|(index, _)| index);
                let Some(index) = idlest else { return Err(no_place) };
                evicted = Some(places.remove(index));
            }
            places.push(OperatorPlace { session, name: name.to_string(), last_active: now, orders });
            evicted
        };
        if let Some(idle) = evicted {
            let why = format!(
                "your place went to {name}: you sent nothing for {:.0} s (idle-timeout {} s) while all {} places were taken",
                now.saturating_duration_since(idle.last_active).as_secs_f64(),
                settings.idle_timeout.as_secs_f64(),
                settings.max_operators
            );
            tracing::info!(operator = %idle.name, session = idle.session, "idle operator closed for {name}");
            let _ = idle.orders.try_send(SessionOrder::Close(why));
            // It holds control no more: the newcomer may ask for it (the
            // controller's lock is taken after the places' is let go: the
            // other order is `take_control`'s).
            if let Ok(mut controller) = self.controller.lock()
                && controller.as_ref().is_some_and(|(holder, _)| *holder == idle.session)
            {
                *controller = None;
            }
        }
        Ok(())
    }

    /// Whether `session` holds control.
    fn holds_control(&self, session: u64) -> bool {
        self.controller.lock().is_ok_and(|c| c.as_ref().is_some_and(|(holder, _)| *holder == session))
    }

    /// `session`'s operator did something (anything but a `PONG`).
    fn touch(&self, session: u64, now: tokio::time::Instant) {
        if let Ok(mut places) = self.operators.lock()
            && let Some(place) = places.iter_mut().find(|p| p.session == session)
        {
            place.last_active = now;
        }
    }

    /// Operators logged in now.
    pub fn operators_served(&self) -> usize {
        self.operators.lock().map(|p| p.len()).unwrap_or(0)
    }

    fn close_session(&self, session: u64, operator: &Option<String>) {
        if let Ok(mut controller) = self.controller.lock()
            && controller.as_ref().is_some_and(|(holder, _)| *holder == session)
        {
            *controller = None;
        }
        if let Ok(mut places) = self.operators.lock() {
            places.retain(|p| p.session != session);
        }
        let _ =
            self.open.fetch_update(std::sync::atomic::Ordering::Relaxed, std::sync::atomic::Ordering::Relaxed, |n| {
                Some(n.saturating_sub(1))
            });
        if let Some(name) = operator {
            tracing::info!(operator = %name, session, "operator disconnected");
        }
        // The event is sent under the lock, so the control loop hears of
        // sessions ending in the order they were listed as ended.
        let mut reports = self.reports.lock().ok();
        if let Some(reports) = reports.as_mut() {
            reports.end(session, self.clock.now_ns() as f64 / 1e9);
        }
        let _ = self.send(NetEvent::Disconnected { session });
        drop(reports);
    }
}

/// The control-loop side of one session.
struct SessionControl {
    buffer: DelayBuffer<ControlCommand>,
    notices: tokio::sync::mpsc::Sender<ServerMessage>,
}

/// The `builtin:teleop` component: outputs `cmd` (released commands) and
/// `goal` (GOTO targets, for a planner).
pub struct TeleopComponent {
    name: String,
    ctx: Arc<ServerContext>,
    events: Receiver<NetEvent>,
    sessions: HashMap<u64, SessionControl>,
    /// The command counts of the newest ended sessions, oldest first (at
    /// most [`MAX_ENDED_SESSIONS_LISTED`]).
    finished: VecDeque<(u64, DelayStats)>,
    /// The command counts of the ended sessions no longer kept one by one.
    earlier: DelayStats,
    priority: PriorityCell,
    base_priority: i32,
    runtime: Option<tokio::runtime::Runtime>,
    listen: SocketAddr,
    /// The arbiters' verdicts on this source, and what the operator in
    /// control was last told of them.
    standings: Standings,
    standings_seen: u64,
    told: Standing,
    mode: Option<Mode>,
}

/// What a network platform shares with the rest of the host.
pub struct Surroundings {
    pub robot: Arc<RunningRobot>,
    pub standings: Standings,
    pub clock: Clock,
    pub waker: Waker,
    /// This source's priority, which the operator's mode moves.
    pub priority: PriorityCell,
    /// The host's emergency-stop locks (`ESTOP`, `RELEASE`).
    pub locks: Locks,
}

impl TeleopComponent {
    /// Binds the listeners and starts the network runtime.
    pub fn start(name: &str, around: Surroundings, settings: TeleopSettings) -> Result<TeleopComponent, BuiltinError> {
        let Surroundings { robot, standings, clock, waker, priority, locks } = around;
        if settings.operators.is_empty() && settings.directory.is_none() {
            return Err(BuiltinError::Refused(
                "nobody may log in: give the 'operators' parameter (a file of NAME TOKEN lines) \
                 or run the host with its portal (users with the operator role)"
                    .into(),
            ));
        }
        let bind = |address: SocketAddr| -> Result<std::net::TcpListener, BuiltinError> {
            crate::admission::listen(address).map_err(|e| BuiltinError::io(format!("cannot listen on {address}"), e))
        };
        let tcp = bind(settings.listen)?;
        let listen = tcp.local_addr().map_err(|e| BuiltinError::io("cannot read the teleoperation address", e))?;
        let websocket = settings.websocket.map(bind).transpose()?;
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(1)
            .thread_name(format!("net-{name}"))
            .enable_all()
            .build()
            .map_err(|e| BuiltinError::io("cannot start the network runtime", e))?;
        let (events_tx, events) = std::sync::mpsc::sync_channel(EVENT_QUEUE);
        let ctx = Arc::new(ServerContext {
            robot,
            settings,
            clock,
            events: events_tx,
            waker,
            locks,
            controller: Mutex::new(None),
            reports: Mutex::new(SessionReports::default()),
            open: Default::default(),
            unauthenticated: crate::admission::Pool::new(
                "unauthenticated connections",
                MAX_UNAUTHENTICATED,
                MAX_UNAUTHENTICATED_PER_ADDRESS,
            ),
            operators: Mutex::new(Vec::new()),
        });
        let tcp_ctx = ctx.clone();
        let line_tls = ctx.settings.tls.as_ref().map(|identity| identity.line_acceptor());
        let http_tls = ctx.settings.tls.as_ref().map(|identity| identity.http_acceptor());
        let over_tls = line_tls.is_some();
        runtime.spawn(async move {
            match tokio::net::TcpListener::from_std(tcp) {
                Ok(listener) => accept_tcp(listener, tcp_ctx, line_tls).await,
                Err(e) => tracing::error!("cannot serve teleoperation: {e}"),
            }
        });
        if let Some(ws) = websocket {
            let ws_address = ws.local_addr().map_err(|e| BuiltinError::io("cannot read the websocket address", e))?;
            let ws_ctx = ctx.clone();
            runtime.spawn(async move {
                let listener = match tokio::net::TcpListener::from_std(ws) {
                    Ok(listener) => listener,
                    Err(e) => return tracing::error!("cannot serve the teleoperation websocket: {e}"),
                };
                let app = websocket_router(ws_ctx);
                crate::admission::serve_http(listener, http_tls, app, crate::admission::HttpLimits::default()).await;
            });
            let scheme = if over_tls { "wss" } else { "ws" };
            tracing::info!(component = name, "teleoperation websocket on {scheme}://{ws_address}/teleop");
        }
        let transport = if over_tls { "tls" } else { "tcp" };
        tracing::info!(component = name, "teleoperation on {transport} {listen}");
        let base_priority = priority.get();
        Ok(TeleopComponent {
            name: name.to_string(),
            ctx,
            events,
            sessions: HashMap::new(),
            finished: VecDeque::new(),
            earlier: DelayStats::default(),
            priority,
            base_priority,
            runtime: Some(runtime),
            listen,
            standings_seen: standings.generation(),
            standings,
            told: Standing::Idle,
            mode: None,
        })
    }

    /// The TCP address operators connect to.
    pub fn listen_address(&self) -> SocketAddr {
        self.listen
    }

    /// The state its sessions share (the portal serves its WebSocket too).
    pub fn context(&self) -> &Arc<ServerContext> {
        &self.ctx
    }
}

/// Accepts line-protocol operators (over TLS when `tls` is given). A
/// connection is admitted to the pool of unauthenticated ones (a refused
/// one is told why in plain text, or closed before a TLS handshake) and has
/// `auth-timeout` from its accept to log in, handshake included.
async fn accept_tcp(
    listener: tokio::net::TcpListener,
    ctx: Arc<ServerContext>,
    tls: Option<tokio_rustls::TlsAcceptor>,
) {
    let mut next_id = 1u64;
    let handshakes = Arc::new(tokio::sync::Semaphore::new(crate::tls::MAX_HANDSHAKES));
    loop {
        let (stream, address) = match listener.accept().await {
            Ok(accepted) => accepted,
            Err(e) => {
                tracing::warn!("accepting a teleoperation connection failed: {e}");
                tokio::time::sleep(Duration::from_millis(50)).await;
                continue;
            }
        };
        let deadline = tokio::time::Instant::now() + ctx.settings.auth_timeout;
        let ticket = match ctx.unauthenticated.admit(address.ip()) {
            Ok(ticket) => ticket,
            Err(refusal) => {
                tracing::debug!("refused a teleoperation connection from {address}: {refusal}");
                if tls.is_none() {
                    crate::admission::refuse_now(stream, &format!("ERR busy: {refusal}\n"));
                }
                continue;
            }
        };
        let _ = stream.set_nodelay(true);
        let id = next_id;
        next_id += 1;
        let ctx = ctx.clone();
        let entry = session::Entry { id, address: address.to_string(), ticket, deadline };
        match &tls {
            None => {
                tokio::spawn(session::serve_tcp(stream, entry, ctx));
            }
            Some(acceptor) => {
                // The handshake runs on the connection's own task, so a
                // peer that stalls in it holds up nobody else, and counts
                // against its auth-timeout.
                let acceptor = acceptor.clone();
                let handshakes = handshakes.clone();
                tokio::spawn(async move {
                    let handshaken = tokio::time::timeout_at(deadline, async {
                        let _permit = handshakes.acquire_owned().await.ok()?;
                        crate::tls::handshake(&acceptor, stream, address).await
                    })
                    .await;
                    if let Ok(Some(stream)) = handshaken {
                        session::serve_tcp(stream, entry, ctx).await;
                    }
                });
            }
        }
    }
}

/// The `/teleop` WebSocket route of the `websocket` parameter's listener.
pub fn websocket_router(ctx: Arc<ServerContext>) -> axum::Router {
    use axum::extract::{ConnectInfo, State, WebSocketUpgrade};
    async fn upgrade(
        ws: WebSocketUpgrade,
        State(ctx): State<Arc<ServerContext>>,
        ConnectInfo(address): ConnectInfo<SocketAddr>,
    ) -> axum::response::Response {
        upgrade_websocket(ws, ctx, address)
    }
    axum::Router::new().route("/teleop", axum::routing::get(upgrade)).with_state(ctx)
}

/// Serves one teleoperation WebSocket on `ctx` (here and in the portal).
pub fn upgrade_websocket(
    ws: axum::extract::WebSocketUpgrade,
    ctx: Arc<ServerContext>,
    address: SocketAddr,
) -> axum::response::Response {
    use axum::response::IntoResponse;
    let deadline = tokio::time::Instant::now() + ctx.settings.auth_timeout;
    let ticket = match ctx.unauthenticated.admit(address.ip()) {
        Ok(ticket) => ticket,
        Err(refusal) => {
            return (axum::http::StatusCode::SERVICE_UNAVAILABLE, format!("busy: {refusal}")).into_response();
        }
    };
    static NEXT: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(1 << 32);
    let id = NEXT.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    let entry = session::Entry { id, address: address.to_string(), ticket, deadline };
    ws.max_message_size(protocol::MAX_LINE_BYTES * 2)
        .on_upgrade(move |socket| session::serve_websocket(socket, entry, ctx))
}

/// The network platforms running now, so the portal can serve their
/// WebSocket at its own `/api/v1/teleop`. Holds weak references: a platform
/// that stopped (replaced by an activation) drops out.
#[derive(Clone, Default)]
pub struct TeleopServers(Arc<Mutex<Vec<std::sync::Weak<ServerContext>>>>);

impl std::fmt::Debug for TeleopServers {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("TeleopServers")
    }
}

impl TeleopServers {
    pub fn register(&self, ctx: &Arc<ServerContext>) {
        if let Ok(mut servers) = self.0.lock() {
            servers.retain(|s| s.strong_count() > 0);
            servers.push(Arc::downgrade(ctx));
        }
    }

    /// The newest running network platform.
    pub fn current(&self) -> Option<Arc<ServerContext>> {
        self.0.lock().ok()?.iter().rev().find_map(|s| s.upgrade())
    }
}

impl TeleopComponent {
    /// Tells the operator in control when the arbiters' verdict on this
    /// source changed: one atomic load when nothing did.
    fn tell_standing(&mut self) {
        let generation = self.standings.generation();
        if generation == self.standings_seen {
            return;
        }
        self.standings_seen = generation;
        let standing = self.standings.get(&self.name);
        if standing == self.told {
            return;
        }
        let controller = self.ctx.controller.lock().ok().and_then(|c| c.as_ref().map(|(session, _)| *session));
        if let Some(control) = controller.and_then(|session| self.sessions.get(&session)) {
            let _ = control.notices.try_send(protocol::control_message(&standing, self.mode, self.base_priority));
        }
        self.told = standing;
    }

    /// Forgets `session`'s delay buffer (nothing it queued is released any
    /// more) and keeps its command counts.
    fn end_session(&mut self, session: u64) {
        let Some(mut control) = self.sessions.remove(&session) else { return };
        control.buffer.clear();
        self.finished.push_back((session, control.buffer.stats().clone()));
        while self.finished.len() > MAX_ENDED_SESSIONS_LISTED {
            if let Some((_, stats)) = self.finished.pop_front() {
                self.earlier.absorb(&stats);
            }
        }
    }

    /// Ends the sessions whose connection closed but whose `Disconnected`
    /// event was lost to a full event queue (a flood of commands can fill
    /// it): without this their buffers would stay, and release what they
    /// held, for the rest of the run. One atomic load when no event is
    /// missing.
    fn end_sessions_heard_of_no_more(&mut self) {
        if self.sessions.len() <= self.ctx.open.load(std::sync::atomic::Ordering::Relaxed) {
            return;
        }
        let closed: Vec<u64> =
            self.sessions.iter().filter(|(_, control)| control.notices.is_closed()).map(|(id, _)| *id).collect();
        for session in closed {
            tracing::warn!(component = %self.name, session, "a session ended without telling the control loop: ended now");
            self.end_session(session);
        }
    }
}

impl Component for TeleopComponent {
    fn tick(&mut self, now_ns: u64, out: &mut Outbox) -> Result<(), CallError> {
        self.poll(now_ns, out);
        Ok(())
    }

    fn poll(&mut self, now_ns: u64, out: &mut Outbox) {
        while let Ok(event) = self.events.try_recv() {
            match event {
                NetEvent::Connected { session, notices } => {
                    self.sessions
                        .insert(session, SessionControl { buffer: DelayBuffer::new(self.ctx.settings.delay), notices });
                }
                NetEvent::Command { session, seq, time_ms, command, arrival_ns } => {
                    let Some(control) = self.sessions.get_mut(&session) else { continue };
                    if let ControlCommand::Goto { x, y } = command {
                        out.push((1, Value::Vector(vec![x, y])));
                        continue;
                    }
                    if let Err(rejected) = control.buffer.push(seq, time_ms, command, arrival_ns) {
                        let _ =
                            control.notices.try_send(ServerMessage::Dropped { seq, reason: rejected.reason().into() });
                    }
                }
                NetEvent::Mode { session, mode } => match mode {
                    Some(mode) => {
                        self.mode = Some(mode);
                        let priority = self.base_priority + mode.priority_offset();
                        self.priority.set(priority);
                        tracing::info!(component = %self.name, session, "operator in {mode} mode: network priority {priority}");
                    }
                    None => {
                        if let Some(control) = self.sessions.get_mut(&session) {
                            control.buffer.clear();
                        }
                    }
                },
                NetEvent::Disconnected { session } => self.end_session(session),
            }
        }
        self.end_sessions_heard_of_no_more();
        for control in self.sessions.values_mut() {
            if let Some(command) = control.buffer.pop_ready(now_ns) {
                out.push((0, Value::Command(command.to_string())));
            }
        }
        self.tell_standing();
    }

    fn next_wake(&self) -> Option<u64> {
        self.sessions.values().filter_map(|c| c.buffer.next_release()).min()
    }

    fn status(&self) -> Option<Box<dyn StatusSection>> {
        let (mut sessions, earlier) = self.ctx.reports.lock().ok()?.listed();
        // The totals count every session, listed or not.
        let mut totals = self.earlier.clone();
        for control in self.sessions.values() {
            totals.absorb(control.buffer.stats());
        }
        for (_, stats) in &self.finished {
            totals.absorb(stats);
        }
        for report in &mut sessions {
            let (stats, delay) = match self.sessions.get(&report.session) {
                Some(control) => (control.buffer.stats().clone(), Some(control.buffer.playout_delay())),
                None => {
                    let ended = self.finished.iter().find(|(session, _)| *session == report.session);
                    (ended.map(|(_, stats)| stats.clone()).unwrap_or_default(), None)
                }
            };
            report.commands = stats;
            report.playout_delay_ms = delay.map(|d| d.as_secs_f64() * 1e3);
        }
        Some(Box::new(TeleopStatus {
            listen: self.listen.to_string(),
            operators_served: self.ctx.operators_served(),
            unauthenticated: self.ctx.unauthenticated.open(),
            sessions,
            earlier_sessions: earlier,
            commands: totals,
            priority: self.priority.get(),
            robot: self.ctx.robot.name(),
        }))
    }
}

impl Drop for TeleopComponent {
    fn drop(&mut self) {
        if let Some(runtime) = self.runtime.take() {
            runtime.shutdown_timeout(Duration::from_secs(1));
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn operators_files_are_checked_line_by_line() {
        let dir = std::env::temp_dir().join(format!("subsume-operators-{}", std::process::id()));
        let _ = std::fs::create_dir_all(&dir);
        let write = |text: &str| {
            let path = dir.join("operators");
            let _ = std::fs::write(&path, text);
            load_operators(&path)
        };
        assert_eq!(write("# ops\nalice 0123456789abcdef\n").map(|o| o.len()), Ok(1));
        assert!(
            write("alice short\n")
                .is_err_and(|e| e.ends_with("operators:1: the token of 'alice' is shorter than 12 characters"))
        );
        assert!(write("Alice 0123456789abcdef\n").is_err_and(|e| e.contains("not [a-z]")));
        assert!(
            write("a 0123456789abcdef\na 0123456789abcdef\n")
                .is_err_and(|e| e.contains(":2: operator 'a' is listed twice"))
        );
        assert!(write("lonely\n").is_err_and(|e| e.contains("expected NAME TOKEN")));
        let settings = TeleopSettings {
            listen: "127.0.0.1:0".parse().unwrap_or_else(|_| SocketAddr::from(([127, 0, 0, 1], 0))),
            websocket: None,
            operators: vec![("alice".into(), "0123456789abcdef".into())],
            directory: None,
            probe_period: Duration::from_secs(1),
            policy: ModePolicy::default(),
            max_operators: 1,
            auth_timeout: Duration::from_secs(5),
            idle_timeout: Duration::from_secs(60),
            delay: DelaySettings::default(),
            tls: None,
        };
        assert!(settings.check_token("alice", "0123456789abcdef"));
        assert!(!settings.check_token("alice", "0123456789abcdeF"));
        assert!(!settings.check_token("bob", "0123456789abcdef"));
        assert!(!settings.check_token("alice", "0123456789abcde"));
    }

    /// Ended sessions past the bound are dropped in the order they ended;
    /// open ones are never dropped, however early they connected.
    #[test]
    fn the_status_lists_every_open_session_and_the_newest_ended_ones() {
        let open = |reports: &mut SessionReports, session: u64| {
            reports.open.push(SessionReport { session, ..SessionReport::default() })
        };
        let extra = 5u64;
        let bound = MAX_ENDED_SESSIONS_LISTED as u64;
        let mut reports = SessionReports::default();
        // Session 0 stays open throughout; 1.. connect two at a time and
        // end in the opposite order.
        open(&mut reports, 0);
        for pair in 0..(bound + extra) / 2 {
            let (first, second) = (2 * pair + 1, 2 * pair + 2);
            open(&mut reports, first);
            open(&mut reports, second);
            reports.end(second, second as f64);
            reports.end(first, second as f64 + 0.5);
            assert!(reports.ended.len() <= MAX_ENDED_SESSIONS_LISTED);
        }
        reports.end(12345, 1.0);
        let ended = 2 * ((bound + extra) / 2);
        let (listed, earlier) = reports.listed();
        let sessions: Vec<u64> = listed.iter().map(|r| r.session).collect();
        let mut expected: Vec<u64> = (ended - bound + 1..=ended)
            .collect::<Vec<_>>()
            .chunks(2)
            .flat_map(|pair| pair.iter().rev().copied().collect::<Vec<_>>())
            .collect();
        expected.push(0);
        assert_eq!(sessions, expected);
        assert_eq!(earlier, ended - bound);
        assert!(listed[..MAX_ENDED_SESSIONS_LISTED].iter().all(|r| r.disconnected_at_s.is_some()));
        assert!(listed[MAX_ENDED_SESSIONS_LISTED].disconnected_at_s.is_none());
    }

    /// A network platform on a free loopback port, with a 100 ms fixed
    /// delay, and its clock.
    fn platform() -> (TeleopComponent, Clock) {
        let settings = TeleopSettings {
            listen: SocketAddr::from(([127, 0, 0, 1], 0)),
            websocket: None,
            operators: vec![("alice".into(), "0123456789abcdef".into())],
            directory: None,
            probe_period: Duration::from_secs(1),
            policy: ModePolicy::default(),
            max_operators: 4,
            auth_timeout: Duration::from_secs(5),
            idle_timeout: Duration::from_secs(60),
            delay: DelaySettings { fixed: Some(Duration::from_millis(100)), ..DelaySettings::default() },
            tls: None,
        };
        let clock = Clock::new();
        let around = Surroundings {
            robot: Arc::new(RunningRobot::new("test")),
            standings: Standings::default(),
            clock: clock.clone(),
            waker: Waker::default(),
            priority: PriorityCell::default(),
            locks: Locks::default(),
        };
        let teleop = TeleopComponent::start("teleop", around, settings).expect("the network platform starts");
        (teleop, clock)
    }

    /// A session whose `Disconnected` event is lost to a full queue is
    /// ended all the same once its connection is gone: its buffered command
    /// is never released, and its counts are kept.
    #[test]
    fn a_session_whose_end_was_lost_in_a_full_queue_is_ended_anyway() {
        let (mut teleop, clock) = platform();
        let ctx = teleop.context().clone();
        let mut out = Vec::new();
        let (notices, notice_rx) = tokio::sync::mpsc::channel(session::NOTICE_QUEUE);
        ctx.open_session(7, "127.0.0.1:1", notices);
        let command = ControlCommand::Vel { linear: 0.2, angular: 0.0 };
        let now = clock.now_ns();
        ctx.send(NetEvent::Command { session: 7, seq: 1, time_ms: 0, command, arrival_ns: now }).ok();
        teleop.poll(now, &mut out);
        assert_eq!(teleop.sessions.len(), 1);
        // A flood fills the queue; the session's end is then lost.
        for seq in 0..EVENT_QUEUE as u64 {
            let flood = NetEvent::Command { session: 99, seq, time_ms: 0, command, arrival_ns: now };
            assert!(ctx.send(flood).is_ok());
        }
        ctx.close_session(7, &None);
        drop(notice_rx);
        teleop.poll(now, &mut out);
        assert!(teleop.sessions.is_empty(), "the session is still open");
        // Its command, due 100 ms after it came, is never released.
        teleop.poll(now + 1_000_000_000, &mut out);
        assert!(out.is_empty(), "{out:?}");
        assert_eq!(teleop.finished.iter().map(|(id, s)| (*id, s.received)).collect::<Vec<_>>(), vec![(7, 1)]);
    }

    /// An operator changing modes over and over: the report keeps the
    /// newest changes, in order, and counts the rest.
    #[test]
    fn a_session_lists_only_its_newest_mode_changes() {
        let (teleop, _clock) = platform();
        let ctx = teleop.context().clone();
        let (notices, _notice_rx) = tokio::sync::mpsc::channel(session::NOTICE_QUEUE);
        ctx.open_session(3, "127.0.0.1:1", notices);
        let extra = 7;
        let modes = [Mode::Direct, Mode::Shared];
        for i in 0..MAX_MODE_CHANGES_LISTED + extra {
            let change = ModeChange {
                at_s: i as f64,
                from: Some(modes[(i + 1) % 2]),
                to: Some(modes[i % 2]),
                reason: "requested".into(),
            };
            ctx.mode_changed(3, change);
        }
        let status = teleop.status().map(|status| status.to_json()).unwrap_or_default();
        let session = &status["sessions"][0];
        let times: Vec<f64> =
            session["mode_changes"].as_array().into_iter().flatten().filter_map(|c| c["at_s"].as_f64()).collect();
        let newest: Vec<f64> = (extra..MAX_MODE_CHANGES_LISTED + extra).map(|i| i as f64).collect();
        assert_eq!(times, newest);
        assert_eq!(session["earlier_mode_changes"], extra as u64);
        assert_eq!(session["mode"], serde_json::json!(modes[(MAX_MODE_CHANGES_LISTED + extra - 1) % 2]));
    }
    fn orders() -> (tokio::sync::mpsc::Sender<SessionOrder>, tokio::sync::mpsc::Receiver<SessionOrder>) {
        tokio::sync::mpsc::channel(ORDER_QUEUE)
    }

    /// Every place taken: a newcomer gets none while everyone was active
    /// within `idle-timeout`; past it, the operator idle longest (pongs do
    /// not count: they never touch) is closed and told, and the newcomer
    /// takes the place. Time is passed in.
    #[test]
    fn an_operator_idle_past_the_timeout_gives_up_their_place_to_a_newcomer() {
        let (teleop, _clock) = platform();
        let ctx = teleop.context().clone();
        let max = ctx.settings.max_operators as u64;
        let idle = ctx.settings.idle_timeout;
        let t0 = tokio::time::Instant::now();
        let mut receivers = HashMap::new();
        for session in 1..=max {
            let (tx, rx) = orders();
            assert_eq!(ctx.claim_place(session, &format!("op{session}"), tx, t0), Ok(()));
            receivers.insert(session, rx);
        }
        // Session `max` was active a second later; the others half-way.
        ctx.touch(max, t0 + Duration::from_secs(1));
        for session in 2..max {
            ctx.touch(session, t0 + idle / 2);
        }
        let no_place = NoPlace { max: max as usize, idle_timeout: idle };
        let (tx, _rx) = orders();
        assert_eq!(ctx.claim_place(100, "late", tx, t0 + idle - Duration::from_millis(1)), Err(no_place));
        assert_eq!(ctx.operators_served(), max as usize);
        // Session 1 is the idlest past the timeout: it goes, told why.
        let (tx, _rx100) = orders();
        assert_eq!(ctx.claim_place(100, "bob", tx, t0 + idle), Ok(()));
        match receivers.get_mut(&1).map(|rx| rx.try_recv()) {
            Some(Ok(SessionOrder::Close(why))) => assert!(why.starts_with("your place went to bob: "), "{why}"),
            other => panic!("session 1 was not closed: {other:?}"),
        }
        // Then session `max` (idle 1 s less), then nobody.
        let (tx, _rx101) = orders();
        assert_eq!(ctx.claim_place(101, "carol", tx, t0 + idle + Duration::from_secs(1)), Ok(()));
        assert!(matches!(receivers.get_mut(&max).map(|rx| rx.try_recv()), Some(Ok(SessionOrder::Close(_)))));
        let (tx, _rx) = orders();
        assert!(ctx.claim_place(102, "dave", tx, t0 + idle + Duration::from_secs(2)).is_err());
        for session in 2..max {
            assert!(receivers.get_mut(&session).is_some_and(|rx| rx.try_recv().is_err()), "{session} was told");
        }
        assert_eq!(ctx.operators_served(), max as usize);
        // A session that ends gives its place back.
        ctx.close_session(2, &Some("op2".into()));
        let (tx, _rx) = orders();
        assert_eq!(ctx.claim_place(102, "dave", tx, t0 + idle + Duration::from_secs(2)), Ok(()));
    }

    /// The holder of control keeps it while active; idle past the timeout,
    /// the next operator's request takes it and the holder is told.
    #[test]
    fn an_idle_holder_loses_control_to_the_operator_who_asks() {
        let (teleop, _clock) = platform();
        let ctx = teleop.context().clone();
        let idle = ctx.settings.idle_timeout;
        let t0 = tokio::time::Instant::now();
        let (alice_tx, mut alice_rx) = orders();
        let (bob_tx, _bob_rx) = orders();
        assert_eq!(ctx.claim_place(1, "alice", alice_tx, t0), Ok(()));
        assert_eq!(ctx.claim_place(2, "bob", bob_tx, t0), Ok(()));
        assert_eq!(ctx.take_control(1, "alice", t0), Ok(()));
        assert_eq!(ctx.take_control(2, "bob", t0 + Duration::from_secs(10)), Err("alice".into()));
        ctx.touch(1, t0 + Duration::from_secs(20));
        let just_before = t0 + Duration::from_secs(20) + idle - Duration::from_millis(1);
        assert_eq!(ctx.take_control(2, "bob", just_before), Err("alice".into()));
        assert!(alice_rx.try_recv().is_err());
        assert_eq!(ctx.take_control(2, "bob", t0 + Duration::from_secs(20) + idle), Ok(()));
        assert!((ctx.holds_control(2), ctx.holds_control(1)) == (true, false));
        match alice_rx.try_recv() {
            Ok(SessionOrder::LoseControl(why)) => assert!(why.starts_with("control passed to bob: "), "{why}"),
            other => panic!("alice was not told: {other:?}"),
        }
    }

    /// Logins at once from many threads: exactly `max-operators` get a
    /// place, the rest none, and every place is given back at the end.
    #[test]
    fn concurrent_logins_never_take_more_places_than_there_are() {
        let (teleop, _clock) = platform();
        let ctx = teleop.context().clone();
        let now = tokio::time::Instant::now();
        for round in 0..50u64 {
            let threads: Vec<_> = (0..16u64)
                .map(|i| {
                    let ctx = ctx.clone();
                    std::thread::spawn(move || {
                        let (tx, rx) = orders();
                        let session = round * 100 + i;
                        ctx.claim_place(session, "op", tx, now).ok().map(|()| (session, rx))
                    })
                })
                .collect();
            let placed: Vec<_> = threads.into_iter().filter_map(|t| t.join().ok().flatten()).collect();
            assert_eq!(placed.len(), ctx.settings.max_operators, "round {round}");
            assert_eq!(ctx.operators_served(), ctx.settings.max_operators);
            for (session, _) in &placed {
                ctx.close_session(*session, &None);
            }
            assert_eq!(ctx.operators_served(), 0);
        }
    }
}
