//! Native components compiled into the host, named `builtin:KIND` in the
//! robot file. They describe themselves with the same [`Description`] as
//! WASM guests and run behind the same [`Component`] trait, so the
//! scheduler does not tell them apart.
//!
//! - `builtin:log`: writes the values it receives to the host log, at most
//!   one line per `interval` seconds per input (with the count in between).
//! - `builtin:publish`: emits a fixed value of a given kind on every tick
//!   (a set-point, a test signal, a stand-in for a sensor that is not wired).
//! - `builtin:arbiter`: subsumption over the motion sources wired into it
//!   (`crate::arbiter`).
//! - `builtin:serial`: the serial link to the motor controller
//!   (`crate::robot::serial`).
//! - `builtin:sim`: a simulated robot behind a pseudo-terminal (`crate::sim`).
//! - `builtin:teleop`: the network platform: remote operators (`crate::net`).

use std::collections::{BTreeMap, HashMap};
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use crate::arbiter::{ArbiterComponent, MAX_SOURCES, PriorityCell, Source};
use crate::config::{ComponentConfig, RobotConfig};
use crate::contract::{Description, ParamKind, ParamSpec, PortSpec, Value, ValueKind, clip};
use crate::net::{self, TeleopComponent};
use crate::robot::protocol::{MAX_RANGES, Profile};
use crate::robot::serial::{LinkSettings, SerialLink};
use crate::robot::translator::{DriveGeometry, ProfileTranslator, Translator};
use crate::runtime::control_loop::{Clock, Waker};
use crate::runtime::{CallError, Component, Outbox};
use crate::sim::physics::Body;
use crate::sim::{SimComponent, SimSettings, SimulatedRobot, world};

/// The built-in kinds, for messages.
pub const KINDS: &[&str] = &["arbiter", "log", "publish", "serial", "sim", "teleop"];

/// Longest vector shown in a log line; the rest is summarised.
pub const LOG_MAX_ELEMENTS: usize = 8;

