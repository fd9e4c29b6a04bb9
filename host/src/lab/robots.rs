//! A lab server's robots as users reach them: the list, one robot's live
//! status, and the lab's STOP (any logged-in user), each STOP audited per
//! robot with its answer. On a robot's own host these answer 404.

use std::sync::Arc;

use serde::Serialize;

use super::{Lab, LabError, server};
use crate::contract::clip;
use crate::runtime::locks::unix_now_ms;
use crate::store::Outcome;
use crate::store::users::Principal;

impl Lab {
    fn fleet_or_refuse(&self) -> Result<&Arc<server::Fleet>, LabError> {
        self.fleet().ok_or_else(|| {
            LabError::NotFound("this host is one robot, not a lab server: GET /api/v1/status shows it".into())
        })
    }

    /// The lab server's robots (any logged-in user).
    pub fn robots(&self) -> Result<Vec<server::RobotView>, LabError> {
        let fleet = self.fleet_or_refuse()?;
        let book = self.lock()?;
        Ok(fleet.robots_with(unix_now_ms(), &book.lab.baselines))
    }

    /// Robot `name`'s live status, asked of it now (any logged-in user).
    /// As `user` may see it (`live_status_for`): another's experiment's
    /// label and robot file name hidden.
    pub fn robot_live(&self, user: &Principal, name: &str) -> Result<serde_json::Value, LabError> {
        let mut status = self.fleet_or_refuse()?.live(name)?;
        super::live_status_for(user, &mut status);
        Ok(status)
    }

    /// The lab's STOP: engages the emergency stop of robot `name`, or of
    /// every robot when `None` (any logged-in user); each robot's answer.
    pub fn stop_robots(&self, user: &Principal, name: Option<&str>) -> Result<Vec<RobotStop>, LabError> {
        let target = name.map_or_else(|| "every robot".to_string(), |n| format!("robot {}", clip(n)));
        let result = self.fleet_or_refuse().and_then(|fleet| fleet.estop(user, name));
        match &result {
            // One line per robot: each robot's answer is its own outcome.
            Ok(answers) => {
                for (robot, answer) in answers {
                    let outcome = match answer {
                        Ok(said) => Outcome::Ok(said),
                        Err(why) => Outcome::Failed(why),
                    };
                    self.audit(&user.name, "lab-estop", &format!("robot {robot}"), outcome);
                }
            }
            Err(e) => self.audit_error(&user.name, "lab-estop", &target, e),
        }
        result.map(|answers| {
            answers
                .into_iter()
                .map(|(robot, answer)| match answer {
                    Ok(said) => RobotStop { robot, engaged: true, message: said },
                    Err(why) => RobotStop { robot, engaged: false, message: why },
                })
                .collect()
        })
    }
}

/// A robot's answer to the lab's STOP.
#[derive(Clone, Debug, Serialize, schemars::JsonSchema)]
pub struct RobotStop {
    pub robot: String,
    pub engaged: bool,
    pub message: String,
}
