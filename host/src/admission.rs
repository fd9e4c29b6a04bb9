//! Who may hold a connection before it has shown who it is: bounded pools
//! of connections counted per client address ([`Pool`], [`Ticket`]), and
//! serving HTTP (the portal, the network platform's WebSocket listener)
//! under those bounds with a deadline on reading a request's headers
//! ([`serve_http`]).
//!
//! The threat: a peer that opens connections and never finishes what it
//! started (a request's headers, a TLS handshake, a login) holds a socket
//! and a task each. Without a bound per address, one peer reconnecting in
//! a loop takes every place there is and locks everyone else out.
//!
//! Invariants: every connection a pool admitted is counted until its
//! [`Ticket`] is dropped, so a pool's counts never drift; a peer address
//! holds at most the pool's per-address share, whatever it does; a full
//! pool refuses the newest connection, never one already admitted; a
//! refused connection costs one `try_write` and a close, never a wait.

use std::collections::HashMap;
use std::net::{IpAddr, Ipv6Addr, SocketAddr};
use std::sync::{Arc, Mutex};
use std::time::Duration;

/// Longest a client may take to send a request's headers, from the moment
/// the connection is ready for one (so an idle keep-alive connection is
/// closed after it too): a slow-loris peer trickling headers holds its
/// connection this long at most.
pub const HEADER_READ_TIMEOUT: Duration = Duration::from_secs(5);
/// Open HTTP connections per client address (per /64 for IPv6) on one
/// listener: a browser opens about six, and the live status and a
/// WebSocket hold one each; more from one address is a peer hoarding them.
pub const MAX_HTTP_CONNECTIONS_PER_ADDRESS: usize = 32;
/// Open HTTP connections on one listener: each holds a socket (a file
/// descriptor) and a task.
pub const MAX_HTTP_CONNECTIONS: usize = 512;

/// Connections the kernel completes and queues for a listener before it
/// accepts them (`listen`'s backlog; std's is 128). A peer reconnecting in
/// a loop can fill a short queue between two accepts, and then the kernel
/// drops everyone's connection attempts, the operator's too, who retries
/// only a second later. The kernel caps it at `net.core.somaxconn`.
pub const LISTEN_BACKLOG: i32 = 4096;

/// Binds a non-blocking TCP listener on `address` with [`LISTEN_BACKLOG`].
pub fn listen(address: SocketAddr) -> std::io::Result<std::net::TcpListener> {
    use std::os::fd::AsRawFd as _;
    let listener = std::net::TcpListener::bind(address)?;
    // Listening again on a listening socket only sets its backlog.
    // SAFETY: the descriptor is the listener's own, open for this call.
    if unsafe { libc::listen(listener.as_raw_fd(), LISTEN_BACKLOG) } != 0 {
        return Err(std::io::Error::last_os_error());
    }
    listener.set_nonblocking(true)?;
    Ok(listener)
}

/// Where a connection comes from, as pools count it: an IPv4 address, or
/// the /64 prefix of an IPv6 address (one machine usually has a whole /64,
/// so counting single IPv6 addresses would be no bound at all).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum PeerKey {
    V4([u8; 4]),
    V6Prefix([u8; 8]),
}

impl PeerKey {
    pub fn of(ip: IpAddr) -> PeerKey {
        match ip {
            IpAddr::V4(v4) => PeerKey::V4(v4.octets()),
            IpAddr::V6(v6) => match v6.to_ipv4_mapped() {
                Some(v4) => PeerKey::V4(v4.octets()),
                None => {
                    let octets = v6.octets();
                    let mut prefix = [0u8; 8];
                    prefix.copy_from_slice(&octets[..8]);
                    PeerKey::V6Prefix(prefix)
                }
            },
        }
    }
}

impl std::fmt::Display for PeerKey {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            PeerKey::V4(octets) => write!(f, "{}", std::net::Ipv4Addr::from(*octets)),
            PeerKey::V6Prefix(prefix) => {
                let mut octets = [0u8; 16];
                octets[..8].copy_from_slice(prefix);
                write!(f, "{}/64", Ipv6Addr::from(octets))
            }
        }
    }
}

