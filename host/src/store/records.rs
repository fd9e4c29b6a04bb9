//! What the store persists, as typed records with a format version.
//!
//! Every file carries `format`. Files written before formats existed (the
//! first store layout) have none and read as format 1; each `parse` brings
//! an older record to the current shape when it is read, and the next write
//! stores it in the current format. A file of a newer format than this host
//! knows is refused, never guessed at.

use std::collections::BTreeMap;
use std::path::PathBuf;

use serde::{Deserialize, Deserializer, Serialize};

use crate::contract::DescriptionDoc;

/// Format of `components.json`, `sets/<id>.json` and `state.json`.
/// 1: the first layout (no `format` field; a translator's description was
/// `{"name", "world"}`); 2: typed descriptions and wiring graphs; 3: each
/// component belongs to its uploader (`components.json` is keyed by
/// `OWNER/NAME`, so two users' uploads of one name are two records).
pub const STORE_FORMAT: u32 = 3;

fn first_format() -> u32 {
    1
}

/// A component as uploaded.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
pub struct ComponentRecord {
    pub name: String,
    pub sha256: String,
    pub size: u64,
    /// Which WIT world it fits.
    pub world: World,
    /// The platform it was uploaded for.
    pub platform: String,
    pub uploaded_by: String,
    pub uploaded_at: u64,
    /// What `describe` returned; translators have none.
    #[serde(default, deserialize_with = "description_or_none")]
    pub description: Option<DescriptionDoc>,
    /// Who besides its owner and the admins may see and run it (`private`:
    /// nobody; `lab`: every user, read-only); private unless its owner
    /// shares it (`store::access`).
    #[serde(default)]
    pub visibility: Visibility,
}

/// Who may run and see an upload besides its owner and the admins.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(rename_all = "lowercase")]
pub enum Visibility {
    /// Its owner and the admins only (and, for an upload of the robot's
    /// own people, every user but a researcher).
    #[default]
    Private,
    /// Every user of the lab, read-only: they may see its record and name
    /// it as `OWNER/NAME.wasm`; only its owner replaces it.
    Lab,
}

impl Visibility {
    pub fn name(self) -> &'static str {
        match self {
            Visibility::Private => "private",
            Visibility::Lab => "lab",
        }
    }
}

/// The WIT world a component fits.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(rename_all = "lowercase")]
pub enum World {
    Component,
    Translator,
    /// A task's scoring component (`wit/robot.wit`'s `scorer` world).
    Scorer,
}

impl World {
    /// Its name in `wit/robot.wit`.
    pub fn name(self) -> &'static str {
        match self {
            World::Component => "component",
            World::Translator => "translator",
            World::Scorer => "scorer",
        }
    }
}

/// Format 1 stored `{"name": .., "world": "translator"}` as a translator's
/// description: that is no description.
fn description_or_none<'de, D: Deserializer<'de>>(deserializer: D) -> Result<Option<DescriptionDoc>, D::Error> {
    let value = serde_json::Value::deserialize(deserializer)?;
    if value.is_null() || value.get("world").is_some() {
        return Ok(None);
    }
    serde_json::from_value(value).map(Some).map_err(serde::de::Error::custom)
}

impl ComponentRecord {
    /// Its key in the store: `OWNER/NAME`.
    pub fn key(&self) -> String {
        component_key(&self.uploaded_by, &self.name)
    }

    /// How a robot file names it from anywhere: `source="OWNER/NAME.wasm"`
    /// (its owner may also write `NAME.wasm`).
    pub fn source(&self) -> String {
        format!("{}.wasm", self.key())
    }
}

/// The store's key of `owner`'s upload `name`. User and component names
/// are both `[a-z][a-z0-9_-]*`, so the `/` is unambiguous.
pub fn component_key(owner: &str, name: &str) -> String {
    format!("{owner}/{name}")
}

/// `components.json`: every uploaded component, by `OWNER/NAME`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct ComponentIndex {
    #[serde(default = "first_format")]
    pub format: u32,
    pub components: BTreeMap<String, ComponentRecord>,
}

