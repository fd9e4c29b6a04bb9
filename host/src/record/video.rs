//! A video of each camera in a recording (docs/camera.md, The video): the
//! `foxglove.CompressedImage` JPEG frames of every `/COMPONENT/frame`
//! topic, fed to the Debian `ffmpeg` binary, which encodes them as VP9 in
//! WebM, a video every browser plays. No codec here: ffmpeg decodes the
//! JPEGs and encodes the video.
//!
//! The video runs at the camera's set rate, one video frame per frame time
//! from the first picture on ([`plan`]): the `frame-info` before each
//! picture names the rate (`rate_hz`) and the picture's frame time (`seq`,
//! which counts frame times, pictures or not), so each picture goes to its
//! own frame time however late it was captured, a frame time whose picture
//! was skipped or dropped shows the picture before it, and the video goes
//! on to the camera's last frame time in the recording: it lasts as long as
//! the camera ran, on a busy machine too. A recording made before
//! `frame-info` had `rate_hz` gets the rate guessed from its capture times
//! ([`frame_rate`]) and ends at its last picture.
//!
//! Where ffmpeg is missing or fails, or takes longer than
//! [`MAX_ENCODE_TIME`], there is no video and [`VideoOutcome::missing`]
//! says why; nothing else changes.

use std::collections::BTreeMap;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use serde_json::Value as Json;

use super::schema::COMPRESSED_IMAGE;

/// The program that makes the videos: the Debian package `ffmpeg`.
pub const FFMPEG: &str = "ffmpeg";
/// Longest one video may take to encode: past it ffmpeg is killed and the
/// camera has no video (a huge recording must not hold the results).
pub const MAX_ENCODE_TIME: Duration = Duration::from_secs(300);
/// Most video frames one video may have (a day at 30 Hz): a recording
/// with capture times far apart must not make an endless video.
pub const MAX_VIDEO_FRAMES: u64 = 30 * 86_400;
/// Largest recording file read for pictures (each is read whole).
pub const MAX_SOURCE_BYTES: u64 = 1 << 30;
/// VP9's constant quality (0 best .. 63 smallest): a simulated world's
/// pictures at 640x480 and 10 fps stay well under 2 MB a minute.
const CRF: &str = "36";

/// What became of the videos of one recording.
#[derive(Debug, Default, PartialEq, Eq)]
pub struct VideoOutcome {
    /// The videos written: (camera, file).
    pub made: Vec<(String, PathBuf)>,
    /// The cameras without a video, and why.
    pub missing: Vec<(String, String)>,
}

/// One picture of a camera as the recording has it, with what the
/// `frame-info` just before it said (none in an old recording).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Picture {
    /// Capture time (unix ns).
    pub stamp: u64,
    /// The number of its frame time (the camera counts every frame time).
    pub seq: Option<u64>,
    /// The camera's set rate.
    pub rate_hz: Option<f64>,
    /// How long after its frame time it was captured (ns).
    pub late_ns: u64,
}

/// What a `frame-info` said, waiting for its picture.
#[derive(Clone, Copy, Debug, Default)]
struct Info {
    seq: Option<u64>,
    rate_hz: Option<f64>,
    late_ns: u64,
}

/// One camera's pictures as the recording has them.
#[derive(Debug, Default)]
struct Camera {
    /// In the order recorded.
    pictures: Vec<Picture>,
    /// The `frame-info` not yet followed by its picture.
    info: Option<Info>,
}

/// Why a camera's pictures make no video.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum PlanError {
    #[error("no pictures")]
    NoPictures,
    /// Without the camera's set rate, one capture time gives no rate.
    #[error("{0} picture: a video needs two")]
    TooFew(usize),
    #[error("more than {MAX_VIDEO_FRAMES} frames")]
    TooLong,
}

/// Where each picture goes in a video, and how long it is.
#[derive(Clone, Debug, PartialEq)]
pub struct Plan {
    pub rate: FrameRate,
    /// Per picture (in the order recorded), its video frame; `None`: not
    /// shown (a second picture in one frame time).
    pub slots: Vec<Option<u64>>,
    /// Video frames in all: after the last picture's, it is repeated.
    pub frames: u64,
}

/// The file name of camera `name`'s video (`video-NAME.webm`), its name's
/// characters other than letters, digits, `-` and `_` as `_`.
pub fn video_name(camera: &str) -> String {
    let safe: String =
        camera.chars().map(|c| if c.is_ascii_alphanumeric() || c == '-' || c == '_' { c } else { '_' }).collect();
    format!("video-{safe}.webm")
}