/// The description of built-in `kind`, shaped by its XML `params` where the
/// kind needs it (`publish` takes its output kind from `kind`). `base_dir`
/// anchors relative paths in parameters (the sim's world file), which are
/// checked here so `subsume check` reports them.
pub fn describe(kind: &str, params: &BTreeMap<String, String>, base_dir: &Path) -> Result<Description, String> {
    let describe = |summary: &str, inputs, outputs, params| Description {
        name: kind.to_string(),
        version: env!("CARGO_PKG_VERSION").into(),
        summary: summary.into(),
        inputs,
        outputs,
        params,
        default_priority: None,
    };
    match kind {
        "log" => Ok(describe(
            "Writes received values to the host log",
            vec![port("in", ValueKind::Any, "any value; logged")],
            vec![],
            vec![param("interval", ParamKind::Number, "1.0", "least seconds between two log lines per input")],
        )),
        "publish" => {
            let kind_name = params.get("kind").map_or("scalar", |k| k.trim());
            let value_kind = match ValueKind::parse(kind_name) {
                Some(ValueKind::Any) | None => {
                    return Err(format!(
                        "builtin:publish: unknown kind '{}' (expected flag, scalar, vector, text, command or bytes)",
                        clip(kind_name)
                    ));
                }
                Some(k) => k,
            };
            if let Some(text) = params.get("value") {
                parse_value(value_kind, text).map_err(|why| format!("builtin:publish: parameter 'value' {why}"))?;
            }
            Ok(describe(
                "Emits a fixed value on every tick",
                vec![],
                vec![port("out", value_kind, "the value, once per tick")],
                vec![
                    param(
                        "kind",
                        ParamKind::Text,
                        "scalar",
                        "kind of the value: flag, scalar, vector, text, command or bytes",
                    ),
                    param(
                        "value",
                        ParamKind::Text,
                        "0",
                        "the value: 'true', '1.5', '1 2 3', text, a control string, or hex bytes",
                    ),
                ],
            ))
        }
        "arbiter" => Ok(describe(
            "Subsumption: the highest-priority active source drives; none active: STOP",
            vec![port(
                "commands",
                ValueKind::Command,
                "control strings; every connection is a source with its sender's priority",
            )],
            vec![port("cmd", ValueKind::Command, "the winning command, or STOP")],
            vec![],
        )),
        "serial" => {
            let device = params.get("device").map(|d| d.trim()).unwrap_or("");
            if device.is_empty() {
                return Err(
                    "builtin:serial: parameter 'device' is required (a device path, or sim:NAME for a builtin:sim)"
                        .into(),
                );
            }
            translator_choice(params, base_dir)?;
            Ok(describe(
                "Serial link to the motor controller: rate limit, watchdog, translator, feedback",
                vec![port("cmd", ValueKind::Command, "the command for the motors (from the arbiter)")],
                vec![
                    port("pose", ValueKind::Vector, "odometry [x m, y m, heading rad]"),
                    port("ranges", ValueKind::Vector, "range readings in metres, right to left"),
                    port("bumper", ValueKind::Flag, "true while the bumper is pressed"),
                    port("battery", ValueKind::Scalar, "battery voltage"),
                ],
                vec![
                    param(
                        "device",
                        ParamKind::Text,
                        "",
                        "serial device path, or sim:NAME for the PTY of a builtin:sim",
                    ),
                    param("baud", ParamKind::Integer, "115200", "baud rate"),
                    param(
                        "translator",
                        ParamKind::Text,
                        "ascii",
                        "ascii, binary (docs/protocols.md), or a .wasm translator component",
                    ),
                    param("min-interval", ParamKind::Number, "0.02", "least seconds between two frames (rate limit)"),
                    param("watchdog", ParamKind::Number, "0.3", "STOP when no command came for this many seconds"),
                    param("refresh", ParamKind::Number, "0.1", "re-send the current command after this many seconds"),
                    param("wheel-base", ParamKind::Number, "0.3", "distance between the wheels, metres"),
                    param("max-wheel-speed", ParamKind::Number, "0.5", "fastest wheel speed, m/s"),
                ],
            ))
        }
        "teleop" => {
            net::settings(params, base_dir).map_err(|e| format!("builtin:teleop: {e}"))?;
            let mut d = describe(
                "Remote operators over TCP and WebSocket: latency probe, control modes, constant-delay buffer",
                vec![],
                vec![
                    port("cmd", ValueKind::Command, "operator commands, released by the delay buffer"),
                    port("goal", ValueKind::Vector, "operator goals (GOTO x y) as [x, y], for a planner"),
                ],
                teleop_params(),
            );
            d.default_priority = Some(1);
            Ok(d)
        }
        "sim" => {
            sim_settings(params, base_dir)?;
            Ok(describe("A simulated differential-drive robot behind a pseudo-terminal", vec![], vec![], sim_params()))
        }
        other => Err(format!("unknown built-in '{}' (known: {})", clip(other), KINDS.join(", "))),
    }
}

fn teleop_params() -> Vec<ParamSpec> {
    vec![
        param("listen", ParamKind::Text, "127.0.0.1:7070", "TCP address of the line protocol (docs/teleop.md)"),
        param(
            "websocket",
            ParamKind::Text,
            "",
            "address of the WebSocket endpoint /teleop (JSON messages); empty: none",
        ),
        param(
            "operators",
            ParamKind::Text,
            "",
            "file of NAME TOKEN lines, relative to the robot file; optional with the portal (its operators log in)",
        ),
        param("probe-period", ParamKind::Number, "300", "seconds between round-trip measurements (and one on connect)"),
        param("direct-below", ParamKind::Number, "0.1", "round-trip time (s) under which direct mode is allowed"),
        param("shared-below", ParamKind::Number, "0.3", "round-trip time (s) under which shared mode is allowed"),
        param("max-operators", ParamKind::Integer, "4", "connections served at once (1 to 64)"),
        param("delay", ParamKind::Text, "adaptive", "playout delay: adaptive (follows jitter) or fixed seconds"),
        param("min-delay", ParamKind::Number, "0.01", "smallest adaptive playout delay, seconds"),
        param("max-delay", ParamKind::Number, "0.2", "largest adaptive playout delay, seconds"),
        param("horizon", ParamKind::Number, "0.5", "commands older than this (seconds) are dropped as stale"),
    ]
}

fn sim_params() -> Vec<ParamSpec> {
    vec![
        param("world", ParamKind::Text, "", "world file, relative to the robot file (config/worlds/*.world)"),
        param("protocol", ParamKind::Text, "ascii", "wire protocol of the simulated controller: ascii or binary"),
        param("wheel-base", ParamKind::Number, "0.3", "distance between the wheels, metres"),
        param("max-wheel-speed", ParamKind::Number, "0.5", "fastest wheel speed, m/s"),
        param("radius", ParamKind::Number, "0.18", "the robot is a disc of this radius, metres"),
        param("rays", ParamKind::Integer, "9", "range rays, spread over fov"),
        param("fov", ParamKind::Number, "3.14159", "angle covered by the rays, radians"),
        param("max-range", ParamKind::Number, "4.0", "longest range reading, metres"),
        param("feedback-rate", ParamKind::Number, "20", "feedback messages per second"),
    ]
}

