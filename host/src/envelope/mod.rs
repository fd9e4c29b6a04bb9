//! The safety envelope (`builtin:envelope`): the owner's limits between the
//! arbiter and the serial link, which uploaded code cannot remove.
//!
//! Every motion command passes it after arbitration and before
//! translation: validation refuses a robot file whose serial link takes
//! commands from anything but an envelope (`config::validate`), and a
//! developer's upload or activation that changes an envelope's settings or
//! wiring is refused (`deploy::stage::envelope_change`). It passes, scales
//! down or stops what the arbiter chose, never more ([`logic`], pure, with
//! explicit time); every intervention is counted, logged and kept for the
//! report and the live view (the `envelope` section), with the reading
//! behind it.
//!
//! Ports: `cmd` in (the arbiter's command), `ranges` in (the link's range
//! readings), `pose` in (odometry), `cmd` out (what may reach the motors),
//! `interventions` out (JSON text when an intervention starts, changes or
//! ends, [`notices`]: what components may learn of it; wiring it changes
//! none of the owner's settings). A sensor input left unwired turns its
//! checks off (no collision monitor without ranges); a geofence needs the
//! pose wired (a validation error otherwise).

pub mod logic;
pub mod notices;

use std::collections::{BTreeMap, VecDeque};
use std::f64::consts::TAU;

use serde::Serialize;

use self::logic::{Action, Envelope, MAX_FENCE_POINTS, Settings, Verdict};
use self::notices::Notices;
use crate::builtin::{
    self, BuildContext, Builtin, BuiltinError, CheckContext, ParamDecl, ParamType, Params, Ports, Registry, number_in,
    positive_up_to,
};
use crate::config::{ComponentSource, ParamProblem, RobotProblem, RobotView};
use crate::contract::control::{Command, ControlCommand};
use crate::contract::{Value, ValueKind, clip};
use crate::runtime::{CallError, Component, NamedSection, Outbox, StatusSection};

/// Fastest speed (m/s) and turn (rad/s) an envelope may allow.
pub const MAX_SPEED_M_S: f64 = 10.0;
pub const MAX_TURN_RAD_S: f64 = 20.0;
/// Largest accelerations an envelope may allow (m/s², rad/s²).
pub const MAX_ACCEL: f64 = 100.0;
/// Largest footprint radius and zone, m.
pub const MAX_ZONE_M: f64 = 5.0;
/// Longest time-to-collision and staleness limits, s.
pub const MAX_ENVELOPE_TIME_S: f64 = 10.0;
/// Interventions kept for the live view: a stream of them must not grow
/// the status without bound.
pub const RECENT_INTERVENTIONS: usize = 10;
/// Least time between two log lines for the same kind of intervention: a
/// driver pushing at a wall 20 times a second must not flood the log.
pub const LOG_INTERVAL_NS: u64 = 1_000_000_000;
/// The default `max-priority`: the obstacle avoider's priority in the
/// subsumption paper's layering (docs/background.md). A WASM component may
/// claim at most this unless the owner raises it: a driver uploaded at a
/// higher priority would suppress the avoider and every operator mode for
/// as long as it drives.
pub const DEFAULT_MAX_PRIORITY: i32 = 3;
/// Port indices.
pub const INPUT_CMD: u32 = 0;
pub const INPUT_RANGES: u32 = 1;
pub const INPUT_POSE: u32 = 2;
pub const INPUT_CAMERA: u32 = 3;
pub const OUTPUT_CMD: u32 = 0;
pub const OUTPUT_INTERVENTIONS: u32 = 1;
/// The output components may connect to (a developer's file may wire it:
/// `deploy::stage::envelope_change` leaves it out).
pub const INTERVENTIONS_PORT: &str = "interventions";

/// [`DEFAULT_MAX_PRIORITY`] as the parameter's default (a unit test keeps
/// the two equal).
const DEFAULT_MAX_PRIORITY_TEXT: &str = "3";

