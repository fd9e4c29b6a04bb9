//! Recording a run to MCAP (`subsume run --record FILE.mcap`): every value
//! on every output port, every call the graph makes (the ticks and inputs
//! replay feeds again), faults and restarts, the components' status
//! sections (the arbiter's holder and suppressed sources, the network
//! platform's mode and round-trip times) and the log.
//!
//! The control thread only clones values into a bounded channel
//! ([`RecordTap`], `try_send`: what does not fit is dropped and counted);
//! the writer thread ([`writer`]) turns them into JSON messages and MCAP
//! chunks. [`schema`] is the messages' form; [`replay`] reads a recording
//! back and feeds chosen components their recorded inputs; [`readable`] is
//! what of a file the MCAP reader may be given.
//!
//! Invariants: nothing here blocks the control thread; a finished chunk is
//! flushed to the file at least every [`FLUSH_INTERVAL`], so a killed host
//! leaves every chunk but the last one readable; a clean stop writes the
//! summary; a file past its size limit is finished and the next one
//! started (`FILE.1.mcap`, `FILE.2.mcap`, ...).

pub mod control;
pub mod live;
pub mod log;
pub mod readable;
pub mod replay;

pub mod scene;
pub mod schema;
pub mod video;
mod writer;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::mpsc::{Receiver, SyncSender, TrySendError};
use std::thread::JoinHandle;
use std::time::Duration;

use thiserror::Error;

use crate::config::RobotConfig;
use crate::contract::{Value, ValueKind};
use crate::runtime::control_loop::{Clock, CycleHook};
use crate::runtime::{Call, Graph, Tap};

/// Events waiting for the writer. A disk slower than the robot must not
/// hold the control loop or grow memory without bound: past this, events
/// are dropped and counted.
pub const QUEUE_DEPTH: usize = 65_536;
/// The topic of the host's log in a recording (`foxglove.Log`).
pub const LOG_TOPIC: &str = "/subsume/log";
/// Longest time a finished chunk waits in memory: what a killed host can
/// lose at most (plus the chunk being filled).
pub const FLUSH_INTERVAL: Duration = Duration::from_millis(500);
/// A chunk is closed once it holds this many bytes.
pub const CHUNK_BYTES: u64 = 256 * 1024;
/// Default size of one file before the recording rotates to the next.
pub const DEFAULT_MAX_FILE_BYTES: u64 = 1 << 30;
/// Smallest size limit accepted: rotation on every few chunks would make a
/// recording of many tiny files.
pub const MIN_MAX_FILE_BYTES: u64 = 1 << 20;
/// How often the components' status sections are sampled (each is written
/// only when it changed).
pub const STATUS_PERIOD_NS: u64 = 100_000_000;
/// Longest reason or log line recorded (guest text is clipped already).
pub const MAX_TEXT_BYTES: usize = 4096;

/// Why a recording could not start or finish.
#[derive(Debug, Error)]
pub enum RecordError {
    #[error("recording {path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("recording {path}: {source}")]
    Mcap {
        path: PathBuf,
        #[source]
        source: mcap::McapError,
    },
    #[error("recording {}: the size limit must be at least {MIN_MAX_FILE_BYTES} bytes, got {}", .1.display(), .0)]
    MaxBytes(u64, PathBuf),
    #[error("recording {}: the file name must end in .mcap", .0.display())]
    Extension(PathBuf),
    #[error("the foxglove live view cannot listen on {address}: {message}")]
    Live { address: std::net::SocketAddr, message: String },
    #[error("recording: neither a file nor a live view was asked for")]
    Nothing,
    #[error("the recording's writer thread failed: {0}")]
    Thread(String),
}

/// What `--record` asked for.
#[derive(Clone, Debug)]
pub struct RecordOptions {
    /// The first file; rotation adds `.1`, `.2`, ... before `.mcap`. No
    /// file: the live view only.
    pub path: Option<PathBuf>,
    /// Size at which a file is finished and the next one started.
    pub max_file_bytes: u64,
    /// Size of every file together at which the recording stops (the file
    /// finished and marked cut); `u64::MAX`: none.
    pub max_total_bytes: u64,
    /// Where the Foxglove WebSocket server listens, if it runs.
    pub live: Option<std::net::SocketAddr>,
    /// Folders the recording names instead of spelling them out (in log
    /// lines, fault reasons and metadata): a recording from the portal or
    /// of a lab experiment is handed to a remote user.
    pub hidden: crate::fsutil::HiddenPaths,
    /// The one user the recording is handed to (a lab experiment's
    /// submitter): log lines that name another user's work (their
    /// `owner` field) are left out of it. `None`: every line.
    pub for_owner: Option<String>,
}

