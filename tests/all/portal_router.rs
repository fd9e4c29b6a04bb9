//! The portal's router without a server (`oneshot`): every endpoint x every
//! role, the malformed-upload corpus, login rate limiting with controlled
//! time, and the OpenAPI document against the routes.

use std::sync::Arc;

use axum::body::Body;
use axum::http::{Request, StatusCode};
use serde_json::Value;
use subsume::builtin::Services;
use subsume::config::Platform;
use subsume::deploy::MAX_UPLOAD_BYTES;
use subsume::deploy::{BootOptions, Deployer};
use subsume::portal::{self, PortalState};
use subsume::record::control::Recordings;
use subsume::runtime::control_loop::{Clock, Shutdown};
use subsume::store::Store;
use subsume::store::users::{Directory, Role};
use subsume::teleop::TeleopServers;
use tower::ServiceExt as _;

use crate::support;

const ROBOT: &str = r#"<robot name="bench">
  <platform name="control">
    <component name="source" source="builtin:publish" rate="10"><param name="value" value="1"/></component>
    <component name="sink" source="builtin:log" rate="0"/>
    <connect from="source.out" to="sink.in"/>
  </platform>
</robot>
"#;

/// (name, role, platforms): one user per case of the matrix.
const USERS: &[(&str, Role, &[Platform])] = &[
    ("viewer", Role::Viewer, &[]),
    ("operator", Role::Operator, &[]),
    ("control-dev", Role::Developer, &[Platform::Control]),
    ("network-dev", Role::Developer, &[Platform::Network]),
    ("researcher", Role::Researcher, &[Platform::Control]),
    ("admin", Role::Admin, &[]),
];

struct Portal {
    app: axum::Router,
    store: Arc<Store>,
    _dir: tempfile::TempDir,
    tokens: std::collections::HashMap<&'static str, String>,
}

fn password(name: &str) -> String {
    format!("{name}-password-123")
}

async fn portal() -> Portal {
    portal_over(false).await
}

/// The portal, as served over TLS (`over_tls`) or plain HTTP.
async fn portal_over(over_tls: bool) -> Portal {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("robot.xml"), ROBOT).unwrap();
    let store = Arc::new(Store::open(&dir.path().join("store")).unwrap());
    {
        let writer = store.lock().unwrap();
        for (name, role, platforms) in USERS {
            writer.users_mut().add(name, *role, platforms, &password(name), false).unwrap();
        }
    }
    let directory = Arc::new(Directory::new(store.users().clone()));
    let shutdown = Shutdown::new();
    let boot = Deployer::boot(BootOptions {
        store: store.clone(),
        sandbox: Arc::new(support::sandbox()),
        services: Services::default().with(directory.clone()).with(Arc::new(TeleopServers::default())).with(Arc::new(
            Recordings::new(
                dir.path().join("recordings"),
                subsume::record::DEFAULT_MAX_FILE_BYTES,
                subsume::record::Timeline::new(0, Clock::new()),
                false,
            )
            .unwrap(),
        )),
        config_path: &dir.path().join("robot.xml"),
        overrides: vec![],
        clock: Clock::new(),
        waker: shutdown.waker(),
    })
    .map_err(|e| e.to_string())
    .unwrap();
    let lab = subsume::lab::Lab::start(
        boot.deployer.clone(),
        subsume::lab::LabOptions {
            preflight: subsume::lab::preflight::PreflightCommand {
                exe: std::path::PathBuf::from(env!("CARGO_BIN_EXE_subsume")),
                cache_dir: Some(support::cache_dir()),
                priority: subsume::lab::preflight::Priority::Background,
                limits: subsume::lab::preflight::PreflightLimits::default(),
            },
            role: subsume::lab::LabRole::Alone,
        },
    )
    .unwrap();
    let state = if over_tls {
        PortalState::over_tls(boot.deployer, lab, directory, portal::logs::LogRing::new())
    } else {
        PortalState::new(boot.deployer, lab, directory, portal::logs::LogRing::new())
    };
    let store_dir = dir.path().join("store");
    let state = state.hiding(subsume::fsutil::HiddenPaths::new(&[
        (dir.path(), "<robot file folder>"),
        (store_dir.as_path(), "<store>"),
    ]));
    let app = portal::app(state);
    let mut tokens = std::collections::HashMap::new();
    for (name, _, _) in USERS {
        let body = serde_json::json!({ "name": name, "password": password(name) }).to_string();
        let (status, json) = send(&app, "POST", "/api/v1/login", None, Body::from(body)).await;
        assert_eq!(status, StatusCode::OK, "{json}");
        tokens.insert(*name, json["token"].as_str().unwrap().to_string());
    }
    Portal { app, store, _dir: dir, tokens }
}

async fn send(app: &axum::Router, method: &str, uri: &str, token: Option<&str>, body: Body) -> (StatusCode, Value) {
    let mut request = Request::builder().method(method).uri(uri);
    if let Some(token) = token {
        request = request.header("authorization", format!("Bearer {token}"));
    }
    let response = app.clone().oneshot(request.body(body).unwrap()).await.unwrap();
    let status = response.status();
    let bytes = axum::body::to_bytes(response.into_body(), usize::MAX).await.unwrap();
    (status, serde_json::from_slice(&bytes).unwrap_or(Value::Null))
}

impl Portal {
    async fn call(&self, user: &str, method: &str, uri: &str, body: impl Into<Body>) -> (StatusCode, Value) {
        send(&self.app, method, uri, self.tokens.get(user).map(String::as_str), body.into()).await
    }

    /// What must not change when a request is refused.
    fn snapshot(&self) -> String {
        format!(
            "{:?} {:?} {}",
            self.store.state().unwrap(),
            self.store.components().unwrap().keys().collect::<Vec<_>>(),
            self.store.sets().unwrap().len()
        )
    }
}

/// Which users may call an endpoint.
#[derive(Clone, Copy, Debug)]
enum Allowed {
    AnyUser,
    Control,
    Network,
    Developer,
    Drive,
    /// Researchers, developers and admins (the lab).
    Submit,
    Admin,
}

impl Allowed {
    fn admits(self, user: &str) -> bool {
        match self {
            Allowed::AnyUser => true,
            Allowed::Control => matches!(user, "control-dev" | "researcher" | "admin"),
            Allowed::Network => matches!(user, "network-dev" | "admin"),
            Allowed::Developer => matches!(user, "control-dev" | "network-dev" | "admin"),
            Allowed::Drive => matches!(user, "operator" | "admin"),
            Allowed::Submit => matches!(user, "control-dev" | "network-dev" | "researcher" | "admin"),
            Allowed::Admin => user == "admin",
        }
    }
}

