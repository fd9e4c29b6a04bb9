//! The log into the recording (`/subsume/log`, `foxglove.Log`): a
//! `tracing` layer the binary installs once, which forwards info-and-above
//! lines to the recording in progress, if there is one.
//!
//! Invariants: logging never blocks: a full recording queue drops the line
//! and counts it, like any other event. A line's time is read from the
//! recording's time line ([`super::Timeline`], never the wall clock) while
//! the recording is held, so the lines reach the writer in the order of
//! their times.

use std::sync::Mutex;

use tracing_subscriber::layer::Context;

use crate::logfields::LogFields;

use super::{Event, Sink, schema};

/// The recording in progress, if any.
static SINK: Mutex<Option<Sink>> = Mutex::new(None);

/// Held by the unit tests that start a recording: the recording in
/// progress is one per process.
#[cfg(test)]
pub(crate) static TEST_RECORDING: Mutex<()> = Mutex::new(());

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
        // A line naming another user's work is not hers to read.
        if let (Some(only), Some(owner)) = (&sink.for_owner, &fields.owner)
            && **only != **owner
        {
            return;
        }
        let unix_ns = sink.timeline.now_unix_ns();
        let name = fields.component.unwrap_or_else(|| metadata.target().to_string());
        sink.send(Event::Log {
            unix_ns,
            level: schema::log_level(metadata.level()),
            name,
            message: fields.message + &fields.extra,
        });
    }
}

#[cfg(test)]
mod tests {
    use tracing_subscriber::layer::SubscriberExt as _;

    use super::*;
    use crate::contract::{Value, ValueKind};
    use crate::record::{ComponentLayout, Layout, PortLayout, RecordOptions, Recorder, Timeline};
    use crate::runtime::control_loop::{self, Clock, Shutdown};
    use crate::runtime::lockstep::Pace;
    use crate::runtime::{CallError, Component, Graph, Outbox};

    /// Logs the graph time of each tick (and emits it).
    struct Talker;

    impl Component for Talker {
        fn tick(&mut self, now_ns: u64, out: &mut Outbox) -> Result<(), CallError> {
            tracing::info!(component = "talker", "tick at {now_ns}");
            out.push((0, Value::Scalar(now_ns as f64)));
            Ok(())
        }
    }

    /// A log line is stamped on the recording's time line, the time of the
    /// call that wrote it, not by the wall clock: ten simulated seconds in
    /// lock-step (a few real milliseconds) give ten lines a simulated
    /// second apart, each at its tick's log time. Stamped by the wall
    /// clock, they were milliseconds apart, off the other channels' times,
    /// and out of log-time order whenever the wall clock was set back
    /// during the run.
    #[test]
    fn log_lines_are_stamped_on_the_recordings_time_line() {
        let _alone = TEST_RECORDING.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("talk.mcap");
        let clock = Clock::simulated(Pace::Lockstep);
        let epoch = 1_700_000_000_000_000_000;
        let layout = Layout {
            worlds: Vec::new(),
            robot: "talk".into(),
            components: vec![ComponentLayout {
                name: "talker".into(),
                inputs: vec![],
                outputs: vec![PortLayout { name: "t".into(), kind: ValueKind::Scalar }],
            }],
            about: Default::default(),
        };
        let recorder =
            Recorder::start(&RecordOptions::new(path.clone()), layout, Timeline::new(epoch, clock.clone())).unwrap();
        let mut graph = Graph::new();
        graph.add("talker", Box::new(Talker), 1, 1.0, 0);
        graph.set_tap(recorder.tap());
        let subscriber = tracing_subscriber::registry().with(layer());
        tracing::subscriber::with_default(subscriber, || {
            control_loop::run(&mut graph, &clock, &Shutdown::new(), Some(9_500_000_000));
        });
        graph.take_tap();
        recorder.finish().unwrap();

        let bytes = std::fs::read(&path).unwrap();
        let (mut ticks, mut lines) = (Vec::new(), Vec::new());
        for message in mcap::MessageStream::new(&bytes).unwrap() {
            let message = message.unwrap();
            let json: serde_json::Value = serde_json::from_slice(&message.data).unwrap();
            match message.channel.topic.as_str() {
                "/talker/t" => ticks.push(message.log_time),
                "/subsume/log" if json["name"] == "talker" => {
                    let said = json["message"].as_str().unwrap().to_string();
                    lines.push((message.log_time, said));
                }
                _ => {}
            }
        }
        assert_eq!(ticks.len(), 10, "{ticks:?}");
        let expected: Vec<(u64, String)> = ticks.iter().map(|&t| (t, format!("tick at {}", t - epoch))).collect();
        assert_eq!(lines, expected);
        assert_eq!(ticks.last().map(|t| t - epoch), Some(9_000_000_000));
    }

    /// A recording handed to one user (a lab experiment's, to its
    /// submitter) leaves out the lines that name another user's work
    /// (their `owner` field); her own lines and the host's stay.
    #[test]
    fn a_recording_for_one_user_leaves_out_lines_naming_another_users_work() {
        let _alone = TEST_RECORDING.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("hers.mcap");
        let layout =
            Layout { worlds: Vec::new(), robot: "r".into(), components: Vec::new(), about: Default::default() };
        let options = RecordOptions { for_owner: Some("ana".into()), ..RecordOptions::new(path.clone()) };
        let clock = Clock::simulated(Pace::Lockstep);
        let recorder = Recorder::start(&options, layout, Timeline::new(1_000, clock)).unwrap();
        let subscriber = tracing_subscriber::registry().with(layer());
        tracing::subscriber::with_default(subscriber, || {
            tracing::info!(owner = "ben", "component 'ben/secret' uploaded by ben");
            tracing::info!(owner = "ana", "component 'ana/mine' uploaded by ana");
            tracing::info!("the host's own line");
        });
        recorder.finish().unwrap();
        let bytes = std::fs::read(&path).unwrap();
        let mut said = Vec::new();
        for message in mcap::MessageStream::new(&bytes).unwrap() {
            let message = message.unwrap();
            if message.channel.topic == "/subsume/log" {
                let json: serde_json::Value = serde_json::from_slice(&message.data).unwrap();
                said.push(json["message"].as_str().unwrap().to_string());
            }
        }
        let said = said.join("\n");
        assert!(!said.contains("ben/secret"), "{said}");
        assert!(said.contains("ana/mine") && said.contains("the host's own line"), "{said}");
    }
}
