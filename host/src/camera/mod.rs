//! `builtin:camera`: a camera whose frames are JPEG pictures on an output
//! port (docs/camera.md). Its sources: the simulator (`source="sim:NAME"`,
//! a `builtin:sim` component): the simulated world seen from above
//! ([`render`]); and an IP camera streaming MJPEG over HTTP
//! (`source="http://HOST:PORT/PATH"`, [`mjpeg`]). V4L2 devices and RTSP
//! are not done.
//!
//! Rendering and encoding, or receiving and checking, run on the camera's
//! own thread (the simulator's paced on the control loop's clock); finished
//! frames wait in a [`FrameQueue`] of at most
//! [`MAX_QUEUED_FRAMES`] that drops the oldest and counts the drops. The
//! component takes them out in `poll`, never waiting: the control loop never
//! waits on a picture. The thread runs at the background's nice value
//! (`runtime::scheduling::BACKGROUND_NICE`), below the loop's.
//!
//! Each frame is two values in the same cycle: `frame` (bytes: the JPEG
//! file) and `frame-info` (text: JSON with its format, size, capture time
//! on the loop's clock, the camera's set rate, and its frame time and
//! sequence number). `seq` counts frame *times*, not pictures: a frame
//! time skipped, dropped or without a picture still advances it, so a
//! recording's video ([`crate::record::video`]) knows every gap exactly.

pub mod live;
pub mod mjpeg;
pub mod render;

use std::collections::HashSet;
use std::collections::VecDeque;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, PoisonError};
use std::thread::JoinHandle;
use std::time::Duration;

use self::live::{LiveCameras, LiveFeed};
use self::mjpeg::{HttpSource, Part, Socket, StreamError};
use self::render::{Scene, render};
use crate::builtin::{
    BuildContext, Builtin, BuiltinError, CheckContext, ParamDecl, ParamType, Params, Ports, Registry, builtin_of, port,
    positive_up_to,
};
use crate::config::{ParamProblem, RobotProblem, RobotView};
use crate::contract::{Value, ValueKind};
use crate::runtime::control_loop::{Clock, Waker};
use crate::runtime::scheduling;
use crate::runtime::{CallError, Component, Family, NamedSection, Outbox, Sample, StatusSection};
use crate::sim::SimRegistry;
use crate::sim::builtin::SimBuiltin;

/// Widest and tallest picture: each frame is width x height x 3 bytes
/// before encoding, rendered and encoded on the host's CPU.
pub const MAX_WIDTH_PX: i64 = 1920;
pub const MAX_HEIGHT_PX: i64 = 1080;
/// Smallest side: the picture must show the robot at all.
pub const MIN_SIDE_PX: i64 = 16;
/// Most frames per second: each costs a render, an encode, a delivery to
/// every listener and a record.
pub const MAX_RATE_HZ: f64 = 30.0;
/// Frames finished but not yet taken by the loop: more would be stale
/// pictures and memory; the oldest is dropped and counted.
pub const MAX_QUEUED_FRAMES: usize = 4;
/// How often the camera's thread looks at the clock between frames (a
/// simulated clock moves only with the loop).
const CLOCK_POLL: Duration = Duration::from_millis(1);

/// A camera is stale (its status says so) when its last frame is older
/// than this many frame periods, and at least [`STALE_AFTER_MIN`]: a
/// component looking at its pictures is looking at the past.
pub const STALE_AFTER_PERIODS: u64 = 3;
pub const STALE_AFTER_MIN: Duration = Duration::from_secs(1);

/// The prefix of a `source` naming a simulated robot.
const SIM_SOURCE: &str = "sim:";
/// The scheme of an IP camera's `source`.
const HTTP_SOURCE: &str = "http://";
/// Output ports.
const OUTPUT_FRAME: u32 = 0;
const OUTPUT_INFO: u32 = 1;

const PARAMS: &[ParamDecl] = &[
    ParamDecl {
        name: "source",
        ty: ParamType::Required,
        default: "",
        unit: "",
        doc: "sim:NAME: the builtin:sim component NAME's world seen from above; http://HOST[:PORT]/PATH: an IP camera's MJPEG stream",
    },
    ParamDecl {
        name: "width",
        ty: ParamType::Integer { min: MIN_SIDE_PX, max: MAX_WIDTH_PX },
        default: "320",
        unit: "px",
        doc: "picture width (sim: sources; an IP camera's frames keep their own size)",
    },
    ParamDecl {
        name: "height",
        ty: ParamType::Integer { min: MIN_SIDE_PX, max: MAX_HEIGHT_PX },
        default: "240",
        unit: "px",
        doc: "picture height (sim: sources)",
    },
    ParamDecl {
        name: "rate",
        ty: positive_up_to(MAX_RATE_HZ),
        default: "5",
        unit: "Hz",
        doc: "frames per second, on the control loop's clock (an IP camera: at most this many are kept)",
    },
    ParamDecl {
        name: "quality",
        ty: ParamType::Integer { min: 1, max: 100 },
        default: "80",
        unit: "",
        doc: "JPEG quality (sim: sources)",
    },
];

