//! Built-ins: native components compiled into the host, named
//! `builtin:KIND` in the robot file. This module is their framework, not
//! any one of them: the [`Builtin`] trait each kind implements in its own
//! module (the arbiter in `arbiter`, the serial link in `robot`, the
//! simulated robot in `sim`, the network platform in `teleop`, `log` and
//! `publish` here), the declared parameters and their typed reader
//! ([`params`]), and what building one may use ([`BuildContext`]).
//! `assemble::registry` lists them.
//!
//! A built-in describes itself with the same [`Description`] as a WASM
//! guest and runs behind the same [`Component`] trait, so neither the
//! validator nor the scheduler tells them apart.
//!
//! Import rule: nothing here imports a built-in's module; they import this.

pub mod log;
pub mod params;
pub mod publish;

use std::any::{Any, TypeId};
use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};
use std::sync::Arc;

use thiserror::Error;

pub use self::params::{Bound, ParamDecl, ParamType, Params, check_values, number_in, positive_up_to};
use crate::config::{
    BuiltinKind, ComponentConfig, ComponentSource, ParamProblem, RobotConfig, RobotProblem, RobotView,
};
use crate::contract::{Description, PortSpec, ValueKind};
use crate::runtime::Component;
use crate::runtime::control_loop::{Clock, Waker};
use crate::runtime::wiring::PriorityCell;
use crate::sandbox::{LoadError, SandboxError, TranslatorArtifact, WasmTranslator};

