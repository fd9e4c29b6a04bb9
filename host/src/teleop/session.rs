//! One operator's connection (TCP lines or WebSocket JSON): authentication,
//! the latency probe, the mode policy and its notices, and forwarding
//! commands to the control loop. Runs on the network runtime; talks to the
//! control loop only through bounded channels.

use std::collections::VecDeque;
use std::sync::Arc;
use std::sync::mpsc::TrySendError;
use std::time::Duration;

use tokio::io::{AsyncRead, AsyncReadExt, AsyncWrite, AsyncWriteExt};
use tokio::sync::mpsc;
use tokio::time::Instant;

use super::protocol::{self, ClientMessage, MAX_LINE_BYTES, ModeChange, ServerMessage};
use super::{NetEvent, ORDER_QUEUE, ServerContext, SessionOrder};
use crate::admission::Ticket;
use crate::runtime::DEFAULT_LOCK;
use crate::runtime::locks::unix_now_ms;
use crate::teleop::mode::{self, Mode};

/// Pings in one measurement round; the round's RTT is their median.
pub const PINGS_PER_ROUND: usize = 5;
/// A ping unanswered this long counts as this RTT (and ends the wait).
pub const PONG_TIMEOUT: Duration = Duration::from_secs(2);
/// Authentication attempts before the connection is closed: guessing tokens
/// must be slow.
pub const MAX_AUTH_FAILURES: u32 = 3;
/// Pause after a failed authentication.
pub const AUTH_FAILURE_DELAY: Duration = Duration::from_millis(300);
/// Notices waiting for a slow client; more are dropped.
pub const NOTICE_QUEUE: usize = 64;
/// Longest wait to hand a logged-in operator's client one message: a peer
/// that stops reading would otherwise hold its task, its place and its
/// socket for good. (Before the login every write is bounded by the
/// connection's `auth-timeout` instead.)
pub const SEND_TIMEOUT: Duration = Duration::from_secs(10);

/// A measurement round of the latency probe.
#[derive(Debug)]
struct Round {
    nonce: u64,
    sent_at: Instant,
    samples: Vec<Duration>,
}

/// The latency probe (the paper's constraint module): rounds of pings on
/// connect and then every `period`.
#[derive(Debug)]
pub struct Probe {
    period: Duration,
    round: Option<Round>,
    next_round_at: Instant,
    next_nonce: u64,
}

/// A finished measurement.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Measurement {
    pub rtt: Duration,
    pub jitter: Duration,
}

impl Probe {
    pub fn new(period: Duration, now: Instant) -> Probe {
        Probe { period, round: None, next_round_at: now, next_nonce: 1 }
    }

    /// When `on_timer` must next run.
    pub fn deadline(&self) -> Instant {
        self.round.as_ref().map_or(self.next_round_at, |r| r.sent_at + PONG_TIMEOUT)
    }

    fn ping(&mut self, now: Instant, samples: Vec<Duration>) -> ServerMessage {
        let nonce = self.next_nonce;
        self.next_nonce += 1;
        self.round = Some(Round { nonce, sent_at: now, samples });
        ServerMessage::Ping { nonce }
    }

    /// Starts a round when one is due; counts an unanswered ping as a
    /// timeout. Returns a ping to send and/or a finished measurement.
    pub fn on_timer(&mut self, now: Instant) -> (Option<ServerMessage>, Option<Measurement>) {
        match self.round.take() {
            None if now >= self.next_round_at => (Some(self.ping(now, Vec::new())), None),
            None => (None, None),
            Some(round) if now >= round.sent_at + PONG_TIMEOUT => {
                let mut samples = round.samples;
                samples.push(PONG_TIMEOUT);
                self.advance(now, samples)
            }
            Some(round) => {
                self.round = Some(round);
                (None, None)
            }
        }
    }

    /// A pong arrived. `Err` when no such ping is outstanding.
    pub(super) fn on_pong(
        &mut self,
        nonce: u64,
        now: Instant,
    ) -> Result<(Option<ServerMessage>, Option<Measurement>), String> {
        match self.round.take() {
            Some(round) if round.nonce == nonce => {
                let mut samples = round.samples;
                samples.push(now.duration_since(round.sent_at));
                Ok(self.advance(now, samples))
            }
            other => {
                self.round = other;
                Err(format!("no PING with nonce {nonce} is outstanding"))
            }
        }
    }

