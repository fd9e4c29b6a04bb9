//! A hardware translator as a WASM component (the `translator` world): the
//! readable ASCII motor protocol of docs/protocols.md, written in the guest.
//! Host -> controller: `M <left mm/s> <right mm/s>` and `S`; controller ->
//! host: `O x y heading`, `R mm...`, `B 0|1`, `P mV`, `F [text]` (the
//! controller's fault status, handed to the host with `Translator::fault`:
//! the last one a `decode` completes).

use subsume_guest::{Decoded, Feedback, Params, Pose, Translator};

/// Longest line kept; longer ones are garbage.
const MAX_LINE: usize = 512;
/// Longest fault text kept, bytes (as the built-in profile's).
const MAX_FAULT: usize = 200;

struct AsciiTranslator {
    wheel_base: f64,
    max_wheel_speed: f64,
    line: Vec<u8>,
    skipping: bool,
    /// The fault status the last `F` line said, for the host to take.
    fault: Option<String>,
}

fn milli(value: f64) -> i64 {
    if value.is_finite() { (value * 1000.0).round() as i64 } else { 0 }
}

impl Translator for AsciiTranslator {
    fn init(params: &Params) -> Result<Self, String> {
        let number = |name: &str, default: f64| params.text(name).map_or(Ok(default), |_| params.number(name));
        let translator = AsciiTranslator {
            wheel_base: number("wheel-base", 0.3)?,
            max_wheel_speed: number("max-wheel-speed", 0.5)?,
            line: Vec::new(),
            skipping: false,
            fault: None,
        };
        if translator.wheel_base <= 0.0 || translator.max_wheel_speed <= 0.0 {
            return Err("wheel-base and max-wheel-speed must be positive".into());
        }
        Ok(translator)
    }

    fn encode(&mut self, command: &str) -> Result<Vec<u8>, String> {
        let words: Vec<&str> = command.split_ascii_whitespace().collect();
        match words.as_slice() {
            [stop] if stop.eq_ignore_ascii_case("STOP") => Ok(b"S\n".to_vec()),
            [vel, linear, angular] if vel.eq_ignore_ascii_case("VEL") => {
                let linear: f64 = linear.parse().map_err(|_| format!("bad linear speed '{linear}'"))?;
                let angular: f64 = angular.parse().map_err(|_| format!("bad angular speed '{angular}'"))?;
                let half = angular * self.wheel_base / 2.0;
                let (mut left, mut right) = (linear - half, linear + half);
                let fastest = left.abs().max(right.abs());
                if fastest > self.max_wheel_speed {
                    let scale = self.max_wheel_speed / fastest;
                    left *= scale;
                    right *= scale;
                }
                Ok(format!("M {} {}\n", milli(left), milli(right)).into_bytes())
            }
            _ => Err(format!("the motors take STOP and VEL, not '{command}'")),
        }
    }

    fn decode(&mut self, bytes: &[u8]) -> Decoded {
        let mut decoded = Decoded { feedback: Vec::new(), malformed: 0 };
        for &byte in bytes {
            if byte == b'\n' {
                if self.skipping {
                    self.skipping = false;
                } else {
                    let line = std::mem::take(&mut self.line);
                    if let Some(fault) = fault_line(&line) {
                        self.fault = Some(fault);
                        continue;
                    }
                    match parse(&line) {
                        Some(Some(feedback)) => decoded.feedback.push(feedback),
                        Some(None) => {}
                        None => decoded.malformed += 1,
                    }
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

    fn fault(&mut self) -> Option<String> {
        self.fault.take()
    }
}

/// The text of an `F` line (its words one space apart, at most
/// `MAX_FAULT` bytes; empty: no fault), or `None` for any other line.
fn fault_line(line: &[u8]) -> Option<String> {
    let text = std::str::from_utf8(line).ok()?;
    let mut words = text.split_ascii_whitespace();
    if words.next() != Some("F") {
        return None;
    }
    let mut fault = words.collect::<Vec<_>>().join(" ");
    if fault.len() > MAX_FAULT {
        let mut end = MAX_FAULT;
        while !fault.is_char_boundary(end) {
            end -= 1;
        }
        fault.truncate(end);
        fault.truncate(fault.trim_end().len());
    }
    Some(fault)
}

/// `Some(Some(feedback))`, `Some(None)` for a blank line, `None` for garbage.
fn parse(line: &[u8]) -> Option<Option<Feedback>> {
    let text = std::str::from_utf8(line).ok()?.trim_end_matches('\r');
    let mut words = text.split_ascii_whitespace();
    let Some(kind) = words.next() else { return Some(None) };
    let numbers: Vec<i64> = words.map(|w| w.parse::<i64>().ok()).collect::<Option<_>>()?;
    let m = |v: i64| v as f64 / 1000.0;
    Some(Some(match (kind, numbers.as_slice()) {
        ("O", [x, y, heading]) => Feedback::Odometry(Pose { x: m(*x), y: m(*y), heading: m(*heading) }),
        ("R", ranges) if ranges.len() <= 64 && ranges.iter().all(|r| *r >= 0) => {
            Feedback::Ranges(ranges.iter().map(|r| m(*r)).collect())
        }
        ("B", [hit @ (0 | 1)]) => Feedback::Bumper(*hit == 1),
        ("P", [mv]) if *mv >= 0 => Feedback::Battery(m(*mv)),
        _ => return None,
    }))
}

subsume_guest::translator!(AsciiTranslator);
