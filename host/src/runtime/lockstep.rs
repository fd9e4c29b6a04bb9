//! Lock-step for simulated time: with a simulated clock
//! ([`Clock::simulated`](super::control_loop::Clock::simulated)) the control
//! loop, each simulated robot and each serial link meet before every cycle,
//! so a run gives the same result for the same inputs however fast it goes.
//!
//! Before the cycle at simulated time `t` ([`Lockstep::before_cycle`]):
//! 1. every link has written every frame the loop handed it
//!    ([`LockstepLink::settle`]);
//! 2. every simulated robot reads exactly the bytes its link wrote, applies
//!    the commands, steps its physics to `t` and writes its feedback
//!    ([`LockstepSim::advance`]);
//! 3. every link has received every byte its robot wrote
//!    ([`LockstepLink::received`]).
//!
//! The bytes still cross the real pseudo-terminal; only the waiting is
//! added. Each wait is bounded by [`LOCKSTEP_WAIT`]: a robot or link that does
//! not answer makes the run lose its determinism (logged), never hang.
//!
//! Import rule: this module knows neither the simulator nor the serial link;
//! they implement its traits and join the registry when they start.

use std::path::Path;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, Weak};
use std::time::{Duration, Instant};

/// Longest one lock-step wait (a link settling, a robot reading its bytes,
/// a link receiving its feedback) holds the loop: a wedged device cannot
/// hang a simulated run; past it the run goes on without the lock-step.
/// A wait ends as soon as the other side is there, so the bound costs
/// nothing when all is well; it is long because a machine whose cores are
/// all busy can keep the link's thread from running for over 500 ms (seen
/// with both cores loaded and several hosts running), and a run must stay
/// deterministic on a busy machine.
pub const LOCKSTEP_WAIT: Duration = Duration::from_secs(5);
/// How often a lock-step wait looks again.
pub const LOCKSTEP_POLL: Duration = Duration::from_micros(20);

/// How fast simulated time goes.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Pace {
    /// This many simulated seconds per real second (when the CPU keeps up).
    Speed(f64),
    /// As fast as the CPU allows.
    Lockstep,
}

impl std::fmt::Display for Pace {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Pace::Speed(speed) => write!(f, "{speed}x real time"),
            Pace::Lockstep => f.write_str("lock-step (as fast as the CPU allows)"),
        }
    }
}

/// Fastest multiple of real time `--speed` accepts; beyond it, ask for
/// `max` (lock-step without pacing).
pub const MAX_SPEED: f64 = 10_000.0;

/// Why a pace did not parse.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[error("--speed must be a number of times real time (more than 0, at most {MAX_SPEED}) or 'max', got '{0}'")]
pub struct PaceError(String);

impl std::str::FromStr for Pace {
    type Err = PaceError;

    fn from_str(text: &str) -> Result<Pace, PaceError> {
        if text.trim() == "max" {
            return Ok(Pace::Lockstep);
        }
        match text.trim().parse::<f64>() {
            Ok(speed) if speed.is_finite() && speed > 0.0 && speed <= MAX_SPEED => Ok(Pace::Speed(speed)),
            _ => Err(PaceError(crate::contract::clip(text))),
        }
    }
}

/// A serial link's side of the lock-step.
pub trait LockstepLink: Send + Sync {
    /// The device the link writes to.
    fn device(&self) -> &Path;
    /// Waits until the device is open and every frame handed to the link has
    /// been written (or discarded); false when `deadline` passed first.
    fn settle(&self, deadline: Instant) -> bool;
    /// Bytes written to the device (frames, openings, STOPs) since the last
    /// call.
    fn take_written(&self) -> u64;
    /// The robot wrote `bytes` more for this link to receive.
    fn expect(&self, bytes: u64);
    /// Waits until every byte expected has been received from the device
    /// and handed to the loop; false when `deadline` passed first.
    fn received(&self, deadline: Instant) -> bool;
}

/// A simulated robot's side of the lock-step.
pub trait LockstepSim: Send + Sync {
    /// The pseudo-terminal end its link opens.
    fn device(&self) -> &Path;
    /// Reads `bytes_in` more bytes (or what arrives before `deadline`),
    /// applies the commands, steps to simulated time `to_ns`, writes the
    /// feedback that is due; returns how many bytes it wrote.
    fn advance(&self, to_ns: u64, bytes_in: u64, deadline: Instant) -> u64;
}

