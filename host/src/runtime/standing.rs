//! How each motion source stands in its arbiter (`Standing`), and the
//! host's board of them (`Standings`), which the network platform reads to
//! tell its operator. Pure (std only): the teleop protocol, which the fuzz
//! targets compile on their own, names `Standing`.

/// How one motion source stands in its arbiter, as last decided.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Standing {
    /// The source has sent nothing within its timeout (or has faulted).
    Idle,
    /// The source's commands reach the motors.
    Holds,
    /// The source is active, but `by` (at `priority`) holds control.
    Suppressed { by: String, priority: i32 },
}

/// The standings of motion sources, by source name: arbiters write a
/// source's standing when it changes; the sources that answer to a person
/// (the network platform) read their own and tell the operator. One per
/// host, so a platform carried across an activation keeps reading the
/// arbiter of the set that runs now.
#[derive(Clone, Debug, Default)]
pub struct Standings {
    by_name: std::sync::Arc<std::sync::Mutex<std::collections::HashMap<String, Standing>>>,
    /// Bumped on every write, so a reader checks for news with one load.
    generation: std::sync::Arc<std::sync::atomic::AtomicU64>,
}

impl Standings {
    /// Records `standing` for `source`.
    pub fn set(&self, source: &str, standing: Standing) {
        if let Ok(mut by_name) = self.by_name.lock() {
            by_name.insert(source.to_string(), standing);
            self.generation.fetch_add(1, std::sync::atomic::Ordering::Release);
        }
    }

    /// `source`'s standing (idle when no arbiter has written it).
    pub fn get(&self, source: &str) -> Standing {
        self.by_name.lock().ok().and_then(|m| m.get(source).cloned()).unwrap_or(Standing::Idle)
    }

    /// Changes with every write.
    pub fn generation(&self) -> u64 {
        self.generation.load(std::sync::atomic::Ordering::Acquire)
    }
}
