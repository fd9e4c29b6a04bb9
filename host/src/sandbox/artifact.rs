//! What loading makes of a component's bytes: a compiled component or
//! translator pre-linked against the world of the contract version it was
//! built against ([`Contract`]), with its description.

use super::guest::GuestState;
use crate::contract::{Description, bindings, translator_bindings, v1};

/// A compiled, linked component and what it says about itself.
pub struct WasmArtifact {
    /// Hex sha256 of the `.wasm` bytes.
    pub sha256: String,
    pub description: Description,
    /// The contract version the component was built against.
    pub contract: Contract,
    pub(super) pre: ComponentPre,
}

/// A version of the WIT contract `subsume:robot`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Contract {
    /// `subsume:robot@0.1.0` (`wit/0.1.0/robot.wit`).
    V0_1,
    /// `subsume:robot@0.2.0` (`wit/robot.wit`).
    V0_2,
}

impl Contract {
    pub fn name(self) -> &'static str {
        match self {
            Contract::V0_1 => "0.1.0",
            Contract::V0_2 => "0.2.0",
        }
    }
}

/// A component pre-linked against the world of its contract version.
pub(super) enum ComponentPre {
    V2(bindings::ComponentPre<GuestState>),
    V1(v1::bindings::ComponentPre<GuestState>),
}

/// A translator pre-linked against the world of its contract version.
pub(super) enum TranslatorPre {
    V2(translator_bindings::TranslatorPre<GuestState>),
    V1(v1::translator_bindings::TranslatorPre<GuestState>),
}

impl std::fmt::Debug for WasmArtifact {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("WasmArtifact").field("sha256", &self.sha256).field("name", &self.description.name).finish()
    }
}

/// A compiled, linked translator component.
pub struct TranslatorArtifact {
    pub sha256: String,
    /// The contract version the translator was built against.
    pub contract: Contract,
    pub(super) pre: TranslatorPre,
}

impl std::fmt::Debug for TranslatorArtifact {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("TranslatorArtifact").field("sha256", &self.sha256).finish()
    }
}
