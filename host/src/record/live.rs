//! The live view: a Foxglove WebSocket server (the `foxglove` crate,
//! subprotocol `foxglove.sdk.v1`) with the same channels, schemas and JSON
//! messages as the recording. Foxglove and Lichtblick connect to it with
//! *Open connection* -> *Foxglove WebSocket*.
//!
//! Invariant: the server runs on its own runtime; the writer thread hands
//! it each message without waiting (a slow viewer's queue drops, not the
//! recording).

use std::collections::HashMap;
use std::net::SocketAddr;
use std::sync::Arc;

use foxglove::WebSocketServerHandle;
use foxglove::{ChannelBuilder, Context, PartialMetadata, RawChannel, Schema, WebSocketServer};

use super::RecordError;
use super::schema;

/// Messages waiting for one slow viewer before its oldest are dropped.
pub const VIEWER_BACKLOG: usize = 1024;

pub(super) struct Live {
    context: Arc<Context>,
    handle: Option<WebSocketServerHandle>,
    channels: HashMap<String, Arc<RawChannel>>,
}

impl Live {
    pub(super) fn start(address: SocketAddr) -> Result<Live, RecordError> {
        let context = Context::new();
        let handle = WebSocketServer::new()
            .name("subsume")
            .bind(address.ip().to_string(), address.port())
            .context(&context)
            .message_backlog_size(VIEWER_BACKLOG)
            .start_blocking()
            .map_err(|e| RecordError::Live { address, message: e.to_string() })?;
        let address = SocketAddr::new(address.ip(), handle.port());
        tracing::info!("foxglove live view on ws://{address} (subprotocol foxglove.sdk.v1)");
        Ok(Live { context, handle: Some(handle), channels: HashMap::new() })
    }

    pub(super) fn log(&mut self, topic: &str, schema_name: &'static str, unix_ns: u64, data: &[u8]) {
        let channel = match self.channels.get(topic) {
            Some(channel) => channel.clone(),
            None => {
                let text = match schema_name {
                    super::scene::SCENE_UPDATE => super::scene::schema(),
                    _ => schema::schema(schema_name),
                }
                .to_string()
                .into_bytes();
                let built = ChannelBuilder::new(topic)
                    .message_encoding("json")
                    .schema(Schema::new(schema_name, "jsonschema", text))
                    .context(&self.context)
                    .build_raw();
                match built {
                    Ok(channel) => {
                        self.channels.insert(topic.to_string(), channel.clone());
                        channel
                    }
                    Err(e) => {
                        tracing::warn!("foxglove live view: no channel {topic}: {e}");
                        return;
                    }
                }
            }
        };
        channel.log_with_meta(data, PartialMetadata { log_time: Some(unix_ns) });
    }
}

impl Drop for Live {
    fn drop(&mut self) {
        if let Some(handle) = self.handle.take() {
            // Waits for the server's tasks: the runtime outlives this call.
            drop(handle.stop());
        }
    }
}
