//! The use cases of a run with a store: boot, upload a component, stage a
//! robot file, activate a set, roll back, engage and release the emergency
//! stop (`estop.rs`). Each one is a method of
//! [`Deployer`] in its own file and has the same shape:
//!
//! 1. authorise ([`authorise`], the one permission check);
//! 2. prepare without the store's lock: check, compile, validate, build the
//!    new graph beside the running one;
//! 3. [`Deployer::commit`]: take the store's lock (the one place a use case
//!    takes it), apply the change, and write the one audit line of the
//!    request, refused or not, under the same lock.
//!
//! Invariants:
//! - a set is validated exactly like `subsume check`, with its WASM sources
//!   pinned to stored blobs by sha256; nothing outside the store is run;
//! - file parameters of built-ins in an uploaded set stay inside the
//!   robot's folder;
//! - the control thread only ever swaps a fully built, initialised graph;
//!   the old graph is dropped on the activating thread, not the loop;
//! - built-ins that own a device, a pseudo-terminal or a socket and are
//!   unchanged keep running across the swap;
//! - `state.json` names the new set only after the swap happened, and the
//!   swap happens under the store's lock, after the set was found still
//!   stored: the active set's record always describes what runs;
//! - on any error the running set is untouched.

mod activate;
pub mod dev;
mod estop;
mod experiment;
mod history;
mod lab_sets;
mod recordings;
mod replay;
mod reset;
mod sim;
mod stage;
mod swap;
mod upload;
mod worlds;

use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};

use thiserror::Error;

pub use self::estop::{AUDIT_QUEUE, Engaged, LocksView, Released};
pub use self::experiment::{
    CheckedSet, Ended, ExperimentGate, LAB_LOCK, LAB_USER, Preempt, PreemptError, RunningExperiment, utc_time,
};
pub use self::history::{HISTORY_PERIOD_NS, HISTORY_SAMPLES, HistorySample, MAX_SAMPLE_SERIES, PlotHistory};
pub use self::lab_sets::SetImport;
pub use self::recordings::RecordingsView;
pub use self::replay::{
    MAX_CONCURRENT_REPLAYS, MAX_REPLAY_COMPONENTS, MAX_REPLAY_DURATION, MAX_REPLAY_RECORDING_BYTES,
};
pub use self::sim::{SimAction, SimView};
pub use self::stage::{MAX_CONCURRENT_VALIDATIONS, MAX_FILE_NAME_LEN, Validated};
pub use self::swap::{ControlHook, LIVE_PERIOD, LiveStatusCell, SWAP_TIMEOUT};
pub use self::upload::{MAX_CONCURRENT_COMPILES, MAX_UPLOAD_BYTES};
pub use self::worlds::WORLD_SUFFIX;
use crate::assemble::{self, Carry, Loader, StartError};
use crate::builtin::Services;
pub use crate::config::limits::MAX_CONFIG_BYTES as MAX_CONFIG_UPLOAD_BYTES;
use crate::config::{ComponentSource, RobotConfig};
pub use crate::config::{Diagnostic, Diagnostics, ParamOverride, Platform, SourceMap, read_and_parse};
use crate::runtime::control_loop::{Clock, Waker};
use crate::runtime::wiring::PriorityCell;
use crate::runtime::{Graph, RunningRobot};
use crate::sandbox::{Sandbox, read_component_file};
pub use crate::sim::world::MAX_WORLD_BYTES as MAX_WORLD_UPLOAD_BYTES;
// What the use cases answer, for the portal (its document names them).
pub use crate::record::control::{RecordingInfo, Stopped};
pub use crate::record::replay::ReplayReport;
pub use crate::sim::physics::SimStatus;
use crate::store::users::Principal;
use crate::store::{Outcome, STORE_FORMAT, SetRecord, Store, StoreError, StoreWriter, sha256_hex, unix_now};

/// The name the robot file given on the command line is imported as: the
/// owner's own set, the robot's.
pub const BOOT_USER: &str = "boot";

