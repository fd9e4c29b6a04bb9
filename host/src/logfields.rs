//! The fields of a `tracing` event as the host's log sinks keep them: the
//! message, the component it names, the user whose work it names
//! (`owner`), and every other field as ` name=value`; and whose set runs
//! or is being built, whose work a component's line names.
//! One visitor for every sink (the portal's log ring, the recording's log
//! channel), so both show a line the same way.

use std::sync::RwLock;

use tracing::field::{Field, Visit};

/// The users whose set runs now (both, while one set replaces another): a
/// line a component writes names their work. One host runs one set, so one
/// value for the process; the deployer keeps it ([`set_running_owners`]).
static RUNNING_OWNERS: RwLock<Vec<String>> = RwLock::new(Vec::new());

/// Notes whose sets run now: `owners` of the running set, or of the set
/// leaving and the set coming while they swap.
pub fn set_running_owners(owners: &[&str]) {
    let mut unique: Vec<String> = Vec::new();
    for owner in owners {
        if !unique.iter().any(|o| o == owner) {
            unique.push((*owner).to_string());
        }
    }
    if let Ok(mut running) = RUNNING_OWNERS.write() {
        *running = unique;
    }
}

/// The owners of the sets whose graphs are being built beside the running
/// one (their components' first lines come before the swap).
static BUILDING_OWNERS: RwLock<Vec<String>> = RwLock::new(Vec::new());

/// While it lives, a component's log line names the work of `owner` too:
/// her set's graph is being built.
pub struct Building(String);

impl Building {
    pub fn of(owner: &str) -> Building {
        if let Ok(mut building) = BUILDING_OWNERS.write() {
            building.push(owner.to_string());
        }
        Building(owner.to_string())
    }
}

impl Drop for Building {
    fn drop(&mut self) {
        if let Ok(mut building) = BUILDING_OWNERS.write()
            && let Some(at) = building.iter().position(|o| *o == self.0)
        {
            building.remove(at);
        }
    }
}

/// Whose sets run or are being built now (see [`set_running_owners`],
/// [`Building`]).
pub fn running_owners() -> Vec<String> {
    let mut owners = RUNNING_OWNERS.read().map(|running| running.clone()).unwrap_or_default();
    if let Ok(building) = BUILDING_OWNERS.read() {
        for owner in building.iter() {
            if !owners.contains(owner) {
                owners.push(owner.clone());
            }
        }
    }
    owners
}

/// A `tracing` event's fields, read by [`Visit`].
#[derive(Debug, Default)]
pub struct LogFields {
    pub message: String,
    pub component: Option<String>,
    /// The user whose work the line names (a field `owner`): the portal
    /// shows the line only to those who may see her work (`store::access`).
    pub owner: Option<String>,
    /// The other fields, each as ` name=value`.
    pub extra: String,
}

impl LogFields {
    /// The fields of `event`.
    pub fn of(event: &tracing::Event<'_>) -> LogFields {
        let mut fields = LogFields::default();
        event.record(&mut fields);
        fields
    }
}

impl Visit for LogFields {
    fn record_str(&mut self, field: &Field, value: &str) {
        match field.name() {
            "message" => self.message = value.to_string(),
            "component" => self.component = Some(value.to_string()),
            "owner" => self.owner = Some(value.to_string()),
            other => self.extra.push_str(&format!(" {other}={value}")),
        }
    }

    fn record_debug(&mut self, field: &Field, value: &dyn std::fmt::Debug) {
        match field.name() {
            "message" => self.message = format!("{value:?}"),
            "component" => self.component = Some(format!("{value:?}").trim_matches('"').to_string()),
            "owner" => self.owner = Some(format!("{value:?}").trim_matches('"').to_string()),
            other => self.extra.push_str(&format!(" {other}={value:?}")),
        }
    }
}
