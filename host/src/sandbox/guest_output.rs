//! A guest's stdout and stderr, written line by line to the host log with the
//! component's name. Nothing the guest prints reaches the host's own stdout.

use std::io;
use std::pin::Pin;
use std::sync::{Arc, Mutex};
use std::task::{Context, Poll};

use bytes::Bytes;
use wasmtime_wasi::cli::{IsTerminal, StdoutStream};
use wasmtime_wasi::p2::{OutputStream, Pollable, StreamError};

use super::LogBudget;

/// Longest line kept from a guest's output; the rest of a longer line is cut,
/// so a guest printing without newlines cannot grow host memory.
pub const MAX_GUEST_LINE_BYTES: usize = 4096;

/// One of a guest's output streams.
#[derive(Clone)]
pub struct GuestOutput {
    component: Arc<str>,
    stream: &'static str,
    pending: Arc<Mutex<Vec<u8>>>,
    logs: LogBudget,
}

impl GuestOutput {
    pub fn new(component: Arc<str>, stream: &'static str, logs: LogBudget) -> Self {
        GuestOutput { component, stream, pending: Arc::new(Mutex::new(Vec::new())), logs }
    }

    /// Logs every complete line; `Err` when the guest is over its log rate.
    fn write_bytes(&self, bytes: &[u8]) -> Result<(), String> {
        let Ok(mut pending) = self.pending.lock() else {
            return Ok(());
        };
        for &byte in bytes {
            if byte == b'\n' {
                self.logs.take()?;
                self.emit_line(&pending);
                pending.clear();
            } else if pending.len() < MAX_GUEST_LINE_BYTES {
                pending.push(byte);
            }
        }
        Ok(())
    }

    fn emit_line(&self, line: &[u8]) {
        let text = String::from_utf8_lossy(line);
        let text = text.trim_end_matches('\r');
        if self.stream == "stderr" {
            tracing::warn!(component = &*self.component, stream = self.stream, "{text}");
        } else {
            tracing::info!(component = &*self.component, stream = self.stream, "{text}");
        }
    }
}

impl Drop for GuestOutput {
    fn drop(&mut self) {
        // The last handle flushes a final line without a newline.
        if Arc::strong_count(&self.pending) == 1
            && let Ok(pending) = self.pending.lock()
            && !pending.is_empty()
        {
            self.emit_line(&pending);
        }
    }
}

impl IsTerminal for GuestOutput {
    fn is_terminal(&self) -> bool {
        false
    }
}

impl StdoutStream for GuestOutput {
    fn p2_stream(&self) -> Box<dyn OutputStream> {
        Box::new(self.clone())
    }
    fn async_stream(&self) -> Box<dyn tokio::io::AsyncWrite + Send + Sync> {
        Box::new(self.clone())
    }
}

#[wasmtime_wasi::async_trait]
impl OutputStream for GuestOutput {
    fn write(&mut self, bytes: Bytes) -> Result<(), StreamError> {
        self.write_bytes(&bytes).map_err(|why| StreamError::Trap(wasmtime::format_err!("{why}")))
    }
    fn flush(&mut self) -> Result<(), StreamError> {
        Ok(())
    }
    fn check_write(&mut self) -> Result<usize, StreamError> {
        Ok(MAX_GUEST_LINE_BYTES)
    }
}

#[wasmtime_wasi::async_trait]
impl Pollable for GuestOutput {
    async fn ready(&mut self) {}
}

impl tokio::io::AsyncWrite for GuestOutput {
    fn poll_write(self: Pin<&mut Self>, _cx: &mut Context<'_>, buf: &[u8]) -> Poll<io::Result<usize>> {
        Poll::Ready(self.write_bytes(buf).map(|()| buf.len()).map_err(io::Error::other))
    }
    fn poll_flush(self: Pin<&mut Self>, _cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Poll::Ready(Ok(()))
    }
    fn poll_shutdown(self: Pin<&mut Self>, _cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Poll::Ready(Ok(()))
    }
}
