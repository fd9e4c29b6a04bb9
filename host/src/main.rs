//! The `subsume` command line: parses arguments, sets up logging and signals,
//! and calls into the library. Errors become messages and exit codes here.

// One file per command is where main.rs is going (host/src/commands/);
// `lab` starts there.
#[path = "commands/lab.rs"]
mod lab_command;

use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Duration;

use anyhow::{Context, bail};
use clap::{Parser, Subcommand};
use subsume::assemble::{Loader, registry};
use subsume::config::{self, ParamOverride};
use subsume::contract::{Description, DescriptionDoc};
use subsume::fsutil;
use subsume::run::{FaultInjection, PortalOptions, RunError, RunOptions};
use subsume::runtime::control_loop::Shutdown;
use subsume::runtime::scheduling::FIFO_PRIORITIES;
use subsume::runtime::stall::{MAX_STALL_LIMIT, MIN_STALL_LIMIT};
use subsume::sandbox::{Sandbox, read_component_file};

#[derive(Parser)]
#[command(name = "subsume", version, about = "Runs robot software as sandboxed WebAssembly components")]
struct Cli {
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
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Load a robot file, start its components and run until stopped.
    Run {
        /// The robot description.
        #[arg(default_value = "config/demo.xml")]
        config: PathBuf,
        /// Stop after this many seconds (simulated seconds with --speed).
        #[arg(long, value_name = "SECONDS")]
        duration: Option<f64>,
        /// Run on simulated time: N times real time, or `max` (lock-step,
        /// as fast as the CPU allows). Same inputs, same results.
        #[arg(long, value_name = "N|max")]
        speed: Option<String>,
        /// Write a JSON report here when stopped (see docs/report.md).
        #[arg(long, value_name = "FILE")]
        report: Option<PathBuf>,
        /// Set a component parameter, overriding the robot file (repeatable).
        #[arg(long = "param", value_name = "COMPONENT.PARAM=VALUE")]
        params: Vec<ParamOverride>,
        /// Where the web portal listens, or `off` to run the file alone
        /// without portal or store.
        #[arg(long, value_name = "ADDRESS|off", env = "SUBSUME_HTTP", default_value = "127.0.0.1:8080")]
        http: String,
        /// The stall watchdog's limit: when one call holds the control loop
        /// this long, every motor gets STOP and the component is faulted
        /// (0.01 to 10).
        #[arg(long, value_name = "SECONDS", default_value = "0.1")]
        stall_limit: f64,
        /// Run the control thread under SCHED_FIFO at this priority (1 to
        /// 99; needs CAP_SYS_NICE or an RLIMIT_RTPRIO). Not a default: see
        /// docs/service.md.
        #[arg(long, value_name = "PRIORITY")]
        control_fifo: Option<i32>,
        /// Pin the control thread to this CPU (keep the CPU free of other
        /// work). Not a default: see docs/service.md.
        #[arg(long, value_name = "CPU")]
        control_cpu: Option<usize>,
        /// The certificate chain (PEM, the host's first) the portal and the
        /// network platforms serve TLS with; needs --tls-key.
        #[arg(long, value_name = "FILE", env = "SUBSUME_TLS_CERT")]
        tls_cert: Option<PathBuf>,
        /// The private key (PEM) of --tls-cert.
        #[arg(long, value_name = "FILE", env = "SUBSUME_TLS_KEY")]
        tls_key: Option<PathBuf>,
        /// Allow plain HTTP and plain teleoperation on addresses other than
        /// loopback (passwords and commands then cross the network in clear).
        #[arg(long, env = "SUBSUME_ALLOW_PLAIN_HTTP")]
        allow_plain_http: bool,
        /// Record the run to this MCAP file (every value, call, fault,
        /// status change and log line; docs/recording.md).
        #[arg(long, value_name = "FILE.mcap")]
        record: Option<PathBuf>,
        /// Start the next file of the recording (FILE.1.mcap, ...) once one
        /// reaches this many MiB.
        #[arg(long, value_name = "MIB", default_value = "1024")]
        record_max_mib: u64,
        /// Serve the same channels live to Foxglove or Lichtblick (Foxglove
        /// WebSocket, subprotocol foxglove.sdk.v1) on this address, or `off`.
        #[arg(long, value_name = "ADDRESS|off", env = "SUBSUME_FOXGLOVE", default_value = "off")]
        foxglove: String,
        /// Write the preflight's verdict here (JSON; docs/lab.md): what the
        /// run saw (collisions, faults, the envelope's interventions)
        /// judged by --criteria. A run on simulated time prints it anyway.
        #[arg(long, value_name = "FILE.json")]
        verdict: Option<PathBuf>,
        /// The lab's preflight criteria (JSON, as the lab kit's
        /// criteria.json); the lab's defaults when not given.
        #[arg(long, value_name = "FILE.json")]
        criteria: Option<PathBuf>,
    },
    /// Feed components of a robot file the inputs they got in a recording
    /// (subsume run --record) and compare their outputs with the recorded
    /// ones, bit for bit; exit 1 at a divergence.
    Replay {
        /// The recording (FILE.mcap).
        recording: PathBuf,
        /// The robot file naming the components to replay.
        config: PathBuf,
        /// Replay only these components (repeatable); every WASM component
        /// of the file by default.
        #[arg(long = "only", value_name = "COMPONENT")]
        only: Vec<String>,
        /// Set a component parameter, overriding the robot file (repeatable).
        #[arg(long = "param", value_name = "COMPONENT.PARAM=VALUE")]
        params: Vec<ParamOverride>,
        /// Print the result as JSON.
        #[arg(long)]
        json: bool,
    },
    /// Manage the portal's users (stored in the store's users.json).
    User {
        #[command(subcommand)]
        action: UserAction,
    },
    /// Check a robot file: print every error as path:line:column: message.
    Check {
        config: PathBuf,
        /// Set a component parameter, overriding the robot file (repeatable).
        #[arg(long = "param", value_name = "COMPONENT.PARAM=VALUE")]
        params: Vec<ParamOverride>,
    },
    /// Engage the emergency stop on a running host through its portal
    /// (any user, viewers included; docs/estop.md).
    Estop {
        /// The portal's address (HOST:PORT or http://HOST:PORT).
        host: String,
        /// The portal user to log in as.
        #[arg(long, env = "SUBSUME_USER")]
        user: String,
        /// Their password (or set SUBSUME_PASSWORD).
        #[arg(long, env = "SUBSUME_PASSWORD", hide_env_values = true)]
        password: String,
    },
    /// Release every engaged lock on a running host through its portal
    /// (a user who may drive: operator or admin).
    Release {
        /// The portal's address (HOST:PORT or http://HOST:PORT).
        host: String,
        /// The portal user to log in as (operator or admin).
        #[arg(long, env = "SUBSUME_USER")]
        user: String,
        /// Their password (or set SUBSUME_PASSWORD).
        #[arg(long, env = "SUBSUME_PASSWORD", hide_env_values = true)]
        password: String,
    },
    /// Drive a robot from the keyboard over its teleoperation port
    /// (arrows: speed and turn, space: stop, m: cycle mode, q: quit).
    Teleop {
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
    },
    /// Print what a component declares: ports, parameters, default
    /// priority. COMPONENT is a .wasm file or builtin:KIND (with its
    /// parameters' bounds).
    Describe {
        component: PathBuf,
        /// Print JSON instead of text.
        #[arg(long)]
        json: bool,
    },
    /// Create a component project that builds with one command (see its README).
    New {
        /// The component's name: [a-z][a-z0-9_-]*.
        name: String,
        /// The language of the project.
        #[arg(long, value_name = "rust|c|python|js")]
        lang: subsume::scaffold::Language,
        /// The project's folder, which must not exist [default: ./NAME].
        #[arg(long, value_name = "DIR")]
        dir: Option<PathBuf>,
    },
    /// Run a robot file with the portal and watch it: each change of the
    /// file or of a component file it names is validated, compiled off the
    /// control loop and swapped in at a cycle boundary; errors are printed
    /// and the running set stays (docs/writing-components.md).
    Dev {
        /// The robot description.
        config: PathBuf,
        /// How often the files are looked at, in seconds (0.02 to 10).
        #[arg(long, value_name = "SECONDS", default_value = "0.25")]
        poll: f64,
        /// Stop after this many seconds (simulated seconds with --speed).
        #[arg(long, value_name = "SECONDS")]
        duration: Option<f64>,
        /// Run on simulated time: N times real time, or `max`.
        #[arg(long, value_name = "N|max")]
        speed: Option<String>,
        /// Write a JSON report here when stopped (see docs/report.md).
        #[arg(long, value_name = "FILE")]
        report: Option<PathBuf>,
        /// Set a component parameter, overriding the robot file (repeatable).
        #[arg(long = "param", value_name = "COMPONENT.PARAM=VALUE")]
        params: Vec<ParamOverride>,
        /// Where the web portal listens (`dev` always runs one).
        #[arg(long, value_name = "ADDRESS", default_value = "127.0.0.1:8080")]
        http: String,
    },
    /// Upload components and/or a robot file to a running host's portal,
    /// stage and activate them in one step (docs/portal.md).
    Deploy {
        /// The portal's address (HOST:PORT or http://HOST:PORT).
        host: String,
        /// A component of the robot and its file: uploaded under NAME
        /// (repeatable). Without --robot, the active robot file's component
        /// NAME is pointed at it.
        #[arg(long = "component", value_name = "NAME=FILE.wasm", value_parser = parse_component_arg)]
        components: Vec<(String, PathBuf)>,
        /// A robot file to stage and activate (its sources may name the
        /// uploaded components as NAME.wasm).
        #[arg(long, value_name = "FILE.xml")]
        robot: Option<PathBuf>,
        /// The platform the uploads belong to.
        #[arg(long, default_value = "control")]
        platform: String,
        /// The portal user to log in as (developer or admin).
        #[arg(long, env = "SUBSUME_USER")]
        user: String,
        /// Their password (or set SUBSUME_PASSWORD).
        #[arg(long, env = "SUBSUME_PASSWORD", hide_env_values = true)]
        password: String,
    },
    /// Submit experiments to a robot's remote lab and follow them, list,
    /// show and cancel them, download their results and the lab kit
    /// (docs/lab.md).
    Lab(lab_command::LabCommand),
}

