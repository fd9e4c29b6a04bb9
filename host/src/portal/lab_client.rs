//! `subsume lab`: the remote lab from the command line (docs/lab.md),
//! through the portal's HTTP API, as the Lab tab uses it.
//!
//! `submit` uploads the components and stages the robot file the way
//! `subsume deploy` does: without `--robot`, the active robot file with the
//! named components pointed at the uploads; with it, the file is read and
//! parsed here first (its errors located in it, nothing sent), then its
//! named components are pointed at the uploads. The portal's diagnostics
//! are located in the person's own file (positions mapped back across those
//! edits). It then submits the staged set and follows the experiment until
//! it ends: every state it enters with its cause, its place in the queue
//! and when it is expected to start, why it did not end `done`. With
//! `--results DIR` its results are unpacked there. `list`, `show`,
//! `cancel` and `results` act on experiments; `kit` unpacks the lab kit.
//!
//! Archives (results, the kit) are unpacked as they arrive into a
//! temporary folder beside the destination, every file checked against the
//! archive's `SHA256SUMS`, and renamed into place only when all match: a
//! cut download or a damaged file leaves nothing at the destination.

use std::collections::BTreeMap;
use std::io::{Read, Write};
use std::path::{Component, Path, PathBuf};
use std::time::{Duration, Instant};

use serde::{Deserialize, Serialize};
use serde_json::{Value, json};
use sha2::{Digest, Sha256};
use thiserror::Error;

pub use super::client::Login;
use super::client::{Answer, ClientError, Connection};
use super::deploy_client::{
    Baseline, DEPLOY_TIMEOUT, DeployClientError, Edit, Portal, file_name, locate, point_source_at, read_components,
    refused, upload_source,
};
use crate::contract::clip;
use crate::deploy::{Diagnostics, SourceMap, read_and_parse, utc_time};
use crate::lab::kit_submission::{KIT_MANIFEST, KitError, KitManifest, kit_submission};
use crate::lab::{MAX_DURATION_CAP_S, MIN_DURATION_S};
use crate::store::experiments::{ExperimentRecord, ExperimentState, MAX_LABEL_LEN, Reservation, Target};

/// How often a followed experiment is asked for.
pub const POLL_INTERVAL: Duration = Duration::from_millis(500);
/// How long a followed experiment's portal may stay unreachable (a host
/// restarting) before `submit` gives up following it; the experiment goes on.
pub const MAX_UNREACHABLE: Duration = Duration::from_secs(120);
/// Largest answer to `list` read: the most records a lab keeps
/// (`MAX_EXPERIMENT_RECORDS`, a few KiB each), and no more from a host
/// that sends without end.
pub const MAX_LIST_ANSWER_BYTES: u64 = 64 << 20;
/// Largest archive unpacked: a host (or something posing as one) cannot
/// fill the researcher's disk.
pub const MAX_ARCHIVE_BYTES: u64 = 64 << 30;
/// Most files an archive may unpack into: a results bundle has a few dozen.
pub const MAX_ARCHIVE_FILES: usize = 10_000;
/// How far a queued experiment's expected start must move before it is
/// printed again.
pub const ETA_SHIFT_MS: u64 = 5_000;

/// What `subsume lab submit` asks.
#[derive(Clone, Debug)]
pub struct SubmitRequest {
    pub login: Login,
    /// The platform the uploads belong to (`control`, `network`).
    pub platform: String,
    /// (component name in the robot file, .wasm file).
    pub components: Vec<(String, PathBuf)>,
    /// A robot file; none: the active one, with the components replaced.
    pub robot: Option<PathBuf>,
    pub duration_s: f64,
    pub label: String,
    /// Unpack the results here when it ends.
    pub results: Option<PathBuf>,
    /// Which robots may run it (a lab server's; `Any` on a robot): the
    /// experiment builds on that robot's or profile's baseline.
    pub target: Target,
}

/// An experiment as the portal shows it to its submitter.
#[derive(Clone, Debug, Deserialize, Serialize)]
pub struct Experiment {
    #[serde(flatten)]
    pub record: ExperimentRecord,
    /// Place in the queue (1: next), while queued.
    #[serde(default)]
    pub place: Option<usize>,
    /// When it is expected to start (ms since the Unix epoch), while queued.
    #[serde(default)]
    pub eta_unix_ms: Option<u64>,
    /// When it ends, while it runs.
    #[serde(default)]
    pub ends_unix_ms: Option<u64>,
    /// It is next, and waits for an admin to confirm the robot was reset.
    #[serde(default)]
    pub awaiting_reset: bool,
}

/// An archive unpacked.
#[derive(Clone, Debug, PartialEq)]
pub struct Unpacked {
    pub dir: PathBuf,
    /// Files written (`SHA256SUMS` among them), and their bytes.
    pub files: usize,
    pub bytes: u64,
}

/// How a submission ended.
#[derive(Clone, Debug)]
pub struct Submitted {
    pub experiment: Experiment,
    /// Its results, when `--results` was given.
    pub results: Option<Unpacked>,
}

/// Why a lab command stopped.
#[derive(Debug, Error)]
pub enum LabClientError {
    #[error(transparent)]
    Portal(#[from] DeployClientError),
    #[error("--duration must be from {MIN_DURATION_S} to {MAX_DURATION_CAP_S} seconds, got {0}")]
    Duration(f64),
    #[error("--label must be at most {MAX_LABEL_LEN} characters, without control characters")]
    Label,
    /// The robot file does not read; nothing was sent.
    #[error("{0}\nnothing was sent")]
    Robot(Diagnostics),
    #[error("{file} has no component '{name}' (it has: {has}); nothing was sent")]
    NoSuchComponent { file: String, name: String, has: String },
    #[error("{what}: the portal at {address} gave an answer this client does not read: {why}")]
    Garbled { what: String, address: String, why: String },
    #[error("{dir}: {why}")]
    Folder { dir: String, why: String },
    #[error("{what} from {address}: {why}; nothing was written to {dir}")]
    Archive { what: String, address: String, dir: String, why: String },
    #[error(
        "the portal at {address} was unreachable for {} s ({reason}); experiment {id} goes on there: `subsume lab show {id} {address}`",
        MAX_UNREACHABLE.as_secs()
    )]
    Lost { address: String, id: u64, reason: String },
    #[error("{user} is not an admin of this lab: only admins see and change its settings")]
    NotAdmin { user: String },
    /// The lab kit's robot file cannot be submitted as it is; nothing was
    /// sent.
    #[error("{0}; nothing was sent")]
    Kit(#[from] KitError),
}

impl From<ClientError> for LabClientError {
    fn from(e: ClientError) -> LabClientError {
        LabClientError::Portal(e.into())
    }
}

/// A logged-in session that logs in again when the portal forgot it (a
/// long wait, a host restarted).
struct Session {
    password: String,
    portal: Portal,
}

impl Session {
    /// Logs in to `connection`'s portal as `login` says.
    fn open(connection: Connection, login: &Login) -> Result<Session, LabClientError> {
        let portal = Portal::login(connection, &login.user, &login.password)?;
        Ok(Session { password: login.password.clone(), portal })
    }

    fn address(&self) -> &str {
        self.portal.address()
    }

