//! Who sees what, as a matrix (docs/portal.md, "Who sees what"; issue 37):
//! one real host with its portal, over real HTTP. Two researchers and an
//! admin each upload a component and stage a robot file that carry markers
//! of their own (the component's bytes, its name, the robot file's name and
//! text, the experiment's label), and submit an experiment that ends, so
//! each has a results bundle; the admin's set is the lab's baseline, so it
//! is the lab kit. Then every read route of the API (the table [`ROUTES`])
//! and the command line's reads ([`CLI_READS`]) are asked by each owner, the
//! other researcher, the admin, a developer, a viewer and nobody (no
//! session), with the uploads private and shared with the lab, and the
//! owner's lab kit off and on, and once more while one of Ana's experiments
//! runs (the live views). No answer body and no file of an archive
//! holds a marker its asker may not read, and every route shows the markers
//! its asker may read (so the matrix cannot pass on empty answers). The
//! expectations are written from the documented model ([`allowed`]), not
//! from `store::access`.

use std::collections::BTreeMap;
use std::path::Path;
use std::process::Command;
use std::time::{Duration, Instant};

use serde_json::Value as Json;

use crate::lab::{Lab, PASSWORD};

/// Who asks: a user's role, or nobody (no session).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Role {
    Researcher,
    Developer,
    Viewer,
    Admin,
    Nobody,
}

/// The owners of the work in the matrix.
const OWNERS: [&str; 3] = ["ana", "ben", "boss"];

/// Everyone who asks ("nobody" has no session).
const ASKERS: [(&str, Role); 6] = [
    ("ana", Role::Researcher),
    ("ben", Role::Researcher),
    ("boss", Role::Admin),
    ("dev", Role::Developer),
    ("vera", Role::Viewer),
    ("nobody", Role::Nobody),
];

fn role_of(name: &str) -> Role {
    ASKERS.iter().find(|(n, _)| *n == name).map_or(Role::Nobody, |(_, r)| *r)
}

/// The kinds of marker each owner's work carries.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
enum Kind {
    /// The upload's name (its record).
    ComponentName,
    /// A custom section inside the upload's bytes.
    ComponentBytes,
    /// The staged robot file's name (the set's record).
    FileName,
    /// A comment inside the robot file's text.
    FileText,
    /// The experiment's label (its record).
    Label,
    /// A line her set's components write to the host log while it runs.
    LogLine,
}

const KINDS: [Kind; 6] =
    [Kind::ComponentName, Kind::ComponentBytes, Kind::FileName, Kind::FileText, Kind::Label, Kind::LogLine];

/// One cell's setting: the owner's lab kit, and whether every upload is
/// shared with the lab.
#[derive(Clone, Copy, Debug)]
struct World {
    kit: bool,
    shared: bool,
}

/// Whether `asker` sees the record of what `owner` made: her own, anything
/// for an admin, the robot's own (an admin's) for every user.
fn sees(asker: &str, owner: &str) -> bool {
    let role = role_of(asker);
    role == Role::Admin || asker == owner || (role != Role::Nobody && role_of(owner) != Role::Researcher)
}

/// Whether `asker` has the bytes or text of what `owner` made: as
/// [`sees`], but a researcher has the robot's own only while the kit is on.
fn reads(asker: &str, owner: &str, world: World) -> bool {
    let role = role_of(asker);
    role == Role::Admin
        || asker == owner
        || (role != Role::Nobody && role_of(owner) != Role::Researcher && (role != Role::Researcher || world.kit))
}

/// The documented model (docs/portal.md, "Who sees what"): whether `asker`
/// may be shown `owner`'s marker of kind `kind`.
fn allowed(kind: Kind, owner: &str, asker: &str, world: World) -> bool {
    if role_of(asker) == Role::Nobody {
        return false;
    }
    match kind {
        Kind::ComponentName => world.shared || sees(asker, owner),
        Kind::ComponentBytes => world.shared || reads(asker, owner, world),
        Kind::FileName => sees(asker, owner),
        Kind::FileText => reads(asker, owner, world),
        // Experiments are their submitter's and the admins'.
        Kind::Label => role_of(asker) == Role::Admin || asker == owner,
        // What her set logs while it runs is hers; the robot's set's
        // lines are everyone's.
        Kind::LogLine => sees(asker, owner),
    }
}

