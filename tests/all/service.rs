//! The host as a service on a network, from outside: the real binary with a
//! certificate from a test CA made here with the openssl CLI. The portal,
//! its login cookie (Secure), `/metrics`, the line protocol and the
//! teleoperation WebSocket speak TLS, checked by independent clients
//! (Python's ssl, `openssl s_client`, Debian's Chromium); plain text is
//! refused off loopback unless allowed; `/metrics` parses with the
//! `prometheus_client` package's OpenMetrics parser and counts what
//! happened; the systemd unit passes `systemd-analyze verify`.

use std::io::{BufRead, BufReader, Write};
use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::time::Duration;

use serde_json::Value;

use crate::support::{self, HostProcess};

const PASSWORD: &str = "service-test-password";
/// The demo robot's operator (config/demo-operators).
const OPERATOR: (&str, &str) = ("demo", "demo-token-change-me");

/// A test CA and a server certificate it signed for 127.0.0.1 and
/// localhost, made with the openssl CLI.
struct Pki {
    _dir: tempfile::TempDir,
    ca: PathBuf,
    cert: PathBuf,
    key: PathBuf,
    /// The CA's key, which does not match `cert`.
    ca_key: PathBuf,
}

fn make_pki() -> Pki {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    support::make_test_pki(d);
    Pki {
        ca: d.join("ca.pem"),
        cert: d.join("chain.pem"),
        key: d.join("server.key"),
        ca_key: d.join("ca.key"),
        _dir: dir,
    }
}

/// A running host; [`Host::address`] is what it said after a marker, as
/// `portal on https://` or `teleoperation on tls `.
struct Host {
    process: HostProcess,
}

impl Host {
    fn address(&self, marker: &str) -> String {
        self.process.address_after(marker, Duration::from_secs(60))
    }
}

/// `subsume --store STORE`.
fn subsume(store: &Path) -> Command {
    let mut command = support::subsume();
    command.arg("--store").arg(store);
    command
}

fn add_admin(store: &Path) {
    support::add_user(store, "admin", "admin", &[], PASSWORD);
}

/// `subsume run config/demo.xml ARGS` on free ports; returns once it logged
/// every address in `wait_for`.
fn start(store: &Path, args: &[&str], wait_for: &[&str]) -> Host {
    let mut command = subsume(store);
    command.args(["run", "config/demo.xml", "--param", "teleop.listen=127.0.0.1:0"]);
    command.args(["--param", "teleop.websocket=127.0.0.1:0"]).args(args);
    let host = Host { process: HostProcess::spawn(command) };
    for marker in wait_for {
        host.address(marker);
    }
    host
}

/// `tests/python/service_peer.py ARGS`, its JSON answer.
fn peer(args: &[&str], env: &[(&str, &str)]) -> Value {
    let output = Command::new(support::python())
        .arg(support::repo_root().join("tests/python/service_peer.py"))
        .args(args)
        .envs(env.iter().copied())
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&output.stdout);
    assert!(output.status.success(), "service_peer.py {args:?}: {stdout}\n{}", String::from_utf8_lossy(&output.stderr));
    serde_json::from_str(&stdout).unwrap_or_else(|e| panic!("{e}: {stdout}"))
}

/// The value of the sample `name` whose labels include `labels`.
fn sample(metrics: &Value, family: &str, name: &str, labels: &[(&str, &str)]) -> Option<f64> {
    metrics["families"][family]["samples"].as_array()?.iter().find_map(|s| {
        let matches = s[0] == name && labels.iter().all(|(k, v)| s[1][*k] == *v);
        if matches { s[2].as_f64() } else { None }
    })
}

fn run_to_end(command: &mut Command) -> Output {
    command.stdout(Stdio::piped()).stderr(Stdio::piped()).output().unwrap()
}