/// Whether `name` is a video [`video_name`] makes.
pub fn is_video_name(name: &str) -> bool {
    name.strip_prefix("video-")
        .and_then(|n| n.strip_suffix(".webm"))
        .is_some_and(|n| !n.is_empty() && n.chars().all(|c| c.is_ascii_alphanumeric() || c == '-' || c == '_'))
}

/// The camera a picture topic belongs to (`/camera/frame` -> `camera`).
fn camera_of(topic: &str) -> Option<&str> {
    topic.strip_prefix('/')?.strip_suffix(&format!("/{}", super::IMAGE_PORT)).filter(|c| !c.is_empty())
}

/// The camera a `frame-info` topic belongs to.
fn info_camera_of(topic: &str) -> Option<&str> {
    topic.strip_prefix('/')?.strip_suffix(&format!("/{}", super::IMAGE_INFO_PORT)).filter(|c| !c.is_empty())
}

/// The component whose outputs, calls or status a topic carries
/// (`/camera/frame`, `/subsume/calls/camera`, `/subsume/status/camera`).
fn component_of(topic: &str) -> Option<&str> {
    let rest = topic.strip_prefix('/')?;
    if let Some(name) = rest.strip_prefix("subsume/calls/").or_else(|| rest.strip_prefix("subsume/status/")) {
        return Some(name);
    }
    rest.split_once('/').map(|(name, _)| name).filter(|n| !n.is_empty() && *n != "subsume")
}

/// What a recorded `frame-info` (a `subsume.Value` whose text is the
/// camera's JSON) says.
fn info_of(json: &Json) -> Option<Info> {
    let text = json.get("value")?.get("text")?.as_str()?;
    let info: Json = serde_json::from_str(text).ok()?;
    let number = |key: &str| info.get(key).and_then(Json::as_u64);
    let late_ns = match (number("capture_ns"), number("frame_ns")) {
        (Some(capture), Some(frame)) => capture.saturating_sub(frame),
        _ => 0,
    };
    Some(Info { seq: number("seq"), rate_hz: info.get("rate_hz").and_then(Json::as_f64), late_ns })
}

/// The capture time of a `foxglove.CompressedImage` message (unix ns).
fn stamp_of(json: &Json) -> Option<u64> {
    let stamp = json.get("timestamp")?;
    Some(stamp.get("sec")?.as_u64()? * 1_000_000_000 + stamp.get("nsec")?.as_u64()?)
}

/// Calls `each(camera, message JSON)` for every picture in the recording
/// files `files`, in order.
fn for_each_picture(files: &[PathBuf], mut each: impl FnMut(&str, &Json)) {
    for_each_message(files, |topic, schema, _, data| {
        let Some(camera) = camera_of(topic).filter(|_| schema == Some(COMPRESSED_IMAGE)) else { return };
        if let Ok(json) = serde_json::from_slice::<Json>(data) {
            each(camera, &json);
        }
    });
}

/// Calls `each(topic, schema, log time, data)` for every message in the
/// recording files `files`, in order.
fn for_each_message(files: &[PathBuf], mut each: impl FnMut(&str, Option<&str>, u64, &[u8])) {
    for file in files {
        let size = std::fs::metadata(file).map(|m| m.len()).unwrap_or(0);
        if size > MAX_SOURCE_BYTES {
            tracing::warn!("{}: {size} bytes, more than the {MAX_SOURCE_BYTES} read for a video", file.display());
            continue;
        }
        let Ok(bytes) = std::fs::read(file) else { continue };
        let readable = super::readable::readable(&bytes);
        let Ok(stream) =
            mcap::MessageStream::new_with_options(readable.bytes, mcap::read::Options::IgnoreEndMagic.into())
        else {
            continue;
        };
        for message in stream {
            // A killed host's recording ends without a footer.
            let Ok(message) = message else { break };
            let schema = message.channel.schema.as_ref().map(|s| s.name.as_str());
            each(&message.channel.topic, schema, message.log_time, &message.data);
        }
    }
}

/// A frame rate as ffmpeg takes it (`NUM/DEN`) and its period (ns).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct FrameRate {
    pub num: u64,
    pub den: u64,
}

