//! A lab of several robots end to end (docs/lab.md, "Several robots"): the
//! real binary as a lab server (`subsume lab serve`) and as three robot
//! hosts (`subsume run ... --lab NAME`, simulated robots), joined over real
//! Zenoh sessions on loopback. Each robot reaches the lab through a TCP
//! relay this test owns, so the test can cut one robot's link and bring it
//! back.
//!
//! - In network namespaces the test makes (each host in its own, veth links
//!   into a hub's bridge), three researchers submit nine experiments to the
//!   lab server; they spread over the three robots and all end `done`, with
//!   bundles the independent `mcap` package reads.
//! - An independent Zenoh client (the `eclipse-zenoh` package) sees each
//!   robot's liveliness token with its name, state and profile.
//! - Cutting a robot's link mid-run: the lab marks its experiment `aborted:
//!   robot lost`, and the robot, on its own, aborts it and goes back to its
//!   baseline within its `--lab-lost` setting; with the link back, the lab
//!   fetches what it recorded.
//! - A second lab server of the same name and another secret sees no robot,
//!   and its heartbeats keep no robot's experiment alive.
//! - The same cut in network namespaces the test makes (each host in its
//!   own, veth links into a hub's bridge; the cut is `ip link set ... down`):
//!   the robot aborts by itself, and the other robots run the other
//!   researchers' experiments to `done`.
//! - A robot that refuses an experiment (over its owner's `max-duration`)
//!   gets it back in the queue once; the second refusal ends it `refused`.
//! - A lab server killed with SIGKILL and started again keeps its users,
//!   results and queue, and relearns its robots from their tokens.
//! - The lab's STOP, pressed by users who submitted nothing (a researcher
//!   for one robot, a viewer for all): each robot's experiment ends
//!   `aborted: emergency stop by USER@LAB`, the robot runs its baseline
//!   with its motors still under the lock, the presses are audited, and
//!   the lock is released on the robot. Before it, the submitter's live
//!   view of their robot is that robot's own status, changing while it
//!   runs; without a session it is refused (401).
//! - Messages forged with another secret by an `eclipse-zenoh` client
//!   (`tests/python/lab_forge.py`) straight to a robot's queryables, a
//!   dispatch and an emergency stop, get no answer and change nothing
//!   there; a stale signed one gets an unsigned refusal; the refusals are
//!   audited in one bounded line.
//! - A peer without the secret (`tests/python/lab_attack.py`, with
//!   `eclipse-zenoh`): a rogue complete queryable on a robot's keys
//!   answering garbage and captured signed replies takes nothing
//!   (experiments end `done`, the STOP engages); a captured dispatch
//!   replayed to its robot or another is refused and counted; a junk
//!   flood during a STOP leaves it engaging at once and the robot's audit
//!   log bounded; a robot's token declared again keeps the robot neither
//!   listed nor its experiment alive.
//! - Through a Zenoh router of `eclipse-zenoh` (`tests/python/zenoh_router.py`)
//!   on the config `subsume lab router-config` prints for the lab (as
//!   shipped in `config/zenoh-lab-router.json5` for lab `lab`), over TLS
//!   (`--tls-cert`, `--tls-key`), its access control on: a third user's and another robot's complete queryables on a
//!   robot's keys are never asked, a session without credentials is
//!   refused, and the robot works (`done`, its results, the STOP).
//! - A robot whose owner marked another baseline refuses an experiment the
//!   lab passed (an envelope difference; a platform its submitter does not
//!   hold): back in the queue once with the reason, then `refused`.
//! - The lab server's page in Chromium (`tests/browser/labserver.mjs`):
//!   every robot with its name, profile, state, experiment and time left;
//!   its STOP buttons stop the robots.
//! - Every `subsume lab` command docs/lab.md shows, as written, against a
//!   lab server on https only (a test authority, `SUBSUME_CA`) with one
//!   robot: each succeeds (a submission followed to `done`, its results
//!   with their recording unpacked) or is refused for the documented
//!   reason; the lab server's maintenance holds its queue.

use std::io::{Read, Write};
use std::net::{Shutdown, TcpListener, TcpStream};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use serde_json::Value as Json;

use crate::lab::{WORLD, download_results, read_mcap, robot};
use crate::support::{self, HostProcess, free_port, http};

const PASSWORD: &str = "labnet-test-password";
const RESEARCHERS: [&str; 3] = ["ana", "ben", "cy"];
const LAB: &str = "testlab";
/// A user of the lab who only watches.
const VIEWER: &str = "vic";
/// The robots' `--lab-lost`: how long a robot runs the lab's experiment
/// without hearing its lab.
const LOST_AFTER_S: f64 = 2.0;

/// A TCP relay between one robot and the lab server's Zenoh listener: the
/// robot's link, which the test cuts (every connection closed, new ones
/// refused) and restores (listening again on the same port).
struct Relay {
    port: u16,
    upstream: u16,
    open: Arc<AtomicBool>,
    streams: Arc<Mutex<Vec<TcpStream>>>,
    /// Bytes it passed from the lab server to the robot.
    to_robot: Arc<AtomicU64>,
}

impl Relay {
    fn new(upstream: u16) -> Relay {
        let relay = Relay {
            port: free_port(),
            upstream,
            open: Arc::new(AtomicBool::new(false)),
            streams: Arc::new(Mutex::new(Vec::new())),
            to_robot: Arc::new(AtomicU64::new(0)),
        };
        relay.restore();
        relay
    }

    fn restore(&self) {
        let listener = TcpListener::bind(("127.0.0.1", self.port)).unwrap();
        listener.set_nonblocking(true).unwrap();
        self.open.store(true, Ordering::SeqCst);
        let (open, streams, upstream, to_robot) =
            (self.open.clone(), self.streams.clone(), self.upstream, self.to_robot.clone());
        std::thread::spawn(move || {
            while open.load(Ordering::SeqCst) {
                let Ok((client, _)) = listener.accept() else {
                    std::thread::sleep(Duration::from_millis(10));
                    continue;
                };
                client.set_nonblocking(false).unwrap();
                let Ok(server) = TcpStream::connect(("127.0.0.1", upstream)) else { continue };
                let _ = client.set_nodelay(true);
                let _ = server.set_nodelay(true);
                let mut held = streams.lock().unwrap();
                held.push(client.try_clone().unwrap());
                held.push(server.try_clone().unwrap());
                pipe(client.try_clone().unwrap(), server.try_clone().unwrap(), None);
                pipe(server, client, Some(to_robot.clone()));
            }
        });
    }

    /// Cuts the link: closes every connection and stops listening.
    fn cut(&self) {
        self.open.store(false, Ordering::SeqCst);
        for stream in self.streams.lock().unwrap().drain(..) {
            let _ = stream.shutdown(Shutdown::Both);
        }
        // The accept loop polls every 10 ms: let it drop the listener.
        std::thread::sleep(Duration::from_millis(50));
    }
}

/// Copies `from` to `to` until either ends, adding what it passed to
/// `counted`.
fn pipe(mut from: TcpStream, mut to: TcpStream, counted: Option<Arc<AtomicU64>>) {
    std::thread::spawn(move || {
        let mut buffer = [0u8; 16 << 10];
        while let Ok(n) = from.read(&mut buffer) {
            if n == 0 || to.write_all(&buffer[..n]).is_err() {
                break;
            }
            if let Some(counted) = &counted {
                counted.fetch_add(n as u64, Ordering::SeqCst);
            }
        }
        let _ = to.shutdown(Shutdown::Both);
    });
}

/// `subsume lab serve` on `store`, its Zenoh listener on `zenoh_port`: the
/// process and its portal's address.
fn spawn_server(store: &Path, zenoh_port: u16) -> (HostProcess, String) {
    spawn_server_at(store, "127.0.0.1", &format!("tcp/127.0.0.1:{zenoh_port}"), None, &[])
}

/// `subsume lab serve` on `store`, its portal on `ip`, its Zenoh listener
/// on `listen`, in namespace 0 of `namespaces` when given, with `extra`
/// arguments. Its portal's address: `HOST:PORT`, or `https://HOST:PORT`
/// when `extra` gives it a certificate (`--tls-cert`).
fn spawn_server_at(
    store: &Path,
    ip: &str,
    listen: &str,
    namespaces: Option<&Namespaces>,
    extra: &[String],
) -> (HostProcess, String) {
    let mut command = support::subsume();
    command
        .arg("--store")
        .arg(store)
        .args(["lab", "serve", "--http", &format!("{ip}:0"), "--lab", LAB, "--allow-plain-http"])
        // Its preflights at `normal`: at `background` the tests beside it
        // starve them.
        .args(["--preflight-priority", "normal"])
        .args(["--listen", listen])
        .args(extra)
        .env_remove("SUBSUME_HTTP");
    if namespaces.is_some() {
        // Plain Zenoh between namespaces the test made: a closed network.
        command.arg("--allow-plain-zenoh");
    }
    let command = match namespaces {
        Some(namespaces) => namespaces.inside(0, &command),
        None => command,
    };
    let server = HostProcess::spawn(command);
    let scheme = if extra.iter().any(|a| a == "--tls-cert") { "https" } else { "http" };
    let address = server.address_after(&format!("lab server '{LAB}' on {scheme}://"), Duration::from_secs(120));
    let address = if scheme == "https" { format!("https://{address}") } else { address };
    (server, address)
}

/// `ip ARGS`, which must succeed.
fn ip(args: &[&str]) {
    let output = std::process::Command::new("ip").args(args).output().unwrap();
    assert!(output.status.success(), "ip {}: {}", args.join(" "), String::from_utf8_lossy(&output.stderr));
}

/// Network namespaces this test made: one per host (0 the lab server), each
/// with a veth link into a hub namespace's bridge, and one veth from the
/// test's own namespace into the hub so the test reaches the portals.
/// Removed on drop.
struct Namespaces {
    prefix: String,
    subnet: String,
    hosts: usize,
}

impl Namespaces {
    fn new(hosts: usize) -> Namespaces {
        static MADE: std::sync::atomic::AtomicU32 = std::sync::atomic::AtomicU32::new(0);
        let made = MADE.fetch_add(1, Ordering::SeqCst);
        let pid = std::process::id();
        let namespaces = Namespaces {
            prefix: format!("ln{:x}{made}", pid & 0xffff),
            subnet: format!("10.{}.{}", 100 + pid % 100, made % 250),
            hosts,
        };
        let hub = namespaces.hub();
        ip(&["netns", "add", &hub]);
        ip(&["-n", &hub, "link", "add", "br0", "type", "bridge"]);
        ip(&["-n", &hub, "link", "set", "br0", "up"]);
        for i in 0..hosts {
            let (ns, inner, outer) = (namespaces.ns(i), format!("{}n{i}", namespaces.prefix), namespaces.hub_device(i));
            ip(&["netns", "add", &ns]);
            ip(&["link", "add", &inner, "type", "veth", "peer", "name", &outer]);
            ip(&["link", "set", &inner, "netns", &ns]);
            ip(&["link", "set", &outer, "netns", &hub]);
            ip(&["-n", &hub, "link", "set", &outer, "master", "br0", "up"]);
            ip(&["-n", &ns, "addr", "add", &format!("{}/24", namespaces.address(i)), "dev", &inner]);
            ip(&["-n", &ns, "link", "set", &inner, "up"]);
            ip(&["-n", &ns, "link", "set", "lo", "up"]);
        }
        let (root, outer) = (format!("{}r", namespaces.prefix), format!("{}rh", namespaces.prefix));
        ip(&["link", "add", &root, "type", "veth", "peer", "name", &outer]);
        ip(&["link", "set", &outer, "netns", &hub]);
        ip(&["-n", &hub, "link", "set", &outer, "master", "br0", "up"]);
        ip(&["addr", "add", &format!("{}.254/24", namespaces.subnet), "dev", &root]);
        ip(&["link", "set", &root, "up"]);
        namespaces
    }

    fn hub(&self) -> String {
        format!("{}-hub", self.prefix)
    }

    fn ns(&self, i: usize) -> String {
        format!("{}-{i}", self.prefix)
    }

    /// Host `i`'s link as the hub sees it: setting it down cuts the host off.
    fn hub_device(&self, i: usize) -> String {
        format!("{}h{i}", self.prefix)
    }

    fn address(&self, i: usize) -> String {
        format!("{}.{}", self.subnet, i + 1)
    }

    /// `command` run inside host `i`'s namespace (`ip netns exec`).
    fn inside(&self, i: usize, command: &std::process::Command) -> std::process::Command {
        let mut wrapped = std::process::Command::new("ip");
        wrapped.args(["netns", "exec"]).arg(self.ns(i)).arg(command.get_program()).args(command.get_args());
        for (key, value) in command.get_envs() {
            match value {
                Some(value) => wrapped.env(key, value),
                None => wrapped.env_remove(key),
            };
        }
        if let Some(dir) = command.get_current_dir() {
            wrapped.current_dir(dir);
        }
        wrapped
    }
}

impl Drop for Namespaces {
    fn drop(&mut self) {
        for i in 0..self.hosts {
            let _ = std::process::Command::new("ip").args(["netns", "del", &self.ns(i)]).status();
        }
        let _ = std::process::Command::new("ip").args(["netns", "del", &self.hub()]).status();
    }
}

/// How a robot reaches its lab: a relay on loopback, or its veth link.
enum Link {
    Relay(Relay),
    Veth { hub: String, device: String },
}

impl Link {
    fn cut(&self) {
        match self {
            Link::Relay(relay) => relay.cut(),
            Link::Veth { hub, device } => ip(&["-n", hub, "link", "set", device, "down"]),
        }
    }

    fn restore(&self) {
        match self {
            Link::Relay(relay) => relay.restore(),
            Link::Veth { hub, device } => ip(&["-n", hub, "link", "set", device, "up"]),
        }
    }

    /// Bytes the lab server sent the robot through its relay.
    fn bytes_to_robot(&self) -> u64 {
        match self {
            Link::Relay(relay) => relay.to_robot.load(Ordering::SeqCst),
            Link::Veth { .. } => panic!("a veth link counts no bytes"),
        }
    }
}

struct Robot {
    name: String,
    host: HostProcess,
    address: String,
    link: Link,
}

struct LabNet {
    dir: PathBuf,
    server: HostProcess,
    address: String,
    /// The lab server's Zenoh listener.
    zenoh: String,
    robots: Vec<Robot>,
    /// What `lab serve` was given beside the usual.
    server_args: Vec<String>,
    /// The authority the lab server's certificate is of, when its portal
    /// is on https.
    ca: Option<PathBuf>,
    /// Last: removed after every host has stopped.
    namespaces: Option<Namespaces>,
}

impl LabNet {
    /// A lab server and `robots` robot hosts, each robot joined through its
    /// own relay; returns once the lab lists every robot idle.
    fn start(dir: &Path, robots: usize) -> LabNet {
        LabNet::start_with(dir, robots, None)
    }

    /// As [`LabNet::start`]; with `also`, every robot also connects to
    /// that Zenoh endpoint, with that Zenoh config file.
    fn start_with(dir: &Path, robots: usize, also: Option<(&str, &Path)>) -> LabNet {
        LabNet::start_on(dir, robots, also, None, &[], None)
    }

    /// As [`LabNet::start`], the lab server's portal on https only, with a
    /// certificate of a test authority made in `DIR/pki`
    /// (`support::make_test_pki`); [`LabNet::call`] and the command line
    /// trust that authority (`LabNet::ca`).
    fn start_over_https(dir: &Path, robots: usize) -> LabNet {
        let pki = dir.join("pki");
        std::fs::create_dir_all(&pki).unwrap();
        support::make_test_pki(&pki);
        let (chain, key) = (pki.join("chain.pem"), pki.join("server.key"));
        let args = ["--tls-cert", chain.to_str().unwrap(), "--tls-key", key.to_str().unwrap()];
        LabNet::start_on(dir, robots, None, None, &args, None)
    }

    /// As [`LabNet::start`], each host in its own network namespace (0 the
    /// lab server), joined by veth links into a hub.
    fn start_in_namespaces(dir: &Path, robots: usize) -> LabNet {
        LabNet::start_on(dir, robots, None, Some(Namespaces::new(robots + 1)), &[], None)
    }

