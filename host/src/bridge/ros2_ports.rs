//! `builtin:ros2-publish` and `builtin:ros2-subscribe`: the ROS 2 face.
//! A port becomes a ROS 2 topic as rmw_zenoh nodes see it (key expression,
//! CDR payload, attachment, liveliness tokens under `@ros2_lv`, so `ros2
//! topic list` shows it), for the message types of [`MessageType`]:
//!
//! | type | port kind | mapping |
//! |---|---|---|
//! | `geometry_msgs/msg/Twist` | command | `VEL v w` <-> linear.x = v, angular.z = w; STOP -> the zero Twist |
//! | `nav_msgs/msg/Odometry` | vector | `[x, y, heading]` <-> pose position and yaw |
//! | `sensor_msgs/msg/LaserScan` | vector (a scan too, out) | ranges right to left over `fov`; in, no return reads as range_max |
//! | `rcl_interfaces/msg/Log` | any / text | each value as a log line (level info) |
//! | `std_msgs/msg/Bool` | flag | data |
//!
//! A Twist publisher sends the zero Twist when STOP comes in, when it
//! faults and when it is dropped (every orderly exit), so a ROS 2 base
//! behind it stops; it also joins `runtime::halt`, so the panic hook and a
//! second signal send it past the queue, and nothing goes out after it.

use std::sync::Arc;
use std::sync::atomic::{AtomicI64, Ordering};
use std::time::Duration;

use super::cdr::{self, Header, LaserScan, Log, Odometry, Time, Twist};
use super::link::{Gate, Inlet, Outlet, Stamp};
use super::ports::{SESSION_PARAM, check_session, session_for};
use super::ros2::{self, Attachment, Distro, EntityKind, MessageType};
use super::session::{BridgeStats, Shared, unix_ns};
use crate::builtin::{
    BuildContext, Builtin, BuiltinError, CheckContext, ParamDecl, ParamType, Params, Ports, Registry, port,
};
use crate::config::{ParamProblem, RobotProblem, RobotView};
use crate::contract::control::ControlCommand;
use crate::contract::{Value, ValueKind, clip};
use crate::runtime::halt::{self, Halt};
use crate::runtime::{CallError, Component, MotorStop, Outbox, StatusSection, StopOutcome};
use zenoh::Wait;

/// Highest ROS 2 domain id (ROS 2's own limit for UDP ports is 232).
pub const MAX_DOMAIN: i64 = 232;

const fn common(topic_doc: &'static str) -> [ParamDecl; 6] {
    [
        ParamDecl { name: "topic", ty: ParamType::Required, default: "", unit: "", doc: topic_doc },
        ParamDecl {
            name: "type",
            ty: ParamType::Choice(MessageType::NAMES),
            default: "geometry_msgs/msg/Twist",
            unit: "",
            doc: "the message type",
        },
        ParamDecl {
            name: "domain",
            ty: ParamType::Integer { min: 0, max: MAX_DOMAIN },
            default: "0",
            unit: "",
            doc: "the ROS_DOMAIN_ID",
        },
        ParamDecl {
            name: "node",
            ty: ParamType::Required,
            default: "subsume",
            unit: "",
            doc: "the node name ROS 2 tools show",
        },
        ParamDecl {
            name: "distro",
            ty: ParamType::Choice(Distro::NAMES),
            default: "jazzy",
            unit: "",
            doc: "jazzy or kilted (RIHS01 type hashes) or humble (TypeHashNotSupported)",
        },
        SESSION_PARAM,
    ]
}

const PUBLISH_PARAMS: [ParamDecl; 10] = {
    let c = common("the topic published (/odom, /scan, /rosout, /cmd_vel)");
    [
        c[0],
        c[1],
        c[2],
        c[3],
        c[4],
        c[5],
        ParamDecl {
            name: "frame-id",
            ty: ParamType::Text,
            default: "base_link",
            unit: "",
            doc: "header.frame_id (odometry: the odom frame is 'odom', this is the child)",
        },
        ParamDecl {
            name: "fov",
            ty: ParamType::Number {
                min: crate::builtin::Bound::Exclusive(0.0),
                max: crate::builtin::Bound::Inclusive(std::f64::consts::TAU),
            },
            default: "3.14159",
            unit: "rad",
            doc: "a scan from a vector: the angle its rays span, right to left",
        },
        ParamDecl {
            name: "range-max",
            ty: ParamType::Number {
                min: crate::builtin::Bound::Exclusive(0.0),
                max: crate::builtin::Bound::Inclusive(1000.0),
            },
            default: "4.0",
            unit: "m",
            doc: "a scan from a vector: its range_max",
        },
        ParamDecl {
            name: "level",
            ty: ParamType::Choice(&["debug", "info", "warn", "error"]),
            default: "info",
            unit: "",
            doc: "a log: the level of each line",
        },
    ]
};

