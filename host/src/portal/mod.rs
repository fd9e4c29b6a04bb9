//! The web portal and its HTTP API under `/api/v1` (documented by the
//! OpenAPI document `openapi/` makes from the route table and the types,
//! served at `/api/v1/openapi.json`; `openapi.json` is its golden copy):
//! login, component and
//! robot-file uploads, sets, activation and rollback, the emergency stop
//! (engage, release, the locks), the live status (SSE),
//! the simulator's controls (reset, pose, pause, resume, step),
//! recordings (start, stop, list, download, delete),
//! the audit log, the teleoperation WebSocket, and the static web files of
//! `web/`, embedded in the binary.
//!
//! The portal only translates HTTP: use cases (and their permission
//! checks, audit lines and store lock) are `deploy`'s; reads go to the
//! store; the live status comes from `report` through `deploy`.
//!
//! Invariants:
//! - every route but login, the OpenAPI document and the static files needs
//!   a session (`auth`);
//! - request bodies are bounded by named limits before a use case sees them;
//! - a refused request changes nothing and says why in JSON (`error`);
//! - the session cookie is HttpOnly and SameSite=Strict (and Secure when
//!   the portal speaks TLS), and the pad authenticates with a one-time
//!   ticket;
//! - `/metrics` answers peers on a loopback address and logged-in users
//!   only;
//! - every answer of the API that refuses is JSON, and no answer shows a
//!   server folder (the store, the cache, the robot file's folder: each is
//!   replaced by a name on the way out, `api_answers`), but for the text
//!   of a stored robot file, answered as its author wrote it so it can be
//!   staged again.

pub mod auth;
pub mod client;
pub mod deploy_client;
pub mod error;
mod lab;
pub mod lab_client;
pub mod logs;
mod openapi;
mod routes;

use std::sync::Arc;

use axum::extract::DefaultBodyLimit;
use axum::http::{StatusCode, header};
use axum::routing::{get, post, put};

use self::auth::{LoginLimiter, Sessions};
pub use self::error::ApiError;
use self::logs::LogRing;
use crate::deploy::{Deployer, MAX_CONFIG_UPLOAD_BYTES, MAX_UPLOAD_BYTES, MAX_WORLD_UPLOAD_BYTES};
use crate::lab::Lab;
use crate::store::users::Directory;

/// Largest JSON request (login, release): nothing else sends JSON.
pub const MAX_JSON_BYTES: usize = 16 << 10;

const INDEX_HTML: &str = include_str!("../../../web/index.html");
const APP_JS: &str = include_str!("../../../web/app.js");
const STYLE_CSS: &str = include_str!("../../../web/style.css");
const LAB_HTML: &str = include_str!("../../../web/lab.html");
const LAB_JS: &str = include_str!("../../../web/lab.js");

/// Largest JSON answer the API rewrites to hide server paths (a set's view
/// with its robot file is at most about `MAX_CONFIG_UPLOAD_BYTES` twice).
const MAX_REWRITTEN_BYTES: usize = 64 << 20;

/// What the portal's handlers share.
pub struct PortalState {
    pub deployer: Arc<Deployer>,
    pub lab: Arc<Lab>,
    pub directory: Arc<Directory>,
    pub logs: Arc<LogRing>,
    sessions: Sessions,
    limiter: LoginLimiter,
    /// The portal speaks TLS: cookies carry `Secure`.
    secure_cookies: bool,
    /// Server folders no answer shows, each with what it shows instead
    /// (longest first): the store, the compile cache, the robot file's
    /// folder, the working directory.
    hidden_paths: crate::fsutil::HiddenPaths,
}

impl PortalState {
    pub fn new(
        deployer: Arc<Deployer>,
        lab: Arc<Lab>,
        directory: Arc<Directory>,
        logs: Arc<LogRing>,
    ) -> Arc<PortalState> {
        PortalState::with_cookies(deployer, lab, directory, logs, false)
    }

    /// The state of a portal served over TLS: its cookies carry `Secure`,
    /// so a browser never sends them over plain HTTP.
    pub fn over_tls(
        deployer: Arc<Deployer>,
        lab: Arc<Lab>,
        directory: Arc<Directory>,
        logs: Arc<LogRing>,
    ) -> Arc<PortalState> {
        PortalState::with_cookies(deployer, lab, directory, logs, true)
    }

