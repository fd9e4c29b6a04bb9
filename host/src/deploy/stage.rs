//! Staging: an uploaded robot file, validated exactly like `subsume check`
//! with its WASM sources resolved to stored components, becomes a new set.
//! A source `NAME.wasm` is the stager's own upload `NAME`, `OWNER/NAME.wasm`
//! is `OWNER`'s ([`upload_for_source`]), and either falls back to what the
//! active set pinned under that exact text.
//! Also what validating a stored set, comparing two robots platform by
//! platform, and the wiring view need.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use super::{DeployError, Deployer, Permission, authorise};
use crate::assemble::{Loader, registry};
use crate::config::{
    BuiltinKind, ComponentConfig, ComponentSource, Diagnostic, Diagnostics, ParamOverride, Platform, ResolveError,
    Resolver, RobotConfig, RobotProblem, RobotView, limits,
};
use crate::contract::{Description, clip, is_valid_name};
use crate::store::users::{Principal, Role};
use crate::store::{
    ComponentRecord, STORE_FORMAT, SetRecord, Store, WiringComponent, WiringConnection, WiringGraph, component_key,
    unix_now,
};

/// Longest robot-file name kept (it names diagnostics).
pub const MAX_FILE_NAME_LEN: usize = 64;

/// Validations at once (the portal's editor validates as its users type):
/// each one loads and describes every component the file names, so a few
/// typists must not occupy the host's cores.
pub const MAX_CONCURRENT_VALIDATIONS: usize = 1;

/// What a robot file that validated would stage.
#[derive(Clone, Debug, serde::Serialize, schemars::JsonSchema)]
pub struct Validated {
    pub components: usize,
    pub connections: usize,
    /// The platforms it changes against the active set.
    pub changes: Vec<String>,
    pub graph: WiringGraph,
}

/// A robot file that validated, waiting to be stored.
pub(super) struct Staged {
    record: SetRecord,
    bytes: Vec<u8>,
    /// How an admin's file changes the envelope, for the audit line.
    envelope: Option<String>,
}

impl Deployer {
    /// Validates an uploaded robot file for `platform` against the stored
    /// components (and the active set's) and stages it as a new set.
    pub fn stage(
        &self,
        user: &Principal,
        platform: Platform,
        file_name: &str,
        bytes: &[u8],
    ) -> Result<SetRecord, DeployError> {
        let target = format!("{} for platform {}", clip(file_name), platform.name());
        let prepared = authorise(user, Permission::Change(platform))
            .and_then(|()| self.prepare_stage(user, platform, file_name, bytes));
        self.commit(
            &user.name,
            "upload-config",
            &target,
            prepared,
            |writer, staged: Staged| {
                let config_sha256 = writer.put_blob(&staged.bytes)?;
                Ok((writer.add_set(SetRecord { config_sha256, ..staged.record })?, staged.envelope))
            },
            |(set, envelope)| match envelope {
                Some(change) => format!("staged as set {}; it {change}", set.id),
                None => format!("staged as set {}", set.id),
            },
        )
        .map(|(set, _)| set)
    }

    /// Validates an uploaded robot file exactly as [`Deployer::stage`]
    /// would (the same permission, checks and diagnostics) and stores
    /// nothing: the portal's editor calls it as its user types. One
    /// validation at a time ([`MAX_CONCURRENT_VALIDATIONS`]); another
    /// meanwhile is refused as busy.
    pub fn validate(
        &self,
        user: &Principal,
        platform: Platform,
        file_name: &str,
        bytes: &[u8],
    ) -> Result<Validated, DeployError> {
        authorise(user, Permission::Change(platform))?;
        let _validating = self
            .validations
            .try_lock()
            .map_err(|_| DeployError::Busy("another robot file is being validated; try again in a moment".into()))?;
        let staged = self.prepare_stage(user, platform, file_name, bytes)?;
        let graph = staged.record.graph;
        Ok(Validated {
            components: graph.components.len(),
            connections: graph.connections.len(),
            changes: staged.record.changes,
            graph,
        })
    }

