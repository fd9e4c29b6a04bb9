//! Who is asking: logins (argon2id through the store's users, rate-limited
//! per address and per name), sessions (cookie `subsume_session` or
//! `Authorization: Bearer`), and the extractors handlers use.

use std::collections::{HashMap, VecDeque};
use std::net::SocketAddr;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use axum::Json;
use axum::body::Bytes;
use axum::extract::{FromRequestParts, State};
use axum::http::request::Parts;
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use serde::Deserialize;
use serde_json::{Value as Json_, json};

use super::PortalState;
use super::error::ApiError;
use crate::contract::clip;
use crate::deploy::Platform;
use crate::store::users::{User, random_hex};

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
/// The session cookie.
pub const COOKIE: &str = "subsume_session";

/// Logged-in sessions: token -> (user name, expiry).
#[derive(Debug, Default)]
pub struct Sessions(Mutex<HashMap<String, (String, tokio::time::Instant)>>);

impl Sessions {
    fn open(&self, user: &str) -> Result<String, ApiError> {
        let token = random_hex(32).map_err(|e| ApiError::internal(e.to_string()))?;
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

/// The user whose session `headers` carry, if it is open.
pub(super) fn user_of(headers: &HeaderMap, state: &PortalState) -> Option<User> {
    let token = session_token(headers)?;
    let name = state.sessions.user(&token)?;
    // Re-read: a user removed or changed with `subsume user` takes effect.
    state.directory.users.get(&name)
}

impl FromRequestParts<Arc<PortalState>> for Authed {
    type Rejection = ApiError;

    async fn from_request_parts(parts: &mut Parts, state: &Arc<PortalState>) -> Result<Authed, ApiError> {
        user_of(&parts.headers, state).map(Authed).ok_or_else(ApiError::unauthorized)
    }
}

/// The client's address, when the server knows it (not in router tests).
pub struct ClientAddress(pub Option<SocketAddr>);

impl<S: Send + Sync> FromRequestParts<S> for ClientAddress {
    type Rejection = std::convert::Infallible;

    async fn from_request_parts(parts: &mut Parts, _state: &S) -> Result<ClientAddress, Self::Rejection> {
        Ok(ClientAddress(parts.extensions.get::<axum::extract::ConnectInfo<SocketAddr>>().map(|c| c.0)))
    }
}

/// The logged-in user, as login and `GET /session` show them.
#[derive(serde::Serialize, schemars::JsonSchema)]
pub(super) struct SessionUser {
    /// Whether they may drive the robot (teleoperation, the simulator's
    /// controls, releasing a lock).
    may_drive: bool,
    name: String,
    /// The platforms they may change (`control`, `network`).
    platforms: Vec<&'static str>,
    role: crate::store::users::Role,
}

fn user_json(user: &User) -> Json_ {
    let platforms: Vec<&str> =
        [Platform::Control, Platform::Network].iter().filter(|p| user.may_change(**p)).map(|p| p.name()).collect();
    let view = SessionUser { may_drive: user.may_drive(), name: user.name.clone(), platforms, role: user.role };
    serde_json::to_value(view).unwrap_or_default()
}

/// The body of `POST /login`.
#[derive(Deserialize, schemars::JsonSchema)]
pub(super) struct LoginRequest {
    name: String,
    password: String,
}

pub(super) async fn login(
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
    let secure = if state.secure_cookies { "; Secure" } else { "" };
    let cookie =
        format!("{COOKIE}={token}; Path=/; HttpOnly; SameSite=Strict; Max-Age={}{secure}", SESSION_TTL.as_secs());
    let mut response = Json(json!({ "token": token, "user": user_json(&user) })).into_response();
    if let Ok(value) = HeaderValue::from_str(&cookie) {
        response.headers_mut().insert(header::SET_COOKIE, value);
    }
    Ok(response)
}

pub(super) async fn logout(State(state): State<Arc<PortalState>>, headers: HeaderMap, Authed(_): Authed) -> Response {
    if let Some(token) = session_token(&headers) {
        state.sessions.close(&token);
    }
    let secure = if state.secure_cookies { "; Secure" } else { "" };
    let cookie = format!("{COOKIE}=; Path=/; HttpOnly; SameSite=Strict; Max-Age=0{secure}");
    ([(header::SET_COOKIE, cookie)], StatusCode::NO_CONTENT).into_response()
}

pub(super) async fn session(Authed(user): Authed) -> Json<Json_> {
    Json(user_json(&user))
}
