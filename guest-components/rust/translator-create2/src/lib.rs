//! A hardware translator for the iRobot Create 2 Open Interface (OI), as a
//! WASM component of the `translator` world.
//!
//! - Opening: Start (128), Safe (131, or Full 132 with `mode=full`), and
//!   Stream (148) of the packets below, which the robot then sends every
//!   15 ms as `19 N [id data]... checksum`.
//! - Commands: Drive Direct (145) with the right and then the left wheel
//!   speed, big-endian i16 mm/s in [-500, 500]; STOP is Drive Direct 0 0.
//! - Feedback: the stream's bumps (7) become the bumper; encoder counts
//!   (43 left, 44 right: 508.8 counts per turn of a 72 mm wheel) become
//!   odometry by dead reckoning from `origin-x/y/heading`; the battery
//!   voltage (22, mV) the battery; the six light-bump signals (46-51,
//!   0-4095) become ranges, right to left, only with `light-bump-range`
//!   set (see docs/protocols.md: the signal is not a calibrated distance).
//! - Poll (every second): when no stream frame arrived since the last poll
//!   (the robot was power-cycled, or dropped to Passive), the opening is
//!   sent again.
//! - Closing: Pause Stream (150 0), then Stop (173): the OI goes off.
//!
//! Options (the link's `options`): `mode=safe|full`, `origin-x`, `origin-y`,
//! `origin-heading`, `light-bump-range` (metres; 0, the default, reports no
//! ranges).

use subsume_guest::drive::{Geometry, Odometry};
use subsume_guest::{Decoded, Feedback, LinkPlan, Params, Translator};

const START: u8 = 128;
const SAFE: u8 = 131;
const FULL: u8 = 132;
const DRIVE_DIRECT: u8 = 145;
const STREAM: u8 = 148;
const PAUSE_RESUME_STREAM: u8 = 150;
const STOP: u8 = 173;
/// First byte of every stream frame.
const STREAM_HEADER: u8 = 19;

const BUMPS_AND_WHEEL_DROPS: u8 = 7;
const VOLTAGE: u8 = 22;
const LEFT_ENCODER: u8 = 43;
const RIGHT_ENCODER: u8 = 44;
/// Light-bump signals, left to right.
const LIGHT_BUMPS: [u8; 6] = [46, 47, 48, 49, 50, 51];
/// The packets streamed, in order.
const STREAMED: [u8; 10] = [BUMPS_AND_WHEEL_DROPS, VOLTAGE, LEFT_ENCODER, RIGHT_ENCODER, 46, 47, 48, 49, 50, 51];

/// The payload of a frame of the packets streamed: one id byte each and
/// their data. A longer N marks a 19 that is no header.
const STREAMED_PAYLOAD: usize = STREAMED.len() + 1 + 2 + 2 + 2 + 6 * 2;

/// The OI's speed limit for one wheel, mm/s.
const MAX_WHEEL_MM_S: f64 = 500.0;
/// Metres of wheel travel per encoder count: a 72 mm wheel, 508.8 counts a
/// turn (OI specification, packets 43 and 44).
const METRES_PER_COUNT: f64 = std::f64::consts::PI * 0.072 / 508.8;
/// Largest light-bump signal.
const LIGHT_BUMP_MAX: f64 = 4095.0;
/// Most bytes kept while waiting for the rest of a frame.
const MAX_BUFFER: usize = 1024;
/// How often the translator checks that the stream flows.
const POLL_PERIOD_MS: u32 = 1000;

struct Create2 {
    geometry: Geometry,
    odometry: Odometry,
    mode: u8,
    light_bump_range: f64,
    buffer: Vec<u8>,
    /// The last encoder counts (left, right).
    counts: Option<(u16, u16)>,
    /// Whether a stream frame arrived since the last poll.
    frames_since_poll: bool,
    polled: bool,
}

/// Size of the data of packet `id`, for the packets this translator reads.
fn packet_size(id: u8) -> Option<usize> {
    match id {
        BUMPS_AND_WHEEL_DROPS => Some(1),
        VOLTAGE | LEFT_ENCODER | RIGHT_ENCODER | 46..=51 => Some(2),
        _ => None,
    }
}

impl Create2 {
    fn opening(&self) -> Vec<u8> {
        let mut bytes = vec![START, self.mode, STREAM, STREAMED.len() as u8];
        bytes.extend_from_slice(&STREAMED);
        bytes
    }

