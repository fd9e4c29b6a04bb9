//! Recordings started and stopped while the host runs (the portal's
//! Recordings tab, `POST /api/v1/recordings/start` and `/stop`): a
//! host-owned folder of MCAP files whose names the host makes up, at most
//! one recording at a time, and the control loop's hook ([`ControlledHook`])
//! that attaches the recording's tap between two cycles and detaches it
//! again. A recording "from a fresh start" is attached in the very
//! `between_cycles` in which an activation swaps a new graph in, so the
//! new graph's first call is recorded and every component starts inside
//! the recording; its time line starts there too (its `epoch_unix_ns` is
//! the wall-clock time of the swap), and nothing from before it, not even
//! a log line, is in it.
//!
//! Invariants: a file name a user gives is only ever looked up in the
//! folder (checked against [`is_recording_name`]), never used as a path; the
//! control thread never waits on a user (it takes the request with
//! `try_lock`); stopping writes the summary and footer like a clean stop of
//! `--record`; the same size limit and rotation apply.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

use serde::Serialize;
use thiserror::Error;

use super::{Event, Layout, RecordError, RecordOptions, RecordTap, Recorder, Sink, Timeline, sample_status};
use crate::runtime::Graph;
use crate::runtime::control_loop::CycleHook;

/// Files the recordings folder may hold before a new recording is refused:
/// a user starting and stopping in a loop must not fill the robot's disk
/// with files (each file is bounded by the size limit; delete old ones).
pub const MAX_STORED_RECORDINGS: usize = 200;
/// Longest recording file name (they are host-made: `rec-DATE-TIME-N.mcap`
/// and its rotations).
pub const MAX_RECORDING_NAME_LEN: usize = 64;

/// Why a recording request was refused or failed.
#[derive(Debug, Error)]
pub enum RecordingError {
    #[error("a recording is running already: {0} (stop it first)")]
    Running(String),
    #[error("no recording is running")]
    NotRunning,
    #[error("this run records with --record or --foxglove already; the graph has one recording tap")]
    CommandLine,
    #[error("'{0}' is not a recording name (rec-DATE-TIME-N.mcap, as GET /api/v1/recordings lists them)")]
    BadName(String),
    #[error("no recording '{0}'")]
    NotFound(String),
    #[error("'{0}' is being written by the running recording; stop it first")]
    InUse(String),
    #[error("the recordings folder holds {0} files, the most allowed: delete old recordings first")]
    Full(usize),
    #[error("recordings folder {path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error(transparent)]
    Record(#[from] RecordError),
    #[error("the recordings' state is unusable (a thread panicked holding it)")]
    Poisoned,
}

/// The running recording as the portal shows it.
#[derive(Clone, Debug, Serialize, schemars::JsonSchema)]
pub struct RecordingInfo {
    pub name: String,
    pub by: String,
    pub started_unix_ms: u64,
    /// Started at a re-activation: every component starts inside it.
    pub fresh_start: bool,
}

/// One file of the recordings folder.
#[derive(Clone, Debug, Serialize, schemars::JsonSchema)]
pub struct RecordingFile {
    pub name: String,
    pub bytes: u64,
    pub modified_unix_ms: u64,
    /// The running recording is writing it.
    pub recording: bool,
}

/// What a stopped recording wrote.
#[derive(Clone, Debug, Serialize, schemars::JsonSchema)]
pub struct Stopped {
    pub name: String,
    pub by: String,
    /// Every file, in order (rotation adds `.1`, `.2`, ...).
    pub files: Vec<String>,
    pub messages: u64,
    pub bytes: u64,
    pub dropped: u64,
}

/// What the control thread should do at its next chance.
#[derive(Default)]
enum Request {
    #[default]
    None,
    Attach(Sink),
    /// Attach to the first graph swapped in after the hook's swap count
    /// was `after`, in the `between_cycles` of that swap.
    AttachAfterSwap {
        sink: Sink,
        after: u64,
    },
    Detach,
}

struct Running {
    info: RecordingInfo,
    /// The recording's first file.
    path: PathBuf,
    recorder: Recorder,
}

/// The host's recordings: the folder, the one running, and the request
/// the control thread picks up.
pub struct Recordings {
    dir: PathBuf,
    max_file_bytes: u64,
    timeline: Timeline,
    /// `--record` runs: the graph's tap is taken.
    command_line: bool,
    running: Mutex<Option<Running>>,
    request: Arc<Mutex<Request>>,
    serial: AtomicU64,
    /// The folders these recordings name instead of spelling them out
    /// (they are downloaded by remote users).
    hidden: Mutex<crate::fsutil::HiddenPaths>,
}

impl std::fmt::Debug for Recordings {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Recordings({})", self.dir.display())
    }
}

