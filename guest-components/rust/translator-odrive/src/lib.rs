//! A hardware translator for ODrive motor controllers over their ASCII
//! protocol (ODrive firmware 0.5, `docs/ascii-protocol.md` of
//! odriverobotics/ODrive), as a WASM component of the `translator` world.
//!
//! - Commands: one `v motor velocity` line per wheel, turns/s; STOP is
//!   velocity 0 on both. Each `v` feeds that motor's watchdog.
//! - Poll (every `poll-ms`, 100 by default): `u 0` and `u 1` feed both
//!   watchdogs even when no command changes; `f 0` and `f 1` ask for
//!   feedback (`pos vel` in turns and turns/s), which becomes odometry by
//!   dead reckoning from `origin-x/y/heading`; every tenth poll, starting
//!   with the first, `r vbus_voltage` asks for the battery voltage; every
//!   tenth, from the sixth, `r axis0.error` and `r axis1.error` ask for the
//!   axes' errors (bit masks; any bit set is the controller's fault, named
//!   as the firmware's `AxisError` names it, e.g. "axis0: motor failed").
//! - Opening (with `arm=yes`, the default): velocity control and closed
//!   loop on both axes (`w axisN.controller.config.control_mode 2`,
//!   `w axisN.requested_state 8`); closing: both axes idle
//!   (`w axisN.requested_state 1`).
//! - With `checksum=on` every line carries the GCode checksum ` *NN` (the
//!   XOR of every character before `*`) and answers must carry a valid one.
//!
//! Options (the link's `options`): `turns-per-metre` (required: motor turns
//! per metre of wheel travel), `left-axis` (0 or 1, default 0; the right
//! wheel is the other), `left-sign`, `right-sign` (1 or -1: -1 for a motor
//! mounted mirrored), `checksum=on|off`, `arm=yes|no`, `poll-ms`,
//! `origin-x`, `origin-y`, `origin-heading`.

use std::collections::VecDeque;

use subsume_guest::drive::{Geometry, Odometry};
use subsume_guest::{Decoded, Feedback, LinkPlan, Params, Translator};

/// Longest line kept; a longer one is garbage.
const MAX_LINE: usize = 256;
/// Most answers waited for: older ones are taken as lost.
const MAX_EXPECTED: usize = 64;
/// Shortest and longest poll period a robot file may set, ms.
const POLL_MS_RANGE: (u32, u32) = (5, 10_000);
/// The battery is read on every this many polls.
const VOLTAGE_EVERY: u64 = 10;
/// The axes' errors are read on every this many polls, at this one.
const ERRORS_EVERY: u64 = 10;
const ERRORS_AT: u64 = 5;
/// The bits of an axis's `error` (firmware 0.5.6's `AxisError`), by name.
const AXIS_ERRORS: [(u32, &str); 12] = [
    (0x0000_0001, "invalid state"),
    (0x0000_0040, "motor failed"),
    (0x0000_0080, "sensorless estimator failed"),
    (0x0000_0100, "encoder failed"),
    (0x0000_0200, "controller failed"),
    (0x0000_0800, "watchdog timer expired"),
    (0x0000_1000, "min endstop pressed"),
    (0x0000_2000, "max endstop pressed"),
    (0x0000_4000, "estop requested"),
    (0x0002_0000, "homing without endstop"),
    (0x0004_0000, "over temp"),
    (0x0008_0000, "unknown position"),
];
/// ODrive's axis states and control modes (firmware 0.5).
const AXIS_STATE_IDLE: u8 = 1;
const AXIS_STATE_CLOSED_LOOP_CONTROL: u8 = 8;
const CONTROL_MODE_VELOCITY: u8 = 2;

/// An answer the translator waits for, in the order asked.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Expected {
    /// `pos vel` of an axis.
    Feedback(usize),
    /// The bus voltage.
    Voltage,
    /// An axis's error bits.
    AxisError(usize),
}

/// What an axis's error bits name: each bit set (one the firmware's list
/// lacks, by its mask); empty for none.
fn axis_error_text(axis: usize, bits: u32) -> String {
    let mut named: Vec<String> =
        AXIS_ERRORS.iter().filter(|(bit, _)| bits & bit != 0).map(|(_, name)| name.to_string()).collect();
    let unknown = bits & !AXIS_ERRORS.iter().fold(0, |all, (bit, _)| all | bit);
    if unknown != 0 {
        named.push(format!("error bits 0x{unknown:08x}"));
    }
    if named.is_empty() { String::new() } else { format!("axis{axis}: {}", named.join(", ")) }
}

