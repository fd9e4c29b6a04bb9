#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic)]
//! Performance side by side (issue 15): one run, one table, every row beside
//! the engine's own floor.
//!
//! - (a) a native `Component` trait call (a relay that re-emits its input),
//!   through `Box<dyn Component>`: the floor without a sandbox; (a') the same
//!   native relay hopped through the graph: what the graph alone costs;
//! - (b) a bare wasmtime call of the relay guest's `on-input` (which emits
//!   once): wasmtime + wasmtime-wasi directly, the host's `bindgen!` output
//!   (`contract::bindings`), a trivial `emit` that keeps the value; no
//!   graph, no budget, no epochs, no pooling, no subsume store: the engine's
//!   limit; (b8) the same bare call to 8 instances in turn, as the chain
//!   (d) makes them: the engine's floor for a chain;
//! - (c) the subsume hop (`Graph::inject` -> relay guest -> route -> sink),
//!   for a scalar and a 100-element vector;
//! - (d) chain throughput: a chain of 8 relay guests, deliveries per second,
//!   and the time per delivery;
//! - (e) the same hop between two processes over a Unix socket: a value
//!   encoded, written, read and decoded by a second process (this bench
//!   re-executed), handed to a native relay there, and the relay's output sent
//!   back the same way; one way is half the round trip. This is what a
//!   process-isolated framework pays to cross its isolation boundary, without
//!   any of its own machinery. The Zenoh half: the same round trip as a
//!   Zenoh put on `peers/ping` and a put back on `peers/pong` between two
//!   peer sessions over TCP loopback (this process listens, the second one
//!   connects), values in subsume's own Zenoh wire form
//!   (`bridge::wire`), each side's subscriber a plain Zenoh FIFO channel.
//!
//! With `PEERS_ENGINE_SETTINGS=1`, the bare call is also measured on engines
//! with one wasmtime setting changed (epochs, pooling, signals-based traps,
//! copy-on-write memory init, lazy table init, concurrency support).
//!
//! Every row is measured in `PEERS_ROUNDS` interleaved rounds (default 3);
//! the table shows the median round. Ratios are against row (b) of the same
//! run; absolute times move between machines and with load.
//!
//! Run: `taskset -c 1 cargo bench --bench peers` (BENCHMARKS.md records the
//! figures).

#[path = "../../tests/all/support.rs"]
mod support;

use std::hint::black_box;
use std::io::{Read, Write};
use std::os::unix::net::{UnixListener, UnixStream};
use std::time::Instant;

use subsume::bridge::wire;
use subsume::config::Policy;
use subsume::contract::bindings;
use subsume::contract::{GuestValue, LogLevel, Value};
use subsume::runtime::{CallError, Component, Graph, Outbox, Vacant};
use subsume::sandbox::{GuestLimits, Sandbox};
use wasmtime::component::{HasSelf, Linker, ResourceTable};
use wasmtime::{Config, Engine, Store};
use wasmtime_wasi::{WasiCtx, WasiCtxBuilder, WasiCtxView, WasiView};

/// Environment variable that turns this binary into the far process of row (e).
const ECHO_SOCKET: &str = "PEERS_ECHO_SOCKET";
/// The same for the Zenoh half of row (e): the endpoint to connect to.
const ECHO_ZENOH: &str = "PEERS_ECHO_ZENOH";
/// Round trips measured per round of the Zenoh row (each one two puts
/// through Zenoh's runtime threads: slower than the socket).
const ZENOH_SAMPLES: usize = 20_000;
const SAMPLES: usize = 200_000;
const WARMUP: usize = 20_000;
/// Round trips measured per round of row (e) (each costs two context switches).
const SOCKET_SAMPLES: usize = 50_000;

// ---------------------------------------------------------------- helpers

fn percentile(sorted: &[u64], p: f64) -> u64 {
    sorted[((sorted.len() - 1) as f64 * p).round() as usize]
}

