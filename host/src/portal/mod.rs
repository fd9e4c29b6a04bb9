//! The web portal and its HTTP API under `/api/v1` (documented by
//! `openapi.json`, served at `/api/v1/openapi.json`): login, component and
//! robot-file uploads, sets, activation and rollback, the live status (SSE),
//! the audit log, the teleoperation WebSocket, and the static web files of
//! `web/`, embedded in the binary.
//!
//! Invariants:
//! - every route but login, the OpenAPI document and the static files needs
//!   a session (cookie `subsume_session`, or `Authorization: Bearer`), and
//!   every change checks the user's role and platform (`users`);
//! - uploads are bounded by named limits and checked before anything is
//!   stored (preamble, then the real linker against the WIT worlds);
//!   compilation runs on blocking threads, never the control loop;
//! - a refused request changes nothing and says why in JSON
//!   (`{"error": ..., "diagnostics": [...]}`).

pub mod logs;

use std::collections::{HashMap, VecDeque};
use std::net::SocketAddr;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use axum::Json;
use axum::body::Bytes;
use axum::extract::{DefaultBodyLimit, FromRequestParts, Path, State, WebSocketUpgrade};
use axum::http::request::Parts;
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post, put};
use serde::Deserialize;
use serde_json::{Value as Json_, json};

use self::logs::LogRing;
use crate::config::{ComponentSource, Diagnostics, Platform, limits};
use crate::contract::{clip, description_json, is_valid_name};
use crate::deploy::{DeployError, Runner};
use crate::loader::MAX_COMPONENT_BYTES;
use crate::store::{ComponentRecord, Outcome, StoreError, unix_now};
use crate::users::{Directory, User, parse_platform, random_hex};

/// Largest component upload: Python and JavaScript components are ~20 MB.
pub const MAX_UPLOAD_BYTES: usize = MAX_COMPONENT_BYTES as usize;
/// Largest robot-file upload.
pub const MAX_CONFIG_UPLOAD_BYTES: usize = limits::MAX_CONFIG_BYTES as usize;
/// Largest JSON request (login): nothing else sends JSON.
pub const MAX_JSON_BYTES: usize = 16 << 10;
/// How long a login lasts.
pub const SESSION_TTL: Duration = Duration::from_secs(12 * 3600);
/// Most live sessions: a client logging in in a loop cannot grow memory.
pub const MAX_SESSIONS: usize = 10_000;
/// Failed logins allowed per client address and per user name within
/// [`LOGIN_FAILURE_WINDOW`]; more are answered 429 (password guessing).
pub const MAX_LOGIN_FAILURES: usize = 5;
pub const LOGIN_FAILURE_WINDOW: Duration = Duration::from_secs(60);
/// Most addresses and names the login limiter tracks.
pub const MAX_LIMITER_KEYS: usize = 10_000;
/// Components compiled at once: compiling is CPU-bound and the machine has
/// few cores to share with the control loop.
pub const MAX_CONCURRENT_COMPILES: usize = 1;
/// Live status pushes per second at most (the control loop publishes at
/// 5 Hz).
pub const COOKIE: &str = "subsume_session";

const OPENAPI: &str = include_str!("openapi.json");
const INDEX_HTML: &str = include_str!("../../../web/index.html");
const APP_JS: &str = include_str!("../../../web/app.js");
const STYLE_CSS: &str = include_str!("../../../web/style.css");

/// Logged-in sessions: token -> (user name, expiry).
#[derive(Debug, Default)]
pub struct Sessions(Mutex<HashMap<String, (String, tokio::time::Instant)>>);

impl Sessions {
    fn open(&self, user: &str) -> Result<String, ApiError> {
        let token = random_hex(32).map_err(ApiError::internal)?;
        let mut sessions = self.0.lock().map_err(|_| ApiError::internal("the session table is unusable"))?;
        let now = tokio::time::Instant::now();
        sessions.retain(|_, (_, expires)| *expires > now);
        if sessions.len() >= MAX_SESSIONS {
            return Err(ApiError::new(StatusCode::SERVICE_UNAVAILABLE, "too many sessions; try again later"));
        }
        sessions.insert(token.clone(), (user.to_string(), now + SESSION_TTL));
        Ok(token)
    }