#[test]
fn the_portal_teleoperation_and_metrics_speak_tls() {
    let pki = make_pki();
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    add_admin(&store);
    let (cert, key, ca) = (pki.cert.to_str().unwrap(), pki.key.to_str().unwrap(), pki.ca.to_str().unwrap());
    let host = start(
        &store,
        &["--http", "127.0.0.1:0", "--tls-cert", cert, "--tls-key", key],
        &["portal on https://", "teleoperation on tls ", "teleoperation websocket on wss://"],
    );
    let portal = host.address("portal on https://");
    let url = format!("https://{portal}/");

    // The login over TLS, verified against the test CA; its cookie is Secure.
    let login = peer(&["login", &url, ca, "admin", PASSWORD], &[]);
    assert_eq!(login["status"], 200, "{login}");
    let cookie = login["set_cookie"].as_str().unwrap();
    assert!(cookie.starts_with("subsume_session="), "{cookie}");
    for attribute in ["HttpOnly", "SameSite=Strict", "Secure"] {
        assert!(cookie.split("; ").any(|a| a == attribute), "{attribute} missing: {cookie}");
    }

    // Plain HTTP on the TLS port gets no HTTP answer.
    let plain = peer(&["plain-http", &portal], &[]);
    assert_eq!(plain["http"], false, "{plain}");

    // The line protocol over TLS (Python's ssl): log in, get measured,
    // drive in direct mode; stay connected while /metrics is scraped.
    let teleop = host.address("teleoperation on tls ");
    let operator = {
        let (teleop, ca) = (teleop.clone(), ca.to_string());
        std::thread::spawn(move || {
            peer(&["teleop-lines", &teleop, &ca, OPERATOR.0, OPERATOR.1, "25"], &[("HOLD_SECONDS", "4")])
        })
    };
    // openssl s_client is a second, independent client of the same port.
    let mut s_client = Command::new("openssl")
        .args(["s_client", "-connect", &teleop, "-CAfile", ca, "-verify_return_error", "-quiet"])
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    // Logs in as another operator name would fail; a wrong token is refused
    // over TLS as over TCP. QUIT ends the session.
    s_client.stdin.take().unwrap().write_all(b"AUTH demo wrong-token-0000\nQUIT\n").unwrap();
    let s_client = s_client.wait_with_output().unwrap();
    let said = String::from_utf8_lossy(&s_client.stdout);
    assert!(said.starts_with("HELLO subsume "), "s_client got: {said}\n{}", String::from_utf8_lossy(&s_client.stderr));
    assert!(said.contains("ERR "), "{said}");

    // The teleoperation WebSocket over TLS greets with its hello.
    let ws = peer(&["teleop-websocket", &host.address("teleoperation websocket on wss://"), ca], &[]);
    assert!(ws["status"].as_str().unwrap().contains(" 101 "), "{ws}");
    assert_eq!(ws["opcode"], 1, "{ws}");
    assert!(ws["message"].as_str().unwrap().contains("\"hello\""), "{ws}");

    // Metrics while the operator is connected: from loopback, no login.
    std::thread::sleep(Duration::from_secs(2));
    let metrics = peer(&["metrics", &url, ca], &[]);
    assert_eq!(metrics["status"], 200, "{metrics}");
    assert!(metrics["content_type"].as_str().unwrap().starts_with("application/openmetrics-text"));
    let operator = operator.join().unwrap();
    let lines: Vec<&str> = operator["lines"].as_array().unwrap().iter().filter_map(Value::as_str).collect();
    assert!(operator["tls_version"].as_str().unwrap().starts_with("TLSv1."), "{operator}");
    assert!(lines.iter().any(|l| l.starts_with("OK ")), "{lines:?}");
    assert!(lines.iter().any(|l| l.starts_with("MODE direct")), "{lines:?}");

    // Every scrape counts afresh: the loop's cycles go on.
    std::thread::sleep(Duration::from_millis(500));
    let again = peer(&["metrics", &url, ca], &[]);
    let cycles = |m: &Value| sample(m, "subsume_loop_cycles", "subsume_loop_cycles_total", &[]).unwrap();
    assert!(cycles(&again) > cycles(&metrics), "{} then {}", cycles(&metrics), cycles(&again));
    let m = &metrics;
    let avoid = [("component", "avoid"), ("platform", "control")];
    assert_eq!(m["families"]["subsume_component_calls"]["type"], "counter");
    assert!(sample(m, "subsume_component_calls", "subsume_component_calls_total", &avoid).unwrap() > 10.0);
    assert_eq!(m["families"]["subsume_component_call_seconds"]["type"], "histogram");
    let calls = sample(m, "subsume_component_call_seconds", "subsume_component_call_seconds_count", &avoid).unwrap();
    let inf = sample(
        m,
        "subsume_component_call_seconds",
        "subsume_component_call_seconds_bucket",
        &[("component", "avoid"), ("le", "+Inf")],
    )
    .unwrap();
    assert!(calls > 10.0 && inf == calls, "count {calls}, +Inf bucket {inf}");
    assert_eq!(sample(m, "subsume_component_faults", "subsume_component_faults_total", &avoid), Some(0.0));
    assert_eq!(sample(m, "subsume_component_running", "subsume_component_running", &avoid), Some(1.0));
    assert!(sample(m, "subsume_component_messages_in", "subsume_component_messages_in_total", &avoid).unwrap() > 0.0);
    let lateness = sample(m, "subsume_loop_lateness_seconds", "subsume_loop_lateness_seconds_count", &[]).unwrap();
    assert!(lateness > 10.0, "{lateness}");
    assert!(
        sample(m, "subsume_arbiter_switches", "subsume_arbiter_switches_total", &[("arbiter", "arbiter")]).is_some()
    );
    let frames = sample(m, "subsume_serial_frames", "subsume_serial_frames_total", &[("link", "motors")]).unwrap();
    assert!(frames > 0.0, "{frames}");
    assert_eq!(sample(m, "subsume_serial_connected", "subsume_serial_connected", &[("link", "motors")]), Some(1.0));
    let rtt = sample(m, "subsume_teleop_rtt_seconds", "subsume_teleop_rtt_seconds", &[("operator", "demo")]);
    assert!(rtt.is_some_and(|s| s > 0.0 && s < 1.0), "{rtt:?}: {}", m["families"]["subsume_teleop_rtt_seconds"]);
    let released = sample(
        m,
        "subsume_teleop_commands_released",
        "subsume_teleop_commands_released_total",
        &[("network", "teleop")],
    );
    assert!(released.is_some_and(|r| r > 0.0), "{released:?}");
    for reason in ["stale", "duplicate", "full", "superseded"] {
        let dropped = sample(
            m,
            "subsume_teleop_commands_dropped",
            "subsume_teleop_commands_dropped_total",
            &[("reason", reason)],
        );
        assert!(dropped.is_some(), "{reason}");
    }
}

