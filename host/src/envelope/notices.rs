//! What the envelope's `interventions` output says: pure, with explicit
//! time, table-tested.
//!
//! A component wired to it learns that the envelope acted, so a geofence
//! hold does not look like a frozen algorithm from inside. One message
//! (JSON text, [`Notice`]) when an intervention starts, when it changes
//! (another action or another cause) and when it ends (commands pass
//! unchanged again), never one per command: a driver held at a wall for a
//! minute hears of it once. At most one message every [`NOTICE_INTERVAL_NS`];
//! a state that came and went within the interval is summed up by the next
//! message's `changes`.

use serde::Serialize;

use super::logic::{Action, Cause, Verdict};
use crate::contract::control::ControlCommand;

/// Least time between two messages on `interventions`: a command that
/// flips between passed and scaled every cycle (a driver at the edge of
/// the slowdown zone) must not send a message into every connected
/// component at the control loop's rate.
pub const NOTICE_INTERVAL_NS: u64 = 100_000_000;

/// One message on the `interventions` output.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Notice {
    /// When this state began (graph time), s.
    pub at_s: f64,
    /// `scaled` or `stopped`: an intervention (started or changed);
    /// `passed`: the intervention ended.
    pub action: Action,
    /// The cause's short name (`geofence`, `stop-zone`, ...; the report
    /// counts by these); none when passed.
    pub cause: Option<&'static str>,
    /// The reading behind the cause, units in the field names
    /// (`{"edge_m": 0.25, "outside": false}`); none when passed.
    pub reading: Option<serde_json::Value>,
    /// The command that came in, and what the envelope let through.
    pub command: String,
    pub output: String,
    /// For people: `stopped VEL 0.2 0.0: geofence: edge 0.25 m away`.
    pub text: String,
    /// States since the previous message: more than 1 when some came and
    /// went within [`NOTICE_INTERVAL_NS`].
    pub changes: u64,
}

impl Notice {
    fn new(command: ControlCommand, verdict: &Verdict, now_ns: u64) -> Notice {
        let text = match (&verdict.action, &verdict.cause) {
            (Action::Passed, _) | (_, None) => format!("passed {command} unchanged"),
            (Action::Scaled, Some(cause)) => format!("scaled {command} to {}: {cause}", verdict.command),
            (Action::Stopped, Some(cause)) => format!("stopped {command}: {cause}"),
        };
        Notice {
            at_s: now_ns as f64 / 1e9,
            action: verdict.action,
            cause: verdict.cause.as_ref().map(Cause::kind),
            reading: verdict.cause.as_ref().map(Cause::reading),
            command: command.to_string(),
            output: verdict.command.to_string(),
            text,
            changes: 0,
        }
    }

    fn state(&self) -> (Action, Option<&'static str>) {
        (self.action, self.cause)
    }
}

/// The `interventions` output's memory: what it last said, and the newest
/// state it has not said yet.
#[derive(Clone, Debug)]
pub struct Notices {
    said: (Action, Option<&'static str>),
    said_at_ns: Option<u64>,
    owed: Option<Notice>,
}

impl Default for Notices {
    fn default() -> Self {
        Notices { said: (Action::Passed, None), said_at_ns: None, owed: None }
    }
}

impl Notices {
    /// Notes the envelope's verdict on `command` at `now_ns`; returns the
    /// message to send now, if one is owed and due.
    pub fn note(&mut self, command: ControlCommand, verdict: &Verdict, now_ns: u64) -> Option<Notice> {
        let state = (verdict.action, verdict.cause.as_ref().map(Cause::kind));
        let current = self.owed.as_ref().map_or(self.said, Notice::state);
        if state != current {
            let changes = self.owed.as_ref().map_or(0, |owed| owed.changes) + 1;
            self.owed = Some(Notice { changes, ..Notice::new(command, verdict, now_ns) });
        }
        self.due(now_ns)
    }