/// How an answer is read.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Body {
    /// Whole, as text or JSON.
    Whole,
    /// A server-sent event stream, read for a second.
    Stream,
    /// A tar archive: every file's name and bytes.
    Archive,
}

/// Expected status of a route for (asker, owner of the thing asked for
/// or "" for a route of everyone's, the world).
type Status = fn(&str, &str, World) -> u16;

/// One read route of the API. `{comp}`, `{owner}`, `{set}` and `{exp}`
/// are the owner's upload, name, set and experiment.
struct Route {
    path: &'static str,
    body: Body,
    status: Status,
    /// Markers it must show (of each owner when the route is everyone's,
    /// of the owner asked for otherwise, of `only` when set) where the
    /// asker may have them.
    shows: &'static [Kind],
    only: Option<&'static str>,
}

const fn route(path: &'static str, body: Body, status: Status, shows: &'static [Kind]) -> Route {
    Route { path, body, status, shows, only: None }
}

fn any_user(asker: &str, _: &str, _: World) -> u16 {
    if role_of(asker) == Role::Nobody { 401 } else { 200 }
}

fn anyone(_: &str, _: &str, _: World) -> u16 {
    200
}

fn developers(asker: &str, _: &str, _: World) -> u16 {
    match role_of(asker) {
        Role::Nobody => 401,
        Role::Admin | Role::Developer => 200,
        _ => 403,
    }
}

fn no_mail(asker: &str, _: &str, _: World) -> u16 {
    if role_of(asker) == Role::Nobody { 401 } else { 409 }
}

/// This lab has no task: 404 saying so.
fn no_task(asker: &str, _: &str, _: World) -> u16 {
    if role_of(asker) == Role::Nobody { 401 } else { 404 }
}

fn admins(asker: &str, _: &str, _: World) -> u16 {
    match role_of(asker) {
        Role::Nobody => 401,
        Role::Admin => 200,
        _ => 403,
    }
}

fn a_lab_server_only(asker: &str, _: &str, _: World) -> u16 {
    if role_of(asker) == Role::Nobody { 401 } else { 404 }
}

/// 200 where `kind` of `owner`'s is the asker's to see, else 404 (as a
/// missing one), 401 without a session.
fn seen_as(kind: Kind) -> impl Fn(&str, &str, World) -> u16 {
    move |asker, owner, world| {
        if role_of(asker) == Role::Nobody {
            401
        } else if allowed(kind, owner, asker, world) {
            200
        } else {
            404
        }
    }
}

fn own_component(asker: &str, owner: &str, _: World) -> u16 {
    match role_of(asker) {
        Role::Nobody => 401,
        _ if asker == owner => 200,
        _ => 404,
    }
}

fn component(asker: &str, owner: &str, world: World) -> u16 {
    seen_as(Kind::ComponentName)(asker, owner, world)
}

fn set(asker: &str, owner: &str, world: World) -> u16 {
    seen_as(Kind::FileName)(asker, owner, world)
}

fn experiment(asker: &str, owner: &str, world: World) -> u16 {
    seen_as(Kind::Label)(asker, owner, world)
}

/// The kit: for those who submit (not viewers), researchers and
/// developers only while the owner lets it leave the robot.
fn kit(asker: &str, _: &str, world: World) -> u16 {
    match role_of(asker) {
        Role::Nobody => 401,
        Role::Admin => 200,
        Role::Researcher | Role::Developer if world.kit => 200,
        _ => 403,
    }
}

use Kind::*;

