#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic)]
//! Safety-envelope benchmark (a bench binary), three parts:
//!
//! 1. cost per command: `Envelope::decide` on a 9-ray scan (straight and
//!    on an arc), and the whole `builtin:envelope` call (parse, decide,
//!    format), median of batches;
//! 2. a range reading inside the stop zone to the STOP bytes at the far end
//!    of a real pseudo-terminal (the envelope's review, the serial link's
//!    rate limit set to let everything through, the ASCII translator, the
//!    link's I/O thread): p50 and p99;
//! 3. a sweep of 20 runs in the simulator (the real physics and world,
//!    simulated time, 60 s each): hostile drivers with random priorities,
//!    speeds (up to twice the robot's fastest) and turns, changing their
//!    minds at random, go through the real arbiter and envelope (the
//!    demo's settings); collisions must be 0; the closest approach is
//!    measured by a twin body with 64 rays all round that follows the same
//!    wheel commands.
//!
//! Run: `cargo bench --bench envelope` (BENCHMARKS.md records the figures).

use std::io::Read;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use serialport::{SerialPort, TTYPort};
use subsume::arbiter::{ArbiterComponent, Source};
use subsume::contract::Value;
use subsume::contract::control::ControlCommand;
use subsume::envelope::logic::{Envelope, Settings};
use subsume::envelope::{EnvelopeComponent, INPUT_CMD, INPUT_POSE, INPUT_RANGES};
use subsume::robot::protocol::Profile;
use subsume::robot::serial::{LinkSettings, SerialLink};
use subsume::robot::translator::{DriveGeometry, ProfileTranslator};
use subsume::runtime::{Component, PriorityCell};
use subsume::sim::physics::{Body, Simulation};

fn percentile(sorted: &[u64], p: f64) -> u64 {
    sorted[((sorted.len() - 1) as f64 * p).round() as usize]
}

/// The demo's envelope (config/demo.xml).
fn demo_settings() -> Settings {
    Settings {
        max_speed: 0.5,
        max_reverse: 0.1,
        max_turn: 2.0,
        max_accel: 1.0,
        max_turn_accel: 6.0,
        radius: 0.18,
        stop_distance: 0.1,
        slow_distance: 0.4,
        ttc_s: 1.0,
        fov: std::f64::consts::PI,
        stale_ns: 500_000_000,
        geofence: vec![[0.3, 0.3], [9.7, 0.3], [9.7, 7.7], [0.3, 7.7]],
        watch_ranges: true,
        watch_pose: true,
        watch_camera: false,
        camera_stale_ns: 1_000_000_000,
    }
}

/// A small deterministic generator (xorshift64*): the sweep is repeatable.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> f64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        (self.0.wrapping_mul(0x2545_F491_4F6C_DD1D) >> 11) as f64 / (1u64 << 53) as f64
    }
    fn range(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * self.next()
    }
}

fn cost_per_command() {
    let scan = [1.2, 0.9, 0.8, 0.75, 0.7, 0.75, 0.8, 0.9, 1.2];
    let batch = 20_000u64;
    let median = |f: &mut dyn FnMut(u64)| {
        let mut per: Vec<u64> = (0..15)
            .map(|b| {
                let start = Instant::now();
                for i in 0..batch {
                    f(b * batch + i);
                }
                start.elapsed().as_nanos() as u64 / batch
            })
            .collect();
        per.sort_unstable();
        per[per.len() / 2]
    };
    let mut envelope = Envelope::new(demo_settings());
    envelope.ranges(&scan, 0);
    envelope.pose(&[5.0, 4.0, 0.0], 0);
    let straight = median(&mut |i| {
        let v = if i % 2 == 0 { 0.3 } else { 0.31 };
        std::hint::black_box(envelope.decide(ControlCommand::Vel { linear: v, angular: 0.0 }, 1_000 + i));
    });
    let arc = median(&mut |i| {
        let v = if i % 2 == 0 { 0.3 } else { 0.31 };
        std::hint::black_box(envelope.decide(ControlCommand::Vel { linear: v, angular: 0.8 }, 1_000 + i));
    });
    // Obstacles within reach on every ray: the arc is marched in full.
    let mut near = Envelope::new(demo_settings());
    near.ranges(&[0.5; 9], 0);
    near.pose(&[5.0, 4.0, 0.0], 0);
    let arc_near = median(&mut |i| {
        let v = if i % 2 == 0 { 0.3 } else { 0.31 };
        std::hint::black_box(near.decide(ControlCommand::Vel { linear: v, angular: 0.8 }, 1_000 + i));
    });
    let scan_cost = median(&mut |i| envelope.ranges(std::hint::black_box(&scan), i));
    let mut component = EnvelopeComponent::new("envelope", demo_settings());
    let mut out = Vec::new();
    component.on_input(INPUT_RANGES, &Value::Vector(scan.to_vec()), 0, 0, &mut out).unwrap();
    component.on_input(INPUT_POSE, &Value::Vector(vec![5.0, 4.0, 0.0]), 0, 0, &mut out).unwrap();
    let commands = [Value::Command("VEL 0.3 0".into()), Value::Command("VEL 0.31 0.8".into())];
    let call = median(&mut |i| {
        out.clear();
        component.on_input(INPUT_CMD, &commands[(i % 2) as usize], 0, 1_000 + i, &mut out).unwrap();
    });
    println!("envelope decide, straight (9 rays + gap points): {straight} ns/command");
    println!("envelope decide, arc (march along the arc):      {arc} ns/command");
    println!("envelope decide, arc, every ray 0.5 m (marched) : {arc_near} ns/command");
    println!("envelope scan of 9 rays (points, gaps):          {scan_cost} ns/scan");
    println!("builtin:envelope call (parse, decide, format):   {call} ns/command");
}

