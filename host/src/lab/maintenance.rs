//! Maintenance (docs/lab.md, "Maintenance"): an admin takes the robot out
//! of service with a reason, and brings it back. While it is out, no
//! experiment starts (the queue holds, every queued submitter sees why and
//! no ETA); a running one goes on. Stored with the lab's state, so a
//! restart keeps it; the owner's webhooks and mail are told.

use super::{Lab, LabError};
use crate::notify::{EventKind, RobotFacts};
use crate::store::experiments::{MAX_MAINTENANCE_REASON, Maintenance};
use crate::store::users::Principal;
use crate::walltime::unix_now_ms;

impl Lab {
    /// Takes the robot out of service (admins), saying why.
    pub fn enter_maintenance(&self, user: &Principal, reason: &str) -> Result<Maintenance, LabError> {
        let reason = reason.trim();
        if reason.is_empty() || reason.chars().count() > MAX_MAINTENANCE_REASON || reason.chars().any(char::is_control)
        {
            return Err(LabError::BadRequest(format!(
                "a reason for maintenance is 1 to {MAX_MAINTENANCE_REASON} characters without control characters"
            )));
        }
        let entered = Maintenance {
            reason: reason.to_string(),
            by: user.name.clone(),
            since_ms: unix_now_ms(),
            ends_at_battery_v: None,
        };
        let what = self.what_maintenance_holds();
        let lab = self.admin_change(user, "maintenance-start", what, |lab| {
            if let Some(already) = &lab.maintenance {
                return Err(LabError::Conflict(format!(
                    "{what} is in maintenance already (by {}: {})",
                    already.by, already.reason
                )));
            }
            lab.maintenance = Some(entered.clone());
            Ok(format!("out of service: {}", entered.reason))
        })?;
        self.tell_robot(EventKind::RobotMaintenanceStarted, &format!("{} (by {})", entered.reason, user.name));
        Ok(lab.maintenance.unwrap_or(entered))
    }

    /// Brings the robot back into service (admins).
    pub fn end_maintenance(&self, user: &Principal) -> Result<(), LabError> {
        let mut ended = None;
        let what = self.what_maintenance_holds();
        self.admin_change(user, "maintenance-end", what, |lab| {
            ended = lab.maintenance.take();
            match &ended {
                Some(m) => Ok(format!("back in service (was: {})", m.reason)),
                None => Err(LabError::Conflict(format!("{what} is not in maintenance"))),
            }
        })?;
        if let Some(m) = ended {
            self.tell_robot(
                EventKind::RobotMaintenanceEnded,
                &format!("back in service by {} (was: {})", user.name, m.reason),
            );
        }
        Ok(())
    }

    /// What an admin's maintenance takes out of service: this robot, or
    /// on a lab server the whole lab (its queue holds for every robot).
    fn what_maintenance_holds(&self) -> &'static str {
        if self.fleet().is_some() { "the lab" } else { "the robot" }
    }

    pub(super) fn tell_robot(&self, kind: EventKind, reason: &str) {
        let name = self.deployer.active().map(|(_, config)| config.name.clone()).unwrap_or_else(|_| "robot".into());
        self.tell_about_robot(kind, &name, reason);
    }

    /// Tells the owner's webhooks and mail `kind` about robot `name` (this
    /// host's, or one of a lab server's).
    pub(super) fn tell_about_robot(&self, kind: EventKind, name: &str, reason: &str) {
        let Some(notifier) = &self.notifier else { return };
        let facts = RobotFacts { name: name.to_string(), reason: reason.to_string() };
        if let Err(e) = notifier.tell_robot(kind, unix_now_ms(), facts) {
            tracing::error!("robot {name}: its {kind:?} event is lost: {e}");
        }
    }
}
