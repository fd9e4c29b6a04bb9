//! A webhook's delivery: each event POSTed as JSON to its URL (`http://`,
//! or `https://` verified against the system's roots or the hook's own
//! authority, with `ureq` on rustls), signed with HMAC-SHA256 under the
//! hook's secret over `TIMESTAMP.BODY` (headers `X-Subsume-Timestamp` and
//! `X-Subsume-Signature: sha256=HEX`; docs/lab.md says how to verify).
//! Runs on the delivery thread only ([`super::delivery`]), holding no lock
//! while it talks.

use std::path::Path;
use std::time::Duration;

use hmac::{Hmac, Mac};
use sha2::Sha256;
use thiserror::Error;

/// Longest webhook URL, bytes.
pub const MAX_URL_BYTES: usize = 2048;
/// How long connecting, sending or waiting for the answer may take: a
/// receiver that hangs must not hold the queue forever.
pub const DELIVERY_TIMEOUT: Duration = Duration::from_secs(10);

/// Why a URL is not a webhook's or a delivery failed.
#[derive(Debug, Error)]
pub enum WebhookError {
    #[error("url {0:?}: {1}")]
    BadUrl(String, &'static str),
    #[error("{url}: {message}")]
    Delivery { url: String, message: String },
}

/// A webhook's URL: `http[s]://HOST[:PORT]/PATH`.
#[derive(Clone, Debug, PartialEq)]
pub struct Url {
    pub text: String,
    pub secure: bool,
    host: String,
    port: u16,
    path: String,
}

impl Url {
    /// Parses `text`, an `http://` or `https://` URL.
    pub fn parse(text: &str) -> Result<Url, WebhookError> {
        let bad = |why| WebhookError::BadUrl(text.chars().take(80).collect(), why);
        if text.len() > MAX_URL_BYTES {
            return Err(bad("longer than 2048 bytes"));
        }
        let (secure, rest) = match (text.strip_prefix("https://"), text.strip_prefix("http://")) {
            (Some(rest), _) => (true, rest),
            (None, Some(rest)) => (false, rest),
            (None, None) => return Err(bad("only http:// and https:// URLs are webhooks")),
        };
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
            _ => (authority, if secure { 443 } else { 80 }),
        };
        if host.is_empty() {
            return Err(bad("no host"));
        }
        Ok(Url { text: text.to_string(), secure, host: host.to_string(), port, path: path.to_string() })
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

/// The client of one webhook: its URL's roots read once, every wait
/// bounded, no redirect followed, no proxy.
pub fn agent(url: &Url, ca: Option<&Path>) -> Result<ureq::Agent, WebhookError> {
    let bad = |message: String| WebhookError::Delivery { url: url.text.clone(), message };
    let mut config = ureq::Agent::config_builder()
        .http_status_as_error(false)
        .max_redirects(0)
        .proxy(None)
        .user_agent(concat!("subsume/", env!("CARGO_PKG_VERSION")))
        .timeout_global(Some(DELIVERY_TIMEOUT));
    match (ca, url.secure) {
        (Some(ca), false) => {
            return Err(bad(format!("ca {} is given for a plain http:// hook", ca.display())));
        }
        (None, false) => {}
        (ca, true) => config = config.tls_config(crate::tls::ureq_tls(ca).map_err(|e| bad(e.to_string()))?),
    }
    Ok(config.build().new_agent())
}

/// POSTs `body` to `url` with `agent`, signed at `timestamp`; Ok when the
/// answer is 2xx.
pub fn post(
    agent: &ureq::Agent,
    url: &Url,
    secret: &[u8],
    event_id: u64,
    timestamp: u64,
    body: &[u8],
) -> Result<(), WebhookError> {
    let failed = |message: String| WebhookError::Delivery { url: url.text.clone(), message };
    let answer = agent
        .post(&url.text)
        .header("Content-Type", "application/json")
        .header("X-Subsume-Event-Id", event_id.to_string())
        .header("X-Subsume-Timestamp", timestamp.to_string())
        .header("X-Subsume-Signature", format!("sha256={}", sign(secret, timestamp, body)))
        .send(body)
        .map_err(|e| failed(e.to_string()))?;
    match answer.status().as_u16() {
        200..=299 => Ok(()),
        code => Err(failed(format!("answered {code}"))),
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
    fn http_and_https_urls_are_webhooks() {
        let url = Url::parse("http://127.0.0.1:8080/hooks/lab?x=1").unwrap();
        assert_eq!((url.host.as_str(), url.port, url.path.as_str()), ("127.0.0.1", 8080, "/hooks/lab?x=1"));
        let url = Url::parse("http://example.org").unwrap();
        assert_eq!((url.port, url.path.as_str(), url.secure), (80, "/", false));
        let url = Url::parse("https://example.org").unwrap();
        assert_eq!((url.port, url.secure), (443, true));
        for (bad, why) in [
            ("ftp://example.org/", "only http:// and https://"),
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
