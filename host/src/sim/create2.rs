//! The simulated robot's iRobot Create 2 Open Interface: the robot side of
//! the OI subset a driving translator uses (guest-components/rust/
//! translator-create2), so the demo can run "as a Create 2".
//!
//! Commands: Start (128: Passive), Safe (131), Full (132), Stop (173: Off),
//! Reset (7: Off), Drive Direct (145, right then left wheel, big-endian i16
//! mm/s; obeyed only in Safe or Full, as on the robot), Drive (137: read and
//! ignored), Stream (148), Pause/Resume Stream (150), Sensors (142) and
//! Query List (149) (read; not answered). Anything else is a malformed byte.
//!
//! Stream frames `19 N [id data]... checksum` carry the packets asked for
//! among: bumps (7), voltage (22, mV), encoder counts (43 left, 44 right,
//! 508.8 a turn of a 72 mm wheel, wrapping at 16 bits) and the six
//! light-bump signals (46-51, left to right). The encoder counts follow the
//! body's actual motion (a blocked robot's wheels do not count), and a
//! light-bump signal is `4095 * (1 - range / max-range)` of the ray it
//! stands for, which needs exactly six rays (docs/protocols.md).

use std::f64::consts::{PI, TAU};

/// The six light bumps, left to right, are rays 5 to 0.
pub const LIGHT_BUMP_RAYS: usize = 6;
/// Metres of wheel travel per encoder count.
pub const METRES_PER_COUNT: f64 = PI * 0.072 / 508.8;
/// Largest light-bump signal.
pub const LIGHT_BUMP_MAX: f64 = 4095.0;
/// Most packets one Stream command may ask for (the OI's own limit is the
/// frame's one-byte length).
pub const MAX_STREAMED_PACKETS: usize = 32;
/// Most command bytes kept while waiting for the rest of a command.
const MAX_PENDING: usize = 512;

const STREAM_HEADER: u8 = 19;

/// The OI's modes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Mode {
    Off,
    Passive,
    Safe,
    Full,
}

/// What the robot's wheels are told.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum WheelCommand {
    /// Left and right wheel speeds, m/s.
    Wheels(f64, f64),
    Stop,
}

/// What the sensors read when a frame is sent.
#[derive(Clone, Debug, PartialEq)]
pub struct Readings {
    pub bumper: bool,
    pub volts: f64,
    /// Range rays, right to left, and the longest range.
    pub ranges: Vec<f64>,
    pub max_range: f64,
}

/// The robot side of the Open Interface.
#[derive(Debug)]
pub struct OpenInterface {
    mode: Mode,
    pending: Vec<u8>,
    streamed: Vec<u8>,
    streaming: bool,
    wheel_base: f64,
    /// Wheel travel (left, right), metres.
    travel: (f64, f64),
    last_pose: Option<(f64, f64, f64)>,
    malformed: u64,
}

fn wrap(angle: f64) -> f64 {
    let a = angle.rem_euclid(TAU);
    if a > PI { a - TAU } else { a }
}

/// Whether the stream can carry packet `id`, and its size.
fn packet_size(id: u8) -> Option<usize> {
    match id {
        7 => Some(1),
        22 | 43 | 44 | 46..=51 => Some(2),
        _ => None,
    }
}

impl OpenInterface {
    pub fn new(wheel_base: f64) -> OpenInterface {
        OpenInterface {
            mode: Mode::Off,
            pending: Vec::new(),
            streamed: Vec::new(),
            streaming: false,
            wheel_base,
            travel: (0.0, 0.0),
            last_pose: None,
            malformed: 0,
        }
    }

    pub fn mode(&self) -> Mode {
        self.mode
    }

    /// Bytes skipped as malformed.
    pub fn malformed(&self) -> u64 {
        self.malformed
    }