impl FrameRate {
    pub fn period_ns(self) -> f64 {
        1e9 * self.den as f64 / self.num as f64
    }

    fn as_arg(self) -> String {
        format!("{}/{}", self.num, self.den)
    }
}

/// The rate the capture times `stamps` were taken at: the span over the
/// frame times in it (each gap a whole number of periods, a gap of a
/// dropped frame two), snapped to a whole or quarter rate within 1% (the
/// camera's setting; capture times come a little after their frame time),
/// else to thousandths. `None` with fewer than two pictures.
pub fn frame_rate(stamps: &[u64]) -> Option<FrameRate> {
    let mut gaps: Vec<u64> = stamps.windows(2).filter(|w| w[1] > w[0]).map(|w| w[1] - w[0]).collect();
    if gaps.is_empty() {
        return None;
    }
    gaps.sort_unstable();
    let median = gaps[gaps.len() / 2] as f64;
    let periods: f64 = gaps.iter().map(|&g| (g as f64 / median).round().max(1.0)).sum();
    let span = (stamps.iter().max()? - stamps.iter().min()?) as f64;
    let hz = periods * 1e9 / span;
    for den in [1, 4] {
        let num = (hz * den as f64).round();
        if num >= 1.0 && (num / den as f64 - hz).abs() <= hz * 0.01 {
            return Some(FrameRate { num: num as u64, den });
        }
    }
    Some(FrameRate { num: ((hz * 1000.0).round() as u64).max(1), den: 1000 })
}

/// A camera's set rate `hz` as ffmpeg takes it: to a thousandth, reduced
/// (`10` -> `10/1`, `2.5` -> `5/2`); `None` when it is no rate.
pub fn stated_rate(hz: f64) -> Option<FrameRate> {
    if !hz.is_finite() || hz <= 0.0 || hz > 1e6 {
        return None;
    }
    let num = (hz * 1000.0).round() as u64;
    if num == 0 {
        return None;
    }
    let (mut a, mut b) = (num, 1000u64);
    while b != 0 {
        (a, b) = (b, a % b);
    }
    Some(FrameRate { num: num / a, den: 1000 / a })
}

/// Where camera pictures `pictures` (in the order recorded) go in its
/// video, `end` (unix ns) the latest time the recording has of the camera.
///
/// With the camera's set rate (`rate_hz`): the first picture is frame 0,
/// each next one `seq` frame times after the one before (by its capture
/// time when it has no `seq`, or a smaller one: a restarted camera), and
/// the video goes on to the last frame time at or before `end`. Without
/// (an old recording): at the rate [`frame_rate`] guesses, each picture at
/// its capture time's frame, up to the last picture.
pub fn plan(pictures: &[Picture], end: u64) -> Result<Plan, PlanError> {
    let first = pictures.first().ok_or(PlanError::NoPictures)?;
    match pictures.iter().find_map(|p| p.rate_hz).and_then(stated_rate) {
        Some(rate) => Ok(stated_plan(pictures, first, rate, end)),
        None => {
            let stamps: Vec<u64> = pictures.iter().map(|p| p.stamp).collect();
            let rate = frame_rate(&stamps).ok_or(PlanError::TooFew(stamps.len()))?;
            let first = *stamps.iter().min().ok_or(PlanError::NoPictures)?;
            let period = rate.period_ns();
            let mut slots = Vec::with_capacity(stamps.len());
            let mut next = 0u64;
            for stamp in stamps {
                let slot = ((stamp - first) as f64 / period).round() as u64;
                // Two pictures in one frame time: the first stands.
                slots.push((slot >= next).then_some(slot));
                next = next.max(slot + 1);
            }
            Ok(Plan { rate, slots, frames: next })
        }
    }
    .and_then(|plan| {
        if plan.frames > MAX_VIDEO_FRAMES {
            return Err(PlanError::TooLong);
        }
        Ok(plan)
    })
}

