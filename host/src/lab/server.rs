//! The lab server's side of a lab of several robots (docs/lab.md, "Several
//! robots"): `subsume lab serve`. It runs no robot. It keeps the lab's
//! users, queue and results in its store as a robot's lab does ([`Lab`]
//! with [`super::LabRole::Server`]: the same records, states, checks and
//! preflights), learns its robots from their liveliness tokens
//! ([`Fleet`]), and, in place of a robot's runner, dispatches: the first
//! queued experiment goes to the first free robot that fits its target.
//!
//! - **Robots.** A robot's token says its name, state and profile; the
//!   newest token of a robot wins while its old one is undeclared. A robot
//!   is online while it has a token and its signed statuses keep coming
//!   (each fresh and newer than the last, within
//!   [`wire::STATUS_SILENCE_PERIODS`] of its period): a token someone
//!   re-declares keeps no dead robot listed. Every request names its
//!   robot, a time and a fresh nonce, and only a reply bound to it is
//!   taken ([`transfer::Asker`]). The first time a baseline hash is seen, the
//!   lab fetches that baseline (its robot file, its components, the files
//!   it names, secrets replaced by stand-ins) and stores it as a set: what
//!   researchers stage against and experiments are checked against.
//! - **Dispatch.** The set as staged, signed; the robot fetches the blobs
//!   it lacks from this server (`subsume/lab/LAB/blobs`), checks the set
//!   again and answers `started` or `refused` with its reasons. A refusal
//!   puts the experiment back in the queue once; the second ends it
//!   `refused`.
//! - **Ends.** When a robot's token no longer says it runs the
//!   experiment, the lab fetches its results (the robot's final state and
//!   cause, its recording, report and log) into the experiment's folder.
//! - **Faults.** A robot whose token drops while it runs an experiment:
//!   `aborted: robot lost` at once, and its results are fetched when it
//!   comes back. A lab server restarted (even after `kill -9`) keeps every
//!   record and relearns each robot's state from its token, giving them
//!   [`FleetOptions::relearn`] to come back first.
//!
//! Lock order: the lab's book, then the fleet's robots; Zenoh's callbacks
//! take only the robots, then wake the dispatcher.

use std::collections::{BTreeMap, BTreeSet};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard, Weak};
use std::time::{Duration, Instant};

use serde::Serialize;
use thiserror::Error;
use zenoh::Wait;

use super::queue::{self, Seat, Unplaced};
use super::transfer::{self, Asker, Gate, TransferError};
use super::wire::{
    self, Ack, Asked, Baseline, BaselineRequest, BlobRef, Dispatch, DispatchOutcome, DispatchReply, Estop, FileRequest,
    FileSource, Heartbeat, Keys, LabKey, Live, LiveRequest, Op, Profile, RefusalTally, Results, ResultsRequest,
    RobotState, SetManifest, Status, Stop, TokenBody, WIRE_VERSION,
};
use super::{Book, Lab, LabError, bundle};
use crate::bridge::session::{self, SessionSettings, Shared};
use crate::deploy::utc_time;
use crate::runtime::locks::unix_now_ms;
use crate::store::experiments::{ExperimentRecord, ExperimentState, Target};
use crate::store::users::Principal;
use crate::store::{Outcome, Store};

/// How often the lab server says it is there.
pub const HEARTBEAT_PERIOD: Duration = Duration::from_millis(500);

/// How long the dispatcher waits for nothing before it looks again.
pub const POLL: Duration = Duration::from_millis(50);

/// How long a robot may take to answer a dispatch, by default: it fetches
/// the set's blobs, checks the set and starts it
/// (`robot_link::START_WAIT`). `lab serve --dispatch-timeout`.
pub const DISPATCH_TIMEOUT: Duration = Duration::from_secs(150);

/// The shortest and longest `--dispatch-timeout`: shorter, a robot that
/// fetches a large set cannot answer in time; longer, a robot that lost
/// the answer holds an experiment for as long.
pub const MIN_DISPATCH_TIMEOUT: Duration = Duration::from_secs(1);
pub const MAX_DISPATCH_TIMEOUT: Duration = Duration::from_secs(600);

/// The start-by time a dispatch carries is this part of the dispatch
/// timeout before the lab stops waiting: the robot's answer has that long
/// to come back.
const ANSWER_MARGIN_DIVISOR: u32 = 5;

/// How long the lab gives its robots to show their tokens after it
/// starts, before an experiment whose robot has none is lost, by default.
pub const DEFAULT_RELEARN: Duration = Duration::from_secs(15);

/// How long after a failed fetch of results or a baseline the lab tries
/// again.
pub const RETRY: Duration = Duration::from_secs(2);

/// Most robots one lab server tracks: a peer declaring tokens under
/// made-up names cannot grow its memory without bound.
pub const MAX_ROBOTS: usize = 1024;

