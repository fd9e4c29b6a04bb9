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
    // The counter first: the cameras are built (and start receiving) once
    // the WASM component is compiled, just before the loop starts.
    let body = format!(
        "<robot name=\"ipcam\">\n  <platform name=\"control\">\n    {COUNTER}\n    {cameras}\n  </platform>\n</robot>"
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
    // after the frame timeout and dialled again (still nothing), said once.
    let stall = camera_section(&report, "stall");
    assert_eq!(stall["frames_sent"], 3, "{stall}\n{log}");
    assert!(stall["stream_errors"].as_u64().unwrap() >= 1, "{stall}");
    assert!(stall["reconnects"].as_u64().unwrap() >= 1, "{stall}");
    assert_eq!(stall["stale"], true, "{stall}");
    assert!(stall["last_frame_age_s"].as_f64().unwrap() > 5.0, "{stall}");
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

/// A live camera stream asked over HTTP/1.0 (so the portal sends the
/// multipart body as it is, not in chunks).
struct Watch {
    stream: std::net::TcpStream,
    buf: Vec<u8>,
}

impl Watch {
    /// Asks `path` as `token`: the status, and the watch when it is 200
    /// (the body otherwise).
    fn open(address: &str, token: Option<&str>, path: &str) -> (u16, Result<Watch, String>) {
        use std::io::Write;
        let mut stream = std::net::TcpStream::connect(address).unwrap();
        stream.set_read_timeout(Some(Duration::from_secs(20))).unwrap();
        let auth = token.map(|t| format!("Authorization: Bearer {t}\r\n")).unwrap_or_default();
        write!(stream, "GET {path} HTTP/1.0\r\nHost: {address}\r\n{auth}\r\n").unwrap();
        let mut watch = Watch { stream, buf: Vec::new() };
        let head = watch.until(b"\r\n\r\n").expect("an answer's head");
        let head = String::from_utf8_lossy(&head).into_owned();
        let status: u16 = head.split(' ').nth(1).unwrap().parse().unwrap();
        if status != 200 {
            let mut body = std::mem::take(&mut watch.buf);
            let _ = std::io::Read::read_to_end(&mut watch.stream, &mut body);
            return (status, Err(String::from_utf8_lossy(&body).into_owned()));
        }
        assert!(
            head.to_ascii_lowercase().contains("content-type: multipart/x-mixed-replace; boundary=subsume-frame"),
            "{head}"
        );
        (status, Ok(watch))
    }

    /// Bytes up to and including `end`; `None` at the end of the stream.
    fn until(&mut self, end: &[u8]) -> Option<Vec<u8>> {
        loop {
            if let Some(at) = self.buf.windows(end.len()).position(|w| w == end) {
                let rest = self.buf.split_off(at + end.len());
                return Some(std::mem::replace(&mut self.buf, rest));
            }
            let mut chunk = [0; 65536];
            let got = std::io::Read::read(&mut self.stream, &mut chunk).unwrap_or(0);
            if got == 0 {
                return None;
            }
            self.buf.extend_from_slice(&chunk[..got]);
        }
    }

    /// The next frame's JPEG bytes; `None` once the stream ends.
    fn frame(&mut self) -> Option<Vec<u8>> {
        self.numbered_frame().map(|(_, jpeg)| jpeg)
    }

    /// The next frame's number (`X-Seq`) and JPEG bytes; `None` once the
    /// stream ends.
    fn numbered_frame(&mut self) -> Option<(u64, Vec<u8>)> {
        let head = self.until(b"\r\n\r\n")?;
        let head = String::from_utf8_lossy(&head).into_owned();
        assert!(head.trim_start().starts_with("--subsume-frame\r\n"), "{head}");
        assert!(head.contains("Content-Type: image/jpeg"), "{head}");
        let length: usize = head
            .lines()
            .find_map(|l| l.strip_prefix("Content-Length: "))
            .unwrap_or_else(|| panic!("no length: {head}"))
            .trim()
            .parse()
            .unwrap();
        while self.buf.len() < length + 2 {
            let mut chunk = [0; 65536];
            let got = std::io::Read::read(&mut self.stream, &mut chunk).unwrap_or(0);
            if got == 0 {
                return None;
            }
            self.buf.extend_from_slice(&chunk[..got]);
        }
        let seq: u64 = head
            .lines()
            .find_map(|l| l.strip_prefix("X-Seq: "))
            .unwrap_or_else(|| panic!("no frame number: {head}"))
            .trim()
            .parse()
            .unwrap();
        let rest = self.buf.split_off(length);
        let jpeg = std::mem::replace(&mut self.buf, rest);
        Some((seq, jpeg))
    }
}

/// A JPEG file of `width` x `height` (its SOF0 header, as jpeg-encoder
/// writes it).
fn assert_picture(jpeg: &[u8], width: u16, height: u16) {
    assert_eq!(&jpeg[..2], &[0xff, 0xd8], "start of image");
    assert_eq!(&jpeg[jpeg.len() - 2..], &[0xff, 0xd9], "end of image");
    let sof = jpeg.windows(2).position(|w| w == [0xff, 0xc0]).unwrap();
    let [h0, h1] = height.to_be_bytes();
    let [w0, w1] = width.to_be_bytes();
    assert_eq!(&jpeg[sof + 5..sof + 9], &[h0, h1, w0, w1]);
}

/// The lab's robot with an overhead camera, turning on the spot for as
/// long as it runs (above the planner, which would otherwise reach its goal
/// and stand still: then every picture is the same, and a browser cannot
/// tell a stream that plays from one that froze).
const LIVE_CAMERA: &str = r#"<component name="overhead" source="builtin:camera">
      <param name="source" value="sim:robot-sim"/>
      <param name="width" value="160"/>
      <param name="height" value="120"/>
      <param name="rate" value="10"/>
    </component>
    <component name="turn" source="builtin:publish" rate="10" priority="2">
      <param name="kind" value="command"/>
      <param name="value" value="VEL 0 0.8"/>
    </component>
    <connect from="turn.out" to="arbiter.commands"/>"#;

/// The portal's live camera by role: the owner (admin) and an operator
/// watch it; a researcher only during her own experiment (not before, not
/// another researcher's, and her stream ends with it); a viewer and a
/// developer never; nobody without a session; a camera that does not run
/// is 404. Eight watch at once beside one that reads nothing, each getting
/// its pictures in order. The Live tab in Chromium (tests/browser/cameras.mjs) plays it
/// for the admin and the operator and shows none to a viewer or a
/// researcher without an experiment.
#[test]
fn the_live_camera_is_shown_to_the_owner_operators_and_a_researcher_only_during_her_experiment() {
    let dir = tempfile::tempdir().unwrap();
    let robot = crate::lab::robot(8.0, LIVE_CAMERA);
    std::fs::write(dir.path().join("robot.xml"), &robot).unwrap();
    std::fs::write(dir.path().join("lab.world"), crate::lab::WORLD).unwrap();
    let store = dir.path().join("store");
    let password = crate::lab::PASSWORD;
    for (name, role, platforms) in [
        ("boss", "admin", &[][..]),
        ("olga", "operator", &[]),
        ("ana", "researcher", &["control"]),
        ("ben", "researcher", &["control"]),
        ("vera", "viewer", &[]),
        ("dev", "developer", &["control"]),
    ] {
        support::add_user(&store, name, role, platforms, password);
    }
    let lab = crate::lab::start(dir.path());
    let address = lab.address.clone();
    let token = |name: &str| support::login(&address, name, password);
    let (boss, olga, ana, ben, vera, dev) =
        (token("boss"), token("olga"), token("ana"), token("ben"), token("vera"), token("dev"));
    let live = "/api/v1/cameras/overhead/live";

    for (who, token) in [("boss", &boss), ("olga", &olga)] {
        let (status, watch) = Watch::open(&address, Some(token), live);
        assert_eq!(status, 200, "{who}: {watch:?}", watch = watch.as_ref().err());
        let mut watch = watch.unwrap();
        for _ in 0..3 {
            assert_picture(&watch.frame().expect("a frame"), 160, 120);
        }
    }
    // Many watchers at once beside one that reads nothing: each that reads
    // gets whole pictures in order, and none waits for the stalled one.
    let stalled = Watch::open(&address, Some(&olga), live).1.unwrap();
    let watchers: Vec<_> = (0..8)
        .map(|i| {
            let (address, token) = (address.clone(), if i % 2 == 0 { boss.clone() } else { olga.clone() });
            std::thread::spawn(move || {
                let (status, watch) = Watch::open(&address, Some(&token), live);
                assert_eq!(status, 200, "watcher {i}: {watch:?}", watch = watch.as_ref().err());
                let mut watch = watch.unwrap();
                (0..10)
                    .map(|_| {
                        let (seq, jpeg) = watch.numbered_frame().expect("a frame");
                        assert_picture(&jpeg, 160, 120);
                        seq
                    })
                    .collect::<Vec<u64>>()
            })
        })
        .collect();
    for watcher in watchers {
        let seqs = watcher.join().unwrap();
        assert!(seqs.windows(2).all(|pair| pair[0] < pair[1]), "frames out of order: {seqs:?}");
    }
    drop(stalled);
    let (status, json) = support::http(&address, "GET", "/api/v1/cameras", Some(&olga), b"");
    assert_eq!((status, json["cameras"].clone()), (200, serde_json::json!(["overhead"])), "{json}");
    for (who, token, expected) in
        [("ana", Some(&ana), 403), ("vera", Some(&vera), 403), ("dev", Some(&dev), 403), ("nobody", None, 401)]
    {
        let (status, body) = Watch::open(&address, token.map(String::as_str), live);
        assert_eq!(status, expected, "{who}: {body:?}", body = body.as_ref().err());
        let body: Json = serde_json::from_str(body.as_ref().err().unwrap()).unwrap();
        assert!(body["error"].is_string(), "{who}: {body}");
    }
    let (status, _) = Watch::open(&address, Some(&boss), "/api/v1/cameras/nowhere/live");
    assert_eq!(status, 404);

    // The portal's Live tab in Chromium: the camera plays for those who may
    // watch, and is not there for the others.
    // Its screenshots stay after the run, beside the other browser tests'.
    let artifacts = support::repo_root().join("target/browser-artifacts/cameras");
    let url = format!("http://{address}/");
    let users: [&dyn AsRef<std::ffi::OsStr>; 6] =
        [&url, &password, &"boss:watch", &"olga:watch", &"vera:none", &"ana:none"];
    let seen: Json =
        serde_json::from_str(support::browser("cameras.mjs", &artifacts, &[], &users).lines().last().unwrap()).unwrap();
    for who in ["boss", "olga"] {
        let shown = &seen[who];
        assert_eq!((shown["cameras"].as_u64(), shown["width"].as_u64()), (Some(1), Some(160)), "{who}: {seen}");
        assert_eq!((shown["height"].as_u64(), shown["changed"].as_bool()), (Some(120), Some(true)), "{who}: {seen}");
    }
    for who in ["vera", "ana"] {
        assert_eq!(
            (seen[who]["cameras"].as_u64(), seen[who]["hidden"].as_bool()),
            (Some(0), Some(true)),
            "{who}: {seen}"
        );
    }

    // Ana's experiment: she watches while it runs, Ben does not.
    let (status, json) =
        support::http(&address, "PUT", "/api/v1/platforms/control/configs/ana.xml", Some(&ana), robot.as_bytes());
    assert_eq!(status, 201, "{json}");
    let set = json["set"]["id"].as_u64().unwrap();
    let body = serde_json::json!({ "set": set, "duration_s": 6.0, "label": "watched" });
    let (status, json) =
        support::http(&address, "POST", "/api/v1/experiments", Some(&ana), body.to_string().as_bytes());
    assert_eq!(status, 201, "{json}");
    let id = json["experiment"]["id"].as_u64().unwrap();
    let state = |id: u64| {
        let (_, json) = support::http(&address, "GET", &format!("/api/v1/experiments/{id}"), Some(&ana), b"");
        json["experiment"]["state"].as_str().unwrap_or("").to_string()
    };
    let deadline = Instant::now() + Duration::from_secs(180);
    while state(id) != "running" {
        assert!(
            !["done", "failed", "aborted", "refused", "cancelled"].contains(&state(id).as_str()),
            "{}",
            lab.host.log()
        );
        assert!(Instant::now() < deadline, "experiment {id} never ran:\n{}", lab.host.log());
        std::thread::sleep(Duration::from_millis(100));
    }
    let (status, watch) = Watch::open(&address, Some(&ana), live);
    assert_eq!(status, 200, "ana during her experiment: {:?}", watch.as_ref().err());
    let mut watch = watch.unwrap();
    assert_picture(&watch.frame().expect("a frame"), 160, 120);
    let (status, body) = Watch::open(&address, Some(&ben), live);
    assert_eq!(status, 403, "ben during ana's experiment: {:?}", body.as_ref().err());
    // Her stream ends with her experiment.
    let mut frames = 1;
    while watch.frame().is_some() {
        frames += 1;
        assert!(Instant::now() < deadline, "the stream outlived the experiment");
    }
    while !["done", "failed", "aborted"].contains(&state(id).as_str()) {
        assert!(Instant::now() < deadline, "experiment {id} never ended");
        std::thread::sleep(Duration::from_millis(100));
    }
    assert!(frames >= 10, "{frames} frames in a 6 s experiment at 10 fps");
    eprintln!("ana watched {frames} frames; the experiment was {} after her stream ended", state(id));
    let (status, body) = Watch::open(&address, Some(&ana), live);
    assert_eq!(status, 403, "ana after her experiment: {:?}", body.as_ref().err());
}

/// A robot cruising at 0.2 m/s whose envelope watches `camera` (its
/// `frame` wired to `envelope.camera`), for `seconds`: the report and
/// the log.
fn cruise_watching(dir: &std::path::Path, camera: &str, seconds: &str) -> (Json, String) {
    std::fs::write(dir.join("open.world"), "bounds 0 0 20 20\nstart 2 10 0\ngoal 18 10 0.3\n").unwrap();
    let body = format!(
        r#"<robot name="watched">
  <platform name="control">
    <component name="sim" source="builtin:sim"><param name="world" value="open.world"/></component>
    <component name="motors" source="builtin:serial" rate="100"><param name="device" value="sim:sim"/></component>
    <component name="camera" source="builtin:camera">
      <param name="source" value="{camera}"/>
      <param name="rate" value="10"/>
    </component>
    <component name="cruise" source="builtin:publish" rate="10" priority="1">
      <param name="kind" value="command"/><param name="value" value="VEL 0.2 0"/>
    </component>
    <component name="arbiter" source="builtin:arbiter" rate="20"/>
    <component name="envelope" source="builtin:envelope" rate="20"><param name="stale-camera" value="1.0"/></component>
    <connect from="cruise.out" to="arbiter.commands"/>
    <connect from="arbiter.cmd" to="envelope.cmd"/>
    <connect from="motors.ranges" to="envelope.ranges"/>
    <connect from="camera.frame" to="envelope.camera"/>
    <connect from="envelope.cmd" to="motors.cmd"/>
  </platform>
</robot>"#
    );
    let robot = support::robot_file(dir, &body);
    let report = dir.join("report.json");
    let output = subsume().args(["run", "--duration", seconds, "--report"]).arg(&report).arg(&robot).output().unwrap();
    let log = text(&output.stderr);
    assert!(output.status.success(), "{log}");
    (read_report(&report), log)
}

/// Issue 42: a camera that stops sending is a stale sensor, and the
/// envelope's staleness rules apply to it when it is wired there (a
/// component steering by it would steer blind). The same cruising robot
/// with a camera that keeps sending (the simulator's) drives on; with one
/// that stalls after three pictures (tests/python/bad_camera.py) it stops
/// once the last picture is older than `stale-camera`, and stays stopped,
/// the envelope naming the camera.
#[test]
fn a_camera_that_stops_sending_stops_the_robot_through_the_envelope_when_wired_there() {
    let dir = tempfile::tempdir().unwrap();
    let (report, log) = cruise_watching(dir.path(), "sim:sim", "5");
    let (sim, envelope) = (&report["sim"], &report["envelope"]);
    let driven = sim["distance_travelled_m"].as_f64().unwrap();
    // 0.2 m/s for 5 s, less the start before the first picture.
    assert!(driven > 0.6, "the robot did not drive with its camera sending: {driven} m\n{envelope}\n{log}");
    let last = envelope["last"]["cause"].as_str().unwrap_or("");
    assert!(!last.starts_with("camera stale"), "{envelope}");

    let mut server = Command::new(support::python())
        .arg(support::repo_root().join("tests/python/bad_camera.py"))
        .arg((MAX_FRAME_BYTES + 1024).to_string())
        .stdout(Stdio::piped())
        .stderr(Stdio::inherit())
        .spawn()
        .unwrap();
    let lines = BufReader::new(server.stdout.take().unwrap()).lines();
    let _server = Killed(server);
    let port = lines
        .take(3)
        .map(Result::unwrap)
        .find_map(|line| line.strip_prefix("stall ").map(str::to_string))
        .expect("the stalling camera's port");
    let (report, log) = cruise_watching(dir.path(), &format!("http://127.0.0.1:{port}/"), "5");
    let (sim, envelope, camera) = (&report["sim"], &report["envelope"], camera_section(&report, "camera"));
    // Its three pictures (on a busy machine two may come so close together
    // that the second is skipped, as sooner than its rate allows).
    let sent = camera["frames_sent"].as_u64().unwrap_or(0);
    assert!((1..=3).contains(&sent), "{camera}\n{log}");
    let driven = sim["distance_travelled_m"].as_f64().unwrap();
    // Three pictures a tenth of a second apart, then 1 s of grace: about
    // 1.3 s of driving once the first came; never the 5 s.
    assert!(driven < 0.45, "the robot drove on blind: {driven} m\n{envelope}");
    assert!(envelope["causes"]["stale-camera"].as_u64().unwrap_or(0) >= 1, "{envelope}");
    // The camera stopped it (on a busy machine the simulator's ranges may
    // go stale later too, and stop it as well).
    let first = &envelope["first"]["stale-camera"];
    assert!(first["cause"].as_str().unwrap_or("").starts_with("camera stale ("), "{envelope}");
    assert_eq!(first["action"], "stopped", "{envelope}");
    assert_eq!(envelope["last"]["action"], "stopped", "{envelope}");
}
