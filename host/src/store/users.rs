//! Portal users: the users file (`users.json` in the store), their roles and
//! per-platform permissions, and argon2id password hashes.
//!
//! Roles, as the paper's per-platform logins:
//! - `viewer`: may watch the robot;
//! - `operator`: may also drive it (portal pad, teleoperation);
//! - `researcher`: may upload components and stage robot files for the
//!   platforms it lists (which changes nothing that runs), submit
//!   experiments, watch, and see, download and cancel its own experiments;
//!   it drives only inside its own reservation (docs/lab.md);
//! - `developer`: may upload and activate components and robot files for the
//!   platforms it lists (`network` and/or `control`);
//! - `admin`: everything, on every platform.
//!
//! Invariants: only argon2id hashes are stored, never a password; the file
//! is replaced atomically; a user removed from the file can no longer log in
//! or use a token issued before (the portal re-checks the file).

use std::path::{Path, PathBuf};
use std::time::SystemTime;

use argon2::password_hash::{PasswordHash, PasswordHasher, PasswordVerifier, SaltString};
use argon2::{Algorithm, Argon2, Params, Version};
use serde::{Deserialize, Serialize};
use thiserror::Error;

use crate::config::Platform;
use crate::contract::is_valid_name;
use crate::fsutil::write_atomically;

/// Shortest password accepted: short passwords are guessed.
pub const MIN_PASSWORD_LEN: usize = 10;
/// Longest password accepted: hashing cost grows with length.
pub const MAX_PASSWORD_LEN: usize = 1024;
/// Most users in the users file: bounds the file a login reads.
pub const MAX_USERS: usize = 1000;
/// Largest users file read.
pub const MAX_USERS_FILE_BYTES: u64 = 4 << 20;
/// Argon2id cost (OWASP's minimum: 19 MiB, 2 passes): makes offline
/// guessing of a stolen users file expensive.
pub const ARGON2_MEMORY_KIB: u32 = 19 * 1024;
pub const ARGON2_PASSES: u32 = 2;
/// Length of generated passwords (alphanumeric): ~119 bits.
pub const GENERATED_PASSWORD_LEN: usize = 20;

#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(rename_all = "lowercase")]
pub enum Role {
    Viewer,
    Operator,
    Researcher,
    Developer,
    Admin,
}

impl Role {
    pub fn name(self) -> &'static str {
        match self {
            Role::Viewer => "viewer",
            Role::Operator => "operator",
            Role::Researcher => "researcher",
            Role::Developer => "developer",
            Role::Admin => "admin",
        }
    }
}

/// A role's name that is none of the five.
#[derive(Clone, Debug, PartialEq, Eq, Error)]
#[error("unknown role '{0}' (expected viewer, operator, researcher, developer or admin)")]
pub struct UnknownRole(pub String);

impl std::str::FromStr for Role {
    type Err = UnknownRole;
    fn from_str(text: &str) -> Result<Role, UnknownRole> {
        match text {
            "viewer" => Ok(Role::Viewer),
            "operator" => Ok(Role::Operator),
            "researcher" => Ok(Role::Researcher),
            "developer" => Ok(Role::Developer),
            "admin" => Ok(Role::Admin),
            other => Err(UnknownRole(other.to_string())),
        }
    }
}

/// Who asks for a use case: a name, a role and the platforms it may
/// change, and never a password hash. A stored [`User`] is one (its
/// `Deref`); so are the host's own jobs ([`Principal::host`]) and a lab's
/// experiment on a robot, whose submitter the lab vouched for.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Principal {
    pub name: String,
    pub role: Role,
    /// Platforms a developer may change (ignored for other roles).
    #[serde(default)]
    pub platforms: Vec<String>,
}

impl Principal {
    /// The host acting on its own (`boot`, `lab`, `dev`): an admin of no
    /// platform in particular (an admin may change every one).
    pub fn host(name: &str) -> Principal {
        Principal { name: name.to_string(), role: Role::Admin, platforms: Vec::new() }
    }