/// The `camera` kind.
pub struct CameraBuiltin;

/// The simulated robot a `source` names.
fn sim_name(source: &str) -> Option<&str> {
    source.strip_prefix(SIM_SOURCE).filter(|name| !name.is_empty())
}

/// What a `source` names.
enum Source<'a> {
    Sim(&'a str),
    Http(HttpSource),
}

/// `source` as a camera source, or why it is none.
fn source_of(source: &str) -> Result<Source<'_>, String> {
    if let Some(sim) = sim_name(source) {
        return Ok(Source::Sim(sim));
    }
    let shown = crate::contract::clip_to(source, 64);
    let is_http = source.get(..HTTP_SOURCE.len()).is_some_and(|s| s.eq_ignore_ascii_case(HTTP_SOURCE));
    if is_http {
        return mjpeg::parse_source(source).map(Source::Http).map_err(|e| match e {
            // Not echoed: the password.
            mjpeg::UrlError::Credentials => format!("is an http:// URL that {e}"),
            e => format!("is an http:// URL that {e}: '{shown}'"),
        });
    }
    let unsupported = match source.split_once("://") {
        Some((scheme, _)) if !scheme.is_empty() && scheme.chars().all(|c| c.is_ascii_alphanumeric() || c == '+') => {
            format!(
                "the scheme {}:// is not supported (RTSP, https:// and V4L2 devices are not yet)",
                scheme.to_ascii_lowercase()
            )
        }
        _ => "V4L2 devices and other sources are not supported yet".to_string(),
    };
    Err(format!(
        "must be sim:NAME (a builtin:sim component) or http://HOST[:PORT]/PATH (an IP camera's MJPEG stream); {unsupported}: '{shown}'"
    ))
}

/// A picture side from parameter `name` (checked against its bounds).
fn side(params: &Params, name: &str) -> Result<u16, BuiltinError> {
    let value = params.integer(name)?;
    u16::try_from(value)
        .map_err(|_| BuiltinError::Param { name: name.into(), why: format!("is out of range: {value}") })
}

impl Builtin for CameraBuiltin {
    fn kind(&self) -> &'static str {
        "camera"
    }

    fn summary(&self) -> &'static str {
        "A camera: JPEG frames of the simulated world seen from above, or of an IP camera's MJPEG stream"
    }

    fn params(&self) -> &'static [ParamDecl] {
        PARAMS
    }

    fn check(&self, params: &Params, _ctx: &mut CheckContext<'_>) -> Vec<ParamProblem> {
        match source_of(params.text("source").unwrap_or_default()) {
            Ok(_) => Vec::new(),
            Err(why) => vec![ParamProblem::new("source", why)],
        }
    }

    /// A `sim:NAME` source names a `builtin:sim` component of the robot.
    fn check_robot(&self, me: usize, params: &Params, view: &RobotView<'_>, registry: Registry) -> Vec<RobotProblem> {
        let robot = view.robot;
        let (Some(camera), Some(sim)) = (robot.components.get(me), sim_name(params.text("source").unwrap_or_default()))
        else {
            return Vec::new();
        };
        if view.failed.iter().any(|failed| failed == sim) {
            return Vec::new();
        }
        let simulated = robot.components.iter().enumerate().any(|(index, c)| {
            c.name == sim && builtin_of(robot, index, registry).is_some_and(|b| b.kind() == SimBuiltin.kind())
        });
        if simulated {
            return Vec::new();
        }
        vec![RobotProblem {
            offset: camera.offset,
            message: format!(
                "camera '{}': source 'sim:{}' names no builtin:sim component",
                camera.name,
                crate::contract::clip_to(sim, 64)
            ),
        }]
    }

    fn ports(&self, _params: &Params) -> Ports {
        Ports {
            inputs: Vec::new(),
            outputs: vec![
                port("frame", ValueKind::Bytes, "a JPEG picture (a whole JFIF file)"),
                port(
                    "frame-info",
                    ValueKind::Text,
                    "JSON about the frame just sent on 'frame': format, width, height, capture_ns (the loop's clock), rate_hz, frame_ns, seq (its frame time's number)",
                ),
            ],
        }
    }

    fn build(&self, params: &Params, ctx: &mut BuildContext<'_>) -> Result<Box<dyn Component>, BuiltinError> {
        let source =
            source_of(params.text("source")?).map_err(|why| BuiltinError::Param { name: "source".into(), why })?;
        let period_ns = (1e9 / params.number("rate")?).round() as u64;
        let name = ctx.component()?.name.clone();
        // The portal's live view, where the host has one.
        let live = ctx.services.get::<LiveCameras>().map(|cameras| cameras.publish(&name));
        let sim = match source {
            Source::Sim(sim) => sim,
            Source::Http(source) => {
                let url = source.to_string();
                let camera =
                    CameraThread::start_http(&name, source, period_ns, ctx.clock.clone(), ctx.waker.clone(), live)
                        .map_err(|e| BuiltinError::io("the camera's thread", e))?;
                return Ok(Box::new(CameraComponent::new(camera, "http").with_url(url)));
            }
        };
        let control = ctx.services.get::<SimRegistry>().and_then(|registry| registry.get(sim)).ok_or_else(|| {
            BuiltinError::Refused(format!("source 'sim:{sim}' names no running builtin:sim component"))
        })?;
        let (world, body) = control.world_and_body();
        let settings = CameraSettings {
            width: side(params, "width")?,
            height: side(params, "height")?,
            period_ns,
            quality: u8::try_from(params.integer("quality")?)
                .map_err(|_| BuiltinError::Param { name: "quality".into(), why: "is out of range".into() })?,
        };
        let snapshot: Snapshot = Box::new(move || {
            let status = control.status();
            let scene =
                Scene { world: &world, body, pose: (status.x, status.y, status.heading), ranges: &status.ranges };
            Some(render(&scene, u32::from(settings.width), u32::from(settings.height)).rgb)
        });
        let camera = CameraThread::start(&name, settings, snapshot, ctx.clock.clone(), ctx.waker.clone(), live)
            .map_err(|e| BuiltinError::io("the camera's thread", e))?;
        Ok(Box::new(CameraComponent::new(camera, "sim")))
    }
}

