#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic)]
//! The remote hop (a bench binary): host A's port -> Zenoh -> host B's
//! port over loopback, against Zenoh's own floor, a bare `put` -> callback
//! subscriber of the same payload, in the same run and interleaved sample
//! by sample so load from elsewhere hits both alike.
//!
//! The remote hop is the bridge's whole path: the value encoded on the
//! control loop, put by A's session (`bridge::link::Outlet`: from the loop
//! itself when the session's congested puts give up at once, as with the
//! host's defaults, else through its sender thread); on B, decoded and checked in Zenoh's callback,
//! queued, the loop woken through its `Waker` and the value drained as a
//! `poll` does (`bridge::link::Inlet`). Two sessions in one process, A
//! listening and B connected over TCP loopback, as two hosts would be.
//!
//! A third route, measured in the same run, is the same bridge on a pair
//! of sessions opened from a config file that keeps Zenoh's default wait
//! before a congested put drops (1 ms), so every message goes through the
//! outlet's sender thread: what the loop's own put saves.
//!
//! Run: `cargo bench --bench zenoh` (BENCHMARKS.md records the figures).

use std::sync::Arc;
use std::sync::mpsc;
use std::time::{Duration, Instant};

use subsume::bridge::link::{Inlet, Outlet};
use subsume::bridge::session::{self, BridgeStats, SessionSettings};
use subsume::bridge::wire;
use subsume::contract::{Value, ValueKind};
use subsume::runtime::control_loop::Shutdown;
use zenoh::Wait;

const SAMPLES: usize = 2000;

fn percentile(sorted: &[u64], p: f64) -> u64 {
    sorted[((sorted.len() - 1) as f64 * p).round() as usize]
}

/// A pair of sessions, A listening and B connected to it over TCP
/// loopback; with `config`, both start from that Zenoh config file.
fn pair(config: Option<&std::path::Path>) -> (Arc<session::Shared>, Arc<session::Shared>) {
    let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
    let endpoint = format!("tcp/127.0.0.1:{port}");
    let config = config.map(std::path::Path::to_path_buf);
    let a = session::session(&SessionSettings {
        connect: vec![],
        listen: vec![endpoint.clone()],
        config: config.clone(),
        max_message_bytes: None,
    })
    .unwrap();
    let b =
        session::session(&SessionSettings { connect: vec![endpoint], listen: vec![], config, max_message_bytes: None })
            .unwrap();
    (a, b)
}

/// The bridge's route between a pair: an `Outlet` on A, an `Inlet` on B
/// woken like the control loop.
struct Route {
    outlet: Outlet,
    inlet: Inlet<Value>,
    signals: Shutdown,
}

impl Route {
    fn new(a: &Arc<session::Shared>, b: &Arc<session::Shared>, key: &str) -> Route {
        let outlet = Outlet::new(a.clone(), key.into(), Arc::new(BridgeStats::default()), None).unwrap();
        let signals = Shutdown::new();
        let inlet: Inlet<Value> =
            Inlet::new(b.clone(), key.into(), Arc::new(BridgeStats::default()), signals.waker(), |bytes, _| {
                wire::decode_as(bytes, ValueKind::Vector).map_err(|e| e.to_string())
            })
            .unwrap();
        Route { outlet, inlet, signals }
    }

    /// One value across, as a control loop sends and then polls: ns.
    fn hop(&self, value: &Value) -> u64 {
        let start = Instant::now();
        self.outlet.send(wire::encode(value));
        let got = loop {
            self.signals.wait(Duration::from_secs(1));
            if let Some(v) = self.inlet.drain().next() {
                break v;
            }
            assert!(start.elapsed() < Duration::from_secs(5), "the hop lost a value");
        };
        let ns = start.elapsed().as_nanos() as u64;
        assert_eq!(&got, value);
        ns
    }
}