    fn prepare_stage(
        &self,
        user: &Principal,
        platform: Platform,
        file_name: &str,
        bytes: &[u8],
    ) -> Result<Staged, DeployError> {
        check_file_name(file_name)?;
        if bytes.len() as u64 > limits::MAX_CONFIG_BYTES {
            return Err(DeployError::BadRequest(format!(
                "{file_name} is {} bytes; at most {} are allowed",
                bytes.len(),
                limits::MAX_CONFIG_BYTES
            )));
        }
        let text = std::str::from_utf8(bytes)
            .map_err(|e| DeployError::BadRequest(format!("{file_name} is not utf-8: {e}")))?;
        // Staged against what the robot runs outside experiments: never
        // another researcher's experiment that runs now.
        let (active_set, active_config) = match self.experiments().before() {
            Some(before) => before,
            None => self.active()?,
        };
        if self.is_headless() && active_set.id == 0 {
            return Err(DeployError::Conflict(
                "the lab knows no robot yet: robot files are staged against a robot's baseline, and none has joined"
                    .into(),
            ));
        }
        let components = self.store.components()?;
        let access = self.access()?;
        // The stager's own upload (or the one of the user it names, when
        // they may see it), then what the active set pinned under that
        // source.
        let lookup = |source: &str| -> Result<String, String> {
            if let Some(record) = upload_for_source(&components, &user.name, source) {
                if !access.may_see_component(user, record) {
                    return Err(format!(
                        "component '{}' is {}'s and not shared with the lab",
                        record.key(),
                        record.uploaded_by
                    ));
                }
                return Ok(record.sha256.clone());
            }
            active_set.sources.get(source).cloned().ok_or_else(|| unknown_component(&components, &user.name, source))
        };
        let record = SetRecord {
            format: STORE_FORMAT,
            id: 0,
            created_by: user.name.clone(),
            created_at: unix_now(),
            platform: Some(platform.name().into()),
            config_name: file_name.into(),
            config_sha256: String::new(),
            base_dir: active_set.base_dir.clone(),
            sources: BTreeMap::new(),
            changes: Vec::new(),
            graph: WiringGraph::default(),
        };
        let worlds = self.store.worlds()?;
        let world_lookup = |name: &str| -> Option<String> {
            worlds.get(name).map(|w| w.sha256.clone()).or_else(|| active_set.sources.get(name).cloned())
        };
        let mut loader = Loader::confined(&self.sandbox);
        let (config, sources) =
            validate_text(&self.store, &record, text, &lookup, &world_lookup, &mut loader, &self.overrides)?;
        let changes = platform_changes(&active_config, &config);
        if let Some(denied) = changes.iter().find(|p| !user.may_change(**p)) {
            return Err(DeployError::Forbidden(format!(
                "{file_name} changes platform {}, which {} may not change",
                denied.name(),
                user.name
            )));
        }
        let envelope = envelope_change(&active_config, &config);
        if let Some(change) = &envelope
            && user.role != Role::Admin
        {
            return Err(DeployError::Forbidden(format!(
                "{file_name} {change}: the envelope's settings are the robot owner's, and only an admin may change them"
            )));
        }
        let record = SetRecord {
            sources,
            changes: changes.iter().map(|p| p.name().to_string()).collect(),
            graph: wiring_graph(&config),
            ..record
        };
        Ok(Staged { record, bytes: bytes.to_vec(), envelope })
    }
}

/// Refuses robot-file names that are not a plain file name.
pub(super) fn check_file_name(name: &str) -> Result<(), DeployError> {
    let plain = !name.is_empty()
        && name.len() <= MAX_FILE_NAME_LEN
        && !name.starts_with('.')
        && name.bytes().all(|b| b.is_ascii_alphanumeric() || b"._-".contains(&b));
    if plain {
        Ok(())
    } else {
        Err(DeployError::BadRequest(format!(
            "file name '{}' is not a plain name of at most {MAX_FILE_NAME_LEN} letters, digits, '.', '_' or '-'",
            clip(name)
        )))
    }
}

