//! The lab's two threads. The checker takes submitted experiments one at a
//! time, oldest first: it checks the set again against the baseline, writes
//! it in its preflight form and runs the preflight (a process of its own at
//! background priority), then queues or refuses it. The runner decides,
//! every [`POLL`] or when woken, whether the experiment on the robot must
//! end (its time is up, a cancel, an emergency stop, an admin's activation)
//! or the next one may start (the queue's rules, no lock engaged, the
//! robot reset), and carries that out through `deploy`.
//!
//! Neither thread holds the lab's lock while it builds a graph or runs a
//! preflight: requests keep being answered.

use std::collections::BTreeMap;
use std::sync::Arc;
use std::time::Duration;

use super::episode::{EpisodeWatch, Seen};
use super::materialize::{self, MaterializeError, PreflightWorld};
use super::preflight::{Outcome, PreflightError};
use super::preflight_runs::{self, Runs};
use super::queue::{self, QueueView};
use super::{Book, Lab, LabError, TURNAROUND, bundle, run_recording};
use crate::deploy::{DeployError, RunningExperiment};
use crate::report::LiveStatus;
use crate::runtime::Locks;
use crate::runtime::locks::unix_now_ms;
use crate::store::experiments::{
    Criteria, DriveReset, ExperimentRecord, ExperimentState, PreflightResult, ResetPolicy,
};
use crate::store::task::EpisodeEnd;
use crate::store::users::Principal;
use crate::store::{Outcome as AuditOutcome, Store};

/// How often the runner looks at the robot and the queue when nothing
/// wakes it.
pub const POLL: Duration = Duration::from_millis(50);

/// A cycle that started this late is the host's lateness, not the
/// algorithm's: a third of the serial link's default watchdog (0.3 s).
pub const LATE_CYCLE_MS: f64 = 100.0;

/// The experiment on the robot.
#[derive(Clone, Debug)]
pub(super) struct OnRobot {
    pub id: u64,
    pub baseline: u64,
    /// Graph time it started and ends at (ns).
    pub started_ns: u64,
    pub ends_ns: u64,
    pub started_unix_ms: u64,
    pub ends_unix_ms: u64,
    /// The live status the runner judges while it runs, when the owner's
    /// criteria (`end_run_on_breach`) or its task's end conditions may end
    /// it early.
    pub watch: Option<Watch>,
}

/// What may end the experiment on the robot early, judged on its live
/// status.
#[derive(Clone, Debug)]
pub(super) struct Watch {
    /// With the owner's `end_run_on_breach`: the criteria it ran under.
    criteria: Option<Criteria>,
    /// Its task's end conditions.
    episode: Option<EpisodeWatch>,
    live: tokio::sync::watch::Receiver<Arc<Option<LiveStatus>>>,
}

/// How an experiment on the robot ends.
#[derive(Clone, Debug)]
struct Ending {
    id: u64,
    state: ExperimentState,
    cause: String,
    /// The queue pauses after it (an admin's activation takes the robot).
    pause: bool,
    /// Why the episode ended, when it ran to its end (`done`).
    episode: Option<EpisodeEnd>,
}

enum Next {
    Wait,
    Start(u64),
    End(Ending),
}

pub(super) fn spawn(lab: &Arc<Lab>) -> Result<(), LabError> {
    let mut threads = lab.threads.lock().map_err(|_| LabError::Host("the lab's threads are unusable".into()))?;
    for (name, work) in [("lab-checks", checks as fn(&Lab)), ("lab-runner", robot as fn(&Lab))] {
        let lab = lab.clone();
        let thread = std::thread::Builder::new()
            .name(name.into())
            .spawn(move || work(&lab))
            .map_err(|e| LabError::Host(format!("cannot start the lab's thread {name}: {e}")))?;
        threads.push(thread);
    }
    Ok(())
}

pub(super) fn checks(lab: &Lab) {
    while !lab.is_stopping() {
        let next = {
            let Ok(book) = lab.book.lock() else { return };
            let next = book.experiments.values().find(|r| r.state == ExperimentState::Checking).map(|r| r.id);
            if next.is_none() {
                let _ = lab.changed.wait_timeout(book, Duration::from_secs(1));
                continue;
            }
            next
        };
        if let Some(id) = next
            && let Err(e) = check(lab, id)
        {
            tracing::error!("experiment {id}: the lab could not check it: {e}");
            fail(lab, id, &format!("failed: {e}"));
        }
    }
}

/// Ends experiment `id` as `failed` (the host's problem), naming `reason`.
fn fail(lab: &Lab, id: u64, reason: &str) {
    if let Ok(mut book) = lab.lock()
        && book.experiments.get(&id).is_some_and(|r| !r.state.is_final())
    {
        let _ = lab.transition(&mut book, id, ExperimentState::Failed, reason, vec![reason.to_string()]);
    }
}

/// Ends experiment `id` as `refused`, with every reason.
fn refuse(lab: &Lab, id: u64, cause: &str, reasons: Vec<String>) -> Result<(), LabError> {
    let mut book = lab.lock()?;
    if book.experiments.get(&id).is_some_and(|r| !r.state.is_final()) {
        lab.transition(&mut book, id, ExperimentState::Refused, cause, reasons)?;
    }
    Ok(())
}

fn user(lab: &Lab, name: &str) -> Option<Principal> {
    lab.store().users().get(name).map(|u| u.principal)
}