/// Every read route of the API (host/src/portal/mod.rs) that a robot's
/// portal serves, with who gets what. Routes with `{...}` are asked of
/// each owner's thing.
const ROUTES: &[Route] = &[
    route("/api/v1/session", Body::Whole, any_user, &[]),
    route("/api/v1/components", Body::Whole, any_user, &[ComponentName]),
    route("/api/v1/components/{comp}", Body::Whole, own_component, &[ComponentName]),
    route("/api/v1/components/{owner}/{comp}", Body::Whole, component, &[ComponentName]),
    route("/api/v1/worlds", Body::Whole, any_user, &[]),
    route("/api/v1/sets", Body::Whole, any_user, &[FileName]),
    route("/api/v1/sets/{set}", Body::Whole, set, &[FileName, FileText]),
    route("/api/v1/logs", Body::Whole, any_user, &[LogLine]),
    route("/api/v1/audit", Body::Whole, developers, &[]),
    route("/api/v1/experiments", Body::Whole, any_user, &[Label]),
    route("/api/v1/experiments/{exp}", Body::Whole, experiment, &[Label]),
    route("/api/v1/experiments/{exp}/results", Body::Archive, experiment, &[Label, FileText, ComponentBytes]),
    route("/api/v1/lab", Body::Whole, any_user, &[]),
    route("/api/v1/lab/events", Body::Stream, any_user, &[Label]),
    Route {
        path: "/api/v1/lab/kit",
        body: Body::Archive,
        status: kit,
        shows: &[FileText, ComponentBytes],
        only: Some("boss"),
    },
    // This lab sends no mail: 409 saying so.
    route("/api/v1/lab/mail", Body::Whole, no_mail, &[]),
    route("/api/v1/tasks/reach/leaderboard", Body::Whole, no_task, &[]),
    route("/api/v1/robots", Body::Whole, a_lab_server_only, &[]),
    route("/api/v1/robots/lab/live", Body::Whole, a_lab_server_only, &[]),
    route("/api/v1/openapi.json", Body::Whole, anyone, &[]),
    route("/api/v1/status", Body::Whole, any_user, &[]),
    route("/api/v1/history", Body::Whole, any_user, &[]),
    route("/api/v1/events", Body::Stream, any_user, &[LogLine]),
    route("/api/v1/world", Body::Whole, any_user, &[]),
    route("/api/v1/locks", Body::Whole, any_user, &[]),
    route("/api/v1/recordings", Body::Whole, developers, &[]),
    // The metrics answer loopback peers without a session.
    route("/metrics", Body::Whole, anyone, &[]),
];

/// The command line's reads (`subsume lab ...`): what each prints, and for
/// `results` and `kit` every file it unpacks. Each succeeds where its
/// route answers 200.
struct CliRead {
    args: &'static [&'static str],
    status: Status,
    shows: &'static [Kind],
    only: Option<&'static str>,
    unpacks: bool,
}

const CLI_READS: &[CliRead] = &[
    CliRead { args: &["list", "{host}"], status: any_user, shows: &[Label], only: None, unpacks: false },
    CliRead { args: &["list", "{host}", "--json"], status: any_user, shows: &[Label], only: None, unpacks: false },
    CliRead { args: &["show", "{exp}", "{host}"], status: experiment, shows: &[Label], only: None, unpacks: false },
    CliRead {
        args: &["show", "{exp}", "{host}", "--json"],
        status: experiment,
        shows: &[Label],
        only: None,
        unpacks: false,
    },
    CliRead { args: &["reservations", "{host}", "--json"], status: any_user, shows: &[], only: None, unpacks: false },
    CliRead { args: &["settings", "{host}"], status: admins, shows: &[], only: None, unpacks: false },
    CliRead {
        args: &["results", "{exp}", "{host}", "-o", "{out}"],
        status: experiment,
        shows: &[Label, FileText, ComponentBytes],
        only: None,
        unpacks: true,
    },
    CliRead {
        args: &["kit", "{host}", "-o", "{out}"],
        status: kit,
        shows: &[FileText, ComponentBytes],
        only: Some("boss"),
        unpacks: true,
    },
];

/// One owner's things in the store.
struct Owned {
    component: String,
    set: u64,
    experiment: u64,
}

/// The files of an answer: (name, bytes); a whole answer is one file.
type Files = Vec<(String, Vec<u8>)>;

fn contains(files: &Files, needle: &str) -> Option<String> {
    files
        .iter()
        .find(|(name, bytes)| name.contains(needle) || bytes.windows(needle.len()).any(|w| w == needle.as_bytes()))
        .map(|(name, _)| name.clone())
}