    fn advance(&mut self, now: Instant, samples: Vec<Duration>) -> (Option<ServerMessage>, Option<Measurement>) {
        if samples.len() < PINGS_PER_ROUND {
            return (Some(self.ping(now, samples)), None);
        }
        self.next_round_at = now + self.period;
        (None, Some(measure(&samples)))
    }
}

/// The median RTT and the mean change between successive RTTs.
pub fn measure(samples: &[Duration]) -> Measurement {
    let mut sorted = samples.to_vec();
    sorted.sort_unstable();
    let rtt = sorted.get(sorted.len() / 2).copied().unwrap_or_default();
    let changes: Vec<f64> = samples.windows(2).map(|w| (w[1].as_secs_f64() - w[0].as_secs_f64()).abs()).collect();
    let jitter = if changes.is_empty() { 0.0 } else { changes.iter().sum::<f64>() / changes.len() as f64 };
    Measurement { rtt, jitter: Duration::from_secs_f64(jitter) }
}

/// How a session's messages travel.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Framing {
    /// One text line per message (TCP).
    Lines,
    /// One JSON object per message (WebSocket).
    Json,
}

impl Framing {
    /// How a lock engaged or released over this framing is recorded.
    fn lock_how(self) -> &'static str {
        match self {
            Framing::Lines => "teleop",
            Framing::Json => "websocket",
        }
    }
}

/// Reads lines of at most [`MAX_LINE_BYTES`]; a longer line is reported and
/// skipped, never buffered whole.
pub struct LineReader<R> {
    reader: R,
    buffer: Vec<u8>,
    overlong: bool,
    ready: VecDeque<Result<String, String>>,
}

impl<R: AsyncRead + Unpin> LineReader<R> {
    pub fn new(reader: R) -> LineReader<R> {
        LineReader { reader, buffer: Vec::new(), overlong: false, ready: VecDeque::new() }
    }

    /// The next line (or why it was refused); `None` at end of stream.
    /// Cancel-safe: nothing is lost if the future is dropped.
    pub async fn next(&mut self) -> std::io::Result<Option<Result<String, String>>> {
        let mut chunk = [0u8; 1024];
        loop {
            if let Some(line) = self.ready.pop_front() {
                return Ok(Some(line));
            }
            let n = self.reader.read(&mut chunk).await?;
            if n == 0 {
                return Ok(None);
            }
            for &byte in &chunk[..n] {
                if byte == b'\n' {
                    let line = std::mem::take(&mut self.buffer);
                    if std::mem::take(&mut self.overlong) {
                        self.ready.push_back(Err(format!("line longer than {MAX_LINE_BYTES} bytes: ignored")));
                    } else {
                        self.ready
                            .push_back(String::from_utf8(line).map_err(|_| "line is not UTF-8: ignored".to_string()));
                    }
                } else if !self.overlong {
                    if self.buffer.len() >= MAX_LINE_BYTES {
                        self.buffer.clear();
                        self.overlong = true;
                    } else {
                        self.buffer.push(byte);
                    }
                }
            }
        }
    }
}

/// Everything a session knows about its operator.
/// What an operator who drove inside their reservation is told when it
/// ends.
pub const GRANT_ENDED: &str = "your reservation has ended: you may no longer drive; closing";

struct Session {
    id: u64,
    framing: Framing,
    operator: Option<String>,
    auth_failures: u32,
    mode: Option<Mode>,
    measurement: Option<Measurement>,
    probe: Probe,
    started: Instant,
    /// Its place among the unauthenticated connections, until it logs in.
    ticket: Option<Ticket>,
    /// When it must have logged in (from its accept, or its upgrade).
    auth_deadline: Instant,
    /// Where the host's orders to this session go (kept with its
    /// operator's place once it logs in).
    orders: mpsc::Sender<SessionOrder>,
    /// Its operator drives only by a grant (a reservation in effect,
    /// docs/lab.md), not by their role: the session ends with the grant.
    by_grant: bool,
}

/// A connection admitted among the unauthenticated ones.
pub struct Entry {
    pub id: u64,
    pub address: String,
    pub ticket: Ticket,
    /// Its login deadline: `auth-timeout` after it was accepted.
    pub deadline: Instant,
}

