//! An experiment's results (docs/lab.md, Results): the files kept in its
//! folder of the store, and the one archive they are given back as
//! (`GET /api/v1/experiments/{id}/results`, a tar file):
//!
//! ```text
//! experiment.json          the record: states with times, submitter, settings that applied
//! robot.xml                the set's robot file in its preflight form (sources under components/)
//! components/NAME.wasm     each WASM component's bytes as it ran
//! files/...                the files robot.xml names (the preflight's world)
//! run.mcap (.1.mcap ...)   the recording of the run on the robot
//! report.json              the run's report (envelope interventions, collisions, goal, faults, call times)
//! log.txt                  the host's log while it ran (from the recording)
//! video-CAMERA.webm        each camera's video of the run (VP9, made by ffmpeg from its frames)
//! video.txt                why a camera has no video (no ffmpeg on the robot, ...), if one has none
//! selftest.json            the robot's self-test after the run, when the owner has one (docs/lab.md)
//! preflight.mcap, preflight-report.json, preflight-verdict.json, preflight.log
//! task.json, score.json    the owner's task and the run's score (preflight-score.json: the preflight's)
//! scorer.wasm              the task's scoring component, when its metric is one (`subsume score` runs it)
//! SHA256SUMS               every other file's sha256 (`sha256sum -c SHA256SUMS`)
//! ```
//!
//! `subsume replay run.mcap robot.xml` on an unpacked bundle reproduces the
//! experiment's WASM components' outputs bit for bit.
//!
//! Retention: the results of finished experiments count against the
//! owner's cap (`retention_bytes`); beyond it the oldest finished
//! experiments' recordings go first, and their records stay, marked
//! `recording_expired`.

use std::collections::BTreeMap;
use std::io::{Read, Write};
use std::path::{Path, PathBuf};

use serde_json::Value as Json;
use sha2::{Digest, Sha256};

use crate::deploy::Ended;
use crate::fsutil::HiddenPaths;
use crate::store::experiments::{ExperimentRecord, ResultFile, RunResult};
use crate::store::{Store, StoreError};

pub const RUN_RECORDING: &str = "run.mcap";
pub const REPORT: &str = "report.json";
pub const LOG: &str = "log.txt";
pub const ROBOT: &str = "robot.xml";
pub const RECORD: &str = "experiment.json";
pub const SUMS: &str = "SHA256SUMS";
/// Why a camera of the run has no video (absent when every camera has one).
pub const VIDEO_NOTE: &str = "video.txt";

/// Largest recording the log is read from (the whole file is read into
/// memory): past it the log says so instead.
pub const MAX_LOG_SOURCE_BYTES: u64 = 1 << 30;

/// Lines of the log kept: a component logging in a loop for two minutes
/// must not make a giant text file.
pub const MAX_LOG_LINES: usize = 200_000;

/// Whether the archive's file `name` is text whose server folders are
/// hidden as it is served ([`write_tar`]): everything but the recordings
/// (MCAP offsets would break; what they carry is hidden as they are
/// written) and the components' bytes.
fn hides_folders(name: &str) -> bool {
    !name.ends_with(".mcap") && !name.ends_with(".wasm") && !crate::record::video::is_video_name(name)
}

/// A copy of `reader` with `hidden`'s folders named, a line at a time, in
/// a temporary file (a log is never held whole); the copy and its size.
fn hidden_copy(reader: impl Read, hidden: &HiddenPaths) -> std::io::Result<(Box<dyn Read>, u64)> {
    let mut copy = tempfile::tempfile()?;
    {
        let mut out = std::io::BufWriter::new(&mut copy);
        let mut lines = std::io::BufReader::new(reader);
        let mut line = Vec::new();
        while std::io::BufRead::read_until(&mut lines, b'\n', &mut line)? > 0 {
            out.write_all(&hidden.hide_bytes(&line))?;
            line.clear();
        }
        out.flush()?;
    }
    let size = copy.metadata()?.len();
    std::io::Seek::seek(&mut copy, std::io::SeekFrom::Start(0))?;
    Ok((Box::new(copy), size))
}

