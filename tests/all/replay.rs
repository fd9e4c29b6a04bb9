//! Replay before activation through the built binary over real HTTP
//! (`POST /api/v1/sets/{id}/replay`): a recording made from the portal, a
//! staged set with the recorded components (identical) and one with a
//! changed planner (the first divergence, checked against the `mcap`
//! package's reading of the file), refusals with clear 4xx errors (bad
//! names, a recording of another robot), one replay at a time (429), and
//! the running robot undisturbed while replays run. Chromium clicks the
//! portal's replay button (tests/browser/replay.mjs).
//!
//! And the portal's recordings and robot-file validation under concurrent
//! clients, many rounds: recording starts race (exactly one wins, nothing
//! lost or half written, the list is the folder), validations race (200,
//! 422 or 429, each with its own text's answer, the store unchanged), and a
//! recording across an activation holds both sets' values.

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use serde_json::{Value as Json, json};

use crate::support::{self, HostProcess, http, subsume};

const PASSWORD: &str = "replay-test-password";

fn add_user(store: &Path, name: &str, role: &str, platforms: &[&str]) {
    support::add_user(store, name, role, platforms, PASSWORD);
}

fn login(address: &str, name: &str) -> String {
    support::login(address, name, PASSWORD)
}

/// What the `mcap` package reads in `file` (every message of `values`'
/// topics too).
fn read_mcap_values(file: &Path, values: &[&str]) -> Json {
    support::read_mcap(file, false, values)
}

fn read_mcap(file: &Path) -> Json {
    read_mcap_values(file, &[])
}

fn demo_text() -> String {
    std::fs::read_to_string(support::repo_root().join("config/demo.xml")).unwrap()
}

/// The demo with its planner taken from the store as `component`.
fn demo_with_planner(component: &str) -> String {
    let planner = "../guest-components/rust/target/wasm32-wasip2/release/planner.wasm";
    assert!(demo_text().contains(planner));
    demo_text().replace(planner, &format!("{component}.wasm"))
}

/// A host with a store, users of every role and the demo running.
struct Portal {
    host: HostProcess,
    address: String,
    store: PathBuf,
    admin: String,
    _dir: tempfile::TempDir,
}

impl Portal {
    fn start() -> Portal {
        let dir = tempfile::tempdir().unwrap();
        let store = dir.path().join("store");
        add_user(&store, "admin", "admin", &[]);
        add_user(&store, "dev", "developer", &["control"]);
        add_user(&store, "operator", "operator", &[]);
        add_user(&store, "viewer", "viewer", &[]);
        let mut command = subsume();
        command.arg("--store").arg(&store).args([
            "run",
            "config/demo.xml",
            "--http",
            "127.0.0.1:0",
            "--param",
            "teleop.listen=127.0.0.1:0",
            "--param",
            "teleop.websocket=",
        ]);
        let host = HostProcess::spawn(command);
        let address = host.portal_address();
        let admin = login(&address, "admin");
        Portal { host, address, store, admin, _dir: dir }
    }

    fn call(&self, token: &str, method: &str, path: &str, body: &[u8]) -> (u16, Json) {
        http(&self.address, method, path, Some(token), body)
    }

    /// A recording of the demo for `seconds` from its very start, made by
    /// `subsume run --record` into the store's recordings folder (the
    /// portal lists and replays it like its own); the name.
    ///
    /// From the start, because a replay starts every component afresh: a
    /// recording started while the robot runs finds stateful components
    /// (the filter's moving average, the planner's last pose) in a state it
    /// did not record (docs/recording.md), and their first replayed outputs
    /// can differ for that reason alone. Portal recordings started mid-run
    /// are tested by the concurrency and activation tests below.
    fn record(&self, seconds: u64) -> String {
        static MADE: std::sync::atomic::AtomicU32 = std::sync::atomic::AtomicU32::new(0);
        let n = MADE.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1;
        let name = format!("rec-20200101-000001-{n}.mcap");
        let scratch = self.store.with_file_name(format!("recording-store-{n}"));
        let output = subsume()
            .arg("--store")
            .arg(&scratch)
            .args(["run", "config/demo.xml", "--duration", &seconds.to_string(), "--record"])
            .arg(self.store.join("recordings").join(&name))
            .args(["--param", "teleop.listen=127.0.0.1:0", "--param", "teleop.websocket="])
            .output()
            .unwrap();
        assert!(output.status.success(), "{}", String::from_utf8_lossy(&output.stderr));
        name
    }

    fn stage(&self, token: &str, file: &str, text: &str) -> u64 {
        let path = format!("/api/v1/platforms/control/configs/{file}");
        let (status, json) = self.call(token, "PUT", &path, text.as_bytes());
        assert_eq!(status, 201, "{json}");
        json["set"]["id"].as_u64().unwrap()
    }

