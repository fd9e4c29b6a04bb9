//! Built-ins, from their declarations: every bound of every parameter of
//! every built-in is a located diagnostic one step past it and accepted at
//! it (through the real validator and loader), and docs/config.md's tables
//! say what the declarations say (`BLESS=1` rewrites them).

use std::fmt::Write as _;

use subsume::assemble::{Loader, registry};
use subsume::builtin::{Bound, Builtin, ParamDecl, ParamType};
use subsume::config;
use subsume::sandbox::Sandbox;

use crate::support;

/// Parameters a built-in needs to be checked at all, beside the one tested.
fn required(kind: &str) -> &'static [(&'static str, &'static str)] {
    match kind {
        "camera" => &[("source", "sim:none")],
        "serial" => &[("device", "sim:none")],
        "sim" => &[("world", "demo.world")],
        _ => &[],
    }
}

/// (value, whether it is allowed) around each bound of `decl`.
fn probes(decl: &ParamDecl) -> Vec<(String, bool)> {
    let past = |x: f64, up: bool| {
        let step = (x.abs() * 1e-6).max(1e-6);
        format!("{}", if up { x + step } else { x - step })
    };
    match decl.ty {
        ParamType::Number { min, max } => {
            let (lo, hi) = (min.value(), max.value());
            vec![
                (format!("{lo}"), matches!(min, Bound::Inclusive(_))),
                (past(lo, false), false),
                (format!("{hi}"), matches!(max, Bound::Inclusive(_))),
                (past(hi, true), false),
                ("not-a-number".into(), false),
            ]
        }
        ParamType::Integer { min, max } => vec![
            (min.to_string(), true),
            ((min - 1).to_string(), false),
            (max.to_string(), true),
            ((max + 1).to_string(), false),
            ("1.5".into(), false),
        ],
        ParamType::Choice(words) => {
            let mut probes: Vec<(String, bool)> = words.iter().map(|w| (w.to_string(), true)).collect();
            probes.push(("no-such-choice".into(), false));
            probes
        }
        ParamType::Address { optional } => {
            vec![("127.0.0.1:0".into(), true), (String::new(), optional), ("localhost".into(), false)]
        }
        ParamType::Required => vec![(String::new(), false)],
        ParamType::File { optional } | ParamType::SecretFile { optional, .. } => vec![(String::new(), optional)],
        ParamType::WordOrFile(words) => {
            let mut probes: Vec<(String, bool)> = words.iter().map(|w| (w.to_string(), true)).collect();
            probes.push((String::new(), false));
            probes
        }
        ParamType::Text => vec![],
    }
}

fn robot(kind: &str, param: &str, value: &str) -> String {
    let mut params = String::new();
    for (name, v) in required(kind) {
        if *name != param {
            let _ = writeln!(params, "      <param name=\"{name}\" value=\"{v}\"/>");
        }
    }
    let escaped = value.replace('&', "&amp;").replace('"', "&quot;").replace('<', "&lt;");
    let _ = writeln!(params, "      <param name=\"{param}\" value=\"{escaped}\"/>");
    format!(
        "<robot name=\"bounds\">\n  <platform name=\"control\">\n    <component name=\"c\" source=\"builtin:{kind}\">\n{params}    </component>\n  </platform>\n</robot>\n"
    )
}

