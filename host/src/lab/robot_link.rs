//! A robot's link to its lab (docs/lab.md, "Several robots"): `subsume run
//! ... --lab NAME`. The robot declares a liveliness token carrying its
//! name, state and profile ([`wire::TokenBody`]), publishes a low-rate
//! status, and answers its lab server's queries: a dispatch, a stop, the
//! lab's emergency stop, the results of an experiment and their files,
//! its baseline, its live status.
//!
//! Safety stays here. A dispatched experiment is checked again (it
//! validates, it changes only the platforms its submitter holds in the
//! lab, never the envelope, its duration is within this robot's
//! `max-duration`) and runs through this host's own lab, like one of its
//! own: from a fresh start, recording, its time enforced here, the
//! baseline back after it, the envelope and the emergency stop throughout.
//! A robot that has heard no heartbeat of its lab for `lost_after` while
//! it runs the lab's experiment aborts it on its own and goes back to its
//! baseline.
//!
//! Who the robot obeys: only requests signed with its lab's secret
//! ([`wire::LabKey`]), naming this robot, fresh, and never seen before
//! ([`transfer::Gate`]); its replies carry the request's nonce and its
//! name under their MAC. A peer without the secret gets no answer, and
//! its heartbeats count for nothing; refusals are counted by class and
//! audited at most once per [`wire::REFUSAL_AUDIT_INTERVAL_MS`], and the
//! count travels in the robot's status to its lab server's /metrics.
//!
//! Threads: one per kind of query, each with its own queryable and
//! backlog (dispatches, which take seconds; stops and emergency stops,
//! which must not wait behind one nor behind junk on other keys; files),
//! and one that keeps the token, the status, the refusals' audit and the
//! lost-lab watch.
//!
//! Beside it: `robot_dispatch.rs` takes a dispatch (checks, sources,
//! queueing, the wait for its start); `robot_files.rs` makes what the robot
//! sends (its baseline's package, files by chunk, an experiment's results).

use std::collections::BTreeMap;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use thiserror::Error;
use zenoh::Wait;

use super::materialize::NamedContent;
use super::transfer::{self, Gate, TransferError};
use super::wire::{
    self, Ack, Answered, Baseline, BaselineRequest, Dispatch, DispatchReply, Estop, FileRequest, Heartbeat, Keys,
    LabKey, Live, LiveRequest, Op, Profile, RefusalTally, Request, ResultsRequest, RobotState, Status, Stop, TokenBody,
    WIRE_VERSION,
};
use super::{Lab, LabError};
use crate::bridge::session::{self, SessionSettings, Shared};
use crate::fsutil::HiddenPaths;
use crate::runtime::Locks;
use crate::runtime::locks::unix_now_ms;
use crate::store::Outcome;
use crate::store::experiments::{ExperimentRecord, ExperimentState};
use crate::store::users::{Principal, Role};

/// How long a robot runs the lab's experiment without hearing its lab
/// before it aborts it on its own, by default.
pub const DEFAULT_LOST_AFTER: Duration = Duration::from_secs(5);
/// The bounds of that setting: shorter than two heartbeats would abort on
/// a late one; longer than ten minutes leaves an experiment nobody can
/// stop from the lab.
pub const MIN_LOST_AFTER: Duration = Duration::from_secs(1);
pub const MAX_LOST_AFTER: Duration = Duration::from_secs(600);

/// How often the robot publishes its status, by default (the lab's list).
pub const DEFAULT_STATUS_PERIOD: Duration = Duration::from_secs(1);
/// Most often it may: a robot must not flood its lab server.
pub const MIN_STATUS_PERIOD: Duration = Duration::from_millis(100);

/// How long a dispatch waits for the experiment to start here before it
/// answers (the reset and the activation).
pub const START_WAIT: Duration = Duration::from_secs(60);

/// Most lab experiments a robot remembers as withdrawn (a dispatch its lab
/// gave up on before it came): the threat is the lab's own withdrawals
/// growing a robot's memory. Past it the oldest is forgotten; a late
/// dispatch of it is still refused by its start-by time.
pub const MAX_WITHDRAWN: usize = 1024;

/// How often the token, the status and the lost-lab watch are looked at.
const WATCH: Duration = Duration::from_millis(100);

