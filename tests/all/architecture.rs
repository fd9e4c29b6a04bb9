//! The import rules of ARCHITECTURE.md, checked by reading the sources:
//! every `crate::MODULE` a file names (in `use` lines and in paths) is an
//! edge from the file's top-level module to MODULE.
//!
//! - the top-level modules form no cycle, and neither do the files inside
//!   each folder (a file names a sibling through `super::x`, `crate::m::x`,
//!   or a name its folder's `mod.rs` re-exports from `x`);
//! - `runtime` imports only the contract and the wall clock (`walltime`); `config` imports no `sandbox` and
//!   of `runtime` only `runtime::wiring`;
//! - `builtin` (the framework) imports no built-in module;
//! - `portal` talks to `deploy`, `lab`, `store`, `report`, `metrics`,
//!   `teleop`, the contract, `logfields`, `fsutil`, `walltime` and `tls`
//!   only, and of `sandbox` to `sandbox::preamble` only (the command line's
//!   client checks a file is a component before uploading it);
//! - nothing but the binary (`main.rs` and its `commands/`) imports `run`,
//!   and nothing imports the crate root (every `crate::X` names a module);
//! - `anyhow` appears only in the binary;
//! - a built-in's kind is a `BuiltinKind` only the registry makes: no
//!   kind string (`"sim"`, `"builtin:sim"`) outside the registry and the
//!   built-ins, no `ComponentSource::Builtin("...")`;
//! - no public function or trait method returns `Result<_, String>`, and no
//!   trait's error is a `String` (`type Err = String`): errors that cross a
//!   module seam are typed.

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

/// A file of the binary (`main.rs` and the commands it dispatches to),
/// not of the library: its `crate::` is the binary's root.
fn in_binary(file: &str) -> bool {
    file == "main.rs" || file.starts_with("commands/")
}