/// Who submitted `record`: a user of this host, or, for a lab's
/// experiment, the lab's user with the rights the lab vouched for.
fn submitter(lab: &Lab, record: &ExperimentRecord) -> Option<Principal> {
    match &record.origin {
        Some(origin) => {
            Some(Principal { name: record.submitter.clone(), role: origin.role, platforms: origin.platforms.clone() })
        }
        None => user(lab, &record.submitter),
    }
}

/// Checks experiment `id` again and runs its preflight.
fn check(lab: &Lab, id: u64) -> Result<(), LabError> {
    let (record, baseline) = {
        let book = lab.lock()?;
        let record = book.experiments.get(&id).cloned().ok_or_else(|| super::not_found(id))?;
        (record, lab.baseline(&book.lab))
    };
    let Some(submitter) = user(lab, &record.submitter) else {
        let reason = format!("refused: the submitter '{}' is no longer a user", record.submitter);
        return refuse(lab, id, &reason, vec![reason.clone()]);
    };
    if let Err(e) = lab.deployer.check_experiment_set(&submitter, record.set, baseline) {
        return match LabError::from(e) {
            LabError::Invalid(diagnostics) => refuse(
                lab,
                id,
                "refused: the set no longer validates",
                diagnostics.0.iter().map(|d| format!("check: {d}")).collect(),
            ),
            e @ (LabError::Forbidden(_) | LabError::NotFound(_) | LabError::BadRequest(_)) => {
                let reason = format!("check: {e}");
                refuse(lab, id, "refused: the set cannot run as an experiment", vec![reason])
            }
            e => Err(e),
        };
    }
    let settings = {
        let mut book = lab.lock()?;
        if book.experiments.get(&id).is_none_or(|r| r.state != ExperimentState::Checking) {
            return Ok(());
        }
        lab.transition(&mut book, id, ExperimentState::Preflight, "checked; it runs in the simulator first", vec![])?;
        book.lab.settings.clone()
    };
    let dir = lab.store().experiment_dir(id);
    let run_dir = dir.join("preflight-run");
    let _ = std::fs::remove_dir_all(&run_dir);
    std::fs::create_dir_all(&run_dir).map_err(|e| LabError::Host(format!("cannot make {}: {e}", run_dir.display())))?;
    let world = match &settings.preflight_world {
        Some(name) => {
            let worlds = lab.store().worlds()?;
            let stored = worlds
                .get(name)
                .ok_or_else(|| LabError::Host(format!("the preflight world '{name}' is not stored")))?;
            Some(PreflightWorld { name: name.clone(), sha256: stored.sha256.clone() })
        }
        None => None,
    };
    let set = lab.store().set(record.set)?;
    let comment = format!(
        "set {} of {}, in its preflight form (docs/lab.md), written by subsume for experiment {id}",
        set.id, set.created_by
    );
    let written = match materialize::write_preflight_form(
        lab.store(),
        &set,
        world.as_ref(),
        settings.start_pose(),
        &run_dir,
        &comment,
    ) {
        Ok(written) => written,
        Err(MaterializeError::NotSimulable(why)) => {
            let reason = format!("preflight: {why}");
            return refuse(lab, id, "refused: it cannot run in the simulator", vec![reason]);
        }
        Err(e) => return Err(LabError::Host(e.to_string())),
    };
    let duration = Duration::from_secs_f64(record.duration_s);
    // The replay against the owner's reference recording is information,
    // never a refusal.
    let replay = settings.reference_recording.as_deref().map(|reference| {
        let admin = Principal::host(crate::deploy::LAB_USER);
        match lab.deployer.replay_set(&admin, record.set, reference, &[]) {
            Ok(report) => serde_json::json!({ "reference": reference, "report": report }),
            Err(e) => serde_json::json!({ "reference": reference, "error": e.to_string() }),
        }
    });
    let cancelled = || lab.is_stopping() || lab.book.lock().map(|b| b.cancels.contains_key(&id)).unwrap_or(true);
    // The task it was submitted under: its end conditions end the preflight
    // as they will end the run.
    let task = record.settings.task.as_ref();
    // Its runs, each but the first with the timing a robot has, seeded
    // (docs/lab.md, "Timing").
    let runs = Runs {
        robot: &written.robot,
        duration,
        criteria: &settings.criteria,
        task,
        timing: settings.preflight_timing,
        experiment: id,
    };
    let outcome = preflight_runs::run_all(&lab.options.preflight, &runs, &dir, &cancelled).map(|(outcome, _)| outcome);
    // The robot file in its preflight form stays with the results; what it
    // named is in the store already.
    if let Err(e) = std::fs::rename(&written.robot, dir.join(bundle::ROBOT)) {
        tracing::warn!("experiment {id}: cannot keep its robot file: {e}");
    }
    for (name, _) in written.files.iter().filter(|(n, _)| n.starts_with("files/")) {
        let to = dir.join(name);
        if let Some(parent) = to.parent() {
            let _ = std::fs::create_dir_all(parent);
        }
        let _ = std::fs::rename(run_dir.join(name), to);
    }
    let _ = std::fs::remove_dir_all(&run_dir);
    // The preflight's score, beside the run's to come (before the lock: it
    // reads the whole recording).
    let preflight_score = match (&outcome, &record.settings.task) {
        (Ok(Outcome::Judged { .. }), Some(task)) => {
            match bundle::write_score_of(lab.store(), id, task, bundle::PREFLIGHT_RECORDING, bundle::PREFLIGHT_SCORE) {
                Ok(score) => Some(score),
                Err(why) => {
                    tracing::warn!("experiment {id}: its preflight could not be scored: {why}");
                    None
                }
            }
        }
        _ => None,
    };
    let mut book = lab.lock()?;
    if let Some(record) = book.experiments.get_mut(&id) {
        record.results = bundle::scan(lab.store(), id);
    }
    if let Ok(Outcome::Judged { verdict, wall_s }) = &outcome
        && let Some(record) = book.experiments.get_mut(&id)
    {
        record.preflight = Some(PreflightResult {
            passed: verdict.passed,
            reasons: verdict.reasons.clone(),
            simulated_s: verdict.observed.simulated_s,
            wall_s: *wall_s,
            replay,
            score: preflight_score,
            ended_by: verdict.observed.ended_by,
        });
    }
    let cancel_asked = book.cancels.contains_key(&id);
    match after_preflight(outcome, lab.is_stopping(), cancel_asked) {
        AfterPreflight::Enter { state, cause, reasons } => {
            lab.transition(&mut book, id, state, &cause, reasons)?;
        }
        AfterPreflight::Cancelled => {
            let by = book.cancels.remove(&id).unwrap_or_default();
            let cause = format!("cancelled by {by} during its preflight");
            lab.transition(&mut book, id, ExperimentState::Cancelled, &cause, vec![cause.clone()])?;
        }
        AfterPreflight::Stays => {}
    }
    book.cancels.remove(&id);
    Ok(())
}