    fn replay(&self, token: &str, set: u64, body: &Json) -> (u16, Json) {
        self.call(token, "POST", &format!("/api/v1/sets/{set}/replay"), body.to_string().as_bytes())
    }

    fn status(&self) -> Json {
        let (status, json) = self.call(&self.admin, "GET", "/api/v1/status", b"");
        assert_eq!(status, 200, "{json}");
        json
    }
}

fn motors_ticks(status: &Json) -> u64 {
    status["components"].as_array().unwrap().iter().find(|c| c["name"] == "motors").unwrap()["ticks"].as_u64().unwrap()
}

#[test]
fn a_staged_set_is_replayed_against_a_portal_recording_before_activation() {
    let portal = Portal::start();
    let name = portal.record(3);
    let file = portal.store.join("recordings").join(&name);
    let active = portal.status()["set"].as_u64().unwrap();

    // A set with the components that were recorded: identical.
    let same = portal.stage(&portal.admin, "same.xml", &demo_text());
    let (status, json) = portal.replay(&portal.admin, same, &json!({ "recording": name }));
    assert_eq!(status, 200, "{json}");
    assert_eq!(json["identical"], true, "{json}");
    let report = &json["report"];
    assert_eq!(report["components"], json!(["filter", "avoid", "planner"]), "{json}");
    assert!(report["compared"].as_u64().unwrap() > 50, "{json}");
    assert!(report["recorded_s"].as_f64().unwrap() > 2.0, "{json}");
    assert_eq!(report["divergences"], json!([]));

    // A developer uploads "version 2" of the planner (commands with two
    // decimals) and stages the demo with it: the first command diverges,
    // the distance does not.
    let dev = login(&portal.address, "dev");
    let wasm = std::fs::read(support::guest("test-planner-v2")).unwrap();
    let (status, json) = portal.call(&dev, "PUT", "/api/v1/platforms/control/components/planner-v2", &wasm);
    assert_eq!(status, 201, "{json}");
    let changed = portal.stage(&dev, "planner-v2.xml", &demo_with_planner("planner-v2"));
    let (status, json) = portal.replay(&dev, changed, &json!({ "recording": name, "only": ["planner"] }));
    assert_eq!(status, 200, "{json}");
    assert_eq!(json["identical"], false, "{json}");
    let divergences = json["report"]["divergences"].as_array().unwrap();
    assert_eq!(divergences.len(), 1, "only the command diverges: {json}");
    let first = &divergences[0];
    assert_eq!((first["component"].as_str(), first["port"].as_str()), (Some("planner"), Some("cmd")), "{first}");
    assert_eq!(first["call_kind"], "tick", "{first}");
    let recorded = read_mcap(&file);
    let first_cmd = &recorded["first"]["/planner/cmd"];
    assert_eq!(first["recorded"], json!([first_cmd["value"]]), "the recorded value is the file's");
    assert_eq!(first["time_s"].as_f64().unwrap(), first_cmd["t"].as_u64().unwrap() as f64 / 1e9);
    let old = first["recorded"][0]["command"].as_str().unwrap();
    let new = first["replayed"][0]["command"].as_str().unwrap();
    let decimals = |c: &str| c.split(' ').nth(1).and_then(|v| v.split('.').nth(1)).map(str::len);
    assert_eq!((decimals(old), decimals(new)), (Some(3), Some(2)), "recorded {old}, new {new}");
    // Every component of the changed set: the filter and the avoider are
    // identical, only the planner's command diverges.
    let (status, json) = portal.replay(&portal.admin, changed, &json!({ "recording": name }));
    assert_eq!(status, 200, "{json}");
    let ports: Vec<String> = json["report"]["divergences"]
        .as_array()
        .unwrap()
        .iter()
        .map(|d| format!("{}.{}", d["component"].as_str().unwrap(), d["port"].as_str().unwrap()))
        .collect();
    assert_eq!(ports, ["planner.cmd"], "{json}");

    // Refusals: clear 4xx errors, nothing changes.
    let cases: Vec<(u64, Json, u16, &str)> = vec![
        (same, json!({ "recording": "../state.json" }), 400, "is not a recording name"),
        (same, json!({ "recording": "rec-1.mcap" }), 404, "no recording 'rec-1.mcap'"),
        (999, json!({ "recording": name }), 404, "no set 999"),
        (same, json!({ "recording": name, "only": ["arbiter"] }), 400, "replay runs WASM components only"),
        (same, json!({ "recording": name, "only": ["nobody"] }), 400, "no component 'nobody'"),
        (same, json!({ "recording": name, "extra": 1 }), 400, "unknown field"),
        (same, json!({ "only": [] }), 400, "missing field `recording`"),
    ];
    for (set, body, expected, message) in cases {
        let (status, json) = portal.replay(&portal.admin, set, &body);
        assert_eq!(status, expected, "{body}: {json}");
        assert!(json["error"].as_str().unwrap().contains(message), "{body}: {json}");
    }
    // Viewers and operators may not replay.
    for user in ["viewer", "operator"] {
        let token = login(&portal.address, user);
        let (status, json) = portal.replay(&token, same, &json!({ "recording": name }));
        assert_eq!(status, 403, "{json}");
        assert!(json["error"].as_str().unwrap().contains("may not record"), "{json}");
    }

    // A recording of another robot: its "planner" is a relay fed scalars.
    let other = portal.store.join("other.xml");
    std::fs::write(
        &other,
        format!(
            r#"<robot name="other">
  <platform name="control">
    <component name="source" source="builtin:publish" rate="50"><param name="value" value="1.5"/></component>
    <component name="planner" source="{}" rate="0"/>
    <connect from="source.out" to="planner.scalar-in"/>
  </platform>
</robot>
"#,
            support::guest("test-relay").display()
        ),
    )
    .unwrap();
    let foreign = "rec-20200101-000000-1.mcap";
    let output = subsume()
        .arg("run")
        .arg(&other)
        .args(["--duration", "1", "--record"])
        .arg(portal.store.join("recordings").join(foreign))
        .output()
        .unwrap();
    assert!(output.status.success(), "{}", String::from_utf8_lossy(&output.stderr));
    let (status, json) = portal.replay(&portal.admin, same, &json!({ "recording": foreign, "only": ["planner"] }));
    assert_eq!(status, 422, "{json}");
    let error = json["error"].as_str().unwrap();
    assert!(
        error.contains(&format!(
            "{foreign}: 'planner' gets input 0 'scalar-in' in the recording, but its input 0 is 'pose'"
        )),
        "{error}"
    );
    let (status, json) = portal.replay(&portal.admin, same, &json!({ "recording": foreign, "only": ["filter"] }));
    assert_eq!(status, 422, "{json}");
    assert!(json["error"].as_str().unwrap().contains("no recorded calls of 'filter'"), "{json}");

    // Nothing ran: the active set is the one before, the others staged.
    assert_eq!(portal.status()["set"].as_u64(), Some(active));
    let (_, sets) = portal.call(&portal.admin, "GET", "/api/v1/sets", b"");
    for s in sets["sets"].as_array().unwrap() {
        let expected = if s["id"].as_u64() == Some(active) { "active" } else { "staged" };
        assert_eq!(s["status"], expected, "{sets}");
    }
}