/// Rewrites the text file at `path` with `hidden`'s folders named, a line
/// at a time through a temporary file beside it (fsynced, renamed in): a
/// robot's result files before they leave for its lab server, which hides
/// only its own folders. Naming again is harmless: a name is no folder.
pub fn hide_in_place(path: &Path, hidden: &HiddenPaths) -> std::io::Result<()> {
    if hidden.is_empty() || !path.is_file() {
        return Ok(());
    }
    let (mut copy, _) = hidden_copy(std::fs::File::open(path)?, hidden)?;
    let dir = path.parent().unwrap_or(Path::new("."));
    let mut temp = tempfile::NamedTempFile::new_in(dir)?;
    std::io::copy(&mut copy, temp.as_file_mut())?;
    temp.as_file().sync_all()?;
    temp.persist(path).map_err(|e| e.error)?;
    std::fs::File::open(dir)?.sync_all()
}

/// One file of the archive and where its bytes come from.
#[derive(Clone, Debug)]
pub enum Source {
    /// A file of the experiment's folder.
    File(PathBuf),
    /// A blob of the store (a component's bytes).
    Blob(String),
    /// Made for the archive (the record, the sums).
    Bytes(Vec<u8>),
}

/// The archive's files, in order.
#[derive(Clone, Debug)]
pub struct Contents {
    /// The folder the archive unpacks into (`experiment-12`, `lab-kit`).
    pub folder: String,
    pub entries: Vec<(String, Source)>,
}

/// Whether `name` is a file the results keep: the known names, and the
/// rotations of the run's recording (`run.1.mcap`, ...).
pub fn is_result_file(name: &str) -> bool {
    const KEPT: [&str; 9] = [
        REPORT,
        LOG,
        ROBOT,
        RUN_RECORDING,
        PREFLIGHT_RECORDING,
        "preflight-report.json",
        "preflight-verdict.json",
        "preflight.log",
        super::preflight_runs::RUNS_FILE,
    ];
    KEPT.contains(&name)
        || name == VIDEO_NOTE
        || name == super::selftest::SELF_TEST_FILE
        || name == crate::score::TASK_FILE
        || name == crate::score::SCORE_FILE
        || name == crate::score::PREFLIGHT_SCORE_FILE
        || name == crate::score::SCORER_FILE
        || crate::record::video::is_video_name(name)
        || name.strip_prefix("run.").and_then(|r| r.strip_suffix(".mcap")).is_some_and(|n| n.parse::<u32>().is_ok())
        || name.strip_prefix("files/").is_some_and(|f| !f.contains('/') && !f.starts_with('.'))
}

/// The result files in experiment `id`'s folder, with their sizes, sorted.
pub fn scan(store: &Store, id: u64) -> Vec<ResultFile> {
    let dir = store.experiment_dir(id);
    let mut files = Vec::new();
    let mut look = |relative: String, path: PathBuf| {
        if is_result_file(&relative)
            && let Ok(meta) = std::fs::symlink_metadata(&path)
            && meta.is_file()
        {
            files.push(ResultFile { name: relative, bytes: meta.len() });
        }
    };
    for folder in ["", "files"] {
        let Ok(entries) = std::fs::read_dir(dir.join(folder)) else { continue };
        for entry in entries.flatten() {
            let name = entry.file_name().to_string_lossy().into_owned();
            let relative = if folder.is_empty() { name } else { format!("{folder}/{name}") };
            look(relative, entry.path());
        }
    }
    files.sort_by(|a, b| a.name.cmp(&b.name));
    files
}

