//! A video of each camera in a recording (docs/camera.md, The video): the
//! `foxglove.CompressedImage` JPEG frames of every `/COMPONENT/frame`
//! topic, fed to the Debian `ffmpeg` binary, which encodes them as VP9 in
//! WebM, a video every browser plays. No codec here: ffmpeg decodes the
//! JPEGs and encodes the video.
//!
//! The video runs at the camera's rate, one video frame per period from the
//! first picture on: a frame time whose picture was dropped or late shows
//! the picture before it, so the video lasts as long as the camera ran.
//! The rate is the recording's own (the span of the capture times over the
//! frame times in it), snapped to the camera's setting.
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

/// One camera's pictures as the recording has them.
#[derive(Debug, Default)]
struct Camera {
    /// Capture times (unix ns), in the order recorded.
    stamps: Vec<u64>,
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

/// The capture time of a `foxglove.CompressedImage` message (unix ns).
fn stamp_of(json: &Json) -> Option<u64> {
    let stamp = json.get("timestamp")?;
    Some(stamp.get("sec")?.as_u64()? * 1_000_000_000 + stamp.get("nsec")?.as_u64()?)
}

/// Calls `each(camera, message JSON)` for every picture in the recording
/// files `files`, in order.
fn for_each_picture(files: &[PathBuf], mut each: impl FnMut(&str, &Json)) {
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
            let is_picture = message.channel.schema.as_ref().is_some_and(|s| s.name == COMPRESSED_IMAGE);
            let Some(camera) = camera_of(&message.channel.topic).filter(|_| is_picture) else { continue };
            let Ok(json) = serde_json::from_slice::<Json>(&message.data) else { continue };
            each(camera, &json);
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

/// Makes `video-CAMERA.webm` in `dir` for each camera whose pictures the
/// recording files `files` (in order: `run.mcap`, `run.1.mcap`, ...) hold,
/// with the program `ffmpeg`. Each is written to a temporary file, synced
/// and renamed into place.
pub fn make_videos(files: &[PathBuf], dir: &Path, ffmpeg: &Path) -> VideoOutcome {
    let mut cameras: BTreeMap<String, Camera> = BTreeMap::new();
    for_each_picture(files, |camera, json| {
        if let Some(stamp) = stamp_of(json) {
            cameras.entry(camera.to_string()).or_default().stamps.push(stamp);
        }
    });
    let mut outcome = VideoOutcome::default();
    for (name, camera) in cameras {
        match make_video(files, &name, &camera, dir, ffmpeg) {
            Ok(path) => outcome.made.push((name, path)),
            Err(why) => outcome.missing.push((name, why)),
        }
    }
    outcome
}

/// One camera's video, or why there is none.
fn make_video(files: &[PathBuf], name: &str, camera: &Camera, dir: &Path, ffmpeg: &Path) -> Result<PathBuf, String> {
    let rate =
        frame_rate(&camera.stamps).ok_or_else(|| format!("{} picture: a video needs two", camera.stamps.len()))?;
    let first = *camera.stamps.iter().min().ok_or("no pictures")?;
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
    let fed = feed(files, name, first, rate, child.stdin.take(), started);
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

/// Writes camera `name`'s pictures to ffmpeg's `stdin`, one per frame time
/// from `first` on at `rate` (a missing one filled with the picture before
/// it); the number of frames written.
fn feed(
    files: &[PathBuf],
    name: &str,
    first: u64,
    rate: FrameRate,
    stdin: Option<std::process::ChildStdin>,
    started: Instant,
) -> Result<u64, String> {
    use base64::Engine as _;
    let mut stdin = stdin.ok_or("ffmpeg has no input")?;
    let period = rate.period_ns();
    let mut written: u64 = 0;
    let mut last: Option<Vec<u8>> = None;
    let mut failure: Option<String> = None;
    for_each_picture(files, |camera, json| {
        if camera != name || failure.is_some() {
            return;
        }
        let (Some(stamp), Some(data)) = (stamp_of(json), json.get("data").and_then(Json::as_str)) else { return };
        let Ok(jpeg) = base64::engine::general_purpose::STANDARD.decode(data) else { return };
        let slot = ((stamp.saturating_sub(first)) as f64 / period).round() as u64;
        if slot < written {
            return; // two pictures in one frame time: the first stands
        }
        if slot >= MAX_VIDEO_FRAMES {
            failure = Some(format!("more than {MAX_VIDEO_FRAMES} frames"));
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
