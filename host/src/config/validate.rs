//! Stage 2: the as-written tree checked and given meaning. Names are unique,
//! numbers parse and sit in their ranges, every component's source loads and
//! describes itself, parameters are declared by the component and fit their
//! kinds, connections join an existing output to an existing input of a
//! compatible kind. Every problem is reported, each at its own position.

use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};
use std::time::Duration;

use super::diagnostic::{Diagnostic, SourceMap};
use super::raw::{RawComponent, RawConnect, RawRobot, Spanned};
use super::{
    BuiltinKind, ComponentConfig, ComponentSource, ConnectionConfig, Platform, Policy, PortRef, RobotConfig, limits,
};
use crate::contract::{Description, Param, ValueKind, clip, is_valid_name};

/// Finds what a component's source declares. The assembler's loader
/// compiles WASM files (and keeps them for running) and checks built-ins'
/// parameters against their declarations; tests may describe from tables.
pub trait Resolver {
    /// The built-in `builtin:KIND` names (reported at the `source` attribute
    /// when there is none).
    fn builtin_kind(&self, kind: &str) -> Result<BuiltinKind, ResolveError>;
    /// The description of the component at `source`. Built-ins check their
    /// XML `params` and may shape their ports from them. `base_dir` is the
    /// robot file's folder (for relative paths in params).
    fn describe(
        &mut self,
        source: &ComponentSource,
        params: &BTreeMap<String, String>,
        base_dir: &Path,
    ) -> Result<Description, ResolveError>;
    /// Each built-in's rules about the robot around it (what feeds it, what
    /// it feeds, which other components it names), asked once every
    /// component and connection is known.
    fn check_robot(&self, robot: &RobotView<'_>) -> Vec<RobotProblem>;
}

/// The robot as the robot-wide rules see it: the components that passed
/// their own checks and the connections between them.
pub struct RobotView<'a> {
    pub robot: &'a RobotConfig,
    /// Components that lost a connection because its other end failed its
    /// own checks (by index): a rule about their wiring would only repeat
    /// that error, so it skips them.
    pub lost_wiring: &'a [bool],
    /// Components the file names that failed their own checks.
    pub failed: &'a [String],
}

impl RobotView<'_> {
    /// Whether component `index`'s wiring is all there to check.
    pub fn wiring_known(&self, index: usize) -> bool {
        !self.lost_wiring.get(index).copied().unwrap_or(false)
    }

    /// Whether the file names a component `name` that failed its own checks
    /// (a rule about it would only repeat that error).
    pub fn failed(&self, name: &str) -> bool {
        self.failed.iter().any(|f| f == name)
    }
}

/// A robot-wide rule broken, at a place in the robot file.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct RobotProblem {
    /// Byte offset of what it is about (a component, a connection).
    pub offset: usize,
    /// Lowercase, complete.
    pub message: String,
}

/// Why a component's source gave no description.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum ResolveError {
    /// The source cannot be read, loaded or described (reported at the
    /// `source` attribute).
    #[error("{0}")]
    Source(String),
    /// Parameters with bad values (each reported at its `<param>`).
    #[error("{}", .0.iter().map(ToString::to_string).collect::<Vec<_>>().join("; "))]
    Params(Vec<ParamProblem>),
}

/// A bad parameter value, found before anything starts.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ParamProblem {
    /// The parameter it is about.
    pub name: String,
    /// Lowercase; completes "parameter 'NAME' of component 'C' ...".
    pub message: String,
}

impl ParamProblem {
    pub fn new(name: &str, message: impl Into<String>) -> ParamProblem {
        ParamProblem { name: name.to_string(), message: message.into() }
    }
}

impl std::fmt::Display for ParamProblem {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "parameter '{}' {}", self.name, self.message)
    }
}