/// Validates stored set `set`; its WASM sources become blob paths.
pub(super) fn validate_set(
    store: &Store,
    set: &SetRecord,
    loader: &mut Loader<'_>,
    overrides: &[ParamOverride],
) -> Result<RobotConfig, DeployError> {
    let bytes = store.blob(&set.config_sha256)?;
    let text =
        String::from_utf8(bytes).map_err(|e| DeployError::Host(format!("stored robot file is not utf-8: {e}")))?;
    let lookup = |source: &str| {
        set.sources
            .get(source)
            .cloned()
            .ok_or_else(|| format!("unknown component '{}': not in set {}", clip(source), set.id))
    };
    let worlds = |name: &str| set.sources.get(name).cloned();
    validate_text(store, set, &text, &lookup, &worlds, loader, overrides).map(|(config, _)| config)
}

/// The stored upload a robot file staged by `stager` means by `source`:
/// `NAME.wasm` is the stager's own upload `NAME`; `OWNER/NAME.wasm` is
/// `OWNER`'s (anyone may run another user's component; only its owner can
/// replace it). Anything else names no upload.
pub fn upload_for_source<'c>(
    components: &'c BTreeMap<String, ComponentRecord>,
    stager: &str,
    source: &str,
) -> Option<&'c ComponentRecord> {
    let stem = source.strip_suffix(".wasm")?;
    let key = match stem.split_once('/') {
        None if is_valid_name(stem) => component_key(stager, stem),
        Some((owner, name)) if is_valid_name(owner) && is_valid_name(name) => component_key(owner, name),
        _ => return None,
    };
    components.get(&key)
}

/// Why `source` resolves to nothing for `stager`, naming other users'
/// uploads of that name (a plain `NAME.wasm` means the stager's own).
fn unknown_component(components: &BTreeMap<String, ComponentRecord>, stager: &str, source: &str) -> String {
    let stem = source.strip_suffix(".wasm").unwrap_or(source);
    let others: Vec<String> = if is_valid_name(stem) {
        components.values().filter(|c| c.name == stem).take(3).map(ComponentRecord::source).collect()
    } else {
        Vec::new()
    };
    if others.is_empty() {
        format!("unknown component '{}': upload it first (GET /api/v1/components lists the stored ones)", clip(source))
    } else {
        format!(
            "unknown component '{}': {stager} has uploaded no '{stem}'; to run another user's, name it as {}",
            clip(source),
            others.join(" or ")
        )
    }
}

/// Validates robot-file `text` for `set`'s folder, resolving WASM sources
/// through `lookup` (the blob's sha256, or why there is none) and uploaded
/// simulator worlds through `worlds`; returns
/// the robot (sources and pinned worlds as blob paths) and the sources and
/// worlds it used, by name.
pub(super) fn validate_text(
    store: &Store,
    set: &SetRecord,
    text: &str,
    lookup: &dyn Fn(&str) -> Result<String, String>,
    worlds: &dyn Fn(&str) -> Option<String>,
    loader: &mut Loader<'_>,
    overrides: &[ParamOverride],
) -> Result<(RobotConfig, BTreeMap<String, String>), DeployError> {
    let path = set.base_dir.join(&set.config_name);
    let mut resolver = SetResolver { store, loader, base_dir: &set.base_dir, lookup, worlds, used: BTreeMap::new() };
    let result = crate::config::parse_and_validate_for_run(&path, text, &mut resolver, overrides);
    let used = resolver.used;
    let mut config = result.map_err(|Diagnostics(list)| {
        DeployError::Invalid(Diagnostics(
            list.into_iter()
                .map(|d| Diagnostic {
                    path: if d.path == path { PathBuf::from(&set.config_name) } else { d.path },
                    ..d
                })
                .collect(),
        ))
    })?;
    for component in &mut config.components {
        if let ComponentSource::Wasm(file) = &component.source
            && let Some(sha) = used.get(&relative_source(&set.base_dir, file))
        {
            component.source = ComponentSource::Wasm(store.blob_path(sha));
        }
        let world_param = match component.source {
            ComponentSource::Builtin(kind) => registry::builtin(kind).world_param(),
            ComponentSource::Wasm(_) => None,
        };
        if let Some(world_param) = world_param {
            for param in component.params.iter_mut().filter(|p| p.name == world_param) {
                if let Some(sha) = used.get(param.value.trim()) {
                    param.value = store.blob_path(sha).to_string_lossy().into_owned();
                }
            }
        }
    }
    Ok((config, used))
}