fn stop_zone_to_pty() {
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
    let mut settings = demo_settings();
    settings.watch_pose = false;
    settings.geofence.clear();
    settings.max_accel = 100.0;
    let mut envelope = EnvelopeComponent::new("envelope", settings);
    let clear = Value::Vector(vec![4.0; 9]);
    let blocked = Value::Vector(vec![4.0, 4.0, 4.0, 4.0, 0.25, 4.0, 4.0, 4.0, 4.0]);
    let mut buffer = [0u8; 64];
    let mut read_line = |master: &mut TTYPort| {
        let mut line = 0;
        while line == 0 || buffer[line - 1] != b'\n' {
            line += master.read(&mut buffer[line..]).unwrap();
        }
        buffer[..line].to_vec()
    };
    let (samples, warmup) = (2000, 200);
    let mut times = Vec::with_capacity(samples);
    let mut out = Vec::new();
    for i in 0..(samples + warmup) {
        let now_ns = (i as u64 + 1) * 10_000_000;
        // Driving freely...
        out.clear();
        envelope.on_input(INPUT_RANGES, &clear, 0, now_ns, &mut out).unwrap();
        envelope.on_input(INPUT_CMD, &Value::Command("VEL 0.3 0".into()), 0, now_ns, &mut out).unwrap();
        for (_, value) in out.drain(..) {
            link.on_input(0, &value, 0, now_ns, &mut Vec::new()).unwrap();
            read_line(&mut master);
        }
        // ... until a reading inside the stop zone.
        let at = now_ns + 5_000_000;
        let start = Instant::now();
        envelope.on_input(INPUT_RANGES, &blocked, 0, at, &mut out).unwrap();
        let (_, stop) = out.pop().expect("the envelope stopped");
        link.on_input(0, &stop, 0, at, &mut Vec::new()).unwrap();
        let line = read_line(&mut master);
        if i >= warmup {
            times.push(start.elapsed().as_nanos() as u64);
        }
        assert!(line.starts_with(b"S"), "expected the STOP frame, got {:?}", String::from_utf8_lossy(&line));
    }
    times.sort_unstable();
    println!(
        "range reading in the stop zone -> STOP bytes at the far end of the pty: p50 {:.1} us   p99 {:.1} us   ({samples} samples)",
        percentile(&times, 0.50) as f64 / 1e3,
        percentile(&times, 0.99) as f64 / 1e3
    );
}