/// Why the lab server could not start.
#[derive(Debug, Error)]
pub enum ServerError {
    #[error(transparent)]
    Session(#[from] session::SessionError),
    #[error(transparent)]
    Transfer(#[from] TransferError),
    #[error("{0}")]
    Start(String),
}

/// What starting the lab server's link needs.
#[derive(Clone, Debug)]
pub struct FleetOptions {
    pub key: LabKey,
    pub session: SessionSettings,
    /// How long robots have to show their tokens after a start.
    pub relearn: Duration,
    /// How long the lab waits for a robot's answer to a dispatch.
    pub dispatch_timeout: Duration,
}

/// One robot as the lab knows it.
#[derive(Debug, Default)]
struct Robot {
    /// Its live tokens (key -> body): the newest is its state.
    tokens: BTreeMap<String, TokenBody>,
    current: Option<TokenBody>,
    /// When its current token came.
    token_at: Option<Instant>,
    status: Option<(Status, Instant)>,
    /// When it was last seen with a token (ms since the Unix epoch).
    seen_ms: u64,
    /// The experiment being dispatched to it.
    dispatching: Option<u64>,
    /// Experiments it accepted, and when (an end is concluded only from a
    /// token newer than that).
    accepted: BTreeMap<u64, Instant>,
    fetching: bool,
    retry_at: Option<Instant>,
    /// Experiments a stop was sent to it for.
    stops_sent: BTreeSet<u64>,
    /// Experiments whose dispatch it did not answer, being withdrawn now.
    withdrawing: BTreeSet<u64>,
    fetching_baseline: bool,
    baseline_error: Option<String>,
    /// Online at the last plan: going offline after it is told once
    /// (`robot.lost`).
    told_online: bool,
}

impl Robot {
    /// It has a token, and its last fresh signed status came within its
    /// silence limit ([`Status::silence_ms`]).
    fn online(&self) -> bool {
        self.online_at(Instant::now())
    }

    fn online_at(&self, now: Instant) -> bool {
        self.current.is_some()
            && self.status.as_ref().is_some_and(|(status, at)| {
                now.saturating_duration_since(*at) <= Duration::from_millis(status.silence_ms())
            })
    }

    fn may_retry(&self) -> bool {
        self.retry_at.is_none_or(|at| Instant::now() >= at)
    }
}

/// A robot as the portal lists it.
#[derive(Clone, Debug, Serialize, schemars::JsonSchema)]
pub struct RobotView {
    pub name: String,
    /// `idle`, `running`, `stopped`, `maintenance`, or `lost`.
    pub state: String,
    pub online: bool,
    /// The lab's experiment it runs.
    pub experiment: Option<u64>,
    pub ends_unix_ms: Option<u64>,
    pub time_left_s: Option<f64>,
    pub stopped_by: Option<String>,
    pub locks: Vec<String>,
    pub profile: Profile,
    pub max_duration_s: f64,
    /// The set its baseline is stored as here, once fetched.
    pub baseline_set: Option<u64>,
    pub baseline_error: Option<String>,
    pub last_seen_unix_ms: u64,
}

/// Counters of the lab's link (the benchmark reads them; the log names
/// the refused).
#[derive(Debug, Default)]
pub struct LinkCounters {
    pub statuses: AtomicU64,
    pub tokens: AtomicU64,
    /// Tokens and statuses not signed with this lab's key (another lab,
    /// or an impostor), ignored.
    pub foreign: AtomicU64,
    /// Signed statuses too old, too new, or not newer than the robot's
    /// last (replayed), ignored.
    pub stale_statuses: AtomicU64,
    /// Replies to the lab's requests skipped: unsigned, refused, or bound
    /// to another request or robot.
    pub skipped_replies: AtomicU64,
}

/// The link's counters and robots at one moment (for /metrics).
#[derive(Clone, Copy, Debug, Default)]
pub struct LinkFigures {
    pub statuses: u64,
    pub tokens: u64,
    pub foreign: u64,
    pub stale_statuses: u64,
    pub skipped_replies: u64,
    /// Requests this server's queryable refused.
    pub refused: u64,
    /// Requests the robots refused, as their statuses say.
    pub robots_refused: u64,
    /// Robots tracked, and those a live token shows.
    pub known: usize,
    pub online: usize,
}

impl LinkFigures {
    /// The refusals' metric families (docs/lab.md, "What holds against a
    /// peer without the secret").
    pub fn refusal_families(&self) -> Vec<crate::runtime::Family> {
        use crate::runtime::{Family, MetricKind};
        vec![
            Family::new(
                "subsume_lab_refused_requests",
                "lab requests refused (not signed, stale, replayed, for another robot, busy): by the robots, as their statuses say, and by this server",
                MetricKind::Counter,
            )
            .counter(vec![("by", "robots".into())], self.robots_refused)
            .counter(vec![("by", "server".into())], self.refused),
            Family::new(
                "subsume_lab_skipped_replies",
                "replies to the lab server's requests skipped: unsigned, refused, or bound to another request or robot",
                MetricKind::Counter,
            )
            .counter(vec![], self.skipped_replies),
            Family::new(
                "subsume_lab_stale_statuses",
                "signed robot statuses ignored: too old, too new, or not newer than the robot's last (replayed)",
                MetricKind::Counter,
            )
            .counter(vec![], self.stale_statuses),
        ]
    }
}

/// The lab server's robots and its Zenoh side.
pub struct Fleet {
    key: LabKey,
    keys: Keys,
    shared: Arc<Shared>,
    store: Arc<Store>,
    started: Instant,
    relearn: Duration,
    dispatch_timeout: Duration,
    robots: Mutex<BTreeMap<String, Robot>>,
    lab: Mutex<Weak<Lab>>,
    pub counters: LinkCounters,
    /// Requests for blobs refused.
    refusals: Arc<Mutex<RefusalTally>>,
    stopping: Arc<AtomicBool>,
    threads: Mutex<Vec<std::thread::JoinHandle<()>>>,
    subscribers: Mutex<Vec<zenoh::pubsub::Subscriber<()>>>,
    _token: Mutex<Option<zenoh::liveliness::LivelinessToken>>,
}

impl std::fmt::Debug for Fleet {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Fleet").field("lab", &self.key.lab()).field("session", &self.shared.id).finish_non_exhaustive()
    }
}

fn lock<T>(mutex: &Mutex<T>) -> MutexGuard<'_, T> {
    mutex.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
}

impl Fleet {
    /// Opens the lab's session: watches the robots' tokens and statuses,
    /// serves the sets' blobs to the robots, says it is there.
    pub fn start(store: Arc<Store>, options: FleetOptions) -> Result<Arc<Fleet>, ServerError> {
        let shared = session::session(&options.session)?;
        let fleet = Arc::new(Fleet {
            keys: Keys::new(&options.key),
            key: options.key,
            shared,
            store,
            started: Instant::now(),
            relearn: options.relearn,
            dispatch_timeout: options.dispatch_timeout.clamp(MIN_DISPATCH_TIMEOUT, MAX_DISPATCH_TIMEOUT),
            robots: Mutex::new(BTreeMap::new()),
            lab: Mutex::new(Weak::new()),
            counters: LinkCounters::default(),
            refusals: Arc::new(Mutex::new(RefusalTally::default())),
            stopping: Arc::new(AtomicBool::new(false)),
            threads: Mutex::new(Vec::new()),
            subscribers: Mutex::new(Vec::new()),
            _token: Mutex::new(None),
        });
        let zenoh = |e: zenoh::Error| ServerError::Start(format!("zenoh: {e}"));
        let weak = Arc::downgrade(&fleet);
        let tokens = fleet
            .shared
            .session
            .liveliness()
            .declare_subscriber(fleet.keys.robot_tokens())
            .history(true)
            .callback(move |sample: zenoh::sample::Sample| {
                if let Some(fleet) = weak.upgrade() {
                    let put = sample.kind() == zenoh::sample::SampleKind::Put;
                    fleet.token_event(sample.key_expr().as_str(), put);
                }
            })
            .wait()
            .map_err(zenoh)?;
        let weak = Arc::downgrade(&fleet);
        let statuses = fleet
            .shared
            .session
            .declare_subscriber(fleet.keys.statuses())
            .callback(move |sample: zenoh::sample::Sample| {
                if let Some(fleet) = weak.upgrade() {
                    fleet.status_event(&sample.payload().to_bytes());
                }
            })
            .wait()
            .map_err(zenoh)?;
        *lock(&fleet.subscribers) = vec![tokens, statuses];
        let token = fleet.shared.session.liveliness().declare_token(fleet.keys.server_token(&fleet.shared.id)).wait();
        *lock(&fleet._token) = Some(token.map_err(zenoh)?);
        let weak = Arc::downgrade(&fleet);
        let gate = Gate {
            key: fleet.key.clone(),
            me: wire::SERVER_TARGET.to_string(),
            max_bytes: super::robot_link::MAX_SMALL_REQUEST_BYTES,
            refusals: fleet.refusals.clone(),
        };
        let blobs = transfer::serve(
            fleet.shared.clone(),
            fleet.keys.blobs(),
            "lab-blobs",
            fleet.stopping.clone(),
            gate,
            move |request: FileRequest, re| weak.upgrade().map(|f| f.serve_blob(&request, re)).unwrap_or_default(),
        )?;
        let beating = fleet.clone();
        let heartbeat = std::thread::Builder::new()
            .name("lab-heartbeat".into())
            .spawn(move || beating.heartbeat())
            .map_err(|e| ServerError::Start(format!("cannot start the heartbeat: {e}")))?;
        lock(&fleet.threads).extend([blobs, heartbeat]);
        tracing::info!("lab '{}' serves its robots (zenoh session {})", fleet.key.lab(), fleet.shared.id);
        Ok(fleet)
    }

