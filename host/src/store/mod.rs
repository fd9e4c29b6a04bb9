//! The store on disk: uploaded components (content-addressed), robot files,
//! deployable sets (a robot file plus the exact components its sources
//! name), which set is active and which were before it, the portal's users
//! and the audit log.
//!
//! Layout under the store's root:
//! ```text
//! lock                        held while a writer changes anything
//! users.json                  portal users (`users`)
//! blobs/<sha256>              component and robot-file bytes, by content
//! components.json             OWNER/NAME -> record: each upload belongs to its uploader (`records::ComponentIndex`)
//! worlds.json                 uploaded simulator worlds, name -> record (`records::WorldIndex`)
//! sets/<id>.json              one set (`records::SetRecord`), never rewritten
//! state.json                  active set, previously active sets, next id
//! audit.log                   one JSON object per line, appended and fsynced
//! lab.json, experiments/      the remote lab (`experiments`)
//! ```
//!
//! Invariants:
//! - one writer: every change goes through a [`StoreWriter`], which holds
//!   the store's lock (a mutex in this process and an exclusive `flock` on
//!   `lock`, so `subsume user` in another process waits its turn); reads
//!   need no lock, because every file but `audit.log` is replaced
//!   atomically (temporary file, fsync, rename, fsync of the folder);
//! - ids are never reused and a set's record never changes once written;
//! - what a record names is written before the record: a kill -9 at any
//!   moment leaves the old state or the new one, never a record naming a
//!   missing blob ([`Store::verify`] checks);
//! - records carry a format version and older ones still load (`records`);
//! - nothing here runs guest code or parses a component: callers validate
//!   before they store.

pub mod access;
pub mod audit;
pub mod experiments;
pub mod records;
pub mod task;
pub mod users;

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};
use std::sync::{Mutex, MutexGuard};

use sha2::{Digest, Sha256};
use thiserror::Error;

pub use self::audit::{AuditEntry, MAX_AUDIT_READ, Outcome};
use self::experiments::{ExperimentRecord, Experiments, LabState, experiment_dir};
pub use self::records::{
    ComponentIndex, ComponentRecord, STORE_FORMAT, SetRecord, StoreState, WiringComponent, WiringConnection,
    WiringGraph, World, WorldIndex, WorldRecord, component_key,
};
use self::users::{Users, UsersError};
use crate::contract::clip;
use crate::fsutil::write_atomically;

/// Most sets the store holds: beyond it a new set is refused, never made
/// room for with another user's (bounds the store's growth).
pub const MAX_SETS: usize = 1000;
/// Most sets one stager keeps (a user, or the host itself as `boot`,
/// `dev`, `robot:NAME`): beyond it their own oldest set that nothing needs
/// is forgotten, audited. One researcher staging in a loop evicts only
/// her own sets, never another user's.
pub const MAX_SETS_PER_USER: usize = 20;
/// Previously active sets remembered for rollback.
pub const MAX_HISTORY: usize = 20;
/// Most named components in the store.
pub const MAX_STORED_COMPONENTS: usize = 500;
/// Most named components one user may keep: one uploader must not fill
/// the store's room (above) and lock every other user out of uploading.
pub const MAX_COMPONENTS_PER_USER: usize = 50;
/// Most uploaded simulator worlds in the store (bounds its growth from
/// uploads; each is at most `sim::world::MAX_WORLD_BYTES`).
pub const MAX_STORED_WORLDS: usize = 200;
/// Largest index file (components.json, state.json, a set) read.
pub const MAX_INDEX_BYTES: u64 = 16 << 20;
/// The user the first run of a store with no users makes
/// ([`Store::add_first_admin`]).
pub const FIRST_ADMIN: &str = "admin";

#[derive(Debug, Error)]
pub enum StoreError {
    #[error("store {path}: {reason}")]
    Io { path: PathBuf, reason: String },
    /// The store's file system has no room (or the owner's quota is used
    /// up): nothing of the change was kept.
    #[error("store {path}: the disk is full: {reason}")]
    Full { path: PathBuf, reason: String },
    #[error("store {path}: damaged: {reason}")]
    Damaged { path: PathBuf, reason: String },
    #[error("no set {0} in the store")]
    NoSet(u64),
    #[error("{0}")]
    Refused(String),
    #[error(transparent)]
    Users(#[from] UsersError),
}

fn io(path: &Path) -> impl Fn(std::io::Error) -> StoreError + '_ {
    move |e| {
        let full = matches!(e.kind(), std::io::ErrorKind::StorageFull | std::io::ErrorKind::QuotaExceeded);
        let (path, reason) = (path.to_path_buf(), e.to_string());
        if full { StoreError::Full { path, reason } } else { StoreError::Io { path, reason } }
    }
}

