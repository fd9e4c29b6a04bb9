//! The composition root of `subsume run`: starts the sandbox, the store and
//! the portal's runtime when asked, assembles the robot, runs the control
//! loop on its own thread (with the stall watchdog beside it) until a
//! shutdown or the duration, and returns the final report; it also holds the
//! exits that cannot wait for the loop (the panic policy, halting every
//! motor). Nothing but `main.rs`, tests and benches imports this.

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

use thiserror::Error;

use crate::assemble::{self, Loader, StartError};
use crate::builtin::Services;
use crate::config::{self, Diagnostics, ParamOverride, RobotConfig};
use crate::deploy::{self, BootOptions, DeployError, Deployer};
use crate::fsutil::HiddenPaths;
use crate::lab::episode::{EndWatch, EpisodeWatch};
use crate::lab::preflight::{HolderWatch, PreflightCommand, PreflightLimits};
use crate::lab::robot_link::{LinkError, RobotLink, RobotLinkOptions};
use crate::lab::server::{Fleet, FleetOptions, ServerError};
use crate::lab::verdict::Criteria;
use crate::lab::{Lab, LabOptions, LabRole};
use crate::portal::{self, logs::LogRing};
use crate::record::control::{RecordingError, Recordings};
use crate::record::{Layout, RecordError, RecordOptions, RecordSummary, Recorder, Timeline};
use crate::report::{self, Report};
use crate::robot::serial::HALT_WAIT;
use crate::runtime::control_loop::{self, Clock, CycleHook, Shutdown, StopReason};
use crate::runtime::lockstep::Pace;
use crate::runtime::scheduling::ControlThreadSettings;
use crate::runtime::stall::{MAX_STALL_LIMIT, MIN_STALL_LIMIT};
use crate::runtime::{Graph, Heartbeat, Locks, RunningRobot, StallWatchdog, Standings, StopOutcome};
use crate::sandbox::{Sandbox, SandboxError};
use crate::sim::perturb::Perturbation;
use crate::store::task::{EpisodeEnd, Task};
use crate::store::users::Directory;
use crate::store::{Store, StoreError};
use crate::teleop::TeleopServers;
use crate::tls::{HostTls, TlsError};

/// What `subsume run` was asked to do.
#[derive(Clone, Debug)]
pub struct RunOptions {
    pub config_path: PathBuf,
    /// Stop after this long; run until shutdown when `None`.
    pub duration: Option<Duration>,
    /// Where compiled components are cached; no cache when `None`.
    pub cache_dir: Option<PathBuf>,
    /// Parameters set on the command line.
    pub overrides: Vec<ParamOverride>,
    /// Serve the portal and run from the store; `None`: run the file alone.
    pub portal: Option<PortalOptions>,
    /// How long one call may hold the control loop before the stall
    /// watchdog stops the motors and faults the component (`--stall-limit`;
    /// `runtime::stall::DEFAULT_STALL_LIMIT` unless set).
    pub stall_limit: Duration,
    /// Faults caused on purpose, for the tests only
    /// (`SUBSUME_FAULT_INJECTION`, see ARCHITECTURE.md).
    pub fault_injection: Option<FaultInjection>,
    /// The certificate the portal and the network platforms serve TLS
    /// with, and whether plain text may leave loopback.
    pub tls: HostTls,
    /// Run on simulated time at this pace (`--speed`); real time when
    /// `None`. The duration is then simulated time.
    pub pace: Option<Pace>,
    /// Record the run to MCAP (`--record`).
    pub record: Option<RecordOptions>,
    /// Real-time settings of the control thread (`--control-fifo`,
    /// `--control-cpu`); none by default.
    pub control: ControlThreadSettings,
    /// Write the preflight's verdict here (`--verdict`, docs/lab.md); a
    /// run on simulated time prints it either way.
    pub verdict: Option<PathBuf>,
    /// The criteria the verdict applies (`--criteria FILE`, JSON); the
    /// lab's defaults when `None`.
    pub criteria: Option<PathBuf>,
    /// The lab's task (`--task FILE`, JSON, as the lab kit's task.json):
    /// the run ends when one of its end conditions holds (docs/lab.md,
    /// "Tasks and scores"), as the lab's runs do.
    pub task: Option<PathBuf>,
    /// Seeded timing perturbations (`--perturb SEED`, `--perturb-bounds`;
    /// `sim::perturb`): on simulated time without the portal only.
    pub perturb: Option<Perturbation>,
}