/// What one `Instant::now()` + `elapsed()` pair costs; subtracted from every
/// sample so the figures are the work, not the stopwatch.
fn timer_overhead() -> u64 {
    let mut times: Vec<u64> = (0..100_000)
        .map(|_| {
            let start = Instant::now();
            start.elapsed().as_nanos() as u64
        })
        .collect();
    times.sort_unstable();
    percentile(&times, 0.5)
}

/// Times `call` `SAMPLES` times after `WARMUP` untimed calls: (p50, p99) ns.
fn sample(overhead: u64, mut call: impl FnMut()) -> (u64, u64) {
    for _ in 0..WARMUP {
        call();
    }
    let mut times = Vec::with_capacity(SAMPLES);
    for _ in 0..SAMPLES {
        let start = Instant::now();
        call();
        times.push((start.elapsed().as_nanos() as u64).saturating_sub(overhead));
    }
    times.sort_unstable();
    (percentile(&times, 0.50), percentile(&times, 0.99))
}

fn vector() -> Value {
    Value::Vector((0..100).map(f64::from).collect())
}

// ------------------------------------------------------- (a) native relay

/// A native component that re-emits each input on the output of the same
/// index: what the relay guest does, without a sandbox.
struct NativeRelay;

impl Component for NativeRelay {
    fn on_input(&mut self, port: u32, value: &Value, _: usize, _: u64, out: &mut Outbox) -> Result<(), CallError> {
        out.push((port, value.clone()));
        Ok(())
    }
}

fn native_call(overhead: u64) -> (u64, u64) {
    let mut relay: Box<dyn Component> = Box::new(NativeRelay);
    let value = Value::Scalar(1.5);
    let mut out = Vec::with_capacity(4);
    sample(overhead, || {
        black_box(&mut relay).on_input(0, black_box(&value), 0, 0, &mut out).unwrap();
        out.clear();
    })
}

// --------------------------------------------------- (b) bare wasmtime call

/// The store data of the bare call: WASI with no capabilities and the one
/// value the guest emitted.
struct Bare {
    wasi: WasiCtx,
    table: ResourceTable,
    emitted: Option<(u32, GuestValue)>,
}

impl WasiView for Bare {
    fn ctx(&mut self) -> WasiCtxView<'_> {
        WasiCtxView { ctx: &mut self.wasi, table: &mut self.table }
    }
}

impl bindings::subsume::robot::types::Host for Bare {}

impl bindings::subsume::robot::host::Host for Bare {
    fn emit(&mut self, port: u32, value: GuestValue) -> wasmtime::Result<()> {
        self.emitted = Some((port, value));
        Ok(())
    }
    fn log(&mut self, _level: LogLevel, _message: String) -> wasmtime::Result<()> {
        Ok(())
    }
    fn now_ns(&mut self) -> wasmtime::Result<u64> {
        Ok(0)
    }
    fn report(&mut self, _message: String) -> wasmtime::Result<()> {
        Ok(())
    }
}

/// The relay guest instantiated on a plain engine: wasmtime's defaults but
/// for concurrency support, which the host turns off too (this build of
/// wasmtime has it compiled out anyway), so the row is the engine at its best.
struct BareRelay {
    store: Store<Bare>,
    instance: bindings::Component,
}

impl BareRelay {
    fn new(bytes: &[u8]) -> BareRelay {
        BareRelay::with(bytes, |_| {}).unwrap()
    }

    /// The same on an engine `tweak` changed (part 6 of the issue: what a
    /// wasmtime setting costs or saves the bare call). An engine the setting
    /// makes invalid is an error.
    fn with(bytes: &[u8], tweak: impl Fn(&mut Config)) -> Result<BareRelay, String> {
        let mut config = Config::new();
        config.wasm_component_model(true);
        config.concurrency_support(false);
        tweak(&mut config);
        let engine = Engine::new(&config).map_err(|e| format!("{e:#}"))?;
        let component = wasmtime::component::Component::new(&engine, bytes).unwrap();
        let mut linker = Linker::new(&engine);
        wasmtime_wasi::p2::add_to_linker_sync(&mut linker).unwrap();
        bindings::Component::add_to_linker::<Bare, HasSelf<Bare>>(&mut linker, |state| state).unwrap();
        let bare = Bare { wasi: WasiCtxBuilder::new().build(), table: ResourceTable::new(), emitted: None };
        let mut store = Store::new(&engine, bare);
        // Only read when the tweak turns epoch interruption on: never reached.
        store.set_epoch_deadline(1 << 40);
        let instance = bindings::Component::instantiate(&mut store, &component, &linker).unwrap();
        instance.call_init(&mut store, &[]).unwrap().unwrap();
        Ok(BareRelay { store, instance })
    }