impl RecordOptions {
    pub fn new(path: PathBuf) -> RecordOptions {
        RecordOptions {
            path: Some(path),
            max_file_bytes: DEFAULT_MAX_FILE_BYTES,
            max_total_bytes: u64::MAX,
            live: None,
            hidden: Default::default(),
            for_owner: None,
        }
    }

    fn check(&self) -> Result<(), RecordError> {
        let Some(path) = &self.path else {
            return if self.live.is_some() { Ok(()) } else { Err(RecordError::Nothing) };
        };
        if path.extension().is_none_or(|e| e != "mcap") {
            return Err(RecordError::Extension(path.clone()));
        }
        if self.max_file_bytes < MIN_MAX_FILE_BYTES {
            return Err(RecordError::MaxBytes(self.max_file_bytes, path.clone()));
        }
        Ok(())
    }
}

/// The `n`th file of a recording (0: the path itself).
pub fn rotated_path(path: &Path, n: u32) -> PathBuf {
    if n == 0 {
        return path.to_path_buf();
    }
    path.with_extension(format!("{n}.mcap"))
}

/// One output port as the recording names it.
#[derive(Clone, Debug)]
pub struct PortLayout {
    pub name: String,
    pub kind: ValueKind,
}

/// One component as the recording names it.
#[derive(Clone, Debug)]
pub struct ComponentLayout {
    pub name: String,
    pub inputs: Vec<String>,
    pub outputs: Vec<PortLayout>,
}

/// The names behind the graph's indices: component `i` of the graph is
/// component `i` of the robot.
#[derive(Clone, Debug)]
pub struct Layout {
    pub robot: String,
    pub components: Vec<ComponentLayout>,
    /// More of what the recording is (the experiment, its submitter, each
    /// component's sha256), written into its `subsume.recording`
    /// metadata.
    pub about: BTreeMap<String, String>,
    /// The simulators' worlds, written as a `foxglove.SceneUpdate`
    /// ([`scene`]).
    pub worlds: Vec<(String, crate::sim::world::World)>,
}

impl Layout {
    pub fn of(config: &RobotConfig) -> Layout {
        let components = config
            .components
            .iter()
            .map(|c| ComponentLayout {
                name: c.name.clone(),
                inputs: c.description.inputs.iter().map(|p| p.name.clone()).collect(),
                outputs: c
                    .description
                    .outputs
                    .iter()
                    .map(|p| PortLayout { name: p.name.clone(), kind: p.kind })
                    .collect(),
            })
            .collect();
        Layout { robot: config.name.clone(), components, about: BTreeMap::new(), worlds: scene::worlds_of(config) }
    }
}

/// The topic of component `component`'s output `port`.
pub fn output_topic(component: &str, port: &str) -> String {
    format!("/{component}/{port}")
}

/// The topic of the calls the graph made into `component`.
pub fn calls_topic(component: &str) -> String {
    format!("/subsume/calls/{component}")
}

/// Whether an output is recorded as a pose (`foxglove.PoseInFrame` and a
/// `foxglove.FrameTransform`): a vector port called `pose`.
pub fn is_pose(port: &PortLayout) -> bool {
    port.kind == ValueKind::Vector && port.name == "pose"
}

/// Whether an output is recorded as a picture (`foxglove.CompressedImage`):
/// a bytes port called `frame` (`builtin:camera`'s), when the value is a
/// JPEG file; anything else on it is recorded as a plain value.
pub fn is_image(port: &PortLayout, value: &Value) -> bool {
    port.kind == ValueKind::Bytes
        && port.name == IMAGE_PORT
        && matches!(value, Value::Bytes(b) if b.starts_with(JPEG_MAGIC))
}

