//! The deploy side of a lab of several robots (docs/lab.md, "Several
//! robots"): sets that arrive whole over the lab's link, and a host that
//! runs no robot.
//!
//! - [`Deployer::import_set`] stores a set that arrives as a robot file
//!   and the blobs its sources were pinned to (a robot's baseline on the
//!   lab server; a lab's experiment on a robot), validated exactly like a
//!   staged one, its built-ins' files resolved in `base_dir`.
//! - [`Deployer::headless`] is the deployer of the lab server: uploads,
//!   staging, validation and the experiments' checks work as on a robot,
//!   against the lab's reference (a robot's baseline it imported), while
//!   nothing ever runs: every activation is refused.
//!
//! Invariants: an imported set's sources are blobs already in the store
//! (checked by sha256 when they were fetched); an identical set already
//! stored is reused, so a robot that runs the same experiment set a
//! hundred times stores it once.

use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};

use super::DeployError;
use super::swap::SwapSlot;
use super::{Deployer, Deployment, ExperimentGate, LiveStatusCell, PlotHistory, stage};
use crate::assemble::Loader;
use crate::builtin::Services;
use crate::config::RobotConfig;
use crate::runtime::control_loop::{Clock, Shutdown};
use crate::sandbox::Sandbox;
use crate::store::{Outcome, STORE_FORMAT, SetRecord, Store, WiringGraph, unix_now};

/// A set that arrives whole.
#[derive(Clone, Debug)]
pub struct SetImport<'a> {
    /// Who it is recorded as made by (`robot:NAME`, `USER@LAB`).
    pub by: &'a str,
    pub config_name: &'a str,
    pub config_text: &'a str,
    pub platform: Option<&'a str>,
    /// Each WASM source (and uploaded world) -> its blob, stored already.
    pub sources: &'a BTreeMap<String, String>,
    /// Where the files its built-ins name are.
    pub base_dir: &'a Path,
}

impl Deployer {
    /// The deployer of a host that runs no robot (the lab server): its
    /// "active set" is the lab's reference, set with
    /// [`Deployer::set_reference`] (none at first: staging is refused
    /// until a robot's baseline is known).
    pub fn headless(store: Arc<Store>, sandbox: Arc<Sandbox>, services: Services) -> Arc<Deployer> {
        let placeholder = SetRecord {
            format: STORE_FORMAT,
            id: 0,
            created_by: String::new(),
            created_at: 0,
            platform: None,
            config_name: String::new(),
            config_sha256: String::new(),
            base_dir: store.root().to_path_buf(),
            sources: BTreeMap::new(),
            changes: Vec::new(),
            graph: WiringGraph::default(),
        };
        let config =
            RobotConfig { name: String::new(), path: PathBuf::new(), components: Vec::new(), connections: Vec::new() };
        let deployment =
            Deployment { set: placeholder, config: Arc::new(config), priorities: Vec::new(), sim_ptys: HashMap::new() };
        Arc::new(Deployer {
            store,
            sandbox,
            services,
            clock: Clock::new(),
            waker: Shutdown::new().waker(),
            overrides: Vec::new(),
            slot: SwapSlot::default(),
            active: Mutex::new(deployment),
            live: LiveStatusCell::default(),
            history: PlotHistory::default(),
            compiles: Mutex::new(()),
            validations: Mutex::new(()),
            replays: Mutex::new(()),
            experiments: ExperimentGate::default(),
            boot_set: 0,
            headless: true,
        })
    }

    /// Whether this host runs no robot (the lab server).
    pub fn is_headless(&self) -> bool {
        self.headless
    }

    /// Makes stored set `id` the reference of a headless deployer: what
    /// uploads are staged against. It must validate.
    pub fn set_reference(&self, id: u64) -> Result<(), DeployError> {
        if !self.headless {
            return Err(DeployError::Conflict("only the lab server has a reference set".into()));
        }
        let set = self.store.set(id)?;
        let mut loader = Loader::new(&self.sandbox);
        let config = stage::validate_set(&self.store, &set, &mut loader, &self.overrides)?;
        let mut active = self.lock_active()?;
        active.set = set;
        active.config = Arc::new(config);
        tracing::info!("the lab's reference is set {id}");
        Ok(())
    }

    /// Refuses what only a robot does, on the lab server.
    pub(super) fn refuse_headless(&self, what: &str) -> Result<(), DeployError> {
        if self.headless {
            return Err(DeployError::Conflict(format!("the lab server runs no robot: it cannot {what}")));
        }
        Ok(())
    }

    /// Stores `import` as a set (validated like a staged one; an identical
    /// stored set is reused), audited as `import.by`.
    pub fn import_set(&self, import: &SetImport<'_>) -> Result<SetRecord, DeployError> {
        let target = format!("{} by {}", import.config_name, import.by);
        let prepared = (|| {
            stage::check_file_name(import.config_name)?;
            let missing = import.sources.values().find(|sha| !self.store.blob_path(sha).is_file());
            if let Some(sha) = missing {
                return Err(DeployError::Host(format!("blob {sha} of the set is not stored")));
            }
            let record = SetRecord {
                format: STORE_FORMAT,
                id: 0,
                created_by: import.by.to_string(),
                created_at: unix_now(),
                platform: import.platform.map(str::to_string),
                config_name: import.config_name.to_string(),
                config_sha256: String::new(),
                base_dir: import.base_dir.to_path_buf(),
                sources: BTreeMap::new(),
                changes: Vec::new(),
                graph: WiringGraph::default(),
            };
            let worlds = |source: &str| import.sources.get(source).cloned();
            let lookup = |source: &str| {
                worlds(source)
                    .ok_or_else(|| format!("unknown source '{}': not sent with the set", crate::contract::clip(source)))
            };
            let mut loader = Loader::new(&self.sandbox);
            let (config, sources) = stage::validate_text(
                &self.store,
                &record,
                import.config_text,
                &lookup,
                &worlds,
                &mut loader,
                &self.overrides,
            )?;
            let (_, active) = self.active()?;
            let changes = stage::platform_changes(&active, &config).iter().map(|p| p.name().to_string()).collect();
            Ok(SetRecord { sources, changes, graph: stage::wiring_graph(&config), ..record })
        })();
        self.commit(
            import.by,
            "import-set",
            &target,
            prepared,
            |writer, record: SetRecord| {
                let config_sha256 = writer.put_blob(import.config_text.as_bytes())?;
                let same = |s: &SetRecord| {
                    s.config_sha256 == config_sha256
                        && s.sources == record.sources
                        && s.base_dir == record.base_dir
                        && s.created_by == record.created_by
                };
                if let Some(existing) = self.store.sets()?.into_iter().rev().find(same) {
                    return Ok(existing);
                }
                Ok(writer.add_set(SetRecord { config_sha256, ..record })?)
            },
            |set| format!("stored as set {}", set.id),
        )
    }

    /// Records `action` on `target` by `user` in the audit log (the lab's
    /// link: a dispatch refused, an emergency stop from the lab).
    pub fn audit(&self, user: &str, action: &str, target: &str, outcome: Outcome<'_>) {
        match self.store.lock() {
            Ok(writer) => writer.record(user, action, target, outcome),
            Err(e) => tracing::error!("cannot lock the store to record {action} by {user}: {e}"),
        }
    }
}