    /// Sends one request; a 401 (the portal forgot the session) logs in
    /// again and sends it once more.
    fn send(&mut self, method: &str, path: &str, body: &[u8]) -> Result<Answer, DeployClientError> {
        let once = |session: &Session| {
            let token = Some(session.portal.token.as_str());
            session.portal.connection.send(method, path, token, "application/json", body)
        };
        let answer = once(self)?;
        if answer.status != 401 {
            return Ok(answer);
        }
        self.portal.log_in_again(&self.password)?;
        Ok(once(self)?)
    }

    /// One JSON request (answers up to `limit` bytes).
    fn request(
        &mut self,
        method: &str,
        path: &str,
        body: &Value,
        what: &str,
        limit: u64,
    ) -> Result<Value, DeployClientError> {
        let body = if body.is_null() { Vec::new() } else { body.to_string().into_bytes() };
        let (status, json, text) = self.send(method, path, &body)?.read(limit)?;
        if (200..300).contains(&status) { Ok(json) } else { Err(refused(status, &json, &text, what)) }
    }

    /// Experiment `id`.
    fn experiment(&mut self, id: u64) -> Result<Experiment, LabClientError> {
        let what = format!("experiment {id}");
        let answer = self.request("GET", &format!("/api/v1/experiments/{id}"), &Value::Null, &what, DEPLOY_LIMIT)?;
        self.parse(&answer["experiment"], &what)
    }

    fn parse<T: serde::de::DeserializeOwned>(&self, value: &Value, what: &str) -> Result<T, LabClientError> {
        T::deserialize(value).map_err(|e| LabClientError::Garbled {
            what: what.to_string(),
            address: self.address().to_string(),
            why: clip(&e.to_string()),
        })
    }

    fn close(self) {
        self.portal.logout();
    }
}

/// Largest answer read for one experiment (as `deploy`'s answers).
const DEPLOY_LIMIT: u64 = super::client::MAX_ANSWER_BYTES;

/// Runs `work` in a session on `login`'s portal, logging out after.
fn in_session<T>(
    login: &Login,
    work: impl FnOnce(&mut Session) -> Result<T, LabClientError>,
) -> Result<T, LabClientError> {
    in_session_on(Connection::open(login, DEPLOY_TIMEOUT)?, login, work)
}

/// Runs `work` in a session on `connection`'s portal, logging out after.
fn in_session_on<T>(
    connection: Connection,
    login: &Login,
    work: impl FnOnce(&mut Session) -> Result<T, LabClientError>,
) -> Result<T, LabClientError> {
    let mut session = Session::open(connection, login)?;
    let result = work(&mut session);
    session.close();
    result
}

/// The robot file to stage: how it is named to the person, its name in the
/// store, the text sent, and where each position of that text is in the
/// person's file.
struct RobotFile {
    shown: String,
    name: String,
    original: String,
    text: String,
    edits: Vec<Edit>,
}

impl RobotFile {
    /// `original` with each of `components` pointed at its upload.
    fn pointed(
        shown: String,
        name: String,
        original: String,
        components: &[(String, Vec<u8>)],
        file: &str,
    ) -> Result<RobotFile, LabClientError> {
        let mut text = original.clone();
        let mut edits = Vec::new();
        for (component, _) in components {
            let (next, edit) = point_source_at(&text, component, &upload_source(component)).map_err(|has| {
                LabClientError::NoSuchComponent { file: file.to_string(), name: component.clone(), has }
            })?;
            text = next;
            edits.push(edit);
        }
        Ok(RobotFile { shown, name, original, text, edits })
    }

    /// Where line `line`, column `column` of the text sent is in the file.
    fn position(&self, line: u64, column: u64) -> (u64, u64) {
        original_position(&self.original, &self.text, &self.edits, line, column)
    }
}

/// Where line `line`, column `column` (1-based, columns in characters) of
/// `sent` (`original` after `edits`, applied in order) is in `original`.
fn original_position(original: &str, sent: &str, edits: &[Edit], line: u64, column: u64) -> (u64, u64) {
    let start: usize = sent.split_inclusive('\n').take(line.saturating_sub(1) as usize).map(str::len).sum();
    let rest = sent.get(start..).unwrap_or_default();
    let mut offset = start + rest.char_indices().nth(column.saturating_sub(1) as usize).map_or(rest.len(), |(i, _)| i);
    for edit in edits.iter().rev() {
        if offset >= edit.at + edit.inserted {
            offset = offset - edit.inserted + edit.removed;
        } else if offset > edit.at {
            offset = edit.at;
        }
    }
    let (line, column) = SourceMap::new(Path::new(""), original).line_column(offset);
    (line as u64, column as u64)
}

/// Reads and parses `path` here (nothing is sent when it does not read).
fn local_robot(path: &Path, components: &[(String, Vec<u8>)]) -> Result<RobotFile, LabClientError> {
    let text = read_and_parse(path).map_err(LabClientError::Robot)?;
    let shown = path.display().to_string();
    RobotFile::pointed(shown.clone(), file_name(path)?, text, components, &shown)
}

/// The lab kit's manifest beside robot file `path`, when it is a kit's.
fn kit_beside(path: &Path) -> Result<Option<KitManifest>, LabClientError> {
    let manifest = path.parent().unwrap_or(Path::new(".")).join(KIT_MANIFEST);
    let bytes = match std::fs::read(&manifest) {
        Ok(bytes) => bytes,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
        Err(e) => return Err(KitError::Manifest(format!("{}: {e}", manifest.display())).into()),
    };
    serde_json::from_slice(&bytes)
        .map(Some)
        .map_err(|e| KitError::Manifest(format!("{}: {e}", manifest.display())).into())
}

fn check_request(request: &SubmitRequest) -> Result<(), LabClientError> {
    let duration = request.duration_s;
    if !duration.is_finite() || !(MIN_DURATION_S..=MAX_DURATION_CAP_S).contains(&duration) {
        return Err(LabClientError::Duration(duration));
    }
    let label = request.label.trim();
    if label.chars().count() > MAX_LABEL_LEN || label.chars().any(char::is_control) {
        return Err(LabClientError::Label);
    }
    Ok(())
}

/// Where `submit` tells what happens: `progress` (uploads, staging) and
/// `states` (the experiment's life, a line each).
pub struct Say<'a> {
    pub progress: &'a mut dyn FnMut(&str),
    pub states: &'a mut dyn FnMut(&str),
}