    /// Whether this principal may drive the robot.
    pub fn may_drive(&self) -> bool {
        matches!(self.role, Role::Operator | Role::Admin)
    }

    /// Whether this principal may upload to and activate `platform`.
    pub fn may_change(&self, platform: Platform) -> bool {
        match self.role {
            Role::Admin => true,
            Role::Developer | Role::Researcher => self.platforms.iter().any(|p| p == platform.name()),
            _ => false,
        }
    }

    /// Whether this principal may activate sets, record and read the audit
    /// log: a developer of some platform, or an admin (a researcher's
    /// changes reach the robot only as experiments).
    pub fn is_developer(&self) -> bool {
        self.role != Role::Researcher && (self.may_change(Platform::Control) || self.may_change(Platform::Network))
    }

    /// Whether this principal may submit experiments (docs/lab.md).
    pub fn may_submit(&self) -> bool {
        matches!(self.role, Role::Researcher | Role::Developer | Role::Admin)
    }
}

/// One user as the users file keeps it: a principal and its password's
/// hash.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct User {
    #[serde(flatten)]
    pub principal: Principal,
    /// PHC string of an argon2id hash.
    pub hash: String,
}

impl std::ops::Deref for User {
    type Target = Principal;
    fn deref(&self) -> &Principal {
        &self.principal
    }
}

impl User {
    /// Whether `password` is this user's (constant time in the hash).
    pub fn check_password(&self, password: &str) -> bool {
        if password.len() > MAX_PASSWORD_LEN {
            return false;
        }
        let Ok(hash) = PasswordHash::new(&self.hash) else { return false };
        hasher().verify_password(password.as_bytes(), &hash).is_ok()
    }
}

#[derive(Debug, Error)]
pub enum UsersError {
    #[error("cannot read users file {path}: {reason}")]
    Read { path: PathBuf, reason: String },
    #[error("users file {path}: {reason}")]
    Invalid { path: PathBuf, reason: String },
    #[error("cannot write users file {path}: {reason}")]
    Write { path: PathBuf, reason: String },
    #[error("{0}")]
    Refused(String),
}

#[derive(Debug, Default, Serialize, Deserialize)]
struct UsersFile {
    users: Vec<User>,
}

/// The users file at a path; reads are re-done when the file changes, so
/// `subsume user ...` takes effect in a running portal.
#[derive(Debug)]
pub struct Users {
    path: PathBuf,
    cached: std::sync::Mutex<Option<(Option<SystemTime>, Vec<User>)>>,
}

impl Users {
    pub fn new(path: PathBuf) -> Users {
        Users { path, cached: std::sync::Mutex::new(None) }
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Every user (none when the file does not exist yet).
    pub fn all(&self) -> Result<Vec<User>, UsersError> {
        let modified = std::fs::metadata(&self.path).and_then(|m| m.modified()).ok();
        if let Ok(cached) = self.cached.lock()
            && let Some((when, users)) = &*cached
            && *when == modified
            && modified.is_some()
        {
            return Ok(users.clone());
        }
        let users = read_users(&self.path)?;
        if let Ok(mut cached) = self.cached.lock() {
            *cached = Some((modified, users.clone()));
        }
        Ok(users)
    }

    /// The user called `name`, if any.
    pub fn get(&self, name: &str) -> Option<User> {
        self.all().ok()?.into_iter().find(|u| u.name == name)
    }

    /// The user called `name` if `password` is theirs. Takes as long for an
    /// unknown name as for a wrong password.
    pub fn authenticate(&self, name: &str, password: &str) -> Option<User> {
        match self.get(name) {
            Some(user) if user.check_password(password) => Some(user),
            Some(_) => None,
            None => {
                let _ = hash_password("a password to spend the same time on");
                None
            }
        }
    }

    fn write(&self, users: Vec<User>) -> Result<(), UsersError> {
        let file = UsersFile { users };
        let text = serde_json::to_vec_pretty(&file)
            .map_err(|e| UsersError::Write { path: self.path.clone(), reason: e.to_string() })?;
        if let Some(parent) = self.path.parent() {
            std::fs::create_dir_all(parent)
                .map_err(|e| UsersError::Write { path: self.path.clone(), reason: e.to_string() })?;
        }
        write_atomically(&self.path, &text)
            .map_err(|e| UsersError::Write { path: self.path.clone(), reason: e.to_string() })?;
        if let Ok(mut cached) = self.cached.lock() {
            *cached = None;
        }
        Ok(())
    }
}

/// The users, open for changes: only a store writer makes one, so every
/// change is serialised with the rest of the store's.
#[derive(Debug)]
pub struct UsersWriter<'a> {
    users: &'a Users,
}

