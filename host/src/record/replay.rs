//! `subsume replay FILE.mcap ROBOT.xml [--only COMPONENT...]`: feeds the
//! chosen WASM components of the robot file the calls they got in the
//! recording (every tick and every input, in the recorded order, at the
//! recorded graph times, as fast as possible), then compares what they emit
//! with what was recorded, call by call and port by port, bit for bit.
//!
//! Each chosen component gets its own recorded inputs, not what a replayed
//! neighbour emits now: a divergence is the component's own.
//!
//! Outputs are paired with the call that produced them: in a recording, a
//! component's output belongs to its last call before it in log order.
//! That holds because the graph tells its tap of a call before making it
//! and of what the call emitted right after it returns, before any other
//! call (`runtime::tap`), the recorder keeps that order through one FIFO
//! channel into the file, and a WASM component emits only from its calls.
//! So an output missing (or extra) in one call is that call's divergence
//! and does not shift the comparison of the calls after it.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use serde_json::Value as Json;
use thiserror::Error;

use super::schema::{self, COMPRESSED_IMAGE, FRAME_TRANSFORM, LASER_SCAN, POSE_IN_FRAME};
use super::{ComponentLayout, Layout, calls_topic, output_topic};
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

/// Where a replayed component's outputs on one port first differ from the
/// recording: the first recorded call whose outputs on that port differ.
#[derive(Clone, Debug, PartialEq, serde::Serialize, schemars::JsonSchema)]
pub struct Divergence {
    pub component: String,
    pub port: String,
    /// Graph time of the call, seconds since the recorded host started.
    pub time_s: f64,
    /// Which recorded call of the component (0: its first in the recording).
    pub call: usize,
    /// What the call was: `tick`, or `input PORT`.
    pub call_kind: String,
    /// What that call emitted on the port in the recording, in subsume's
    /// JSON form, in order; empty: nothing.
    pub recorded: Vec<Json>,
    /// What the same call emitted on the port in the replay; empty: nothing.
    pub replayed: Vec<Json>,
    /// How many of the component's compared calls differ on this port.
    pub calls_differing: u64,
}

/// Values as a divergence shows them: `nothing`, the value, or a list.
fn show_values(values: &[Json]) -> String {
    match values {
        [] => "nothing".to_string(),
        [one] => one.to_string(),
        many => Json::Array(many.to_vec()).to_string(),
    }
}

impl std::fmt::Display for Divergence {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{}.{} diverges at {:.6} s (call {}: {}): recorded {}, replayed {} ({} call{} differ{})",
            self.component,
            self.port,
            self.time_s,
            self.call,
            self.call_kind,
            show_values(&self.recorded),
            show_values(&self.replayed),
            self.calls_differing,
            if self.calls_differing == 1 { "" } else { "s" },
            if self.calls_differing == 1 { "s" } else { "" },
        )
    }
}

