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
//! before its header is read.
//!
//! Requests and replies are bound ([`Asked`], [`Answered`]): every request
//! names the robot it is for, the time it was issued and a fresh random
//! nonce; a robot refuses one naming another robot, one issued beyond
//! [`MAX_CLOCK_SKEW_MS`] from its clock, and one whose nonce it has seen
//! ([`Replays`]: a captured request replayed to it or to another robot).
//! Its reply carries the request's nonce and its own name under the
//! reply's MAC, and the asker takes only a reply bound to its request
//! ([`bound`]): a reply captured from another exchange answers nothing.
//! A message that does not verify gets no signed answer (no reply at all,
//! or an unsigned fixed refusal), so nobody collects signed replies by
//! sending junk; refusals are counted by [`Refusal`] class
//! ([`RefusalTally`]) and audited at most once per
//! [`REFUSAL_AUDIT_INTERVAL_MS`].
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

/// The version of every message's header (`v`). A receiver refuses any
/// other, by name, never guesses at it: version 2 binds replies to their
/// requests, and a host of version 1 could not tell them apart.
pub const WIRE_VERSION: u32 = 2;

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

/// Largest message the lab's Zenoh sessions reassemble (Zenoh's own
/// `transport/link/rx/max_message_size`, 1 GiB by default): a lab message
/// and Zenoh's framing. A peer sending more is dropped by Zenoh before the
/// lab's code holds it.
pub const MAX_ZENOH_MESSAGE_BYTES: usize = MAX_MESSAGE_BYTES + (64 << 10);

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

/// Random bytes of a request's nonce (hex in the header).
pub const NONCE_BYTES: usize = 16;

/// Most nonces a queryable remembers within the freshness window: the
/// threat is the lab's own traffic (or a flood of replayed signed
/// requests) growing a robot's memory. Past it, the oldest is forgotten
/// and nothing issued at or before it is taken any more.
pub const MAX_REMEMBERED_NONCES: usize = 4096;

/// How often, at most, a robot's audit log gets a line about refused lab
/// messages (their counts by class): a flood of junk queries must not
/// write (and fsync) one line each.
pub const REFUSAL_AUDIT_INTERVAL_MS: u64 = 10_000;

/// What a request for the lab server itself (a blob of a set) names as
/// its target: never a robot's name (`@` is not in a plain name).
pub const SERVER_TARGET: &str = "@server";

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
    #[error(
        "the message's version {got} is not this host's {WIRE_VERSION}: lab hosts of both versions cannot work together; run one version"
    )]
    Version { got: u32 },
    #[error("the message is refused: {0}")]
    Invalid(String),
    #[error("the request was issued {skew_ms} ms from this host's clock; at most {MAX_CLOCK_SKEW_MS} are accepted")]
    Stale { skew_ms: u64 },
    #[error("the request names robot '{named}', not this one")]
    OtherTarget { named: String },
    #[error("the request was seen already (a replay), or is older than the oldest one remembered")]
    Replayed,
    #[error("the reply is not bound to this request: {0}")]
    Unbound(String),
}

impl WireError {
    /// The class of a refusal, as counted and audited.
    pub fn class(&self) -> Refusal {
        match self {
            WireError::BadSignature { .. } => Refusal::NotSigned,
            WireError::TooLarge { .. }
            | WireError::NotAnEnvelope
            | WireError::Truncated
            | WireError::UnknownKind(_)
            | WireError::WrongKind { .. }
            | WireError::Header(_)
            | WireError::Invalid(_) => Refusal::Malformed,
            WireError::Version { .. } => Refusal::Version,
            WireError::Stale { .. } => Refusal::Stale,
            WireError::OtherTarget { .. } => Refusal::OtherTarget,
            WireError::Replayed => Refusal::Replayed,
            WireError::Unbound(_) => Refusal::Unbound,
        }
    }

