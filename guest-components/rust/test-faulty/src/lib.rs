//! Test guest that misbehaves on purpose, chosen by the `mode` parameter,
//! after `after` good ticks (each good tick emits the tick count on `out`):
//!
//! - `trap-on-tick`: executes `unreachable` (a Rust panic) in `tick`;
//! - `loop-on-tick`: spins forever in `tick` (must hit the time budget);
//! - `bad-port-on-tick`: emits on an output port that does not exist;
//! - `error-on-tick`: returns `err` from `tick` (not a fault: only logged);
//! - `error-on-init`: refuses to start;
//! - `none`: behaves.

use subsume_guest::{Component, Description, ParamKind, Params, Value, ValueKind, emit, output, param};

struct Faulty {
    mode: String,
    after: i64,
    ticks: i64,
}

impl Component for Faulty {
    fn describe() -> Description {
        Description::new("test-faulty", "Misbehaves on purpose, for fault-isolation tests")
            .output(output("out", ValueKind::Scalar, "number of good ticks so far"))
            .param(param("mode", ParamKind::Text, "none", "how to misbehave"))
            .param(param("after", ParamKind::Integer, "0", "good ticks before misbehaving"))
    }
    fn init(params: &Params) -> Result<Self, String> {
        let mode = params.text("mode").unwrap_or("none").to_string();
        if mode == "error-on-init" {
            return Err("refusing to start, as asked".into());
        }
        Ok(Faulty { mode, after: params.integer("after")?, ticks: 0 })
    }
    fn tick(&mut self, _now_ns: u64) -> Result<(), String> {
        if self.ticks < self.after || self.mode == "none" {
            self.ticks += 1;
            emit(0, &Value::Scalar(self.ticks as f64));
            return Ok(());
        }
        match self.mode.as_str() {
            "trap-on-tick" => std::process::abort(),
            "loop-on-tick" => {
                let mut spins: u64 = 0;
                loop {
                    spins = std::hint::black_box(spins.wrapping_add(1));
                }
            }
            "bad-port-on-tick" => {
                emit(99, &Value::Scalar(0.0));
                Ok(())
            }
            "error-on-tick" => Err(format!("failing on purpose at tick {}", self.ticks)),
            other => Err(format!("unknown mode '{other}'")),
        }
    }
}

subsume_guest::component!(Faulty);
