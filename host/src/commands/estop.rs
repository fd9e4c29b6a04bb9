//! `subsume estop`: engage the emergency stop on a running host.

use std::process::ExitCode;

use subsume::portal::client::LockAction;

use super::Context;
use super::flags::LoginFlags;

/// Engage the emergency stop on a running host through its portal (any
/// user, viewers included; docs/estop.md).
#[derive(clap::Args)]
pub struct EstopCommand {
    #[command(flatten)]
    login: LoginFlags,
}

impl EstopCommand {
    pub fn execute(self, _: &Context) -> anyhow::Result<ExitCode> {
        self.login.lock_action(LockAction::Engage)
    }
}