/// A session's deadline for one write: its login deadline until it has
/// logged in, then [`SEND_TIMEOUT`] from now.
fn send_deadline(session: &Session) -> Instant {
    match session.operator {
        None => session.auth_deadline,
        Some(_) => Instant::now() + SEND_TIMEOUT,
    }
}

/// Serves one line-protocol connection (plain TCP or TLS) until it
/// closes.
pub async fn serve_tcp<S>(stream: S, entry: Entry, ctx: Arc<ServerContext>)
where
    S: AsyncRead + AsyncWrite + Send + Unpin + 'static,
{
    let (read, write) = tokio::io::split(stream);
    let mut lines = LineReader::new(read);
    let mut transport = LineTransport { writer: write };
    let (notices, mut notice_rx) = mpsc::channel(NOTICE_QUEUE);
    let (orders, mut order_rx) = mpsc::channel(ORDER_QUEUE);
    let id = entry.id;
    ctx.open_session(id, &entry.address, notices);
    let mut session = Session::new(Framing::Lines, &ctx, entry, orders);
    let mut outgoing = Reply::Send(vec![ServerMessage::Hello { robot: ctx.robot.name() }]);
    loop {
        let (messages, close) = outgoing.split();
        let mut failed = false;
        for message in &messages {
            let sent = tokio::time::timeout_at(send_deadline(&session), transport.send(&session, message)).await;
            failed |= !matches!(sent, Ok(Ok(())));
        }
        if close || failed {
            break;
        }
        let deadline = if session.operator.is_some() { session.probe.deadline() } else { session.auth_deadline };
        outgoing = tokio::select! {
            line = lines.next() => match line {
                Ok(Some(Ok(text))) => session.handle(protocol::parse_line(&text), &ctx).await,
                Ok(Some(Err(why))) => Reply::Send(vec![ServerMessage::Error(why)]),
                Ok(None) | Err(_) => Reply::Close(Vec::new()),
            },
            Some(notice) = notice_rx.recv() => Reply::Send(vec![notice]),
            Some(order) = order_rx.recv() => session.obey(order, &ctx),
            () = tokio::time::sleep_until(deadline) => session.on_timer(&ctx),
        };
    }
    ctx.close_session(id, &session.operator);
}

/// Serves one WebSocket connection (JSON messages) until it closes.
pub async fn serve_websocket(mut socket: axum::extract::ws::WebSocket, entry: Entry, ctx: Arc<ServerContext>) {
    use axum::extract::ws::Message;
    let (notices, mut notice_rx) = mpsc::channel(NOTICE_QUEUE);
    let (orders, mut order_rx) = mpsc::channel(ORDER_QUEUE);
    let id = entry.id;
    ctx.open_session(id, &entry.address, notices);
    let mut session = Session::new(Framing::Json, &ctx, entry, orders);
    let mut outgoing = Reply::Send(vec![ServerMessage::Hello { robot: ctx.robot.name() }]);
    loop {
        let (messages, close) = outgoing.split();
        let mut failed = false;
        for message in &messages {
            let text = Message::Text(message.to_json().into());
            let sent = tokio::time::timeout_at(send_deadline(&session), socket.send(text)).await;
            failed |= !matches!(sent, Ok(Ok(())));
        }
        if close || failed {
            break;
        }
        let deadline = if session.operator.is_some() { session.probe.deadline() } else { session.auth_deadline };
        outgoing = tokio::select! {
            message = socket.recv() => match message {
                Some(Ok(Message::Text(text))) if text.len() <= MAX_LINE_BYTES => session.handle(protocol::parse_json(&text), &ctx).await,
                Some(Ok(Message::Text(_))) => Reply::Send(vec![ServerMessage::Error(format!("message longer than {MAX_LINE_BYTES} bytes: ignored"))]),
                Some(Ok(Message::Binary(_))) => Reply::Send(vec![ServerMessage::Error("binary messages are not part of the protocol: send JSON text".into())]),
                Some(Ok(_)) => Reply::Send(Vec::new()),
                Some(Err(_)) | None => Reply::Close(Vec::new()),
            },
            Some(notice) = notice_rx.recv() => Reply::Send(vec![notice]),
            Some(order) = order_rx.recv() => session.obey(order, &ctx),
            () = tokio::time::sleep_until(deadline) => session.on_timer(&ctx),
        };
    }
    ctx.close_session(id, &session.operator);
}

struct LineTransport<W> {
    writer: W,
}

