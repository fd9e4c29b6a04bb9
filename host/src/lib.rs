//! subsume: a host that runs robot software as sandboxed WebAssembly
//! components, wired from an XML robot description.
//!
//! The binary (`main.rs`) parses the command line and calls [`run`]; see
//! `ARCHITECTURE.md` for the map of the modules below.

pub mod arbiter;
pub mod builtin;
pub mod config;
pub mod contract;
pub mod deploy;
pub mod fsutil;
pub mod loader;
pub mod mode;
pub mod net;
pub mod portal;
pub mod preamble;
pub mod report;
pub mod robot;
pub mod runtime;
pub mod sandbox;
pub mod scaffold;
pub mod sim;
pub mod store;
pub mod teleop_client;
pub mod users;

use std::collections::HashMap;
use std::path::PathBuf;
use std::time::Duration;

use thiserror::Error;

use crate::arbiter::PriorityCell;
use crate::builtin::{BuildContext, Services};
use crate::config::{ComponentConfig, ComponentSource, Diagnostics, RobotConfig};
use crate::loader::Loader;
use crate::report::Report;
use crate::runtime::control_loop::{self, Clock, Shutdown, Waker};
use crate::runtime::{Component, Graph};
use crate::sandbox::{Sandbox, SandboxError};

/// What `subsume run` was asked to do.
#[derive(Clone, Debug)]
pub struct RunOptions {
    pub config_path: PathBuf,
    /// Stop after this long; run until shutdown when `None`.
    pub duration: Option<Duration>,
    /// Where compiled components are cached; no cache when `None`.
    pub cache_dir: Option<PathBuf>,
    /// Parameters set on the command line.
    pub overrides: Vec<config::ParamOverride>,
    /// Serve the portal and run from the store; `None`: run the file alone.
    pub portal: Option<PortalOptions>,
}

/// Where the portal listens and where its store lives.
#[derive(Clone, Debug)]
pub struct PortalOptions {
    pub listen: std::net::SocketAddr,
    pub store_dir: PathBuf,
    /// Recent log lines (fed by the binary's `tracing` subscriber).
    pub logs: std::sync::Arc<portal::logs::LogRing>,
}

