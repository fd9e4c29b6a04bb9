//! What users see of the lab: their experiments (an admin: every one) with
//! each queued one's place and ETA, the lab's overview for every tab's
//! banner, and a finished experiment's results bundle. Someone else's
//! experiment answers as a missing one.

use serde::Serialize;

use super::queue::{self, QueueView, Waiting};
use super::{Book, Lab, LabError, TURNAROUND, bundle, not_found, server, visible};
use crate::deploy::RunningExperiment;
use crate::runtime::locks::unix_now_ms;
use crate::store::access::Access;
use crate::store::experiments::{ExperimentRecord, ExperimentState, LabSettings, Reservation};
use crate::store::users::{Principal, Role};

impl Lab {
    /// The queue's ETAs now.
    pub(super) fn etas(&self, book: &Book, now: u64) -> Vec<(u64, Option<u64>)> {
        // Held (an emergency stop, a reset to confirm, maintenance):
        // nobody can say when it goes on, so no ETA is shown.
        let held = book.lab.paused || book.held.is_some();
        if let Some(fleet) = self.fleet() {
            // A lab server: each robot's end, and each experiment's
            // target; one being dispatched starts now.
            let mut etas = Vec::new();
            let mut unplaced = Vec::new();
            for record in book.experiments.values().filter(|r| r.state == ExperimentState::Queued) {
                match record.placement.as_ref() {
                    Some(p) if p.robot.is_some() => etas.push((record.id, (!held).then_some(now))),
                    placement => unplaced.push(queue::Unplaced {
                        id: record.id,
                        target: placement.map(|p| p.target.clone()).unwrap_or_default(),
                        duration_s: record.duration_s,
                    }),
                }
            }
            let turnaround = TURNAROUND.as_millis() as u64;
            etas.extend(queue::fleet_etas(&unplaced, &fleet.freeing(now), now, turnaround, held));
            return etas;
        }
        let waiting = Self::waiting(book);
        let view = QueueView {
            now_ms: now,
            running_until_ms: book.running.as_ref().map(|r| r.ends_unix_ms),
            waiting: &waiting,
            reservations: &book.lab.reservations,
            paused: held,
            turnaround_ms: TURNAROUND.as_millis() as u64,
        };
        queue::etas(&view)
    }

    /// The queued experiments, in submission order.
    pub(super) fn waiting(book: &Book) -> Vec<Waiting> {
        book.experiments
            .values()
            .filter(|r| r.state == ExperimentState::Queued)
            .map(|r| Waiting { id: r.id, user: r.submitter.clone(), duration_ms: (r.duration_s * 1000.0) as u64 })
            .collect()
    }

    fn view(&self, book: &Book, record: &ExperimentRecord, etas: &[(u64, Option<u64>)]) -> ExperimentView {
        let place = etas.iter().position(|(id, _)| *id == record.id).map(|i| i + 1);
        let eta = etas.iter().find(|(id, _)| *id == record.id).and_then(|(_, eta)| *eta);
        let ends = book.running.as_ref().filter(|r| r.id == record.id).map(|r| r.ends_unix_ms);
        ExperimentView {
            record: record.clone(),
            place,
            eta_unix_ms: eta,
            ends_unix_ms: ends,
            awaiting_reset: book.awaiting_reset == Some(record.id),
        }
    }

    /// `user`'s experiments (an admin's: every one), newest first.
    pub fn list(&self, user: &Principal) -> Result<Vec<ExperimentView>, LabError> {
        let book = self.lock()?;
        let etas = self.etas(&book, unix_now_ms());
        Ok(book.experiments.values().rev().filter(|r| visible(user, r)).map(|r| self.view(&book, r, &etas)).collect())
    }

    /// Experiment `id`, if `user` may see it.
    pub fn get(&self, user: &Principal, id: u64) -> Result<ExperimentView, LabError> {
        let book = self.lock()?;
        let record = book.experiments.get(&id).filter(|r| visible(user, r)).ok_or_else(|| not_found(id))?;
        let etas = self.etas(&book, unix_now_ms());
        Ok(self.view(&book, record, &etas))
    }

    /// The lab as `user` sees it (the owner's settings for admins only).
    pub fn overview(&self, user: &Principal) -> Result<LabView, LabError> {
        let book = self.lock()?;
        let now = unix_now_ms();
        // Everyone sees that an experiment runs and until when; its label
        // is its submitter's.
        let running = self.deployer.experiments().running().map(|mut running| {
            if !super::sees_experiments_of(user, &running.submitter) {
                running.label.clear();
            }
            running
        });
        Ok(LabView {
            running,
            queued: book.experiments.values().filter(|r| r.state == ExperimentState::Queued).count(),
            paused: book.lab.paused,
            held: book.held.clone(),
            awaiting_reset: book.awaiting_reset,
            baseline: self.baseline(&book.lab),
            reservations: book.lab.reservations.iter().filter(|r| r.end_ms > now).cloned().collect(),
            reserved_now: queue::reservation_at(&book.lab.reservations, now).cloned(),
            maintenance: book.lab.maintenance.clone(),
            settings: (user.role == Role::Admin).then(|| book.lab.settings.clone()),
            task: book.lab.settings.task.as_ref().map(|task| TaskSummary {
                name: task.name.clone(),
                description: task.description.clone(),
                metric: task.metric,
                better: if task.higher_is_better() { "higher" } else { "lower" },
            }),
            self_tests: (user.role == Role::Admin).then(|| book.lab.self_tests.clone()),
            now_unix_ms: now,
            robots: self.fleet().map(|f| f.robots_with(now, &book.lab.baselines)),
        })
    }

