//! The API's handlers. Each one translates HTTP into a use case of
//! `deploy` (which authorises, audits and locks) or a read-only query of
//! the store, on a blocking thread, and the result back into HTTP.

use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use axum::Json;
use axum::body::Bytes;
use axum::extract::{Path, State, WebSocketUpgrade};
use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};
use serde_json::{Value as Json_, json};

use super::PortalState;
use super::auth::{Authed, ClientAddress};
use super::error::ApiError;
use crate::contract::clip;
use crate::deploy::{Permission, Platform, SimAction, authorise};
use crate::report::LiveStatus;
use crate::store::users::User;
use crate::store::{ComponentRecord, MAX_AUDIT_READ, StoreState};
use crate::teleop::TeleopServers;

fn platform_of(text: &str) -> Result<Platform, ApiError> {
    Platform::parse(text).map_err(|e| ApiError::new(StatusCode::NOT_FOUND, e.to_string()))
}

async fn blocking<T: Send + 'static>(
    work: impl FnOnce() -> Result<T, ApiError> + Send + 'static,
) -> Result<T, ApiError> {
    tokio::task::spawn_blocking(work).await.map_err(|e| ApiError::internal(format!("the worker failed: {e}")))?
}

/// A stored component as the API shows it: its record, and the `source`
/// a robot file names it by from any user's file.
#[derive(serde::Serialize, schemars::JsonSchema)]
pub(super) struct ComponentView {
    #[serde(flatten)]
    record: ComponentRecord,
    /// How a robot file names it from anywhere: `OWNER/NAME.wasm` (its
    /// owner may also write `NAME.wasm`).
    source: String,
}

/// A stored component as the API shows it (`ComponentView`), as JSON.
fn component_json(record: ComponentRecord) -> Json_ {
    let source = record.source();
    serde_json::to_value(ComponentView { record, source }).unwrap_or_default()
}

/// Every stored component of every user, by owner then name.
pub(super) async fn list_components(
    State(state): State<Arc<PortalState>>,
    Authed(user): Authed,
) -> Result<Json<Json_>, ApiError> {
    let (store, lab) = (state.deployer.store.clone(), state.lab.clone());
    let components = blocking(move || {
        let (access, _) = lab.access()?;
        Ok(store.components()?.into_values().filter(|c| access.may_see_component(&user, c)).collect::<Vec<_>>())
    })
    .await?;
    Ok(Json(json!({ "components": components.into_iter().map(component_json).collect::<Vec<_>>() })))
}

async fn one_component(state: &PortalState, user: User, owner: String, name: String) -> Result<Json<Json_>, ApiError> {
    let (store, lab) = (state.deployer.store.clone(), state.lab.clone());
    let key = crate::store::component_key(&clip(&owner), &clip(&name));
    let found = blocking(move || {
        let (access, _) = lab.access()?;
        Ok(store.component(&owner, &name)?.filter(|c| access.may_see_component(&user, c)))
    })
    .await?;
    // Someone else's private upload answers as a missing one.
    found
        .map(|record| Json(component_json(record)))
        .ok_or_else(|| ApiError::new(StatusCode::NOT_FOUND, format!("no component '{key}' in the store")))
}

/// The caller's own upload `name`.
pub(super) async fn get_own_component(
    State(state): State<Arc<PortalState>>,
    Authed(user): Authed,
    Path(name): Path<String>,
) -> Result<Json<Json_>, ApiError> {
    let owner = user.name.clone();
    one_component(&state, user, owner, name).await
}

/// User `owner`'s upload `name`, if the caller may see it
/// (`store::access`).
pub(super) async fn get_component(
    State(state): State<Arc<PortalState>>,
    Authed(user): Authed,
    Path((owner, name)): Path<(String, String)>,
) -> Result<Json<Json_>, ApiError> {
    one_component(&state, user, owner, name).await
}

/// The body of `PUT /components/{owner}/{name}/visibility`.
#[derive(serde::Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
pub(super) struct VisibilityBody {
    visibility: crate::store::access::Visibility,
}

