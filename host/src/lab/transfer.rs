//! The Zenoh side of the lab's messages, shared by the lab server and its
//! robots: asking a queryable and reading its signed answer ([`ask`]),
//! answering queries on a thread of their own ([`serve`]), and moving a
//! file in signed chunks ([`fetch_file`], [`fetch_blob`], [`chunk_of`]),
//! checked by its sha256 before it is kept.
//!
//! Invariants: a chunk is at most [`wire::MAX_CHUNK_BYTES`]; a file is
//! written to `NAME.part` and renamed only once its sha256 matches, so a
//! cut transfer leaves nothing that looks whole. An asker asks every
//! queryable on a key and takes the first reply that verifies and is bound
//! to its request; the rest are skipped and counted, never taken (a rogue
//! complete queryable answers nothing). A queryable admits a request
//! ([`Gate`]: size, MAC, bounds, its target, freshness, its nonce) on
//! Zenoh's own thread before it takes a place in its backlog
//! ([`QUERY_BACKLOG`]), so junk never fills it; what does not verify gets
//! no answer, and a signed request refused (stale, replayed, for another
//! robot) an unsigned one: nobody collects signed replies by asking.

use std::io::{Read, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::Duration;

use sha2::{Digest, Sha256};
use thiserror::Error;
use zenoh::Wait;

use super::wire::{
    self, Answered, Asked, BlobRef, Chunk, FileRequest, FileSource, LabKey, Refusal, RefusalTally, Replays, Reply,
    Request, WIRE_VERSION, WireError,
};
use crate::bridge::session::Shared;
use crate::contract::clip;
use crate::runtime::locks::unix_now_ms;

/// How long an answer may take (a dispatch waits longer: the robot
/// fetches the set and starts it).
pub const QUERY_TIMEOUT: Duration = Duration::from_secs(10);

/// Admitted queries waiting per queryable; beyond it the newest is
/// refused (`busy`): the lab's own flood cannot grow memory, and junk is
/// never admitted.
pub const QUERY_BACKLOG: usize = 16;

/// Most reasons a failed ask keeps of the replies it skipped: a rogue
/// answering many times must not grow the error.
pub const MAX_SKIPPED_REASONS: usize = 4;

/// How often a serving thread looks whether it should stop.
const POLL: Duration = Duration::from_millis(200);

/// Why a request over the lab's link failed.
#[derive(Debug, Error)]
pub enum TransferError {
    #[error("zenoh: {0}")]
    Zenoh(String),
    #[error("no answer on {key} within {} s{}", .timeout.as_secs_f64(), skipped_text(.skipped))]
    NoAnswer { key: String, timeout: Duration, skipped: Vec<String> },
    #[error("{0}")]
    Missing(String),
    #[error("{what}: the bytes' sha256 is {got}, not {expected}")]
    Digest { what: String, expected: String, got: String },
    #[error("{what} is {bytes} bytes; at most {limit} are taken")]
    TooLarge { what: String, bytes: u64, limit: u64 },
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
}

fn skipped_text(skipped: &[String]) -> String {
    if skipped.is_empty() { String::new() } else { format!(" (replies skipped: {})", skipped.join("; ")) }
}

fn zenoh_error(e: impl std::fmt::Display) -> TransferError {
    TransferError::Zenoh(clip(&e.to_string()))
}

fn lock<T>(mutex: &Mutex<T>) -> MutexGuard<'_, T> {
    mutex.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
}

/// Who asks: the session, the lab's key, and where skipped replies are
/// counted.
#[derive(Clone, Copy)]
pub struct Asker<'a> {
    pub shared: &'a Shared,
    pub key: &'a LabKey,
    /// Replies skipped: unsigned, refused, or bound to another request or
    /// robot.
    pub skipped: &'a AtomicU64,
}

