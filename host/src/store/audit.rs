//! The audit log (`audit.log`): one JSON object per request, appended and
//! fsynced. A torn last line (a crash mid-write) is skipped when read.

use std::io::Write;
use std::path::Path;

use serde::{Deserialize, Serialize};

use super::StoreError;

/// Audit entries returned by one read (the file itself keeps everything).
pub const MAX_AUDIT_READ: usize = 1000;
/// Most bytes of an entry's detail: enough to name what was refused
/// and why (an envelope setting and its values), while one request cannot
/// grow the log without bound.
pub const MAX_AUDIT_DETAIL: usize = 300;

/// At most [`MAX_AUDIT_DETAIL`] bytes of `detail`, without control
/// characters.
pub fn clip_detail(detail: &str) -> String {
    crate::contract::clip_to(detail, MAX_AUDIT_DETAIL)
}

/// One line of the audit log.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
pub struct AuditEntry {
    /// Seconds since the Unix epoch.
    pub time: u64,
    pub user: String,
    /// "upload-component", "upload-config", "activate", "rollback", "boot",
    /// "user-add", ...
    pub action: String,
    pub target: String,
    /// "ok", "refused" or "failed".
    pub result: String,
    pub detail: String,
}

/// How an audited request ended, with the detail to record.
#[derive(Clone, Copy, Debug)]
pub enum Outcome<'a> {
    Ok(&'a str),
    /// The request was refused (permission, bad input): nothing changed.
    Refused(&'a str),
    /// The host failed to carry it out.
    Failed(&'a str),
}

impl Outcome<'_> {
    pub fn result(&self) -> &'static str {
        match self {
            Outcome::Ok(_) => "ok",
            Outcome::Refused(_) => "refused",
            Outcome::Failed(_) => "failed",
        }
    }

    pub fn detail(&self) -> &str {
        match self {
            Outcome::Ok(d) | Outcome::Refused(d) | Outcome::Failed(d) => d,
        }
    }
}

/// Appends `entry` to the log at `path` in one write, and fsyncs it.
pub(super) fn append(path: &Path, entry: &AuditEntry) -> Result<(), StoreError> {
    let io = super::io(path);
    let mut line =
        serde_json::to_vec(entry).map_err(|e| StoreError::Io { path: path.into(), reason: e.to_string() })?;
    line.push(b'\n');
    let mut file = std::fs::OpenOptions::new().create(true).append(true).open(path).map_err(&io)?;
    file.write_all(&line).map_err(&io)?;
    file.sync_data().map_err(&io)
}

/// The newest `limit` entries of the log at `path` (at most
/// [`MAX_AUDIT_READ`]), oldest first.
pub(super) fn read(path: &Path, limit: usize) -> Result<Vec<AuditEntry>, StoreError> {
    let text = match std::fs::read_to_string(path) {
        Ok(text) => text,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Vec::new()),
        Err(e) => return Err(StoreError::Io { path: path.to_path_buf(), reason: e.to_string() }),
    };
    let entries: Vec<AuditEntry> = text.lines().filter_map(|l| serde_json::from_str(l).ok()).collect();
    let skip = entries.len().saturating_sub(limit.min(MAX_AUDIT_READ));
    Ok(entries.into_iter().skip(skip).collect())
}