/// Uploads, stages and submits `request`, and follows the experiment until
/// it ends (then unpacks its results when asked).
pub fn submit(request: &SubmitRequest, say: &mut Say<'_>) -> Result<Submitted, LabClientError> {
    check_request(request)?;
    let connection = Connection::open(&request.login, DEPLOY_TIMEOUT)?;
    if let Some(dir) = &request.results {
        check_destination(dir)?;
    }
    // Everything local first: a missing file, a file that is not a
    // component or a broken robot file changes nothing remotely.
    let components = read_components(&request.components)?;
    let local = request.robot.as_deref().map(|path| local_robot(path, &components)).transpose()?;
    let kit = request.robot.as_deref().map(kit_beside).transpose()?.flatten();
    in_session_on(connection, &request.login, |session| {
        let mut components = components;
        let robot = match (local, kit, request.robot.as_deref()) {
            (Some(local), Some(manifest), Some(path)) => {
                // The lab kit's robot file: the baseline with her changes.
                let Baseline { set, name, text, whose } = session.portal.baseline_robot(&request.target)?;
                let dir = path.parent().unwrap_or(Path::new("."));
                let sha_of = |source: &str| {
                    std::fs::read(dir.join(source)).ok().map(|bytes| hex::encode(Sha256::digest(&bytes)))
                };
                let sent = kit_submission(&manifest, path, &local.original, set, &text, &sha_of)?;
                // Her --component flags come last: they win.
                let kit_uploads: Vec<(String, PathBuf)> = sent
                    .uploads
                    .iter()
                    .filter(|(c, _)| !components.iter().any(|(given, _)| given == c))
                    .map(|(c, source)| (c.clone(), dir.join(source)))
                    .collect();
                let mut all = read_components(&kit_uploads)?;
                all.append(&mut components);
                components = all;
                let shown = format!("{} (on {whose}, set {set})", local.shown);
                let file = format!("the baseline's robot file {name}");
                let robot = RobotFile::pointed(shown, name.clone(), sent.text, &components, &file)?;
                let hash = hex::encode(Sha256::digest(text.as_bytes()));
                let changes = if sent.changes.is_empty() {
                    "no changes: the kit as it came".to_string()
                } else {
                    sent.changes.join("; ")
                };
                (say.progress)(&format!(
                    "building on {whose} {name} (set {set}, sha256 {hash}) with the changes of {}: {changes}",
                    local.shown
                ));
                robot
            }
            (Some(robot), _, _) => robot,
            (None, _, _) => {
                // The lab's baseline, never whatever runs now (another
                // researcher's experiment, say).
                let Baseline { set, name, text, whose } = session.portal.baseline_robot(&request.target)?;
                let shown = format!("{name} ({whose})");
                let file = format!("the baseline's robot file {name}");
                let robot = RobotFile::pointed(shown, name.clone(), text.clone(), &components, &file)?;
                let pointed: Vec<String> =
                    components.iter().map(|(c, _)| format!("{c} -> {}", upload_source(c))).collect();
                let with = if pointed.is_empty() { String::new() } else { format!(" with {}", pointed.join(", ")) };
                let hash = hex::encode(Sha256::digest(text.as_bytes()));
                (say.progress)(&format!("building on {whose} {name} (set {set}, sha256 {hash}){with}"));
                robot
            }
        };
        if !components.is_empty() {
            session.portal.check_may_change(&request.platform)?;
        }
        for (component, bytes) in &components {
            session.portal.upload(&request.platform, component, bytes, say.progress)?;
        }
        let position = |line, column| robot.position(line, column);
        let set =
            session.portal.stage(&request.platform, &robot.name, robot.text.as_bytes(), &robot.shown, &position)?;
        (say.progress)(&format!("staged {} as set {set}; submitting...", robot.shown));
        let mut body = json!({ "set": set, "duration_s": request.duration_s, "label": request.label.trim() });
        if request.target != Target::Any {
            body["target"] = json!(request.target);
        }
        let what = format!("submitting set {set}");
        let answer = match session.request("POST", "/api/v1/experiments", &body, &what, DEPLOY_LIMIT) {
            Ok(answer) => answer,
            Err(e) => {
                // A refused submission leaves nothing staged behind.
                let forgotten = format!("forgetting set {set}");
                match session.request("DELETE", &format!("/api/v1/sets/{set}"), &Value::Null, &forgotten, DEPLOY_LIMIT)
                {
                    Ok(_) => (say.progress)(&format!("the submission was refused: set {set} is forgotten")),
                    Err(why) => (say.progress)(&format!("the submission was refused; set {set} stays: {why}")),
                }
                return Err(locate(e, &robot.shown, &position).into());
            }
        };
        let record: ExperimentRecord = session.parse(&answer["experiment"], &what)?;
        let label = if record.label.is_empty() { String::new() } else { format!(", \"{}\"", record.label) };
        (say.states)(&format!(
            "experiment {} submitted: set {set}, {} s{label}; follow it with `subsume lab show {} {}`",
            record.id,
            record.duration_s,
            record.id,
            session.address()
        ));
        let experiment = follow(session, record.id, say)?;
        let results = match &request.results {
            Some(dir) => {
                let what = format!("the results of experiment {}", record.id);
                let path = format!("/api/v1/experiments/{}/results", record.id);
                let unpacked = download(session, &path, &what, dir)?;
                (say.states)(&unpacked_text(record.id, &unpacked));
                Some(unpacked)
            }
            None => None,
        };
        Ok(Submitted { experiment, results })
    })
}

/// Follows experiment `id` until it ends, telling each change.
fn follow(session: &mut Session, id: u64, say: &mut Say<'_>) -> Result<Experiment, LabClientError> {
    let mut seen = Seen::default();
    let mut unreachable: Option<Instant> = None;
    loop {
        match session.experiment(id) {
            Ok(experiment) => {
                unreachable = None;
                for line in seen.news(&experiment, now_ms()) {
                    (say.states)(&line);
                }
                if experiment.record.state.is_final() {
                    if let Some(outcome) = experiment.record.run.as_ref().and_then(|r| r.outcome.as_ref()) {
                        (say.states)(&format!("outcome of experiment {id}: {}", outcome.said()));
                    }
                    return Ok(experiment);
                }
            }
            Err(LabClientError::Portal(DeployClientError::Portal(ClientError::Connect { reason, .. }))) => {
                let since = *unreachable.get_or_insert_with(|| {
                    (say.progress)(&format!(
                        "the portal at {} is unreachable ({reason}); trying again",
                        session.address()
                    ));
                    Instant::now()
                });
                if since.elapsed() > MAX_UNREACHABLE {
                    return Err(LabClientError::Lost { address: session.address().to_string(), id, reason });
                }
            }
            Err(e) => return Err(e),
        }
        std::thread::sleep(POLL_INTERVAL);
    }
}

/// What was told of a followed experiment already.
#[derive(Debug, Default)]
struct Seen {
    /// States of its history told.
    states: usize,
    /// The queue place and expected start told last.
    place: Option<(usize, Option<u64>)>,
    awaiting_reset: bool,
}

impl Seen {
    /// The lines to tell about `experiment` now (`now_ms`), given what was
    /// told before.
    fn news(&mut self, experiment: &Experiment, now_ms: u64) -> Vec<String> {
        let record = &experiment.record;
        let id = record.id;
        let mut lines = Vec::new();
        let new_states = record.history.len() > self.states;
        for (i, change) in record.history.iter().enumerate().skip(self.states) {
            let mut line = format!("experiment {id}: {}", said(change.state, &change.cause));
            let latest = i + 1 == record.history.len();
            if latest
                && change.state == ExperimentState::Running
                && let Some(ends) = experiment.ends_unix_ms
            {
                line.push_str(&format!(" (ends at {}, in {})", utc_time(ends), span(ends.saturating_sub(now_ms))));
            }
            lines.push(line);
        }
        self.states = record.history.len();
        if record.state == ExperimentState::Queued
            && let Some(place) = experiment.place
        {
            let moved = match self.place {
                Some((told, told_eta)) => {
                    told != place
                        || told_eta.is_some() != experiment.eta_unix_ms.is_some()
                        || told_eta.zip(experiment.eta_unix_ms).is_some_and(|(a, b)| a.abs_diff(b) >= ETA_SHIFT_MS)
                }
                None => true,
            };
            if moved || new_states {
                self.place = Some((place, experiment.eta_unix_ms));
                lines.push(format!("experiment {id}: queued: {}", queue_place(place, experiment.eta_unix_ms, now_ms)));
            }
        }
        if experiment.awaiting_reset && !self.awaiting_reset {
            lines.push(format!(
                "experiment {id}: next, waiting for the robot to be reset (an admin confirms it in the portal)"
            ));
        }
        self.awaiting_reset = experiment.awaiting_reset;
        if record.state.is_final() {
            let cause = record.history.last().map(|c| c.cause.as_str());
            lines.extend(record.reasons.iter().filter(|r| Some(r.as_str()) != cause).map(|r| format!("  {r}")));
        }
        lines
    }
}