/// What a preflight's outcome makes of its experiment.
#[derive(Debug, PartialEq)]
enum AfterPreflight {
    /// It goes to `state` for `cause`, with `reasons`.
    Enter { state: ExperimentState, cause: String, reasons: Vec<String> },
    /// Its cancel was asked for: cancelled, naming who asked.
    Cancelled,
    /// The host stops: it stays in its preflight and is checked again when
    /// the host starts.
    Stays,
}

/// The preflight outcome's mapping to a state, pure: passed -> queued;
/// judged and failed, did not start, or too slow -> refused (the
/// submitter's); starved or broken -> failed (the host's); cancelled ->
/// cancelled, unless the host is `stopping`. A cancel asked for while it
/// ran (`cancel_asked`) wins over whatever outcome came first: the
/// preflight may end by itself between the ask and its next look, and the
/// one who asked waits for the experiment to end.
fn after_preflight(outcome: Result<Outcome, PreflightError>, stopping: bool, cancel_asked: bool) -> AfterPreflight {
    let enter = |state, cause: String, reasons| AfterPreflight::Enter { state, cause, reasons };
    if cancel_asked {
        return AfterPreflight::Cancelled;
    }
    match outcome {
        Ok(Outcome::Judged { verdict, wall_s }) if verdict.passed => enter(
            ExperimentState::Queued,
            format!("passed its preflight ({:.0} s simulated in {wall_s:.1} s); queued", verdict.observed.simulated_s),
            vec![],
        ),
        Ok(Outcome::Judged { verdict, .. }) => {
            enter(ExperimentState::Refused, "refused by its preflight".into(), verdict.reasons)
        }
        Ok(Outcome::DidNotStart(errors)) => {
            enter(ExperimentState::Refused, "refused: it did not start in the simulator".into(), errors)
        }
        Ok(Outcome::Starved { cpu, waited }) => {
            let reason = format!(
                "failed: the host was too busy to run its preflight (it got {:.1} s of cpu in {} s); submit it again",
                cpu.as_secs_f64(),
                waited.as_secs()
            );
            enter(ExperimentState::Failed, reason.clone(), vec![reason])
        }
        Ok(Outcome::TooSlow { limit }) => {
            let reason = format!(
                "preflight: it used more than {} s of cpu without finishing (its components use most of their budgets)",
                limit.as_secs()
            );
            enter(ExperimentState::Refused, "refused: its preflight was too slow".into(), vec![reason])
        }
        Err(PreflightError::Cancelled) if stopping => AfterPreflight::Stays,
        Err(PreflightError::Cancelled) => AfterPreflight::Cancelled,
        Err(e) => {
            let reason = format!("failed: {e}");
            enter(ExperimentState::Failed, reason.clone(), vec![reason])
        }
    }
}

fn robot(lab: &Lab) {
    while !lab.is_stopping() {
        let next = match lab.lock() {
            Ok(mut book) => {
                let next = decide(lab, &mut book);
                if matches!(next, Next::Wait) {
                    let _ = lab.changed.wait_timeout(book, POLL);
                    continue;
                }
                next
            }
            Err(_) => return,
        };
        match next {
            Next::Wait => {}
            Next::Start(id) => start(lab, id),
            Next::End(ending) => end(lab, &ending),
        }
    }
}

/// The holder of the reservation in effect may drive until it ends.
fn grant(lab: &Lab, book: &mut Book) {
    let now = unix_now_ms();
    let granted = queue::reservation_at(&book.lab.reservations, now).map(|r| (r.user.clone(), r.end_ms));
    if granted != book.granted {
        if let Some(directory) = lab.deployer.services.get::<crate::store::users::Directory>() {
            directory.grants.set(granted.clone());
        }
        match &granted {
            Some((user, until)) => {
                tracing::info!("{user}'s reservation begins: they may drive until {}", crate::deploy::utc_time(*until))
            }
            None => tracing::info!("no reservation is in effect"),
        }
        book.granted = granted;
        lab.notify();
    }
}

