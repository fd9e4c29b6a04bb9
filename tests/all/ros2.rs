//! The ROS 2 face end to end, against implementations no one here wrote:
//! `tests/python/ros2_peer.py` is the ROS 2 side, built on the
//! `eclipse-zenoh` package (the Zenoh peer) and `rosbags` (CDR for every
//! message, REP-2016 type hashes computed from the definitions). The wire
//! format (key expressions, attachment, liveliness tokens) is rmw_zenoh's
//! (ros2/rmw_zenoh docs/design.md); the fixtures in `bridge::ros2`'s unit
//! tests are the document's own examples.

use std::io::{BufRead, BufReader, Write};
use std::process::{Child, ChildStdin, ChildStdout, Command, Stdio};
use std::time::Duration;

use serde_json::Value as Json;
use subsume::bridge::cdr::{self, Header, LaserScan, Log, Odometry, Time, Twist};
use subsume::bridge::ros2::MessageType;

use crate::support::{self, free_port, read_report, subsume, wait_for_exit};

fn peer_once(mode: &str) -> Json {
    let out = Command::new(support::python())
        .arg(support::repo_root().join("tests/python/ros2_peer.py"))
        .arg(mode)
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    serde_json::from_slice(&out.stdout).unwrap()
}

#[test]
fn the_type_hashes_are_the_ones_rosbags_computes_from_the_definitions() {
    let hashes = peer_once("hashes");
    for (name, ty) in MessageType::ALL {
        assert_eq!(hashes[name], ty.rihs01(), "{name}");
    }
}

#[test]
fn the_cdr_bytes_are_the_ones_rosbags_writes() {
    let fixtures = peer_once("fixtures");
    let stamp = Time { sec: 12, nanosec: 34 };
    let header = |frame: &str| Header { stamp, frame_id: frame.into() };
    let ours = [
        ("twist", Twist { linear: [0.5, 0.0, 0.0], angular: [0.0, 0.0, -1.0] }.encode()),
        ("bool", cdr::encode_bool(true)),
        ("log", Log { stamp, level: 20, name: "subsume".into(), msg: "hello".into(), ..Log::default() }.encode()),
        (
            "scan",
            LaserScan {
                header: header("base_scan"),
                angle_min: -1.5,
                angle_max: 1.5,
                angle_increment: 1.5,
                range_max: 4.0,
                ranges: vec![1.0, 2.0, 3.0],
                ..LaserScan::default()
            }
            .encode(),
        ),
        (
            "odom",
            Odometry {
                header: header("odom"),
                child_frame_id: "base_link".into(),
                position: [1.5, -2.0, 0.0],
                orientation: [0.0, 0.0, 0.5, 0.75],
                twist: Twist::default(),
            }
            .encode(),
        ),
    ];
    for (name, bytes) in ours {
        assert_eq!(hex::encode(&bytes), fixtures[name].as_str().unwrap(), "{name}");
        let theirs = hex::decode(fixtures[name].as_str().unwrap()).unwrap();
        match name {
            "twist" => assert!(Twist::decode(&theirs).is_ok()),
            "log" => assert_eq!(Log::decode(&theirs).unwrap().msg, "hello"),
            "scan" => assert_eq!(LaserScan::decode(&theirs).unwrap().ranges, vec![1.0, 2.0, 3.0]),
            "odom" => assert_eq!(Odometry::decode(&theirs).unwrap().position, [1.5, -2.0, 0.0]),
            _ => assert_eq!(cdr::decode_bool(&theirs), Ok(true)),
        }
    }
}

struct Peer {
    child: Child,
    stdin: Option<ChildStdin>,
    stdout: BufReader<ChildStdout>,
}

impl Peer {
    fn start(mode: &str, endpoint: &str) -> Peer {
        Peer::spawn(&[mode, endpoint])
    }

    /// `ros2_peer.py ARGS`, once it is ready.
    fn spawn(args: &[&str]) -> Peer {
        let mut child = Command::new(support::python())
            .arg(support::repo_root().join("tests/python/ros2_peer.py"))
            .args(args)
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .spawn()
            .unwrap();
        let stdin = child.stdin.take();
        let mut stdout = BufReader::new(child.stdout.take().unwrap());
        let mut line = String::new();
        stdout.read_line(&mut line).unwrap();
        assert_eq!(line.trim(), "ready");
        Peer { child, stdin, stdout }
    }

