//! `subsume teleop`: drive a robot from the keyboard.

use std::path::PathBuf;
use std::process::ExitCode;

use subsume::teleop::client::{ClientOptions, run};

use super::Context;

/// Drive a robot from the keyboard over its teleoperation port (arrows:
/// speed and turn, space: stop, m: cycle mode, q: quit).
#[derive(clap::Args)]
pub struct TeleopCommand {
    /// The robot's teleoperation address (builtin:teleop's `listen`).
    address: String,
    /// Operator name, as in the robot's operators file.
    #[arg(long, env = "SUBSUME_OPERATOR")]
    name: String,
    /// Operator token (or set SUBSUME_TOKEN).
    #[arg(long, env = "SUBSUME_TOKEN", hide_env_values = true)]
    token: String,
    /// Speak TLS to a host with a certificate, trusting this CA (PEM).
    #[arg(long, value_name = "FILE", env = "SUBSUME_TLS_CA")]
    tls_ca: Option<PathBuf>,
}

impl TeleopCommand {
    pub fn execute(self, _: &Context) -> anyhow::Result<ExitCode> {
        let TeleopCommand { address, name, token, tls_ca } = self;
        run(&ClientOptions { address, name, token, tls_ca })?;
        Ok(ExitCode::SUCCESS)
    }
}