    fn with_cookies(
        deployer: Arc<Deployer>,
        lab: Arc<Lab>,
        directory: Arc<Directory>,
        logs: Arc<LogRing>,
        secure_cookies: bool,
    ) -> Arc<PortalState> {
        Arc::new(PortalState {
            deployer,
            lab,
            directory,
            logs,
            sessions: Sessions::default(),
            limiter: LoginLimiter::default(),
            secure_cookies,
            hidden_paths: crate::fsutil::HiddenPaths::default(),
        })
    }

    /// The same state, hiding `hidden` in every answer of the API.
    pub fn hiding(mut self: Arc<Self>, hidden: crate::fsutil::HiddenPaths) -> Arc<PortalState> {
        if let Some(state) = Arc::get_mut(&mut self) {
            state.hidden_paths = hidden;
        }
        self
    }
}

/// Every answer of the API, on its way out: JSON whatever refused it (a
/// handler's `ApiError`, or one of axum's own rejections, which answer
/// plain text), and no server folder in it (`PortalState::hiding`).
async fn api_answers(
    axum::extract::State(state): axum::extract::State<Arc<PortalState>>,
    request: axum::extract::Request,
    next: axum::middleware::Next,
) -> axum::response::Response {
    use axum::response::IntoResponse as _;
    // A stored robot file (a set's `config`) is answered as stored: its
    // text is its author's, and a client edits it and stages it again byte
    // for byte (a path in it replaced by a name would no longer resolve).
    // The rest of the answer hides server folders as every answer does.
    let as_stored = request.method() == axum::http::Method::GET && names_a_set(request.uri().path());
    let response = next.run(request).await;
    let content_type = response.headers().get(header::CONTENT_TYPE).map(|v| v.as_bytes().to_vec());
    let json = content_type.as_deref().is_some_and(|t| t.starts_with(b"application/json"));
    let refused_in_text = !json && response.status().as_u16() >= 400;
    if !json && !refused_in_text {
        return response;
    }
    let (parts, body) = response.into_parts();
    let Ok(bytes) = axum::body::to_bytes(body, MAX_REWRITTEN_BYTES).await else {
        return ApiError::internal("an answer too large to send").into_response();
    };
    let mut text = String::from_utf8_lossy(&bytes).into_owned();
    let mut robot_file = None;
    if as_stored && json && parts.status.is_success() {
        let mut answer: serde_json::Value = serde_json::from_str(&text).unwrap_or_default();
        robot_file = answer.get_mut("config").map(serde_json::Value::take);
        text = answer.to_string();
    }
    state.hidden_paths.hide(&mut text);
    if let Some(robot_file) = robot_file {
        let mut answer: serde_json::Value = serde_json::from_str(&text).unwrap_or_default();
        answer["config"] = robot_file;
        text = answer.to_string();
    }
    if refused_in_text {
        let why = if text.trim().is_empty() {
            parts.status.canonical_reason().unwrap_or("refused").to_lowercase()
        } else {
            text.trim().to_string()
        };
        let mut refusal = ApiError::new(parts.status, why).into_response();
        for name in [header::ALLOW, header::RETRY_AFTER] {
            if let Some(value) = parts.headers.get(&name) {
                refusal.headers_mut().insert(name, value.clone());
            }
        }
        return refusal;
    }
    let mut parts = parts;
    parts.headers.remove(header::CONTENT_LENGTH);
    axum::response::Response::from_parts(parts, axum::body::Body::from(text))
}

/// Whether `path` is one set's (`.../sets/ID`), whose answer holds a robot
/// file as stored.
fn names_a_set(path: &str) -> bool {
    let mut segments = path.trim_end_matches('/').rsplit('/');
    let id = segments.next().unwrap_or_default();
    segments.next() == Some("sets") && !id.is_empty() && id.bytes().all(|b| b.is_ascii_digit())
}

