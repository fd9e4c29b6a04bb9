//! Recording and replay through the built binary: `subsume run --record`
//! read back by the `mcap` package from PyPI (tests/python/mcap_reader.py),
//! a killed host's file, rotation, and `subsume replay`.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::time::{Duration, Instant};

use serde_json::Value as Json;

use crate::support::{self, FREE_TELEOP_PORTS, component, http, http_bytes, read_report, robot_file, subsume, text};

fn run(args: &[&str]) -> Output {
    subsume().args(args).output().unwrap()
}

/// What the `mcap` package reads in `file`.
fn read_mcap(file: &Path, truncated: bool) -> Json {
    support::read_mcap(file, truncated, &[])
}

fn channel<'a>(read: &'a Json, topic: &str) -> &'a Json {
    let channel = &read["channels"][topic];
    assert!(channel.is_object(), "no channel {topic} in {}", read["channels"]);
    channel
}

#[test]
fn the_demo_recording_has_every_value_call_status_and_log_line() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("demo.mcap");
    let report_path = dir.path().join("report.json");
    let mut args = vec!["run", "config/demo.xml", "--duration", "3", "--record", file.to_str().unwrap()];
    args.extend(["--report", report_path.to_str().unwrap()]);
    args.extend(FREE_TELEOP_PORTS);
    let output = run(&args);
    let log = text(&output.stderr);
    assert!(output.status.success(), "{log}");
    let read = read_mcap(&file, false);
    assert_eq!(read["complete"], true);
    assert_eq!(read["in_order_per_channel"], true, "{}", read["out_of_order"]);
    // The summary a clean stop writes agrees with what was read.
    assert_eq!(read["summary"]["message_count"], read["messages"]);
    for (topic, entry) in read["channels"].as_object().unwrap() {
        assert_eq!(read["summary"]["channel_message_counts"][topic], entry["count"], "{topic}");
        assert_eq!(entry["schema_encoding"], "jsonschema", "{topic}");
        assert_eq!(entry["message_encoding"], "json", "{topic}");
        assert_eq!(entry["schema_is_json"], true, "{topic}");
    }
    // Foxglove's well-known schemas where they fit.
    assert_eq!(channel(&read, "/motors/pose")["schema"], "foxglove.PoseInFrame");
    assert_eq!(channel(&read, "/motors/pose/tf")["schema"], "foxglove.FrameTransform");
    assert_eq!(channel(&read, "/subsume/log")["schema"], "foxglove.Log");
    assert_eq!(channel(&read, "/arbiter/cmd")["schema"], "subsume.Value");
    // The simulated robot's ranges are a scan with its geometry (config/demo.xml:
    // 9 rays over fov 3.14159, max-range 4 m by default): Foxglove's LaserScan.
    assert_eq!(channel(&read, "/motors/ranges")["schema"], "foxglove.LaserScan");
    let scan = &read["first"]["/motors/ranges"];
    assert_eq!(scan["frame_id"], "motors");
    assert_eq!(scan["ranges"].as_array().unwrap().len(), 9, "{scan}");
    let close = |field: &str, want: f64| {
        let got = scan[field].as_f64().unwrap();
        assert!((got - want).abs() < 1e-9, "{field}: {got}, expected {want}: {scan}");
    };
    let fov: f64 = "3.14159".parse().unwrap(); // as written in config/demo.xml
    close("start_angle", -fov / 2.0);
    close("end_angle", fov / 2.0);
    close("angle_increment", fov / 8.0);
    close("range_min", 0.0);
    close("range_max", 4.0);
    // The filter (a vector input) received the same readings, as a vector.
    let filter_in = &read["first"]["/subsume/calls/filter"];
    assert_eq!(filter_in["value"]["vector"], scan["ranges"], "{filter_in}");
    let pose = &read["first"]["/motors/pose"];
    assert_eq!(pose["frame_id"], "world");
    assert!(pose["pose"]["orientation"]["w"].is_number(), "{pose}");
    assert_eq!(pose["value"].as_array().unwrap().len(), 3);
    // Every value every component emitted is there: the report's counts.
    let report: Json = read_report(&report_path);
    for name in ["motors", "filter", "avoid", "planner", "arbiter", "envelope"] {
        let recorded: u64 = read["channels"]
            .as_object()
            .unwrap()
            .iter()
            .filter(|(topic, _)| topic.starts_with(&format!("/{name}/")) && !topic.ends_with("/tf"))
            .map(|(_, entry)| entry["count"].as_u64().unwrap())
            .sum();
        assert_eq!(recorded, component(&report, name)["messages_out"].as_u64().unwrap(), "{name}");
        // Every call: ticks and inputs.
        let c = component(&report, name);
        let calls = channel(&read, &format!("/subsume/calls/{name}"))["count"].as_u64().unwrap();
        assert_eq!(calls, c["ticks"].as_u64().unwrap() + c["messages_in"].as_u64().unwrap(), "{name}: {c}");
    }
    // The arbiter's decisions and the network platform's state.
    let arbiter = &read["last"]["/subsume/status/arbiter"];
    assert_eq!(arbiter["kind"], "arbiter");
    assert!(arbiter["status"]["holder"].is_string() || arbiter["status"]["holder"].is_null(), "{arbiter}");
    assert!(read["channels"]["/subsume/status/teleop"].is_object());
    let input = &read["first"]["/subsume/calls/avoid"];
    assert!(input["call"] == "tick" || input["call"] == "input", "{input}");
    assert!(log.contains("recording finished:"), "{log}");
    assert!(log.contains("0 events dropped"), "{log}");
}

