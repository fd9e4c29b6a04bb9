//! What TLS and metrics cost, through the real binary on loopback.
//!
//! One host per transport (plain HTTP, then TLS with a certificate from a
//! CA made here with the openssl CLI), each running the demo robot with
//! its portal:
//! - upload -> active: a fresh Rust avoider uploaded, a robot file naming it
//!   staged, activated, each request on a new connection (a new handshake
//!   under TLS);
//! - the teleoperation WebSocket round trip: a message the session answers
//!   at once, on one connection;
//! - then, with TLS, what scraping `/metrics` once a second costs the
//!   control loop: the loop-lateness histogram over 15 s without scraping
//!   and over 15 s with a scrape every second, in the same process.
//!
//! `cargo bench --bench service` (SERVICE_BENCH_SECONDS for the two periods)

#[path = "../../tests/all/support.rs"]
mod support;

use std::io::{Read, Write};
use std::net::TcpStream;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::Arc;
use std::time::{Duration, Instant};

use tokio_rustls::rustls;

const ROUNDS: usize = 8;
const ROUND_TRIPS: usize = 2000;
const PASSWORD: &str = "bench-password-1";

fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

/// A connection to the host, plain or TLS.
trait Stream: Read + Write {}
impl<T: Read + Write> Stream for T {}

struct Client {
    tls: Option<Arc<rustls::ClientConfig>>,
}

impl Client {
    fn connect(&self, address: &str) -> Result<Box<dyn Stream>, String> {
        let tcp = TcpStream::connect(address).map_err(|e| e.to_string())?;
        tcp.set_nodelay(true).map_err(|e| e.to_string())?;
        let Some(config) = &self.tls else { return Ok(Box::new(tcp)) };
        let name = rustls::pki_types::ServerName::try_from("127.0.0.1").map_err(|e| e.to_string())?;
        let connection = rustls::ClientConnection::new(config.clone(), name).map_err(|e| e.to_string())?;
        Ok(Box::new(rustls::StreamOwned::new(connection, tcp)))
    }

    /// One request on a new connection; (status, body).
    fn request(
        &self,
        address: &str,
        method: &str,
        path: &str,
        token: &str,
        body: &[u8],
    ) -> Result<(u16, String), String> {
        let mut stream = self.connect(address)?;
        let head = format!(
            "{method} {path} HTTP/1.1\r\nHost: {address}\r\nAuthorization: Bearer {token}\r\nContent-Length: {}\r\nConnection: close\r\n\r\n",
            body.len()
        );
        stream.write_all(head.as_bytes()).map_err(|e| e.to_string())?;
        stream.write_all(body).map_err(|e| e.to_string())?;
        let mut response = Vec::new();
        // A TLS peer that closes without close_notify reads as an error
        // after the whole response: keep what came.
        let _ = stream.read_to_end(&mut response);
        let text = String::from_utf8_lossy(&response).to_string();
        let status = text.split(' ').nth(1).and_then(|s| s.parse().ok()).unwrap_or(0);
        let body = text.split_once("\r\n\r\n").map(|(_, b)| b.to_string()).unwrap_or_default();
        Ok((status, body))
    }
}

struct Host {
    child: Child,
    portal: String,
    websocket: String,
}

impl Drop for Host {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn start(store: &Path, cache: &Path, tls: Option<&Path>) -> Result<Host, String> {
    use std::io::BufRead;
    let mut command = Command::new(env!("CARGO_BIN_EXE_subsume"));
    command
        .current_dir(repo())
        .args(["--store", &store.display().to_string(), "--cache-dir", &cache.display().to_string()])
        .args(["run", "config/demo.xml", "--http", "127.0.0.1:0"])
        .args(["--param", "teleop.listen=127.0.0.1:0", "--param", "teleop.websocket=127.0.0.1:0"])
        .env_remove("SUBSUME_HTTP")
        .env("NO_COLOR", "1")
        .stdout(Stdio::null())
        .stderr(Stdio::piped());
    if let Some(dir) = tls {
        command.arg("--tls-cert").arg(dir.join("server.pem")).arg("--tls-key").arg(dir.join("server.key"));
    }
    let mut child = command.spawn().map_err(|e| e.to_string())?;
    let stderr = child.stderr.take().ok_or("no stderr")?;
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        for line in std::io::BufReader::new(stderr).lines().map_while(Result::ok) {
            for marker in ["portal on http://", "portal on https://", "websocket on ws://", "websocket on wss://"] {
                if let Some(at) = line.find(marker) {
                    let rest = &line[at + marker.len()..];
                    let address = rest.split(['/', ' ']).next().unwrap_or("").to_string();
                    let _ = tx.send((marker.starts_with("portal"), address));
                }
            }
        }
    });
    let (mut portal, mut websocket) = (String::new(), String::new());
    while portal.is_empty() || websocket.is_empty() {
        let (is_portal, address) = rx.recv_timeout(Duration::from_secs(60)).map_err(|_| "the host did not start")?;
        if is_portal { portal = address } else { websocket = address }
    }
    Ok(Host { child, portal, websocket })
}

