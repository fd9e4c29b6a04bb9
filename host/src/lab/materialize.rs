//! A stored set written out as a folder that `subsume run` and `subsume
//! replay` read on their own: `robot.xml` in its preflight form,
//! `components/NAME.wasm` (each WASM component's stored bytes), `files/`
//! (the files built-ins name, the preflight's world among them).
//!
//! The preflight form is the set with every built-in asked how it takes
//! part in a preflight (`Builtin::preflight`): a serial link to a real
//! device gets a simulated controller of the same protocol, simulated
//! robots run in the owner's preflight world, the network platform listens
//! on a port of the system's choosing, Zenoh sessions talk to nobody;
//! everything else stays as the set has it. The preflight runs this
//! folder; the lab kit and the results bundle carry it (the operators file
//! and Zenoh's config file, which hold secrets, are never written).
//!
//! Invariants: every path written is made here (component names and
//! host-made file names), never taken from the robot file; every byte
//! written comes from the store (blobs by sha256) or from the set's own
//! folder, bounded by [`MAX_NAMED_FILE_BYTES`].

use std::collections::BTreeMap;
use std::io::Read;
use std::path::{Path, PathBuf};

use thiserror::Error;

use crate::assemble::registry;
use crate::builtin::{Builtin, PreflightContext, check_values};
use crate::config::SourceMap;
use crate::config::raw::{self, RawComponent, RawParam, Spanned};
use crate::store::experiments::Pose;
use crate::store::{SetRecord, Store, StoreError};

/// Largest file a built-in names that is copied (a world, a translator):
/// a robot file cannot make the lab copy a disk's worth.
pub const MAX_NAMED_FILE_BYTES: u64 = 64 << 20;

/// The robot file's name in a written folder.
pub const ROBOT_FILE: &str = "robot.xml";

/// Why a set could not be written out.
#[derive(Debug, Error)]
pub enum MaterializeError {
    #[error(transparent)]
    Store(#[from] StoreError),
    /// The set cannot take part in a preflight (a built-in said why).
    #[error("{0}")]
    NotSimulable(String),
    #[error("set {set}: {reason}")]
    Damaged { set: u64, reason: String },
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
}

/// The world the preflight's simulated robots use.
#[derive(Clone, Debug)]
pub struct PreflightWorld {
    /// Its name (an uploaded world's), for the comment.
    pub name: String,
    /// The world file's stored bytes.
    pub sha256: String,
}

/// A written folder.
#[derive(Clone, Debug)]
pub struct Written {
    /// `DIR/robot.xml`.
    pub robot: PathBuf,
    /// Every file written, relative to the folder, with its size.
    pub files: Vec<(String, u64)>,
    /// Each component's name, source as the stored robot file writes it,
    /// and the sha256 of the WASM bytes it ran (`None`: a built-in).
    pub components: Vec<(String, String, Option<String>)>,
}

fn io(path: &Path) -> impl Fn(std::io::Error) -> MaterializeError + '_ {
    move |source| MaterializeError::Io { path: path.to_path_buf(), source }
}

/// The world file `bytes` with its `start` line set to `pose` (the lab's
/// reset-by-driving start pose, docs/lab.md): the preflight's simulated
/// robot starts where the robot will. Other lines are kept; a file that is
/// not text is kept as it is (its check says why).
pub fn world_with_start(bytes: &[u8], pose: Pose) -> Vec<u8> {
    let Ok(text) = std::str::from_utf8(bytes) else { return bytes.to_vec() };
    let start = format!("start {} {} {}", pose.x, pose.y, pose.heading);
    let mut found = false;
    let mut lines: Vec<String> = text
        .lines()
        .map(|line| {
            if line.split_whitespace().next() == Some("start") {
                found = true;
                format!("{start} # the lab's reset pose")
            } else {
                line.to_string()
            }
        })
        .collect();
    if !found {
        lines.push(start);
    }
    let mut out = lines.join("\n");
    out.push('\n');
    out.into_bytes()
}

