//! The Zenoh router config of a lab (docs/lab.md, "A Zenoh router that lets
//! each peer touch only its own keys"): `subsume lab router-config` prints
//! what [`router_config`] makes of a lab's name and its robots' names, a
//! Zenoh 1.10 router config (JSON5, with comments) whose `usrpwd` auth and
//! `access_control` let the lab server's user do everything under
//! `subsume/lab/LAB/**` and each robot's user (user name = robot name) only
//! its own keys, everyone else nothing. `config/zenoh-lab-router.json5` is
//! its output for lab `lab` and robots `robot1`, `robot2`.
//!
//! Pure: text in, text out. Invariants: every name is a plain name
//! ([`wire::is_name`], the rule the lab's wire and its robots keep), so it
//! is a key-expression chunk and a user name the users file can hold; no
//! robot is named twice or after the lab server's user (its user would get
//! the lab server's rights); the endpoint and the users file's path are
//! written as JSON strings and hold no control character, so nothing given
//! can end a comment or a string early.

use std::fmt::Write as _;

use thiserror::Error;

use super::wire;
use crate::contract::clip;

/// Where the router listens unless told: every address, Zenoh's port.
pub const DEFAULT_LISTEN: &str = "tcp/0.0.0.0:7447";
/// Where the router reads its `user:password` lines unless told.
pub const DEFAULT_USERS_FILE: &str = "/etc/subsume/zenoh-lab-users.txt";
/// The lab server's user unless told.
pub const DEFAULT_LAB_SERVER_USER: &str = "lab-server";

/// What a lab's router config is made of.
#[derive(Clone, Debug)]
pub struct RouterConfigOptions {
    /// The lab's name (`subsume lab serve --lab NAME`).
    pub lab: String,
    /// Its robots' names (`subsume run ... --lab-robot NAME`), each also
    /// its user's name on the router.
    pub robots: Vec<String>,
    /// The router's listen endpoint, `PROTOCOL/ADDRESS`.
    pub listen: String,
    /// The router's users file (`user:password` per line).
    pub users_file: String,
    /// The lab server's user on the router.
    pub lab_server_user: String,
    /// The router's certificate chain and its private key (PEM files), on
    /// the router's machine: needed, and only allowed, with a `tls/`
    /// listen endpoint.
    pub tls_certificate: Option<String>,
    pub tls_private_key: Option<String>,
}

impl RouterConfigOptions {
    /// Lab `lab` with `robots`, every other option its default.
    pub fn new(lab: &str, robots: &[&str]) -> RouterConfigOptions {
        RouterConfigOptions {
            lab: lab.to_string(),
            robots: robots.iter().map(|r| r.to_string()).collect(),
            listen: DEFAULT_LISTEN.to_string(),
            users_file: DEFAULT_USERS_FILE.to_string(),
            lab_server_user: DEFAULT_LAB_SERVER_USER.to_string(),
            tls_certificate: None,
            tls_private_key: None,
        }
    }
}

/// Why no router config was made.
#[derive(Debug, Error, PartialEq, Eq)]
pub enum RouterConfigError {
    #[error(
        "{what} '{name}' is not a plain name: 1 to {max} letters, digits, '-', '_' or '.' (not first)",
        max = wire::MAX_NAME_LEN
    )]
    Name { what: &'static str, name: String },
    #[error("no robots: name each of the lab's robots with --robot NAME")]
    NoRobots,
    #[error("robot '{0}' is named twice")]
    Duplicate(String),
    #[error("robot '{0}' has the lab server's user name: its user would have the lab server's rights")]
    RobotIsLabServer(String),
    #[error("listen endpoint '{0}' is not PROTOCOL/ADDRESS without spaces (such as {DEFAULT_LISTEN})")]
    Endpoint(String),
    #[error("users file '{0}' is not a path: empty, or with a control character")]
    UsersFile(String),
    #[error(
        "listen endpoint '{0}' is tls/: give the router's certificate chain and key (--tls-cert PATH --tls-key PATH)"
    )]
    TlsWithoutCertificate(String),
    #[error("--tls-cert and --tls-key are for a tls/ listen endpoint, and '{0}' is not one")]
    CertificateWithoutTls(String),
    #[error("--tls-cert and --tls-key go together: one was given without the other")]
    HalfACertificate,
    #[error("{what} '{path}' is not a path: empty, or with a control character")]
    TlsFile { what: &'static str, path: String },
}