/// The host's log lines in the recording at `path` (`/subsume/log`),
/// one per line: `SECONDS LEVEL NAME: MESSAGE`.
pub fn log_of(path: &Path) -> String {
    let size = std::fs::metadata(path).map(|m| m.len()).unwrap_or(0);
    if size > MAX_LOG_SOURCE_BYTES {
        return format!("(the recording is {size} bytes, more than the {MAX_LOG_SOURCE_BYTES} read for the log)\n");
    }
    let Ok(bytes) = std::fs::read(path) else { return String::new() };
    let readable = crate::record::readable::readable(&bytes);
    let Ok(stream) = mcap::MessageStream::new_with_options(readable.bytes, mcap::read::Options::IgnoreEndMagic.into())
    else {
        return String::new();
    };
    let mut out = String::new();
    let mut lines = 0;
    for message in stream {
        // A killed host's recording ends without a footer: what came
        // before the cut is all there is.
        let Ok(message) = message else { break };
        if message.channel.topic != crate::record::LOG_TOPIC {
            continue;
        }
        let Ok(json) = serde_json::from_slice::<Json>(&message.data) else { continue };
        let level = match json["level"].as_u64() {
            Some(4) => "ERROR",
            Some(3) => "WARN",
            Some(2) => "INFO",
            _ => "DEBUG",
        };
        let seconds = json["timestamp"]["sec"].as_u64().unwrap_or(0);
        let nanos = json["timestamp"]["nsec"].as_u64().unwrap_or(0);
        out.push_str(&format!(
            "{seconds}.{:03} {level} {}: {}\n",
            nanos / 1_000_000,
            json["name"].as_str().unwrap_or(""),
            json["message"].as_str().unwrap_or("")
        ));
        lines += 1;
        if lines >= MAX_LOG_LINES {
            out.push_str(&format!("(the log stops here: at most {MAX_LOG_LINES} lines are kept)\n"));
            break;
        }
    }
    out
}

/// Writes what experiment `record`'s run on the robot left (the report,
/// the log from its recording) into its folder, and fills in its run
/// summary and result files. The videos are made before, by
/// [`write_videos`], with no lock held (ffmpeg takes seconds). `watchdog_margin_ms`: how late a cycle may
/// start before the serial link's watchdog could stop the robot for it.
pub fn write_run_results(
    store: &Store,
    record: &mut ExperimentRecord,
    ended: &Ended,
    started_ms: u64,
    watchdog_margin_ms: f64,
) {
    let dir = store.experiment_dir(record.id);
    let mut run = RunResult { started_ms, ended_ms: crate::runtime::locks::unix_now_ms(), ..RunResult::default() };
    if let Some(report) = &ended.report {
        run.ran_s = report.duration_s;
        run.worst_lateness_ms = report.loop_lateness.max_ms;
        run.late_cycles = report.loop_lateness.histogram.count_above((watchdog_margin_ms * 1e6) as u64);
        run.outcome = Some(super::preflight::outcome(report));
        match serde_json::to_vec_pretty(report) {
            Ok(bytes) => {
                if let Err(e) = crate::fsutil::write_atomically(&dir.join(REPORT), &bytes) {
                    tracing::error!("experiment {}: cannot write its report: {e}", record.id);
                }
            }
            Err(e) => tracing::error!("experiment {}: cannot encode its report: {e}", record.id),
        }
    }
    write_log(&dir, record.id);
    record.run = Some(run);
    record.results = scan(store, record.id);
}

/// Writes the self-test that followed experiment `record`'s run into its
/// folder, with its result files.
pub fn write_self_test(store: &Store, record: &mut ExperimentRecord, test: &crate::store::experiments::SelfTest) {
    let path = store.experiment_dir(record.id).join(super::selftest::SELF_TEST_FILE);
    let written = serde_json::to_vec_pretty(test)
        .map_err(|e| e.to_string())
        .and_then(|bytes| crate::fsutil::write_atomically(&path, &bytes).map_err(|e| e.to_string()));
    if let Err(e) = written {
        tracing::error!("experiment {}: cannot write its self-test: {e}", record.id);
    }
    record.results = scan(store, record.id);
}