fn main() {
    let (a, b) = pair(None);
    assert!(a.loop_puts, "the host's default session lets the loop put");
    // Zenoh's own default wait before a congested put drops (1 ms): the
    // outlet hands every message to its sender thread, as before.
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("zenoh.json5");
    std::fs::write(&file, "{ mode: \"peer\", scouting: { multicast: { enabled: false } } }").unwrap();
    let (ta, tb) = pair(Some(&file));
    assert!(!ta.loop_puts, "a config file without the setting keeps Zenoh's wait");
    let value = Value::Vector(vec![1.25; 9]);
    let payload = wire::encode(&value);

    let direct = Route::new(&a, &b, "bench/hop");
    let threaded = Route::new(&ta, &tb, "bench/hop-thread");

    // The floor: a bare publisher and a callback subscriber.
    let publisher = a.session.declare_publisher("bench/bare").wait().unwrap();
    let (tx, rx) = mpsc::sync_channel::<Vec<u8>>(64);
    let _subscriber = b
        .session
        .declare_subscriber("bench/bare")
        .callback(move |sample| {
            let _ = tx.try_send(sample.payload().to_bytes().into_owned());
        })
        .wait()
        .unwrap();

    // Wait for the peers to meet and every route to carry.
    let deadline = Instant::now() + Duration::from_secs(20);
    loop {
        assert!(Instant::now() < deadline, "the sessions never met");
        direct.outlet.send(payload.clone());
        threaded.outlet.send(payload.clone());
        publisher.put(payload.clone()).wait().unwrap();
        std::thread::sleep(Duration::from_millis(50));
        let hop = direct.inlet.drain().count() > 0;
        let thread_hop = threaded.inlet.drain().count() > 0;
        let bare = rx.try_iter().count() > 0;
        if hop && thread_hop && bare {
            break;
        }
    }

    let mut hop = Vec::with_capacity(SAMPLES);
    let mut thread_hop = Vec::with_capacity(SAMPLES);
    let mut bare = Vec::with_capacity(SAMPLES);
    for _ in 0..SAMPLES {
        hop.push(direct.hop(&value));
        std::thread::sleep(Duration::from_millis(1));
        thread_hop.push(threaded.hop(&value));
        std::thread::sleep(Duration::from_millis(1));
        // Floor.
        let start = Instant::now();
        publisher.put(payload.clone()).wait().unwrap();
        let bytes = rx.recv_timeout(Duration::from_secs(5)).expect("the bare route lost a value");
        bare.push(start.elapsed().as_nanos() as u64);
        assert_eq!(bytes, payload);
        std::thread::sleep(Duration::from_millis(1));
    }
    hop.sort_unstable();
    thread_hop.sort_unstable();
    bare.sort_unstable();
    let us = |ns: u64| ns as f64 / 1000.0;
    let (h50, h99, t50, t99, b50, b99) = (
        percentile(&hop, 0.5),
        percentile(&hop, 0.99),
        percentile(&thread_hop, 0.5),
        percentile(&thread_hop, 0.99),
        percentile(&bare, 0.5),
        percentile(&bare, 0.99),
    );
    println!(
        "zenoh/remote-hop   p50 {:8.1} us  p99 {:8.1} us  ({SAMPLES} samples, {} bytes; the loop puts)",
        us(h50),
        us(h99),
        payload.len()
    );
    println!(
        "zenoh/thread-hop   p50 {:8.1} us  p99 {:8.1} us  (Zenoh's default wait: the sender thread puts)",
        us(t50),
        us(t99)
    );
    println!("zenoh/bare-put-sub p50 {:8.1} us  p99 {:8.1} us", us(b50), us(b99));
    println!("ratio remote-hop / bare: p50 {:.2}x  p99 {:.2}x", h50 as f64 / b50 as f64, h99 as f64 / b99 as f64);
    println!("ratio thread-hop / bare: p50 {:.2}x  p99 {:.2}x", t50 as f64 / b50 as f64, t99 as f64 / b99 as f64);
}