impl<'a> UsersWriter<'a> {
    pub(super) fn new(users: &'a Users) -> UsersWriter<'a> {
        UsersWriter { users }
    }

    /// Adds a user, or replaces one with `replace`.
    pub fn add(
        &self,
        name: &str,
        role: Role,
        platforms: &[Platform],
        password: &str,
        replace: bool,
    ) -> Result<(), UsersError> {
        if !is_valid_name(name) {
            return Err(UsersError::Refused(format!("user name '{name}' is not [a-z][a-z0-9_-]* (at most 64)")));
        }
        check_password_strength(password)?;
        if matches!(role, Role::Developer | Role::Researcher) && platforms.is_empty() {
            return Err(UsersError::Refused(format!(
                "{} '{name}' needs at least one --platform (network or control)",
                role.name()
            )));
        }
        let mut users = read_users(&self.users.path)?;
        let exists = users.iter().any(|u| u.name == name);
        if exists && !replace {
            return Err(UsersError::Refused(format!("user '{name}' exists already")));
        }
        if !exists && users.len() >= MAX_USERS {
            return Err(UsersError::Refused(format!("at most {MAX_USERS} users are allowed")));
        }
        let mut platforms: Vec<String> = platforms.iter().map(|p| p.name().to_string()).collect();
        platforms.sort();
        platforms.dedup();
        let user = User { principal: Principal { name: name.into(), role, platforms }, hash: hash_password(password)? };
        users.retain(|u| u.name != name);
        users.push(user);
        users.sort_by(|a, b| a.name.cmp(&b.name));
        self.users.write(users)
    }

    /// Sets a new password for an existing user.
    pub fn set_password(&self, name: &str, password: &str) -> Result<(), UsersError> {
        check_password_strength(password)?;
        let mut users = read_users(&self.users.path)?;
        let user = users
            .iter_mut()
            .find(|u| u.name == name)
            .ok_or_else(|| UsersError::Refused(format!("no user '{name}'")))?;
        user.hash = hash_password(password)?;
        self.users.write(users)
    }

    pub fn remove(&self, name: &str) -> Result<(), UsersError> {
        let mut users = read_users(&self.users.path)?;
        let before = users.len();
        users.retain(|u| u.name != name);
        if users.len() == before {
            return Err(UsersError::Refused(format!("no user '{name}'")));
        }
        self.users.write(users)
    }
}

fn read_users(path: &Path) -> Result<Vec<User>, UsersError> {
    let read_error = |reason: String| UsersError::Read { path: path.to_path_buf(), reason };
    let size = match std::fs::metadata(path) {
        Ok(meta) => meta.len(),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Vec::new()),
        Err(e) => return Err(read_error(e.to_string())),
    };
    if size > MAX_USERS_FILE_BYTES {
        return Err(read_error(format!("{size} bytes; at most {MAX_USERS_FILE_BYTES} are allowed")));
    }
    let text = std::fs::read(path).map_err(|e| read_error(e.to_string()))?;
    let invalid = |reason: String| UsersError::Invalid { path: path.to_path_buf(), reason };
    let file: UsersFile = serde_json::from_slice(&text).map_err(|e| invalid(e.to_string()))?;
    for (i, user) in file.users.iter().enumerate() {
        if !is_valid_name(&user.name) {
            return Err(invalid(format!("user {}: name '{}' is not [a-z][a-z0-9_-]*", i + 1, user.name)));
        }
        if let Some(bad) = user.platforms.iter().find(|p| Platform::parse(p).is_err()) {
            return Err(invalid(format!("user '{}': unknown platform '{bad}'", user.name)));
        }
        if file.users[..i].iter().any(|u| u.name == user.name) {
            return Err(invalid(format!("user '{}' is listed twice", user.name)));
        }
    }
    if file.users.len() > MAX_USERS {
        return Err(invalid(format!("more than {MAX_USERS} users")));
    }
    Ok(file.users)
}