/// A TLS client connection to `address` from the source address `from`,
/// trusting `ca` only.
fn tls_from(
    from: std::net::IpAddr,
    address: &str,
    ca: &Path,
) -> tokio_rustls::rustls::StreamOwned<tokio_rustls::rustls::ClientConnection, std::net::TcpStream> {
    let tcp = support::flood::connect_from(from, address.parse().unwrap()).unwrap();
    tcp.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
    let config = subsume::tls::client_config(ca).unwrap();
    let name = rustls_pki_types::ServerName::try_from("127.0.0.1".to_string()).unwrap();
    let connection = tokio_rustls::rustls::ClientConnection::new(config, name).unwrap();
    tokio_rustls::rustls::StreamOwned::new(connection, tcp)
}

/// Issue 34 over TLS and WebSocket: while 127.0.0.2 holds 200 connections
/// that never finish a TLS handshake (or an upgrade) on the line protocol's
/// and the WebSocket's listeners, and reconnects in a loop beside them, an
/// operator from 127.0.0.3 logs in over each within 1 s, every time.
#[test]
fn no_flood_keeps_an_operator_out_over_tls_or_websocket() {
    use support::flood::Flood;
    let pki = make_pki();
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    add_admin(&store);
    let (cert, key) = (pki.cert.to_str().unwrap(), pki.key.to_str().unwrap());
    let host = start(
        &store,
        &["--http", "off", "--tls-cert", cert, "--tls-key", key],
        &["teleoperation on tls ", "teleoperation websocket on wss://"],
    );
    let lines = host.address("teleoperation on tls ");
    let websocket = host.address("teleoperation websocket on wss://");
    let (attacker, operator) = ("127.0.0.2".parse().unwrap(), "127.0.0.3".parse().unwrap());
    let floods = [
        Flood::start(attacker, lines.parse().unwrap(), 200, b"", None),
        Flood::start(attacker, websocket.parse().unwrap(), 200, b"", None),
    ];
    std::thread::sleep(Duration::from_secs(1));
    let (name, token) = OPERATOR;
    let mut slowest = Duration::ZERO;
    for attempt in 0..10 {
        let started = std::time::Instant::now();
        // The line protocol over TLS.
        let mut stream = tls_from(operator, &lines, &pki.ca);
        let mut reader = BufReader::new(&mut stream);
        let mut line = String::new();
        reader.read_line(&mut line).unwrap();
        assert!(line.starts_with("HELLO subsume "), "attempt {attempt}: {line}");
        drop(reader);
        stream.write_all(format!("AUTH {name} {token}\n").as_bytes()).unwrap();
        let mut reader = BufReader::new(&mut stream);
        line.clear();
        reader.read_line(&mut line).unwrap();
        assert!(line.starts_with("OK authenticated as demo"), "attempt {attempt}: {line}");
        let took = started.elapsed();
        assert!(took < Duration::from_secs(1), "attempt {attempt} over tls took {took:?} to get in");
        slowest = slowest.max(took);
        // The WebSocket over TLS.
        let started = std::time::Instant::now();
        let stream = tls_from(operator, &websocket, &pki.ca);
        let (mut socket, _) = tungstenite::client(format!("wss://{websocket}/teleop"), stream).unwrap();
        let hello = socket.read().unwrap();
        assert!(hello.to_text().unwrap().contains("\"hello\""), "attempt {attempt}: {hello}");
        let auth = serde_json::json!({"type": "auth", "name": name, "token": token}).to_string();
        socket.send(tungstenite::Message::Text(auth.into())).unwrap();
        let ok: Value = serde_json::from_str(socket.read().unwrap().to_text().unwrap()).unwrap();
        assert_eq!(ok["type"], "ok", "attempt {attempt}: {ok}");
        let took = started.elapsed();
        assert!(took < Duration::from_secs(1), "attempt {attempt} over wss took {took:?} to get in");
        slowest = slowest.max(took);
        std::thread::sleep(Duration::from_millis(500));
    }
    for flood in floods {
        let flood = flood.stop();
        eprintln!("slowest login {slowest:?}; a flood: {flood:?}");
        assert!(flood.connects > 1_000, "the flood never flooded: {flood:?}");
    }
}