/// A GET of `path` as `token` with curl: (status, body); a stream is read
/// for a second.
fn get(address: &str, token: Option<&str>, path: &str, body: Body) -> (u16, Vec<u8>) {
    let mut curl = Command::new("curl");
    curl.args(["-s", "-N", "-o", "-", "-w", "%{stderr}%{http_code}"]);
    if body == Body::Stream {
        curl.args(["--max-time", "1"]);
    }
    if let Some(token) = token {
        curl.args(["-H", &format!("Authorization: Bearer {token}")]);
    }
    let output = curl.arg(format!("http://{address}{path}")).output().unwrap();
    let status = String::from_utf8_lossy(&output.stderr).trim().parse().unwrap_or(0);
    (status, output.stdout)
}

fn unpack(bytes: &[u8]) -> Files {
    let mut archive = tar::Archive::new(bytes);
    let mut files = Vec::new();
    for entry in archive.entries().unwrap() {
        let mut entry = entry.unwrap();
        let name = entry.path().unwrap().display().to_string();
        let mut content = Vec::new();
        std::io::Read::read_to_end(&mut entry, &mut content).unwrap();
        files.push((name, content));
    }
    files
}

/// Every file under `root`: (path, bytes).
fn files_under(root: &Path) -> Files {
    let mut files = Vec::new();
    let mut folders = vec![root.to_path_buf()];
    while let Some(folder) = folders.pop() {
        let Ok(entries) = std::fs::read_dir(&folder) else { continue };
        for entry in entries {
            let path = entry.unwrap().path();
            if path.is_dir() {
                folders.push(path);
            } else {
                files.push((path.display().to_string(), std::fs::read(&path).unwrap()));
            }
        }
    }
    files
}

/// What one cell found wrong: a marker the asker may not have, or one she
/// may have that the route does not show.
fn judge(
    what: &str,
    asker: &str,
    world: World,
    owner_asked: Option<&str>,
    (shows, only): (&[Kind], Option<&str>),
    files: &Files,
    markers: &BTreeMap<(&str, Kind), String>,
) -> Vec<String> {
    let mut wrong = Vec::new();
    for ((owner, kind), marker) in markers {
        // A name the asker wrote in the request, said back (404 "no
        // component 'ben/NAME'"), tells her nothing.
        let found = contains(files, marker);
        let may = allowed(*kind, owner, asker, world);
        if let (false, Some(file), false) = (may, &found, what.contains(marker.as_str())) {
            wrong.push(format!("LEAK {what} as {asker} ({world:?}): {owner}'s {kind:?} in {file}"));
        }
        let shown_here =
            shows.contains(kind) && owner_asked.is_none_or(|o| o == *owner) && only.is_none_or(|o| o == *owner);
        if may && shown_here && found.is_none() {
            let names: Vec<&str> = files.iter().map(|(n, _)| n.as_str()).collect();
            wrong
                .push(format!("MISSING {what} as {asker} ({world:?}): {owner}'s {kind:?} not shown (files {names:?})"));
        }
    }
    wrong
}

fn fill(template: &str, owner: Option<(&str, &Owned)>, host: &str, out: &Path) -> String {
    let mut text = template.replace("{host}", host).replace("{out}", &out.display().to_string());
    if let Some((name, owned)) = owner {
        text = text
            .replace("{owner}", name)
            .replace("{comp}", &owned.component)
            .replace("{set}", &owned.set.to_string())
            .replace("{exp}", &owned.experiment.to_string());
    }
    text
}

