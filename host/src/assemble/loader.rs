//! Turns component sources into descriptions (for validation) and running
//! components (for the graph). WASM files are read with a size limit and
//! compiled once per loader; built-ins come from the [`registry`], their
//! parameters checked against their declarations.
//!
//! [`registry`]: super::registry

use std::collections::{BTreeMap, HashMap};
use std::path::{Component as PathPart, Path, PathBuf};
use std::sync::Arc;

use super::registry;
use crate::builtin::{self, BuildContext, BuiltinError, CheckContext, Params, Services, WasmTranslators};
use crate::config::{
    BuiltinKind, ComponentConfig, ComponentSource, ParamProblem, ResolveError, Resolver, RobotConfig, RobotProblem,
    RobotView,
};
use crate::contract::{Description, Param, clip};
use crate::runtime::control_loop::{Clock, Waker};
use crate::runtime::{Component, PriorityCell, Restarter};
use crate::sandbox::{
    GuestLimits, LoadError, Sandbox, SandboxError, TranslatorArtifact, WasmArtifact, WasmTranslator,
    read_component_file,
};

/// Why a component did not start.
#[derive(Debug, thiserror::Error)]
pub enum StartError {
    #[error("failed to start component '{name}': {source}")]
    Builtin {
        name: String,
        #[source]
        source: BuiltinError,
    },
    #[error("failed to start component '{name}': {source}")]
    Load {
        name: String,
        #[source]
        source: LoadError,
    },
    #[error("failed to start component '{name}': {source}")]
    Wasm {
        name: String,
        #[source]
        source: SandboxError,
    },
    #[error("failed to start component '{name}': {why}")]
    Unknown { name: String, why: String },
}

/// What building one component may use from the graph being built.
pub struct Surroundings<'s> {
    pub robot: &'s RobotConfig,
    pub ptys: &'s mut HashMap<String, PathBuf>,
    pub priorities: &'s [PriorityCell],
    pub clock: Clock,
    pub waker: Waker,
    pub services: &'s Services,
}

/// Loads components through one sandbox, compiling each file once.
pub struct Loader<'a> {
    sandbox: &'a Sandbox,
    artifacts: HashMap<PathBuf, Result<Arc<WasmArtifact>, LoadError>>,
    translators: HashMap<PathBuf, Result<Arc<TranslatorArtifact>, LoadError>>,
    /// File parameters of built-ins must stay inside the robot's folder
    /// (robot files uploaded through the portal).
    confined: bool,
}

