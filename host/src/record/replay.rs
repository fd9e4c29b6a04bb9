//! `subsume replay FILE.mcap ROBOT.xml [--only COMPONENT...]`: feeds the
//! chosen WASM components of the robot file the calls they got in the
//! recording (every tick and every input, in the recorded order, at the
//! recorded graph times, as fast as possible), then compares what they emit
//! with what was recorded, port by port, bit for bit.
//!
//! Each chosen component gets its own recorded inputs, not what a replayed
//! neighbour emits now: a divergence is the component's own.

use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use serde_json::Value as Json;
use thiserror::Error;

use super::schema::{self, FRAME_TRANSFORM, LASER_SCAN, POSE_IN_FRAME};
use super::{calls_topic, output_topic};
use crate::assemble::{self, Loader, StartError};
use crate::builtin::Services;
use crate::config::{self, ComponentSource, Diagnostics, ParamOverride, RobotConfig};
use crate::contract::Value;
use crate::runtime::control_loop::{Clock, Shutdown};
use crate::runtime::{Call, Tap};
use crate::sandbox::{Sandbox, SandboxError};

/// Most recorded bytes replay reads: the recording is read whole into memory.
pub const MAX_RECORDING_BYTES: u64 = 4 << 30;

/// What `subsume replay` was asked to do.
#[derive(Clone, Debug)]
pub struct ReplayOptions {
    pub recording: PathBuf,
    pub config_path: PathBuf,
    /// The components to replay; every WASM component of the file when empty.
    pub only: Vec<String>,
    pub overrides: Vec<ParamOverride>,
    pub cache_dir: Option<PathBuf>,
}

#[derive(Debug, Error)]
pub enum ReplayError {
    #[error("{0}")]
    Config(Diagnostics),
    #[error(transparent)]
    Sandbox(#[from] SandboxError),
    #[error("{}", .0.iter().map(ToString::to_string).collect::<Vec<_>>().join("\n"))]
    Start(Vec<StartError>),
    #[error("{path}: {source}")]
    Read {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{path}: not a recording replay can read: {source}")]
    Mcap {
        path: PathBuf,
        #[source]
        source: mcap::McapError,
    },
    #[error("{}: not a recording replay can read: it does not start with the MCAP magic", .0.display())]
    NotMcap(PathBuf),
    #[error("{}: {size} bytes, larger than the {max} bytes a replay reads", .path.display())]
    TooLarge { path: PathBuf, size: u64, max: u64 },
    #[error("{}: the replay took longer than {} s and was stopped after {done} of {calls} calls", .path.display(), .bound.as_secs_f64())]
    TooLong { path: PathBuf, bound: Duration, done: usize, calls: usize },
    #[error("{}: '{component}' gets input {port} '{recorded}' in the recording, but its input {port} is {now} (was it recorded with another robot file?)", .path.display())]
    PortMismatch { path: PathBuf, component: String, port: u32, recorded: String, now: String },
    #[error("{}: no component '{component}' in the robot file", .path.display())]
    UnknownComponent { path: PathBuf, component: String },
    #[error("{}: '{component}' is {source_kind}: replay runs WASM components only (built-ins own devices and sockets)", .path.display())]
    NotWasm { path: PathBuf, component: String, source_kind: String },
    #[error("{}: the robot file has no WASM component to replay", .0.display())]
    NothingToReplay(PathBuf),
    #[error("{path}: no recorded calls of '{component}' (was it recorded under this name?)")]
    NotRecorded { path: PathBuf, component: String },
    #[error("{path}: message {index} on {topic}: {problem}")]
    BadMessage { path: PathBuf, index: u64, topic: String, problem: String },
}

/// Where a replayed component's outputs first differ from the recording.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct Divergence {
    pub component: String,
    pub port: String,
    /// Graph time of the first different output, seconds since the recorded
    /// host started.
    pub time_s: f64,
    /// Which output on that port (0: the first).
    pub index: usize,
    /// The recorded value in subsume's JSON form; `None`: nothing recorded.
    pub recorded: Option<Json>,
    /// The replayed value; `None`: the component emitted nothing there.
    pub replayed: Option<Json>,
}

impl std::fmt::Display for Divergence {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let show = |v: &Option<Json>| v.as_ref().map_or_else(|| "nothing".to_string(), Json::to_string);
        write!(
            f,
            "{}.{} diverges at {:.6} s (output {}): recorded {}, replayed {}",
            self.component,
            self.port,
            self.time_s,
            self.index,
            show(&self.recorded),
            show(&self.replayed)
        )
    }
}