/// The port a picture travels on, and the text port beside it whose JSON
/// `capture_ns` (graph time) is the next picture's capture time.
pub const IMAGE_PORT: &str = "frame";
pub const IMAGE_INFO_PORT: &str = "frame-info";
/// A JPEG file's first bytes (start of image, then a marker).
const JPEG_MAGIC: &[u8] = &[0xff, 0xd8, 0xff];

/// The capture time (graph time, ns) a `frame-info` text names.
pub fn capture_ns_of(port: &PortLayout, value: &Value) -> Option<u64> {
    match value {
        Value::Text(text) if port.kind == ValueKind::Text && port.name == IMAGE_INFO_PORT => {
            serde_json::from_str::<serde_json::Value>(text).ok()?.get("capture_ns")?.as_u64()
        }
        _ => None,
    }
}

/// The recording's one time line: the host's [`Clock`] (graph time) on the
/// wall clock's scale, `epoch_unix_ns + clock.now_ns()`, the wall clock
/// read once, when the time line is made. Every message's log time is on
/// it, the log's lines too: a wall clock set back mid-run (NTP, a resumed
/// virtual machine) cannot put a channel out of log-time order, and on a
/// simulated clock a log line sits at the simulated time of the call that
/// wrote it.
#[derive(Clone, Debug)]
pub struct Timeline {
    epoch_unix_ns: u64,
    clock: Clock,
}

impl Timeline {
    /// `clock`'s time line, its zero at the wall-clock time now less
    /// `clock`'s reading.
    pub fn of(clock: &Clock) -> Timeline {
        let now = crate::walltime::unix_now_ns();
        Timeline { epoch_unix_ns: now.saturating_sub(clock.now_ns()), clock: clock.clone() }
    }

    /// `clock`'s time line with its zero at `epoch_unix_ns`.
    pub fn new(epoch_unix_ns: u64, clock: Clock) -> Timeline {
        Timeline { epoch_unix_ns, clock }
    }

    /// The wall-clock time of graph time 0, in ns since the Unix epoch.
    pub fn epoch_unix_ns(&self) -> u64 {
        self.epoch_unix_ns
    }

    /// Now on the time line, in ns since the Unix epoch.
    pub fn now_unix_ns(&self) -> u64 {
        self.epoch_unix_ns.saturating_add(self.clock.now_ns())
    }
}

/// What the control thread (and the log) hands the writer.
#[derive(Debug)]
enum Event {
    Call {
        index: usize,
        t: u64,
        input: Option<(u32, usize, Value)>,
    },
    Emitted {
        from: usize,
        port: u32,
        t: u64,
        value: Value,
    },
    Fault {
        index: usize,
        t: u64,
        reason: String,
    },
    Restart {
        index: usize,
        t: u64,
        attempt: u64,
    },
    Status {
        index: usize,
        t: u64,
        kind: &'static str,
        section: serde_json::Value,
    },
    Log {
        unix_ns: u64,
        level: u8,
        name: String,
        message: String,
    },
    /// Another graph runs from now on (an activation).
    Layout(Arc<Layout>),
    /// A recording from a fresh start begins: the graph time of its swap,
    /// its time line's zero.
    Start(u64),
    /// Finish the file and stop.
    Stop,
}

/// The sending side, shared by the tap, the status sampler and the log.
#[derive(Clone, Debug)]
struct Sink {
    sender: SyncSender<Event>,
    dropped: Arc<AtomicU64>,
    /// When the log's lines happen (the tap's events carry graph time).
    timeline: Timeline,
    /// Log lines naming another user's work are left out
    /// ([`RecordOptions::for_owner`]).
    for_owner: Option<Arc<str>>,
}

impl Sink {
    fn send(&self, event: Event) {
        match self.sender.try_send(event) {
            Ok(()) => {}
            Err(TrySendError::Full(_)) => {
                self.dropped.fetch_add(1, Ordering::Relaxed);
            }
            // Stopped: nothing is recorded any more.
            Err(TrySendError::Disconnected(_)) => {}
        }
    }
}

