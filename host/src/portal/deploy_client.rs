//! `subsume deploy`: upload components and/or a robot file to a running
//! host's portal, stage and activate them in one step, through the same
//! HTTP API (and so the same checks) as the page: log in, `PUT` each
//! component, `PUT` the robot file (a staged set), `POST` its activation,
//! log out.
//!
//! Uploads belong to their uploader (the portal stores user U's `avoid` as
//! `U/avoid`): a second user's deploy of a name never replaces the first
//! user's stored upload. Without `--robot`, the robot file of the active
//! set is fetched and each deployed component's `source` in it is pointed
//! at the upload by its full name (`USER/NAME.wasm`, so the file says whose
//! code runs, whoever stages it next), so "replace component NAME of the
//! running robot" is one command. Everything local (files, names, the
//! components the robot file must have, that each component file is a
//! WebAssembly component by its preamble) is checked before anything is
//! sent; any refusal after that leaves the running set as it was (a
//! component that was uploaded stays in the store as the user's, as a page
//! upload would).

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use serde_json::{Value, json};
use thiserror::Error;

use super::client::{ClientError, Connection, Login, MAX_ANSWER_BYTES};
use crate::contract::{clip, is_valid_name};
use crate::sandbox::preamble::check_component_preamble;
use crate::store::experiments::Target;

/// Longest wait for one upload or activation: the portal answers an upload
/// only after compiling it (a Python component takes 14-19 s on a loaded
/// 2-core machine), and an activation after instantiating the new set.
pub const DEPLOY_TIMEOUT: Duration = Duration::from_secs(300);
/// Largest local file read for an upload: the portal's own limit
/// (`MAX_UPLOAD_BYTES`), so an oversized file is refused before sending.
pub const MAX_DEPLOY_FILE_BYTES: u64 = 32 << 20;

/// What to deploy, and where.
#[derive(Clone, Debug)]
pub struct DeployRequest {
    /// Who deploys, and where.
    pub login: Login,
    /// The platform the uploads belong to (`control`, `network`).
    pub platform: String,
    /// (component name in the robot file and in the store, .wasm file).
    pub components: Vec<(String, PathBuf)>,
    /// A robot file; none: the active one, with the components replaced.
    pub robot: Option<PathBuf>,
}

/// What a deploy did.
#[derive(Clone, Debug, PartialEq)]
pub struct Deployed {
    /// The set that now runs.
    pub set: u64,
    /// Seconds each component's upload took (sent, compiled, checked).
    pub uploads: Vec<(String, f64)>,
}