    /// The owed message, once [`NOTICE_INTERVAL_NS`] has passed since the
    /// last one (a tick calls this, so a held message goes out without a
    /// new command).
    pub fn due(&mut self, now_ns: u64) -> Option<Notice> {
        let ready = self.said_at_ns.is_none_or(|at| now_ns.saturating_sub(at) >= NOTICE_INTERVAL_NS);
        if !ready {
            return None;
        }
        let notice = self.owed.take()?;
        self.said = notice.state();
        self.said_at_ns = Some(now_ns);
        Some(notice)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const MS: u64 = 1_000_000;

    fn vel(linear: f64, angular: f64) -> ControlCommand {
        ControlCommand::Vel { linear, angular }
    }

    fn passed(command: ControlCommand) -> Verdict {
        Verdict { command, action: Action::Passed, cause: None }
    }

    fn fence() -> Verdict {
        Verdict {
            command: ControlCommand::Stop,
            action: Action::Stopped,
            cause: Some(Cause::Geofence { edge: 0.25, outside: false }),
        }
    }

    fn slowed(cap: f64) -> Verdict {
        Verdict {
            command: vel(cap, 0.0),
            action: Action::Scaled,
            cause: Some(Cause::SlowZone { ahead: 0.3, zone: 0.4, cap }),
        }
    }

    /// (ms, verdict, or None for a tick; the message expected then:
    /// action, cause, changes)
    type Row = (u64, Option<Verdict>, Option<(Action, Option<&'static str>, u64)>);

    #[test]
    fn one_message_when_an_intervention_starts_changes_or_ends_at_most_one_per_interval() {
        let command = vel(0.3, 0.0);
        #[rustfmt::skip]
        let table: Vec<Row> = vec![
            (0,    Some(passed(command)), None),                                   // passing: nothing to say
            (10,   Some(fence()), Some((Action::Stopped, Some("geofence"), 1))),    // it starts
            (20,   Some(fence()), None),                                           // held: said already
            (500,  Some(fence()), None),
            (510,  Some(slowed(0.2)), Some((Action::Scaled, Some("slowdown-zone"), 1))), // it changes
            (520,  Some(slowed(0.1)), None),                                       // same cause, new reading
            (530,  Some(passed(command)), None),                                   // ended, but too soon:
            (600,  None, None),                                                    // owed ...
            (610,  None, Some((Action::Passed, None, 1))),                         // ... sent by a tick
            (620,  Some(fence()), None),                                           // comes and goes
            (630,  Some(passed(command)), None),                                   // within the interval:
            (700,  Some(passed(command)), None),
            (710,  None, Some((Action::Passed, None, 2))),                         // summed up
            (800,  None, None),                                                    // nothing owed
            (900,  Some(fence()), Some((Action::Stopped, Some("geofence"), 1))),
        ];
        let mut notices = Notices::default();
        for (ms, verdict, expected) in table {
            let sent = match &verdict {
                Some(verdict) => notices.note(command, verdict, ms * MS),
                None => notices.due(ms * MS),
            };
            assert_eq!(sent.as_ref().map(|n| (n.action, n.cause, n.changes)), expected, "at {ms} ms");
        }
    }

    #[test]
    fn a_message_carries_the_reading_and_the_commands() {
        let mut notices = Notices::default();
        let notice = notices.note(vel(0.3, 0.0), &fence(), 1_500 * MS);
        let json = notice.map(|n| serde_json::to_value(n).unwrap_or_default()).unwrap_or_default();
        assert_eq!(
            json,
            serde_json::json!({
                "at_s": 1.5, "action": "stopped", "cause": "geofence",
                "reading": {"edge_m": 0.25, "outside": false},
                "command": "VEL 0.3 0.0", "output": "STOP",
                "text": "stopped VEL 0.3 0.0: geofence: edge 0.25 m away", "changes": 1
            })
        );
    }
}
