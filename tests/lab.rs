#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic)]
//! The remote lab end to end (docs/lab.md): the real binary with its portal,
//! over real HTTP. Three researchers submit six experiments at once; one is
//! refused by its preflight (a collision, named with its time), one is
//! cancelled while queued, one while running, one is aborted by an
//! emergency stop and two are done. Every state change is checked in
//! order, every bundle is read by the `mcap` package from PyPI and its
//! recording replays identical with `subsume replay`, and the baseline runs
//! between experiments and after the last. A host killed with SIGKILL
//! during an experiment starts again on the baseline, the experiment
//! aborted with what it recorded, and the queue goes on.

#[path = "../host/tests/support/mod.rs"]
mod support;

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

use serde_json::Value as Json;
use support::{HostProcess, http};

const PASSWORD: &str = "lab-test-password";
const RESEARCHERS: [&str; 3] = ["ana", "ben", "cy"];

/// The baseline: the demo's behaviours in an open arena, the envelope
/// without a geofence; the planner drives to a goal in a straight line.
const BASELINE: &str = r#"<robot name="lab">
  <platform name="control">
    <component name="robot-sim" source="builtin:sim">
      <param name="world" value="lab.world"/>
      <param name="rays" value="9"/>
      <param name="fov" value="3.14159"/>
    </component>
    <component name="motors" source="builtin:serial" rate="100">
      <param name="device" value="sim:robot-sim"/>
      <param name="min-interval" value="0.02"/>
      <param name="watchdog" value="0.3"/>
    </component>
    <component name="filter" source="GUEST(range-filter)" rate="0" budget="5ms" memory="16MiB"/>
    <component name="avoid" source="GUEST(avoider)" rate="20" budget="5ms" memory="16MiB" timeout="400ms"/>
    <component name="planner" source="GUEST(planner)" rate="10" budget="5ms" memory="16MiB" timeout="400ms">
      <param name="goal-x" value="GOAL_X"/>
      <param name="goal-y" value="1.0"/>
    </component>
    <component name="arbiter" source="builtin:arbiter" rate="20"/>
    <component name="envelope" source="builtin:envelope" rate="20">
      <param name="fov" value="3.14159"/>
    </component>
    EXTRA
    <connect from="motors.ranges" to="filter.ranges"/>
    <connect from="filter.filtered" to="avoid.ranges"/>
    <connect from="motors.pose" to="planner.pose"/>
    <connect from="avoid.cmd" to="arbiter.commands"/>
    <connect from="planner.cmd" to="arbiter.commands"/>
    <connect from="arbiter.cmd" to="envelope.cmd"/>
    <connect from="motors.ranges" to="envelope.ranges"/>
    <connect from="motors.pose" to="envelope.pose"/>
    <connect from="envelope.cmd" to="motors.cmd"/>
  </platform>
  <platform name="network">
    <component name="teleop" source="builtin:teleop" rate="50" timeout="300ms">
      <param name="listen" value="127.0.0.1:0"/>
    </component>
    <connect from="teleop.cmd" to="arbiter.commands"/>
  </platform>
</robot>
"#;

/// A source that reverses blindly (the rays look ahead) into the wall
/// behind the start: a collision the preflight must catch.
const REVERSE: &str = r#"<component name="reverse" source="builtin:publish" rate="10" priority="2">
      <param name="kind" value="command"/>
      <param name="value" value="VEL -0.1 0"/>
    </component>
    <connect from="reverse.out" to="arbiter.commands"/>"#;

const WORLD: &str = "bounds 0 0 10 8\nstart 1 1 0\ngoal 8 1 0.3\ncircle 8 6 0.4\n";

fn robot(goal_x: f64, extra: &str) -> String {
    let mut xml = BASELINE.replace("GOAL_X", &goal_x.to_string()).replace("EXTRA", extra);
    for name in ["avoider", "planner", "range-filter"] {
        xml = xml.replace(&format!("GUEST({name})"), &support::guest(name).display().to_string());
    }
    xml
}

struct Lab {
    host: HostProcess,
    address: String,
}

/// `subsume run` of the baseline in `dir` with its portal on a free port,
/// on the store in `dir/store`.
fn start(dir: &Path) -> Lab {
    support::guest_dir();
    let mut command = support::subsume();
    command
        .arg("--store")
        .arg(dir.join("store"))
        .arg("run")
        .arg(dir.join("robot.xml"))
        .args(["--http", "127.0.0.1:0"])
        .env_remove("SUBSUME_HTTP");
    let host = HostProcess::spawn(command);
    let address = host.word_after("portal on http://", Duration::from_secs(120)).trim_end_matches('/').to_string();
    Lab { host, address }
}

