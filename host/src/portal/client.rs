//! `subsume estop HOST` and `subsume release HOST`: the emergency stop from
//! a script or a physical button wired to a small computer, through the
//! portal's HTTP API (docs/estop.md): log in, `POST /api/v1/estop` or
//! `/api/v1/release`, log out. Plain HTTP/1.1 on one connection per
//! request, with every wait bounded; a portal that speaks TLS is not
//! reached by this client (use `curl` against the API). `deploy` and `lab`
//! send their requests through [`send`], whose answers' bodies are read as
//! they arrive (a results archive is never held whole).

use std::io::{BufRead, BufReader, Read, Write};
use std::net::{TcpStream, ToSocketAddrs};
use std::time::Duration;

use serde_json::{Value, json};
use thiserror::Error;

use crate::contract::clip;

/// Longest wait to connect, and for each read or write: a stop that cannot
/// be delivered must say so quickly, not hang the button's script.
pub const CLIENT_TIMEOUT: Duration = Duration::from_secs(5);
/// Largest answer read: the API's answers here are a few hundred bytes.
pub const MAX_ANSWER_BYTES: u64 = 1 << 20;

/// What the command line asks.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum LockAction {
    Engage,
    Release,
}

/// Why the stop or release did not happen.
#[derive(Debug, Error)]
pub enum ClientError {
    #[error("bad host '{0}': expected HOST:PORT or http://HOST:PORT")]
    Host(String),
    #[error("cannot reach the portal at {address}: {reason}")]
    Connect { address: String, reason: String },
    #[error("the portal at {address} answered {status}: {message}")]
    Refused { address: String, status: u16, message: String },
    #[error("the portal at {0} gave an answer that is not HTTP")]
    Garbled(String),
}

/// Engages or releases on the portal at `host` as `user` with `password`;
/// returns what the portal said, in a line.
pub fn lock_action(host: &str, user: &str, password: &str, action: LockAction) -> Result<String, ClientError> {
    let address = portal_address(host)?;
    let login = request(&address, "POST", "/api/v1/login", None, &json!({"name": user, "password": password}))?;
    let token = login["token"].as_str().ok_or_else(|| ClientError::Garbled(address.clone()))?.to_string();
    let path = match action {
        LockAction::Engage => "/api/v1/estop",
        LockAction::Release => "/api/v1/release",
    };
    let answer = request(&address, "POST", path, Some(&token), &Value::Null);
    let _ = request(&address, "POST", "/api/v1/logout", Some(&token), &Value::Null);
    let answer = answer?;
    Ok(match action {
        LockAction::Engage if answer["newly"] == true => "estop engaged: the motors are stopped".to_string(),
        LockAction::Engage => {
            let by = answer["engaged"].as_array().and_then(|e| e.first()).and_then(|e| e["by"].as_str());
            format!("estop was engaged already (by {}): the motors are stopped", by.unwrap_or("someone"))
        }
        LockAction::Release => {
            let released: Vec<String> = answer["released"]
                .as_array()
                .into_iter()
                .flatten()
                .map(|r| {
                    format!(
                        "{} after {:.1} s",
                        r["lock"].as_str().unwrap_or("?"),
                        r["held_ms"].as_f64().unwrap_or(0.0) / 1e3
                    )
                })
                .collect();
            format!("released {}", released.join(", "))
        }
    })
}

/// The `HOST:PORT` of a portal given as `HOST:PORT` or `http://HOST:PORT`.
pub(crate) fn portal_address(host: &str) -> Result<String, ClientError> {
    let address = host.strip_prefix("http://").unwrap_or(host).trim_end_matches('/').to_string();
    if address.is_empty() || address.contains('/') || host.starts_with("https://") {
        return Err(ClientError::Host(address));
    }
    Ok(address)
}

/// One request; the JSON answer of a 2xx, else the portal's error.
fn request(address: &str, method: &str, path: &str, token: Option<&str>, body: &Value) -> Result<Value, ClientError> {
    let body = if body.is_null() { String::new() } else { body.to_string() };
    let (status, json, text) = send(address, method, path, token, "application/json", body.as_bytes(), CLIENT_TIMEOUT)?
        .read(MAX_ANSWER_BYTES)?;
    if (200..300).contains(&status) {
        return Ok(json);
    }
    let message = json["error"].as_str().map_or_else(|| text.trim().to_string(), str::to_string);
    Err(ClientError::Refused { address: address.to_string(), status, message: clip(&message) })
}

