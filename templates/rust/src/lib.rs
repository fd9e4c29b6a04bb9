//! {{name}}: a subsume robot component, made by `subsume new`.
//!
//! A starting point that already drives a robot: while something in the
//! front cone (`cone` radians wide, centred on the heading) is nearer than
//! `threshold`, it emits `VEL <creep-speed> <turn>` on every tick, turning
//! toward the side whose nearest reading is farther; otherwise it stays
//! silent, and a lower-priority source drives. The rays spread evenly over
//! `fov` from right to left. Its ports and parameters match the demo's
//! obstacle avoider, so it can take that one's place in subsume's
//! config/demo.xml, and passes the lab's preflight there unchanged.

use subsume_guest::{Component, Description, LogLevel, ParamKind, Params, Value, ValueKind, emit, input, log, output, param};

struct App {
    threshold: f64,
    fov: f64,
    cone: f64,
    turn_rate: f64,
    creep_speed: f64,
    ranges: Vec<f64>,
}

impl Component for App {
    /// Declared once: the host reads it before `init` to check the wiring.
    fn describe() -> Description {
        Description::new("{{name}}", "Turns away from what is close in front")
            .input(input("ranges", ValueKind::Vector, "ranges in metres, rays from -fov/2 (right) to +fov/2 (left)"))
            .output(output("cmd", ValueKind::Command, "VEL commands while something is close; silent otherwise"))
            .param(param("threshold", ParamKind::Number, "0.5", "nearer than this in front (metres) is too close"))
            .param(param("fov", ParamKind::Number, "3.14159", "angle the rays cover, radians"))
            .param(param("cone", ParamKind::Number, "1.6", "width of the watched front cone, radians"))
            .param(param("turn-rate", ParamKind::Number, "1.2", "turn rate while turning away, rad/s"))
            .param(param("creep-speed", ParamKind::Number, "0.0", "forward speed while turning away, m/s"))
            .priority(3)
    }

    fn init(params: &Params) -> Result<Self, String> {
        let app = App {
            threshold: params.number("threshold")?,
            fov: params.number("fov")?,
            cone: params.number("cone")?,
            turn_rate: params.number("turn-rate")?,
            creep_speed: params.number("creep-speed")?,
            ranges: Vec::new(),
        };
        if app.fov <= 0.0 || app.cone <= 0.0 {
            return Err("fov and cone must be positive".into()); // refuses to start
        }
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
        // Each ray's angle, counter-clockwise from ahead: evenly over fov.
        let step = if self.ranges.len() > 1 { self.fov / (self.ranges.len() - 1) as f64 } else { 0.0 };
        let rays = || self.ranges.iter().enumerate().map(|(i, &r)| (-self.fov / 2.0 + step * i as f64, r));
        let nearest = |side: fn(f64, f64) -> bool| {
            rays().filter(|&(a, _)| side(a, self.cone)).map(|(_, r)| r).fold(f64::INFINITY, f64::min)
        };
        if nearest(|a, cone| a.abs() <= cone / 2.0) < self.threshold {
            let (left, right) = (nearest(|a, _| a > 0.0), nearest(|a, _| a < 0.0));
            let turn = if left >= right { self.turn_rate } else { -self.turn_rate };
            emit(0, &Value::Command(format!("VEL {:.3} {:.3}", self.creep_speed, turn)));
        }
        Ok(())
    }
}

subsume_guest::component!(App);