#[test]
fn replays_run_one_at_a_time_and_leave_the_running_robot_alone() {
    let portal = Portal::start();
    let name = portal.record(3);
    let active = portal.status()["set"].as_u64().unwrap();
    let same = portal.stage(&portal.admin, "same.xml", &demo_text());
    // Warm up (compiled components come from the cache from now on) and
    // measure one replay.
    let started = Instant::now();
    let (status, json) = portal.replay(&portal.admin, same, &json!({ "recording": name }));
    assert_eq!(status, 200, "{json}");
    let one = started.elapsed();

    // The serial link's rate with nothing else happening, over 2 s.
    let rate =
        |from: &Json, to: &Json, wall: Duration| (motors_ticks(to) - motors_ticks(from)) as f64 / wall.as_secs_f64();
    let (before, t0) = (portal.status(), Instant::now());
    std::thread::sleep(Duration::from_secs(2));
    let quiet = rate(&before, &portal.status(), t0.elapsed());

    // Four clients replaying at once, rounds for about 4 s: each answer is
    // 200 (identical) or 429 (another replay runs), never anything else.
    let (during, t1) = (portal.status(), Instant::now());
    let answers: Vec<(u16, Json)> = std::thread::scope(|scope| {
        let workers: Vec<_> = (0..4)
            .map(|_| {
                scope.spawn(|| {
                    let mut answers = Vec::new();
                    while t1.elapsed() < Duration::from_secs(4) {
                        let answer = portal.replay(&portal.admin, same, &json!({ "recording": name }));
                        if answer.0 == 429 {
                            // Back off as Retry-After asks (shorter: many
                            // rounds), not a busy loop of connections.
                            std::thread::sleep(Duration::from_millis(5));
                        }
                        answers.push(answer);
                    }
                    answers
                })
            })
            .collect();
        workers.into_iter().flat_map(|w| w.join().unwrap()).collect()
    });
    let busy_rate = rate(&during, &portal.status(), t1.elapsed());
    let (mut ok, mut busy) = (0, 0);
    for (status, json) in &answers {
        match status {
            200 => {
                assert_eq!(json["identical"], true, "{json}");
                ok += 1;
            }
            429 => {
                assert!(json["error"].as_str().unwrap().contains("another replay is running"), "{json}");
                busy += 1;
            }
            other => panic!("a concurrent replay answered {other}: {json}"),
        }
    }
    eprintln!(
        "one replay {:.0} ms; {ok} replays and {busy} refused as busy in 4 s; motors {quiet:.1} ticks/s quiet, {busy_rate:.1} during",
        one.as_secs_f64() * 1e3
    );
    assert!(ok >= 2, "{ok} replays done");
    assert!(busy >= 1, "four clients at once never met a running replay ({ok} done)");
    // The control loop keeps its rate: the 100 Hz link ticks while replays
    // take a core (bound from the quiet rate measured here, the machine is
    // shared).
    assert!(quiet > 50.0, "the link ticks {quiet:.1}/s with nothing else running");
    assert!(busy_rate > 0.8 * quiet, "motors {busy_rate:.1} ticks/s during replays, {quiet:.1} before");
    assert_eq!(portal.status()["set"].as_u64(), Some(active), "the running set changed");
    let log = portal.host.log();
    assert!(!log.contains("panicked"), "{log}");
}