fn check_password_strength(password: &str) -> Result<(), UsersError> {
    let length = password.chars().count();
    if length < MIN_PASSWORD_LEN {
        return Err(UsersError::Refused(format!("passwords need at least {MIN_PASSWORD_LEN} characters")));
    }
    if password.len() > MAX_PASSWORD_LEN {
        return Err(UsersError::Refused(format!("passwords may have at most {MAX_PASSWORD_LEN} bytes")));
    }
    Ok(())
}

fn hasher() -> Argon2<'static> {
    let params = Params::new(ARGON2_MEMORY_KIB, ARGON2_PASSES, 1, None).unwrap_or_default();
    Argon2::new(Algorithm::Argon2id, Version::V0x13, params)
}

/// The argon2id PHC string of `password` with a fresh random salt.
pub fn hash_password(password: &str) -> Result<String, UsersError> {
    let mut salt = [0u8; 16];
    getrandom::fill(&mut salt).map_err(|e| UsersError::Refused(format!("no randomness for a salt: {e}")))?;
    let salt = SaltString::encode_b64(&salt).map_err(|e| UsersError::Refused(e.to_string()))?;
    hasher()
        .hash_password(password.as_bytes(), &salt)
        .map(|h| h.to_string())
        .map_err(|e| UsersError::Refused(format!("cannot hash the password: {e}")))
}

/// `bytes` random bytes as lowercase hex (tokens, tickets).
pub fn random_hex(bytes: usize) -> Result<String, NoRandomness> {
    let mut buffer = vec![0u8; bytes];
    getrandom::fill(&mut buffer).map_err(|e| NoRandomness(e.to_string()))?;
    Ok(hex::encode(buffer))
}

/// A new random alphanumeric password.
pub fn generate_password() -> Result<String, NoRandomness> {
    const ALPHABET: &[u8] = b"abcdefghijkmnpqrstuvwxyzABCDEFGHJKLMNPQRSTUVWXYZ23456789";
    let mut password = String::with_capacity(GENERATED_PASSWORD_LEN);
    while password.len() < GENERATED_PASSWORD_LEN {
        let mut byte = [0u8; 1];
        getrandom::fill(&mut byte).map_err(|e| NoRandomness(e.to_string()))?;
        // Rejection sampling keeps every character equally likely.
        let limit = 256 - 256 % ALPHABET.len();
        if (byte[0] as usize) < limit {
            password.push(ALPHABET[byte[0] as usize % ALPHABET.len()] as char);
        }
    }
    Ok(password)
}

/// The system's random source failed.
#[derive(Clone, Debug, PartialEq, Eq, Error)]
#[error("no randomness: {0}")]
pub struct NoRandomness(pub String);