fn setup(dir: &Path) {
    std::fs::write(dir.join("robot.xml"), robot(8.0, "")).unwrap();
    std::fs::write(dir.join("lab.world"), WORLD).unwrap();
    let store = dir.join("store");
    support::add_user(&store, "boss", "admin", &[], PASSWORD);
    for name in RESEARCHERS {
        support::add_user(&store, name, "researcher", &["control"], PASSWORD);
    }
}

impl Lab {
    fn token(&self, user: &str) -> String {
        support::login(&self.address, user, PASSWORD)
    }

    fn call(&self, token: &str, method: &str, path: &str, body: &str) -> (u16, Json) {
        http(&self.address, method, path, Some(token), body.as_bytes())
    }

    /// Stages `xml` as `user`'s robot file: the set's id.
    fn stage(&self, token: &str, file: &str, xml: &str) -> u64 {
        let (status, json) = self.call(token, "PUT", &format!("/api/v1/platforms/control/configs/{file}"), xml);
        assert_eq!(status, 201, "{json}");
        json["set"]["id"].as_u64().unwrap()
    }

    fn experiment(&self, token: &str, id: u64) -> Json {
        let (status, json) = self.call(token, "GET", &format!("/api/v1/experiments/{id}"), "");
        assert_eq!(status, 200, "{json}");
        json["experiment"].clone()
    }

    /// Waits until experiment `id` is in `state` (or any final state when
    /// `state` is final), up to `timeout`; returns it.
    fn wait_for(&self, token: &str, id: u64, state: &str, timeout: Duration) -> Json {
        let deadline = Instant::now() + timeout;
        loop {
            let experiment = self.experiment(token, id);
            if experiment["state"] == state {
                return experiment;
            }
            assert!(
                Instant::now() < deadline,
                "experiment {id} never reached {state}: {experiment:#}\n{}",
                self.host.log()
            );
            std::thread::sleep(Duration::from_millis(50));
        }
    }

    fn active_set(&self, token: &str) -> u64 {
        let (status, json) = self.call(token, "GET", "/api/v1/status", "");
        assert_eq!(status, 200, "{json}");
        json["set"].as_u64().unwrap()
    }

    /// Downloads experiment `id`'s results and unpacks them into `into`:
    /// the bundle's folder.
    fn results(&self, token: &str, id: u64, into: &Path) -> PathBuf {
        let archive = into.join(format!("experiment-{id}.tar"));
        let status = Command::new("curl")
            .args(["-s", "-f", "-o"])
            .arg(&archive)
            .args(["-H", &format!("Authorization: Bearer {token}")])
            .arg(format!("http://{}/api/v1/experiments/{id}/results", self.address))
            .status()
            .unwrap();
        assert!(status.success(), "downloading experiment {id}'s results failed");
        // Python's tarfile: an archive reader no one here wrote.
        let unpacked = Command::new(support::python())
            .args(["-c", "import sys, tarfile; tarfile.open(sys.argv[1]).extractall(sys.argv[2], filter='data')"])
            .arg(&archive)
            .arg(into)
            .output()
            .unwrap();
        assert!(unpacked.status.success(), "{}", String::from_utf8_lossy(&unpacked.stderr));
        let folder = into.join(format!("experiment-{id}"));
        let sums = Command::new("sha256sum").arg("-c").arg("--quiet").arg("SHA256SUMS").current_dir(&folder).output();
        let sums = sums.unwrap();
        assert!(sums.status.success(), "{}", String::from_utf8_lossy(&sums.stdout));
        folder
    }
}

/// The states an experiment went through, in order.
fn states(experiment: &Json) -> Vec<String> {
    experiment["history"].as_array().unwrap().iter().map(|c| c["state"].as_str().unwrap().to_string()).collect()
}

/// When experiment `e` entered `state` (ms), if it did.
fn entered(experiment: &Json, state: &str) -> Option<u64> {
    experiment["history"]
        .as_array()
        .unwrap()
        .iter()
        .rev()
        .find(|c| c["state"] == state)
        .map(|c| c["at_ms"].as_u64().unwrap())
}

