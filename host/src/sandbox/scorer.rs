//! Running a task's scoring component (the `scorer` world of
//! `wit/robot.wit`): one call of `score` over a run's recorded streams,
//! sandboxed like every guest (no capabilities, a CPU-time budget with its
//! wall-clock cap, a memory limit), on an engine of its own that the
//! control loop never shares.
//!
//! Invariants:
//! - the same bytes and the same episode give the same verdict: the
//!   scorer imports nothing of the host's, its WASI clocks stand still at
//!   0 (the wall clock reads the Unix epoch), its generators are seeded
//!   from one fixed name, and a verdict with a NaN or an infinity is
//!   refused (wasm's only non-deterministic floats are NaNs' bits);
//! - a scorer that traps, overruns its budget or memory, or returns a bad
//!   verdict gives [`ScorerError`], never a score.

use std::sync::{Arc, Mutex, OnceLock};
use std::time::Duration;

use sha2::{Digest, Sha256};
use thiserror::Error;
use wasmtime::component::{Component, Linker};
use wasmtime::{Engine, Store};

use super::engine::{EpochTicker, check_component_header, engine_config};
use super::guest::{GuestLimits, GuestState, arm, call_error, new_store};
use super::limits::MAX_GUEST_MESSAGE_BYTES;
use super::{SandboxError, error_text};
use crate::contract::clip_to;
use crate::contract::scorer_bindings::{Episode, ScorerPre, Verdict};

/// CPU time one scoring may use. The threat: a scorer that loops would
/// hold the lab's runner (the next experiment waits on the score), and
/// anyone's `subsume score`. Scoring a 60 s episode takes milliseconds
/// (BENCHMARKS.md asks for at most 1 s); the wall-clock cap is
/// [`WALL_CAP_FACTOR`](super::WALL_CAP_FACTOR) times this.
pub const SCORER_BUDGET: Duration = Duration::from_secs(2);
/// Memory one scoring may use, the episode's samples included. The
/// threat: a scorer that allocates without bound would take the lab
/// host's memory.
pub const SCORER_MEMORY_BYTES: u64 = 256 << 20;
/// Most sub-scores a verdict may hold, and the longest name of one. The
/// threat: a verdict as large as the scorer's memory in every `score.json`,
/// record and leaderboard.
pub const MAX_SUB_SCORES: usize = 64;
pub const MAX_SUB_SCORE_NAME: usize = 64;
/// Compiled scorers kept in this process, by sha256: a lab scores every run
/// and its preflight with the same one. The threat: memory held by
/// compilations of scorers no task names any more.
pub const MAX_COMPILED_SCORERS: usize = 4;
/// The contract's interface of types, which a scorer may import.
const TYPES_INTERFACE: &str = "subsume:robot/types@0.2.0";
/// The name a scorer's store runs under: its WASI generators are seeded
/// from it, the same for every scorer everywhere.
const SCORER_NAME: &str = "scorer";

/// Why a scorer gave no verdict.
#[derive(Clone, Debug, PartialEq, Eq, Error)]
pub enum ScorerError {
    #[error("cannot start the webassembly engine: {0}")]
    Engine(String),
    #[error("not a scoring component (the subsume:robot/scorer world): {0}")]
    NotAScorer(String),
    /// It trapped, overran its budget or memory.
    #[error("{0}")]
    Faulted(String),
    /// `score` returned `err`.
    #[error("refused to score the run: {0}")]
    Refused(String),
    #[error("returned a bad verdict: {0}")]
    BadVerdict(String),
}

/// The scorers' engine, linker (WASI only) and compilations.
struct ScorerEngine {
    engine: Engine,
    linker: Linker<GuestState>,
    compiled: Mutex<Vec<(String, Component)>>,
    _ticker: EpochTicker,
}

fn scorer_engine() -> Result<&'static ScorerEngine, ScorerError> {
    static ENGINE: OnceLock<Result<ScorerEngine, String>> = OnceLock::new();
    let made = ENGINE.get_or_init(|| {
        // On-demand instances: a scorer runs now and then, and the pool's
        // reservations are the control loop's.
        let engine = Engine::new(&engine_config(false, true)).map_err(|e| error_text(&e))?;
        let mut linker = Linker::new(&engine);
        super::wasi::add_to_linker(&mut linker).map_err(|e| error_text(&e))?;
        // The contract's types, no functions: a scorer built with a guest
        // SDK that also knows the other worlds imports them.
        linker.instance(TYPES_INTERFACE).map_err(|e| error_text(&e))?;
        let ticker = EpochTicker::start(engine.clone());
        Ok(ScorerEngine { engine, linker, compiled: Mutex::new(Vec::new()), _ticker: ticker })
    });
    made.as_ref().map_err(|why| ScorerError::Engine(why.clone()))
}

impl ScorerEngine {
    /// `bytes` compiled and linked against the `scorer` world.
    fn prepare(&self, bytes: &[u8]) -> Result<ScorerPre<GuestState>, ScorerError> {
        check_component_header(bytes).map_err(|e| ScorerError::NotAScorer(reason(e)))?;
        let sha256 = hex::encode(Sha256::digest(bytes));
        let kept = self.compiled.lock().ok().and_then(|c| c.iter().find(|(s, _)| *s == sha256).map(|(_, c)| c.clone()));
        let component = match kept {
            Some(component) => component,
            None => {
                let component =
                    Component::new(&self.engine, bytes).map_err(|e| ScorerError::NotAScorer(error_text(&e)))?;
                if let Ok(mut compiled) = self.compiled.lock() {
                    if compiled.len() >= MAX_COMPILED_SCORERS {
                        compiled.remove(0);
                    }
                    compiled.push((sha256, component.clone()));
                }
                component
            }
        };
        let instance_pre =
            self.linker.instantiate_pre(&component).map_err(|e| ScorerError::NotAScorer(error_text(&e)))?;
        ScorerPre::new(instance_pre).map_err(|e| ScorerError::NotAScorer(error_text(&e)))
    }
}

