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

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

use crate::support::{HostProcess, http};
use serde_json::Value as Json;

pub(crate) const PASSWORD: &str = "lab-test-password";
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

pub(crate) const WORLD: &str = "bounds 0 0 10 8\nstart 1 1 0\ngoal 8 1 0.3\ncircle 8 6 0.4\n";

/// The lab's robot file without its simulator: its serial link drives
/// `device` (a pseudo-terminal the test plays the controller on).
fn real_robot(goal_x: f64, device: &str) -> String {
    robot(goal_x, "")
        .replace(
            r#"<component name="robot-sim" source="builtin:sim">
      <param name="world" value="lab.world"/>
      <param name="rays" value="9"/>
      <param name="fov" value="3.14159"/>
    </component>"#,
            "",
        )
        .replace("sim:robot-sim", device)
}

/// A motor controller played on the robot's pseudo-terminal by a thread:
/// every 50 ms it sends odometry, range readings and the lines `feedback`
/// makes of the value the test set last, until stopped.
struct PlayedController<T> {
    value: std::sync::Arc<std::sync::Mutex<T>>,
    going: std::sync::Arc<std::sync::atomic::AtomicBool>,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl<T: Send + 'static> PlayedController<T> {
    fn start(mut motors: crate::support::MotorRecorder, first: T, feedback: fn(&T) -> String) -> Self {
        use std::sync::atomic::Ordering;
        let value = std::sync::Arc::new(std::sync::Mutex::new(first));
        let going = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(true));
        let thread = {
            let (value, going) = (value.clone(), going.clone());
            std::thread::spawn(move || {
                let mut sent = Instant::now();
                while going.load(Ordering::Relaxed) {
                    motors.read();
                    if sent.elapsed() >= Duration::from_millis(50) {
                        let more = feedback(&value.lock().unwrap());
                        let lines = format!("O 1000 1000 0\nR 3000 3000 3000 3000 3000 3000 3000 3000 3000\n{more}");
                        motors.write(lines.as_bytes());
                        sent = Instant::now();
                    }
                }
            })
        };
        PlayedController { value, going, thread: Some(thread) }
    }

    /// What the controller says from its next feedback on.
    fn set(&self, value: T) {
        *self.value.lock().unwrap() = value;
    }

    /// Stops the controller, failing if its thread did.
    fn stop(mut self) {
        self.going.store(false, std::sync::atomic::Ordering::Relaxed);
        if let Some(thread) = self.thread.take() {
            thread.join().unwrap();
        }
    }
}

impl<T> Drop for PlayedController<T> {
    fn drop(&mut self) {
        self.going.store(false, std::sync::atomic::Ordering::Relaxed);
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
    }
}

/// A lab on robot file `xml` (a played controller's) in `dir`, with boss
/// (admin) and ana (researcher), the arena as its preflight world and manual
/// resets: the lab, ana's and boss's tokens, and the owner's settings as
/// they are, to change and put.
fn lab_on_a_played_robot(dir: &Path, xml: &str) -> (Lab, String, String, Json) {
    std::fs::write(dir.join("robot.xml"), xml).unwrap();
    let store = dir.join("store");
    crate::support::add_user(&store, "boss", "admin", &[], PASSWORD);
    crate::support::add_user(&store, "ana", "researcher", &["control"], PASSWORD);
    let lab = start(dir);
    let (ana, boss) = (lab.token("ana"), lab.token("boss"));
    let (status, json) = lab.call(&boss, "PUT", "/api/v1/worlds/arena.world", WORLD);
    assert_eq!(status, 201, "{json}");
    let (_, overview) = lab.call(&boss, "GET", "/api/v1/lab", "");
    let mut settings = overview["lab"]["settings"].clone();
    settings["preflight_world"] = Json::String("arena.world".into());
    settings["reset"] = Json::String("manual".into());
    (lab, ana, boss, settings)
}

pub(crate) fn robot(goal_x: f64, extra: &str) -> String {
    robot_of(BASELINE, goal_x, extra)
}

fn robot_of(baseline: &str, goal_x: f64, extra: &str) -> String {
    let mut xml = baseline.replace("GOAL_X", &goal_x.to_string()).replace("EXTRA", extra);
    for name in ["avoider", "planner", "range-filter"] {
        xml = xml.replace(&format!("GUEST({name})"), &crate::support::guest(name).display().to_string());
    }
    xml
}

/// A source that drives straight ahead at 0.4 m/s, above the planner.
const STRAIGHT: &str = r#"<component name="drive" source="builtin:publish" rate="10" priority="2">
      <param name="kind" value="command"/>
      <param name="value" value="VEL 0.4 0"/>
    </component>
    <connect from="drive.out" to="arbiter.commands"/>"#;

/// The baseline without its avoider, driven straight at the wall ahead
/// (docs/lab.md, "Timing"): the envelope slows it down and, with the
/// lock-step's perfect timing, stops it just short of its stop zone; with a
/// robot's sensor latency and serial delay it enters the stop zone (as a
/// 30 s run of it in real time did). Its network platform is the baseline's.
pub(crate) fn straight_at_the_wall() -> String {
    let without_avoider = BASELINE
        .replace(
            r#"    <component name="avoid" source="GUEST(avoider)" rate="20" budget="5ms" memory="16MiB" timeout="400ms"/>
"#,
            "",
        )
        .replace("    <connect from=\"filter.filtered\" to=\"avoid.ranges\"/>\n", "")
        .replace("    <connect from=\"avoid.cmd\" to=\"arbiter.commands\"/>\n", "");
    assert!(!without_avoider.contains("avoid"), "{without_avoider}");
    robot_of(&without_avoider, 8.0, STRAIGHT)
}

/// `xml` without its network platform (its teleoperation needs the
/// portal's users or an operators file): to run alone with `--http off`.
pub(crate) fn without_network(xml: &str) -> String {
    let start = xml.find("  <platform name=\"network\">").unwrap();
    let end = start + xml[start..].find("</platform>\n").unwrap() + "</platform>\n".len();
    format!("{}{}", &xml[..start], &xml[end..])
}

pub(crate) struct Lab {
    pub(crate) host: HostProcess,
    pub(crate) address: String,
}

/// `subsume run` of the baseline in `dir` with its portal on a free port,
/// on the store in `dir/store`. Its preflights run at `normal` priority:
/// at the default (`idle`), or at `background`, the tests running beside
/// this one starve them (the priorities are `lab::preflight`'s unit test).
pub(crate) fn start(dir: &Path) -> Lab {
    crate::support::guest_dir();
    let mut command = crate::support::subsume();
    command
        .arg("--store")
        .arg(dir.join("store"))
        .arg("run")
        .arg(dir.join("robot.xml"))
        .args(["--http", "127.0.0.1:0", "--preflight-priority", "normal"])
        .env_remove("SUBSUME_HTTP");
    let host = HostProcess::spawn(command);
    let address = host.word_after("portal on http://", Duration::from_secs(120)).trim_end_matches('/').to_string();
    Lab { host, address }
}

pub(crate) fn setup(dir: &Path) {
    std::fs::write(dir.join("robot.xml"), robot(8.0, "")).unwrap();
    std::fs::write(dir.join("lab.world"), WORLD).unwrap();
    let store = dir.join("store");
    crate::support::add_user(&store, "boss", "admin", &[], PASSWORD);
    for name in RESEARCHERS {
        crate::support::add_user(&store, name, "researcher", &["control"], PASSWORD);
    }
}

impl Lab {
    /// tests/browser/leaderboard.mjs: `owner`'s experiment `id`, scored,
    /// on her card and first on the task's board; `other` sees a pseudonym.
    fn board_in_chromium(&self, owner: &str, other: &str, id: u64) {
        let artifacts = crate::support::repo_root().join("target/browser-artifacts");
        let url = format!("http://{}/", self.address);
        let shown = crate::support::browser(
            "leaderboard.mjs",
            &artifacts,
            &[],
            &[&url, &owner, &other, &PASSWORD, &id.to_string()],
        );
        assert!(shown.contains(&format!("ok: experiment {id} ranked 1")), "{shown}");
    }

    pub(crate) fn token(&self, user: &str) -> String {
        crate::support::login(&self.address, user, PASSWORD)
    }

    pub(crate) fn call(&self, token: &str, method: &str, path: &str, body: &str) -> (u16, Json) {
        http(&self.address, method, path, Some(token), body.as_bytes())
    }

    /// Stages `xml` as `user`'s robot file for the control platform: the
    /// set's id.
    pub(crate) fn stage(&self, token: &str, file: &str, xml: &str) -> u64 {
        self.stage_for(token, "control", file, xml)
    }

    fn stage_for(&self, token: &str, platform: &str, file: &str, xml: &str) -> u64 {
        let (status, json) = self.call(token, "PUT", &format!("/api/v1/platforms/{platform}/configs/{file}"), xml);
        assert_eq!(status, 201, "{json}");
        json["set"]["id"].as_u64().unwrap()
    }

    pub(crate) fn experiment(&self, token: &str, id: u64) -> Json {
        let (status, json) = self.call(token, "GET", &format!("/api/v1/experiments/{id}"), "");
        assert_eq!(status, 200, "{json}");
        json["experiment"].clone()
    }

    /// Submits set `set` for `duration_s` as `token`'s user: its id.
    fn submit(&self, token: &str, set: u64, duration_s: f64) -> u64 {
        let body = serde_json::json!({ "set": set, "duration_s": duration_s }).to_string();
        let (status, json) = self.call(token, "POST", "/api/v1/experiments", &body);
        assert_eq!(status, 201, "{json}");
        json["experiment"]["id"].as_u64().unwrap()
    }

    /// Waits (up to 120 s) until experiment `id` waits for the manual reset,
    /// then says the robot is back as admin `admin`.
    fn reset_when_awaited(&self, token: &str, admin: &str, id: u64) {
        let deadline = Instant::now() + Duration::from_secs(120);
        while self.experiment(token, id)["awaiting_reset"] != true {
            assert!(Instant::now() < deadline, "experiment {id} never waited for the reset\n{}", self.host.log());
            std::thread::sleep(Duration::from_millis(50));
        }
        let (status, json) = self.call(admin, "POST", "/api/v1/lab/reset", "");
        assert_eq!(status, 200, "{json}");
    }

    /// Submits set `set` for `duration_s` as `token`'s user and waits (up
    /// to 240 s) until it is done: its id and record.
    fn run_to_done(&self, token: &str, set: u64, duration_s: f64) -> (u64, Json) {
        let id = self.submit(token, set, duration_s);
        let done = self.wait_for(token, id, "done", Duration::from_secs(240));
        assert_eq!(done["state"], "done", "{done:#}");
        (id, done)
    }

