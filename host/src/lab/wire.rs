//! The lab's messages over Zenoh (docs/lab.md, "Several robots"): what a
//! lab server and its robots say to each other, typed, versioned
//! ([`WIRE_VERSION`]), bounded and signed with the lab's shared secret.
//!
//! Every message is one envelope:
//!
//! ```text
//! "SLB1" | HMAC-SHA256 (32 bytes) | kind (1 byte) | header length (u32 LE) | header (JSON) | attachment
//! ```
//!
//! The MAC covers the lab's name, the kind, the header and the attachment,
//! under the lab's secret ([`LabKey`]): a robot obeys only messages of the
//! lab it was configured with, a status cannot be replayed as a dispatch
//! (the kind is signed), and a lab of another name or secret is refused
//! before its header is read. Requests that change something (a dispatch,
//! a stop) carry the time they were issued, refused beyond
//! [`MAX_CLOCK_SKEW_MS`] (a captured request replayed later).
//!
//! A robot's liveliness token carries its name, state and profile in its
//! key expression ([`TokenBody`], hex-encoded JSON with its MAC), so any
//! Zenoh client sees the robots (`subsume/lab/LAB/robot/**`).
//!
//! Invariants: nothing is parsed before its size and MAC are checked;
//! every list and text in a header is bounded ([`TokenBody::check`],
//! [`Dispatch::check`], ...), so a peer cannot make the other side hold
//! more than [`MAX_MESSAGE_BYTES`].

use std::collections::BTreeMap;

use hmac::{Hmac, Mac};
use serde::de::DeserializeOwned;
use serde::{Deserialize, Serialize};
use sha2::Sha256;
use thiserror::Error;

use crate::contract::clip;
use crate::store::experiments::{ExperimentState, RunResult, StateChange};

/// The version of every message's header (`v`). A receiver refuses a
/// newer one, never guesses at it.
pub const WIRE_VERSION: u32 = 1;

/// The envelope's first bytes.
pub const MAGIC: &[u8; 4] = b"SLB1";

/// Largest piece of a file or blob in one message: a peer never makes the
/// other hold more than this of a recording or a component at once.
pub const MAX_CHUNK_BYTES: usize = 1 << 20;

/// Largest header: a dispatch carries a whole robot file
/// (`config::limits::MAX_CONFIG_BYTES`) and its sources' list.
pub const MAX_HEADER_BYTES: usize = (crate::config::limits::MAX_CONFIG_BYTES as usize) + (64 << 10);

/// Largest message: a header and a chunk (a peer sending more is refused
/// before anything is parsed).
pub const MAX_MESSAGE_BYTES: usize = 4 + 32 + 1 + 4 + MAX_HEADER_BYTES + MAX_CHUNK_BYTES;

/// Fewest bytes a lab's secret has: a guessable secret lets anyone on the
/// Zenoh network send the robots work.
pub const MIN_SECRET_BYTES: usize = 16;

/// Largest secret file read.
pub const MAX_SECRET_BYTES: usize = 4096;

/// Longest name (a lab, a robot, a world, a translator, a file): names
/// are chunks of key expressions and lines of the portal.
pub const MAX_NAME_LEN: usize = 64;

/// Most worlds or translators a profile lists.
pub const MAX_PROFILE_ITEMS: usize = 16;

/// Most sources (components, uploaded worlds) a dispatched set names.
pub const MAX_SOURCES: usize = 64;

/// Most named files (worlds, translators) a baseline brings.
pub const MAX_NAMED_FILES: usize = 16;

/// Most result files an experiment gives back (the recording's rotations
/// among them).
pub const MAX_RESULT_FILES: usize = 64;

/// Most reasons or state changes carried (the rest are in the bundle).
pub const MAX_REASONS: usize = 32;

/// Longest text (a reason, a cause, a label) carried.
pub const MAX_TEXT_LEN: usize = 2000;

/// How far a request's issue time may be from the receiver's clock: a
/// captured dispatch or stop replayed later is refused.
pub const MAX_CLOCK_SKEW_MS: u64 = 30_000;

/// What a message is; signed with it, so one kind is never read as another.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[repr(u8)]
pub enum Kind {
    Token = 1,
    Heartbeat = 2,
    Status = 3,
    Dispatch = 4,
    DispatchReply = 5,
    Stop = 6,
    Estop = 7,
    Ack = 8,
    ResultsRequest = 9,
    Results = 10,
    FileRequest = 11,
    Chunk = 12,
    BaselineRequest = 13,
    Baseline = 14,
    LiveRequest = 15,
    Live = 16,
}

impl Kind {
    fn from_byte(byte: u8) -> Option<Kind> {
        use Kind::*;
        [
            Token,
            Heartbeat,
            Status,
            Dispatch,
            DispatchReply,
            Stop,
            Estop,
            Ack,
            ResultsRequest,
            Results,
            FileRequest,
            Chunk,
            BaselineRequest,
            Baseline,
            LiveRequest,
            Live,
        ]
        .into_iter()
        .find(|k| *k as u8 == byte)
    }
}

