//! The Zenoh side of the lab's messages, shared by the lab server and its
//! robots: asking a queryable and reading its signed answer ([`ask`]),
//! answering queries on a thread of their own ([`serve`]), and moving a
//! file in signed chunks ([`fetch_file`], [`fetch_blob`], [`chunk_of`]),
//! checked by its sha256 before it is kept.
//!
//! Invariants: a chunk is at most [`wire::MAX_CHUNK_BYTES`]; a file is
//! written to `NAME.part` and renamed only once its sha256 matches, so a
//! cut transfer leaves nothing that looks whole; a queryable's backlog is
//! bounded ([`QUERY_BACKLOG`], the oldest query dropped), so a flood of
//! queries holds no memory.

use std::io::{Read, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use sha2::{Digest, Sha256};
use thiserror::Error;
use zenoh::Wait;

use super::wire::{self, BlobRef, Chunk, FileRequest, FileSource, LabKey, Message, WIRE_VERSION, WireError};
use crate::bridge::session::Shared;
use crate::contract::clip;

/// How long an answer may take (a dispatch waits longer: the robot
/// fetches the set and starts it).
pub const QUERY_TIMEOUT: Duration = Duration::from_secs(10);

/// Queries waiting per queryable; beyond it the oldest is dropped (its
/// asker times out): a flood of queries cannot grow memory.
pub const QUERY_BACKLOG: usize = 16;

/// How often a serving thread looks whether it should stop.
const POLL: Duration = Duration::from_millis(200);

/// Why a request over the lab's link failed.
#[derive(Debug, Error)]
pub enum TransferError {
    #[error("zenoh: {0}")]
    Zenoh(String),
    #[error("no answer on {key} within {} s", .timeout.as_secs_f64())]
    NoAnswer { key: String, timeout: Duration },
    #[error("the answer on {key} was refused: {source}")]
    Refused {
        key: String,
        #[source]
        source: WireError,
    },
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

fn zenoh_error(e: impl std::fmt::Display) -> TransferError {
    TransferError::Zenoh(clip(&e.to_string()))
}

/// Asks `key_expr` with `request` (signed with `key`) and reads the first
/// answer of kind `A`, with its attachment.
pub fn ask<Q: Message, A: Message>(
    shared: &Shared,
    key: &LabKey,
    key_expr: &str,
    request: &Q,
    timeout: Duration,
) -> Result<(A, Vec<u8>), TransferError> {
    let replies =
        shared.session.get(key_expr).payload(key.seal(request, &[])).timeout(timeout).wait().map_err(zenoh_error)?;
    while let Ok(reply) = replies.recv() {
        let Ok(sample) = reply.result() else { continue };
        let bytes = sample.payload().to_bytes();
        return match key.open::<A>(&bytes) {
            Ok((answer, attachment)) => Ok((answer, attachment.to_vec())),
            Err(source) => Err(TransferError::Refused { key: key_expr.to_string(), source }),
        };
    }
    Err(TransferError::NoAnswer { key: key_expr.to_string(), timeout })
}

/// Answers every query on `key_expr` with `answer(payload)`, on a thread
/// named `name`, until `stopping`.
pub fn serve(
    shared: Arc<Shared>,
    key_expr: String,
    name: &str,
    stopping: Arc<AtomicBool>,
    answer: impl Fn(&[u8]) -> Vec<u8> + Send + 'static,
) -> Result<std::thread::JoinHandle<()>, TransferError> {
    let queryable = shared
        .session
        .declare_queryable(key_expr.clone())
        .with(zenoh::handlers::RingChannel::new(QUERY_BACKLOG))
        .wait()
        .map_err(zenoh_error)?;
    std::thread::Builder::new()
        .name(name.into())
        .spawn(move || {
            while !stopping.load(Ordering::Acquire) {
                let query = match queryable.recv_timeout(POLL) {
                    Ok(Some(query)) => query,
                    Ok(None) => continue,
                    Err(_) => return,
                };
                let payload = query.payload().map(|p| p.to_bytes().into_owned()).unwrap_or_default();
                let reply = answer(&payload);
                if let Err(e) = query.reply(query.key_expr().clone(), reply).wait() {
                    tracing::debug!("lab link: a reply on {key_expr} was not sent: {e}");
                }
            }
            drop(shared);
        })
        .map_err(|e| TransferError::Zenoh(format!("cannot start the thread {name}: {e}")))
}

/// The chunk of the file at `path` that `request` asks for, sealed, or
/// what is missing.
pub fn chunk_of(key: &LabKey, path: Option<&Path>, request: &FileRequest) -> Vec<u8> {
    let missing =
        |why: String| key.seal(&Chunk { v: WIRE_VERSION, offset: request.offset, total: 0, missing: Some(why) }, &[]);
    let Some(path) = path else { return missing("no such file".into()) };
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
            key.seal(&Chunk { v: WIRE_VERSION, offset: request.offset, total, missing: None }, &bytes)
        }
        Err(e) => missing(format!("cannot read it: {e}")),
    }
}

/// The chunk of `bytes` (a file held in memory) that `request` asks for,
/// sealed.
pub fn chunk_of_bytes(key: &LabKey, bytes: &[u8], request: &FileRequest) -> Vec<u8> {
    let total = bytes.len() as u64;
    let start = request.offset.min(total) as usize;
    let end = (request.offset.saturating_add(request.len.min(wire::MAX_CHUNK_BYTES as u64))).min(total) as usize;
    key.seal(&Chunk { v: WIRE_VERSION, offset: request.offset, total, missing: None }, &bytes[start..end])
}

/// Fetches `source` from `key_expr` chunk by chunk into `write`; returns
/// the sha256 of what was written. `expected_bytes` bounds it.
fn fetch_into(
    shared: &Shared,
    key: &LabKey,
    key_expr: &str,
    source: &FileSource,
    expected_bytes: u64,
    what: &str,
    write: &mut dyn FnMut(&[u8]) -> std::io::Result<()>,
) -> Result<String, TransferError> {
    let mut hash = Sha256::new();
    let mut offset = 0u64;
    loop {
        let request =
            FileRequest { v: WIRE_VERSION, source: source.clone(), offset, len: wire::MAX_CHUNK_BYTES as u64 };
        let (chunk, bytes): (Chunk, Vec<u8>) = ask(shared, key, key_expr, &request, QUERY_TIMEOUT)?;
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

/// Fetches `source` (`expected`: its sha256 and size) into the file
/// `dest`, through `dest.part`, renamed only when the sha256 matches.
pub fn fetch_file(
    shared: &Shared,
    key: &LabKey,
    key_expr: &str,
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
    let got = fetch_into(shared, key, key_expr, source, expected.bytes, &what, &mut |bytes| file.write_all(bytes));
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

/// Fetches blob `expected` from `key_expr` into memory, checked by its
/// sha256 (at most [`wire::MAX_BLOB_BYTES`]).
pub fn fetch_blob(
    shared: &Shared,
    key: &LabKey,
    key_expr: &str,
    source: &FileSource,
    expected: &BlobRef,
) -> Result<Vec<u8>, TransferError> {
    let what = format!("blob {}", expected.sha256);
    if expected.bytes > wire::MAX_BLOB_BYTES {
        return Err(TransferError::TooLarge { what, bytes: expected.bytes, limit: wire::MAX_BLOB_BYTES });
    }
    let mut bytes = Vec::with_capacity(expected.bytes as usize);
    let got = fetch_into(shared, key, key_expr, source, expected.bytes, &what, &mut |chunk| {
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
