//! `builtin:zenoh` (a session and its settings), `builtin:zenoh-publish`
//! and `builtin:zenoh-subscribe`: ports over
//! Zenoh between subsume hosts. A publisher puts every value on its input
//! on a key expression ([`super::wire`] encoding); a subscriber emits every
//! value that arrives on its key expression and fits its declared kind.
//! A subscriber of kind `command` wired into an arbiter is one more motion
//! source, with the priority and timeout this robot file gives it: nothing
//! a peer sends changes them.

use std::sync::Arc;

use super::link::{Inlet, Outlet};
use super::session::{self, BridgeStats, SESSION_PARAMS, SessionSettings};
use super::wire;
use crate::builtin::{
    self, BuildContext, Builtin, BuiltinError, CheckContext, ParamDecl, ParamType, Params, Ports, PreflightContext,
    PreflightForm, Registry, check_values, port,
};
use crate::config::{ParamProblem, RobotProblem, RobotView};
use crate::contract::{Value, ValueKind, clip};
use crate::runtime::{CallError, Component, Outbox, StatusSection};

/// The kinds a subscriber may declare.
pub const KINDS: &[&str] = &["flag", "scalar", "vector", "text", "command", "bytes", "scan"];

/// Checks a key expression: Zenoh's syntax, no admin space (`@`), and for
/// a publisher no wildcard.
fn check_key(key: &str, publish: bool) -> Result<(), String> {
    let ke = zenoh::key_expr::keyexpr::new(key).map_err(|_| {
        format!(
            "is not a zenoh key expression (chunks separated by '/', none empty, no leading or trailing '/', \
             no '?' or '#'): '{}'",
            clip(key)
        )
    })?;
    if key.starts_with('@') {
        return Err(format!("is in zenoh's reserved '@' space: '{}'", clip(key)));
    }
    if publish && ke.is_wild() {
        return Err(format!("has a wildcard, but a publisher needs one key: '{}'", clip(key)));
    }
    Ok(())
}

/// The session a bridge uses when its robot file names none.
pub const DEFAULT_SESSION: &str = "zenoh";

/// A bridge's robot-wide rule: the session it names is a `builtin:zenoh`
/// component of this robot (one that failed its own checks was reported
/// already).
pub fn check_session(
    bridge: &dyn Builtin,
    me: usize,
    params: &Params,
    view: &RobotView<'_>,
    registry: Registry,
) -> Vec<RobotProblem> {
    let robot = view.robot;
    let Some(component) = robot.components.get(me) else { return Vec::new() };
    let session = params.text(SESSION_PARAM.name).unwrap_or_default();
    if view.failed(session) {
        return Vec::new();
    }
    let why = match robot.components.iter().position(|c| c.name == session) {
        Some(index) => match builtin::builtin_of(robot, index, registry) {
            Some(b) if b.kind() == ZenohSession.kind() => return Vec::new(),
            _ => format!("'{}' comes from {}, not builtin:zenoh", clip(session), robot.components[index].source),
        },
        None => format!(
            "this robot has no component '{}' (add <component name=\"{}\" source=\"builtin:zenoh\"/>)",
            clip(session),
            clip(session)
        ),
    };
    vec![RobotProblem {
        offset: component.offset,
        message: format!(
            "builtin:{} '{}' names zenoh session '{}', but {why}",
            bridge.kind(),
            component.name,
            clip(session)
        ),
    }]
}

/// The parameter naming the session component, which every Zenoh and
/// ROS 2 built-in declares.
pub const SESSION_PARAM: ParamDecl = ParamDecl {
    name: "session",
    ty: ParamType::Required,
    default: DEFAULT_SESSION,
    unit: "",
    doc: "the builtin:zenoh component (in this robot file) whose session this uses",
};