/// What the camera's thread needs to make frames.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct CameraSettings {
    pub width: u16,
    pub height: u16,
    /// Time between frames on the loop's clock.
    pub period_ns: u64,
    pub quality: u8,
}

/// Takes one picture: its RGB pixels (`width` x `height` x 3), or `None`
/// when there is nothing to see.
pub type Snapshot = Box<dyn FnMut() -> Option<Vec<u8>> + Send>;

/// One encoded frame.
#[derive(Clone, Debug, PartialEq)]
pub struct Frame {
    pub jpeg: Vec<u8>,
    pub width: u16,
    pub height: u16,
    /// When the picture was taken, on the control loop's clock.
    pub capture_ns: u64,
    /// The frame time it was taken for, on the control loop's clock (at
    /// or a little before `capture_ns`).
    pub frame_ns: u64,
    /// The number of its frame time, counted from the camera's first at
    /// 0: frame times without a picture (skipped, dropped, failed) count.
    pub seq: u64,
}

/// Finished frames on their way to the loop: at most `capacity`; a new one
/// pushes the oldest out and counts it.
#[derive(Debug)]
pub struct FrameQueue {
    frames: Mutex<VecDeque<Frame>>,
    capacity: usize,
    dropped: AtomicU64,
}

impl FrameQueue {
    pub fn new(capacity: usize) -> FrameQueue {
        FrameQueue { frames: Mutex::new(VecDeque::new()), capacity: capacity.max(1), dropped: AtomicU64::new(0) }
    }

    /// Queues `frame`, dropping the oldest when full.
    pub fn push(&self, frame: Frame) {
        let mut frames = self.frames.lock().unwrap_or_else(PoisonError::into_inner);
        while frames.len() >= self.capacity {
            frames.pop_front();
            self.dropped.fetch_add(1, Ordering::Relaxed);
        }
        frames.push_back(frame);
    }

    /// Every queued frame, oldest first. The lock is held only to move
    /// them out, never while a frame is made.
    pub fn take(&self) -> Vec<Frame> {
        self.frames.lock().unwrap_or_else(PoisonError::into_inner).drain(..).collect()
    }

    /// Frames pushed out before the loop took them.
    pub fn dropped(&self) -> u64 {
        self.dropped.load(Ordering::Relaxed)
    }
}

/// Counters the camera's thread keeps.
#[derive(Debug, Default)]
struct Counters {
    made: AtomicU64,
    encode_failures: AtomicU64,
    /// Frame times skipped because the previous frame took longer.
    late: AtomicU64,
    /// The simulator's next frame time (the loop's clock): the frame
    /// times from it up to now that the thread is too busy for are late
    /// too, even before it says so.
    next_ns: AtomicU64,
    /// Nanoseconds of wall time spent rendering and encoding (or receiving
    /// and checking).
    busy_ns: AtomicU64,
    /// Parts of an IP camera's stream that were not frames: not JPEG, too
    /// large, or too wide.
    rejected: AtomicU64,
    /// Frames an IP camera sent sooner than `rate` allows.
    skipped: AtomicU64,
    /// Connections to an IP camera given up (stalled, closed, garbage,
    /// refused).
    stream_errors: AtomicU64,
    /// Connections to an IP camera opened after the first.
    reconnects: AtomicU64,
    /// An IP camera's stream is open.
    connected: AtomicBool,
}

