//! The log into the recording (`/subsume/log`, `foxglove.Log`): a
//! `tracing` layer the binary installs once, which forwards info-and-above
//! lines to the recording in progress, if there is one.
//!
//! Invariant: logging never blocks: a full recording queue drops the line
//! and counts it, like any other event.

use std::sync::Mutex;

use tracing_subscriber::layer::Context;

use crate::logfields::LogFields;

use super::{Event, Sink, schema};

/// The recording in progress, if any.
static SINK: Mutex<Option<Sink>> = Mutex::new(None);

pub(super) fn install(sink: Sink) {
    if let Ok(mut slot) = SINK.lock() {
        *slot = Some(sink);
    }
}

pub(super) fn uninstall() {
    if let Ok(mut slot) = SINK.lock() {
        *slot = None;
    }
}

/// The `tracing` layer that feeds the recording in progress.
pub struct RecordLogLayer;

/// A layer for the binary's subscriber.
pub fn layer() -> RecordLogLayer {
    RecordLogLayer
}

impl<S: tracing::Subscriber> tracing_subscriber::Layer<S> for RecordLogLayer {
    fn on_event(&self, event: &tracing::Event<'_>, _ctx: Context<'_, S>) {
        let metadata = event.metadata();
        if *metadata.level() > tracing::Level::INFO || metadata.target().starts_with("wasmtime") {
            return;
        }
        let Ok(slot) = SINK.lock() else { return };
        let Some(sink) = slot.as_ref() else { return };
        let fields = LogFields::of(event);
        let unix_ns = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map(|d| d.as_nanos() as u64)
            .unwrap_or(0);
        let name = fields.component.unwrap_or_else(|| metadata.target().to_string());
        sink.send(Event::Log {
            unix_ns,
            level: schema::log_level(metadata.level()),
            name,
            message: fields.message + &fields.extra,
        });
    }
}