    /// Stops the link's threads.
    pub fn shut_down(&self) {
        self.stopping.store(true, Ordering::Release);
        for thread in std::mem::take(&mut *lock(&self.threads)) {
            let _ = thread.join();
        }
        lock(&self.subscribers).clear();
    }

    /// The link's counters and how many robots it tracks.
    pub fn link_figures(&self) -> LinkFigures {
        let refused = lock(&self.refusals).sum();
        let robots = lock(&self.robots);
        LinkFigures {
            statuses: self.counters.statuses.load(Ordering::Relaxed),
            tokens: self.counters.tokens.load(Ordering::Relaxed),
            foreign: self.counters.foreign.load(Ordering::Relaxed),
            stale_statuses: self.counters.stale_statuses.load(Ordering::Relaxed),
            skipped_replies: self.counters.skipped_replies.load(Ordering::Relaxed),
            refused,
            robots_refused: robots.values().filter_map(|r| r.status.as_ref()).map(|(s, _)| s.refused).sum(),
            known: robots.len(),
            online: robots.values().filter(|r| r.online()).count(),
        }
    }

    pub fn lab_name(&self) -> &str {
        self.key.lab()
    }

    /// Who asks the robots: this server, counting the replies it skips.
    fn asker(&self) -> Asker<'_> {
        Asker { shared: &self.shared, key: &self.key, skipped: &self.counters.skipped_replies }
    }

    fn wake(&self) {
        if let Some(lab) = lock(&self.lab).upgrade() {
            lab.notify();
        }
    }

    fn heartbeat(&self) {
        let publisher = match self.shared.session.declare_publisher(self.keys.heartbeat()).wait() {
            Ok(publisher) => publisher,
            Err(e) => return tracing::error!("the lab's heartbeat cannot be published: {e}"),
        };
        while !self.stopping.load(Ordering::Acquire) {
            let beat = Heartbeat { v: WIRE_VERSION, server: self.shared.id.clone(), at_unix_ms: unix_now_ms() };
            if let Err(e) = publisher.put(self.key.seal(&beat, &[])).wait() {
                tracing::debug!("a heartbeat was not published: {e}");
            }
            std::thread::sleep(HEARTBEAT_PERIOD);
        }
    }

    fn token_event(&self, key: &str, put: bool) {
        let token = match self.key.read_token(key) {
            Ok(token) => token,
            Err(e) => {
                if self.counters.foreign.fetch_add(1, Ordering::Relaxed) < 10 {
                    tracing::warn!("lab '{}': a robot token was ignored: {e}", self.key.lab());
                }
                return;
            }
        };
        self.counters.tokens.fetch_add(1, Ordering::Relaxed);
        let mut robots = lock(&self.robots);
        if !robots.contains_key(&token.name) && robots.len() >= MAX_ROBOTS {
            tracing::warn!("lab '{}' tracks {MAX_ROBOTS} robots already: '{}' ignored", self.key.lab(), token.name);
            return;
        }
        let name = token.name.clone();
        let robot = robots.entry(name.clone()).or_default();
        if put {
            robot.tokens.insert(key.to_string(), token);
        } else {
            robot.tokens.remove(key);
        }
        let newest = robot.tokens.values().max_by_key(|t| (t.boot_ms, t.seq)).cloned();
        let changed = newest != robot.current;
        let was_online = robot.online();
        robot.current = newest;
        if changed {
            robot.token_at = Some(Instant::now());
        }
        if robot.online() {
            robot.seen_ms = unix_now_ms();
        }
        match (&robot.current, was_online) {
            (Some(t), _) if changed => tracing::info!("lab '{}': robot '{name}' is {}", self.key.lab(), t.state.word()),
            (None, true) => tracing::warn!("lab '{}': robot '{name}' is lost (its token went)", self.key.lab()),
            _ => {}
        }
        drop(robots);
        self.wake();
    }

    fn status_event(&self, bytes: &[u8]) {
        let status = match self.key.open::<Status>(bytes) {
            Ok((status, _)) => status,
            Err(_) => {
                self.counters.foreign.fetch_add(1, Ordering::Relaxed);
                return;
            }
        };
        // Fresh, and newer than the robot's last: a replayed status keeps
        // no robot online.
        if wire::fresh(status.at_unix_ms, unix_now_ms()).is_err() {
            self.counters.stale_statuses.fetch_add(1, Ordering::Relaxed);
            return;
        }
        let mut robots = lock(&self.robots);
        if !robots.contains_key(&status.name) && robots.len() >= MAX_ROBOTS {
            return;
        }
        let robot = robots.entry(status.name.clone()).or_default();
        if robot.status.as_ref().is_some_and(|(last, _)| last.at_unix_ms >= status.at_unix_ms) {
            self.counters.stale_statuses.fetch_add(1, Ordering::Relaxed);
            return;
        }
        self.counters.statuses.fetch_add(1, Ordering::Relaxed);
        let was_online = robot.online();
        robot.status = Some((status, Instant::now()));
        if !was_online && robot.online() {
            drop(robots);
            self.wake();
        }
    }

    /// A chunk of a blob a robot asks for: the blobs of this store only.
    fn serve_blob(&self, request: &FileRequest, re: wire::Answered) -> Vec<u8> {
        let path = match &request.source {
            FileSource::Blob { sha256 } => Some(self.store.blob_path(sha256)).filter(|p| p.is_file()),
            _ => None,
        };
        transfer::chunk_of(&self.key, re, path.as_deref(), request)
    }

    /// Every robot the lab knows, as the portal lists them, with the set
    /// each one's baseline is stored as (`baselines`: the lab's).
    pub fn robots_with(&self, now_ms: u64, baselines: &BTreeMap<String, u64>) -> Vec<RobotView> {
        let robots = lock(&self.robots);
        robots
            .iter()
            .filter_map(|(name, robot)| {
                let token = robot.current.clone().or_else(|| robot.tokens.values().next().cloned());
                let (profile, max_duration_s) = match &robot.current {
                    Some(t) => (t.profile.clone(), t.max_duration_s),
                    None => (token.as_ref()?.profile.clone(), token.as_ref()?.max_duration_s),
                };
                let status = robot.status.as_ref().map(|(s, _)| s);
                let (state, experiment, stopped_by) = match robot.current.as_ref().filter(|_| robot.online()) {
                    None => ("lost".to_string(), None, None),
                    Some(t) => match &t.state {
                        RobotState::Running { experiment } => ("running".into(), Some(*experiment), None),
                        RobotState::Stopped { by } => ("stopped".into(), None, Some(by.clone())),
                        other => (other.word(), None, None),
                    },
                };
                let ends = status.filter(|_| experiment.is_some()).and_then(|s| s.ends_unix_ms);
                Some(RobotView {
                    name: name.clone(),
                    state,
                    online: robot.online(),
                    experiment,
                    ends_unix_ms: ends,
                    time_left_s: ends.map(|e| e.saturating_sub(now_ms) as f64 / 1000.0),
                    stopped_by,
                    locks: status.map(|s| s.locks.clone()).unwrap_or_default(),
                    baseline_set: baselines.get(&profile.baseline).copied(),
                    profile,
                    max_duration_s,
                    baseline_error: robot.baseline_error.clone(),
                    last_seen_unix_ms: robot.seen_ms,
                })
            })
            .collect()
    }

    /// Every robot in service as the ETAs see it at `now_ms`: online and
    /// idle (free now) or running an experiment (free at its end, as its
    /// signed status says). Robots lost, stopped or in maintenance are
    /// not counted: nobody can say when they come back.
    pub fn freeing(&self, now_ms: u64) -> Vec<queue::Freeing> {
        let robots = lock(&self.robots);
        robots
            .iter()
            .filter_map(|(name, robot)| {
                let token = robot.current.as_ref().filter(|_| robot.online())?;
                let free_at_ms = match &token.state {
                    RobotState::Idle => now_ms,
                    RobotState::Running { .. } => {
                        robot.status.as_ref().and_then(|(s, _)| s.ends_unix_ms).unwrap_or(now_ms).max(now_ms)
                    }
                    RobotState::Stopped { .. } | RobotState::Maintenance => return None,
                };
                let seat = Seat {
                    name: name.clone(),
                    profile: token.profile.id.clone(),
                    max_duration_s: token.max_duration_s,
                    free: free_at_ms <= now_ms,
                };
                Some(queue::Freeing { seat, free_at_ms })
            })
            .collect()
    }

    /// The baseline set experiments for `target` are checked against:
    /// the baseline of the robot or profile it names, else `reference`.
    pub fn baseline_for(
        &self,
        target: &Target,
        baselines: &BTreeMap<String, u64>,
        reference: u64,
    ) -> Result<u64, LabError> {
        let robots = lock(&self.robots);
        let hash = match target {
            Target::Any => return Ok(reference),
            Target::Robot(name) => {
                let token = robots
                    .get(name)
                    .and_then(|r| r.current.as_ref().or_else(|| r.tokens.values().next()))
                    .ok_or_else(|| {
                        LabError::BadRequest(format!(
                            "no robot '{}' has joined lab '{}'",
                            crate::contract::clip(name),
                            self.key.lab()
                        ))
                    })?;
                token.profile.baseline.clone()
            }
            Target::Profile(id) => {
                let token =
                    robots.values().filter_map(|r| r.current.as_ref()).find(|t| t.profile.id == *id).ok_or_else(
                        || {
                            LabError::BadRequest(format!(
                                "no robot of profile '{}' is in lab '{}'",
                                crate::contract::clip(id),
                                self.key.lab()
                            ))
                        },
                    )?;
                token.profile.baseline.clone()
            }
        };
        Ok(baselines.get(&hash).copied().unwrap_or(reference))
    }

    /// Engages the emergency stop of robot `name` (every online robot
    /// when `None`) for `user`: each robot's answer.
    pub fn estop(&self, user: &Principal, name: Option<&str>) -> Result<Vec<RobotAnswer>, LabError> {
        let names: Vec<String> = {
            let robots = lock(&self.robots);
            match name {
                Some(name) => {
                    if !robots.get(name).is_some_and(Robot::online) {
                        return Err(LabError::NotFound(format!(
                            "no robot '{}' is online in lab '{}'",
                            crate::contract::clip(name),
                            self.key.lab()
                        )));
                    }
                    vec![name.to_string()]
                }
                None => robots.iter().filter(|(_, r)| r.online()).map(|(n, _)| n.clone()).collect(),
            }
        };
        // Every robot at once: a STOP for all must not wait robot by robot.
        let answers = std::thread::scope(|scope| {
            let asks: Vec<_> = names
                .iter()
                .map(|robot| {
                    let estop = Estop { v: WIRE_VERSION, to: Asked::new(robot, unix_now_ms()), by: user.name.clone() };
                    let key_expr = self.keys.rpc(robot, Op::Estop);
                    scope.spawn(move || {
                        match self.asker().ask::<Estop, Ack>(&key_expr, &estop, transfer::QUERY_TIMEOUT) {
                            Ok((ack, _)) if ack.ok => Ok(ack.message),
                            Ok((ack, _)) => Err(ack.message),
                            Err(e) => Err(e.to_string()),
                        }
                    })
                })
                .collect();
            asks.into_iter().map(|a| a.join().unwrap_or_else(|_| Err("the request failed".into()))).collect::<Vec<_>>()
        });
        Ok(names.into_iter().zip(answers).collect())
    }

    /// Robot `name`'s live status (its portal's `/api/v1/status`).
    pub fn live(&self, name: &str) -> Result<serde_json::Value, LabError> {
        if !lock(&self.robots).get(name).is_some_and(Robot::online) {
            return Err(LabError::NotFound(format!("no robot '{}' is online", crate::contract::clip(name))));
        }
        let request = LiveRequest { v: WIRE_VERSION, to: Asked::new(name, unix_now_ms()) };
        let key_expr = self.keys.rpc(name, Op::Live);
        self.asker()
            .ask::<LiveRequest, Live>(&key_expr, &request, transfer::QUERY_TIMEOUT)
            .map(|(live, _)| live.status)
            .map_err(|e| LabError::Host(format!("robot '{name}': {e}")))
    }
}