/// Why a message was refused.
#[derive(Debug, Error, PartialEq, Eq)]
pub enum WireError {
    #[error("the message is {size} bytes; at most {MAX_MESSAGE_BYTES} are accepted")]
    TooLarge { size: usize },
    #[error("the message is not a lab message (no SLB1 envelope)")]
    NotAnEnvelope,
    #[error("the message is cut short")]
    Truncated,
    #[error("the message's kind {0} is unknown")]
    UnknownKind(u8),
    #[error("expected a {expected:?} message, got {got:?}")]
    WrongKind { expected: Kind, got: Kind },
    #[error("the message is not signed by lab '{lab}' (another lab, or another secret)")]
    BadSignature { lab: String },
    #[error("the message's header does not read: {0}")]
    Header(String),
    #[error("the message's version {got} is newer than this host's {WIRE_VERSION}")]
    Version { got: u32 },
    #[error("the message is refused: {0}")]
    Invalid(String),
    #[error("the request was issued {skew_ms} ms from this host's clock; at most {MAX_CLOCK_SKEW_MS} are accepted")]
    Stale { skew_ms: u64 },
}

/// A broken bound of a message's header: what is wrong.
#[derive(Debug, Error, PartialEq, Eq)]
#[error("{0}")]
pub struct Broken(pub String);

impl From<&str> for Broken {
    fn from(text: &str) -> Broken {
        Broken(text.to_string())
    }
}

/// `Broken(format!(...))`.
macro_rules! broken {
    ($($arg:tt)*) => { Broken(format!($($arg)*)) };
}

/// Why a lab's key could not be made.
#[derive(Debug, Error)]
pub enum KeyError {
    #[error("lab secret {path}: {why}")]
    File { path: std::path::PathBuf, why: String },
    #[error("lab name '{0}': {MAX_NAME_LEN} letters, digits, '-' or '_' at most")]
    Name(String),
}

/// A lab's name and shared secret: what signs and checks its messages.
#[derive(Clone)]
pub struct LabKey {
    lab: String,
    /// The secret as HMAC's key block: zero-padded to SHA-256's block
    /// size, or hashed first when longer (RFC 2104), so making the MAC
    /// never fails.
    block: [u8; 64],
}

impl std::fmt::Debug for LabKey {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("LabKey").field("lab", &self.lab).finish_non_exhaustive()
    }
}

impl LabKey {
    /// The key of lab `lab` with `secret` (at least [`MIN_SECRET_BYTES`]).
    pub fn new(lab: &str, secret: &[u8]) -> Result<LabKey, KeyError> {
        if !is_name(lab) {
            return Err(KeyError::Name(clip(lab)));
        }
        let mut block = [0u8; 64];
        if secret.len() > block.len() {
            let digest = <Sha256 as sha2::Digest>::digest(secret);
            block[..digest.len()].copy_from_slice(&digest);
        } else {
            block[..secret.len()].copy_from_slice(secret);
        }
        Ok(LabKey { lab: lab.to_string(), block })
    }

    /// The key of lab `lab` with the secret in `path` (its first line,
    /// trimmed; at least [`MIN_SECRET_BYTES`]).
    pub fn from_file(lab: &str, path: &std::path::Path) -> Result<LabKey, KeyError> {
        let bad = |why: String| KeyError::File { path: path.to_path_buf(), why };
        let bytes = read_bounded(path, MAX_SECRET_BYTES as u64).map_err(|e| bad(e.to_string()))?;
        let text = String::from_utf8(bytes).map_err(|_| bad("is not text".into()))?;
        let secret = text.lines().next().unwrap_or_default().trim();
        if secret.len() < MIN_SECRET_BYTES {
            return Err(bad(format!(
                "holds {} bytes on its first line; a lab's secret has at least {MIN_SECRET_BYTES} (e.g. `openssl rand -hex 32`)",
                secret.len()
            )));
        }
        LabKey::new(lab, secret.as_bytes())
    }

    pub fn lab(&self) -> &str {
        &self.lab
    }

    /// The key of lab `lab` with the secret in `path`, which is made (32
    /// random bytes in hex, readable by its owner only) when missing: the
    /// lab server's first start.
    pub fn from_file_or_new(lab: &str, path: &std::path::Path) -> Result<LabKey, KeyError> {
        if !path.exists() {
            let bad = |why: String| KeyError::File { path: path.to_path_buf(), why };
            let secret = crate::store::users::random_hex(32).map_err(|e| bad(e.to_string()))?;
            let mut options = std::fs::OpenOptions::new();
            options.write(true).create_new(true);
            #[cfg(unix)]
            std::os::unix::fs::OpenOptionsExt::mode(&mut options, 0o600);
            let mut file = options.open(path).map_err(|e| bad(e.to_string()))?;
            std::io::Write::write_all(&mut file, format!("{secret}\n").as_bytes()).map_err(|e| bad(e.to_string()))?;
            file.sync_all().map_err(|e| bad(e.to_string()))?;
            tracing::info!("made the lab's secret {}: copy it to each robot (--lab-secret)", path.display());
        }
        LabKey::from_file(lab, path)
    }

    fn mac(&self, kind: Kind, header: &[u8], attachment: &[u8]) -> Hmac<Sha256> {
        let mut mac = <Hmac<Sha256> as hmac::digest::KeyInit>::new(&self.block.into());
        mac.update(self.lab.as_bytes());
        mac.update(&[0, kind as u8, 0]);
        mac.update(&(header.len() as u32).to_le_bytes());
        mac.update(header);
        mac.update(attachment);
        mac
    }

    /// The envelope of `message` with `attachment`.
    pub fn seal<M: Message>(&self, message: &M, attachment: &[u8]) -> Vec<u8> {
        let header = serde_json::to_vec(message).unwrap_or_default();
        let tag = self.mac(M::KIND, &header, attachment).finalize().into_bytes();
        let mut out = Vec::with_capacity(4 + 32 + 1 + 4 + header.len() + attachment.len());
        out.extend_from_slice(MAGIC);
        out.extend_from_slice(&tag);
        out.push(M::KIND as u8);
        out.extend_from_slice(&(header.len() as u32).to_le_bytes());
        out.extend_from_slice(&header);
        out.extend_from_slice(attachment);
        out
    }

