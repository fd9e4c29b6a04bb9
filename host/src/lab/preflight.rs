//! The preflight: every experiment first runs headless in the simulator,
//! for its whole duration, before it may drive the robot (docs/lab.md).
//!
//! It is `subsume run` on the set's robot file in its preflight form
//! ([`super::materialize`]), in a process of its own at a low priority
//! ([`Priority`]): its own sandbox instances, its own memory,
//! and a crash or a runaway guest of its own never reaches the robot's
//! control loop. It runs on simulated time as fast as the machine allows,
//! records to MCAP, writes the run report, and judges what it saw
//! ([`super::verdict`]) with the owner's criteria: `subsume run --verdict`.
//!
//! Child side: [`HolderWatch`] (who held control when, from the arbiter's
//! standings, one atomic load a cycle) and [`observe`] (what the run saw, read
//! from the graph, the simulated robots and the report when it ends).
//! Parent side: [`run`] starts the child, bounds the CPU time it uses (and how long a
//! host too busy to run it makes the lab wait), and reads its verdict.

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use thiserror::Error;

use super::verdict::{ContactAt, Criteria, Fault, HolderTimeline, Interventions, Observations, Verdict, judge};
use crate::config::RobotConfig;
use crate::envelope::EnvelopeStatus;
use crate::report::Report;
use crate::runtime::Graph;
use crate::runtime::control_loop::CycleHook;
use crate::runtime::graph::ComponentState;
use crate::runtime::{Standing, Standings};
use crate::sim::SimSection;
use crate::sim::perturb::Perturbation;
use crate::store::experiments::{FaultSeen, MAX_OUTCOME_FAULTS, RunOutcome};
use crate::store::task::Task;

/// Most CPU time a preflight may use, beyond its simulated duration: a
/// preflight whose components use their whole budgets on every call runs
/// slower than real time, and must not hold the lab's checks forever. It is
/// CPU time, not wall-clock time, so a preflight the robot's own work
/// starved (it runs at idle priority) is not blamed on the submitter.
pub const PREFLIGHT_CPU_GRACE: Duration = Duration::from_secs(60);

/// Longest wall-clock time the lab waits for a preflight beyond its CPU
/// bound: a host too busy to give it the CPU fails the experiment as the
/// host's problem rather than holding the lab's checks forever.
pub const PREFLIGHT_STARVED_AFTER: Duration = Duration::from_secs(600);

/// Most bytes of a preflight's output kept in its log (`preflight.log`): a
/// guest that logs without end (its `max-logs` lines a second, each up to
/// 4 KiB, for the whole preflight) must not fill the owner's disk. Past it
/// the log says it was cut, and the rest is read and dropped.
pub const MAX_PREFLIGHT_LOG_BYTES: u64 = 16 << 20;

/// Most bytes of a preflight's recording (`preflight.mcap`,
/// `--record-max-total-mib`): a set that emits as much as it may for its
/// whole duration must not fill the owner's disk. Past it the recording
/// stops (its file finished, marked cut) and the log says so. Below the
/// rotation size, so a preflight's recording is one file.
pub const MAX_PREFLIGHT_RECORDING_BYTES: u64 = 512 << 20;

/// Most memory a preflight process may map writable (`RLIMIT_DATA`: its
/// heap and every guest's accessible linear memory; not the address space
/// wasmtime only reserves, terabytes with its pooling allocator, which
/// `RLIMIT_AS` would count): a preflight whose guests grow their memories
/// must not take the robot's memory. Measured: the demo's preflight maps
/// 2.2 GB with the pooling allocator (its pools, mostly never touched); a
/// machine whose pools do not fit falls back to allocating on demand.
pub const PREFLIGHT_MEMORY_BYTES: u64 = 4 << 30;

/// The bounds of a preflight, the named limits above unless a test sets
/// its own.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct PreflightLimits {
    /// [`MAX_PREFLIGHT_LOG_BYTES`].
    pub log_bytes: u64,
    /// [`MAX_PREFLIGHT_RECORDING_BYTES`] (whole MiB).
    pub recording_bytes: u64,
    /// [`PREFLIGHT_MEMORY_BYTES`].
    pub memory_bytes: u64,
}

impl Default for PreflightLimits {
    fn default() -> PreflightLimits {
        PreflightLimits {
            log_bytes: MAX_PREFLIGHT_LOG_BYTES,
            recording_bytes: MAX_PREFLIGHT_RECORDING_BYTES,
            memory_bytes: PREFLIGHT_MEMORY_BYTES,
        }
    }
}

