//! The store on disk: uploaded components (content-addressed), robot files,
//! deployable sets (a robot file plus the exact components its sources
//! name), which set is active and which were before it, and the audit log.
//!
//! Layout under the store's root:
//! ```text
//! users.json                  portal users (crate::users)
//! blobs/<sha256>              component and robot-file bytes, by content
//! components.json             upload name -> blob, world, description
//! sets/<id>.json              one set: robot file blob + source -> blob map
//! state.json                  active set, previously active sets, next id
//! audit.log                   one JSON object per line, appended and fsynced
//! ```
//!
//! Invariants: every file but `audit.log` is replaced atomically (temporary
//! file, fsync, rename, fsync of the folder), and what a record names is
//! written before the record: a kill -9 at any moment leaves the old state
//! or the new one, never a record naming a missing blob. A torn last line of
//! `audit.log` is skipped when read. Nothing here runs guest code or parses
//! a component: callers validate before they store.

use std::collections::BTreeMap;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::{SystemTime, UNIX_EPOCH};

use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};
use thiserror::Error;

use crate::fsutil::write_atomically;

/// Most sets kept; the oldest ones that are neither active nor in the
/// rollback history are forgotten beyond this (bounds the store's growth).
pub const MAX_SETS: usize = 200;
/// Previously active sets remembered for rollback.
pub const MAX_HISTORY: usize = 20;
/// Most named components in the store.
pub const MAX_STORED_COMPONENTS: usize = 500;
/// Audit entries returned by one read (the file itself keeps everything).
pub const MAX_AUDIT_READ: usize = 1000;
/// Largest index file (components.json, state.json, a set) read.
pub const MAX_INDEX_BYTES: u64 = 16 << 20;

#[derive(Debug, Error)]
pub enum StoreError {
    #[error("store {path}: {reason}")]
    Io { path: PathBuf, reason: String },
    #[error("store {path}: damaged: {reason}")]
    Damaged { path: PathBuf, reason: String },
    #[error("no set {0} in the store")]
    NoSet(u64),
    #[error("{0}")]
    Refused(String),
}

fn io(path: &Path) -> impl Fn(std::io::Error) -> StoreError + '_ {
    move |e| StoreError::Io { path: path.to_path_buf(), reason: e.to_string() }
}

/// A component as uploaded.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ComponentRecord {
    pub name: String,
    pub sha256: String,
    pub size: u64,
    /// "component" or "translator".
    pub world: String,
    /// The platform it was uploaded for.
    pub platform: String,
    pub uploaded_by: String,
    pub uploaded_at: u64,
    /// What `describe` returned (contract::description_json).
    pub description: serde_json::Value,
}

/// A robot file with the components it runs, ready to activate.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SetRecord {
    pub id: u64,
    pub created_by: String,
    pub created_at: u64,
    /// The platform the upload was for; `None` for a set imported at boot.
    pub platform: Option<String>,
    /// The robot file's name as uploaded (diagnostics use it).
    pub config_name: String,
    pub config_sha256: String,
    /// Folder that relative file parameters (world files) resolve against.
    pub base_dir: PathBuf,
    /// Each WASM source as the robot file writes it -> blob.
    pub sources: BTreeMap<String, String>,
    /// Platforms whose components or connections differ from the set that
    /// was active when this one was made.
    #[serde(default)]
    pub changes: Vec<String>,
    /// Components (with their ports) and connections, for the wiring view:
    /// worked out once, when the set is validated.
    #[serde(default)]
    pub graph: serde_json::Value,
}

#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct StoreState {
    pub active: Option<u64>,
    /// Sets active before, oldest first.
    pub history: Vec<u64>,
    pub next_set: u64,
    /// sha256 of the robot file last imported at boot.
    pub boot_config_sha256: Option<String>,
}

/// One line of the audit log.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct AuditEntry {
    /// Seconds since the Unix epoch.
    pub time: u64,
    pub user: String,
    /// "upload-component", "upload-config", "activate", "rollback", "login", "boot".
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

/// Seconds since the Unix epoch.
pub fn unix_now() -> u64 {
    SystemTime::now().duration_since(UNIX_EPOCH).map(|d| d.as_secs()).unwrap_or(0)
}

pub fn sha256_hex(bytes: &[u8]) -> String {
    hex::encode(Sha256::digest(bytes))
}

