//! Little-endian CDR (the OMG CDR that ROS 2 middlewares put on the wire,
//! after the four-byte encapsulation header `00 01 00 00`) for the message
//! types the ROS 2 face speaks: `geometry_msgs/msg/Twist`,
//! `nav_msgs/msg/Odometry`, `sensor_msgs/msg/LaserScan`,
//! `rcl_interfaces/msg/Log` and `std_msgs/msg/Bool`.
//!
//! Pure (no I/O, no clock) and fuzzed (`fuzz/fuzz_targets/cdr.rs`): every
//! decoder reads untrusted bytes from the network, so every length is
//! checked against what is left and against [`MAX_SEQUENCE_LEN`] /
//! [`MAX_STRING_LEN`] before anything is allocated. Alignment is relative to
//! the end of the encapsulation header, each primitive aligned to its size
//! (8 for `float64`), as Fast DDS, Cyclone DDS and `rosbags` do.

use thiserror::Error;

/// The encapsulation header of little-endian plain CDR.
pub const HEADER_LE: [u8; 4] = [0x00, 0x01, 0x00, 0x00];

/// Most elements in one sequence a peer may announce (a scan of 8192 rays
/// is already generous): a forged length cannot make the host allocate more.
pub const MAX_SEQUENCE_LEN: usize = 8192;

/// Longest string a peer may send (bytes, with the terminating NUL): a forged
/// length cannot make the host allocate more.
pub const MAX_STRING_LEN: usize = 4096;

