//! How a port's value travels between subsume hosts over Zenoh: one tag
//! byte (the kind), then the value, little-endian, lengths as `u32`.
//! Pure and fuzzed with the CDR decoders: what arrives is untrusted, so
//! every length is checked against what is left and [`MAX_VALUE_BYTES`]
//! before anything is allocated, numbers must be finite, text UTF-8, and a
//! command a valid control string.
//!
//! | tag | kind | body |
//! |---|---|---|
//! | 1 | flag | 1 byte, 0 or 1 |
//! | 2 | scalar | f64 |
//! | 3 | vector | u32 n, n x f64 |
//! | 4 | text | u32 n, n bytes of UTF-8 |
//! | 5 | command | u32 n, n bytes (a control string) |
//! | 6 | bytes | u32 n, n bytes |
//! | 7 | scan | f64 angle-min, angle-increment, range-min, range-max, u32 n, n x f64 |

use thiserror::Error;

use crate::contract::control::Command;
use crate::contract::{Scan, Value, ValueKind};

/// Largest encoded value a peer may send (a scan of 8k rays fits): a peer
/// cannot make the host allocate or route more per message.
pub const MAX_VALUE_BYTES: usize = 64 * 1024;

/// Why bytes from a peer are not a value.
#[derive(Clone, Debug, Error, PartialEq, Eq)]
pub enum WireError {
    #[error("empty message")]
    Empty,
    #[error("message of {0} bytes exceeds the limit of {MAX_VALUE_BYTES}")]
    TooLarge(usize),
    #[error("unknown kind tag {0}")]
    UnknownTag(u8),
    #[error("message ends early")]
    Truncated,
    #[error("{0} trailing bytes")]
    Trailing(usize),
    #[error("a number is not finite")]
    NotFinite,
    #[error("text is not utf-8")]
    NotUtf8,
    #[error("invalid flag byte {0}")]
    BadFlag(u8),
    #[error("invalid control string: {0}")]
    BadCommand(String),
    #[error("a {got} arrived where {expected} was declared")]
    WrongKind { got: &'static str, expected: &'static str },
}

fn tag(value: &Value) -> u8 {
    match value {
        Value::Flag(_) => 1,
        Value::Scalar(_) => 2,
        Value::Vector(_) => 3,
        Value::Text(_) => 4,
        Value::Command(_) => 5,
        Value::Bytes(_) => 6,
        Value::Scan(_) => 7,
    }
}

fn put_f64s(out: &mut Vec<u8>, xs: &[f64]) {
    out.extend_from_slice(&(xs.len() as u32).to_le_bytes());
    for x in xs {
        out.extend_from_slice(&x.to_le_bytes());
    }
}

fn put_bytes(out: &mut Vec<u8>, b: &[u8]) {
    out.extend_from_slice(&(b.len() as u32).to_le_bytes());
    out.extend_from_slice(b);
}

/// The bytes of `value`.
pub fn encode(value: &Value) -> Vec<u8> {
    let mut out = vec![tag(value)];
    match value {
        Value::Flag(b) => out.push(*b as u8),
        Value::Scalar(x) => out.extend_from_slice(&x.to_le_bytes()),
        Value::Vector(v) => put_f64s(&mut out, v),
        Value::Text(t) => put_bytes(&mut out, t.as_bytes()),
        Value::Command(c) => put_bytes(&mut out, c.text().as_bytes()),
        Value::Bytes(b) => put_bytes(&mut out, b),
        Value::Scan(s) => {
            for x in [s.angle_min, s.angle_increment, s.range_min, s.range_max] {
                out.extend_from_slice(&x.to_le_bytes());
            }
            put_f64s(&mut out, &s.ranges);
        }
    }
    out
}

struct Cursor<'a> {
    bytes: &'a [u8],
}