fn unix_ms(time: std::time::SystemTime) -> u64 {
    time.duration_since(std::time::UNIX_EPOCH).map_or(0, |d| d.as_millis() as u64)
}

/// `YYYYMMDD-HHMMSS` in UTC.
fn utc_stamp(unix_s: u64) -> String {
    crate::walltime::stamp(unix_s)
}

/// Whether `name` is a name this host gives recordings (and so a plain
/// file name inside the folder): `rec-`, digits and dashes, an optional
/// rotation number, `.mcap`.
pub fn is_recording_name(name: &str) -> bool {
    let Some(stem) = name.strip_prefix("rec-").and_then(|n| n.strip_suffix(".mcap")) else { return false };
    let (base, rotation) = match stem.split_once('.') {
        Some((base, n)) => (base, Some(n)),
        None => (stem, None),
    };
    name.len() <= MAX_RECORDING_NAME_LEN
        && !base.is_empty()
        && base.bytes().all(|b| b.is_ascii_digit() || b == b'-')
        && rotation.is_none_or(|n| !n.is_empty() && n.bytes().all(|b| b.is_ascii_digit()))
}

impl Recordings {
    /// The recordings in `dir` (created if missing), each file at most
    /// `max_file_bytes` before rotating, on `timeline` (the graph's clock).
    /// `command_line`: `--record` runs, so none may start here.
    pub fn new(
        dir: PathBuf,
        max_file_bytes: u64,
        timeline: Timeline,
        command_line: bool,
    ) -> Result<Recordings, RecordingError> {
        std::fs::create_dir_all(&dir).map_err(|source| RecordingError::Io { path: dir.clone(), source })?;
        let probe = RecordOptions {
            path: Some(dir.join("rec-0.mcap")),
            max_file_bytes,
            max_total_bytes: u64::MAX,
            live: None,
            hidden: Default::default(),
            for_owner: None,
        };
        probe.check()?;
        Ok(Recordings {
            dir,
            max_file_bytes,
            timeline,
            command_line,
            running: Mutex::new(None),
            request: Arc::new(Mutex::new(Request::None)),
            serial: AtomicU64::new(0),
            hidden: Mutex::new(crate::fsutil::HiddenPaths::default()),
        })
    }

    /// Every recording started from now on names `hidden`'s folders
    /// instead of spelling them out (known once the deployer is built).
    pub fn hide(&self, hidden: crate::fsutil::HiddenPaths) {
        if let Ok(mut current) = self.hidden.lock() {
            *current = hidden;
        }
    }

    pub fn dir(&self) -> &Path {
        &self.dir
    }

    fn ask(&self, request: Request) -> Result<(), RecordingError> {
        *self.request.lock().map_err(|_| RecordingError::Poisoned)? = request;
        Ok(())
    }

    /// Starts a recording of the running graph, `layout` its names, for
    /// user `by`; the control thread attaches it before its next cycle.
    pub fn start(&self, by: &str, layout: Layout) -> Result<RecordingInfo, RecordingError> {
        self.start_when(by, layout, None, None, false)
    }

    /// Starts a recording that the control thread attaches to the next
    /// graph an activation swaps in (the first swap after the hook counted
    /// `after` swaps), before that graph's first call; nothing of the graph
    /// running now is recorded. If that swap does not happen, the caller
    /// [`Recordings::abandon`]s it.
    pub fn start_after_swap(&self, by: &str, layout: Layout, after: u64) -> Result<RecordingInfo, RecordingError> {
        self.start_when(by, layout, Some(after), None, false)
    }

