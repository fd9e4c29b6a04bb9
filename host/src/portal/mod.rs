//! The web portal and its HTTP API under `/api/v1` (documented by
//! `openapi.json`, served at `/api/v1/openapi.json`): login, component and
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
//!   only.

pub mod auth;
pub mod client;
pub mod deploy_client;
pub mod error;
mod lab;
pub mod lab_client;
pub mod logs;
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

const OPENAPI: &str = include_str!("openapi.json");
const INDEX_HTML: &str = include_str!("../../../web/index.html");
const APP_JS: &str = include_str!("../../../web/app.js");
const STYLE_CSS: &str = include_str!("../../../web/style.css");

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
}

impl PortalState {
    pub fn new(
        deployer: Arc<Deployer>,
        lab: Arc<Lab>,
        directory: Arc<Directory>,
        logs: Arc<LogRing>,
    ) -> Arc<PortalState> {
        Arc::new(PortalState {
            deployer,
            lab,
            directory,
            logs,
            sessions: Sessions::default(),
            limiter: LoginLimiter::default(),
            secure_cookies: false,
        })
    }

    /// The state of a portal served over TLS: its cookies carry `Secure`,
    /// so a browser never sends them over plain HTTP.
    pub fn over_tls(
        deployer: Arc<Deployer>,
        lab: Arc<Lab>,
        directory: Arc<Directory>,
        logs: Arc<LogRing>,
    ) -> Arc<PortalState> {
        Arc::new(PortalState {
            deployer,
            lab,
            directory,
            logs,
            sessions: Sessions::default(),
            limiter: LoginLimiter::default(),
            secure_cookies: true,
        })
    }
}

/// The portal: API routes, the teleoperation WebSocket and the web files.
pub fn app(state: Arc<PortalState>) -> axum::Router {
    use routes::*;
    let api = axum::Router::new()
        .route("/login", post(auth::login).layer(DefaultBodyLimit::max(MAX_JSON_BYTES)))
        .route("/logout", post(auth::logout))
        .route("/session", get(auth::session))
        .route("/components", get(list_components))
        .route("/components/{name}", get(get_component))
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
        .route("/sets/{id}", get(get_set))
        .route("/sets/{id}/activate", post(activate))
        .route("/sets/{id}/replay", post(replay_set).layer(DefaultBodyLimit::max(MAX_JSON_BYTES)))
        .route("/rollback", post(rollback))
        .route("/status", get(status))
        .route("/history", get(history))
        .route("/events", get(events))
        .route("/world", get(world))
        .route("/sim/{action}", post(sim_control))
        .route("/logs", get(recent_logs))
        .route("/audit", get(audit_log))
        .route("/estop", post(estop))
        .route("/release", post(release).layer(DefaultBodyLimit::max(MAX_JSON_BYTES)))
        .route("/locks", get(locks))
        .route("/recordings", get(list_recordings))
        .route("/recordings/start", post(start_recording).layer(DefaultBodyLimit::max(MAX_JSON_BYTES)))
        .route("/recordings/stop", post(stop_recording))
        .route("/recordings/{name}", get(download_recording).delete(delete_recording))
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
        .route("/lab/reset", post(lab::confirm_reset))
        .route("/lab/reservations", post(lab::book).layer(DefaultBodyLimit::max(MAX_JSON_BYTES)))
        .route("/lab/reservations/{id}", axum::routing::delete(lab::unbook))
        .route("/lab/kit", get(lab::kit))
        .route("/teleop/ticket", post(teleop_ticket))
        .route("/teleop", get(teleop_socket))
        .route("/openapi.json", get(|| async { ([(header::CONTENT_TYPE, "application/json")], OPENAPI) }))
        .fallback(|| async { ApiError::new(StatusCode::NOT_FOUND, "no such API route (see /api/v1/openapi.json)") });
    axum::Router::new()
        .nest("/api/v1", api)
        .route("/", get(|| async { ([(header::CONTENT_TYPE, "text/html; charset=utf-8")], INDEX_HTML) }))
        .route("/app.js", get(|| async { ([(header::CONTENT_TYPE, "text/javascript; charset=utf-8")], APP_JS) }))
        .route("/metrics", get(metrics))
        .route("/style.css", get(|| async { ([(header::CONTENT_TYPE, "text/css; charset=utf-8")], STYLE_CSS) }))
        .with_state(state)
}
