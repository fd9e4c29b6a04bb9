//! The control loop: reads the clock, steps the graph, sleeps until the next
//! tick is due or a shutdown is asked for. It runs on its own thread; nothing
//! else calls into components. On a simulated clock ([`Clock::simulated`])
//! it jumps from one due cycle to the next instead of sleeping (paced to a
//! multiple of real time, or not at all), and holds the simulated robots and
//! their links in lock-step before each cycle ([`super::lockstep`]).

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Condvar, Mutex};
use std::time::{Duration, Instant};

use super::Graph;
use super::cpu_wait::{READ_INTERVAL, thread_run_delay_ns};
use super::lockstep::{Lockstep, Pace};
use super::stall::{Activity, Heartbeat};

/// Longest sleep when no component ticks: the loop still notices a shutdown
/// at once (the condvar wakes it), this only bounds idle wake-ups.
pub const IDLE_WAIT: Duration = Duration::from_millis(100);

/// The host's monotonic clock: nanoseconds since it was made; or, made
/// with [`Clock::simulated`], simulated nanoseconds that only the control
/// loop moves.
#[derive(Clone, Debug)]
pub struct Clock {
    start: Instant,
    simulated: Option<Arc<Simulated>>,
}

/// The state of a simulated clock.
#[derive(Debug)]
struct Simulated {
    now_ns: AtomicU64,
    pace: Pace,
    lockstep: Arc<Lockstep>,
}

impl Default for Clock {
    fn default() -> Self {
        Clock::new()
    }
}

impl Clock {
    pub fn new() -> Clock {
        Clock { start: Instant::now(), simulated: None }
    }

    /// A simulated clock at 0, advanced by the control loop from one due
    /// cycle to the next at `pace`.
    pub fn simulated(pace: Pace) -> Clock {
        let simulated = Simulated { now_ns: AtomicU64::new(0), pace, lockstep: Arc::new(Lockstep::default()) };
        Clock { start: Instant::now(), simulated: Some(Arc::new(simulated)) }
    }

    pub fn now_ns(&self) -> u64 {
        match &self.simulated {
            Some(simulated) => simulated.now_ns.load(Ordering::Acquire),
            None => self.start.elapsed().as_nanos() as u64,
        }
    }

    /// The lock-step registry of a simulated clock: simulated robots and
    /// serial links join it so the loop can hold them in step.
    pub fn lockstep(&self) -> Option<&Arc<Lockstep>> {
        self.simulated.as_ref().map(|s| &s.lockstep)
    }

    /// The pace of a simulated clock.
    pub fn pace(&self) -> Option<Pace> {
        self.simulated.as_ref().map(|s| s.pace)
    }
}

/// Why the loop stopped.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum StopReason {
    /// The requested duration passed.
    Duration,
    /// Someone asked for a shutdown (SIGINT, SIGTERM, the caller).
    Requested,
}

impl StopReason {
    pub fn name(self) -> &'static str {
        match self {
            StopReason::Duration => "duration",
            StopReason::Requested => "shutdown",
        }
    }
}

#[derive(Debug, Default)]
struct Signals {
    shutdown: bool,
    wake: bool,
}

/// A shutdown request shared between signal handlers and the loop; it also
/// hands out [`Waker`]s.
#[derive(Clone, Debug, Default)]
pub struct Shutdown {
    inner: Arc<(Mutex<Signals>, Condvar)>,
}

/// Wakes the control loop early (input arrived from outside the graph).
#[derive(Clone, Debug, Default)]
pub struct Waker {
    inner: Arc<(Mutex<Signals>, Condvar)>,
}

impl Waker {
    pub fn wake(&self) {
        let (signals, wake) = &*self.inner;
        if let Ok(mut signals) = signals.lock() {
            signals.wake = true;
        }
        wake.notify_all();
    }
}

impl Shutdown {
    pub fn new() -> Shutdown {
        Shutdown::default()
    }

    /// Asks the loop to stop; wakes it if it sleeps.
    pub fn request(&self) {
        let (signals, wake) = &*self.inner;
        if let Ok(mut signals) = signals.lock() {
            signals.shutdown = true;
        }
        wake.notify_all();
    }

    pub fn is_requested(&self) -> bool {
        self.inner.0.lock().map(|s| s.shutdown).unwrap_or(true)
    }

    /// A waker for this loop.
    pub fn waker(&self) -> Waker {
        Waker { inner: self.inner.clone() }
    }

    /// Sleeps up to `timeout`, or until woken; returns true when a shutdown
    /// is asked.
    pub fn wait(&self, timeout: Duration) -> bool {
        let (signals, wake) = &*self.inner;
        let Ok(guard) = signals.lock() else { return true };
        match wake.wait_timeout_while(guard, timeout, |s| !s.shutdown && !s.wake) {
            Ok((mut signals, _)) => {
                signals.wake = false;
                signals.shutdown
            }
            Err(_) => true,
        }
    }
}