fn name_ok(what: &'static str, name: &str) -> Result<(), RouterConfigError> {
    if wire::is_name(name) { Ok(()) } else { Err(RouterConfigError::Name { what, name: clip(name) }) }
}

/// Checks `options`: every refusal [`RouterConfigError`] names.
fn check(options: &RouterConfigOptions) -> Result<(), RouterConfigError> {
    name_ok("lab name", &options.lab)?;
    name_ok("lab server user", &options.lab_server_user)?;
    if options.robots.is_empty() {
        return Err(RouterConfigError::NoRobots);
    }
    let mut seen = std::collections::BTreeSet::new();
    for robot in &options.robots {
        name_ok("robot name", robot)?;
        if !seen.insert(robot.as_str()) {
            return Err(RouterConfigError::Duplicate(robot.clone()));
        }
        if *robot == options.lab_server_user {
            return Err(RouterConfigError::RobotIsLabServer(robot.clone()));
        }
    }
    let endpoint_ok = options.listen.split_once('/').is_some_and(|(protocol, address)| {
        !protocol.is_empty()
            && protocol.bytes().all(|b| b.is_ascii_alphanumeric())
            && !address.is_empty()
            && !address.chars().any(|c| c.is_whitespace() || c.is_control())
    });
    if !endpoint_ok {
        return Err(RouterConfigError::Endpoint(clip(&options.listen)));
    }
    if !path_ok(&options.users_file) {
        return Err(RouterConfigError::UsersFile(clip(&options.users_file)));
    }
    let tls = options.listen.starts_with("tls/");
    match (&options.tls_certificate, &options.tls_private_key) {
        (None, None) if tls => return Err(RouterConfigError::TlsWithoutCertificate(clip(&options.listen))),
        (None, None) => {}
        (Some(_), Some(_)) if !tls => return Err(RouterConfigError::CertificateWithoutTls(clip(&options.listen))),
        (Some(certificate), Some(key)) => {
            for (what, path) in [("--tls-cert", certificate), ("--tls-key", key)] {
                if !path_ok(path) {
                    return Err(RouterConfigError::TlsFile { what, path: clip(path) });
                }
            }
        }
        _ => return Err(RouterConfigError::HalfACertificate),
    }
    Ok(())
}

/// A path written into the config: not empty, no control character (so
/// it cannot end a comment or a string early).
fn path_ok(path: &str) -> bool {
    !path.is_empty() && !path.chars().any(char::is_control)
}

/// Text as a JSON (and JSON5) string.
fn quoted(text: &str) -> String {
    serde_json::Value::String(text.to_string()).to_string()
}

/// The widest line of the config's body.
const WIDTH: usize = 120;

/// `key: ["a", "b"],` at `indent` spaces, wrapped at [`WIDTH`]: on one
/// line when it fits, else one line of items at a time.
fn list(out: &mut String, indent: usize, key: &str, items: &[String]) {
    let pad = " ".repeat(indent);
    let quoted_items: Vec<String> = items.iter().map(|i| quoted(i)).collect();
    let one_line = format!("{pad}{key}: [{}],", quoted_items.join(", "));
    if one_line.len() <= WIDTH {
        out.push_str(&one_line);
        out.push('\n');
        return;
    }
    let inner = " ".repeat(indent + 2);
    let _ = writeln!(out, "{pad}{key}: [");
    let mut line = String::new();
    for item in &quoted_items {
        if !line.is_empty() && inner.len() + line.len() + 1 + item.len() + 1 > WIDTH {
            let _ = writeln!(out, "{inner}{line}");
            line.clear();
        }
        if !line.is_empty() {
            line.push(' ');
        }
        line.push_str(item);
        line.push(',');
    }
    let _ = writeln!(out, "{inner}{line}");
    let _ = writeln!(out, "{pad}],");
}

