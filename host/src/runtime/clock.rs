//! The graph's stopwatch: a monotonic nanosecond count that times every
//! component call (its `call_ns`, its histogram and the stall check after
//! it). A call costs one reading, so the reading is on the hot path:
//! `Instant::now()` goes through the vDSO's `clock_gettime` (about 25 ns on
//! a KVM guest), while reading the CPU's time-stamp counter directly costs
//! about 10 ns.
//!
//! The counter is used only where the kernel itself keeps time with it
//! (x86_64, clock source `tsc`: the kernel checked it is invariant and
//! synchronised across CPUs); its rate is measured once against
//! `Instant`, over [`CALIBRATION`]. Anywhere else the stopwatch is
//! `Instant`. Readings never go backwards from one call to the next that
//! the graph makes (differences saturate at zero).

use std::sync::OnceLock;
use std::time::{Duration, Instant};

/// How long the counter's rate is measured against `Instant` at the first
/// reading: two readings each within about a microsecond over 5 ms is an
/// error of at most about 4e-4 on every duration.
pub const CALIBRATION: Duration = Duration::from_millis(5);

/// Where the kernel names its clock source.
const CLOCKSOURCE: &str = "/sys/devices/system/clocksource/clocksource0/current_clocksource";

/// How readings are taken.
#[derive(Clone, Copy, Debug)]
enum Source {
    /// Time-stamp counter: ns = (ticks - origin) * mult >> 32.
    #[cfg(target_arch = "x86_64")]
    Tsc { origin: u64, mult: u64 },
    /// `Instant`, from an origin.
    Instant(Instant),
}

fn source() -> &'static Source {
    static SOURCE: OnceLock<Source> = OnceLock::new();
    SOURCE.get_or_init(|| {
        let tsc = std::fs::read_to_string(CLOCKSOURCE).is_ok_and(|s| s.trim() == "tsc");
        match tsc.then(calibrate).flatten() {
            Some(source) => source,
            None => Source::Instant(Instant::now()),
        }
    })
}

#[cfg(target_arch = "x86_64")]
#[inline]
fn ticks() -> u64 {
    // SAFETY: `rdtsc` exists on every x86_64 CPU and only reads the counter.
    unsafe { core::arch::x86_64::_rdtsc() }
}

/// Most ticks between the two counter readings around an `Instant`
/// reading for the pair to count (about a microsecond): a pair the thread
/// was preempted in the middle of is taken again, so a busy machine does
/// not skew the rate.
#[cfg(target_arch = "x86_64")]
const TIGHT_PAIR_TICKS: u64 = 4096;

/// An (`Instant`, counter) pair read back to back, or `None` when no try of
/// many was tight.
#[cfg(target_arch = "x86_64")]
fn pair() -> Option<(Instant, u64)> {
    for _ in 0..1000 {
        let before = ticks();
        let wall = Instant::now();
        let after = ticks();
        if after >= before && after - before <= TIGHT_PAIR_TICKS {
            return Some((wall, before + (after - before) / 2));
        }
    }
    None
}

/// The counter's rate against `Instant`, or `None` when it does not tick
/// or no tight reading could be taken.
#[cfg(target_arch = "x86_64")]
fn calibrate() -> Option<Source> {
    let (wall0, tsc0) = pair()?;
    while wall0.elapsed() < CALIBRATION {
        std::hint::spin_loop();
    }
    let (wall1, tsc1) = pair()?;
    let ns = wall1.duration_since(wall0).as_nanos();
    let counted = u128::from(tsc1.checked_sub(tsc0)?);
    if counted == 0 || ns == 0 {
        return None;
    }
    // ns per tick, as a 32.32 fixed-point number.
    let mult = u64::try_from((ns << 32) / counted).ok()?;
    Some(Source::Tsc { origin: tsc0, mult })
}

#[cfg(not(target_arch = "x86_64"))]
fn calibrate() -> Option<Source> {
    None
}

/// Nanoseconds since an origin fixed at the first reading in the process.
#[inline]
pub fn now_ns() -> u64 {
    match *source() {
        #[cfg(target_arch = "x86_64")]
        Source::Tsc { origin, mult } => {
            let ticks = ticks().saturating_sub(origin);
            ((u128::from(ticks) * u128::from(mult)) >> 32) as u64
        }
        Source::Instant(origin) => origin.elapsed().as_nanos() as u64,
    }
}

/// Measures the counter's rate now if it was not yet (it takes
/// [`CALIBRATION`]): a graph does it when it is built, so the first cycle
/// of a control loop does not pay it.
pub fn init() {
    source();
}

/// Whether the stopwatch reads the time-stamp counter (else `Instant`).
#[cfg(target_arch = "x86_64")]
pub fn uses_tsc() -> bool {
    matches!(source(), Source::Tsc { .. })
}

/// Whether the stopwatch reads the time-stamp counter: never off x86_64.
#[cfg(not(target_arch = "x86_64"))]
pub fn uses_tsc() -> bool {
    false
}

#[cfg(test)]
mod tests {
    use super::*;

    /// (stopwatch, `Instant`) read back to back: retried while the thread
    /// was preempted between the two (a loaded machine).
    fn both() -> (u64, Instant) {
        loop {
            let (before, wall, after) = (now_ns(), Instant::now(), now_ns());
            if after - before < 20_000 {
                return (before, wall);
            }
        }
    }

    #[test]
    fn it_agrees_with_instant_and_never_goes_back() {
        let (start, wall) = both();
        let mut last = start;
        while wall.elapsed() < Duration::from_millis(50) {
            let now = now_ns();
            assert!(now >= last, "the stopwatch went back: {last} -> {now}");
            last = now;
        }
        let (end, wall_end) = both();
        let (counted, elapsed) = (end - start, wall_end.duration_since(wall).as_nanos() as u64);
        // Both measured the same interval: within 0.5 % (the calibration's
        // error bound is about 0.04 %) and the readings' own spread.
        let diff = counted.abs_diff(elapsed);
        assert!(diff <= elapsed / 200 + 40_000, "stopwatch {counted} ns, Instant {elapsed} ns (tsc: {})", uses_tsc());
    }
}
