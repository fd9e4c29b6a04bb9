//! Recording from the portal (docs/recording.md): start and stop a
//! recording of the running robot, list, download and delete the host's
//! recordings. Developers and admins only ([`Permission::Record`]): a
//! recording holds every value, log line and operator's round-trip time.
//! Starting, stopping and deleting write an audit line, refused or not.
//!
//! A recording "from a fresh start" re-activates the active set: its graph
//! is built beside the running one exactly as for an activation (WASM
//! components fresh, unchanged device and socket built-ins carried over, the
//! envelope rebuilt from the same settings) and swapped in at a cycle
//! boundary, and the recording is attached in that same boundary, so the
//! new graph's first call is its first recorded call and a replay of it is
//! exact from there. It is audited as an activation (`activate`, done
//! before the swap is reported) and as a recording start.

use std::path::PathBuf;
use std::sync::Arc;

use super::activate::Ready;
use super::{DeployError, Deployer, Permission, authorise};
use crate::record::Layout;
use crate::record::control::{RecordingError, RecordingFile, RecordingInfo, Recordings, Stopped};
use crate::store::Outcome;
use crate::store::users::Principal;

impl From<RecordingError> for DeployError {
    fn from(e: RecordingError) -> DeployError {
        match e {
            RecordingError::Running(_) | RecordingError::NotRunning | RecordingError::CommandLine => {
                DeployError::Conflict(e.to_string())
            }
            RecordingError::InUse(_) | RecordingError::Full(_) => DeployError::Conflict(e.to_string()),
            RecordingError::BadName(_) => DeployError::BadRequest(e.to_string()),
            RecordingError::NotFound(_) => DeployError::NotFound(e.to_string()),
            RecordingError::Io { .. } | RecordingError::Poisoned | RecordingError::Record(_) => {
                DeployError::Host(e.to_string())
            }
        }
    }
}

/// The recordings folder as the portal shows it.
#[derive(Clone, Debug, serde::Serialize, schemars::JsonSchema)]
pub struct RecordingsView {
    /// The running recording, if any.
    pub recording: Option<RecordingInfo>,
    pub files: Vec<RecordingFile>,
}

impl Deployer {
    fn recordings(&self) -> Result<Arc<Recordings>, DeployError> {
        self.services
            .get::<Recordings>()
            .ok_or_else(|| DeployError::NotFound("this host keeps no recordings (run it with the portal)".into()))
    }

    /// Starts recording the running robot into the host's recordings
    /// folder; `fresh_start`: from a re-activation of the active set (see
    /// the module's docs).
    pub fn start_recording(&self, user: &Principal, fresh_start: bool) -> Result<RecordingInfo, DeployError> {
        if fresh_start {
            return self.start_recording_fresh(user);
        }
        let prepared = authorise(user, Permission::Record).and_then(|()| {
            let recordings = self.recordings()?;
            let (_, config) = self.active()?;
            Ok((recordings, Layout::of(&config)))
        });
        self.commit(
            &user.name,
            "start-recording",
            "recordings",
            prepared,
            |_, (recordings, layout)| Ok(recordings.start(&user.name, layout)?),
            |info| format!("recording to {}", info.name),
        )
    }

    fn start_recording_fresh(&self, user: &Principal) -> Result<RecordingInfo, DeployError> {
        let admitted = self.experiments.admit(user, "start a recording from a fresh start");
        // Held through the whole re-activation, as an activation holds it.
        let mut active = self.lock_active()?;
        let prepared = authorise(user, Permission::Record).and(admitted).and_then(|_| {
            let recordings = self.recordings()?;
            // Refused before anything is built, with a recording's reasons.
            recordings.check_start()?;
            let ready: Ready = self.build_beside(user, active.set.clone(), &active)?;
            Ok((recordings, ready))
        });
        self.commit(
            &user.name,
            "start-recording",
            "recordings",
            prepared,
            |writer, (recordings, ready)| {
                let id = ready.set.id;
                let info = recordings.start_after_swap(&user.name, Layout::of(&ready.config), self.slot.swaps())?;
                if let Err(e) = self.swap_in(ready, &mut active) {
                    if let Err(abandoned) = recordings.abandon() {
                        tracing::error!("the fresh-start recording {} was not removed: {abandoned}", info.name);
                    }
                    writer.record(&user.name, "activate", &format!("set {id}"), Outcome::Failed(&e.to_string()));
                    return Err(e);
                }
                let detail = format!("re-activated set {id} for recording {} from a fresh start", info.name);
                writer.record(&user.name, "activate", &format!("set {id}"), Outcome::Ok(&detail));
                tracing::info!("set {id} re-activated by {}: recording {} from a fresh start", user.name, info.name);
                Ok((info, id))
            },
            |(info, id)| format!("recording to {} from a fresh start (set {id} re-activated)", info.name),
        )
        .map(|(info, _)| info)
    }

    /// Stops the running recording; its files are complete (summary and
    /// footer written).
    pub fn stop_recording(&self, user: &Principal) -> Result<Stopped, DeployError> {
        let prepared = authorise(user, Permission::Record).and_then(|()| self.recordings());
        self.commit(
            &user.name,
            "stop-recording",
            "recordings",
            prepared,
            |_, recordings| Ok(recordings.stop()?),
            |s| {
                format!(
                    "{} (started by {}): {} messages, {} bytes in {}",
                    s.name,
                    s.by,
                    s.messages,
                    s.bytes,
                    s.files.join(", ")
                )
            },
        )
    }

    /// The running recording and the stored files.
    pub fn list_recordings(&self, user: &Principal) -> Result<RecordingsView, DeployError> {
        authorise(user, Permission::Record)?;
        let recordings = self.recordings()?;
        Ok(RecordingsView { recording: recordings.current(), files: recordings.list()? })
    }

    /// The path and size of recording file `name`, for a download.
    pub fn recording_file(&self, user: &Principal, name: &str) -> Result<(PathBuf, u64), DeployError> {
        authorise(user, Permission::Record)?;
        Ok(self.recordings()?.file(name)?)
    }

    /// Deletes recording file `name`.
    pub fn delete_recording(&self, user: &Principal, name: &str) -> Result<(), DeployError> {
        let target = crate::contract::clip(name);
        let prepared = authorise(user, Permission::Record).and_then(|()| self.recordings());
        self.commit(
            &user.name,
            "delete-recording",
            &target,
            prepared,
            |_, recordings| Ok(recordings.delete(name)?),
            |_| "deleted".into(),
        )
    }
}