/// The `nice` value of a preflight process at [`Priority::Idle`]: it only
/// gets the CPU the robot does not use.
pub const PREFLIGHT_NICE: i32 = 19;

/// How a preflight process is scheduled beside the host that starts it
/// (`--preflight-priority`, docs/lab.md).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Priority {
    /// `nice` [`PREFLIGHT_NICE`] under `SCHED_IDLE`: only the CPU every
    /// other thread leaves. A robot's default: its control loop and portal
    /// come first, always; a busy robot makes the lab wait (up to
    /// [`PREFLIGHT_STARVED_AFTER`]) instead.
    #[default]
    Idle,
    /// `nice` [`crate::runtime::scheduling::BACKGROUND_NICE`], as a
    /// component's compile: a share of a busy CPU, behind the host's own
    /// threads. The lab server's default (it drives no robot), and a
    /// robot's choice when its own work keeps the machine busy.
    Background,
    /// The host's own priority: a fair share of a busy CPU. For a lab
    /// server whose machine does nothing else, and for the tests, whose
    /// neighbours keep every core busy.
    Normal,
}

impl Priority {
    /// The setting's spelling.
    pub const NAMES: [&str; 3] = ["idle", "background", "normal"];
}

/// A preflight priority's name that is none of [`Priority::NAMES`].
#[derive(Clone, Debug, PartialEq, Eq, Error)]
#[error("unknown preflight priority '{0}': expected idle, background or normal")]
pub struct UnknownPriority(pub String);

impl std::str::FromStr for Priority {
    type Err = UnknownPriority;
    fn from_str(text: &str) -> Result<Priority, UnknownPriority> {
        match text {
            "idle" => Ok(Priority::Idle),
            "background" => Ok(Priority::Background),
            "normal" => Ok(Priority::Normal),
            other => Err(UnknownPriority(other.to_string())),
        }
    }
}

/// Notes who holds control, on the control thread, between cycles: one
/// atomic load a cycle, a look at each source's standing only when an
/// arbiter changed one.
pub struct HolderWatch {
    standings: Standings,
    sources: Vec<String>,
    seen: u64,
    timeline: HolderTimeline,
}

impl HolderWatch {
    /// Watches the sources of `config` through `standings` (the one the
    /// run's arbiters write).
    pub fn new(config: &RobotConfig, standings: Standings) -> HolderWatch {
        let sources = config.components.iter().filter(|c| c.priority.is_some()).map(|c| c.name.clone()).collect();
        HolderWatch { standings, sources, seen: u64::MAX, timeline: HolderTimeline::default() }
    }

    pub fn timeline(&self) -> &HolderTimeline {
        &self.timeline
    }
}

impl CycleHook for HolderWatch {
    fn between_cycles(&mut self, _graph: &mut Graph, now_ns: u64) {
        let generation = self.standings.generation();
        if generation == self.seen {
            return;
        }
        self.seen = generation;
        let holder = self.sources.iter().find(|s| self.standings.get(s) == Standing::Holds);
        self.timeline.note(now_ns as f64 / 1e9, holder.map(String::as_str));
    }
}

/// Why what a run saw could not be read.
#[derive(Debug, Error)]
#[error("the run's report cannot be judged: {0}")]
pub struct ObserveError(String);

/// What the run of `config` saw, once it stopped: its faults from `graph`,
/// the collisions of its simulated robots and the envelope's interventions
/// from `report`'s sections, who held control when from `holders`.
pub fn observe(
    config: &RobotConfig,
    graph: &Graph,
    report: &Report,
    holders: HolderTimeline,
) -> Result<Observations, ObserveError> {
    let mut observed = Observations { simulated_s: report.duration_s, holders, ..Observations::default() };
    for (index, component) in config.components.iter().enumerate() {
        if let Some(ComponentState::Faulted { reason, at_ns }) = graph.state(index) {
            observed.faults.push(Fault {
                component: component.name.clone(),
                at_s: *at_ns as f64 / 1e9,
                reason: reason.clone(),
            });
        }
    }
    observed.faults.sort_by(|a, b| a.at_s.total_cmp(&b.at_s));
    seen_in_sections(report, &mut observed);
    Ok(observed)
}

