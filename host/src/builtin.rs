//! Native components compiled into the host, named `builtin:KIND` in the
//! robot file. They describe themselves with the same [`Description`] as
//! WASM guests and run behind the same [`Component`] trait, so the
//! scheduler does not tell them apart.
//!
//! - `builtin:log`: writes the values it receives to the host log, at most
//!   one line per `interval` seconds per input (with the count in between).
//! - `builtin:publish`: emits a fixed value of a given kind on every tick
//!   (a set-point, a test signal, a stand-in for a sensor that is not wired).

use std::collections::BTreeMap;
use std::fmt::Write as _;

use crate::contract::{Description, Param, ParamKind, ParamSpec, PortSpec, Value, ValueKind, clip};
use crate::runtime::{CallError, Component, Outbox};

/// The built-in kinds, for messages.
pub const KINDS: &[&str] = &["log", "publish"];

/// Longest vector shown in a log line; the rest is summarised.
pub const LOG_MAX_ELEMENTS: usize = 8;

/// The description of built-in `kind`, shaped by its XML `params` where the
/// kind needs it (`publish` takes its output kind from `kind`).
pub fn describe(kind: &str, params: &BTreeMap<String, String>) -> Result<Description, String> {
    match kind {
        "log" => Ok(Description {
            name: "log".into(),
            version: env!("CARGO_PKG_VERSION").into(),
            summary: "Writes received values to the host log".into(),
            inputs: vec![port("in", ValueKind::Any, "any value; logged")],
            outputs: Vec::new(),
            params: vec![param(
                "interval",
                ParamKind::Number,
                "1.0",
                "least seconds between two log lines per input",
            )],
            default_priority: None,
        }),
        "publish" => {
            let kind_name = params.get("kind").map_or("scalar", |k| k.trim());
            let value_kind = match ValueKind::parse(kind_name) {
                Some(ValueKind::Any) | None => {
                    return Err(format!(
                        "builtin:publish: unknown kind '{}' (expected flag, scalar, vector, text, command or bytes)",
                        clip(kind_name)
                    ));
                }
                Some(k) => k,
            };
            if let Some(text) = params.get("value") {
                parse_value(value_kind, text)
                    .map_err(|why| format!("builtin:publish: parameter 'value' {why}"))?;
            }
            Ok(Description {
                name: "publish".into(),
                version: env!("CARGO_PKG_VERSION").into(),
                summary: "Emits a fixed value on every tick".into(),
                inputs: Vec::new(),
                outputs: vec![port("out", value_kind, "the value, once per tick")],
                params: vec![
                    param(
                        "kind",
                        ParamKind::Text,
                        "scalar",
                        "kind of the value: flag, scalar, vector, text, command or bytes",
                    ),
                    param(
                        "value",
                        ParamKind::Text,
                        "0",
                        "the value: 'true', '1.5', '1 2 3', text, a control string, or hex bytes",
                    ),
                ],
                default_priority: None,
            })
        }
        other => Err(format!(
            "unknown built-in '{}' (known: {})",
            clip(other),
            KINDS.join(", ")
        )),
    }
}

/// A running built-in of `kind` named `name`, from its complete parameters.
pub fn instantiate(
    kind: &str,
    name: &str,
    description: &Description,
    params: &[Param],
) -> Result<Box<dyn Component>, String> {
    let get = |key: &str| {
        params
            .iter()
            .find(|p| p.name == key)
            .map(|p| p.value.as_str())
    };
    match kind {
        "log" => {
            let interval = get("interval")
                .unwrap_or("1.0")
                .trim()
                .parse::<f64>()
                .map_err(|e| format!("interval: {e}"))?;
            if !(interval >= 0.0 && interval.is_finite()) {
                return Err(format!(
                    "interval must be a number of seconds >= 0, got {interval}"
                ));
            }
            let inputs = description.inputs.len();
            Ok(Box::new(LogSink {
                name: name.into(),
                interval_ns: (interval * 1e9) as u64,
                last: vec![None; inputs],
                unlogged: vec![0; inputs],
            }))
        }
        "publish" => {
            let kind = description
                .outputs
                .first()
                .map_or(ValueKind::Scalar, |p| p.kind);
            let value = parse_value(kind, get("value").unwrap_or("0"))?;
            Ok(Box::new(Publisher { value }))
        }
        other => Err(format!("unknown built-in '{}'", clip(other))),
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
        let more = if skipped > 0 {
            format!(" (+{skipped} since last line)")
        } else {
            String::new()
        };
        tracing::info!(component = %self.name, "received {}{more}", format_value(value));
        Ok(())
    }

    fn tick(&mut self, _now_ns: u64, _out: &mut Outbox) -> Result<(), CallError> {
        Ok(())
    }
}

