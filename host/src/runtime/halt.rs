//! The process-wide list of halt actions: every component that drives
//! motors from outside the process (a serial link's final STOP frame, a ROS 2
//! `cmd_vel` publisher's zero Twist) joins it when it starts, and the exits
//! that cannot wait for the control loop (the panic hook, a second SIGINT or
//! SIGTERM) run every action on it with [`halt_all`].
//!
//! Orderly exits do not need the list: the graph is dropped, and each
//! component sends its last word from its own `Drop`. The list holds weak
//! references, so a component that ended is skipped (and its entry pruned).
//! A halt is final: after it, the component sends nothing more.
//!
//! Invariant: a halt action waits at most the `wait` it is given for its
//! device or session, so a stuck one cannot keep the others from stopping.

use std::sync::{Arc, Mutex, MutexGuard, PoisonError, TryLockError, Weak};
use std::time::{Duration, Instant};

use super::stall::StopOutcome;

/// How often a halt retries a lock another thread holds.
const LOCK_POLL: Duration = Duration::from_millis(1);

/// The final stop of one component, from any thread.
pub trait Halt: Send + Sync {
    /// What is stopped, for the log (`serial link 'motors'`).
    fn label(&self) -> String;
    /// Sends the final stop now, past anything queued, and nothing after
    /// it; waits at most `wait`.
    fn halt(&self, wait: Duration) -> StopOutcome;
    /// Called on every action after all have halted, before the process
    /// exits: pushes out what the halt queued (a network session flushes
    /// and closes), waiting at most `wait`.
    fn settle(&self, wait: Duration) {
        let _ = wait;
    }
}

/// A list of halt actions (weak references).
pub struct HaltList(Mutex<Vec<Weak<dyn Halt>>>);

impl HaltList {
    pub const fn new() -> HaltList {
        HaltList(Mutex::new(Vec::new()))
    }

    /// Adds `action` to the list for as long as it lives.
    pub fn register(&self, action: &Arc<dyn Halt>) {
        let mut live = self.0.lock().unwrap_or_else(PoisonError::into_inner);
        live.retain(|a| a.strong_count() > 0);
        live.push(Arc::downgrade(action));
    }

    /// Runs every live action, each waiting at most `wait`, then lets each
    /// settle. Returns each action's label and outcome, in the order they
    /// joined.
    pub fn halt_all(&self, wait: Duration) -> Vec<(String, StopOutcome)> {
        let actions: Vec<Arc<dyn Halt>> = match lock_within(&self.0, Instant::now() + wait) {
            Some(live) => live.iter().filter_map(Weak::upgrade).collect(),
            None => {
                return vec![(
                    "every motor".into(),
                    StopOutcome::Failed("the list of halt actions stayed locked".into()),
                )];
            }
        };
        let outcomes = actions.iter().map(|a| (a.label(), a.halt(wait))).collect();
        for action in &actions {
            action.settle(wait);
        }
        outcomes
    }
}

impl Default for HaltList {
    fn default() -> HaltList {
        HaltList::new()
    }
}

/// Every halt action alive in this process.
static LIVE: HaltList = HaltList::new();

/// Adds `action` to the process's list for as long as it lives.
pub fn register(action: &Arc<dyn Halt>) {
    LIVE.register(action);
}

/// Runs every live halt action of the process, each waiting at most
/// `wait`: for the panic hook and an exit that cannot wait for the control
/// loop.
pub fn halt_all(wait: Duration) -> Vec<(String, StopOutcome)> {
    LIVE.halt_all(wait)
}

/// Takes `mutex` if it comes free before `deadline`. A poisoned lock is
/// taken all the same: stopping the motors matters more than the panic
/// that poisoned it.
pub fn lock_within<T: ?Sized>(mutex: &Mutex<T>, deadline: Instant) -> Option<MutexGuard<'_, T>> {
    loop {
        match mutex.try_lock() {
            Ok(guard) => return Some(guard),
            Err(TryLockError::Poisoned(poisoned)) => return Some(poisoned.into_inner()),
            Err(TryLockError::WouldBlock) if Instant::now() < deadline => std::thread::sleep(LOCK_POLL),
            Err(TryLockError::WouldBlock) => return None,
        }
    }
}

#[cfg(test)]
mod tests {
    use std::sync::atomic::{AtomicU32, Ordering};

    use super::*;

    /// Counts halts in its first digit and settles in its second; a settle
    /// before the halt would show as 1 in the first.
    struct Counting(AtomicU32, &'static str);

    impl Halt for Counting {
        fn label(&self) -> String {
            self.1.into()
        }
        fn halt(&self, _wait: Duration) -> StopOutcome {
            self.0.fetch_add(10, Ordering::SeqCst);
            StopOutcome::Sent
        }
        fn settle(&self, _wait: Duration) {
            self.0.fetch_add(1, Ordering::SeqCst);
        }
    }

    #[test]
    fn every_live_action_runs_and_ended_ones_are_skipped() {
        let kept = Arc::new(Counting(AtomicU32::new(0), "halt-test-kept"));
        let gone: Arc<dyn Halt> = Arc::new(Counting(AtomicU32::new(0), "halt-test-gone"));
        let list = HaltList::new();
        list.register(&(kept.clone() as Arc<dyn Halt>));
        list.register(&gone);
        drop(gone);
        let ran = list.halt_all(Duration::from_millis(100));
        assert_eq!(ran, vec![("halt-test-kept".to_string(), StopOutcome::Sent)]);
        assert_eq!(kept.0.load(Ordering::SeqCst), 11);
    }
}