/// `STATE: CAUSE`, without the state twice when the cause names it
/// already (`aborted: emergency stop by ...`, not `aborted: aborted: ...`).
fn said(state: ExperimentState, cause: &str) -> String {
    let name = state.name();
    match cause.strip_prefix(name).and_then(|rest| rest.strip_prefix(": ")) {
        Some(_) => cause.to_string(),
        None => format!("{name}: {cause}"),
    }
}

/// `place 2 in the queue, starts in about 1 min 5 s (at 18:05:00 UTC)`.
fn queue_place(place: usize, eta_unix_ms: Option<u64>, now_ms: u64) -> String {
    let when = match eta_unix_ms {
        Some(at) if at <= now_ms => "starts now".to_string(),
        Some(at) => format!("starts in about {} (at {})", span(at - now_ms), utc_time(at)),
        None => "no estimate while the queue is held (paused, or a reservation)".to_string(),
    };
    format!("place {place} in the queue, {when}")
}

/// A span of time in words: `45 s`, `3 min 5 s`, `2 h 5 min`.
fn span(ms: u64) -> String {
    let s = ms.div_ceil(1000);
    match s {
        0..60 => format!("{s} s"),
        60..3600 if s.is_multiple_of(60) => format!("{} min", s / 60),
        60..3600 => format!("{} min {} s", s / 60, s % 60),
        _ => format!("{} h {} min", s / 3600, s / 60 % 60),
    }
}

/// A size in words: `900 B`, `12.5 KiB`, `3.1 MiB`.
fn size(bytes: u64) -> String {
    match bytes {
        0..1024 => format!("{bytes} B"),
        1024..1_048_576 => format!("{:.1} KiB", bytes as f64 / 1024.0),
        _ => format!("{:.1} MiB", bytes as f64 / 1_048_576.0),
    }
}

/// The caller's experiments (an admin's: every one), newest first.
pub fn list(login: &Login) -> Result<Vec<Experiment>, LabClientError> {
    in_session(login, |session| {
        let what = "listing experiments";
        let answer = session.request("GET", "/api/v1/experiments", &Value::Null, what, MAX_LIST_ANSWER_BYTES)?;
        session.parse(&answer["experiments"], what)
    })
}

/// Books the robot from `start_ms` to `end_ms` (ms since the Unix epoch)
/// for the caller (or, for an admin, for `user`).
pub fn reserve(login: &Login, start_ms: u64, end_ms: u64, user: Option<&str>) -> Result<Reservation, LabClientError> {
    in_session(login, |session| {
        let mut body = json!({ "start_ms": start_ms, "end_ms": end_ms });
        if let Some(user) = user {
            body["user"] = json!(user);
        }
        let what = "booking the robot";
        let answer = session.request("POST", "/api/v1/lab/reservations", &body, what, DEPLOY_LIMIT)?;
        session.parse(&answer["reservation"], what)
    })
}

/// What a maintenance took out of service, or brought back.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum MaintenanceOf {
    /// One robot: its queue holds.
    Robot,
    /// A lab server's whole lab: no experiment goes to any robot.
    Lab,
}

/// Takes the robot (on a lab server: the whole lab) out of service
/// (admins) with `reason`, or with `None` brings it back; which it was.
pub fn maintenance(login: &Login, reason: Option<&str>) -> Result<MaintenanceOf, LabClientError> {
    in_session(login, |session| {
        let (method, body, what) = match reason {
            Some(reason) => ("POST", json!({ "reason": reason }), "taking the lab out of service"),
            None => ("DELETE", Value::Null, "bringing the lab back into service"),
        };
        session.request(method, "/api/v1/lab/maintenance", &body, what, DEPLOY_LIMIT)?;
        // A lab server's view lists its robots; one robot's does not.
        let lab = session.request("GET", "/api/v1/lab", &Value::Null, "reading the lab", DEPLOY_LIMIT)?;
        Ok(if lab["lab"]["robots"].is_array() { MaintenanceOf::Lab } else { MaintenanceOf::Robot })
    })
}

/// Runs the owner's self-test now (admins): its result.
pub fn self_test(login: &Login) -> Result<crate::store::experiments::SelfTest, LabClientError> {
    in_session(login, |session| {
        let what = "running the self-test";
        let answer = session.request("POST", "/api/v1/lab/selftest", &Value::Null, what, DEPLOY_LIMIT)?;
        session.parse(&answer["self_test"], what)
    })
}

/// The reservations not over yet, soonest first.
pub fn reservations(login: &Login) -> Result<Vec<Reservation>, LabClientError> {
    in_session(login, |session| {
        let what = "reading the lab's reservations";
        let answer = session.request("GET", "/api/v1/lab", &Value::Null, what, MAX_LIST_ANSWER_BYTES)?;
        let mut reservations: Vec<Reservation> = session.parse(&answer["lab"]["reservations"], what)?;
        reservations.sort_by_key(|r| r.start_ms);
        Ok(reservations)
    })
}

/// Cancels reservation `id` (one's own; an admin: any).
pub fn unreserve(login: &Login, id: u64) -> Result<(), LabClientError> {
    in_session(login, |session| {
        let what = format!("cancelling reservation {id}");
        session.request("DELETE", &format!("/api/v1/lab/reservations/{id}"), &Value::Null, &what, DEPLOY_LIMIT)?;
        Ok(())
    })
}

/// The owner's settings (admins), as `GET /api/v1/lab` shows them.
pub fn settings(login: &Login) -> Result<Value, LabClientError> {
    in_session(login, |session| {
        let what = "reading the lab's settings";
        let answer = session.request("GET", "/api/v1/lab", &Value::Null, what, DEPLOY_LIMIT)?;
        match &answer["lab"]["settings"] {
            Value::Null => Err(LabClientError::NotAdmin { user: login.user.clone() }),
            settings => Ok(settings.clone()),
        }
    })
}

/// Replaces the owner's settings (admins) with `settings`; the portal's
/// answer, as stored.
pub fn set_settings(login: &Login, settings: &Value) -> Result<Value, LabClientError> {
    in_session(login, |session| {
        let what = "changing the lab's settings";
        let answer = session.request("PUT", "/api/v1/lab/settings", settings, what, DEPLOY_LIMIT)?;
        Ok(answer["settings"].clone())
    })
}

/// `subsume lab reservations`'s text: one line each, with its date.
pub fn reservations_text(reservations: &[Reservation], now_ms: u64) -> String {
    if reservations.is_empty() {
        return "no reservations\n".into();
    }
    let mut out = String::new();
    for r in reservations {
        let now = if r.contains(now_ms) { "  (now)" } else { "" };
        out.push_str(&format!(
            "{:>4}  {:<12}  {} to {} ({}){now}\n",
            r.id,
            r.user,
            crate::walltime::shown_at(r.start_ms, 0),
            crate::walltime::shown_at(r.end_ms, 0),
            span(r.end_ms.saturating_sub(r.start_ms))
        ));
    }
    out
}

/// Experiment `id`.
pub fn show(login: &Login, id: u64) -> Result<Experiment, LabClientError> {
    in_session(login, |session| session.experiment(id))
}

