//! The writer thread's side of a recording: events -> JSON messages ->
//! MCAP chunks in the file, channels created as topics first appear,
//! periodic flushes and rotation by size.

use std::collections::{BTreeMap, HashMap};
use std::fs::File;
use std::io::{BufWriter, Seek, SeekFrom, Write};
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Instant;

use mcap::records::MessageHeader;
use serde_json::{Value as Json, json};

use super::live::Live;
use super::schema::{self, COMPRESSED_IMAGE, FRAME_TRANSFORM, LASER_SCAN, POSE_IN_FRAME};
use super::{
    CHUNK_BYTES, Event, FLUSH_INTERVAL, Layout, MAX_TEXT_BYTES, RecordError, RecordOptions, RecordSummary, calls_topic,
    capture_ns_of, is_image, is_pose, output_topic, rotated_path,
};
use crate::contract::{Value, ValueKind};

/// A file that counts the bytes written to it (its size, for rotation).
struct Counted {
    file: BufWriter<File>,
    position: u64,
    /// A character device or FIFO: no seeking; where it is is what was
    /// written.
    streamed: bool,
    /// The file's size so far, which the writer thread reads.
    size: Arc<AtomicU64>,
}

impl Write for Counted {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        let n = self.file.write(buf)?;
        self.position += n as u64;
        self.size.fetch_max(self.position, Ordering::Relaxed);
        Ok(n)
    }

    fn flush(&mut self) -> std::io::Result<()> {
        self.file.flush()
    }
}

impl Seek for Counted {
    fn seek(&mut self, pos: SeekFrom) -> std::io::Result<u64> {
        if self.streamed {
            return match pos {
                SeekFrom::Current(0) => Ok(self.position),
                _ => Err(std::io::Error::other("a recording into a device or FIFO cannot seek")),
            };
        }
        self.position = self.file.seek(pos)?;
        Ok(self.position)
    }
}

/// The open file of a recording and where it is.
struct OpenFile {
    mcap: mcap::Writer<Counted>,
    /// topic -> channel id, in this file.
    channels: HashMap<String, u16>,
    schemas: HashMap<&'static str, u16>,
    sequence: u32,
    size: Arc<AtomicU64>,
}

pub(super) struct Writer {
    options: RecordOptions,
    /// The Foxglove live view, if it runs.
    live: Option<Live>,
    layout: Arc<Layout>,
    /// The wall-clock time of graph time 0: a message's log time is this
    /// plus its graph time.
    graph_epoch_unix_ns: u64,
    /// The recording's time line's zero (`epoch_unix_ns` in its metadata):
    /// graph time 0, or for a recording from a fresh start the graph time
    /// of its swap (`start_ns`).
    epoch_unix_ns: u64,
    /// The graph time the recording starts at: 0, or a fresh start's swap.
    start_ns: u64,
    /// A recording from a fresh start whose swap has not come yet: nothing
    /// is written (not even the file's `subsume.recording` metadata) until
    /// it does (`Event::Start`).
    awaiting_start: bool,
    /// It records from a fresh start (its metadata says when it started).
    from_swap: bool,
    file: Option<OpenFile>,
    /// Index of the open file (0: the path itself).
    index: u32,
    /// The recording goes into a character device or FIFO: one stream,
    /// never rotated (there is no FILE.1.mcap beside /dev/stdout).
    streamed: bool,
    /// The files reached `max_total_bytes`: nothing more is written.
    cut: bool,
    summary: RecordSummary,
    last_flush: Instant,
    /// Per component: the capture time (graph ns) its last `frame-info`
    /// named, for the picture that follows it.
    capture_ns: HashMap<usize, u64>,
    /// The latest log time written (a scene written later is stamped so).
    last_unix_ns: u64,
}

impl Writer {
    pub(super) fn create(
        options: RecordOptions,
        layout: Arc<Layout>,
        epoch_unix_ns: u64,
        from_swap: bool,
    ) -> Result<Writer, RecordError> {
        let live = options.live.map(Live::start).transpose()?;
        let mut writer = Writer {
            options,
            live,
            layout,
            graph_epoch_unix_ns: epoch_unix_ns,
            epoch_unix_ns,
            start_ns: 0,
            awaiting_start: from_swap,
            from_swap,
            file: None,
            index: 0,
            streamed: false,
            cut: false,
            summary: RecordSummary::default(),
            last_flush: Instant::now(),
            capture_ns: HashMap::new(),
            last_unix_ns: 0,
        };
        if writer.options.path.is_some() {
            writer.open()?;
        }
        Ok(writer)
    }

