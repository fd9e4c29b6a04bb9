//! The WASI 0.2 surface a guest is linked against, and the host's own
//! implementations where wasmtime-wasi's would block the control loop or
//! make a run depend on the machine:
//!
//! - `wasi:clocks/monotonic-clock`: the cycle's time (`now-ns`), constant
//!   within a call; a subscription is ready at once when it is already due
//!   (a zero sleep) and never within the call otherwise;
//! - `wasi:clocks/wall-clock`: the system's wall time when the instance
//!   first asked, moved on by the cycle's time since: constant within a
//!   call, and advancing exactly as the monotonic clock does, on simulated
//!   time too, so no guest can tell a preflight from the robot by its
//!   clocks;
//! - `wasi:io/poll`: `poll` and `block` never wait: they return what is
//!   ready now, and when nothing is, the call traps with [`BlockingCall`]
//!   (a sleep, a timer or a read that would wait);
//! - `wasi:random/*`: generators seeded from the component's name
//!   ([`random_seed`](super::random_seed)), so a run can be replayed.
//!
//! Everything else is wasmtime-wasi's, with no capabilities (`guest.rs`
//! builds the context): no preopened directories, no sockets, no
//! environment or arguments, stdin closed, stdout and stderr to the log.
//! `docs/sandbox.md` lists every interface and the decision for it.
//!
//! Invariant: no function a guest can reach through WASI waits for time or
//! input to pass.

use std::time::{Duration, SystemTime};

use thiserror::Error;
use wasmtime::component::{HasData, Linker, Resource, ResourceTable};
use wasmtime_wasi::p2::bindings::clocks::{monotonic_clock, wall_clock};
use wasmtime_wasi::p2::bindings::sync::io::poll;
use wasmtime_wasi::p2::{DynPollable, Pollable, subscribe};

use super::guest::GuestState;

/// A guest asked to wait (`wasi:io/poll`) on something that is not ready:
/// the call is stopped instead of blocking the control loop.
#[derive(Clone, Debug, PartialEq, Eq, Error)]
#[error("blocking calls are not allowed: {call} would wait for {what} (a sleep, a timer or a read)")]
pub struct BlockingCall {
    /// The WASI function: `wasi:io/poll.poll` or `wasi:io/poll.pollable.block`.
    pub call: &'static str,
    /// What it would wait for.
    pub what: String,
}

/// Links WASI into `linker`: wasmtime-wasi's synchronous WASI 0.2, then the
/// host's clocks and poll over it.
pub(super) fn add_to_linker(linker: &mut Linker<GuestState>) -> wasmtime::Result<()> {
    wasmtime_wasi::p2::add_to_linker_sync(linker)?;
    linker.allow_shadowing(true);
    monotonic_clock::add_to_linker::<GuestState, CycleClocks>(linker, cycle_clocks)?;
    wall_clock::add_to_linker::<GuestState, CycleClocks>(linker, cycle_clocks)?;
    poll::add_to_linker::<GuestState, NonBlocking>(linker, |state| NonBlockingPoll(&mut state.table))?;
    linker.allow_shadowing(false);
    Ok(())
}

/// The clocks' view of a store: its table and the current call's times.
struct CycleClocksView<'a> {
    table: &'a mut ResourceTable,
    now_ns: u64,
    wall_anchor: &'a mut Option<(Duration, u64)>,
}

struct CycleClocks;

impl HasData for CycleClocks {
    type Data<'a> = CycleClocksView<'a>;
}

fn cycle_clocks(state: &mut GuestState) -> CycleClocksView<'_> {
    CycleClocksView { table: &mut state.table, now_ns: state.now_ns, wall_anchor: &mut state.wall_anchor }
}

impl CycleClocksView<'_> {
    /// A pollable that is ready at once when `due`, and never otherwise
    /// (the cycle's time does not pass within a call).
    fn wait(&mut self, due: bool) -> wasmtime::Result<Resource<DynPollable>> {
        let wait = self.table.push(ClockWait { due })?;
        subscribe(self.table, wait)
    }
}

