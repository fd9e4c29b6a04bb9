//! Assembly: a validated [`RobotConfig`] and a [`Loader`] -> a wired
//! [`Graph`], and what an activation carries over from the running graph.
//!
//! Invariants: component `i` of the graph is component `i` of the config;
//! simulated robots are built first, so serial links can open their
//! pseudo-terminals; every component that fails to start is reported and
//! no graph is returned; carried components hold [`Vacant`] until the swap
//! moves the running instances in.

pub mod loader;
pub mod registry;

use std::collections::HashMap;
use std::path::PathBuf;
use std::sync::Arc;

pub use self::loader::{Loader, StartError, Surroundings};
use crate::builtin::Services;
use crate::config::{ComponentConfig, ComponentSource, RobotConfig};
use crate::runtime::control_loop::{Clock, Waker};
use crate::runtime::{Component, Convert, Graph, Locks, PriorityCell, RunningRobot, Standings, Vacant};

/// Components a new graph takes over from the running one instead of
/// building them: their graph slots hold [`Vacant`] until the swap moves
/// the running instances in.
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

/// Instantiates and initialises every component of `config` and wires them.
pub fn build_graph(
    config: &RobotConfig,
    loader: &mut Loader<'_>,
    clock: Clock,
    waker: &Waker,
) -> Result<Graph, Vec<StartError>> {
    build(config, loader, clock, waker, &Services::default(), &Carry::default()).map(|built| built.graph)
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
) -> Result<Built, Vec<StartError>> {
    let start_ns = clock.now_ns();
    let services = &with_graph_services(services, config, waker);
    let mut ptys = carry.sim_ptys.clone();
    let priorities: Vec<PriorityCell> = config
        .components
        .iter()
        .enumerate()
        .map(|(i, c)| carry.priorities.get(&i).cloned().unwrap_or_else(|| PriorityCell::new(c.priority.unwrap_or(0))))
        .collect();
    let mut built: Vec<Option<Box<dyn Component>>> = (0..config.components.len()).map(|_| None).collect();
    let mut errors = Vec::new();
    let first =
        |c: &ComponentConfig| matches!(&c.source, ComponentSource::Builtin(k) if registry::builtin(*k).built_first());
    let order = (0..config.components.len())
        .filter(|&i| first(&config.components[i]))
        .chain((0..config.components.len()).filter(|&i| !first(&config.components[i])));
    for index in order {
        if carry.priorities.contains_key(&index) {
            built[index] = Some(Box::new(Vacant));
            continue;
        }
        let around = Surroundings {
            robot: config,
            ptys: &mut ptys,
            priorities: &priorities,
            clock: clock.clone(),
            waker: waker.clone(),
            services,
        };
        match loader.instantiate(index, around) {
            Ok(instance) => built[index] = Some(instance),
            Err(e) => errors.push(e),
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
        let kind = |component: usize, port: u32, outputs: bool| {
            config.components.get(component).and_then(|comp| {
                let ports = if outputs { &comp.description.outputs } else { &comp.description.inputs };
                ports.get(port as usize).map(|p| p.kind)
            })
        };
        let convert = match (kind(c.from.component, c.from.port, true), kind(c.to.component, c.to.port, false)) {
            (Some(from), Some(to)) => Convert::between(from, to),
            _ => Convert::Nothing,
        };
        graph.connect_converting(c.from.component, c.from.port, c.to.component, c.to.port, c.policy, convert);
    }
    Ok(Built { graph, priorities, sim_ptys: ptys })
}

/// `services`, plus what the components of one graph share when the host
/// did not provide it for all its graphs: the standings of the motion
/// sources and the running robot's name.
fn with_graph_services(services: &Services, config: &RobotConfig, waker: &Waker) -> Services {
    let mut services = services.clone();
    if services.get::<Locks>().is_none() {
        // Without a host-wide board, the graph's arbiter and network
        // platform share one of their own.
        services = services.with(Arc::new(Locks::with_waker(waker.clone())));
    }
    if services.get::<Standings>().is_none() {
        services = services.with(Arc::new(Standings::default()));
    }
    if services.get::<RunningRobot>().is_none() {
        services = services.with(Arc::new(RunningRobot::new(&config.name)));
    }
    services
}

/// What identifies a running instance: everything but its place in the file.
pub fn instance_key(c: &ComponentConfig) -> String {
    format!(
        "{}|{}|{}|{:?}|{:?}|{:?}|{}|{}|{}|{}|{:?}|{:?}",
        c.name,
        c.source,
        c.rate_hz,
        c.priority,
        c.budget,
        c.timeout,
        c.memory_bytes,
        c.max_emits,
        c.max_message_bytes,
        c.max_logs_per_s,
        c.restart,
        c.params.iter().map(|p| (&p.name, &p.value)).collect::<Vec<_>>()
    )
}

/// (old index, new index) of the built-ins `new` takes over from `old`:
/// the unchanged ones that own something outside the host.
pub fn carry_plan(old: &RobotConfig, new: &RobotConfig) -> Vec<(usize, usize)> {
    plan_carrying(old, new, false)
}

/// [`carry_plan`] with every simulated robot of `new` built afresh (at its
/// world's start, time 0, on a new PTY), and so the serial links on its
/// PTY too: nothing the robot said before reaches the new graph (a lab
/// run's first pose is its start, not where the robot was before it).
pub fn carry_plan_fresh_simulators(old: &RobotConfig, new: &RobotConfig) -> Vec<(usize, usize)> {
    plan_carrying(old, new, true)
}

fn plan_carrying(old: &RobotConfig, new: &RobotConfig, fresh_simulators: bool) -> Vec<(usize, usize)> {
    let sim = registry::kind_of(&crate::sim::builtin::SimBuiltin);
    let carried_kind = |c: &ComponentConfig| {
        matches!(&c.source, ComponentSource::Builtin(k)
            if registry::builtin(*k).carried() && !(fresh_simulators && Some(*k) == sim))
    };
    let mut pairs: Vec<(usize, usize)> = new
        .components
        .iter()
        .enumerate()
        .filter(|(_, c)| carried_kind(c))
        .filter_map(|(n, c)| {
            let o = old.components.iter().position(|o| instance_key(o) == instance_key(c))?;
            Some((o, n))
        })
        .collect();
    // A serial link on a simulated robot's PTY is carried only with it.
    let carried_names: Vec<String> = pairs.iter().map(|&(_, n)| new.components[n].name.clone()).collect();
    pairs.retain(|&(_, n)| {
        let c = &new.components[n];
        let device = c.params.iter().find(|p| p.name == "device").map(|p| p.value.trim().to_string());
        match device.as_deref().and_then(|d| d.strip_prefix("sim:")) {
            Some(sim) => carried_names.iter().any(|name| name == sim),
            None => true,
        }
    });
    pairs
}
