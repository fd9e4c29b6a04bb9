//! The preflight's verdict: what a run in the simulator saw, judged
//! against the owner's criteria (docs/lab.md). Pure: the run hands in what
//! it observed (contacts, faults, the envelope's interventions, who held
//! control when), [`judge`] says whether it passes and names every reason,
//! with its time, place and holder: `preflight: collision at 12.4 s at
//! (3.10, 2.02) while 'my-planner' held control`.
//!
//! `subsume run --verdict FILE` writes it (the preflight is such a run in a
//! process of its own), so a researcher's `subsume run robot.xml --speed
//! max` on the lab kit gives the verdict the lab would.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

use crate::sim::physics::Contact;
pub use crate::store::experiments::Criteria;
use crate::store::experiments::RunOutcome;

/// Holder changes kept by a run (past it, the holder is unknown): a holder
/// switching every cycle for an hour must not grow the run's memory.
pub const MAX_HOLDER_CHANGES: usize = 10_000;

/// Who held control when: each change, in time order (seconds of graph
/// time; `None`: nobody).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct HolderTimeline {
    pub changes: Vec<(f64, Option<String>)>,
    /// Changes past [`MAX_HOLDER_CHANGES`] were not kept.
    pub truncated: bool,
}

impl HolderTimeline {
    /// Records that `holder` holds control from `at_s` on (nothing when it
    /// is the same holder).
    pub fn note(&mut self, at_s: f64, holder: Option<&str>) {
        if self.changes.last().map(|(_, h)| h.as_deref()) == Some(holder) {
            return;
        }
        if self.changes.len() >= MAX_HOLDER_CHANGES {
            self.truncated = true;
            return;
        }
        self.changes.push((at_s, holder.map(str::to_string)));
    }

    /// Who held control at `at_s`: `None` for nobody, or when it is not
    /// known (before the first change, or past the kept ones).
    pub fn at(&self, at_s: f64) -> Option<&str> {
        if self.truncated && self.changes.last().is_some_and(|(t, _)| *t <= at_s) {
            return None;
        }
        self.changes.iter().rev().find(|(t, _)| *t <= at_s).and_then(|(_, h)| h.as_deref())
    }
}

/// A component that faulted during the run.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Fault {
    pub component: String,
    pub at_s: f64,
    pub reason: String,
}

/// The envelope's interventions of one cause (`stop-zone`, `geofence`, ...).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Interventions {
    pub count: u64,
    /// When the first one happened (graph seconds), if known.
    pub first_at_s: Option<f64>,
    /// Its text (`stopped VEL 0.45 0.0: obstacle 0.18 m ahead, ...`).
    pub first: Option<String>,
}

/// What a run saw.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Observations {
    /// Graph seconds it ran.
    pub simulated_s: f64,
    /// Collisions counted by the simulated robots.
    pub collisions: u64,
    /// The first ones, with time (simulated seconds) and place.
    pub contacts: Vec<ContactAt>,
    pub faults: Vec<Fault>,
    /// The envelope's interventions, by cause.
    pub envelope: BTreeMap<String, Interventions>,
    pub holders: HolderTimeline,
    /// Whether the goal of the world was reached (information).
    pub goal_reached: Option<bool>,
    /// Why the run ended, when it ran with the task's end conditions
    /// (`subsume run --task`): at the goal, at its first collision, or at
    /// its duration.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ended_by: Option<crate::store::task::EpisodeEnd>,
}

/// A contact and the simulated robot it happened to.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ContactAt {
    pub robot: String,
    pub time_s: f64,
    pub x: f64,
    pub y: f64,
}

impl ContactAt {
    pub fn of(robot: &str, contact: &Contact) -> ContactAt {
        ContactAt { robot: robot.to_string(), time_s: contact.time_s, x: contact.x, y: contact.y }
    }
}

/// The verdict: passed, or every reason it did not.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Verdict {
    pub passed: bool,
    pub reasons: Vec<String>,
    pub criteria: Criteria,
    pub observed: Observations,
}

/// The envelope's cause for an obstacle inside the stop zone.
pub const STOP_ZONE: &str = "stop-zone";
/// The envelope's cause for the geofence.
pub const GEOFENCE: &str = "geofence";

fn while_held(holders: &HolderTimeline, at_s: f64) -> String {
    match holders.at(at_s) {
        Some(holder) => format!(" while '{holder}' held control"),
        None => " while no source held control".to_string(),
    }
}