/// The store rooted at a folder. Methods take `&self`; callers serialise
/// changes (the portal holds one lock around each change).
#[derive(Debug)]
pub struct Store {
    root: PathBuf,
}

impl Store {
    /// Opens (creating when missing) the store at `root`.
    pub fn open(root: &Path) -> Result<Store, StoreError> {
        for dir in [root.to_path_buf(), root.join("blobs"), root.join("sets")] {
            std::fs::create_dir_all(&dir).map_err(io(&dir))?;
        }
        let store = Store { root: root.to_path_buf() };
        store.state()?;
        store.components()?;
        Ok(store)
    }

    pub fn root(&self) -> &Path {
        &self.root
    }

    pub fn users_path(&self) -> PathBuf {
        self.root.join("users.json")
    }

    pub fn blob_path(&self, sha256: &str) -> PathBuf {
        self.root.join("blobs").join(sha256)
    }

    /// Stores `bytes` by content; returns its sha256. Idempotent.
    pub fn put_blob(&self, bytes: &[u8]) -> Result<String, StoreError> {
        let sha = sha256_hex(bytes);
        let path = self.blob_path(&sha);
        let complete = std::fs::metadata(&path).is_ok_and(|m| m.len() == bytes.len() as u64);
        if !complete {
            write_atomically(&path, bytes).map_err(io(&path))?;
        }
        Ok(sha)
    }

    /// Reads a blob back, checking its content still matches its name.
    pub fn blob(&self, sha256: &str) -> Result<Vec<u8>, StoreError> {
        if sha256.len() != 64 || !sha256.bytes().all(|b| b.is_ascii_hexdigit()) {
            return Err(StoreError::Refused(format!("'{sha256}' is not a sha256")));
        }
        let path = self.blob_path(sha256);
        let bytes = std::fs::read(&path).map_err(io(&path))?;
        if sha256_hex(&bytes) != sha256 {
            return Err(StoreError::Damaged { path, reason: "content does not match its sha256".into() });
        }
        Ok(bytes)
    }

    fn read_json<T: for<'de> Deserialize<'de> + Default>(&self, path: &Path) -> Result<T, StoreError> {
        let size = match std::fs::metadata(path) {
            Ok(m) => m.len(),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(T::default()),
            Err(e) => return Err(io(path)(e)),
        };
        if size > MAX_INDEX_BYTES {
            return Err(StoreError::Damaged { path: path.into(), reason: format!("{size} bytes is too large") });
        }
        let bytes = std::fs::read(path).map_err(io(path))?;
        serde_json::from_slice(&bytes).map_err(|e| StoreError::Damaged { path: path.into(), reason: e.to_string() })
    }

    fn write_json<T: Serialize>(&self, path: &Path, value: &T) -> Result<(), StoreError> {
        let bytes = serde_json::to_vec_pretty(value)
            .map_err(|e| StoreError::Io { path: path.into(), reason: e.to_string() })?;
        write_atomically(path, &bytes).map_err(io(path))
    }

    /// Every named component, by name.
    pub fn components(&self) -> Result<BTreeMap<String, ComponentRecord>, StoreError> {
        self.read_json(&self.root.join("components.json"))
    }

    /// Records `record` under its name (its blob must be stored already).
    pub fn put_component(&self, record: ComponentRecord) -> Result<(), StoreError> {
        let mut components = self.components()?;
        if !components.contains_key(&record.name) && components.len() >= MAX_STORED_COMPONENTS {
            return Err(StoreError::Refused(format!("the store holds {MAX_STORED_COMPONENTS} components already")));
        }
        if !self.blob_path(&record.sha256).is_file() {
            return Err(StoreError::Refused(format!("blob {} is not stored", record.sha256)));
        }
        components.insert(record.name.clone(), record);
        self.write_json(&self.root.join("components.json"), &components)
    }

    pub fn state(&self) -> Result<StoreState, StoreError> {
        let mut state: StoreState = self.read_json(&self.root.join("state.json"))?;
        state.next_set = state.next_set.max(1);
        Ok(state)
    }

    fn write_state(&self, state: &StoreState) -> Result<(), StoreError> {
        self.write_json(&self.root.join("state.json"), state)
    }

