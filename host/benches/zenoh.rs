#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic)]
//! The remote hop (a bench binary): host A's port -> Zenoh -> host B's
//! port over loopback, against Zenoh's own floor, a bare `put` -> callback
//! subscriber of the same payload, in the same run and interleaved sample
//! by sample so load from elsewhere hits both alike.
//!
//! The remote hop is the bridge's whole path: the value encoded on the
//! control loop, queued to the sender thread (`bridge::link::Outlet`),
//! put by A's session; on B, decoded and checked in Zenoh's callback,
//! queued, the loop woken through its `Waker` and the value drained as a
//! `poll` does (`bridge::link::Inlet`). Two sessions in one process, A
//! listening and B connected over TCP loopback, as two hosts would be.
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

fn main() {
    let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
    let endpoint = format!("tcp/127.0.0.1:{port}");
    let a =
        session::session(&SessionSettings { connect: vec![], listen: vec![endpoint.clone()], config: None }).unwrap();
    let b = session::session(&SessionSettings { connect: vec![endpoint], listen: vec![], config: None }).unwrap();
    let value = Value::Vector(vec![1.25; 9]);
    let payload = wire::encode(&value);

    // The bridge: Outlet on A, Inlet on B woken like the control loop.
    let outlet = Outlet::new(a.clone(), "bench/hop".into(), Arc::new(BridgeStats::default()), None).unwrap();
    let loop_signals = Shutdown::new();
    let inlet: Inlet<Value> = Inlet::new(
        b.clone(),
        "bench/hop".into(),
        Arc::new(BridgeStats::default()),
        loop_signals.waker(),
        |bytes, _| wire::decode_as(bytes, ValueKind::Vector).map_err(|e| e.to_string()),
    )
    .unwrap();

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

    // Wait for the peers to meet and both routes to carry.
    let deadline = Instant::now() + Duration::from_secs(20);
    loop {
        assert!(Instant::now() < deadline, "the sessions never met");
        outlet.send(payload.clone());
        publisher.put(payload.clone()).wait().unwrap();
        std::thread::sleep(Duration::from_millis(50));
        let hop = inlet.drain().count() > 0;
        let bare = rx.try_iter().count() > 0;
        if hop && bare {
            break;
        }
    }

    let mut hop = Vec::with_capacity(SAMPLES);
    let mut bare = Vec::with_capacity(SAMPLES);
    for _ in 0..SAMPLES {
        // Remote hop.
        let start = Instant::now();
        outlet.send(wire::encode(&value));
        let got = loop {
            loop_signals.wait(Duration::from_secs(1));
            if let Some(v) = inlet.drain().next() {
                break v;
            }
            assert!(start.elapsed() < Duration::from_secs(5), "the hop lost a value");
        };
        hop.push(start.elapsed().as_nanos() as u64);
        assert_eq!(got, value);
        // Floor.
        let start = Instant::now();
        publisher.put(payload.clone()).wait().unwrap();
        let bytes = rx.recv_timeout(Duration::from_secs(5)).expect("the bare route lost a value");
        bare.push(start.elapsed().as_nanos() as u64);
        assert_eq!(bytes, payload);
        std::thread::sleep(Duration::from_millis(1));
    }
    hop.sort_unstable();
    bare.sort_unstable();
    let us = |ns: u64| ns as f64 / 1000.0;
    let (h50, h99, b50, b99) =
        (percentile(&hop, 0.5), percentile(&hop, 0.99), percentile(&bare, 0.5), percentile(&bare, 0.99));
    println!(
        "zenoh/remote-hop   p50 {:8.1} us  p99 {:8.1} us  ({SAMPLES} samples, {} bytes)",
        us(h50),
        us(h99),
        payload.len()
    );
    println!("zenoh/bare-put-sub p50 {:8.1} us  p99 {:8.1} us", us(b50), us(b99));
    println!("ratio remote-hop / bare: p50 {:.2}x  p99 {:.2}x", h50 as f64 / b50 as f64, h99 as f64 / b99 as f64);
}