#[test]
fn the_keyboard_client_speaks_tls() {
    let pki = make_pki();
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    let (cert, key) = (pki.cert.to_str().unwrap(), pki.key.to_str().unwrap());
    let host = start(
        &store,
        &["--http", "off", "--tls-cert", cert, "--tls-key", key, "--duration", "60"],
        &["teleoperation on tls "],
    );
    let address = host.address("teleoperation on tls ");
    // Another CA's certificate is refused, before the terminal is touched.
    let other = make_pki();
    let refused = run_to_end(
        subsume(&store)
            .args(["teleop", &address, "--name", OPERATOR.0, "--token", OPERATOR.1])
            .args(["--tls-ca", other.ca.to_str().unwrap()]),
    );
    let stderr = String::from_utf8_lossy(&refused.stderr);
    assert!(!refused.status.success());
    assert!(stderr.contains(&format!("error: TLS with {address} failed: invalid peer certificate")), "{stderr}");
    // The right CA: `script` gives the client a real terminal; it logs in,
    // is measured, gets direct mode, and quits on q.
    let client = format!(
        "{} teleop {address} --name {} --token {} --tls-ca {}",
        support::BIN,
        OPERATOR.0,
        OPERATOR.1,
        pki.ca.display()
    );
    let mut terminal = support::Terminal::start(&client);
    for text in ["mode direct", "rtt "] {
        terminal.wait_for(text);
    }
    terminal.press(b"q");
    assert!(terminal.wait_for_quit().success());
}