#[test]
fn every_bound_of_every_builtin_parameter_is_checked_at_its_param_line() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::copy(support::repo_root().join("config/worlds/demo.world"), dir.path().join("demo.world")).unwrap();
    let sandbox = Sandbox::new(None).unwrap();
    let mut failures = Vec::new();
    let mut probed = 0;
    for builtin in registry::BUILTINS {
        for decl in builtin.params() {
            for (value, allowed) in probes(decl) {
                probed += 1;
                let path = dir.path().join(format!("{}-{}.xml", builtin.kind(), decl.name));
                let text = robot(builtin.kind(), decl.name, &value);
                std::fs::write(&path, &text).unwrap();
                let mut loader = Loader::new(&sandbox);
                let diagnostics = match config::load(&path, &mut loader) {
                    Ok(_) => Vec::new(),
                    Err(d) => d.0,
                };
                let line = text.lines().position(|l| l.contains(&format!("name=\"{}\"", decl.name))).unwrap() + 1;
                let about: Vec<_> = diagnostics
                    .iter()
                    .filter(|d| d.message.starts_with(&format!("parameter '{}' of component 'c' ", decl.name)))
                    .collect();
                let case = format!("builtin:{} {}='{value}'", builtin.kind(), decl.name);
                // A value at its bound passes its own check; checks between
                // parameters (`direct-below` <= `shared-below`) are tested below.
                let own = about.iter().find(|d| !d.message.contains("must not exceed"));
                if allowed && let Some(d) = own {
                    failures.push(format!("{case} should pass: {d}"));
                }
                if !allowed {
                    match about.first() {
                        None => failures.push(format!("{case} should be refused; got {diagnostics:?}")),
                        Some(d) if d.line != line => {
                            failures.push(format!("{case}: reported at line {}, not {line}", d.line))
                        }
                        Some(_) => {}
                    }
                }
            }
        }
    }
    assert!(probed > 80, "only {probed} probes");
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}

/// The markdown table of one built-in, as docs/config.md shows it.
fn table(builtin: &dyn Builtin) -> String {
    let params = builtin.params();
    let defaults = subsume::builtin::check_values(params, &Default::default()).unwrap_or_default();
    let description = subsume::builtin::describe(builtin, &defaults);
    let ports = |ports: &[subsume::contract::PortSpec]| {
        if ports.is_empty() {
            "none".to_string()
        } else {
            ports.iter().map(|p| format!("`{}` ({})", p.name, p.kind.name())).collect::<Vec<_>>().join(", ")
        }
    };
    let mut s = String::new();
    let _ = writeln!(s, "{}.", builtin.summary());
    let _ = writeln!(s, "Inputs: {}. Outputs: {}.", ports(&description.inputs), ports(&description.outputs));
    if let Some(p) = builtin.default_priority() {
        let _ = writeln!(s, "Default priority: {p}.");
    }
    if params.is_empty() {
        let _ = writeln!(s, "\nNo parameters.");
        return s;
    }
    let _ = writeln!(s, "\n| parameter | default | allowed | meaning |\n|---|---|---|---|");
    for p in params {
        let default = match (p.is_required(), p.default.is_empty()) {
            (true, _) => "(required)".to_string(),
            (false, true) => "(empty)".to_string(),
            (false, false) => format!("`{}`", p.default),
        };
        let _ = writeln!(s, "| `{}` | {default} | {} | {} |", p.name, p.expected(), p.doc);
    }
    s
}

#[test]
fn the_tables_of_docs_config_md_match_the_declarations() {
    let path = support::repo_root().join("docs/config.md");
    let mut text = std::fs::read_to_string(&path).unwrap();
    let bless = std::env::var_os("BLESS").is_some();
    let mut stale = Vec::new();
    for builtin in registry::BUILTINS {
        let (open, close) =
            (format!("<!-- builtin:{} -->\n", builtin.kind()), format!("<!-- /builtin:{} -->", builtin.kind()));
        let start = text.find(&open).map(|i| i + open.len());
        let end = text.find(&close);
        let (Some(start), Some(end)) = (start, end) else {
            stale.push(format!("docs/config.md has no {open}...{close} section"));
            continue;
        };
        let expected = table(*builtin);
        if text[start..end] != expected {
            if bless {
                text.replace_range(start..end, &expected);
            } else {
                stale.push(format!(
                    "builtin:{}:\n--- docs\n{}--- declaration\n{expected}",
                    builtin.kind(),
                    &text[start..end]
                ));
            }
        }
    }
    if bless {
        std::fs::write(&path, text).unwrap();
        return;
    }
    assert!(
        stale.is_empty(),
        "docs/config.md differs from the declarations (BLESS=1 to rewrite):\n{}",
        stale.join("\n")
    );
}

