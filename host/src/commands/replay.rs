//! `subsume replay`: feed components the inputs of a recording and compare
//! their outputs with the recorded ones.

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::Context as _;
use subsume::record::replay::{ReplayError, ReplayOptions, replay};

use super::Context;
use super::flags::ParamFlags;

/// Feed components of a robot file the inputs they got in a recording
/// (subsume run --record) and compare their outputs with the recorded
/// ones, bit for bit; exit 1 at a divergence.
#[derive(clap::Args)]
pub struct ReplayCommand {
    /// The recording (FILE.mcap).
    recording: PathBuf,
    /// The robot file naming the components to replay.
    config: PathBuf,
    /// Replay only these components (repeatable); every WASM component
    /// of the file by default.
    #[arg(long = "only", value_name = "COMPONENT")]
    only: Vec<String>,
    #[command(flatten)]
    params: ParamFlags,
    /// Print the result as JSON.
    #[arg(long)]
    json: bool,
}

impl ReplayCommand {
    pub fn execute(self, context: &Context) -> anyhow::Result<ExitCode> {
        let options = ReplayOptions {
            recording: self.recording,
            config_path: self.config,
            only: self.only,
            overrides: self.params.params,
            cache_dir: context.cache_dir.clone(),
        };
        let report = match replay(&options) {
            Ok(report) => report,
            Err(ReplayError::Config(diagnostics)) => {
                println!("{diagnostics}");
                eprintln!("error: {} problem(s) in {}", diagnostics.0.len(), options.config_path.display());
                return Ok(ExitCode::FAILURE);
            }
            Err(e) => return Err(e.into()),
        };
        if self.json {
            println!("{}", serde_json::to_string_pretty(&report).context("failed to encode the replay report")?);
        } else {
            let speed = if report.wall_s > 0.0 { report.recorded_s / report.wall_s } else { 0.0 };
            println!(
                "replayed {} against {}: {} calls, {} outputs compared, {:.2} recorded s in {:.2} s ({speed:.1}x real time){}",
                report.components.join(", "),
                options.recording.display(),
                report.calls,
                report.compared,
                report.recorded_s,
                report.wall_s,
                if report.truncated { "; the recording was cut short" } else { "" }
            );
            for divergence in &report.divergences {
                println!("{divergence}");
            }
            if report.identical() {
                println!("identical: every output matches the recording bit for bit");
            }
        }
        Ok(if report.identical() { ExitCode::SUCCESS } else { ExitCode::FAILURE })
    }
}