/// The translator a serial link uses.
#[derive(Clone, Debug, PartialEq)]
pub enum TranslatorChoice {
    Profile(Profile),
    /// A WASM component of the `translator` world.
    Wasm(PathBuf),
}

/// Builds WASM translators for serial links (the loader, with its sandbox).
pub trait TranslatorLoader {
    /// A running translator from the `.wasm` file at `path`, for the serial
    /// link `link` (its parameters go to the translator's `init`).
    fn wasm_translator(&mut self, path: &Path, link: &ComponentConfig) -> Result<Box<dyn Translator>, String>;
}

/// The translator named by a serial link's `translator` parameter: `ascii`,
/// `binary`, or a `.wasm` path relative to `base_dir`.
pub fn translator_choice(params: &BTreeMap<String, String>, base_dir: &Path) -> Result<TranslatorChoice, String> {
    let name = params.get("translator").map_or("ascii", |t| t.trim());
    if name.ends_with(".wasm") {
        return Ok(TranslatorChoice::Wasm(base_dir.join(name)));
    }
    Profile::parse(name)
        .map(TranslatorChoice::Profile)
        .ok_or_else(|| format!("unknown translator '{}' (expected ascii, binary or a .wasm translator)", clip(name)))
}

/// What instantiating a built-in may need beyond its own parameters.
#[derive(Debug)]
pub struct BuildContext<'a> {
    pub robot: &'a RobotConfig,
    /// Index of the component being built, in `robot.components`.
    pub index: usize,
    /// PTY paths of the simulated robots built so far, by component name.
    pub sim_ptys: &'a mut HashMap<String, PathBuf>,
    /// Every component's current priority (the arbiter reads them; the
    /// network platform moves its own).
    pub priorities: &'a [PriorityCell],
    /// The control loop's clock and a waker for it.
    pub clock: Clock,
    pub waker: Waker,
    pub services: Services,
}

/// What the host shares with the built-ins it starts, beyond one robot.
#[derive(Clone, Debug, Default)]
pub struct Services {
    /// The portal's users: `builtin:teleop` lets operators drive with their
    /// password or a pad ticket.
    pub directory: Option<std::sync::Arc<crate::users::Directory>>,
    /// Where `builtin:teleop` registers itself for the portal's WebSocket.
    pub teleop_servers: net::TeleopServers,
}