/// A robot's name and its answer (what it said, or why it failed).
pub type RobotAnswer = (String, Result<String, String>);

/// What the dispatcher does next.
enum Action {
    Dispatch { id: u64, robot: String },
    Fetch { id: u64, robot: String },
    Stop { id: u64, robot: String, by: String },
    Withdraw { id: u64, robot: String },
    Baseline { robot: String },
}

/// Starts the dispatcher of `lab` over `fleet`.
pub(super) fn spawn(lab: &Arc<Lab>, fleet: Arc<Fleet>) -> Result<(), LabError> {
    *lock(&fleet.lab) = Arc::downgrade(lab);
    let reference = lab.lock()?.lab.baseline;
    if let Some(set) = reference
        && let Err(e) = lab.deployer.set_reference(set)
    {
        tracing::error!("the lab's reference (set {set}) does not validate: {e}");
    }
    let mut threads = lab.threads.lock().map_err(|_| LabError::Host("the lab's threads are unusable".into()))?;
    let checker = lab.clone();
    threads.push(
        std::thread::Builder::new()
            .name("lab-checks".into())
            .spawn(move || super::runner::checks(&checker))
            .map_err(|e| LabError::Host(format!("cannot start the lab's checks: {e}")))?,
    );
    let dispatcher = lab.clone();
    threads.push(
        std::thread::Builder::new()
            .name("lab-dispatch".into())
            .spawn(move || dispatch_loop(&dispatcher, &fleet))
            .map_err(|e| LabError::Host(format!("cannot start the lab's dispatcher: {e}")))?,
    );
    Ok(())
}

fn dispatch_loop(lab: &Arc<Lab>, fleet: &Arc<Fleet>) {
    while !lab.is_stopping() {
        let actions = match lab.lock() {
            Ok(mut book) => {
                let actions = plan(lab, fleet, &mut book);
                // After the plan (it holds the robots' lock the ETAs take):
                // an experiment no robot started in time is refused, saying
                // why (docs/lab.md, "Nothing silently stuck").
                super::runner::refuse_stuck(lab, &mut book);
                if actions.is_empty() {
                    let _ = lab.changed.wait_timeout(book, POLL);
                    continue;
                }
                actions
            }
            Err(_) => return,
        };
        for action in actions {
            let (lab, fleet) = (lab.clone(), fleet.clone());
            let spawned = std::thread::Builder::new().name("lab-dispatch-job".into()).spawn(move || match action {
                Action::Dispatch { id, robot } => dispatch(&lab, &fleet, id, &robot),
                Action::Fetch { id, robot } => fetch(&lab, &fleet, id, &robot),
                Action::Stop { id, robot, by } => stop(&fleet, id, &robot, &by),
                Action::Withdraw { id, robot } => withdraw(&lab, &fleet, id, &robot),
                Action::Baseline { robot } => fetch_baseline(&lab, &fleet, &robot),
            });
            if let Err(e) = spawned {
                tracing::error!("the lab cannot start a job: {e}");
            }
        }
    }
    fleet.shut_down();
}