/// What ends the running experiment early so far, by its latest live
/// status (published every `LIVE_PERIOD` while watched).
#[derive(Debug, PartialEq)]
enum EarlyEnd {
    /// It breaks the owner's criteria (`end_run_on_breach`): why.
    Breach(String),
    /// One of its task's end conditions holds.
    Episode(EpisodeEnd),
}

/// How the running experiment ends early by its latest live status, if it
/// does: the owner's criteria first (a breach aborts it), then its task's
/// end conditions (the episode is done). Each status is looked at once.
fn early_end(running: &mut OnRobot) -> Option<EarlyEnd> {
    let watch = running.watch.as_mut()?;
    if !watch.live.has_changed().unwrap_or(false) {
        return None;
    }
    let status = watch.live.borrow_and_update().clone();
    let status = status.as_ref().as_ref()?;
    if status.experiment.as_ref().map(|e| e.id) != Some(running.id) {
        return None;
    }
    if let Some(criteria) = &watch.criteria
        && let Some(why) = super::verdict::breach(criteria, &super::preflight::outcome(&status.report))
    {
        return Some(EarlyEnd::Breach(why));
    }
    let episode = watch.episode.as_mut()?;
    let seen = Seen::in_report(&status.report, episode.pose_port());
    episode.look(seen).map(EarlyEnd::Episode)
}

/// Notes each queued experiment's first ETA, and refuses those that have
/// waited past `queue::stuck_at`, saying why (nothing silently stuck).
/// On a lab server, one being dispatched to a robot (its placement names
/// it) is that robot's to start or refuse, not stuck.
pub(super) fn refuse_stuck(lab: &Lab, book: &mut Book) {
    let now = unix_now_ms();
    let min_ms = book.lab.settings.stuck_after_min_s.saturating_mul(1000);
    let queued: Vec<(u64, u64, Option<u64>)> = book
        .experiments
        .values()
        .filter(|r| r.state == ExperimentState::Queued)
        .filter(|r| r.placement.as_ref().is_none_or(|p| p.robot.is_none()))
        .map(|r| {
            let at =
                r.history.iter().rev().find(|c| c.state == ExperimentState::Queued).map_or(r.submitted_ms, |c| c.at_ms);
            (r.id, at, r.first_wait_ms)
        })
        .collect();
    if queued.is_empty() {
        return;
    }
    // A held queue has no ETAs: none is computed at every look while it
    // holds (the runner looks every 50 ms).
    let unestimated = queued.iter().any(|(_, _, first)| first.is_none());
    let etas = if unestimated && book.held.is_none() { lab.etas(book, now) } else { Vec::new() };
    for (id, queued_at, first_wait) in queued {
        let noted =
            first_wait.is_none().then(|| etas.iter().find(|(e, _)| *e == id).and_then(|(_, eta)| *eta)).flatten();
        if let Some(eta) = noted
            && let Some(mut record) = book.experiments.get(&id).cloned()
        {
            record.first_wait_ms = Some(eta.saturating_sub(queued_at));
            match lab.store().lock().and_then(|w| w.put_experiment(&record)) {
                Ok(()) => {
                    book.experiments.insert(id, record);
                }
                Err(e) => tracing::error!("experiment {id}: its first ETA was not stored: {e}"),
            }
        }
        let first_wait = book.experiments.get(&id).and_then(|r| r.first_wait_ms);
        if now < queue::stuck_at(queued_at, first_wait, min_ms) {
            continue;
        }
        let waited = crate::deploy::utc_time(queued_at);
        let estimate = match first_wait {
            Some(w) => format!("twice its first estimate of {} s", w.div_ceil(1000)),
            None => "it never had an estimate".to_string(),
        };
        let why = match &book.held {
            Some(held) => format!(": {held}"),
            None => String::new(),
        };
        let cause = format!(
            "refused: queued at {waited}, it did not start in time ({estimate}; at least {} s){why}",
            min_ms / 1000
        );
        if let Err(e) = lab.transition(book, id, ExperimentState::Refused, &cause, vec![cause.clone()]) {
            tracing::error!("experiment {id}: {e}");
        }
    }
}