/// What a replay found.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct ReplayReport {
    pub components: Vec<String>,
    /// Recorded calls fed again.
    pub calls: u64,
    /// Outputs compared (recorded and replayed, over every port).
    pub compared: u64,
    /// Graph time the replayed calls span, seconds.
    pub recorded_s: f64,
    /// Wall-clock time the replay took, seconds.
    pub wall_s: f64,
    /// Whether the recording ended without its footer (a killed host).
    pub truncated: bool,
    /// The first divergence of each port that has one, earliest first.
    pub divergences: Vec<Divergence>,
}

impl ReplayReport {
    pub fn identical(&self) -> bool {
        self.divergences.is_empty()
    }
}

/// One output as compared: graph time and exact JSON text.
type Output = (u64, String);

/// Collects what the replayed components emit.
struct Collect(Arc<Mutex<Recorded>>);

impl Tap for Collect {
    fn call(&mut self, _index: usize, _call: Call<'_>, _now_ns: u64) {}

    fn emitted(&mut self, from: usize, port: u32, value: &Value, now_ns: u64) {
        if let Ok(mut outputs) = self.0.lock() {
            outputs.entry((from, port)).or_default().push((now_ns, schema::value_json(value).to_string()));
        }
    }

    fn faulted(&mut self, _index: usize, _reason: &str, _now_ns: u64) {}

    fn restarted(&mut self, _index: usize, _attempt: u64, _now_ns: u64) {}
}

/// A recorded call of a replayed component.
struct RecordedCall {
    component: usize,
    t: u64,
    input: Option<(u32, Value)>,
}

/// What bounds one replay: the recording's size (it is read whole into
/// memory) and the wall-clock time the calls may take.
#[derive(Clone, Copy, Debug)]
pub struct ReplayLimits {
    pub max_recording_bytes: u64,
    /// `None`: no bound (the command line's replay).
    pub max_duration: Option<Duration>,
}

impl Default for ReplayLimits {
    fn default() -> ReplayLimits {
        ReplayLimits { max_recording_bytes: MAX_RECORDING_BYTES, max_duration: None }
    }
}

/// Replays `options.only` (or every WASM component) against the recording.
pub fn replay(options: &ReplayOptions) -> Result<ReplayReport, ReplayError> {
    let sandbox = Sandbox::new(options.cache_dir.clone())?;
    let mut loader = Loader::new(&sandbox);
    let config =
        config::load_with(&options.config_path, &mut loader, &options.overrides).map_err(ReplayError::Config)?;
    replay_robot(&config, &mut loader, &options.recording, &options.only, ReplayLimits::default())
}

/// Replays components `only` (or every WASM component) of the validated
/// robot `config` against the recording at `recording`: builds them alone
/// (no built-in, no connection: nothing here touches a device, a socket or
/// the running graph), feeds each its recorded calls and compares.
pub fn replay_robot(
    config: &RobotConfig,
    loader: &mut Loader<'_>,
    recording: &Path,
    only: &[String],
    limits: ReplayLimits,
) -> Result<ReplayReport, ReplayError> {
    let chosen = choose(config, only)?;
    let sub = RobotConfig {
        name: config.name.clone(),
        path: config.path.clone(),
        components: chosen.iter().map(|&i| config.components[i].clone()).collect(),
        connections: Vec::new(),
    };
    let (calls, recorded, truncated) = read_recording(recording, &sub, limits.max_recording_bytes)?;
    for (index, component) in sub.components.iter().enumerate() {
        if !calls.iter().any(|c| c.component == index) {
            return Err(ReplayError::NotRecorded { path: recording.into(), component: component.name.clone() });
        }
    }
    let shutdown = Shutdown::new();
    let mut graph = assemble::build(
        &sub,
        loader,
        Clock::new(),
        &shutdown.waker(),
        &Services::default(),
        &assemble::Carry::default(),
    )
    .map(|built| built.graph)
    .map_err(ReplayError::Start)?;
    let outputs = Arc::new(Mutex::new(HashMap::new()));
    graph.set_tap(Box::new(Collect(outputs.clone())));
    let started = Instant::now();
    for (n, call) in calls.iter().enumerate() {
        if let Some(bound) = limits.max_duration
            && n % 256 == 0
            && started.elapsed() > bound
        {
            return Err(ReplayError::TooLong { path: recording.into(), bound, done: n, calls: calls.len() });
        }
        // The sender is not replayed: WASM components are not told who sent.
        graph.drive(call.component, call.input.clone().map(|(port, value)| (port, value, usize::MAX)), call.t);
    }
    let wall_s = started.elapsed().as_secs_f64();
    drop(graph);
    let replayed = outputs.lock().map(|o| o.clone()).unwrap_or_default();
    let span = calls.first().zip(calls.last()).map_or(0, |(a, b)| b.t.saturating_sub(a.t));
    let mut report = ReplayReport {
        components: sub.components.iter().map(|c| c.name.clone()).collect(),
        calls: calls.len() as u64,
        compared: 0,
        recorded_s: span as f64 / 1e9,
        wall_s,
        truncated,
        divergences: Vec::new(),
    };
    let last_call_t = calls.last().map_or(0, |c| c.t);
    for (index, component) in sub.components.iter().enumerate() {
        for (port, spec) in component.description.outputs.iter().enumerate() {
            let empty = Vec::new();
            let old = recorded.get(&(index, port as u32)).unwrap_or(&empty);
            let new = replayed.get(&(index, port as u32)).unwrap_or(&empty);
            // A recording cut short may hold outputs of calls it lost, and
            // the last calls' outputs may have missed the cut: compare up to
            // the last recorded call.
            let old: Vec<&Output> = old.iter().filter(|(t, _)| *t <= last_call_t).collect();
            report.compared += old.len().max(new.len()) as u64;
            let first_difference =
                (0..old.len().max(new.len())).find(|&i| old.get(i).map(|o| &o.1) != new.get(i).map(|n| &n.1));
            if let Some(i) = first_difference {
                let parse = |text: &String| serde_json::from_str::<Json>(text).ok();
                let time_ns = new.get(i).map(|n| n.0).or_else(|| old.get(i).map(|o| o.0)).unwrap_or(0);
                report.divergences.push(Divergence {
                    component: component.name.clone(),
                    port: spec.name.clone(),
                    time_s: time_ns as f64 / 1e9,
                    index: i,
                    recorded: old.get(i).and_then(|o| parse(&o.1)),
                    replayed: new.get(i).and_then(|n| parse(&n.1)),
                });
            }
        }
    }
    report.divergences.sort_by(|a, b| a.time_s.total_cmp(&b.time_s));
    Ok(report)
}

fn choose(config: &RobotConfig, only: &[String]) -> Result<Vec<usize>, ReplayError> {
    let path = config.path.clone();
    if only.is_empty() {
        let all: Vec<usize> = (0..config.components.len())
            .filter(|&i| matches!(config.components[i].source, ComponentSource::Wasm(_)))
            .collect();
        if all.is_empty() {
            return Err(ReplayError::NothingToReplay(path));
        }
        return Ok(all);
    }
    let mut chosen = Vec::new();
    for name in only {
        let Some(index) = config.components.iter().position(|c| &c.name == name) else {
            return Err(ReplayError::UnknownComponent { path, component: name.clone() });
        };
        if let ComponentSource::Builtin(kind) = &config.components[index].source {
            return Err(ReplayError::NotWasm { path, component: name.clone(), source_kind: kind.clone() });
        }
        if !chosen.contains(&index) {
            chosen.push(index);
        }
    }
    chosen.sort_unstable();
    Ok(chosen)
}

type Recorded = HashMap<(usize, u32), Vec<Output>>;

/// The calls of `sub`'s components in recorded order, and their recorded
/// outputs per port; whether the file was cut short.
fn read_recording(
    path: &Path,
    sub: &RobotConfig,
    max_bytes: u64,
) -> Result<(Vec<RecordedCall>, Recorded, bool), ReplayError> {
    let size = std::fs::metadata(path).map_err(|source| ReplayError::Read { path: path.into(), source })?.len();
    if size > max_bytes {
        return Err(ReplayError::TooLarge { path: path.into(), size, max: max_bytes });
    }
    let bytes = std::fs::read(path).map_err(|source| ReplayError::Read { path: path.into(), source })?;
    let mut calls_of: BTreeMap<String, usize> = BTreeMap::new();
    let mut outputs_of: BTreeMap<String, (usize, u32)> = BTreeMap::new();
    for (index, component) in sub.components.iter().enumerate() {
        calls_of.insert(calls_topic(&component.name), index);
        for (port, spec) in component.description.outputs.iter().enumerate() {
            outputs_of.insert(output_topic(&component.name, &spec.name), (index, port as u32));
        }
    }
    if !bytes.starts_with(mcap::MAGIC) {
        return Err(ReplayError::NotMcap(path.into()));
    }
    let stream = mcap::MessageStream::new_with_options(&bytes, mcap::read::Options::IgnoreEndMagic.into())
        .map_err(|source| ReplayError::Mcap { path: path.into(), source })?;
    let mut calls = Vec::new();
    let mut recorded: Recorded = HashMap::new();
    let mut truncated = false;
    for (read, message) in (1u64..).zip(stream) {
        let message = match message {
            Ok(message) => message,
            Err(e) if read > 0 => {
                tracing::warn!(
                    "{}: the recording ends early ({e}); replaying the {read} messages before",
                    path.display()
                );
                truncated = true;
                break;
            }
            Err(source) => return Err(ReplayError::Mcap { path: path.into(), source }),
        };
        let topic = message.channel.topic.as_str();
        let bad = |problem: &str| ReplayError::BadMessage {
            path: path.into(),
            index: read,
            topic: topic.to_string(),
            problem: problem.to_string(),
        };
        if let Some(&component) = calls_of.get(topic) {
            let json: Json = serde_json::from_slice(&message.data).map_err(|e| bad(&e.to_string()))?;
            let t = json["t"].as_u64().ok_or_else(|| bad("no time 't'"))?;
            let input = match json["call"].as_str() {
                Some("tick") => None,
                Some("input") => {
                    let port = json["port"].as_u64().ok_or_else(|| bad("no input port"))? as u32;
                    let inputs = &sub.components[component].description.inputs;
                    let now = inputs.get(port as usize).map(|p| p.name.as_str());
                    if let Some(recorded) = json["port_name"].as_str()
                        && now != Some(recorded)
                    {
                        return Err(ReplayError::PortMismatch {
                            path: path.into(),
                            component: sub.components[component].name.clone(),
                            port,
                            recorded: recorded.to_string(),
                            now: now.map_or_else(|| "missing".to_string(), |n| format!("'{n}'")),
                        });
                    }
                    if now.is_none() {
                        return Err(bad(&format!("input port {port} is not an input of this component")));
                    }
                    let value = schema::value_from_json(&json["value"]).ok_or_else(|| bad("not a value"))?;
                    Some((port, value))
                }
                _ => return Err(bad("'call' is neither tick nor input")),
            };
            calls.push(RecordedCall { component, t, input });
        } else if let Some(&key) = outputs_of.get(topic) {
            let json: Json = serde_json::from_slice(&message.data).map_err(|e| bad(&e.to_string()))?;
            let epoch: u64 = message.channel.metadata.get("epoch_unix_ns").and_then(|e| e.parse().ok()).unwrap_or(0);
            let schema_name = message.channel.schema.as_ref().map(|s| s.name.clone()).unwrap_or_default();
            let (t, value) = match schema_name.as_str() {
                LASER_SCAN => (message.log_time.saturating_sub(epoch), schema::scan_from_laser_scan(&json)),
                POSE_IN_FRAME => (message.log_time.saturating_sub(epoch), schema::vector_from_pose(&json)),
                FRAME_TRANSFORM => continue,
                _ => (json["t"].as_u64().ok_or_else(|| bad("no time 't'"))?, schema::value_from_json(&json["value"])),
            };
            let value = value.ok_or_else(|| bad("not a value"))?;
            recorded.entry(key).or_default().push((t, schema::value_json(&value).to_string()));
        }
    }
    Ok((calls, recorded, truncated))
}