fn reason(err: SandboxError) -> String {
    match err {
        SandboxError::Call { call, reason } => format!("{call} {reason}"),
        other => other.to_string(),
    }
}

/// Checks that `bytes` are a component of the `scorer` world (compiled
/// and linked; nothing runs).
pub fn check_scorer(bytes: &[u8]) -> Result<(), ScorerError> {
    scorer_engine()?.prepare(bytes).map(|_| ())
}

/// Runs the scorer `bytes` over `episode`: its verdict, checked.
pub fn run_scorer(bytes: &[u8], episode: &Episode) -> Result<Verdict, ScorerError> {
    let engine = scorer_engine()?;
    let pre = engine.prepare(bytes)?;
    let limits = GuestLimits {
        memory_bytes: SCORER_MEMORY_BYTES,
        budget: SCORER_BUDGET,
        // What the scorer hands back is checked below; the episode it is
        // handed is bounded by its memory.
        max_message_bytes: SCORER_MEMORY_BYTES,
        ..GuestLimits::default()
    };
    let mut store: Store<GuestState> = new_store(&engine.engine, Arc::from(SCORER_NAME), &limits, Arc::from([]));
    // The clocks stand still at 0: the wall clock at the Unix epoch.
    store.data_mut().now_ns = 0;
    store.data_mut().wall_anchor = Some((Duration::ZERO, 0));
    arm(&mut store, SCORER_BUDGET);
    let instance = pre
        .instantiate(&mut store)
        .map_err(|e| ScorerError::Faulted(reason(call_error("instantiation", SCORER_BUDGET, &e))))?;
    let verdict = match instance.call_score(&mut store, episode) {
        Ok(Ok(verdict)) => verdict,
        Ok(Err(message)) => return Err(ScorerError::Refused(clip_to(&message, MAX_GUEST_MESSAGE_BYTES))),
        Err(e) => return Err(ScorerError::Faulted(reason(call_error("score()", SCORER_BUDGET, &e)))),
    };
    check_verdict(&verdict).map_err(ScorerError::BadVerdict)?;
    Ok(verdict)
}

/// A verdict within the rules of the `scorer` world, or why not.
fn check_verdict(verdict: &Verdict) -> Result<(), String> {
    if !verdict.score.is_finite() {
        return Err(format!("the score is {}, not a finite number", verdict.score));
    }
    if verdict.sub_scores.len() > MAX_SUB_SCORES {
        return Err(format!("{} sub-scores; at most {MAX_SUB_SCORES} are allowed", verdict.sub_scores.len()));
    }
    let mut seen = std::collections::BTreeSet::new();
    for sub in &verdict.sub_scores {
        let shaped = !sub.name.is_empty()
            && sub.name.len() <= MAX_SUB_SCORE_NAME
            && sub.name.bytes().all(|b| b.is_ascii_lowercase() || b.is_ascii_digit() || b"_.-".contains(&b));
        if !shaped {
            return Err(format!(
                "sub-score name '{}' is not 1 to {MAX_SUB_SCORE_NAME} of a-z, 0-9, '_', '.' and '-'",
                crate::contract::clip(&sub.name)
            ));
        }
        if !sub.value.is_finite() {
            return Err(format!("sub-score {} is {}, not a finite number", sub.name, sub.value));
        }
        if !seen.insert(sub.name.as_str()) {
            return Err(format!("sub-score {} appears twice", sub.name));
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::contract::scorer_bindings::SubScore;

    #[test]
    fn a_verdict_must_be_finite_named_and_bounded() {
        let sub = |name: &str, value: f64| SubScore { name: name.into(), value };
        let verdict = |score: f64, subs: Vec<SubScore>| Verdict { score, sub_scores: subs };
        assert_eq!(check_verdict(&verdict(1.5, vec![sub("final_distance_m", 0.2), sub("a.b-c", -1.0)])), Ok(()));
        let cases = [
            (verdict(f64::NAN, vec![]), "the score is NaN, not a finite number"),
            (verdict(f64::INFINITY, vec![]), "the score is inf"),
            (verdict(0.0, vec![sub("x", f64::NAN)]), "sub-score x is NaN"),
            (verdict(0.0, vec![sub("Big", 1.0)]), "sub-score name 'Big' is not"),
            (verdict(0.0, vec![sub("", 1.0)]), "sub-score name '' is not"),
            (verdict(0.0, vec![sub("x", 1.0), sub("x", 2.0)]), "sub-score x appears twice"),
            (verdict(0.0, (0..=MAX_SUB_SCORES).map(|n| sub(&format!("s{n}"), 0.0)).collect()), "65 sub-scores"),
        ];
        for (verdict, expected) in cases {
            let why = check_verdict(&verdict).unwrap_err();
            assert!(why.contains(expected), "{why} vs {expected}");
        }
    }

    #[test]
    fn bytes_that_are_no_component_are_not_a_scorer() {
        let err = check_scorer(b"\0asm\x01\x00\x00\x00").unwrap_err();
        assert!(matches!(err, ScorerError::NotAScorer(_)), "{err}");
        assert!(err.to_string().contains("core webassembly module"), "{err}");
    }
}