const SUBSCRIBE_PARAMS: [ParamDecl; 6] = common("the topic subscribed (/cmd_vel, /scan, /odom)");

fn check_common(params: &Params) -> Vec<ParamProblem> {
    let mut problems = Vec::new();
    if let Err(e) = ros2::topic_path(params.text("topic").unwrap_or_default()) {
        problems.push(ParamProblem::new("topic", format!("is not a ros 2 topic name: {}", e.0)));
    }
    if let Err(e) = ros2::check_node_name(params.text("node").unwrap_or_default()) {
        problems.push(ParamProblem::new("node", format!("is not a ros 2 node name: {}", e.0)));
    }
    problems
}

fn message_type(params: &Params) -> MessageType {
    params.text("type").ok().and_then(MessageType::parse).unwrap_or(MessageType::Twist)
}

/// One ROS 2 entity: its key, its tokens (alive while this is).
struct Entity {
    key: String,
    gid: [u8; 16],
    shared: Arc<Shared>,
    _tokens: [zenoh::liveliness::LivelinessToken; 2],
}

fn declare(params: &Params, ctx: &BuildContext<'_>, kind: EntityKind) -> Result<Entity, BuiltinError> {
    let shared = session_for(params, ctx)?;
    let ty = message_type(params);
    let domain = params.integer("domain")? as u32;
    let distro = Distro::parse(params.text("distro")?).unwrap_or(Distro::Jazzy);
    let node = params.text("node")?;
    let path = ros2::topic_path(params.text("topic")?).map_err(|e| BuiltinError::Refused(e.0))?;
    let entity = shared.next_entity();
    let token = |key: String| {
        shared
            .session
            .liveliness()
            .declare_token(key.clone())
            .wait()
            .map_err(|why| BuiltinError::Refused(format!("liveliness token '{}': {why}", clip(&key))))
    };
    let node_token = token(ros2::node_token(domain, &shared.id, 0, node))?;
    let entity_token = token(ros2::entity_token(domain, &shared.id, 0, entity, kind, node, path, ty, distro))?;
    Ok(Entity {
        key: ros2::topic_key(domain, path, ty, distro),
        gid: ros2::gid(&shared.id, entity),
        shared: shared.clone(),
        _tokens: [node_token, entity_token],
    })
}

/// `builtin:ros2-publish`.
pub struct Ros2Publish;

