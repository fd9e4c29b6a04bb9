//! Mail (docs/lab.md, "People are told"): the owner's SMTP server and
//! addresses (`mail.json` beside the store, read at start, like the
//! webhooks' file: its password never travels through the portal), the
//! researchers' own subscriptions (`mail-subscriptions.json` beside it,
//! each user's address and the events of her own experiments she wants;
//! written to a temporary file, fsynced and renamed), and one message sent
//! over SMTP with `lettre` on rustls. Mails wait in the same outbox as the
//! webhooks' events, under the destination `mailto:ADDRESS`.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Duration;

use lettre::message::Mailbox;
use lettre::message::header::ContentType;
use lettre::transport::smtp::authentication::Credentials;
use lettre::transport::smtp::client::{Certificate, CertificateStore, Tls, TlsParameters};
use lettre::{Address, Message, SmtpTransport, Transport};
use serde::{Deserialize, Serialize};
use thiserror::Error;

use super::{Event, EventKind};
use crate::fsutil::write_atomically;

/// The owner's mail configuration, in the store's folder.
pub const MAIL_FILE: &str = "mail.json";
/// The researchers' subscriptions, in the store's folder.
pub const SUBSCRIPTIONS_FILE: &str = "mail-subscriptions.json";
/// The prefix of a mail's destination in the outbox.
pub const MAILTO: &str = "mailto:";
/// Largest configuration file read, bytes.
pub const MAX_MAIL_FILE_BYTES: u64 = 64 * 1024;
/// Longest address, bytes (RFC 5321's path limit).
pub const MAX_ADDRESS_BYTES: usize = 254;
/// Most owner addresses: each event is written once per address under the
/// lab's lock.
pub const MAX_OWNER_ADDRESSES: usize = 16;
/// Most subscriptions kept: one per user; a portal with more users than
/// this refuses the next one rather than grow the file without end.
pub const MAX_SUBSCRIPTIONS: usize = 10_000;
/// How long connecting to the SMTP server or any of its answers may take:
/// a server that hangs must not hold the queue forever.
pub const MAIL_TIMEOUT: Duration = Duration::from_secs(10);

/// The events a researcher may ask mail for: those of her own experiments.
pub const RESEARCHER_EVENTS: [EventKind; 4] = [
    EventKind::ExperimentAccepted,
    EventKind::ExperimentRefused,
    EventKind::ExperimentStarted,
    EventKind::ExperimentEnded,
];

/// How the connection to the SMTP server is protected.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Security {
    /// TLS from the first byte (port 465).
    Tls,
    /// Plain, then STARTTLS, required (port 587).
    Starttls,
    /// No TLS: only to a server on loopback, or with `allow_plain`.
    Plain,
}

/// One of the owner's addresses and the events it gets.
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct OwnerAddress {
    pub address: String,
    pub events: Vec<EventKind>,
}

/// `mail.json`.
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MailConfig {
    /// The SMTP server's host name (checked against its certificate).
    pub server: String,
    /// Its port; by default 465 for `tls`, 587 for `starttls`, 25 for `plain`.
    pub port: Option<u16>,
    pub security: Security,
    /// Who the mails are from.
    pub from: String,
    /// The SMTP login, when the server asks for one.
    pub user: Option<String>,
    /// Its password; never logged nor shown.
    pub password: Option<String>,
    /// A PEM file of the authority that signed the server's certificate;
    /// by default the system's roots.
    pub ca: Option<PathBuf>,
    /// Allows `plain` to a server off loopback (a closed network).
    #[serde(default)]
    pub allow_plain: bool,
    /// The owner's addresses (e.g. told when a robot enters maintenance).
    #[serde(default)]
    pub owner: Vec<OwnerAddress>,
}

/// A researcher's subscription: where her mail goes and for which events
/// of her own experiments.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct Subscription {
    pub address: String,
    pub events: Vec<EventKind>,
}

/// Why mail cannot be configured, kept or sent.
#[derive(Debug, Error)]
pub enum MailError {
    #[error("mail file {path}: {message}")]
    Config { path: PathBuf, message: String },
    #[error("{0}")]
    Subscription(String),
    #[error("mail subscriptions {path}: {source}")]
    Io { path: PathBuf, source: std::io::Error },
    #[error("mail to {to}: {message}")]
    Send { to: String, message: String },
}

/// Checks an address as SMTP takes it.
fn parse_address(text: &str) -> Result<Address, String> {
    if text.len() > MAX_ADDRESS_BYTES {
        return Err(format!("address longer than {MAX_ADDRESS_BYTES} bytes"));
    }
    text.parse::<Address>().map_err(|e| format!("address {:?}: {e}", text.chars().take(80).collect::<String>()))
}

