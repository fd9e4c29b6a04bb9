//! Seeded timing perturbations of a simulated run (`subsume run --perturb
//! SEED --perturb-bounds FILE.json`, docs/lab.md "Timing"): the timing a
//! robot has and a lock-step simulation has not, drawn from a seed within
//! the owner's bounds ([`PerturbBounds`]), so that a set whose verdict
//! hangs on perfect timing is found in the preflight and any run is
//! reproduced from its seed.
//!
//! - the phase of each component's tick against the simulator: its first
//!   tick comes a seeded fraction of its period late
//!   ([`Perturbation::first_tick_delay_ns`]);
//! - sensor latency and noise: each feedback message of a simulated
//!   controller reaches the wire a seeded delay after it was measured, and
//!   each range reading carries seeded noise ([`SimTiming`]);
//! - the serial link's delay: each command reaches the simulated
//!   controller a seeded delay after it was written ([`SimTiming`]).
//!
//! Every draw comes from a stream of its own, keyed by the seed, the
//! component's name and what is drawn: the same seed and bounds give the
//! same run bit for bit, and one perturbation never shifts another's
//! draws. Delays never reorder: a message is never released before the
//! one measured (or written) before it.
//!
//! Import rule: nothing here knows the graph or the lock-step; the run
//! (`run.rs`) and the simulated robot (`sim::builtin`) apply it.

use std::collections::VecDeque;

use serde::{Deserialize, Serialize};
use thiserror::Error;

/// Longest sensor latency the bounds may name (ms). Threat: a bound past
/// any real robot's (a sensor read over a slow bus is tens of ms) makes
/// every set fail its preflight for a delay the robot never has.
pub const MAX_SENSOR_LATENCY_MS: f64 = 1000.0;
/// Largest range noise the bounds may name (m). Threat as above: a real
/// range sensor is off by centimetres, not metres.
pub const MAX_RANGE_NOISE_M: f64 = 1.0;
/// Longest serial delay the bounds may name (ms). Threat as above: a USB
/// serial adapter holds bytes for at most its latency timer (16 ms by
/// default on an FTDI chip).
pub const MAX_SERIAL_DELAY_MS: f64 = 1000.0;

/// How far a seeded run's timing may stray from the lock-step's: each
/// delay and noise is drawn uniformly from zero to its bound.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PerturbBounds {
    /// Offset each component's first tick by a seeded fraction of its
    /// period.
    pub tick_phase: bool,
    /// Most a feedback message (odometry, ranges, bumper) waits between
    /// its measurement and the wire (ms, 0 to [`MAX_SENSOR_LATENCY_MS`]).
    pub sensor_latency_ms: f64,
    /// Most a range reading is off, either way (m, 0 to
    /// [`MAX_RANGE_NOISE_M`]).
    pub range_noise_m: f64,
    /// Most a command waits between the wire and the motor controller
    /// (ms, 0 to [`MAX_SERIAL_DELAY_MS`]).
    pub serial_delay_ms: f64,
}

/// A bound out of its range, named by its field.
#[derive(Clone, Debug, PartialEq, Error)]
#[error("{field} must be from 0 to {max}, got {got}")]
pub struct BoundError {
    pub field: &'static str,
    pub max: f64,
    pub got: f64,
}

impl PerturbBounds {
    /// No perturbation: the lock-step's own timing.
    pub const NONE: PerturbBounds =
        PerturbBounds { tick_phase: false, sensor_latency_ms: 0.0, range_noise_m: 0.0, serial_delay_ms: 0.0 };

    /// The lab's defaults, the timing of a small robot on a USB serial
    /// link: any tick phase; feedback up to 30 ms old when it arrives
    /// (the 16 ms latency timer of a USB serial adapter, plus a range
    /// sensor's own measuring time); ranges off by up to 2 cm (an
    /// infrared or ultrasonic sensor's stated accuracy at a metre);
    /// commands up to 16 ms late at the motors (the adapter's latency
    /// timer).
    pub const DEFAULT: PerturbBounds =
        PerturbBounds { tick_phase: true, sensor_latency_ms: 30.0, range_noise_m: 0.02, serial_delay_ms: 16.0 };

    /// Every bound within its range.
    pub fn check(&self) -> Result<(), BoundError> {
        let bounds = [
            ("sensor_latency_ms", self.sensor_latency_ms, MAX_SENSOR_LATENCY_MS),
            ("range_noise_m", self.range_noise_m, MAX_RANGE_NOISE_M),
            ("serial_delay_ms", self.serial_delay_ms, MAX_SERIAL_DELAY_MS),
        ];
        for (field, got, max) in bounds {
            if !(got.is_finite() && (0.0..=max).contains(&got)) {
                return Err(BoundError { field, max, got });
            }
        }
        Ok(())
    }
}

