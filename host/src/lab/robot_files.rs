//! What a robot sends its lab server (docs/lab.md, "What travels over
//! Zenoh"): its baseline as a package (the set, its files by hash, the
//! profile the lab server places experiments by), the files the lab server
//! asks for by chunk, and an experiment's results (only what the run left
//! here: the lab server's own files are not sent back).

use std::collections::BTreeMap;
use std::path::PathBuf;

use super::materialize::{self, NamedContent};
use super::robot_link::{LinkError, Package, RobotLink, local_id, lock};
use super::transfer;
use super::wire::{
    self, Ack, Answered, Baseline, BlobRef, FileRequest, FileSource, Profile, SetManifest, WIRE_VERSION,
};
use super::{Lab, bundle};

impl RobotLink {
    pub(super) fn refresh_package(&self) -> Result<(), LinkError> {
        let baseline = {
            let book = self.lab.lock()?;
            self.lab.baseline(&book.lab)
        };
        if lock(&self.package).as_ref().is_some_and(|p| p.set == baseline) {
            return Ok(());
        }
        let package = package(&self.lab, baseline)?;
        tracing::info!("robot '{}': profile {} (baseline set {baseline})", self.options.robot, package.profile.id);
        *lock(&self.package) = Some(package);
        Ok(())
    }

    /// A chunk of a file the lab asks for.
    pub(super) fn file(&self, request: &FileRequest, re: Answered) -> Vec<u8> {
        let key = &self.options.key;
        if let FileSource::Named { path } = &request.source
            && let Some(NamedContent::StandIn(bytes)) =
                lock(&self.package).as_ref().and_then(|p| p.files.get(path)).cloned()
        {
            return transfer::chunk_of_bytes(key, re, &bytes, request);
        }
        let path = self.file_path(&request.source);
        transfer::chunk_of(key, re, path.as_deref(), request)
    }

    /// The robot's baseline, as its lab server gets it.
    pub(super) fn baseline(&self, re: Answered) -> Vec<u8> {
        let _ = self.refresh_package();
        match lock(&self.package).as_ref() {
            Some(package) => self.options.key.seal(&Baseline { re, ..package.message.clone() }, &[]),
            None => self.options.key.seal(&Ack { v: WIRE_VERSION, re, ok: false, message: "no baseline".into() }, &[]),
        }
    }

    pub(super) fn results(&self, lab_id: u64, re: Answered) -> wire::Results {
        let empty = wire::Results {
            v: WIRE_VERSION,
            re: re.clone(),
            lab_id,
            found: false,
            state: None,
            history: Vec::new(),
            reasons: Vec::new(),
            run: None,
            files: Vec::new(),
            local_id: None,
        };
        let Ok(book) = self.lab.lock() else { return empty };
        let Some(record) = local_id(&book.experiments, self.options.key.lab(), lab_id)
            .and_then(|id| book.experiments.get(&id))
            .cloned()
        else {
            return empty;
        };
        drop(book);
        let dir = self.lab.store().experiment_dir(record.id);
        if record.state.is_final() {
            // Its text leaves this machine: this robot's folders named,
            // never spelled out (the lab server hides only its own).
            for name in [bundle::REPORT, bundle::LOG] {
                if record.results.iter().any(|f| f.name == name)
                    && let Err(e) = bundle::hide_in_place(&dir.join(name), &self.hidden)
                {
                    tracing::warn!(
                        "experiment {}: its {name} could not have this robot's folders hidden: {e}",
                        record.id
                    );
                }
            }
        }
        let files = if record.state.is_final() {
            record
                .results
                .iter()
                .filter(|f| sent_to_lab(&f.name))
                .filter_map(|f| {
                    let digest = transfer::digest_file(&dir.join(&f.name)).ok()?;
                    Some(wire::FileRef { name: f.name.clone(), bytes: digest.bytes, sha256: digest.sha256 })
                })
                .take(wire::MAX_RESULT_FILES)
                .collect()
        } else {
            Vec::new()
        };
        let skip = record.history.len().saturating_sub(wire::MAX_REASONS);
        wire::Results {
            v: WIRE_VERSION,
            re,
            lab_id,
            found: true,
            state: Some(record.state),
            history: record.history.into_iter().skip(skip).collect(),
            reasons: record.reasons.into_iter().take(wire::MAX_REASONS).collect(),
            run: record.run,
            files,
            local_id: Some(record.id),
        }
    }

