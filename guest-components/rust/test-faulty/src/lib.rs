//! Test guest that misbehaves on purpose, chosen by the `mode` parameter,
//! after `after` good ticks (each good tick emits the tick count on `out`
//! and, in `command-then-loop`, a motion command on `cmd`):
//!
//! - `trap-on-tick`: aborts (a trap) in `tick`;
//! - `panic-on-tick`: a Rust `panic!` in `tick` (a trap, with a message);
//! - `loop-on-tick`, `loop-on-init`, `loop-on-input`: spins forever there;
//! - `recurse-on-tick`: recursion without end (stack overflow);
//! - `grow-memory`: allocates and keeps 1 MiB per tick, without bound;
//! - `emit-flood`: emits a million values in one tick;
//! - `giant-emit`: emits one vector of 262144 numbers (2 MiB, over the
//!   default `max-message`);
//! - `log-flood`: writes ten thousand log lines in one tick;
//! - `bad-port-on-tick`: emits on an output port that does not exist;
//! - `error-on-tick`: returns `err` from `tick` (not a fault: only logged);
//! - `error-on-init`: refuses to start;
//! - `wasi-probe`: tries files, sockets and the environment, and returns
//!   what happened as its `err` (all must fail for lack of capability);
//! - `command-then-loop`: drives (`VEL 0.3 0` on `cmd`) for `after` ticks,
//!   then spins forever while holding control;
//! - `sleep-on-tick`, `sleep-on-input`, `sleep-on-init`: sleeps 10 s there
//!   (`std::thread::sleep`: a monotonic-clock subscription and a blocking
//!   wait on it); in `tick` it logs "sleeping now" first;
//! - `poll-far-future`: `wasi:io/poll.poll` on a subscription an hour
//!   ahead of the monotonic clock;
//! - `read-stdin`: reads stdin, and returns what happened as its `err`;
//! - `busy-wall-clock`: spins until the wall clock says 10 ms passed;
//! - `clock-evasion`: behaves while the wall clock and the monotonic clock
//!   advance alike since its first tick, and faults (naming both) once they
//!   differ by more than a tenth: a component that tells a preflight on
//!   simulated time from the robot by its clocks;
//! - `exit-on-tick`: calls `exit(3)` (WASI 0.2 carries it as status 1);
//! - `random-probe`: returns as its `err` a hash with the std library's
//!   random keys (from `wasi:random`): the same for the same seed;
//! - `busy-on-tick`: behaves, but each tick first spins `spins` times on
//!   the CPU (a component that uses much of its budget);
//! - `none`: behaves.
//!
//! With `drive` = `yes`, every good tick also emits `VEL 0.3 0` on `cmd`.

use std::io::Read as _;
use std::time::{Duration, SystemTime};

use subsume_guest::{
    Component, Description, LogLevel, ParamKind, Params, Value, ValueKind, emit, input, log, output, param,
};

/// The two WASI interfaces `poll-far-future` calls directly (Rust's std
/// library has no `poll`), as WASI 0.2.0 defines them (the linker merges
/// them with the standard library's copies, which must match).
mod wasi_poll {
    wit_bindgen::generate!({
        inline: r#"
            package test:faulty;

            package wasi:io@0.2.0 {
                interface poll {
                    resource pollable {
                        ready: func() -> bool;
                        block: func();
                    }
                    poll: func(in: list<borrow<pollable>>) -> list<u32>;
                }
            }

            package wasi:clocks@0.2.0 {
                interface monotonic-clock {
                    use wasi:io/poll@0.2.0.{pollable};
                    type instant = u64;
                    type duration = u64;
                    now: func() -> instant;
                    resolution: func() -> duration;
                    subscribe-instant: func(when: instant) -> pollable;
                    subscribe-duration: func(when: duration) -> pollable;
                }
            }

            world probe {
                import wasi:io/poll@0.2.0;
                import wasi:clocks/monotonic-clock@0.2.0;
            }
        "#,
        world: "test:faulty/probe",
        generate_all,
    });
}

