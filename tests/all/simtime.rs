//! Simulated time, end to end: the built `subsume` binary runs the demo on
//! a simulated clock (`--speed N`, `--speed max`), faster than real time and
//! with the same result for the same inputs.

use std::path::Path;
use std::time::{Duration, Instant};

use serde_json::Value as Json;

use crate::support::{FREE_TELEOP_PORTS, read_report, subsume};

/// Runs the demo on simulated time; returns the report and the wall time.
fn run_demo(dir: &Path, label: &str, speed: &str, seconds: &str) -> (Json, Duration) {
    run_robot(dir, "config/demo.xml", label, speed, seconds)
}

fn run_robot(dir: &Path, robot: &str, label: &str, speed: &str, seconds: &str) -> (Json, Duration) {
    let report = dir.join(format!("{label}.json"));
    let started = Instant::now();
    let output = subsume()
        .args(["run", robot, "--speed", speed, "--duration", seconds])
        .args(["--report", report.to_str().unwrap()])
        .args(FREE_TELEOP_PORTS)
        .output()
        .unwrap();
    let wall = started.elapsed();
    let log = String::from_utf8_lossy(&output.stderr);
    assert!(output.status.success(), "{log}");
    assert!(log.contains("simulated time:"), "{log}");
    assert!(!log.contains("no longer deterministic"), "a lock-step wait ran out:\n{log}");
    (read_report(&report), wall)
}

/// What must not differ between two runs with the same inputs: the
/// simulated robot's state (pose, distance, collisions, goal, ranges), the
/// link's counters and the graph's message counts, as bytes.
fn outcome(report: &Json) -> String {
    let mut sim = report["sim"].clone();
    sim.as_object_mut().unwrap().remove("pty");
    let mut serial = report["serial"].clone();
    serial.as_object_mut().unwrap().remove("device");
    serde_json::to_string(&(sim, serial, &report["messages"], &report["cycles"], &report["duration_s"])).unwrap()
}

#[test]
fn two_lockstep_runs_of_the_demo_give_byte_identical_outcomes_faster_than_real_time() {
    let dir = tempfile::tempdir().unwrap();
    let (first, wall) = run_demo(dir.path(), "first", "max", "60");
    let (second, _) = run_demo(dir.path(), "second", "max", "60");
    assert_eq!(outcome(&first), outcome(&second));
    // The demo does what it does in real time: it reaches its goal unharmed.
    assert_eq!(first["sim"]["goal_reached"], true, "{}", first["sim"]);
    assert_eq!(first["sim"]["collisions"], 0);
    assert_eq!(first["duration_s"], 60.0);
    // Measured: 60 simulated seconds take about 1 s here; half real time is a
    // bound no loaded machine comes near.
    assert!(wall < Duration::from_secs(30), "60 simulated seconds took {wall:?}");
}

#[test]
fn speed_n_paces_simulated_time_and_gives_the_lockstep_result() {
    let dir = tempfile::tempdir().unwrap();
    let (paced, wall) = run_demo(dir.path(), "paced", "4", "4");
    let (free, _) = run_demo(dir.path(), "free", "max", "4");
    // 4 simulated seconds at 4x real time cannot take less than 1 s.
    assert!(wall >= Duration::from_secs(1), "{wall:?}");
    assert_eq!(outcome(&paced), outcome(&free));
}

#[test]
fn the_demo_as_a_create2_is_repeatable_in_lockstep_too() {
    // The Create 2 translator polls its sensor stream: polls are frames the
    // lock-step waits for like commands.
    let dir = tempfile::tempdir().unwrap();
    let (first, _) = run_robot(dir.path(), "config/demo-create2.xml", "first", "max", "30");
    let (second, _) = run_robot(dir.path(), "config/demo-create2.xml", "second", "max", "30");
    assert_eq!(outcome(&first), outcome(&second));
    assert!(first["sim"]["distance_travelled_m"].as_f64().unwrap() > 1.0, "{}", first["sim"]);
}

