//! `subsume describe`: what a component (a `.wasm` file or `builtin:KIND`)
//! declares.

use std::fmt::Write as _;
use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::{Context as _, bail};
use subsume::assemble::registry;
use subsume::contract::{Description, DescriptionDoc};
use subsume::sandbox::{Sandbox, read_component_file};

use super::Context;

/// Print what a component declares: ports, parameters, default priority.
/// COMPONENT is a .wasm file or builtin:KIND (with its parameters' bounds).
#[derive(clap::Args)]
pub struct DescribeCommand {
    component: PathBuf,
    /// Print JSON instead of text.
    #[arg(long)]
    json: bool,
}

impl DescribeCommand {
    pub fn execute(self, context: &Context) -> anyhow::Result<ExitCode> {
        if let Some(kind) = self.component.to_str().and_then(|p| p.strip_prefix("builtin:")) {
            return describe_builtin(kind, self.json);
        }
        let path = &self.component;
        let sandbox = Sandbox::new(context.cache_dir.clone())?;
        let bytes = read_component_file(path)?;
        let artifact = sandbox.load(&bytes).with_context(|| format!("failed to load component {}", path.display()))?;
        let d = &artifact.description;
        if self.json {
            let mut doc = serde_json::to_value(DescriptionDoc::new(d, &artifact.sha256))?;
            doc["contract"] = artifact.contract.name().into();
            println!("{}", serde_json::to_string_pretty(&doc)?);
        } else {
            print!("{}", description_text(d, &artifact.sha256));
            println!("contract: subsume:robot@{}", artifact.contract.name());
        }
        Ok(ExitCode::SUCCESS)
    }
}

/// `subsume describe builtin:KIND`: the declaration, with every
/// parameter's bounds and unit.
fn describe_builtin(kind: &str, as_json: bool) -> anyhow::Result<ExitCode> {
    let Some(builtin) = registry::find(kind) else {
        bail!("unknown built-in '{kind}' (known: {})", registry::kinds().join(", "));
    };
    let defaults = subsume::builtin::check_values(builtin.params(), &Default::default()).unwrap_or_default();
    let d = subsume::builtin::describe(builtin, &defaults);
    if as_json {
        let params: Vec<serde_json::Value> = builtin
            .params()
            .iter()
            .map(|p| {
                serde_json::json!({
                    "name": p.name, "kind": p.kind().name(), "default": p.default, "unit": p.unit,
                    "expected": p.expected(), "doc": p.doc,
                })
            })
            .collect();
        let mut doc = serde_json::to_value(DescriptionDoc::new(&d, ""))?;
        doc["params"] = params.into();
        doc["carried"] = builtin.carried().into();
        println!("{}", serde_json::to_string_pretty(&doc)?);
        return Ok(ExitCode::SUCCESS);
    }
    let mut s = description_text(&d, "");
    if let Some(at) = s.find("params:\n") {
        s.truncate(at);
    }
    let _ = writeln!(s, "params:");
    if builtin.params().is_empty() {
        let _ = writeln!(s, "  (none)");
    }
    for p in builtin.params() {
        let default = p.default_in_words();
        let _ = writeln!(s, "  {} ({default}): {}; {}", p.name, p.expected(), p.doc);
    }
    print!("{s}");
    Ok(ExitCode::SUCCESS)
}

fn description_text(d: &Description, sha256: &str) -> String {
    let mut s = String::new();
    let _ = writeln!(s, "{} {}: {}", d.name, d.version, d.summary);
    if !sha256.is_empty() {
        let _ = writeln!(s, "sha256: {sha256}");
    }
    let priority = d.default_priority.map_or_else(|| "none (emits no motion commands)".to_string(), |p| p.to_string());
    let _ = writeln!(s, "default priority: {priority}");
    for (title, ports) in [("inputs", &d.inputs), ("outputs", &d.outputs)] {
        let _ = writeln!(s, "{title}:");
        if ports.is_empty() {
            let _ = writeln!(s, "  (none)");
        }
        for (i, p) in ports.iter().enumerate() {
            let _ = writeln!(s, "  {i}: {} ({}) {}", p.name, p.kind.name(), p.doc);
        }
    }
    let _ = writeln!(s, "params:");
    if d.params.is_empty() {
        let _ = writeln!(s, "  (none)");
    }
    for p in &d.params {
        let _ = writeln!(s, "  {} ({}, default '{}') {}", p.name, p.kind.name(), p.default_value, p.doc);
    }
    s
}