/// What `report`'s sections say: the collisions of its simulated robots and
/// whether they reached the goal, and the envelope's interventions.
fn seen_in_sections(report: &Report, observed: &mut Observations) {
    for (name, sim) in report.sections.of::<SimSection>() {
        let status = &sim.simulation;
        observed.collisions += status.collisions;
        observed.contacts.extend(status.contacts.iter().map(|c| ContactAt::of(name, c)));
        observed.goal_reached = Some(observed.goal_reached.unwrap_or(true) && status.goal_reached);
    }
    observed.contacts.sort_by(|a, b| a.time_s.total_cmp(&b.time_s));
    for (_, envelope) in report.sections.of::<EnvelopeStatus>() {
        for (cause, count) in &envelope.causes {
            let first = envelope.first.get(cause);
            let seen = observed.envelope.entry((*cause).to_string()).or_insert(Interventions {
                count: 0,
                first_at_s: None,
                first: None,
            });
            seen.count += count;
            if let Some(first) = first
                && seen.first_at_s.is_none_or(|at| first.at_s < at)
            {
                seen.first_at_s = Some(first.at_s);
                seen.first = Some(first.text.clone());
            }
        }
    }
}

/// How the algorithm did in a run on the robot, from the run's `report`
/// alone (the robot's run has no holder timeline): its components' faults,
/// collisions, the envelope's interventions by cause, the goal.
pub fn outcome(report: &Report) -> RunOutcome {
    let mut seen = Observations::default();
    seen_in_sections(report, &mut seen);
    let faults = report
        .components
        .iter()
        .filter(|c| c.faults > 0 || c.fault.is_some())
        .map(|c| FaultSeen {
            component: c.name.clone(),
            at_s: c.faulted_at_s,
            reason: c.fault.clone().unwrap_or_else(|| format!("faulted {} times and was restarted", c.faults)),
        })
        .take(MAX_OUTCOME_FAULTS)
        .collect();
    let interventions = seen
        .envelope
        .iter()
        .filter(|(_, seen)| seen.count > 0)
        .map(|(cause, seen)| (cause.clone(), seen.count))
        .collect();
    RunOutcome { faults, collisions: seen.collisions, interventions, goal_reached: seen.goal_reached, ended_by: None }
}

/// The verdict of the run of `config` (see [`observe`]).
pub fn verdict(
    criteria: &Criteria,
    config: &RobotConfig,
    graph: &Graph,
    report: &Report,
    holders: HolderTimeline,
) -> Result<Verdict, ObserveError> {
    Ok(judge(criteria, observe(config, graph, report, holders)?))
}

/// Where a preflight writes what it leaves.
#[derive(Clone, Debug)]
pub struct PreflightFiles {
    pub recording: PathBuf,
    pub report: PathBuf,
    pub verdict: PathBuf,
    pub criteria: PathBuf,
    /// The task whose end conditions end it, as on the robot (`--task`).
    pub task: PathBuf,
    /// The child's standard output and error.
    pub log: PathBuf,
    /// The bounds of a seeded run's timing (`--perturb-bounds`).
    pub bounds: PathBuf,
}

impl PreflightFiles {
    /// The files of a preflight in `dir`.
    pub fn in_dir(dir: &Path) -> PreflightFiles {
        PreflightFiles {
            recording: dir.join("preflight.mcap"),
            report: dir.join("preflight-report.json"),
            verdict: dir.join("preflight-verdict.json"),
            criteria: dir.join("preflight-criteria.json"),
            task: dir.join("preflight-task.json"),
            log: dir.join("preflight.log"),
            bounds: dir.join("preflight-bounds.json"),
        }
    }
}

/// How a preflight run ended.
#[derive(Debug)]
pub enum Outcome {
    /// It ran its whole duration and was judged.
    Judged { verdict: Verdict, wall_s: f64 },
    /// The robot file did not start in the simulator: the submitter's
    /// problem, with what `subsume run` said.
    DidNotStart(Vec<String>),
    /// It used more CPU time than its bound and was killed.
    TooSlow { limit: Duration },
    /// The host gave it too little CPU to finish within
    /// [`PREFLIGHT_STARVED_AFTER`] of its bound (the host's problem): it
    /// was killed having used `cpu` in `waited`.
    Starved { cpu: Duration, waited: Duration },
}