/// A running built-in of `kind` for component `ctx.index`.
pub fn instantiate(
    kind: &str,
    ctx: &mut BuildContext<'_>,
    translators: &mut dyn TranslatorLoader,
) -> Result<Box<dyn Component>, String> {
    let Some(config) = ctx.robot.components.get(ctx.index) else {
        return Err("no such component".into());
    };
    let (name, description) = (config.name.as_str(), &config.description);
    let params: BTreeMap<String, String> = config.params.iter().map(|p| (p.name.clone(), p.value.clone())).collect();
    let base_dir = ctx.robot.path.parent().unwrap_or(Path::new("")).to_path_buf();
    match kind {
        "log" => {
            let interval = number(&params, "interval")?;
            if interval < 0.0 {
                return Err(format!("interval must be a number of seconds >= 0, got {interval}"));
            }
            let inputs = description.inputs.len();
            Ok(Box::new(LogSink {
                name: name.into(),
                interval_ns: (interval * 1e9) as u64,
                last: vec![None; inputs],
                unlogged: vec![0; inputs],
            }))
        }
        "publish" => {
            let kind = description.outputs.first().map_or(ValueKind::Scalar, |p| p.kind);
            let value = parse_value(kind, params.get("value").map_or("0", String::as_str))?;
            Ok(Box::new(Publisher { value }))
        }
        "arbiter" => {
            let mut sources: Vec<Source> = Vec::new();
            for connection in ctx.robot.connections.iter().filter(|c| c.to.component == ctx.index) {
                let from = &ctx.robot.components[connection.from.component];
                if sources.iter().any(|s| s.component == connection.from.component) {
                    continue;
                }
                if from.priority.is_none() {
                    return Err(format!("source '{}' has no priority", from.name));
                }
                let priority = ctx.priorities.get(connection.from.component).cloned().unwrap_or_default();
                sources.push(Source {
                    component: connection.from.component,
                    name: from.name.clone(),
                    priority,
                    timeout_ns: from.timeout.as_nanos() as u64,
                });
            }
            if sources.len() > MAX_SOURCES {
                return Err(format!("{} sources; at most {MAX_SOURCES} are allowed", sources.len()));
            }
            let listed: Vec<String> =
                sources.iter().map(|s| format!("{} (priority {})", s.name, s.priority.get())).collect();
            tracing::info!(
                component = name,
                "motion sources: {}",
                if listed.is_empty() { "none".into() } else { listed.join(", ") }
            );
            Ok(Box::new(ArbiterComponent::new(name, sources)))
        }
        "serial" => {
            let device = params.get("device").map(|d| d.trim().to_string()).unwrap_or_default();
            let device = match device.strip_prefix("sim:") {
                Some(sim) => ctx
                    .sim_ptys
                    .get(sim)
                    .cloned()
                    .ok_or_else(|| format!("device 'sim:{sim}' names no builtin:sim component"))?,
                None => PathBuf::from(device),
            };
            let seconds = |key: &str| -> Result<u64, String> {
                let s = number(&params, key)?;
                if s <= 0.0 {
                    return Err(format!("{key} must be a positive number of seconds, got {s}"));
                }
                Ok((s * 1e9) as u64)
            };
            let baud = params
                .get("baud")
                .and_then(|b| b.trim().parse::<u32>().ok())
                .filter(|b| *b > 0)
                .ok_or("baud must be a positive whole number")?;
            let settings = LinkSettings {
                device,
                baud,
                min_interval_ns: seconds("min-interval")?,
                watchdog_ns: seconds("watchdog")?,
                refresh_ns: seconds("refresh")?,
            };
            let translator: Box<dyn Translator> = match translator_choice(&params, &base_dir)? {
                TranslatorChoice::Profile(profile) => Box::new(ProfileTranslator::new(profile, geometry(&params)?)),
                TranslatorChoice::Wasm(path) => translators.wasm_translator(&path, config)?,
            };
            Ok(Box::new(SerialLink::start(name, settings, translator)?))
        }
        "teleop" => {
            let mut settings = net::settings(&params, &base_dir)?;
            settings.directory = ctx.services.directory.clone();
            let priority = ctx.priorities.get(ctx.index).cloned().unwrap_or_default();
            let component =
                TeleopComponent::start(name, &ctx.robot.name, settings, ctx.clock, ctx.waker.clone(), priority)?;
            ctx.services.teleop_servers.register(component.context());
            Ok(Box::new(component))
        }
        "sim" => {
            let settings = sim_settings(&params, &base_dir)?;
            let robot = SimulatedRobot::start(name, settings)?;
            ctx.sim_ptys.insert(name.to_string(), robot.pty_path().clone());
            Ok(Box::new(SimComponent::new(robot)))
        }
        other => Err(format!("unknown built-in '{}'", clip(other))),
    }
}

fn number(params: &BTreeMap<String, String>, key: &str) -> Result<f64, String> {
    let text = params.get(key).map_or("", String::as_str);
    text.trim()
        .parse::<f64>()
        .ok()
        .filter(|x| x.is_finite())
        .ok_or_else(|| format!("{key} must be a number, got '{}'", clip(text)))
}

fn geometry(params: &BTreeMap<String, String>) -> Result<DriveGeometry, String> {
    let get = |key: &str, default: f64| -> Result<f64, String> {
        match params.get(key) {
            None => Ok(default),
            Some(_) => number(params, key)
                .and_then(|v| if v > 0.0 { Ok(v) } else { Err(format!("{key} must be positive, got {v}")) }),
        }
    };
    Ok(DriveGeometry { wheel_base: get("wheel-base", 0.3)?, max_wheel_speed: get("max-wheel-speed", 0.5)? })
}