impl ComponentIndex {
    /// Reads `components.json` of any known format: format 1 was the bare
    /// map of name -> record, formats 1 and 2 kept one record per name (the
    /// last uploader's), which becomes that uploader's record.
    pub(super) fn parse(bytes: &[u8]) -> Result<ComponentIndex, String> {
        let value: serde_json::Value = serde_json::from_slice(bytes).map_err(|e| e.to_string())?;
        let index = if value.get("format").is_some() {
            serde_json::from_value::<ComponentIndex>(value).map_err(|e| e.to_string())?
        } else {
            let components = serde_json::from_value(value).map_err(|e| e.to_string())?;
            ComponentIndex { format: 1, components }
        };
        index.migrate()
    }

    fn migrate(mut self) -> Result<ComponentIndex, String> {
        if self.format > STORE_FORMAT {
            return Err(format!("format {} is newer than this host's {STORE_FORMAT}", self.format));
        }
        // Keyed by what each record says, whatever the file's keys were.
        self.components = self.components.into_values().map(|record| (record.key(), record)).collect();
        self.format = STORE_FORMAT;
        Ok(self)
    }
}

/// A simulator world file as uploaded (its bytes are a blob).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
pub struct WorldRecord {
    pub name: String,
    pub sha256: String,
    pub size: u64,
    pub uploaded_by: String,
    pub uploaded_at: u64,
}

/// `worlds.json`: every uploaded world file, by name. New in format 2, so
/// it has no older shape.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct WorldIndex {
    pub format: u32,
    pub worlds: BTreeMap<String, WorldRecord>,
}

impl WorldIndex {
    pub(super) fn parse(bytes: &[u8]) -> Result<WorldIndex, String> {
        let index: WorldIndex = serde_json::from_slice(bytes).map_err(|e| e.to_string())?;
        if index.format > STORE_FORMAT {
            return Err(format!("format {} is newer than this host's {STORE_FORMAT}", index.format));
        }
        Ok(index)
    }
}

/// A robot file with the components it runs, ready to activate. Never
/// changed once written.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
pub struct SetRecord {
    #[serde(default = "first_format")]
    pub format: u32,
    pub id: u64,
    pub created_by: String,
    pub created_at: u64,
    /// The platform the upload was for; `None` for a set imported at boot.
    pub platform: Option<String>,
    /// The robot file's name as uploaded (diagnostics use it).
    pub config_name: String,
    pub config_sha256: String,
    /// Folder that relative file parameters (world files) resolve against.
    pub base_dir: PathBuf,
    /// Each WASM source as the robot file writes it -> blob.
    pub sources: BTreeMap<String, String>,
    /// Platforms whose components or connections differ from the set that
    /// was active when this one was made.
    #[serde(default)]
    pub changes: Vec<String>,
    /// Components (with their ports) and connections, for the wiring view:
    /// worked out once, when the set is validated.
    #[serde(default, deserialize_with = "graph_or_empty")]
    pub graph: WiringGraph,
}

fn graph_or_empty<'de, D: Deserializer<'de>>(deserializer: D) -> Result<WiringGraph, D::Error> {
    let value = serde_json::Value::deserialize(deserializer)?;
    if value.is_null() {
        return Ok(WiringGraph::default());
    }
    serde_json::from_value(value).map_err(serde::de::Error::custom)
}

impl SetRecord {
    pub(super) fn parse(bytes: &[u8]) -> Result<SetRecord, String> {
        let mut record: SetRecord = serde_json::from_slice(bytes).map_err(|e| e.to_string())?;
        if record.format > STORE_FORMAT {
            return Err(format!("format {} is newer than this host's {STORE_FORMAT}", record.format));
        }
        record.format = STORE_FORMAT;
        Ok(record)
    }
}