/// Why a lab server's queue waits, when an admin took the whole lab out
/// of service and an experiment is queued: the line every queued
/// submitter sees (`held` in `GET /api/v1/lab`).
fn held_by_maintenance(book: &Book) -> Option<String> {
    let maintenance = book.lab.maintenance.as_ref()?;
    let queued = book.experiments.values().any(|r| r.state == ExperimentState::Queued);
    queued.then(|| {
        format!(
            "the lab is in maintenance since {} ({}: {}): no experiment goes to a robot until an admin ends it",
            crate::walltime::shown(maintenance.since_ms),
            maintenance.by,
            maintenance.reason
        )
    })
}

/// Looks at every experiment on or for a robot and every robot, and
/// decides what to do (under the book's lock and the robots').
fn plan(lab: &Lab, fleet: &Fleet, book: &mut Book) -> Vec<Action> {
    let mut actions = Vec::new();
    let mut robots = lock(&fleet.robots);
    let relearned = fleet.started.elapsed() >= fleet.relearn;
    // A robot that was online and is not any more: the owner is told once.
    for (name, robot) in robots.iter_mut() {
        let online = robot.online();
        if robot.told_online && !online {
            let reason = "it left the lab: its token went or its signed statuses stopped".to_string();
            lab.tell_about_robot(crate::notify::EventKind::RobotLost, name, &reason);
        }
        robot.told_online = online;
    }
    // Baselines not seen before are fetched once.
    for (name, robot) in robots.iter_mut() {
        if let Some(token) = &robot.current
            && !book.lab.baselines.contains_key(&token.profile.baseline)
            && !robot.fetching_baseline
            && robot.may_retry()
        {
            robot.fetching_baseline = true;
            actions.push(Action::Baseline { robot: name.clone() });
        }
    }
    let placed: Vec<(u64, ExperimentState, String, bool, Option<u64>)> = book
        .experiments
        .values()
        .filter_map(|r| {
            let p = r.placement.as_ref()?;
            Some((r.id, r.state, p.robot.clone()?, p.fetch_pending, p.unanswered_start_by_ms))
        })
        .collect();
    let mut busy: BTreeSet<String> = BTreeSet::new();
    for (id, state, name, pending, unanswered) in placed {
        let robot = robots.entry(name.clone()).or_default();
        let running_here = matches!(&robot.current, Some(t) if t.state == RobotState::Running { experiment: id });
        match state {
            ExperimentState::Running | ExperimentState::Finishing => {
                busy.insert(name.clone());
                if !robot.online() {
                    if relearned {
                        lost(lab, book, id, &name);
                    }
                    continue;
                }
                if running_here {
                    if let Some(by) = book.cancels.get(&id).cloned()
                        && robot.stops_sent.insert(id)
                    {
                        actions.push(Action::Stop { id, robot: name.clone(), by });
                    }
                    continue;
                }
                // Its token no longer says it runs it: it ended there,
                // once the token is newer than the robot's acceptance.
                let newer = match (robot.accepted.get(&id), robot.token_at) {
                    (Some(accepted), Some(token_at)) => token_at > *accepted,
                    (None, _) => true,
                    (Some(accepted), None) => accepted.elapsed() > transfer::QUERY_TIMEOUT,
                };
                if newer && !robot.fetching && robot.may_retry() {
                    if state == ExperimentState::Running {
                        let cause = format!("it ended on robot {name}; the lab fetches what it recorded");
                        let _ = lab.transition(book, id, ExperimentState::Finishing, &cause, vec![]);
                    }
                    robot.fetching = true;
                    actions.push(Action::Fetch { id, robot: name.clone() });
                }
            }
            ExperimentState::Queued if !book.dispatching.contains(&id) => {
                // Its dispatch unanswered (timed out, or in flight when
                // the server stopped): the robot's token says whether it
                // took it, once it is online (its status too: adopted
                // before, the run would be lost at once).
                if running_here && robot.online() {
                    busy.insert(name.clone());
                    robot.accepted.insert(id, Instant::now());
                    if let Some(placement) = book.experiments.get_mut(&id).and_then(|r| r.placement.as_mut()) {
                        placement.unanswered_start_by_ms = None;
                    }
                    let cause = format!("runs on robot {name} (its token says so)");
                    let _ = lab.transition(book, id, ExperimentState::Running, &cause, vec![]);
                } else if let Some(start_by) = unanswered {
                    // Held on that robot until it says it will not run it,
                    // or can no longer start it by any clock.
                    busy.insert(name.clone());
                    if unix_now_ms() >= start_by.saturating_add(wire::MAX_CLOCK_SKEW_MS) {
                        let cause = format!(
                            "robot {name} never answered its dispatch, and cannot start it after {}; back in the queue",
                            utc_time(start_by)
                        );
                        requeue(lab, book, id, &cause);
                    } else if robot.online() && robot.withdrawing.insert(id) {
                        actions.push(Action::Withdraw { id, robot: name.clone() });
                    }
                } else if (relearned || robot.online())
                    && let Some(record) = book.experiments.get_mut(&id)
                    && let Some(placement) = record.placement.as_mut()
                {
                    placement.robot = None;
                    let record = record.clone();
                    if let Ok(writer) = lab.store().lock() {
                        let _ = writer.put_experiment(&record);
                    }
                }
            }
            ExperimentState::Queued => {
                busy.insert(name.clone());
            }
            s if s.is_final() && pending && robot.online() && !robot.fetching && robot.may_retry() => {
                robot.fetching = true;
                actions.push(Action::Fetch { id, robot: name.clone() });
            }
            _ => {}
        }
    }
    // A robot that runs an experiment this lab ended (lost, then back
    // before it noticed) is told to stop it.
    for (name, robot) in robots.iter_mut() {
        if let Some(TokenBody { state: RobotState::Running { experiment }, .. }) = &robot.current {
            let experiment = *experiment;
            let ours = book.experiments.get(&experiment);
            let elsewhere = |r: &crate::store::experiments::ExperimentRecord| {
                r.placement.as_ref().and_then(|p| p.robot.as_deref()) != Some(name.as_str())
            };
            let ended = ours.is_none_or(|r| r.state.is_final() || elsewhere(r));
            if ended && robot.stops_sent.insert(experiment) {
                actions.push(Action::Stop { id: experiment, robot: name.clone(), by: "lab".into() });
            }
            busy.insert(name.clone());
        }
    }
    // Paused, or the whole lab taken out of service by an admin (`subsume
    // lab maintenance`): nothing new goes to any robot, and the queue's
    // view says why.
    let held = held_by_maintenance(book);
    if held != book.held {
        book.held = held;
        lab.notify();
    }
    if book.lab.paused || book.lab.maintenance.is_some() {
        return actions;
    }
    // The queue, first in, first out: each experiment to the first free
    // robot that fits it (queue::place).
    let queued: Vec<Unplaced> = book
        .experiments
        .values()
        .filter(|r| r.state == ExperimentState::Queued && !book.dispatching.contains(&r.id))
        .filter_map(|r| {
            let p = r.placement.as_ref()?;
            p.robot.is_none().then(|| Unplaced { id: r.id, target: p.target.clone(), duration_s: r.duration_s })
        })
        .collect();
    let online: Vec<Seat> = robots
        .iter()
        .filter_map(|(name, robot)| {
            let token = robot.current.as_ref()?;
            Some(Seat {
                name: name.clone(),
                profile: token.profile.id.clone(),
                max_duration_s: token.max_duration_s,
                // Online (its status too), not only its token: a robot
                // that started it before its status came would be lost.
                free: token.state == RobotState::Idle
                    && robot.online()
                    && !busy.contains(name)
                    && robot.dispatching.is_none(),
            })
        })
        .collect();
    for (id, name) in queue::place(&queued, &online) {
        if let Some(robot) = robots.get_mut(&name) {
            robot.dispatching = Some(id);
        }
        book.dispatching.insert(id);
        if let Some(record) = book.experiments.get_mut(&id)
            && let Some(placement) = record.placement.as_mut()
        {
            placement.robot = Some(name.clone());
            let record = record.clone();
            if let Ok(writer) = lab.store().lock()
                && let Err(e) = writer.put_experiment(&record)
            {
                tracing::error!("experiment {id}: {e}");
            }
        }
        actions.push(Action::Dispatch { id, robot: name });
    }
    actions
}

