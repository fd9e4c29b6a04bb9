//! The robot description: XML text -> typed, validated [`RobotConfig`].
//!
//! Two stages. [`raw`] reads the file as written (quick-xml, spans kept,
//! unknown elements and attributes rejected); [`validate`] resolves names,
//! loads each component's self-description through a [`Resolver`] and checks
//! the wiring against it. Both stages report every problem they find, as
//! `file:line:column: message`; a file with any problem yields no config, so
//! nothing starts. The format is documented in `docs/config.md` and
//! `config/robot.xsd`.

pub mod diagnostic;
pub mod limits;
pub mod raw;
pub mod validate;

use std::path::{Path, PathBuf};
use std::time::Duration;

pub use diagnostic::{Diagnostic, Diagnostics, SourceMap};
pub use validate::{ParamProblem, ResolveError, Resolver, RobotProblem, RobotView, parse_duration, parse_size};

use crate::contract::{Description, Param};
pub use crate::runtime::wiring::{Policy, RestartPolicy};

/// The two platforms of the paper: the network platform (remote operators)
/// and the control platform (the robot's own behaviours).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Platform {
    Network,
    Control,
}

/// A platform name that is neither `network` nor `control`.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[error("unknown platform '{0}' (expected network or control)")]
pub struct UnknownPlatform(pub String);

impl Platform {
    /// Parses a platform name as the command line and the API write it.
    pub fn parse(text: &str) -> Result<Platform, UnknownPlatform> {
        match text {
            "network" => Ok(Platform::Network),
            "control" => Ok(Platform::Control),
            other => Err(UnknownPlatform(crate::contract::clip(other))),
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            Platform::Network => "network",
            Platform::Control => "control",
        }
    }
}

/// The kind of a built-in (`KIND` of `builtin:KIND`). Only the registry
/// (`assemble::registry`) makes one, so a kind always names a built-in that
/// exists, and questions about it are asked of the registry's built-in, not
/// of its name (the architecture test checks both).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct BuiltinKind {
    /// The built-in's place in the registry's list.
    index: usize,
    name: &'static str,
}

impl BuiltinKind {
    /// The registry's kind number `index`, named `name`. For the registry
    /// alone.
    #[doc(hidden)]
    pub const fn registered(index: usize, name: &'static str) -> BuiltinKind {
        BuiltinKind { index, name }
    }

    /// Its place in the registry's list.
    pub fn index(self) -> usize {
        self.index
    }

    pub fn name(self) -> &'static str {
        self.name
    }
}

impl std::fmt::Display for BuiltinKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name)
    }
}

/// Where a component's code comes from.
#[derive(Clone, Debug, PartialEq, Eq, Hash)]
pub enum ComponentSource {
    /// A native component compiled into the host (`builtin:log`).
    Builtin(BuiltinKind),
    /// A WASM component file; relative paths are resolved against the
    /// directory of the robot file.
    Wasm(PathBuf),
}

impl std::fmt::Display for ComponentSource {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            ComponentSource::Builtin(kind) => write!(f, "builtin:{kind}"),
            ComponentSource::Wasm(path) => write!(f, "{}", path.display()),
        }
    }
}

/// A validated robot: every component loaded and described, every
/// connection checked.
#[derive(Clone, Debug)]
pub struct RobotConfig {
    pub name: String,
    /// The robot file this came from.
    pub path: PathBuf,
    pub components: Vec<ComponentConfig>,
    pub connections: Vec<ConnectionConfig>,
}

impl RobotConfig {
    /// `COMPONENT.PORT` of an output, as the robot file writes it.
    pub fn output_name(&self, port: PortRef) -> String {
        self.port_name(port, true)
    }

    /// `COMPONENT.PORT` of an input, as the robot file writes it.
    pub fn input_name(&self, port: PortRef) -> String {
        self.port_name(port, false)
    }

    fn port_name(&self, port: PortRef, output: bool) -> String {
        self.components.get(port.component).map_or_else(String::new, |c| {
            let ports = if output { &c.description.outputs } else { &c.description.inputs };
            format!("{}.{}", c.name, ports.get(port.port as usize).map_or("?", |p| p.name.as_str()))
        })
    }
}

#[derive(Clone, Debug)]
pub struct ComponentConfig {
    pub name: String,
    /// Byte offset of the `<component>` element in the robot file.
    pub offset: usize,
    pub platform: Platform,
    pub source: ComponentSource,
    /// From the XML file, else the component's own default, else none.
    pub priority: Option<i32>,
    /// Ticks per second; 0 means the component only reacts to input.
    pub rate_hz: f64,
    /// Time budget of each call into the component.
    pub budget: Duration,
    /// As a motion source: how long it stays active after its last command.
    pub timeout: Duration,
    /// Linear memory limit.
    pub memory_bytes: u64,
    /// Caps on what the component may push at the host.
    pub max_emits: u32,
    pub max_message_bytes: u64,
    pub max_logs_per_s: u32,
    /// Whether and how often a faulted WASM component is restarted.
    pub restart: Option<RestartPolicy>,
    /// Every declared parameter, XML value or default, in declaration order.
    pub params: Vec<Param>,
    pub description: Description,
}

/// One port of one component: `component` indexes `RobotConfig::components`,
/// `port` the component's inputs or outputs.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct PortRef {
    pub component: usize,
    pub port: u32,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ConnectionConfig {
    /// Byte offset of the `<connect>`'s `from` attribute in the robot file
    /// (where a robot-wide rule about the connection points).
    pub offset: usize,
    /// An output port.
    pub from: PortRef,
    /// An input port.
    pub to: PortRef,
    pub policy: Policy,
    /// The platform whose `<platform>` element declares the connection.
    pub platform: Platform,
}

