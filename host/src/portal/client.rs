//! The command line's HTTP client of a portal, and `subsume estop HOST` and
//! `subsume release HOST` on it: the emergency stop from a script or a
//! physical button wired to a small computer, through the portal's HTTP API
//! (docs/estop.md): log in, `POST /api/v1/estop` or `/api/v1/release`, log
//! out. `deploy` and `lab` (`deploy_client.rs`, `lab_client.rs`) send their
//! requests through the same [`Connection`].
//!
//! HTTP is `ureq`'s (blocking HTTP/1.1), over rustls with the ring provider
//! for `https://`. A portal's certificate is checked against the system's
//! trusted roots (`tls::system_roots`: Debian's `/etc/ssl/certs`, or
//! `SSL_CERT_FILE`), or only against a lab's own authority (`--ca FILE`).
//! Every wait is bounded (connecting, each read and write), answers are read
//! as they arrive (a results archive is never held whole), no proxy and no
//! redirect is followed.
//!
//! Invariants: everything that can be checked here is checked before any
//! connection is made (the address, the certificates to trust); a password
//! never goes in clear to an address other than loopback unless the person
//! said so (`--allow-plain-http`).

use std::net::IpAddr;
use std::path::PathBuf;
use std::time::Duration;

use serde_json::{Value, json};
use thiserror::Error;
use tokio_rustls::rustls;

use crate::contract::clip_to;
use crate::tls::{self, TlsError};

/// Longest wait to resolve the portal's name, and to connect: a stop that
/// cannot be delivered must say so quickly, not hang the button's script.
pub const CONNECT_TIMEOUT: Duration = Duration::from_secs(5);
/// Longest wait for each read or write of `estop` and `release` (the TLS
/// handshake's included): a portal that stalls is reported within seconds.
pub const CLIENT_TIMEOUT: Duration = Duration::from_secs(5);
/// Largest answer read: the API's answers here are a few hundred bytes; a
/// host that sends without end cannot fill the client's memory.
pub const MAX_ANSWER_BYTES: u64 = 1 << 20;
/// Largest head of an answer (status line and headers): a host that sends
/// headers without end cannot fill the client's memory.
pub const MAX_HEAD_BYTES: usize = 64 << 10;
/// Connections kept idle for the next request: none. Each request has its
/// own connection (as the hand-written client had): a request sent on a
/// kept connection the portal has just closed (its header deadline,
/// `admission::HEADER_READ_TIMEOUT`, closes idle ones) would fail, and
/// `ureq` does not send it again.
pub const MAX_IDLE_CONNECTIONS: usize = 0;

/// Who logs in, where, and how the portal is trusted.
#[derive(Clone, Debug)]
pub struct Login {
    /// The portal's address: `https://HOST[:PORT]`, `http://HOST[:PORT]`
    /// or `HOST:PORT` (plain http).
    pub host: String,
    pub user: String,
    pub password: String,
    /// Trust only this authority (PEM) for the portal's certificate, not
    /// the system's roots (`--ca`).
    pub ca: Option<PathBuf>,
    /// Send the password in clear to an address other than loopback
    /// (`--allow-plain-http`).
    pub allow_plain_http: bool,
}

/// What the command line asks.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum LockAction {
    Engage,
    Release,
}

/// Why a request to a portal did not happen or was refused.
#[derive(Debug, Error)]
pub enum ClientError {
    #[error("bad portal address '{0}': expected https://HOST[:PORT], http://HOST[:PORT] or HOST:PORT")]
    Host(String),
    #[error(
        "refusing to send a password in clear to http://{0}, which is not a loopback address: \
         use https:// (with --ca FILE for a lab's own authority), or give --allow-plain-http \
         on a network you trust"
    )]
    PlainRemote(String),
    #[error("--ca {} is for a portal on https://, and {address} is plain http", .ca.display())]
    CaWithoutTls { ca: PathBuf, address: String },
    #[error(transparent)]
    Tls(#[from] TlsError),
    #[error("cannot make a request of {path}: {why}")]
    Request { path: String, why: String },
    #[error("cannot reach the portal at {address}: {reason}")]
    Connect { address: String, reason: String },
    #[error("the portal at {address} presented a certificate this client does not trust ({reason}): {hint}")]
    Untrusted { address: String, reason: String, hint: String },
    #[error("the portal at {address} answered {status}: {message}")]
    Refused { address: String, status: u16, message: String },
    #[error("the portal at {0} gave an answer that is not HTTP")]
    Garbled(String),
    #[error(
        "the portal at {address} does not speak TLS ({reason}): if it serves plain http on loopback, \
         give http://{host}:{port}"
    )]
    NotTls { address: String, reason: String, host: String, port: u16 },
    #[error("the answer of the portal at {address} is larger than {limit} bytes, the most read")]
    TooLarge { address: String, limit: u64 },
}