fn parse_component_arg(text: &str) -> Result<(String, PathBuf), String> {
    subsume::portal::deploy_client::component_arg(text).map_err(|e| e.to_string())
}

#[derive(Subcommand)]
enum UserAction {
    /// Add a user; prints a generated password unless --password-stdin.
    Add {
        name: String,
        /// viewer, operator (may drive), researcher (may upload, stage and
        /// submit experiments on its platforms), developer (may upload and
        /// activate on its platforms) or admin.
        #[arg(long)]
        role: String,
        /// network or control (repeatable; developers and researchers need at least one).
        #[arg(long = "platform")]
        platforms: Vec<String>,
        /// Read the password from the first line of standard input.
        #[arg(long)]
        password_stdin: bool,
        /// Replace the user if it exists.
        #[arg(long)]
        replace: bool,
    },
    /// Set a new password (generated, or from standard input).
    Passwd {
        name: String,
        #[arg(long)]
        password_stdin: bool,
    },
    /// Remove a user.
    Remove { name: String },
    /// List users and their roles.
    List,
}

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
    use tracing_subscriber::Layer as _;
    return_large_blocks();
    use tracing_subscriber::layer::SubscriberExt as _;
    use tracing_subscriber::util::SubscriberInitExt as _;
    let cli = Cli::parse();
    let logs = subsume::portal::logs::LogRing::new();
    tracing_subscriber::registry()
        .with(
            tracing_subscriber::fmt::layer().with_writer(std::io::stderr).with_filter(
                tracing_subscriber::EnvFilter::try_from_default_env()
                    .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info,wasmtime=warn,cranelift=warn")),
            ),
        )
        // A filter per layer: an unfiltered layer would turn on every trace
        // event in the process (cranelift traces slow compiles down 4x).
        .with(logs.layer().with_filter(tracing_subscriber::filter::LevelFilter::INFO))
        .with(subsume::record::log::layer().with_filter(tracing_subscriber::filter::LevelFilter::INFO))
        .init();
    let store_dir = cli.store.clone().or_else(default_store_dir);
    let cache_dir = if cli.no_cache { None } else { cli.cache_dir.clone().or_else(default_cache_dir) };
    let result = match cli.command {
        Command::Run {
            config,
            duration,
            speed,
            report,
            params,
            http,
            stall_limit,
            control_fifo,
            control_cpu,
            tls_cert,
            tls_key,
            allow_plain_http,
            record,
            record_max_mib,
            foxglove,
            verdict,
            criteria,
        } => {
            let live = match foxglove.as_str() {
                "off" => Ok(None),
                address => address
                    .parse::<std::net::SocketAddr>()
                    .map(Some)
                    .map_err(|e| anyhow::anyhow!("--foxglove must be ADDRESS:PORT or off, got '{address}': {e}")),
            };
            let record = live.map(|live| {
                (record.is_some() || live.is_some()).then(|| subsume::record::RecordOptions {
                    path: record,
                    max_file_bytes: record_max_mib.saturating_mul(1 << 20),
                    live,
                })
            });
            let portal = portal_options(&http, store_dir, logs).map(|portal| {
                portal.map(|p| subsume::run::PortalOptions {
                    record_max_file_bytes: record_max_mib.saturating_mul(1 << 20),
                    ..p
                })
            });
            record.and_then(|record| portal.map(|portal| (portal, record))).and_then(|(portal, record)| {
                let identity = subsume::tls::TlsIdentity::from_options(tls_cert.as_deref(), tls_key.as_deref())?;
                let tls = subsume::tls::HostTls { identity, allow_plain_remote: allow_plain_http };
                let pace = speed.map(|s| s.parse::<subsume::runtime::lockstep::Pace>()).transpose()?;
                let control = subsume::runtime::scheduling::ControlThreadSettings {
                    fifo_priority: control_fifo,
                    cpu: control_cpu,
                };
                run(RunArgs {
                    config,
                    duration,
                    pace,
                    report,
                    params,
                    cache_dir,
                    portal,
                    stall_limit,
                    control,
                    tls,
                    record,
                    verdict,
                    criteria,
                })
            })
        }
        Command::Dev { config, poll, duration, speed, report, params, http } => {
            let dev = DevArgs { config, poll, duration, speed, report, params, http };
            portal_options(&dev.http, store_dir, logs).and_then(|portal| run_dev(dev, portal, cache_dir))
        }
        Command::User { action } => user(action, store_dir),
        Command::Replay { recording, config, only, params, json } => {
            let options = subsume::record::replay::ReplayOptions {
                recording,
                config_path: config,
                only,
                overrides: params,
                cache_dir,
            };
            replay(&options, json)
        }
        Command::Check { config, params } => check(&config, &params, cache_dir),
        Command::Describe { component, json } => describe(&component, json, cache_dir),
        Command::New { name, lang, dir } => subsume::scaffold::create(&name, lang, dir.as_deref())
            .map(|project| {
                print!("{}", project.next_steps());
                ExitCode::SUCCESS
            })
            .map_err(anyhow::Error::from),
        Command::Estop { host, user, password } => {
            use subsume::portal::client::{LockAction, lock_action};
            lock_action(&host, &user, &password, LockAction::Engage)
                .map(|said| {
                    println!("{said}");
                    ExitCode::SUCCESS
                })
                .map_err(anyhow::Error::from)
        }
        Command::Deploy { host, components, robot, platform, user, password } => {
            use subsume::portal::deploy_client::{DeployRequest, deploy};
            let request = DeployRequest { host, user, password, platform, components, robot };
            deploy(&request, &mut |line| eprintln!("deploy: {line}"))
                .map(|done| {
                    println!("deployed: set {} is running", done.set);
                    ExitCode::SUCCESS
                })
                .map_err(anyhow::Error::from)
        }
        Command::Release { host, user, password } => {
            use subsume::portal::client::{LockAction, lock_action};
            lock_action(&host, &user, &password, LockAction::Release)
                .map(|said| {
                    println!("{said}");
                    ExitCode::SUCCESS
                })
                .map_err(anyhow::Error::from)
        }
        Command::Lab(command) => command.execute(),
        Command::Teleop { address, name, token, tls_ca } => {
            let options = subsume::teleop::client::ClientOptions { address, name, token, tls_ca };
            subsume::teleop::client::run(&options).map(|()| ExitCode::SUCCESS).map_err(anyhow::Error::from)
        }
    };
    match result {
        Ok(code) => code,
        Err(err) => {
            eprintln!("error: {err:#}");
            ExitCode::FAILURE
        }
    }
}