    /// Whether the message was signed with the lab's key (the error came
    /// after its MAC verified): only those may get an answer, and then an
    /// unsigned one.
    pub fn signed(&self) -> bool {
        !matches!(
            self,
            WireError::BadSignature { .. }
                | WireError::TooLarge { .. }
                | WireError::NotAnEnvelope
                | WireError::Truncated
                | WireError::UnknownKind(_)
        )
    }
}

/// Why a message was refused, as counted: one word each.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum Refusal {
    /// Not signed with the lab's key (junk, another lab, a forger).
    NotSigned,
    /// Not a lab message, cut short, too large, or breaking a bound.
    Malformed,
    /// Another wire version.
    Version,
    /// Issued too far from the receiver's clock.
    Stale,
    /// Seen already.
    Replayed,
    /// Naming another robot.
    OtherTarget,
    /// A reply bound to another request or robot (the asker's side).
    Unbound,
    /// Admitted, but the queryable's backlog was full.
    Busy,
}

impl Refusal {
    pub const ALL: [Refusal; 8] = [
        Refusal::NotSigned,
        Refusal::Malformed,
        Refusal::Version,
        Refusal::Stale,
        Refusal::Replayed,
        Refusal::OtherTarget,
        Refusal::Unbound,
        Refusal::Busy,
    ];

    pub fn word(self) -> &'static str {
        match self {
            Refusal::NotSigned => "not-signed",
            Refusal::Malformed => "malformed",
            Refusal::Version => "version",
            Refusal::Stale => "stale",
            Refusal::Replayed => "replayed",
            Refusal::OtherTarget => "other-robot",
            Refusal::Unbound => "unbound",
            Refusal::Busy => "busy",
        }
    }
}

/// Refusals counted by class, and when they were last audited: at most
/// one audit line per [`REFUSAL_AUDIT_INTERVAL_MS`], carrying the counts
/// since the last (explicit time: `now_ms`).
#[derive(Clone, Debug, Default)]
pub struct RefusalTally {
    total: BTreeMap<Refusal, u64>,
    unaudited: BTreeMap<Refusal, u64>,
    last_audit_ms: Option<u64>,
}

impl RefusalTally {
    pub fn note(&mut self, class: Refusal) {
        *self.total.entry(class).or_default() += 1;
        *self.unaudited.entry(class).or_default() += 1;
    }

    /// Every refusal so far, by class.
    pub fn totals(&self) -> &BTreeMap<Refusal, u64> {
        &self.total
    }

    pub fn sum(&self) -> u64 {
        self.total.values().sum()
    }

    /// The audit line due at `now_ms`, if any: the counts since the last
    /// line, once the interval has passed since it.
    pub fn due(&mut self, now_ms: u64) -> Option<String> {
        if self.unaudited.is_empty()
            || self.last_audit_ms.is_some_and(|at| now_ms.saturating_sub(at) < REFUSAL_AUDIT_INTERVAL_MS)
        {
            return None;
        }
        self.last_audit_ms = Some(now_ms);
        let counts = std::mem::take(&mut self.unaudited);
        let n: u64 = counts.values().sum();
        let each: Vec<String> = counts.iter().map(|(class, count)| format!("{} {count}", class.word())).collect();
        Some(format!("{n} lab messages refused since the last line ({})", each.join(", ")))
    }
}

/// The unsigned refusal a queryable answers a signed request it will not
/// obey with (a replay, a stale one, one for another robot): fixed text,
/// no MAC, so it answers nothing.
pub fn refusal_text(error: &WireError) -> String {
    format!("refused ({}): {error}", error.class().word())
}

/// Who a request is for, when it was issued, and its nonce.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Asked {
    /// The robot asked ([`SERVER_TARGET`] for the lab server).
    pub robot: String,
    pub issued_unix_ms: u64,
    /// [`NONCE_BYTES`] random bytes in hex.
    pub nonce: String,
}