#[test]
fn the_portals_replay_button_shows_identical_and_the_first_divergence_in_a_real_browser() {
    let portal = Portal::start();
    let name = portal.record(3);
    let same = portal.stage(&portal.admin, "same.xml", &demo_text());
    let wasm = std::fs::read(support::guest("test-planner-v2")).unwrap();
    let (status, json) = portal.call(&portal.admin, "PUT", "/api/v1/platforms/control/components/planner-v2", &wasm);
    assert_eq!(status, 201, "{json}");
    let changed = portal.stage(&portal.admin, "planner-v2.xml", &demo_with_planner("planner-v2"));
    let artifacts: PathBuf = support::repo_root().join("target/browser-artifacts");
    let stdout = support::browser(
        "replay.mjs",
        &artifacts,
        &[],
        &[&format!("http://{}/", portal.address), &"admin", &PASSWORD, &name, &same.to_string(), &changed.to_string()],
    );
    assert!(stdout.contains("ok: "), "{stdout}");
    for shot in ["replay-1-identical", "replay-2-divergence", "replay-3-refused"] {
        assert!(artifacts.join(format!("{shot}.png")).is_file(), "{shot}.png");
    }
}

/// `clients` threads send `request(client)` at the same moment, `rounds`
/// times; the answers of each round, by client.
fn race<T: Send>(clients: usize, request: impl Fn(usize) -> T + Sync) -> Vec<T> {
    let barrier = std::sync::Barrier::new(clients);
    std::thread::scope(|scope| {
        let workers: Vec<_> = (0..clients)
            .map(|client| {
                let (barrier, request) = (&barrier, &request);
                scope.spawn(move || {
                    barrier.wait();
                    request(client)
                })
            })
            .collect();
        workers.into_iter().map(|w| w.join().unwrap()).collect()
    })
}

/// The recordings folder as it is on disk: name -> bytes.
fn on_disk(dir: &Path) -> std::collections::BTreeMap<String, u64> {
    std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap())
        .map(|e| (e.file_name().to_string_lossy().into_owned(), e.metadata().unwrap().len()))
        .collect()
}