    fn path(&self) -> std::path::PathBuf {
        self.options.path.as_deref().map(|p| rotated_path(p, self.index)).unwrap_or_default()
    }

    /// `text` with the hidden folders named.
    fn hidden(&self, mut text: String) -> String {
        self.options.hidden.hide(&mut text);
        text
    }

    fn mcap_error(&self, source: mcap::McapError) -> RecordError {
        RecordError::Mcap { path: self.path(), source }
    }

    fn open(&mut self) -> Result<(), RecordError> {
        let path = self.path();
        let (file, target) =
            crate::fsutil::create_output(&path).map_err(|source| RecordError::Io { path: path.clone(), source })?;
        let streamed = target == crate::fsutil::Target::Stream;
        self.streamed = streamed;
        let size = Arc::new(AtomicU64::new(0));
        let counted = Counted { file: BufWriter::new(file), position: 0, streamed, size: size.clone() };
        let mcap = mcap::WriteOptions::new()
            .disable_seeking(streamed)
            .compression(None)
            .chunk_size(Some(CHUNK_BYTES))
            .profile("")
            .library(format!("subsume {}", env!("CARGO_PKG_VERSION")))
            .create(counted)
            .map_err(|source| RecordError::Mcap { path: path.clone(), source })?;
        let open = OpenFile { mcap, channels: HashMap::new(), schemas: HashMap::new(), sequence: 0, size };
        self.summary.files.push(path);
        self.file = Some(open);
        if self.awaiting_start { Ok(()) } else { self.write_header() }
    }

    /// The open file's `subsume.recording` metadata and the scene.
    fn write_header(&mut self) -> Result<(), RecordError> {
        let path = self.path();
        let mut about = self.layout.about.clone();
        about.extend([
            ("robot".to_string(), self.layout.robot.clone()),
            ("epoch_unix_ns".to_string(), self.epoch_unix_ns.to_string()),
            ("file_index".to_string(), self.index.to_string()),
            ("format".to_string(), "1".to_string()),
        ]);
        if self.from_swap {
            about.insert("start_ns".to_string(), self.start_ns.to_string());
        }
        for value in about.values_mut() {
            self.options.hidden.hide(value);
        }
        let metadata = mcap::records::Metadata { name: "subsume.recording".into(), metadata: about };
        if let Some(open) = &mut self.file {
            open.mcap.write_metadata(&metadata).map_err(|source| RecordError::Mcap { path, source })?;
        }
        self.write_scene()
    }

    /// A fresh start's recording begins at graph time `start_ns` (its
    /// swap): its time line's zero; nothing before it is written.
    fn start(&mut self, start_ns: u64) -> Result<(), RecordError> {
        if !self.awaiting_start {
            return Ok(());
        }
        self.awaiting_start = false;
        self.start_ns = start_ns;
        self.epoch_unix_ns = self.graph_epoch_unix_ns.saturating_add(start_ns);
        self.write_header()
    }

    /// The simulators' worlds, if there are any (docs/recording.md).
    fn write_scene(&mut self) -> Result<(), RecordError> {
        if self.layout.worlds.is_empty() {
            return Ok(());
        }
        let at = self.last_unix_ns.max(self.epoch_unix_ns);
        let scene = super::scene::scene_update(&self.layout.worlds, at);
        self.message(super::scene::SCENE_TOPIC, super::scene::SCENE_UPDATE, at, &scene)
    }

    /// Finishes the open file (summary and footer).
    fn close(&mut self, dropped: u64) -> Result<(), RecordError> {
        let Some(mut open) = self.file.take() else { return Ok(()) };
        let end = mcap::records::Metadata {
            name: "subsume.recording.end".into(),
            metadata: BTreeMap::from([("dropped".to_string(), dropped.to_string())]),
        };
        open.mcap.write_metadata(&end).map_err(|e| self.mcap_error(e))?;
        open.mcap.finish().map_err(|e| self.mcap_error(e))?;
        let mut counted = open.mcap.into_inner();
        counted.flush().map_err(|source| RecordError::Io { path: self.path(), source })?;
        self.summary.bytes += open.size.load(Ordering::Relaxed);
        Ok(())
    }