/// Why a use case did not happen. The running set is untouched in every case.
#[derive(Debug, Error)]
pub enum DeployError {
    /// The robot file has errors (path:line:column: message each).
    #[error("{0}")]
    Invalid(Diagnostics),
    /// The set validated but some component failed to start.
    #[error("{}", .0.iter().map(ToString::to_string).collect::<Vec<_>>().join("\n"))]
    Start(Vec<StartError>),
    /// The user lacks a permission.
    #[error("{0}")]
    Forbidden(String),
    /// The request makes no sense now (the set is active already, ...).
    #[error("{0}")]
    Conflict(String),
    /// The request itself is malformed (a bad name, an empty upload, ...).
    #[error("{0}")]
    BadRequest(String),
    /// The upload is not a WebAssembly component.
    #[error("not a webassembly component: {0}")]
    NotAComponent(String),
    /// The upload is a component but fits neither world.
    #[error("{0}")]
    WrongWorld(String),
    /// What the request names does not exist.
    #[error("{0}")]
    NotFound(String),
    #[error(transparent)]
    Store(#[from] StoreError),
    /// The host is doing as many of these as it allows; try again soon.
    #[error("{0}")]
    Busy(String),
    /// The request is well formed but cannot be carried out on what it
    /// names (a recording of another robot, ...).
    #[error("{0}")]
    Unprocessable(String),
    /// The host failed (a thread, the control loop, a file it needs).
    #[error("{0}")]
    Host(String),
}

impl DeployError {
    /// Whether the host failed (rather than refused the request).
    pub fn is_failure(&self) -> bool {
        match self {
            DeployError::Store(StoreError::NoSet(_)) => false,
            DeployError::Store(_) | DeployError::Host(_) | DeployError::Start(_) => true,
            _ => false,
        }
    }
}

/// What a user may ask for.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Permission {
    /// Upload a component or a robot file for a platform.
    Change(Platform),
    /// Activate a set or roll back.
    Activate,
    /// Drive the robot (the portal's pad, teleoperation).
    Drive,
    /// Read the audit log.
    ReadAudit,
    /// Start, stop, list, download and delete recordings.
    Record,
}

/// The one permission check of every use case.
pub fn authorise(user: &Principal, permission: Permission) -> Result<(), DeployError> {
    let allowed = match permission {
        Permission::Change(platform) => user.may_change(platform),
        Permission::Activate | Permission::ReadAudit | Permission::Record => user.is_developer(),
        Permission::Drive => user.may_drive(),
    };
    if allowed {
        return Ok(());
    }
    Err(DeployError::Forbidden(match permission {
        Permission::Change(platform) => format!("{} may not change platform {}", user.name, platform.name()),
        Permission::Activate => format!("{} may not activate sets", user.name),
        Permission::Drive => format!("{} may not drive (role {})", user.name, user.role.name()),
        Permission::ReadAudit => format!("{} may not read the audit log", user.name),
        Permission::Record => format!("{} may not record (developers and admins may)", user.name),
    }))
}

/// What is running: the set, its validated robot and what the next
/// activation needs to carry parts over.
pub struct Deployment {
    pub set: SetRecord,
    pub config: Arc<RobotConfig>,
    priorities: Vec<PriorityCell>,
    sim_ptys: HashMap<String, PathBuf>,
}

/// The deployment side of a run with a store: owns what is active and
/// carries out the use cases.
pub struct Deployer {
    pub store: Arc<Store>,
    pub sandbox: Arc<Sandbox>,
    pub services: Services,
    clock: Clock,
    waker: Waker,
    overrides: Vec<ParamOverride>,
    slot: swap::SwapSlot,
    /// Held through a whole activation or rollback (before the store's
    /// lock, never after it), so two cannot interleave.
    active: Mutex<Deployment>,
    live: LiveStatusCell,
    /// The plots' history, sampled by the control thread.
    history: PlotHistory,
    /// One compile at a time (see [`MAX_CONCURRENT_COMPILES`]).
    compiles: Mutex<()>,
    /// One validation at a time (see [`MAX_CONCURRENT_VALIDATIONS`]).
    validations: Mutex<()>,
    /// One replay at a time (see [`MAX_CONCURRENT_REPLAYS`]).
    replays: Mutex<()>,
    /// The experiment that runs, if any (docs/lab.md).
    experiments: ExperimentGate,
    /// The set the host started with.
    boot_set: u64,
    /// It runs no robot (the lab server): every activation is refused.
    headless: bool,
}