impl<'a> Cursor<'a> {
    fn take(&mut self, n: usize) -> Result<&'a [u8], WireError> {
        if n > self.bytes.len() {
            return Err(WireError::Truncated);
        }
        let (head, rest) = self.bytes.split_at(n);
        self.bytes = rest;
        Ok(head)
    }

    fn u32(&mut self) -> Result<usize, WireError> {
        let b = self.take(4)?;
        Ok(u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as usize)
    }

    fn f64(&mut self) -> Result<f64, WireError> {
        let mut a = [0u8; 8];
        a.copy_from_slice(self.take(8)?);
        let x = f64::from_le_bytes(a);
        if x.is_finite() { Ok(x) } else { Err(WireError::NotFinite) }
    }

    fn f64s(&mut self) -> Result<Vec<f64>, WireError> {
        let n = self.u32()?;
        if n.saturating_mul(8) > self.bytes.len() {
            return Err(WireError::Truncated);
        }
        (0..n).map(|_| self.f64()).collect()
    }

    fn blob(&mut self) -> Result<&'a [u8], WireError> {
        let n = self.u32()?;
        self.take(n)
    }

    fn text(&mut self) -> Result<String, WireError> {
        std::str::from_utf8(self.blob()?).map(str::to_string).map_err(|_| WireError::NotUtf8)
    }
}

/// The value in `bytes`.
pub fn decode(bytes: &[u8]) -> Result<Value, WireError> {
    if bytes.len() > MAX_VALUE_BYTES {
        return Err(WireError::TooLarge(bytes.len()));
    }
    let (&tag, body) = bytes.split_first().ok_or(WireError::Empty)?;
    let mut c = Cursor { bytes: body };
    let value = match tag {
        1 => match c.take(1)?[0] {
            0 => Value::Flag(false),
            1 => Value::Flag(true),
            other => return Err(WireError::BadFlag(other)),
        },
        2 => Value::Scalar(c.f64()?),
        3 => Value::Vector(c.f64s()?),
        4 => Value::Text(c.text()?),
        5 => {
            let command = Command::parse(&c.text()?);
            command.parsed().map_err(|e| WireError::BadCommand(e.to_string()))?;
            Value::Command(command)
        }
        6 => Value::Bytes(c.blob()?.to_vec()),
        7 => {
            let (angle_min, angle_increment, range_min, range_max) = (c.f64()?, c.f64()?, c.f64()?, c.f64()?);
            Value::Scan(Scan { angle_min, angle_increment, range_min, range_max, ranges: c.f64s()? })
        }
        other => return Err(WireError::UnknownTag(other)),
    };
    if !c.bytes.is_empty() {
        return Err(WireError::Trailing(c.bytes.len()));
    }
    Ok(value)
}

/// The value in `bytes`, which must fit a port of `kind`.
pub fn decode_as(bytes: &[u8], kind: ValueKind) -> Result<Value, WireError> {
    let value = decode(bytes)?;
    let got = crate::contract::kind_of(&value);
    if kind.accepts(&value) { Ok(value) } else { Err(WireError::WrongKind { got: got.name(), expected: kind.name() }) }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_kind_round_trips() {
        let values = [
            Value::Flag(true),
            Value::Scalar(-1.25),
            Value::Vector(vec![1.0, 2.0]),
            Value::Text("hé".into()),
            Value::Command("VEL 0.2 0.1".into()),
            Value::Bytes(vec![0, 255]),
            Value::Scan(Scan {
                angle_min: -1.0,
                angle_increment: 0.5,
                range_min: 0.1,
                range_max: 4.0,
                ranges: vec![1.0, 2.0, 3.0, 4.0, 0.5],
            }),
        ];
        for v in values {
            assert_eq!(decode(&encode(&v)), Ok(v));
        }
        assert_eq!(encode(&Value::Scalar(1.0)), [&[2u8][..], &1.0f64.to_le_bytes()].concat());
    }

    #[test]
    fn malformed_messages_are_named() {
        assert_eq!(decode(&[]), Err(WireError::Empty));
        assert_eq!(decode(&[9]), Err(WireError::UnknownTag(9)));
        assert_eq!(decode(&[3, 255, 255, 255, 255]), Err(WireError::Truncated));
        assert_eq!(decode(&[1, 2]), Err(WireError::BadFlag(2)));
        assert_eq!(decode(&[1, 1, 0]), Err(WireError::Trailing(1)));
        let nan = [&[2u8][..], &f64::NAN.to_le_bytes()].concat();
        assert_eq!(decode(&nan), Err(WireError::NotFinite));
        assert!(matches!(decode(&encode(&Value::Command("FLY 1".into()))), Err(WireError::BadCommand(_))));
        assert_eq!(decode(&vec![6; MAX_VALUE_BYTES + 1]), Err(WireError::TooLarge(MAX_VALUE_BYTES + 1)));
        assert_eq!(
            decode_as(&encode(&Value::Scalar(1.0)), ValueKind::Command),
            Err(WireError::WrongKind { got: "scalar", expected: "command" })
        );
    }
}