/// One run of the sweep; returns (collisions, closest approach m, distance m,
/// interventions).
fn hostile_run(world: &Path, seed: u64) -> (u64, f64, f64, u64) {
    let mut rng = Rng(seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1);
    let world = subsume::sim::world::load(world).unwrap();
    let geometry = DriveGeometry { wheel_base: 0.3, max_wheel_speed: 0.5 };
    let body = Body { radius: 0.18, geometry, rays: 9, fov: std::f64::consts::PI, max_range: 4.0 };
    let twin_body = Body { rays: 64, fov: std::f64::consts::TAU * 63.0 / 64.0, ..body };
    let mut sim = Simulation::new(world.clone(), body).unwrap();
    let mut twin = Simulation::new(world, twin_body).unwrap();
    // 1 to 3 hostile sources, random priorities.
    let drivers = 1 + (rng.next() * 3.0) as usize;
    let sources: Vec<Source> = (0..drivers)
        .map(|d| Source {
            component: 10 + d,
            name: format!("hostile{d}"),
            priority: PriorityCell::new((rng.range(-1000.0, 1000.0)) as i32),
            timeout_ns: 400_000_000,
            operator: false,
        })
        .collect();
    let mut arbiter = ArbiterComponent::new("arbiter", sources);
    let mut envelope = EnvelopeComponent::new("envelope", demo_settings());
    let mut plans: Vec<(f64, f64, u64)> = vec![(0.0, 0.0, 0); drivers];
    let (dt_ns, end_ns) = (50_000_000u64, 60_000_000_000u64);
    let mut closest = f64::INFINITY;
    let mut wheels = (0.0, 0.0);
    let mut now = 0;
    while now < end_ns {
        // Feedback, as the link would emit it.
        let mut out = Vec::new();
        let (x, y, h) = sim.pose();
        envelope.on_input(INPUT_RANGES, &Value::Vector(sim.ranges()), 0, now, &mut out).unwrap();
        envelope.on_input(INPUT_POSE, &Value::Vector(vec![x, y, h]), 0, now, &mut out).unwrap();
        // Each driver: a new random VEL now and then (up to twice the
        // robot's fastest, any turn, mostly forward).
        for (d, plan) in plans.iter_mut().enumerate() {
            if now >= plan.2 {
                *plan = (rng.range(-0.3, 1.0), rng.range(-3.0, 3.0), now + (rng.range(0.5, 6.0) * 1e9) as u64);
            }
            let text = format!("VEL {} {}", plan.0, plan.1);
            arbiter.on_input(0, &Value::Command(text.into()), 10 + d, now, &mut Vec::new()).ok();
        }
        let mut decided = Vec::new();
        arbiter.tick(now, &mut decided).unwrap();
        for (_, value) in decided {
            envelope.on_input(INPUT_CMD, &value, 0, now, &mut out).unwrap();
        }
        envelope.tick(now, &mut out).unwrap();
        if let Some((_, Value::Command(command))) = out.last() {
            wheels = match command.parsed().unwrap() {
                ControlCommand::Vel { linear, angular } => geometry.wheels(linear, angular),
                _ => (0.0, 0.0),
            };
        }
        sim.set_wheels(wheels.0, wheels.1);
        twin.set_wheels(wheels.0, wheels.1);
        let before = sim.status().collisions;
        sim.step(dt_ns as f64 / 1e9);
        twin.step(dt_ns as f64 / 1e9);
        if std::env::var_os("ENVELOPE_DEBUG").is_some() && sim.status().collisions > before {
            eprintln!(
                "collision at {:.2} s: pose {:?} wheels {wheels:?} out {:?} ranges {:?}",
                now as f64 / 1e9,
                sim.pose(),
                out.last(),
                sim.ranges()
            );
        }
        closest = closest.min(twin.ranges().into_iter().fold(f64::INFINITY, f64::min) - body.radius);
        now += dt_ns;
    }
    let status = sim.status();
    let report = envelope.report();
    (status.collisions, closest, status.distance_travelled_m, report.scaled + report.stopped)
}

fn hostile_sweep() {
    let world = Path::new(env!("CARGO_MANIFEST_DIR")).join("../config/worlds/demo.world");
    let mut worst = f64::INFINITY;
    let mut collisions = 0;
    let runs: u64 = std::env::var("SWEEP_RUNS").ok().and_then(|r| r.parse().ok()).unwrap_or(20);
    for run in 0..runs {
        let (c, closest, distance, interventions) = hostile_run(&world, run + 1);
        println!(
            "  run {run:2}: collisions {c}   closest approach {closest:.3} m   travelled {distance:.1} m   interventions {interventions}"
        );
        collisions += c;
        worst = worst.min(closest);
    }
    println!("hostile sweep ({runs} runs x 60 s simulated): collisions {collisions}   closest approach {worst:.3} m");
    assert_eq!(collisions, 0, "the envelope let a hostile driver collide");
}

fn main() {
    let only = std::env::args().skip(1).find(|a| !a.starts_with('-'));
    let wanted = |name: &str| only.as_deref().is_none_or(|o| name.contains(o));
    if wanted("cost") {
        cost_per_command();
    }
    if wanted("pty") {
        stop_zone_to_pty();
    }
    if wanted("sweep") {
        hostile_sweep();
    }
}