/// Why no ticket was issued.
#[derive(Clone, Debug, PartialEq, Eq, Error)]
pub enum TicketError {
    #[error(transparent)]
    NoRandomness(#[from] NoRandomness),
    #[error("more than {MAX_TICKETS} tickets are waiting; try again in a minute")]
    TooMany,
    #[error("the ticket table is unusable")]
    Unusable,
}

/// How long a pad ticket stays valid: the browser redeems it at once.
pub const TICKET_TTL: std::time::Duration = std::time::Duration::from_secs(60);
/// Most unredeemed tickets kept: a client asking for tickets in a loop
/// cannot grow memory.
pub const MAX_TICKETS: usize = 1000;

/// One-time teleoperation tickets: the portal issues one to a logged-in user
/// who may drive, and the browser's pad presents it as its `AUTH` token on
/// the teleoperation WebSocket, so the session cookie never reaches script.
#[derive(Debug, Default)]
pub struct Tickets {
    issued: std::sync::Mutex<std::collections::HashMap<String, (String, std::time::Instant)>>,
}

impl Tickets {
    /// A new ticket for `user`.
    pub fn issue(&self, user: &str) -> Result<String, TicketError> {
        let ticket = random_hex(24)?;
        let mut issued = self.issued.lock().map_err(|_| TicketError::Unusable)?;
        let now = std::time::Instant::now();
        issued.retain(|_, (_, expires)| *expires > now);
        if issued.len() >= MAX_TICKETS {
            return Err(TicketError::TooMany);
        }
        issued.insert(ticket.clone(), (user.to_string(), now + TICKET_TTL));
        Ok(ticket)
    }

    /// Whether `ticket` was issued to `user` and is still valid; it is used
    /// up either way.
    pub fn redeem(&self, user: &str, ticket: &str) -> bool {
        let Ok(mut issued) = self.issued.lock() else { return false };
        match issued.remove(ticket) {
            Some((owner, expires)) => owner == user && expires > std::time::Instant::now(),
            None => false,
        }
    }
}

/// The users file and the tickets, as the network platform checks them.
#[derive(Debug)]
pub struct Directory {
    pub users: std::sync::Arc<Users>,
    pub tickets: Tickets,
    /// Who may drive beyond their role now (a researcher in their
    /// reservation).
    pub grants: DriveGrants,
}

impl Directory {
    pub fn new(users: std::sync::Arc<Users>) -> Directory {
        Directory { users, tickets: Tickets::default(), grants: DriveGrants::default() }
    }

    /// Whether `user` may drive now: by role, or by a grant.
    pub fn may_drive(&self, user: &Principal) -> bool {
        user.may_drive() || self.grants.allows(&user.name, crate::runtime::locks::unix_now_ms())
    }

    /// Whether `name` may drive with `token` (a pad ticket or their password).
    pub fn check_operator(&self, name: &str, token: &str) -> bool {
        if self.tickets.redeem(name, token) {
            return self.users.get(name).is_some_and(|u| self.may_drive(&u));
        }
        self.users.authenticate(name, token).is_some_and(|u| self.may_drive(&u))
    }
}

/// The one user who may drive beyond their role, until when (ms since the
/// Unix epoch): the holder of the reservation in effect (docs/lab.md). The
/// lab sets it as windows open and close.
#[derive(Debug, Default)]
pub struct DriveGrants(std::sync::Mutex<Option<(String, u64)>>);

impl DriveGrants {
    /// `user` may drive until `until_ms`; `None`: nobody beyond their role.
    pub fn set(&self, grant: Option<(String, u64)>) {
        if let Ok(mut slot) = self.0.lock() {
            *slot = grant;
        }
    }