/// Experiment `id`'s robot `robot` is lost: `aborted: robot lost`, and
/// what it recorded is fetched when it comes back.
fn lost(lab: &Lab, book: &mut Book, id: u64, robot: &str) {
    if let Some(record) = book.experiments.get_mut(&id)
        && let Some(placement) = record.placement.as_mut()
    {
        placement.fetch_pending = true;
    }
    let cause = "aborted: robot lost";
    let reasons = vec![format!("aborted: robot lost ('{robot}' left the lab while it ran)")];
    if let Err(e) = lab.transition(book, id, ExperimentState::Aborted, cause, reasons) {
        tracing::error!("experiment {id}: {e}");
    }
}

/// The set of experiment `record` as a robot gets it.
fn manifest(store: &Store, set: u64) -> Result<SetManifest, String> {
    let set = store.set(set).map_err(|e| e.to_string())?;
    let text = store.blob(&set.config_sha256).map_err(|e| e.to_string())?;
    let config_text = String::from_utf8(text).map_err(|e| format!("the robot file is not utf-8: {e}"))?;
    let mut sources = BTreeMap::new();
    for (key, sha) in &set.sources {
        let bytes = std::fs::metadata(store.blob_path(sha)).map_err(|e| format!("blob {sha}: {e}"))?.len();
        sources.insert(key.clone(), BlobRef { sha256: sha.clone(), bytes });
    }
    Ok(SetManifest { config_name: set.config_name, config_text, platform: set.platform, sources })
}

fn dispatch(lab: &Lab, fleet: &Fleet, id: u64, robot: &str) {
    let issued_ms = unix_now_ms();
    let margin = fleet.dispatch_timeout / ANSWER_MARGIN_DIVISOR;
    let start_by = issued_ms + (fleet.dispatch_timeout - margin).as_millis() as u64;
    let prepared = (|| {
        let record = mark_sent(lab, id, start_by)?;
        let user = lab
            .store()
            .users()
            .get(&record.submitter)
            .ok_or_else(|| format!("the submitter '{}' is no longer a user", record.submitter))?;
        let set = manifest(lab.store(), record.set)?;
        Ok::<_, String>(Dispatch {
            v: WIRE_VERSION,
            to: Asked::new(robot, issued_ms),
            lab_id: id,
            submitter: record.submitter.clone(),
            role: user.role,
            platforms: user.platforms.clone(),
            label: record.label.clone(),
            duration_s: record.duration_s,
            set,
            start_by_unix_ms: Some(start_by),
        })
    })();
    let answer = match prepared {
        Ok(message) => {
            let key_expr = fleet.keys.rpc(robot, Op::Dispatch);
            tracing::info!("experiment {id}: dispatched to robot {robot}");
            fleet
                .asker()
                .ask::<Dispatch, DispatchReply>(&key_expr, &message, fleet.dispatch_timeout)
                .and_then(|(reply, _)| {
                    if reply.lab_id == id {
                        Ok(reply.outcome)
                    } else {
                        Err(TransferError::Missing(format!("it answered about experiment {}", reply.lab_id)))
                    }
                })
                .map_err(|e| e.to_string())
        }
        Err(why) => Ok(DispatchOutcome::Refused { reasons: vec![format!("the lab could not send it: {why}")] }),
    };
    let Ok(mut book) = lab.lock() else { return };
    book.dispatching.remove(&id);
    let mut robots = lock(&fleet.robots);
    let entry = robots.entry(robot.to_string()).or_default();
    entry.dispatching = None;
    match answer {
        Err(why) => {
            drop(robots);
            unanswered(lab, &mut book, id, robot, &why, start_by);
        }
        Ok(DispatchOutcome::Started { local_id, ends_unix_ms, .. }) => {
            entry.accepted.insert(id, Instant::now());
            drop(robots);
            if let Some(placement) = book.experiments.get_mut(&id).and_then(|r| r.placement.as_mut()) {
                placement.local_id = Some(local_id);
                placement.unanswered_start_by_ms = None;
            }
            let cause = format!("runs on robot {robot} (its experiment {local_id}) until {}", utc_time(ends_unix_ms));
            if let Err(e) = lab.transition(&mut book, id, ExperimentState::Running, &cause, vec![]) {
                tracing::error!("experiment {id}: {e}");
            }
        }
        Ok(DispatchOutcome::Refused { reasons }) => {
            drop(robots);
            refused(lab, &mut book, id, robot, reasons);
        }
    }
}

/// Marks experiment `id`'s dispatch, about to be sent, unanswered until
/// `start_by` in its stored record: a lab server killed before the answer
/// comes holds it on that robot when it starts again (`plan` withdraws it
/// there), as after a timeout, rather than placing it again while the
/// robot may still start the dispatch it has. Not sent unless stored.
/// The record as dispatched.
fn mark_sent(lab: &Lab, id: u64, start_by: u64) -> Result<ExperimentRecord, String> {
    let mut book = lab.lock().map_err(|e| e.to_string())?;
    let mut record = book.experiments.get(&id).cloned().ok_or("no record")?;
    record.placement.get_or_insert_with(Default::default).unanswered_start_by_ms = Some(start_by);
    lab.store().lock().and_then(|writer| writer.put_experiment(&record)).map_err(|e| e.to_string())?;
    book.experiments.insert(id, record.clone());
    Ok(record)
}

/// Robot `robot` did not answer the dispatch of experiment `id` (no
/// verified reply in time): it stays placed there, marked, until the
/// robot says it will not run it (`plan` withdraws it) or runs it. Not a
/// refusal: a lost answer must not end an experiment, nor let it run
/// twice.
fn unanswered(lab: &Lab, book: &mut Book, id: u64, robot: &str, why: &str, start_by: u64) {
    let Some(record) = book.experiments.get_mut(&id) else { return };
    if record.state != ExperimentState::Queued {
        return;
    }
    tracing::warn!("experiment {id}: robot {robot} did not answer its dispatch: {why}");
    if let Some(by) = book.cancels.remove(&id) {
        let cause = format!("cancelled by {by}");
        let _ = lab.transition(book, id, ExperimentState::Cancelled, &cause, vec![cause.clone()]);
        return;
    }
    let placement = record.placement.get_or_insert_with(Default::default);
    placement.unanswered_start_by_ms = Some(start_by);
    let cause = format!(
        "robot {robot} did not answer its dispatch ({why}); the lab withdraws it there before placing it again"
    );
    if let Err(e) = lab.transition(book, id, ExperimentState::Queued, &cause, vec![]) {
        tracing::error!("experiment {id}: {e}");
    }
}