/// What the runner does now.
fn decide(lab: &Lab, book: &mut Book) -> Next {
    grant(lab, book);
    let locks = lab.deployer.services.get::<Locks>();
    let engaged = locks.as_ref().and_then(|l| l.engaged().into_iter().next());
    if let Some(running) = book.running.as_mut() {
        let early = early_end(running);
        let running = running.clone();
        let id = running.id;
        if let Some((_, by, what)) = book.preempt.clone().filter(|(p, _, _)| *p == id) {
            return Next::End(Ending {
                id,
                state: ExperimentState::Cancelled,
                cause: format!("cancelled: admin {by} is about to {what}"),
                pause: true,
                episode: None,
            });
        }
        if let Some(by) = book.cancels.get(&id) {
            return Next::End(Ending {
                id,
                state: ExperimentState::Cancelled,
                cause: format!("cancelled by {by}"),
                pause: false,
                episode: None,
            });
        }
        if let Some(cause) = book.aborts.get(&id) {
            let cause = cause.clone();
            return Next::End(Ending { id, state: ExperimentState::Aborted, cause, pause: false, episode: None });
        }
        if let Some(lock) = engaged {
            return Next::End(Ending {
                id,
                state: ExperimentState::Aborted,
                cause: format!("aborted: emergency stop by {} ({})", lock.by, lock.how),
                pause: false,
                episode: None,
            });
        }
        match early {
            Some(EarlyEnd::Breach(why)) => {
                return Next::End(Ending {
                    id,
                    state: ExperimentState::Aborted,
                    cause: format!("aborted: ended early by the owner's criteria: {why}"),
                    pause: false,
                    episode: None,
                });
            }
            Some(EarlyEnd::Episode(end)) => {
                let cause = match end {
                    EpisodeEnd::Goal => "the robot reached the task's goal (its end condition goal)",
                    EpisodeEnd::Collision => "its first collision (the task's end condition collision)",
                    EpisodeEnd::TimeOut => "its time is up",
                };
                return Next::End(Ending {
                    id,
                    state: ExperimentState::Done,
                    cause: cause.into(),
                    pause: false,
                    episode: Some(end),
                });
            }
            None => {}
        }
        if lab.deployer.graph_now_ns() >= running.ends_ns {
            return Next::End(Ending {
                id,
                state: ExperimentState::Done,
                cause: "its time is up".into(),
                pause: false,
                episode: Some(EpisodeEnd::TimeOut),
            });
        }
        refuse_stuck(lab, book);
        return Next::Wait;
    }
    if book.self_testing {
        return Next::Wait;
    }
    let now = unix_now_ms();
    let waiting = Lab::waiting(book);
    let view = QueueView {
        now_ms: now,
        running_until_ms: None,
        waiting: &waiting,
        reservations: &book.lab.reservations,
        paused: book.lab.paused,
        turnaround_ms: TURNAROUND.as_millis() as u64,
    };
    let next = queue::next_to_start(&view);
    let (manual, confirmed) = (book.lab.settings.reset == ResetPolicy::Manual, book.reset_confirmed);
    let awaits_reset = |id| manual && confirmed != Some(id);
    // The same answer at every look while nothing changes: the views (and
    // the ETAs they hide while held) must not flap between looks.
    lab.watch_battery(book);
    let maintenance = book.lab.maintenance.clone();
    if book.resting_until_ms.is_some_and(|until| now >= until) {
        book.resting_until_ms = None;
    }
    let resting = book.resting_until_ms.zip(book.lab.settings.duty_cycle);
    let held = match (next, &engaged) {
        (Some(_), Some(lock)) => {
            Some(format!("the emergency stop is engaged (by {}): the queue waits for its release", lock.by))
        }
        (Some(_), None) if maintenance.is_some() => maintenance.as_ref().map(|m| {
            format!(
                "the robot is in maintenance since {} ({}: {}): the queue waits for an admin to end it",
                crate::walltime::shown(m.since_ms),
                m.by,
                m.reason
            )
        }),
        (Some(_), None) if resting.is_some() => resting.map(|(until, duty)| {
            format!(
                "the robot rests until {} (the owner's duty cycle: {} s of experiments, then {} s of rest)",
                crate::walltime::shown(until),
                duty.run_s,
                duty.rest_s
            )
        }),
        (Some(id), None) if awaits_reset(id) => {
            Some(format!("experiment {id} waits for the robot to be reset (an admin confirms)"))
        }
        _ => None,
    };
    if held != book.held {
        book.held = held;
        lab.notify();
    }
    // After `held`: an ETA noted while the queue is held would be wrong.
    refuse_stuck(lab, book);
    let Some(id) = next else { return Next::Wait };
    if engaged.is_some() || maintenance.is_some() || resting.is_some() {
        return Next::Wait;
    }
    if awaits_reset(id) {
        if book.awaiting_reset != Some(id) {
            book.awaiting_reset = Some(id);
            lab.notify();
        }
        return Next::Wait;
    }
    Next::Start(id)
}

/// Starts experiment `id` on the robot.
fn start(lab: &Lab, id: u64) {
    let prepared = (|| {
        let mut book = lab.lock()?;
        let record = book.experiments.get(&id).cloned().ok_or_else(|| super::not_found(id))?;
        if record.state != ExperimentState::Queued {
            return Ok(None);
        }
        // A lab's dispatch starts only before the lab stops waiting for
        // its answer: later, the lab has placed it elsewhere or refused it.
        if let Some(start_by) = record.origin.as_ref().and_then(|o| o.start_by_unix_ms)
            && unix_now_ms() >= start_by
        {
            let cause = format!(
                "cancelled: its lab '{}' stopped waiting for it at {} before it could start here",
                record.origin.as_ref().map_or("", |o| o.lab.as_str()),
                crate::deploy::utc_time(start_by)
            );
            lab.transition(&mut book, id, ExperimentState::Cancelled, &cause, vec![cause.clone()])?;
            return Ok(None);
        }
        // An admin's self-test began since the runner decided: it runs on
        // the baseline, so the start waits for it (decided again after).
        if book.self_testing {
            return Ok(None);
        }
        book.starting = Some(id);
        let baseline = lab.baseline(&book.lab);
        let drive = book.lab.settings.drive_reset().cloned();
        Ok::<_, LabError>(Some((record, baseline, book.lab.settings.reset, drive)))
    })();
    let (record, baseline, reset, drive) = match prepared {
        Ok(Some(prepared)) => prepared,
        Ok(None) => return,
        Err(e) => return fail(lab, id, &format!("failed: {e}")),
    };
    if let Some(drive) = drive
        && !reset_by_driving(lab, id, baseline, &drive)
    {
        return;
    }
    let outcome = start_on_robot(lab, &record, baseline, reset);
    let Ok(mut book) = lab.lock() else { return };
    book.starting = None;
    match outcome {
        Ok(on_robot) => {
            book.running = Some(on_robot);
            book.awaiting_reset = None;
            book.reset_confirmed = None;
            book.held = None;
            let cause = "started on the robot from a fresh start, recording";
            if let Err(e) = lab.transition(&mut book, id, ExperimentState::Running, cause, vec![]) {
                tracing::error!("experiment {id} runs but its record was not stored: {e}");
            }
        }
        Err((state, reason)) => {
            let cause = format!("{}: {reason}", state.name());
            let _ = lab.transition(&mut book, id, state, &cause, vec![reason]);
        }
    }
}