    fn start_on(
        dir: &Path,
        robots: usize,
        also: Option<(&str, &Path)>,
        namespaces: Option<Namespaces>,
        server_args: &[&str],
        through: Option<&LabRouter>,
    ) -> LabNet {
        let mut server_args: Vec<String> = server_args.iter().map(|a| a.to_string()).collect();
        support::guest_dir();
        let store = dir.join("lab").join("store");
        support::add_user(&store, "boss", "admin", &[], PASSWORD);
        for name in RESEARCHERS {
            support::add_user(&store, name, "researcher", &["control"], PASSWORD);
        }
        support::add_user(&store, VIEWER, "viewer", &[], PASSWORD);
        let zenoh_port = through.map_or_else(free_port, |router| router.port);
        let server_ip = namespaces.as_ref().map_or_else(|| "127.0.0.1".to_string(), |n| n.address(0));
        let zenoh = match through {
            Some(_) => LabRouter::endpoint(zenoh_port),
            None => format!("tcp/{server_ip}:{zenoh_port}"),
        };
        // Through a router, the lab server is one of its clients (its own
        // user) and listens on nothing.
        let listen = match through {
            Some(router) => {
                server_args.extend(["--zenoh-config".into(), router.client_config("lab-server")]);
                server_args.extend(["--connect".into(), zenoh.clone()]);
                String::new()
            }
            None => zenoh.clone(),
        };
        let (server, address) = spawn_server_at(&store, &server_ip, &listen, namespaces.as_ref(), &server_args);
        // A certificate of `support::make_test_pki`'s folder: trusted by
        // its authority.
        let ca = server_args.iter().position(|a| a == "--tls-cert").map(|at| {
            let chain = Path::new(&server_args[at + 1]);
            chain.with_file_name("ca.pem")
        });
        let secret = store.join("lab.secret");
        let robots = (1..=robots)
            .map(|n| {
                let name = format!("r{n}");
                let home = dir.join(&name);
                std::fs::create_dir_all(&home).unwrap();
                std::fs::write(home.join("robot.xml"), robot(8.0, "")).unwrap();
                std::fs::write(home.join("lab.world"), WORLD).unwrap();
                support::add_user(&home.join("store"), "owner", "admin", &[], PASSWORD);
                let (link, mut connect, robot_ip) = match &namespaces {
                    Some(namespaces) => (
                        Link::Veth { hub: namespaces.hub(), device: namespaces.hub_device(n) },
                        zenoh.clone(),
                        namespaces.address(n),
                    ),
                    None => {
                        let relay = Relay::new(zenoh_port);
                        let connect = match through {
                            Some(_) => LabRouter::endpoint(relay.port),
                            None => format!("tcp/127.0.0.1:{}", relay.port),
                        };
                        (Link::Relay(relay), connect, "127.0.0.1".to_string())
                    }
                };
                let mut command = support::subsume();
                command.arg("--store").arg(home.join("store")).arg("run").arg(home.join("robot.xml"));
                if let Some((endpoint, config)) = also {
                    connect = format!("{connect},{endpoint}");
                    command.arg("--lab-zenoh-config").arg(config);
                }
                if let Some(router) = through {
                    command.arg("--lab-zenoh-config").arg(router.client_config(&name));
                }
                command
                    .args(["--http", &format!("{robot_ip}:0"), "--allow-plain-http"])
                    .args(["--lab", LAB, "--lab-robot", &name])
                    .arg("--lab-secret")
                    .arg(&secret)
                    .args(["--lab-connect", &connect])
                    .args(["--lab-lost", &LOST_AFTER_S.to_string()])
                    .env_remove("SUBSUME_HTTP");
                if namespaces.is_some() {
                    command.arg("--lab-allow-plain");
                }
                let command = match &namespaces {
                    Some(namespaces) => namespaces.inside(n, &command),
                    None => command,
                };
                let host = HostProcess::spawn(command);
                let address = host.portal_address();
                Robot { name, host, address, link }
            })
            .collect();
        let lab = LabNet { dir: dir.to_path_buf(), server, address, zenoh, robots, server_args, ca, namespaces };
        let boss = lab.token("boss");
        lab.wait_robots(&boss, Duration::from_secs(120), |robots| {
            robots.len() == lab.robots.len()
                && robots.iter().all(|r| r["state"] == "idle" && r["baseline_set"].as_u64().is_some())
        });
        lab
    }

    fn token(&self, user: &str) -> String {
        let body = serde_json::json!({ "name": user, "password": PASSWORD }).to_string();
        let (status, json) = self.call_as(None, "POST", "/api/v1/login", &body);
        assert_eq!(status, 200, "{json}");
        json["token"].as_str().unwrap().to_string()
    }

    /// Kills the lab server with SIGKILL.
    fn kill_server(&mut self) {
        support::signal(self.server.child.id(), "KILL");
        support::wait_for_exit(&mut self.server.child, Duration::from_secs(20));
    }

    /// Starts the lab server again on its store and its Zenoh port.
    fn restart_server(&mut self) {
        let ip = self.namespaces.as_ref().map_or_else(|| "127.0.0.1".to_string(), |n| n.address(0));
        let store = self.dir.join("lab").join("store");
        let (server, address) = spawn_server_at(&store, &ip, &self.zenoh, self.namespaces.as_ref(), &self.server_args);
        self.server = server;
        self.address = address;
    }

    fn call(&self, token: &str, method: &str, path: &str, body: &str) -> (u16, Json) {
        self.call_as(Some(token), method, path, body)
    }

    /// One request to the lab server's portal, over https when it is on
    /// https.
    fn call_as(&self, token: Option<&str>, method: &str, path: &str, body: &str) -> (u16, Json) {
        match &self.ca {
            Some(ca) => support::https(&self.address, ca, method, path, token, body.as_bytes()),
            None => http(&self.address, method, path, token, body.as_bytes()),
        }
    }

    fn robots(&self, token: &str) -> Vec<Json> {
        let (status, json) = self.call(token, "GET", "/api/v1/robots", "");
        assert_eq!(status, 200, "{json}");
        json["robots"].as_array().unwrap().clone()
    }

    /// Waits until the lab's robots satisfy `done`; returns them.
    fn wait_robots(&self, token: &str, timeout: Duration, done: impl Fn(&[Json]) -> bool) -> Vec<Json> {
        let deadline = Instant::now() + timeout;
        loop {
            let robots = self.robots(token);
            if done(&robots) {
                return robots;
            }
            assert!(Instant::now() < deadline, "the robots never got there: {robots:#?}\n{}", self.logs());
            std::thread::sleep(Duration::from_millis(100));
        }
    }

    /// Waits until the lab's view (`GET /api/v1/lab`'s `lab`) satisfies
    /// `done`; returns it.
    fn wait_overview(&self, token: &str, timeout: Duration, done: impl Fn(&Json) -> bool) -> Json {
        let deadline = Instant::now() + timeout;
        loop {
            let (status, json) = self.call(token, "GET", "/api/v1/lab", "");
            assert_eq!(status, 200, "{json}");
            if done(&json["lab"]) {
                return json["lab"].clone();
            }
            assert!(Instant::now() < deadline, "the lab's view never got there: {json:#}\n{}", self.logs());
            std::thread::sleep(Duration::from_millis(100));
        }
    }

    fn logs(&self) -> String {
        let mut text = format!("--- lab server:\n{}\n", self.server.log());
        for robot in &self.robots {
            text += &format!("--- {}:\n{}\n", robot.name, robot.host.log());
        }
        text
    }

    /// Stages `xml` as the user's robot file on the lab server; the set.
    /// The set's answer names the lab server's store, never spells it out.
    fn stage(&self, token: &str, file: &str, xml: &str) -> u64 {
        let (status, json) = self.call(token, "PUT", &format!("/api/v1/platforms/control/configs/{file}"), xml);
        assert_eq!(status, 201, "{json}\n{}", self.logs());
        let set = json["set"]["id"].as_u64().unwrap();
        let (status, shown) = self.call(token, "GET", &format!("/api/v1/sets/{set}"), "");
        assert_eq!(status, 200, "{shown}");
        let text = shown.to_string();
        let store = self.dir.join("lab").join("store");
        assert!(text.contains("<store>/") && !text.contains(store.to_str().unwrap()), "{shown:#}");
        set
    }

    fn submit(&self, token: &str, set: u64, duration_s: f64, target: Option<&str>) -> u64 {
        let mut body = serde_json::json!({ "set": set, "duration_s": duration_s, "label": "several robots" });
        if let Some(robot) = target {
            body["target"] = serde_json::json!({ "robot": robot });
        }
        let (status, json) = self.call(token, "POST", "/api/v1/experiments", &body.to_string());
        assert_eq!(status, 201, "{json}\n{}", self.logs());
        json["experiment"]["id"].as_u64().unwrap()
    }

    fn experiment(&self, token: &str, id: u64) -> Json {
        let (status, json) = self.call(token, "GET", &format!("/api/v1/experiments/{id}"), "");
        assert_eq!(status, 200, "{json}");
        json["experiment"].clone()
    }

    /// Waits until experiment `id` is in `state` (or has ended), up to
    /// `timeout`.
    fn wait_for(&self, token: &str, id: u64, state: &str, timeout: Duration) -> Json {
        let deadline = Instant::now() + timeout;
        loop {
            let experiment = self.experiment(token, id);
            let ended =
                ["done", "refused", "cancelled", "aborted", "failed"].contains(&experiment["state"].as_str().unwrap());
            if experiment["state"] == state || ended {
                return experiment;
            }
            assert!(
                Instant::now() < deadline,
                "experiment {id} never reached {state}: {experiment:#}\n{}",
                self.logs()
            );
            std::thread::sleep(Duration::from_millis(100));
        }
    }

    /// Runs `set` for 2 s on robot `robot` as the user of `token`: it ends
    /// `done`, and its results come back with the run's recording whole.
    fn run_to_done_with_whole_results(&self, token: &str, set: u64, robot: &str) {
        let id = self.submit(token, set, 2.0, Some(robot));
        let done = self.wait_for(token, id, "done", Duration::from_secs(180));
        assert_eq!(done["state"], "done", "{done:#}\n{}", self.logs());
        let out = self.dir.join(format!("results-{id}"));
        std::fs::create_dir_all(&out).unwrap();
        let bundle = download_results(&self.address, token, id, &out);
        assert!(read_mcap(&bundle.join("run.mcap"), false)["complete"].as_bool().unwrap());
    }

    fn robot(&self, name: &str) -> &Robot {
        self.robots.iter().find(|r| r.name == name).unwrap()
    }
}

/// The robot's active set, as its own portal says.
fn active_set(robot: &Robot) -> u64 {
    let token = support::login(&robot.address, "owner", PASSWORD);
    let (status, json) = http(&robot.address, "GET", "/api/v1/status", Some(&token), b"");
    assert_eq!(status, 200, "{json}");
    json["set"].as_u64().unwrap()
}

#[test]
fn nine_experiments_of_three_researchers_spread_over_three_robots_in_namespaces_and_end_done() {
    let dir = tempfile::tempdir().unwrap();
    let lab = LabNet::start_in_namespaces(dir.path(), 3);
    let tokens: Vec<String> = RESEARCHERS.iter().map(|r| lab.token(r)).collect();
    let baselines: Vec<u64> = lab.robots.iter().map(active_set).collect();
    // Every researcher stages their own robot file and submits it three
    // times, all at once.
    let ids: Vec<(usize, u64)> = std::thread::scope(|scope| {
        let handles: Vec<_> = tokens
            .iter()
            .enumerate()
            .map(|(r, token)| {
                let lab = &lab;
                scope.spawn(move || {
                    let set = lab.stage(token, &format!("{}.xml", RESEARCHERS[r]), &robot(6.0 + r as f64, ""));
                    (0..3).map(|_| (r, lab.submit(token, set, 3.0, None))).collect::<Vec<_>>()
                })
            })
            .collect();
        handles.into_iter().flat_map(|h| h.join().unwrap()).collect()
    });
    assert_eq!(ids.len(), 9);
    let mut ran_on = std::collections::BTreeSet::new();
    let out = lab.dir.join("results");
    std::fs::create_dir_all(&out).unwrap();
    for (r, id) in &ids {
        let experiment = lab.wait_for(&tokens[*r], *id, "done", Duration::from_secs(300));
        assert_eq!(experiment["state"], "done", "{experiment:#}\n{}", lab.logs());
        let robot = experiment["placement"]["robot"].as_str().unwrap().to_string();
        ran_on.insert(robot);
        let bundle = download_results(&lab.address, &tokens[*r], *id, &out);
        let read = read_mcap(&bundle.join("run.mcap"), false);
        assert!(read["complete"].as_bool().unwrap() && read["in_order_per_channel"].as_bool().unwrap(), "{read:#}");
        assert!(read["channels"]["/planner/cmd"]["count"].as_u64().is_some_and(|n| n > 10), "{read:#}");
        let preflight = read_mcap(&bundle.join("preflight.mcap"), false);
        assert!(preflight["complete"].as_bool().unwrap(), "{preflight:#}");
        // No file spells out a folder of the robots' or the lab server's
        // machines (all of them live under the test's folder).
        let folder = dir.path().display().to_string();
        for entry in walk(&bundle) {
            let bytes = std::fs::read(&entry).unwrap();
            let text = String::from_utf8_lossy(&bytes);
            assert!(!text.contains(&folder), "{} spells out {folder}", entry.display());
        }
    }
    assert!(ran_on.len() >= 2, "nine experiments ran on {ran_on:?} only");
    // Every robot runs its baseline again, and the lab sees them idle.
    let boss = lab.token("boss");
    lab.wait_robots(&boss, Duration::from_secs(30), |robots| robots.iter().all(|r| r["state"] == "idle"));
    let after: Vec<u64> = lab.robots.iter().map(active_set).collect();
    assert_eq!(after, baselines);
}