/// A portal's address, parsed.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct PortalUrl {
    /// `https://`.
    pub secure: bool,
    /// A name, an IPv4 address, or an IPv6 address in brackets.
    pub host: String,
    pub port: u16,
}

impl PortalUrl {
    /// `https://HOST[:PORT]` (port 443), `http://HOST[:PORT]` (port 80)
    /// or `HOST:PORT` (plain http); a trailing `/` is allowed, no path.
    pub fn parse(text: &str) -> Result<PortalUrl, ClientError> {
        let bad = || ClientError::Host(clip_to(text, MAX_SHOWN_ADDRESS));
        let trimmed = text.strip_suffix('/').unwrap_or(text);
        let (secure, rest, port_needed) = if let Some(rest) = trimmed.strip_prefix("https://") {
            (true, rest, false)
        } else if let Some(rest) = trimmed.strip_prefix("http://") {
            (false, rest, false)
        } else {
            (false, trimmed, true)
        };
        let forbidden = |c: char| c.is_whitespace() || c.is_control() || "/?#@\\".contains(c);
        if rest.is_empty() || rest.chars().any(forbidden) {
            return Err(bad());
        }
        let (host, port) = match rest.strip_prefix('[') {
            Some(v6) => {
                let (inside, after) = v6.split_once(']').ok_or_else(bad)?;
                inside.parse::<std::net::Ipv6Addr>().map_err(|_| bad())?;
                let port = if after.is_empty() { None } else { Some(after.strip_prefix(':').ok_or_else(bad)?) };
                (format!("[{inside}]"), port)
            }
            None => match rest.split_once(':') {
                Some((host, port)) => (host.to_string(), Some(port)),
                None => (rest.to_string(), None),
            },
        };
        if host.is_empty() || (port_needed && port.is_none()) {
            return Err(bad());
        }
        let port = match port {
            Some(port) => port.parse::<u16>().ok().filter(|p| *p != 0).ok_or_else(bad)?,
            None if secure => 443,
            None => 80,
        };
        Ok(PortalUrl { secure, host, port })
    }

    /// `https://HOST:PORT` or `http://HOST:PORT`.
    fn base(&self) -> String {
        format!("{}://{}:{}", if self.secure { "https" } else { "http" }, self.host, self.port)
    }

    /// The address as messages show it, as the commands take it:
    /// `HOST:PORT` for plain http, `https://HOST[:PORT]` (443 left out).
    pub fn shown(&self) -> String {
        match (self.secure, self.port) {
            (true, 443) => format!("https://{}", self.host),
            (true, _) => self.base(),
            (false, _) => format!("{}:{}", self.host, self.port),
        }
    }

    /// `localhost`, or an address of the loopback network (127.0.0.0/8,
    /// ::1, and IPv4's loopback mapped into IPv6).
    pub fn is_loopback(&self) -> bool {
        let bare = self.host.trim_start_matches('[').trim_end_matches(']');
        bare.eq_ignore_ascii_case("localhost") || bare.parse::<IpAddr>().is_ok_and(|ip| ip.to_canonical().is_loopback())
    }
}

/// Most bytes of a bad address quoted in its error.
const MAX_SHOWN_ADDRESS: usize = 200;