impl<W: AsyncWrite + Unpin> LineTransport<W> {
    async fn send(&mut self, session: &Session, message: &ServerMessage) -> std::io::Result<()> {
        let mut text = match session.framing {
            Framing::Lines => message.to_line(),
            Framing::Json => message.to_json(),
        };
        text.push('\n');
        self.writer.write_all(text.as_bytes()).await
    }
}

enum Reply {
    Send(Vec<ServerMessage>),
    Close(Vec<ServerMessage>),
}

impl Reply {
    /// The messages to send, and whether to close afterwards.
    fn split(self) -> (Vec<ServerMessage>, bool) {
        match self {
            Reply::Send(messages) => (messages, false),
            Reply::Close(messages) => (messages, true),
        }
    }
}

impl Session {
    fn new(framing: Framing, ctx: &ServerContext, entry: Entry, orders: mpsc::Sender<SessionOrder>) -> Session {
        let now = Instant::now();
        Session {
            id: entry.id,
            framing,
            operator: None,
            auth_failures: 0,
            mode: None,
            measurement: None,
            probe: Probe::new(ctx.settings.probe_period, now),
            started: now,
            ticket: Some(entry.ticket),
            auth_deadline: entry.deadline,
            orders,
            by_grant: false,
        }
    }

    /// The close of a session whose operator drove by a grant that has
    /// ended (their reservation is over or was cancelled): checked at each
    /// message and probe, so their commands stop at once.
    fn grant_ended(&self, ctx: &ServerContext) -> Option<Reply> {
        let operator = self.operator.as_deref().filter(|_| self.by_grant)?;
        if ctx.settings.grant_holds(operator) {
            return None;
        }
        tracing::info!(operator = %operator, session = self.id, "the operator's reservation ended: closing");
        Some(Reply::Close(vec![ServerMessage::Error(GRANT_ENDED.into())]))
    }

    /// Carries out what the host ordered from outside the session.
    fn obey(&mut self, order: SessionOrder, ctx: &ServerContext) -> Reply {
        match order {
            SessionOrder::Close(why) => Reply::Close(vec![ServerMessage::Error(why)]),
            SessionOrder::LoseControl(why) => {
                if self.mode.is_some() {
                    self.set_mode(None, "control passed to another operator while idle", ctx);
                }
                Reply::Send(vec![ServerMessage::Error(why)])
            }
        }
    }

