//! A task's end conditions (docs/lab.md, "Tasks and scores"): what ends a
//! run, an episode, before its duration (its time out, always). The
//! decision is [`EpisodeWatch::look`], pure over what the run's status
//! sections show look after look ([`Seen`]: the pose the task's `pose`
//! port last reported, the feedback its serial link read so far, the
//! collisions its simulated robots counted). The lab's runner feeds it the
//! robot's live status (every `deploy::LIVE_PERIOD`); a run with `--task`
//! (the preflight) feeds it its own graph's sections at the same period of
//! graph time through [`EndWatch`], so the preflight's episode ends as the
//! robot's would and their scores compare.
//!
//! The goal is watched on the task's `pose` port when it is a serial
//! link's `pose` (its odometry, as the reset by driving reads it); a pose
//! counts once the link read feedback after the first look (a link carried
//! over from the baseline shows the baseline's last pose until then).
//! Collisions count from the first look too.

use crate::report::Report;
use crate::robot::serial::SerialStatus;
use crate::runtime::control_loop::{CycleHook, Shutdown};
use crate::runtime::{Graph, StatusSection};
use crate::sim::SimSection;
use crate::store::task::{EndCondition, EpisodeEnd, Goal, Task};

/// What one look at a run's status sections shows.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Seen {
    /// The pose `[x, y, heading]` of the task's `pose` port, when a serial
    /// link reports it.
    pub pose: Option<[f64; 3]>,
    /// Feedback messages that link has read so far.
    pub feedback: u64,
    /// Collisions the simulated robots counted.
    pub collisions: u64,
}

impl Seen {
    /// What `sections` (each with its component's name) show of the pose
    /// on `pose_port` (`COMPONENT.PORT`) and the collisions.
    pub fn of<'a>(sections: impl IntoIterator<Item = (&'a str, &'a dyn StatusSection)>, pose_port: &str) -> Seen {
        let link = pose_port.strip_suffix(".pose");
        let mut seen = Seen::default();
        for (component, section) in sections {
            if let Some(sim) = section.downcast_ref::<SimSection>() {
                seen.collisions += sim.simulation.collisions;
            }
            if Some(component) == link
                && let Some(serial) = section.downcast_ref::<SerialStatus>()
            {
                seen.pose = serial.pose;
                seen.feedback = serial.feedback_messages;
            }
        }
        seen
    }

    /// What `report` (a live status's) shows.
    pub fn in_report(report: &Report, pose_port: &str) -> Seen {
        Seen::of(report.sections.0.iter().map(|s| (s.component.as_str(), &*s.status)), pose_port)
    }
}

/// A task's end conditions, judged look after look over one run.
#[derive(Clone, Debug)]
pub struct EpisodeWatch {
    conditions: Vec<EndCondition>,
    goal: Goal,
    pose_port: String,
    /// The first look: what the run started with.
    first: Option<Seen>,
}

impl EpisodeWatch {
    /// The watch of `task`'s end conditions; `None` when it has none.
    pub fn new(task: &Task) -> Option<EpisodeWatch> {
        (!task.end_on.is_empty()).then(|| EpisodeWatch {
            conditions: task.end_on.clone(),
            goal: task.goal,
            pose_port: task.pose.clone(),
            first: None,
        })
    }

    /// The port whose poses the goal is judged on.
    pub fn pose_port(&self) -> &str {
        &self.pose_port
    }

    /// The end `seen` shows, if one of the conditions holds: a collision
    /// counted since the first look, or a pose the link read since then
    /// within the goal (a collision first when a look shows both). The
    /// first look only notes where the run started.
    pub fn look(&mut self, seen: Seen) -> Option<EpisodeEnd> {
        let Some(first) = self.first else {
            self.first = Some(seen);
            return None;
        };
        let collided = seen.collisions > first.collisions;
        let at_goal = seen.feedback > first.feedback && seen.pose.is_some_and(|[x, y, _]| self.goal.contains(x, y));
        let fired = |condition| self.conditions.contains(&condition);
        if collided && fired(EndCondition::Collision) {
            return Some(EpisodeEnd::Collision);
        }
        if at_goal && fired(EndCondition::Goal) {
            return Some(EpisodeEnd::Goal);
        }
        None
    }
}

/// Ends a run (`subsume run --task`) when its task's end condition holds:
/// looks at the graph's sections every `period_ns` of graph time, and asks
/// for the run's shutdown at the first end.
pub struct EndWatch {
    watch: EpisodeWatch,
    shutdown: Shutdown,
    period_ns: u64,
    next_look_ns: u64,
    ended: Option<EpisodeEnd>,
}

impl EndWatch {
    /// Watches with `watch`, looking every `deploy::LIVE_PERIOD` (as the
    /// lab's runner sees the robot), ending the run through `shutdown`.
    pub fn new(watch: EpisodeWatch, shutdown: Shutdown) -> EndWatch {
        let period_ns = crate::deploy::LIVE_PERIOD.as_nanos() as u64;
        EndWatch { watch, shutdown, period_ns, next_look_ns: 0, ended: None }
    }

    /// The end that stopped the run, if one did.
    pub fn ended(&self) -> Option<EpisodeEnd> {
        self.ended
    }
}