/// Whether a password may go to `url`: over TLS, on loopback, or where the
/// person allowed plain http.
pub fn check_plain(url: &PortalUrl, allow_plain_http: bool) -> Result<(), ClientError> {
    if url.secure || allow_plain_http || url.is_loopback() {
        Ok(())
    } else {
        Err(ClientError::PlainRemote(url.shown()))
    }
}

/// Requests to one portal, every wait bounded.
pub struct Connection {
    agent: ureq::Agent,
    url: PortalUrl,
    shown: String,
    /// `--ca`, named when a certificate is not trusted.
    ca: Option<PathBuf>,
}

impl Connection {
    /// A client of `login`'s portal whose reads and writes wait at most
    /// `timeout` each. Checks, before anything is sent: the address, that
    /// a password may go there, and the certificates to trust.
    pub fn open(login: &Login, timeout: Duration) -> Result<Connection, ClientError> {
        let url = PortalUrl::parse(&login.host)?;
        check_plain(&url, login.allow_plain_http)?;
        let shown = url.shown();
        let mut config = ureq::Agent::config_builder()
            .http_status_as_error(false)
            .max_redirects(0)
            .proxy(None)
            .user_agent(concat!("subsume/", env!("CARGO_PKG_VERSION")))
            .max_response_header_size(MAX_HEAD_BYTES)
            .max_idle_connections(MAX_IDLE_CONNECTIONS)
            .max_idle_connections_per_host(MAX_IDLE_CONNECTIONS)
            .timeout_resolve(Some(CONNECT_TIMEOUT))
            .timeout_connect(Some(CONNECT_TIMEOUT))
            .timeout_per_read(Some(timeout))
            .timeout_per_write(Some(timeout));
        match (&login.ca, url.secure) {
            (Some(ca), false) => return Err(ClientError::CaWithoutTls { ca: ca.clone(), address: shown }),
            (None, false) => {}
            (ca, true) => config = config.tls_config(tls::ureq_tls(ca.as_deref())?),
        }
        Ok(Connection { agent: config.build().new_agent(), url, shown, ca: login.ca.clone() })
    }

    /// The portal's address as messages show it.
    pub fn address(&self) -> &str {
        &self.shown
    }

    /// Sends one request with `body` as `content_type` and reads the
    /// answer's head; its body is read as it arrives.
    pub fn send(
        &self,
        method: &str,
        path: &str,
        token: Option<&str>,
        content_type: &str,
        body: &[u8],
    ) -> Result<Answer, ClientError> {
        let mut request = ureq::http::Request::builder()
            .method(method)
            .uri(format!("{}{path}", self.url.base()))
            .header("content-type", content_type);
        if let Some(token) = token {
            request = request.header("authorization", format!("Bearer {token}"));
        }
        let request = request
            .body(body)
            .map_err(|e| ClientError::Request { path: clip_to(path, MAX_SHOWN_ADDRESS), why: e.to_string() })?;
        let answer = self.agent.run(request).map_err(|e| self.failed(e))?;
        Ok(Answer { status: answer.status().as_u16(), body: answer.into_body(), address: self.shown.clone() })
    }

    /// One JSON request; the JSON answer of a 2xx, else the portal's
    /// error, whole (bounded by [`MAX_ANSWER_BYTES`]).
    fn request(&self, method: &str, path: &str, token: Option<&str>, body: &Value) -> Result<Value, ClientError> {
        let body = if body.is_null() { String::new() } else { body.to_string() };
        let (status, json, text) =
            self.send(method, path, token, "application/json", body.as_bytes())?.read(MAX_ANSWER_BYTES)?;
        if (200..300).contains(&status) {
            return Ok(json);
        }
        let message = json["error"].as_str().map_or_else(|| text.trim().to_string(), str::to_string);
        Err(ClientError::Refused {
            address: self.shown.clone(),
            status,
            message: clip_to(&message, MAX_ANSWER_BYTES as usize),
        })
    }

