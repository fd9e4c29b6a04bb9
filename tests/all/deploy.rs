//! `subsume deploy` end to end: the built binary against a real `subsume
//! run` with the portal, over real HTTP. A component replaced in the
//! running robot in one command; a robot file and its component in one
//! command; a bad robot file answered with located errors and nothing
//! changed; a component the running robot does not have refused before
//! anything is uploaded.
//!
//! `subsume lab` end to end the same way (docs/lab.md, the command line): a
//! submission with a component and one with a robot file, each followed
//! through every state to `done`, its results unpacked and read by the
//! `mcap` package; refusals (a robot file that does not read, one the
//! portal finds wrong, located in the file; a preflight that fails); show,
//! list and cancel between two researchers; the lab kit's verdict equal to
//! the lab's preflight's on the same set.

use std::io::{BufRead, BufReader};
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::Duration;

use crate::lab_docs;
use crate::support::{self, HostProcess, http, subsume};

const PASSWORD: &str = "deploy-test-password";

/// A running `subsume run` and its portal's address.
struct Host {
    _process: HostProcess,
    address: String,
}

fn add_admin(store: &Path) {
    support::add_user(store, "admin", "admin", &[], PASSWORD);
}

/// `subsume run ROBOT` with its portal on a free port; the lab's
/// preflights at `normal` priority (at `idle` the tests beside it starve
/// them).
fn start(store: &Path, robot: &Path) -> Host {
    let mut command = subsume();
    command.args(["--store", store.to_str().unwrap(), "run"]).arg(robot).args(["--http", "127.0.0.1:0"]);
    command.args(["--preflight-priority", "normal"]);
    let process = HostProcess::spawn(command);
    let address = process.portal_address();
    Host { _process: process, address }
}

fn token(address: &str) -> String {
    support::login(address, "admin", PASSWORD)
}

/// The active set: (id, robot name, the sha256 of the component `name` runs).
fn active(address: &str, name: &str) -> (u64, String, Option<String>) {
    let token = token(address);
    let (_, status) = http(address, "GET", "/api/v1/status", Some(&token), b"");
    let set = status["set"].as_u64().unwrap();
    let (_, record) = http(address, "GET", &format!("/api/v1/sets/{set}"), Some(&token), b"");
    let config = record["config"].as_str().unwrap();
    let source = config.split(&format!("name=\"{name}\" source=\"")).nth(1).map(|s| s.split('"').next().unwrap());
    let sha = source.and_then(|s| record["set"]["sources"][s].as_str()).map(str::to_string);
    (set, status["robot"].as_str().unwrap().to_string(), sha)
}

/// `subsume deploy ARGS... ADDRESS` as admin: (success, stdout, stderr).
fn deploy(address: &str, args: &[&str]) -> (bool, String, String) {
    deploy_as("admin", address, args)
}

/// `subsume deploy ARGS... ADDRESS` as `user`: (success, stdout, stderr).
fn deploy_as(user: &str, address: &str, args: &[&str]) -> (bool, String, String) {
    let output = subsume()
        .arg("deploy")
        .args(args)
        .arg(address)
        .env("SUBSUME_USER", user)
        .env("SUBSUME_PASSWORD", PASSWORD)
        .output()
        .unwrap();
    let text = |b: &[u8]| String::from_utf8_lossy(b).into_owned();
    (output.status.success(), text(&output.stdout), text(&output.stderr))
}

/// The relay's bytes with a custom section: a component no one uploaded.
fn unique_relay(dir: &Path, tag: &str) -> std::path::PathBuf {
    unique_guest(dir, "test-relay", tag)
}

/// Guest `guest`'s bytes with a custom section: a component no one uploaded.
fn unique_guest(dir: &Path, guest: &str, tag: &str) -> std::path::PathBuf {
    let mut wasm = std::fs::read(support::guest(guest)).unwrap();
    let name = b"test";
    wasm.extend_from_slice(&[0, (1 + name.len() + tag.len()) as u8, name.len() as u8]);
    wasm.extend_from_slice(name);
    wasm.extend_from_slice(tag.as_bytes());
    let path = dir.join(format!("{guest}-{tag}.wasm"));
    std::fs::write(&path, wasm).unwrap();
    path
}

fn sha256(path: &Path) -> String {
    use sha2::Digest;
    hex::encode(sha2::Sha256::digest(std::fs::read(path).unwrap()))
}

fn robot(name: &str, relay_source: &str) -> String {
    format!(
        r#"<robot name="{name}">
  <platform name="control">
    <component name="source" source="builtin:publish" rate="20"><param name="value" value="1"/></component>
    <component name="relay" source="{relay_source}" rate="0"/>
    <component name="sink" source="builtin:log" rate="0"/>
    <connect from="source.out" to="relay.scalar-in"/>
    <connect from="relay.scalar-out" to="sink.in"/>
  </platform>
</robot>
"#
    )
}