pub(super) fn validate(
    map: &SourceMap<'_>,
    config_path: &Path,
    raw: RawRobot,
    resolver: &mut dyn Resolver,
    errors: &mut Vec<Diagnostic>,
) -> RobotConfig {
    let base_dir = config_path.parent().unwrap_or(Path::new("")).to_path_buf();
    let name = match raw.name {
        Some(name) if is_valid_name(&name.value) => name.value,
        Some(name) => {
            errors.push(map.at(name.offset, format!("robot name '{}' is not [a-z][a-z0-9_-]*", clip(&name.value))));
            name.value
        }
        None => String::new(),
    };

    let mut robot =
        RobotConfig { name, path: config_path.to_path_buf(), components: Vec::new(), connections: Vec::new() };
    // Every component by name, including those that failed to load (so a
    // connection to them is not reported a second time as unknown).
    let mut known: HashMap<String, (usize, Option<usize>)> = HashMap::new();
    let mut seen_platforms: HashMap<Platform, usize> = HashMap::new();
    let mut connects: Vec<(Platform, RawConnect)> = Vec::new();
    let mut component_count = 0usize;

    for platform in raw.platforms {
        let kind = match platform.name.value.as_str() {
            "network" => Platform::Network,
            "control" => Platform::Control,
            other => {
                errors.push(map.at(
                    platform.name.offset,
                    format!("unknown platform '{}' (expected 'network' or 'control')", clip(other)),
                ));
                continue;
            }
        };
        if let Some(first) = seen_platforms.insert(kind, platform.offset) {
            let (line, column) = map.line_column(first);
            errors.push(
                map.at(platform.offset, format!("platform '{}' is already defined at {line}:{column}", kind.name())),
            );
        }
        for component in platform.components {
            component_count += 1;
            if component_count == limits::MAX_COMPONENTS + 1 {
                errors.push(map.at(
                    component.offset,
                    format!("too many components: at most {} are allowed", limits::MAX_COMPONENTS),
                ));
            }
            let name = component.name.clone();
            if !is_valid_name(&name.value) {
                errors.push(map.at(
                    name.offset,
                    format!(
                        "component name '{}' is not [a-z][a-z0-9_-]* of at most {} characters",
                        clip(&name.value),
                        crate::contract::MAX_NAME_LEN
                    ),
                ));
            }
            if let Some((first, _)) = known.get(&name.value) {
                let (line, column) = map.line_column(*first);
                errors.push(
                    map.at(name.offset, format!("component '{}' is already defined at {line}:{column}", name.value)),
                );
                continue;
            }
            let index = component_config(map, &base_dir, kind, component, resolver, errors).map(|c| {
                robot.components.push(c);
                robot.components.len() - 1
            });
            known.insert(name.value, (name.offset, index));
        }
        connects.extend(platform.connections.into_iter().map(|c| (kind, c)));
    }

    let mut seen_connections: HashMap<(PortRef, PortRef), usize> = HashMap::new();
    let raw_connects = connects.clone();
    for (platform, connect) in connects {
        let from = endpoint(map, &connect.from, "from", &known, &robot.components, errors);
        let to = endpoint(map, &connect.to, "to", &known, &robot.components, errors);
        let policy = policy(map, &connect, errors);
        let (Some(from), Some(to), Some(policy)) = (from, to, policy) else {
            continue;
        };
        let out_kind = robot.components[from.component].description.outputs[from.port as usize].kind;
        let in_kind = robot.components[to.component].description.inputs[to.port as usize].kind;
        if !out_kind.can_feed(in_kind) {
            let why = if in_kind == ValueKind::Scan && out_kind == ValueKind::Vector {
                "a vector carries no ray geometry; a scan input needs a scan output (a serial link on sim:NAME, a 0.2.0 component's scan)"
            } else {
                "the kinds differ"
            };
            errors.push(map.at(
                connect.to.offset,
                format!(
                    "cannot connect '{}' ({out_kind}) to '{}' ({in_kind}): {why}",
                    connect.from.value, connect.to.value
                ),
            ));
            continue;
        }
        if let Some(first) = seen_connections.insert((from, to), connect.offset) {
            let (line, column) = map.line_column(first);
            errors.push(map.at(
                connect.offset,
                format!(
                    "connection '{}' -> '{}' is already defined at {line}:{column}",
                    connect.from.value, connect.to.value
                ),
            ));
            continue;
        }
        robot.connections.push(ConnectionConfig { offset: connect.from.offset, from, to, policy, platform });
    }
    // Robot-wide rules, each the built-in's own (through the resolver).
    let mut lost_wiring = vec![false; robot.components.len()];
    for (_, connect) in &raw_connects {
        let index_of = |text: &Spanned<String>| text.value.split_once('.').and_then(|(c, _)| known.get(c).copied());
        if let (Some((_, Some(i))), Some((_, None))) | (Some((_, None)), Some((_, Some(i)))) =
            (index_of(&connect.from), index_of(&connect.to))
        {
            lost_wiring[i] = true;
        }
    }
    let failed: Vec<String> = known.iter().filter(|(_, (_, index))| index.is_none()).map(|(n, _)| n.clone()).collect();
    let view = RobotView { robot: &robot, lost_wiring: &lost_wiring, failed: &failed };
    for problem in resolver.check_robot(&view) {
        errors.push(map.at(problem.offset, problem.message));
    }
    robot
}

