//! `builtin:teleop`: the network platform, declared ([`TeleopBuiltin`]):
//! its parameters with their bounds and the checks between them, the
//! operators file (read with the rest of the robot file), and starting the
//! servers.

use std::net::SocketAddr;
use std::path::Path;
use std::sync::Arc;
use std::time::Duration;

use super::delay::DelaySettings;
use super::mode::ModePolicy;
use super::{TeleopComponent, TeleopServers, TeleopSettings, load_operators};
use crate::builtin::{
    BuildContext, Builtin, BuiltinError, CheckContext, ParamDecl, ParamType, Params, Ports, PreflightContext,
    PreflightForm, number_in, port, positive_up_to,
};
use crate::config::ParamProblem;
use crate::contract::{ValueKind, clip};
use crate::runtime::{Component, Locks, RunningRobot, Standings};
use crate::store::users::Directory;
use crate::tls::{HostTls, TlsIdentity};

/// Most operators served at once: each holds a connection and a task.
pub const MAX_OPERATORS: i64 = 64;
/// Longest probe period (a day) and shortest (a tenth of a second: more
/// often would make the probe itself the load on the link).
pub const PROBE_PERIOD_RANGE_S: (f64, f64) = (0.1, 86_400.0);
/// Largest round-trip threshold and playout delay, seconds: a link slower
/// than this is not one to drive over.
pub const MAX_LINK_DELAY_S: f64 = 10.0;
/// Largest playout delay of the constant-delay buffer: every command waits
/// this long at most.
pub const MAX_PLAYOUT_DELAY_S: f64 = 5.0;
/// Bounds of `auth-timeout`: long enough for a TLS handshake and a typed
/// login over a slow link, short enough that a peer holding connections it
/// never logs in on gives them back within a minute.
pub const AUTH_TIMEOUT_RANGE_S: (f64, f64) = (0.5, 60.0);
/// Bounds of `idle-timeout`: an idle operator keeps a place another needs
/// for a day at most.
pub const IDLE_TIMEOUT_RANGE_S: (f64, f64) = (1.0, 86_400.0);

const PARAMS: &[ParamDecl] = &[
    ParamDecl {
        name: "listen",
        ty: ParamType::Address { optional: false },
        default: "127.0.0.1:7070",
        unit: "",
        doc: "TCP address of the line protocol (docs/teleop.md)",
    },
    ParamDecl {
        name: "websocket",
        ty: ParamType::Address { optional: true },
        default: "",
        unit: "",
        doc: "address of the WebSocket endpoint /teleop (JSON messages); empty: none",
    },
    ParamDecl {
        name: "tls",
        ty: ParamType::Choice(&["auto", "on", "off"]),
        default: "auto",
        unit: "",
        doc: "TLS on both listeners with the host's certificate (--tls-cert): auto (when the host has one), on (required), off",
    },
    ParamDecl {
        name: "operators",
        ty: ParamType::SecretFile {
            optional: true,
            stand_in: "# stands in for the robot's operators file: nobody drives from the lab server\n",
        },
        default: "",
        unit: "",
        doc: "file of NAME TOKEN lines, relative to the robot file; optional with the portal (its operators log in)",
    },
    ParamDecl {
        name: "probe-period",
        ty: number_in(PROBE_PERIOD_RANGE_S.0, PROBE_PERIOD_RANGE_S.1),
        default: "300",
        unit: "s",
        doc: "time between round-trip measurements (and one on connect)",
    },
    ParamDecl {
        name: "direct-below",
        ty: number_in(0.0, MAX_LINK_DELAY_S),
        default: "0.1",
        unit: "s",
        doc: "round-trip time under which direct mode is allowed",
    },
    ParamDecl {
        name: "shared-below",
        ty: number_in(0.0, MAX_LINK_DELAY_S),
        default: "0.3",
        unit: "s",
        doc: "round-trip time under which shared mode is allowed",
    },
    ParamDecl {
        name: "max-operators",
        ty: ParamType::Integer { min: 1, max: MAX_OPERATORS },
        default: "4",
        unit: "",
        doc: "operators logged in at once (connections that have not logged in take no place)",
    },
    ParamDecl {
        name: "auth-timeout",
        ty: number_in(AUTH_TIMEOUT_RANGE_S.0, AUTH_TIMEOUT_RANGE_S.1),
        default: "5",
        unit: "s",
        doc: "a connection that has not logged in this long after it opened is closed (TLS handshake included)",
    },
    ParamDecl {
        name: "idle-timeout",
        ty: number_in(IDLE_TIMEOUT_RANGE_S.0, IDLE_TIMEOUT_RANGE_S.1),
        default: "60",
        unit: "s",
        doc: "an operator who sent nothing but pongs this long gives up their place, or control, to another who asks",
    },
    ParamDecl {
        name: "delay",
        ty: ParamType::Required,
        default: "adaptive",
        unit: "s",
        doc: "playout delay: adaptive (follows jitter) or a fixed number of seconds",
    },
    ParamDecl {
        name: "min-delay",
        ty: number_in(0.0, MAX_PLAYOUT_DELAY_S),
        default: "0.01",
        unit: "s",
        doc: "smallest adaptive playout delay",
    },
    ParamDecl {
        name: "max-delay",
        ty: number_in(0.0, MAX_PLAYOUT_DELAY_S),
        default: "0.2",
        unit: "s",
        doc: "largest adaptive playout delay",
    },
    ParamDecl {
        name: "horizon",
        ty: positive_up_to(MAX_LINK_DELAY_S),
        default: "0.5",
        unit: "s",
        doc: "commands older than this are dropped as stale",
    },
];