/// The owner's reset by driving before experiment `id`: its outcome goes
/// on the record; false (the experiment stays queued, the robot out of
/// service) when it failed.
fn reset_by_driving(lab: &Lab, id: u64, baseline: u64, drive: &DriveReset) -> bool {
    let outcome = lab.drive_reset(id, baseline, drive);
    let Ok(mut book) = lab.lock() else { return false };
    let passed = outcome.passed;
    if let Some(record) = book.experiments.get(&id) {
        let mut record = record.clone();
        record.reset = Some(outcome.clone());
        match lab.store().lock().and_then(|w| w.put_experiment(&record)) {
            Ok(()) => {
                book.experiments.insert(id, record);
            }
            Err(e) => tracing::error!("experiment {id}: its reset's outcome was not stored: {e}"),
        }
    }
    if !passed {
        book.starting = None;
        lab.keep_failed_reset(&mut book, id, &outcome);
        lab.notify();
    }
    passed
}

fn start_on_robot(
    lab: &Lab,
    record: &ExperimentRecord,
    baseline: u64,
    reset: ResetPolicy,
) -> Result<OnRobot, (ExperimentState, String)> {
    let refused = |why: String| (ExperimentState::Refused, why);
    let failed = |why: String| (ExperimentState::Failed, why);
    let submitter = submitter(lab, record)
        .ok_or_else(|| refused(format!("the submitter '{}' is no longer a user", record.submitter)))?;
    let reset_sim = reset == ResetPolicy::Sim;
    if reset_sim && !lab.deployer.has_simulated_robot().map_err(|e| failed(e.to_string()))? {
        return Err(failed("the reset policy is sim, but the robot has no simulated robot to reset".into()));
    }
    let started_unix_ms = unix_now_ms();
    let duration_ms = (record.duration_s * 1000.0) as u64;
    let tag = RunningExperiment {
        id: record.id,
        submitter: record.submitter.clone(),
        set: record.set,
        label: record.label.clone(),
        started_unix_ms,
        ends_unix_ms: started_unix_ms + duration_ms,
    };
    let mut about = BTreeMap::from([
        ("experiment".to_string(), record.id.to_string()),
        ("submitter".to_string(), record.submitter.clone()),
        ("set".to_string(), record.set.to_string()),
        ("label".to_string(), record.label.clone()),
    ]);
    for component in &record.components {
        if let Some(sha) = &component.sha256 {
            about.insert(format!("sha256.{}", component.name), sha.clone());
        }
    }
    let path = run_recording(lab.store(), record.id);
    let started_ns = lab.deployer.graph_now_ns();
    lab.deployer.start_experiment(&submitter, tag, path, about, reset_sim).map_err(|e| match e {
        DeployError::Invalid(d) => refused(format!("at its turn the set no longer validates: {d}")),
        DeployError::Forbidden(m) | DeployError::Conflict(m) => refused(format!("at its turn: {m}")),
        DeployError::Start(errors) => refused(format!(
            "at its turn the set did not start: {}",
            errors.iter().map(ToString::to_string).collect::<Vec<_>>().join("; ")
        )),
        other => failed(other.to_string()),
    })?;
    let criteria = Some(record.settings.criteria).filter(|c| c.end_run_on_breach);
    let episode = record.settings.task.as_ref().and_then(EpisodeWatch::new);
    let watch = (criteria.is_some() || episode.is_some()).then(|| Watch {
        criteria,
        episode,
        live: lab.deployer.live().subscribe(),
    });
    Ok(OnRobot {
        id: record.id,
        baseline,
        started_ns,
        ends_ns: started_ns + duration_ms * 1_000_000,
        started_unix_ms,
        ends_unix_ms: started_unix_ms + duration_ms,
        watch,
    })
}