const PARAMS: &[ParamDecl] = &[
    ParamDecl {
        name: "max-speed",
        ty: positive_up_to(MAX_SPEED_M_S),
        default: "0.5",
        unit: "m/s",
        doc: "fastest forward speed",
    },
    ParamDecl {
        name: "max-reverse",
        ty: number_in(0.0, MAX_SPEED_M_S),
        default: "0.1",
        unit: "m/s",
        doc: "fastest reverse speed (0: no reversing)",
    },
    ParamDecl {
        name: "max-turn",
        ty: positive_up_to(MAX_TURN_RAD_S),
        default: "2.0",
        unit: "rad/s",
        doc: "fastest turn",
    },
    ParamDecl {
        name: "max-accel",
        ty: positive_up_to(MAX_ACCEL),
        default: "1.0",
        unit: "m/s2",
        doc: "largest increase of the linear speed per second (slowing down is never delayed)",
    },
    ParamDecl {
        name: "max-turn-accel",
        ty: positive_up_to(MAX_ACCEL),
        default: "6.0",
        unit: "rad/s2",
        doc: "largest increase of the turn rate per second",
    },
    ParamDecl {
        name: "radius",
        ty: positive_up_to(MAX_ZONE_M),
        default: "0.18",
        unit: "m",
        doc: "the footprint: a disc of this radius around the range sensor",
    },
    ParamDecl {
        name: "stop-distance",
        ty: number_in(0.0, MAX_ZONE_M),
        default: "0.1",
        unit: "m",
        doc: "stop zone: linear motion stops when an obstacle is this close along the path",
    },
    ParamDecl {
        name: "slow-distance",
        ty: number_in(0.0, MAX_ZONE_M),
        default: "0.4",
        unit: "m",
        doc: "slowdown zone: the speed falls from max-speed at this clearance to 0 at the stop zone (equal: none)",
    },
    ParamDecl {
        name: "ttc",
        ty: number_in(0.0, MAX_ENVELOPE_TIME_S),
        default: "1.0",
        unit: "s",
        doc: "least time to collision at the commanded speed (0: off)",
    },
    ParamDecl {
        name: "fov",
        ty: positive_up_to(TAU),
        default: "3.14159",
        unit: "rad",
        doc: "angle covered by the range readings, right to left, centred on the heading",
    },
    ParamDecl {
        name: "stale",
        ty: positive_up_to(MAX_ENVELOPE_TIME_S),
        default: "0.5",
        unit: "s",
        doc: "STOP when the wired ranges or pose are older than this",
    },
    ParamDecl {
        name: "stale-camera",
        ty: positive_up_to(MAX_ENVELOPE_TIME_S),
        default: "1.0",
        unit: "s",
        doc: "STOP when the wired camera's last picture is older than this (a camera slower than 1 fps needs more)",
    },
    ParamDecl {
        name: "max-priority",
        ty: ParamType::Integer { min: -1000, max: 1000 },
        default: DEFAULT_MAX_PRIORITY_TEXT,
        unit: "",
        doc: "highest priority a WASM component feeding the arbiter may claim (validation refuses more)",
    },
    ParamDecl {
        name: "geofence",
        ty: ParamType::Text,
        default: "",
        unit: "m",
        doc: "polygon in odometry coordinates the robot may not leave: 'x,y x,y x,y ...' (empty: none)",
    },
];

/// Parses a geofence: at least three `x,y` corners separated by blanks.
pub fn parse_geofence(text: &str) -> Result<Vec<[f64; 2]>, String> {
    let text = text.trim();
    if text.is_empty() {
        return Ok(Vec::new());
    }
    let mut corners = Vec::new();
    for (i, word) in text.split_whitespace().enumerate() {
        if i >= MAX_FENCE_POINTS {
            return Err(format!("has more than {MAX_FENCE_POINTS} corners"));
        }
        let corner = word.split_once(',').and_then(|(x, y)| {
            let (x, y) = (x.trim().parse::<f64>().ok()?, y.trim().parse::<f64>().ok()?);
            (x.is_finite() && y.is_finite()).then_some([x, y])
        });
        match corner {
            Some(c) => corners.push(c),
            None => return Err(format!("corner {} is not 'x,y' in metres: '{}'", i + 1, clip(word))),
        }
    }
    if corners.len() < 3 {
        return Err(format!("needs at least 3 corners 'x,y', got {}", corners.len()));
    }
    Ok(corners)
}