/// Why a built-in did not start.
#[derive(Debug, Error)]
pub enum BuiltinError {
    /// A parameter the built-in read is not declared or not of its type
    /// (values are checked before any build, so this is a bug).
    #[error("parameter '{name}' {why}")]
    Param { name: String, why: String },
    /// A device, file, socket or thread the built-in needs failed.
    #[error("{what}: {source}")]
    Io {
        what: String,
        #[source]
        source: std::io::Error,
    },
    /// A WASM translator did not load.
    #[error(transparent)]
    Load(#[from] LoadError),
    /// A WASM translator did not start.
    #[error("translator: {0}")]
    Sandbox(#[from] SandboxError),
    /// The robot around the built-in does not let it start (a source
    /// without priority, a device naming no simulated robot, ...).
    #[error("{0}")]
    Refused(String),
}

impl BuiltinError {
    pub fn io(what: impl Into<String>, source: std::io::Error) -> BuiltinError {
        BuiltinError::Io { what: what.into(), source }
    }
}

/// A native component kind.
pub trait Builtin: Sync {
    /// The `KIND` of `builtin:KIND`.
    fn kind(&self) -> &'static str;
    /// One line for humans.
    fn summary(&self) -> &'static str;
    /// Every parameter, in the order the description lists them.
    fn params(&self) -> &'static [ParamDecl];
    /// Priority of its motion commands when the robot file gives none.
    fn default_priority(&self) -> Option<i32> {
        None
    }
    /// Whether a running instance owns something outside the host (a
    /// device, a pseudo-terminal, a socket): an activation carries an
    /// unchanged one into the next set instead of building it twice.
    fn carried(&self) -> bool {
        false
    }
    /// Whether it is built before the others, because it owns something
    /// they open (the simulated robot's pseudo-terminal).
    fn built_first(&self) -> bool {
        false
    }
    /// Whether its motion commands come from a person (a remote operator):
    /// such a source wins ties in an arbiter.
    fn answers_to_a_person(&self) -> bool {
        false
    }
    /// Whether it arbitrates between motion sources (its inputs are
    /// sources with priorities).
    fn arbitrates(&self) -> bool {
        false
    }
    /// Whether it guards the motors: the one kind that may feed a serial
    /// link's commands.
    fn guards_motors(&self) -> bool {
        false
    }
    /// The parameter naming a world file an upload may replace (the
    /// simulated robot's `world`).
    fn world_param(&self) -> Option<&'static str> {
        None
    }
    /// Checks between parameters and of the files they name, after each
    /// value passed its declaration. Every problem names its parameter.
    fn check(&self, params: &Params, ctx: &mut CheckContext<'_>) -> Vec<ParamProblem> {
        let _ = (params, ctx);
        Vec::new()
    }
    /// What this component becomes in a preflight: the robot file run in
    /// the simulator, in a process of its own beside the robot
    /// (docs/lab.md), which must reach none of the robot's devices,
    /// sockets or networks. Unchanged by default; an `Err` says why this
    /// component cannot take part in one.
    fn preflight(&self, params: &Params, ctx: &PreflightContext<'_>) -> Result<PreflightForm, NotSimulable> {
        let _ = (params, ctx);
        Ok(PreflightForm::default())
    }
    /// Rules about the robot around component `me` (this built-in, with its
    /// checked `params`): what feeds it, what it feeds, which components it
    /// names. Asked once every component and connection is known; each
    /// problem points into the robot file.
    fn check_robot(&self, me: usize, params: &Params, robot: &RobotView<'_>, registry: Registry) -> Vec<RobotProblem> {
        let _ = (me, params, robot, registry);
        Vec::new()
    }
    /// Inputs and outputs; they may depend on parameters (`publish`'s kind).
    fn ports(&self, params: &Params) -> Ports;
    /// A running instance, from checked parameters.
    fn build(&self, params: &Params, ctx: &mut BuildContext<'_>) -> Result<Box<dyn Component>, BuiltinError>;
}

/// What a preflight knows when it asks a built-in for its preflight form.
#[derive(Clone, Debug)]
pub struct PreflightContext<'a> {
    /// The component's name in the robot file.
    pub component: &'a str,
    /// The world file the preflight's simulated robots use (relative to
    /// the robot file it writes); `None`: each simulated robot keeps its
    /// own.
    pub world: Option<&'a str>,
    /// The name a simulated controller added for this component gets.
    pub sim_name: String,
}

/// Why a component cannot take part in a preflight (it names the
/// component and what the owner can do).
#[derive(Clone, Debug, PartialEq, Eq, Error)]
#[error("{0}")]
pub struct NotSimulable(pub String);

/// A built-in's preflight form: the parameters it runs with instead, and a
/// simulated controller to put behind it (a serial link to a real
/// device), with that controller's parameters.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct PreflightForm {
    pub set: Vec<(&'static str, String)>,
    /// Files to write beside the robot file, each named by a parameter
    /// (parameter, contents).
    pub files: Vec<(&'static str, Vec<u8>)>,
    pub simulated_by: Option<Vec<(&'static str, String)>>,
}

/// The registry's answer to "which built-in is this kind"
/// (`assemble::registry::builtin`): a built-in asks it what another
/// component is, without naming the other's kind.
pub type Registry = fn(BuiltinKind) -> &'static dyn Builtin;

/// The built-in component `index` of `robot` is, or `None` for a WASM
/// component (or no such component).
pub fn builtin_of(robot: &RobotConfig, index: usize, registry: Registry) -> Option<&'static dyn Builtin> {
    match robot.components.get(index).map(|c| &c.source) {
        Some(ComponentSource::Builtin(kind)) => Some(registry(*kind)),
        _ => None,
    }
}

/// The checked parameters of component `config`, a `builtin`.
pub fn checked_params(builtin: &dyn Builtin, config: &ComponentConfig) -> Result<Params, Vec<ParamProblem>> {
    let given: BTreeMap<String, String> = config.params.iter().map(|p| (p.name.clone(), p.value.clone())).collect();
    check_values(builtin.params(), &given)
}

/// A built-in's inputs and outputs.
#[derive(Clone, Debug, Default)]
pub struct Ports {
    pub inputs: Vec<PortSpec>,
    pub outputs: Vec<PortSpec>,
}

/// A port, for declarations.
pub fn port(name: &str, kind: ValueKind, doc: &str) -> PortSpec {
    PortSpec { name: name.into(), kind, doc: doc.into() }
}

/// The description of `builtin` with `params`.
pub fn describe(builtin: &dyn Builtin, params: &Params) -> Description {
    let ports = builtin.ports(params);
    Description {
        name: builtin.kind().to_string(),
        version: env!("CARGO_PKG_VERSION").into(),
        summary: builtin.summary().into(),
        inputs: ports.inputs,
        outputs: ports.outputs,
        params: builtin.params().iter().map(ParamDecl::spec).collect(),
        default_priority: builtin.default_priority(),
    }
}

/// Checks `given` (a component's `<param>` values) against `builtin`'s
/// declaration and its own checks; returns the checked parameters and the
/// description, or every problem.
pub fn resolve(
    builtin: &dyn Builtin,
    given: &BTreeMap<String, String>,
    ctx: &mut CheckContext<'_>,
) -> Result<(Params, Description), Vec<ParamProblem>> {
    let params = check_values(builtin.params(), given)?;
    let problems = builtin.check(&params, ctx);
    if !problems.is_empty() {
        return Err(problems);
    }
    let description = describe(builtin, &params);
    Ok((params, description))
}

/// Loads and starts WASM translators (the assembler's loader, with its
/// sandbox and compile cache).
pub trait WasmTranslators {
    /// Reads, compiles and links the translator component at `path`.
    fn load(&mut self, path: &Path) -> Result<Arc<TranslatorArtifact>, LoadError>;
    /// A running translator of `artifact` for serial link `link`, under the
    /// link's limits, initialised with its parameters and `extra` ones.
    fn start(
        &mut self,
        artifact: &TranslatorArtifact,
        link: &ComponentConfig,
        extra: Vec<crate::contract::Param>,
    ) -> Result<WasmTranslator, SandboxError>;
}

/// What a built-in's check may use.
pub struct CheckContext<'a> {
    /// The robot file's folder: file parameters are relative to it.
    pub base_dir: &'a Path,
    pub translators: &'a mut dyn WasmTranslators,
}

/// What building a built-in may use beyond its parameters.
pub struct BuildContext<'a> {
    pub robot: &'a RobotConfig,
    /// Index of the component being built, in `robot.components`.
    pub index: usize,
    /// The robot file's folder.
    pub base_dir: &'a Path,
    /// Pseudo-terminals of the simulated robots built so far, by component
    /// name (a serial link's `device="sim:NAME"`).
    pub ptys: &'a mut HashMap<String, PathBuf>,
    /// Every component's current priority (the arbiter reads them; the
    /// network platform moves its own).
    pub priorities: &'a [PriorityCell],
    /// The control loop's clock and a waker for it.
    pub clock: Clock,
    pub waker: Waker,
    pub services: &'a Services,
    pub translators: &'a mut dyn WasmTranslators,
    pub registry: Registry,
}

