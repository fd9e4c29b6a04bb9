//! The lab kit's robot file as a submission (docs/lab.md, "From the kit to
//! the lab"): a researcher changes `kit/robot.xml` (a component's `source`
//! pointed at her own `.wasm`, its parameters, its limits), runs it on her
//! machine, and submits that same file. The kit's robot file is the
//! baseline in its preflight form (simulated controllers, files under
//! `files/`), so it is never sent as it is: [`kit_submission`] finds what
//! she changed against the kit as written ([`KitManifest`], `kit.json`)
//! and makes the same changes to the lab's baseline robot file.
//!
//! Pure: the caller reads the files and talks to the lab. Invariants:
//! - a component whose file's sha256 is the kit's is the lab's own and is
//!   never uploaded; any other bytes are hers and are uploaded;
//! - only a WASM component's source, attributes and parameters carry over;
//!   a change to a built-in (the kit has it in its preflight form), to the
//!   connections, or a component added or removed is refused, naming the
//!   line in her file: nothing is guessed.

use std::collections::BTreeMap;
use std::path::Path;

use serde::{Deserialize, Serialize};
use thiserror::Error;

use crate::config::SourceMap;
use crate::config::raw::{self, RawComponent, RawRobot, Spanned};

/// The kit's manifest, beside its robot file.
pub const KIT_MANIFEST: &str = "kit.json";

/// What the kit was written from, for a submission of its robot file to
/// find what the researcher changed.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct KitManifest {
    /// The baseline set the kit is of.
    pub baseline: u64,
    /// The sha256 of the baseline's robot file.
    pub baseline_sha256: String,
    /// The kit's `robot.xml` as the lab wrote it.
    pub robot: String,
    /// Each WASM component's file in the kit and the sha256 of its bytes.
    pub components: BTreeMap<String, KitComponent>,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct KitComponent {
    pub file: String,
    pub sha256: String,
}

/// The baseline with the researcher's changes.
#[derive(Clone, Debug, PartialEq)]
pub struct KitSubmission {
    /// The robot file to stage.
    pub text: String,
    /// Components whose bytes are hers: (component, the `source` her file
    /// gives, which names a file beside it). The caller uploads each and
    /// points the component at the upload.
    pub uploads: Vec<(String, String)>,
    /// A line per change, for the researcher.
    pub changes: Vec<String>,
}

/// Why a kit's robot file cannot be submitted.
#[derive(Debug, Error, PartialEq)]
pub enum KitError {
    #[error(
        "{file} is the lab kit of set {kit}, and the lab's baseline is set {baseline} now: download the kit again (`subsume lab kit`) and make your changes there"
    )]
    Stale { file: String, kit: u64, baseline: u64 },
    #[error("{0}: the kit's manifest does not read; download the kit again")]
    Manifest(String),
    #[error("{at}: {what}")]
    Unsupported { at: String, what: String },
    #[error("{0}")]
    Unreadable(String),
}