/// Every route and CLI read as `asker`: (cells asked, what was wrong).
fn ask_everything(
    lab: &Lab,
    asker: &str,
    token: Option<&str>,
    world: World,
    owned: &BTreeMap<&str, Owned>,
    markers: &BTreeMap<(&str, Kind), String>,
) -> (usize, Vec<String>) {
    let (mut cells, mut wrong) = (0, Vec::new());
    let scratch = tempfile::tempdir().unwrap();
    for route in ROUTES {
        let targets: Vec<Option<(&str, &Owned)>> =
            if route.path.contains('{') { owned.iter().map(|(o, t)| Some((*o, t))).collect() } else { vec![None] };
        for target in targets {
            let path = fill(route.path, target, "", scratch.path());
            let (status, body) = get(&lab.address, token, &path, route.body);
            cells += 1;
            let expected = (route.status)(asker, target.map_or("", |t| t.0), world);
            if status != expected {
                let text = String::from_utf8_lossy(&body[..body.len().min(300)]).into_owned();
                wrong.push(format!("STATUS GET {path} as {asker} ({world:?}): {status}, expected {expected}: {text}"));
            }
            let files = if route.body == Body::Archive && status == 200 {
                unpack(&body)
            } else {
                vec![("the answer".to_string(), body)]
            };
            let shows = if status == 200 { route.shows } else { &[] };
            let what = format!("GET {path}");
            wrong.extend(judge(&what, asker, world, target.map(|t| t.0), (shows, route.only), &files, markers));
        }
    }
    if token.is_none() {
        return (cells, wrong);
    }
    let host = format!("http://{}", lab.address);
    for (n, read) in CLI_READS.iter().enumerate() {
        let targets: Vec<Option<(&str, &Owned)>> = if read.args.iter().any(|a| a.contains("{exp}")) {
            owned.iter().map(|(o, t)| Some((*o, t))).collect()
        } else {
            vec![None]
        };
        for target in targets {
            let out = scratch.path().join(format!("cli-{n}-{}", target.map_or("all", |t| t.0)));
            let args: Vec<String> = read.args.iter().map(|a| fill(a, target, &host, &out)).collect();
            let output = crate::support::subsume()
                .arg("lab")
                .args(&args)
                .env("SUBSUME_USER", asker)
                .env("SUBSUME_PASSWORD", PASSWORD)
                .output()
                .unwrap();
            cells += 1;
            let what = format!("subsume lab {}", args.join(" "));
            let expected = (read.status)(asker, target.map_or("", |t| t.0), world) == 200;
            if output.status.success() != expected {
                wrong.push(format!(
                    "STATUS {what} as {asker} ({world:?}): success {}, expected {expected}: {}",
                    output.status.success(),
                    String::from_utf8_lossy(&output.stderr)
                ));
            }
            let mut files =
                vec![("stdout".to_string(), output.stdout.clone()), ("stderr".to_string(), output.stderr.clone())];
            if read.unpacks {
                files.extend(files_under(&out));
            }
            let shows = if output.status.success() { read.shows } else { &[] };
            wrong.extend(judge(&what, asker, world, target.map(|t| t.0), (shows, read.only), &files, markers));
        }
    }
    (cells, wrong)
}

/// `wasm` with a custom section holding `marker` (a component may carry
/// custom sections anywhere; the host keeps the bytes as uploaded).
fn with_custom_section(wasm: &[u8], marker: &str) -> Vec<u8> {
    fn leb(mut n: usize, out: &mut Vec<u8>) {
        loop {
            let byte = (n & 0x7f) as u8;
            n >>= 7;
            if n == 0 {
                out.push(byte);
                return;
            }
            out.push(byte | 0x80);
        }
    }
    let name = b"ownership-marker";
    let mut payload = Vec::new();
    leb(name.len(), &mut payload);
    payload.extend_from_slice(name);
    payload.extend_from_slice(marker.as_bytes());
    let mut bytes = wasm.to_vec();
    bytes.push(0);
    leb(payload.len(), &mut bytes);
    bytes.extend_from_slice(&payload);
    bytes
}

fn set_kit(lab: &Lab, boss: &str, kit: bool) {
    let (status, json) = lab.call(boss, "GET", "/api/v1/lab", "");
    assert_eq!(status, 200, "{json}");
    let mut settings = json["lab"]["settings"].clone();
    settings["kit"] = Json::Bool(kit);
    let (status, json) = lab.call(boss, "PUT", "/api/v1/lab/settings", &settings.to_string());
    assert_eq!(status, 200, "{json}");
}