impl Asked {
    /// A request for `robot` issued at `now_ms`, with a fresh nonce.
    pub fn new(robot: &str, now_ms: u64) -> Asked {
        Asked { robot: robot.to_string(), issued_unix_ms: now_ms, nonce: nonce() }
    }

    fn check(&self) -> Result<(), Broken> {
        if self.robot != SERVER_TARGET {
            name_ok("the robot asked", &self.robot)?;
        }
        nonce_ok(&self.nonce)
    }
}

/// A reply's binding: the answering robot and the request's nonce.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Answered {
    pub robot: String,
    pub nonce: String,
}

impl Answered {
    /// The binding of `me`'s reply to `asked`.
    pub fn to(asked: &Asked, me: &str) -> Answered {
        Answered { robot: me.to_string(), nonce: asked.nonce.clone() }
    }

    fn check(&self) -> Result<(), Broken> {
        if self.robot != SERVER_TARGET {
            name_ok("the robot answering", &self.robot)?;
        }
        nonce_ok(&self.nonce)
    }
}

fn nonce_ok(nonce: &str) -> Result<(), Broken> {
    if nonce.len() == 2 * NONCE_BYTES && nonce.bytes().all(|b| b.is_ascii_hexdigit() && !b.is_ascii_uppercase()) {
        Ok(())
    } else {
        Err(Broken(format!("'{}' is not a nonce ({NONCE_BYTES} bytes in hex)", clip(nonce))))
    }
}

/// A fresh nonce: random bytes from the system; should it have none, a
/// hash of the process, the time and a counter (a nonce needs to be
/// unique, not secret).
fn nonce() -> String {
    let mut bytes = [0u8; NONCE_BYTES];
    if getrandom::fill(&mut bytes).is_ok() {
        return hex::encode(bytes);
    }
    static COUNTER: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
    let n = COUNTER.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    let nanos = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map_or(0, |d| d.as_nanos());
    let seed = format!("{}-{nanos}-{n}", std::process::id());
    crate::store::sha256_hex(seed.as_bytes())[..2 * NONCE_BYTES].to_string()
}

/// A request: it says whom it asks, when, and its nonce.
pub trait Request: Message {
    fn asked(&self) -> &Asked;
}

/// A reply: it says who answers which request.
pub trait Reply: Message {
    fn answered(&self) -> &Answered;
}

/// Whether `reply` answers `asked`: its nonce, from the robot asked.
pub fn bound(asked: &Asked, reply: &Answered) -> Result<(), WireError> {
    if reply.nonce != asked.nonce {
        return Err(WireError::Unbound("it answers another request (another nonce)".into()));
    }
    if reply.robot != asked.robot {
        return Err(WireError::Unbound(format!(
            "robot '{}' answered a request for '{}'",
            clip(&reply.robot),
            clip(&asked.robot)
        )));
    }
    Ok(())
}

/// The requests one queryable admitted within the freshness window, by
/// nonce: who it is (`me`), and the rules a request passes before it is
/// obeyed (explicit time; a table test covers them).
#[derive(Debug)]
pub struct Replays {
    me: String,
    seen: std::collections::HashSet<String>,
    by_time: std::collections::BTreeSet<(u64, String)>,
    /// Nothing issued at or before this is taken: a nonce that old may
    /// have been forgotten.
    floor_ms: u64,
    capacity: usize,
}

impl Replays {
    pub fn new(me: &str) -> Replays {
        Replays::with_capacity(me, MAX_REMEMBERED_NONCES)
    }

    pub fn with_capacity(me: &str, capacity: usize) -> Replays {
        Replays {
            me: me.to_string(),
            seen: Default::default(),
            by_time: Default::default(),
            floor_ms: 0,
            capacity: capacity.max(1),
        }
    }

