//! People are told (docs/lab.md, "People are told"): the lab's events sent
//! to the owner's webhooks and by mail. This module owns the webhooks'
//! configuration (`webhooks.json` beside the store, read at start), the
//! mail's ([`mail`]: `mail.json`, and the researchers' own subscriptions),
//! the [`Event`] and its JSON, the [`outbox`] on disk where every event
//! waits until its receiver acknowledged it, and the delivery thread
//! ([`delivery`]: each destination in order, retried with backoff; a
//! [`webhook`] gets a signed POST, an address a mail). The lab hands it
//! events (`Lab::transition` for experiments); writing an event to the
//! outbox is the only work done there, delivery is off every lock, on a
//! thread of its own.

pub mod delivery;
pub mod mail;
pub mod outbox;
pub mod webhook;

use std::path::{Path, PathBuf};
use std::sync::{Arc, Condvar, Mutex};
use std::time::Duration;

use serde::{Deserialize, Serialize};
use thiserror::Error;

use crate::store::experiments::RunOutcome;

use self::mail::{MAIL_FILE, MAILTO, MailError, Mailer, SUBSCRIPTIONS_FILE, Subscription, Subscriptions};
use self::outbox::{Outbox, OutboxError};
use self::webhook::{Url, WebhookError};

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
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, schemars::JsonSchema)]
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
    /// The robot left service (a failed reset or self-test, a low battery,
    /// an admin).
    #[serde(rename = "robot.maintenance.started")]
    RobotMaintenanceStarted,
    /// The robot is back in service.
    #[serde(rename = "robot.maintenance.ended")]
    RobotMaintenanceEnded,
    /// A lab server's robot left the lab (its token went, or its signed
    /// statuses stopped).
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
    /// The robot an event about a robot is about.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub robot: Option<RobotFacts>,
}

/// The robot a `robot.*` event is about.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RobotFacts {
    pub name: String,
    /// Why it left (or came back into) service, and who said so.
    pub reason: String,
}

/// The experiment an event is about.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ExperimentFacts {
    pub id: u64,
    pub submitter: String,
    /// The state it entered (`queued`, `refused`, `running`, `done`, ...):
    /// the run's status.
    pub state: String,
    pub reasons: Vec<String>,
    /// How the algorithm did, once it ran (the goal, collisions, faults,
    /// the envelope's interventions), apart from the status.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub outcome: Option<RunOutcome>,
    /// Its score against the owner's task, once its run ended scored.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub score: Option<crate::store::task::Score>,
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
    /// For an `https://` hook: a PEM file of the authority that signed its
    /// certificate; by default the system's roots.
    pub ca: Option<PathBuf>,
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
    #[error(transparent)]
    Mail(#[from] MailError),
    #[error(transparent)]
    Webhook(#[from] WebhookError),
    #[error("{0}: no longer configured; the event is not sent")]
    Gone(String),
    #[error("cannot start the notifications' delivery thread: {0}")]
    Thread(std::io::Error),
}

/// A webhook checked: its URL parsed, its client made.
pub(crate) struct Hook {
    pub url: Url,
    pub events: Vec<EventKind>,
    pub secret: Vec<u8>,
    pub agent: ureq::Agent,
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
        if hook.ca.is_some() && !hook.url.starts_with("https://") {
            return Err(bad(format!("webhook {n} ({}): a ca is only for an https:// hook", hook.url)));
        }
    }
    Ok(Some(file.webhooks))
}

/// The host's notifications: events in, signed POSTs and mails out.
pub struct Notifier {
    hooks: Vec<Hook>,
    mailer: Option<Mailer>,
    subscriptions: Mutex<Subscriptions>,
    outbox: Mutex<Outbox>,
    /// Wakes the delivery thread when an event is written.
    written: Condvar,
}

