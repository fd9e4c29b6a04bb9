//! The lab's handlers (docs/lab.md): experiments (submit, list, one,
//! cancel, results), the lab's view and live events, the owner's settings,
//! the baseline, pause and resume, the manual reset's confirmation,
//! reservations and the lab kit. Each hands a use case of `lab::Lab` to a
//! blocking thread, and the answer back as JSON (or a tar archive).

use std::sync::Arc;

use axum::Json;
use axum::body::Bytes;
use axum::extract::{Path, State};
use axum::http::{StatusCode, header};
use axum::response::{IntoResponse, Response};
use serde_json::{Value as Json_, json};

use super::PortalState;
use super::auth::Authed;
use super::error::ApiError;
use crate::lab::{LabError, Submission, bundle};
use crate::store::experiments::LabSettings;

impl From<LabError> for ApiError {
    fn from(e: LabError) -> ApiError {
        match e {
            LabError::Forbidden(m) => ApiError::forbidden(m),
            LabError::NotFound(m) => ApiError::new(StatusCode::NOT_FOUND, m),
            LabError::BadRequest(m) => ApiError::new(StatusCode::BAD_REQUEST, m),
            LabError::Conflict(m) => ApiError::new(StatusCode::CONFLICT, m),
            LabError::OverLimit { message, retry_after_s } => {
                ApiError { retry_after: retry_after_s, ..ApiError::new(StatusCode::TOO_MANY_REQUESTS, message) }
            }
            LabError::Invalid(diagnostics) => ApiError {
                status: StatusCode::UNPROCESSABLE_ENTITY,
                message: format!("{} problem(s) in the set's robot file; nothing was submitted", diagnostics.0.len()),
                diagnostics: Some(diagnostics),
                retry_after: None,
            },
            LabError::Store(e) => ApiError::from(e),
            LabError::Host(m) => ApiError::internal(m),
            e @ LabError::Illegal(_) => ApiError::internal(e.to_string()),
        }
    }
}

async fn blocking<T: Send + 'static>(
    work: impl FnOnce() -> Result<T, LabError> + Send + 'static,
) -> Result<T, ApiError> {
    tokio::task::spawn_blocking(work)
        .await
        .map_err(|e| ApiError::internal(format!("the worker failed: {e}")))?
        .map_err(ApiError::from)
}

fn body<T: serde::de::DeserializeOwned>(bytes: &Bytes, shape: &str) -> Result<T, ApiError> {
    serde_json::from_slice(bytes).map_err(|e| ApiError::new(StatusCode::BAD_REQUEST, format!("expected {shape}: {e}")))
}

pub(super) async fn list_experiments(
    State(state): State<Arc<PortalState>>,
    Authed(user): Authed,
) -> Result<Json<Json_>, ApiError> {
    let lab = state.lab.clone();
    let experiments = blocking(move || lab.list(&user)).await?;
    Ok(Json(json!({ "experiments": experiments })))
}

pub(super) async fn submit_experiment(
    State(state): State<Arc<PortalState>>,
    Authed(user): Authed,
    bytes: Bytes,
) -> Result<(StatusCode, Json<Json_>), ApiError> {
    let submission: Submission = body(&bytes, r#"{"set": ID, "duration_s": SECONDS, "label": TEXT}"#)?;
    let lab = state.lab.clone();
    let record = blocking(move || lab.submit(&user, &submission)).await?;
    Ok((StatusCode::CREATED, Json(json!({ "experiment": record }))))
}

pub(super) async fn get_experiment(
    State(state): State<Arc<PortalState>>,
    Authed(user): Authed,
    Path(id): Path<u64>,
) -> Result<Json<Json_>, ApiError> {
    let lab = state.lab.clone();
    let view = blocking(move || lab.get(&user, id)).await?;
    Ok(Json(json!({ "experiment": view })))
}

pub(super) async fn cancel_experiment(
    State(state): State<Arc<PortalState>>,
    Authed(user): Authed,
    Path(id): Path<u64>,
) -> Result<Json<Json_>, ApiError> {
    let lab = state.lab.clone();
    let record = blocking(move || lab.cancel(&user, id)).await?;
    Ok(Json(json!({ "experiment": record })))
}

/// Streams `contents` as a tar archive named `file`; `keep` lives until
/// the last byte is written (a temporary folder the files are in).
fn tar_response<K: Send + 'static>(state: &PortalState, contents: bundle::Contents, file: String, keep: K) -> Response {
    let (tx, rx) = tokio::sync::mpsc::channel::<Result<Bytes, std::io::Error>>(4);
    let store = state.deployer.store.clone();
    let hidden = state.hidden_paths.clone();
    tokio::task::spawn_blocking(move || {
        let _keep = keep;
        let mut out = ChannelWriter { tx: tx.clone(), buffer: Vec::with_capacity(CHUNK) };
        if let Err(e) = bundle::write_tar(&store, &contents, &hidden, &mut out) {
            tracing::warn!("the archive {} stopped: {e}", contents.folder);
            let _ = tx.blocking_send(Err(e));
        }
    });
    let stream = futures_util::stream::unfold(rx, |mut rx| async move { rx.recv().await.map(|item| (item, rx)) });
    (
        [
            (header::CONTENT_TYPE, "application/x-tar".to_string()),
            (header::CONTENT_DISPOSITION, format!("attachment; filename=\"{file}\"")),
        ],
        axum::body::Body::from_stream(stream),
    )
        .into_response()
}