/// [`plan`] at the camera's set rate.
fn stated_plan(pictures: &[Picture], first: &Picture, rate: FrameRate, end: u64) -> Plan {
    let period = rate.period_ns();
    let mut slots = Vec::with_capacity(pictures.len());
    // The last picture placed: its frame, seq and capture time.
    let mut last: Option<(u64, Option<u64>, u64)> = None;
    for picture in pictures {
        let slot = match last {
            None => 0,
            Some((slot, Some(seq), _)) if picture.seq.is_some_and(|s| s > seq) => {
                slot.saturating_add(picture.seq.unwrap_or(seq) - seq)
            }
            Some((slot, _, stamp)) => {
                let periods = (picture.stamp.saturating_sub(stamp) as f64 / period).round() as u64;
                slot.saturating_add(periods.max(1))
            }
        };
        slots.push(Some(slot));
        last = Some((slot, picture.seq, picture.stamp));
    }
    let placed = last.map_or(0, |(slot, _, _)| slot.saturating_add(1));
    // The first picture's frame time, and the last one before `end`.
    let origin = first.stamp.saturating_sub(first.late_ns);
    let to_end = (end.saturating_sub(origin) as f64 / period).floor() as u64;
    Plan { rate, slots, frames: placed.max(to_end.saturating_add(1)) }
}

/// Makes `video-CAMERA.webm` in `dir` for each camera whose pictures the
/// recording files `files` (in order: `run.mcap`, `run.1.mcap`, ...) hold,
/// with the program `ffmpeg`. Each is written to a temporary file, synced
/// and renamed into place.
pub fn make_videos(files: &[PathBuf], dir: &Path, ffmpeg: &Path) -> VideoOutcome {
    let mut outcome = VideoOutcome::default();
    for (name, (pictures, end)) in read_cameras(files) {
        let made = plan(&pictures, end).map_err(|e| e.to_string());
        match made.and_then(|plan| make_video(files, &name, &plan, dir, ffmpeg)) {
            Ok(path) => outcome.made.push((name, path)),
            Err(why) => outcome.missing.push((name, why)),
        }
    }
    outcome
}

/// Each camera's pictures in the recording files `files` (each with what
/// the `frame-info` before it said) and the latest log time of its
/// outputs, calls and status (unix ns): how long the camera ran.
fn read_cameras(files: &[PathBuf]) -> BTreeMap<String, (Vec<Picture>, u64)> {
    let mut cameras: BTreeMap<String, Camera> = BTreeMap::new();
    // Per component: the latest log time of its outputs, calls and status.
    let mut ends: BTreeMap<String, u64> = BTreeMap::new();
    for_each_message(files, |topic, schema, log_time, data| {
        if let Some(component) = component_of(topic) {
            let end = ends.entry(component.to_string()).or_default();
            *end = (*end).max(log_time);
        }
        if let Some(camera) = info_camera_of(topic) {
            let info = serde_json::from_slice::<Json>(data).ok().as_ref().and_then(info_of);
            cameras.entry(camera.to_string()).or_default().info = info;
        } else if let Some(camera) = camera_of(topic).filter(|_| schema == Some(COMPRESSED_IMAGE))
            && let Some(stamp) = serde_json::from_slice::<Json>(data).ok().as_ref().and_then(stamp_of)
        {
            let camera = cameras.entry(camera.to_string()).or_default();
            let info = camera.info.take().unwrap_or_default();
            let (seq, rate_hz, late_ns) = (info.seq, info.rate_hz, info.late_ns);
            camera.pictures.push(Picture { stamp, seq, rate_hz, late_ns });
        }
    });
    cameras
        .into_iter()
        .filter(|(_, camera)| !camera.pictures.is_empty())
        .map(|(name, camera)| {
            let end = ends.get(&name).copied().unwrap_or(0);
            (name, (camera.pictures, end))
        })
        .collect()
}

