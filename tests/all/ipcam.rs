//! `builtin:camera` with an IP camera as its source (`source="http://..."`,
//! MJPEG over HTTP), through the built binary. The camera is Debian's
//! `ffmpeg` serving its test pattern (`-f mpjpeg -listen 1`: chunked, no
//! boundary in its Content-Type); the recording is read back by the `mcap`
//! package and every frame decoded by Pillow (tests/python/camera_frames.py),
//! and the video `record::video` makes of it is read by `ffprobe`. Three
//! misbehaving cameras (tests/python/bad_camera.py: garbage, oversized
//! frames, a stall) are dropped, counted and logged once while the loop
//! keeps its rate.

use std::io::{BufRead, BufReader};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use serde_json::Value as Json;
use subsume::camera::mjpeg::MAX_FRAME_BYTES;

use crate::support::{self, component, read_report, subsume, text};

/// A child process killed when the test ends.
struct Killed(Child);

impl Drop for Killed {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// Waits until something listens on loopback `port` (read from
/// /proc/net/tcp: connecting would use up ffmpeg's one client).
fn wait_listening(port: u16, server: &mut Child) {
    let needle = format!(":{port:04X} 00000000:0000 0A");
    let deadline = Instant::now() + Duration::from_secs(20);
    loop {
        let table = std::fs::read_to_string("/proc/net/tcp").unwrap();
        if table.contains(&needle) {
            return;
        }
        assert!(server.try_wait().unwrap().is_none(), "the camera server exited");
        assert!(Instant::now() < deadline, "nothing listens on port {port}");
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// The camera section of `name` in a report (`camera`, or `camera:NAME`
/// for the cameras after the first).
fn camera_section<'a>(report: &'a Json, name: &str) -> &'a Json {
    let keyed = &report[format!("camera:{name}")];
    if keyed.is_object() {
        return keyed;
    }
    &report["camera"]
}

/// A 100 Hz counter beside the cameras, to show the loop kept its rate.
const COUNTER: &str = r#"<component name="counter" source="GUEST(test-counter)" rate="100"/>
    <component name="sink" source="builtin:log" rate="0"><param name="interval" value="100"/></component>
    <connect from="counter.count" to="sink.in"/>"#;

fn run(dir: &std::path::Path, cameras: &str, seconds: &str, record: Option<&std::path::Path>) -> (String, Json) {
    support::guest_dir();
    let body = format!(
        "<robot name=\"ipcam\">\n  <platform name=\"control\">\n    {cameras}\n    {COUNTER}\n  </platform>\n</robot>"
    );
    let robot = support::robot_file(dir, &body);
    let report = dir.join("report.json");
    let mut command = subsume();
    command.args(["run", "--duration", seconds, "--report", report.to_str().unwrap()]);
    if let Some(file) = record {
        command.arg("--record").arg(file);
    }
    command.arg(&robot);
    let output = command.output().unwrap();
    let log = text(&output.stderr);
    assert!(output.status.success(), "{log}");
    (log, read_report(&report))
}

const FFMPEG_RATE_HZ: f64 = 10.0;

#[test]
fn an_ip_cameras_mjpeg_stream_served_by_ffmpeg_is_recorded_as_jpeg_frames_and_makes_a_video() {
    let dir = tempfile::tempdir().unwrap();
    let port = support::free_port();
    let mut ffmpeg = Command::new("ffmpeg")
        .args(["-nostdin", "-loglevel", "error", "-re", "-f", "lavfi", "-i", "testsrc=size=320x240:rate=10"])
        .args(["-f", "mpjpeg", "-listen", "1"])
        .arg(format!("http://127.0.0.1:{port}/cam.mjpg"))
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .expect("ffmpeg (Debian's, scripts/setup installs it)");
    wait_listening(port, &mut ffmpeg);
    let _ffmpeg = Killed(ffmpeg);
    let file = dir.path().join("run.mcap");
    let cameras = format!(
        r#"<component name="camera" source="builtin:camera">
      <param name="source" value="http://127.0.0.1:{port}/cam.mjpg"/>
      <param name="rate" value="10"/>
    </component>"#
    );
    let seconds = 4.0;
    let (log, report) = run(dir.path(), &cameras, "4", Some(&file));

    let camera = camera_section(&report, "camera");
    eprintln!("ffmpeg's camera: {camera}; loop lateness {}", report["loop_lateness"]);
    assert_eq!(camera["source"], "http", "{camera}");
    assert_eq!(camera["url"], format!("http://127.0.0.1:{port}/cam.mjpg"), "{camera}");
    assert_eq!((camera["width"].as_u64(), camera["height"].as_u64()), (Some(320), Some(240)), "{camera}");
    assert_eq!(camera["frames_rejected"], 0, "{camera}\n{log}");
    assert_eq!(camera["frames_dropped"], 0, "{camera}");
    assert_eq!(camera["stream_errors"], 0, "{camera}\n{log}");
    assert_eq!(camera["stale"], false, "{camera}");
    let sent = camera["frames_sent"].as_f64().unwrap();
    // ffmpeg paces its pattern at 10 fps (-re); the first frames come once
    // the host has started and dialled.
    assert!(sent >= FFMPEG_RATE_HZ * seconds * 0.6, "{sent} frames: {camera}\n{log}");
    assert!(sent <= FFMPEG_RATE_HZ * seconds + 2.0, "{sent} frames: {camera}");
    support::kept_its_rate(&report, component(&report, "counter"), 100.0, 0.05, 0.0, "counter beside the camera");

    // The recording, read by the mcap package; each frame decoded by Pillow.
    let read = Command::new(support::python())
        .arg(support::repo_root().join("tests/python/camera_frames.py"))
        .args([file.to_str().unwrap(), "/camera/frame", "/no/pose"])
        .output()
        .unwrap();
    assert!(read.status.success(), "{}", text(&read.stderr));
    let read: Json = serde_json::from_slice(&read.stdout).unwrap();
    let frames = read["frames"].as_array().unwrap();
    assert_eq!(frames.len() as f64, sent, "every frame sent is recorded");
    for frame in frames {
        assert_eq!((frame["format"].as_str(), frame["decoded_format"].as_str()), (Some("jpeg"), Some("JPEG")));
        assert_eq!((frame["width"].as_u64(), frame["height"].as_u64()), (Some(320), Some(240)), "{frame}");
        let (stamp, logged) = (frame["stamp_ns"].as_u64().unwrap(), frame["log_time"].as_u64().unwrap());
        assert!(stamp <= logged && logged - stamp < 500_000_000, "{frame}");
    }
    // The test pattern moves: frames differ.
    let lumas: Vec<f64> = frames.iter().map(|f| f["luma"].as_f64().unwrap()).collect();
    assert!(lumas.iter().any(|l| (l - lumas[0]).abs() > 0.01), "{lumas:?}");
    // Captured at ffmpeg's pace, on the loop's clock.
    let stamps: Vec<u64> = frames.iter().map(|f| f["stamp_ns"].as_u64().unwrap()).collect();
    assert!(stamps.windows(2).all(|w| w[0] < w[1]), "{stamps:?}");
    let mut gaps: Vec<u64> = stamps.windows(2).map(|w| w[1] - w[0]).collect();
    gaps.sort_unstable();
    let median = gaps[gaps.len() / 2] as f64 / 1e9;
    assert!((median - 1.0 / FFMPEG_RATE_HZ).abs() < 0.02, "median gap {median} s: {stamps:?}");

    // The video the lab makes of a run's cameras, read by ffprobe.
    let videos = dir.path().join("videos");
    std::fs::create_dir_all(&videos).unwrap();
    let outcome = subsume::record::video::make_videos(
        std::slice::from_ref(&file),
        &videos,
        std::path::Path::new(subsume::record::video::FFMPEG),
    );
    let video = videos.join(subsume::record::video::video_name("camera"));
    assert!(video.is_file(), "no video: {outcome:?}");
    let probe = Command::new("ffprobe")
        .args(["-v", "error", "-count_frames", "-select_streams", "v:0", "-of", "json"])
        .args(["-show_entries", "stream=codec_name,width,height,r_frame_rate,nb_read_frames"])
        .arg(&video)
        .output()
        .unwrap();
    assert!(probe.status.success(), "{}", text(&probe.stderr));
    let probe: Json = serde_json::from_slice(&probe.stdout).unwrap();
    let stream = &probe["streams"][0];
    assert_eq!((stream["width"].as_u64(), stream["height"].as_u64()), (Some(320), Some(240)), "{probe}");
    assert_eq!(stream["r_frame_rate"], "10/1", "{probe}");
    let video_frames: f64 = stream["nb_read_frames"].as_str().unwrap().parse().unwrap();
    assert!(video_frames >= sent, "{video_frames} video frames for {sent} pictures: {probe}");
}

/// How often `what` is in `log`.
fn said(log: &str, what: &str) -> usize {
    log.matches(what).count()
}

#[test]
fn garbage_oversized_and_stalled_cameras_are_dropped_counted_logged_once_and_the_loop_keeps_its_rate() {
    let dir = tempfile::tempdir().unwrap();
    let big = MAX_FRAME_BYTES + 1024 * 1024;
    let mut server = Command::new(support::python())
        .arg(support::repo_root().join("tests/python/bad_camera.py"))
        .arg(big.to_string())
        .stdout(Stdio::piped())
        .stderr(Stdio::inherit())
        .spawn()
        .unwrap();
    let mut lines = BufReader::new(server.stdout.take().unwrap()).lines();
    let _server = Killed(server);
    let mut cameras = String::new();
    for _ in 0..3 {
        let line = lines.next().unwrap().unwrap();
        let (name, port) = line.split_once(' ').unwrap();
        cameras.push_str(&format!(
            r#"<component name="{name}" source="builtin:camera">
      <param name="source" value="http://127.0.0.1:{port}/"/>
      <param name="rate" value="10"/>
    </component>
    "#
        ));
    }
    let (log, report) = run(dir.path(), &cameras, "8", None);

    // Garbage: parts that are not JPEG dropped and counted, said once; the
    // unframed bytes lose the stream, which is dialled again, said once.
    let garbage = camera_section(&report, "garbage");
    assert!(garbage["frames_sent"].as_u64().unwrap() >= 5, "{garbage}");
    assert!(garbage["frames_rejected"].as_u64().unwrap() >= 5, "{garbage}");
    assert!(garbage["stream_errors"].as_u64().unwrap() >= 1, "{garbage}");
    assert!(garbage["reconnects"].as_u64().unwrap() >= 1, "{garbage}");
    assert_eq!(said(&log, "a part is not a JPEG file (no start-of-image marker)"), 1, "{log}");
    assert_eq!(said(&log, "the stream lost its multipart framing"), 1, "{log}");

    // Oversized: each dropped and counted (announced or not), said once;
    // the good frames between them keep coming.
    let oversized = camera_section(&report, "oversized");
    assert!(oversized["frames_sent"].as_u64().unwrap() >= 10, "{oversized}");
    assert!(oversized["frames_rejected"].as_u64().unwrap() >= 10, "{oversized}");
    assert_eq!(oversized["stream_errors"], 0, "{oversized}\n{log}");
    assert_eq!(said(&log, "is larger than the limit"), 1, "{log}");
    assert!(oversized["last_frame_age_s"].as_f64().unwrap() < 1.0, "{oversized}");
    assert_eq!(oversized["stale"], false, "{oversized}");

    // Stalled: three frames, then nothing: stale, its age shown; given up
    // after the frame timeout, dialled again (three more), said once.
    let stall = camera_section(&report, "stall");
    assert_eq!(stall["frames_sent"], 6, "{stall}\n{log}");
    assert_eq!(stall["stream_errors"], 1, "{stall}");
    assert_eq!(stall["reconnects"], 1, "{stall}");
    assert_eq!(stall["stale"], true, "{stall}");
    assert!(stall["last_frame_age_s"].as_f64().unwrap() > 2.0, "{stall}");
    assert_eq!(said(&log, "(the camera stalled)"), 1, "{log}");

    for name in ["garbage", "oversized", "stall"] {
        let section = camera_section(&report, name);
        eprintln!("{name}: {section}");
        assert_eq!(section["frames_dropped"], 0, "{name}: {section}");
    }
    let counter = component(&report, "counter");
    eprintln!(
        "counter: {} ticks, {} missed; loop lateness {}",
        counter["ticks"], counter["missed_ticks"], report["loop_lateness"]
    );
    support::kept_its_rate(&report, counter, 100.0, 0.05, 0.0, "counter beside bad cameras");
}