fn component_config(
    map: &SourceMap<'_>,
    base_dir: &Path,
    platform: Platform,
    raw: RawComponent,
    resolver: &mut dyn Resolver,
    errors: &mut Vec<Diagnostic>,
) -> Option<ComponentConfig> {
    let name = raw.name.value.clone();
    let errors_before = errors.len();
    let source = source(map, base_dir, &raw.source, &name, &*resolver, errors);
    let priority = raw.priority.as_ref().and_then(|p| {
        let value = p.value.trim().parse::<i32>().ok().filter(|v| limits::PRIORITY_RANGE.contains(v));
        if value.is_none() {
            errors.push(map.at(
                p.offset,
                format!(
                    "priority '{}' is not a whole number from {} to {}",
                    clip(&p.value),
                    limits::PRIORITY_RANGE.start(),
                    limits::PRIORITY_RANGE.end()
                ),
            ));
        }
        value
    });
    let rate_hz = match &raw.rate {
        None => Some(limits::DEFAULT_RATE_HZ),
        Some(r) => {
            let value = r.value.trim().parse::<f64>().ok().filter(|v| (0.0..=limits::MAX_RATE_HZ).contains(v));
            if value.is_none() {
                errors.push(map.at(
                    r.offset,
                    format!("rate '{}' is not a number of hertz from 0 to {}", clip(&r.value), limits::MAX_RATE_HZ),
                ));
            }
            value
        }
    };
    let budget = match &raw.budget {
        None => Some(limits::DEFAULT_CALL_BUDGET),
        Some(b) => {
            let value = parse_duration(&b.value).filter(|d| limits::CALL_BUDGET_RANGE.contains(d));
            if value.is_none() {
                errors.push(map.at(
                    b.offset,
                    format!(
                        "budget '{}' is not a duration from {} ms to {} ms (write it as '10ms' or '0.2s')",
                        clip(&b.value),
                        limits::CALL_BUDGET_RANGE.start().as_millis(),
                        limits::CALL_BUDGET_RANGE.end().as_millis()
                    ),
                ));
            }
            value
        }
    };
    let timeout = match &raw.timeout {
        None => Some(limits::DEFAULT_SOURCE_TIMEOUT),
        Some(t) => {
            let value = parse_duration(&t.value).filter(|d| limits::SOURCE_TIMEOUT_RANGE.contains(d));
            if value.is_none() {
                errors.push(map.at(
                    t.offset,
                    format!(
                        "timeout '{}' is not a duration from {} ms to {} ms (write it as '500ms' or '1s')",
                        clip(&t.value),
                        limits::SOURCE_TIMEOUT_RANGE.start().as_millis(),
                        limits::SOURCE_TIMEOUT_RANGE.end().as_millis()
                    ),
                ));
            }
            value
        }
    };
    let memory_bytes = match &raw.memory {
        None => Some(limits::DEFAULT_MEMORY_BYTES),
        Some(m) => {
            let value = parse_size(&m.value).filter(|s| limits::MEMORY_RANGE.contains(s));
            if value.is_none() {
                errors.push(map.at(
                    m.offset,
                    format!(
                        "memory '{}' is not a size from {} MiB to {} MiB (write it as '64MiB' or '1GiB')",
                        clip(&m.value),
                        limits::MEMORY_RANGE.start() >> 20,
                        limits::MEMORY_RANGE.end() >> 20
                    ),
                ));
            }
            value
        }
    };

    let whole = |attr: &Option<Spanned<String>>,
                 name: &str,
                 range: std::ops::RangeInclusive<u32>,
                 default: u32,
                 errors: &mut Vec<Diagnostic>| match attr {
        None => Some(default),
        Some(a) => {
            let value = a.value.trim().parse::<u32>().ok().filter(|v| range.contains(v));
            if value.is_none() {
                errors.push(map.at(
                    a.offset,
                    format!(
                        "{name} '{}' is not a whole number from {} to {}",
                        clip(&a.value),
                        range.start(),
                        range.end()
                    ),
                ));
            }
            value
        }
    };
    let max_emits =
        whole(&raw.max_emits, "max-emits", limits::EMITS_PER_CALL_RANGE, limits::DEFAULT_EMITS_PER_CALL, errors);
    let max_logs = whole(&raw.max_logs, "max-logs", limits::LOG_LINES_RANGE, limits::DEFAULT_LOG_LINES_PER_S, errors);
    let max_message_bytes = match &raw.max_message {
        None => Some(limits::DEFAULT_MESSAGE_BYTES),
        Some(m) => {
            let value = parse_size(&m.value).filter(|s| limits::MESSAGE_BYTES_RANGE.contains(s));
            if value.is_none() {
                errors.push(map.at(
                    m.offset,
                    format!(
                        "max-message '{}' is not a size from {} KiB to {} MiB (write it as '64KiB' or '1MiB')",
                        clip(&m.value),
                        limits::MESSAGE_BYTES_RANGE.start() >> 10,
                        limits::MESSAGE_BYTES_RANGE.end() >> 20
                    ),
                ));
            }
            value
        }
    };

    let max_restarts =
        whole(&raw.max_restarts, "max-restarts", limits::MAX_RESTARTS_RANGE, limits::DEFAULT_MAX_RESTARTS, errors);
    let restart = match raw.restart.as_ref().map(|r| (r.value.trim(), r.offset)) {
        None | Some(("never", _)) => {
            if let Some(m) = &raw.max_restarts {
                errors.push(map.at(m.offset, "'max-restarts' only applies to restart=\"on-failure\""));
            }
            Some(None)
        }
        Some(("on-failure", _)) => max_restarts.map(|max_restarts| {
            Some(super::RestartPolicy { max_restarts, backoff_ns: limits::RESTART_BACKOFF.as_nanos() as u64 })
        }),
        Some((other, offset)) => {
            errors.push(
                map.at(offset, format!("unknown restart policy '{}' (expected 'never' or 'on-failure')", clip(other))),
            );
            None
        }
    };

    // Parameters as written: no duplicates, bounded.
    let mut xml_params: BTreeMap<String, String> = BTreeMap::new();
    let mut param_spans: Vec<(&Spanned<String>, &Spanned<String>)> = Vec::new();
    for (i, p) in raw.params.iter().enumerate() {
        if i == limits::MAX_PARAMS_PER_COMPONENT {
            errors.push(map.at(
                p.offset,
                format!("too many parameters on component '{name}': at most {}", limits::MAX_PARAMS_PER_COMPONENT),
            ));
        }
        if p.value.value.len() > limits::MAX_PARAM_VALUE_LEN {
            errors.push(map.at(
                p.value.offset,
                format!(
                    "value of parameter '{}' is longer than {} bytes",
                    clip(&p.name.value),
                    limits::MAX_PARAM_VALUE_LEN
                ),
            ));
            continue;
        }
        if let Some((first, _)) = param_spans.iter().find(|(n, _)| n.value == p.name.value) {
            let (line, column) = map.line_column(first.offset);
            errors.push(map.at(
                p.name.offset,
                format!("parameter '{}' of component '{name}' is already set at {line}:{column}", clip(&p.name.value)),
            ));
            continue;
        }
        xml_params.insert(p.name.value.clone(), p.value.value.clone());
        param_spans.push((&p.name, &p.value));
    }

    let source = source?;
    if let (ComponentSource::Builtin(_), Some(r)) = (&source, &raw.restart) {
        errors.push(map.at(r.offset, "'restart' only applies to WASM components (built-ins do not fault)"));
    }
    let description = match resolver.describe(&source, &xml_params, base_dir) {
        Ok(d) => d,
        Err(ResolveError::Source(why)) => {
            errors.push(map.at(raw.source.offset, format!("component '{name}': {why}")));
            return None;
        }
        Err(ResolveError::Params(problems)) => {
            for problem in problems {
                // At the value when the file sets it; else at the component.
                let offset = param_spans
                    .iter()
                    .find(|(n, _)| n.value == problem.name)
                    .map_or(raw.offset, |(_, value)| value.offset);
                errors.push(
                    map.at(offset, format!("parameter '{}' of component '{name}' {}", problem.name, problem.message)),
                );
            }
            return None;
        }
    };

    // Parameters against what the component declares; defaults fill the rest.
    let mut params = Vec::with_capacity(description.params.len());
    for (pname, pvalue) in &param_spans {
        match description.params.iter().find(|spec| spec.name == pname.value) {
            None => {
                let declared: Vec<&str> = description.params.iter().map(|s| s.name.as_str()).collect();
                let declared = if declared.is_empty() {
                    String::from("it declares none")
                } else {
                    format!("it declares: {}", declared.join(", "))
                };
                errors.push(map.at(
                    pname.offset,
                    format!("component '{name}' has no parameter '{}' ({declared})", clip(&pname.value)),
                ));
            }
            Some(spec) => {
                if let Err(why) = spec.kind.check(&pvalue.value) {
                    errors
                        .push(map.at(pvalue.offset, format!("parameter '{}' of component '{name}' {why}", spec.name)));
                }
            }
        }
    }
    for spec in &description.params {
        let value = xml_params.get(&spec.name).cloned().unwrap_or_else(|| spec.default_value.clone());
        params.push(Param { name: spec.name.clone(), value });
    }

    if errors.len() > errors_before {
        return None;
    }
    Some(ComponentConfig {
        name,
        offset: raw.offset,
        platform,
        source,
        priority: priority.or(description.default_priority),
        rate_hz: rate_hz?,
        budget: budget?,
        timeout: timeout?,
        memory_bytes: memory_bytes?,
        max_emits: max_emits?,
        max_message_bytes: max_message_bytes?,
        max_logs_per_s: max_logs?,
        restart: restart?,
        params,
        description,
    })
}

