//! The Zenoh sessions of this host: one per distinct set of settings
//! (`connect`, `listen`, `zenoh-config`), opened by the first built-in that
//! needs it and closed when the last one using it is dropped, so a robot
//! file with nothing Zenoh starts nothing Zenoh.
//!
//! Defaults follow rmw_zenoh's session: peer mode, multicast scouting off
//! (robots on one network do not find each other by accident), endpoints
//! given explicitly. A JSON5 config file (Zenoh's own format) is the base
//! when given, for TLS and user/password authentication; `connect` and
//! `listen`, when given, replace its endpoints.
//!
//! Zenoh runs its own tokio runtime; nothing here runs on the control loop
//! but the open at build time (and small puts, when a congested put gives
//! up at once: `link::Outlet`). A watcher thread per session counts its
//! peers for the status.

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::str::FromStr;
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, Weak};
use std::time::Duration;

use thiserror::Error;
use zenoh::Wait;

use crate::builtin::{BuiltinError, ParamDecl, ParamType, Params};
use crate::config::ParamProblem;
use crate::contract::clip;
use crate::runtime::status::json_of;
use crate::runtime::{NamedSection, StatusSection};

/// Most endpoints one setting may list: each is a connection attempt.
pub const MAX_ENDPOINTS: usize = 16;

/// How often a session's peers are counted for the status.
const PEER_POLL: Duration = Duration::from_millis(500);

/// Zenoh's setting for how long a droppable put waits for a free batch
/// before it drops the message (microseconds; Zenoh's default is 1000).
pub const WAIT_BEFORE_DROP_KEY: &str = "transport/link/tx/queue/congestion_control/drop/wait_before_drop";

/// What this host sets [`WAIT_BEFORE_DROP_KEY`] to when no `zenoh-config`
/// file is given: a put that finds the network congested gives up within a
/// microsecond (the message is dropped and counted, as it would be 1 ms
/// later), so the control loop can put small messages itself
/// (`link::Outlet`) without ever waiting on the network. Multi-batch
/// (fragmented) messages still wait up to Zenoh's own fragment limit, on
/// the sender thread.
pub const LOOP_WAIT_BEFORE_DROP_US: i64 = 1;

/// Most a session's [`WAIT_BEFORE_DROP_KEY`] may be for the control loop to
/// put on it directly. The threat: a loop that waits up to Zenoh's default
/// millisecond for a congested network misses a 1 kHz cycle; a config file
/// with a larger value keeps every put on the sender thread.
pub const MAX_LOOP_WAIT_BEFORE_DROP_US: i64 = 10;

/// Zenoh's setting for the largest message a link reassembles (bytes;
/// Zenoh's default is 1 GiB): a peer sending more is dropped by Zenoh
/// itself, before anything here holds it.
pub const MAX_MESSAGE_SIZE_KEY: &str = "transport/link/rx/max_message_size";