/// The camera's thread and what it shares.
pub struct CameraThread {
    queue: Arc<FrameQueue>,
    counters: Arc<Counters>,
    stop: Arc<AtomicBool>,
    thread: Option<JoinHandle<()>>,
    settings: CameraSettings,
    /// An IP camera's open socket, shut to stop the thread mid-read.
    socket: Option<Socket>,
}

impl CameraThread {
    /// Starts taking a picture with `snapshot` every `settings.period_ns` on
    /// `clock`, encoding it and queueing it (and offering it to `live`);
    /// `waker` brings the loop round.
    pub fn start(
        name: &str,
        settings: CameraSettings,
        mut snapshot: Snapshot,
        clock: Clock,
        waker: Waker,
        live: Option<LiveFeed>,
    ) -> std::io::Result<CameraThread> {
        let queue = Arc::new(FrameQueue::new(MAX_QUEUED_FRAMES));
        let counters = Arc::new(Counters::default());
        let stop = Arc::new(AtomicBool::new(false));
        let (q, c, s) = (queue.clone(), counters.clone(), stop.clone());
        let label = name.to_string();
        let thread = std::thread::Builder::new().name(format!("camera-{name}")).spawn(move || {
            // A picture may wait; the loop may not: the kernel gives this
            // thread about a tenth of the loop's share of a busy CPU.
            if !scheduling::lower_to_background() {
                tracing::debug!(component = label.as_str(), "the camera's thread keeps its priority");
            }
            let period = settings.period_ns.max(1);
            let mut next_ns = clock.now_ns();
            // The number of the frame time `next_ns`.
            let mut next_seq = 0;
            c.next_ns.store(next_ns, Ordering::Relaxed);
            while !s.load(Ordering::Relaxed) {
                let now = clock.now_ns();
                if now < next_ns {
                    std::thread::sleep(CLOCK_POLL);
                    continue;
                }
                // The latest frame time due is taken; the ones before it
                // are late, and counted in `seq` all the same.
                let skipped = (now - next_ns) / period;
                c.late.fetch_add(skipped, Ordering::Relaxed);
                let seq = next_seq + skipped;
                let frame_ns = next_ns + skipped * period;
                next_seq = seq + 1;
                next_ns = frame_ns + period;
                c.next_ns.store(next_ns, Ordering::Relaxed);
                let started = std::time::Instant::now();
                let Some(rgb) = snapshot() else { continue };
                match encode(&rgb, settings) {
                    Ok(jpeg) => {
                        let (width, height) = (settings.width, settings.height);
                        let frame = Frame { jpeg, width, height, capture_ns: now, frame_ns, seq };
                        if let Some(live) = &live {
                            live.offer(&frame);
                        }
                        q.push(frame);
                        c.made.fetch_add(1, Ordering::Relaxed);
                        waker.wake();
                    }
                    Err(e) => {
                        if c.encode_failures.fetch_add(1, Ordering::Relaxed) == 0 {
                            tracing::warn!(component = label.as_str(), "a frame did not encode: {e}");
                        }
                    }
                }
                let busy = u64::try_from(started.elapsed().as_nanos()).unwrap_or(u64::MAX);
                c.busy_ns.fetch_add(busy, Ordering::Relaxed);
            }
        })?;
        Ok(CameraThread { queue, counters, stop, thread: Some(thread), settings, socket: None })
    }