/// Shares an upload with the lab, or makes it private again (its owner,
/// or an admin).
pub(super) async fn put_component_visibility(
    State(state): State<Arc<PortalState>>,
    Authed(user): Authed,
    Path((owner, name)): Path<(String, String)>,
    body: Bytes,
) -> Result<Json<Json_>, ApiError> {
    let body: VisibilityBody = serde_json::from_slice(&body).map_err(|e| {
        ApiError::new(StatusCode::BAD_REQUEST, format!("expected {{\"visibility\": \"private\" or \"lab\"}}: {e}"))
    })?;
    let deployer = state.deployer.clone();
    let record =
        blocking(move || Ok(deployer.set_component_visibility(&user, &owner, &name, body.visibility)?)).await?;
    Ok(Json(component_json(record)))
}

pub(super) async fn upload_component(
    State(state): State<Arc<PortalState>>,
    Authed(user): Authed,
    Path((platform, name)): Path<(String, String)>,
    body: Bytes,
) -> Result<(StatusCode, Json<Json_>), ApiError> {
    let platform = platform_of(&platform)?;
    let deployer = state.deployer.clone();
    let record = blocking(move || Ok(deployer.upload_component(&user, platform, &name, &body)?)).await?;
    Ok((StatusCode::CREATED, Json(component_json(record))))
}

pub(super) async fn upload_config(
    State(state): State<Arc<PortalState>>,
    Authed(user): Authed,
    Path((platform, file)): Path<(String, String)>,
    body: Bytes,
) -> Result<(StatusCode, Json<Json_>), ApiError> {
    let platform = platform_of(&platform)?;
    let deployer = state.deployer.clone();
    let set = blocking(move || Ok(deployer.stage(&user, platform, &file, &body)?)).await?;
    Ok((StatusCode::CREATED, Json(json!({ "set": set }))))
}

/// Every uploaded simulator world.
pub(super) async fn list_worlds(
    State(state): State<Arc<PortalState>>,
    Authed(_): Authed,
) -> Result<Json<Json_>, ApiError> {
    let deployer = state.deployer.clone();
    let worlds = blocking(move || Ok(deployer.worlds()?)).await?;
    Ok(Json(json!({ "worlds": worlds })))
}

/// Uploads a simulator world file (checked like `subsume check` checks
/// one; a robot file staged later names it in its simulator's `world`).
pub(super) async fn upload_world(
    State(state): State<Arc<PortalState>>,
    Authed(user): Authed,
    Path(file): Path<String>,
    body: Bytes,
) -> Result<(StatusCode, Json<Json_>), ApiError> {
    let deployer = state.deployer.clone();
    let world = blocking(move || Ok(deployer.upload_world(&user, &file, &body)?)).await?;
    Ok((StatusCode::CREATED, Json(json!({ "world": world }))))
}

/// Validates a robot file as staging would and stores nothing (the
/// editor's validate-as-you-type): 200 with what it would stage, or the
/// diagnostics of `subsume check`.
pub(super) async fn validate_config(
    State(state): State<Arc<PortalState>>,
    Authed(user): Authed,
    Path((platform, file)): Path<(String, String)>,
    body: Bytes,
) -> Result<Json<crate::deploy::Validated>, ApiError> {
    let platform = platform_of(&platform)?;
    let deployer = state.deployer.clone();
    let validated = blocking(move || Ok(deployer.validate(&user, platform, &file, &body)?)).await?;
    Ok(Json(validated))
}

/// Where a set stands among the active set and its rollback history.
#[derive(Clone, Copy, serde::Serialize, schemars::JsonSchema)]
#[serde(rename_all = "snake_case")]
pub(super) enum SetStatus {
    /// It runs.
    Active,
    /// It ran just before the active one: a rollback brings it back.
    Previous,
    /// It ran before that, and is in the rollback history.
    #[serde(rename = "was active")]
    WasActive,
    /// It never ran.
    Staged,
}

fn set_status(id: u64, state: &StoreState) -> SetStatus {
    if state.active == Some(id) {
        SetStatus::Active
    } else if state.history.last() == Some(&id) {
        SetStatus::Previous
    } else if state.history.contains(&id) {
        SetStatus::WasActive
    } else {
        SetStatus::Staged
    }
}

