//! A guest call's time limits: its budget counts the CPU time the call used
//! (the calling thread's CPU clock), so a busy machine does not fault a
//! component for being preempted; a separate wall-clock cap stops a call
//! that never finishes however the scheduler treats it.
//!
//! How: before a call the store's epoch deadline is set to the next epoch
//! tick (nothing else: a call shorter than a tick reads no clock). When the
//! deadline is reached, wasmtime calls [`check`] on the guest's thread. The
//! first check marks the thread's CPU clock and the wall clock; every later
//! one compares what the call used since the mark with its budget and its
//! cap, faults the call with the figures when one is broken, and otherwise
//! sets the next deadline where the budget could run out at the earliest.
//!
//! On simulated time ([`crate::sandbox::Sandbox::on_simulated_time`]) a call
//! has no wall-clock cap: a run there must give the same results on a busy
//! machine as on an idle one (a preflight at idle priority is preempted for
//! seconds at a time), and no motor waits on it; the CPU budget still stops
//! a runaway call.
//!
//! Invariants: a call is never stopped before it used its whole budget of
//! CPU time (the time before the first check, at most one epoch tick, is
//! not counted: it is the guest's); a runaway call is stopped within about
//! one tick after its CPU time reaches the budget, or its wall time reaches
//! the cap; a call blocked in a host function is not seen here (the host
//! functions a guest can reach never block: `wasi.rs`; the stall watchdog
//! catches the rest).

use std::time::{Duration, Instant};

use thiserror::Error;
use wasmtime::UpdateDeadline;

use super::limits::EPOCH_TICK;

/// The wall-clock cap of a call, as a multiple of its budget. The threat: a
/// call that makes no progress on the CPU (preempted for good, or spinning
/// in a way the CPU clock does not see) would otherwise hold the control
/// loop without bound; several times the budget leaves a well-behaved call
/// room to be preempted on a loaded machine (two busy processes on two
/// cores give the control thread about a third of a core).
pub const WALL_CAP_FACTOR: u32 = 10;

/// A call's limits and what the epoch checks have seen of it.
#[derive(Clone, Copy, Debug)]
pub(super) struct CallBudget {
    /// CPU time the call may use.
    pub(super) budget: Duration,
    /// Wall time the call may take (`Duration::MAX`: no cap).
    pub(super) wall_cap: Duration,
    /// Whether calls have a wall-clock cap at all.
    capped: bool,
    /// The thread's CPU clock and the wall clock at the call's first check.
    mark: Option<(Duration, Instant)>,
}

impl CallBudget {
    /// A call under `budget`, with the wall-clock cap that goes with it
    /// when `capped`.
    pub(super) fn new(budget: Duration, capped: bool) -> CallBudget {
        let wall_cap = if capped { wall_cap(budget) } else { Duration::MAX };
        CallBudget { budget, wall_cap, capped, mark: None }
    }

    /// Starts a new call under `budget`.
    pub(super) fn reset(&mut self, budget: Duration) {
        *self = CallBudget::new(budget, self.capped);
    }
}

/// The wall-clock cap that goes with `budget`.
pub fn wall_cap(budget: Duration) -> Duration {
    budget.saturating_mul(WALL_CAP_FACTOR)
}

/// Which limit a call broke, with the figures.
#[derive(Clone, Debug, PartialEq, Eq, Error)]
pub enum OverBudget {
    #[error(
        "exceeded its cpu-time budget of {} (used {} of cpu in {} of wall time)",
        millis(*.budget), millis(*.cpu), millis(*.wall)
    )]
    Cpu { budget: Duration, cpu: Duration, wall: Duration },
    #[error(
        "exceeded its wall-clock cap of {} ({WALL_CAP_FACTOR} x its {} budget; used {} of cpu in {} of wall time)",
        millis(*.cap), millis(*.budget), millis(*.cpu), millis(*.wall)
    )]
    Wall { cap: Duration, budget: Duration, cpu: Duration, wall: Duration },
}

fn millis(d: Duration) -> String {
    let ms = d.as_secs_f64() * 1e3;
    if ms >= 100.0 || ms.fract() == 0.0 { format!("{ms:.0} ms") } else { format!("{ms:.1} ms") }
}

/// The epoch-deadline callback's work for one guest: see the module doc.
pub(super) fn check(call: &mut CallBudget) -> wasmtime::Result<UpdateDeadline> {
    let cpu = thread_cpu_time();
    let now = Instant::now();
    let Some((cpu_mark, wall_mark)) = call.mark else {
        call.mark = Some((cpu, now));
        return Ok(UpdateDeadline::Continue(ticks(call.budget.min(call.wall_cap))));
    };
    let used = cpu.saturating_sub(cpu_mark);
    let wall = now.saturating_duration_since(wall_mark);
    if used >= call.budget {
        return Err(OverBudget::Cpu { budget: call.budget, cpu: used, wall }.into());
    }
    if wall >= call.wall_cap {
        return Err(OverBudget::Wall { cap: call.wall_cap, budget: call.budget, cpu: used, wall }.into());
    }
    // The budget cannot run out before `budget - used` of wall time has
    // passed: check again then (or at the cap).
    let next = (call.budget - used).min(call.wall_cap - wall);
    Ok(UpdateDeadline::Continue(ticks(next)))
}