#[test]
fn the_portal_works_in_a_real_browser_over_https() {
    let pki = make_pki();
    // Chromium trusts chains through the test CA's key, and nothing else
    // (the hash of its SubjectPublicKeyInfo).
    let spki = Command::new("sh")
        .arg("-c")
        .arg("openssl x509 -in \"$1\" -pubkey -noout | openssl pkey -pubin -outform der | openssl dgst -sha256 -binary | base64")
        .args(["sh", pki.ca.to_str().unwrap()])
        .output()
        .unwrap();
    let spki = String::from_utf8(spki.stdout).unwrap().trim().to_string();
    assert_eq!(spki.len(), 44, "{spki}");
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    add_admin(&store);
    let (cert, key) = (pki.cert.to_str().unwrap(), pki.key.to_str().unwrap());
    let host = start(&store, &["--http", "127.0.0.1:0", "--tls-cert", cert, "--tls-key", key], &["portal on https://"]);
    let demo = std::fs::read_to_string(support::repo_root().join("config/demo.xml")).unwrap();
    let robot = dir.path().join("browser-demo.xml");
    let using =
        demo.replace("../guest-components/rust/target/wasm32-wasip2/release/avoider.wasm", "browser-avoider.wasm");
    std::fs::write(&robot, &using).unwrap();
    let bad = dir.path().join("broken.xml");
    std::fs::write(&bad, using.replace("arbiter.commands\"/>", "arbiter.command\"/>")).unwrap();
    let artifacts: PathBuf = support::repo_root().join("target/browser-artifacts/https");
    let stdout = support::browser(
        "portal.mjs",
        &artifacts,
        &[("CA_SPKI", spki.as_str())],
        &[
            &format!("https://{}/", host.address("portal on https://")),
            &"admin",
            &PASSWORD,
            &support::guest("avoider"),
            &robot,
            &bad,
        ],
    );
    assert!(stdout.contains("step: over https, the session cookie is Secure"), "{stdout}");
    assert!(stdout.contains("ok: "), "{stdout}");
}