    /// The message of kind `M` in `bytes`, checked (size, signature,
    /// version, bounds), with its attachment.
    pub fn open<'b, M: Message>(&self, bytes: &'b [u8]) -> Result<(M, &'b [u8]), WireError> {
        if bytes.len() > MAX_MESSAGE_BYTES {
            return Err(WireError::TooLarge { size: bytes.len() });
        }
        if bytes.len() < 4 || &bytes[..4] != MAGIC {
            return Err(WireError::NotAnEnvelope);
        }
        if bytes.len() < 4 + 32 + 1 + 4 {
            return Err(WireError::Truncated);
        }
        let tag = &bytes[4..36];
        let kind = Kind::from_byte(bytes[36]).ok_or(WireError::UnknownKind(bytes[36]))?;
        let header_len = u32::from_le_bytes([bytes[37], bytes[38], bytes[39], bytes[40]]) as usize;
        let rest = &bytes[41..];
        if header_len > MAX_HEADER_BYTES || header_len > rest.len() {
            return Err(WireError::Truncated);
        }
        let (header, attachment) = rest.split_at(header_len);
        self.mac(kind, header, attachment)
            .verify_slice(tag)
            .map_err(|_| WireError::BadSignature { lab: self.lab.clone() })?;
        if kind != M::KIND {
            return Err(WireError::WrongKind { expected: M::KIND, got: kind });
        }
        let version: Versioned = serde_json::from_slice(header).map_err(|e| WireError::Header(clip(&e.to_string())))?;
        if version.v > WIRE_VERSION {
            return Err(WireError::Version { got: version.v });
        }
        let message: M = serde_json::from_slice(header).map_err(|e| WireError::Header(clip(&e.to_string())))?;
        message.check().map_err(|b| WireError::Invalid(b.0))?;
        Ok((message, attachment))
    }

    /// The MAC of a token's body, as the key expression spells it (hex).
    fn token_tag(&self, body: &[u8]) -> String {
        hex::encode(self.mac(Kind::Token, body, &[]).finalize().into_bytes())
    }
}

/// The first `limit` bytes of the file at `path`; an error when it holds
/// more.
fn read_bounded(path: &std::path::Path, limit: u64) -> std::io::Result<Vec<u8>> {
    use std::io::Read;
    let mut bytes = Vec::new();
    std::fs::File::open(path)?.take(limit + 1).read_to_end(&mut bytes)?;
    if bytes.len() as u64 > limit {
        return Err(std::io::Error::other(format!("is larger than {limit} bytes")));
    }
    Ok(bytes)
}

#[derive(Deserialize)]
struct Versioned {
    v: u32,
}

/// A typed message: its kind and the checks of its bounds.
pub trait Message: Serialize + DeserializeOwned {
    const KIND: Kind;
    /// Every bound of the header; `Err` says which is broken.
    fn check(&self) -> Result<(), Broken> {
        Ok(())
    }
}

/// Whether `name` is a plain name: letters, digits, `-`, `_`, `.` (not
/// first), at most [`MAX_NAME_LEN`]: a key-expression chunk and a file
/// name at once.
pub fn is_name(name: &str) -> bool {
    !name.is_empty()
        && name.len() <= MAX_NAME_LEN
        && !name.starts_with('.')
        && name.bytes().all(|b| b.is_ascii_alphanumeric() || b"-_.".contains(&b))
}

fn name_ok(what: &str, name: &str) -> Result<(), Broken> {
    if is_name(name) { Ok(()) } else { Err(broken!("{what} '{}' is not a plain name", clip(name))) }
}

fn text_ok(what: &str, text: &str) -> Result<(), Broken> {
    if text.len() <= MAX_TEXT_LEN {
        Ok(())
    } else {
        Err(broken!("{what} is {} bytes; at most {MAX_TEXT_LEN}", text.len()))
    }
}

fn texts_ok(what: &str, texts: &[String]) -> Result<(), Broken> {
    if texts.len() > MAX_REASONS {
        return Err(broken!("{what} lists {}; at most {MAX_REASONS}", texts.len()));
    }
    texts.iter().try_for_each(|t| text_ok(what, t))
}

fn sha_ok(sha: &str) -> Result<(), Broken> {
    if sha.len() == 64 && sha.bytes().all(|b| b.is_ascii_hexdigit() && !b.is_ascii_uppercase()) {
        Ok(())
    } else {
        Err(broken!("'{}' is not a sha256 in hex", clip(sha)))
    }
}

/// Whether a request issued at `issued_ms` may be obeyed at `now_ms`.
pub fn fresh(issued_ms: u64, now_ms: u64) -> Result<(), WireError> {
    let skew_ms = issued_ms.abs_diff(now_ms);
    if skew_ms > MAX_CLOCK_SKEW_MS { Err(WireError::Stale { skew_ms }) } else { Ok(()) }
}

// ---------------------------------------------------------------------------
// Key expressions

/// The key expressions of lab `lab`.
#[derive(Clone, Debug)]
pub struct Keys {
    lab: String,
}

impl Keys {
    pub fn new(key: &LabKey) -> Keys {
        Keys { lab: key.lab.clone() }
    }

    /// Every robot's liveliness token.
    pub fn robot_tokens(&self) -> String {
        format!("subsume/lab/{}/robot/**", self.lab)
    }

    /// The lab server's liveliness token (informational: robots watch its
    /// heartbeat, which is signed).
    pub fn server_token(&self, instance: &str) -> String {
        format!("subsume/lab/{}/server/{instance}", self.lab)
    }