/// Epoch ticks that cover `d`, at least one.
fn ticks(d: Duration) -> u64 {
    let tick = EPOCH_TICK.as_nanos().max(1);
    (d.as_nanos().div_ceil(tick) as u64).max(1)
}

/// CPU time the calling thread has used (`CLOCK_THREAD_CPUTIME_ID`).
pub fn thread_cpu_time() -> Duration {
    let mut ts = libc::timespec { tv_sec: 0, tv_nsec: 0 };
    // SAFETY: `ts` is a valid, writable timespec; clock_gettime writes only
    // into it. The thread CPU clock exists on every Linux this host supports;
    // on failure `ts` stays zero and the budget only counts wall time (the
    // cap still holds).
    let rc = unsafe { libc::clock_gettime(libc::CLOCK_THREAD_CPUTIME_ID, &mut ts) };
    if rc != 0 {
        return Duration::ZERO;
    }
    Duration::new(u64::try_from(ts.tv_sec).unwrap_or(0), u32::try_from(ts.tv_nsec).unwrap_or(0))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn spin_cpu(d: Duration) {
        let start = thread_cpu_time();
        while thread_cpu_time() - start < d {
            std::hint::black_box(0u64);
        }
    }

    #[test]
    fn the_first_check_only_marks_and_waits_for_the_budget() {
        let mut call = CallBudget::new(Duration::from_millis(5), true);
        let next = check(&mut call).unwrap();
        assert!(matches!(next, UpdateDeadline::Continue(5)));
        assert!(call.mark.is_some());
        call.reset(Duration::from_millis(5));
        assert!(call.mark.is_none());
    }

    #[test]
    fn a_call_that_used_its_cpu_budget_is_stopped_naming_the_figures() {
        let mut call = CallBudget::new(Duration::from_millis(3), true);
        check(&mut call).unwrap();
        spin_cpu(Duration::from_millis(3));
        let err = check(&mut call).err().expect("over budget");
        let over = err.downcast_ref::<OverBudget>().expect("an OverBudget");
        match over {
            OverBudget::Cpu { budget, cpu, wall } => {
                assert_eq!(*budget, Duration::from_millis(3));
                assert!(*cpu >= Duration::from_millis(3), "{over}");
                // The thread ran all along: the wall time is about the same.
                assert!(*wall + Duration::from_micros(100) >= *cpu, "{over}");
            }
            other => panic!("expected the cpu limit, got {other}"),
        }
        assert!(over.to_string().starts_with("exceeded its cpu-time budget of 3 ms (used "), "{over}");
    }

    #[test]
    fn sleeping_uses_no_cpu_budget_but_meets_the_wall_cap() {
        let mut call = CallBudget::new(Duration::from_millis(2), true);
        check(&mut call).unwrap();
        // Off the CPU for longer than the budget: not a cpu overrun.
        std::thread::sleep(Duration::from_millis(4));
        let next = check(&mut call).unwrap();
        assert!(matches!(next, UpdateDeadline::Continue(n) if n >= 1));
        std::thread::sleep(wall_cap(Duration::from_millis(2)));
        let err = check(&mut call).err().expect("over the wall cap");
        let text = err.to_string();
        assert!(text.starts_with("exceeded its wall-clock cap of 20 ms (10 x its 2 ms budget; used "), "{text}");
    }

    /// On simulated time a call off the CPU for many times its budget is
    /// not stopped (and keeps no cap across calls); its CPU budget holds.
    #[test]
    fn without_a_wall_cap_only_the_cpu_budget_stops_a_call() {
        let mut call = CallBudget::new(Duration::from_millis(2), false);
        check(&mut call).unwrap();
        std::thread::sleep(wall_cap(Duration::from_millis(2)) * 2);
        // Twice the wall-clock cap later: not stopped for the wall clock.
        // (It once failed on a loaded machine, where only the CPU budget
        // can have stopped it: the CPU clock must have charged the thread
        // 2 ms across the sleep. That stop is the CPU budget's to make.)
        match check(&mut call) {
            Ok(UpdateDeadline::Continue(n)) => assert!(n >= 1),
            Ok(_) => panic!("the check neither continued nor stopped the call"),
            Err(e) => assert!(
                matches!(e.downcast_ref::<OverBudget>(), Some(OverBudget::Cpu { .. })),
                "stopped for the wall clock: {e}"
            ),
        }
        call.reset(Duration::from_millis(2));
        assert_eq!(call.wall_cap, Duration::MAX);
        check(&mut call).unwrap();
        spin_cpu(Duration::from_millis(2));
        let err = check(&mut call).err().expect("over budget");
        assert!(matches!(err.downcast_ref::<OverBudget>(), Some(OverBudget::Cpu { .. })), "{err}");
    }

    #[test]
    fn the_thread_cpu_clock_advances_with_work_only() {
        let before = thread_cpu_time();
        spin_cpu(Duration::from_millis(2));
        let after = thread_cpu_time();
        assert!(after - before >= Duration::from_millis(2));
        std::thread::sleep(Duration::from_millis(20));
        // Sleeping costs a few microseconds of CPU at most, never 20 ms.
        assert!(thread_cpu_time() - after < Duration::from_millis(10));
    }

    #[test]
    fn figures_read_in_milliseconds() {
        assert_eq!(millis(Duration::from_millis(5)), "5 ms");
        assert_eq!(millis(Duration::from_micros(5300)), "5.3 ms");
        assert_eq!(millis(Duration::from_millis(1000)), "1000 ms");
    }
}
