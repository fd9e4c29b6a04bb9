//! The constant-delay buffer for network commands (MISSION M12).
//!
//! Each command carries the operator's sequence number and send time (on the
//! operator's clock). The buffer releases command `i` at
//!
//! ```text
//! release_i = send_i + base + D
//! base      = min over the last WINDOW commands of (arrival_j - send_j)
//!             (the clock offset plus the smallest one-way delay seen)
//! J         = RFC 3550 jitter: J += (|transit_i - transit_(i-1)| - J) / 16
//! D         = clamp(JITTER_FACTOR * J, min_delay, max_delay)   (or a fixed D),
//!             rounded up to DELAY_STEP; raised at once, lowered only when
//!             two steps too long, so it holds still in steady traffic
//! ```
//!
//! so commands reach the arbiter with the spacing they were sent with, delayed
//! by a constant that follows the link's delay and jitter. A command whose
//! sequence number is not above the last accepted one (duplicate or
//! reordered) is dropped; one older than `horizon` on arrival
//! (arrival - send - base > horizon) is dropped as stale. When several
//! commands are due at once (late arrivals after a stall), only the newest is
//! released and the rest count as superseded: the robot never receives a
//! burst of old commands. Time is passed in; nothing here reads a clock.

use std::collections::VecDeque;
use std::time::Duration;

use serde::Serialize;

/// Commands over which the minimum transit (the base) is taken: long enough
/// that the base holds still, short enough to follow clock drift.
pub const WINDOW: usize = 512;
/// The adaptive delay moves in steps of this size, up at once when the
/// jitter needs it, down only when it is two steps too long: a delay that
/// changed with every command would change the release spacing with it.
pub const DELAY_STEP: Duration = Duration::from_millis(5);
/// D = JITTER_FACTOR * jitter (before clamping): four jitters cover nearly
/// every late arrival of a roughly normal delay.
pub const JITTER_FACTOR: f64 = 4.0;
/// Commands waiting in one buffer at most; a flood beyond is dropped.
pub const MAX_QUEUED: usize = 256;

/// How the playout delay is chosen.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DelaySettings {
    /// A fixed D, or `None` to follow the jitter.
    pub fixed: Option<Duration>,
    pub min_delay: Duration,
    pub max_delay: Duration,
    /// Older commands are dropped as stale.
    pub horizon: Duration,
}

impl Default for DelaySettings {
    fn default() -> Self {
        DelaySettings {
            fixed: None,
            min_delay: Duration::from_millis(10),
            max_delay: Duration::from_millis(200),
            horizon: Duration::from_millis(500),
        }
    }
}

/// Why a command was not accepted.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Rejected {
    /// Its sequence number is not above the last accepted one.
    Duplicate,
    /// It is older than the horizon.
    Stale,
    /// The buffer is full.
    Full,
}

impl Rejected {
    pub fn reason(self) -> &'static str {
        match self {
            Rejected::Duplicate => "duplicate or out of order",
            Rejected::Stale => "stale",
            Rejected::Full => "buffer full",
        }
    }
}

#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct DelayStats {
    pub received: u64,
    pub released: u64,
    pub dropped_stale: u64,
    pub dropped_duplicate: u64,
    pub dropped_full: u64,
    /// Due at the same time as a newer command, so never released.
    pub superseded: u64,
}

impl DelayStats {
    /// Adds `other`'s counts to these (the totals of the sessions no
    /// longer listed one by one).
    pub fn absorb(&mut self, other: &DelayStats) {
        self.received += other.received;
        self.released += other.released;
        self.dropped_stale += other.dropped_stale;
        self.dropped_duplicate += other.dropped_duplicate;
        self.dropped_full += other.dropped_full;
        self.superseded += other.superseded;
    }
}

#[derive(Clone, Debug)]
pub struct DelayBuffer<T> {
    settings: DelaySettings,
    transits: VecDeque<i128>,
    last_transit: Option<i128>,
    jitter_ns: f64,
    delay: Duration,
    last_seq: Option<u64>,
    queue: VecDeque<(u64, T)>,
    stats: DelayStats,
}

impl<T> DelayBuffer<T> {
    pub fn new(settings: DelaySettings) -> DelayBuffer<T> {
        DelayBuffer {
            settings,
            transits: VecDeque::with_capacity(WINDOW),
            last_transit: None,
            jitter_ns: 0.0,
            delay: settings.min_delay,
            last_seq: None,
            queue: VecDeque::new(),
            stats: DelayStats::default(),
        }
    }

