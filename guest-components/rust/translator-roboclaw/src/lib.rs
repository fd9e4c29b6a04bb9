//! A hardware translator for Basicmicro RoboClaw motor controllers in
//! packet serial mode, as a WASM component of the `translator` world.
//!
//! - Commands: 37, "drive M1/M2 with signed speed" (mixed speed):
//!   `address 37 m1(i32) m2(i32) crc16`, speeds in encoder counts per second,
//!   big-endian; STOP is speed 0 on both. The controller answers every write
//!   with one byte, 0xFF (ACK).
//! - Poll (every `poll-ms`, 50 by default): 78, "read encoder counters":
//!   `address 78` (a read carries no CRC); the answer is `enc1(u32) enc2(u32) crc16`, the CRC taken
//!   over the address, the command and the data. Counts become odometry by
//!   dead reckoning from `origin-x/y/heading`. Every tenth poll, from the
//!   first, reads the main battery instead: 24, "read main battery
//!   voltage": `address 24`; the answer is `volts(u16, tenths) crc16`.
//!   Every tenth poll, from the sixth, reads the controller's status
//!   instead: 90, "read status": `address 90`; the answer is `status(u32)
//!   crc16`, a bit mask of errors (low 16 bits: e-stop, temperature, logic
//!   and main voltage, driver faults, speed, position and current errors)
//!   and warnings (high 16 bits: over current, voltage, temperature, speed
//!   and position error limits; S4 and S5 signals), as the RoboClaw user
//!   manual's table for command 90 has them. Every error and warning set is
//!   the controller's fault, named (e.g. "m1 over current warning"); the S4
//!   and S5 signals (home and limit switches the owner wires) are not.
//! - The CRC is CRC16-CCITT (XModem: polynomial 0x1021, initial 0), sent
//!   high byte first.
//!
//! Options (the link's `options`): `counts-per-metre` (required: encoder
//! counts per metre of wheel travel), `address` (128..=135, default 128),
//! `left=m1|m2` (default m1), `poll-ms`, `origin-x`, `origin-y`,
//! `origin-heading`.

use subsume_guest::drive::{Geometry, Odometry};
use subsume_guest::{Decoded, Feedback, LinkPlan, Params, Translator};

const MIXED_SPEED: u8 = 37;
const READ_ENCODERS: u8 = 78;
const READ_MAIN_BATTERY: u8 = 24;
const READ_STATUS: u8 = 90;
const ACK: u8 = 0xFF;
/// Encoder answer: two u32 and the CRC.
const ENCODER_REPLY_BYTES: usize = 10;
/// Main battery answer: a u16 (tenths of a volt) and the CRC.
const BATTERY_REPLY_BYTES: usize = 4;
/// Status answer: a u32 bit mask and the CRC.
const STATUS_REPLY_BYTES: usize = 6;
/// One poll in this many reads the main battery (the first among them).
const BATTERY_EVERY: u32 = 10;
/// One poll in this many reads the status (the sixth among them: half way
/// between two battery reads).
const STATUS_EVERY: u32 = 10;
const STATUS_AT: u32 = 5;
/// The status bits that are faults, as the RoboClaw user manual names them
/// (command 90): errors in the low 16 bits, warnings in the high.
const STATUS_BITS: [(u32, &str); 24] = [
    (0x0000_0001, "e-stop"),
    (0x0000_0002, "temperature error"),
    (0x0000_0004, "temperature 2 error"),
    (0x0000_0008, "main voltage high error"),
    (0x0000_0010, "logic voltage high error"),
    (0x0000_0020, "logic voltage low error"),
    (0x0000_0040, "m1 driver fault error"),
    (0x0000_0080, "m2 driver fault error"),
    (0x0000_0100, "m1 speed error"),
    (0x0000_0200, "m2 speed error"),
    (0x0000_0400, "m1 position error"),
    (0x0000_0800, "m2 position error"),
    (0x0000_1000, "m1 current error"),
    (0x0000_2000, "m2 current error"),
    (0x0000_4000, "main voltage low error"),
    (0x0000_8000, "main voltage high error (hysteresis)"),
    (0x0001_0000, "m1 over current warning"),
    (0x0002_0000, "m2 over current warning"),
    (0x0004_0000, "main voltage high warning"),
    (0x0008_0000, "main voltage low warning"),
    (0x0010_0000, "temperature warning"),
    (0x0020_0000, "temperature 2 warning"),
    (0x0100_0000, "speed error limit warning"),
    (0x0200_0000, "position error limit warning"),
];
/// S4 and S5 signal triggered: inputs (home or limit switches), not faults.
const SIGNAL_BITS: u32 = 0x0040_0000 | 0x0080_0000;

