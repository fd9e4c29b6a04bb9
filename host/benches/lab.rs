#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic)]
//! The remote lab's goals (issue 30, part 8; docs/lab.md), in one run:
//!
//! 1. preflight speed: a 60 s preflight of the demo robot (`subsume run
//!    --speed max --verdict`, a process at nice 19 and SCHED_IDLE, as the
//!    lab starts it) while the demo robot runs beside it in this process:
//!    simulated seconds per wall-clock second (goal: 10x or more);
//! 2. the robot's loop lateness p99 with preflights running back to back,
//!    against the same figure without them, in the same run (goal: 1.1x
//!    or less); lateness is how long after its time each cycle started,
//!    read exactly in the loop's hook, as `kilohertz` does;
//! 3. turnaround: from the end of one experiment to the start of the next
//!    (a reset and two activations), on the real binary with its portal,
//!    from the experiments' recorded state changes (goal: 1 s or less);
//! 4. submit to results of a 60 s experiment with an empty queue: from the
//!    POST to the last byte of the results archive (goal: 75 s or less).
//!
//! Settings (environment): `LAB_SECONDS` (default 30): each half of part 2.
//! Run: `taskset -c 0,1 cargo bench --bench lab` (BENCHMARKS.md).

#[path = "../../tests/all/support.rs"]
mod support;

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use subsume::assemble::{self, Loader};
use subsume::builtin::Services;
use subsume::config::{self, ParamOverride};
use subsume::lab::preflight::{self, Outcome, PreflightCommand, PreflightFiles, Priority};
use subsume::lab::verdict::Criteria;
use subsume::runtime::Graph;
use subsume::runtime::control_loop::{Clock, CycleHook, Shutdown, run_with};
use subsume::sandbox::Sandbox;

/// The demo robot in `dir` (with its world and operators file beside it),
/// its components where the build left them, and no fixed ports.
fn demo_robot(dir: &Path) -> PathBuf {
    let root = support::repo_root();
    std::fs::create_dir_all(dir.join("worlds")).unwrap();
    std::fs::copy(root.join("config/worlds/demo.world"), dir.join("worlds/demo.world")).unwrap();
    std::fs::copy(root.join("config/demo-operators"), dir.join("demo-operators")).unwrap();
    let text = std::fs::read_to_string(root.join("config/demo.xml")).unwrap();
    let text = text
        .replace("../guest-components", &root.join("guest-components").display().to_string())
        .replace("127.0.0.1:7070", "127.0.0.1:0")
        .replace("127.0.0.1:7071", "127.0.0.1:0");
    let path = dir.join("demo.xml");
    std::fs::write(&path, text).unwrap();
    path
}

/// Each cycle's lateness, read in the loop's hook, marked by phase.
struct Lateness {
    samples: Vec<(u64, bool)>,
    busy: Arc<AtomicBool>,
}

impl CycleHook for Lateness {
    fn between_cycles(&mut self, graph: &mut Graph, now_ns: u64) {
        if let Some(due) = graph.next_due_ns().filter(|due| *due <= now_ns) {
            self.samples.push((now_ns - due, self.busy.load(Ordering::Relaxed)));
        }
    }
}

fn percentile(sorted: &[u64], p: f64) -> u64 {
    sorted.get(((sorted.len().saturating_sub(1)) as f64 * p).round() as usize).copied().unwrap_or(0)
}

fn preflights_beside_the_robot(seconds: f64) {
    let dir = tempfile::tempdir().unwrap();
    let robot = demo_robot(dir.path());
    // The robot, in this process, on its own control thread.
    let sandbox = Sandbox::new(Some(support::cache_dir())).unwrap();
    let mut loader = Loader::new(&sandbox);
    let config = config::load_with(&robot, &mut loader, &[] as &[ParamOverride]).unwrap();
    let clock = Clock::new();
    let shutdown = Shutdown::new();
    let mut graph = assemble::build(
        &config,
        &mut loader,
        clock.clone(),
        &shutdown.waker(),
        &Services::default(),
        &Default::default(),
    )
    .map(|b| b.graph)
    .unwrap_or_else(|e| panic!("{e:?}"));
    let busy = Arc::new(AtomicBool::new(false));
    let mut hook = Lateness { samples: Vec::with_capacity(200_000), busy: busy.clone() };
    let until = clock.now_ns() + ((2.0 * seconds + 2.0) * 1e9) as u64;
    let loop_clock = clock.clone();
    let loop_shutdown = shutdown.clone();
    let robot_thread = std::thread::spawn(move || {
        run_with(&mut graph, &loop_clock, &loop_shutdown, Some(until), &mut hook);
        hook
    });
    // First half alone; second half with preflights back to back.
    std::thread::sleep(Duration::from_secs_f64(seconds + 1.0));
    busy.store(true, Ordering::Relaxed);
    let command =
        // A robot's preflight, at a robot's default priority.
        PreflightCommand {
            exe: PathBuf::from(env!("CARGO_BIN_EXE_subsume")),
            cache_dir: Some(support::cache_dir()),
            priority: Priority::Idle,
            limits: subsume::lab::preflight::PreflightLimits::default(),
        };
    let started = Instant::now();
    let mut speeds = Vec::new();
    let mut n = 0;
    while started.elapsed().as_secs_f64() < seconds {
        n += 1;
        let out = dir.path().join(format!("p{n}"));
        std::fs::create_dir_all(&out).unwrap();
        let files = PreflightFiles::in_dir(&out);
        match preflight::run(&command, &robot, Duration::from_secs(60), &Criteria::default(), None, &files, &|| false) {
            Ok(Outcome::Judged { verdict, wall_s }) => {
                speeds.push(verdict.observed.simulated_s / wall_s);
            }
            other => panic!("preflight {n}: {other:?}\n{}", std::fs::read_to_string(&files.log).unwrap_or_default()),
        }
    }
    busy.store(false, Ordering::Relaxed);
    let hook = robot_thread.join().unwrap();
    let phase = |busy: bool| {
        let mut v: Vec<u64> = hook.samples.iter().filter(|(_, b)| *b == busy).map(|(l, _)| *l).collect();
        v.sort_unstable();
        v
    };
    let (alone, beside) = (phase(false), phase(true));
    let us = |ns: u64| ns as f64 / 1e3;
    println!(
        "preflights: {} of 60 s simulated, {:.1}x real time on average (slowest {:.1}x), beside the demo robot",
        speeds.len(),
        speeds.iter().sum::<f64>() / speeds.len().max(1) as f64,
        speeds.iter().copied().fold(f64::INFINITY, f64::min)
    );
    println!(
        "robot loop lateness p99: {:.1} us alone ({} cycles), {:.1} us with preflights back to back ({} cycles): {:.2}x",
        us(percentile(&alone, 0.99)),
        alone.len(),
        us(percentile(&beside, 0.99)),
        beside.len(),
        percentile(&beside, 0.99) as f64 / percentile(&alone, 0.99).max(1) as f64
    );
    println!(
        "robot loop lateness p50: {:.1} us alone, {:.1} us beside; max {:.1} us alone, {:.1} us beside",
        us(percentile(&alone, 0.5)),
        us(percentile(&beside, 0.5)),
        us(alone.last().copied().unwrap_or(0)),
        us(beside.last().copied().unwrap_or(0))
    );
}

