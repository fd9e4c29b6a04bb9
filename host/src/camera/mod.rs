//! `builtin:camera`: a camera whose frames are JPEG pictures on an output
//! port (docs/camera.md). Its one source today is the simulator
//! (`source="sim:NAME"`, a `builtin:sim` component): the simulated world
//! seen from above ([`render`]). V4L2 devices and IP cameras are not done.
//!
//! Rendering and encoding run on the camera's own thread, paced on the
//! control loop's clock; finished frames wait in a [`FrameQueue`] of at most
//! [`MAX_QUEUED_FRAMES`] that drops the oldest and counts the drops. The
//! component takes them out in `poll`, never waiting: the control loop never
//! waits on a picture. The thread runs at the background's nice value
//! (`runtime::scheduling::BACKGROUND_NICE`), below the loop's.
//!
//! Each frame is two values in the same cycle: `frame` (bytes: the JPEG
//! file) and `frame-info` (text: JSON with its format, size, capture time
//! on the loop's clock, and sequence number).

pub mod render;

use std::collections::VecDeque;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, PoisonError};
use std::thread::JoinHandle;
use std::time::Duration;

use self::render::{Scene, render};
use crate::builtin::{
    BuildContext, Builtin, BuiltinError, CheckContext, ParamDecl, ParamType, Params, Ports, Registry, builtin_of, port,
    positive_up_to,
};
use crate::config::{ParamProblem, RobotProblem, RobotView};
use crate::contract::{Value, ValueKind};
use crate::runtime::control_loop::{Clock, Waker};
use crate::runtime::scheduling;
use crate::runtime::{CallError, Component, NamedSection, Outbox, StatusSection};
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

/// The prefix of a `source` naming a simulated robot.
const SIM_SOURCE: &str = "sim:";
/// Output ports.
const OUTPUT_FRAME: u32 = 0;
const OUTPUT_INFO: u32 = 1;

const PARAMS: &[ParamDecl] = &[
    ParamDecl {
        name: "source",
        ty: ParamType::Required,
        default: "",
        unit: "",
        doc: "sim:NAME: the builtin:sim component NAME's world seen from above (the only source so far)",
    },
    ParamDecl {
        name: "width",
        ty: ParamType::Integer { min: MIN_SIDE_PX, max: MAX_WIDTH_PX },
        default: "320",
        unit: "px",
        doc: "picture width",
    },
    ParamDecl {
        name: "height",
        ty: ParamType::Integer { min: MIN_SIDE_PX, max: MAX_HEIGHT_PX },
        default: "240",
        unit: "px",
        doc: "picture height",
    },
    ParamDecl {
        name: "rate",
        ty: positive_up_to(MAX_RATE_HZ),
        default: "5",
        unit: "Hz",
        doc: "frames per second, on the control loop's clock",
    },
    ParamDecl {
        name: "quality",
        ty: ParamType::Integer { min: 1, max: 100 },
        default: "80",
        unit: "",
        doc: "JPEG quality",
    },
];

/// The `camera` kind.
pub struct CameraBuiltin;

/// The simulated robot a `source` names.
fn sim_name(source: &str) -> Option<&str> {
    source.strip_prefix(SIM_SOURCE).filter(|name| !name.is_empty())
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
        "A camera: JPEG frames of the simulated world seen from above"
    }

    fn params(&self) -> &'static [ParamDecl] {
        PARAMS
    }

    fn check(&self, params: &Params, _ctx: &mut CheckContext<'_>) -> Vec<ParamProblem> {
        let source = params.text("source").unwrap_or_default();
        if sim_name(source).is_none() {
            let shown = crate::contract::clip_to(source, 64);
            return vec![ParamProblem::new(
                "source",
                format!(
                    "must be sim:NAME, naming a builtin:sim component (V4L2 and IP cameras are not supported yet), not '{shown}'"
                ),
            )];
        }
        Vec::new()
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
                    "JSON about the frame just sent on 'frame': format, width, height, capture_ns (the loop's clock), seq",
                ),
            ],
        }
    }

    fn build(&self, params: &Params, ctx: &mut BuildContext<'_>) -> Result<Box<dyn Component>, BuiltinError> {
        let source = params.text("source")?;
        let sim = sim_name(source).ok_or_else(|| BuiltinError::Param {
            name: "source".into(),
            why: format!("is not sim:NAME: '{source}'"),
        })?;
        let control = ctx.services.get::<SimRegistry>().and_then(|registry| registry.get(sim)).ok_or_else(|| {
            BuiltinError::Refused(format!("source 'sim:{sim}' names no running builtin:sim component"))
        })?;
        let (world, body) = control.world_and_body();
        let settings = CameraSettings {
            width: side(params, "width")?,
            height: side(params, "height")?,
            period_ns: (1e9 / params.number("rate")?).round() as u64,
            quality: u8::try_from(params.integer("quality")?)
                .map_err(|_| BuiltinError::Param { name: "quality".into(), why: "is out of range".into() })?,
        };
        let snapshot: Snapshot = Box::new(move || {
            let status = control.status();
            let scene =
                Scene { world: &world, body, pose: (status.x, status.y, status.heading), ranges: &status.ranges };
            Some(render(&scene, u32::from(settings.width), u32::from(settings.height)).rgb)
        });
        let name = ctx.component()?.name.clone();
        let camera = CameraThread::start(&name, settings, snapshot, ctx.clock.clone(), ctx.waker.clone())
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
    /// Nanoseconds of wall time spent rendering and encoding.
    busy_ns: AtomicU64,
}