/// Why a session did not open.
#[derive(Debug, Error)]
pub enum SessionError {
    #[error("zenoh config {path}: {why}")]
    ConfigFile { path: PathBuf, why: String },
    #[error("zenoh setting {key}: {why}")]
    Setting { key: &'static str, why: String },
    #[error("zenoh session did not open: {0}")]
    Open(String),
}

impl From<SessionError> for BuiltinError {
    fn from(e: SessionError) -> BuiltinError {
        BuiltinError::Refused(e.to_string())
    }
}

/// The session parameters every Zenoh built-in declares.
pub const SESSION_PARAMS: [ParamDecl; 3] = [
    ParamDecl {
        name: "connect",
        ty: ParamType::Text,
        default: "",
        unit: "",
        doc: "zenoh endpoints to connect to, comma-separated (tcp/192.168.1.7:7447, tls/robot-a.local:7447); empty: none",
    },
    ParamDecl {
        name: "listen",
        ty: ParamType::Text,
        default: "",
        unit: "",
        doc: "zenoh endpoints to listen on, comma-separated (tcp/0.0.0.0:7447); empty: none",
    },
    ParamDecl {
        name: "zenoh-config",
        ty: ParamType::SecretFile {
            optional: true,
            stand_in: "// stands in for the robot's Zenoh config: the lab server never opens it\n{}\n",
        },
        default: "",
        unit: "",
        doc: "a Zenoh JSON5 config file (TLS, user/password); connect and listen replace its endpoints",
    },
];

/// What identifies a session: equal settings share one.
#[derive(Clone, Debug, PartialEq, Eq, Hash)]
pub struct SessionSettings {
    pub connect: Vec<String>,
    pub listen: Vec<String>,
    pub config: Option<PathBuf>,
    /// The largest message Zenoh reassembles on this session
    /// ([`MAX_MESSAGE_SIZE_KEY`]); `None`: the config's, else Zenoh's.
    pub max_message_bytes: Option<usize>,
}

fn endpoints(text: &str, key: &'static str) -> Result<Vec<String>, SessionError> {
    let list: Vec<String> = text.split(',').map(str::trim).filter(|s| !s.is_empty()).map(str::to_string).collect();
    if list.len() > MAX_ENDPOINTS {
        return Err(SessionError::Setting { key, why: format!("lists more than {MAX_ENDPOINTS} endpoints") });
    }
    for e in &list {
        zenoh::config::EndPoint::from_str(e).map_err(|_| SessionError::Setting {
            key,
            why: format!("lists '{}', which is not an endpoint (PROTOCOL/ADDRESS: tcp/127.0.0.1:7447)", clip(e)),
        })?;
        if !(e.starts_with("tcp/") || e.starts_with("tls/")) {
            return Err(SessionError::Setting {
                key,
                why: format!(
                    "lists '{}', but this host speaks zenoh over tcp and tls only (tcp/HOST:PORT, tls/HOST:PORT)",
                    clip(e)
                ),
            });
        }
    }
    Ok(list)
}

impl SessionSettings {
    /// The settings in `params`, files relative to `base_dir`.
    pub fn from_params(params: &Params, base_dir: &Path) -> Result<SessionSettings, SessionError> {
        let text = |name| params.text(name).unwrap_or_default();
        let config = Some(text("zenoh-config").trim()).filter(|s| !s.is_empty()).map(|f| base_dir.join(f));
        Ok(SessionSettings {
            connect: endpoints(text("connect"), "connect")?,
            listen: endpoints(text("listen"), "listen")?,
            config,
            max_message_bytes: None,
        })
    }

    /// Every problem of the session parameters, for a built-in's check.
    pub fn check(params: &Params, base_dir: &Path) -> Vec<ParamProblem> {
        let mut problems = Vec::new();
        for key in ["connect", "listen"] {
            if let Err(SessionError::Setting { why, .. }) = endpoints(params.text(key).unwrap_or_default(), "connect") {
                problems.push(ParamProblem::new(key, why));
            }
        }
        if let Ok(settings) = SessionSettings::from_params(params, base_dir)
            && let Err(e) = settings.zenoh_config()
        {
            problems.push(ParamProblem::new("zenoh-config", e.to_string()));
        }
        problems
    }

    /// The Zenoh configuration these settings stand for.
    pub fn zenoh_config(&self) -> Result<zenoh::Config, SessionError> {
        let set = |config: &mut zenoh::Config, key: &'static str, value: String| {
            config.insert_json5(key, &value).map_err(|why| SessionError::Setting { key, why: why.to_string() })
        };
        let mut config = match &self.config {
            Some(path) => zenoh::Config::from_file(path)
                .map_err(|why| SessionError::ConfigFile { path: path.clone(), why: why.to_string() })?,
            None => {
                let mut config = zenoh::Config::default();
                set(&mut config, "mode", "\"peer\"".into())?;
                set(&mut config, "scouting/multicast/enabled", "false".into())?;
                set(&mut config, WAIT_BEFORE_DROP_KEY, LOOP_WAIT_BEFORE_DROP_US.to_string())?;
                config
            }
        };
        let json = |list: &[String]| serde_json::to_string(list).unwrap_or_else(|_| "[]".into());
        if !self.connect.is_empty() || self.config.is_none() {
            set(&mut config, "connect/endpoints", json(&self.connect))?;
        }
        if !self.listen.is_empty() || self.config.is_none() {
            set(&mut config, "listen/endpoints", json(&self.listen))?;
        }
        if let Some(bytes) = self.max_message_bytes {
            set(&mut config, MAX_MESSAGE_SIZE_KEY, bytes.to_string())?;
        }
        Ok(config)
    }
}