/// Why a deploy stopped; nothing that runs was changed.
#[derive(Debug, Error)]
pub enum DeployClientError {
    #[error(transparent)]
    Portal(#[from] ClientError),
    #[error("'{0}' is not NAME=FILE.wasm with NAME [a-z][a-z0-9_-]*")]
    BadComponent(String),
    #[error("nothing to deploy: give --component NAME=FILE.wasm and/or --robot FILE.xml")]
    Nothing,
    #[error("{path}: {why}")]
    File { path: String, why: String },
    #[error("{path} is not a webassembly component: {why}; nothing was uploaded")]
    NotAComponent { path: String, why: String },
    #[error("{user} may not upload to platform {platform} (role {role}; may change: {may}); nothing was uploaded")]
    MayNotChange { user: String, role: String, platform: String, may: String },
    #[error("the running robot file {file} has no component '{name}' (it has: {has})")]
    NoSuchComponent { file: String, name: String, has: String },
    #[error("{0} was refused; nothing was changed:\n{1}")]
    Invalid(String, String),
    #[error("{what}: the portal answered {status}: {message}")]
    Refused { what: String, status: u16, message: String },
    #[error("--target '{0}' is neither robot=NAME nor profile=ID")]
    BadTarget(String),
    #[error("--target {target}: {why}; nothing was sent")]
    NoTarget { target: String, why: String },
}

/// A baseline an experiment builds on.
#[derive(Clone, Debug)]
pub(super) struct Baseline {
    /// Its set's id.
    pub set: u64,
    /// Its robot file's name and text.
    pub name: String,
    pub text: String,
    /// Whose it is, for a person: "the lab's baseline", "robot r2's
    /// baseline".
    pub whose: String,
}

/// `robot=NAME` or `profile=ID`, as the command line and messages say it.
pub fn target_text(target: &Target) -> String {
    match target {
        Target::Any => "any robot".to_string(),
        Target::Robot(name) => format!("robot={name}"),
        Target::Profile(id) => format!("profile={id}"),
    }
}

/// Parses `--target robot=NAME` or `--target profile=ID`.
pub fn target_arg(text: &str) -> Result<Target, DeployClientError> {
    match text.split_once('=') {
        Some(("robot", name)) if !name.is_empty() => Ok(Target::Robot(name.to_string())),
        Some(("profile", id)) if !id.is_empty() => Ok(Target::Profile(id.to_string())),
        _ => Err(DeployClientError::BadTarget(clip(text))),
    }
}

/// The set and owner's words of `target`'s baseline among a lab server's
/// `robots` (`GET /api/v1/robots`): the robot of that name, or the first
/// robot of that profile whose baseline the lab server has stored.
fn target_baseline(target: &Target, robots: &[Value]) -> Result<(u64, String), DeployClientError> {
    let no_target = |why: String| DeployClientError::NoTarget { target: target_text(target), why };
    let names = || {
        let names: Vec<String> = robots
            .iter()
            .map(|r| {
                format!(
                    "{} (profile {})",
                    r["name"].as_str().unwrap_or("?"),
                    r["profile"]["id"].as_str().unwrap_or("?")
                )
            })
            .collect();
        if names.is_empty() { "none has joined".to_string() } else { format!("it has: {}", names.join(", ")) }
    };
    let fits = |robot: &&Value| match target {
        Target::Any => true,
        Target::Robot(name) => robot["name"].as_str() == Some(name),
        Target::Profile(id) => robot["profile"]["id"].as_str() == Some(id),
    };
    let fitting: Vec<&Value> = robots.iter().filter(fits).collect();
    if fitting.is_empty() {
        return Err(no_target(format!("the lab has no such robot: {}", names())));
    }
    let stored = fitting.iter().find_map(|robot| {
        let set = robot["baseline_set"].as_u64()?;
        Some((set, robot["name"].as_str().unwrap_or("?").to_string()))
    });
    match (stored, target) {
        (Some((set, _)), Target::Robot(name)) => Ok((set, format!("robot {name}'s baseline"))),
        (Some((set, robot)), Target::Profile(id)) => Ok((set, format!("the baseline of profile {id} (robot {robot})"))),
        (Some((set, _)), Target::Any) => Ok((set, "the lab's baseline".to_string())),
        (None, _) => {
            let why = fitting.iter().find_map(|r| r["baseline_error"].as_str()).unwrap_or("it is not fetched yet");
            Err(no_target(format!("the lab server has not stored its baseline: {why}")))
        }
    }
}

/// Parses `NAME=FILE` from the command line.
pub fn component_arg(text: &str) -> Result<(String, PathBuf), DeployClientError> {
    match text.split_once('=') {
        Some((name, file)) if is_valid_name(name) && !file.is_empty() => Ok((name.to_string(), PathBuf::from(file))),
        _ => Err(DeployClientError::BadComponent(clip(text))),
    }
}

/// Deploys `request`; `say` gets a line per step (progress for a person).
pub fn deploy(request: &DeployRequest, say: &mut dyn FnMut(&str)) -> Result<Deployed, DeployClientError> {
    if request.components.is_empty() && request.robot.is_none() {
        return Err(DeployClientError::Nothing);
    }
    let connection = Connection::open(&request.login, DEPLOY_TIMEOUT)?;
    // Everything local first: a missing file changes nothing remotely.
    let components = read_components(&request.components)?;
    let robot = match &request.robot {
        Some(path) => Some((path.display().to_string(), file_name(path)?, read(path)?)),
        None => None,
    };
    let portal = Portal::login(connection, &request.login.user, &request.login.password)?;
    let result = portal.deploy(&request.platform, &components, robot, say);
    portal.logout();
    result
}

/// The component files to upload (`deploy`'s and `lab submit`'s), each
/// checked to be a WebAssembly component by its preamble, before anything
/// is sent: a core module, a native artifact or a text file is named here,
/// not found out after the other uploads.
pub(super) fn read_components(components: &[(String, PathBuf)]) -> Result<Vec<(String, Vec<u8>)>, DeployClientError> {
    let mut read_ones = Vec::new();
    for (name, path) in components {
        if !is_valid_name(name) {
            return Err(DeployClientError::BadComponent(clip(name)));
        }
        let bytes = read(path)?;
        check_component_preamble(&bytes).map_err(|why| DeployClientError::NotAComponent {
            path: path.display().to_string(),
            why: why.to_string(),
        })?;
        read_ones.push((name.clone(), bytes));
    }
    Ok(read_ones)
}

/// A local file to upload, bounded by [`MAX_DEPLOY_FILE_BYTES`].
pub(super) fn read(path: &Path) -> Result<Vec<u8>, DeployClientError> {
    let file = |why: String| DeployClientError::File { path: path.display().to_string(), why };
    let size = std::fs::metadata(path).map_err(|e| file(e.to_string()))?.len();
    if size > MAX_DEPLOY_FILE_BYTES {
        return Err(file(format!("{size} bytes; the portal takes at most {MAX_DEPLOY_FILE_BYTES}")));
    }
    std::fs::read(path).map_err(|e| file(e.to_string()))
}

pub(super) fn file_name(path: &Path) -> Result<String, DeployClientError> {
    path.file_name()
        .and_then(|n| n.to_str())
        .map(str::to_string)
        .ok_or_else(|| DeployClientError::File { path: path.display().to_string(), why: "has no file name".into() })
}

/// A logged-in session on one portal (`deploy`'s and `lab`'s).
pub(super) struct Portal {
    pub(super) connection: Connection,
    pub(super) token: String,
    /// Who is logged in (uploads are stored as theirs).
    pub(super) user: String,
    /// Their role and the platforms they may change, as the portal said at
    /// login (`None`: it did not say).
    may_change: Option<(String, Vec<String>)>,
}

impl Portal {
    pub(super) fn login(connection: Connection, user: &str, password: &str) -> Result<Portal, DeployClientError> {
        let answer = log_in(&connection, user, password)?;
        let token = answer["token"].as_str().ok_or_else(|| ClientError::Garbled(connection.address().to_string()))?;
        let role = answer["user"]["role"].as_str().map(str::to_string);
        let platforms = answer["user"]["platforms"]
            .as_array()
            .map(|p| p.iter().filter_map(|p| p.as_str().map(str::to_string)).collect());
        Ok(Portal { token: token.to_string(), connection, user: user.to_string(), may_change: role.zip(platforms) })
    }