/// Where a run starts: the deployer, the first graph, and the hook to run
/// it with.
pub struct Boot {
    pub deployer: Arc<Deployer>,
    pub graph: Graph,
    pub hook: ControlHook,
}

/// Options of [`Deployer::boot`].
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

impl Deployer {
    /// Starts from the store: the last activated set, unless the robot file
    /// given on the command line changed since it was last imported (or
    /// nothing was ever activated), in which case that file and the
    /// components it names are imported as a new set and activated.
    pub fn boot(options: BootOptions<'_>) -> Result<Boot, DeployError> {
        let BootOptions { store, sandbox, mut services, config_path, overrides, clock, waker } = options;
        if services.get::<crate::runtime::Locks>().is_none() {
            // One board for every set this host will run.
            services = services.with(Arc::new(crate::runtime::Locks::with_waker(waker.clone())));
        }
        let text = crate::config::read_config(config_path).map_err(DeployError::Invalid)?;
        let sha = sha256_hex(text.as_bytes());
        let state = store.state()?;
        let set = match state.active {
            Some(id) if state.boot_config_sha256.as_deref() == Some(sha.as_str()) => {
                let set = store.set(id)?;
                tracing::info!(
                    owner = %set.created_by,
                    "restoring set {id} ({}, by {}) from {}",
                    set.config_name,
                    set.created_by,
                    store.root().display()
                );
                set
            }
            _ => import(&store, &sandbox, config_path, &text, &overrides, Import::Boot)?,
        };
        let mut loader = Loader::new(&sandbox);
        let config = stage::validate_set(&store, &set, &mut loader, &overrides)?;
        if let Some(robot) = services.get::<RunningRobot>() {
            robot.rename(&config.name);
        }
        // A component's log lines name the work of the set's owner.
        crate::logfields::set_running_owners(&[&set.created_by]);
        let built = assemble::build(&config, &mut loader, clock.clone(), &waker, &services, &Carry::default())
            .map_err(DeployError::Start)?;
        let config = Arc::new(config);
        let live = LiveStatusCell::default();
        let history = PlotHistory::default();
        let slot = swap::SwapSlot::default();
        let hook = ControlHook::new(slot.clone(), config.clone(), set.id, live.clone(), history.clone());
        let boot_set = set.id;
        let deployment = Deployment { set, config, priorities: built.priorities, sim_ptys: built.sim_ptys };
        if let Some(locks) = services.get::<crate::runtime::Locks>() {
            estop::audit_locks(&locks, store.clone())?;
        }
        let deployer = Deployer {
            store,
            sandbox,
            services,
            clock,
            waker,
            overrides,
            slot,
            active: Mutex::new(deployment),
            live,
            history,
            compiles: Mutex::new(()),
            validations: Mutex::new(()),
            replays: Mutex::new(()),
            experiments: ExperimentGate::default(),
            boot_set,
            headless: false,
        };
        Ok(Boot { deployer: Arc::new(deployer), graph: built.graph, hook })
    }

    /// [`authorise`] for [`Permission::Drive`], with the grants of the
    /// portal's directory: a researcher drives inside their reservation
    /// (docs/lab.md) with an operator's rights.
    pub fn authorise_drive(&self, user: &Principal) -> Result<(), DeployError> {
        let granted = self.services.get::<crate::store::users::Directory>().is_some_and(|d| d.may_drive(user));
        if granted { Ok(()) } else { authorise(user, Permission::Drive) }
    }

