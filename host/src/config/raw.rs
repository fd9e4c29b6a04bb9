//! Stage 1: the robot XML file as written. Every element and attribute keeps
//! its byte offset; unknown elements and attributes, missing required
//! attributes, stray text and DOCTYPEs are errors. Values stay text: stage 2
//! (`validate`) gives them meaning.

use quick_xml::Reader;
use quick_xml::events::{BytesStart, Event};

use super::diagnostic::{Diagnostic, SourceMap};

/// A value from the file and the byte offset where it was written.
#[derive(Clone, Debug, PartialEq)]
pub struct Spanned<T> {
    pub value: T,
    pub offset: usize,
}

#[derive(Clone, Debug, Default)]
pub struct RawRobot {
    /// False when an element was left out (unknown, or missing a required
    /// attribute) or the XML is malformed: validating what is left would
    /// report consequences of those errors as errors of their own.
    pub complete: bool,
    pub offset: usize,
    pub name: Option<Spanned<String>>,
    pub platforms: Vec<RawPlatform>,
}

#[derive(Clone, Debug)]
pub struct RawPlatform {
    pub offset: usize,
    pub name: Spanned<String>,
    pub components: Vec<RawComponent>,
    pub connections: Vec<RawConnect>,
}

#[derive(Clone, Debug)]
pub struct RawComponent {
    pub offset: usize,
    pub name: Spanned<String>,
    pub source: Spanned<String>,
    pub priority: Option<Spanned<String>>,
    pub rate: Option<Spanned<String>>,
    pub budget: Option<Spanned<String>>,
    pub timeout: Option<Spanned<String>>,
    pub memory: Option<Spanned<String>>,
    pub max_emits: Option<Spanned<String>>,
    pub max_message: Option<Spanned<String>>,
    pub max_logs: Option<Spanned<String>>,
    pub restart: Option<Spanned<String>>,
    pub max_restarts: Option<Spanned<String>>,
    pub params: Vec<RawParam>,
}

#[derive(Clone, Debug)]
pub struct RawParam {
    pub offset: usize,
    pub name: Spanned<String>,
    pub value: Spanned<String>,
}

#[derive(Clone, Debug)]
pub struct RawConnect {
    pub offset: usize,
    pub from: Spanned<String>,
    pub to: Spanned<String>,
    pub policy: Option<Spanned<String>>,
    pub depth: Option<Spanned<String>>,
}

/// Where the parser is in the element tree.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Context {
    Document,
    Robot,
    Platform,
    Component,
    /// An element with no children allowed (`param`, `connect`).
    Leaf,
    /// Inside an element already reported as unknown: its content is skipped.
    Skipped,
}

/// The attributes of one element, by name, checked against what it allows.
struct Attrs {
    items: Vec<(String, Spanned<String>)>,
}

impl Attrs {
    fn take(&mut self, name: &str) -> Option<Spanned<String>> {
        let i = self.items.iter().position(|(n, _)| n == name)?;
        Some(self.items.swap_remove(i).1)
    }
}

/// Parses `text` into the as-written tree. Diagnostics go to `errors`; the
/// tree holds what could be read (elements missing a required attribute are
/// left out, after their error is recorded).
pub fn parse(map: &SourceMap<'_>, text: &str, errors: &mut Vec<Diagnostic>) -> RawRobot {
    let mut reader = Reader::from_str(text);
    reader.config_mut().check_end_names = true;
    let mut robot = RawRobot { complete: true, ..RawRobot::default() };
    let mut seen_root = false;
    let mut stack: Vec<Context> = vec![Context::Document];

    loop {
        let before = reader.buffer_position() as usize;
        let event = match reader.read_event() {
            Ok(event) => event,
            Err(err) => {
                let at = reader.error_position() as usize;
                errors.push(map.at(at, format!("malformed xml: {err}")));
                robot.complete = false;
                return robot;
            }
        };
        let context = stack.last().copied().unwrap_or(Context::Document);
        match event {
            Event::Start(ref e) | Event::Empty(ref e) => {
                let has_children = matches!(event, Event::Start(_));
                let offset = element_offset(map, e, before);
                let errors_before = errors.len();
                let child = open_element(map, e, offset, context, &mut robot, &mut seen_root, errors);
                if child == Context::Skipped && context != Context::Skipped && errors.len() > errors_before {
                    robot.complete = false;
                }
                if has_children {
                    stack.push(child);
                }
            }
            Event::End(_) => {
                stack.pop();
            }
            Event::Text(ref t) => {
                let text: &str = t.as_ref();
                let is_blank = text.chars().all(char::is_whitespace);
                if !is_blank && context != Context::Skipped {
                    let at = map.offset_of(text.trim_start().as_bytes()).unwrap_or(before);
                    let shown: String = text.trim().chars().take(20).collect();
                    errors.push(map.at(at, format!("unexpected text '{shown}': values go in attributes")));
                }
            }
            Event::CData(_) | Event::GeneralRef(_) => {
                if context != Context::Skipped {
                    errors.push(map.at(before, "unexpected text: values go in attributes"));
                }
            }
            Event::DocType(_) => {
                errors
                    .push(map.at(before, "doctype declarations are not allowed (entities could expand without bound)"));
            }
            Event::Comment(ref c) => {
                let text: &str = c.as_ref();
                if let Some(at) = text.find("--") {
                    let offset = map.offset_of(text.as_bytes()).map_or(before, |start| start + at);
                    errors.push(map.at(offset, "'--' is not allowed inside an xml comment"));
                }
            }
            Event::Decl(_) | Event::PI(_) => {}
            Event::Eof => {
                if stack.len() > 1 {
                    errors.push(
                        map.at(text.len(), "malformed xml: the file ends inside an element that was never closed"),
                    );
                    robot.complete = false;
                }
                break;
            }
        }
    }
    if !seen_root {
        robot.complete = false;
        if errors.is_empty() {
            errors.push(map.at(0, "missing root element <robot>"));
        }
    }
    robot
}

