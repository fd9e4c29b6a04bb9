//! The two ways data crosses between the control loop and Zenoh, both
//! bounded and never blocking the loop:
//! - [`Outlet`]: a small payload, when nothing waits in the queue, is put
//!   by the loop itself if the session's puts give up at once on a
//!   congested network (`session::loop_puts`: then a put never waits for
//!   the network, and skipping the hand-off saves a thread wake-up per
//!   message); otherwise the loop hands it to a sender thread through a
//!   bounded queue (`try_send`; when full the message is dropped and
//!   counted), which puts it on its key. Messages go out in the order they
//!   were sent either way. Its [`Gate`] lets another thread put a final
//!   message past the queue (`runtime::halt`), after which nothing goes
//!   out; the loop never waits for it (`try_lock`). [`Gate::stop_now`]
//!   (the stall watchdog's) puts a message past the queue and drops what
//!   was queued before it; later messages still go out.
//! - [`Inlet`]: Zenoh's callback decodes each sample on Zenoh's own
//!   threads (malformed payloads are counted and dropped there), queues the
//!   result (bounded; full: dropped and counted) and wakes the loop; the
//!   component drains the queue in `poll`.

use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::mpsc::{self, Receiver, SyncSender, TrySendError};
use std::sync::{Arc, Mutex, PoisonError, TryLockError};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use zenoh::Wait;

use super::session::{BridgeStats, Shared, unix_ns};
use crate::builtin::BuiltinError;
use crate::runtime::StopOutcome;
use crate::runtime::control_loop::Waker;
use crate::runtime::halt::lock_within;

/// Messages waiting between the loop and Zenoh, each way: a fast peer or a
/// stalled network cannot grow the host's memory; past it, messages are
/// dropped and counted.
pub const QUEUE_DEPTH: usize = 64;

/// Largest payload the loop puts itself (`Outlet::send`): far below one
/// Zenoh batch (64 KiB by default), so it is never fragmented, and a put
/// that finds no free batch drops it at once instead of waiting. Larger
/// payloads go through the sender thread.
pub const MAX_LOOP_PUT_BYTES: usize = 16 * 1024;

/// Largest payload a peer may send us: bigger samples are malformed.
pub const MAX_PAYLOAD_BYTES: usize = 256 * 1024;

/// Makes the attachment of each publication at the moment it is put (so
/// sequence numbers follow the order on the wire).
pub type Stamp = Box<dyn Fn() -> Vec<u8> + Send + Sync>;

/// A publisher and whether it has sent its final message: the sender
/// thread and a halt from any other thread take turns through its lock, so
/// nothing goes out after the final message.
pub struct Gate {
    inner: Mutex<GateState>,
    /// Bumped (under the lock) by every [`Gate::stop_now`]: a message the
    /// loop queued before it carries an older number and is dropped, so no
    /// stale command follows the stop.
    generation: AtomicU64,
    stamp: Option<Stamp>,
    stats: Arc<BridgeStats>,
}

struct GateState {
    publisher: zenoh::pubsub::Publisher<'static>,
    halted: bool,
}

impl Gate {
    /// Puts `payload`, queued in `generation`, unless the gate was halted
    /// or stopped since.
    fn put(&self, generation: u64, payload: Vec<u8>) {
        let state = self.inner.lock().unwrap_or_else(PoisonError::into_inner);
        if state.halted || generation != self.generation.load(Ordering::Acquire) {
            self.stats.dropped.fetch_add(1, Ordering::Relaxed);
            return;
        }
        self.put_locked(&state, payload);
    }

    /// Puts `payload` unless the gate was halted, or hands it back when
    /// another thread holds the gate (a halt in progress): never waits.
    fn try_put(&self, payload: Vec<u8>) -> Result<(), Vec<u8>> {
        let state = match self.inner.try_lock() {
            Ok(state) => state,
            Err(TryLockError::Poisoned(poisoned)) => poisoned.into_inner(),
            Err(TryLockError::WouldBlock) => return Err(payload),
        };
        if state.halted {
            self.stats.dropped.fetch_add(1, Ordering::Relaxed);
            return Ok(());
        }
        self.put_locked(&state, payload);
        Ok(())
    }

