//! Data-driven tests of the robot-file reader and validator: every
//! `tests/config/NAME.xml` is checked with the real loader (real guests, real
//! compilation) and its diagnostics, one per line, must equal
//! `NAME.expected` (or `ok: ...` for a good file).
//!
//! `BLESS=1 cargo test --test all config_cases::` rewrites the expected
//! files.

use std::path::Path;

use subsume::assemble::Loader;
use subsume::config;
use subsume::sandbox::Sandbox;

use crate::support;

fn render(dir: &Path, file: &Path, sandbox: &Sandbox) -> String {
    let mut loader = Loader::new(sandbox);
    let text = match config::load(file, &mut loader) {
        Ok(robot) => format!(
            "ok: robot '{}', {} components, {} connections\n",
            robot.name,
            robot.components.len(),
            robot.connections.len()
        ),
        Err(diagnostics) => format!("{diagnostics}\n"),
    };
    text.replace(&format!("{}/", dir.display()), "")
}

#[test]
fn every_case_gives_its_expected_diagnostics() {
    let dir = support::repo_root().join("tests/config");
    let sandbox = support::sandbox();
    let bless = std::env::var_os("BLESS").is_some();
    let mut cases: Vec<_> = std::fs::read_dir(&dir)
        .unwrap_or_else(|e| panic!("{e}"))
        .filter_map(Result::ok)
        .map(|e| e.path())
        .filter(|p| p.extension().is_some_and(|x| x == "xml"))
        .collect();
    cases.sort();
    assert!(cases.len() >= 15, "expected at least 15 cases in {}", dir.display());
    let mut failures = Vec::new();
    for case in &cases {
        let actual = render(&dir, case, &sandbox);
        let expected_path = case.with_extension("expected");
        if bless {
            std::fs::write(&expected_path, &actual).unwrap_or_else(|e| panic!("{e}"));
            continue;
        }
        let expected = std::fs::read_to_string(&expected_path).unwrap_or_default();
        if actual != expected {
            failures.push(format!(
                "{}:\n--- expected\n{expected}--- actual\n{actual}",
                case.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default()
            ));
        }
    }
    assert!(failures.is_empty(), "{} case(s) differ (BLESS=1 to accept):\n{}", failures.len(), failures.join("\n"));
}

#[test]
fn the_example_robot_files_are_valid() {
    let sandbox = support::sandbox();
    let dir = support::repo_root().join("config");
    let mut checked = 0;
    for entry in std::fs::read_dir(&dir).unwrap() {
        let path = entry.unwrap().path();
        if path.extension().is_none_or(|x| x != "xml") {
            continue;
        }
        let mut loader = Loader::new(&sandbox);
        if let Err(diagnostics) = config::load(&path, &mut loader) {
            panic!("{} is invalid:\n{diagnostics}", path.display());
        }
        checked += 1;
    }
    assert!(checked >= 1, "no robot files in {}", dir.display());
}
