//! Homing (the lab's reset by driving, docs/lab.md): drives the robot back
//! to a start pose. On every tick with a known pose it steers toward
//! (`goal-x`, `goal-y`) as the planner does; once within `tolerance` it
//! turns in place to `goal-heading`; once within `heading-tolerance` too it
//! commands `STOP` and holds still. Put the avoider above it in the
//! arbiter, as the demo puts it above the planner: near an obstacle the
//! avoider takes over (config/demo-reset.xml).
//!
//! It leaves the position only when it is 1.5 times `tolerance` away, so a
//! robot that turns in place and drifts a little does not start over.

use std::f64::consts::PI;

use subsume_guest::{
    Component, Description, LogLevel, ParamKind, Params, Value, ValueKind, emit, input, log, output, param,
};

/// Decimals of the speeds in `VEL` commands.
const DECIMALS: usize = 3;

/// Where the homing is.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Phase {
    /// Driving to the position.
    Drive,
    /// At the position, turning to the heading.
    Turn,
    /// At the pose: holding still.
    Home,
}

struct Homing {
    goal: (f64, f64, f64),
    tolerance: f64,
    heading_tolerance: f64,
    max_speed: f64,
    max_turn: f64,
    heading_gain: f64,
    pose: Option<(f64, f64, f64)>,
    phase: Phase,
}

/// `angle` in (-pi, pi].
fn wrap(angle: f64) -> f64 {
    let wrapped = angle.rem_euclid(2.0 * PI);
    if wrapped > PI { wrapped - 2.0 * PI } else { wrapped }
}

impl Homing {
    /// The phase at `pose` after `phase`: the position is reached within
    /// `tolerance` and left beyond 1.5 times it; the heading likewise.
    fn next_phase(&self, (x, y, heading): (f64, f64, f64)) -> Phase {
        let distance = (self.goal.0 - x).hypot(self.goal.1 - y);
        let heading_error = wrap(self.goal.2 - heading).abs();
        let (near, far) = (self.tolerance, 1.5 * self.tolerance);
        let (aligned, astray) = (self.heading_tolerance, 1.5 * self.heading_tolerance);
        match self.phase {
            Phase::Drive if distance > near => Phase::Drive,
            _ if distance > far => Phase::Drive,
            Phase::Home if heading_error <= astray => Phase::Home,
            _ if heading_error <= aligned => Phase::Home,
            _ => Phase::Turn,
        }
    }

    fn command(&self, (x, y, heading): (f64, f64, f64)) -> String {
        let vel = |speed: f64, turn: f64| format!("VEL {speed:.prec$} {turn:.prec$}", prec = DECIMALS);
        match self.phase {
            Phase::Home => "STOP".into(),
            Phase::Turn => {
                let error = wrap(self.goal.2 - heading);
                vel(0.0, (self.heading_gain * error).clamp(-self.max_turn, self.max_turn))
            }
            Phase::Drive => {
                let (dx, dy) = (self.goal.0 - x, self.goal.1 - y);
                let distance = dx.hypot(dy);
                let error = wrap(dy.atan2(dx) - heading);
                let turn = (self.heading_gain * error).clamp(-self.max_turn, self.max_turn);
                let speed = self.max_speed * error.cos().max(0.0) * (distance / 0.5).min(1.0);
                vel(speed, turn)
            }
        }
    }
}

impl Component for Homing {
    fn describe() -> Description {
        Description::new("homing", "Drives the robot back to a start pose (position, then heading)")
            .input(input("pose", ValueKind::Vector, "robot pose [x m, y m, heading rad]"))
            .output(output("cmd", ValueKind::Command, "VEL toward the pose, STOP at it"))
            .output(output("distance", ValueKind::Scalar, "distance left to the position, metres"))
            .param(param("goal-x", ParamKind::Number, "0.0", "start x, metres"))
            .param(param("goal-y", ParamKind::Number, "0.0", "start y, metres"))
            .param(param("goal-heading", ParamKind::Number, "0.0", "start heading, radians"))
            .param(param("tolerance", ParamKind::Number, "0.1", "distance that counts as at the position, metres"))
            .param(param(
                "heading-tolerance",
                ParamKind::Number,
                "0.1",
                "heading error that counts as aligned, radians",
            ))
            .param(param("max-speed", ParamKind::Number, "0.3", "top forward speed, m/s"))
            .param(param("max-turn", ParamKind::Number, "1.0", "top turn rate, rad/s"))
            .param(param("heading-gain", ParamKind::Number, "2.0", "turn rate per radian of heading error"))
            .priority(1)
    }

    fn init(params: &Params) -> Result<Self, String> {
        let homing = Homing {
            goal: (params.number("goal-x")?, params.number("goal-y")?, params.number("goal-heading")?),
            tolerance: params.number("tolerance")?,
            heading_tolerance: params.number("heading-tolerance")?,
            max_speed: params.number("max-speed")?,
            max_turn: params.number("max-turn")?,
            heading_gain: params.number("heading-gain")?,
            pose: None,
            phase: Phase::Drive,
        };
        if homing.max_speed < 0.0 || homing.max_turn < 0.0 {
            return Err("max-speed and max-turn must not be negative".into());
        }
        if homing.tolerance <= 0.0 || homing.heading_tolerance <= 0.0 {
            return Err("tolerance and heading-tolerance must be positive".into());
        }
        Ok(homing)
    }

    fn on_input(&mut self, port: u32, value: Value) -> Result<(), String> {
        match (port, value) {
            (0, Value::Vector(v)) if v.len() >= 3 => self.pose = Some((v[0], v[1], v[2])),
            _ => return Err("pose: expected a vector [x, y, heading]".into()),
        }
        Ok(())
    }

    fn tick(&mut self, _now_ns: u64) -> Result<(), String> {
        let Some(pose) = self.pose else {
            return Ok(());
        };
        let phase = self.next_phase(pose);
        if phase != self.phase && phase == Phase::Home {
            log(LogLevel::Info, &format!("home at ({:.2}, {:.2}, {:.2} rad)", pose.0, pose.1, pose.2));
        }
        self.phase = phase;
        emit(1, &Value::Scalar((self.goal.0 - pose.0).hypot(self.goal.1 - pose.1)));
        emit(0, &Value::Command(self.command(pose)));
        Ok(())
    }
}

subsume_guest::component!(Homing);
