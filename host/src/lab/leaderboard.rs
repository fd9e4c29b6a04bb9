//! A task's leaderboard (docs/lab.md, "Leaderboard"): each user's best
//! (or latest, the owner's choice) scored run of the owner's task, ranked
//! by the task's metric, with its sub-scores, the preflight's value beside
//! it (the simulator against the robot), when it ran and the sha256 of the
//! recording its score came from: anyone with that bundle recomputes it.
//!
//! [`rank`] is the pure decision over the records; [`Lab::leaderboard`]
//! asks it of the lab's book. Others are shown by pseudonym
//! (`participant-N`, N by their first scored run) unless the owner turned
//! pseudonyms off; a user always sees her own name and her experiments'
//! ids, admins everyone's.

use std::collections::BTreeMap;

use serde::Serialize;

use super::{Lab, LabError};
use crate::store::experiments::{ExperimentRecord, ExperimentState};
use crate::store::task::{BoardChoice, Metric, Score, Task};
use crate::store::users::{Principal, Role};

/// A leaderboard as its reader sees it.
#[derive(Clone, Debug, PartialEq, Serialize, schemars::JsonSchema)]
pub struct Board {
    pub task: String,
    pub description: String,
    pub metric: Metric,
    /// `lower` or `higher`: which ranks first.
    #[schemars(extend("enum" = ["lower", "higher"]))]
    pub better: &'static str,
    pub board: BoardChoice,
    pub entries: Vec<Entry>,
}

/// One user's ranked run.
#[derive(Clone, Debug, PartialEq, Serialize, schemars::JsonSchema)]
pub struct Entry {
    /// 1 for the first; `None` for a run whose metric is undefined (a goal
    /// never reached): listed after the ranked ones.
    pub rank: Option<usize>,
    /// The user's name, or her pseudonym (`participant-N`) when the owner
    /// shows pseudonyms; the reader's own, and for admins every one, by name.
    pub user: String,
    /// Whether it is the reader's own.
    pub yours: bool,
    /// The experiment (its id): the reader's own, or any for admins.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub experiment: Option<u64>,
    pub value: Option<f64>,
    pub sub_scores: BTreeMap<String, f64>,
    /// The preflight's value of the same metric (the simulator's side).
    pub preflight_value: Option<f64>,
    /// `value` less `preflight_value`.
    pub gap: Option<f64>,
    /// When the run ended (ms since the Unix epoch).
    pub ended_ms: u64,
    /// The sha256 of the recording the score came from (`run.mcap` in its
    /// bundle).
    pub recording_sha256: String,
}

/// `a` ranks before `b` by a metric where `higher` values are better, or
/// lower ones (defined values first; ties: the earlier experiment).
fn before(higher: bool, a: (Option<f64>, u64), b: (Option<f64>, u64)) -> std::cmp::Ordering {
    use std::cmp::Ordering;
    let by_value = match (a.0, b.0) {
        (Some(x), Some(y)) if higher => y.total_cmp(&x),
        (Some(x), Some(y)) => x.total_cmp(&y),
        (Some(_), None) => Ordering::Less,
        (None, Some(_)) => Ordering::Greater,
        (None, None) => Ordering::Equal,
    };
    by_value.then(a.1.cmp(&b.1))
}