/// One seeded run's perturbation: its seed and bounds.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Perturbation {
    pub seed: u64,
    pub bounds: PerturbBounds,
}

impl Perturbation {
    /// The stream of draws for `what` of component `component`.
    fn stream(&self, component: &str, what: &str) -> Draws {
        // FNV-1a: stable across builds and platforms, unlike std's hasher.
        let mut key: u64 = 0xcbf2_9ce4_8422_2325;
        for byte in component.bytes().chain([0]).chain(what.bytes()) {
            key = (key ^ u64::from(byte)).wrapping_mul(0x0000_0100_0000_01b3);
        }
        Draws(self.seed ^ key)
    }

    /// How late component `component`'s first tick comes, for a period of
    /// `period_ns`: a seeded fraction of the period; 0 without
    /// `tick_phase`.
    pub fn first_tick_delay_ns(&self, component: &str, period_ns: u64) -> u64 {
        if !self.bounds.tick_phase || period_ns == 0 {
            return 0;
        }
        self.stream(component, "tick-phase").next_u64() % period_ns
    }

    /// The simulated controller `component`'s delays and noise.
    pub fn sim_timing(&self, component: &str) -> SimTiming {
        SimTiming {
            latency_s: self.bounds.sensor_latency_ms / 1e3,
            noise_m: self.bounds.range_noise_m,
            serial_s: self.bounds.serial_delay_ms / 1e3,
            latency: self.stream(component, "sensor-latency"),
            noise: self.stream(component, "range-noise"),
            serial: self.stream(component, "serial-delay"),
            held_feedback: VecDeque::new(),
            held_commands: VecDeque::new(),
        }
    }
}

/// A stream of seeded draws (SplitMix64: small, and the same on every
/// build, which a library generator does not promise).
#[derive(Clone, Debug)]
struct Draws(u64);

impl Draws {
    fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }

    /// Uniform in [0, 1).
    fn unit(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }
}

/// A simulated controller's seeded timing: what it holds back, and the
/// draws it holds it back by.
#[derive(Clone, Debug)]
pub struct SimTiming {
    latency_s: f64,
    noise_m: f64,
    serial_s: f64,
    latency: Draws,
    noise: Draws,
    serial: Draws,
    /// Feedback measured and not yet on the wire: (when it is, its bytes).
    held_feedback: VecDeque<(f64, Vec<u8>)>,
    /// Commands written and not yet at the controller: (when they are,
    /// left and right wheel speeds).
    held_commands: VecDeque<(f64, f64, f64)>,
}

impl SimTiming {
    /// Whether feedback waits before it goes out.
    pub fn holds_feedback(&self) -> bool {
        self.latency_s > 0.0
    }

    /// Whether commands wait before they are acted on.
    pub fn holds_commands(&self) -> bool {
        self.serial_s > 0.0
    }

    /// Holds feedback `bytes` measured at `now_s` for its seeded latency.
    pub fn hold_feedback(&mut self, now_s: f64, bytes: Vec<u8>) {
        let after = now_s + self.latency.unit() * self.latency_s;
        let at = self.held_feedback.back().map_or(after, |(last, _)| after.max(*last));
        self.held_feedback.push_back((at, bytes));
    }

    /// Appends to `out` the feedback whose time came by `now_s`.
    pub fn release_feedback(&mut self, now_s: f64, out: &mut Vec<u8>) {
        while self.held_feedback.front().is_some_and(|(at, _)| *at <= now_s) {
            if let Some((_, bytes)) = self.held_feedback.pop_front() {
                out.extend(bytes);
            }
        }
    }

    /// Holds a command written at `now_s` for its seeded delay.
    pub fn hold_command(&mut self, now_s: f64, left: f64, right: f64) {
        let after = now_s + self.serial.unit() * self.serial_s;
        let at = self.held_commands.back().map_or(after, |(last, _, _)| after.max(*last));
        self.held_commands.push_back((at, left, right));
    }

    /// The next held command due by `until_s`: (when, left, right).
    pub fn next_command_by(&mut self, until_s: f64) -> Option<(f64, f64, f64)> {
        if self.held_commands.front().is_some_and(|(at, _, _)| *at <= until_s) {
            return self.held_commands.pop_front();
        }
        None
    }

