//! Declared parameters of built-ins and the typed reader over them.
//!
//! A built-in declares each parameter once, next to its code
//! ([`ParamDecl`]: name, type with bounds, default, unit, doc), the way a
//! WASM component's `describe` does. `subsume check`, portal staging,
//! activation, `subsume describe builtin:KIND` and the tables of
//! docs/config.md all read the same declaration. [`check_values`] turns
//! every bad value into a [`ParamProblem`] naming its parameter, so the
//! validator can point at the `<param>` line; nothing is clamped.
//!
//! After the check, [`Params`] reads values by name and type; a read that
//! fails means a built-in asked for a parameter it did not declare (a bug,
//! reported as [`BuiltinError::Param`], never a panic).

use std::collections::BTreeMap;
use std::net::SocketAddr;
use std::time::Duration;

use super::BuiltinError;
use crate::config::ParamProblem;
use crate::contract::{ParamKind, ParamSpec, clip};

/// One end of a number's allowed range.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Bound {
    Inclusive(f64),
    Exclusive(f64),
}

impl Bound {
    fn admits_above(self, x: f64) -> bool {
        match self {
            Bound::Inclusive(b) => x >= b,
            Bound::Exclusive(b) => x > b,
        }
    }

    fn admits_below(self, x: f64) -> bool {
        match self {
            Bound::Inclusive(b) => x <= b,
            Bound::Exclusive(b) => x < b,
        }
    }

    /// The bound's value.
    pub fn value(self) -> f64 {
        match self {
            Bound::Inclusive(b) | Bound::Exclusive(b) => b,
        }
    }
}

/// What a parameter's text must be.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum ParamType {
    /// Any text, empty included.
    Text,
    /// Text that is not empty.
    Required,
    /// One of these words.
    Choice(&'static [&'static str]),
    /// A finite decimal number within bounds.
    Number { min: Bound, max: Bound },
    /// A whole number within bounds.
    Integer { min: i64, max: i64 },
    /// An IP address and port (`127.0.0.1:7070`); empty when `optional`.
    Address { optional: bool },
    /// A file, relative to the robot file's folder; empty when `optional`.
    /// The built-in's own check reads it.
    File { optional: bool },
    /// As `File`, for a file that holds the robot's secrets (operators'
    /// tokens, a Zenoh config's credentials): it never leaves the robot. A
    /// lab server's copy of the set, and the preflight, get `stand_in` in
    /// its place: it validates, and nobody can use it.
    SecretFile { optional: bool, stand_in: &'static str },
    /// One of these words, or a file relative to the robot file's folder.
    WordOrFile(&'static [&'static str]),
}

/// One declared parameter of a built-in.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ParamDecl {
    pub name: &'static str,
    pub ty: ParamType,
    /// The value when the robot file gives none, as it would be written.
    pub default: &'static str,
    /// Unit of a number (`s`, `m`, `m/s`, `rad`, `Hz`), or empty.
    pub unit: &'static str,
    /// One line for humans.
    pub doc: &'static str,
}

impl ParamDecl {
    /// The kind a description reports for this parameter.
    pub fn kind(&self) -> ParamKind {
        match self.ty {
            ParamType::Number { .. } => ParamKind::Number,
            ParamType::Integer { .. } => ParamKind::Integer,
            _ => ParamKind::Text,
        }
    }