#[test]
fn a_robot_whose_link_is_cut_mid_run_aborts_by_itself_and_the_lab_marks_it_lost() {
    let dir = tempfile::tempdir().unwrap();
    // The owner's webhook hears of the lost robot (Python's http.server
    // and hmac on the other side).
    let posts = dir.path().join("posts.jsonl");
    let mut receiver = std::process::Command::new(support::python())
        .arg(support::repo_root().join("tests/python/webhook_receiver.py"))
        .args(["a-webhook-secret-of-the-owner", posts.to_str().unwrap()])
        .stdout(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let mut line = String::new();
    std::io::BufRead::read_line(&mut std::io::BufReader::new(receiver.stdout.take().unwrap()), &mut line).unwrap();
    let port = line.trim().strip_prefix("listening on ").unwrap().to_string();
    let hooks = serde_json::json!({ "webhooks": [{
        "url": format!("http://127.0.0.1:{port}/hooks"), "events": ["robot.lost"], "secret": "a-webhook-secret-of-the-owner",
    }]});
    std::fs::create_dir_all(dir.path().join("lab/store")).unwrap();
    std::fs::write(dir.path().join("lab/store/webhooks.json"), hooks.to_string()).unwrap();
    let lab = LabNet::start(dir.path(), 2);
    let ana = lab.token("ana");
    let set = lab.stage(&ana, "ana.xml", &robot(7.0, ""));
    let id = lab.submit(&ana, set, 60.0, Some("r1"));
    let running = lab.wait_for(&ana, id, "running", Duration::from_secs(180));
    assert_eq!(running["state"], "running", "{running:#}");
    let r1 = lab.robot("r1");
    let boss = lab.token("boss");
    lab.wait_robots(&boss, Duration::from_secs(30), |robots| {
        robots.iter().any(|r| r["name"] == "r1" && r["state"] == "running")
    });
    let baseline = {
        let token = support::login(&r1.address, "owner", PASSWORD);
        let (_, json) = http(&r1.address, "GET", "/api/v1/lab", Some(&token), b"");
        json["baseline"].as_u64()
    };
    let from = r1.host.log().lines().count();
    r1.link.cut();
    let cut_at = Instant::now();
    // The lab: the robot's token went with its link.
    let lost = lab.wait_for(&ana, id, "aborted", Duration::from_secs(30));
    assert_eq!(lost["state"], "aborted", "{lost:#}");
    let cause = lost["history"].as_array().unwrap().last().unwrap()["cause"].as_str().unwrap().to_string();
    assert!(cause.contains("robot lost"), "{cause}");
    let deadline = Instant::now() + Duration::from_secs(60);
    loop {
        let text = std::fs::read_to_string(&posts).unwrap_or_default();
        if let Some(post) = text.lines().map(|l| serde_json::from_str::<Json>(l).unwrap()).next() {
            assert_eq!(post["valid"], true, "{post:#}");
            assert_eq!(
                (&post["body"]["event"], &post["body"]["robot"]["name"]),
                (&Json::from("robot.lost"), &Json::from("r1"))
            );
            break;
        }
        assert!(Instant::now() < deadline, "no robot.lost event\n{}", lab.logs());
        std::thread::sleep(Duration::from_millis(100));
    }
    let _ = receiver.kill();
    let _ = receiver.wait();
    // The robot, on its own: the experiment aborted, the baseline back.
    r1.host.lines_until(from, "back to the baseline", Duration::from_secs(30));
    let noticed = cut_at.elapsed();
    assert!(noticed >= Duration::from_secs_f64(LOST_AFTER_S * 0.9), "it aborted after {noticed:?}");
    let deadline = Instant::now() + Duration::from_secs(30);
    let token = support::login(&r1.address, "owner", PASSWORD);
    loop {
        let (_, json) = http(&r1.address, "GET", "/api/v1/experiments", Some(&token), b"");
        let local = json["experiments"].as_array().unwrap().first().cloned().unwrap_or_default();
        if local["state"] == "aborted" {
            let cause = local["history"].as_array().unwrap().last().unwrap()["cause"].as_str().unwrap().to_string();
            assert!(cause.contains("lost its lab"), "{cause}");
            break;
        }
        assert!(Instant::now() < deadline, "the robot's experiment never ended: {local:#}\n{}", lab.logs());
        std::thread::sleep(Duration::from_millis(100));
    }
    if let Some(baseline) = baseline {
        assert_eq!(active_set(r1), baseline);
    }
    // The other robot ran on, and takes work.
    let ben = lab.token("ben");
    let other = lab.stage(&ben, "ben.xml", &robot(6.0, ""));
    let next = lab.submit(&ben, other, 2.0, Some("r2"));
    assert_eq!(lab.wait_for(&ben, next, "done", Duration::from_secs(180))["state"], "done");
    // The link back: the robot shows its token again, idle, and the lab
    // fetches what it recorded before the cut.
    r1.link.restore();
    lab.wait_robots(&boss, Duration::from_secs(60), |robots| {
        robots.iter().any(|r| r["name"] == "r1" && r["state"] == "idle" && r["online"] == true)
    });
    let deadline = Instant::now() + Duration::from_secs(60);
    loop {
        let experiment = lab.experiment(&ana, id);
        let reasons = experiment["reasons"].to_string();
        if reasons.contains("came back: what it recorded was fetched") {
            assert_eq!(experiment["state"], "aborted", "{experiment:#}");
            break;
        }
        assert!(Instant::now() < deadline, "its recording was never fetched: {experiment:#}\n{}", lab.logs());
        std::thread::sleep(Duration::from_millis(200));
    }
    let out = lab.dir.join("results");
    std::fs::create_dir_all(&out).unwrap();
    let bundle = download_results(&lab.address, &ana, id, &out);
    let read = read_mcap(&bundle.join("run.mcap"), true);
    assert!(read["channels"]["/planner/cmd"]["count"].as_u64().is_some_and(|n| n > 0), "{read:#}");
}

#[test]
fn a_lab_server_killed_and_restarted_loses_nothing_and_relearns_its_robots() {
    let dir = tempfile::tempdir().unwrap();
    let mut lab = LabNet::start(dir.path(), 2);
    let ana = lab.token("ana");
    let set = lab.stage(&ana, "ana.xml", &robot(7.0, ""));
    let done = lab.submit(&ana, set, 2.0, None);
    assert_eq!(lab.wait_for(&ana, done, "done", Duration::from_secs(180))["state"], "done");
    // One runs on r1 and one waits for r1 when the server is killed.
    let running = lab.submit(&ana, set, 30.0, Some("r1"));
    assert_eq!(lab.wait_for(&ana, running, "running", Duration::from_secs(180))["state"], "running");
    let waiting = lab.submit(&ana, set, 2.0, Some("r1"));
    assert_eq!(lab.wait_for(&ana, waiting, "queued", Duration::from_secs(120))["state"], "queued");
    let before = lab.experiment(&ana, done);
    let from = lab.robot("r1").host.log().lines().count();
    lab.kill_server();
    // r1 hears its lab no more: it aborts on its own and runs its baseline.
    lab.robot("r1").host.lines_until(from, "back to the baseline", Duration::from_secs(30));
    lab.restart_server();
    // The users, the results and the queue are all there.
    let ana = lab.token("ana");
    assert_eq!(lab.experiment(&ana, done)["history"], before["history"]);
    let out = lab.dir.join("results");
    std::fs::create_dir_all(&out).unwrap();
    let bundle = download_results(&lab.address, &ana, done, &out);
    assert!(read_mcap(&bundle.join("run.mcap"), false)["complete"].as_bool().unwrap());
    // It relearns the robots from their tokens. r1 lost its lab while the
    // server was down and aborted on its own; the lab learns that from it.
    let boss = lab.token("boss");
    lab.wait_robots(&boss, Duration::from_secs(60), |robots| {
        robots.len() == 2 && robots.iter().all(|r| r["online"] == true)
    });
    let ended = lab.wait_for(&ana, running, "aborted", Duration::from_secs(120));
    assert_eq!(ended["state"], "aborted", "{ended:#}");
    assert!(ended.to_string().contains("lost its lab"), "{ended:#}");
    assert_eq!(lab.wait_for(&ana, waiting, "done", Duration::from_secs(180))["state"], "done");
}

#[test]
fn an_independent_zenoh_client_sees_each_robots_token_with_its_name_state_and_profile() {
    let dir = tempfile::tempdir().unwrap();
    let lab = LabNet::start(dir.path(), 2);
    let output = std::process::Command::new(support::python())
        .arg(support::repo_root().join("tests/python/lab_tokens.py"))
        .args([&lab.zenoh, LAB])
        .output()
        .unwrap();
    assert!(output.status.success(), "{}", String::from_utf8_lossy(&output.stderr));
    let tokens: Vec<Json> =
        String::from_utf8_lossy(&output.stdout).lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    let mut names: Vec<&str> = tokens.iter().map(|t| t["name"].as_str().unwrap()).collect();
    names.sort();
    assert_eq!(names, ["r1", "r2"], "{tokens:#?}");
    let boss = lab.token("boss");
    let listed = lab.robots(&boss);
    // Each robot as the lab lists it has the fields openapi.json documents.
    let doc: Json = serde_json::from_str(
        &std::fs::read_to_string(support::repo_root().join("host/src/portal/openapi.json")).unwrap(),
    )
    .unwrap();
    let schema = &doc["paths"]["/api/v1/robots"]["get"]["responses"]["200"]["content"]["application/json"]["schema"];
    let required = schema["properties"]["robots"]["items"]["required"].as_array().unwrap();
    for robot in &listed {
        let mut fields: Vec<&String> = robot.as_object().unwrap().keys().collect();
        let mut documented: Vec<&str> = required.iter().map(|f| f.as_str().unwrap()).collect();
        fields.sort();
        documented.sort();
        assert_eq!(fields, documented, "{robot:#}");
    }
    for token in &tokens {
        assert_eq!(token["state"], "idle");
        assert_eq!(token["body"]["name"], token["name"]);
        let robot = listed.iter().find(|r| r["name"] == token["name"]).unwrap();
        assert_eq!(token["body"]["profile"], robot["profile"], "{token:#}");
        assert_eq!(token["body"]["profile"]["baseline"].as_str().unwrap().len(), 64, "{token:#}");
    }
    // The lab server's /metrics (from loopback): its robots, and the
    // statuses it accepted from them (one a second each, by default).
    let deadline = Instant::now() + Duration::from_secs(30);
    loop {
        let (status, body) = support::http_bytes(&lab.address, "GET", "/metrics", None, b"");
        let text = support::text(&body);
        assert_eq!(status, 200, "{text}");
        let value = |name: &str| {
            text.lines().find_map(|l| l.strip_prefix(name)?.trim().parse::<f64>().ok()).unwrap_or_default()
        };
        let online = value("subsume_lab_robots{online=\"true\"}");
        if online == 2.0 && value("subsume_lab_statuses_total") >= 4.0 && value("subsume_lab_tokens_total") >= 2.0 {
            assert_eq!(value("subsume_lab_foreign_messages_total"), 0.0, "{text}");
            assert_eq!(value("subsume_experiment_queue_length"), 0.0, "{text}");
            break;
        }
        assert!(Instant::now() < deadline, "the lab server's metrics never counted its robots' statuses:\n{text}");
        std::thread::sleep(Duration::from_millis(250));
    }
}

#[test]
fn a_robot_obeys_only_its_own_lab_and_a_second_server_of_the_same_name_keeps_nothing_alive() {
    let dir = tempfile::tempdir().unwrap();
    // A second lab server under the same name, with a secret of its own; r1
    // connects to it too (no gossip: the links stay the ones the test made).
    let rogue_store = dir.path().join("rogue").join("store");
    support::add_user(&rogue_store, "mallory", "admin", &[], PASSWORD);
    let rogue_port = free_port();
    let (rogue, rogue_address) = spawn_server(&rogue_store, rogue_port);
    let config = dir.path().join("robot-zenoh.json5");
    std::fs::write(
        &config,
        r#"{ mode: "peer", listen: { endpoints: [] }, scouting: { multicast: { enabled: false }, gossip: { enabled: false } } }"#,
    )
    .unwrap();
    let rogue_endpoint = format!("tcp/127.0.0.1:{rogue_port}");
    let lab = LabNet::start_with(dir.path(), 1, Some((&rogue_endpoint, &config)));
    // The rogue hears r1's token, signed with another secret, and ignores it:
    // it knows no robot to send work to.
    rogue.lines_until(0, &format!("lab '{LAB}': a robot token was ignored"), Duration::from_secs(60));
    let mallory = support::login(&rogue_address, "mallory", PASSWORD);
    let (status, json) = http(&rogue_address, "GET", "/api/v1/robots", Some(&mallory), b"");
    assert_eq!((status, json["robots"].as_array().map(Vec::len)), (200, Some(0)), "{json}");
    // r1 runs its own lab's experiment; cut from its lab, it aborts it on
    // its own although the rogue's heartbeats still reach it.
    let ana = lab.token("ana");
    let set = lab.stage(&ana, "ana.xml", &robot(7.0, ""));
    let id = lab.submit(&ana, set, 60.0, Some("r1"));
    assert_eq!(lab.wait_for(&ana, id, "running", Duration::from_secs(180))["state"], "running");
    let r1 = lab.robot("r1");
    let from = r1.host.log().lines().count();
    r1.link.cut();
    r1.host.lines_until(from, "back to the baseline", Duration::from_secs(30));
    let lost = lab.wait_for(&ana, id, "aborted", Duration::from_secs(30));
    assert!(lost.to_string().contains("robot lost"), "{lost:#}");
    assert!(!rogue.log().contains("robot 'r1' is"), "{}", rogue.log());
}

#[test]
fn in_network_namespaces_a_robot_whose_link_goes_down_aborts_by_itself_and_the_others_run_on() {
    let dir = tempfile::tempdir().unwrap();
    let lab = LabNet::start_in_namespaces(dir.path(), 3);
    let ana = lab.token("ana");
    let set = lab.stage(&ana, "ana.xml", &robot(7.0, ""));
    let long = lab.submit(&ana, set, 60.0, Some("r1"));
    assert_eq!(lab.wait_for(&ana, long, "running", Duration::from_secs(180))["state"], "running");
    // Two more researchers' experiments, for any robot.
    let others: Vec<(String, u64)> = ["ben", "cy"]
        .iter()
        .flat_map(|user| {
            let token = lab.token(user);
            let set = lab.stage(&token, &format!("{user}.xml"), &robot(6.5, ""));
            (0..2).map(|_| (token.clone(), lab.submit(&token, set, 2.0, None))).collect::<Vec<_>>()
        })
        .collect();
    let r1 = lab.robot("r1");
    let from = r1.host.log().lines().count();
    r1.link.cut();
    let cut_at = Instant::now();
    let lost = lab.wait_for(&ana, long, "aborted", Duration::from_secs(30));
    assert!(lost.to_string().contains("robot lost"), "{lost:#}");
    r1.host.lines_until(from, "back to the baseline", Duration::from_secs(30));
    assert!(cut_at.elapsed() >= Duration::from_secs_f64(LOST_AFTER_S * 0.9));
    let out = lab.dir.join("results");
    std::fs::create_dir_all(&out).unwrap();
    for (token, id) in &others {
        let experiment = lab.wait_for(token, *id, "done", Duration::from_secs(300));
        assert_eq!(experiment["state"], "done", "{experiment:#}\n{}", lab.logs());
        assert_ne!(experiment["placement"]["robot"], "r1", "{experiment:#}");
        let bundle = download_results(&lab.address, token, *id, &out);
        assert!(read_mcap(&bundle.join("run.mcap"), false)["complete"].as_bool().unwrap());
    }
    r1.link.restore();
    let boss = lab.token("boss");
    lab.wait_robots(&boss, Duration::from_secs(60), |robots| {
        robots.iter().any(|r| r["name"] == "r1" && r["state"] == "idle" && r["online"] == true)
    });
}

#[test]
fn a_robot_that_refuses_gets_the_experiment_back_in_the_queue_once_then_it_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let lab = LabNet::start(dir.path(), 1);
    // The robot's owner allows 10 s at most; the lab allows more.
    let r1 = lab.robot("r1");
    let owner = support::login(&r1.address, "owner", PASSWORD);
    let (status, json) = http(&r1.address, "GET", "/api/v1/lab", Some(&owner), b"");
    assert_eq!(status, 200, "{json}");
    let mut settings = json["lab"]["settings"].clone();
    settings["max_duration_s"] = serde_json::json!(10.0);
    let (status, json) =
        http(&r1.address, "PUT", "/api/v1/lab/settings", Some(&owner), settings.to_string().as_bytes());
    assert_eq!(status, 200, "{json}");
    let boss = lab.token("boss");
    lab.wait_robots(&boss, Duration::from_secs(30), |robots| robots.iter().all(|r| r["max_duration_s"] == 10.0));
    // No robot allows 20 s: it goes to r1 anyway, which refuses it twice.
    let ana = lab.token("ana");
    let set = lab.stage(&ana, "ana.xml", &robot(7.0, ""));
    let id = lab.submit(&ana, set, 20.0, None);
    let refused = lab.wait_for(&ana, id, "refused", Duration::from_secs(180));
    assert_eq!(refused["state"], "refused", "{refused:#}");
    let causes: Vec<&str> =
        refused["history"].as_array().unwrap().iter().map(|c| c["cause"].as_str().unwrap()).collect();
    assert_eq!(causes.iter().filter(|c| c.contains("back in the queue once")).count(), 1, "{causes:#?}");
    assert!(causes.last().unwrap().contains("refused it a second time"), "{causes:#?}");
    assert!(refused["reasons"].to_string().contains("max-duration of 10 s"), "{refused:#}");
    assert_eq!(refused["placement"]["refusals"], 2, "{refused:#}");
}

