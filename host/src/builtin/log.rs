//! `builtin:log`: writes the values it receives to the host log, at most one
//! line per `interval` seconds per input (with the count of values in
//! between).

use std::fmt::Write as _;

use super::{BuildContext, Builtin, BuiltinError, ParamDecl, Params, Ports, number_in, port};
use crate::contract::{Value, ValueKind, clip};
use crate::runtime::{CallError, Component, Outbox};

/// Longest vector shown in a log line; the rest is summarised.
pub const LOG_MAX_ELEMENTS: usize = 8;
/// Longest `interval`: an hour between lines is as quiet as a log needs.
pub const MAX_LOG_INTERVAL_S: f64 = 3600.0;

const PARAMS: &[ParamDecl] = &[ParamDecl {
    name: "interval",
    ty: number_in(0.0, MAX_LOG_INTERVAL_S),
    default: "1.0",
    unit: "s",
    doc: "least seconds between two log lines per input",
}];

/// The `log` kind.
pub struct Log;

impl Builtin for Log {
    fn kind(&self) -> &'static str {
        "log"
    }

    fn summary(&self) -> &'static str {
        "Writes received values to the host log"
    }

    fn params(&self) -> &'static [ParamDecl] {
        PARAMS
    }

    fn ports(&self, _params: &Params) -> Ports {
        Ports { inputs: vec![port("in", ValueKind::Any, "any value; logged")], outputs: vec![] }
    }

    fn build(&self, params: &Params, ctx: &mut BuildContext<'_>) -> Result<Box<dyn Component>, BuiltinError> {
        let interval = params.seconds("interval")?;
        let config = ctx.component()?;
        let inputs = config.description.inputs.len();
        Ok(Box::new(LogSink {
            name: config.name.clone(),
            interval_ns: interval.as_nanos() as u64,
            last: vec![None; inputs],
            unlogged: vec![0; inputs],
        }))
    }
}

struct LogSink {
    name: String,
    interval_ns: u64,
    last: Vec<Option<u64>>,
    unlogged: Vec<u64>,
}

impl Component for LogSink {
    fn on_input(
        &mut self,
        port: u32,
        value: &Value,
        _from: usize,
        now_ns: u64,
        _out: &mut Outbox,
    ) -> Result<(), CallError> {
        let i = port as usize;
        let (Some(last), Some(unlogged)) = (self.last.get_mut(i), self.unlogged.get_mut(i)) else {
            return Ok(());
        };
        if last.is_some_and(|t| now_ns.saturating_sub(t) < self.interval_ns) {
            *unlogged += 1;
            return Ok(());
        }
        let skipped = std::mem::take(unlogged);
        *last = Some(now_ns);
        let more = if skipped > 0 { format!(" (+{skipped} since last line)") } else { String::new() };
        tracing::info!(component = %self.name, "received {}{more}", format_value(value));
        Ok(())
    }
}

/// A short human form of `value` for log lines.
pub fn format_value(value: &Value) -> String {
    match value {
        Value::Flag(b) => format!("flag {b}"),
        Value::Scalar(x) => format!("scalar {x:.3}"),
        Value::Vector(v) => {
            let mut s = String::from("vector [");
            for (i, x) in v.iter().take(LOG_MAX_ELEMENTS).enumerate() {
                if i > 0 {
                    s.push_str(", ");
                }
                let _ = write!(s, "{x:.3}");
            }
            if v.len() > LOG_MAX_ELEMENTS {
                let _ = write!(s, ", ... {} in all", v.len());
            }
            s.push(']');
            s
        }
        Value::Text(t) => format!("text {:?}", clip(t)),
        Value::Command(c) => format!("command '{}'", clip(&c.text())),
        Value::Bytes(b) => format!("bytes ({} bytes)", b.len()),
        Value::Scan(s) => format!(
            "scan of {} rays from {:.3} rad by {:.3} rad: {}",
            s.ranges.len(),
            s.angle_min,
            s.angle_increment,
            format_value(&Value::Vector(s.ranges.clone()))
        ),
    }
}
