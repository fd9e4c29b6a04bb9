//! How the host's threads ask the kernel for the CPU, so the control loop
//! wins it when something else wants it too:
//!
//! - the control thread sleeps with a timer slack of [`CONTROL_TIMER_SLACK`]
//!   instead of Linux's default 50 µs, so a cycle starts when it is due;
//! - background work that can take seconds of CPU (compiling an uploaded
//!   component) runs at [`BACKGROUND_NICE`], so on a machine with few cores
//!   a compile yields to the loop instead of sharing the CPU with it evenly.
//!
//! Neither needs a privilege: a thread may always lower its own priority and
//! set its own timer slack. Real-time scheduling (`SCHED_FIFO`) and pinning
//! the control thread to a CPU are settings ([`ControlThreadSettings`],
//! `subsume run --control-fifo/--control-cpu`), never defaults: they need a
//! privilege and a machine set up for them (docs/service.md). Outside Linux
//! every function here does nothing.

use std::time::Duration;

use thiserror::Error;

/// Lowest and highest `SCHED_FIFO` priority a control thread may ask for
/// (Linux's range).
pub const FIFO_PRIORITIES: std::ops::RangeInclusive<i32> = 1..=99;

/// What the control thread may be given beyond the defaults.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct ControlThreadSettings {
    /// Run it under `SCHED_FIFO` at this priority.
    pub fifo_priority: Option<i32>,
    /// Pin it to this CPU.
    pub cpu: Option<usize>,
}

