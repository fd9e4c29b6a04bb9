//! The outbox: events waiting for their webhook, one file each in a folder
//! beside the store (`ID.json`, written to a temporary file, fsynced and
//! renamed in), removed once their receiver acknowledged them. A restart
//! reads them back in order and sends them; the last id given is kept in
//! `last-id` so ids never repeat. Bounded: when full, the oldest waiting
//! event is dropped, counted, and the log says so once.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
use thiserror::Error;

use super::Event;
use crate::fsutil::write_atomically;

/// Most events waiting: a receiver gone for good must not fill the disk.
pub const MAX_OUTBOX_ENTRIES: usize = 10_000;
/// Largest entry file read back, bytes: a corrupt or planted file is not
/// read whole into memory.
pub const MAX_ENTRY_BYTES: u64 = 1 << 20;
/// The file keeping the last id given.
const LAST_ID_FILE: &str = "last-id";

/// Why the outbox cannot keep or read an event.
#[derive(Debug, Error)]
pub enum OutboxError {
    #[error("outbox {path}: {source}")]
    Io { path: PathBuf, source: std::io::Error },
    #[error("the outbox's state is unusable")]
    Poisoned,
}

/// One event waiting for one webhook (an entry file's content).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Entry {
    /// The webhook's URL.
    pub hook: String,
    pub event: Event,
}

/// The events waiting, in the order they were written.
pub struct Outbox {
    dir: PathBuf,
    max: usize,
    entries: BTreeMap<u64, Entry>,
    last_id: u64,
    /// Events dropped because the outbox was full, since the start.
    dropped: u64,
}

impl Outbox {
    /// Opens (creating) the outbox in `dir`, holding at most `max` events;
    /// reads back the events waiting. A file that cannot be read is named
    /// in the log and left where it is.
    pub fn open(dir: &Path, max: usize) -> Result<Outbox, OutboxError> {
        let io = |path: &Path| {
            let path = path.to_path_buf();
            move |source| OutboxError::Io { path, source }
        };
        std::fs::create_dir_all(dir).map_err(io(dir))?;
        let mut entries = BTreeMap::new();
        for item in std::fs::read_dir(dir).map_err(io(dir))? {
            let path = item.map_err(io(dir))?.path();
            let Some(id) = path
                .file_name()
                .and_then(|n| n.to_str())
                .and_then(|n| n.strip_suffix(".json"))
                .and_then(|n| n.parse::<u64>().ok())
            else {
                continue;
            };
            match read_entry(&path) {
                Ok(entry) => {
                    entries.insert(id, entry);
                }
                Err(e) => tracing::error!("outbox: cannot read {}, left in place: {e}", path.display()),
            }
        }
        let last_file = dir.join(LAST_ID_FILE);
        let last_id = match std::fs::read_to_string(&last_file) {
            Ok(text) => text.trim().parse::<u64>().unwrap_or(0),
            Err(_) => 0,
        };
        let last_id = last_id.max(entries.keys().next_back().copied().unwrap_or(0));
        Ok(Outbox { dir: dir.to_path_buf(), max, entries, last_id, dropped: 0 })
    }

    /// A new event id, never given before in this outbox.
    pub fn next_id(&mut self) -> u64 {
        self.last_id += 1;
        self.last_id
    }

    /// Keeps `event` for webhook `hook` on disk (fsynced); when full, the
    /// oldest waiting event goes first.
    pub fn push(&mut self, hook: &str, event: &Event) -> Result<(), OutboxError> {
        let entry = Entry { hook: hook.to_string(), event: event.clone() };
        let bytes = serde_json::to_vec(&entry)
            .map_err(|e| OutboxError::Io { path: self.dir.clone(), source: std::io::Error::other(e) })?;
        let last = self.dir.join(LAST_ID_FILE);
        let last_id = self.last_id.max(event.id);
        write_atomically(&last, last_id.to_string().as_bytes())
            .map_err(|source| OutboxError::Io { path: last, source })?;
        self.last_id = last_id;
        while self.entries.len() >= self.max.max(1) {
            let Some((&oldest, _)) = self.entries.iter().next() else { break };
            self.remove(oldest)?;
            self.dropped += 1;
            if self.dropped == 1 {
                tracing::warn!(
                    "outbox full ({} events waiting): the oldest are dropped from now on (counted in the log at each delivery)",
                    self.max
                );
            }
        }
        let path = self.path(event.id);
        write_atomically(&path, &bytes).map_err(|source| OutboxError::Io { path, source })?;
        self.entries.insert(event.id, entry);
        Ok(())
    }

    /// The oldest waiting event.
    pub fn oldest(&self) -> Option<Entry> {
        self.entries.values().next().cloned()
    }

    /// Each destination's oldest waiting event, oldest first.
    pub fn oldest_per_destination(&self) -> Vec<Entry> {
        let mut seen = std::collections::BTreeSet::new();
        self.entries.values().filter(|e| seen.insert(e.hook.as_str())).cloned().collect()
    }

