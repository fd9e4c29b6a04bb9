//! The stall watchdog: a thread outside the control loop that sees a loop
//! which has stopped cycling, stops the motors without waiting for it, and
//! names the call that holds it.
//!
//! The graph publishes a [`Heartbeat`]: one word saying which component and
//! which call runs now (or that the loop sleeps), rewritten before every
//! call (one relaxed store; the hot path pays nothing else). The
//! [`StallWatchdog`] samples it every quarter of the limit. When the same
//! call has been running for the whole limit, and the watchdog saw it at
//! every sample of it, it marks that call stalled
//! (the graph faults the component when the call returns, and discards what
//! it emitted), asks every [`MotorStop`] the graph holds to send its stop
//! frame now (the serial link writes it from this thread, past the loop's
//! queue), and logs the stall with the component and the call.
//!
//! Counting samples, not only the clock, keeps the watchdog of a process
//! that was frozen as a whole (stopped, or starved of every CPU: a preflight
//! at idle priority on a busy robot) from declaring the call it happened to
//! be in: the watchdog was frozen too, and wakes to a call that then has to
//! hold the loop for a whole limit more, with the watchdog watching, to be
//! a stall. On simulated time that is the only judge
//! ([`Heartbeat::on_simulated_time`]); on real time the graph also faults a
//! call that took the limit on the wall clock, after it returns.
//!
//! Invariants: the watchdog never touches the graph, only the heartbeat and
//! the motor stops the graph handed it; a stall is declared no sooner than
//! `limit` after the call began, and one sampling period (`limit / 4`)
//! later at most, plus however long the watchdog thread waits for a CPU;
//! the loop sleeping is never a stall.

use std::fmt;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Condvar, Mutex, PoisonError};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

/// Shortest stall limit: below a few milliseconds, an ordinary scheduling
/// delay of the control thread would fault the component it was calling.
pub const MIN_STALL_LIMIT: Duration = Duration::from_millis(10);
/// Longest stall limit: a loop stuck longer than this leaves the motors on
/// their last command for too long (the serial link's own watchdog bound).
pub const MAX_STALL_LIMIT: Duration = Duration::from_secs(10);
/// The default: the "a stall longer than 100 ms", ten cycles of a
/// 100 Hz link, twenty times the default 5 ms guest budget.
pub const DEFAULT_STALL_LIMIT: Duration = Duration::from_millis(100);
/// How long the watchdog waits for one link to take its stop frame: the
/// link's writer holds the device for at most one frame.
pub const STOP_WAIT: Duration = Duration::from_millis(200);

/// What the control thread is doing, as the heartbeat says.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[repr(u8)]
pub enum Activity {
    /// Waiting for the next tick (or the loop has ended): never a stall.
    Asleep = 0,
    /// Between calls: the cycle hook (graph swap, live status), routing.
    Cycle = 1,
    Tick = 2,
    OnInput = 3,
    Poll = 4,
    /// Building a fresh instance after a fault (`init` runs).
    Restart = 5,
    PeerFaulted = 6,
    PeerRestarted = 7,
}

impl Activity {
    fn from_bits(bits: u8) -> Activity {
        match bits {
            1 => Activity::Cycle,
            2 => Activity::Tick,
            3 => Activity::OnInput,
            4 => Activity::Poll,
            5 => Activity::Restart,
            6 => Activity::PeerFaulted,
            7 => Activity::PeerRestarted,
            _ => Activity::Asleep,
        }
    }

    /// The call's name as the contract and the logs spell it.
    pub fn name(self) -> &'static str {
        match self {
            Activity::Asleep => "asleep",
            Activity::Cycle => "the cycle between calls",
            Activity::Tick => "tick",
            Activity::OnInput => "on-input",
            Activity::Poll => "poll",
            Activity::Restart => "restart (init)",
            Activity::PeerFaulted => "peer-faulted",
            Activity::PeerRestarted => "peer-restarted",
        }
    }
}

/// No component: the loop itself (sleeping, or between calls).
const NO_NODE: u32 = 0x00FF_FFFF;

/// One heartbeat word: `seq` (32 bits) | node (24 bits) | activity (8 bits).
/// `seq` changes on every write, so an unchanged word means no progress.
fn pack(seq: u32, node: u32, activity: Activity) -> u64 {
    (u64::from(seq) << 32) | (u64::from(node & NO_NODE) << 8) | activity as u64
}

fn unpack(word: u64) -> (Option<usize>, Activity) {
    let node = ((word >> 8) as u32) & NO_NODE;
    (if node == NO_NODE { None } else { Some(node as usize) }, Activity::from_bits(word as u8))
}

/// Stops a device's motors from any thread, without the control loop.
pub trait MotorStop: Send + Sync {
    /// The component that owns the device (for the log).
    fn name(&self) -> &str;
    /// Sends the stop frame now, ahead of anything the loop queued, and
    /// flushes it to the device; waits at most `wait` for the device.
    /// Commands the loop sends afterwards still go out.
    fn stop_now(&self, wait: Duration) -> StopOutcome;
}

