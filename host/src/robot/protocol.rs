//! The motor controller's serial protocols, both directions: the host side
//! (translator) encodes motor commands and decodes feedback; the controller
//! side (the simulated robot, or real firmware) decodes commands and encodes
//! feedback. Two built-in profiles, documented in `docs/protocols.md`:
//!
//! - `ascii`: readable lines. Host -> controller `M <left mm/s> <right mm/s>`
//!   and `S`; controller -> host `O <x mm> <y mm> <heading mrad>`,
//!   `R <mm> <mm> ...`, `B <0|1>`, `P <mV>`, `F [text]` (the controller's
//!   fault, none when the text is empty). Lines end in `\n` (a `\r` before
//!   it is ignored).
//! - `binary`: frames `A5 LEN TYPE PAYLOAD CHK`, LEN = 1 + payload length,
//!   CHK chosen so that TYPE + PAYLOAD + CHK = 0 (mod 256); little-endian
//!   integers. Types: 01 wheels (i16 left, i16 right, mm/s), 02 stop,
//!   81 odometry (i32 x mm, i32 y mm, i16 heading mrad), 82 ranges (u16 mm
//!   each), 83 bumper (u8), 84 battery (u16 mV), 85 fault (UTF-8 text, at
//!   most [`MAX_FAULT_BYTES`]; empty: no fault).
//!
//! Decoders are streaming: bytes arrive in any chunks; malformed input is
//! skipped and counted, never fatal.

/// Longest ASCII line kept; a longer one is garbage and is dropped whole.
pub const MAX_LINE_BYTES: usize = 512;
/// Most range readings in one feedback message.
pub const MAX_RANGES: usize = 64;
/// Largest magnitude of a number on an ascii line, in thousandths (a million
/// metres, volts or radians): nothing a controller sends is larger, and up to
/// it a value survives the trip through f64 exactly, so re-encoding a decoded
/// message gives the same bytes.
pub const MAX_ASCII_MAGNITUDE: i64 = 1_000_000_000;
/// Longest fault text a controller's message carries, bytes: a binary
/// frame's LEN is one byte, and a longer text is more than a person reads in
/// a status line (a longer one is cut at a character boundary when encoded).
pub const MAX_FAULT_BYTES: usize = 200;
/// Start byte of a binary frame.
pub const FRAME_START: u8 = 0xA5;

/// What the motors are told.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum MotorCommand {
    /// Wheel surface speeds in m/s, forward positive.
    Wheels {
        left: f64,
        right: f64,
    },
    Stop,
}

/// What the controller reports back.
#[derive(Clone, Debug, PartialEq)]
pub enum Feedback {
    /// Pose by odometry: metres, metres, radians.
    Odometry {
        x: f64,
        y: f64,
        heading: f64,
    },
    /// Range readings in metres, rays from right to left.
    Ranges(Vec<f64>),
    Bumper(bool),
    /// Battery voltage in volts.
    Battery(f64),
    /// The controller's fault status as it last read it: the fault's text
    /// (naming what is wrong, e.g. "m1 over current warning"), or `None`
    /// when it reports none.
    Fault(Option<String>),
}

/// A built-in wire profile.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Profile {
    Ascii,
    Binary,
}

impl Profile {
    pub fn parse(name: &str) -> Option<Profile> {
        match name {
            "ascii" => Some(Profile::Ascii),
            "binary" => Some(Profile::Binary),
            _ => None,
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            Profile::Ascii => "ascii",
            Profile::Binary => "binary",
        }
    }

    /// Appends the bytes of `command` to `out`.
    pub fn encode_command(self, command: &MotorCommand, out: &mut Vec<u8>) {
        match (self, command) {
            (Profile::Ascii, MotorCommand::Stop) => out.extend_from_slice(b"S\n"),
            (Profile::Ascii, MotorCommand::Wheels { left, right }) => {
                out.extend_from_slice(format!("M {} {}\n", mm(*left), mm(*right)).as_bytes());
            }
            (Profile::Binary, MotorCommand::Stop) => frame(0x02, &[], out),
            (Profile::Binary, MotorCommand::Wheels { left, right }) => {
                let mut payload = [0u8; 4];
                payload[..2].copy_from_slice(&clamp_i16(mm(*left)).to_le_bytes());
                payload[2..].copy_from_slice(&clamp_i16(mm(*right)).to_le_bytes());
                frame(0x01, &payload, out);
            }
        }
    }