/// Which of the envelope's sensor inputs are wired: those are watched.
#[derive(Clone, Copy, Debug, Default)]
pub struct Wired {
    pub ranges: bool,
    pub pose: bool,
    pub camera: bool,
}

/// The settings of checked `params`, with which sensors are wired.
pub fn settings(params: &Params, wired: Wired) -> Result<Settings, BuiltinError> {
    let geofence =
        parse_geofence(params.text("geofence")?).map_err(|why| BuiltinError::Param { name: "geofence".into(), why })?;
    Ok(Settings {
        max_speed: params.number("max-speed")?,
        max_reverse: params.number("max-reverse")?,
        max_turn: params.number("max-turn")?,
        max_accel: params.number("max-accel")?,
        max_turn_accel: params.number("max-turn-accel")?,
        radius: params.number("radius")?,
        stop_distance: params.number("stop-distance")?,
        slow_distance: params.number("slow-distance")?,
        ttc_s: params.number("ttc")?,
        fov: params.number("fov")?,
        stale_ns: params.seconds("stale")?.as_nanos() as u64,
        geofence,
        watch_ranges: wired.ranges,
        watch_pose: wired.pose,
        watch_camera: wired.camera,
        camera_stale_ns: params.seconds("stale-camera")?.as_nanos() as u64,
    })
}

/// The `envelope` kind.
pub struct EnvelopeBuiltin;

impl Builtin for EnvelopeBuiltin {
    fn kind(&self) -> &'static str {
        "envelope"
    }

    fn summary(&self) -> &'static str {
        "Safety envelope between the arbiter and the motors: limits, collision monitor, geofence, stale sensors"
    }

    fn params(&self) -> &'static [ParamDecl] {
        PARAMS
    }

    fn guards_motors(&self) -> bool {
        true
    }

    /// `max-priority` caps the WASM sources feeding an arbiter; a geofence
    /// needs the pose wired.
    fn check_robot(&self, me: usize, params: &Params, view: &RobotView<'_>, registry: Registry) -> Vec<RobotProblem> {
        let robot = view.robot;
        let Some(envelope) = robot.components.get(me) else { return Vec::new() };
        let mut problems = Vec::new();
        if let Ok(cap) = params.integer("max-priority") {
            let feeds_an_arbiter = |i: usize| {
                robot.connections.iter().any(|k| {
                    k.from.component == i
                        && builtin::builtin_of(robot, k.to.component, registry).is_some_and(|b| b.arbitrates())
                })
            };
            for (i, source) in robot.components.iter().enumerate() {
                let over = source.priority.filter(|p| i64::from(*p) > cap);
                if let (ComponentSource::Wasm(_), Some(priority)) = (&source.source, over)
                    && feeds_an_arbiter(i)
                {
                    problems.push(RobotProblem {
                        offset: source.offset,
                        message: format!(
                            "component '{}' claims priority {priority}, but envelope '{}' allows WASM motion sources at most {cap}",
                            source.name, envelope.name
                        ),
                    });
                }
            }
        }
        let fenced = !params.text("geofence").unwrap_or_default().is_empty();
        let pose_wired = robot.connections.iter().any(|c| c.to.component == me && c.to.port == INPUT_POSE);
        if fenced && !pose_wired && view.wiring_known(me) {
            problems.push(RobotProblem {
                offset: envelope.offset,
                message: format!(
                    "envelope '{}' has a geofence but no pose: connect the odometry to '{}.pose'",
                    envelope.name, envelope.name
                ),
            });
        }
        problems
    }

    fn check(&self, params: &Params, _ctx: &mut CheckContext<'_>) -> Vec<ParamProblem> {
        let mut problems = Vec::new();
        if let Err(why) = parse_geofence(params.text("geofence").unwrap_or_default()) {
            problems.push(ParamProblem::new("geofence", why));
        }
        let (stop, slow) = (params.number("stop-distance"), params.number("slow-distance"));
        if let (Ok(stop), Ok(slow)) = (stop, slow)
            && stop > slow
        {
            problems.push(ParamProblem::new(
                "stop-distance",
                format!("must not exceed slow-distance ({slow} m), got {stop} m"),
            ));
        }
        problems
    }

    fn ports(&self, _params: &Params) -> Ports {
        Ports {
            inputs: vec![
                builtin::port("cmd", ValueKind::Command, "the arbiter's command"),
                builtin::port("ranges", ValueKind::Vector, "range readings in metres, right to left over fov"),
                builtin::port("pose", ValueKind::Vector, "odometry [x m, y m, heading rad]"),
                builtin::port(
                    "camera",
                    ValueKind::Bytes,
                    "a camera's pictures (e.g. builtin:camera's frame), wired when a component steers by them: STOP when they stop",
                ),
            ],
            outputs: vec![
                builtin::port("cmd", ValueKind::Command, "the command as the envelope lets it through"),
                builtin::port(
                    INTERVENTIONS_PORT,
                    ValueKind::Text,
                    "JSON when an intervention starts, changes or ends: action, cause, reading, commands (at most 10 a second)",
                ),
            ],
        }
    }

    fn build(&self, params: &Params, ctx: &mut BuildContext<'_>) -> Result<Box<dyn Component>, BuiltinError> {
        let wired = |port: u32| ctx.robot.connections.iter().any(|c| c.to.component == ctx.index && c.to.port == port);
        let settings = settings(
            params,
            Wired { ranges: wired(INPUT_RANGES), pose: wired(INPUT_POSE), camera: wired(INPUT_CAMERA) },
        )?;
        let name = ctx.component()?.name.clone();
        if !settings.watch_ranges {
            tracing::warn!(component = %name, "no ranges wired: the collision monitor is off");
        }
        if !settings.geofence.is_empty() && !settings.watch_pose {
            return Err(BuiltinError::Refused("a geofence needs the pose wired to the envelope's 'pose' input".into()));
        }
        Ok(Box::new(EnvelopeComponent::new(&name, settings)))
    }
}

