//! TLS for the host's listeners: the portal (with its WebSockets) and the
//! network platform (its line protocol and its WebSocket). Owns the server
//! identity read from PEM files (`--tls-cert`, `--tls-key`), the rule that
//! plain text is served on loopback addresses only unless the robot's owner
//! opts in (`--allow-plain-http`), and the handshake with its deadline
//! (`admission::serve_http` serves HTTP over it). For the clients: a
//! lab's own authority read from PEM (`--ca`, `--tls-ca`) and the system's
//! trusted roots.
//!
//! Invariants: a listener that is not on a loopback address speaks TLS
//! unless the owner allowed plain text explicitly; a peer that opens
//! connections and never finishes the handshake holds a task for at most
//! [`HANDSHAKE_TIMEOUT`], and at most [`MAX_HANDSHAKES`] handshakes run at
//! once per listener.

use std::io::BufReader;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

use rustls_pki_types::pem::PemObject as _;
use rustls_pki_types::{CertificateDer, PrivateKeyDer};
use thiserror::Error;
use tokio_rustls::TlsAcceptor;
use tokio_rustls::rustls;

/// Longest TLS handshake: a peer that connects and stalls holds a task and
/// a socket this long at most.
pub const HANDSHAKE_TIMEOUT: Duration = Duration::from_secs(10);
/// Handshakes in progress at once on one listener (each costs public-key
/// operations): more connections wait for one to end, within their own
/// deadlines.
pub const MAX_HANDSHAKES: usize = 64;
/// Largest certificate chain or key file read: these are kilobytes; a
/// mistaken path to a large file must not be read whole.
pub const MAX_PEM_BYTES: u64 = 1 << 20;

/// Why the TLS identity or a listener's transport was refused.
#[derive(Debug, Error)]
pub enum TlsError {
    #[error("cannot read the TLS {what} {}: {source}", .path.display())]
    Read {
        what: &'static str,
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("the TLS {what} {} is larger than {} bytes", .path.display(), MAX_PEM_BYTES)]
    TooLarge { what: &'static str, path: PathBuf },
    #[error("{}: {why}", .path.display())]
    Pem { path: PathBuf, why: String },
    #[error("{}: no certificate in it (expected PEM blocks 'BEGIN CERTIFICATE')", .path.display())]
    NoCertificate { path: PathBuf },
    #[error("the certificate {} and the key {} do not make a TLS identity: {why}", .cert.display(), .key.display())]
    Identity { cert: PathBuf, key: PathBuf, why: String },
    #[error("the system has no trusted root certificates ({why}): give the portal's authority with --ca FILE")]
    NoSystemRoots { why: String },
    #[error("--tls-cert and --tls-key go together: give both or neither")]
    HalfIdentity,
    #[error(
        "the {what} would speak plain text on {address}, which is not a loopback address: \
         give the host a certificate (--tls-cert and --tls-key), listen on 127.0.0.1, \
         or accept passwords and commands crossing the network in clear with --allow-plain-http"
    )]
    PlainRemote { what: String, address: SocketAddr },
}

/// The host's TLS identity: its certificate chain and private key.
#[derive(Clone)]
pub struct TlsIdentity {
    /// For HTTP listeners (ALPN `http/1.1`).
    http: Arc<rustls::ServerConfig>,
    /// For the teleoperation line protocol (no ALPN).
    lines: Arc<rustls::ServerConfig>,
    pub cert_path: PathBuf,
}

impl std::fmt::Debug for TlsIdentity {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "TlsIdentity({})", self.cert_path.display())
    }
}

fn read_pem(what: &'static str, path: &Path) -> Result<Vec<u8>, TlsError> {
    use std::io::Read as _;
    let file = std::fs::File::open(path).map_err(|source| TlsError::Read { what, path: path.into(), source })?;
    let mut bytes = Vec::new();
    file.take(MAX_PEM_BYTES + 1).read_to_end(&mut bytes).map_err(|source| TlsError::Read {
        what,
        path: path.into(),
        source,
    })?;
    if bytes.len() as u64 > MAX_PEM_BYTES {
        return Err(TlsError::TooLarge { what, path: path.into() });
    }
    Ok(bytes)
}