#[test]
fn deploy_replaces_a_component_or_a_whole_robot_in_one_step_and_changes_nothing_on_failure() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    add_admin(&store);
    let boot = dir.path().join("boot.xml");
    std::fs::write(&boot, robot("boot", &support::guest("test-relay").display().to_string())).unwrap();
    let host = start(&store, &boot);
    let (first, name, _) = active(&host.address, "relay");
    assert_eq!(name, "boot");

    // One component of the running robot, replaced in one command.
    let v2 = unique_relay(dir.path(), "v2");
    let (ok, stdout, stderr) = deploy(&host.address, &["--component", &format!("relay={}", v2.display())]);
    assert!(ok, "{stderr}");
    let (second, name, sha) = active(&host.address, "relay");
    assert!(second > first, "{stdout}");
    assert_eq!(stdout.trim(), format!("deployed: set {second} is running"));
    assert_eq!((name.as_str(), sha.as_deref()), ("boot", Some(sha256(&v2).as_str())));
    assert!(stderr.contains("deploy: uploaded relay in "), "{stderr}");

    // A robot file and a component in one command.
    let v3 = unique_relay(dir.path(), "v3");
    let next = dir.path().join("next.xml");
    std::fs::write(&next, robot("next", "relay.wasm")).unwrap();
    let relay_arg = format!("relay={}", v3.display());
    let (ok, _, stderr) = deploy(&host.address, &["--component", &relay_arg, "--robot", next.to_str().unwrap()]);
    assert!(ok, "{stderr}");
    let (third, name, sha) = active(&host.address, "relay");
    assert!(third > second);
    assert_eq!((name.as_str(), sha.as_deref()), ("next", Some(sha256(&v3).as_str())));

    // A bad robot file: located errors (the local path), nothing changed.
    let bad = dir.path().join("bad.xml");
    std::fs::write(&bad, robot("bad", "relay.wasm").replace("relay.scalar-in", "relay.nothing")).unwrap();
    let (ok, _, stderr) = deploy(&host.address, &["--robot", bad.to_str().unwrap()]);
    assert!(!ok);
    let located = format!("{}:6:36: unknown input port 'nothing' on component 'relay'", bad.display());
    assert!(stderr.contains(&located), "{stderr}");
    assert!(stderr.contains("nothing was changed"), "{stderr}");
    assert_eq!(active(&host.address, "relay"), (third, "next".to_string(), Some(sha256(&v3))));

    // A component the running robot does not have: refused before any upload.
    let ghost = unique_relay(dir.path(), "ghost");
    let (ok, _, stderr) = deploy(&host.address, &["--component", &format!("ghost={}", ghost.display())]);
    assert!(!ok);
    assert!(
        stderr.contains("the running robot file next.xml has no component 'ghost' (it has: source, relay, sink)"),
        "{stderr}"
    );
    let (status, _) = http(&host.address, "GET", "/api/v1/components/ghost", Some(&token(&host.address)), b"");
    assert_eq!(status, 404);
    assert_eq!(active(&host.address, "relay").0, third);

    // A file that is not a component: named by the client before anything
    // is uploaded (its preamble), or refused by the portal (it does not
    // compile); nothing changed either way. (case, bytes, what it says,
    // whether it was sent).
    let cases: [(&str, &[u8], &str, bool); 3] = [
        (
            "text",
            b"not wasm",
            "is not a webassembly component: the file does not start with the webassembly magic bytes",
            false,
        ),
        (
            "a core module",
            b"\0asm\x01\0\0\0",
            "is not a webassembly component: this is a core webassembly module",
            false,
        ),
        ("a component's preamble, then junk", b"\0asm\x0d\0\x01\0junk", "component relay: the portal answered 4", true),
    ];
    for (case, bytes, says, sent) in cases {
        let junk = dir.path().join("junk.wasm");
        std::fs::write(&junk, bytes).unwrap();
        let (ok, _, stderr) = deploy(&host.address, &["--component", &format!("relay={}", junk.display())]);
        assert!(!ok, "{case}");
        assert!(stderr.contains(says), "{case}: {stderr}");
        assert_eq!(stderr.contains("uploading relay"), sent, "{case}: {stderr}");
        assert_eq!(active(&host.address, "relay").0, third, "{case}");
    }

    // Staged, then its activation refused (a component that will not
    // start): the set it staged is forgotten, nothing is left behind.
    let sets = || subsume::store::Store::open(&store).unwrap().sets().unwrap().len();
    let before = sets();
    let refusing = dir.path().join("refusing.xml");
    let bad = r#"<component name="bad" source="bad.wasm" rate="10"><param name="mode" value="error-on-init"/></component>
    <component name="sink""#;
    std::fs::write(&refusing, robot("refusing", "relay.wasm").replace(r#"<component name="sink""#, bad)).unwrap();
    let bad_arg = format!("bad={}", support::guest("test-faulty").display());
    let (ok, _, stderr) = deploy(&host.address, &["--component", &bad_arg, "--robot", refusing.to_str().unwrap()]);
    assert!(!ok, "{stderr}");
    assert!(stderr.contains("the activation was refused: set ") && stderr.contains(" is forgotten"), "{stderr}");
    assert_eq!(sets(), before, "the refused activation's set is forgotten");
    assert_eq!(active(&host.address, "relay").0, third);
}

/// The sha256 of `owner`'s stored upload `name`, if any.
fn stored(address: &str, owner: &str, name: &str) -> Option<String> {
    let (status, record) =
        http(address, "GET", &format!("/api/v1/components/{owner}/{name}"), Some(&token(address)), b"");
    (status == 200).then(|| record["sha256"].as_str().unwrap().to_string())
}

/// The source the active robot file gives component `name`.
fn active_source(address: &str, name: &str) -> String {
    let token = token(address);
    let (_, status) = http(address, "GET", "/api/v1/status", Some(&token), b"");
    let (_, record) = http(address, "GET", &format!("/api/v1/sets/{}", status["set"]), Some(&token), b"");
    let config = record["config"].as_str().unwrap();
    let source = config.split(&format!("name=\"{name}\" source=\"")).nth(1).unwrap();
    source.split('"').next().unwrap().to_string()
}

#[test]
fn a_second_users_deploy_of_the_same_name_does_not_overwrite_the_first_users_upload() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    add_admin(&store);
    support::add_user(&store, "bob", "developer", &["control"], PASSWORD);
    let boot = dir.path().join("boot.xml");
    std::fs::write(&boot, robot("boot", &support::guest("test-relay").display().to_string())).unwrap();
    let host = start(&store, &boot);

    // The admin replaces the running relay: the file now names the admin's upload.
    let first = unique_relay(dir.path(), "admin-1");
    let (ok, _, stderr) = deploy(&host.address, &["--component", &format!("relay={}", first.display())]);
    assert!(ok, "{stderr}");
    assert_eq!(active_source(&host.address, "relay"), "admin/relay.wasm");
    assert_eq!(stored(&host.address, "admin", "relay"), Some(sha256(&first)));

    // Bob deploys his own relay under the same name: it runs, named as his,
    // and the admin's stored upload is untouched.
    let second = unique_relay(dir.path(), "bob-1");
    let (ok, stdout, stderr) =
        deploy_as("bob", &host.address, &["--component", &format!("relay={}", second.display())]);
    assert!(ok, "{stderr}");
    assert!(stderr.contains("with relay -> bob/relay.wasm"), "{stderr}");
    let (set, _, sha) = active(&host.address, "relay");
    assert_eq!(stdout.trim(), format!("deployed: set {set} is running"));
    assert_eq!(sha, Some(sha256(&second)));
    assert_eq!(active_source(&host.address, "relay"), "bob/relay.wasm");
    assert_eq!(stored(&host.address, "bob", "relay"), Some(sha256(&second)));
    assert_eq!(
        stored(&host.address, "admin", "relay"),
        Some(sha256(&first)),
        "bob's deploy replaced the admin's upload"
    );

    // A robot file of Bob's may run the admin's by owner and name (read-only).
    let shared = dir.path().join("shared.xml");
    std::fs::write(&shared, robot("shared", "admin/relay.wasm")).unwrap();
    let (ok, _, stderr) = deploy_as("bob", &host.address, &["--robot", shared.to_str().unwrap()]);
    assert!(ok, "{stderr}");
    assert_eq!(active(&host.address, "relay").2, Some(sha256(&first)));
    assert_eq!(stored(&host.address, "admin", "relay"), Some(sha256(&first)));
    assert_eq!(stored(&host.address, "bob", "relay"), Some(sha256(&second)));
}

/// `subsume dev ROBOT` with the portal on a free port.
fn start_dev(store: &Path, robot: &Path) -> HostProcess {
    let mut command = subsume();
    command.args(["--store", store.to_str().unwrap(), "dev"]).arg(robot).args([
        "--http",
        "127.0.0.1:0",
        "--poll",
        "0.05",
    ]);
    HostProcess::spawn(command)
}

/// The host's log lines after the `seen` ones until one contains `what`
/// (all of them, that one last); counts them into `seen`.
fn until(host: &HostProcess, seen: &mut usize, what: &str) -> Vec<String> {
    let lines = host.lines_until(*seen, what, Duration::from_secs(120));
    *seen += lines.len();
    lines
}

fn sim_robot(name: &str, relay_to: &str) -> String {
    let world = support::repo_root().join("config/worlds/demo.world");
    format!(
        r#"<robot name="{name}">
  <platform name="control">
    <component name="robot-sim" source="builtin:sim"><param name="world" value="{world}"/></component>
    <component name="motors" source="builtin:serial" rate="50"><param name="device" value="sim:robot-sim"/></component>
    <component name="relay" source="relay.wasm" rate="0"/>
    <component name="sink" source="builtin:log" rate="0"/>
    <connect from="motors.ranges" to="relay.{relay_to}"/>
    <connect from="relay.vector-out" to="sink.in"/>
  </platform>
</robot>
"#,
        world = world.display()
    )
}

#[test]
fn dev_swaps_a_changed_component_in_and_keeps_the_running_set_when_the_robot_file_breaks() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    let robot = dir.path().join("robot.xml");
    let relay = dir.path().join("relay.wasm");
    std::fs::copy(support::guest("test-relay"), &relay).unwrap();
    std::fs::write(&robot, sim_robot("dev", "vector-in")).unwrap();
    let host = start_dev(&store, &robot);
    let mut seen = 0;
    let watching = until(&host, &mut seen, "dev: watching 2 file(s) every 50 ms");
    assert!(watching.last().unwrap().contains(&relay.display().to_string()), "{watching:?}");

    // A new build of the component: swapped in, the simulated robot and
    // its link carried across.
    std::fs::copy(unique_relay(dir.path(), "edit1"), &relay).unwrap();
    let swapped = until(&host, &mut seen, "dev: set 2 is running");
    let text = swapped.join("\n");
    assert!(text.contains(&format!("dev: changed: {}", relay.display())), "{text}");
    assert!(text.contains("kept running") && text.contains("robot-sim"), "{text}");
    eprintln!("edit -> running (Rust relay): {}", swapped.last().unwrap());

    // A broken robot file: located errors, the running set stays.
    std::fs::write(&robot, sim_robot("dev", "nothing")).unwrap();
    let refused = until(&host, &mut seen, "the running set is unchanged");
    let text = refused.join("\n");
    assert!(text.contains(&format!("dev: {}:7:", robot.display())), "{text}");
    assert!(text.contains("unknown input port 'nothing' on component 'relay'"), "{text}");
    assert!(!text.contains("is running"), "{text}");

    // Fixed again: the next set runs.
    std::fs::write(&robot, sim_robot("dev2", "vector-in")).unwrap();
    until(&host, &mut seen, "dev: set 3 is running");
}

// ---- subsume lab ----

const RESEARCHER_PASSWORD: &str = "lab-test-password";

/// A robot in `dir` (beside a copy of `wall-ahead.world`): a driver
/// (`driver_source`, with `driver_params`) at priority 1 through the
/// arbiter and `envelope` to a simulated robot 4 m from a wall.
fn lab_robot(dir: &Path, file: &str, driver_source: &str, driver_params: &str, envelope: &str) -> std::path::PathBuf {
    std::fs::copy(support::repo_root().join("tests/worlds/wall-ahead.world"), dir.join("wall.world")).unwrap();
    let xml = format!(
        r#"<robot name="lab">
  <platform name="control">
    <component name="sim" source="builtin:sim"><param name="world" value="wall.world"/></component>
    <component name="motors" source="builtin:serial" rate="50"><param name="device" value="sim:sim"/></component>
    <component name="driver" source="{driver_source}" rate="10" timeout="300ms">{driver_params}</component>
    <component name="arbiter" source="builtin:arbiter" rate="20"/>
    {envelope}
    <connect from="driver.cmd" to="arbiter.commands"/>
    <connect from="arbiter.cmd" to="envelope.cmd"/>
    <connect from="envelope.cmd" to="motors.cmd"/>
  </platform>
</robot>
"#
    );
    let path = dir.join(file);
    std::fs::write(&path, xml).unwrap();
    path
}

