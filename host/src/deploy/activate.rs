//! Activation and rollback: the set is validated and its graph built beside
//! the running one (carrying unchanged devices and sockets over); then,
//! under the store's lock, the control thread swaps it in at a cycle
//! boundary and the store records it.

use std::sync::Arc;

use super::swap::{ReportRequest, SwapRequest};
use super::{DeployError, Deployer, Deployment, Permission, authorise, stage};
use crate::assemble::{self, Built, Carry, Loader};
use crate::config::RobotConfig;
use crate::runtime::RunningRobot;
use crate::store::users::{Principal, Role};
use crate::store::{SetRecord, StoreError};

/// A set whose graph is built and waits for the swap.
pub(super) struct Ready {
    pub(super) set: SetRecord,
    pub(super) config: Arc<RobotConfig>,
    built: Built,
    carry: Vec<(usize, usize)>,
    /// How an admin's switch changes the envelope, for the audit line.
    envelope: Option<String>,
}

impl Deployer {
    /// Activates set `id`: see the module's invariants.
    pub fn activate(&self, user: &Principal, id: u64) -> Result<SetRecord, DeployError> {
        self.switch(user, Some(id), false).map(|(set, _)| set)
    }

    /// [`Deployer::activate`], and what an admin's activation did first
    /// (it ends a running experiment: docs/lab.md), for the answer.
    pub fn activate_noting(&self, user: &Principal, id: u64) -> Result<(SetRecord, Option<String>), DeployError> {
        self.switch(user, Some(id), false)
    }

    /// Activates the set that was active before the current one.
    pub fn rollback(&self, user: &Principal) -> Result<SetRecord, DeployError> {
        self.switch(user, None, true).map(|(set, _)| set)
    }

    /// [`Deployer::rollback`], and what it did first (see
    /// [`Deployer::activate_noting`]).
    pub fn rollback_noting(&self, user: &Principal) -> Result<(SetRecord, Option<String>), DeployError> {
        self.switch(user, None, true)
    }