/// The fault a status mask names: every fault bit set, by name (a bit the
/// manual does not name, by its mask); empty when none is set.
fn fault_text(status: u32) -> String {
    let mut named: Vec<String> =
        STATUS_BITS.iter().filter(|(bit, _)| status & bit != 0).map(|(_, name)| name.to_string()).collect();
    let known = STATUS_BITS.iter().fold(SIGNAL_BITS, |all, (bit, _)| all | bit);
    let unknown = status & !known;
    if unknown != 0 {
        named.push(format!("status bits 0x{unknown:08x}"));
    }
    named.join(", ")
}
/// Most encoder reads outstanding: no new read is sent while this many
/// await their answers (a slow controller, or a busy host, is not flooded
/// with reads whose answers would then arrive past what is expected and be
/// taken for garbage).
const MAX_PENDING_READS: u32 = 4;
/// How long the outstanding reads may go unanswered before they are taken
/// as lost and reading starts afresh (a reply that arrives later counts as
/// malformed): a controller that lost a request must not stop the odometry
/// for good.
const READS_LOST_AFTER_NS: u64 = 1_000_000_000;
/// Most bytes kept while waiting for the rest of an answer.
const MAX_BUFFER: usize = 1024;
/// Shortest and longest poll period a robot file may set, ms.
const POLL_MS_RANGE: (u32, u32) = (5, 10_000);

/// CRC16-CCITT as the RoboClaw computes it.
fn crc16(bytes: &[u8]) -> u16 {
    let mut crc: u16 = 0;
    for byte in bytes {
        crc ^= u16::from(*byte) << 8;
        for _ in 0..8 {
            crc = if crc & 0x8000 != 0 { (crc << 1) ^ 0x1021 } else { crc << 1 };
        }
    }
    crc
}

struct RoboClaw {
    geometry: Geometry,
    odometry: Odometry,
    address: u8,
    counts_per_metre: f64,
    left_is_m1: bool,
    poll_ms: u32,
    buffer: Vec<u8>,
    /// The reads sent and not yet answered, oldest first (their commands).
    pending: std::collections::VecDeque<u8>,
    /// Polls sent, for the battery's turn.
    polls: u32,
    /// When the oldest read still awaiting its answer was sent (or the last
    /// answer came, if later).
    waiting_since_ns: u64,
    /// The time of the last poll, for the answers `decode` takes.
    now_ns: u64,
    counts: Option<(u32, u32)>,
    /// The fault the last status answer named, for the host to take.
    fault: Option<String>,
}

impl RoboClaw {
    fn packet(&self, command: u8, data: &[u8]) -> Vec<u8> {
        let mut bytes = vec![self.address, command];
        bytes.extend_from_slice(data);
        let crc = crc16(&bytes);
        bytes.extend_from_slice(&crc.to_be_bytes());
        bytes
    }

    /// Whether the buffer starts with a well-formed answer to read
    /// `command` of `size` bytes (its data and the CRC).
    fn reply_at_start(&self, command: u8, size: usize) -> bool {
        let Some(reply) = self.buffer.get(..size) else { return false };
        let mut covered = vec![self.address, command];
        covered.extend_from_slice(&reply[..size - 2]);
        crc16(&covered) == u16::from_be_bytes([reply[size - 2], reply[size - 1]])
    }

    fn encoders(&mut self, reply: &[u8], out: &mut Vec<Feedback>) {
        let m1 = u32::from_be_bytes([reply[0], reply[1], reply[2], reply[3]]);
        let m2 = u32::from_be_bytes([reply[4], reply[5], reply[6], reply[7]]);
        let (left, right) = if self.left_is_m1 { (m1, m2) } else { (m2, m1) };
        if let Some((old_left, old_right)) = self.counts {
            // Counters wrap at 32 bits: the difference is the travel.
            let dl = left.wrapping_sub(old_left) as i32;
            let dr = right.wrapping_sub(old_right) as i32;
            self.odometry.advance(f64::from(dl) / self.counts_per_metre, f64::from(dr) / self.counts_per_metre);
        }
        self.counts = Some((left, right));
        out.push(Feedback::Odometry(self.odometry.pose()));
    }
}

