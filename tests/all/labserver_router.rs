//! A lab server's portal as a matrix of (route, who asks) (issue 37; the
//! robot's portal has its own: tests/all/portal_router.rs and
//! tests/all/ownership.rs). The lab server is built in this process as
//! `subsume lab serve` builds it (`portal::lab_server_app` on a headless
//! deployer, its lab in the server role over a [`Fleet`]), and asked
//! through its router with `oneshot`, with no network: its Zenoh session
//! has no endpoint and no scouting, and its one robot, `r1`, is a robot's
//! lab and link ([`RobotLink`]) in this process on that same session.
//!
//! Every route the lab server serves ([`served`]: its own, the robots'
//! list, their STOP and live view, included) is asked by every role
//! (viewer, operator, developer, researcher, another researcher, admin)
//! and without a session, each expecting the status the documented model
//! gives it (docs/portal.md, "Users and roles" and "Who sees what";
//! docs/lab.md, "Roles" and "Several robots"; the permissions of
//! openapi.json), not the code's checks. Each route answers at least one
//! asker with success and a body, so the matrix cannot pass on refusals
//! alone. The robot's own routes ([`robot_only`]) answer nobody on a lab
//! server. Every route of the table is in openapi.json, every route of
//! openapi.json is in one of the two tables, and every route
//! `host/src/portal/mod.rs` mounts for a lab server is in [`served`].

use std::collections::BTreeMap;
use std::path::Path;
use std::sync::Arc;
use std::time::{Duration, Instant};

use axum::body::Body;
use axum::http::Request;
use serde_json::Value as Json;
use subsume::bridge::session::SessionSettings;
use subsume::builtin::Services;
use subsume::config::Platform;
use subsume::deploy::{BootOptions, Deployer};
use subsume::fsutil::HiddenPaths;
use subsume::lab::robot_link::{RobotLink, RobotLinkOptions};
use subsume::lab::server::{Fleet, FleetOptions};
use subsume::lab::wire::LabKey;
use subsume::lab::{Lab, LabOptions, LabRole};
use subsume::portal::{self, PortalState};
use subsume::runtime::control_loop::{Clock, Shutdown};
use subsume::store::Store;
use subsume::store::users::{Directory, Principal, Role};
use tower::ServiceExt as _;

use crate::support;

const LAB: &str = "routerlab";
const ROBOT_NAME: &str = "r1";

/// The robot's baseline: both platforms, built-ins only.
fn robot_file(control: u32, network: u32) -> String {
    format!(
        r#"<robot name="bench">
  <platform name="control">
    <component name="source" source="builtin:publish" rate="10"><param name="value" value="{control}"/></component>
    <component name="sink" source="builtin:log" rate="0"/>
    <connect from="source.out" to="sink.in"/>
  </platform>
  <platform name="network">
    <component name="beacon" source="builtin:publish" rate="1"><param name="value" value="{network}"/></component>
  </platform>
</robot>
"#
    )
}

/// (name, role, platforms): the users of the lab server. "nobody" asks
/// without a session.
const USERS: &[(&str, Role, &[Platform])] = &[
    ("viewer", Role::Viewer, &[]),
    ("operator", Role::Operator, &[]),
    ("developer", Role::Developer, &[Platform::Control]),
    ("researcher", Role::Researcher, &[Platform::Control]),
    ("other-researcher", Role::Researcher, &[Platform::Control]),
    ("admin", Role::Admin, &[]),
];

const NOBODY: &str = "nobody";

/// The owner of the researcher's work in the fixtures.
const OWNER: &str = "researcher";

fn password(name: &str) -> String {
    format!("{name}-password-123")
}

fn role_of(asker: &str) -> Option<Role> {
    USERS.iter().find(|(name, _, _)| *name == asker).map(|(_, role, _)| *role)
}

fn holds_control(asker: &str) -> bool {
    USERS.iter().any(|(name, role, platforms)| {
        *name == asker && (*role == Role::Admin || platforms.contains(&Platform::Control))
    })
}

// The documented model: what each asker gets from a route. `ok` is the
// route's success status.

/// Everyone, with or without a session (the document, the page).
fn anyone(_: &str, ok: u16) -> u16 {
    ok
}

/// Every logged-in user.
fn any_user(asker: &str, ok: u16) -> u16 {
    if role_of(asker).is_some() { ok } else { 401 }
}

/// Admins alone (the owner's settings, the baseline, pause, maintenance,
/// the self-test); 403 for every other user.
fn admins(asker: &str, ok: u16) -> u16 {
    match role_of(asker) {
        None => 401,
        Some(Role::Admin) => ok,
        Some(_) => 403,
    }
}