    fn user(&self, token: &str) -> Option<String> {
        let sessions = self.0.lock().ok()?;
        let (user, expires) = sessions.get(token)?;
        (*expires > tokio::time::Instant::now()).then(|| user.clone())
    }

    fn close(&self, token: &str) {
        if let Ok(mut sessions) = self.0.lock() {
            sessions.remove(token);
        }
    }
}

/// Failed logins per client address and per user name.
#[derive(Debug, Default)]
pub struct LoginLimiter(Mutex<HashMap<String, VecDeque<tokio::time::Instant>>>);

impl LoginLimiter {
    /// Seconds to wait if `keys` failed too often lately, else `None`.
    fn blocked(&self, keys: &[String]) -> Option<u64> {
        let mut failures = self.0.lock().ok()?;
        let now = tokio::time::Instant::now();
        keys.iter()
            .filter_map(|key| {
                let times = failures.get_mut(key)?;
                while times.front().is_some_and(|t| now.duration_since(*t) >= LOGIN_FAILURE_WINDOW) {
                    times.pop_front();
                }
                let oldest = *times.front()?;
                (times.len() >= MAX_LOGIN_FAILURES)
                    .then(|| (LOGIN_FAILURE_WINDOW - now.duration_since(oldest)).as_secs().max(1))
            })
            .max()
    }

    fn failed(&self, keys: &[String]) {
        let Ok(mut failures) = self.0.lock() else { return };
        let now = tokio::time::Instant::now();
        if failures.len() >= MAX_LIMITER_KEYS {
            failures.retain(|_, times| times.back().is_some_and(|t| now.duration_since(*t) < LOGIN_FAILURE_WINDOW));
        }
        for key in keys {
            if failures.len() < MAX_LIMITER_KEYS || failures.contains_key(key) {
                let times = failures.entry(key.clone()).or_default();
                times.push_back(now);
                if times.len() > MAX_LOGIN_FAILURES {
                    times.pop_front();
                }
            }
        }
    }
}

/// What the portal's handlers share.
pub struct PortalState {
    pub runner: Arc<Runner>,
    pub directory: Arc<Directory>,
    pub logs: Arc<LogRing>,
    sessions: Sessions,
    limiter: LoginLimiter,
    compiles: tokio::sync::Semaphore,
}

impl PortalState {
    pub fn new(runner: Arc<Runner>, directory: Arc<Directory>, logs: Arc<LogRing>) -> Arc<PortalState> {
        Arc::new(PortalState {
            runner,
            directory,
            logs,
            sessions: Sessions::default(),
            limiter: LoginLimiter::default(),
            compiles: tokio::sync::Semaphore::new(MAX_CONCURRENT_COMPILES),
        })
    }
}

/// A refused or failed request.
#[derive(Debug)]
pub struct ApiError {
    pub status: StatusCode,
    pub message: String,
    pub diagnostics: Option<Diagnostics>,
    pub retry_after: Option<u64>,
}

impl ApiError {
    pub fn new(status: StatusCode, message: impl Into<String>) -> ApiError {
        ApiError { status, message: message.into(), diagnostics: None, retry_after: None }
    }

    fn internal(message: impl Into<String>) -> ApiError {
        ApiError::new(StatusCode::INTERNAL_SERVER_ERROR, message)
    }

    fn unauthorized() -> ApiError {
        ApiError::new(StatusCode::UNAUTHORIZED, "log in first (POST /api/v1/login)")
    }

    fn forbidden(message: impl Into<String>) -> ApiError {
        ApiError::new(StatusCode::FORBIDDEN, message)
    }
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        let diagnostics: Vec<Json_> = self
            .diagnostics
            .iter()
            .flat_map(|d| d.0.iter())
            .map(|d| {
                json!({
                    "file": d.path.display().to_string(),
                    "line": d.line,
                    "column": d.column,
                    "message": d.message,
                    "text": d.to_string(),
                })
            })
            .collect();
        let mut response =
            (self.status, Json(json!({ "error": self.message, "diagnostics": diagnostics }))).into_response();
        if let Some(seconds) = self.retry_after
            && let Ok(value) = HeaderValue::from_str(&seconds.to_string())
        {
            response.headers_mut().insert(header::RETRY_AFTER, value);
        }
        response
    }
}