/// One intervention, as the live view and the report show it.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Intervention {
    pub at_s: f64,
    pub action: Action,
    /// What came in and what went out.
    pub command: String,
    pub output: String,
    /// Why, with the reading behind it.
    pub cause: String,
    /// "stopped VEL 0.45 0.0: obstacle 0.18 m ahead, stop zone 0.25 m".
    pub text: String,
}

impl NamedSection for EnvelopeStatus {
    const SECTION: &'static str = "envelope";
}

/// The envelope's section of the report and the live status.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct EnvelopeStatus {
    /// The zones and limits (the live view draws the zones).
    pub settings: Settings,
    pub passed: u64,
    pub scaled: u64,
    pub stopped: u64,
    /// Interventions by cause.
    pub causes: BTreeMap<&'static str, u64>,
    /// The first intervention of each cause over the run (a preflight names
    /// when the robot first met the fence or the stop zone).
    pub first: BTreeMap<&'static str, Intervention>,
    pub last: Option<Intervention>,
    pub recent: VecDeque<Intervention>,
    /// Smallest clearance between the footprint and a range point, now
    /// and over the run, m.
    pub closest_m: Option<f64>,
    pub closest_ever_m: Option<f64>,
    /// The longest reaction time the envelope budgeted over the run, s: the
    /// worst recent interval between its judgments (a busy machine makes it
    /// longer, and the robot keeps further from what it sees).
    pub reaction_max_s: f64,
    /// The odometry pose the envelope last saw.
    pub pose: Option<[f64; 3]>,
    /// Commands that were not valid control strings (stopped).
    pub rejected: u64,
}

/// `builtin:envelope` at run time.
pub struct EnvelopeComponent {
    name: String,
    envelope: Envelope,
    /// The arbiter's latest command, as it entered (a review re-judges it).
    last_command: Option<(Command, ControlCommand)>,
    status: EnvelopeStatus,
    logged: BTreeMap<&'static str, u64>,
    /// What `interventions` has said and owes.
    notices: Notices,
}