    /// Logs in again (the portal forgot the session).
    pub(super) fn log_in_again(&mut self, password: &str) -> Result<(), DeployClientError> {
        let answer = log_in(&self.connection, &self.user, password)?;
        let token = answer["token"].as_str().ok_or_else(|| ClientError::Garbled(self.address().to_string()))?;
        self.token = token.to_string();
        Ok(())
    }

    /// Whether the user may upload to `platform`, as the portal told at
    /// login: checked before anything is uploaded (the portal checks it
    /// again on each upload).
    pub(super) fn check_may_change(&self, platform: &str) -> Result<(), DeployClientError> {
        match &self.may_change {
            Some((role, platforms)) if !platforms.iter().any(|p| p == platform) => {
                Err(DeployClientError::MayNotChange {
                    user: self.user.clone(),
                    role: role.clone(),
                    platform: clip(platform),
                    may: if platforms.is_empty() { "none".into() } else { platforms.join(", ") },
                })
            }
            _ => Ok(()),
        }
    }

    pub(super) fn address(&self) -> &str {
        self.connection.address()
    }

    pub(super) fn logout(&self) {
        let logout = self.connection.send("POST", "/api/v1/logout", Some(&self.token), "application/json", b"");
        let _ = logout.and_then(|answer| answer.read(MAX_ANSWER_BYTES));
    }