fn element_offset(map: &SourceMap<'_>, e: &BytesStart<'_>, fallback: usize) -> usize {
    // The name follows '<' directly; point at the '<'.
    map.offset_of(e.name().as_ref().as_bytes()).map_or(fallback, |at| at.saturating_sub(1))
}

/// Handles one opening (or empty) element in `context`; returns the context
/// for its children.
fn open_element(
    map: &SourceMap<'_>,
    e: &BytesStart<'_>,
    offset: usize,
    context: Context,
    robot: &mut RawRobot,
    seen_root: &mut bool,
    errors: &mut Vec<Diagnostic>,
) -> Context {
    let name = e.name().as_ref().to_string();
    let expected: &[&str] = match context {
        Context::Document => &["robot"],
        Context::Robot => &["platform"],
        Context::Platform => &["component", "connect"],
        Context::Component => &["param"],
        Context::Leaf => &[],
        Context::Skipped => return Context::Skipped,
    };
    if !expected.contains(&name.as_str()) {
        let message = match (context, expected) {
            (Context::Document, _) if *seen_root => {
                format!("unexpected second root element <{name}>")
            }
            (_, []) => format!("unexpected element <{name}>: this element has no children"),
            _ => format!("unknown element <{name}> (expected {})", one_of(expected, "<", ">")),
        };
        errors.push(map.at(offset, message));
        return Context::Skipped;
    }
    match name.as_str() {
        "robot" => {
            if *seen_root {
                errors.push(map.at(offset, "unexpected second root element <robot>"));
                return Context::Skipped;
            }
            *seen_root = true;
            let mut attrs = read_attrs(map, e, offset, "robot", &["name"], errors);
            robot.offset = offset;
            robot.name = required(map, &mut attrs, "robot", "name", offset, errors);
            Context::Robot
        }
        "platform" => {
            let mut attrs = read_attrs(map, e, offset, "platform", &["name"], errors);
            match required(map, &mut attrs, "platform", "name", offset, errors) {
                Some(name) => {
                    robot.platforms.push(RawPlatform { offset, name, components: Vec::new(), connections: Vec::new() });
                    Context::Platform
                }
                None => Context::Skipped,
            }
        }
        "component" => {
            let allowed = [
                "name",
                "source",
                "priority",
                "rate",
                "budget",
                "timeout",
                "memory",
                "max-emits",
                "max-message",
                "max-logs",
                "restart",
                "max-restarts",
            ];
            let mut attrs = read_attrs(map, e, offset, "component", &allowed, errors);
            let name = required(map, &mut attrs, "component", "name", offset, errors);
            let source = required(map, &mut attrs, "component", "source", offset, errors);
            let (Some(name), Some(source), Some(platform)) = (name, source, robot.platforms.last_mut()) else {
                return Context::Skipped;
            };
            platform.components.push(RawComponent {
                offset,
                name,
                source,
                priority: attrs.take("priority"),
                rate: attrs.take("rate"),
                budget: attrs.take("budget"),
                timeout: attrs.take("timeout"),
                memory: attrs.take("memory"),
                max_emits: attrs.take("max-emits"),
                max_message: attrs.take("max-message"),
                max_logs: attrs.take("max-logs"),
                restart: attrs.take("restart"),
                max_restarts: attrs.take("max-restarts"),
                params: Vec::new(),
            });
            Context::Component
        }
        "param" => {
            let mut attrs = read_attrs(map, e, offset, "param", &["name", "value"], errors);
            let name = required(map, &mut attrs, "param", "name", offset, errors);
            let value = required(map, &mut attrs, "param", "value", offset, errors);
            let component = robot.platforms.last_mut().and_then(|p| p.components.last_mut());
            if let (Some(name), Some(value), Some(component)) = (name, value, component) {
                component.params.push(RawParam { offset, name, value });
            }
            Context::Leaf
        }
        "connect" => {
            let allowed = ["from", "to", "policy", "depth"];
            let mut attrs = read_attrs(map, e, offset, "connect", &allowed, errors);
            let from = required(map, &mut attrs, "connect", "from", offset, errors);
            let to = required(map, &mut attrs, "connect", "to", offset, errors);
            if let (Some(from), Some(to), Some(platform)) = (from, to, robot.platforms.last_mut()) {
                platform.connections.push(RawConnect {
                    offset,
                    from,
                    to,
                    policy: attrs.take("policy"),
                    depth: attrs.take("depth"),
                });
            }
            Context::Leaf
        }
        _ => Context::Skipped,
    }
}