/// The session the component being built names in its `session` parameter.
pub fn session_for(params: &Params, ctx: &BuildContext<'_>) -> Result<Arc<session::Shared>, BuiltinError> {
    let name = params.text("session")?;
    let component = ctx
        .robot
        .components
        .iter()
        .enumerate()
        .find(|(i, c)| {
            c.name == name
                && builtin::builtin_of(ctx.robot, *i, ctx.registry).is_some_and(|b| b.kind() == ZenohSession.kind())
        })
        .map(|(_, c)| c)
        .ok_or_else(|| {
            BuiltinError::Refused(format!("session '{}' is not a builtin:zenoh component of this robot", clip(name)))
        })?;
    let given = component.params.iter().map(|p| (p.name.clone(), p.value.clone())).collect();
    let session_params = check_values(&SESSION_PARAMS, &given)
        .map_err(|problems| BuiltinError::Refused(format!("session '{name}': {} bad parameters", problems.len())))?;
    let settings = SessionSettings::from_params(&session_params, ctx.base_dir)?;
    Ok(session::session(&settings)?)
}

/// `builtin:zenoh`: one Zenoh session and its settings, which the other
/// Zenoh and ROS 2 built-ins name. It has no ports.
pub struct ZenohSession;

impl Builtin for ZenohSession {
    fn kind(&self) -> &'static str {
        "zenoh"
    }

    fn summary(&self) -> &'static str {
        "A Zenoh session (peer mode, no multicast scouting) the Zenoh and ROS 2 built-ins share"
    }

    fn params(&self) -> &'static [ParamDecl] {
        &SESSION_PARAMS
    }

    fn check(&self, params: &Params, ctx: &mut CheckContext<'_>) -> Vec<ParamProblem> {
        SessionSettings::check(params, ctx.base_dir)
    }

    /// A preflight's session talks to nobody: no endpoints, no config
    /// file (multicast scouting is off for every session), so nothing it
    /// publishes reaches the robot's peers and nothing of theirs reaches it.
    fn preflight(
        &self,
        _params: &Params,
        _ctx: &PreflightContext<'_>,
    ) -> Result<PreflightForm, crate::builtin::NotSimulable> {
        Ok(PreflightForm {
            set: vec![("connect", String::new()), ("listen", String::new()), ("zenoh-config", String::new())],
            files: Vec::new(),
            simulated_by: None,
        })
    }

    fn ports(&self, _params: &Params) -> Ports {
        Ports::default()
    }

    fn build(&self, params: &Params, ctx: &mut BuildContext<'_>) -> Result<Box<dyn Component>, BuiltinError> {
        let settings = SessionSettings::from_params(params, ctx.base_dir)?;
        let shared = session::session(&settings)?;
        Ok(Box::new(SessionComponent { shared, settings }))
    }
}

struct SessionComponent {
    shared: Arc<session::Shared>,
    settings: SessionSettings,
}

impl Component for SessionComponent {
    fn status(&self) -> Option<Box<dyn StatusSection>> {
        Some(Box::new(session::SessionStatus {
            session: self.shared.id.clone(),
            peers: self.shared.peers(),
            connect: self.settings.connect.clone(),
            listen: self.settings.listen.clone(),
        }))
    }
}

const PUBLISH_PARAMS: [ParamDecl; 2] = [
    ParamDecl {
        name: "key",
        ty: ParamType::Required,
        default: "",
        unit: "",
        doc: "the zenoh key expression values are put on (robot-a/ranges)",
    },
    SESSION_PARAM,
];

const SUBSCRIBE_PARAMS: [ParamDecl; 3] = [
    ParamDecl {
        name: "key",
        ty: ParamType::Required,
        default: "",
        unit: "",
        doc: "the zenoh key expression values arrive on (wildcards allowed)",
    },
    ParamDecl {
        name: "kind",
        ty: ParamType::Choice(KINDS),
        default: "scalar",
        unit: "",
        doc: "kind of the values: others are counted as malformed and dropped",
    },
    SESSION_PARAM,
];

fn check(params: &Params, publish: bool) -> Vec<ParamProblem> {
    match check_key(params.text("key").unwrap_or_default(), publish) {
        Ok(()) => Vec::new(),
        Err(why) => vec![ParamProblem::new("key", why)],
    }
}

/// `builtin:zenoh-publish`.
pub struct ZenohPublish;

