//! People are told (docs/lab.md, "People are told"): the lab's events sent
//! to the owner's webhooks. This module owns the webhooks' configuration
//! (`webhooks.json` beside the store, read at start), the [`Event`] and its
//! JSON, the [`outbox`] on disk where every event waits until its receiver
//! acknowledged it, and the delivery thread ([`webhook`]: signed POSTs,
//! retried with backoff). The lab hands it events from one place
//! (`Lab::transition`); writing an event to the outbox is the only work
//! done there, delivery is off every lock, on a thread of its own.

pub mod outbox;
pub mod webhook;

use std::path::{Path, PathBuf};
use std::sync::{Arc, Condvar, Mutex};
use std::time::Duration;

use serde::{Deserialize, Serialize};
use thiserror::Error;

use self::outbox::{Outbox, OutboxError};
use self::webhook::Url;

/// The webhooks' configuration file, in the store's folder.
pub const WEBHOOKS_FILE: &str = "webhooks.json";
/// The outbox's folder, in the store's folder.
pub const OUTBOX_DIR: &str = "outbox";
/// Most webhooks: each event is written once per hook, so a long list
/// multiplies the writes under the lab's lock.
pub const MAX_WEBHOOKS: usize = 16;
/// Longest secret, bytes: a file read whole into memory.
pub const MAX_SECRET_BYTES: usize = 1024;
/// Shortest secret, bytes: a guessable secret signs nothing.
pub const MIN_SECRET_BYTES: usize = 16;
/// Largest configuration file, bytes.
pub const MAX_WEBHOOKS_FILE_BYTES: u64 = 256 * 1024;

/// What happened (the `event` field of the JSON).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum EventKind {
    /// Its preflight passed: queued.
    #[serde(rename = "experiment.accepted")]
    ExperimentAccepted,
    /// A check or the preflight failed (the reasons say which).
    #[serde(rename = "experiment.refused")]
    ExperimentRefused,
    /// On the robot.
    #[serde(rename = "experiment.started")]
    ExperimentStarted,
    /// Done, cancelled, aborted or failed (the state and reasons say which).
    #[serde(rename = "experiment.ended")]
    ExperimentEnded,
    /// Declared for configurations; nothing emits it yet.
    #[serde(rename = "robot.maintenance.started")]
    RobotMaintenanceStarted,
    /// Declared for configurations; nothing emits it yet.
    #[serde(rename = "robot.maintenance.ended")]
    RobotMaintenanceEnded,
    /// Declared for configurations; nothing emits it yet.
    #[serde(rename = "robot.lost")]
    RobotLost,
}

/// One thing that happened, as its receivers get it (the POST's body).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Event {
    /// Unique and increasing on this host: a receiver drops a second copy
    /// by it (delivery is at least once).
    pub id: u64,
    pub event: EventKind,
    /// When it happened, milliseconds since the Unix epoch.
    pub at_ms: u64,
    pub experiment: Option<ExperimentFacts>,
}

/// The experiment an event is about.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ExperimentFacts {
    pub id: u64,
    pub submitter: String,
    /// The state it entered (`queued`, `refused`, `running`, `done`, ...).
    pub state: String,
    pub reasons: Vec<String>,
}

/// The event an experiment entering state `state` (its name) makes, if any.
pub fn experiment_event(state: &str) -> Option<EventKind> {
    match state {
        "queued" => Some(EventKind::ExperimentAccepted),
        "refused" => Some(EventKind::ExperimentRefused),
        "running" => Some(EventKind::ExperimentStarted),
        "done" | "cancelled" | "aborted" | "failed" => Some(EventKind::ExperimentEnded),
        _ => None,
    }
}

