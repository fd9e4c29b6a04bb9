//! `subsume deploy` end to end: the built binary against a real `subsume
//! run` with the portal, over real HTTP. A component replaced in the
//! running robot in one command; a robot file and its component in one
//! command; a bad robot file answered with located errors and nothing
//! changed; a component the running robot does not have refused before
//! anything is uploaded.

use std::path::Path;
use std::time::Duration;

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

/// `subsume run ROBOT` with the portal on a free port.
fn start(store: &Path, robot: &Path) -> Host {
    let mut command = subsume();
    command.args(["--store", store.to_str().unwrap(), "run"]).arg(robot).args(["--http", "127.0.0.1:0"]);
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
    let output = subsume()
        .arg("deploy")
        .args(args)
        .arg(address)
        .env("SUBSUME_USER", "admin")
        .env("SUBSUME_PASSWORD", PASSWORD)
        .output()
        .unwrap();
    let text = |b: &[u8]| String::from_utf8_lossy(b).into_owned();
    (output.status.success(), text(&output.stdout), text(&output.stderr))
}

/// The relay's bytes with a custom section: a component no one uploaded.
fn unique_relay(dir: &Path, tag: &str) -> std::path::PathBuf {
    let mut wasm = std::fs::read(support::guest("test-relay")).unwrap();
    let name = b"test";
    wasm.extend_from_slice(&[0, (1 + name.len() + tag.len()) as u8, name.len() as u8]);
    wasm.extend_from_slice(name);
    wasm.extend_from_slice(tag.as_bytes());
    let path = dir.join(format!("relay-{tag}.wasm"));
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

    // A file that is not a component: the portal's check, nothing changed.
    let junk = dir.path().join("junk.wasm");
    std::fs::write(&junk, b"not wasm").unwrap();
    let (ok, _, stderr) = deploy(&host.address, &["--component", &format!("relay={}", junk.display())]);
    assert!(!ok);
    assert!(stderr.contains("component relay: the portal answered 415"), "{stderr}");
    assert_eq!(active(&host.address, "relay").0, third);
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
