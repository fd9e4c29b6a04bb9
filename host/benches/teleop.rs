#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic)]
//! Network command latency (a bench binary): an operator's `CMD` line written
//! to the TCP socket, through the session, the control loop, the delay buffer
//! (set to 0), the arbiter, the serial link and its I/O thread, until the
//! motor bytes are read at the far end of a real PTY. p50 and p99. The host
//! runs in this process (`subsume::run`), exactly as the binary runs it.
//!
//! Run: `cargo bench --bench teleop` (BENCHMARKS.md records the figures).

use std::io::{BufRead, BufReader, Read, Write};
use std::net::{TcpListener, TcpStream};
use std::time::{Duration, Instant};

use serialport::{SerialPort, TTYPort};
use subsume::run::RunOptions;
use subsume::runtime::control_loop::Shutdown;

fn percentile(sorted: &[u64], p: f64) -> u64 {
    sorted[((sorted.len() - 1) as f64 * p).round() as usize]
}

fn main() {
    let (mut master, slave) = TTYPort::pair().unwrap();
    master.set_timeout(Duration::from_secs(2)).unwrap();
    let port = TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("operators"), "bench bench-token-0123456789\n").unwrap();
    let robot = format!(
        r#"<robot name="bench">
  <platform name="network">
    <component name="teleop" source="builtin:teleop" rate="1" timeout="10s">
      <param name="listen" value="127.0.0.1:{port}"/>
      <param name="operators" value="operators"/>
      <param name="delay" value="0"/>
      <param name="horizon" value="10"/>
    </component>
  </platform>
  <platform name="control">
    <component name="arbiter" source="builtin:arbiter" rate="1"/>
    <component name="motors" source="builtin:serial" rate="1">
      <param name="device" value="{}"/>
      <param name="min-interval" value="0.001"/>
      <param name="watchdog" value="10"/>
      <param name="refresh" value="10"/>
    </component>
    <connect from="teleop.cmd" to="arbiter.commands"/>
    <component name="envelope" source="builtin:envelope" rate="20">
      <param name="max-speed" value="10"/><param name="max-reverse" value="10"/><param name="max-turn" value="20"/>
      <param name="max-accel" value="100"/><param name="max-turn-accel" value="100"/>
    </component>
    <connect from="arbiter.cmd" to="envelope.cmd"/>
    <connect from="envelope.cmd" to="motors.cmd"/>
  </platform>
</robot>"#,
        slave.name().unwrap()
    );
    std::fs::write(dir.path().join("robot.xml"), robot).unwrap();
    let shutdown = Shutdown::new();
    let options = RunOptions {
        config_path: dir.path().join("robot.xml"),
        duration: None,
        cache_dir: None,
        overrides: vec![],
        portal: None,
        stall_limit: subsume::runtime::stall::DEFAULT_STALL_LIMIT,
        fault_injection: None,
        tls: Default::default(),
        pace: None,
        record: None,
        control: Default::default(),
        verdict: None,
        criteria: None,
        task: None,
        perturb: None,
    };
    let host_shutdown = shutdown.clone();
    let host =
        std::thread::spawn(move || subsume::run::run(&options, host_shutdown).map(|_| ()).map_err(|e| e.to_string()));

    let stream = (0..200).find_map(|_| {
        TcpStream::connect(("127.0.0.1", port)).ok().or_else(|| {
            std::thread::sleep(Duration::from_millis(20));
            None
        })
    });
    let Some(stream) = stream else {
        let why = if host.is_finished() { format!("{:?}", host.join()) } else { "it is still starting".into() };
        panic!("the host never listened: {why}");
    };
    stream.set_nodelay(true).unwrap();
    let mut writer = stream.try_clone().unwrap();
    let mut reader = BufReader::new(stream);
    let mut line = String::new();
    let mut expect = |reader: &mut BufReader<TcpStream>, writer: &mut TcpStream, prefix: &str| loop {
        line.clear();
        reader.read_line(&mut line).unwrap();
        if let Some(nonce) = line.trim().strip_prefix("PING ") {
            writer.write_all(format!("PONG {nonce}\n").as_bytes()).unwrap();
        } else if line.starts_with(prefix) {
            break;
        }
    };
    expect(&mut reader, &mut writer, "HELLO");
    writer.write_all(b"AUTH bench bench-token-0123456789\n").unwrap();
    expect(&mut reader, &mut writer, "RTT");
    writer.write_all(b"MODE direct\n").unwrap();
    expect(&mut reader, &mut writer, "MODE direct");

    let samples = 2000;
    let warmup = 200;
    let started = Instant::now();
    let mut times = Vec::with_capacity(samples);
    let mut buffer = [0u8; 128];
    for seq in 1..=(samples + warmup) as u64 {
        let speed = if seq % 2 == 0 { "0.1" } else { "0.2" };
        let command = format!("CMD {seq} {} VEL {speed} 0\n", started.elapsed().as_millis());
        let start = Instant::now();
        writer.write_all(command.as_bytes()).unwrap();
        let mut got = 0;
        while got == 0 || buffer[got - 1] != b'\n' {
            got += master.read(&mut buffer[got..]).unwrap();
        }
        if seq > warmup as u64 {
            times.push(start.elapsed().as_nanos() as u64);
        }
        // Space the commands like a real operator would (and keep the
        // delay buffer's transit estimate honest).
        std::thread::sleep(Duration::from_millis(2));
    }
    times.sort_unstable();
    println!(
        "tcp CMD written -> motor bytes read at the far end of the pty (delay buffer 0): p50 {:.1} us   p99 {:.1} us   ({samples} samples)",
        percentile(&times, 0.50) as f64 / 1e3,
        percentile(&times, 0.99) as f64 / 1e3
    );
    writer.write_all(b"QUIT\n").unwrap();
    shutdown.request();
    host.join().unwrap().unwrap();
}