fn relative_source(base_dir: &Path, file: &Path) -> String {
    file.strip_prefix(base_dir).unwrap_or(file).to_string_lossy().into_owned()
}

/// Resolves a set's WASM sources to stored blobs, and a simulated robot's
/// `world` that names an uploaded world to its stored blob (an uploaded
/// world wins over a file of that name beside the robot file); built-ins
/// go to the loader (confined to the robot's folder when staging uploads).
struct SetResolver<'r, 'l> {
    store: &'r Store,
    loader: &'r mut Loader<'l>,
    base_dir: &'r Path,
    lookup: &'r dyn Fn(&str) -> Result<String, String>,
    worlds: &'r dyn Fn(&str) -> Option<String>,
    used: BTreeMap<String, String>,
}

impl Resolver for SetResolver<'_, '_> {
    fn builtin_kind(&self, kind: &str) -> Result<BuiltinKind, ResolveError> {
        self.loader.builtin_kind(kind)
    }

    fn check_robot(&self, view: &RobotView<'_>) -> Vec<RobotProblem> {
        self.loader.check_robot(view)
    }

    fn describe(
        &mut self,
        source: &ComponentSource,
        params: &BTreeMap<String, String>,
        base_dir: &Path,
    ) -> Result<Description, ResolveError> {
        match source {
            ComponentSource::Builtin(kind) if registry::builtin(*kind).world_param().is_some() => {
                let world_param = registry::builtin(*kind).world_param().unwrap_or_default();
                let world = params.get(world_param).map(|w| w.trim().to_string()).unwrap_or_default();
                // Only a plain `NAME.world` can be an uploaded world (what
                // `upload_world` accepts); anything else is a file path.
                let uploaded = world.ends_with(super::WORLD_SUFFIX) && !world.contains('/');
                match uploaded.then(|| (self.worlds)(&world)).flatten() {
                    Some(sha) => {
                        // Checked as the blob it is, named by its hash inside
                        // the store's blob folder (so a confined loader accepts it).
                        let blob = self.store.blob_path(&sha);
                        let blobs = blob.parent().unwrap_or(base_dir).to_path_buf();
                        let mut pinned = params.clone();
                        pinned.insert(world_param.into(), sha.clone());
                        let description = self.loader.describe(source, &pinned, &blobs)?;
                        self.used.insert(world, sha);
                        Ok(description)
                    }
                    None => self.loader.describe(source, params, base_dir),
                }
            }
            ComponentSource::Builtin(_) => self.loader.describe(source, params, base_dir),
            ComponentSource::Wasm(file) => {
                let key = relative_source(self.base_dir, file);
                let sha = (self.lookup)(&key).map_err(ResolveError::Source)?;
                let description = self
                    .loader
                    .load_wasm(&self.store.blob_path(&sha))
                    .map_err(|e| ResolveError::Source(e.to_string()))?
                    .description
                    .clone();
                self.used.insert(key, sha);
                Ok(description)
            }
        }
    }
}

/// The platforms whose components or connections differ between two robots.
pub fn platform_changes(old: &RobotConfig, new: &RobotConfig) -> Vec<Platform> {
    let fingerprint = |robot: &RobotConfig, platform: Platform| -> Vec<String> {
        let mut lines: Vec<String> =
            robot.components.iter().filter(|c| c.platform == platform).map(crate::assemble::instance_key).collect();
        let name = |i: usize| robot.components.get(i).map_or("?", |c| c.name.as_str());
        lines.extend(robot.connections.iter().filter(|c| c.platform == platform).map(|c| {
            format!(
                "{}.{} -> {}.{} {:?}",
                name(c.from.component),
                c.from.port,
                name(c.to.component),
                c.to.port,
                c.policy
            )
        }));
        lines.sort();
        lines
    };
    [Platform::Control, Platform::Network]
        .into_iter()
        .filter(|p| fingerprint(old, *p) != fingerprint(new, *p))
        .collect()
}

