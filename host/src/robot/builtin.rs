//! `builtin:serial`: the serial link to the motor controller, declared
//! ([`SerialBuiltin`]): its parameters with their bounds, the translator it
//! picks (a built-in profile or a WASM translator component), and building
//! the link from checked parameters.

use std::path::{Path, PathBuf};

use super::protocol::Profile;
use super::serial::{LinkError, LinkSettings, ScanGeometry, SerialLink};
use super::translator::{DriveGeometry, ProfileTranslator, Translator};
use crate::builtin::{
    self, BuildContext, Builtin, BuiltinError, CheckContext, ParamDecl, ParamType, Params, Ports, PreflightContext,
    PreflightForm, Registry, number_in, positive_up_to,
};
use crate::config::{ParamProblem, RobotConfig, RobotProblem, RobotView};
use crate::contract::{Param, ValueKind, clip};
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
        name: "options",
        ty: ParamType::Text,
        default: "",
        unit: "",
        doc: "settings for a WASM translator: name=value pairs separated by spaces (docs/protocols.md)",
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
    ParamDecl {
        name: "preflight-protocol",
        ty: ParamType::Choice(&["auto", "ascii", "binary", "create2"]),
        default: "auto",
        unit: "",
        doc: "the protocol of the simulated controller that stands in for a real device in a preflight (docs/lab.md); auto: the translator's profile (a WASM translator needs one named)",
    },
];

/// A `device` naming a simulated robot: `sim:NAME`.
const SIM_DEVICE: &str = "sim:";

/// The geometry of the rays of the simulated robot `sim` (its `fov` and
/// `max-range` parameters, as checked when the robot file was): the link
/// emits its ranges as a scan with it.
fn sim_scan_geometry(robot: &RobotConfig, sim: &str) -> Result<ScanGeometry, BuiltinError> {
    let component = robot
        .components
        .iter()
        .find(|c| c.name == sim)
        .ok_or_else(|| BuiltinError::Refused(format!("device 'sim:{sim}' names no builtin:sim component")))?;
    let number = |name: &str| {
        component.params.iter().find(|p| p.name == name).and_then(|p| p.value.trim().parse::<f64>().ok()).ok_or_else(
            || BuiltinError::Refused(format!("device 'sim:{sim}': the simulated robot has no number '{name}'")),
        )
    };
    Ok(ScanGeometry { fov: number("fov")?, max_range: number("max-range")? })
}

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

/// Most `name=value` pairs in `options`, and the longest value: the
/// translator's `init` gets them, so a robot file cannot flood it.
pub const MAX_TRANSLATOR_OPTIONS: usize = 32;
pub const MAX_OPTION_VALUE_BYTES: usize = 256;

/// Why a link's `options` parameter does not read.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[error("{0}")]
pub struct OptionsError(String);

/// The `name=value` pairs of a link's `options` parameter, in order.
pub fn translator_options(text: &str) -> Result<Vec<(String, String)>, OptionsError> {
    parse_options(text).map_err(OptionsError)
}

fn parse_options(text: &str) -> Result<Vec<(String, String)>, String> {
    let mut pairs: Vec<(String, String)> = Vec::new();
    for word in text.split_ascii_whitespace() {
        let Some((name, value)) = word.split_once('=') else {
            return Err(format!("expected name=value pairs, found '{}'", clip(word)));
        };
        if name.is_empty() || !name.chars().all(|c| c.is_ascii_alphanumeric() || c == '-') {
            return Err(format!("'{}' is not an option name (letters, digits and '-')", clip(name)));
        }
        if value.len() > MAX_OPTION_VALUE_BYTES {
            return Err(format!("the value of '{name}' is longer than {MAX_OPTION_VALUE_BYTES} bytes"));
        }
        if pairs.iter().any(|(n, _)| n == name) || PARAMS.iter().any(|p| p.name == name) {
            return Err(format!("'{name}' is given twice (or is one of the link's own parameters)"));
        }
        pairs.push((name.to_string(), value.to_string()));
    }
    if pairs.len() > MAX_TRANSLATOR_OPTIONS {
        return Err(format!("{} options; at most {MAX_TRANSLATOR_OPTIONS}", pairs.len()));
    }
    Ok(pairs)
}

