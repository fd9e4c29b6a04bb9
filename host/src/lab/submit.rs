//! Submitting an experiment: the checks a submission passes at once
//! (permission, label, duration, the set validates against the baseline,
//! the per-user limits under the lab's lock), then its record, which the
//! checker thread takes from `checking`. Old finished records beyond
//! [`MAX_EXPERIMENT_RECORDS`] are forgotten here.

use super::queue::{self, Charge, OverLimit};
use super::{Book, Lab, LabError, LabRole, MIN_DURATION_S, seconds_until};
use crate::deploy::utc_time;
use crate::runtime::locks::unix_now_ms;
use crate::store::experiments::{
    AppliedSettings, ComponentHash, ExperimentRecord, ExperimentState, LabSettings, MAX_EXPERIMENT_RECORDS,
    MAX_LABEL_LEN, NewExperiment, Placement, Target,
};
use crate::store::users::Principal;

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
            self.forget_oldest(&mut book);
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

    /// Forgets the oldest finished experiments beyond
    /// [`MAX_EXPERIMENT_RECORDS`].
    fn forget_oldest(&self, book: &mut Book) {
        let excess = book.experiments.len().saturating_sub(MAX_EXPERIMENT_RECORDS);
        let old: Vec<u64> =
            book.experiments.values().filter(|r| r.state.is_final()).map(|r| r.id).take(excess).collect();
        for id in old {
            match self.store().lock().and_then(|writer| writer.forget_experiment(id)) {
                Ok(()) => {
                    book.experiments.remove(&id);
                }
                Err(e) => tracing::warn!("cannot forget experiment {id}: {e}"),
            }
        }
    }
}

/// The body of a submission.
#[derive(Clone, Debug, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Submission {
    pub set: u64,
    pub duration_s: f64,
    #[serde(default)]
    pub label: String,
    /// On a lab server: which robots may run it (`{"robot": NAME}`,
    /// `{"profile": ID}`); the first free robot when missing.
    #[serde(default)]
    pub target: Option<Target>,
}
