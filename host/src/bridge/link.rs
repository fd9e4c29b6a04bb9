//! The two ways data crosses between the control loop and Zenoh, both
//! bounded and never blocking the loop:
//! - [`Outlet`]: the loop hands a payload to a sender thread through a
//!   bounded queue (`try_send`; when full the message is dropped and
//!   counted); the thread puts it on its key. Its [`Gate`] lets another
//!   thread put a final message past the queue (`runtime::halt`), after
//!   which nothing goes out.
//! - [`Inlet`]: Zenoh's callback decodes each sample on Zenoh's own
//!   threads (malformed payloads are counted and dropped there), queues the
//!   result (bounded; full: dropped and counted) and wakes the loop; the
//!   component drains the queue in `poll`.

use std::sync::atomic::Ordering;
use std::sync::mpsc::{self, Receiver, SyncSender, TrySendError};
use std::sync::{Arc, Mutex, PoisonError};
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
    stamp: Option<Stamp>,
    stats: Arc<BridgeStats>,
}

struct GateState {
    publisher: zenoh::pubsub::Publisher<'static>,
    halted: bool,
}

impl Gate {
    /// Puts `payload` unless the gate was halted.
    fn put(&self, payload: Vec<u8>) {
        let state = self.inner.lock().unwrap_or_else(PoisonError::into_inner);
        if state.halted {
            self.stats.dropped.fetch_add(1, Ordering::Relaxed);
            return;
        }
        self.put_locked(&state, payload);
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
    tx: Option<SyncSender<Vec<u8>>>,
    thread: Option<JoinHandle<()>>,
    gate: Arc<Gate>,
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
        let gate =
            Arc::new(Gate { inner: Mutex::new(GateState { publisher, halted: false }), stamp, stats: stats.clone() });
        let (tx, rx) = mpsc::sync_channel::<Vec<u8>>(QUEUE_DEPTH);
        let thread_gate = gate.clone();
        let thread = std::thread::Builder::new()
            .name("zenoh-out".into())
            .spawn(move || {
                let _keep = shared;
                for payload in rx {
                    thread_gate.put(payload);
                }
            })
            .map_err(|e| BuiltinError::io("zenoh sender thread", e))?;
        Ok(Outlet { tx: Some(tx), thread: Some(thread), gate, stats })
    }

    /// The publication's gate, for a halt from another thread.
    pub fn gate(&self) -> Arc<Gate> {
        self.gate.clone()
    }

    /// Queues a message without waiting; a full queue drops it (counted).
    pub fn send(&self, payload: Vec<u8>) {
        if let Some(tx) = &self.tx
            && let Err(TrySendError::Full(_) | TrySendError::Disconnected(_)) = tx.try_send(payload)
        {
            self.stats.dropped.fetch_add(1, Ordering::Relaxed);
        }
    }

    /// Sends `last` (waiting for room: this is the end), then closes the
    /// publisher once everything queued is out. After a halt nothing more
    /// goes out.
    pub fn finish(&mut self, last: Option<Vec<u8>>) {
        if let Some(tx) = self.tx.take() {
            if let Some(payload) = last {
                let _ = tx.send(payload);
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
