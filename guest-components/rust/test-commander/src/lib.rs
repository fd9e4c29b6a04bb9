//! Test guest: a motion source that emits `command` on each of its first
//! `ticks` ticks, then falls silent (so the arbiter's timeout and the serial
//! link's watchdog can be tested end to end).

use subsume_guest::{Component, Description, ParamKind, Params, Value, ValueKind, emit, output, param};

struct Commander {
    command: String,
    ticks_left: i64,
}

impl Component for Commander {
    fn describe() -> Description {
        Description::new("test-commander", "Emits a control string for a number of ticks, then nothing")
            .output(output("cmd", ValueKind::Command, "the command, while it lasts"))
            .param(param("command", ParamKind::Text, "VEL 0.2 0", "the control string to emit"))
            .param(param("ticks", ParamKind::Integer, "10", "how many ticks to emit it on"))
            .priority(1)
    }
    fn init(params: &Params) -> Result<Self, String> {
        Ok(Commander {
            command: params.text("command").unwrap_or("STOP").to_string(),
            ticks_left: params.integer("ticks")?,
        })
    }
    fn tick(&mut self, _now_ns: u64) -> Result<(), String> {
        if self.ticks_left > 0 {
            self.ticks_left -= 1;
            emit(0, &Value::Command(self.command.clone()));
        }
        Ok(())
    }
}

subsume_guest::component!(Commander);