impl Asker<'_> {
    /// Asks every queryable on `key_expr` with `request` (signed) and
    /// takes the first reply of kind `A` that verifies and is bound to
    /// this request and the robot it names ([`wire::bound`]), with its
    /// attachment. Every other reply is skipped and counted.
    pub fn ask<Q: Request, A: Reply>(
        &self,
        key_expr: &str,
        request: &Q,
        timeout: Duration,
    ) -> Result<(A, Vec<u8>), TransferError> {
        let replies = self
            .shared
            .session
            .get(key_expr)
            .payload(self.key.seal(request, &[]))
            .target(zenoh::query::QueryTarget::All)
            .consolidation(zenoh::query::ConsolidationMode::None)
            .timeout(timeout)
            .wait()
            .map_err(zenoh_error)?;
        let mut skipped = Vec::new();
        while let Ok(reply) = replies.recv() {
            let why = match reply.result() {
                Ok(sample) => {
                    let bytes = sample.payload().to_bytes();
                    let taken = self.key.open::<A>(&bytes).and_then(|(answer, attachment)| {
                        wire::bound(request.asked(), answer.answered()).map(|()| (answer, attachment))
                    });
                    match taken {
                        Ok((answer, attachment)) => return Ok((answer, attachment.to_vec())),
                        Err(e) => e.to_string(),
                    }
                }
                Err(refusal) => format!("unsigned: {}", String::from_utf8_lossy(&refusal.payload().to_bytes())),
            };
            self.skipped.fetch_add(1, Ordering::Relaxed);
            if skipped.len() < MAX_SKIPPED_REASONS {
                skipped.push(clip(&why));
            }
        }
        Err(TransferError::NoAnswer { key: key_expr.to_string(), timeout, skipped })
    }
}

/// What a queryable admits: requests of its kind signed with `key`, at
/// most `max_bytes`, naming `me`, fresh, and not seen before.
pub struct Gate {
    pub key: LabKey,
    /// The robot's name ([`wire::SERVER_TARGET`] on the lab server).
    pub me: String,
    pub max_bytes: usize,
    /// Where refusals are counted (and, on a robot, audited from).
    pub refusals: Arc<Mutex<RefusalTally>>,
}

impl Gate {
    /// Whether `payload` is a request this queryable obeys (explicit time).
    fn admit<Q: Request>(&self, replays: &Mutex<Replays>, payload: &[u8], now_ms: u64) -> Result<Q, WireError> {
        if payload.len() > self.max_bytes {
            return Err(WireError::TooLarge { size: payload.len() });
        }
        let (request, _) = self.key.open::<Q>(payload)?;
        lock(replays).admit(request.asked(), now_ms)?;
        Ok(request)
    }
}

/// Answers every query on `key_expr` the `gate` admits with
/// `answer(request, binding)`, on a thread named `name`, until
/// `stopping`. Admission runs on Zenoh's thread, before the backlog: junk
/// gets no answer and takes no place; a signed request refused gets an
/// unsigned refusal.
pub fn serve<Q: Request + Send + 'static>(
    shared: Arc<Shared>,
    key_expr: String,
    name: &str,
    stopping: Arc<AtomicBool>,
    gate: Gate,
    answer: impl Fn(Q, Answered) -> Vec<u8> + Send + 'static,
) -> Result<std::thread::JoinHandle<()>, TransferError> {
    let (sender, receiver) = std::sync::mpsc::sync_channel::<(zenoh::query::Query, Q)>(QUERY_BACKLOG);
    let me = gate.me.clone();
    let replays = Mutex::new(Replays::new(&gate.me).since(unix_now_ms()));
    let queryable = shared
        .session
        .declare_queryable(key_expr.clone())
        .callback(move |query: zenoh::query::Query| {
            let size = query.payload().map_or(0, zenoh::bytes::ZBytes::len);
            let admitted = if size > gate.max_bytes {
                Err(WireError::TooLarge { size })
            } else {
                let payload = query.payload().map(|p| p.to_bytes()).unwrap_or_default();
                gate.admit::<Q>(&replays, &payload, unix_now_ms())
            };
            let refused = match admitted {
                Ok(request) => match sender.try_send((query, request)) {
                    Ok(()) => return,
                    Err(std::sync::mpsc::TrySendError::Full((query, _))) => (query, Refusal::Busy, None),
                    Err(std::sync::mpsc::TrySendError::Disconnected(_)) => return,
                },
                Err(e) => {
                    let text = e.signed().then(|| wire::refusal_text(&e));
                    (query, e.class(), text)
                }
            };
            let (query, class, text) = refused;
            lock(&gate.refusals).note(class);
            let text = match class {
                Refusal::Busy => Some("refused (busy): the queryable's backlog is full".to_string()),
                _ => text,
            };
            // Unsigned, fixed: it answers nothing. Junk gets nothing.
            if let Some(text) = text {
                let _ = query.reply_err(text).wait();
            }
        })
        .wait()
        .map_err(zenoh_error)?;
    std::thread::Builder::new()
        .name(name.into())
        .spawn(move || {
            let _queryable = queryable;
            while !stopping.load(Ordering::Acquire) {
                let (query, request) = match receiver.recv_timeout(POLL) {
                    Ok(admitted) => admitted,
                    Err(std::sync::mpsc::RecvTimeoutError::Timeout) => continue,
                    Err(std::sync::mpsc::RecvTimeoutError::Disconnected) => return,
                };
                let binding = Answered::to(request.asked(), &me);
                let reply = answer(request, binding);
                if let Err(e) = query.reply(query.key_expr().clone(), reply).wait() {
                    tracing::debug!("lab link: a reply on {key_expr} was not sent: {e}");
                }
            }
            drop(shared);
        })
        .map_err(|e| TransferError::Zenoh(format!("cannot start the thread {name}: {e}")))
}

