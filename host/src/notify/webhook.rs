//! Delivering the outbox: each event POSTed as JSON to its webhook over
//! HTTP/1.1, signed with HMAC-SHA256 under the hook's secret over
//! `TIMESTAMP.BODY` (headers `X-Subsume-Timestamp` and
//! `X-Subsume-Signature: sha256=HEX`; docs/lab.md says how to verify), in
//! the order written; a refusal or no answer is retried with backoff.
//! Runs on the delivery thread only, holding no lock while it talks.

use std::io::{Read, Write};
use std::net::{TcpStream, ToSocketAddrs};
use std::time::Duration;

use hmac::{Hmac, Mac};
use sha2::Sha256;
use thiserror::Error;

use super::Notifier;
use super::outbox::Entry;
use crate::walltime::unix_now_s;

/// Longest webhook URL, bytes.
pub const MAX_URL_BYTES: usize = 2048;
/// How long connecting, sending or waiting for the answer may take: a
/// receiver that hangs must not hold the queue forever.
pub const DELIVERY_TIMEOUT: Duration = Duration::from_secs(10);
/// The first retry's wait; each next one waits twice as long.
pub const FIRST_RETRY: Duration = Duration::from_millis(250);
/// The longest wait between two tries: a receiver back up is reached soon.
pub const LONGEST_RETRY: Duration = Duration::from_secs(300);
/// Tries of one event before it is given up (logged): a receiver gone for
/// good must not hold the events behind it forever (about 3 hours).
pub const MAX_ATTEMPTS: u32 = 40;
/// Most bytes of an answer read (its status line is all that counts).
const MAX_ANSWER_BYTES: usize = 4096;