/// Cancels experiment `id`: its record once the portal answered (a running
/// experiment's once the robot runs the baseline again).
pub fn cancel(login: &Login, id: u64) -> Result<ExperimentRecord, LabClientError> {
    in_session(login, |session| {
        let what = format!("cancelling experiment {id}");
        let answer =
            session.request("POST", &format!("/api/v1/experiments/{id}/cancel"), &Value::Null, &what, DEPLOY_LIMIT)?;
        session.parse(&answer["experiment"], &what)
    })
}

/// Unpacks experiment `id`'s results into `dir`.
pub fn results(login: &Login, id: u64, dir: &Path) -> Result<Unpacked, LabClientError> {
    check_destination(dir)?;
    in_session(login, |session| {
        let what = format!("the results of experiment {id}");
        download(session, &format!("/api/v1/experiments/{id}/results"), &what, dir)
    })
}

/// Unpacks the lab kit into `dir`.
pub fn kit(login: &Login, dir: &Path) -> Result<Unpacked, LabClientError> {
    check_destination(dir)?;
    in_session(login, |session| download(session, "/api/v1/lab/kit", "the lab kit", dir))
}

/// `dir` must not exist, or be an empty folder: results never mix with
/// other files, and nothing is overwritten.
fn check_destination(dir: &Path) -> Result<(), LabClientError> {
    let folder = |why: String| LabClientError::Folder { dir: dir.display().to_string(), why };
    match std::fs::read_dir(dir) {
        Ok(mut entries) => match entries.next() {
            Some(_) => Err(folder("is not empty; give a new or empty folder".into())),
            None => Ok(()),
        },
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(()),
        Err(e) => Err(folder(e.to_string())),
    }
}

/// Fails a read past `left` bytes (instead of cutting the archive short).
struct Bounded<R> {
    inner: R,
    left: u64,
}

impl<R: Read> Read for Bounded<R> {
    fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
        let n = self.inner.read(buf)?;
        self.left = self.left.checked_sub(n as u64).ok_or_else(|| {
            std::io::Error::other(format!("the archive is larger than {MAX_ARCHIVE_BYTES} bytes, the most unpacked"))
        })?;
        Ok(n)
    }
}

/// Downloads the tar archive at `path` and unpacks it into `dir` (see the
/// module's doc).
fn download(session: &mut Session, path: &str, what: &str, dir: &Path) -> Result<Unpacked, LabClientError> {
    let answer = session.send("GET", path, b"")?;
    if answer.status != 200 {
        let (status, json, text) = answer.read(DEPLOY_LIMIT)?;
        return Err(refused(status, &json, &text, what).into());
    }
    let archive_error = |why: String| LabClientError::Archive {
        what: what.to_string(),
        address: session.address().to_string(),
        dir: dir.display().to_string(),
        why,
    };
    let folder_error = |why: String| LabClientError::Folder { dir: dir.display().to_string(), why };
    let parent = match dir.parent() {
        Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
        _ => PathBuf::from("."),
    };
    std::fs::create_dir_all(&parent).map_err(|e| folder_error(format!("cannot make its folder: {e}")))?;
    let staging = tempfile::Builder::new()
        .prefix(".subsume-download-")
        .tempdir_in(&parent)
        .map_err(|e| folder_error(format!("cannot make a temporary folder beside it: {e}")))?;
    let written = unpack(Bounded { inner: answer.into_reader(), left: MAX_ARCHIVE_BYTES }, staging.path())
        .map_err(archive_error)?;
    // Into place: an empty folder there is replaced.
    if dir.exists() {
        std::fs::remove_dir(dir).map_err(|e| folder_error(e.to_string()))?;
    }
    let kept = staging.keep();
    std::fs::rename(&kept, dir).map_err(|e| {
        let _ = std::fs::remove_dir_all(&kept);
        folder_error(format!("cannot move the unpacked files into place: {e}"))
    })?;
    Ok(Unpacked { dir: dir.to_path_buf(), files: written.len(), bytes: written.values().map(|(_, n)| n).sum() })
}

/// Unpacks the tar archive `archive` (every file under one folder) into
/// `dir` without that folder, syncing each file, and checks every file
/// against its `SHA256SUMS`. Returns each file's sha256 and size.
fn unpack(archive: impl Read, dir: &Path) -> Result<BTreeMap<String, (String, u64)>, String> {
    let mut archive = tar::Archive::new(archive);
    let mut written: BTreeMap<String, (String, u64)> = BTreeMap::new();
    let mut top: Option<String> = None;
    for entry in archive.entries().map_err(|e| format!("not a tar archive: {e}"))? {
        let mut entry = entry.map_err(|e| format!("the archive is cut or damaged: {e}"))?;
        let shown = clip(&entry.path_bytes().escape_ascii().to_string());
        let path = entry.path().map_err(|e| format!("entry '{shown}': {e}"))?.into_owned();
        let mut parts = Vec::new();
        for part in path.components() {
            match part {
                Component::Normal(p) => parts.push(p.to_str().ok_or_else(|| format!("entry '{shown}' is not utf-8"))?),
                _ => return Err(format!("entry '{shown}' is not a plain relative path")),
            }
        }
        let kind = entry.header().entry_type();
        if kind.is_dir() {
            continue;
        }
        if !kind.is_file() {
            return Err(format!("entry '{shown}' is not a regular file"));
        }
        let (first, rest) = match parts.split_first() {
            Some((first, rest)) if !rest.is_empty() => (*first, rest),
            _ => return Err(format!("entry '{shown}' is not inside the archive's folder")),
        };
        if *top.get_or_insert_with(|| first.to_string()) != first {
            return Err(format!("entry '{shown}' is outside the archive's folder '{}'", top.unwrap_or_default()));
        }
        let name = rest.join("/");
        if written.contains_key(&name) {
            return Err(format!("'{name}' is in the archive twice"));
        }
        if written.len() >= MAX_ARCHIVE_FILES {
            return Err(format!("more than {MAX_ARCHIVE_FILES} files"));
        }
        let target = rest.iter().fold(dir.to_path_buf(), |path, part| path.join(part));
        if let Some(parent) = target.parent() {
            std::fs::create_dir_all(parent).map_err(|e| format!("cannot make {}: {e}", parent.display()))?;
        }
        let mut file = std::fs::File::create_new(&target).map_err(|e| format!("cannot write {name}: {e}"))?;
        let mut hash = Sha256::new();
        let mut bytes = 0u64;
        let mut buffer = vec![0u8; 64 << 10];
        loop {
            let n = entry.read(&mut buffer).map_err(|e| format!("the archive is cut or damaged at '{name}': {e}"))?;
            if n == 0 {
                break;
            }
            hash.update(&buffer[..n]);
            file.write_all(&buffer[..n]).map_err(|e| format!("cannot write {name}: {e}"))?;
            bytes += n as u64;
        }
        file.sync_all().map_err(|e| format!("cannot write {name}: {e}"))?;
        written.insert(name, (hex::encode(hash.finalize()), bytes));
    }
    check_sums(dir, &written)?;
    Ok(written)
}