impl monotonic_clock::Host for CycleClocksView<'_> {
    fn now(&mut self) -> wasmtime::Result<monotonic_clock::Instant> {
        Ok(self.now_ns)
    }

    fn resolution(&mut self) -> wasmtime::Result<monotonic_clock::Duration> {
        Ok(1)
    }

    fn subscribe_instant(&mut self, when: monotonic_clock::Instant) -> wasmtime::Result<Resource<DynPollable>> {
        let due = when <= self.now_ns;
        self.wait(due)
    }

    fn subscribe_duration(&mut self, duration: monotonic_clock::Duration) -> wasmtime::Result<Resource<DynPollable>> {
        self.wait(duration == 0)
    }
}

impl wall_clock::Host for CycleClocksView<'_> {
    fn now(&mut self) -> wasmtime::Result<wall_clock::Datetime> {
        let now_ns = self.now_ns;
        let (wall, at_ns) = *self.wall_anchor.get_or_insert_with(|| {
            (SystemTime::now().duration_since(SystemTime::UNIX_EPOCH).unwrap_or_default(), now_ns)
        });
        let now = wall.saturating_add(Duration::from_nanos(now_ns.saturating_sub(at_ns)));
        Ok(wall_clock::Datetime { seconds: now.as_secs(), nanoseconds: now.subsec_nanos() })
    }

    fn resolution(&mut self) -> wasmtime::Result<wall_clock::Datetime> {
        Ok(wall_clock::Datetime { seconds: 0, nanoseconds: 1 })
    }
}

/// A clock subscription: see [`CycleClocksView::wait`].
struct ClockWait {
    due: bool,
}

#[wasmtime_wasi::async_trait]
impl Pollable for ClockWait {
    async fn ready(&mut self) {
        if !self.due {
            std::future::pending::<()>().await;
        }
    }
}

/// `wasi:io/poll` over a store's table, never waiting.
struct NonBlockingPoll<'a>(&'a mut ResourceTable);

struct NonBlocking;

impl HasData for NonBlocking {
    type Data<'a> = NonBlockingPoll<'a>;
}

impl NonBlockingPoll<'_> {
    /// Whether `pollable` is ready now (wasmtime-wasi's `ready`: polls its
    /// future once).
    fn is_ready(&mut self, pollable: &Resource<DynPollable>) -> wasmtime::Result<bool> {
        let handle = Resource::new_borrow(pollable.rep());
        poll::HostPollable::ready(&mut *self.0, handle)
    }
}

impl poll::Host for NonBlockingPoll<'_> {
    fn poll(&mut self, pollables: Vec<Resource<DynPollable>>) -> wasmtime::Result<Vec<u32>> {
        if pollables.is_empty() {
            return Err(wasmtime::format_err!("empty poll list"));
        }
        let mut ready = Vec::new();
        for (index, pollable) in pollables.iter().enumerate() {
            if self.is_ready(pollable)? {
                ready.push(u32::try_from(index)?);
            }
        }
        if ready.is_empty() {
            let what = match pollables.len() {
                1 => "a pollable that is not ready".to_string(),
                n => format!("{n} pollables, none of them ready"),
            };
            return Err(BlockingCall { call: "wasi:io/poll.poll", what }.into());
        }
        Ok(ready)
    }
}

