//! `builtin:serial`: the serial link to the motor controller, declared
//! ([`SerialBuiltin`]): its parameters with their bounds, the translator it
//! picks (a built-in profile or a WASM translator component), and building
//! the link from checked parameters.

use std::path::{Path, PathBuf};

use super::protocol::Profile;
use super::serial::{LinkError, LinkSettings, SerialLink};
use super::translator::{DriveGeometry, ProfileTranslator, Translator};
use crate::builtin::{
    self, BuildContext, Builtin, BuiltinError, CheckContext, ParamDecl, ParamType, Params, Ports, number_in,
    positive_up_to,
};
use crate::config::ParamProblem;
use crate::contract::{ValueKind, clip};
use crate::runtime::Component;

/// Slowest and fastest baud rates: the range of standard UART rates; a
/// typo must not open the device at a rate nothing speaks.
pub const BAUD_RANGE: (i64, i64) = (50, 4_000_000);
/// Longest `watchdog`, `refresh` and `min-interval`: a silent link may keep
/// the motors on their last command for at most this long.
pub const MAX_LINK_TIMING_S: f64 = 10.0;
/// Largest wheel base (m) and wheel speed (m/s) a robot file may claim.
pub const MAX_WHEEL_BASE_M: f64 = 10.0;
pub const MAX_WHEEL_SPEED_M_S: f64 = 10.0;

const PARAMS: &[ParamDecl] = &[
    ParamDecl {
        name: "device",
        ty: ParamType::Required,
        default: "",
        unit: "",
        doc: "serial device path, or sim:NAME for the PTY of a builtin:sim",
    },
    ParamDecl {
        name: "baud",
        ty: ParamType::Integer { min: BAUD_RANGE.0, max: BAUD_RANGE.1 },
        default: "115200",
        unit: "",
        doc: "baud rate",
    },
    ParamDecl {
        name: "translator",
        ty: ParamType::WordOrFile(&["ascii", "binary"]),
        default: "ascii",
        unit: "",
        doc: "ascii, binary (docs/protocols.md), or a .wasm translator component",
    },
    ParamDecl {
        name: "min-interval",
        ty: number_in(0.001, 1.0),
        default: "0.02",
        unit: "s",
        doc: "least seconds between two frames (rate limit)",
    },
    ParamDecl {
        name: "watchdog",
        ty: positive_up_to(MAX_LINK_TIMING_S),
        default: "0.3",
        unit: "s",
        doc: "STOP when no command came for this many seconds",
    },
    ParamDecl {
        name: "refresh",
        ty: positive_up_to(MAX_LINK_TIMING_S),
        default: "0.1",
        unit: "s",
        doc: "re-send the current command after this many seconds",
    },
    ParamDecl {
        name: "wheel-base",
        ty: positive_up_to(MAX_WHEEL_BASE_M),
        default: "0.3",
        unit: "m",
        doc: "distance between the wheels",
    },
    ParamDecl {
        name: "max-wheel-speed",
        ty: positive_up_to(MAX_WHEEL_SPEED_M_S),
        default: "0.5",
        unit: "m/s",
        doc: "fastest wheel speed",
    },
];

/// The translator a serial link uses.
#[derive(Clone, Debug, PartialEq)]
pub enum TranslatorChoice {
    Profile(Profile),
    /// A WASM component of the `translator` world.
    Wasm(PathBuf),
}

/// The translator named by a link's `translator` parameter: `ascii`,
/// `binary`, or a `.wasm` path relative to `base_dir`.
fn translator_choice(name: &str, base_dir: &Path) -> Result<TranslatorChoice, String> {
    let name = name.trim();
    if name.ends_with(".wasm") {
        return Ok(TranslatorChoice::Wasm(base_dir.join(name)));
    }
    Profile::parse(name)
        .map(TranslatorChoice::Profile)
        .ok_or_else(|| format!("names no translator: '{}' (expected ascii, binary or a .wasm translator)", clip(name)))
}

/// The `serial` kind.
pub struct SerialBuiltin;

impl Builtin for SerialBuiltin {
    fn kind(&self) -> &'static str {
        "serial"
    }

    fn summary(&self) -> &'static str {
        "Serial link to the motor controller: rate limit, watchdog, translator, feedback"
    }

    fn params(&self) -> &'static [ParamDecl] {
        PARAMS
    }

    fn carried(&self) -> bool {
        true
    }

    fn check(&self, params: &Params, ctx: &mut CheckContext<'_>) -> Vec<ParamProblem> {
        let name = params.text("translator").unwrap_or_default();
        match translator_choice(name, ctx.base_dir) {
            Ok(TranslatorChoice::Profile(_)) => Vec::new(),
            Ok(TranslatorChoice::Wasm(path)) => match ctx.translators.load(&path) {
                Ok(_) => Vec::new(),
                Err(e) => vec![ParamProblem::new("translator", format!("does not load: {e}"))],
            },
            Err(why) => vec![ParamProblem::new("translator", why)],
        }
    }

    fn ports(&self, _params: &Params) -> Ports {
        Ports {
            inputs: vec![builtin::port("cmd", ValueKind::Command, "the command for the motors (from the arbiter)")],
            outputs: vec![
                builtin::port("pose", ValueKind::Vector, "odometry [x m, y m, heading rad]"),
                builtin::port("ranges", ValueKind::Vector, "range readings in metres, right to left"),
                builtin::port("bumper", ValueKind::Flag, "true while the bumper is pressed"),
                builtin::port("battery", ValueKind::Scalar, "battery voltage"),
            ],
        }
    }

    fn build(&self, params: &Params, ctx: &mut BuildContext<'_>) -> Result<Box<dyn Component>, BuiltinError> {
        let device = params.text("device")?;
        let device =
            match device.strip_prefix("sim:") {
                Some(sim) => ctx.ptys.get(sim).cloned().ok_or_else(|| {
                    BuiltinError::Refused(format!("device 'sim:{sim}' names no builtin:sim component"))
                })?,
                None => PathBuf::from(device),
            };
        let nanos = |name: &str| params.seconds(name).map(|d| d.as_nanos() as u64);
        let baud = params.integer("baud")?;
        let settings = LinkSettings {
            device,
            baud: u32::try_from(baud)
                .map_err(|_| BuiltinError::Param { name: "baud".into(), why: format!("is out of range: {baud}") })?,
            min_interval_ns: nanos("min-interval")?,
            watchdog_ns: nanos("watchdog")?,
            refresh_ns: nanos("refresh")?,
        };
        let geometry = DriveGeometry {
            wheel_base: params.number("wheel-base")?,
            max_wheel_speed: params.number("max-wheel-speed")?,
        };
        let translator: Box<dyn Translator> = match translator_choice(params.text("translator")?, ctx.base_dir)
            .map_err(|why| BuiltinError::Param { name: "translator".into(), why })?
        {
            TranslatorChoice::Profile(profile) => Box::new(ProfileTranslator::new(profile, geometry)),
            TranslatorChoice::Wasm(path) => {
                let artifact = ctx.translators.load(&path)?;
                let robot = ctx.robot;
                let link =
                    robot.components.get(ctx.index).ok_or_else(|| BuiltinError::Refused("no such component".into()))?;
                Box::new(ctx.translators.start(&artifact, link)?)
            }
        };
        let name = ctx.component()?.name.clone();
        let link = SerialLink::start(&name, settings, translator).map_err(|e| match e {
            LinkError::Thread(source) => BuiltinError::io("cannot start the serial thread", source),
            refused @ LinkError::NoStopFrame(_) => BuiltinError::Refused(refused.to_string()),
        })?;
        Ok(Box::new(link))
    }
}