    /// Whether a request `asked` may be obeyed at `now_ms`: it names this
    /// host, is fresh, and its nonce is new (then remembered).
    pub fn admit(&mut self, asked: &Asked, now_ms: u64) -> Result<(), WireError> {
        if asked.robot != self.me {
            return Err(WireError::OtherTarget { named: clip(&asked.robot) });
        }
        fresh(asked.issued_unix_ms, now_ms)?;
        // What can no longer pass the freshness check needs no memory.
        while let Some((issued, _)) = self.by_time.first()
            && issued.saturating_add(MAX_CLOCK_SKEW_MS) < now_ms
        {
            if let Some((_, nonce)) = self.by_time.pop_first() {
                self.seen.remove(&nonce);
            }
        }
        if asked.issued_unix_ms <= self.floor_ms || self.seen.contains(&asked.nonce) {
            return Err(WireError::Replayed);
        }
        if self.seen.len() >= self.capacity
            && let Some((issued, nonce)) = self.by_time.pop_first()
        {
            self.seen.remove(&nonce);
            self.floor_ms = self.floor_ms.max(issued);
            if asked.issued_unix_ms <= self.floor_ms {
                return Err(WireError::Replayed);
            }
        }
        self.seen.insert(asked.nonce.clone());
        self.by_time.insert((asked.issued_unix_ms, asked.nonce.clone()));
        Ok(())
    }

    /// These replays, taking nothing issued at or before `start_ms` (this
    /// process's start): a request captured before a robot restarted is
    /// not taken by the new process, which remembers none.
    pub fn since(mut self, start_ms: u64) -> Replays {
        self.floor_ms = self.floor_ms.max(start_ms);
        self
    }

    /// How many nonces are remembered.
    pub fn len(&self) -> usize {
        self.seen.len()
    }

    pub fn is_empty(&self) -> bool {
        self.seen.is_empty()
    }
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
        if version.v != WIRE_VERSION {
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
    /// Its owner paused its queue, or an admin took it out of service
    /// (`lab/maintenance.rs`): it takes no work.
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
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize, schemars::JsonSchema)]
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
        if version.v != WIRE_VERSION {
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
    /// How often it publishes its status (ms): the lab server counts it
    /// lost after [`STATUS_SILENCE_PERIODS`] of them without one.
    pub period_ms: u64,
    /// Lab messages its link refused so far (junk, replays, stale, for
    /// another robot): the lab server's /metrics sums them.
    pub refused: u64,
}

/// How many status periods without a fresh signed status make a robot
/// lost (never less than [`MIN_STATUS_SILENCE_MS`]): a liveliness token
/// someone re-declares must not keep a dead robot listed.
pub const STATUS_SILENCE_PERIODS: u64 = 5;
/// The least silence that makes a robot lost: a robot or lab server
/// starved for seconds on a loaded machine (seen at a load of 20 on two
/// cores: 3 s aborted running experiments) must not lose its experiments.
/// A robot whose token goes is lost at once anyway.
pub const MIN_STATUS_SILENCE_MS: u64 = 10_000;

impl Status {
    /// How long without a newer status makes this robot lost.
    pub fn silence_ms(&self) -> u64 {
        self.period_ms.saturating_mul(STATUS_SILENCE_PERIODS).max(MIN_STATUS_SILENCE_MS)
    }
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
    pub to: Asked,
    pub lab_id: u64,
    pub submitter: String,
    pub role: crate::store::users::Role,
    pub platforms: Vec<String>,
    pub label: String,
    pub duration_s: f64,
    pub set: SetManifest,
    /// The lab stops waiting for the answer at this time (ms since the
    /// Unix epoch, the lab server's clock): the robot takes it and starts
    /// it only before then, so a dispatch whose answer was lost never runs
    /// behind the lab's back (docs/lab.md, "When a dispatch goes
    /// unanswered").
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub start_by_unix_ms: Option<u64>,
}

