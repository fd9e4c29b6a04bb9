//! The JSON run report written by `subsume run --report FILE` (documented in
//! `docs/report.md`), and the live status the portal shows while a set runs
//! (the same layout, `stopped_by: "running"`, with the active set's id).
//! Built-ins add their own sections (`Component::status`).

use std::sync::Arc;

use serde::Serialize;
use serde::ser::SerializeMap as _;

use crate::config::{Policy, RobotConfig};
use crate::runtime::control_loop::StopReason;
use crate::runtime::{ComponentState, Graph, Histogram, StatusSection};

/// Version of the report's layout; bumped when a field changes meaning.
/// 2: the network platform's section is `teleop` (was `network`); states
/// are closed sets (`stopped_by`, a component's `state`, a connection's
/// `policy`).
pub const REPORT_FORMAT: u32 = 2;

/// Why the report was written: what stopped the run, or `running` in the
/// live status.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, schemars::JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum StoppedBy {
    /// `--duration` passed.
    Duration,
    /// A signal or the portal asked to stop.
    Shutdown,
    /// Not stopped: the live status.
    Running,
    /// An experiment's run ended (its record says why: docs/lab.md).
    Experiment,
}

/// A component's state.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, schemars::JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum ComponentRunState {
    Running,
    Faulted,
}

/// A connection's delivery policy.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, schemars::JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum PolicyName {
    Latest,
    Queue,
}

/// One built-in's section, with the component it belongs to.
#[derive(Clone, Debug)]
pub struct Section {
    /// Its key in the JSON: the section's name, or `NAME:COMPONENT` when
    /// two components have a section of that name.
    pub key: String,
    pub component: String,
    pub status: Arc<dyn StatusSection>,
}

/// The built-ins' sections, typed; in the JSON each is a field of the
/// report under its key.
#[derive(Clone, Debug, Default)]
pub struct Sections(pub Vec<Section>);

impl Sections {
    /// Every section of type `T`, with its component's name.
    pub fn of<T: StatusSection>(&self) -> impl Iterator<Item = (&str, &T)> {
        self.0.iter().filter_map(|s| s.status.downcast_ref::<T>().map(|t| (s.component.as_str(), t)))
    }

    /// The section under `key` in the JSON.
    pub fn get(&self, key: &str) -> Option<&Section> {
        self.0.iter().find(|s| s.key == key)
    }
}

impl Serialize for Sections {
    fn serialize<S: serde::Serializer>(&self, serializer: S) -> Result<S::Ok, S::Error> {
        let mut map = serializer.serialize_map(Some(self.0.len()))?;
        for section in &self.0 {
            map.serialize_entry(&section.key, &section.status.to_json())?;
        }
        map.end()
    }
}

/// In the JSON each section is a field of the report, an object of its
/// built-in's own (docs/report.md); which there are is the robot file's.
impl schemars::JsonSchema for Sections {
    fn schema_name() -> std::borrow::Cow<'static, str> {
        "Sections".into()
    }

    fn json_schema(_: &mut schemars::SchemaGenerator) -> schemars::Schema {
        schemars::json_schema!({ "type": "object", "additionalProperties": { "type": "object" } })
    }
}

#[derive(Clone, Debug, Serialize, schemars::JsonSchema)]
pub struct Report {
    pub format: u32,
    pub robot: String,
    pub config: String,
    pub stopped_by: StoppedBy,
    pub duration_s: f64,
    /// Control-loop cycles run.
    pub cycles: u64,
    pub components: Vec<ComponentReport>,
    pub connections: Vec<ConnectionReport>,
    pub messages: MessageTotals,
    /// How late the control loop ran its scheduled cycles, and how long it
    /// waited for a CPU: a reader can tell a busy machine from a slow host.
    pub loop_lateness: LoopLateness,
    /// Sections of built-in components, by name: `arbiter`, `serial`, `sim`
    /// (`name:component` when a name appears twice).
    #[serde(flatten)]
    pub sections: Sections,
}