impl Simulated {
    /// Moves simulated time from `now` to `wake` (never back), first
    /// waiting until real time since `origin` catches up with `wake` divided
    /// by the speed (none at [`Pace::Lockstep`]). Returns true when a
    /// shutdown is asked meanwhile.
    fn advance(&self, origin: Instant, now: u64, wake: u64, shutdown: &Shutdown) -> bool {
        let wake = wake.max(now);
        if let Pace::Speed(speed) = self.pace {
            let due = origin + Duration::from_secs_f64(wake as f64 / 1e9 / speed);
            loop {
                let left = due.saturating_duration_since(Instant::now());
                if left.is_zero() {
                    break;
                }
                // An early wake-up (input from outside) is taken at the next
                // due cycle: simulated time only moves in steps of the graph.
                if shutdown.wait(left) {
                    return true;
                }
            }
        } else if shutdown.is_requested() {
            return true;
        }
        self.now_ns.store(wake, Ordering::Release);
        false
    }
}

/// Work done between two cycles, on the control thread: swapping in a newly
/// activated graph, publishing the live status. It must be quick.
pub trait CycleHook {
    fn between_cycles(&mut self, graph: &mut Graph, now_ns: u64);
}

/// No work between cycles.
pub struct NoHook;

impl CycleHook for NoHook {
    fn between_cycles(&mut self, _graph: &mut Graph, _now_ns: u64) {}
}

/// Runs `graph` until `shutdown` is requested or `until_ns` (on `clock`)
/// passes.
pub fn run(graph: &mut Graph, clock: &Clock, shutdown: &Shutdown, until_ns: Option<u64>) -> StopReason {
    run_with(graph, clock, shutdown, until_ns, &mut NoHook)
}

/// Like [`run`], calling `hook` before every cycle.
pub fn run_with(
    graph: &mut Graph,
    clock: &Clock,
    shutdown: &Shutdown,
    until_ns: Option<u64>,
    hook: &mut dyn CycleHook,
) -> StopReason {
    run_watched(graph, clock, shutdown, until_ns, hook, None)
}

/// Like [`run_with`], publishing the loop's pulse on `heartbeat` for a
/// [`StallWatchdog`](super::StallWatchdog): every graph the loop runs
/// (including one an activation swapped in) is attached before its first
/// call, and the loop says when it sleeps.
pub fn run_watched(
    graph: &mut Graph,
    clock: &Clock,
    shutdown: &Shutdown,
    until_ns: Option<u64>,
    hook: &mut dyn CycleHook,
    heartbeat: Option<&Arc<Heartbeat>>,
) -> StopReason {
    if clock.simulated.is_none() {
        // Wake-ups on time, not up to 50 µs after (the kernel's default).
        super::scheduling::tighten_timer_slack();
    }
    let stopped_by = cycle(graph, clock, shutdown, until_ns, hook, heartbeat);
    // Building the report is not a stall.
    graph.asleep();
    if clock.simulated.is_none()
        && let Some(reading) = thread_run_delay_ns()
    {
        graph.note_cpu_wait(reading);
    }
    stopped_by
}

fn cycle(
    graph: &mut Graph,
    clock: &Clock,
    shutdown: &Shutdown,
    until_ns: Option<u64>,
    hook: &mut dyn CycleHook,
    heartbeat: Option<&Arc<Heartbeat>>,
) -> StopReason {
    let mut next_cpu_wait_read = 0;
    loop {
        if shutdown.is_requested() {
            return StopReason::Requested;
        }
        let now = clock.now_ns();
        if until_ns.is_some_and(|until| now >= until) {
            return StopReason::Duration;
        }
        if let Some(heartbeat) = heartbeat {
            graph.attach(heartbeat);
            graph.beat(None, Activity::Cycle);
        }
        hook.between_cycles(graph, now);
        if let Some(heartbeat) = heartbeat {
            // The hook may have swapped in a new graph.
            graph.attach(heartbeat);
        }
        // On real time, how long the thread waited for a CPU: read when a
        // graph starts (an activation may have swapped one in), then once
        // every READ_INTERVAL.
        if clock.simulated.is_none() && (!graph.cpu_wait().started() || now >= next_cpu_wait_read) {
            if let Some(reading) = thread_run_delay_ns() {
                graph.note_cpu_wait(reading);
            }
            next_cpu_wait_read = now + READ_INTERVAL.as_nanos() as u64;
        }
        if let Some(simulated) = &clock.simulated {
            // Waiting for bytes on the simulated robots' wires (bounded by
            // `lockstep::LOCKSTEP_WAIT`) is not a stall.
            graph.asleep();
            simulated.lockstep.before_cycle(now);
            graph.beat(None, Activity::Cycle);
        }
        graph.step(now);
        if graph.has_pending() {
            continue;
        }
        let due = graph.next_due_ns();
        let mut wake = due.unwrap_or(now + IDLE_WAIT.as_nanos() as u64);
        if let Some(until) = until_ns {
            wake = wake.min(until);
        }
        if let Some(simulated) = &clock.simulated {
            graph.asleep();
            if simulated.advance(clock.start, now, wake, shutdown) {
                return StopReason::Requested;
            }
            continue;
        }
        let now = clock.now_ns();
        if wake > now {
            graph.asleep();
            if shutdown.wait(Duration::from_nanos(wake - now)) {
                return StopReason::Requested;
            }
            // Lateness of a scheduled cycle: how long after its time the
            // loop got to run it (an early wake-up by the network is not
            // counted).
            let woke = clock.now_ns();
            if due.is_some() && woke >= wake {
                graph.record_lateness(woke - wake);
            }
        } else if due.is_some() {
            // Already behind: the next cycle starts at once, this late.
            graph.record_lateness(now - wake);
        }
    }
}