/// Components (with their ports) and connections, for the wiring view.
pub fn wiring_graph(config: &RobotConfig) -> WiringGraph {
    let names = |ports: &[crate::contract::PortSpec]| ports.iter().map(|p| p.name.clone()).collect::<Vec<_>>();
    let components = config
        .components
        .iter()
        .map(|c: &ComponentConfig| WiringComponent {
            name: c.name.clone(),
            platform: c.platform.name().into(),
            source: match &c.source {
                ComponentSource::Builtin(kind) => format!("builtin:{kind}"),
                ComponentSource::Wasm(_) => format!("wasm:{}", c.description.name),
            },
            priority: c.priority,
            rate_hz: c.rate_hz,
            inputs: names(&c.description.inputs),
            outputs: names(&c.description.outputs),
        })
        .collect();
    let connections = config
        .connections
        .iter()
        .map(|c| WiringConnection {
            from: config.output_name(c.from),
            to: config.input_name(c.to),
            platform: c.platform.name().into(),
        })
        .collect();
    WiringGraph { robot: config.name.clone(), components, connections }
}

/// The first difference between the envelopes of two robots (their
/// parameters, rate and every connection into or out of them but those
/// from their `interventions` output), in words naming the setting; None
/// when they are the same. Envelope settings are the owner's: only an
/// admin may change them.
pub fn envelope_change(old: &RobotConfig, new: &RobotConfig) -> Option<String> {
    fn envelopes(robot: &RobotConfig) -> BTreeMap<String, (usize, &ComponentConfig)> {
        robot
            .components
            .iter()
            .enumerate()
            .filter(|(_, c)| matches!(c.source, ComponentSource::Builtin(k) if registry::builtin(k).guards_motors()))
            .map(|(i, c)| (c.name.clone(), (i, c)))
            .collect()
    }
    let wiring = |robot: &RobotConfig, index: usize| -> Vec<String> {
        let port = |component: usize, port: u32, output: bool| -> String {
            let Some(c) = robot.components.get(component) else { return "?".into() };
            let ports = if output { &c.description.outputs } else { &c.description.inputs };
            let source = match &c.source {
                ComponentSource::Builtin(kind) => format!("builtin:{kind}"),
                ComponentSource::Wasm(_) => format!("wasm:{}", c.description.name),
            };
            format!("{} ({source}).{}", c.name, ports.get(port as usize).map_or("?", |p| p.name.as_str()))
        };
        // Components may listen to what the envelope did: wiring its
        // `interventions` output changes none of the owner's settings.
        let tells_interventions = |c: &crate::config::ConnectionConfig| {
            c.from.component == index
                && robot
                    .components
                    .get(index)
                    .and_then(|envelope| envelope.description.outputs.get(c.from.port as usize))
                    .is_some_and(|port| port.name == crate::envelope::INTERVENTIONS_PORT)
        };
        let mut lines: Vec<String> = robot
            .connections
            .iter()
            .filter(|c| (c.from.component == index || c.to.component == index) && !tells_interventions(c))
            .map(|c| {
                format!("{} -> {}", port(c.from.component, c.from.port, true), port(c.to.component, c.to.port, false))
            })
            .collect();
        lines.sort();
        lines
    };
    let (before, after) = (envelopes(old), envelopes(new));
    for (name, (i, was)) in &before {
        let Some((j, now)) = after.get(name) else {
            return Some(format!("removes envelope '{name}'"));
        };
        for (p, q) in was.params.iter().zip(&now.params) {
            if p.name != q.name || p.value.trim() != q.value.trim() {
                return Some(format!(
                    "changes parameter '{}' of envelope '{name}' from '{}' to '{}'",
                    q.name,
                    clip(p.value.trim()),
                    clip(q.value.trim())
                ));
            }
        }
        if was.rate_hz != now.rate_hz {
            return Some(format!("changes the rate of envelope '{name}' from {} to {}", was.rate_hz, now.rate_hz));
        }
        let (w0, w1) = (wiring(old, *i), wiring(new, *j));
        if let Some(gone) = w0.iter().find(|l| !w1.contains(l)) {
            return Some(format!("changes the wiring of envelope '{name}': removes {gone}"));
        }
        if let Some(added) = w1.iter().find(|l| !w0.contains(l)) {
            return Some(format!("changes the wiring of envelope '{name}': adds {added}"));
        }
    }
    after.keys().find(|name| !before.contains_key(*name)).map(|name| format!("adds envelope '{name}'"))
}