impl From<DeployError> for ApiError {
    fn from(e: DeployError) -> ApiError {
        match e {
            DeployError::Invalid(diagnostics) => ApiError {
                status: StatusCode::UNPROCESSABLE_ENTITY,
                message: format!("{} problem(s) in the robot file; nothing was changed", diagnostics.0.len()),
                diagnostics: Some(diagnostics),
                retry_after: None,
            },
            DeployError::Start(errors) => ApiError::new(
                StatusCode::UNPROCESSABLE_ENTITY,
                format!("the set did not start; the running set is unchanged: {}", errors.join("; ")),
            ),
            DeployError::Forbidden(m) => ApiError::forbidden(m),
            DeployError::Conflict(m) => ApiError::new(StatusCode::CONFLICT, m),
            DeployError::BadRequest(m) => ApiError::new(StatusCode::BAD_REQUEST, m),
            DeployError::Store(StoreError::NoSet(id)) => ApiError::new(StatusCode::NOT_FOUND, format!("no set {id}")),
            other => ApiError::internal(other.to_string()),
        }
    }
}

/// The logged-in user of a request.
pub struct Authed(pub User);

fn session_token(headers: &HeaderMap) -> Option<String> {
    if let Some(bearer) = headers.get(header::AUTHORIZATION).and_then(|v| v.to_str().ok())
        && let Some(token) = bearer.strip_prefix("Bearer ")
    {
        return Some(token.trim().to_string());
    }
    headers
        .get_all(header::COOKIE)
        .iter()
        .filter_map(|v| v.to_str().ok())
        .flat_map(|v| v.split(';'))
        .find_map(|pair| pair.trim().strip_prefix(&format!("{COOKIE}=")).map(str::to_string))
}

impl FromRequestParts<Arc<PortalState>> for Authed {
    type Rejection = ApiError;

    async fn from_request_parts(parts: &mut Parts, state: &Arc<PortalState>) -> Result<Authed, ApiError> {
        let token = session_token(&parts.headers).ok_or_else(ApiError::unauthorized)?;
        let name = state.sessions.user(&token).ok_or_else(ApiError::unauthorized)?;
        // Re-read: a user removed or changed with `subsume user` takes effect.
        let user = state.directory.users.get(&name).ok_or_else(ApiError::unauthorized)?;
        Ok(Authed(user))
    }
}

/// The client's address, when the server knows it (not in router tests).
pub struct ClientAddress(Option<SocketAddr>);

impl<S: Send + Sync> FromRequestParts<S> for ClientAddress {
    type Rejection = std::convert::Infallible;

    async fn from_request_parts(parts: &mut Parts, _state: &S) -> Result<ClientAddress, Self::Rejection> {
        Ok(ClientAddress(parts.extensions.get::<axum::extract::ConnectInfo<SocketAddr>>().map(|c| c.0)))
    }
}

/// The portal: API routes, the teleoperation WebSocket and the web files.
pub fn app(state: Arc<PortalState>) -> axum::Router {
    let api = axum::Router::new()
        .route("/login", post(login).layer(DefaultBodyLimit::max(MAX_JSON_BYTES)))
        .route("/logout", post(logout))
        .route("/session", get(session))
        .route("/components", get(list_components))
        .route("/components/{name}", get(get_component))
        .route(
            "/platforms/{platform}/components/{name}",
            put(upload_component).layer(DefaultBodyLimit::max(MAX_UPLOAD_BYTES)),
        )
        .route(
            "/platforms/{platform}/configs/{file}",
            put(upload_config).layer(DefaultBodyLimit::max(MAX_CONFIG_UPLOAD_BYTES)),
        )
        .route("/sets", get(list_sets))
        .route("/sets/{id}", get(get_set))
        .route("/sets/{id}/activate", post(activate))
        .route("/rollback", post(rollback))
        .route("/status", get(status))
        .route("/events", get(events))
        .route("/world", get(world))
        .route("/logs", get(recent_logs))
        .route("/audit", get(audit_log))
        .route("/teleop/ticket", post(teleop_ticket))
        .route("/teleop", get(teleop_socket))
        .route("/openapi.json", get(|| async { ([(header::CONTENT_TYPE, "application/json")], OPENAPI) }))
        .fallback(|| async { ApiError::new(StatusCode::NOT_FOUND, "no such API route (see /api/v1/openapi.json)") });
    axum::Router::new()
        .nest("/api/v1", api)
        .route("/", get(|| async { ([(header::CONTENT_TYPE, "text/html; charset=utf-8")], INDEX_HTML) }))
        .route("/app.js", get(|| async { ([(header::CONTENT_TYPE, "text/javascript; charset=utf-8")], APP_JS) }))
        .route("/style.css", get(|| async { ([(header::CONTENT_TYPE, "text/css; charset=utf-8")], STYLE_CSS) }))
        .with_state(state)
}