/// Why a URL is not a webhook's or a delivery failed.
#[derive(Debug, Error)]
pub enum WebhookError {
    #[error("url {0:?}: {1}")]
    BadUrl(String, &'static str),
    #[error("{url}: {message}")]
    Delivery { url: String, message: String },
}

/// A webhook's URL: `http://HOST[:PORT]/PATH`.
#[derive(Clone, Debug, PartialEq)]
pub struct Url {
    pub text: String,
    host: String,
    port: u16,
    path: String,
}

impl Url {
    /// Parses `text`; only plain `http` is delivered for now (a hook on a
    /// host's own network or behind a TLS-terminating proxy).
    pub fn parse(text: &str) -> Result<Url, WebhookError> {
        let bad = |why| WebhookError::BadUrl(text.chars().take(80).collect(), why);
        if text.len() > MAX_URL_BYTES {
            return Err(bad("longer than 2048 bytes"));
        }
        if text.starts_with("https://") {
            return Err(bad("https is not delivered yet: use http (to a proxy that adds TLS)"));
        }
        let rest = text.strip_prefix("http://").ok_or_else(|| bad("only http:// URLs are webhooks"))?;
        if rest.chars().any(|c| c.is_whitespace() || c.is_control()) {
            return Err(bad("it contains a space or a control character"));
        }
        let (authority, path) = match rest.find('/') {
            Some(at) => (&rest[..at], &rest[at..]),
            None => (rest, "/"),
        };
        if authority.contains('@') {
            return Err(bad("user names in URLs are not taken (the secret signs instead)"));
        }
        let (host, port) = match authority.rsplit_once(':') {
            Some((host, port)) if !host.ends_with(']') || authority.starts_with('[') => {
                (host, port.parse::<u16>().map_err(|_| bad("its port is not a number up to 65535"))?)
            }
            _ => (authority, 80),
        };
        if host.is_empty() {
            return Err(bad("no host"));
        }
        Ok(Url { text: text.to_string(), host: host.to_string(), port, path: path.to_string() })
    }
}

/// The signature of `body` sent at `timestamp` (seconds since the Unix
/// epoch) under `secret`: hex HMAC-SHA256 of `TIMESTAMP.BODY`.
pub fn sign(secret: &[u8], timestamp: u64, body: &[u8]) -> String {
    // HMAC takes a key of any length: the error branch is never taken (an
    // empty signature would verify nowhere).
    let Ok(mut mac) = Hmac::<Sha256>::new_from_slice(secret) else { return String::new() };
    mac.update(timestamp.to_string().as_bytes());
    mac.update(b".");
    mac.update(body);
    hex::encode(mac.finalize().into_bytes())
}

/// The wait before try `attempt` (1 is the first retry).
pub fn backoff(attempt: u32) -> Duration {
    let factor = 1u32.checked_shl(attempt.saturating_sub(1)).unwrap_or(u32::MAX);
    FIRST_RETRY.saturating_mul(factor).min(LONGEST_RETRY)
}

/// POSTs `body` to `url` signed at `timestamp`; Ok when the answer is 2xx.
pub fn post(url: &Url, secret: &[u8], event_id: u64, timestamp: u64, body: &[u8]) -> Result<(), WebhookError> {
    let failed = |message: String| WebhookError::Delivery { url: url.text.clone(), message };
    let address = (url.host.trim_start_matches('[').trim_end_matches(']'), url.port)
        .to_socket_addrs()
        .map_err(|e| failed(format!("cannot resolve: {e}")))?
        .next()
        .ok_or_else(|| failed("resolves to no address".into()))?;
    let mut stream = TcpStream::connect_timeout(&address, DELIVERY_TIMEOUT).map_err(|e| failed(e.to_string()))?;
    stream.set_read_timeout(Some(DELIVERY_TIMEOUT)).map_err(|e| failed(e.to_string()))?;
    stream.set_write_timeout(Some(DELIVERY_TIMEOUT)).map_err(|e| failed(e.to_string()))?;
    let host = if url.port == 80 { url.host.clone() } else { format!("{}:{}", url.host, url.port) };
    let head = format!(
        "POST {} HTTP/1.1\r\nHost: {host}\r\nUser-Agent: subsume\r\nContent-Type: application/json\r\n\
         Content-Length: {}\r\nX-Subsume-Event-Id: {event_id}\r\nX-Subsume-Timestamp: {timestamp}\r\n\
         X-Subsume-Signature: sha256={}\r\nConnection: close\r\n\r\n",
        url.path,
        body.len(),
        sign(secret, timestamp, body)
    );
    stream.write_all(head.as_bytes()).and_then(|_| stream.write_all(body)).map_err(|e| failed(e.to_string()))?;
    let mut answer = Vec::new();
    let mut chunk = [0u8; 512];
    while !answer.windows(2).any(|w| w == b"\r\n") && answer.len() < MAX_ANSWER_BYTES {
        match stream.read(&mut chunk) {
            Ok(0) => break,
            Ok(n) => answer.extend_from_slice(&chunk[..n]),
            Err(e) => return Err(failed(format!("no answer: {e}"))),
        }
    }
    let line = String::from_utf8_lossy(&answer);
    let line = line.lines().next().unwrap_or("");
    let status = line.split_whitespace().nth(1).and_then(|s| s.parse::<u16>().ok());
    match status {
        Some(200..=299) => Ok(()),
        Some(code) => Err(failed(format!("answered {code}"))),
        None => Err(failed(format!("answered no HTTP status: {:?}", line.chars().take(80).collect::<String>()))),
    }
}

/// The delivery thread: the oldest waiting event is sent until its
/// receiver acknowledges it (or it has been tried [`MAX_ATTEMPTS`] times),
/// then removed; then the next one.
pub(crate) fn deliver_forever(notifier: &Notifier) {
    let mut attempts = 0u32;
    let mut dropped_told = 0u64;
    loop {
        let (oldest, dropped) = match notifier.outbox() {
            Ok(outbox) => (outbox.oldest(), outbox.dropped()),
            Err(e) => {
                tracing::error!("webhooks: delivery stops: {e}");
                return;
            }
        };
        if dropped > dropped_told {
            tracing::warn!("webhooks: {dropped} events dropped so far because the outbox was full");
            dropped_told = dropped;
        }
        let Some(entry) = oldest else {
            notifier.wait(Duration::from_secs(60));
            continue;
        };
        let id = entry.event.id;
        match deliver(notifier, &entry) {
            Ok(()) => {
                attempts = 0;
                forget(notifier, id);
            }
            Err(e) => {
                attempts += 1;
                if attempts >= MAX_ATTEMPTS {
                    tracing::error!("webhooks: event {id} given up after {attempts} tries: {e}");
                    attempts = 0;
                    forget(notifier, id);
                } else {
                    let wait = backoff(attempts);
                    tracing::warn!("webhooks: event {id} not delivered (try {attempts}), again in {wait:?}: {e}");
                    std::thread::sleep(wait);
                }
            }
        }
    }
}

fn deliver(notifier: &Notifier, entry: &Entry) -> Result<(), WebhookError> {
    let Some(hook) = notifier.hook(&entry.hook) else {
        return Err(WebhookError::Delivery {
            url: entry.hook.clone(),
            message: "no longer configured; the event is not sent".into(),
        });
    };
    let body = serde_json::to_vec(&entry.event)
        .map_err(|e| WebhookError::Delivery { url: entry.hook.clone(), message: e.to_string() })?;
    post(&hook.url, &hook.secret, entry.event.id, unix_now_s(), &body)
}

fn forget(notifier: &Notifier, id: u64) {
    match notifier.outbox().and_then(|mut outbox| outbox.remove(id)) {
        Ok(()) => {}
        Err(e) => tracing::error!("webhooks: event {id} sent but cannot be removed from the outbox: {e}"),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_signature_is_hmac_sha256_of_the_timestamp_a_dot_and_the_body() {
        // RFC 4231 test case 2's key and message, with this scheme's
        // framing: HMAC-SHA256("Jefe", "1700000000.what do ya want for nothing?")
        // as computed by Python's hmac (tests/python is its venv):
        // hmac.new(b"Jefe", b"1700000000.what do ya want for nothing?", "sha256").hexdigest()
        let signed = sign(b"Jefe", 1_700_000_000, b"what do ya want for nothing?");
        assert_eq!(signed, PYTHON_SIGNATURE);
        // The timestamp is bound: another second, another signature.
        assert_ne!(sign(b"Jefe", 1_700_000_001, b"what do ya want for nothing?"), signed);
    }

    const PYTHON_SIGNATURE: &str = "1cdd0650c8be1cb0974b1788d458b1e781206cfef59b85faafc582d2e182c57e";

    #[test]
    fn retries_wait_twice_as_long_each_time_up_to_the_longest() {
        assert_eq!(backoff(1), FIRST_RETRY);
        assert_eq!(backoff(2), FIRST_RETRY * 2);
        assert_eq!(backoff(5), FIRST_RETRY * 16);
        assert_eq!(backoff(30), LONGEST_RETRY);
        assert_eq!(backoff(u32::MAX), LONGEST_RETRY);
    }

    #[test]
    fn only_plain_http_urls_are_webhooks() {
        let url = Url::parse("http://127.0.0.1:8080/hooks/lab?x=1").unwrap();
        assert_eq!((url.host.as_str(), url.port, url.path.as_str()), ("127.0.0.1", 8080, "/hooks/lab?x=1"));
        let url = Url::parse("http://example.org").unwrap();
        assert_eq!((url.port, url.path.as_str()), (80, "/"));
        for (bad, why) in [
            ("ftp://example.org/", "only http"),
            ("https://example.org/", "https is not delivered yet"),
            ("http://:80/", "no host"),
            ("http://a:99999/", "port"),
            ("http://u:p@a/", "user names"),
            ("http://a/ b", "space"),
        ] {
            let e = Url::parse(bad).unwrap_err().to_string();
            assert!(e.contains(why), "{bad}: {e}");
        }
        assert!(Url::parse(&format!("http://a/{}", "x".repeat(MAX_URL_BYTES))).is_err());
    }
}