/// Why a preflight could not be carried out (the host's problem).
#[derive(Debug, Error)]
pub enum PreflightError {
    #[error("cannot start the preflight process {exe}: {source}")]
    Spawn {
        exe: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("preflight file {path}: {reason}")]
    File { path: PathBuf, reason: String },
    #[error("the preflight process ended without a verdict ({status}); its last words: {last}")]
    Crashed { status: String, last: String },
    #[error("the preflight was cancelled")]
    Cancelled,
}

/// What starting a preflight needs.
#[derive(Clone, Debug)]
pub struct PreflightCommand {
    /// The `subsume` binary.
    pub exe: PathBuf,
    /// The compile cache to share with the host (no cache when `None`).
    pub cache_dir: Option<PathBuf>,
    /// How the process is scheduled.
    pub priority: Priority,
    /// Its log, recording and memory bounds.
    pub limits: PreflightLimits,
}

/// Lines of the child's output kept as a reason when the robot did not start.
const LAST_WORDS: usize = 12;

/// Runs the preflight of the robot file `robot` for `duration` in a
/// process of its own at `command.priority`, writing `files`; `cancelled`
/// is polled to stop it early. With `task`'s end conditions it ends as the
/// robot's run would (`--task`).
pub fn run(
    command: &PreflightCommand,
    robot: &Path,
    duration: Duration,
    criteria: &Criteria,
    task: Option<&Task>,
    files: &PreflightFiles,
    cancelled: &dyn Fn() -> bool,
) -> Result<Outcome, PreflightError> {
    run_seeded(command, robot, duration, criteria, task, None, files, cancelled)
}