    pub fn heartbeat(&self) -> String {
        format!("subsume/lab/{}/heartbeat", self.lab)
    }

    /// Where the lab server serves the blobs of the sets it dispatches.
    pub fn blobs(&self) -> String {
        format!("subsume/lab/{}/blobs", self.lab)
    }

    pub fn status(&self, robot: &str) -> String {
        format!("subsume/lab/{}/status/{robot}", self.lab)
    }

    pub fn statuses(&self) -> String {
        format!("subsume/lab/{}/status/*", self.lab)
    }

    /// A robot's queryable for `op`.
    pub fn rpc(&self, robot: &str, op: Op) -> String {
        format!("subsume/lab/{}/rpc/{robot}/{}", self.lab, op.name())
    }
}

/// What a robot answers.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Op {
    Dispatch,
    Stop,
    Estop,
    Results,
    File,
    Baseline,
    Live,
}

impl Op {
    pub const ALL: [Op; 7] = [Op::Dispatch, Op::Stop, Op::Estop, Op::Results, Op::File, Op::Baseline, Op::Live];

    pub fn name(self) -> &'static str {
        match self {
            Op::Dispatch => "dispatch",
            Op::Stop => "stop",
            Op::Estop => "estop",
            Op::Results => "results",
            Op::File => "file",
            Op::Baseline => "baseline",
            Op::Live => "live",
        }
    }
}

// ---------------------------------------------------------------------------
// The robot's token and status

/// What a robot is doing.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(tag = "state", rename_all = "lowercase")]
pub enum RobotState {
    /// It runs its baseline and takes work.
    Idle,
    /// It runs the lab's experiment `experiment`.
    Running { experiment: u64 },
    /// An emergency stop is engaged (by whom).
    Stopped { by: String },
    /// Its owner paused its queue: it takes no work.
    Maintenance,
}

impl RobotState {
    /// One word for the key expression and the portal.
    pub fn word(&self) -> String {
        match self {
            RobotState::Idle => "idle".into(),
            RobotState::Running { experiment } => format!("running-{experiment}"),
            RobotState::Stopped { .. } => "stopped".into(),
            RobotState::Maintenance => "maintenance".into(),
        }
    }
}

/// What a robot can run: the worlds and translators it has, and its
/// baseline's hash; `id` is the short hash of the rest, which experiments
/// name ("any robot of profile P").
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Profile {
    pub id: String,
    pub baseline: String,
    pub worlds: Vec<String>,
    pub translators: Vec<String>,
}

/// Hex digits of a profile's id.
pub const PROFILE_ID_LEN: usize = 12;

impl Profile {
    /// The profile of a baseline with hash `baseline` and these worlds and
    /// translators (sorted, bounded), with its id.
    pub fn new(baseline: String, mut worlds: Vec<String>, mut translators: Vec<String>) -> Profile {
        for list in [&mut worlds, &mut translators] {
            list.sort();
            list.dedup();
            list.retain(|n| is_name(n));
            list.truncate(MAX_PROFILE_ITEMS);
        }
        let canonical = serde_json::json!({ "baseline": baseline, "worlds": worlds, "translators": translators });
        let id = crate::store::sha256_hex(canonical.to_string().as_bytes())[..PROFILE_ID_LEN].to_string();
        Profile { id, baseline, worlds, translators }
    }

    fn check(&self) -> Result<(), Broken> {
        if self.id.len() != PROFILE_ID_LEN || !self.id.bytes().all(|b| b.is_ascii_hexdigit()) {
            return Err(broken!("profile id '{}' is not {PROFILE_ID_LEN} hex digits", clip(&self.id)));
        }
        sha_ok(&self.baseline)?;
        for list in [&self.worlds, &self.translators] {
            if list.len() > MAX_PROFILE_ITEMS {
                return Err(broken!("a profile lists at most {MAX_PROFILE_ITEMS} worlds or translators"));
            }
            list.iter().try_for_each(|n| name_ok("a profile's item", n))?;
        }
        Ok(())
    }
}

/// What a robot's liveliness token says.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TokenBody {
    pub v: u32,
    pub name: String,
    /// Rises with every new token of this robot process: the newest wins
    /// while the old one is being undeclared.
    pub seq: u64,
    /// The robot process's start (ms since the Unix epoch): with `seq`,
    /// orders tokens across the robot's restarts.
    pub boot_ms: u64,
    #[serde(flatten)]
    pub state: RobotState,
    pub profile: Profile,
    /// The robot's own `max-duration`, seconds.
    pub max_duration_s: f64,
}

impl Message for TokenBody {
    const KIND: Kind = Kind::Token;
    fn check(&self) -> Result<(), Broken> {
        name_ok("robot", &self.name)?;
        if let RobotState::Stopped { by } = &self.state {
            text_ok("who stopped it", by)?;
        }
        self.profile.check()
    }
}

/// Longest token key expression: a token's body is small, and a peer's
/// must not make the lab hold more.
pub const MAX_TOKEN_KEY_LEN: usize = 4096;

impl LabKey {
    /// The key expression of `body`'s token:
    /// `subsume/lab/LAB/robot/NAME/STATE/HEX(JSON)/HEX(MAC)`.
    pub fn token_key(&self, body: &TokenBody) -> String {
        let json = serde_json::to_vec(body).unwrap_or_default();
        let tag = self.token_tag(&json);
        format!("subsume/lab/{}/robot/{}/{}/{}/{tag}", self.lab, body.name, body.state.word(), hex::encode(&json))
    }