/// The leaderboard of `task` over `records` as `reader` sees it: the runs
/// that ended `done` with a score of this task, each submitter's best (or
/// latest), ranked.
pub fn rank<'r>(task: &Task, records: impl Iterator<Item = &'r ExperimentRecord>, reader: &Principal) -> Board {
    // A task scored by a component ranks only the scores of its bytes.
    let scorer_sha256 = task.scorer.as_ref().map(|s| s.sha256.clone());
    let scored: Vec<(&ExperimentRecord, &Score)> = records
        .filter(|r| r.state == ExperimentState::Done)
        .filter_map(|r| {
            r.score
                .as_ref()
                .filter(|s| s.task == task.name && s.metric == task.metric && s.scorer_sha256 == scorer_sha256)
                .map(|s| (r, s))
        })
        .collect();
    // Pseudonyms by each user's first scored run.
    let mut firsts: Vec<(u64, &str)> = Vec::new();
    for (record, _) in &scored {
        match firsts.iter_mut().find(|(_, user)| *user == record.submitter) {
            Some(first) => first.0 = first.0.min(record.id),
            None => firsts.push((record.id, &record.submitter)),
        }
    }
    firsts.sort();
    let ended = |r: &ExperimentRecord| r.run.as_ref().map_or(0, |run| run.ended_ms);
    let mut chosen: BTreeMap<&str, (&ExperimentRecord, &Score)> = BTreeMap::new();
    for (record, score) in scored {
        let better = match chosen.get(record.submitter.as_str()) {
            None => true,
            Some((held, held_score)) => match task.board {
                BoardChoice::Best => {
                    before(task.higher_is_better(), (score.value, record.id), (held_score.value, held.id)).is_lt()
                }
                BoardChoice::Latest => (ended(record), record.id) > (ended(held), held.id),
            },
        };
        if better {
            chosen.insert(&record.submitter, (record, score));
        }
    }
    let mut runs: Vec<(&ExperimentRecord, &Score)> = chosen.into_values().collect();
    runs.sort_by(|(a, sa), (b, sb)| before(task.higher_is_better(), (sa.value, a.id), (sb.value, b.id)));
    let sees_names = reader.role == Role::Admin || !task.pseudonyms;
    let mut ranked = 0;
    let entries = runs
        .into_iter()
        .map(|(record, score)| {
            let yours = record.submitter == reader.name;
            let user = if sees_names || yours {
                record.submitter.clone()
            } else {
                let n = firsts.iter().position(|(_, u)| *u == record.submitter).map_or(0, |p| p + 1);
                format!("participant-{n}")
            };
            let rank = score.value.map(|_| {
                ranked += 1;
                ranked
            });
            let preflight_value = record.preflight.as_ref().and_then(|p| p.score.as_ref()).and_then(|s| s.value);
            Entry {
                rank,
                user,
                yours,
                experiment: (yours || reader.role == Role::Admin).then_some(record.id),
                value: score.value,
                gap: score.value.zip(preflight_value).map(|(real, simulated)| real - simulated),
                preflight_value,
                sub_scores: score.sub_scores.clone(),
                ended_ms: ended(record),
                recording_sha256: score.recording_sha256.clone(),
            }
        })
        .collect();
    Board {
        task: task.name.clone(),
        description: task.description.clone(),
        metric: task.metric,
        better: if task.higher_is_better() { "higher" } else { "lower" },
        board: task.board,
        entries,
    }
}

