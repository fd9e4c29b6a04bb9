#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic)]
//! Motion-path benchmark (a bench binary): from the arbiter deciding on a new
//! command to its bytes arriving at the far end of a real pseudo-terminal,
//! through the serial link's rate limit (set to let everything through), the
//! ASCII translator and the link's I/O thread. p50 and p99.
//!
//! Run: `cargo bench --bench motion` (BENCHMARKS.md records the figures).

use std::io::Read;
use std::path::PathBuf;
use std::time::{Duration, Instant};

use serialport::{SerialPort, TTYPort};
use subsume::arbiter::{ArbiterComponent, Source};
use subsume::contract::Value;
use subsume::robot::protocol::Profile;
use subsume::robot::serial::{LinkSettings, SerialLink};
use subsume::robot::translator::{DriveGeometry, ProfileTranslator};
use subsume::runtime::Component;
use subsume::runtime::PriorityCell;

fn percentile(sorted: &[u64], p: f64) -> u64 {
    sorted[((sorted.len() - 1) as f64 * p).round() as usize]
}

fn main() {
    let (mut master, slave) = TTYPort::pair().unwrap();
    master.set_timeout(Duration::from_secs(1)).unwrap();
    let settings = LinkSettings {
        device: PathBuf::from(slave.name().unwrap()),
        baud: 115_200,
        min_interval_ns: 1,
        watchdog_ns: u64::MAX / 2,
        refresh_ns: u64::MAX / 2,
    };
    let translator = ProfileTranslator::new(Profile::Ascii, DriveGeometry { wheel_base: 0.3, max_wheel_speed: 1.0 });
    let mut link = SerialLink::start("motors", settings, Box::new(translator)).unwrap();
    while !link.status().connected {
        std::thread::sleep(Duration::from_millis(1));
    }
    let source = Source {
        component: 7,
        name: "planner".into(),
        priority: PriorityCell::new(1),
        timeout_ns: u64::MAX / 2,
        operator: false,
    };
    let mut arbiter = ArbiterComponent::new("arbiter", vec![source]);

    let samples = 3000;
    let warmup = 300;
    let mut times = Vec::with_capacity(samples);
    let mut decided = Vec::new();
    let mut buffer = [0u8; 64];
    for i in 0..(samples + warmup) {
        // Alternate speeds so every command changes the arbiter's output.
        let command = Value::Command(if i % 2 == 0 { "VEL 0.1 0" } else { "VEL 0.2 0" }.into());
        let now_ns = i as u64 * 1_000_000;
        let start = Instant::now();
        decided.clear();
        arbiter.on_input(0, &command, 7, now_ns, &mut decided).unwrap();
        let (_, decision) = decided.pop().expect("the arbiter decided");
        link.on_input(0, &decision, 0, now_ns, &mut Vec::new()).unwrap();
        let mut line = 0;
        while line == 0 || buffer[line - 1] != b'\n' {
            line += master.read(&mut buffer[line..]).unwrap();
        }
        if i >= warmup {
            times.push(start.elapsed().as_nanos() as u64);
        }
    }
    times.sort_unstable();
    println!(
        "arbiter decision -> bytes read at the far end of the pty: p50 {:.1} us   p99 {:.1} us   ({samples} samples)",
        percentile(&times, 0.50) as f64 / 1e3,
        percentile(&times, 0.99) as f64 / 1e3
    );
}
