//! The subcommands of `subsume`, one file each: a `clap::Args` struct with
//! an `execute`. `flags.rs` holds the flags several commands share (declared
//! once, flattened) and the value parsers that check ranges against the
//! library's named limits. A new command is a file here and one line in
//! [`Command`].

mod check;
mod deploy;
mod describe;
mod dev;
mod estop;
mod flags;
mod lab;
mod new;
mod release;
mod replay;
mod run;
mod score;
mod teleop;
mod user;

use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::Arc;

use clap::{Parser, Subcommand};
use subsume::portal::logs::LogRing;

#[derive(Parser)]
#[command(name = "subsume", version, about = "Runs robot software as sandboxed WebAssembly components")]
pub struct Cli {
    #[command(flatten)]
    global: GlobalFlags,
    #[command(subcommand)]
    command: Command,
}

/// Flags every command takes.
#[derive(clap::Args)]
struct GlobalFlags {
    /// Directory for compiled components [default: $SUBSUME_CACHE_DIR,
    /// $XDG_CACHE_HOME/subsume or ~/.cache/subsume]
    #[arg(long, global = true, value_name = "DIR")]
    cache_dir: Option<PathBuf>,
    /// Compile every component afresh and cache nothing.
    #[arg(long, global = true)]
    no_cache: bool,
    /// The portal's store: users, uploads, sets, audit log [default:
    /// $SUBSUME_STORE, $XDG_DATA_HOME/subsume or ~/.local/share/subsume]
    #[arg(long, global = true, value_name = "DIR", env = "SUBSUME_STORE")]
    store: Option<PathBuf>,
}

// Parsed once per process: the size of `run`'s variant (its host and lab
// flags) costs nothing.
#[allow(clippy::large_enum_variant)]
#[derive(Subcommand)]
enum Command {
    Run(run::RunCommand),
    Replay(replay::ReplayCommand),
    Score(score::ScoreCommand),
    User(user::UserCommand),
    Check(check::CheckCommand),
    Estop(estop::EstopCommand),
    Release(release::ReleaseCommand),
    Teleop(teleop::TeleopCommand),
    Describe(describe::DescribeCommand),
    New(new::NewCommand),
    Dev(dev::DevCommand),
    Deploy(deploy::DeployCommand),
    Lab(lab::LabCommand),
}

/// What every command gets besides its own flags.
pub struct Context {
    /// Where compiled components are cached; `None` with `--no-cache`.
    pub cache_dir: Option<PathBuf>,
    /// The portal's store, when a folder was given or found.
    pub store_dir: Option<PathBuf>,
    /// Recent log lines, for the portal.
    pub logs: Arc<LogRing>,
}

impl Context {
    /// The store folder, or the error saying how to give one.
    fn store_dir(&self) -> anyhow::Result<PathBuf> {
        use anyhow::Context as _;
        self.store_dir.clone().context("no store folder: pass --store DIR or set SUBSUME_STORE")
    }
}

impl Cli {
    /// Runs the command.
    pub fn execute(self, logs: Arc<LogRing>) -> anyhow::Result<ExitCode> {
        let GlobalFlags { cache_dir, no_cache, store } = self.global;
        let context = Context {
            cache_dir: if no_cache { None } else { cache_dir.or_else(default_cache_dir) },
            store_dir: store.or_else(default_store_dir),
            logs,
        };
        match self.command {
            Command::Run(command) => command.execute(&context),
            Command::Replay(command) => command.execute(&context),
            Command::Score(command) => command.execute(&context),
            Command::User(command) => command.execute(&context),
            Command::Check(command) => command.execute(&context),
            Command::Estop(command) => command.execute(&context),
            Command::Release(command) => command.execute(&context),
            Command::Teleop(command) => command.execute(&context),
            Command::Describe(command) => command.execute(&context),
            Command::New(command) => command.execute(&context),
            Command::Dev(command) => command.execute(&context),
            Command::Deploy(command) => command.execute(&context),
            Command::Lab(command) => command.execute(&context),
        }
    }
}

/// A value of an environment variable, if set and not empty.
fn env_dir(name: &str) -> Option<PathBuf> {
    std::env::var_os(name).filter(|v| !v.is_empty()).map(PathBuf::from)
}

fn default_store_dir() -> Option<PathBuf> {
    env_dir("XDG_DATA_HOME")
        .map(|d| d.join("subsume"))
        .or_else(|| env_dir("HOME").map(|d| d.join(".local").join("share").join("subsume")))
}

fn default_cache_dir() -> Option<PathBuf> {
    env_dir("SUBSUME_CACHE_DIR")
        .or_else(|| env_dir("XDG_CACHE_HOME").map(|d| d.join("subsume")))
        .or_else(|| env_dir("HOME").map(|d| d.join(".cache").join("subsume")))
}