    /// Appends the bytes of `feedback` to `out`.
    pub fn encode_feedback(self, feedback: &Feedback, out: &mut Vec<u8>) {
        match self {
            Profile::Ascii => {
                let line = match feedback {
                    Feedback::Odometry { x, y, heading } => format!("O {} {} {}\n", mm(*x), mm(*y), mm(*heading)),
                    Feedback::Ranges(ranges) => {
                        let mut line = String::from("R");
                        for r in ranges.iter().take(MAX_RANGES) {
                            line.push(' ');
                            line.push_str(&mm(*r).to_string());
                        }
                        line.push('\n');
                        line
                    }
                    Feedback::Bumper(hit) => format!("B {}\n", u8::from(*hit)),
                    Feedback::Battery(volts) => format!("P {}\n", mm(*volts)),
                    Feedback::Fault(None) => "F\n".to_string(),
                    Feedback::Fault(Some(text)) => format!("F {}\n", fault_text(text)),
                };
                out.extend_from_slice(line.as_bytes());
            }
            Profile::Binary => match feedback {
                Feedback::Odometry { x, y, heading } => {
                    let mut payload = Vec::with_capacity(10);
                    payload.extend_from_slice(&(mm(*x).clamp(i32::MIN as i64, i32::MAX as i64) as i32).to_le_bytes());
                    payload.extend_from_slice(&(mm(*y).clamp(i32::MIN as i64, i32::MAX as i64) as i32).to_le_bytes());
                    payload.extend_from_slice(&clamp_i16(mm(*heading)).to_le_bytes());
                    frame(0x81, &payload, out);
                }
                Feedback::Ranges(ranges) => {
                    let payload: Vec<u8> = ranges
                        .iter()
                        .take(MAX_RANGES)
                        .flat_map(|r| (mm(*r).clamp(0, u16::MAX as i64) as u16).to_le_bytes())
                        .collect();
                    frame(0x82, &payload, out);
                }
                Feedback::Bumper(hit) => frame(0x83, &[u8::from(*hit)], out),
                Feedback::Battery(volts) => {
                    frame(0x84, &(mm(*volts).clamp(0, u16::MAX as i64) as u16).to_le_bytes(), out)
                }
                Feedback::Fault(text) => frame(0x85, fault_text(text.as_deref().unwrap_or_default()).as_bytes(), out),
            },
        }
    }
}

/// A fault's text as a message carries it: words separated by one space
/// (no line break can end an ascii line early), at most
/// [`MAX_FAULT_BYTES`].
fn fault_text(text: &str) -> String {
    let mut words = text.split_ascii_whitespace().collect::<Vec<_>>().join(" ");
    if words.len() > MAX_FAULT_BYTES {
        let mut end = MAX_FAULT_BYTES;
        while !words.is_char_boundary(end) {
            end -= 1;
        }
        words.truncate(end);
        words.truncate(words.trim_end().len());
    }
    words
}

/// Metres (or volts, radians) to whole thousandths.
fn mm(value: f64) -> i64 {
    if value.is_finite() { (value * 1000.0).round() as i64 } else { 0 }
}

fn clamp_i16(value: i64) -> i16 {
    value.clamp(i16::MIN as i64, i16::MAX as i64) as i16
}

fn frame(kind: u8, payload: &[u8], out: &mut Vec<u8>) {
    let sum = payload.iter().fold(kind, |acc, b| acc.wrapping_add(*b));
    out.push(FRAME_START);
    out.push((payload.len() + 1) as u8);
    out.push(kind);
    out.extend_from_slice(payload);
    out.push(0u8.wrapping_sub(sum));
}

/// One decoded message of either direction.
#[derive(Clone, Debug, PartialEq)]
pub enum Message {
    Command(MotorCommand),
    Feedback(Feedback),
}

/// A streaming decoder of one profile. Feed it bytes as they arrive; it
/// yields whole messages and counts what it had to skip.
#[derive(Debug)]
pub struct Decoder {
    profile: Profile,
    pending: Vec<u8>,
    /// Dropping the rest of an over-long ASCII line.
    skipping: bool,
    malformed: u64,
}