struct Crate {
    /// File of the library (relative to host/src) -> its top-level module
    /// and the modules it names.
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
        if !in_binary(&relative) {
            files.insert(relative.clone(), (top, crate_paths(&text)));
        }
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

const BUILTIN_MODULES: &[&str] = &["arbiter", "bridge", "camera", "envelope", "robot", "sim", "teleop"];

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

/// The first cycle in a graph of names, as `a -> b -> a`.
fn find_cycle(edges: &BTreeMap<String, BTreeSet<String>>) -> Option<String> {
    fn visit(
        node: &str,
        edges: &BTreeMap<String, BTreeSet<String>>,
        path: &mut Vec<String>,
        done: &mut BTreeSet<String>,
    ) -> Option<String> {
        if let Some(at) = path.iter().position(|n| n == node) {
            let mut cycle = path[at..].to_vec();
            cycle.push(node.to_string());
            return Some(cycle.join(" -> "));
        }
        if !done.insert(node.to_string()) {
            return None;
        }
        path.push(node.to_string());
        for next in edges.get(node).into_iter().flatten() {
            if let Some(cycle) = visit(next, edges, path, done) {
                return Some(cycle);
            }
        }
        path.pop();
        None
    }
    let mut done = BTreeSet::new();
    edges.keys().find_map(|node| visit(node, edges, &mut Vec::new(), &mut done))
}

/// Inside one folder (`dir`, relative to host/src, with a `mod.rs`): each
/// file -> the sibling files it names.
fn sibling_edges(krate: &Crate, dir: &str) -> BTreeMap<String, BTreeSet<String>> {
    let prefix = format!("{dir}/");
    let siblings: BTreeSet<String> = krate
        .code
        .keys()
        .filter_map(|f| f.strip_prefix(&prefix))
        .map(|rest| rest.split('/').next().unwrap().trim_end_matches(".rs").to_string())
        .filter(|name| name != "mod")
        .collect();
    // Names `mod.rs` takes from a sibling (`pub use x::{A, B}`, `use x::A`).
    let mut reexported: BTreeMap<String, String> = BTreeMap::new();
    for line in krate.code[&format!("{prefix}mod.rs")].split(';') {
        let line = line.trim();
        let Some(at) = line.find("use ") else { continue };
        if !line[..at].trim().is_empty() && !line[..at].trim().starts_with("pub") {
            continue;
        }
        let path = line[at + 4..].trim();
        let Some((from, items)) = path.split_once("::") else { continue };
        if !siblings.contains(from) {
            continue;
        }
        for item in items.trim_matches(|c| c == '{' || c == '}' || char::is_whitespace(c)).split(',') {
            let item = item.trim();
            let name = item.rsplit(" as ").next().unwrap_or(item).rsplit("::").next().unwrap_or(item).trim();
            if !name.is_empty() {
                reexported.insert(name.to_string(), from.to_string());
            }
        }
    }
    let module_path = format!("crate::{}::", dir.replace('/', "::"));
    let mut edges: BTreeMap<String, BTreeSet<String>> = BTreeMap::new();
    for (file, code) in &krate.code {
        let Some(rest) = file.strip_prefix(&prefix) else { continue };
        let me = rest.split('/').next().unwrap().trim_end_matches(".rs").to_string();
        if me == "mod" {
            continue;
        }
        // A file of a sub-folder counts as the sub-folder; its `super::` is
        // this folder from the sub-folder's mod.rs, `super::super::` below it.
        let up = match rest.matches('/').count() {
            0 => "super::",
            _ if rest.ends_with("/mod.rs") => "super::",
            _ => "super::super::",
        };
        let mut named = BTreeSet::new();
        for marker in [up, module_path.as_str()] {
            for (at, _) in code.match_indices(marker) {
                let after = &code[at + marker.len()..];
                let items: Vec<&str> = match after.strip_prefix('{') {
                    Some(group) => group[..group.find('}').unwrap_or(group.len())].split(',').collect(),
                    None => vec![after],
                };
                for item in items {
                    let first: String = item.trim().chars().take_while(|c| c.is_alphanumeric() || *c == '_').collect();
                    if siblings.contains(&first) {
                        named.insert(first);
                    } else if let Some(from) = reexported.get(&first) {
                        named.insert(from.clone());
                    }
                }
            }
        }
        named.remove(&me);
        edges.entry(me).or_default().extend(named);
    }
    edges
}

#[test]
fn the_files_inside_each_folder_form_no_cycle() {
    let krate = read_crate();
    let folders: BTreeSet<String> = krate
        .code
        .keys()
        .filter(|f| !in_binary(f))
        .filter_map(|f| f.strip_suffix("/mod.rs"))
        .map(str::to_string)
        .collect();
    assert!(folders.contains("sandbox") && folders.contains("runtime"), "{folders:?}");
    let cycles: Vec<String> = folders
        .iter()
        .filter_map(|dir| find_cycle(&sibling_edges(&krate, dir)).map(|cycle| format!("{dir}/: {cycle}")))
        .collect();
    assert!(
        cycles.is_empty(),
        "import cycles inside folders (each file imports only files below it):\n{}",
        cycles.join("\n")
    );
}

#[test]
fn the_folder_checker_sees_siblings_and_reexports() {
    let mut code = BTreeMap::new();
    code.insert("f/mod.rs".to_string(), code_of("mod a;\nmod b;\nmod c;\npub use b::{Thing, other as renamed};"));
    code.insert("f/a.rs".to_string(), code_of("use super::Thing;\n// super::c\nfn x() { super::c::y(); }"));
    code.insert("f/b.rs".to_string(), code_of("use crate::f::{c::Z};"));
    code.insert("f/c.rs".to_string(), code_of("use super::a::W;"));
    let krate = Crate { files: BTreeMap::new(), code, modules: BTreeSet::new() };
    let edges = sibling_edges(&krate, "f");
    let show = |k: &str| edges[k].iter().cloned().collect::<Vec<_>>();
    assert_eq!(show("a"), ["b", "c"]);
    assert_eq!(show("b"), ["c"]);
    assert_eq!(show("c"), ["a"]);
    assert_eq!(find_cycle(&edges).as_deref(), Some("a -> b -> c -> a"));
}

#[test]
fn every_import_rule_holds() {
    let krate = read_crate();
    let mut broken = Vec::new();
    broken.extend(violations(&krate, |_, top, m| top == "runtime" && m != "contract" && m != "walltime"));
    broken.extend(violations(&krate, |_, top, m| top == "config" && m == "sandbox"));
    broken.extend(violations(&krate, |file, top, m| {
        top == "config" && m == "runtime" && {
            let code = &krate.code[file];
            code.match_indices("crate::runtime::").any(|(at, _)| !code[at..].starts_with("crate::runtime::wiring"))
        }
    }));
    broken.extend(violations(&krate, |_, top, m| top == "builtin" && BUILTIN_MODULES.contains(&m)));
    broken.extend(violations(&krate, |file, top, m| {
        top == "portal"
            && ![
                "deploy",
                "lab",
                "store",
                "report",
                "teleop",
                "contract",
                "metrics",
                "logfields",
                "fsutil",
                "tls",
                "walltime",
            ]
            .contains(&m)
            && !(m == "sandbox" && {
                let code = &krate.code[file];
                code.match_indices("crate::sandbox").all(|(at, _)| code[at..].starts_with("crate::sandbox::preamble"))
            })
    }));
    broken.extend(violations(&krate, |_, _, m| m == "run"));
    broken.extend(violations(&krate, |_, _, m| !krate.modules.contains(m)));
    assert!(broken.is_empty(), "import rules broken (ARCHITECTURE.md, \"Import rules\"):\n{}", broken.join("\n"));
}

#[test]
fn anyhow_lives_only_in_main_and_no_public_function_returns_a_string_error() {
    let krate = read_crate();
    let mut broken = Vec::new();
    for (file, code) in &krate.code {
        if !in_binary(file) && code.contains("anyhow") {
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
            // `FromStr` and the other conversion traits carry their error
            // as an associated type.
            if trimmed.replace(' ', "").starts_with("typeErr=String;") {
                broken.push(format!("{file}:{}: {}", i + 1, trimmed));
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

/// The string literals of `text` before its tests (`#[cfg(test)]`).
fn string_literals(text: &str) -> Vec<String> {
    let text = text.split("#[cfg(test)]").next().unwrap_or("");
    let chars: Vec<char> = text.chars().collect();
    let mut found = Vec::new();
    let mut i = 0;
    while i < chars.len() {
        if chars[i] == '/' && chars.get(i + 1) == Some(&'/') {
            while i < chars.len() && chars[i] != '\n' {
                i += 1;
            }
            continue;
        }
        if chars[i] == '\'' && chars.get(i + 2) == Some(&'\'') {
            i += 3;
            continue;
        }
        if chars[i] == '"' {
            let mut literal = String::new();
            i += 1;
            while i < chars.len() && chars[i] != '"' {
                if chars[i] == '\\' {
                    i += 1;
                }
                literal.extend(chars.get(i));
                i += 1;
            }
            found.push(literal);
        }
        i += 1;
    }
    found
}

/// Files that may name kinds: the registry and the built-ins themselves.
fn may_name_kinds(file: &str) -> bool {
    let top = file.split('/').next().unwrap_or("").trim_end_matches(".rs");
    file == "assemble/registry.rs" || BUILTIN_MODULES.contains(&top) || file.starts_with("builtin/")
}

#[test]
fn kinds_are_made_by_the_registry_alone_and_named_by_no_one_else() {
    let krate = read_crate();
    let kinds = subsume::assemble::registry::kinds();
    let src = support::repo_root().join("host/src");
    let mut broken = Vec::new();
    for (file, code) in &krate.code {
        if in_binary(file) || may_name_kinds(file) {
            continue;
        }
        let code = code.split("#[cfg(test)]").next().unwrap_or("");
        if code.contains("BuiltinKind::registered") && file != "config/mod.rs" {
            broken.push(format!("{file} makes a BuiltinKind"));
        }
        let text = std::fs::read_to_string(src.join(file)).unwrap();
        for literal in string_literals(&text) {
            let kind = literal.strip_prefix("builtin:").unwrap_or(&literal);
            // Names that are also words of other meaning (a log event, a
            // report section) are allowed where listed here.
            let allowed = [("portal/routes.rs", "log")];
            if kinds.contains(&kind) && !allowed.contains(&(file.as_str(), kind)) {
                broken.push(format!("{file} names kind \"{literal}\""));
            }
        }
    }
    for (file, code) in &krate.code {
        if file != "assemble/registry.rs" && code.replace(' ', "").contains("ComponentSource::Builtin(\"") {
            broken.push(format!("{file} writes ComponentSource::Builtin(\"...\")"));
        }
    }
    assert!(broken.is_empty(), "kinds named outside the registry and the built-ins:\n{}", broken.join("\n"));
}

#[test]
fn the_checker_sees_imports_and_ignores_docs() {
    let code = code_of(
        "use crate::{config::X, runtime};\n// crate::portal\nlet s = \"crate::deploy\"; let c = '\"'; crate::store::open();\nlet r = r#\"crate::sim \"x\"\"#; crate::sandbox::x();",
    );
    assert_eq!(crate_paths(&code).into_iter().collect::<Vec<_>>(), ["config", "runtime", "sandbox", "store"]);
}
