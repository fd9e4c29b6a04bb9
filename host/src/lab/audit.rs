//! The lab's audit lines: one per use case, refused or not (`audited`, the
//! lab's `deploy::commit`), and the lines of the lab's own state changes.
//! A store that cannot be locked is logged as an error with the line it
//! lost, never skipped in silence.

use super::{Lab, LabError};
use crate::store::Outcome;

impl Lab {
    /// Writes one audit line; a store that cannot be locked is logged as an
    /// error with the line it lost, never skipped in silence.
    pub(super) fn audit(&self, user: &str, action: &str, target: &str, outcome: Outcome<'_>) {
        match self.store().lock() {
            Ok(writer) => writer.record(user, action, target, outcome),
            Err(e) => {
                tracing::error!("cannot lock the store to record {action} by {user} on {target} ({outcome:?}): {e}")
            }
        }
    }

    /// The audit line of a refused or failed request.
    pub(super) fn audit_error(&self, user: &str, action: &str, target: &str, e: &LabError) {
        let detail = e.to_string();
        let outcome = if e.is_failure() { Outcome::Failed(&detail) } else { Outcome::Refused(&detail) };
        self.audit(user, action, target, outcome);
    }

    /// Runs `use_case` for `user` and writes its one audit line whatever
    /// happened: `done(value)` when it succeeded, the refusal or the
    /// failure otherwise. The lab's [`crate::deploy`] `commit`: a lab use
    /// case takes the lab's lock before the store's, so the line is written
    /// after it, and a store that cannot be locked then is logged as an
    /// error, never skipped in silence.
    pub(super) fn audited<T>(
        &self,
        user: &str,
        action: &str,
        target: &str,
        use_case: impl FnOnce() -> Result<T, LabError>,
        done: impl FnOnce(&T) -> String,
    ) -> Result<T, LabError> {
        let result = use_case();
        match &result {
            Ok(value) => self.audit(user, action, target, Outcome::Ok(&done(value))),
            Err(e) => self.audit_error(user, action, target, e),
        }
        result
    }
}