#[test]
fn plain_text_is_refused_off_loopback_unless_allowed() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    add_admin(&store);
    // The portal on every interface without a certificate: refused, before
    // anything starts.
    let refused = run_to_end(subsume(&store).args(["run", "config/demo.xml", "--http", "0.0.0.0:0"]));
    let stderr = String::from_utf8_lossy(&refused.stderr);
    assert!(!refused.status.success());
    assert!(
        stderr.contains("error: the portal would speak plain text on 0.0.0.0:0, which is not a loopback address"),
        "{stderr}"
    );
    assert!(stderr.contains("--allow-plain-http"), "{stderr}");
    // The network platform too, without the portal.
    let refused = run_to_end(subsume(&store).args([
        "run",
        "config/demo.xml",
        "--http",
        "off",
        "--param",
        "teleop.listen=0.0.0.0:0",
        "--param",
        "teleop.websocket=",
    ]));
    let stderr = String::from_utf8_lossy(&refused.stderr);
    assert!(!refused.status.success());
    assert!(stderr.contains("the teleoperation line protocol would speak plain text on 0.0.0.0:0"), "{stderr}");
    // tls="on" needs the host's certificate.
    let refused = run_to_end(subsume(&store).args([
        "run",
        "config/demo.xml",
        "--http",
        "off",
        "--param",
        "teleop.tls=on",
        "--param",
        "teleop.listen=127.0.0.1:0",
        "--param",
        "teleop.websocket=",
    ]));
    let stderr = String::from_utf8_lossy(&refused.stderr);
    assert!(!refused.status.success());
    assert!(
        stderr.contains("parameter 'tls' is on but the host has no certificate: run it with --tls-cert and --tls-key"),
        "{stderr}"
    );
    // The owner may opt in.
    let host = start(
        &store,
        &["--http", "0.0.0.0:0", "--allow-plain-http", "--duration", "30"],
        &["portal on http://", "teleoperation on tcp "],
    );
    assert!(host.address("portal on http://").starts_with("0.0.0.0:"));
}

#[test]
fn bad_certificates_are_refused_with_the_file_named() {
    let pki = make_pki();
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    let run = |extra: &[&str]| {
        let output = run_to_end(subsume(&store).args(["run", "config/demo.xml", "--http", "127.0.0.1:0"]).args(extra));
        assert!(!output.status.success(), "{extra:?} started");
        String::from_utf8_lossy(&output.stderr).to_string()
    };
    let (cert, key, ca_key) = (pki.cert.to_str().unwrap(), pki.key.to_str().unwrap(), pki.ca_key.to_str().unwrap());
    let missing = dir.path().join("missing.pem");
    let stderr = run(&["--tls-cert", missing.to_str().unwrap(), "--tls-key", key]);
    assert!(stderr.contains(&format!("error: cannot read the TLS certificate {}", missing.display())), "{stderr}");
    let stderr = run(&["--tls-cert", cert]);
    assert!(stderr.contains("error: --tls-cert and --tls-key go together"), "{stderr}");
    // The key in place of the certificate, and a key of another certificate.
    let stderr = run(&["--tls-cert", key, "--tls-key", key]);
    assert!(stderr.contains("server.key: no certificate in it"), "{stderr}");
    let stderr = run(&["--tls-cert", cert, "--tls-key", ca_key]);
    assert!(stderr.contains("do not make a TLS identity"), "{stderr}");
    let stderr = run(&["--tls-cert", cert, "--tls-key", cert]);
    assert!(stderr.contains("chain.pem: no private key in it"), "{stderr}");
}