struct Publisher {
    value: Value,
}

impl Component for Publisher {
    fn on_input(
        &mut self,
        _port: u32,
        _value: &Value,
        _now_ns: u64,
        _out: &mut Outbox,
    ) -> Result<(), CallError> {
        Ok(())
    }

    fn tick(&mut self, _now_ns: u64, out: &mut Outbox) -> Result<(), CallError> {
        out.push((0, self.value.clone()));
        Ok(())
    }
}

/// Parses the text form of a value of `kind` (as `builtin:publish` takes it).
pub fn parse_value(kind: ValueKind, text: &str) -> Result<Value, String> {
    let trimmed = text.trim();
    match kind {
        ValueKind::Flag => match trimmed {
            "true" => Ok(Value::Flag(true)),
            "false" => Ok(Value::Flag(false)),
            _ => Err(format!("expects true or false, got '{}'", clip(text))),
        },
        ValueKind::Scalar => trimmed
            .parse::<f64>()
            .ok()
            .filter(|x| x.is_finite())
            .map(Value::Scalar)
            .ok_or_else(|| format!("expects a finite number, got '{}'", clip(text))),
        ValueKind::Vector => trimmed
            .split(|c: char| c.is_whitespace() || c == ',')
            .filter(|s| !s.is_empty())
            .map(|s| s.parse::<f64>().ok().filter(|x| x.is_finite()))
            .collect::<Option<Vec<f64>>>()
            .map(Value::Vector)
            .ok_or_else(|| {
                format!(
                    "expects numbers separated by spaces or commas, got '{}'",
                    clip(text)
                )
            }),
        ValueKind::Text => Ok(Value::Text(text.to_string())),
        ValueKind::Command => Ok(Value::Command(trimmed.to_string())),
        ValueKind::Bytes => hex::decode(trimmed.replace(' ', ""))
            .map(Value::Bytes)
            .map_err(|_| format!("expects hex bytes like '0a ff', got '{}'", clip(text))),
        ValueKind::Any => Err("a value needs a concrete kind".into()),
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
        Value::Command(c) => format!("command '{}'", clip(c)),
        Value::Bytes(b) => format!("bytes ({} bytes)", b.len()),
    }
}

fn port(name: &str, kind: ValueKind, doc: &str) -> PortSpec {
    PortSpec {
        name: name.into(),
        kind,
        doc: doc.into(),
    }
}

fn param(name: &str, kind: ParamKind, default: &str, doc: &str) -> ParamSpec {
    ParamSpec {
        name: name.into(),
        kind,
        default_value: default.into(),
        doc: doc.into(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn values_parse_from_their_text_form() {
        assert_eq!(
            parse_value(ValueKind::Vector, "1, 2 3"),
            Ok(Value::Vector(vec![1.0, 2.0, 3.0]))
        );
        assert_eq!(
            parse_value(ValueKind::Bytes, "0a ff"),
            Ok(Value::Bytes(vec![10, 255]))
        );
        assert_eq!(parse_value(ValueKind::Flag, "true"), Ok(Value::Flag(true)));
        assert!(parse_value(ValueKind::Scalar, "nan").is_err());
        assert!(parse_value(ValueKind::Vector, "1 x").is_err());
    }

    #[test]
    fn publish_takes_its_output_kind_from_its_params() {
        let params = BTreeMap::from([("kind".to_string(), "vector".to_string())]);
        let d = describe("publish", &params);
        assert_eq!(d.map(|d| d.outputs[0].kind), Ok(ValueKind::Vector));
        let bad = BTreeMap::from([("kind".to_string(), "any".to_string())]);
        assert!(describe("publish", &bad).is_err());
        assert!(
            describe("nope", &BTreeMap::new()).is_err_and(|e| e.contains("known: log, publish"))
        );
    }

    #[test]
    fn publisher_emits_its_value_every_tick() -> Result<(), String> {
        let params = BTreeMap::from([("kind".to_string(), "scalar".to_string())]);
        let d = describe("publish", &params)?;
        let full = vec![
            Param {
                name: "kind".into(),
                value: "scalar".into(),
            },
            Param {
                name: "value".into(),
                value: "2.5".into(),
            },
        ];
        let mut c = instantiate("publish", "p", &d, &full)?;
        let mut out = Vec::new();
        c.tick(0, &mut out).map_err(|e| format!("{e:?}"))?;
        c.tick(1, &mut out).map_err(|e| format!("{e:?}"))?;
        assert_eq!(out, vec![(0, Value::Scalar(2.5)), (0, Value::Scalar(2.5))]);
        Ok(())
    }
}