impl poll::HostPollable for NonBlockingPoll<'_> {
    fn ready(&mut self, pollable: Resource<DynPollable>) -> wasmtime::Result<bool> {
        self.is_ready(&pollable)
    }

    fn block(&mut self, pollable: Resource<DynPollable>) -> wasmtime::Result<()> {
        if self.is_ready(&pollable)? {
            return Ok(());
        }
        Err(BlockingCall { call: "wasi:io/poll.pollable.block", what: "a pollable that is not ready".to_string() }
            .into())
    }

    fn drop(&mut self, pollable: Resource<DynPollable>) -> wasmtime::Result<()> {
        poll::HostPollable::drop(&mut *self.0, pollable)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sandbox::random_seed;

    fn view<'a>(
        table: &'a mut ResourceTable,
        wall_anchor: &'a mut Option<(Duration, u64)>,
        now_ns: u64,
    ) -> CycleClocksView<'a> {
        CycleClocksView { table, now_ns, wall_anchor }
    }

    #[test]
    fn the_monotonic_clock_is_the_cycles_time_and_due_waits_are_ready_at_once() {
        let mut table = ResourceTable::new();
        let mut wall = None;
        let mut clocks = view(&mut table, &mut wall, 7_000_000);
        assert_eq!(monotonic_clock::Host::now(&mut clocks).unwrap(), 7_000_000);
        let zero = monotonic_clock::Host::subscribe_duration(&mut clocks, 0).unwrap();
        let past = monotonic_clock::Host::subscribe_instant(&mut clocks, 6_000_000).unwrap();
        let later = monotonic_clock::Host::subscribe_duration(&mut clocks, 1).unwrap();
        let future = monotonic_clock::Host::subscribe_instant(&mut clocks, 7_000_001).unwrap();
        let mut io = NonBlockingPoll(&mut table);
        assert!(poll::HostPollable::ready(&mut io, Resource::new_borrow(zero.rep())).unwrap());
        assert!(poll::HostPollable::ready(&mut io, Resource::new_borrow(past.rep())).unwrap());
        assert!(!poll::HostPollable::ready(&mut io, Resource::new_borrow(later.rep())).unwrap());
        assert!(!poll::HostPollable::ready(&mut io, Resource::new_borrow(future.rep())).unwrap());
        poll::HostPollable::block(&mut io, Resource::new_borrow(zero.rep())).unwrap();
        let list = |r: &[&Resource<DynPollable>]| r.iter().map(|p| Resource::new_borrow(p.rep())).collect();
        assert_eq!(poll::Host::poll(&mut io, list(&[&later, &zero, &future])).unwrap(), vec![1]);
        for pollable in [zero, past, later, future] {
            poll::HostPollable::drop(&mut io, pollable).unwrap();
        }
    }

    #[test]
    fn waiting_on_what_is_not_ready_is_refused_not_blocked() {
        let mut table = ResourceTable::new();
        let mut wall = None;
        let mut clocks = view(&mut table, &mut wall, 0);
        let sleep = monotonic_clock::Host::subscribe_duration(&mut clocks, 10_000_000_000).unwrap();
        let far = monotonic_clock::Host::subscribe_instant(&mut clocks, u64::MAX).unwrap();
        let mut io = NonBlockingPoll(&mut table);
        let started = std::time::Instant::now();
        let err = poll::HostPollable::block(&mut io, Resource::new_borrow(sleep.rep())).unwrap_err();
        assert_eq!(
            err.downcast_ref::<BlockingCall>(),
            Some(&BlockingCall { call: "wasi:io/poll.pollable.block", what: "a pollable that is not ready".into() })
        );
        let both = vec![Resource::new_borrow(sleep.rep()), Resource::new_borrow(far.rep())];
        let err = poll::Host::poll(&mut io, both).unwrap_err().to_string();
        assert_eq!(
            err,
            "blocking calls are not allowed: wasi:io/poll.poll would wait for 2 pollables, none of them ready \
             (a sleep, a timer or a read)"
        );
        assert!(poll::Host::poll(&mut io, Vec::new()).is_err());
        assert!(started.elapsed() < Duration::from_secs(1), "nothing waited");
    }

    #[test]
    fn the_wall_clock_stands_still_within_a_call_and_moves_with_the_cycles_time() {
        let mut table = ResourceTable::new();
        let mut wall = None;
        let mut clocks = view(&mut table, &mut wall, 0);
        let first = wall_clock::Host::now(&mut clocks).unwrap();
        std::thread::sleep(Duration::from_millis(2));
        let second = wall_clock::Host::now(&mut clocks).unwrap();
        assert_eq!((first.seconds, first.nanoseconds), (second.seconds, second.nanoseconds));
        let unix = SystemTime::now().duration_since(SystemTime::UNIX_EPOCH).unwrap().as_secs();
        assert!(first.seconds.abs_diff(unix) <= 1);
        // A later call sees the anchor moved on by the cycle's time, not
        // by the wall time that passed: ten simulated seconds later, ten
        // seconds later, however fast they went by.
        let mut clocks = view(&mut table, &mut wall, 10_000_000_000);
        let later = wall_clock::Host::now(&mut clocks).unwrap();
        let ns = |d: &wall_clock::Datetime| u128::from(d.seconds) * 1_000_000_000 + u128::from(d.nanoseconds);
        assert_eq!(ns(&later) - ns(&first), 10_000_000_000);
    }

    #[test]
    fn seeds_follow_the_component_name() {
        assert_eq!(random_seed("a"), random_seed("a"));
        assert_ne!(random_seed("a"), random_seed("b"));
    }
}
