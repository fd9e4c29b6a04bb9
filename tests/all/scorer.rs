//! A task's scoring component (issue 41; docs/lab.md, "Tasks and scores"),
//! on the real binary with no lab: a bundle-shaped folder (a run's
//! recording from `subsume run --record`, `task.json` naming the scorer
//! and its sha256, `scorer.wasm`) scored by `subsume score`, offline.

use std::path::Path;
use std::process::{Command, Output};

use serde_json::Value as Json;

/// A folder holding a run of the lab's baseline to (6, 1) (without its
/// teleoperation, which wants a portal) recorded as `run.mcap`, and
/// `scorer` as `scorer.wasm`.
fn recorded_run(dir: &Path, scorer: &str) {
    let robot = crate::lab::robot(6.0, "");
    let teleop = robot.find("<platform name=\"network\">").unwrap();
    let end = robot[teleop..].find("</platform>").unwrap() + teleop + "</platform>".len();
    let robot = format!("{}{}", &robot[..teleop], &robot[end..]);
    std::fs::write(dir.join("robot.xml"), robot).unwrap();
    std::fs::write(dir.join("lab.world"), crate::lab::WORLD).unwrap();
    let ran = crate::support::subsume()
        .arg("run")
        .arg(dir.join("robot.xml"))
        .args(["--http", "off", "--speed", "max", "--duration", "25", "--record"])
        .arg(dir.join("run.mcap"))
        .output()
        .unwrap();
    assert!(ran.status.success(), "{}", String::from_utf8_lossy(&ran.stderr));
    std::fs::copy(crate::support::guest(scorer), dir.join("scorer.wasm")).unwrap();
}

fn sha256_of(path: &Path) -> String {
    use sha2::Digest as _;
    hex::encode(sha2::Sha256::digest(std::fs::read(path).unwrap()))
}

/// Writes `dir/task.json`: task `name` to (6, 1), scored by `dir`'s
/// scorer.wasm pinned as `sha256`.
fn write_task(dir: &Path, name: &str, sha256: &str) -> Json {
    let task = serde_json::json!({
        "name": name, "goal": {"x": 6.0, "y": 1.0, "radius": 0.4}, "metric": "scorer",
        "scorer": {"component": "boss/goal-distance", "sha256": sha256}
    });
    std::fs::write(dir.join("task.json"), serde_json::to_vec_pretty(&task).unwrap()).unwrap();
    task
}

fn rescore(dir: &Path, json: bool) -> Output {
    let mut command = crate::support::subsume();
    command.arg("score").arg(dir);
    if json {
        command.arg("--json");
    }
    command.output().unwrap()
}

fn text(bytes: &[u8]) -> String {
    String::from_utf8_lossy(bytes).into_owned()
}