impl TlsIdentity {
    /// Reads a PEM certificate chain (the server's certificate first) and
    /// a PEM private key (PKCS#8, PKCS#1 or SEC1), and checks they match.
    pub fn load(cert: &Path, key: &Path) -> Result<TlsIdentity, TlsError> {
        let cert_pem = read_pem("certificate", cert)?;
        let chain = CertificateDer::pem_reader_iter(BufReader::new(cert_pem.as_slice()))
            .collect::<Result<Vec<_>, _>>()
            .map_err(|e| TlsError::Pem { path: cert.into(), why: format!("not a PEM certificate chain: {e}") })?;
        if chain.is_empty() {
            return Err(TlsError::NoCertificate { path: cert.into() });
        }
        let key_pem = read_pem("key", key)?;
        let private = PrivateKeyDer::from_pem_slice(&key_pem).map_err(|e| TlsError::Pem {
            path: key.into(),
            why: format!(
                "no private key in it (expected PEM 'PRIVATE KEY', 'RSA PRIVATE KEY' or 'EC PRIVATE KEY'): {e}"
            ),
        })?;
        let provider = Arc::new(rustls::crypto::ring::default_provider());
        let identity_error = |why: String| TlsError::Identity { cert: cert.into(), key: key.into(), why };
        let base = rustls::ServerConfig::builder_with_provider(provider)
            .with_safe_default_protocol_versions()
            .map_err(|e| identity_error(e.to_string()))?
            .with_no_client_auth()
            .with_single_cert(chain, private)
            .map_err(|e| identity_error(e.to_string()))?;
        let mut http = base.clone();
        http.alpn_protocols = vec![b"http/1.1".to_vec()];
        Ok(TlsIdentity { http: Arc::new(http), lines: Arc::new(base), cert_path: cert.into() })
    }

    /// Loads the identity when both paths are given, none when neither is.
    pub fn from_options(cert: Option<&Path>, key: Option<&Path>) -> Result<Option<TlsIdentity>, TlsError> {
        match (cert, key) {
            (Some(cert), Some(key)) => TlsIdentity::load(cert, key).map(Some),
            (None, None) => Ok(None),
            _ => Err(TlsError::HalfIdentity),
        }
    }

    /// The acceptor for HTTP (and WebSocket) listeners.
    pub fn http_acceptor(&self) -> TlsAcceptor {
        TlsAcceptor::from(self.http.clone())
    }

    /// The acceptor for the teleoperation line protocol.
    pub fn line_acceptor(&self) -> TlsAcceptor {
        TlsAcceptor::from(self.lines.clone())
    }
}

/// The CA certificates in `ca` (PEM), each checked to be one a client can
/// trust as a root; at least one.
pub fn read_authority(ca: &Path) -> Result<Vec<CertificateDer<'static>>, TlsError> {
    let pem = read_pem("CA certificate", ca)?;
    let mut roots = rustls::RootCertStore::empty();
    let mut certificates = Vec::new();
    for cert in CertificateDer::pem_reader_iter(BufReader::new(pem.as_slice())) {
        let cert = cert.map_err(|e| TlsError::Pem { path: ca.into(), why: format!("not a PEM certificate: {e}") })?;
        roots
            .add(cert.clone())
            .map_err(|e| TlsError::Pem { path: ca.into(), why: format!("not a CA certificate: {e}") })?;
        certificates.push(cert);
    }
    if certificates.is_empty() {
        return Err(TlsError::NoCertificate { path: ca.into() });
    }
    Ok(certificates)
}

/// The system's trusted roots, as `rustls-native-certs` reads them: on
/// Linux the distribution's bundle (Debian's `/etc/ssl/certs`, found
/// with openssl-probe), or the files `SSL_CERT_FILE` and `SSL_CERT_DIR`
/// name when set. At least one.
/// `ureq`'s TLS settings (rustls, the ring provider) trusting the
/// authority in `ca`, or the system's roots: the one way the host's HTTPS
/// clients (the command line's portal client, the webhooks) trust a server.
pub fn ureq_tls(ca: Option<&Path>) -> Result<ureq::tls::TlsConfig, TlsError> {
    let roots = match ca {
        Some(ca) => read_authority(ca)?,
        None => system_roots()?,
    };
    let roots: Vec<ureq::tls::Certificate<'static>> =
        roots.iter().map(|c| ureq::tls::Certificate::from_der(c.as_ref()).to_owned()).collect();
    Ok(ureq::tls::TlsConfig::builder()
        .provider(ureq::tls::TlsProvider::Rustls)
        .root_certs(ureq::tls::RootCerts::new_with_certs(&roots))
        .unversioned_rustls_crypto_provider(Arc::new(rustls::crypto::ring::default_provider()))
        .build())
}

pub fn system_roots() -> Result<Vec<CertificateDer<'static>>, TlsError> {
    let found = rustls_native_certs::load_native_certs();
    if found.certs.is_empty() {
        let why = found.errors.first().map_or_else(|| "none found".to_string(), ToString::to_string);
        return Err(TlsError::NoSystemRoots { why });
    }
    Ok(found.certs)
}