impl Builtin for ZenohPublish {
    fn kind(&self) -> &'static str {
        "zenoh-publish"
    }

    fn check_robot(&self, me: usize, params: &Params, view: &RobotView<'_>, registry: Registry) -> Vec<RobotProblem> {
        check_session(self, me, params, view, registry)
    }

    fn summary(&self) -> &'static str {
        "Puts every value on its input on a Zenoh key expression"
    }

    fn params(&self) -> &'static [ParamDecl] {
        &PUBLISH_PARAMS
    }

    fn check(&self, params: &Params, _ctx: &mut CheckContext<'_>) -> Vec<ParamProblem> {
        check(params, true)
    }

    fn ports(&self, _params: &Params) -> Ports {
        Ports { inputs: vec![port("in", ValueKind::Any, "values to publish")], outputs: vec![] }
    }

    fn build(&self, params: &Params, ctx: &mut BuildContext<'_>) -> Result<Box<dyn Component>, BuiltinError> {
        let key = params.text("key")?.to_string();
        let shared = session_for(params, ctx)?;
        let outlet = Outlet::new(shared.clone(), key.clone(), Arc::new(BridgeStats::default()), None)?;
        Ok(Box::new(Publisher { key, shared, outlet }))
    }
}

struct Publisher {
    key: String,
    shared: Arc<session::Shared>,
    outlet: Outlet,
}

impl Component for Publisher {
    fn on_input(
        &mut self,
        _port: u32,
        value: &Value,
        _from: usize,
        _now_ns: u64,
        _out: &mut Outbox,
    ) -> Result<(), CallError> {
        self.outlet.send(wire::encode(value));
        Ok(())
    }

    fn status(&self) -> Option<Box<dyn StatusSection>> {
        Some(Box::new(self.outlet.stats.status("zenoh", &self.key, &self.shared)))
    }
}

/// `builtin:zenoh-subscribe`.
pub struct ZenohSubscribe;

impl Builtin for ZenohSubscribe {
    fn kind(&self) -> &'static str {
        "zenoh-subscribe"
    }

    fn check_robot(&self, me: usize, params: &Params, view: &RobotView<'_>, registry: Registry) -> Vec<RobotProblem> {
        check_session(self, me, params, view, registry)
    }

    fn summary(&self) -> &'static str {
        "Emits every value that arrives on a Zenoh key expression"
    }

    fn params(&self) -> &'static [ParamDecl] {
        &SUBSCRIBE_PARAMS
    }

    fn check(&self, params: &Params, _ctx: &mut CheckContext<'_>) -> Vec<ParamProblem> {
        check(params, false)
    }

    fn ports(&self, params: &Params) -> Ports {
        let kind = params.text("kind").ok().and_then(ValueKind::parse).unwrap_or(ValueKind::Scalar);
        Ports { inputs: vec![], outputs: vec![port("out", kind, "values from the key expression")] }
    }

    fn build(&self, params: &Params, ctx: &mut BuildContext<'_>) -> Result<Box<dyn Component>, BuiltinError> {
        let key = params.text("key")?.to_string();
        let kind = ValueKind::parse(params.text("kind")?).unwrap_or(ValueKind::Scalar);
        let shared = session_for(params, ctx)?;
        let inlet = Inlet::new(
            shared.clone(),
            key.clone(),
            Arc::new(BridgeStats::default()),
            ctx.waker.clone(),
            move |bytes, _| wire::decode_as(bytes, kind).map_err(|e| e.to_string()),
        )?;
        Ok(Box::new(Subscriber { key, shared, inlet }))
    }
}

struct Subscriber {
    key: String,
    shared: Arc<session::Shared>,
    inlet: Inlet<Value>,
}

impl Component for Subscriber {
    fn poll(&mut self, _now_ns: u64, out: &mut Outbox) {
        for value in self.inlet.drain() {
            out.push((0, value));
        }
    }

    fn status(&self) -> Option<Box<dyn StatusSection>> {
        Some(Box::new(self.inlet.stats.status("zenoh", &self.key, &self.shared)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn key_expressions_are_checked() {
        assert!(check_key("robot-a/ranges", true).is_ok());
        assert!(check_key("robot-a/*", false).is_ok());
        assert!(check_key("robot-a/*", true).is_err());
        assert!(check_key("robot-a//ranges", false).is_err());
        assert!(check_key("/ranges", false).is_err());
        assert!(check_key("@ros2_lv/x", false).is_err());
        assert!(check_key("a/b?c", false).is_err());
    }
}