/// A lab server's queue expects each experiment when a robot of its
/// target frees (a running one at its experiment's end, as its signed
/// status says, plus the turnaround), and refuses one no robot started in
/// time, saying why (docs/lab.md, "Nothing silently stuck"): with r1
/// stopped, nobody can say when an experiment for r1 starts.
#[test]
fn a_lab_servers_etas_follow_its_robots_and_one_no_robot_starts_in_time_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let lab = LabNet::start(dir.path(), 1);
    let (boss, ana) = (lab.token("boss"), lab.token("ana"));
    let (_, json) = lab.call(&boss, "GET", "/api/v1/lab", "");
    let mut settings = json["lab"]["settings"].clone();
    settings["stuck_after_min_s"] = serde_json::json!(1);
    let (status, json) = lab.call(&boss, "PUT", "/api/v1/lab/settings", &settings.to_string());
    assert_eq!(status, 200, "{json}");
    let set = lab.stage(&ana, "ana.xml", &robot(8.0, ""));
    let first = lab.submit(&ana, set, 30.0, Some("r1"));
    let running = lab.wait_for(&ana, first, "running", Duration::from_secs(180));
    assert_eq!(running["state"], "running", "{running:#}\n{}", lab.logs());
    let robots = lab.wait_robots(&boss, Duration::from_secs(30), |r| r[0]["ends_unix_ms"].is_u64());
    let ends = robots[0]["ends_unix_ms"].as_u64().unwrap();
    let second = lab.submit(&ana, set, 2.0, Some("r1"));
    let queued = lab.wait_for(&ana, second, "queued", Duration::from_secs(180));
    assert_eq!(queued["state"], "queued", "{queued:#}\n{}", lab.logs());
    let eta = queued["eta_unix_ms"].as_u64().unwrap_or_else(|| panic!("no ETA: {queued:#}"));
    // r1's end as it said it, plus the turnaround (1 s), give or take
    // how its status moved the end since.
    assert!(
        eta + 500 >= ends && eta <= ends + 1000 + 1500,
        "ETA {eta} for r1's end {ends} and a turnaround of 1 s: {queued:#}\n{robots:#?}"
    );
    assert_eq!(queued["place"], 1, "{queued:#}");
    // r1 stopped: neither queued experiment has an ETA, and the one queued
    // after the stop, never estimated, is refused after 1 s.
    let (status, json) = lab.call(&boss, "POST", "/api/v1/robots/r1/stop", "");
    assert_eq!(status, 200, "{json}");
    let aborted = lab.wait_for(&ana, first, "aborted", Duration::from_secs(60));
    assert_eq!(aborted["state"], "aborted", "{aborted:#}");
    lab.wait_robots(&boss, Duration::from_secs(30), |r| r[0]["state"] == "stopped");
    let third = lab.submit(&ana, set, 2.0, Some("r1"));
    let refused = lab.wait_for(&ana, third, "refused", Duration::from_secs(180));
    assert_eq!(refused["state"], "refused", "{refused:#}\n{}", lab.logs());
    let cause = refused["history"].as_array().unwrap().last().unwrap()["cause"].as_str().unwrap().to_string();
    assert!(cause.contains("it did not start in time (it never had an estimate; at least 1 s)"), "{cause}");
    let waiting = lab.experiment(&ana, second);
    assert!(waiting["eta_unix_ms"].is_null(), "{waiting:#}");
}

/// A robot its owner takes out of service is listed `maintenance` by the
/// lab server, which sends its experiments to the other robot; back in
/// service, it takes work again, and what its run left beside the
/// recording (its self-test after the run, its camera's video) reaches the
/// lab server's bundle.
#[test]
fn a_lab_server_routes_around_a_robot_in_maintenance() {
    let dir = tempfile::tempdir().unwrap();
    let lab = LabNet::start(dir.path(), 2);
    let r1 = lab.robot("r1");
    let owner = support::login(&r1.address, "owner", PASSWORD);
    let reason = br#"{"reason": "a bumper to glue"}"#;
    let (status, json) = http(&r1.address, "POST", "/api/v1/lab/maintenance", Some(&owner), reason);
    assert_eq!(status, 200, "{json}");
    let boss = lab.token("boss");
    lab.wait_robots(&boss, Duration::from_secs(30), |robots| {
        robots.iter().any(|r| r["name"] == "r1" && r["state"] == "maintenance")
    });
    let ana = lab.token("ana");
    let set = lab.stage(&ana, "ana.xml", &robot(7.0, ""));
    let ids: Vec<u64> = (0..2).map(|_| lab.submit(&ana, set, 2.0, None)).collect();
    for id in &ids {
        let done = lab.wait_for(&ana, *id, "done", Duration::from_secs(180));
        assert_eq!(done["state"], "done", "{done:#}\n{}", lab.logs());
        assert_eq!(done["placement"]["robot"], "r2", "not to the robot in maintenance: {done:#}");
    }
    let (status, json) = http(&r1.address, "DELETE", "/api/v1/lab/maintenance", Some(&owner), b"");
    assert_eq!(status, 200, "{json}");
    lab.wait_robots(&boss, Duration::from_secs(30), |robots| robots.iter().all(|r| r["state"] == "idle"));
    // Its owner has it test itself after every run: the self-test reaches
    // the lab server's bundle with the run's files.
    let (status, json) = http(&r1.address, "GET", "/api/v1/lab", Some(&owner), b"");
    assert_eq!(status, 200, "{json}");
    let mut settings = json["lab"]["settings"].clone();
    settings["self_test"] = serde_json::json!({"window_ms": 1000});
    let (status, json) =
        http(&r1.address, "PUT", "/api/v1/lab/settings", Some(&owner), settings.to_string().as_bytes());
    assert_eq!(status, 200, "{json}");
    // Ana's set has a camera: its video comes back with the run's files.
    let camera = r#"<component name="camera" source="builtin:camera">
      <param name="source" value="sim:robot-sim"/>
      <param name="width" value="160"/>
      <param name="height" value="120"/>
      <param name="rate" value="5"/>
    </component>"#;
    let set = lab.stage(&ana, "camera.xml", &robot(7.0, camera));
    // The lab server's task: the run is scored there, from the recording
    // that came back.
    let (_, json) = lab.call(&boss, "GET", "/api/v1/lab", "");
    let mut settings = json["lab"]["settings"].clone();
    settings["task"] =
        serde_json::json!({"name": "reach", "goal": {"x": 7.0, "y": 1.0, "radius": 0.5}, "metric": "path_length"});
    let (status, json) = lab.call(&boss, "PUT", "/api/v1/lab/settings", &settings.to_string());
    assert_eq!(status, 200, "{json}");
    let id = lab.submit(&ana, set, 2.0, Some("r1"));
    let done = lab.wait_for(&ana, id, "done", Duration::from_secs(180));
    assert_eq!((&done["state"], &done["placement"]["robot"]), (&Json::from("done"), &Json::from("r1")), "{done:#}");
    let out = dir.path().join("results");
    std::fs::create_dir_all(&out).unwrap();
    let bundle = download_results(&lab.address, &ana, id, &out);
    let test: Json = serde_json::from_slice(&std::fs::read(bundle.join("selftest.json")).unwrap()).unwrap();
    assert_eq!(test["passed"], true, "{test:#}");
    assert!(test["checks"].to_string().contains("feedback messages"), "{test:#}");
    let video = std::fs::metadata(bundle.join("video-camera.webm")).map(|m| m.len()).unwrap_or(0);
    assert!(
        video > 0,
        "the robot's video did not reach the lab: {:?}",
        std::fs::read_dir(&bundle).unwrap().collect::<Vec<_>>()
    );
    let score: Json = serde_json::from_slice(&std::fs::read(bundle.join("score.json")).unwrap()).unwrap();
    assert_eq!(score["task"], "reach", "{score:#}");
    assert_eq!(done["score"], score, "{done:#}");
    assert!(score["sub_scores"]["path_length_m"].as_f64().unwrap() > 0.0, "{score:#}");
    let again = support::subsume().arg("score").arg(&bundle).output().unwrap();
    let said = String::from_utf8_lossy(&again.stdout);
    assert!(again.status.success() && said.contains("identical"), "{said}");
}

/// Every local record robot `robot` holds of lab experiment `lab_id`.
fn local_records(robot: &Robot, lab_id: u64) -> Vec<Json> {
    let token = support::login(&robot.address, "owner", PASSWORD);
    let (status, json) = http(&robot.address, "GET", "/api/v1/experiments", Some(&token), b"");
    assert_eq!(status, 200, "{json}");
    json["experiments"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|r| r["origin"]["lab"] == LAB && r["origin"]["id"] == lab_id)
        .cloned()
        .collect()
}

/// The robot whose answer to a dispatch never comes (its process stopped
/// past the lab's dispatch timeout) gets the experiment withdrawn, not
/// refused; when it comes back it does not start the late copy behind
/// the lab's back (it came after its start-by time), and the experiment
/// then runs once, `done`, on the robot both sides name. The other robot
/// was free meanwhile: the lab holds the experiment until the silent robot
/// says it will not run it.
#[test]
fn a_dispatch_whose_answer_never_comes_is_withdrawn_and_runs_once_where_both_sides_agree() {
    unanswered_dispatch(true);
}

/// The same with the other robot kept out of service, as in a lab of one
/// robot: the experiment can only go back to the robot that did not
/// answer. Once it answers again, the stale dispatch is refused or
/// withdrawn there, and a new one runs it, once, `done`: the lost answer
/// is counted as no refusal. (A copy that a robot took and that ended
/// without running is as if it never came: `robot_link`'s unit test
/// `a_copy_that_ended_without_running_...`.)
#[test]
fn a_dispatch_whose_answer_never_comes_runs_on_the_same_robot_when_it_is_the_only_one() {
    unanswered_dispatch(false);
}

/// Tokens and the experiment of [`queued_for_r1_alone`].
struct QueuedForR1 {
    /// r2's owner's, on r2's own portal.
    owner2: String,
    boss: String,
    ana: String,
    id: u64,
}

/// r2 taken out of service by its owner (so a dispatch can only go to r1),
/// the lab's queue paused, and Ana's experiment of 3 s queued (its
/// preflight passed), her set's robot file `robot(7.0, "")`.
fn queued_for_r1_alone(lab: &LabNet) -> QueuedForR1 {
    let r2 = lab.robot("r2");
    let owner2 = support::login(&r2.address, "owner", PASSWORD);
    let reason = br#"{"reason": "held out for the first dispatch"}"#;
    let (status, json) = http(&r2.address, "POST", "/api/v1/lab/maintenance", Some(&owner2), reason);
    assert_eq!(status, 200, "{json}");
    let boss = lab.token("boss");
    lab.wait_robots(&boss, Duration::from_secs(30), |robots| {
        robots.iter().any(|r| r["name"] == "r2" && r["state"] == "maintenance")
    });
    let (status, json) = lab.call(&boss, "POST", "/api/v1/lab/pause", "");
    assert_eq!(status, 200, "{json}");
    let ana = lab.token("ana");
    let set = lab.stage(&ana, "ana.xml", &robot(7.0, ""));
    let id = lab.submit(&ana, set, 3.0, None);
    let queued = lab.wait_for(&ana, id, "queued", Duration::from_secs(180));
    assert_eq!(queued["state"], "queued", "{queued:#}\n{}", lab.logs());
    QueuedForR1 { owner2, boss, ana, id }
}

/// The body of the two tests above: `free_r2` frees the other robot once
/// the dispatch to r1 went unanswered.
fn unanswered_dispatch(free_r2: bool) {
    let dir = tempfile::tempdir().unwrap();
    let lab = LabNet::start_on(dir.path(), 2, None, None, &["--dispatch-timeout", "3"], None);
    let (r1, r2) = (lab.robot("r1"), lab.robot("r2"));
    let QueuedForR1 { owner2, boss, ana, id } = queued_for_r1_alone(&lab);
    // r1 cannot answer: its process is stopped, its link held open.
    support::signal(r1.host.child.id(), "STOP");
    let (status, json) = lab.call(&boss, "POST", "/api/v1/lab/resume", "");
    assert_eq!(status, 200, "{json}");
    let deadline = Instant::now() + Duration::from_secs(30);
    let after_timeout = loop {
        let experiment = lab.experiment(&ana, id);
        let said = experiment["history"].to_string();
        if said.contains("did not answer its dispatch") || said.contains("refused it") {
            break experiment;
        }
        assert!(Instant::now() < deadline, "no word of the unanswered dispatch: {experiment:#}\n{}", lab.logs());
        std::thread::sleep(Duration::from_millis(100));
    };
    // r2 is free now (or kept out); r1 stays stopped past its start-by time.
    if free_r2 {
        let (status, json) = http(&r2.address, "DELETE", "/api/v1/lab/maintenance", Some(&owner2), b"");
        assert_eq!(status, 200, "{json}");
    }
    std::thread::sleep(Duration::from_secs(3));
    support::signal(r1.host.child.id(), "CONT");
    let ended = lab.wait_for(&ana, id, "done", Duration::from_secs(180));
    assert_eq!(ended["state"], "done", "{ended:#}\n{}", lab.logs());
    let causes = ended["history"].to_string();
    assert!(after_timeout["history"].to_string().contains("did not answer its dispatch"), "{after_timeout:#}");
    assert!(!causes.contains("refused"), "a lost answer is not a refusal: {ended:#}");
    assert_eq!(ended["placement"]["refusals"], 0, "{ended:#}");
    assert!(causes.contains("withdrawn from robot r1"), "{ended:#}\n{}", lab.logs());
    // Both sides agree: the robot the lab names ran it once, as the
    // local experiment the lab names; no other copy ever ran anywhere.
    let ran_on = ended["placement"]["robot"].as_str().unwrap().to_string();
    let local_id = ended["placement"]["local_id"].clone();
    let mut runs = Vec::new();
    for robot in [r1, r2] {
        for record in local_records(robot, id) {
            let started = record["history"].as_array().unwrap().iter().any(|c| c["state"] == "running");
            if started {
                runs.push((robot.name.clone(), record["id"].clone(), record["state"].clone()));
            } else {
                assert_eq!(record["state"], "cancelled", "{}: {record:#}", robot.name);
            }
        }
    }
    assert_eq!(runs, vec![(ran_on, local_id, Json::from("done"))], "{}", lab.logs());
    // r1 refused the late copy, or had it withdrawn before it came.
    let r1_said = robot_audit(r1).iter().map(|line| line.to_string()).collect::<Vec<_>>().join("\n");
    assert!(r1_said.contains("lab-withdraw") || r1_said.contains("after its lab stopped waiting"), "{r1_said}");
}

/// When the lab server is killed, its dispatch to r1 unanswered.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Kill {
    /// The dispatch is on its way (waiting in r1's socket), its answer not
    /// due yet: the server kept nothing of it but where it sent it.
    BeforeTheTimeout,
    /// Just after the server stopped waiting for the answer (it kept the
    /// dispatch's start-by time, to withdraw it).
    AfterTheTimeout,
}

/// A lab server killed (SIGKILL) and started again while its dispatch is
/// unanswered (r1's process stopped, r2 in maintenance), sent but not yet
/// timed out: r1, continued after the restart, finds the dead server's
/// dispatch in its socket before its start-by time. The restarted server
/// holds the experiment on r1 until r1 says whether it runs it, so the
/// experiment runs once, `done`, on the robot the lab names as the local
/// experiment the lab names; no other copy ran anywhere, none stays queued
/// on a robot, and a lost answer is no refusal.
#[test]
fn a_lab_server_killed_while_its_dispatch_is_unanswered_runs_it_once_where_both_sides_agree() {
    dispatch_unanswered_across_a_server_restart(Kill::BeforeTheTimeout);
}

/// As above, the lab server killed just after its dispatch timed out: the
/// restarted server withdraws it from r1 (or waits out its start-by
/// time), r1 refuses the late dispatch it finds, and the experiment runs
/// once, `done`, where both sides say.
#[test]
fn a_lab_server_killed_right_after_its_dispatch_timed_out_runs_it_once_where_both_sides_agree() {
    dispatch_unanswered_across_a_server_restart(Kill::AfterTheTimeout);
}