/// What the `mcap` package reads in `file`.
fn read_mcap(file: &Path, truncated: bool) -> Json {
    let mut command = Command::new(support::python());
    command.arg(support::repo_root().join("tests/python/mcap_reader.py")).arg(file);
    if truncated {
        command.arg("--truncated");
    }
    let output = command.output().unwrap();
    assert!(
        output.status.success(),
        "mcap reader failed on {}: {}",
        file.display(),
        String::from_utf8_lossy(&output.stderr)
    );
    serde_json::from_slice(&output.stdout).unwrap()
}

/// `subsume replay` of the bundle's run against its own robot file.
fn replays_identical(bundle: &Path) {
    let output =
        support::subsume().arg("replay").arg(bundle.join("run.mcap")).arg(bundle.join("robot.xml")).output().unwrap();
    let stdout = String::from_utf8_lossy(&output.stdout);
    assert!(
        output.status.success() && stdout.contains("identical"),
        "replay of {}: {stdout}\n{}",
        bundle.display(),
        String::from_utf8_lossy(&output.stderr)
    );
}

#[test]
fn six_experiments_of_three_researchers_end_as_they_should_and_the_baseline_runs_between() {
    let dir = tempfile::tempdir().unwrap();
    setup(dir.path());
    let lab = start(dir.path());
    let tokens: Vec<String> = RESEARCHERS.iter().map(|r| lab.token(r)).collect();
    let boss = lab.token("boss");
    let baseline = lab.active_set(&boss);
    // Each researcher stages two robot files: ana's first reverses into a
    // wall; the others drive the planner to goals of their own.
    let mut plans = Vec::new();
    for (r, token) in tokens.iter().enumerate() {
        for n in 0..2 {
            let extra = if r == 0 && n == 0 { REVERSE } else { "" };
            let duration = if extra.is_empty() { 3.0 } else { 12.0 };
            let set = lab.stage(token, &format!("{}-{n}.xml", RESEARCHERS[r]), &robot(6.0 + n as f64, extra));
            plans.push((r, set, duration, !extra.is_empty()));
        }
    }
    // All six at once.
    let submitted: Vec<(usize, u64, bool)> = std::thread::scope(|scope| {
        let handles: Vec<_> = plans
            .iter()
            .map(|&(r, set, duration, collides)| {
                let (lab, token) = (&lab, &tokens[r]);
                scope.spawn(move || {
                    let body = serde_json::json!({ "set": set, "duration_s": duration, "label": format!("set {set}") });
                    let (status, json) = lab.call(token, "POST", "/api/v1/experiments", &body.to_string());
                    assert_eq!(status, 201, "{json}");
                    (r, json["experiment"]["id"].as_u64().unwrap(), collides)
                })
            })
            .collect();
        handles.into_iter().map(|h| h.join().unwrap()).collect()
    });
    let token_of = |id: u64| &tokens[submitted.iter().find(|(_, e, _)| *e == id).unwrap().0];
    // A researcher sees only their own experiments; someone else's is as
    // if it did not exist.
    let (_, mine) = lab.call(&tokens[1], "GET", "/api/v1/experiments", "");
    let listed: Vec<u64> = mine["experiments"].as_array().unwrap().iter().map(|e| e["id"].as_u64().unwrap()).collect();
    let bens: Vec<u64> = submitted.iter().filter(|(r, _, _)| *r == 1).map(|(_, e, _)| *e).collect();
    assert_eq!(listed.len(), 2, "{mine}");
    assert!(listed.iter().all(|id| bens.contains(id)), "{mine}");
    let anas = submitted.iter().find(|(r, _, _)| *r == 0).unwrap().1;
    let (status, theirs) = lab.call(&tokens[1], "GET", &format!("/api/v1/experiments/{anas}"), "");
    let (missing_status, missing) = lab.call(&tokens[1], "GET", "/api/v1/experiments/9999", "");
    assert_eq!(
        (status, &theirs["error"]),
        (missing_status, &Json::String(format!("no experiment {anas}"))),
        "{theirs} {missing}"
    );

    // The collision is refused in preflight, naming when and where.
    let collider = submitted.iter().find(|(_, _, c)| *c).unwrap().1;
    let refused = lab.wait_for(&tokens[0], collider, "refused", Duration::from_secs(120));
    assert_eq!(states(&refused), ["checking", "preflight", "refused"], "{refused:#}");
    let reason = refused["reasons"][0].as_str().unwrap();
    assert!(
        reason.starts_with("preflight: collision at ")
            && reason.contains(" s at (")
            && reason.contains("while 'reverse' held control"),
        "{reason}"
    );

    // The other five in queue order (first in, first out: by id).
    let mut queue: Vec<u64> = submitted.iter().filter(|(_, _, c)| !*c).map(|(_, e, _)| *e).collect();
    queue.sort_unstable();
    let (first, to_cancel_running, to_abort, last, to_cancel_queued) =
        (queue[0], queue[1], queue[2], queue[3], queue[4]);
    // Cancelled while queued (it passes its preflight first, or is
    // cancelled before it: either way it never runs).
    lab.wait_for(token_of(to_cancel_queued), to_cancel_queued, "queued", Duration::from_secs(120));
    let (status, json) =
        lab.call(token_of(to_cancel_queued), "POST", &format!("/api/v1/experiments/{to_cancel_queued}/cancel"), "");
    assert_eq!((status, json["experiment"]["state"].as_str()), (200, Some("cancelled")), "{json}");

    let done_first = lab.wait_for(token_of(first), first, "done", Duration::from_secs(120));
    // Cancelled while running: the answer comes once the baseline is back.
    lab.wait_for(token_of(to_cancel_running), to_cancel_running, "running", Duration::from_secs(60));
    let (status, json) =
        lab.call(token_of(to_cancel_running), "POST", &format!("/api/v1/experiments/{to_cancel_running}/cancel"), "");
    assert_eq!((status, json["experiment"]["state"].as_str()), (200, Some("cancelled")), "{json}");
    // Aborted by an emergency stop (any user may press it); the lock stays
    // engaged, the baseline comes back under it, and the queue waits for
    // the release.
    lab.wait_for(token_of(to_abort), to_abort, "running", Duration::from_secs(60));
    let (status, json) = lab.call(&tokens[2], "POST", "/api/v1/estop", "");
    assert_eq!(status, 200, "{json}");
    let aborted = lab.wait_for(token_of(to_abort), to_abort, "aborted", Duration::from_secs(30));
    assert!(aborted["reasons"][0].as_str().unwrap().starts_with("aborted: emergency stop by cy"), "{aborted:#}");
    assert_eq!(lab.active_set(&boss), baseline, "the baseline runs under the lock");
    std::thread::sleep(Duration::from_millis(500));
    assert_eq!(lab.experiment(token_of(last), last)["state"], "queued", "the queue waits while a lock is engaged");
    let (status, json) = lab.call(&boss, "POST", "/api/v1/release", "");
    assert_eq!(status, 200, "{json}");
    let done_last = lab.wait_for(token_of(last), last, "done", Duration::from_secs(60));

    // Every state, in order.
    let passed = ["checking", "preflight", "queued"];
    let ran = |end: &'static str| [&passed[..], &["running", "finishing", end]].concat();
    assert_eq!(states(&done_first), ran("done"), "{done_first:#}");
    assert_eq!(states(&done_last), ran("done"), "{done_last:#}");
    let cancelled_running = lab.experiment(token_of(to_cancel_running), to_cancel_running);
    assert_eq!(states(&cancelled_running), ran("cancelled"), "{cancelled_running:#}");
    assert_eq!(states(&aborted), ran("aborted"), "{aborted:#}");
    let cancelled_queued = lab.experiment(token_of(to_cancel_queued), to_cancel_queued);
    assert_eq!(states(&cancelled_queued), [&passed[..], &["cancelled"]].concat(), "{cancelled_queued:#}");
    // One at a time, first in, first out.
    let ran_ones = [&done_first, &cancelled_running, &aborted, &done_last];
    for pair in ran_ones.windows(2) {
        let (before, after) = (pair[0], pair[1]);
        assert!(
            entered(before, "done").or(entered(before, "cancelled")).or(entered(before, "aborted")).unwrap()
                <= entered(after, "running").unwrap()
        );
    }
    assert_eq!(lab.active_set(&boss), baseline, "the baseline runs after the last");
    // The baseline came back after each run: the audit log says so.
    let (_, audit) = lab.call(&boss, "GET", "/api/v1/audit", "");
    let ends: Vec<&Json> =
        audit["entries"].as_array().unwrap().iter().filter(|e| e["action"] == "experiment-end").collect();
    assert_eq!(ends.len(), 4, "{audit:#}");
    assert!(
        ends.iter().all(|e| e["result"] == "ok"
            && e["detail"].as_str().unwrap().contains(&format!("the baseline (set {baseline}) runs"))),
        "{ends:#?}"
    );

    // Each bundle reads with the `mcap` package and replays identical.
    let out = dir.path().join("results");
    std::fs::create_dir_all(&out).unwrap();
    for experiment in ran_ones {
        let id = experiment["id"].as_u64().unwrap();
        let bundle = lab.results(token_of(id), id, &out);
        let read = read_mcap(&bundle.join("run.mcap"), false);
        assert!(read["complete"].as_bool().unwrap() && read["in_order_per_channel"].as_bool().unwrap(), "{read:#}");
        if experiment["state"] == "done" {
            assert!(read["channels"]["/planner/cmd"]["count"].as_u64().is_some_and(|n| n > 10), "{read:#}");
        }
        replays_identical(&bundle);
        let record: Json = serde_json::from_slice(&std::fs::read(bundle.join("experiment.json")).unwrap()).unwrap();
        assert_eq!(record["id"], id);
        assert!(bundle.join("report.json").is_file() && bundle.join("log.txt").is_file());
        let preflight = read_mcap(&bundle.join("preflight.mcap"), false);
        assert!(preflight["complete"].as_bool().unwrap(), "{preflight:#}");
    }
    // The refused one's bundle has its preflight, which shows the collision.
    let bundle = lab.results(&tokens[0], collider, &out);
    let verdict: Json = serde_json::from_slice(&std::fs::read(bundle.join("preflight-verdict.json")).unwrap()).unwrap();
    assert!(verdict["observed"]["collisions"].as_u64().unwrap() >= 1, "{verdict:#}");
    assert!(read_mcap(&bundle.join("preflight.mcap"), false)["complete"].as_bool().unwrap());
}