    /// Who may see what of the store now (`store::access`, with the
    /// owner's lab kit setting), and the baseline's set.
    pub fn access(&self) -> Result<(Access, u64), LabError> {
        let (kit, baseline) = {
            let book = self.lock()?;
            (book.lab.settings.kit, self.baseline(&book.lab))
        };
        Ok((self.deployer.access_with_kit(kit)?, baseline))
    }

    /// The files of experiment `id`'s results bundle, if `user` may see
    /// it: see [`bundle::contents`]. Only what `user` may read is in it:
    /// a component's bytes and the robot file when they are `user`'s own,
    /// shared with the lab, or the robot's where the lab kit lets them
    /// leave the robot; the record names every component's hash.
    pub fn results(&self, user: &Principal, id: u64) -> Result<bundle::Contents, LabError> {
        let record = {
            let book = self.lock()?;
            book.experiments.get(&id).filter(|r| visible(user, r)).cloned().ok_or_else(|| not_found(id))?
        };
        if !record.state.is_final() {
            return Err(LabError::Conflict(format!(
                "experiment {id} is {}: its results come when it ends",
                record.state.name()
            )));
        }
        let (access, _) = self.access()?;
        let components = self.store().components()?;
        let set = self.store().set(record.set).ok();
        let readable = bundle::Readable {
            robot_file: set.as_ref().is_some_and(|set| access.may_read_set(user, set)),
            component: &|sha: &str| {
                let records: Vec<_> = components.values().filter(|c| c.sha256 == sha).collect();
                if records.is_empty() {
                    // Pinned from a robot's set, not uploaded: the robot's.
                    access.may_read(user, crate::deploy::BOOT_USER)
                } else {
                    records.iter().any(|c| access.may_read_component(user, c))
                }
            },
        };
        bundle::contents(self.store(), &record, &readable).map_err(LabError::from)
    }
}

/// An experiment as its submitter (or an admin) sees it.
#[derive(Clone, Debug, Serialize, schemars::JsonSchema)]
pub struct ExperimentView {
    #[serde(flatten)]
    pub record: ExperimentRecord,
    /// Place in the queue (1: next), while queued.
    pub place: Option<usize>,
    /// When it is expected to start (ms since the Unix epoch), while queued.
    pub eta_unix_ms: Option<u64>,
    /// When it ends (ms since the Unix epoch), while it runs.
    pub ends_unix_ms: Option<u64>,
    /// It is next, and waits for an admin to confirm the robot was reset.
    pub awaiting_reset: bool,
}

/// The owner's task as everyone sees it.
#[derive(Clone, Debug, Serialize, schemars::JsonSchema)]
pub struct TaskSummary {
    pub name: String,
    pub description: String,
    pub metric: crate::store::task::Metric,
    /// `lower` or `higher`: which value ranks first.
    #[schemars(extend("enum" = ["lower", "higher"]))]
    pub better: &'static str,
}

/// The lab as a user sees it.
#[derive(Clone, Debug, Serialize, schemars::JsonSchema)]
pub struct LabView {
    /// The experiment on the robot now, for every tab's banner.
    pub running: Option<RunningExperiment>,
    pub queued: usize,
    pub paused: bool,
    /// Why the head of the queue waits, when it does (a lock, a reset).
    pub held: Option<String>,
    pub awaiting_reset: Option<u64>,
    pub baseline: u64,
    pub reservations: Vec<Reservation>,
    /// The reservation in effect now.
    pub reserved_now: Option<Reservation>,
    /// Why the robot is out of service, when it is: no experiment starts.
    pub maintenance: Option<crate::store::experiments::Maintenance>,
    /// The robot's newest self-tests, oldest first (admins only).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub self_tests: Option<Vec<crate::store::experiments::SelfTest>>,
    /// On a lab server: every robot it knows.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub robots: Option<Vec<server::RobotView>>,
    /// The owner's settings (admins only).
    pub settings: Option<LabSettings>,
    /// The owner's task, for everyone: what runs are scored against, and
    /// the name of its leaderboard.
    pub task: Option<TaskSummary>,
    /// The host's clock when this view was made (ms since the Unix epoch):
    /// a client whose own clock is off counts down to `running`'s end and
    /// to ETAs from it.
    pub now_unix_ms: u64,
}
