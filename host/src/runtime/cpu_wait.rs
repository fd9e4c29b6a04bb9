//! How long the control thread waited for a CPU while it was ready to run:
//! the kernel's run delay for the thread (`/proc/thread-self/schedstat`,
//! second field, nanoseconds). It tells a busy machine from a slow host:
//! ticks a component missed while the loop waited for the CPU are the
//! machine's doing, the rest the host's or a component's. The control loop
//! reads it at most once a second ([`READ_INTERVAL`]), so it costs nothing
//! per cycle.

use std::time::Duration;

/// How often the control loop reads the run delay (a file read: a few
/// microseconds, so not on every cycle).
pub const READ_INTERVAL: Duration = Duration::from_secs(1);

/// The calling thread's run delay so far, or `None` where the kernel does
/// not keep it (no `CONFIG_SCHED_INFO`, or not Linux).
pub fn thread_run_delay_ns() -> Option<u64> {
    let text = std::fs::read_to_string("/proc/thread-self/schedstat").ok()?;
    text.split_whitespace().nth(1)?.parse().ok()
}

/// The run delay of one graph's control thread since that graph started
/// running (a graph swapped in by an activation starts from zero).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct CpuWait {
    base_ns: Option<u64>,
    latest_ns: u64,
}

impl CpuWait {
    /// Whether a first reading was taken.
    pub fn started(&self) -> bool {
        self.base_ns.is_some()
    }

    /// Takes a reading of [`thread_run_delay_ns`]; the first one is the base.
    pub fn note(&mut self, reading_ns: u64) {
        self.base_ns.get_or_insert(reading_ns);
        self.latest_ns = reading_ns;
    }

    /// Run delay between the first reading and the last.
    pub fn waited_ns(&self) -> u64 {
        self.base_ns.map_or(0, |base| self.latest_ns.saturating_sub(base))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn thread_cpu_time() -> Duration {
        let mut ts = libc::timespec { tv_sec: 0, tv_nsec: 0 };
        // SAFETY: `ts` is a valid timespec to write into.
        assert_eq!(unsafe { libc::clock_gettime(libc::CLOCK_THREAD_CPUTIME_ID, &mut ts) }, 0);
        Duration::new(ts.tv_sec as u64, ts.tv_nsec as u32)
    }

    /// Pins the calling thread to `cpu`.
    fn pin(cpu: usize) {
        // SAFETY: a zeroed cpu_set_t is a valid empty set; CPU_SET writes
        // inside it; pid 0 is the calling thread.
        unsafe {
            let mut set: libc::cpu_set_t = std::mem::zeroed();
            libc::CPU_SET(cpu, &mut set);
            assert_eq!(libc::sched_setaffinity(0, std::mem::size_of::<libc::cpu_set_t>(), &set), 0);
        }
    }

    #[test]
    fn a_thread_sharing_its_cpu_with_a_busy_one_waits_and_the_wait_is_counted() {
        let Some(before) = thread_run_delay_ns() else {
            panic!("this kernel keeps no per-thread run delay (/proc/thread-self/schedstat)");
        };
        let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
        let spinner = {
            let stop = stop.clone();
            std::thread::spawn(move || {
                pin(0);
                while !stop.load(std::sync::atomic::Ordering::Relaxed) {
                    std::hint::spin_loop();
                }
            })
        };
        pin(0);
        // 100 ms of CPU on a CPU shared with a spinner: the scheduler makes
        // this thread wait about as long again.
        let start = thread_cpu_time();
        while thread_cpu_time() - start < Duration::from_millis(100) {
            std::hint::spin_loop();
        }
        stop.store(true, std::sync::atomic::Ordering::Relaxed);
        spinner.join().unwrap();
        let waited = thread_run_delay_ns().unwrap() - before;
        assert!(waited >= 30_000_000, "waited {waited} ns for the cpu beside a spinner");

        let mut wait = CpuWait::default();
        assert!(!wait.started());
        wait.note(before);
        wait.note(before + waited);
        assert!(wait.started());
        assert_eq!(wait.waited_ns(), waited);
    }
}