pub(super) async fn list_sets(
    State(state): State<Arc<PortalState>>,
    Authed(user): Authed,
) -> Result<Json<Json_>, ApiError> {
    let (store, lab) = (state.deployer.store.clone(), state.lab.clone());
    blocking(move || {
        let st = store.state()?;
        let (access, baseline) = lab.access()?;
        let sets: Vec<Json_> = store
            .sets()?
            .into_iter()
            .rev()
            .filter(|s| s.id == baseline || access.may_see_set(&user, s))
            .map(|s| {
                let status = set_status(s.id, &st);
                let mut value = serde_json::to_value(s).unwrap_or_default();
                if let Some(fields) = value.as_object_mut() {
                    // The wiring is for one set's page (GET /sets/{id}).
                    fields.remove("graph");
                    fields.insert("status".into(), serde_json::to_value(status).unwrap_or_default());
                }
                value
            })
            .collect();
        Ok(Json(json!({ "active": st.active, "previous": st.history.last(), "sets": sets })))
    })
    .await
}

/// Set `id`, if the caller may see it (`store::access`; the baseline is
/// everyone's to see): its record, wiring, status and robot file, the
/// robot file only when the caller may read it (a researcher gets the
/// robot's own only while the owner's lab kit is on).
pub(super) async fn get_set(
    State(state): State<Arc<PortalState>>,
    Authed(user): Authed,
    Path(id): Path<String>,
) -> Result<Json<Json_>, ApiError> {
    let id = set_id(&id)?;
    let (store, lab) = (state.deployer.store.clone(), state.lab.clone());
    // Parameters set with `subsume run --param`: a set runs with those that
    // name one of its components (the others are skipped for it).
    let overrides = state.deployer.overrides().to_vec();
    blocking(move || {
        let set = store.set(id)?;
        let (access, baseline) = lab.access()?;
        if id != baseline && !access.may_see_set(&user, &set) {
            // Someone else's set answers as a missing one.
            return Err(ApiError::from(crate::store::StoreError::NoSet(id)));
        }
        let overrides: Vec<&crate::deploy::ParamOverride> =
            overrides.iter().filter(|o| set.graph.components.iter().any(|c| c.name == o.component)).collect();
        let config = if access.may_read_set(&user, &set) {
            Json_::String(String::from_utf8_lossy(&store.blob(&set.config_sha256)?).into_owned())
        } else {
            Json_::Null
        };
        let status = set_status(id, &store.state()?);
        Ok(Json(json!({
            "graph": set.graph,
            "set": set,
            "status": status,
            "config": config,
            "overrides": overrides,
        })))
    })
    .await
}

/// Forgets a set the caller staged that nothing needs (an admin: anyone's):
/// what a refused submission or activation left.
pub(super) async fn forget_set(
    State(state): State<Arc<PortalState>>,
    Authed(user): Authed,
    Path(id): Path<String>,
) -> Result<StatusCode, ApiError> {
    let id = set_id(&id)?;
    let deployer = state.deployer.clone();
    blocking(move || Ok(deployer.forget_set(&user, id)?)).await?;
    Ok(StatusCode::NO_CONTENT)
}

pub(super) async fn activate(
    State(state): State<Arc<PortalState>>,
    Authed(user): Authed,
    Path(id): Path<String>,
) -> Result<Json<Json_>, ApiError> {
    let id = set_id(&id)?;
    let deployer = state.deployer.clone();
    let (set, note) = blocking(move || Ok(deployer.activate_noting(&user, id)?)).await?;
    Ok(Json(json!({ "active": set, "note": note })))
}

/// The body of `POST /sets/{id}/replay`.
#[derive(serde::Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
pub(super) struct ReplayRequest {
    /// A file of the recordings folder.
    recording: String,
    /// The components to replay; every WASM component when missing or empty.
    #[serde(default)]
    only: Vec<String>,
}

/// Replays stored set `id`'s components against a stored recording before
/// anyone activates it (`POST /sets/{id}/replay`, body
/// `{"recording": NAME, "only": [COMPONENT...]}`): 200 with the report
/// (identical, or the first divergence of each port), on a blocking thread.
pub(super) async fn replay_set(
    State(state): State<Arc<PortalState>>,
    Authed(user): Authed,
    Path(id): Path<String>,
    body: Bytes,
) -> Result<Json<Json_>, ApiError> {
    let id = set_id(&id)?;
    authorise(&user, Permission::Record)?;
    let request: ReplayRequest = serde_json::from_slice(&body).map_err(|e| {
        ApiError::new(
            StatusCode::BAD_REQUEST,
            format!("expected {{\"recording\": NAME, \"only\": [COMPONENT...]}}: {e}"),
        )
    })?;
    let deployer = state.deployer.clone();
    let report = blocking(move || Ok(deployer.replay_set(&user, id, &request.recording, &request.only)?)).await?;
    let identical = report.identical();
    Ok(Json(json!({ "set": id, "identical": identical, "report": report })))
}