    /// `ureq`'s error as this client's: a certificate not trusted, an
    /// answer that is not HTTP, or a portal not reached.
    fn failed(&self, error: ureq::Error) -> ClientError {
        let address = self.shown.clone();
        if let Some(reason) = certificate_problem(&error) {
            let hint = match &self.ca {
                Some(ca) => {
                    format!("it was not issued for {} by the authority in --ca {}", self.url.host, ca.display())
                }
                None => "give the lab's own authority with --ca FILE (PEM), or give the portal a certificate \
                         from an authority the system trusts"
                    .to_string(),
            };
            return ClientError::Untrusted { address, reason, hint };
        }
        if let Some(e @ rustls::Error::InvalidMessage(_)) = rustls_error(&error) {
            let (host, port) = (self.url.host.clone(), self.url.port);
            return ClientError::NotTls { address, reason: e.to_string(), host, port };
        }
        answer_error(error, address)
    }
}

/// What rustls said, when the error is a TLS one.
fn rustls_error(error: &ureq::Error) -> Option<&rustls::Error> {
    match error {
        ureq::Error::Rustls(e) => Some(e),
        ureq::Error::Io(e) => e.get_ref().and_then(|inner| inner.downcast_ref::<rustls::Error>()),
        _ => None,
    }
}

/// A certificate the client refused, as rustls said it.
fn certificate_problem(error: &ureq::Error) -> Option<String> {
    let rustls_error = rustls_error(error)?;
    matches!(rustls_error, rustls::Error::InvalidCertificate(_)).then(|| rustls_error.to_string())
}

/// An error reading or waiting for an answer from `address`.
fn answer_error(error: ureq::Error, address: String) -> ClientError {
    match error {
        ureq::Error::BodyExceedsLimit(limit) => ClientError::TooLarge { address, limit },
        ureq::Error::Protocol(_) | ureq::Error::LargeResponseHeader(..) => ClientError::Garbled(address),
        ureq::Error::Io(e) => ClientError::Connect { address, reason: e.to_string() },
        other => ClientError::Connect { address, reason: other.to_string() },
    }
}

/// An answer whose head was read; its body is read as it arrives.
pub struct Answer {
    pub status: u16,
    body: ureq::Body,
    address: String,
}

impl Answer {
    /// The status, the body as JSON (`Null` when it is not) and as text;
    /// an answer longer than `limit` bytes is an error.
    pub fn read(self, limit: u64) -> Result<(u16, Value, String), ClientError> {
        let status = self.status;
        let text = self.text(limit)?;
        let json: Value = serde_json::from_str(text.trim()).unwrap_or(Value::Null);
        Ok((status, json, text))
    }

    /// The body as text; an answer longer than `limit` bytes is an error.
    pub fn text(self, limit: u64) -> Result<String, ClientError> {
        let bytes =
            self.body.into_with_config().limit(limit).read_to_vec().map_err(|e| answer_error(e, self.address))?;
        Ok(String::from_utf8_lossy(&bytes).into_owned())
    }

    /// The body as a reader, streamed as it arrives; the caller bounds
    /// what it reads (`lab_client`'s archives: `MAX_ARCHIVE_BYTES`).
    pub fn into_reader(self) -> ureq::BodyReader<'static> {
        self.body.into_reader()
    }
}

