//! `builtin:sim`: the simulated robot, declared ([`SimBuiltin`]): its
//! parameters with their bounds, the world file it loads (checked with the
//! rest of the robot file), and starting it behind a pseudo-terminal.

use std::f64::consts::TAU;

use super::create2::LIGHT_BUMP_RAYS;
use super::physics::{Body, Simulation};
use super::world::{self, World};
use super::{SimComponent, SimProtocol, SimSettings, SimulatedRobot};
use crate::builtin::{
    BuildContext, Builtin, BuiltinError, CheckContext, ParamDecl, ParamType, Params, Ports, PreflightContext,
    PreflightForm, positive_up_to,
};
use crate::config::ParamProblem;
use crate::robot::protocol::MAX_RANGES;
use crate::robot::translator::DriveGeometry;
use crate::runtime::Component;

/// Largest body radius (m) and longest range (m) of a simulated robot.
pub const MAX_RADIUS_M: f64 = 5.0;
pub const MAX_RANGE_M: f64 = 100.0;
/// Fastest feedback: more would flood the PTY and the control loop.
pub const MAX_FEEDBACK_HZ: f64 = 1000.0;
/// Longest watchdog of the simulated controller.
pub const MAX_CONTROLLER_WATCHDOG_S: f64 = 10.0;

/// The parameter naming the world file.
pub const WORLD_PARAM: &str = "world";

const PARAMS: &[ParamDecl] = &[
    ParamDecl {
        name: WORLD_PARAM,
        ty: ParamType::File { optional: false },
        default: "",
        unit: "",
        doc: "world file, relative to the robot file (config/worlds/*.world), or a world uploaded to the portal",
    },
    ParamDecl {
        name: "protocol",
        ty: ParamType::Choice(&["ascii", "binary", "create2"]),
        default: "ascii",
        unit: "",
        doc: "wire protocol of the simulated controller: ascii, binary (docs/protocols.md) or create2 (iRobot Create 2 OI)",
    },
    ParamDecl {
        name: "wheel-base",
        ty: positive_up_to(crate::robot::builtin::MAX_WHEEL_BASE_M),
        default: "0.3",
        unit: "m",
        doc: "distance between the wheels",
    },
    ParamDecl {
        name: "max-wheel-speed",
        ty: positive_up_to(crate::robot::builtin::MAX_WHEEL_SPEED_M_S),
        default: "0.5",
        unit: "m/s",
        doc: "fastest wheel speed",
    },
    ParamDecl {
        name: "radius",
        ty: positive_up_to(MAX_RADIUS_M),
        default: "0.18",
        unit: "m",
        doc: "the robot is a disc of this radius",
    },
    ParamDecl {
        name: "rays",
        ty: ParamType::Integer { min: 1, max: MAX_RANGES as i64 },
        default: "9",
        unit: "",
        doc: "range rays, spread over fov",
    },
    ParamDecl {
        name: "fov",
        ty: positive_up_to(TAU),
        default: "3.14159",
        unit: "rad",
        doc: "angle covered by the rays",
    },
    ParamDecl {
        name: "max-range",
        ty: positive_up_to(MAX_RANGE_M),
        default: "4.0",
        unit: "m",
        doc: "longest range reading",
    },
    ParamDecl {
        name: "feedback-rate",
        ty: positive_up_to(MAX_FEEDBACK_HZ),
        default: "20",
        unit: "Hz",
        doc: "feedback messages per second",
    },
    ParamDecl {
        name: "controller-watchdog",
        ty: positive_up_to(MAX_CONTROLLER_WATCHDOG_S),
        default: "1.0",
        unit: "s",
        doc: "the simulated controller stops the wheels when no command came for this long",
    },
];

/// The `sim` kind.
pub struct SimBuiltin;

fn load_world(params: &Params, ctx_base: &std::path::Path) -> Result<World, String> {
    let file = params.text("world").unwrap_or_default();
    world::load(&ctx_base.join(file)).map_err(|e| format!("names a bad world file:\n{e}"))
}