/// Finds what `local` (the kit's robot file at `path` as the researcher
/// has it) changes against the kit as written (`manifest`), and makes
/// those changes to the baseline's robot file (`baseline`, set
/// `baseline_set`). `file_sha256(source)`: the sha256 of the file a
/// `source` names beside the robot file, `None` when there is no such file
/// (the source then names a component stored on the lab).
pub fn kit_submission(
    manifest: &KitManifest,
    path: &Path,
    local: &str,
    baseline_set: u64,
    baseline: &str,
    file_sha256: &dyn Fn(&str) -> Option<String>,
) -> Result<KitSubmission, KitError> {
    let shown = path.display().to_string();
    if manifest.baseline != baseline_set {
        return Err(KitError::Stale { file: shown, kit: manifest.baseline, baseline: baseline_set });
    }
    let local_map = SourceMap::new(path, local);
    let at = |offset: usize| {
        let (line, column) = local_map.line_column(offset);
        format!("{shown}:{line}:{column}")
    };
    let unsupported = |offset: usize, what: String| KitError::Unsupported { at: at(offset), what };
    let kit_path = Path::new("kit.json#robot");
    let written = parse(kit_path, &manifest.robot).map_err(|why| KitError::Manifest(format!("{shown}: {why}")))?;
    let mine = parse(path, local).map_err(KitError::Unreadable)?;
    let base_path = Path::new("the lab's baseline");
    let mut base = parse(base_path, baseline).map_err(KitError::Unreadable)?;

    let names = |r: &RawRobot| r.platforms.iter().map(|p| p.name.value.clone()).collect::<Vec<_>>();
    if names(&written) != names(&mine) {
        return Err(unsupported(
            mine.offset,
            "its platforms differ from the kit's: a submission from the kit changes components, not platforms".into(),
        ));
    }
    let mut uploads = Vec::new();
    let mut changes = Vec::new();
    for (kit_platform, my_platform) in written.platforms.iter().zip(&mine.platforms) {
        let connections = |p: &raw::RawPlatform| {
            p.connections
                .iter()
                .map(|k| {
                    (
                        k.from.value.clone(),
                        k.to.value.clone(),
                        k.policy.as_ref().map(|v| v.value.clone()),
                        k.depth.as_ref().map(|v| v.value.clone()),
                    )
                })
                .collect::<Vec<_>>()
        };
        if connections(kit_platform) != connections(my_platform) {
            let offset = my_platform
                .connections
                .iter()
                .zip(kit_platform.connections.iter().map(Some).chain(std::iter::repeat(None)))
                .find(|(m, k)| k.is_none_or(|k| m.from != k.from || m.to != k.to))
                .map_or(my_platform.offset, |(m, _)| m.offset);
            return Err(unsupported(
                offset,
                format!(
                    "the connections of platform '{}' differ from the kit's: a submission from the kit changes components, not how they are wired; submit a robot file of your own with --robot",
                    my_platform.name.value
                ),
            ));
        }
        for mine in &my_platform.components {
            if !kit_platform.components.iter().any(|k| k.name.value == mine.name.value) {
                return Err(unsupported(
                    mine.offset,
                    format!(
                        "component '{}' is not in the kit: a submission from the kit changes the lab's components, it adds none; submit a robot file of your own with --robot",
                        mine.name.value
                    ),
                ));
            }
        }
        for kit in &kit_platform.components {
            let name = &kit.name.value;
            let Some(mine) = my_platform.components.iter().find(|m| &m.name.value == name) else {
                return Err(unsupported(
                    my_platform.offset,
                    format!("component '{name}' of the kit is gone: a submission from the kit removes none"),
                ));
            };
            let Some(stored) = manifest.components.get(name) else {
                // A built-in, in its preflight form: it stays the lab's.
                if !same_component(kit, mine) {
                    return Err(unsupported(
                        mine.offset,
                        format!(
                            "'{name}' ({}) is the lab's own, here in its preflight form: an experiment cannot change it from the kit",
                            kit.source.value
                        ),
                    ));
                }
                continue;
            };
            let Some(target) = base
                .platforms
                .iter_mut()
                .find(|p| p.name.value == my_platform.name.value)
                .and_then(|p| p.components.iter_mut().find(|c| &c.name.value == name))
            else {
                return Err(KitError::Manifest(format!("{shown}: the baseline has no component '{name}'")));
            };
            match file_sha256(&mine.source.value) {
                Some(sha) if sha == stored.sha256 => {}
                Some(sha) => {
                    uploads.push((name.clone(), mine.source.value.clone()));
                    changes.push(format!("{name}: your {} (sha256 {sha})", mine.source.value));
                }
                None if mine.source.value == kit.source.value => {
                    return Err(unsupported(
                        mine.source.offset,
                        format!("'{name}': its file {} is missing", mine.source.value),
                    ));
                }
                None => {
                    changes.push(format!("{name}: {} as stored on the lab", mine.source.value));
                    target.source.value = mine.source.value.clone();
                }
            }
            for (attribute, kit_value, my_value, value) in attributes(kit, mine, target) {
                if kit_value != my_value {
                    let shown = |v: &Option<String>| v.clone().unwrap_or_else(|| "(none)".into());
                    changes.push(format!("{name}: {attribute} {} -> {}", shown(&kit_value), shown(&my_value)));
                    *value = my_value.map(|v| Spanned { value: v, offset: 0 });
                }
            }
            let (kit_params, my_params) = (params(kit), params(mine));
            for (param, value) in &my_params {
                if kit_params.get(param) != Some(value) {
                    let was = kit_params.get(param).map_or("(none)", String::as_str);
                    changes.push(format!("{name}: {param} {was} -> {value}"));
                    super::materialize::set_param(target, param, value);
                }
            }
            for param in kit_params.keys().filter(|p| !my_params.contains_key(*p)) {
                changes.push(format!("{name}: {param} removed"));
                target.params.retain(|p| &p.name.value != param);
            }
        }
    }
    let comment = format!(
        "the lab's baseline (set {baseline_set}) with the changes of {shown}, written by subsume lab submit from the lab kit"
    );
    Ok(KitSubmission { text: raw::write(&base, &comment), uploads, changes })
}

