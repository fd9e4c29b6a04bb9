//! `subsume run`: load a robot file and run it until stopped, with the portal
//! unless `--http off`. Also the one conversion from flags to
//! [`RunOptions`] and the launch (panic policy, signals, report) that `dev`
//! shares.

use std::io::IsTerminal as _;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Duration;

use anyhow::Context as _;
use subsume::fsutil;
use subsume::lab::preflight::Priority;
use subsume::record::RecordOptions;
use subsume::run::{FaultInjection, PortalOptions, RunError, RunOptions};
use subsume::runtime::control_loop::Shutdown;
use subsume::runtime::scheduling::ControlThreadSettings;
use subsume::runtime::stall::DEFAULT_STALL_LIMIT;
use subsume::sim::perturb::{PerturbBounds, Perturbation};
use subsume::tls::{HostTls, TlsIdentity};

use super::Context;
use super::flags::{self, Listen, RobotFlags};

/// Load a robot file, start its components and run until stopped.
#[derive(clap::Args)]
pub struct RunCommand {
    /// The robot description.
    #[arg(default_value = "config/demo.xml")]
    config: PathBuf,
    #[command(flatten)]
    robot: RobotFlags,
    /// Where the web portal listens, or `off` to run the file alone
    /// without portal or store.
    #[arg(long, value_name = "ADDRESS|off", env = "SUBSUME_HTTP", default_value = "127.0.0.1:8080",
          value_parser = flags::address_or_off)]
    http: Listen,
    #[command(flatten)]
    host: HostFlags,
    #[command(flatten)]
    join: flags::LabJoinFlags,
}

/// How the host runs a robot: the watchdog, the control thread, TLS,
/// recording. `dev` runs with the defaults.
#[derive(clap::Args, Clone, Debug, PartialEq)]
pub struct HostFlags {
    /// The stall watchdog's limit: when one call holds the control loop
    /// this long, every motor gets STOP and the component is faulted
    /// (0.01 to 10).
    #[arg(long, value_name = "SECONDS", default_value = "0.1", value_parser = flags::stall_limit)]
    stall_limit: Duration,
    /// Run the control thread under SCHED_FIFO at this priority (1 to
    /// 99; needs CAP_SYS_NICE or an RLIMIT_RTPRIO). Not a default: see
    /// docs/service.md.
    #[arg(long, value_name = "PRIORITY", value_parser = flags::fifo_priority)]
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
    #[arg(long, value_name = "MIB", default_value = "1024", value_parser = clap::value_parser!(u64).range(1..))]
    record_max_mib: u64,
    /// Stop recording once the files together reach this many MiB (the
    /// last file is finished and marked cut; the log says so). No limit
    /// when not given.
    #[arg(long, value_name = "MIB", value_parser = clap::value_parser!(u64).range(1..))]
    record_max_total_mib: Option<u64>,
    /// Serve the same channels live to Foxglove or Lichtblick (Foxglove
    /// WebSocket, subprotocol foxglove.sdk.v1) on this address, or `off`.
    #[arg(long, value_name = "ADDRESS|off", env = "SUBSUME_FOXGLOVE", default_value = "off",
          value_parser = flags::address_or_off)]
    foxglove: Listen,
    /// Write the preflight's verdict here (JSON; docs/lab.md): what the
    /// run saw (collisions, faults, the envelope's interventions) judged
    /// by --criteria. A run on simulated time prints it anyway.
    #[arg(long, value_name = "FILE.json")]
    verdict: Option<PathBuf>,
    /// The lab's preflight criteria (JSON, as the lab kit's criteria.json);
    /// the lab's defaults when not given.
    #[arg(long, value_name = "FILE.json")]
    criteria: Option<PathBuf>,
    /// The lab's task (JSON, as the lab kit's task.json): the run ends
    /// when one of its end conditions holds (the robot at its goal, its
    /// first collision), as the lab's runs and preflights do. With --http
    /// off.
    #[arg(long, value_name = "FILE.json")]
    task: Option<PathBuf>,
    /// Seed the timing a robot has into this simulated run (with --speed
    /// and --http off): each component's tick phase, the sensors' latency
    /// and noise, the serial link's delay, drawn from SEED within
    /// --perturb-bounds. The same seed and bounds give the same run bit
    /// for bit; the lab's preflight runs are rerun this way (docs/lab.md,
    /// "Timing").
    #[arg(long, value_name = "SEED")]
    perturb: Option<u64>,
    /// The bounds of --perturb (JSON, as the lab kit's perturb-bounds.json:
    /// tick_phase, sensor_latency_ms, range_noise_m, serial_delay_ms); the
    /// lab's defaults when not given.
    #[arg(long, value_name = "FILE.json", requires = "perturb")]
    perturb_bounds: Option<PathBuf>,
    /// How the lab's preflights run beside the robot: `idle` (only the CPU
    /// the robot leaves), `background` (nice 10, as a compile; for a robot
    /// whose own work keeps the machine busy) or `normal`. docs/lab.md.
    #[arg(long, value_name = "idle|background|normal", default_value = "idle")]
    preflight_priority: Priority,
}