    /// What stands in for the file this parameter names where the robot's
    /// secrets must not go (`ParamType::SecretFile`); `None`: the file
    /// itself may travel.
    pub fn stand_in(&self) -> Option<&'static str> {
        match self.ty {
            ParamType::SecretFile { stand_in, .. } => Some(stand_in),
            _ => None,
        }
    }

    /// The file `value` names, if this parameter names files and `value`
    /// is not one of its words.
    pub fn file<'v>(&self, value: &'v str) -> Option<&'v str> {
        let value = value.trim();
        match self.ty {
            ParamType::File { .. } | ParamType::SecretFile { .. } if !value.is_empty() => Some(value),
            ParamType::WordOrFile(words) if !words.contains(&value) => Some(value),
            _ => None,
        }
    }

    /// Whether the robot file must give a value: the default fails the
    /// parameter's own check (an empty default of a required type).
    pub fn is_required(&self) -> bool {
        self.check(self.default).is_err()
    }

    /// The default as a person reads it: `required`, `default: none` (an
    /// empty default that is allowed, such as no geofence) or
    /// `default 'VALUE'`.
    pub fn default_in_words(&self) -> String {
        if self.is_required() {
            "required".into()
        } else if self.default.is_empty() {
            "default: none".into()
        } else {
            format!("default '{}'", self.default)
        }
    }

    /// The parameter as a description lists it.
    pub fn spec(&self) -> ParamSpec {
        ParamSpec {
            name: self.name.into(),
            kind: self.kind(),
            default_value: self.default.into(),
            doc: self.doc.into(),
        }
    }

    /// What the value must be, in words: `a number in (0, 10] s`.
    pub fn expected(&self) -> String {
        let unit = if self.unit.is_empty() { String::new() } else { format!(" {}", self.unit) };
        match self.ty {
            ParamType::Text => "any text".into(),
            ParamType::Required => "non-empty text".into(),
            ParamType::Choice(words) => format!("one of {}", words.join(", ")),
            ParamType::Number { min, max } => {
                let open = if matches!(min, Bound::Inclusive(_)) { '[' } else { '(' };
                let close = if matches!(max, Bound::Inclusive(_)) { ']' } else { ')' };
                format!("a number in {open}{}, {}{close}{unit}", min.value(), max.value())
            }
            ParamType::Integer { min, max } => format!("a whole number from {min} to {max}{unit}"),
            ParamType::Address { optional } => {
                format!("an address like 127.0.0.1:7070{}", if optional { ", or empty for none" } else { "" })
            }
            ParamType::File { optional } | ParamType::SecretFile { optional, .. } => {
                format!("a file relative to the robot file{}", if optional { ", or empty for none" } else { "" })
            }
            ParamType::WordOrFile(words) => format!("{} or a file relative to the robot file", words.join(", ")),
        }
    }

    /// Checks `text` against the type; the problem says what was expected.
    pub fn check(&self, text: &str) -> Result<(), ParamProblem> {
        let trimmed = text.trim();
        let ok = match self.ty {
            ParamType::Text => true,
            ParamType::Required => !trimmed.is_empty(),
            ParamType::Choice(words) => words.contains(&trimmed),
            ParamType::Number { min, max } => {
                trimmed.parse::<f64>().is_ok_and(|x| x.is_finite() && min.admits_above(x) && max.admits_below(x))
            }
            ParamType::Integer { min, max } => trimmed.parse::<i64>().is_ok_and(|x| (min..=max).contains(&x)),
            ParamType::Address { optional } => {
                (optional && trimmed.is_empty()) || trimmed.parse::<SocketAddr>().is_ok()
            }
            ParamType::File { optional } | ParamType::SecretFile { optional, .. } => optional || !trimmed.is_empty(),
            ParamType::WordOrFile(_) => !trimmed.is_empty(),
        };
        if ok {
            Ok(())
        } else {
            Err(ParamProblem::new(self.name, format!("must be {}, got '{}'", self.expected(), clip(text))))
        }
    }
}

/// Every declared parameter's value (the robot file's, or the default),
/// read by name and type.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Params {
    values: BTreeMap<String, String>,
}

/// Checks the values the robot file gives against `decls` and fills in
/// defaults. Names not declared are left to the validator (it reports them
/// with the list of declared ones); every bad value is a problem.
pub fn check_values(decls: &[ParamDecl], given: &BTreeMap<String, String>) -> Result<Params, Vec<ParamProblem>> {
    let mut problems = Vec::new();
    let mut values = BTreeMap::new();
    for decl in decls {
        let value = match given.get(decl.name) {
            Some(text) => {
                if let Err(problem) = decl.check(text) {
                    problems.push(problem);
                }
                text.clone()
            }
            None => {
                if decl.is_required() {
                    problems.push(ParamProblem::new(decl.name, format!("is required ({})", decl.doc)));
                }
                decl.default.to_string()
            }
        };
        values.insert(decl.name.to_string(), value);
    }
    if problems.is_empty() { Ok(Params { values }) } else { Err(problems) }
}

impl Params {
    /// Values as given, for tests and tools that build a built-in by hand;
    /// still checked against the declaration.
    pub fn from_pairs(decls: &[ParamDecl], pairs: &[(&str, &str)]) -> Result<Params, Vec<ParamProblem>> {
        let given = pairs.iter().map(|(k, v)| (k.to_string(), v.to_string())).collect();
        check_values(decls, &given)
    }

    fn raw(&self, name: &str) -> Result<&str, BuiltinError> {
        self.values
            .get(name)
            .map(|v| v.trim())
            .ok_or_else(|| BuiltinError::Param { name: name.to_string(), why: "is not declared".into() })
    }

    /// The text of parameter `name`, trimmed.
    pub fn text(&self, name: &str) -> Result<&str, BuiltinError> {
        self.raw(name)
    }

    /// The text of parameter `name` as written (not trimmed).
    pub fn verbatim(&self, name: &str) -> Result<&str, BuiltinError> {
        self.values
            .get(name)
            .map(String::as_str)
            .ok_or_else(|| BuiltinError::Param { name: name.to_string(), why: "is not declared".into() })
    }