    fn set_path(&self, id: u64) -> PathBuf {
        self.root.join("sets").join(format!("{id}.json"))
    }

    pub fn set(&self, id: u64) -> Result<SetRecord, StoreError> {
        let path = self.set_path(id);
        if !path.is_file() {
            return Err(StoreError::NoSet(id));
        }
        let bytes = std::fs::read(&path).map_err(io(&path))?;
        serde_json::from_slice(&bytes).map_err(|e| StoreError::Damaged { path, reason: e.to_string() })
    }

    /// Every set, oldest first.
    pub fn sets(&self) -> Result<Vec<SetRecord>, StoreError> {
        let dir = self.root.join("sets");
        let mut ids: Vec<u64> = std::fs::read_dir(&dir)
            .map_err(io(&dir))?
            .filter_map(|e| e.ok())
            .filter_map(|e| e.file_name().to_str()?.strip_suffix(".json")?.parse().ok())
            .collect();
        ids.sort_unstable();
        ids.into_iter().map(|id| self.set(id)).collect()
    }

    /// Stores a new set (id assigned here) and returns it. Its blobs must be
    /// stored already.
    pub fn add_set(&self, mut record: SetRecord) -> Result<SetRecord, StoreError> {
        for sha in record.sources.values().chain(std::iter::once(&record.config_sha256)) {
            if !self.blob_path(sha).is_file() {
                return Err(StoreError::Refused(format!("blob {sha} is not stored")));
            }
        }
        let mut state = self.state()?;
        record.id = state.next_set;
        state.next_set += 1;
        // The counter first: a crash between the two writes skips an id,
        // it never reuses one.
        self.write_state(&state)?;
        self.write_json(&self.set_path(record.id), &record)?;
        self.forget_old_sets(&state)?;
        Ok(record)
    }

    fn forget_old_sets(&self, state: &StoreState) -> Result<(), StoreError> {
        let sets = self.sets()?;
        let excess = sets.len().saturating_sub(MAX_SETS);
        for set in sets.iter().take(excess) {
            if state.active != Some(set.id) && !state.history.contains(&set.id) {
                let _ = std::fs::remove_file(self.set_path(set.id));
            }
        }
        Ok(())
    }

    /// Records that set `id` is now the active one (the previous active set
    /// goes onto the rollback history).
    pub fn mark_active(&self, id: u64) -> Result<StoreState, StoreError> {
        self.set(id)?;
        let mut state = self.state()?;
        if let Some(previous) = state.active
            && previous != id
        {
            state.history.push(previous);
            let excess = state.history.len().saturating_sub(MAX_HISTORY);
            state.history.drain(..excess);
        }
        state.active = Some(id);
        self.write_state(&state)?;
        Ok(state)
    }

    /// Records a rollback: `id` (the last of the history) is active again.
    pub fn mark_rolled_back(&self, id: u64) -> Result<StoreState, StoreError> {
        let mut state = self.state()?;
        if state.history.last() != Some(&id) {
            return Err(StoreError::Refused(format!("set {id} is not the previous active set")));
        }
        state.history.pop();
        state.active = Some(id);
        self.write_state(&state)?;
        Ok(state)
    }

    pub fn set_boot_config(&self, sha256: &str) -> Result<(), StoreError> {
        let mut state = self.state()?;
        state.boot_config_sha256 = Some(sha256.to_string());
        self.write_state(&state)
    }

    /// Appends `entry` to the audit log and fsyncs it.
    pub fn audit(&self, entry: &AuditEntry) -> Result<(), StoreError> {
        let path = self.root.join("audit.log");
        let mut line =
            serde_json::to_vec(entry).map_err(|e| StoreError::Io { path: path.clone(), reason: e.to_string() })?;
        line.push(b'\n');
        let mut file = std::fs::OpenOptions::new().create(true).append(true).open(&path).map_err(io(&path))?;
        file.write_all(&line).map_err(io(&path))?;
        file.sync_data().map_err(io(&path))
    }