    /// Reads command bytes; pushes the wheel commands they complete.
    pub fn feed(&mut self, bytes: &[u8], out: &mut Vec<WheelCommand>) {
        self.pending.extend_from_slice(bytes);
        let mut at = 0;
        while let Some(&opcode) = self.pending.get(at) {
            let rest = &self.pending[at + 1..];
            // Bytes after the opcode, or `None` until they are all here.
            let length = match opcode {
                7 | 128 | 131 | 132 | 173 => Some(0),
                142 | 150 => Some(1),
                137 | 145 => Some(4),
                148 | 149 => rest.first().map(|n| 1 + usize::from(*n)),
                _ => {
                    self.malformed += 1;
                    at += 1;
                    continue;
                }
            };
            let Some(length) = length else { break };
            let Some(data) = rest.get(..length) else { break };
            let data = data.to_vec();
            at += 1 + length;
            self.command(opcode, &data, out);
        }
        self.pending.drain(..at);
        if self.pending.len() > MAX_PENDING {
            self.malformed += self.pending.len() as u64;
            self.pending.clear();
        }
    }

    fn command(&mut self, opcode: u8, data: &[u8], out: &mut Vec<WheelCommand>) {
        match opcode {
            128 => {
                // Start from any mode: Passive, wheels stopped.
                self.mode = Mode::Passive;
                out.push(WheelCommand::Stop);
            }
            131 | 132 if self.mode != Mode::Off => {
                self.mode = if opcode == 131 { Mode::Safe } else { Mode::Full };
            }
            7 | 173 => {
                self.mode = Mode::Off;
                self.streaming = false;
                out.push(WheelCommand::Stop);
            }
            145 if matches!(self.mode, Mode::Safe | Mode::Full) => {
                let right = i16::from_be_bytes([data[0], data[1]]);
                let left = i16::from_be_bytes([data[2], data[3]]);
                let mm = |v: i16| f64::from(v.clamp(-500, 500)) / 1000.0;
                out.push(WheelCommand::Wheels(mm(left), mm(right)));
            }
            148 if self.mode != Mode::Off => {
                let ids = &data[1..];
                if ids.len() > MAX_STREAMED_PACKETS || ids.iter().any(|id| packet_size(*id).is_none()) {
                    self.malformed += 1;
                    return;
                }
                self.streamed = ids.to_vec();
                self.streaming = !ids.is_empty();
            }
            150 if self.mode != Mode::Off => self.streaming = data[0] == 1 && !self.streamed.is_empty(),
            // Valid, but nothing this robot acts on (or not in this mode).
            _ => {}
        }
    }

    /// Follows the body's motion: the wheels' travel that moved it from the
    /// last pose to `pose`.
    pub fn track(&mut self, pose: (f64, f64, f64)) {
        let (x, y, heading) = pose;
        if let Some((x0, y0, h0)) = self.last_pose {
            let turn = wrap(heading - h0);
            let mid = h0 + turn / 2.0;
            let distance = (x - x0) * mid.cos() + (y - y0) * mid.sin();
            let half = turn * self.wheel_base / 2.0;
            self.travel.0 += distance - half;
            self.travel.1 += distance + half;
        }
        self.last_pose = Some(pose);
    }