pub(super) async fn rollback(
    State(state): State<Arc<PortalState>>,
    Authed(user): Authed,
) -> Result<Json<Json_>, ApiError> {
    let deployer = state.deployer.clone();
    let (set, note) = blocking(move || Ok(deployer.rollback_noting(&user)?)).await?;
    Ok(Json(json!({ "active": set, "note": note })))
}

/// The next live status the control loop publishes (the last one may be
/// old: the loop publishes only while someone is subscribed). It comes
/// within one cycle, or `deploy::LIVE_PERIOD` while others watch; after a
/// second without one, the last.
async fn fresh_live_status(state: &PortalState) -> Arc<Option<LiveStatus>> {
    let mut live = state.deployer.live().subscribe();
    live.borrow_and_update();
    let _ = tokio::time::timeout(Duration::from_secs(1), live.changed()).await;
    live.borrow().clone()
}

/// The live status as `user` may see it: everyone watches the robot, but
/// an experiment's label and its robot file's name are its submitter's
/// and the admins' (`lab::sees_experiments_of`).
fn live_status_for(user: &User, status: &Option<LiveStatus>) -> Json_ {
    let mut value = serde_json::to_value(status).unwrap_or_default();
    if status.is_some() {
        crate::lab::live_status_for(user, &mut value);
    }
    value
}

pub(super) async fn status(State(state): State<Arc<PortalState>>, Authed(user): Authed) -> Json<Json_> {
    let current = fresh_live_status(&state).await;
    Json(live_status_for(&user, &current))
}

/// The plots' history kept on the host (`GET /history`): a sample a
/// second over the last minutes, for whoever may see the status; the page
/// draws it when it opens, then goes on with the live events.
pub(super) async fn history(State(state): State<Arc<PortalState>>, Authed(_): Authed) -> Json<Json_> {
    let deployer = state.deployer.clone();
    let (samples, now_s) = deployer.plot_history();
    Json(json!({
        "period_s": crate::deploy::HISTORY_PERIOD_NS as f64 / 1e9,
        "max_samples": crate::deploy::HISTORY_SAMPLES,
        "now_s": now_s,
        "samples": samples,
    }))
}

/// Prometheus metrics (OpenMetrics text) of the running set: for peers on
/// a loopback address (a Prometheus or agent on the robot) and for
/// logged-in users (a session cookie or `Authorization: Bearer`).
pub(super) async fn metrics(
    State(state): State<Arc<PortalState>>,
    ClientAddress(peer): ClientAddress,
    headers: axum::http::HeaderMap,
) -> Response {
    let local = peer.is_some_and(|p| p.ip().is_loopback());
    if !local && super::auth::user_of(&headers, &state).is_none() {
        return ApiError::new(
            StatusCode::UNAUTHORIZED,
            "metrics are for loopback peers and logged-in users: log in, or scrape from the robot itself",
        )
        .into_response();
    }
    if state.lab.fleet().is_some() {
        // A lab server runs no robot: the lab's families alone, with its
        // link's counters.
        let text = crate::metrics::encode_families(state.lab.metrics().families());
        return ([(axum::http::header::CONTENT_TYPE, crate::metrics::CONTENT_TYPE)], text).into_response();
    }
    let current = fresh_live_status(&state).await;
    let Some(status) = current.as_ref() else {
        return ApiError::new(StatusCode::SERVICE_UNAVAILABLE, "the control loop has not published a status yet")
            .into_response();
    };
    let text = crate::metrics::encode_with(status, state.lab.metrics().families());
    ([(axum::http::header::CONTENT_TYPE, crate::metrics::CONTENT_TYPE)], text).into_response()
}