/// The owner's envelope with its sensors wired in.
const WATCHFUL: &str = r#"<component name="envelope" source="builtin:envelope" rate="20"/>
    <connect from="motors.ranges" to="envelope.ranges"/>
    <connect from="motors.pose" to="envelope.pose"/>"#;

fn commander(command: &str, ticks: u64) -> String {
    format!(r#"<param name="command" value="{command}"/><param name="ticks" value="{ticks}"/>"#)
}

/// A host on `boot` with researchers `ada` and `bob` (platform control).
fn lab_host(dir: &Path, boot: &Path) -> Host {
    let store = dir.join("store");
    for name in ["ada", "bob"] {
        support::add_user(&store, name, "researcher", &["control"], RESEARCHER_PASSWORD);
    }
    start(&store, boot)
}

/// A host whose robot drives gently for 1.5 s (its preflight passes),
/// with researchers `ada` and `bob`.
fn gentle_lab(dir: &Path) -> Host {
    let commander_path = support::guest("test-commander").display().to_string();
    let boot = lab_robot(dir, "boot.xml", &commander_path, &commander("VEL 0.2 0", 15), WATCHFUL);
    lab_host(dir, &boot)
}

/// `subsume lab ARGS...` as `user` (by the environment).
fn lab(user: &str, args: &[&str]) -> std::process::Output {
    subsume()
        .arg("lab")
        .args(args)
        .env("SUBSUME_USER", user)
        .env("SUBSUME_PASSWORD", RESEARCHER_PASSWORD)
        .output()
        .unwrap()
}

fn out(output: &std::process::Output) -> (String, String) {
    let text = |b: &[u8]| String::from_utf8_lossy(b).into_owned();
    (text(&output.stdout), text(&output.stderr))
}

/// The states `subsume lab submit` told for experiment `id`, in order,
/// each once (a queue place is told as `queued` too).
fn told_states(stdout: &str, id: u64) -> Vec<String> {
    let mut states: Vec<String> = Vec::new();
    for line in stdout.lines() {
        let Some(rest) = line.strip_prefix(&format!("experiment {id}: ")) else { continue };
        let state = rest.split(':').next().unwrap().to_string();
        if states.last() != Some(&state) {
            states.push(state);
        }
    }
    states
}

/// What the `mcap` package (PyPI) reads in `file`.
fn read_mcap(file: &Path) -> serde_json::Value {
    let output = Command::new(support::python())
        .arg(support::repo_root().join("tests/python/mcap_reader.py"))
        .arg(file)
        .output()
        .unwrap();
    let (stdout, stderr) = out(&output);
    assert!(output.status.success(), "the mcap package cannot read {}: {stderr}", file.display());
    serde_json::from_str(&stdout).unwrap()
}

/// Checks an unpacked bundle against its SHA256SUMS independently of the
/// client: every file listed matches, every file is listed.
fn check_sums(dir: &Path) {
    let sums = std::fs::read_to_string(dir.join("SHA256SUMS")).unwrap();
    let mut listed = std::collections::BTreeSet::new();
    for line in sums.lines() {
        let (sum, name) = line.split_once("  ").unwrap();
        assert_eq!(sha256(&dir.join(name)), sum, "{name}");
        listed.insert(name.to_string());
    }
    let mut files = std::collections::BTreeSet::new();
    let mut dirs = vec![dir.to_path_buf()];
    while let Some(d) = dirs.pop() {
        for entry in std::fs::read_dir(&d).unwrap() {
            let path = entry.unwrap().path();
            if path.is_dir() {
                dirs.push(path);
            } else if path.file_name().unwrap() != "SHA256SUMS" {
                files.insert(path.strip_prefix(dir).unwrap().to_str().unwrap().to_string());
            }
        }
    }
    assert_eq!(files, listed);
}

const DONE: [&str; 6] = ["checking", "preflight", "queued", "running", "finishing", "done"];

#[test]
fn lab_submit_follows_an_experiment_to_done_and_unpacks_results_the_mcap_package_reads() {
    let dir = tempfile::tempdir().unwrap();
    let host = gentle_lab(dir.path());

    // A component of the running robot replaced, by the environment's
    // credentials.
    let v2 = unique_guest(dir.path(), "test-commander", "v2");
    let results = dir.path().join("results/first");
    let output = lab(
        "ada",
        &[
            "submit",
            "--component",
            &format!("driver={}", v2.display()),
            "--duration",
            "2",
            "--label",
            "first try",
            "--results",
            results.to_str().unwrap(),
            &host.address,
        ],
    );
    let (stdout, stderr) = out(&output);
    assert!(output.status.success(), "{stdout}\n{stderr}");
    let first = stdout.lines().next().unwrap();
    assert!(first.starts_with("experiment 1 submitted: set "), "{stdout}");
    assert!(first.contains(", 2 s, \"first try\"; follow it with `subsume lab show 1 "), "{stdout}");
    assert_eq!(told_states(&stdout, 1), DONE, "{stdout}");
    assert!(stdout.contains("experiment 1: running: started on the robot") && stdout.contains("(ends at "), "{stdout}");
    assert!(stderr.contains("lab: uploaded driver in "), "{stderr}");
    // `lab submit --results` and `lab results` say the bundle alike.
    let said = |text: &str| {
        let line = text.lines().find(|l| l.starts_with("results of experiment 1: ")).expect(text);
        line.split_once(" (").expect(line).1.to_string()
    };
    let submitted = said(&stdout);
    assert!(submitted.contains("sha256 checked: the result files `lab show` counts, with experiment.json"), "{stdout}");
    let again = dir.path().join("results/again");
    let output = lab("ada", &["results", "1", &host.address, "-o", again.to_str().unwrap()]);
    assert!(output.status.success(), "{}", out(&output).1);
    assert_eq!(said(&out(&output).0), submitted);
    check_sums(&results);
    assert_eq!(sha256(&results.join("components/driver.wasm")), sha256(&v2));
    let record: serde_json::Value =
        serde_json::from_slice(&std::fs::read(results.join("experiment.json")).unwrap()).unwrap();
    assert_eq!((record["state"].as_str(), record["submitter"].as_str()), (Some("done"), Some("ada")), "{record}");
    for recording in ["run.mcap", "preflight.mcap"] {
        let read = read_mcap(&results.join(recording));
        assert_eq!(read["complete"], true, "{recording}: {read}");
        assert!(read["messages"].as_u64().unwrap() > 10, "{recording}: {read}");
    }

    // A robot file of the researcher's own, its driver built locally:
    // pointed at the upload; the credentials as flags.
    let v3 = unique_guest(dir.path(), "test-commander", "v3");
    let own = lab_robot(dir.path(), "own.xml", "build/driver.wasm", &commander("VEL 0.15 0", 15), WATCHFUL);
    let results = dir.path().join("results/second");
    let output = subsume()
        .args(["lab", "submit", "--robot", own.to_str().unwrap(), "--component"])
        .arg(format!("driver={}", v3.display()))
        .args(["--duration", "2", "--user", "ada", "--password", RESEARCHER_PASSWORD, "--results"])
        .arg(&results)
        .arg(&host.address)
        .env_remove("SUBSUME_USER")
        .env_remove("SUBSUME_PASSWORD")
        .output()
        .unwrap();
    let (stdout, stderr) = out(&output);
    assert!(output.status.success(), "{stdout}\n{stderr}");
    assert_eq!(told_states(&stdout, 2), DONE, "{stdout}");
    check_sums(&results);
    assert_eq!(sha256(&results.join("components/driver.wasm")), sha256(&v3));
    assert!(std::fs::read_to_string(results.join("robot.xml")).unwrap().contains("VEL 0.15 0"));
    assert_eq!(read_mcap(&results.join("run.mcap"))["complete"], true);
}

#[test]
fn a_refused_submission_says_why_in_the_robot_files_own_lines_and_exits_1() {
    let dir = tempfile::tempdir().unwrap();
    let host = gentle_lab(dir.path());
    let store = dir.path().join("store");
    let sets = || subsume::store::Store::open(&store).unwrap().sets().unwrap().len();
    let before = sets();
    let submit = |robot: &Path, component: &str| {
        lab(
            "ada",
            &["submit", "--robot", robot.to_str().unwrap(), "--component", component, "--duration", "3", &host.address],
        )
    };
    let driver = format!("driver={}", support::guest("test-commander").display());

    // Not even XML: found here, nothing sent.
    let broken = dir.path().join("broken.xml");
    std::fs::write(&broken, "<robot name=\"x\">\n  <platform name=\"control\">\n</robot>\n").unwrap();
    let output = submit(&broken, &driver);
    let (_, stderr) = out(&output);
    assert!(!output.status.success());
    assert!(stderr.contains(&format!("{}:3:1: malformed xml", broken.display())), "{stderr}");
    assert!(stderr.contains("nothing was sent"), "{stderr}");

    // Wrong where only the portal can tell: its diagnostics, at the
    // positions of the file as written (the source that was pointed at
    // the upload comes before the bad value on its line).
    let bad = lab_robot(
        dir.path(),
        "bad.xml",
        "build/a/long/way/to/driver.wasm\" priority=\"x1",
        &commander("VEL 0.2 0", 15),
        WATCHFUL,
    )
    .to_str()
    .unwrap()
    .to_string();
    let text = std::fs::read_to_string(&bad).unwrap().replace("to=\"envelope.cmd\"", "to=\"envelope.nothing\"");
    std::fs::write(&bad, &text).unwrap();
    let position = |needle: &str| {
        let (line, l) = text.lines().enumerate().find(|(_, l)| l.contains(needle)).unwrap();
        format!("{}:{}", line + 1, l[..l.find(needle).unwrap()].chars().count() + 1)
    };
    let output = submit(Path::new(&bad), &driver);
    let (stdout, stderr) = out(&output);
    assert!(!output.status.success());
    assert!(stderr.contains(&format!("{bad}:{}: priority 'x1' is not a whole number", position("x1\""))), "{stderr}");
    assert!(
        stderr.contains(&format!("{bad}:{}: unknown input port 'nothing'", position("envelope.nothing"))),
        "{stderr}"
    );
    assert!(!stdout.contains("submitted"), "{stdout}");
    assert_eq!(sets(), before, "nothing was staged");

    // Staged and submitted, refused by its preflight: the fault named.
    let faulty = unique_guest(dir.path(), "test-faulty", "trap");
    let params =
        r#"<param name="mode" value="trap-on-tick"/><param name="after" value="10"/><param name="drive" value="yes"/>"#;
    let trap = lab_robot(dir.path(), "trap.xml", "driver.wasm", params, WATCHFUL);
    // Staged, then refused at once (over the robot's max-duration): the
    // set it staged is forgotten, nothing is left behind.
    let trap_driver = format!("driver={}", faulty.display());
    let over = lab(
        "ada",
        &[
            "submit",
            "--robot",
            trap.to_str().unwrap(),
            "--component",
            &trap_driver,
            "--duration",
            "3000",
            &host.address,
        ],
    );
    let (stdout, stderr) = out(&over);
    assert!(!over.status.success(), "{stdout}");
    assert!(stderr.contains("duration_s must be from"), "{stderr}");
    assert!(stderr.contains("the submission was refused: set ") && stderr.contains(" is forgotten"), "{stderr}");
    assert_eq!(sets(), before, "the refused submission's set is forgotten");
    let output = submit(&trap, &format!("driver={}", faulty.display()));
    let (stdout, stderr) = out(&output);
    assert_eq!(output.status.code(), Some(1), "{stdout}\n{stderr}");
    assert_eq!(told_states(&stdout, 1), ["checking", "preflight", "refused"], "{stdout}");
    assert!(stdout.contains("experiment 1: refused: refused by its preflight"), "{stdout}");
    assert!(stdout.contains("\n  preflight: component 'driver' faulted at "), "{stdout}");
}

#[test]
fn lab_show_list_and_cancel_act_on_ones_own_experiments_only() {
    let dir = tempfile::tempdir().unwrap();
    let host = gentle_lab(dir.path());

    // A long experiment (the running robot file as it is), followed by a
    // submit in the background.
    let results = dir.path().join("results/long");
    let mut follower = subsume()
        .args(["lab", "submit", "--duration", "60", "--label", "long", "--results"])
        .arg(&results)
        .arg(&host.address)
        .env("SUBSUME_USER", "ada")
        .env("SUBSUME_PASSWORD", RESEARCHER_PASSWORD)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let lines = BufReader::new(follower.stdout.take().unwrap()).lines();
    let (tx, told) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        for line in lines.map_while(Result::ok) {
            let _ = tx.send(line);
        }
    });
    let mut followed = Vec::new();
    while !followed.iter().any(|l: &String| l.starts_with("experiment 1: running:")) {
        match told.recv_timeout(Duration::from_secs(120)) {
            Ok(line) => followed.push(line),
            Err(e) => {
                let _ = follower.kill();
                let stderr = out(&follower.wait_with_output().unwrap()).1;
                panic!("experiment 1 did not start ({e}): {followed:?}\n{stderr}");
            }
        }
    }

    // A second one waits behind it.
    let ada = support::login(&host.address, "ada", RESEARCHER_PASSWORD);
    let (_, one) = http(&host.address, "GET", "/api/v1/experiments/1", Some(&ada), b"");
    let set = one["experiment"]["set"].as_u64().unwrap();
    let body = serde_json::json!({ "set": set, "duration_s": 5, "label": "next" }).to_string();
    let (status, json) = http(&host.address, "POST", "/api/v1/experiments", Some(&ada), body.as_bytes());
    assert_eq!(status, 201, "{json}");
    let deadline = std::time::Instant::now() + Duration::from_secs(60);
    let shown = loop {
        let output = lab("ada", &["show", "2", &host.address]);
        let (stdout, stderr) = out(&output);
        assert!(output.status.success(), "{stderr}");
        if stdout.starts_with("experiment 2: queued #1\n") {
            break stdout;
        }
        assert!(std::time::Instant::now() < deadline, "experiment 2 was not queued: {stdout}");
        std::thread::sleep(Duration::from_millis(200));
    };
    assert!(shown.contains("  queue      place 1 in the queue, starts in about "), "{shown}");
    assert!(shown.contains("  label      next\n") && shown.contains("checking   submitted by ada"), "{shown}");
    let output = lab("ada", &["list", &host.address]);
    let (listed, _) = out(&output);
    let rows: Vec<Vec<&str>> = listed.lines().map(|l| l.split_whitespace().collect()).collect();
    assert_eq!(rows[0], ["ID", "STATE", "SUBMITTER", "SET", "DURATION", "SUBMITTED", "LABEL"], "{listed}");
    assert_eq!(&rows[1][..4], ["2", "queued", "#1", "ada"], "{listed}");
    assert_eq!(&rows[2][..3], ["1", "running", "ada"], "{listed}");
    assert_eq!((rows[1].last(), rows[2].last(), rows.len()), (Some(&"next"), Some(&"long"), 3), "{listed}");
    let output = lab("ada", &["list", "--json", &host.address]);
    let json: serde_json::Value = serde_json::from_slice(&output.stdout).unwrap();
    assert_eq!(json.as_array().map(Vec::len), Some(2), "{json}");

    // Another researcher sees neither, and cannot cancel them.
    assert_eq!(out(&lab("bob", &["list", &host.address])).0, "no experiments\n");
    for args in [["show", "1"], ["cancel", "1"]] {
        let output = lab("bob", &[args[0], args[1], &host.address]);
        assert!(!output.status.success());
        assert!(out(&output).1.contains(": the portal answered 404: no experiment 1"), "{:?}", out(&output));
    }

    // Cancelled waiting, then running: the follower tells it and exits 1
    // with what the run left.
    let output = lab("ada", &["cancel", "2", &host.address]);
    assert_eq!(out(&output).0, "experiment 2: cancelled: cancelled by ada\n", "{:?}", out(&output));
    let output = lab("ada", &["cancel", "1", &host.address]);
    assert_eq!(out(&output).0, "experiment 1: cancelled: cancelled by ada\n", "{:?}", out(&output));
    let status = follower.wait().unwrap();
    followed.extend(told.iter());
    let followed = followed.join("\n");
    assert_eq!(status.code(), Some(1), "{followed}");
    assert!(followed.contains("experiment 1: cancelled: cancelled by ada"), "{followed}");
    check_sums(&results);
    assert!(read_mcap(&results.join("run.mcap"))["messages"].as_u64().unwrap() > 0);
    let output = lab("ada", &["show", "1", &host.address]);
    assert!(out(&output).0.starts_with("experiment 1: cancelled\n"), "{:?}", out(&output));

    // Its results again, by `lab results`; never into a folder with files.
    let again = dir.path().join("again");
    let output = lab("ada", &["results", "1", &host.address, "-o", again.to_str().unwrap()]);
    assert!(output.status.success(), "{:?}", out(&output));
    assert_eq!(sha256(&again.join("run.mcap")), sha256(&results.join("run.mcap")));
    let output = lab("ada", &["results", "1", &host.address, "-o", again.to_str().unwrap()]);
    assert!(!output.status.success());
    assert!(out(&output).1.contains("is not empty; give a new or empty folder"), "{:?}", out(&output));
}

