//! Scoring a run against the owner's task (docs/lab.md, "Tasks and
//! scores"): every sub-score is computed from the run's recording alone
//! (its poses, commands and status messages, on the recording's time
//! line), in file order, so the same bytes give the same numbers bit for
//! bit: on the robot at the end of a run, and on anyone's machine from the
//! bundle (`subsume score BUNDLE_DIR`).
//!
//! The metric is built in, or the task's scoring component (the `scorer`
//! world, run in `crate::sandbox`'s scorer engine): the recording's poses,
//! commands and status messages are handed to it in file order, and its
//! verdict is the score. A bundle carries the component's bytes
//! (`scorer.wasm`), checked against the sha256 its task pins.
//!
//! [`score_recording`] is pure over the recording's (and the scorer's)
//! bytes; [`score_bundle`] reads a bundle's `task.json`, `scorer.wasm` and
//! recordings.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use serde_json::Value as Json;
use sha2::{Digest, Sha256};
use thiserror::Error;

use crate::assemble::registry;
use crate::contract::Value;
use crate::contract::scorer_bindings::{Episode, Event, Goal as WitGoal, Position, Ranges, Sample};
use crate::store::task::{Metric, Score, Task};

/// A bundle's task, the one its score was computed for.
pub const TASK_FILE: &str = "task.json";
/// A bundle's score.
pub const SCORE_FILE: &str = "score.json";
/// The run's recording in a bundle (and its rotated files after it).
pub const RUN_RECORDING: &str = "run.mcap";
/// The preflight's recording in a bundle, and its score: the simulator's
/// side, to compare with the robot's.
pub const PREFLIGHT_RECORDING: &str = "preflight.mcap";
pub const PREFLIGHT_SCORE_FILE: &str = "preflight-score.json";
/// A bundle's scoring component, when its task's metric is one.
pub const SCORER_FILE: &str = "scorer.wasm";
/// Largest recording scored (all its files): as `subsume replay` reads.
pub const MAX_SCORED_BYTES: u64 = 4 << 30;

/// Why a run could not be scored.
#[derive(Debug, Error)]
pub enum ScoreError {
    #[error("{path}: {source}")]
    Read {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{path}: not a task: {why}")]
    Task { path: PathBuf, why: String },
    #[error("{path}: {why}")]
    Recording { path: PathBuf, why: String },
    #[error("{path}: message {index} on {topic}: {why}")]
    Message { path: PathBuf, index: u64, topic: String, why: String },
    #[error("{path}: the recording has no poses on {topic} (the task's pose port)")]
    NoPoses { path: PathBuf, topic: String },
    #[error("{path}: cannot write: {why}")]
    Write { path: PathBuf, why: String },
    /// The task's scoring component gave no score (or could not be had).
    #[error("task {task}: its scorer {component}: {why}")]
    Scorer { task: String, component: String, why: String },
}

impl ScoreError {
    fn scorer(task: &Task, why: impl Into<String>) -> ScoreError {
        let component = task.scorer.as_ref().map_or_else(|| "(none named)".to_string(), |s| s.component.clone());
        ScoreError::Scorer { task: task.name.clone(), component, why: why.into() }
    }
}

/// Checks that `bytes` are the scorer `task` pins (its sha256): the
/// bytes, or why not.
pub fn check_scorer_bytes<'b>(task: &Task, bytes: &'b [u8]) -> Result<&'b [u8], ScoreError> {
    let Some(scorer) = &task.scorer else {
        return Err(ScoreError::scorer(task, "the task's metric is scorer but it names no scorer"));
    };
    let sha256 = hex::encode(Sha256::digest(bytes));
    if sha256 != scorer.sha256 {
        return Err(ScoreError::scorer(
            task,
            format!("its bytes' sha256 is {sha256}, but the task pins {}", scorer.sha256),
        ));
    }
    Ok(bytes)
}

/// The topic a task's `COMPONENT.PORT` is recorded on.
fn topic_of(port: &str) -> String {
    match port.split_once('.') {
        Some((component, port)) => crate::record::output_topic(component, port),
        None => format!("/{port}"),
    }
}

/// The status sections' kinds the score reads (as the registry names the
/// built-ins).
struct StatusKinds {
    sim: Option<String>,
    envelope: Option<String>,
}