#[test]
fn a_0_1_0_and_a_0_2_0_component_run_side_by_side_on_the_simulated_robots_scan() {
    let dir = tempfile::tempdir().unwrap();
    let world = support::repo_root().join("config/worlds/demo.world");
    let body = r#"<robot name="scans">
  <platform name="control">
    <component name="robot-sim" source="builtin:sim">
      <param name="world" value="WORLD"/>
      <param name="rays" value="5"/>
      <param name="fov" value="2.0"/>
      <param name="max-range" value="3.5"/>
    </component>
    <component name="motors" source="builtin:serial" rate="50">
      <param name="device" value="sim:robot-sim"/>
    </component>
    <component name="new" source="GUEST(test-relay)" rate="0"/>
    <component name="old" source="GUEST(test-relay-v1)" rate="0"/>
    <connect from="motors.ranges" to="new.vector-in"/>
    <connect from="motors.ranges" to="new.scan-in"/>
    <connect from="motors.ranges" to="old.vector-in"/>
  </platform>
</robot>"#;
    let robot = robot_file(dir.path(), &body.replace("WORLD", world.to_str().unwrap()));
    let file = dir.path().join("scans.mcap");
    let report_path = dir.path().join("report.json");
    let output = run(&[
        "run",
        robot.to_str().unwrap(),
        "--duration",
        "1",
        "--record",
        file.to_str().unwrap(),
        "--report",
        report_path.to_str().unwrap(),
    ]);
    let log = text(&output.stderr);
    assert!(output.status.success(), "{log}");
    let read = read_mcap(&file, false);
    let scan = &read["first"]["/motors/ranges"];
    assert_eq!(channel(&read, "/motors/ranges")["schema"], "foxglove.LaserScan");
    assert_eq!(scan["ranges"].as_array().unwrap().len(), 5, "{scan}");
    assert_eq!(scan["start_angle"], -1.0);
    assert_eq!(scan["end_angle"], 1.0);
    assert_eq!(scan["angle_increment"], 0.5);
    assert_eq!(scan["range_max"], 3.5);
    // The 0.2.0 relay's scan input keeps the geometry; both versions' vector
    // inputs get the same readings.
    let relayed = &read["first"]["/new/scan-out"];
    assert_eq!(channel(&read, "/new/scan-out")["schema"], "foxglove.LaserScan");
    for field in ["ranges", "start_angle", "end_angle", "angle_increment", "range_min", "range_max"] {
        assert_eq!(relayed[field], scan[field], "{field}");
    }
    assert_eq!(read["first"]["/new/vector-out"]["value"]["vector"], scan["ranges"]);
    assert_eq!(read["first"]["/old/vector-out"]["value"]["vector"], scan["ranges"]);
    let report: Json = read_report(&report_path);
    let scans = component(&report, "motors")["messages_out"].as_u64().unwrap();
    assert!(scans > 0);
    for (relay, inputs) in [("new", 2), ("old", 1)] {
        let c = component(&report, relay);
        assert_eq!(c["state"], "running", "{c}");
        assert_eq!(c["errors"], 0, "{c}");
        assert!(c["messages_in"].as_u64().unwrap() >= inputs, "{c}");
    }
}

