//! `subsume release`: release every engaged lock on a running host.

use std::process::ExitCode;

use subsume::portal::client::LockAction;

use super::Context;
use super::flags::LoginFlags;

/// Release every engaged lock on a running host through its portal (a user
/// who may drive: operator or admin).
#[derive(clap::Args)]
pub struct ReleaseCommand {
    #[command(flatten)]
    login: LoginFlags,
}

impl ReleaseCommand {
    pub fn execute(self, _: &Context) -> anyhow::Result<ExitCode> {
        self.login.lock_action(LockAction::Release)
    }
}