/// Reads and checks `path`; `Ok(None)` when there is no file.
pub fn read_mail_config(path: &Path) -> Result<Option<MailConfig>, MailError> {
    let bad = |message: String| MailError::Config { path: path.to_path_buf(), message };
    let bytes = match std::fs::metadata(path) {
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
        Err(e) => return Err(bad(e.to_string())),
        Ok(m) if m.len() > MAX_MAIL_FILE_BYTES => return Err(bad(format!("larger than {MAX_MAIL_FILE_BYTES} bytes"))),
        Ok(_) => std::fs::read(path).map_err(|e| bad(e.to_string()))?,
    };
    let config: MailConfig = serde_json::from_slice(&bytes).map_err(|e| bad(e.to_string()))?;
    if config.server.is_empty() || config.server.chars().any(|c| c.is_whitespace() || c == '/') {
        return Err(bad(format!("server {:?} is not a host name", config.server)));
    }
    parse_address(&config.from).map_err(|e| bad(format!("from: {e}")))?;
    if config.user.is_some() != config.password.is_some() {
        return Err(bad("user and password go together".into()));
    }
    if config.security == Security::Plain && !config.allow_plain && !is_loopback(&config.server) {
        return Err(bad(format!(
            "security \"plain\" to {} would send mail (and any password) in clear off loopback: use tls or starttls, or set allow_plain for a closed network",
            config.server
        )));
    }
    if config.owner.len() > MAX_OWNER_ADDRESSES {
        return Err(bad(format!("{} owner addresses, at most {MAX_OWNER_ADDRESSES}", config.owner.len())));
    }
    for (n, owner) in config.owner.iter().enumerate() {
        parse_address(&owner.address).map_err(|e| bad(format!("owner {n}: {e}")))?;
        if owner.events.is_empty() {
            return Err(bad(format!("owner {n} ({}): no events", owner.address)));
        }
    }
    Ok(Some(config))
}

fn is_loopback(host: &str) -> bool {
    host == "localhost"
        || host
            .trim_start_matches('[')
            .trim_end_matches(']')
            .parse::<std::net::IpAddr>()
            .is_ok_and(|ip| ip.is_loopback())
}

/// The owner's mail, ready to send.
pub struct Mailer {
    config: MailConfig,
    from: Mailbox,
    transport: SmtpTransport,
}

impl Mailer {
    /// Builds the SMTP client of `config` (read from `path`, named in
    /// errors); the trusted roots are read now.
    pub fn new(config: MailConfig, path: &Path) -> Result<Mailer, MailError> {
        let bad = |message: String| MailError::Config { path: path.to_path_buf(), message };
        let from = Mailbox::new(Some("subsume lab".into()), parse_address(&config.from).map_err(bad)?);
        let tls = match config.security {
            Security::Plain => Tls::None,
            Security::Tls | Security::Starttls => {
                let roots = match &config.ca {
                    Some(ca) => crate::tls::read_authority(ca).map_err(|e| bad(e.to_string()))?,
                    None => crate::tls::system_roots().map_err(|e| bad(e.to_string()))?,
                };
                let mut parameters =
                    TlsParameters::builder(config.server.clone()).certificate_store(CertificateStore::None);
                for root in roots {
                    let root = Certificate::from_der(root.as_ref().to_vec()).map_err(|e| bad(format!("ca: {e}")))?;
                    parameters = parameters.add_root_certificate(root);
                }
                let parameters = parameters.build_rustls().map_err(|e| bad(format!("tls: {e}")))?;
                if config.security == Security::Tls { Tls::Wrapper(parameters) } else { Tls::Required(parameters) }
            }
        };
        let port = config.port.unwrap_or(match config.security {
            Security::Tls => 465,
            Security::Starttls => 587,
            Security::Plain => 25,
        });
        let mut builder =
            SmtpTransport::builder_dangerous(config.server.clone()).port(port).tls(tls).timeout(Some(MAIL_TIMEOUT));
        if let (Some(user), Some(password)) = (&config.user, &config.password) {
            builder = builder.credentials(Credentials::new(user.clone(), password.clone()));
        }
        Ok(Mailer { config, from, transport: builder.build() })
    }

    /// The owner's addresses that get `kind`.
    pub fn owner_addresses(&self, kind: EventKind) -> impl Iterator<Item = &str> {
        self.config.owner.iter().filter(move |o| o.events.contains(&kind)).map(|o| o.address.as_str())
    }