    /// Like [`Recordings::start_after_swap`], into the file `path` (an
    /// `.mcap` path the host made, outside this folder: an experiment's
    /// results, handed to `by`, its submitter: log lines naming another
    /// user's work are left out); it is not listed with this folder's
    /// recordings.
    pub fn start_after_swap_to(
        &self,
        by: &str,
        layout: Layout,
        after: u64,
        path: PathBuf,
    ) -> Result<RecordingInfo, RecordingError> {
        self.start_when(by, layout, Some(after), Some(path), true)
    }

    /// Whether a recording could start now: the refusals of
    /// [`Recordings::start`] without starting one (a fresh start checks
    /// before it builds the graph).
    pub fn check_start(&self) -> Result<(), RecordingError> {
        let running = self.running.lock().map_err(|_| RecordingError::Poisoned)?;
        self.refusal(running.as_ref())
    }

    fn refusal(&self, running: Option<&Running>) -> Result<(), RecordingError> {
        if self.command_line {
            return Err(RecordingError::CommandLine);
        }
        if let Some(current) = running {
            return Err(RecordingError::Running(current.info.name.clone()));
        }
        let stored = self.list_files(None)?.len();
        if stored >= MAX_STORED_RECORDINGS {
            return Err(RecordingError::Full(stored));
        }
        Ok(())
    }

    fn start_when(
        &self,
        by: &str,
        layout: Layout,
        after_swap: Option<u64>,
        to: Option<PathBuf>,
        only_theirs: bool,
    ) -> Result<RecordingInfo, RecordingError> {
        let mut running = self.running.lock().map_err(|_| RecordingError::Poisoned)?;
        self.refusal(running.as_ref())?;
        let now = std::time::SystemTime::now();
        let stamp = utc_stamp(unix_ms(now) / 1000);
        let (name, path) = match to {
            Some(path) => (path.file_name().map_or_else(String::new, |n| n.to_string_lossy().into_owned()), path),
            None => loop {
                let serial = self.serial.fetch_add(1, Ordering::Relaxed) + 1;
                let name = format!("rec-{stamp}-{serial}.mcap");
                let path = self.dir.join(&name);
                if !path.exists() {
                    break (name, path);
                }
            },
        };
        let hidden = self.hidden.lock().map_err(|_| RecordingError::Poisoned)?.clone();
        let options = RecordOptions {
            path: Some(path.clone()),
            max_file_bytes: self.max_file_bytes,
            max_total_bytes: u64::MAX,
            live: None,
            hidden,
            for_owner: only_theirs.then(|| by.to_string()),
        };
        let recorder = match after_swap {
            None => Recorder::start(&options, layout, self.timeline.clone())?,
            Some(_) => Recorder::start_from_swap(&options, layout, self.timeline.clone())?,
        };
        let sink = recorder.sink.clone();
        self.ask(match after_swap {
            None => Request::Attach(sink),
            Some(after) => Request::AttachAfterSwap { sink, after },
        })?;
        let info = RecordingInfo {
            name,
            by: by.to_string(),
            started_unix_ms: unix_ms(now),
            fresh_start: after_swap.is_some(),
        };
        *running = Some(Running { info: info.clone(), path, recorder });
        Ok(info)
    }

    /// Stops the running recording: the control thread detaches it, the
    /// writer writes what is queued, the summary and the footer.
    pub fn stop(&self) -> Result<Stopped, RecordingError> {
        let mut running = self.running.lock().map_err(|_| RecordingError::Poisoned)?;
        let Running { info, recorder, .. } = running.take().ok_or(RecordingError::NotRunning)?;
        self.ask(Request::Detach)?;
        // Events the tap still sends go to a closed channel and are ignored.
        let summary = recorder.finish()?;
        let files =
            summary.files.iter().filter_map(|f| f.file_name().map(|n| n.to_string_lossy().into_owned())).collect();
        Ok(Stopped {
            name: info.name,
            by: info.by,
            files,
            messages: summary.messages,
            bytes: summary.bytes,
            dropped: summary.dropped,
        })
    }