    /// Starts reading the MJPEG stream of `source`: each whole JPEG frame,
    /// at most one per three quarters of `period_ns` (on `clock`), is
    /// queued with its capture time (when its last byte came); `waker`
    /// brings the loop round. A part that is not a frame is dropped and
    /// counted; a connection that fails, stalls or loses its framing is
    /// dialled again after a backoff. Each kind of fault is logged once.
    /// Each frame queued is offered to `live`.
    pub fn start_http(
        name: &str,
        source: HttpSource,
        period_ns: u64,
        clock: Clock,
        waker: Waker,
        live: Option<LiveFeed>,
    ) -> std::io::Result<CameraThread> {
        let queue = Arc::new(FrameQueue::new(MAX_QUEUED_FRAMES));
        let counters = Arc::new(Counters::default());
        let stop = Arc::new(AtomicBool::new(false));
        let socket: Socket = Arc::new(Mutex::new(None));
        let (q, c, s, sock) = (queue.clone(), counters.clone(), stop.clone(), socket.clone());
        let label = name.to_string();
        let thread = std::thread::Builder::new().name(format!("camera-{name}")).spawn(move || {
            if !scheduling::lower_to_background() {
                tracing::debug!(component = label.as_str(), "the camera's thread keeps its priority");
            }
            let url = source.to_string();
            let mut said: HashSet<&'static str> = HashSet::new();
            let mut backoff = mjpeg::RECONNECT_MIN;
            let mut opened = 0u64;
            let period = period_ns.max(1);
            // The first frame's capture time (the frame times' origin) and
            // the number of the last frame time kept.
            let mut origin: Option<u64> = None;
            let mut last_seq: Option<u64> = None;
            let mut last_kept: Option<u64> = None;
            let min_gap = period_ns.saturating_mul(3) / 4;
            while !s.load(Ordering::Relaxed) {
                let failure = match mjpeg::Stream::open(&source, &sock, &s) {
                    Err(e) => e,
                    Ok(mut stream) => {
                        opened += 1;
                        if opened > 1 {
                            c.reconnects.fetch_add(1, Ordering::Relaxed);
                        }
                        if said.insert("connected") {
                            tracing::info!(component = label.as_str(), "camera {url}: receiving its MJPEG stream");
                        }
                        c.connected.store(true, Ordering::Relaxed);
                        loop {
                            let part = match stream.next_part() {
                                Ok(part) => part,
                                Err(e) => break e,
                            };
                            let started = std::time::Instant::now();
                            match part {
                                Part::Frame { jpeg, width, height } => {
                                    backoff = mjpeg::RECONNECT_MIN;
                                    let now = clock.now_ns();
                                    // Its frame time: the nearest on the
                                    // rate's grid from the first frame.
                                    let first = *origin.get_or_insert(now);
                                    let seq = (now.saturating_sub(first) + period / 2) / period;
                                    if last_kept.is_some_and(|last| now.saturating_sub(last) < min_gap)
                                        || last_seq.is_some_and(|last| seq <= last)
                                    {
                                        c.skipped.fetch_add(1, Ordering::Relaxed);
                                        continue;
                                    }
                                    last_kept = Some(now);
                                    last_seq = Some(seq);
                                    let frame_ns = first + seq * period;
                                    let frame = Frame { jpeg, width, height, capture_ns: now, frame_ns, seq };
                                    if let Some(live) = &live {
                                        live.offer(&frame);
                                    }
                                    q.push(frame);
                                    c.made.fetch_add(1, Ordering::Relaxed);
                                    waker.wake();
                                }
                                Part::Rejected(why) => {
                                    c.rejected.fetch_add(1, Ordering::Relaxed);
                                    if said.insert(why.kind()) {
                                        tracing::warn!(
                                            component = label.as_str(),
                                            "camera {url}: {why}; such frames are dropped and counted (frames_rejected), this is said once"
                                        );
                                    }
                                }
                            }
                            let busy = u64::try_from(started.elapsed().as_nanos()).unwrap_or(u64::MAX);
                            c.busy_ns.fetch_add(busy, Ordering::Relaxed);
                            if s.load(Ordering::Relaxed) {
                                break StreamError::Ended;
                            }
                        }
                    }
                };
                c.connected.store(false, Ordering::Relaxed);
                mjpeg::shut(&sock);
                if s.load(Ordering::Relaxed) {
                    break;
                }
                c.stream_errors.fetch_add(1, Ordering::Relaxed);
                if said.insert(failure.kind()) {
                    tracing::warn!(
                        component = label.as_str(),
                        "camera {url}: {failure}; dialling again (from {} ms up to {} s apart; this is said once)",
                        mjpeg::RECONNECT_MIN.as_millis(),
                        mjpeg::RECONNECT_MAX.as_secs()
                    );
                }
                mjpeg::pause(backoff, &s);
                backoff = (backoff * 2).min(mjpeg::RECONNECT_MAX);
            }
        })?;
        let settings = CameraSettings { width: 0, height: 0, period_ns, quality: 0 };
        Ok(CameraThread { queue, counters, stop, thread: Some(thread), settings, socket: Some(socket) })
    }
}

impl Drop for CameraThread {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::SeqCst);
        if let Some(socket) = &self.socket {
            mjpeg::shut(socket);
        }
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
    }
}

/// `rgb` (`settings.width` x `settings.height` x 3) as a JPEG file.
pub fn encode(rgb: &[u8], settings: CameraSettings) -> Result<Vec<u8>, jpeg_encoder::EncodingError> {
    let mut jpeg = Vec::new();
    jpeg_encoder::Encoder::new(&mut jpeg, settings.quality).encode(
        rgb,
        settings.width,
        settings.height,
        jpeg_encoder::ColorType::Rgb,
    )?;
    Ok(jpeg)
}