    /// Sends `event` to `to`; Ok once the server accepted it.
    pub fn send(&self, to: &str, event: &Event) -> Result<(), MailError> {
        let failed = |message: String| MailError::Send { to: to.to_string(), message };
        let address = parse_address(to).map_err(failed)?;
        let (subject, body) = compose(event);
        let message = Message::builder()
            .from(self.from.clone())
            .to(Mailbox::new(None, address))
            .subject(subject)
            .header(ContentType::TEXT_PLAIN)
            .body(body)
            .map_err(|e| failed(e.to_string()))?;
        self.transport.send(&message).map(|_| ()).map_err(|e| failed(e.to_string()))
    }
}

/// The subject and text of `event`'s mail.
pub fn compose(event: &Event) -> (String, String) {
    let what = serde_json::to_value(event.event).ok().and_then(|v| v.as_str().map(str::to_string)).unwrap_or_default();
    // A mail is read later: always with its date.
    let when = crate::walltime::shown_at(event.at_ms, 0);
    match &event.experiment {
        Some(e) => {
            let mut body = format!(
                "Experiment {} by {} is now {} ({when}).\n\nEvent: {what}\nEvent id: {}\n",
                e.id, e.submitter, e.state, event.id
            );
            if let Some(outcome) = &e.outcome {
                body.push_str(&format!("Outcome: {}\n", outcome.said()));
            }
            if let Some(score) = &e.score {
                let value = score.value.map_or_else(|| "none".to_string(), |v| v.to_string());
                body.push_str(&format!("Score: task {}: {} = {value}\n", score.task, score.metric.name()));
            }
            if !e.reasons.is_empty() {
                body.push_str("\nReasons:\n");
                for reason in &e.reasons {
                    body.push_str(&format!("- {reason}\n"));
                }
            }
            body.push_str(&format!("\n`subsume lab show {}` shows it whole.\n", e.id));
            (format!("[subsume lab] experiment {} {}", e.id, e.state), body)
        }
        None => match &event.robot {
            Some(robot) => (
                format!("[subsume lab] robot {}: {what}", robot.name),
                format!("Robot {}: {what} ({when}).\n\n{}\n\nEvent id: {}\n", robot.name, robot.reason, event.id),
            ),
            None => (format!("[subsume lab] {what}"), format!("Event: {what} ({when})\nEvent id: {}\n", event.id)),
        },
    }
}

/// The researchers' subscriptions, by user name, kept on disk.
pub struct Subscriptions {
    path: PathBuf,
    by_user: BTreeMap<String, Subscription>,
}

impl Subscriptions {
    /// Reads `path` (none yet: empty).
    pub fn open(path: &Path) -> Result<Subscriptions, MailError> {
        let io = |source| MailError::Io { path: path.to_path_buf(), source };
        let by_user = match std::fs::read(path) {
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => BTreeMap::new(),
            Err(e) => return Err(io(e)),
            Ok(bytes) => serde_json::from_slice(&bytes).map_err(|e| io(std::io::Error::other(e)))?,
        };
        Ok(Subscriptions { path: path.to_path_buf(), by_user })
    }

    pub fn get(&self, user: &str) -> Option<&Subscription> {
        self.by_user.get(user)
    }