impl Translator for RoboClaw {
    fn init(params: &Params) -> Result<Self, String> {
        let geometry = Geometry::from_params(params, 0.3, 0.5)?;
        let odometry = Odometry::from_params(params, geometry.wheel_base)?;
        if params.text("counts-per-metre").is_none() {
            return Err("option 'counts-per-metre' is required (encoder counts per metre of wheel travel)".into());
        }
        let counts_per_metre = params.number("counts-per-metre")?;
        if !(counts_per_metre.is_finite() && counts_per_metre > 0.0) {
            return Err("option 'counts-per-metre' must be positive".into());
        }
        let address = match params.text("address") {
            None => 128,
            Some(_) => params.integer("address")?,
        };
        let address = u8::try_from(address)
            .ok()
            .filter(|a| (128..=135).contains(a))
            .ok_or_else(|| format!("option 'address': {address} is not a packet serial address (128 to 135)"))?;
        let left_is_m1 = match params.text("left").map(str::trim) {
            None | Some("m1") => true,
            Some("m2") => false,
            Some(other) => return Err(format!("option 'left': '{other}' is not m1 or m2")),
        };
        let poll_ms = match params.text("poll-ms") {
            None => 50,
            Some(_) => params.integer("poll-ms")?,
        };
        let poll_ms = u32::try_from(poll_ms)
            .ok()
            .filter(|p| (POLL_MS_RANGE.0..=POLL_MS_RANGE.1).contains(p))
            .ok_or_else(|| format!("option 'poll-ms': {poll_ms} is not within {POLL_MS_RANGE:?}"))?;
        Ok(RoboClaw {
            geometry,
            odometry,
            address,
            counts_per_metre,
            left_is_m1,
            poll_ms,
            buffer: Vec::new(),
            pending: std::collections::VecDeque::new(),
            polls: 0,
            waiting_since_ns: 0,
            now_ns: 0,
            counts: None,
            fault: None,
        })
    }

    fn link(&self) -> LinkPlan {
        LinkPlan { opening: Vec::new(), poll_period_ms: self.poll_ms, closing: Vec::new() }
    }

    fn encode(&mut self, command: &str) -> Result<Vec<u8>, String> {
        let (left, right) = self.geometry.command(command)?;
        let qpps = |v: f64| (v * self.counts_per_metre).round().clamp(f64::from(i32::MIN), f64::from(i32::MAX)) as i32;
        let (m1, m2) = if self.left_is_m1 { (qpps(left), qpps(right)) } else { (qpps(right), qpps(left)) };
        let mut data = m1.to_be_bytes().to_vec();
        data.extend_from_slice(&m2.to_be_bytes());
        Ok(self.packet(MIXED_SPEED, &data))
    }

    fn decode(&mut self, bytes: &[u8]) -> Decoded {
        let mut decoded = Decoded { feedback: Vec::new(), malformed: 0 };
        self.buffer.extend_from_slice(bytes);
        let mut garbage = false;
        while let Some(&first) = self.buffer.first() {
            let expected = self.pending.front().map(|&command| {
                let size = match command {
                    READ_MAIN_BATTERY => BATTERY_REPLY_BYTES,
                    READ_STATUS => STATUS_REPLY_BYTES,
                    _ => ENCODER_REPLY_BYTES,
                };
                (command, size)
            });
            if let Some((command, size)) = expected
                && self.reply_at_start(command, size)
            {
                let reply: Vec<u8> = self.buffer.drain(..size).collect();
                self.pending.pop_front();
                self.waiting_since_ns = self.now_ns;
                match command {
                    READ_MAIN_BATTERY => {
                        let tenths = u16::from_be_bytes([reply[0], reply[1]]);
                        decoded.feedback.push(Feedback::Battery(f64::from(tenths) / 10.0));
                    }
                    READ_STATUS => {
                        self.fault = Some(fault_text(u32::from_be_bytes([reply[0], reply[1], reply[2], reply[3]])));
                    }
                    _ => self.encoders(&reply, &mut decoded.feedback),
                }
                garbage = false;
                continue;
            }
            // An answer to a read may still be arriving: wait for it whole
            // before taking its first byte for anything else.
            if expected.is_some_and(|(_, size)| self.buffer.len() < size) {
                break;
            }
            self.buffer.remove(0);
            if first == ACK {
                garbage = false;
            } else if !garbage {
                garbage = true;
                decoded.malformed += 1;
            }
        }
        if self.buffer.len() > MAX_BUFFER {
            self.buffer.clear();
            decoded.malformed += 1;
        }
        decoded
    }

    fn poll(&mut self, now_ns: u64) -> Vec<u8> {
        self.now_ns = now_ns;
        if self.pending.len() as u32 >= MAX_PENDING_READS {
            if now_ns.saturating_sub(self.waiting_since_ns) < READS_LOST_AFTER_NS {
                return Vec::new();
            }
            // The part of a lost answer still waiting goes with it: read
            // against the next read's size, it would be taken apart
            // differently depending on when it came.
            self.pending.clear();
            self.buffer.clear();
        }
        if self.pending.is_empty() {
            self.waiting_since_ns = now_ns;
        }
        let command = if self.polls.is_multiple_of(BATTERY_EVERY) {
            READ_MAIN_BATTERY
        } else if self.polls % STATUS_EVERY == STATUS_AT {
            READ_STATUS
        } else {
            READ_ENCODERS
        };
        self.polls = self.polls.wrapping_add(1);
        self.pending.push_back(command);
        // A read is the address and the command alone: the CRC comes back.
        vec![self.address, command]
    }

    fn fault(&mut self) -> Option<String> {
        self.fault.take()
    }
}

subsume_guest::translator!(RoboClaw);