/// What became of a request to stop the motors.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum StopOutcome {
    /// The stop frame was written and drained to the device.
    Sent,
    /// The device is not open (lost, or never opened): the motors are
    /// treated as stopped; nothing could be written.
    NotConnected,
    /// The link has ended already and sent its final stop.
    Closed,
    /// The device did not take the frame.
    Failed(String),
}

impl fmt::Display for StopOutcome {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            StopOutcome::Sent => f.write_str("STOP sent"),
            StopOutcome::NotConnected => f.write_str("device not connected (treated as stopped)"),
            StopOutcome::Closed => f.write_str("link closed after its final STOP"),
            StopOutcome::Failed(why) => write!(f, "STOP failed: {why}"),
        }
    }
}

/// What the graph attached to a heartbeat tells the watchdog.
#[derive(Default)]
struct Attached {
    names: Vec<Arc<str>>,
    stops: Vec<Arc<dyn MotorStop>>,
}

/// The control loop's pulse, shared by the graph (writer) and the
/// [`StallWatchdog`] (reader).
pub struct Heartbeat {
    word: AtomicU64,
    /// The word the watchdog declared stalled (0: none).
    verdict: AtomicU64,
    limit: Duration,
    /// Whether the graph also faults a call that held the loop for the
    /// limit on the wall clock though the watchdog never declared it (it
    /// may have been late). Not on simulated time: there a call's wall time
    /// says how busy the machine was, not what the call did, and the same
    /// inputs must give the same results.
    judge_after: bool,
    attached: Mutex<Attached>,
}

impl fmt::Debug for Heartbeat {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("Heartbeat").field("limit", &self.limit).finish_non_exhaustive()
    }
}

impl Heartbeat {
    /// A heartbeat whose loop stalls when one call runs for `limit`.
    pub fn new(limit: Duration) -> Arc<Heartbeat> {
        Heartbeat::judging_after(limit, true)
    }

    /// The heartbeat of a loop on simulated time: only the watchdog's own
    /// verdict faults a call (see [`Heartbeat::after_the_call`]).
    pub fn on_simulated_time(limit: Duration) -> Arc<Heartbeat> {
        Heartbeat::judging_after(limit, false)
    }

    fn judging_after(limit: Duration, judge_after: bool) -> Arc<Heartbeat> {
        Arc::new(Heartbeat {
            word: AtomicU64::new(pack(0, NO_NODE, Activity::Asleep)),
            verdict: AtomicU64::new(0),
            limit,
            judge_after,
            attached: Mutex::new(Attached::default()),
        })
    }

    /// Whether a call that held the loop for `held` (wall clock, measured
    /// by the graph when it returned) is a stall the watchdog missed: on
    /// real time when `held` reached the limit, never on simulated time.
    pub fn after_the_call(&self, held: Duration) -> bool {
        self.judge_after && held >= self.limit
    }

    /// The stall limit.
    pub fn limit(&self) -> Duration {
        self.limit
    }

    /// Publishes what the loop does now (the graph's writer side).
    #[inline]
    pub(super) fn beat(&self, seq: u32, node: Option<usize>, activity: Activity) -> u64 {
        let node = node.map_or(NO_NODE, |n| u32::try_from(n).unwrap_or(NO_NODE).min(NO_NODE - 1));
        let word = pack(seq, node, activity);
        self.word.store(word, Ordering::Release);
        word
    }

    /// The sequence number of the word published last (a newly attached
    /// graph goes on from it, so no word repeats across an activation).
    pub(super) fn last_seq(&self) -> u32 {
        (self.word.load(Ordering::Acquire) >> 32) as u32
    }

    /// Whether the watchdog declared the call published as `word` stalled.
    #[inline]
    pub(super) fn stalled(&self, word: u64) -> bool {
        self.verdict.load(Ordering::Acquire) == word
    }

    /// The graph's components and the motor stops they hold.
    pub(super) fn attach(&self, names: Vec<Arc<str>>, stops: Vec<Arc<dyn MotorStop>>) {
        let mut attached = self.attached.lock().unwrap_or_else(PoisonError::into_inner);
        *attached = Attached { names, stops };
    }
}

/// Counters of a watchdog.
#[derive(Debug, Default)]
struct WatchStats {
    stalls: AtomicU64,
}

/// One stall as the watchdog saw it.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Stall {
    /// The component being called, if the loop was in a component.
    pub component: Option<String>,
    pub call: &'static str,
    /// How long the call had been running when the stall was declared.
    pub held: Duration,
    /// Each motor stop and what became of it.
    pub stops: Vec<(String, StopOutcome)>,
}

impl fmt::Display for Stall {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match &self.component {
            Some(name) => write!(f, "'{name}' {} has not returned for {} ms", self.call, self.held.as_millis())?,
            None => write!(f, "{} has not ended for {} ms", self.call, self.held.as_millis())?,
        }
        if self.stops.is_empty() {
            f.write_str("; no motors to stop")
        } else {
            let stops: Vec<String> = self.stops.iter().map(|(name, outcome)| format!("'{name}': {outcome}")).collect();
            write!(f, "; motors: {}", stops.join(", "))
        }
    }
}