/// Every file unpacked is listed in `SHA256SUMS` with its sha256, and
/// every file listed was unpacked.
fn check_sums(dir: &Path, written: &BTreeMap<String, (String, u64)>) -> Result<(), String> {
    const SUMS: &str = crate::lab::bundle::SUMS;
    if !written.contains_key(SUMS) {
        return Err(format!("it has no {SUMS}: it was cut short"));
    }
    let text = std::fs::read_to_string(dir.join(SUMS)).map_err(|e| format!("{SUMS}: {e}"))?;
    let mut listed = BTreeMap::new();
    for (i, line) in text.lines().enumerate() {
        let Some((sum, name)) = line.split_once("  ") else {
            return Err(format!("{SUMS}:{}: not 'SHA256  NAME'", i + 1));
        };
        listed.insert(name.to_string(), sum.to_string());
    }
    for (name, (sum, _)) in written.iter().filter(|(name, _)| name.as_str() != SUMS) {
        match listed.remove(name) {
            Some(expected) if expected == *sum => {}
            Some(_) => return Err(format!("{name} does not match its sha256 in {SUMS}")),
            None => return Err(format!("{name} is not listed in {SUMS}")),
        }
    }
    match listed.keys().next() {
        Some(missing) => Err(format!("{missing}, listed in {SUMS}, is not in the archive")),
        None => Ok(()),
    }
}

/// Now, in ms since the Unix epoch.
pub fn now_ms() -> u64 {
    std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map_or(0, |d| d.as_millis() as u64)
}

/// How long ago `at_ms` was, in whole minutes past the first: `12 min ago`.
fn ago(at_ms: u64, now_ms: u64) -> String {
    let ms = now_ms.saturating_sub(at_ms);
    let ms = if ms >= 60_000 { ms / 60_000 * 60_000 } else { ms };
    format!("{} ago", span(ms))
}

/// A state with the queue place: `queued #2`.
fn state_text(experiment: &Experiment) -> String {
    match experiment.place {
        Some(place) if experiment.record.state == ExperimentState::Queued => format!("queued #{place}"),
        _ => experiment.record.state.to_string(),
    }
}

/// `subsume lab list`'s table.
pub fn list_text(experiments: &[Experiment], now_ms: u64) -> String {
    if experiments.is_empty() {
        return "no experiments\n".to_string();
    }
    let rows: Vec<[String; 7]> = experiments
        .iter()
        .map(|e| {
            let r = &e.record;
            [
                r.id.to_string(),
                state_text(e),
                r.submitter.clone(),
                r.set.to_string(),
                format!("{} s", r.duration_s),
                ago(r.submitted_ms, now_ms),
                r.label.clone(),
            ]
        })
        .collect();
    let head = ["ID", "STATE", "SUBMITTER", "SET", "DURATION", "SUBMITTED", "LABEL"].map(String::from);
    let mut widths = [0usize; 7];
    for row in std::iter::once(&head).chain(&rows) {
        for (width, cell) in widths.iter_mut().zip(row) {
            *width = (*width).max(cell.chars().count());
        }
    }
    let mut out = String::new();
    for row in std::iter::once(&head).chain(&rows) {
        let cells: Vec<String> = row.iter().zip(widths).map(|(cell, width)| format!("{cell:<width$}")).collect();
        out.push_str(cells.join("  ").trim_end());
        out.push('\n');
    }
    out
}

/// What `lab submit --results` and `lab results` say of an unpacked
/// bundle, alike: its files and bytes as unpacked, and that they are the
/// result files `lab show` counts plus the bundle's own.
pub fn unpacked_text(id: u64, unpacked: &Unpacked) -> String {
    format!(
        "results of experiment {id}: {} ({} files, {}, sha256 checked: the result files `lab show` counts, \
         with experiment.json, robot.xml, the components and SHA256SUMS)",
        unpacked.dir.display(),
        unpacked.files,
        size(unpacked.bytes)
    )
}