/// The audit log: developers and admins ("upload, validate, activate,
/// roll back, audit log"; a researcher has no audit log).
fn developers(asker: &str, ok: u16) -> u16 {
    match role_of(asker) {
        None => 401,
        Some(Role::Admin | Role::Developer) => ok,
        Some(_) => 403,
    }
}

/// Uploading and staging for the control platform: developers and
/// researchers who hold it, admins.
fn control_holders(asker: &str, ok: u16) -> u16 {
    match role_of(asker) {
        None => 401,
        Some(_) if holds_control(asker) => ok,
        Some(_) => 403,
    }
}

/// For the network platform: no one here holds it but the admin.
fn network_holders(asker: &str, ok: u16) -> u16 {
    admins(asker, ok)
}

/// Submitting experiments and the lab kit (on): researchers, developers
/// and admins; viewers and operators watch.
fn submitters(asker: &str, ok: u16) -> u16 {
    match role_of(asker) {
        None => 401,
        Some(Role::Researcher | Role::Developer | Role::Admin) => ok,
        Some(_) => 403,
    }
}

/// A researcher's work (her upload, set, experiment, results): hers and
/// the admins'; anyone else gets 404 as for a missing one.
fn owner_and_admins(asker: &str, ok: u16) -> u16 {
    match role_of(asker) {
        None => 401,
        Some(Role::Admin) => ok,
        Some(_) if asker == OWNER => ok,
        Some(_) => 404,
    }
}

/// The caller's own upload by its name: only the admin uploaded
/// `robot-part`.
fn own_upload_of_admin(asker: &str, ok: u16) -> u16 {
    match role_of(asker) {
        None => 401,
        Some(Role::Admin) => ok,
        Some(_) => 404,
    }
}

/// A route of a robot's own portal: a lab server has none ("no such API
/// route on a lab server"), whoever asks.
fn not_on_a_lab_server(_: &str, _: u16) -> u16 {
    404
}

type Expect = fn(&str, u16) -> u16;

/// What a request carries.
#[derive(Clone, Copy, Debug)]
enum Payload {
    Nothing,
    Text(&'static str),
    /// The asker's own name and password.
    Login,
    /// A component's bytes.
    Wasm,
    /// The baseline with the control (or network) platform changed.
    ControlFile,
    NetworkFile,
    /// The owner's settings as they are.
    Settings,
    /// `{"set": BASELINE}`.
    Baseline,
    /// The baseline as an experiment.
    Submission,
    /// A simulator's world.
    World,
}

/// How an answer is read.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Read {
    Whole,
    /// A server-sent event stream: its head.
    Stream,
}

struct Route {
    method: &'static str,
    /// `{base}` the baseline's set, `{set}` the researcher's set, `{exp}`
    /// her ended experiment, `{comp}` her upload; `{doomed}` and `{live}`
    /// a set and an experiment of hers, one for each asker who may end
    /// it (forgetting and cancelling succeed once).
    path: &'static str,
    send: Payload,
    read: Read,
    ok: u16,
    expect: Expect,
    /// Text every success answer holds (with `{base}` filled in): what
    /// shows the route did its work, not merely that it answered.
    shows: &'static str,
}

const fn route(method: &'static str, path: &'static str, send: Payload, ok: u16, expect: Expect) -> Route {
    Route { method, path, send, read: Read::Whole, ok, expect, shows: "" }
}

impl Route {
    const fn showing(self, shows: &'static str) -> Route {
        Route { shows, ..self }
    }
}