#[test]
fn the_systemd_unit_installs_verifies_and_is_hardened() {
    let analyze = Command::new("systemd-analyze").arg("--version").output();
    assert!(analyze.is_ok_and(|o| o.status.success()), "systemd-analyze is needed (Debian package systemd)");
    let root = support::repo_root();
    let dir = tempfile::tempdir().unwrap();
    // The install script's dry run writes every file under a root of our
    // own and says what it would run.
    let output = Command::new(root.join("packaging/install"))
        .args(["--dry-run", "--simulator", "--device", "/dev/ttyACM0", "--root"])
        .arg(dir.path())
        .arg("--binary")
        .arg(support::BIN)
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&output.stdout);
    assert!(output.status.success(), "{stdout}\n{}", String::from_utf8_lossy(&output.stderr));
    for file in [
        "usr/local/bin/subsume",
        "etc/systemd/system/subsume.service",
        "etc/systemd/system/subsume.service.d/simulator.conf",
        "etc/subsume/subsume.env",
        "etc/subsume/robot.xml",
    ] {
        assert!(dir.path().join(file).is_file(), "{file} not installed: {stdout}");
    }
    // The robot's copy has no debug info (the test binary has line tables).
    let sections = |binary: &Path| {
        let output = Command::new("readelf").args(["-S", "-W"]).arg(binary).output().unwrap();
        assert!(output.status.success(), "readelf: {}", String::from_utf8_lossy(&output.stderr));
        String::from_utf8_lossy(&output.stdout).into_owned()
    };
    let installed = dir.path().join("usr/local/bin/subsume");
    assert!(
        sections(Path::new(env!("CARGO_BIN_EXE_subsume"))).contains(".debug_line"),
        "the test binary has no line tables"
    );
    let installed_sections = sections(&installed);
    assert!(
        !installed_sections.contains(".debug_line") && !installed_sections.contains(".debug_info"),
        "installed with debug info: {stdout}"
    );
    let size = std::fs::metadata(&installed).unwrap().len();
    assert!(
        stdout.contains(&format!("binary -> {} ({} MB, debug info stripped)", installed.display(), size / 1_000_000)),
        "{stdout}"
    );
    assert!(stdout.contains("would run: useradd --system"), "{stdout}");
    assert!(stdout.contains("would run: systemctl enable subsume.service"), "{stdout}");
    let unit = std::fs::read_to_string(dir.path().join("etc/systemd/system/subsume.service")).unwrap();
    assert!(unit.contains("DeviceAllow=/dev/ttyACM0 rw") && !unit.contains("@DEVICE@"), "{unit}");
    for setting in ["User=subsume", "DevicePolicy=closed", "Restart=on-failure", "NoNewPrivileges=yes"] {
        assert!(unit.lines().any(|l| l == setting), "{setting} missing");
    }
    // A bad device is refused before anything is written.
    let refused = Command::new(root.join("packaging/install"))
        .args(["--dry-run", "--device", "ttyUSB0", "--root"])
        .arg(dir.path().join("other"))
        .output()
        .unwrap();
    assert!(!refused.status.success());
    assert!(String::from_utf8_lossy(&refused.stderr).contains("--device must be a path under /dev"));
    assert!(!dir.path().join("other").exists());
    // systemd-analyze verify checks the unit's syntax, every setting's
    // value and that ExecStart's binary exists: point it at the one built.
    let checked = dir.path().join("subsume.service");
    std::fs::write(&checked, unit.replace("/usr/local/bin/subsume", support::BIN)).unwrap();
    let verify = Command::new("systemd-analyze").args(["verify", "--man=no"]).arg(&checked).output().unwrap();
    let said = format!("{}{}", String::from_utf8_lossy(&verify.stdout), String::from_utf8_lossy(&verify.stderr));
    assert!(verify.status.success() && said.trim().is_empty(), "systemd-analyze verify: {said}");
    // Its exposure, as systemd-analyze security rates it offline (0 to
    // 100 here; 1.6 of 10, "OK", when this was written).
    let security = Command::new("systemd-analyze")
        .args(["security", "--offline=yes", "--threshold=25", "--no-pager"])
        .arg(&checked)
        .output()
        .unwrap();
    let said = String::from_utf8_lossy(&security.stdout);
    assert!(security.status.success(), "systemd-analyze security: {said}{}", String::from_utf8_lossy(&security.stderr));
    assert!(said.contains("Overall exposure level for subsume.service"), "{said}");
}

/// The tasks of process `pid` whose name is `name`.
fn tasks_named(pid: u32, name: &str) -> Vec<PathBuf> {
    let Ok(tasks) = std::fs::read_dir(format!("/proc/{pid}/task")) else { return Vec::new() };
    tasks
        .filter_map(Result::ok)
        .map(|t| t.path())
        .filter(|t| std::fs::read_to_string(t.join("comm")).is_ok_and(|c| c.trim() == name))
        .collect()
}

/// Field `n` (1-based, as proc(5) numbers them) of a task's `stat`.
fn stat_field(task: &Path, n: usize) -> i64 {
    let stat = std::fs::read_to_string(task.join("stat")).unwrap();
    // The fields after the command name (which is in parentheses) start at 3.
    let after_name = &stat[stat.rfind(')').unwrap() + 2..];
    after_name.split_whitespace().nth(n - 3).unwrap().parse().unwrap()
}