/// Experiment `id` goes back to the queue, placed nowhere (`cause` says
/// why); not counted as a refusal.
fn requeue(lab: &Lab, book: &mut Book, id: u64, cause: &str) {
    let Some(placement) = book.experiments.get_mut(&id).and_then(|r| r.placement.as_mut()) else { return };
    placement.robot = None;
    placement.unanswered_start_by_ms = None;
    if let Err(e) = lab.transition(book, id, ExperimentState::Queued, cause, vec![]) {
        tracing::error!("experiment {id}: {e}");
    }
}

/// Withdraws experiment `id` from robot `robot`, which did not answer its
/// dispatch: back in the queue once the robot says it will not run it;
/// running there if the robot says it started it.
fn withdraw(lab: &Lab, fleet: &Fleet, id: u64, robot: &str) {
    let message =
        Stop { v: WIRE_VERSION, to: Asked::new(robot, unix_now_ms()), lab_id: id, by: "lab".into(), withdraw: true };
    let key_expr = fleet.keys.rpc(robot, Op::Stop);
    let answer = fleet.asker().ask::<Stop, Ack>(&key_expr, &message, transfer::QUERY_TIMEOUT);
    let Ok(mut book) = lab.lock() else { return };
    let mut robots = lock(&fleet.robots);
    let entry = robots.entry(robot.to_string()).or_default();
    entry.withdrawing.remove(&id);
    let still = book.experiments.get(&id).is_some_and(|r| {
        r.state == ExperimentState::Queued
            && r.placement
                .as_ref()
                .is_some_and(|p| p.robot.as_deref() == Some(robot) && p.unanswered_start_by_ms.is_some())
    });
    let ack = match answer {
        Ok((ack, _)) => ack,
        // Sent again at the next look while the robot is online.
        Err(e) => return tracing::warn!("experiment {id}: its withdrawal from robot {robot} was not answered: {e}"),
    };
    if !still {
        return;
    }
    if ack.ok {
        drop(robots);
        let cause = format!(
            "withdrawn from robot {robot}, which did not answer its dispatch ({}); back in the queue",
            ack.message
        );
        requeue(lab, &mut book, id, &cause);
    } else {
        entry.accepted.insert(id, Instant::now());
        drop(robots);
        if let Some(placement) = book.experiments.get_mut(&id).and_then(|r| r.placement.as_mut()) {
            placement.unanswered_start_by_ms = None;
        }
        let cause = format!("runs on robot {robot}, whose answer to its dispatch was lost ({})", ack.message);
        if let Err(e) = lab.transition(&mut book, id, ExperimentState::Running, &cause, vec![]) {
            tracing::error!("experiment {id}: {e}");
        }
    }
}

/// Robot `robot` refused experiment `id`: back in the queue the first
/// time, `refused` the second.
fn refused(lab: &Lab, book: &mut Book, id: u64, robot: &str, reasons: Vec<String>) {
    let Some(record) = book.experiments.get_mut(&id) else { return };
    if record.state != ExperimentState::Queued {
        return;
    }
    let said = reasons.join("; ");
    let reasons: Vec<String> = reasons.into_iter().map(|r| format!("robot {robot} refused it: {r}")).collect();
    if let Some(by) = book.cancels.remove(&id) {
        let cause = format!("cancelled by {by}");
        let _ = lab.transition(book, id, ExperimentState::Cancelled, &cause, vec![cause.clone()]);
        return;
    }
    let refusals = {
        let placement = record.placement.get_or_insert_with(Default::default);
        placement.refusals += 1;
        placement.robot = None;
        placement.unanswered_start_by_ms = None;
        placement.refusals
    };
    tracing::warn!("experiment {id}: robot {robot} refused it: {said}");
    let result = if refusals < 2 {
        let cause = format!("robot {robot} refused it ({said}); back in the queue once");
        lab.transition(book, id, ExperimentState::Queued, &cause, reasons)
    } else {
        let cause = format!("refused: robot {robot} refused it a second time ({said})");
        lab.transition(book, id, ExperimentState::Refused, &cause, reasons)
    };
    if let Err(e) = result {
        tracing::error!("experiment {id}: {e}");
    }
}

fn stop(fleet: &Fleet, id: u64, robot: &str, by: &str) {
    let message =
        Stop { v: WIRE_VERSION, to: Asked::new(robot, unix_now_ms()), lab_id: id, by: by.to_string(), withdraw: false };
    let key_expr = fleet.keys.rpc(robot, Op::Stop);
    match fleet.asker().ask::<Stop, Ack>(&key_expr, &message, transfer::QUERY_TIMEOUT) {
        Ok((ack, _)) => tracing::info!("experiment {id} on robot {robot}: stop by {by}: {}", ack.message),
        Err(e) => {
            tracing::warn!("experiment {id} on robot {robot}: the stop was not answered: {e}");
            // Sent again at the next look.
            lock(&fleet.robots).entry(robot.to_string()).or_default().stops_sent.remove(&id);
        }
    }
}

/// Fetches what robot `robot` kept of experiment `id`, and gives the
/// experiment its final state there (unless it ended here already).
fn fetch(lab: &Lab, fleet: &Fleet, id: u64, robot: &str) {
    let outcome = fetch_results(lab, fleet, id, robot);
    // The lab's own score of the run, from the recording just fetched
    // (before the lock: it reads the recording whole).
    let score = match &outcome {
        Ok(Some(_)) => score_fetched(lab, id),
        _ => None,
    };
    let Ok(mut book) = lab.lock() else { return };
    {
        let mut robots = lock(&fleet.robots);
        let entry = robots.entry(robot.to_string()).or_default();
        entry.fetching = false;
        if outcome.is_err() {
            entry.retry_at = Some(Instant::now() + RETRY);
        }
    }
    let results = match outcome {
        Ok(Some(results)) => results,
        // Still running there: looked at again with its next token.
        Ok(None) => {
            let mut robots = lock(&fleet.robots);
            robots.entry(robot.to_string()).or_default().retry_at = Some(Instant::now() + RETRY);
            return;
        }
        Err(e) => return tracing::warn!("experiment {id}: its results on robot {robot} did not come: {e}"),
    };
    let store = lab.store().clone();
    let Some(record) = book.experiments.get_mut(&id) else { return };
    record.results = bundle::scan(&store, id);
    if let Some(run) = results.run.clone() {
        record.run = Some(run);
    }
    match score {
        Some(Ok(score)) => record.score = Some(score),
        Some(Err(e)) => record.add_reason(format!("its run could not be scored: {e}")),
        None => {}
    }
    if let Some(placement) = record.placement.as_mut() {
        placement.fetch_pending = false;
        // The robot names its record: a run the lab adopted (its token
        // said so, or it refused a withdrawal) came with no answer.
        if results.local_id.is_some() {
            placement.local_id = results.local_id;
        }
    }
    let state = record.state;
    // A robot's ending the experiment's life does not lead to here (its
    // bug, or a newer host's state) ends it failed, never stuck.
    let robot_state = results.state.filter(|s| state.may_enter(*s)).unwrap_or(ExperimentState::Failed);
    let robot_cause = results.history.last().map(|c| c.cause.clone()).unwrap_or_default();
    if matches!(state, ExperimentState::Running | ExperimentState::Finishing) {
        let cause = format!("on robot {robot}: {robot_cause}");
        let reasons = if robot_state == ExperimentState::Done { Vec::new() } else { results.reasons.clone() };
        if let Err(e) = lab.transition(&mut book, id, robot_state, &cause, reasons) {
            tracing::error!("experiment {id}: {e}");
        }
    } else {
        record.add_reason(format!(
            "robot {robot} came back: what it recorded was fetched (there it ended {}: {robot_cause})",
            robot_state.name()
        ));
        let record = record.clone();
        if let Ok(writer) = store.lock() {
            let _ = writer.put_experiment(&record);
        }
        drop(book);
        lab.notify();
        return;
    }
    super::runner::retain(lab, &mut book);
}

