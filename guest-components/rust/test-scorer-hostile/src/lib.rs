//! A hostile scoring component for the tests (the `scorer` world): what it
//! does depends on the task's name.
//!
//! - `...loops...`: never returns (its budget stops it);
//! - `...traps...`: panics (a trap);
//! - `...nan...`: returns NaN as the score;
//! - `...hoards...`: allocates without end (its memory limit stops it);
//! - `...refuses...`: returns `err`;
//! - `...clocks...`: returns what the clocks and the generator say, as
//!   sub-scores (they must be the same on every run);
//! - anything else: scores 1.

use subsume_guest::{Episode, Scorer, SubScore, Verdict};

struct Hostile;

impl Scorer for Hostile {
    fn score(episode: &Episode) -> Result<Verdict, String> {
        let task = episode.task.as_str();
        let sub = |name: &str, value: f64| SubScore { name: name.into(), value };
        if task.contains("loops") {
            let mut n = 0u64;
            loop {
                n = std::hint::black_box(n.wrapping_add(1));
            }
        }
        if task.contains("traps") {
            panic!("the scorer gives up");
        }
        if task.contains("nan") {
            return Ok(Verdict { score: f64::NAN, sub_scores: Vec::new() });
        }
        if task.contains("hoards") {
            let mut kept: Vec<Vec<u8>> = Vec::new();
            loop {
                kept.push(vec![1u8; 16 << 20]);
                std::hint::black_box(&kept);
            }
        }
        if task.contains("refuses") {
            return Err("no score for this run".into());
        }
        if task.contains("clocks") {
            let wall =
                std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map_or(-1.0, |d| d.as_secs_f64());
            let start = std::time::Instant::now();
            let mut hashed = std::collections::hash_map::RandomState::new();
            let random = {
                use std::hash::BuildHasher as _;
                hashed = std::hint::black_box(hashed);
                (hashed.hash_one(1u8) >> 11) as f64
            };
            return Ok(Verdict {
                score: 1.0,
                sub_scores: vec![
                    sub("wall_s", wall),
                    sub("elapsed_s", start.elapsed().as_secs_f64()),
                    sub("random", random),
                ],
            });
        }
        Ok(Verdict { score: 1.0, sub_scores: vec![sub("samples", episode.samples.len() as f64)] })
    }
}

subsume_guest::scorer!(Hostile);