impl<'a> Loader<'a> {
    pub fn new(sandbox: &'a Sandbox) -> Loader<'a> {
        Loader { sandbox, artifacts: HashMap::new(), translators: HashMap::new(), confined: false }
    }

    /// A loader that refuses built-in file parameters reaching outside the
    /// robot's folder (absolute paths, `..`).
    pub fn confined(sandbox: &'a Sandbox) -> Loader<'a> {
        Loader { confined: true, ..Loader::new(sandbox) }
    }

    pub fn sandbox(&self) -> &'a Sandbox {
        self.sandbox
    }

    /// The compiled artifact of the `.wasm` file at `path`.
    pub fn load_wasm(&mut self, path: &Path) -> Result<Arc<WasmArtifact>, LoadError> {
        if let Some(result) = self.artifacts.get(path) {
            return result.clone();
        }
        let sandbox = self.sandbox;
        let result = read_component_file(path).and_then(|bytes| {
            sandbox.load(&bytes).map_err(|source| LoadError::Component { path: path.to_path_buf(), source })
        });
        self.artifacts.insert(path.to_path_buf(), result.clone());
        result
    }

    /// The compiled translator of the `.wasm` file at `path`.
    pub fn load_translator(&mut self, path: &Path) -> Result<Arc<TranslatorArtifact>, LoadError> {
        if let Some(result) = self.translators.get(path) {
            return result.clone();
        }
        let sandbox = self.sandbox;
        let result = read_component_file(path).and_then(|bytes| {
            sandbox.load_translator(&bytes).map_err(|source| LoadError::Translator { path: path.to_path_buf(), source })
        });
        self.translators.insert(path.to_path_buf(), result.clone());
        result
    }

    /// A running, initialised instance of component `index` of `around.robot`.
    pub fn instantiate(&mut self, index: usize, around: Surroundings<'_>) -> Result<Box<dyn Component>, StartError> {
        let Some(config) = around.robot.components.get(index) else {
            return Err(StartError::Unknown { name: format!("#{index}"), why: "no such component".into() });
        };
        let name = config.name.clone();
        match &config.source {
            ComponentSource::Builtin(kind) => {
                let builtin = registry::builtin(*kind);
                let params = builtin::checked_params(builtin, config).map_err(|problems| StartError::Unknown {
                    name: name.clone(),
                    why: ResolveError::Params(problems).to_string(),
                })?;
                let base_dir = around.robot.path.parent().unwrap_or(Path::new("")).to_path_buf();
                let mut ctx = BuildContext {
                    robot: around.robot,
                    index,
                    base_dir: &base_dir,
                    ptys: around.ptys,
                    priorities: around.priorities,
                    clock: around.clock,
                    waker: around.waker,
                    services: around.services,
                    translators: self,
                    registry: registry::builtin,
                };
                builtin.build(&params, &mut ctx).map_err(|source| StartError::Builtin { name, source })
            }
            ComponentSource::Wasm(path) => {
                let artifact =
                    self.load_wasm(path).map_err(|source| StartError::Load { name: name.clone(), source })?;
                let component = self
                    .sandbox
                    .instantiate(&artifact, &config.name, &GuestLimits::of(config), &config.params)
                    .map_err(|source| StartError::Wasm { name, source })?;
                Ok(Box::new(component))
            }
        }
    }

    /// A restarter for `config` when it is a WASM component with a restart
    /// policy.
    pub fn restarter(&mut self, config: &ComponentConfig) -> Option<Restarter> {
        let (ComponentSource::Wasm(path), Some(_)) = (&config.source, config.restart) else { return None };
        let artifact = self.load_wasm(path).ok()?;
        Some(self.sandbox.restarter(artifact, &config.name, GuestLimits::of(config), config.params.clone()))
    }

    /// Problems with built-in file parameters that reach outside the
    /// robot's folder, when this loader is confined.
    fn confinement(&self, builtin: &dyn builtin::Builtin, params: &BTreeMap<String, String>) -> Vec<ParamProblem> {
        if !self.confined {
            return Vec::new();
        }
        let mut problems = Vec::new();
        for decl in builtin.params() {
            let Some(file) = params.get(decl.name).and_then(|v| decl.file(v)) else { continue };
            if Path::new(file).components().any(|p| !matches!(p, PathPart::Normal(_))) {
                problems.push(ParamProblem::new(
                    decl.name,
                    format!("must be a path inside the robot's folder, got '{}'", clip(file)),
                ));
            }
        }
        problems
    }
}

fn unknown_builtin(kind: &str) -> String {
    format!("unknown built-in '{}' (known: {})", clip(kind), registry::kinds().join(", "))
}

impl Resolver for Loader<'_> {
    fn builtin_kind(&self, kind: &str) -> Result<BuiltinKind, ResolveError> {
        registry::kind(kind).ok_or_else(|| ResolveError::Source(unknown_builtin(kind)))
    }

    fn check_robot(&self, view: &RobotView<'_>) -> Vec<RobotProblem> {
        check_robot(view)
    }

    fn describe(
        &mut self,
        source: &ComponentSource,
        params: &BTreeMap<String, String>,
        base_dir: &Path,
    ) -> Result<Description, ResolveError> {
        match source {
            ComponentSource::Builtin(kind) => {
                let builtin = registry::builtin(*kind);
                let outside = self.confinement(builtin, params);
                if !outside.is_empty() {
                    return Err(ResolveError::Params(outside));
                }
                let mut ctx = CheckContext { base_dir, translators: self };
                builtin::resolve(builtin, params, &mut ctx)
                    .map(|(_, description)| description)
                    .map_err(ResolveError::Params)
            }
            ComponentSource::Wasm(path) => {
                self.load_wasm(path).map(|a| a.description.clone()).map_err(|e| ResolveError::Source(e.to_string()))
            }
        }
    }
}

impl WasmTranslators for Loader<'_> {
    fn load(&mut self, path: &Path) -> Result<Arc<TranslatorArtifact>, LoadError> {
        self.load_translator(path)
    }

    fn start(
        &mut self,
        artifact: &TranslatorArtifact,
        link: &ComponentConfig,
        extra: Vec<Param>,
    ) -> Result<WasmTranslator, SandboxError> {
        let mut params = link.params.clone();
        params.extend(extra);
        self.sandbox.instantiate_translator(artifact, &link.name, &GuestLimits::of(link), &params)
    }
}

/// The checked parameters of built-in component `config`, or `None` when it
/// is not a built-in.
pub fn builtin_params(config: &ComponentConfig) -> Option<Params> {
    let ComponentSource::Builtin(kind) = &config.source else { return None };
    builtin::checked_params(registry::builtin(*kind), config).ok()
}

/// Every built-in's robot-wide rules (`Builtin::check_robot`).
pub fn check_robot(view: &RobotView<'_>) -> Vec<RobotProblem> {
    let mut problems = Vec::new();
    for (index, component) in view.robot.components.iter().enumerate() {
        let ComponentSource::Builtin(kind) = &component.source else { continue };
        let builtin = registry::builtin(*kind);
        // Its own checks passed, so its parameters do.
        let Ok(params) = builtin::checked_params(builtin, component) else { continue };
        problems.extend(builtin.check_robot(index, &params, view, registry::builtin));
    }
    problems
}