fn write_log(dir: &Path, id: u64) {
    let log = log_of(&dir.join(RUN_RECORDING));
    if let Err(e) = crate::fsutil::write_atomically(&dir.join(LOG), log.as_bytes()) {
        tracing::error!("experiment {id}: cannot write its log: {e}");
    }
}

/// Scores experiment `id`'s run (its recording, stopped) against `task`:
/// `task.json` and `score.json` written in its folder, for anyone to
/// recompute (`subsume score`). Reads the whole recording: called with no
/// lock held, before [`write_run_results`].
pub fn write_score(
    store: &Store,
    id: u64,
    task: &crate::store::task::Task,
) -> Result<crate::store::task::Score, crate::score::ScoreError> {
    write_score_of(store, id, task, RUN_RECORDING, crate::score::SCORE_FILE)
}

/// The preflight's recording in an experiment's folder, and its score.
pub const PREFLIGHT_RECORDING: &str = crate::score::PREFLIGHT_RECORDING;
pub const PREFLIGHT_SCORE: &str = crate::score::PREFLIGHT_SCORE_FILE;

/// Scores the recording `recording` of experiment `id`'s folder against
/// `task` into `score_file`, with `task.json` beside it (and, when the
/// task's metric is a scoring component, its bytes from the store as
/// `scorer.wasm`: the bundle alone recomputes the score).
pub fn write_score_of(
    store: &Store,
    id: u64,
    task: &crate::store::task::Task,
    recording: &str,
    score_file: &str,
) -> Result<crate::store::task::Score, crate::score::ScoreError> {
    use crate::score::ScoreError;
    let dir = store.experiment_dir(id);
    let scorer = match task.scorer.as_ref().filter(|_| task.metric == crate::store::task::Metric::Scorer) {
        Some(scorer) => Some(store.blob(&scorer.sha256).map_err(|e| ScoreError::Scorer {
            task: task.name.clone(),
            component: scorer.component.clone(),
            why: format!("its bytes cannot be read from the store: {e}"),
        })?),
        None => None,
    };
    let task_path = dir.join(crate::score::TASK_FILE);
    let task_json = serde_json::to_vec_pretty(task)
        .map_err(|e| ScoreError::Write { path: task_path.clone(), why: e.to_string() })?;
    let write = |path: PathBuf, bytes: &[u8]| {
        crate::fsutil::write_atomically(&path, bytes).map_err(|e| ScoreError::Write { path, why: e.to_string() })
    };
    // The task and its scorer first: a run the scorer faults on still
    // carries what anyone needs to see why.
    write(task_path, &task_json)?;
    if let Some(bytes) = &scorer {
        write(dir.join(crate::score::SCORER_FILE), bytes)?;
    }
    let score = crate::score::score_files(task, scorer.as_deref(), &dir.join(recording))?;
    write(dir.join(score_file), &crate::score::encode(&score))?;
    Ok(score)
}

/// Makes each camera's video of experiment `id`'s run from its recording
/// (stopped), and says in [`VIDEO_NOTE`] why a camera has none. Seconds of
/// ffmpeg: called with no lock held, before [`write_run_results`].
pub fn write_videos(store: &Store, id: u64) {
    let dir = store.experiment_dir(id);
    let dir = dir.as_path();
    let recording = dir.join(RUN_RECORDING);
    let files: Vec<PathBuf> =
        (0..).map(|n| crate::record::rotated_path(&recording, n)).take_while(|file| file.exists()).collect();
    let outcome = crate::record::video::make_videos(&files, dir, Path::new(crate::record::video::FFMPEG));
    let note = dir.join(VIDEO_NOTE);
    if outcome.missing.is_empty() {
        let _ = std::fs::remove_file(&note);
        return;
    }
    let mut text = String::new();
    for (camera, why) in &outcome.missing {
        tracing::warn!("experiment {id}: camera {camera} has no video: {why}");
        text.push_str(&format!("camera {camera}: no video: {why}\n"));
    }
    if let Err(e) = crate::fsutil::write_atomically(&note, text.as_bytes()) {
        tracing::error!("experiment {id}: cannot write {VIDEO_NOTE}: {e}");
    }
}