    /// The graph's time now (ns): what durations on the robot are measured
    /// in (simulated time on a simulated clock).
    pub fn graph_now_ns(&self) -> u64 {
        self.clock.now_ns()
    }

    /// The live status, as the control loop last published it.
    pub fn live(&self) -> &LiveStatusCell {
        &self.live
    }

    /// The newest frames of the running camera `name`, for `user`, if she
    /// may watch the robot ([`Deployer::may_watch_cameras`]).
    pub fn watch_camera(
        &self,
        user: &Principal,
        name: &str,
    ) -> Result<tokio::sync::watch::Receiver<crate::camera::live::Latest>, DeployError> {
        self.may_watch_cameras(user)?;
        self.services.get::<crate::camera::live::LiveCameras>().and_then(|cameras| cameras.watch(name)).ok_or_else(
            || DeployError::NotFound(format!("no camera '{}' runs on this robot", crate::contract::clip_to(name, 64))),
        )
    }

    /// The running cameras' names.
    pub fn camera_names(&self) -> Vec<String> {
        self.services.get::<crate::camera::live::LiveCameras>().map(|cameras| cameras.names()).unwrap_or_default()
    }

    /// Whether `user` may watch the robot's cameras now: the owner (admin)
    /// and operators, who may watch the robot; a researcher only while her
    /// own experiment runs on it (a camera sees the lab, and other people's
    /// runs); no one else.
    pub fn may_watch_cameras(&self, user: &Principal) -> Result<(), DeployError> {
        use crate::store::users::Role;
        match user.role {
            Role::Admin | Role::Operator => Ok(()),
            Role::Researcher if self.experiments.running().is_some_and(|e| e.submitter == user.name) => Ok(()),
            Role::Researcher => Err(DeployError::Forbidden(format!(
                "{} may watch the cameras only while her own experiment runs on the robot",
                user.name
            ))),
            role => Err(DeployError::Forbidden(format!(
                "{} may not watch the cameras (role {}): the owner, operators, and a researcher during her own experiment may",
                user.name,
                role.name()
            ))),
        }
    }

    /// The plots' history (a sample a second, the last
    /// [`HISTORY_SAMPLES`]) and the graph time now, seconds: for whoever
    /// may see the live status.
    pub fn plot_history(&self) -> (Vec<HistorySample>, f64) {
        (self.history.samples(), self.clock.now_ns() as f64 / 1e9)
    }

    /// The active set and robot.
    pub fn active(&self) -> Result<(SetRecord, Arc<RobotConfig>), DeployError> {
        let active = self.active.lock().map_err(|_| DeployError::Host("the active set is unusable".into()))?;
        Ok((active.set.clone(), active.config.clone()))
    }

    /// The second half of every use case: takes the store's lock, applies
    /// `prepared` with `apply` when it is `Ok`, and records the request in
    /// the audit log under the same lock, whatever happened.
    fn commit<P, T>(
        &self,
        user: &str,
        action: &str,
        target: &str,
        prepared: Result<P, DeployError>,
        apply: impl FnOnce(&StoreWriter<'_>, P) -> Result<T, DeployError>,
        done: impl FnOnce(&T) -> String,
    ) -> Result<T, DeployError> {
        let writer = match self.store.lock() {
            Ok(writer) => writer,
            Err(e) => {
                tracing::error!("cannot lock the store to record {action} by {user}: {e}");
                return Err(e.into());
            }
        };
        let result = prepared.and_then(|p| apply(&writer, p));
        match &result {
            Ok(value) => writer.record(user, action, target, Outcome::Ok(&done(value))),
            Err(e) => {
                let detail = e.to_string();
                let outcome = if e.is_failure() { Outcome::Failed(&detail) } else { Outcome::Refused(&detail) };
                writer.record(user, action, target, outcome);
            }
        }
        result
    }
}

/// Gives the memory that an activation's or a compile's short-lived
/// allocations freed back to the system. glibc keeps it in the thread
/// arenas of the threads that did the work, where a later, differently
/// shaped activation rarely fits it again: the hour soak grew about 10 KiB
/// per activation that way with no allocation held (BENCHMARKS.md,
/// 2026-11-27: heaptrack finds nothing held; with a trim after every
/// activation the RSS levels off). Costs a walk of the arenas, off the
/// control loop (uploads and activations run on blocking threads).
fn give_back_freed_memory() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: malloc_trim only returns free pages to the system; it takes
    // each arena's own lock, like any allocation.
    unsafe {
        libc::malloc_trim(0);
    }
}