/// The `builtin:camera` component: hands the thread's frames to the graph.
pub struct CameraComponent {
    camera: CameraThread,
    source: &'static str,
    /// An IP camera's URL.
    url: Option<String>,
    sent: u64,
    /// The size of the last frame sent.
    size: (u16, u16),
    /// The loop's time at the first and the latest call.
    first_ns: Option<u64>,
    now_ns: u64,
    /// The capture time of the last frame sent.
    last_capture_ns: Option<u64>,
}

impl CameraComponent {
    pub fn new(camera: CameraThread, source: &'static str) -> CameraComponent {
        let size = (camera.settings.width, camera.settings.height);
        CameraComponent { camera, source, url: None, sent: 0, size, first_ns: None, now_ns: 0, last_capture_ns: None }
    }

    /// The camera's URL, shown in its status.
    pub fn with_url(mut self, url: String) -> CameraComponent {
        self.url = Some(url);
        self
    }

    /// How long (ns on the loop's clock) the loop has gone without a new
    /// picture at its latest call: since the last frame's capture, or since
    /// the camera started when none came yet.
    fn age_ns(&self) -> u64 {
        let since = self.last_capture_ns.or(self.first_ns).unwrap_or(self.now_ns);
        self.now_ns.saturating_sub(since)
    }

    /// The simulator's frame times past at the latest call that its busy
    /// thread will skip: all but the latest due (an IP camera: none).
    fn overdue(&self) -> u64 {
        let next = self.camera.counters.next_ns.load(Ordering::Relaxed);
        if self.url.is_some() || next == 0 || self.now_ns < next {
            return 0;
        }
        (self.now_ns - next) / self.camera.settings.period_ns.max(1)
    }

    /// The last picture is older than [`STALE_AFTER_PERIODS`] periods (and
    /// [`STALE_AFTER_MIN`]).
    fn stale(&self) -> bool {
        let min = u64::try_from(STALE_AFTER_MIN.as_nanos()).unwrap_or(u64::MAX);
        self.age_ns() > self.camera.settings.period_ns.saturating_mul(STALE_AFTER_PERIODS).max(min)
    }
}

/// The JSON `frame-info` carries; `period_ns` is the camera's set period.
fn frame_info(frame: &Frame, period_ns: u64) -> String {
    serde_json::json!({
        "format": "jpeg",
        "width": frame.width,
        "height": frame.height,
        "capture_ns": frame.capture_ns,
        "rate_hz": 1e9 / period_ns.max(1) as f64,
        "frame_ns": frame.frame_ns,
        "seq": frame.seq,
    })
    .to_string()
}

impl Component for CameraComponent {
    fn poll(&mut self, now_ns: u64, out: &mut Outbox) {
        self.first_ns.get_or_insert(now_ns);
        self.now_ns = self.now_ns.max(now_ns);
        for frame in self.camera.queue.take() {
            self.size = (frame.width, frame.height);
            self.last_capture_ns = Some(frame.capture_ns);
            out.push((OUTPUT_INFO, Value::Text(frame_info(&frame, self.camera.settings.period_ns))));
            out.push((OUTPUT_FRAME, Value::Bytes(frame.jpeg)));
            self.sent += 1;
        }
    }

    fn tick(&mut self, now_ns: u64, out: &mut Outbox) -> Result<(), CallError> {
        self.poll(now_ns, out);
        Ok(())
    }

    fn status(&self) -> Option<Box<dyn StatusSection>> {
        let c = &self.camera.counters;
        let http = self.url.is_some();
        Some(Box::new(CameraSection {
            source: self.source,
            url: self.url.clone(),
            width: self.size.0,
            height: self.size.1,
            frames_made: c.made.load(Ordering::Relaxed),
            frames_sent: self.sent,
            frames_dropped: self.camera.queue.dropped(),
            frames_late: c.late.load(Ordering::Relaxed) + self.overdue(),
            encode_failures: c.encode_failures.load(Ordering::Relaxed),
            busy_s: c.busy_ns.load(Ordering::Relaxed) as f64 / 1e9,
            last_frame_age_s: self.age_ns() as f64 / 1e9,
            stale: self.stale(),
            frames_rejected: http.then(|| c.rejected.load(Ordering::Relaxed)),
            frames_skipped: http.then(|| c.skipped.load(Ordering::Relaxed)),
            stream_errors: http.then(|| c.stream_errors.load(Ordering::Relaxed)),
            reconnects: http.then(|| c.reconnects.load(Ordering::Relaxed)),
            connected: http.then(|| c.connected.load(Ordering::Relaxed)),
        }))
    }
}