/// Reads, parses and validates the robot file at `path`.
pub fn load(path: &Path, resolver: &mut dyn Resolver) -> Result<RobotConfig, Diagnostics> {
    load_with(path, resolver, &[])
}

/// A parameter set from outside the robot file (`--param comp.name=value`),
/// replacing or adding a `<param>` before validation.
#[derive(Clone, Debug, PartialEq, Eq, serde::Serialize, schemars::JsonSchema)]
pub struct ParamOverride {
    pub component: String,
    pub param: String,
    pub value: String,
}

/// A `--param` that is not `COMPONENT.PARAM=VALUE`.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[error("'{0}' is not COMPONENT.PARAM=VALUE")]
pub struct BadOverride(pub String);

impl std::str::FromStr for ParamOverride {
    type Err = BadOverride;

    fn from_str(text: &str) -> Result<Self, Self::Err> {
        let shape = || BadOverride(text.to_string());
        let (target, value) = text.split_once('=').ok_or_else(shape)?;
        let (component, param) = target.split_once('.').ok_or_else(shape)?;
        if component.is_empty() || param.is_empty() {
            return Err(shape());
        }
        Ok(ParamOverride { component: component.into(), param: param.into(), value: value.into() })
    }
}

/// Like [`load`], with parameters overridden from the command line.
pub fn load_with(
    path: &Path,
    resolver: &mut dyn Resolver,
    overrides: &[ParamOverride],
) -> Result<RobotConfig, Diagnostics> {
    let text = read_config(path)?;
    parse_and_validate_with(path, &text, resolver, overrides)
}

/// Reads a robot file, bounded by [`limits::MAX_CONFIG_BYTES`].
pub fn read_config(path: &Path) -> Result<String, Diagnostics> {
    let fail =
        |message: String| Diagnostics(vec![Diagnostic { path: path.to_path_buf(), line: 1, column: 1, message }]);
    let size = std::fs::metadata(path).map_err(|e| fail(format!("cannot read robot file: {e}")))?.len();
    if size > limits::MAX_CONFIG_BYTES {
        return Err(fail(format!("robot file is {size} bytes; at most {} are allowed", limits::MAX_CONFIG_BYTES)));
    }
    let bytes = std::fs::read(path).map_err(|e| fail(format!("cannot read robot file: {e}")))?;
    String::from_utf8(bytes).map_err(|e| fail(format!("robot file is not utf-8: {e}")))
}

/// Reads the robot file at `path` and parses it (the XML, its elements and
/// their attributes) without validating it against components: what a
/// client checks before it sends the file to a portal. Its text, or every
/// error located in it.
pub fn read_and_parse(path: &Path) -> Result<String, Diagnostics> {
    let text = read_config(path)?;
    let mut errors = Vec::new();
    raw::parse(&SourceMap::new(path, &text), &text, &mut errors);
    if errors.is_empty() { Ok(text) } else { Err(Diagnostics(errors)) }
}

/// Parses and validates robot-file `text`; `path` names it in diagnostics and
/// anchors relative component paths.
pub fn parse_and_validate(path: &Path, text: &str, resolver: &mut dyn Resolver) -> Result<RobotConfig, Diagnostics> {
    parse_and_validate_with(path, text, resolver, &[])
}

/// Like [`parse_and_validate`], with parameters overridden. An override of
/// a component the file does not have is an error.
pub fn parse_and_validate_with(
    path: &Path,
    text: &str,
    resolver: &mut dyn Resolver,
    overrides: &[ParamOverride],
) -> Result<RobotConfig, Diagnostics> {
    parse_and_validate_overriding(path, text, resolver, overrides, false)
}

/// Like [`parse_and_validate_with`], but an override of a component the file
/// does not have is skipped: a run's `--param`s apply to every set the
/// portal activates, and not every set has every component.
pub fn parse_and_validate_for_run(
    path: &Path,
    text: &str,
    resolver: &mut dyn Resolver,
    overrides: &[ParamOverride],
) -> Result<RobotConfig, Diagnostics> {
    parse_and_validate_overriding(path, text, resolver, overrides, true)
}

fn parse_and_validate_overriding(
    path: &Path,
    text: &str,
    resolver: &mut dyn Resolver,
    overrides: &[ParamOverride],
    skip_unknown: bool,
) -> Result<RobotConfig, Diagnostics> {
    let map = SourceMap::new(path, text);
    let mut errors = Vec::new();
    let mut raw = raw::parse(&map, text, &mut errors);
    for o in overrides {
        let component =
            raw.platforms.iter_mut().flat_map(|p| p.components.iter_mut()).find(|c| c.name.value == o.component);
        let Some(component) = component else {
            if skip_unknown {
                continue;
            }
            errors.push(Diagnostic {
                path: PathBuf::from("--param"),
                line: 1,
                column: 1,
                message: format!("no component '{}' in {} to set '{}' on", o.component, path.display(), o.param),
            });
            continue;
        };
        let value = raw::Spanned { value: o.value.clone(), offset: component.offset };
        match component.params.iter_mut().find(|p| p.name.value == o.param) {
            Some(param) => param.value = value,
            None => component.params.push(raw::RawParam {
                offset: component.offset,
                name: raw::Spanned { value: o.param.clone(), offset: component.offset },
                value,
            }),
        }
    }
    let robot = raw.complete.then(|| validate::validate(&map, path, raw, resolver, &mut errors));
    match robot {
        Some(robot) if errors.is_empty() => Ok(robot),
        _ => {
            // Stage 1 and stage 2 find problems in different orders; the
            // reader wants them in file order (stable: same place, found order).
            errors.sort_by_key(|d| (d.line, d.column));
            Err(Diagnostics(errors))
        }
    }
}
