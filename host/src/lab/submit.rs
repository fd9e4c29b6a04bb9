//! Submitting an experiment: the checks a submission passes at once
//! (permission, label, duration, the set validates against the baseline,
//! the per-user limits under the lab's lock), then its record, which the
//! checker thread takes from `checking`. Old finished records beyond each
//! user's share are forgotten here, the user's own first.

use std::collections::BTreeMap;

use super::queue::{self, Charge, OverLimit};
use super::{Book, Lab, LabError, LabRole, MIN_DURATION_S, seconds_until};
use crate::deploy::utc_time;
use crate::runtime::locks::unix_now_ms;
use crate::store::Outcome;
use crate::store::experiments::{
    AppliedSettings, ComponentHash, ExperimentRecord, ExperimentState, LabSettings, MAX_EXPERIMENT_RECORDS,
    MAX_EXPERIMENT_RECORDS_PER_USER, MAX_LABEL_LEN, NewExperiment, Placement, Target,
};
use crate::store::users::Principal;

/// Most experiments one user submits in [`SUBMISSION_WINDOW_MS`]: a script
/// submitting and cancelling in a loop cannot flood the checker, the
/// store's records or the audit log.
pub const MAX_SUBMISSIONS_PER_WINDOW: usize = 30;
/// The window of that limit.
pub const SUBMISSION_WINDOW_MS: u64 = 60_000;

impl Lab {
    /// Submits set `submission.set` as `user`'s experiment: checked at once
    /// (permission, duration, the set validates against the baseline, the
    /// limits), then preflighted and queued by the lab's threads.
    pub fn submit(&self, user: &Principal, submission: &Submission) -> Result<ExperimentRecord, LabError> {
        let target = format!("set {}", submission.set);
        let submitted = || {
            let (settings, components, baseline) = self.prepare_submit(user, submission)?;
            let mut book = self.lock()?;
            let now = unix_now_ms();
            let duration_ms = (submission.duration_s * 1000.0) as u64;
            self.admit(&book, user, duration_ms, now)?;
            let new = NewExperiment {
                submitter: user.name.clone(),
                set: submission.set,
                label: submission.label.trim().to_string(),
                duration_s: submission.duration_s,
                submitted_ms: now,
                settings: AppliedSettings::of(&settings, baseline),
                components,
            };
            let cause = format!("submitted by {}", user.name);
            let mut record = ExperimentRecord::new(new, ExperimentState::Checking, &cause);
            record.placement = self
                .fleet()
                .map(|_| Placement { target: submission.target.clone().unwrap_or_default(), ..Placement::default() });
            let writer = self.store().lock()?;
            let record = writer.add_experiment(&mut book.lab, record)?;
            drop(writer);
            book.experiments.insert(record.id, record.clone());
            self.forget_oldest(&mut book, &user.name);
            drop(book);
            tracing::info!("experiment {} submitted by {}: set {}", record.id, user.name, submission.set);
            self.notify();
            Ok(record)
        };
        self.audited(&user.name, "submit-experiment", &target, submitted, |record| {
            format!("experiment {} ({} s)", record.id, submission.duration_s)
        })
    }

    /// The checks a submission passes before the lab's lock: the slow
    /// ones (validating the set).
    #[allow(clippy::type_complexity)]
    fn prepare_submit(
        &self,
        user: &Principal,
        submission: &Submission,
    ) -> Result<(LabSettings, Vec<ComponentHash>, u64), LabError> {
        if !user.may_submit() {
            return Err(LabError::Forbidden(format!(
                "{} may not submit experiments (researchers, developers and admins may)",
                user.name
            )));
        }
        let label = submission.label.trim();
        if label.chars().count() > MAX_LABEL_LEN || label.chars().any(char::is_control) {
            return Err(LabError::BadRequest(format!(
                "the label must be at most {MAX_LABEL_LEN} characters, without control characters"
            )));
        }
        if let LabRole::Joined { lab } = &self.options.role {
            return Err(LabError::Conflict(format!(
                "this robot takes its experiments from lab '{lab}': submit them to the lab's server"
            )));
        }
        let (settings, mut baseline, baselines) = {
            let book = self.lock()?;
            (book.lab.settings.clone(), self.baseline(&book.lab), book.lab.baselines.clone())
        };
        match (self.fleet(), &submission.target) {
            (None, Some(_)) => {
                return Err(LabError::BadRequest(
                    "this host is one robot: a target is for a lab server (subsume lab serve)".into(),
                ));
            }
            (Some(fleet), target) => {
                let target = target.clone().unwrap_or_default();
                baseline = fleet.baseline_for(&target, &baselines, baseline)?;
                if baseline == 0 {
                    return Err(LabError::Conflict(
                        "the lab knows no robot yet: experiments are checked against a robot's baseline".into(),
                    ));
                }
            }
            (None, None) => {}
        }
        let duration = submission.duration_s;
        if !duration.is_finite() || duration < MIN_DURATION_S || duration > settings.max_duration_s {
            return Err(LabError::BadRequest(format!(
                "duration_s must be from {MIN_DURATION_S} to the robot's max-duration of {} s, got {}",
                settings.max_duration_s, duration
            )));
        }
        // Her own sets, or the baseline: someone else's set answers as a
        // missing one (store::access).
        let set =
            self.store().set(submission.set).map_err(|_| LabError::NotFound(format!("no set {}", submission.set)))?;
        if submission.set != baseline && !self.deployer.access()?.may_see_set(user, &set) {
            return Err(LabError::NotFound(format!("no set {}", submission.set)));
        }
        let checked = self.deployer.check_experiment_set(user, submission.set, baseline)?;
        let components = checked
            .components
            .into_iter()
            .map(|(name, source, sha256)| ComponentHash { name, source, sha256 })
            .collect();
        Ok((settings, components, baseline))
    }