    fn call(&mut self, value: &GuestValue) {
        self.instance.call_on_input(&mut self.store, 0, value).unwrap();
        let emitted = self.store.data_mut().emitted.take();
        assert!(matches!(emitted, Some((0, _))), "the relay guest did not emit");
        black_box(emitted);
    }
}

fn bare_call(relay: &mut BareRelay, overhead: u64) -> (u64, u64) {
    let value = GuestValue::Scalar(1.5);
    sample(overhead, || relay.call(&value))
}

/// The bare call to `relays` instances in turn, one call each: what the
/// engine alone costs a chain, whose calls each enter a different store
/// (its memory and tables no longer in the cache), unlike (b)'s one hot
/// instance.
fn bare_round_robin(relays: &mut [BareRelay], overhead: u64) -> (u64, u64) {
    let value = GuestValue::Scalar(1.5);
    let mut next = 0;
    sample(overhead, || {
        relays[next].call(&value);
        next = (next + 1) % relays.len();
    })
}

/// The bare call on engines with one wasmtime setting changed: p50 per
/// round, as ratios to the plain bare engine measured in the same round.
fn engine_settings(bytes: &[u8], rounds: usize, overhead: u64) {
    type Tweak = fn(&mut Config);
    let variants: [(&str, Tweak); 6] = [
        ("epoch interruption on (as subsume; deadline never reached)", |c| {
            c.epoch_interruption(true);
        }),
        ("pooling allocator (default sizes)", |c| {
            c.allocation_strategy(wasmtime::InstanceAllocationStrategy::Pooling(
                wasmtime::PoolingAllocationConfig::default(),
            ));
        }),
        ("signals-based traps off (explicit checks)", |c| {
            c.signals_based_traps(false);
        }),
        ("copy-on-write memory init off", |c| {
            c.memory_init_cow(false);
        }),
        ("lazy table init off", |c| {
            c.table_lazy_init(false);
        }),
        ("concurrency support on (wasmtime's default)", |c| {
            c.concurrency_support(true);
        }),
    ];
    println!();
    println!(
        "the bare call (b) on an engine with one setting changed (p50, median of {rounds} rounds, ratio to (b) in the same round):"
    );
    println!();
    println!("| engine | p50 | / (b) |");
    println!("|---|---|---|");
    for (label, tweak) in variants {
        let mut ratios = Vec::new();
        let mut p50s = Vec::new();
        for _ in 0..rounds {
            let mut plain = BareRelay::new(bytes);
            let mut changed = match BareRelay::with(bytes, tweak) {
                Ok(relay) => relay,
                Err(why) => {
                    println!("| {label} | refused: {why} | |");
                    break;
                }
            };
            let base = bare_call(&mut plain, overhead).0 as f64;
            let p50 = bare_call(&mut changed, overhead).0 as f64;
            ratios.push(p50 / base);
            p50s.push(p50);
        }
        if ratios.is_empty() {
            continue;
        }
        ratios.sort_by(f64::total_cmp);
        p50s.sort_by(f64::total_cmp);
        println!("| {label} | {:.0} ns | {:.2} |", p50s[p50s.len() / 2], ratios[ratios.len() / 2]);
    }
}

// ------------------------------------------------ (c), (d) the subsume hop

fn limits() -> GuestLimits {
    GuestLimits { memory_bytes: 16 << 20, ..GuestLimits::default() }
}

