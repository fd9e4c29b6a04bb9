//! The two ways data crosses between the control loop and Zenoh, both
//! bounded and never blocking the loop:
//! - [`Outlet`]: the loop hands a payload to a sender thread through a
//!   bounded queue (`try_send`; when full the message is dropped and
//!   counted); the thread puts it on its key.
//! - [`Inlet`]: Zenoh's callback decodes each sample on Zenoh's own
//!   threads (malformed payloads are counted and dropped there), queues the
//!   result (bounded; full: dropped and counted) and wakes the loop; the
//!   component drains the queue in `poll`.

use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::sync::mpsc::{self, Receiver, SyncSender, TrySendError};
use std::thread::JoinHandle;

use zenoh::Wait;

use super::session::{BridgeStats, Shared, unix_ns};
use crate::builtin::BuiltinError;
use crate::runtime::control_loop::Waker;

/// Messages waiting between the loop and Zenoh, each way: a fast peer or a
/// stalled network cannot grow the host's memory; past it, messages are
/// dropped and counted.
pub const QUEUE_DEPTH: usize = 64;

/// Largest payload a peer may send us: bigger samples are malformed.
pub const MAX_PAYLOAD_BYTES: usize = 256 * 1024;

struct Message {
    payload: Vec<u8>,
    attachment: Option<Vec<u8>>,
}

/// The loop's side of a publication.
pub struct Outlet {
    tx: Option<SyncSender<Message>>,
    thread: Option<JoinHandle<()>>,
    pub stats: Arc<BridgeStats>,
}

impl Outlet {
    /// A publisher on `key` and its sender thread.
    pub fn new(shared: Arc<Shared>, key: String, stats: Arc<BridgeStats>) -> Result<Outlet, BuiltinError> {
        let publisher = shared
            .session
            .declare_publisher(key.clone())
            .wait()
            .map_err(|why| BuiltinError::Refused(format!("zenoh publisher on '{key}': {why}")))?;
        let (tx, rx) = mpsc::sync_channel::<Message>(QUEUE_DEPTH);
        let counters = stats.clone();
        let thread = std::thread::Builder::new()
            .name("zenoh-out".into())
            .spawn(move || {
                let _keep = shared;
                for message in rx {
                    let put = publisher.put(message.payload);
                    let put = match message.attachment {
                        Some(a) => put.attachment(a),
                        None => put,
                    };
                    match put.wait() {
                        Ok(()) => counters.messages_out.fetch_add(1, Ordering::Relaxed),
                        Err(_) => counters.dropped.fetch_add(1, Ordering::Relaxed),
                    };
                }
            })
            .map_err(|e| BuiltinError::io("zenoh sender thread", e))?;
        Ok(Outlet { tx: Some(tx), thread: Some(thread), stats })
    }

    /// Queues a message without waiting; a full queue drops it (counted).
    pub fn send(&self, payload: Vec<u8>, attachment: Option<Vec<u8>>) {
        if let Some(tx) = &self.tx
            && let Err(TrySendError::Full(_) | TrySendError::Disconnected(_)) =
                tx.try_send(Message { payload, attachment })
        {
            self.stats.dropped.fetch_add(1, Ordering::Relaxed);
        }
    }

    /// Sends `last` (waiting for room: this is the end), then closes the
    /// publisher once everything queued is out.
    pub fn finish(&mut self, last: Option<(Vec<u8>, Option<Vec<u8>>)>) {
        if let Some(tx) = self.tx.take() {
            if let Some((payload, attachment)) = last {
                let _ = tx.send(Message { payload, attachment });
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