/// What a host that stopped during experiment `record` left of it (found
/// at the next start): its recording as it was cut, and the log in it.
pub fn salvage(store: &Store, record: &mut ExperimentRecord) {
    let dir = store.experiment_dir(record.id);
    write_log(&dir, record.id);
    record.results = scan(store, record.id);
}

/// The archive of experiment `record`'s results.
/// What of an experiment's set the one who downloads its results may
/// have (`store::access`): the rest is named by its hash in the record.
pub struct Readable<'a> {
    /// The set's robot file (`robot.xml`).
    pub robot_file: bool,
    /// A component's bytes, by their sha256.
    pub component: &'a dyn Fn(&str) -> bool,
}

pub fn contents(store: &Store, record: &ExperimentRecord, readable: &Readable<'_>) -> Result<Contents, StoreError> {
    let dir = store.experiment_dir(record.id);
    let record_json = serde_json::to_vec_pretty(record)
        .map_err(|e| StoreError::Io { path: dir.join(RECORD), reason: e.to_string() })?;
    let mut entries = vec![(RECORD.to_string(), Source::Bytes(record_json))];
    for file in scan(store, record.id) {
        if file.name == ROBOT && !readable.robot_file {
            continue;
        }
        let path = dir.join(&file.name);
        entries.push((file.name, Source::File(path)));
    }
    for component in &record.components {
        if let Some(sha) = component.sha256.as_ref().filter(|sha| (readable.component)(sha)) {
            entries.push((format!("components/{}.wasm", component.name), Source::Blob(sha.clone())));
        }
    }
    Ok(Contents { folder: format!("experiment-{}", record.id), entries })
}

/// The bytes of one source, read whole (components and reports are small
/// next to recordings, which are streamed by [`write_tar`]).
fn open(store: &Store, source: &Source) -> std::io::Result<(Box<dyn Read>, u64)> {
    match source {
        Source::File(path) => {
            let file = std::fs::File::open(path)?;
            let size = file.metadata()?.len();
            Ok((Box::new(file), size))
        }
        Source::Blob(sha) => {
            let bytes = store.blob(sha).map_err(std::io::Error::other)?;
            let size = bytes.len() as u64;
            Ok((Box::new(std::io::Cursor::new(bytes)), size))
        }
        Source::Bytes(bytes) => Ok((Box::new(std::io::Cursor::new(bytes.clone())), bytes.len() as u64)),
    }
}

/// Hashes what `reader` gives while it is read.
struct Hashing<R> {
    inner: R,
    hash: Sha256,
}

impl<R: Read> Read for Hashing<R> {
    fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
        let n = self.inner.read(buf)?;
        self.hash.update(&buf[..n]);
        Ok(n)
    }
}

/// Writes `contents` as a tar archive (in its folder) to `out`, ending
/// with `SHA256SUMS` of every file before it. Files are streamed, never
/// held whole; in every text file the `hidden` folders (the store, the
/// robot file's folder: the owner's machine) are named, never spelled out.
pub fn write_tar(store: &Store, contents: &Contents, hidden: &HiddenPaths, out: impl Write) -> std::io::Result<()> {
    let folder = &contents.folder;
    let mut builder = tar::Builder::new(out);
    let mut sums = String::new();
    for (name, source) in &contents.entries {
        let (reader, size) = open(store, source)?;
        let (reader, size) = if hides_folders(name) && !hidden.is_empty() {
            hidden_copy(reader.take(size), hidden)?
        } else {
            (reader, size)
        };
        let mut header = tar::Header::new_gnu();
        header.set_size(size);
        header.set_mode(0o644);
        header.set_mtime(crate::store::unix_now());
        header.set_entry_type(tar::EntryType::Regular);
        let mut hashing = Hashing { inner: reader.take(size), hash: Sha256::new() };
        builder.append_data(&mut header, format!("{folder}/{name}"), &mut hashing)?;
        sums.push_str(&format!("{}  {name}\n", hex::encode(hashing.hash.finalize())));
    }
    let mut header = tar::Header::new_gnu();
    header.set_size(sums.len() as u64);
    header.set_mode(0o644);
    header.set_mtime(crate::store::unix_now());
    header.set_entry_type(tar::EntryType::Regular);
    builder.append_data(&mut header, format!("{folder}/{SUMS}"), sums.as_bytes())?;
    builder.into_inner()?.flush()
}

