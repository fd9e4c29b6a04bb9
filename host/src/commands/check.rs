//! `subsume check`: validate a robot file and print every problem.

use std::path::PathBuf;
use std::process::ExitCode;

use subsume::assemble::Loader;
use subsume::config;
use subsume::sandbox::Sandbox;

use super::Context;
use super::flags::ParamFlags;

/// Check a robot file: print every error as path:line:column: message.
#[derive(clap::Args)]
pub struct CheckCommand {
    config: PathBuf,
    #[command(flatten)]
    params: ParamFlags,
}

impl CheckCommand {
    pub fn execute(self, context: &Context) -> anyhow::Result<ExitCode> {
        let sandbox = Sandbox::new(context.cache_dir.clone())?;
        let mut loader = Loader::new(&sandbox);
        match config::load_with(&self.config, &mut loader, &self.params.params) {
            Ok(robot) => {
                println!(
                    "{}: ok: robot '{}', {} components, {} connections",
                    self.config.display(),
                    robot.name,
                    robot.components.len(),
                    robot.connections.len()
                );
                Ok(ExitCode::SUCCESS)
            }
            Err(diagnostics) => {
                println!("{diagnostics}");
                Ok(ExitCode::FAILURE)
            }
        }
    }
}
