// The planner's code, shared by `planner` and `test-planner-v2` (which
// include it after defining NAME, SUMMARY and DECIMALS).

use subsume_guest::{
    Component, Description, LogLevel, ParamKind, Params, Value, ValueKind, emit, input, log, output, param,
};

struct Planner {
    goal: (f64, f64),
    max_speed: f64,
    max_turn: f64,
    tolerance: f64,
    heading_gain: f64,
    pose: Option<(f64, f64, f64)>,
    reached: bool,
}

impl Component for Planner {
    fn describe() -> Description {
        Description::new(NAME, SUMMARY)
            .input(input("pose", ValueKind::Vector, "robot pose [x m, y m, heading rad]"))
            .input(input("goal", ValueKind::Vector, "new goal [x m, y m]"))
            .output(output("cmd", ValueKind::Command, "VEL toward the goal, STOP at it"))
            .output(output("distance", ValueKind::Scalar, "distance left to the goal, metres"))
            .param(param("goal-x", ParamKind::Number, "0.0", "goal x, metres"))
            .param(param("goal-y", ParamKind::Number, "0.0", "goal y, metres"))
            .param(param("max-speed", ParamKind::Number, "0.3", "top forward speed, m/s"))
            .param(param("max-turn", ParamKind::Number, "1.0", "top turn rate, rad/s"))
            .param(param(
                "tolerance",
                ParamKind::Number,
                "0.15",
                "distance at which the goal counts as reached, metres",
            ))
            .param(param("heading-gain", ParamKind::Number, "2.0", "turn rate per radian of heading error"))
            .priority(1)
    }

    fn init(params: &Params) -> Result<Self, String> {
        let planner = Planner {
            goal: (params.number("goal-x")?, params.number("goal-y")?),
            max_speed: params.number("max-speed")?,
            max_turn: params.number("max-turn")?,
            tolerance: params.number("tolerance")?,
            heading_gain: params.number("heading-gain")?,
            pose: None,
            reached: false,
        };
        if planner.max_speed < 0.0 || planner.max_turn < 0.0 || planner.tolerance <= 0.0 {
            return Err("max-speed and max-turn must not be negative, tolerance must be positive".into());
        }
        Ok(planner)
    }

    fn on_input(&mut self, port: u32, value: Value) -> Result<(), String> {
        match (port, value) {
            (0, Value::Vector(v)) if v.len() >= 3 => self.pose = Some((v[0], v[1], v[2])),
            (1, Value::Vector(v)) if v.len() >= 2 => {
                self.goal = (v[0], v[1]);
                self.reached = false;
                log(LogLevel::Info, &format!("new goal ({:.2}, {:.2})", v[0], v[1]));
            }
            (0, _) => return Err("pose: expected a vector [x, y, heading]".into()),
            _ => return Err("goal: expected a vector [x, y]".into()),
        }
        Ok(())
    }

    fn tick(&mut self, _now_ns: u64) -> Result<(), String> {
        let Some((x, y, heading)) = self.pose else {
            return Ok(());
        };
        let (dx, dy) = (self.goal.0 - x, self.goal.1 - y);
        let distance = dx.hypot(dy);
        emit(1, &Value::Scalar(distance));
        if distance <= self.tolerance {
            if !self.reached {
                self.reached = true;
                log(LogLevel::Info, &format!("goal reached at ({x:.2}, {y:.2})"));
            }
            emit(0, &Value::Command("STOP".into()));
            return Ok(());
        }
        let mut error = dy.atan2(dx) - heading;
        while error > std::f64::consts::PI {
            error -= 2.0 * std::f64::consts::PI;
        }
        while error < -std::f64::consts::PI {
            error += 2.0 * std::f64::consts::PI;
        }
        let turn = (self.heading_gain * error).clamp(-self.max_turn, self.max_turn);
        let speed = self.max_speed * error.cos().max(0.0) * (distance / 0.5).min(1.0);
        emit(0, &Value::Command(format!("VEL {speed:.prec$} {turn:.prec$}", prec = DECIMALS)));
        Ok(())
    }
}

subsume_guest::component!(Planner);