    pub fn number(&self, name: &str) -> Result<f64, BuiltinError> {
        let text = self.raw(name)?;
        text.parse::<f64>()
            .ok()
            .filter(|x| x.is_finite())
            .ok_or_else(|| BuiltinError::Param { name: name.into(), why: format!("is not a number: '{}'", clip(text)) })
    }

    pub fn integer(&self, name: &str) -> Result<i64, BuiltinError> {
        let text = self.raw(name)?;
        text.parse::<i64>().map_err(|_| BuiltinError::Param {
            name: name.into(),
            why: format!("is not a whole number: '{}'", clip(text)),
        })
    }

    /// A number of seconds as a duration.
    pub fn seconds(&self, name: &str) -> Result<Duration, BuiltinError> {
        let seconds = self.number(name)?;
        Duration::try_from_secs_f64(seconds)
            .map_err(|_| BuiltinError::Param { name: name.into(), why: format!("is not a duration: {seconds}") })
    }

    /// An address, or `None` when the parameter is empty.
    pub fn address(&self, name: &str) -> Result<Option<SocketAddr>, BuiltinError> {
        let text = self.raw(name)?;
        if text.is_empty() {
            return Ok(None);
        }
        text.parse::<SocketAddr>()
            .map(Some)
            .map_err(|_| BuiltinError::Param { name: name.into(), why: format!("is not an address: '{}'", clip(text)) })
    }

    /// Every value, for a WASM translator's `init` (the link's parameters).
    pub fn pairs(&self) -> impl Iterator<Item = (&str, &str)> {
        self.values.iter().map(|(k, v)| (k.as_str(), v.as_str()))
    }
}

/// Shorthand for declaring a number in `[min, max]`.
pub const fn number_in(min: f64, max: f64) -> ParamType {
    ParamType::Number { min: Bound::Inclusive(min), max: Bound::Inclusive(max) }
}

/// Shorthand for declaring a number in `(0, max]`.
pub const fn positive_up_to(max: f64) -> ParamType {
    ParamType::Number { min: Bound::Exclusive(0.0), max: Bound::Inclusive(max) }
}

#[cfg(test)]
mod tests {
    use super::*;

    const DECLS: &[ParamDecl] = &[
        ParamDecl {
            name: "baud",
            ty: ParamType::Integer { min: 50, max: 4_000_000 },
            default: "115200",
            unit: "",
            doc: "",
        },
        ParamDecl { name: "watchdog", ty: positive_up_to(10.0), default: "0.3", unit: "s", doc: "" },
        ParamDecl { name: "mode", ty: ParamType::Choice(&["a", "b"]), default: "a", unit: "", doc: "" },
        ParamDecl { name: "at", ty: ParamType::Address { optional: true }, default: "", unit: "", doc: "" },
    ];

    #[test]
    fn every_bad_value_is_a_problem_naming_its_parameter() {
        let given: BTreeMap<String, String> = [("baud", "0"), ("watchdog", "-1"), ("mode", "c"), ("at", "nowhere")]
            .into_iter()
            .map(|(k, v)| (k.to_string(), v.to_string()))
            .collect();
        let problems = check_values(DECLS, &given).err().unwrap_or_default();
        let text: Vec<String> = problems.iter().map(ToString::to_string).collect();
        assert_eq!(
            text,
            [
                "parameter 'baud' must be a whole number from 50 to 4000000, got '0'",
                "parameter 'watchdog' must be a number in (0, 10] s, got '-1'",
                "parameter 'mode' must be one of a, b, got 'c'",
                "parameter 'at' must be an address like 127.0.0.1:7070, or empty for none, got 'nowhere'",
            ]
        );
    }

    #[test]
    fn defaults_fill_in_and_values_read_by_type() -> Result<(), BuiltinError> {
        let params = Params::from_pairs(DECLS, &[("watchdog", " 0.5 ")])
            .map_err(|p| BuiltinError::Param { name: "all".into(), why: format!("{p:?}") })?;
        assert_eq!(params.integer("baud")?, 115_200);
        assert_eq!(params.seconds("watchdog")?, Duration::from_millis(500));
        assert_eq!(params.address("at")?, None);
        assert!(params.number("nope").is_err());
        Ok(())
    }

    #[test]
    fn bounds_are_exact_at_their_edges() {
        let open = ParamDecl { name: "x", ty: positive_up_to(1.0), default: "1", unit: "", doc: "" };
        assert!(open.check("0").is_err());
        assert!(open.check("1e-9").is_ok());
        assert!(open.check("1").is_ok());
        assert!(open.check("1.000001").is_err());
        assert!(open.check("nan").is_err());
    }
}
