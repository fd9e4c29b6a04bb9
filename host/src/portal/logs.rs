//! Recent log lines for the portal: a `tracing` layer keeps the newest lines
//! in a ring and broadcasts each new one to live viewers.
//!
//! Invariant: logging never blocks on a viewer; a slow viewer misses lines
//! (the broadcast channel lags), the ring and the host carry on.

use std::collections::VecDeque;
use std::sync::{Arc, Mutex};

use serde::Serialize;
use tracing_subscriber::layer::Context;

use crate::logfields::LogFields;

/// Lines kept for a viewer who joins late.
pub const LOG_RING_LINES: usize = 500;
/// Lines waiting for a slow viewer before it skips ahead.
pub const LOG_BROADCAST_DEPTH: usize = 256;
/// Longest line kept: a guest's log line is capped by the sandbox already.
pub const MAX_LOG_LINE_BYTES: usize = 2048;

#[derive(Clone, Debug, Serialize, schemars::JsonSchema)]
pub struct LogLine {
    /// Seconds since the Unix epoch.
    pub time: f64,
    pub level: String,
    pub component: Option<String>,
    pub message: String,
    /// The users whose work the line names: the one its `owner` field
    /// names (an upload, an activation), or, for a line of a component,
    /// whoever's set runs (`logfields::running_owners`). Shown only to those
    /// who may see the work of each (`store::access`).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub owners: Vec<String>,
}

impl LogLine {
    /// Whether `reader` may see this line: it names no one's work, or
    /// only work `reader` may see.
    pub fn visible_to(&self, reader: &crate::store::users::Principal, access: &crate::store::access::Access) -> bool {
        self.owners.iter().all(|owner| access.may_see(reader, owner))
    }
}

/// The newest lines and a broadcast of new ones.
#[derive(Debug)]
pub struct LogRing {
    lines: Mutex<VecDeque<LogLine>>,
    sender: tokio::sync::broadcast::Sender<LogLine>,
}

impl LogRing {
    pub fn new() -> Arc<LogRing> {
        let (sender, _) = tokio::sync::broadcast::channel(LOG_BROADCAST_DEPTH);
        Arc::new(LogRing { lines: Mutex::new(VecDeque::with_capacity(LOG_RING_LINES)), sender })
    }

    pub fn push(&self, line: LogLine) {
        if let Ok(mut lines) = self.lines.lock() {
            if lines.len() == LOG_RING_LINES {
                lines.pop_front();
            }
            lines.push_back(line.clone());
        }
        let _ = self.sender.send(line);
    }

    /// The newest lines, oldest first.
    pub fn recent(&self) -> Vec<LogLine> {
        self.lines.lock().map(|l| l.iter().cloned().collect()).unwrap_or_default()
    }

    pub fn subscribe(&self) -> tokio::sync::broadcast::Receiver<LogLine> {
        self.sender.subscribe()
    }

    /// A `tracing` layer that feeds this ring (info and above).
    pub fn layer(self: &Arc<Self>) -> RingLayer {
        RingLayer(self.clone())
    }
}

pub struct RingLayer(Arc<LogRing>);

impl<S: tracing::Subscriber> tracing_subscriber::Layer<S> for RingLayer {
    fn on_event(&self, event: &tracing::Event<'_>, _ctx: Context<'_, S>) {
        let level = *event.metadata().level();
        if level > tracing::Level::INFO || event.metadata().target().starts_with("wasmtime") {
            return;
        }
        let fields = LogFields::of(event);
        let mut message = fields.message + &fields.extra;
        if message.len() > MAX_LOG_LINE_BYTES {
            let mut cut = MAX_LOG_LINE_BYTES;
            while !message.is_char_boundary(cut) {
                cut -= 1;
            }
            message.truncate(cut);
        }
        let time = crate::walltime::unix_now_s_f64();
        let owners = match (fields.owner, &fields.component) {
            (Some(owner), _) => vec![owner],
            (None, Some(_)) => crate::logfields::running_owners(),
            (None, None) => Vec::new(),
        };
        let component = fields.component;
        self.0.push(LogLine { time, level: level.as_str().to_lowercase(), component, message, owners });
    }
}