/// Writes set `set` into `dir` (which must exist) in its preflight form,
/// its simulated robots in `world` when given, starting at `start` when
/// given; `comment` heads the robot file.
pub fn write_preflight_form(
    store: &Store,
    set: &SetRecord,
    world: Option<&PreflightWorld>,
    start: Option<Pose>,
    dir: &Path,
    comment: &str,
) -> Result<Written, MaterializeError> {
    let started = |bytes: Vec<u8>| match start {
        Some(pose) => world_with_start(&bytes, pose),
        None => bytes,
    };
    let damaged = |reason: String| MaterializeError::Damaged { set: set.id, reason };
    let text = String::from_utf8(store.blob(&set.config_sha256)?)
        .map_err(|e| damaged(format!("the robot file is not utf-8: {e}")))?;
    let name = PathBuf::from(&set.config_name);
    let map = SourceMap::new(&name, &text);
    let mut errors = Vec::new();
    let mut robot = raw::parse(&map, &text, &mut errors);
    if !errors.is_empty() || !robot.complete {
        let first = errors.first().map_or_else(|| "incomplete".to_string(), ToString::to_string);
        return Err(damaged(format!("the stored robot file does not read: {first}")));
    }
    let mut out = Folder { dir, files: Vec::new() };
    let world_file = match world {
        Some(world) => {
            let bytes = started(store.blob(&world.sha256)?);
            Some(out.write("files/preflight.world", &bytes)?)
        }
        None => None,
    };
    // The simulator's source text, as the registry names its kind.
    let sim_source = registry::kind_of(&crate::sim::builtin::SimBuiltin)
        .map(|kind| format!("builtin:{kind}"))
        .ok_or_else(|| damaged("the simulator is not a registered built-in".into()))?;
    let mut components = Vec::new();
    for platform in &mut robot.platforms {
        let mut added = Vec::new();
        for component in &mut platform.components {
            let name = component.name.value.clone();
            let source = component.source.value.clone();
            let Some(kind) = source.strip_prefix("builtin:") else {
                let sha = set.sources.get(&source).ok_or_else(|| damaged(format!("no stored bytes for '{source}'")))?;
                let bytes = store.blob(sha)?;
                let file = out.write(&component_file(&name), &bytes)?;
                component.source.value = file;
                components.push((name, source, Some(sha.clone())));
                continue;
            };
            components.push((name.clone(), source.clone(), None));
            let builtin = registry::find(kind).ok_or_else(|| damaged(format!("unknown built-in '{kind}'")))?;
            let given: BTreeMap<String, String> =
                component.params.iter().map(|p| (p.name.value.clone(), p.value.value.clone())).collect();
            let params = check_values(builtin.params(), &given)
                .map_err(|problems| damaged(format!("'{name}': {}", problem_text(&problems))))?;
            let ctx = PreflightContext {
                component: &name,
                world: world_file.as_deref(),
                sim_name: format!("preflight-sim-{name}"),
            };
            let form = builtin.preflight(&params, &ctx).map_err(|e| MaterializeError::NotSimulable(e.0))?;
            for (param, value) in &form.set {
                set_param(component, param, value);
            }
            for (param, contents) in &form.files {
                let written = out.write(&format!("files/{name}-{param}"), contents)?;
                set_param(component, param, &written);
            }
            // Files the built-in names (that its form did not replace) are
            // copied beside the robot file.
            for decl in builtin.params() {
                if form.set.iter().any(|(p, _)| *p == decl.name) || form.files.iter().any(|(p, _)| *p == decl.name) {
                    continue;
                }
                let Some(file) =
                    component.params.iter().find(|p| p.name.value == decl.name).map(|p| p.value.value.clone())
                else {
                    continue;
                };
                let Some(file) = decl.file(&file) else { continue };
                let mut bytes = named_file(store, set, file)?;
                if decl.name == crate::sim::builtin::WORLD_PARAM
                    && builtin.kind() == crate::sim::builtin::SimBuiltin.kind()
                {
                    bytes = started(bytes);
                }
                let base =
                    Path::new(file).file_name().map_or_else(|| "file".into(), |n| n.to_string_lossy().into_owned());
                let written = out.write(&format!("files/{name}-{}-{}", decl.name, safe_name(&base)), &bytes)?;
                set_param(component, decl.name, &written);
            }
            if let Some(sim_params) = form.simulated_by {
                let mut sim = RawComponent {
                    offset: component.offset,
                    name: spanned(&ctx.sim_name),
                    source: spanned(&sim_source),
                    priority: None,
                    rate: None,
                    budget: None,
                    timeout: None,
                    memory: None,
                    max_emits: None,
                    max_message: None,
                    max_logs: None,
                    restart: None,
                    max_restarts: None,
                    params: Vec::new(),
                };
                for (param, value) in sim_params {
                    set_param(&mut sim, param, &value);
                }
                components.push((ctx.sim_name.clone(), sim_source.clone(), None));
                added.push(sim);
            }
        }
        // Simulated controllers go first (they own the PTYs the links open).
        added.append(&mut platform.components);
        platform.components = added;
    }
    let text = raw::write(&robot, comment);
    let robot_file = out.write(ROBOT_FILE, text.as_bytes())?;
    Ok(Written { robot: dir.join(robot_file), files: out.files, components })
}