/// Largest head of an answer read (status line and headers).
const MAX_HEAD_BYTES: u64 = 64 << 10;

/// An answer whose head was read; its body is read as it arrives.
pub(crate) struct Answer {
    pub status: u16,
    pub body: Body,
}

impl Answer {
    /// The status, the body as JSON (`Null` when it is not) and as text, at
    /// most `limit` bytes of it (the rest is not read).
    pub(crate) fn read(self, limit: u64) -> Result<(u16, Value, String), ClientError> {
        let status = self.status;
        let text = self.text(limit)?;
        let json: Value = serde_json::from_str(text.trim()).unwrap_or(Value::Null);
        Ok((status, json, text))
    }

    /// The body as text, at most `limit` bytes of it (the rest is not read).
    pub(crate) fn text(self, limit: u64) -> Result<String, ClientError> {
        let address = self.body.address.clone();
        let mut bytes = Vec::new();
        self.body
            .take(limit)
            .read_to_end(&mut bytes)
            .map_err(|e| ClientError::Connect { address, reason: e.to_string() })?;
        Ok(String::from_utf8_lossy(&bytes).into_owned())
    }
}

/// Longest line of the chunked framing read (a chunk's size, a trailer).
const MAX_FRAMING_LINE: u64 = 1024;

/// How the body's end is known.
enum Framing {
    /// `Transfer-Encoding: chunked`: bytes left in the current chunk, and
    /// whether the last chunk was read.
    Chunked { left: u64, ended: bool },
    /// `Content-Length`: bytes left.
    Length(u64),
    /// Until the connection closes.
    ToEnd,
}

/// The body of an [`Answer`], de-chunked.
pub(crate) struct Body {
    reader: Box<dyn BufRead + Send>,
    framing: Framing,
    address: String,
}

fn cut_short() -> std::io::Error {
    std::io::Error::new(std::io::ErrorKind::UnexpectedEof, "the answer ended before its last chunk")
}

impl Body {
    /// One line of the chunked framing, without its CRLF.
    fn framing_line(&mut self) -> std::io::Result<String> {
        let mut line = String::new();
        (&mut self.reader).take(MAX_FRAMING_LINE).read_line(&mut line)?;
        if !line.ends_with('\n') {
            return Err(cut_short());
        }
        Ok(line.trim_end().to_string())
    }
}

impl Read for Body {
    fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
        match self.framing {
            Framing::ToEnd => self.reader.read(buf),
            Framing::Length(0) => Ok(0),
            Framing::Length(left) => {
                let want = buf.len().min(usize::try_from(left).unwrap_or(usize::MAX));
                let n = self.reader.read(&mut buf[..want])?;
                if n == 0 {
                    return Err(cut_short());
                }
                self.framing = Framing::Length(left - n as u64);
                Ok(n)
            }
            Framing::Chunked { ended: true, .. } => Ok(0),
            Framing::Chunked { left: 0, .. } => {
                let line = self.framing_line()?;
                let size = line.split(';').next().unwrap_or_default().trim();
                let size = u64::from_str_radix(size, 16).map_err(|_| {
                    std::io::Error::new(std::io::ErrorKind::InvalidData, format!("bad chunk size '{}'", clip(size)))
                })?;
                if size == 0 {
                    // Trailers, then the empty line.
                    while !self.framing_line()?.is_empty() {}
                    self.framing = Framing::Chunked { left: 0, ended: true };
                    return Ok(0);
                }
                self.framing = Framing::Chunked { left: size, ended: false };
                self.read(buf)
            }
            Framing::Chunked { left, .. } => {
                let want = buf.len().min(usize::try_from(left).unwrap_or(usize::MAX));
                let n = self.reader.read(&mut buf[..want])?;
                if n == 0 {
                    return Err(cut_short());
                }
                let left = left - n as u64;
                if left == 0 && !self.framing_line()?.is_empty() {
                    return Err(std::io::Error::new(std::io::ErrorKind::InvalidData, "a chunk longer than its size"));
                }
                self.framing = Framing::Chunked { left, ended: false };
                Ok(n)
            }
        }
    }
}