    /// The token body a key expression carries, checked.
    pub fn read_token(&self, key: &str) -> Result<TokenBody, WireError> {
        if key.len() > MAX_TOKEN_KEY_LEN {
            return Err(WireError::TooLarge { size: key.len() });
        }
        let prefix = format!("subsume/lab/{}/robot/", self.lab);
        let rest = key.strip_prefix(&prefix).ok_or(WireError::NotAnEnvelope)?;
        let parts: Vec<&str> = rest.split('/').collect();
        let [name, word, body, tag] = parts[..] else { return Err(WireError::NotAnEnvelope) };
        let json = hex::decode(body).map_err(|_| WireError::NotAnEnvelope)?;
        let expected = self.token_tag(&json);
        let tag_bytes = hex::decode(tag).map_err(|_| WireError::BadSignature { lab: self.lab.clone() })?;
        if tag_bytes.len() != 32 || !constant_time_eq(expected.as_bytes(), tag.as_bytes()) {
            return Err(WireError::BadSignature { lab: self.lab.clone() });
        }
        let version: Versioned = serde_json::from_slice(&json).map_err(|e| WireError::Header(clip(&e.to_string())))?;
        if version.v > WIRE_VERSION {
            return Err(WireError::Version { got: version.v });
        }
        let token: TokenBody = serde_json::from_slice(&json).map_err(|e| WireError::Header(clip(&e.to_string())))?;
        token.check().map_err(|b| WireError::Invalid(b.0))?;
        if token.name != name || token.state.word() != word {
            return Err(WireError::Invalid("the key's name or state differs from its body".into()));
        }
        Ok(token)
    }
}

fn constant_time_eq(a: &[u8], b: &[u8]) -> bool {
    a.len() == b.len() && a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
}

/// The lab server is there: a robot that hears none for its lab-lost
/// setting ends the lab's experiment on its own.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Heartbeat {
    pub v: u32,
    /// The lab server process (its Zenoh id).
    pub server: String,
    pub at_unix_ms: u64,
}

impl Message for Heartbeat {
    const KIND: Kind = Kind::Heartbeat;
    fn check(&self) -> Result<(), Broken> {
        text_ok("server", &self.server)
    }
}

/// A robot's low-rate status.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Status {
    pub v: u32,
    pub name: String,
    pub at_unix_ms: u64,
    #[serde(flatten)]
    pub state: RobotState,
    /// The lab experiment it runs: when it started and ends (ms since the
    /// Unix epoch).
    pub started_unix_ms: Option<u64>,
    pub ends_unix_ms: Option<u64>,
    /// The engaged locks.
    pub locks: Vec<String>,
    /// The set that runs.
    pub set: Option<u64>,
}

impl Message for Status {
    const KIND: Kind = Kind::Status;
    fn check(&self) -> Result<(), Broken> {
        name_ok("robot", &self.name)?;
        texts_ok("locks", &self.locks)?;
        if let RobotState::Stopped { by } = &self.state {
            text_ok("who stopped it", by)?;
        }
        Ok(())
    }
}

// ---------------------------------------------------------------------------
// Dispatch

/// Stored bytes, named by their sha256.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct BlobRef {
    pub sha256: String,
    pub bytes: u64,
}

/// A set as staged: its robot file and the bytes each WASM source (and
/// uploaded world) was pinned to. Files its built-ins name that are not
/// among the sources are the robot's own (its profile's worlds and
/// translators).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SetManifest {
    pub config_name: String,
    pub config_text: String,
    pub platform: Option<String>,
    pub sources: BTreeMap<String, BlobRef>,
}

/// Largest blob a set names: a component upload's own limit.
pub const MAX_BLOB_BYTES: u64 = 256 << 20;

impl SetManifest {
    fn check(&self) -> Result<(), Broken> {
        name_ok("the robot file's name", &self.config_name)?;
        if self.config_text.len() as u64 > crate::config::limits::MAX_CONFIG_BYTES {
            return Err("the robot file is too large".into());
        }
        if self.sources.len() > MAX_SOURCES {
            return Err(broken!("the set names {} sources; at most {MAX_SOURCES}", self.sources.len()));
        }
        for (key, blob) in &self.sources {
            if key.is_empty() || key.len() > 1024 || key.chars().any(char::is_control) {
                return Err(broken!("source '{}' is not a source name", clip(key)));
            }
            sha_ok(&blob.sha256)?;
            if blob.bytes > MAX_BLOB_BYTES {
                return Err(broken!("source '{}' is {} bytes; at most {MAX_BLOB_BYTES}", clip(key), blob.bytes));
            }
        }
        if let Some(platform) = &self.platform {
            name_ok("platform", platform)?;
        }
        Ok(())
    }
}

/// The lab gives experiment `lab_id` to a robot: the set as staged, who
/// submitted it with the rights they hold in the lab, its duration.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Dispatch {
    pub v: u32,
    pub lab_id: u64,
    pub issued_unix_ms: u64,
    pub submitter: String,
    pub role: crate::store::users::Role,
    pub platforms: Vec<String>,
    pub label: String,
    pub duration_s: f64,
    pub set: SetManifest,
}

impl Message for Dispatch {
    const KIND: Kind = Kind::Dispatch;
    fn check(&self) -> Result<(), Broken> {
        name_ok("submitter", &self.submitter)?;
        text_ok("label", &self.label)?;
        if self.platforms.len() > 8 {
            return Err("too many platforms".into());
        }
        self.platforms.iter().try_for_each(|p| name_ok("platform", p))?;
        if !self.duration_s.is_finite() || self.duration_s <= 0.0 {
            return Err(broken!("duration {} is not a positive number of seconds", self.duration_s));
        }
        self.set.check()
    }
}

