//! `subsume dev`: the researcher's inner loop. A thread polls the robot
//! file and every component file the running set was imported from; when
//! one changes (and has stayed unchanged for one more poll, so a build that
//! is still writing is not read half-way), the file is imported again (read,
//! validated, compiled: on this thread, never on the control loop) and the
//! new set activated like any other, so the control thread swaps it in at a
//! cycle boundary and the simulated robot, the serial link and the network
//! platform keep running. A file that does not validate or a component that
//! does not start is reported in place (each problem as `path:line:column`)
//! and the running set stays as it was; the next change tries again.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Weak};
use std::time::{Duration, Instant, SystemTime};

use super::{DeployError, Deployer, Import, import};
use crate::store::users::Principal;

/// The user `subsume dev`'s imports and activations are made as (in the
/// audit log and the sets' `created_by`); the person at the terminal
/// owns the host, so it acts as an admin.
pub const DEV_USER: &str = "dev";
/// Shortest poll interval `--poll` accepts: a tighter loop only burns CPU
/// beside the control loop.
pub const MIN_POLL: Duration = Duration::from_millis(20);
/// Longest poll interval: a change must show within seconds.
pub const MAX_POLL: Duration = Duration::from_secs(10);

/// What a watched file looked like: (modified, length), `None` when missing.
type Seen = Option<(SystemTime, u64)>;

fn look(path: &Path) -> Seen {
    std::fs::metadata(path).ok().map(|m| (m.modified().unwrap_or(SystemTime::UNIX_EPOCH), m.len()))
}

/// The files to watch: the robot file and each WASM component file it
/// names (`source` attributes that are not `builtin:`), relative to its
/// folder. A file that does not parse yields the robot file alone (its
/// next change is read again).
fn watched(robot: &Path) -> Vec<PathBuf> {
    use quick_xml::events::Event;
    let mut files = vec![robot.to_path_buf()];
    let Ok(text) = std::fs::read_to_string(robot) else { return files };
    let folder = robot.parent().unwrap_or(Path::new("."));
    let mut reader = quick_xml::Reader::from_str(&text);
    loop {
        match reader.read_event() {
            Ok(Event::Eof) | Err(_) => break,
            Ok(Event::Start(e) | Event::Empty(e)) if e.name().as_ref() == "component" => {
                let source =
                    e.attributes().flatten().find(|a| a.key.as_ref() == "source").map(|a| a.value.into_owned());
                if let Some(source) = source.filter(|s| !s.starts_with("builtin:")) {
                    let file = folder.join(&source);
                    if !files.contains(&file) {
                        files.push(file);
                    }
                }
            }
            Ok(_) => {}
        }
    }
    files
}

/// Starts the watcher of `robot` for `deployer`, polling every `poll`; it
/// ends with the deployer (the run).
pub fn watch(deployer: &Arc<Deployer>, robot: PathBuf, poll: Duration) -> std::io::Result<()> {
    let deployer = Arc::downgrade(deployer);
    std::thread::Builder::new().name("dev-watch".into()).spawn(move || watch_loop(&deployer, &robot, poll))?;
    Ok(())
}

fn watch_loop(deployer: &Weak<Deployer>, robot: &Path, poll: Duration) {
    let mut files = watched(robot);
    let mut seen: BTreeMap<PathBuf, Seen> = files.iter().map(|f| (f.clone(), look(f))).collect();
    tracing::info!(
        "dev: watching {} file(s) every {} ms: {}",
        files.len(),
        poll.as_millis(),
        files.iter().map(|f| f.display().to_string()).collect::<Vec<_>>().join(", ")
    );
    loop {
        std::thread::sleep(poll);
        let now: BTreeMap<PathBuf, Seen> = files.iter().map(|f| (f.clone(), look(f))).collect();
        if now == seen {
            continue;
        }
        // Settle: the same again one poll later, so a file being written
        // is read whole.
        std::thread::sleep(poll);
        let settled: BTreeMap<PathBuf, Seen> = files.iter().map(|f| (f.clone(), look(f))).collect();
        if settled != now {
            continue;
        }
        let changed: Vec<String> =
            settled.iter().filter(|(f, s)| seen.get(*f) != Some(*s)).map(|(f, _)| f.display().to_string()).collect();
        seen = settled;
        let Some(deployer) = deployer.upgrade() else { return };
        let edited = seen.values().flatten().map(|(modified, _)| *modified).max();
        tracing::info!("dev: changed: {}; validating and compiling off the control loop...", changed.join(", "));
        let started = Instant::now();
        match deployer.reimport(robot) {
            Ok(id) => {
                let since_edit = edited.and_then(|t| SystemTime::now().duration_since(t).ok());
                tracing::info!(
                    "dev: set {id} is running ({:.2} s after the change was seen{})",
                    started.elapsed().as_secs_f64(),
                    since_edit.map(|d| format!(", {:.2} s after the edit", d.as_secs_f64())).unwrap_or_default()
                );
            }
            Err(DeployError::Invalid(diagnostics)) => {
                for d in &diagnostics.0 {
                    tracing::error!("dev: {d}");
                }
                tracing::error!("dev: {} problem(s); the running set is unchanged", diagnostics.0.len());
            }
            Err(e) => tracing::error!("dev: {e}; the running set is unchanged"),
        }
        let now_named = watched(robot);
        if now_named != files {
            // The file now names other components: watch those from here
            // on. Files watched before keep what they were when imported, so
            // an edit made during the import is still seen as a change.
            seen = now_named.iter().map(|f| (f.clone(), seen.get(f).copied().unwrap_or_else(|| look(f)))).collect();
            files = now_named;
        }
    }
}

impl Deployer {
    /// Imports the robot file at `path` (and the component files it names)
    /// again and activates it: `subsume dev`'s use case. Returns the set
    /// that runs now; on any error the running set is untouched.
    pub fn reimport(&self, path: &Path) -> Result<u64, DeployError> {
        let text = crate::config::read_config(path).map_err(DeployError::Invalid)?;
        let set = {
            let _compiling =
                self.compiles.lock().map_err(|_| DeployError::Host("the compile lock is unusable".into()))?;
            import(&self.store, &self.sandbox, path, &text, &self.overrides, Import::Dev)?
        };
        let user = Principal::host(DEV_USER);
        self.activate(&user, set.id).map(|record| record.id)
    }
}