    fn finish(mut self) -> Json {
        if let Some(mut stdin) = self.stdin.take() {
            let _ = stdin.flush();
        }
        let mut line = String::new();
        self.stdout.read_line(&mut line).unwrap();
        let _ = self.child.wait();
        serde_json::from_str(&line).unwrap_or_else(|e| panic!("peer said {line:?}: {e}"))
    }
}

impl Drop for Peer {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// `subsume run CONFIG --param zenoh.connect=ENDPOINT`, stopped by SIGTERM
/// after `run_for`; returns its report.
fn run_host(config: &str, endpoint: &str, run_for: Duration) -> Json {
    let dir = tempfile::tempdir().unwrap();
    let report = dir.path().join("report.json");
    let mut child = subsume()
        .args(["run", config])
        .args(["--param", &format!("zenoh.connect={endpoint}")])
        .args(["--duration", "120", "--report", report.to_str().unwrap()])
        .stdout(Stdio::null())
        .stderr(Stdio::inherit())
        .spawn()
        .unwrap();
    std::thread::sleep(run_for);
    support::signal(child.id(), "TERM");
    wait_for_exit(&mut child, Duration::from_secs(20));
    read_report(&report)
}

fn section<'a>(report: &'a Json, key_part: &str) -> &'a Json {
    report
        .as_object()
        .unwrap()
        .iter()
        .find(|(name, v)| name.starts_with("ros2") && v["key"].as_str().unwrap_or("").contains(key_part))
        .map(|(_, v)| v)
        .unwrap_or_else(|| panic!("no ros2 section for {key_part}"))
}

#[test]
fn use_a_ros2_tools_drive_the_simulated_robot_and_decode_scan_and_odom() {
    let endpoint = format!("tcp/127.0.0.1:{}", free_port());
    let peer = Peer::start("robot", &endpoint);
    // Drive for a few seconds once connected; the host's session retries
    // its connect until the peer answers.
    let report = std::thread::scope(|s| {
        let host = s.spawn(|| run_host("config/ros2-demo.xml", &endpoint, Duration::from_secs(6)));
        std::thread::sleep(Duration::from_secs(5));
        let summary = peer.finish();
        (host.join().unwrap(), summary)
    });
    let (report, summary) = report;
    assert_eq!(summary["bad"], Json::Array(vec![]), "{summary}");
    // /odom decoded by rosbags: the Twist moved the robot.
    let first = &summary["odom_first"];
    let last = &summary["odom_last"];
    let moved = ((last[0].as_f64().unwrap() - first[0].as_f64().unwrap()).powi(2)
        + (last[1].as_f64().unwrap() - first[1].as_f64().unwrap()).powi(2))
    .sqrt();
    assert!(moved > 0.3, "the robot moved {moved} m: {first} -> {last}");
    assert_eq!((last[3].as_str(), last[4].as_str()), (Some("odom"), Some("base_link")));
    assert!(summary["odom_count"].as_u64().unwrap() > 20, "{summary}");
    // /scan decoded by rosbags: the simulator's 9 rays over 180 degrees.
    let scan = &summary["scan"];
    assert_eq!(scan["ranges"].as_array().unwrap().len(), 9, "{scan}");
    assert!((scan["angle_min"].as_f64().unwrap() + std::f64::consts::FRAC_PI_2).abs() < 1e-3, "{scan}");
    assert!((scan["angle_increment"].as_f64().unwrap() - std::f64::consts::FRAC_PI_8).abs() < 1e-3, "{scan}");
    assert_eq!(scan["frame_id"], "base_scan");
    assert!(summary["scans"].as_u64().unwrap() > 20);
    // The liveliness tokens `ros2 node list` and `ros2 topic list` read.
    let tokens: Vec<&str> = summary["tokens"].as_array().unwrap().iter().filter_map(|t| t.as_str()).collect();
    let has = |pattern: &[&str]| tokens.iter().any(|t| pattern.iter().all(|p| t.contains(p)));
    assert!(has(&["@ros2_lv/0/", "/0/0/NN/%/%/subsume"]), "{tokens:?}");
    for (kind, topic, ty) in [
        ("MS", "%cmd_vel", MessageType::Twist),
        ("MP", "%odom", MessageType::Odometry),
        ("MP", "%scan", MessageType::LaserScan),
        ("MP", "%rosout", MessageType::Log),
    ] {
        let tail = format!("/{kind}/%/%/subsume/{topic}/{}/{}/::,10:,:,:,,", ty.dds_name(), ty.rihs01());
        assert!(tokens.iter().any(|t| t.ends_with(&tail)), "{tail} in {tokens:?}");
    }
    // The cut-short Twists were counted and dropped; the rest went in.
    let cmd = section(&report, "/cmd_vel/");
    let garbage = summary["garbage"].as_u64().unwrap();
    let malformed = cmd["malformed"].as_u64().unwrap();
    assert!(malformed >= 1 && malformed <= garbage, "{cmd} for {garbage} sent");
    assert!(cmd["in"].as_u64().unwrap() > 20, "{cmd}");
    assert!(section(&report, "/odom/")["out"].as_u64().unwrap() > 20);
    assert!(section(&report, "/rosout/")["out"].as_u64().unwrap() > 0);
    // /cmd_vel held control (priority 2, over the planner's 1).
    let held = report["arbiter"]["held_s"].as_array().unwrap();
    assert!(held.iter().any(|h| h[0] == "cmd-vel" && h[1].as_f64().unwrap_or(0.0) > 1.0), "{}", report["arbiter"]);
}