#[test]
fn faults_restarts_and_rotation_are_recorded_and_every_file_reads() {
    let dir = tempfile::tempdir().unwrap();
    // A busy counter fills a 1 MiB file within a few seconds.
    let robot = robot_file(
        dir.path(),
        r#"<robot name="busy">
  <platform name="control">
    <component name="bad" source="GUEST(test-faulty)" rate="50" budget="5ms" restart="on-failure" max-restarts="1">
      <param name="mode" value="trap-on-tick"/>
      <param name="after" value="5"/>
    </component>
    <component name="good" source="GUEST(test-counter)" rate="1000"/>
    <component name="sink" source="builtin:log" rate="0"/>
    <connect from="good.count" to="sink.in"/>
    <connect from="bad.out" to="sink.in"/>
  </platform>
</robot>"#,
    );
    let file = dir.path().join("busy.mcap");
    let output = run(&[
        "run",
        robot.to_str().unwrap(),
        "--duration",
        "8",
        "--record",
        file.to_str().unwrap(),
        "--record-max-mib",
        "1",
    ]);
    let log = text(&output.stderr);
    assert!(output.status.success(), "{log}");
    let second = dir.path().join("busy.1.mcap");
    assert!(second.is_file(), "no rotation: {log}");
    let first = read_mcap(&file, false);
    let next = read_mcap(&second, false);
    assert_eq!(first["complete"], true);
    assert!(std::fs::metadata(&file).unwrap().len() >= 1 << 20);
    assert!(
        std::fs::metadata(&file).unwrap().len() < (1 << 20) + (1 << 19),
        "a file overshoots its limit by a chunk at most"
    );
    // The counter's values continue across the files, none lost.
    let last = first["last"]["/good/count"]["value"]["scalar"].as_f64().unwrap();
    let resumed = next["first"]["/good/count"]["value"]["scalar"].as_f64().unwrap();
    assert_eq!(resumed, last + 1.0);
    let fault = &first["first"]["/subsume/events"];
    assert_eq!(fault["component"], "bad");
    assert_eq!(fault["event"], "fault");
    assert!(!fault["reason"].as_str().unwrap().is_empty(), "{fault}");
    // Brought back after 1 s: the restart is the next event.
    let events = [&first, &next].map(|r| r["channels"]["/subsume/events"]["count"].as_u64().unwrap_or(0));
    assert!(events.iter().sum::<u64>() >= 2, "{events:?}: {log}");
    assert!(log.contains("restarted (restart 1 of 1)"), "{log}");
}