/// `subsume lab show`'s text.
pub fn show_text(experiment: &Experiment, now_ms: u64) -> String {
    let r = &experiment.record;
    let mut out = format!("experiment {}: {}\n", r.id, state_text(experiment));
    let mut field = |name: &str, value: String| out.push_str(&format!("  {name:<11}{value}\n"));
    field("submitter", r.submitter.clone());
    field("set", r.set.to_string());
    if !r.label.is_empty() {
        field("label", r.label.clone());
    }
    field("duration", format!("{} s", r.duration_s));
    field("submitted", format!("{} ({})", utc_time(r.submitted_ms), ago(r.submitted_ms, now_ms)));
    if let Some(place) = experiment.place.filter(|_| r.state == ExperimentState::Queued) {
        field("queue", queue_place(place, experiment.eta_unix_ms, now_ms));
    }
    if let Some(ends) = experiment.ends_unix_ms {
        field("ends", format!("{} (in {})", utc_time(ends), span(ends.saturating_sub(now_ms))));
    }
    if experiment.awaiting_reset {
        field("waiting", "for the robot to be reset (an admin confirms it in the portal)".into());
    }
    if let Some(reset) = &r.reset {
        let at = |p: &Option<crate::store::experiments::Pose>| {
            p.map_or("no pose".to_string(), |p| format!("({:.2}, {:.2}, {:.2} rad)", p.x, p.y, p.heading))
        };
        let how = match &reset.error {
            None => format!("driven back in {:.1} s from {} to {}", reset.took_s, at(&reset.from), at(&reset.pose)),
            Some(error) => format!("failed after {:.1} s: {error}", reset.took_s),
        };
        field("reset", how);
    }
    if let Some(p) = &r.preflight {
        let verdict = if p.passed { "passed" } else { "refused" };
        let ended = p.ended_by.map(|end| format!(", ended: {}", end.name())).unwrap_or_default();
        field("preflight", format!("{verdict}: {} s simulated in {:.1} s{ended}", p.simulated_s, p.wall_s));
    }
    if let Some(run) = &r.run {
        field(
            "run",
            format!(
                "{:.1} s on the robot, {} late cycles (worst lateness {:.1} ms)",
                run.ran_s, run.late_cycles, run.worst_lateness_ms
            ),
        );
        if let Some(outcome) = &run.outcome {
            field("outcome", outcome.said());
        }
    }
    if let Some(score) = &r.score {
        let shown = |v: Option<f64>| v.map_or_else(|| "none".to_string(), |v| v.to_string());
        let simulated = r
            .preflight
            .as_ref()
            .and_then(|p| p.score.as_ref())
            .map_or(String::new(), |p| format!(" (the preflight's: {})", shown(p.value)));
        field("score", format!("task {}: {} = {}{simulated}", score.task, score.metric.name(), shown(score.value)));
    }
    if !r.results.is_empty() || r.recording_expired {
        let bytes: u64 = r.results.iter().map(|f| f.bytes).sum();
        let expired = if r.recording_expired { "; its recordings expired" } else { "" };
        field(
            "results",
            format!(
                "{} result files, {}{expired} (the bundle adds experiment.json, robot.xml, the components and SHA256SUMS)",
                r.results.len(),
                size(bytes)
            ),
        );
    }
    out.push_str("  history\n");
    for change in &r.history {
        out.push_str(&format!("    {}  {:<10} {}\n", utc_time(change.at_ms), change.state.name(), change.cause));
    }
    if !r.components.is_empty() {
        out.push_str("  components\n");
        let width = r.components.iter().map(|c| c.name.chars().count()).max().unwrap_or(0);
        for c in &r.components {
            let sha = c.sha256.as_deref().unwrap_or("built-in");
            out.push_str(&format!("    {:<width$}  {sha}  {}\n", c.name, c.source));
        }
    }
    if !r.reasons.is_empty() {
        out.push_str("  reasons\n");
        for reason in &r.reasons {
            out.push_str(&format!("    {reason}\n"));
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn experiment(states: &[(ExperimentState, u64, &str)]) -> Experiment {
        let history: Vec<Value> =
            states.iter().map(|(s, at, cause)| json!({"state": s, "at_ms": at, "cause": cause})).collect();
        let last = states.last().map_or(ExperimentState::Checking, |s| s.0);
        serde_json::from_value(json!({
            "format": 1, "id": 7, "submitter": "ada", "set": 3, "label": "", "duration_s": 60.0,
            "submitted_ms": 1000, "state": last, "history": history, "reasons": [],
            "settings": {
                "max_duration_s": 120.0,
                "limits": {"max_queued": 3, "robot_minutes_per_day": 30.0, "max_reservation_s": 1800, "reservation_per_day_s": 3600},
                "criteria": {"max_collisions": 0, "allow_faults": false, "allow_geofence": false, "allow_stop_zone": false},
                "reset": "sim", "preflight_world": null, "baseline": 1
            },
            "place": null, "eta_unix_ms": null, "ends_unix_ms": null, "awaiting_reset": false
        }))
        .unwrap()
    }

    /// The lines told at each poll of one experiment's life, as the portal
    /// shows it at each.
    #[test]
    fn a_state_is_said_once_even_when_its_cause_names_it() {
        use ExperimentState::*;
        let cases = [
            (Aborted, "aborted: emergency stop by admin (portal)", "aborted: emergency stop by admin (portal)"),
            (Cancelled, "cancelled by ana", "cancelled: cancelled by ana"),
            (Failed, "failed: the host was too busy", "failed: the host was too busy"),
            (Refused, "refused by its preflight", "refused: refused by its preflight"),
            (Done, "its time is up", "done: its time is up"),
            (Aborted, "aborted:no space", "aborted: aborted:no space"),
        ];
        for (state, cause, expected) in cases {
            assert_eq!(super::said(state, cause), expected, "{cause}");
        }
    }

    #[test]
    fn each_state_is_told_once_with_the_queue_place_and_the_reasons_at_the_end() {
        use ExperimentState::*;
        let mut history = vec![(Checking, 0, "submitted by ada")];
        let mut seen = Seen::default();
        let mut polls: Vec<(Experiment, Vec<String>)> = Vec::new();
        let mut poll = |e: Experiment, now: u64, seen: &mut Seen| {
            let lines = seen.news(&e, now);
            polls.push((e, lines.clone()));
            lines
        };
        assert_eq!(poll(experiment(&history), 0, &mut seen), ["experiment 7: checking: submitted by ada"]);
        assert_eq!(poll(experiment(&history), 500, &mut seen), Vec::<String>::new(), "nothing new");
        // Two states between polls: both told, in order.
        history.push((Preflight, 600, "checked; it runs in the simulator first"));
        history.push((Queued, 900, "passed its preflight; queued"));
        let queued = |place, eta| Experiment { place: Some(place), eta_unix_ms: eta, ..experiment(&history) };
        let eta = 1_795_000_000_000 + 65_000;
        assert_eq!(
            poll(queued(2, Some(eta)), 1_795_000_000_000, &mut seen),
            [
                "experiment 7: preflight: checked; it runs in the simulator first",
                "experiment 7: queued: passed its preflight; queued",
                &format!(
                    "experiment 7: queued: place 2 in the queue, starts in about 1 min 5 s (at {})",
                    utc_time(eta)
                ),
            ]
        );
        assert!(
            poll(queued(2, Some(eta + 1000)), 1_795_000_001_000, &mut seen).is_empty(),
            "a small shift is not told"
        );
        assert_eq!(
            poll(queued(1, Some(eta)), 1_795_000_010_000, &mut seen),
            [format!("experiment 7: queued: place 1 in the queue, starts in about 55 s (at {})", utc_time(eta))]
        );
        assert_eq!(
            poll(queued(1, None), 1_795_000_011_000, &mut seen),
            [
                "experiment 7: queued: place 1 in the queue, no estimate while the queue is held (paused, or a reservation)"
            ]
        );
        let waiting = Experiment { awaiting_reset: true, ..queued(1, None) };
        assert_eq!(
            poll(waiting.clone(), 1_795_000_012_000, &mut seen),
            ["experiment 7: next, waiting for the robot to be reset (an admin confirms it in the portal)"]
        );
        assert!(poll(waiting, 1_795_000_013_000, &mut seen).is_empty());
        history.push((Running, 1_795_000_020_000, "started on the robot"));
        let running = Experiment { ends_unix_ms: Some(1_795_000_080_000), ..experiment(&history) };
        assert_eq!(
            poll(running, 1_795_000_020_000, &mut seen),
            [format!(
                "experiment 7: running: started on the robot (ends at {}, in 1 min)",
                utc_time(1_795_000_080_000)
            )]
        );
        history.push((Aborted, 1_795_000_030_000, "emergency stop by admin"));
        let mut aborted = experiment(&history);
        aborted.record.reasons = vec!["emergency stop by admin".into(), "its recording was kept".into()];
        assert_eq!(
            poll(aborted, 1_795_000_031_000, &mut seen),
            ["experiment 7: aborted: emergency stop by admin", "  its recording was kept"],
            "a reason that repeats the cause is not told twice"
        );
        assert_eq!(polls.len(), 10);
    }

    #[test]
    fn spans_and_sizes_read_as_words() {
        for (ms, text) in [
            (0, "0 s"),
            (1, "1 s"),
            (59_000, "59 s"),
            (60_000, "1 min"),
            (65_000, "1 min 5 s"),
            (7_500_000, "2 h 5 min"),
        ] {
            assert_eq!(span(ms), text, "{ms}");
        }
        for (bytes, text) in [(900, "900 B"), (12_800, "12.5 KiB"), (3_250_586, "3.1 MiB")] {
            assert_eq!(size(bytes), text, "{bytes}");
        }
    }

    /// (case, file, components repointed, (line, column) in the text sent,
    /// the position expected in the file).
    #[test]
    fn positions_in_the_text_sent_map_back_to_the_file() {
        let file = "<robot name=\"r\">\n  <platform name=\"control\">\n    <component name=\"plan\" source=\"build/long/path/plan.wasm\" rate=\"bad\"/>\n    <component name=\"é\" source=\"x.wasm\" rate=\"1\"/>\n    <connect from=\"a\" to=\"b\"/>\n  </platform>\n</robot>\n";
        let components = vec![("plan".to_string(), Vec::new())];
        let robot = RobotFile::pointed("f.xml".into(), "f.xml".into(), file.into(), &components, "f.xml").unwrap();
        assert!(robot.text.contains("source=\"plan.wasm\" rate=\"bad\""));
        let sent_column = |line: usize, needle: &str| {
            let l = robot.text.lines().nth(line - 1).unwrap();
            (line as u64, l[..l.find(needle).unwrap()].chars().count() as u64 + 1)
        };
        let file_column = |line: usize, needle: &str| {
            let l = file.lines().nth(line - 1).unwrap();
            (line as u64, l[..l.find(needle).unwrap()].chars().count() as u64 + 1)
        };
        let cases = [
            ("before the edit", sent_column(3, "<component"), file_column(3, "<component")),
            ("after the edit on its line", sent_column(3, "rate="), file_column(3, "rate=")),
            ("inside the new value", sent_column(3, "plan.wasm"), file_column(3, "build/long")),
            ("a later line", sent_column(5, "to="), file_column(5, "to=")),
            ("a line with a wide character", sent_column(4, "rate="), file_column(4, "rate=")),
        ];
        for (case, sent, expected) in cases {
            assert_eq!(robot.position(sent.0, sent.1), expected, "{case}");
        }
    }

    fn tar_of(entries: &[(&str, &[u8])], sums: Option<&str>) -> Vec<u8> {
        let mut builder = tar::Builder::new(Vec::new());
        let mut listed = String::new();
        for (name, bytes) in entries {
            let mut header = tar::Header::new_gnu();
            header.set_size(bytes.len() as u64);
            header.set_mode(0o644);
            header.set_entry_type(tar::EntryType::Regular);
            builder.append_data(&mut header, name, *bytes).unwrap();
            let base = name.split_once('/').map_or(*name, |(_, b)| b);
            listed.push_str(&format!("{}  {base}\n", hex::encode(Sha256::digest(bytes))));
        }
        let sums = sums.map_or(listed, str::to_string);
        let mut header = tar::Header::new_gnu();
        header.set_size(sums.len() as u64);
        header.set_mode(0o644);
        header.set_entry_type(tar::EntryType::Regular);
        builder.append_data(&mut header, "exp-1/SHA256SUMS", sums.as_bytes()).unwrap();
        builder.into_inner().unwrap()
    }

    #[test]
    fn archives_unpack_without_their_folder_and_only_when_every_sum_matches() {
        let dir = tempfile::tempdir().unwrap();
        let good = tar_of(&[("exp-1/run.mcap", b"mcap"), ("exp-1/components/a.wasm", b"wasm")], None);
        let written = unpack(&good[..], dir.path()).unwrap();
        assert_eq!(written.len(), 3);
        assert_eq!(std::fs::read(dir.path().join("components/a.wasm")).unwrap(), b"wasm");
        // (case, archive, the error expected to contain).
        let wrong = format!("{}  run.mcap\n", hex::encode(Sha256::digest(b"other")));
        let cases: Vec<(&str, Vec<u8>, &str)> = vec![
            (
                "a damaged file",
                tar_of(&[("exp-1/run.mcap", b"mcap")], Some(&wrong)),
                "run.mcap does not match its sha256",
            ),
            ("an unlisted file", tar_of(&[("exp-1/run.mcap", b"mcap")], Some("")), "run.mcap is not listed"),
            (
                "a listed file missing",
                tar_of(&[], Some(&wrong)),
                "run.mcap, listed in SHA256SUMS, is not in the archive",
            ),
            ("cut short", good[..good.len() / 2].to_vec(), ""),
            ("two folders", tar_of(&[("other/run.mcap", b"mcap")], None), "outside the archive's folder"),
            ("no folder", tar_of(&[("run.mcap", b"mcap")], None), "not inside the archive's folder"),
        ];
        for (case, archive, expected) in cases {
            let dir = tempfile::tempdir().unwrap();
            let error = unpack(&archive[..], dir.path()).unwrap_err();
            assert!(error.contains(expected), "{case}: {error}");
        }
        // A path that climbs out is refused before anything is written
        // (tar::Builder refuses to write one, so the header is set by hand).
        let mut header = tar::Header::new_gnu();
        header.as_old_mut().name[..16].copy_from_slice(b"exp-1/../../evil");
        header.set_size(1);
        header.set_entry_type(tar::EntryType::Regular);
        header.set_cksum();
        let mut climbing = header.as_bytes().to_vec();
        climbing.extend_from_slice(&[b'x'; 512]);
        climbing.extend_from_slice(&[0; 1024]);
        let dir = tempfile::tempdir().unwrap();
        let error = unpack(&climbing[..], dir.path()).unwrap_err();
        assert!(error.contains("not a plain relative path"), "{error}");
        assert!(!dir.path().parent().unwrap().join("evil").exists());
    }

    /// A portal that nothing listens on.
    fn login() -> Login {
        Login { host: "127.0.0.1:1".into(), user: "u".into(), password: "p".into(), ca: None, allow_plain_http: false }
    }

    #[test]
    fn bad_arguments_are_refused_before_anything_is_sent() {
        let request = |duration_s: f64, label: &str, robot: Option<&str>| SubmitRequest {
            login: login(),
            platform: "control".into(),
            components: vec![],
            robot: robot.map(PathBuf::from),
            duration_s,
            label: label.into(),
            results: None,
            target: Target::Any,
        };
        let mut quiet = |_: &str| {};
        let mut quiet2 = |_: &str| {};
        let mut say = Say { progress: &mut quiet, states: &mut quiet2 };
        let error = |r: SubmitRequest, say: &mut Say<'_>| submit(&r, say).unwrap_err().to_string();
        assert!(error(request(0.5, "", None), &mut say).starts_with("--duration must be from 1"));
        assert!(error(request(f64::NAN, "", None), &mut say).starts_with("--duration"));
        assert!(error(request(10.0, "a\nb", None), &mut say).starts_with("--label"));
        let dir = tempfile::tempdir().unwrap();
        let broken = dir.path().join("broken.xml");
        std::fs::write(&broken, "<robot name=\"r\">\n  <platform name=\"control\">\n</robot>\n").unwrap();
        let text = error(request(10.0, "", Some(broken.to_str().unwrap())), &mut say);
        assert!(text.starts_with(&format!("{}:3:", broken.display())), "{text}");
        assert!(text.ends_with("nothing was sent"), "{text}");
        let full = dir.path().join("full");
        std::fs::create_dir(&full).unwrap();
        std::fs::write(full.join("x"), "").unwrap();
        let text = results(&login(), 1, &full).unwrap_err().to_string();
        assert!(text.ends_with("is not empty; give a new or empty folder"), "{text}");
    }

    #[test]
    fn show_says_the_reset_and_the_score_apart_from_the_state() {
        let mut shown = experiment(&[(ExperimentState::Done, 2000, "its time is up")]);
        shown.record.reset = Some(crate::store::experiments::ResetOutcome {
            at_ms: 1500,
            passed: true,
            took_s: 12.34,
            from: Some(crate::store::experiments::Pose { x: 7.4, y: 1.0, heading: 0.1 }),
            pose: Some(crate::store::experiments::Pose { x: 1.02, y: 0.98, heading: 0.03 }),
            error: None,
        });
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
        shown.record.score = Some(score.clone());
        shown.record.preflight = Some(crate::store::experiments::PreflightResult {
            passed: true,
            reasons: Vec::new(),
            simulated_s: 25.0,
            wall_s: 1.0,
            replay: None,
            score: Some(crate::store::task::Score { value: None, ..score }),
            ended_by: Some(crate::store::task::EpisodeEnd::TimeOut),
        });
        let text = show_text(&shown, 3000);
        assert!(text.contains("  preflight  passed: 25 s simulated in 1.0 s, ended: time-out\n"), "{text}");
        assert!(text.contains("experiment 7: done"), "{text}");
        assert!(
            text.contains("  reset      driven back in 12.3 s from (7.40, 1.00, 0.10 rad) to (1.02, 0.98, 0.03 rad)\n"),
            "{text}"
        );
        assert!(text.contains("  score      task reach-6: time_to_goal_s = 17.25 (the preflight's: none)\n"), "{text}");
        shown.record.reset = shown.record.reset.map(|r| crate::store::experiments::ResetOutcome {
            passed: false,
            error: Some("the emergency stop was engaged (by ana: portal)".into()),
            ..r
        });
        let text = show_text(&shown, 3000);
        assert!(
            text.contains("  reset      failed after 12.3 s: the emergency stop was engaged (by ana: portal)\n"),
            "{text}"
        );
    }
}