    pub(super) fn finish(&mut self, dropped: u64) -> Result<RecordSummary, RecordError> {
        // A fresh start whose swap never came: the file says what it is.
        self.start(0)?;
        self.close(dropped)?;
        self.summary.dropped = dropped;
        Ok(self.summary.clone())
    }

    /// Writes finished chunks to the file every [`FLUSH_INTERVAL`] and
    /// rotates past the size limit.
    pub(super) fn flush_if_due(&mut self) -> Result<(), RecordError> {
        if self.last_flush.elapsed() < FLUSH_INTERVAL {
            return Ok(());
        }
        self.last_flush = Instant::now();
        let path = self.path();
        if let Some(open) = &mut self.file {
            open.mcap.flush().map_err(|source| RecordError::Mcap { path, source })?;
        }
        Ok(())
    }

    /// At `max_total_bytes` over every file: finishes the open file with
    /// a `subsume.recording.cut` record and stops recording; true then.
    fn cut_if_full(&mut self, dropped: u64) -> Result<bool, RecordError> {
        let Some(open) = &mut self.file else { return Ok(false) };
        let total = self.summary.bytes + open.size.load(Ordering::Relaxed);
        if total < self.options.max_total_bytes {
            return Ok(false);
        }
        let limit = self.options.max_total_bytes;
        let cut = mcap::records::Metadata {
            name: "subsume.recording.cut".into(),
            metadata: BTreeMap::from([("max_total_bytes".to_string(), limit.to_string())]),
        };
        open.mcap.write_metadata(&cut).map_err(|e| self.mcap_error(e))?;
        self.close(dropped)?;
        self.cut = true;
        tracing::warn!("the recording stops here: its files reached {total} bytes, the most it may take ({limit})");
        Ok(true)
    }

    fn rotate_if_full(&mut self, dropped: u64) -> Result<(), RecordError> {
        if self.file.is_none() || self.streamed {
            return Ok(());
        }
        let size = self.file.as_ref().map_or(0, |f| f.size.load(Ordering::Relaxed));
        if size < self.options.max_file_bytes {
            return Ok(());
        }
        self.close(dropped)?;
        self.index += 1;
        tracing::info!("recording continues in {}", self.path().display());
        self.open()
    }