    /// Sets (or with `None`, ends) `user`'s subscription, stored before it
    /// counts; a failed write changes nothing.
    pub fn set(&mut self, user: &str, subscription: Option<Subscription>) -> Result<(), MailError> {
        let mut next = self.by_user.clone();
        match subscription {
            Some(s) => {
                parse_address(&s.address).map_err(MailError::Subscription)?;
                if let Some(kind) = s.events.iter().find(|k| !RESEARCHER_EVENTS.contains(k)) {
                    return Err(MailError::Subscription(format!(
                        "{}: only the events of one's own experiments are mailed to a user",
                        serde_json::to_string(kind).unwrap_or_default()
                    )));
                }
                if !next.contains_key(user) && next.len() >= MAX_SUBSCRIPTIONS {
                    return Err(MailError::Subscription(format!("{MAX_SUBSCRIPTIONS} subscriptions already")));
                }
                next.insert(user.to_string(), s);
            }
            None => {
                next.remove(user);
            }
        }
        let bytes = serde_json::to_vec_pretty(&next).map_err(|e| MailError::Subscription(e.to_string()))?;
        write_atomically(&self.path, &bytes).map_err(|source| MailError::Io { path: self.path.clone(), source })?;
        self.by_user = next;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::notify::ExperimentFacts;

    const PASSWORD: &str = "never-shown-anywhere";

    #[test]
    fn a_bad_mail_file_is_refused_naming_what_is_wrong_and_never_the_password() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join(MAIL_FILE);
        assert!(read_mail_config(&path).unwrap().is_none(), "no file: no mail");
        let good = r#"{"server": "127.0.0.1", "port": 2525, "security": "plain", "from": "lab@example.org",
            "owner": [{"address": "owner@example.org", "events": ["robot.maintenance.started"]}]}"#;
        std::fs::write(&path, good).unwrap();
        let config = read_mail_config(&path).unwrap().unwrap();
        assert_eq!(config.owner[0].events, [EventKind::RobotMaintenanceStarted]);
        for (body, why) in [
            (
                r#"{"server": "mail.example.org", "security": "plain", "from": "lab@example.org"}"#.to_string(),
                "in clear off loopback",
            ),
            (r#"{"server": "a b", "security": "tls", "from": "lab@example.org"}"#.to_string(), "not a host name"),
            (r#"{"server": "a", "security": "tls", "from": "not an address"}"#.to_string(), "from: address"),
            (
                format!(r#"{{"server": "a", "security": "tls", "from": "l@a", "password": "{PASSWORD}"}}"#),
                "go together",
            ),
            (
                r#"{"server": "a", "security": "tls", "from": "l@a", "owner": [{"address": "o@a", "events": []}]}"#
                    .to_string(),
                "no events",
            ),
            (r#"{"server": "a", "security": "ssl3", "from": "l@a"}"#.to_string(), "unknown variant"),
            (r#"{"server": "a", "security": "tls", "from": "l@a", "extra": 1}"#.to_string(), "unknown field"),
        ] {
            std::fs::write(&path, &body).unwrap();
            let e = read_mail_config(&path).unwrap_err().to_string();
            assert!(e.contains(why) && e.contains(MAIL_FILE), "{body}: {e}");
            assert!(!e.contains(PASSWORD), "a password is never in an error: {e}");
        }
        std::fs::write(
            &path,
            r#"{"server": "mail.example.org", "security": "plain", "from": "l@a", "allow_plain": true}"#,
        )
        .unwrap();
        assert!(read_mail_config(&path).is_ok(), "plain off loopback when allowed");
    }

    #[test]
    fn subscriptions_are_kept_on_disk_and_take_only_ones_own_experiments_events() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join(SUBSCRIPTIONS_FILE);
        let mut subscriptions = Subscriptions::open(&path).unwrap();
        let ana = Subscription { address: "ana@example.org".into(), events: vec![EventKind::ExperimentEnded] };
        subscriptions.set("ana", Some(ana.clone())).unwrap();
        for (bad, why) in [
            (Subscription { address: "nope".into(), events: vec![EventKind::ExperimentEnded] }, "address"),
            (Subscription { address: "a@b".into(), events: vec![EventKind::RobotLost] }, "one's own experiments"),
        ] {
            let e = subscriptions.set("ana", Some(bad)).unwrap_err().to_string();
            assert!(e.contains(why), "{e}");
        }
        let reopened = Subscriptions::open(&path).unwrap();
        assert_eq!(reopened.get("ana"), Some(&ana), "a refused change changed nothing, on disk either");
        subscriptions.set("ana", None).unwrap();
        assert!(Subscriptions::open(&path).unwrap().get("ana").is_none());
    }

    #[test]
    fn a_mail_names_the_experiment_its_state_and_its_reasons() {
        let event = Event {
            id: 9,
            event: EventKind::ExperimentRefused,
            at_ms: 1_700_000_000_000,
            experiment: Some(ExperimentFacts {
                id: 4,
                submitter: "ana".into(),
                state: "refused".into(),
                reasons: vec!["preflight: 3 collisions".into()],
                outcome: None,
                score: None,
            }),
            robot: None,
        };
        let (subject, body) = compose(&event);
        assert_eq!(subject, "[subsume lab] experiment 4 refused");
        for part in
            ["Experiment 4 by ana is now refused", "experiment.refused", "- preflight: 3 collisions", "2023-11-14"]
        {
            assert!(body.contains(part), "{part} in {body}");
        }
    }

    #[test]
    fn a_mail_of_an_ended_run_says_its_score_apart_from_its_state() {
        let score = crate::store::task::Score {
            task: "reach-6".into(),
            metric: crate::store::task::Metric::TimeToGoal,
            value: Some(17.25),
            sub_scores: Default::default(),
            poses: 10,
            commands: 5,
            recorded_s: 25.0,
            recording_sha256: String::new(),
            built_in: Default::default(),
            scorer_sha256: None,
        };
        let event = Event {
            id: 10,
            event: EventKind::ExperimentEnded,
            at_ms: 1_700_000_000_000,
            experiment: Some(ExperimentFacts {
                id: 5,
                submitter: "ana".into(),
                state: "done".into(),
                reasons: Vec::new(),
                outcome: None,
                score: Some(score),
            }),
            robot: None,
        };
        let (_, body) = compose(&event);
        for part in ["Experiment 5 by ana is now done", "Score: task reach-6: time_to_goal_s = 17.25\n"] {
            assert!(body.contains(part), "{part} in {body}");
        }
    }
}