/// Seconds since the Unix epoch.
pub use crate::walltime::unix_now_s as unix_now;

pub fn sha256_hex(bytes: &[u8]) -> String {
    hex::encode(Sha256::digest(bytes))
}

/// The store rooted at a folder. Reads take `&self`; changes take a
/// [`StoreWriter`] from [`Store::lock`].
#[derive(Debug)]
pub struct Store {
    root: PathBuf,
    writer: Mutex<()>,
    users: std::sync::Arc<Users>,
}

/// The one writer of a store, while it lives. Reads through it see every
/// change it made.
pub struct StoreWriter<'s> {
    store: &'s Store,
    _in_process: MutexGuard<'s, ()>,
    /// Holds the exclusive `flock` until dropped.
    _across_processes: std::fs::File,
}

impl std::ops::Deref for StoreWriter<'_> {
    type Target = Store;

    fn deref(&self) -> &Store {
        self.store
    }
}

impl Store {
    /// Opens (creating when missing) the store at `root`.
    pub fn open(root: &Path) -> Result<Store, StoreError> {
        for dir in [root.to_path_buf(), root.join("blobs"), root.join("sets")] {
            std::fs::create_dir_all(&dir).map_err(io(&dir))?;
        }
        let store = Store {
            root: root.to_path_buf(),
            writer: Mutex::new(()),
            users: std::sync::Arc::new(Users::new(root.join("users.json"))),
        };
        store.state()?;
        store.components()?;
        Ok(store)
    }

