//! Deployments: turns sets from the store into validated robots, stages
//! uploaded robot files, and activates a set: builds it beside the running
//! one (off the control loop), then swaps it in at a cycle boundary, or
//! leaves the running set untouched and returns the errors.
//!
//! Invariants:
//! - a set is validated exactly like `subsume check`, with its WASM sources
//!   pinned to stored blobs by sha256; nothing outside the store is run;
//! - file parameters of built-ins in a set (world files, operators files,
//!   translators) are relative paths inside the robot's folder;
//! - the control thread only ever swaps a fully built, initialised graph;
//!   the old graph is dropped on the activating thread, not the loop;
//! - built-ins that own a device, a pseudo-terminal or a socket (sim,
//!   serial, teleop) and are unchanged keep running across the swap (the
//!   simulated robot keeps its pose, operators stay connected);
//! - `state.json` names the new set only after the swap happened.

use std::collections::{BTreeMap, HashMap};
use std::path::{Component as PathPart, Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::{Receiver, SyncSender};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use thiserror::Error;

use crate::arbiter::PriorityCell;
use crate::builtin::Services;
use crate::config::{
    ComponentConfig, ComponentSource, Diagnostic, Diagnostics, ParamOverride, Platform, Resolver, RobotConfig, limits,
};
use crate::contract::Description;
use crate::loader::{Loader, read_component_file};
use crate::report;
use crate::runtime::Graph;
use crate::runtime::control_loop::{Clock, CycleHook, StopReason, Waker};
use crate::sandbox::Sandbox;
use crate::store::{Outcome, SetRecord, Store, StoreError, sha256_hex, unix_now};
use crate::users::User;

/// Built-in kinds that own something outside the host; unchanged ones are
/// carried into the next set instead of being built twice.
pub const CARRIED_KINDS: &[&str] = &["sim", "serial", "teleop"];
/// Longest wait for the control loop to take a new graph: a loop stuck in a
/// call is bounded by the call's budget, so this only fires if it is gone.
pub const SWAP_TIMEOUT: Duration = Duration::from_secs(5);
/// How often the live status is published while someone watches.
pub const LIVE_PERIOD: Duration = Duration::from_millis(200);
/// Longest robot-file name kept (it names diagnostics).
pub const MAX_FILE_NAME_LEN: usize = 64;

/// Why a staging, activation or rollback did not happen. The running set is
/// untouched in every case.
#[derive(Debug, Error)]
pub enum DeployError {
    /// The robot file has errors (path:line:column: message each).
    #[error("{0}")]
    Invalid(Diagnostics),
    /// The set validated but some component failed to start.
    #[error("{}", .0.join("\n"))]
    Start(Vec<String>),
    /// The user lacks a permission, or the request makes no sense now.
    #[error("{0}")]
    Forbidden(String),
    #[error("{0}")]
    Conflict(String),
    #[error("{0}")]
    BadRequest(String),
    #[error(transparent)]
    Store(#[from] StoreError),
    #[error("{0}")]
    Host(String),
}

/// What is running: the set, its validated robot and what the next
/// activation needs to carry parts over.
pub struct Deployment {
    pub set: SetRecord,
    pub config: Arc<RobotConfig>,
    priorities: Vec<PriorityCell>,
    sim_ptys: HashMap<String, PathBuf>,
}

/// A graph waiting for the control thread.
pub struct SwapRequest {
    graph: Graph,
    /// (old index, new index) of carried components.
    carry: Vec<(usize, usize)>,
    config: Arc<RobotConfig>,
    set_id: u64,
    done: SyncSender<Graph>,
}

#[derive(Clone, Default)]
struct SwapSlot {
    request: Arc<Mutex<Option<SwapRequest>>>,
    waiting: Arc<AtomicBool>,
}

/// The live status the control loop publishes (the report's layout, with
/// `stopped_by: "running"` and the active set's id).
pub type LiveStatus = Arc<serde_json::Value>;

/// Runs on the control thread between cycles: swaps graphs, publishes the
/// live status.
pub struct ControlHook {
    slot: SwapSlot,
    config: Arc<RobotConfig>,
    set_id: u64,
    live: tokio::sync::watch::Sender<LiveStatus>,
    next_live_ns: u64,
}

impl ControlHook {
    /// The robot running now (for the final report).
    pub fn config(&self) -> &Arc<RobotConfig> {
        &self.config
    }
}

impl CycleHook for ControlHook {
    fn between_cycles(&mut self, graph: &mut Graph, now_ns: u64) {
        if self.slot.waiting.load(Ordering::Acquire) {
            self.slot.waiting.store(false, Ordering::Release);
            let request = self.slot.request.lock().ok().and_then(|mut slot| slot.take());
            if let Some(mut request) = request {
                for &(old, new) in &request.carry {
                    if let Some(component) = graph.take_component(old) {
                        request.graph.replace_component(new, component);
                    }
                }
                std::mem::swap(graph, &mut request.graph);
                self.config = request.config;
                self.set_id = request.set_id;
                self.next_live_ns = now_ns;
                // The activating thread drops the old graph.
                let _ = request.done.try_send(request.graph);
            }
        }
        if now_ns >= self.next_live_ns && self.live.receiver_count() > 0 {
            self.next_live_ns = now_ns + LIVE_PERIOD.as_nanos() as u64;
            let status = report::build(&self.config, graph, StopReason::Requested, now_ns as f64 / 1e9);
            if let Ok(mut value) = serde_json::to_value(status) {
                value["stopped_by"] = "running".into();
                value["set"] = self.set_id.into();
                self.live.send_replace(Arc::new(value));
            }
        }
    }
}

/// The deployment side of a run with a store: owns what is active and
/// performs stagings, activations and rollbacks (one at a time).
pub struct Runner {
    pub store: Arc<Store>,
    pub sandbox: Arc<Sandbox>,
    pub services: Services,
    clock: Clock,
    waker: Waker,
    overrides: Vec<ParamOverride>,
    slot: SwapSlot,
    active: Mutex<Deployment>,
    live: tokio::sync::watch::Receiver<LiveStatus>,
}

/// Where a run starts: the runner, the first graph, and the hook to run it
/// with.
pub struct Boot {
    pub runner: Arc<Runner>,
    pub graph: Graph,
    pub hook: ControlHook,
}

/// Options of [`Runner::boot`].
pub struct BootOptions<'a> {
    pub store: Arc<Store>,
    pub sandbox: Arc<Sandbox>,
    pub services: Services,
    /// The robot file given on the command line.
    pub config_path: &'a Path,
    pub overrides: Vec<ParamOverride>,
    pub clock: Clock,
    pub waker: Waker,
}

impl Runner {
    /// Starts from the store: the last activated set, unless the robot file
    /// given on the command line changed since it was last imported (or
    /// nothing was ever activated), in which case that file and the
    /// components it names are imported as a new set and activated.
    pub fn boot(options: BootOptions<'_>) -> Result<Boot, DeployError> {
        let BootOptions { store, sandbox, services, config_path, overrides, clock, waker } = options;
        let text = crate::config::read_config(config_path).map_err(DeployError::Invalid)?;
        let sha = sha256_hex(text.as_bytes());
        let state = store.state()?;
        let set = match state.active {
            Some(id) if state.boot_config_sha256.as_deref() == Some(sha.as_str()) => {
                let set = store.set(id)?;
                tracing::info!(
                    "restoring set {id} ({}, by {}) from {}",
                    set.config_name,
                    set.created_by,
                    store.root().display()
                );
                set
            }
            _ => import(&store, &sandbox, config_path, &text, &overrides)?,
        };
        let mut loader = Loader::new(&sandbox);
        let config = validate_set(&store, &set, &mut loader, &overrides)?;
        let built = crate::build(&config, &mut loader, clock, &waker, &services, &crate::Carry::default())
            .map_err(DeployError::Start)?;
        let config = Arc::new(config);
        let (live_tx, live) = tokio::sync::watch::channel(Arc::new(serde_json::Value::Null));
        let slot = SwapSlot::default();
        let hook =
            ControlHook { slot: slot.clone(), config: config.clone(), set_id: set.id, live: live_tx, next_live_ns: 0 };
        let deployment = Deployment { set, config, priorities: built.priorities, sim_ptys: built.sim_ptys };
        let runner =
            Runner { store, sandbox, services, clock, waker, overrides, slot, active: Mutex::new(deployment), live };
        Ok(Boot { runner: Arc::new(runner), graph: built.graph, hook })
    }

    /// A receiver of the live status.
    pub fn live(&self) -> tokio::sync::watch::Receiver<LiveStatus> {
        self.live.clone()
    }

    /// The active set and robot.
    pub fn active(&self) -> Result<(SetRecord, Arc<RobotConfig>), DeployError> {
        let active = self.active.lock().map_err(|_| DeployError::Host("the active set is unusable".into()))?;
        Ok((active.set.clone(), active.config.clone()))
    }

    /// Records `result` of `action` in the audit log and returns it.
    fn audited(
        &self,
        user: &User,
        action: &str,
        target: &str,
        result: Result<SetRecord, DeployError>,
        done: &str,
    ) -> Result<SetRecord, DeployError> {
        let (ok, error) = match &result {
            Ok(set) => (format!("{done} set {}", set.id), String::new()),
            Err(e) => (String::new(), e.to_string()),
        };
        let outcome = match &result {
            Ok(_) => Outcome::Ok(&ok),
            Err(
                DeployError::Invalid(_)
                | DeployError::Forbidden(_)
                | DeployError::Conflict(_)
                | DeployError::BadRequest(_)
                | DeployError::Store(StoreError::NoSet(_)),
            ) => Outcome::Refused(&error),
            Err(_) => Outcome::Failed(&error),
        };
        self.store.record(&user.name, action, target, outcome);
        result
    }

    /// Validates an uploaded robot file for `platform` against the stored
    /// components (and the active set's) and stages it as a new set.
    pub fn stage(
        &self,
        user: &User,
        platform: Platform,
        file_name: &str,
        bytes: &[u8],
    ) -> Result<SetRecord, DeployError> {
        let target = format!("{file_name} for platform {}", platform.name());
        self.audited(user, "upload-config", &target, self.stage_inner(user, platform, file_name, bytes), "staged as")
    }

    fn stage_inner(
        &self,
        user: &User,
        platform: Platform,
        file_name: &str,
        bytes: &[u8],
    ) -> Result<SetRecord, DeployError> {
        if !user.may_change(platform) {
            return Err(DeployError::Forbidden(format!("{} may not change platform {}", user.name, platform.name())));
        }
        check_file_name(file_name)?;
        if bytes.len() as u64 > limits::MAX_CONFIG_BYTES {
            return Err(DeployError::BadRequest(format!(
                "{file_name} is {} bytes; at most {} are allowed",
                bytes.len(),
                limits::MAX_CONFIG_BYTES
            )));
        }
        let text = std::str::from_utf8(bytes)
            .map_err(|e| DeployError::BadRequest(format!("{file_name} is not utf-8: {e}")))?;
        let (active_set, active_config) = self.active()?;
        let components = self.store.components()?;
        let lookup = |source: &str| -> Option<String> {
            let name = source.strip_suffix(".wasm").unwrap_or(source);
            components.get(name).map(|c| c.sha256.clone()).or_else(|| active_set.sources.get(source).cloned())
        };
        let record = SetRecord {
            id: 0,
            created_by: user.name.clone(),
            created_at: unix_now(),
            platform: Some(platform.name().into()),
            config_name: file_name.into(),
            config_sha256: String::new(),
            base_dir: active_set.base_dir.clone(),
            sources: BTreeMap::new(),
            changes: Vec::new(),
            graph: serde_json::Value::Null,
        };
        let mut loader = Loader::new(&self.sandbox);
        let (config, sources) = validate_text(&self.store, &record, text, &lookup, &mut loader, &self.overrides)?;
        let changes = platform_changes(&active_config, &config);
        if let Some(denied) = changes.iter().find(|p| !user.may_change(**p)) {
            return Err(DeployError::Forbidden(format!(
                "{file_name} changes platform {}, which {} may not change",
                denied.name(),
                user.name
            )));
        }
        let config_sha256 = self.store.put_blob(bytes)?;
        let record = SetRecord {
            config_sha256,
            sources,
            changes: changes.iter().map(|p| p.name().to_string()).collect(),
            graph: graph_json(&config),
            ..record
        };
        Ok(self.store.add_set(record)?)
    }

    /// Activates set `id`: see the module's invariants.
    pub fn activate(&self, user: &User, id: u64) -> Result<SetRecord, DeployError> {
        self.audited(user, "activate", &format!("set {id}"), self.switch(user, id, false), "activated")
    }

    /// Activates the set that was active before the current one.
    pub fn rollback(&self, user: &User) -> Result<SetRecord, DeployError> {
        let previous = self.store.state()?.history.last().copied();
        let target = previous.map_or_else(|| "none".to_string(), |id| format!("set {id}"));
        let result = match previous {
            _ if !user.is_developer() => Err(may_not_activate(user)),
            Some(id) => self.switch(user, id, true),
            None => Err(DeployError::Conflict("there is no previous set to roll back to".into())),
        };
        self.audited(user, "rollback", &target, result, "rolled back to")
    }

    fn switch(&self, user: &User, id: u64, rollback: bool) -> Result<SetRecord, DeployError> {
        if !user.is_developer() {
            return Err(may_not_activate(user));
        }
        let mut active = self.active.lock().map_err(|_| DeployError::Host("the active set is unusable".into()))?;
        if active.set.id == id {
            return Err(DeployError::Conflict(format!("set {id} is active already")));
        }
        let set = self.store.set(id)?;
        let mut loader = Loader::new(&self.sandbox);
        let config = validate_set(&self.store, &set, &mut loader, &self.overrides)?;
        let changes = platform_changes(&active.config, &config);
        if let Some(denied) = changes.iter().find(|p| !user.may_change(**p)) {
            return Err(DeployError::Forbidden(format!(
                "set {id} changes platform {}, which {} may not change",
                denied.name(),
                user.name
            )));
        }
        let pairs = carry_plan(&active.config, &config);
        let mut carry = crate::Carry::default();
        for &(old, new) in &pairs {
            if let Some(cell) = active.priorities.get(old) {
                carry.priorities.insert(new, cell.clone());
            }
            let name = &active.config.components[old].name;
            if let Some(pty) = active.sim_ptys.get(name) {
                carry.sim_ptys.insert(name.clone(), pty.clone());
            }
        }
        let built = crate::build(&config, &mut loader, self.clock, &self.waker, &self.services, &carry)
            .map_err(DeployError::Start)?;
        let config = Arc::new(config);
        let (done, old_graph) = std::sync::mpsc::sync_channel(1);
        let request = SwapRequest { graph: built.graph, carry: pairs, config: config.clone(), set_id: id, done };
        self.hand_over(request, &old_graph)?;
        let state = if rollback { self.store.mark_rolled_back(id) } else { self.store.mark_active(id) };
        if let Err(e) = state {
            tracing::error!("set {id} runs, but the store could not record it: {e}");
        }
        tracing::info!(
            "set {id} ({}) is active; {} by {}",
            set.config_name,
            if rollback { "rolled back" } else { "activated" },
            user.name
        );
        *active = Deployment { set: set.clone(), config, priorities: built.priorities, sim_ptys: built.sim_ptys };
        Ok(set)
    }

    /// Gives `request` to the control thread and waits for the old graph,
    /// which is dropped here.
    fn hand_over(&self, request: SwapRequest, old_graph: &Receiver<Graph>) -> Result<(), DeployError> {
        {
            let mut slot =
                self.slot.request.lock().map_err(|_| DeployError::Host("the swap slot is unusable".into()))?;
            *slot = Some(request);
        }
        self.slot.waiting.store(true, Ordering::Release);
        self.waker.wake();
        match old_graph.recv_timeout(SWAP_TIMEOUT) {
            Ok(old) => {
                drop(old);
                Ok(())
            }
            Err(_) => {
                let taken_back = self.slot.request.lock().ok().and_then(|mut slot| slot.take());
                if taken_back.is_some() {
                    return Err(DeployError::Host(format!(
                        "the control loop did not reach a cycle boundary within {} s",
                        SWAP_TIMEOUT.as_secs()
                    )));
                }
                // It was taken just now: the swap happened.
                drop(old_graph.recv_timeout(SWAP_TIMEOUT));
                Ok(())
            }
        }
    }
}

fn may_not_activate(user: &User) -> DeployError {
    DeployError::Forbidden(format!("{} may not activate sets", user.name))
}

/// Refuses robot-file names that are not a plain file name.
fn check_file_name(name: &str) -> Result<(), DeployError> {
    let plain = !name.is_empty()
        && name.len() <= MAX_FILE_NAME_LEN
        && !name.starts_with('.')
        && name.bytes().all(|b| b.is_ascii_alphanumeric() || b"._-".contains(&b));
    if plain {
        Ok(())
    } else {
        Err(DeployError::BadRequest(format!(
            "file name '{}' is not a plain name of at most {MAX_FILE_NAME_LEN} letters, digits, '.', '_' or '-'",
            crate::contract::clip(name)
        )))
    }
}

/// Imports the robot file at `path` and the components it names into the
/// store as a new active set.
fn import(
    store: &Store,
    sandbox: &Sandbox,
    path: &Path,
    text: &str,
    overrides: &[ParamOverride],
) -> Result<SetRecord, DeployError> {
    let mut loader = Loader::new(sandbox);
    let config =
        crate::config::parse_and_validate_for_run(path, text, &mut loader, overrides).map_err(DeployError::Invalid)?;
    let folder = path.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(Path::new("."));
    let base_dir = std::fs::canonicalize(folder)
        .map_err(|e| DeployError::Host(format!("cannot resolve {}: {e}", folder.display())))?;
    let mut sources = BTreeMap::new();
    for component in &config.components {
        if let ComponentSource::Wasm(file) = &component.source {
            let bytes = read_component_file(file).map_err(DeployError::Host)?;
            let key = file.strip_prefix(folder).unwrap_or(file).to_string_lossy().into_owned();
            sources.insert(key, store.put_blob(&bytes)?);
        }
    }
    let config_name = path.file_name().map_or_else(|| "robot.xml".into(), |n| n.to_string_lossy().into_owned());
    let sha = store.put_blob(text.as_bytes())?;
    let record = store.add_set(SetRecord {
        id: 0,
        created_by: "boot".into(),
        created_at: unix_now(),
        platform: None,
        config_name,
        config_sha256: sha.clone(),
        base_dir,
        sources,
        changes: vec![Platform::Control.name().into(), Platform::Network.name().into()],
        graph: graph_json(&config),
    })?;
    store.mark_active(record.id)?;
    store.set_boot_config(&sha)?;
    let detail = format!("imported {} and activated it", path.display());
    store.record("boot", "boot", &format!("set {}", record.id), Outcome::Ok(&detail));
    tracing::info!("imported {} as set {} and activated it", path.display(), record.id);
    Ok(record)
}

/// Validates stored set `set`; its WASM sources become blob paths.
pub fn validate_set(
    store: &Store,
    set: &SetRecord,
    loader: &mut Loader<'_>,
    overrides: &[ParamOverride],
) -> Result<RobotConfig, DeployError> {
    let bytes = store.blob(&set.config_sha256)?;
    let text =
        String::from_utf8(bytes).map_err(|e| DeployError::Host(format!("stored robot file is not utf-8: {e}")))?;
    let lookup = |source: &str| set.sources.get(source).cloned();
    validate_text(store, set, &text, &lookup, loader, overrides).map(|(config, _)| config)
}

/// Validates robot-file `text` for `set`'s folder, resolving WASM sources
/// through `lookup`; returns the robot and the sources it used.
fn validate_text(
    store: &Store,
    set: &SetRecord,
    text: &str,
    lookup: &dyn Fn(&str) -> Option<String>,
    loader: &mut Loader<'_>,
    overrides: &[ParamOverride],
) -> Result<(RobotConfig, BTreeMap<String, String>), DeployError> {
    let path = set.base_dir.join(&set.config_name);
    let mut resolver = SetResolver { store, loader, base_dir: &set.base_dir, lookup, used: BTreeMap::new() };
    let result = crate::config::parse_and_validate_for_run(&path, text, &mut resolver, overrides);
    let used = resolver.used;
    let mut config = result.map_err(|Diagnostics(list)| {
        DeployError::Invalid(Diagnostics(
            list.into_iter()
                .map(|d| Diagnostic {
                    path: if d.path == path { PathBuf::from(&set.config_name) } else { d.path },
                    ..d
                })
                .collect(),
        ))
    })?;
    for component in &mut config.components {
        if let ComponentSource::Wasm(file) = &component.source
            && let Some(sha) = used.get(&relative_source(&set.base_dir, file))
        {
            component.source = ComponentSource::Wasm(store.blob_path(sha));
        }
    }
    Ok((config, used))
}

fn relative_source(base_dir: &Path, file: &Path) -> String {
    file.strip_prefix(base_dir).unwrap_or(file).to_string_lossy().into_owned()
}

/// Resolves a set's sources to stored blobs and keeps built-ins' file
/// parameters inside the robot's folder.
struct SetResolver<'r, 'l> {
    store: &'r Store,
    loader: &'r mut Loader<'l>,
    base_dir: &'r Path,
    lookup: &'r dyn Fn(&str) -> Option<String>,
    used: BTreeMap<String, String>,
}

/// Parameters of built-ins that name files.
const FILE_PARAMS: &[&str] = &["world", "operators", "translator"];

impl Resolver for SetResolver<'_, '_> {
    fn describe(
        &mut self,
        source: &ComponentSource,
        params: &BTreeMap<String, String>,
        base_dir: &Path,
    ) -> Result<Description, String> {
        match source {
            ComponentSource::Builtin(_) => {
                for key in FILE_PARAMS {
                    if let Some(value) = params.get(*key) {
                        let path = Path::new(value.trim());
                        if path.components().any(|p| !matches!(p, PathPart::Normal(_))) {
                            return Err(format!(
                                "parameter '{key}' must be a path inside the robot's folder, got '{}'",
                                crate::contract::clip(value)
                            ));
                        }
                    }
                }
                self.loader.describe(source, params, base_dir)
            }
            ComponentSource::Wasm(file) => {
                let key = relative_source(self.base_dir, file);
                let sha = (self.lookup)(&key).ok_or_else(|| {
                    format!(
                        "unknown component '{}': upload it first (GET /api/v1/components lists the stored ones)",
                        crate::contract::clip(&key)
                    )
                })?;
                let description = self.loader.load_wasm(&self.store.blob_path(&sha))?.description.clone();
                self.used.insert(key, sha);
                Ok(description)
            }
        }
    }
}

/// What identifies a running instance: everything but its place in the file.
fn instance_key(c: &ComponentConfig) -> String {
    format!(
        "{}|{}|{}|{:?}|{:?}|{:?}|{}|{}|{}|{}|{:?}|{:?}",
        c.name,
        c.source,
        c.rate_hz,
        c.priority,
        c.budget,
        c.timeout,
        c.memory_bytes,
        c.max_emits,
        c.max_message_bytes,
        c.max_logs_per_s,
        c.restart,
        c.params.iter().map(|p| (&p.name, &p.value)).collect::<Vec<_>>()
    )
}

/// (old index, new index) of the built-ins `new` takes over from `old`.
pub fn carry_plan(old: &RobotConfig, new: &RobotConfig) -> Vec<(usize, usize)> {
    let carried_kind =
        |c: &ComponentConfig| matches!(&c.source, ComponentSource::Builtin(k) if CARRIED_KINDS.contains(&k.as_str()));
    let mut pairs: Vec<(usize, usize)> = new
        .components
        .iter()
        .enumerate()
        .filter(|(_, c)| carried_kind(c))
        .filter_map(|(n, c)| {
            let o = old.components.iter().position(|o| instance_key(o) == instance_key(c))?;
            Some((o, n))
        })
        .collect();
    // A serial link on a simulated robot's PTY is carried only with it.
    let carried_names: Vec<String> = pairs.iter().map(|&(_, n)| new.components[n].name.clone()).collect();
    pairs.retain(|&(_, n)| {
        let c = &new.components[n];
        let device = c.params.iter().find(|p| p.name == "device").map(|p| p.value.trim().to_string());
        match device.as_deref().and_then(|d| d.strip_prefix("sim:")) {
            Some(sim) => carried_names.iter().any(|name| name == sim),
            None => true,
        }
    });
    pairs
}

/// The platforms whose components or connections differ between two robots.
pub fn platform_changes(old: &RobotConfig, new: &RobotConfig) -> Vec<Platform> {
    let fingerprint = |robot: &RobotConfig, platform: Platform| -> Vec<String> {
        let mut lines: Vec<String> =
            robot.components.iter().filter(|c| c.platform == platform).map(instance_key).collect();
        let name = |i: usize| robot.components.get(i).map_or("?", |c| c.name.as_str());
        lines.extend(robot.connections.iter().filter(|c| c.platform == platform).map(|c| {
            format!(
                "{}.{} -> {}.{} {:?}",
                name(c.from.component),
                c.from.port,
                name(c.to.component),
                c.to.port,
                c.policy
            )
        }));
        lines.sort();
        lines
    };
    [Platform::Control, Platform::Network]
        .into_iter()
        .filter(|p| fingerprint(old, *p) != fingerprint(new, *p))
        .collect()
}

/// Components (with their ports) and connections, for the wiring view.
pub fn graph_json(config: &RobotConfig) -> serde_json::Value {
    let components: Vec<serde_json::Value> = config
        .components
        .iter()
        .map(|c| {
            let names = |ports: &[crate::contract::PortSpec]| ports.iter().map(|p| p.name.clone()).collect::<Vec<_>>();
            serde_json::json!({
                "name": c.name,
                "platform": c.platform.name(),
                "source": match &c.source {
                    ComponentSource::Builtin(kind) => format!("builtin:{kind}"),
                    ComponentSource::Wasm(_) => format!("wasm:{}", c.description.name),
                },
                "priority": c.priority,
                "rate_hz": c.rate_hz,
                "inputs": names(&c.description.inputs),
                "outputs": names(&c.description.outputs),
            })
        })
        .collect();
    let port = |index: usize, port: u32, output: bool| -> String {
        let Some(c) = config.components.get(index) else { return "?".into() };
        let ports = if output { &c.description.outputs } else { &c.description.inputs };
        format!("{}.{}", c.name, ports.get(port as usize).map_or("?", |p| p.name.as_str()))
    };
    let connections: Vec<serde_json::Value> = config
        .connections
        .iter()
        .map(|c| {
            serde_json::json!({
                "from": port(c.from.component, c.from.port, true),
                "to": port(c.to.component, c.to.port, false),
                "platform": c.platform.name(),
            })
        })
        .collect();
    serde_json::json!({ "robot": config.name, "components": components, "connections": connections })
}