#[test]
fn describe_builtin_prints_every_declared_parameter_with_its_bounds() {
    for builtin in registry::BUILTINS {
        let output = support::subsume().args(["describe", &format!("builtin:{}", builtin.kind())]).output().unwrap();
        assert!(output.status.success(), "{}", String::from_utf8_lossy(&output.stderr));
        let text = String::from_utf8_lossy(&output.stdout);
        for decl in builtin.params() {
            let line = text.lines().find(|l| l.trim_start().starts_with(&format!("{} (", decl.name)));
            assert!(
                line.is_some_and(|l| l.contains(&decl.expected())),
                "builtin:{} {}:\n{text}",
                builtin.kind(),
                decl.name
            );
            // "(required)" exactly when a robot file that leaves the
            // parameter out is refused; an allowed empty default reads "none".
            let refused_without = subsume::builtin::check_values(&[*decl], &Default::default()).is_err();
            let line = line.unwrap_or_default().trim_start();
            let says = |what: &str| line.starts_with(&format!("{} ({what}):", decl.name));
            assert_eq!(says("required"), refused_without, "builtin:{}: {line}", builtin.kind());
            if !refused_without && decl.default.is_empty() {
                assert!(says("default: none"), "builtin:{}: {line}", builtin.kind());
            }
        }
    }
    // The newcomer's case: the envelope's geofence defaults to no fence.
    let output = support::subsume().args(["describe", "builtin:envelope"]).output().unwrap();
    let text = String::from_utf8_lossy(&output.stdout);
    assert!(text.contains("  geofence (default: none): any text;"), "{text}");
    let output = support::subsume().args(["describe", "builtin:nope"]).output().unwrap();
    assert!(!output.status.success());
    assert!(
        String::from_utf8_lossy(&output.stderr)
            .contains("unknown built-in 'nope' (known: arbiter, camera, envelope, log, publish, ros2-publish, ros2-subscribe, serial, sim, teleop, zenoh, zenoh-publish, zenoh-subscribe)")
    );
}

#[test]
fn a_missing_file_parameter_points_at_its_line() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("r.xml");
    std::fs::write(&path, robot("sim", "world", "nowhere.world")).unwrap();
    let sandbox = Sandbox::new(None).unwrap();
    let err = config::load(&path, &mut Loader::new(&sandbox)).err().unwrap().to_string();
    assert!(err.starts_with(&format!("{}:4:", path.display())), "{err}");
    assert!(err.contains("parameter 'world' of component 'c' names a bad world file"), "{err}");
}

#[test]
fn checks_between_teleop_parameters_name_the_first_one() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("r.xml");
    let text = r#"<robot name="t"><platform name="network">
  <component name="c" source="builtin:teleop">
    <param name="direct-below" value="0.5"/>
    <param name="shared-below" value="0.2"/>
    <param name="min-delay" value="0.3"/>
    <param name="max-delay" value="0.1"/>
    <param name="delay" value="later"/>
  </component>
</platform></robot>
"#;
    std::fs::write(&path, text).unwrap();
    let sandbox = Sandbox::new(None).unwrap();
    let err = config::load(&path, &mut Loader::new(&sandbox)).err().unwrap().to_string();
    let name = path.display();
    assert_eq!(
        err,
        format!(
            "{name}:3:39: parameter 'direct-below' of component 'c' must not exceed shared-below (0.2 s), got 0.5 s\n\
             {name}:5:36: parameter 'min-delay' of component 'c' must not exceed max-delay (0.1 s), got 0.3 s\n\
             {name}:7:32: parameter 'delay' of component 'c' must be adaptive or a number in [0, 5] s, got 'later'"
        )
    );
}
