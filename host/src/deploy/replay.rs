//! Replay before activation (docs/recording.md, "Replay from the portal"):
//! a stored set's WASM components, or some of them, are fed the calls a
//! stored recording holds and their outputs compared with the recorded
//! ones, before anyone activates the set. Developers and admins only
//! ([`Permission::Record`]: a replay reads a recording). Nothing here
//! touches the running robot: the set's components are built alone, with
//! their own clock and no built-in, on the caller's (blocking) thread.

use std::time::Duration;

use super::{DeployError, Deployer, Permission, authorise, stage};
use crate::assemble::Loader;
use crate::record::control::Recordings;
use crate::record::replay::{ReplayError, ReplayLimits, ReplayReport, replay_robot};
use crate::store::users::Principal;

/// Replays at once: a replay runs the set's components as fast as the CPU
/// allows, so a few developers clicking must not take the host's cores from
/// the control loop.
pub const MAX_CONCURRENT_REPLAYS: usize = 1;

/// Largest recording file a portal replay reads (it is read whole into
/// memory): a request must not make the host allocate gigabytes.
pub const MAX_REPLAY_RECORDING_BYTES: u64 = 256 << 20;

/// Longest a portal replay may run its calls: a slow or looping component
/// must not hold the replay slot (and a core) for long.
pub const MAX_REPLAY_DURATION: Duration = Duration::from_secs(120);

/// Most components one replay request may name (a bound on the request).
pub const MAX_REPLAY_COMPONENTS: usize = 64;

impl From<ReplayError> for DeployError {
    fn from(e: ReplayError) -> DeployError {
        match e {
            ReplayError::Config(diagnostics) => DeployError::Invalid(diagnostics),
            ReplayError::Start(errors) => DeployError::Start(errors),
            ReplayError::UnknownComponent { .. } | ReplayError::NotWasm { .. } | ReplayError::NothingToReplay(_) => {
                DeployError::BadRequest(e.to_string())
            }
            ReplayError::NotRecorded { .. }
            | ReplayError::PortMismatch { .. }
            | ReplayError::NotMcap(_)
            | ReplayError::Mcap { .. }
            | ReplayError::BadMessage { .. }
            | ReplayError::TooLarge { .. }
            | ReplayError::TooLong { .. } => DeployError::Unprocessable(e.to_string()),
            ReplayError::Sandbox(_) | ReplayError::Read { .. } => DeployError::Host(e.to_string()),
        }
    }
}

impl Deployer {
    /// Replays components `only` (every WASM component when empty) of
    /// stored set `id` against recording `recording` of the host's
    /// recordings folder. One replay at a time ([`MAX_CONCURRENT_REPLAYS`]):
    /// another meanwhile is refused as busy. Blocks for the replay's
    /// duration: call it off the async runtime.
    pub fn replay_set(
        &self,
        user: &Principal,
        id: u64,
        recording: &str,
        only: &[String],
    ) -> Result<ReplayReport, DeployError> {
        authorise(user, Permission::Record)?;
        if only.len() > MAX_REPLAY_COMPONENTS {
            return Err(DeployError::BadRequest(format!(
                "{} components named; a replay takes at most {MAX_REPLAY_COMPONENTS}",
                only.len()
            )));
        }
        let recordings = self
            .services
            .get::<Recordings>()
            .ok_or_else(|| DeployError::NotFound("this host keeps no recordings (run it with the portal)".into()))?;
        let (path, _) = recordings.file(recording)?;
        let _replaying = self
            .replays
            .try_lock()
            .map_err(|_| DeployError::Busy("another replay is running; try again when it is done".into()))?;
        let set = self.store.set(id)?;
        let mut loader = Loader::confined(&self.sandbox);
        let config = stage::validate_set(&self.store, &set, &mut loader, &self.overrides)?;
        let limits =
            ReplayLimits { max_recording_bytes: MAX_REPLAY_RECORDING_BYTES, max_duration: Some(MAX_REPLAY_DURATION) };
        let report = replay_robot(&config, &mut loader, &path, only, limits)?;
        tracing::info!(
            user = %user.name,
            "replayed set {id} against {recording}: {} calls, {} outputs compared, {}",
            report.calls,
            report.compared,
            report.divergences.first().map_or_else(|| "identical".to_string(), ToString::to_string)
        );
        Ok(report)
    }
}