/// The participants of one simulated clock. Each holds itself: the
/// registry keeps weak references, so a component that is dropped leaves.
#[derive(Default)]
pub struct Lockstep {
    links: Mutex<Vec<Weak<dyn LockstepLink>>>,
    sims: Mutex<Vec<Weak<dyn LockstepSim>>>,
    /// Waits that ran out (the run lost its determinism there).
    timeouts: AtomicU64,
}

impl std::fmt::Debug for Lockstep {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Lockstep({} timeouts)", self.timeouts())
    }
}

impl Lockstep {
    pub fn join_link(&self, link: &Arc<dyn LockstepLink>) {
        if let Ok(mut links) = self.links.lock() {
            links.retain(|l| l.strong_count() > 0);
            links.push(Arc::downgrade(link));
        }
    }

    pub fn join_sim(&self, sim: &Arc<dyn LockstepSim>) {
        if let Ok(mut sims) = self.sims.lock() {
            sims.retain(|s| s.strong_count() > 0);
            sims.push(Arc::downgrade(sim));
        }
    }

    /// Lock-step waits that ran out since the start.
    pub fn timeouts(&self) -> u64 {
        self.timeouts.load(Ordering::Relaxed)
    }

    fn timed_out(&self, what: &str, device: &Path) {
        if self.timeouts.fetch_add(1, Ordering::Relaxed) == 0 {
            tracing::warn!(
                "lock-step: {what} on {} took longer than {} ms; this run is no longer deterministic",
                device.display(),
                LOCKSTEP_WAIT.as_millis()
            );
        }
    }

    /// Brings every simulated robot and its link to simulated time `now_ns`
    /// (see the module's docs).
    pub fn before_cycle(&self, now_ns: u64) {
        let links: Vec<Arc<dyn LockstepLink>> =
            self.links.lock().map(|l| l.iter().filter_map(Weak::upgrade).collect()).unwrap_or_default();
        let sims: Vec<Arc<dyn LockstepSim>> =
            self.sims.lock().map(|s| s.iter().filter_map(Weak::upgrade).collect()).unwrap_or_default();
        for link in &links {
            if !link.settle(Instant::now() + LOCKSTEP_WAIT) {
                self.timed_out("writing the frames", link.device());
            }
        }
        for sim in &sims {
            let talking: Vec<&Arc<dyn LockstepLink>> = links.iter().filter(|l| l.device() == sim.device()).collect();
            let bytes_in = talking.iter().map(|l| l.take_written()).sum();
            let out = sim.advance(now_ns, bytes_in, Instant::now() + LOCKSTEP_WAIT);
            for link in talking {
                link.expect(out);
            }
        }
        for link in &links {
            if !link.received(Instant::now() + LOCKSTEP_WAIT) {
                self.timed_out("receiving the feedback", link.device());
            }
        }
    }
}

/// Polls `done` until it holds or `deadline` passes.
pub fn wait_until(deadline: Instant, mut done: impl FnMut() -> bool) -> bool {
    let mut spins = 0u32;
    loop {
        if done() {
            return true;
        }
        if Instant::now() >= deadline {
            return false;
        }
        // A few yields first: the other side is usually a moment away.
        if spins < 50 {
            spins += 1;
            std::thread::yield_now();
        } else {
            std::thread::sleep(LOCKSTEP_POLL);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_pace_is_a_speed_or_max() {
        assert_eq!("4".parse::<Pace>(), Ok(Pace::Speed(4.0)));
        assert_eq!("0.5".parse::<Pace>(), Ok(Pace::Speed(0.5)));
        assert_eq!("max".parse::<Pace>(), Ok(Pace::Lockstep));
        for bad in ["0", "-1", "nan", "inf", "20000", "fast", ""] {
            let error = bad.parse::<Pace>().map(|_| ()).unwrap_err().to_string();
            assert!(error.starts_with("--speed must be"), "{bad}: {error}");
        }
    }
}