#[test]
fn concurrent_recording_starts_and_stops_have_one_winner_and_lose_no_file() {
    const CLIENTS: usize = 8;
    const ROUNDS: usize = 6;
    let portal = Portal::start();
    let dev = login(&portal.address, "dev");
    let tokens: Vec<&str> =
        (0..CLIENTS).map(|i| if i % 2 == 0 { portal.admin.as_str() } else { dev.as_str() }).collect();
    let folder = portal.store.join("recordings");
    let mut stopped = Vec::new();
    for round in 0..ROUNDS {
        let starts = race(CLIENTS, |client| portal.call(tokens[client], "POST", "/api/v1/recordings/start", b""));
        let winners: Vec<&Json> = starts.iter().filter(|(s, _)| *s == 201).map(|(_, j)| j).collect();
        assert_eq!(winners.len(), 1, "round {round}: {starts:?}");
        let name = winners[0]["recording"]["name"].as_str().unwrap().to_string();
        for (status, json) in &starts {
            if *status != 201 {
                assert_eq!(*status, 409, "round {round}: {json}");
                let error = json["error"].as_str().unwrap();
                assert!(error.contains(&format!("a recording is running already: {name}")), "{error}");
            }
        }
        std::thread::sleep(Duration::from_millis(300));
        // Stops race too: one stops it, the others find none running.
        let stops = race(CLIENTS, |client| portal.call(tokens[client], "POST", "/api/v1/recordings/stop", b""));
        let done: Vec<&Json> = stops.iter().filter(|(s, _)| *s == 200).map(|(_, j)| j).collect();
        assert_eq!(done.len(), 1, "round {round}: {stops:?}");
        for (status, json) in &stops {
            if *status != 200 {
                assert_eq!(*status, 409, "round {round}: {json}");
                assert!(json["error"].as_str().unwrap().contains("no recording is running"), "{json}");
            }
        }
        assert_eq!(done[0]["stopped"]["name"], name.as_str());
        stopped.push(done[0]["stopped"].clone());
        // The list equals the folder, between rounds and with no recording.
        let (status, listed) = portal.call(&portal.admin, "GET", "/api/v1/recordings", b"");
        assert_eq!(status, 200, "{listed}");
        assert!(listed["recording"].is_null(), "{listed}");
        let listed: std::collections::BTreeMap<String, u64> = listed["files"]
            .as_array()
            .unwrap()
            .iter()
            .map(|f| (f["name"].as_str().unwrap().to_string(), f["bytes"].as_u64().unwrap()))
            .collect();
        assert_eq!(listed, on_disk(&folder), "round {round}");
    }
    // One file per round, every one complete: summary, footer, and as many
    // messages as the stop said.
    let files = on_disk(&folder);
    assert_eq!(files.len(), ROUNDS, "{files:?}");
    for stop in &stopped {
        let name = stop["name"].as_str().unwrap();
        assert_eq!(files.get(name), stop["bytes"].as_u64().as_ref(), "{name}: {stop}");
        let read = read_mcap(&folder.join(name));
        assert_eq!(read["complete"], true, "{name}");
        assert_eq!(read["messages"], stop["messages"], "{name}: {stop}");
        assert_eq!(read["summary"]["message_count"], read["messages"], "{name}");
        assert!(read["messages"].as_u64().unwrap() > 10, "{name}: {stop}");
    }
    // Every start and stop is audited, refused or not.
    let (_, audit) = portal.call(&portal.admin, "GET", "/api/v1/audit?limit=1000", b"");
    let count = |action: &str, result: &str| {
        audit["entries"].as_array().unwrap().iter().filter(|e| e["action"] == action && e["result"] == result).count()
    };
    assert_eq!(count("start-recording", "ok"), ROUNDS, "{audit}");
    assert_eq!(count("start-recording", "refused"), ROUNDS * (CLIENTS - 1), "{audit}");
    assert_eq!(count("stop-recording", "ok"), ROUNDS, "{audit}");
}

#[test]
fn concurrent_validations_answer_each_its_own_text_and_store_nothing() {
    const CLIENTS: usize = 8;
    const ROUNDS: usize = 5;
    let portal = Portal::start();
    let dev = login(&portal.address, "dev");
    let before = support::store_snapshot(&["recordings"], &portal.store);
    let demo = demo_text();
    assert!(demo.contains("to=\"filter.ranges\""));
    let base_components = demo.matches("<component ").count();
    // Client i's text: valid with i extra log components (even i), or with
    // an input port named after it (odd i), so each answer tells whose.
    let text = |round: usize, client: usize| -> String {
        if client.is_multiple_of(2) {
            let extra: String = (0..client + round)
                .map(|k| format!("    <component name=\"extra-{k}\" source=\"builtin:log\" rate=\"0\"/>\n"))
                .collect();
            demo.replacen("  <platform name=\"control\">\n", &format!("  <platform name=\"control\">\n{extra}"), 1)
        } else {
            demo.replace("to=\"filter.ranges\"", &format!("to=\"filter.rangez{round}x{client}\""))
        }
    };
    let (mut ok, mut invalid, mut busy) = (0, 0, 0);
    for round in 0..ROUNDS {
        // Each client retries after a 429 (as the editor would) until its
        // text is answered: every text gets its own answer while others run.
        let answers = race(CLIENTS, |client| {
            let token = if client % 4 == 1 { dev.as_str() } else { portal.admin.as_str() };
            let path = format!("/api/v1/platforms/control/validate/c{client}.xml");
            let mut refused = Vec::new();
            for _ in 0..500 {
                let answer = portal.call(token, "POST", &path, text(round, client).as_bytes());
                if answer.0 != 429 {
                    return (refused, answer);
                }
                refused.push(answer.1);
                std::thread::sleep(Duration::from_millis(10));
            }
            panic!("client {client} was refused 500 times: {:?}", refused.last());
        });
        let mut answered = Vec::new();
        for (refused, answer) in answers {
            busy += refused.len();
            for json in &refused {
                assert!(json["error"].as_str().unwrap().contains("another robot file is being validated"), "{json}");
            }
            answered.push(answer);
        }
        for (client, (status, json)) in answered.iter().enumerate() {
            match (status, client % 2) {
                (200, 0) => {
                    ok += 1;
                    assert_eq!(json["components"].as_u64(), Some((base_components + client + round) as u64), "{json}");
                }
                (422, 1) => {
                    invalid += 1;
                    let diagnostics = json["diagnostics"].as_array().unwrap();
                    assert_eq!(diagnostics.len(), 1, "{json}");
                    let message = diagnostics[0]["text"].as_str().unwrap();
                    assert!(message.starts_with(&format!("c{client}.xml:")), "{message}");
                    assert!(message.contains(&format!("unknown input port 'rangez{round}x{client}'")), "{message}");
                }
                _ => panic!("round {round}, client {client}: {status} {json}"),
            }
        }
    }
    eprintln!("{ok} valid, {invalid} invalid answered, {busy} refused as busy on the way");
    assert_eq!((ok, invalid), (CLIENTS * ROUNDS / 2, CLIENTS * ROUNDS / 2), "every text is answered");
    assert!(busy > 0, "eight validations at once never met a running one");
    // Nothing stored, nothing audited, no set added.
    assert_eq!(support::store_snapshot(&["recordings"], &portal.store), before, "validation changed the store");
    let log = portal.host.log();
    assert!(!log.contains("panicked"), "{log}");
}

