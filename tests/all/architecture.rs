//! The import rules of ARCHITECTURE.md, checked by reading the sources:
//! every `crate::MODULE` a file names (in `use` lines and in paths) is an
//! edge from the file's top-level module to MODULE.
//!
//! - the top-level modules form no cycle;
//! - `runtime` imports only the contract; `config` imports no `sandbox` and
//!   of `runtime` only `runtime::wiring`;
//! - `builtin` (the framework) imports no built-in module;
//! - `portal` talks to `deploy`, `store`, `report`, `metrics`, `teleop`
//!   and the contract only;
//! - nothing but `main.rs` imports `run`, and nothing imports the crate
//!   root (every `crate::X` names a module);
//! - `anyhow` appears only in `main.rs`;
//! - no public function or trait method returns `Result<_, String>`: errors
//!   that cross a module seam are typed.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

use crate::support;

/// Every `.rs` file under `dir`.
fn sources(dir: &Path, out: &mut Vec<PathBuf>) {
    for entry in std::fs::read_dir(dir).unwrap() {
        let path = entry.unwrap().path();
        if path.is_dir() {
            sources(&path, out);
        } else if path.extension().is_some_and(|e| e == "rs") {
            out.push(path);
        }
    }
}

/// The code of a file without comments and string literals (a small
/// lexer: enough that docs or strings mentioning `crate::x` are not
/// imports). Raw strings and `'"'` are handled; block comments are not used
/// in this crate.
fn code_of(text: &str) -> String {
    let chars: Vec<char> = text.chars().collect();
    let mut out = String::with_capacity(text.len());
    let mut i = 0;
    while i < chars.len() {
        let c = chars[i];
        if c == '/' && chars.get(i + 1) == Some(&'/') {
            while i < chars.len() && chars[i] != '\n' {
                i += 1;
            }
            continue;
        }
        if c == '\'' && chars.get(i + 2) == Some(&'\'') {
            // A char literal like '"': skip it whole.
            out.push_str("' '");
            i += 3;
            continue;
        }
        let raw = c == 'r'
            && (chars.get(i + 1) == Some(&'#') || chars.get(i + 1) == Some(&'"'))
            && (i == 0 || !(chars[i - 1].is_alphanumeric() || chars[i - 1] == '_'));
        if raw {
            let hashes = chars[i + 1..].iter().take_while(|c| **c == '#').count();
            if chars.get(i + 1 + hashes) == Some(&'"') {
                i += 2 + hashes;
                let closing: String = std::iter::once('"').chain(std::iter::repeat_n('#', hashes)).collect();
                while i < chars.len() && !chars[i..].iter().take(closing.len()).copied().eq(closing.chars()) {
                    if chars[i] == '\n' {
                        out.push('\n');
                    }
                    i += 1;
                }
                i += closing.len();
                out.push_str("\"\"");
                continue;
            }
        }
        if c == '"' {
            i += 1;
            while i < chars.len() && chars[i] != '"' {
                if chars[i] == '\\' {
                    i += 1;
                }
                if chars.get(i) == Some(&'\n') {
                    out.push('\n');
                }
                i += 1;
            }
            i += 1;
            out.push_str("\"\"");
            continue;
        }
        out.push(c);
        i += 1;
    }
    out
}

/// The crate paths a file names: `crate::a::b` and the items of
/// `use crate::{a, b::c}` groups, as their first segment.
fn crate_paths(code: &str) -> BTreeSet<String> {
    let mut found = BTreeSet::new();
    let mut rest = code;
    while let Some(at) = rest.find("crate::") {
        let after = &rest[at + "crate::".len()..];
        if let Some(group) = after.strip_prefix('{') {
            let end = group.find('}').unwrap_or(group.len());
            for item in group[..end].split(',') {
                let first = item.trim().split("::").next().unwrap_or("").trim();
                if !first.is_empty() {
                    found.insert(first.to_string());
                }
            }
        } else {
            let name: String = after.chars().take_while(|c| c.is_alphanumeric() || *c == '_').collect();
            found.insert(name);
        }
        rest = after;
    }
    found
}

struct Crate {
    /// File (relative to host/src) -> its top-level module and the modules
    /// it names.
    files: BTreeMap<String, (String, BTreeSet<String>)>,
    /// File -> its code without comments or strings.
    code: BTreeMap<String, String>,
    modules: BTreeSet<String>,
}

fn read_crate() -> Crate {
    let src = support::repo_root().join("host/src");
    let mut paths = Vec::new();
    sources(&src, &mut paths);
    let lib = std::fs::read_to_string(src.join("lib.rs")).unwrap();
    let modules: BTreeSet<String> = lib
        .lines()
        .filter_map(|l| l.trim().strip_prefix("pub mod ").and_then(|m| m.strip_suffix(';')))
        .map(str::to_string)
        .collect();
    let mut files = BTreeMap::new();
    let mut code = BTreeMap::new();
    for path in paths {
        let relative = path.strip_prefix(&src).unwrap().to_string_lossy().into_owned();
        let top = relative.split('/').next().unwrap().trim_end_matches(".rs").to_string();
        let text = code_of(&std::fs::read_to_string(&path).unwrap());
        files.insert(relative.clone(), (top, crate_paths(&text)));
        code.insert(relative, text);
    }
    Crate { files, code, modules }
}

