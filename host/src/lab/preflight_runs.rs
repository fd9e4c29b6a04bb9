//! The preflight's runs (docs/lab.md, "Timing"): a set runs its preflight
//! [`PreflightTiming::runs`] times. Run 1 has the lock-step's own timing
//! (the lab kit's plain `subsume run --speed max`); each later run has the
//! timing a robot has, seeded from the experiment and the run's number
//! ([`seed_of`]) within the owner's bounds (`sim::perturb`). A set whose
//! verdict changes between runs hangs on timing and is refused, naming the
//! runs and their seeds ([`combine`]); every run is reproduced from its
//! seed with `subsume run --perturb SEED`.
//!
//! The experiment's folder keeps one run's files under the preflight's
//! usual names (the first refusing run's, else run 1's) and
//! [`RUNS_FILE`], every run's seed and verdict.

use std::path::Path;
use std::time::Duration;

use serde::{Deserialize, Serialize};

use super::preflight::{self, Outcome, PreflightCommand, PreflightError, PreflightFiles};
use super::verdict::{Criteria, Verdict};
use crate::sim::perturb::{PerturbBounds, Perturbation};
use crate::store::experiments::PreflightTiming;
use crate::store::task::Task;

/// The file listing every run of a preflight: its seed and verdict.
pub const RUNS_FILE: &str = "preflight-runs.json";

/// The folder the runs write into, inside the experiment's, while they run.
const RUNS_DIR: &str = "preflight-runs";

/// One run of a preflight and its verdict.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RunVerdict {
    /// Its number, from 1.
    pub run: u32,
    /// The seed of its timing; `None`: the lock-step's own (run 1).
    pub seed: Option<u64>,
    pub passed: bool,
    pub reasons: Vec<String>,
}

impl RunVerdict {
    /// "run 2 (seed 123)", "run 1 (unperturbed)".
    fn name(&self) -> String {
        match self.seed {
            Some(seed) => format!("run {} (seed {seed})", self.run),
            None => format!("run {} (unperturbed)", self.run),
        }
    }
}

/// What a preflight's runs say together.
#[derive(Clone, Debug, PartialEq)]
pub struct Combined {
    pub passed: bool,
    /// Why it was refused: the first refusing run's reasons, naming it and
    /// its seed.
    pub reasons: Vec<String>,
    /// The run whose files the results keep (an index into the runs): the
    /// first refusing one, else the first.
    pub chosen: usize,
}

/// The runs' verdict, pure: every run passed -> passed; every run refused
/// -> refused with the first run's reasons, then which run they are from;
/// the verdict changed -> refused, naming every run and its seed, then
/// the first refusing run's reasons.
pub fn combine(runs: &[RunVerdict]) -> Combined {
    let Some(chosen) = runs.iter().position(|r| !r.passed) else {
        return Combined { passed: true, reasons: Vec::new(), chosen: 0 };
    };
    let refused = &runs[chosen];
    if runs.iter().all(|r| !r.passed) {
        let mut reasons = refused.reasons.clone();
        reasons.push(format!(
            "preflight: every run of {} refused it; the reasons above are {}'s",
            runs.len(),
            refused.name()
        ));
        return Combined { passed: false, reasons, chosen };
    }
    let each: Vec<String> = runs
        .iter()
        .map(|r| match r.reasons.first() {
            _ if r.passed => format!("{} passed", r.name()),
            Some(first) => format!("{} refused: {}", r.name(), first.strip_prefix("preflight: ").unwrap_or(first)),
            None => format!("{} refused", r.name()),
        })
        .collect();
    let mut reasons = vec![format!("preflight: the verdict changed between runs: {}", each.join("; "))];
    reasons.extend(refused.reasons.iter().map(|r| format!("{r} ({})", refused.name())));
    Combined { passed: false, reasons, chosen }
}

/// The seed of run `run` (from 2) of experiment `experiment`'s
/// preflight: the same for the same experiment and run, different across
/// them, short enough to type.
pub fn seed_of(experiment: u64, run: u32) -> u64 {
    let mixed = experiment.wrapping_mul(0x9e37_79b9_7f4a_7c15) ^ u64::from(run).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    let mixed = (mixed ^ (mixed >> 31)).wrapping_mul(0x94d0_49bb_1331_11eb);
    (mixed >> 34) % 1_000_000_000
}

/// What a preflight's runs need beside the command.
pub struct Runs<'a> {
    pub robot: &'a Path,
    pub duration: Duration,
    pub criteria: &'a Criteria,
    pub task: Option<&'a Task>,
    pub timing: PreflightTiming,
    /// The experiment the seeds are derived from.
    pub experiment: u64,
}