#[test]
fn the_lab_kit_run_locally_gives_the_verdict_the_labs_preflight_gave() {
    let dir = tempfile::tempdir().unwrap();
    // The lab's robot drives blind at the wall, its envelope loosened by
    // the owner: its preflight finds the collision.
    let blind = r#"<component name="envelope" source="builtin:envelope" rate="20">
      <param name="max-speed" value="10"/><param name="max-reverse" value="10"/><param name="max-turn" value="20"/>
      <param name="max-accel" value="100"/><param name="max-turn-accel" value="100"/>
    </component>"#;
    let commander_path = support::guest("test-commander").display().to_string();
    let boot = lab_robot(dir.path(), "boot.xml", &commander_path, &commander("VEL 0.45 0", 100_000_000), blind);
    let host = lab_host(dir.path(), &boot);
    let results = dir.path().join("results");
    let output = lab("ada", &["submit", "--duration", "60", "--results", results.to_str().unwrap(), &host.address]);
    let (stdout, stderr) = out(&output);
    assert_eq!(output.status.code(), Some(1), "{stdout}\n{stderr}");
    assert_eq!(told_states(&stdout, 1), ["checking", "preflight", "refused"], "{stdout}\n{stderr}");
    let reason = stdout.lines().find_map(|l| l.strip_prefix("  preflight: collision at ")).expect(&stdout).to_string();
    assert!(reason.ends_with("while 'driver' held control"), "{reason}");

    let kit = dir.path().join("kit");
    let output = lab("ada", &["kit", &host.address, "-o", kit.to_str().unwrap()]);
    let (stdout, stderr) = out(&output);
    assert!(output.status.success(), "{stderr}");
    assert!(stdout.contains(&format!("subsume run {}/robot.xml --http off --speed max --duration 60", kit.display())));
    check_sums(&kit);
    let verdict = kit.join("verdict.json");
    let output = subsume()
        .arg("run")
        .arg(kit.join("robot.xml"))
        .args(["--http", "off", "--speed", "max", "--duration", "60", "--criteria"])
        .arg(kit.join("criteria.json"))
        .arg("--verdict")
        .arg(&verdict)
        .output()
        .unwrap();
    let (_, stderr) = out(&output);
    assert!(output.status.success(), "{stderr}");
    assert!(stderr.contains(&format!("preflight verdict: refused\n  preflight: collision at {reason}")), "{stderr}");
    let read = |path: &Path| serde_json::from_slice::<serde_json::Value>(&std::fs::read(path).unwrap()).unwrap();
    let (local, lab) = (read(&verdict), read(&results.join("preflight-verdict.json")));
    assert_eq!(local["passed"], false, "{local}");
    assert_eq!(local, lab, "the kit's verdict differs from the lab's preflight's");
}