fn settings(params: &Params, world: World) -> Result<SimSettings, BuiltinError> {
    let protocol = params.text("protocol")?;
    let protocol = SimProtocol::parse(protocol)
        .ok_or_else(|| BuiltinError::Param { name: "protocol".into(), why: format!("is unknown: '{protocol}'") })?;
    let rays = params.integer("rays")?;
    if protocol == SimProtocol::Create2 && rays != LIGHT_BUMP_RAYS as i64 {
        return Err(BuiltinError::Param {
            name: "rays".into(),
            why: format!("must be {LIGHT_BUMP_RAYS} with protocol create2 (one per light bump), not {rays}"),
        });
    }
    Ok(SimSettings {
        world,
        body: Body {
            radius: params.number("radius")?,
            geometry: DriveGeometry {
                wheel_base: params.number("wheel-base")?,
                max_wheel_speed: params.number("max-wheel-speed")?,
            },
            rays: usize::try_from(rays)
                .map_err(|_| BuiltinError::Param { name: "rays".into(), why: format!("is out of range: {rays}") })?,
            fov: params.number("fov")?,
            max_range: params.number("max-range")?,
        },
        protocol,
        feedback_hz: params.number("feedback-rate")?,
        controller_watchdog: params.seconds("controller-watchdog")?,
        timing: None,
    })
}

impl Builtin for SimBuiltin {
    fn kind(&self) -> &'static str {
        "sim"
    }

    /// Its pseudo-terminal must exist before a serial link opens it.
    fn built_first(&self) -> bool {
        true
    }

    fn world_param(&self) -> Option<&'static str> {
        Some(WORLD_PARAM)
    }

    fn summary(&self) -> &'static str {
        "A simulated differential-drive robot behind a pseudo-terminal"
    }

    fn params(&self) -> &'static [ParamDecl] {
        PARAMS
    }

    fn carried(&self) -> bool {
        true
    }

    fn check(&self, params: &Params, ctx: &mut CheckContext<'_>) -> Vec<ParamProblem> {
        let world = match load_world(params, ctx.base_dir) {
            Ok(world) => world,
            Err(why) => return vec![ParamProblem::new("world", why)],
        };
        // The robot must fit where the world starts it.
        match settings(params, world).map(|s| Simulation::new(s.world, s.body)) {
            Ok(Ok(_)) => Vec::new(),
            Ok(Err(e)) => vec![ParamProblem::new("world", format!("does not fit this robot: {e}"))],
            Err(BuiltinError::Param { name, why }) => vec![ParamProblem::new(&name, why)],
            Err(e) => vec![ParamProblem::new("world", e.to_string())],
        }
    }

    /// The preflight's world, when the lab's owner set one.
    fn preflight(
        &self,
        _params: &Params,
        ctx: &PreflightContext<'_>,
    ) -> Result<PreflightForm, crate::builtin::NotSimulable> {
        let set = ctx.world.map(|world| vec![("world", world.to_string())]).unwrap_or_default();
        Ok(PreflightForm { set, files: Vec::new(), simulated_by: None })
    }

    fn ports(&self, _params: &Params) -> Ports {
        Ports::default()
    }

    fn build(&self, params: &Params, ctx: &mut BuildContext<'_>) -> Result<Box<dyn Component>, BuiltinError> {
        let world =
            load_world(params, ctx.base_dir).map_err(|why| BuiltinError::Param { name: "world".into(), why })?;
        let name = ctx.component()?.name.clone();
        let mut settings = settings(params, world)?;
        // A seeded run's delays and noise (`subsume run --perturb`).
        settings.timing = ctx.services.get::<super::perturb::Perturbation>().map(|p| p.sim_timing(&name));
        let robot = SimulatedRobot::start(&name, settings, ctx.clock.lockstep())
            .map_err(|e| BuiltinError::Refused(format!("the simulated robot did not start: {e}")))?;
        if let Some(registry) = ctx.services.get::<super::SimRegistry>() {
            robot.register(&name, &registry);
        }
        ctx.ptys.insert(name, robot.pty_path().clone());
        Ok(Box::new(SimComponent::new(robot)))
    }
}