/// Runs the preflight of `runs` [`PreflightTiming::runs`] times, one after
/// the other, in experiment folder `dir` (see the module's docs). A run
/// that is not judged (it did not start, was too slow, was cancelled)
/// ends the preflight with its outcome and files; all judged, the outcome
/// is the chosen run's verdict with the runs' combined pass and reasons,
/// and the wall time of them all. Also returns every judged run.
pub fn run_all(
    command: &PreflightCommand,
    runs: &Runs<'_>,
    dir: &Path,
    cancelled: &dyn Fn() -> bool,
) -> Result<(Outcome, Vec<RunVerdict>), PreflightError> {
    let folder = dir.join(RUNS_DIR);
    let _ = std::fs::remove_dir_all(&folder);
    let bounds: PerturbBounds = runs.timing.bounds();
    let mut verdicts = Vec::new();
    let mut judged: Vec<Verdict> = Vec::new();
    let mut wall = 0.0;
    for run in 1..=runs.timing.runs.max(1) {
        let run_dir = folder.join(format!("run-{run}"));
        std::fs::create_dir_all(&run_dir)
            .map_err(|e| PreflightError::File { path: run_dir.clone(), reason: e.to_string() })?;
        let seed = (run > 1).then(|| seed_of(runs.experiment, run));
        let perturb = seed.map(|seed| Perturbation { seed, bounds });
        let files = PreflightFiles::in_dir(&run_dir);
        let outcome = preflight::run_seeded(
            command,
            runs.robot,
            runs.duration,
            runs.criteria,
            runs.task,
            perturb.as_ref(),
            &files,
            cancelled,
        );
        match outcome {
            Ok(Outcome::Judged { verdict, wall_s }) => {
                wall += wall_s;
                verdicts.push(RunVerdict { run, seed, passed: verdict.passed, reasons: verdict.reasons.clone() });
                judged.push(verdict);
            }
            other => {
                keep(&run_dir, dir);
                let _ = std::fs::remove_dir_all(&folder);
                return other.map(|outcome| (outcome, verdicts));
            }
        }
    }
    let combined = combine(&verdicts);
    keep(&folder.join(format!("run-{}", combined.chosen + 1)), dir);
    let _ = std::fs::remove_dir_all(&folder);
    let listing = serde_json::json!({ "bounds": bounds, "kept": combined.chosen + 1, "runs": verdicts });
    let path = dir.join(RUNS_FILE);
    let bytes = serde_json::to_vec_pretty(&listing)
        .map_err(|e| PreflightError::File { path: path.clone(), reason: e.to_string() })?;
    crate::fsutil::write_atomically(&path, &bytes)
        .map_err(|e| PreflightError::File { path: path.clone(), reason: e.to_string() })?;
    let mut verdict = judged.swap_remove(combined.chosen);
    verdict.passed = combined.passed;
    verdict.reasons = combined.reasons;
    Ok((Outcome::Judged { verdict, wall_s: wall }, verdicts))
}

/// Moves the preflight files of run folder `from` into `to` under their
/// usual names (the results' `preflight.mcap`, ...).
fn keep(from: &Path, to: &Path) {
    let (from, to) = (PreflightFiles::in_dir(from), PreflightFiles::in_dir(to));
    let pairs = [
        (&from.recording, &to.recording),
        (&from.report, &to.report),
        (&from.verdict, &to.verdict),
        (&from.criteria, &to.criteria),
        (&from.task, &to.task),
        (&from.log, &to.log),
    ];
    for (from, to) in pairs {
        if from.exists()
            && let Err(e) = std::fs::rename(from, to)
        {
            tracing::warn!("cannot keep the preflight's {}: {e}", from.display());
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn run(run: u32, seed: Option<u64>, refused: Option<&str>) -> RunVerdict {
        RunVerdict {
            run,
            seed,
            passed: refused.is_none(),
            reasons: refused.map(|r| vec![r.to_string()]).unwrap_or_default(),
        }
    }

    /// (the runs, the combined verdict): all pass, all refuse, and the
    /// verdict changing either way, each refusal naming runs and seeds.
    #[test]
    fn the_runs_verdicts_combine_naming_the_runs_and_their_seeds() {
        let collision = "preflight: collision at 12.4 s at (9.8, 1.0) while 'drive' held control";
        let cases = [
            (
                vec![run(1, None, None), run(2, Some(8123), None), run(3, Some(9912), None)],
                Combined { passed: true, reasons: vec![], chosen: 0 },
            ),
            (
                vec![run(1, None, Some(collision)), run(2, Some(8123), Some("preflight: other")), run(3, Some(9912), Some("x"))],
                Combined {
                    passed: false,
                    reasons: vec![
                        collision.to_string(),
                        "preflight: every run of 3 refused it; the reasons above are run 1 (unperturbed)'s".to_string(),
                    ],
                    chosen: 0,
                },
            ),
            (
                vec![run(1, None, None), run(2, Some(9912), Some(collision)), run(3, Some(8123), None)],
                Combined {
                    passed: false,
                    reasons: vec![
                        "preflight: the verdict changed between runs: run 1 (unperturbed) passed; run 2 (seed 9912) refused: collision at 12.4 s at (9.8, 1.0) while 'drive' held control; run 3 (seed 8123) passed".to_string(),
                        format!("{collision} (run 2 (seed 9912))"),
                    ],
                    chosen: 1,
                },
            ),
            (
                vec![run(1, None, Some(collision)), run(2, Some(77), None)],
                Combined {
                    passed: false,
                    reasons: vec![
                        "preflight: the verdict changed between runs: run 1 (unperturbed) refused: collision at 12.4 s at (9.8, 1.0) while 'drive' held control; run 2 (seed 77) passed".to_string(),
                        format!("{collision} (run 1 (unperturbed))"),
                    ],
                    chosen: 0,
                },
            ),
            (vec![run(1, None, None)], Combined { passed: true, reasons: vec![], chosen: 0 }),
        ];
        for (runs, expected) in cases {
            assert_eq!(combine(&runs), expected, "{runs:?}");
        }
    }

    /// A run's seed is its experiment's and its number's, and typed in nine
    /// digits at most.
    #[test]
    fn seeds_are_the_experiments_and_the_runs() {
        assert_eq!(seed_of(12, 2), seed_of(12, 2));
        let mut seen = std::collections::BTreeSet::new();
        for experiment in 1..50 {
            for run in 2..=4 {
                let seed = seed_of(experiment, run);
                assert!(seed < 1_000_000_000);
                seen.insert(seed);
            }
        }
        assert_eq!(seen.len(), 49 * 3, "no two runs share a seed");
    }
}