impl Builtin for Ros2Publish {
    fn kind(&self) -> &'static str {
        "ros2-publish"
    }

    fn check_robot(&self, me: usize, params: &Params, view: &RobotView<'_>, registry: Registry) -> Vec<RobotProblem> {
        check_session(self, me, params, view, registry)
    }

    fn summary(&self) -> &'static str {
        "Publishes its input as a ROS 2 topic (rmw_zenoh wire format)"
    }

    fn params(&self) -> &'static [ParamDecl] {
        &PUBLISH_PARAMS
    }

    fn check(&self, params: &Params, _ctx: &mut CheckContext<'_>) -> Vec<ParamProblem> {
        check_common(params)
    }

    fn ports(&self, params: &Params) -> Ports {
        let kind = match message_type(params) {
            MessageType::Twist => ValueKind::Command,
            MessageType::Odometry | MessageType::LaserScan => ValueKind::Vector,
            MessageType::Log => ValueKind::Any,
            MessageType::Bool => ValueKind::Flag,
        };
        Ports { inputs: vec![port("in", kind, "the values to publish")], outputs: vec![] }
    }

    fn build(&self, params: &Params, ctx: &mut BuildContext<'_>) -> Result<Box<dyn Component>, BuiltinError> {
        let entity = declare(params, ctx, EntityKind::Publisher)?;
        let sequence = Arc::new(AtomicI64::new(0));
        let gid = entity.gid;
        let stamp_sequence = sequence.clone();
        let stamp: Stamp = Box::new(move || {
            let sequence = stamp_sequence.fetch_add(1, Ordering::Relaxed) + 1;
            Attachment { sequence, timestamp_ns: unix_ns() as i64, gid }.encode().to_vec()
        });
        let outlet =
            Outlet::new(entity.shared.clone(), entity.key.clone(), Arc::new(BridgeStats::default()), Some(stamp))?;
        let ty = message_type(params);
        // A Twist publisher drives a base: it joins the exits that cannot
        // wait for the loop (the panic hook, a second signal).
        let name = ctx.robot.components.get(ctx.index).map(|c| c.name.clone()).unwrap_or_default();
        let halt = (ty == MessageType::Twist).then(|| {
            let action: Arc<dyn Halt> = Arc::new(ZeroTwist {
                label: format!("ros2 publisher '{name}'"),
                gate: outlet.gate(),
                shared: entity.shared.clone(),
            });
            halt::register(&action);
            action
        });
        // ... and the stall watchdog stops the base with a zero Twist past
        // the queue (what the loop queued before it is dropped).
        let stop = (ty == MessageType::Twist)
            .then(|| Arc::new(TwistStop { name: name.clone(), gate: outlet.gate() }) as Arc<dyn MotorStop>);
        Ok(Box::new(Ros2Publisher {
            ty,
            node: params.text("node")?.to_string(),
            frame_id: params.text("frame-id")?.to_string(),
            fov: params.number("fov")?,
            range_max: params.number("range-max")?,
            level: match params.text("level")? {
                "debug" => 10,
                "warn" => 30,
                "error" => 40,
                _ => 20,
            },
            entity,
            outlet,
            _halt: halt,
            stop,
        }))
    }
}

/// The final zero Twist of a `cmd_vel` publisher, from any thread.
struct ZeroTwist {
    label: String,
    gate: Arc<Gate>,
    shared: Arc<Shared>,
}

impl Halt for ZeroTwist {
    fn label(&self) -> String {
        self.label.clone()
    }

    fn halt(&self, wait: Duration) -> StopOutcome {
        self.gate.halt(Twist::default().encode(), wait)
    }

    /// The process is about to exit: closing the session flushes what is
    /// queued for the wire (the zero Twist) and tells the peers.
    /// Waits at most `wait` (Zenoh's own close timeout is not a stable
    /// setting, so the close runs on a thread of its own).
    fn settle(&self, wait: Duration) {
        let (done, closed) = std::sync::mpsc::sync_channel(1);
        let shared = self.shared.clone();
        let started = std::thread::Builder::new().name("zenoh-close".into()).spawn(move || {
            let _ = done.send(shared.session.close().wait().map_err(|why| why.to_string()));
        });
        let outcome = match started {
            Ok(_) => closed.recv_timeout(wait).map_err(|_| format!("not closed within {} ms", wait.as_millis())),
            Err(e) => Err(format!("cannot start a thread: {e}")),
        };
        if let Err(why) | Ok(Err(why)) = outcome {
            tracing::warn!("{}: closing the zenoh session: {why}", self.label);
        }
    }
}

/// The stall watchdog's stop of a `cmd_vel` publisher: a zero Twist now.
struct TwistStop {
    name: String,
    gate: Arc<Gate>,
}

impl MotorStop for TwistStop {
    fn name(&self) -> &str {
        &self.name
    }

    fn stop_now(&self, wait: Duration) -> StopOutcome {
        self.gate.stop_now(Twist::default().encode(), wait)
    }
}

struct Ros2Publisher {
    ty: MessageType,
    node: String,
    frame_id: String,
    fov: f64,
    range_max: f64,
    level: u8,
    entity: Entity,
    outlet: Outlet,
    /// Registered with `runtime::halt` while this lives (Twist only).
    _halt: Option<Arc<dyn Halt>>,
    /// The stall watchdog's handle (Twist only).
    stop: Option<Arc<dyn MotorStop>>,
}

