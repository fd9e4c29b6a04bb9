//! Obstacle avoider (subsumption layer, default priority 3).
//!
//! Reads a range scan whose rays are spread evenly from -fov/2 (right) to
//! +fov/2 (left) of the heading. While an obstacle inside the front cone is
//! nearer than `threshold`, it emits `VEL <creep> <turn>` on every tick,
//! turning toward the freer side. Otherwise it stays silent: silence tells the
//! arbiter this behaviour is not active, so a lower layer drives.

use subsume_guest::{Component, Description, ParamKind, Params, Value, ValueKind, emit, input, output, param};

struct Avoider {
    threshold: f64,
    fov: f64,
    cone: f64,
    turn_rate: f64,
    creep_speed: f64,
    ranges: Vec<f64>,
}

impl Component for Avoider {
    fn describe() -> Description {
        Description::new("avoider", "Turns away from obstacles nearer than a threshold")
            .input(input("ranges", ValueKind::Vector, "ranges in metres, rays from -fov/2 (right) to +fov/2 (left)"))
            .output(output("cmd", ValueKind::Command, "VEL commands while an obstacle is near; silent otherwise"))
            .param(param(
                "threshold",
                ParamKind::Number,
                "0.5",
                "an obstacle nearer than this (metres) triggers avoidance",
            ))
            .param(param("fov", ParamKind::Number, "3.14159", "angle covered by the scan, radians"))
            .param(param("cone", ParamKind::Number, "1.6", "width of the front cone that is watched, radians"))
            .param(param("turn-rate", ParamKind::Number, "1.2", "turn rate while avoiding, rad/s"))
            .param(param("creep-speed", ParamKind::Number, "0.0", "forward speed while avoiding, m/s"))
            .priority(3)
    }

    fn init(params: &Params) -> Result<Self, String> {
        let avoider = Avoider {
            threshold: params.number("threshold")?,
            fov: params.number("fov")?,
            cone: params.number("cone")?,
            turn_rate: params.number("turn-rate")?,
            creep_speed: params.number("creep-speed")?,
            ranges: Vec::new(),
        };
        if avoider.threshold <= 0.0 || avoider.fov <= 0.0 || avoider.cone <= 0.0 {
            return Err("threshold, fov and cone must be positive".into());
        }
        Ok(avoider)
    }

    fn on_input(&mut self, _port: u32, value: Value) -> Result<(), String> {
        match value {
            Value::Vector(ranges) => {
                self.ranges = ranges;
                Ok(())
            }
            _ => Err("ranges: expected a vector".into()),
        }
    }

    fn tick(&mut self, _now_ns: u64) -> Result<(), String> {
        let n = self.ranges.len();
        if n == 0 {
            return Ok(());
        }
        let step = if n > 1 { self.fov / (n - 1) as f64 } else { 0.0 };
        let (mut near, mut left, mut right) = (false, 0.0, 0.0);
        for (i, &r) in self.ranges.iter().enumerate() {
            let angle = -self.fov / 2.0 + step * i as f64;
            if angle.abs() <= self.cone / 2.0 && r < self.threshold {
                near = true;
            }
            if angle > 0.0 {
                left += r
            } else if angle < 0.0 {
                right += r
            }
        }
        if near {
            let turn = if left >= right { self.turn_rate } else { -self.turn_rate };
            let cmd = format!("VEL {:.3} {:.3}", self.creep_speed, turn);
            emit(0, &Value::Command(cmd));
        }
        Ok(())
    }
}

subsume_guest::component!(Avoider);