/// A set's components and connections, as the wiring view draws them.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
pub struct WiringGraph {
    pub robot: String,
    pub components: Vec<WiringComponent>,
    pub connections: Vec<WiringConnection>,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
pub struct WiringComponent {
    pub name: String,
    pub platform: String,
    /// `builtin:KIND` or `wasm:NAME`.
    pub source: String,
    pub priority: Option<i32>,
    pub rate_hz: f64,
    pub inputs: Vec<String>,
    pub outputs: Vec<String>,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
pub struct WiringConnection {
    /// `component.port`
    pub from: String,
    pub to: String,
    pub platform: String,
}

/// `state.json`: which set runs and which ran before.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct StoreState {
    #[serde(default = "first_format")]
    pub format: u32,
    pub active: Option<u64>,
    /// Sets active before, oldest first.
    pub history: Vec<u64>,
    /// The next set's id; ids are never reused.
    pub next_set: u64,
    /// sha256 of the robot file last imported at boot.
    pub boot_config_sha256: Option<String>,
}

impl Default for StoreState {
    fn default() -> Self {
        StoreState { format: STORE_FORMAT, active: None, history: Vec::new(), next_set: 1, boot_config_sha256: None }
    }
}

impl StoreState {
    pub(super) fn parse(bytes: &[u8]) -> Result<StoreState, String> {
        let mut state: StoreState = serde_json::from_slice(bytes).map_err(|e| e.to_string())?;
        if state.format > STORE_FORMAT {
            return Err(format!("format {} is newer than this host's {STORE_FORMAT}", state.format));
        }
        state.format = STORE_FORMAT;
        state.next_set = state.next_set.max(1);
        Ok(state)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Records as the first store layout wrote them (no `format`, untyped
    /// descriptions and graphs) still load.
    #[test]
    fn format_one_records_load() -> Result<(), String> {
        let components = br#"{
          "avoider": {"name": "avoider", "sha256": "ab", "size": 3, "world": "component", "platform": "control",
                      "uploaded_by": "ana", "uploaded_at": 1,
                      "description": {"name": "avoider", "version": "1", "summary": "s", "sha256": "ab",
                                      "default_priority": 3, "inputs": [], "outputs": [], "params": []}},
          "tr": {"name": "tr", "sha256": "cd", "size": 3, "world": "translator", "platform": "control",
                 "uploaded_by": "ana", "uploaded_at": 1, "description": {"name": "tr", "world": "translator"}}
        }"#;
        let index = ComponentIndex::parse(components)?;
        assert_eq!(index.format, STORE_FORMAT);
        assert_eq!(index.components["ana/avoider"].description.as_ref().map(|d| d.default_priority), Some(Some(3)));
        assert_eq!(index.components["ana/tr"].description, None);
        assert_eq!(index.components["ana/tr"].world, World::Translator);
        let set = br#"{"id": 3, "created_by": "boot", "created_at": 1, "platform": null, "config_name": "demo.xml",
                       "config_sha256": "ef", "base_dir": "/r", "sources": {}, "changes": [], "graph": null}"#;
        assert_eq!(SetRecord::parse(set)?.graph, WiringGraph::default());
        let state = br#"{"active": 3, "history": [1, 2], "next_set": 4, "boot_config_sha256": null}"#;
        assert_eq!(StoreState::parse(state)?.active, Some(3));
        Ok(())
    }

    /// A format 2 index (one record per name, the last uploader's) loads
    /// with each record under its uploader; a format 3 index keeps two
    /// users' uploads of one name apart.
    #[test]
    fn format_two_components_belong_to_their_uploaders() -> Result<(), String> {
        let record = |name: &str, by: &str, sha: &str| {
            format!(
                r#"{{"name": "{name}", "sha256": "{sha}", "size": 3, "world": "component", "platform": "control",
                    "uploaded_by": "{by}", "uploaded_at": 1, "description": null}}"#
            )
        };
        let two = format!(
            r#"{{"format": 2, "components": {{"avoid": {}, "filter": {}}}}}"#,
            record("avoid", "bob", "b1"),
            record("filter", "ana", "a1")
        );
        let index = ComponentIndex::parse(two.as_bytes())?;
        let keys: Vec<&str> = index.components.keys().map(String::as_str).collect();
        assert_eq!(keys, ["ana/filter", "bob/avoid"]);
        assert_eq!(index.components["bob/avoid"].source(), "bob/avoid.wasm");
        let three = format!(
            r#"{{"format": 3, "components": {{"ana/avoid": {}, "bob/avoid": {}}}}}"#,
            record("avoid", "ana", "a2"),
            record("avoid", "bob", "b2")
        );
        let index = ComponentIndex::parse(three.as_bytes())?;
        let shas: Vec<&str> = index.components.values().map(|c| c.sha256.as_str()).collect();
        assert_eq!(shas, ["a2", "b2"]);
        Ok(())
    }

    #[test]
    fn newer_formats_are_refused() {
        let state = br#"{"format": 99, "active": null, "history": [], "next_set": 1, "boot_config_sha256": null}"#;
        assert!(StoreState::parse(state).is_err_and(|e| e.contains("format 99 is newer")));
    }
}