/// The link's one input: the command for the motors.
const INPUT_CMD: u32 = 0;

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

    /// A link to a real device gets a simulated controller of the same
    /// protocol in the preflight's world; a link to a simulated robot
    /// stays as it is.
    fn preflight(
        &self,
        params: &Params,
        ctx: &PreflightContext<'_>,
    ) -> Result<PreflightForm, crate::builtin::NotSimulable> {
        let device = params.text("device").unwrap_or_default().trim();
        if device.starts_with(SIM_DEVICE) {
            return Ok(PreflightForm::default());
        }
        let named = params.text("preflight-protocol").unwrap_or_default().trim();
        let translator = params.text("translator").unwrap_or_default().trim();
        let protocol = match (named, Profile::parse(translator)) {
            ("auto", Some(_)) => translator,
            ("auto", None) => {
                return Err(crate::builtin::NotSimulable(format!(
                    "the preflight cannot simulate the controller behind '{}' on {}: its translator is a WASM \
                     component; set its preflight-protocol (ascii, binary or create2)",
                    ctx.component,
                    clip(device)
                )));
            }
            (named, _) => named,
        };
        let Some(world) = ctx.world else {
            return Err(crate::builtin::NotSimulable(format!(
                "the preflight needs a world for the simulated controller behind '{}' (the robot has none of its own): \
                 the lab's owner sets the preflight world",
                ctx.component
            )));
        };
        let copy = |name: &'static str| (name, params.text(name).unwrap_or_default().to_string());
        Ok(PreflightForm {
            set: vec![("device", format!("{SIM_DEVICE}{}", ctx.sim_name))],
            files: Vec::new(),
            simulated_by: Some(vec![
                ("world", world.to_string()),
                ("protocol", protocol.to_string()),
                copy("wheel-base"),
                copy("max-wheel-speed"),
            ]),
        })
    }

    /// Only a motor guard (an envelope) may feed the link's commands.
    fn check_robot(&self, me: usize, _: &Params, view: &RobotView<'_>, registry: Registry) -> Vec<RobotProblem> {
        let robot = view.robot;
        let Some(link) = robot.components.get(me) else { return Vec::new() };
        let mut problems = Vec::new();
        for c in robot.connections.iter().filter(|c| c.to.component == me && c.to.port == INPUT_CMD) {
            if builtin::builtin_of(robot, c.from.component, registry).is_some_and(|b| b.guards_motors()) {
                continue;
            }
            let (from, to) = (robot.output_name(c.from), robot.input_name(c.to));
            problems.push(RobotProblem {
                offset: c.offset,
                message: format!(
                    "'{from}' feeds serial link '{}' directly: motion commands must pass a builtin:envelope \
                     (connect '{from}' to an envelope's 'cmd' input and the envelope's 'cmd' to '{to}')",
                    link.name
                ),
            });
        }
        problems
    }

    fn check(&self, params: &Params, ctx: &mut CheckContext<'_>) -> Vec<ParamProblem> {
        let name = params.text("translator").unwrap_or_default();
        let options = params.text("options").unwrap_or_default();
        match (translator_choice(name, ctx.base_dir), translator_options(options)) {
            (_, Err(why)) => vec![ParamProblem::new("options", why.to_string())],
            (Ok(TranslatorChoice::Profile(_)), Ok(pairs)) if !pairs.is_empty() => {
                vec![ParamProblem::new("options", "are for a WASM translator; the built-in profiles take none")]
            }
            (Ok(TranslatorChoice::Profile(_)), Ok(_)) => Vec::new(),
            (Ok(TranslatorChoice::Wasm(path)), Ok(_)) => match ctx.translators.load(&path) {
                Ok(_) => Vec::new(),
                Err(e) => vec![ParamProblem::new("translator", format!("does not load: {e}"))],
            },
            (Err(why), Ok(_)) => vec![ParamProblem::new("translator", why)],
        }
    }

    fn ports(&self, params: &Params) -> Ports {
        let ranges = match params.text("device").map(|d| d.starts_with(SIM_DEVICE)) {
            Ok(true) => builtin::port(
                "ranges",
                ValueKind::Scan,
                "range scan with its geometry (the simulated robot's rays, fov and max-range); feeds vector inputs as its ranges",
            ),
            _ => builtin::port(
                "ranges",
                ValueKind::Vector,
                "range readings in metres, right to left (a scan with its geometry when device is sim:NAME)",
            ),
        };
        Ports {
            inputs: vec![builtin::port("cmd", ValueKind::Command, "the command for the motors (from the arbiter)")],
            outputs: vec![
                builtin::port("pose", ValueKind::Vector, "odometry [x m, y m, heading rad]"),
                ranges,
                builtin::port("bumper", ValueKind::Flag, "true while the bumper is pressed"),
                builtin::port("battery", ValueKind::Scalar, "battery voltage"),
                builtin::port(
                    "fault",
                    ValueKind::Text,
                    "the motor controller's fault as it reads it (empty: none), where its protocol has one",
                ),
            ],
        }
    }

    fn build(&self, params: &Params, ctx: &mut BuildContext<'_>) -> Result<Box<dyn Component>, BuiltinError> {
        let device = params.text("device")?;
        let scan = match device.strip_prefix(SIM_DEVICE) {
            Some(sim) => Some(sim_scan_geometry(ctx.robot, sim)?),
            None => None,
        };
        let device =
            match device.strip_prefix(SIM_DEVICE) {
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
                // The link's `options` reach the translator as parameters of their own.
                let options = translator_options(params.text("options")?)
                    .map_err(|why| BuiltinError::Param { name: "options".into(), why: why.to_string() })?;
                let extra = options.into_iter().map(|(name, value)| Param { name, value }).collect();
                Box::new(ctx.translators.start(&artifact, link, extra)?)
            }
        };
        let name = ctx.component()?.name.clone();
        let mut link = SerialLink::start(&name, settings, translator).map_err(|e| match e {
            LinkError::Thread(source) => BuiltinError::io("cannot start the serial thread", source),
            refused @ LinkError::NoStopFrame(_) => BuiltinError::Refused(refused.to_string()),
        })?;
        if let Some(lockstep) = ctx.clock.lockstep() {
            link.join_lockstep(lockstep);
        }
        if let Some(geometry) = scan {
            link = link.with_scan(geometry);
        }
        Ok(Box::new(link))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn options_are_name_value_pairs_and_bad_ones_are_named() {
        let pairs = translator_options("  counts-per-metre=2000 left=m2 ").unwrap();
        assert_eq!(pairs, vec![("counts-per-metre".into(), "2000".into()), ("left".into(), "m2".into())]);
        assert_eq!(translator_options(""), Ok(vec![]));
        let error = |text: &str| translator_options(text).unwrap_err().to_string();
        assert_eq!(error("mode"), "expected name=value pairs, found 'mode'");
        assert_eq!(error("=1"), "'' is not an option name (letters, digits and '-')");
        assert_eq!(error("a=1 a=2"), "'a' is given twice (or is one of the link's own parameters)");
        assert_eq!(error("baud=9600"), "'baud' is given twice (or is one of the link's own parameters)");
        let many: Vec<String> = (0..=MAX_TRANSLATOR_OPTIONS).map(|i| format!("o{i}=1")).collect();
        assert_eq!(error(&many.join(" ")), "33 options; at most 32");
        assert!(error(&format!("a={}", "x".repeat(MAX_OPTION_VALUE_BYTES + 1))).contains("longer than 256 bytes"));
    }
}