/// [`run`], with its timing seeded by `perturb` (`--perturb`,
/// `sim::perturb`) when given.
#[allow(clippy::too_many_arguments)]
pub fn run_seeded(
    command: &PreflightCommand,
    robot: &Path,
    duration: Duration,
    criteria: &Criteria,
    task: Option<&Task>,
    perturb: Option<&Perturbation>,
    files: &PreflightFiles,
    cancelled: &dyn Fn() -> bool,
) -> Result<Outcome, PreflightError> {
    let file_error = |path: &Path| {
        let path = path.to_path_buf();
        move |e: std::io::Error| PreflightError::File { path: path.clone(), reason: e.to_string() }
    };
    let criteria_json = serde_json::to_vec_pretty(criteria)
        .map_err(|e| PreflightError::File { path: files.criteria.clone(), reason: e.to_string() })?;
    crate::fsutil::write_atomically(&files.criteria, &criteria_json).map_err(file_error(&files.criteria))?;
    let task = task.filter(|t| !t.end_on.is_empty());
    if let Some(task) = task {
        let task_json = serde_json::to_vec_pretty(task)
            .map_err(|e| PreflightError::File { path: files.task.clone(), reason: e.to_string() })?;
        crate::fsutil::write_atomically(&files.task, &task_json).map_err(file_error(&files.task))?;
    }
    if let Some(perturb) = perturb {
        let bounds_json = serde_json::to_vec_pretty(&perturb.bounds)
            .map_err(|e| PreflightError::File { path: files.bounds.clone(), reason: e.to_string() })?;
        crate::fsutil::write_atomically(&files.bounds, &bounds_json).map_err(file_error(&files.bounds))?;
    }
    let log = std::fs::File::create(&files.log).map_err(file_error(&files.log))?;
    // Standard output and error into one pipe the host reads into the log,
    // up to its bound.
    let (output, output_end) = std::io::pipe().map_err(file_error(&files.log))?;
    let output_err = output_end.try_clone().map_err(file_error(&files.log))?;
    let recording_mib = (command.limits.recording_bytes >> 20).max(1).to_string();
    let mut child = Command::new(&command.exe);
    child
        .arg("run")
        .arg(robot)
        .args(["--http", "off", "--speed", "max", "--foxglove", "off"])
        .arg("--duration")
        .arg(format!("{}", duration.as_secs_f64()))
        .arg("--record")
        .arg(&files.recording)
        .args(["--record-max-mib", &recording_mib, "--record-max-total-mib", &recording_mib])
        .arg("--report")
        .arg(&files.report)
        .arg("--verdict")
        .arg(&files.verdict)
        .arg("--criteria")
        .arg(&files.criteria)
        .env("RUST_LOG", "info")
        .env("NO_COLOR", "1")
        .env_remove("SUBSUME_FAULT_INJECTION")
        .env_remove("SUBSUME_HTTP")
        .env_remove("SUBSUME_FOXGLOVE")
        .stdin(Stdio::null())
        .stdout(Stdio::from(output_end))
        .stderr(Stdio::from(output_err));
    match &command.cache_dir {
        Some(dir) => child.arg("--cache-dir").arg(dir),
        None => child.arg("--no-cache"),
    };
    if task.is_some() {
        child.arg("--task").arg(&files.task);
    }
    if let Some(perturb) = perturb {
        child.arg("--perturb").arg(perturb.seed.to_string()).arg("--perturb-bounds").arg(&files.bounds);
    }
    lowered(&mut child, command.priority, command.limits.memory_bytes);
    let started = Instant::now();
    let limit = duration + PREFLIGHT_CPU_GRACE;
    let spawned = child.spawn();
    // The pipe's writing ends are the child's alone now: the reader sees
    // its end when the child's output closes.
    drop(child);
    let mut process = spawned.map_err(|source| PreflightError::Spawn { exe: command.exe.clone(), source })?;
    let log_bytes = command.limits.log_bytes;
    let copier = std::thread::Builder::new()
        .name("preflight-log".into())
        .spawn(move || copy_bounded(output, log, log_bytes))
        .map_err(|source| PreflightError::Spawn { exe: command.exe.clone(), source })?;
    let copied = || {
        if let Ok(Err(e)) = copier.join() {
            tracing::warn!("the preflight's log: {e}");
        }
    };
    let status = loop {
        match process.try_wait() {
            Ok(Some(status)) => break status,
            Ok(None) => {}
            Err(e) => return Err(PreflightError::Crashed { status: e.to_string(), last: String::new() }),
        }
        let cpu = cpu_time(process.id());
        let too_slow = cpu.is_some_and(|cpu| cpu > limit);
        let starved = started.elapsed() > limit + PREFLIGHT_STARVED_AFTER;
        if cancelled() || too_slow || starved {
            let _ = process.kill();
            let _ = process.wait();
            copied();
            if cancelled() {
                return Err(PreflightError::Cancelled);
            }
            if too_slow {
                return Ok(Outcome::TooSlow { limit });
            }
            return Ok(Outcome::Starved { cpu: cpu.unwrap_or_default(), waited: started.elapsed() });
        }
        std::thread::sleep(Duration::from_millis(20));
    };
    let wall_s = started.elapsed().as_secs_f64();
    copied();
    let output = std::fs::read_to_string(&files.log).unwrap_or_default();
    if status.success() {
        let bytes = std::fs::read(&files.verdict).map_err(file_error(&files.verdict))?;
        let verdict: Verdict = serde_json::from_slice(&bytes)
            .map_err(|e| PreflightError::File { path: files.verdict.clone(), reason: e.to_string() })?;
        return Ok(Outcome::Judged { verdict, wall_s });
    }
    let errors: Vec<String> = output
        .lines()
        .filter_map(|l| l.strip_prefix("error: "))
        .map(|l| format!("preflight: {l}"))
        .take(LAST_WORDS)
        .collect();
    // Exit code 1 with errors: the robot file did not start (a config or
    // start error, the submitter's). Anything else (a panic, a signal) is
    // the host's.
    if status.code() == Some(1) && !errors.is_empty() {
        return Ok(Outcome::DidNotStart(errors));
    }
    let last = output.lines().rev().take(3).collect::<Vec<_>>().join(" | ");
    Err(PreflightError::Crashed { status: status.to_string(), last: crate::contract::clip(&last) })
}

/// Copies `from` into `to` up to `limit` bytes; past it `to` says it was
/// cut, and the rest of `from` is read (the child never blocks on a full
/// pipe) and dropped. Returns the bytes `from` gave.
fn copy_bounded(mut from: impl std::io::Read, mut to: impl std::io::Write, limit: u64) -> std::io::Result<u64> {
    let mut buffer = vec![0u8; 64 * 1024];
    let mut total: u64 = 0;
    loop {
        let n = match from.read(&mut buffer) {
            Ok(0) => break,
            Ok(n) => n,
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => continue,
            Err(e) => return Err(e),
        };
        let room = limit.saturating_sub(total);
        if room > 0 {
            let kept = (n as u64).min(room) as usize;
            to.write_all(&buffer[..kept])?;
            if kept < n {
                write!(
                    to,
                    "\n(the preflight's log stops here: it is cut at {limit} bytes, the most kept; the rest of its output was dropped)\n"
                )?;
            }
        }
        total += n as u64;
    }
    to.flush()?;
    Ok(total)
}