fn source(
    map: &SourceMap<'_>,
    base_dir: &Path,
    source: &Spanned<String>,
    component: &str,
    resolver: &dyn Resolver,
    errors: &mut Vec<Diagnostic>,
) -> Option<ComponentSource> {
    let text = source.value.trim();
    if let Some(kind) = text.strip_prefix("builtin:") {
        return match resolver.builtin_kind(kind) {
            Ok(kind) => Some(ComponentSource::Builtin(kind)),
            Err(why) => {
                errors.push(map.at(source.offset, format!("component '{component}': {why}")));
                None
            }
        };
    }
    if text.is_empty() || !text.ends_with(".wasm") {
        errors.push(map.at(
            source.offset,
            format!("source '{}' is neither 'builtin:KIND' nor a path to a .wasm file", clip(text)),
        ));
        return None;
    }
    let path = PathBuf::from(text);
    Some(ComponentSource::Wasm(if path.is_absolute() { path } else { base_dir.join(path) }))
}

fn endpoint(
    map: &SourceMap<'_>,
    text: &Spanned<String>,
    attribute: &str,
    known: &HashMap<String, (usize, Option<usize>)>,
    components: &[ComponentConfig],
    errors: &mut Vec<Diagnostic>,
) -> Option<PortRef> {
    let Some((component, port)) = text.value.split_once('.') else {
        errors.push(map.at(text.offset, format!("'{attribute}' must be COMPONENT.PORT, got '{}'", clip(&text.value))));
        return None;
    };
    let Some((_, index)) = known.get(component) else {
        errors.push(map.at(text.offset, format!("unknown component '{}' in '{attribute}'", clip(component))));
        return None;
    };
    // A component that failed to load was reported already.
    let index = (*index)?;
    let description = &components[index].description;
    let (wanted, other, direction, other_direction) = if attribute == "from" {
        (&description.outputs, &description.inputs, "output", "input")
    } else {
        (&description.inputs, &description.outputs, "input", "output")
    };
    if let Some(i) = wanted.iter().position(|p| p.name == port) {
        return Some(PortRef { component: index, port: i as u32 });
    }
    let names: Vec<&str> = wanted.iter().map(|p| p.name.as_str()).collect();
    let names = if names.is_empty() { String::from("it has none") } else { format!("it has: {}", names.join(", ")) };
    let message = if other.iter().any(|p| p.name == port) {
        format!(
            "'{}' is an {other_direction} port; '{attribute}' needs an {direction} port of '{component}' ({names})",
            clip(&text.value)
        )
    } else {
        format!("unknown {direction} port '{}' on component '{component}' ({names})", clip(port))
    };
    errors.push(map.at(text.offset, message));
    None
}

