//! The owner's task and a run's score, as stored (docs/lab.md, "Tasks and
//! scores"): what a submission is measured by, and what it measured. The
//! score is computed from the run's recording alone (`crate::score`), so
//! anyone with the bundle recomputes it bit for bit.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

/// Longest task name and description.
pub const MAX_TASK_NAME: usize = 64;
pub const MAX_TASK_DESCRIPTION: usize = 2000;

/// A task: a goal region, and the metric a run is ranked by.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct Task {
    /// `[a-z0-9-]`, 1 to 64.
    pub name: String,
    #[serde(default)]
    pub description: String,
    pub goal: Goal,
    pub metric: Metric,
    /// The scoring component whose score is the metric (with
    /// [`Metric::Scorer`], and only then).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub scorer: Option<ScorerRef>,
    /// The output port whose poses `[x, y, heading]` are the robot's
    /// (`COMPONENT.PORT`).
    #[serde(default = "default_pose_port")]
    pub pose: String,
    /// The output port whose commands reach the motors (energy).
    #[serde(default = "default_commands_port")]
    pub commands: String,
    /// The output port whose range readings a scoring component reads
    /// (a scan or a vector of ranges).
    #[serde(default = "default_ranges_port")]
    pub ranges: String,
    /// The distance between the wheels (m), for the commanded wheel speeds.
    #[serde(default = "default_wheel_base_m")]
    pub wheel_base_m: f64,
    /// Which run of each user the leaderboard ranks.
    #[serde(default)]
    pub board: BoardChoice,
    /// Whether the leaderboard shows other users by pseudonym
    /// (`participant-N`) rather than by name (admins always see names).
    #[serde(default = "default_pseudonyms")]
    pub pseudonyms: bool,
    /// What ends a run before its duration (its time out, always): the
    /// robot at the goal, its first collision. None (the default): only
    /// its duration.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub end_on: Vec<EndCondition>,
}

/// A task's end condition: what ends a run (an episode) before its
/// duration.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Serialize, schemars::JsonSchema)]
#[serde(rename_all = "kebab-case")]
pub enum EndCondition {
    /// A pose of the task's `pose` port within the goal's radius.
    Goal,
    /// The first collision the simulator counts.
    Collision,
}

impl EndCondition {
    pub const ALL: [EndCondition; 2] = [EndCondition::Goal, EndCondition::Collision];

    /// Its name in the settings.
    pub fn name(self) -> &'static str {
        match self {
            EndCondition::Goal => "goal",
            EndCondition::Collision => "collision",
        }
    }
}

/// An unknown name is refused naming the field it is in (a plain enum
/// would name only the variant).
impl<'de> Deserialize<'de> for EndCondition {
    fn deserialize<D: serde::Deserializer<'de>>(deserializer: D) -> Result<EndCondition, D::Error> {
        let name = String::deserialize(deserializer)?;
        EndCondition::ALL.into_iter().find(|c| c.name() == name).ok_or_else(|| {
            serde::de::Error::custom(format!(
                "task.end_on: unknown end condition '{}' (expected goal or collision)",
                crate::contract::clip(&name)
            ))
        })
    }
}

/// Why a run (an episode) ended, as its outcome says (`run.outcome.ended_by`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(rename_all = "kebab-case")]
pub enum EpisodeEnd {
    /// The robot reached the task's goal (its end condition `goal`).
    Goal,
    /// Its first collision (the end condition `collision`).
    Collision,
    /// Its duration passed.
    TimeOut,
}

impl EpisodeEnd {
    /// Its name in the record.
    pub fn name(self) -> &'static str {
        match self {
            EpisodeEnd::Goal => "goal",
            EpisodeEnd::Collision => "collision",
            EpisodeEnd::TimeOut => "time-out",
        }
    }

    /// The end condition that ends a run this way.
    pub fn of(condition: EndCondition) -> EpisodeEnd {
        match condition {
            EndCondition::Goal => EpisodeEnd::Goal,
            EndCondition::Collision => EpisodeEnd::Collision,
        }
    }
}

/// Which of a user's scored runs the leaderboard ranks.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(rename_all = "lowercase")]
pub enum BoardChoice {
    /// Their best by the metric.
    #[default]
    Best,
    /// Their latest.
    Latest,
}

fn default_pseudonyms() -> bool {
    true
}