/// Why a payload is not a message of the expected type.
#[derive(Clone, Debug, Error, PartialEq, Eq)]
pub enum CdrError {
    #[error("payload shorter than the cdr header")]
    NoHeader,
    #[error("unsupported cdr encapsulation {0:02x}{1:02x} (expected little-endian plain cdr 0001)")]
    Encapsulation(u8, u8),
    #[error("payload ends at byte {at} while reading {what}")]
    Truncated { what: &'static str, at: usize },
    #[error("{what} of {len} exceeds the limit of {limit}")]
    TooLong { what: &'static str, len: usize, limit: usize },
    #[error("{what} is not a terminated utf-8 string")]
    BadString { what: &'static str },
    #[error("{what} is not a finite number")]
    NotFinite { what: &'static str },
}

/// Writes one message: header, then fields in declaration order.
pub struct Writer {
    buf: Vec<u8>,
}

impl Default for Writer {
    fn default() -> Self {
        Writer::new()
    }
}

impl Writer {
    pub fn new() -> Writer {
        Writer { buf: HEADER_LE.to_vec() }
    }

    fn align(&mut self, n: usize) {
        while !(self.buf.len() - 4).is_multiple_of(n) {
            self.buf.push(0);
        }
    }

    pub fn u8(&mut self, v: u8) {
        self.buf.push(v);
    }

    pub fn u32(&mut self, v: u32) {
        self.align(4);
        self.buf.extend_from_slice(&v.to_le_bytes());
    }

    pub fn i32(&mut self, v: i32) {
        self.align(4);
        self.buf.extend_from_slice(&v.to_le_bytes());
    }

    pub fn f32(&mut self, v: f32) {
        self.align(4);
        self.buf.extend_from_slice(&v.to_le_bytes());
    }

    pub fn f64(&mut self, v: f64) {
        self.align(8);
        self.buf.extend_from_slice(&v.to_le_bytes());
    }

    pub fn string(&mut self, s: &str) {
        self.u32(s.len() as u32 + 1);
        self.buf.extend_from_slice(s.as_bytes());
        self.buf.push(0);
    }

    pub fn f32_seq(&mut self, v: &[f32]) {
        self.u32(v.len() as u32);
        for x in v {
            self.f32(*x);
        }
    }

    pub fn finish(self) -> Vec<u8> {
        self.buf
    }
}

/// Reads one message; every read is bounds-checked.
pub struct Reader<'a> {
    bytes: &'a [u8],
    at: usize,
}

impl<'a> Reader<'a> {
    /// A reader past the header, which must be little-endian plain CDR.
    pub fn new(bytes: &'a [u8]) -> Result<Reader<'a>, CdrError> {
        if bytes.len() < 4 {
            return Err(CdrError::NoHeader);
        }
        if bytes[0] != 0x00 || bytes[1] != 0x01 {
            return Err(CdrError::Encapsulation(bytes[0], bytes[1]));
        }
        Ok(Reader { bytes, at: 4 })
    }

    fn align(&mut self, n: usize) {
        let pos = self.at - 4;
        self.at += (n - pos % n) % n;
    }

    fn take(&mut self, n: usize, what: &'static str) -> Result<&'a [u8], CdrError> {
        let end = self.at.checked_add(n).filter(|end| *end <= self.bytes.len());
        match end {
            Some(end) => {
                let slice = &self.bytes[self.at..end];
                self.at = end;
                Ok(slice)
            }
            None => Err(CdrError::Truncated { what, at: self.bytes.len().min(self.at) }),
        }
    }

    fn array<const N: usize>(&mut self, what: &'static str) -> Result<[u8; N], CdrError> {
        self.align(N);
        let mut out = [0u8; N];
        out.copy_from_slice(self.take(N, what)?);
        Ok(out)
    }

    pub fn u8(&mut self, what: &'static str) -> Result<u8, CdrError> {
        Ok(self.take(1, what)?[0])
    }

    pub fn u32(&mut self, what: &'static str) -> Result<u32, CdrError> {
        self.array::<4>(what).map(u32::from_le_bytes)
    }

    pub fn i32(&mut self, what: &'static str) -> Result<i32, CdrError> {
        self.array::<4>(what).map(i32::from_le_bytes)
    }

    pub fn f32(&mut self, what: &'static str) -> Result<f32, CdrError> {
        self.array::<4>(what).map(f32::from_le_bytes)
    }

    pub fn f64(&mut self, what: &'static str) -> Result<f64, CdrError> {
        self.array::<8>(what).map(f64::from_le_bytes)
    }

    /// A finite `float64` (what reaches a component is never NaN or infinite).
    pub fn finite(&mut self, what: &'static str) -> Result<f64, CdrError> {
        let v = self.f64(what)?;
        if v.is_finite() { Ok(v) } else { Err(CdrError::NotFinite { what }) }
    }

    pub fn string(&mut self, what: &'static str) -> Result<String, CdrError> {
        let len = self.u32(what)? as usize;
        if len > MAX_STRING_LEN {
            return Err(CdrError::TooLong { what, len, limit: MAX_STRING_LEN });
        }
        if len == 0 {
            // Some writers send an empty string as length 0.
            return Ok(String::new());
        }
        let bytes = self.take(len, what)?;
        let (last, text) = bytes.split_last().ok_or(CdrError::BadString { what })?;
        if *last != 0 {
            return Err(CdrError::BadString { what });
        }
        std::str::from_utf8(text).map(str::to_string).map_err(|_| CdrError::BadString { what })
    }

    pub fn f32_seq(&mut self, what: &'static str) -> Result<Vec<f32>, CdrError> {
        let len = self.u32(what)? as usize;
        if len > MAX_SEQUENCE_LEN {
            return Err(CdrError::TooLong { what, len, limit: MAX_SEQUENCE_LEN });
        }
        if len.saturating_mul(4) > self.bytes.len().saturating_sub(self.at) {
            return Err(CdrError::Truncated { what, at: self.bytes.len() });
        }
        (0..len).map(|_| self.f32(what)).collect()
    }
}

/// `builtin_interfaces/msg/Time`.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Time {
    pub sec: i32,
    pub nanosec: u32,
}

impl Time {
    /// From nanoseconds since the UNIX epoch.
    pub fn from_unix_ns(ns: u64) -> Time {
        Time { sec: (ns / 1_000_000_000).min(i32::MAX as u64) as i32, nanosec: (ns % 1_000_000_000) as u32 }
    }

    fn write(&self, w: &mut Writer) {
        w.i32(self.sec);
        w.u32(self.nanosec);
    }

    fn read(r: &mut Reader<'_>) -> Result<Time, CdrError> {
        Ok(Time { sec: r.i32("stamp.sec")?, nanosec: r.u32("stamp.nanosec")? })
    }
}

/// `std_msgs/msg/Header`.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Header {
    pub stamp: Time,
    pub frame_id: String,
}

impl Header {
    fn write(&self, w: &mut Writer) {
        self.stamp.write(w);
        w.string(&self.frame_id);
    }

    fn read(r: &mut Reader<'_>) -> Result<Header, CdrError> {
        Ok(Header { stamp: Time::read(r)?, frame_id: r.string("header.frame_id")? })
    }
}

/// `geometry_msgs/msg/Twist` (linear and angular `Vector3`s).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Twist {
    pub linear: [f64; 3],
    pub angular: [f64; 3],
}

impl Twist {
    fn write_into(&self, w: &mut Writer) {
        for v in self.linear.iter().chain(&self.angular) {
            w.f64(*v);
        }
    }

    fn read_from(r: &mut Reader<'_>) -> Result<Twist, CdrError> {
        let mut t = Twist::default();
        for v in t.linear.iter_mut() {
            *v = r.finite("twist.linear")?;
        }
        for v in t.angular.iter_mut() {
            *v = r.finite("twist.angular")?;
        }
        Ok(t)
    }

    pub fn encode(&self) -> Vec<u8> {
        let mut w = Writer::new();
        self.write_into(&mut w);
        w.finish()
    }

    pub fn decode(bytes: &[u8]) -> Result<Twist, CdrError> {
        Twist::read_from(&mut Reader::new(bytes)?)
    }
}

/// `nav_msgs/msg/Odometry`, planar: a pose (x, y, heading) and a twist;
/// covariances are written as zeros and skipped when read.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Odometry {
    pub header: Header,
    pub child_frame_id: String,
    /// Position x, y, z.
    pub position: [f64; 3],
    /// Orientation quaternion x, y, z, w.
    pub orientation: [f64; 4],
    pub twist: Twist,
}

impl Odometry {
    /// A planar pose: x, y in metres, heading in radians about z.
    pub fn planar(header: Header, child_frame_id: &str, x: f64, y: f64, heading: f64) -> Odometry {
        let (s, c) = (heading / 2.0).sin_cos();
        Odometry {
            header,
            child_frame_id: child_frame_id.into(),
            position: [x, y, 0.0],
            orientation: [0.0, 0.0, s, c],
            twist: Twist::default(),
        }
    }