fn relay(sandbox: &Sandbox, bytes: &[u8]) -> Box<dyn Component> {
    let artifact = sandbox.load(bytes).unwrap();
    Box::new(sandbox.instantiate(&artifact, "relay", &limits(), &[]).unwrap())
}

/// source (native, only used to inject) -> `relays` relays -> sink.
fn chain(relays: usize, port: u32, mut make: impl FnMut() -> Box<dyn Component>) -> (Graph, usize) {
    let mut graph = Graph::new();
    let source = graph.add("source", Box::new(Vacant), 2, 0.0, 0);
    let mut previous = source;
    for _ in 0..relays {
        let next = graph.add("relay", make(), 2, 0.0, 0);
        graph.connect(previous, port, next, port, Policy::Latest);
        previous = next;
    }
    let sink = graph.add("sink", Box::new(Vacant), 0, 0.0, 0);
    graph.connect(previous, port, sink, port, Policy::Latest);
    (graph, source)
}

fn hop(make: impl FnMut() -> Box<dyn Component>, port: u32, value: &Value, overhead: u64) -> (u64, u64) {
    let (mut graph, source) = chain(1, port, make);
    let result = sample(overhead, || graph.inject(source, port, value.clone(), 0));
    graph.asleep();
    result
}

/// Deliveries per second through a chain of 8 relay guests.
fn chain_rate(sandbox: &Sandbox, bytes: &[u8]) -> f64 {
    let relays = 8;
    let (mut graph, source) = chain(relays, 0, || relay(sandbox, bytes));
    let values = 200_000u64;
    for i in 0..10_000 {
        graph.inject(source, 0, Value::Scalar(i as f64), 0);
    }
    let before = graph.stats(relays).unwrap().messages_in;
    let start = Instant::now();
    for i in 0..values {
        graph.inject(source, 0, Value::Scalar(i as f64), 0);
    }
    let elapsed = start.elapsed();
    assert_eq!(graph.stats(relays).unwrap().messages_in - before, values, "the chain lost values");
    graph.asleep();
    (values * (relays as u64 + 1)) as f64 / elapsed.as_secs_f64()
}

// --------------------------------------------- (e) across a process boundary

/// A value on the wire: a tag, then a scalar's 8 bytes or a vector's count
/// and elements (what the cheapest hand-written framing costs; real
/// frameworks add headers, type hashes and routing on top).
fn encode(value: &Value, buffer: &mut Vec<u8>) {
    buffer.clear();
    buffer.extend_from_slice(&[0; 4]);
    match value {
        Value::Scalar(x) => {
            buffer.push(1);
            buffer.extend_from_slice(&x.to_le_bytes());
        }
        Value::Vector(v) => {
            buffer.push(2);
            for x in v {
                buffer.extend_from_slice(&x.to_le_bytes());
            }
        }
        other => panic!("the socket row carries scalars and vectors, not {other:?}"),
    }
    let len = (buffer.len() - 4) as u32;
    buffer[..4].copy_from_slice(&len.to_le_bytes());
}

fn decode(frame: &[u8]) -> Value {
    let body = &frame[1..];
    let f = |c: &[u8]| f64::from_le_bytes(c.try_into().unwrap());
    match frame[0] {
        1 => Value::Scalar(f(body)),
        2 => Value::Vector(body.chunks_exact(8).map(f).collect()),
        tag => panic!("unknown tag {tag}"),
    }
}

/// Reads one frame into `frame`; false at the end of the stream.
fn read_frame(stream: &mut UnixStream, frame: &mut Vec<u8>) -> bool {
    let mut len = [0u8; 4];
    if stream.read_exact(&mut len).is_err() {
        return false;
    }
    frame.resize(u32::from_le_bytes(len) as usize, 0);
    stream.read_exact(frame).is_ok()
}

