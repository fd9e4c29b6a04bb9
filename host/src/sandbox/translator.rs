//! A running WASM translator (the `translator` world, 0.2.0 or 0.1.0):
//! encode, decode and poll under the link's time budget; once it breaks it
//! is never called again. A 0.1.0 translator has an empty link plan (no
//! opening or closing bytes, no poll).
//!
//! The controller's fault status reaches the host without a new type in
//! the contract: a 0.2.0 translator's `decode` that completes a fault status
//! calls `host.report` with its text (the fault's, or empty for none), and
//! [`WasmTranslator::decode`] returns it beside the feedback.

use std::time::Duration;

use thiserror::Error;
use wasmtime::Store;

use super::SandboxError;
use super::artifact::TranslatorPre;
use super::guest::{GuestState, arm, call_error};
use super::limits::{INIT_BUDGET, MAX_GUEST_MESSAGE_BYTES};
use crate::contract::bindings::subsume::robot::types::{Decoded, Feedback as WitFeedback, Pose};
use crate::contract::v1::translator_bindings as v1_bindings;
use crate::contract::{LinkPlan, Param, clip_to, translator_bindings, v1};

/// Most bytes one `encode` or `poll` may return: a motor frame is a few
/// dozen bytes.
pub const MAX_TRANSLATED_FRAME_BYTES: usize = 1024;
/// Most feedback messages one `decode` may return.
pub const MAX_FEEDBACK_PER_DECODE: usize = 1024;
/// Most opening or closing bytes a translator may ask for.
pub const MAX_LINK_SEQUENCE_BYTES: usize = 4096;
/// Shortest poll period a translator may ask for: polling faster would
/// flood the device and the control loop.
pub const MIN_POLL_PERIOD: Duration = Duration::from_millis(5);

/// An instance of the world its translator was built against.
enum Instance {
    V2(translator_bindings::Translator),
    V1(v1_bindings::Translator),
}

/// A running WASM translator (the `translator` world).
pub struct WasmTranslator {
    store: Store<GuestState>,
    instance: Instance,
    plan: LinkPlan,
    budget: Duration,
    malformed: u64,
    /// Why it broke, once it has: it is never called again.
    broken: Option<String>,
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
    /// Instantiates `pre` in `store`, calls `init` with `params` and (0.2.0)
    /// asks for its link plan, checking it against the limits above.
    pub(super) fn start(
        mut store: Store<GuestState>,
        pre: &TranslatorPre,
        budget: Duration,
        params: &[Param],
    ) -> Result<WasmTranslator, SandboxError> {
        arm(&mut store, INIT_BUDGET);
        let instantiation = |e| call_error("instantiation", INIT_BUDGET, &e);
        let (instance, init) = match pre {
            TranslatorPre::V2(pre) => {
                let instance = pre.instantiate(&mut store).map_err(instantiation)?;
                let init = instance.call_init(&mut store, params);
                (Instance::V2(instance), init)
            }
            TranslatorPre::V1(pre) => {
                let instance = pre.instantiate(&mut store).map_err(instantiation)?;
                let init = instance.call_init(&mut store, &v1::params_to_v1(params));
                (Instance::V1(instance), init)
            }
        };
        match init {
            Ok(Ok(())) => {}
            Ok(Err(message)) => {
                return Err(SandboxError::Call { call: "init()", reason: clip_to(&message, MAX_GUEST_MESSAGE_BYTES) });
            }
            Err(e) => return Err(call_error("init()", INIT_BUDGET, &e)),
        }
        let plan = match &instance {
            Instance::V2(instance) => {
                let plan = instance.call_link(&mut store).map_err(|e| call_error("link()", INIT_BUDGET, &e))?;
                check_plan(&plan)?;
                plan
            }
            Instance::V1(_) => LinkPlan { opening: Vec::new(), poll_period_ms: 0, closing: Vec::new() },
        };
        Ok(WasmTranslator { store, instance, plan, budget, malformed: 0, broken: None })
    }

    fn check(&self) -> Result<(), TranslatorCallError> {
        self.broken.clone().map_or(Ok(()), |why| Err(TranslatorCallError::Broken(why)))
    }

    fn break_with(&mut self, call: &'static str, err: &wasmtime::Error) -> TranslatorCallError {
        let reason = match call_error(call, self.budget, err) {
            SandboxError::Call { reason, .. } => format!("{call}: {reason}"),
            other => other.to_string(),
        };
        self.broken = Some(reason.clone());
        TranslatorCallError::Broken(reason)
    }

    fn broken_by(&mut self, reason: String) -> TranslatorCallError {
        self.broken = Some(reason.clone());
        TranslatorCallError::Broken(reason)
    }

    /// What the link sends on opening and closing the device, and how often
    /// it polls.
    pub fn plan(&self) -> &LinkPlan {
        &self.plan
    }