/// The routes a robot's portal and a lab server's share: login, uploads,
/// staging, the sets, the log, the experiments, the lab and its robots (on
/// a robot, `/robots` answers that it is no lab server), the document.
fn shared_api() -> axum::Router<Arc<PortalState>> {
    use routes::*;
    axum::Router::new()
        .route("/login", post(auth::login).layer(DefaultBodyLimit::max(MAX_JSON_BYTES)))
        .route("/logout", post(auth::logout))
        .route("/session", get(auth::session))
        .route("/components", get(list_components))
        .route("/components/{name}", get(get_own_component))
        .route("/components/{owner}/{name}", get(get_component))
        .route(
            "/components/{owner}/{name}/visibility",
            put(put_component_visibility).layer(DefaultBodyLimit::max(MAX_JSON_BYTES)),
        )
        .route(
            "/platforms/{platform}/components/{name}",
            put(upload_component).layer(DefaultBodyLimit::max(MAX_UPLOAD_BYTES)),
        )
        .route(
            "/platforms/{platform}/configs/{file}",
            put(upload_config).layer(DefaultBodyLimit::max(MAX_CONFIG_UPLOAD_BYTES as usize)),
        )
        .route(
            "/platforms/{platform}/validate/{file}",
            post(validate_config).layer(DefaultBodyLimit::max(MAX_CONFIG_UPLOAD_BYTES as usize)),
        )
        .route("/worlds", get(list_worlds))
        .route("/worlds/{file}", put(upload_world).layer(DefaultBodyLimit::max(MAX_WORLD_UPLOAD_BYTES as usize)))
        .route("/sets", get(list_sets))
        .route("/sets/{id}", get(get_set).delete(forget_set))
        .route("/logs", get(recent_logs))
        .route("/audit", get(audit_log))
        .route(
            "/experiments",
            get(lab::list_experiments).post(lab::submit_experiment).layer(DefaultBodyLimit::max(MAX_JSON_BYTES)),
        )
        .route("/experiments/{id}", get(lab::get_experiment))
        .route("/experiments/{id}/cancel", post(lab::cancel_experiment))
        .route("/experiments/{id}/results", get(lab::experiment_results))
        .route("/lab", get(lab::overview))
        .route("/lab/events", get(lab::events))
        .route("/lab/settings", put(lab::put_settings).layer(DefaultBodyLimit::max(MAX_JSON_BYTES)))
        .route("/lab/baseline", put(lab::put_baseline).layer(DefaultBodyLimit::max(MAX_JSON_BYTES)))
        .route("/lab/pause", post(lab::pause))
        .route("/lab/resume", post(lab::resume))
        .route("/lab/kit", get(lab::kit))
        .route("/tasks/{name}/leaderboard", get(lab::leaderboard))
        .route(
            "/lab/maintenance",
            post(lab::enter_maintenance).delete(lab::end_maintenance).layer(DefaultBodyLimit::max(MAX_JSON_BYTES)),
        )
        .route(
            "/lab/mail",
            get(lab::get_mail).put(lab::put_mail).delete(lab::delete_mail).layer(DefaultBodyLimit::max(MAX_JSON_BYTES)),
        )
        .route("/robots", get(lab::robots))
        .route("/robots/stop", post(lab::stop_all))
        .route("/robots/{name}/live", get(lab::robot_live))
        .route("/robots/{name}/stop", post(lab::stop_robot))
        .route("/openapi.json", get(|| async { ([(header::CONTENT_TYPE, "application/json")], openapi::served()) }))
}

/// The lab server's portal (`subsume lab serve`, docs/lab.md "Several
/// robots"): the shared routes, its own page; no route that drives,
/// activates or tests a robot, since it runs none.
pub fn lab_server_app(state: Arc<PortalState>) -> axum::Router {
    let api = shared_api()
        .fallback(|uri: axum::http::Uri| async move { not_on_a_lab_server(uri.path()) })
        .layer(axum::middleware::from_fn_with_state(state.clone(), api_answers));
    axum::Router::new()
        .nest("/api/v1", api)
        .route("/", get(|| async { ([(header::CONTENT_TYPE, "text/html; charset=utf-8")], LAB_HTML) }))
        .route("/lab.js", get(|| async { ([(header::CONTENT_TYPE, "text/javascript; charset=utf-8")], LAB_JS) }))
        .route("/metrics", get(routes::metrics))
        .route("/style.css", get(|| async { ([(header::CONTENT_TYPE, "text/css; charset=utf-8")], STYLE_CSS) }))
        .with_state(state)
}

