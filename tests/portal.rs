#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic)]
//! The portal end to end: the real binary over real HTTP. A kill -9 during
//! uploads and activations leaves a consistent store and the last activated
//! set comes back; and Debian's headless Chromium, driven by playwright-core
//! (tests/browser/portal.mjs), logs in, uploads, activates, watches and
//! drives.

#[path = "../host/tests/support/mod.rs"]
mod support;

use std::io::{BufRead, BufReader, Read, Write};
use std::net::TcpStream;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::Duration;

use serde_json::Value;

const PASSWORD: &str = "portal-test-password";

struct Host {
    child: Child,
    address: String,
}

impl Drop for Host {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn add_admin(store: &Path) {
    let mut child = Command::new(env!("CARGO_BIN_EXE_subsume"))
        .args(["user", "add", "admin", "--role", "admin", "--password-stdin", "--store"])
        .arg(store)
        .stdin(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    child.stdin.take().unwrap().write_all(format!("{PASSWORD}\n").as_bytes()).unwrap();
    assert!(child.wait().unwrap().success());
}

/// Starts `subsume run ROBOT` with the portal on a free port; returns once
/// the portal listens.
fn start(store: &Path, robot: &Path) -> Host {
    support::guest_dir();
    let mut child = Command::new(env!("CARGO_BIN_EXE_subsume"))
        .current_dir(support::repo_root())
        .args(["--cache-dir", support::cache_dir().to_str().unwrap(), "--store", store.to_str().unwrap(), "run"])
        .arg(robot)
        .args(["--http", "127.0.0.1:0", "--param", "teleop.listen=127.0.0.1:0", "--param", "teleop.websocket="])
        .stderr(Stdio::piped())
        .stdout(Stdio::null())
        .spawn()
        .unwrap();
    let stderr = child.stderr.take().unwrap();
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        for line in BufReader::new(stderr).lines().map_while(Result::ok) {
            if let Some(rest) = line.split("portal on http://").nth(1) {
                let _ = tx.send(rest.split('/').next().unwrap_or("").to_string());
            }
        }
    });
    let address = rx.recv_timeout(Duration::from_secs(60)).expect("the portal did not start");
    Host { child, address }
}

/// One HTTP/1.1 request; returns (status, JSON body).
fn http(address: &str, method: &str, path: &str, token: Option<&str>, body: &[u8]) -> (u16, Value) {
    let mut stream = TcpStream::connect(address).unwrap();
    stream.set_read_timeout(Some(Duration::from_secs(30))).unwrap();
    let auth = token.map(|t| format!("Authorization: Bearer {t}\r\n")).unwrap_or_default();
    let head = format!(
        "{method} {path} HTTP/1.1\r\nHost: {address}\r\n{auth}Content-Length: {}\r\nConnection: close\r\n\r\n",
        body.len()
    );
    stream.write_all(head.as_bytes()).unwrap();
    let _ = stream.write_all(body);
    let mut response = Vec::new();
    let _ = stream.read_to_end(&mut response);
    let text = String::from_utf8_lossy(&response);
    let status = text.split(' ').nth(1).and_then(|s| s.parse().ok()).unwrap_or(0);
    let body = text.split("\r\n\r\n").nth(1).unwrap_or("");
    (status, serde_json::from_str(body).unwrap_or(Value::Null))
}

fn login(address: &str) -> String {
    let body = serde_json::json!({ "name": "admin", "password": PASSWORD }).to_string();
    let (status, json) = http(address, "POST", "/api/v1/login", None, body.as_bytes());
    assert_eq!(status, 200, "{json}");
    json["token"].as_str().unwrap().to_string()
}

/// The demo robot, with its avoider taken from the store by name.
fn demo_using(component: &str) -> String {
    std::fs::read_to_string(support::repo_root().join("config/demo.xml"))
        .unwrap()
        .replace("../guest-components/rust/target/wasm32-wasip2/release/avoider.wasm", &format!("{component}.wasm"))
}