/// docs/lab.md's path from the kit to the lab: the kit's robot file,
/// changed (the driver's parameters, its file moved), run on the
/// researcher's machine and submitted as it is. The lab runs its baseline
/// with those changes (its own component recognised by its sha256, so
/// nothing is uploaded), and its preflight's verdict is the local one. A
/// change the kit cannot carry (a built-in's parameter) is refused at its
/// line before anything is sent.
#[test]
fn the_lab_kits_robot_file_changed_and_run_locally_submits_as_it_is_with_the_same_verdict() {
    let dir = tempfile::tempdir().unwrap();
    let commander_path = support::guest("test-commander").display().to_string();
    let boot = lab_robot(dir.path(), "boot.xml", &commander_path, &commander("VEL 0.45 0", 100_000_000), WATCHFUL);
    let host = lab_host(dir.path(), &boot);
    let kit = dir.path().join("kit");
    let output = lab("ada", &["kit", &host.address, "-o", kit.to_str().unwrap()]);
    assert!(output.status.success(), "{}", out(&output).1);
    let manifest: serde_json::Value = serde_json::from_slice(&std::fs::read(kit.join("kit.json")).unwrap()).unwrap();
    assert_eq!(manifest["baseline"], 1, "{manifest}");
    assert_eq!(manifest["components"]["driver"]["sha256"], sha256(&kit.join("components/driver.wasm")));
    // Her changes: a gentler command for a shorter time, and the driver's
    // file where she keeps hers.
    std::fs::rename(kit.join("components/driver.wasm"), dir.path().join("driver.wasm")).unwrap();
    let robot = kit.join("robot.xml");
    let text = std::fs::read_to_string(&robot).unwrap();
    let changed = text
        .replace("components/driver.wasm", "../driver.wasm")
        .replace(r#"value="VEL 0.45 0""#, r#"value="VEL 0.2 0""#)
        .replace(r#"value="100000000""#, r#"value="15""#);
    assert_ne!(changed, text);
    std::fs::write(&robot, &changed).unwrap();
    let verdict = dir.path().join("verdict.json");
    let output = subsume()
        .arg("run")
        .arg(&robot)
        .args(["--http", "off", "--speed", "max", "--duration", "5", "--criteria"])
        .arg(kit.join("criteria.json"))
        .arg("--verdict")
        .arg(&verdict)
        .output()
        .unwrap();
    assert!(output.status.success(), "{}", out(&output).1);

    let results = dir.path().join("results");
    let output = lab(
        "ada",
        &[
            "submit",
            "--robot",
            robot.to_str().unwrap(),
            "--duration",
            "5",
            "--results",
            results.to_str().unwrap(),
            &host.address,
        ],
    );
    let (stdout, stderr) = out(&output);
    assert!(output.status.success(), "{stdout}\n{stderr}");
    let both = format!("{stdout}{stderr}");
    let base_sha = sha256(&boot);
    assert!(
        both.contains(&format!(
            "building on the lab's baseline boot.xml (set 1, sha256 {base_sha}) with the changes of {}: driver: command VEL 0.45 0 -> VEL 0.2 0; driver: ticks 100000000 -> 15",
            robot.display()
        )),
        "{both}"
    );
    assert!(!both.contains("uploading"), "the lab's own driver was uploaded again:\n{both}");
    let states = told_states(&stdout, 1);
    assert_eq!(
        (states.first().map(String::as_str), states.last().map(String::as_str)),
        (Some("checking"), Some("done")),
        "{stdout}"
    );
    let read = |path: &Path| serde_json::from_slice::<serde_json::Value>(&std::fs::read(path).unwrap()).unwrap();
    let (local, lab_verdict) = (read(&verdict), read(&results.join("preflight-verdict.json")));
    assert_eq!(local["passed"], true, "{local}");
    assert_eq!(local, lab_verdict, "the kit's verdict differs from the lab's preflight's");
    // The robot ran the baseline's own built-ins, with her driver's changes.
    let ran = std::fs::read_to_string(results.join("robot.xml")).unwrap();
    assert!(ran.contains(r#"value="VEL 0.2 0""#) && ran.contains(r#"name="ticks" value="15""#), "{ran}");

    // A built-in's attributes are the lab's: refused at its line, nothing
    // sent.
    let quicker = changed.replacen(
        r#"<component name="arbiter" source="builtin:arbiter" rate="20""#,
        r#"<component name="arbiter" source="builtin:arbiter" rate="50""#,
        1,
    );
    assert_ne!(quicker, changed);
    std::fs::write(&robot, &quicker).unwrap();
    let line = quicker.lines().position(|l| l.contains(r#"name="arbiter""#)).unwrap() + 1;
    let output = lab("ada", &["submit", "--robot", robot.to_str().unwrap(), "--duration", "5", &host.address]);
    let (stdout, stderr) = out(&output);
    assert!(!output.status.success(), "{stdout}");
    assert!(
        stderr.contains(&format!(
            "{}:{line}:5: 'arbiter' (builtin:arbiter) is the lab's own, here in its preflight form: an experiment cannot change it from the kit; nothing was sent",
            robot.display()
        )),
        "{stderr}"
    );
    let ada = support::login(&host.address, "ada", RESEARCHER_PASSWORD);
    let (_, listed) = http(&host.address, "GET", "/api/v1/experiments", Some(&ada), b"");
    assert_eq!(listed["experiments"].as_array().map(Vec::len), Some(1), "{listed}");
}

/// One argument of a command line.
type Arg<'a> = &'a dyn AsRef<std::ffi::OsStr>;

/// `subsume ARGS...` as `user` (by the environment) with `env` set and
/// `SUBSUME_CA` unset: (success, stdout, stderr).
fn as_user(user: &str, args: &[Arg], env: &[(&str, &Path)]) -> (bool, String, String) {
    let password = if user == "admin" { PASSWORD } else { RESEARCHER_PASSWORD };
    let mut command = subsume();
    command.args(args).env("SUBSUME_USER", user).env("SUBSUME_PASSWORD", password).env_remove("SUBSUME_CA");
    for (name, value) in env {
        command.env(name, value);
    }
    let output = command.output().unwrap();
    let (stdout, stderr) = out(&output);
    (output.status.success(), stdout, stderr)
}

/// The gentle lab's robot with its portal on https, its certificate from
/// the test authority in `pki`; an admin and researchers `ada` and `bob`.
/// Its `https://127.0.0.1:PORT` address.
fn start_https(dir: &Path, pki: &Path) -> (HostProcess, String) {
    let store = dir.join("store");
    add_admin(&store);
    for name in ["ada", "bob"] {
        support::add_user(&store, name, "researcher", &["control"], RESEARCHER_PASSWORD);
    }
    let commander_path = support::guest("test-commander").display().to_string();
    let boot = lab_robot(dir, "boot.xml", &commander_path, &commander("VEL 0.2 0", 15), WATCHFUL);
    let mut command = subsume();
    command.args(["--store", store.to_str().unwrap(), "run"]).arg(boot).args(["--http", "127.0.0.1:0"]);
    command.arg("--tls-cert").arg(pki.join("chain.pem")).arg("--tls-key").arg(pki.join("server.key"));
    command.args(["--preflight-priority", "normal"]);
    let process = HostProcess::spawn(command);
    let address = format!("https://{}", process.address_after("portal on https://", Duration::from_secs(120)));
    (process, address)
}

/// What Python's own TLS client (OpenSSL, trusting `ca`) reads from the
/// API at `address` as the admin: each path's JSON (`{set}`: the active
/// set).
fn read_over_tls(address: &str, ca: &Path, paths: &[&str]) -> Vec<serde_json::Value> {
    let output = Command::new(support::python())
        .arg(support::repo_root().join("tests/python/service_peer.py"))
        .args(["get", &format!("{address}/"), ca.to_str().unwrap(), "admin", PASSWORD])
        .args(paths)
        .output()
        .unwrap();
    let (stdout, stderr) = out(&output);
    assert!(output.status.success(), "service_peer.py get: {stderr}");
    let answers: Vec<serde_json::Value> = serde_json::from_str(&stdout).unwrap();
    answers.into_iter().map(|a| a["json"].clone()).collect()
}

#[test]
fn every_portal_command_speaks_https_trusting_the_labs_own_authority_or_the_systems() {
    let dir = tempfile::tempdir().unwrap();
    let (pki, other) = (dir.path().join("pki"), dir.path().join("other-pki"));
    for d in [&pki, &other] {
        std::fs::create_dir(d).unwrap();
        support::make_test_pki(d);
    }
    let (ca, other_ca) = (pki.join("ca.pem"), other.join("ca.pem"));
    let (_host, address) = start_https(dir.path(), &pki);
    let ca_flag: [Arg; 2] = [&"--ca", &ca];
    let locks = || read_over_tls(&address, &ca, &["/api/v1/locks"]).remove(0);

    // The emergency stop and its release; a refusal's reason printed whole.
    let (ok, stdout, stderr) = as_user("bob", &[&"estop", &address, &ca_flag[0], &ca_flag[1]], &[]);
    assert!(ok && stdout.contains("estop engaged: the motors are stopped"), "{stdout}{stderr}");
    assert!(locks().to_string().contains("estop"), "{}", locks());
    let (ok, _, stderr) = as_user("ada", &[&"release", &address, &ca_flag[0], &ca_flag[1]], &[]);
    assert!(!ok);
    assert!(
        stderr.contains(&format!(
            "the portal at {address} answered 403: ada may not drive (role researcher): releasing a lock needs a role that may drive\n"
        )),
        "{stderr}"
    );
    let (ok, stdout, stderr) = as_user("admin", &[&"release", &address, &ca_flag[0], &ca_flag[1]], &[]);
    assert!(ok && stdout.contains("released estop after"), "{stdout}{stderr}");

    // Deploy: upload, stage, activate; the active set read back by an
    // independent client runs the upload.
    let v2 = unique_guest(dir.path(), "test-commander", "v2");
    let driver = format!("driver={}", v2.display());
    let (ok, stdout, stderr) =
        as_user("admin", &[&"deploy", &"--component", &driver, &address, &ca_flag[0], &ca_flag[1]], &[]);
    assert!(ok, "{stderr}");
    let answers = read_over_tls(&address, &ca, &["/api/v1/status", "/api/v1/sets/{set}"]);
    let set = answers[0]["set"].as_u64().unwrap();
    assert_eq!(stdout.trim(), format!("deployed: set {set} is running"));
    assert_eq!(answers[1]["set"]["sources"]["admin/driver.wasm"], sha256(&v2), "{}", answers[1]);

    // lab submit, followed to done, its results unpacked and checked; the
    // same results downloaded again by `lab results`.
    let v3 = unique_guest(dir.path(), "test-commander", "v3");
    let driver = format!("driver={}", v3.display());
    let results = dir.path().join("results");
    let submit: [Arg; 9] =
        [&"lab", &"submit", &"--component", &driver, &"--duration", &"2", &"--results", &results, &address];
    let (ok, stdout, stderr) = as_user("ada", &[&submit[..], &ca_flag[..]].concat(), &[]);
    assert!(ok, "{stdout}\n{stderr}");
    assert_eq!(told_states(&stdout, 1), DONE, "{stdout}");
    assert!(stdout.contains(&format!("follow it with `subsume lab show 1 {address}`")), "{stdout}");
    check_sums(&results);
    assert_eq!(sha256(&results.join("components/driver.wasm")), sha256(&v3));
    let again = dir.path().join("again");
    let (ok, stdout, stderr) =
        as_user("ada", &[&"lab", &"results", &"1", &address, &"-o", &again, &ca_flag[0], &ca_flag[1]], &[]);
    assert!(ok && stdout.contains("sha256 checked"), "{stdout}{stderr}");
    check_sums(&again);
    assert_eq!(sha256(&again.join("run.mcap")), sha256(&results.join("run.mcap")));

    // The system's roots (rustls-native-certs reads SSL_CERT_FILE as the
    // system's bundle): trusted when they hold the lab's authority, and
    // only then. Both test authorities have the same name, so rustls
    // finds the other one and its signature does not match. (case, args,
    // SSL_CERT_FILE, what it says).
    let list: [Arg; 3] = [&"lab", &"list", &address];
    let cases: [(&str, Vec<Arg>, &Path, &str); 3] = [
        ("the system trusts the lab's authority", list.to_vec(), &ca, "ID  STATE"),
        (
            "the system does not trust it",
            list.to_vec(),
            &other_ca,
            "does not trust (invalid peer certificate: BadSignature): give the lab's own authority with --ca FILE (PEM)",
        ),
        (
            "--ca names another authority",
            [&list[..], &[&"--ca" as Arg, &other_ca]].concat(),
            &ca,
            "(invalid peer certificate: BadSignature): it was not issued for 127.0.0.1 by the authority in --ca",
        ),
    ];
    // The system's folder of certificates, emptied for the test.
    let no_certs = dir.path().join("no-certs");
    std::fs::create_dir(&no_certs).unwrap();
    for (case, args, roots, says) in cases {
        let env = [("SSL_CERT_FILE", roots), ("SSL_CERT_DIR", no_certs.as_path())];
        let (ok, stdout, stderr) = as_user("ada", &args, &env);
        assert_eq!(ok, case.starts_with("the system trusts"), "{case}: {stdout}{stderr}");
        assert!(format!("{stdout}{stderr}").contains(says), "{case}: {stdout}{stderr}");
    }

    // A platform the user may not change: refused before any upload, as
    // the portal told at login.
    let (ok, _, stderr) = as_user(
        "ada",
        &[&"deploy", &"--platform", &"network", &"--component", &driver, &address, &ca_flag[0], &ca_flag[1]],
        &[],
    );
    assert!(!ok && !stderr.contains("uploading"), "{stderr}");
    assert!(
        stderr.contains(
            "ada may not upload to platform network (role researcher; may change: control); nothing was uploaded"
        ),
        "{stderr}"
    );

    // A file that is not a component: named before anything is sent.
    let junk = dir.path().join("junk.wasm");
    std::fs::write(&junk, b"\0asm\x01\0\0\0").unwrap();
    let driver = format!("driver={}", junk.display());
    let (ok, _, stderr) = as_user(
        "ada",
        &[&"lab", &"submit", &"--component", &driver, &"--duration", &"2", &address, &ca_flag[0], &ca_flag[1]],
        &[],
    );
    assert!(!ok && !stderr.contains("uploading"), "{stderr}");
    assert!(stderr.contains(&format!("{} is not a webassembly component: this is a core", junk.display())), "{stderr}");
    let experiments = read_over_tls(&address, &ca, &["/api/v1/experiments"]).remove(0);
    assert_eq!(experiments["experiments"].as_array().map(Vec::len), Some(1), "{experiments}");
}

/// A listener on every address and this machine's address on its
/// default route (not loopback), when it has one.
fn non_loopback_listener() -> (std::net::TcpListener, Option<std::net::IpAddr>) {
    let listener = std::net::TcpListener::bind("0.0.0.0:0").unwrap();
    listener.set_nonblocking(true).unwrap();
    // Connecting a UDP socket sends nothing; it picks the route's source.
    let ip = std::net::UdpSocket::bind("0.0.0.0:0")
        .and_then(|s| s.connect("192.0.2.1:9").and_then(|()| s.local_addr()))
        .map(|a| a.ip())
        .ok()
        .filter(|ip| !ip.is_loopback() && !ip.is_unspecified());
    (listener, ip)
}

#[test]
fn no_command_sends_a_password_in_clear_off_loopback_unless_allowed() {
    let dir = tempfile::tempdir().unwrap();
    let (listener, ip) = non_loopback_listener();
    // Without an address of its own off loopback, the documentation
    // address: the refusal comes before any connection all the same (a
    // connection to it would wait for its timeout).
    let port = listener.local_addr().unwrap().port();
    let address = format!("http://{}:{port}", ip.map_or_else(|| "192.0.2.1".to_string(), |ip| ip.to_string()));
    let component = dir.path().join("driver.wasm");
    std::fs::copy(support::guest("test-commander"), &component).unwrap();
    let driver = format!("driver={}", component.display());
    let out_dir = dir.path().join("out");
    let commands: [Vec<Arg>; 8] = [
        vec![&"estop", &address],
        vec![&"release", &address],
        vec![&"deploy", &"--component", &driver, &address],
        vec![&"lab", &"submit", &"--component", &driver, &"--duration", &"2", &address],
        vec![&"lab", &"list", &address],
        vec![&"lab", &"cancel", &"1", &address],
        vec![&"lab", &"results", &"1", &address, &"-o", &out_dir],
        vec![&"lab", &"kit", &address, &"-o", &out_dir],
    ];
    let shown = address.trim_start_matches("http://");
    for args in commands {
        let started = std::time::Instant::now();
        let (ok, _, stderr) = as_user("ada", &args, &[]);
        let line = args.iter().map(|a| a.as_ref().to_string_lossy().into_owned()).collect::<Vec<_>>().join(" ");
        assert!(!ok, "{line}: {stderr}");
        assert!(
            stderr.contains(&format!(
                "refusing to send a password in clear to http://{shown}, which is not a loopback address: use https://"
            )) && stderr.contains("--allow-plain-http"),
            "{line}: {stderr}"
        );
        // Without an address of our own, only the time tells: a
        // connection would wait for `CONNECT_TIMEOUT` (5 s).
        if ip.is_none() {
            assert!(started.elapsed() < Duration::from_secs(4), "{line} took {:?}", started.elapsed());
        }
        assert!(listener.accept().is_err(), "{line} connected");
        assert!(!out_dir.exists(), "{line} wrote {}", out_dir.display());
    }
    // With --allow-plain-http it does connect (and fails on a peer that
    // closes at once).
    if ip.is_some() {
        let mut child = subsume()
            .args(["estop", &address, "--user", "ada", "--password", "x", "--allow-plain-http"])
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .unwrap();
        let deadline = std::time::Instant::now() + Duration::from_secs(10);
        let connected = loop {
            match listener.accept() {
                Ok(_) => break true,
                Err(_) if std::time::Instant::now() < deadline => std::thread::sleep(Duration::from_millis(20)),
                Err(_) => break false,
            }
        };
        assert!(connected, "--allow-plain-http did not connect");
        assert!(!child.wait().unwrap().success());
    }
}

#[test]
fn a_portal_on_the_other_scheme_is_told_apart_from_an_unreachable_one() {
    // A plain-http server on loopback, answering anything with a 401.
    let plain = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let port = plain.local_addr().unwrap().port();
    std::thread::spawn(move || {
        for stream in plain.incoming().take(2) {
            use std::io::Write;
            let mut stream = stream.unwrap();
            let _ = stream.write_all(b"HTTP/1.1 401 Unauthorized\r\ncontent-length: 0\r\nconnection: close\r\n\r\n");
        }
    });
    // A TLS server (the portal).
    let dir = tempfile::tempdir().unwrap();
    let pki = dir.path().join("pki");
    std::fs::create_dir(&pki).unwrap();
    support::make_test_pki(&pki);
    let (_host, address) = start_https(dir.path(), &pki);
    // (case, address given, what it says).
    let cases = [
        (
            "https:// to plain http",
            format!("https://127.0.0.1:{port}"),
            format!(
                "the portal at https://127.0.0.1:{port} does not speak TLS (received corrupt message of type \
                 InvalidContentType): if it serves plain http on loopback, give http://127.0.0.1:{port}"
            ),
        ),
        (
            "http:// to TLS",
            address.replace("https://", "http://"),
            format!("the portal at {} gave an answer that is not HTTP", address.trim_start_matches("https://")),
        ),
        ("nobody there", "127.0.0.1:1".to_string(), "cannot reach the portal at 127.0.0.1:1: ".to_string()),
    ];
    for (case, given, says) in cases {
        let ca = pki.join("ca.pem");
        let args: Vec<Arg> =
            if given.starts_with("https://") { vec![&"estop", &given, &"--ca", &ca] } else { vec![&"estop", &given] };
        let (ok, _, stderr) = as_user("admin", &args, &[]);
        assert!(!ok && stderr.contains(&says), "{case}: {stderr}");
    }
}

/// The run's status and its outcome are apart: a run whose component
/// faulted on the robot (the owner's criteria allow faults) ends `done`,
/// `lab submit` exits 0, and both it and `lab show` say the outcome: the
/// fault, with its component and time.
#[test]
fn a_run_that_faults_on_the_robot_is_done_and_its_outcome_says_so() {
    let dir = tempfile::tempdir().unwrap();
    add_admin(&dir.path().join("store"));
    let host = gentle_lab(dir.path());
    let token = support::login(&host.address, "admin", PASSWORD);
    let (_, overview) = http(&host.address, "GET", "/api/v1/lab", Some(&token), b"");
    let mut settings = overview["lab"]["settings"].clone();
    settings["criteria"]["allow_faults"] = serde_json::Value::Bool(true);
    let (status, json) =
        http(&host.address, "PUT", "/api/v1/lab/settings", Some(&token), settings.to_string().as_bytes());
    assert_eq!(status, 200, "{json}");
    let faulty = unique_guest(dir.path(), "test-faulty", "trap");
    let params =
        r#"<param name="mode" value="trap-on-tick"/><param name="after" value="10"/><param name="drive" value="yes"/>"#;
    let trap = lab_robot(dir.path(), "trap.xml", "driver.wasm", params, WATCHFUL);
    let driver = format!("driver={}", faulty.display());
    let output = lab(
        "ada",
        &["submit", "--robot", trap.to_str().unwrap(), "--component", &driver, "--duration", "3", &host.address],
    );
    let (stdout, stderr) = out(&output);
    assert_eq!(output.status.code(), Some(0), "done is the run's status: {stdout}\n{stderr}");
    assert_eq!(
        told_states(&stdout, 1),
        ["checking", "preflight", "queued", "running", "finishing", "done"],
        "{stdout}"
    );
    let outcome = stdout.lines().find_map(|l| l.strip_prefix("outcome of experiment 1: ")).expect(&stdout).to_string();
    assert!(outcome.contains("component 'driver' faulted at ") && outcome.contains("trap"), "{outcome}");
    assert!(outcome.contains("no collision"), "{outcome}");

    let output = lab("ada", &["show", "1", &host.address]);
    let (stdout, stderr) = out(&output);
    assert!(output.status.success(), "{stderr}");
    assert!(stdout.contains("experiment 1: done"), "{stdout}");
    let shown = stdout.lines().find_map(|l| l.trim().strip_prefix("outcome")).expect(&stdout).trim().to_string();
    assert_eq!(shown, outcome, "lab show and lab submit say it alike");
    let output = lab("ada", &["show", "1", "--json", &host.address]);
    let record: serde_json::Value = serde_json::from_slice(&output.stdout).unwrap();
    let faults = &record["run"]["outcome"]["faults"];
    assert_eq!(faults[0]["component"], "driver", "{record:#}");
    assert!(faults[0]["at_s"].as_f64().unwrap() > 0.5, "after 10 good ticks at 10 Hz: {record:#}");
}

/// `subsume lab reserve`, `reservations`, `unreserve` and `settings`, each
/// as its user may, with the portal's reasons when refused.
#[test]
fn reservations_and_the_owners_settings_from_the_command_line() {
    let dir = tempfile::tempdir().unwrap();
    add_admin(&dir.path().join("store"));
    let host = gentle_lab(dir.path());
    let admin = |args: &[&str]| {
        subsume().arg("lab").args(args).env("SUBSUME_USER", "admin").env("SUBSUME_PASSWORD", PASSWORD).output().unwrap()
    };
    let output = lab("ada", &["reserve", "--start", "+60", "--minutes", "20", &host.address]);
    let (stdout, stderr) = out(&output);
    assert!(output.status.success(), "{stdout}\n{stderr}");
    assert!(stdout.starts_with("reservation 1 for ada:"), "{stdout}");
    assert!(stdout.contains("(20 min)") || stdout.contains("20 min"), "{stdout}");
    // Bob's window overlaps hers: the portal's reason, exit 1.
    let output = lab("bob", &["reserve", "--start", "+70", "--minutes", "5", &host.address]);
    let (stdout, stderr) = out(&output);
    assert!(!output.status.success(), "{stdout}");
    assert!(stderr.contains("overlaps") || stderr.contains("reserved"), "{stderr}");
    for (bad, why) in [("yesterday", "neither +MINUTES nor a UTC time"), ("+x", "+MINUTES takes a number")] {
        let output = lab("bob", &["reserve", "--start", bad, "--minutes", "5", &host.address]);
        assert!(!output.status.success());
        assert!(out(&output).1.contains(why), "{bad}: {}", out(&output).1);
    }
    let output = lab("bob", &["reservations", &host.address]);
    let (stdout, stderr) = out(&output);
    assert!(output.status.success(), "{stderr}");
    let line = stdout.lines().next().unwrap_or_default().to_string();
    assert!(line.contains("ada") && line.contains(" UTC to ") && line.contains("-"), "with its date: {stdout}");
    let output = lab("bob", &["reservations", "--json", &host.address]);
    let listed: serde_json::Value = serde_json::from_slice(&output.stdout).unwrap();
    assert_eq!(listed.as_array().map(Vec::len), Some(1), "{listed}");

    // The owner's settings: admins only.
    let output = lab("ada", &["settings", &host.address]);
    assert!(!output.status.success());
    assert!(out(&output).1.contains("ada is not an admin of this lab"), "{}", out(&output).1);
    let output = admin(&["settings", &host.address]);
    assert!(output.status.success(), "{}", out(&output).1);
    let mut settings: serde_json::Value = serde_json::from_slice(&output.stdout).unwrap();
    assert_eq!(settings["kit"], true, "{settings}");
    settings["max_duration_s"] = serde_json::json!(90.0);
    let file = dir.path().join("settings.json");
    std::fs::write(&file, settings.to_string()).unwrap();
    let output = admin(&["settings", "--set", file.to_str().unwrap(), &host.address]);
    assert!(output.status.success(), "{}", out(&output).1);
    let output = admin(&["settings", &host.address]);
    let stored: serde_json::Value = serde_json::from_slice(&output.stdout).unwrap();
    assert_eq!(stored["max_duration_s"], 90.0, "{stored}");
    settings["max_duration_s"] = serde_json::json!(-1.0);
    std::fs::write(&file, settings.to_string()).unwrap();
    let output = admin(&["settings", "--set", file.to_str().unwrap(), &host.address]);
    assert!(!output.status.success(), "a bad value is refused by the portal");
    let output = admin(&["settings", &host.address]);
    let stored: serde_json::Value = serde_json::from_slice(&output.stdout).unwrap();
    assert_eq!(stored["max_duration_s"], 90.0, "a refused change changed nothing: {stored}");

    let output = lab("bob", &["unreserve", "1", &host.address]);
    assert!(!output.status.success(), "not his: {}", out(&output).0);
    let output = lab("ada", &["unreserve", "1", &host.address]);
    assert!(output.status.success(), "{}", out(&output).1);
    assert_eq!(out(&output).0, "reservation 1 cancelled\n");
    let output = lab("ada", &["reservations", &host.address]);
    assert_eq!(out(&output).0, "no reservations\n");
}

/// With the owner's `end_run_on_breach`, the criteria judge the robot's
/// run too: a driver that passes the preflight (the owner's open preflight
/// world) but meets the robot's wall ends early, aborted, the stop zone
/// named; the outcome says what happened.
#[test]
fn the_owners_criteria_end_a_robot_run_early_when_asked() {
    let dir = tempfile::tempdir().unwrap();
    add_admin(&dir.path().join("store"));
    let commander_path = support::guest("test-commander").display().to_string();
    let boot = lab_robot(dir.path(), "boot.xml", &commander_path, &commander("VEL 0.45 0", 100_000_000), WATCHFUL);
    let host = lab_host(dir.path(), &boot);
    let token = support::login(&host.address, "admin", PASSWORD);
    let open = b"bounds 0 0 40 8\nstart 1 4 0\ngoal 39 4 0.3\n";
    let (status, json) = http(&host.address, "PUT", "/api/v1/worlds/open.world", Some(&token), open);
    assert_eq!(status, 201, "{json}");
    let (_, overview) = http(&host.address, "GET", "/api/v1/lab", Some(&token), b"");
    let mut settings = overview["lab"]["settings"].clone();
    settings["preflight_world"] = serde_json::json!("open.world");
    settings["criteria"]["end_run_on_breach"] = serde_json::Value::Bool(true);
    let (status, json) =
        http(&host.address, "PUT", "/api/v1/lab/settings", Some(&token), settings.to_string().as_bytes());
    assert_eq!(status, 200, "{json}");
    assert_eq!(json["settings"]["criteria"]["end_run_on_breach"], true, "{json}");

    let output = lab("ada", &["submit", "--duration", "60", &host.address]);
    let (stdout, stderr) = out(&output);
    assert_eq!(output.status.code(), Some(1), "{stdout}\n{stderr}");
    let states = told_states(&stdout, 1);
    assert_eq!(states.first().map(String::as_str), Some("checking"), "{stdout}");
    assert!(states.contains(&"queued".to_string()), "the preflight passed: {stdout}");
    assert_eq!(states.last().map(String::as_str), Some("aborted"), "{stdout}");
    assert!(
        stdout.contains("aborted: ended early by the owner's criteria: the envelope's stop zone stopped the robot"),
        "{stdout}"
    );
    let outcome = stdout.lines().find_map(|l| l.strip_prefix("outcome of experiment 1: ")).expect(&stdout).to_string();
    assert!(outcome.contains("stop-zone"), "{outcome}");
    let output = lab("ada", &["show", "1", "--json", &host.address]);
    let record: serde_json::Value = serde_json::from_slice(&output.stdout).unwrap();
    let ran = record["run"]["ran_s"].as_f64().unwrap();
    assert!(ran < 40.0, "it ended at its first stop, long before its 60 s: {ran} s");
}

/// Every `subsume lab` command docs/lab.md shows, as written there, run
/// against a real robot in the order the document gives them (the
/// placeholders filled: HOST, ID, DIR; the submit's component and
/// duration made this test robot's; `router-config` needs no robot and
/// prints into its file). Each either succeeds or, for
/// `cancel` of an experiment already ended, is refused by the portal for
/// that reason: none fails on its arguments or on a route the robot lacks.
#[test]
fn every_lab_command_docs_lab_md_shows_runs_as_written_against_a_robot() {
    let dir = tempfile::tempdir().unwrap();
    add_admin(&dir.path().join("store"));
    let host = gentle_lab(dir.path());
    let commands: Vec<_> = lab_docs::lab_commands().into_iter().filter(|c| !c.serves()).collect();
    assert!(
        commands.len() >= 12,
        "the document's lab commands: {:#?}",
        commands.iter().map(|c| &c.text).collect::<Vec<_>>()
    );
    let driver = format!("driver={}", support::guest("test-commander").display());
    let work = dir.path().join("work");
    std::fs::create_dir_all(&work).unwrap();
    let filling = lab_docs::Filling { host: &host.address, work: &work, component: &driver, duration_s: "2", id: 1 };
    let mut ran = Vec::new();
    for (n, command) in commands.iter().enumerate() {
        let filled = lab_docs::fill(command, n, &filling);
        let admin = ["maintenance", "settings"].contains(&filled.subcommand());
        let (user, password) = if admin { ("admin", PASSWORD) } else { ("ada", RESEARCHER_PASSWORD) };
        let output = subsume()
            .args(&filled.words[1..])
            .current_dir(&work)
            .env("SUBSUME_USER", user)
            .env("SUBSUME_PASSWORD", password)
            .output()
            .unwrap();
        let (stdout, stderr) = out(&output);
        if let Some(file) = &filled.into {
            std::fs::write(file, &output.stdout).unwrap();
        }
        let refused_as_ended = filled.subcommand() == "cancel" && stderr.contains("experiment 1");
        // docs/lab.md, "Several robots": a target is a lab server's.
        let targeted = filled.words.iter().any(|w| w == "--target");
        let refused_as_one_robot = targeted
            && stderr.contains("--target robot=r1: ")
            && stderr.contains("is one robot's portal, not a lab server's; nothing was sent");
        assert_eq!(
            targeted,
            refused_as_one_robot,
            "docs/lab.md's `{}` (as `{}`) against one robot: exit {:?}\n{stdout}\n{stderr}",
            command.text,
            filled.line,
            output.status.code()
        );
        assert!(
            output.status.success() || refused_as_ended || refused_as_one_robot,
            "docs/lab.md's `{}` (as `{}`): exit {:?}\n{stdout}\n{stderr}",
            command.text,
            filled.line,
            output.status.code()
        );
        assert!(!stderr.contains("no such API route"), "`{}`: {stderr}", command.text);
        if filled.subcommand() == "maintenance" {
            let said = if filled.words.iter().any(|w| w == "--end") {
                "the robot is back in service"
            } else {
                "the robot is in maintenance: "
            };
            assert!(stdout.starts_with(said), "`{}`: {stdout}", command.text);
        }
        ran.push(filled.subcommand().to_string());
    }
    for needed in [
        "submit",
        "list",
        "show",
        "results",
        "reserve",
        "reservations",
        "unreserve",
        "kit",
        "maintenance",
        "router-config",
    ] {
        assert!(ran.iter().any(|c| c == needed), "docs/lab.md shows no `lab {needed}`: {ran:?}");
    }
}
