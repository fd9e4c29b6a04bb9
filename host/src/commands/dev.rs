//! `subsume dev`: `run` with the portal and a watcher that activates each
//! change of the robot file or of a component file it names.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Duration;

use super::Context;
use super::flags::{self, RobotFlags};
use super::run::{HostFlags, PortalFlags, launch, run_options};

/// Run a robot file with the portal and watch it: each change of the file
/// or of a component file it names is validated, compiled off the control
/// loop and swapped in at a cycle boundary; errors are printed and the
/// running set stays (docs/writing-components.md).
#[derive(clap::Args)]
pub struct DevCommand {
    /// The robot description.
    config: PathBuf,
    /// How often the files are looked at, in seconds (0.02 to 10).
    #[arg(long, value_name = "SECONDS", default_value = "0.25", value_parser = flags::poll)]
    poll: Duration,
    #[command(flatten)]
    robot: RobotFlags,
    /// Where the web portal listens (`dev` always runs one).
    #[arg(long, value_name = "ADDRESS", default_value = "127.0.0.1:8080")]
    http: SocketAddr,
}

impl DevCommand {
    pub fn execute(self, context: &Context) -> anyhow::Result<ExitCode> {
        let portal = PortalFlags { listen: self.http, watch: Some(self.poll) };
        let report = self.robot.report.clone();
        launch(run_options(self.config, self.robot, HostFlags::default(), Some(portal), context)?, report)
    }
}