/// How long the sleeping modes sleep.
const SLEEP: Duration = Duration::from_secs(10);

struct Faulty {
    mode: String,
    after: i64,
    drive: bool,
    spins: u64,
    ticks: i64,
    hoard: Vec<&'static mut [u8]>,
    /// `clock-evasion`: the wall and monotonic clocks at its first tick.
    clocks_at_first: Option<(SystemTime, u64)>,
}

fn spin() -> ! {
    let mut spins: u64 = 0;
    loop {
        spins = std::hint::black_box(spins.wrapping_add(1));
    }
}

#[allow(unconditional_recursion)] // endless on purpose: the stack must overflow
fn recurse(depth: u64) -> u64 {
    let local = std::hint::black_box([depth; 16]);
    recurse(depth + 1).wrapping_add(local[3])
}

impl Component for Faulty {
    fn describe() -> Description {
        Description::new("test-faulty", "Misbehaves on purpose, for fault-isolation tests")
            .input(input("in", ValueKind::Scalar, "any number; loop-on-input spins on it"))
            .output(output("out", ValueKind::Scalar, "number of good ticks so far"))
            .output(output("report", ValueKind::Text, "what wasi-probe found"))
            .output(output("cmd", ValueKind::Command, "motion commands in command-then-loop"))
            .output(output("data", ValueKind::Vector, "giant-emit's giant vector"))
            .param(param("mode", ParamKind::Text, "none", "how to misbehave"))
            .param(param("after", ParamKind::Integer, "0", "good ticks before misbehaving"))
            .param(param("drive", ParamKind::Text, "no", "yes: every good tick emits VEL 0.3 0 on cmd"))
            .param(param("spins", ParamKind::Integer, "1000000", "busy-on-tick's spins per tick"))
            .priority(2)
    }

    fn init(params: &Params) -> Result<Self, String> {
        let mode = params.text("mode").unwrap_or("none").to_string();
        match mode.as_str() {
            "error-on-init" => return Err("refusing to start, as asked".into()),
            "loop-on-init" => spin(),
            "sleep-on-init" => std::thread::sleep(SLEEP),
            _ => {}
        }
        let drive = params.text("drive").unwrap_or("no") == "yes";
        // Optional: a host that instantiates without the declared defaults
        // (the runtime tests) gives only what it names.
        let spins = match params.text("spins") {
            None => 1_000_000,
            Some(_) => u64::try_from(params.integer("spins")?).map_err(|_| "spins must not be negative".to_string())?,
        };
        Ok(Faulty {
            mode,
            after: params.integer("after")?,
            drive,
            spins,
            ticks: 0,
            hoard: Vec::new(),
            clocks_at_first: None,
        })
    }

    fn on_input(&mut self, _port: u32, _value: Value) -> Result<(), String> {
        match self.mode.as_str() {
            "loop-on-input" => spin(),
            "sleep-on-input" if self.ticks >= self.after => std::thread::sleep(SLEEP),
            _ => {}
        }
        Ok(())
    }