/// A setting the kernel refused.
#[derive(Debug, Error, PartialEq, Eq)]
pub enum SchedulingError {
    #[error("SCHED_FIFO priority {priority} is out of range (1 to 99)")]
    FifoPriorityRange { priority: i32 },
    #[error("cannot run the control thread under SCHED_FIFO at priority {priority}: {why}")]
    Fifo { priority: i32, why: String },
    #[error("cannot pin the control thread to cpu {cpu}: {why}")]
    Pin { cpu: usize, why: String },
    #[error("this system cannot {what}")]
    Unsupported { what: &'static str },
}

impl ControlThreadSettings {
    /// Applies the settings to the calling thread (the control thread),
    /// pinning first, each on its own: what was applied, in words, and what
    /// the kernel refused.
    pub fn apply(&self) -> (Vec<String>, Vec<SchedulingError>) {
        let (mut applied, mut refused) = (Vec::new(), Vec::new());
        if let Some(cpu) = self.cpu {
            match pin_to_cpu(cpu) {
                Ok(()) => applied.push(format!("pinned to cpu {cpu}")),
                Err(err) => refused.push(err),
            }
        }
        if let Some(priority) = self.fifo_priority {
            match run_fifo(priority) {
                Ok(()) => applied.push(format!("SCHED_FIFO at priority {priority}")),
                Err(err) => refused.push(err),
            }
        }
        (applied, refused)
    }
}

/// Pins the calling thread to `cpu`.
pub fn pin_to_cpu(cpu: usize) -> Result<(), SchedulingError> {
    #[cfg(target_os = "linux")]
    {
        if cpu >= libc::CPU_SETSIZE as usize {
            return Err(SchedulingError::Pin { cpu, why: "no such cpu".into() });
        }
        // SAFETY: a zeroed cpu_set_t is a valid empty set; CPU_SET writes
        // inside it (cpu < CPU_SETSIZE) and sched_setaffinity only reads it.
        let rc = unsafe {
            let mut set: libc::cpu_set_t = std::mem::zeroed();
            libc::CPU_SET(cpu, &mut set);
            libc::sched_setaffinity(0, std::mem::size_of::<libc::cpu_set_t>(), &set)
        };
        match rc {
            0 => Ok(()),
            _ => Err(SchedulingError::Pin { cpu, why: std::io::Error::last_os_error().to_string() }),
        }
    }
    #[cfg(not(target_os = "linux"))]
    {
        let _ = cpu;
        Err(SchedulingError::Unsupported { what: "pin a thread to a cpu" })
    }
}

/// Runs the calling thread under `SCHED_FIFO` at `priority`. Threads it
/// creates afterwards inherit the policy: call it on the control thread
/// only, after every other thread is made.
pub fn run_fifo(priority: i32) -> Result<(), SchedulingError> {
    if !FIFO_PRIORITIES.contains(&priority) {
        return Err(SchedulingError::FifoPriorityRange { priority });
    }
    #[cfg(target_os = "linux")]
    {
        let param = libc::sched_param { sched_priority: priority };
        // SAFETY: pid 0 is the calling thread; `param` is a valid sched_param.
        let rc = unsafe { libc::sched_setscheduler(0, libc::SCHED_FIFO, &param) };
        match rc {
            0 => Ok(()),
            _ => Err(SchedulingError::Fifo { priority, why: std::io::Error::last_os_error().to_string() }),
        }
    }
    #[cfg(not(target_os = "linux"))]
    {
        Err(SchedulingError::Unsupported { what: "run a thread under SCHED_FIFO" })
    }
}

/// Timer slack of the control thread: how late the kernel may end its
/// sleeps to batch wake-ups. Linux's default (50 µs) is 5% of a 1 kHz
/// period; a control loop wants its wake-up on time.
pub const CONTROL_TIMER_SLACK: Duration = Duration::from_micros(1);

/// Nice value of background threads (compiles). Threat: an upload of a large
/// component (a Python one compiles for seconds on every core) takes the
/// CPU from the control loop, which then starts its cycles late. At nice 10
/// a background thread weighs about a tenth of the loop's in the kernel's
/// share of the CPU.
pub const BACKGROUND_NICE: i32 = 10;

/// Sets the calling thread's timer slack to [`CONTROL_TIMER_SLACK`]; false
/// when the kernel refused (or outside Linux).
pub fn tighten_timer_slack() -> bool {
    #[cfg(target_os = "linux")]
    {
        let slack = CONTROL_TIMER_SLACK.as_nanos() as libc::c_ulong;
        // SAFETY: PR_SET_TIMERSLACK takes one integer argument and changes
        // only the calling thread.
        unsafe { libc::prctl(libc::PR_SET_TIMERSLACK, slack, 0, 0, 0) == 0 }
    }
    #[cfg(not(target_os = "linux"))]
    {
        false
    }
}

/// The calling thread's timer slack, in nanoseconds (`None` outside Linux).
pub fn timer_slack_ns() -> Option<u64> {
    #[cfg(target_os = "linux")]
    {
        // SAFETY: PR_GET_TIMERSLACK takes no argument and returns the slack.
        let slack = unsafe { libc::prctl(libc::PR_GET_TIMERSLACK, 0, 0, 0, 0) };
        u64::try_from(slack).ok()
    }
    #[cfg(not(target_os = "linux"))]
    {
        None
    }
}

/// Lowers the calling thread (only it: Linux keeps a nice value per thread)
/// to [`BACKGROUND_NICE`], unless it is already at or below it. Threads it
/// creates afterwards inherit the value. False when the kernel refused.
pub fn lower_to_background() -> bool {
    #[cfg(target_os = "linux")]
    {
        match thread_nice() {
            Some(nice) if nice >= BACKGROUND_NICE => true,
            _ => {
                // SAFETY: gettid has no arguments; setpriority with
                // PRIO_PROCESS and a thread id changes that thread only.
                unsafe {
                    let tid = libc::gettid() as libc::id_t;
                    libc::setpriority(libc::PRIO_PROCESS, tid, BACKGROUND_NICE) == 0
                }
            }
        }
    }
    #[cfg(not(target_os = "linux"))]
    {
        false
    }
}

/// The calling thread's nice value (`None` outside Linux or on error).
pub fn thread_nice() -> Option<i32> {
    #[cfg(target_os = "linux")]
    {
        // SAFETY: errno is thread-local; getpriority may legitimately return
        // -1, so errno is cleared first and read after.
        unsafe {
            *libc::__errno_location() = 0;
            let tid = libc::gettid() as libc::id_t;
            let nice = libc::getpriority(libc::PRIO_PROCESS, tid);
            (*libc::__errno_location() == 0).then_some(nice)
        }
    }
    #[cfg(not(target_os = "linux"))]
    {
        None
    }
}

/// Runs `work` on a new thread at [`BACKGROUND_NICE`] and waits for it; the
/// calling thread keeps its own priority. When no thread can be made, `work`
/// runs on the calling thread instead (it is never refused for that).
pub fn in_background<T: Send>(name: &str, work: impl FnOnce() -> T + Send) -> T {
    let slot = std::sync::Mutex::new(Some(work));
    let take = || slot.lock().unwrap_or_else(|poisoned| poisoned.into_inner()).take();
    std::thread::scope(|scope| {
        let spawned = std::thread::Builder::new().name(name.to_string()).spawn_scoped(scope, || {
            lower_to_background();
            take().map(|work| work())
        });
        let ran = match spawned {
            Ok(handle) => match handle.join() {
                Ok(ran) => ran,
                Err(panic) => std::panic::resume_unwind(panic),
            },
            Err(_) => None,
        };
        match ran {
            Some(result) => result,
            // Not spawned: the work is still in the slot.
            None => match take() {
                Some(work) => work(),
                None => neither_ran(),
            },
        }
    })
}

/// The spawned thread either took the work and ran it, or never started and
/// left it in the slot: there is no third case.
#[cold]
fn neither_ran<T>() -> T {
    #[allow(clippy::panic)]
    {
        panic!("background work was taken but did not run")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_control_thread_gets_a_tight_timer_slack() {
        std::thread::spawn(|| {
            let before = timer_slack_ns();
            assert!(tighten_timer_slack());
            assert_eq!(timer_slack_ns(), Some(CONTROL_TIMER_SLACK.as_nanos() as u64));
            assert_ne!(before, timer_slack_ns(), "the default slack is 50 us, not 1 us");
        })
        .join()
        .unwrap();
    }

    #[test]
    fn background_work_runs_niced_and_the_caller_keeps_its_priority() {
        std::thread::spawn(|| {
            let caller = thread_nice().unwrap();
            assert!(caller < BACKGROUND_NICE, "the test thread starts at {caller}");
            let (inside, child) = in_background("test-background", || {
                let inside = thread_nice();
                // A thread the background work starts (as a compile's worker
                // pool does) inherits the value.
                let child = std::thread::spawn(thread_nice).join().unwrap();
                (inside, child)
            });
            assert_eq!(inside, Some(BACKGROUND_NICE));
            assert_eq!(child, Some(BACKGROUND_NICE));
            assert_eq!(thread_nice(), Some(caller), "only the background thread was lowered");
        })
        .join()
        .unwrap();
    }

    #[test]
    fn control_thread_settings_pin_and_refuse_what_they_cannot_do() {
        std::thread::spawn(|| {
            let settings = ControlThreadSettings { fifo_priority: None, cpu: Some(0) };
            assert_eq!(settings.apply(), (vec!["pinned to cpu 0".to_string()], vec![]));
            let allowed = std::fs::read_to_string("/proc/thread-self/status").unwrap();
            assert!(allowed.lines().any(|l| l.split_whitespace().collect::<Vec<_>>() == ["Cpus_allowed_list:", "0"]));
            // Each setting on its own: a refused one does not undo the other.
            let both = ControlThreadSettings { fifo_priority: Some(0), cpu: Some(100_000) };
            let (applied, refused) = both.apply();
            assert!(applied.is_empty());
            assert!(matches!(refused[0], SchedulingError::Pin { cpu: 100_000, .. }), "{refused:?}");
            assert_eq!(refused[1], SchedulingError::FifoPriorityRange { priority: 0 });
            for priority in [100, -1] {
                let bad = ControlThreadSettings { fifo_priority: Some(priority), cpu: None };
                assert_eq!(bad.apply(), (vec![], vec![SchedulingError::FifoPriorityRange { priority }]));
            }
        })
        .join()
        .unwrap();
    }

    #[test]
    fn a_panic_in_background_work_reaches_the_caller() {
        let caught = std::panic::catch_unwind(|| in_background("test-background", || panic!("boom")));
        assert!(caught.is_err());
    }
}