impl Ros2Publisher {
    /// The CDR payload for `value`, or why it has none.
    fn payload(&self, value: &Value) -> Result<Vec<u8>, String> {
        let header = || Header { stamp: Time::from_unix_ns(unix_ns()), frame_id: self.frame_id.clone() };
        match (self.ty, value) {
            (MessageType::Twist, Value::Command(command)) => match command.parsed() {
                Ok(ControlCommand::Stop) => Ok(Twist::default().encode()),
                Ok(ControlCommand::Vel { linear, angular }) => {
                    Ok(Twist { linear: [linear, 0.0, 0.0], angular: [0.0, 0.0, angular] }.encode())
                }
                Ok(ControlCommand::Goto { .. }) => Err("a GOTO has no Twist".into()),
                Err(e) => Err(format!("invalid control string: {e}")),
            },
            (MessageType::Odometry, Value::Vector(v)) if v.len() >= 3 => {
                Ok(Odometry::planar(Header { frame_id: "odom".into(), ..header() }, &self.frame_id, v[0], v[1], v[2])
                    .encode())
            }
            (MessageType::LaserScan, Value::Vector(v)) if !v.is_empty() => {
                let step = if v.len() > 1 { self.fov / (v.len() - 1) as f64 } else { 0.0 };
                Ok(LaserScan {
                    header: header(),
                    angle_min: (-self.fov / 2.0) as f32,
                    angle_max: (self.fov / 2.0) as f32,
                    angle_increment: step as f32,
                    range_max: self.range_max as f32,
                    ranges: v.iter().map(|x| *x as f32).collect(),
                    ..LaserScan::default()
                }
                .encode())
            }
            (MessageType::LaserScan, Value::Scan(s)) => Ok(LaserScan {
                header: header(),
                angle_min: s.angle_min as f32,
                angle_max: (s.angle_min + s.angle_increment * s.ranges.len().saturating_sub(1) as f64) as f32,
                angle_increment: s.angle_increment as f32,
                range_min: s.range_min as f32,
                range_max: s.range_max as f32,
                ranges: s.ranges.iter().map(|x| *x as f32).collect(),
                ..LaserScan::default()
            }
            .encode()),
            (MessageType::Log, value) => {
                let msg = match value {
                    Value::Text(t) => clip(t),
                    Value::Command(c) => clip(&c.text()),
                    Value::Scalar(x) => x.to_string(),
                    Value::Flag(b) => b.to_string(),
                    other => clip(&format!("{other:?}")),
                };
                Ok(Log {
                    stamp: Time::from_unix_ns(unix_ns()),
                    level: self.level,
                    name: self.node.clone(),
                    msg,
                    ..Log::default()
                }
                .encode())
            }
            (MessageType::Bool, Value::Flag(b)) => Ok(cdr::encode_bool(*b)),
            (ty, value) => Err(format!("{} cannot carry a {}", ty.ros_name(), crate::contract::kind_of(value).name())),
        }
    }

    fn zero_twist(&self) -> Option<Vec<u8>> {
        (self.ty == MessageType::Twist).then(|| Twist::default().encode())
    }
}

impl Component for Ros2Publisher {
    fn on_input(
        &mut self,
        _port: u32,
        value: &Value,
        _from: usize,
        _now_ns: u64,
        _out: &mut Outbox,
    ) -> Result<(), CallError> {
        match self.payload(value) {
            Ok(payload) => self.outlet.send(payload),
            Err(why) => self.outlet.stats.malformed(why),
        }
        Ok(())
    }

    fn motor_stop(&self) -> Option<Arc<dyn MotorStop>> {
        self.stop.clone()
    }

    fn faulted(&mut self) {
        let last = self.zero_twist();
        self.outlet.finish(last);
    }

    fn status(&self) -> Option<Box<dyn StatusSection>> {
        Some(Box::new(self.outlet.stats.status("ros2", &self.entity.key, &self.entity.shared)))
    }
}

impl Drop for Ros2Publisher {
    fn drop(&mut self) {
        let last = self.zero_twist();
        self.outlet.finish(last);
    }
}

/// `builtin:ros2-subscribe`.
pub struct Ros2Subscribe;