/// What a replay found.
#[derive(Clone, Debug, PartialEq, serde::Serialize, schemars::JsonSchema)]
pub struct ReplayReport {
    pub components: Vec<String>,
    /// Recorded calls fed again.
    pub calls: u64,
    /// Outputs compared (per call and port, the larger of the recorded and
    /// the replayed count, over every call and port).
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

/// One output as compared: output port and exact JSON text.
type Output = (u32, String);

/// Collects what the replayed components emit, for the call being made.
struct Collect(Arc<Mutex<Vec<Output>>>);

impl Tap for Collect {
    fn call(&mut self, _index: usize, _call: Call<'_>, _now_ns: u64) {}

    fn emitted(&mut self, _from: usize, port: u32, value: &Value, _now_ns: u64) {
        if let Ok(mut outputs) = self.0.lock() {
            outputs.push((port, schema::value_json(value).to_string()));
        }
    }

    fn faulted(&mut self, _index: usize, _reason: &str, _now_ns: u64) {}

    fn restarted(&mut self, _index: usize, _attempt: u64, _now_ns: u64) {}
}

/// A recorded call of a replayed component and what it emitted.
struct RecordedCall {
    component: usize,
    t: u64,
    input: Option<(u32, Value)>,
    /// What the call emitted in the recording, in order.
    outputs: Vec<Output>,
    /// Whether its outputs are compared: not the last call of the file,
    /// whose outputs a stop or a kill may have cut off.
    compared: bool,
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
    // Replay reads the recording's time, not the wall clock's.
    let sandbox = Sandbox::new(options.cache_dir.clone())?.on_simulated_time();
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
    let layouts = Layout::of(&sub).components;
    let (calls, truncated) = read_recording(recording, &layouts, limits.max_recording_bytes)?;
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
    let emitted = Arc::new(Mutex::new(Vec::new()));
    graph.set_tap(Box::new(Collect(emitted.clone())));
    let started = Instant::now();
    let mut replayed: Vec<Vec<Output>> = Vec::with_capacity(calls.len());
    for (n, call) in calls.iter().enumerate() {
        if let Some(bound) = limits.max_duration
            && n % 256 == 0
            && started.elapsed() > bound
        {
            return Err(ReplayError::TooLong { path: recording.into(), bound, done: n, calls: calls.len() });
        }
        // The sender is not replayed: WASM components are not told who sent.
        graph.drive(call.component, call.input.clone().map(|(port, value)| (port, value, usize::MAX)), call.t);
        replayed.push(emitted.lock().map(|mut e| std::mem::take(&mut *e)).unwrap_or_default());
    }
    let wall_s = started.elapsed().as_secs_f64();
    drop(graph);
    let span = calls.first().zip(calls.last()).map_or(0, |(a, b)| b.t.saturating_sub(a.t));
    let (compared, divergences) = compare(&layouts, &calls, &replayed);
    Ok(ReplayReport {
        components: sub.components.iter().map(|c| c.name.clone()).collect(),
        calls: calls.len() as u64,
        compared,
        recorded_s: span as f64 / 1e9,
        wall_s,
        truncated,
        divergences,
    })
}

/// The outputs on `port`, in order.
fn on_port(outputs: &[Output], port: u32) -> Vec<&String> {
    outputs.iter().filter(|(p, _)| *p == port).map(|(_, text)| text).collect()
}

/// Compares, call by call, what each recorded call emitted with what the
/// same call emitted in the replay (`replayed[n]`: call `n`'s outputs), per
/// output port; the outputs compared and the first divergence of each port
/// that has one, earliest first.
fn compare(layouts: &[ComponentLayout], calls: &[RecordedCall], replayed: &[Vec<Output>]) -> (u64, Vec<Divergence>) {
    let mut compared = 0;
    let mut divergences = Vec::new();
    for (index, layout) in layouts.iter().enumerate() {
        for (port, spec) in layout.outputs.iter().enumerate() {
            let port = port as u32;
            let mut first: Option<Divergence> = None;
            let mut differing = 0;
            let mut ordinal = 0;
            for (n, call) in calls.iter().enumerate() {
                if call.component != index {
                    continue;
                }
                let this = ordinal;
                ordinal += 1;
                if !call.compared {
                    continue;
                }
                let old = on_port(&call.outputs, port);
                let new = replayed.get(n).map(|r| on_port(r, port)).unwrap_or_default();
                compared += old.len().max(new.len()) as u64;
                if old == new {
                    continue;
                }
                differing += 1;
                if first.is_none() {
                    let parse = |texts: &[&String]| -> Vec<Json> {
                        texts.iter().filter_map(|t| serde_json::from_str::<Json>(t).ok()).collect()
                    };
                    first = Some(Divergence {
                        component: layout.name.clone(),
                        port: spec.name.clone(),
                        time_s: call.t as f64 / 1e9,
                        call: this,
                        call_kind: match &call.input {
                            None => "tick".to_string(),
                            Some((input, _)) => format!(
                                "input {}",
                                layout.inputs.get(*input as usize).map_or_else(|| input.to_string(), Clone::clone)
                            ),
                        },
                        recorded: parse(&old),
                        replayed: parse(&new),
                        calls_differing: 0,
                    });
                }
            }
            if let Some(mut divergence) = first {
                divergence.calls_differing = differing;
                divergences.push(divergence);
            }
        }
    }
    divergences.sort_by(|a, b| a.time_s.total_cmp(&b.time_s));
    (compared, divergences)
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
            return Err(ReplayError::NotWasm { path, component: name.clone(), source_kind: kind.name().to_string() });
        }
        if !chosen.contains(&index) {
            chosen.push(index);
        }
    }
    chosen.sort_unstable();
    Ok(chosen)
}

