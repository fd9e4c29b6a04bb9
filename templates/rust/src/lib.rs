//! {{name}}: a subsume robot component, made by `subsume new`.
//!
//! A starting point that already drives a robot: while something in the
//! middle third of the range scan is nearer than `threshold`, it emits
//! `VEL <creep-speed> <turn>` on every tick, turning toward the side with
//! more room; otherwise it stays silent, and a lower-priority source drives.
//! Its ports and parameters match the demo's obstacle avoider, so it can
//! take that one's place in subsume's config/demo.xml.

use subsume_guest::{Component, Description, LogLevel, ParamKind, Params, Value, ValueKind, emit, input, log, output, param};

struct App {
    threshold: f64,
    turn_rate: f64,
    creep_speed: f64,
    ranges: Vec<f64>,
}

impl Component for App {
    /// Declared once: the host reads it before `init` to check the wiring.
    fn describe() -> Description {
        Description::new("{{name}}", "Turns away from what is close in front")
            .input(input("ranges", ValueKind::Vector, "ranges in metres, rays from right to left"))
            .output(output("cmd", ValueKind::Command, "VEL commands while something is close; silent otherwise"))
            .param(param("threshold", ParamKind::Number, "0.5", "nearer than this in front (metres) is too close"))
            .param(param("turn-rate", ParamKind::Number, "1.2", "turn rate while turning away, rad/s"))
            .param(param("creep-speed", ParamKind::Number, "0.0", "forward speed while turning away, m/s"))
            .priority(3)
    }

    fn init(params: &Params) -> Result<Self, String> {
        let app = App {
            threshold: params.number("threshold")?,
            turn_rate: params.number("turn-rate")?,
            creep_speed: params.number("creep-speed")?,
            ranges: Vec::new(),
        };
        log(LogLevel::Info, &format!("ready: turning away from anything nearer than {} m", app.threshold));
        Ok(app)
    }

    fn on_input(&mut self, _port: u32, value: Value) -> Result<(), String> {
        if let Value::Vector(ranges) = value {
            self.ranges = ranges;
        }
        Ok(())
    }

    fn tick(&mut self, _now_ns: u64) -> Result<(), String> {
        let third = self.ranges.len() / 3;
        let (right, rest) = self.ranges.split_at(third);
        let (front, left) = rest.split_at(rest.len() - third);
        let nearest = |rays: &[f64]| rays.iter().copied().fold(f64::INFINITY, f64::min);
        if nearest(front) < self.threshold {
            let turn = if nearest(left) >= nearest(right) { self.turn_rate } else { -self.turn_rate };
            emit(0, &Value::Command(format!("VEL {:.3} {:.3}", self.creep_speed, turn)));
        }
        Ok(())
    }
}

subsume_guest::component!(App);