#[test]
fn every_read_route_and_cli_read_shows_each_asker_what_is_hers_to_see_and_nothing_else() {
    let dir = tempfile::tempdir().unwrap();
    crate::lab::setup(dir.path());
    let store = dir.path().join("store");
    crate::support::add_user(&store, "dev", "developer", &["control"], PASSWORD);
    crate::support::add_user(&store, "vera", "viewer", &[], PASSWORD);
    let began = Instant::now();
    let lab = crate::lab::start(dir.path());
    let tokens: BTreeMap<&str, String> =
        ASKERS.iter().filter(|(_, r)| *r != Role::Nobody).map(|(n, _)| (*n, lab.token(n))).collect();
    // Markers no answer holds by chance.
    let nanos = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap().as_nanos();
    let run = format!("{:x}{nanos:x}", std::process::id());
    let mut markers = BTreeMap::new();
    for owner in OWNERS {
        for kind in KINDS {
            let tag = match kind {
                ComponentName => "comp",
                ComponentBytes => "bytes",
                FileName => "file",
                FileText => "text",
                Label => "label",
                LogLine => "logline",
            };
            markers.insert((owner, kind), format!("{tag}-{owner}-q{run}z"));
        }
    }
    // Each owner's upload (its bytes carry a marker), robot file (its name
    // and text carry one, and it runs the upload as its planner) and an
    // experiment of it (its label carries one), all at once.
    let planner = std::fs::read(crate::support::guest("planner")).unwrap();
    let planner_path = crate::support::guest("planner").display().to_string();
    let mut owned = BTreeMap::new();
    for owner in OWNERS {
        let token = &tokens[owner];
        let component = markers[&(owner, ComponentName)].clone();
        let bytes = with_custom_section(&planner, &markers[&(owner, ComponentBytes)]);
        let (status, json) = crate::support::http(
            &lab.address,
            "PUT",
            &format!("/api/v1/platforms/control/components/{component}"),
            Some(token),
            &bytes,
        );
        assert_eq!(status, 201, "{json}");
        // The text marker is a parameter's value: the bundle and the kit
        // hold the robot file rewritten (comments go), parameters kept;
        // the set's wiring (its record) has no parameters. At rate 0 with
        // no input, the component never publishes it. The log marker is
        // published twice a second to a log sink: the set's own log lines.
        let note = format!(
            r#"<component name="note" source="builtin:publish" rate="0">
      <param name="kind" value="text"/>
      <param name="value" value="{}"/>
    </component>
    <component name="chatter" source="builtin:publish" rate="2">
      <param name="kind" value="text"/>
      <param name="value" value="{}"/>
    </component>
    <component name="diary" source="builtin:log" rate="0">
      <param name="interval" value="0.5"/>
    </component>
    <connect from="chatter.out" to="diary.in"/>"#,
            markers[&(owner, FileText)],
            markers[&(owner, LogLine)]
        );
        let xml = crate::lab::robot(7.0, &note).replace(&planner_path, &format!("{component}.wasm"));
        let set = lab.stage(token, &format!("{}.xml", markers[&(owner, FileName)]), &xml);
        let body = serde_json::json!({ "set": set, "duration_s": 1.0, "label": markers[&(owner, Label)] });
        let (status, json) = lab.call(token, "POST", "/api/v1/experiments", &body.to_string());
        assert_eq!(status, 201, "{json}");
        let experiment = json["experiment"]["id"].as_u64().unwrap();
        owned.insert(owner, Owned { component, set, experiment });
    }
    let deadline = Instant::now() + Duration::from_secs(240);
    for (owner, things) in &owned {
        loop {
            let record = lab.experiment(&tokens[owner], things.experiment);
            if record["state"] == "done" {
                break;
            }
            let ended = ["refused", "cancelled", "aborted", "failed"].contains(&record["state"].as_str().unwrap_or(""));
            assert!(!ended && Instant::now() < deadline, "{owner}'s experiment: {record:#}\n{}", lab.host.log());
            std::thread::sleep(Duration::from_millis(100));
        }
    }
    eprintln!("ownership: the host up and three experiments done in {:.1} s", began.elapsed().as_secs_f64());
    // The admin's set is the robot's own: the lab's baseline, so the kit.
    let boss = &tokens["boss"];
    let (status, json) =
        lab.call(boss, "PUT", "/api/v1/lab/baseline", &serde_json::json!({ "set": owned["boss"].set }).to_string());
    assert_eq!(status, 200, "{json}");

    let mut wrong = Vec::new();
    let mut cells = 0;
    for world in [
        World { kit: false, shared: false },
        World { kit: true, shared: false },
        World { kit: true, shared: true },
        World { kit: false, shared: true },
    ] {
        set_kit(&lab, boss, world.kit);
        if world.shared {
            for (owner, things) in &owned {
                let path = format!("/api/v1/components/{owner}/{}/visibility", things.component);
                let (status, json) = lab.call(&tokens[owner], "PUT", &path, r#"{"visibility":"lab"}"#);
                assert_eq!((status, json["visibility"].as_str()), (200, Some("lab")), "{json}");
            }
        }
        // Every asker at once: the host's answers do not depend on the order.
        let found: Vec<(usize, Vec<String>)> = std::thread::scope(|scope| {
            let handles: Vec<_> = ASKERS
                .iter()
                .map(|(asker, _)| {
                    let (lab, owned, markers) = (&lab, &owned, &markers);
                    let token = tokens.get(asker).map(String::as_str);
                    scope.spawn(move || ask_everything(lab, asker, token, world, owned, markers))
                })
                .collect();
            handles.into_iter().map(|h| h.join().unwrap()).collect()
        });
        for (n, w) in found {
            cells += n;
            wrong.extend(w);
        }
        eprintln!("ownership: {world:?} asked, {cells} cells so far, at {:.1} s", began.elapsed().as_secs_f64());
    }
    // While Ana's experiment runs (her set again, long enough to be asked
    // about), the lab's and the robot's live views are hers for no one
    // else: no label, file or log line of hers in anyone else's answer.
    let ana = &tokens["ana"];
    let body = serde_json::json!({ "set": owned["ana"].set, "duration_s": 30.0, "label": markers[&("ana", Label)] });
    let (status, json) = lab.call(ana, "POST", "/api/v1/experiments", &body.to_string());
    assert_eq!(status, 201, "{json}");
    let running = json["experiment"]["id"].as_u64().unwrap();
    let deadline = Instant::now() + Duration::from_secs(120);
    while lab.experiment(ana, running)["state"] != "running" {
        assert!(Instant::now() < deadline, "{:#}", lab.experiment(ana, running));
        std::thread::sleep(Duration::from_millis(100));
    }
    // Her lines reach the log while it runs.
    std::thread::sleep(Duration::from_secs(1));
    let world = World { kit: false, shared: true };
    let found: Vec<(usize, Vec<String>)> = std::thread::scope(|scope| {
        let handles: Vec<_> = ASKERS
            .iter()
            .map(|(asker, _)| {
                let (lab, owned, markers) = (&lab, &owned, &markers);
                let token = tokens.get(asker).map(String::as_str);
                scope.spawn(move || ask_everything(lab, asker, token, world, owned, markers))
            })
            .collect();
        handles.into_iter().map(|h| h.join().unwrap()).collect()
    });
    assert_eq!(lab.experiment(ana, running)["state"], "running", "the matrix was asked while it ran");
    for (n, w) in found {
        cells += n;
        wrong.extend(w.into_iter().map(|w| format!("(while Ana's experiment ran) {w}")));
    }
    eprintln!("ownership: asked while an experiment ran, {cells} cells, at {:.1} s", began.elapsed().as_secs_f64());
    // Every route of the table, each owner's thing where it names one, for
    // every asker in every world.
    let per_world: usize = ROUTES.iter().map(|r| if r.path.contains('{') { OWNERS.len() } else { 1 }).sum();
    assert!(cells >= per_world * ASKERS.len() * 5, "only {cells} cells asked");
    assert!(wrong.is_empty(), "{} of {cells} cells wrong:\n{}", wrong.len(), wrong.join("\n"));
}