const PASSWORD: &str = "lab-bench-password";

fn on_the_real_binary() {
    let dir = tempfile::tempdir().unwrap();
    let robot = demo_robot(dir.path());
    let store = dir.path().join("store");
    support::add_user(&store, "ana", "researcher", &["control"], PASSWORD);
    let mut command = support::subsume();
    command
        .arg("--store")
        .arg(&store)
        .arg("run")
        .arg(&robot)
        .args(["--http", "127.0.0.1:0"])
        .env_remove("SUBSUME_HTTP");
    let host = support::HostProcess::spawn(command);
    let address = host.word_after("portal on http://", Duration::from_secs(120)).trim_end_matches('/').to_string();
    let token = support::login(&address, "ana", PASSWORD);
    let text = std::fs::read_to_string(&robot).unwrap().replace("value=\"8.5\"", "value=\"8.0\"");
    let (status, json) =
        support::http(&address, "PUT", "/api/v1/platforms/control/configs/mine.xml", Some(&token), text.as_bytes());
    assert_eq!(status, 201, "{json}");
    let set = json["set"]["id"].as_u64().unwrap();
    let submit = |duration: f64| {
        let body = serde_json::json!({ "set": set, "duration_s": duration }).to_string();
        let (status, json) = support::http(&address, "POST", "/api/v1/experiments", Some(&token), body.as_bytes());
        assert_eq!(status, 201, "{json}");
        json["experiment"]["id"].as_u64().unwrap()
    };
    let wait = |id: u64| loop {
        let (_, json) = support::http(&address, "GET", &format!("/api/v1/experiments/{id}"), Some(&token), b"");
        let experiment = json["experiment"].clone();
        if experiment["state"]
            .as_str()
            .is_some_and(|s| ["done", "refused", "cancelled", "aborted", "failed"].contains(&s))
        {
            assert_eq!(experiment["state"], "done", "{experiment:#}\n{}", host.log());
            return experiment;
        }
        std::thread::sleep(Duration::from_millis(20));
    };
    let at = |experiment: &serde_json::Value, state: &str| {
        experiment["history"].as_array().unwrap().iter().find(|c| c["state"] == state).unwrap()["at_ms"]
            .as_u64()
            .unwrap()
    };
    // Turnaround, over a few pairs.
    let mut turnarounds = Vec::new();
    for _ in 0..3 {
        let (a, b) = (submit(5.0), submit(5.0));
        let (a, b) = (wait(a), wait(b));
        turnarounds.push(at(&b, "running") as f64 - at(&a, "finishing") as f64);
    }
    println!(
        "turnaround (one experiment's end to the next one's start: a reset and two activations): {} ms",
        turnarounds.iter().map(|t| format!("{t:.0}")).collect::<Vec<_>>().join(", ")
    );
    // Submit to results.
    let started = Instant::now();
    let id = submit(60.0);
    let done = wait(id);
    let archive = dir.path().join("results.tar");
    let fetched = std::process::Command::new("curl")
        .args(["-s", "-f", "-o"])
        .arg(&archive)
        .args(["-H", &format!("Authorization: Bearer {token}")])
        .arg(format!("http://{address}/api/v1/experiments/{id}/results"))
        .status()
        .unwrap();
    assert!(fetched.success());
    let total = started.elapsed().as_secs_f64();
    println!(
        "submit to results of a 60 s experiment, empty queue: {total:.1} s (preflight {:.1} s, queued to running {} ms, archive {:.1} MB)",
        done["preflight"]["wall_s"].as_f64().unwrap_or(0.0),
        at(&done, "running") - at(&done, "queued"),
        std::fs::metadata(&archive).map(|m| m.len()).unwrap_or(0) as f64 / 1e6
    );
}

fn main() {
    let seconds = std::env::var("LAB_SECONDS").ok().and_then(|s| s.parse().ok()).unwrap_or(30.0);
    support::guest_dir();
    preflights_beside_the_robot(seconds);
    on_the_real_binary();
}