    /// The feedback of one frame's payload, or `None` when it is malformed.
    fn frame(&mut self, payload: &[u8], out: &mut Vec<Feedback>) -> Option<()> {
        let mut bumper = None;
        let mut voltage = None;
        let (mut left, mut right) = (None, None);
        let mut lights = [None; 6];
        let mut rest = payload;
        while let [id, tail @ ..] = rest {
            let size = packet_size(*id)?;
            let data = tail.get(..size)?;
            let word = || u16::from_be_bytes([data[0], data.get(1).copied().unwrap_or(0)]);
            match *id {
                BUMPS_AND_WHEEL_DROPS => bumper = Some(data[0] & 0b11 != 0),
                VOLTAGE => voltage = Some(word()),
                LEFT_ENCODER => left = Some(word()),
                RIGHT_ENCODER => right = Some(word()),
                light => {
                    let slot = LIGHT_BUMPS.iter().position(|l| *l == light)?;
                    lights[slot] = Some(word());
                }
            }
            rest = &tail[size..];
        }
        if let (Some(left), Some(right)) = (left, right) {
            if let Some((old_left, old_right)) = self.counts {
                // Counts wrap at 16 bits: the difference is the travel.
                let dl = left.wrapping_sub(old_left) as i16;
                let dr = right.wrapping_sub(old_right) as i16;
                self.odometry.advance(f64::from(dl) * METRES_PER_COUNT, f64::from(dr) * METRES_PER_COUNT);
            }
            self.counts = Some((left, right));
            out.push(Feedback::Odometry(self.odometry.pose()));
        }
        if self.light_bump_range > 0.0 && lights.iter().all(Option::is_some) {
            let ranges = lights
                .iter()
                .rev()
                .map(|s| {
                    let signal = f64::from(s.unwrap_or(0)).min(LIGHT_BUMP_MAX);
                    self.light_bump_range * (1.0 - signal / LIGHT_BUMP_MAX)
                })
                .collect();
            out.push(Feedback::Ranges(ranges));
        }
        if let Some(bumper) = bumper {
            out.push(Feedback::Bumper(bumper));
        }
        if let Some(mv) = voltage {
            out.push(Feedback::Battery(f64::from(mv) / 1000.0));
        }
        Some(())
    }
}

impl Translator for Create2 {
    fn init(params: &Params) -> Result<Self, String> {
        let geometry = Geometry::from_params(params, 0.235, 0.5)?;
        let odometry = Odometry::from_params(params, geometry.wheel_base)?;
        let mode = match params.text("mode").map(str::trim) {
            None | Some("safe") => SAFE,
            Some("full") => FULL,
            Some(other) => return Err(format!("option 'mode': '{other}' is not safe or full")),
        };
        let light_bump_range = match params.text("light-bump-range") {
            None => 0.0,
            Some(_) => params.number("light-bump-range")?,
        };
        if !(light_bump_range.is_finite() && light_bump_range >= 0.0) {
            return Err("option 'light-bump-range' must be 0 or more metres".into());
        }
        Ok(Create2 {
            geometry,
            odometry,
            mode,
            light_bump_range,
            buffer: Vec::new(),
            counts: None,
            frames_since_poll: false,
            polled: false,
        })
    }

    fn link(&self) -> LinkPlan {
        LinkPlan {
            opening: self.opening(),
            poll_period_ms: POLL_PERIOD_MS,
            closing: vec![PAUSE_RESUME_STREAM, 0, STOP],
        }
    }

    fn encode(&mut self, command: &str) -> Result<Vec<u8>, String> {
        let (left, right) = self.geometry.command(command)?;
        let mm = |v: f64| (v * 1000.0).round().clamp(-MAX_WHEEL_MM_S, MAX_WHEEL_MM_S) as i16;
        let mut bytes = vec![DRIVE_DIRECT];
        bytes.extend_from_slice(&mm(right).to_be_bytes());
        bytes.extend_from_slice(&mm(left).to_be_bytes());
        Ok(bytes)
    }

    fn decode(&mut self, bytes: &[u8]) -> Decoded {
        let mut decoded = Decoded { feedback: Vec::new(), malformed: 0 };
        self.buffer.extend_from_slice(bytes);
        loop {
            let Some(start) = self.buffer.iter().position(|b| *b == STREAM_HEADER) else {
                if !self.buffer.is_empty() {
                    decoded.malformed += 1;
                    self.buffer.clear();
                }
                break;
            };
            if start > 0 {
                decoded.malformed += 1;
                self.buffer.drain(..start);
            }
            let Some(&n) = self.buffer.get(1) else { break };
            if usize::from(n) > STREAMED_PAYLOAD {
                decoded.malformed += 1;
                self.buffer.drain(..1);
                continue;
            }
            let total = usize::from(n) + 3;
            if self.buffer.len() < total {
                break;
            }
            let sum = self.buffer[..total].iter().fold(0u8, |s, b| s.wrapping_add(*b));
            if sum != 0 {
                // Not a frame (or a damaged one): look for the next header.
                decoded.malformed += 1;
                self.buffer.drain(..1);
                continue;
            }
            let payload: Vec<u8> = self.buffer[2..total - 1].to_vec();
            self.buffer.drain(..total);
            let mut feedback = Vec::new();
            match self.frame(&payload, &mut feedback) {
                Some(()) => {
                    self.frames_since_poll = true;
                    decoded.feedback.extend(feedback);
                }
                None => decoded.malformed += 1,
            }
        }
        if self.buffer.len() > MAX_BUFFER {
            self.buffer.clear();
            decoded.malformed += 1;
        }
        decoded
    }

    fn poll(&mut self, _now_ns: u64) -> Vec<u8> {
        let silent = self.polled && !self.frames_since_poll;
        self.polled = true;
        self.frames_since_poll = false;
        if silent { self.opening() } else { Vec::new() }
    }
}

subsume_guest::translator!(Create2);