#[derive(Debug, Error)]
pub enum RunError {
    #[error("{0}")]
    Config(Diagnostics),
    #[error(transparent)]
    Sandbox(#[from] SandboxError),
    #[error("{}", .0.join("\n"))]
    Start(Vec<String>),
    #[error("the control loop thread failed: {0}")]
    ControlLoop(String),
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
    let graph = build_graph(&config, &mut loader, clock, &shutdown.waker()).map_err(RunError::Start)?;
    let (graph, _, stopped_by, ran_ns) =
        run_control_thread(graph, clock, shutdown, options.duration, control_loop::NoHook)?;
    Ok(final_report(&config, &graph, stopped_by, ran_ns))
}

/// Runs the control loop on its own thread, with `hook` between cycles,
/// until a shutdown or `duration`; returns the graph, the hook, why it
/// stopped and how long it ran (ns).
fn run_control_thread<H: control_loop::CycleHook + Send + 'static>(
    mut graph: Graph,
    clock: Clock,
    shutdown: Shutdown,
    duration: Option<Duration>,
    mut hook: H,
) -> Result<(Graph, H, control_loop::StopReason, u64), RunError> {
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

fn final_report(config: &RobotConfig, graph: &Graph, stopped_by: control_loop::StopReason, ran_ns: u64) -> Report {
    tracing::info!(
        "stopped ({}) after {:.2} s, {} messages routed",
        stopped_by.name(),
        ran_ns as f64 / 1e9,
        graph.messages_routed()
    );
    report::build(config, graph, stopped_by, ran_ns as f64 / 1e9)
}

/// [`run`] with the portal: starts from the store (see `deploy::Runner::boot`),
/// serves the portal on its own runtime, and lets it activate sets while
/// the control loop runs.
fn run_with_portal(options: &RunOptions, portal: &PortalOptions, shutdown: Shutdown) -> Result<Report, RunError> {
    use std::sync::Arc;
    let sandbox = Arc::new(Sandbox::new(options.cache_dir.clone())?);
    let store = Arc::new(store::Store::open(&portal.store_dir).map_err(|e| RunError::Start(vec![e.to_string()]))?);
    let directory = Arc::new(users::Directory::new(users::Users::new(store.users_path())));
    match directory.users.all() {
        Ok(users) if users.is_empty() => tracing::warn!(
            "the portal has no users yet: add one with `subsume user add NAME --role admin --store {}`",
            store.root().display()
        ),
        Ok(_) => {}
        Err(e) => return Err(RunError::Start(vec![e.to_string()])),
    }
    let services = Services { directory: Some(directory.clone()), teleop_servers: Default::default() };
    let clock = Clock::new();
    let boot = deploy::Runner::boot(deploy::BootOptions {
        store,
        sandbox,
        services,
        config_path: &options.config_path,
        overrides: options.overrides.clone(),
        clock,
        waker: shutdown.waker(),
    })
    .map_err(|e| match e {
        deploy::DeployError::Invalid(d) => RunError::Config(d),
        deploy::DeployError::Start(errors) => RunError::Start(errors),
        other => RunError::Start(vec![other.to_string()]),
    })?;
    let deploy::Boot { runner, graph, hook } = boot;
    let listener = std::net::TcpListener::bind(portal.listen)
        .map_err(|e| RunError::Start(vec![format!("the portal cannot listen on {}: {e}", portal.listen)]))?;
    let address = listener.local_addr().map_err(|e| RunError::Start(vec![e.to_string()]))?;
    listener.set_nonblocking(true).map_err(|e| RunError::Start(vec![e.to_string()]))?;
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .thread_name("portal")
        .enable_all()
        .build()
        .map_err(|e| RunError::Start(vec![format!("cannot start the portal runtime: {e}")]))?;
    let state = portal::PortalState::new(runner.clone(), directory, portal.logs.clone());
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

/// Instantiates and initialises every component of `config` and wires them.
/// Component `i` of the graph is component `i` of the config. Simulated
/// robots are built first, so serial links can open their pseudo-terminals.
/// Every component that fails to start is reported.
pub fn build_graph(
    config: &RobotConfig,
    loader: &mut Loader<'_>,
    clock: Clock,
    waker: &Waker,
) -> Result<Graph, Vec<String>> {
    build(config, loader, clock, waker, &Services::default(), &Carry::default()).map(|built| built.graph)
}

/// Components a new graph takes over from the running one instead of
/// building them (see `deploy`): their graph slots hold [`runtime::Vacant`]
/// until the swap moves the running instances in.
#[derive(Clone, Debug, Default)]
pub struct Carry {
    /// New index -> the running component's priority cell.
    pub priorities: HashMap<usize, PriorityCell>,
    /// PTYs of carried simulated robots, by component name.
    pub sim_ptys: HashMap<String, PathBuf>,
}

/// A graph with what a later activation needs to carry its parts over.
pub struct Built {
    pub graph: Graph,
    pub priorities: Vec<PriorityCell>,
    pub sim_ptys: HashMap<String, PathBuf>,
}

/// [`build_graph`] with the host's shared services, building every
/// component but the carried ones.
pub fn build(
    config: &RobotConfig,
    loader: &mut Loader<'_>,
    clock: Clock,
    waker: &Waker,
    services: &Services,
    carry: &Carry,
) -> Result<Built, Vec<String>> {
    let start_ns = clock.now_ns();
    let mut sim_ptys = carry.sim_ptys.clone();
    let priorities: Vec<PriorityCell> = config
        .components
        .iter()
        .enumerate()
        .map(|(i, c)| carry.priorities.get(&i).cloned().unwrap_or_else(|| PriorityCell::new(c.priority.unwrap_or(0))))
        .collect();
    let mut built: Vec<Option<Box<dyn Component>>> = (0..config.components.len()).map(|_| None).collect();
    let mut errors = Vec::new();
    let is_sim = |c: &ComponentConfig| c.source == ComponentSource::Builtin("sim".into());
    let order = (0..config.components.len())
        .filter(|&i| is_sim(&config.components[i]))
        .chain((0..config.components.len()).filter(|&i| !is_sim(&config.components[i])));
    for index in order {
        let component = &config.components[index];
        if carry.priorities.contains_key(&index) {
            built[index] = Some(Box::new(runtime::Vacant));
            continue;
        }
        let mut ctx = BuildContext {
            robot: config,
            index,
            sim_ptys: &mut sim_ptys,
            priorities: &priorities,
            clock,
            waker: waker.clone(),
            services: services.clone(),
        };
        match loader.instantiate(&mut ctx) {
            Ok(instance) => built[index] = Some(instance),
            Err(why) => errors.push(format!("failed to start component '{}': {why}", component.name)),
        }
    }
    if !errors.is_empty() {
        return Err(errors);
    }
    let mut graph = Graph::new();
    for (index, (component, instance)) in config.components.iter().zip(built).enumerate() {
        let Some(instance) = instance else { continue };
        let d = &component.description;
        let how = if carry.priorities.contains_key(&index) { "kept running" } else { "started" };
        tracing::info!(
            component = %component.name,
            "{how} {} {} from {} ({} in, {} out, {} Hz{})",
            d.name,
            d.version,
            component.source,
            d.inputs.len(),
            d.outputs.len(),
            component.rate_hz,
            component.priority.map(|p| format!(", priority {p}")).unwrap_or_default()
        );
        let index = graph.add(&component.name, instance, d.outputs.len(), component.rate_hz, start_ns);
        if let (Some(policy), Some(restarter)) = (component.restart, loader.restarter(component)) {
            graph.set_restart(index, policy, restarter);
        }
    }
    for c in &config.connections {
        graph.connect(c.from.component, c.from.port, c.to.component, c.to.port, c.policy);
    }
    Ok(Built { graph, priorities, sim_ptys })
}