    async fn handle(&mut self, message: Result<ClientMessage, String>, ctx: &ServerContext) -> Reply {
        let message = match message {
            Ok(message) => message,
            Err(why) => {
                ctx.count_malformed(self.id);
                return Reply::Send(vec![ServerMessage::Error(why)]);
            }
        };
        let now = Instant::now();
        if let Some(ended) = self.grant_ended(ctx) {
            return ended;
        }
        if self.operator.is_some() && !matches!(message, ClientMessage::Pong { .. }) {
            ctx.touch(self.id, now);
        }
        match message {
            ClientMessage::Quit => Reply::Close(vec![ServerMessage::Ok("bye".into())]),
            ClientMessage::Pong { nonce } => match self.probe.on_pong(nonce, now) {
                Ok((ping, measurement)) => Reply::Send(self.after_probe(ping, measurement, ctx)),
                Err(why) => Reply::Send(vec![ServerMessage::Error(why)]),
            },
            ClientMessage::Auth { name, token } => {
                if let Some(operator) = &self.operator {
                    return Reply::Send(vec![ServerMessage::Error(format!("already authenticated as {operator}"))]);
                }
                if ctx.settings.check_token(&name, &token) {
                    if let Err(no_place) = ctx.claim_place(self.id, &name, self.orders.clone(), now) {
                        tracing::info!(operator = %name, session = self.id, "operator refused: {no_place}");
                        return Reply::Close(vec![ServerMessage::Error(no_place.to_string())]);
                    }
                    // A logged-in operator leaves the unauthenticated pool.
                    self.ticket = None;
                    self.by_grant = ctx.settings.drives_by_grant(&name);
                    self.operator = Some(name.clone());
                    ctx.authenticated(self.id, &name);
                    tracing::info!(operator = %name, session = self.id, "operator authenticated");
                    let (ping, _) = self.probe.on_timer(now);
                    let mut replies =
                        vec![ServerMessage::Ok(format!("authenticated as {name}; measuring the round-trip time"))];
                    replies.extend(ping);
                    return Reply::Send(replies);
                }
                self.auth_failures += 1;
                tokio::time::sleep(AUTH_FAILURE_DELAY).await;
                let error = ServerMessage::Error("authentication failed".into());
                if self.auth_failures >= MAX_AUTH_FAILURES {
                    tracing::warn!(session = self.id, "closing after {} failed authentications", self.auth_failures);
                    Reply::Close(vec![error, ServerMessage::Error("too many failed attempts: closing".into())])
                } else {
                    Reply::Send(vec![error])
                }
            }
            _ if self.operator.is_none() => {
                Reply::Send(vec![ServerMessage::Error("authenticate first: AUTH <name> <token>".into())])
            }
            ClientMessage::Mode(mode) => Reply::Send(vec![self.request_mode(mode, ctx)]),
            ClientMessage::Estop => {
                let operator = self.operator.clone().unwrap_or_default();
                let how = self.framing.lock_how();
                let locks = &ctx.locks;
                if locks.engage(DEFAULT_LOCK, &operator, how, unix_now_ms()) {
                    tracing::warn!(operator = %operator, session = self.id, "emergency stop engaged over {how}");
                    Reply::Send(vec![ServerMessage::Ok(format!("{DEFAULT_LOCK} engaged: the motors are stopped"))])
                } else {
                    let by = locks.engaged().into_iter().find(|e| e.lock == DEFAULT_LOCK).map(|e| e.by);
                    Reply::Send(vec![ServerMessage::Ok(format!(
                        "{DEFAULT_LOCK} is engaged already (by {}): the motors are stopped",
                        by.unwrap_or_default()
                    ))])
                }
            }
            ClientMessage::Release { lock } => {
                // Only users who may drive authenticate here, so an
                // authenticated operator may release (docs/estop.md).
                let operator = self.operator.clone().unwrap_or_default();
                let released = ctx.locks.release(lock.as_deref(), &operator, self.framing.lock_how(), unix_now_ms());
                if released.is_empty() {
                    return Reply::Send(vec![ServerMessage::Error(match lock {
                        Some(name) => format!("lock '{}' is not engaged", crate::contract::clip(&name)),
                        None => "no lock is engaged".into(),
                    })]);
                }
                let said: Vec<String> =
                    released.iter().map(|(name, ms)| format!("{name} after {:.1} s", *ms as f64 / 1000.0)).collect();
                tracing::warn!(operator = %operator, session = self.id, "released {}", said.join(", "));
                Reply::Send(vec![ServerMessage::Ok(format!("released {}", said.join(", ")))])
            }
            ClientMessage::Cmd { seq, time_ms, command } => {
                if self.mode.is_some() && !ctx.holds_control(self.id) {
                    // Control passed on while this session was idle, and
                    // its order has not been read yet.
                    self.set_mode(None, "control passed to another operator while idle", ctx);
                }
                if self.mode.is_none() {
                    return Reply::Send(vec![ServerMessage::Error(
                        "ask for a control mode first: MODE direct|shared|supervisory".into(),
                    )]);
                }
                let event =
                    NetEvent::Command { session: self.id, seq, time_ms, command, arrival_ns: ctx.clock.now_ns() };
                match ctx.send(event) {
                    Ok(()) => Reply::Send(Vec::new()),
                    Err(TrySendError::Full(_)) => {
                        Reply::Send(vec![ServerMessage::Dropped { seq, reason: "the host is busy".into() }])
                    }
                    Err(TrySendError::Disconnected(_)) => {
                        Reply::Close(vec![ServerMessage::Error("the robot is shutting down".into())])
                    }
                }
            }
        }
    }

    fn on_timer(&mut self, ctx: &ServerContext) -> Reply {
        if self.operator.is_none() {
            return Reply::Close(vec![ServerMessage::Error("no authentication in time: closing".into())]);
        }
        if let Some(ended) = self.grant_ended(ctx) {
            return ended;
        }
        let (ping, measurement) = self.probe.on_timer(Instant::now());
        Reply::Send(self.after_probe(ping, measurement, ctx))
    }