/// The chunk of the file at `path` that `request` asks for, sealed with
/// its binding `re`, or what is missing.
pub fn chunk_of(key: &LabKey, re: Answered, path: Option<&Path>, request: &FileRequest) -> Vec<u8> {
    let missing = |re: Answered, why: String| {
        key.seal(&Chunk { v: WIRE_VERSION, re, offset: request.offset, total: 0, missing: Some(why) }, &[])
    };
    let Some(path) = path else { return missing(re, "no such file".into()) };
    let read = (|| {
        let mut file = std::fs::File::open(path)?;
        let total = file.metadata()?.len();
        let len = request.len.min(wire::MAX_CHUNK_BYTES as u64).min(total.saturating_sub(request.offset));
        file.seek(SeekFrom::Start(request.offset.min(total)))?;
        let mut bytes = vec![0; len as usize];
        file.read_exact(&mut bytes)?;
        Ok::<_, std::io::Error>((total, bytes))
    })();
    match read {
        Ok((total, bytes)) => {
            key.seal(&Chunk { v: WIRE_VERSION, re, offset: request.offset, total, missing: None }, &bytes)
        }
        Err(e) => missing(re, format!("cannot read it: {e}")),
    }
}

/// The chunk of `bytes` (a file held in memory) that `request` asks for,
/// sealed.
pub fn chunk_of_bytes(key: &LabKey, re: Answered, bytes: &[u8], request: &FileRequest) -> Vec<u8> {
    let total = bytes.len() as u64;
    let start = request.offset.min(total) as usize;
    let end = (request.offset.saturating_add(request.len.min(wire::MAX_CHUNK_BYTES as u64))).min(total) as usize;
    key.seal(&Chunk { v: WIRE_VERSION, re, offset: request.offset, total, missing: None }, &bytes[start..end])
}

