//! The `subsume` binary: sets up logging and signals, parses the command
//! line and hands it to its command (`commands/`, one file per subcommand).
//! Errors become messages and exit codes here.

mod commands;

use std::io::IsTerminal as _;
use std::process::ExitCode;

use anyhow::Context as _;
use clap::Parser as _;
use subsume::portal::logs::LogRing;
use subsume::runtime::control_loop::Shutdown;

/// Allocations at least this large are mapped on their own and unmapped when
/// freed. glibc's default threshold rises after the first large free, after
/// which every login's argon2id working memory (19 MiB) stays resident in a
/// per-thread arena: measured, the demo went from 15 to 74 MiB RSS after 10
/// operator logins; with the threshold fixed it stays at 15 MiB.
#[cfg(all(target_os = "linux", target_env = "gnu"))]
const MALLOC_MMAP_THRESHOLD: i32 = 128 << 10;

/// Fixes glibc's mmap threshold (see [`MALLOC_MMAP_THRESHOLD`]); elsewhere
/// nothing to do.
fn return_large_blocks() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: mallopt only changes the allocator's tuning; called first in
    // main, before any other thread exists.
    unsafe {
        libc::mallopt(libc::M_MMAP_THRESHOLD, MALLOC_MMAP_THRESHOLD);
    }
}

fn main() -> ExitCode {
    return_large_blocks();
    let cli = commands::Cli::parse();
    let logs = install_logging();
    match cli.execute(logs) {
        Ok(code) => code,
        Err(err) => {
            eprintln!("error: {err:#}");
            ExitCode::FAILURE
        }
    }
}

/// Logs go to standard error (filtered by `RUST_LOG`), to the portal's ring
/// of recent lines and to a recording's log channel. Returns the ring.
fn install_logging() -> std::sync::Arc<LogRing> {
    use tracing_subscriber::Layer as _;
    use tracing_subscriber::filter::{EnvFilter, LevelFilter};
    use tracing_subscriber::layer::SubscriberExt as _;
    use tracing_subscriber::util::SubscriberInitExt as _;
    let logs = LogRing::new();
    let filter =
        EnvFilter::try_from_default_env().unwrap_or_else(|_| EnvFilter::new("info,wasmtime=warn,cranelift=warn"));
    tracing_subscriber::registry()
        .with(
            tracing_subscriber::fmt::layer()
                .with_writer(std::io::stderr)
                .with_ansi(colour_on_stderr())
                .with_filter(filter),
        )
        // A filter per layer: an unfiltered layer would turn on every trace
        // event in the process (cranelift traces slow compiles down 4x).
        .with(logs.layer().with_filter(LevelFilter::INFO))
        .with(subsume::record::log::layer().with_filter(LevelFilter::INFO))
        .init();
    logs
}

/// Whether the log may be coloured: only on a terminal (a redirected log or
/// the journal gets plain text), and never when `NO_COLOR` is set to
/// anything but empty (no-color.org).
fn colour_on_stderr() -> bool {
    let no_color = std::env::var_os("NO_COLOR").is_some_and(|v| !v.is_empty());
    !no_color && std::io::stderr().is_terminal()
}

/// SIGINT and SIGTERM request a clean shutdown; a second one sends the
/// final stop of every motor (serial links, ROS 2 `cmd_vel` publishers) and
/// exits at once (130).
fn install_signal_handlers(shutdown: Shutdown) -> anyhow::Result<signal_hook::iterator::Handle> {
    use signal_hook::consts::{SIGINT, SIGTERM};
    let mut signals =
        signal_hook::iterator::Signals::new([SIGINT, SIGTERM]).context("failed to install signal handlers")?;
    let handle = signals.handle();
    std::thread::Builder::new()
        .name("subsume-signals".into())
        .spawn(move || {
            for signal in signals.forever() {
                if shutdown.is_requested() {
                    for (label, outcome) in subsume::run::halt_every_motor() {
                        eprintln!("second signal: {label}: {outcome}");
                    }
                    eprintln!("second signal: exiting now");
                    std::process::exit(130);
                }
                tracing::info!("signal {signal} received: stopping");
                shutdown.request();
            }
        })
        .context("failed to start the signal thread")?;
    Ok(handle)
}