/// One open session, shared by the built-ins with its settings.
pub struct Shared {
    pub session: zenoh::Session,
    /// This session's id, as tokens and GIDs spell it.
    pub id: String,
    peers: AtomicUsize,
    next_entity: AtomicU64,
    /// Whether a droppable put on this session gives up at once on a
    /// congested network ([`MAX_LOOP_WAIT_BEFORE_DROP_US`]), so the control
    /// loop may put small messages itself.
    pub loop_puts: bool,
}

impl Shared {
    /// How many peers the session is connected to (counted every 500 ms).
    pub fn peers(&self) -> usize {
        self.peers.load(Ordering::Relaxed)
    }

    /// A fresh entity id within this session (ROS 2 tokens and GIDs).
    pub fn next_entity(&self) -> u32 {
        self.next_entity.fetch_add(1, Ordering::Relaxed) as u32 + 1
    }
}

type Registry = Mutex<HashMap<SessionSettings, Weak<Shared>>>;

fn registry() -> &'static Registry {
    static SESSIONS: std::sync::OnceLock<Registry> = std::sync::OnceLock::new();
    SESSIONS.get_or_init(Default::default)
}

/// The session for `settings`: the running one, or a new one.
pub fn session(settings: &SessionSettings) -> Result<Arc<Shared>, SessionError> {
    let mut sessions = registry().lock().map_err(|_| SessionError::Open("session registry poisoned".into()))?;
    if let Some(shared) = sessions.get(settings).and_then(Weak::upgrade) {
        return Ok(shared);
    }
    let config = settings.zenoh_config()?;
    let session = zenoh::open(config.clone()).wait().map_err(|why| open_error(settings, &config, &why.to_string()))?;
    let id = session.zid().to_string();
    let loop_puts = loop_puts(&config);
    let shared =
        Arc::new(Shared { session, id, peers: AtomicUsize::new(0), next_entity: AtomicU64::new(0), loop_puts });
    sessions.retain(|_, weak| weak.strong_count() > 0);
    sessions.insert(settings.clone(), Arc::downgrade(&shared));
    let watched = Arc::downgrade(&shared);
    let _ = std::thread::Builder::new().name("zenoh-peers".into()).spawn(move || {
        while let Some(shared) = watched.upgrade() {
            let peers = shared.session.info().peers_zid().wait().count();
            shared.peers.store(peers, Ordering::Relaxed);
            drop(shared);
            std::thread::sleep(PEER_POLL);
        }
    });
    tracing::info!(session = %shared.id, connect = ?settings.connect, listen = ?settings.listen, "zenoh session open");
    Ok(shared)
}

/// The links of a Zenoh config that cross a network unprotected: what a
/// lab refuses unless its owner allows it (a closed network).
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct LinkExposure {
    /// Endpoints off loopback without TLS (anyone on the path reads them).
    pub plain: Vec<String>,
    /// Endpoints off loopback over TLS with neither mutual TLS nor
    /// user/password (anyone who reaches them joins).
    pub unauthenticated: Vec<String>,
}

impl LinkExposure {
    pub fn is_empty(&self) -> bool {
        self.plain.is_empty() && self.unauthenticated.is_empty()
    }
}

