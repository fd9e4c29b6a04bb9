//! Who sees which experiments (docs/portal.md, "Who sees what"): a user sees
//! her own experiments, an admin every one; the rest see that one runs, not
//! what it is. Pure: the use cases (`views`, `cancel`, `robots`) and the
//! portal's live status ask here, and one that may not see a record gets
//! the answer a record that does not exist gets.

use crate::store::experiments::ExperimentRecord;
use crate::store::users::{Principal, Role};

/// Whether `user` may see `record`.
pub(super) fn visible(user: &Principal, record: &ExperimentRecord) -> bool {
    sees_experiments_of(user, &record.submitter)
}

/// Whether `user` may see the experiments `submitter` submitted (their
/// records, labels, robot files' names, results): their own, and anyone's
/// for an admin. The rest see that one runs, not what it is.
pub fn sees_experiments_of(user: &Principal, submitter: &str) -> bool {
    user.role == Role::Admin || submitter == user.name
}

/// A live status (as JSON) as `user` may see it: everyone watches the
/// robot, but the running experiment's label and its robot file's name are
/// its submitter's and the admins' ([`sees_experiments_of`]). The robot's
/// portal and a lab server's `/robots/{name}/live` both show it so.
pub fn live_status_for(user: &Principal, status: &mut serde_json::Value) {
    let hidden = status["experiment"]["submitter"].as_str().is_some_and(|s| !sees_experiments_of(user, s));
    if hidden {
        let id = status["experiment"]["id"].clone();
        status["experiment"]["label"] = serde_json::Value::String(String::new());
        status["config"] = serde_json::Value::String(format!("experiment {id}'s robot file"));
    }
}