/// One access-control rule, with its comment lines.
struct Rule<'a> {
    comment: &'a [&'a str],
    id: String,
    messages: &'a [&'a str],
    flows: &'a [&'a str],
    keys: Vec<String>,
}

fn rule(out: &mut String, rule: &Rule<'_>) {
    out.push_str("      {\n");
    for line in rule.comment {
        let _ = writeln!(out, "        // {line}");
    }
    let _ = writeln!(out, "        id: {},", quoted(&rule.id));
    let messages: Vec<String> = rule.messages.iter().map(|m| m.to_string()).collect();
    list(out, 8, "messages", &messages);
    let flows: Vec<String> = rule.flows.iter().map(|f| quoted(f)).collect();
    let _ = writeln!(out, "        flows: [{}],", flows.join(", "));
    out.push_str("        permission: \"allow\",\n");
    list(out, 8, "key_exprs", &rule.keys);
    out.push_str("      },\n");
}

/// A policy: its id, rules and subjects.
fn policy(out: &mut String, id: &str, rules: &[String], subjects: &[String]) {
    let one_line = format!(
        "      {{ id: {}, rules: [{}], subjects: [{}] }},",
        quoted(id),
        rules.iter().map(|r| quoted(r)).collect::<Vec<_>>().join(", "),
        subjects.iter().map(|s| quoted(s)).collect::<Vec<_>>().join(", ")
    );
    if one_line.len() <= WIDTH {
        out.push_str(&one_line);
        out.push('\n');
        return;
    }
    out.push_str("      {\n");
    let _ = writeln!(out, "        id: {},", quoted(id));
    list(out, 8, "rules", rules);
    list(out, 8, "subjects", subjects);
    out.push_str("      },\n");
}

/// A rule's shape: its comment lines, id (or id suffix), messages and
/// flow.
type Shape = (&'static [&'static str], &'static str, &'static [&'static str], &'static str);

/// The rules every robot shares, each with its key under the lab's prefix.
const SHARED_RULES: [(Shape, &str); 5] = [
    ((&[], "robots-hear-the-heartbeat", &["declare_subscriber"], "ingress"), "heartbeat"),
    ((&[], "robots-get-the-heartbeat", &["put"], "egress"), "heartbeat"),
    ((&[], "robots-fetch-blobs", &["query"], "ingress"), "blobs"),
    ((&[], "robots-get-blob-replies", &["reply"], "egress"), "blobs"),
    (
        (
            &["A robot's status publisher learns that the lab listens."],
            "robots-learn-the-status-subscriber",
            &["declare_subscriber"],
            "egress",
        ),
        "status/*",
    ),
];

/// The rules of one robot's own keys (their keys: [`own_keys`]).
const OWN_RULES: [Shape; 3] = [
    (
        &["It declares its queryables (dispatch, stop, estop, results, file,", "baseline, live) and answers on them."],
        "serves-its-rpc",
        &["declare_queryable", "reply"],
        "ingress",
    ),
    (&[], "is-asked-on-its-rpc", &["query"], "egress"),
    (&[], "tells-its-status-and-token", &["put", "liveliness_token"], "ingress"),
];

/// The `link` block of the router's TLS listener, when it has one.
fn tls_link(options: &RouterConfigOptions) -> String {
    let (Some(certificate), Some(key)) = (&options.tls_certificate, &options.tls_private_key) else {
        return String::new();
    };
    format!(
        "    link: {{
      // The router's certificate chain and key (PEM). Each client trusts
      // the authority that signed it (its root_ca_certificate) and logs in
      // with its user and password over the encrypted link.
      tls: {{
        listen_certificate: {},
        listen_private_key: {},
      }},
    }},