#[test]
fn a_host_killed_during_an_experiment_starts_again_on_the_baseline_and_the_queue_goes_on() {
    let dir = tempfile::tempdir().unwrap();
    setup(dir.path());
    let mut lab = start(dir.path());
    let ana = lab.token("ana");
    let boss = lab.token("boss");
    let baseline = lab.active_set(&boss);
    let set = lab.stage(&ana, "ana.xml", &robot(7.0, ""));
    let submit = |lab: &Lab, duration: f64| {
        let body = serde_json::json!({ "set": set, "duration_s": duration }).to_string();
        let (status, json) = lab.call(&ana, "POST", "/api/v1/experiments", &body);
        assert_eq!(status, 201, "{json}");
        json["experiment"]["id"].as_u64().unwrap()
    };
    let long = submit(&lab, 60.0);
    let next = submit(&lab, 3.0);
    lab.wait_for(&ana, long, "running", Duration::from_secs(120));
    lab.wait_for(&ana, next, "queued", Duration::from_secs(120));
    // Paused, the queue starts nothing after the restart until it resumes:
    // what runs then is what the host started on.
    let (status, json) = lab.call(&boss, "POST", "/api/v1/lab/pause", "");
    assert_eq!((status, &json["paused"]), (200, &Json::Bool(true)), "{json}");
    // Let it record a while (chunks reach the file every 500 ms).
    std::thread::sleep(Duration::from_secs(2));
    assert_ne!(lab.active_set(&boss), baseline, "the experiment's set runs");
    lab.host.child.kill().unwrap();
    lab.host.child.wait().unwrap();

    lab = start(dir.path());
    let (ana, boss) = (lab.token("ana"), lab.token("boss"));
    assert_eq!(
        lab.active_set(&boss),
        baseline,
        "the host starts again on the baseline: {}\n{}",
        std::fs::read_to_string(dir.path().join("store/audit.log")).unwrap_or_default(),
        lab.host.log()
    );
    let aborted = lab.experiment(&ana, long);
    assert_eq!(aborted["state"], "aborted", "{aborted:#}");
    assert!(aborted["reasons"].as_array().unwrap().iter().any(|r| r == "aborted: host stopped"), "{aborted:#}");
    // What it recorded until the kill is in its bundle.
    let out = dir.path().join("results");
    std::fs::create_dir_all(&out).unwrap();
    let bundle = lab.results(&ana, long, &out);
    let read = read_mcap(&bundle.join("run.mcap"), true);
    assert!(read["messages"].as_u64().unwrap() > 100, "{read:#}");
    // The queue goes on.
    assert_eq!(lab.experiment(&ana, next)["state"], "queued");
    let (status, json) = lab.call(&boss, "POST", "/api/v1/lab/resume", "");
    assert_eq!((status, &json["paused"]), (200, &Json::Bool(false)), "{json}");
    let done = lab.wait_for(&ana, next, "done", Duration::from_secs(120));
    assert_eq!(done["reasons"].as_array().map(Vec::len), Some(0), "{done:#}");
    assert_eq!(lab.active_set(&boss), baseline);
}