/// Server-sent events: `status` (the live status, 5 per second) and `log`
/// (each new log line; the recent ones first), but the lines naming work
/// the caller may not see (`LogLine::owner`, `store::access`).
pub(super) async fn events(State(state): State<Arc<PortalState>>, Authed(user): Authed) -> Response {
    use axum::response::sse::{Event, KeepAlive, Sse};
    use futures_util::StreamExt as _;
    let deployer = state.deployer.clone();
    let access = match blocking(move || Ok(deployer.access()?)).await {
        Ok(access) => Arc::new(access),
        Err(e) => return e.into_response(),
    };
    let live = state.deployer.live().subscribe();
    let logs = state.logs.subscribe();
    let backlog: Vec<Result<Event, std::convert::Infallible>> = state
        .logs
        .recent()
        .into_iter()
        .filter(|line| line.visible_to(&user, &access))
        .filter_map(|line| Event::default().event("log").json_data(line).ok())
        .map(Ok)
        .collect();
    let watcher = user.clone();
    let statuses = futures_util::stream::unfold((live, watcher), |(mut live, watcher)| async move {
        live.changed().await.ok()?;
        let value = live.borrow_and_update().clone();
        let event = Event::default().event("status").json_data(live_status_for(&watcher, &value)).unwrap_or_default();
        Some((Ok(event), (live, watcher)))
    });
    let lines = futures_util::stream::unfold((logs, user, access), |(mut logs, user, access)| async move {
        loop {
            match logs.recv().await {
                Ok(line) if !line.visible_to(&user, &access) => continue,
                Ok(line) => {
                    let event = Event::default().event("log").json_data(line).unwrap_or_default();
                    return Some((Ok(event), (logs, user, access)));
                }
                Err(tokio::sync::broadcast::error::RecvError::Lagged(_)) => continue,
                Err(tokio::sync::broadcast::error::RecvError::Closed) => return None,
            }
        }
    });
    let stream = futures_util::stream::iter(backlog).chain(futures_util::stream::select(statuses, lines));
    Sse::new(stream).keep_alive(KeepAlive::default()).into_response()
}

/// The boundary between the frames of a live camera stream.
const LIVE_BOUNDARY: &str = "subsume-frame";
/// How often a live camera stream with no new frame checks that its
/// watcher may still watch: a researcher's stream ends within this of her
/// experiment's end.
const LIVE_RECHECK: Duration = Duration::from_secs(1);

/// The running cameras (`GET /cameras`), for whoever may watch them.
pub(super) async fn cameras(
    State(state): State<Arc<PortalState>>,
    Authed(user): Authed,
) -> Result<Json<Json_>, ApiError> {
    state.deployer.may_watch_cameras(&user)?;
    Ok(Json(json!({ "cameras": state.deployer.camera_names() })))
}

/// A camera live (`GET /cameras/{name}/live`): its newest frames as an
/// MJPEG stream (`multipart/x-mixed-replace`, which a browser's `<img>`
/// shows), for whoever may watch the robot (`Deployer::may_watch_cameras`:
/// the owner, operators, a researcher during her own experiment). A slow
/// watcher skips frames (only the newest waits). The stream ends when the
/// camera stops (a new set) or the watcher may no longer watch.
pub(super) async fn camera_live(
    State(state): State<Arc<PortalState>>,
    Authed(user): Authed,
    Path(name): Path<String>,
) -> Response {
    let receiver = match state.deployer.watch_camera(&user, &name) {
        Ok(receiver) => receiver,
        Err(e) => return ApiError::from(e).into_response(),
    };
    let deployer = state.deployer.clone();
    let frames = futures_util::stream::unfold((receiver, deployer, user), |(mut frames, deployer, user)| async move {
        loop {
            match tokio::time::timeout(LIVE_RECHECK, frames.changed()).await {
                Ok(Ok(())) => {}
                Ok(Err(_)) => return None,
                Err(_) => {
                    deployer.may_watch_cameras(&user).ok()?;
                    continue;
                }
            }
            deployer.may_watch_cameras(&user).ok()?;
            let latest = frames.borrow_and_update().clone();
            let Some(frame) = latest else { continue };
            let mut part = format!(
                "--{LIVE_BOUNDARY}\r\nContent-Type: image/jpeg\r\nContent-Length: {}\r\nX-Capture-Ns: {}\r\nX-Seq: {}\r\n\r\n",
                frame.jpeg.len(),
                frame.capture_ns,
                frame.seq
            )
            .into_bytes();
            part.extend_from_slice(&frame.jpeg);
            part.extend_from_slice(b"\r\n");
            return Some((Ok::<_, std::convert::Infallible>(Bytes::from(part)), (frames, deployer, user)));
        }
    });
    (
        [
            (axum::http::header::CONTENT_TYPE, format!("multipart/x-mixed-replace; boundary={LIVE_BOUNDARY}")),
            (axum::http::header::CACHE_CONTROL, "no-store".to_string()),
        ],
        axum::body::Body::from_stream(frames),
    )
        .into_response()
}