    fn put_locked(&self, state: &GateState, payload: Vec<u8>) -> bool {
        let put = state.publisher.put(payload);
        let put = match &self.stamp {
            Some(stamp) => put.attachment(stamp()),
            None => put,
        };
        let sent = put.wait().is_ok();
        if sent {
            self.stats.messages_out.fetch_add(1, Ordering::Relaxed);
        } else {
            self.stats.dropped.fetch_add(1, Ordering::Relaxed);
        }
        sent
    }

    /// Puts `payload` now, past the queue, and drops what the loop queued
    /// before it (the stall watchdog's stop); what is sent afterwards still
    /// goes out. Waits at most `wait` for a put in progress.
    pub fn stop_now(&self, payload: Vec<u8>, wait: Duration) -> StopOutcome {
        let Some(state) = lock_within(&self.inner, Instant::now() + wait) else {
            return StopOutcome::Failed(format!("the publisher stayed busy for {} ms", wait.as_millis()));
        };
        if state.halted {
            return StopOutcome::Closed;
        }
        self.generation.fetch_add(1, Ordering::AcqRel);
        if self.put_locked(&state, payload) {
            StopOutcome::Sent
        } else {
            StopOutcome::Failed("zenoh refused the put".into())
        }
    }

    /// Puts `payload` now, past the queue, as the last message of this
    /// publication: nothing queued before or after it goes out. Waits at
    /// most `wait` for a put in progress.
    pub fn halt(&self, payload: Vec<u8>, wait: Duration) -> StopOutcome {
        let Some(mut state) = lock_within(&self.inner, Instant::now() + wait) else {
            return StopOutcome::Failed(format!("the publisher stayed busy for {} ms", wait.as_millis()));
        };
        if state.halted {
            return StopOutcome::Closed;
        }
        state.halted = true;
        if self.put_locked(&state, payload) {
            StopOutcome::Sent
        } else {
            StopOutcome::Failed("zenoh refused the put".into())
        }
    }
}

/// The loop's side of a publication.
pub struct Outlet {
    /// Payloads with the gate's generation when they were sent.
    tx: Option<SyncSender<(u64, Vec<u8>)>>,
    thread: Option<JoinHandle<()>>,
    gate: Arc<Gate>,
    /// Messages handed to the sender thread and not yet put: the loop puts
    /// itself only when none are, so the order on the wire is kept.
    queued: Arc<AtomicUsize>,
    /// Whether the loop may put small payloads itself (`session::loop_puts`).
    loop_puts: bool,
    pub stats: Arc<BridgeStats>,
}

impl Outlet {
    /// A publisher on `key` and its sender thread; `stamp`, when given,
    /// makes each publication's attachment.
    pub fn new(
        shared: Arc<Shared>,
        key: String,
        stats: Arc<BridgeStats>,
        stamp: Option<Stamp>,
    ) -> Result<Outlet, BuiltinError> {
        let publisher = shared
            .session
            .declare_publisher(key.clone())
            .wait()
            .map_err(|why| BuiltinError::Refused(format!("zenoh publisher on '{key}': {why}")))?;
        let gate = Arc::new(Gate {
            inner: Mutex::new(GateState { publisher, halted: false }),
            generation: AtomicU64::new(0),
            stamp,
            stats: stats.clone(),
        });
        let (tx, rx) = mpsc::sync_channel::<(u64, Vec<u8>)>(QUEUE_DEPTH);
        let thread_gate = gate.clone();
        let queued = Arc::new(AtomicUsize::new(0));
        let thread_queued = queued.clone();
        let loop_puts = shared.loop_puts;
        let thread = std::thread::Builder::new()
            .name("zenoh-out".into())
            .spawn(move || {
                let _keep = shared;
                for (generation, payload) in rx {
                    thread_gate.put(generation, payload);
                    thread_queued.fetch_sub(1, Ordering::AcqRel);
                }
            })
            .map_err(|e| BuiltinError::io("zenoh sender thread", e))?;
        Ok(Outlet { tx: Some(tx), thread: Some(thread), gate, queued, loop_puts, stats })
    }