struct ODrive {
    geometry: Geometry,
    odometry: Odometry,
    turns_per_metre: f64,
    left_axis: usize,
    /// Sign of each axis (index: axis number).
    signs: [f64; 2],
    checksum: bool,
    arm: bool,
    poll_ms: u32,
    polls: u64,
    expected: VecDeque<Expected>,
    line: Vec<u8>,
    skipping: bool,
    /// Fresh positions (turns) of each axis since the last odometry step.
    fresh: [Option<f64>; 2],
    /// The positions (turns) at the last odometry step.
    last: Option<[f64; 2]>,
    /// Each axis's error bits as last read.
    errors: [Option<u32>; 2],
    /// The fault the last error answers named, for the host to take.
    fault: Option<String>,
}

/// The GCode checksum: XOR of every byte.
fn checksum(text: &str) -> u8 {
    text.bytes().fold(0, |x, b| x ^ b)
}

/// A number as the ODrive reads it: at most four decimals, no `-0`.
fn number(value: f64) -> String {
    let rounded = (value * 10_000.0).round() / 10_000.0;
    if rounded == 0.0 { "0".into() } else { format!("{rounded}") }
}

impl ODrive {
    /// `command` as a line, with its checksum when they are on.
    fn push_line(&self, command: &str, out: &mut Vec<u8>) {
        if self.checksum {
            let body = format!("{command} ");
            out.extend_from_slice(format!("{body}*{}\n", checksum(&body)).as_bytes());
        } else {
            out.extend_from_slice(command.as_bytes());
            out.push(b'\n');
        }
    }

    fn for_both_axes(&self, what: impl Fn(usize) -> String) -> Vec<u8> {
        let mut out = Vec::new();
        for axis in 0..2 {
            self.push_line(&what(axis), &mut out);
        }
        out
    }

    /// The text of an answer line without its checksum, or `None` when the
    /// checksum is missing or wrong (with checksums on).
    fn answer<'a>(&self, text: &'a str) -> Option<&'a str> {
        if !self.checksum {
            return Some(text);
        }
        let (body, sum) = text.rsplit_once('*')?;
        (sum.trim().parse::<u8>().ok()? == checksum(body)).then_some(body)
    }

    /// One answer line: feedback, a voltage, or garbage (`false`).
    fn take_line(&mut self, text: &str, out: &mut Vec<Feedback>) -> bool {
        let Some(text) = self.answer(text) else { return false };
        let numbers: Option<Vec<f64>> =
            text.split_ascii_whitespace().map(|w| w.parse::<f64>().ok().filter(|v| v.is_finite())).collect();
        let Some(numbers) = numbers else { return false };
        let shape = |e: &Expected| {
            matches!((e, numbers.len()), (Expected::Feedback(_), 2) | (Expected::Voltage | Expected::AxisError(_), 1))
        };
        // Answers come in the order asked; any skipped were lost.
        let Some(at) = self.expected.iter().position(shape) else { return false };
        self.expected.drain(..at);
        match self.expected.pop_front() {
            Some(Expected::Voltage) => out.push(Feedback::Battery(numbers[0])),
            Some(Expected::AxisError(axis)) => {
                let value = numbers[0];
                if !(value >= 0.0 && value <= f64::from(u32::MAX) && value.fract() == 0.0) {
                    return false;
                }
                self.errors[axis] = Some(value as u32);
                let named: Vec<String> = self
                    .errors
                    .iter()
                    .enumerate()
                    .filter_map(|(axis, bits)| bits.map(|bits| axis_error_text(axis, bits)))
                    .filter(|text| !text.is_empty())
                    .collect();
                self.fault = Some(named.join("; "));
            }
            Some(Expected::Feedback(axis)) => {
                self.fresh[axis] = Some(numbers[0]);
                if let [Some(a0), Some(a1)] = self.fresh {
                    self.fresh = [None, None];
                    let positions = [a0, a1];
                    let last = self.last.replace(positions);
                    if let Some(last) = last {
                        let travel =
                            |axis: usize| (positions[axis] - last[axis]) * self.signs[axis] / self.turns_per_metre;
                        let right_axis = 1 - self.left_axis;
                        // Absurd positions (the pose would stop being a
                        // number) are garbage; the next step starts from them.
                        if !self.odometry.advance(travel(self.left_axis), travel(right_axis)) {
                            return false;
                        }
                    }
                    out.push(Feedback::Odometry(self.odometry.pose()));
                }
            }
            None => return false,
        }
        true
    }
}

fn option_in(params: &Params, name: &str, default: i64, allowed: &[i64]) -> Result<i64, String> {
    let value = match params.text(name) {
        None => default,
        Some(_) => params.integer(name)?,
    };
    if allowed.contains(&value) {
        Ok(value)
    } else {
        Err(format!("option '{name}': {value} is not one of {allowed:?}"))
    }
}

fn switch(params: &Params, name: &str, on: &str, off: &str, default: bool) -> Result<bool, String> {
    match params.text(name).map(str::trim) {
        None => Ok(default),
        Some(word) if word == on => Ok(true),
        Some(word) if word == off => Ok(false),
        Some(other) => Err(format!("option '{name}': '{other}' is not {on} or {off}")),
    }
}