/// The calls of the components `layouts` names in recorded order, each with
/// the outputs it emitted (an output belongs to its component's last call
/// before it in log order; one before any call of its component, as at
/// the start of a rotated file, is not compared); whether the file was cut
/// short.
fn read_recording(
    path: &Path,
    layouts: &[ComponentLayout],
    max_bytes: u64,
) -> Result<(Vec<RecordedCall>, bool), ReplayError> {
    let size = std::fs::metadata(path).map_err(|source| ReplayError::Read { path: path.into(), source })?.len();
    if size > max_bytes {
        return Err(ReplayError::TooLarge { path: path.into(), size, max: max_bytes });
    }
    let bytes = std::fs::read(path).map_err(|source| ReplayError::Read { path: path.into(), source })?;
    let mut calls_of: BTreeMap<String, usize> = BTreeMap::new();
    let mut outputs_of: BTreeMap<String, (usize, u32)> = BTreeMap::new();
    for (index, component) in layouts.iter().enumerate() {
        calls_of.insert(calls_topic(&component.name), index);
        for (port, spec) in component.outputs.iter().enumerate() {
            outputs_of.insert(output_topic(&component.name, &spec.name), (index, port as u32));
        }
    }
    if !bytes.starts_with(mcap::MAGIC) {
        return Err(ReplayError::NotMcap(path.into()));
    }
    let readable = super::readable::readable(&bytes);
    let stream = mcap::MessageStream::new_with_options(readable.bytes, mcap::read::Options::IgnoreEndMagic.into())
        .map_err(|source| ReplayError::Mcap { path: path.into(), source })?;
    let mut calls: Vec<RecordedCall> = Vec::new();
    // Each component's last call so far (an index into `calls`).
    let mut last_call: Vec<Option<usize>> = vec![None; layouts.len()];
    // Whether the last call message of the file is one of `calls`' (of a
    // replayed component) rather than another component's.
    let mut last_is_ours = false;
    let calls_prefix = calls_topic("");
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
        if topic.starts_with(&calls_prefix) && !calls_of.contains_key(topic) {
            last_is_ours = false;
        }
        if let Some(&component) = calls_of.get(topic) {
            let json: Json = serde_json::from_slice(&message.data).map_err(|e| bad(&e.to_string()))?;
            let t = json["t"].as_u64().ok_or_else(|| bad("no time 't'"))?;
            let input = match json["call"].as_str() {
                Some("tick") => None,
                Some("input") => {
                    let port = json["port"].as_u64().ok_or_else(|| bad("no input port"))? as u32;
                    let inputs = &layouts[component].inputs;
                    let now = inputs.get(port as usize).map(String::as_str);
                    if let Some(recorded) = json["port_name"].as_str()
                        && now != Some(recorded)
                    {
                        return Err(ReplayError::PortMismatch {
                            path: path.into(),
                            component: layouts[component].name.clone(),
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
            last_call[component] = Some(calls.len());
            last_is_ours = true;
            calls.push(RecordedCall { component, t, input, outputs: Vec::new(), compared: true });
        } else if let Some(&(component, port)) = outputs_of.get(topic) {
            let json: Json = serde_json::from_slice(&message.data).map_err(|e| bad(&e.to_string()))?;
            let schema_name = message.channel.schema.as_ref().map(|s| s.name.clone()).unwrap_or_default();
            let value = match schema_name.as_str() {
                LASER_SCAN => schema::scan_from_laser_scan(&json),
                POSE_IN_FRAME => schema::vector_from_pose(&json),
                COMPRESSED_IMAGE => schema::bytes_from_compressed_image(&json),
                FRAME_TRANSFORM => continue,
                _ => schema::value_from_json(&json["value"]),
            };
            let value = value.ok_or_else(|| bad("not a value"))?;
            if let Some(call) = last_call[component].and_then(|n| calls.get_mut(n)) {
                call.outputs.push((port, schema::value_json(&value).to_string()));
            }
        }
    }
    if let Some(at) = readable.cut_at
        && !truncated
    {
        tracing::warn!(
            "{}: the recording ends early (the record at byte {at} runs past the file); replaying what came before",
            path.display()
        );
        truncated = true;
    }
    // The file's last call may have lost outputs to a stop (the recording
    // is detached between cycles, but its writer may stop mid-call) or to
    // a kill: it is fed, not compared.
    if last_is_ours && let Some(last) = calls.last_mut() {
        last.compared = false;
    }
    Ok((calls, truncated))
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic)]

    use super::*;
    use crate::contract::ValueKind;
    use crate::record::{PortLayout, RecordOptions, Recorder, Timeline};
    use crate::runtime::control_loop::Clock;
    use crate::runtime::{CallError, Component, Graph, Outbox, Policy};

    /// Ticks at 100 Hz and emits the number of the tick.
    struct Counter(f64);

    impl Component for Counter {
        fn tick(&mut self, _now_ns: u64, out: &mut Outbox) -> Result<(), CallError> {
            self.0 += 1.0;
            out.push((0, Value::Scalar(self.0)));
            Ok(())
        }
    }

    /// On an odd number: emits it and ten times it on port 0; on an even
    /// one, nothing. Every second tick: `tick` on port 1.
    struct Echo(u64);

    impl Component for Echo {
        fn on_input(&mut self, _: u32, value: &Value, _: usize, _: u64, out: &mut Outbox) -> Result<(), CallError> {
            if let Value::Scalar(x) = value
                && *x as u64 % 2 == 1
            {
                out.push((0, Value::Scalar(*x)));
                out.push((0, Value::Scalar(*x * 10.0)));
            }
            Ok(())
        }

        fn tick(&mut self, _now_ns: u64, out: &mut Outbox) -> Result<(), CallError> {
            self.0 += 1;
            if self.0.is_multiple_of(2) {
                out.push((1, Value::Text("tick".into())));
            }
            Ok(())
        }
    }

    fn layouts() -> Vec<ComponentLayout> {
        let port = |name: &str, kind| PortLayout { name: name.into(), kind };
        vec![
            ComponentLayout { name: "counter".into(), inputs: vec![], outputs: vec![port("n", ValueKind::Scalar)] },
            ComponentLayout {
                name: "echo".into(),
                inputs: vec!["in".into()],
                outputs: vec![port("odd", ValueKind::Scalar), port("beat", ValueKind::Text)],
            },
        ]
    }

    /// Found by the `mcap_replay` fuzz target: a record whose length is
    /// near `u64::MAX` made the `mcap` reader's arithmetic wrap and panic
    /// (which ends `subsume run`). The file now ends early there.
    #[test]
    fn a_record_length_past_the_file_ends_it_early_and_panics_nothing() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("huge.mcap");
        let header = [&[0x01][..], &8u64.to_le_bytes(), &[0; 8]].concat();
        for len in [u64::MAX, u64::MAX - 8, 1 << 40] {
            let huge = [&[0x05][..], &len.to_le_bytes(), b"body"].concat();
            std::fs::write(&path, [mcap::MAGIC, &header, &huge].concat()).unwrap();
            let (calls, truncated) = read_recording(&path, &layouts(), MAX_RECORDING_BYTES).unwrap();
            assert!(calls.is_empty() && truncated, "length {len}");
        }
    }

    /// What the graph tells its tap reaches the file in the order it
    /// happened, so reading pairs every output with the call that emitted
    /// it: checked on a real graph recorded by the real recorder.
    #[test]
    fn outputs_pair_with_the_call_that_emitted_them_in_log_order() {
        let _alone = crate::record::log::TEST_RECORDING.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("pairs.mcap");
        let mut graph = Graph::new();
        let counter = graph.add("counter", Box::new(Counter(0.0)), 1, 100.0, 0);
        let echo = graph.add("echo", Box::new(Echo(0)), 2, 30.0, 0);
        graph.connect(counter, 0, echo, 0, Policy::Queue { depth: 8 });
        let recorder = Recorder::start(
            &RecordOptions::new(path.clone()),
            Layout { robot: "pairs".into(), components: layouts(), about: Default::default(), worlds: Vec::new() },
            Timeline::new(0, Clock::new()),
        )
        .unwrap();
        graph.set_tap(recorder.tap());
        for cycle in 0..200u64 {
            graph.step(cycle * 10_000_000);
        }
        drop(graph);
        let summary = recorder.finish().unwrap();
        assert_eq!(summary.dropped, 0);

        let (calls, truncated) = read_recording(&path, &layouts()[1..], MAX_RECORDING_BYTES).unwrap();
        assert!(!truncated);
        let (mut inputs, mut ticks) = (0, 0);
        for call in &calls {
            let outputs: Vec<(u32, Json)> =
                call.outputs.iter().map(|(p, text)| (*p, serde_json::from_str(text).unwrap())).collect();
            match &call.input {
                Some((0, Value::Scalar(x))) => {
                    inputs += 1;
                    let expected = if *x as u64 % 2 == 1 {
                        vec![(0, serde_json::json!({ "scalar": x })), (0, serde_json::json!({ "scalar": x * 10.0 }))]
                    } else {
                        vec![]
                    };
                    assert_eq!(outputs, expected, "input {x}");
                }
                None => {
                    ticks += 1;
                    let expected =
                        if ticks % 2 == 0 { vec![(1, serde_json::json!({ "text": "tick" }))] } else { vec![] };
                    assert_eq!(outputs, expected, "tick {ticks}");
                }
                other => panic!("unexpected call {other:?}"),
            }
        }
        assert_eq!(inputs, 200);
        assert!(ticks >= 59, "{ticks} ticks");
        // The last call of the file is fed but not compared (a stop may
        // cut its outputs); every other is.
        assert_eq!(calls.iter().filter(|c| !c.compared).count(), 1);
        assert!(!calls.last().unwrap().compared);
    }

    fn call(t: u64, outputs: &[&str], compared: bool) -> RecordedCall {
        RecordedCall {
            component: 0,
            t,
            input: None,
            outputs: outputs.iter().map(|o| (0, format!(r#"{{"command":"{o}"}}"#))).collect(),
            compared,
        }
    }

    fn replayed(outputs: &[&[&str]]) -> Vec<Vec<Output>> {
        outputs.iter().map(|call| call.iter().map(|o| (0, format!(r#"{{"command":"{o}"}}"#))).collect()).collect()
    }

    /// A call that emitted one output less in the replay (a component that
    /// had state the recording does not hold) is one divergence, at that
    /// call; the calls after it compare equal (by index they would all
    /// have shifted). Cases: (recorded, replayed, expected divergence as
    /// (call, recorded, replayed, calls differing)).
    #[test]
    fn a_missing_or_extra_output_is_its_calls_divergence_and_shifts_nothing() {
        let layouts = vec![ComponentLayout {
            name: "planner".into(),
            inputs: vec!["pose".into()],
            outputs: vec![PortLayout { name: "cmd".into(), kind: ValueKind::Command }],
        }];
        type Case<'a> = (&'a [&'a [&'a str]], &'a [&'a [&'a str]], Option<(usize, Vec<&'a str>, Vec<&'a str>, u64)>);
        let cases: Vec<Case> = vec![
            (&[&["A"], &["B"], &["C"]], &[&[], &["B"], &["C"]], Some((0, vec!["A"], vec![], 1))),
            (&[&[], &["B"], &["C"]], &[&["X"], &["B"], &["C"]], Some((0, vec![], vec!["X"], 1))),
            (&[&["A"], &["B", "B2"], &["C"]], &[&["A"], &["B"], &["D"]], Some((1, vec!["B", "B2"], vec!["B"], 2))),
            (&[&["A"], &["B"], &["C"]], &[&["A"], &["B"], &["C"]], None),
        ];
        for (recorded, new, expected) in cases {
            let calls: Vec<RecordedCall> =
                recorded.iter().enumerate().map(|(n, o)| call(n as u64 * 100_000_000, o, true)).collect();
            let (compared, divergences) = compare(&layouts, &calls, &replayed(new));
            let total: usize = recorded.iter().zip(new).map(|(a, b)| a.len().max(b.len())).sum();
            assert_eq!(compared, total as u64);
            let got = divergences.first().map(|d| {
                let texts = |v: &[Json]| -> Vec<String> {
                    v.iter().map(|j| j["command"].as_str().unwrap().to_string()).collect()
                };
                (d.call, texts(&d.recorded), texts(&d.replayed), d.calls_differing)
            });
            let expected = expected.map(|(call, r, n, differing)| {
                (
                    call,
                    r.iter().map(ToString::to_string).collect(),
                    n.iter().map(ToString::to_string).collect(),
                    differing,
                )
            });
            assert_eq!(got, expected, "recorded {recorded:?}, replayed {new:?}");
            if let Some(d) = divergences.first() {
                assert_eq!(d.time_s, d.call as f64 * 0.1);
                assert_eq!(d.call_kind, "tick");
                assert!(
                    d.to_string()
                        .starts_with(&format!("planner.cmd diverges at {:.6} s (call {}: tick)", d.time_s, d.call))
                );
            }
        }
        // A call not compared (the file's last) differs without a divergence.
        let calls = vec![call(0, &["A"], true), call(1, &["B"], false)];
        let (compared, divergences) = compare(&layouts, &calls, &replayed(&[&["A"], &[]]));
        assert_eq!((compared, divergences.len()), (1, 0));
        // Nothing on one side reads "nothing".
        let calls = vec![call(0, &["A"], true)];
        let (_, divergences) = compare(&layouts, &calls, &replayed(&[&[]]));
        assert!(divergences[0].to_string().contains(r#"recorded {"command":"A"}, replayed nothing (1 call differs)"#));
    }
}