impl StatusKinds {
    fn registered() -> StatusKinds {
        let named = |builtin: &dyn crate::builtin::Builtin| registry::kind_of(builtin).map(|k| k.to_string());
        StatusKinds { sim: named(&crate::sim::builtin::SimBuiltin), envelope: named(&crate::envelope::EnvelopeBuiltin) }
    }
}

/// What the sums see of a recording, in file order.
#[derive(Default)]
struct Tally {
    epoch_ns: Option<u64>,
    first_ns: Option<u64>,
    last_ns: u64,
    poses: u64,
    last_pose: Option<(f64, f64)>,
    path_length_m: f64,
    reached_at_ns: Option<u64>,
    commands: u64,
    /// The command in force (left, right wheel speeds, m/s) since when.
    wheels: Option<((f64, f64), u64)>,
    energy: f64,
    collisions: Option<f64>,
    interventions: Option<BTreeMap<String, f64>>,
    /// What a scoring component is handed, when the task has one.
    samples: Option<Vec<Sample>>,
}

impl Tally {
    fn sample(&mut self, t_ns: u64, event: impl FnOnce() -> Event) {
        if let Some(samples) = &mut self.samples {
            samples.push(Sample { t_ns, event: event() });
        }
    }
}

/// The wheel speeds a command asks for: `VEL v w` on a base of `base` m;
/// anything else (STOP, a GOTO the link refuses) is at rest.
fn wheels(command: &str, base: f64) -> (f64, f64) {
    let mut words = command.split_ascii_whitespace();
    if words.next() != Some("VEL") {
        return (0.0, 0.0);
    }
    let mut number = || words.next().and_then(|w| w.parse::<f64>().ok()).filter(|n| n.is_finite());
    match (number(), number()) {
        (Some(v), Some(w)) => (v - w * base / 2.0, v + w * base / 2.0),
        _ => (0.0, 0.0),
    }
}

impl Tally {
    /// The energy of the command in force from its start to `until_ns`.
    fn close_command(&mut self, until_ns: u64) {
        if let Some(((left, right), since)) = self.wheels {
            let dt = until_ns.saturating_sub(since) as f64 / 1e9;
            self.energy += (left * left + right * right) * dt;
        }
    }
}