impl Translator for ODrive {
    fn init(params: &Params) -> Result<Self, String> {
        let geometry = Geometry::from_params(params, 0.3, 0.5)?;
        let odometry = Odometry::from_params(params, geometry.wheel_base)?;
        if params.text("turns-per-metre").is_none() {
            return Err("option 'turns-per-metre' is required (motor turns per metre of wheel travel)".into());
        }
        let turns_per_metre = params.number("turns-per-metre")?;
        if !(turns_per_metre.is_finite() && turns_per_metre > 0.0) {
            return Err("option 'turns-per-metre' must be positive".into());
        }
        let left_axis = option_in(params, "left-axis", 0, &[0, 1])? as usize;
        let left_sign = option_in(params, "left-sign", 1, &[1, -1])? as f64;
        let right_sign = option_in(params, "right-sign", 1, &[1, -1])? as f64;
        let mut signs = [right_sign; 2];
        signs[left_axis] = left_sign;
        let poll_ms = match params.text("poll-ms") {
            None => 100,
            Some(_) => params.integer("poll-ms")?,
        };
        let poll_ms = u32::try_from(poll_ms)
            .ok()
            .filter(|p| (POLL_MS_RANGE.0..=POLL_MS_RANGE.1).contains(p))
            .ok_or_else(|| format!("option 'poll-ms': {poll_ms} is not within {POLL_MS_RANGE:?}"))?;
        Ok(ODrive {
            geometry,
            odometry,
            turns_per_metre,
            left_axis,
            signs,
            checksum: switch(params, "checksum", "on", "off", false)?,
            arm: switch(params, "arm", "yes", "no", true)?,
            poll_ms,
            polls: 0,
            expected: VecDeque::new(),
            line: Vec::new(),
            skipping: false,
            fresh: [None, None],
            last: None,
            errors: [None, None],
            fault: None,
        })
    }

    fn link(&self) -> LinkPlan {
        let (opening, closing) = if self.arm {
            let mut opening =
                self.for_both_axes(|a| format!("w axis{a}.controller.config.control_mode {CONTROL_MODE_VELOCITY}"));
            opening
                .extend(self.for_both_axes(|a| format!("w axis{a}.requested_state {AXIS_STATE_CLOSED_LOOP_CONTROL}")));
            (opening, self.for_both_axes(|a| format!("w axis{a}.requested_state {AXIS_STATE_IDLE}")))
        } else {
            (Vec::new(), Vec::new())
        };
        LinkPlan { opening, poll_period_ms: self.poll_ms, closing }
    }

    fn encode(&mut self, command: &str) -> Result<Vec<u8>, String> {
        let (left, right) = self.geometry.command(command)?;
        let mut speeds = [right; 2];
        speeds[self.left_axis] = left;
        Ok(self.for_both_axes(|a| format!("v {a} {}", number(speeds[a] * self.turns_per_metre * self.signs[a]))))
    }

    fn decode(&mut self, bytes: &[u8]) -> Decoded {
        let mut decoded = Decoded { feedback: Vec::new(), malformed: 0 };
        for &byte in bytes {
            if byte == b'\n' {
                if std::mem::take(&mut self.skipping) {
                    continue;
                }
                let line = std::mem::take(&mut self.line);
                let Ok(text) = std::str::from_utf8(&line) else {
                    decoded.malformed += 1;
                    continue;
                };
                let text = text.trim_end_matches('\r');
                if !text.trim().is_empty() && !self.take_line(text, &mut decoded.feedback) {
                    decoded.malformed += 1;
                }
            } else if !self.skipping {
                if self.line.len() >= MAX_LINE {
                    self.line.clear();
                    self.skipping = true;
                    decoded.malformed += 1;
                } else {
                    self.line.push(byte);
                }
            }
        }
        decoded
    }

    fn poll(&mut self, _now_ns: u64) -> Vec<u8> {
        let mut out = self.for_both_axes(|a| format!("u {a}"));
        out.extend(self.for_both_axes(|a| format!("f {a}")));
        self.expected.extend([Expected::Feedback(0), Expected::Feedback(1)]);
        if self.polls.is_multiple_of(VOLTAGE_EVERY) {
            self.push_line("r vbus_voltage", &mut out);
            self.expected.push_back(Expected::Voltage);
        }
        if self.polls % ERRORS_EVERY == ERRORS_AT {
            for axis in 0..2 {
                self.push_line(&format!("r axis{axis}.error"), &mut out);
                self.expected.push_back(Expected::AxisError(axis));
            }
        }
        self.polls += 1;
        while self.expected.len() > MAX_EXPECTED {
            self.expected.pop_front();
        }
        out
    }

    fn fault(&mut self) -> Option<String> {
        self.fault.take()
    }
}

subsume_guest::translator!(ODrive);
