//! A guest's stdout and stderr, written line by line to the host log with the
//! component's name. Nothing the guest prints reaches the host's own stdout.
//! What a guest last wrote to stderr in a call ([`LastWords`]: a Rust panic's
//! message, a Python traceback's last line, a JavaScript error) is kept, so a
//! fault can say what the guest said rather than only `unreachable`.

use std::io;
use std::pin::Pin;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::task::{Context, Poll};
use std::time::Duration;

use bytes::Bytes;
use wasmtime_wasi::cli::{IsTerminal, StdoutStream};
use wasmtime_wasi::p2::{OutputStream, Pollable, StreamError};

use crate::contract::clip_to;

/// Longest line kept from a guest's output; the rest of a longer line is cut,
/// so a guest printing without newlines cannot grow host memory.
pub const MAX_GUEST_LINE_BYTES: usize = 4096;

/// Longest text kept of what a guest last said on stderr: a fault reason
/// is shown in the report and the portal, and the guest controls the text.
pub const MAX_LAST_WORDS_BYTES: usize = 240;

/// The last meaningful line a guest wrote to stderr in the current call
/// (a panic's message, an exception), cleared when a call begins.
#[derive(Clone, Default)]
pub struct LastWords(Arc<Words>);

#[derive(Default)]
struct Words {
    line: Mutex<String>,
    /// Whether `line` may hold something: a call that said nothing (nearly
    /// all) is cleared without taking the lock.
    said: AtomicBool,
}

impl LastWords {
    /// Forgets what an earlier call said.
    pub fn clear(&self) {
        if self.0.said.swap(false, Ordering::AcqRel)
            && let Ok(mut words) = self.0.line.lock()
        {
            words.clear();
        }
    }

    /// What the guest last said in this call, if anything.
    pub fn take(&self) -> Option<String> {
        let words = std::mem::take(&mut *self.0.line.lock().ok()?);
        (!words.is_empty()).then_some(words)
    }

    fn hear(&self, line: &str) {
        let line = line.trim();
        // Rust's panic header and its hint after the message, the
        // traceback's header and frames, and componentize-py's own panic
        // after the traceback say nothing about what went wrong.
        let noise = line.is_empty()
            || line.starts_with("note: run with `RUST_BACKTRACE")
            || (line.starts_with("thread '") && line.contains(" panicked at "))
            || line == "Python function threw an unexpected exception"
            || line.starts_with("Traceback (most recent call last)")
            || line.starts_with("File \"")
            || line.starts_with("at ");
        if noise {
            return;
        }
        if let Ok(mut words) = self.0.line.lock() {
            *words = clip_to(line, MAX_LAST_WORDS_BYTES);
            self.0.said.store(true, Ordering::Release);
        }
    }
}

/// One of a guest's output streams.
#[derive(Clone)]
pub struct GuestOutput {
    component: Arc<str>,
    stream: &'static str,
    pending: Arc<Mutex<Vec<u8>>>,
    logs: LogBudget,
    last_words: Option<LastWords>,
}

impl GuestOutput {
    pub fn new(component: Arc<str>, stream: &'static str, logs: LogBudget) -> Self {
        GuestOutput { component, stream, pending: Arc::new(Mutex::new(Vec::new())), logs, last_words: None }
    }

    /// This stream, keeping its last meaningful line in `last_words`.
    pub fn keeping_last_words(mut self, last_words: LastWords) -> Self {
        self.last_words = Some(last_words);
        self
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
        // Control characters (a terminal's escapes, a forged line) go here.
        let text = clip_to(text.trim_end_matches('\r'), MAX_GUEST_LINE_BYTES);
        let text = text.as_str();
        if let Some(last_words) = &self.last_words {
            last_words.hear(text);
        }
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

/// A guest's log lines this second, shared by `log`, stdout and stderr.
#[derive(Clone, Debug)]
pub struct LogBudget {
    max_per_s: u32,
    window: Arc<std::sync::Mutex<(std::time::Instant, u32)>>,
}

impl LogBudget {
    pub fn new(max_per_s: u32) -> LogBudget {
        LogBudget { max_per_s, window: Arc::new(std::sync::Mutex::new((std::time::Instant::now(), 0))) }
    }

    /// Counts one line; `Err` when the guest is over its rate.
    pub(super) fn take(&self) -> Result<(), String> {
        let Ok(mut window) = self.window.lock() else { return Ok(()) };
        if window.0.elapsed() >= Duration::from_secs(1) {
            *window = (std::time::Instant::now(), 0);
        }
        window.1 += 1;
        if window.1 > self.max_per_s {
            return Err(format!("wrote more than {} log lines in one second (max-logs)", self.max_per_s));
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn last_words_are_the_last_line_that_says_what_went_wrong() {
        let cases: [(&[&str], Option<&str>); 4] = [
            (
                &[
                    "thread '<unnamed>' panicked at src/lib.rs:152:33:",
                    "giving up on purpose at tick 4",
                    "note: run with `RUST_BACKTRACE=1` environment variable to display a backtrace",
                ],
                Some("giving up on purpose at tick 4"),
            ),
            (
                &[
                    "Traceback (most recent call last):",
                    "  File \"app.py\", line 58, in tick",
                    "ValueError: giving up",
                    "thread '<unnamed>' (1) panicked at runtime/src/lib.rs:1293:29:",
                    "Python function threw an unexpected exception",
                ],
                Some("ValueError: giving up"),
            ),
            (&["Error: bad state", "    at tick (app.js:3:9)"], Some("Error: bad state")),
            (&["", "note: run with `RUST_BACKTRACE=1`"], None),
        ];
        for (lines, expected) in cases {
            let words = LastWords::default();
            for line in lines {
                words.hear(line);
            }
            assert_eq!(words.take().as_deref(), expected, "{lines:?}");
            assert_eq!(words.take(), None, "taken once");
        }
        let words = LastWords::default();
        words.hear(&"x".repeat(1000));
        assert!(words.take().is_some_and(|w| w.len() <= MAX_LAST_WORDS_BYTES + 3));
    }
}