    /// The writer: waits for any other writer, in this process or another.
    pub fn lock(&self) -> Result<StoreWriter<'_>, StoreError> {
        let guard = self
            .writer
            .lock()
            .map_err(|_| StoreError::Refused("the store's lock was poisoned by a crash of another writer".into()))?;
        let path = self.root.join("lock");
        let file =
            std::fs::OpenOptions::new().create(true).truncate(false).write(true).open(&path).map_err(io(&path))?;
        file.lock().map_err(io(&path))?;
        Ok(StoreWriter { store: self, _in_process: guard, _across_processes: file })
    }

    pub fn root(&self) -> &Path {
        &self.root
    }

    /// The portal's users (read them here; change them through a writer).
    pub fn users(&self) -> &std::sync::Arc<Users> {
        &self.users
    }

    /// On a store with no users: adds [`FIRST_ADMIN`], an admin with a
    /// generated password, records it in the audit log (by `first-run`)
    /// and returns the password, for the caller to show once; it is
    /// stored only as its hash. On a store with users: nothing, `None`.
    /// Under the store's lock, so hosts starting at once on one store make
    /// one admin between them.
    pub fn add_first_admin(&self) -> Result<Option<String>, StoreError> {
        let writer = self.lock()?;
        if !writer.users().all()?.is_empty() {
            return Ok(None);
        }
        let password = users::generate_password().map_err(|e| StoreError::Refused(e.to_string()))?;
        let added = writer.users_mut().add(FIRST_ADMIN, users::Role::Admin, &[], &password, false);
        let target = format!("user '{FIRST_ADMIN}'");
        match &added {
            Ok(()) => writer.record("first-run", "user-add", &target, Outcome::Ok("")),
            Err(e) => writer.record("first-run", "user-add", &target, Outcome::Refused(&e.to_string())),
        }
        added?;
        Ok(Some(password))
    }

    pub fn blob_path(&self, sha256: &str) -> PathBuf {
        self.root.join("blobs").join(sha256)
    }

    /// Reads a blob back, checking its content still matches its name.
    pub fn blob(&self, sha256: &str) -> Result<Vec<u8>, StoreError> {
        if sha256.len() != 64 || !sha256.bytes().all(|b| b.is_ascii_hexdigit()) {
            return Err(StoreError::Refused(format!("'{}' is not a sha256", clip(sha256))));
        }
        let path = self.blob_path(sha256);
        let bytes = std::fs::read(&path).map_err(io(&path))?;
        if sha256_hex(&bytes) != sha256 {
            return Err(StoreError::Damaged { path, reason: "content does not match its sha256".into() });
        }
        Ok(bytes)
    }

    /// The bytes of index file `path`, or `None` when it does not exist.
    fn read_index(&self, path: &Path) -> Result<Option<Vec<u8>>, StoreError> {
        let size = match std::fs::metadata(path) {
            Ok(m) => m.len(),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
            Err(e) => return Err(io(path)(e)),
        };
        if size > MAX_INDEX_BYTES {
            return Err(StoreError::Damaged { path: path.into(), reason: format!("{size} bytes is too large") });
        }
        std::fs::read(path).map(Some).map_err(io(path))
    }

    fn damaged(path: &Path) -> impl Fn(String) -> StoreError + '_ {
        move |reason| StoreError::Damaged { path: path.to_path_buf(), reason }
    }

    /// `owner`'s upload `name`, if there is one.
    pub fn component(&self, owner: &str, name: &str) -> Result<Option<ComponentRecord>, StoreError> {
        Ok(self.components()?.remove(&component_key(owner, name)))
    }

    /// Every uploaded component, by `OWNER/NAME` ([`component_key`]).
    pub fn components(&self) -> Result<BTreeMap<String, ComponentRecord>, StoreError> {
        let path = self.root.join("components.json");
        match self.read_index(&path)? {
            None => Ok(BTreeMap::new()),
            Some(bytes) => ComponentIndex::parse(&bytes).map(|i| i.components).map_err(Self::damaged(&path)),
        }
    }

    /// Every uploaded simulator world, by name.
    pub fn worlds(&self) -> Result<BTreeMap<String, WorldRecord>, StoreError> {
        let path = self.root.join("worlds.json");
        match self.read_index(&path)? {
            None => Ok(BTreeMap::new()),
            Some(bytes) => WorldIndex::parse(&bytes).map(|i| i.worlds).map_err(Self::damaged(&path)),
        }
    }

    pub fn state(&self) -> Result<StoreState, StoreError> {
        let path = self.root.join("state.json");
        match self.read_index(&path)? {
            None => Ok(StoreState::default()),
            Some(bytes) => StoreState::parse(&bytes).map_err(Self::damaged(&path)),
        }
    }

    fn set_path(&self, id: u64) -> PathBuf {
        self.root.join("sets").join(format!("{id}.json"))
    }

    pub fn set(&self, id: u64) -> Result<SetRecord, StoreError> {
        let path = self.set_path(id);
        match self.read_index(&path)? {
            None => Err(StoreError::NoSet(id)),
            Some(bytes) => SetRecord::parse(&bytes).map_err(Self::damaged(&path)),
        }
    }

    /// Ids of every stored set, oldest first.
    fn set_ids(&self) -> Result<Vec<u64>, StoreError> {
        let dir = self.root.join("sets");
        let mut ids: Vec<u64> = std::fs::read_dir(&dir)
            .map_err(io(&dir))?
            .filter_map(|e| e.ok())
            .filter_map(|e| e.file_name().to_str()?.strip_suffix(".json")?.parse().ok())
            .collect();
        ids.sort_unstable();
        Ok(ids)
    }

    /// Every set, oldest first. A set forgotten while this reads is left out.
    pub fn sets(&self) -> Result<Vec<SetRecord>, StoreError> {
        let mut sets = Vec::new();
        for id in self.set_ids()? {
            match self.set(id) {
                Ok(set) => sets.push(set),
                Err(StoreError::NoSet(_)) => {}
                Err(e) => return Err(e),
            }
        }
        Ok(sets)
    }

    /// The remote lab's state (defaults before the first change).
    pub fn lab_state(&self) -> Result<LabState, StoreError> {
        let path = self.root.join("lab.json");
        match self.read_index(&path)? {
            None => Ok(LabState::default()),
            Some(bytes) => LabState::parse(&bytes).map_err(Self::damaged(&path)),
        }
    }

    /// The folder of experiment `id` (its record and results).
    pub fn experiment_dir(&self, id: u64) -> PathBuf {
        experiment_dir(&self.root, id)
    }

    /// Experiment `id`, or `None` when there is none.
    pub fn experiment(&self, id: u64) -> Result<Option<ExperimentRecord>, StoreError> {
        let path = self.experiment_dir(id).join("experiment.json");
        match self.read_index(&path)? {
            None => Ok(None),
            Some(bytes) => ExperimentRecord::parse(&bytes).map(Some).map_err(Self::damaged(&path)),
        }
    }

    /// Every experiment, by id. A folder without a record (a crash before
    /// its first write) is left out.
    pub fn experiments(&self) -> Result<Experiments, StoreError> {
        let dir = self.root.join("experiments");
        let entries = match std::fs::read_dir(&dir) {
            Ok(entries) => entries,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Experiments::new()),
            Err(e) => return Err(io(&dir)(e)),
        };
        let mut all = Experiments::new();
        for entry in entries.filter_map(|e| e.ok()) {
            let Some(id) = entry.file_name().to_str().and_then(|n| n.parse::<u64>().ok()) else { continue };
            if let Some(record) = self.experiment(id)? {
                all.insert(id, record);
            }
        }
        Ok(all)
    }

    /// The newest `limit` audit entries (at most [`MAX_AUDIT_READ`]), oldest
    /// first. Lines that do not parse (a torn last write) are skipped.
    pub fn audit_entries(&self, limit: usize) -> Result<Vec<AuditEntry>, StoreError> {
        audit::read(&self.root.join("audit.log"), limit)
    }

    /// Checks that everything the state names exists and matches its hash,
    /// that every set parses and has an id below `next_set`, and that every
    /// component's blob is intact.
    pub fn verify(&self) -> Result<(), StoreError> {
        let state = self.state()?;
        for id in state.active.iter().chain(state.history.iter()) {
            let set = self.set(*id)?;
            for sha in set.sources.values().chain(std::iter::once(&set.config_sha256)) {
                self.blob(sha)?;
            }
        }
        for id in self.set_ids()? {
            let set = self.set(id)?;
            if set.id != id || id >= state.next_set {
                return Err(StoreError::Damaged {
                    path: self.set_path(id),
                    reason: format!("holds set {} (next id {})", set.id, state.next_set),
                });
            }
        }
        for record in self.components()?.values() {
            self.blob(&record.sha256)?;
        }
        for record in self.worlds()?.values() {
            self.blob(&record.sha256)?;
        }
        Ok(())
    }
}