/// Every route a lab server serves, in the order asked (each leaves the
/// next's expectations as they were: the admin's pause is resumed, the
/// maintenance ended, a visibility set as it was).
fn served() -> Vec<Route> {
    use Payload::*;
    vec![
        route("POST", "/api/v1/login", Login, 200, anyone),
        route("GET", "/api/v1/session", Nothing, 200, any_user),
        route("GET", "/api/v1/components", Nothing, 200, any_user).showing("admin/robot-part.wasm"),
        route("GET", "/api/v1/components/robot-part", Nothing, 200, own_upload_of_admin),
        // The robot's own upload (an admin's): every user sees it.
        route("GET", "/api/v1/components/admin/robot-part", Nothing, 200, any_user),
        route("GET", "/api/v1/components/researcher/{comp}", Nothing, 200, owner_and_admins),
        route(
            "PUT",
            "/api/v1/components/researcher/{comp}/visibility",
            Text(r#"{"visibility":"private"}"#),
            200,
            owner_and_admins,
        ),
        route("PUT", "/api/v1/platforms/control/components/uploaded", Wasm, 201, control_holders),
        route("PUT", "/api/v1/platforms/network/components/uploaded", Wasm, 201, network_holders),
        route("PUT", "/api/v1/platforms/control/configs/staged.xml", ControlFile, 201, control_holders),
        route("PUT", "/api/v1/platforms/network/configs/staged.xml", NetworkFile, 201, network_holders),
        route("POST", "/api/v1/platforms/control/validate/checked.xml", ControlFile, 200, control_holders),
        route("POST", "/api/v1/platforms/network/validate/checked.xml", NetworkFile, 200, network_holders),
        route("GET", "/api/v1/worlds", Nothing, 200, any_user),
        route("PUT", "/api/v1/worlds/arena.world", World, 201, control_holders),
        route("GET", "/api/v1/sets", Nothing, 200, any_user).showing(r#""id":{base}"#),
        // The baseline the lab learned from its robot: the robot's own.
        route("GET", "/api/v1/sets/{base}", Nothing, 200, any_user),
        route("GET", "/api/v1/sets/{set}", Nothing, 200, owner_and_admins),
        route("DELETE", "/api/v1/sets/{doomed}", Nothing, 204, owner_and_admins),
        route("GET", "/api/v1/logs", Nothing, 200, any_user),
        route("GET", "/api/v1/audit", Nothing, 200, developers),
        route("GET", "/api/v1/experiments", Nothing, 200, any_user),
        route("POST", "/api/v1/experiments", Submission, 201, submitters),
        route("GET", "/api/v1/experiments/{exp}", Nothing, 200, owner_and_admins),
        route("GET", "/api/v1/experiments/{exp}/results", Nothing, 200, owner_and_admins).showing("experiment.json"),
        route("POST", "/api/v1/experiments/{live}/cancel", Nothing, 200, owner_and_admins),
        route("GET", "/api/v1/lab", Nothing, 200, any_user),
        Route { read: Read::Stream, ..route("GET", "/api/v1/lab/events", Nothing, 200, any_user) }
            .showing("text/event-stream"),
        route("PUT", "/api/v1/lab/settings", Settings, 200, admins),
        route("PUT", "/api/v1/lab/baseline", Baseline, 200, admins),
        route("POST", "/api/v1/lab/pause", Nothing, 200, admins),
        route("POST", "/api/v1/lab/resume", Nothing, 200, admins),
        route("GET", "/api/v1/lab/kit", Nothing, 200, submitters).showing("robot.xml"),
        route("GET", "/api/v1/tasks/reach/leaderboard", Nothing, 200, any_user),
        route("POST", "/api/v1/lab/maintenance", Text(r#"{"reason": "a wheel to change"}"#), 200, admins),
        route("DELETE", "/api/v1/lab/maintenance", Nothing, 200, admins),
        route("GET", "/api/v1/lab/mail", Nothing, 200, any_user),
        route(
            "PUT",
            "/api/v1/lab/mail",
            Text(r#"{"address": "someone@example.org", "events": ["experiment.started"]}"#),
            200,
            any_user,
        ),
        route("DELETE", "/api/v1/lab/mail", Nothing, 200, any_user),
        // The lab server's own: its robots, their live view and STOP.
        route("GET", "/api/v1/robots", Nothing, 200, any_user).showing(r#""name":"r1""#),
        // Asked of the robot over Zenoh; it runs no control loop here, so
        // its live status is `null`, but a signed answer came back.
        route("GET", "/api/v1/robots/r1/live", Nothing, 200, any_user).showing(r#""status":"#),
        route("POST", "/api/v1/robots/r1/stop", Nothing, 200, any_user).showing(r#""engaged":true"#),
        route("POST", "/api/v1/robots/stop", Nothing, 200, any_user).showing(r#""robot":"r1""#),
        route("GET", "/api/v1/openapi.json", Nothing, 200, anyone),
        route("GET", "/", Nothing, 200, anyone),
        route("GET", "/lab.js", Nothing, 200, anyone),
        route("GET", "/style.css", Nothing, 200, anyone),
        // From a peer off loopback: logged-in users.
        route("GET", "/metrics", Nothing, 200, any_user).showing("subsume_lab_robots"),
        // Last: it ends the session (asked with a session of its own).
        route("POST", "/api/v1/logout", Nothing, 204, any_user),
    ]
}

/// Why a lab server refuses a reservation (docs/lab.md, "Several robots").
const NO_RESERVATIONS: &str = "a lab server takes no reservations (not built yet";

/// The routes of a robot's own portal that a lab server, running no
/// robot, does not serve.
fn robot_only() -> Vec<Route> {
    let gone = |method, path| route(method, path, Payload::Nothing, 404, not_on_a_lab_server);
    vec![
        gone("POST", "/api/v1/sets/{base}/activate"),
        gone("POST", "/api/v1/sets/{base}/replay"),
        gone("POST", "/api/v1/rollback"),
        gone("GET", "/api/v1/status"),
        gone("GET", "/api/v1/history"),
        gone("GET", "/api/v1/events"),
        gone("GET", "/api/v1/world"),
        gone("GET", "/api/v1/cameras"),
        gone("GET", "/api/v1/cameras/front/live"),
        gone("POST", "/api/v1/sim/reset"),
        gone("POST", "/api/v1/estop"),
        gone("POST", "/api/v1/release"),
        gone("GET", "/api/v1/locks"),
        gone("GET", "/api/v1/recordings"),
        gone("POST", "/api/v1/recordings/start"),
        gone("POST", "/api/v1/recordings/stop"),
        gone("GET", "/api/v1/recordings/rec-1.mcap"),
        gone("DELETE", "/api/v1/recordings/rec-1.mcap"),
        // The robot's self-test: a lab server has no robot to test (its
        // owner's settings may name one; each robot tests itself).
        gone("POST", "/api/v1/lab/selftest"),
        gone("POST", "/api/v1/lab/reset"),
        // Reservations: the lab server says why (`subsume lab reserve`).
        gone("POST", "/api/v1/lab/reservations").showing(NO_RESERVATIONS),
        gone("DELETE", "/api/v1/lab/reservations/1").showing(NO_RESERVATIONS),
        gone("POST", "/api/v1/teleop/ticket"),
        gone("GET", "/api/v1/teleop"),
    ]
}

/// What the fixtures made, by placeholder; per asker where it differs.
struct Fixtures {
    base: u64,
    values: BTreeMap<&'static str, String>,
    per_asker: BTreeMap<(&'static str, &'static str), String>,
    wasm: Vec<u8>,
    settings: Json,
}

impl Fixtures {
    fn fill(&self, path: &str, asker: &str) -> String {
        let mut path = path.replace("{base}", &self.base.to_string());
        for (key, value) in &self.values {
            path = path.replace(&format!("{{{key}}}"), value);
        }
        for ((key, who), value) in &self.per_asker {
            if *who == asker {
                path = path.replace(&format!("{{{key}}}"), value);
            }
        }
        // Askers with no target of their own ask for the owner's.
        for ((key, who), value) in &self.per_asker {
            if *who == OWNER {
                path = path.replace(&format!("{{{key}}}"), value);
            }
        }
        path
    }

    fn body(&self, send: Payload, asker: &str) -> Vec<u8> {
        match send {
            Payload::Nothing => Vec::new(),
            Payload::Text(text) => text.as_bytes().to_vec(),
            Payload::Login => {
                // Nobody logs in as the viewer: login needs no session.
                let name = if asker == NOBODY { "viewer" } else { asker };
                serde_json::json!({ "name": name, "password": password(name) }).to_string().into_bytes()
            }
            Payload::Wasm => self.wasm.clone(),
            Payload::ControlFile => robot_file(2, 1).into_bytes(),
            Payload::NetworkFile => robot_file(1, 2).into_bytes(),
            Payload::World => crate::lab::WORLD.as_bytes().to_vec(),
            Payload::Settings => self.settings.to_string().into_bytes(),
            Payload::Baseline => serde_json::json!({ "set": self.base }).to_string().into_bytes(),
            Payload::Submission => {
                serde_json::json!({ "set": self.base, "duration_s": 1.0, "label": format!("by {asker}") })
                    .to_string()
                    .into_bytes()
            }
        }
    }
}

/// The lab server and its robot, in this process.
struct LabServer {
    app: axum::Router,
    tokens: BTreeMap<&'static str, String>,
    lab: Arc<Lab>,
    fleet: Arc<Fleet>,
    robot_lab: Arc<Lab>,
    link: Arc<RobotLink>,
    _dir: tempfile::TempDir,
}

impl Drop for LabServer {
    fn drop(&mut self) {
        self.link.shut_down();
        self.robot_lab.shut_down(None);
        self.lab.shut_down(None);
        self.fleet.shut_down();
    }
}

/// A Zenoh session of this test alone: peer mode, no endpoint, no
/// scouting (the lab server and its robot share it: equal settings share
/// one session).
fn local_session(dir: &Path) -> SessionSettings {
    let config = dir.join("zenoh.json5");
    std::fs::write(
        &config,
        r#"{ mode: "peer", listen: { endpoints: [] }, connect: { endpoints: [] },
  scouting: { multicast: { enabled: false }, gossip: { enabled: false } } }"#,
    )
    .unwrap();
    SessionSettings {
        connect: vec![],
        listen: vec![],
        config: Some(config),
        max_message_bytes: Some(subsume::lab::wire::MAX_ZENOH_MESSAGE_BYTES),
    }
}

fn preflight() -> subsume::lab::preflight::PreflightCommand {
    subsume::lab::preflight::PreflightCommand {
        exe: std::path::PathBuf::from(env!("CARGO_BIN_EXE_subsume")),
        cache_dir: Some(support::cache_dir()),
        priority: subsume::lab::preflight::Priority::Normal,
        limits: subsume::lab::preflight::PreflightLimits::default(),
    }
}

/// Robot `r1`: a robot host's deployer and lab on its own store, joined
/// to the lab over `session`, out of service (so the lab server
/// dispatches nothing to it: it runs no control loop).
fn start_robot(dir: &Path, key: &LabKey, session: &SessionSettings) -> (Arc<Lab>, Arc<RobotLink>) {
    std::fs::create_dir_all(dir).unwrap();
    std::fs::write(dir.join("robot.xml"), robot_file(1, 1)).unwrap();
    let store = Arc::new(Store::open(&dir.join("store")).unwrap());
    let directory = Arc::new(Directory::new(store.users().clone()));
    let shutdown = Shutdown::new();
    let boot = Deployer::boot(BootOptions {
        store,
        sandbox: Arc::new(support::sandbox()),
        services: Services::default().with(directory),
        config_path: &dir.join("robot.xml"),
        overrides: vec![],
        clock: Clock::new(),
        waker: shutdown.waker(),
    })
    .map_err(|e| e.to_string())
    .unwrap();
    let lab = Lab::start(
        boot.deployer,
        LabOptions { preflight: preflight(), role: LabRole::Joined { lab: LAB.to_string() } },
    )
    .unwrap();
    let owner = Principal { name: "owner".into(), role: Role::Admin, platforms: vec![] };
    lab.enter_maintenance(&owner, "no control loop runs in this test").unwrap();
    let link = RobotLink::start(
        lab.clone(),
        RobotLinkOptions {
            key: key.clone(),
            session: session.clone(),
            robot: ROBOT_NAME.to_string(),
            lost_after: Duration::from_secs(30),
            status_period: Duration::from_millis(200),
        },
        HiddenPaths::default(),
    )
    .unwrap();
    (lab, link)
}

/// One request through the router from a peer off loopback: (status,
/// body). A stream answers its head only.
async fn send(
    app: &axum::Router,
    method: &str,
    uri: &str,
    token: Option<&str>,
    body: Vec<u8>,
    read: Read,
) -> (u16, Vec<u8>) {
    let mut request = Request::builder().method(method).uri(uri);
    if let Some(token) = token {
        request = request.header("authorization", format!("Bearer {token}"));
    }
    let mut request = request.body(Body::from(body)).unwrap();
    let peer: std::net::SocketAddr = "192.0.2.7:40000".parse().unwrap();
    request.extensions_mut().insert(axum::extract::ConnectInfo(peer));
    let response = app.clone().oneshot(request).await.unwrap();
    let status = response.status().as_u16();
    if read == Read::Stream && status == 200 {
        let head = format!("{:?}", response.headers().get("content-type"));
        return (status, head.into_bytes());
    }
    let bytes = axum::body::to_bytes(response.into_body(), usize::MAX).await.unwrap();
    (status, bytes.to_vec())
}

fn json(bytes: &[u8]) -> Json {
    serde_json::from_slice(bytes).unwrap_or(Json::Null)
}

impl LabServer {
    fn start(runtime: &tokio::runtime::Runtime) -> (LabServer, Fixtures) {
        let dir = tempfile::tempdir().unwrap();
        let store_dir = dir.path().join("lab-store");
        let store = Arc::new(Store::open(&store_dir).unwrap());
        {
            let writer = store.lock().unwrap();
            for (name, role, platforms) in USERS {
                writer.users_mut().add(name, *role, platforms, &password(name), false).unwrap();
            }
        }
        // The lab sends mail (to nobody listening): the mail routes work.
        let mail =
            serde_json::json!({ "server": "127.0.0.1", "port": 9, "security": "plain", "from": "lab@example.org" });
        std::fs::write(store_dir.join("mail.json"), mail.to_string()).unwrap();
        let key = LabKey::from_file_or_new(LAB, &store_dir.join("lab.secret")).unwrap();
        let session = local_session(dir.path());
        let directory = Arc::new(Directory::new(store.users().clone()));
        let deployer = Deployer::headless(
            store.clone(),
            Arc::new(support::sandbox()),
            Services::default().with(directory.clone()),
        );
        let fleet = Fleet::start(
            store.clone(),
            FleetOptions {
                key: key.clone(),
                session: session.clone(),
                relearn: Duration::from_secs(15),
                dispatch_timeout: Duration::from_secs(150),
            },
        )
        .unwrap();
        let lab =
            Lab::start(deployer.clone(), LabOptions { preflight: preflight(), role: LabRole::Server(fleet.clone()) })
                .unwrap();
        let state = PortalState::new(deployer, lab.clone(), directory, portal::logs::LogRing::new())
            .hiding(HiddenPaths::new(&[(store_dir.as_path(), "<store>")]));
        let app = portal::lab_server_app(state);
        let (robot_lab, link) = start_robot(&dir.path().join("robot"), &key, &session);
        let mut server = LabServer { app, tokens: BTreeMap::new(), lab, fleet, robot_lab, link, _dir: dir };
        let fixtures = runtime.block_on(server.fixtures());
        (server, fixtures)
    }

    async fn call(&self, user: &str, method: &str, uri: &str, body: impl Into<Vec<u8>>) -> (u16, Json) {
        let token = self.tokens.get(user).map(String::as_str);
        let (status, bytes) = send(&self.app, method, uri, token, body.into(), Read::Whole).await;
        (status, json(&bytes))
    }

    async fn login(&self, user: &str) -> String {
        let body = serde_json::json!({ "name": user, "password": password(user) }).to_string();
        let (status, bytes) = send(&self.app, "POST", "/api/v1/login", None, body.into_bytes(), Read::Whole).await;
        assert_eq!(status, 200, "{}", String::from_utf8_lossy(&bytes));
        json(&bytes)["token"].as_str().unwrap().to_string()
    }

    /// Logs everyone in, waits for the robot and its baseline, and makes
    /// what the routes ask for.
    async fn fixtures(&mut self) -> Fixtures {
        for (name, _, _) in USERS {
            let token = self.login(name).await;
            self.tokens.insert(name, token);
        }
        let deadline = Instant::now() + Duration::from_secs(60);
        let base = loop {
            let (status, listed) = self.call("admin", "GET", "/api/v1/robots", "").await;
            assert_eq!(status, 200, "{listed}");
            let robot = &listed["robots"][0];
            if robot["online"] == true
                && let Some(set) = robot["baseline_set"].as_u64()
            {
                assert_eq!((robot["name"].as_str(), robot["state"].as_str()), (Some(ROBOT_NAME), Some("maintenance")));
                break set;
            }
            assert!(Instant::now() < deadline, "robot r1 never joined with its baseline: {listed}");
            tokio::time::sleep(Duration::from_millis(50)).await;
        };
        let wasm = std::fs::read(support::guest("test-relay")).unwrap();
        let (status, json) =
            self.call("admin", "PUT", "/api/v1/platforms/control/components/robot-part", wasm.clone()).await;
        assert_eq!(status, 201, "{json}");
        let comp = "private-part";
        let uri = format!("/api/v1/platforms/control/components/{comp}");
        let (status, json) = self.call(OWNER, "PUT", &uri, wasm.clone()).await;
        assert_eq!(status, 201, "{json}");
        // Her set, and a set for each asker who may forget one.
        let stage = async |file: &str| {
            let uri = format!("/api/v1/platforms/control/configs/{file}");
            let (status, json) = self.call(OWNER, "PUT", &uri, robot_file(3, 1)).await;
            assert_eq!(status, 201, "{json}");
            json["set"]["id"].as_u64().unwrap().to_string()
        };
        let set = stage("hers.xml").await;
        let doomed_hers = stage("doomed.xml").await;
        let doomed_admins = stage("doomed-too.xml").await;
        // Her experiments: one ended, and one live for each who may cancel.
        let submit = async |label: &str| {
            let body = serde_json::json!({ "set": set.parse::<u64>().unwrap(), "duration_s": 1.0, "label": label });
            let (status, json) = self.call(OWNER, "POST", "/api/v1/experiments", body.to_string()).await;
            assert_eq!(status, 201, "{json}");
            json["experiment"]["id"].as_u64().unwrap().to_string()
        };
        let exp = submit("ended").await;
        let live_hers = submit("live").await;
        let live_admins = submit("live too").await;
        let (status, json) = self.call(OWNER, "POST", &format!("/api/v1/experiments/{exp}/cancel"), "").await;
        assert_eq!(status, 200, "{json}");
        // The owner's settings, with a task (its leaderboard).
        let (status, overview) = self.call("admin", "GET", "/api/v1/lab", "").await;
        assert_eq!(status, 200, "{overview}");
        let mut settings = overview["lab"]["settings"].clone();
        settings["task"] = serde_json::json!({ "name": "reach", "description": "reach (6, 1)",
            "goal": {"x": 6.0, "y": 1.0, "radius": 0.4}, "metric": "time_to_goal",
            "pose": "motors.pose", "commands": "envelope.cmd", "board": "best", "pseudonyms": true });
        // A self-test in the settings: a lab server still runs none.
        settings["self_test"] = serde_json::json!({ "window_ms": 200 });
        let (status, json) = self.call("admin", "PUT", "/api/v1/lab/settings", settings.to_string()).await;
        assert_eq!(status, 200, "{json}");
        let settings = json["settings"].clone();
        Fixtures {
            base,
            values: BTreeMap::from([("set", set), ("exp", exp), ("comp", comp.to_string())]),
            per_asker: BTreeMap::from([
                (("doomed", OWNER), doomed_hers),
                (("doomed", "admin"), doomed_admins),
                (("live", OWNER), live_hers),
                (("live", "admin"), live_admins),
            ]),
            wasm,
            settings,
        }
    }

    /// Asks `route` as every asker: what was wrong, and how many
    /// askers it answered with success.
    async fn ask(&self, route: &Route, fixtures: &Fixtures, served_here: bool) -> (Vec<String>, usize) {
        let askers: Vec<&str> = std::iter::once(NOBODY).chain(USERS.iter().map(|(n, _, _)| *n)).collect();
        let mut asks = Vec::new();
        for asker in &askers {
            let uri = fixtures.fill(route.path, asker);
            let body = fixtures.body(route.send, asker);
            let token = if route.path.ends_with("/logout") && *asker != NOBODY {
                Some(self.login(asker).await)
            } else {
                self.tokens.get(asker).cloned()
            };
            // One after another: a second validation meanwhile answers 429.
            let (status, bytes) = send(&self.app, route.method, &uri, token.as_deref(), body, route.read).await;
            asks.push((*asker, uri, status, bytes));
        }
        let mut wrong = Vec::new();
        let mut succeeded = 0;
        for (asker, uri, status, bytes) in asks {
            let expected = (route.expect)(asker, route.ok);
            let text = String::from_utf8_lossy(&bytes[..bytes.len().min(300)]).into_owned();
            let cell = format!("{} {uri} as {asker}", route.method);
            if status != expected {
                wrong.push(format!("{cell}: {status}, expected {expected}: {text}"));
                continue;
            }
            if (200..300).contains(&status) {
                succeeded += 1;
                let shows = route.shows.replace("{base}", &fixtures.base.to_string());
                if status != 204 && bytes.is_empty() {
                    wrong.push(format!("{cell}: {status} with an empty answer"));
                } else if !shows.is_empty() && !bytes.windows(shows.len()).any(|w| w == shows.as_bytes()) {
                    wrong.push(format!("{cell}: {status} without {shows}: {text}"));
                }
            } else if uri.starts_with("/api/") && json(&bytes)["error"].as_str().is_none_or(str::is_empty) {
                wrong.push(format!("{cell}: {status} without a JSON error saying why: {text}"));
            } else if !served_here {
                // A robot's route the command line has a command for is
                // answered with why; any other, as a route it lacks.
                let lacks = if route.shows.is_empty() { "no such API route on a lab server" } else { route.shows };
                if !text.contains(lacks) {
                    wrong.push(format!("{cell}: 404 but not as a route the lab server lacks ({lacks}): {text}"));
                }
            } else if !uri.starts_with("/api/v1/openapi") && text.contains("no such API route") {
                wrong.push(format!("{cell}: the lab server does not route it: {text}"));
            }
        }
        (wrong, succeeded)
    }
}

/// `(METHOD, /api/v1/PATTERN)` of every operation openapi.json documents.
fn documented(doc: &Json) -> Vec<(String, String)> {
    let mut routes = Vec::new();
    for (path, methods) in doc["paths"].as_object().unwrap() {
        for method in methods.as_object().unwrap().keys() {
            routes.push((method.to_uppercase(), path.clone()));
        }
    }
    routes
}

/// Whether `path` (a table's path, its placeholders as segments) is an
/// instance of `pattern` (openapi.json's, or the router's, `{param}`s).
fn matches(pattern: &str, path: &str) -> bool {
    let pattern: Vec<&str> = pattern.split('/').collect();
    let parts: Vec<&str> = path.split('/').collect();
    pattern.len() == parts.len()
        && pattern.iter().zip(&parts).all(|(a, b)| a == b || (a.starts_with('{') && a.ends_with('}')))
}

/// `(METHODS, PATH)` of every `.route(...)` in the body of function `name`
/// in `source`.
fn mounted(source: &str, name: &str) -> Vec<(Vec<&'static str>, String)> {
    let start = source.find(&format!("fn {name}(")).unwrap_or_else(|| panic!("no fn {name} in portal/mod.rs"));
    let body = &source[start..];
    let body = &body[..body.find("\n}\n").unwrap()];
    let mut routes = Vec::new();
    for call in body.split(".route(").skip(1) {
        let path = call.split('"').nth(1).unwrap().to_string();
        let methods = ["get", "post", "put", "delete"]
            .into_iter()
            .filter(|m| {
                call.match_indices(&format!("{m}(")).any(|(at, _)| {
                    at == 0 || !call.as_bytes()[at - 1].is_ascii_alphanumeric() && call.as_bytes()[at - 1] != b'_'
                })
            })
            .collect();
        routes.push((methods, path));
    }
    routes
}

#[test]
fn every_route_of_a_lab_server_answers_every_role_as_the_documented_model_says() {
    let began = Instant::now();
    let runtime = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build().unwrap();
    let (server, fixtures) = LabServer::start(&runtime);
    eprintln!("labserver_router: the lab server and its robot up in {:.1} s", began.elapsed().as_secs_f64());
    let served = served();
    let robot_only = robot_only();

    // The tables against the routes: every route the lab server mounts is
    // in `served`; every documented route is in one table, and every
    // served API route is documented.
    let mut wrong = Vec::new();
    let source = std::fs::read_to_string(support::repo_root().join("host/src/portal/mod.rs")).unwrap();
    let mut mounts: Vec<(Vec<&str>, String)> =
        mounted(&source, "shared_api").into_iter().map(|(m, p)| (m, format!("/api/v1{p}"))).collect();
    mounts.extend(mounted(&source, "lab_server_app"));
    assert!(mounts.len() > 30, "{mounts:?}");
    for (methods, path) in &mounts {
        assert!(!methods.is_empty(), "no method found for {path}");
        for method in methods {
            if !served.iter().any(|r| r.method.eq_ignore_ascii_case(method) && matches(path, r.path)) {
                wrong.push(format!("{method} {path} is mounted on a lab server but not in `served`"));
            }
        }
    }
    let (status, doc) = runtime.block_on(server.call(NOBODY, "GET", "/api/v1/openapi.json", ""));
    assert_eq!(status, 200);
    let documented = documented(&doc);
    for (method, path) in &documented {
        let mut tables = served.iter().chain(&robot_only);
        if !tables.any(|r| r.method == method && matches(path, r.path)) {
            wrong.push(format!("{method} {path} is documented but in neither table"));
        }
    }
    for route in served.iter().chain(&robot_only).filter(|r| r.path.starts_with("/api/")) {
        if !documented.iter().any(|(m, p)| m == route.method && matches(p, route.path)) {
            wrong.push(format!("{} {} is in a table but not in openapi.json", route.method, route.path));
        }
    }

    let mut cells = 0;
    let tables = served.iter().map(|r| (r, true)).chain(robot_only.iter().map(|r| (r, false)));
    for (route, served_here) in tables {
        let (found, succeeded) = runtime.block_on(server.ask(route, &fixtures, served_here));
        cells += USERS.len() + 1;
        wrong.extend(found);
        if served_here && succeeded == 0 {
            wrong.push(format!("{} {} answered no one with success", route.method, route.path));
        }
    }
    eprintln!("labserver_router: {cells} cells asked in {:.1} s", began.elapsed().as_secs_f64());
    assert!(wrong.is_empty(), "{} of {cells} cells wrong:\n{}", wrong.len(), wrong.join("\n"));
    drop(server);
}