    /// The publication's gate, for a halt from another thread.
    pub fn gate(&self) -> Arc<Gate> {
        self.gate.clone()
    }

    /// Sends a message without waiting: puts it at once when the loop may
    /// (see the module doc), else queues it; a full queue drops it (counted).
    pub fn send(&self, payload: Vec<u8>) {
        let Some(tx) = &self.tx else { return };
        let payload =
            if self.loop_puts && payload.len() <= MAX_LOOP_PUT_BYTES && self.queued.load(Ordering::Acquire) == 0 {
                match self.gate.try_put(payload) {
                    Ok(()) => return,
                    Err(payload) => payload,
                }
            } else {
                payload
            };
        self.queued.fetch_add(1, Ordering::AcqRel);
        let generation = self.gate.generation.load(Ordering::Acquire);
        if let Err(TrySendError::Full(_) | TrySendError::Disconnected(_)) = tx.try_send((generation, payload)) {
            self.queued.fetch_sub(1, Ordering::AcqRel);
            self.stats.dropped.fetch_add(1, Ordering::Relaxed);
        }
    }

    /// Messages handed to the sender thread and not yet put.
    pub fn queued(&self) -> usize {
        self.queued.load(Ordering::Acquire)
    }

    /// Sends `last` (waiting for room: this is the end), then closes the
    /// publisher once everything queued is out. After a halt nothing more
    /// goes out.
    pub fn finish(&mut self, last: Option<Vec<u8>>) {
        if let Some(tx) = self.tx.take() {
            if let Some(payload) = last {
                self.queued.fetch_add(1, Ordering::AcqRel);
                let _ = tx.send((self.gate.generation.load(Ordering::Acquire), payload));
            }
            drop(tx);
        }
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
    }
}

impl Drop for Outlet {
    fn drop(&mut self) {
        self.finish(None);
    }
}

/// The loop's side of a subscription: decoded values of type `T`.
pub struct Inlet<T> {
    rx: Receiver<T>,
    _subscriber: zenoh::pubsub::Subscriber<()>,
    _shared: Arc<Shared>,
    pub stats: Arc<BridgeStats>,
}

impl<T: Send + 'static> Inlet<T> {
    /// A subscriber on `key` whose samples `decode` turns into `T` (an
    /// error: malformed, counted and dropped).
    pub fn new(
        shared: Arc<Shared>,
        key: String,
        stats: Arc<BridgeStats>,
        waker: Waker,
        decode: impl Fn(&[u8], Option<&[u8]>) -> Result<T, String> + Send + Sync + 'static,
    ) -> Result<Inlet<T>, BuiltinError> {
        let (tx, rx) = mpsc::sync_channel::<T>(QUEUE_DEPTH);
        let counters = stats.clone();
        let subscriber = shared
            .session
            .declare_subscriber(key.clone())
            .callback(move |sample: zenoh::sample::Sample| {
                counters.messages_in.fetch_add(1, Ordering::Relaxed);
                counters.last_seen_ns.store(unix_ns(), Ordering::Relaxed);
                let payload = sample.payload();
                if payload.len() > MAX_PAYLOAD_BYTES {
                    counters.malformed(format!("payload of {} bytes exceeds {MAX_PAYLOAD_BYTES}", payload.len()));
                    return;
                }
                let bytes = payload.to_bytes();
                let attachment = sample.attachment().map(|a| a.to_bytes());
                match decode(&bytes, attachment.as_deref()) {
                    Ok(value) => match tx.try_send(value) {
                        Ok(()) => waker.wake(),
                        Err(_) => {
                            counters.dropped.fetch_add(1, Ordering::Relaxed);
                        }
                    },
                    Err(why) => counters.malformed(why),
                }
            })
            .wait()
            .map_err(|why| BuiltinError::Refused(format!("zenoh subscriber on '{key}': {why}")))?;
        Ok(Inlet { rx, _subscriber: subscriber, _shared: shared, stats })
    }

    /// Everything that arrived since the last call.
    pub fn drain(&self) -> impl Iterator<Item = T> + '_ {
        self.rx.try_iter()
    }
}