    /// Accepts command `seq`, sent at `send_ms` on the operator's clock and
    /// arrived at `arrival_ns` on the host's; returns when it will be released.
    pub fn push(&mut self, seq: u64, send_ms: u64, command: T, arrival_ns: u64) -> Result<u64, Rejected> {
        self.stats.received += 1;
        if self.last_seq.is_some_and(|last| seq <= last) {
            self.stats.dropped_duplicate += 1;
            return Err(Rejected::Duplicate);
        }
        let send_ns = i128::from(send_ms) * 1_000_000;
        let transit = i128::from(arrival_ns) - send_ns;
        if let Some(last) = self.last_transit {
            let delta = (transit - last).abs() as f64;
            self.jitter_ns += (delta - self.jitter_ns) / 16.0;
        }
        self.adapt_delay();
        self.last_transit = Some(transit);
        if self.transits.len() == WINDOW {
            self.transits.pop_front();
        }
        self.transits.push_back(transit);
        let base = self.transits.iter().copied().min().unwrap_or(transit);
        // The send time on the host clock, plus the smallest delay seen.
        let sent_here = send_ns + base;
        let age = i128::from(arrival_ns) - sent_here;
        self.last_seq = Some(seq);
        if age > self.settings.horizon.as_nanos() as i128 {
            self.stats.dropped_stale += 1;
            return Err(Rejected::Stale);
        }
        if self.queue.len() >= MAX_QUEUED {
            self.stats.dropped_full += 1;
            return Err(Rejected::Full);
        }
        let release = (sent_here + self.playout_delay().as_nanos() as i128).max(0) as u64;
        // Keep release order even if the base moved.
        let release = self.queue.back().map_or(release, |(last, _)| release.max(*last));
        self.queue.push_back((release, command));
        Ok(release)
    }

    /// The newest command due at `now_ns`, if any; older due ones are
    /// superseded.
    pub fn pop_ready(&mut self, now_ns: u64) -> Option<T> {
        let mut ready = None;
        while self.queue.front().is_some_and(|(release, _)| *release <= now_ns) {
            if ready.is_some() {
                self.stats.superseded += 1;
            }
            ready = self.queue.pop_front().map(|(_, c)| c);
        }
        if ready.is_some() {
            self.stats.released += 1;
        }
        ready
    }

    /// When the next command is due.
    pub fn next_release(&self) -> Option<u64> {
        self.queue.front().map(|(release, _)| *release)
    }

    /// Drops everything waiting (the operator left).
    pub fn clear(&mut self) {
        self.queue.clear();
    }

    fn adapt_delay(&mut self) {
        let step = DELAY_STEP.as_nanos() as u64;
        let wanted = ((JITTER_FACTOR * self.jitter_ns) as u64).div_ceil(step) * step;
        let target = Duration::from_nanos(wanted).clamp(self.settings.min_delay, self.settings.max_delay);
        if target > self.delay || target + 2 * DELAY_STEP <= self.delay {
            self.delay = target;
        }
    }

    /// The current playout delay D.
    pub fn playout_delay(&self) -> Duration {
        self.settings.fixed.unwrap_or(self.delay)
    }

    pub fn jitter(&self) -> Duration {
        Duration::from_nanos(self.jitter_ns as u64)
    }