/// The settings of a `builtin:sim` from its parameters; loads the world.
fn sim_settings(params: &BTreeMap<String, String>, base_dir: &Path) -> Result<SimSettings, String> {
    let defaults: BTreeMap<String, String> = sim_params().into_iter().map(|p| (p.name, p.default_value)).collect();
    let get = |key: &str| params.get(key).or_else(|| defaults.get(key)).cloned().unwrap_or_default();
    let all: BTreeMap<String, String> = defaults.keys().map(|k| (k.clone(), get(k))).collect();
    let world_path = get("world");
    if world_path.trim().is_empty() {
        return Err("builtin:sim: parameter 'world' is required (a world file, e.g. worlds/demo.world)".into());
    }
    let world_path = base_dir.join(world_path.trim());
    let world = world::load(&world_path).map_err(|e| format!("builtin:sim: bad world file:\n{e}"))?;
    let protocol = get("protocol");
    let profile = Profile::parse(protocol.trim())
        .ok_or_else(|| format!("builtin:sim: unknown protocol '{}' (expected ascii or binary)", clip(&protocol)))?;
    let positive = |key: &str| {
        number(&all, key)
            .and_then(|v| if v > 0.0 { Ok(v) } else { Err(format!("builtin:sim: {key} must be positive, got {v}")) })
    };
    let rays = get("rays")
        .trim()
        .parse::<usize>()
        .ok()
        .filter(|r| (1..=MAX_RANGES).contains(r))
        .ok_or(format!("builtin:sim: rays must be a whole number from 1 to {MAX_RANGES}"))?;
    Ok(SimSettings {
        world,
        body: Body {
            radius: positive("radius")?,
            geometry: DriveGeometry {
                wheel_base: positive("wheel-base")?,
                max_wheel_speed: positive("max-wheel-speed")?,
            },
            rays,
            fov: positive("fov")?,
            max_range: positive("max-range")?,
        },
        profile,
        feedback_hz: positive("feedback-rate")?,
    })
}

struct LogSink {
    name: String,
    interval_ns: u64,
    last: Vec<Option<u64>>,
    unlogged: Vec<u64>,
}

impl Component for LogSink {
    fn on_input(
        &mut self,
        port: u32,
        value: &Value,
        _from: usize,
        now_ns: u64,
        _out: &mut Outbox,
    ) -> Result<(), CallError> {
        let i = port as usize;
        let (Some(last), Some(unlogged)) = (self.last.get_mut(i), self.unlogged.get_mut(i)) else {
            return Ok(());
        };
        if last.is_some_and(|t| now_ns.saturating_sub(t) < self.interval_ns) {
            *unlogged += 1;
            return Ok(());
        }
        let skipped = std::mem::take(unlogged);
        *last = Some(now_ns);
        let more = if skipped > 0 { format!(" (+{skipped} since last line)") } else { String::new() };
        tracing::info!(component = %self.name, "received {}{more}", format_value(value));
        Ok(())
    }
}

struct Publisher {
    value: Value,
}

impl Component for Publisher {
    fn tick(&mut self, _now_ns: u64, out: &mut Outbox) -> Result<(), CallError> {
        out.push((0, self.value.clone()));
        Ok(())
    }
}

/// Parses the text form of a value of `kind` (as `builtin:publish` takes it).
pub fn parse_value(kind: ValueKind, text: &str) -> Result<Value, String> {
    let trimmed = text.trim();
    match kind {
        ValueKind::Flag => match trimmed {
            "true" => Ok(Value::Flag(true)),
            "false" => Ok(Value::Flag(false)),
            _ => Err(format!("expects true or false, got '{}'", clip(text))),
        },
        ValueKind::Scalar => trimmed
            .parse::<f64>()
            .ok()
            .filter(|x| x.is_finite())
            .map(Value::Scalar)
            .ok_or_else(|| format!("expects a finite number, got '{}'", clip(text))),
        ValueKind::Vector => trimmed
            .split(|c: char| c.is_whitespace() || c == ',')
            .filter(|s| !s.is_empty())
            .map(|s| s.parse::<f64>().ok().filter(|x| x.is_finite()))
            .collect::<Option<Vec<f64>>>()
            .map(Value::Vector)
            .ok_or_else(|| format!("expects numbers separated by spaces or commas, got '{}'", clip(text))),
        ValueKind::Text => Ok(Value::Text(text.to_string())),
        ValueKind::Command => Ok(Value::Command(trimmed.to_string())),
        ValueKind::Bytes => hex::decode(trimmed.replace(' ', ""))
            .map(Value::Bytes)
            .map_err(|_| format!("expects hex bytes like '0a ff', got '{}'", clip(text))),
        ValueKind::Any => Err("a value needs a concrete kind".into()),
    }
}