/// Ends the experiment on the robot: the baseline comes back, the results
/// are written, the record gets its final state.
fn end(lab: &Lab, ending: &Ending) {
    let id = ending.id;
    let (running, task) = {
        let Ok(mut book) = lab.lock() else { return };
        let Some(running) = book.running.clone().filter(|r| r.id == id) else { return };
        if let Err(e) = lab.transition(&mut book, id, ExperimentState::Finishing, &ending.cause, vec![]) {
            tracing::error!("experiment {id}: {e}");
        }
        let task = book.experiments.get(&id).and_then(|r| r.settings.task.clone());
        (running, task)
    };
    let ran_ns = lab.deployer.graph_now_ns().saturating_sub(running.started_ns);
    let ended = lab.deployer.end_experiment(id, running.baseline, &ending.cause, ran_ns);
    // The owner's self-test, on the baseline now back, before anything
    // else can start (the experiment is still the running one).
    let self_test = lab.lock().ok().and_then(|book| book.lab.settings.self_test);
    let self_test = match (&ended, self_test) {
        (Ok(_), Some(settings)) => Some(lab.self_test(Some(id), &settings)),
        _ => None,
    };
    // The cameras' videos, before the lab's lock: seconds of ffmpeg must
    // not hold the portal's views and the queue.
    bundle::write_videos(lab.store(), id);
    // The score, from the recording alone, before the lab's lock too.
    let score = match (&ended, &task) {
        (Ok(_), Some(task)) => Some(bundle::write_score(lab.store(), id, task)),
        _ => None,
    };
    let Ok(mut book) = lab.lock() else { return };
    let duty = book.lab.settings.duty_cycle;
    let (counted, rest) = queue::after_run(duty, book.duty_counted_ms, ran_ns / 1_000_000, unix_now_ms());
    book.duty_counted_ms = counted;
    if let Some(until) = rest {
        tracing::info!("the robot rests until {} (its duty cycle)", crate::walltime::shown(until));
        book.resting_until_ms = Some(until);
    }
    let (state, cause, mut reasons) = match &ended {
        Ok(_) => (ending.state, ending.cause.clone(), Vec::new()),
        Err(e) => {
            let reason = format!("failed: the baseline did not come back ({e}); the emergency stop is engaged");
            (ExperimentState::Failed, reason.clone(), vec![ending.cause.clone(), reason])
        }
    };
    if state != ExperimentState::Done && reasons.is_empty() {
        reasons.push(ending.cause.clone());
    }
    if let Some(Err(why)) = &score {
        tracing::error!("experiment {id}: its run could not be scored: {why}");
        reasons.push(format!("its run could not be scored: {why}"));
    }
    let ended = ended.unwrap_or_default();
    if let Some(record) = book.experiments.get_mut(&id) {
        bundle::write_run_results(lab.store(), record, &ended, running.started_unix_ms, LATE_CYCLE_MS);
        // Why the episode ended, for a run that ran to its end.
        if state == ExperimentState::Done
            && let Some(outcome) = record.run.as_mut().and_then(|run| run.outcome.as_mut())
        {
            outcome.ended_by = ending.episode;
        }
        if let Some(Ok(score)) = score {
            record.score = Some(score);
        }
        if let Some(test) = &self_test {
            bundle::write_self_test(lab.store(), record, test);
        }
    }
    if let Some(test) = self_test {
        lab.keep_self_test(&mut book, test);
    }
    book.running = None;
    book.cancels.remove(&id);
    book.aborts.remove(&id);
    if book.preempt.as_ref().is_some_and(|(p, _, _)| *p == id) {
        book.preempt = None;
    }
    if ending.pause && !book.lab.paused {
        let mut paused = book.lab.clone();
        paused.paused = true;
        match lab.store().lock().and_then(|w| w.put_lab_state(&paused)) {
            Ok(()) => book.lab = paused,
            Err(e) => tracing::error!("the queue could not be paused: {e}"),
        }
    }
    if let Err(e) = lab.transition(&mut book, id, state, &cause, reasons) {
        tracing::error!("experiment {id} ended but its record was not stored: {e}");
    }
    retain(lab, &mut book);
}

/// What a host that starts again does with the records it left: an
/// experiment that ran is `aborted: host stopped` with what it recorded;
/// one in its preflight is checked again. A lab server's experiments on
/// robots ran on without it (`is_server`): it learns their end from the
/// robots.
pub(super) fn recover(
    store: &Store,
    experiments: &mut BTreeMap<u64, ExperimentRecord>,
    is_server: bool,
) -> Result<(), LabError> {
    let now = unix_now_ms();
    let writer = store.lock()?;
    for record in experiments.values_mut() {
        let ran = matches!(record.state, ExperimentState::Running | ExperimentState::Finishing);
        let cause = match record.state {
            _ if ran && is_server => continue,
            _ if ran => "the host stopped while it ran",
            ExperimentState::Preflight => "the host stopped during its preflight; it is checked again",
            _ => continue,
        };
        if ran {
            record.add_reason("aborted: host stopped".into());
            bundle::salvage(store, record);
            record.enter(ExperimentState::Aborted, now, cause)?;
        } else {
            record.enter(ExperimentState::Checking, now, cause)?;
        }
        writer.put_experiment(record)?;
        writer.record(
            super::LAB_AUDIT_USER,
            "experiment",
            &format!("experiment {}", record.id),
            AuditOutcome::Ok(cause),
        );
    }
    Ok(())
}

/// Applies the owner's retention cap to the finished experiments.
pub(super) fn retain(lab: &Lab, book: &mut Book) {
    let cap = book.lab.settings.retention_bytes;
    let changed = bundle::enforce_retention(lab.store(), book.experiments.values_mut(), cap);
    if changed.is_empty() {
        return;
    }
    if let Ok(writer) = lab.store().lock() {
        for id in changed {
            if let Some(record) = book.experiments.get(&id)
                && let Err(e) = writer.put_experiment(record)
            {
                tracing::error!("experiment {id}: {e}");
            }
        }
    }
}