    pub(super) fn call(
        &self,
        method: &str,
        path: &str,
        content_type: &str,
        body: &[u8],
        what: &str,
    ) -> Result<Value, DeployClientError> {
        call(&self.connection, Some(&self.token), method, path, content_type, body, what)
    }

    fn deploy(
        &self,
        platform: &str,
        components: &[(String, Vec<u8>)],
        robot: Option<(String, String, Vec<u8>)>,
        say: &mut dyn FnMut(&str),
    ) -> Result<Deployed, DeployClientError> {
        if !components.is_empty() {
            self.check_may_change(platform)?;
        }
        // The robot file: the given one, or the active one pointed at the
        // uploads (checked before anything is uploaded).
        let (shown, name, text) = match robot {
            Some(robot) => robot,
            None => {
                let (set, name, mut text) = self.active_robot()?;
                for (component, _) in components {
                    text = point_source_at(&text, component, &self.source(component))
                        .map_err(|has| DeployClientError::NoSuchComponent {
                            file: name.clone(),
                            name: component.clone(),
                            has,
                        })?
                        .0;
                }
                say(&format!("using the active robot file {name} (set {set}) with {}", self.list(components)));
                (format!("{name} (the active robot file)"), name, text.into_bytes())
            }
        };
        let mut uploads = Vec::new();
        for (component, bytes) in components {
            uploads.push((component.clone(), self.upload(platform, component, bytes, say)?));
        }
        let set = self.stage(platform, &name, &text, &shown, &|line, column| (line, column))?;
        say(&format!("staged {shown} as set {set}; activating..."));
        let activated = self.call(
            "POST",
            &format!("/api/v1/sets/{set}/activate"),
            "application/json",
            b"",
            &format!("activating set {set}"),
        );
        if let Err(e) = activated {
            // A refused activation leaves nothing staged behind.
            match self.call(
                "DELETE",
                &format!("/api/v1/sets/{set}"),
                "application/json",
                b"",
                &format!("forgetting set {set}"),
            ) {
                Ok(_) => say(&format!("the activation was refused: set {set} is forgotten")),
                Err(why) => say(&format!("the activation was refused; set {set} stays: {why}")),
            }
            return Err(locate(e, &format!("activating set {set}"), &|line, column| (line, column)));
        }
        say(&format!("set {set} is running"));
        Ok(Deployed { set, uploads })
    }

    /// The active set's id, its robot file's name and its text.
    pub(super) fn active_robot(&self) -> Result<(u64, String, String), DeployClientError> {
        let status = self.call("GET", "/api/v1/status", "application/json", b"", "reading the status")?;
        let set = status["set"].as_u64().ok_or_else(|| ClientError::Garbled(self.address().to_string()))?;
        self.robot_of(set, "the active set")
    }

    /// The baseline an experiment for `target` builds on, whatever runs
    /// now: the lab's (`Target::Any`), or on a lab server the baseline of
    /// the robot named, or of the first robot of the profile named, as the
    /// lab server stored it (`GET /api/v1/robots`'s `baseline_set`).
    pub(super) fn baseline_robot(&self, target: &Target) -> Result<Baseline, DeployClientError> {
        let (set, whose) = match target {
            Target::Any => {
                let lab = self.call("GET", "/api/v1/lab", "application/json", b"", "reading the lab")?;
                let set =
                    lab["lab"]["baseline"].as_u64().ok_or_else(|| ClientError::Garbled(self.address().to_string()))?;
                (set, "the lab's baseline".to_string())
            }
            Target::Robot(_) | Target::Profile(_) => {
                let what = "reading the lab's robots";
                let robots = match self.call("GET", "/api/v1/robots", "application/json", b"", what) {
                    Err(DeployClientError::Refused { status: 404, .. }) => {
                        return Err(DeployClientError::NoTarget {
                            target: target_text(target),
                            why: format!("{} is one robot's portal, not a lab server's", self.address()),
                        });
                    }
                    answer => answer?,
                };
                let robots = robots["robots"].as_array().cloned().unwrap_or_default();
                target_baseline(target, &robots)?
            }
        };
        let (set, name, text) = self.robot_of(set, &whose)?;
        Ok(Baseline { set, name, text, whose })
    }