fn user_json(user: &User) -> Json_ {
    let platforms: Vec<&str> =
        [Platform::Control, Platform::Network].iter().filter(|p| user.may_change(**p)).map(|p| p.name()).collect();
    json!({
        "name": user.name,
        "role": user.role.name(),
        "platforms": platforms,
        "may_drive": user.may_drive(),
    })
}

#[derive(Deserialize)]
struct LoginRequest {
    name: String,
    password: String,
}

async fn login(
    State(state): State<Arc<PortalState>>,
    ClientAddress(address): ClientAddress,
    body: Bytes,
) -> Result<Response, ApiError> {
    let request: LoginRequest = serde_json::from_slice(&body).map_err(|e| {
        ApiError::new(StatusCode::BAD_REQUEST, format!("expected {{\"name\": ..., \"password\": ...}}: {e}"))
    })?;
    let mut keys = vec![format!("user:{}", clip(&request.name))];
    if let Some(address) = address {
        keys.push(format!("address:{}", address.ip()));
    }
    if let Some(seconds) = state.limiter.blocked(&keys) {
        let mut error =
            ApiError::new(StatusCode::TOO_MANY_REQUESTS, format!("too many failed logins; try again in {seconds} s"));
        error.retry_after = Some(seconds);
        return Err(error);
    }
    let directory = state.directory.clone();
    let (name, password) = (request.name.clone(), request.password);
    let user = tokio::task::spawn_blocking(move || directory.users.authenticate(&name, &password))
        .await
        .map_err(|e| ApiError::internal(e.to_string()))?;
    let Some(user) = user else {
        state.limiter.failed(&keys);
        tracing::warn!("failed portal login for '{}'", clip(&request.name));
        return Err(ApiError::new(StatusCode::UNAUTHORIZED, "wrong user name or password"));
    };
    let token = state.sessions.open(&user.name)?;
    tracing::info!("{} logged in to the portal", user.name);
    let cookie = format!("{COOKIE}={token}; Path=/; HttpOnly; SameSite=Strict; Max-Age={}", SESSION_TTL.as_secs());
    let mut response = Json(json!({ "token": token, "user": user_json(&user) })).into_response();
    if let Ok(value) = HeaderValue::from_str(&cookie) {
        response.headers_mut().insert(header::SET_COOKIE, value);
    }
    Ok(response)
}

async fn logout(State(state): State<Arc<PortalState>>, headers: HeaderMap, Authed(_): Authed) -> Response {
    if let Some(token) = session_token(&headers) {
        state.sessions.close(&token);
    }
    let cookie = format!("{COOKIE}=; Path=/; HttpOnly; SameSite=Strict; Max-Age=0");
    ([(header::SET_COOKIE, cookie)], StatusCode::NO_CONTENT).into_response()
}

async fn session(Authed(user): Authed) -> Json<Json_> {
    Json(user_json(&user))
}

fn platform_of(text: &str) -> Result<Platform, ApiError> {
    parse_platform(text).map_err(|e| ApiError::new(StatusCode::NOT_FOUND, e))
}

async fn blocking<T: Send + 'static>(
    work: impl FnOnce() -> Result<T, ApiError> + Send + 'static,
) -> Result<T, ApiError> {
    tokio::task::spawn_blocking(work).await.map_err(|e| ApiError::internal(format!("the worker failed: {e}")))?
}

