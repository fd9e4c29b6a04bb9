//! The composition root of `subsume run`: starts the sandbox, the store and
//! the portal's runtime when asked, assembles the robot, runs the control
//! loop on its own thread until a shutdown or the duration, and returns the
//! final report. Nothing but `main.rs`, tests and benches imports this.

use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

use thiserror::Error;

use crate::assemble::{self, Loader, StartError};
use crate::builtin::Services;
use crate::config::{self, Diagnostics, ParamOverride, RobotConfig};
use crate::deploy::{self, BootOptions, DeployError, Deployer};
use crate::portal::{self, logs::LogRing};
use crate::report::{self, Report};
use crate::runtime::Graph;
use crate::runtime::control_loop::{self, Clock, CycleHook, Shutdown, StopReason};
use crate::sandbox::{Sandbox, SandboxError};
use crate::store::users::Directory;
use crate::store::{Store, StoreError};
use crate::teleop::TeleopServers;

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
}

/// Where the portal listens and where its store lives.
#[derive(Clone, Debug)]
pub struct PortalOptions {
    pub listen: std::net::SocketAddr,
    pub store_dir: PathBuf,
    /// Recent log lines (fed by the binary's `tracing` subscriber).
    pub logs: Arc<LogRing>,
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
    #[error("the portal cannot listen on {address}: {source}")]
    Listen {
        address: std::net::SocketAddr,
        #[source]
        source: std::io::Error,
    },
    #[error("cannot start the portal runtime: {0}")]
    PortalRuntime(#[source] std::io::Error),
    #[error("the control loop thread failed: {0}")]
    ControlLoop(String),
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
    if let Some(portal) = &options.portal {
        return run_with_portal(options, portal, shutdown);
    }
    let sandbox = Sandbox::new(options.cache_dir.clone())?;
    let mut loader = Loader::new(&sandbox);
    let config = config::load_with(&options.config_path, &mut loader, &options.overrides).map_err(RunError::Config)?;
    tracing::info!(
        "robot '{}' from {}: {} components, {} connections",
        config.name,
        config.path.display(),
        config.components.len(),
        config.connections.len()
    );
    let clock = Clock::new();
    let graph = assemble::build_graph(&config, &mut loader, clock, &shutdown.waker()).map_err(RunError::Start)?;
    let (graph, _, stopped_by, ran_ns) =
        run_control_thread(graph, clock, shutdown, options.duration, control_loop::NoHook)?;
    Ok(final_report(&config, &graph, stopped_by, ran_ns))
}

/// Runs the control loop on its own thread, with `hook` between cycles,
/// until a shutdown or `duration`; returns the graph, the hook, why it
/// stopped and how long it ran (ns).
fn run_control_thread<H: CycleHook + Send + 'static>(
    mut graph: Graph,
    clock: Clock,
    shutdown: Shutdown,
    duration: Option<Duration>,
    mut hook: H,
) -> Result<(Graph, H, StopReason, u64), RunError> {
    let until_ns = duration.map(|d| clock.now_ns().saturating_add(d.as_nanos() as u64));
    let control = std::thread::Builder::new()
        .name("subsume-control".into())
        .spawn(move || {
            let stopped_by = control_loop::run_with(&mut graph, &clock, &shutdown, until_ns, &mut hook);
            (graph, hook, stopped_by, clock.now_ns())
        })
        .map_err(|e| RunError::ControlLoop(e.to_string()))?;
    control.join().map_err(|_| RunError::ControlLoop("it panicked".into()))
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

/// [`run`] with the portal: starts from the store (see
/// [`Deployer::boot`]), serves the portal on its own runtime, and lets it
/// activate sets while the control loop runs.
fn run_with_portal(options: &RunOptions, portal: &PortalOptions, shutdown: Shutdown) -> Result<Report, RunError> {
    let sandbox = Arc::new(Sandbox::new(options.cache_dir.clone())?);
    let store = Arc::new(Store::open(&portal.store_dir)?);
    let directory = Arc::new(Directory::new(store.users().clone()));
    match directory.users.all() {
        Ok(users) if users.is_empty() => tracing::warn!(
            "the portal has no users yet: add one with `subsume user add NAME --role admin --store {}`",
            store.root().display()
        ),
        Ok(_) => {}
        Err(e) => return Err(StoreError::from(e).into()),
    }
    let services = Services::default().with(directory.clone()).with(Arc::new(TeleopServers::default()));
    let clock = Clock::new();
    let boot = Deployer::boot(BootOptions {
        store,
        sandbox,
        services,
        config_path: &options.config_path,
        overrides: options.overrides.clone(),
        clock,
        waker: shutdown.waker(),
    })?;
    let deploy::Boot { deployer, graph, hook } = boot;
    let listener = std::net::TcpListener::bind(portal.listen)
        .and_then(|l| l.set_nonblocking(true).map(|()| l))
        .map_err(|source| RunError::Listen { address: portal.listen, source })?;
    let address = listener.local_addr().map_err(|source| RunError::Listen { address: portal.listen, source })?;
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .thread_name("portal")
        .enable_all()
        .build()
        .map_err(RunError::PortalRuntime)?;
    let state = portal::PortalState::new(deployer, directory, portal.logs.clone());
    runtime.spawn(async move {
        match tokio::net::TcpListener::from_std(listener) {
            Ok(listener) => {
                let app = portal::app(state).into_make_service_with_connect_info::<std::net::SocketAddr>();
                if let Err(e) = axum::serve(listener, app).await {
                    tracing::error!("the portal stopped: {e}");
                }
            }
            Err(e) => tracing::error!("the portal cannot serve: {e}"),
        }
    });
    tracing::info!("portal on http://{address}/ (store {})", portal.store_dir.display());
    let (graph, hook, stopped_by, ran_ns) = run_control_thread(graph, clock, shutdown, options.duration, hook)?;
    runtime.shutdown_timeout(Duration::from_secs(1));
    Ok(final_report(hook.config(), &graph, stopped_by, ran_ns))
}