    pub(super) fn write(&mut self, event: Event, dropped: u64) -> Result<(), RecordError> {
        if self.cut || self.cut_if_full(dropped)? {
            return Ok(());
        }
        self.rotate_if_full(dropped)?;
        // A fresh start's recording holds only what happened from its swap.
        match &event {
            Event::Start(start_ns) => return self.start(*start_ns),
            Event::Log { unix_ns, .. } if self.awaiting_start || *unix_ns < self.epoch_unix_ns => return Ok(()),
            Event::Call { t, .. }
            | Event::Emitted { t, .. }
            | Event::Fault { t, .. }
            | Event::Restart { t, .. }
            | Event::Status { t, .. } => {
                // The swap's own start was dropped (a full queue): the
                // first event of the new graph starts it.
                self.start(*t)?;
                if *t < self.start_ns {
                    return Ok(());
                }
            }
            _ => {}
        }
        let epoch = self.graph_epoch_unix_ns;
        let layout = self.layout.clone();
        let name = |index: usize| layout.components.get(index).map_or("?", |c| c.name.as_str());
        match event {
            Event::Call { index, t, input } => {
                let message = match &input {
                    None => json!({ "t": t, "call": "tick" }),
                    Some((port, from, value)) => {
                        let port_name = layout
                            .components
                            .get(index)
                            .and_then(|c| c.inputs.get(*port as usize))
                            .map_or("?", String::as_str);
                        json!({ "t": t, "call": "input", "port": port, "port_name": port_name, "from": name(*from), "value": schema::value_json(value) })
                    }
                };
                self.message(&calls_topic(name(index)), schema::CALL, epoch + t, &message)
            }
            Event::Emitted { from, port, t, value } => {
                let Some(component) = layout.components.get(from) else { return Ok(()) };
                let Some(spec) = component.outputs.get(port as usize) else { return Ok(()) };
                let topic = output_topic(&component.name, &spec.name);
                let unix = epoch + t;
                if let Some(capture) = capture_ns_of(spec, &value) {
                    self.capture_ns.insert(from, capture);
                }
                match &value {
                    Value::Bytes(jpeg) if is_image(spec, &value) => {
                        let captured = self.capture_ns.remove(&from).filter(|&c| c <= t).unwrap_or(t);
                        let image = schema::compressed_image(jpeg, &component.name, epoch + captured);
                        self.message(&topic, COMPRESSED_IMAGE, unix, &image)
                    }
                    Value::Scan(scan) if spec.kind == ValueKind::Scan => {
                        self.message(&topic, LASER_SCAN, unix, &schema::laser_scan(scan, &component.name, unix))
                    }
                    Value::Vector(v) if is_pose(spec) && v.len() == 3 => {
                        self.message(&topic, POSE_IN_FRAME, unix, &schema::pose_in_frame(v, unix))?;
                        self.message(&format!("{topic}/tf"), FRAME_TRANSFORM, unix, &schema::frame_transform(v, unix))
                    }
                    _ => self.message(
                        &topic,
                        schema::VALUE,
                        unix,
                        &json!({ "t": t, "value": schema::value_json(&value) }),
                    ),
                }
            }
            Event::Fault { index, t, reason } => self.message(
                "/subsume/events",
                schema::EVENT,
                epoch + t,
                &json!({ "t": t, "component": name(index), "event": "fault", "reason": clip(&self.hidden(reason)) }),
            ),
            Event::Restart { index, t, attempt } => self.message(
                "/subsume/events",
                schema::EVENT,
                epoch + t,
                &json!({ "t": t, "component": name(index), "event": "restart", "attempt": attempt }),
            ),
            Event::Status { index, t, kind, section } => self.message(
                &format!("/subsume/status/{}", name(index)),
                schema::STATUS,
                epoch + t,
                &json!({ "t": t, "component": name(index), "kind": kind, "status": section }),
            ),
            Event::Log { unix_ns, level, name, message } => self.message(
                super::LOG_TOPIC,
                schema::LOG,
                unix_ns,
                &schema::log(level, &name, clip(&self.hidden(message)), unix_ns),
            ),
            Event::Layout(layout) => {
                let moved = layout.worlds != self.layout.worlds;
                self.layout = layout;
                if moved && !self.awaiting_start { self.write_scene() } else { Ok(()) }
            }
            Event::Start(_) | Event::Stop => Ok(()),
        }
    }

    fn message(
        &mut self,
        topic: &str,
        schema_name: &'static str,
        unix_ns: u64,
        message: &Json,
    ) -> Result<(), RecordError> {
        let path = self.path();
        let epoch = self.epoch_unix_ns;
        let data = serde_json::to_vec(message).unwrap_or_default();
        self.last_unix_ns = self.last_unix_ns.max(unix_ns);
        if let Some(live) = &mut self.live {
            live.log(topic, schema_name, unix_ns, &data);
        }
        let Some(open) = &mut self.file else { return Ok(()) };
        let error = |source| RecordError::Mcap { path: path.clone(), source };
        let channel = match open.channels.get(topic) {
            Some(&id) => id,
            None => {
                let schema_id = match open.schemas.get(schema_name) {
                    Some(&id) => id,
                    None => {
                        let text = match schema_name {
                            super::scene::SCENE_UPDATE => super::scene::schema(),
                            _ => schema::schema(schema_name),
                        }
                        .to_string();
                        let id = open.mcap.add_schema(schema_name, "jsonschema", text.as_bytes()).map_err(error)?;
                        open.schemas.insert(schema_name, id);
                        id
                    }
                };
                let metadata = BTreeMap::from([("epoch_unix_ns".to_string(), epoch.to_string())]);
                let id = open.mcap.add_channel(schema_id, topic, "json", &metadata).map_err(error)?;
                open.channels.insert(topic.to_string(), id);
                id
            }
        };
        open.sequence = open.sequence.wrapping_add(1);
        let header =
            MessageHeader { channel_id: channel, sequence: open.sequence, log_time: unix_ns, publish_time: unix_ns };
        open.mcap.write_to_known_channel(&header, &data).map_err(error)?;
        self.summary.messages += 1;
        Ok(())
    }
}

fn clip(text: &str) -> &str {
    if text.len() <= MAX_TEXT_BYTES {
        return text;
    }
    let mut cut = MAX_TEXT_BYTES;
    while !text.is_char_boundary(cut) {
        cut -= 1;
    }
    &text[..cut]
}