/// A new store state written beside `state.json`, not yet in its place
/// ([`StoreWriter::prepare_switch`]); dropped, it changes nothing.
#[derive(Debug)]
pub struct PendingState {
    write: crate::fsutil::PreparedWrite,
    state: StoreState,
    path: PathBuf,
}

impl PendingState {
    /// Puts the new state in place.
    pub fn commit(self) -> Result<StoreState, StoreError> {
        self.write.commit().map_err(io(&self.path))?;
        Ok(self.state)
    }
}

impl StoreWriter<'_> {
    fn write_json<T: serde::Serialize>(&self, path: &Path, value: &T) -> Result<(), StoreError> {
        let bytes = serde_json::to_vec_pretty(value)
            .map_err(|e| StoreError::Io { path: path.into(), reason: e.to_string() })?;
        write_atomically(path, &bytes).map_err(io(path))
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

    /// Records `record` as its uploader's component of its name (its blob
    /// must be stored already): it replaces that uploader's earlier upload
    /// of the name, never another user's.
    pub fn put_component(&self, record: ComponentRecord) -> Result<(), StoreError> {
        let mut components = self.components()?;
        let key = record.key();
        if !components.contains_key(&key) {
            if components.len() >= MAX_STORED_COMPONENTS {
                return Err(StoreError::Refused(format!("the store holds {MAX_STORED_COMPONENTS} components already")));
            }
            let owned = components.values().filter(|c| c.uploaded_by == record.uploaded_by).count();
            if owned >= MAX_COMPONENTS_PER_USER {
                return Err(StoreError::Refused(format!(
                    "{} has {MAX_COMPONENTS_PER_USER} components stored already",
                    record.uploaded_by
                )));
            }
        }
        if !self.blob_path(&record.sha256).is_file() {
            return Err(StoreError::Refused(format!("blob {} is not stored", record.sha256)));
        }
        components.insert(key, record);
        let index = ComponentIndex { format: STORE_FORMAT, components };
        self.write_json(&self.root.join("components.json"), &index)
    }

    /// Records the world `record` under its name (its blob must be stored
    /// already); a later upload of the same name replaces the record, never
    /// what a staged set pinned.
    pub fn put_world(&self, record: WorldRecord) -> Result<(), StoreError> {
        let mut worlds = self.worlds()?;
        if !worlds.contains_key(&record.name) && worlds.len() >= MAX_STORED_WORLDS {
            return Err(StoreError::Refused(format!("the store holds {MAX_STORED_WORLDS} worlds already")));
        }
        if !self.blob_path(&record.sha256).is_file() {
            return Err(StoreError::Refused(format!("blob {} is not stored", record.sha256)));
        }
        worlds.insert(record.name.clone(), record);
        self.write_json(&self.root.join("worlds.json"), &WorldIndex { format: STORE_FORMAT, worlds })
    }

    fn write_state(&self, state: &StoreState) -> Result<(), StoreError> {
        self.write_json(&self.root.join("state.json"), state)
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
        let evicted = self.room_for_set(&record.created_by, &state)?;
        // A set file beyond the counter (a crash between the two writes
        // below in an older host) must not be overwritten.
        let highest = self.set_ids()?.last().copied().unwrap_or(0);
        record.id = state.next_set.max(highest + 1);
        record.format = STORE_FORMAT;
        state.next_set = record.id + 1;
        // The counter first: a crash between the two writes skips an id,
        // it never reuses one.
        self.write_state(&state)?;
        self.write_json(&self.set_path(record.id), &record)?;
        if let Some(old) = evicted {
            match std::fs::remove_file(self.set_path(old)) {
                Ok(()) => {
                    let detail =
                        format!("{} keeps at most {MAX_SETS_PER_USER} sets; set {} came", record.created_by, record.id);
                    self.record(
                        "store",
                        "forget-set",
                        &format!("set {old} of {}", record.created_by),
                        Outcome::Ok(&detail),
                    );
                    tracing::info!("set {old} of {} forgotten: {detail}", record.created_by);
                }
                Err(e) => tracing::warn!("set {old} could not be forgotten: {e}"),
            }
        }
        Ok(record)
    }

    /// Forgets set `id`, which nothing may need (see [`Self::needed_sets`]):
    /// a stager's set that a refused submission or activation left.
    pub fn forget_set(&self, id: u64) -> Result<(), StoreError> {
        self.set(id)?;
        if self.needed_sets(&self.state()?)?.contains(&id) {
            return Err(StoreError::Refused(format!(
                "set {id} is needed (active, in the rollback history, a baseline or an experiment's)"
            )));
        }
        std::fs::remove_file(self.set_path(id)).map_err(io(&self.set_path(id)))
    }

    /// The sets something needs: the active one, the rollback history, the
    /// lab's baselines, and every experiment's that has not ended.
    fn needed_sets(&self, state: &StoreState) -> Result<BTreeSet<u64>, StoreError> {
        let mut needed: BTreeSet<u64> = state.history.iter().copied().chain(state.active).collect();
        let lab = self.lab_state()?;
        needed.extend(lab.baseline);
        needed.extend(lab.baselines.values().copied());
        needed.extend(lab.settings.drive_reset.as_ref().map(|d| d.set));
        needed.extend(self.experiments()?.values().filter(|r| !r.state.is_final()).map(|r| r.set));
        Ok(needed)
    }

    /// Room for one more set of `stager`'s: the id of their own oldest set
    /// nothing needs when they are at their quota; refused when the store
    /// or their quota is full of needed sets.
    fn room_for_set(&self, stager: &str, state: &StoreState) -> Result<Option<u64>, StoreError> {
        let ids = self.set_ids()?;
        let mut theirs = Vec::new();
        for id in &ids {
            if self.set(*id).is_ok_and(|set| set.created_by == stager) {
                theirs.push(*id);
            }
        }
        if theirs.len() < MAX_SETS_PER_USER {
            if ids.len() >= MAX_SETS {
                return Err(StoreError::Refused(format!("the store holds {MAX_SETS} sets already")));
            }
            return Ok(None);
        }
        let needed = self.needed_sets(state)?;
        match theirs.into_iter().find(|id| !needed.contains(id)) {
            Some(oldest) => Ok(Some(oldest)),
            None => Err(StoreError::Refused(format!(
                "{stager} has {MAX_SETS_PER_USER} sets, each needed (active, in the rollback history, a baseline or an experiment's); one must end first"
            ))),
        }
    }

    /// Records that set `id` is now the active one (the previous active set
    /// goes onto the rollback history).
    pub fn mark_active(&self, id: u64) -> Result<StoreState, StoreError> {
        self.prepare_state(self.active_state(id)?)?.commit()
    }

    /// The state with `id` active (the active one before it goes to the
    /// history).
    fn active_state(&self, id: u64) -> Result<StoreState, StoreError> {
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
        Ok(state)
    }

    /// Records a rollback: `id` (the last of the history) is active again.
    pub fn mark_rolled_back(&self, id: u64) -> Result<StoreState, StoreError> {
        self.prepare_state(self.rolled_back_state(id)?)?.commit()
    }

    fn rolled_back_state(&self, id: u64) -> Result<StoreState, StoreError> {
        let mut state = self.state()?;
        if state.history.last() != Some(&id) {
            return Err(StoreError::Refused(format!("set {id} is not the previous active set")));
        }
        state.history.pop();
        state.active = Some(id);
        Ok(state)
    }

    /// [`mark_active`](Self::mark_active) (or, with `rollback`,
    /// [`mark_rolled_back`](Self::mark_rolled_back)) in two halves: the new
    /// state is written beside the old one now (a full disk fails here,
    /// before anything changed), and takes its place when the returned
    /// [`PendingState`] is committed.
    pub fn prepare_switch(&self, id: u64, rollback: bool) -> Result<PendingState, StoreError> {
        let state = if rollback { self.rolled_back_state(id)? } else { self.active_state(id)? };
        self.prepare_state(state)
    }

    fn prepare_state(&self, state: StoreState) -> Result<PendingState, StoreError> {
        let path = self.root.join("state.json");
        let bytes = serde_json::to_vec_pretty(&state)
            .map_err(|e| StoreError::Io { path: path.clone(), reason: e.to_string() })?;
        let write = crate::fsutil::prepare_atomically(&path, &bytes).map_err(io(&path))?;
        Ok(PendingState { write, state, path })
    }

    pub fn set_boot_config(&self, sha256: &str) -> Result<(), StoreError> {
        let mut state = self.state()?;
        state.boot_config_sha256 = Some(sha256.to_string());
        self.write_state(&state)
    }

    /// Replaces the lab's state.
    pub fn put_lab_state(&self, state: &LabState) -> Result<(), StoreError> {
        self.write_json(&self.root.join("lab.json"), state)
    }

    /// Stores a new experiment with the next id of `lab` (the lab's state,
    /// which its owner keeps in memory: the counter goes up in it and is
    /// written first, so a crash skips an id and never reuses one) and
    /// returns it.
    pub fn add_experiment(
        &self,
        lab: &mut LabState,
        mut record: ExperimentRecord,
    ) -> Result<ExperimentRecord, StoreError> {
        let mut next = lab.clone();
        record.id = next.next_experiment;
        next.next_experiment += 1;
        self.put_lab_state(&next)?;
        *lab = next;
        let dir = self.experiment_dir(record.id);
        std::fs::create_dir_all(&dir).map_err(io(&dir))?;
        self.put_experiment(&record)?;
        Ok(record)
    }

    /// Replaces experiment `record.id`'s record.
    pub fn put_experiment(&self, record: &ExperimentRecord) -> Result<(), StoreError> {
        let dir = self.experiment_dir(record.id);
        std::fs::create_dir_all(&dir).map_err(io(&dir))?;
        self.write_json(&dir.join("experiment.json"), record)
    }

    /// Forgets experiment `id`: its record and results (the lab keeps at
    /// most [`experiments::MAX_EXPERIMENT_RECORDS`]).
    pub fn forget_experiment(&self, id: u64) -> Result<(), StoreError> {
        let dir = self.experiment_dir(id);
        match std::fs::remove_dir_all(&dir) {
            Ok(()) => Ok(()),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(()),
            Err(e) => Err(io(&dir)(e)),
        }
    }

    /// Records one request in the audit log: now, by `user`. A log that
    /// cannot be written is reported in the host log; the request stands.
    pub fn record(&self, user: &str, action: &str, target: &str, outcome: Outcome<'_>) {
        let entry = AuditEntry {
            time: unix_now(),
            user: user.into(),
            action: action.into(),
            target: clip(target),
            result: outcome.result().into(),
            detail: audit::clip_detail(outcome.detail()),
        };
        if let Err(e) = audit::append(&self.root.join("audit.log"), &entry) {
            tracing::error!("cannot write the audit log: {e}");
        }
    }

    /// The users, to change (see `users::Users`).
    pub fn users_mut(&self) -> users::UsersWriter<'_> {
        users::UsersWriter::new(&self.store.users)
    }
}