impl EnvelopeComponent {
    pub fn new(name: &str, settings: Settings) -> EnvelopeComponent {
        EnvelopeComponent {
            name: name.to_string(),
            status: EnvelopeStatus {
                settings: settings.clone(),
                passed: 0,
                scaled: 0,
                stopped: 0,
                causes: BTreeMap::new(),
                first: BTreeMap::new(),
                last: None,
                recent: VecDeque::new(),
                closest_m: None,
                closest_ever_m: None,
                reaction_max_s: 0.0,
                pose: None,
                rejected: 0,
            },
            envelope: Envelope::new(settings),
            last_command: None,
            logged: BTreeMap::new(),
            notices: Notices::default(),
        }
    }

    /// The report's section.
    pub fn report(&self) -> &EnvelopeStatus {
        &self.status
    }

    /// Sends the verdict on `command` (`entered` is its text as it came in:
    /// a passed command goes on as it entered, a changed one is the host's).
    fn record(&mut self, entered: &Command, command: ControlCommand, verdict: &Verdict, now_ns: u64, out: &mut Outbox) {
        let output = match verdict.action {
            Action::Passed => entered.clone(),
            Action::Scaled | Action::Stopped => Command::from(verdict.command),
        };
        out.push((OUTPUT_CMD, Value::Command(output)));
        let notice = self.notices.note(command, verdict, now_ns);
        Self::say(notice, out);
        self.status.reaction_max_s = self.status.reaction_max_s.max(self.envelope.reaction_s());
        match verdict.action {
            Action::Passed => {
                self.status.passed += 1;
                return;
            }
            Action::Scaled => self.status.scaled += 1,
            Action::Stopped => self.status.stopped += 1,
        }
        let Some(cause) = &verdict.cause else { return };
        *self.status.causes.entry(cause.kind()).or_default() += 1;
        let verb = match verdict.action {
            Action::Scaled => format!("scaled {entered} to {}", verdict.command),
            _ => format!("stopped {entered}"),
        };
        let intervention = Intervention {
            at_s: now_ns as f64 / 1e9,
            action: verdict.action,
            command: entered.to_string(),
            output: verdict.command.to_string(),
            cause: cause.to_string(),
            text: format!("{verb}: {cause}"),
        };
        let due = self.logged.get(cause.kind()).is_none_or(|at| now_ns.saturating_sub(*at) >= LOG_INTERVAL_NS);
        if due {
            self.logged.insert(cause.kind(), now_ns);
            match verdict.action {
                Action::Stopped => tracing::warn!(component = %self.name, "{}", intervention.text),
                _ => tracing::info!(component = %self.name, "{}", intervention.text),
            }
        }
        if self.status.recent.len() >= RECENT_INTERVENTIONS {
            self.status.recent.pop_front();
        }
        self.status.first.entry(cause.kind()).or_insert_with(|| intervention.clone());
        self.status.recent.push_back(intervention.clone());
        self.status.last = Some(intervention);
    }

    /// Sends `notice` on the `interventions` output.
    fn say(notice: Option<notices::Notice>, out: &mut Outbox) {
        if let Some(text) = notice.and_then(|n| serde_json::to_string(&n).ok()) {
            out.push((OUTPUT_INTERVENTIONS, Value::Text(text)));
        }
    }

    /// Re-judges the latest command after new data or on a tick; emits
    /// only a more restrictive output.
    fn review(&mut self, now_ns: u64, out: &mut Outbox) {
        if let Some((entered, command)) = self.last_command.clone()
            && let Some(verdict) = self.envelope.review(command, now_ns)
        {
            self.record(&entered, command, &verdict, now_ns, out);
        }
    }
}