    /// Adds the seeded noise to `ranges`, each kept within 0 and `max`.
    pub fn add_noise(&mut self, ranges: &mut [f64], max: f64) {
        if self.noise_m <= 0.0 {
            return;
        }
        for range in ranges {
            let off = (self.noise.unit() * 2.0 - 1.0) * self.noise_m;
            *range = (*range + off).clamp(0.0, max);
        }
    }

    /// Forgets what is held (the world was reset: its time starts again).
    pub fn clear(&mut self) {
        self.held_feedback.clear();
        self.held_commands.clear();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const BOUNDS: PerturbBounds =
        PerturbBounds { tick_phase: true, sensor_latency_ms: 30.0, range_noise_m: 0.02, serial_delay_ms: 16.0 };

    /// (bounds, the field the error names, if any).
    #[test]
    fn bounds_out_of_range_are_refused_naming_the_field() {
        let with = |f: fn(&mut PerturbBounds)| {
            let mut bounds = BOUNDS;
            f(&mut bounds);
            bounds
        };
        let cases = [
            (BOUNDS, None),
            (PerturbBounds::NONE, None),
            (with(|b| b.sensor_latency_ms = -1.0), Some("sensor_latency_ms")),
            (with(|b| b.sensor_latency_ms = MAX_SENSOR_LATENCY_MS + 1.0), Some("sensor_latency_ms")),
            (with(|b| b.range_noise_m = f64::NAN), Some("range_noise_m")),
            (with(|b| b.range_noise_m = 2.0), Some("range_noise_m")),
            (with(|b| b.serial_delay_ms = f64::INFINITY), Some("serial_delay_ms")),
        ];
        for (bounds, field) in cases {
            let checked = bounds.check();
            assert_eq!(checked.as_ref().err().map(|e| e.field), field, "{bounds:?}");
            if let Err(e) = checked {
                assert!(e.to_string().starts_with(&format!("{} must be from 0 to", e.field)), "{e}");
            }
        }
    }

    /// The same seed draws the same; another seed, or another component,
    /// draws otherwise; every draw is within its bound.
    #[test]
    fn draws_are_the_seeds_and_within_their_bounds() {
        let a = Perturbation { seed: 7, bounds: BOUNDS };
        let b = Perturbation { seed: 8, bounds: BOUNDS };
        let phases = |p: &Perturbation, name: &str| p.first_tick_delay_ns(name, 50_000_000);
        assert_eq!(phases(&a, "avoid"), phases(&a, "avoid"));
        assert_ne!(phases(&a, "avoid"), phases(&b, "avoid"));
        assert_ne!(phases(&a, "avoid"), phases(&a, "planner"));
        assert_eq!(Perturbation { seed: 7, bounds: PerturbBounds::NONE }.first_tick_delay_ns("avoid", 50_000_000), 0);
        for seed in 0..200 {
            let p = Perturbation { seed, bounds: BOUNDS };
            assert!(phases(&p, "x") < 50_000_000);
            let mut timing = p.sim_timing("robot-sim");
            let mut ranges = [1.0, 0.0, 4.0];
            timing.add_noise(&mut ranges, 4.0);
            assert!((ranges[0] - 1.0).abs() <= 0.02 && (0.0..=0.02).contains(&ranges[1]), "{ranges:?}");
            assert!((3.98..=4.0).contains(&ranges[2]), "{ranges:?}");
            timing.hold_command(1.0, 0.1, 0.1);
            assert_eq!(timing.next_command_by(0.999), None);
            let (at, _, _) = timing.next_command_by(1.016).unwrap();
            assert!((1.0..=1.016).contains(&at), "{at}");
        }
    }

    /// Held feedback goes out in order, never before its time nor before
    /// what was measured before it.
    #[test]
    fn held_feedback_keeps_its_order_and_its_time() {
        let mut timing = Perturbation { seed: 3, bounds: BOUNDS }.sim_timing("robot-sim");
        for (n, at) in [0.0, 0.05, 0.1, 0.15].iter().enumerate() {
            timing.hold_feedback(*at, vec![n as u8]);
        }
        let mut out = Vec::new();
        timing.release_feedback(0.0, &mut out);
        assert!(out.len() <= 1);
        timing.release_feedback(0.08, &mut out);
        assert!((1..=2).contains(&out.len()), "{out:?}");
        timing.release_feedback(0.2, &mut out);
        assert_eq!(out, [0, 1, 2, 3]);
    }
}