impl Decoder {
    pub fn new(profile: Profile) -> Decoder {
        Decoder { profile, pending: Vec::new(), skipping: false, malformed: 0 }
    }

    /// Messages (or garbage) skipped so far.
    pub fn malformed(&self) -> u64 {
        self.malformed
    }

    /// Decodes what `bytes` complete; partial messages wait for more bytes.
    pub fn feed(&mut self, bytes: &[u8], out: &mut Vec<Message>) {
        match self.profile {
            Profile::Ascii => self.feed_ascii(bytes, out),
            Profile::Binary => self.feed_binary(bytes, out),
        }
    }

    fn feed_ascii(&mut self, bytes: &[u8], out: &mut Vec<Message>) {
        for &byte in bytes {
            if byte == b'\n' {
                if self.skipping {
                    self.skipping = false;
                } else {
                    let line = std::mem::take(&mut self.pending);
                    match parse_ascii_line(&line) {
                        Some(Some(message)) => out.push(message),
                        Some(None) => {}
                        None => self.malformed += 1,
                    }
                }
            } else if !self.skipping {
                if self.pending.len() >= MAX_LINE_BYTES {
                    self.pending.clear();
                    self.skipping = true;
                    self.malformed += 1;
                } else {
                    self.pending.push(byte);
                }
            }
        }
    }

    fn feed_binary(&mut self, bytes: &[u8], out: &mut Vec<Message>) {
        self.pending.extend_from_slice(bytes);
        let mut start = 0;
        loop {
            // Resynchronise on the start byte.
            match self.pending[start..].iter().position(|&b| b == FRAME_START) {
                Some(0) => {}
                Some(skip) => {
                    self.malformed += 1;
                    start += skip;
                }
                None => {
                    if start < self.pending.len() {
                        self.malformed += 1;
                    }
                    start = self.pending.len();
                    break;
                }
            }
            let rest = &self.pending[start..];
            let Some(&len) = rest.get(1) else { break };
            let len = len as usize;
            if len == 0 {
                self.malformed += 1;
                start += 1;
                continue;
            }
            let total = 2 + len + 1;
            if rest.len() < total {
                break;
            }
            let body = &rest[2..2 + len];
            let check = rest[2 + len];
            let sum = body.iter().fold(check, |acc, b| acc.wrapping_add(*b));
            match (sum == 0).then(|| parse_binary_body(body)).flatten() {
                Some(message) => {
                    out.push(message);
                    start += total;
                }
                None => {
                    // Bad checksum or unknown content: skip the start byte
                    // and look for the next frame inside these bytes.
                    self.malformed += 1;
                    start += 1;
                }
            }
        }
        self.pending.drain(..start);
        if self.pending.len() > 2 + 255 + 1 {
            // Cannot happen with LEN <= 255; bounds memory all the same.
            self.pending.clear();
        }
    }
}

/// `Some(Some(message))`: a message; `Some(None)`: a blank line; `None`: garbage.
fn parse_ascii_line(line: &[u8]) -> Option<Option<Message>> {
    let text = std::str::from_utf8(line).ok()?.trim_end_matches('\r');
    let mut words = text.split_ascii_whitespace();
    let Some(kind) = words.next() else { return Some(None) };
    if kind == "F" {
        let text = fault_text(&words.collect::<Vec<_>>().join(" "));
        return Some(Some(Message::Feedback(Feedback::Fault((!text.is_empty()).then_some(text)))));
    }
    let numbers: Option<Vec<i64>> =
        words.map(|w| w.parse::<i64>().ok().filter(|v| v.abs() <= MAX_ASCII_MAGNITUDE)).collect();
    let n = numbers?;
    let milli = |v: i64| v as f64 / 1000.0;
    let message = match (kind, n.as_slice()) {
        ("S", []) => Message::Command(MotorCommand::Stop),
        ("M", [left, right]) => Message::Command(MotorCommand::Wheels { left: milli(*left), right: milli(*right) }),
        ("O", [x, y, heading]) => {
            Message::Feedback(Feedback::Odometry { x: milli(*x), y: milli(*y), heading: milli(*heading) })
        }
        ("R", ranges) if ranges.len() <= MAX_RANGES && ranges.iter().all(|r| *r >= 0) => {
            Message::Feedback(Feedback::Ranges(ranges.iter().map(|r| milli(*r)).collect()))
        }
        ("B", [hit @ (0 | 1)]) => Message::Feedback(Feedback::Bumper(*hit == 1)),
        ("P", [millivolts]) if *millivolts >= 0 => Message::Feedback(Feedback::Battery(milli(*millivolts))),
        _ => return None,
    };
    Some(Some(message))
}