/// The far process: decode each value, hand it to a native relay, send its
/// output back.
fn echo_child(path: &str) {
    let mut stream = UnixStream::connect(path).unwrap();
    let mut relay = NativeRelay;
    let (mut frame, mut buffer, mut out) = (Vec::new(), Vec::new(), Vec::with_capacity(4));
    while read_frame(&mut stream, &mut frame) {
        let value = decode(&frame);
        relay.on_input(0, &value, 0, 0, &mut out).unwrap();
        for (_, value) in out.drain(..) {
            encode(&value, &mut buffer);
            stream.write_all(&buffer).unwrap();
        }
    }
}

struct Echo {
    stream: UnixStream,
    child: std::process::Child,
    _dir: tempfile::TempDir,
}

impl Echo {
    fn start() -> Echo {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("peers.sock");
        let listener = UnixListener::bind(&path).unwrap();
        let child =
            std::process::Command::new(std::env::current_exe().unwrap()).env(ECHO_SOCKET, &path).spawn().unwrap();
        let (stream, _) = listener.accept().unwrap();
        Echo { stream, child, _dir: dir }
    }

    /// One-way (half a round trip) p50 and p99 for `value`.
    fn hop(&mut self, value: &Value, overhead: u64) -> (u64, u64) {
        let (mut buffer, mut frame) = (Vec::new(), Vec::new());
        let mut round_trip = || {
            encode(value, &mut buffer);
            self.stream.write_all(&buffer).unwrap();
            assert!(read_frame(&mut self.stream, &mut frame), "the echo process hung up");
            black_box(decode(&frame));
        };
        for _ in 0..WARMUP / 4 {
            round_trip();
        }
        let mut times = Vec::with_capacity(SOCKET_SAMPLES);
        for _ in 0..SOCKET_SAMPLES {
            let start = Instant::now();
            round_trip();
            times.push((start.elapsed().as_nanos() as u64).saturating_sub(overhead) / 2);
        }
        times.sort_unstable();
        (percentile(&times, 0.50), percentile(&times, 0.99))
    }
}

impl Drop for Echo {
    fn drop(&mut self) {
        let _ = self.stream.shutdown(std::net::Shutdown::Both);
        let _ = self.child.wait();
    }
}

/// A Zenoh peer session: no multicast scouting, the given endpoints.
fn zenoh_session(key: &str, endpoint: &str) -> zenoh::Session {
    use zenoh::Wait;
    let mut config = zenoh::Config::default();
    config.insert_json5("mode", "\"peer\"").unwrap();
    config.insert_json5("scouting/multicast/enabled", "false").unwrap();
    config.insert_json5(key, &format!("[\"{endpoint}\"]")).unwrap();
    zenoh::open(config).wait().unwrap()
}

/// The far process of the Zenoh row: each value on `peers/ping` decoded,
/// handed to a native relay, its output put on `peers/pong`.
fn zenoh_echo_child(endpoint: &str) {
    use zenoh::Wait;
    let session = zenoh_session("connect/endpoints", endpoint);
    let pong = session.declare_publisher("peers/pong").wait().unwrap();
    let ping = session.declare_subscriber("peers/ping").wait().unwrap();
    let mut relay = NativeRelay;
    let mut out = Vec::with_capacity(4);
    while let Ok(sample) = ping.recv() {
        let bytes = sample.payload().to_bytes();
        if bytes.is_empty() {
            break;
        }
        let value = wire::decode(&bytes).unwrap();
        relay.on_input(0, &value, 0, 0, &mut out).unwrap();
        for (_, value) in out.drain(..) {
            pong.put(wire::encode(&value)).wait().unwrap();
        }
    }
}

struct ZenohEcho {
    session: zenoh::Session,
    ping: zenoh::pubsub::Publisher<'static>,
    pong: zenoh::pubsub::Subscriber<zenoh::handlers::FifoChannelHandler<zenoh::sample::Sample>>,
    child: std::process::Child,
}