    /// The heading about z of the orientation, radians.
    pub fn heading(&self) -> f64 {
        let [x, y, z, w] = self.orientation;
        (2.0 * (w * z + x * y)).atan2(1.0 - 2.0 * (y * y + z * z))
    }

    pub fn encode(&self) -> Vec<u8> {
        let mut w = Writer::new();
        self.header.write(&mut w);
        w.string(&self.child_frame_id);
        for v in self.position.iter().chain(&self.orientation) {
            w.f64(*v);
        }
        for _ in 0..36 {
            w.f64(0.0);
        }
        self.twist.write_into(&mut w);
        for _ in 0..36 {
            w.f64(0.0);
        }
        w.finish()
    }

    pub fn decode(bytes: &[u8]) -> Result<Odometry, CdrError> {
        let mut r = Reader::new(bytes)?;
        let header = Header::read(&mut r)?;
        let child_frame_id = r.string("child_frame_id")?;
        let mut position = [0.0; 3];
        for v in position.iter_mut() {
            *v = r.finite("pose.position")?;
        }
        let mut orientation = [0.0; 4];
        for v in orientation.iter_mut() {
            *v = r.finite("pose.orientation")?;
        }
        for _ in 0..36 {
            r.f64("pose.covariance")?;
        }
        let twist = Twist::read_from(&mut r)?;
        for _ in 0..36 {
            r.f64("twist.covariance")?;
        }
        Ok(Odometry { header, child_frame_id, position, orientation, twist })
    }
}

/// `sensor_msgs/msg/LaserScan`.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct LaserScan {
    pub header: Header,
    pub angle_min: f32,
    pub angle_max: f32,
    pub angle_increment: f32,
    pub time_increment: f32,
    pub scan_time: f32,
    pub range_min: f32,
    pub range_max: f32,
    pub ranges: Vec<f32>,
    pub intensities: Vec<f32>,
}

impl LaserScan {
    pub fn encode(&self) -> Vec<u8> {
        let mut w = Writer::new();
        self.header.write(&mut w);
        for v in [
            self.angle_min,
            self.angle_max,
            self.angle_increment,
            self.time_increment,
            self.scan_time,
            self.range_min,
            self.range_max,
        ] {
            w.f32(v);
        }
        w.f32_seq(&self.ranges);
        w.f32_seq(&self.intensities);
        w.finish()
    }

    pub fn decode(bytes: &[u8]) -> Result<LaserScan, CdrError> {
        let mut r = Reader::new(bytes)?;
        let header = Header::read(&mut r)?;
        let mut f = [0f32; 7];
        for v in f.iter_mut() {
            *v = r.f32("scan angles and limits")?;
            if !v.is_finite() {
                return Err(CdrError::NotFinite { what: "scan angles and limits" });
            }
        }
        let ranges = r.f32_seq("ranges")?;
        let intensities = r.f32_seq("intensities")?;
        Ok(LaserScan {
            header,
            angle_min: f[0],
            angle_max: f[1],
            angle_increment: f[2],
            time_increment: f[3],
            scan_time: f[4],
            range_min: f[5],
            range_max: f[6],
            ranges,
            intensities,
        })
    }
}