fn policy(map: &SourceMap<'_>, connect: &RawConnect, errors: &mut Vec<Diagnostic>) -> Option<Policy> {
    let policy = connect.policy.as_ref().map_or("latest", |p| p.value.trim());
    let depth = match &connect.depth {
        None => None,
        Some(d) => {
            let value = d.value.trim().parse::<usize>().ok().filter(|v| (1..=limits::MAX_QUEUE_DEPTH).contains(v));
            if value.is_none() {
                errors.push(map.at(
                    d.offset,
                    format!("depth '{}' is not a whole number from 1 to {}", clip(&d.value), limits::MAX_QUEUE_DEPTH),
                ));
                return None;
            }
            value
        }
    };
    match policy {
        "latest" => {
            if let Some(d) = &connect.depth {
                errors.push(map.at(d.offset, "'depth' only applies to policy=\"queue\""));
                return None;
            }
            Some(Policy::Latest)
        }
        "queue" => Some(Policy::Queue { depth: depth.unwrap_or(limits::DEFAULT_QUEUE_DEPTH) }),
        other => {
            let offset = connect.policy.as_ref().map_or(connect.offset, |p| p.offset);
            errors.push(map.at(offset, format!("unknown policy '{}' (expected 'latest' or 'queue')", clip(other))));
            None
        }
    }
}