fn dispatch_unanswered_across_a_server_restart(kill: Kill) {
    let dir = tempfile::tempdir().unwrap();
    // Before the timeout: a start-by time (16 s after the dispatch) r1 is
    // continued well within. After it: the timeout as short as the
    // neighbour's, r1 stopped past it.
    let timeout = match kill {
        Kill::BeforeTheTimeout => "20",
        Kill::AfterTheTimeout => "3",
    };
    // The restarted server relearns its robots within a second: r1's
    // silence then says nothing of whether it has the dispatch.
    let args = ["--dispatch-timeout", timeout, "--relearn", "1"];
    let mut lab = LabNet::start_on(dir.path(), 2, None, None, &args, None);
    let r1_pid = lab.robot("r1").host.child.id();
    let r2_address = lab.robot("r2").address.clone();
    let QueuedForR1 { owner2, boss, ana, id } = queued_for_r1_alone(&lab);
    // r1 cannot answer: its process is stopped, its link held open.
    support::signal(r1_pid, "STOP");
    let sent_before = lab.robot("r1").link.bytes_to_robot();
    let from = lab.server.log().lines().count();
    let (status, json) = lab.call(&boss, "POST", "/api/v1/lab/resume", "");
    assert_eq!(status, 200, "{json}");
    match kill {
        Kill::BeforeTheTimeout => {
            let dispatched = format!("experiment {id}: dispatched to robot r1");
            lab.server.lines_until(from, &dispatched, Duration::from_secs(60));
            // The dispatch, the set's robot file in it, passed r1's relay:
            // it waits in r1's socket.
            let deadline = Instant::now() + Duration::from_secs(30);
            let xml = robot(7.0, "");
            while lab.robot("r1").link.bytes_to_robot() - sent_before < xml.len() as u64 {
                assert!(Instant::now() < deadline, "the dispatch never reached r1's link\n{}", lab.logs());
                std::thread::sleep(Duration::from_millis(20));
            }
            let pending = lab.experiment(&ana, id);
            assert_eq!(pending["state"], "queued", "{pending:#}");
            assert!(!pending["history"].to_string().contains("did not answer"), "{pending:#}");
        }
        Kill::AfterTheTimeout => {
            let deadline = Instant::now() + Duration::from_secs(30);
            loop {
                let experiment = lab.experiment(&ana, id);
                if experiment["history"].to_string().contains("did not answer its dispatch") {
                    break;
                }
                assert!(
                    Instant::now() < deadline,
                    "no word of the unanswered dispatch: {experiment:#}\n{}",
                    lab.logs()
                );
                std::thread::sleep(Duration::from_millis(100));
            }
        }
    }
    lab.kill_server();
    lab.restart_server();
    // r2 is free; r1 stays stopped past the restarted server's relearning,
    // then comes back with the dead server's dispatch in its socket.
    let (status, json) = http(&r2_address, "DELETE", "/api/v1/lab/maintenance", Some(&owner2), b"");
    assert_eq!(status, 200, "{json}");
    let boss = lab.token("boss");
    lab.wait_robots(&boss, Duration::from_secs(60), |robots| {
        robots.iter().any(|r| r["name"] == "r2" && r["state"] == "idle" && r["online"] == true)
    });
    // The stretch r1 stays silent (twice the server's relearning) is the
    // scenario: a server that forgot its dispatch places the experiment
    // on r2 in it, while r1 may still start the dispatch it has.
    std::thread::sleep(Duration::from_secs(2));
    support::signal(r1_pid, "CONT");
    let ana = lab.token("ana");
    let ended = lab.wait_for(&ana, id, "done", Duration::from_secs(180));
    assert_eq!(ended["state"], "done", "{ended:#}\n{}", lab.logs());
    let causes = ended["history"].to_string();
    assert!(!causes.contains("refused"), "a lost answer is not a refusal: {ended:#}\n{}", lab.logs());
    assert_eq!(ended["placement"]["refusals"], 0, "{ended:#}");
    // Both robots idle again: a copy left queued on either would run now.
    lab.wait_robots(&boss, Duration::from_secs(60), |robots| {
        robots.len() == 2 && robots.iter().all(|r| r["state"] == "idle")
    });
    // Both sides agree: the robot the lab names ran it once, as the
    // local experiment the lab names; every other copy was cancelled
    // before it started, on either robot.
    let ran_on = ended["placement"]["robot"].as_str().unwrap().to_string();
    let local_id = ended["placement"]["local_id"].clone();
    let mut runs = Vec::new();
    for robot in &lab.robots {
        for record in local_records(robot, id) {
            let started = record["history"].as_array().unwrap().iter().any(|c| c["state"] == "running");
            if started {
                runs.push((robot.name.clone(), record["id"].clone(), record["state"].clone()));
            } else {
                assert_eq!(record["state"], "cancelled", "{}: {record:#}\n{}", robot.name, lab.logs());
            }
        }
    }
    assert_eq!(runs, vec![(ran_on, local_id, Json::from("done"))], "{ended:#}\n{}", lab.logs());
    // r1 did get the dead server's dispatch: it answered one dispatch of
    // the experiment more than the restarted server sent it.
    let target = format!("lab experiment {id}");
    let answered = robot_audit(lab.robot("r1"))
        .iter()
        .filter(|e| e["action"] == "lab-dispatch" && e["target"] == target.as_str())
        .count();
    let sent = lab.server.log().matches(&format!("experiment {id}: dispatched to robot r1")).count();
    assert_eq!(answered, sent + 1, "{}", lab.logs());
}

/// Robot `robot`'s live status, as its own portal gives it to its owner.
fn robot_status(robot: &Robot) -> Json {
    let token = support::login(&robot.address, "owner", PASSWORD);
    let (status, json) = http(&robot.address, "GET", "/api/v1/status", Some(&token), b"");
    assert_eq!(status, 200, "{json}");
    json
}

/// Waits until `robot`'s motors stand still under its engaged lock: its
/// arbiter holds the lock `by` engaged, and two looks, the loop having run
/// at least 100 cycles between them, see the simulated robot where it was.
fn wait_stopped_by(robot: &Robot, by: &str) -> Json {
    let deadline = Instant::now() + Duration::from_secs(120);
    let mut before = robot_status(robot);
    loop {
        std::thread::sleep(Duration::from_millis(500));
        let now = robot_status(robot);
        let locked = now["arbiter"]["engaged"].as_array().is_some_and(|e| e.iter().any(|l| l["by"] == by));
        let ran = now["cycles"].as_u64().unwrap_or(0) >= before["cycles"].as_u64().unwrap_or(u64::MAX) + 100;
        let still = now["sim"]["distance_travelled_m"] == before["sim"]["distance_travelled_m"]
            && now["sim"]["x"] == before["sim"]["x"]
            && now["sim"]["y"] == before["sim"]["y"];
        if locked && ran && still {
            return now;
        }
        assert!(Instant::now() < deadline, "robot {} never stood still under {by}'s lock: {now:#}", robot.name);
        if ran {
            before = now;
        }
    }
}

#[test]
fn the_submitter_watches_their_robot_live_and_any_user_stops_one_robot_or_all() {
    let dir = tempfile::tempdir().unwrap();
    let lab = LabNet::start(dir.path(), 2);
    let (ana, ben, cy, vic) = (lab.token("ana"), lab.token("ben"), lab.token("cy"), lab.token(VIEWER));
    let baselines: Vec<u64> = lab.robots.iter().map(active_set).collect();
    let ana_set = lab.stage(&ana, "ana.xml", &robot(7.0, ""));
    let ben_set = lab.stage(&ben, "ben.xml", &robot(6.0, ""));
    let on_r1 = lab.submit(&ana, ana_set, 110.0, Some("r1"));
    let on_r2 = lab.submit(&ben, ben_set, 110.0, Some("r2"));
    for (token, id) in [(&ana, on_r1), (&ben, on_r2)] {
        assert_eq!(lab.wait_for(token, id, "running", Duration::from_secs(240))["state"], "running");
    }
    let local_r1 = lab.experiment(&ana, on_r1)["placement"]["local_id"].as_u64().unwrap();

    // The submitter's live view of r1: r1's own status, asked of it now,
    // with ana's experiment in it, and changing while it runs.
    let live =
        |token: Option<&str>, name: &str| http(&lab.address, "GET", &format!("/api/v1/robots/{name}/live"), token, b"");
    let (status, first) = live(Some(&ana), "r1");
    assert_eq!(status, 200, "{first}");
    let first = &first["status"];
    assert_eq!(first["experiment"]["id"], local_r1, "{first:#}");
    assert_eq!(first["experiment"]["submitter"], "ana", "{first:#}");
    assert_ne!(first["set"].as_u64(), Some(baselines[0]), "r1 runs ana's set, not its baseline: {first:#}");
    // It names r1's folders (its store, its robot file's), as r1's own
    // portal does, never spells them out.
    let folders = dir.path().to_str().unwrap();
    assert!(!first.to_string().contains(folders), "{first:#}");
    assert!(first.to_string().contains("<store>/blobs/"), "{first:#}");
    let deadline = Instant::now() + Duration::from_secs(120);
    loop {
        let (status, json) = live(Some(&ana), "r1");
        assert_eq!(status, 200, "{json}");
        let now = &json["status"];
        assert_eq!(now["experiment"]["id"], local_r1, "{now:#}");
        let later = |field: &str| now[field].as_f64().unwrap() > first[field].as_f64().unwrap();
        if later("cycles") && now["sim"]["time_s"].as_f64().unwrap() > first["sim"]["time_s"].as_f64().unwrap() {
            assert!(later("duration_s"), "{now:#}");
            break;
        }
        assert!(Instant::now() < deadline, "r1's live status never changed: {first:#}\n{now:#}");
        std::thread::sleep(Duration::from_millis(200));
    }
    // r2's live view is r2's, with ben's experiment.
    let (status, json) = live(Some(&ben), "r2");
    assert_eq!((status, &json["status"]["experiment"]["submitter"]), (200, &Json::from("ben")), "{json}");
    // Who may not see it, as the portal's matrix says (any logged-in
    // user may): nobody without a session, and no robot the lab lacks.
    for (token, name, expected) in
        [(None, "r1", 401), (Some("not-a-session"), "r1", 401), (Some(ana.as_str()), "r9", 404)]
    {
        let (status, json) = live(token, name);
        assert_eq!(status, expected, "{name} with {token:?}: {json}");
        assert!(json["status"].is_null(), "{json}");
    }
    // Everyone may watch; another's experiment's label and robot file's
    // name are hers and the admins' (as on the robot's own portal).
    let (_, own) = live(Some(&ana), "r1");
    assert_eq!(own["status"]["experiment"]["label"], "several robots", "{own:#}");
    assert!(own["status"]["config"].as_str().unwrap().contains("ana.xml"), "{own:#}");
    for token in [&vic, &ben] {
        let (status, json) = live(Some(token), "r1");
        assert_eq!(status, 200, "a viewer or another researcher may watch: {json}");
        let seen = &json["status"];
        assert_eq!(
            (&seen["experiment"]["submitter"], &seen["experiment"]["label"]),
            (&Json::from("ana"), &Json::from(""))
        );
        assert!(!seen.to_string().contains("ana.xml") && !seen.to_string().contains("several robots"), "{seen:#}");
    }

    // STOP for r1, by a user who submitted nothing: r1's emergency stop.
    let (status, json) = lab.call(&cy, "POST", "/api/v1/robots/r1/stop", "");
    assert_eq!(status, 200, "{json}");
    assert_eq!(json["stopped"], serde_json::json!([{"robot": "r1", "engaged": true, "message": "engaged"}]));
    let stopped_by_cy = format!("cy@{LAB}");
    let aborted = lab.wait_for(&ana, on_r1, "aborted", Duration::from_secs(120));
    assert_eq!(aborted["state"], "aborted", "{aborted:#}\n{}", lab.logs());
    let cause = aborted["history"].as_array().unwrap().last().unwrap()["cause"].as_str().unwrap().to_string();
    assert!(cause.contains(&format!("on robot r1: aborted: emergency stop by {stopped_by_cy}")), "{cause}");
    // On r1 itself: its experiment aborted with that cause, the baseline
    // back, the motors standing still under cy's lock.
    let r1 = lab.robot("r1");
    let stopped = wait_stopped_by(r1, &stopped_by_cy);
    assert_eq!(stopped["set"].as_u64(), Some(baselines[0]), "{stopped:#}");
    assert!(stopped["experiment"].is_null(), "{stopped:#}");
    let owner = support::login(&r1.address, "owner", PASSWORD);
    let (_, json) = http(&r1.address, "GET", &format!("/api/v1/experiments/{local_r1}"), Some(&owner), b"");
    assert_eq!(json["experiment"]["state"], "aborted", "{json:#}");
    assert!(json["experiment"]["reasons"].to_string().contains(&format!("emergency stop by {stopped_by_cy}")));
    // The lab lists r1 stopped by cy; r2 runs on.
    lab.wait_robots(&cy, Duration::from_secs(60), |robots| {
        robots.iter().any(|r| r["name"] == "r1" && r["state"] == "stopped" && r["stopped_by"] == stopped_by_cy.as_str())
    });
    assert_eq!(lab.experiment(&ben, on_r2)["state"], "running", "r2 runs on after r1's STOP");
    // The live view of r1 shows it stopped, too.
    let (status, json) = live(Some(&ana), "r1");
    assert_eq!(status, 200, "{json}");
    assert!(json["status"]["arbiter"]["engaged"].to_string().contains(&stopped_by_cy), "{json:#}");

    // STOP for all, by a viewer: every robot answers; r2's experiment ends.
    let (status, json) = lab.call(&vic, "POST", "/api/v1/robots/stop", "");
    assert_eq!(status, 200, "{json}");
    let mut answers: Vec<(String, bool, String)> = json["stopped"]
        .as_array()
        .unwrap()
        .iter()
        .map(|a| (a["robot"].as_str().unwrap().into(), a["engaged"] == true, a["message"].as_str().unwrap().into()))
        .collect();
    answers.sort();
    assert_eq!(
        answers,
        [("r1".into(), true, "engaged already".into()), ("r2".into(), true, "engaged".into())],
        "{json}"
    );
    let stopped_by_vic = format!("{VIEWER}@{LAB}");
    let aborted = lab.wait_for(&ben, on_r2, "aborted", Duration::from_secs(120));
    assert_eq!(aborted["state"], "aborted", "{aborted:#}\n{}", lab.logs());
    assert!(aborted.to_string().contains(&format!("emergency stop by {stopped_by_vic}")), "{aborted:#}");
    let stopped = wait_stopped_by(lab.robot("r2"), &stopped_by_vic);
    assert_eq!(stopped["set"].as_u64(), Some(baselines[1]), "{stopped:#}");
    lab.wait_robots(&vic, Duration::from_secs(60), |robots| {
        robots.len() == 2 && robots.iter().all(|r| r["state"] == "stopped")
    });
    // The lab's audit log names who pressed which STOP.
    let (status, audit) = lab.call(&lab.token("boss"), "GET", "/api/v1/audit", "");
    assert_eq!(status, 200, "{audit}");
    let mut presses: Vec<(String, String, String)> = audit["entries"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|e| e["action"] == "lab-estop")
        .map(|e| (e["user"].as_str().unwrap().into(), e["target"].as_str().unwrap().into(), e["result"].to_string()))
        .collect();
    presses.sort();
    let ok = Json::from("ok").to_string();
    let expected = [("cy", "robot r1"), (VIEWER, "robot r1"), (VIEWER, "robot r2")]
        .map(|(user, target)| (user.to_string(), target.to_string(), ok.clone()));
    assert_eq!(presses, expected, "{audit:#}");
    // The lock is released on each robot, as always: the lab lists them idle.
    for robot in &lab.robots {
        let owner = support::login(&robot.address, "owner", PASSWORD);
        let (status, json) = http(&robot.address, "POST", "/api/v1/release", Some(&owner), b"");
        assert_eq!(status, 200, "{json}");
    }
    lab.wait_robots(&vic, Duration::from_secs(60), |robots| robots.iter().all(|r| r["state"] == "idle"));
}