#[cfg(test)]
mod tests {
    use std::sync::mpsc::RecvTimeoutError;

    use super::*;
    use crate::bridge::session::{self, SessionSettings};

    fn free_port() -> u16 {
        std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port()
    }

    /// A session of its own (the registry shares sessions by settings).
    fn lone_session() -> Arc<Shared> {
        let listen = vec![format!("tcp/127.0.0.1:{}", free_port())];
        session::session(&SessionSettings { connect: vec![], listen, config: None, max_message_bytes: None }).unwrap()
    }

    #[test]
    fn small_messages_are_put_by_the_sending_thread_itself() {
        let shared = lone_session();
        assert!(shared.loop_puts);
        let stats = Arc::new(BridgeStats::default());
        let outlet = Outlet::new(shared, "link-test/direct".into(), stats.clone(), None).unwrap();
        for n in 1..=20u64 {
            outlet.send(vec![n as u8; 64]);
            // Put before `send` returned: no hand-off to the sender thread.
            assert_eq!(stats.messages_out.load(Ordering::Relaxed), n);
            assert_eq!(outlet.queued(), 0);
        }
    }

    #[test]
    fn a_halt_holding_the_gate_never_blocks_send_and_the_message_is_dropped_after_it() {
        let shared = lone_session();
        let stats = Arc::new(BridgeStats::default());
        let outlet = Outlet::new(shared, "link-test/halt".into(), stats.clone(), None).unwrap();
        let gate = outlet.gate();
        // Another thread (a halt) holds the gate: `send` must return at once.
        let mut held = gate.inner.lock().unwrap();
        let (done_tx, done_rx) = mpsc::channel();
        let sender = std::thread::spawn(move || {
            outlet.send(vec![1; 64]);
            done_tx.send(outlet.queued()).unwrap();
            outlet
        });
        let queued = done_rx.recv_timeout(Duration::from_secs(10));
        assert!(!matches!(queued, Err(RecvTimeoutError::Timeout)), "send waited for the gate");
        assert_eq!(queued.unwrap(), 1, "the message waits for the sender thread");
        // The halt ends the publication (as `Gate::halt` does under the
        // lock): the queued message never goes out.
        held.halted = true;
        assert!(gate.put_locked(&held, vec![0; 8]));
        drop(held);
        assert_eq!(gate.halt(vec![0; 8], Duration::from_secs(5)), StopOutcome::Closed);
        let mut outlet = sender.join().unwrap();
        outlet.finish(None);
        assert_eq!(outlet.queued(), 0);
        assert_eq!(stats.messages_out.load(Ordering::Relaxed), 1, "only the halt's message went out");
        assert_eq!(stats.dropped.load(Ordering::Relaxed), 1);
    }

