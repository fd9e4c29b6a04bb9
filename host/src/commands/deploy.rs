//! `subsume deploy`: upload, stage and activate in one step on a running
//! host.

use std::path::PathBuf;
use std::process::ExitCode;

use subsume::portal::deploy_client::{DeployRequest, component_arg, deploy};

use super::Context;
use super::flags::LoginFlags;

/// Upload components and/or a robot file to a running host's portal, stage
/// and activate them in one step (docs/portal.md).
#[derive(clap::Args)]
pub struct DeployCommand {
    /// A component of the robot and its file: uploaded as the user's
    /// NAME, never replacing another user's (repeatable). Without
    /// --robot, the active robot file's component NAME is pointed at it
    /// (USER/NAME.wasm).
    #[arg(long = "component", value_name = "NAME=FILE.wasm", value_parser = component_arg)]
    components: Vec<(String, PathBuf)>,
    /// A robot file to stage and activate (its sources may name the
    /// user's uploads as NAME.wasm, another user's as OWNER/NAME.wasm).
    #[arg(long, value_name = "FILE.xml")]
    robot: Option<PathBuf>,
    /// The platform the uploads belong to.
    #[arg(long, default_value = "control")]
    platform: String,
    #[command(flatten)]
    login: LoginFlags,
}

impl DeployCommand {
    pub fn execute(self, _: &Context) -> anyhow::Result<ExitCode> {
        let request = DeployRequest {
            login: self.login.login(),
            platform: self.platform,
            components: self.components,
            robot: self.robot,
        };
        let done = deploy(&request, &mut |line| eprintln!("deploy: {line}"))?;
        println!("deployed: set {} is running", done.set);
        Ok(ExitCode::SUCCESS)
    }
}
