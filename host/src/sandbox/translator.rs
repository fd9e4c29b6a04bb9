//! A running WASM translator (the `translator` world): encode and decode
//! under the link's time budget; once it breaks it is never called again.

use std::time::Duration;

use thiserror::Error;
use wasmtime::Store;

use super::SandboxError;
use super::guest::{GuestState, MAX_GUEST_MESSAGE_BYTES, call_error, truncate};
use crate::contract::bindings::subsume::robot::types::Feedback as WitFeedback;
use crate::contract::translator_bindings;

/// Most bytes one `encode` may return: a motor frame is a few dozen bytes.
pub const MAX_TRANSLATED_FRAME_BYTES: usize = 1024;
/// Most feedback messages one `decode` may return.
pub const MAX_FEEDBACK_PER_DECODE: usize = 1024;

/// A running WASM translator (the `translator` world).
pub struct WasmTranslator {
    pub(super) store: Store<GuestState>,
    pub(super) instance: translator_bindings::Translator,
    pub(super) budget: Duration,
    pub(super) budget_ticks: u64,
    pub(super) malformed: u64,
    /// Why it broke, once it has: it is never called again.
    pub(super) broken: Option<String>,
}

impl WasmTranslator {
    fn check(&self) -> Result<(), String> {
        self.broken.clone().map_or(Ok(()), Err)
    }

    fn break_with(&mut self, call: &'static str, err: &wasmtime::Error) -> String {
        let reason = match call_error(call, self.budget, err) {
            SandboxError::Call { reason, .. } => format!("{call}: {reason}"),
            other => other.to_string(),
        };
        self.broken = Some(reason.clone());
        reason
    }
}

/// Why a translator call gave no result.
#[derive(Clone, Debug, PartialEq, Eq, Error)]
pub enum TranslatorCallError {
    /// `encode` returned `err`: the hardware cannot carry the command.
    #[error("{0}")]
    Refused(String),
    /// The translator trapped, overran its budget or returned too much: it
    /// is never called again.
    #[error("{0}")]
    Broken(String),
}

impl WasmTranslator {
    /// Appends the bytes for control string `command` to `out`.
    pub fn encode(&mut self, command: &str, out: &mut Vec<u8>) -> Result<(), TranslatorCallError> {
        self.check().map_err(TranslatorCallError::Broken)?;
        self.store.set_epoch_deadline(self.budget_ticks);
        match self.instance.call_encode(&mut self.store, command) {
            Ok(Ok(bytes)) if bytes.len() <= MAX_TRANSLATED_FRAME_BYTES => {
                out.extend_from_slice(&bytes);
                Ok(())
            }
            Ok(Ok(bytes)) => {
                let reason =
                    format!("encode: returned {} bytes; at most {MAX_TRANSLATED_FRAME_BYTES} are allowed", bytes.len());
                self.broken = Some(reason.clone());
                Err(TranslatorCallError::Broken(reason))
            }
            Ok(Err(message)) => Err(TranslatorCallError::Refused(truncate(message, MAX_GUEST_MESSAGE_BYTES))),
            Err(err) => Err(TranslatorCallError::Broken(self.break_with("encode", &err))),
        }
    }

    /// The feedback that `bytes` complete.
    pub fn decode(&mut self, bytes: &[u8]) -> Result<Vec<WitFeedback>, TranslatorCallError> {
        self.check().map_err(TranslatorCallError::Broken)?;
        self.store.set_epoch_deadline(self.budget_ticks);
        let decoded = match self.instance.call_decode(&mut self.store, bytes) {
            Ok(decoded) => decoded,
            Err(err) => return Err(TranslatorCallError::Broken(self.break_with("decode", &err))),
        };
        if decoded.feedback.len() > MAX_FEEDBACK_PER_DECODE {
            let reason = format!(
                "decode: returned {} messages; at most {MAX_FEEDBACK_PER_DECODE} are allowed",
                decoded.feedback.len()
            );
            self.broken = Some(reason.clone());
            return Err(TranslatorCallError::Broken(reason));
        }
        self.malformed += u64::from(decoded.malformed);
        Ok(decoded.feedback)
    }

    /// Messages the translator reported skipping as malformed.
    pub fn malformed(&self) -> u64 {
        self.malformed
    }
}