/// One webhook of the configuration.
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Webhook {
    pub url: String,
    pub events: Vec<EventKind>,
    /// The HMAC-SHA256 key; never logged nor shown.
    pub secret: String,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct WebhooksFile {
    webhooks: Vec<Webhook>,
}

/// Why the webhooks cannot be configured or an event kept.
#[derive(Debug, Error)]
pub enum NotifyError {
    #[error("webhooks file {path}: {message}")]
    Config { path: PathBuf, message: String },
    #[error(transparent)]
    Outbox(#[from] OutboxError),
    #[error("cannot start the webhooks' delivery thread: {0}")]
    Thread(std::io::Error),
}

/// A webhook checked: its URL parsed.
#[derive(Clone, Debug)]
pub(crate) struct Hook {
    pub url: Url,
    pub events: Vec<EventKind>,
    pub secret: Vec<u8>,
}

/// Reads and checks `path`'s webhooks; `Ok(None)` when there is no file.
pub fn read_webhooks(path: &Path) -> Result<Option<Vec<Webhook>>, NotifyError> {
    let bad = |message: String| NotifyError::Config { path: path.to_path_buf(), message };
    let bytes = match std::fs::metadata(path) {
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
        Err(e) => return Err(bad(e.to_string())),
        Ok(m) if m.len() > MAX_WEBHOOKS_FILE_BYTES => {
            return Err(bad(format!("larger than {MAX_WEBHOOKS_FILE_BYTES} bytes")));
        }
        Ok(_) => std::fs::read(path).map_err(|e| bad(e.to_string()))?,
    };
    let file: WebhooksFile = serde_json::from_slice(&bytes).map_err(|e| bad(e.to_string()))?;
    if file.webhooks.len() > MAX_WEBHOOKS {
        return Err(bad(format!("{} webhooks, at most {MAX_WEBHOOKS}", file.webhooks.len())));
    }
    for (n, hook) in file.webhooks.iter().enumerate() {
        Url::parse(&hook.url).map_err(|e| bad(format!("webhook {n}: {e}")))?;
        if !(MIN_SECRET_BYTES..=MAX_SECRET_BYTES).contains(&hook.secret.len()) {
            return Err(bad(format!(
                "webhook {n} ({}): its secret must be {MIN_SECRET_BYTES} to {MAX_SECRET_BYTES} bytes",
                hook.url
            )));
        }
        if hook.events.is_empty() {
            return Err(bad(format!("webhook {n} ({}): no events", hook.url)));
        }
    }
    Ok(Some(file.webhooks))
}

/// The host's webhooks: events in, signed POSTs out.
pub struct Notifier {
    hooks: Vec<Hook>,
    outbox: Mutex<Outbox>,
    /// Wakes the delivery thread when an event is written.
    written: Condvar,
}

impl Notifier {
    /// The webhooks configured beside the store in `store_dir`, with their
    /// outbox there and the delivery thread started; `None` when no file
    /// configures any.
    pub fn start(store_dir: &Path) -> Result<Option<Arc<Notifier>>, NotifyError> {
        let Some(webhooks) = read_webhooks(&store_dir.join(WEBHOOKS_FILE))? else {
            return Ok(None);
        };
        let mut hooks = Vec::new();
        for webhook in webhooks {
            let url = Url::parse(&webhook.url)
                .map_err(|e| NotifyError::Config { path: store_dir.join(WEBHOOKS_FILE), message: e.to_string() })?;
            hooks.push(Hook { url, events: webhook.events, secret: webhook.secret.into_bytes() });
        }
        let outbox = Outbox::open(&store_dir.join(OUTBOX_DIR), outbox::MAX_OUTBOX_ENTRIES)?;
        tracing::info!("webhooks: {} configured, {} events waiting in the outbox", hooks.len(), outbox.len());
        let notifier = Arc::new(Notifier { hooks, outbox: Mutex::new(outbox), written: Condvar::new() });
        let deliverer = notifier.clone();
        std::thread::Builder::new()
            .name("webhooks".into())
            .spawn(move || webhook::deliver_forever(&deliverer))
            .map_err(NotifyError::Thread)?;
        Ok(Some(notifier))
    }

    /// Writes `kind` about `experiment` to the outbox once per webhook that
    /// asked for it (fsynced before this returns) and wakes the delivery.
    pub fn tell(&self, kind: EventKind, at_ms: u64, experiment: Option<ExperimentFacts>) -> Result<(), NotifyError> {
        let mut outbox = self.outbox.lock().map_err(|_| OutboxError::Poisoned)?;
        for hook in self.hooks.iter().filter(|h| h.events.contains(&kind)) {
            let id = outbox.next_id();
            let event = Event { id, event: kind, at_ms, experiment: experiment.clone() };
            outbox.push(&hook.url.text, &event)?;
        }
        drop(outbox);
        self.written.notify_all();
        Ok(())
    }

    pub(crate) fn hook(&self, url: &str) -> Option<&Hook> {
        self.hooks.iter().find(|h| h.url.text == url)
    }

    /// Waits up to `timeout` for an event to be written.
    pub(crate) fn wait(&self, timeout: Duration) {
        if let Ok(outbox) = self.outbox.lock()
            && outbox.is_empty()
        {
            let _ = self.written.wait_timeout(outbox, timeout);
        }
    }

    pub(crate) fn outbox(&self) -> Result<std::sync::MutexGuard<'_, Outbox>, OutboxError> {
        self.outbox.lock().map_err(|_| OutboxError::Poisoned)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const SECRET: &str = "sixteen-bytes-or-more";

    fn hook(url: &str, events: &str, secret: &str) -> String {
        format!(r#"{{"url": "{url}", "events": {events}, "secret": "{secret}"}}"#)
    }

    #[test]
    fn a_bad_webhooks_file_is_refused_naming_what_is_wrong() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join(WEBHOOKS_FILE);
        assert!(read_webhooks(&path).unwrap().is_none(), "no file: no webhooks");
        let good = hook("http://127.0.0.1:9/x", r#"["experiment.ended"]"#, SECRET);
        std::fs::write(&path, format!(r#"{{"webhooks": [{good}]}}"#)).unwrap();
        let hooks = read_webhooks(&path).unwrap().unwrap();
        assert_eq!(hooks[0].events, [EventKind::ExperimentEnded]);
        let many = vec![good.clone(); MAX_WEBHOOKS + 1].join(",");
        for (body, why) in [
            (format!(r#"{{"webhooks": [{many}]}}"#), "17 webhooks, at most 16"),
            (format!(r#"{{"webhooks": [{}]}}"#, hook("https://a/", r#"["robot.lost"]"#, SECRET)), "webhook 0: url"),
            (format!(r#"{{"webhooks": [{}]}}"#, hook("http://a/", r#"["robot.lost"]"#, "short")), "its secret must be"),
            (format!(r#"{{"webhooks": [{}]}}"#, hook("http://a/", "[]", SECRET)), "no events"),
            (
                format!(r#"{{"webhooks": [{}]}}"#, hook("http://a/", r#"["experiment.exploded"]"#, SECRET)),
                "unknown variant",
            ),
            (r#"{"webhooks": [], "extra": 1}"#.to_string(), "unknown field"),
        ] {
            std::fs::write(&path, &body).unwrap();
            let e = read_webhooks(&path).unwrap_err().to_string();
            assert!(e.contains(why) && e.contains(WEBHOOKS_FILE), "{body}: {e}");
            assert!(!e.contains(SECRET), "a secret is never in an error: {e}");
        }
    }
}
