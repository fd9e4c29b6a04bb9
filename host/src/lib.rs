//! subsume: a host that runs robot software as sandboxed WebAssembly
//! components, wired from an XML robot description.
//!
//! The binary (`main.rs`) parses the command line and calls [`run`]; see
//! `ARCHITECTURE.md` for the map of the modules below.

pub mod arbiter;
pub mod builtin;
pub mod config;
pub mod contract;
pub mod fsutil;
pub mod loader;
pub mod mode;
pub mod net;
pub mod preamble;
pub mod report;
pub mod robot;
pub mod runtime;
pub mod sandbox;
pub mod sim;
pub mod teleop_client;

use std::collections::HashMap;
use std::path::PathBuf;
use std::time::Duration;

use thiserror::Error;

use crate::arbiter::PriorityCell;
use crate::builtin::BuildContext;
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
    let mut graph = build_graph(&config, &mut loader, clock, &shutdown.waker()).map_err(RunError::Start)?;
    let until_ns = options.duration.map(|d| clock.now_ns().saturating_add(d.as_nanos() as u64));
    let control = std::thread::Builder::new()
        .name("subsume-control".into())
        .spawn(move || {
            let stopped_by = control_loop::run(&mut graph, &clock, &shutdown, until_ns);
            (graph, stopped_by, clock.now_ns())
        })
        .map_err(|e| RunError::ControlLoop(e.to_string()))?;
    let (graph, stopped_by, ran_ns) = control.join().map_err(|_| RunError::ControlLoop("it panicked".into()))?;
    tracing::info!(
        "stopped ({}) after {:.2} s, {} messages routed",
        stopped_by.name(),
        ran_ns as f64 / 1e9,
        graph.messages_routed()
    );
    Ok(report::build(&config, &graph, stopped_by, ran_ns as f64 / 1e9))
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
    let start_ns = clock.now_ns();
    let mut sim_ptys = HashMap::new();
    let priorities: Vec<PriorityCell> =
        config.components.iter().map(|c| PriorityCell::new(c.priority.unwrap_or(0))).collect();
    let mut built: Vec<Option<Box<dyn Component>>> = (0..config.components.len()).map(|_| None).collect();
    let mut errors = Vec::new();
    let is_sim = |c: &ComponentConfig| c.source == ComponentSource::Builtin("sim".into());
    let order = (0..config.components.len())
        .filter(|&i| is_sim(&config.components[i]))
        .chain((0..config.components.len()).filter(|&i| !is_sim(&config.components[i])));
    for index in order {
        let component = &config.components[index];
        let mut ctx = BuildContext {
            robot: config,
            index,
            sim_ptys: &mut sim_ptys,
            priorities: &priorities,
            clock,
            waker: waker.clone(),
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
    for (component, instance) in config.components.iter().zip(built) {
        let Some(instance) = instance else { continue };
        let d = &component.description;
        tracing::info!(
            component = %component.name,
            "started {} {} from {} ({} in, {} out, {} Hz{})",
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
    Ok(graph)
}