/// What a finished recording wrote.
#[derive(Clone, Debug, Default, PartialEq, serde::Serialize)]
pub struct RecordSummary {
    /// Every file written, in order.
    pub files: Vec<PathBuf>,
    /// Messages written, over every file.
    pub messages: u64,
    /// Events dropped because the writer fell behind.
    pub dropped: u64,
    /// Bytes written, over every file.
    pub bytes: u64,
}

/// A running recording: the writer thread and the channel into it.
pub struct Recorder {
    sink: Sink,
    writer: Option<JoinHandle<Result<RecordSummary, RecordError>>>,
}

impl Recorder {
    /// Creates the first file and starts the writer thread. Messages' log
    /// times are on `timeline`: `epoch_unix_ns + t` for graph time `t`.
    pub fn start(options: &RecordOptions, layout: Layout, timeline: Timeline) -> Result<Recorder, RecordError> {
        Recorder::start_when(options, layout, timeline, false)
    }

    /// [`Recorder::start`] for a recording from a fresh start: it records
    /// nothing until its swap (`Event::Start`, sent by the hook that
    /// attaches it), and its time line starts there: its `epoch_unix_ns`
    /// is the wall-clock time of the swap, as a run's recording from the
    /// robot's start has it.
    pub(crate) fn start_from_swap(
        options: &RecordOptions,
        layout: Layout,
        timeline: Timeline,
    ) -> Result<Recorder, RecordError> {
        Recorder::start_when(options, layout, timeline, true)
    }

    fn start_when(
        options: &RecordOptions,
        layout: Layout,
        timeline: Timeline,
        from_swap: bool,
    ) -> Result<Recorder, RecordError> {
        options.check()?;
        let (sender, receiver) = std::sync::mpsc::sync_channel(QUEUE_DEPTH);
        let dropped = Arc::new(AtomicU64::new(0));
        let mut writer =
            writer::Writer::create(options.clone(), Arc::new(layout), timeline.epoch_unix_ns(), from_swap)?;
        let counted = dropped.clone();
        let handle = std::thread::Builder::new()
            .name("subsume-record".into())
            .spawn(move || {
                let result = writer_loop(&mut writer, &receiver, &counted);
                let finished = writer.finish(counted.load(Ordering::Relaxed));
                result.and(finished)
            })
            .map_err(|e| RecordError::Thread(e.to_string()))?;
        // Said before the recording hears the log: a recording downloaded
        // from the portal shows no server path.
        if let Some(path) = &options.path {
            tracing::info!("recording to {}", path.display());
        }
        let sink = Sink { sender, dropped, timeline, for_owner: options.for_owner.as_deref().map(Arc::from) };
        log::install(sink.clone());
        Ok(Recorder { sink, writer: Some(handle) })
    }

    /// The tap to attach to the graph (`Graph::set_tap`).
    pub fn tap(&self) -> Box<dyn Tap> {
        Box::new(RecordTap { sink: self.sink.clone() })
    }

    /// Wraps the control loop's hook: samples the components' status
    /// sections every [`STATUS_PERIOD_NS`].
    pub fn hook<H: CycleHook>(&self, inner: H) -> RecordHook<H> {
        RecordHook { inner, sink: self.sink.clone(), next_ns: 0, last: Vec::new(), layout_of: None }
    }

    /// [`Recorder::hook`] for a hook that may swap the graph (an
    /// activation): the next graph gets the tap before its first call, and
    /// the recording the names of its components (`layout_of`).
    pub fn swapping_hook<H: CycleHook>(&self, inner: H, layout_of: fn(&H) -> Layout) -> RecordHook<H> {
        RecordHook { inner, sink: self.sink.clone(), next_ns: 0, last: Vec::new(), layout_of: Some(layout_of) }
    }

    /// Events dropped so far.
    pub fn dropped(&self) -> u64 {
        self.sink.dropped.load(Ordering::Relaxed)
    }

    /// Writes what is queued, the summary and the footer, and closes the file.
    pub fn finish(mut self) -> Result<RecordSummary, RecordError> {
        self.stop()
    }

    fn stop(&mut self) -> Result<RecordSummary, RecordError> {
        log::uninstall();
        let Some(handle) = self.writer.take() else { return Ok(RecordSummary::default()) };
        // A blocking send: the stop must not be dropped like an event.
        let _ = self.sink.sender.send(Event::Stop);
        let summary = handle.join().map_err(|_| RecordError::Thread("it panicked".into()))??;
        tracing::info!(
            "recording finished: {} messages, {} bytes in {} file(s), {} events dropped",
            summary.messages,
            summary.bytes,
            summary.files.len(),
            summary.dropped
        );
        Ok(summary)
    }
}