    pub fn stats(&self) -> &DelayStats {
        &self.stats
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const MS: u64 = 1_000_000;

    /// Polls every millisecond from `from` to `to`; returns (time, command).
    fn drain(buffer: &mut DelayBuffer<u64>, from: u64, to: u64) -> Vec<(u64, u64)> {
        (from..=to).filter_map(|ms| buffer.pop_ready(ms * MS).map(|c| (ms, c))).collect()
    }

    /// A deterministic pseudo-random delay in [20, 60) ms.
    fn delay(i: u64) -> u64 {
        20 + (i.wrapping_mul(2_654_435_761) >> 7) % 40
    }

    #[test]
    fn releases_keep_the_send_spacing_under_jitter() {
        let mut buffer = DelayBuffer::new(DelaySettings::default());
        // The operator's clock is 5 s behind the host's; one command per 50 ms.
        let offset = 5_000;
        let mut released = Vec::new();
        let mut polled = 0;
        for i in 0..100u64 {
            let send = i * 50;
            let arrival = send + offset + delay(i);
            // Poll every millisecond up to this arrival, then deliver it.
            released.extend(drain(&mut buffer, polled, arrival - 1));
            polled = arrival;
            let _ = buffer.push(i, send, i, arrival * MS);
        }
        released.extend(drain(&mut buffer, polled, polled + 400));
        // Once the jitter is learned (after 40 commands) every command comes
        // out, in order, 50 ms after the previous one, except where the delay
        // steps up (by DELAY_STEP) as the jitter estimate settles.
        let steady: Vec<_> = released.iter().filter(|(_, c)| *c >= 40).collect();
        assert_eq!(steady.len(), 60, "{released:?}");
        let spacings: Vec<u64> = steady.windows(2).map(|p| p[1].0 - p[0].0).collect();
        assert!(steady.windows(2).all(|p| p[1].1 == p[0].1 + 1));
        assert!(spacings.iter().all(|s| (50..=55).contains(s)), "{spacings:?}");
        assert!(spacings.iter().filter(|s| **s == 50).count() >= 56, "{spacings:?}");
        let d = buffer.playout_delay();
        assert!(d > Duration::from_millis(20) && d < Duration::from_millis(100), "{d:?}");
        assert_eq!(buffer.stats().dropped_stale + buffer.stats().dropped_duplicate, 0);
    }

    #[test]
    fn duplicates_and_reordered_commands_are_dropped() {
        let mut buffer = DelayBuffer::new(DelaySettings::default());
        assert!(buffer.push(1, 0, 1, 30 * MS).is_ok());
        assert!(buffer.push(3, 100, 3, 130 * MS).is_ok());
        assert_eq!(buffer.push(3, 100, 3, 131 * MS), Err(Rejected::Duplicate));
        assert_eq!(buffer.push(2, 50, 2, 140 * MS), Err(Rejected::Duplicate));
        assert_eq!(buffer.stats().dropped_duplicate, 2);
        assert_eq!(drain(&mut buffer, 0, 300).iter().map(|(_, c)| *c).collect::<Vec<_>>(), vec![1, 3]);
    }

    #[test]
    fn after_a_stall_there_is_no_burst_of_stale_commands() {
        let settings = DelaySettings { fixed: Some(Duration::from_millis(20)), ..DelaySettings::default() };
        let mut buffer = DelayBuffer::new(settings);
        // Normal traffic: 10 ms transit, one command per 100 ms.
        for i in 0..5u64 {
            let _ = buffer.push(i, i * 100, i, (i * 100 + 10) * MS);
        }
        assert_eq!(drain(&mut buffer, 0, 500).len(), 5);
        // The link stalls for 2 s; 20 commands then arrive at once.
        let arrival = 2_510;
        let mut accepted = 0;
        for i in 5..25u64 {
            if buffer.push(i, i * 100, i, arrival * MS).is_ok() {
                accepted += 1;
            }
        }
        // Only those sent within the 500 ms horizon survive ...
        assert_eq!(buffer.stats().dropped_stale, 15);
        assert_eq!(accepted, 5);
        // ... and of those, only the newest is released: no burst.
        let after = drain(&mut buffer, arrival, arrival + 1_000);
        assert_eq!(after, vec![(arrival, 24)]);
        assert_eq!(buffer.stats().superseded, 4);
    }

    #[test]
    fn a_zero_fixed_delay_releases_on_arrival() {
        let settings = DelaySettings { fixed: Some(Duration::ZERO), ..DelaySettings::default() };
        let mut buffer = DelayBuffer::new(settings);
        let release = buffer.push(1, 1_000, 7, 1_003 * MS);
        assert_eq!(release, Ok(1_003 * MS));
        assert_eq!(buffer.pop_ready(1_003 * MS), Some(7));
    }

    #[test]
    fn absorbing_counts_adds_every_field() {
        let one = DelayStats {
            received: 1,
            released: 2,
            dropped_stale: 3,
            dropped_duplicate: 4,
            dropped_full: 5,
            superseded: 6,
        };
        let mut total = one.clone();
        total.absorb(&one);
        let doubled = DelayStats {
            received: 2,
            released: 4,
            dropped_stale: 6,
            dropped_duplicate: 8,
            dropped_full: 10,
            superseded: 12,
        };
        assert_eq!(total, doubled);
    }
}