impl Component for EnvelopeComponent {
    fn on_input(
        &mut self,
        port: u32,
        value: &Value,
        _from: usize,
        now_ns: u64,
        out: &mut Outbox,
    ) -> Result<(), CallError> {
        match (port, value) {
            (INPUT_CMD, Value::Command(entered)) => match entered.parsed() {
                Ok(command) => {
                    self.last_command = Some((entered.clone(), command));
                    let verdict = self.envelope.decide(command, now_ns);
                    self.record(entered, command, &verdict, now_ns, out);
                    Ok(())
                }
                Err(err) => {
                    // Whatever was meant, nothing unchecked moves the robot.
                    self.status.rejected += 1;
                    let stop = ControlCommand::Stop;
                    self.last_command = Some((Command::from(stop), stop));
                    let verdict = self.envelope.decide(stop, now_ns);
                    out.push((OUTPUT_CMD, Value::Command(Command::from(verdict.command))));
                    Err(CallError::Reported(format!("stopped an invalid control string: {err}")))
                }
            },
            (INPUT_RANGES, Value::Vector(ranges)) => {
                self.envelope.ranges(ranges, now_ns);
                let closest = self.envelope.closest();
                self.status.closest_m = closest;
                if let Some(c) = closest {
                    self.status.closest_ever_m = Some(self.status.closest_ever_m.map_or(c, |e| e.min(c)));
                }
                self.review(now_ns, out);
                Ok(())
            }
            (INPUT_CAMERA, Value::Bytes(_)) => {
                self.envelope.picture(now_ns);
                Ok(())
            }
            (INPUT_POSE, Value::Vector(pose)) => {
                if self.envelope.pose(pose, now_ns) {
                    self.status.pose = pose.get(..3).and_then(|p| <[f64; 3]>::try_from(p).ok());
                    self.review(now_ns, out);
                    Ok(())
                } else {
                    Err(CallError::Reported(format!("pose: expected [x, y, heading], got {} numbers", pose.len())))
                }
            }
            _ => Err(CallError::Reported(format!("input {port}: unexpected {}", crate::contract::kind_of(value)))),
        }
    }

    fn tick(&mut self, now_ns: u64, out: &mut Outbox) -> Result<(), CallError> {
        self.review(now_ns, out);
        // A message held back by the interval goes out without waiting
        // for the next command.
        let notice = self.notices.due(now_ns);
        Self::say(notice, out);
        Ok(())
    }