    /// Where the file a request names is, if it may be given.
    pub(super) fn file_path(&self, source: &FileSource) -> Option<PathBuf> {
        match source {
            FileSource::Result { lab_id, name } => {
                let book = self.lab.lock().ok()?;
                let id = local_id(&book.experiments, self.options.key.lab(), *lab_id)?;
                let record = book.experiments.get(&id)?;
                record.results.iter().any(|f| f.name == *name).then(|| self.lab.store().experiment_dir(id).join(name))
            }
            FileSource::Blob { sha256 } => {
                let package = lock(&self.package);
                package
                    .as_ref()?
                    .message
                    .set
                    .sources
                    .values()
                    .any(|b| b.sha256 == *sha256)
                    .then(|| self.lab.store().blob_path(sha256))
            }
            FileSource::Named { path } => match lock(&self.package).as_ref()?.files.get(path)? {
                NamedContent::File(file) => Some(file.clone()),
                NamedContent::Blob(sha) => Some(self.lab.store().blob_path(sha)),
                NamedContent::StandIn(_) => None,
            },
        }
    }
}

/// Whether a result file of a lab's experiment goes back to the lab: what
/// the run left here (recordings, report, log, videos, the self-test after
/// it). The robot file and its files are the lab server's own.
fn sent_to_lab(name: &str) -> bool {
    name.ends_with(".mcap")
        || [bundle::REPORT, bundle::LOG, bundle::VIDEO_NOTE, super::selftest::SELF_TEST_FILE].contains(&name)
        || crate::record::video::is_video_name(name)
}

/// The robot's baseline (set `set`) as its lab server gets it, with its
/// profile.
pub(super) fn package(lab: &Lab, set: u64) -> Result<Package, LinkError> {
    let store = lab.store();
    let record = store.set(set).map_err(|e| LinkError::Baseline(e.to_string()))?;
    let text = store.blob(&record.config_sha256).map_err(|e| LinkError::Baseline(e.to_string()))?;
    let config_text = String::from_utf8(text).map_err(|e| LinkError::Baseline(e.to_string()))?;
    let mut sources = BTreeMap::new();
    for (key, sha) in &record.sources {
        let bytes = std::fs::metadata(store.blob_path(sha)).map(|m| m.len()).unwrap_or(0);
        sources.insert(key.clone(), BlobRef { sha256: sha.clone(), bytes });
    }
    let named = materialize::named_files(store, &record).map_err(|e| LinkError::Baseline(e.to_string()))?;
    let mut files = BTreeMap::new();
    let mut contents = BTreeMap::new();
    let (mut worlds, mut translators) = (Vec::new(), Vec::new());
    for file in named {
        if wire::named_path_ok(&file.path).is_err() {
            continue;
        }
        if crate::assemble::registry::find(&file.kind).and_then(|b| b.world_param()) == Some(file.param) {
            worlds.extend(std::path::Path::new(&file.path).file_name().map(|n| n.to_string_lossy().into_owned()));
        }
        let blob = match &file.content {
            NamedContent::Blob(_) => continue,
            NamedContent::File(path) => {
                transfer::digest_file(path).map_err(|e| LinkError::Baseline(format!("{}: {e}", path.display())))?
            }
            NamedContent::StandIn(bytes) => {
                BlobRef { sha256: crate::store::sha256_hex(bytes), bytes: bytes.len() as u64 }
            }
        };
        files.insert(file.path.clone(), blob);
        contents.insert(file.path, file.content);
    }
    // Uploaded worlds and translators the robot holds count too.
    if let Ok(stored) = store.worlds() {
        worlds.extend(stored.into_keys());
    }
    // A serial link's translator: a built-in profile's name, or a WASM
    // translator's file name.
    if let Ok((_, config)) = lab.deployer.active() {
        for param in config.components.iter().flat_map(|c| c.params.iter()).filter(|p| p.name == "translator") {
            let value = param.value.trim();
            let name = std::path::Path::new(value).file_name().map(|n| n.to_string_lossy().into_owned());
            translators.extend(name.filter(|n| !n.is_empty()));
        }
    }
    let set_manifest = SetManifest {
        config_name: record.config_name.clone(),
        config_text,
        platform: record.platform.clone(),
        sources,
    };
    let canonical = serde_json::json!({
        "config": record.config_sha256,
        "sources": set_manifest.sources.iter().map(|(k, b)| (k.clone(), b.sha256.clone())).collect::<BTreeMap<_, _>>(),
        "files": files.iter().map(|(k, b)| (k.clone(), b.sha256.clone())).collect::<BTreeMap<_, _>>(),
    });
    let hash = crate::store::sha256_hex(canonical.to_string().as_bytes());
    let profile = Profile::new(hash.clone(), worlds, translators);
    // Its binding is the request's, set as each is answered.
    let re = Answered { robot: String::new(), nonce: String::new() };
    let message = Baseline { v: WIRE_VERSION, re, hash, set: set_manifest, files };
    Ok(Package { set, message, profile, files: contents })
}