    /// Waits until experiment `id` is in `state` or has passed it, up to
    /// `timeout`; returns it.
    fn wait_for(&self, token: &str, id: u64, state: &str, timeout: Duration) -> Json {
        let deadline = Instant::now() + timeout;
        loop {
            let experiment = self.experiment(token, id);
            // Reached: in it now, or past it (a short state may come and go
            // between two polls on a busy machine; the history keeps it).
            let passed = experiment["history"].as_array().is_some_and(|h| h.iter().any(|c| c["state"] == state));
            if experiment["state"] == state || passed {
                return experiment;
            }
            assert!(
                Instant::now() < deadline,
                "experiment {id} never reached {state}: {experiment:#}\n{}\n{}",
                self.host.log(),
                self.host.children()
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
        download_results(&self.address, token, id, into)
    }
}

/// Downloads experiment `id`'s results from the portal at `address` and
/// unpacks them into `into` (Python's tarfile), every file checked by
/// `sha256sum -c`: the bundle's folder.
pub(crate) fn download_results(address: &str, token: &str, id: u64, into: &Path) -> PathBuf {
    let archive = into.join(format!("experiment-{id}.tar"));
    let status = Command::new("curl")
        .args(["-s", "-f", "-o"])
        .arg(&archive)
        .args(["-H", &format!("Authorization: Bearer {token}")])
        .arg(format!("http://{}/api/v1/experiments/{id}/results", address))
        .status()
        .unwrap();
    assert!(status.success(), "downloading experiment {id}'s results failed");
    // Python's tarfile: an archive reader no one here wrote.
    let unpacked = Command::new(crate::support::python())
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

/// Downloads the lab kit as `token` and unpacks it into `out` (GNU tar):
/// its folder, `out/lab-kit`.
fn fetch_kit(lab: &Lab, token: &str, out: &Path) -> PathBuf {
    let kit = out.join("kit.tar");
    let fetched = Command::new("curl")
        .args(["-s", "-f", "-o"])
        .arg(&kit)
        .args(["-H", &format!("Authorization: Bearer {token}")])
        .arg(format!("http://{}/api/v1/lab/kit", lab.address))
        .status()
        .unwrap();
    assert!(fetched.success());
    let unpacked = Command::new("tar").arg("-xf").arg(&kit).arg("-C").arg(out).status().unwrap();
    assert!(unpacked.success());
    out.join("lab-kit")
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
pub(crate) fn read_mcap(file: &Path, truncated: bool) -> Json {
    let mut command = Command::new(crate::support::python());
    command.arg(crate::support::repo_root().join("tests/python/mcap_reader.py")).arg(file);
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
    let output = crate::support::subsume()
        .arg("replay")
        .arg(bundle.join("run.mcap"))
        .arg(bundle.join("robot.xml"))
        .output()
        .unwrap();
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
            // Long enough that a busy machine still sees each run (one is
            // cancelled and one stopped while running).
            let duration = if extra.is_empty() { 10.0 } else { 12.0 };
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

/// `subsume run` for the refusal cases: the baseline, a researcher of each
/// platform, a developer and an admin.
fn start_with_users(dir: &Path) -> Lab {
    setup(dir);
    let store = dir.join("store");
    crate::support::add_user(&store, "nora", "researcher", &["network"], PASSWORD);
    crate::support::add_user(&store, "dev", "developer", &["control"], PASSWORD);
    start(dir)
}

/// Uploads `guest` as `user`'s component `name`.
fn upload(lab: &Lab, token: &str, name: &str, guest: &str) {
    let bytes = std::fs::read(crate::support::guest(guest)).unwrap();
    let (status, json) =
        http(&lab.address, "PUT", &format!("/api/v1/platforms/control/components/{name}"), Some(token), &bytes);
    assert_eq!(status, 201, "{json}");
}

/// A component that misbehaves in the preflight: test-faulty in `mode`
/// after a few good ticks, unconnected.
fn faulty(mode: &str) -> String {
    format!(
        r#"<component name="bad" source="faulty.wasm" rate="10" budget="5ms" memory="16MiB">
      <param name="mode" value="{mode}"/>
      <param name="after" value="5"/>
    </component>"#
    )
}

/// Each bad submission is refused with the status and words it should
/// have, at once or by its preflight, and nothing runs.
#[test]
fn bad_submissions_are_refused_with_their_reason() {
    let dir = tempfile::tempdir().unwrap();
    let lab = start_with_users(dir.path());
    let ana = lab.token("ana");
    let nora = lab.token("nora");
    let good = lab.stage(&ana, "good.xml", &robot(7.0, ""));
    // Nora's set changes the network platform, which ana does not hold.
    let network = lab.stage_for(&nora, "network", "net.xml", &robot(8.0, "").replace("rate=\"50\"", "rate=\"40\""));
    // A set whose world file goes away after it was staged.
    std::fs::write(dir.path().join("gone.world"), WORLD).unwrap();
    let gone = lab.stage(&ana, "gone.xml", &robot(7.0, "").replace("lab.world", "gone.world"));
    std::fs::remove_file(dir.path().join("gone.world")).unwrap();
    upload(&lab, &ana, "faulty", "test-faulty");
    let mut faults = Vec::new();
    for (mode, words) in [
        ("loop-on-tick", "exceeded its cpu-time budget"),
        ("trap-on-tick", "trapped"),
        ("sleep-on-tick", "blocking calls are not allowed"),
    ] {
        let set = lab.stage(&ana, &format!("{mode}.xml"), &robot(7.0, &faulty(mode)));
        faults.push((mode, set, words));
    }
    let body = |set: u64, duration: f64| serde_json::json!({ "set": set, "duration_s": duration }).to_string();
    // (case, body, status, words of the error)
    let hers_alone = format!("no set {network}");
    let at_once: Vec<(&str, String, u16, &str)> = vec![
        ("over the max duration", body(good, 121.0), 400, "max-duration of 120 s"),
        ("no duration", body(good, 0.0), 400, "duration_s must be from 1"),
        ("not json", "{set: 1".into(), 400, "expected {\"set\": ID"),
        ("an unknown field", r#"{"set": 1, "duration_s": 5, "robot": "x"}"#.into(), 400, "unknown field"),
        (
            "a label too long",
            serde_json::json!({"set": good, "duration_s": 5, "label": "x".repeat(200)}).to_string(),
            400,
            "at most 120 characters",
        ),
        ("no such set", body(9999, 5.0), 404, "no set 9999"),
        // Nora's set is hers: to ana it is no set at all (store::access).
        ("another researcher's set", body(network, 5.0), 404, &hers_alone),
        ("a set that no longer validates", body(gone, 5.0), 422, "problem(s) in the set's robot file"),
    ];
    for (case, body, status, words) in &at_once {
        let (got, json) = lab.call(&ana, "POST", "/api/v1/experiments", body);
        assert_eq!(got, *status, "{case}: {json}");
        assert!(json["error"].as_str().unwrap().contains(words), "{case}: {json}");
        if *status == 422 {
            let diagnostic = json["diagnostics"][0]["text"].as_str().unwrap();
            assert!(diagnostic.starts_with("gone.xml:") && diagnostic.contains("gone.world"), "{case}: {json}");
        }
    }
    let (_, listed) = lab.call(&ana, "GET", "/api/v1/experiments", "");
    assert_eq!(listed["experiments"].as_array().unwrap().len(), 0, "a refused submission leaves nothing: {listed}");
    // Guests that loop, trap or sleep are refused by their preflight,
    // naming the fault.
    for (mode, set, words) in faults {
        let (status, json) = lab.call(&ana, "POST", "/api/v1/experiments", &body(set, 5.0));
        assert_eq!(status, 201, "{mode}: {json}");
        let id = json["experiment"]["id"].as_u64().unwrap();
        let refused = lab.wait_for(&ana, id, "refused", Duration::from_secs(120));
        let reasons = refused["reasons"].to_string();
        assert!(reasons.contains("component 'bad' faulted at") && reasons.contains(words), "{mode}: {refused:#}");
        assert!(entered(&refused, "running").is_none(), "{mode}: {refused:#}");
    }
}

/// While an experiment runs, a developer's activation is refused naming
/// it; an admin's ends it first, says so, and pauses the queue.
#[test]
fn nobody_else_changes_what_runs_during_an_experiment_but_an_admin_who_ends_it() {
    let dir = tempfile::tempdir().unwrap();
    let lab = start_with_users(dir.path());
    let (ana, dev, boss) = (lab.token("ana"), lab.token("dev"), lab.token("boss"));
    let baseline = lab.active_set(&boss);
    let set = lab.stage(&ana, "ana.xml", &robot(7.0, ""));
    let other = lab.stage(&dev, "dev.xml", &robot(6.5, ""));
    let (status, json) =
        lab.call(&ana, "POST", "/api/v1/experiments", &serde_json::json!({"set": set, "duration_s": 60}).to_string());
    assert_eq!(status, 201, "{json}");
    let id = json["experiment"]["id"].as_u64().unwrap();
    lab.wait_for(&ana, id, "running", Duration::from_secs(120));
    for (what, path) in
        [("activate", format!("/api/v1/sets/{other}/activate")), ("roll back", "/api/v1/rollback".into())]
    {
        let (status, json) = lab.call(&dev, "POST", &path, "");
        let error = json["error"].as_str().unwrap_or_default();
        assert_eq!(status, 409, "{what}: {json}");
        assert!(
            error.starts_with(&format!("experiment {id} by ana runs until ")) && error.contains(" s from now"),
            "{what}: {json}"
        );
    }
    let (status, json) = lab.call(&ana, "POST", &format!("/api/v1/sets/{other}/activate"), "");
    assert_eq!(status, 403, "a researcher never activates: {json}");
    assert_eq!(lab.experiment(&ana, id)["state"], "running");
    // An admin's activation that is refused changes nothing: the
    // experiment runs on and the queue is not paused.
    for (what, path, expected, words) in [
        ("the baseline", format!("/api/v1/sets/{baseline}/activate"), 409, "is what runs after experiment"),
        ("no such set", "/api/v1/sets/9999/activate".to_string(), 404, "no set 9999"),
    ] {
        let (status, json) = lab.call(&boss, "POST", &path, "");
        assert_eq!(status, expected, "{what}: {json}");
        assert!(json["error"].as_str().unwrap_or_default().contains(words), "{what}: {json}");
        assert_eq!(lab.experiment(&ana, id)["state"], "running", "{what}");
        let (_, overview) = lab.call(&boss, "GET", "/api/v1/lab", "");
        assert_eq!(overview["lab"]["paused"], false, "{what}: {overview}");
    }
    let (status, json) = lab.call(&boss, "POST", &format!("/api/v1/sets/{other}/activate"), "");
    assert_eq!(status, 200, "{json}");
    let note = json["note"].as_str().unwrap();
    assert_eq!(note, format!("it cancelled experiment {id} (by ana) first; the queue is paused"), "{json}");
    let cancelled = lab.experiment(&ana, id);
    assert_eq!(cancelled["state"], "cancelled", "{cancelled:#}");
    assert!(
        cancelled["reasons"][0]
            .as_str()
            .unwrap()
            .starts_with(&format!("cancelled: admin boss is about to activate set {other}"))
    );
    assert_eq!(lab.active_set(&boss), other);
    let (_, overview) = lab.call(&boss, "GET", "/api/v1/lab", "");
    assert_eq!(overview["lab"]["paused"], true, "{overview}");
    assert_eq!(overview["lab"]["baseline"].as_u64(), Some(baseline));
}

/// Four users submit 20 experiments each at once, many times: the limits
/// hold exactly (experiments waiting, then robot-minutes), and no
/// experiment is lost or duplicated.
#[test]
fn concurrent_submissions_never_pass_the_limits_nor_lose_an_experiment() {
    let dir = tempfile::tempdir().unwrap();
    let lab = start_with_users(dir.path());
    let store = dir.path().join("store");
    let users = ["ana", "ben", "cy", "dev"];
    let tokens: Vec<String> = users.iter().map(|u| lab.token(u)).collect();
    let boss = lab.token("boss");
    let sets: Vec<u64> =
        tokens.iter().enumerate().map(|(i, t)| lab.stage(t, &format!("s{i}.xml"), &robot(7.0, ""))).collect();
    // Paused, nothing starts: an experiment waits until it is cancelled.
    let (status, _) = lab.call(&boss, "POST", "/api/v1/lab/pause", "");
    assert_eq!(status, 200);
    let settings = |max_queued: u32, minutes: f64| {
        serde_json::json!({
            "max_duration_s": 120.0,
            "limits": {"max_queued": max_queued, "robot_minutes_per_day": minutes, "max_reservation_s": 1800, "reservation_per_day_s": 3600},
            "criteria": {"max_collisions": 0, "allow_faults": false, "allow_geofence": false, "allow_stop_zone": false},
            "reset": "sim", "preflight_world": null, "reference_recording": null, "retention_bytes": 10737418240_u64, "kit": true
        })
        .to_string()
    };
    let mut seen = std::collections::BTreeSet::new();
    // (max queued, robot minutes a day, each experiment's seconds, accepted per user)
    let rounds = [(3, 30.0, 5.0, 3), (100, 1.0, 10.0, 6), (2, 30.0, 5.0, 2), (100, 0.5, 10.0, 3)];
    for (round, (max_queued, minutes, duration, expected)) in rounds.iter().enumerate() {
        let (status, json) = lab.call(&boss, "PUT", "/api/v1/lab/settings", &settings(*max_queued, *minutes));
        assert_eq!(status, 200, "{json}");
        let outcomes: Vec<Vec<(u16, Json)>> = std::thread::scope(|scope| {
            let handles: Vec<_> = (0..users.len())
                .map(|u| {
                    let (lab, token, set) = (&lab, &tokens[u], sets[u]);
                    // Each user from an address of their own: one address's
                    // connections are bounded (admission).
                    let from: std::net::IpAddr = format!("127.0.0.{}", 10 + u).parse().unwrap();
                    scope.spawn(move || {
                        let inner: Vec<_> = (0..20)
                            .map(|_| {
                                scope.spawn(move || {
                                    let body = serde_json::json!({ "set": set, "duration_s": duration }).to_string();
                                    let to = lab.address.parse().unwrap();
                                    let stream = crate::support::flood::connect_from(from, to).unwrap();
                                    let path = "/api/v1/experiments";
                                    crate::support::http_on(
                                        stream,
                                        &lab.address,
                                        "POST",
                                        path,
                                        Some(token),
                                        body.as_bytes(),
                                    )
                                })
                            })
                            .collect();
                        inner.into_iter().map(|h| h.join().unwrap()).collect::<Vec<_>>()
                    })
                })
                .collect();
            handles.into_iter().map(|h| h.join().unwrap()).collect()
        });
        for (u, results) in outcomes.iter().enumerate() {
            let accepted: Vec<u64> = results
                .iter()
                .filter(|(s, _)| *s == 201)
                .map(|(_, j)| j["experiment"]["id"].as_u64().unwrap())
                .collect();
            let refused = results.iter().filter(|(s, _)| *s == 429).count();
            assert_eq!(
                (accepted.len(), refused),
                (*expected, 20 - expected),
                "round {round}, {}: {results:?}",
                users[u]
            );
            for (_, json) in results.iter().filter(|(s, _)| *s == 429) {
                let error = json["error"].as_str().unwrap();
                assert!(
                    error.contains(users[u]) && (error.contains("waiting") || error.contains("robot-minutes")),
                    "{error}"
                );
            }
            for id in accepted {
                assert!(seen.insert(id), "experiment {id} was handed out twice");
            }
        }
        // Everything accepted is listed, once, and on disk; then it is
        // cancelled, which frees the limits for the next round.
        let (_, all) = lab.call(&boss, "GET", "/api/v1/experiments", "");
        let listed: Vec<u64> =
            all["experiments"].as_array().unwrap().iter().map(|e| e["id"].as_u64().unwrap()).collect();
        assert_eq!(listed.iter().copied().collect::<std::collections::BTreeSet<_>>(), seen, "round {round}");
        assert_eq!(listed.len(), seen.len(), "round {round}: a duplicate in the list");
        for id in &listed {
            assert!(store.join(format!("experiments/{id}/experiment.json")).is_file(), "experiment {id}");
        }
        for experiment in all["experiments"].as_array().unwrap() {
            let id = experiment["id"].as_u64().unwrap();
            if !["cancelled", "refused"].contains(&experiment["state"].as_str().unwrap()) {
                let (status, json) = lab.call(&boss, "POST", &format!("/api/v1/experiments/{id}/cancel"), "");
                assert_eq!(status, 200, "{json}");
            }
        }
    }
    // Ids were handed out in order, none skipped: nothing refused left a record.
    let max = *seen.iter().max().unwrap();
    assert_eq!(seen.len() as u64, max, "ids 1..={max}");
}

/// A cancel that races the start of the experiment: one outcome, recorded
/// once, and the baseline runs after it.
#[test]
fn a_cancel_racing_the_start_has_one_outcome() {
    let dir = tempfile::tempdir().unwrap();
    let lab = start_with_users(dir.path());
    let (ana, boss) = (lab.token("ana"), lab.token("boss"));
    let baseline = lab.active_set(&boss);
    let set = lab.stage(&ana, "ana.xml", &robot(7.0, ""));
    let mut ran = 0;
    for round in 0..8 {
        let (status, _) = lab.call(&boss, "POST", "/api/v1/lab/pause", "");
        assert_eq!(status, 200);
        let (status, json) = lab.call(
            &ana,
            "POST",
            "/api/v1/experiments",
            &serde_json::json!({"set": set, "duration_s": 30}).to_string(),
        );
        assert_eq!(status, 201, "{json}");
        let id = json["experiment"]["id"].as_u64().unwrap();
        lab.wait_for(&ana, id, "queued", Duration::from_secs(120));
        // Resume and cancel at once, the cancel a little later each round.
        let (resumed, cancelled) = std::thread::scope(|scope| {
            let resume = scope.spawn(|| lab.call(&boss, "POST", "/api/v1/lab/resume", ""));
            let cancel = scope.spawn(|| {
                std::thread::sleep(Duration::from_millis(round * 15));
                lab.call(&ana, "POST", &format!("/api/v1/experiments/{id}/cancel"), "")
            });
            (resume.join().unwrap(), cancel.join().unwrap())
        });
        assert_eq!(resumed.0, 200);
        assert_eq!(cancelled.0, 200, "{}", cancelled.1);
        let experiment = lab.experiment(&ana, id);
        let history = states(&experiment);
        assert_eq!(experiment["state"], "cancelled", "round {round}: {experiment:#}");
        let finals = history
            .iter()
            .filter(|s| ["done", "cancelled", "aborted", "failed", "refused"].contains(&s.as_str()))
            .count();
        assert_eq!(finals, 1, "round {round}: {history:?}");
        if history.contains(&"running".to_string()) {
            ran += 1;
            assert_eq!(&history[history.len() - 3..], ["running", "finishing", "cancelled"], "round {round}");
        } else {
            assert_eq!(&history[history.len() - 2..], ["queued", "cancelled"], "round {round}");
        }
    }
    let (_, audit) = lab.call(&boss, "GET", "/api/v1/audit", "");
    let entries = audit["entries"].as_array().unwrap();
    let cancels = entries.iter().filter(|e| e["action"] == "cancel-experiment").count();
    let starts = entries.iter().filter(|e| e["action"] == "experiment-start").count();
    let ends = entries.iter().filter(|e| e["action"] == "experiment-end").count();
    assert_eq!((cancels, starts, ends), (8, ran, ran), "each cancel and each run recorded once");
    let (status, _) = lab.call(&boss, "POST", "/api/v1/lab/pause", "");
    assert_eq!(status, 200);
    assert_eq!(lab.active_set(&boss), baseline);
}

/// A robot with a real motor controller (here the far end of a PTY): its
/// experiments' preflight runs against a simulated controller of the same
/// protocol in the owner's preflight world, the manual reset waits for an
/// admin, the run drives the real device, and the lab kit runs the same
/// preflight form on a researcher's machine with the same verdict.
#[test]
fn a_real_robot_is_preflighted_against_a_simulated_controller() {
    let dir = tempfile::tempdir().unwrap();
    let (mut motors, _slave, device) = crate::support::MotorRecorder::new();
    let real = |goal_x: f64| real_robot(goal_x, &device);
    let reading = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(true));
    let keep_reading = reading.clone();
    let recorder = std::thread::spawn(move || {
        motors.read_while(|| keep_reading.load(std::sync::atomic::Ordering::Relaxed));
        motors
    });
    // The owner's preflight world, and a manual reset (nothing simulated
    // on the robot to reset).
    let (lab, ana, boss, settings) = lab_on_a_played_robot(dir.path(), &real(8.0));
    let (status, json) = lab.call(&boss, "PUT", "/api/v1/lab/settings", &settings.to_string());
    assert_eq!(status, 200, "{json}");
    let set = lab.stage(&ana, "ana.xml", &real(7.0));
    let body = serde_json::json!({ "set": set, "duration_s": 3 }).to_string();
    let (status, json) = lab.call(&ana, "POST", "/api/v1/experiments", &body);
    assert_eq!(status, 201, "{json}");
    let id = json["experiment"]["id"].as_u64().unwrap();
    let queued = lab.wait_for(&ana, id, "queued", Duration::from_secs(120));
    // The preflight drove a simulated robot: the planner moved it.
    let preflight = queued["preflight"].clone();
    assert_eq!(preflight["passed"], true, "{queued:#}");
    // The manual reset: it waits for an admin.
    let deadline = Instant::now() + Duration::from_secs(60);
    loop {
        let experiment = lab.experiment(&ana, id);
        if experiment["awaiting_reset"] == true {
            break;
        }
        assert!(Instant::now() < deadline, "never waited for the reset: {experiment:#}");
        std::thread::sleep(Duration::from_millis(50));
    }
    let (_, overview) = lab.call(&ana, "GET", "/api/v1/lab", "");
    assert!(overview["lab"]["held"].as_str().unwrap().contains("waits for the robot to be reset"), "{overview}");
    // Held: the same at every look (no flapping), and no estimate of when.
    for _ in 0..5 {
        std::thread::sleep(Duration::from_millis(60));
        let (_, overview) = lab.call(&ana, "GET", "/api/v1/lab", "");
        assert!(overview["lab"]["held"].is_string(), "{overview}");
        let waiting = lab.experiment(&ana, id);
        assert!(waiting["eta_unix_ms"].is_null() && waiting["place"] == 1, "{waiting:#}");
    }
    let (status, json) = lab.call(&ana, "POST", "/api/v1/lab/reset", "");
    assert_eq!(status, 403, "only an admin confirms: {json}");
    let (status, json) = lab.call(&boss, "POST", "/api/v1/lab/reset", "");
    assert_eq!((status, json["confirmed_for"].as_u64()), (200, Some(id)), "{json}");
    lab.wait_for(&ana, id, "done", Duration::from_secs(60));
    reading.store(false, std::sync::atomic::Ordering::Relaxed);
    let motors = recorder.join().unwrap();
    // No feedback comes from this controller, so the envelope holds the
    // robot (stale sensors): the frames on the wire are the ascii STOP.
    assert!(motors.lines.iter().any(|(_, l)| l == "S"), "the real device got frames: {:?}", motors.lines);
    // The bundle's robot file is the preflight form: a simulated controller
    // stands in for the device, in the owner's world.
    let out = dir.path().join("results");
    std::fs::create_dir_all(&out).unwrap();
    let bundle = lab.results(&ana, id, &out);
    let written = std::fs::read_to_string(bundle.join("robot.xml")).unwrap();
    assert!(
        written.contains(r#"<component name="preflight-sim-motors" source="builtin:sim">"#)
            && written.contains(r#"<param name="device" value="sim:preflight-sim-motors"/>"#)
            && !written.contains(&device),
        "{written}"
    );
    // The kit: the baseline in its preflight form, which `subsume run`
    // judges as the lab does.
    fetch_kit(&lab, &ana, &out);
    let verdict = out.join("kit-verdict.json");
    let run = crate::support::subsume()
        .arg("run")
        .arg(out.join("lab-kit/robot.xml"))
        .args(["--http", "off", "--speed", "max", "--duration", "3", "--criteria"])
        .arg(out.join("lab-kit/criteria.json"))
        .arg("--verdict")
        .arg(&verdict)
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert!(run.status.success(), "{stderr}");
    assert!(stderr.contains("preflight verdict: passed"), "{stderr}");
    let verdict: Json = serde_json::from_slice(&std::fs::read(&verdict).unwrap()).unwrap();
    assert_eq!(verdict["passed"], preflight["passed"], "{verdict:#}");
}

/// A researcher drives only inside a reservation of their own (docs/lab.md):
/// before it their teleoperation login is refused; inside it they log in
/// with their password and are heard; when it is cancelled, their session
/// is closed at their next line, saying why, so their commands stop.
#[test]
fn a_researcher_drives_inside_their_reservation_and_is_cut_off_when_it_ends() {
    let dir = tempfile::tempdir().unwrap();
    setup(dir.path());
    let lab = start(dir.path());
    let teleop = lab.host.word_after("teleoperation on tcp ", Duration::from_secs(60));
    let ana = lab.token("ana");
    let auth = format!("AUTH ana {PASSWORD}");

    let (mut outside, _) = crate::support::Operator::connect_to(&teleop);
    assert_eq!(outside.say(&auth), "ERR authentication failed");
    drop(outside);

    let now = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap().as_millis() as u64;
    let booking = serde_json::json!({ "start_unix_ms": now, "end_unix_ms": now + 900_000 }).to_string();
    let (status, json) = lab.call(&ana, "POST", "/api/v1/lab/reservations", &booking);
    assert_eq!(status, 201, "{json}");
    let id = json["reservation"]["id"].as_u64().unwrap();

    // The lab grants the drive as the window opens (its runner's next turn).
    let deadline = Instant::now() + Duration::from_secs(20);
    let mut inside = loop {
        let (mut operator, _) = crate::support::Operator::connect_to(&teleop);
        let answer = operator.say(&auth);
        if answer.starts_with("OK authenticated as ana") {
            break operator;
        }
        assert!(Instant::now() < deadline, "ana never got in during her reservation: {answer}\n{}", lab.host.log());
        std::thread::sleep(Duration::from_millis(200));
    };

    let (status, json) = lab.call(&ana, "DELETE", &format!("/api/v1/lab/reservations/{id}"), "");
    assert_eq!(status, 200, "{json}");
    let deadline = Instant::now() + Duration::from_secs(20);
    let closed = loop {
        inside.send("CMD 1 0 VEL 0.1 0");
        let mut line = String::new();
        let n = std::io::BufRead::read_line(&mut inside.reader, &mut line).unwrap_or(0);
        if n == 0 || line.starts_with("ERR your reservation has ended") {
            break line;
        }
        assert!(Instant::now() < deadline, "ana still drives after her reservation: {line}\n{}", lab.host.log());
        std::thread::sleep(Duration::from_millis(100));
    };
    assert_eq!(closed.trim_end(), format!("ERR {}", subsume::teleop::session::GRANT_ENDED));
    let mut rest = String::new();
    assert_eq!(std::io::BufRead::read_line(&mut inside.reader, &mut rest).unwrap_or(0), 0, "still open: {rest}");
}

/// The names of the files in bundle folder `folder`, relative to it.
fn bundle_files(folder: &Path) -> Vec<String> {
    let mut names: Vec<String> =
        every_file(folder).into_iter().map(|(path, _)| path.to_string_lossy().into_owned()).collect();
    names.sort();
    names
}

/// A researcher's uploads, sets, experiments and results are hers
/// (docs/portal.md, "Who sees what"): another researcher sees none of it
/// through any route, cannot run it, submit it or get its bytes through a
/// bundle, and the robot's own robot file and components stay on the robot
/// while the owner's lab kit is off. Sharing an upload with the lab lets
/// others see and run it; an admin sees everything.
#[test]
fn a_researchers_work_is_hers_unless_she_shares_it() {
    let dir = tempfile::tempdir().unwrap();
    let lab = start_with_users(dir.path());
    let (ana, ben, boss) = (lab.token("ana"), lab.token("ben"), lab.token("boss"));
    let baseline = lab.active_set(&boss);
    // The owner keeps the robot's own files on the robot.
    let (status, settings) = lab.call(&boss, "GET", "/api/v1/lab", "");
    assert_eq!(status, 200, "{settings}");
    let mut settings = settings["lab"]["settings"].clone();
    settings["kit"] = Json::Bool(false);
    let (status, json) = lab.call(&boss, "PUT", "/api/v1/lab/settings", &settings.to_string());
    assert_eq!(status, 200, "{json}");
    // Ben's private planner, and his robot file that runs it.
    upload(&lab, &ben, "secret", "planner");
    let bens = robot(7.0, "").replace(&crate::support::guest("planner").display().to_string(), "secret.wasm");
    let ben_set = lab.stage(&ben, "ben.xml", &bens);
    let get = |token: &str, path: &str| lab.call(token, "GET", path, "");
    // (who, what, status): Ben's things are his and the admin's.
    let answers = [
        (&ana, format!("/api/v1/sets/{ben_set}"), 404),
        (&ana, "/api/v1/components/ben/secret".to_string(), 404),
        (&ben, format!("/api/v1/sets/{ben_set}"), 200),
        (&ben, "/api/v1/components/secret".to_string(), 200),
        (&boss, format!("/api/v1/sets/{ben_set}"), 200),
        (&boss, "/api/v1/components/ben/secret".to_string(), 200),
        (&ana, format!("/api/v1/sets/{baseline}"), 200),
    ];
    for (token, path, expected) in &answers {
        let (status, json) = get(token, path);
        assert_eq!(status, *expected, "GET {path}: {json}");
    }
    // The baseline's record, but not its robot file, while the kit is off.
    let (_, set) = get(&ana, &format!("/api/v1/sets/{baseline}"));
    assert!(set["config"].is_null(), "{set:#}");
    let (_, set) = get(&boss, &format!("/api/v1/sets/{baseline}"));
    assert!(set["config"].as_str().is_some_and(|c| c.contains("<robot")), "{set:#}");
    // Listings carry none of Ben's.
    let (_, sets) = get(&ana, "/api/v1/sets");
    let ids: Vec<u64> = sets["sets"].as_array().unwrap().iter().map(|s| s["id"].as_u64().unwrap()).collect();
    assert!(!ids.contains(&ben_set) && ids.contains(&baseline), "{sets:#}");
    let (_, components) = get(&ana, "/api/v1/components");
    assert!(!components.to_string().contains("secret"), "{components:#}");
    // Ana can neither run Ben's upload by name nor submit his set.
    let naming = bens.replace("secret.wasm", "ben/secret.wasm");
    let (status, json) = lab.call(&ana, "PUT", "/api/v1/platforms/control/configs/mine.xml", &naming);
    assert_eq!(status, 422, "{json}");
    assert!(json.to_string().contains("component 'ben/secret' is ben's and not shared with the lab"), "{json}");
    let submit = |token: &str, set: u64| {
        lab.call(token, "POST", "/api/v1/experiments", &serde_json::json!({"set": set, "duration_s": 2}).to_string())
    };
    let (status, json) = submit(&ana, ben_set);
    assert_eq!((status, json["error"].as_str()), (404, Some(format!("no set {ben_set}").as_str())), "{json}");
    // Ana submits the baseline as her own experiment and cancels it: its
    // bundle names the baseline's components by hash, never holds them.
    let (status, json) = submit(&ana, baseline);
    assert_eq!(status, 201, "{json}");
    let id = json["experiment"]["id"].as_u64().unwrap();
    // Cancelled once its preflight wrote the robot file in its preflight
    // form (or ended already: either way its results are whole).
    lab.wait_for(&ana, id, "queued", Duration::from_secs(120));
    let (status, json) = lab.call(&ana, "POST", &format!("/api/v1/experiments/{id}/cancel"), "");
    assert!(status == 200 || status == 409, "{json}");
    let deadline = Instant::now() + Duration::from_secs(60);
    while !["cancelled", "done"].contains(&lab.experiment(&ana, id)["state"].as_str().unwrap_or("")) {
        assert!(Instant::now() < deadline, "{:#}", lab.experiment(&ana, id));
        std::thread::sleep(Duration::from_millis(50));
    }
    let into = tempfile::tempdir().unwrap();
    let folder = lab.results(&ana, id, into.path());
    let files = bundle_files(&folder);
    assert!(files.iter().all(|f| !f.starts_with("components/") && f != "robot.xml"), "{files:?}");
    let record: Json = serde_json::from_slice(&std::fs::read(folder.join("experiment.json")).unwrap()).unwrap();
    let hashes = record["components"].as_array().unwrap().iter().filter(|c| c["sha256"].is_string()).count();
    assert_eq!(hashes, 3, "the three guests are named by their hashes: {record:#}");
    // The admin's copy of the same bundle holds them.
    let into = tempfile::tempdir().unwrap();
    let files = bundle_files(&lab.results(&boss, id, into.path()));
    assert_eq!(files.iter().filter(|f| f.starts_with("components/")).count(), 3, "{files:?}");
    assert!(files.contains(&"robot.xml".to_string()), "{files:?}");
    // Ben shares his upload with the lab: Ana sees it and runs it by name,
    // read-only; Ana cannot share it for him.
    let (status, json) = lab.call(&ana, "PUT", "/api/v1/components/ben/secret/visibility", r#"{"visibility":"lab"}"#);
    assert_eq!(status, 404, "{json}");
    let (status, json) = lab.call(&ben, "PUT", "/api/v1/components/ben/secret/visibility", r#"{"visibility":"lab"}"#);
    assert_eq!((status, json["visibility"].as_str()), (200, Some("lab")), "{json}");
    let (status, json) = get(&ana, "/api/v1/components/ben/secret");
    assert_eq!(status, 200, "{json}");
    let (status, json) = lab.call(&ana, "PUT", "/api/v1/platforms/control/configs/mine.xml", &naming);
    assert_eq!(status, 201, "{json}");
    // His set stays his.
    let (status, _) = get(&ana, &format!("/api/v1/sets/{ben_set}"));
    assert_eq!(status, 404);
}

/// Every file of every regular file under `root`, as (path relative to
/// `root`, bytes).
fn every_file(root: &Path) -> Vec<(PathBuf, Vec<u8>)> {
    let mut files = Vec::new();
    let mut folders = vec![root.to_path_buf()];
    while let Some(folder) = folders.pop() {
        for entry in std::fs::read_dir(&folder).unwrap() {
            let path = entry.unwrap().path();
            if path.is_dir() {
                folders.push(path);
            } else {
                let bytes = std::fs::read(&path).unwrap();
                files.push((path.strip_prefix(root).unwrap().to_path_buf(), bytes));
            }
        }
    }
    files.sort();
    files
}

/// Where `needle` occurs in the files, with some bytes around it.
fn occurrences(files: &[(PathBuf, Vec<u8>)], needle: &str) -> Vec<String> {
    let needle = needle.as_bytes();
    let mut found = Vec::new();
    for (name, bytes) in files {
        if let Some(at) = bytes.windows(needle.len()).position(|w| w == needle) {
            let around = &bytes[at.saturating_sub(60)..(at + needle.len() + 60).min(bytes.len())];
            found.push(format!("{}: …{}…", name.display(), String::from_utf8_lossy(around)));
        }
    }
    found
}

/// No file of an experiment's results bundle nor of the lab kit spells out
/// a folder of the owner's machine (the store, the robot file's folder,
/// the working folder): the API's names stand in for them, in the text
/// files and in the recordings alike.
#[test]
fn a_bundle_and_the_kit_spell_out_no_folder_of_the_owners_machine() {
    let dir = tempfile::tempdir().unwrap();
    setup(dir.path());
    let lab = start(dir.path());
    let ana = lab.token("ana");
    let set = lab.stage(&ana, "ana.xml", &robot(6.0, ""));
    let body = serde_json::json!({ "set": set, "duration_s": 2.0, "label": "paths" });
    let (status, json) = lab.call(&ana, "POST", "/api/v1/experiments", &body.to_string());
    assert_eq!(status, 201, "{json}");
    let id = json["experiment"]["id"].as_u64().unwrap();
    let done = lab.wait_for(&ana, id, "done", Duration::from_secs(180));
    assert_eq!(done["state"], "done", "{done:#}");

    let out = tempfile::tempdir().unwrap();
    let bundle = lab.results(&ana, id, out.path());
    let kit = out.path().join("lab-kit.tar");
    let fetched = Command::new("curl")
        .args(["-s", "-f", "-o"])
        .arg(&kit)
        .args(["-H", &format!("Authorization: Bearer {ana}")])
        .arg(format!("http://{}/api/v1/lab/kit", lab.address))
        .status()
        .unwrap();
    assert!(fetched.success());
    let unpacked = Command::new("tar").arg("-xf").arg(&kit).arg("-C").arg(out.path()).status().unwrap();
    assert!(unpacked.success());

    let mut files = every_file(&bundle);
    for name in ["log.txt", "preflight.log", "report.json", "preflight-report.json", "run.mcap", "preflight.mcap"] {
        assert!(files.iter().any(|(n, _)| n == Path::new(name)), "the bundle has no {name}");
    }
    let kit_files = every_file(&out.path().join("lab-kit"));
    assert!(kit_files.iter().any(|(n, _)| n == Path::new("robot.xml")), "the kit has no robot.xml");
    files.extend(kit_files.into_iter().map(|(n, b)| (Path::new("lab-kit").join(n), b)));

    let store = dir.path().join("store");
    let working = crate::support::repo_root();
    let mut folders = Vec::new();
    for folder in [dir.path().to_path_buf(), store, working] {
        folders.push(folder.display().to_string());
        folders.push(std::fs::canonicalize(&folder).unwrap().display().to_string());
    }
    let found: Vec<String> = folders.iter().flat_map(|f| occurrences(&files, f)).collect();
    assert!(found.is_empty(), "the owner's folders are spelled out:\n{}", found.join("\n"));
    // The names the API shows stand in for them.
    let report = String::from_utf8_lossy(&files.iter().find(|(n, _)| n == Path::new("report.json")).unwrap().1);
    assert!(report.contains("\"config\": \"<"), "{report}");
}

/// A preflight is bounded (docs/lab.md, Preflight): a guest that logs
/// without end (10,000 lines in a tick, up to its `max-logs`) fills the log
/// only to its limit, and the log says it was cut; its recording stops at
/// its limit, finished (the `mcap` package reads it whole) and marked cut,
/// and the log says so. Either way the preflight is judged.
#[test]
fn a_preflight_that_logs_without_end_is_cut_at_its_limits() {
    use subsume::lab::preflight::{self, Outcome, PreflightCommand, PreflightFiles, PreflightLimits, Priority};
    let flood = format!(
        r#"<component name="chatty" source="{}" rate="10" budget="200ms" max-logs="10000">
      <param name="mode" value="log-flood"/>
      <param name="after" value="0"/>
    </component>"#,
        crate::support::guest("test-faulty").display()
    );
    let cases = [
        ("log", PreflightLimits { log_bytes: 64 << 10, ..PreflightLimits::default() }),
        ("recording", PreflightLimits { recording_bytes: 1 << 20, ..PreflightLimits::default() }),
    ];
    for (bound, limits) in cases {
        let dir = tempfile::tempdir().unwrap();
        let robot = dir.path().join("robot.xml");
        // The preflight form has no network platform (no teleoperation).
        let xml = self::robot(8.0, &flood);
        let network = xml.find("  <platform name=\"network\">").unwrap();
        let xml = format!("{}</robot>\n", &xml[..network]);
        std::fs::write(&robot, xml).unwrap();
        std::fs::write(dir.path().join("lab.world"), WORLD).unwrap();
        let command = PreflightCommand {
            exe: PathBuf::from(env!("CARGO_BIN_EXE_subsume")),
            cache_dir: Some(crate::support::cache_dir()),
            priority: Priority::Normal,
            limits,
        };
        let files = PreflightFiles::in_dir(dir.path());
        let criteria = subsume::lab::verdict::Criteria::default();
        let outcome = preflight::run(&command, &robot, Duration::from_secs(3), &criteria, None, &files, &|| false);
        let log = std::fs::read_to_string(&files.log).unwrap();
        assert!(matches!(outcome, Ok(Outcome::Judged { .. })), "{bound}: {outcome:?}\n{log}");
        let recording = std::fs::read(&files.recording).unwrap();
        match bound {
            "log" => {
                let note = "\n(the preflight's log stops here: it is cut at 65536 bytes";
                let at = log.find(note).unwrap_or_else(|| panic!("the log does not say it was cut:\n{log}"));
                assert_eq!(at, 64 << 10, "cut where it should be");
                assert!(log.ends_with("the rest of its output was dropped)\n"), "{}", &log[at..]);
            }
            _ => {
                assert!(log.contains("the recording stops here"), "the log does not say so:\n{log}");
                let marked = recording.windows(21).any(|w| w == b"subsume.recording.cut");
                assert!(marked, "the recording is not marked cut");
                // The limit, plus the chunk being filled and the summary.
                assert!(recording.len() < (1 << 20) + (512 << 10), "{} bytes", recording.len());
                let read = read_mcap(&files.recording, false);
                assert_eq!(read["complete"], true, "{read}");
            }
        }
    }
}

/// Submit-and-cancel in a loop is bounded per user (at most 30 a minute,
/// then 429 saying when to try again) and erases nothing of anyone
/// else's: another researcher's experiment is still there, as it was.
#[test]
fn submit_and_cancel_churn_is_bounded_and_erases_nothing_of_anyone_elses() {
    let dir = tempfile::tempdir().unwrap();
    let lab = start_with_users(dir.path());
    let (ana, ben, boss) = (lab.token("ana"), lab.token("ben"), lab.token("boss"));
    let (status, _) = lab.call(&boss, "POST", "/api/v1/lab/pause", "");
    assert_eq!(status, 200);
    let submit = |token: &str, set: u64| {
        lab.call(token, "POST", "/api/v1/experiments", &serde_json::json!({"set": set, "duration_s": 2}).to_string())
    };
    let bens_set = lab.stage(&ben, "ben.xml", &robot(7.0, ""));
    let (status, json) = submit(&ben, bens_set);
    assert_eq!(status, 201, "{json}");
    let bens = json["experiment"]["id"].as_u64().unwrap();
    let anas_set = lab.stage(&ana, "ana.xml", &robot(7.0, ""));
    for round in 0..subsume::lab::MAX_SUBMISSIONS_PER_WINDOW {
        let (status, json) = submit(&ana, anas_set);
        assert_eq!(status, 201, "round {round}: {json}");
        let id = json["experiment"]["id"].as_u64().unwrap();
        let (status, json) = lab.call(&ana, "POST", &format!("/api/v1/experiments/{id}/cancel"), "");
        assert_eq!(status, 200, "round {round}: {json}");
    }
    let (status, json) = submit(&ana, anas_set);
    assert_eq!(status, 429, "{json}");
    let error = json["error"].as_str().unwrap();
    assert!(error.starts_with("ana submitted 30 experiments in the last 60 s, the most allowed"), "{error}");
    let bens_now = lab.experiment(&ben, bens);
    assert_eq!(bens_now["submitter"], "ben", "{bens_now:#}");
    assert_ne!(bens_now["state"], "cancelled", "{bens_now:#}");
}

/// A webhook receiver (tests/python/webhook_receiver.py: Python's
/// http.server and hmac) on 127.0.0.1; killed when dropped.
struct Receiver {
    child: std::process::Child,
    port: u16,
}

impl Receiver {
    fn start(secret: &str, out: &Path, port: u16, fail: u32) -> Receiver {
        Receiver::spawn(secret, out, port, fail, None)
    }

    /// `tls`: the folder of `make_test_pki`, whose server certificate it
    /// serves HTTPS with.
    fn spawn(secret: &str, out: &Path, port: u16, fail: u32, tls: Option<&Path>) -> Receiver {
        let mut command = Command::new(crate::support::python());
        command.arg(crate::support::repo_root().join("tests/python/webhook_receiver.py")).args([
            secret,
            &out.display().to_string(),
            "--port",
            &port.to_string(),
            "--fail",
            &fail.to_string(),
        ]);
        if let Some(pki) = tls {
            command.arg("--tls").arg(pki.join("chain.pem")).arg(pki.join("server.key"));
        }
        let (child, port) = listening(command);
        Receiver { child, port }
    }

    fn url(&self) -> String {
        format!("http://127.0.0.1:{}/hooks/lab", self.port)
    }
}

impl Drop for Receiver {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Spawns `command` (a Python peer) and reads its "listening on PORT".
fn listening(mut command: Command) -> (std::process::Child, u16) {
    use std::io::BufRead;
    let mut child = command.stdout(std::process::Stdio::piped()).spawn().unwrap();
    let mut line = String::new();
    std::io::BufReader::new(child.stdout.take().unwrap()).read_line(&mut line).unwrap();
    let port =
        line.trim().strip_prefix("listening on ").unwrap_or_else(|| panic!("peer said {line:?}")).parse().unwrap();
    (child, port)
}

/// The POSTs `out` received, waiting up to a minute for `count`.
fn received(out: &Path, count: usize, host: &HostProcess) -> Vec<Json> {
    let deadline = Instant::now() + Duration::from_secs(60);
    loop {
        let text = std::fs::read_to_string(out).unwrap_or_default();
        let lines: Vec<Json> = text.lines().map(|l| serde_json::from_str(l).unwrap()).collect();
        if lines.len() >= count {
            return lines;
        }
        assert!(Instant::now() < deadline, "{} of {count} posts received: {lines:#?}\n{}", lines.len(), host.log());
        std::thread::sleep(Duration::from_millis(50));
    }
}

const HOOK_SECRET: &str = "a-webhook-secret-of-the-owner";

fn configure_webhook(dir: &Path, url: &str) {
    let config = serde_json::json!({ "webhooks": [{
        "url": url,
        "events": ["experiment.accepted", "experiment.refused", "experiment.started", "experiment.ended"],
        "secret": HOOK_SECRET,
    }]});
    std::fs::write(dir.join("store/webhooks.json"), config.to_string()).unwrap();
}

/// (event, experiment id, state) of each acknowledged post, in order.
fn acknowledged(posts: &[Json]) -> Vec<(String, u64, String)> {
    posts
        .iter()
        .filter(|p| p["answered"] == 200)
        .map(|p| {
            let body = &p["body"];
            (
                body["event"].as_str().unwrap().to_string(),
                body["experiment"]["id"].as_u64().unwrap(),
                body["experiment"]["state"].as_str().unwrap().to_string(),
            )
        })
        .collect()
}

#[test]
fn webhooks_tell_of_an_experiment_in_order_signed_and_retried() {
    let dir = tempfile::tempdir().unwrap();
    setup(dir.path());
    let out = dir.path().join("posts.jsonl");
    // The first two posts are answered 500: the first event is retried.
    let receiver = Receiver::start(HOOK_SECRET, &out, 0, 2);
    configure_webhook(dir.path(), &receiver.url());
    let lab = start(dir.path());
    let ana = lab.token("ana");
    let set = lab.stage(&ana, "ana.xml", &robot(7.0, ""));
    let (id, _) = lab.run_to_done(&ana, set, 2.0);
    let posts = received(&out, 5, &lab.host);
    assert!(posts.iter().all(|p| p["valid"] == true), "every signature verifies with Python's hmac: {posts:#?}");
    assert_eq!(
        acknowledged(&posts),
        [
            ("experiment.accepted".to_string(), id, "queued".to_string()),
            ("experiment.started".to_string(), id, "running".to_string()),
            ("experiment.ended".to_string(), id, "done".to_string()),
        ],
        "{posts:#?}"
    );
    // The ended event carries the run's outcome apart from its status.
    let ended = posts.iter().rev().find(|p| p["body"]["event"] == "experiment.ended").unwrap();
    let outcome = &ended["body"]["experiment"]["outcome"];
    assert!(outcome["collisions"].is_u64() && outcome["faults"].is_array(), "{ended:#}");
    // The refused posts were the first event, sent again until acknowledged.
    let first = &posts[2]["event_id"];
    assert_eq!((&posts[0]["event_id"], &posts[1]["event_id"]), (first, first), "{posts:#?}");
    assert_eq!((&posts[0]["answered"], &posts[1]["answered"]), (&Json::from(500), &Json::from(500)));
    assert!(lab.host.log().contains("not delivered (try 2)"), "{}", lab.host.log());
}

#[test]
fn a_host_killed_with_undelivered_events_sends_them_after_restart() {
    let dir = tempfile::tempdir().unwrap();
    setup(dir.path());
    let out = dir.path().join("posts.jsonl");
    // A receiver that is not there: its port, freed.
    let port = Receiver::start(HOOK_SECRET, &out, 0, 0).port;
    configure_webhook(dir.path(), &format!("http://127.0.0.1:{port}/hooks/lab"));
    let mut lab = start(dir.path());
    let ana = lab.token("ana");
    let set = lab.stage(&ana, "ana.xml", &robot(7.0, ""));
    let (id, _) = lab.run_to_done(&ana, set, 2.0);
    let outbox = dir.path().join("store/outbox");
    let waiting = || {
        std::fs::read_dir(&outbox)
            .unwrap()
            .filter(|e| e.as_ref().unwrap().path().extension().is_some_and(|x| x == "json"))
            .count()
    };
    let deadline = Instant::now() + Duration::from_secs(30);
    while waiting() < 3 {
        assert!(Instant::now() < deadline, "{} events in the outbox\n{}", waiting(), lab.host.log());
        std::thread::sleep(Duration::from_millis(50));
    }
    lab.host.child.kill().unwrap();
    lab.host.child.wait().unwrap();

    let _receiver = Receiver::start(HOOK_SECRET, &out, port, 0);
    lab = start(dir.path());
    let posts = received(&out, 3, &lab.host);
    assert!(posts.iter().all(|p| p["valid"] == true), "{posts:#?}");
    assert_eq!(
        acknowledged(&posts),
        [
            ("experiment.accepted".to_string(), id, "queued".to_string()),
            ("experiment.started".to_string(), id, "running".to_string()),
            ("experiment.ended".to_string(), id, "done".to_string()),
        ],
        "{posts:#?}"
    );
    let deadline = Instant::now() + Duration::from_secs(30);
    while waiting() > 0 {
        assert!(Instant::now() < deadline, "{} events still in the outbox\n{}", waiting(), lab.host.log());
        std::thread::sleep(Duration::from_millis(50));
    }
    // Acknowledged, none is sent again by the next start.
    lab.host.child.kill().unwrap();
    lab.host.child.wait().unwrap();
    let lab = start(dir.path());
    assert!(
        lab.host.log().contains("notifications: 1 webhooks, mail not configured, 0 events waiting"),
        "{}",
        lab.host.log()
    );
    assert_eq!(received(&out, 3, &lab.host).len(), 3);
}

#[test]
fn an_https_webhook_is_verified_against_its_authority_and_an_untrusted_one_holds_up_no_other() {
    let dir = tempfile::tempdir().unwrap();
    setup(dir.path());
    let pki = dir.path().join("pki");
    std::fs::create_dir(&pki).unwrap();
    crate::support::make_test_pki(&pki);
    let trusted_out = dir.path().join("trusted.jsonl");
    let untrusted_out = dir.path().join("untrusted.jsonl");
    let trusted = Receiver::spawn(HOOK_SECRET, &trusted_out, 0, 0, Some(&pki));
    let untrusted = Receiver::spawn(HOOK_SECRET, &untrusted_out, 0, 0, Some(&pki));
    let events = ["experiment.accepted", "experiment.started", "experiment.ended"];
    // The same server certificate: one hook trusts the test's authority,
    // the other only the system's roots, which do not hold it.
    let config = serde_json::json!({ "webhooks": [
        { "url": format!("https://localhost:{}/hooks/lab", untrusted.port), "events": events, "secret": HOOK_SECRET },
        { "url": format!("https://127.0.0.1:{}/hooks/lab", trusted.port), "events": events, "secret": HOOK_SECRET,
          "ca": pki.join("ca.pem") },
    ]});
    std::fs::write(dir.path().join("store/webhooks.json"), config.to_string()).unwrap();
    let lab = start(dir.path());
    let ana = lab.token("ana");
    let set = lab.stage(&ana, "ana.xml", &robot(7.0, ""));
    let (id, _) = lab.run_to_done(&ana, set, 2.0);
    let posts = received(&trusted_out, 3, &lab.host);
    assert!(posts.iter().all(|p| p["valid"] == true), "{posts:#?}");
    assert_eq!(
        acknowledged(&posts),
        [
            ("experiment.accepted".to_string(), id, "queued".to_string()),
            ("experiment.started".to_string(), id, "running".to_string()),
            ("experiment.ended".to_string(), id, "done".to_string()),
        ],
        "all three over TLS while the untrusted hook keeps failing: {posts:#?}"
    );
    let log = lab.host.log();
    assert!(
        std::fs::read_to_string(&untrusted_out).unwrap_or_default().is_empty(),
        "nothing is posted to a certificate not trusted"
    );
    assert!(
        log.contains(&format!("https://localhost:{}/hooks/lab", untrusted.port)) && log.contains("not delivered"),
        "{log}"
    );
    assert!(log.to_lowercase().contains("certificate"), "the log says why: {log}");
}

/// The test's SMTP server (Python's aiosmtpd: STARTTLS required, one
/// login), each message it accepted a line of `out`.
struct MailServer {
    child: std::process::Child,
    port: u16,
}

impl MailServer {
    fn start(out: &Path, pki: &Path, fail: u32) -> MailServer {
        let mut command = Command::new(crate::support::python());
        command
            .arg(crate::support::repo_root().join("tests/python/smtp_receiver.py"))
            .arg(out)
            .arg("--cert")
            .arg(pki.join("chain.pem"))
            .arg("--key")
            .arg(pki.join("server.key"))
            .args(["--user", "lab-mailer", "--password", MAIL_PASSWORD, "--fail", &fail.to_string()]);
        let (child, port) = listening(command);
        MailServer { child, port }
    }
}

impl Drop for MailServer {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

const MAIL_PASSWORD: &str = "the-smtp-password-of-the-lab";

/// The mails `out` holds, waiting up to a minute for `count`.
fn mails(out: &Path, count: usize, host: &HostProcess) -> Vec<Json> {
    received(out, count, host)
}

#[test]
fn mail_tells_a_researcher_of_her_own_experiments_and_the_owner_of_everyones() {
    let dir = tempfile::tempdir().unwrap();
    setup(dir.path());
    let pki = dir.path().join("pki");
    std::fs::create_dir(&pki).unwrap();
    crate::support::make_test_pki(&pki);
    let out = dir.path().join("mails.jsonl");
    // The server answers the first message "451 try again later": it is
    // sent again.
    let server = MailServer::start(&out, &pki, 1);
    let config = serde_json::json!({
        "server": "localhost", "port": server.port, "security": "starttls",
        "from": "lab@robots.example.org", "user": "lab-mailer", "password": MAIL_PASSWORD,
        "ca": pki.join("ca.pem"),
        "owner": [{ "address": "owner@robots.example.org", "events": ["experiment.ended"] }],
    });
    std::fs::write(dir.path().join("store/mail.json"), config.to_string()).unwrap();
    let lab = start(dir.path());
    let ana = lab.token("ana");
    let ben = lab.token("ben");
    // Her own subscription: checked, kept, shown to her alone.
    let (status, json) = lab.call(&ana, "GET", "/api/v1/lab/mail", "");
    assert_eq!((status, &json["mail"]), (200, &Json::Null), "{json}");
    for (bad, why) in [
        (r#"{"address": "not an address", "events": ["experiment.ended"]}"#, "address"),
        (r#"{"address": "ana@example.org", "events": ["robot.lost"]}"#, "own experiments"),
        (r#"{"address": "ana@example.org", "events": ["experiment.ended"], "cc": "x"}"#, "unknown field"),
    ] {
        let (status, json) = lab.call(&ana, "PUT", "/api/v1/lab/mail", bad);
        assert_eq!(status, 400, "{bad}: {json}");
        assert!(json["error"].as_str().unwrap_or_default().contains(why), "{bad}: {json}");
    }
    let wanted = r#"{"address": "ana@example.org", "events": ["experiment.ended", "experiment.refused"]}"#;
    let (status, json) = lab.call(&ana, "PUT", "/api/v1/lab/mail", wanted);
    assert_eq!(status, 200, "{json}");
    assert_eq!(json["mail"]["address"], "ana@example.org");
    let (_, json) = lab.call(&ben, "GET", "/api/v1/lab/mail", "");
    assert_eq!(json["mail"], Json::Null, "ben sees his own subscription, not hers");

    let mut ids = Vec::new();
    for token in [&ana, &ben] {
        let set = lab.stage(token, "mine.xml", &robot(7.0, ""));
        let (id, _) = lab.run_to_done(token, set, 1.0);
        ids.push(id);
    }
    let got = mails(&out, 3, &lab.host);
    for mail in &got {
        assert_eq!(mail["tls"], true, "over STARTTLS: {mail}");
        assert_eq!(mail["login"], "lab-mailer", "logged in: {mail}");
        assert_eq!(mail["from"], "lab@robots.example.org");
    }
    let to = |address: &str| -> Vec<String> {
        got.iter().filter(|m| m["to"][0] == address).map(|m| m["subject"].as_str().unwrap().to_string()).collect()
    };
    assert_eq!(to("ana@example.org"), [format!("[subsume lab] experiment {} done", ids[0])], "{got:#?}");
    assert_eq!(
        to("owner@robots.example.org"),
        [format!("[subsume lab] experiment {} done", ids[0]), format!("[subsume lab] experiment {} done", ids[1])],
        "the owner hears of everyone's; ben, not subscribed, of nothing: {got:#?}"
    );
    assert_eq!(got.len(), 3, "{got:#?}");
    let body = got.iter().find(|m| m["to"][0] == "ana@example.org").unwrap()["body"].as_str().unwrap().to_string();
    assert!(body.contains(&format!("Experiment {} by ana is now done", ids[0])), "{body}");
    assert!(
        body.contains("Outcome: ended: time-out, goal ") && body.contains("collision"),
        "the outcome beside the status, why the run ended first: {body}"
    );
    assert!(lab.host.log().contains("not delivered (try 1)"), "the 451 was retried: {}", lab.host.log());
    assert!(!lab.host.log().contains(MAIL_PASSWORD), "the password is never logged");
    // Ending it: no more mail for her.
    let (status, json) = lab.call(&ana, "DELETE", "/api/v1/lab/mail", "");
    assert_eq!((status, &json["mail"]), (200, &Json::Null), "{json}");
    let audit = std::fs::read_to_string(dir.path().join("store/audit.log")).unwrap_or_default();
    assert!(audit.contains("mail-subscription"), "audited: {audit}");
}

#[test]
fn a_lab_without_mail_says_so_when_a_user_subscribes() {
    let dir = tempfile::tempdir().unwrap();
    setup(dir.path());
    let lab = start(dir.path());
    let ana = lab.token("ana");
    let (status, json) =
        lab.call(&ana, "PUT", "/api/v1/lab/mail", r#"{"address": "a@b.org", "events": ["experiment.ended"]}"#);
    assert_eq!(status, 409, "{json}");
    assert!(json["error"].as_str().unwrap().contains("sends no mail"), "{json}");
}

/// An admin takes the robot out of service: nothing starts, the queued
/// submitter sees why and no ETA, a restart keeps it, the owner's webhook
/// hears of both ends of it, and the queue goes on once it ends.
#[test]
fn maintenance_holds_the_queue_with_its_reason_through_a_restart_until_an_admin_ends_it() {
    let dir = tempfile::tempdir().unwrap();
    setup(dir.path());
    let out = dir.path().join("posts.jsonl");
    let receiver = Receiver::start(HOOK_SECRET, &out, 0, 0);
    let config = serde_json::json!({ "webhooks": [{
        "url": receiver.url(),
        "events": ["robot.maintenance.started", "robot.maintenance.ended"],
        "secret": HOOK_SECRET,
    }]});
    std::fs::write(dir.path().join("store/webhooks.json"), config.to_string()).unwrap();
    let mut lab = start(dir.path());
    let (ana, boss) = (lab.token("ana"), lab.token("boss"));
    let reason = r#"{"reason": "the left wheel slips: new tyre"}"#;
    let (status, json) = lab.call(&ana, "POST", "/api/v1/lab/maintenance", reason);
    assert_eq!(status, 403, "a researcher may not: {json}");
    let (status, json) = lab.call(&boss, "POST", "/api/v1/lab/maintenance", r#"{"reason": "  "}"#);
    assert_eq!(status, 400, "a reason is needed: {json}");
    let (status, json) = lab.call(&boss, "POST", "/api/v1/lab/maintenance", reason);
    assert_eq!(status, 200, "{json}");
    assert_eq!(json["maintenance"]["by"], "boss");
    let (status, _) = lab.call(&boss, "POST", "/api/v1/lab/maintenance", reason);
    assert_eq!(status, 409, "in maintenance already");

    let set = lab.stage(&ana, "ana.xml", &robot(7.0, ""));
    let body = serde_json::json!({ "set": set, "duration_s": 2.0 }).to_string();
    let (status, json) = lab.call(&ana, "POST", "/api/v1/experiments", &body);
    assert_eq!(status, 201, "{json}");
    let id = json["experiment"]["id"].as_u64().unwrap();
    lab.wait_for(&ana, id, "queued", Duration::from_secs(120));
    // The runner looked at the head of the queue and holds it: the reason
    // is in the lab's view, the experiment waits without an ETA.
    let held = |lab: &Lab, token: &str| {
        let deadline = Instant::now() + Duration::from_secs(30);
        loop {
            let (_, view) = lab.call(token, "GET", "/api/v1/lab", "");
            if view["lab"]["held"].as_str().is_some_and(|h| h.contains("maintenance")) {
                return view;
            }
            assert!(Instant::now() < deadline, "never held: {view:#}");
            std::thread::sleep(Duration::from_millis(50));
        }
    };
    let view = held(&lab, &ana);
    assert!(view["lab"]["held"].as_str().unwrap().contains("the left wheel slips: new tyre"), "{view:#}");
    assert_eq!(view["lab"]["maintenance"]["reason"], "the left wheel slips: new tyre");
    let experiment = lab.experiment(&ana, id);
    assert_eq!(
        (&experiment["state"], &experiment["eta_unix_ms"]),
        (&Json::from("queued"), &Json::Null),
        "{experiment:#}"
    );

    // A restart keeps it: stored with the lab's state.
    lab.host.child.kill().unwrap();
    lab.host.child.wait().unwrap();
    lab = start(dir.path());
    let (ana, boss) = (lab.token("ana"), lab.token("boss"));
    let view = held(&lab, &ana);
    assert_eq!(view["lab"]["maintenance"]["by"], "boss", "{view:#}");
    assert_eq!(lab.experiment(&ana, id)["state"], "queued");

    // From the command line, as the admin: back in service; it runs.
    let output = crate::support::subsume()
        .args(["lab", "maintenance", "--end", &lab.address])
        .env("SUBSUME_USER", "boss")
        .env("SUBSUME_PASSWORD", PASSWORD)
        .output()
        .unwrap();
    assert!(output.status.success(), "{}", String::from_utf8_lossy(&output.stderr));
    lab.wait_for(&ana, id, "done", Duration::from_secs(120));
    let (status, _) = lab.call(&boss, "DELETE", "/api/v1/lab/maintenance", "");
    assert_eq!(status, 409, "not in maintenance any more");

    let posts = received(&out, 2, &lab.host);
    let events: Vec<(&str, &str)> = posts
        .iter()
        .map(|p| (p["body"]["event"].as_str().unwrap(), p["body"]["robot"]["reason"].as_str().unwrap_or_default()))
        .collect();
    assert_eq!(events[0], ("robot.maintenance.started", "the left wheel slips: new tyre (by boss)"), "{posts:#?}");
    assert_eq!(events[1].0, "robot.maintenance.ended", "{posts:#?}");
    assert!(posts.iter().all(|p| p["valid"] == true && p["body"]["robot"]["name"] == "lab"), "{posts:#?}");
    let audit = std::fs::read_to_string(dir.path().join("store/audit.log")).unwrap_or_default();
    assert!(audit.contains("maintenance-start") && audit.contains("maintenance-end"), "{audit}");
}

/// A tmpfs of `mib` MiB mounted at `dir` for one test (as root, as CI
/// runs), unmounted when dropped.
struct Tmpfs(PathBuf);

impl Tmpfs {
    fn mount(dir: &Path, mib: u32) -> Tmpfs {
        std::fs::create_dir_all(dir).unwrap();
        let output = Command::new("mount")
            .args(["-t", "tmpfs", "-o", &format!("size={mib}m"), "tmpfs"])
            .arg(dir)
            .output()
            .unwrap_or_else(|e| panic!("mount is needed for the full-disk test: {e}"));
        assert!(output.status.success(), "mounting a tmpfs needs root: {}", String::from_utf8_lossy(&output.stderr));
        Tmpfs(dir.to_path_buf())
    }
}

impl Drop for Tmpfs {
    fn drop(&mut self) {
        let _ = Command::new("umount").arg("-l").arg(&self.0).output();
    }
}

/// A full disk under the store: staging and submitting answer 507 naming
/// the cause, the store and the lab show exactly what they showed before,
/// and once space is freed the same requests succeed.
#[test]
fn a_full_disk_answers_507_and_changes_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let _disk = Tmpfs::mount(&dir.path().join("store"), 16);
    setup(dir.path());
    let lab = start(dir.path());
    let ana = lab.token("ana");
    let good = lab.stage(&ana, "good.xml", &robot(7.0, ""));
    let look = |lab: &Lab| {
        let (_, sets) = lab.call(&ana, "GET", "/api/v1/sets", "");
        let (_, experiments) = lab.call(&ana, "GET", "/api/v1/experiments", "");
        (sets["sets"].as_array().map(Vec::len), experiments["experiments"].as_array().map(Vec::len))
    };
    let before = look(&lab);
    // Fill what is left of the disk.
    let filler = dir.path().join("store/filler");
    let mut file = std::fs::File::create(&filler).unwrap();
    let chunk = vec![0u8; 1 << 20];
    while std::io::Write::write_all(&mut file, &chunk).is_ok() {}
    let _ = file.sync_all();
    let mut tail = vec![0u8; 4096];
    while std::io::Write::write_all(&mut file, &tail).is_ok() {}
    tail.truncate(1);
    while std::io::Write::write_all(&mut file, &tail).is_ok() {}
    drop(file);

    let (status, json) = lab.call(&ana, "PUT", "/api/v1/platforms/control/configs/more.xml", &robot(6.0, ""));
    assert_eq!(status, 507, "{json}");
    assert!(json["error"].as_str().unwrap_or_default().contains("disk is full"), "{json}");
    let body = serde_json::json!({ "set": good, "duration_s": 2.0 }).to_string();
    let (status, json) = lab.call(&ana, "POST", "/api/v1/experiments", &body);
    assert_eq!(status, 507, "{json}");
    assert_eq!(look(&lab), before, "nothing of either request was kept, nor shown");

    std::fs::remove_file(&filler).unwrap();
    lab.stage(&ana, "more.xml", &robot(6.0, ""));
    let (status, json) = lab.call(&ana, "POST", "/api/v1/experiments", &body);
    assert_eq!(status, 201, "with space again: {json}");
    let id = json["experiment"]["id"].as_u64().unwrap();
    lab.wait_for(&ana, id, "done", Duration::from_secs(120));
}

/// Nothing silently stuck: a queued experiment that cannot start (the
/// robot in maintenance) is refused once it has waited the owner's
/// `stuck_after_min_s` (twice its first ETA when that is longer), with
/// why; its submitter's webhook hears it.
#[test]
fn a_queued_experiment_that_never_starts_is_refused_saying_why() {
    let dir = tempfile::tempdir().unwrap();
    setup(dir.path());
    let out = dir.path().join("posts.jsonl");
    let receiver = Receiver::start(HOOK_SECRET, &out, 0, 0);
    configure_webhook(dir.path(), &receiver.url());
    let lab = start(dir.path());
    let (ana, boss) = (lab.token("ana"), lab.token("boss"));
    let (_, overview) = lab.call(&boss, "GET", "/api/v1/lab", "");
    let mut settings = overview["lab"]["settings"].clone();
    assert_eq!(settings["stuck_after_min_s"], 900, "15 minutes by default: {settings}");
    settings["stuck_after_min_s"] = Json::from(0);
    let (status, json) = lab.call(&boss, "PUT", "/api/v1/lab/settings", &settings.to_string());
    assert_eq!(status, 400, "{json}");
    settings["stuck_after_min_s"] = Json::from(3);
    let (status, json) = lab.call(&boss, "PUT", "/api/v1/lab/settings", &settings.to_string());
    assert_eq!(status, 200, "{json}");
    let (status, json) = lab.call(&boss, "POST", "/api/v1/lab/maintenance", r#"{"reason": "a motor to swap"}"#);
    assert_eq!(status, 200, "{json}");
    let set = lab.stage(&ana, "ana.xml", &robot(7.0, ""));
    let body = serde_json::json!({ "set": set, "duration_s": 2.0 }).to_string();
    let (status, json) = lab.call(&ana, "POST", "/api/v1/experiments", &body);
    assert_eq!(status, 201, "{json}");
    let id = json["experiment"]["id"].as_u64().unwrap();
    let refused = lab.wait_for(&ana, id, "refused", Duration::from_secs(120));
    let queued_at = refused["history"].as_array().unwrap().iter().find(|c| c["state"] == "queued").unwrap()["at_ms"]
        .as_u64()
        .unwrap();
    let refused_at = refused["history"].as_array().unwrap().last().unwrap()["at_ms"].as_u64().unwrap();
    assert!(refused_at >= queued_at + 3000, "not before its 3 s: {refused:#}");
    let reason = refused["reasons"][0].as_str().unwrap_or_default();
    assert!(reason.contains("did not start in time (it never had an estimate; at least 3 s)"), "{reason}");
    assert!(reason.contains("maintenance") && reason.contains("a motor to swap"), "says why: {reason}");
    let posts = received(&out, 2, &lab.host);
    let told: Vec<&str> = posts.iter().map(|p| p["body"]["event"].as_str().unwrap()).collect();
    assert_eq!(told, ["experiment.accepted", "experiment.refused"], "{posts:#?}");
}

/// The owner's duty cycle: after `run_s` of experiments the robot rests
/// `rest_s` before the next starts, and the lab says so while it does.
#[test]
fn the_duty_cycle_rests_the_robot_between_experiments_and_says_so() {
    let dir = tempfile::tempdir().unwrap();
    setup(dir.path());
    let lab = start(dir.path());
    let (ana, boss) = (lab.token("ana"), lab.token("boss"));
    let (_, overview) = lab.call(&boss, "GET", "/api/v1/lab", "");
    let mut settings = overview["lab"]["settings"].clone();
    assert_eq!(settings["duty_cycle"], Json::Null, "off by default");
    settings["duty_cycle"] = serde_json::json!({ "run_s": 0, "rest_s": 4 });
    let (status, json) = lab.call(&boss, "PUT", "/api/v1/lab/settings", &settings.to_string());
    assert_eq!(status, 400, "{json}");
    settings["duty_cycle"] = serde_json::json!({ "run_s": 2, "rest_s": 4 });
    let (status, json) = lab.call(&boss, "PUT", "/api/v1/lab/settings", &settings.to_string());
    assert_eq!(status, 200, "{json}");
    let set = lab.stage(&ana, "ana.xml", &robot(7.0, ""));
    let body = serde_json::json!({ "set": set, "duration_s": 2.0 }).to_string();
    let ids: Vec<u64> = (0..2)
        .map(|_| {
            let (status, json) = lab.call(&ana, "POST", "/api/v1/experiments", &body);
            assert_eq!(status, 201, "{json}");
            json["experiment"]["id"].as_u64().unwrap()
        })
        .collect();
    lab.wait_for(&ana, ids[0], "done", Duration::from_secs(120));
    let deadline = Instant::now() + Duration::from_secs(30);
    loop {
        let (_, view) = lab.call(&ana, "GET", "/api/v1/lab", "");
        let held = view["lab"]["held"].as_str().unwrap_or_default().to_string();
        if held.contains("rests until") {
            assert!(held.contains("duty cycle: 2 s of experiments, then 4 s of rest"), "{held}");
            break;
        }
        let second = lab.experiment(&ana, ids[1]);
        assert!(second["state"] == "queued" && Instant::now() < deadline, "never said it rests: {view:#} {second:#}");
        std::thread::sleep(Duration::from_millis(50));
    }
    let second = lab.wait_for(&ana, ids[1], "done", Duration::from_secs(120));
    let at = |record: &Json, state: &str| {
        record["history"].as_array().unwrap().iter().find(|c| c["state"] == state).unwrap()["at_ms"].as_u64().unwrap()
    };
    let first = lab.experiment(&ana, ids[0]);
    let rested = at(&second, "running") - at(&first, "done");
    assert!(rested >= 3_900, "the second started {rested} ms after the first ended, before its 4 s of rest");
}

/// A real robot (a pseudo-terminal playing its motor controller, which
/// gives odometry, ranges and its battery) with the owner's self-test: a
/// healthy controller passes it after the run, into the bundle and the
/// lab's history; a battery run down below the owner's threshold fails it
/// after the next run, which still ends `done`. The robot is then out of
/// service by the self-test, saying why: the next experiment waits, and
/// /metrics says so. Charged above the owner's second threshold, it comes
/// back by itself and the waiting experiment runs.
#[test]
fn a_self_test_after_each_run_takes_a_robot_whose_battery_ran_down_out_of_service_until_it_is_charged() {
    let dir = tempfile::tempdir().unwrap();
    let (motors, _slave, device) = crate::support::MotorRecorder::new();
    let real = |goal_x: f64| real_robot(goal_x, &device);
    // The controller's battery, in mV, as the test sets it.
    let controller = PlayedController::start(motors, 12_400u32, |volts| format!("P {volts}\n"));
    let (lab, ana, boss, mut settings) = lab_on_a_played_robot(dir.path(), &real(8.0));
    // A window shorter than the owner may set is refused by name.
    settings["self_test"] = serde_json::json!({"window_ms": 50, "min_battery_v": 11.0});
    let (status, json) = lab.call(&boss, "PUT", "/api/v1/lab/settings", &settings.to_string());
    assert_eq!(status, 400, "{json}");
    assert!(json["error"].as_str().unwrap().contains("self_test.window_ms must be from 200 to 10000"), "{json}");
    settings["self_test"] = serde_json::json!({"window_ms": 1000, "min_battery_v": 11.0, "resume_battery_v": 10.0});
    let (status, json) = lab.call(&boss, "PUT", "/api/v1/lab/settings", &settings.to_string());
    assert_eq!(status, 400, "{json}");
    assert!(json["error"].as_str().unwrap().contains("resume_battery_v must be above min_battery_v"), "{json}");
    settings["self_test"] = serde_json::json!({"window_ms": 1000, "min_battery_v": 11.0, "resume_battery_v": 12.2});
    let (status, json) = lab.call(&boss, "PUT", "/api/v1/lab/settings", &settings.to_string());
    assert_eq!(status, 200, "{json}");
    let set = lab.stage(&ana, "ana.xml", &real(7.0));
    let run = |expected_reset: bool| {
        let id = lab.submit(&ana, set, 2.0);
        if expected_reset {
            lab.reset_when_awaited(&ana, &boss, id);
        }
        id
    };
    let first = run(true);
    assert_eq!(lab.wait_for(&ana, first, "done", Duration::from_secs(120))["state"], "done");
    let (_, overview) = lab.call(&boss, "GET", "/api/v1/lab", "");
    let tests = overview["lab"]["self_tests"].as_array().unwrap().clone();
    assert_eq!(tests.len(), 1, "{overview:#}");
    assert_eq!((&tests[0]["passed"], &tests[0]["experiment"]), (&Json::Bool(true), &Json::from(first)), "{tests:#?}");
    let said = tests[0]["checks"].to_string();
    assert!(said.contains("feedback messages in 1.0 s") && said.contains("battery 12.40 V"), "{said}");
    assert!(overview["lab"]["maintenance"].is_null(), "{overview:#}");
    // Researchers do not see the owner's history.
    let (_, seen) = lab.call(&ana, "GET", "/api/v1/lab", "");
    assert!(seen["lab"].get("self_tests").is_none(), "{seen:#}");
    // The bundle holds the self-test that followed the run.
    let out = dir.path().join("results");
    std::fs::create_dir_all(&out).unwrap();
    let bundle = lab.results(&ana, first, &out);
    let kept: Json = serde_json::from_slice(&std::fs::read(bundle.join("selftest.json")).unwrap()).unwrap();
    assert_eq!(kept, tests[0]);
    // The battery runs down: the next run completes; its self-test fails.
    controller.set(10_400);
    let second = run(true);
    assert_eq!(lab.wait_for(&ana, second, "done", Duration::from_secs(120))["state"], "done");
    let (_, overview) = lab.call(&boss, "GET", "/api/v1/lab", "");
    let maintenance = overview["lab"]["maintenance"].clone();
    assert_eq!(maintenance["by"], "self-test", "{overview:#}");
    let reason = maintenance["reason"].as_str().unwrap();
    assert!(reason.contains(&format!("the self-test after experiment {second} failed")), "{reason}");
    assert!(reason.contains("battery 10.40 V is under 11.00 V"), "{reason}");
    let tests = overview["lab"]["self_tests"].as_array().unwrap();
    assert_eq!((tests.len(), &tests[1]["passed"]), (2, &Json::Bool(false)), "{tests:#?}");
    // Out of service: the next experiment waits, saying why.
    let third = {
        let body = serde_json::json!({ "set": set, "duration_s": 2 }).to_string();
        let (status, json) = lab.call(&ana, "POST", "/api/v1/experiments", &body);
        assert_eq!(status, 201, "{json}");
        json["experiment"]["id"].as_u64().unwrap()
    };
    let queued = lab.wait_for(&ana, third, "queued", Duration::from_secs(120));
    assert_eq!(queued["state"], "queued", "{queued:#}");
    std::thread::sleep(Duration::from_secs(2));
    let (_, overview) = lab.call(&ana, "GET", "/api/v1/lab", "");
    assert!(overview["lab"]["held"].as_str().unwrap_or_default().contains("maintenance"), "{overview:#}");
    assert_eq!(lab.experiment(&ana, third)["state"], "queued");
    let (status, metrics) = crate::support::http_bytes(&lab.address, "GET", "/metrics", Some(&boss), b"");
    let metrics = String::from_utf8_lossy(&metrics);
    assert_eq!(status, 200);
    assert!(
        metrics.contains("subsume_lab_self_test_passed 0") && metrics.contains("subsume_lab_maintenance 1"),
        "{metrics}"
    );
    // Charged, but not yet above the second threshold: still out.
    controller.set(11_600);
    std::thread::sleep(Duration::from_secs(2));
    let (_, overview) = lab.call(&boss, "GET", "/api/v1/lab", "");
    assert_eq!(overview["lab"]["maintenance"]["by"], "self-test", "{overview:#}");
    // Charged above it: back in service by itself, and the queue goes on.
    controller.set(12_600);
    let deadline = Instant::now() + Duration::from_secs(30);
    while lab.experiment(&ana, third)["awaiting_reset"] != true {
        let (_, overview) = lab.call(&boss, "GET", "/api/v1/lab", "");
        assert!(Instant::now() < deadline, "the charged robot never came back: {overview:#}");
        std::thread::sleep(Duration::from_millis(50));
    }
    let (_, overview) = lab.call(&boss, "GET", "/api/v1/lab", "");
    assert!(overview["lab"]["maintenance"].is_null(), "{overview:#}");
    let (status, json) = lab.call(&boss, "POST", "/api/v1/lab/reset", "");
    assert_eq!(status, 200, "{json}");
    assert_eq!(lab.wait_for(&ana, third, "done", Duration::from_secs(120))["state"], "done");
    let (_, audit) = lab.call(&boss, "GET", "/api/v1/audit", "");
    let ended = audit["entries"].as_array().unwrap().iter().any(|e| {
        e["action"] == "maintenance-end" && e["user"] == "self-test" && e.to_string().contains("the battery is charged")
    });
    assert!(ended, "{audit:#}");
    // An admin runs the self-test from the command line: a low battery
    // fails it (exit 1) and takes the robot out of service; charged over
    // the least (not yet the resume threshold), it passes, and that ends
    // the maintenance the self-test began. A researcher may not run it.
    let selftest = |user: &str| {
        crate::support::subsume()
            .args(["lab", "selftest", &lab.address])
            .env("SUBSUME_USER", user)
            .env("SUBSUME_PASSWORD", PASSWORD)
            .output()
            .unwrap()
    };
    controller.set(10_400);
    std::thread::sleep(Duration::from_millis(300));
    let failed = selftest("boss");
    let said = String::from_utf8_lossy(&failed.stdout);
    assert_eq!(failed.status.code(), Some(1), "{said}{}", String::from_utf8_lossy(&failed.stderr));
    assert!(said.contains("FAIL battery: link 'motors': battery 10.40 V is under 11.00 V"), "{said}");
    assert!(said.contains("ok   feedback: link 'motors'"), "{said}");
    let (_, overview) = lab.call(&boss, "GET", "/api/v1/lab", "");
    assert_eq!(overview["lab"]["maintenance"]["by"], "self-test", "{overview:#}");
    controller.set(11_500);
    std::thread::sleep(Duration::from_millis(300));
    let passed = selftest("boss");
    let said = String::from_utf8_lossy(&passed.stdout);
    assert!(passed.status.success(), "{said}{}", String::from_utf8_lossy(&passed.stderr));
    assert!(
        said.contains("ok   battery: link 'motors': battery 11.50 V") && said.contains("the self-test passed"),
        "{said}"
    );
    let (_, overview) = lab.call(&boss, "GET", "/api/v1/lab", "");
    assert!(overview["lab"]["maintenance"].is_null(), "{overview:#}");
    let tests = overview["lab"]["self_tests"].as_array().unwrap();
    assert_eq!(tests.last().unwrap()["experiment"], Json::Null, "{tests:#?}");
    let refused = selftest("ana");
    assert!(!refused.status.success());
    assert!(String::from_utf8_lossy(&refused.stderr).contains("may not run the self-test"), "{refused:?}");
    controller.stop();
}

/// Issue 40: a real robot whose motor controller (a pseudo-terminal
/// playing it on the ascii profile, which reports its fault status with
/// `F`) goes into fault during a run: the self-test after it fails its
/// "controller" check, naming the fault, and takes the robot out of
/// service until an admin brings it back (a fault does not clear by
/// itself, as a low battery does); the next experiment waits. The owner's
/// settings need nothing for it: the check is on by default.
#[test]
fn a_motor_controller_reporting_a_fault_fails_the_self_test_and_puts_the_robot_in_maintenance() {
    let dir = tempfile::tempdir().unwrap();
    let (motors, _slave, device) = crate::support::MotorRecorder::new();
    let real = |goal_x: f64| real_robot(goal_x, &device);
    // The controller's fault, as the test sets it (none: an empty F line).
    let controller = PlayedController::start(motors, String::new(), |fault| format!("P 12400\nF {fault}\n"));
    let (lab, ana, boss, mut settings) = lab_on_a_played_robot(dir.path(), &real(8.0));
    settings["self_test"] = serde_json::json!({"window_ms": 1000, "min_battery_v": 11.0, "resume_battery_v": 12.2});
    let (status, json) = lab.call(&boss, "PUT", "/api/v1/lab/settings", &settings.to_string());
    assert_eq!(status, 200, "{json}");
    let (_, overview) = lab.call(&boss, "GET", "/api/v1/lab", "");
    assert_eq!(overview["lab"]["settings"]["self_test"]["controller_faults"], true, "on by default: {overview:#}");
    let set = lab.stage(&ana, "ana.xml", &real(7.0));
    let submit = || lab.submit(&ana, set, 2.0);
    let reset = |id: u64| lab.reset_when_awaited(&ana, &boss, id);
    // A healthy controller: the check passes, saying the link reads no fault.
    let first = submit();
    reset(first);
    assert_eq!(lab.wait_for(&ana, first, "done", Duration::from_secs(120))["state"], "done");
    let (_, overview) = lab.call(&boss, "GET", "/api/v1/lab", "");
    let tests = overview["lab"]["self_tests"].as_array().unwrap().clone();
    assert_eq!((tests.len(), &tests[0]["passed"]), (1, &Json::Bool(true)), "{tests:#?}");
    let controller_check = |test: &Json| {
        test["checks"].as_array().unwrap().iter().find(|c| c["check"] == "controller").cloned().unwrap_or_default()
    };
    assert_eq!(controller_check(&tests[0])["detail"], "link 'motors': no fault", "{tests:#?}");
    // The controller goes into fault during the next run: it still ends
    // `done`; the self-test after it fails, and the robot is out of service.
    let second = submit();
    reset(second);
    controller.set("m1 over current warning".into());
    assert_eq!(lab.wait_for(&ana, second, "done", Duration::from_secs(120))["state"], "done");
    let (_, overview) = lab.call(&boss, "GET", "/api/v1/lab", "");
    let tests = overview["lab"]["self_tests"].as_array().unwrap();
    assert_eq!((tests.len(), &tests[1]["passed"]), (2, &Json::Bool(false)), "{tests:#?}");
    let failed = controller_check(&tests[1]);
    assert_eq!(failed["passed"], false, "{failed:#}");
    assert_eq!(failed["detail"], "link 'motors': the motor controller reports m1 over current warning", "{failed:#}");
    let maintenance = overview["lab"]["maintenance"].clone();
    assert_eq!(maintenance["by"], "self-test", "{overview:#}");
    let reason = maintenance["reason"].as_str().unwrap();
    assert!(reason.contains(&format!("the self-test after experiment {second} failed")), "{reason}");
    assert!(reason.contains("controller: link 'motors': the motor controller reports m1 over current"), "{reason}");
    assert_eq!(maintenance["ends_at_battery_v"], Json::Null, "a fault needs an admin: {maintenance:#}");
    // Out of service: the next experiment waits, even once the fault has
    // cleared (an admin runs the self-test again to bring the robot back).
    let third = submit();
    // (queued once its preflight passed: on a busy machine that takes more
    // than the 2 s below)
    assert_eq!(lab.wait_for(&ana, third, "queued", Duration::from_secs(120))["state"], "queued");
    controller.set(String::new());
    std::thread::sleep(Duration::from_secs(2));
    assert_eq!(lab.experiment(&ana, third)["state"], "queued");
    let (_, overview) = lab.call(&boss, "GET", "/api/v1/lab", "");
    assert!(overview["lab"]["held"].as_str().unwrap_or_default().contains("maintenance"), "{overview:#}");
    controller.stop();
}

/// The self-test's motion check (docs/lab.md, "Self-test"): a controller
/// whose odometry never moves while the baseline's planner drives (a motor
/// that does not answer) fails it after the run, naming the distances, and
/// the robot goes out of service; an odometry ratio out of range is
/// refused by name. The serial link counts what its commands asked for
/// and what the odometry showed (`commanded_m`, `odometry_m` in its
/// status).
#[test]
fn a_motor_that_does_not_answer_fails_the_self_tests_motion_check() {
    let dir = tempfile::tempdir().unwrap();
    let (motors, _slave, device) = crate::support::MotorRecorder::new();
    let real = |goal_x: f64| real_robot(goal_x, &device);
    // Odometry stuck at (1, 1), whatever the motors are told.
    let controller = PlayedController::start(motors, (), |_| String::new());
    let (lab, ana, boss, mut settings) = lab_on_a_played_robot(dir.path(), &real(8.0));
    settings["self_test"] = serde_json::json!({"window_ms": 1000, "odometry_ratio": 1.5});
    let (status, json) = lab.call(&boss, "PUT", "/api/v1/lab/settings", &settings.to_string());
    assert_eq!(status, 400, "{json}");
    assert!(
        json["error"].as_str().unwrap().contains("self_test.odometry_ratio must be above 0 and at most 1, got 1.5"),
        "{json}"
    );
    settings["self_test"] = serde_json::json!({"window_ms": 1000, "odometry_ratio": 0.5});
    let (status, json) = lab.call(&boss, "PUT", "/api/v1/lab/settings", &settings.to_string());
    assert_eq!(status, 200, "{json}");
    let set = lab.stage(&ana, "ana.xml", &real(7.0));
    let id = lab.submit(&ana, set, 2.0);
    lab.reset_when_awaited(&ana, &boss, id);
    assert_eq!(lab.wait_for(&ana, id, "done", Duration::from_secs(120))["state"], "done");
    let deadline = Instant::now() + Duration::from_secs(30);
    let overview = loop {
        let (_, overview) = lab.call(&boss, "GET", "/api/v1/lab", "");
        if overview["lab"]["self_tests"].as_array().is_some_and(|t| !t.is_empty()) {
            break overview;
        }
        assert!(Instant::now() < deadline, "no self-test after the run: {overview:#}");
        std::thread::sleep(Duration::from_millis(100));
    };
    let test = &overview["lab"]["self_tests"][0];
    let motion =
        test["checks"].as_array().unwrap().iter().find(|c| c["check"] == "motion").cloned().unwrap_or_default();
    assert_eq!((&test["passed"], &motion["passed"]), (&Json::Bool(false), &Json::Bool(false)), "{test:#}");
    let detail = motion["detail"].as_str().unwrap_or_default();
    assert!(
        detail.starts_with("link 'motors': ")
            && detail.contains(" m commanded, the odometry shows 0.00 m in 1.0 s, outside 0.50 to 2.00 of it"),
        "{test:#}"
    );
    let maintenance = &overview["lab"]["maintenance"];
    assert_eq!(maintenance["by"], "self-test", "{overview:#}");
    assert!(maintenance["reason"].as_str().unwrap().contains("motion: link 'motors': "), "{overview:#}");
    controller.stop();
}

/// Many at once: six researchers change their own mail subscriptions
/// (subscribe with a new address, or unsubscribe) while two admins take the
/// robot out of service and back, forty times each. Nothing is lost: each
/// researcher ends with exactly the subscription she last asked for, and
/// the maintenance state, the successful starts and ends, and their audit
/// lines agree.
#[test]
fn concurrent_mail_subscriptions_and_maintenance_lose_nothing() {
    let dir = tempfile::tempdir().unwrap();
    setup(dir.path());
    let store = dir.path().join("store");
    let users: Vec<String> = (0..6).map(|n| format!("user{n}")).collect();
    for user in &users {
        crate::support::add_user(&store, user, "researcher", &["control"], PASSWORD);
    }
    crate::support::add_user(&store, "boss2", "admin", &[], PASSWORD);
    // Mail configured (never sent here: no experiment runs).
    let config = serde_json::json!({
        "server": "127.0.0.1", "port": 9, "security": "plain",
        "from": "lab@robots.example.org", "owner": [],
    });
    std::fs::write(store.join("mail.json"), config.to_string()).unwrap();
    let lab = start(dir.path());
    const ROUNDS: usize = 40;
    let subscribers: Vec<(String, String)> = users.iter().map(|u| (u.clone(), lab.token(u))).collect();
    let admins = [lab.token("boss"), lab.token("boss2")];
    let (last, toggles) = std::thread::scope(|scope| {
        let mail: Vec<_> = subscribers
            .iter()
            .map(|(user, token)| {
                let lab = &lab;
                scope.spawn(move || {
                    let mut last = None;
                    for round in 0..ROUNDS {
                        // Two subscriptions, then an unsubscription, in turn.
                        if round % 3 == 2 {
                            let (status, json) = lab.call(token, "DELETE", "/api/v1/lab/mail", "");
                            assert_eq!(status, 200, "{user}: {json}");
                            last = None;
                        } else {
                            let address = format!("{user}-{round}@example.org");
                            let body = serde_json::json!({ "address": address, "events": ["experiment.ended"] });
                            let (status, json) = lab.call(token, "PUT", "/api/v1/lab/mail", &body.to_string());
                            assert_eq!(status, 200, "{user}: {json}");
                            last = Some(address);
                        }
                    }
                    (user.clone(), last)
                })
            })
            .collect();
        let maintenance: Vec<_> = admins
            .iter()
            .enumerate()
            .map(|(a, token)| {
                let lab = &lab;
                scope.spawn(move || {
                    let (mut started, mut ended) = (0usize, 0usize);
                    for round in 0..ROUNDS {
                        let (status, json) = if round % 2 == 0 {
                            let body = serde_json::json!({ "reason": format!("admin {a}, round {round}") });
                            lab.call(token, "POST", "/api/v1/lab/maintenance", &body.to_string())
                        } else {
                            lab.call(token, "DELETE", "/api/v1/lab/maintenance", "")
                        };
                        match (round % 2, status) {
                            (0, 200) => started += 1,
                            (1, 200) => ended += 1,
                            (_, 409) => {}
                            _ => panic!("admin {a}, round {round}: {status} {json}"),
                        }
                    }
                    (started, ended)
                })
            })
            .collect();
        let last: Vec<(String, Option<String>)> = mail.into_iter().map(|t| t.join().unwrap()).collect();
        let toggles: Vec<(usize, usize)> = maintenance.into_iter().map(|t| t.join().unwrap()).collect();
        (last, toggles)
    });
    for ((user, wanted), (_, token)) in last.iter().zip(&subscribers) {
        let (status, json) = lab.call(token, "GET", "/api/v1/lab/mail", "");
        assert_eq!(status, 200, "{json}");
        assert_eq!(json["mail"]["address"].as_str(), wanted.as_deref(), "{user}: {json}");
    }
    let started: usize = toggles.iter().map(|t| t.0).sum();
    let ended: usize = toggles.iter().map(|t| t.1).sum();
    let (_, overview) = lab.call(&admins[0], "GET", "/api/v1/lab", "");
    let inside = !overview["lab"]["maintenance"].is_null();
    assert_eq!(started, ended + usize::from(inside), "{started} starts, {ended} ends, in maintenance: {inside}");
    assert!(started >= 1, "no admin ever took the robot out");
    let (_, audit) = lab.call(&admins[0], "GET", "/api/v1/audit", "");
    let count = |action: &str| {
        audit["entries"].as_array().unwrap().iter().filter(|e| e["action"] == action && e["result"] == "ok").count()
    };
    assert_eq!((count("maintenance-start"), count("maintenance-end")), (started, ended), "{audit:#}");
}

/// The reset set of the lab's baseline: the same robot, with the planner
/// replaced by the homing component (uploaded as `homing`) driving to
/// (`x`, `y`, `heading`).
fn reset_robot(x: f64, y: f64, heading: f64) -> String {
    let planner = format!(r#"source="{}""#, crate::support::guest("planner").display());
    let goal = r#"<param name="goal-x" value="8"/>
      <param name="goal-y" value="1.0"/>"#;
    let xml = robot(8.0, "");
    assert!(xml.contains(&planner) && xml.contains(goal), "the baseline's planner changed: {xml}");
    xml.replace(&planner, r#"source="homing.wasm""#).replace(
        goal,
        &format!(
            r#"<param name="goal-x" value="{x}"/>
      <param name="goal-y" value="{y}"/>
      <param name="goal-heading" value="{heading}"/>
      <param name="tolerance" value="0.1"/>
      <param name="heading-tolerance" value="0.1"/>
      <param name="max-speed" value="0.5"/>
      <param name="max-turn" value="1.5"/>"#
        ),
    )
}

/// The simulated robot's pose as the portal's live status shows it.
fn sim_pose(lab: &Lab, token: &str) -> (f64, f64, f64) {
    let (status, json) = lab.call(token, "GET", "/api/v1/status", "");
    assert_eq!(status, 200, "{json}");
    let sim = &json["sim"];
    (
        sim["x"].as_f64().unwrap_or(f64::NAN),
        sim["y"].as_f64().unwrap_or(f64::NAN),
        sim["heading"].as_f64().unwrap_or(f64::NAN),
    )
}

/// Issue 40, reset by driving: with the `drive` policy, before each
/// experiment the owner's reset set (the homing component above the
/// avoider, under the robot's own envelope) drives the simulated robot
/// back from wherever the baseline left it (nothing resets the simulated
/// world) to the start pose; the outcome is on the record, and the
/// experiment starts there (the preflight's simulated robot too). A
/// reset that cannot reach its pose in time takes the robot out of
/// service `by: reset`, and leaves the experiment queued, the baseline running; fixed
/// and back in service, the experiment runs. Bad settings are refused by
/// name.
#[test]
fn a_drive_reset_brings_the_robot_back_before_each_experiment_and_one_that_cannot_takes_it_out_of_service() {
    let dir = tempfile::tempdir().unwrap();
    setup(dir.path());
    let lab = start(dir.path());
    let (ana, boss) = (lab.token("ana"), lab.token("boss"));
    let baseline = lab.active_set(&boss);
    let homing = std::fs::read(crate::support::guest("homing")).unwrap();
    let (status, json) = http(&lab.address, "PUT", "/api/v1/platforms/control/components/homing", Some(&boss), &homing);
    assert_eq!(status, 201, "{json}");
    let reset_set = lab.stage(&boss, "reset.xml", &reset_robot(1.0, 1.0, 0.0));
    // A reset set that loosens the envelope is not one.
    let envelope = r#"<component name="envelope" source="builtin:envelope" rate="20">"#;
    let loose =
        reset_robot(1.0, 1.0, 0.0).replace(envelope, &format!(r#"{envelope}<param name="max-speed" value="2.0"/>"#));
    assert_ne!(loose, reset_robot(1.0, 1.0, 0.0));
    let loose_set = lab.stage(&boss, "loose.xml", &loose);
    let (_, overview) = lab.call(&boss, "GET", "/api/v1/lab", "");
    let mut settings = overview["lab"]["settings"].clone();
    let drive = |set: u64, x: f64, y: f64, timeout_s: u64| {
        serde_json::json!({
            "set": set, "pose": {"x": x, "y": y, "heading": 0.0},
            "tolerance": {"position_m": 0.3, "heading_rad": 0.3}, "timeout_s": timeout_s, "settle_s": 1.0
        })
    };
    settings["reset"] = Json::String("drive".into());
    let refused = [
        (Json::Null, "reset: drive needs drive_reset"),
        (drive(reset_set, 1.0, 1.0, 0), "drive_reset.timeout_s must be from 1 to 600, got 0"),
        (drive(9999, 1.0, 1.0, 60), "drive_reset.set: "),
        (drive(loose_set, 1.0, 1.0, 60), "an experiment runs with the robot's own envelope settings"),
    ];
    for (given, expected) in refused {
        settings["drive_reset"] = given;
        let (status, json) = lab.call(&boss, "PUT", "/api/v1/lab/settings", &settings.to_string());
        assert_eq!(status, 400, "{expected}: {json}");
        assert!(json["error"].as_str().unwrap().contains(expected), "{expected}: {json}");
    }
    settings["drive_reset"] = drive(reset_set, 1.0, 1.0, 90);
    let (status, json) = lab.call(&ana, "PUT", "/api/v1/lab/settings", &settings.to_string());
    assert_eq!(status, 403, "{json}");
    let (status, json) = lab.call(&boss, "PUT", "/api/v1/lab/settings", &settings.to_string());
    assert_eq!(status, 200, "{json}");
    // The preflight (and the kit, which is the baseline in the preflight's
    // form) starts the simulated robot at the start pose.
    let out = dir.path().join("results");
    std::fs::create_dir_all(&out).unwrap();
    let kit = fetch_kit(&lab, &boss, &out);
    let world = std::fs::read_to_string(kit.join("files/robot-sim-world-lab.world")).unwrap();
    assert!(world.contains("start 1 1 0 # the lab's reset pose") && !world.contains("start 1 1 0\n"), "{world}");
    // The baseline drives the robot away from the start, toward (8, 1).
    let wait_driven_away = || {
        let deadline = Instant::now() + Duration::from_secs(120);
        while sim_pose(&lab, &boss).0 < 3.0 {
            assert!(Instant::now() < deadline, "the baseline never drove away: {:?}", sim_pose(&lab, &boss));
            std::thread::sleep(Duration::from_millis(100));
        }
    };
    wait_driven_away();
    let set = lab.stage(&ana, "ana.xml", &robot(6.0, ""));
    let submit = || {
        let body = serde_json::json!({ "set": set, "duration_s": 3 }).to_string();
        let (status, json) = lab.call(&ana, "POST", "/api/v1/experiments", &body);
        assert_eq!(status, 201, "{json}");
        json["experiment"]["id"].as_u64().unwrap()
    };
    let first = submit();
    let done = lab.wait_for(&ana, first, "done", Duration::from_secs(240));
    assert_eq!(done["state"], "done", "{done:#}");
    let reset = &done["reset"];
    assert_eq!(reset["passed"], true, "{done:#}");
    let from = (reset["from"]["x"].as_f64().unwrap(), reset["from"]["y"].as_f64().unwrap());
    assert!(from.0 >= 3.0, "the reset began where the baseline left the robot: {reset}");
    let (x, y, heading) = (
        reset["pose"]["x"].as_f64().unwrap(),
        reset["pose"]["y"].as_f64().unwrap(),
        reset["pose"]["heading"].as_f64().unwrap(),
    );
    assert!((x - 1.0).hypot(y - 1.0) <= 0.3 && heading.sin().atan2(heading.cos()).abs() <= 0.3, "{reset}");
    // Driving 2 m and more at most 0.5 m/s, then the settle.
    assert!(reset["took_s"].as_f64().unwrap() >= 5.0, "{reset}");
    // The reset came before the run, and the run started at the start pose:
    // its recorded first pose is where the reset ended.
    let bundle = lab.results(&ana, first, &out);
    let recorded = read_mcap(&bundle.join("run.mcap"), false);
    let first_pose = &recorded["first"]["/motors/pose"]["value"];
    let (px, py) = (first_pose[0].as_f64().unwrap(), first_pose[1].as_f64().unwrap());
    assert!((px - x).hypot(py - y) < 0.2, "the run's first pose ({px}, {py}) vs the reset's ({x}, {y})");
    let (_, audit) = lab.call(&boss, "GET", "/api/v1/audit", "");
    let actions: Vec<String> = audit["entries"].as_array().unwrap().iter().map(|e| e["action"].to_string()).collect();
    for action in ["reset-start", "reset-end"] {
        assert!(actions.iter().any(|a| a.contains(action)), "no {action} in {actions:?}");
    }
    assert_eq!(lab.active_set(&boss), baseline);
    // A timeout too short to drive back the 2 m and more the baseline
    // takes the robot away again: the reset cannot make it.
    settings["drive_reset"] = drive(reset_set, 1.0, 1.0, 1);
    let (status, json) = lab.call(&boss, "PUT", "/api/v1/lab/settings", &settings.to_string());
    assert_eq!(status, 200, "{json}");
    wait_driven_away();
    let second = submit();
    let deadline = Instant::now() + Duration::from_secs(240);
    let maintenance = loop {
        let (_, overview) = lab.call(&boss, "GET", "/api/v1/lab", "");
        if !overview["lab"]["maintenance"].is_null() {
            break overview["lab"]["maintenance"].clone();
        }
        assert!(
            Instant::now() < deadline,
            "the failed reset never took the robot out: {overview:#}\n{}",
            lab.host.log()
        );
        std::thread::sleep(Duration::from_millis(100));
    };
    assert_eq!(maintenance["by"], "reset", "{maintenance:#}");
    let reason = maintenance["reason"].as_str().unwrap();
    assert!(reason.contains(&format!("the reset before experiment {second} failed")), "{reason}");
    assert!(
        reason.contains("after 1 s, not at the start pose (1.00, 1.00, 0.00 rad) within 0.30 m and 0.30 rad"),
        "{reason}"
    );
    let waiting = lab.experiment(&ana, second);
    assert_eq!(waiting["state"], "queued", "{waiting:#}");
    assert_eq!(waiting["reset"]["passed"], false, "{waiting:#}");
    assert_eq!(lab.active_set(&boss), baseline, "the baseline runs again after the failed reset");
    std::thread::sleep(Duration::from_secs(2));
    assert_eq!(lab.experiment(&ana, second)["state"], "queued");
    // Fixed, and back in service: the experiment runs, from the start.
    settings["drive_reset"] = drive(reset_set, 1.0, 1.0, 90);
    let (status, json) = lab.call(&boss, "PUT", "/api/v1/lab/settings", &settings.to_string());
    assert_eq!(status, 200, "{json}");
    let (status, json) = lab.call(&boss, "DELETE", "/api/v1/lab/maintenance", "");
    assert_eq!(status, 200, "{json}");
    let done = lab.wait_for(&ana, second, "done", Duration::from_secs(240));
    assert_eq!((&done["state"], &done["reset"]["passed"]), (&Json::from("done"), &Json::Bool(true)), "{done:#}");
}

/// Issue 41, a task and a score anyone recomputes: with the owner's task
/// (reach a goal; ranked by the time to it), every run's score is computed
/// from its recording when it ends, kept on the record (its outcome, beside
/// its state) and in its bundle (`task.json`, `score.json`). `subsume score`
/// recomputes it from the bundle alone, bit for bit, and says when the
/// bundle's score differs; a scorer no one here wrote (Python over the
/// `mcap` package) finds the same path length, time to the goal and
/// energy. The preflight's score of the same task (the simulator's side)
/// is kept and recomputed beside it, with the gap between the two. The
/// task's leaderboard ranks the run, under its submitter's name for her
/// and admins, a pseudonym for others, over the API and in the portal's
/// Lab tab in Chromium. A bad task is refused by name.
#[test]
fn a_runs_score_against_the_owners_task_is_in_its_bundle_and_anyone_recomputes_it_bit_for_bit() {
    let dir = tempfile::tempdir().unwrap();
    setup(dir.path());
    let lab = start(dir.path());
    let (ana, boss) = (lab.token("ana"), lab.token("boss"));
    let (_, overview) = lab.call(&boss, "GET", "/api/v1/lab", "");
    let mut settings = overview["lab"]["settings"].clone();
    let task = serde_json::json!({
        "name": "reach-6", "description": "drive from (1, 1) to (6, 1)",
        "goal": {"x": 6.0, "y": 1.0, "radius": 0.4}, "metric": "time_to_goal"
    });
    let refused = [
        ("name", serde_json::json!("Reach 6"), "task.name must be 1 to 64 of a-z, 0-9 and '-', got 'Reach 6'"),
        ("pose", serde_json::json!("motors"), "task.pose must name an output port as COMPONENT.PORT, got 'motors'"),
        ("metric", serde_json::json!("speed"), "unknown variant `speed`"),
    ];
    for (field, value, expected) in refused {
        let mut bad = task.clone();
        bad[field] = value;
        settings["task"] = bad;
        let (status, json) = lab.call(&boss, "PUT", "/api/v1/lab/settings", &settings.to_string());
        assert!(status == 400 || status == 422, "{field}: {status} {json}");
        assert!(json.to_string().contains(expected), "{field}: {json}");
    }
    settings["task"] = task.clone();
    let (status, json) = lab.call(&boss, "PUT", "/api/v1/lab/settings", &settings.to_string());
    assert_eq!(status, 200, "{json}");
    // The kit carries the task: a researcher scores her local run as the
    // lab will (the baseline's planner passes through the goal).
    let local = dir.path().join("local");
    std::fs::create_dir_all(&local).unwrap();
    let kit = fetch_kit(&lab, &ana, &local);
    let kit_task: Json = serde_json::from_slice(&std::fs::read(kit.join("task.json")).unwrap()).unwrap();
    assert_eq!((&kit_task["name"], &kit_task["goal"]), (&task["name"], &task["goal"]), "{kit_task:#}");
    let ran = crate::support::subsume()
        .arg("run")
        .arg(kit.join("robot.xml"))
        .args(["--http", "off", "--speed", "max", "--duration", "25", "--record"])
        .arg(kit.join("run.mcap"))
        .output()
        .unwrap();
    assert!(ran.status.success(), "{}", String::from_utf8_lossy(&ran.stderr));
    let scored = crate::support::subsume().arg("score").arg(&kit).output().unwrap();
    let said = String::from_utf8_lossy(&scored.stdout);
    assert!(scored.status.success(), "{said}{}", String::from_utf8_lossy(&scored.stderr));
    assert!(said.contains("run: task reach-6: time_to_goal_s = ") && said.contains("goal_reached = 1"), "{said}");
    assert!(said.contains("score.json is not in the bundle: nothing to compare"), "{said}");
    let set = lab.stage(&ana, "ana.xml", &robot(6.0, ""));
    let (id, done) = lab.run_to_done(&ana, set, 25.0);
    let score = done["score"].clone();
    assert_eq!((&score["task"], &score["metric"]), (&Json::from("reach-6"), &Json::from("time_to_goal")), "{done:#}");
    assert_eq!(score["sub_scores"]["goal_reached"], 1.0, "{score:#}");
    let to_goal = score["value"].as_f64().unwrap();
    assert!((5.0..25.0).contains(&to_goal), "{score:#}");
    assert_eq!(score["sub_scores"]["time_to_goal_s"].as_f64(), Some(to_goal));
    // The bundle holds the task and the score the record shows.
    let out = dir.path().join("results");
    std::fs::create_dir_all(&out).unwrap();
    let bundle = lab.results(&ana, id, &out);
    let kept: Json = serde_json::from_slice(&std::fs::read(bundle.join("score.json")).unwrap()).unwrap();
    assert_eq!(kept, score);
    let kept_task: Json = serde_json::from_slice(&std::fs::read(bundle.join("task.json")).unwrap()).unwrap();
    assert_eq!(kept_task["goal"], task["goal"], "{kept_task:#}");
    // Anyone recomputes it from the bundle, with no network: bit for bit.
    let rescore = |folder: &Path| crate::support::subsume().arg("score").arg(folder).output().unwrap();
    let again = rescore(&bundle);
    let said = String::from_utf8_lossy(&again.stdout);
    assert!(again.status.success() && said.contains("identical"), "{said}{}", String::from_utf8_lossy(&again.stderr));
    assert!(said.contains(&format!("time_to_goal_s = {to_goal}")), "{said}");
    // An independent scorer over the same recording finds the same numbers.
    let independent = Command::new(crate::support::python())
        .arg(crate::support::repo_root().join("tests/python/score_check.py"))
        .arg(bundle.join("run.mcap"))
        .arg(bundle.join("task.json"))
        .output()
        .unwrap();
    assert!(independent.status.success(), "{}", String::from_utf8_lossy(&independent.stderr));
    let found: Json = serde_json::from_slice(&independent.stdout).unwrap();
    assert_eq!(found["poses"], score["poses"], "{found} vs {score}");
    for name in ["path_length_m", "goal_reached", "time_to_goal_s", "energy"] {
        let (ours, theirs) = (score["sub_scores"][name].as_f64().unwrap(), found[name].as_f64().unwrap());
        assert!((ours - theirs).abs() <= 1e-9 * ours.abs().max(1.0), "{name}: {ours} vs {theirs}");
    }
    assert!(score["sub_scores"]["path_length_m"].as_f64().unwrap() > 4.5, "{score:#}");
    // The preflight's score, from its simulated run of the same task,
    // beside the robot's: on the record, in the bundle, recomputed too.
    let preflight = done["preflight"]["score"].clone();
    assert_eq!(preflight["sub_scores"]["goal_reached"], 1.0, "{done:#}");
    let kept: Json = serde_json::from_slice(&std::fs::read(bundle.join("preflight-score.json")).unwrap()).unwrap();
    assert_eq!(kept, preflight);
    let simulated = preflight["value"].as_f64().unwrap();
    assert!(said.contains("identical: ") && said.contains("preflight-score.json matches"), "{said}");
    assert!(said.contains(&format!("time_to_goal_s: robot {to_goal}, simulator {simulated}, gap")), "{said}");
    // The leaderboard: ana's run ranked first; ana sees her name and
    // experiment, ben a pseudonym and no id, an admin both.
    let board = |token: &str, name: &str| lab.call(token, "GET", &format!("/api/v1/tasks/{name}/leaderboard"), "");
    let (status, json) = board(&ana, "reach-6");
    assert_eq!(status, 200, "{json}");
    let entry = &json["leaderboard"]["entries"][0];
    assert_eq!(
        (&entry["rank"], &entry["user"], &entry["experiment"]),
        (&Json::from(1), &Json::from("ana"), &Json::from(id))
    );
    assert_eq!((&entry["value"], &json["leaderboard"]["better"]), (&Json::from(to_goal), &Json::from("lower")));
    assert_eq!(entry["preflight_value"].as_f64(), Some(simulated));
    // The recording the score came from is the bundle's run.mcap.
    let sums = std::fs::read_to_string(bundle.join("SHA256SUMS")).unwrap();
    let recording = entry["recording_sha256"].as_str().unwrap();
    assert!(sums.contains(&format!("{recording}  run.mcap")), "{recording} not in {sums}");
    let ben = lab.token("ben");
    let (_, json) = board(&ben, "reach-6");
    let entry = &json["leaderboard"]["entries"][0];
    assert_eq!(
        (&entry["user"], entry.get("experiment"), &entry["yours"]),
        (&Json::from("participant-1"), None, &Json::Bool(false))
    );
    assert!(!json.to_string().contains("ana"), "{json}");
    let (_, json) = board(&boss, "reach-6");
    assert_eq!(json["leaderboard"]["entries"][0]["user"], "ana");
    let (status, json) = board(&ben, "other");
    assert_eq!((status, json["error"].as_str()), (404, Some("no task 'other' in this lab")), "{json}");
    let (status, _) = http(&lab.address, "GET", "/api/v1/tasks/reach-6/leaderboard", None, b"");
    assert_eq!(status, 401);
    // The same in the portal's Lab tab, in Chromium.
    lab.board_in_chromium("ana", "ben", id);
    // A bundle whose score was changed is caught.
    let changed = std::fs::read_to_string(bundle.join("score.json")).unwrap().replacen(&to_goal.to_string(), "1.5", 1);
    std::fs::write(bundle.join("score.json"), changed).unwrap();
    let caught = rescore(&bundle);
    assert_eq!(caught.status.code(), Some(1), "{}", String::from_utf8_lossy(&caught.stdout));
    assert!(String::from_utf8_lossy(&caught.stdout).contains("differs"));
    // A folder without a task says which file it lacks.
    std::fs::remove_file(bundle.join("task.json")).unwrap();
    let lost = rescore(&bundle);
    let said = String::from_utf8_lossy(&lost.stderr);
    assert!(!lost.status.success() && said.contains("task.json") && said.contains("No such file"), "{said}");
}

/// Issue 41, a task scored by a component: the owner uploads a scoring
/// component (the `scorer` world) like any other and pins its sha256 in
/// the task; a task pinning other bytes, or a component of another world,
/// is refused by name. A run's score is the component's (its metric
/// `scorer`, its sub-scores), the bundle and the lab kit carry its bytes
/// (`scorer.wasm`), and `subsume score` recomputes the same bits from the
/// bundle alone. A scorer that traps gives the run no score, and its
/// record says why.
#[test]
fn a_task_scored_by_a_component_scores_every_run_and_the_bundle_carries_the_scorer() {
    let dir = tempfile::tempdir().unwrap();
    setup(dir.path());
    let lab = start(dir.path());
    let (ana, boss) = (lab.token("ana"), lab.token("boss"));
    let uploaded = |name: &str, guest: &str| {
        let bytes = std::fs::read(crate::support::guest(guest)).unwrap();
        let path = format!("/api/v1/platforms/control/components/{name}");
        let (status, json) = http(&lab.address, "PUT", &path, Some(&boss), &bytes);
        assert_eq!(status, 201, "{json}");
        json
    };
    let scorer = uploaded("goal-distance", "scorer-goal-distance");
    assert_eq!(scorer["world"], "scorer", "{scorer:#}");
    let sha256 = scorer["sha256"].as_str().unwrap().to_string();
    let hostile = uploaded("hostile", "test-scorer-hostile");
    let avoider = uploaded("avoid", "avoider");
    let (_, overview) = lab.call(&boss, "GET", "/api/v1/lab", "");
    let mut settings = overview["lab"]["settings"].clone();
    let task = |name: &str, component: &str, pinned: &str| {
        serde_json::json!({
            "name": name, "goal": {"x": 6.0, "y": 1.0, "radius": 0.4}, "metric": "scorer",
            "scorer": {"component": component, "sha256": pinned}
        })
    };
    let other = "0".repeat(64);
    let refused = [
        (
            task("reach-6", "boss/goal-distance", &other),
            format!("is stored with sha256 {sha256}, but the task pins {other}"),
        ),
        (
            task("reach-6", "boss/avoid", avoider["sha256"].as_str().unwrap()),
            "'boss/avoid' is not a scoring component (it fits the component world".to_string(),
        ),
        (task("reach-6", "boss/nothing", &sha256), "task.scorer: no component 'boss/nothing' in the store".to_string()),
        (
            serde_json::json!({"name": "reach-6", "goal": {"x": 6.0, "y": 1.0, "radius": 0.4}, "metric": "scorer"}),
            "task.scorer must name the scoring component".to_string(),
        ),
    ];
    for (bad, expected) in refused {
        settings["task"] = bad;
        let (status, json) = lab.call(&boss, "PUT", "/api/v1/lab/settings", &settings.to_string());
        assert_eq!(status, 400, "{json}");
        assert!(json.to_string().contains(&expected), "{expected}: {json}");
    }
    settings["task"] = task("reach-6", "boss/goal-distance", &sha256);
    let (status, json) = lab.call(&boss, "PUT", "/api/v1/lab/settings", &settings.to_string());
    assert_eq!(status, 200, "{json}");
    // The kit carries the scorer's bytes.
    let local = dir.path().join("local");
    std::fs::create_dir_all(&local).unwrap();
    let kit = fetch_kit(&lab, &ana, &local);
    assert_eq!(
        std::fs::read(kit.join("scorer.wasm")).unwrap(),
        std::fs::read(crate::support::guest("scorer-goal-distance")).unwrap()
    );
    // A run, scored by the component, with the kit turned off now: the
    // scorer is public all the same (docs/lab.md: a score anyone recomputes).
    settings["kit"] = Json::Bool(false);
    let (status, json) = lab.call(&boss, "PUT", "/api/v1/lab/settings", &settings.to_string());
    assert_eq!(status, 200, "{json}");
    let set = lab.stage(&ana, "ana.xml", &robot(6.0, ""));
    let (id, done) = lab.run_to_done(&ana, set, 25.0);
    let score = done["score"].clone();
    assert_eq!(
        (&score["metric"], &score["scorer_sha256"]),
        (&Json::from("scorer"), &Json::from(sha256.clone())),
        "{done:#}"
    );
    let sub = |name: &str| score["sub_scores"][name].as_f64().unwrap_or_else(|| panic!("{name}: {score:#}"));
    assert_eq!(sub("reached"), 1.0, "{score:#}");
    assert_eq!(score["value"].as_f64(), Some(sub("final_distance_m") + 0.1 * sub("path_length_m")), "{score:#}");
    assert_eq!(done["preflight"]["score"]["metric"], "scorer", "{done:#}");
    // The bundle carries the scorer; anyone recomputes the score from it.
    let out = dir.path().join("results");
    std::fs::create_dir_all(&out).unwrap();
    let bundle = lab.results(&ana, id, &out);
    let kept: Json = serde_json::from_slice(&std::fs::read(bundle.join("score.json")).unwrap()).unwrap();
    assert_eq!(kept, score);
    let sums = std::fs::read_to_string(bundle.join("SHA256SUMS")).unwrap();
    assert!(sums.contains(&format!("{sha256}  scorer.wasm")), "{sums}");
    let again = crate::support::subsume().arg("score").arg(&bundle).output().unwrap();
    let said = String::from_utf8_lossy(&again.stdout);
    assert!(again.status.success(), "{said}{}", String::from_utf8_lossy(&again.stderr));
    assert!(
        said.contains("identical: ")
            && said.contains("score.json matches")
            && said.contains("preflight-score.json matches"),
        "{said}"
    );
    let (_, json) = lab.call(&ana, "GET", "/api/v1/tasks/reach-6/leaderboard", "");
    assert_eq!(
        (&json["leaderboard"]["metric"], &json["leaderboard"]["better"]),
        (&Json::from("scorer"), &Json::from("lower")),
        "{json}"
    );
    assert_eq!(json["leaderboard"]["entries"][0]["value"], score["value"], "{json}");
    // The run's card and the board in the portal's Lab tab, in Chromium.
    lab.board_in_chromium("ana", "ben", id);
    // A scorer that traps: no score, and the record says why.
    settings["task"] = task("scorer-traps", "boss/hostile", hostile["sha256"].as_str().unwrap());
    let (status, json) = lab.call(&boss, "PUT", "/api/v1/lab/settings", &settings.to_string());
    assert_eq!(status, 200, "{json}");
    let (_, ended) = lab.run_to_done(&ana, set, 25.0);
    assert!(ended["score"].is_null() && ended["preflight"]["score"].is_null(), "{ended:#}");
    let reasons = ended["reasons"].to_string();
    assert!(
        reasons.contains("its run could not be scored: task scorer-traps: its scorer boss/hostile: score() trapped"),
        "{ended:#}"
    );
}

/// Issue 40: an admin's self-test racing the experiments' starts. While
/// experiments follow one another (each with the self-test after it), an
/// admin asks for the self-test again and again, from two threads at once.
/// Each ask either runs on the idle robot and passes, or is refused (409)
/// because an experiment runs or starts, or a self-test runs already; no
/// experiment starts under a self-test (which would see no baseline and
/// fail), so the robot never goes out of service, every experiment ends
/// `done`, and every self-test kept passed.
#[test]
fn an_admins_self_test_racing_the_experiments_starts_never_fails_nor_holds_one_up() {
    let dir = tempfile::tempdir().unwrap();
    setup(dir.path());
    let lab = start(dir.path());
    let (ana, boss) = (lab.token("ana"), lab.token("boss"));
    let (_, overview) = lab.call(&boss, "GET", "/api/v1/lab", "");
    let mut settings = overview["lab"]["settings"].clone();
    // A window long enough that a loaded machine's simulated robot still
    // answers within it (the self-test's own sensitivity is not under test).
    settings["self_test"] = serde_json::json!({"window_ms": 1000});
    let (status, json) = lab.call(&boss, "PUT", "/api/v1/lab/settings", &settings.to_string());
    assert_eq!(status, 200, "{json}");
    let set = lab.stage(&ana, "ana.xml", &robot(6.0, ""));
    let ids: Vec<u64> = (0..3)
        .map(|_| {
            // Longer than the self-test waits for the baseline's status
            // (`selftest::LIVE_WAIT`, 3 s): one started under a self-test
            // would fail it.
            let body = serde_json::json!({ "set": set, "duration_s": 5 }).to_string();
            let (status, json) = lab.call(&ana, "POST", "/api/v1/experiments", &body);
            assert_eq!(status, 201, "{json}");
            json["experiment"]["id"].as_u64().unwrap()
        })
        .collect();
    let finished = std::sync::atomic::AtomicBool::new(false);
    let answers: Vec<(u16, Json)> = std::thread::scope(|scope| {
        let askers: Vec<_> = (0..2)
            .map(|_| {
                scope.spawn(|| {
                    let mut answers = Vec::new();
                    while !finished.load(std::sync::atomic::Ordering::Relaxed) {
                        answers.push(lab.call(&boss, "POST", "/api/v1/lab/selftest", ""));
                    }
                    answers
                })
            })
            .collect();
        for id in &ids {
            let ended = lab.wait_for(&ana, *id, "done", Duration::from_secs(240));
            assert_eq!(ended["state"], "done", "{ended:#}");
        }
        finished.store(true, std::sync::atomic::Ordering::Relaxed);
        askers.into_iter().flat_map(|a| a.join().unwrap()).collect()
    });
    let ran = answers.iter().filter(|(status, _)| *status == 200).count();
    for (status, json) in &answers {
        match status {
            200 => assert_eq!(json["self_test"]["passed"], true, "{json:#}"),
            409 => {
                let why = json["error"].as_str().unwrap_or_default();
                assert!(
                    why.contains("runs on the robot: the self-test runs on the baseline, after it")
                        || why.contains("a self-test runs already"),
                    "{json}"
                );
            }
            _ => panic!("the self-test answered {status}: {json}"),
        }
    }
    assert!(ran >= 2, "only {ran} of {} asks ran", answers.len());
    let (_, overview) = lab.call(&boss, "GET", "/api/v1/lab", "");
    assert!(overview["lab"]["maintenance"].is_null(), "{overview:#}");
    let tests = overview["lab"]["self_tests"].as_array().unwrap();
    assert!(tests.iter().all(|t| t["passed"] == true), "{tests:#?}");
    for id in &ids {
        assert_eq!(lab.experiment(&ana, *id)["state"], "done");
    }
}

/// Issue 41, a task's end conditions: with the owner's task ending runs at
/// its goal (`end_on: ["goal"]`; an unknown condition is refused naming the
/// field), a run whose planner drives through the goal ends there, `done`,
/// long before its duration (the baseline's robot stood near the goal as it
/// started: only poses of the run count), and its outcome says why the
/// episode ended (`goal`) on the record, in the bundle's `experiment.json`
/// and in `lab show`; its preflight ended at the goal too. The recording
/// ends where the run ended, and `subsume score` recomputes the bundle's
/// score bit for bit. A run whose planner stays at the start ends at its
/// duration, `time-out`.
#[test]
fn a_task_ending_runs_at_its_goal_ends_a_run_there_done_and_its_outcome_says_why() {
    let began = Instant::now();
    let dir = tempfile::tempdir().unwrap();
    setup(dir.path());
    let lab = start(dir.path());
    let (ana, boss) = (lab.token("ana"), lab.token("boss"));
    let (_, overview) = lab.call(&boss, "GET", "/api/v1/lab", "");
    let mut settings = overview["lab"]["settings"].clone();
    settings["task"] = serde_json::json!({
        "name": "reach-2", "goal": {"x": 2.0, "y": 2.5, "radius": 0.3}, "metric": "time_to_goal",
        "end_on": ["collision", "arrival"]
    });
    let (status, json) = lab.call(&boss, "PUT", "/api/v1/lab/settings", &settings.to_string());
    assert_eq!(status, 400, "{json}");
    assert!(
        json["error"]
            .as_str()
            .unwrap()
            .contains("task.end_on: unknown end condition 'arrival' (expected goal or collision)"),
        "{json}"
    );
    settings["task"]["end_on"] = serde_json::json!(["goal"]);
    let (status, json) = lab.call(&boss, "PUT", "/api/v1/lab/settings", &settings.to_string());
    assert_eq!(status, 200, "{json}");
    assert_eq!(json["settings"]["task"]["end_on"], serde_json::json!(["goal"]), "{json}");
    // A planner whose own goal is the start (1, 1), so it stays there; and
    // one driving from the start to the task's goal, off the baseline's
    // line (y = 1), so no pose of the robot before a run is in it. The one
    // that stays runs first: the other ends in the goal, where the baseline
    // takes the robot over until the sim's reset.
    let through = robot(2.0, "").replace(r#"name="goal-y" value="1.0""#, r#"name="goal-y" value="2.5""#);
    let through = lab.stage(&ana, "through.xml", &through);
    let stays = lab.stage(&ana, "stays.xml", &robot(1.0, ""));
    let (duration_s, short_s) = (20.0, 2.0);
    let timed_out = lab.submit(&ana, stays, short_s);
    let reached = lab.submit(&ana, through, duration_s);

    // The run that never gets there ends at its duration.
    let done = lab.wait_for(&ana, timed_out, "done", Duration::from_secs(120));
    assert_eq!(done["state"], "done", "{done:#}");
    assert_eq!(done["run"]["outcome"]["ended_by"], "time-out", "{done:#}");
    assert_eq!(done["preflight"]["ended_by"], "time-out", "{done:#}");
    assert_eq!(done["score"]["sub_scores"]["goal_reached"], 0.0, "{done:#}");
    let ran = done["run"]["ran_s"].as_f64().unwrap();
    assert!(ran >= short_s - 0.05, "it ran its whole {short_s} s: {ran} s");

    let done = lab.wait_for(&ana, reached, "done", Duration::from_secs(120));
    assert_eq!(done["state"], "done", "{done:#}");
    let outcome = &done["run"]["outcome"];
    assert_eq!(outcome["ended_by"], "goal", "{done:#}");
    let cause =
        done["history"].as_array().unwrap().iter().find(|c| c["state"] == "finishing").unwrap()["cause"].clone();
    assert_eq!(cause, "the robot reached the task's goal (its end condition goal)", "{done:#}");
    let ran = done["run"]["ran_s"].as_f64().unwrap();
    let score = &done["score"];
    let to_goal = score["sub_scores"]["time_to_goal_s"].as_f64().unwrap();
    assert_eq!(score["sub_scores"]["goal_reached"], 1.0, "{score:#}");
    // It ended at the goal its own poses reached (the recording shows it
    // there), long before its duration; its recording ends shortly after
    // the goal.
    assert!(ran > 1.0 && ran < duration_s / 2.0, "{ran} s of {duration_s}: {done:#}");
    let recorded = score["recorded_s"].as_f64().unwrap();
    assert!(recorded < to_goal + 1.5, "reached at {to_goal} s of a recording of {recorded} s: {done:#}");
    // The preflight ended at the goal in the simulator too.
    let preflight = &done["preflight"];
    assert_eq!(preflight["ended_by"], "goal", "{done:#}");
    assert!(preflight["simulated_s"].as_f64().unwrap() < duration_s / 2.0, "{preflight:#}");
    assert_eq!(preflight["score"]["sub_scores"]["goal_reached"], 1.0, "{preflight:#}");
    // The bundle carries the outcome, and its score recomputes bit for bit.
    let out = dir.path().join("results");
    std::fs::create_dir_all(&out).unwrap();
    let bundle = lab.results(&ana, reached, &out);
    let record: Json = serde_json::from_slice(&std::fs::read(bundle.join("experiment.json")).unwrap()).unwrap();
    assert_eq!(record["run"]["outcome"]["ended_by"], "goal", "{record:#}");
    let kept: Json = serde_json::from_slice(&std::fs::read(bundle.join("score.json")).unwrap()).unwrap();
    assert_eq!(&kept, score);
    let again = crate::support::subsume().arg("score").arg(&bundle).output().unwrap();
    let said = String::from_utf8_lossy(&again.stdout);
    assert!(again.status.success() && said.contains("identical"), "{said}{}", String::from_utf8_lossy(&again.stderr));
    // `lab show` says it on the outcome's line.
    let shown = crate::support::subsume()
        .args(["lab", "show", &reached.to_string(), &lab.address])
        .env("SUBSUME_USER", "ana")
        .env("SUBSUME_PASSWORD", PASSWORD)
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&shown.stdout);
    assert!(shown.status.success(), "{text}{}", String::from_utf8_lossy(&shown.stderr));
    let line = text.lines().find_map(|l| l.trim().strip_prefix("outcome")).unwrap_or_default().trim().to_string();
    assert!(line.starts_with("ended: goal, "), "{text}");
    assert!(text.contains("s simulated in ") && text.contains(", ended: goal\n"), "{text}");
    eprintln!("end conditions: {:.1} s", began.elapsed().as_secs_f64());
}

/// A run's recording holds only the run: the baseline leaves the simulated
/// robot inside the task's goal; the sim's reset puts the experiment's
/// robot back at the start, where a planner whose goal is the start keeps
/// it for 2 s. Its score reaches no goal (no pose from before the run, as
/// the serial link heard it before the reset, is in the recording), and
/// its recording's time line starts at the run's start, as the
/// preflight's does: it is about as long as the run, not as the host's
/// time so far. `subsume score` recomputes it bit for bit.
#[test]
fn a_runs_recording_starts_at_its_start_without_a_pose_of_the_baseline() {
    let began = Instant::now();
    let dir = tempfile::tempdir().unwrap();
    setup(dir.path());
    // The baseline drives into the task's goal at (2, 1) and stays there.
    // Its serial link (the experiment's too, so it is carried over) ticks
    // at 2 Hz: when the run starts, the odometry the link heard since its
    // last tick, from before the sim's reset, is waiting for its next.
    let slow_link =
        |xml: String| xml.replace(r#"source="builtin:serial" rate="100""#, r#"source="builtin:serial" rate="2""#);
    std::fs::write(dir.path().join("robot.xml"), slow_link(robot(2.0, ""))).unwrap();
    let lab = start(dir.path());
    let (ana, boss) = (lab.token("ana"), lab.token("boss"));
    let (_, overview) = lab.call(&boss, "GET", "/api/v1/lab", "");
    let mut settings = overview["lab"]["settings"].clone();
    assert_eq!(settings["reset"], "sim", "{settings:#}");
    settings["task"] = serde_json::json!({
        "name": "reach-2", "goal": {"x": 2.0, "y": 1.0, "radius": 0.4}, "metric": "time_to_goal"
    });
    let (status, json) = lab.call(&boss, "PUT", "/api/v1/lab/settings", &settings.to_string());
    assert_eq!(status, 200, "{json}");
    let deadline = Instant::now() + Duration::from_secs(60);
    while sim_pose(&lab, &boss).0 < 1.7 {
        assert!(Instant::now() < deadline, "the baseline never reached the goal: {:?}", sim_pose(&lab, &boss));
        std::thread::sleep(Duration::from_millis(50));
    }
    let stays = lab.stage(&ana, "stays.xml", &slow_link(robot(1.0, "")));
    let duration_s = 2.0;
    let (id, done) = lab.run_to_done(&ana, stays, duration_s);
    let score = &done["score"];
    assert_eq!(score["sub_scores"]["goal_reached"], 0.0, "{done:#}");
    assert!(score["sub_scores"].get("time_to_goal_s").is_none(), "{score:#}");
    assert!(score["sub_scores"]["path_length_m"].as_f64().unwrap() < 0.05, "{score:#}");
    let ran = done["run"]["ran_s"].as_f64().unwrap();
    let recorded = score["recorded_s"].as_f64().unwrap();
    assert!(recorded <= ran + 0.25 && recorded >= ran - 0.5, "{recorded} s recorded of a {ran} s run: {done:#}");
    let preflight = done["preflight"]["score"]["recorded_s"].as_f64().unwrap();
    assert!((recorded - preflight).abs() < 0.5, "robot {recorded} s, preflight {preflight} s: {done:#}");
    let out = dir.path().join("results");
    std::fs::create_dir_all(&out).unwrap();
    let bundle = lab.results(&ana, id, &out);
    let again = crate::support::subsume().arg("score").arg(&bundle).output().unwrap();
    let said = String::from_utf8_lossy(&again.stdout);
    assert!(again.status.success() && said.contains("identical"), "{said}{}", String::from_utf8_lossy(&again.stderr));
    eprintln!("a run's own recording: {:.1} s", began.elapsed().as_secs_f64());
}

/// The preflight runs three times, each run after the first with the
/// timing a robot has, seeded (docs/lab.md, "Timing"). A set that drives
/// straight at a wall passes the first (the lock-step's perfect timing:
/// the envelope stops it just short of its stop zone) and not the others:
/// it is refused, naming each run and its seed, and its results keep the
/// first refusing run and list every one. That run, rerun from its seed
/// with the bundle's robot file and bounds, gives the lab's verdict byte
/// for byte. The baseline, robust to timing, still passes.
#[test]
fn a_set_that_passes_only_on_perfect_timing_is_refused_naming_its_seeds_and_a_robust_one_passes() {
    let dir = tempfile::tempdir().unwrap();
    setup(dir.path());
    let lab = start(dir.path());
    let ana = lab.token("ana");
    let marginal = lab.stage(&ana, "straight.xml", &straight_at_the_wall());
    let id = lab.submit(&ana, marginal, 30.0);
    let refused = lab.wait_for(&ana, id, "refused", Duration::from_secs(180));
    assert_eq!(states(&refused), ["checking", "preflight", "refused"], "{refused:#}");
    let (second, third) = (subsume::lab::preflight_runs::seed_of(id, 2), subsume::lab::preflight_runs::seed_of(id, 3));
    let reasons: Vec<&str> = refused["reasons"].as_array().unwrap().iter().map(|r| r.as_str().unwrap()).collect();
    let changed = format!(
        "preflight: the verdict changed between runs: run 1 (unperturbed) passed; run 2 (seed {second}) refused: the envelope's stop zone stopped the robot "
    );
    assert!(reasons[0].starts_with(&changed), "{reasons:#?}");
    assert!(reasons[0].contains(&format!("; run 3 (seed {third}) ")), "{reasons:#?}");
    assert!(
        reasons[1].starts_with("preflight: the envelope's stop zone stopped the robot ")
            && reasons[1].ends_with(&format!(" (run 2 (seed {second}))")),
        "{reasons:#?}"
    );

    // The results: run 2's files, and every run listed.
    let out = dir.path().join("results");
    std::fs::create_dir_all(&out).unwrap();
    let bundle = lab.results(&ana, id, &out);
    let read = |name: &str| -> Json { serde_json::from_slice(&std::fs::read(bundle.join(name)).unwrap()).unwrap() };
    let runs = read("preflight-runs.json");
    assert_eq!(runs["kept"], 2, "{runs:#}");
    let listed: Vec<(u64, Json, bool)> = runs["runs"]
        .as_array()
        .unwrap()
        .iter()
        .map(|r| (r["run"].as_u64().unwrap(), r["seed"].clone(), r["passed"].as_bool().unwrap()))
        .collect();
    assert_eq!(listed[..2], [(1, Json::Null, true), (2, Json::from(second), false)], "{runs:#}");
    assert_eq!(listed[2].0, 3);
    assert_eq!(listed[2].1, Json::from(third));
    let lab_verdict = read("preflight-verdict.json");
    assert_eq!(lab_verdict["passed"], false);
    assert_eq!(lab_verdict["reasons"], runs["runs"][1]["reasons"], "{lab_verdict:#}");

    // Run 2 again, from its seed, with the bundle's robot file and the
    // bounds the lab used: the lab's verdict, byte for byte.
    let bounds = out.join("bounds.json");
    std::fs::write(&bounds, runs["bounds"].to_string()).unwrap();
    let local = out.join("local-verdict.json");
    let rerun = crate::support::subsume()
        .arg("run")
        .arg(bundle.join("robot.xml"))
        .args(["--http", "off", "--speed", "max", "--duration", "30", "--perturb", &second.to_string()])
        .arg("--perturb-bounds")
        .arg(&bounds)
        .arg("--verdict")
        .arg(&local)
        .output()
        .unwrap();
    assert!(rerun.status.success(), "{}", String::from_utf8_lossy(&rerun.stderr));
    let local: Json = serde_json::from_slice(&std::fs::read(&local).unwrap()).unwrap();
    assert_eq!(local, lab_verdict, "run 2 rerun from its seed is not the lab's");

    // The baseline passes all three.
    let robust = lab.stage(&ana, "robust.xml", &robot(8.0, ""));
    let id = lab.submit(&ana, robust, 10.0);
    let queued = lab.wait_for(&ana, id, "queued", Duration::from_secs(180));
    assert!(states(&queued).contains(&"queued".to_string()), "{queued:#}");
    assert_eq!(queued["preflight"]["passed"], true, "{queued:#}");
}