/// Bytes sent to the client at a time.
const CHUNK: usize = 256 * 1024;

/// A `Write` that hands chunks to the response's body.
struct ChannelWriter {
    tx: tokio::sync::mpsc::Sender<Result<Bytes, std::io::Error>>,
    buffer: Vec<u8>,
}

impl std::io::Write for ChannelWriter {
    fn write(&mut self, bytes: &[u8]) -> std::io::Result<usize> {
        self.buffer.extend_from_slice(bytes);
        if self.buffer.len() >= CHUNK {
            self.flush()?;
        }
        Ok(bytes.len())
    }

    fn flush(&mut self) -> std::io::Result<()> {
        if self.buffer.is_empty() {
            return Ok(());
        }
        let chunk = Bytes::from(std::mem::replace(&mut self.buffer, Vec::with_capacity(CHUNK)));
        self.tx
            .blocking_send(Ok(chunk))
            .map_err(|_| std::io::Error::new(std::io::ErrorKind::BrokenPipe, "the client went away"))
    }
}

pub(super) async fn experiment_results(
    State(state): State<Arc<PortalState>>,
    Authed(user): Authed,
    Path(id): Path<u64>,
) -> Result<Response, ApiError> {
    let lab = state.lab.clone();
    let contents = blocking(move || lab.results(&user, id)).await?;
    Ok(tar_response(&state, contents, format!("experiment-{id}.tar"), ()))
}

pub(super) async fn kit(State(state): State<Arc<PortalState>>, Authed(user): Authed) -> Result<Response, ApiError> {
    let lab = state.lab.clone();
    let (dir, contents) = blocking(move || lab.kit(&user)).await?;
    Ok(tar_response(&state, contents, "lab-kit.tar".into(), dir))
}

pub(super) async fn overview(
    State(state): State<Arc<PortalState>>,
    Authed(user): Authed,
) -> Result<Json<Json_>, ApiError> {
    let lab = state.lab.clone();
    let view = blocking(move || lab.overview(&user)).await?;
    Ok(Json(json!({ "lab": view })))
}

/// The lab's live view for one user: an event `lab` with the lab and the
/// user's experiments at every change (and the first at once).
pub(super) async fn events(State(state): State<Arc<PortalState>>, Authed(user): Authed) -> Response {
    use axum::response::sse::{Event, KeepAlive, Sse};
    let changes = state.lab.subscribe();
    let lab = state.lab.clone();
    let stream = futures_util::stream::unfold((changes, true), move |(mut changes, first)| {
        let lab = lab.clone();
        let user = user.clone();
        async move {
            if !first {
                changes.changed().await.ok()?;
            }
            changes.borrow_and_update();
            let snapshot = tokio::task::spawn_blocking(move || {
                Ok::<_, LabError>(json!({ "lab": lab.overview(&user)?, "experiments": lab.list(&user)? }))
            })
            .await
            .ok()?
            .ok()?;
            let event = Event::default().event("lab").json_data(snapshot).unwrap_or_default();
            Some((Ok::<_, std::convert::Infallible>(event), (changes, false)))
        }
    });
    Sse::new(stream).keep_alive(KeepAlive::default()).into_response()
}