#[test]
fn a_dispatch_or_stop_forged_with_another_secret_straight_to_a_robot_is_refused_and_changes_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let lab = LabNet::start(dir.path(), 1);
    let r1 = lab.robot("r1");
    let owner = support::login(&r1.address, "owner", PASSWORD);
    let on_robot = |path: &str| {
        let (status, json) = http(&r1.address, "GET", path, Some(&owner), b"");
        assert_eq!(status, 200, "{path}: {json}");
        json
    };
    let before = (active_set(r1), on_robot("/api/v1/sets")["sets"].clone(), on_robot("/api/v1/experiments"));
    let secret = std::fs::read_to_string(dir.path().join("lab").join("store").join("lab.secret")).unwrap();
    let secret = secret.trim();
    let other = "0f".repeat(32);
    let xml = robot(7.0, "");
    // What a forger on the lab's Zenoh network sends r1 (an
    // `eclipse-zenoh` client, the envelope written from the format), and
    // what r1 must answer: nothing to what is not signed (no signing
    // oracle), an unsigned refusal to a stale signed request, a signed
    // refusal to a well-made one it will not run. The last two show the
    // forger's messages are well made, so the silence above them is the
    // signature's.
    let cases = [
        (serde_json::json!({"op": "dispatch", "secret": other, "config_text": xml}), None),
        (serde_json::json!({"op": "estop", "secret": other}), None),
        (
            serde_json::json!({"op": "dispatch", "secret": secret, "config_text": xml, "skew_ms": -120_000}),
            Some((false, "refused (stale): the request was issued")),
        ),
        (
            serde_json::json!({"op": "dispatch", "secret": secret, "config_text": xml, "duration_s": 1000.0}),
            Some((true, "over this robot's max-duration")),
        ),
    ];
    let list: Vec<&Json> = cases.iter().map(|(case, _)| case).collect();
    let output = std::process::Command::new(support::python())
        .arg(support::repo_root().join("tests/python/lab_forge.py"))
        .args([&lab.zenoh, LAB, "r1", &serde_json::to_string(&list).unwrap()])
        .output()
        .unwrap();
    assert!(output.status.success(), "{}", String::from_utf8_lossy(&output.stderr));
    let answers: Vec<Json> =
        String::from_utf8_lossy(&output.stdout).lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    assert_eq!(answers.len(), cases.len(), "{answers:#?}");
    for ((case, expected), answer) in cases.iter().zip(&answers) {
        let replies = answer["answers"].as_array().unwrap();
        let Some((signed, words)) = expected else {
            assert_eq!(replies.len(), 0, "{case}: no answer to what is not signed: {answer:#}");
            continue;
        };
        assert_eq!(replies.len(), 1, "{case}: {answer:#}");
        let reply = &replies[0];
        if *signed {
            assert_eq!(reply["outcome"], "refused", "{case}: {reply:#}");
            assert_eq!(reply["re"]["robot"], "r1", "{case}: the reply names its robot: {reply:#}");
        } else {
            assert!(reply["refused"].is_string(), "{case}: an unsigned refusal: {reply:#}");
        }
        assert!(reply.to_string().contains(words), "{case}: expected '{words}' in {reply:#}");
    }
    // Nothing changed on r1: no experiment, no new set, the same set runs,
    // no lock; the refusals are in its audit log. The lab lists it idle.
    let after = (active_set(r1), on_robot("/api/v1/sets")["sets"].clone(), on_robot("/api/v1/experiments"));
    assert_eq!(after, before);
    assert_eq!(before.2["experiments"].as_array().map(Vec::len), Some(0), "{:#}", before.2);
    let status = robot_status(r1);
    assert_eq!(status["arbiter"]["engaged"], serde_json::json!([]), "{status:#}");
    // The dispatch r1 read and refused is audited as any; the messages it
    // would not read are counted, and audited in bounded summary lines
    // (at most one every 10 s): two not signed, one stale.
    let deadline = Instant::now() + Duration::from_secs(30);
    loop {
        let audit = on_robot("/api/v1/audit");
        let entries = audit["entries"].as_array().unwrap();
        let dispatches: Vec<&Json> = entries.iter().filter(|e| e["action"] == "lab-dispatch").collect();
        assert_eq!(dispatches.len(), 1, "{audit:#}");
        assert!(dispatches[0]["detail"].as_str().unwrap().contains("max-duration"), "{audit:#}");
        let summaries: Vec<String> = entries
            .iter()
            .filter(|e| e["action"] == "lab-refusals")
            .map(|e| e["detail"].as_str().unwrap().to_string())
            .collect();
        let count = |class: &str| -> u64 {
            summaries
                .iter()
                .filter_map(|s| s.split(&format!("{class} ")).nth(1)?.split([',', ')']).next()?.parse::<u64>().ok())
                .sum()
        };
        if count("not-signed") == 2 && count("stale") == 1 {
            assert!(summaries.len() <= 2, "{summaries:#?}");
            break;
        }
        assert!(Instant::now() < deadline, "the refusals were never audited: {summaries:#?}");
        std::thread::sleep(Duration::from_millis(500));
    }
    let boss = lab.token("boss");
    assert!(lab.robots(&boss).iter().all(|r| r["state"] == "idle" && r["experiment"].is_null()));
}

#[test]
fn a_robot_whose_baseline_differs_refuses_an_envelope_or_platform_change_back_to_the_queue_once_then_refused() {
    let dir = tempfile::tempdir().unwrap();
    let lab = LabNet::start(dir.path(), 1);
    let r1 = lab.robot("r1");
    let owner = support::login(&r1.address, "owner", PASSWORD);
    let boss = lab.token("boss");
    let ana = lab.token("ana");
    let running = active_set(r1);
    let reference = lab.robots(&boss)[0]["baseline_set"].as_u64().unwrap();
    // The lab checks ana's experiments against r1's first baseline (its
    // reference); r1's owner then marks another baseline, which the
    // experiment, checked again on r1, changes in a way ana may not.
    let cases = [
        (
            "envelope",
            r#"source="builtin:envelope" rate="20""#,
            r#"source="builtin:envelope" rate="10""#,
            "changes the rate of envelope 'envelope' from 10 to 20: an experiment runs with the robot's own envelope settings",
        ),
        (
            "network",
            r#"source="builtin:teleop" rate="50""#,
            r#"source="builtin:teleop" rate="40""#,
            "changes platform network of the baseline, which ana does not hold",
        ),
    ];
    for (n, (what, from, to, expected)) in cases.iter().enumerate() {
        let previous = lab.robots(&boss)[0]["profile"]["baseline"].clone();
        let xml = robot(8.0, "").replace(from, to);
        assert_ne!(xml, robot(8.0, ""), "{what}");
        let path = format!("/api/v1/platforms/control/configs/owner-{n}.xml");
        let (status, json) = http(&r1.address, "PUT", &path, Some(&owner), xml.as_bytes());
        assert_eq!(status, 201, "{what}: {json}");
        let set = json["set"]["id"].as_u64().unwrap();
        let body = serde_json::json!({ "set": set }).to_string();
        let (status, json) = http(&r1.address, "PUT", "/api/v1/lab/baseline", Some(&owner), body.as_bytes());
        assert_eq!(status, 200, "{what}: {json}");
        // The lab sees r1's new profile and stores its baseline.
        lab.wait_robots(&boss, Duration::from_secs(120), |robots| {
            robots[0]["profile"]["baseline"] != previous
                && robots[0]["baseline_set"].as_u64().is_some_and(|s| s != reference)
                && robots[0]["state"] == "idle"
        });
        let staged = lab.stage(&ana, &format!("ana-{n}.xml"), &robot(7.0, ""));
        let id = lab.submit(&ana, staged, 5.0, None);
        let refused = lab.wait_for(&ana, id, "refused", Duration::from_secs(240));
        assert_eq!(refused["state"], "refused", "{what}: {refused:#}\n{}", lab.logs());
        let causes: Vec<&str> =
            refused["history"].as_array().unwrap().iter().map(|c| c["cause"].as_str().unwrap()).collect();
        assert_eq!(causes.iter().filter(|c| c.contains("back in the queue once")).count(), 1, "{what}: {causes:#?}");
        assert!(causes.last().unwrap().contains("refused it a second time"), "{what}: {causes:#?}");
        assert!(
            causes.iter().filter(|c| c.contains("refused it")).all(|c| c.contains(expected)),
            "{what}: {causes:#?}"
        );
        assert!(refused["reasons"].to_string().contains(expected), "{what}: {refused:#}");
        assert_eq!(refused["placement"]["refusals"], 2, "{what}: {refused:#}");
        // Nothing ran on r1: no experiment there, its set runs on.
        let (_, json) = http(&r1.address, "GET", "/api/v1/experiments", Some(&owner), b"");
        assert_eq!(json["experiments"], serde_json::json!([]), "{what}: {json:#}");
        assert_eq!(active_set(r1), running, "{what}");
    }
}

/// The lab server's page in Chromium (tests/browser/labserver.mjs): a
/// viewer sees both robots with their name, profile, state, the experiment
/// one runs and its time left; watches it live; its STOP stops that robot
/// only, STOP ALL the other too. The experiment ends aborted by the
/// viewer, and each robot's motors stand still under the viewer's lock.
#[test]
fn the_lab_servers_page_lists_every_robot_and_its_stop_buttons_work_in_a_real_browser() {
    let dir = tempfile::tempdir().unwrap();
    let lab = LabNet::start(dir.path(), 2);
    let ana = lab.token("ana");
    let set = lab.stage(&ana, "ana.xml", &robot(7.0, ""));
    let duration_s = 100.0;
    let id = lab.submit(&ana, set, duration_s, Some("r1"));
    assert_eq!(lab.wait_for(&ana, id, "running", Duration::from_secs(240))["state"], "running");
    let vic = lab.token(VIEWER);
    let listed = lab.wait_robots(&vic, Duration::from_secs(60), |robots| {
        robots.iter().any(|r| r["name"] == "r1" && r["experiment"] == id && r["time_left_s"].is_f64())
    });
    let expected: Vec<Json> = ["r1", "r2"]
        .iter()
        .map(|name| {
            let robot = listed.iter().find(|r| r["name"] == *name).unwrap();
            let running = *name == "r1";
            serde_json::json!({
                "name": name,
                "profile": robot["profile"]["id"],
                "state": if running { "running" } else { "idle" },
                "experiment": if running { Json::from(id) } else { Json::Null },
                "duration_s": duration_s,
            })
        })
        .collect();
    let artifacts: PathBuf = support::repo_root().join("target/browser-artifacts");
    let url = format!("http://{}/", lab.address);
    let robots = serde_json::to_string(&expected).unwrap();
    let stdout = support::browser("labserver.mjs", &artifacts, &[], &[&url, &VIEWER, &PASSWORD, &robots]);
    assert!(stdout.contains("ok: r1, r2 listed and stopped"), "{stdout}");
    for shot in ["1-robots", "2-live", "3-stopped-one", "4-stopped-all"] {
        assert!(artifacts.join(format!("labserver-{shot}.png")).is_file(), "{shot}");
    }
    // What the clicks did: the experiment aborted by the viewer, both
    // robots' motors still under the viewer's lock, each press audited.
    let by = format!("{VIEWER}@{LAB}");
    let aborted = lab.wait_for(&ana, id, "aborted", Duration::from_secs(120));
    assert_eq!(aborted["state"], "aborted", "{aborted:#}\n{}", lab.logs());
    assert!(aborted.to_string().contains(&format!("emergency stop by {by}")), "{aborted:#}");
    for robot in &lab.robots {
        wait_stopped_by(robot, &by);
    }
    let (_, audit) = lab.call(&lab.token("boss"), "GET", "/api/v1/audit", "");
    let presses =
        audit["entries"].as_array().unwrap().iter().filter(|e| e["action"] == "lab-estop" && e["user"] == VIEWER);
    assert_eq!(presses.count(), 3, "r1, then r1 and r2: {audit:#}");
}

/// An attack of `tests/python/lab_attack.py` (an `eclipse-zenoh` peer
/// without the lab's secret) running beside the lab: its output line by
/// line; its standard input held open until [`Attack::finish`].
struct Attack {
    child: std::process::Child,
    lines: std::sync::mpsc::Receiver<String>,
}

impl Attack {
    fn start(args: &[&str]) -> Attack {
        Self::trusting(None, args)
    }

    /// As [`Attack::start`], its TLS links trusting authority `ca` (PEM).
    fn trusting(ca: Option<&str>, args: &[&str]) -> Attack {
        let mut command = std::process::Command::new(support::python());
        if let Some(ca) = ca {
            command.env("ZENOH_ROOT_CA", ca);
        }
        let mut child = command
            .arg(support::repo_root().join("tests/python/lab_attack.py"))
            .args(args)
            .stdin(std::process::Stdio::piped())
            .stdout(std::process::Stdio::piped())
            .spawn()
            .unwrap();
        let stdout = child.stdout.take().unwrap();
        let (sender, lines) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            for line in std::io::BufRead::lines(std::io::BufReader::new(stdout)).map_while(Result::ok) {
                if sender.send(line).is_err() {
                    break;
                }
            }
        });
        Attack { child, lines }
    }

    /// Its next line of output.
    fn line(&self, timeout: Duration) -> String {
        self.lines.recv_timeout(timeout).unwrap_or_else(|e| panic!("the attack said nothing within {timeout:?}: {e}"))
    }

    /// Closes its standard input; its last line, as JSON.
    fn finish(mut self, timeout: Duration) -> Json {
        drop(self.child.stdin.take());
        let line = self.line(timeout);
        let _ = self.child.wait();
        serde_json::from_str(&line).unwrap_or_else(|e| panic!("{e}: {line}"))
    }
}

/// A value of the lab server's /metrics (0 when it is not there).
fn lab_metric(lab: &LabNet, name: &str) -> f64 {
    let (status, body) = support::http_bytes(&lab.address, "GET", "/metrics", None, b"");
    assert_eq!(status, 200);
    let text = support::text(&body);
    text.lines().find_map(|l| l.strip_prefix(name)?.trim().parse::<f64>().ok()).unwrap_or_default()
}

/// Robot `robot`'s audit entries, as its owner sees them.
fn robot_audit(robot: &Robot) -> Vec<Json> {
    let owner = support::login(&robot.address, "owner", PASSWORD);
    let (status, json) = http(&robot.address, "GET", "/api/v1/audit", Some(&owner), b"");
    assert_eq!(status, 200, "{json}");
    json["entries"].as_array().unwrap().clone()
}

#[test]
fn a_rogue_complete_queryable_on_a_robots_keys_takes_nothing_experiments_end_done_and_the_stop_engages() {
    let dir = tempfile::tempdir().unwrap();
    let lab = LabNet::start(dir.path(), 1);
    let secret = std::fs::read_to_string(dir.path().join("lab").join("store").join("lab.secret")).unwrap();
    // The rogue answers every query on r1's keys at once, before r1 does.
    let rogue = Attack::start(&["rogue", &lab.zenoh, LAB, "r1", secret.trim()]);
    assert_eq!(rogue.line(Duration::from_secs(60)), "ready");
    let ana = lab.token("ana");
    let set = lab.stage(&ana, "ana.xml", &robot(7.0, ""));
    // Its results come from r1, whole, past the rogue's chunks.
    lab.run_to_done_with_whole_results(&ana, set, "r1");
    // The lab's STOP reaches r1 through the rogue's answers.
    let long = lab.submit(&ana, set, 110.0, Some("r1"));
    assert_eq!(lab.wait_for(&ana, long, "running", Duration::from_secs(180))["state"], "running");
    let pressed = Instant::now();
    let (status, json) = lab.call(&ana, "POST", "/api/v1/robots/r1/stop", "");
    let took = pressed.elapsed();
    assert_eq!(status, 200, "{json}");
    assert_eq!(json["stopped"], serde_json::json!([{"robot": "r1", "engaged": true, "message": "engaged"}]));
    eprintln!("the lab's STOP, a rogue answering first: engaged in {took:?}");
    assert!(took < Duration::from_secs(5), "{took:?}");
    wait_stopped_by(lab.robot("r1"), &format!("ana@{LAB}"));
    let aborted = lab.wait_for(&ana, long, "aborted", Duration::from_secs(120));
    assert!(aborted.to_string().contains("emergency stop by ana@testlab"), "{aborted:#}");
    // The rogue was asked every time, and everything it said was skipped.
    let answered = rogue.finish(Duration::from_secs(30));
    for op in ["dispatch", "results", "file", "estop"] {
        assert!(answered["answered"][op].as_u64().unwrap() > 0, "{op}: {answered}");
    }
    assert!(lab_metric(&lab, "subsume_lab_skipped_replies_total") >= 5.0 * 4.0, "{}", lab.logs());
}

