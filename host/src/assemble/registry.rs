//! The one list of built-ins: `builtin:KIND` -> its [`Builtin`]. Adding a
//! built-in is its own module plus one line here. The only maker of a
//! [`BuiltinKind`] (the architecture test checks it): code elsewhere asks
//! the kind's built-in what it is, never compares its name.

use crate::arbiter::ArbiterBuiltin;
use crate::bridge::ports::{ZenohPublish, ZenohSession, ZenohSubscribe};
use crate::bridge::ros2_ports::{Ros2Publish, Ros2Subscribe};
use crate::builtin::Builtin;
use crate::builtin::log::Log;
use crate::builtin::publish::Publish;
use crate::camera::CameraBuiltin;
use crate::config::BuiltinKind;
use crate::envelope::EnvelopeBuiltin;
use crate::robot::builtin::SerialBuiltin;
use crate::sim::builtin::SimBuiltin;
use crate::teleop::builtin::TeleopBuiltin;

/// Every built-in, in alphabetical order of kind.
pub const BUILTINS: &[&dyn Builtin] = &[
    &ArbiterBuiltin,
    &CameraBuiltin,
    &EnvelopeBuiltin,
    &Log,
    &Publish,
    &Ros2Publish,
    &Ros2Subscribe,
    &SerialBuiltin,
    &SimBuiltin,
    &TeleopBuiltin,
    &ZenohSession,
    &ZenohPublish,
    &ZenohSubscribe,
];

/// The built-in of `kind`, by the name the robot file writes.
pub fn find(kind: &str) -> Option<&'static dyn Builtin> {
    BUILTINS.iter().copied().find(|b| b.kind() == kind)
}

/// The kind the robot file's `builtin:NAME` names, if a built-in has it.
pub fn kind(name: &str) -> Option<BuiltinKind> {
    BUILTINS.iter().position(|b| b.kind() == name).map(|index| BuiltinKind::registered(index, BUILTINS[index].kind()))
}

/// The kind of `builtin` (one of [`BUILTINS`]).
pub fn kind_of(builtin: &dyn Builtin) -> Option<BuiltinKind> {
    kind(builtin.kind())
}

/// The built-in of `kind`. Every kind comes from this list, so there is
/// always one.
pub fn builtin(kind: BuiltinKind) -> &'static dyn Builtin {
    BUILTINS[kind.index()]
}

/// Every kind, for messages.
pub fn kinds() -> Vec<&'static str> {
    BUILTINS.iter().map(|b| b.kind()).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_kind_names_its_own_builtin() {
        for b in BUILTINS {
            let kind = kind(b.kind()).unwrap();
            assert_eq!(builtin(kind).kind(), b.kind());
            assert_eq!(kind.name(), b.kind());
            assert_eq!(kind_of(*b), Some(kind));
        }
        assert!(kind("no-such-kind").is_none());
    }

    #[test]
    fn kinds_are_unique_sorted_and_their_defaults_pass_their_own_checks() {
        let kinds = kinds();
        let mut sorted = kinds.clone();
        sorted.sort_unstable();
        sorted.dedup();
        assert_eq!(kinds, sorted);
        for builtin in BUILTINS {
            for decl in builtin.params() {
                // A default that fails its check marks a required parameter:
                // only an empty default of a required type may.
                if decl.is_required() {
                    let required = matches!(
                        decl.ty,
                        crate::builtin::ParamType::Required
                            | crate::builtin::ParamType::File { optional: false }
                            | crate::builtin::ParamType::SecretFile { optional: false, .. }
                    );
                    assert!(required && decl.default.is_empty(), "builtin:{} {}", builtin.kind(), decl.name);
                }
                assert!(crate::contract::is_valid_name(decl.name), "{}", decl.name);
            }
        }
    }
}