fn parse(path: &Path, text: &str) -> Result<RawRobot, String> {
    let map = SourceMap::new(path, text);
    let mut errors = Vec::new();
    let robot = raw::parse(&map, text, &mut errors);
    match errors.first() {
        Some(first) => Err(first.to_string()),
        None if !robot.complete => Err(format!("{}: incomplete", path.display())),
        None => Ok(robot),
    }
}

type Attribute<'t> = (&'static str, Option<String>, Option<String>, &'t mut Option<Spanned<String>>);

/// Each optional attribute: its name, the kit's value, hers, and the
/// baseline's to change.
fn attributes<'t>(kit: &RawComponent, mine: &RawComponent, target: &'t mut RawComponent) -> Vec<Attribute<'t>> {
    let value = |v: &Option<Spanned<String>>| v.as_ref().map(|s| s.value.clone());
    macro_rules! each {
        ($($field:ident => $name:literal),*) => {
            vec![$(($name, value(&kit.$field), value(&mine.$field), &mut target.$field)),*]
        };
    }
    each!(priority => "priority", rate => "rate", budget => "budget", timeout => "timeout", memory => "memory",
        max_emits => "max-emits", max_message => "max-message", max_logs => "max-logs", restart => "restart",
        max_restarts => "max-restarts")
}

/// A component's parameters, by name.
fn params(component: &RawComponent) -> BTreeMap<String, String> {
    component.params.iter().map(|p| (p.name.value.clone(), p.value.value.clone())).collect()
}

/// Whether two components say the same (offsets aside).
fn same_component(a: &RawComponent, b: &RawComponent) -> bool {
    let mut scratch = a.clone();
    a.source.value == b.source.value
        && params(a) == params(b)
        && attributes(a, b, &mut scratch).iter().all(|(_, x, y, _)| x == y)
}

#[cfg(test)]
mod tests {
    use super::*;

    const BASELINE: &str = r#"<robot name="lab">
  <platform name="control">
    <component name="motors" source="builtin:serial" rate="50"><param name="device" value="/dev/ttyUSB0"/></component>
    <component name="driver" source="driver.wasm" rate="10"><param name="speed" value="0.3"/></component>
    <component name="envelope" source="builtin:envelope"><param name="max-speed" value="0.5"/></component>
    <connect from="driver.cmd" to="envelope.cmd"/>
    <connect from="envelope.cmd" to="motors.cmd"/>
  </platform>
</robot>"#;

    /// The kit as the lab writes it: the serial link simulated, the WASM
    /// component under components/ (the baseline otherwise, line for line).
    fn kit() -> String {
        BASELINE
            .replace(r#"value="/dev/ttyUSB0""#, r#"value="sim:preflight-sim-motors""#)
            .replace(r#"source="driver.wasm""#, r#"source="components/driver.wasm""#)
    }

    fn manifest() -> KitManifest {
        KitManifest {
            baseline: 3,
            baseline_sha256: "b".repeat(64),
            robot: kit(),
            components: [(
                "driver".to_string(),
                KitComponent { file: "components/driver.wasm".into(), sha256: "a".repeat(64) },
            )]
            .into(),
        }
    }

    fn files(source: &str) -> Option<String> {
        match source {
            "components/driver.wasm" => Some("a".repeat(64)),
            "../mine.wasm" => Some("c".repeat(64)),
            _ => None,
        }
    }

    fn submit(local: &str) -> Result<KitSubmission, KitError> {
        kit_submission(&manifest(), Path::new("kit/robot.xml"), local, 3, BASELINE, &files)
    }

    fn component<'r>(robot: &'r RawRobot, name: &str) -> &'r RawComponent {
        robot.platforms[0].components.iter().find(|c| c.name.value == name).unwrap()
    }

    fn parsed(text: &str) -> RawRobot {
        parse(Path::new("sent.xml"), text).unwrap()
    }