/// `subsume lab router-config ARGS`, the real binary: its stdout, or its
/// exit code and stderr.
fn router_config(args: &[&str]) -> Result<String, (Option<i32>, String)> {
    let output = std::process::Command::new(support::BIN)
        .args(["lab", "router-config"])
        .args(args)
        .env("NO_COLOR", "1")
        .output()
        .unwrap();
    let stdout = String::from_utf8(output.stdout).unwrap();
    let stderr = String::from_utf8_lossy(&output.stderr).into_owned();
    if output.status.success() { Ok(stdout) } else { Err((output.status.code(), stderr)) }
}

/// `config/zenoh-lab-router.json5` is exactly what `subsume lab
/// router-config --lab lab --robot robot1 --robot robot2` prints
/// (`BLESS=1` rewrites it).
#[test]
fn the_shipped_lab_router_config_is_what_the_generator_prints_for_lab_lab_and_two_robots() {
    let made = router_config(&["--lab", "lab", "--robot", "robot1", "--robot", "robot2"]).unwrap();
    let path = support::repo_root().join("config/zenoh-lab-router.json5");
    if std::env::var_os("BLESS").is_some() {
        std::fs::write(&path, &made).unwrap();
    }
    let shipped = std::fs::read_to_string(&path).unwrap();
    assert!(shipped == made, "{} differs from the generator's (BLESS=1 to rewrite):\n{made}", path.display());
}

/// `subsume lab router-config` refuses, exit 1 with the reason naming the
/// thing, a bad lab or robot name, a robot named twice, none, or one with
/// the lab server's user name.
#[test]
fn lab_router_config_refuses_bad_names_duplicates_and_no_robots() {
    let cases: [(&[&str], &str); 5] = [
        (&["--lab", "my lab", "--robot", "r1"], "lab name 'my lab' is not a plain name"),
        (&["--lab", "lab", "--robot", "r1", "--robot", "r/2"], "robot name 'r/2' is not a plain name"),
        (&["--lab", "lab", "--robot", "r1", "--robot", "r1"], "robot 'r1' is named twice"),
        (&["--lab", "lab"], "no robots: name each of the lab's robots with --robot NAME"),
        (
            &["--lab", "lab", "--robot", "boss", "--lab-server-user", "boss"],
            "robot 'boss' has the lab server's user name",
        ),
    ];
    for (args, says) in cases {
        let (code, stderr) = router_config(args).unwrap_err();
        assert_eq!(code, Some(1), "{args:?}: {stderr}");
        assert!(stderr.contains(says), "{args:?}: {stderr}");
    }
}

/// A Zenoh router of the `eclipse-zenoh` package
/// (`tests/python/zenoh_router.py`) on the config `subsume lab
/// router-config` prints for this test's lab and its robots `r1`, `r2`
/// (listening on loopback, with a users file of the lab server's, the
/// robots' and a third user's passwords), run as it is printed.
struct LabRouter {
    child: std::process::Child,
    port: u16,
    dir: PathBuf,
}

/// The password of the router's third user, `mallory`, who is neither the
/// lab server nor a robot.
const MALLORY_PASSWORD: &str = "mallory-router-password";

impl LabRouter {
    fn start(dir: &Path) -> LabRouter {
        let dir = dir.join("router");
        std::fs::create_dir_all(&dir).unwrap();
        let users_file = dir.join("users.txt");
        let users =
            ["lab-server", "r1", "r2"].iter().map(|u| format!("{u}:{}\n", Self::password(u))).collect::<String>();
        std::fs::write(&users_file, format!("{users}mallory:{MALLORY_PASSWORD}\n")).unwrap();
        let port = free_port();
        // Over TLS, as on the internet: the router's certificate from a
        // test authority every client trusts.
        support::make_test_pki(&dir);
        let listen = format!("tls/127.0.0.1:{port}");
        let users_path = users_file.to_str().unwrap();
        let (certificate, key) = (dir.join("chain.pem"), dir.join("server.key"));
        let config = router_config(&[
            "--lab",
            LAB,
            "--robot",
            "r1",
            "--robot",
            "r2",
            "--listen",
            &listen,
            "--users-file",
            users_path,
            "--tls-cert",
            certificate.to_str().unwrap(),
            "--tls-key",
            key.to_str().unwrap(),
        ])
        .unwrap_or_else(|e| panic!("subsume lab router-config: {e:?}"));
        std::fs::write(dir.join("router.json5"), config).unwrap();
        let mut child = std::process::Command::new(support::python())
            .arg(support::repo_root().join("tests/python/zenoh_router.py"))
            .arg(dir.join("router.json5"))
            .stdin(std::process::Stdio::piped())
            .stdout(std::process::Stdio::piped())
            .spawn()
            .unwrap();
        let mut lines = std::io::BufRead::lines(std::io::BufReader::new(child.stdout.take().unwrap()));
        let ready = lines.next().and_then(Result::ok).unwrap_or_default();
        assert!(ready.contains("\"ready\""), "the router did not start: {ready:?}");
        // What it says later (its log) goes to the test's output.
        std::thread::spawn(move || lines.map_while(Result::ok).for_each(|line| eprintln!("router: {line}")));
        LabRouter { child, port, dir }
    }

    fn password(user: &str) -> String {
        format!("{user}-router-password")
    }

    /// The authority that signed the router's certificate (PEM).
    fn authority(&self) -> String {
        self.dir.join("ca.pem").to_str().unwrap().to_string()
    }

    /// Its endpoint (`PORT`: the router's, or a relay's to it).
    fn endpoint(port: u16) -> String {
        format!("tls/127.0.0.1:{port}")
    }

    /// A client config (JSON5) that logs in to this router as `user`.
    fn client_config(&self, user: &str) -> String {
        let path = self.dir.join(format!("{user}.json5"));
        let config = serde_json::json!({
            "mode": "client",
            // A client listens on nothing: every message goes through the router.
            "listen": { "endpoints": [] },
            "scouting": { "multicast": { "enabled": false } },
            "transport": {
                "link": { "tls": { "root_ca_certificate": self.authority() } },
                "auth": { "usrpwd": { "user": user, "password": Self::password(user) } },
            },
        });
        std::fs::write(&path, config.to_string()).unwrap();
        path.to_str().unwrap().to_string()
    }
}