/// The camera's thread and what it shares.
pub struct CameraThread {
    queue: Arc<FrameQueue>,
    counters: Arc<Counters>,
    stop: Arc<AtomicBool>,
    thread: Option<JoinHandle<()>>,
    settings: CameraSettings,
}

impl CameraThread {
    /// Starts taking a picture with `snapshot` every `settings.period_ns` on
    /// `clock`, encoding it and queueing it; `waker` brings the loop round.
    pub fn start(
        name: &str,
        settings: CameraSettings,
        mut snapshot: Snapshot,
        clock: Clock,
        waker: Waker,
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
            let mut seq = 0;
            while !s.load(Ordering::Relaxed) {
                let now = clock.now_ns();
                if now < next_ns {
                    std::thread::sleep(CLOCK_POLL);
                    continue;
                }
                let skipped = (now - next_ns) / period;
                c.late.fetch_add(skipped, Ordering::Relaxed);
                next_ns += (skipped + 1) * period;
                let started = std::time::Instant::now();
                let Some(rgb) = snapshot() else { continue };
                match encode(&rgb, settings) {
                    Ok(jpeg) => {
                        q.push(Frame { jpeg, width: settings.width, height: settings.height, capture_ns: now, seq });
                        seq += 1;
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
        Ok(CameraThread { queue, counters, stop, thread: Some(thread), settings })
    }
}

impl Drop for CameraThread {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
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
    sent: u64,
}

impl CameraComponent {
    pub fn new(camera: CameraThread, source: &'static str) -> CameraComponent {
        CameraComponent { camera, source, sent: 0 }
    }
}

/// The JSON `frame-info` carries.
fn frame_info(frame: &Frame) -> String {
    serde_json::json!({
        "format": "jpeg",
        "width": frame.width,
        "height": frame.height,
        "capture_ns": frame.capture_ns,
        "seq": frame.seq,
    })
    .to_string()
}

impl Component for CameraComponent {
    fn poll(&mut self, _now_ns: u64, out: &mut Outbox) {
        for frame in self.camera.queue.take() {
            out.push((OUTPUT_INFO, Value::Text(frame_info(&frame))));
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
        Some(Box::new(CameraSection {
            source: self.source,
            width: self.camera.settings.width,
            height: self.camera.settings.height,
            frames_made: c.made.load(Ordering::Relaxed),
            frames_sent: self.sent,
            frames_dropped: self.camera.queue.dropped(),
            frames_late: c.late.load(Ordering::Relaxed),
            encode_failures: c.encode_failures.load(Ordering::Relaxed),
            busy_s: c.busy_ns.load(Ordering::Relaxed) as f64 / 1e9,
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
    /// Frame times skipped because the one before took longer than a period.
    pub frames_late: u64,
    pub encode_failures: u64,
    /// Wall time the camera's thread spent rendering and encoding.
    pub busy_s: f64,
}

impl NamedSection for CameraSection {
    const SECTION: &'static str = "camera";
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]

    use std::sync::mpsc;

    use super::*;

    fn frame(seq: u64) -> Frame {
        Frame { jpeg: vec![0xff, 0xd8], width: 16, height: 16, capture_ns: seq, seq }
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
        let _camera = CameraThread::start("nice", SETTINGS, snapshot, Clock::new(), Waker::default()).unwrap();
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
        let camera = CameraThread::start("test", SETTINGS, snapshot, clock, Waker::default()).unwrap();
        let mut component = CameraComponent::new(camera, "test");
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
        assert_eq!(info["seq"], 10 - MAX_QUEUED_FRAMES as u64);
        assert_eq!((info["width"].as_u64(), info["format"].as_str()), (Some(16), Some("jpeg")));
        assert!(matches!(&out[1], (OUTPUT_FRAME, Value::Bytes(b)) if b.starts_with(&[0xff, 0xd8])));
        drop(release);
    }
}