/// `subsume run`'s arguments.
struct RunArgs {
    config: PathBuf,
    duration: Option<f64>,
    pace: Option<subsume::runtime::lockstep::Pace>,
    report: Option<PathBuf>,
    params: Vec<ParamOverride>,
    cache_dir: Option<PathBuf>,
    portal: Option<PortalOptions>,
    stall_limit: f64,
    control: subsume::runtime::scheduling::ControlThreadSettings,
    tls: subsume::tls::HostTls,
    record: Option<subsume::record::RecordOptions>,
    verdict: Option<PathBuf>,
    criteria: Option<PathBuf>,
}

struct DevArgs {
    config: PathBuf,
    poll: f64,
    duration: Option<f64>,
    speed: Option<String>,
    report: Option<PathBuf>,
    params: Vec<ParamOverride>,
    http: String,
}

/// `subsume dev`: `run` with the portal and the file watcher.
fn run_dev(dev: DevArgs, portal: Option<PortalOptions>, cache_dir: Option<PathBuf>) -> anyhow::Result<ExitCode> {
    use subsume::deploy::dev::{MAX_POLL, MIN_POLL};
    let DevArgs { config, poll, duration, speed, report, params, http: _ } = dev;
    let (min, max) = (MIN_POLL.as_secs_f64(), MAX_POLL.as_secs_f64());
    if !(poll.is_finite() && (min..=max).contains(&poll)) {
        bail!("--poll must be between {min} and {max} seconds, got {poll}");
    }
    let Some(mut portal) = portal else {
        bail!("subsume dev needs the portal: give --http ADDRESS, not off");
    };
    portal.watch = Some(Duration::from_secs_f64(poll));
    let tls = subsume::tls::HostTls { identity: None, allow_plain_remote: false };
    let pace = speed.map(|s| s.parse::<subsume::runtime::lockstep::Pace>()).transpose()?;
    let stall_limit = subsume::runtime::stall::DEFAULT_STALL_LIMIT.as_secs_f64();
    let portal = Some(portal);
    let control = subsume::runtime::scheduling::ControlThreadSettings::default();
    run(RunArgs {
        config,
        duration,
        pace,
        report,
        params,
        cache_dir,
        portal,
        stall_limit,
        control,
        tls,
        record: None,
        verdict: None,
        criteria: None,
    })
}

