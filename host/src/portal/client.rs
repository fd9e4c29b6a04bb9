//! `subsume estop HOST` and `subsume release HOST`: the emergency stop from
//! a script or a physical button wired to a small computer, through the
//! portal's HTTP API (docs/estop.md): log in, `POST /api/v1/estop` or
//! `/api/v1/release`, log out. Plain HTTP/1.1 on one connection per
//! request, with every wait bounded; a portal that speaks TLS is not
//! reached by this client (use `curl` against the API).

use std::io::{Read, Write};
use std::net::{TcpStream, ToSocketAddrs};
use std::time::Duration;

use serde_json::{Value, json};
use thiserror::Error;

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
    let address = host.strip_prefix("http://").unwrap_or(host).trim_end_matches('/').to_string();
    if address.is_empty() || address.contains('/') || host.starts_with("https://") {
        return Err(ClientError::Host(address));
    }
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

/// One request; the JSON answer of a 2xx, else the portal's error.
fn request(address: &str, method: &str, path: &str, token: Option<&str>, body: &Value) -> Result<Value, ClientError> {
    let body = if body.is_null() { String::new() } else { body.to_string() };
    let (status, json, text) =
        exchange(address, method, path, token, "application/json", body.as_bytes(), CLIENT_TIMEOUT)?;
    if (200..300).contains(&status) {
        return Ok(json);
    }
    let message = json["error"].as_str().map_or_else(|| text.trim().to_string(), str::to_string);
    Err(ClientError::Refused { address: address.to_string(), status, message: crate::contract::clip(&message) })
}

/// One request with `body` as `content_type`, every wait bounded by
/// `timeout`: the status, the answer as JSON (`Null` when it is not) and as
/// text.
pub(crate) fn exchange(
    address: &str,
    method: &str,
    path: &str,
    token: Option<&str>,
    content_type: &str,
    body: &[u8],
    timeout: Duration,
) -> Result<(u16, Value, String), ClientError> {
    let connect = |reason: String| ClientError::Connect { address: address.to_string(), reason };
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
    let mut answer = Vec::new();
    stream.take(MAX_ANSWER_BYTES).read_to_end(&mut answer).map_err(|e| connect(e.to_string()))?;
    let text = String::from_utf8_lossy(&answer);
    let (head, body) = text.split_once("\r\n\r\n").ok_or_else(|| ClientError::Garbled(address.to_string()))?;
    let status: u16 = head
        .split_whitespace()
        .nth(1)
        .and_then(|s| s.parse().ok())
        .ok_or_else(|| ClientError::Garbled(address.to_string()))?;
    let chunked = head.to_ascii_lowercase().contains("transfer-encoding: chunked");
    let body = if chunked { dechunk(body) } else { body.to_string() };
    let json: Value = serde_json::from_str(body.trim()).unwrap_or(Value::Null);
    Ok((status, json, body))
}

/// The payload of a chunked body.
fn dechunk(mut body: &str) -> String {
    let mut out = String::new();
    while let Some((size, rest)) = body.split_once("\r\n") {
        let Ok(size) = usize::from_str_radix(size.trim(), 16) else { break };
        if size == 0 || rest.len() < size {
            break;
        }
        out.push_str(&rest[..size]);
        body = rest[size..].trim_start_matches("\r\n");
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn chunked_bodies_are_joined_and_bad_hosts_refused() {
        assert_eq!(dechunk("4\r\n{\"a\"\r\n3\r\n:1}\r\n0\r\n\r\n"), "{\"a\":1}");
        assert!(matches!(lock_action("https://x:1", "u", "p", LockAction::Engage), Err(ClientError::Host(_))));
        assert!(matches!(lock_action("x:1/y", "u", "p", LockAction::Engage), Err(ClientError::Host(_))));
    }
}