fn violations(krate: &Crate, rule: impl Fn(&str, &str, &str) -> bool) -> Vec<String> {
    let mut found = Vec::new();
    for (file, (top, named)) in &krate.files {
        for module in named {
            if module != top && rule(file, top, module) {
                found.push(format!("{file} names crate::{module}"));
            }
        }
    }
    found
}

const BUILTIN_MODULES: &[&str] = &["arbiter", "bridge", "envelope", "robot", "sim", "teleop"];

#[test]
fn the_top_level_modules_form_no_cycle() {
    let krate = read_crate();
    let mut edges: BTreeMap<&str, BTreeSet<&str>> = BTreeMap::new();
    for (top, named) in krate.files.values() {
        for module in named {
            if module != top && krate.modules.contains(module) {
                edges.entry(top.as_str()).or_default().insert(module.as_str());
            }
        }
    }
    // Depth-first search for a back edge; report the cycle it closes.
    fn visit<'a>(
        node: &'a str,
        edges: &BTreeMap<&'a str, BTreeSet<&'a str>>,
        path: &mut Vec<&'a str>,
        done: &mut BTreeSet<&'a str>,
    ) -> Option<String> {
        if let Some(at) = path.iter().position(|n| *n == node) {
            let mut cycle = path[at..].to_vec();
            cycle.push(node);
            return Some(cycle.join(" -> "));
        }
        if !done.insert(node) {
            return None;
        }
        path.push(node);
        for next in edges.get(node).into_iter().flatten() {
            if let Some(cycle) = visit(next, edges, path, done) {
                return Some(cycle);
            }
        }
        path.pop();
        None
    }
    let mut done = BTreeSet::new();
    for module in &krate.modules {
        let mut path = Vec::new();
        if let Some(cycle) = visit(module, &edges, &mut path, &mut done) {
            panic!("import cycle: {cycle}");
        }
    }
}

#[test]
fn every_import_rule_holds() {
    let krate = read_crate();
    let mut broken = Vec::new();
    broken.extend(violations(&krate, |_, top, m| top == "runtime" && m != "contract"));
    broken.extend(violations(&krate, |_, top, m| top == "config" && m == "sandbox"));
    broken.extend(violations(&krate, |file, top, m| {
        top == "config" && m == "runtime" && {
            let code = &krate.code[file];
            code.match_indices("crate::runtime::").any(|(at, _)| !code[at..].starts_with("crate::runtime::wiring"))
        }
    }));
    broken.extend(violations(&krate, |_, top, m| top == "builtin" && BUILTIN_MODULES.contains(&m)));
    broken.extend(violations(&krate, |_, top, m| {
        top == "portal" && !["deploy", "store", "report", "teleop", "contract", "metrics", "logfields"].contains(&m)
    }));
    broken.extend(violations(&krate, |file, _, m| m == "run" && file != "main.rs"));
    broken.extend(violations(&krate, |_, _, m| !krate.modules.contains(m)));
    assert!(broken.is_empty(), "import rules broken (ARCHITECTURE.md, \"Import rules\"):\n{}", broken.join("\n"));
}

#[test]
fn anyhow_lives_only_in_main_and_no_public_function_returns_a_string_error() {
    let krate = read_crate();
    let mut broken = Vec::new();
    for (file, code) in &krate.code {
        if file != "main.rs" && code.contains("anyhow") {
            broken.push(format!("{file} uses anyhow"));
        }
        // Public functions, and methods of public traits (their `fn`s carry
        // no `pub` but are public with the trait).
        let mut in_pub_trait = false;
        for (i, line) in code.lines().enumerate() {
            let trimmed = line.trim_start();
            if trimmed.starts_with("pub trait ") {
                in_pub_trait = true;
            } else if line.starts_with('}') {
                in_pub_trait = false;
            }
            let public = trimmed.starts_with("pub fn ") || (in_pub_trait && trimmed.starts_with("fn "));
            if !public {
                continue;
            }
            // The signature up to its body or `;`, and its return type.
            let signature: String = code.lines().skip(i).take(12).collect::<Vec<_>>().join(" ");
            let signature = signature.split(['{', ';']).next().unwrap_or("");
            let returns = signature.split_once("->").map(|(_, r)| r.replace(' ', "")).unwrap_or_default();
            if returns.starts_with("Result<") && returns.ends_with(",String>") {
                broken.push(format!("{file}:{}: {}", i + 1, trimmed));
            }
        }
    }
    assert!(broken.is_empty(), "{}", broken.join("\n"));
}

#[test]
fn the_checker_sees_imports_and_ignores_docs() {
    let code = code_of(
        "use crate::{config::X, runtime};\n// crate::portal\nlet s = \"crate::deploy\"; let c = '\"'; crate::store::open();\nlet r = r#\"crate::sim \"x\"\"#; crate::sandbox::x();",
    );
    assert_eq!(crate_paths(&code).into_iter().collect::<Vec<_>>(), ["config", "runtime", "sandbox", "store"]);
}