/// Fetches `source` from `key_expr` (of robot `target`) chunk by chunk
/// into `write`; returns the sha256 of what was written. `expected_bytes`
/// bounds it.
fn fetch_into(
    asker: Asker<'_>,
    (key_expr, target): (&str, &str),
    source: &FileSource,
    expected_bytes: u64,
    what: &str,
    write: &mut dyn FnMut(&[u8]) -> std::io::Result<()>,
) -> Result<String, TransferError> {
    let mut hash = Sha256::new();
    let mut offset = 0u64;
    loop {
        let request = FileRequest {
            v: WIRE_VERSION,
            to: Asked::new(target, unix_now_ms()),
            source: source.clone(),
            offset,
            len: wire::MAX_CHUNK_BYTES as u64,
        };
        let (chunk, bytes): (Chunk, Vec<u8>) = asker.ask(key_expr, &request, QUERY_TIMEOUT)?;
        if let Some(why) = chunk.missing {
            return Err(TransferError::Missing(format!("{what}: {why}")));
        }
        if chunk.total != expected_bytes || chunk.offset != offset {
            return Err(TransferError::Missing(format!(
                "{what}: it is {} bytes there, {expected_bytes} were announced",
                chunk.total
            )));
        }
        hash.update(&bytes);
        write(&bytes).map_err(|e| TransferError::Io { path: PathBuf::from(what), source: e })?;
        offset += bytes.len() as u64;
        if offset >= expected_bytes || bytes.is_empty() {
            break;
        }
    }
    if offset != expected_bytes {
        return Err(TransferError::Missing(format!("{what}: only {offset} of {expected_bytes} bytes came")));
    }
    Ok(hex::encode(hash.finalize()))
}

/// Fetches `source` (`expected`: its sha256 and size) from `key_expr` of
/// robot `target` into the file `dest`, through `dest.part`, renamed only
/// when the sha256 matches.
pub fn fetch_file(
    asker: Asker<'_>,
    at: (&str, &str),
    source: &FileSource,
    expected: &BlobRef,
    dest: &Path,
) -> Result<(), TransferError> {
    let io = |path: &Path| {
        let path = path.to_path_buf();
        move |source| TransferError::Io { path: path.clone(), source }
    };
    if let Some(parent) = dest.parent() {
        std::fs::create_dir_all(parent).map_err(io(parent))?;
    }
    let part = dest.with_extension(format!(
        "{}part",
        dest.extension().map(|e| format!("{}.", e.to_string_lossy())).unwrap_or_default()
    ));
    let mut file = std::fs::File::create(&part).map_err(io(&part))?;
    let what = dest.display().to_string();
    let got = fetch_into(asker, at, source, expected.bytes, &what, &mut |bytes| file.write_all(bytes));
    let got = match got {
        Ok(got) => got,
        Err(e) => {
            let _ = std::fs::remove_file(&part);
            return Err(e);
        }
    };
    if got != expected.sha256 {
        let _ = std::fs::remove_file(&part);
        return Err(TransferError::Digest { what, expected: expected.sha256.clone(), got });
    }
    file.sync_all().map_err(io(&part))?;
    drop(file);
    std::fs::rename(&part, dest).map_err(io(dest))
}

/// Fetches blob `expected` from `key_expr` of `target` into memory,
/// checked by its sha256 (at most [`wire::MAX_BLOB_BYTES`]).
pub fn fetch_blob(
    asker: Asker<'_>,
    at: (&str, &str),
    source: &FileSource,
    expected: &BlobRef,
) -> Result<Vec<u8>, TransferError> {
    let what = format!("blob {}", expected.sha256);
    if expected.bytes > wire::MAX_BLOB_BYTES {
        return Err(TransferError::TooLarge { what, bytes: expected.bytes, limit: wire::MAX_BLOB_BYTES });
    }
    let mut bytes = Vec::with_capacity(expected.bytes as usize);
    let got = fetch_into(asker, at, source, expected.bytes, &what, &mut |chunk| {
        bytes.extend_from_slice(chunk);
        Ok(())
    })?;
    if got != expected.sha256 {
        return Err(TransferError::Digest { what, expected: expected.sha256.clone(), got });
    }
    Ok(bytes)
}

/// The sha256 and size of the file at `path`, read in pieces.
pub fn digest_file(path: &Path) -> std::io::Result<BlobRef> {
    let mut file = std::fs::File::open(path)?;
    let mut hash = Sha256::new();
    let mut buffer = vec![0u8; 256 << 10];
    let mut bytes = 0u64;
    loop {
        let n = file.read(&mut buffer)?;
        if n == 0 {
            break;
        }
        hash.update(&buffer[..n]);
        bytes += n as u64;
    }
    Ok(BlobRef { sha256: hex::encode(hash.finalize()), bytes })
}