async fn list_components(State(state): State<Arc<PortalState>>, Authed(_): Authed) -> Result<Json<Json_>, ApiError> {
    let store = state.runner.store.clone();
    let components = blocking(move || store.components().map_err(|e| ApiError::internal(e.to_string()))).await?;
    Ok(Json(json!({ "components": components.into_values().collect::<Vec<_>>() })))
}

async fn get_component(
    State(state): State<Arc<PortalState>>,
    Authed(_): Authed,
    Path(name): Path<String>,
) -> Result<Json<ComponentRecord>, ApiError> {
    let store = state.runner.store.clone();
    let components = blocking(move || store.components().map_err(|e| ApiError::internal(e.to_string()))).await?;
    components
        .get(&name)
        .cloned()
        .map(Json)
        .ok_or_else(|| ApiError::new(StatusCode::NOT_FOUND, format!("no component '{}' in the store", clip(&name))))
}

async fn upload_component(
    State(state): State<Arc<PortalState>>,
    Authed(user): Authed,
    Path((platform, name)): Path<(String, String)>,
    body: Bytes,
) -> Result<(StatusCode, Json<ComponentRecord>), ApiError> {
    let platform = platform_of(&platform)?;
    if !user.may_change(platform) {
        return Err(ApiError::forbidden(format!("{} may not upload to platform {}", user.name, platform.name())));
    }
    let target = format!("component '{}' for platform {}", clip(&name), platform.name());
    let result = check_and_store_component(&state, &user, platform, &name, body).await;
    let stored;
    let outcome = match &result {
        Ok(record) => {
            stored = format!("sha256 {}", record.sha256);
            Outcome::Ok(&stored)
        }
        Err(e) if e.status.is_client_error() => Outcome::Refused(&e.message),
        Err(e) => Outcome::Failed(&e.message),
    };
    state.runner.store.record(&user.name, "upload-component", &target, outcome);
    result.map(|record| (StatusCode::CREATED, Json(record)))
}

async fn check_and_store_component(
    state: &Arc<PortalState>,
    user: &User,
    platform: Platform,
    name: &str,
    body: Bytes,
) -> Result<ComponentRecord, ApiError> {
    if !is_valid_name(name) {
        return Err(ApiError::new(
            StatusCode::BAD_REQUEST,
            format!("component name '{}' is not [a-z][a-z0-9_-]* of at most 64 characters", clip(name)),
        ));
    }
    if body.is_empty() {
        return Err(ApiError::new(StatusCode::BAD_REQUEST, "the upload is empty: send the .wasm file as the body"));
    }
    crate::preamble::check_component_preamble(&body).map_err(|why| {
        ApiError::new(StatusCode::UNSUPPORTED_MEDIA_TYPE, format!("not a webassembly component: {why}"))
    })?;
    let _permit = state.compiles.acquire().await.map_err(|e| ApiError::internal(e.to_string()))?;
    let runner = state.runner.clone();
    let (name, uploaded_by) = (name.to_string(), user.name.clone());
    blocking(move || {
        let (world, description) = match runner.sandbox.load(&body) {
            Ok(artifact) => ("component", description_json(&artifact.description, &artifact.sha256)),
            Err(as_component) => match runner.sandbox.load_translator(&body) {
                Ok(_) => ("translator", json!({ "name": name, "world": "translator" })),
                Err(as_translator) => {
                    return Err(ApiError::new(
                        StatusCode::UNPROCESSABLE_ENTITY,
                        format!(
                            "'{name}' fits neither world subsume:robot/component ({as_component}) \
                             nor subsume:robot/translator ({as_translator})"
                        ),
                    ));
                }
            },
        };
        let stored = runner.store.put_blob(&body).map_err(|e| ApiError::internal(e.to_string()))?;
        let record = ComponentRecord {
            name,
            sha256: stored,
            size: body.len() as u64,
            world: world.into(),
            platform: platform.name().into(),
            uploaded_by,
            uploaded_at: unix_now(),
            description,
        };
        runner.store.put_component(record.clone()).map_err(|e| ApiError::internal(e.to_string()))?;
        tracing::info!("component '{}' uploaded by {} ({} bytes)", record.name, record.uploaded_by, record.size);
        Ok(record)
    })
    .await
}

