//! Cancelling an experiment (its submitter or an admin), and an admin's
//! activation ending the one that runs first ([`crate::deploy::Preempt`]).
//! A waiting experiment is cancelled at once; one in its preflight or on
//! the robot is cancelled by the thread that has it, and the request waits
//! for that, at most [`END_WAIT`].

use std::sync::MutexGuard;

use super::{Book, END_WAIT, Lab, LabError, not_found, visible};
use crate::deploy::{Preempt, PreemptError};
use crate::store::experiments::{ExperimentRecord, ExperimentState};
use crate::store::users::Principal;

impl Lab {
    /// Cancels experiment `id` for `user` (its submitter or an admin):
    /// at once while it waits; while it runs, the robot goes back to the
    /// baseline first (this waits for that, at most [`END_WAIT`]).
    pub fn cancel(&self, user: &Principal, id: u64) -> Result<ExperimentRecord, LabError> {
        let target = format!("experiment {id}");
        self.audited(
            &user.name,
            "cancel-experiment",
            &target,
            || self.cancel_inner(user, id),
            |record| record.state.name().to_string(),
        )
    }

    fn cancel_inner(&self, user: &Principal, id: u64) -> Result<ExperimentRecord, LabError> {
        let mut book = self.lock()?;
        let record = book.experiments.get(&id).filter(|r| visible(user, r)).ok_or_else(|| not_found(id))?;
        let cause = format!("cancelled by {}", user.name);
        match record.state {
            s if s.is_final() => Err(LabError::Conflict(format!("experiment {id} has ended already ({})", s.name()))),
            ExperimentState::Queued if book.starting == Some(id) || book.dispatching.contains(&id) => {
                self.cancel_when_it_runs(book, id, &user.name)
            }
            ExperimentState::Checking | ExperimentState::Queued => {
                let record = self.transition(&mut book, id, ExperimentState::Cancelled, &cause, vec![cause.clone()])?;
                Ok(record)
            }
            // In preflight or on the robot: the thread that has it ends it.
            _ => self.cancel_when_it_runs(book, id, &user.name),
        }
    }

    /// Asks the thread that has experiment `id` to cancel it, and waits
    /// (at most [`END_WAIT`]) for it to end.
    fn cancel_when_it_runs(
        &self,
        mut book: MutexGuard<'_, Book>,
        id: u64,
        by: &str,
    ) -> Result<ExperimentRecord, LabError> {
        book.cancels.insert(id, by.to_string());
        self.notify();
        let (book, _) = self
            .changed
            .wait_timeout_while(book, END_WAIT, |b| b.experiments.get(&id).is_some_and(|r| !r.state.is_final()))
            .map_err(|_| LabError::Host("the lab's state is unusable".into()))?;
        book.experiments.get(&id).cloned().ok_or_else(|| not_found(id))
    }
}

impl Preempt for Lab {
    fn preempt(&self, id: u64, by: &str, what: &str) -> Result<String, PreemptError> {
        let mut book = self.book.lock().map_err(|_| PreemptError("the lab's state is unusable".into()))?;
        if book.running.as_ref().is_none_or(|r| r.id != id) {
            return Ok(String::new());
        }
        book.preempt = Some((id, by.to_string(), what.to_string()));
        self.notify();
        let (book, timeout) = self
            .changed
            .wait_timeout_while(book, END_WAIT, |b| b.running.as_ref().is_some_and(|r| r.id == id))
            .map_err(|_| PreemptError("the lab's state is unusable".into()))?;
        if timeout.timed_out() {
            return Err(PreemptError(format!("experiment {id} did not end within {} s", END_WAIT.as_secs())));
        }
        let submitter = book.experiments.get(&id).map(|r| r.submitter.clone()).unwrap_or_default();
        Ok(format!("it cancelled experiment {id} (by {submitter}) first; the queue is paused"))
    }
}