/// `loop_lateness` in the JSON (docs/report.md).
#[derive(Clone, Debug, Serialize, schemars::JsonSchema)]
pub struct LoopLateness {
    /// Scheduled cycles whose lateness the loop measured.
    pub cycles: u64,
    /// The sum of their lateness.
    pub total_ms: f64,
    /// The worst one.
    pub max_ms: f64,
    /// How long the control thread was ready to run but waited for a CPU
    /// (the kernel's run delay; 0 on simulated time or where the kernel
    /// keeps none).
    pub waited_for_cpu_ms: f64,
    /// The whole histogram, for `/metrics`.
    #[serde(skip)]
    pub histogram: Histogram,
}

impl LoopLateness {
    pub fn of(graph: &Graph) -> LoopLateness {
        let histogram = graph.lateness().clone();
        LoopLateness {
            cycles: histogram.count(),
            total_ms: histogram.sum_ns() as f64 / 1e6,
            max_ms: histogram.max_ns() as f64 / 1e6,
            waited_for_cpu_ms: graph.cpu_wait().waited_ns() as f64 / 1e6,
            histogram,
        }
    }
}

#[derive(Clone, Debug, Serialize, schemars::JsonSchema)]
pub struct ComponentReport {
    pub name: String,
    pub platform: String,
    pub source: String,
    pub rate_hz: f64,
    pub priority: Option<i32>,
    pub state: ComponentRunState,
    pub fault: Option<String>,
    pub faulted_at_s: Option<f64>,
    pub calls: u64,
    pub ticks: u64,
    pub missed_ticks: u64,
    pub call_time_ms: f64,
    pub messages_in: u64,
    pub messages_out: u64,
    pub messages_dropped: u64,
    pub errors: u64,
    pub last_error: Option<String>,
    /// Restarts after faults (`restart="on-failure"`).
    pub restarts: u64,
    /// Times it was faulted (a restarted component may fault again).
    pub faults: u64,
    /// The time of each call (for `/metrics`; not in the JSON).
    #[serde(skip)]
    pub call_times: Histogram,
}

#[derive(Clone, Debug, Serialize, schemars::JsonSchema)]
pub struct ConnectionReport {
    pub from: String,
    pub to: String,
    pub policy: PolicyName,
    pub depth: Option<usize>,
    pub routed: u64,
    pub delivered: u64,
    pub dropped: u64,
    pub overwritten: u64,
}

#[derive(Clone, Debug, Serialize, schemars::JsonSchema)]
pub struct MessageTotals {
    /// Values put into mailboxes (one per receiving connection).
    pub routed: u64,
    /// Values handed to receiving components.
    pub delivered: u64,
    /// Values dropped from full queues.
    pub dropped: u64,
}

/// Version of the live status's layout.
pub const LIVE_STATUS_FORMAT: u32 = 1;

/// What the portal shows while a set runs: the report so far and the set.
#[derive(Clone, Debug, Serialize, schemars::JsonSchema)]
pub struct LiveStatus {
    pub live_format: u32,
    /// The active set's id.
    pub set: u64,
    /// The experiment the set runs as, if it does (docs/lab.md).
    pub experiment: Option<ExperimentTag>,
    #[serde(flatten)]
    pub report: Report,
}

/// Whose code drives: the experiment a set runs as, its submitter and
/// each WASM component's sha256.
#[derive(Clone, Debug, PartialEq, Serialize, schemars::JsonSchema)]
pub struct ExperimentTag {
    pub id: u64,
    pub submitter: String,
    pub label: String,
    /// Component name -> the sha256 of the WASM it runs.
    pub sha256: std::collections::BTreeMap<String, String>,
}