/// Sends one request with `body` as `content_type` and reads the answer's
/// head; every wait (connecting, each read and write) is bounded by
/// `timeout`.
pub(crate) fn send(
    address: &str,
    method: &str,
    path: &str,
    token: Option<&str>,
    content_type: &str,
    body: &[u8],
    timeout: Duration,
) -> Result<Answer, ClientError> {
    let connect = |reason: String| ClientError::Connect { address: address.to_string(), reason };
    let garbled = || ClientError::Garbled(address.to_string());
    let target = address
        .to_socket_addrs()
        .map_err(|e| connect(e.to_string()))?
        .next()
        .ok_or_else(|| ClientError::Host(address.to_string()))?;
    let mut stream = TcpStream::connect_timeout(&target, CLIENT_TIMEOUT).map_err(|e| connect(e.to_string()))?;
    stream.set_read_timeout(Some(timeout)).map_err(|e| connect(e.to_string()))?;
    stream.set_write_timeout(Some(timeout)).map_err(|e| connect(e.to_string()))?;
    let auth = token.map(|t| format!("Authorization: Bearer {t}\r\n")).unwrap_or_default();
    let head = format!(
        "{method} {path} HTTP/1.1\r\nHost: {address}\r\n{auth}Content-Type: {content_type}\r\nContent-Length: {}\r\nConnection: close\r\n\r\n",
        body.len()
    );
    stream.write_all(head.as_bytes()).and_then(|()| stream.write_all(body)).map_err(|e| connect(e.to_string()))?;
    let mut reader = BufReader::new(stream);
    let mut head = Vec::new();
    let mut limited = (&mut reader).take(MAX_HEAD_BYTES);
    loop {
        let before = head.len();
        let n = limited.read_until(b'\n', &mut head).map_err(|e| connect(e.to_string()))?;
        if n == 0 {
            return Err(garbled());
        }
        if head[before..].iter().all(|b| b.is_ascii_whitespace()) {
            break;
        }
    }
    let head = String::from_utf8_lossy(&head).to_ascii_lowercase();
    let mut lines = head.lines();
    let status: u16 =
        lines.next().and_then(|l| l.split_whitespace().nth(1)).and_then(|s| s.parse().ok()).ok_or_else(garbled)?;
    let header = |name: &str| {
        head.lines().skip(1).find_map(|l| l.split_once(':').filter(|(k, _)| k.trim() == name).map(|(_, v)| v.trim()))
    };
    let framing = if header("transfer-encoding").is_some_and(|v| v.contains("chunked")) {
        Framing::Chunked { left: 0, ended: false }
    } else if let Some(length) = header("content-length") {
        Framing::Length(length.parse().map_err(|_| garbled())?)
    } else {
        Framing::ToEnd
    };
    Ok(Answer { status, body: Body { reader: Box::new(reader), framing, address: address.to_string() } })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn body(text: &str, framing: Framing) -> Result<String, std::io::Error> {
        let reader = Box::new(std::io::Cursor::new(text.as_bytes().to_vec()));
        let mut out = String::new();
        Body { reader, framing, address: "x:1".into() }.read_to_string(&mut out)?;
        Ok(out)
    }

    #[test]
    fn chunked_bodies_are_joined_and_cut_ones_refused_and_bad_hosts_refused() {
        let chunked = || Framing::Chunked { left: 0, ended: false };
        assert_eq!(body("4\r\n{\"a\"\r\n3;x=y\r\n:1}\r\n0\r\nT: 1\r\n\r\n", chunked()).unwrap(), "{\"a\":1}");
        for cut in ["4\r\n{\"a\"\r\n", "4\r\n{\"", "4\r\n{\"a\"xx\r\n0\r\n\r\n", "z\r\n"] {
            assert!(body(cut, chunked()).is_err(), "{cut:?}");
        }
        assert_eq!(body("abcdef", Framing::Length(3)).unwrap(), "abc");
        assert!(body("ab", Framing::Length(3)).is_err());
        assert_eq!(body("abc", Framing::ToEnd).unwrap(), "abc");
        assert!(matches!(lock_action("https://x:1", "u", "p", LockAction::Engage), Err(ClientError::Host(_))));
        assert!(matches!(lock_action("x:1/y", "u", "p", LockAction::Engage), Err(ClientError::Host(_))));
    }
}