async fn upload_config(
    State(state): State<Arc<PortalState>>,
    Authed(user): Authed,
    Path((platform, file)): Path<(String, String)>,
    body: Bytes,
) -> Result<(StatusCode, Json<Json_>), ApiError> {
    // The runner checks the permission (and audits a refusal).
    let platform = platform_of(&platform)?;
    let runner = state.runner.clone();
    let set = blocking(move || runner.stage(&user, platform, &file, &body).map_err(ApiError::from)).await?;
    Ok((StatusCode::CREATED, Json(json!({ "set": set }))))
}

fn set_status(id: u64, state: &crate::store::StoreState) -> &'static str {
    if state.active == Some(id) {
        "active"
    } else if state.history.last() == Some(&id) {
        "previous"
    } else if state.history.contains(&id) {
        "was active"
    } else {
        "staged"
    }
}

async fn list_sets(State(state): State<Arc<PortalState>>, Authed(_): Authed) -> Result<Json<Json_>, ApiError> {
    let store = state.runner.store.clone();
    blocking(move || {
        let internal = |e: StoreError| ApiError::internal(e.to_string());
        let st = store.state().map_err(internal)?;
        let sets: Vec<Json_> = store
            .sets()
            .map_err(internal)?
            .into_iter()
            .rev()
            .map(|s| {
                let status = set_status(s.id, &st);
                let mut value = serde_json::to_value(s).unwrap_or_default();
                if let Some(fields) = value.as_object_mut() {
                    // The wiring is for one set's page (GET /sets/{id}).
                    fields.remove("graph");
                }
                value["status"] = status.into();
                value
            })
            .collect();
        Ok(Json(json!({ "active": st.active, "previous": st.history.last(), "sets": sets })))
    })
    .await
}

async fn get_set(
    State(state): State<Arc<PortalState>>,
    Authed(_): Authed,
    Path(id): Path<u64>,
) -> Result<Json<Json_>, ApiError> {
    let runner = state.runner.clone();
    blocking(move || {
        let store = &runner.store;
        let set = store.set(id).map_err(|e| ApiError::from(DeployError::Store(e)))?;
        let text = store.blob(&set.config_sha256).map_err(|e| ApiError::internal(e.to_string()))?;
        let status = set_status(id, &store.state().map_err(|e| ApiError::internal(e.to_string()))?);
        Ok(Json(json!({
            "graph": set.graph,
            "set": set,
            "status": status,
            "config": String::from_utf8_lossy(&text),
        })))
    })
    .await
}

async fn activate(
    State(state): State<Arc<PortalState>>,
    Authed(user): Authed,
    Path(id): Path<u64>,
) -> Result<Json<Json_>, ApiError> {
    let runner = state.runner.clone();
    let set = blocking(move || runner.activate(&user, id).map_err(ApiError::from)).await?;
    Ok(Json(json!({ "active": set })))
}

async fn rollback(State(state): State<Arc<PortalState>>, Authed(user): Authed) -> Result<Json<Json_>, ApiError> {
    let runner = state.runner.clone();
    let set = blocking(move || runner.rollback(&user).map_err(ApiError::from)).await?;
    Ok(Json(json!({ "active": set })))
}

async fn status(State(state): State<Arc<PortalState>>, Authed(_): Authed) -> Json<Json_> {
    let mut live = state.runner.live();
    // Mark it seen, so the control loop starts (or keeps) publishing, and
    // wait briefly for a fresh status when none was published yet.
    let current = live.borrow_and_update().clone();
    if current.is_null() {
        let _ = tokio::time::timeout(Duration::from_secs(1), live.changed()).await;
        return Json((*live.borrow().clone()).clone());
    }
    Json((*current).clone())
}

