//! `subsume score`: recompute a run's score from its bundle, with no
//! network (docs/lab.md, "Tasks and scores").

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::Context as _;
use subsume::score::{PREFLIGHT_RECORDING, PREFLIGHT_SCORE_FILE, RUN_RECORDING, SCORE_FILE, score_bundle_recording};
use subsume::store::task::Score;

use super::Context;

/// Recompute the score of an experiment's results (a bundle's folder: its
/// task.json and run.mcap, and its preflight.mcap when the bundle holds
/// the preflight's score) and compare each with the bundle's, bit for bit;
/// exit 1 when one differs.
#[derive(clap::Args)]
pub struct ScoreCommand {
    /// The bundle's folder (`subsume lab results ID -o DIR`, or the
    /// unpacked `experiment-ID.tar`).
    bundle: PathBuf,
    /// Print only the run's recomputed score.json.
    #[arg(long)]
    json: bool,
}

fn shown(value: Option<f64>) -> String {
    value.map_or_else(|| "none".to_string(), |v| v.to_string())
}

impl ScoreCommand {
    pub fn execute(self, _context: &Context) -> anyhow::Result<ExitCode> {
        let (run, bytes) = score_bundle_recording(&self.bundle, RUN_RECORDING)?;
        if self.json {
            print!("{}", String::from_utf8_lossy(&bytes));
            return Ok(ExitCode::SUCCESS);
        }
        let mut identical = self.compare("run", &run, &bytes, SCORE_FILE, true)?;
        // The preflight's score, when the bundle has one: the simulator's
        // side of the same task.
        if self.bundle.join(PREFLIGHT_SCORE_FILE).exists() {
            let (preflight, bytes) = score_bundle_recording(&self.bundle, PREFLIGHT_RECORDING)?;
            identical &= self.compare("preflight", &preflight, &bytes, PREFLIGHT_SCORE_FILE, false)?;
            if let (Some(real), Some(simulated)) = (run.value, preflight.value) {
                println!("{}: robot {real}, simulator {simulated}, gap {}", run.metric.name(), real - simulated);
            }
        }
        Ok(if identical { ExitCode::SUCCESS } else { ExitCode::FAILURE })
    }

    /// Prints `score` (of the `which` recording; with `all`, every
    /// sub-score) and compares its `bytes` with the bundle's `file`:
    /// whether they are identical (a file absent has nothing to differ).
    fn compare(&self, which: &str, score: &Score, bytes: &[u8], file: &str, all: bool) -> anyhow::Result<bool> {
        println!(
            "{which}: task {}: {} = {} ({} poses, {} commands, {:.2} s recorded)",
            score.task,
            score.metric.name(),
            shown(score.value),
            score.poses,
            score.commands,
            score.recorded_s
        );
        if all {
            for (name, value) in &score.sub_scores {
                println!("  {name} = {value}");
            }
        }
        let kept_path = self.bundle.join(file);
        let kept = match std::fs::read(&kept_path) {
            Ok(kept) => kept,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
                println!("{file} is not in the bundle: nothing to compare");
                return Ok(true);
            }
            Err(e) => return Err(e).with_context(|| format!("cannot read {}", kept_path.display())),
        };
        if kept == bytes {
            println!("identical: {} matches the recomputed score bit for bit", kept_path.display());
            Ok(true)
        } else {
            println!("differs: {} is not the recomputed score; recomputed:", kept_path.display());
            print!("{}", String::from_utf8_lossy(bytes));
            Ok(false)
        }
    }
}