impl Drop for LabRouter {
    fn drop(&mut self) {
        drop(self.child.stdin.take());
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

#[test]
fn through_the_lab_router_over_tls_with_access_control_a_third_users_rogue_queryable_is_never_asked_and_the_robot_works()
 {
    let dir = tempfile::tempdir().unwrap();
    let router = LabRouter::start(dir.path());
    let lab = LabNet::start_on(dir.path(), 1, None, None, &[], Some(&router));
    let secret = std::fs::read_to_string(dir.path().join("lab").join("store").join("lab.secret")).unwrap();
    // Without a user and password the router refuses the session.
    let ca = router.authority();
    let anonymous = Attack::trusting(Some(&ca), &["rogue", &lab.zenoh, LAB, "r1", secret.trim()]);
    let said: Json = serde_json::from_str(&anonymous.line(Duration::from_secs(60))).unwrap();
    assert!(said["refused"].is_string(), "{said}");
    // A third user of the router declares complete queryables on every rpc
    // key of r1, ready to answer first.
    let rogue =
        Attack::trusting(Some(&ca), &["rogue", &lab.zenoh, LAB, "r1", secret.trim(), "mallory", MALLORY_PASSWORD]);
    assert_eq!(rogue.line(Duration::from_secs(60)), "ready");
    // So does robot r2's user (a robot taken over), on r1's keys.
    let r2_password = LabRouter::password("r2");
    let robot_rogue = Attack::trusting(Some(&ca), &["rogue", &lab.zenoh, LAB, "r1", secret.trim(), "r2", &r2_password]);
    assert_eq!(robot_rogue.line(Duration::from_secs(60)), "ready");
    let ana = lab.token("ana");
    // Ana's own component, which r1 does not hold: r1 fetches it from the
    // lab server's blobs through the router.
    let counter = std::fs::read(support::guest("test-counter")).unwrap();
    let (status, json) =
        http(&lab.address, "PUT", "/api/v1/platforms/control/components/counter", Some(&ana), &counter);
    assert_eq!(status, 201, "{json}");
    let set = lab.stage(&ana, "ana.xml", &robot(7.0, r#"<component name="count" source="counter.wasm" rate="10"/>"#));
    // r1 works through the router: its results, whole.
    lab.run_to_done_with_whole_results(&ana, set, "r1");
    // The lab's STOP reaches r1 through the router.
    let long = lab.submit(&ana, set, 110.0, Some("r1"));
    assert_eq!(lab.wait_for(&ana, long, "running", Duration::from_secs(180))["state"], "running");
    // The lab's heartbeats reach r1 (which would abort after `--lab-lost`
    // without them), and its statuses the lab (which would mark it lost).
    std::thread::sleep(Duration::from_secs_f64(LOST_AFTER_S * 3.0));
    assert_eq!(lab.experiment(&ana, long)["state"], "running", "{}", lab.logs());
    let (status, json) = lab.call(&ana, "POST", "/api/v1/robots/r1/stop", "");
    assert_eq!(status, 200, "{json}");
    assert_eq!(json["stopped"], serde_json::json!([{"robot": "r1", "engaged": true, "message": "engaged"}]));
    wait_stopped_by(lab.robot("r1"), &format!("ana@{LAB}"));
    let aborted = lab.wait_for(&ana, long, "aborted", Duration::from_secs(120));
    assert!(aborted.to_string().contains("emergency stop by ana@testlab"), "{aborted:#}");
    // The router never let the rogue's queryables in: not one query of the
    // lab's reached them, and the lab skipped no reply.
    for (who, rogue) in [("mallory", rogue), ("r2", robot_rogue)] {
        let answered = rogue.finish(Duration::from_secs(30));
        for op in ["dispatch", "stop", "estop", "results", "file", "baseline", "live"] {
            assert_eq!(answered["answered"][op], 0, "{who}, {op}: {answered}");
        }
    }
    assert_eq!(lab_metric(&lab, "subsume_lab_skipped_replies_total"), 0.0, "{}", lab.logs());
}

#[test]
fn a_captured_dispatch_replayed_to_its_robot_or_to_another_is_refused_and_counted() {
    let dir = tempfile::tempdir().unwrap();
    let lab = LabNet::start(dir.path(), 2);
    let capture = Attack::start(&["capture", &lab.zenoh, LAB, "r1", "r2"]);
    assert_eq!(capture.line(Duration::from_secs(60)), "ready");
    let ana = lab.token("ana");
    let set = lab.stage(&ana, "ana.xml", &robot(7.0, ""));
    let id = lab.submit(&ana, set, 2.0, Some("r1"));
    let replayed: Json = serde_json::from_str(&capture.line(Duration::from_secs(240))).unwrap();
    assert_eq!(replayed["captured"]["lab_id"], id, "{replayed:#}");
    assert_eq!(replayed["captured"]["to"]["robot"], "r1", "{replayed:#}");
    // (to, what the unsigned refusal says): each replay once, nothing signed.
    let expected = [("r1", "refused (replayed)"), ("r1", "refused (replayed)"), ("r2", "names robot 'r1'")];
    let replays = replayed["replays"].as_array().unwrap();
    assert_eq!(replays.len(), expected.len(), "{replayed:#}");
    for ((to, words), replay) in expected.iter().zip(replays) {
        assert_eq!(replay["to"], *to, "{replay:#}");
        let answers = replay["answers"].as_array().unwrap();
        assert_eq!(answers.len(), 1, "{replay:#}");
        assert!(answers[0]["refused"].as_str().is_some_and(|t| t.contains(words)), "{words}: {replay:#}");
    }
    // The experiment ran once, on r1, to its end; r2 ran nothing.
    assert_eq!(lab.wait_for(&ana, id, "done", Duration::from_secs(180))["state"], "done", "{}", lab.logs());
    let experiments = |robot: &Robot| {
        let owner = support::login(&robot.address, "owner", PASSWORD);
        let (_, json) = http(&robot.address, "GET", "/api/v1/experiments", Some(&owner), b"");
        json["experiments"].as_array().unwrap().len()
    };
    assert_eq!((experiments(lab.robot("r1")), experiments(lab.robot("r2"))), (1, 0));
    // Counted: in each robot's audit (bounded lines) and the lab's metrics.
    let deadline = Instant::now() + Duration::from_secs(60);
    loop {
        let lines = |robot: &Robot| -> String {
            robot_audit(robot)
                .iter()
                .filter(|e| e["action"] == "lab-refusals")
                .map(|e| e["detail"].to_string())
                .collect()
        };
        let (r1, r2) = (lines(lab.robot("r1")), lines(lab.robot("r2")));
        if r1.contains("replayed")
            && r2.contains("other-robot 1")
            && lab_metric(&lab, "subsume_lab_refused_requests_total{by=\"robots\"}") >= 3.0
        {
            break;
        }
        assert!(Instant::now() < deadline, "the replays were never counted: r1 {r1}, r2 {r2}\n{}", lab.logs());
        std::thread::sleep(Duration::from_millis(500));
    }
}

#[test]
fn a_junk_query_flood_during_a_stop_leaves_it_engaging_at_once_and_the_robots_audit_bounded() {
    let dir = tempfile::tempdir().unwrap();
    let lab = LabNet::start(dir.path(), 1);
    let ana = lab.token("ana");
    let set = lab.stage(&ana, "ana.xml", &robot(7.0, ""));
    let id = lab.submit(&ana, set, 110.0, Some("r1"));
    assert_eq!(lab.wait_for(&ana, id, "running", Duration::from_secs(180))["state"], "running");
    let r1 = lab.robot("r1");
    let before = robot_audit(r1).len();
    let flood = Attack::start(&["flood", &lab.zenoh, LAB, "r1", "8", "1000"]);
    assert_eq!(flood.line(Duration::from_secs(60)), "ready");
    std::thread::sleep(Duration::from_secs(2));
    let pressed = Instant::now();
    let (status, json) = lab.call(&ana, "POST", "/api/v1/robots/r1/stop", "");
    let took = pressed.elapsed();
    assert_eq!(status, 200, "{json}");
    assert_eq!(json["stopped"], serde_json::json!([{"robot": "r1", "engaged": true, "message": "engaged"}]));
    assert!(took < Duration::from_secs(2), "{took:?}");
    // Pressed 19 times more during the flood: every press reaches r1.
    let mut times = vec![took];
    for _ in 0..19 {
        let pressed = Instant::now();
        let (status, json) = lab.call(&ana, "POST", "/api/v1/robots/r1/stop", "");
        times.push(pressed.elapsed());
        assert_eq!(status, 200, "{json}");
        assert_eq!(json["stopped"][0]["engaged"], true, "{json}");
    }
    times.sort();
    eprintln!("the lab's STOP during a junk flood, 20 presses: median {:?}, slowest {:?}", times[10], times[19]);
    assert!(times[19] < Duration::from_secs(2), "{times:?}");
    let sent = flood.finish(Duration::from_secs(60));
    let sent = sent["sent"].as_u64().unwrap();
    assert!(sent >= 4000, "the flood sent {sent}");
    wait_stopped_by(r1, &format!("ana@{LAB}"));
    assert_eq!(lab.wait_for(&ana, id, "aborted", Duration::from_secs(120))["state"], "aborted");
    // Every junk query was counted, none answered, and the audit log got a
    // summary line at most every 10 s, not a line each.
    let deadline = Instant::now() + Duration::from_secs(30);
    while lab_metric(&lab, "subsume_lab_refused_requests_total{by=\"robots\"}") < sent as f64 * 0.9 {
        assert!(Instant::now() < deadline, "the junk was not counted\n{}", lab.logs());
        std::thread::sleep(Duration::from_millis(500));
    }
    let audit = robot_audit(r1);
    let added: Vec<&Json> = audit.iter().skip(before).collect();
    let summaries = added.iter().filter(|e| e["action"] == "lab-refusals").count();
    assert!((1..=3).contains(&summaries), "{added:#?}");
    assert!(added.len() <= 12, "the flood's audit is not bounded: {added:#?}");
}

/// A process's resident and peak resident memory (KiB), from the kernel.
fn memory_kib(pid: u32) -> (u64, u64) {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap();
    let field = |name: &str| {
        let line = status.lines().find(|l| l.starts_with(name)).unwrap_or_else(|| panic!("no {name} for {pid}"));
        line.split_whitespace().nth(1).and_then(|n| n.parse::<u64>().ok()).unwrap()
    };
    (field("VmRSS:"), field("VmHWM:"))
}

/// A peer without the secret sends messages of 32 MiB, far over the lab's
/// bound (`wire::MAX_ZENOH_MESSAGE_BYTES`, which the lab's Zenoh sessions
/// apply to what they reassemble), to a running robot's keys. Zenoh drops
/// them before the lab's code holds them: neither the lab server's nor the
/// robot's peak memory grows by one such message, the experiment runs on,
/// and the lab's STOP engages at once afterwards (issue 37, "bounded
/// messages at the Zenoh layer too").
#[test]
fn oversized_messages_from_a_peer_are_dropped_by_zenoh_and_the_lab_runs_on_and_stops() {
    const MESSAGE_BYTES: u64 = 32 << 20;
    assert!(MESSAGE_BYTES > 8 * subsume::lab::wire::MAX_ZENOH_MESSAGE_BYTES as u64);
    let dir = tempfile::tempdir().unwrap();
    let lab = LabNet::start(dir.path(), 1);
    let ana = lab.token("ana");
    let set = lab.stage(&ana, "ana.xml", &robot(7.0, ""));
    let id = lab.submit(&ana, set, 110.0, Some("r1"));
    assert_eq!(lab.wait_for(&ana, id, "running", Duration::from_secs(180))["state"], "running");
    let r1 = lab.robot("r1");
    let (server_pid, robot_pid) = (lab.server.child.id(), r1.host.child.id());
    let (server_before, robot_before) = (memory_kib(server_pid), memory_kib(robot_pid));
    let attack = Attack::start(&["oversized", &lab.zenoh, LAB, "r1", "6", &MESSAGE_BYTES.to_string()]);
    assert_eq!(attack.line(Duration::from_secs(60)), "ready");
    let said: Json = serde_json::from_str(&attack.line(Duration::from_secs(120))).unwrap();
    assert_eq!(said["bytes"].as_u64().unwrap(), MESSAGE_BYTES + 41, "{said}");
    assert!(said["sent"].as_u64().unwrap() + said["failed"].as_u64().unwrap() == 6, "{said}");
    // Neither process ever held one of them: its peak stayed where it was,
    // or under half a message above what it held before (RSS moves by a
    // few MiB on its own).
    let margin_kib = MESSAGE_BYTES / 1024 / 2;
    for (name, pid, (rss, peak_before)) in
        [("the lab server", server_pid, server_before), ("robot r1", robot_pid, robot_before)]
    {
        let (now, peak) = memory_kib(pid);
        assert!(
            peak <= peak_before.max(rss + margin_kib),
            "{name} held an oversized message: {rss} KiB before (peak {peak_before} KiB), peak {peak} KiB since, \
             now {now} KiB ({said})"
        );
    }
    let experiment = lab.experiment(&ana, id);
    assert_eq!(experiment["state"], "running", "{experiment:#}\n{}", lab.logs());
    let pressed = Instant::now();
    let (status, json) = lab.call(&ana, "POST", "/api/v1/robots/r1/stop", "");
    assert_eq!(status, 200, "{json}");
    assert_eq!(json["stopped"][0]["engaged"], true, "{json}");
    assert!(pressed.elapsed() < Duration::from_secs(2), "{:?}", pressed.elapsed());
    wait_stopped_by(r1, &format!("ana@{LAB}"));
    assert_eq!(lab.wait_for(&ana, id, "aborted", Duration::from_secs(120))["state"], "aborted");
}

#[test]
fn a_robots_token_declared_again_keeps_it_neither_listed_nor_its_experiment_alive() {
    let dir = tempfile::tempdir().unwrap();
    let lab = LabNet::start(dir.path(), 1);
    let ana = lab.token("ana");
    let set = lab.stage(&ana, "ana.xml", &robot(7.0, ""));
    let id = lab.submit(&ana, set, 60.0, Some("r1"));
    assert_eq!(lab.wait_for(&ana, id, "running", Duration::from_secs(180))["state"], "running");
    let boss = lab.token("boss");
    lab.wait_robots(&boss, Duration::from_secs(30), |robots| {
        robots.iter().any(|r| r["name"] == "r1" && r["state"] == "running")
    });
    // A peer declares r1's running token again, then r1's link is cut.
    let holder = Attack::start(&["token", &lab.zenoh, LAB, "r1"]);
    let keys: Json = serde_json::from_str(&holder.line(Duration::from_secs(60))).unwrap();
    let keys = keys["ready"].as_array().unwrap().clone();
    assert!(keys.iter().any(|k| k.as_str().unwrap().contains(&format!("/running-{id}/"))), "{keys:?}");
    lab.robot("r1").link.cut();
    std::thread::sleep(Duration::from_secs(1));
    // At the Zenoh layer r1's token is still there: any client sees it.
    let output = std::process::Command::new(support::python())
        .arg(support::repo_root().join("tests/python/lab_tokens.py"))
        .args([&lab.zenoh, LAB])
        .output()
        .unwrap();
    assert!(String::from_utf8_lossy(&output.stdout).contains("\"r1\""), "{output:?}");
    // The lab goes by r1's signed statuses: lost, its experiment aborted.
    let lost = lab.wait_for(&ana, id, "aborted", Duration::from_secs(30));
    assert!(lost.to_string().contains("robot lost"), "{lost:#}\n{}", lab.logs());
    lab.wait_robots(&boss, Duration::from_secs(30), |robots| {
        robots.iter().any(|r| r["name"] == "r1" && r["state"] == "lost" && r["online"] == false)
    });
    assert_eq!(holder.finish(Duration::from_secs(30))["released"], keys.len());
}

#[test]
fn a_lab_link_off_loopback_without_tls_and_authentication_is_refused_unless_allowed_and_then_logged() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    let port = free_port();
    let serve = |extra: &[&str]| {
        let mut command = support::subsume();
        command
            .arg("--store")
            .arg(&store)
            .args(["lab", "serve", "--http", "127.0.0.1:0", "--lab", LAB])
            .args(["--listen", &format!("tcp/0.0.0.0:{port}")])
            .args(extra)
            .env_remove("SUBSUME_HTTP");
        HostProcess::spawn(command)
    };
    // A lab server listening on every address in plain text.
    let mut refused = serve(&[]);
    let status = support::wait_for_exit(&mut refused.child, Duration::from_secs(60));
    assert!(!status.success());
    let said = refused.lines_until(0, "on a closed network", Duration::from_secs(10)).join("\n");
    assert!(said.contains(&format!("is plain text off loopback (tcp/0.0.0.0:{port})")), "{said}");
    assert!(said.contains("--allow-plain-zenoh on a closed network"), "{said}");
    // A robot connecting over TLS that authenticates nobody.
    let home = dir.path().join("r1");
    std::fs::create_dir_all(&home).unwrap();
    std::fs::write(home.join("robot.xml"), robot(8.0, "")).unwrap();
    std::fs::write(home.join("lab.world"), WORLD).unwrap();
    std::fs::write(home.join("lab.secret"), "0123456789abcdef0123456789abcdef\n").unwrap();
    let mut command = support::subsume();
    command
        .arg("--store")
        .arg(home.join("store"))
        .arg("run")
        .arg(home.join("robot.xml"))
        .args(["--http", "127.0.0.1:0", "--lab", LAB, "--lab-robot", "r1"])
        .arg("--lab-secret")
        .arg(home.join("lab.secret"))
        .args(["--lab-connect", "tls/192.0.2.1:7447"])
        .env_remove("SUBSUME_HTTP");
    let mut robot_host = HostProcess::spawn(command);
    let status = support::wait_for_exit(&mut robot_host.child, Duration::from_secs(60));
    assert!(!status.success());
    let said = robot_host.lines_until(0, "on a closed network", Duration::from_secs(10)).join("\n");
    assert!(said.contains("is TLS without mutual TLS or user/password (tls/192.0.2.1:7447)"), "{said}");
    assert!(said.contains("--lab-allow-plain on a closed network"), "{said}");
    // Allowed on a closed network: it starts, and says so in its log.
    let allowed = serve(&["--allow-plain-zenoh"]);
    allowed.lines_until(0, "allowed by --allow-plain-zenoh (a closed network only)", Duration::from_secs(60));
    allowed.address_after(&format!("lab server '{LAB}' on http://"), Duration::from_secs(120));
}

/// Every file under `dir`, recursively.
fn walk(dir: &Path) -> Vec<PathBuf> {
    let mut files = Vec::new();
    for entry in std::fs::read_dir(dir).unwrap() {
        let path = entry.unwrap().path();
        if path.is_dir() {
            files.extend(walk(&path));
        } else {
            files.push(path);
        }
    }
    files
}

/// Every `subsume lab` command docs/lab.md shows, as written there, run
/// against a lab server whose portal is on https only (a certificate of
/// the test's authority, trusted by `SUBSUME_CA`, as the document tells a
/// researcher), with one robot joined over Zenoh on loopback, in the
/// document's order (placeholders filled as against a robot:
/// `lab_docs::fill`; `lab serve` itself is how this lab server started,
/// by [`LabNet`]). `lab submit` follows its experiment to `done` and
/// unpacks its results with the run's recording; the kit's robot file
/// submits as it is. Each command succeeds or is refused by the portal
/// for the reason the document gives (`cancel` of an ended experiment, a
/// reservation on a lab server); none fails on its arguments or on a
/// route the lab server lacks. Between `maintenance --reason` and
/// `--end`, the lab server holds its queue: an experiment that passed
/// its preflight is dispatched to no robot until the maintenance ends.
#[test]
fn every_lab_command_docs_lab_md_shows_runs_as_written_against_a_lab_server_over_https() {
    let dir = tempfile::tempdir().unwrap();
    let lab = LabNet::start_over_https(dir.path(), 1);
    assert!(lab.address.starts_with("https://"), "{}", lab.address);
    let ca = lab.ca.clone().unwrap();
    let all = crate::lab_docs::lab_commands();
    let several: Vec<&str> = all.iter().filter(|c| c.section == "Several robots").map(|c| c.text.as_str()).collect();
    assert!(
        several.iter().any(|c| c.starts_with("subsume lab serve"))
            && several.iter().any(|c| c.starts_with("subsume lab router-config")),
        "the lab commands of \"Several robots\": {several:#?}"
    );
    let commands: Vec<_> = all.iter().filter(|c| !c.serves()).collect();
    let planner = format!("planner={}", support::guest("planner").display());
    let work = dir.path().join("work");
    std::fs::create_dir_all(&work).unwrap();
    // Experiment 1 is the one held by the maintenance; the document's
    // `submit` is experiment 2, its `ID`.
    let (held, submitted) = (1, 2);
    let filling = crate::lab_docs::Filling {
        host: &lab.address,
        work: &work,
        component: &planner,
        duration_s: "2",
        id: submitted,
    };
    let mut ran = Vec::new();
    for (n, command) in commands.iter().enumerate() {
        let filled = crate::lab_docs::fill(command, n, &filling);
        let admin = ["maintenance", "settings"].contains(&filled.subcommand());
        let output = support::subsume()
            .args(&filled.words[1..])
            .current_dir(&work)
            .env("SUBSUME_USER", if admin { "boss" } else { "ana" })
            .env("SUBSUME_PASSWORD", PASSWORD)
            .env("SUBSUME_CA", &ca)
            .output()
            .unwrap();
        let (stdout, stderr) = (support::text(&output.stdout), support::text(&output.stderr));
        if let Some(file) = &filled.into {
            std::fs::write(file, &output.stdout).unwrap();
        }
        let said = format!(
            "docs/lab.md's `{}` (as `{}`): exit {:?}\n{stdout}\n{stderr}\n{}",
            command.text,
            filled.line,
            output.status.code(),
            lab.logs()
        );
        assert!(!stderr.contains("no such API route"), "{said}");
        match filled.subcommand() {
            // docs/lab.md, "Several robots": a lab server takes none.
            "reserve" | "unreserve" => {
                assert!(!output.status.success() && stderr.contains("a lab server takes no reservations"), "{said}")
            }
            // It ended before: the portal's 409.
            "cancel" => assert!(
                !output.status.success() && stderr.contains(&format!("experiment {submitted} has ended already")),
                "{said}"
            ),
            _ => assert!(output.status.success(), "{said}"),
        }
        match (filled.subcommand(), filled.words.iter().any(|w| w == "--reason")) {
            ("maintenance", true) => {
                assert!(stdout.starts_with("the lab is in maintenance: "), "{said}");
                let ana = lab.token("ana");
                let set = lab.stage(&ana, "held.xml", &robot(8.0, ""));
                assert_eq!(lab.submit(&ana, set, 1.0, None), held);
                let queued = lab.wait_for(&ana, held, "queued", Duration::from_secs(180));
                assert_eq!(queued["state"], "queued", "{queued:#}\n{}", lab.logs());
                // Every queued submitter sees why the queue waits.
                let why = lab.wait_overview(&ana, Duration::from_secs(30), |view| view["held"].is_string());
                let why = why["held"].as_str().unwrap_or_default();
                assert!(
                    why.starts_with("the lab is in maintenance since ")
                        && why.ends_with("no experiment goes to a robot until an admin ends it"),
                    "{why}"
                );
                // A free robot, and an experiment for it: without the
                // maintenance it is dispatched within a heartbeat.
                let until = Instant::now() + Duration::from_secs(3);
                while Instant::now() < until {
                    let record = lab.experiment(&ana, held);
                    assert!(
                        record["state"] == "queued" && record["placement"]["robot"].is_null(),
                        "dispatched while the lab server is in maintenance: {record:#}\n{}",
                        lab.logs()
                    );
                    std::thread::sleep(Duration::from_millis(100));
                }
            }
            ("maintenance", false) => assert!(stdout.starts_with("the lab is back in service"), "{said}"),
            ("submit", _) if filled.words.iter().any(|w| w == "--target") => {
                // docs/lab.md, "Several robots": built on r1's baseline,
                // sent to r1, and run there.
                let set = lab.robots(&lab.token("boss"))[0]["baseline_set"].as_u64().unwrap();
                assert!(
                    stderr.contains(&format!("building on robot r1's baseline robot.xml (set {set}, sha256 ")),
                    "{said}"
                );
                let id: u64 = stdout
                    .split("experiment ")
                    .nth(1)
                    .and_then(|rest| rest.split(' ').next())
                    .and_then(|id| id.parse().ok())
                    .unwrap_or_else(|| panic!("no experiment id: {said}"));
                let record = lab.experiment(&lab.token("ana"), id);
                assert_eq!(record["placement"]["target"], serde_json::json!({ "robot": "r1" }), "{said}\n{record:#}");
                assert_eq!(record["placement"]["robot"], "r1", "{said}\n{record:#}");
                assert!(stdout.contains(&format!("experiment {id}: done")), "{said}");
            }
            ("submit", _) if filled.words.iter().any(|w| w == "--component") => {
                assert!(stdout.contains(&format!("experiment {submitted} submitted")), "{said}");
                assert!(stdout.contains(&format!("experiment {submitted}: done")), "{said}");
                assert!(stdout.contains(&format!("results of experiment {submitted}: ")), "{said}");
                let recording = work.join("turns").join("run.mcap");
                assert!(read_mcap(&recording, false)["complete"].as_bool().unwrap(), "{said}");
            }
            ("submit", _) => assert!(stdout.contains(": done"), "{said}"),
            ("results", _) => {
                let unpacked = filled.words.iter().skip_while(|w| *w != "-o").nth(1).unwrap();
                assert!(Path::new(unpacked).join("run.mcap").is_file(), "{said}");
            }
            _ => {}
        }
        ran.push(filled.subcommand().to_string());
    }
    let ana = lab.token("ana");
    assert_eq!(lab.experiment(&ana, held)["state"], "done", "{}", lab.logs());
    for needed in [
        "submit",
        "list",
        "show",
        "cancel",
        "results",
        "reserve",
        "reservations",
        "unreserve",
        "settings",
        "kit",
        "maintenance",
        "router-config",
    ] {
        assert!(ran.iter().any(|c| c == needed), "docs/lab.md shows no `lab {needed}`: {ran:?}");
    }
}