fn run(args: RunArgs) -> anyhow::Result<ExitCode> {
    let RunArgs {
        config: config_path,
        duration,
        pace,
        report: report_path,
        params: overrides,
        cache_dir,
        portal,
        stall_limit,
        control,
        tls,
        record,
        verdict,
        criteria,
    } = args;
    let duration = match duration {
        None => None,
        Some(s) if s.is_finite() && s > 0.0 => Some(Duration::from_secs_f64(s)),
        Some(s) => bail!("--duration must be a positive number of seconds, got {s}"),
    };
    let (min, max) = (MIN_STALL_LIMIT.as_secs_f64(), MAX_STALL_LIMIT.as_secs_f64());
    if !(stall_limit.is_finite() && (min..=max).contains(&stall_limit)) {
        bail!("--stall-limit must be between {min} and {max} seconds, got {stall_limit}");
    }
    if let Some(priority) = control.fifo_priority.filter(|p| !FIFO_PRIORITIES.contains(p)) {
        bail!(
            "--control-fifo must be between {} and {}, got {priority}",
            FIFO_PRIORITIES.start(),
            FIFO_PRIORITIES.end()
        );
    }
    let fault_injection = match std::env::var("SUBSUME_FAULT_INJECTION") {
        Ok(text) if !text.is_empty() => Some(text.parse::<FaultInjection>()?),
        _ => None,
    };
    // From here on a panic on any thread stops every motor, then exits.
    subsume::run::stop_motors_on_panic();
    let shutdown = Shutdown::new();
    let signals = install_signal_handlers(shutdown.clone())?;
    let options = RunOptions {
        config_path,
        duration,
        cache_dir,
        overrides,
        portal,
        stall_limit: Duration::from_secs_f64(stall_limit),
        control,
        fault_injection,
        tls,
        pace,
        record,
        verdict,
        criteria,
    };
    let result = subsume::run::run(&options, shutdown);
    signals.close();
    let report = match result {
        Ok(report) => report,
        Err(RunError::Config(diagnostics)) => {
            println!("{diagnostics}");
            eprintln!(
                "error: {} problem(s) in {}; nothing was started",
                diagnostics.0.len(),
                options.config_path.display()
            );
            return Ok(ExitCode::FAILURE);
        }
        Err(err) => return Err(err.into()),
    };
    if let Some(path) = report_path {
        let text = serde_json::to_vec_pretty(&report).context("failed to encode the report")?;
        fsutil::write_atomically(&path, &text).with_context(|| format!("failed to write report {}", path.display()))?;
        tracing::info!("report written to {}", path.display());
    }
    Ok(ExitCode::SUCCESS)
}