/// Why a pool refused a connection.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum Refusal {
    #[error("{what}: {max} are open already; try again shortly")]
    Full { what: &'static str, max: usize },
    #[error("{what}: {max} are open from {peer} already")]
    PerAddress { what: &'static str, max: usize, peer: PeerKey },
}

#[derive(Debug, Default)]
struct Counts {
    total: usize,
    per_peer: HashMap<PeerKey, usize>,
}

/// A bounded pool of connections: at most `max` at once, at most
/// `per_address` from one [`PeerKey`].
#[derive(Debug)]
pub struct Pool {
    /// What the pool holds, for refusals ("unauthenticated connections").
    what: &'static str,
    max: usize,
    per_address: usize,
    counts: Mutex<Counts>,
}

/// One admitted connection's place in its pool, given back on drop.
#[derive(Debug)]
pub struct Ticket {
    pool: Arc<Pool>,
    peer: PeerKey,
}

impl Pool {
    pub fn new(what: &'static str, max: usize, per_address: usize) -> Arc<Pool> {
        Arc::new(Pool { what, max, per_address, counts: Mutex::new(Counts::default()) })
    }

    /// A place for a connection from `ip`, unless the pool or that
    /// address's share is full (the newcomer is refused, nobody admitted
    /// is pushed out).
    pub fn admit(self: &Arc<Self>, ip: IpAddr) -> Result<Ticket, Refusal> {
        let peer = PeerKey::of(ip);
        let what = self.what;
        let Ok(mut counts) = self.counts.lock() else { return Err(Refusal::Full { what, max: self.max }) };
        if counts.total >= self.max {
            return Err(Refusal::Full { what, max: self.max });
        }
        let from_peer = counts.per_peer.entry(peer).or_insert(0);
        if *from_peer >= self.per_address {
            return Err(Refusal::PerAddress { what, max: self.per_address, peer });
        }
        *from_peer += 1;
        counts.total += 1;
        Ok(Ticket { pool: self.clone(), peer })
    }

    /// Connections admitted and not yet given back.
    pub fn open(&self) -> usize {
        self.counts.lock().map(|c| c.total).unwrap_or(0)
    }

    /// Connections from `ip`'s [`PeerKey`] admitted and not yet given back.
    pub fn open_from(&self, ip: IpAddr) -> usize {
        let peer = PeerKey::of(ip);
        self.counts.lock().map(|c| c.per_peer.get(&peer).copied().unwrap_or(0)).unwrap_or(0)
    }
}

impl Drop for Ticket {
    fn drop(&mut self) {
        if let Ok(mut counts) = self.pool.counts.lock() {
            counts.total = counts.total.saturating_sub(1);
            if let Some(from_peer) = counts.per_peer.get_mut(&self.peer) {
                *from_peer -= 1;
                if *from_peer == 0 {
                    counts.per_peer.remove(&self.peer);
                }
            }
        }
    }
}

/// Tells a refused peer why in one write that never waits (a full socket
/// buffer loses the text, not the time), then closes.
pub fn refuse_now(stream: tokio::net::TcpStream, text: &str) {
    let _ = stream.try_write(text.as_bytes());
    drop(stream);
}

/// An HTTP answer for a refused connection (plain text only: over TLS
/// the connection is just closed, before the handshake costs anything).
fn http_refusal(refusal: &Refusal) -> String {
    let body = format!("{refusal}\n");
    format!(
        "HTTP/1.1 503 Service Unavailable\r\nContent-Type: text/plain; charset=utf-8\r\nRetry-After: 1\r\n\
         Connection: close\r\nContent-Length: {}\r\n\r\n{body}",
        body.len()
    )
}

/// The bounds [`serve_http`] keeps on one listener.
#[derive(Clone, Copy, Debug)]
pub struct HttpLimits {
    pub header_read: Duration,
    pub per_address: usize,
    pub max: usize,
}

impl Default for HttpLimits {
    fn default() -> HttpLimits {
        HttpLimits {
            header_read: HEADER_READ_TIMEOUT,
            per_address: MAX_HTTP_CONNECTIONS_PER_ADDRESS,
            max: MAX_HTTP_CONNECTIONS,
        }
    }
}

/// Serves `app` on `listener` until the runtime stops, over TLS when
/// `tls` is given: each connection is admitted to a pool of `limits` (a
/// refused one gets a 503 in plain text, or is closed before the TLS
/// handshake), handshaken on its own task (at most
/// [`crate::tls::MAX_HANDSHAKES`] at once, each within
/// [`crate::tls::HANDSHAKE_TIMEOUT`]), then served by hyper's HTTP/1.1 with
/// upgrades (WebSockets) and the header deadline, with the peer's address
/// as axum's `ConnectInfo<SocketAddr>`.
pub async fn serve_http(
    listener: tokio::net::TcpListener,
    tls: Option<tokio_rustls::TlsAcceptor>,
    app: axum::Router,
    limits: HttpLimits,
) {
    let pool = Pool::new("HTTP connections", limits.max, limits.per_address);
    let handshakes = Arc::new(tokio::sync::Semaphore::new(crate::tls::MAX_HANDSHAKES));
    loop {
        let (tcp, peer) = match listener.accept().await {
            Ok(accepted) => accepted,
            Err(e) => {
                tracing::warn!("accepting an HTTP connection failed: {e}");
                tokio::time::sleep(Duration::from_millis(50)).await;
                continue;
            }
        };
        let ticket = match pool.admit(peer.ip()) {
            Ok(ticket) => ticket,
            Err(refusal) => {
                tracing::debug!("refused an HTTP connection from {peer}: {refusal}");
                if tls.is_none() {
                    refuse_now(tcp, &http_refusal(&refusal));
                }
                continue;
            }
        };
        let _ = tcp.set_nodelay(true);
        let app = app.clone();
        let tls = tls.clone();
        let handshakes = handshakes.clone();
        tokio::spawn(async move {
            let _ticket = ticket;
            match tls {
                Some(acceptor) => {
                    let Ok(permit) = handshakes.acquire_owned().await else { return };
                    let Some(stream) = crate::tls::handshake(&acceptor, tcp, peer).await else { return };
                    drop(permit);
                    serve_connection(stream, peer, app, limits.header_read).await;
                }
                None => serve_connection(tcp, peer, app, limits.header_read).await,
            }
        });
    }
}

async fn serve_connection<S>(stream: S, peer: SocketAddr, app: axum::Router, header_read: Duration)
where
    S: tokio::io::AsyncRead + tokio::io::AsyncWrite + Send + Unpin + 'static,
{
    let service = hyper::service::service_fn(move |mut request: hyper::Request<hyper::body::Incoming>| {
        use tower::ServiceExt as _;
        request.extensions_mut().insert(axum::extract::ConnectInfo(peer));
        app.clone().oneshot(request)
    });
    let io = hyper_util::rt::TokioIo::new(stream);
    let served = hyper::server::conn::http1::Builder::new()
        .timer(hyper_util::rt::TokioTimer::new())
        .header_read_timeout(header_read)
        .serve_connection(io, service)
        .with_upgrades()
        .await;
    if let Err(e) = served {
        tracing::debug!("http connection from {peer} ended: {e}");
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ip(text: &str) -> IpAddr {
        text.parse().unwrap_or(IpAddr::V4(std::net::Ipv4Addr::UNSPECIFIED))
    }

    #[test]
    fn peers_are_ipv4_addresses_or_ipv6_prefixes() {
        let cases = [
            ("127.0.0.2", "127.0.0.2"),
            ("::ffff:10.1.2.3", "10.1.2.3"),
            ("2001:db8:1:2:3:4:5:6", "2001:db8:1:2::/64"),
            ("2001:db8:1:2:ffff::1", "2001:db8:1:2::/64"),
            ("::1", "::/64"),
        ];
        for (address, key) in cases {
            assert_eq!(PeerKey::of(ip(address)).to_string(), key, "{address}");
        }
        assert_ne!(PeerKey::of(ip("2001:db8:1:2::1")), PeerKey::of(ip("2001:db8:1:3::1")));
    }

    /// One address hoarding takes its share and no more; the others still
    /// get in until the pool is full; then the newest is refused, and
    /// every place given back is reusable.
    #[test]
    fn a_pool_bounds_each_address_and_refuses_the_newest_when_full() {
        let pool = Pool::new("test connections", 6, 2);
        let hoarder = ip("127.0.0.2");
        let held: Vec<Ticket> = (0..2).filter_map(|_| pool.admit(hoarder).ok()).collect();
        assert_eq!(held.len(), 2);
        for _ in 0..100 {
            assert_eq!(
                pool.admit(hoarder).map(|_| ()),
                Err(Refusal::PerAddress { what: "test connections", max: 2, peer: PeerKey::of(hoarder) })
            );
        }
        let others: Vec<Ticket> = ["127.0.0.3", "127.0.0.4", "127.0.0.5", "127.0.0.6"]
            .iter()
            .filter_map(|a| pool.admit(ip(a)).ok())
            .collect();
        assert_eq!(others.len(), 4);
        assert_eq!(pool.admit(ip("127.0.0.7")).map(|_| ()), Err(Refusal::Full { what: "test connections", max: 6 }));
        assert_eq!((pool.open(), pool.open_from(hoarder)), (6, 2));
        drop(others);
        assert_eq!(pool.open(), 2);
        assert!(pool.admit(ip("127.0.0.7")).is_ok());
        drop(held);
        assert_eq!((pool.open(), pool.open_from(hoarder)), (0, 0));
        assert!(pool.admit(hoarder).is_ok());
    }

    /// Many threads admitting and dropping at once: no place is lost or
    /// counted twice, and no address ever holds more than its share.
    #[test]
    fn concurrent_admissions_keep_the_counts_exact() {
        let pool = Pool::new("test connections", 40, 3);
        let over = Arc::new(std::sync::atomic::AtomicBool::new(false));
        let threads: Vec<_> = (0..8)
            .map(|t| {
                let pool = pool.clone();
                let over = over.clone();
                std::thread::spawn(move || {
                    let mut held = Vec::new();
                    for i in 0..5000usize {
                        let peer = IpAddr::V4(std::net::Ipv4Addr::new(127, 0, 0, ((i + t) % 5) as u8 + 1));
                        if let Ok(ticket) = pool.admit(peer) {
                            held.push(ticket);
                        }
                        if pool.open_from(peer) > 3 || pool.open() > 40 {
                            over.store(true, std::sync::atomic::Ordering::Relaxed);
                        }
                        if i % 3 == 0 {
                            held.pop();
                        }
                        if held.len() > 4 {
                            held.remove(0);
                        }
                    }
                })
            })
            .collect();
        for thread in threads {
            assert!(thread.join().is_ok());
        }
        assert!(!over.load(std::sync::atomic::Ordering::Relaxed), "a bound was exceeded");
        assert_eq!(pool.open(), 0);
        assert!(pool.counts.lock().map(|c| c.per_peer.is_empty()).unwrap_or(false));
    }
    /// A portal-like app on a loopback port under `limits`, on paused
    /// tokio time: its address.
    async fn serving(limits: HttpLimits) -> SocketAddr {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.expect("a loopback port");
        let address = listener.local_addr().expect("its address");
        let app = axum::Router::new().route("/", axum::routing::get(|| async { "hello" }));
        tokio::spawn(serve_http(listener, None, app, limits));
        address
    }

    async fn read_all(stream: &mut tokio::net::TcpStream) -> String {
        use tokio::io::AsyncReadExt as _;
        let mut text = Vec::new();
        let _ = stream.read_to_end(&mut text).await;
        String::from_utf8_lossy(&text).into_owned()
    }

    /// A request whose headers are still incomplete after the header
    /// deadline (a byte a second, slow-loris) is closed; a connection that
    /// sends nothing at all too; one that sends its request in time is
    /// answered. Time is tokio's paused clock.
    #[tokio::test(start_paused = true)]
    async fn headers_must_arrive_within_the_deadline() {
        use tokio::io::AsyncWriteExt as _;
        let limits = HttpLimits { header_read: Duration::from_secs(5), per_address: 8, max: 16 };
        let address = serving(limits).await;
        let mut slow = tokio::net::TcpStream::connect(address).await.expect("connects");
        let mut silent = tokio::net::TcpStream::connect(address).await.expect("connects");
        let _ = slow.write_all(b"GET / HTTP/1.1\r\nHost: x\r\nX-Slow: ").await;
        let started = tokio::time::Instant::now();
        let mut closed_at = None;
        for _ in 0..20 {
            tokio::time::sleep(Duration::from_secs(1)).await;
            if slow.write_all(b"x").await.is_err() {
                closed_at = Some(started.elapsed());
                break;
            }
        }
        let closed_at = closed_at.expect("the slow request is never cut off");
        assert!(closed_at >= Duration::from_secs(5) && closed_at <= Duration::from_secs(7), "{closed_at:?}");
        assert!(read_all(&mut silent).await.is_empty());
        let mut prompt = tokio::net::TcpStream::connect(address).await.expect("connects");
        let _ = prompt.write_all(b"GET / HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n").await;
        let answer = read_all(&mut prompt).await;
        assert!(answer.starts_with("HTTP/1.1 200 OK") && answer.ends_with("hello"), "{answer}");
    }

    /// One address holding its share of connections gets a 503 for the
    /// next one, which says why; the share comes back when one closes.
    #[tokio::test(start_paused = true)]
    async fn an_address_past_its_share_is_refused_with_a_reason() {
        use tokio::io::AsyncWriteExt as _;
        let limits = HttpLimits { header_read: Duration::from_secs(60), per_address: 3, max: 16 };
        let address = serving(limits).await;
        let mut held = Vec::new();
        for _ in 0..3 {
            held.push(tokio::net::TcpStream::connect(address).await.expect("connects"));
        }
        // The server has taken them in before the next one arrives.
        tokio::time::sleep(Duration::from_millis(10)).await;
        let mut refused = tokio::net::TcpStream::connect(address).await.expect("connects");
        let answer = read_all(&mut refused).await;
        assert!(answer.starts_with("HTTP/1.1 503 Service Unavailable\r\n"), "{answer}");
        assert!(answer.ends_with("HTTP connections: 3 are open from 127.0.0.1 already\n"), "{answer}");
        drop(held.pop());
        tokio::time::sleep(Duration::from_millis(10)).await;
        let mut next = tokio::net::TcpStream::connect(address).await.expect("connects");
        let _ = next.write_all(b"GET / HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n").await;
        assert!(read_all(&mut next).await.starts_with("HTTP/1.1 200 OK"));
    }
}