    #[test]
    fn the_kit_unchanged_is_the_baseline_with_nothing_uploaded() {
        let sent = submit(&kit()).unwrap();
        assert!(sent.uploads.is_empty() && sent.changes.is_empty(), "{sent:?}");
        let robot = parsed(&sent.text);
        assert_eq!(component(&robot, "motors").params[0].value.value, "/dev/ttyUSB0");
        assert_eq!(component(&robot, "driver").source.value, "driver.wasm");
    }

    #[test]
    fn her_component_bytes_a_parameter_and_a_rate_carry_over_to_the_baseline() {
        let local = kit()
            .replace(r#"source="components/driver.wasm" rate="10""#, r#"source="../mine.wasm" rate="20""#)
            .replace(r#"value="0.3""#, r#"value="0.25"/><param name="gain" value="2""#);
        let sent = submit(&local).unwrap();
        assert_eq!(sent.uploads, vec![("driver".to_string(), "../mine.wasm".to_string())]);
        assert_eq!(
            sent.changes,
            vec![
                format!("driver: your ../mine.wasm (sha256 {})", "c".repeat(64)),
                "driver: rate 10 -> 20".to_string(),
                "driver: gain (none) -> 2".to_string(),
                "driver: speed 0.3 -> 0.25".to_string(),
            ]
        );
        let robot = parsed(&sent.text);
        let driver = component(&robot, "driver");
        assert_eq!(driver.rate.as_ref().unwrap().value, "20");
        let params: Vec<_> = driver.params.iter().map(|p| (p.name.value.as_str(), p.value.value.as_str())).collect();
        assert_eq!(params, [("speed", "0.25"), ("gain", "2")]);
        // The built-ins are the baseline's, not the kit's preflight form.
        assert_eq!(component(&robot, "motors").params[0].value.value, "/dev/ttyUSB0");
    }

    #[test]
    fn a_source_naming_no_file_here_names_a_stored_component() {
        let local = kit().replace("components/driver.wasm", "ana/driver.wasm");
        let sent = submit(&local).unwrap();
        assert!(sent.uploads.is_empty());
        assert_eq!(component(&parsed(&sent.text), "driver").source.value, "ana/driver.wasm");
    }

    #[test]
    fn what_a_kit_cannot_carry_is_refused_at_its_line() {
        let cases = [
            (
                "a built-in changed",
                kit().replace(r#"name="max-speed" value="0.5""#, r#"name="max-speed" value="5""#),
                "kit/robot.xml:5:5: 'envelope' (builtin:envelope) is the lab's own, here in its preflight form: an experiment cannot change it from the kit",
            ),
            (
                "a component added",
                kit().replace(
                    "    <connect from=\"driver.cmd\"",
                    "    <component name=\"extra\" source=\"x.wasm\"/>\n    <connect from=\"driver.cmd\"",
                ),
                "kit/robot.xml:6:5: component 'extra' is not in the kit: a submission from the kit changes the lab's components, it adds none; submit a robot file of your own with --robot",
            ),
            (
                "a connection changed",
                kit().replace(
                    r#"<connect from="driver.cmd" to="envelope.cmd"/>"#,
                    r#"<connect from="driver.cmd" to="motors.cmd"/>"#,
                ),
                "kit/robot.xml:6:5: the connections of platform 'control' differ from the kit's: a submission from the kit changes components, not how they are wired; submit a robot file of your own with --robot",
            ),
        ];
        for (case, local, expected) in cases {
            let got = submit(&local);
            assert_eq!(got.map_err(|e| e.to_string()), Err(expected.to_string()), "{case}");
        }
        let missing = kit_submission(&manifest(), Path::new("kit/robot.xml"), &kit(), 3, BASELINE, &|_| None);
        assert_eq!(
            missing.map_err(|e| e.to_string()),
            Err("kit/robot.xml:4:38: 'driver': its file components/driver.wasm is missing".to_string())
        );
    }

    #[test]
    fn a_kit_of_an_older_baseline_is_refused_naming_both_sets() {
        let got = kit_submission(&manifest(), Path::new("kit/robot.xml"), &kit(), 4, BASELINE, &files);
        assert_eq!(got, Err(KitError::Stale { file: "kit/robot.xml".into(), kit: 3, baseline: 4 }));
    }
}