/// Reads the attributes of `e`, reporting malformed, duplicate and unknown ones.
fn read_attrs(
    map: &SourceMap<'_>,
    e: &BytesStart<'_>,
    offset: usize,
    element: &str,
    allowed: &[&str],
    errors: &mut Vec<Diagnostic>,
) -> Attrs {
    let mut items: Vec<(String, Spanned<String>)> = Vec::new();
    for attr in e.attributes() {
        let attr = match attr {
            Ok(attr) => attr,
            Err(err) => {
                errors.push(map.at(offset, format!("malformed attribute on <{element}>: {err}")));
                continue;
            }
        };
        let key = attr.key.as_ref().to_string();
        let key_offset = map.offset_of(attr.key.as_ref().as_bytes()).unwrap_or(offset);
        if !allowed.contains(&key.as_str()) {
            errors.push(map.at(
                key_offset,
                format!("unknown attribute '{key}' on <{element}> (expected {})", one_of(allowed, "'", "'")),
            ));
            continue;
        }
        let value_offset = map.offset_of(attr.value.as_bytes()).unwrap_or(key_offset);
        match attr.normalized_value(quick_xml::XmlVersion::Implicit1_0) {
            Ok(value) => items.push((key, Spanned { value: value.into_owned(), offset: value_offset })),
            Err(err) => {
                errors.push(map.at(value_offset, format!("bad value for '{key}' on <{element}>: {err}")));
                // Keep the raw text so the attribute is not also reported missing.
                items.push((key, Spanned { value: attr.value.clone().into_owned(), offset: value_offset }));
            }
        }
    }
    Attrs { items }
}

fn required(
    map: &SourceMap<'_>,
    attrs: &mut Attrs,
    element: &str,
    name: &str,
    offset: usize,
    errors: &mut Vec<Diagnostic>,
) -> Option<Spanned<String>> {
    let found = attrs.take(name);
    if found.is_none() {
        errors.push(map.at(offset, format!("<{element}> is missing required attribute '{name}'")));
    }
    found
}

/// `'a', 'b' or 'c'`, with `open`/`close` around each item.
fn one_of(items: &[&str], open: &str, close: &str) -> String {
    let quoted: Vec<String> = items.iter().map(|i| format!("{open}{i}{close}")).collect();
    match quoted.split_last() {
        None => String::from("nothing"),
        Some((last, [])) => last.clone(),
        Some((last, rest)) => format!("{} or {last}", rest.join(", ")),
    }
}

/// Writes `robot` as a robot file: the elements and attributes it holds, in
/// their order, values escaped (comments and layout are not kept), after a
/// comment saying where it came from. What [`parse`] reads from it is
/// `robot` again, offsets aside: the lab writes a set's robot file in its
/// preflight form this way (docs/lab.md).
pub fn write(robot: &RawRobot, comment: &str) -> String {
    use std::fmt::Write as _;
    fn attr(out: &mut String, name: &str, value: Option<&Spanned<String>>) {
        if let Some(value) = value {
            let _ = write!(out, " {name}=\"{}\"", escape(&value.value));
        }
    }
    let mut out = String::from("<?xml version=\"1.0\" encoding=\"UTF-8\"?>\n");
    let _ = writeln!(out, "<!-- {} -->", comment.replace("--", "- -"));
    out.push_str("<robot");
    attr(&mut out, "name", robot.name.as_ref());
    out.push_str(">\n");
    for platform in &robot.platforms {
        let _ = writeln!(out, "  <platform name=\"{}\">", escape(&platform.name.value));
        for c in &platform.components {
            out.push_str("    <component");
            attr(&mut out, "name", Some(&c.name));
            attr(&mut out, "source", Some(&c.source));
            for (name, value) in [
                ("priority", &c.priority),
                ("rate", &c.rate),
                ("budget", &c.budget),
                ("timeout", &c.timeout),
                ("memory", &c.memory),
                ("max-emits", &c.max_emits),
                ("max-message", &c.max_message),
                ("max-logs", &c.max_logs),
                ("restart", &c.restart),
                ("max-restarts", &c.max_restarts),
            ] {
                attr(&mut out, name, value.as_ref());
            }
            if c.params.is_empty() {
                out.push_str("/>\n");
                continue;
            }
            out.push_str(">\n");
            for p in &c.params {
                let _ = writeln!(
                    out,
                    "      <param name=\"{}\" value=\"{}\"/>",
                    escape(&p.name.value),
                    escape(&p.value.value)
                );
            }
            out.push_str("    </component>\n");
        }
        for k in &platform.connections {
            out.push_str("    <connect");
            attr(&mut out, "from", Some(&k.from));
            attr(&mut out, "to", Some(&k.to));
            attr(&mut out, "policy", k.policy.as_ref());
            attr(&mut out, "depth", k.depth.as_ref());
            out.push_str("/>\n");
        }
        out.push_str("  </platform>\n");
    }
    out.push_str("</robot>\n");
    out
}