/// The live status of `graph` (running `config`, set `set`, as
/// `experiment` if any) at `now_s`.
pub fn live(
    config: &RobotConfig,
    graph: &Graph,
    set: u64,
    experiment: Option<&std::sync::Arc<ExperimentTag>>,
    now_s: f64,
) -> LiveStatus {
    LiveStatus {
        live_format: LIVE_STATUS_FORMAT,
        set,
        experiment: experiment.map(|e| (**e).clone()),
        report: report(config, graph, StoppedBy::Running, now_s),
    }
}

/// The report of `graph`, built from `config` (component and connection
/// indices in the graph are those of the config).
pub fn build(config: &RobotConfig, graph: &Graph, stopped_by: StopReason, duration_s: f64) -> Report {
    let stopped_by = match stopped_by {
        StopReason::Duration => StoppedBy::Duration,
        StopReason::Requested => StoppedBy::Shutdown,
    };
    report(config, graph, stopped_by, duration_s)
}

/// An experiment's report, taken as its graph is swapped out after
/// `duration_s` (docs/lab.md: its record says why it ended).
pub fn build_experiment(config: &RobotConfig, graph: &Graph, duration_s: f64) -> Report {
    report(config, graph, StoppedBy::Experiment, duration_s)
}

fn report(config: &RobotConfig, graph: &Graph, stopped_by: StoppedBy, duration_s: f64) -> Report {
    let components = config
        .components
        .iter()
        .enumerate()
        .map(|(i, c)| {
            let stats = graph.stats(i).cloned().unwrap_or_default();
            let (state, fault, faulted_at_s) = match graph.state(i) {
                Some(ComponentState::Faulted { reason, at_ns }) => {
                    (ComponentRunState::Faulted, Some(reason.clone()), Some(*at_ns as f64 / 1e9))
                }
                _ => (ComponentRunState::Running, None, None),
            };
            ComponentReport {
                name: c.name.clone(),
                platform: c.platform.name().to_string(),
                source: c.source.to_string(),
                rate_hz: c.rate_hz,
                priority: c.priority,
                state,
                fault,
                faulted_at_s,
                calls: stats.calls,
                ticks: stats.ticks,
                missed_ticks: stats.missed_ticks,
                call_time_ms: stats.call_ns as f64 / 1e6,
                messages_in: stats.messages_in,
                messages_out: stats.messages_out,
                messages_dropped: stats.messages_dropped,
                errors: stats.errors,
                last_error: stats.last_error,
                restarts: stats.restarts,
                faults: stats.faults,
                call_times: stats.call_times,
            }
        })
        .collect();
    let mut delivered = 0;
    let connections = config
        .connections
        .iter()
        .enumerate()
        .map(|(i, c)| {
            let stats = graph.connection_stats(i).cloned().unwrap_or_default();
            delivered += stats.delivered;
            let (policy, depth) = match c.policy {
                Policy::Latest => (PolicyName::Latest, None),
                Policy::Queue { depth } => (PolicyName::Queue, Some(depth)),
            };
            ConnectionReport {
                from: config.output_name(c.from),
                to: config.input_name(c.to),
                policy,
                depth,
                routed: stats.routed,
                delivered: stats.delivered,
                dropped: stats.dropped,
                overwritten: stats.overwritten,
            }
        })
        .collect();
    let mut sections = Sections::default();
    for (name, status) in graph.statuses() {
        let kind = status.section();
        let key = if sections.get(kind).is_some() { format!("{kind}:{name}") } else { kind.to_string() };
        sections.0.push(Section { key, component: name.to_string(), status: Arc::from(status) });
    }
    Report {
        sections,
        format: REPORT_FORMAT,
        robot: config.name.clone(),
        config: config.path.display().to_string(),
        stopped_by,
        duration_s,
        cycles: graph.cycles(),
        loop_lateness: LoopLateness::of(graph),
        components,
        connections,
        messages: MessageTotals { routed: graph.messages_routed(), delivered, dropped: graph.messages_dropped() },
    }
}