/// The conventional e-stop topic (docs/estop.md): a `std_msgs/msg/Bool`
/// true on `/estop` engages the arbiter's `estop` lock. The Twists on
/// `/cmd_vel` keep coming, and nothing moves the robot again: a lock ends
/// only by an explicit release.
#[test]
fn a_bool_on_the_estop_topic_stops_the_robot_and_the_lock_holds() {
    let endpoint = format!("tcp/127.0.0.1:{}", free_port());
    let peer = Peer::spawn(&["robot-estop", &endpoint, "2.5"]);
    let (report, summary) = std::thread::scope(|s| {
        let host = s.spawn(|| run_host("config/ros2-demo.xml", &endpoint, Duration::from_secs(7)));
        std::thread::sleep(Duration::from_secs(6));
        let summary = peer.finish();
        (host.join().unwrap(), summary)
    });
    assert_eq!(summary["bad"], Json::Array(vec![]), "{summary}");
    let first = &summary["odom_first"];
    let at_estop = &summary["odom_at_estop"];
    let distance = |a: &Json, b: &Json| {
        (a[0].as_f64().unwrap() - b[0].as_f64().unwrap()).hypot(a[1].as_f64().unwrap() - b[1].as_f64().unwrap())
    };
    assert!(distance(first, at_estop) > 0.1, "the Twists drove the robot before the e-stop: {summary}");
    // From a second after the e-stop on, the robot stands still although
    // the Twists keep coming.
    let after = summary["odom_after_estop"].as_array().unwrap();
    assert!(after.len() >= 5, "{summary}");
    for odom in after {
        assert!(distance(&after[0], odom) < 0.005, "moved after the e-stop: {} -> {odom}", after[0]);
    }
    // The arbiter names the lock, who engaged it and how.
    let arbiter = &report["arbiter"];
    let engaged = arbiter["engaged"].as_array().unwrap();
    assert!(engaged.iter().any(|e| e.to_string().contains("estop")), "{arbiter}");
    assert!(section(&report, "/estop/")["in"].as_u64().unwrap() >= 1, "{report}");
}

/// The Twists the Python base received, as [lx, ly, lz, ax, ay, az].
fn twists_of(summary: &Json) -> Vec<Vec<f64>> {
    assert_eq!(summary["bad"], Json::Array(vec![]), "{summary}");
    summary["twists"]
        .as_array()
        .unwrap()
        .iter()
        .map(|t| t.as_array().unwrap().iter().map(|x| x.as_f64().unwrap()).collect())
        .collect()
}