    /// The active deployment, held through a whole activation (before the
    /// store's lock, never after it).
    pub(super) fn lock_active(&self) -> Result<std::sync::MutexGuard<'_, Deployment>, DeployError> {
        self.active.lock().map_err(|_| DeployError::Host("the active set is unusable".into()))
    }

    /// Activates `id`, or the previous set when rolling back.
    fn switch(
        &self,
        user: &Principal,
        id: Option<u64>,
        rollback: bool,
    ) -> Result<(SetRecord, Option<String>), DeployError> {
        // An experiment that runs refuses the change, or, for an admin, is
        // ended first (before the active set's lock, which ending it takes).
        let what = match id {
            Some(id) => format!("activate set {id}"),
            None => "roll back".to_string(),
        };
        let id = match id {
            Some(id) => Ok(id),
            None => self.store.state().map_err(DeployError::from).and_then(|state| {
                state
                    .history
                    .last()
                    .copied()
                    .ok_or_else(|| DeployError::Conflict("there is no previous set to roll back to".into()))
            }),
        };
        // What can be known before the experiment ends is checked first: a
        // refused activation changes nothing, not even the experiment.
        let preempted = authorise(user, Permission::Activate)
            .and_then(|()| match &id {
                Ok(id) => self.precheck(*id),
                // Said by the activation itself, below.
                Err(_) => Ok(()),
            })
            .and_then(|()| self.experiments.admit(user, &what));
        let mut active = self.lock_active()?;
        let (action, target) = match (&id, rollback) {
            (Ok(id), false) => ("activate", format!("set {id}")),
            (Ok(id), true) => ("rollback", format!("set {id}")),
            (Err(_), _) => ("rollback", "none".to_string()),
        };
        let prepared = preempted.and_then(|preempted| {
            id.and_then(|id| self.prepare_switch(user, id, &active)).map(|ready| (ready, preempted))
        });
        let switched = self
            .commit(
                &user.name,
                action,
                &target,
                prepared,
                |writer, (ready, preempted): (Ready, Option<String>)| {
                    let id = ready.set.id;
                    // Under the lock: the set is still stored and, for a
                    // rollback, still the previous one; only then does it run.
                    writer.set(id)?;
                    if rollback && writer.state()?.history.last() != Some(&id) {
                        return Err(DeployError::Conflict(format!("set {id} is no longer the previous active set")));
                    }
                    // The new state is on disk before the swap (a full disk
                    // refuses the activation here, with nothing changed), and
                    // in place after it.
                    let pending = writer.prepare_switch(id, rollback)?;
                    let (set, envelope) = (ready.set.clone(), ready.envelope.clone());
                    self.swap_in(ready, &mut active)?;
                    if let Err(e) = pending.commit() {
                        tracing::error!("set {id} runs, but the store could not record it: {e}");
                    }
                    tracing::info!(
                        owner = %set.created_by,
                        "set {id} ({}) is active; {} by {}",
                        set.config_name,
                        if rollback { "rolled back" } else { "activated" },
                        user.name
                    );
                    Ok((set, envelope, preempted))
                },
                |(set, envelope, preempted)| {
                    let mut done = format!("{} set {}", if rollback { "rolled back to" } else { "activated" }, set.id);
                    if let Some(change) = envelope {
                        done = format!("{done}; it {change}");
                    }
                    if let Some(preempted) = preempted {
                        done = format!("{done}; {preempted}");
                    }
                    done
                },
            )
            .map(|(set, _, preempted)| (set, preempted.filter(|p| !p.is_empty())));
        drop(active);
        // The old graph (or the one that did not start) is gone by now.
        super::give_back_freed_memory();
        switched
    }

    /// Hands the built graph to the control thread, which swaps it in at
    /// a cycle boundary (carrying the unchanged built-ins over), and makes
    /// it the active deployment. Activations, rollbacks and fresh-start
    /// recordings all swap through here.
    pub(super) fn swap_in(&self, ready: Ready, active: &mut Deployment) -> Result<(), DeployError> {
        self.swap_in_reporting(ready, active, None, None)
    }

    /// [`Deployer::swap_in`], and with `report` the control thread sends
    /// the old graph's report (stopped by, ran ns) before it swaps.
    pub(super) fn swap_in_reporting(
        &self,
        ready: Ready,
        active: &mut Deployment,
        report: Option<ReportRequest>,
        experiment: Option<std::sync::Arc<crate::report::ExperimentTag>>,
    ) -> Result<(), DeployError> {
        self.refuse_headless("swap a set in")?;
        // Until the swap is done a component's log line may be either
        // set's: it names the work of both owners.
        crate::logfields::set_running_owners(&[&active.set.created_by, &ready.set.created_by]);
        let (done, old_graph) = std::sync::mpsc::sync_channel(1);
        let request = SwapRequest {
            graph: ready.built.graph,
            carry: ready.carry,
            config: ready.config.clone(),
            set_id: ready.set.id,
            experiment,
            done,
            report,
        };
        if let Err(e) = self.slot.hand_over(request, &old_graph, &self.waker) {
            crate::logfields::set_running_owners(&[&active.set.created_by]);
            return Err(e);
        }
        crate::logfields::set_running_owners(&[&ready.set.created_by]);
        if let Some(robot) = self.services.get::<RunningRobot>() {
            robot.rename(&ready.config.name);
        }
        *active = Deployment {
            set: ready.set,
            config: ready.config,
            priorities: ready.built.priorities,
            sim_ptys: ready.built.sim_ptys,
        };
        Ok(())
    }

    /// While an experiment runs, what an activation of set `id` would be
    /// refused for once it ended: the set is what comes back after it, it
    /// is not stored, or it no longer validates.
    fn precheck(&self, id: u64) -> Result<(), DeployError> {
        let Some(running) = self.experiments.running() else { return Ok(()) };
        if let Some((before, _)) = self.experiments.before()
            && before.id == id
        {
            return Err(DeployError::Conflict(format!(
                "set {id} is what runs after experiment {} (by {}): cancel the experiment to have it back",
                running.id, running.submitter
            )));
        }
        let set = self.store.set(id)?;
        let mut loader = Loader::new(&self.sandbox);
        stage::validate_set(&self.store, &set, &mut loader, &self.overrides).map(|_| ())
    }

    fn prepare_switch(&self, user: &Principal, id: u64, active: &Deployment) -> Result<Ready, DeployError> {
        if active.set.id == id {
            return Err(DeployError::Conflict(format!("set {id} is active already")));
        }
        let set = self.store.set(id).map_err(|e| match e {
            StoreError::NoSet(id) => DeployError::Store(StoreError::NoSet(id)),
            other => other.into(),
        })?;
        self.build_beside(user, set, active)
    }

    /// Validates stored set `set` again and builds its graph beside the
    /// running one (`active`), with every WASM component a fresh instance
    /// and the unchanged device and socket built-ins to be carried over:
    /// what an activation swaps in. Refused when it changes a platform the
    /// user may not change, or the envelope for anyone but an admin.
    pub(super) fn build_beside(
        &self,
        user: &Principal,
        set: SetRecord,
        active: &Deployment,
    ) -> Result<Ready, DeployError> {
        self.build_beside_carrying(user, set, active, false)
    }

    /// [`Deployer::build_beside`]; with `fresh_simulators`, its simulated
    /// robots (and the serial links on them) are built afresh rather than
    /// carried over: a lab run from the world's start.
    pub(super) fn build_beside_carrying(
        &self,
        user: &Principal,
        set: SetRecord,
        active: &Deployment,
        fresh_simulators: bool,
    ) -> Result<Ready, DeployError> {
        let id = set.id;
        let mut loader = Loader::new(&self.sandbox);
        let config = stage::validate_set(&self.store, &set, &mut loader, &self.overrides)?;
        let changes = stage::platform_changes(&active.config, &config);
        if let Some(denied) = changes.iter().find(|p| !user.may_change(**p)) {
            return Err(DeployError::Forbidden(format!(
                "set {id} changes platform {}, which {} may not change",
                denied.name(),
                user.name
            )));
        }
        let envelope = stage::envelope_change(&active.config, &config);
        if let Some(change) = &envelope
            && user.role != Role::Admin
        {
            return Err(DeployError::Forbidden(format!(
                "set {id} {change}: the envelope's settings are the robot owner's, and only an admin may change them"
            )));
        }
        let pairs = if fresh_simulators {
            assemble::carry_plan_fresh_simulators(&active.config, &config)
        } else {
            assemble::carry_plan(&active.config, &config)
        };
        let mut carry = Carry::default();
        for &(old, new) in &pairs {
            if let Some(cell) = active.priorities.get(old) {
                carry.priorities.insert(new, cell.clone());
            }
            let name = &active.config.components[old].name;
            if let Some(pty) = active.sim_ptys.get(name) {
                carry.sim_ptys.insert(name.clone(), pty.clone());
            }
        }
        let building = crate::logfields::Building::of(&set.created_by);
        let built = assemble::build(&config, &mut loader, self.clock.clone(), &self.waker, &self.services, &carry)
            .map_err(DeployError::Start)?;
        drop(building);
        Ok(Ready { set, config: Arc::new(config), built, carry: pairs, envelope })
    }
}