    /// Records one request in the audit log: now, by `user`. A log that
    /// cannot be written is reported in the host log; the request stands.
    pub fn record(&self, user: &str, action: &str, target: &str, outcome: Outcome<'_>) {
        let (result, detail) = match outcome {
            Outcome::Ok(detail) => ("ok", detail),
            Outcome::Refused(detail) => ("refused", detail),
            Outcome::Failed(detail) => ("failed", detail),
        };
        let entry = AuditEntry {
            time: unix_now(),
            user: user.into(),
            action: action.into(),
            target: crate::contract::clip(target).to_string(),
            result: result.into(),
            detail: crate::contract::clip(detail).to_string(),
        };
        if let Err(e) = self.audit(&entry) {
            tracing::error!("cannot write the audit log: {e}");
        }
    }

    /// The newest `limit` audit entries (at most [`MAX_AUDIT_READ`]), oldest
    /// first. Lines that do not parse (a torn last write) are skipped.
    pub fn audit_entries(&self, limit: usize) -> Result<Vec<AuditEntry>, StoreError> {
        let path = self.root.join("audit.log");
        let text = match std::fs::read_to_string(&path) {
            Ok(text) => text,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Vec::new()),
            Err(e) => return Err(io(&path)(e)),
        };
        let entries: Vec<AuditEntry> = text.lines().filter_map(|l| serde_json::from_str(l).ok()).collect();
        let skip = entries.len().saturating_sub(limit.min(MAX_AUDIT_READ));
        Ok(entries.into_iter().skip(skip).collect())
    }

    /// Checks that everything the state names exists and matches its hash;
    /// the kill -9 tests call it.
    pub fn verify(&self) -> Result<(), StoreError> {
        let state = self.state()?;
        for id in state.active.iter().chain(state.history.iter()) {
            let set = self.set(*id)?;
            for sha in set.sources.values().chain(std::iter::once(&set.config_sha256)) {
                self.blob(sha)?;
            }
        }
        for record in self.components()?.values() {
            self.blob(&record.sha256)?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn set(store: &Store, text: &[u8]) -> SetRecord {
        let sha = store.put_blob(text).unwrap();
        store
            .add_set(SetRecord {
                id: 0,
                created_by: "alice".into(),
                created_at: unix_now(),
                platform: Some("control".into()),
                config_name: "robot.xml".into(),
                config_sha256: sha,
                base_dir: PathBuf::from("/tmp"),
                sources: BTreeMap::new(),
                changes: vec![],
                graph: serde_json::Value::Null,
            })
            .unwrap()
    }

    #[test]
    fn sets_activate_and_roll_back_in_order() {
        let dir = tempfile::tempdir().unwrap();
        let store = Store::open(dir.path()).unwrap();
        let one = set(&store, b"<robot/>");
        let two = set(&store, b"<robot name='b'/>");
        assert_eq!((one.id, two.id), (1, 2));
        store.mark_active(1).unwrap();
        let state = store.mark_active(2).unwrap();
        assert_eq!((state.active, state.history.clone()), (Some(2), vec![1]));
        assert!(store.mark_rolled_back(2).is_err());
        let state = store.mark_rolled_back(1).unwrap();
        assert_eq!((state.active, state.history), (Some(1), vec![]));
        let reopened = Store::open(dir.path()).unwrap();
        assert_eq!(reopened.state().unwrap().active, Some(1));
        assert_eq!(reopened.sets().unwrap().len(), 2);
        reopened.verify().unwrap();
        assert!(matches!(store.mark_active(9), Err(StoreError::NoSet(9))));
    }

    #[test]
    fn damaged_blobs_and_torn_audit_lines_are_found() {
        let dir = tempfile::tempdir().unwrap();
        let store = Store::open(dir.path()).unwrap();
        let one = set(&store, b"<robot/>");
        store.mark_active(one.id).unwrap();
        let entry = AuditEntry {
            time: 1,
            user: "alice".into(),
            action: "activate".into(),
            target: "set 1".into(),
            result: "ok".into(),
            detail: String::new(),
        };
        store.audit(&entry).unwrap();
        let mut log = std::fs::OpenOptions::new().append(true).open(dir.path().join("audit.log")).unwrap();
        log.write_all(b"{\"time\": 2, \"us").unwrap();
        assert_eq!(store.audit_entries(10).unwrap(), vec![entry]);
        std::fs::write(store.blob_path(&one.config_sha256), b"tampered").unwrap();
        let err = store.verify().unwrap_err().to_string();
        assert!(err.ends_with("content does not match its sha256"), "{err}");
        assert!(store.blob("../../etc/passwd").is_err());
    }
}