/// Scores the run recorded in `files` (its recording and the rotated files
/// after it, in order; `path` names it in errors) against `task`; with
/// [`Metric::Scorer`], by the scoring component `scorer` (its bytes,
/// checked against the sha256 the task pins).
pub fn score_recording(
    task: &Task,
    scorer: Option<&[u8]>,
    files: &[Vec<u8>],
    path: &Path,
) -> Result<Score, ScoreError> {
    let pose_topic = topic_of(&task.pose);
    let commands_topic = topic_of(&task.commands);
    let ranges_topic = topic_of(&task.ranges);
    let kinds = StatusKinds::registered();
    let scorer = match (task.metric, scorer) {
        (Metric::Scorer, Some(bytes)) => Some(check_scorer_bytes(task, bytes)?),
        (Metric::Scorer, None) => return Err(ScoreError::scorer(task, "its bytes are not here")),
        _ => None,
    };
    let mut tally = Tally { samples: scorer.map(|_| Vec::new()), ..Tally::default() };
    let mut index = 0u64;
    let mut hash = Sha256::new();
    for bytes in files {
        hash.update(bytes);
    }
    for bytes in files {
        if !bytes.starts_with(mcap::MAGIC) {
            return Err(ScoreError::Recording { path: path.into(), why: "not an MCAP file".into() });
        }
        let readable = crate::record::readable::readable(bytes);
        let stream = mcap::MessageStream::new_with_options(readable.bytes, mcap::read::Options::IgnoreEndMagic.into())
            .map_err(|e| ScoreError::Recording { path: path.into(), why: e.to_string() })?;
        for message in stream {
            index += 1;
            // A file cut short (a killed host) is scored up to where it ends,
            // as replay reads it.
            let Ok(message) = message else { break };
            let topic = message.channel.topic.as_str();
            let bad =
                |why: &str| ScoreError::Message { path: path.into(), index, topic: topic.to_string(), why: why.into() };
            let epoch = match tally.epoch_ns {
                Some(epoch) => epoch,
                None => {
                    let epoch = message
                        .channel
                        .metadata
                        .get("epoch_unix_ns")
                        .and_then(|e| e.parse::<u64>().ok())
                        .ok_or_else(|| bad("its channel has no epoch_unix_ns"))?;
                    *tally.epoch_ns.insert(epoch)
                }
            };
            let t = message.log_time.saturating_sub(epoch);
            tally.first_ns.get_or_insert(t);
            tally.last_ns = tally.last_ns.max(t);
            if topic == pose_topic {
                let json: Json = serde_json::from_slice(&message.data).map_err(|e| bad(&e.to_string()))?;
                let value = json["value"].as_array().ok_or_else(|| bad("no value [x, y, heading]"))?;
                let (Some(x), Some(y)) = (value.first().and_then(Json::as_f64), value.get(1).and_then(Json::as_f64))
                else {
                    return Err(bad("the value is not [x, y, heading]"));
                };
                tally.poses += 1;
                if let Some((px, py)) = tally.last_pose {
                    tally.path_length_m += (x - px).hypot(y - py);
                }
                tally.last_pose = Some((x, y));
                let heading = value.get(2).and_then(Json::as_f64).unwrap_or(0.0);
                tally.sample(t, || Event::Pose(Position { x, y, heading }));
                if tally.reached_at_ns.is_none() && task.goal.contains(x, y) {
                    tally.reached_at_ns = Some(t);
                }
            } else if topic == commands_topic {
                let json: Json = serde_json::from_slice(&message.data).map_err(|e| bad(&e.to_string()))?;
                let command = json["value"]["command"].as_str().ok_or_else(|| bad("no value {command}"))?;
                tally.commands += 1;
                tally.close_command(t);
                tally.wheels = Some((wheels(command, task.wheel_base_m), t));
                tally.sample(t, || Event::Command(command.to_string()));
            } else if topic == ranges_topic && tally.samples.is_some() {
                let json: Json = serde_json::from_slice(&message.data).map_err(|e| bad(&e.to_string()))?;
                let ranges = ranges_of(&json).ok_or_else(|| bad("not a scan or a vector of ranges"))?;
                tally.sample(t, || Event::Ranges(ranges));
            } else if topic.starts_with("/subsume/status/") {
                let json: Json = serde_json::from_slice(&message.data).map_err(|e| bad(&e.to_string()))?;
                let kind = json["kind"].as_str();
                if kind.is_some() && kind == kinds.sim.as_deref() {
                    tally.collisions = json["status"]["collisions"].as_f64();
                    if let Some(collisions) = tally.collisions {
                        tally.sample(t, || Event::Collisions(collisions));
                    }
                } else if kind.is_some() && kind == kinds.envelope.as_deref() {
                    let causes = json["status"]["causes"]
                        .as_object()
                        .map(|causes| causes.iter().filter_map(|(k, v)| v.as_f64().map(|n| (k.clone(), n))).collect());
                    tally.interventions = causes;
                    if let Some(causes) = &tally.interventions {
                        let causes: Vec<(String, f64)> = causes.iter().map(|(k, v)| (k.clone(), *v)).collect();
                        tally.sample(t, || Event::Interventions(causes));
                    }
                }
            }
        }
    }
    if tally.poses == 0 {
        return Err(ScoreError::NoPoses { path: path.into(), topic: pose_topic });
    }
    let end = tally.last_ns;
    let recorded_s = end.saturating_sub(tally.first_ns.unwrap_or(0)) as f64 / 1e9;
    let recording_sha256 = hex::encode(hash.finalize());
    if let (Some(bytes), Some(samples)) = (scorer, tally.samples.take()) {
        let episode = Episode {
            task: task.name.clone(),
            goal: WitGoal { x: task.goal.x, y: task.goal.y, radius: task.goal.radius },
            wheel_base_m: task.wheel_base_m,
            samples,
        };
        let verdict =
            crate::sandbox::run_scorer(bytes, &episode).map_err(|e| ScoreError::scorer(task, e.to_string()))?;
        return Ok(Score {
            task: task.name.clone(),
            metric: Metric::Scorer,
            value: Some(verdict.score),
            sub_scores: verdict.sub_scores.into_iter().map(|s| (s.name, s.value)).collect(),
            built_in: built_in_sub_scores(&mut tally, end),
            poses: tally.poses,
            commands: tally.commands,
            recorded_s,
            recording_sha256,
            scorer_sha256: Some(hex::encode(Sha256::digest(bytes))),
        });
    }
    let sub_scores = built_in_sub_scores(&mut tally, end);
    Ok(Score {
        task: task.name.clone(),
        metric: task.metric,
        value: sub_scores.get(task.metric.name()).copied(),
        sub_scores,
        built_in: BTreeMap::new(),
        poses: tally.poses,
        commands: tally.commands,
        recorded_s,
        recording_sha256,
        scorer_sha256: None,
    })
}