impl std::fmt::Display for LinkExposure {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let mut parts = Vec::new();
        if !self.plain.is_empty() {
            parts.push(format!("is plain text off loopback ({})", self.plain.join(", ")));
        }
        if !self.unauthenticated.is_empty() {
            parts.push(format!("is TLS without mutual TLS or user/password ({})", self.unauthenticated.join(", ")));
        }
        f.write_str(&parts.join(" and "))
    }
}

/// Whether `endpoint` (`PROTO/HOST:PORT`, maybe with `?config` or
/// `#metadata`) stays on this machine.
pub fn is_loopback_endpoint(endpoint: &str) -> bool {
    let address = endpoint.split(['?', '#']).next().unwrap_or_default();
    let address = address.split_once('/').map_or(address, |(_, rest)| rest);
    let host = address.rsplit_once(':').map_or(address, |(host, _)| host);
    let host = host.trim_start_matches('[').trim_end_matches(']');
    host == "localhost" || host.parse::<std::net::IpAddr>().is_ok_and(|ip| ip.is_loopback())
}

/// The endpoints of `config` (connect and listen) off loopback that are
/// plain text, or TLS that authenticates nobody.
pub fn link_exposure(config: &zenoh::Config) -> LinkExposure {
    fn strings(value: &serde_json::Value, out: &mut Vec<String>) {
        match value {
            serde_json::Value::String(text) => out.push(text.clone()),
            serde_json::Value::Array(items) => items.iter().for_each(|v| strings(v, out)),
            serde_json::Value::Object(map) => map.values().for_each(|v| strings(v, out)),
            _ => {}
        }
    }
    let json =
        |key: &str| config.get_json(key).ok().and_then(|text| serde_json::from_str::<serde_json::Value>(&text).ok());
    let mut endpoints = Vec::new();
    for key in ["connect/endpoints", "listen/endpoints"] {
        if let Some(value) = json(key) {
            strings(&value, &mut endpoints);
        }
    }
    let set = |key: &str| json(key).is_some_and(|v| !v.is_null() && v != serde_json::Value::Bool(false));
    let authenticated = set("transport/link/tls/enable_mtls")
        || set("transport/auth/usrpwd/user")
        || set("transport/auth/usrpwd/dictionary_file");
    let mut exposure = LinkExposure::default();
    for endpoint in endpoints.into_iter().filter(|e| !is_loopback_endpoint(e)) {
        if !endpoint.starts_with("tls/") {
            exposure.plain.push(endpoint);
        } else if !authenticated {
            exposure.unauthenticated.push(endpoint);
        }
    }
    exposure
}

/// Whether `config` lets a droppable put wait at most
/// [`MAX_LOOP_WAIT_BEFORE_DROP_US`] for a free batch.
pub fn loop_puts(config: &zenoh::Config) -> bool {
    config
        .get_json(WAIT_BEFORE_DROP_KEY)
        .ok()
        .and_then(|text| text.trim().parse::<i64>().ok())
        .is_some_and(|us| us <= MAX_LOOP_WAIT_BEFORE_DROP_US)
}

/// Why a session did not open, in words an operator can act on. Zenoh's
/// handshake does not tell the connecting side why a peer closed it (a
/// wrong user/password and an untrusted certificate look the same there),
/// so the likely causes are named.
fn open_error(settings: &SessionSettings, config: &zenoh::Config, why: &str) -> SessionError {
    if why.starts_with("Unable to connect") {
        let endpoints: Vec<String> = config
            .get_json("connect/endpoints")
            .ok()
            .and_then(|json| serde_json::from_str(&json).ok())
            .unwrap_or_default();
        let file = settings.config.as_ref().map(|p| format!(" in {}", p.display())).unwrap_or_default();
        return SessionError::Open(format!(
            "no peer accepted the connection to {} within the connect timeout; a peer closes the handshake \
             without saying why when the user/password or the TLS certificate{file} is refused, or it is not there",
            clip(&endpoints.join(", "))
        ));
    }
    SessionError::Open(clip(why.split(" at /").next().unwrap_or(why)))
}