#[test]
fn use_b_a_python_base_gets_cmd_vel_and_the_zero_twist_when_the_host_stops() {
    let endpoint = format!("tcp/127.0.0.1:{}", free_port());
    let peer = Peer::start("base", &endpoint);
    let report = run_host("config/ros2-base.xml", &endpoint, Duration::from_secs(6));
    // Let the last Twist arrive.
    std::thread::sleep(Duration::from_millis(500));
    let twists = twists_of(&peer.finish());
    assert!(twists.len() > 20, "{} twists", twists.len());
    // The planner drives toward its goal ahead: forward, decoded by rosbags.
    assert!(twists.iter().any(|t| t[0] > 0.05), "{twists:?}");
    // Only linear.x and angular.z are ever set.
    assert!(twists.iter().all(|t| t[1] == 0.0 && t[2] == 0.0 && t[3] == 0.0 && t[4] == 0.0));
    // The host stopped: the last Twist is the zero Twist.
    assert_eq!(twists.last().unwrap(), &vec![0.0; 6], "{:?}", &twists[twists.len().saturating_sub(3)..]);
    let scan = section(&report, "/scan/");
    assert!(scan["in"].as_u64().unwrap() > 20, "{scan}");
    assert_eq!(scan["malformed"], 0, "{scan}");
    // The base was still connected when the host stopped.
    assert_eq!(scan["peers"], 1, "{scan}");
}

/// A run of config/ros2-base.xml that ends by a panic
/// (`SUBSUME_FAULT_INJECTION=WHAT:SECONDS`) or a second SIGTERM; returns
/// its exit code and what it printed on stderr.
fn run_base_to_a_hard_exit(
    endpoint: &str,
    fault: Option<&str>,
    second_signal_after: Option<Duration>,
) -> (i32, String) {
    let mut command = subsume();
    command
        .args(["run", "config/ros2-base.xml"])
        .args(["--param", &format!("zenoh.connect={endpoint}")])
        .args(["--duration", "120"])
        .stdout(Stdio::null())
        .stderr(Stdio::piped());
    if let Some(fault) = fault {
        command.env("SUBSUME_FAULT_INJECTION", fault);
    }
    let mut child = command.spawn().unwrap();
    let mut stderr = child.stderr.take().unwrap();
    let log = std::thread::spawn(move || {
        let mut text = String::new();
        std::io::Read::read_to_string(&mut stderr, &mut text).unwrap();
        text
    });
    if let Some(after) = second_signal_after {
        std::thread::sleep(after);
        // The first asks for a clean stop; the loop is hung by the fault,
        // so only the second one ends the process.
        for _ in 0..2 {
            support::signal(child.id(), "TERM");
            std::thread::sleep(Duration::from_millis(300));
        }
    }
    let status = wait_for_exit(&mut child, Duration::from_secs(30));
    (status.code().unwrap_or(-1), log.join().unwrap())
}

/// The base's Twists: forward ones came, and the last one is the zero Twist.
fn assert_driven_then_zero(twists: &[Vec<f64>]) {
    assert!(twists.iter().any(|t| t[0] > 0.05), "no forward Twist: {twists:?}");
    assert_eq!(twists.last().unwrap(), &vec![0.0; 6], "{:?}", &twists[twists.len().saturating_sub(3)..]);
}

#[test]
fn use_b_the_zero_twist_goes_out_when_the_host_panics() {
    for fault in ["panic-control:5", "panic-thread:5"] {
        let endpoint = format!("tcp/127.0.0.1:{}", free_port());
        let peer = Peer::start("base", &endpoint);
        let (code, log) = run_base_to_a_hard_exit(&endpoint, Some(fault), None);
        std::thread::sleep(Duration::from_millis(500));
        let twists = twists_of(&peer.finish());
        assert_eq!(code, 101, "{fault}: {log}");
        assert!(log.contains("after the panic, ros2 publisher 'cmd-vel': STOP sent"), "{fault}: {log}");
        assert_driven_then_zero(&twists);
    }
}

#[test]
fn use_b_the_zero_twist_goes_out_on_a_second_signal_when_the_loop_is_stuck() {
    let endpoint = format!("tcp/127.0.0.1:{}", free_port());
    let peer = Peer::start("base", &endpoint);
    let (code, log) = run_base_to_a_hard_exit(&endpoint, Some("hang-control:5"), Some(Duration::from_secs(7)));
    std::thread::sleep(Duration::from_millis(500));
    let twists = twists_of(&peer.finish());
    assert_eq!(code, 130, "{log}");
    // The stall watchdog stopped the base first, within the stall limit of
    // the hang (issue 12: the Twist publisher is a motor stop), and the
    // second signal's final zero Twist still went out after it.
    assert!(log.contains("the control loop is stalled"), "{log}");
    assert!(log.contains("motors: 'cmd-vel': STOP sent"), "{log}");
    assert!(log.contains("second signal: ros2 publisher 'cmd-vel': STOP sent"), "{log}");
    assert_driven_then_zero(&twists);
}