#[test]
fn a_portal_recording_across_an_activation_holds_both_sets_values() {
    let portal = Portal::start();
    let wasm = std::fs::read(support::guest("test-planner-v2")).unwrap();
    let (status, json) = portal.call(&portal.admin, "PUT", "/api/v1/platforms/control/components/planner-v2", &wasm);
    assert_eq!(status, 201, "{json}");
    let v2 = portal.stage(&portal.admin, "planner-v2.xml", &demo_with_planner("planner-v2"));
    let first_set = portal.status()["set"].as_u64().unwrap();
    let (status, json) = portal.call(&portal.admin, "POST", "/api/v1/recordings/start", b"");
    assert_eq!(status, 201, "{json}");
    let name = json["recording"]["name"].as_str().unwrap().to_string();
    std::thread::sleep(Duration::from_secs(2));
    let (status, json) = portal.call(&portal.admin, "POST", &format!("/api/v1/sets/{v2}/activate"), b"");
    assert_eq!(status, 200, "{json}");
    assert_eq!(portal.status()["set"].as_u64(), Some(v2));
    std::thread::sleep(Duration::from_secs(2));
    let (status, stopped) = portal.call(&portal.admin, "POST", "/api/v1/recordings/stop", b"");
    assert_eq!(status, 200, "{stopped}");
    assert_eq!(stopped["stopped"]["files"], json!([name]), "{stopped}");
    assert_ne!(first_set, v2);

    let file = portal.store.join("recordings").join(&name);
    let read = read_mcap_values(&file, &["/planner/cmd", "/planner/distance"]);
    assert_eq!(read["complete"], true);
    assert_eq!(read["in_order_per_channel"], true, "{}", read["out_of_order"]);
    assert_eq!(read["messages"], stopped["stopped"]["messages"], "{}", read["summary"]);
    assert_eq!(read["summary"]["message_count"], read["messages"]);
    // The old planner's commands (three decimals), then the new one's (two),
    // never mixed: the swap is one moment in the file.
    let commands: Vec<String> = read["values"]["/planner/cmd"]
        .as_array()
        .unwrap()
        .iter()
        .map(|m| m["value"]["command"].as_str().unwrap().to_string())
        .collect();
    let decimals = |c: &str| c.split(' ').nth(1).and_then(|v| v.split('.').nth(1)).map_or(0, str::len);
    let old = commands.iter().take_while(|c| decimals(c) == 3).count();
    let new = commands[old..].iter().filter(|c| decimals(c) == 2).count();
    assert_eq!(old + new, commands.len(), "the commands mix both forms: {commands:?}");
    // The planner ticks at 10 Hz: about 2 s of each.
    assert!((10..=30).contains(&old), "{old} commands of the first set: {commands:?}");
    assert!((10..=30).contains(&new), "{new} commands of the activated set: {commands:?}");
    let times: Vec<u64> =
        read["values"]["/planner/cmd"].as_array().unwrap().iter().map(|m| m["t"].as_u64().unwrap()).collect();
    assert!(times.windows(2).all(|w| w[0] < w[1]), "graph times go on across the swap: {times:?}");
    // The distance is computed alike by both: recorded throughout.
    assert_eq!(read["values"]["/planner/distance"].as_array().unwrap().len(), commands.len());
    // The host says when it swapped.
    let host_log = portal.host.log();
    assert!(host_log.contains(&format!("set {v2} (planner-v2.xml) is active")), "{host_log}");
}