    /// Whether `user` may have one more experiment of `duration_ms` now
    /// (the per-user limits), with the answer a 429 carries.
    fn admit(&self, book: &Book, user: &Principal, duration_ms: u64, now: u64) -> Result<(), LabError> {
        let recent: Vec<u64> = book
            .experiments
            .values()
            .filter(|r| r.submitter == user.name && r.submitted_ms.saturating_add(SUBMISSION_WINDOW_MS) > now)
            .map(|r| r.submitted_ms)
            .collect();
        if recent.len() >= MAX_SUBMISSIONS_PER_WINDOW {
            let frees = recent.iter().min().map_or(now, |first| first + SUBMISSION_WINDOW_MS);
            return Err(LabError::OverLimit {
                message: format!(
                    "{} submitted {} experiments in the last {} s, the most allowed; submit again in {} s",
                    user.name,
                    recent.len(),
                    SUBMISSION_WINDOW_MS / 1000,
                    seconds_until(frees, now).max(1)
                ),
                retry_after_s: Some(seconds_until(frees, now).max(1)),
            });
        }
        let charges: Vec<Charge> = book
            .experiments
            .values()
            .filter(|r| r.submitter == user.name)
            .map(|r| Charge { submitted_ms: r.submitted_ms, waiting: r.state.is_waiting(), robot_ms: r.robot_ms() })
            .collect();
        let first_start = self
            .etas(book, now)
            .into_iter()
            .filter(|(id, _)| book.experiments.get(id).is_some_and(|r| r.submitter == user.name))
            .filter_map(|(_, eta)| eta)
            .min();
        queue::admit(&book.lab.settings.limits, &charges, duration_ms, now, first_start).map_err(|over| {
            let frees = over.frees_ms();
            let when = match frees {
                Some(at) => format!("it frees at {} (in {} s)", utc_time(at), seconds_until(at, now)),
                None => "it frees when one of them ends or is cancelled".to_string(),
            };
            let message = match over {
                OverLimit::Queued { limit, .. } => {
                    format!("{} has {limit} experiments waiting, the most allowed; {when}", user.name)
                }
                OverLimit::RobotMinutes { limit, used, asked, frees_ms } => {
                    let when = match frees_ms {
                        Some(at) => format!("enough frees at {} (in {} s)", utc_time(at), seconds_until(at, now)),
                        None => format!("an experiment of {asked:.1} min never fits the daily limit"),
                    };
                    format!(
                        "{} has used {used:.1} of {limit} robot-minutes in the last 24 hours and this experiment needs {asked:.1}; {when}",
                        user.name
                    )
                }
            };
            LabError::OverLimit { message, retry_after_s: frees.map(|at| seconds_until(at, now).max(1)) }
        })
    }

    /// Forgets `user`'s oldest finished experiments beyond
    /// [`MAX_EXPERIMENT_RECORDS_PER_USER`], and, beyond
    /// [`MAX_EXPERIMENT_RECORDS`] in all, the oldest of whoever keeps the
    /// most: one user's churn forgets her own records, never another's.
    /// A record whose robot time still counts (it ran within the last
    /// day) is never forgotten, so forgetting never gives robot-minutes
    /// back.
    fn forget_oldest(&self, book: &mut Book, user: &str) {
        let now = unix_now_ms();
        let forgettable = |r: &ExperimentRecord| {
            r.state.is_final()
                && (r.robot_ms() == 0 || r.history.last().is_none_or(|c| c.at_ms.saturating_add(queue::DAY_MS) < now))
        };
        let mut old: Vec<u64> = Vec::new();
        let theirs = book.experiments.values().filter(|r| r.submitter == user).count();
        let excess = theirs.saturating_sub(MAX_EXPERIMENT_RECORDS_PER_USER);
        old.extend(
            book.experiments.values().filter(|r| r.submitter == user && forgettable(r)).map(|r| r.id).take(excess),
        );
        let excess = book.experiments.len().saturating_sub(MAX_EXPERIMENT_RECORDS + old.len());
        if excess > 0 {
            let mut kept: BTreeMap<&str, usize> = BTreeMap::new();
            for record in book.experiments.values() {
                *kept.entry(record.submitter.as_str()).or_default() += 1;
            }
            if let Some((most, _)) = kept.into_iter().max_by_key(|(u, n)| (*n, std::cmp::Reverse(*u))) {
                let most = most.to_string();
                let more: Vec<u64> = book
                    .experiments
                    .values()
                    .filter(|r| r.submitter == most && forgettable(r) && !old.contains(&r.id))
                    .map(|r| r.id)
                    .take(excess)
                    .collect();
                old.extend(more);
            }
        }
        for id in old {
            match self.store().lock().and_then(|writer| writer.forget_experiment(id)) {
                Ok(()) => {
                    if let Some(record) = book.experiments.remove(&id) {
                        let target = format!("experiment {id} of {}", record.submitter);
                        self.audit(
                            super::LAB_AUDIT_USER,
                            "forget-experiment",
                            &target,
                            Outcome::Ok("records kept per user"),
                        );
                    }
                }
                Err(e) => tracing::warn!("cannot forget experiment {id}: {e}"),
            }
        }
    }
}

/// The body of a submission.
#[derive(Clone, Debug, serde::Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct Submission {
    pub set: u64,
    pub duration_s: f64,
    #[serde(default)]
    pub label: String,
    /// On a lab server: which robots may run it (`{"robot": NAME}`,
    /// `{"profile": ID}`); the first free robot when missing. One robot's
    /// portal refuses it (400).
    #[serde(default)]
    pub target: Option<Target>,
}