/// `text` as an XML attribute value between double quotes.
fn escape(text: &str) -> String {
    let mut out = String::with_capacity(text.len());
    for ch in text.chars() {
        match ch {
            '&' => out.push_str("&amp;"),
            '<' => out.push_str("&lt;"),
            '>' => out.push_str("&gt;"),
            '"' => out.push_str("&quot;"),
            '\'' => out.push_str("&apos;"),
            '\n' => out.push_str("&#10;"),
            '\r' => out.push_str("&#13;"),
            '\t' => out.push_str("&#9;"),
            other => out.push(other),
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use std::path::Path;

    use super::*;

    /// What a robot holds, offsets left out.
    fn shape(robot: &RawRobot) -> String {
        let mut out = format!("{:?}\n", robot.name.as_ref().map(|n| &n.value));
        let v = |s: &Option<Spanned<String>>| s.as_ref().map(|s| s.value.clone());
        for p in &robot.platforms {
            out += &format!("platform {}\n", p.name.value);
            for c in &p.components {
                out += &format!(
                    "{} {} {:?} {:?} {:?} {:?} {:?} {:?} {:?} {:?} {:?} {:?}\n",
                    c.name.value,
                    c.source.value,
                    v(&c.priority),
                    v(&c.rate),
                    v(&c.budget),
                    v(&c.timeout),
                    v(&c.memory),
                    v(&c.max_emits),
                    v(&c.max_message),
                    v(&c.max_logs),
                    v(&c.restart),
                    v(&c.max_restarts)
                );
                for param in &c.params {
                    out += &format!("  {}={:?}\n", param.name.value, param.value.value);
                }
            }
            for k in &p.connections {
                out += &format!("{} -> {} {:?} {:?}\n", k.from.value, k.to.value, v(&k.policy), v(&k.depth));
            }
        }
        out
    }

    /// Every robot file of the repository that reads without errors reads
    /// the same after it was written, and so does a value with every
    /// character that needs escaping.
    #[test]
    fn a_written_robot_reads_back_the_same() {
        let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
        let mut files: Vec<_> = ["config", "tests/config", "tests/worlds"]
            .iter()
            .filter_map(|dir| std::fs::read_dir(root.join(dir)).ok())
            .flatten()
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| p.extension().is_some_and(|e| e == "xml"))
            .collect();
        files.sort();
        let mut read = 0;
        let mut texts: Vec<(String, String)> =
            files.iter().filter_map(|p| Some((p.display().to_string(), std::fs::read_to_string(p).ok()?))).collect();
        texts.push((
            "escapes".into(),
            "<robot name='r'><platform name='control'><component name='c' source='builtin:log'>\
             <param name='p' value='a&amp;b &lt;c&gt; &quot;d&quot; &apos;e&apos; -- &#10;f'/></component></platform></robot>"
                .into(),
        ));
        for (name, text) in texts {
            let map = SourceMap::new(Path::new(&name), &text);
            let mut errors = Vec::new();
            let robot = parse(&map, &text, &mut errors);
            if !errors.is_empty() || !robot.complete {
                continue;
            }
            let written = write(&robot, "written by a test -- of the writer");
            let map = SourceMap::new(Path::new("written.xml"), &written);
            let mut again = Vec::new();
            let reread = parse(&map, &written, &mut again);
            assert!(again.is_empty(), "{name}: {again:?}\n{written}");
            assert_eq!(shape(&reread), shape(&robot), "{name}:\n{written}");
            read += 1;
        }
        assert!(read >= 5, "only {read} robot files were read");
    }
}
