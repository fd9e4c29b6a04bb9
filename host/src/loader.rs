//! Turns component sources into descriptions (for validation) and running
//! components (for the graph). WASM files are read with a size limit and
//! compiled once per run; built-ins come from [`crate::builtin`].

use std::collections::{BTreeMap, HashMap};
use std::io::Read;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use crate::builtin::{self, BuildContext, TranslatorChoice, TranslatorLoader};
use crate::config::{ComponentConfig, ComponentSource, Resolver};
use crate::contract::Description;
use crate::robot::translator::Translator;
use crate::runtime::Component;
use crate::sandbox::{GuestLimits, Sandbox, TranslatorArtifact, WasmArtifact};

/// Largest `.wasm` file loaded: big enough for Python and JavaScript
/// components (~20 MB), small enough that a bogus file cannot exhaust memory.
pub const MAX_COMPONENT_BYTES: u64 = 32 << 20;

/// Loads components through one sandbox, compiling each file once.
pub struct Loader<'a> {
    sandbox: &'a Sandbox,
    artifacts: HashMap<PathBuf, Result<Arc<WasmArtifact>, String>>,
    translators: HashMap<PathBuf, Result<Arc<TranslatorArtifact>, String>>,
}

impl<'a> Loader<'a> {
    pub fn new(sandbox: &'a Sandbox) -> Loader<'a> {
        Loader { sandbox, artifacts: HashMap::new(), translators: HashMap::new() }
    }

    /// The compiled artifact of the `.wasm` file at `path`.
    pub fn load_wasm(&mut self, path: &Path) -> Result<Arc<WasmArtifact>, String> {
        if let Some(result) = self.artifacts.get(path) {
            return result.clone();
        }
        let result = read_component_file(path)
            .and_then(|bytes| self.sandbox.load(&bytes).map_err(|e| format!("cannot load '{}': {e}", path.display())));
        self.artifacts.insert(path.to_path_buf(), result.clone());
        result
    }

    /// The compiled translator of the `.wasm` file at `path`.
    pub fn load_translator(&mut self, path: &Path) -> Result<Arc<TranslatorArtifact>, String> {
        if let Some(result) = self.translators.get(path) {
            return result.clone();
        }
        let result = read_component_file(path).and_then(|bytes| {
            self.sandbox
                .load_translator(&bytes)
                .map_err(|e| format!("cannot load translator '{}': {e}", path.display()))
        });
        self.translators.insert(path.to_path_buf(), result.clone());
        result
    }

    /// A running, initialised instance of component `ctx.index` of
    /// `ctx.robot`.
    pub fn instantiate(&mut self, ctx: &mut BuildContext<'_>) -> Result<Box<dyn Component>, String> {
        let Some(config) = ctx.robot.components.get(ctx.index) else {
            return Err("no such component".into());
        };
        match &config.source {
            ComponentSource::Builtin(kind) => builtin::instantiate(kind, ctx, self),
            ComponentSource::Wasm(path) => {
                let artifact = self.load_wasm(path)?;
                let component = self
                    .sandbox
                    .instantiate(&artifact, &config.name, &GuestLimits::of(config), &config.params)
                    .map_err(|e| e.to_string())?;
                Ok(Box::new(component))
            }
        }
    }
}

impl Loader<'_> {
    /// A restarter for `config` when it is a WASM component with a restart
    /// policy.
    pub fn restarter(&mut self, config: &ComponentConfig) -> Option<crate::runtime::Restarter> {
        let (ComponentSource::Wasm(path), Some(_)) = (&config.source, config.restart) else { return None };
        let artifact = self.load_wasm(path).ok()?;
        Some(self.sandbox.restarter(artifact, &config.name, GuestLimits::of(config), config.params.clone()))
    }
}

impl Resolver for Loader<'_> {
    fn describe(
        &mut self,
        source: &ComponentSource,
        params: &BTreeMap<String, String>,
        base_dir: &Path,
    ) -> Result<Description, String> {
        match source {
            ComponentSource::Builtin(kind) => {
                let description = builtin::describe(kind, params, base_dir)?;
                if kind == "serial"
                    && let TranslatorChoice::Wasm(path) = builtin::translator_choice(params, base_dir)?
                {
                    self.load_translator(&path)?;
                }
                Ok(description)
            }
            ComponentSource::Wasm(path) => self.load_wasm(path).map(|a| a.description.clone()),
        }
    }
}

impl TranslatorLoader for Loader<'_> {
    fn wasm_translator(&mut self, path: &Path, link: &ComponentConfig) -> Result<Box<dyn Translator>, String> {
        let artifact = self.load_translator(path)?;
        let translator = self
            .sandbox
            .instantiate_translator(&artifact, &link.name, &GuestLimits::of(link), &link.params)
            .map_err(|e| format!("translator '{}': {e}", path.display()))?;
        Ok(Box::new(translator))
    }
}

/// Reads a component file, refusing files over [`MAX_COMPONENT_BYTES`].
pub fn read_component_file(path: &Path) -> Result<Vec<u8>, String> {
    let file = std::fs::File::open(path).map_err(|e| format!("cannot read '{}': {e}", path.display()))?;
    let mut bytes = Vec::new();
    file.take(MAX_COMPONENT_BYTES + 1)
        .read_to_end(&mut bytes)
        .map_err(|e| format!("cannot read '{}': {e}", path.display()))?;
    if bytes.len() as u64 > MAX_COMPONENT_BYTES {
        return Err(format!("'{}' is larger than {} MiB", path.display(), MAX_COMPONENT_BYTES >> 20));
    }
    Ok(bytes)
}