/// The lab's default settings as a body (changes nothing when an admin
/// sends it).
const LAB_SETTINGS: &[u8] = br#"{"max_duration_s": 120.0, "limits": {"max_queued": 3, "robot_minutes_per_day": 30.0,
  "max_reservation_s": 1800, "reservation_per_day_s": 3600}, "criteria": {"max_collisions": 0, "allow_faults": false,
  "allow_geofence": false, "allow_stop_zone": false}, "reset": "sim", "preflight_world": null,
  "reference_recording": null, "retention_bytes": 10737418240, "kit": true}"#;

/// Every authenticated endpoint with a request that does no lasting harm.
fn endpoints() -> Vec<(&'static str, &'static str, &'static [u8], Allowed)> {
    vec![
        ("GET", "/api/v1/session", b"", Allowed::AnyUser),
        ("GET", "/api/v1/components", b"", Allowed::AnyUser),
        ("GET", "/api/v1/components/none", b"", Allowed::AnyUser),
        ("GET", "/api/v1/components/admin/none", b"", Allowed::AnyUser),
        // Someone else's upload, or none: 404 for every role (not 403).
        ("PUT", "/api/v1/components/admin/none/visibility", br#"{"visibility":"lab"}"#, Allowed::AnyUser),
        ("PUT", "/api/v1/platforms/control/components/x", b"not wasm", Allowed::Control),
        ("PUT", "/api/v1/platforms/network/components/x", b"not wasm", Allowed::Network),
        ("PUT", "/api/v1/platforms/control/configs/r.xml", b"<robot", Allowed::Control),
        ("PUT", "/api/v1/platforms/network/configs/r.xml", b"<robot", Allowed::Network),
        ("POST", "/api/v1/platforms/control/validate/r.xml", b"<robot", Allowed::Control),
        ("POST", "/api/v1/platforms/network/validate/r.xml", b"<robot", Allowed::Network),
        ("GET", "/api/v1/worlds", b"", Allowed::AnyUser),
        ("PUT", "/api/v1/worlds/w.world", b"bounds 0 0", Allowed::Control),
        ("GET", "/api/v1/sets", b"", Allowed::AnyUser),
        ("GET", "/api/v1/sets/1", b"", Allowed::AnyUser),
        // No such set (or someone else's): 404 for every role.
        ("DELETE", "/api/v1/sets/999", b"", Allowed::AnyUser),
        ("POST", "/api/v1/sets/999/activate", b"", Allowed::Developer),
        ("POST", "/api/v1/sets/1/replay", br#"{"recording":"rec-1.mcap"}"#, Allowed::Developer),
        ("POST", "/api/v1/rollback", b"", Allowed::Developer),
        ("GET", "/api/v1/status", b"", Allowed::AnyUser),
        ("GET", "/api/v1/history", b"", Allowed::AnyUser),
        ("GET", "/api/v1/world", b"", Allowed::AnyUser),
        ("GET", "/api/v1/logs", b"", Allowed::AnyUser),
        ("GET", "/api/v1/audit", b"", Allowed::Developer),
        ("GET", "/api/v1/recordings", b"", Allowed::Developer),
        ("POST", "/api/v1/recordings/start", b"", Allowed::Developer),
        ("POST", "/api/v1/recordings/stop", b"", Allowed::Developer),
        ("GET", "/api/v1/recordings/rec-1.mcap", b"", Allowed::Developer),
        ("DELETE", "/api/v1/recordings/rec-1.mcap", b"", Allowed::Developer),
        ("POST", "/api/v1/teleop/ticket", b"", Allowed::Drive),
        ("POST", "/api/v1/sim/reset", b"", Allowed::Drive),
        ("POST", "/api/v1/sim/step?seconds=0.1", b"", Allowed::Drive),
        ("POST", "/api/v1/estop", b"", Allowed::AnyUser),
        ("POST", "/api/v1/release", b"", Allowed::Drive),
        ("GET", "/api/v1/locks", b"", Allowed::AnyUser),
        ("GET", "/api/v1/experiments", b"", Allowed::AnyUser),
        ("POST", "/api/v1/experiments", br#"{"set": 999, "duration_s": 5}"#, Allowed::Submit),
        ("GET", "/api/v1/experiments/999", b"", Allowed::AnyUser),
        ("POST", "/api/v1/experiments/999/cancel", b"", Allowed::AnyUser),
        ("GET", "/api/v1/experiments/999/results", b"", Allowed::AnyUser),
        ("GET", "/api/v1/lab", b"", Allowed::AnyUser),
        ("PUT", "/api/v1/lab/settings", LAB_SETTINGS, Allowed::Admin),
        ("PUT", "/api/v1/lab/baseline", br#"{"set": 999}"#, Allowed::Admin),
        ("POST", "/api/v1/lab/resume", b"", Allowed::Admin),
        ("POST", "/api/v1/lab/reset", b"", Allowed::Admin),
        ("POST", "/api/v1/lab/reservations", br#"{"start_unix_ms": 0, "end_unix_ms": 1}"#, Allowed::Submit),
        ("DELETE", "/api/v1/lab/reservations/999", b"", Allowed::AnyUser),
        ("GET", "/api/v1/lab/kit", b"", Allowed::Submit),
        ("POST", "/api/v1/lab/maintenance", br#"{"reason": "a wheel to change"}"#, Allowed::Admin),
        ("DELETE", "/api/v1/lab/maintenance", b"", Allowed::Admin),
        // Her own mail subscription; this portal sends no mail: 409.
        ("GET", "/api/v1/lab/mail", b"", Allowed::AnyUser),
        ("PUT", "/api/v1/lab/mail", br#"{"address": "a@b.org", "events": ["experiment.ended"]}"#, Allowed::AnyUser),
        ("DELETE", "/api/v1/lab/mail", b"", Allowed::AnyUser),
        // A lab server's robots: on a robot, any user hears it is no lab
        // server (tests/all/labnet.rs drives them on a lab server).
        ("GET", "/api/v1/robots", b"", Allowed::AnyUser),
        ("POST", "/api/v1/robots/stop", b"", Allowed::AnyUser),
        ("GET", "/api/v1/robots/none/live", b"", Allowed::AnyUser),
        ("POST", "/api/v1/robots/none/stop", b"", Allowed::AnyUser),
        // The cameras: the owner and operators; a researcher only during
        // her own experiment (none runs here: tests/all/ipcam.rs has one).
        // No camera runs: 404 for those who may watch.
        ("GET", "/api/v1/cameras", b"", Allowed::Drive),
        ("GET", "/api/v1/cameras/none/live", b"", Allowed::Drive),
        ("POST", "/api/v1/logout", b"", Allowed::AnyUser),
    ]
}

#[tokio::test]
async fn every_endpoint_answers_every_role_as_its_permissions_say() {
    let portal = portal().await;
    for (method, uri, body, allowed) in endpoints() {
        let (status, json) = send(&portal.app, method, uri, None, Body::from(body)).await;
        assert_eq!(status, StatusCode::UNAUTHORIZED, "{method} {uri} without login: {json}");
        let (status, _) = send(&portal.app, method, uri, Some("not-a-token"), Body::from(body)).await;
        assert_eq!(status, StatusCode::UNAUTHORIZED, "{method} {uri} with a bad token");
        for (user, _, _) in USERS {
            if uri.ends_with("/logout") {
                continue;
            }
            let (status, json) = portal.call(user, method, uri, body).await;
            if allowed.admits(user) {
                assert!(
                    status != StatusCode::UNAUTHORIZED && status != StatusCode::FORBIDDEN,
                    "{method} {uri} as {user}: {status} {json}"
                );
            } else {
                assert_eq!(status, StatusCode::FORBIDDEN, "{method} {uri} as {user}: {json}");
                assert!(json["error"].as_str().is_some_and(|e| e.contains(user)), "{json}");
            }
        }
    }
    // Logging out ends the session.
    let (status, _) = portal.call("viewer", "POST", "/api/v1/logout", "").await;
    assert_eq!(status, StatusCode::NO_CONTENT);
    let (status, _) = portal.call("viewer", "GET", "/api/v1/session", "").await;
    assert_eq!(status, StatusCode::UNAUTHORIZED);
}

#[tokio::test]
async fn the_session_cookie_works_like_the_bearer_token() {
    let portal = portal().await;
    let request = Request::get("/api/v1/session")
        .header("cookie", format!("other=1; subsume_session={}", portal.tokens["viewer"]))
        .body(Body::empty())
        .unwrap();
    let response = portal.app.clone().oneshot(request).await.unwrap();
    assert_eq!(response.status(), StatusCode::OK);
}

#[tokio::test(start_paused = true)]
async fn failed_logins_are_rate_limited_per_user_and_recover() {
    let portal = portal().await;
    let login = |name: &str, password: &str| serde_json::json!({ "name": name, "password": password }).to_string();
    for _ in 0..portal::auth::MAX_LOGIN_FAILURES {
        let (status, _) = send(&portal.app, "POST", "/api/v1/login", None, login("admin", "wrong").into()).await;
        assert_eq!(status, StatusCode::UNAUTHORIZED);
    }
    // Even the right password is refused now, with the time to wait.
    let (status, json) =
        send(&portal.app, "POST", "/api/v1/login", None, login("admin", &password("admin")).into()).await;
    assert_eq!(status, StatusCode::TOO_MANY_REQUESTS, "{json}");
    assert!(json["error"].as_str().unwrap().starts_with("too many failed logins; try again in"), "{json}");
    // Other users are not locked out by it.
    let (status, _) =
        send(&portal.app, "POST", "/api/v1/login", None, login("viewer", &password("viewer")).into()).await;
    assert_eq!(status, StatusCode::OK);
    tokio::time::advance(portal::auth::LOGIN_FAILURE_WINDOW).await;
    let (status, _) = send(&portal.app, "POST", "/api/v1/login", None, login("admin", &password("admin")).into()).await;
    assert_eq!(status, StatusCode::OK);
    let (status, json) = send(&portal.app, "POST", "/api/v1/login", None, "{\"name\": 1}".into()).await;
    assert_eq!(status, StatusCode::BAD_REQUEST, "{json}");
}

/// (case, uri, body, expected status, words the error must contain)
fn malformed_uploads() -> Vec<(&'static str, String, Vec<u8>, StatusCode, &'static str)> {
    let component = |name: &str| format!("/api/v1/platforms/control/components/{name}");
    let config = |file: &str| format!("/api/v1/platforms/control/configs/{file}");
    let avoider = std::fs::read(support::guest("avoider")).unwrap();
    let robot = |body: &str| {
        format!("<robot name=\"bench\">\n  <platform name=\"control\">\n{body}\n  </platform>\n</robot>\n").into_bytes()
    };
    let publish =
        r#"<component name="source" source="builtin:publish" rate="10"><param name="value" value="1"/></component>"#;
    use StatusCode as S;
    vec![
        ("empty component", component("a"), vec![], S::BAD_REQUEST, "the upload is empty"),
        ("truncated component", component("a"), avoider[..avoider.len() / 2].to_vec(), S::UNPROCESSABLE_ENTITY, "fits neither world"),
        ("core module", component("a"), b"\0asm\x01\0\0\0".to_vec(), S::UNSUPPORTED_MEDIA_TYPE, "core webassembly module"),
        ("precompiled artifact", component("a"), b"\x7fELF\x02\x01\x01\0rest".to_vec(), S::UNSUPPORTED_MEDIA_TYPE, "precompiled native artifact"),
        ("garbage", component("a"), b"hello, robot".to_vec(), S::UNSUPPORTED_MEDIA_TYPE, "magic bytes"),
        ("component of no known world", component("a"), b"\0asm\x0d\0\x01\0".to_vec(), S::UNPROCESSABLE_ENTITY, "fits neither world"),
        ("oversize component", component("a"), vec![0u8; MAX_UPLOAD_BYTES + 1], S::PAYLOAD_TOO_LARGE, ""),
        ("name with a path", component("..%2Fevil"), avoider.clone(), S::BAD_REQUEST, "is not [a-z]"),
        ("name in capitals", component("Evil"), avoider.clone(), S::BAD_REQUEST, "is not [a-z]"),
        ("name in another user's uploads", component("admin%2Favoid"), avoider.clone(), S::BAD_REQUEST, "is not [a-z]"),
        ("unknown platform", "/api/v1/platforms/kitchen/components/a".into(), avoider, S::NOT_FOUND, "unknown platform 'kitchen'"),
        ("bad xml", config("r.xml"), b"<robot name=\"bench\"><platform name=\"control\">".to_vec(), S::UNPROCESSABLE_ENTITY, "r.xml:1:"),
        (
            "entity tricks",
            config("r.xml"),
            b"<!DOCTYPE robot [<!ENTITY x \"builtin:log\">]><robot name=\"bench\"><platform name=\"control\"><component name=\"a\" source=\"&x;\"/></platform></robot>".to_vec(),
            S::UNPROCESSABLE_ENTITY,
            "r.xml:1:",
        ),
        ("unknown component", config("r.xml"), robot(r#"<component name="a" source="nowhere.wasm"/>"#), S::UNPROCESSABLE_ENTITY, "unknown component 'nowhere.wasm'"),
        ("component outside the store", config("r.xml"), robot(r#"<component name="a" source="../../../etc/passwd.wasm"/>"#), S::UNPROCESSABLE_ENTITY, "unknown component"),
        ("another user's component that is not there", config("r.xml"), robot(r#"<component name="a" source="admin/nowhere.wasm"/>"#), S::UNPROCESSABLE_ENTITY, "unknown component 'admin/nowhere.wasm'"),
        ("an owner that is not a name", config("r.xml"), robot(r#"<component name="a" source="Admin/../nowhere.wasm"/>"#), S::UNPROCESSABLE_ENTITY, "unknown component"),
        ("world file outside the folder", config("r.xml"), robot(&format!("{publish}<component name=\"sim\" source=\"builtin:sim\"><param name=\"world\" value=\"../../etc/passwd\"/></component>")), S::UNPROCESSABLE_ENTITY, "must be a path inside the robot's folder"),
        ("file name with a path", config("..%2Fr.xml"), robot(publish), S::BAD_REQUEST, "is not a plain name"),
        ("file name hidden", config(".r.xml"), robot(publish), S::BAD_REQUEST, "is not a plain name"),
        ("not utf-8", config("r.xml"), b"<robot name=\"\xff\"/>".to_vec(), S::BAD_REQUEST, "is not utf-8"),
        ("oversize robot file", config("r.xml"), vec![b' '; subsume::deploy::MAX_CONFIG_UPLOAD_BYTES as usize + 1], S::PAYLOAD_TOO_LARGE, ""),
        (
            "a control developer changing the network platform",
            config("r.xml"),
            format!(
                "<robot name=\"bench\"><platform name=\"control\">{publish}<component name=\"sink\" source=\"builtin:log\" rate=\"0\"/><connect from=\"source.out\" to=\"sink.in\"/></platform><platform name=\"network\"><component name=\"n\" source=\"builtin:log\"/></platform></robot>"
            )
            .into_bytes(),
            S::FORBIDDEN,
            "changes platform network, which control-dev may not change",
        ),
    ]
}

#[tokio::test]
async fn malformed_uploads_are_refused_with_a_reason_and_change_nothing() {
    let portal = portal().await;
    let before = portal.snapshot();
    let cases = malformed_uploads();
    assert!(cases.len() >= 15);
    for (case, uri, body, expected, words) in cases {
        let (status, json) = portal.call("control-dev", "PUT", &uri, body).await;
        assert_eq!(status, expected, "{case}: {json}");
        if status != StatusCode::PAYLOAD_TOO_LARGE {
            let text = format!("{} {}", json["error"], json["diagnostics"]);
            assert!(text.contains(words), "{case}: '{words}' not in {text}");
        }
        assert_eq!(portal.snapshot(), before, "{case} changed the store");
    }
    // Every refusal is in the audit log, with who and why.
    let (_, audit) = portal.call("admin", "GET", "/api/v1/audit", "").await;
    let refused = audit["entries"].as_array().unwrap().iter().filter(|e| e["result"] == "refused").count();
    assert!(refused >= 12, "{audit}");
}

#[tokio::test]
async fn an_uploaded_component_shows_its_ports_and_a_robot_file_using_it_is_staged() {
    let portal = portal().await;
    let bytes = std::fs::read(support::guest("range_filter")).unwrap();
    let (status, json) = portal.call("control-dev", "PUT", "/api/v1/platforms/control/components/smooth", bytes).await;
    assert_eq!(status, StatusCode::CREATED, "{json}");
    assert_eq!(json["world"], "component");
    let (_, json) = portal.call("viewer", "GET", "/api/v1/components/control-dev/smooth", "").await;
    assert_eq!(json["description"]["inputs"][0]["name"], "ranges", "{json}");
    let robot = ROBOT.replace(
        r#"<connect from="source.out" to="sink.in"/>"#,
        r#"<component name="smooth" source="smooth.wasm" rate="0"/><connect from="source.out" to="sink.in"/>"#,
    );
    let (status, json) = portal.call("control-dev", "PUT", "/api/v1/platforms/control/configs/new.xml", robot).await;
    assert_eq!(status, StatusCode::CREATED, "{json}");
    assert_eq!(json["set"]["changes"], serde_json::json!(["control"]));
    assert_eq!(json["set"]["id"], 2);
    let (_, json) = portal.call("viewer", "GET", "/api/v1/sets/2", "").await;
    let names: Vec<&str> =
        json["graph"]["components"].as_array().unwrap().iter().map(|c| c["name"].as_str().unwrap()).collect();
    assert_eq!(names, ["source", "sink", "smooth"], "{json}");
    assert_eq!(json["status"], "staged");
    let (_, json) = portal.call("viewer", "GET", "/api/v1/sets", "").await;
    assert_eq!(json["active"], 1, "staging does not activate");
}

#[tokio::test]
async fn the_openapi_document_lists_exactly_the_routes() {
    let portal = portal().await;
    let (status, doc) = send(&portal.app, "GET", "/api/v1/openapi.json", None, Body::empty()).await;
    assert_eq!(status, StatusCode::OK);
    let mut documented = Vec::new();
    for (path, methods) in doc["paths"].as_object().unwrap() {
        for method in methods.as_object().unwrap().keys() {
            documented.push((method.to_uppercase(), path.clone()));
        }
    }
    // Every documented route exists (the fallback says "no such API route").
    for (method, path) in &documented {
        let uri = path
            .replace("{platform}", "control")
            .replace("{owner}", "admin")
            .replace("{name}", "x")
            .replace("{file}", "x.xml")
            .replace("{id}", "1");
        if path.ends_with("/events") {
            // An endless stream: only its start is checked.
            let request = Request::get(&uri).header("authorization", format!("Bearer {}", portal.tokens["admin"]));
            let response = portal.app.clone().oneshot(request.body(Body::empty()).unwrap()).await.unwrap();
            assert_eq!(response.status(), StatusCode::OK);
            assert_eq!(response.headers()["content-type"], "text/event-stream");
            continue;
        }
        let (status, json) = portal.call("admin", method, &uri, "").await;
        assert!(
            status != StatusCode::METHOD_NOT_ALLOWED
                && !json["error"].as_str().unwrap_or("").starts_with("no such API route"),
            "{method} {path} is documented but not routed: {status} {json}"
        );
    }
    // Every routed endpoint of the matrix is documented.
    for (method, uri, _, _) in endpoints() {
        let found = documented.iter().any(|(m, p)| {
            m == method && {
                let pattern: Vec<&str> = p.split('/').collect();
                let parts: Vec<&str> = uri.split('/').collect();
                pattern.len() == parts.len()
                    && pattern.iter().zip(&parts).all(|(a, b)| a == b || (a.starts_with('{') && a.ends_with('}')))
            }
        });
        assert!(found, "{method} {uri} is routed but not in openapi.json");
    }
    for path in ["/", "/app.js", "/style.css"] {
        let response = portal.app.clone().oneshot(Request::get(path).body(Body::empty()).unwrap()).await.unwrap();
        assert_eq!(response.status(), StatusCode::OK, "{path}");
    }
    assert!(support::repo_root().join("host/src/portal/openapi.json").is_file());
    // Every success answer says what it carries (a 204 carries nothing):
    // schemathesis checks each answer against it, so a renamed or missing
    // field of an answer fails the test command.
    let schemas = &doc["components"]["schemas"];
    for (path, methods) in doc["paths"].as_object().unwrap() {
        for (method, operation) in methods.as_object().unwrap() {
            for (code, answer) in operation["responses"].as_object().unwrap() {
                if !code.starts_with('2') || code == "204" {
                    continue;
                }
                let content = answer["content"].as_object();
                let schema = content.and_then(|c| c.values().next()).map(|c| &c["schema"]);
                let schema = match schema.and_then(|s| s["$ref"].as_str()) {
                    Some(name) => &schemas[name.trim_start_matches("#/components/schemas/")],
                    None => schema.unwrap_or(&Value::Null),
                };
                assert!(schema.is_object(), "{method} {path} {code} documents no schema: {answer}");
                if content.is_some_and(|c| c.contains_key("application/json")) && path != "/api/v1/openapi.json" {
                    assert!(
                        schema["required"].as_array().is_some_and(|r| !r.is_empty()),
                        "{method} {path} {code}: a JSON answer names the fields it always has: {schema}"
                    );
                }
            }
        }
    }
}

/// What the API fuzzer (schemathesis, tests/python/api_fuzz.py) found, one
/// case each: refusals axum made itself answered plain text, or statuses
/// the document did not list. Each is now JSON `{"error", "diagnostics"}`
/// saying why, with a status openapi.json lists for the operation.
#[tokio::test]
async fn what_the_api_fuzzer_found_is_refused_in_json_with_a_documented_status() {
    let portal = portal().await;
    let (_, doc) = send(&portal.app, "GET", "/api/v1/openapi.json", None, Body::empty()).await;
    #[rustfmt::skip]
    let cases: &[(&str, &str, &str, StatusCode, &str)] = &[
        ("GET", "/api/v1/teleop", "/api/v1/teleop", StatusCode::BAD_REQUEST, "this is the teleoperation WebSocket: connect with a WebSocket client"),
        ("GET", "/api/v1/sets/null,null", "/api/v1/sets/{id}", StatusCode::BAD_REQUEST, "set id 'null,null' is not a whole number"),
        ("POST", "/api/v1/sets/-1/activate", "/api/v1/sets/{id}/activate", StatusCode::BAD_REQUEST, "set id '-1' is not a whole number"),
        ("POST", "/api/v1/sets/x/replay", "/api/v1/sets/{id}/replay", StatusCode::BAD_REQUEST, "set id 'x' is not a whole number"),
        // Not UTF-8 once decoded: axum's own path rejection, now in JSON.
        ("GET", "/api/v1/components/%FF", "/api/v1/components/{name}", StatusCode::BAD_REQUEST, "invalid url"),
    ];
    for (method, uri, documented_as, status, error) in cases {
        let (got, json) = portal.call("admin", method, uri, "").await;
        assert_eq!(got, *status, "{method} {uri}: {json}");
        let message = json["error"].as_str().unwrap_or_default().to_lowercase();
        assert!(message.starts_with(&error.to_lowercase()), "{method} {uri}: {json}");
        assert!(json["diagnostics"].is_array(), "{method} {uri}: {json}");
        let listed = &doc["paths"][documented_as][method.to_lowercase()]["responses"][status.as_str()];
        assert!(listed["content"]["application/json"].is_object(), "{method} {documented_as} does not list {status}");
    }
}

/// No answer shows where the server keeps its files: the sets' folder and
/// the store's paths are named, not shown (the fuzzer's `no_server_path`
/// check found both in `GET /sets` and `GET /status`).
#[tokio::test]
async fn answers_name_the_servers_folders_instead_of_showing_them() {
    let portal = portal().await;
    let root = portal.store.root().parent().unwrap().display().to_string();
    for uri in ["/api/v1/sets", "/api/v1/sets/1", "/api/v1/components", "/api/v1/audit"] {
        let (status, json) = portal.call("admin", "GET", uri, "").await;
        assert_eq!(status, StatusCode::OK, "{uri}: {json}");
        let text = json.to_string();
        assert!(!text.contains(&root), "{uri} shows {root}: {text}");
        if uri == "/api/v1/sets" {
            assert_eq!(json["sets"][0]["base_dir"], "<robot file folder>", "{json}");
        }
        if uri == "/api/v1/sets/1" {
            // The robot file itself is its author's text, as stored: a
            // client stages it again (the deploy and lab clients do).
            assert_eq!(json["set"]["base_dir"], "<robot file folder>", "{json}");
            assert_eq!(json["config"], ROBOT, "{json}");
        }
    }
}

/// A recording from a fresh start re-activates the active set and waits
/// for the control loop to swap it in; when that never happens (here no
/// loop runs), it is undone: 500 naming why, no recording runs, no file is
/// left, the running set is the same, and the audit log has the failed
/// activation and recording start.
#[tokio::test]
async fn a_fresh_start_whose_swap_does_not_happen_leaves_no_recording() {
    let portal = portal().await;
    let (status, json) = portal.call("admin", "POST", "/api/v1/recordings/start", r#"{"fresh_start": true}"#).await;
    assert_eq!(status, StatusCode::INTERNAL_SERVER_ERROR, "{json}");
    assert!(json["error"].as_str().unwrap().contains("did not reach a cycle boundary"), "{json}");
    let (_, json) = portal.call("admin", "GET", "/api/v1/recordings", "").await;
    assert!(json["recording"].is_null(), "{json}");
    assert_eq!(json["files"], serde_json::json!([]), "{json}");
    let (_, json) = portal.call("admin", "GET", "/api/v1/sets", "").await;
    assert_eq!(json["active"], 1, "{json}");
    let (_, audit) = portal.call("admin", "GET", "/api/v1/audit", "").await;
    let results: Vec<(String, String)> = audit["entries"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|e| e["action"] == "activate" || e["action"] == "start-recording")
        .map(|e| (e["action"].as_str().unwrap().to_string(), e["result"].as_str().unwrap().to_string()))
        .collect();
    let failed = |action: &str| (action.to_string(), "failed".to_string());
    assert_eq!(results, [failed("activate"), failed("start-recording")], "{audit}");
    // Nothing was left half done: a plain start works.
    let (status, json) = portal.call("admin", "POST", "/api/v1/recordings/start", "").await;
    assert_eq!(status, StatusCode::CREATED, "{json}");
    assert_eq!(json["recording"]["fresh_start"], false, "{json}");
}

#[tokio::test]
async fn anyone_may_stop_the_robot_and_only_a_driver_may_release_it_and_both_are_audited() {
    let portal = portal().await;
    let (status, json) = portal.call("viewer", "POST", "/api/v1/estop", "").await;
    assert_eq!(status, StatusCode::OK, "{json}");
    assert_eq!(json["newly"], true);
    assert_eq!(json["engaged"][0]["by"], "viewer");
    assert_eq!(json["engaged"][0]["how"], "portal");
    let (_, json) = portal.call("control-dev", "POST", "/api/v1/estop", "").await;
    assert_eq!(json["newly"], false, "the first engagement stands: {json}");
    for user in ["viewer", "control-dev", "network-dev"] {
        let (status, json) = portal.call(user, "POST", "/api/v1/release", "").await;
        assert_eq!(status, StatusCode::FORBIDDEN, "{user}: {json}");
        assert!(json["error"].as_str().unwrap().contains("needs a role that may drive"), "{json}");
    }
    let (_, json) = portal.call("viewer", "GET", "/api/v1/locks", "").await;
    assert_eq!(json["engaged"].as_array().unwrap().len(), 1, "a refused release changes nothing: {json}");
    let (status, json) = portal.call("operator", "POST", "/api/v1/release", r#"{"lock": 7}"#).await;
    assert_eq!(status, StatusCode::BAD_REQUEST, "{json}");
    let (status, json) = portal.call("operator", "POST", "/api/v1/release", r#"{"lock": "bumper"}"#).await;
    assert_eq!(status, StatusCode::CONFLICT, "{json}");
    let (status, json) = portal.call("operator", "POST", "/api/v1/release", "").await;
    assert_eq!(status, StatusCode::OK, "{json}");
    assert_eq!(json["released"][0]["lock"], "estop");
    let (status, _) = portal.call("operator", "POST", "/api/v1/release", "").await;
    assert_eq!(status, StatusCode::CONFLICT, "nothing left to release");
    // The audit log: the engage and release (written off the request by
    // the audit thread) and the three refusals.
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(5);
    loop {
        let entries = portal.store.audit_entries(100).unwrap();
        let lines: Vec<(String, String, String)> = entries
            .iter()
            .filter(|e| e.action.ends_with("-lock"))
            .map(|e| (e.user.clone(), e.action.clone(), e.result.clone()))
            .collect();
        let expected = |u: &str, a: &str, r: &str| (u.to_string(), a.to_string(), r.to_string());
        let want = [
            expected("viewer", "engage-lock", "ok"),
            expected("viewer", "release-lock", "refused"),
            expected("control-dev", "release-lock", "refused"),
            expected("network-dev", "release-lock", "refused"),
            expected("operator", "release-lock", "ok"),
        ];
        if want.iter().all(|w| lines.contains(w)) {
            let release = entries.iter().find(|e| e.action == "release-lock" && e.result == "ok").unwrap();
            assert!(release.detail.contains("engaged (by viewer)"), "{release:?}");
            break;
        }
        assert!(std::time::Instant::now() < deadline, "audit lines missing: {lines:?}");
        tokio::time::sleep(std::time::Duration::from_millis(20)).await;
    }
}

/// The session cookie a login sets.
async fn login_cookie(app: &axum::Router) -> String {
    let body = serde_json::json!({ "name": "viewer", "password": password("viewer") }).to_string();
    let request = Request::post("/api/v1/login").body(Body::from(body)).unwrap();
    let response = app.clone().oneshot(request).await.unwrap();
    assert_eq!(response.status(), StatusCode::OK);
    response.headers()["set-cookie"].to_str().unwrap().to_string()
}

#[tokio::test]
async fn cookies_are_secure_when_the_portal_speaks_tls() {
    let plain = login_cookie(&portal_over(false).await.app).await;
    let tls = login_cookie(&portal_over(true).await.app).await;
    for cookie in [&plain, &tls] {
        assert!(cookie.contains("; HttpOnly; SameSite=Strict;"), "{cookie}");
    }
    assert!(!plain.contains("Secure"), "{plain}");
    assert!(tls.ends_with("; Secure"), "{tls}");
    // Logging out clears the cookie with the same attributes.
    let portal = portal_over(true).await;
    let request = Request::post("/api/v1/logout")
        .header("authorization", format!("Bearer {}", portal.tokens["viewer"]))
        .body(Body::empty())
        .unwrap();
    let response = portal.app.clone().oneshot(request).await.unwrap();
    let cleared = response.headers()["set-cookie"].to_str().unwrap();
    assert!(cleared.contains("Max-Age=0") && cleared.ends_with("; Secure"), "{cleared}");
}

#[tokio::test]
async fn metrics_are_for_loopback_peers_and_logged_in_users() {
    let portal = portal().await;
    let scrape = |peer: &str, token: Option<&str>| {
        let mut request = Request::get("/metrics");
        if let Some(token) = token {
            request = request.header("authorization", format!("Bearer {token}"));
        }
        let mut request = request.body(Body::empty()).unwrap();
        let peer: std::net::SocketAddr = peer.parse().unwrap();
        request.extensions_mut().insert(axum::extract::ConnectInfo(peer));
        let app = portal.app.clone();
        async move {
            let response = app.oneshot(request).await.unwrap();
            let status = response.status();
            let bytes = axum::body::to_bytes(response.into_body(), usize::MAX).await.unwrap();
            (status, serde_json::from_slice::<Value>(&bytes).unwrap_or(Value::Null))
        }
    };
    let (status, json) = scrape("192.0.2.7:40000", None).await;
    assert_eq!(status, StatusCode::UNAUTHORIZED, "{json}");
    assert!(json["error"].as_str().unwrap().starts_with("metrics are for loopback peers and logged-in users"));
    let (status, _) = scrape("192.0.2.7:40000", Some("not-a-session")).await;
    assert_eq!(status, StatusCode::UNAUTHORIZED);
    // Admitted: no control loop runs here, so no status was published.
    let not_yet = "the control loop has not published a status yet";
    for (peer, token) in [("192.0.2.7:40000", Some(portal.tokens["viewer"].as_str())), ("127.0.0.1:40000", None)] {
        let (status, json) = scrape(peer, token).await;
        assert_eq!((status, json["error"].as_str()), (StatusCode::SERVICE_UNAVAILABLE, Some(not_yet)), "{peer}");
    }
    let (status, _) = scrape("[::1]:40000", None).await;
    assert_eq!(status, StatusCode::SERVICE_UNAVAILABLE);
}

#[tokio::test]
async fn validating_answers_like_staging_with_the_same_diagnostics_and_stores_nothing() {
    let portal = portal().await;
    let before = portal.snapshot();
    let audit_lines = |json: &Value| json["entries"].as_array().unwrap().len();
    let (_, audit) = portal.call("admin", "GET", "/api/v1/audit", "").await;
    let audited = audit_lines(&audit);
    let mut compared = 0;
    for (case, uri, body, expected, _) in malformed_uploads() {
        if !uri.contains("/configs/") || expected == StatusCode::PAYLOAD_TOO_LARGE {
            continue;
        }
        let validate_uri = uri.replace("/configs/", "/validate/");
        let (status, validated) = portal.call("control-dev", "POST", &validate_uri, body.clone()).await;
        assert_eq!(portal.snapshot(), before, "{case}: validating changed the store");
        let (staged_status, staged) = portal.call("control-dev", "PUT", &uri, body).await;
        assert_eq!(status, staged_status, "{case}: {validated} vs {staged}");
        assert_eq!(validated["diagnostics"], staged["diagnostics"], "{case}");
        assert_eq!(validated["error"], staged["error"], "{case}");
        compared += 1;
    }
    assert!(compared >= 8, "{compared}");
    // The first problem of a bad file, located.
    let (status, json) = portal
        .call(
            "control-dev",
            "POST",
            "/api/v1/platforms/control/validate/r.xml",
            ROBOT.replace("sink.in", "sink.nowhere"),
        )
        .await;
    assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY, "{json}");
    let first = &json["diagnostics"][0];
    assert_eq!((first["file"].as_str(), first["line"].as_u64()), (Some("r.xml"), Some(5)), "{json}");
    assert!(first["column"].as_u64().unwrap() > 0 && first["message"].as_str().unwrap().contains("nowhere"), "{json}");
    // A good file: what it would stage, and still nothing stored.
    let robot = ROBOT.replace(r#"value="1""#, r#"value="2""#);
    let (status, json) = portal.call("control-dev", "POST", "/api/v1/platforms/control/validate/new.xml", robot).await;
    assert_eq!(status, StatusCode::OK, "{json}");
    assert_eq!((json["components"].as_u64(), json["connections"].as_u64()), (Some(2), Some(1)), "{json}");
    assert_eq!(json["changes"], serde_json::json!(["control"]), "{json}");
    assert_eq!(json["graph"]["components"][0]["name"], "source", "{json}");
    assert_eq!(portal.snapshot(), before);
    // Validation writes no audit line; each refused staging above wrote one.
    let (_, audit) = portal.call("admin", "GET", "/api/v1/audit", "").await;
    assert_eq!(audit_lines(&audit), audited + compared, "{audit}");
}

/// The lab's view carries the host's clock, so a page whose own clock is
/// off counts down to an experiment's end by the host's; each user sees
/// it, and the owner's settings only an admin.
#[tokio::test]
async fn the_lab_view_carries_the_hosts_clock_and_the_settings_for_admins_only() {
    let portal = portal().await;
    let now = || std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap().as_millis() as u64;
    for (user, _, _) in USERS {
        let before = now();
        let (status, json) = portal.call(user, "GET", "/api/v1/lab", "").await;
        let after = now();
        assert_eq!(status, StatusCode::OK, "{user}: {json}");
        let host = json["lab"]["now_unix_ms"].as_u64().unwrap_or_default();
        assert!((before..=after).contains(&host), "{user}: {before} <= {host} <= {after}: {json}");
        assert_eq!(json["lab"]["settings"].is_object(), *user == "admin", "{user}: {json}");
    }
}

/// The lab writes its state back whole (pause, a reservation, settings)
/// from its copy in memory; experiments submitted before and after each of
/// them keep distinct ids, and none replaces another's record.
#[tokio::test]
async fn experiments_submitted_around_lab_changes_never_share_an_id() {
    let portal = portal().await;
    let robot = ROBOT.replace(r#"value="1""#, r#"value="7""#);
    let (status, json) = portal.call("researcher", "PUT", "/api/v1/platforms/control/configs/mine.xml", robot).await;
    assert_eq!(status, StatusCode::CREATED, "{json}");
    let set = json["set"]["id"].as_u64().unwrap();
    let now = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap().as_millis() as u64;
    let booking = serde_json::json!({ "start_unix_ms": now + 3_600_000, "end_unix_ms": now + 3_900_000 }).to_string();
    let changes: [(&str, &str, &str, String); 3] = [
        ("admin", "POST", "/api/v1/lab/pause", String::new()),
        ("researcher", "POST", "/api/v1/lab/reservations", booking),
        ("admin", "POST", "/api/v1/lab/resume", String::new()),
    ];
    let mut ids = Vec::new();
    for (n, (user, method, uri, body)) in changes.into_iter().enumerate() {
        let submission = serde_json::json!({ "set": set, "duration_s": 2, "label": format!("try {n}") }).to_string();
        let (status, json) = portal.call("researcher", "POST", "/api/v1/experiments", submission).await;
        assert_eq!(status, StatusCode::CREATED, "{json}");
        ids.push(json["experiment"]["id"].as_u64().unwrap());
        let (status, json) = portal.call(user, method, uri, body).await;
        assert!(status.is_success(), "{uri}: {json}");
    }
    assert_eq!(ids, [1, 2, 3]);
    for (n, id) in ids.iter().enumerate() {
        let (status, json) = portal.call("researcher", "GET", &format!("/api/v1/experiments/{id}"), "").await;
        assert_eq!(status, StatusCode::OK, "{json}");
        assert_eq!(json["experiment"]["label"], format!("try {n}"), "{json}");
    }
    assert_eq!(portal.store.lab_state().unwrap().next_experiment, 4);
}

/// A WASM motion source above the envelope's default cap (the obstacle
/// avoider's priority, 3: the file sets no `max-priority`) is refused at
/// the component that claims it, with nothing stored; at the cap it stages.
#[tokio::test]
async fn a_motion_source_above_the_default_priority_cap_is_refused_where_it_is_declared() {
    let portal = portal().await;
    let avoider = std::fs::read(support::guest("avoider")).unwrap();
    for user in ["control-dev", "admin"] {
        let uri = "/api/v1/platforms/control/components/avoid";
        let (status, json) = portal.call(user, "PUT", uri, avoider.clone()).await;
        assert_eq!(status, StatusCode::CREATED, "{user}: {json}");
    }
    let robot = |priority: i32| {
        ROBOT.replace(
            "    <connect from=\"source.out\"",
            &format!(
                "    <component name=\"avoid\" source=\"avoid.wasm\" rate=\"10\" priority=\"{priority}\"/>\n    \
                 <component name=\"arbiter\" source=\"builtin:arbiter\" rate=\"20\"/>\n    \
                 <component name=\"envelope\" source=\"builtin:envelope\" rate=\"20\"/>\n    \
                 <connect from=\"avoid.cmd\" to=\"arbiter.commands\"/>\n    \
                 <connect from=\"arbiter.cmd\" to=\"envelope.cmd\"/>\n    \
                 <connect from=\"source.out\""
            ),
        )
    };
    let before = portal.snapshot();
    for user in ["control-dev", "admin"] {
        let (status, json) = portal.call(user, "PUT", "/api/v1/platforms/control/configs/r.xml", robot(50)).await;
        assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY, "{user}: {json}");
        assert_eq!(
            json["diagnostics"][0]["text"],
            "r.xml:5:5: component 'avoid' claims priority 50, but envelope 'envelope' allows WASM motion sources at most 3",
            "{user}: {json}"
        );
        assert_eq!(portal.snapshot(), before, "{user}: the refusal changed the store");
    }
    let (status, json) = portal.call("admin", "PUT", "/api/v1/platforms/control/configs/r.xml", robot(3)).await;
    assert_eq!(status, StatusCode::CREATED, "{json}");
}

/// Two users' uploads of one name are two records: each user's robot
/// files run their own by `NAME.wasm`, anyone's run another user's by
/// `OWNER/NAME.wasm`, and one user's upload never replaces the other's.
#[tokio::test]
async fn uploads_belong_to_their_uploader_and_another_users_are_used_by_owner_and_name() {
    let portal = portal().await;
    let filter = std::fs::read(support::guest("range_filter")).unwrap();
    let relay = std::fs::read(support::guest("test-relay")).unwrap();
    let uri = "/api/v1/platforms/control/components/smooth";
    let (status, ana) = portal.call("control-dev", "PUT", uri, filter.clone()).await;
    assert_eq!(status, StatusCode::CREATED, "{ana}");
    assert_eq!(
        (ana["uploaded_by"].as_str(), ana["source"].as_str()),
        (Some("control-dev"), Some("control-dev/smooth.wasm"))
    );
    let (status, admin) = portal.call("admin", "PUT", uri, relay.clone()).await;
    assert_eq!(status, StatusCode::CREATED, "{admin}");
    assert_ne!(ana["sha256"], admin["sha256"]);
    // Both records are there; each user's own is theirs, and anyone reads either.
    let (_, list) = portal.call("viewer", "GET", "/api/v1/components", "").await;
    let listed: Vec<(&str, &str)> = list["components"]
        .as_array()
        .unwrap()
        .iter()
        .map(|c| (c["source"].as_str().unwrap(), c["sha256"].as_str().unwrap()))
        .collect();
    let (ana_sha, admin_sha) = (ana["sha256"].as_str().unwrap(), admin["sha256"].as_str().unwrap());
    assert_eq!(listed, [("admin/smooth.wasm", admin_sha), ("control-dev/smooth.wasm", ana_sha)], "{list}");
    let (_, own) = portal.call("control-dev", "GET", "/api/v1/components/smooth", "").await;
    assert_eq!(own["sha256"], ana["sha256"], "{own}");
    let (_, own) = portal.call("admin", "GET", "/api/v1/components/smooth", "").await;
    assert_eq!(own["sha256"], admin["sha256"], "{own}");
    let (_, other) = portal.call("viewer", "GET", "/api/v1/components/control-dev/smooth", "").await;
    assert_eq!(other["sha256"], ana["sha256"], "{other}");
    let (status, _) = portal.call("viewer", "GET", "/api/v1/components/smooth", "").await;
    assert_eq!(status, StatusCode::NOT_FOUND, "the viewer uploaded nothing");

    // Staging: `smooth.wasm` is the stager's own, `OWNER/smooth.wasm` the owner's.
    let robot = |source: &str| {
        ROBOT.replace(
            r#"<connect from="source.out" to="sink.in"/>"#,
            &format!(
                r#"<component name="smooth" source="{source}" rate="0"/><connect from="source.out" to="sink.in"/>"#
            ),
        )
    };
    let staged = |json: &Value, source: &str| json["set"]["sources"][source].as_str().map(str::to_string);
    for (user, source, expected) in [
        ("control-dev", "smooth.wasm", ana_sha),
        ("admin", "smooth.wasm", admin_sha),
        ("control-dev", "admin/smooth.wasm", admin_sha),
        ("admin", "control-dev/smooth.wasm", ana_sha),
    ] {
        let (status, json) = portal.call(user, "PUT", "/api/v1/platforms/control/configs/r.xml", robot(source)).await;
        assert_eq!(status, StatusCode::CREATED, "{user} {source}: {json}");
        assert_eq!(staged(&json, source).as_deref(), Some(expected), "{user} {source}: {json}");
    }
    // A user with no upload of the name is told whose there are.
    let (status, json) =
        portal.call("network-dev", "POST", "/api/v1/platforms/network/validate/r.xml", robot("smooth.wasm")).await;
    assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY, "{json}");
    let message = json["diagnostics"][0]["message"].as_str().unwrap_or_default();
    assert!(
        message.ends_with(
            "unknown component 'smooth.wasm': network-dev has uploaded no 'smooth'; to run another user's, \
             name it as admin/smooth.wasm or control-dev/smooth.wasm"
        ),
        "{json}"
    );

    // Uploading again replaces only the uploader's own record.
    let (status, json) = portal.call("admin", "PUT", uri, filter).await;
    assert_eq!(status, StatusCode::CREATED, "{json}");
    let (_, other) = portal.call("admin", "GET", "/api/v1/components/control-dev/smooth", "").await;
    assert_eq!(other["sha256"], ana["sha256"], "{other}");
    let audit = portal.store.audit_entries(100).unwrap();
    // The audit log names whose record each upload wrote (targets are clipped).
    let uploads: Vec<&str> =
        audit.iter().filter(|e| e.action == "upload-component").map(|e| e.target.as_str()).collect();
    let expected = ["component 'control-dev/smooth'", "component 'admin/smooth'", "component 'admin/smooth'"];
    assert_eq!(uploads.len(), expected.len(), "{uploads:?}");
    for (target, start) in uploads.iter().zip(expected) {
        assert!(target.starts_with(start), "{uploads:?}");
    }
}