/// One camera's video, or why there is none.
fn make_video(files: &[PathBuf], name: &str, plan: &Plan, dir: &Path, ffmpeg: &Path) -> Result<PathBuf, String> {
    let rate = plan.rate;
    let path = dir.join(video_name(name));
    let temporary = tempfile::Builder::new()
        .prefix(".video-")
        .suffix(".webm")
        .tempfile_in(dir)
        .map_err(|e| format!("cannot make a temporary file in the results: {e}"))?;
    let mut child = Command::new(ffmpeg)
        .args(["-hide_banner", "-loglevel", "error", "-y", "-f", "image2pipe", "-c:v", "mjpeg"])
        .args(["-framerate", &rate.as_arg(), "-i", "pipe:0"])
        .args(["-c:v", "libvpx-vp9", "-pix_fmt", "yuv420p", "-crf", CRF, "-b:v", "0"])
        .args(["-deadline", "realtime", "-cpu-used", "8", "-row-mt", "1", "-threads", "1"])
        .args(["-f", "webm"])
        .arg(temporary.path())
        .stdin(Stdio::piped())
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .map_err(|e| match e.kind() {
            std::io::ErrorKind::NotFound => {
                format!("{} was not found on this robot (install the Debian package ffmpeg)", ffmpeg.display())
            }
            _ => format!("{} did not start: {e}", ffmpeg.display()),
        })?;
    let started = Instant::now();
    // ffmpeg's complaints, read beside it (a full pipe would stall it).
    let complaints = child.stderr.take().map(|mut stderr| {
        std::thread::spawn(move || {
            let mut text = String::new();
            let _ = std::io::Read::read_to_string(&mut std::io::Read::take(&mut stderr, 64 * 1024), &mut text);
            text
        })
    });
    let fed = feed(files, name, plan, child.stdin.take(), started);
    let status = loop {
        match child.try_wait() {
            Ok(Some(status)) => break Ok(status),
            Ok(None) if started.elapsed() > MAX_ENCODE_TIME => {
                let _ = child.kill();
                let _ = child.wait();
                break Err(format!("ffmpeg took more than {} s", MAX_ENCODE_TIME.as_secs()));
            }
            Ok(None) => std::thread::sleep(Duration::from_millis(20)),
            Err(e) => break Err(format!("ffmpeg: {e}")),
        }
    };
    let complaints = complaints.and_then(|c| c.join().ok()).unwrap_or_default();
    let status = status?;
    let frames = fed?;
    if !status.success() {
        let said = complaints.lines().last().unwrap_or("").to_string();
        return Err(format!("ffmpeg failed ({status}): {said}"));
    }
    temporary.as_file().sync_all().map_err(|e| format!("cannot sync the video: {e}"))?;
    temporary.persist(&path).map_err(|e| format!("cannot keep the video: {e}"))?;
    tracing::info!("camera {name}: a video of {frames} frames at {} fps", rate.as_arg());
    Ok(path)
}