/// The host stops: the experiment on the robot, if any, is aborted with
/// what it recorded and `report`.
pub(super) fn host_stopped(lab: &Lab, report: Option<&crate::report::Report>) {
    let Ok(mut book) = lab.lock() else { return };
    let Some(running) = book.running.take() else { return };
    let id = running.id;
    lab.deployer.forget_experiment();
    let ended = crate::deploy::Ended { report: report.cloned(), recording: None };
    // The host stops: nothing waits on the lab's lock any more.
    bundle::write_videos(lab.store(), id);
    if let Some(record) = book.experiments.get_mut(&id) {
        bundle::write_run_results(lab.store(), record, &ended, running.started_unix_ms, LATE_CYCLE_MS);
    }
    let cause = "aborted: host stopped";
    if let Err(e) = lab.transition(&mut book, id, ExperimentState::Aborted, cause, vec![cause.into()]) {
        tracing::error!("experiment {id}: {e}");
    }
}

#[cfg(test)]
mod tests {
    use std::time::Duration;

    use super::{AfterPreflight, after_preflight};
    use crate::lab::preflight::{Outcome, PreflightError};
    use crate::lab::verdict::{Observations, Verdict};
    use crate::store::experiments::{Criteria, ExperimentState};

    fn judged(passed: bool, reasons: &[&str]) -> Outcome {
        let observed = Observations { simulated_s: 30.0, ..Observations::default() };
        let reasons = reasons.iter().map(|r| r.to_string()).collect();
        Outcome::Judged { verdict: Verdict { passed, reasons, criteria: Criteria::default(), observed }, wall_s: 0.5 }
    }

    #[test]
    fn every_preflight_outcome_has_its_state() {
        let strings = |r: &[&str]| r.iter().map(|s| s.to_string()).collect::<Vec<_>>();
        let crashed = PreflightError::Crashed { status: "signal 9".into(), last: "oom".into() };
        // (case, outcome, the host stopping, a cancel asked, what it makes)
        type Case = (&'static str, Result<Outcome, PreflightError>, bool, bool, AfterPreflight);
        let cases: Vec<Case> = vec![
            (
                "passed",
                Ok(judged(true, &[])),
                false,
                false,
                AfterPreflight::Enter {
                    state: ExperimentState::Queued,
                    cause: "passed its preflight (30 s simulated in 0.5 s); queued".into(),
                    reasons: vec![],
                },
            ),
            (
                "judged and failed",
                Ok(judged(false, &["preflight: collision at 3.0 s"])),
                false,
                false,
                AfterPreflight::Enter {
                    state: ExperimentState::Refused,
                    cause: "refused by its preflight".into(),
                    reasons: strings(&["preflight: collision at 3.0 s"]),
                },
            ),
            (
                "did not start",
                Ok(Outcome::DidNotStart(strings(&["robot.xml:3:5: unknown port"]))),
                false,
                false,
                AfterPreflight::Enter {
                    state: ExperimentState::Refused,
                    cause: "refused: it did not start in the simulator".into(),
                    reasons: strings(&["robot.xml:3:5: unknown port"]),
                },
            ),
            (
                "too slow",
                Ok(Outcome::TooSlow { limit: Duration::from_secs(120) }),
                false,
                false,
                AfterPreflight::Enter {
                    state: ExperimentState::Refused,
                    cause: "refused: its preflight was too slow".into(),
                    reasons: strings(&[
                        "preflight: it used more than 120 s of cpu without finishing (its components use most of their budgets)",
                    ]),
                },
            ),
            (
                "starved: the host's",
                Ok(Outcome::Starved { cpu: Duration::from_millis(1500), waited: Duration::from_secs(600) }),
                false,
                false,
                AfterPreflight::Enter {
                    state: ExperimentState::Failed,
                    cause: "failed: the host was too busy to run its preflight (it got 1.5 s of cpu in 600 s); submit it again".into(),
                    reasons: strings(&[
                        "failed: the host was too busy to run its preflight (it got 1.5 s of cpu in 600 s); submit it again",
                    ]),
                },
            ),
            (
                "crashed: the host's",
                Err(crashed),
                false,
                false,
                AfterPreflight::Enter {
                    state: ExperimentState::Failed,
                    cause: "failed: the preflight process ended without a verdict (signal 9); its last words: oom".into(),
                    reasons: strings(&[
                        "failed: the preflight process ended without a verdict (signal 9); its last words: oom",
                    ]),
                },
            ),
            ("cancelled", Err(PreflightError::Cancelled), false, true, AfterPreflight::Cancelled),
            ("the host stops", Err(PreflightError::Cancelled), true, false, AfterPreflight::Stays),
            // The preflight passed by itself just after the cancel was
            // asked for (a fresh-clone CI run lost that cancel: the
            // experiment went to the queue, the canceller waited 30 s).
            ("a cancel asked as it passed", Ok(judged(true, &[])), false, true, AfterPreflight::Cancelled),
            ("a cancel asked as it failed", Ok(judged(false, &["preflight: collision"])), false, true, AfterPreflight::Cancelled),
            ("a cancel asked as the host stops", Err(PreflightError::Cancelled), true, true, AfterPreflight::Cancelled),
        ];
        for (case, outcome, stopping, cancel_asked, expected) in cases {
            assert_eq!(after_preflight(outcome, stopping, cancel_asked), expected, "{case}");
        }
    }
}