    /// Sends the next ping; on a finished measurement, reports it and moves
    /// the operator to an allowed mode if theirs no longer is.
    fn after_probe(
        &mut self,
        ping: Option<ServerMessage>,
        measurement: Option<Measurement>,
        ctx: &ServerContext,
    ) -> Vec<ServerMessage> {
        let mut out: Vec<ServerMessage> = ping.into_iter().collect();
        let Some(m) = measurement else { return out };
        self.measurement = Some(m);
        let allowed = ctx.settings.policy.allowed(m.rtt);
        ctx.measured(self.id, m);
        out.push(ServerMessage::Rtt { rtt_ms: ms(m.rtt), jitter_ms: ms(m.jitter), allowed: allowed.clone() });
        if let Some(current) = self.mode.filter(|mode| !allowed.contains(mode)) {
            let best = ctx.settings.policy.best(m.rtt);
            let reason = format!("downgraded from {current}: rtt {:.1} ms allows {}", ms(m.rtt), mode::list(&allowed));
            tracing::info!(session = self.id, "operator {}", reason);
            self.set_mode(Some(best), &reason, ctx);
            out.push(ServerMessage::Mode { mode: best, reason });
        }
        out
    }

    fn request_mode(&mut self, mode: Mode, ctx: &ServerContext) -> ServerMessage {
        let Some(m) = self.measurement else {
            return ServerMessage::Error("no round-trip measurement yet: wait for the RTT line".into());
        };
        let allowed = ctx.settings.policy.allowed(m.rtt);
        if !allowed.contains(&mode) {
            return ServerMessage::Error(format!(
                "mode {mode} is not allowed: measured rtt {:.1} ms allows {}",
                ms(m.rtt),
                mode::list(&allowed)
            ));
        }
        if let Err(holder) = ctx.take_control(self.id, self.operator.as_deref().unwrap_or(""), Instant::now()) {
            return ServerMessage::Error(format!("control is held by {holder}"));
        }
        let reason = format!("granted: rtt {:.1} ms allows {}", ms(m.rtt), mode::list(&allowed));
        self.set_mode(Some(mode), "requested", ctx);
        ServerMessage::Mode { mode, reason }
    }

    fn set_mode(&mut self, mode: Option<Mode>, reason: &str, ctx: &ServerContext) {
        let change = ModeChange {
            at_s: self.started.elapsed().as_secs_f64(),
            from: self.mode,
            to: mode,
            reason: reason.to_string(),
        };
        self.mode = mode;
        ctx.mode_changed(self.id, change);
        let _ = ctx.send(NetEvent::Mode { session: self.id, mode });
    }
}

fn ms(d: Duration) -> f64 {
    d.as_secs_f64() * 1e3
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_round_takes_the_median_and_the_mean_change() {
        let ms = Duration::from_millis;
        let m = measure(&[ms(50), ms(52), ms(48), ms(200), ms(51)]);
        assert_eq!(m.rtt, ms(51));
        // |52-50| + |48-52| + |200-48| + |51-200| = 2 + 4 + 152 + 149 = 307; / 4.
        assert!((m.jitter.as_secs_f64() * 1e3 - 76.75).abs() < 1e-6);
    }

    #[tokio::test(start_paused = true)]
    async fn the_probe_pings_on_connect_then_every_period_and_times_out_lost_pongs() {
        let start = Instant::now();
        let mut probe = Probe::new(Duration::from_secs(60), start);
        let (ping, _) = probe.on_timer(start);
        let mut nonce = match ping {
            Some(ServerMessage::Ping { nonce }) => nonce,
            other => panic!("{other:?}"),
        };
        let mut now = start;
        for i in 0..PINGS_PER_ROUND {
            now += Duration::from_millis(40);
            let (ping, measurement) = match probe.on_pong(nonce, now) {
                Ok(r) => r,
                Err(e) => panic!("{e}"),
            };
            if i + 1 < PINGS_PER_ROUND {
                nonce = match ping {
                    Some(ServerMessage::Ping { nonce }) => nonce,
                    other => panic!("{other:?}"),
                };
            } else {
                assert_eq!(measurement.map(|m| m.rtt), Some(Duration::from_millis(40)));
            }
        }
        assert_eq!(probe.deadline(), now + Duration::from_secs(60));
        assert!(probe.on_pong(999, now).is_err());
        // Next round: a lost pong counts as the timeout.
        let (ping, _) = probe.on_timer(now + Duration::from_secs(60));
        assert!(matches!(ping, Some(ServerMessage::Ping { .. })));
        assert_eq!(probe.deadline(), now + Duration::from_secs(60) + PONG_TIMEOUT);
    }
}