    #[test]
    fn a_stop_drops_what_was_queued_before_it_and_what_follows_goes_out() {
        let shared = lone_session();
        let stats = Arc::new(BridgeStats::default());
        let mut outlet = Outlet::new(shared, "link-test/stop".into(), stats.clone(), None).unwrap();
        let gate = outlet.gate();
        // The sender thread waits on the gate with three queued commands
        // (large: the loop does not put those itself).
        let held = gate.inner.lock().unwrap();
        for n in 0..3u8 {
            outlet.send(vec![n; MAX_LOOP_PUT_BYTES + 1]);
        }
        assert_eq!(outlet.queued(), 3);
        // The stop, as `stop_now` does it under the lock.
        gate.generation.fetch_add(1, Ordering::AcqRel);
        assert!(gate.put_locked(&held, vec![0; 8]));
        drop(held);
        let deadline = Instant::now() + Duration::from_secs(10);
        while outlet.queued() > 0 {
            assert!(Instant::now() < deadline, "the sender thread never drained");
            std::thread::sleep(Duration::from_millis(5));
        }
        assert_eq!(stats.messages_out.load(Ordering::Relaxed), 1, "a stale command went out after the stop");
        assert_eq!(stats.dropped.load(Ordering::Relaxed), 3);
        // `stop_now` itself: sent, and what follows still goes out (both ways).
        assert_eq!(gate.stop_now(vec![0; 8], Duration::from_secs(5)), StopOutcome::Sent);
        outlet.send(vec![1; 64]);
        outlet.send(vec![2; MAX_LOOP_PUT_BYTES + 1]);
        while outlet.queued() > 0 {
            assert!(Instant::now() < deadline, "the sender thread never drained");
            std::thread::sleep(Duration::from_millis(5));
        }
        assert_eq!(stats.messages_out.load(Ordering::Relaxed), 4);
        // After the final message, a stop has nothing left to do.
        assert_eq!(gate.halt(vec![0; 8], Duration::from_secs(5)), StopOutcome::Sent);
        assert_eq!(gate.stop_now(vec![0; 8], Duration::from_secs(5)), StopOutcome::Closed);
        outlet.finish(None);
    }

    #[test]
    fn messages_arrive_in_the_order_sent_whichever_thread_puts_them() {
        let port = free_port();
        let endpoint = format!("tcp/127.0.0.1:{port}");
        let a = session::session(&SessionSettings {
            connect: vec![],
            listen: vec![endpoint.clone()],
            config: None,
            max_message_bytes: None,
        })
        .unwrap();
        let b = session::session(&SessionSettings {
            connect: vec![endpoint],
            listen: vec![],
            config: None,
            max_message_bytes: None,
        })
        .unwrap();
        let (tx, rx) = mpsc::channel::<Vec<u8>>();
        let _subscriber = b
            .session
            .declare_subscriber("link-test/order")
            .callback(move |sample| {
                let _ = tx.send(sample.payload().to_bytes().into_owned());
            })
            .wait()
            .unwrap();
        let stats = Arc::new(BridgeStats::default());
        let outlet = Outlet::new(a, "link-test/order".into(), stats.clone(), None).unwrap();
        // Wait for the peers to meet.
        let deadline = Instant::now() + Duration::from_secs(20);
        loop {
            assert!(Instant::now() < deadline, "the sessions never met");
            outlet.send(vec![0xff]);
            if rx.recv_timeout(Duration::from_millis(50)).is_ok() {
                break;
            }
        }
        std::thread::sleep(Duration::from_millis(100));
        while rx.try_recv().is_ok() {}
        // Bursts of a large payload (the sender thread) then small ones
        // (the loop puts them itself unless the large one is still queued).
        let mut sent = Vec::new();
        for burst in 0..20u8 {
            let mut large = vec![burst; MAX_LOOP_PUT_BYTES + 1];
            large[0] = 2 * burst;
            outlet.send(large);
            outlet.send(vec![2 * burst + 1; 16]);
            sent.extend([2 * burst, 2 * burst + 1]);
            std::thread::sleep(Duration::from_millis(5));
        }
        let mut got = Vec::new();
        while got.len() < sent.len() {
            match rx.recv_timeout(Duration::from_secs(5)) {
                Ok(payload) => got.push(payload[0]),
                Err(_) => break,
            }
        }
        // A congested put drops (counted); what arrives keeps its order.
        let dropped = stats.dropped.load(Ordering::Relaxed) as usize;
        assert_eq!(got.len() + dropped, sent.len(), "got {got:?}");
        assert!(got.windows(2).all(|w| w[0] < w[1]), "out of order: {got:?}");
    }
}
