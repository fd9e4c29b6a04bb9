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
//! - `none`: behaves.

use subsume_guest::{
    Component, Description, LogLevel, ParamKind, Params, Value, ValueKind, emit, input, log, output, param,
};

struct Faulty {
    mode: String,
    after: i64,
    ticks: i64,
    hoard: Vec<&'static mut [u8]>,
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
            .priority(2)
    }

    fn init(params: &Params) -> Result<Self, String> {
        let mode = params.text("mode").unwrap_or("none").to_string();
        match mode.as_str() {
            "error-on-init" => return Err("refusing to start, as asked".into()),
            "loop-on-init" => spin(),
            _ => {}
        }
        Ok(Faulty { mode, after: params.integer("after")?, ticks: 0, hoard: Vec::new() })
    }

    fn on_input(&mut self, _port: u32, _value: Value) -> Result<(), String> {
        if self.mode == "loop-on-input" {
            spin();
        }
        Ok(())
    }

    fn tick(&mut self, _now_ns: u64) -> Result<(), String> {
        if self.ticks < self.after || self.mode == "none" {
            self.ticks += 1;
            emit(0, &Value::Scalar(self.ticks as f64));
            if self.mode == "command-then-loop" {
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
            "error-on-tick" => Err(format!("failing on purpose at tick {}", self.ticks)),
            other => Err(format!("unknown mode '{other}'")),
        }
    }
}

subsume_guest::component!(Faulty);