/// `10ms`, `500us`, `0.2s` -> a duration.
pub fn parse_duration(text: &str) -> Option<Duration> {
    let text = text.trim();
    let (number, scale) = if let Some(n) = text.strip_suffix("ms") {
        (n, 1e-3)
    } else if let Some(n) = text.strip_suffix("us") {
        (n, 1e-6)
    } else if let Some(n) = text.strip_suffix('s') {
        (n, 1.0)
    } else {
        return None;
    };
    let seconds = number.trim().parse::<f64>().ok()? * scale;
    Duration::try_from_secs_f64(seconds).ok()
}

/// `64MiB`, `1GiB`, `512KiB`, `1048576` -> bytes.
pub fn parse_size(text: &str) -> Option<u64> {
    let text = text.trim();
    let (number, scale) = if let Some(n) = text.strip_suffix("GiB") {
        (n, 1u64 << 30)
    } else if let Some(n) = text.strip_suffix("MiB") {
        (n, 1 << 20)
    } else if let Some(n) = text.strip_suffix("KiB") {
        (n, 1 << 10)
    } else {
        (text, 1)
    };
    number.trim().parse::<u64>().ok()?.checked_mul(scale)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn durations_and_sizes_parse_with_units() {
        assert_eq!(parse_duration("10ms"), Some(Duration::from_millis(10)));
        assert_eq!(parse_duration("500us"), Some(Duration::from_micros(500)));
        assert_eq!(parse_duration("0.2s"), Some(Duration::from_millis(200)));
        assert_eq!(parse_duration("10"), None);
        assert_eq!(parse_duration("-1ms"), None);
        assert_eq!(parse_size("64MiB"), Some(64 << 20));
        assert_eq!(parse_size("1GiB"), Some(1 << 30));
        assert_eq!(parse_size("4096"), Some(4096));
        assert_eq!(parse_size("1.5MiB"), None);
        assert_eq!(parse_size("99999999999999GiB"), None);
    }
}