    /// The last id given: it changes whenever an event is written.
    pub fn last_id(&self) -> u64 {
        self.last_id
    }

    /// Forgets event `id` (delivered, or given up): its file is removed.
    pub fn remove(&mut self, id: u64) -> Result<(), OutboxError> {
        if self.entries.remove(&id).is_none() {
            return Ok(());
        }
        let path = self.path(id);
        match std::fs::remove_file(&path) {
            Err(e) if e.kind() != std::io::ErrorKind::NotFound => return Err(OutboxError::Io { path, source: e }),
            _ => {}
        }
        std::fs::File::open(&self.dir)
            .and_then(|d| d.sync_all())
            .map_err(|source| OutboxError::Io { path: self.dir.clone(), source })
    }

    pub fn len(&self) -> usize {
        self.entries.len()
    }

    pub fn is_empty(&self) -> bool {
        self.entries.is_empty()
    }

    /// Events dropped because the outbox was full, since it was opened.
    pub fn dropped(&self) -> u64 {
        self.dropped
    }

    fn path(&self, id: u64) -> PathBuf {
        self.dir.join(format!("{id:020}.json"))
    }
}

fn read_entry(path: &Path) -> Result<Entry, String> {
    let size = std::fs::metadata(path).map_err(|e| e.to_string())?.len();
    if size > MAX_ENTRY_BYTES {
        return Err(format!("larger than {MAX_ENTRY_BYTES} bytes"));
    }
    let bytes = std::fs::read(path).map_err(|e| e.to_string())?;
    serde_json::from_slice(&bytes).map_err(|e| e.to_string())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::notify::{EventKind, ExperimentFacts};

    fn event(id: u64) -> Event {
        Event {
            id,
            event: EventKind::ExperimentEnded,
            at_ms: 1_700_000_000_000 + id,
            experiment: Some(ExperimentFacts {
                id: 7,
                submitter: "ana".into(),
                state: "done".into(),
                reasons: vec![],
                outcome: None,
                score: None,
            }),
            robot: None,
        }
    }

    fn push(outbox: &mut Outbox, hook: &str) -> u64 {
        let id = outbox.next_id();
        outbox.push(hook, &event(id)).unwrap();
        id
    }

    fn files(dir: &Path) -> Vec<String> {
        let mut names: Vec<String> =
            std::fs::read_dir(dir).unwrap().map(|e| e.unwrap().file_name().to_string_lossy().into_owned()).collect();
        names.sort();
        names
    }

    #[test]
    fn events_come_back_in_order_after_a_reopen_and_ids_never_repeat() {
        let dir = tempfile::tempdir().unwrap();
        let mut outbox = Outbox::open(dir.path(), 100).unwrap();
        let ids: Vec<u64> = (0..5).map(|_| push(&mut outbox, "http://a/")).collect();
        assert_eq!(ids, [1, 2, 3, 4, 5]);
        outbox.remove(1).unwrap();
        outbox.remove(2).unwrap();
        // Only whole entries and the id counter: no temporary file is left.
        assert_eq!(
            files(dir.path()),
            ["00000000000000000003.json", "00000000000000000004.json", "00000000000000000005.json", "last-id"]
        );
        drop(outbox);
        let mut outbox = Outbox::open(dir.path(), 100).unwrap();
        let mut seen = Vec::new();
        while let Some(entry) = outbox.oldest() {
            assert_eq!(entry.event, event(entry.event.id));
            seen.push(entry.event.id);
            outbox.remove(entry.event.id).unwrap();
        }
        assert_eq!(seen, [3, 4, 5]);
        drop(outbox);
        // Emptied, the outbox still gives ids after the last one.
        let mut outbox = Outbox::open(dir.path(), 100).unwrap();
        assert_eq!(push(&mut outbox, "http://a/"), 6);
    }

    #[test]
    fn a_full_outbox_drops_its_oldest_and_counts_them() {
        let dir = tempfile::tempdir().unwrap();
        let mut outbox = Outbox::open(dir.path(), 3).unwrap();
        for _ in 0..5 {
            push(&mut outbox, "http://a/");
        }
        assert_eq!((outbox.len(), outbox.dropped()), (3, 2));
        assert_eq!(outbox.oldest().unwrap().event.id, 3);
        assert_eq!(files(dir.path()).len(), 4, "three entries and the counter");
    }

    #[test]
    fn an_unreadable_entry_is_left_in_place_and_the_others_are_read() {
        let dir = tempfile::tempdir().unwrap();
        let mut outbox = Outbox::open(dir.path(), 10).unwrap();
        push(&mut outbox, "http://a/");
        push(&mut outbox, "http://a/");
        drop(outbox);
        std::fs::write(dir.path().join("00000000000000000001.json"), b"{ half").unwrap();
        let outbox = Outbox::open(dir.path(), 10).unwrap();
        assert_eq!(outbox.len(), 1);
        assert_eq!(outbox.oldest().unwrap().event.id, 2);
        assert!(dir.path().join("00000000000000000001.json").exists());
    }
}