#[cfg(test)]
mod tests {
    use std::io::Write;

    use super::*;

    fn set(store: &Store, text: &[u8]) -> Result<SetRecord, StoreError> {
        set_of(store, "alice", text)
    }

    fn set_of(store: &Store, by: &str, text: &[u8]) -> Result<SetRecord, StoreError> {
        let writer = store.lock()?;
        let sha = writer.put_blob(text)?;
        writer.add_set(SetRecord {
            format: STORE_FORMAT,
            id: 0,
            created_by: by.into(),
            created_at: unix_now(),
            platform: Some("control".into()),
            config_name: "robot.xml".into(),
            config_sha256: sha,
            base_dir: PathBuf::from("/tmp"),
            sources: BTreeMap::new(),
            changes: vec![],
            graph: WiringGraph::default(),
        })
    }

    #[test]
    fn sets_activate_and_roll_back_in_order() -> Result<(), StoreError> {
        let dir = tempfile::tempdir().map_err(io(Path::new("tmp")))?;
        let store = Store::open(dir.path())?;
        let one = set(&store, b"<robot/>")?;
        let two = set(&store, b"<robot name='b'/>")?;
        assert_eq!((one.id, two.id), (1, 2));
        let writer = store.lock()?;
        writer.mark_active(1)?;
        let state = writer.mark_active(2)?;
        assert_eq!((state.active, state.history.clone()), (Some(2), vec![1]));
        assert!(writer.mark_rolled_back(2).is_err());
        let state = writer.mark_rolled_back(1)?;
        assert_eq!((state.active, state.history), (Some(1), vec![]));
        assert!(matches!(writer.mark_active(9), Err(StoreError::NoSet(9))));
        drop(writer);
        let reopened = Store::open(dir.path())?;
        assert_eq!(reopened.state()?.active, Some(1));
        assert_eq!(reopened.sets()?.len(), 2);
        reopened.verify()
    }