/// The `teleop` kind.
pub struct TeleopBuiltin;

/// A fixed playout delay, or `None` for adaptive; the error completes
/// "parameter 'delay' ...".
fn fixed_delay(text: &str) -> Result<Option<Duration>, String> {
    let text = text.trim();
    if text == "adaptive" {
        return Ok(None);
    }
    text.parse::<f64>()
        .ok()
        .filter(|s| (0.0..=MAX_PLAYOUT_DELAY_S).contains(s))
        .map(|s| Some(Duration::from_secs_f64(s)))
        .ok_or_else(|| format!("must be adaptive or a number in [0, {MAX_PLAYOUT_DELAY_S}] s, got '{}'", clip(text)))
}

fn operators(params: &Params, base_dir: &Path) -> Result<Vec<(String, String)>, String> {
    let file = params.text("operators").unwrap_or_default();
    if file.is_empty() { Ok(Vec::new()) } else { load_operators(&base_dir.join(file)) }
}

/// The settings of a network platform from checked parameters.
pub fn settings(params: &Params, base_dir: &Path) -> Result<TeleopSettings, BuiltinError> {
    let listen = params
        .address("listen")?
        .ok_or_else(|| BuiltinError::Param { name: "listen".into(), why: "is empty".into() })?;
    let max_operators = params.integer("max-operators")?;
    Ok(TeleopSettings {
        listen,
        websocket: params.address("websocket")?,
        operators: operators(params, base_dir).map_err(|why| BuiltinError::Param { name: "operators".into(), why })?,
        directory: None,
        tls: None,
        probe_period: params.seconds("probe-period")?,
        policy: ModePolicy {
            direct_below: params.seconds("direct-below")?,
            shared_below: params.seconds("shared-below")?,
        },
        max_operators: usize::try_from(max_operators).map_err(|_| BuiltinError::Param {
            name: "max-operators".into(),
            why: format!("is out of range: {max_operators}"),
        })?,
        auth_timeout: params.seconds("auth-timeout")?,
        idle_timeout: params.seconds("idle-timeout")?,
        delay: DelaySettings {
            fixed: fixed_delay(params.text("delay")?)
                .map_err(|why| BuiltinError::Param { name: "delay".into(), why })?,
            min_delay: params.seconds("min-delay")?,
            max_delay: params.seconds("max-delay")?,
            horizon: params.seconds("horizon")?,
        },
    })
}

/// The identity both listeners serve TLS with (`None`: plain text), from
/// the `tls` parameter and the host's transport settings: `on` needs the
/// host's certificate, and plain text off loopback needs the owner's
/// `--allow-plain-http`.
fn transport(
    mode: &str,
    host: &HostTls,
    listen: SocketAddr,
    websocket: Option<SocketAddr>,
) -> Result<Option<TlsIdentity>, BuiltinError> {
    let identity = match mode {
        "off" => None,
        "on" => Some(host.identity.clone().ok_or_else(|| BuiltinError::Param {
            name: "tls".into(),
            why: "is on but the host has no certificate: run it with --tls-cert and --tls-key".into(),
        })?),
        _ => host.identity.clone(),
    };
    if identity.is_none() {
        let refused = |e: crate::tls::TlsError| BuiltinError::Refused(e.to_string());
        host.check_plain("teleoperation line protocol", listen).map_err(refused)?;
        if let Some(websocket) = websocket {
            host.check_plain("teleoperation websocket", websocket).map_err(refused)?;
        }
    }
    Ok(identity)
}