    fn tick(&mut self, _now_ns: u64) -> Result<(), String> {
        if self.mode == "clock-evasion" {
            use wasi_poll::wasi::clocks::monotonic_clock;
            let (wall, mono) = (SystemTime::now(), monotonic_clock::now());
            let (wall0, mono0) = *self.clocks_at_first.get_or_insert((wall, mono));
            let walled = wall.duration_since(wall0).unwrap_or_default().as_nanos() as f64;
            let passed = mono.saturating_sub(mono0) as f64;
            if passed > 1e9 && (walled - passed).abs() > passed / 10.0 {
                return Err(format!(
                    "the clocks disagree: the wall clock advanced {:.2} s while the monotonic one advanced {:.2} s",
                    walled / 1e9,
                    passed / 1e9
                ));
            }
            self.ticks += 1;
            emit(0, &Value::Scalar(self.ticks as f64));
            return Ok(());
        }
        if self.mode == "busy-on-tick" {
            let mut spun: u64 = 0;
            for _ in 0..self.spins {
                spun = std::hint::black_box(spun.wrapping_add(1));
            }
        }
        if self.ticks < self.after || matches!(self.mode.as_str(), "none" | "sleep-on-input" | "busy-on-tick") {
            self.ticks += 1;
            emit(0, &Value::Scalar(self.ticks as f64));
            if self.mode == "command-then-loop" || self.drive {
                emit(2, &Value::Command("VEL 0.3 0".into()));
            }
            return Ok(());
        }
        match self.mode.as_str() {
            "trap-on-tick" => std::process::abort(),
            "panic-on-tick" => panic!("giving up on purpose at tick {}", self.ticks),
            "loop-on-tick" | "command-then-loop" => spin(),
            "recurse-on-tick" => {
                emit(0, &Value::Scalar(recurse(0) as f64));
                Ok(())
            }
            "grow-memory" => {
                self.hoard.push(vec![1u8; 1 << 20].leak());
                Ok(())
            }
            "emit-flood" => {
                for i in 0..1_000_000 {
                    emit(0, &Value::Scalar(f64::from(i)));
                }
                Ok(())
            }
            "giant-emit" => {
                emit(3, &Value::Vector(vec![0.5f64; 1 << 18]));
                Ok(())
            }
            "log-flood" => {
                for i in 0..10_000 {
                    log(LogLevel::Info, &format!("line {i}"));
                }
                Ok(())
            }
            "bad-port-on-tick" => {
                emit(99, &Value::Scalar(0.0));
                Ok(())
            }
            "wasi-probe" => {
                let file = match std::fs::read("/etc/hostname") {
                    Ok(bytes) => format!("read {} bytes", bytes.len()),
                    Err(e) => format!("refused ({e})"),
                };
                let socket = match std::net::TcpStream::connect("127.0.0.1:7") {
                    Ok(_) => "connected".to_string(),
                    Err(e) => format!("refused ({e})"),
                };
                let environment = match std::env::vars().count() {
                    0 => "empty".to_string(),
                    n => format!("{n} variables"),
                };
                self.mode = "none".into();
                Err(format!("file: {file}; socket: {socket}; environment: {environment}"))
            }
            "sleep-on-tick" => {
                // The host log's timestamp marks the blocking call (the
                // blocking bench measures from it).
                log(LogLevel::Info, "sleeping now");
                std::thread::sleep(SLEEP);
                Ok(())
            }
            "poll-far-future" => {
                use wasi_poll::wasi::clocks::monotonic_clock;
                let hour_ahead = monotonic_clock::now().saturating_add(3_600_000_000_000);
                let far = monotonic_clock::subscribe_instant(hour_ahead);
                let ready = wasi_poll::wasi::io::poll::poll(&[&far]);
                Err(format!("poll returned {ready:?}"))
            }
            "read-stdin" => {
                let mut buffer = [0u8; 64];
                let read = match std::io::stdin().read(&mut buffer) {
                    Ok(0) => "end of file".to_string(),
                    Ok(n) => format!("read {n} bytes"),
                    Err(e) => format!("error ({e})"),
                };
                self.mode = "none".into();
                Err(format!("stdin: {read}"))
            }
            "busy-wall-clock" => {
                let start = SystemTime::now();
                while start.elapsed().unwrap_or_default() < Duration::from_millis(10) {
                    std::hint::black_box(0u64);
                }
                Ok(())
            }
            "exit-on-tick" => std::process::exit(3),
            "random-probe" => {
                use std::hash::BuildHasher as _;
                let hash = std::collections::hash_map::RandomState::new().hash_one(0u8);
                self.mode = "none".into();
                Err(format!("hash: {hash:016x}"))
            }
            "error-on-tick" => Err(format!("failing on purpose at tick {}", self.ticks)),
            other => Err(format!("unknown mode '{other}'")),
        }
    }
}

subsume_guest::component!(Faulty);