impl Notifier {
    /// The webhooks and mail configured beside the store in `store_dir`,
    /// with their outbox there and the delivery thread started; `None`
    /// when no file configures either.
    pub fn start(store_dir: &Path) -> Result<Option<Arc<Notifier>>, NotifyError> {
        let webhooks_path = store_dir.join(WEBHOOKS_FILE);
        let mail_path = store_dir.join(MAIL_FILE);
        let webhooks = read_webhooks(&webhooks_path)?;
        let mail = mail::read_mail_config(&mail_path)?;
        if webhooks.is_none() && mail.is_none() {
            return Ok(None);
        }
        let mut hooks = Vec::new();
        for webhook in webhooks.unwrap_or_default() {
            let bad = |message: String| NotifyError::Config { path: webhooks_path.clone(), message };
            let url = Url::parse(&webhook.url).map_err(|e| bad(e.to_string()))?;
            let agent = webhook::agent(&url, webhook.ca.as_deref()).map_err(|e| bad(e.to_string()))?;
            hooks.push(Hook { url, events: webhook.events, secret: webhook.secret.into_bytes(), agent });
        }
        let mailer = mail.map(|config| Mailer::new(config, &mail_path)).transpose()?;
        let subscriptions = Subscriptions::open(&store_dir.join(SUBSCRIPTIONS_FILE))?;
        let outbox = Outbox::open(&store_dir.join(OUTBOX_DIR), outbox::MAX_OUTBOX_ENTRIES)?;
        tracing::info!(
            "notifications: {} webhooks, mail {}, {} events waiting in the outbox",
            hooks.len(),
            if mailer.is_some() { "configured" } else { "not configured" },
            outbox.len()
        );
        let notifier = Arc::new(Notifier {
            hooks,
            mailer,
            subscriptions: Mutex::new(subscriptions),
            outbox: Mutex::new(outbox),
            written: Condvar::new(),
        });
        let deliverer = notifier.clone();
        std::thread::Builder::new()
            .name("notifications".into())
            .spawn(move || delivery::deliver_forever(&deliverer))
            .map_err(NotifyError::Thread)?;
        Ok(Some(notifier))
    }

    /// Writes `kind` (about `experiment`) to the outbox once per webhook
    /// that asked for it, once per owner address, and once for the
    /// experiment's submitter when she subscribed to it (fsynced before
    /// this returns), and wakes the delivery.
    pub fn tell(&self, kind: EventKind, at_ms: u64, experiment: Option<ExperimentFacts>) -> Result<(), NotifyError> {
        self.tell_about(kind, at_ms, experiment, None)
    }

    /// Writes `kind` about `robot` to the outbox, as [`Notifier::tell`]
    /// does about an experiment.
    pub fn tell_robot(&self, kind: EventKind, at_ms: u64, robot: RobotFacts) -> Result<(), NotifyError> {
        self.tell_about(kind, at_ms, None, Some(robot))
    }

    fn tell_about(
        &self,
        kind: EventKind,
        at_ms: u64,
        experiment: Option<ExperimentFacts>,
        robot: Option<RobotFacts>,
    ) -> Result<(), NotifyError> {
        let mut destinations: Vec<String> =
            self.hooks.iter().filter(|h| h.events.contains(&kind)).map(|h| h.url.text.clone()).collect();
        if let Some(mailer) = &self.mailer {
            destinations.extend(mailer.owner_addresses(kind).map(|a| format!("{MAILTO}{a}")));
            if let Some(facts) = &experiment {
                let subscriptions = self.subscriptions.lock().map_err(|_| OutboxError::Poisoned)?;
                if let Some(s) = subscriptions.get(&facts.submitter).filter(|s| s.events.contains(&kind)) {
                    destinations.push(format!("{MAILTO}{}", s.address));
                }
            }
        }
        if destinations.is_empty() {
            return Ok(());
        }
        let mut outbox = self.outbox.lock().map_err(|_| OutboxError::Poisoned)?;
        for destination in destinations {
            let id = outbox.next_id();
            let event = Event { id, event: kind, at_ms, experiment: experiment.clone(), robot: robot.clone() };
            outbox.push(&destination, &event)?;
        }
        drop(outbox);
        self.written.notify_all();
        Ok(())
    }

    /// Whether this lab sends mail.
    pub fn mails(&self) -> bool {
        self.mailer.is_some()
    }

    /// `user`'s mail subscription.
    pub fn subscription(&self, user: &str) -> Result<Option<Subscription>, NotifyError> {
        let subscriptions = self.subscriptions.lock().map_err(|_| OutboxError::Poisoned)?;
        Ok(subscriptions.get(user).cloned())
    }

    /// Sets (or with `None`, ends) `user`'s mail subscription.
    pub fn subscribe(&self, user: &str, subscription: Option<Subscription>) -> Result<(), NotifyError> {
        let mut subscriptions = self.subscriptions.lock().map_err(|_| OutboxError::Poisoned)?;
        Ok(subscriptions.set(user, subscription)?)
    }

    pub(crate) fn hook(&self, url: &str) -> Option<&Hook> {
        self.hooks.iter().find(|h| h.url.text == url)
    }

    pub(crate) fn mailer(&self) -> Option<&Mailer> {
        self.mailer.as_ref()
    }

    /// Waits up to `timeout` for an event written after `last_id`.
    pub(crate) fn wait_for_news(&self, last_id: u64, timeout: Duration) {
        if let Ok(outbox) = self.outbox.lock()
            && outbox.last_id() == last_id
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
            (format!(r#"{{"webhooks": [{}]}}"#, hook("ftp://a/", r#"["robot.lost"]"#, SECRET)), "webhook 0: url"),
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