fn parse_binary_body(body: &[u8]) -> Option<Message> {
    let (&kind, payload) = body.split_first()?;
    let i16_at = |i: usize| payload.get(i..i + 2).map(|b| i16::from_le_bytes([b[0], b[1]]) as f64 / 1000.0);
    let i32_at = |i: usize| payload.get(i..i + 4).map(|b| i32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f64 / 1000.0);
    Some(match (kind, payload.len()) {
        (0x01, 4) => Message::Command(MotorCommand::Wheels { left: i16_at(0)?, right: i16_at(2)? }),
        (0x02, 0) => Message::Command(MotorCommand::Stop),
        (0x81, 10) => Message::Feedback(Feedback::Odometry { x: i32_at(0)?, y: i32_at(4)?, heading: i16_at(8)? }),
        (0x82, n) if n % 2 == 0 && n / 2 <= MAX_RANGES => Message::Feedback(Feedback::Ranges(
            payload.chunks_exact(2).map(|b| u16::from_le_bytes([b[0], b[1]]) as f64 / 1000.0).collect(),
        )),
        (0x83, 1) if payload[0] <= 1 => Message::Feedback(Feedback::Bumper(payload[0] == 1)),
        (0x84, 2) => Message::Feedback(Feedback::Battery(u16::from_le_bytes([payload[0], payload[1]]) as f64 / 1000.0)),
        (0x85, n) if n <= MAX_FAULT_BYTES => {
            let text = std::str::from_utf8(payload).ok()?;
            if fault_text(text) != text {
                return None;
            }
            Message::Feedback(Feedback::Fault((!text.is_empty()).then(|| text.to_string())))
        }
        _ => return None,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn encode_command(profile: Profile, command: MotorCommand) -> Vec<u8> {
        let mut out = Vec::new();
        profile.encode_command(&command, &mut out);
        out
    }

    fn encode_feedback(profile: Profile, feedback: Feedback) -> Vec<u8> {
        let mut out = Vec::new();
        profile.encode_feedback(&feedback, &mut out);
        out
    }

    #[test]
    fn golden_bytes_of_the_ascii_profile() {
        let a = Profile::Ascii;
        assert_eq!(encode_command(a, MotorCommand::Stop), b"S\n");
        assert_eq!(encode_command(a, MotorCommand::Wheels { left: 0.125, right: -0.3 }), b"M 125 -300\n");
        assert_eq!(encode_feedback(a, Feedback::Odometry { x: 1.5, y: -2.0, heading: 0.8125 }), b"O 1500 -2000 813\n");
        assert_eq!(encode_feedback(a, Feedback::Ranges(vec![0.5, 4.0])), b"R 500 4000\n");
        assert_eq!(encode_feedback(a, Feedback::Bumper(true)), b"B 1\n");
        assert_eq!(encode_feedback(a, Feedback::Battery(12.25)), b"P 12250\n");
        assert_eq!(encode_feedback(a, Feedback::Fault(Some("m1  over\ncurrent".into()))), b"F m1 over current\n");
        assert_eq!(encode_feedback(a, Feedback::Fault(None)), b"F\n");
    }

    #[test]
    fn golden_bytes_of_the_binary_profile() {
        let b = Profile::Binary;
        assert_eq!(encode_command(b, MotorCommand::Stop), [0xA5, 0x01, 0x02, 0xFE]);
        // left 125 = 0x007D, right -300 = 0xFED4; sum 01+7D+00+D4+FE = 0x250 -> CHK 0xB0.
        assert_eq!(
            encode_command(b, MotorCommand::Wheels { left: 0.125, right: -0.3 }),
            [0xA5, 0x05, 0x01, 0x7D, 0x00, 0xD4, 0xFE, 0xB0]
        );
        assert_eq!(encode_feedback(b, Feedback::Bumper(true)), [0xA5, 0x02, 0x83, 0x01, 0x7C]);
        assert_eq!(encode_feedback(b, Feedback::Ranges(vec![0.5])), [0xA5, 0x03, 0x82, 0xF4, 0x01, 0x89]);
        // 85 'e' 'x': 0x85+0x65+0x78 = 0x162 -> CHK 0x9E; no fault: 85 alone, CHK 0x7B.
        assert_eq!(encode_feedback(b, Feedback::Fault(Some("ex".into()))), [0xA5, 0x03, 0x85, 0x65, 0x78, 0x9E]);
        assert_eq!(encode_feedback(b, Feedback::Fault(None)), [0xA5, 0x01, 0x85, 0x7B]);
    }

    #[test]
    fn every_message_round_trips_through_both_profiles_in_any_chunking() {
        let messages = vec![
            Message::Command(MotorCommand::Wheels { left: 0.25, right: -0.5 }),
            Message::Command(MotorCommand::Stop),
            Message::Feedback(Feedback::Odometry { x: 3.25, y: -1.5, heading: 3.125 }),
            Message::Feedback(Feedback::Ranges(vec![0.25, 1.0, 3.999])),
            Message::Feedback(Feedback::Bumper(false)),
            Message::Feedback(Feedback::Battery(11.9)),
            Message::Feedback(Feedback::Fault(Some("m2 current error; e-stop".into()))),
            Message::Feedback(Feedback::Fault(None)),
            Message::Feedback(Feedback::Fault(Some("x".repeat(MAX_FAULT_BYTES)))),
        ];
        for profile in [Profile::Ascii, Profile::Binary] {
            let mut bytes = Vec::new();
            for m in &messages {
                match m {
                    Message::Command(c) => profile.encode_command(c, &mut bytes),
                    Message::Feedback(f) => profile.encode_feedback(f, &mut bytes),
                }
            }
            for chunk in [1, 2, 3, 7, bytes.len()] {
                let mut decoder = Decoder::new(profile);
                let mut out = Vec::new();
                for piece in bytes.chunks(chunk) {
                    decoder.feed(piece, &mut out);
                }
                assert_eq!(out, messages, "{profile:?} in chunks of {chunk}");
                assert_eq!(decoder.malformed(), 0);
            }
        }
    }

    #[test]
    fn garbage_is_skipped_and_counted() {
        let mut decoder = Decoder::new(Profile::Ascii);
        let mut out = Vec::new();
        decoder.feed(b"hello\nM 1 2\nR -5\n\nB 7\n\xff\xfe\nS\n", &mut out);
        assert_eq!(
            out,
            vec![
                Message::Command(MotorCommand::Wheels { left: 0.001, right: 0.002 }),
                Message::Command(MotorCommand::Stop)
            ]
        );
        assert_eq!(decoder.malformed(), 4);
        let long = vec![b'x'; MAX_LINE_BYTES * 3];
        decoder.feed(&long, &mut out);
        decoder.feed(b"\nS\n", &mut out);
        assert_eq!(out.len(), 3);
        assert_eq!(decoder.malformed(), 5);

        let mut decoder = Decoder::new(Profile::Binary);
        let mut out = Vec::new();
        let mut bytes = vec![0x00, 0x13, 0x37];
        bytes.extend_from_slice(&[0xA5, 0x01, 0x02, 0x00]); // bad checksum
        bytes.extend_from_slice(&[0xA5, 0x01, 0x02, 0xFE]); // good stop
        bytes.extend_from_slice(&[0xA5, 0x01, 0x09, 0xF7]); // unknown type
        bytes.extend_from_slice(&[0xA5, 0x01, 0x02, 0xFE]); // good stop
        decoder.feed(&bytes, &mut out);
        assert_eq!(out, vec![Message::Command(MotorCommand::Stop), Message::Command(MotorCommand::Stop)]);
        assert!(decoder.malformed() >= 3, "{}", decoder.malformed());
    }

    #[test]
    fn numbers_too_large_to_be_readings_are_garbage() {
        // Found by the feedback fuzz target: beyond f64's exact range the
        // re-encoded line differed from the one decoded.
        let mut decoder = Decoder::new(Profile::Ascii);
        let mut out = Vec::new();
        decoder.feed(b"P 4444444444444442\nP 1000000000\nM -1000000001 0\n", &mut out);
        assert_eq!(out, vec![Message::Feedback(Feedback::Battery(1_000_000.0))]);
        assert_eq!(decoder.malformed(), 2);
    }
}