impl CycleHook for EndWatch {
    fn between_cycles(&mut self, graph: &mut Graph, now_ns: u64) {
        if self.ended.is_some() || now_ns < self.next_look_ns {
            return;
        }
        self.next_look_ns = now_ns.saturating_add(self.period_ns);
        let statuses = graph.statuses();
        let seen = Seen::of(statuses.iter().map(|(name, status)| (*name, &**status)), self.watch.pose_port());
        if let Some(end) = self.watch.look(seen) {
            tracing::info!("the task's end condition ends the run at {:.2} s: {}", now_ns as f64 / 1e9, end.name());
            self.ended = Some(end);
            self.shutdown.request();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::store::task::Metric;

    fn task(end_on: &[EndCondition]) -> Task {
        let json = serde_json::json!({
            "name": "reach", "goal": {"x": 2.0, "y": 1.0, "radius": 0.3}, "metric": "time_to_goal",
            "end_on": end_on.iter().map(|c| c.name()).collect::<Vec<_>>(),
        });
        serde_json::from_value(json).unwrap()
    }

    fn seen(pose: Option<(f64, f64)>, feedback: u64, collisions: u64) -> Seen {
        Seen { pose: pose.map(|(x, y)| [x, y, 0.0]), feedback, collisions }
    }

    /// (case, the task's end conditions, the looks in order, the end each
    /// look gives).
    #[test]
    fn a_run_ends_at_the_first_look_that_shows_one_of_its_end_conditions() {
        use EndCondition::{Collision, Goal as AtGoal};
        let start = seen(Some((1.0, 1.0)), 10, 0);
        let at_goal = seen(Some((2.1, 1.1)), 14, 0);
        type Case = (&'static str, Vec<EndCondition>, Vec<Seen>, Vec<Option<EpisodeEnd>>);
        let cases: Vec<Case> = vec![
            (
                "driving to the goal",
                vec![AtGoal],
                vec![start, seen(Some((1.5, 1.0)), 12, 0), at_goal],
                vec![None, None, Some(EpisodeEnd::Goal)],
            ),
            (
                "the goal's edge is in it",
                vec![AtGoal],
                vec![start, seen(Some((2.3, 1.0)), 11, 0)],
                vec![None, Some(EpisodeEnd::Goal)],
            ),
            ("just outside", vec![AtGoal], vec![start, seen(Some((2.31, 1.0)), 11, 0)], vec![None, None]),
            (
                "a pose carried from before the run (the first look) is not the run's",
                vec![AtGoal],
                vec![seen(Some((2.0, 1.0)), 10, 0), seen(Some((2.0, 1.0)), 10, 0), seen(Some((1.0, 1.0)), 11, 0)],
                vec![None, None, None],
            ),
            ("no pose reported", vec![AtGoal], vec![seen(None, 0, 0), seen(None, 0, 0)], vec![None, None]),
            ("the goal without the condition", vec![Collision], vec![start, at_goal], vec![None, None]),
            (
                "the first collision",
                vec![Collision],
                vec![start, seen(Some((1.2, 1.0)), 12, 1)],
                vec![None, Some(EpisodeEnd::Collision)],
            ),
            (
                "collisions from before the run do not count",
                vec![Collision],
                vec![seen(Some((1.0, 1.0)), 10, 3), seen(Some((1.1, 1.0)), 11, 3)],
                vec![None, None],
            ),
            ("a collision without the condition", vec![AtGoal], vec![start, seen(None, 12, 1)], vec![None, None]),
            (
                "both at one look: the collision",
                vec![AtGoal, Collision],
                vec![start, seen(Some((2.0, 1.0)), 12, 1)],
                vec![None, Some(EpisodeEnd::Collision)],
            ),
        ];
        for (case, conditions, looks, expected) in cases {
            let mut watch = EpisodeWatch::new(&task(&conditions)).unwrap();
            let got: Vec<Option<EpisodeEnd>> = looks.into_iter().map(|s| watch.look(s)).collect();
            assert_eq!(got, expected, "{case}");
        }
        assert!(EpisodeWatch::new(&task(&[])).is_none(), "no end conditions: only the duration");
    }

    #[test]
    fn the_end_conditions_are_read_by_name_and_an_unknown_one_is_refused_naming_the_field() {
        let read = |end_on: serde_json::Value| {
            let json = serde_json::json!({
                "name": "reach", "goal": {"x": 2.0, "y": 1.0, "radius": 0.3}, "metric": "time_to_goal",
                "end_on": end_on,
            });
            serde_json::from_value::<Task>(json).map(|t| t.end_on).map_err(|e| e.to_string())
        };
        assert_eq!(
            read(serde_json::json!(["goal", "collision"])),
            Ok(vec![EndCondition::Goal, EndCondition::Collision])
        );
        let refused = read(serde_json::json!(["goal", "timeout"])).unwrap_err();
        assert!(
            refused.contains("task.end_on: unknown end condition 'timeout' (expected goal or collision)"),
            "{refused}"
        );
        // A task written before end conditions reads as one without, and
        // writes none.
        let old = serde_json::json!({"name": "reach", "goal": {"x": 2.0, "y": 1.0, "radius": 0.3}, "metric": "energy"});
        let task: Task = serde_json::from_value(old).unwrap();
        assert_eq!((task.end_on.len(), task.metric), (0, Metric::Energy));
        assert!(serde_json::to_value(&task).unwrap().get("end_on").is_none());
    }
}