    /// Appends the bytes for control string `command` to `out`.
    pub fn encode(&mut self, command: &str, out: &mut Vec<u8>) -> Result<(), TranslatorCallError> {
        self.check()?;
        arm(&mut self.store, self.budget);
        let result = match &self.instance {
            Instance::V2(instance) => instance.call_encode(&mut self.store, command),
            Instance::V1(instance) => instance.call_encode(&mut self.store, command),
        };
        match result {
            Ok(Ok(bytes)) if bytes.len() <= MAX_TRANSLATED_FRAME_BYTES => {
                out.extend_from_slice(&bytes);
                Ok(())
            }
            Ok(Ok(bytes)) => Err(self.broken_by(format!(
                "encode: returned {} bytes; at most {MAX_TRANSLATED_FRAME_BYTES} are allowed",
                bytes.len()
            ))),
            Ok(Err(message)) => Err(TranslatorCallError::Refused(clip_to(&message, MAX_GUEST_MESSAGE_BYTES))),
            Err(err) => Err(self.break_with("encode", &err)),
        }
    }

    /// The feedback that `bytes` complete, and the fault status they
    /// complete (what the translator reported during the call: the fault's
    /// text, empty for none), if any.
    pub fn decode(&mut self, bytes: &[u8]) -> Result<(Vec<WitFeedback>, Option<String>), TranslatorCallError> {
        self.check()?;
        arm(&mut self.store, self.budget);
        self.store.data_mut().reported = None;
        let decoded = match &self.instance {
            Instance::V2(instance) => instance.call_decode(&mut self.store, bytes),
            Instance::V1(instance) => instance.call_decode(&mut self.store, bytes).map(decoded_from_v1),
        };
        let decoded = match decoded {
            Ok(decoded) => decoded,
            Err(err) => return Err(self.break_with("decode", &err)),
        };
        if decoded.feedback.len() > MAX_FEEDBACK_PER_DECODE {
            return Err(self.broken_by(format!(
                "decode: returned {} messages; at most {MAX_FEEDBACK_PER_DECODE} are allowed",
                decoded.feedback.len()
            )));
        }
        self.malformed += u64::from(decoded.malformed);
        Ok((decoded.feedback, self.store.data_mut().reported.take()))
    }

    /// The bytes a poll at `now_ns` asks to send (none for 0.1.0).
    pub fn poll(&mut self, now_ns: u64, out: &mut Vec<u8>) -> Result<(), TranslatorCallError> {
        self.check()?;
        let Instance::V2(instance) = &self.instance else { return Ok(()) };
        arm(&mut self.store, self.budget);
        match instance.call_poll(&mut self.store, now_ns) {
            Ok(bytes) if bytes.len() <= MAX_TRANSLATED_FRAME_BYTES => {
                out.extend_from_slice(&bytes);
                Ok(())
            }
            Ok(bytes) => Err(self.broken_by(format!(
                "poll: returned {} bytes; at most {MAX_TRANSLATED_FRAME_BYTES} are allowed",
                bytes.len()
            ))),
            Err(err) => Err(self.break_with("poll", &err)),
        }
    }

    /// Messages the translator reported skipping as malformed.
    pub fn malformed(&self) -> u64 {
        self.malformed
    }
}

/// A link plan within the limits, or why not.
fn check_plan(plan: &LinkPlan) -> Result<(), SandboxError> {
    let refuse = |reason: String| Err(SandboxError::Call { call: "link()", reason });
    for (what, bytes) in [("opening", &plan.opening), ("closing", &plan.closing)] {
        if bytes.len() > MAX_LINK_SEQUENCE_BYTES {
            return refuse(format!(
                "asked for {} {what} bytes; at most {MAX_LINK_SEQUENCE_BYTES} are allowed",
                bytes.len()
            ));
        }
    }
    let period = Duration::from_millis(u64::from(plan.poll_period_ms));
    if plan.poll_period_ms > 0 && period < MIN_POLL_PERIOD {
        return refuse(format!(
            "asked to be polled every {} ms; at least {} ms apart",
            plan.poll_period_ms,
            MIN_POLL_PERIOD.as_millis()
        ));
    }
    Ok(())
}

/// What a 0.1.0 translator's `decode` found, in 0.2.0's terms.
fn decoded_from_v1(decoded: v1::bindings::subsume::robot::types::Decoded) -> Decoded {
    use v1::bindings::subsume::robot::types::Feedback as Old;
    Decoded {
        feedback: decoded
            .feedback
            .into_iter()
            .map(|f| match f {
                Old::Odometry(p) => WitFeedback::Odometry(Pose { x: p.x, y: p.y, heading: p.heading }),
                Old::Ranges(r) => WitFeedback::Ranges(r),
                Old::Bumper(b) => WitFeedback::Bumper(b),
                Old::Battery(v) => WitFeedback::Battery(v),
            })
            .collect(),
        malformed: decoded.malformed,
    }
}