pub(super) async fn world(State(state): State<Arc<PortalState>>, Authed(_): Authed) -> Result<Json<Json_>, ApiError> {
    let deployer = state.deployer.clone();
    let view = blocking(move || Ok(deployer.sim_view()?)).await?;
    Ok(Json(serde_json::to_value(view).unwrap_or_default()))
}

/// A number from the query string, named in the error when missing or bad.
fn query_number(query: &std::collections::HashMap<String, String>, name: &str) -> Result<f64, ApiError> {
    let text = query
        .get(name)
        .ok_or_else(|| ApiError::new(StatusCode::BAD_REQUEST, format!("the query parameter '{name}' is missing")))?;
    text.trim().parse::<f64>().ok().filter(|v| v.is_finite()).ok_or_else(|| {
        ApiError::new(
            StatusCode::BAD_REQUEST,
            format!("the query parameter '{name}' is not a number: '{}'", clip(text)),
        )
    })
}

/// Resets, poses, pauses, resumes or steps the active set's simulated robot
/// (`POST /sim/{action}`; pose takes `x`, `y`, `heading`, step takes
/// `seconds` in the query).
pub(super) async fn sim_control(
    State(state): State<Arc<PortalState>>,
    Authed(user): Authed,
    Path(action): Path<String>,
    axum::extract::Query(query): axum::extract::Query<std::collections::HashMap<String, String>>,
) -> Result<Json<Json_>, ApiError> {
    // Permission is checked (and a refusal audited) by the deployer.
    let action = match action.as_str() {
        "reset" => SimAction::Reset,
        "pause" => SimAction::Pause,
        "resume" => SimAction::Resume,
        "step" => SimAction::Step { seconds: query_number(&query, "seconds")? },
        "pose" => SimAction::Pose {
            x: query_number(&query, "x")?,
            y: query_number(&query, "y")?,
            heading: query_number(&query, "heading")?,
        },
        other => {
            return Err(ApiError::new(
                StatusCode::NOT_FOUND,
                format!("no simulator action '{}': reset, pose, pause, resume or step", clip(other)),
            ));
        }
    };
    let deployer = state.deployer.clone();
    let status = blocking(move || Ok(deployer.sim_control(&user, action)?)).await?;
    Ok(Json(serde_json::to_value(status).unwrap_or_default()))
}

/// The host's recent log lines, but those naming work the caller may not
/// see (`LogLine::owner`, `store::access`).
pub(super) async fn recent_logs(
    State(state): State<Arc<PortalState>>,
    Authed(user): Authed,
) -> Result<Json<Json_>, ApiError> {
    let deployer = state.deployer.clone();
    let access = blocking(move || Ok(deployer.access()?)).await?;
    let lines: Vec<_> = state.logs.recent().into_iter().filter(|line| line.visible_to(&user, &access)).collect();
    Ok(Json(json!({ "lines": lines })))
}

pub(super) async fn audit_log(
    State(state): State<Arc<PortalState>>,
    Authed(user): Authed,
) -> Result<Json<Json_>, ApiError> {
    authorise(&user, Permission::ReadAudit)?;
    let deployer = state.deployer.clone();
    // A researcher's actions name her work: a developer sees the robot's
    // people's entries, an admin every one (`store::access`).
    let entries = blocking(move || {
        let access = deployer.access()?;
        let entries = deployer.store.audit_entries(MAX_AUDIT_READ)?;
        Ok(entries.into_iter().filter(|entry| access.may_see(&user, &entry.user)).collect::<Vec<_>>())
    })
    .await?;
    Ok(Json(json!({ "entries": entries })))
}