/// The Rust scoring component's score of a recorded run: what it computes
/// (the final distance to the goal, the path length; the score is their
/// weighted sum) is what Python over the `mcap` package finds in the same
/// recording; `subsume score` gives the same bytes on every run, and says
/// when the bundle's `score.json` matches them.
#[test]
fn a_scoring_component_scores_a_recorded_run_as_python_does_and_the_same_bits_every_time() {
    let dir = tempfile::tempdir().unwrap();
    recorded_run(dir.path(), "scorer-goal-distance");
    let sha256 = sha256_of(&dir.path().join("scorer.wasm"));
    write_task(dir.path(), "reach-6", &sha256);
    let first = rescore(dir.path(), true);
    assert!(first.status.success(), "{}{}", text(&first.stdout), text(&first.stderr));
    let score: Json = serde_json::from_slice(&first.stdout).unwrap();
    assert_eq!((&score["metric"], &score["scorer_sha256"]), (&Json::from("scorer"), &Json::from(sha256.clone())));
    let sub = |name: &str| score["sub_scores"][name].as_f64().unwrap_or_else(|| panic!("{name}: {score:#}"));
    assert_eq!(sub("reached"), 1.0, "{score:#}");
    assert!(sub("final_distance_m") < 1.0 && sub("path_length_m") > 4.5, "{score:#}");
    // The ranges reached it: the wall behind the start is 1 m away.
    assert!(sub("closest_m") > 0.0 && sub("closest_m") <= 1.0, "{score:#}");
    let value = score["value"].as_f64().unwrap();
    assert_eq!(value, sub("final_distance_m") + 0.1 * sub("path_length_m"), "{score:#}");
    // Python over the same recording.
    let independent = Command::new(crate::support::python())
        .arg(crate::support::repo_root().join("tests/python/score_check.py"))
        .arg(dir.path().join("run.mcap"))
        .arg(dir.path().join("task.json"))
        .output()
        .unwrap();
    assert!(independent.status.success(), "{}", text(&independent.stderr));
    let found: Json = serde_json::from_slice(&independent.stdout).unwrap();
    for (ours, theirs) in [
        ("final_distance_m", "final_distance_m"),
        ("path_length_m", "path_length_m"),
        ("reached", "goal_reached"),
        ("commands", "commands"),
        ("closest_m", "closest_m"),
    ] {
        let (ours, theirs) = (sub(ours), found[theirs].as_f64().unwrap());
        assert!((ours - theirs).abs() <= 1e-9 * ours.abs().max(1.0), "{ours} vs {theirs}: {found}");
    }
    // The built-in metrics beside the component's, as Python finds them.
    let built_in = |name: &str| score["built_in"][name].as_f64().unwrap_or_else(|| panic!("{name}: {score:#}"));
    for name in ["path_length_m", "goal_reached", "energy"] {
        let (ours, theirs) = (built_in(name), found[name].as_f64().unwrap());
        assert!((ours - theirs).abs() <= 1e-9 * ours.abs().max(1.0), "{name}: {ours} vs {theirs}: {found}");
    }
    let theirs = found["goal_distance_score"].as_f64().unwrap();
    assert!((value - theirs).abs() <= 1e-9 * value.abs().max(1.0), "{value} vs {theirs}");
    // The same bits again, and `score.json` of those bits is identical.
    let again = rescore(dir.path(), true);
    assert_eq!(first.stdout, again.stdout);
    std::fs::write(dir.path().join("score.json"), &first.stdout).unwrap();
    let compared = rescore(dir.path(), false);
    let said = text(&compared.stdout);
    assert!(compared.status.success() && said.contains("identical: "), "{said}{}", text(&compared.stderr));
    assert!(said.contains("run: task reach-6: score = ") && said.contains("final_distance_m = "), "{said}");
}