/// A disc the robot must reach.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct Goal {
    pub x: f64,
    pub y: f64,
    pub radius: f64,
}

impl Goal {
    /// Whether (`x`, `y`) is within its radius (the score's `goal_reached`
    /// and the end condition `goal` alike).
    pub fn contains(&self, x: f64, y: f64) -> bool {
        (x - self.x).hypot(y - self.y) <= self.radius
    }
}

/// A task's scoring component (the `scorer` world of `wit/robot.wit`): an
/// upload of the `scorer` world named `OWNER/NAME`, pinned by its sha256,
/// so a task always scores with the bytes its owner chose (a new upload of
/// the same name is refused until the task names its sha256).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct ScorerRef {
    /// The upload, `OWNER/NAME`.
    pub component: String,
    /// The hex sha256 of its bytes.
    pub sha256: String,
    /// Whether a higher score ranks first (else a lower one does).
    #[serde(default)]
    pub higher_is_better: bool,
}

/// What a run is ranked by (built in; each is also a sub-score; or the
/// task's scoring component).
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum Metric {
    /// Seconds from the run's start to the first pose inside the goal
    /// (lower is better; none when it never got there).
    TimeToGoal,
    /// 1 when a pose was inside the goal, else 0 (higher is better).
    GoalReached,
    /// Metres between successive poses (lower is better).
    PathLength,
    /// Contacts the simulator counted (lower is better; simulated robots).
    Collisions,
    /// The envelope's interventions, every cause (lower is better).
    Interventions,
    /// The integral of the squared commanded wheel speeds, m^2/s (lower
    /// is better).
    Energy,
    /// The score of the task's scoring component (its `scorer`); the
    /// sub-scores are the component's.
    Scorer,
}

impl Metric {
    /// Whether a higher value ranks first (else a lower one does), for a
    /// built-in metric ([`Task::higher_is_better`] for any).
    pub fn higher_is_better(self) -> bool {
        self == Metric::GoalReached
    }

    /// Its name as a sub-score.
    pub fn name(self) -> &'static str {
        match self {
            Metric::TimeToGoal => "time_to_goal_s",
            Metric::GoalReached => "goal_reached",
            Metric::PathLength => "path_length_m",
            Metric::Collisions => "collisions",
            Metric::Interventions => "interventions",
            Metric::Energy => "energy",
            Metric::Scorer => "score",
        }
    }
}

impl Task {
    /// Whether a higher value of its metric ranks first.
    pub fn higher_is_better(&self) -> bool {
        match (&self.metric, &self.scorer) {
            (Metric::Scorer, Some(scorer)) => scorer.higher_is_better,
            (metric, _) => metric.higher_is_better(),
        }
    }
}

fn default_pose_port() -> String {
    "motors.pose".into()
}

fn default_commands_port() -> String {
    "envelope.cmd".into()
}

fn default_ranges_port() -> String {
    "motors.ranges".into()
}

fn default_wheel_base_m() -> f64 {
    0.3
}

/// A run's score (`score.json` in its bundle): the task's metric and
/// every sub-score, from its recording.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
pub struct Score {
    pub task: String,
    pub metric: Metric,
    /// The metric's value (`None`: undefined for this run, e.g. the time
    /// to a goal never reached, or collisions without a simulator).
    pub value: Option<f64>,
    /// Every sub-score that the recording defines, by name (with
    /// [`Metric::Scorer`], the scoring component's).
    pub sub_scores: BTreeMap<String, f64>,
    /// With [`Metric::Scorer`], the built-in metrics beside the
    /// component's (the same names as a built-in metric's sub-scores), so
    /// runs scored by a component still compare on them; empty otherwise
    /// (they are `sub_scores` then).
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub built_in: BTreeMap<String, f64>,
    /// The poses and commands it was computed from, and the recording's
    /// length (s), for a reader to check it against.
    pub poses: u64,
    pub commands: u64,
    pub recorded_s: f64,
    /// The sha256 of the recording it was computed from (its files, in
    /// order, as one stream): `run.mcap`'s line of the bundle's
    /// `SHA256SUMS` when it is one file.
    pub recording_sha256: String,
    /// The sha256 of the scoring component that computed it (the bundle's
    /// `scorer.wasm`), with [`Metric::Scorer`].
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub scorer_sha256: Option<String>,
}