pub(super) async fn put_settings(
    State(state): State<Arc<PortalState>>,
    Authed(user): Authed,
    bytes: Bytes,
) -> Result<Json<Json_>, ApiError> {
    let settings: LabSettings = body(&bytes, "the lab's settings (GET /api/v1/lab as an admin shows them)")?;
    let lab = state.lab.clone();
    let settings = blocking(move || lab.set_settings(&user, settings)).await?;
    Ok(Json(json!({ "settings": settings })))
}

/// The body of `POST /lab/maintenance`.
#[derive(serde::Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
pub(super) struct MaintenanceRequest {
    /// Why the robot is out of service (shown to every user).
    reason: String,
}

/// Takes the robot out of service (admins), with a reason.
pub(super) async fn enter_maintenance(
    State(state): State<Arc<PortalState>>,
    Authed(user): Authed,
    bytes: Bytes,
) -> Result<Json<Json_>, ApiError> {
    let request: MaintenanceRequest = body(&bytes, r#"{"reason": "why the robot is out of service"}"#)?;
    let lab = state.lab.clone();
    let maintenance = blocking(move || lab.enter_maintenance(&user, &request.reason)).await?;
    Ok(Json(json!({ "maintenance": maintenance })))
}

/// A task's leaderboard (any user of the lab).
pub(super) async fn leaderboard(
    State(state): State<Arc<PortalState>>,
    Authed(user): Authed,
    Path(name): Path<String>,
) -> Result<Json<Json_>, ApiError> {
    let lab = state.lab.clone();
    let board = blocking(move || lab.leaderboard(&user, &name)).await?;
    Ok(Json(json!({ "leaderboard": board })))
}

/// Runs the owner's self-test now (admins): its result.
pub(super) async fn run_self_test(
    State(state): State<Arc<PortalState>>,
    Authed(user): Authed,
) -> Result<Json<Json_>, ApiError> {
    let lab = state.lab.clone();
    let test = blocking(move || lab.run_self_test(&user)).await?;
    Ok(Json(json!({ "self_test": test })))
}

/// Brings the robot back into service (admins).
pub(super) async fn end_maintenance(
    State(state): State<Arc<PortalState>>,
    Authed(user): Authed,
) -> Result<Json<Json_>, ApiError> {
    let lab = state.lab.clone();
    blocking(move || lab.end_maintenance(&user)).await?;
    Ok(Json(json!({ "maintenance": null })))
}

/// The caller's own mail subscription (`null` when she has none).
pub(super) async fn get_mail(
    State(state): State<Arc<PortalState>>,
    Authed(user): Authed,
) -> Result<Json<Json_>, ApiError> {
    let lab = state.lab.clone();
    let subscription = blocking(move || lab.mail_subscription(&user)).await?;
    Ok(Json(json!({ "mail": subscription })))
}

/// Sets the caller's own mail subscription.
pub(super) async fn put_mail(
    State(state): State<Arc<PortalState>>,
    Authed(user): Authed,
    bytes: Bytes,
) -> Result<Json<Json_>, ApiError> {
    let subscription: crate::lab::MailSubscription =
        body(&bytes, r#"{"address": "you@example.org", "events": ["experiment.ended", "experiment.refused"]}"#)?;
    let lab = state.lab.clone();
    let subscription = blocking(move || lab.set_mail_subscription(&user, Some(subscription))).await?;
    Ok(Json(json!({ "mail": subscription })))
}

/// Ends the caller's own mail subscription.
pub(super) async fn delete_mail(
    State(state): State<Arc<PortalState>>,
    Authed(user): Authed,
) -> Result<Json<Json_>, ApiError> {
    let lab = state.lab.clone();
    let subscription = blocking(move || lab.set_mail_subscription(&user, None)).await?;
    Ok(Json(json!({ "mail": subscription })))
}

/// The body of `PUT /lab/baseline`.
#[derive(serde::Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
pub(super) struct BaselineRequest {
    /// The stored set every experiment's set is checked against and the
    /// robot returns to after each.
    set: u64,
}

pub(super) async fn put_baseline(
    State(state): State<Arc<PortalState>>,
    Authed(user): Authed,
    bytes: Bytes,
) -> Result<Json<Json_>, ApiError> {
    let request: BaselineRequest = body(&bytes, r#"{"set": ID}"#)?;
    let lab = state.lab.clone();
    let baseline = blocking(move || lab.set_baseline(&user, request.set)).await?;
    Ok(Json(json!({ "baseline": baseline })))
}

pub(super) async fn pause(
    State(state): State<Arc<PortalState>>,
    Authed(user): Authed,
) -> Result<Json<Json_>, ApiError> {
    let lab = state.lab.clone();
    let paused = blocking(move || lab.set_paused(&user, true)).await?;
    Ok(Json(json!({ "paused": paused })))
}

pub(super) async fn resume(
    State(state): State<Arc<PortalState>>,
    Authed(user): Authed,
) -> Result<Json<Json_>, ApiError> {
    let lab = state.lab.clone();
    let paused = blocking(move || lab.set_paused(&user, false)).await?;
    Ok(Json(json!({ "paused": paused })))
}

pub(super) async fn confirm_reset(
    State(state): State<Arc<PortalState>>,
    Authed(user): Authed,
) -> Result<Json<Json_>, ApiError> {
    let lab = state.lab.clone();
    let id = blocking(move || lab.confirm_reset(&user)).await?;
    Ok(Json(json!({ "confirmed_for": id })))
}

/// The body of `POST /lab/reservations`.
#[derive(serde::Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
pub(super) struct BookingRequest {
    /// When it starts (ms since the Unix epoch); also spelled as the
    /// answer spells it (`start_ms`).
    #[serde(alias = "start_ms")]
    start_unix_ms: u64,
    /// When it ends (ms since the Unix epoch; `end_ms` too).
    #[serde(alias = "end_ms")]
    end_unix_ms: u64,
    /// Whom for (admins may book for anyone); the caller when missing.
    #[serde(default)]
    user: Option<String>,
}

pub(super) async fn book(
    State(state): State<Arc<PortalState>>,
    Authed(user): Authed,
    bytes: Bytes,
) -> Result<(StatusCode, Json<Json_>), ApiError> {
    let request: BookingRequest = body(&bytes, r#"{"start_unix_ms": MS, "end_unix_ms": MS, "user": NAME}"#)?;
    let lab = state.lab.clone();
    let reservation = blocking(move || {
        let for_user = request.user.unwrap_or_else(|| user.name.clone());
        lab.book(&user, &for_user, request.start_unix_ms, request.end_unix_ms)
    })
    .await?;
    Ok((StatusCode::CREATED, Json(json!({ "reservation": reservation }))))
}

pub(super) async fn unbook(
    State(state): State<Arc<PortalState>>,
    Authed(user): Authed,
    Path(id): Path<u64>,
) -> Result<Json<Json_>, ApiError> {
    let lab = state.lab.clone();
    blocking(move || lab.unbook(&user, id)).await?;
    Ok(Json(json!({ "cancelled": id })))
}

/// The lab server's robots (any logged-in user): name, profile, state,
/// the experiment each runs and its time left.
pub(super) async fn robots(
    State(state): State<Arc<PortalState>>,
    Authed(_user): Authed,
) -> Result<Json<Json_>, ApiError> {
    let lab = state.lab.clone();
    let robots = blocking(move || lab.robots()).await?;
    Ok(Json(json!({ "robots": robots })))
}

/// One robot's live status, asked of it now (any logged-in user).
pub(super) async fn robot_live(
    State(state): State<Arc<PortalState>>,
    Authed(user): Authed,
    Path(name): Path<String>,
) -> Result<Json<Json_>, ApiError> {
    let lab = state.lab.clone();
    let status = blocking(move || lab.robot_live(&user, &name)).await?;
    Ok(Json(json!({ "status": status })))
}

/// The lab's STOP for one robot (any logged-in user).
pub(super) async fn stop_robot(
    State(state): State<Arc<PortalState>>,
    Authed(user): Authed,
    Path(name): Path<String>,
) -> Result<Json<Json_>, ApiError> {
    let lab = state.lab.clone();
    let answers = blocking(move || lab.stop_robots(&user, Some(&name))).await?;
    Ok(Json(json!({ "stopped": answers })))
}

/// The lab's STOP for every robot (any logged-in user).
pub(super) async fn stop_all(
    State(state): State<Arc<PortalState>>,
    Authed(user): Authed,
) -> Result<Json<Json_>, ApiError> {
    let lab = state.lab.clone();
    let answers = blocking(move || lab.stop_robots(&user, None)).await?;
    Ok(Json(json!({ "stopped": answers })))
}