/// Nanoseconds since the UNIX epoch (timestamps on the wire).
pub use crate::walltime::unix_now_ns as unix_ns;

/// Counters of one bridge (a Zenoh or ROS 2 built-in), for the report and
/// the live status. Written by the control loop (out) and Zenoh's threads
/// (in, malformed, dropped).
#[derive(Debug, Default)]
pub struct BridgeStats {
    pub messages_in: AtomicU64,
    pub messages_out: AtomicU64,
    /// Payloads that did not decode (counted and dropped).
    pub malformed: AtomicU64,
    /// Messages dropped because a queue was full.
    pub dropped: AtomicU64,
    /// When the last message arrived, ns since the UNIX epoch (0: never).
    pub last_seen_ns: AtomicU64,
    /// The last decode error, for the status.
    pub last_error: Mutex<Option<String>>,
}

impl BridgeStats {
    pub fn malformed(&self, why: String) {
        self.malformed.fetch_add(1, Ordering::Relaxed);
        if let Ok(mut last) = self.last_error.lock() {
            *last = Some(clip(&why));
        }
    }

    /// The status section of a bridge on `key`: `section` is `zenoh` or
    /// `ros2`.
    pub fn status(&self, section: &'static str, key: &str, shared: &Shared) -> BridgeStatus {
        let last = self.last_seen_ns.load(Ordering::Relaxed);
        let age = (last > 0).then(|| unix_ns().saturating_sub(last) as f64 / 1e9);
        BridgeStatus {
            section,
            key: key.to_string(),
            session: shared.id.clone(),
            peers: shared.peers(),
            messages_in: self.messages_in.load(Ordering::Relaxed),
            messages_out: self.messages_out.load(Ordering::Relaxed),
            malformed: self.malformed.load(Ordering::Relaxed),
            dropped: self.dropped.load(Ordering::Relaxed),
            last_seen_s_ago: age,
            last_error: self.last_error.lock().ok().and_then(|e| e.clone()),
        }
    }
}

/// A Zenoh or ROS 2 bridge's section of the report and the live status.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct BridgeStatus {
    #[serde(skip)]
    pub section: &'static str,
    pub key: String,
    pub session: String,
    pub peers: usize,
    #[serde(rename = "in")]
    pub messages_in: u64,
    #[serde(rename = "out")]
    pub messages_out: u64,
    pub malformed: u64,
    pub dropped: u64,
    pub last_seen_s_ago: Option<f64>,
    pub last_error: Option<String>,
}

impl StatusSection for BridgeStatus {
    fn section(&self) -> &'static str {
        self.section
    }

    fn to_json(&self) -> serde_json::Value {
        json_of(self)
    }
}

/// A `builtin:zenoh` session's section of the report and the live status.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct SessionStatus {
    pub session: String,
    pub peers: usize,
    pub connect: Vec<String>,
    pub listen: Vec<String>,
}

impl NamedSection for SessionStatus {
    const SECTION: &'static str = "zenoh-session";
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn endpoints_are_checked() {
        assert_eq!(endpoints(" tcp/127.0.0.1:7447 , ", "connect").ok(), Some(vec!["tcp/127.0.0.1:7447".to_string()]));
        assert!(endpoints("127.0.0.1:7447", "connect").is_err());
        assert!(endpoints("udp/127.0.0.1:7447", "connect").is_err());
        let many = vec!["tcp/127.0.0.1:1"; MAX_ENDPOINTS + 1].join(",");
        assert!(endpoints(&many, "listen").is_err());
    }

    #[test]
    fn the_default_config_is_peer_mode_without_multicast() {
        let settings = SessionSettings {
            connect: vec!["tcp/127.0.0.1:7447".into()],
            listen: vec![],
            config: None,
            max_message_bytes: None,
        };
        let config = settings.zenoh_config().unwrap_or_default();
        let get = |key| config.get_json(key).unwrap_or_default();
        assert_eq!(get("mode"), "\"peer\"");
        assert_eq!(get("scouting/multicast/enabled"), "false");
        assert_eq!(get("connect/endpoints"), "[\"tcp/127.0.0.1:7447\"]");
        assert_eq!(get("listen/endpoints"), "[]");
    }

