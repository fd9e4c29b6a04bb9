//! Uploading a component: checked (preamble, then compiled and linked
//! against the WIT worlds, then described) before anything is stored, off
//! the control loop and one compile at a time. Each upload belongs to its
//! uploader: user U's `avoid` is stored as `U/avoid` and replaces only U's
//! earlier `avoid`, never another user's (`store::records::component_key`).

use super::{DeployError, Deployer, Permission, Platform, authorise};
use crate::contract::{DescriptionDoc, clip, is_valid_name};
use crate::sandbox::{MAX_COMPONENT_BYTES, preamble};
use crate::store::StoreError;
use crate::store::access::Visibility;
use crate::store::users::{Principal, Role};
use crate::store::{ComponentRecord, MAX_COMPONENTS_PER_USER, World, component_key, unix_now};

/// Largest component upload: Python and JavaScript components are ~20 MB.
pub const MAX_UPLOAD_BYTES: usize = MAX_COMPONENT_BYTES as usize;
/// Components compiled at once: compiling is CPU-bound and the machine has
/// few cores to share with the control loop.
pub const MAX_CONCURRENT_COMPILES: usize = 1;

impl Deployer {
    /// Checks, compiles and stores `bytes` as `user`'s component `name` for
    /// `platform`.
    pub fn upload_component(
        &self,
        user: &Principal,
        platform: Platform,
        name: &str,
        bytes: &[u8],
    ) -> Result<ComponentRecord, DeployError> {
        let target = format!("component '{}' for platform {}", component_key(&user.name, &clip(name)), platform.name());
        let prepared = authorise(user, Permission::Change(platform))
            .and_then(|()| self.prepare_upload(user, platform, name, bytes));
        // The compile's working memory is freed by now.
        super::give_back_freed_memory();
        self.commit(
            &user.name,
            "upload-component",
            &target,
            prepared,
            |writer, record: ComponentRecord| {
                let stored = writer.put_blob(bytes)?;
                let record = ComponentRecord { sha256: stored, ..record };
                writer.put_component(record.clone())?;
                tracing::info!(
                    owner = %record.uploaded_by,
                    "component '{}' uploaded by {} ({} bytes)",
                    record.key(),
                    record.uploaded_by,
                    record.size
                );
                Ok(record)
            },
            |record| format!("sha256 {}", record.sha256),
        )
    }

    fn prepare_upload(
        &self,
        user: &Principal,
        platform: Platform,
        name: &str,
        bytes: &[u8],
    ) -> Result<ComponentRecord, DeployError> {
        if !is_valid_name(name) {
            return Err(DeployError::BadRequest(format!(
                "component name '{}' is not [a-z][a-z0-9_-]* of at most 64 characters",
                clip(name)
            )));
        }
        if bytes.is_empty() {
            return Err(DeployError::BadRequest("the upload is empty: send the .wasm file as the body".into()));
        }
        if bytes.len() > MAX_UPLOAD_BYTES {
            return Err(DeployError::BadRequest(format!(
                "the upload is {} bytes; at most {MAX_UPLOAD_BYTES} are allowed",
                bytes.len()
            )));
        }
        preamble::check_component_preamble(bytes).map_err(|why| DeployError::NotAComponent(why.to_string()))?;
        // The user's room, before the compile (the store checks it again
        // under its lock).
        let stored = self.store.components()?;
        let owned = stored.values().filter(|c| c.uploaded_by == user.name).count();
        if !stored.contains_key(&component_key(&user.name, name)) && owned >= MAX_COMPONENTS_PER_USER {
            return Err(DeployError::Conflict(format!(
                "{} has {MAX_COMPONENTS_PER_USER} components stored already; upload one of their names again to replace it",
                user.name
            )));
        }
        let _compiling = self.compiles.lock().map_err(|_| DeployError::Host("the compile lock is unusable".into()))?;
        let (world, description) = match self.sandbox.load(bytes) {
            Ok(artifact) => (World::Component, Some(DescriptionDoc::new(&artifact.description, &artifact.sha256))),
            Err(as_component) => match self.sandbox.load_translator(bytes) {
                Ok(_) => (World::Translator, None),
                Err(as_translator) => match crate::sandbox::check_scorer(bytes) {
                    // A task's scoring component: its metric names it.
                    Ok(()) => (World::Scorer, None),
                    Err(_) => {
                        return Err(DeployError::WrongWorld(format!(
                            "'{name}' fits neither world subsume:robot/component ({as_component}) \
                             nor subsume:robot/translator ({as_translator})"
                        )));
                    }
                },
            },
        };
        Ok(ComponentRecord {
            name: name.to_string(),
            sha256: String::new(),
            size: bytes.len() as u64,
            world,
            platform: platform.name().into(),
            uploaded_by: user.name.clone(),
            uploaded_at: unix_now(),
            description,
            // A new version of an upload keeps its owner's choice.
            visibility: stored.get(&component_key(&user.name, name)).map(|c| c.visibility).unwrap_or_default(),
        })
    }
}

impl Deployer {
    /// Shares `owner`'s upload `name` with the lab, or makes it private
    /// again (its owner, or an admin): who else may see and run it
    /// (`store::access`).
    pub fn set_component_visibility(
        &self,
        user: &Principal,
        owner: &str,
        name: &str,
        visibility: Visibility,
    ) -> Result<ComponentRecord, DeployError> {
        let key = component_key(&clip(owner), &clip(name));
        let target = format!("component '{key}'");
        let prepared = if user.name == owner || user.role == Role::Admin {
            Ok(())
        } else {
            // Someone else's upload answers as a missing one.
            Err(DeployError::NotFound(format!("no component '{key}' in the store")))
        };
        self.commit(
            &user.name,
            "component-visibility",
            &target,
            prepared,
            |writer, ()| {
                let record = self
                    .store
                    .component(owner, name)?
                    .ok_or_else(|| DeployError::NotFound(format!("no component '{key}' in the store")))?;
                let record = ComponentRecord { visibility, ..record };
                writer.put_component(record.clone())?;
                Ok(record)
            },
            |record| format!("visibility {}", record.visibility.name()),
        )
    }
}

impl Deployer {
    /// Forgets set `id` that `user` staged (an admin: anyone's) and that
    /// nothing needs: what a refused submission or activation left behind.
    /// Someone else's set answers as a missing one.
    pub fn forget_set(&self, user: &Principal, id: u64) -> Result<(), DeployError> {
        let prepared = match self.store.set(id) {
            Ok(set) if set.created_by == user.name || user.role == Role::Admin => Ok(()),
            Ok(_) | Err(StoreError::NoSet(_)) => Err(DeployError::Store(StoreError::NoSet(id))),
            Err(e) => Err(e.into()),
        };
        self.commit(
            &user.name,
            "forget-set",
            &format!("set {id}"),
            prepared,
            |writer, ()| {
                writer.forget_set(id).map_err(|e| match e {
                    StoreError::Refused(why) => DeployError::Conflict(why),
                    other => other.into(),
                })
            },
            |()| "forgotten".to_string(),
        )
    }
}