impl ZenohEcho {
    fn start() -> ZenohEcho {
        use zenoh::Wait;
        let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
        let endpoint = format!("tcp/127.0.0.1:{port}");
        let session = zenoh_session("listen/endpoints", &endpoint);
        let ping = session.declare_publisher("peers/ping").wait().unwrap();
        let pong = session.declare_subscriber("peers/pong").wait().unwrap();
        let child =
            std::process::Command::new(std::env::current_exe().unwrap()).env(ECHO_ZENOH, &endpoint).spawn().unwrap();
        // Until the far side is connected and subscribed, pings are lost.
        let hello = wire::encode(&Value::Scalar(0.0));
        let deadline = Instant::now() + std::time::Duration::from_secs(30);
        loop {
            ping.put(hello.clone()).wait().unwrap();
            if pong.recv_timeout(std::time::Duration::from_millis(100)).is_ok_and(|s| s.is_some()) {
                break;
            }
            assert!(Instant::now() < deadline, "the zenoh echo process never answered");
        }
        // Drain answers to the extra hellos.
        std::thread::sleep(std::time::Duration::from_millis(200));
        while pong.try_recv().is_ok_and(|s| s.is_some()) {}
        ZenohEcho { session, ping, pong, child }
    }

    /// One-way (half a round trip) p50 and p99 for `value`.
    fn hop(&mut self, value: &Value, overhead: u64) -> (u64, u64) {
        use zenoh::Wait;
        let round_trip = || {
            self.ping.put(wire::encode(value)).wait().unwrap();
            let sample = self.pong.recv().unwrap();
            black_box(wire::decode(&sample.payload().to_bytes()).unwrap());
        };
        for _ in 0..WARMUP / 10 {
            round_trip();
        }
        let mut times = Vec::with_capacity(ZENOH_SAMPLES);
        for _ in 0..ZENOH_SAMPLES {
            let start = Instant::now();
            round_trip();
            times.push((start.elapsed().as_nanos() as u64).saturating_sub(overhead) / 2);
        }
        times.sort_unstable();
        (percentile(&times, 0.50), percentile(&times, 0.99))
    }
}

impl Drop for ZenohEcho {
    fn drop(&mut self) {
        use zenoh::Wait;
        // An empty payload tells the far side to end.
        let _ = self.ping.put(Vec::<u8>::new()).wait();
        let _ = self.child.wait();
        let _ = self.session.close().wait();
    }
}

// ------------------------------------------------------------------ table

#[derive(Default)]
struct Row {
    label: &'static str,
    /// Per round: (p50, p99) ns, or for throughput (per-delivery ns, rate/s).
    rounds: Vec<(f64, f64)>,
    throughput: bool,
}

impl Row {
    fn new(label: &'static str) -> Row {
        Row { label, ..Row::default() }
    }
    fn push(&mut self, (p50, p99): (u64, u64)) {
        self.rounds.push((p50 as f64, p99 as f64));
    }
    /// The round with the median first figure.
    fn median(&self) -> (f64, f64) {
        let mut rounds = self.rounds.clone();
        rounds.sort_by(|a, b| a.0.total_cmp(&b.0));
        rounds[rounds.len() / 2]
    }
}