/// Where a WASM component's bytes are written, relative to the folder.
pub fn component_file(component: &str) -> String {
    format!("components/{component}.wasm")
}

fn spanned(value: &str) -> Spanned<String> {
    Spanned { value: value.to_string(), offset: 0 }
}

/// Sets parameter `name` of `component` to `value`, adding it if absent.
pub(super) fn set_param(component: &mut RawComponent, name: &str, value: &str) {
    match component.params.iter_mut().find(|p| p.name.value == name) {
        Some(param) => param.value.value = value.to_string(),
        None => {
            component.params.push(RawParam { offset: component.offset, name: spanned(name), value: spanned(value) })
        }
    }
}

fn problem_text(problems: &[crate::config::ParamProblem]) -> String {
    problems.iter().map(ToString::to_string).collect::<Vec<_>>().join("; ")
}

/// Letters, digits, `.`, `-` and `_` of `name`, the rest as `_`.
fn safe_name(name: &str) -> String {
    name.chars().map(|c| if c.is_ascii_alphanumeric() || matches!(c, '.' | '-' | '_') { c } else { '_' }).collect()
}

/// The bytes of file `file` a built-in of `set` names: an uploaded world
/// pinned to a blob, else the file in the set's folder.
fn named_file(store: &Store, set: &SetRecord, file: &str) -> Result<Vec<u8>, MaterializeError> {
    if let Some(sha) = set.sources.get(file) {
        return Ok(store.blob(sha)?);
    }
    let path = set.base_dir.join(file);
    let opened = std::fs::File::open(&path).map_err(io(&path))?;
    let mut bytes = Vec::new();
    opened.take(MAX_NAMED_FILE_BYTES + 1).read_to_end(&mut bytes).map_err(io(&path))?;
    if bytes.len() as u64 > MAX_NAMED_FILE_BYTES {
        return Err(MaterializeError::Damaged {
            set: set.id,
            reason: format!("{} is larger than {MAX_NAMED_FILE_BYTES} bytes", path.display()),
        });
    }
    Ok(bytes)
}

/// A file a built-in of a set names (a world, a translator), as a robot
/// sends it to its lab server with its baseline.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct NamedFile {
    /// The component and the parameter naming it.
    pub component: String,
    pub param: &'static str,
    /// The built-in's kind (`sim`, `serial`, ...).
    pub kind: String,
    /// The path as the robot file writes it (relative to its folder).
    pub path: String,
    pub content: NamedContent,
}

/// Where a named file's bytes come from.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum NamedContent {
    /// An uploaded file, stored as this blob.
    Blob(String),
    /// The file in the set's folder.
    File(PathBuf),
    /// A stand-in for a file that holds the robot's secrets (its
    /// operators, its Zenoh config): it validates, and nobody can use it.
    StandIn(Vec<u8>),
}

/// Every file the built-ins of `set` name (a relative path each; an
/// absolute one or one with `..` cannot travel and is left out), with
/// where its bytes come from.
pub fn named_files(store: &Store, set: &SetRecord) -> Result<Vec<NamedFile>, MaterializeError> {
    let damaged = |reason: String| MaterializeError::Damaged { set: set.id, reason };
    let text = String::from_utf8(store.blob(&set.config_sha256)?)
        .map_err(|e| damaged(format!("the robot file is not utf-8: {e}")))?;
    let map = SourceMap::new(Path::new(&set.config_name), &text);
    let mut errors = Vec::new();
    let robot = raw::parse(&map, &text, &mut errors);
    if !errors.is_empty() || !robot.complete {
        let first = errors.first().map_or_else(|| "incomplete".to_string(), ToString::to_string);
        return Err(damaged(format!("the stored robot file does not read: {first}")));
    }
    let mut files = Vec::new();
    for component in robot.platforms.iter().flat_map(|p| p.components.iter()) {
        let Some(kind) = component.source.value.strip_prefix("builtin:") else { continue };
        let Some(builtin) = registry::find(kind) else { continue };
        for decl in builtin.params() {
            let Some(value) = component.params.iter().find(|p| p.name.value == decl.name).map(|p| &p.value.value)
            else {
                continue;
            };
            let Some(path) = decl.file(value) else { continue };
            let relative = Path::new(path);
            if relative.is_absolute() || relative.components().any(|c| !matches!(c, std::path::Component::Normal(_))) {
                continue;
            }
            let content = match decl.stand_in() {
                Some(text) => NamedContent::StandIn(text.as_bytes().to_vec()),
                None => match set.sources.get(path) {
                    Some(sha) => NamedContent::Blob(sha.clone()),
                    None => NamedContent::File(set.base_dir.join(path)),
                },
            };
            files.push(NamedFile {
                component: component.name.value.clone(),
                param: decl.name,
                kind: kind.to_string(),
                path: path.to_string(),
                content,
            });
        }
    }
    Ok(files)
}

