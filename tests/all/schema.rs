//! The XSD schema in config/ agrees with the host: the example robot files
//! and every case the host accepts validate against it, and files with
//! structural errors the schema can see are rejected by it too.
//! Needs `xmllint` (Debian package libxml2-utils; .ci/run installs it).

use std::path::PathBuf;
use std::process::Command;

use crate::support;

fn xmllint(files: &[PathBuf]) -> (bool, String) {
    let root = support::repo_root();
    let output = Command::new("xmllint")
        .arg("--noout")
        .arg("--schema")
        .arg(root.join("config/robot.xsd"))
        .args(files)
        .output()
        .unwrap_or_else(|e| panic!("cannot run xmllint (apt-get install libxml2-utils): {e}"));
    (output.status.success(), String::from_utf8_lossy(&output.stderr).into_owned())
}

#[test]
fn accepted_robot_files_validate_against_the_schema() {
    let root = support::repo_root();
    let mut files: Vec<PathBuf> = std::fs::read_dir(root.join("config"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|x| x == "xml"))
        .collect();
    assert!(!files.is_empty());
    files.push(root.join("tests/config/good-robot.xml"));
    let (ok, log) = xmllint(&files);
    assert!(ok, "{log}");
}

#[test]
fn structurally_bad_files_fail_the_schema_too() {
    let root = support::repo_root().join("tests/config");
    for case in [
        "unknown-element.xml",
        "unknown-attribute.xml",
        "missing-attribute.xml",
        "duplicate-names.xml",
        "bad-names.xml",
        "numbers-out-of-range.xml",
        "wrong-root.xml",
        "comment-with-double-hyphen.xml",
    ] {
        let (ok, log) = xmllint(&[root.join(case)]);
        assert!(!ok, "{case} validated against the schema:\n{log}");
    }
}