/// Scores experiment `id`'s fetched run against the task it was submitted
/// under (the lab server's), when it has one and a recording came back.
fn score_fetched(lab: &Lab, id: u64) -> Option<Result<crate::store::task::Score, crate::score::ScoreError>> {
    let task = lab.lock().ok()?.experiments.get(&id)?.settings.task.clone()?;
    let recording = lab.store().experiment_dir(id).join(bundle::RUN_RECORDING);
    if !recording.exists() {
        return None;
    }
    let score = bundle::write_score(lab.store(), id, &task);
    if let Err(e) = &score {
        tracing::warn!("experiment {id}: its run could not be scored: {e}");
    }
    Some(score)
}

/// The results of experiment `id` on `robot`, their files fetched into
/// its folder; `None` while it still runs there.
fn fetch_results(lab: &Lab, fleet: &Fleet, id: u64, robot: &str) -> Result<Option<Results>, TransferError> {
    let request = ResultsRequest { v: WIRE_VERSION, to: Asked::new(robot, unix_now_ms()), lab_id: id };
    let key_expr = fleet.keys.rpc(robot, Op::Results);
    let (results, _) = fleet.asker().ask::<ResultsRequest, Results>(&key_expr, &request, transfer::QUERY_TIMEOUT)?;
    // Bound to this request, and about the experiment asked.
    if results.lab_id != id {
        return Err(TransferError::Missing(format!(
            "robot {robot} answered about experiment {}, not {id}",
            results.lab_id
        )));
    }
    if !results.found {
        return Ok(Some(Results {
            state: Some(ExperimentState::Aborted),
            reasons: vec![format!("aborted: robot {robot} does not know it (it was lost before it kept it)")],
            history: vec![crate::store::experiments::StateChange {
                state: ExperimentState::Aborted,
                at_ms: unix_now_ms(),
                cause: "aborted: the robot does not know it".into(),
            }],
            ..results
        }));
    }
    if !results.state.is_some_and(ExperimentState::is_final) {
        return Ok(None);
    }
    let dir = lab.store().experiment_dir(id);
    let file_key = fleet.keys.rpc(robot, Op::File);
    for file in &results.files {
        let dest = dir.join(&file.name);
        if transfer::digest_file(&dest).is_ok_and(|d| d.sha256 == file.sha256) {
            continue;
        }
        let source = FileSource::Result { lab_id: id, name: file.name.clone() };
        let expected = BlobRef { sha256: file.sha256.clone(), bytes: file.bytes };
        transfer::fetch_file(fleet.asker(), (&file_key, robot), &source, &expected, &dest)?;
    }
    tracing::info!("experiment {id}: {} result files fetched from robot {robot}", results.files.len());
    Ok(Some(results))
}

/// Fetches robot `robot`'s baseline and stores it as a set (the first
/// becomes the lab's reference).
fn fetch_baseline(lab: &Lab, fleet: &Fleet, robot: &str) {
    let outcome = import_baseline(lab, fleet, robot);
    let mut robots = lock(&fleet.robots);
    let entry = robots.entry(robot.to_string()).or_default();
    entry.fetching_baseline = false;
    match outcome {
        Ok(set) => {
            entry.baseline_error = None;
            drop(robots);
            tracing::info!("lab '{}': robot {robot}'s baseline is set {set} here", fleet.key.lab());
        }
        Err(e) => {
            tracing::warn!("lab '{}': robot {robot}'s baseline did not come: {e}", fleet.key.lab());
            entry.baseline_error = Some(crate::contract::clip(&e));
            entry.retry_at = Some(Instant::now() + RETRY * 5);
        }
    }
    lab.notify();
}

fn import_baseline(lab: &Lab, fleet: &Fleet, robot: &str) -> Result<u64, String> {
    let request = BaselineRequest { v: WIRE_VERSION, to: Asked::new(robot, unix_now_ms()) };
    let key_expr = fleet.keys.rpc(robot, Op::Baseline);
    let (baseline, _) = fleet
        .asker()
        .ask::<BaselineRequest, Baseline>(&key_expr, &request, transfer::QUERY_TIMEOUT)
        .map_err(|e| e.to_string())?;
    if let Some(set) = lab.lock().map_err(|e| e.to_string())?.lab.baselines.get(&baseline.hash) {
        return Ok(*set);
    }
    let store = lab.store();
    let file_key = fleet.keys.rpc(robot, Op::File);
    for blob in baseline.set.sources.values() {
        if store.blob_path(&blob.sha256).is_file() {
            continue;
        }
        let source = FileSource::Blob { sha256: blob.sha256.clone() };
        let bytes =
            transfer::fetch_blob(fleet.asker(), (&file_key, robot), &source, blob).map_err(|e| e.to_string())?;
        store.lock().and_then(|w| w.put_blob(&bytes)).map_err(|e| e.to_string())?;
    }
    let dir = store.root().join("baselines").join(&baseline.hash);
    for (path, blob) in &baseline.files {
        wire::named_path_ok(path).map_err(|b| b.0)?;
        let dest = dir.join(path);
        if transfer::digest_file(&dest).is_ok_and(|d| d.sha256 == blob.sha256) {
            continue;
        }
        let source = FileSource::Named { path: path.clone() };
        transfer::fetch_file(fleet.asker(), (&file_key, robot), &source, blob, &dest).map_err(|e| e.to_string())?;
    }
    let by = format!("robot:{robot}");
    let set = lab.import_manifest(&baseline.set, &by, &dir).map_err(|e| e.to_string())?;
    let mut book = lab.lock().map_err(|e| e.to_string())?;
    let mut state = book.lab.clone();
    state.baselines.insert(baseline.hash.clone(), set.id);
    let first = state.baseline.is_none();
    if first {
        state.baseline = Some(set.id);
    }
    store.lock().and_then(|w| w.put_lab_state(&state)).map_err(|e| e.to_string())?;
    book.lab = state;
    drop(book);
    if first {
        lab.deployer.set_reference(set.id).map_err(|e| e.to_string())?;
        if let Ok(writer) = store.lock() {
            let detail = format!("robot {robot}'s baseline (set {}) is the lab's reference", set.id);
            writer.record(super::LAB_AUDIT_USER, "lab-reference", &format!("set {}", set.id), Outcome::Ok(&detail));
        }
    }
    Ok(set.id)
}