/// The built-in metrics of the run `tally` holds, ended at `end` (ns), by
/// name: each built-in metric where the recording defines it, and the
/// interventions by cause.
fn built_in_sub_scores(tally: &mut Tally, end: u64) -> BTreeMap<String, f64> {
    tally.close_command(end);
    let mut sub_scores = BTreeMap::new();
    sub_scores.insert(Metric::GoalReached.name().to_string(), if tally.reached_at_ns.is_some() { 1.0 } else { 0.0 });
    if let Some(at) = tally.reached_at_ns {
        sub_scores.insert(Metric::TimeToGoal.name().to_string(), at as f64 / 1e9);
    }
    sub_scores.insert(Metric::PathLength.name().to_string(), tally.path_length_m);
    sub_scores.insert(Metric::Energy.name().to_string(), tally.energy);
    if let Some(collisions) = tally.collisions {
        sub_scores.insert(Metric::Collisions.name().to_string(), collisions);
    }
    if let Some(causes) = &tally.interventions {
        sub_scores.insert(Metric::Interventions.name().to_string(), causes.values().sum());
        for (cause, count) in causes {
            sub_scores.insert(format!("interventions.{cause}"), *count);
        }
    }
    sub_scores
}

/// A recorded range reading as a scorer sees it: a scan (recorded as a
/// `foxglove.LaserScan`) with its geometry, a vector of ranges without.
fn ranges_of(json: &Json) -> Option<Ranges> {
    let value = match json.get("value") {
        Some(value) => crate::record::schema::value_from_json(value)?,
        None => crate::record::schema::scan_from_laser_scan(json)?,
    };
    match value {
        Value::Scan(scan) => Some(Ranges {
            angle_min: scan.angle_min,
            angle_increment: scan.angle_increment,
            range_min: scan.range_min,
            range_max: scan.range_max,
            ranges: scan.ranges,
        }),
        Value::Vector(ranges) => Some(Ranges {
            angle_min: 0.0,
            angle_increment: 0.0,
            range_min: 0.0,
            range_max: ranges.iter().copied().fold(0.0, f64::max),
            ranges,
        }),
        _ => None,
    }
}

/// `score` as `score.json` holds it.
pub fn encode(score: &Score) -> Vec<u8> {
    let mut bytes = serde_json::to_vec_pretty(score).unwrap_or_default();
    bytes.push(b'\n');
    bytes
}

/// The recording files of the run whose first file is `recording`.
pub fn recording_files(recording: &Path) -> Vec<PathBuf> {
    (0..).map(|n| crate::record::rotated_path(recording, n)).take_while(|file| file.exists()).collect()
}

/// Scores the run recorded in `recording` (and its rotated files) against
/// `task` (with its `scorer`'s bytes when it has one), reading at most
/// [`MAX_SCORED_BYTES`].
pub fn score_files(task: &Task, scorer: Option<&[u8]>, recording: &Path) -> Result<Score, ScoreError> {
    let mut files = Vec::new();
    let mut total = 0u64;
    let paths = recording_files(recording);
    if paths.is_empty() {
        return Err(ScoreError::Read {
            path: recording.into(),
            source: std::io::Error::new(std::io::ErrorKind::NotFound, "no such recording"),
        });
    }
    for path in paths {
        let size = std::fs::metadata(&path).map_err(|source| ScoreError::Read { path: path.clone(), source })?.len();
        total += size;
        if total > MAX_SCORED_BYTES {
            return Err(ScoreError::Recording {
                path: recording.into(),
                why: format!("more than {MAX_SCORED_BYTES} bytes of recording"),
            });
        }
        files.push(std::fs::read(&path).map_err(|source| ScoreError::Read { path: path.clone(), source })?);
    }
    score_recording(task, scorer, &files, recording)
}