/// A client configuration trusting the CA certificates in `ca` (PEM) and
/// nothing else: for `subsume teleop --tls-ca` and the benchmarks.
pub fn client_config(ca: &Path) -> Result<Arc<rustls::ClientConfig>, TlsError> {
    let mut roots = rustls::RootCertStore::empty();
    for cert in read_authority(ca)? {
        roots.add(cert).map_err(|e| TlsError::Pem { path: ca.into(), why: format!("not a CA certificate: {e}") })?;
    }
    let provider = Arc::new(rustls::crypto::ring::default_provider());
    let config = rustls::ClientConfig::builder_with_provider(provider)
        .with_safe_default_protocol_versions()
        .map_err(|e| TlsError::Pem { path: ca.into(), why: e.to_string() })?
        .with_root_certificates(roots)
        .with_no_client_auth();
    Ok(Arc::new(config))
}

/// The owner's transport settings, shared by every listener of the host
/// (the portal, and each network platform through `builtin::Services`).
#[derive(Clone, Debug, Default)]
pub struct HostTls {
    /// The certificate listeners use, if the host has one.
    pub identity: Option<TlsIdentity>,
    /// Plain text allowed on addresses other than loopback
    /// (`--allow-plain-http`).
    pub allow_plain_remote: bool,
}

impl HostTls {
    /// Whether a listener on `address` may speak plain text; `what` names
    /// it in the error ("portal", "teleoperation line protocol", ...).
    pub fn check_plain(&self, what: &str, address: SocketAddr) -> Result<(), TlsError> {
        if address.ip().is_loopback() || self.allow_plain_remote {
            Ok(())
        } else {
            Err(TlsError::PlainRemote { what: what.to_string(), address })
        }
    }
}

/// The TLS handshake with `peer`, within [`HANDSHAKE_TIMEOUT`]; `None`
/// (logged at debug level: scanners are common) when it fails.
pub async fn handshake(
    acceptor: &TlsAcceptor,
    tcp: tokio::net::TcpStream,
    peer: SocketAddr,
) -> Option<tokio_rustls::server::TlsStream<tokio::net::TcpStream>> {
    match tokio::time::timeout(HANDSHAKE_TIMEOUT, acceptor.accept(tcp)).await {
        Ok(Ok(stream)) => Some(stream),
        Ok(Err(e)) => {
            tracing::debug!("TLS handshake with {peer} failed: {e}");
            None
        }
        Err(_) => {
            tracing::debug!("TLS handshake with {peer} timed out after {} s", HANDSHAKE_TIMEOUT.as_secs());
            None
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn plain_text_is_for_loopback_unless_allowed() {
        let strict = HostTls::default();
        let loopback: SocketAddr = "127.0.0.1:8080".parse().unwrap_or_else(|_| SocketAddr::from(([127, 0, 0, 1], 0)));
        let v6: SocketAddr = "[::1]:8080".parse().unwrap_or(loopback);
        let any: SocketAddr = "0.0.0.0:8080".parse().unwrap_or(loopback);
        assert!(strict.check_plain("portal", loopback).is_ok());
        assert!(strict.check_plain("portal", v6).is_ok());
        let refused = strict.check_plain("portal", any).map_err(|e| e.to_string());
        assert!(
            refused.as_ref().is_err_and(|e| e.starts_with("the portal would speak plain text on 0.0.0.0:8080")),
            "{refused:?}"
        );
        let allowed = HostTls { identity: None, allow_plain_remote: true };
        assert!(allowed.check_plain("portal", any).is_ok());
    }

    #[test]
    fn bad_identity_files_are_named() {
        let dir = tempfile::tempdir().ok();
        let Some(dir) = dir else { return };
        let missing = TlsIdentity::load(&dir.path().join("nope.pem"), &dir.path().join("key.pem"));
        assert!(
            missing.as_ref().is_err_and(|e| e.to_string().starts_with("cannot read the TLS certificate ")),
            "{missing:?}"
        );
        let empty = dir.path().join("empty.pem");
        let _ = std::fs::write(&empty, "not pem\n");
        let none = TlsIdentity::load(&empty, &empty).map_err(|e| e.to_string());
        assert!(
            none.as_ref().is_err_and(
                |e| e.ends_with("empty.pem: no certificate in it (expected PEM blocks 'BEGIN CERTIFICATE')")
            ),
            "{none:?}"
        );
        assert!(matches!(TlsIdentity::from_options(Some(&empty), None), Err(TlsError::HalfIdentity)));
        assert!(matches!(TlsIdentity::from_options(None, None), Ok(None)));
    }
}