    /// One stager's sets beyond their quota evict only their own oldest
    /// that nothing needs, audited; a needed set is never evicted, and a
    /// quota full of needed sets refuses the next one.
    #[test]
    fn a_stager_evicts_only_their_own_sets_that_nothing_needs() -> Result<(), StoreError> {
        let dir = tempfile::tempdir().map_err(io(Path::new("tmp")))?;
        let store = Store::open(dir.path())?;
        let bens = set_of(&store, "ben", b"<robot name='ben'/>")?.id;
        let first = set_of(&store, "ana", b"<robot name='a0'/>")?.id;
        store.lock()?.mark_active(first)?;
        let mut anas = vec![first];
        for i in 1..MAX_SETS_PER_USER {
            anas.push(set_of(&store, "ana", format!("<robot name='a{i}'/>").as_bytes())?.id);
        }
        // At her quota: her oldest set that nothing needs goes (the first
        // is active), and nobody else's.
        let next = set_of(&store, "ana", b"<robot name='more'/>")?.id;
        let ids: Vec<u64> = store.sets()?.iter().map(|s| s.id).collect();
        assert!(ids.contains(&bens) && ids.contains(&first) && ids.contains(&next), "{ids:?}");
        assert!(!ids.contains(&anas[1]), "{ids:?}");
        assert_eq!(ids.len(), MAX_SETS_PER_USER + 1);
        let audit = store.audit_entries(10)?;
        assert!(
            audit.iter().any(|e| e.action == "forget-set" && e.target == format!("set {} of ana", anas[1])),
            "{audit:?}"
        );
        // Every one of hers needed (the rollback history): the next is
        // refused, and nothing is evicted.
        let writer = store.lock()?;
        for id in store.sets()?.iter().filter(|s| s.created_by == "ana").map(|s| s.id) {
            writer.mark_active(id)?;
        }
        writer.mark_active(bens)?;
        drop(writer);
        let before = store.sets()?.len();
        assert!(matches!(set_of(&store, "ana", b"<robot name='refused'/>"), Err(StoreError::Refused(_))));
        assert_eq!(store.sets()?.len(), before);
        Ok(())
    }