impl Default for HostFlags {
    /// The flags' defaults, as clap gives them (a test checks they agree).
    fn default() -> HostFlags {
        HostFlags {
            stall_limit: DEFAULT_STALL_LIMIT,
            control_fifo: None,
            control_cpu: None,
            tls_cert: None,
            tls_key: None,
            allow_plain_http: false,
            record: None,
            record_max_mib: subsume::record::DEFAULT_MAX_FILE_BYTES >> 20,
            record_max_total_mib: None,
            foxglove: Listen::Off,
            verdict: None,
            criteria: None,
            task: None,
            perturb: None,
            perturb_bounds: None,
            preflight_priority: Priority::Idle,
        }
    }
}

/// The portal a run serves: where it listens, and for `dev` how often the
/// files are looked at.
pub struct PortalFlags {
    pub listen: SocketAddr,
    pub watch: Option<Duration>,
}

impl RunCommand {
    pub fn execute(self, context: &Context) -> anyhow::Result<ExitCode> {
        let portal = self.http.address().map(|listen| PortalFlags { listen, watch: None });
        let report = self.robot.report.clone();
        let link = self.join.link(context.store_dir.as_deref())?;
        if link.is_some() && portal.is_none() {
            anyhow::bail!(
                "--lab needs the portal and its store (the lab's experiments run through them): not --http off"
            );
        }
        let mut options = run_options(self.config, self.robot, self.host, portal, context)?;
        if let Some(portal) = &mut options.portal {
            portal.lab = link;
        }
        launch(options, report)
    }
}

/// The one conversion from the flags to [`RunOptions`].
pub fn run_options(
    config_path: PathBuf,
    robot: RobotFlags,
    host: HostFlags,
    portal: Option<PortalFlags>,
    context: &Context,
) -> anyhow::Result<RunOptions> {
    let max_file_bytes = host.record_max_mib.saturating_mul(1 << 20);
    let portal = match portal {
        None => None,
        Some(PortalFlags { listen, watch }) => Some(PortalOptions {
            listen,
            store_dir: context.store_dir()?,
            logs: context.logs.clone(),
            record_max_file_bytes: max_file_bytes,
            watch,
            // A person at a terminal gets a first admin and its password; a
            // service unit or a pipe gets a hint instead (the password
            // would end up in a log file).
            first_user: if std::io::stdout().is_terminal() {
                subsume::run::FirstUser::MakeAdmin
            } else {
                subsume::run::FirstUser::Hint
            },
            lab: None,
            preflight_priority: host.preflight_priority,
        }),
    };
    let live = host.foxglove.address();
    let record = (host.record.is_some() || live.is_some()).then_some(RecordOptions {
        path: host.record,
        max_file_bytes,
        max_total_bytes: host.record_max_total_mib.map_or(u64::MAX, |mib| mib.saturating_mul(1 << 20)),
        live,
        hidden: Default::default(),
        for_owner: None,
    });
    let identity = TlsIdentity::from_options(host.tls_cert.as_deref(), host.tls_key.as_deref())?;
    let fault_injection = match std::env::var("SUBSUME_FAULT_INJECTION") {
        Ok(text) if !text.is_empty() => Some(text.parse::<FaultInjection>()?),
        _ => None,
    };
    let perturb = match host.perturb {
        None => None,
        Some(seed) => Some(Perturbation { seed, bounds: perturb_bounds(host.perturb_bounds.as_deref())? }),
    };
    Ok(RunOptions {
        config_path,
        duration: robot.duration,
        cache_dir: context.cache_dir.clone(),
        overrides: robot.params.params,
        portal,
        stall_limit: host.stall_limit,
        fault_injection,
        tls: HostTls { identity, allow_plain_remote: host.allow_plain_http },
        pace: robot.speed,
        record,
        control: ControlThreadSettings { fifo_priority: host.control_fifo, cpu: host.control_cpu },
        verdict: host.verdict,
        criteria: host.criteria,
        task: host.task,
        perturb,
    })
}

/// The bounds in `path` (checked), else the lab's defaults.
fn perturb_bounds(path: Option<&std::path::Path>) -> anyhow::Result<PerturbBounds> {
    let Some(path) = path else { return Ok(PerturbBounds::DEFAULT) };
    let text = std::fs::read(path).with_context(|| format!("cannot read the bounds {}", path.display()))?;
    let bounds: PerturbBounds =
        serde_json::from_slice(&text).with_context(|| format!("{}: not the bounds of --perturb", path.display()))?;
    bounds.check().with_context(|| format!("{}: the bounds of --perturb", path.display()))?;
    Ok(bounds)
}

/// Runs the robot until stopped, with the panic policy and the signal
/// handlers in place, and writes the report.
pub fn launch(options: RunOptions, report_path: Option<PathBuf>) -> anyhow::Result<ExitCode> {
    // From here on a panic on any thread stops every motor, then exits.
    subsume::run::stop_motors_on_panic();
    let shutdown = Shutdown::new();
    let signals = crate::install_signal_handlers(shutdown.clone())?;
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

#[cfg(test)]
mod tests {
    use clap::Parser as _;

    use super::*;
    use crate::commands::{Cli, Command};

    #[test]
    fn the_host_flags_default_as_clap_defaults_them() {
        let cli = Cli::try_parse_from(["subsume", "run", "--http", "off"]).unwrap();
        let Command::Run(run) = cli.command else { panic!("not run") };
        assert_eq!(run.host, HostFlags::default());
        assert_eq!(run.http, Listen::Off);
    }
}