    /// Stops the running recording and deletes its files: a fresh start
    /// whose swap did not happen recorded nothing.
    pub fn abandon(&self) -> Result<(), RecordingError> {
        let dir = match self.running.lock().map_err(|_| RecordingError::Poisoned)?.as_ref() {
            Some(running) => running.path.parent().map_or_else(|| self.dir.clone(), Path::to_path_buf),
            None => self.dir.clone(),
        };
        let stopped = self.stop()?;
        for name in &stopped.files {
            let path = dir.join(name);
            std::fs::remove_file(&path).map_err(|source| RecordingError::Io { path, source })?;
        }
        Ok(())
    }

    /// The running recording, if any.
    pub fn current(&self) -> Option<RecordingInfo> {
        self.running.lock().ok().and_then(|r| r.as_ref().map(|r| r.info.clone()))
    }

    /// The files of the folder, oldest first.
    pub fn list(&self) -> Result<Vec<RecordingFile>, RecordingError> {
        let running = self.running.lock().map_err(|_| RecordingError::Poisoned)?;
        self.list_files(running.as_ref())
    }

    fn list_files(&self, running: Option<&Running>) -> Result<Vec<RecordingFile>, RecordingError> {
        let io = |source| RecordingError::Io { path: self.dir.clone(), source };
        let mut files = Vec::new();
        for entry in std::fs::read_dir(&self.dir).map_err(io)? {
            let entry = entry.map_err(io)?;
            let name = entry.file_name().to_string_lossy().into_owned();
            if !is_recording_name(&name) {
                continue;
            }
            let meta = entry.metadata().map_err(io)?;
            if !meta.is_file() {
                continue;
            }
            files.push(RecordingFile {
                recording: running.is_some_and(|r| belongs_to(&r.path, &name)),
                bytes: meta.len(),
                modified_unix_ms: meta.modified().map_or(0, unix_ms),
                name,
            });
        }
        files.sort_by(|a, b| (a.modified_unix_ms, &a.name).cmp(&(b.modified_unix_ms, &b.name)));
        Ok(files)
    }

    /// The path of recording file `name` (for a download), checked.
    pub fn file(&self, name: &str) -> Result<(PathBuf, u64), RecordingError> {
        if !is_recording_name(name) {
            return Err(RecordingError::BadName(crate::contract::clip(name)));
        }
        let path = self.dir.join(name);
        match std::fs::symlink_metadata(&path) {
            Ok(meta) if meta.is_file() => Ok((path, meta.len())),
            _ => Err(RecordingError::NotFound(name.to_string())),
        }
    }

    /// Deletes recording file `name` (not one the running recording writes).
    pub fn delete(&self, name: &str) -> Result<(), RecordingError> {
        let running = self.running.lock().map_err(|_| RecordingError::Poisoned)?;
        let (path, _) = self.file(name)?;
        if running.as_ref().is_some_and(|r| belongs_to(&r.path, name)) {
            return Err(RecordingError::InUse(name.to_string()));
        }
        std::fs::remove_file(&path).map_err(|source| RecordingError::Io { path, source })
    }

    /// Stops the running recording, if any (the host is stopping).
    pub fn finish(&self) -> Option<Result<Stopped, RecordingError>> {
        self.current()?;
        Some(self.stop())
    }

    /// Wraps the control loop's hook: attaches and detaches recordings
    /// between cycles, re-attaches after an activation swapped the graph
    /// (`layout_of` names the new one), and samples the status sections.
    /// `swaps_of` counts the graphs the inner hook swapped in (a fresh
    /// start waits for the next).
    pub fn hook<H: CycleHook>(
        &self,
        inner: H,
        layout_of: fn(&H) -> Layout,
        swaps_of: fn(&H) -> u64,
    ) -> ControlledHook<H> {
        ControlledHook { inner, request: self.request.clone(), layout_of, swaps_of, active: None, pending: None }
    }
}

/// Whether file `name` is the recording at `first` or one of its rotations.
fn belongs_to(first: &Path, name: &str) -> bool {
    let Some(first) = first.file_name().map(|n| n.to_string_lossy().into_owned()) else { return false };
    let Some(stem) = first.strip_suffix(".mcap") else { return false };
    name == first || name.strip_prefix(stem).and_then(|r| r.strip_prefix('.')).is_some()
}

struct Attached {
    sink: Sink,
    next_ns: u64,
    last: Vec<Option<serde_json::Value>>,
}