/// Writes camera `name`'s pictures to ffmpeg's `stdin`, each at its
/// frame of `plan` (a frame between two filled with the picture before it,
/// and the frames after the last picture with it); the number of frames
/// written.
fn feed(
    files: &[PathBuf],
    name: &str,
    plan: &Plan,
    stdin: Option<std::process::ChildStdin>,
    started: Instant,
) -> Result<u64, String> {
    use base64::Engine as _;
    let mut stdin = stdin.ok_or("ffmpeg has no input")?;
    let mut written: u64 = 0;
    let mut last: Option<Vec<u8>> = None;
    let mut failure: Option<String> = None;
    // The pictures are counted as `make_videos` counted them: each with a
    // capture time.
    let mut index = 0usize;
    for_each_picture(files, |camera, json| {
        if camera != name || failure.is_some() || stamp_of(json).is_none() {
            return;
        }
        index += 1;
        let Some(slot) = plan.slots.get(index - 1).copied().flatten() else { return };
        let Some(data) = json.get("data").and_then(Json::as_str) else { return };
        let Ok(jpeg) = base64::engine::general_purpose::STANDARD.decode(data) else { return };
        if slot < written {
            return;
        }
        let mut write = |bytes: &[u8]| stdin.write_all(bytes).map_err(|e| format!("ffmpeg stopped reading: {e}"));
        while written < slot {
            if let Some(previous) = &last
                && let Err(e) = write(previous)
            {
                failure = Some(e);
                return;
            }
            written += 1;
        }
        if let Err(e) = write(&jpeg) {
            failure = Some(e);
            return;
        }
        written += 1;
        last = Some(jpeg);
        if started.elapsed() > MAX_ENCODE_TIME {
            failure = Some(format!("ffmpeg took more than {} s", MAX_ENCODE_TIME.as_secs()));
        }
    });
    while failure.is_none() && written < plan.frames {
        if let Some(previous) = &last
            && let Err(e) = stdin.write_all(previous)
        {
            failure = Some(format!("ffmpeg stopped reading: {e}"));
        }
        written += 1;
    }
    drop(stdin);
    match failure {
        Some(why) => Err(why),
        None => Ok(written),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// (capture times in ms, the rate found).
    #[test]
    fn the_rate_is_the_cameras_even_with_late_and_dropped_pictures() {
        let ms = |v: &[u64]| v.iter().map(|m| m * 1_000_000).collect::<Vec<_>>();
        let cases: [(&[u64], Option<FrameRate>); 6] = [
            (&[0, 200, 401, 600, 800], Some(FrameRate { num: 5, den: 1 })),
            // A dropped picture (400) and late ones.
            (&[0, 201, 600, 801, 1000, 1200], Some(FrameRate { num: 5, den: 1 })),
            (&[0, 100, 200, 301, 400, 500, 600, 700, 800, 900, 1000], Some(FrameRate { num: 10, den: 1 })),
            (&[0, 400, 800, 1200], Some(FrameRate { num: 10, den: 4 })),
            (&[0, 333, 667, 1000], Some(FrameRate { num: 3, den: 1 })),
            (&[5], None),
        ];
        for (stamps, rate) in cases {
            assert_eq!(frame_rate(&ms(stamps)), rate, "{stamps:?}");
        }
    }

    const MS: u64 = 1_000_000;
    /// A recording's epoch (unix ns).
    const EPOCH: u64 = 1_700_000_000_000_000_000;

    /// Pictures at 10 Hz as the camera's `frame-info` names them: (frame
    /// time's seq, capture time's lateness in ms).
    fn at_10hz(frames: &[(u64, u64)]) -> Vec<Picture> {
        let picture = |&(seq, late): &(u64, u64)| Picture {
            stamp: EPOCH + seq * 100 * MS + late * MS,
            seq: Some(seq),
            rate_hz: Some(10.0),
            late_ns: late * MS,
        };
        frames.iter().map(picture).collect()
    }

    const TEN: FrameRate = FrameRate { num: 10, den: 1 };

    /// Every frame time has its picture: one video frame each, the video
    /// to the last frame time before the recording's end.
    #[test]
    fn at_the_stated_rate_each_picture_is_one_video_frame() {
        let pictures = at_10hz(&[(0, 2), (1, 3), (2, 1), (3, 2), (4, 2)]);
        let plan = plan(&pictures, EPOCH + 450 * MS).unwrap();
        assert_eq!(plan, Plan { rate: TEN, slots: (0..5).map(Some).collect(), frames: 5 });
    }

    /// Dropped and skipped frame times (seq jumps): each picture at its
    /// own frame time, the gaps repeat the picture before.
    #[test]
    fn dropped_frame_times_leave_gaps_of_exactly_their_number() {
        let pictures = at_10hz(&[(0, 1), (1, 1), (4, 1), (5, 1), (9, 1)]);
        let plan = plan(&pictures, EPOCH + 990 * MS).unwrap();
        assert_eq!(plan.rate, TEN);
        assert_eq!(plan.slots, vec![Some(0), Some(1), Some(4), Some(5), Some(9)]);
        assert_eq!(plan.frames, 10);
    }

    /// Captures delayed by most of a period, some bunched together: the
    /// frame times (seq), not the capture times, place them.
    #[test]
    fn delayed_captures_stay_at_their_frame_times() {
        let pictures = at_10hz(&[(0, 0), (1, 95), (2, 5), (3, 90), (4, 99), (5, 0)]);
        let plan = plan(&pictures, EPOCH + 500 * MS).unwrap();
        assert_eq!((plan.rate, plan.frames), (TEN, 6));
        assert_eq!(plan.slots, (0..6).map(Some).collect::<Vec<_>>());
    }

    /// A starved camera: one picture a second at 10 Hz, the last long
    /// before the run ended. The video keeps 10 fps and runs to the end
    /// (the old guess from capture times made it about 1 fps).
    #[test]
    fn a_starved_camera_keeps_its_rate_and_the_video_lasts_the_run() {
        let pictures = at_10hz(&[(0, 30), (10, 40), (21, 80), (31, 10)]);
        let plan = plan(&pictures, EPOCH + 5_990 * MS).unwrap();
        assert_eq!(plan.rate, TEN);
        assert_eq!(plan.slots, vec![Some(0), Some(10), Some(21), Some(31)]);
        assert_eq!(plan.frames, 60);
        // One picture and the run's end: a video all the same.
        let one = plan_of(&at_10hz(&[(0, 30)]), EPOCH + 1_000 * MS);
        assert_eq!((one.frames, one.slots), (11, vec![Some(0)]));
        // A camera's last message a year on: no endless video.
        let year = EPOCH + 365 * 86_400 * 1_000 * MS;
        assert_eq!(super::plan(&at_10hz(&[(0, 30)]), year), Err(PlanError::TooLong));
    }

    fn plan_of(pictures: &[Picture], end: u64) -> Plan {
        plan(pictures, end).unwrap()
    }

    /// A picture whose `frame-info` was lost, and a restarted camera (its
    /// seq starts again): placed by capture time after the one before.
    #[test]
    fn pictures_without_a_usable_seq_are_placed_by_their_capture_times() {
        let mut pictures = at_10hz(&[(0, 1), (1, 1), (2, 1), (3, 1)]);
        pictures[2].seq = None;
        pictures.extend(at_10hz(&[(0, 1), (1, 1)]).into_iter().map(|mut p| {
            p.stamp += 700 * MS; // restarted 0.7 s after the first
            p
        }));
        let plan = plan_of(&pictures, EPOCH + 1_250 * MS);
        assert_eq!(plan.slots, vec![Some(0), Some(1), Some(2), Some(3), Some(7), Some(8)]);
        assert_eq!((plan.rate, plan.frames), (TEN, 13));
    }

    /// An old recording (no `rate_hz`): the rate is guessed from the
    /// capture times and the video ends at its last picture.
    #[test]
    fn an_old_recording_gets_the_guessed_rate() {
        let pictures: Vec<Picture> = [0u64, 201, 600, 801, 1000, 1200]
            .iter()
            .map(|ms| Picture { stamp: EPOCH + ms * MS, ..Picture::default() })
            .collect();
        let guessed = plan_of(&pictures, EPOCH + 5_000 * MS);
        assert_eq!(guessed.rate, FrameRate { num: 5, den: 1 });
        assert_eq!(guessed.slots, vec![Some(0), Some(1), Some(3), Some(4), Some(5), Some(6)]);
        assert_eq!(guessed.frames, 7);
        assert_eq!(plan(&pictures[..1], EPOCH).unwrap_err().to_string(), "1 picture: a video needs two");
        assert_eq!(plan(&[], EPOCH).unwrap_err(), PlanError::NoPictures);
    }

    #[test]
    fn a_stated_rate_is_a_reduced_fraction() {
        assert_eq!(stated_rate(10.0), Some(TEN));
        assert_eq!(stated_rate(2.5), Some(FrameRate { num: 5, den: 2 }));
        assert_eq!(stated_rate(1e9 / 333_333_333.0), Some(FrameRate { num: 3, den: 1 }));
        assert_eq!(stated_rate(0.125), Some(FrameRate { num: 1, den: 8 }));
        for no in [0.0, -1.0, f64::NAN, f64::INFINITY, 1e-5] {
            assert_eq!(stated_rate(no), None, "{no}");
        }
    }

    /// A recording file of `messages` (topic, schema, log time, JSON).
    fn recording(path: &Path, messages: &[(&str, &str, u64, Json)]) {
        let mut writer = mcap::Writer::new(std::io::BufWriter::new(std::fs::File::create(path).unwrap())).unwrap();
        let mut channels = BTreeMap::new();
        for (n, (topic, schema_name, log_time, json)) in messages.iter().enumerate() {
            let channel = *channels.entry(topic.to_string()).or_insert_with(|| {
                let schema = serde_json::to_vec(&super::super::schema::schema(schema_name)).unwrap();
                let schema = writer.add_schema(schema_name, "jsonschema", &schema).unwrap();
                writer.add_channel(schema, topic, "json", &BTreeMap::new()).unwrap()
            });
            let header = mcap::records::MessageHeader {
                channel_id: channel,
                sequence: n as u32,
                log_time: *log_time,
                publish_time: *log_time,
            };
            writer.write_to_known_channel(&header, &serde_json::to_vec(json).unwrap()).unwrap();
        }
        writer.finish().unwrap();
    }

    /// The recording as the host writes it: each picture after its
    /// `frame-info`, a lost `frame-info`, and the camera's status going on
    /// after its last picture: each picture gets what its own `frame-info`
    /// said, and the camera ran to its last status.
    #[test]
    fn each_picture_is_read_with_its_frame_info_and_the_camera_runs_to_its_last_message() {
        use super::super::schema::{STATUS, VALUE, compressed_image};
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("run.mcap");
        let info = |seq: u64, capture: u64| {
            let text = serde_json::json!({"format": "jpeg", "width": 16, "height": 16, "capture_ns": capture,
                "rate_hz": 10.0, "frame_ns": seq * 100 * MS, "seq": seq});
            serde_json::json!({"t": capture, "value": {"text": text.to_string()}})
        };
        let jpeg = [0xff, 0xd8, 0xff, 0xd9];
        let mut messages = Vec::new();
        for (seq, capture, with_info) in [(0, 20 * MS, true), (3, 330 * MS, true), (4, 410 * MS, false)] {
            if with_info {
                messages.push(("/camera/frame-info", VALUE, EPOCH + capture + MS, info(seq, capture)));
            }
            messages.push((
                "/camera/frame",
                COMPRESSED_IMAGE,
                EPOCH + capture + MS,
                compressed_image(&jpeg, "camera", EPOCH + capture),
            ));
        }
        messages.push(("/subsume/status/camera", STATUS, EPOCH + 1_450 * MS, serde_json::json!({})));
        messages.push(("/subsume/log", super::super::schema::LOG, EPOCH + 9_000 * MS, serde_json::json!({})));
        recording(&file, &messages);
        let cameras = read_cameras(&[file]);
        let (pictures, end) = &cameras["camera"];
        assert_eq!(*end, EPOCH + 1_450 * MS, "the log is not the camera's");
        let expected = vec![
            Picture { stamp: EPOCH + 20 * MS, seq: Some(0), rate_hz: Some(10.0), late_ns: 20 * MS },
            Picture { stamp: EPOCH + 330 * MS, seq: Some(3), rate_hz: Some(10.0), late_ns: 30 * MS },
            Picture { stamp: EPOCH + 410 * MS, seq: None, rate_hz: None, late_ns: 0 },
        ];
        assert_eq!(pictures, &expected);
        let plan = plan_of(pictures, *end);
        assert_eq!((plan.rate, plan.slots, plan.frames), (TEN, vec![Some(0), Some(3), Some(4)], 15));
    }

    #[test]
    fn video_names_are_safe_file_names() {
        assert_eq!(video_name("camera"), "video-camera.webm");
        assert_eq!(video_name("top.cam/x"), "video-top_cam_x.webm");
        for name in ["video-camera.webm", "video-a_b-1.webm"] {
            assert!(is_video_name(name), "{name}");
        }
        for name in ["video-.webm", "video-../x.webm", "video-a.mp4", "camera.webm", "video-a.b.webm"] {
            assert!(!is_video_name(name), "{name}");
        }
        assert_eq!(camera_of("/camera/frame"), Some("camera"));
        assert_eq!(camera_of("/camera/frame-info"), None);
    }

    /// A recording with pictures and no ffmpeg: no video, and why.
    #[test]
    fn without_ffmpeg_there_is_no_video_and_the_outcome_says_why() {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("run.mcap");
        let mut writer = mcap::Writer::new(std::io::BufWriter::new(std::fs::File::create(&file).unwrap())).unwrap();
        let schema = serde_json::to_vec(&super::super::schema::schema(COMPRESSED_IMAGE)).unwrap();
        let schema = writer.add_schema(COMPRESSED_IMAGE, "jsonschema", &schema).unwrap();
        let channel = writer.add_channel(schema, "/camera/frame", "json", &BTreeMap::new()).unwrap();
        for n in 0..3u64 {
            let json = super::super::schema::compressed_image(&[0xff, 0xd8, 0xff, 0xd9], "camera", n * 200_000_000);
            let header = mcap::records::MessageHeader {
                channel_id: channel,
                sequence: n as u32,
                log_time: n * 200_000_000,
                publish_time: n * 200_000_000,
            };
            writer.write_to_known_channel(&header, &serde_json::to_vec(&json).unwrap()).unwrap();
        }
        writer.finish().unwrap();
        drop(writer);
        let outcome = make_videos(&[file], dir.path(), Path::new("/nonexistent/ffmpeg"));
        assert!(outcome.made.is_empty());
        assert_eq!(outcome.missing.len(), 1, "{outcome:?}");
        let (camera, why) = &outcome.missing[0];
        assert_eq!(camera, "camera");
        assert!(why.contains("/nonexistent/ffmpeg was not found on this robot"), "{why}");
        let left: Vec<_> = std::fs::read_dir(dir.path()).unwrap().flatten().map(|e| e.file_name()).collect();
        assert_eq!(left, vec![std::ffi::OsString::from("run.mcap")], "a temporary file was left");
    }
}