    /// Set `set`'s robot file's name and text (`what` names it).
    fn robot_of(&self, set: u64, what: &str) -> Result<(u64, String, String), DeployClientError> {
        let answer =
            self.call("GET", &format!("/api/v1/sets/{set}"), "application/json", b"", &format!("reading {what}"))?;
        let name = answer["set"]["config_name"].as_str().unwrap_or("robot.xml").to_string();
        let Some(text) = answer["config"].as_str() else {
            return Err(DeployClientError::Portal(ClientError::Refused {
                address: self.address().to_string(),
                status: 403,
                message: format!(
                    "{what} (set {set}) keeps its robot file on the robot (the owner's lab kit is off): give a robot file of your own with --robot"
                ),
            }));
        };
        Ok((set, name, text.to_string()))
    }

    /// Uploads component `component` of `platform`; the seconds it took
    /// (sent, compiled, checked).
    pub(super) fn upload(
        &self,
        platform: &str,
        component: &str,
        bytes: &[u8],
        say: &mut dyn FnMut(&str),
    ) -> Result<f64, DeployClientError> {
        say(&format!(
            "uploading {component} ({} KiB): the portal compiles and checks it...",
            bytes.len().div_ceil(1024)
        ));
        let started = Instant::now();
        let path = format!("/api/v1/platforms/{platform}/components/{component}");
        self.call("PUT", &path, "application/wasm", bytes, &format!("component {component}"))?;
        let took = started.elapsed().as_secs_f64();
        say(&format!("uploaded {component} in {took:.1} s"));
        Ok(took)
    }

    /// Stages robot file `text` as `name` of `platform`; the staged set's
    /// id. A refusal's diagnostics name `shown`, at the positions
    /// `position` gives for each line and column of `text`.
    pub(super) fn stage(
        &self,
        platform: &str,
        name: &str,
        text: &[u8],
        shown: &str,
        position: &dyn Fn(u64, u64) -> (u64, u64),
    ) -> Result<u64, DeployClientError> {
        let path = format!("/api/v1/platforms/{platform}/configs/{name}");
        let staged = self.call("PUT", &path, "application/xml", text, shown).map_err(|e| locate(e, shown, position))?;
        staged["set"]["id"].as_u64().ok_or_else(|| ClientError::Garbled(self.address().to_string()).into())
    }
}

/// How a robot file the logged-in user stages names their own upload
/// `component` (staging resolves `NAME.wasm` to the stager's upload).
pub(super) fn upload_source(component: &str) -> String {
    format!("{component}.wasm")
}

impl Portal {
    /// How a robot file names this user's upload `component` from anyone's
    /// file.
    fn source(&self, component: &str) -> String {
        format!("{}/{component}.wasm", self.user)
    }