impl RunOptions {
    /// The clock this run keeps: real time, or simulated at `pace`.
    fn clock(&self) -> Clock {
        match self.pace {
            Some(pace) => Clock::simulated(pace),
            None => Clock::new(),
        }
    }

    /// The sandbox the run's guests live in: on simulated time, without
    /// wall-clock caps.
    fn sandbox(&self) -> Result<Sandbox, SandboxError> {
        let sandbox = Sandbox::new(self.cache_dir.clone())?;
        Ok(if self.pace.is_some() { sandbox.on_simulated_time() } else { sandbox })
    }
}

/// A fault the tests cause in the real binary, to check that every way out
/// leaves the motors stopped. Read only from `SUBSUME_FAULT_INJECTION`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum FaultInjection {
    /// `panic-control:SECONDS`: the control thread panics this long after
    /// the loop started.
    PanicControl(Duration),
    /// `panic-thread:SECONDS`: a thread outside the control loop panics
    /// this long after the loop started.
    PanicThread(Duration),
    /// `hang-control:SECONDS`: the control thread blocks between two
    /// cycles, for good, this long after the loop started (a stuck loop:
    /// the stall watchdog's case, and a shutdown that cannot finish).
    HangControl(Duration),
}

/// Why `SUBSUME_FAULT_INJECTION` did not parse.
#[derive(Clone, Debug, PartialEq, Eq, Error)]
#[error(
    "SUBSUME_FAULT_INJECTION must be panic-control:SECONDS, panic-thread:SECONDS or hang-control:SECONDS (a test-only setting), got '{0}'"
)]
pub struct FaultInjectionError(String);

impl std::str::FromStr for FaultInjection {
    type Err = FaultInjectionError;

    fn from_str(text: &str) -> Result<FaultInjection, FaultInjectionError> {
        let bad = || FaultInjectionError(crate::contract::clip(text));
        let (what, seconds) = text.split_once(':').ok_or_else(bad)?;
        let after = seconds
            .trim()
            .parse::<f64>()
            .ok()
            .filter(|s| s.is_finite() && *s >= 0.0 && *s <= 3600.0)
            .map(Duration::from_secs_f64)
            .ok_or_else(bad)?;
        match what.trim() {
            "panic-control" => Ok(FaultInjection::PanicControl(after)),
            "panic-thread" => Ok(FaultInjection::PanicThread(after)),
            "hang-control" => Ok(FaultInjection::HangControl(after)),
            _ => Err(bad()),
        }
    }
}

/// Where the portal listens and where its store lives.
#[derive(Clone, Debug)]
pub struct PortalOptions {
    pub listen: std::net::SocketAddr,
    pub store_dir: PathBuf,
    /// Recent log lines (fed by the binary's `tracing` subscriber).
    pub logs: Arc<LogRing>,
    /// Size of one file of a recording started from the portal before it
    /// rotates (`--record-max-mib`, as for `--record`).
    pub record_max_file_bytes: u64,
    /// `subsume dev`: watch the robot file and its component files at this
    /// poll interval, and activate each change (`deploy::dev`).
    pub watch: Option<Duration>,
    /// What a store with no users gets at start.
    pub first_user: FirstUser,
    /// Join a lab of several robots (`--lab NAME`, docs/lab.md): its
    /// experiments come from that lab's server only.
    pub lab: Option<RobotLinkOptions>,
    /// How the lab's preflights are scheduled beside the robot
    /// (`--preflight-priority`).
    pub preflight_priority: crate::lab::preflight::Priority,
}

/// What the portal does when its store has no users yet.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FirstUser {
    /// Someone reads standard output (a terminal): make `admin` with a
    /// generated password and print it once there, with the portal's
    /// address, so the first run ends with a working login.
    MakeAdmin,
    /// Nobody may read it (a service unit, a pipe into a log): make no user;
    /// the log says how to add one.
    Hint,
}

/// What `subsume lab serve` was asked to do.
#[derive(Clone, Debug)]
pub struct LabServeOptions {
    pub listen: std::net::SocketAddr,
    pub store_dir: PathBuf,
    pub logs: Arc<LogRing>,
    pub cache_dir: Option<PathBuf>,
    pub tls: HostTls,
    pub fleet: FleetOptions,
    /// What a store with no users gets at start.
    pub first_user: FirstUser,
    /// How the lab's preflights are scheduled (`--preflight-priority`).
    pub preflight_priority: crate::lab::preflight::Priority,
}