",
        quoted(certificate),
        quoted(key)
    )
}

/// The keys of one robot's rule `suffix`, under `prefix`
/// (`subsume/lab/LAB`).
fn own_keys(prefix: &str, suffix: &str, robot: &str) -> Vec<String> {
    match suffix {
        "tells-its-status-and-token" => vec![format!("{prefix}/status/{robot}"), format!("{prefix}/robot/{robot}/**")],
        _ => vec![format!("{prefix}/rpc/{robot}/*")],
    }
}

/// The command that makes `options`' config (the defaults left out), as
/// comment lines of at most 80 columns, continued with `\`.
fn command_lines(options: &RouterConfigOptions) -> String {
    let mut units = vec!["subsume lab router-config".to_string(), format!("--lab {}", options.lab)];
    units.extend(options.robots.iter().map(|robot| format!("--robot {robot}")));
    if options.listen != DEFAULT_LISTEN {
        units.push(format!("--listen {}", options.listen));
    }
    if options.users_file != DEFAULT_USERS_FILE {
        units.push(format!("--users-file {}", quoted(&options.users_file)));
    }
    if options.lab_server_user != DEFAULT_LAB_SERVER_USER {
        units.push(format!("--lab-server-user {}", options.lab_server_user));
    }
    if let (Some(certificate), Some(key)) = (&options.tls_certificate, &options.tls_private_key) {
        units.push(format!("--tls-cert {}", quoted(certificate)));
        units.push(format!("--tls-key {}", quoted(key)));
    }
    let mut lines: Vec<String> = Vec::new();
    let mut line = String::new();
    for unit in units {
        // `//       ` before, ` \` after: 80 columns at most.
        if !line.is_empty() && 9 + line.len() + 1 + unit.len() + 2 > 80 {
            lines.push(std::mem::take(&mut line));
        }
        if !line.is_empty() {
            line.push(' ');
        }
        line.push_str(&unit);
    }
    lines.push(line);
    let indented: Vec<String> = lines
        .iter()
        .enumerate()
        .map(|(n, line)| if n == 0 { format!("//     {line}") } else { format!("//       {line}") })
        .collect();
    indented.join(" \\\n")
}

/// `text` as comment lines at `indent` spaces, wrapped at [`WIDTH`] on
/// spaces.
fn comment(out: &mut String, indent: usize, text: &str) {
    let head = format!("{}//", " ".repeat(indent));
    let mut line = head.clone();
    for word in text.split(' ') {
        if line.len() > head.len() && line.len() + 1 + word.len() > WIDTH {
            let _ = writeln!(out, "{line}");
            line = head.clone();
        }
        line.push(' ');
        line.push_str(word);
    }
    let _ = writeln!(out, "{line}");
}