/// How a robot answered a dispatch.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "outcome", rename_all = "lowercase")]
pub enum DispatchOutcome {
    /// It runs (its own experiment `local_id`).
    Started { local_id: u64, started_unix_ms: u64, ends_unix_ms: u64 },
    /// It does not run it, and why (a check, its envelope, busy).
    Refused { reasons: Vec<String> },
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct DispatchReply {
    pub v: u32,
    pub lab_id: u64,
    #[serde(flatten)]
    pub outcome: DispatchOutcome,
}

impl Message for DispatchReply {
    const KIND: Kind = Kind::DispatchReply;
    fn check(&self) -> Result<(), Broken> {
        match &self.outcome {
            DispatchOutcome::Refused { reasons } => texts_ok("reasons", reasons),
            DispatchOutcome::Started { .. } => Ok(()),
        }
    }
}

/// Ends lab experiment `lab_id` on the robot (a cancel).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Stop {
    pub v: u32,
    pub lab_id: u64,
    pub by: String,
    pub issued_unix_ms: u64,
}

impl Message for Stop {
    const KIND: Kind = Kind::Stop;
    fn check(&self) -> Result<(), Broken> {
        name_ok("who", &self.by)
    }
}

/// Engages the robot's emergency stop (the lab's STOP).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Estop {
    pub v: u32,
    pub by: String,
    pub issued_unix_ms: u64,
}

impl Message for Estop {
    const KIND: Kind = Kind::Estop;
    fn check(&self) -> Result<(), Broken> {
        name_ok("who", &self.by)
    }
}

/// The answer to a stop or an emergency stop.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Ack {
    pub v: u32,
    pub ok: bool,
    pub message: String,
}

impl Message for Ack {
    const KIND: Kind = Kind::Ack;
    fn check(&self) -> Result<(), Broken> {
        text_ok("message", &self.message)
    }
}

// ---------------------------------------------------------------------------
// Results and files

/// Asks what the robot kept of lab experiment `lab_id`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ResultsRequest {
    pub v: u32,
    pub lab_id: u64,
}

impl Message for ResultsRequest {
    const KIND: Kind = Kind::ResultsRequest;
}

/// A file of an experiment's results on the robot.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct FileRef {
    pub name: String,
    pub bytes: u64,
    pub sha256: String,
}

/// What the robot kept of a lab experiment: its state there, and its files.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Results {
    pub v: u32,
    pub lab_id: u64,
    /// Whether the robot knows the experiment at all.
    pub found: bool,
    pub state: Option<ExperimentState>,
    pub history: Vec<StateChange>,
    pub reasons: Vec<String>,
    pub run: Option<RunResult>,
    pub files: Vec<FileRef>,
}

impl Message for Results {
    const KIND: Kind = Kind::Results;
    fn check(&self) -> Result<(), Broken> {
        texts_ok("reasons", &self.reasons)?;
        if self.history.len() > MAX_REASONS {
            return Err(broken!("the history lists {}; at most {MAX_REASONS}", self.history.len()));
        }
        self.history.iter().try_for_each(|c| text_ok("a cause", &c.cause))?;
        if self.files.len() > MAX_RESULT_FILES {
            return Err(broken!("{} result files; at most {MAX_RESULT_FILES}", self.files.len()));
        }
        for file in &self.files {
            if !crate::lab::bundle::is_result_file(&file.name) {
                return Err(broken!("'{}' is not a result file", clip(&file.name)));
            }
            sha_ok(&file.sha256)?;
        }
        Ok(())
    }
}

/// Which file a chunk is asked of.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(tag = "from", rename_all = "lowercase")]
pub enum FileSource {
    /// A result file of lab experiment `lab_id` (robot).
    Result { lab_id: u64, name: String },
    /// A stored blob (robot: its baseline's; lab server: a set's).
    Blob { sha256: String },
    /// A file the robot's baseline names, relative to its folder (robot).
    Named { path: String },
}

/// Asks `len` bytes of a file from `offset`.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct FileRequest {
    pub v: u32,
    #[serde(flatten)]
    pub source: FileSource,
    pub offset: u64,
    pub len: u64,
}

impl Message for FileRequest {
    const KIND: Kind = Kind::FileRequest;
    fn check(&self) -> Result<(), Broken> {
        if self.len > MAX_CHUNK_BYTES as u64 {
            return Err(broken!("a chunk is at most {MAX_CHUNK_BYTES} bytes"));
        }
        match &self.source {
            FileSource::Result { name, .. } if !crate::lab::bundle::is_result_file(name) => {
                Err(broken!("'{}' is not a result file", clip(name)))
            }
            FileSource::Result { .. } => Ok(()),
            FileSource::Blob { sha256 } => sha_ok(sha256),
            FileSource::Named { path } => named_path_ok(path),
        }
    }
}

/// Whether `path` is a relative path of plain names (a baseline's named
/// file): never absolute, never `..`.
pub fn named_path_ok(path: &str) -> Result<(), Broken> {
    let parts: Vec<&str> = path.split('/').collect();
    if path.len() > 256 || parts.len() > 4 || !parts.iter().all(|p| is_name(p)) {
        return Err(broken!("'{}' is not a relative path of plain names", clip(path)));
    }
    Ok(())
}

/// A piece of a file (the bytes are the attachment).
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Chunk {
    pub v: u32,
    pub offset: u64,
    /// The whole file's size.
    pub total: u64,
    /// Why there is none (no such file), when there is none.
    pub missing: Option<String>,
}

