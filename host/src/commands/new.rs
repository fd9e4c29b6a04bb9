//! `subsume new`: a component project that builds with one command.

use std::path::PathBuf;
use std::process::ExitCode;

use subsume::scaffold::{self, Language};

use super::Context;

/// Create a component project that builds with one command (see its README).
#[derive(clap::Args)]
pub struct NewCommand {
    /// The component's name: [a-z][a-z0-9_-]*.
    name: String,
    /// The language of the project.
    #[arg(long, value_name = "rust|c|python|js")]
    lang: Language,
    /// The project's folder, which must not exist [default: ./NAME].
    #[arg(long, value_name = "DIR")]
    dir: Option<PathBuf>,
}

impl NewCommand {
    pub fn execute(self, _: &Context) -> anyhow::Result<ExitCode> {
        let project = scaffold::create(&self.name, self.lang, self.dir.as_deref())?;
        print!("{}", project.next_steps());
        Ok(ExitCode::SUCCESS)
    }
}