impl Drop for Recorder {
    fn drop(&mut self) {
        if self.writer.is_some()
            && let Err(e) = self.stop()
        {
            tracing::error!("{e}");
        }
    }
}

fn writer_loop(
    writer: &mut writer::Writer,
    receiver: &Receiver<Event>,
    dropped: &AtomicU64,
) -> Result<(), RecordError> {
    loop {
        match receiver.recv_timeout(FLUSH_INTERVAL) {
            Ok(Event::Stop) | Err(std::sync::mpsc::RecvTimeoutError::Disconnected) => return Ok(()),
            Ok(event) => writer.write(event, dropped.load(Ordering::Relaxed))?,
            Err(std::sync::mpsc::RecvTimeoutError::Timeout) => {}
        }
        writer.flush_if_due()?;
    }
}

/// The graph's tap: clones what it sees into the writer's channel.
struct RecordTap {
    sink: Sink,
}

impl Tap for RecordTap {
    fn call(&mut self, index: usize, call: Call<'_>, now_ns: u64) {
        let input = match call {
            Call::Tick => None,
            Call::Input { port, value, from } => Some((port, from, value.clone())),
        };
        self.sink.send(Event::Call { index, t: now_ns, input });
    }

    fn emitted(&mut self, from: usize, port: u32, value: &Value, now_ns: u64) {
        self.sink.send(Event::Emitted { from, port, t: now_ns, value: value.clone() });
    }

    fn faulted(&mut self, index: usize, reason: &str, now_ns: u64) {
        self.sink.send(Event::Fault { index, t: now_ns, reason: crate::contract::clip(reason) });
    }

    fn restarted(&mut self, index: usize, attempt: u64, now_ns: u64) {
        self.sink.send(Event::Restart { index, t: now_ns, attempt });
    }
}

/// The control loop's hook with the status sampler around it.
pub struct RecordHook<H> {
    inner: H,
    sink: Sink,
    /// The names of a graph the inner hook swapped in.
    layout_of: Option<fn(&H) -> Layout>,
    next_ns: u64,
    /// The last section sent per component, to send only changes.
    last: Vec<Option<serde_json::Value>>,
}

impl<H> RecordHook<H> {
    /// The hook it wraps.
    pub fn into_inner(self) -> H {
        self.inner
    }

    pub fn inner(&self) -> &H {
        &self.inner
    }
}

impl<H: CycleHook> CycleHook for RecordHook<H> {
    fn between_cycles(&mut self, graph: &mut Graph, now_ns: u64) {
        self.inner.between_cycles(graph, now_ns);
        let sink = &self.sink;
        if let Some(layout_of) = self.layout_of
            && !graph.has_tap()
        {
            // Another graph runs: its names go first, then its events.
            sink.send(Event::Layout(Arc::new(layout_of(&self.inner))));
            graph.set_tap(Box::new(RecordTap { sink: sink.clone() }));
            self.last.clear();
        }
        sample_status(sink, graph, now_ns, &mut self.next_ns, &mut self.last);
    }
}

/// Sends the components' status sections that changed, every
/// [`STATUS_PERIOD_NS`] (`next_ns`: the next sample; `last`: the sections
/// sent last, per component).
fn sample_status(
    sink: &Sink,
    graph: &Graph,
    now_ns: u64,
    next_ns: &mut u64,
    last: &mut Vec<Option<serde_json::Value>>,
) {
    if now_ns < *next_ns {
        return;
    }
    *next_ns = now_ns + STATUS_PERIOD_NS;
    last.resize(graph.len(), None);
    for (index, sent) in last.iter_mut().enumerate() {
        let Some((_, status)) = graph.component_status(index) else { continue };
        let (kind, section) = (status.section(), status.to_json());
        if sent.as_ref() != Some(&section) {
            *sent = Some(section.clone());
            sink.send(Event::Status { index, t: now_ns, kind, section });
        }
    }
}