impl Message for Chunk {
    const KIND: Kind = Kind::Chunk;
    fn check(&self) -> Result<(), Broken> {
        self.missing.as_deref().map_or(Ok(()), |m| text_ok("why", m))
    }
}

// ---------------------------------------------------------------------------
// The robot's baseline, and its live view

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct BaselineRequest {
    pub v: u32,
}

impl Message for BaselineRequest {
    const KIND: Kind = Kind::BaselineRequest;
}

/// A robot's baseline as staged, with the files its built-ins name
/// (relative to its folder): what the lab server stages and preflights
/// experiments for robots of its profile against.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Baseline {
    pub v: u32,
    pub hash: String,
    pub set: SetManifest,
    pub files: BTreeMap<String, BlobRef>,
}

impl Message for Baseline {
    const KIND: Kind = Kind::Baseline;
    fn check(&self) -> Result<(), Broken> {
        sha_ok(&self.hash)?;
        self.set.check()?;
        if self.files.len() > MAX_NAMED_FILES {
            return Err(broken!("a baseline names at most {MAX_NAMED_FILES} files"));
        }
        for (path, blob) in &self.files {
            named_path_ok(path)?;
            sha_ok(&blob.sha256)?;
        }
        Ok(())
    }
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct LiveRequest {
    pub v: u32,
}

impl Message for LiveRequest {
    const KIND: Kind = Kind::LiveRequest;
}

/// Largest live status carried (the portal's live status of one robot).
pub const MAX_LIVE_BYTES: usize = 256 << 10;

/// A robot's live status (the portal's `/api/v1/status` of that robot).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Live {
    pub v: u32,
    pub status: serde_json::Value,
}

impl Message for Live {
    const KIND: Kind = Kind::Live;
}

#[cfg(test)]
mod tests {
    use super::*;

    fn key(lab: &str, secret: &str) -> LabKey {
        LabKey::new(lab, secret.as_bytes()).unwrap_or_else(|e| panic!("{e}"))
    }

    fn profile() -> Profile {
        Profile::new("a".repeat(64), vec!["lab.world".into()], vec!["ascii".into()])
    }

    fn dispatch() -> Dispatch {
        Dispatch {
            v: WIRE_VERSION,
            lab_id: 7,
            issued_unix_ms: 1000,
            submitter: "ana".into(),
            role: crate::store::users::Role::Researcher,
            platforms: vec!["control".into()],
            label: "wall follower".into(),
            duration_s: 5.0,
            set: SetManifest {
                config_name: "ana.xml".into(),
                config_text: "<robot/>".into(),
                platform: Some("control".into()),
                sources: BTreeMap::from([("planner.wasm".to_string(), BlobRef { sha256: "b".repeat(64), bytes: 10 })]),
            },
        }
    }

    #[test]
    fn a_sealed_message_opens_with_its_key_and_attachment() {
        let lab = key("lab-a", "0123456789abcdef-secret");
        let sealed = lab.seal(&dispatch(), b"bytes");
        let (opened, attachment) = lab.open::<Dispatch>(&sealed).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!((opened, attachment), (dispatch(), &b"bytes"[..]));
    }

    #[test]
    fn another_lab_or_secret_or_kind_or_a_changed_byte_is_refused() {
        let lab = key("lab-a", "0123456789abcdef-secret");
        let sealed = lab.seal(&dispatch(), b"");
        let bad_signature = |e: Result<(Dispatch, &[u8]), WireError>| matches!(e, Err(WireError::BadSignature { .. }));
        assert!(bad_signature(key("lab-a", "0123456789abcdef-other").open::<Dispatch>(&sealed)));
        assert!(bad_signature(key("lab-b", "0123456789abcdef-secret").open::<Dispatch>(&sealed)));
        for at in [4, 20, 36, 41, sealed.len() - 1] {
            let mut changed = sealed.clone();
            changed[at] ^= 1;
            assert!(lab.open::<Dispatch>(&changed).is_err(), "byte {at}");
        }
        // A signed status is not a dispatch.
        let status = lab.seal(&Ack { v: 1, ok: true, message: String::new() }, b"");
        assert_eq!(
            lab.open::<Dispatch>(&status).err(),
            Some(WireError::WrongKind { expected: Kind::Dispatch, got: Kind::Ack })
        );
    }

    #[test]
    fn malformed_and_oversized_messages_are_refused_before_parsing() {
        let lab = key("lab-a", "0123456789abcdef-secret");
        // (case, bytes, expected error)
        let cases: Vec<(&str, Vec<u8>, WireError)> = vec![
            ("empty", vec![], WireError::NotAnEnvelope),
            ("other magic", b"XXXX0000000000000000000000000000000000000000".to_vec(), WireError::NotAnEnvelope),
            ("cut short", b"SLB1abc".to_vec(), WireError::Truncated),
            ("too large", vec![0; MAX_MESSAGE_BYTES + 1], WireError::TooLarge { size: MAX_MESSAGE_BYTES + 1 }),
        ];
        for (case, bytes, expected) in cases {
            assert_eq!(lab.open::<Dispatch>(&bytes).err(), Some(expected), "{case}");
        }
        let mut long_header = lab.seal(&dispatch(), b"");
        long_header[37..41].copy_from_slice(&u32::MAX.to_le_bytes());
        assert_eq!(lab.open::<Dispatch>(&long_header).err(), Some(WireError::Truncated));
    }