/// A set's id from the path: a whole number, else 400 saying so (JSON, as
/// every refusal).
fn set_id(text: &str) -> Result<u64, ApiError> {
    text.parse()
        .map_err(|_| ApiError::new(StatusCode::BAD_REQUEST, format!("set id '{}' is not a whole number", clip(text))))
}

fn teleop_servers(state: &PortalState) -> Result<Arc<crate::teleop::ServerContext>, ApiError> {
    state
        .deployer
        .services
        .get::<TeleopServers>()
        .and_then(|servers| servers.current())
        .ok_or_else(|| ApiError::new(StatusCode::NOT_FOUND, "the active set has no network platform (builtin:teleop)"))
}

pub(super) async fn teleop_ticket(
    State(state): State<Arc<PortalState>>,
    Authed(user): Authed,
) -> Result<Json<Json_>, ApiError> {
    state.deployer.authorise_drive(&user)?;
    teleop_servers(&state)?;
    let ticket = state.directory.tickets.issue(&user.name).map_err(|e| ApiError::internal(e.to_string()))?;
    Ok(Json(json!({ "name": user.name, "ticket": ticket, "websocket": "/api/v1/teleop" })))
}

/// The network platform's WebSocket protocol; the session authenticates
/// inside it (`auth` with a ticket or a password), as on its own listener.
pub(super) async fn teleop_socket(
    State(state): State<Arc<PortalState>>,
    ClientAddress(address): ClientAddress,
    ws: Result<WebSocketUpgrade, axum::extract::ws::rejection::WebSocketUpgradeRejection>,
) -> Response {
    let ws = match ws {
        Ok(ws) => ws,
        Err(rejection) => {
            let why = format!("this is the teleoperation WebSocket: connect with a WebSocket client ({rejection})");
            return ApiError::new(StatusCode::BAD_REQUEST, why).into_response();
        }
    };
    match teleop_servers(&state) {
        Ok(ctx) => {
            crate::teleop::upgrade_websocket(ws, ctx, address.unwrap_or_else(|| SocketAddr::from(([0, 0, 0, 0], 0))))
        }
        Err(e) => e.into_response(),
    }
}

/// Engages the emergency stop: any logged-in user, viewers included. Not
/// on a blocking thread: the lock is engaged at once, its audit line
/// follows off the request.
pub(super) async fn estop(
    State(state): State<Arc<PortalState>>,
    Authed(user): Authed,
) -> Result<Json<Json_>, ApiError> {
    let engaged = state.deployer.engage_lock(&user, "portal")?;
    Ok(Json(serde_json::to_value(engaged).unwrap_or_default()))
}

/// Releases a lock (`{"lock": NAME}`) or every engaged lock (no body): a
/// user who may drive.
pub(super) async fn release(
    State(state): State<Arc<PortalState>>,
    Authed(user): Authed,
    body: Bytes,
) -> Result<Json<Json_>, ApiError> {
    let lock = if body.iter().all(u8::is_ascii_whitespace) {
        None
    } else {
        let value: Json_ = serde_json::from_slice(&body).map_err(|e| {
            ApiError::new(StatusCode::BAD_REQUEST, format!("expected {{\"lock\": NAME}} or no body: {e}"))
        })?;
        match value.get("lock") {
            None | Some(Json_::Null) => None,
            Some(Json_::String(name)) => Some(name.clone()),
            Some(_) => return Err(ApiError::new(StatusCode::BAD_REQUEST, "field 'lock' must be a string")),
        }
    };
    let deployer = state.deployer.clone();
    let released = blocking(move || Ok(deployer.release_lock(&user, lock.as_deref(), "portal")?)).await?;
    Ok(Json(json!({ "released": released })))
}

/// The engaged locks and the latest engage and release events.
pub(super) async fn locks(State(state): State<Arc<PortalState>>, Authed(_): Authed) -> Result<Json<Json_>, ApiError> {
    let view = state.deployer.locks_view()?;
    Ok(Json(serde_json::to_value(view).unwrap_or_default()))
}

/// Bytes read from disk per piece of a download.
const DOWNLOAD_CHUNK: u64 = 256 << 10;

