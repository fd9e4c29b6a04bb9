//! Cranelift's incremental compilation cache, kept on disk in the host's
//! private cache folder: compiled functions keyed by their contents
//! (`wasmtime::CacheStore`). A rebuilt component whose bytes changed (a new
//! sha256, so the whole-component cache in `cache.rs` misses) but whose
//! functions mostly did not (a componentize-py component after an edit of
//! the Python source: the interpreter is the same, the snapshot of the
//! user's code is data) compiles only the functions that changed.
//!
//! Invariants: an entry is one file `functions/<hex sha256 of the key>`
//! holding the sha256 of its value followed by the value; it is written to a
//! temporary file and renamed into place (a reader never sees half an
//! entry); an entry whose checksum does not match, or that is larger than
//! [`MAX_FUNCTION_ENTRY_BYTES`], is ignored (the function is compiled
//! again); the folder is kept under [`MAX_FUNCTION_CACHE_BYTES`] by removing
//! the oldest entries after a compile. Like the component cache, the folder
//! is this host's own (mode 0700) and only compiled output is written there:
//! bytes from outside are never stored as entries.

use std::borrow::Cow;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};

use sha2::{Digest, Sha256};

/// Total size of the function cache folder. Threat: uploads of ever-new
/// components (each compile stores its functions) filling the disk. Past
/// it, the oldest entries are removed down to [`FUNCTION_CACHE_PRUNE_TO`].
pub const MAX_FUNCTION_CACHE_BYTES: u64 = 1 << 30;
/// What the folder is pruned down to once it passes the limit (so pruning,
/// a scan of the folder, is not repeated after every compile).
pub const FUNCTION_CACHE_PRUNE_TO: u64 = MAX_FUNCTION_CACHE_BYTES / 4 * 3;
/// Largest entry stored or read. Threat: a component with one huge function
/// making the cache read (into memory) or write an outsized file; such a
/// function is simply compiled each time.
pub const MAX_FUNCTION_ENTRY_BYTES: u64 = 16 << 20;

/// Bytes of the checksum in front of each entry's value.
const CHECKSUM_BYTES: usize = 32;

/// Counters of what the cache served, since the process started.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct FunctionCacheStats {
    /// Functions served from the cache.
    pub hits: u64,
    /// Functions looked up and not found (or found unusable): compiled.
    pub misses: u64,
    /// Entries written.
    pub stored: u64,
}

/// The on-disk function cache.
#[derive(Debug)]
pub struct FunctionCache {
    dir: PathBuf,
    /// Bytes in the folder as far as this process knows (scanned at start,
    /// grown by each write, rescanned when pruning).
    bytes: AtomicU64,
    hits: AtomicU64,
    misses: AtomicU64,
    stored: AtomicU64,
}

impl FunctionCache {
    /// The cache in `dir` (created private when missing).
    pub fn open(dir: PathBuf) -> std::io::Result<FunctionCache> {
        use std::os::unix::fs::DirBuilderExt;
        std::fs::DirBuilder::new().recursive(true).mode(0o700).create(&dir)?;
        let bytes = entries(&dir).iter().map(|e| e.len).sum();
        Ok(FunctionCache {
            dir,
            bytes: AtomicU64::new(bytes),
            hits: AtomicU64::new(0),
            misses: AtomicU64::new(0),
            stored: AtomicU64::new(0),
        })
    }

    pub fn stats(&self) -> FunctionCacheStats {
        FunctionCacheStats {
            hits: self.hits.load(Ordering::Relaxed),
            misses: self.misses.load(Ordering::Relaxed),
            stored: self.stored.load(Ordering::Relaxed),
        }
    }

    fn path(&self, key: &[u8]) -> PathBuf {
        self.dir.join(hex::encode(Sha256::digest(key)))
    }

    fn read(&self, key: &[u8]) -> Option<Vec<u8>> {
        let path = self.path(key);
        let len = std::fs::metadata(&path).ok()?.len();
        if len > MAX_FUNCTION_ENTRY_BYTES + CHECKSUM_BYTES as u64 {
            return None;
        }
        let mut entry = std::fs::read(&path).ok()?;
        if entry.len() < CHECKSUM_BYTES {
            tracing::debug!("ignoring truncated function cache entry {}", path.display());
            return None;
        }
        let value = entry.split_off(CHECKSUM_BYTES);
        if Sha256::digest(&value).as_slice() != entry.as_slice() {
            tracing::debug!("ignoring function cache entry {} (checksum mismatch)", path.display());
            return None;
        }
        Some(value)
    }

    fn write(&self, key: &[u8], value: &[u8]) -> std::io::Result<()> {
        let mut file = tempfile::NamedTempFile::new_in(&self.dir)?;
        file.write_all(&Sha256::digest(value))?;
        file.write_all(value)?;
        // No fsync: an entry lost or torn by a crash fails its checksum
        // and is compiled again; the rename keeps readers from half entries.
        file.persist(self.path(key)).map_err(|e| e.error)?;
        Ok(())
    }

    /// Removes the oldest entries once the folder has passed
    /// [`MAX_FUNCTION_CACHE_BYTES`], down to [`FUNCTION_CACHE_PRUNE_TO`].
    pub fn prune(&self) {
        self.prune_to(MAX_FUNCTION_CACHE_BYTES, FUNCTION_CACHE_PRUNE_TO);
    }