impl Builtin for TeleopBuiltin {
    fn kind(&self) -> &'static str {
        "teleop"
    }

    fn answers_to_a_person(&self) -> bool {
        true
    }

    fn summary(&self) -> &'static str {
        "Remote operators over TCP and WebSocket: latency probe, control modes, constant-delay buffer"
    }

    fn params(&self) -> &'static [ParamDecl] {
        PARAMS
    }

    fn default_priority(&self) -> Option<i32> {
        Some(1)
    }

    fn carried(&self) -> bool {
        true
    }

    fn check(&self, params: &Params, ctx: &mut CheckContext<'_>) -> Vec<ParamProblem> {
        let mut problems = Vec::new();
        if let Err(why) = fixed_delay(params.text("delay").unwrap_or_default()) {
            problems.push(ParamProblem::new("delay", why));
        }
        if let Err(why) = operators(params, ctx.base_dir) {
            problems.push(ParamProblem::new("operators", why));
        }
        let number = |name: &str| params.number(name).unwrap_or(0.0);
        if number("direct-below") > number("shared-below") {
            problems.push(ParamProblem::new(
                "direct-below",
                format!(
                    "must not exceed shared-below ({} s), got {} s",
                    number("shared-below"),
                    number("direct-below")
                ),
            ));
        }
        if number("min-delay") > number("max-delay") {
            problems.push(ParamProblem::new(
                "min-delay",
                format!("must not exceed max-delay ({} s), got {} s", number("max-delay"), number("min-delay")),
            ));
        }
        problems
    }

    /// Nobody drives a preflight: the line protocol listens on a port of
    /// the system's choosing on loopback (the robot's own stays the
    /// robot's), without the WebSocket or TLS, and the operators file is
    /// one of its own whose token nobody was told.
    fn preflight(
        &self,
        _params: &Params,
        _ctx: &PreflightContext<'_>,
    ) -> Result<PreflightForm, crate::builtin::NotSimulable> {
        let mut secret = [0u8; 24];
        getrandom::fill(&mut secret)
            .map_err(|e| crate::builtin::NotSimulable(format!("no randomness for a one-time token: {e}")))?;
        Ok(PreflightForm {
            set: vec![("listen", "127.0.0.1:0".into()), ("websocket", String::new()), ("tls", "off".into())],
            files: vec![(
                "operators",
                format!("# nobody drives a preflight\npreflight {}\n", hex::encode(secret)).into_bytes(),
            )],
            simulated_by: None,
        })
    }

    fn ports(&self, _params: &Params) -> Ports {
        Ports {
            inputs: vec![],
            outputs: vec![
                port("cmd", ValueKind::Command, "operator commands, released by the delay buffer"),
                port("goal", ValueKind::Vector, "operator goals (GOTO x y) as [x, y], for a planner"),
            ],
        }
    }

    fn build(&self, params: &Params, ctx: &mut BuildContext<'_>) -> Result<Box<dyn Component>, BuiltinError> {
        let mut settings = settings(params, ctx.base_dir)?;
        settings.directory = ctx.services.get::<Directory>();
        let host = ctx.services.get::<HostTls>().unwrap_or_default();
        settings.tls = transport(params.text("tls")?, &host, settings.listen, settings.websocket)?;
        let priority = ctx.priorities.get(ctx.index).cloned().unwrap_or_default();
        let name = ctx.component()?.name.clone();
        let robot = ctx.services.get::<RunningRobot>().unwrap_or_else(|| Arc::new(RunningRobot::new(&ctx.robot.name)));
        let standings = ctx.services.get::<Standings>().map(|s| (*s).clone()).unwrap_or_default();
        let locks = ctx.services.get::<Locks>().map(|l| (*l).clone()).unwrap_or_default();
        let component = TeleopComponent::start(
            &name,
            super::Surroundings {
                robot,
                standings,
                clock: ctx.clock.clone(),
                waker: ctx.waker.clone(),
                priority,
                locks,
            },
            settings,
        )?;
        if let Some(servers) = ctx.services.get::<TeleopServers>() {
            servers.register(component.context());
        }
        Ok(Box::new(component))
    }
}