/// `bytes` with a custom section appended: a new component to every cache.
fn unique(bytes: &[u8], tag: &str) -> Vec<u8> {
    let name = b"bench";
    let content_len = 1 + name.len() + tag.len();
    let mut out = bytes.to_vec();
    out.push(0);
    out.push(content_len as u8);
    out.push(name.len() as u8);
    out.extend_from_slice(name);
    out.extend_from_slice(tag.as_bytes());
    out
}

fn percentile(sorted: &[Duration], p: f64) -> f64 {
    sorted[((sorted.len() - 1) as f64 * p).round() as usize].as_secs_f64() * 1e3
}

fn upload_to_active(
    client: &Client,
    host: &Host,
    token: &str,
    wasm: &[u8],
    label: &str,
) -> Result<Vec<Duration>, String> {
    let demo = std::fs::read_to_string(repo().join("config/demo.xml")).map_err(|e| e.to_string())?;
    let mut times = Vec::new();
    for round in 0..ROUNDS {
        let name = format!("{label}-{round}");
        let robot =
            demo.replace("../guest-components/rust/target/wasm32-wasip2/release/avoider.wasm", &format!("{name}.wasm"));
        let bytes = unique(wasm, &format!("{label} {round} {:?}", Instant::now()));
        let start = Instant::now();
        let uri = format!("/api/v1/platforms/control/components/{name}");
        let (status, body) = client.request(&host.portal, "PUT", &uri, token, &bytes)?;
        if status != 201 {
            return Err(format!("upload: {status} {body}"));
        }
        let uri = format!("/api/v1/platforms/control/configs/{name}.xml");
        let (status, body) = client.request(&host.portal, "PUT", &uri, token, robot.as_bytes())?;
        let json: serde_json::Value = serde_json::from_str(&body).unwrap_or_default();
        let Some(id) = json["set"]["id"].as_u64().filter(|_| status == 201) else {
            return Err(format!("stage: {status} {body}"));
        };
        let (status, body) =
            client.request(&host.portal, "POST", &format!("/api/v1/sets/{id}/activate"), token, b"")?;
        if status != 200 {
            return Err(format!("activate: {status} {body}"));
        }
        times.push(start.elapsed());
    }
    times.sort();
    Ok(times)
}

/// Round trips of a message the session answers at once (a command before
/// logging in: "authenticate first").
fn websocket_round_trips(client: &Client, host: &Host) -> Result<Vec<Duration>, String> {
    use tungstenite::Message;
    let stream = client.connect(&host.websocket)?;
    let scheme = if client.tls.is_some() { "wss" } else { "ws" };
    let url = format!("{scheme}://{}/teleop", host.websocket);
    let (mut socket, _) = tungstenite::client(url.as_str(), stream).map_err(|e| e.to_string())?;
    socket.read().map_err(|e| e.to_string())?; // hello
    let command = r#"{"type":"cmd","seq":1,"time_ms":0,"command":"STOP"}"#;
    let mut times = Vec::with_capacity(ROUND_TRIPS);
    for _ in 0..ROUND_TRIPS {
        let start = Instant::now();
        socket.send(Message::text(command)).map_err(|e| e.to_string())?;
        loop {
            if let Message::Text(_) = socket.read().map_err(|e| e.to_string())? {
                break;
            }
        }
        times.push(start.elapsed());
    }
    times.sort();
    Ok(times)
}

/// The loop-lateness histogram of a scrape: (upper bound s, cumulative).
fn lateness(client: &Client, host: &Host, token: &str) -> Result<Vec<(f64, f64)>, String> {
    let (status, body) = client.request(&host.portal, "GET", "/metrics", token, b"")?;
    if status != 200 {
        return Err(format!("/metrics: {status} {body}"));
    }
    let mut buckets = Vec::new();
    for line in body.lines().filter(|l| l.starts_with("subsume_loop_lateness_seconds_bucket{le=\"")) {
        let rest = &line["subsume_loop_lateness_seconds_bucket{le=\"".len()..];
        let (bound, count) = rest.split_once("\"} ").unwrap_or(("", ""));
        let bound = if bound == "+Inf" { f64::INFINITY } else { bound.parse().unwrap_or(f64::NAN) };
        buckets.push((bound, count.trim().parse().unwrap_or(0.0)));
    }
    Ok(buckets)
}

