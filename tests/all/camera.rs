//! `builtin:camera` with the simulator as its source, through the built
//! binary: `subsume run config/demo-camera.xml --record`, the recording read
//! back by the `mcap` package and every JPEG decoded by Pillow (both PyPI,
//! tests/python/camera_frames.py): the frames' count, size and time stamps,
//! and the robot drawn where the recorded pose says.

use std::process::Command;

use serde_json::Value as Json;
use subsume::camera::render::Viewport;
use subsume::sim::world;

use crate::support::{self, FREE_TELEOP_PORTS, read_report, subsume, text};

/// As config/demo-camera.xml sets them.
const WIDTH: u32 = 320;
const HEIGHT: u32 = 240;
const RATE_HZ: f64 = 5.0;
const SECONDS: f64 = 4.0;
/// How far (px) the robot's drawn centre may be from its recorded pose:
/// JPEG's error, the heading line inside the disc, and the odometry being
/// up to one feedback period (50 ms, <= 2.5 cm) older than the picture.
const TOLERANCE_PX: f64 = 3.0;

#[test]
fn the_demo_cameras_frames_are_recorded_as_jpeg_showing_the_robot_where_the_pose_says() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("camera.mcap");
    let report_path = dir.path().join("report.json");
    let mut args = vec!["run", "config/demo-camera.xml", "--duration", "4", "--record", file.to_str().unwrap()];
    args.extend(["--report", report_path.to_str().unwrap()]);
    args.extend(FREE_TELEOP_PORTS);
    let output = subsume().args(&args).output().unwrap();
    assert!(output.status.success(), "{}", text(&output.stderr));

    let read = Command::new(support::python())
        .arg(support::repo_root().join("tests/python/camera_frames.py"))
        .args([file.to_str().unwrap(), "/camera/frame", "/motors/pose"])
        .output()
        .unwrap();
    assert!(read.status.success(), "{}", text(&read.stderr));
    let read: Json = serde_json::from_slice(&read.stdout).unwrap();
    let frames = read["frames"].as_array().unwrap();
    let poses: Vec<Vec<f64>> = read["poses"]
        .as_array()
        .unwrap()
        .iter()
        .map(|p| p.as_array().unwrap().iter().map(|x| x.as_f64().unwrap()).collect())
        .collect();

    // rate x duration frame times, the first at the start: each one a frame
    // or, on a machine too loaded for the camera's (background) thread, a
    // frame time counted late (a loaded machine may lose one at the end to
    // the shutdown).
    let report = read_report(&report_path);
    let camera = &report["camera"];
    let expected = RATE_HZ * SECONDS;
    let count = frames.len() as f64;
    let times = count + camera["frames_late"].as_f64().unwrap();
    assert!((expected - 2.0..=expected + 1.0).contains(&times), "{count} frames, {camera}, expected about {expected}");
    assert!(count >= expected / 2.0, "{count} frames: {camera}");
    assert_eq!(camera["frames_sent"].as_u64(), Some(frames.len() as u64), "{camera}");
    assert_eq!(camera["frames_dropped"], 0, "{camera}");
    for frame in frames {
        assert_eq!((frame["format"].as_str(), frame["decoded_format"].as_str()), (Some("jpeg"), Some("JPEG")));
        assert_eq!((frame["width"].as_u64(), frame["height"].as_u64()), (Some(WIDTH.into()), Some(HEIGHT.into())));
        assert_eq!(frame["mode"], "RGB");
        // Captured before it was recorded, and not long before.
        let (stamp, logged) = (frame["stamp_ns"].as_u64().unwrap(), frame["log_time"].as_u64().unwrap());
        assert!(stamp <= logged && logged - stamp < 500_000_000, "{frame}");
    }
    // One frame per period on the loop's clock.
    let stamps: Vec<u64> = frames.iter().map(|f| f["stamp_ns"].as_u64().unwrap()).collect();
    let mut gaps: Vec<u64> = stamps.windows(2).map(|w| w[1] - w[0]).collect();
    gaps.sort_unstable();
    let median = gaps[gaps.len() / 2] as f64 / 1e9;
    assert!((median - 1.0 / RATE_HZ).abs() < 0.02, "median gap {median} s: {stamps:?}");

    // The robot where the pose recorded nearest to the picture says.
    let world = world::load(&support::repo_root().join("config/worlds/demo.world")).unwrap();
    let view = Viewport::fit(&world, WIDTH, HEIGHT);
    let mut compared = Vec::new();
    for frame in frames {
        let stamp = frame["stamp_ns"].as_f64().unwrap();
        let pose = poses.iter().min_by(|a, b| (a[0] - stamp).abs().total_cmp(&(b[0] - stamp).abs())).unwrap();
        if (pose[0] - stamp).abs() > 60e6 {
            continue; // no odometry near this picture (the very first)
        }
        let (px, py) = view.to_pixel(pose[1], pose[2]);
        let drawn = frame["robot_px"].as_array().unwrap_or_else(|| panic!("no robot in {frame}"));
        let (dx, dy) = (drawn[0].as_f64().unwrap() - px, drawn[1].as_f64().unwrap() - py);
        assert!(dx.hypot(dy) <= TOLERANCE_PX, "robot drawn at {drawn:?}, pose {pose:?} is at ({px:.1}, {py:.1})");
        compared.push((px, py));
    }
    assert!(compared.len() as f64 >= count - 3.0, "only {} of {count} frames had a pose near them", compared.len());
    let (first, last) = (compared[0], compared[compared.len() - 1]);
    assert!((last.0 - first.0).hypot(last.1 - first.1) > 5.0, "the robot did not move: {compared:?}");
}