    /// The stream frame due now, if a stream is on.
    pub fn frame(&self, readings: &Readings) -> Option<Vec<u8>> {
        if !self.streaming || self.mode == Mode::Off {
            return None;
        }
        let counts = |travel: f64| ((travel / METRES_PER_COUNT).round() as i64).rem_euclid(1 << 16) as u16;
        let mut payload = Vec::new();
        for &id in &self.streamed {
            payload.push(id);
            match id {
                7 => payload.push(if readings.bumper { 0b11 } else { 0 }),
                22 => payload
                    .extend_from_slice(&((readings.volts * 1000.0).round().clamp(0.0, 65535.0) as u16).to_be_bytes()),
                43 => payload.extend_from_slice(&counts(self.travel.0).to_be_bytes()),
                44 => payload.extend_from_slice(&counts(self.travel.1).to_be_bytes()),
                46..=51 => {
                    let ray = LIGHT_BUMP_RAYS - 1 - usize::from(id - 46);
                    let range = readings.ranges.get(ray).copied().unwrap_or(readings.max_range);
                    let signal =
                        (LIGHT_BUMP_MAX * (1.0 - range / readings.max_range)).round().clamp(0.0, LIGHT_BUMP_MAX);
                    payload.extend_from_slice(&(signal as u16).to_be_bytes());
                }
                _ => {}
            }
        }
        let length = u8::try_from(payload.len()).ok()?;
        let mut frame = vec![STREAM_HEADER, length];
        frame.extend_from_slice(&payload);
        let sum = frame.iter().fold(0u8, |s, b| s.wrapping_add(*b));
        frame.push(0u8.wrapping_sub(sum));
        Some(frame)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn feed(oi: &mut OpenInterface, bytes: &[u8]) -> Vec<WheelCommand> {
        let mut out = Vec::new();
        oi.feed(bytes, &mut out);
        out
    }

    #[test]
    fn drive_direct_is_obeyed_only_after_start_and_safe() {
        let mut oi = OpenInterface::new(0.235);
        assert_eq!(feed(&mut oi, &[145, 0, 100, 0, 50]), vec![]);
        assert_eq!(feed(&mut oi, &[128, 131]), vec![WheelCommand::Stop]);
        // Right 100 mm/s, left -50 mm/s, in two chunks.
        assert_eq!(feed(&mut oi, &[145, 0, 100]), vec![]);
        assert_eq!(feed(&mut oi, &[0xFF, 0xCE]), vec![WheelCommand::Wheels(-0.05, 0.1)]);
        assert_eq!(feed(&mut oi, &[173]), vec![WheelCommand::Stop]);
        assert_eq!(oi.mode(), Mode::Off);
        assert_eq!(feed(&mut oi, &[145, 0, 100, 0, 100]), vec![], "off: ignored");
        assert_eq!(oi.malformed(), 0);
        feed(&mut oi, &[3, 128]);
        assert_eq!((oi.malformed(), oi.mode()), (1, Mode::Passive));
    }

    #[test]
    fn a_stream_frame_carries_the_asked_packets_with_a_zero_sum() {
        let mut oi = OpenInterface::new(0.2);
        feed(&mut oi, &[128, 131, 148, 4, 7, 22, 43, 44]);
        oi.track((0.0, 0.0, 0.0));
        // 0.1 m straight ahead: 0.1 / METRES_PER_COUNT = 224.9 -> 225 counts.
        oi.track((0.1, 0.0, 0.0));
        let readings = Readings { bumper: true, volts: 14.4, ranges: vec![], max_range: 4.0 };
        let frame = oi.frame(&readings).unwrap();
        assert_eq!(frame[..2], [19, 11]);
        assert_eq!(frame[2..13], [7, 3, 22, 0x38, 0x40, 43, 0, 225, 44, 0, 225]);
        assert_eq!(frame.iter().fold(0u8, |s, b| s.wrapping_add(*b)), 0);
        feed(&mut oi, &[150, 0]);
        assert_eq!(oi.frame(&readings), None);
    }

    #[test]
    fn a_turn_on_the_spot_counts_the_wheels_apart_and_light_bumps_follow_the_rays() {
        let mut oi = OpenInterface::new(0.2);
        feed(&mut oi, &[128, 131, 148, 8, 43, 44, 46, 47, 48, 49, 50, 51]);
        oi.track((1.0, 1.0, 0.0));
        oi.track((1.0, 1.0, 0.5));
        let ranges = vec![4.0, 3.0, 2.0, 1.0, 0.0, 2.0];
        let frame = oi.frame(&Readings { bumper: false, volts: 0.0, ranges, max_range: 4.0 }).unwrap();
        let word = |at: usize| u16::from_be_bytes([frame[at], frame[at + 1]]);
        // 0.05 m per wheel, opposite ways: 112.47 counts; left wraps below 0.
        assert_eq!((word(3), word(6)), (u16::MAX - 111, 112));
        // Left (46) is ray 5, right (51) is ray 0.
        let signals: Vec<u16> = (0..6).map(|i| word(9 + 3 * i)).collect();
        assert_eq!(signals, vec![2048, 4095, 3071, 2048, 1024, 0]);
    }
}
