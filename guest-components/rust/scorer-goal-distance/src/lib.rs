//! A task's scoring component (the `scorer` world): how close a run ended
//! to the task's goal and how far it drove to get there. Lower is better.
//!
//! - `final_distance_m`: from the last pose to the goal's centre;
//! - `path_length_m`: metres between successive poses;
//! - `reached`: 1 when a pose was inside the goal disc, else 0;
//! - `commands`: the commands recorded;
//! - `interventions`: the envelope's interventions, every cause (its last
//!   count);
//! - `closest_m`: the shortest valid range reading (`[range-min,
//!   range-max)`), when there was one;
//! - the score: `final_distance_m + 0.1 * path_length_m`, so ending at the
//!   goal matters most and a shorter path breaks ties.
//!
//! `tests/python/score_check.py --goal-distance` computes the same from the
//! recording with the `mcap` package.

use subsume_guest::{Episode, Event, Scorer, SubScore, Verdict};

/// What one metre of path costs in the score, against a metre from the goal.
const PATH_WEIGHT: f64 = 0.1;

struct GoalDistance;

impl Scorer for GoalDistance {
    fn score(episode: &Episode) -> Result<Verdict, String> {
        let goal = &episode.goal;
        let mut last: Option<(f64, f64)> = None;
        let mut path_length_m = 0.0;
        let mut reached = false;
        let mut commands = 0u64;
        let mut interventions = 0.0;
        let mut closest: Option<f64> = None;
        for sample in &episode.samples {
            match &sample.event {
                Event::Pose(pose) => {
                    if let Some((x, y)) = last {
                        path_length_m += (pose.x - x).hypot(pose.y - y);
                    }
                    last = Some((pose.x, pose.y));
                    reached |= (pose.x - goal.x).hypot(pose.y - goal.y) <= goal.radius;
                }
                Event::Command(_) => commands += 1,
                Event::Interventions(causes) => interventions = causes.iter().map(|(_, n)| n).sum(),
                Event::Collisions(_) => {}
                Event::Ranges(scan) => {
                    let valid = scan.ranges.iter().filter(|r| **r >= scan.range_min && **r < scan.range_max);
                    for &r in valid {
                        closest = Some(closest.map_or(r, |c: f64| c.min(r)));
                    }
                }
            }
        }
        let Some((x, y)) = last else {
            return Err("the run has no poses".into());
        };
        let final_distance_m = (x - goal.x).hypot(y - goal.y);
        let sub = |name: &str, value: f64| SubScore { name: name.into(), value };
        let mut sub_scores = vec![
            sub("final_distance_m", final_distance_m),
            sub("path_length_m", path_length_m),
            sub("reached", if reached { 1.0 } else { 0.0 }),
            sub("commands", commands as f64),
            sub("interventions", interventions),
        ];
        if let Some(closest) = closest {
            sub_scores.push(sub("closest_m", closest));
        }
        Ok(Verdict { score: final_distance_m + PATH_WEIGHT * path_length_m, sub_scores })
    }
}

subsume_guest::scorer!(GoalDistance);