#[test]
fn a_replay_past_its_bounds_is_stopped_with_a_clear_error() {
    use subsume::record::replay::{ReplayError, ReplayLimits, replay_robot};
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("demo.mcap");
    let output = subsume()
        .args(["run", "config/demo.xml", "--duration", "1", "--record"])
        .arg(&file)
        .args(["--param", "teleop.listen=127.0.0.1:0", "--param", "teleop.websocket="])
        .output()
        .unwrap();
    assert!(output.status.success(), "{}", String::from_utf8_lossy(&output.stderr));
    let sandbox = support::sandbox();
    let mut loader = subsume::assemble::Loader::new(&sandbox);
    let config = subsume::config::load_with(&support::repo_root().join("config/demo.xml"), &mut loader, &[]).unwrap();
    let only = ["planner".to_string()];
    // Within generous bounds: identical.
    let report = replay_robot(&config, &mut loader, &file, &only, ReplayLimits::default()).unwrap();
    assert!(report.identical() && report.compared > 5, "{report:?}");
    // A file larger than the bound is not read.
    let size = std::fs::metadata(&file).unwrap().len();
    let small = ReplayLimits { max_recording_bytes: size - 1, max_duration: None };
    let error = replay_robot(&config, &mut loader, &file, &only, small).unwrap_err();
    assert!(matches!(error, ReplayError::TooLarge { .. }), "{error}");
    assert!(error.to_string().ends_with(&format!("{size} bytes, larger than the {} bytes a replay reads", size - 1)));
    // A replay running past its duration is stopped.
    let instant = ReplayLimits { max_recording_bytes: size, max_duration: Some(Duration::ZERO) };
    let error = replay_robot(&config, &mut loader, &file, &only, instant).unwrap_err();
    assert!(matches!(error, ReplayError::TooLong { done: 0, .. }), "{error}");
    assert!(error.to_string().contains("the replay took longer than 0 s and was stopped after 0 of "), "{error}");
}

/// How a recording of the running demo is started, and what replaying its
/// stateful components (the filter's moving average, the planner's last
/// pose) must then show.
struct FreshCase {
    fresh_start: bool,
    /// Identical from the first call; else: the filter diverges at its
    /// first recorded call, and nothing is shifted.
    identical: bool,
}