/// Reads `dir/task.json`.
pub fn read_task(dir: &Path) -> Result<Task, ScoreError> {
    let path = dir.join(TASK_FILE);
    let bytes = std::fs::read(&path).map_err(|source| ScoreError::Read { path: path.clone(), source })?;
    serde_json::from_slice(&bytes).map_err(|e| ScoreError::Task { path, why: e.to_string() })
}

/// Scores the bundle in `dir` (its `task.json` and `run.mcap`): the score,
/// and its bytes as `score.json` holds them.
pub fn score_bundle(dir: &Path) -> Result<(Score, Vec<u8>), ScoreError> {
    score_bundle_recording(dir, RUN_RECORDING)
}

/// Reads `dir/scorer.wasm` when `task`'s metric is a scoring component
/// (at most [`crate::sandbox::MAX_COMPONENT_BYTES`]).
pub fn read_scorer(dir: &Path, task: &Task) -> Result<Option<Vec<u8>>, ScoreError> {
    if task.metric != Metric::Scorer {
        return Ok(None);
    }
    let path = dir.join(SCORER_FILE);
    crate::sandbox::read_component_file(&path).map(Some).map_err(|e| ScoreError::scorer(task, e.to_string()))
}

/// Scores `recording` of the bundle in `dir` against its `task.json` (and
/// its `scorer.wasm`, when the task's metric is one).
pub fn score_bundle_recording(dir: &Path, recording: &str) -> Result<(Score, Vec<u8>), ScoreError> {
    let task = read_task(dir)?;
    let scorer = read_scorer(dir, &task)?;
    let score = score_files(&task, scorer.as_deref(), &dir.join(recording))?;
    let bytes = encode(&score);
    Ok((score, bytes))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::store::task::Goal;

    fn task(metric: Metric) -> Task {
        Task {
            name: "reach".into(),
            description: String::new(),
            goal: Goal { x: 3.0, y: 0.0, radius: 0.5 },
            metric,
            scorer: None,
            pose: "motors.pose".into(),
            commands: "envelope.cmd".into(),
            ranges: "motors.ranges".into(),
            wheel_base_m: 0.4,
            board: Default::default(),
            pseudonyms: true,
            end_on: Vec::new(),
        }
    }

    /// An MCAP file of `messages` (topic, ns since the epoch, JSON), written
    /// with the `mcap` crate as the recorder writes them.
    fn recording(messages: &[(&str, u64, Json)]) -> Vec<u8> {
        let epoch = 1_000_000_000_000u64;
        let mut out = std::io::Cursor::new(Vec::new());
        {
            let mut writer = mcap::Writer::new(&mut out).unwrap();
            let schema = writer.add_schema("subsume.Value", "jsonschema", b"{}").unwrap();
            let mut channels = BTreeMap::new();
            for (n, (topic, t, json)) in messages.iter().enumerate() {
                let channel = *channels.entry(*topic).or_insert_with(|| {
                    let metadata = BTreeMap::from([("epoch_unix_ns".to_string(), epoch.to_string())]);
                    writer.add_channel(schema, topic, "json", &metadata).unwrap()
                });
                let header = mcap::records::MessageHeader {
                    channel_id: channel,
                    sequence: n as u32,
                    log_time: epoch + t,
                    publish_time: epoch + t,
                };
                writer.write_to_known_channel(&header, json.to_string().as_bytes()).unwrap();
            }
            writer.finish().unwrap();
        }
        out.into_inner()
    }

    fn pose(t_ms: u64, x: f64, y: f64) -> (&'static str, u64, Json) {
        ("/motors/pose", t_ms * 1_000_000, serde_json::json!({"value": [x, y, 0.0]}))
    }

    fn command(t_ms: u64, text: &str) -> (&'static str, u64, Json) {
        ("/envelope/cmd", t_ms * 1_000_000, serde_json::json!({"t": t_ms * 1_000_000, "value": {"command": text}}))
    }

    #[test]
    fn each_sub_score_is_what_the_recording_says() {
        let kinds = StatusKinds::registered();
        let (sim, envelope) = (kinds.sim.unwrap(), kinds.envelope.unwrap());
        let bytes = recording(&[
            pose(0, 0.0, 0.0),
            command(0, "VEL 0.5 0"),
            pose(1000, 1.0, 0.0),
            command(2000, "VEL 0 1"),
            pose(2000, 2.0, 0.0),
            (
                "/subsume/status/envelope",
                2_500_000_000,
                serde_json::json!({"kind": envelope, "status": {"causes": {"stop_zone": 2, "geofence": 1}}}),
            ),
            pose(3000, 2.75, 0.0),
            command(3000, "STOP"),
            ("/subsume/status/robot-sim", 3_500_000_000, serde_json::json!({"kind": sim, "status": {"collisions": 1}})),
            pose(4000, 2.75, 0.0),
        ]);
        let score = score_recording(&task(Metric::TimeToGoal), None, &[bytes], Path::new("run.mcap")).unwrap();
        let expected: BTreeMap<String, f64> = [
            ("goal_reached", 1.0),
            ("time_to_goal_s", 3.0),
            ("path_length_m", 2.75),
            // 2 s at 0.5 m/s on both wheels, then 1 s turning at 0.2 m/s
            // each way, then rest until the end.
            ("energy", 2.0 * 0.5 + 1.0 * 0.08),
            ("collisions", 1.0),
            ("interventions", 3.0),
            ("interventions.geofence", 1.0),
            ("interventions.stop_zone", 2.0),
        ]
        .into_iter()
        .map(|(k, v)| (k.to_string(), v))
        .collect();
        assert_eq!(score.sub_scores.len(), expected.len(), "{score:#?}");
        for (name, value) in &expected {
            assert!((score.sub_scores[name] - value).abs() < 1e-12, "{name}: {score:#?}");
        }
        assert_eq!((score.value, score.poses, score.commands, score.recorded_s), (Some(3.0), 5, 3, 4.0));
    }

    #[test]
    fn the_metric_picks_its_sub_score_and_an_undefined_one_has_no_value() {
        let never = recording(&[pose(0, 0.0, 0.0), pose(1000, 1.0, 0.0)]);
        let cases = [
            (Metric::TimeToGoal, None),
            (Metric::GoalReached, Some(0.0)),
            (Metric::PathLength, Some(1.0)),
            (Metric::Collisions, None),
            (Metric::Interventions, None),
            (Metric::Energy, Some(0.0)),
        ];
        for (metric, expected) in cases {
            let score =
                score_recording(&task(metric), None, std::slice::from_ref(&never), Path::new("run.mcap")).unwrap();
            assert_eq!(score.value, expected, "{metric:?}");
        }
    }

    #[test]
    fn a_recording_that_cannot_be_scored_says_why() {
        let no_poses = recording(&[command(0, "STOP")]);
        let bad_pose = recording(&[("/motors/pose", 0, serde_json::json!({"value": "here"}))]);
        let cases: [(&str, Vec<u8>, &str); 3] = [
            ("no poses", no_poses, "run.mcap: the recording has no poses on /motors/pose (the task's pose port)"),
            ("a pose without [x, y]", bad_pose, "run.mcap: message 1 on /motors/pose: no value [x, y, heading]"),
            ("not mcap", b"hello".to_vec(), "run.mcap: not an MCAP file"),
        ];
        for (case, bytes, expected) in cases {
            let error = score_recording(&task(Metric::PathLength), None, &[bytes], Path::new("run.mcap")).unwrap_err();
            assert_eq!(error.to_string(), expected, "{case}");
        }
    }

    #[test]
    fn the_same_bytes_score_the_same_bits() {
        let bytes =
            recording(&[pose(0, 0.1, 0.2), command(5, "VEL 0.31 -0.7"), pose(13, 0.4, 0.9), pose(29, 1.7, 0.3)]);
        let first = encode(
            &score_recording(&task(Metric::Energy), None, std::slice::from_ref(&bytes), Path::new("a")).unwrap(),
        );
        let again = encode(&score_recording(&task(Metric::Energy), None, &[bytes], Path::new("a")).unwrap());
        assert_eq!(first, again);
    }
}