/// The control loop's hook with the portal's recordings around it.
pub struct ControlledHook<H> {
    inner: H,
    request: Arc<Mutex<Request>>,
    layout_of: fn(&H) -> Layout,
    swaps_of: fn(&H) -> u64,
    active: Option<Attached>,
    /// A fresh start's recording, waiting for the swap after this count.
    pending: Option<(Sink, u64)>,
}

impl<H> ControlledHook<H> {
    pub fn inner(&self) -> &H {
        &self.inner
    }
}

impl<H: CycleHook> CycleHook for ControlledHook<H> {
    fn between_cycles(&mut self, graph: &mut Graph, now_ns: u64) {
        let swaps_before = (self.swaps_of)(&self.inner);
        self.inner.between_cycles(graph, now_ns);
        let swaps = (self.swaps_of)(&self.inner);
        // Never wait for the portal: a request taken now or next cycle.
        let request = match self.request.try_lock() {
            Ok(mut slot) => std::mem::take(&mut *slot),
            Err(_) => Request::None,
        };
        match request {
            Request::None => {}
            Request::Attach(sink) => {
                graph.take_tap();
                self.active = Some(Attached { sink, next_ns: 0, last: Vec::new() });
            }
            Request::AttachAfterSwap { sink, after } => {
                graph.take_tap();
                self.active = None;
                self.pending = Some((sink, after));
            }
            Request::Detach => {
                graph.take_tap();
                self.active = None;
                self.pending = None;
            }
        }
        // The inner hook swapped a new graph in during this very call (it
        // runs first), and it has made no call yet: a fresh start's
        // recording begins with it.
        if self.pending.as_ref().is_some_and(|(_, after)| swaps > *after)
            && let Some((sink, _)) = self.pending.take()
        {
            if swaps > swaps_before {
                graph.take_tap();
                // Its time line starts here, at the new graph's start.
                sink.send(Event::Start(now_ns));
                self.active = Some(Attached { sink, next_ns: 0, last: Vec::new() });
            } else {
                // The request was taken after its swap (it cannot be, as
                // it is asked for before the swap is handed over): the new
                // graph has run, so the recording would not be fresh.
                tracing::error!("a fresh-start recording missed its activation's swap; it records nothing");
            }
        }
        let Some(active) = &mut self.active else { return };
        if !graph.has_tap() {
            // A new recording, or another graph after an activation: its
            // names go first, then its events.
            active.sink.send(Event::Layout(Arc::new((self.layout_of)(&self.inner))));
            graph.set_tap(Box::new(RecordTap { sink: active.sink.clone() }));
            active.last.clear();
        }
        sample_status(&active.sink, graph, now_ns, &mut active.next_ns, &mut active.last);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_are_the_hosts_own_and_plain() {
        for good in ["rec-20261123-171500-1.mcap", "rec-20261123-171500-1.2.mcap", "rec-0.mcap"] {
            assert!(is_recording_name(good), "{good}");
        }
        for bad in [
            "../rec-1.mcap",
            "rec-1/../../etc.mcap",
            "rec-.mcap",
            "rec-1.mcap.bak",
            "rec-1..mcap",
            "rec-1.x.mcap",
            "REC-1.mcap",
            ".rec-1.mcap",
            "rec-1",
            "state.json",
        ] {
            assert!(!is_recording_name(bad), "{bad}");
        }
        assert!(!is_recording_name(&format!("rec-{}.mcap", "1".repeat(60))));
    }

    #[test]
    fn stamps_are_utc_calendar_dates() {
        assert_eq!(utc_stamp(0), "19700101-000000");
        // 2026-11-23 17:15:09 UTC.
        assert_eq!(utc_stamp(1_795_454_109), "20261123-171509");
        // A leap day.
        assert_eq!(utc_stamp(951_782_400), "20000229-000000");
    }

    #[test]
    fn rotations_belong_to_their_recording() {
        let first = Path::new("/r/rec-20261123-1.mcap");
        assert!(belongs_to(first, "rec-20261123-1.mcap"));
        assert!(belongs_to(first, "rec-20261123-1.3.mcap"));
        assert!(!belongs_to(first, "rec-20261123-11.mcap"));
    }
}