#[test]
fn a_fresh_start_recording_replays_identically_and_a_mid_run_one_differs_at_its_first_call() {
    let portal = Portal::start();
    let folder = portal.store.join("recordings");
    let active = portal.status()["set"].as_u64().unwrap();
    // The filter and the planner get state: the robot drives a few seconds.
    let started = Instant::now();
    while portal.status()["duration_s"].as_f64().unwrap() < 4.0 {
        assert!(started.elapsed() < Duration::from_secs(60), "the robot does not run");
        std::thread::sleep(Duration::from_millis(200));
    }
    let cases = [FreshCase { fresh_start: true, identical: true }, FreshCase { fresh_start: false, identical: false }];
    for case in &cases {
        let what = if case.fresh_start { "fresh start" } else { "mid-run" };
        let body = json!({ "fresh_start": case.fresh_start }).to_string();
        let (status, json) = portal.call(&portal.admin, "POST", "/api/v1/recordings/start", body.as_bytes());
        assert_eq!(status, 201, "{what}: {json}");
        assert_eq!(json["recording"]["fresh_start"], case.fresh_start, "{json}");
        let name = json["recording"]["name"].as_str().unwrap().to_string();
        if case.fresh_start {
            // While it runs, another fresh start is refused like a start,
            // before anything is rebuilt, and audited as refused.
            let (status, json) = portal.call(&portal.admin, "POST", "/api/v1/recordings/start", body.as_bytes());
            assert_eq!(status, 409, "{json}");
            assert!(json["error"].as_str().unwrap().contains(&format!("a recording is running already: {name}")));
        }
        std::thread::sleep(Duration::from_secs(3));
        let (status, json) = portal.call(&portal.admin, "POST", "/api/v1/recordings/stop", b"");
        assert_eq!(status, 200, "{what}: {json}");
        assert_eq!(json["stopped"]["dropped"], 0, "{json}");
        // The mcap package reads it as a complete file.
        let read = read_mcap(&folder.join(&name));
        assert_eq!(read["complete"], true, "{what}");
        assert_eq!(read["in_order_per_channel"], true, "{what}: {}", read["out_of_order"]);
        for topic in ["/subsume/calls/filter", "/subsume/calls/planner", "/planner/cmd", "/filter/filtered"] {
            assert!(read["channels"][topic]["count"].as_u64().unwrap_or(0) > 5, "{what}: {topic}: {read}");
        }

        // The recorded set replayed against it, its stateful components.
        let (status, json) =
            portal.replay(&portal.admin, active, &json!({ "recording": name, "only": ["filter", "planner"] }));
        assert_eq!(status, 200, "{what}: {json}");
        let report = &json["report"];
        eprintln!(
            "{what}: {} calls, {} outputs compared, divergences: {}",
            report["calls"], report["compared"], report["divergences"]
        );
        assert!(report["compared"].as_u64().unwrap() > 100, "{what}: {json}");
        assert_eq!(json["identical"], case.identical, "{what}: {json}");
        if case.identical {
            assert_eq!(report["divergences"], json!([]), "{what}");
            continue;
        }
        // Mid-run: the filter's first smoothed scan differs (its running
        // average is not in the recording) at its first recorded call;
        // the planner, if its first recorded tick came before any recorded
        // pose, lacks that one command and nothing after it is shifted.
        let divergences = report["divergences"].as_array().unwrap();
        let filter = divergences.iter().find(|d| d["component"] == "filter" && d["port"] == "filtered");
        let filter = filter.unwrap_or_else(|| panic!("no filter divergence: {json}"));
        assert_eq!(
            (filter["call"].as_u64(), filter["call_kind"].as_str()),
            (Some(0), Some("input ranges")),
            "{filter}"
        );
        assert_eq!(filter["recorded"].as_array().unwrap().len(), 1, "{filter}");
        assert_eq!(filter["replayed"].as_array().unwrap().len(), 1, "{filter}");
        for d in divergences.iter().filter(|d| d["component"] == "planner") {
            assert_eq!(d["call_kind"], "tick", "{d}");
            assert_eq!(d["recorded"].as_array().unwrap().len(), 1, "{d}");
            assert_eq!(d["replayed"], json!([]), "a fresh planner has no pose yet: {d}");
            assert_eq!(d["calls_differing"], 1, "one call differs, the rest are not shifted: {d}");
        }
    }
    // The fresh start was an activation of the same set: audited as one and
    // as a recording start; the set is still the active one.
    let (_, audit) = portal.call(&portal.admin, "GET", "/api/v1/audit?limit=1000", b"");
    let entries = audit["entries"].as_array().unwrap();
    let has = |action: &str, result: &str, detail: &str| {
        entries
            .iter()
            .any(|e| e["action"] == action && e["result"] == result && e["detail"].as_str().unwrap().contains(detail))
    };
    assert!(has("activate", "ok", &format!("re-activated set {active} for recording ")), "{audit}");
    assert!(has("start-recording", "ok", &format!("from a fresh start (set {active} re-activated)")), "{audit}");
    assert!(has("start-recording", "refused", "a recording is running already"), "{audit}");
    assert_eq!(portal.status()["set"].as_u64(), Some(active));

    // Refusals: a viewer or operator may not; a body that is not the
    // object is a 400; nothing was started or re-activated.
    for user in ["viewer", "operator"] {
        let token = login(&portal.address, user);
        let (status, json) = portal.call(&token, "POST", "/api/v1/recordings/start", br#"{"fresh_start": true}"#);
        assert_eq!(status, 403, "{json}");
    }
    for body in [&br#"{"fresh_start": "yes"}"#[..], br#"{"fresh": true}"#, b"[1]"] {
        let (status, json) = portal.call(&portal.admin, "POST", "/api/v1/recordings/start", body);
        assert_eq!(status, 400, "{json}");
        assert!(json["error"].as_str().unwrap().contains("fresh_start"), "{json}");
    }
    let (_, listed) = portal.call(&portal.admin, "GET", "/api/v1/recordings", b"");
    assert!(listed["recording"].is_null(), "{listed}");

    // The motors' rules hold across the swap as for an activation: an
    // engaged emergency stop stays engaged (the board is the host's) and
    // the robot does not move through the re-activation.
    let (status, json) = portal.call(&portal.admin, "POST", "/api/v1/estop", b"");
    assert_eq!(status, 200, "{json}");
    std::thread::sleep(Duration::from_secs(1));
    let pose = |s: &Json| (s["sim"]["x"].as_f64().unwrap(), s["sim"]["y"].as_f64().unwrap());
    let before = pose(&portal.status());
    let (status, json) = portal.call(&portal.admin, "POST", "/api/v1/recordings/start", br#"{"fresh_start": true}"#);
    assert_eq!(status, 201, "{json}");
    std::thread::sleep(Duration::from_secs(1));
    let (_, locks) = portal.call(&portal.admin, "GET", "/api/v1/locks", b"");
    assert_eq!(locks["engaged"].as_array().unwrap().len(), 1, "{locks}");
    let after = pose(&portal.status());
    assert!((after.0 - before.0).abs() < 1e-3 && (after.1 - before.1).abs() < 1e-3, "moved: {before:?} -> {after:?}");
    let (status, json) = portal.call(&portal.admin, "POST", "/api/v1/recordings/stop", b"");
    assert_eq!(status, 200, "{json}");
    let (status, json) = portal.call(&portal.admin, "POST", "/api/v1/release", b"");
    assert_eq!(status, 200, "{json}");
    let log = portal.host.log();
    assert!(!log.contains("panicked"), "{log}");
}