fn main() {
    if let Ok(path) = std::env::var(ECHO_SOCKET) {
        echo_child(&path);
        return;
    }
    if let Ok(endpoint) = std::env::var(ECHO_ZENOH) {
        zenoh_echo_child(&endpoint);
        return;
    }
    let rounds: usize = std::env::var("PEERS_ROUNDS").ok().and_then(|r| r.parse().ok()).unwrap_or(3).max(1);
    let bytes = std::fs::read(support::guest("test-relay")).unwrap();
    let v1_bytes = std::fs::read(support::guest("test-relay-v1")).unwrap();
    let sandbox = Sandbox::new(Some(support::cache_dir())).unwrap();
    let overhead = timer_overhead();
    let mut bare = BareRelay::new(&bytes);
    let mut bare8: Vec<BareRelay> = (0..8).map(|_| BareRelay::new(&bytes)).collect();
    let mut echo = Echo::start();
    let mut zecho = ZenohEcho::start();
    let scalar = Value::Scalar(1.5);

    let mut a = Row::new("(a) native `Component` call (relay, emits once)");
    let mut a2 = Row::new("(a') native relay, hop through the graph");
    let mut b = Row::new("(b) bare wasmtime `on-input` call (relay guest, emits once)");
    let mut b8 = Row::new("(b8) bare wasmtime calls to 8 relay instances in turn (the chain's engine floor)");
    let mut c = Row::new("(c) subsume hop, scalar");
    let mut cv = Row::new("(c) subsume hop, vector of 100 f64");
    let mut c1 = Row::new("(c) subsume hop, scalar, a 0.1.0 relay (`on-input` returns a result)");
    let mut d = Row { throughput: true, ..Row::new("(d) chain of 8 relay guests, per delivery") };
    let mut e = Row::new("(e) Unix socket to a second process, scalar (one way)");
    let mut ev = Row::new("(e) Unix socket to a second process, vector of 100 f64 (one way)");
    let mut z = Row::new("(e) Zenoh put/subscribe to a second process over TCP loopback, scalar (one way)");
    let mut zv = Row::new("(e) Zenoh put/subscribe to a second process over TCP loopback, vector of 100 f64 (one way)");
    for round in 0..rounds {
        eprintln!("round {} of {rounds}", round + 1);
        a.push(native_call(overhead));
        a2.push(hop(|| Box::new(NativeRelay), 0, &scalar, overhead));
        b.push(bare_call(&mut bare, overhead));
        b8.push(bare_round_robin(&mut bare8, overhead));
        c.push(hop(|| relay(&sandbox, &bytes), 0, &scalar, overhead));
        cv.push(hop(|| relay(&sandbox, &bytes), 1, &vector(), overhead));
        c1.push(hop(|| relay(&sandbox, &v1_bytes), 0, &scalar, overhead));
        let rate = chain_rate(&sandbox, &bytes);
        d.rounds.push((1e9 / rate, rate));
        e.push(echo.hop(&scalar, overhead));
        ev.push(echo.hop(&vector(), overhead));
        z.push(zecho.hop(&scalar, overhead));
        zv.push(zecho.hop(&vector(), overhead));
    }
    drop(echo);
    drop(zecho);

    let floor = b.median().0;
    println!("timer overhead subtracted from each sample: {overhead} ns; {rounds} rounds, median round shown");
    println!();
    println!("| row | p50 | p99 | p50 / (b) |");
    println!("|---|---|---|---|");
    for row in [&a, &a2, &b, &b8, &c, &cv, &c1, &d, &e, &ev, &z, &zv] {
        let (first, second) = row.median();
        if row.throughput {
            println!(
                "| {} | {first:.0} ns ({:.2} M messages/s) | | {:.2} (rate x (b) = {:.2}) |",
                row.label,
                second / 1e6,
                first / floor,
                second * floor / 1e9
            );
        } else {
            println!("| {} | {first:.0} ns | {second:.0} ns | {:.2} |", row.label, first / floor);
        }
    }
    println!();
    let (c50, cv50, d_rate) = (c.median().0, cv.median().0, d.median().1);
    let verdict = |ok: bool| if ok { "met" } else { "not met" };
    println!("goals (issue 15, part 2):");
    println!("- hop p50 <= 1.25 x (b): {:.2} x, {}", c50 / floor, verdict(c50 <= 1.25 * floor));
    println!(
        "- chain throughput >= 0.8 / (b): {:.2} / (b), {}",
        d_rate * floor / 1e9,
        verdict(d_rate * floor / 1e9 >= 0.8)
    );
    println!("- vector hop p50 <= 1.5 x scalar hop: {:.2} x, {}", cv50 / c50, verdict(cv50 <= 1.5 * c50));
    if std::env::var("PEERS_ENGINE_SETTINGS").is_ok_and(|v| v != "0") {
        engine_settings(&bytes, rounds, overhead);
    }
    for row in [&a, &a2, &b, &b8, &c, &cv, &c1, &d, &e, &ev, &z, &zv] {
        let firsts: Vec<String> = row.rounds.iter().map(|r| format!("{:.0}", r.0)).collect();
        println!("rounds, {}: {} ns", row.label, firsts.join(" / "));
    }
}