impl Message for Dispatch {
    const KIND: Kind = Kind::Dispatch;
    fn check(&self) -> Result<(), Broken> {
        self.to.check()?;
        name_ok("submitter", &self.submitter)?;
        text_ok("label", &self.label)?;
        if self.platforms.len() > 8 {
            return Err("too many platforms".into());
        }
        self.platforms.iter().try_for_each(|p| name_ok("platform", p))?;
        if !self.duration_s.is_finite() || self.duration_s <= 0.0 {
            return Err(broken!("duration {} is not a positive number of seconds", self.duration_s));
        }
        if let Some(start_by) = self.start_by_unix_ms
            && start_by < self.to.issued_unix_ms
        {
            return Err(broken!("its start-by time {start_by} is before its issue time {}", self.to.issued_unix_ms));
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
    pub re: Answered,
    pub lab_id: u64,
    #[serde(flatten)]
    pub outcome: DispatchOutcome,
}

impl Message for DispatchReply {
    const KIND: Kind = Kind::DispatchReply;
    fn check(&self) -> Result<(), Broken> {
        self.re.check()?;
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
    pub to: Asked,
    pub lab_id: u64,
    pub by: String,
    /// A withdrawal of a dispatch the lab got no answer to: the robot
    /// cancels it if it is only queued there, remembers it as withdrawn
    /// if it never came (a late copy is then refused), and never stops
    /// it once it runs (it answers `ok: false` and the lab adopts the run).
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub withdraw: bool,
}

impl Message for Stop {
    const KIND: Kind = Kind::Stop;
    fn check(&self) -> Result<(), Broken> {
        self.to.check()?;
        name_ok("who", &self.by)
    }
}

/// Engages the robot's emergency stop (the lab's STOP).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Estop {
    pub v: u32,
    pub to: Asked,
    pub by: String,
}

/// Largest stop or emergency stop accepted: both are a few hundred bytes,
/// and a STOP's queryable checks nothing larger (junk on it costs little).
pub const MAX_STOP_BYTES: usize = 4096;

impl Message for Estop {
    const KIND: Kind = Kind::Estop;
    fn check(&self) -> Result<(), Broken> {
        self.to.check()?;
        name_ok("who", &self.by)
    }
}

/// The answer to a stop or an emergency stop.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Ack {
    pub v: u32,
    pub re: Answered,
    pub ok: bool,
    pub message: String,
}

impl Message for Ack {
    const KIND: Kind = Kind::Ack;
    fn check(&self) -> Result<(), Broken> {
        self.re.check()?;
        text_ok("message", &self.message)
    }
}

// ---------------------------------------------------------------------------
// Results and files

/// Asks what the robot kept of lab experiment `lab_id`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ResultsRequest {
    pub v: u32,
    pub to: Asked,
    pub lab_id: u64,
}

impl Message for ResultsRequest {
    const KIND: Kind = Kind::ResultsRequest;
    fn check(&self) -> Result<(), Broken> {
        self.to.check()
    }
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
    pub re: Answered,
    pub lab_id: u64,
    /// Whether the robot knows the experiment at all.
    pub found: bool,
    pub state: Option<ExperimentState>,
    pub history: Vec<StateChange>,
    pub reasons: Vec<String>,
    pub run: Option<RunResult>,
    pub files: Vec<FileRef>,
    /// Its id on the robot, when found: what the lab names in its
    /// placement, also for a run it adopted without the dispatch's answer.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub local_id: Option<u64>,
}