/// A run on simulated time that the machine keeps stopping (here `SIGSTOP`
/// and `SIGCONT`, as a preflight at idle priority is preempted by the
/// robot's work) has the outcome of one that ran straight: no call of a
/// component busy for most of its budget is faulted for the wall time it
/// spent stopped (on simulated time a call has no wall-clock cap).
#[test]
fn a_run_on_simulated_time_stopped_and_continued_gives_the_outcome_of_one_that_ran_straight() {
    let dir = tempfile::tempdir().unwrap();
    let faulty = crate::support::guest("test-faulty");
    let robot = dir.path().join("busy.xml");
    std::fs::write(
        &robot,
        format!(
            r#"<robot name="busy">
  <platform name="control">
    <component name="busy" source="{}" rate="100" budget="20ms" memory="16MiB">
      <param name="mode" value="busy-on-tick"/>
      <param name="spins" value="2000000"/>
    </component>
  </platform>
</robot>
"#,
            faulty.display()
        ),
    )
    .unwrap();
    let run = |label: &str, stop_and_continue: bool| {
        let report = dir.path().join(format!("{label}.json"));
        let mut child = subsume()
            .args(["run", robot.to_str().unwrap(), "--http", "off", "--speed", "max", "--duration", "30"])
            .args(["--report", report.to_str().unwrap()])
            .stderr(std::process::Stdio::piped())
            .spawn()
            .unwrap();
        let pid = child.id().to_string();
        let mut stops = 0;
        while stop_and_continue && child.try_wait().unwrap().is_none() {
            // Each stop is many times the 200 ms wall-clock cap a 20 ms
            // budget has in real time.
            let _ = std::process::Command::new("kill").args(["-STOP", &pid]).status();
            std::thread::sleep(Duration::from_millis(400));
            let _ = std::process::Command::new("kill").args(["-CONT", &pid]).status();
            stops += 1;
            std::thread::sleep(Duration::from_millis(100));
        }
        let output = child.wait_with_output().unwrap();
        let log = String::from_utf8_lossy(&output.stderr).into_owned();
        assert!(output.status.success(), "{log}");
        (read_report(&report), stops, log)
    };
    let (straight, _, _) = run("straight", false);
    let (stopped, stops, log) = run("stopped", true);
    assert!(stops >= 5, "the run was stopped only {stops} times: too short to mean anything\n{log}");
    let component =
        |report: &Json| report["components"].as_array().unwrap().iter().find(|c| c["name"] == "busy").cloned().unwrap();
    assert_eq!(component(&stopped)["faults"], 0, "{:#}\n{log}", component(&stopped));
    assert_eq!(component(&stopped)["state"], "running");
    assert_eq!((&stopped["messages"], &stopped["cycles"]), (&straight["messages"], &straight["cycles"]),);
}

#[test]
fn a_bad_speed_is_refused_and_nothing_runs() {
    for bad in ["0", "fast", "1e9"] {
        let output = subsume().args(["run", "config/demo.xml", "--speed", bad, "--duration", "1"]).output().unwrap();
        let stderr = String::from_utf8_lossy(&output.stderr);
        assert!(!output.status.success());
        assert!(
            stderr.contains(&format!(
                "error: invalid value '{bad}' for '--speed <N|max>': --speed must be a number of times real time (more than 0, at most 10000) or 'max', got '{bad}'"
            )),
            "{stderr}"
        );
        assert!(!stderr.contains("simulated robot on"), "{stderr}");
    }
}

/// Every message of the recording at `path`, as (topic, nanoseconds from
/// the first message, data), with the wall-clock `timestamp`s taken out of
/// JSON data (two runs start at different wall-clock times), the
/// pseudo-terminal's name out of the status (the system's choice), and a serial
/// link's `frames_written` and `bytes_written` out of its status: its
/// writer thread counts them beside the loop, and the status is read
/// between cycles without waiting for it, so a snapshot may count a frame
/// a cycle early (seen with seeded tick phases; every message, call, pose,
/// range and log line is identical).
fn recorded_messages(path: &Path) -> Vec<(String, u64, String)> {
    fn without_timestamps(value: &mut Json) {
        match value {
            Json::Object(map) => {
                map.remove("timestamp");
                map.values_mut().for_each(without_timestamps);
            }
            Json::Array(items) => items.iter_mut().for_each(without_timestamps),
            _ => {}
        }
    }
    let bytes = std::fs::read(path).unwrap();
    let messages: Vec<_> = mcap::MessageStream::new(&bytes).unwrap().map(Result::unwrap).collect();
    let first = messages.iter().map(|m| m.log_time).min().unwrap_or(0);
    messages
        .into_iter()
        .map(|m| {
            let data = match serde_json::from_slice::<Json>(&m.data) {
                Ok(mut json) => {
                    without_timestamps(&mut json);
                    let serial = json["kind"] == "serial";
                    if let Some(status) = json["status"].as_object_mut() {
                        // The pseudo-terminal each run gets is the system's choice.
                        status.remove("pty");
                        status.remove("device");
                        if serial {
                            status.remove("frames_written");
                            status.remove("bytes_written");
                        }
                    }
                    json.to_string()
                }
                Err(_) => format!("{:?}", m.data),
            };
            (m.channel.topic.clone(), m.log_time - first, data)
        })
        .collect()
}