/// A short human form of `value` for log lines.
pub fn format_value(value: &Value) -> String {
    match value {
        Value::Flag(b) => format!("flag {b}"),
        Value::Scalar(x) => format!("scalar {x:.3}"),
        Value::Vector(v) => {
            let mut s = String::from("vector [");
            for (i, x) in v.iter().take(LOG_MAX_ELEMENTS).enumerate() {
                if i > 0 {
                    s.push_str(", ");
                }
                let _ = write!(s, "{x:.3}");
            }
            if v.len() > LOG_MAX_ELEMENTS {
                let _ = write!(s, ", ... {} in all", v.len());
            }
            s.push(']');
            s
        }
        Value::Text(t) => format!("text {:?}", clip(t)),
        Value::Command(c) => format!("command '{}'", clip(c)),
        Value::Bytes(b) => format!("bytes ({} bytes)", b.len()),
    }
}

fn port(name: &str, kind: ValueKind, doc: &str) -> PortSpec {
    PortSpec { name: name.into(), kind, doc: doc.into() }
}

fn param(name: &str, kind: ParamKind, default: &str, doc: &str) -> ParamSpec {
    ParamSpec { name: name.into(), kind, default_value: default.into(), doc: doc.into() }
}

#[cfg(test)]
mod tests {
    use std::path::Path;

    use super::*;
    use crate::config::{self, ComponentSource, Resolver};

    /// Describes built-ins only; has no WASM translators.
    struct Builtins;

    impl TranslatorLoader for Builtins {
        fn wasm_translator(&mut self, path: &Path, _link: &ComponentConfig) -> Result<Box<dyn Translator>, String> {
            Err(format!("no translator {} in this test", path.display()))
        }
    }

    impl Resolver for Builtins {
        fn describe(
            &mut self,
            source: &ComponentSource,
            params: &BTreeMap<String, String>,
            base_dir: &Path,
        ) -> Result<Description, String> {
            match source {
                ComponentSource::Builtin(kind) => describe(kind, params, base_dir),
                ComponentSource::Wasm(_) => Err("no guests in this test".into()),
            }
        }
    }

    #[test]
    fn values_parse_from_their_text_form() {
        assert_eq!(parse_value(ValueKind::Vector, "1, 2 3"), Ok(Value::Vector(vec![1.0, 2.0, 3.0])));
        assert_eq!(parse_value(ValueKind::Bytes, "0a ff"), Ok(Value::Bytes(vec![10, 255])));
        assert_eq!(parse_value(ValueKind::Flag, "true"), Ok(Value::Flag(true)));
        assert!(parse_value(ValueKind::Scalar, "nan").is_err());
        assert!(parse_value(ValueKind::Vector, "1 x").is_err());
    }

    #[test]
    fn publish_takes_its_output_kind_from_its_params() {
        let here = Path::new(".");
        let params = BTreeMap::from([("kind".to_string(), "vector".to_string())]);
        assert_eq!(describe("publish", &params, here).map(|d| d.outputs[0].kind), Ok(ValueKind::Vector));
        let bad = BTreeMap::from([("kind".to_string(), "any".to_string())]);
        assert!(describe("publish", &bad, here).is_err());
        assert!(
            describe("nope", &BTreeMap::new(), here)
                .is_err_and(|e| e.contains("known: arbiter, log, publish, serial, sim"))
        );
    }

    #[test]
    fn publisher_emits_its_value_every_tick() -> Result<(), String> {
        let xml = r#"<robot name="t"><platform name="control">
            <component name="p" source="builtin:publish"><param name="value" value="2.5"/></component>
        </platform></robot>"#;
        let robot = config::parse_and_validate(Path::new("t.xml"), xml, &mut Builtins).map_err(|e| e.to_string())?;
        let mut ptys = HashMap::new();
        let mut c = instantiate(
            "publish",
            &mut BuildContext {
                robot: &robot,
                index: 0,
                sim_ptys: &mut ptys,
                priorities: &[PriorityCell::new(0)],
                clock: Clock::new(),
                waker: Waker::default(),
                services: Services::default(),
            },
            &mut Builtins,
        )?;
        let mut out = Vec::new();
        c.tick(0, &mut out).map_err(|e| format!("{e:?}"))?;
        c.tick(1, &mut out).map_err(|e| format!("{e:?}"))?;
        assert_eq!(out, vec![(0, Value::Scalar(2.5)), (0, Value::Scalar(2.5))]);
        Ok(())
    }
}
