//! The lab kit (docs/lab.md): the baseline in its preflight form, the
//! criteria and a README, for a researcher to run the lab's robot on their
//! own machine and get the verdict the preflight would give. The owner's
//! `kit` setting turns it off for everyone but admins.

use super::kit_submission::{KIT_MANIFEST, KitComponent, KitManifest};
use super::{Lab, LabError, bundle, materialize};
use crate::store::users::{Principal, Role};

/// The kit's bounds of the preflight's seeded runs (`--perturb-bounds`).
pub const KIT_BOUNDS: &str = "perturb-bounds.json";

impl Lab {
    /// The lab kit (docs/lab.md): the baseline in its preflight form (the
    /// robot file, its components, its world), the criteria and a README,
    /// for `user` to run the lab's robot on their own machine; written into
    /// a temporary folder the caller keeps until the archive is sent.
    pub fn kit(&self, user: &Principal) -> Result<(tempfile::TempDir, bundle::Contents), LabError> {
        self.audited(
            &user.name,
            "lab-kit",
            "the lab kit",
            || self.write_kit(user),
            |(_, contents)| format!("downloaded ({} files)", contents.entries.len()),
        )
    }

    fn write_kit(&self, user: &Principal) -> Result<(tempfile::TempDir, bundle::Contents), LabError> {
        let (settings, baseline) = {
            let book = self.lock()?;
            (book.lab.settings.clone(), self.baseline(&book.lab))
        };
        if !user.may_submit() {
            return Err(LabError::Forbidden(format!("{} may not download the lab kit", user.name)));
        }
        if !settings.kit && user.role != Role::Admin {
            return Err(LabError::Forbidden("the robot's owner turned the lab kit off".into()));
        }
        let set = self.store().set(baseline)?;
        let world = match &settings.preflight_world {
            Some(name) => {
                let worlds = self.store().worlds()?;
                let stored = worlds
                    .get(name)
                    .ok_or_else(|| LabError::Host(format!("the preflight world '{name}' is not stored")))?;
                Some(materialize::PreflightWorld { name: name.clone(), sha256: stored.sha256.clone() })
            }
            None => None,
        };
        let dir = tempfile::tempdir().map_err(|e| LabError::Host(format!("cannot make the kit's folder: {e}")))?;
        let comment = format!("the lab's baseline (set {baseline}) in its preflight form: the lab kit (docs/lab.md)");
        let written = materialize::write_preflight_form(
            self.store(),
            &set,
            world.as_ref(),
            settings.start_pose(),
            dir.path(),
            &comment,
        )
        .map_err(|e| LabError::Host(e.to_string()))?;
        let criteria = serde_json::to_vec_pretty(&settings.criteria).map_err(|e| LabError::Host(e.to_string()))?;
        let readme = format!(
            "The lab's robot (set {baseline}), as the lab's preflight runs it.\n\n\
             Check an experiment's components the way the lab will, for up to {} s:\n\n    \
             subsume run robot.xml --http off --speed max --duration 60 --criteria criteria.json\n\n\
             It ends with the verdict the preflight would give. Replace a component's source in\n\
             robot.xml with your own .wasm to try yours, and submit that same file:\n\n    \
             subsume lab submit --robot robot.xml --duration 60 HOST\n\n\
             sends the lab's robot with your changes (kit.json says what the kit was written from).\n\
             The envelope component's parameters are the robot's safety settings: an experiment may\n\
             not change them.\n",
            settings.max_duration_s
        );
        let mut readme = readme;
        // The bounds of the preflight's seeded runs: a researcher reruns
        // any of them from the seed its refusal names.
        let timing = settings.preflight_timing;
        let bounds = serde_json::to_vec_pretty(&timing.bounds()).map_err(|e| LabError::Host(e.to_string()))?;
        readme.push_str(&format!(
            "\nThe lab's preflight runs {} times: run 1 as above, each later one with the timing a robot\n\
             has, seeded (perturb-bounds.json: tick phase, sensor latency and noise, serial delay). A\n\
             set whose verdict changes between runs is refused, naming each run's seed. Rerun one:\n\n    \
             subsume run robot.xml --http off --speed max --duration 60 --criteria criteria.json \\\n        \
             --perturb SEED --perturb-bounds perturb-bounds.json\n",
            timing.runs
        ));
        let mut entries = vec![
            ("criteria.json".to_string(), bundle::Source::Bytes(criteria)),
            (KIT_BOUNDS.to_string(), bundle::Source::Bytes(bounds)),
            (KIT_MANIFEST.to_string(), bundle::Source::Bytes(manifest(baseline, &set.config_sha256, &written)?)),
        ];
        // The owner's task: a researcher scores her local run as the lab
        // will score hers on the robot.
        if let Some(task) = &settings.task {
            let task_json = serde_json::to_vec_pretty(task).map_err(|e| LabError::Host(e.to_string()))?;
            entries.push((crate::score::TASK_FILE.to_string(), bundle::Source::Bytes(task_json)));
            // Its scoring component, when the metric is one: the bytes the
            // task pins.
            if let Some(scorer) = task.scorer.as_ref().filter(|_| task.metric == crate::store::task::Metric::Scorer) {
                let bytes = self.store().blob(&scorer.sha256).map_err(|e| {
                    LabError::Host(format!("the task's scorer {} cannot be read: {e}", scorer.component))
                })?;
                entries.push((crate::score::SCORER_FILE.to_string(), bundle::Source::Bytes(bytes)));
            }
            readme.push_str(&format!(
                "\nThe lab scores every run against its task '{}' (task.json, and scorer.wasm when its metric is\n\
                 a scoring component). Score yours as it will (--task ends the run as the task's end\n\
                 conditions end the lab's, if it has any):\n\n    \
                 subsume run robot.xml --http off --speed max --duration 60 --task task.json --record run.mcap\n    \
                 subsume score .\n",
                task.name
            ));
        }
        entries.push(("README.txt".to_string(), bundle::Source::Bytes(readme.into_bytes())));
        for (name, _) in &written.files {
            entries.push((name.clone(), bundle::Source::File(dir.path().join(name))));
        }
        Ok((dir, bundle::Contents { folder: "lab-kit".into(), entries }))
    }
}

/// The kit's manifest (`kit.json`): the baseline it is of, its robot file
/// as written, and each WASM component's file and sha256.
fn manifest(baseline: u64, baseline_sha256: &str, written: &materialize::Written) -> Result<Vec<u8>, LabError> {
    let robot = std::fs::read_to_string(&written.robot)
        .map_err(|e| LabError::Host(format!("cannot read the kit's {}: {e}", written.robot.display())))?;
    let components = written
        .components
        .iter()
        .filter_map(|(name, _, sha)| {
            let sha256 = sha.clone()?;
            Some((name.clone(), KitComponent { file: materialize::component_file(name), sha256 }))
        })
        .collect();
    let manifest = KitManifest { baseline, baseline_sha256: baseline_sha256.to_string(), robot, components };
    serde_json::to_vec_pretty(&manifest).map_err(|e| LabError::Host(e.to_string()))
}
