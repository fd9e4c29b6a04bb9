//! A peer that tries to lock everyone else out of a listener: from one
//! loopback source address it holds as many connections open as it can,
//! doing nothing with them (or trickling a request's headers, slow-loris),
//! and beside them reconnects in a loop as fast as it can. Bounded in time
//! (it stops when told, or after [`FLOOD_LIMIT`] whatever happens) and in
//! sockets.

#![allow(dead_code, clippy::panic, clippy::unwrap_used, clippy::expect_used)]

use std::collections::BTreeSet;
use std::io::{Read, Write};
use std::net::{IpAddr, SocketAddr, TcpStream};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

/// The longest a flood runs, even if the test that started it never stops it.
pub const FLOOD_LIMIT: Duration = Duration::from_secs(120);
/// Most distinct first lines a flood keeps of what it was told.
const MAX_HEARD: usize = 50;

/// A TCP connection to `to` from the loopback address `from` (any port).
pub fn connect_from(from: IpAddr, to: SocketAddr) -> std::io::Result<TcpStream> {
    let socket = socket2::Socket::new(socket2::Domain::for_address(to), socket2::Type::STREAM, None)?;
    socket.bind(&SocketAddr::new(from, 0).into())?;
    socket.connect_timeout(&to.into(), Duration::from_secs(2))?;
    Ok(socket.into())
}

/// What a flood did and heard.
#[derive(Debug, Default)]
pub struct FloodCounts {
    /// Connections it opened, idle ones and the loop's.
    pub connects: u64,
    /// Connections that could not be opened.
    pub failed_connects: u64,
    /// The first line of each distinct thing the host said to it.
    pub heard: BTreeSet<String>,
}

/// A running flood; [`Flood::stop`] ends it and says what it did.
pub struct Flood {
    stop: Arc<AtomicBool>,
    threads: Vec<std::thread::JoinHandle<FloodCounts>>,
}

fn hear(heard: &mut BTreeSet<String>, bytes: &[u8]) {
    let text = String::from_utf8_lossy(bytes);
    let first = text.lines().next().unwrap_or("").chars().take(160).collect::<String>();
    if heard.len() < MAX_HEARD {
        heard.insert(first);
    }
}

impl Flood {
    /// From `from` to `to`: `idle` connections held open (each reopened
    /// when the host closes it) that send `prefix` and then one byte of
    /// `trickle` a second, if given; and a loop that connects, sends
    /// `prefix`, and closes at once (a reset), as fast as it can.
    pub fn start(from: IpAddr, to: SocketAddr, idle: usize, prefix: &'static [u8], trickle: Option<u8>) -> Flood {
        let stop = Arc::new(AtomicBool::new(false));
        let started = Instant::now();
        let going = {
            let stop = stop.clone();
            move || !stop.load(Ordering::Relaxed) && started.elapsed() < FLOOD_LIMIT
        };
        let holder = {
            let going = going.clone();
            std::thread::spawn(move || {
                let mut counts = FloodCounts::default();
                let open = |counts: &mut FloodCounts| -> Option<TcpStream> {
                    counts.connects += 1;
                    let mut stream = connect_from(from, to).map_err(|_| counts.failed_connects += 1).ok()?;
                    let _ = stream.write_all(prefix);
                    stream.set_nonblocking(true).ok()?;
                    Some(stream)
                };
                let mut held: Vec<Option<TcpStream>> = (0..idle).map(|_| open(&mut counts)).collect();
                let mut last_trickle = Instant::now();
                let mut buffer = [0u8; 512];
                while going() {
                    let trickle_now = trickle.is_some() && last_trickle.elapsed() >= Duration::from_secs(1);
                    if trickle_now {
                        last_trickle = Instant::now();
                    }
                    for slot in &mut held {
                        let closed = match slot {
                            None => true,
                            Some(stream) => {
                                if let (true, Some(byte)) = (trickle_now, trickle) {
                                    let _ = stream.write(&[byte]);
                                }
                                match stream.read(&mut buffer) {
                                    Ok(0) => true,
                                    Ok(n) => {
                                        hear(&mut counts.heard, &buffer[..n]);
                                        false
                                    }
                                    Err(e) => e.kind() != std::io::ErrorKind::WouldBlock,
                                }
                            }
                        };
                        if closed && going() {
                            *slot = open(&mut counts);
                        }
                    }
                    std::thread::sleep(Duration::from_millis(10));
                }
                counts
            })
        };
        let looper = std::thread::spawn(move || {
            let mut counts = FloodCounts::default();
            while going() {
                counts.connects += 1;
                match connect_from(from, to) {
                    Ok(mut stream) => {
                        let _ = stream.write_all(prefix);
                        // Close with a reset: no TIME_WAIT, so the loop
                        // never runs out of ports.
                        let _ = socket2::SockRef::from(&stream).set_linger(Some(Duration::ZERO));
                    }
                    Err(_) => counts.failed_connects += 1,
                }
            }
            counts
        });
        Flood { stop, threads: vec![holder, looper] }
    }

    /// Stops the flood; what it did in all.
    pub fn stop(self) -> FloodCounts {
        self.stop.store(true, Ordering::Relaxed);
        let mut all = FloodCounts::default();
        for thread in self.threads {
            let counts = thread.join().unwrap_or_else(|_| panic!("a flood thread panicked"));
            all.connects += counts.connects;
            all.failed_connects += counts.failed_connects;
            all.heard.extend(counts.heard);
        }
        all
    }
}
