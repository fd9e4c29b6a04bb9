//! Value kinds: the kind of a value, kind names, which port carries which
//! value. Pure over the contract's value types (no wasmtime of its own), so
//! the fuzz target of the Zenoh wire format compiles it (fuzz/).

use std::fmt;

use super::{Value, ValueKind};

/// The kind of `value`.
pub fn kind_of(value: &Value) -> ValueKind {
    match value {
        Value::Flag(_) => ValueKind::Flag,
        Value::Scalar(_) => ValueKind::Scalar,
        Value::Vector(_) => ValueKind::Vector,
        Value::Text(_) => ValueKind::Text,
        Value::Command(_) => ValueKind::Command,
        Value::Bytes(_) => ValueKind::Bytes,
        Value::Scan(_) => ValueKind::Scan,
    }
}

impl ValueKind {
    /// The name used in WIT, XML and messages.
    pub fn name(self) -> &'static str {
        match self {
            ValueKind::Flag => "flag",
            ValueKind::Scalar => "scalar",
            ValueKind::Vector => "vector",
            ValueKind::Text => "text",
            ValueKind::Command => "command",
            ValueKind::Bytes => "bytes",
            ValueKind::Any => "any",
            ValueKind::Scan => "scan",
        }
    }

    /// Parses a kind name as written in XML or WIT.
    pub fn parse(name: &str) -> Option<ValueKind> {
        Some(match name {
            "flag" => ValueKind::Flag,
            "scalar" => ValueKind::Scalar,
            "vector" => ValueKind::Vector,
            "text" => ValueKind::Text,
            "command" => ValueKind::Command,
            "bytes" => ValueKind::Bytes,
            "any" => ValueKind::Any,
            "scan" => ValueKind::Scan,
            _ => return None,
        })
    }

    /// Whether a port of this kind may carry `value`.
    pub fn accepts(self, value: &Value) -> bool {
        self == ValueKind::Any || self == kind_of(value)
    }

    /// Whether an output of kind `self` may feed an input of kind `input`.
    /// A scan may feed a vector input, which receives the ranges.
    pub fn can_feed(self, input: ValueKind) -> bool {
        input == ValueKind::Any || input == self || (self == ValueKind::Scan && input == ValueKind::Vector)
    }
}

impl fmt::Display for ValueKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}