/// The camera's section of the report and the live status.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct CameraSection {
    pub source: &'static str,
    pub width: u16,
    pub height: u16,
    /// Frames rendered and encoded.
    pub frames_made: u64,
    /// Frames the loop took and sent on `frame`.
    pub frames_sent: u64,
    /// Frames pushed out of the full queue before the loop took them.
    pub frames_dropped: u64,
    /// Frame times skipped because the one before took longer than a
    /// period, up to the latest cycle (the ones the busy thread has not
    /// come back to yet included).
    pub frames_late: u64,
    pub encode_failures: u64,
    /// Wall time the camera's thread spent rendering and encoding (an IP
    /// camera: checking the frames it received).
    pub busy_s: f64,
    /// How long the loop has gone without a new picture (since the camera
    /// started, before the first), at the latest cycle.
    pub last_frame_age_s: f64,
    /// `last_frame_age_s` is past [`STALE_AFTER_PERIODS`] frame periods
    /// (and [`STALE_AFTER_MIN`]).
    pub stale: bool,
    /// An IP camera's URL.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub url: Option<String>,
    /// An IP camera's parts that were not frames (not JPEG, larger than
    /// `mjpeg::MAX_FRAME_BYTES`, or wider than the size limits).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub frames_rejected: Option<u64>,
    /// An IP camera's frames that came sooner than `rate` allows.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub frames_skipped: Option<u64>,
    /// An IP camera's connections given up (failed, stalled, closed,
    /// garbage).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub stream_errors: Option<u64>,
    /// An IP camera's connections opened after the first.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub reconnects: Option<u64>,
    /// An IP camera's stream is open now.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub connected: Option<bool>,
}

impl NamedSection for CameraSection {
    const SECTION: &'static str = "camera";

    fn families(&self, component: &str) -> Vec<Family> {
        let mut rows = vec![
            ("subsume_camera_frames", "frames the loop took and sent on 'frame'", Sample::Counter(self.frames_sent)),
            (
                "subsume_camera_frames_dropped",
                "frames pushed out of the full queue before the loop took them",
                Sample::Counter(self.frames_dropped),
            ),
            (
                "subsume_camera_frame_age_seconds",
                "how long the loop has gone without a new picture",
                Sample::Gauge(self.last_frame_age_s),
            ),
        ];
        if let Some(rejected) = self.frames_rejected {
            rows.push((
                "subsume_camera_frames_rejected",
                "an IP camera's parts that were not frames (not JPEG, too large, too wide)",
                Sample::Counter(rejected),
            ));
        }
        if let Some(reconnects) = self.reconnects {
            rows.push((
                "subsume_camera_reconnects",
                "an IP camera's connections opened again",
                Sample::Counter(reconnects),
            ));
        }
        Family::each(("camera", component), &rows)
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]

    use std::sync::mpsc;

    use super::*;

    fn frame(seq: u64) -> Frame {
        Frame { jpeg: vec![0xff, 0xd8], width: 16, height: 16, capture_ns: seq, frame_ns: seq, seq }
    }

    const SETTINGS: CameraSettings = CameraSettings { width: 16, height: 16, period_ns: 1_000_000, quality: 80 };

    #[cfg(target_os = "linux")]
    #[test]
    fn pictures_are_made_below_the_loops_priority() {
        let (tell, nice) = mpsc::channel();
        let snapshot: Snapshot = Box::new(move || {
            let _ = tell.send(scheduling::thread_nice());
            None
        });
        let _camera = CameraThread::start("nice", SETTINGS, snapshot, Clock::new(), Waker::default(), None).unwrap();
        let seen = nice.recv_timeout(Duration::from_secs(10)).unwrap();
        assert!(seen >= Some(scheduling::BACKGROUND_NICE), "{seen:?}");
    }

    #[test]
    fn a_full_queue_drops_the_oldest_frames_and_counts_them() {
        let queue = FrameQueue::new(4);
        for seq in 0..10 {
            queue.push(frame(seq));
        }
        assert_eq!(queue.dropped(), 6);
        let kept: Vec<u64> = queue.take().iter().map(|f| f.seq).collect();
        assert_eq!(kept, vec![6, 7, 8, 9]);
        assert!(queue.take().is_empty());
    }

    #[test]
    fn frames_are_jpeg_files_of_the_set_size() {
        let jpeg = encode(&vec![128; 16 * 16 * 3], SETTINGS).unwrap();
        assert_eq!(&jpeg[..2], &[0xff, 0xd8], "start of image");
        assert_eq!(&jpeg[jpeg.len() - 2..], &[0xff, 0xd9], "end of image");
        // The frame header (SOF0) carries height then width.
        let sof = jpeg.windows(2).position(|w| w == [0xff, 0xc0]).unwrap();
        assert_eq!(&jpeg[sof + 5..sof + 9], &[0, 16, 0, 16]);
    }