/// `rcl_interfaces/msg/Log` (levels: 10 debug, 20 info, 30 warn, 40 error,
/// 50 fatal).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Log {
    pub stamp: Time,
    pub level: u8,
    pub name: String,
    pub msg: String,
    pub file: String,
    pub function: String,
    pub line: u32,
}

impl Log {
    pub fn encode(&self) -> Vec<u8> {
        let mut w = Writer::new();
        self.stamp.write(&mut w);
        w.u8(self.level);
        w.string(&self.name);
        w.string(&self.msg);
        w.string(&self.file);
        w.string(&self.function);
        w.u32(self.line);
        w.finish()
    }

    pub fn decode(bytes: &[u8]) -> Result<Log, CdrError> {
        let mut r = Reader::new(bytes)?;
        Ok(Log {
            stamp: Time::read(&mut r)?,
            level: r.u8("level")?,
            name: r.string("name")?,
            msg: r.string("msg")?,
            file: r.string("file")?,
            function: r.string("function")?,
            line: r.u32("line")?,
        })
    }
}

/// `std_msgs/msg/Bool`.
pub fn encode_bool(data: bool) -> Vec<u8> {
    let mut w = Writer::new();
    w.u8(data as u8);
    w.finish()
}

pub fn decode_bool(bytes: &[u8]) -> Result<bool, CdrError> {
    let mut r = Reader::new(bytes)?;
    Ok(r.u8("data")? != 0)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn twist_bytes_are_the_header_then_six_aligned_doubles() {
        let t = Twist { linear: [0.5, 0.0, 0.0], angular: [0.0, 0.0, -1.0] };
        let bytes = t.encode();
        assert_eq!(bytes.len(), 4 + 48);
        assert_eq!(&bytes[..4], &HEADER_LE);
        assert_eq!(&bytes[4..12], &0.5f64.to_le_bytes());
        assert_eq!(&bytes[44..52], &(-1.0f64).to_le_bytes());
        assert_eq!(Twist::decode(&bytes), Ok(t));
    }

    #[test]
    fn every_message_round_trips() {
        let header = Header { stamp: Time { sec: 12, nanosec: 34 }, frame_id: "odom".into() };
        let odom = Odometry::planar(header.clone(), "base_link", 1.5, -2.0, 0.75);
        let back = Odometry::decode(&odom.encode()).unwrap_or_default();
        assert_eq!(back, odom);
        assert!((back.heading() - 0.75).abs() < 1e-12);
        let scan = LaserScan {
            header,
            angle_min: -1.5,
            angle_max: 1.5,
            angle_increment: 0.375,
            range_max: 4.0,
            ranges: vec![1.0, 2.0, 3.0],
            ..LaserScan::default()
        };
        assert_eq!(LaserScan::decode(&scan.encode()), Ok(scan));
        let log = Log { level: 20, name: "subsume".into(), msg: "hello".into(), line: 7, ..Log::default() };
        assert_eq!(Log::decode(&log.encode()), Ok(log));
        assert_eq!(decode_bool(&encode_bool(true)), Ok(true));
    }

    #[test]
    fn malformed_payloads_are_refused_without_allocating_their_claims() {
        assert_eq!(Twist::decode(&[0, 1]), Err(CdrError::NoHeader));
        assert_eq!(Twist::decode(&[0, 0, 0, 0]), Err(CdrError::Encapsulation(0, 0)));
        assert!(matches!(Twist::decode(&HEADER_LE), Err(CdrError::Truncated { .. })));
        let mut nan = Twist::default().encode();
        nan[4..12].copy_from_slice(&f64::NAN.to_le_bytes());
        assert_eq!(Twist::decode(&nan), Err(CdrError::NotFinite { what: "twist.linear" }));
        // A scan claiming 4 billion ranges.
        let mut w = Writer::new();
        Header::default().write(&mut w);
        for _ in 0..7 {
            w.f32(0.0);
        }
        w.u32(u32::MAX);
        assert!(matches!(LaserScan::decode(&w.finish()), Err(CdrError::TooLong { what: "ranges", .. })));
        // A string without its NUL.
        let mut w = Writer::new();
        w.i32(0);
        w.u32(0);
        w.u8(20);
        w.u32(3);
        let mut bytes = w.finish();
        bytes.extend_from_slice(b"abc");
        assert_eq!(Log::decode(&bytes), Err(CdrError::BadString { what: "name" }));
    }
}