/// Judges what a run saw against `criteria`.
pub fn judge(criteria: &Criteria, observed: Observations) -> Verdict {
    let mut reasons = Vec::new();
    if observed.collisions > u64::from(criteria.max_collisions) {
        for contact in &observed.contacts {
            reasons.push(format!(
                "preflight: collision at {:.1} s at ({:.2}, {:.2}){}",
                contact.time_s,
                contact.x,
                contact.y,
                while_held(&observed.holders, contact.time_s)
            ));
        }
        let unlisted = observed.collisions.saturating_sub(observed.contacts.len() as u64);
        if unlisted > 0 || observed.contacts.is_empty() {
            reasons.push(format!(
                "preflight: {} collisions in all (at most {} allowed)",
                observed.collisions, criteria.max_collisions
            ));
        }
    }
    if !criteria.allow_faults {
        for fault in &observed.faults {
            reasons.push(format!(
                "preflight: component '{}' faulted at {:.1} s: {}",
                fault.component, fault.at_s, fault.reason
            ));
        }
    }
    let mut envelope = |cause: &str, what: &str| {
        if let Some(seen) = observed.envelope.get(cause).filter(|s| s.count > 0) {
            let first = match (seen.first_at_s, &seen.first) {
                (Some(at), Some(text)) => format!(", first at {at:.1} s{} ({text})", while_held(&observed.holders, at)),
                (Some(at), None) => format!(", first at {at:.1} s{}", while_held(&observed.holders, at)),
                _ => String::new(),
            };
            let times = if seen.count == 1 { "once".to_string() } else { format!("{} times", seen.count) };
            reasons.push(format!("preflight: {what} {times}{first}"));
        }
    };
    if !criteria.allow_geofence {
        envelope(GEOFENCE, "the envelope held the robot at its geofence");
    }
    if !criteria.allow_stop_zone {
        envelope(STOP_ZONE, "the envelope's stop zone stopped the robot");
    }
    Verdict { passed: reasons.is_empty(), reasons, criteria: *criteria, observed }
}