/// Engages or releases on `login`'s portal; returns what the portal said,
/// in a line.
pub fn lock_action(login: &Login, action: LockAction) -> Result<String, ClientError> {
    let portal = Connection::open(login, CLIENT_TIMEOUT)?;
    let answer =
        portal.request("POST", "/api/v1/login", None, &json!({"name": login.user, "password": login.password}))?;
    let token = answer["token"].as_str().ok_or_else(|| ClientError::Garbled(portal.shown.clone()))?.to_string();
    let path = match action {
        LockAction::Engage => "/api/v1/estop",
        LockAction::Release => "/api/v1/release",
    };
    let answer = portal.request("POST", path, Some(&token), &Value::Null);
    let _ = portal.request("POST", "/api/v1/logout", Some(&token), &Value::Null);
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

#[cfg(test)]
mod tests {
    use super::*;

    /// (address as given, parsed: (https, host, port), or refused).
    #[test]
    fn addresses_parse_with_their_scheme_and_default_port_and_bad_ones_are_refused() {
        type Parsed<'a> = Option<(bool, &'a str, u16)>;
        let cases: [(&str, Parsed); 17] = [
            ("127.0.0.1:8080", Some((false, "127.0.0.1", 8080))),
            ("http://127.0.0.1:8080/", Some((false, "127.0.0.1", 8080))),
            ("http://robot.lan", Some((false, "robot.lan", 80))),
            ("https://lab.example.org", Some((true, "lab.example.org", 443))),
            ("https://lab.example.org:8443/", Some((true, "lab.example.org", 8443))),
            ("https://[::1]:8443", Some((true, "[::1]", 8443))),
            ("http://[fe80::1]", Some((false, "[fe80::1]", 80))),
            ("robot.lan", None),
            ("", None),
            ("https://", None),
            ("x:1/y", None),
            ("https://x:1/api", None),
            ("ftp://x:1", None),
            ("https://user@x:1", None),
            ("http://x:0", None),
            ("http://x:99999", None),
            ("http://[::1", None),
        ];
        for (text, expected) in cases {
            let parsed = PortalUrl::parse(text).ok().map(|u| (u.secure, u.host, u.port));
            assert_eq!(parsed, expected.map(|(s, h, p)| (s, h.to_string(), p)), "{text}");
        }
        // As messages show them: as a command takes them again.
        for (text, shown) in [
            ("http://127.0.0.1:8080/", "127.0.0.1:8080"),
            ("https://lab.example.org:443", "https://lab.example.org"),
            ("https://[::1]:8443/", "https://[::1]:8443"),
        ] {
            assert_eq!(PortalUrl::parse(text).unwrap().shown(), shown, "{text}");
        }
    }

    /// (address, allowed without --allow-plain-http).
    #[test]
    fn a_password_goes_in_clear_only_to_loopback_unless_allowed() {
        let cases = [
            ("127.0.0.1:8080", true),
            ("http://127.3.2.1:80", true),
            ("http://localhost:8080", true),
            ("http://LOCALHOST:8080", true),
            ("http://[::1]:8080", true),
            ("http://[::ffff:127.0.0.1]:8080", true),
            ("https://192.0.2.1:8443", true),
            ("https://lab.example.org", true),
            ("http://192.0.2.1:1", false),
            ("192.0.2.1:8080", false),
            ("http://10.0.0.5:8080", false),
            ("http://[2001:db8::1]:80", false),
            ("http://robot.lan:8080", false),
            ("http://localhost.example.org:8080", false),
            ("http://0.0.0.0:8080", false),
        ];
        for (text, allowed) in cases {
            let url = PortalUrl::parse(text).unwrap();
            assert_eq!(check_plain(&url, false).is_ok(), allowed, "{text}");
            assert!(check_plain(&url, true).is_ok(), "{text} with --allow-plain-http");
        }
        let error = check_plain(&PortalUrl::parse("http://192.0.2.1:1").unwrap(), false).unwrap_err().to_string();
        assert!(error.starts_with("refusing to send a password in clear to http://192.0.2.1:1, "), "{error}");
        assert!(error.contains("--allow-plain-http"), "{error}");
    }

    #[test]
    fn nothing_is_sent_to_an_address_refused_before_connecting() {
        let login = |host: &str, ca: Option<&str>| Login {
            host: host.into(),
            user: "u".into(),
            password: "p".into(),
            ca: ca.map(PathBuf::from),
            allow_plain_http: false,
        };
        let refused = |l: Login| lock_action(&l, LockAction::Engage).unwrap_err();
        assert!(matches!(refused(login("ftp://x:1", None)), ClientError::Host(_)));
        assert!(matches!(refused(login("http://192.0.2.1:1", None)), ClientError::PlainRemote(_)));
        assert!(matches!(refused(login("127.0.0.1:1", Some("ca.pem"))), ClientError::CaWithoutTls { .. }));
        let missing = refused(login("https://127.0.0.1:1", Some("/nonexistent/ca.pem"))).to_string();
        assert!(missing.starts_with("cannot read the TLS CA certificate /nonexistent/ca.pem: "), "{missing}");
    }
}