    fn prune_to(&self, limit: u64, target: u64) {
        if self.bytes.load(Ordering::Relaxed) <= limit {
            return;
        }
        let mut found = entries(&self.dir);
        let mut total: u64 = found.iter().map(|e| e.len).sum();
        found.sort_by_key(|e| e.modified);
        let mut removed = 0usize;
        for entry in found {
            if total <= target {
                break;
            }
            if std::fs::remove_file(&entry.path).is_ok() {
                total = total.saturating_sub(entry.len);
                removed += 1;
            }
        }
        self.bytes.store(total, Ordering::Relaxed);
        tracing::info!("function cache: removed {removed} oldest entries, {} MiB left", total >> 20);
    }
}

impl wasmtime::CacheStore for FunctionCache {
    fn get(&self, key: &[u8]) -> Option<Cow<'_, [u8]>> {
        match self.read(key) {
            Some(value) => {
                self.hits.fetch_add(1, Ordering::Relaxed);
                Some(Cow::Owned(value))
            }
            None => {
                self.misses.fetch_add(1, Ordering::Relaxed);
                None
            }
        }
    }

    fn insert(&self, key: &[u8], value: Vec<u8>) -> bool {
        if value.len() as u64 > MAX_FUNCTION_ENTRY_BYTES {
            return false;
        }
        match self.write(key, &value) {
            Ok(()) => {
                self.bytes.fetch_add((value.len() + CHECKSUM_BYTES) as u64, Ordering::Relaxed);
                self.stored.fetch_add(1, Ordering::Relaxed);
                true
            }
            Err(err) => {
                tracing::debug!("cannot write function cache entry: {err}");
                false
            }
        }
    }
}

struct Entry {
    path: PathBuf,
    len: u64,
    modified: std::time::SystemTime,
}

/// The entry files in `dir` (temporary files of writes under way excluded).
fn entries(dir: &Path) -> Vec<Entry> {
    let Ok(read) = std::fs::read_dir(dir) else { return Vec::new() };
    read.filter_map(|e| {
        let e = e.ok()?;
        let name = e.file_name();
        let name = name.to_str()?;
        if name.len() != 64 || !name.bytes().all(|b| b.is_ascii_hexdigit()) {
            return None;
        }
        let meta = e.metadata().ok()?;
        meta.is_file().then(|| Entry {
            path: e.path(),
            len: meta.len(),
            modified: meta.modified().unwrap_or(std::time::UNIX_EPOCH),
        })
    })
    .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use wasmtime::CacheStore;

    #[test]
    fn an_entry_comes_back_and_a_corrupt_one_is_ignored() -> std::io::Result<()> {
        let dir = tempfile::tempdir()?;
        let cache = FunctionCache::open(dir.path().join("functions"))?;
        assert!(cache.get(b"key").is_none());
        assert!(cache.insert(b"key", b"compiled code".to_vec()));
        assert_eq!(cache.get(b"key").as_deref(), Some(&b"compiled code"[..]));
        assert_eq!(cache.stats(), FunctionCacheStats { hits: 1, misses: 1, stored: 1 });
        // One bit flipped in the value: ignored, counted as a miss.
        let path = cache.path(b"key");
        let mut bytes = std::fs::read(&path)?;
        if let Some(last) = bytes.last_mut() {
            *last ^= 1;
        }
        std::fs::write(&path, &bytes)?;
        assert!(cache.get(b"key").is_none());
        // Truncated below the checksum: ignored too.
        std::fs::write(&path, b"short")?;
        assert!(cache.get(b"key").is_none());
        assert_eq!(cache.stats().misses, 3);
        // Written again, it is served again; no temporary file is left.
        assert!(cache.insert(b"key", b"compiled code".to_vec()));
        assert_eq!(cache.get(b"key").as_deref(), Some(&b"compiled code"[..]));
        assert_eq!(std::fs::read_dir(dir.path().join("functions"))?.count(), 1);
        Ok(())
    }

    #[test]
    fn an_oversized_entry_is_neither_stored_nor_read() -> std::io::Result<()> {
        let dir = tempfile::tempdir()?;
        let cache = FunctionCache::open(dir.path().to_path_buf())?;
        let huge = vec![0u8; (MAX_FUNCTION_ENTRY_BYTES + 1) as usize];
        assert!(!cache.insert(b"big", huge.clone()));
        // Planted from outside the cache's own writes: not read.
        let mut planted = Sha256::digest(&huge).to_vec();
        planted.extend_from_slice(&huge);
        std::fs::write(cache.path(b"big"), planted)?;
        assert!(cache.get(b"big").is_none());
        Ok(())
    }

    #[test]
    fn past_the_limit_the_oldest_entries_go_first() -> std::io::Result<()> {
        let dir = tempfile::tempdir()?;
        let cache = FunctionCache::open(dir.path().to_path_buf())?;
        let old = std::time::SystemTime::now() - std::time::Duration::from_secs(3600);
        for i in 0..10u8 {
            assert!(cache.insert(&[i], vec![i; 68]));
            // Entry i is i minutes newer than the first.
            let file = std::fs::File::options().write(true).open(cache.path(&[i]))?;
            file.set_modified(old + std::time::Duration::from_secs(60 * u64::from(i)))?;
        }
        // Ten entries of 100 bytes: under a limit of 1000 nothing goes.
        cache.prune_to(1000, 500);
        assert_eq!(entries(dir.path()).len(), 10);
        cache.prune_to(999, 500);
        let kept: Vec<bool> = (0..10u8).map(|i| cache.path(&[i]).is_file()).collect();
        assert_eq!(kept, [false, false, false, false, false, true, true, true, true, true]);
        // The count starts from what is on disk when the cache is opened.
        let reopened = FunctionCache::open(dir.path().to_path_buf())?;
        assert_eq!(reopened.bytes.load(Ordering::Relaxed), 500);
        Ok(())
    }
}