#[test]
fn a_killed_host_leaves_a_file_whose_chunks_read() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("killed.mcap");
    let mut args = vec!["run", "config/demo.xml", "--record", file.to_str().unwrap()];
    args.extend(FREE_TELEOP_PORTS);
    let mut child = subsume().args(&args).stderr(std::process::Stdio::null()).spawn().unwrap();
    // Past a few flushes of finished chunks.
    let started = Instant::now();
    while std::fs::metadata(&file).map_or(0, |m| m.len()) < 300_000 {
        assert!(started.elapsed() < Duration::from_secs(60), "the recording does not grow");
        std::thread::sleep(Duration::from_millis(100));
    }
    child.kill().unwrap();
    child.wait().unwrap();
    let read = read_mcap(&file, true);
    assert_eq!(read["complete"], false, "a killed host writes no footer");
    assert!(read["messages"].as_u64().unwrap() > 500, "{}", read["messages"]);
    assert_eq!(read["in_order_per_channel"], true, "{}", read["out_of_order"]);
    for topic in ["/motors/pose", "/arbiter/cmd", "/subsume/calls/avoid", "/subsume/log"] {
        assert!(channel(&read, topic)["count"].as_u64().unwrap() > 0, "{topic}");
    }
    // Replay reads it too, up to the cut, and the components agree with it.
    let (code, report, log) = replay(&[file.to_str().unwrap(), "config/demo.xml"]);
    assert_eq!(code, Some(0), "{report} {log}");
    assert_eq!(report["truncated"], true);
    assert!(report["compared"].as_u64().unwrap() > 50, "{report}");
}

/// Records the demo for `seconds` into `dir`; returns the file.
fn record_demo(dir: &Path, seconds: &str) -> PathBuf {
    let file = dir.join("demo.mcap");
    let mut args = vec!["run", "config/demo.xml", "--duration", seconds, "--record", file.to_str().unwrap()];
    args.extend(FREE_TELEOP_PORTS);
    let output = run(&args);
    assert!(output.status.success(), "{}", text(&output.stderr));
    file
}

fn replay(args: &[&str]) -> (Option<i32>, Json, String) {
    let output = run(&[&["replay"], args, &["--json"]].concat());
    let json = serde_json::from_slice(&output.stdout).unwrap_or(Json::Null);
    (output.status.code(), json, text(&output.stderr))
}

#[test]
fn identical_components_replay_bit_for_bit_and_a_changed_one_is_caught_where_it_diverges() {
    let dir = tempfile::tempdir().unwrap();
    let file = record_demo(dir.path(), "3");
    let recording = file.to_str().unwrap();
    // Every WASM component of the demo, fed its recorded calls again.
    let (code, report, log) = replay(&[recording, "config/demo.xml"]);
    assert_eq!(code, Some(0), "{report} {log}");
    assert_eq!(report["components"], serde_json::json!(["filter", "avoid", "planner"]));
    assert!(report["compared"].as_u64().unwrap() > 100, "{report}");
    assert_eq!(report["divergences"], serde_json::json!([]));
    assert!(report["recorded_s"].as_f64().unwrap() > 2.5, "{report}");
    // The planner with another top speed: its first command differs.
    let (code, report, log) =
        replay(&[recording, "config/demo.xml", "--only", "planner", "--param", "planner.max-speed=0.3"]);
    assert_eq!(code, Some(1), "{report} {log}");
    assert_eq!(report["components"], serde_json::json!(["planner"]));
    let first = &report["divergences"][0];
    assert_eq!(first["component"], "planner");
    assert_eq!(first["port"], "cmd");
    // The planner's first tick with a pose: the call that emitted the
    // first command.
    assert_eq!(first["call_kind"], "tick", "{first}");
    let recorded = read_mcap(&file, false);
    let first_cmd = &recorded["first"]["/planner/cmd"];
    assert_eq!(first["recorded"], serde_json::json!([first_cmd["value"]]), "the recorded value is the recording's");
    assert_eq!(first["time_s"].as_f64().unwrap(), first_cmd["t"].as_u64().unwrap() as f64 / 1e9);
    let replayed = first["replayed"][0]["command"].as_str().unwrap();
    assert!(replayed.starts_with("VEL 0.300 "), "{first}");
    assert_ne!(first["recorded"], first["replayed"]);
    // The text form names time, port and both values.
    let output =
        run(&["replay", recording, "config/demo.xml", "--only", "planner", "--param", "planner.max-speed=0.3"]);
    let stdout = text(&output.stdout);
    assert!(stdout.contains("planner.cmd diverges at "), "{stdout}");
    assert!(stdout.contains(": tick): recorded {\"command\":\"VEL 0.450 "), "{stdout}");
}