/// The answer of a lab server to an API route it does not serve: for a
/// robot's route that `subsume lab` has a command for, why a lab server
/// does not do it (docs/lab.md, "Several robots"); else that there is no
/// such route. `path` is the route's, under `/api/v1`.
fn not_on_a_lab_server(path: &str) -> ApiError {
    let path = path.strip_prefix("/api/v1").unwrap_or(path);
    let why = if path.starts_with("/lab/reservations") {
        "a lab server takes no reservations (not built yet: docs/lab.md, \"Several robots\"): \
         its queue gives each experiment to the first free robot that fits"
    } else {
        "no such API route on a lab server (see /api/v1/openapi.json)"
    };
    ApiError::new(StatusCode::NOT_FOUND, why)
}

/// The portal: API routes, the teleoperation WebSocket and the web files.
pub fn app(state: Arc<PortalState>) -> axum::Router {
    use routes::*;
    let api = shared_api()
        .route("/sets/{id}/activate", post(activate))
        .route("/sets/{id}/replay", post(replay_set).layer(DefaultBodyLimit::max(MAX_JSON_BYTES)))
        .route("/rollback", post(rollback))
        .route("/status", get(status))
        .route("/history", get(history))
        .route("/events", get(events))
        .route("/world", get(world))
        .route("/cameras", get(cameras))
        .route("/cameras/{name}/live", get(camera_live))
        .route("/sim/{action}", post(sim_control))
        .route("/estop", post(estop))
        .route("/release", post(release).layer(DefaultBodyLimit::max(MAX_JSON_BYTES)))
        .route("/locks", get(locks))
        .route("/recordings", get(list_recordings))
        .route("/recordings/start", post(start_recording).layer(DefaultBodyLimit::max(MAX_JSON_BYTES)))
        .route("/recordings/stop", post(stop_recording))
        .route("/recordings/{name}", get(download_recording).delete(delete_recording))
        .route("/lab/reset", post(lab::confirm_reset))
        // A robot's check of itself: a lab server has no robot to test
        // (its self-test would fail for want of a live status and take the
        // whole lab out of service); each robot tests itself.
        .route("/lab/selftest", post(lab::run_self_test))
        .route("/lab/reservations", post(lab::book).layer(DefaultBodyLimit::max(MAX_JSON_BYTES)))
        .route("/lab/reservations/{id}", axum::routing::delete(lab::unbook))
        .route("/teleop/ticket", post(teleop_ticket))
        .route("/teleop", get(teleop_socket))
        .fallback(|| async { ApiError::new(StatusCode::NOT_FOUND, "no such API route (see /api/v1/openapi.json)") })
        .layer(axum::middleware::from_fn_with_state(state.clone(), api_answers));
    axum::Router::new()
        .nest("/api/v1", api)
        .route("/", get(|| async { ([(header::CONTENT_TYPE, "text/html; charset=utf-8")], INDEX_HTML) }))
        .route("/app.js", get(|| async { ([(header::CONTENT_TYPE, "text/javascript; charset=utf-8")], APP_JS) }))
        .route("/metrics", get(metrics))
        .route("/style.css", get(|| async { ([(header::CONTENT_TYPE, "text/css; charset=utf-8")], STYLE_CSS) }))
        .with_state(state)
}

#[cfg(test)]
mod tests {
    use super::names_a_set;

    #[test]
    fn only_one_sets_answer_is_a_robot_file_as_stored() {
        let cases = [
            ("/sets/12", true),
            ("/api/v1/sets/3", true),
            ("/api/v1/sets/3/", true),
            ("/api/v1/sets", false),
            ("/api/v1/sets/3/activate", false),
            ("/api/v1/sets/x", false),
            ("/api/v1/experiments/3", false),
        ];
        for (path, expected) in cases {
            assert_eq!(names_a_set(path), expected, "{path}");
        }
    }
}