impl Message for Results {
    const KIND: Kind = Kind::Results;
    fn check(&self) -> Result<(), Broken> {
        self.re.check()?;
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
    pub to: Asked,
    #[serde(flatten)]
    pub source: FileSource,
    pub offset: u64,
    pub len: u64,
}

impl Message for FileRequest {
    const KIND: Kind = Kind::FileRequest;
    fn check(&self) -> Result<(), Broken> {
        self.to.check()?;
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
    pub re: Answered,
    pub offset: u64,
    /// The whole file's size.
    pub total: u64,
    /// Why there is none (no such file), when there is none.
    pub missing: Option<String>,
}

impl Message for Chunk {
    const KIND: Kind = Kind::Chunk;
    fn check(&self) -> Result<(), Broken> {
        self.re.check()?;
        self.missing.as_deref().map_or(Ok(()), |m| text_ok("why", m))
    }
}

// ---------------------------------------------------------------------------
// The robot's baseline, and its live view

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct BaselineRequest {
    pub v: u32,
    pub to: Asked,
}

impl Message for BaselineRequest {
    const KIND: Kind = Kind::BaselineRequest;
    fn check(&self) -> Result<(), Broken> {
        self.to.check()
    }
}

/// A robot's baseline as staged, with the files its built-ins name
/// (relative to its folder): what the lab server stages and preflights
/// experiments for robots of its profile against.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Baseline {
    pub v: u32,
    pub re: Answered,
    pub hash: String,
    pub set: SetManifest,
    pub files: BTreeMap<String, BlobRef>,
}

impl Message for Baseline {
    const KIND: Kind = Kind::Baseline;
    fn check(&self) -> Result<(), Broken> {
        self.re.check()?;
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
    pub to: Asked,
}

impl Message for LiveRequest {
    const KIND: Kind = Kind::LiveRequest;
    fn check(&self) -> Result<(), Broken> {
        self.to.check()
    }
}

/// Largest live status carried (the portal's live status of one robot).
pub const MAX_LIVE_BYTES: usize = 256 << 10;

/// A robot's live status (the portal's `/api/v1/status` of that robot).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Live {
    pub v: u32,
    pub re: Answered,
    pub status: serde_json::Value,
}

impl Message for Live {
    const KIND: Kind = Kind::Live;
    fn check(&self) -> Result<(), Broken> {
        self.re.check()
    }
}

/// `impl Request for T` and `impl Reply for T`, by their binding field.
macro_rules! bound_messages {
    (requests: $($request:ty),*; replies: $($reply:ty),*) => {
        $(impl Request for $request { fn asked(&self) -> &Asked { &self.to } })*
        $(impl Reply for $reply { fn answered(&self) -> &Answered { &self.re } })*
    };
}

bound_messages!(
    requests: Dispatch, Stop, Estop, ResultsRequest, FileRequest, BaselineRequest, LiveRequest;
    replies: DispatchReply, Ack, Results, Chunk, Baseline, Live
);

#[cfg(test)]
mod tests {
    use super::*;

    fn key(lab: &str, secret: &str) -> LabKey {
        LabKey::new(lab, secret.as_bytes()).unwrap_or_else(|e| panic!("{e}"))
    }

    /// A request for `robot` issued at `at`, its nonce `n` repeated.
    fn asked(robot: &str, at: u64, n: u8) -> Asked {
        Asked { robot: robot.into(), issued_unix_ms: at, nonce: hex::encode([n; NONCE_BYTES]) }
    }

    fn profile() -> Profile {
        Profile::new("a".repeat(64), vec!["lab.world".into()], vec!["ascii".into()])
    }