    /// Hosts starting at once on one empty store (threads with a handle
    /// each, as processes would): one admin is made, its password (the one
    /// returned to exactly one of them) logs in, and a later start makes none.
    #[test]
    fn hosts_starting_at_once_on_an_empty_store_make_one_admin() -> Result<(), StoreError> {
        let dir = tempfile::tempdir().map_err(io(Path::new("tmp")))?;
        Store::open(dir.path())?;
        let passwords: Vec<Option<String>> = std::thread::scope(|scope| {
            let handles: Vec<_> = (0..6)
                .map(|_| {
                    let root = dir.path().to_path_buf();
                    scope.spawn(move || Store::open(&root).and_then(|store| store.add_first_admin()))
                })
                .collect();
            handles.into_iter().map(|h| h.join().unwrap_or(Ok(None))).collect::<Result<_, _>>()
        })?;
        let made: Vec<&String> = passwords.iter().flatten().collect();
        assert_eq!(made.len(), 1, "{passwords:?}");
        let store = Store::open(dir.path())?;
        let users = store.users().all()?;
        assert_eq!(
            users.iter().map(|u| (u.name.as_str(), u.role)).collect::<Vec<_>>(),
            [(FIRST_ADMIN, users::Role::Admin)]
        );
        assert!(store.users().authenticate(FIRST_ADMIN, made[0]).is_some());
        assert_eq!(store.add_first_admin()?, None);
        let audit = store.audit_entries(100)?;
        assert_eq!(
            audit.iter().map(|e| (e.user.as_str(), e.action.as_str())).collect::<Vec<_>>(),
            [("first-run", "user-add")]
        );
        Ok(())
    }

