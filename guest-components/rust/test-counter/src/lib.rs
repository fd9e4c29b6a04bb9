//! Test guest: emits `start`, `start + step`, ... on `count`, one per tick.

use subsume_guest::{Component, Description, ParamKind, Params, Value, ValueKind, emit, output, param};

struct Counter {
    next: f64,
    step: f64,
}

impl Component for Counter {
    fn describe() -> Description {
        Description::new("test-counter", "Emits an increasing number on every tick")
            .output(output("count", ValueKind::Scalar, "start, start + step, ..."))
            .param(param("start", ParamKind::Number, "0", "first value"))
            .param(param("step", ParamKind::Number, "1", "increment per tick"))
    }
    fn init(params: &Params) -> Result<Self, String> {
        Ok(Counter { next: params.number("start")?, step: params.number("step")? })
    }
    fn tick(&mut self, _now_ns: u64) -> Result<(), String> {
        emit(0, &Value::Scalar(self.next));
        self.next += self.step;
        Ok(())
    }
}

subsume_guest::component!(Counter);