    fn dispatch() -> Dispatch {
        Dispatch {
            v: WIRE_VERSION,
            to: asked("r1", 1000, 0xab),
            lab_id: 7,
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
            start_by_unix_ms: Some(151_000),
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
        let status = lab.seal(
            &Ack { v: WIRE_VERSION, re: Answered::to(&asked("r1", 0, 1), "r1"), ok: true, message: String::new() },
            b"",
        );
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
        assert_eq!(
            lab.open::<Dispatch>(&lab.seal(&newer, b"")).err(),
            Some(WireError::Version { got: WIRE_VERSION + 1 })
        );
        // A host of the version before refuses ours, and ours refuses its.
        let older = Dispatch { v: 1, ..dispatch() };
        assert_eq!(lab.open::<Dispatch>(&lab.seal(&older, b"")).err(), Some(WireError::Version { got: 1 }));
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
            (
                "a start-by before its issue",
                Dispatch { start_by_unix_ms: Some(999), ..dispatch() },
                "start-by time 999",
            ),
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
        let request = |source| FileRequest { v: WIRE_VERSION, to: asked("r1", 0, 2), source, offset: 0, len: 10 };
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
    fn a_robot_admits_a_request_for_it_fresh_and_new_only_once() {
        let now = 1_000_000;
        let mut replays = Replays::new("r1");
        // (case, request, receiver's clock, expected): in order, on one
        // robot's memory.
        let cases: Vec<(&str, Asked, u64, Result<(), WireError>)> = vec![
            ("a fresh request for r1", asked("r1", now, 1), now, Ok(())),
            ("the same again (a replay)", asked("r1", now, 1), now + 10, Err(WireError::Replayed)),
            (
                "the same for r2 (replayed to another robot)",
                asked("r2", now, 1),
                now,
                Err(WireError::OtherTarget { named: "r2".into() }),
            ),
            ("a new nonce", asked("r1", now, 2), now, Ok(())),
            (
                "issued too long ago",
                asked("r1", now - MAX_CLOCK_SKEW_MS - 1, 3),
                now,
                Err(WireError::Stale { skew_ms: MAX_CLOCK_SKEW_MS + 1 }),
            ),
            (
                "issued too far ahead",
                asked("r1", now + MAX_CLOCK_SKEW_MS + 5, 4),
                now,
                Err(WireError::Stale { skew_ms: MAX_CLOCK_SKEW_MS + 5 }),
            ),
            ("at the edge of the window", asked("r1", now - MAX_CLOCK_SKEW_MS, 5), now, Ok(())),
            (
                "the first, replayed when it is stale",
                asked("r1", now, 1),
                now + MAX_CLOCK_SKEW_MS + 1,
                Err(WireError::Stale { skew_ms: MAX_CLOCK_SKEW_MS + 1 }),
            ),
            (
                "the server's target is not a robot's",
                asked(SERVER_TARGET, now, 6),
                now,
                Err(WireError::OtherTarget { named: SERVER_TARGET.into() }),
            ),
        ];
        for (case, request, at, expected) in cases {
            assert_eq!(replays.admit(&request, at), expected, "{case}");
        }
        // A request issued before this process started (a capture replayed
        // across a restart) is not taken; one after it is.
        let mut restarted = Replays::new("r1").since(now);
        assert_eq!(restarted.admit(&asked("r1", now - 5, 8), now), Err(WireError::Replayed));
        assert_eq!(restarted.admit(&asked("r1", now + 1, 9), now + 1), Ok(()));
        // Requests that can no longer pass the freshness check are forgotten.
        assert_eq!(replays.admit(&asked("r1", now + 3 * MAX_CLOCK_SKEW_MS, 7), now + 3 * MAX_CLOCK_SKEW_MS), Ok(()));
        assert_eq!(replays.len(), 1);
    }

    #[test]
    fn the_nonce_memory_is_bounded_and_forgets_only_what_it_then_refuses() {
        let now = 1_000_000;
        let mut replays = Replays::with_capacity("r1", 3);
        for n in 0..3u8 {
            assert_eq!(replays.admit(&asked("r1", now + u64::from(n), n), now), Ok(()));
        }
        // Full: the oldest (issued at `now`) is forgotten, and nothing
        // issued at or before it is taken any more.
        assert_eq!(replays.admit(&asked("r1", now + 10, 10), now), Ok(()));
        assert_eq!(replays.len(), 3);
        assert_eq!(replays.admit(&asked("r1", now, 0), now), Err(WireError::Replayed), "the forgotten one, replayed");
        assert_eq!(replays.admit(&asked("r1", now, 20), now), Err(WireError::Replayed), "as old as the floor");
        assert_eq!(replays.admit(&asked("r1", now + 11, 21), now), Ok(()));
        assert_eq!(replays.len(), 3);
    }

    #[test]
    fn a_reply_is_taken_only_from_the_robot_asked_for_that_request() {
        let request = asked("r1", 1000, 1);
        // (case, reply's binding, expected)
        let cases: Vec<(&str, Answered, bool)> = vec![
            ("r1 answers this request", Answered::to(&request, "r1"), true),
            ("r1's answer to another request", Answered::to(&asked("r1", 1000, 2), "r1"), false),
            ("r2 answers with this request's nonce", Answered::to(&request, "r2"), false),
            ("another request of r2's", Answered::to(&asked("r2", 1000, 3), "r2"), false),
        ];
        for (case, reply, ok) in cases {
            assert_eq!(bound(&request, &reply).is_ok(), ok, "{case}");
        }
        // The binding is under the reply's MAC: changing it breaks the MAC.
        let lab = key("lab-a", "0123456789abcdef-secret");
        let ack = Ack { v: WIRE_VERSION, re: Answered::to(&request, "r1"), ok: true, message: "engaged".into() };
        let sealed = lab.seal(&ack, b"");
        let mut changed = sealed.clone();
        let at = changed.windows(4).position(|w| w == b"\"r1\"").unwrap_or_else(|| panic!("no robot in the header"));
        changed[at + 2] = b'2';
        assert!(lab.open::<Ack>(&sealed).is_ok());
        assert!(matches!(lab.open::<Ack>(&changed), Err(WireError::BadSignature { .. })));
        // A request or reply without a well-made binding is refused.
        let bad = Ack { re: Answered { robot: "r1".into(), nonce: "xyz".into() }, ..ack };
        assert!(matches!(lab.open::<Ack>(&lab.seal(&bad, b"")), Err(WireError::Invalid(_))));
    }

    #[test]
    fn only_signed_refusals_are_answered_and_every_class_is_counted() {
        // (error, signed with the lab's key, class)
        let cases = [
            (WireError::BadSignature { lab: "l".into() }, false, Refusal::NotSigned),
            (WireError::NotAnEnvelope, false, Refusal::Malformed),
            (WireError::TooLarge { size: 1 }, false, Refusal::Malformed),
            (WireError::Header("x".into()), true, Refusal::Malformed),
            (WireError::Version { got: 1 }, true, Refusal::Version),
            (WireError::Stale { skew_ms: 1 }, true, Refusal::Stale),
            (WireError::Replayed, true, Refusal::Replayed),
            (WireError::OtherTarget { named: "r2".into() }, true, Refusal::OtherTarget),
        ];
        for (error, signed, class) in cases {
            assert_eq!((error.signed(), error.class()), (signed, class), "{error}");
        }
    }

    #[test]
    fn refusals_are_audited_at_most_once_an_interval_with_their_counts() {
        let mut tally = RefusalTally::default();
        assert_eq!(tally.due(0), None, "nothing refused, nothing to say");
        tally.note(Refusal::NotSigned);
        let first = tally.due(1_000).unwrap_or_default();
        assert!(first.starts_with("1 lab messages refused") && first.contains("not-signed 1"), "{first}");
        for _ in 0..1000 {
            tally.note(Refusal::NotSigned);
        }
        tally.note(Refusal::Replayed);
        assert_eq!(tally.due(1_000 + REFUSAL_AUDIT_INTERVAL_MS - 1), None, "within the interval");
        let next = tally.due(1_000 + REFUSAL_AUDIT_INTERVAL_MS).unwrap_or_default();
        assert!(next.contains("1001 lab messages") && next.contains("not-signed 1000, replayed 1"), "{next}");
        assert_eq!(tally.due(1_000 + 5 * REFUSAL_AUDIT_INTERVAL_MS), None, "nothing new");
        assert_eq!(tally.sum(), 1002);
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