    /// Many threads staging at once, each with its own store handle (as two
    /// processes would): every set gets its own id and keeps its own bytes.
    #[test]
    fn concurrent_writers_never_share_an_id() -> Result<(), StoreError> {
        let dir = tempfile::tempdir().map_err(io(Path::new("tmp")))?;
        Store::open(dir.path())?;
        let results: Vec<Result<Vec<(u64, String)>, StoreError>> = std::thread::scope(|scope| {
            let handles: Vec<_> = (0..8)
                .map(|t| {
                    let root = dir.path().to_path_buf();
                    scope.spawn(move || {
                        let store = Store::open(&root)?;
                        let mut made = Vec::new();
                        for i in 0..10 {
                            let text = format!("<robot name='t{t}-{i}'/>");
                            // A stager per thread, within their quota.
                            let set = set_of(&store, &format!("t{t}"), text.as_bytes())?;
                            made.push((set.id, text));
                            if i % 3 == 0 {
                                store.lock()?.mark_active(set.id)?;
                            }
                        }
                        Ok(made)
                    })
                })
                .collect();
            handles.into_iter().map(|h| h.join().unwrap_or_else(|_| Ok(Vec::new()))).collect()
        });
        let store = Store::open(dir.path())?;
        let mut ids = Vec::new();
        for made in results {
            for (id, text) in made? {
                let set = store.set(id)?;
                assert_eq!(store.blob(&set.config_sha256)?, text.as_bytes(), "set {id}");
                ids.push(id);
            }
        }
        let count = ids.len();
        ids.sort_unstable();
        ids.dedup();
        assert_eq!((ids.len(), count), (80, 80));
        assert_eq!(store.state()?.next_set, 81);
        store.verify()
    }

    /// One user's uploads of a name replace only that user's record, and a
    /// user's room is bounded without touching anyone else's.
    #[test]
    fn components_belong_to_their_uploader_within_each_users_room() -> Result<(), StoreError> {
        let dir = tempfile::tempdir().map_err(io(Path::new("tmp")))?;
        let store = Store::open(dir.path())?;
        let writer = store.lock()?;
        let record = |owner: &str, name: &str, bytes: &[u8]| -> Result<ComponentRecord, StoreError> {
            Ok(ComponentRecord {
                name: name.into(),
                sha256: writer.put_blob(bytes)?,
                size: bytes.len() as u64,
                world: World::Component,
                platform: "control".into(),
                uploaded_by: owner.into(),
                uploaded_at: 1,
                description: None,
                visibility: Default::default(),
            })
        };
        writer.put_component(record("ana", "avoid", b"ana 1")?)?;
        writer.put_component(record("bob", "avoid", b"bob 1")?)?;
        writer.put_component(record("ana", "avoid", b"ana 2")?)?;
        assert_eq!(store.component("ana", "avoid")?.map(|c| c.sha256), Some(sha256_hex(b"ana 2")));
        assert_eq!(store.component("bob", "avoid")?.map(|c| c.sha256), Some(sha256_hex(b"bob 1")));
        for i in 1..MAX_COMPONENTS_PER_USER {
            writer.put_component(record("ana", &format!("c{i}"), b"x")?)?;
        }
        let full = writer.put_component(record("ana", "one-more", b"x")?);
        assert!(matches!(full, Err(StoreError::Refused(ref why)) if why.contains("ana has 50 components")), "{full:?}");
        writer.put_component(record("ana", "avoid", b"ana 3")?)?;
        writer.put_component(record("bob", "one-more", b"x")?)?;
        assert_eq!(store.components()?.len(), MAX_COMPONENTS_PER_USER + 2);
        drop(writer);
        store.verify()
    }

    #[test]
    fn damaged_blobs_and_torn_audit_lines_are_found() -> Result<(), StoreError> {
        let dir = tempfile::tempdir().map_err(io(Path::new("tmp")))?;
        let store = Store::open(dir.path())?;
        let one = set(&store, b"<robot/>")?;
        let writer = store.lock()?;
        writer.mark_active(one.id)?;
        writer.record("alice", "activate", "set 1", Outcome::Ok(""));
        drop(writer);
        let entry = store.audit_entries(10)?.pop();
        let mut log = std::fs::OpenOptions::new()
            .append(true)
            .open(dir.path().join("audit.log"))
            .map_err(io(Path::new("audit.log")))?;
        log.write_all(b"{\"time\": 2, \"us").map_err(io(Path::new("audit.log")))?;
        assert_eq!(store.audit_entries(10)?.len(), 1);
        assert_eq!(entry.map(|e| (e.user, e.result)), Some(("alice".into(), "ok".into())));
        std::fs::write(store.blob_path(&one.config_sha256), b"tampered").map_err(io(Path::new("blob")))?;
        let err = store.verify().err().map(|e| e.to_string()).unwrap_or_default();
        assert!(err.ends_with("content does not match its sha256"), "{err}");
        assert!(store.blob("../../etc/passwd").is_err());
        Ok(())
    }
}