/// Server-sent events: `status` (the live status, 5 per second) and `log`
/// (each new log line; the recent ones first).
async fn events(State(state): State<Arc<PortalState>>, Authed(_): Authed) -> Response {
    use axum::response::sse::{Event, KeepAlive, Sse};
    use futures_util::StreamExt as _;
    let live = state.runner.live();
    let logs = state.logs.subscribe();
    let backlog: Vec<Result<Event, std::convert::Infallible>> = state
        .logs
        .recent()
        .into_iter()
        .filter_map(|line| Event::default().event("log").json_data(line).ok())
        .map(Ok)
        .collect();
    let statuses = futures_util::stream::unfold(live, |mut live| async move {
        live.changed().await.ok()?;
        let value = live.borrow_and_update().clone();
        let event = Event::default().event("status").json_data(&*value).unwrap_or_default();
        Some((Ok(event), live))
    });
    let lines = futures_util::stream::unfold(logs, |mut logs| async move {
        loop {
            match logs.recv().await {
                Ok(line) => {
                    let event = Event::default().event("log").json_data(line).unwrap_or_default();
                    return Some((Ok(event), logs));
                }
                Err(tokio::sync::broadcast::error::RecvError::Lagged(_)) => continue,
                Err(tokio::sync::broadcast::error::RecvError::Closed) => return None,
            }
        }
    });
    let stream = futures_util::stream::iter(backlog).chain(futures_util::stream::select(statuses, lines));
    Sse::new(stream).keep_alive(KeepAlive::default()).into_response()
}

async fn world(State(state): State<Arc<PortalState>>, Authed(_): Authed) -> Result<Json<Json_>, ApiError> {
    let (set, config) = state.runner.active().map_err(ApiError::from)?;
    let sim = config
        .components
        .iter()
        .find(|c| c.source == ComponentSource::Builtin("sim".into()))
        .ok_or_else(|| ApiError::new(StatusCode::NOT_FOUND, "the active set has no simulated robot"))?;
    let param = |key: &str| sim.params.iter().find(|p| p.name == key).map(|p| p.value.trim().to_string());
    let world_file = param("world").unwrap_or_default();
    let path = set.base_dir.join(&world_file);
    let world = blocking(move || {
        crate::sim::world::load(&path).map_err(|e| ApiError::internal(format!("cannot read the world: {e}")))
    })
    .await?;
    let number = |key: &str| param(key).and_then(|v| v.parse::<f64>().ok());
    Ok(Json(json!({
        "component": sim.name,
        "world": world,
        "rays": number("rays"),
        "fov": number("fov"),
        "max_range": number("max-range"),
        "radius": number("radius"),
    })))
}

async fn recent_logs(State(state): State<Arc<PortalState>>, Authed(_): Authed) -> Json<Json_> {
    Json(json!({ "lines": state.logs.recent() }))
}

async fn audit_log(State(state): State<Arc<PortalState>>, Authed(user): Authed) -> Result<Json<Json_>, ApiError> {
    if !user.is_developer() {
        return Err(ApiError::forbidden(format!("{} may not read the audit log", user.name)));
    }
    let store = state.runner.store.clone();
    let entries = blocking(move || {
        store.audit_entries(crate::store::MAX_AUDIT_READ).map_err(|e| ApiError::internal(e.to_string()))
    })
    .await?;
    Ok(Json(json!({ "entries": entries })))
}

async fn teleop_ticket(State(state): State<Arc<PortalState>>, Authed(user): Authed) -> Result<Json<Json_>, ApiError> {
    if !user.may_drive() {
        return Err(ApiError::forbidden(format!("{} may not drive (role {})", user.name, user.role.name())));
    }
    if state.runner.services.teleop_servers.current().is_none() {
        return Err(ApiError::new(StatusCode::NOT_FOUND, "the active set has no network platform (builtin:teleop)"));
    }
    let ticket = state.directory.tickets.issue(&user.name).map_err(ApiError::internal)?;
    Ok(Json(json!({ "name": user.name, "ticket": ticket, "websocket": "/api/v1/teleop" })))
}

/// The network platform's WebSocket protocol; the session authenticates
/// inside it (`auth` with a ticket or a password), as on its own listener.
async fn teleop_socket(
    State(state): State<Arc<PortalState>>,
    ClientAddress(address): ClientAddress,
    ws: WebSocketUpgrade,
) -> Response {
    match state.runner.services.teleop_servers.current() {
        Some(ctx) => {
            crate::net::upgrade_websocket(ws, ctx, address.unwrap_or_else(|| SocketAddr::from(([0, 0, 0, 0], 0))))
        }
        None => ApiError::new(StatusCode::NOT_FOUND, "the active set has no network platform (builtin:teleop)")
            .into_response(),
    }
}