#[test]
fn replay_refuses_built_ins_unknown_names_and_what_is_not_a_recording() {
    let dir = tempfile::tempdir().unwrap();
    let file = record_demo(dir.path(), "1");
    let recording = file.to_str().unwrap();
    let output = run(&["replay", recording, "config/demo.xml", "--only", "arbiter"]);
    assert_eq!(output.status.code(), Some(1));
    let err = text(&output.stderr);
    assert!(err.contains("config/demo.xml: 'arbiter' is arbiter: replay runs WASM components only"), "{err}");
    let output = run(&["replay", recording, "config/demo.xml", "--only", "nobody"]);
    assert!(text(&output.stderr).contains("config/demo.xml: no component 'nobody' in the robot file"));
    let junk = dir.path().join("junk.mcap");
    std::fs::write(&junk, b"not an mcap file at all").unwrap();
    let output = run(&["replay", junk.to_str().unwrap(), "config/demo.xml"]);
    assert_eq!(output.status.code(), Some(1));
    assert!(text(&output.stderr).contains("junk.mcap: not a recording replay can read"), "{}", text(&output.stderr));
}

#[test]
fn a_foxglove_websocket_client_subscribes_to_the_live_view_and_decodes_poses_and_scans() {
    let mut command = subsume();
    command.args(["run", "config/demo.xml", "--duration", "60", "--foxglove", "127.0.0.1:0"]).args(FREE_TELEOP_PORTS);
    let host = support::HostProcess::spawn(command);
    let url = format!("ws://{}", host.word_after("foxglove live view on ws://", Duration::from_secs(60)));
    let output = Command::new(support::python())
        .arg(support::repo_root().join("tests/python/foxglove_client.py"))
        .args([&url, "5", "/motors/pose", "/motors/pose/tf", "/motors/ranges", "/arbiter/cmd", "/subsume/log"])
        .output()
        .unwrap();
    drop(host);
    assert!(output.status.success(), "{}", text(&output.stderr));
    let seen: Json = serde_json::from_slice(&output.stdout).unwrap();
    assert_eq!(seen["server"], "subsume");
    assert_eq!(seen["channels"]["/motors/pose"]["schemaName"], "foxglove.PoseInFrame");
    assert_eq!(seen["channels"]["/motors/pose"]["encoding"], "json");
    assert_eq!(seen["channels"]["/motors/pose"]["schemaEncoding"], "jsonschema");
    assert_eq!(seen["channels"]["/motors/pose/tf"]["schemaName"], "foxglove.FrameTransform");
    assert_eq!(seen["times_in_order"], true);
    for pose in seen["messages"]["/motors/pose"].as_array().unwrap() {
        assert_eq!(pose["frame_id"], "world");
        let value = pose["value"].as_array().unwrap();
        assert_eq!(pose["pose"]["position"]["x"], value[0]);
        assert_eq!(pose["pose"]["position"]["y"], value[1]);
    }
    let tf = &seen["messages"]["/motors/pose/tf"][0];
    assert_eq!(tf["parent_frame_id"], "world");
    assert_eq!(tf["child_frame_id"], "base_link");
    assert!(seen["messages"]["/arbiter/cmd"][0]["value"]["command"].is_string(), "{seen}");
    // The simulated robot's scan, with its geometry (config/demo.xml: 9
    // rays over fov 3.14159, max-range 4 m), as Foxglove's LaserScan.
    assert_eq!(seen["channels"]["/motors/ranges"]["schemaName"], "foxglove.LaserScan");
    let fov: f64 = "3.14159".parse().unwrap();
    for scan in seen["messages"]["/motors/ranges"].as_array().unwrap() {
        assert_eq!(scan["frame_id"], "motors", "{scan}");
        let ranges = scan["ranges"].as_array().unwrap();
        assert_eq!(ranges.len(), 9, "{scan}");
        assert!(ranges.iter().all(|r| r.as_f64().is_some_and(|r| (0.0..=4.0).contains(&r))), "{scan}");
        for (field, want) in [("start_angle", -fov / 2.0), ("end_angle", fov / 2.0), ("range_max", 4.0)] {
            let got = scan[field].as_f64().unwrap();
            assert!((got - want).abs() < 1e-9, "{field}: {got}, expected {want}: {scan}");
        }
    }
}

