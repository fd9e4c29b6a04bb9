//! `builtin:publish`: emits a fixed value of a given kind on every tick (a
//! set-point, a test signal, a stand-in for a sensor that is not wired).

use super::{BuildContext, Builtin, BuiltinError, ParamDecl, ParamType, Params, Ports, port};
use crate::config::ParamProblem;
use crate::contract::{Value, ValueKind, clip};
use crate::runtime::{CallError, Component, Outbox};

/// The kinds `publish` can emit (every kind but `any`).
pub const KINDS: &[&str] = &["flag", "scalar", "vector", "text", "command", "bytes"];

const PARAMS: &[ParamDecl] = &[
    ParamDecl {
        name: "kind",
        ty: ParamType::Choice(KINDS),
        default: "scalar",
        unit: "",
        doc: "kind of the value: flag, scalar, vector, text, command or bytes",
    },
    ParamDecl {
        name: "value",
        ty: ParamType::Text,
        default: "0",
        unit: "",
        doc: "the value: 'true', '1.5', '1 2 3', text, a control string, or hex bytes",
    },
];

/// The `publish` kind.
pub struct Publish;

fn kind_of(params: &Params) -> ValueKind {
    params.text("kind").ok().and_then(ValueKind::parse).unwrap_or(ValueKind::Scalar)
}

impl Builtin for Publish {
    fn kind(&self) -> &'static str {
        "publish"
    }

    fn summary(&self) -> &'static str {
        "Emits a fixed value on every tick"
    }

    fn params(&self) -> &'static [ParamDecl] {
        PARAMS
    }

    fn check(&self, params: &Params, _ctx: &mut super::CheckContext<'_>) -> Vec<ParamProblem> {
        let value = params.verbatim("value").unwrap_or_default();
        match parse_value(kind_of(params), value) {
            Ok(_) => Vec::new(),
            Err(why) => vec![ParamProblem::new("value", why)],
        }
    }

    fn ports(&self, params: &Params) -> Ports {
        Ports { inputs: vec![], outputs: vec![port("out", kind_of(params), "the value, once per tick")] }
    }

    fn build(&self, params: &Params, _ctx: &mut BuildContext<'_>) -> Result<Box<dyn Component>, BuiltinError> {
        let value = parse_value(kind_of(params), params.verbatim("value")?)
            .map_err(|why| BuiltinError::Param { name: "value".into(), why })?;
        Ok(Box::new(Publisher { value }))
    }
}

struct Publisher {
    value: Value,
}

impl Component for Publisher {
    fn tick(&mut self, _now_ns: u64, out: &mut Outbox) -> Result<(), CallError> {
        out.push((0, self.value.clone()));
        Ok(())
    }
}

/// Parses the text form of a value of `kind`; the error completes
/// "parameter 'value' ...".
fn parse_value(kind: ValueKind, text: &str) -> Result<Value, String> {
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
            .ok_or_else(|| format!("expects numbers separated by spaces or commas, got '{}'", clip(text))),
        ValueKind::Text => Ok(Value::Text(text.to_string())),
        ValueKind::Command => Ok(Value::Command(trimmed.into())),
        ValueKind::Bytes => hex::decode(trimmed.replace(' ', ""))
            .map(Value::Bytes)
            .map_err(|_| format!("expects hex bytes like '0a ff', got '{}'", clip(text))),
        ValueKind::Any => Err("a value needs a concrete kind".into()),
        ValueKind::Scan => Err("a scan is not written as a parameter".into()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn values_parse_from_their_text_form() {
        assert_eq!(parse_value(ValueKind::Vector, "1, 2 3"), Ok(Value::Vector(vec![1.0, 2.0, 3.0])));
        assert_eq!(parse_value(ValueKind::Bytes, "0a ff"), Ok(Value::Bytes(vec![10, 255])));
        assert_eq!(parse_value(ValueKind::Flag, "true"), Ok(Value::Flag(true)));
        assert!(parse_value(ValueKind::Scalar, "nan").is_err());
        assert!(parse_value(ValueKind::Vector, "1 x").is_err());
    }

    #[test]
    fn publish_takes_its_output_kind_from_its_params() {
        let params = Params::from_pairs(PARAMS, &[("kind", "vector"), ("value", "1 2")]).unwrap_or_default();
        assert_eq!(Publish.ports(&params).outputs[0].kind, ValueKind::Vector);
        assert!(Params::from_pairs(PARAMS, &[("kind", "any")]).is_err());
    }
}