    #[test]
    fn a_bounded_session_drops_a_larger_message_at_the_zenoh_layer_over_any_config_file() {
        let dir = tempfile::tempdir().unwrap_or_else(|e| panic!("tempdir: {e}"));
        let file = dir.path().join("zenoh.json5");
        std::fs::write(&file, "{ mode: \"peer\" }").unwrap_or_else(|e| panic!("write: {e}"));
        for config in [None, Some(file)] {
            let settings = SessionSettings { connect: vec![], listen: vec![], config, max_message_bytes: Some(1234) };
            let config = settings.zenoh_config().unwrap_or_else(|e| panic!("{e}"));
            assert_eq!(config.get_json(MAX_MESSAGE_SIZE_KEY).unwrap_or_default(), "1234");
        }
        // Over a real link: a message larger than the bound never arrives;
        // one within it, sent after it on the same link, does.
        let port = std::net::TcpListener::bind("127.0.0.1:0")
            .and_then(|l| l.local_addr())
            .map(|a| a.port())
            .unwrap_or_else(|e| panic!("{e}"));
        let endpoint = format!("tcp/127.0.0.1:{port}");
        let bounded = session(&SessionSettings {
            connect: vec![],
            listen: vec![endpoint.clone()],
            config: None,
            max_message_bytes: Some(256 << 10),
        })
        .unwrap_or_else(|e| panic!("{e}"));
        let sender = session(&SessionSettings {
            connect: vec![endpoint],
            listen: vec![],
            config: None,
            max_message_bytes: None,
        })
        .unwrap_or_else(|e| panic!("{e}"));
        let (heard, sizes) = std::sync::mpsc::channel();
        let _subscriber = bounded
            .session
            .declare_subscriber("subsume/test/bounded")
            .callback(move |sample: zenoh::sample::Sample| {
                let _ = heard.send(sample.payload().len());
            })
            .wait()
            .unwrap_or_else(|e| panic!("{e}"));
        let put = |bytes: usize| {
            sender
                .session
                .put("subsume/test/bounded", vec![7u8; bytes])
                .congestion_control(zenoh::qos::CongestionControl::Block)
                .wait()
                .unwrap_or_else(|e| panic!("{e}"))
        };
        let deadline = std::time::Instant::now() + Duration::from_secs(20);
        loop {
            put(10);
            if sizes.recv_timeout(Duration::from_millis(200)).is_ok() {
                break;
            }
            assert!(std::time::Instant::now() < deadline, "the sessions never linked");
        }
        put(1 << 20);
        put(100 << 10);
        let mut arrived = Vec::new();
        while let Ok(size) = sizes.recv_timeout(Duration::from_secs(3)) {
            arrived.push(size);
            if size == 100 << 10 {
                break;
            }
        }
        assert!(arrived.contains(&(100 << 10)) && !arrived.contains(&(1 << 20)), "{arrived:?}");
    }

