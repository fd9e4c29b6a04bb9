//! `subsume score`: recompute a run's score from its bundle, with no
//! network (docs/lab.md, "Tasks and scores").

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::Context as _;
use subsume::score::{SCORE_FILE, score_bundle};

use super::Context;

/// Recompute the score of an experiment's results (a bundle's folder: its
/// task.json and run.mcap) and compare it with the bundle's score.json,
/// bit for bit; exit 1 when they differ.
#[derive(clap::Args)]
pub struct ScoreCommand {
    /// The bundle's folder (`subsume lab results ID -o DIR`, or the
    /// unpacked `experiment-ID.tar`).
    bundle: PathBuf,
    /// Print only the recomputed score.json.
    #[arg(long)]
    json: bool,
}

impl ScoreCommand {
    pub fn execute(self, _context: &Context) -> anyhow::Result<ExitCode> {
        let (score, bytes) = score_bundle(&self.bundle)?;
        if self.json {
            print!("{}", String::from_utf8_lossy(&bytes));
            return Ok(ExitCode::SUCCESS);
        }
        let value = score.value.map_or_else(|| "none".to_string(), |v| v.to_string());
        println!(
            "task {}: {} = {value} ({} poses, {} commands, {:.2} s recorded)",
            score.task,
            score.metric.name(),
            score.poses,
            score.commands,
            score.recorded_s
        );
        for (name, value) in &score.sub_scores {
            println!("  {name} = {value}");
        }
        let kept_path = self.bundle.join(SCORE_FILE);
        let kept = match std::fs::read(&kept_path) {
            Ok(kept) => kept,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
                println!("{} is not in the bundle: nothing to compare", SCORE_FILE);
                return Ok(ExitCode::SUCCESS);
            }
            Err(e) => return Err(e).with_context(|| format!("cannot read {}", kept_path.display())),
        };
        if kept == bytes {
            println!("identical: {} matches the recomputed score bit for bit", kept_path.display());
            Ok(ExitCode::SUCCESS)
        } else {
            println!("differs: {} is not the recomputed score; recomputed:", kept_path.display());
            print!("{}", String::from_utf8_lossy(&bytes));
            Ok(ExitCode::FAILURE)
        }
    }
}