    fn status(&self) -> Option<Box<dyn StatusSection>> {
        Some(Box::new(self.status.clone()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const MS: u64 = 1_000_000;

    fn component(pairs: &[(&str, &str)]) -> EnvelopeComponent {
        let params = Params::from_pairs(PARAMS, pairs).unwrap_or_default();
        let settings = settings(&params, Wired { ranges: true, ..Wired::default() }).map_err(|e| e.to_string());
        EnvelopeComponent::new("envelope", settings.unwrap_or_else(|e| panic!("{e}")))
    }

    fn cmd(text: &str) -> Value {
        Value::Command(text.into())
    }

    #[test]
    fn the_default_priority_cap_is_the_avoiders() {
        assert_eq!(DEFAULT_MAX_PRIORITY_TEXT.parse::<i32>(), Ok(DEFAULT_MAX_PRIORITY));
    }

    #[test]
    fn the_interventions_port_says_its_rate_bound() {
        let ports = EnvelopeBuiltin.ports(&Params::from_pairs(PARAMS, &[]).unwrap_or_default());
        let doc = ports.outputs.get(OUTPUT_INTERVENTIONS as usize).map(|p| p.doc.clone()).unwrap_or_default();
        assert_eq!(1_000_000_000 / notices::NOTICE_INTERVAL_NS, 10);
        assert!(doc.ends_with("(at most 10 a second)"), "{doc}");
    }

    #[test]
    fn geofences_parse_or_say_which_corner_is_wrong() {
        assert_eq!(parse_geofence(""), Ok(vec![]));
        assert_eq!(parse_geofence(" 0,0 4,0  4,3 "), Ok(vec![[0.0, 0.0], [4.0, 0.0], [4.0, 3.0]]));
        assert_eq!(parse_geofence("0,0 4,0"), Err("needs at least 3 corners 'x,y', got 2".into()));
        assert_eq!(parse_geofence("0,0 4;0 1,1"), Err("corner 2 is not 'x,y' in metres: '4;0'".into()));
        assert_eq!(parse_geofence("0,0 inf,0 1,1"), Err("corner 2 is not 'x,y' in metres: 'inf,0'".into()));
        let many = vec!["1,1"; MAX_FENCE_POINTS + 1].join(" ");
        assert!(parse_geofence(&many).is_err());
    }

    /// The last command on the `cmd` output.
    fn last_cmd(out: &Outbox) -> Option<&Value> {
        out.iter().rev().find(|(port, _)| *port == OUTPUT_CMD).map(|(_, value)| value)
    }

    /// The messages on the `interventions` output, parsed.
    fn notices_sent(out: &Outbox) -> Vec<serde_json::Value> {
        out.iter()
            .filter(|(port, _)| *port == OUTPUT_INTERVENTIONS)
            .filter_map(|(_, value)| match value {
                Value::Text(text) => serde_json::from_str(text).ok(),
                _ => None,
            })
            .collect()
    }

    #[test]
    fn a_wall_in_the_stop_zone_stops_at_once_and_is_reported() {
        let mut envelope = component(&[("max-accel", "100"), ("stop-distance", "0.25")]);
        let mut out = Vec::new();
        envelope.on_input(INPUT_RANGES, &Value::Vector(vec![4.0, 4.0, 4.0]), 0, 0, &mut out).ok();
        envelope.on_input(INPUT_CMD, &cmd("VEL 0.45 0"), 0, 10 * MS, &mut out).ok();
        // A passed command goes on as it came in (not reformatted).
        assert_eq!(last_cmd(&out), Some(&cmd("VEL 0.45 0")));
        // A reading in the stop zone: STOP goes out on the reading itself.
        envelope.on_input(INPUT_RANGES, &Value::Vector(vec![4.0, 0.36, 4.0]), 0, 20 * MS, &mut out).ok();
        assert_eq!(last_cmd(&out), Some(&cmd("STOP")));
        let status = envelope.report();
        assert_eq!((status.passed, status.stopped), (1, 1));
        assert_eq!(
            status.last.as_ref().map(|i| i.text.as_str()),
            Some("stopped VEL 0.45 0: obstacle 0.18 m ahead, stop zone 0.25 m")
        );
        assert_eq!(status.causes.get("stop-zone"), Some(&1));
        assert!(status.closest_ever_m.is_some_and(|c| (c - 0.18).abs() < 1e-9));
        // Components wired to `interventions` hear of it once, with the reading.
        let said = notices_sent(&out);
        assert_eq!(said.len(), 1, "{said:?}");
        assert_eq!((said[0]["action"].as_str(), said[0]["cause"].as_str()), (Some("stopped"), Some("stop-zone")));
        assert!(said[0]["reading"]["ahead_m"].as_f64().is_some_and(|a| (a - 0.18).abs() < 1e-9), "{said:?}");
        // The driver keeps pushing: every command is stopped.
        envelope.on_input(INPUT_CMD, &cmd("VEL 0.45 0"), 0, 30 * MS, &mut out).ok();
        assert_eq!(last_cmd(&out), Some(&cmd("STOP")));
        // Garbage is stopped too, and counted.
        let err = envelope.on_input(INPUT_CMD, &cmd("FLY"), 0, 40 * MS, &mut out);
        assert!(err.is_err());
        assert_eq!(last_cmd(&out), Some(&cmd("STOP")));
        assert_eq!(envelope.report().rejected, 1);
        assert_eq!(notices_sent(&out).len(), 1, "the hold went on: nothing more to say");
    }

    #[test]
    fn a_tick_stops_when_the_ranges_go_stale() {
        let mut envelope = component(&[("max-accel", "100"), ("stale", "0.2")]);
        let mut out = Vec::new();
        envelope.on_input(INPUT_RANGES, &Value::Vector(vec![4.0; 5]), 0, 0, &mut out).ok();
        envelope.on_input(INPUT_CMD, &cmd("VEL 0.3 0"), 0, 10 * MS, &mut out).ok();
        envelope.tick(150 * MS, &mut out).ok();
        assert_eq!(out.len(), 1, "fresh data: the tick sends nothing, and nothing was changed");
        envelope.tick(250 * MS, &mut out).ok();
        assert_eq!(last_cmd(&out), Some(&cmd("STOP")));
        assert_eq!(envelope.report().causes.get("stale-ranges"), Some(&1));
    }
}