/// Largest request but a dispatch (results, a file's chunk, the baseline,
/// the live status): each is a few hundred bytes; junk larger is refused
/// before its MAC is computed.
pub const MAX_SMALL_REQUEST_BYTES: usize = 16 << 10;

/// Why the link could not start.
#[derive(Debug, Error)]
pub enum LinkError {
    #[error(transparent)]
    Session(#[from] session::SessionError),
    #[error(transparent)]
    Transfer(#[from] TransferError),
    #[error("the robot's name '{0}' is not a plain name (letters, digits, '-', '_', at most 64)")]
    Name(String),
    #[error("{0}")]
    Settings(String),
    #[error("the robot's baseline cannot be sent to its lab: {0}")]
    Baseline(String),
    #[error(transparent)]
    Lab(#[from] LabError),
}

/// What joining a lab needs.
#[derive(Clone, Debug)]
pub struct RobotLinkOptions {
    pub key: LabKey,
    pub session: SessionSettings,
    /// The robot's name in the lab.
    pub robot: String,
    pub lost_after: Duration,
    pub status_period: Duration,
}

/// The robot's baseline as its lab server gets it.
#[derive(Clone, Debug)]
pub(super) struct Package {
    pub(super) set: u64,
    pub(super) message: Baseline,
    pub(super) profile: Profile,
    /// Where each named file's bytes are here.
    pub(super) files: BTreeMap<String, NamedContent>,
}

/// The robot's side of its lab.
pub struct RobotLink {
    pub(super) lab: Arc<Lab>,
    pub(super) options: RobotLinkOptions,
    pub(super) keys: Keys,
    pub(super) shared: Arc<Shared>,
    pub(super) boot_ms: u64,
    /// When the lab was last heard (a heartbeat or a dispatch).
    pub(super) heard: Mutex<Option<Instant>>,
    /// The newest heartbeat's time: an older one (replayed) is not heard.
    pub(super) last_beat_ms: AtomicU64,
    /// Lab messages refused, by class, and their audit.
    pub(super) refusals: Arc<Mutex<RefusalTally>>,
    /// Replies this robot skipped when it asked its lab server (blobs).
    pub(super) skipped: AtomicU64,
    pub(super) package: Mutex<Option<Package>>,
    /// Lab experiments withdrawn before they came (oldest first), with the
    /// withdrawal's issue time: a dispatch of it issued before that is
    /// refused; a new dispatch of it, issued after, is taken.
    pub(super) withdrawn: Mutex<std::collections::VecDeque<(u64, u64)>>,
    pub(super) stopping: Arc<AtomicBool>,
    pub(super) threads: Mutex<Vec<std::thread::JoinHandle<()>>>,
    pub(super) _heartbeats: Mutex<Option<zenoh::pubsub::Subscriber<()>>>,
    /// The robot's folders its live status must not spell out to the lab
    /// (its portal hides the same).
    pub(super) hidden: HiddenPaths,
}

pub(super) fn lock<T>(mutex: &Mutex<T>) -> MutexGuard<'_, T> {
    mutex.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
}

/// The lab's name on this robot's records.
pub(super) fn lab_user(options: &RobotLinkOptions, submitter: &str) -> String {
    format!("{submitter}@{}", options.key.lab())
}

impl RobotLink {
    /// Joins the lab: opens the session, answers the lab's queries,
    /// declares the robot's token. The live status it gives the lab names
    /// the `hidden` folders, never spells them out.
    pub fn start(lab: Arc<Lab>, options: RobotLinkOptions, hidden: HiddenPaths) -> Result<Arc<RobotLink>, LinkError> {
        if !wire::is_name(&options.robot) {
            return Err(LinkError::Name(crate::contract::clip(&options.robot)));
        }
        if !(MIN_LOST_AFTER..=MAX_LOST_AFTER).contains(&options.lost_after) {
            return Err(LinkError::Settings(format!(
                "--lab-lost must be from {} to {} s",
                MIN_LOST_AFTER.as_secs(),
                MAX_LOST_AFTER.as_secs()
            )));
        }
        if options.status_period < MIN_STATUS_PERIOD {
            return Err(LinkError::Settings(format!(
                "the lab status is published at most every {} ms",
                MIN_STATUS_PERIOD.as_millis()
            )));
        }
        let shared = session::session(&options.session)?;
        let link = Arc::new(RobotLink {
            keys: Keys::new(&options.key),
            lab,
            options,
            shared,
            boot_ms: unix_now_ms(),
            heard: Mutex::new(None),
            last_beat_ms: AtomicU64::new(0),
            refusals: Arc::new(Mutex::new(RefusalTally::default())),
            skipped: AtomicU64::new(0),
            package: Mutex::new(None),
            withdrawn: Mutex::new(std::collections::VecDeque::new()),
            stopping: Arc::new(AtomicBool::new(false)),
            threads: Mutex::new(Vec::new()),
            _heartbeats: Mutex::new(None),
            hidden,
        });
        link.refresh_package()?;
        let weak = Arc::downgrade(&link);
        let key = link.options.key.clone();
        let subscriber = link
            .shared
            .session
            .declare_subscriber(link.keys.heartbeat())
            .callback(move |sample: zenoh::sample::Sample| {
                let Some(link) = weak.upgrade() else { return };
                let bytes = sample.payload().to_bytes();
                match key.open::<Heartbeat>(&bytes) {
                    // Fresh, and newer than the newest heard: a replayed
                    // heartbeat keeps no experiment alive.
                    Ok((beat, _))
                        if wire::fresh(beat.at_unix_ms, unix_now_ms()).is_ok()
                            && link.last_beat_ms.fetch_max(beat.at_unix_ms, Ordering::AcqRel) < beat.at_unix_ms =>
                    {
                        link.heard_lab()
                    }
                    Ok(_) => tracing::debug!("lab heartbeat too old, too new or replayed: ignored"),
                    Err(e) => {
                        lock(&link.refusals).note(e.class());
                        tracing::debug!("a heartbeat on the lab's key was refused: {e}")
                    }
                }
            })
            .wait()
            .map_err(|e| TransferError::Zenoh(e.to_string()))?;
        *lock(&link._heartbeats) = Some(subscriber);
        // Each kind of query its own queryable, backlog and thread: the
        // STOP's first, and nothing on other keys reaches its backlog.
        let small = MAX_SMALL_REQUEST_BYTES;
        let threads = vec![
            link.serve(Op::Estop, "lab-estop", wire::MAX_STOP_BYTES, |link, estop: Estop, re| {
                link.options.key.seal(&link.estop(&estop, re), &[])
            })?,
            link.serve(Op::Stop, "lab-stop", wire::MAX_STOP_BYTES, |link, stop: Stop, re| {
                link.options.key.seal(&link.stop(&stop, re), &[])
            })?,
            link.serve(Op::Dispatch, "lab-dispatch", wire::MAX_MESSAGE_BYTES, |link, dispatch: Dispatch, re| {
                let outcome = link.dispatch(&dispatch);
                link.options.key.seal(&DispatchReply { v: WIRE_VERSION, re, lab_id: dispatch.lab_id, outcome }, &[])
            })?,
            link.serve(Op::Results, "lab-results", small, |link, request: ResultsRequest, re| {
                link.options.key.seal(&link.results(request.lab_id, re), &[])
            })?,
            link.serve(Op::File, "lab-files", small, |link, request: FileRequest, re| link.file(&request, re))?,
            link.serve(Op::Baseline, "lab-baseline", small, |link, _: BaselineRequest, re| link.baseline(re))?,
            link.serve(Op::Live, "lab-live", small, |link, _: LiveRequest, re| {
                link.options.key.seal(&Live { v: WIRE_VERSION, re, status: link.live_status() }, &[])
            })?,
        ];
        let mut threads = threads;
        let watched = link.clone();
        threads.push(
            std::thread::Builder::new()
                .name("lab-link".into())
                .spawn(move || watched.watch())
                .map_err(|e| LinkError::Settings(format!("cannot start the lab link's thread: {e}")))?,
        );
        *lock(&link.threads) = threads;
        tracing::info!(
            "robot '{}' joined lab '{}' (zenoh session {})",
            link.options.robot,
            link.options.key.lab(),
            link.shared.id
        );
        Ok(link)
    }

    /// Serves `op`'s queries with `answer`, admitting requests of kind `Q`
    /// of at most `max_bytes`.
    fn serve<Q: Request + Send + 'static>(
        self: &Arc<Self>,
        op: Op,
        name: &str,
        max_bytes: usize,
        answer: fn(&RobotLink, Q, Answered) -> Vec<u8>,
    ) -> Result<std::thread::JoinHandle<()>, LinkError> {
        let weak = Arc::downgrade(self);
        let key_expr = self.keys.rpc(&self.options.robot, op);
        let gate = Gate {
            key: self.options.key.clone(),
            me: self.options.robot.clone(),
            max_bytes,
            refusals: self.refusals.clone(),
        };
        Ok(transfer::serve(self.shared.clone(), key_expr, name, self.stopping.clone(), gate, move |request, re| {
            match weak.upgrade() {
                Some(link) => answer(&link, request, re),
                None => Vec::new(),
            }
        })?)
    }

    /// Leaves the lab: the token goes, the threads end.
    pub fn shut_down(&self) {
        self.stopping.store(true, Ordering::Release);
        let threads = std::mem::take(&mut *lock(&self.threads));
        for thread in threads {
            let _ = thread.join();
        }
        *lock(&self._heartbeats) = None;
    }

    pub(super) fn heard_lab(&self) {
        *lock(&self.heard) = Some(Instant::now());
    }

    /// The robot's state as its token says it.
    pub(super) fn state(&self) -> (RobotState, Option<(u64, u64)>) {
        let Ok(book) = self.lab.lock() else { return (RobotState::Maintenance, None) };
        if let Some(running) = &book.running
            && let Some(origin) = book.experiments.get(&running.id).and_then(|r| r.origin.as_ref())
        {
            let times = Some((running.started_unix_ms, running.ends_unix_ms));
            return (RobotState::Running { experiment: origin.id }, times);
        }
        let locks = self.lab.deployer.services.get::<Locks>();
        if let Some(lock) = locks.and_then(|l| l.engaged().into_iter().next()) {
            return (RobotState::Stopped { by: crate::contract::clip(&lock.by) }, None);
        }
        if book.lab.paused || book.lab.maintenance.is_some() {
            return (RobotState::Maintenance, None);
        }
        (RobotState::Idle, None)
    }

    /// Keeps the token and the status, and watches for a lost lab.
    fn watch(&self) {
        let mut seq = 0u64;
        let mut token: Option<(String, zenoh::liveliness::LivelinessToken)> = None;
        let mut last_status = Instant::now() - self.options.status_period;
        let publisher = self.shared.session.declare_publisher(self.keys.status(&self.options.robot)).wait();
        let publisher = match publisher {
            Ok(publisher) => Some(publisher),
            Err(e) => {
                tracing::error!("the lab status cannot be published: {e}");
                None
            }
        };
        while !self.stopping.load(Ordering::Acquire) {
            if let Err(e) = self.refresh_package() {
                tracing::warn!("{e}");
            }
            if let Some(line) = lock(&self.refusals).due(unix_now_ms()) {
                tracing::warn!("lab '{}': {line}", self.options.key.lab());
                self.lab.deployer.audit("lab", "lab-refusals", "lab messages", Outcome::Refused(&line));
            }
            let (state, times) = self.state();
            let Some(package) = lock(&self.package).clone() else {
                std::thread::sleep(WATCH);
                continue;
            };
            let max_duration_s = self.lab.lock().map(|b| b.lab.settings.max_duration_s).unwrap_or(0.0);
            let body = |seq| TokenBody {
                v: WIRE_VERSION,
                name: self.options.robot.clone(),
                seq,
                boot_ms: self.boot_ms,
                state: state.clone(),
                profile: package.profile.clone(),
                max_duration_s,
            };
            let stale = token.as_ref().is_none_or(|(key, _)| {
                self.options.key.read_token(key).map(|t| TokenBody { seq: 0, ..t }).ok() != Some(body(0))
            });
            if stale {
                seq += 1;
                let key = self.options.key.token_key(&body(seq));
                match self.shared.session.liveliness().declare_token(key.clone()).wait() {
                    // The new token first, then the old one goes: the lab
                    // never sees the robot without one.
                    Ok(new) => {
                        tracing::info!(
                            "lab '{}': robot '{}' is {}",
                            self.options.key.lab(),
                            self.options.robot,
                            state.word()
                        );
                        token = Some((key, new));
                    }
                    Err(e) => tracing::error!("the robot's liveliness token was not declared: {e}"),
                }
            }
            if let RobotState::Running { experiment } = &state {
                let silent = lock(&self.heard).map_or(Duration::MAX, |at| at.elapsed());
                if silent > self.options.lost_after {
                    self.abort_lost(*experiment, silent);
                }
            }
            if last_status.elapsed() >= self.options.status_period
                && let Some(publisher) = &publisher
            {
                last_status = Instant::now();
                let locks = self.lab.deployer.services.get::<Locks>();
                let status = Status {
                    v: WIRE_VERSION,
                    name: self.options.robot.clone(),
                    at_unix_ms: unix_now_ms(),
                    state: state.clone(),
                    started_unix_ms: times.map(|t| t.0),
                    ends_unix_ms: times.map(|t| t.1),
                    locks: locks.map(|l| l.engaged().into_iter().map(|e| e.lock).collect()).unwrap_or_default(),
                    set: self.lab.deployer.active().ok().map(|(set, _)| set.id),
                    period_ms: self.options.status_period.as_millis() as u64,
                    refused: lock(&self.refusals).sum(),
                };
                if let Err(e) = publisher.put(self.options.key.seal(&status, &[])).wait() {
                    tracing::debug!("the lab status was not published: {e}");
                }
            }
            std::thread::sleep(WATCH);
        }
        drop(token);
    }

    /// Aborts the lab's experiment `lab_id`: the lab was not heard for
    /// `silent`.
    fn abort_lost(&self, lab_id: u64, silent: Duration) {
        let Ok(mut book) = self.lab.lock() else { return };
        let Some(id) = local_id(&book.experiments, self.options.key.lab(), lab_id) else { return };
        if book.aborts.contains_key(&id) {
            return;
        }
        let cause = format!(
            "aborted: lost its lab '{}' for more than {} s",
            self.options.key.lab(),
            self.options.lost_after.as_secs_f64()
        );
        tracing::warn!(
            "experiment {id} (lab {lab_id}): {cause} (silent {:.1} s); back to the baseline",
            silent.as_secs_f64()
        );
        book.aborts.insert(id, cause);
        drop(book);
        self.lab.notify();
    }

    fn stop(&self, stop: &Stop, re: Answered) -> Ack {
        let ack = |ok, message: String| Ack { v: WIRE_VERSION, re: re.clone(), ok, message };
        self.heard_lab();
        let by = lab_user(&self.options, &stop.by);
        let Ok(mut book) = self.lab.lock() else { return ack(false, "the lab's state is unusable".into()) };
        let found = if stop.withdraw { live_local_id } else { local_id };
        let Some(id) = found(&book.experiments, self.options.key.lab(), stop.lab_id) else {
            if !stop.withdraw {
                return ack(false, format!("no lab experiment {} here", stop.lab_id));
            }
            drop(book);
            remember_withdrawn(&mut lock(&self.withdrawn), stop.lab_id, stop.to.issued_unix_ms);
            let message = "withdrawn: it never came here, and will not be taken if it does".to_string();
            self.lab.deployer.audit(
                &by,
                "lab-withdraw",
                &format!("lab experiment {}", stop.lab_id),
                Outcome::Ok(&message),
            );
            return ack(true, message);
        };
        let state = book.experiments.get(&id).map(|r| r.state);
        if stop.withdraw && !(state == Some(ExperimentState::Queued) && book.starting != Some(id)) {
            // Started (or ended) before the lab's start-by time: the lab
            // adopts the run rather than losing it.
            let said = state.map_or("gone", |s| s.name());
            return ack(false, format!("it is {said} here as experiment {id}: not withdrawn"));
        }
        let message = match state {
            Some(s) if s.is_final() => format!("it ended already ({})", s.name()),
            Some(ExperimentState::Queued) if book.starting != Some(id) => {
                let cause = format!("cancelled by {by}");
                match self.lab.transition(&mut book, id, ExperimentState::Cancelled, &cause, vec![cause.clone()]) {
                    Ok(_) => "cancelled before it started".into(),
                    Err(e) => return ack(false, e.to_string()),
                }
            }
            _ => {
                book.cancels.insert(id, by.clone());
                drop(book);
                self.lab.notify();
                "stopping it; the baseline comes back".into()
            }
        };
        self.lab.deployer.audit(&by, "lab-stop", &format!("lab experiment {}", stop.lab_id), Outcome::Ok(&message));
        ack(true, message)
    }

    fn estop(&self, estop: &Estop, re: Answered) -> Ack {
        self.heard_lab();
        let user = Principal { name: lab_user(&self.options, &estop.by), role: Role::Viewer, platforms: Vec::new() };
        match self.lab.deployer.engage_lock(&user, &format!("lab '{}'", self.options.key.lab())) {
            Ok(engaged) => Ack {
                v: WIRE_VERSION,
                re,
                ok: true,
                message: if engaged.newly { "engaged".into() } else { "engaged already".into() },
            },
            Err(e) => Ack { v: WIRE_VERSION, re, ok: false, message: e.to_string() },
        }
    }

    /// The live status of this robot (its portal's `/api/v1/status`): the
    /// next one the control loop publishes, or the last within a second.
    fn live_status(&self) -> serde_json::Value {
        let mut live = self.lab.deployer.live().subscribe();
        live.borrow_and_update();
        let deadline = Instant::now() + Duration::from_secs(1);
        while Instant::now() < deadline && !live.has_changed().unwrap_or(true) {
            std::thread::sleep(Duration::from_millis(20));
        }
        let status = live.borrow().clone();
        let mut text = serde_json::to_string(&*status).unwrap_or_default();
        self.hidden.hide(&mut text);
        if text.len() > wire::MAX_LIVE_BYTES {
            return serde_json::json!({ "error": "the live status is larger than the lab link carries" });
        }
        serde_json::from_str(&text).unwrap_or_default()
    }
}

/// The local id of lab `lab`'s experiment `lab_id`, if it came here.
pub(super) fn local_id(experiments: &BTreeMap<u64, ExperimentRecord>, lab: &str, lab_id: u64) -> Option<u64> {
    experiments.values().rev().find(|r| r.origin.as_ref().is_some_and(|o| o.lab == lab && o.id == lab_id)).map(|r| r.id)
}

/// The local experiment of lab experiment `lab_id` that a dispatch or a
/// withdrawal of it concerns: the newest, unless it ended without ever
/// running (withdrawn, or not started by its start-by time). Such a copy
/// is as if it never came: a later dispatch is taken as new (not refused
/// with the old copy's reasons), and a withdrawal is granted (not answered
/// "not withdrawn", which would make the lab adopt a run that never was).
pub(super) fn live_local_id(experiments: &BTreeMap<u64, ExperimentRecord>, lab: &str, lab_id: u64) -> Option<u64> {
    local_id(experiments, lab, lab_id).filter(|id| experiments.get(id).is_some_and(|r| !r.ended_unrun()))
}

/// Remembers lab experiment `lab_id` as withdrawn by a withdrawal issued
/// at `issued_ms`, forgetting the oldest past [`MAX_WITHDRAWN`].
fn remember_withdrawn(withdrawn: &mut std::collections::VecDeque<(u64, u64)>, lab_id: u64, issued_ms: u64) {
    if let Some(entry) = withdrawn.iter_mut().find(|(id, _)| *id == lab_id) {
        entry.1 = entry.1.max(issued_ms);
        return;
    }
    if withdrawn.len() >= MAX_WITHDRAWN {
        withdrawn.pop_front();
    }
    withdrawn.push_back((lab_id, issued_ms));
}

/// Whether a dispatch of lab experiment `lab_id` issued at `issued_ms` was
/// withdrawn (by a withdrawal issued after it, on the same lab clock).
pub(super) fn withdrawn_before(
    withdrawn: &std::collections::VecDeque<(u64, u64)>,
    lab_id: u64,
    issued_ms: u64,
) -> bool {
    withdrawn.iter().any(|(id, at)| *id == lab_id && issued_ms <= *at)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::store::experiments::{AppliedSettings, ExperimentState::*, LabSettings, NewExperiment, Origin};
    use crate::store::users::Role;

    /// Local experiment `id` of lab `lab`'s experiment `lab_id`, through
    /// `states` (after `checking`).
    fn copy(id: u64, lab: &str, lab_id: u64, states: &[ExperimentState]) -> ExperimentRecord {
        let new = NewExperiment {
            submitter: "ana".into(),
            set: 1,
            label: String::new(),
            duration_s: 1.0,
            submitted_ms: 1,
            settings: AppliedSettings::of(&LabSettings::default(), 1),
            components: Vec::new(),
        };
        let mut record = ExperimentRecord::new(new, Checking, "dispatched");
        record.id = id;
        record.origin = Some(Origin {
            lab: lab.into(),
            id: lab_id,
            role: Role::Researcher,
            platforms: vec![],
            start_by_unix_ms: None,
        });
        for (at, state) in states.iter().enumerate() {
            record.enter(*state, at as u64 + 2, "on").unwrap();
        }
        record
    }

    #[test]
    fn a_copy_that_ended_without_running_is_not_what_a_new_dispatch_or_a_withdrawal_concerns() {
        // (the local copies of lab experiment 7 of lab "lab", oldest first;
        // what local_id and live_local_id find)
        let withdrawn = [Preflight, Queued, Cancelled];
        let cases: Vec<(Vec<ExperimentRecord>, Option<u64>, Option<u64>)> = vec![
            (vec![], None, None),
            (vec![copy(1, "lab", 7, &[Preflight, Queued])], Some(1), Some(1)),
            (vec![copy(1, "lab", 7, &[Preflight, Queued, Running])], Some(1), Some(1)),
            (vec![copy(1, "lab", 7, &[Preflight, Queued, Running, Finishing, Done])], Some(1), Some(1)),
            (vec![copy(1, "lab", 7, &[Preflight, Queued, Running, Finishing, Aborted])], Some(1), Some(1)),
            // Withdrawn, or not started by its start-by time: as if it never came.
            (vec![copy(1, "lab", 7, &withdrawn)], Some(1), None),
            (vec![copy(1, "lab", 7, &[Refused])], Some(1), None),
            // Taken again later: the new copy is the one.
            (vec![copy(1, "lab", 7, &withdrawn), copy(2, "lab", 7, &[Preflight, Queued])], Some(2), Some(2)),
            (vec![copy(1, "lab", 7, &withdrawn), copy(2, "lab", 7, &withdrawn)], Some(2), None),
            // Another lab's experiment 7, or this lab's experiment 8.
            (vec![copy(1, "other", 7, &[Preflight, Queued]), copy(2, "lab", 8, &[Preflight])], None, None),
        ];
        for (copies, newest, live) in cases {
            let states: Vec<_> = copies.iter().map(|r| (r.id, r.state)).collect();
            let experiments: BTreeMap<u64, ExperimentRecord> = copies.into_iter().map(|r| (r.id, r)).collect();
            assert_eq!(local_id(&experiments, "lab", 7), newest, "{states:?}");
            assert_eq!(live_local_id(&experiments, "lab", 7), live, "{states:?}");
        }
    }

    #[test]
    fn a_withdrawal_refuses_the_dispatches_issued_before_it_and_takes_later_ones() {
        let mut withdrawn = std::collections::VecDeque::new();
        remember_withdrawn(&mut withdrawn, 7, 10_000);
        // (lab id, dispatch issued at, refused)
        let cases = [(7, 9_000, true), (7, 10_000, true), (7, 10_001, false), (8, 9_000, false)];
        for (lab_id, issued, expected) in cases {
            assert_eq!(withdrawn_before(&withdrawn, lab_id, issued), expected, "{lab_id} at {issued}");
        }
        // A later withdrawal of the same experiment moves its time on.
        remember_withdrawn(&mut withdrawn, 7, 20_000);
        assert!(withdrawn_before(&withdrawn, 7, 15_000));
        assert_eq!(withdrawn.len(), 1);
        // Bounded: the oldest is forgotten.
        for id in 100..100 + MAX_WITHDRAWN as u64 {
            remember_withdrawn(&mut withdrawn, id, 1);
        }
        assert_eq!(withdrawn.len(), MAX_WITHDRAWN);
        assert!(!withdrawn_before(&withdrawn, 7, 15_000));
    }
}
