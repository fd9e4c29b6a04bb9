//! The simulator's use cases: what the portal shows of the active set's
//! simulated robot (its world and body) and what it may do to it (reset,
//! pose, pause, resume, step), each audited.

use super::{DeployError, Deployer};
use crate::assemble::registry;
use crate::builtin::{self, Builtin as _};
use crate::config::{ComponentConfig, ComponentSource, RobotConfig};
use crate::sim::builtin::{SimBuiltin, WORLD_PARAM};
use crate::sim::physics::SimStatus;
use crate::sim::world::{self, World};
use crate::sim::{SimError, SimRegistry};
use crate::store::users::Principal;

/// The simulated robot of the active set, for the portal's map.
#[derive(Clone, Debug, serde::Serialize, schemars::JsonSchema)]
pub struct SimView {
    pub component: String,
    pub world: World,
    pub rays: Option<f64>,
    pub fov: Option<f64>,
    pub max_range: Option<f64>,
    pub radius: Option<f64>,
}

/// What the portal may do to the active set's simulated robot.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum SimAction {
    /// Back to the world's start, at rest, time 0.
    Reset,
    /// Put the robot here (m, m, rad), at rest.
    Pose {
        x: f64,
        y: f64,
        heading: f64,
    },
    Pause,
    Resume,
    /// While paused: run the world this many seconds forward.
    Step {
        seconds: f64,
    },
}

impl SimAction {
    pub fn name(&self) -> &'static str {
        match self {
            SimAction::Reset => "reset",
            SimAction::Pose { .. } => "pose",
            SimAction::Pause => "pause",
            SimAction::Resume => "resume",
            SimAction::Step { .. } => "step",
        }
    }

    /// The request as the audit log shows it (`pose x 1.00 y 2.00 heading 0.50`).
    pub fn detail(&self) -> String {
        match self {
            SimAction::Pose { x, y, heading } => format!("pose x {x:.2} y {y:.2} heading {heading:.2}"),
            SimAction::Step { seconds } => format!("step {seconds} s"),
            other => other.name().to_owned(),
        }
    }
}

/// The active set's simulated robot.
fn simulator(config: &RobotConfig) -> Result<&ComponentConfig, DeployError> {
    let sim = registry::kind_of(&SimBuiltin);
    config
        .components
        .iter()
        .find(|c| matches!(c.source, ComponentSource::Builtin(k) if Some(k) == sim))
        .ok_or_else(|| DeployError::NotFound("the active set has no simulated robot".into()))
}

impl Deployer {
    /// Resets, poses, pauses, resumes or steps the active set's simulated
    /// robot; for those who may drive (it moves the robot). Returns the
    /// simulation's state after it.
    pub fn sim_control(&self, user: &Principal, action: SimAction) -> Result<SimStatus, DeployError> {
        let prepared = self.authorise_drive(user).and_then(|()| {
            let (_, config) = self.active()?;
            let name = simulator(&config)?.name.clone();
            let control = self
                .services
                .get::<SimRegistry>()
                .and_then(|registry| registry.get(&name))
                .ok_or_else(|| DeployError::NotFound(format!("the simulated robot '{name}' is not running")))?;
            Ok((name, control))
        });
        // Audited like every change (who, what, when): action `sim-ACTION`,
        // target the simulated robot, detail the request and where it left
        // the robot.
        let target = prepared.as_ref().map(|(name, _)| name.clone()).unwrap_or_else(|_| SimBuiltin.kind().to_string());
        let request = action.detail();
        self.commit(
            &user.name,
            &format!("sim-{}", action.name()),
            &target,
            prepared,
            |_, (name, control)| {
                let refused = |e: SimError| DeployError::Conflict(e.to_string());
                let status = match action {
                    SimAction::Reset => control.reset(),
                    SimAction::Pose { x, y, heading } => control.set_pose(x, y, heading).map_err(refused)?,
                    SimAction::Pause => control.pause(true),
                    SimAction::Resume => control.pause(false),
                    SimAction::Step { seconds } => control.step(seconds).map_err(refused)?,
                };
                tracing::info!(user = %user.name, "simulator: {} ({name})", action.name());
                Ok(status)
            },
            |status| {
                format!(
                    "{request}: t = {:.2} s at x {:.2} y {:.2} heading {:.2}",
                    status.time_s, status.x, status.y, status.heading
                )
            },
        )
    }

    /// The world and body of the active set's simulated robot.
    pub fn sim_view(&self) -> Result<SimView, DeployError> {
        let (set, config) = self.active()?;
        let sim = simulator(&config)?;
        let params = builtin::checked_params(&SimBuiltin, sim)
            .map_err(|_| DeployError::Host(format!("the simulated robot '{}' has bad parameters", sim.name)))?;
        let path = set.base_dir.join(params.text(WORLD_PARAM).map_err(|e| DeployError::Host(e.to_string()))?);
        let world = world::load(&path).map_err(|e| DeployError::Host(format!("cannot read the world: {e}")))?;
        let number = |key: &str| params.number(key).ok();
        Ok(SimView {
            component: sim.name.clone(),
            world,
            rays: number("rays"),
            fov: number("fov"),
            max_range: number("max-range"),
            radius: number("radius"),
        })
    }
}