/// The first way a run on the robot, as `outcome` says so far, breaks
/// `criteria` (what `end_run_on_breach` ends it for); `None` while it
/// keeps them.
pub fn breach(criteria: &Criteria, outcome: &RunOutcome) -> Option<String> {
    if !criteria.allow_faults
        && let Some(fault) = outcome.faults.first()
    {
        let at = fault.at_s.map(|s| format!(" at {s:.1} s")).unwrap_or_default();
        return Some(format!("component '{}' faulted{at}: {}", fault.component, fault.reason));
    }
    if outcome.collisions > u64::from(criteria.max_collisions) {
        return Some(format!("{} collisions (at most {} allowed)", outcome.collisions, criteria.max_collisions));
    }
    let fired = |cause: &str| {
        outcome.interventions.get(cause).copied().filter(|n| *n > 0).map(|n| match n {
            1 => "once".to_string(),
            n => format!("{n} times"),
        })
    };
    if !criteria.allow_stop_zone
        && let Some(n) = fired(STOP_ZONE)
    {
        return Some(format!("the envelope's stop zone stopped the robot {n}"));
    }
    if !criteria.allow_geofence
        && let Some(n) = fired(GEOFENCE)
    {
        return Some(format!("the envelope held the robot at its geofence {n}"));
    }
    None
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::store::experiments::FaultSeen;

    fn timeline(changes: &[(f64, Option<&str>)]) -> HolderTimeline {
        let mut t = HolderTimeline::default();
        for (at, holder) in changes {
            t.note(*at, *holder);
        }
        t
    }

    #[test]
    fn the_timeline_says_who_held_control_when() {
        let t = timeline(&[(0.0, None), (1.0, Some("planner")), (1.5, Some("planner")), (3.0, Some("avoid"))]);
        assert_eq!(t.changes.len(), 3, "a repeated holder is one change");
        assert_eq!(t.at(0.5), None);
        assert_eq!(t.at(1.0), Some("planner"));
        assert_eq!(t.at(2.9), Some("planner"));
        assert_eq!(t.at(10.0), Some("avoid"));
        let mut full = HolderTimeline::default();
        for i in 0..MAX_HOLDER_CHANGES + 5 {
            full.note(i as f64, Some(if i % 2 == 0 { "a" } else { "b" }));
        }
        assert_eq!(full.changes.len(), MAX_HOLDER_CHANGES);
        assert!(full.truncated);
        assert_eq!(full.at(5.0), Some("b"));
        assert_eq!(full.at(1e9), None, "past the kept changes the holder is unknown");
    }

    fn observed() -> Observations {
        Observations {
            simulated_s: 60.0,
            holders: timeline(&[(0.0, Some("my-planner")), (20.0, Some("avoid"))]),
            ..Observations::default()
        }
    }

    /// (case, criteria, what was seen, the reasons expected).
    #[test]
    fn every_reason_is_named_with_its_time_place_and_holder() {
        let strict = Criteria::default();
        let contact = ContactAt { robot: "sim".into(), time_s: 12.44, x: 3.1, y: 2.02 };
        let fault = Fault { component: "my-planner".into(), at_s: 3.25, reason: "tick: trapped".into() };
        let stops = Interventions { count: 3, first_at_s: Some(21.0), first: Some("stopped VEL 0.4 0".into()) };
        let fence = Interventions { count: 1, first_at_s: Some(5.0), first: None };
        type Case = (&'static str, Criteria, Observations, Vec<&'static str>);
        let cases: Vec<Case> = vec![
            ("nothing happened", strict, observed(), vec![]),
            (
                "a collision",
                strict,
                Observations { collisions: 1, contacts: vec![contact.clone()], ..observed() },
                vec!["preflight: collision at 12.4 s at (3.10, 2.02) while 'my-planner' held control"],
            ),
            (
                "more collisions than kept",
                strict,
                Observations { collisions: 20, contacts: vec![contact.clone()], ..observed() },
                vec![
                    "preflight: collision at 12.4 s at (3.10, 2.02) while 'my-planner' held control",
                    "preflight: 20 collisions in all (at most 0 allowed)",
                ],
            ),
            (
                "collisions the owner allows",
                Criteria { max_collisions: 1, ..strict },
                Observations { collisions: 1, contacts: vec![contact], ..observed() },
                vec![],
            ),
            (
                "a fault",
                strict,
                Observations { faults: vec![fault.clone()], ..observed() },
                vec!["preflight: component 'my-planner' faulted at 3.2 s: tick: trapped"],
            ),
            (
                "a fault allowed",
                Criteria { allow_faults: true, ..strict },
                Observations { faults: vec![fault], ..observed() },
                vec![],
            ),
            (
                "stop zone and geofence",
                strict,
                Observations {
                    envelope: BTreeMap::from([(STOP_ZONE.into(), stops.clone()), (GEOFENCE.into(), fence.clone())]),
                    ..observed()
                },
                vec![
                    "preflight: the envelope held the robot at its geofence once, first at 5.0 s while 'my-planner' held control",
                    "preflight: the envelope's stop zone stopped the robot 3 times, first at 21.0 s while 'avoid' held control (stopped VEL 0.4 0)",
                ],
            ),
            (
                "both allowed",
                Criteria { allow_geofence: true, allow_stop_zone: true, ..strict },
                Observations {
                    envelope: BTreeMap::from([(STOP_ZONE.into(), stops), (GEOFENCE.into(), fence)]),
                    ..observed()
                },
                vec![],
            ),
        ];
        for (case, criteria, seen, expected) in cases {
            let verdict = judge(&criteria, seen);
            assert_eq!(verdict.reasons, expected, "{case}");
            assert_eq!(verdict.passed, expected.is_empty(), "{case}");
        }
    }

    #[test]
    fn a_run_on_the_robot_breaks_the_criteria_by_its_first_breach() {
        let strict = Criteria::default();
        let lenient =
            Criteria { max_collisions: 2, allow_faults: true, allow_geofence: true, allow_stop_zone: true, ..strict };
        let fault = FaultSeen { component: "planner".into(), at_s: Some(3.26), reason: "trapped".into() };
        let outcome = |faults: Vec<FaultSeen>, collisions: u64, kinds: &[(&str, u64)]| RunOutcome {
            faults,
            collisions,
            interventions: kinds.iter().map(|(c, n)| (c.to_string(), *n)).collect(),
            goal_reached: None,
            ended_by: None,
        };
        let cases = [
            (strict, outcome(vec![], 0, &[("acceleration", 9)]), None),
            (strict, outcome(vec![fault.clone()], 3, &[]), Some("component 'planner' faulted at 3.3 s: trapped")),
            (lenient, outcome(vec![fault.clone()], 2, &[(STOP_ZONE, 4)]), None),
            (lenient, outcome(vec![], 3, &[]), Some("3 collisions (at most 2 allowed)")),
            (strict, outcome(vec![], 0, &[(STOP_ZONE, 4)]), Some("the envelope's stop zone stopped the robot 4 times")),
            (strict, outcome(vec![], 0, &[(GEOFENCE, 1)]), Some("the envelope held the robot at its geofence once")),
        ];
        for (criteria, outcome, want) in cases {
            assert_eq!(breach(&criteria, &outcome).as_deref(), want, "{criteria:?} {outcome:?}");
        }
    }
}