/// The watchdog thread: see the module's docs. Stops when dropped.
pub struct StallWatchdog {
    stop: Arc<(Mutex<bool>, Condvar)>,
    stats: Arc<WatchStats>,
    thread: Option<JoinHandle<()>>,
}

impl StallWatchdog {
    /// Starts watching `heartbeat`; `on_stall` hears about each stall after
    /// the motors were told to stop (the binary only logs; tests and
    /// benches take the time).
    pub fn start(heartbeat: Arc<Heartbeat>, on_stall: Box<dyn Fn(&Stall) + Send>) -> std::io::Result<StallWatchdog> {
        let stop = Arc::new((Mutex::new(false), Condvar::new()));
        let stats = Arc::new(WatchStats::default());
        let thread = {
            let (stop, stats) = (stop.clone(), stats.clone());
            std::thread::Builder::new()
                .name("subsume-stall-watchdog".into())
                .spawn(move || watch(&heartbeat, &stop, &stats, &*on_stall))?
        };
        Ok(StallWatchdog { stop, stats, thread: Some(thread) })
    }

    /// Stalls seen so far.
    pub fn stalls(&self) -> u64 {
        self.stats.stalls.load(Ordering::Relaxed)
    }
}

impl Drop for StallWatchdog {
    fn drop(&mut self) {
        let (stopped, wake) = &*self.stop;
        *stopped.lock().unwrap_or_else(PoisonError::into_inner) = true;
        wake.notify_all();
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
    }
}

/// Sleeps `period`; true when the watchdog is told to stop.
fn sleep(stop: &(Mutex<bool>, Condvar), period: Duration) -> bool {
    let (stopped, wake) = stop;
    let guard = stopped.lock().unwrap_or_else(PoisonError::into_inner);
    match wake.wait_timeout_while(guard, period, |stopped| !*stopped) {
        Ok((stopped, _)) => *stopped,
        Err(poisoned) => *poisoned.into_inner().0,
    }
}

/// Samples of one call, after the first, that make a stall: one limit of
/// watching at the sampling period (`limit / SAMPLES_PER_LIMIT`).
const SAMPLES_PER_LIMIT: u32 = 4;

fn watch(heartbeat: &Heartbeat, stop: &(Mutex<bool>, Condvar), stats: &WatchStats, on_stall: &dyn Fn(&Stall)) {
    let period = (heartbeat.limit / SAMPLES_PER_LIMIT).max(Duration::from_millis(1));
    // The word last seen, when it was first seen, how many samples saw it
    // since, and whether it stalled.
    let mut seen: Option<(u64, Instant, u32, bool)> = None;
    while !sleep(stop, period) {
        let word = heartbeat.word.load(Ordering::Acquire);
        let (node, activity) = unpack(word);
        if activity == Activity::Asleep {
            if let Some((_, since, _, true)) = seen {
                heartbeat.verdict.store(0, Ordering::Release);
                tracing::warn!("the control loop is moving again after {} ms", since.elapsed().as_millis());
            }
            seen = None;
            continue;
        }
        match seen {
            Some((last, since, samples, stalled)) if last == word => {
                let held = since.elapsed();
                let samples = samples + 1;
                seen = Some((word, since, samples, stalled));
                if !stalled && held >= heartbeat.limit && samples >= SAMPLES_PER_LIMIT {
                    seen = Some((word, since, samples, true));
                    stats.stalls.fetch_add(1, Ordering::Relaxed);
                    let stall = declare(heartbeat, word, node, activity, held);
                    tracing::error!("the control loop is stalled: {stall}");
                    on_stall(&stall);
                }
            }
            _ => {
                if let Some((_, since, _, true)) = seen {
                    // The graph read the verdict before it moved on.
                    heartbeat.verdict.store(0, Ordering::Release);
                    tracing::warn!("the control loop is moving again after {} ms", since.elapsed().as_millis());
                }
                seen = Some((word, Instant::now(), 0, false));
            }
        }
    }
}

/// Marks `word` stalled (the graph faults the call when it returns), then
/// stops every motor.
fn declare(heartbeat: &Heartbeat, word: u64, node: Option<usize>, activity: Activity, held: Duration) -> Stall {
    heartbeat.verdict.store(word, Ordering::Release);
    let (component, stops) = {
        let attached = heartbeat.attached.lock().unwrap_or_else(PoisonError::into_inner);
        let name = node.and_then(|n| attached.names.get(n)).map(|n| n.to_string());
        (name, attached.stops.clone())
    };
    let stops = stops.iter().map(|stop| (stop.name().to_string(), stop.stop_now(STOP_WAIT))).collect();
    Stall { component, call: activity.name(), held, stops }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn words_carry_the_component_and_the_call() {
        for (node, activity) in [(Some(0), Activity::Tick), (Some(63), Activity::OnInput), (None, Activity::Cycle)] {
            let word = pack(7, node.map_or(NO_NODE, |n| n as u32), activity);
            assert_eq!(unpack(word), (node, activity));
            assert_ne!(word, pack(8, node.map_or(NO_NODE, |n| n as u32), activity), "seq changes the word");
        }
    }
}
