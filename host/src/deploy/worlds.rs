//! Uploading a simulator world file: parsed (every statement checked, each
//! error located in the world file) before anything is stored. A robot file
//! staged later names it in its simulator's `world` parameter, and the set
//! pins the world's bytes (by sha256), so a later upload of the same name
//! never changes a staged or active set.

use std::path::Path;

use super::{DeployError, Deployer, Permission, Platform, authorise};
use crate::contract::clip;
use crate::sim::world::{self, MAX_WORLD_BYTES};
use crate::store::users::Principal;
use crate::store::{WorldRecord, unix_now};

/// How an uploaded world's name must end (robot files name it so).
pub const WORLD_SUFFIX: &str = ".world";

impl Deployer {
    /// Checks and stores `bytes` as world file `name`. Worlds belong to the
    /// simulated robot, which is on the control platform.
    pub fn upload_world(&self, user: &Principal, name: &str, bytes: &[u8]) -> Result<WorldRecord, DeployError> {
        let target = format!("world '{}'", clip(name));
        let prepared =
            authorise(user, Permission::Change(Platform::Control)).and_then(|()| prepare_world(user, name, bytes));
        self.commit(
            &user.name,
            "upload-world",
            &target,
            prepared,
            |writer, record: WorldRecord| {
                let record = WorldRecord { sha256: writer.put_blob(bytes)?, ..record };
                writer.put_world(record.clone())?;
                tracing::info!("world '{}' uploaded by {} ({} bytes)", record.name, record.uploaded_by, record.size);
                Ok(record)
            },
            |record| format!("sha256 {}", record.sha256),
        )
    }

    /// The uploaded worlds, by name.
    pub fn worlds(&self) -> Result<Vec<WorldRecord>, DeployError> {
        Ok(self.store.worlds()?.into_values().collect())
    }
}

fn prepare_world(user: &Principal, name: &str, bytes: &[u8]) -> Result<WorldRecord, DeployError> {
    super::stage::check_file_name(name)?;
    if !name.ends_with(WORLD_SUFFIX) || name.len() == WORLD_SUFFIX.len() {
        return Err(DeployError::BadRequest(format!(
            "world file name '{}' must end with '{WORLD_SUFFIX}'",
            clip(name)
        )));
    }
    if bytes.len() as u64 > MAX_WORLD_BYTES {
        return Err(DeployError::BadRequest(format!(
            "{name} is {} bytes; at most {MAX_WORLD_BYTES} are allowed",
            bytes.len()
        )));
    }
    let text = std::str::from_utf8(bytes).map_err(|e| DeployError::BadRequest(format!("{name} is not utf-8: {e}")))?;
    world::parse(Path::new(name), text).map_err(DeployError::Invalid)?;
    Ok(WorldRecord {
        name: name.to_string(),
        sha256: String::new(),
        size: bytes.len() as u64,
        uploaded_by: user.name.clone(),
        uploaded_at: unix_now(),
    })
}