impl BuildContext<'_> {
    /// The component being built.
    pub fn component(&self) -> Result<&ComponentConfig, BuiltinError> {
        self.robot.components.get(self.index).ok_or_else(|| BuiltinError::Refused("no such component".into()))
    }
}

/// What the host shares with the built-ins it starts, beyond one robot,
/// by type: the portal's users, the registry of running network platforms,
/// ... The module that needs a service defines its type; the composition
/// root provides it.
#[derive(Clone, Default)]
pub struct Services(HashMap<TypeId, Arc<dyn Any + Send + Sync>>);

impl std::fmt::Debug for Services {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Services({} provided)", self.0.len())
    }
}

impl Services {
    /// These services and `service`.
    pub fn with<T: Any + Send + Sync>(mut self, service: Arc<T>) -> Services {
        self.0.insert(TypeId::of::<T>(), service);
        self
    }

    /// The service of type `T`, if the host provides one.
    pub fn get<T: Any + Send + Sync>(&self) -> Option<Arc<T>> {
        self.0.get(&TypeId::of::<T>()).cloned().and_then(|s| s.downcast::<T>().ok())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn services_are_found_by_type() {
        let services = Services::default().with(Arc::new(7u32)).with(Arc::new(String::from("x")));
        assert_eq!(services.get::<u32>().as_deref(), Some(&7));
        assert_eq!(services.get::<String>().as_deref().map(String::as_str), Some("x"));
        assert!(services.get::<i64>().is_none());
    }
}