/// Imports the robot file at `path` and the components it names into the
/// store as a new active set (boot's own use case: the robot's owner, on
/// the command line).
fn import(
    store: &Store,
    sandbox: &Sandbox,
    path: &Path,
    text: &str,
    overrides: &[ParamOverride],
    how: Import,
) -> Result<SetRecord, DeployError> {
    let mut loader = Loader::new(sandbox);
    let config =
        crate::config::parse_and_validate_for_run(path, text, &mut loader, overrides).map_err(DeployError::Invalid)?;
    let folder = path.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(Path::new("."));
    let base_dir = std::fs::canonicalize(folder)
        .map_err(|e| DeployError::Host(format!("cannot resolve {}: {e}", folder.display())))?;
    let mut files = Vec::new();
    for component in &config.components {
        if let ComponentSource::Wasm(file) = &component.source {
            let bytes = read_component_file(file).map_err(|e| DeployError::Host(e.to_string()))?;
            let key = file.strip_prefix(folder).unwrap_or(file).to_string_lossy().into_owned();
            files.push((key, bytes));
        }
    }
    let config_name = path.file_name().map_or_else(|| "robot.xml".into(), |n| n.to_string_lossy().into_owned());
    let writer = store.lock()?;
    let mut sources = BTreeMap::new();
    for (key, bytes) in files {
        sources.insert(key, writer.put_blob(&bytes)?);
    }
    let sha = writer.put_blob(text.as_bytes())?;
    let record = writer.add_set(SetRecord {
        format: STORE_FORMAT,
        id: 0,
        created_by: match how {
            Import::Boot => BOOT_USER.into(),
            Import::Dev => dev::DEV_USER.into(),
        },
        created_at: unix_now(),
        platform: None,
        config_name,
        config_sha256: sha.clone(),
        base_dir,
        sources,
        changes: vec![Platform::Control.name().into(), Platform::Network.name().into()],
        graph: stage::wiring_graph(&config),
    })?;
    if how == Import::Dev {
        let detail = format!("imported {} (subsume dev)", path.display());
        writer.record(dev::DEV_USER, "import", &format!("set {}", record.id), Outcome::Ok(&detail));
        return Ok(record);
    }
    writer.mark_active(record.id)?;
    writer.set_boot_config(&sha)?;
    let detail = format!("imported {} and activated it", path.display());
    writer.record(BOOT_USER, "boot", &format!("set {}", record.id), Outcome::Ok(&detail));
    tracing::info!("imported {} as set {} and activated it", path.display(), record.id);
    Ok(record)
}

/// Why a robot file is imported from disk: at boot (it becomes the active
/// set at once: nothing runs yet), or by `subsume dev` (a staged set, then
/// activated like any other).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Import {
    Boot,
    Dev,
}

impl Deployer {
    /// Who may see what of the store now (`store::access`), with the
    /// owner's lab kit setting `kit`.
    pub fn access_with_kit(&self, kit: bool) -> Result<crate::store::access::Access, DeployError> {
        let users = self.store.users().all().map_err(|e| DeployError::Host(e.to_string()))?;
        Ok(crate::store::access::Access::new(&users, kit))
    }

    /// Who may see what of the store now, for what never leaves the robot
    /// by the kit (records, staging).
    pub fn access(&self) -> Result<crate::store::access::Access, DeployError> {
        self.access_with_kit(false)
    }

    /// The parameters this host sets on every set it validates (`subsume
    /// run --param`): what the set view shows as in effect beyond the file.
    pub fn overrides(&self) -> &[ParamOverride] {
        &self.overrides
    }
}