#[test]
fn a_kill_during_uploads_and_activations_leaves_a_consistent_store_that_restarts() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    add_admin(&store);
    let robot = support::repo_root().join("config/demo.xml");
    let wasm = std::fs::read(support::guest("avoider")).unwrap();
    // The moments of the kill, from the start of the upload.
    for (round, delay_ms) in [0u64, 5, 15, 40, 80, 150].into_iter().enumerate() {
        let mut host = start(&store, &robot);
        let token = login(&host.address);
        let (address, name, wasm) = (host.address.clone(), format!("up{round}"), wasm.clone());
        let worker = std::thread::spawn(move || {
            let uri = format!("/api/v1/platforms/control/components/{name}");
            http(&address, "PUT", &uri, Some(&token), &wasm);
            let xml = demo_using(&name);
            let uri = format!("/api/v1/platforms/control/configs/{name}.xml");
            let (_, staged) = http(&address, "PUT", &uri, Some(&token), xml.as_bytes());
            if let Some(id) = staged["set"]["id"].as_u64() {
                http(&address, "POST", &format!("/api/v1/sets/{id}/activate"), Some(&token), b"");
            }
        });
        std::thread::sleep(Duration::from_millis(delay_ms));
        host.child.kill().unwrap(); // SIGKILL
        host.child.wait().unwrap();
        let _ = worker.join();
        let opened = subsume::store::Store::open(&store).unwrap();
        opened.verify().unwrap_or_else(|e| panic!("round {round}: {e}"));
        let active = opened.state().unwrap().active;
        // Restart: the last activated set comes back.
        let host = start(&store, &robot);
        let token = login(&host.address);
        let (status, live) = http(&host.address, "GET", "/api/v1/status", Some(&token), b"");
        assert_eq!(status, 200);
        assert_eq!(live["set"].as_u64(), active, "round {round}: {live}");
    }
    // The audit log recorded what happened, in order, with who did it.
    let entries = subsume::store::Store::open(&store).unwrap().audit_entries(1000).unwrap();
    assert_eq!((entries[0].action.as_str(), entries[0].user.as_str()), ("user-add", "cli"));
    assert_eq!(entries[1].action, "boot");
    assert!(entries.iter().any(|e| e.action == "upload-component" && e.user == "admin" && e.result == "ok"));
}

#[test]
fn the_portal_works_in_a_real_browser() {
    let node_modules = support::repo_root().join("tests/browser/node_modules/playwright-core");
    assert!(node_modules.is_dir(), "run scripts/setup first: it installs playwright-core and chromium");
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    add_admin(&store);
    let host = start(&store, &support::repo_root().join("config/demo.xml"));
    let robot = dir.path().join("browser-demo.xml");
    std::fs::write(&robot, demo_using("browser-avoider")).unwrap();
    let bad = dir.path().join("broken.xml");
    std::fs::write(&bad, demo_using("browser-avoider").replace("arbiter.commands\"/>", "arbiter.command\"/>")).unwrap();
    let artifacts: PathBuf = support::repo_root().join("target/browser-artifacts");
    let output = Command::new("node")
        .current_dir(support::repo_root().join("tests/browser"))
        .env("ARTIFACTS", &artifacts)
        .arg("portal.mjs")
        .arg(format!("http://{}/", host.address))
        .args(["admin", PASSWORD])
        .arg(support::guest("avoider"))
        .arg(&robot)
        .arg(&bad)
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&output.stdout);
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(
        output.status.success(),
        "browser test failed:\n{stdout}\n{stderr}\n(screenshots in {})",
        artifacts.display()
    );
    assert!(stdout.contains("ok: "), "{stdout}");
    for shot in ["1-component", "2-diagnostics", "3-wiring", "4-live", "5-drive", "6-rolled-back"] {
        assert!(artifacts.join(format!("{shot}.png")).is_file(), "{shot}.png");
    }
}