/// The Zenoh 1.10 router config (JSON5, commented) of lab `options.lab`
/// and its robots, or why there is none.
pub fn router_config(options: &RouterConfigOptions) -> Result<String, RouterConfigError> {
    check(options)?;
    let prefix = format!("subsume/lab/{}", options.lab);
    let server = &options.lab_server_user;
    let Some(first) = options.robots.first() else { return Err(RouterConfigError::NoRobots) };
    let mut out = String::new();
    let _ = write!(
        out,
        "\
// A Zenoh router for the subsume lab `{lab}` (docs/lab.md, \"A Zenoh router
// that lets each peer touch only its own keys\"), in the config format of
// Zenoh 1.10 (eclipse-zenoh / zenohd 1.10.2). Made by
{command}
// (for another lab or other robots, make it again rather than edit it).
//
// The lab server and every robot connect to this router in client mode
// (clients talk only through the router, so every message passes its
// access control), each with its own user and password. The router lets:
//   - the lab server's user `{server}` do everything under the lab's keys,
//     {prefix}/**;
//   - each robot's user (user name = robot name) declare its queryables,
//     answer and be asked on its own rpc keys only, put its own status,
//     declare its own liveliness token, hear the lab's heartbeat and fetch
//     the lab's blobs;
//   - everyone else nothing (default deny): a peer with another user's
//     password cannot even declare a queryable on a robot's keys.
//
// To use it: write the users file (`user:password` per line for {server}
// and each robot, chmod 600; its path is below) and start a Zenoh 1.10
// router on this file:
//     zenohd -c zenoh-lab-router.json5
// or, with the tests' Python package:
//     tests/python/.venv/bin/python tests/python/zenoh_router.py zenoh-lab-router.json5
// Give the lab server and each robot a client config with their user
// (docs/lab.md shows one).
//
// Tested with eclipse-zenoh 1.10.2 as the router (tests/all/labnet.rs,
// through_the_lab_router_...): each robot rule below is needed (without
// any one of them the robot is not listed, does not get its blobs, or
// aborts for want of the heartbeat), and without this access_control
// block a third user's rogue queryable is asked the lab's dispatches.
{{
  mode: \"router\",
  listen: {{
    // Off a closed network, a tls/ endpoint (--tls-cert, --tls-key).
    endpoints: [{listen}],
  }},
  scouting: {{
    multicast: {{ enabled: false }},
    gossip: {{ enabled: false }},
  }},
  transport: {{
{link}    auth: {{
      usrpwd: {{
",
        lab = options.lab,
        command = command_lines(options),
        listen = quoted(&options.listen),
        link = tls_link(options),
    );
    comment(&mut out, 8, &format!("`user:password` per line: {server}, {}.", options.robots.join(", ")));
    let _ = write!(
        out,
        "        dictionary_file: {users},
      }},
    }},
  }},
  access_control: {{
    enabled: true,
    // Whatever no rule below allows is denied, to every user.
    default_permission: \"deny\",
    rules: [
",
        users = quoted(&options.users_file),
    );
    rule(
        &mut out,
        &Rule {
            comment: &[],
            id: "lab-server-all".into(),
            messages: &[
                "put",
                "delete",
                "declare_subscriber",
                "query",
                "declare_queryable",
                "reply",
                "liveliness_token",
                "declare_liveliness_subscriber",
                "liveliness_query",
            ],
            flows: &["ingress", "egress"],
            keys: vec![format!("{prefix}/**")],
        },
    );
    out.push_str("      // What every robot needs of the lab server.\n");
    for ((comment, id, messages, flow), key) in SHARED_RULES {
        let flows = std::slice::from_ref(&flow);
        rule(&mut out, &Rule { comment, id: id.to_string(), messages, flows, keys: vec![format!("{prefix}/{key}")] });
    }
    for robot in &options.robots {
        if robot == first {
            let _ = writeln!(out, "      // Robot {robot}: its own keys only.");
        } else {
            let _ = writeln!(out, "      // Robot {robot}: as {first}.");
        }
        for (comment, suffix, messages, flow) in OWN_RULES {
            let comment = if robot == first { comment } else { &[] };
            let keys = own_keys(&prefix, suffix, robot);
            let flows = std::slice::from_ref(&flow);
            rule(&mut out, &Rule { comment, id: format!("{robot}-{suffix}"), messages, flows, keys });
        }
    }
    out.push_str("    ],\n    subjects: [\n");
    let _ = writeln!(out, "      {{ id: {}, usernames: [{}] }},", quoted(server), quoted(server));
    for robot in &options.robots {
        let _ = writeln!(out, "      {{ id: {}, usernames: [{}] }},", quoted(robot), quoted(robot));
    }
    out.push_str("    ],\n    policies: [\n");
    policy(&mut out, "the-lab-server", &["lab-server-all".to_string()], std::slice::from_ref(server));
    let shared_ids: Vec<String> = SHARED_RULES.iter().map(|((_, id, ..), _)| id.to_string()).collect();
    policy(&mut out, "every-robot", &shared_ids, &options.robots);
    for robot in &options.robots {
        let rules: Vec<String> = OWN_RULES.iter().map(|(_, suffix, ..)| format!("{robot}-{suffix}")).collect();
        policy(&mut out, &format!("{robot}-own-keys"), &rules, std::slice::from_ref(robot));
    }
    out.push_str("    ],\n  },\n}\n");
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn made(options: &RouterConfigOptions) -> Result<String, RouterConfigError> {
        router_config(options)
    }

    #[test]
    fn a_lab_of_two_robots_is_a_zenoh_config_with_each_robots_rules_and_no_other_lab() {
        let text = made(&RouterConfigOptions::new("north", &["r1", "r2.b"])).unwrap();
        let config = zenoh::Config::from_json5(&text).unwrap();
        assert_eq!(config.get_json("access_control/enabled").unwrap(), "true");
        let json: serde_json::Value = serde_json::from_str(&config.get_json("access_control").unwrap()).unwrap();
        let rule_ids: Vec<&str> = json["rules"].as_array().unwrap().iter().map(|r| r["id"].as_str().unwrap()).collect();
        for id in ["lab-server-all", "r1-serves-its-rpc", "r2.b-is-asked-on-its-rpc", "r2.b-tells-its-status-and-token"]
        {
            assert!(rule_ids.contains(&id), "{id}: {rule_ids:?}");
        }
        let keys = json["rules"].to_string();
        assert!(keys.contains("subsume/lab/north/rpc/r2.b/*"), "{keys}");
        assert!(!keys.contains("subsume/lab/lab/"), "{keys}");
        let subjects: Vec<&str> =
            json["subjects"].as_array().unwrap().iter().map(|s| s["usernames"][0].as_str().unwrap()).collect();
        assert_eq!(subjects, ["lab-server", "r1", "r2.b"]);
        assert_eq!(config.get_json("listen/endpoints").unwrap(), r#"["tcp/0.0.0.0:7447"]"#);
    }

    #[test]
    fn the_endpoint_users_file_and_lab_server_user_given_are_used_and_the_command_says_them() {
        let mut options = RouterConfigOptions::new("lab", &["r1"]);
        options.listen = "tls/[::]:7448".into();
        options.users_file = "/srv/lab \"users\".txt".into();
        options.lab_server_user = "boss".into();
        options.tls_certificate = Some("/etc/subsume/router.pem".into());
        options.tls_private_key = Some("/etc/subsume/router.key".into());
        let text = made(&options).unwrap();
        let config = zenoh::Config::from_json5(&text).unwrap();
        assert_eq!(config.get_json("listen/endpoints").unwrap(), r#"["tls/[::]:7448"]"#);
        assert_eq!(config.get_json("transport/link/tls/listen_certificate").unwrap(), r#""/etc/subsume/router.pem""#);
        assert_eq!(config.get_json("transport/link/tls/listen_private_key").unwrap(), r#""/etc/subsume/router.key""#);
        assert_eq!(config.get_json("transport/auth/usrpwd/dictionary_file").unwrap(), r#""/srv/lab \"users\".txt""#);
        assert!(config.get_json("access_control/subjects").unwrap().contains(r#"["boss"]"#), "{text}");
        let command = "//     subsume lab router-config --lab lab --robot r1 --listen tls/[::]:7448 \\\n\
                       //       --users-file \"/srv/lab \\\"users\\\".txt\" --lab-server-user boss \\\n\
                       //       --tls-cert \"/etc/subsume/router.pem\" \\\n\
                       //       --tls-key \"/etc/subsume/router.key\"\n";
        assert!(text.contains(command), "{text}");
    }

    #[test]
    fn many_robots_wrap_their_lists_and_still_parse() {
        let names: Vec<String> = (1..=40).map(|n| format!("robot-number-{n}")).collect();
        let refs: Vec<&str> = names.iter().map(String::as_str).collect();
        let text = made(&RouterConfigOptions::new("lab", &refs)).unwrap();
        let config = zenoh::Config::from_json5(&text).unwrap();
        let subjects = config.get_json("access_control/subjects").unwrap();
        assert!(subjects.contains("robot-number-40"), "{subjects}");
        assert!(text.lines().all(|l| l.len() <= WIDTH), "{text}");
        assert!(text.contains("--robot robot-number-40\n"), "{text}");
    }

    #[test]
    fn bad_names_duplicates_no_robots_and_bad_paths_are_refused_by_name() {
        let refused = |f: &dyn Fn(&mut RouterConfigOptions)| {
            let mut options = RouterConfigOptions::new("lab", &["r1", "r2"]);
            f(&mut options);
            made(&options).unwrap_err()
        };
        let name = |what, name: &str| RouterConfigError::Name { what, name: name.into() };
        assert_eq!(refused(&|o| o.lab = "a/b".into()), name("lab name", "a/b"));
        assert_eq!(refused(&|o| o.lab = String::new()), name("lab name", ""));
        assert_eq!(refused(&|o| o.robots[1] = ".hidden".into()), name("robot name", ".hidden"));
        assert_eq!(refused(&|o| o.robots[0] = "r*".into()), name("robot name", "r*"));
        assert_eq!(refused(&|o| o.robots[0] = "x".repeat(65)), name("robot name", &clip(&"x".repeat(65))));
        assert_eq!(refused(&|o| o.lab_server_user = "a:b".into()), name("lab server user", "a:b"));
        assert_eq!(refused(&|o| o.robots.clear()), RouterConfigError::NoRobots);
        assert_eq!(refused(&|o| o.robots.push("r1".into())), RouterConfigError::Duplicate("r1".into()));
        assert_eq!(
            refused(&|o| o.robots.push("lab-server".into())),
            RouterConfigError::RobotIsLabServer("lab-server".into())
        );
        for bad in ["", "tcp", "/x", "tcp/", "tcp/a b", "tc p/a", "tcp/a\n//"] {
            assert_eq!(refused(&|o| o.listen = bad.into()), RouterConfigError::Endpoint(clip(bad)), "{bad:?}");
        }
        assert!(matches!(refused(&|o| o.users_file = String::new()), RouterConfigError::UsersFile(_)));
        let tls = |o: &mut RouterConfigOptions| o.listen = "tls/0.0.0.0:7447".into();
        assert_eq!(refused(&tls), RouterConfigError::TlsWithoutCertificate("tls/0.0.0.0:7447".into()));
        let pem = |o: &mut RouterConfigOptions| {
            o.tls_certificate = Some("r.pem".into());
            o.tls_private_key = Some("r.key".into());
        };
        assert_eq!(refused(&pem), RouterConfigError::CertificateWithoutTls(DEFAULT_LISTEN.into()));
        let half = |o: &mut RouterConfigOptions| {
            tls(o);
            o.tls_certificate = Some("r.pem".into());
        };
        assert_eq!(refused(&half), RouterConfigError::HalfACertificate);
        let bad_key = |o: &mut RouterConfigOptions| {
            tls(o);
            pem(o);
            o.tls_private_key = Some("r.key\n}".into());
        };
        assert_eq!(refused(&bad_key), RouterConfigError::TlsFile { what: "--tls-key", path: "r.key?}".into() });
        let newline = refused(&|o| o.users_file = "/a\n}".into());
        assert_eq!(newline.to_string(), "users file '/a?}' is not a path: empty, or with a control character");
        assert_eq!(
            refused(&|o| o.robots[0] = "r 1".into()).to_string(),
            "robot name 'r 1' is not a plain name: 1 to 64 letters, digits, '-', '_' or '.' (not first)"
        );
    }
}