    fn list(&self, components: &[(String, Vec<u8>)]) -> String {
        components.iter().map(|(name, _)| format!("{name} -> {}", self.source(name))).collect::<Vec<_>>().join(", ")
    }
}

/// Logs in as `user`; the portal's answer (the token, the user).
fn log_in(connection: &Connection, user: &str, password: &str) -> Result<Value, DeployClientError> {
    let body = json!({ "name": user, "password": password }).to_string();
    call(connection, None, "POST", "/api/v1/login", "application/json", body.as_bytes(), "login")
}

/// One request whose non-2xx answer becomes `Refused` (diagnostics kept in
/// the message, one per line, for [`locate`]).
fn call(
    connection: &Connection,
    token: Option<&str>,
    method: &str,
    path: &str,
    content_type: &str,
    body: &[u8],
    what: &str,
) -> Result<Value, DeployClientError> {
    let (status, answer, text) = connection.send(method, path, token, content_type, body)?.read(MAX_ANSWER_BYTES)?;
    if (200..300).contains(&status) {
        return Ok(answer);
    }
    Err(refused(status, &answer, &text, what))
}

/// A non-2xx answer as `Refused`: the portal's own answer (bounded by
/// `MAX_ANSWER_BYTES`), whole, its diagnostics one per line (for
/// [`locate`]): they are what the person needs to see.
pub(super) fn refused(status: u16, answer: &Value, text: &str, what: &str) -> DeployClientError {
    let mut message = answer["error"].as_str().map_or_else(|| text.trim().to_string(), str::to_string);
    for d in answer["diagnostics"].as_array().into_iter().flatten() {
        let line = format!(
            "{}:{}:{}: {}",
            d["file"].as_str().unwrap_or("?"),
            d["line"].as_u64().unwrap_or(0),
            d["column"].as_u64().unwrap_or(0),
            d["message"].as_str().unwrap_or("?")
        );
        message.push('\n');
        message.push_str(&line);
    }
    DeployClientError::Refused { what: what.to_string(), status, message }
}

/// A robot file's refusal with its diagnostics as `FILE:line:column:
/// message` lines, `FILE` the local path (the portal names the upload),
/// at the line and column `position` gives for the portal's.
pub(super) fn locate(
    error: DeployClientError,
    shown: &str,
    position: &dyn Fn(u64, u64) -> (u64, u64),
) -> DeployClientError {
    match error {
        DeployClientError::Refused { status: 422, message, .. } if message.contains('\n') => {
            let mut lines = message.lines();
            let head = lines.next().unwrap_or_default();
            let located: Vec<String> = lines
                .map(|l| {
                    let mut parts = l.splitn(4, ':');
                    let (_, line, column, rest) = (parts.next(), parts.next(), parts.next(), parts.next());
                    match (line.and_then(|n| n.parse().ok()), column.and_then(|n| n.parse().ok()), rest) {
                        (Some(line), Some(column), Some(rest)) => {
                            let (line, column) = position(line, column);
                            format!("{shown}:{line}:{column}:{rest}")
                        }
                        _ => l.to_string(),
                    }
                })
                .collect();
            DeployClientError::Invalid(shown.to_string(), format!("{head}\n{}", located.join("\n")))
        }
        other => other,
    }
}

/// One replacement in a text: at byte `at`, `removed` bytes were replaced
/// by `inserted` bytes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) struct Edit {
    pub at: usize,
    pub removed: usize,
    pub inserted: usize,
}

/// `xml` with the `source` attribute of `<component name="NAME" ...>` set
/// to `source`, the rest byte for byte, and where it changed. Err: the
/// names of the components it has.
pub(super) fn point_source_at(xml: &str, name: &str, source: &str) -> Result<(String, Edit), String> {
    use quick_xml::events::Event;
    let mut reader = quick_xml::Reader::from_str(xml);
    let mut names = Vec::new();
    loop {
        let before = reader.buffer_position() as usize;
        let event = match reader.read_event() {
            Ok(Event::Eof) | Err(_) => break,
            Ok(event) => event,
        };
        let (Event::Start(e) | Event::Empty(e)) = event else { continue };
        if e.name().as_ref() != "component" {
            continue;
        }
        let this = e
            .attributes()
            .flatten()
            .find(|a| a.key.as_ref() == "name")
            .map(|a| a.value.clone().into_owned())
            .unwrap_or_default();
        if this != name {
            names.push(this);
            continue;
        }
        let after = reader.buffer_position() as usize;
        let element = xml.get(before..after).unwrap_or_default();
        if let Some((from, to)) = attribute_value(element, "source") {
            let edit = Edit { at: before + from, removed: to - from, inserted: source.len() };
            return Ok((format!("{}{source}{}", &xml[..before + from], &xml[before + to..]), edit));
        }
        names.push(this);
    }
    Err(if names.is_empty() { "no components".into() } else { names.join(", ") })
}