    /// Every other snapshot has nothing to see, and the loop takes the
    /// frames while they come: `seq` counts the frame times without a
    /// picture too, each frame's `frame_ns` is its frame time on the
    /// period's grid, and `frame-info` names the set rate.
    #[test]
    fn seq_counts_frame_times_with_or_without_a_picture() {
        let mut calls = 0u32;
        let snapshot: Snapshot = Box::new(move || {
            calls += 1;
            (calls % 2 == 1).then(|| vec![0; 16 * 16 * 3])
        });
        let camera = CameraThread::start("test", SETTINGS, snapshot, Clock::new(), Waker::default(), None).unwrap();
        let mut component = CameraComponent::new(camera, "test");
        let mut infos: Vec<serde_json::Value> = Vec::new();
        let deadline = std::time::Instant::now() + Duration::from_secs(20);
        while infos.len() < 6 && std::time::Instant::now() < deadline {
            let mut out = Outbox::new();
            component.poll(0, &mut out);
            for (port, value) in out {
                if let (OUTPUT_INFO, Value::Text(text)) = (port, value) {
                    infos.push(serde_json::from_str(&text).unwrap());
                }
            }
            std::thread::sleep(Duration::from_micros(200));
        }
        assert!(infos.len() >= 6, "{infos:?}");
        let period = SETTINGS.period_ns;
        for pair in infos.windows(2) {
            let (a, b) = (&pair[0], &pair[1]);
            let gap = b["seq"].as_u64().unwrap() - a["seq"].as_u64().unwrap();
            assert!(gap >= 2, "a frame time without a picture is counted: {a} {b}");
            let frame_gap = b["frame_ns"].as_u64().unwrap() - a["frame_ns"].as_u64().unwrap();
            assert_eq!(frame_gap, gap * period, "{a} {b}");
        }
        for info in &infos {
            assert_eq!(info["rate_hz"], 1000.0, "{info}");
            let (capture, frame) = (info["capture_ns"].as_u64().unwrap(), info["frame_ns"].as_u64().unwrap());
            assert!(capture >= frame && capture - frame < period, "captured within its frame time: {info}");
        }
    }

    /// A camera whose pictures wait for the test: while it is stalled the
    /// loop's calls return with nothing; once the loop stops taking frames,
    /// the queue keeps the newest and counts the rest.
    #[test]
    fn a_stalled_camera_never_holds_the_loop_and_a_slow_loop_drops_frames_counted() {
        let (release, gate) = mpsc::channel::<()>();
        let snapshot: Snapshot = Box::new(move || {
            gate.recv().ok()?;
            Some(vec![0; 16 * 16 * 3])
        });
        let clock = Clock::new();
        let camera = CameraThread::start("test", SETTINGS, snapshot, clock, Waker::default(), None).unwrap();
        let mut component = CameraComponent::new(camera, "test");
        // Dropped before the component (which joins the camera's thread,
        // waiting at `gate`): a failed assert fails, never hangs.
        let release = release;
        let mut out = Outbox::new();
        // Stalled: every call returns at once with nothing.
        for now in 0..1000 {
            component.poll(now, &mut out);
            component.tick(now, &mut out).unwrap();
        }
        assert!(out.is_empty());
        // Ten pictures while the loop takes none.
        for _ in 0..10 {
            release.send(()).unwrap();
        }
        while component.camera.counters.made.load(Ordering::Relaxed) < 10 {
            std::thread::sleep(Duration::from_millis(1));
        }
        component.poll(0, &mut out);
        let status = component.status().unwrap().to_json();
        assert_eq!(status["frames_made"], 10);
        assert_eq!(status["frames_dropped"], 10 - MAX_QUEUED_FRAMES as u64);
        assert_eq!(status["frames_sent"], MAX_QUEUED_FRAMES as u64);
        assert_eq!(out.len(), 2 * MAX_QUEUED_FRAMES);
        let info: serde_json::Value = match &out[0] {
            (OUTPUT_INFO, Value::Text(text)) => serde_json::from_str(text).unwrap(),
            other => panic!("{other:?}"),
        };
        // The sixth picture made: at least its frame time's number (the
        // frame times of the stall count too).
        assert!(info["seq"].as_u64().unwrap() >= 10 - MAX_QUEUED_FRAMES as u64, "{info}");
        assert_eq!((info["width"].as_u64(), info["format"].as_str()), (Some(16), Some("jpeg")));
        assert!(matches!(&out[1], (OUTPUT_FRAME, Value::Bytes(b)) if b.starts_with(&[0xff, 0xd8])));
        drop(release);
    }
}