fn http_json(address: &str, method: &str, path: &str, token: Option<&str>) -> (u16, Json) {
    http(address, method, path, token, b"")
}

#[test]
fn a_recording_started_and_stopped_from_the_portal_is_listed_downloaded_and_reads() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    const PASSWORD: &str = "recording-password-1";
    for (name, role) in [("admin", "admin"), ("viewer", "viewer"), ("operator", "operator")] {
        support::add_user(&store, name, role, &[], PASSWORD);
    }
    let mut command = subsume();
    command.args(["--store", store.to_str().unwrap(), "run", "config/demo.xml", "--http", "127.0.0.1:0"]);
    command.args(FREE_TELEOP_PORTS);
    let mut host = support::HostProcess::spawn(command);
    let address = host.portal_address();
    let login = |name: &str| support::login(&address, name, PASSWORD);
    let (admin, viewer, operator) = (login("admin"), login("viewer"), login("operator"));

    // Viewers and operators may not record; the refusals are audited.
    for token in [&viewer, &operator] {
        let (status, json) = http_json(&address, "POST", "/api/v1/recordings/start", Some(token));
        assert_eq!(status, 403, "{json}");
        assert!(json["error"].as_str().unwrap().contains("may not record"), "{json}");
        assert_eq!(http_json(&address, "GET", "/api/v1/recordings", Some(token)).0, 403);
    }
    let (status, json) = http_json(&address, "POST", "/api/v1/recordings/start", Some(&admin));
    assert_eq!(status, 201, "{json}");
    let name = json["recording"]["name"].as_str().unwrap().to_string();
    assert!(name.starts_with("rec-") && name.ends_with(".mcap"), "{name}");
    let (status, json) = http_json(&address, "POST", "/api/v1/recordings/start", Some(&admin));
    assert_eq!(status, 409, "{json}");
    assert!(json["error"].as_str().unwrap().contains(&name), "{json}");
    std::thread::sleep(Duration::from_secs(3));
    let (_, listed) = http_json(&address, "GET", "/api/v1/recordings", Some(&admin));
    assert_eq!(listed["recording"]["name"], name.as_str(), "{listed}");
    assert_eq!(listed["files"][0]["recording"], true, "{listed}");
    let (status, stopped) = http_json(&address, "POST", "/api/v1/recordings/stop", Some(&admin));
    assert_eq!(status, 200, "{stopped}");
    assert_eq!(stopped["stopped"]["files"], serde_json::json!([name]), "{stopped}");
    assert_eq!(stopped["stopped"]["dropped"], 0, "{stopped}");
    assert_eq!(http_json(&address, "POST", "/api/v1/recordings/stop", Some(&admin)).0, 409);

    // Listed, downloaded whole, and read by the mcap package.
    let (_, listed) = http_json(&address, "GET", "/api/v1/recordings", Some(&admin));
    assert!(listed["recording"].is_null(), "{listed}");
    let file = &listed["files"][0];
    assert_eq!((file["name"].as_str(), file["recording"].as_bool()), (Some(name.as_str()), Some(false)), "{listed}");
    let (status, bytes) = http_bytes(&address, "GET", &format!("/api/v1/recordings/{name}"), Some(&admin), b"");
    assert_eq!(status, 200);
    assert_eq!(bytes.len() as u64, file["bytes"].as_u64().unwrap());
    let downloaded = dir.path().join("downloaded.mcap");
    std::fs::write(&downloaded, &bytes).unwrap();
    let read = read_mcap(&downloaded, false);
    assert_eq!(read["complete"], true);
    assert_eq!(read["in_order_per_channel"], true, "{}", read["out_of_order"]);
    assert_eq!(read["messages"], stopped["stopped"]["messages"], "{read}");
    assert_eq!(read["summary"]["message_count"], read["messages"]);
    assert_eq!(channel(&read, "/motors/pose")["schema"], "foxglove.PoseInFrame");
    assert_eq!(channel(&read, "/subsume/log")["schema"], "foxglove.Log");
    assert!(read["last"]["/subsume/status/arbiter"]["status"].is_object(), "{}", read["last"]);
    // The serial link reports the pose about 20 times a second (the Live
    // tab shows motors 76 messages out/s over its four outputs): about 3 s.
    let poses = channel(&read, "/motors/pose")["count"].as_u64().unwrap();
    assert!((30..=200).contains(&poses), "{poses} poses in about 3 s");
    for topic in ["/arbiter/cmd", "/subsume/calls/avoid", "/filter/filtered"] {
        assert!(channel(&read, topic)["count"].as_u64().unwrap() > 0, "{topic}");
    }

    // Names are the host's: no paths, nothing outside the folder.
    for (path, expected) in [
        ("/api/v1/recordings/..%2Fstate.json", 400),
        ("/api/v1/recordings/state.json", 400),
        ("/api/v1/recordings/rec-1.mcap", 404),
    ] {
        let (status, json) = http_json(&address, "GET", path, Some(&admin));
        assert_eq!(status, expected, "{path}: {json}");
    }
    assert_eq!(http_bytes(&address, "GET", &format!("/api/v1/recordings/{name}"), Some(&viewer), b"").0, 403);

    // Audited: who started and stopped, and who was refused.
    let (_, audit) = http_json(&address, "GET", "/api/v1/audit", Some(&admin));
    let entries = audit["entries"].as_array().unwrap();
    let has = |action: &str, user: &str, result: &str| {
        entries.iter().any(|e| e["action"] == action && e["user"] == user && e["result"] == result)
    };
    assert!(has("start-recording", "admin", "ok") && has("stop-recording", "admin", "ok"), "{audit}");
    assert!(has("start-recording", "viewer", "refused") && has("start-recording", "operator", "refused"), "{audit}");

    // Deleted on request; a recording running when the host stops is
    // finished cleanly (summary and footer).
    let (status, json) = http_json(&address, "DELETE", &format!("/api/v1/recordings/{name}"), Some(&admin));
    assert_eq!(status, 200, "{json}");
    let (status, json) = http_json(&address, "POST", "/api/v1/recordings/start", Some(&admin));
    assert_eq!(status, 201, "{json}");
    let second = json["recording"]["name"].as_str().unwrap().to_string();
    std::thread::sleep(Duration::from_secs(1));
    let (_, listed) = http_json(&address, "GET", "/api/v1/recordings", Some(&admin));
    assert_eq!(listed["files"].as_array().unwrap().len(), 1, "{listed}");
    support::signal(host.child.id(), "TERM");
    support::wait_for_exit(&mut host.child, Duration::from_secs(30));
    let read = read_mcap(&store.join("recordings").join(&second), false);
    assert_eq!(read["complete"], true, "{}", host.log());
    assert!(read["messages"].as_u64().unwrap() > 100, "{read}");
    // (Waits for the log's last lines: the host has exited, its log is read on.)
    host.word_after(&format!("recording {second} stopped with the run"), Duration::from_secs(10));
}