/// The folder being written, and what was written.
struct Folder<'a> {
    dir: &'a Path,
    files: Vec<(String, u64)>,
}

impl Folder<'_> {
    /// Writes `bytes` at `relative` (a host-made path) atomically; returns
    /// `relative`.
    fn write(&mut self, relative: &str, bytes: &[u8]) -> Result<String, MaterializeError> {
        let path = self.dir.join(relative);
        if let Some(parent) = path.parent() {
            std::fs::create_dir_all(parent).map_err(io(parent))?;
        }
        crate::fsutil::write_atomically(&path, bytes).map_err(io(&path))?;
        self.files.retain(|(name, _)| name != relative);
        self.files.push((relative.to_string(), bytes.len() as u64));
        Ok(relative.to_string())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The files a set's built-ins name: the world travels as it is; the
    /// operators file and the Zenoh config (parameters declared as secret
    /// files) travel only as their built-in's stand-in, whatever they hold.
    #[test]
    fn files_that_hold_secrets_travel_only_as_their_stand_ins() {
        let dir = tempfile::tempdir().unwrap();
        let store = Store::open(&dir.path().join("store")).unwrap();
        let robot = r#"<robot name="r">
  <platform name="control">
    <component name="sim" source="builtin:sim"><param name="world" value="arena.world"/></component>
  </platform>
  <platform name="network">
    <component name="teleop" source="builtin:teleop"><param name="operators" value="ops.txt"/></component>
    <component name="bus" source="builtin:zenoh"><param name="zenoh-config" value="zenoh.json5"/></component>
  </platform>
</robot>
"#;
        let set = SetRecord {
            format: 1,
            id: 7,
            created_by: "owner".into(),
            created_at: 0,
            platform: None,
            config_name: "robot.xml".into(),
            config_sha256: store.lock().unwrap().put_blob(robot.as_bytes()).unwrap(),
            base_dir: dir.path().to_path_buf(),
            sources: BTreeMap::new(),
            changes: Vec::new(),
            graph: Default::default(),
        };
        let files = named_files(&store, &set).unwrap();
        let content = |param: &str| files.iter().find(|f| f.param == param).map(|f| f.content.clone());
        assert_eq!(content("world"), Some(NamedContent::File(dir.path().join("arena.world"))), "{files:#?}");
        for (param, words) in [("operators", "nobody drives from the lab server"), ("zenoh-config", "never opens it")] {
            match content(param) {
                Some(NamedContent::StandIn(bytes)) => {
                    assert!(String::from_utf8(bytes).unwrap().contains(words), "{param}: {files:#?}")
                }
                other => panic!("{param} travels as {other:?}, not as its stand-in"),
            }
        }
    }

    #[test]
    fn the_reset_pose_replaces_the_worlds_start_and_the_world_still_reads() {
        let pose = Pose { x: 2.5, y: 1.0, heading: -0.5 };
        let cases: [(&str, &[u8], &str); 3] = [
            ("a start line", b"bounds 0 0 10 8\nstart 1 1 0.6\ngoal 8 1 0.3\n", "start 2.5 1 -0.5"),
            (
                "indented, among comments",
                b"# a world\nbounds 0 0 10 8\n  start   1 1 0\ngoal 8 1 0.3",
                "start 2.5 1 -0.5",
            ),
            ("no start line (the check says so without it)", b"bounds 0 0 10 8\ngoal 8 1 0.3\n", "start 2.5 1 -0.5"),
        ];
        for (case, world, expected) in cases {
            let written = String::from_utf8(world_with_start(world, pose)).unwrap();
            assert_eq!(written.lines().filter(|l| l.trim_start().starts_with("start")).count(), 1, "{case}: {written}");
            assert!(written.contains(expected), "{case}: {written}");
            let parsed = crate::sim::world::parse(Path::new("w.world"), &written);
            let (at, heading) = parsed.unwrap_or_else(|e| panic!("{case}: {e}")).start;
            assert_eq!((at.x, at.y, heading), (2.5, 1.0, -0.5), "{case}");
        }
        let binary = [0xff, 0xfe, b's'];
        assert_eq!(world_with_start(&binary, pose), binary.to_vec(), "not text: kept as it is");
    }
}