    #[test]
    fn newer_versions_and_broken_bounds_are_refused_by_name() {
        let lab = key("lab-a", "0123456789abcdef-secret");
        let newer = Dispatch { v: WIRE_VERSION + 1, ..dispatch() };
        assert_eq!(lab.open::<Dispatch>(&lab.seal(&newer, b"")).err(), Some(WireError::Version { got: 2 }));
        let mut too_many = dispatch();
        for i in 0..=MAX_SOURCES {
            too_many.set.sources.insert(format!("c{i}.wasm"), BlobRef { sha256: "c".repeat(64), bytes: 1 });
        }
        let cases: Vec<(&str, Dispatch, &str)> = vec![
            ("a path as submitter", Dispatch { submitter: "../x".into(), ..dispatch() }, "submitter '../x'"),
            ("no duration", Dispatch { duration_s: 0.0, ..dispatch() }, "duration 0"),
            ("a negative duration", Dispatch { duration_s: -1.0, ..dispatch() }, "duration -1"),
            ("too many sources", too_many, "at most 64"),
            ("a long label", Dispatch { label: "x".repeat(MAX_TEXT_LEN + 1), ..dispatch() }, "label is"),
        ];
        // JSON has no NaN: serde writes null, refused as it is read.
        let nan = Dispatch { duration_s: f64::NAN, ..dispatch() };
        assert!(matches!(lab.open::<Dispatch>(&lab.seal(&nan, b"")), Err(WireError::Header(_))));
        for (case, message, words) in cases {
            match lab.open::<Dispatch>(&lab.seal(&message, b"")) {
                Err(WireError::Invalid(why)) => assert!(why.contains(words), "{case}: {why}"),
                other => panic!("{case}: {other:?}"),
            }
        }
    }

    #[test]
    fn a_token_key_carries_the_robot_and_reads_back_only_with_the_labs_key() {
        let lab = key("lab-a", "0123456789abcdef-secret");
        let body = TokenBody {
            v: WIRE_VERSION,
            name: "r1".into(),
            seq: 3,
            boot_ms: 99,
            state: RobotState::Running { experiment: 12 },
            profile: profile(),
            max_duration_s: 120.0,
        };
        let token = lab.token_key(&body);
        assert!(token.starts_with("subsume/lab/lab-a/robot/r1/running-12/"), "{token}");
        assert!(zenoh::key_expr::KeyExpr::try_from(token.clone()).is_ok(), "{token}");
        assert_eq!(lab.read_token(&token).ok(), Some(body.clone()));
        assert!(matches!(
            key("lab-a", "0123456789abcdef-other").read_token(&token),
            Err(WireError::BadSignature { .. })
        ));
        // The key's plain chunks must agree with the signed body.
        let lied = token.replace("/running-12/", "/idle/");
        assert!(matches!(lab.read_token(&lied), Err(WireError::Invalid(_))));
        assert!(lab.read_token("subsume/lab/lab-a/robot/r1").is_err());
    }

    #[test]
    fn profiles_are_named_by_their_contents() {
        let a = profile();
        let b = Profile::new("a".repeat(64), vec!["lab.world".into(), "lab.world".into()], vec!["ascii".into()]);
        let c = Profile::new("a".repeat(64), vec!["other.world".into()], vec!["ascii".into()]);
        assert_eq!(a, b);
        assert_ne!(a.id, c.id);
        assert_eq!(a.id.len(), PROFILE_ID_LEN);
    }

    #[test]
    fn requests_are_fresh_only_near_the_receivers_clock() {
        assert!(fresh(100_000, 100_000 + MAX_CLOCK_SKEW_MS).is_ok());
        assert_eq!(fresh(100_000, 100_001 + MAX_CLOCK_SKEW_MS), Err(WireError::Stale { skew_ms: 30_001 }));
        assert!(fresh(200_000, 100_000).is_err());
    }

    #[test]
    fn file_requests_name_only_result_files_and_relative_paths() {
        let request = |source| FileRequest { v: 1, source, offset: 0, len: 10 };
        let ok = [
            FileSource::Result { lab_id: 1, name: "run.mcap".into() },
            FileSource::Named { path: "worlds/lab.world".into() },
            FileSource::Blob { sha256: "d".repeat(64) },
        ];
        for source in ok {
            assert_eq!(request(source.clone()).check(), Ok(()), "{source:?}");
        }
        let bad = [
            FileSource::Result { lab_id: 1, name: "../store/users.json".into() },
            FileSource::Named { path: "/etc/passwd".into() },
            FileSource::Named { path: "../secret".into() },
            FileSource::Blob { sha256: "../x".into() },
        ];
        for source in bad {
            assert!(request(source.clone()).check().is_err(), "{source:?}");
        }
        let big =
            FileRequest { len: MAX_CHUNK_BYTES as u64 + 1, ..request(FileSource::Blob { sha256: "d".repeat(64) }) };
        assert!(big.check().is_err());
    }

    #[test]
    fn a_secret_file_must_hold_enough() {
        let dir = tempfile::tempdir().unwrap_or_else(|e| panic!("{e}"));
        let path = dir.path().join("secret");
        std::fs::write(&path, "short\n").unwrap_or_else(|e| panic!("{e}"));
        let error = LabKey::from_file("lab", &path).err().map(|e| e.to_string()).unwrap_or_default();
        assert!(error.contains("at least 16"), "{error}");
        std::fs::write(&path, "0123456789abcdef0123\nignored\n").unwrap_or_else(|e| panic!("{e}"));
        assert!(LabKey::from_file("lab", &path).is_ok());
        assert!(LabKey::new("a/b", b"0123456789abcdef").is_err());
    }
}