/// The bucket bound under which `p` of the cycles between two scrapes ran
/// late, and how many cycles that was.
fn late_percentile(before: &[(f64, f64)], after: &[(f64, f64)], p: f64) -> (f64, f64) {
    let counts: Vec<(f64, f64)> = after.iter().zip(before).map(|(a, b)| (a.0, a.1 - b.1)).collect();
    let total = counts.last().map_or(0.0, |c| c.1);
    let bound = counts.iter().find(|c| c.1 >= total * p).map_or(f64::NAN, |c| c.0);
    (bound, total)
}

fn main() -> Result<(), String> {
    let dir = tempfile::tempdir().map_err(|e| e.to_string())?;
    support::make_test_pki(dir.path());
    let store = dir.path().join("store");
    let mut add = Command::new(env!("CARGO_BIN_EXE_subsume"))
        .args(["--store", &store.display().to_string(), "user", "add", "bench", "--role", "admin", "--password-stdin"])
        .stdin(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .map_err(|e| e.to_string())?;
    add.stdin.take().ok_or("no stdin")?.write_all(format!("{PASSWORD}\n").as_bytes()).map_err(|e| e.to_string())?;
    add.wait().map_err(|e| e.to_string())?;
    let config = subsume::tls::client_config(&dir.path().join("ca.pem")).map_err(|e| e.to_string())?;
    let avoider = std::fs::read(repo().join("guest-components/rust/target/wasm32-wasip2/release/avoider.wasm"))
        .map_err(|e| format!("build the guests first (scripts/setup): {e}"))?;
    let seconds: u64 = std::env::var("SERVICE_BENCH_SECONDS").ok().and_then(|s| s.parse().ok()).unwrap_or(15);
    for (label, tls) in [("http", false), ("https", true)] {
        let client = Client { tls: tls.then(|| config.clone()) };
        let host = start(&store, &dir.path().join("cache"), tls.then_some(dir.path()))?;
        let login = serde_json::json!({ "name": "bench", "password": PASSWORD }).to_string();
        let (_, body) = client.request(&host.portal, "POST", "/api/v1/login", "", login.as_bytes())?;
        let token = serde_json::from_str::<serde_json::Value>(&body).map_err(|e| format!("{e}: {body}"))?["token"]
            .as_str()
            .unwrap_or_default()
            .to_string();
        let times = upload_to_active(&client, &host, &token, &avoider, label)?;
        println!(
            "{label}: upload -> active p50 {:.1} ms, min {:.1} ms, max {:.1} ms ({ROUNDS} rounds, 3 requests each on new connections)",
            percentile(&times, 0.5),
            percentile(&times, 0.0),
            percentile(&times, 1.0)
        );
        let trips = websocket_round_trips(&client, &host)?;
        println!(
            "{label}: teleoperation websocket round trip p50 {:.3} ms, p99 {:.3} ms, max {:.3} ms ({ROUND_TRIPS} trips)",
            percentile(&trips, 0.5),
            percentile(&trips, 0.99),
            percentile(&trips, 1.0)
        );
        if tls {
            let start = lateness(&client, &host, &token)?;
            std::thread::sleep(Duration::from_secs(seconds));
            let quiet = lateness(&client, &host, &token)?;
            for _ in 0..seconds {
                std::thread::sleep(Duration::from_secs(1));
                lateness(&client, &host, &token)?;
            }
            let scraped = lateness(&client, &host, &token)?;
            for (what, before, after) in [("no scrapes", &start, &quiet), ("a scrape every second", &quiet, &scraped)] {
                let (p50, cycles) = late_percentile(before, after, 0.5);
                let (p99, _) = late_percentile(before, after, 0.99);
                let (p999, _) = late_percentile(before, after, 0.999);
                println!(
                    "{label}: loop lateness over {seconds} s with {what}: {cycles} cycles; p50 <= {:.3} ms, p99 <= {:.3} ms, p99.9 <= {:.3} ms (bucket bounds)",
                    p50 * 1e3,
                    p99 * 1e3,
                    p999 * 1e3
                );
            }
        }
    }
    Ok(())
}