    #[test]
    fn links_off_loopback_without_tls_or_authentication_are_named() {
        let dir = tempfile::tempdir().unwrap_or_else(|e| panic!("tempdir: {e}"));
        let file = dir.path().join("zenoh.json5");
        /// (case, config file, connect, listen, plain, unauthenticated)
        type Case<'a> = (&'a str, Option<&'a str>, &'a str, &'a str, Vec<&'a str>, Vec<&'a str>);
        let cases: Vec<Case> = vec![
            ("loopback only", None, "tcp/127.0.0.1:7447", "tcp/[::1]:7448", vec![], vec![]),
            ("localhost", None, "tcp/localhost:7447", "", vec![], vec![]),
            ("a plain listener", None, "", "tcp/0.0.0.0:7447", vec!["tcp/0.0.0.0:7447"], vec![]),
            ("a plain connection", None, "tcp/10.0.0.2:7447", "", vec!["tcp/10.0.0.2:7447"], vec![]),
            (
                "TLS, nobody authenticated",
                None,
                "tls/lab.example.org:7447",
                "",
                vec![],
                vec!["tls/lab.example.org:7447"],
            ),
            (
                "TLS with user/password",
                Some(
                    "{ listen: { endpoints: [] }, transport: { auth: { usrpwd: { user: \"r1\", password: \"secret\" } } } }",
                ),
                "tls/lab.example.org:7447",
                "",
                vec![],
                vec![],
            ),
            (
                "TLS with mutual TLS",
                Some("{ transport: { link: { tls: { enable_mtls: true } } } }"),
                "",
                "tls/0.0.0.0:7447",
                vec![],
                vec![],
            ),
            (
                "a config file naming no listener: Zenoh's default listens on every address",
                Some("{ mode: \"peer\" }"),
                "tcp/127.0.0.1:7447",
                "",
                vec!["tcp/[::]:0", "tcp/[::]:7447"],
                vec![],
            ),
            (
                "endpoints from the file",
                Some("{ listen: { endpoints: [\"tcp/192.168.1.2:7447\"] } }"),
                "",
                "",
                vec!["tcp/192.168.1.2:7447"],
                vec![],
            ),
        ];
        for (case, text, connect, listen, plain, unauthenticated) in cases {
            let config = text.map(|text| {
                std::fs::write(&file, text).unwrap_or_else(|e| panic!("write: {e}"));
                file.clone()
            });
            let list = |t: &str| t.split(',').filter(|s| !s.is_empty()).map(str::to_string).collect();
            let settings =
                SessionSettings { connect: list(connect), listen: list(listen), config, max_message_bytes: None };
            let config = settings.zenoh_config().unwrap_or_else(|e| panic!("{case}: {e}"));
            let exposure = link_exposure(&config);
            assert_eq!(
                (
                    exposure.plain.iter().map(String::as_str).collect::<Vec<_>>(),
                    exposure.unauthenticated.iter().map(String::as_str).collect::<Vec<_>>()
                ),
                (plain, unauthenticated),
                "{case}"
            );
        }
    }

    #[test]
    fn the_loop_puts_itself_only_when_a_congested_put_gives_up_at_once() {
        let settings = SessionSettings { connect: vec![], listen: vec![], config: None, max_message_bytes: None };
        let config = settings.zenoh_config().unwrap_or_default();
        assert_eq!(config.get_json(WAIT_BEFORE_DROP_KEY).unwrap_or_default(), LOOP_WAIT_BEFORE_DROP_US.to_string());
        assert!(loop_puts(&config));
        // A config file keeps its own value: Zenoh's default millisecond
        // keeps every put on the sender thread.
        let dir = tempfile::tempdir().unwrap_or_else(|e| panic!("tempdir: {e}"));
        let file = dir.path().join("zenoh.json5");
        std::fs::write(&file, "{ mode: \"peer\" }").unwrap_or_else(|e| panic!("write: {e}"));
        let settings =
            SessionSettings { connect: vec![], listen: vec![], config: Some(file.clone()), max_message_bytes: None };
        let config = settings.zenoh_config().unwrap_or_else(|e| panic!("{e}"));
        assert!(!loop_puts(&config));
        let quick = format!(
            "{{ mode: \"peer\", transport: {{ link: {{ tx: {{ queue: {{ congestion_control: {{ drop: {{ wait_before_drop: {MAX_LOOP_WAIT_BEFORE_DROP_US} }} }} }} }} }} }} }}"
        );
        std::fs::write(&file, quick).unwrap_or_else(|e| panic!("write: {e}"));
        let config = settings.zenoh_config().unwrap_or_else(|e| panic!("{e}"));
        assert!(loop_puts(&config));
    }
}