/// The byte range of attribute `key`'s value inside one start tag.
fn attribute_value(tag: &str, key: &str) -> Option<(usize, usize)> {
    let bytes = tag.as_bytes();
    let mut at = 0;
    while let Some(found) = tag[at..].find(key) {
        let start = at + found;
        at = start + key.len();
        if start == 0 || !bytes[start - 1].is_ascii_whitespace() {
            continue;
        }
        let rest = tag[at..].trim_start();
        let Some(rest) = rest.strip_prefix('=') else { continue };
        let rest = rest.trim_start();
        let quote = rest.chars().next()?;
        if quote != '"' && quote != '\'' {
            continue;
        }
        let value_start = tag.len() - rest.len() + 1;
        let value_end = value_start + tag[value_start..].find(quote)?;
        return Some((value_start, value_end));
    }
    None
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_target_is_parsed_from_robot_or_profile_and_nothing_else() {
        let cases: [(&str, Option<Target>); 6] = [
            ("robot=r1", Some(Target::Robot("r1".into()))),
            ("profile=0a1b2c3d4e5f", Some(Target::Profile("0a1b2c3d4e5f".into()))),
            ("robot=", None),
            ("r1", None),
            ("any=r1", None),
            ("profile", None),
        ];
        for (text, expected) in cases {
            match (target_arg(text), expected) {
                (Ok(target), Some(expected)) => assert_eq!(target, expected, "{text}"),
                (Err(e), None) => assert!(e.to_string().contains("neither robot=NAME nor profile=ID"), "{text}: {e}"),
                (got, expected) => panic!("{text}: {got:?}, expected {expected:?}"),
            }
        }
    }

    /// A target's baseline among a lab server's robots: the named robot's,
    /// or the first of the profile whose baseline is stored; else why not.
    #[test]
    fn a_targets_baseline_is_its_robots_as_the_lab_server_stored_it() {
        let robots = vec![
            json!({ "name": "r1", "profile": { "id": "aaa" }, "baseline_set": 4 }),
            json!({ "name": "r2", "profile": { "id": "bbb" }, "baseline_set": null, "baseline_error": "r2 did not answer" }),
            json!({ "name": "r3", "profile": { "id": "bbb" }, "baseline_set": 9 }),
            json!({ "name": "r4", "profile": { "id": "ccc" }, "baseline_set": null }),
        ];
        let robot = |n: &str| Target::Robot(n.into());
        let profile = |p: &str| Target::Profile(p.into());
        /// The set and whose words expected, or the error's first words.
        type Expected = Result<(u64, &'static str), &'static str>;
        let cases: [(Target, Expected); 6] = [
            (robot("r1"), Ok((4, "robot r1's baseline"))),
            (robot("r3"), Ok((9, "robot r3's baseline"))),
            (profile("bbb"), Ok((9, "the baseline of profile bbb (robot r3)"))),
            (robot("r2"), Err("--target robot=r2: the lab server has not stored its baseline: r2 did not answer")),
            (
                profile("ccc"),
                Err("--target profile=ccc: the lab server has not stored its baseline: it is not fetched yet"),
            ),
            (
                robot("r9"),
                Err(
                    "--target robot=r9: the lab has no such robot: it has: r1 (profile aaa), r2 (profile bbb), r3 (profile bbb), r4 (profile ccc); nothing was sent",
                ),
            ),
        ];
        for (target, expected) in cases {
            match (target_baseline(&target, &robots), expected) {
                (Ok((set, whose)), Ok((expected_set, expected_whose))) => {
                    assert_eq!((set, whose.as_str()), (expected_set, expected_whose), "{target:?}")
                }
                (Err(e), Err(expected)) => assert!(e.to_string().starts_with(expected), "{target:?}: {e}"),
                (got, expected) => panic!("{target:?}: {got:?}, expected {expected:?}"),
            }
        }
        assert_eq!(
            target_baseline(&robot("r1"), &[]).unwrap_err().to_string(),
            "--target robot=r1: the lab has no such robot: none has joined; nothing was sent"
        );
    }

    #[test]
    fn a_component_source_is_repointed_and_nothing_else_changes() {
        let xml = "<robot name=\"r\">\n  <platform name=\"control\">\n    <component name=\"filter\" source=\"a/filter.wasm\"/>\n    <component rate=\"20\" name=\"avoid\"\n      source = 'x/avoider.wasm' budget=\"5ms\">\n      <param name=\"source\" value=\"1\"/>\n    </component>\n  </platform>\n</robot>\n";
        let (out, edit) = point_source_at(xml, "avoid", "avoid.wasm").unwrap();
        assert_eq!(out, xml.replace("x/avoider.wasm", "avoid.wasm"));
        let at = xml.find("x/avoider.wasm").unwrap();
        assert_eq!(edit, Edit { at, removed: "x/avoider.wasm".len(), inserted: "avoid.wasm".len() });
        assert_eq!(point_source_at(xml, "ghost", "g.wasm").unwrap_err(), "filter, avoid");
    }

    #[test]
    fn component_arguments_and_hosts_are_checked_before_anything_is_sent() {
        assert_eq!(component_arg("avoid=build/a.wasm").unwrap(), ("avoid".into(), PathBuf::from("build/a.wasm")));
        for bad in ["avoid", "=a.wasm", "Avoid=a.wasm", "avoid="] {
            assert!(matches!(component_arg(bad), Err(DeployClientError::BadComponent(_))), "{bad}");
        }
        let request = |host: &str, components: Vec<(String, PathBuf)>| DeployRequest {
            login: Login {
                host: host.into(),
                user: "u".into(),
                password: "p".into(),
                ca: None,
                allow_plain_http: false,
            },
            platform: "control".into(),
            components,
            robot: None,
        };
        assert!(matches!(deploy(&request("x:1", vec![]), &mut |_| {}), Err(DeployClientError::Nothing)));
        let missing = vec![("avoid".to_string(), PathBuf::from("/nonexistent/a.wasm"))];
        // A missing file is reported before the (unreachable) host is tried.
        let error = deploy(&request("127.0.0.1:1", missing.clone()), &mut |_| {}).unwrap_err().to_string();
        assert!(error.starts_with("/nonexistent/a.wasm: "), "{error}");
        assert!(matches!(deploy(&request("ftp://x:1", missing), &mut |_| {}), Err(DeployClientError::Portal(_))));
        // A file that is not a component is named before anything is sent
        // (the host is unreachable).
        let dir = tempfile::tempdir().unwrap();
        let cases: [(&str, &[u8], &str); 4] = [
            ("core.wasm", b"\0asm\x01\0\0\0", "this is a core webassembly module, not a component"),
            ("native.cwasm", b"\x7fELF\x02\x01", "precompiled native artifact"),
            ("text.wasm", b"<robot/>", "does not start with the webassembly magic bytes"),
            ("short.wasm", b"\0asm", "too short"),
        ];
        for (file, bytes, why) in cases {
            let path = dir.path().join(file);
            std::fs::write(&path, bytes).unwrap();
            let good = support_component(dir.path());
            let components = vec![("good".to_string(), good), ("bad".to_string(), path.clone())];
            let error = deploy(&request("127.0.0.1:1", components), &mut |_| {}).unwrap_err().to_string();
            assert!(error.starts_with(&format!("{} is not a webassembly component: ", path.display())), "{error}");
            assert!(error.contains(why) && error.ends_with("nothing was uploaded"), "{file}: {error}");
        }
    }

    /// A file whose preamble is a component's (the compiler would check
    /// the rest; the client only reads the preamble).
    fn support_component(dir: &Path) -> PathBuf {
        let path = dir.join("good.wasm");
        std::fs::write(&path, b"\0asm\x0d\0\x01\0").unwrap();
        path
    }
}