/// The recordings of an experiment (what retention removes first).
fn recordings(record: &ExperimentRecord) -> impl Iterator<Item = &ResultFile> {
    record.results.iter().filter(|f| f.name.ends_with(".mcap"))
}

/// Removes the recordings of the oldest finished experiments until the
/// results of all of them fit in `cap` bytes; returns the experiments
/// changed (their records must be stored).
pub fn enforce_retention<'r>(
    store: &Store,
    experiments: impl Iterator<Item = &'r mut ExperimentRecord>,
    cap: u64,
) -> Vec<u64> {
    let mut finished: Vec<&mut ExperimentRecord> = experiments.filter(|r| r.state.is_final()).collect();
    let mut total: u64 = finished.iter().flat_map(|r| r.results.iter()).map(|f| f.bytes).sum();
    let mut changed = Vec::new();
    finished.sort_by_key(|r| r.id);
    // Each user's recordings: the one holding the most gives first, so
    // one user's churn expires her own results, not everyone's.
    let mut held: BTreeMap<String, u64> = BTreeMap::new();
    for record in &finished {
        *held.entry(record.submitter.clone()).or_default() += recordings(record).map(|f| f.bytes).sum::<u64>();
    }
    while total > cap {
        let Some(user) = held
            .iter()
            .filter(|(_, b)| **b > 0)
            .max_by_key(|(u, b)| (**b, std::cmp::Reverse(*u)))
            .map(|(u, _)| u.clone())
        else {
            break;
        };
        let Some(record) = finished.iter_mut().find(|r| r.submitter == user && recordings(r).any(|f| f.bytes > 0))
        else {
            held.remove(&user);
            continue;
        };
        let dir = store.experiment_dir(record.id);
        let freed: u64 = recordings(record).map(|f| f.bytes).sum();
        for file in recordings(record) {
            if let Err(e) = std::fs::remove_file(dir.join(&file.name)) {
                tracing::warn!("experiment {}: cannot remove {}: {e}", record.id, file.name);
            }
        }
        record.results.retain(|f| !f.name.ends_with(".mcap"));
        record.recording_expired = true;
        total = total.saturating_sub(freed);
        if let Some(bytes) = held.get_mut(&user) {
            *bytes = bytes.saturating_sub(freed);
        }
        tracing::info!(
            "experiment {} ({user}): its recordings expired ({freed} bytes; the retention cap is {cap}, and {user} held the most)",
            record.id
        );
        changed.push(record.id);
    }
    changed
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::store::experiments::{AppliedSettings, ExperimentState, LAB_FORMAT, ResetPolicy};

    /// Experiment `id` in `state` with a report of 100 bytes and a
    /// recording of 1000, both written in its folder.
    fn experiment(store: &Store, id: u64, state: ExperimentState) -> ExperimentRecord {
        let dir = store.experiment_dir(id);
        std::fs::create_dir_all(&dir).unwrap();
        std::fs::write(dir.join(REPORT), vec![b'r'; 100]).unwrap();
        std::fs::write(dir.join(RUN_RECORDING), vec![b'm'; 1000]).unwrap();
        ExperimentRecord {
            format: LAB_FORMAT,
            id,
            submitter: "ana".into(),
            set: 1,
            label: String::new(),
            duration_s: 1.0,
            submitted_ms: id,
            state,
            history: Vec::new(),
            reasons: Vec::new(),
            settings: AppliedSettings {
                max_duration_s: 120.0,
                limits: Default::default(),
                criteria: Default::default(),
                reset: ResetPolicy::Sim,
                preflight_world: None,
                baseline: None,
                task: None,
            },
            components: Vec::new(),
            preflight: None,
            run: None,
            results: vec![
                ResultFile { name: REPORT.into(), bytes: 100 },
                ResultFile { name: RUN_RECORDING.into(), bytes: 1000 },
            ],
            recording_expired: false,
            first_wait_ms: None,
            origin: None,
            placement: None,
            reset: None,
            score: None,
        }
    }

    /// (cap in bytes, the experiments whose recordings expire): four
    /// finished experiments (1, 2, 4, 5: 4,400 bytes) and a running one (3).
    #[test]
    fn retention_removes_the_oldest_finished_recordings_first_and_keeps_the_records() {
        let cases: [(u64, &[u64]); 5] =
            [(10_000, &[]), (4_400, &[]), (4_399, &[1]), (2_400, &[1, 2]), (0, &[1, 2, 4, 5])];
        for (cap, expired) in cases {
            let dir = tempfile::tempdir().unwrap();
            let store = Store::open(dir.path()).unwrap();
            let states = [
                ExperimentState::Done,
                ExperimentState::Aborted,
                ExperimentState::Running,
                ExperimentState::Cancelled,
                ExperimentState::Done,
            ];
            let mut records: Vec<ExperimentRecord> =
                states.into_iter().zip(1..).map(|(state, id)| experiment(&store, id, state)).collect();
            let changed = enforce_retention(&store, records.iter_mut(), cap);
            assert_eq!(changed, expired, "cap {cap}");
            for record in &records {
                let gone = expired.contains(&record.id);
                let dir = store.experiment_dir(record.id);
                assert_eq!(record.recording_expired, gone, "cap {cap}, experiment {}", record.id);
                assert_eq!(!dir.join(RUN_RECORDING).exists(), gone, "cap {cap}, experiment {}", record.id);
                assert!(dir.join(REPORT).exists(), "cap {cap}: experiment {}'s report went", record.id);
                assert_eq!(record.results.len(), if gone { 1 } else { 2 }, "cap {cap}");
            }
        }
    }

    /// Ben's two old runs and Ana's four newer ones: the cap takes from
    /// whoever holds the most first (Ana, her oldest), so one user's
    /// churn never expires another's results before her own.
    #[test]
    fn retention_takes_first_from_the_user_who_holds_the_most() {
        let cases: [(u64, &[u64]); 4] = [(6_600, &[]), (6_599, &[3]), (4_600, &[3, 4]), (3_299, &[3, 4, 5, 1])];
        for (cap, expired) in cases {
            let dir = tempfile::tempdir().unwrap();
            let store = Store::open(dir.path()).unwrap();
            let mut records: Vec<ExperimentRecord> = (1..=6)
                .map(|id| {
                    let mut record = experiment(&store, id, ExperimentState::Done);
                    record.submitter = if id <= 2 { "ben".into() } else { "ana".into() };
                    record
                })
                .collect();
            assert_eq!(enforce_retention(&store, records.iter_mut(), cap), expired, "cap {cap}");
        }
    }

    #[test]
    fn only_known_result_files_are_kept() {
        for name in [REPORT, LOG, ROBOT, RUN_RECORDING, "run.1.mcap", "run.12.mcap", "preflight.mcap", "files/a.world"]
        {
            assert!(is_result_file(name), "{name}");
        }
        for name in ["video-camera.webm", VIDEO_NOTE, "task.json", "score.json", "scorer.wasm"] {
            assert!(is_result_file(name), "{name}");
        }
        for name in [
            "video-../x.webm",
            "video-.webm",
            "experiment.json",
            "run.x.mcap",
            "../x",
            "files/../x",
            "files/.hidden",
            "preflight-run",
            "other",
        ] {
            assert!(!is_result_file(name), "{name}");
        }
    }
}
