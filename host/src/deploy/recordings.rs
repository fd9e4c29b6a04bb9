//! Recording from the portal (docs/recording.md): start and stop a
//! recording of the running robot, list, download and delete the host's
//! recordings. Developers and admins only ([`Permission::Record`]): a
//! recording holds every value, log line and operator's round-trip time.
//! Starting, stopping and deleting write an audit line, refused or not.

use std::path::PathBuf;
use std::sync::Arc;

use super::{DeployError, Deployer, Permission, authorise};
use crate::record::Layout;
use crate::record::control::{RecordingError, RecordingFile, RecordingInfo, Recordings, Stopped};
use crate::store::users::User;

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
#[derive(Clone, Debug, serde::Serialize)]
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

    /// Starts recording the running robot into the host's recordings folder.
    pub fn start_recording(&self, user: &User) -> Result<RecordingInfo, DeployError> {
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

    /// Stops the running recording; its files are complete (summary and
    /// footer written).
    pub fn stop_recording(&self, user: &User) -> Result<Stopped, DeployError> {
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
    pub fn list_recordings(&self, user: &User) -> Result<RecordingsView, DeployError> {
        authorise(user, Permission::Record)?;
        let recordings = self.recordings()?;
        Ok(RecordingsView { recording: recordings.current(), files: recordings.list()? })
    }

    /// The path and size of recording file `name`, for a download.
    pub fn recording_file(&self, user: &User, name: &str) -> Result<(PathBuf, u64), DeployError> {
        authorise(user, Permission::Record)?;
        Ok(self.recordings()?.file(name)?)
    }

    /// Deletes recording file `name`.
    pub fn delete_recording(&self, user: &User, name: &str) -> Result<(), DeployError> {
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