/// The CPU time process `pid` has used so far, user and system, from
/// `/proc/PID/stat`; `None` when it cannot be read.
fn cpu_time(pid: u32) -> Option<Duration> {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).ok()?;
    cpu_time_of(&stat, clock_ticks_per_second()?)
}

/// The user and system time in a `/proc/PID/stat` line (fields 14 and 15;
/// the command name in parentheses may hold spaces).
fn cpu_time_of(stat: &str, ticks_per_second: u64) -> Option<Duration> {
    let fields: Vec<&str> = stat.rsplit_once(')')?.1.split_whitespace().collect();
    let user: u64 = fields.get(11)?.parse().ok()?;
    let system: u64 = fields.get(12)?.parse().ok()?;
    Some(Duration::from_secs_f64((user + system) as f64 / ticks_per_second.max(1) as f64))
}

fn clock_ticks_per_second() -> Option<u64> {
    // SAFETY: sysconf only reads a configuration value.
    let ticks = unsafe { libc::sysconf(libc::_SC_CLK_TCK) };
    u64::try_from(ticks).ok().filter(|t| *t > 0)
}

/// The child runs at `priority` with at most `memory_bytes` mapped
/// writable (`RLIMIT_DATA`), and is killed when the thread that
/// started it ends: a host killed mid-preflight (`kill -9`, a panic that
/// exits) leaves no orphan running on its CPU and holding its files.
fn lowered(command: &mut Command, priority: Priority, memory_bytes: u64) {
    use std::os::unix::process::CommandExt;
    let parent = std::process::id() as libc::pid_t;
    // SAFETY: between fork and exec only async-signal-safe calls are made
    // (prctl, getppid, getrlimit, setrlimit, setpriority and
    // sched_setscheduler are system calls), and nothing allocates
    // (`from_raw_os_error` does not). A refused priority leaves the child
    // at the host's, which is still a separate process; a refused memory
    // limit fails the start.
    unsafe {
        command.pre_exec(move || {
            if libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGKILL) != 0 {
                return Err(std::io::Error::last_os_error());
            }
            // The parent may have died before the prctl took hold.
            if libc::getppid() != parent {
                return Err(std::io::Error::from_raw_os_error(libc::ESRCH));
            }
            // Never above what the host itself may map.
            let mut memory = libc::rlimit { rlim_cur: 0, rlim_max: 0 };
            if libc::getrlimit(libc::RLIMIT_DATA, &mut memory) != 0 {
                return Err(std::io::Error::last_os_error());
            }
            memory.rlim_max = memory.rlim_max.min(memory_bytes);
            memory.rlim_cur = memory.rlim_max;
            if libc::setrlimit(libc::RLIMIT_DATA, &memory) != 0 {
                return Err(std::io::Error::last_os_error());
            }
            match priority {
                Priority::Idle => {
                    libc::setpriority(libc::PRIO_PROCESS, 0, PREFLIGHT_NICE);
                    let param = libc::sched_param { sched_priority: 0 };
                    libc::sched_setscheduler(0, libc::SCHED_IDLE, &param);
                }
                Priority::Background => {
                    libc::setpriority(libc::PRIO_PROCESS, 0, crate::runtime::scheduling::BACKGROUND_NICE);
                }
                Priority::Normal => {}
            }
            Ok(())
        });
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// (a `/proc/PID/stat` line, ticks per second, the CPU time read).
    #[test]
    fn the_cpu_time_is_read_past_a_command_name_with_spaces_and_parentheses() {
        let cases = [
            ("4242 (subsume) S 1 4242 4242 0 -1 4194560 100 0 0 0 250 50 0 0 39 19 8 0", 100, Some(3.0)),
            ("7 (a (b) c) R 1 7 7 0 -1 0 0 0 0 0 10 5 0 0 20 0 1 0", 100, Some(0.15)),
            ("7 (x) R 1 7", 100, None),
            ("no parenthesis", 100, None),
        ];
        for (stat, ticks, expected) in cases {
            assert_eq!(cpu_time_of(stat, ticks).map(|d| d.as_secs_f64()), expected, "{stat}");
        }
    }

    /// (priority, the child's nice value, its scheduling policy), read
    /// from `/proc/PID/stat` (fields 19 and 41).
    #[test]
    fn a_preflight_process_runs_at_its_priority() {
        // SAFETY: getpriority only reads this thread's nice value.
        let own = i64::from(unsafe { libc::getpriority(libc::PRIO_PROCESS, 0) });
        let cases = [
            (Priority::Idle, 19, libc::SCHED_IDLE as i64),
            (Priority::Background, 10, libc::SCHED_OTHER as i64),
            (Priority::Normal, own, libc::SCHED_OTHER as i64),
        ];
        for (priority, nice, policy) in cases {
            let mut command = Command::new("sleep");
            command.arg("30");
            lowered(&mut command, priority, PREFLIGHT_MEMORY_BYTES);
            let mut child = command.spawn().unwrap();
            let stat = std::fs::read_to_string(format!("/proc/{}/stat", child.id())).unwrap();
            let _ = child.kill();
            let _ = child.wait();
            let fields: Vec<i64> =
                stat.rsplit_once(')').unwrap().1.split_whitespace().skip(1).map(|f| f.parse().unwrap_or(-1)).collect();
            // Fields are counted from 1 and the list starts at field 4.
            assert_eq!((fields[19 - 4], fields[41 - 4]), (nice, policy), "{priority:?}: {stat}");
        }
        let names: Vec<Priority> = Priority::NAMES.iter().map(|n| n.parse().unwrap()).collect();
        assert_eq!(names, [Priority::Idle, Priority::Background, Priority::Normal]);
        assert!("fast".parse::<Priority>().unwrap_err().to_string().contains("'fast'"));
    }

    /// A preflight process may map at most its memory limit writable: the
    /// child's `Max data size` in `/proc/PID/limits`, soft and hard.
    #[test]
    fn a_preflight_process_has_its_memory_limit() {
        for limit in [PREFLIGHT_MEMORY_BYTES, 256 << 20] {
            let mut command = Command::new("sleep");
            command.arg("30");
            lowered(&mut command, Priority::Normal, limit);
            let mut child = command.spawn().unwrap();
            let limits = std::fs::read_to_string(format!("/proc/{}/limits", child.id())).unwrap();
            let _ = child.kill();
            let _ = child.wait();
            let line = limits.lines().find(|l| l.starts_with("Max data size")).unwrap();
            let values: Vec<&str> = line["Max data size".len()..].split_whitespace().collect();
            assert_eq!(values, [limit.to_string().as_str(), limit.to_string().as_str(), "bytes"], "{limits}");
        }
    }

    /// The log keeps its first `limit` bytes and says it was cut; the
    /// writer is read to its end (it never blocks), and a log within its
    /// limit is kept whole, unmarked.
    #[test]
    fn a_log_past_its_limit_is_cut_and_says_so() {
        use std::io::Read as _;
        let limit = 1000;
        let endless = std::io::repeat(b'x').take(10 << 20);
        let mut log = Vec::new();
        assert_eq!(copy_bounded(endless, &mut log, limit).unwrap(), 10 << 20);
        let text = String::from_utf8(log).unwrap();
        let (kept, note) = text.split_at(limit as usize);
        assert!(kept.bytes().all(|b| b == b'x'));
        assert!(note.starts_with("\n(the preflight's log stops here: it is cut at 1000 bytes"), "{note}");
        let mut short = Vec::new();
        copy_bounded(&b"line\n"[..], &mut short, limit).unwrap();
        assert_eq!(short, b"line\n");
    }

    /// A preflight dies with the thread that started it (a host killed
    /// mid-preflight leaves no orphan): the child of a thread that ended
    /// was killed by SIGKILL, not left to sleep its 30 s.
    #[test]
    fn a_preflight_process_dies_with_the_thread_that_started_it() {
        use std::os::unix::process::ExitStatusExt;
        let mut child = std::thread::spawn(|| {
            let mut command = Command::new("sleep");
            command.arg("30");
            lowered(&mut command, Priority::Background, PREFLIGHT_MEMORY_BYTES);
            command.spawn().unwrap()
        })
        .join()
        .unwrap();
        let status = child.wait().unwrap();
        assert_eq!(status.signal(), Some(libc::SIGKILL), "{status}");
    }

    #[test]
    fn this_process_has_used_some_cpu() {
        let spent = cpu_time(std::process::id());
        assert!(spent.is_some(), "cannot read this process's cpu time");
    }
}
