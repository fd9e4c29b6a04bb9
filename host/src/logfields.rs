//! The fields of a `tracing` event as the host's log sinks keep them: the
//! message, the component it names, the user whose work it names
//! (`owner`), and every other field as ` name=value`.
//! One visitor for every sink (the portal's log ring, the recording's log
//! channel), so both show a line the same way.

use tracing::field::{Field, Visit};

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