/// A seeded run (`--perturb SEED`, docs/lab.md "Timing"): the same seed
/// and bounds give the same recording, message for message, and a
/// different seed (or none) a different one: the lab's set that drives
/// straight at a wall, stopped by the envelope just short of its stop zone
/// on the lock-step's timing, enters it on a robot's. The bounds are the
/// lab's defaults, given as the kit gives them.
#[test]
fn a_seeded_run_is_its_seed_bit_for_bit_and_another_seed_changes_it() {
    let dir = tempfile::tempdir().unwrap();
    let robot = dir.path().join("straight.xml");
    std::fs::write(&robot, crate::lab::without_network(&crate::lab::straight_at_the_wall())).unwrap();
    std::fs::write(dir.path().join("lab.world"), crate::lab::WORLD).unwrap();
    let bounds = dir.path().join("perturb-bounds.json");
    std::fs::write(
        &bounds,
        r#"{"tick_phase": true, "sensor_latency_ms": 30, "range_noise_m": 0.02, "serial_delay_ms": 16}"#,
    )
    .unwrap();
    let phase_only = dir.path().join("phase-only.json");
    std::fs::write(
        &phase_only,
        r#"{"tick_phase": true, "sensor_latency_ms": 0, "range_noise_m": 0, "serial_delay_ms": 0}"#,
    )
    .unwrap();
    let run_within = |label: &str, seed: Option<u64>, bounds: &Path| {
        let (recording, verdict) = (dir.path().join(format!("{label}.mcap")), dir.path().join(format!("{label}.json")));
        let mut command = subsume();
        command
            .args(["run", robot.to_str().unwrap(), "--http", "off", "--speed", "max", "--duration", "30"])
            .arg("--record")
            .arg(&recording)
            .arg("--verdict")
            .arg(&verdict);
        if let Some(seed) = seed {
            command.args(["--perturb", &seed.to_string()]).arg("--perturb-bounds").arg(bounds);
        }
        let output = command.output().unwrap();
        let log = String::from_utf8_lossy(&output.stderr);
        assert!(output.status.success(), "{log}");
        assert!(!log.contains("no longer deterministic"), "a lock-step wait ran out:\n{log}");
        let verdict: Json = serde_json::from_slice(&std::fs::read(&verdict).unwrap()).unwrap();
        (recorded_messages(&recording), verdict)
    };
    let run = |label: &str, seed: Option<u64>| run_within(label, seed, &bounds);
    let (first, first_verdict) = run("first", Some(712));
    let (again, again_verdict) = run("again", Some(712));
    assert!(first.len() > 1000, "{} messages", first.len());
    assert_eq!(first.len(), again.len());
    if let Some(at) = first.iter().zip(&again).position(|(a, b)| a != b) {
        panic!("the same seed gave another run from message {at}: {:?} against {:?}", first[at], again[at]);
    }
    assert_eq!(first_verdict, again_verdict);
    // Another seed, and the lock-step's own timing, are other runs: this
    // set passes on the lock-step's timing and not on a robot's.
    let (other, other_verdict) = run("other", Some(713));
    let (plain, plain_verdict) = run("plain", None);
    // Not only in the log line naming the seed: in what the robot did.
    let run_of = |messages: &[(String, u64, String)]| {
        messages.iter().filter(|(topic, _, _)| topic != "/subsume/log").cloned().collect::<Vec<_>>()
    };
    assert!(run_of(&first) != run_of(&other), "seeds 712 and 713 gave the same run");
    assert!(run_of(&first) != run_of(&plain), "seed 712 gave the lock-step's own run");
    // The tick phase alone moves the components' ticks off the grid.
    let (phase, _) = run_within("phase", Some(712), &phase_only);
    let first_ticks = |messages: &[(String, u64, String)]| {
        messages
            .iter()
            .filter(|(topic, _, data)| topic.starts_with("/subsume/calls/") && data.contains("\"tick\""))
            .take(8)
            .map(|(topic, at, _)| (topic.clone(), *at))
            .collect::<Vec<_>>()
    };
    assert!(first_ticks(&phase) != first_ticks(&plain), "{:?}", first_ticks(&phase));
    assert_eq!(plain_verdict["passed"], true, "{plain_verdict:#}");
    for verdict in [&first_verdict, &other_verdict] {
        assert_eq!(verdict["passed"], false, "{verdict:#}");
        assert!(
            verdict["reasons"][0]
                .as_str()
                .unwrap()
                .starts_with("preflight: the envelope's stop zone stopped the robot")
        );
    }
}

/// `--perturb` seeds a simulated run alone; bounds out of range are
/// refused naming the field; nothing runs.
#[test]
fn a_seeded_run_needs_simulated_time_and_bounds_in_range() {
    let dir = tempfile::tempdir().unwrap();
    let bounds = dir.path().join("bounds.json");
    std::fs::write(
        &bounds,
        r#"{"tick_phase": true, "sensor_latency_ms": 5000, "range_noise_m": 0, "serial_delay_ms": 0}"#,
    )
    .unwrap();
    let cases: [(&[&str], &str); 3] = [
        (&["--http", "off", "--perturb", "1"], "--perturb seeds a simulated run: it needs --speed and --http off"),
        (
            &["--http", "off", "--speed", "max", "--perturb", "1", "--perturb-bounds", bounds.to_str().unwrap()],
            "sensor_latency_ms must be from 0 to 1000, got 5000",
        ),
        (&["--http", "off", "--speed", "max", "--perturb-bounds", bounds.to_str().unwrap()], "--perturb"),
    ];
    for (args, said) in cases {
        let output = subsume()
            .args(["run", "config/demo.xml", "--duration", "1"])
            .args(args)
            .args(FREE_TELEOP_PORTS)
            .output()
            .unwrap();
        let stderr = String::from_utf8_lossy(&output.stderr);
        assert!(!output.status.success() && stderr.contains(said), "{args:?}: {stderr}");
        assert!(!stderr.contains("simulated robot on"), "{args:?} started: {stderr}");
    }
}