    /// Whether `user` holds a grant at `now_ms`.
    pub fn allows(&self, user: &str, now_ms: u64) -> bool {
        self.0.lock().ok().is_some_and(|g| g.as_ref().is_some_and(|(u, until)| u == user && now_ms < *until))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn users_are_added_checked_and_removed() {
        let dir = tempfile::tempdir().unwrap();
        let users = Users::new(dir.path().join("users.json"));
        assert_eq!(users.all().unwrap(), vec![]);
        UsersWriter::new(&users)
            .add("alice", Role::Developer, &[Platform::Control], "correct horse battery", false)
            .unwrap();
        let text = std::fs::read_to_string(users.path()).unwrap();
        assert!(text.contains("$argon2id$"), "{text}");
        assert!(!text.contains("correct horse"), "{text}");
        let alice = users.authenticate("alice", "correct horse battery").unwrap();
        assert!(alice.may_change(Platform::Control));
        assert!(!alice.may_change(Platform::Network));
        assert!(!alice.may_drive());
        assert!(users.authenticate("alice", "wrong horse battery").is_none());
        assert!(users.authenticate("bob", "correct horse battery").is_none());
        let err = UsersWriter::new(&users).add("alice", Role::Viewer, &[], "another password", false).unwrap_err();
        assert_eq!(err.to_string(), "user 'alice' exists already");
        let err = UsersWriter::new(&users).add("bob", Role::Developer, &[], "another password", false).unwrap_err();
        assert!(err.to_string().contains("needs at least one --platform"), "{err}");
        let err = UsersWriter::new(&users).add("bob", Role::Viewer, &[], "short", false).unwrap_err();
        assert!(err.to_string().contains("at least 10 characters"), "{err}");
        let err = UsersWriter::new(&users).add("Bob", Role::Viewer, &[], "long enough pw", false).unwrap_err();
        assert!(err.to_string().contains("user name 'Bob'"), "{err}");
        UsersWriter::new(&users).set_password("alice", "a brand new password").unwrap();
        assert!(users.authenticate("alice", "a brand new password").is_some());
        UsersWriter::new(&users).remove("alice").unwrap();
        assert!(users.get("alice").is_none());
        assert_eq!(UsersWriter::new(&users).remove("alice").unwrap_err().to_string(), "no user 'alice'");
    }

    #[test]
    fn a_damaged_users_file_is_an_error_naming_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("users.json");
        std::fs::write(&path, "{\"users\": [{\"name\": \"x\"").unwrap();
        let err = Users::new(path.clone()).all().unwrap_err().to_string();
        assert!(err.starts_with(&format!("users file {}:", path.display())), "{err}");
        std::fs::write(
            &path,
            r#"{"users":[{"name":"a","role":"admin","hash":"h"},{"name":"a","role":"admin","hash":"h"}]}"#,
        )
        .unwrap();
        let err = Users::new(path).all().unwrap_err().to_string();
        assert!(err.ends_with("user 'a' is listed twice"), "{err}");
    }

    #[test]
    fn tickets_are_single_use_and_bound_to_their_user() {
        let dir = tempfile::tempdir().unwrap();
        let users = Users::new(dir.path().join("users.json"));
        UsersWriter::new(&users).add("op", Role::Operator, &[], "operator password", false).unwrap();
        UsersWriter::new(&users).add("view", Role::Viewer, &[], "viewer password", false).unwrap();
        let directory = Directory::new(std::sync::Arc::new(users));
        let ticket = directory.tickets.issue("op").unwrap();
        assert!(!directory.check_operator("view", &ticket), "a ticket is its user's only");
        let ticket = directory.tickets.issue("op").unwrap();
        assert!(directory.check_operator("op", &ticket));
        assert!(!directory.check_operator("op", &ticket), "a ticket is used once");
        assert!(directory.check_operator("op", "operator password"));
        assert!(!directory.check_operator("view", "viewer password"), "viewers may not drive");
    }

    #[test]
    fn generated_passwords_are_long_and_differ() {
        let a = generate_password().unwrap();
        let b = generate_password().unwrap();
        assert_eq!(a.len(), GENERATED_PASSWORD_LEN);
        assert_ne!(a, b);
        assert!(a.chars().all(|c| c.is_ascii_alphanumeric()));
    }
}