impl Builtin for Ros2Subscribe {
    fn kind(&self) -> &'static str {
        "ros2-subscribe"
    }

    fn check_robot(&self, me: usize, params: &Params, view: &RobotView<'_>, registry: Registry) -> Vec<RobotProblem> {
        check_session(self, me, params, view, registry)
    }

    fn summary(&self) -> &'static str {
        "Emits the messages of a ROS 2 topic (rmw_zenoh wire format)"
    }

    fn params(&self) -> &'static [ParamDecl] {
        &SUBSCRIBE_PARAMS
    }

    fn check(&self, params: &Params, _ctx: &mut CheckContext<'_>) -> Vec<ParamProblem> {
        check_common(params)
    }

    fn ports(&self, params: &Params) -> Ports {
        let kind = match message_type(params) {
            MessageType::Twist => ValueKind::Command,
            MessageType::Odometry => ValueKind::Vector,
            MessageType::LaserScan => ValueKind::Vector,
            MessageType::Log => ValueKind::Text,
            MessageType::Bool => ValueKind::Flag,
        };
        Ports { inputs: vec![], outputs: vec![port("out", kind, "the messages, as values")] }
    }

    fn build(&self, params: &Params, ctx: &mut BuildContext<'_>) -> Result<Box<dyn Component>, BuiltinError> {
        let entity = declare(params, ctx, EntityKind::Subscription)?;
        let ty = message_type(params);
        let inlet = Inlet::new(
            entity.shared.clone(),
            entity.key.clone(),
            Arc::new(BridgeStats::default()),
            ctx.waker.clone(),
            move |payload, attachment| decode(ty, payload, attachment),
        )?;
        Ok(Box::new(Ros2Subscriber { entity, inlet }))
    }
}

/// A ROS 2 message as a value (untrusted bytes: every error is a reason).
fn decode(ty: MessageType, payload: &[u8], attachment: Option<&[u8]>) -> Result<Value, String> {
    if let Some(a) = attachment
        && Attachment::decode(a).is_none()
    {
        return Err(format!("attachment of {} bytes is not rmw_zenoh's", a.len()));
    }
    let value = match ty {
        MessageType::Twist => {
            let t = Twist::decode(payload).map_err(|e| e.to_string())?;
            Value::Command(ControlCommand::Vel { linear: t.linear[0], angular: t.angular[2] }.into())
        }
        MessageType::Odometry => {
            let o = Odometry::decode(payload).map_err(|e| e.to_string())?;
            Value::Vector(vec![o.position[0], o.position[1], o.heading()])
        }
        MessageType::LaserScan => {
            let s = LaserScan::decode(payload).map_err(|e| e.to_string())?;
            // The ranges, as the serial link gives them (right to left):
            // what the avoider, the filter and the envelope read. No return
            // (inf, NaN) reads as range_max.
            let range_max = s.range_max as f64;
            Value::Vector(s.ranges.iter().map(|r| if r.is_finite() { *r as f64 } else { range_max }).collect())
        }
        MessageType::Log => {
            let l = Log::decode(payload).map_err(|e| e.to_string())?;
            Value::Text(clip(&format!("{}: {}", l.name, l.msg)))
        }
        MessageType::Bool => Value::Flag(cdr::decode_bool(payload).map_err(|e| e.to_string())?),
    };
    Ok(value)
}

struct Ros2Subscriber {
    entity: Entity,
    inlet: Inlet<Value>,
}

impl Component for Ros2Subscriber {
    fn poll(&mut self, _now_ns: u64, out: &mut Outbox) {
        for value in self.inlet.drain() {
            out.push((0, value));
        }
    }

    fn status(&self) -> Option<Box<dyn StatusSection>> {
        Some(Box::new(self.inlet.stats.status("ros2", &self.entity.key, &self.entity.shared)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn twists_become_control_strings_and_bad_bytes_are_reasons() {
        let t = Twist { linear: [0.3, 0.0, 0.0], angular: [0.0, 0.0, -0.5] }.encode();
        assert_eq!(decode(MessageType::Twist, &t, None), Ok(Value::Command("VEL 0.3 -0.5".into())));
        assert!(decode(MessageType::Twist, &t[..20], None).is_err());
        assert!(decode(MessageType::Twist, &t, Some(&[1, 2, 3])).is_err());
        let scan = LaserScan { range_max: 4.0, ranges: vec![1.0, f32::INFINITY], ..LaserScan::default() };
        assert_eq!(decode(MessageType::LaserScan, &scan.encode(), None), Ok(Value::Vector(vec![1.0, 4.0])));
    }
}