/// A task's CPUs (`Cpus_allowed_list`) and scheduling policy (field 41 of
/// `stat`: 0 normal, 1 SCHED_FIFO).
fn cpus_and_policy(task: &Path) -> (String, u32) {
    let status = std::fs::read_to_string(task.join("status")).unwrap();
    let cpus = status.lines().find_map(|l| l.strip_prefix("Cpus_allowed_list:")).unwrap().trim().to_string();
    (cpus, stat_field(task, 41) as u32)
}

/// A task's nice value (field 19 of `stat`).
fn nice(task: &Path) -> i64 {
    stat_field(task, 19)
}

/// `--control-cpu` and `--control-fifo` reach the control thread, and only
/// it; a setting the kernel refuses is said in the log and the loop runs.
/// The compile's threads (here without a cache, so the demo's components
/// are compiled) run at the background nice value; the loop's at 0.
#[test]
fn the_control_thread_takes_its_real_time_settings_and_no_other_thread_does() {
    let mut command = support::subsume();
    command.arg("--no-cache");
    command.args([
        "run",
        "config/demo.xml",
        "--http",
        "off",
        "--duration",
        "60",
        "--param",
        "teleop.listen=127.0.0.1:0",
    ]);
    command.args(["--param", "teleop.websocket=127.0.0.1:0", "--control-cpu", "0", "--control-fifo", "10"]);
    let host = support::HostProcess::spawn(command);
    let said = host.word_after("control thread: ", Duration::from_secs(60));
    let pid = host.child.id();
    let control = tasks_named(pid, "subsume-control");
    assert_eq!(control.len(), 1, "{}", host.log());
    let (cpus, policy) = cpus_and_policy(&control[0]);
    assert_eq!(said, "pinned", "{}", host.log());
    assert_eq!(cpus, "0");
    let fifo_refused = host.log().contains("cannot run the control thread under SCHED_FIFO at priority 10");
    if fifo_refused {
        // Without CAP_SYS_NICE: said, and the loop runs on as a normal thread.
        assert_eq!(policy, 0);
    } else {
        assert!(host.log().contains("pinned to cpu 0, SCHED_FIFO at priority 10"), "{}", host.log());
        assert_eq!(policy, 1, "the control thread runs under SCHED_FIFO");
    }
    // Every other thread keeps the defaults (the settings are not the
    // process's, and no thread was made from the control thread after).
    let main = PathBuf::from(format!("/proc/{pid}/task/{pid}"));
    let (main_cpus, main_policy) = cpus_and_policy(&main);
    assert_eq!(main_policy, 0);
    assert_ne!(main_cpus, "0", "only the control thread is pinned");
    for task in tasks_named(pid, "subsume-epoch") {
        assert_eq!(cpus_and_policy(&task).1, 0);
    }
    assert_eq!(nice(&control[0]), 0, "the control thread keeps nice 0");
    assert_eq!(nice(&main), 0);
    // Thread names are cut to 15 bytes in `comm`: the pool's are short.
    let workers = (0..10).flat_map(|i| tasks_named(pid, &format!("compile-pool-{i}"))).collect::<Vec<_>>();
    assert!(!workers.is_empty(), "the demo was compiled, so the compile workers exist: {}", host.log());
    for worker in &workers {
        assert_eq!(nice(worker), 10, "{} runs at the background nice value", worker.display());
    }

    let mut bad = support::subsume();
    bad.args(["run", "config/demo.xml", "--http", "off", "--duration", "1", "--control-fifo", "100"]);
    let output = run_to_end(&mut bad);
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(!output.status.success());
    assert!(
        stderr.contains("invalid value '100' for '--control-fifo <PRIORITY>': must be between 1 and 99, got 100"),
        "{stderr}"
    );
}