fn replay(options: &subsume::record::replay::ReplayOptions, json: bool) -> anyhow::Result<ExitCode> {
    let report = match subsume::record::replay::replay(options) {
        Ok(report) => report,
        Err(subsume::record::replay::ReplayError::Config(diagnostics)) => {
            println!("{diagnostics}");
            eprintln!("error: {} problem(s) in {}", diagnostics.0.len(), options.config_path.display());
            return Ok(ExitCode::FAILURE);
        }
        Err(e) => return Err(e.into()),
    };
    if json {
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

fn check(config_path: &Path, overrides: &[ParamOverride], cache_dir: Option<PathBuf>) -> anyhow::Result<ExitCode> {
    let sandbox = Sandbox::new(cache_dir)?;
    let mut loader = Loader::new(&sandbox);
    match config::load_with(config_path, &mut loader, overrides) {
        Ok(robot) => {
            println!(
                "{}: ok: robot '{}', {} components, {} connections",
                config_path.display(),
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

fn describe(path: &Path, as_json: bool, cache_dir: Option<PathBuf>) -> anyhow::Result<ExitCode> {
    if let Some(kind) = path.to_str().and_then(|p| p.strip_prefix("builtin:")) {
        return describe_builtin(kind, as_json);
    }
    let sandbox = Sandbox::new(cache_dir)?;
    let bytes = read_component_file(path)?;
    let artifact = sandbox.load(&bytes).with_context(|| format!("failed to load component {}", path.display()))?;
    let d = &artifact.description;
    if as_json {
        let mut doc = serde_json::to_value(DescriptionDoc::new(d, &artifact.sha256))?;
        doc["contract"] = artifact.contract.name().into();
        println!("{}", serde_json::to_string_pretty(&doc)?);
    } else {
        print!("{}", description_text(d, &artifact.sha256));
        println!("contract: subsume:robot@{}", artifact.contract.name());
    }
    Ok(ExitCode::SUCCESS)
}

/// `subsume describe builtin:KIND`: the declaration, with every
/// parameter's bounds and unit.
fn describe_builtin(kind: &str, as_json: bool) -> anyhow::Result<ExitCode> {
    use std::fmt::Write as _;
    let Some(builtin) = registry::find(kind) else {
        bail!("unknown built-in '{kind}' (known: {})", registry::kinds().join(", "));
    };
    let defaults = subsume::builtin::check_values(builtin.params(), &Default::default()).unwrap_or_default();
    let d = subsume::builtin::describe(builtin, &defaults);
    if as_json {
        let params: Vec<serde_json::Value> = builtin
            .params()
            .iter()
            .map(|p| {
                serde_json::json!({
                    "name": p.name, "kind": p.kind().name(), "default": p.default, "unit": p.unit,
                    "expected": p.expected(), "doc": p.doc,
                })
            })
            .collect();
        let mut doc = serde_json::to_value(DescriptionDoc::new(&d, ""))?;
        doc["params"] = params.into();
        doc["carried"] = builtin.carried().into();
        println!("{}", serde_json::to_string_pretty(&doc)?);
        return Ok(ExitCode::SUCCESS);
    }
    let mut s = description_text(&d, "");
    if let Some(at) = s.find("params:\n") {
        s.truncate(at);
    }
    let _ = writeln!(s, "params:");
    if builtin.params().is_empty() {
        let _ = writeln!(s, "  (none)");
    }
    for p in builtin.params() {
        let default = if p.default.is_empty() { "required".to_string() } else { format!("default '{}'", p.default) };
        let _ = writeln!(s, "  {} ({default}): {}; {}", p.name, p.expected(), p.doc);
    }
    print!("{s}");
    Ok(ExitCode::SUCCESS)
}

fn description_text(d: &Description, sha256: &str) -> String {
    use std::fmt::Write as _;
    let mut s = String::new();
    let _ = writeln!(s, "{} {}: {}", d.name, d.version, d.summary);
    if !sha256.is_empty() {
        let _ = writeln!(s, "sha256: {sha256}");
    }
    let priority = d.default_priority.map_or_else(|| "none (emits no motion commands)".to_string(), |p| p.to_string());
    let _ = writeln!(s, "default priority: {priority}");
    for (title, ports) in [("inputs", &d.inputs), ("outputs", &d.outputs)] {
        let _ = writeln!(s, "{title}:");
        if ports.is_empty() {
            let _ = writeln!(s, "  (none)");
        }
        for (i, p) in ports.iter().enumerate() {
            let _ = writeln!(s, "  {i}: {} ({}) {}", p.name, p.kind.name(), p.doc);
        }
    }
    let _ = writeln!(s, "params:");
    if d.params.is_empty() {
        let _ = writeln!(s, "  (none)");
    }
    for p in &d.params {
        let _ = writeln!(s, "  {} ({}, default '{}') {}", p.name, p.kind.name(), p.default_value, p.doc);
    }
    s
}

fn portal_options(
    http: &str,
    store_dir: Option<PathBuf>,
    logs: std::sync::Arc<subsume::portal::logs::LogRing>,
) -> anyhow::Result<Option<PortalOptions>> {
    if http == "off" {
        return Ok(None);
    }
    let listen =
        http.parse().with_context(|| format!("--http must be an address like 127.0.0.1:8080 or off, got '{http}'"))?;
    let store_dir = store_dir.context("no store folder: pass --store DIR or set SUBSUME_STORE")?;
    Ok(Some(PortalOptions {
        listen,
        store_dir,
        logs,
        record_max_file_bytes: subsume::record::DEFAULT_MAX_FILE_BYTES,
        watch: None,
    }))
}

fn user(action: UserAction, store_dir: Option<PathBuf>) -> anyhow::Result<ExitCode> {
    use subsume::config::Platform;
    use subsume::store::users::{Role, generate_password};
    use subsume::store::{Outcome, Store};
    let store_dir = store_dir.context("no store folder: pass --store DIR or set SUBSUME_STORE")?;
    let store = Store::open(&store_dir)?;
    let password = |from_stdin: bool| -> anyhow::Result<(String, bool)> {
        if from_stdin {
            let mut line = String::new();
            std::io::stdin().read_line(&mut line).context("cannot read the password from standard input")?;
            Ok((line.trim_end_matches(['\r', '\n']).to_string(), false))
        } else {
            Ok((generate_password()?, true))
        }
    };
    // Changes take the store's lock (a running portal waits for it) and
    // leave a line in the audit log.
    let audit = |action: &str, name: &str, result: &Result<(), subsume::store::users::UsersError>| {
        if let Ok(writer) = store.lock() {
            let detail = result.as_ref().err().map(ToString::to_string).unwrap_or_default();
            let outcome = if result.is_ok() { Outcome::Ok(&detail) } else { Outcome::Refused(&detail) };
            writer.record("cli", action, &format!("user '{name}'"), outcome);
        }
    };
    match action {
        UserAction::Add { name, role, platforms, password_stdin, replace } => {
            let role: Role = role.parse().map_err(anyhow::Error::msg)?;
            let platforms = platforms.iter().map(|p| Platform::parse(p)).collect::<Result<Vec<_>, _>>()?;
            let (password, generated) = password(password_stdin)?;
            let result = store.lock()?.users_mut().add(&name, role, &platforms, &password, replace);
            audit("user-add", &name, &result);
            result?;
            eprintln!("added {} '{name}' to {}", role.name(), store.users().path().display());
            if generated {
                println!("{password}");
                eprintln!("(that is the password; it is shown once and stored only as an argon2id hash)");
            }
        }
        UserAction::Passwd { name, password_stdin } => {
            let (password, generated) = password(password_stdin)?;
            let result = store.lock()?.users_mut().set_password(&name, &password);
            audit("user-passwd", &name, &result);
            result?;
            if generated {
                println!("{password}");
            }
            eprintln!("new password set for '{name}'");
        }
        UserAction::Remove { name } => {
            let result = store.lock()?.users_mut().remove(&name);
            audit("user-remove", &name, &result);
            result?;
            eprintln!("removed '{name}'");
        }
        UserAction::List => {
            for u in store.users().all()? {
                println!("{} {} {}", u.name, u.role.name(), u.platforms.join(","));
            }
        }
    }
    Ok(ExitCode::SUCCESS)
}

fn default_store_dir() -> Option<PathBuf> {
    let env = |name: &str| std::env::var_os(name).filter(|v| !v.is_empty()).map(PathBuf::from);
    env("XDG_DATA_HOME")
        .map(|d| d.join("subsume"))
        .or_else(|| env("HOME").map(|d| d.join(".local").join("share").join("subsume")))
}

fn default_cache_dir() -> Option<PathBuf> {
    let env = |name: &str| std::env::var_os(name).filter(|v| !v.is_empty()).map(PathBuf::from);
    env("SUBSUME_CACHE_DIR")
        .or_else(|| env("XDG_CACHE_HOME").map(|d| d.join("subsume")))
        .or_else(|| env("HOME").map(|d| d.join(".cache").join("subsume")))
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