/// A scorer that loops, traps, hoards memory, returns NaN or refuses gives
/// no score: `subsume score` fails and says which task, which scorer and
/// what went wrong. Bytes that are not the ones the task pins are refused
/// before they run. The clocks a scorer can read stand still, so even one
/// that scores by them gives the same bits every time.
#[test]
fn a_hostile_scorer_gives_a_clear_error_and_never_a_score() {
    let dir = tempfile::tempdir().unwrap();
    recorded_run(dir.path(), "test-scorer-hostile");
    let sha256 = sha256_of(&dir.path().join("scorer.wasm"));
    let cases = [
        ("scorer-loops", "score() exceeded its cpu-time budget of 2000 ms"),
        ("scorer-traps", "score() trapped: wasm trap: wasm `unreachable` instruction executed"),
        ("scorer-hoards", "score() exceeded its memory limit"),
        ("scorer-nan", "returned a bad verdict: the score is NaN, not a finite number"),
        ("scorer-refuses", "refused to score the run: no score for this run"),
    ];
    for (task, expected) in cases {
        write_task(dir.path(), task, &sha256);
        let started = std::time::Instant::now();
        let scored = rescore(dir.path(), true);
        let said = text(&scored.stderr);
        assert!(!scored.status.success(), "{task}: {}", text(&scored.stdout));
        assert!(scored.stdout.is_empty(), "{task}: a score was printed: {}", text(&scored.stdout));
        assert!(said.contains(&format!("task {task}: its scorer boss/goal-distance: ")), "{task}: {said}");
        assert!(said.contains(expected), "{task}: {said}");
        assert!(started.elapsed() < std::time::Duration::from_secs(60), "{task}: {:?}", started.elapsed());
    }
    // Not the pinned bytes.
    write_task(dir.path(), "fine", &"0".repeat(64));
    let scored = rescore(dir.path(), true);
    let said = text(&scored.stderr);
    assert!(!scored.status.success(), "{}", text(&scored.stdout));
    assert!(said.contains(&format!("its bytes' sha256 is {sha256}, but the task pins {}", "0".repeat(64))), "{said}");
    // The clocks and the generator: the same every time, the wall clock at
    // the Unix epoch.
    write_task(dir.path(), "scorer-clocks", &sha256);
    let first = rescore(dir.path(), true);
    assert!(first.status.success(), "{}", text(&first.stderr));
    let score_json: Json = serde_json::from_slice(&first.stdout).unwrap();
    assert_eq!(
        (&score_json["sub_scores"]["wall_s"], &score_json["sub_scores"]["elapsed_s"]),
        (&0.0.into(), &0.0.into())
    );
    assert_eq!(first.stdout, rescore(dir.path(), true).stdout);
    // No scorer.wasm: said so.
    std::fs::remove_file(dir.path().join("scorer.wasm")).unwrap();
    let scored = rescore(dir.path(), true);
    let said = text(&scored.stderr);
    assert!(!scored.status.success() && said.contains("scorer.wasm"), "{said}");
}

/// Scorings at once in one process share the scorers' engine and its
/// compiled cache (a host scores every run that ends, and `score` on a
/// lab server may overlap): eight threads, each scoring the same bundle
/// five times, all get the bytes one scoring alone gets, and a bundle whose
/// scorer traps, scored among them, fails each time without touching the
/// others' results.
#[test]
fn scorings_at_once_share_the_compiled_scorer_and_each_gets_the_same_bits() {
    let dir = tempfile::tempdir().unwrap();
    let (good, hostile) = (dir.path().join("good"), dir.path().join("hostile"));
    std::fs::create_dir_all(&good).unwrap();
    recorded_run(&good, "scorer-goal-distance");
    write_task(&good, "reach-6", &sha256_of(&good.join("scorer.wasm")));
    std::fs::create_dir_all(&hostile).unwrap();
    for file in ["run.mcap", "robot.xml"] {
        std::fs::copy(good.join(file), hostile.join(file)).unwrap();
    }
    std::fs::copy(crate::support::guest("test-scorer-hostile"), hostile.join("scorer.wasm")).unwrap();
    // (the hostile scorer traps on a task named "...traps...")
    write_task(&hostile, "scorer-traps", &sha256_of(&hostile.join("scorer.wasm")));
    let (_, alone) = subsume::score::score_bundle(&good).unwrap();
    let threads: Vec<_> = (0..8)
        .map(|i| {
            let (good, hostile) = (good.clone(), hostile.clone());
            std::thread::spawn(move || {
                let mut scored = Vec::new();
                for round in 0..5 {
                    if (i + round) % 4 == 0 {
                        let failed = subsume::score::score_bundle(&hostile).err().map(|e| e.to_string());
                        let failed = failed.unwrap_or_else(|| panic!("thread {i}: the trapping scorer gave a score"));
                        assert!(failed.contains("score() trapped"), "thread {i}: {failed}");
                    }
                    scored.push(subsume::score::score_bundle(&good).map(|(_, bytes)| bytes));
                }
                scored
            })
        })
        .collect();
    for (i, thread) in threads.into_iter().enumerate() {
        for (round, scored) in thread.join().unwrap().into_iter().enumerate() {
            let bytes = scored.unwrap_or_else(|e| panic!("thread {i} round {round}: {e}"));
            assert_eq!(bytes, alone, "thread {i} round {round}");
        }
    }
}