impl Lab {
    /// The leaderboard of the owner's task `name`, as `reader` sees it
    /// (any user of the lab).
    pub fn leaderboard(&self, reader: &Principal, name: &str) -> Result<Board, LabError> {
        let book = self.lock()?;
        let task = book
            .lab
            .settings
            .task
            .as_ref()
            .filter(|t| t.name == name)
            .ok_or_else(|| LabError::NotFound(format!("no task '{}' in this lab", crate::contract::clip(name))))?;
        Ok(rank(task, book.experiments.values(), reader))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::store::experiments::{AppliedSettings, LabSettings, NewExperiment, PreflightResult, RunResult};
    use crate::store::task::Goal;

    fn task(metric: Metric, board: BoardChoice, pseudonyms: bool) -> Task {
        Task {
            name: "reach".into(),
            description: "get there".into(),
            goal: Goal { x: 1.0, y: 1.0, radius: 0.3 },
            metric,
            scorer: None,
            pose: "motors.pose".into(),
            commands: "envelope.cmd".into(),
            ranges: "motors.ranges".into(),
            wheel_base_m: 0.3,
            board,
            pseudonyms,
            end_on: Vec::new(),
        }
    }

    /// Experiment `id` of `user`, ended at `ended_ms` in `state`, scored
    /// `value` (and `simulated` in its preflight) against task `reach`.
    fn run(
        id: u64,
        user: &str,
        state: ExperimentState,
        value: Option<f64>,
        simulated: Option<f64>,
    ) -> ExperimentRecord {
        let settings = AppliedSettings::of(&LabSettings::default(), 1);
        let new = NewExperiment {
            submitter: user.into(),
            set: 1,
            label: String::new(),
            duration_s: 1.0,
            submitted_ms: id,
            settings,
            components: Vec::new(),
        };
        let mut record = ExperimentRecord::new(new, state, "test");
        record.id = id;
        let score = |value: Option<f64>| Score {
            task: "reach".into(),
            metric: Metric::TimeToGoal,
            value,
            sub_scores: value.map(|v| ("time_to_goal_s".to_string(), v)).into_iter().collect(),
            poses: 1,
            commands: 0,
            recorded_s: 1.0,
            recording_sha256: format!("sha-{id}"),
            built_in: Default::default(),
            scorer_sha256: None,
        };
        record.score = Some(score(value));
        record.preflight = simulated.map(|s| PreflightResult {
            passed: true,
            reasons: Vec::new(),
            simulated_s: 1.0,
            wall_s: 1.0,
            replay: None,
            score: Some(score(Some(s))),
            ended_by: None,
        });
        record.run = Some(RunResult { ended_ms: 1000 + id, ..RunResult::default() });
        record
    }

    fn reader(name: &str, role: Role) -> Principal {
        Principal { name: name.into(), role, platforms: Vec::new() }
    }

    /// (user shown, rank, value, experiment shown) of an entry.
    type Shown = (String, Option<usize>, Option<f64>, Option<u64>);

    fn shown(board: &Board) -> Vec<Shown> {
        board.entries.iter().map(|e| (e.user.clone(), e.rank, e.value, e.experiment)).collect()
    }

    fn runs() -> Vec<ExperimentRecord> {
        use ExperimentState::*;
        vec![
            run(1, "ana", Done, Some(20.0), Some(18.0)),
            run(2, "ben", Done, None, None),
            run(3, "ana", Done, Some(15.0), None),
            run(4, "cy", Aborted, Some(1.0), None),
            run(5, "cy", Done, Some(17.5), Some(17.0)),
            run(6, "ana", Done, Some(19.0), None),
            run(7, "dee", Done, Some(17.5), None),
        ]
    }

    #[test]
    fn each_users_best_or_latest_done_run_is_ranked_by_the_metric_the_undefined_last() {
        let runs = runs();
        let admin = reader("boss", Role::Admin);
        let o = |u: &str, rank: Option<usize>, value: Option<f64>, id: u64| (u.to_string(), rank, value, Some(id));
        let cases = [
            (
                "best: ana's 15 of three, cy's aborted 1 not counted, a tie by the earlier run, ben never reached it",
                BoardChoice::Best,
                vec![
                    o("ana", Some(1), Some(15.0), 3),
                    o("cy", Some(2), Some(17.5), 5),
                    o("dee", Some(3), Some(17.5), 7),
                    o("ben", None, None, 2),
                ],
            ),
            (
                "latest: ana's last run",
                BoardChoice::Latest,
                vec![
                    o("cy", Some(1), Some(17.5), 5),
                    o("dee", Some(2), Some(17.5), 7),
                    o("ana", Some(3), Some(19.0), 6),
                    o("ben", None, None, 2),
                ],
            ),
        ];
        for (case, choice, expected) in cases {
            let board = rank(&task(Metric::TimeToGoal, choice, true), runs.iter(), &admin);
            assert_eq!(shown(&board), expected, "{case}");
        }
        let board = rank(&task(Metric::TimeToGoal, BoardChoice::Best, true), runs.iter(), &admin);
        assert_eq!((board.entries[1].preflight_value, board.entries[1].gap), (Some(17.0), Some(0.5)));
        assert_eq!(board.entries[1].recording_sha256, "sha-5");
    }

    #[test]
    fn others_are_pseudonyms_by_their_first_run_unless_the_owner_shows_names() {
        let runs = runs();
        let p = |u: &str, id: Option<u64>| (u.to_string(), id);
        let seen = |board: Board| board.entries.iter().map(|e| (e.user.clone(), e.experiment)).collect::<Vec<_>>();
        let task_with = |pseudonyms| task(Metric::TimeToGoal, BoardChoice::Best, pseudonyms);
        let cases = [
            (
                "ben, pseudonyms on: his own name and id, the others by their first run (ana 1, ben 2, cy 5, dee 7)",
                task_with(true),
                reader("ben", Role::Researcher),
                vec![p("participant-1", None), p("participant-3", None), p("participant-4", None), p("ben", Some(2))],
            ),
            (
                "ben, pseudonyms off: names, but only his own id",
                task_with(false),
                reader("ben", Role::Researcher),
                vec![p("ana", None), p("cy", None), p("dee", None), p("ben", Some(2))],
            ),
            (
                "an admin: names and ids",
                task_with(true),
                reader("boss", Role::Admin),
                vec![p("ana", Some(3)), p("cy", Some(5)), p("dee", Some(7)), p("ben", Some(2))],
            ),
        ];
        for (case, task, reader, expected) in cases {
            assert_eq!(seen(rank(&task, runs.iter(), &reader)), expected, "{case}");
        }
    }

    #[test]
    fn a_higher_is_better_metric_ranks_the_highest_first() {
        let mut runs = runs();
        for record in &mut runs {
            if let Some(score) = &mut record.score {
                score.metric = Metric::GoalReached;
                score.value = Some(if record.submitter == "ben" { 1.0 } else { 0.0 });
            }
        }
        let board =
            rank(&task(Metric::GoalReached, BoardChoice::Best, false), runs.iter(), &reader("boss", Role::Admin));
        assert_eq!(board.better, "higher");
        assert_eq!(board.entries[0].user, "ben");
        assert_eq!(board.entries.iter().map(|e| e.rank).collect::<Vec<_>>(), [Some(1), Some(2), Some(3), Some(4)]);
    }

    #[test]
    fn runs_scored_against_another_task_or_metric_are_not_on_the_board() {
        let mut runs = runs();
        if let Some(score) = &mut runs[0].score {
            score.task = "other".into();
        }
        if let Some(score) = &mut runs[2].score {
            score.metric = Metric::Energy;
        }
        let board =
            rank(&task(Metric::TimeToGoal, BoardChoice::Best, false), runs.iter(), &reader("boss", Role::Admin));
        assert_eq!(board.entries[0].experiment, Some(5), "ana's 15 was scored by another metric: {board:#?}");
        assert_eq!(board.entries.iter().find(|e| e.user == "ana").and_then(|e| e.experiment), Some(6));
    }
}