#[derive(Debug, Error)]
pub enum RunError {
    #[error("{0}")]
    Config(Diagnostics),
    #[error(transparent)]
    Sandbox(#[from] SandboxError),
    #[error("{}", .0.iter().map(ToString::to_string).collect::<Vec<_>>().join("\n"))]
    Start(Vec<StartError>),
    #[error(transparent)]
    Store(#[from] StoreError),
    #[error(transparent)]
    Deploy(DeployError),
    #[error(transparent)]
    Tls(#[from] TlsError),
    #[error("the portal cannot listen on {address}: {source}")]
    Listen {
        address: std::net::SocketAddr,
        #[source]
        source: std::io::Error,
    },
    #[error("cannot start the portal runtime: {0}")]
    PortalRuntime(#[source] std::io::Error),
    #[error("cannot start the file watcher (subsume dev): {0}")]
    Watch(#[source] std::io::Error),
    #[error("the control loop thread failed: {0}")]
    ControlLoop(String),
    #[error(transparent)]
    Record(#[from] RecordError),
    #[error(transparent)]
    Recording(#[from] RecordingError),
    #[error("{path}: {reason}")]
    Verdict { path: PathBuf, reason: String },
    #[error(transparent)]
    Lab(#[from] crate::lab::LabError),
    #[error("the lab's link: {0}")]
    LabLink(#[from] LinkError),
    #[error("the lab server: {0}")]
    LabServer(#[from] ServerError),
    #[error("--perturb seeds a simulated run: it needs --speed and --http off")]
    Perturb,
    #[error(
        "the stall limit must be between {} and {} ms, got {} ms",
        MIN_STALL_LIMIT.as_millis(),
        MAX_STALL_LIMIT.as_millis(),
        .0.as_millis()
    )]
    StallLimit(Duration),
}

impl From<DeployError> for RunError {
    fn from(e: DeployError) -> RunError {
        match e {
            DeployError::Invalid(d) => RunError::Config(d),
            DeployError::Start(errors) => RunError::Start(errors),
            other => RunError::Deploy(other),
        }
    }
}

/// Loads the robot at `options.config_path`, starts every component, runs the
/// control loop until `shutdown` is requested or the duration passes, and
/// returns the run's report.
pub fn run(options: &RunOptions, shutdown: Shutdown) -> Result<Report, RunError> {
    if !(MIN_STALL_LIMIT..=MAX_STALL_LIMIT).contains(&options.stall_limit) {
        return Err(RunError::StallLimit(options.stall_limit));
    }
    if options.perturb.is_some() && (options.portal.is_some() || options.pace.is_none()) {
        return Err(RunError::Perturb);
    }
    if let Some(portal) = &options.portal {
        if let Some(path) = &options.task {
            return Err(RunError::Verdict {
                path: path.clone(),
                reason: "--task ends a run without the portal (--http off); with it, the lab ends each experiment by its task".into(),
            });
        }
        return run_with_portal(options, portal, shutdown);
    }
    let sandbox = options.sandbox()?;
    let mut loader = Loader::new(&sandbox);
    let config = config::load_with(&options.config_path, &mut loader, &options.overrides).map_err(RunError::Config)?;
    tracing::info!(
        "robot '{}' from {}: {} components, {} connections",
        config.name,
        config.path.display(),
        config.components.len(),
        config.connections.len()
    );
    let clock = options.clock();
    let criteria = read_criteria(options)?;
    let judge = options.verdict.is_some() || options.pace.is_some();
    let standings = Standings::default();
    // The simulated robots, by name: a camera (`sim:NAME`) looks at one.
    let mut services =
        Services::default().with(Arc::new(options.tls.clone())).with(Arc::new(crate::sim::SimRegistry::default()));
    if judge {
        services = services.with(Arc::new(standings.clone()));
    }
    if let Some(perturb) = options.perturb {
        tracing::info!("seeded timing: seed {} within {:?}", perturb.seed, perturb.bounds);
        services = services.with(Arc::new(perturb));
    }
    let mut graph =
        assemble::build(&config, &mut loader, clock.clone(), &shutdown.waker(), &services, &assemble::Carry::default())
            .map(|built| built.graph)
            .map_err(RunError::Start)?;
    if let Some(perturb) = &options.perturb {
        shift_tick_phases(&mut graph, perturb);
    }
    let ends = read_task(options)?.as_ref().and_then(EpisodeWatch::new).map(|w| EndWatch::new(w, shutdown.clone()));
    let watch = Judge { holders: judge.then(|| HolderWatch::new(&config, standings)), ends };
    let Some(record) = &options.record else {
        let (graph, watch, stopped_by, ran_ns) = run_control_thread(graph, clock, shutdown, options, watch)?;
        let report = final_report(&config, &graph, stopped_by, ran_ns);
        judge_run(options, &criteria, &config, &graph, &report, &watch)?;
        return Ok(report);
    };
    if let Some(address) = record.live {
        options.tls.check_plain("foxglove live view", address)?;
    }
    let recorder = Recorder::start(record, Layout::of(&config), Timeline::of(&clock))?;
    graph.set_tap(recorder.tap());
    let hook = recorder.hook(watch);
    let (mut graph, hook, stopped_by, ran_ns) = run_control_thread(graph, clock, shutdown, options, hook)?;
    graph.take_tap();
    let summary = recorder.finish()?;
    let report = final_report(&config, &graph, stopped_by, ran_ns);
    judge_run(options, &criteria, &config, &graph, &report, hook.inner())?;
    drop(graph);
    log_recording(&summary);
    Ok(report)
}

/// Each component's first tick a seeded fraction of its period late
/// (`sim::perturb`): the phase of its ticks against the simulator.
fn shift_tick_phases(graph: &mut Graph, perturb: &Perturbation) {
    for index in 0..graph.len() {
        let (Some(name), Some(period)) = (graph.name(index), graph.period_ns(index)) else { continue };
        let delay = perturb.first_tick_delay_ns(name, period);
        graph.delay_next_tick(index, delay);
    }
}

/// Who held control when, watched in runs that are judged (`--verdict`,
/// or any run on simulated time); the task's end conditions, with
/// `--task`.
struct Judge {
    holders: Option<HolderWatch>,
    ends: Option<EndWatch>,
}

impl CycleHook for Judge {
    fn between_cycles(&mut self, graph: &mut Graph, now_ns: u64) {
        if let Some(watch) = &mut self.holders {
            watch.between_cycles(graph, now_ns);
        }
        if let Some(ends) = &mut self.ends {
            ends.between_cycles(graph, now_ns);
        }
    }
}

/// The task of `--task`, if given.
fn read_task(options: &RunOptions) -> Result<Option<Task>, RunError> {
    let Some(path) = &options.task else { return Ok(None) };
    let bad = |reason: String| RunError::Verdict { path: path.clone(), reason };
    let text = std::fs::read(path).map_err(|e| bad(format!("cannot read the task: {e}")))?;
    serde_json::from_slice(&text).map(Some).map_err(|e| bad(format!("not the lab's task: {e}")))
}

/// The criteria of `--criteria`, else the lab's defaults.
fn read_criteria(options: &RunOptions) -> Result<Criteria, RunError> {
    let Some(path) = &options.criteria else { return Ok(Criteria::default()) };
    let bad = |reason: String| RunError::Verdict { path: path.clone(), reason };
    let text = std::fs::read(path).map_err(|e| bad(format!("cannot read the criteria: {e}")))?;
    serde_json::from_slice(&text).map_err(|e| bad(format!("not the lab's criteria: {e}")))
}

/// Judges a run that is judged (see [`Judge`]): prints the verdict, and
/// writes it to `--verdict`.
fn judge_run(
    options: &RunOptions,
    criteria: &Criteria,
    config: &RobotConfig,
    graph: &Graph,
    report: &Report,
    watch: &Judge,
) -> Result<(), RunError> {
    let Some(holders) = &watch.holders else { return Ok(()) };
    let path = options.verdict.clone().unwrap_or_default();
    let mut verdict = crate::lab::preflight::verdict(criteria, config, graph, report, holders.timeline().clone())
        .map_err(|e| RunError::Verdict { path: path.clone(), reason: e.to_string() })?;
    // With the task's end conditions: why the episode ended (a run stopped
    // otherwise, by a signal, ended for none of them).
    verdict.observed.ended_by = watch.ends.as_ref().and_then(|ends| {
        ends.ended().or((report.stopped_by == crate::report::StoppedBy::Duration).then_some(EpisodeEnd::TimeOut))
    });
    if verdict.passed {
        tracing::info!("preflight verdict: passed ({:.1} s simulated)", verdict.observed.simulated_s);
    } else {
        tracing::warn!("preflight verdict: refused\n  {}", verdict.reasons.join("\n  "));
    }
    if let Some(path) = &options.verdict {
        let bytes = serde_json::to_vec_pretty(&verdict)
            .map_err(|e| RunError::Verdict { path: path.clone(), reason: e.to_string() })?;
        crate::fsutil::write_atomically(path, &bytes)
            .map_err(|e| RunError::Verdict { path: path.clone(), reason: e.to_string() })?;
    }
    Ok(())
}

fn log_recording(summary: &RecordSummary) {
    let files: Vec<String> = summary.files.iter().map(|f| f.display().to_string()).collect();
    tracing::info!("recorded {} messages ({} bytes) to {}", summary.messages, summary.bytes, files.join(", "));
}

/// Runs the control loop on its own thread, with `hook` between cycles and
/// the stall watchdog beside it, until a shutdown or the duration; returns
/// the graph, the hook, why it stopped and how long it ran (ns).
fn run_control_thread<H: CycleHook + Send + 'static>(
    mut graph: Graph,
    clock: Clock,
    shutdown: Shutdown,
    options: &RunOptions,
    mut hook: H,
) -> Result<(Graph, H, StopReason, u64), RunError> {
    let until_ns = options.duration.map(|d| clock.now_ns().saturating_add(d.as_nanos() as u64));
    let heartbeat = match options.pace {
        Some(_) => Heartbeat::on_simulated_time(options.stall_limit),
        None => Heartbeat::new(options.stall_limit),
    };
    let watchdog = StallWatchdog::start(heartbeat.clone(), Box::new(|_| {}))
        .map_err(|e| RunError::ControlLoop(format!("cannot start the stall watchdog: {e}")))?;
    let injected = options.fault_injection;
    let control = options.control;
    if let Some(FaultInjection::PanicThread(after)) = injected {
        inject_thread_panic(after)?;
    }
    if let Some(pace) = clock.pace() {
        tracing::info!("simulated time: {pace}");
    }
    let control = std::thread::Builder::new()
        .name("subsume-control".into())
        .spawn(move || {
            let at = |after: Duration| clock.now_ns() + after.as_nanos() as u64;
            let fault = match injected {
                Some(FaultInjection::PanicControl(after)) => Some((at(after), false)),
                Some(FaultInjection::HangControl(after)) => Some((at(after), true)),
                _ => None,
            };
            // Settings the kernel refuses are said loudly; the loop runs
            // without them (the motors are as safe either way).
            let (applied, refused) = control.apply();
            if !applied.is_empty() {
                tracing::info!("control thread: {}", applied.join(", "));
            }
            for err in refused {
                tracing::error!("{err}; the control loop runs without it");
            }
            let mut cycle_hook = InjectFault { inner: &mut hook, fault };
            let stopped_by =
                control_loop::run_watched(&mut graph, &clock, &shutdown, until_ns, &mut cycle_hook, Some(&heartbeat));
            (graph, hook, stopped_by, clock.now_ns())
        })
        .map_err(|e| RunError::ControlLoop(e.to_string()))?;
    let joined = control.join().map_err(|_| RunError::ControlLoop("it panicked".into()));
    drop(watchdog);
    joined
}

/// The cycle hook, and the control thread's injected fault when it is due:
/// (when, whether it hangs rather than panics).
struct InjectFault<'a> {
    inner: &'a mut dyn CycleHook,
    fault: Option<(u64, bool)>,
}

impl CycleHook for InjectFault<'_> {
    fn between_cycles(&mut self, graph: &mut Graph, now_ns: u64) {
        match self.fault {
            Some((at, true)) if now_ns >= at => {
                tracing::warn!("fault injection: the control thread hangs");
                loop {
                    std::thread::sleep(Duration::from_secs(3600));
                }
            }
            Some((at, false)) if now_ns >= at => {
                #[allow(clippy::panic)] // The test-only fault injection: a real panic on the control thread.
                {
                    panic!("fault injection: the control thread panics");
                }
            }
            _ => {}
        }
        self.inner.between_cycles(graph, now_ns);
    }
}

/// Starts a thread outside the control loop that panics after `after`.
fn inject_thread_panic(after: Duration) -> Result<(), RunError> {
    std::thread::Builder::new()
        .name("fault-injection".into())
        .spawn(move || {
            std::thread::sleep(after);
            #[allow(clippy::panic)] // The test-only fault injection: a real panic outside the loop.
            {
                panic!("fault injection: a thread outside the control loop panics");
            }
        })
        .map(drop)
        .map_err(|e| RunError::ControlLoop(format!("cannot start the fault injection: {e}")))
}

/// Sends the final stop of every motor of this process at once (each
/// serial link's STOP frame, each ROS 2 `cmd_vel` publisher's zero Twist:
/// `runtime::halt`), without the control loop: for an exit that cannot wait
/// for it (a second signal). Each waits at most `robot::serial::HALT_WAIT`.
pub fn halt_every_motor() -> Vec<(String, StopOutcome)> {
    crate::runtime::halt::halt_all(HALT_WAIT)
}

/// The panic policy of `subsume run`, for the binary to install: a panic on
/// any thread first sends the final stop of every motor (`halt_every_motor`), then prints
/// the panic as Rust does, then ends the process with exit code 101. After
/// a panic the state of the run is unknown (a lock may be poisoned, a
/// thread the loop relies on gone), so the robot does not go on under it;
/// the run report is not written.
pub fn stop_motors_on_panic() {
    let previous = std::panic::take_hook();
    std::panic::set_hook(Box::new(move |info| {
        let outcomes = halt_every_motor();
        previous(info);
        for (label, outcome) in outcomes {
            eprintln!("after the panic, {label}: {outcome}");
        }
        eprintln!("error: a thread panicked; the motors were told to stop; exiting");
        std::process::exit(101);
    }));
}

fn final_report(config: &RobotConfig, graph: &Graph, stopped_by: StopReason, ran_ns: u64) -> Report {
    tracing::info!(
        "stopped ({}) after {:.2} s, {} messages routed",
        stopped_by.name(),
        ran_ns as f64 / 1e9,
        graph.messages_routed()
    );
    report::build(config, graph, stopped_by, ran_ns as f64 / 1e9)
}

/// A store with no users at start: makes the first admin and prints its
/// login on standard output, once (never into the log, which the portal
/// and recordings show), or says how to add a user.
fn first_user(store: &Store, what: &str, first: FirstUser, url: &str) {
    let hint = || {
        tracing::warn!(
            "the {what} has no users yet: add one with `subsume user add NAME --role admin --store {}`",
            store.root().display()
        );
    };
    if first == FirstUser::Hint {
        return hint();
    }
    match store.add_first_admin() {
        Ok(Some(password)) => println!(
            "\nfirst run: the store had no users, so subsume made one. Log in at\n\n    {url}\n    user {}  password {password}\n\n\
             The password is shown this once (the store keeps only a hash); `subsume user` adds users and sets passwords.\n",
            crate::store::FIRST_ADMIN
        ),
        Ok(None) => {}
        Err(e) => {
            tracing::error!("cannot make the first admin: {e}");
            hint();
        }
    }
}

/// What a portal serves from.
struct PortalParts {
    deployer: Arc<Deployer>,
    lab: Arc<Lab>,
    directory: Arc<Directory>,
    logs: Arc<LogRing>,
}

/// A portal being served on its own runtime.
struct ServedPortal {
    runtime: tokio::runtime::Runtime,
    scheme: &'static str,
    address: std::net::SocketAddr,
}

/// The folders no answer to a remote user shows: `hidden`, the compile
/// cache and the working folder.
fn answer_hidden(deployer: &Deployer, hidden: &[(&Path, &'static str)]) -> HiddenPaths {
    let working_dir = std::env::current_dir().unwrap_or_default();
    let mut all = hidden.to_vec();
    all.push((working_dir.as_path(), "<working folder>"));
    if let Some(cache) = deployer.sandbox.cache_dir() {
        all.push((cache, "<cache>"));
    }
    HiddenPaths::new(&all)
}

/// Serves `app` over `parts` on `listen` (TLS when the host has an
/// identity) on a runtime of its own. No answer shows a server path: the
/// `hidden` folders, the compile cache and the working folder are named,
/// never spelled out.
fn serve_portal(
    listen: std::net::SocketAddr,
    tls: &HostTls,
    hidden: &[(&Path, &'static str)],
    parts: PortalParts,
    app: fn(Arc<portal::PortalState>) -> axum::Router,
) -> Result<ServedPortal, RunError> {
    let listener = crate::admission::listen(listen).map_err(|source| RunError::Listen { address: listen, source })?;
    let address = listener.local_addr().map_err(|source| RunError::Listen { address: listen, source })?;
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .thread_name("portal")
        .enable_all()
        .build()
        .map_err(RunError::PortalRuntime)?;
    let acceptor = tls.identity.as_ref().map(|identity| identity.http_acceptor());
    let hidden = answer_hidden(&parts.deployer, hidden);
    let PortalParts { deployer, lab, directory, logs } = parts;
    let state = match acceptor {
        Some(_) => portal::PortalState::over_tls(deployer, lab, directory, logs),
        None => portal::PortalState::new(deployer, lab, directory, logs),
    }
    .hiding(hidden);
    let scheme = if acceptor.is_some() { "https" } else { "http" };
    runtime.spawn(async move {
        let listener = match tokio::net::TcpListener::from_std(listener) {
            Ok(listener) => listener,
            Err(e) => return tracing::error!("the portal cannot serve: {e}"),
        };
        crate::admission::serve_http(listener, acceptor, app(state), crate::admission::HttpLimits::default()).await;
    });
    Ok(ServedPortal { runtime, scheme, address })
}

/// [`run`] with the portal: starts from the store (see
/// [`Deployer::boot`]), serves the portal on its own runtime, and lets it
/// activate sets while the control loop runs.
fn run_with_portal(options: &RunOptions, portal: &PortalOptions, shutdown: Shutdown) -> Result<Report, RunError> {
    let sandbox = Arc::new(options.sandbox()?);
    let store = Arc::new(Store::open(&portal.store_dir)?);
    let directory = Arc::new(Directory::new(store.users().clone()));
    let no_users = directory.users.all().map_err(StoreError::from)?.is_empty();
    let first_store = store.clone();
    if options.tls.identity.is_none() {
        options.tls.check_plain("portal", portal.listen)?;
    }
    // One of each for every set this host runs: a network platform carried
    // across an activation reads the new set's robot name and arbiter.
    let services = Services::default()
        .with(directory.clone())
        .with(Arc::new(TeleopServers::default()))
        .with(Arc::new(RunningRobot::default()))
        .with(Arc::new(Standings::default()))
        .with(Arc::new(crate::sim::SimRegistry::default()))
        // The cameras' newest frames, for the portal's live view.
        .with(Arc::new(crate::camera::live::LiveCameras::default()))
        .with(Arc::new(Locks::with_waker(shutdown.waker())))
        .with(Arc::new(options.tls.clone()));
    let clock = options.clock();
    // Recordings started from the portal, in the store's folder; none while
    // --record or --foxglove holds the graph's one tap.
    let recordings = Arc::new(Recordings::new(
        store.root().join("recordings"),
        portal.record_max_file_bytes,
        Timeline::of(&clock),
        options.record.is_some(),
    )?);
    let services = services.with(recordings.clone());
    let boot = Deployer::boot(BootOptions {
        store,
        sandbox,
        services,
        config_path: &options.config_path,
        overrides: options.overrides.clone(),
        clock: clock.clone(),
        waker: shutdown.waker(),
    })?;
    let deploy::Boot { deployer, graph, hook } = boot;
    let exe = std::env::current_exe().map_err(|e| RunError::ControlLoop(format!("cannot find this program: {e}")))?;
    let role = match &portal.lab {
        Some(link) => LabRole::Joined { lab: link.key.lab().to_string() },
        None => LabRole::Alone,
    };
    let lab = Lab::start(
        deployer.clone(),
        LabOptions {
            preflight: PreflightCommand {
                exe,
                cache_dir: options.cache_dir.clone(),
                priority: portal.preflight_priority,
                limits: PreflightLimits::default(),
            },
            role,
        },
    )?;
    let robot_dir = options.config_path.parent().map(Path::to_path_buf).unwrap_or_default();
    let hidden = [(portal.store_dir.as_path(), "<store>"), (robot_dir.as_path(), "<robot file folder>")];
    // The robot's live status reaches the lab's users through the lab
    // server: it hides the robot's folders as the robot's own portal does.
    // So does every recording the portal or the lab starts: each is
    // downloaded by a remote user (a results bundle's run.mcap).
    recordings.hide(answer_hidden(&deployer, &hidden));
    let link =
        portal.lab.clone().map(|o| RobotLink::start(lab.clone(), o, answer_hidden(&deployer, &hidden))).transpose()?;
    if let Some(poll) = portal.watch {
        deploy::dev::watch(&deployer, options.config_path.clone(), poll).map_err(RunError::Watch)?;
    }
    let served = serve_portal(
        portal.listen,
        &options.tls,
        &hidden,
        PortalParts { deployer, lab: lab.clone(), directory, logs: portal.logs.clone() },
        portal::app,
    )?;
    let (runtime, scheme, address) = (served.runtime, served.scheme, served.address);
    // Before the portal's line: whoever waits for that line has the login.
    if no_users {
        first_user(&first_store, "portal", portal.first_user, &format!("{scheme}://{address}/"));
    }
    tracing::info!("portal on {scheme}://{address}/ (store {})", portal.store_dir.display());
    let Some(record) = &options.record else {
        let hook = recordings.hook(hook, |hook| Layout::of(hook.config()), deploy::ControlHook::swaps);
        let (graph, hook, stopped_by, ran_ns) = run_control_thread(graph, clock, shutdown, options, hook)?;
        runtime.shutdown_timeout(Duration::from_secs(1));
        // A recording started from the portal ends cleanly with the run.
        match recordings.finish() {
            Some(Ok(stopped)) => tracing::info!(
                "recording {} stopped with the run: {} messages, {} bytes",
                stopped.name,
                stopped.messages,
                stopped.bytes
            ),
            Some(Err(e)) => tracing::error!("the portal's recording did not finish cleanly: {e}"),
            None => {}
        }
        let report = final_report(hook.inner().config(), &graph, stopped_by, ran_ns);
        if let Some(link) = &link {
            link.shut_down();
        }
        lab.shut_down(Some(&report));
        return Ok(report);
    };
    let mut graph = graph;
    if let Some(address) = record.live {
        options.tls.check_plain("foxglove live view", address)?;
    }
    let recorder = Recorder::start(record, Layout::of(hook.config()), Timeline::of(&clock))?;
    graph.set_tap(recorder.tap());
    let hook = recorder.swapping_hook(hook, |hook| Layout::of(hook.config()));
    let (mut graph, hook, stopped_by, ran_ns) = run_control_thread(graph, clock, shutdown, options, hook)?;
    runtime.shutdown_timeout(Duration::from_secs(1));
    graph.take_tap();
    let summary = recorder.finish()?;
    let report = final_report(hook.inner().config(), &graph, stopped_by, ran_ns);
    if let Some(link) = &link {
        link.shut_down();
    }
    lab.shut_down(Some(&report));
    log_recording(&summary);
    Ok(report)
}

/// `subsume lab serve` (docs/lab.md, "Several robots"): a lab server with
/// no robot: its store (users, uploads, sets, experiments), the preflights,
/// the dispatcher over the lab's Zenoh session, and its portal; until
/// `shutdown`.
pub fn serve_lab(options: &LabServeOptions, shutdown: Shutdown) -> Result<(), RunError> {
    let sandbox = Arc::new(Sandbox::new(options.cache_dir.clone())?);
    let store = Arc::new(Store::open(&options.store_dir)?);
    let directory = Arc::new(Directory::new(store.users().clone()));
    let no_users = directory.users.all().map_err(StoreError::from)?.is_empty();
    if options.tls.identity.is_none() {
        options.tls.check_plain("lab portal", options.listen)?;
    }
    let services = Services::default().with(directory.clone()).with(Arc::new(options.tls.clone()));
    let deployer = Deployer::headless(store.clone(), sandbox, services);
    let fleet = Fleet::start(store.clone(), options.fleet.clone())?;
    let exe = std::env::current_exe().map_err(|e| RunError::ControlLoop(format!("cannot find this program: {e}")))?;
    let lab = Lab::start(
        deployer.clone(),
        LabOptions {
            preflight: PreflightCommand {
                exe,
                cache_dir: options.cache_dir.clone(),
                priority: options.preflight_priority,
                limits: PreflightLimits::default(),
            },
            role: LabRole::Server(fleet.clone()),
        },
    )?;
    let served = serve_portal(
        options.listen,
        &options.tls,
        &[(options.store_dir.as_path(), "<store>")],
        PortalParts { deployer, lab: lab.clone(), directory, logs: options.logs.clone() },
        portal::lab_server_app,
    )?;
    let (runtime, scheme, address) = (served.runtime, served.scheme, served.address);
    // Before the server's line: whoever waits for that line has the login.
    if no_users {
        first_user(&store, "lab", options.first_user, &format!("{scheme}://{address}/"));
    }
    tracing::info!(
        "lab server '{}' on {scheme}://{address}/ (store {})",
        fleet.lab_name(),
        options.store_dir.display()
    );
    while !shutdown.wait(Duration::from_secs(1)) {}
    runtime.shutdown_timeout(Duration::from_secs(1));
    lab.shut_down(None);
    fleet.shut_down();
    Ok(())
}