/// The running recording and the recordings folder's files.
pub(super) async fn list_recordings(
    State(state): State<Arc<PortalState>>,
    Authed(user): Authed,
) -> Result<Json<crate::deploy::RecordingsView>, ApiError> {
    let deployer = state.deployer.clone();
    Ok(Json(blocking(move || Ok(deployer.list_recordings(&user)?)).await?))
}

/// The body of `POST /recordings/start` (optional: an empty body is a
/// plain start).
#[derive(serde::Deserialize, Default, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
pub(super) struct StartRecording {
    /// Re-activate the active set and record from its first call.
    #[serde(default)]
    fresh_start: bool,
}

/// Starts recording the running robot (`POST /recordings/start`, body
/// empty or `{"fresh_start": true}`).
pub(super) async fn start_recording(
    State(state): State<Arc<PortalState>>,
    Authed(user): Authed,
    body: Bytes,
) -> Result<(StatusCode, Json<Json_>), ApiError> {
    // Who may not record is refused (and audited) by the use case.
    let request: StartRecording = if body.iter().all(u8::is_ascii_whitespace) {
        StartRecording::default()
    } else {
        serde_json::from_slice(&body).map_err(|e| {
            ApiError::new(StatusCode::BAD_REQUEST, format!("expected nothing or {{\"fresh_start\": BOOL}}: {e}"))
        })?
    };
    let deployer = state.deployer.clone();
    let info = blocking(move || Ok(deployer.start_recording(&user, request.fresh_start)?)).await?;
    Ok((StatusCode::CREATED, Json(json!({ "recording": info }))))
}

/// Stops the running recording (`POST /recordings/stop`).
pub(super) async fn stop_recording(
    State(state): State<Arc<PortalState>>,
    Authed(user): Authed,
) -> Result<Json<Json_>, ApiError> {
    let deployer = state.deployer.clone();
    let stopped = blocking(move || Ok(deployer.stop_recording(&user)?)).await?;
    Ok(Json(json!({ "stopped": stopped })))
}

/// Deletes a recording file (`DELETE /recordings/{name}`).
pub(super) async fn delete_recording(
    State(state): State<Arc<PortalState>>,
    Authed(user): Authed,
    Path(name): Path<String>,
) -> Result<Json<Json_>, ApiError> {
    let deployer = state.deployer.clone();
    let deleted = name.clone();
    blocking(move || Ok(deployer.delete_recording(&user, &name)?)).await?;
    Ok(Json(json!({ "deleted": deleted })))
}

/// Downloads a recording file (`GET /recordings/{name}`), streamed from
/// disk: the bytes it had when asked (a running recording keeps growing).
pub(super) async fn download_recording(
    State(state): State<Arc<PortalState>>,
    Authed(user): Authed,
    Path(name): Path<String>,
) -> Result<Response, ApiError> {
    use axum::http::header;
    let deployer = state.deployer.clone();
    let asked = name.clone();
    let (path, size) = blocking(move || Ok(deployer.recording_file(&user, &asked)?)).await?;
    let (tx, rx) = tokio::sync::mpsc::channel::<Result<Bytes, std::io::Error>>(4);
    tokio::task::spawn_blocking(move || {
        use std::io::Read as _;
        let mut file = match std::fs::File::open(&path) {
            Ok(file) => file,
            Err(e) => {
                let _ = tx.blocking_send(Err(e));
                return;
            }
        };
        let mut left = size;
        while left > 0 {
            let mut piece = vec![0u8; DOWNLOAD_CHUNK.min(left) as usize];
            match file.read(&mut piece) {
                Ok(0) => break,
                Ok(n) => {
                    piece.truncate(n);
                    left -= n as u64;
                    if tx.blocking_send(Ok(Bytes::from(piece))).is_err() {
                        break;
                    }
                }
                Err(e) => {
                    let _ = tx.blocking_send(Err(e));
                    break;
                }
            }
        }
    });
    let stream = futures_util::stream::unfold(rx, |mut rx| async move { rx.recv().await.map(|piece| (piece, rx)) });
    Ok((
        [
            (header::CONTENT_TYPE, "application/octet-stream".to_string()),
            (header::CONTENT_LENGTH, size.to_string()),
            (header::CONTENT_DISPOSITION, format!("attachment; filename=\"{name}\"")),
        ],
        axum::body::Body::from_stream(stream),
    )
        .into_response())
}
