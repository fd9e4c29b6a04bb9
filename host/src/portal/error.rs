//! The portal's errors: every refused or failed request answers JSON
//! `{"error": ..., "diagnostics": [...]}` with the status that fits, and a
//! use case's [`DeployError`] maps to one here, in one place.

use axum::Json;
use axum::http::{HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};

use crate::deploy::{DeployError, Diagnostics};
use crate::store::StoreError;

/// Every refusal and failure: why, and for a robot file the problems,
/// each at its place.
#[derive(serde::Serialize, schemars::JsonSchema)]
pub(super) struct ErrorBody {
    /// Empty but for a robot file's problems.
    diagnostics: Vec<DiagnosticView>,
    /// Why, lowercase, naming the thing and the place.
    error: String,
}

/// One problem of a robot file.
#[derive(serde::Serialize, schemars::JsonSchema)]
struct DiagnosticView {
    /// 1-based, in characters.
    column: usize,
    /// The file's name as uploaded.
    file: String,
    /// 1-based.
    line: usize,
    message: String,
    /// `file:line:column: message`.
    text: String,
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

    pub fn internal(message: impl Into<String>) -> ApiError {
        ApiError::new(StatusCode::INTERNAL_SERVER_ERROR, message)
    }

    pub fn unauthorized() -> ApiError {
        ApiError::new(StatusCode::UNAUTHORIZED, "log in first (POST /api/v1/login)")
    }

    pub fn forbidden(message: impl Into<String>) -> ApiError {
        ApiError::new(StatusCode::FORBIDDEN, message)
    }
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        let diagnostics = self
            .diagnostics
            .iter()
            .flat_map(|d| d.0.iter())
            .map(|d| DiagnosticView {
                column: d.column,
                file: d.path.display().to_string(),
                line: d.line,
                message: d.message.clone(),
                text: d.to_string(),
            })
            .collect();
        let body = ErrorBody { diagnostics, error: self.message };
        let mut response = (self.status, Json(body)).into_response();
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
                format!(
                    "the set did not start; the running set is unchanged: {}",
                    errors.iter().map(ToString::to_string).collect::<Vec<_>>().join("; ")
                ),
            ),
            DeployError::Forbidden(m) => ApiError::forbidden(m),
            DeployError::Conflict(m) => ApiError::new(StatusCode::CONFLICT, m),
            DeployError::BadRequest(m) => ApiError::new(StatusCode::BAD_REQUEST, m),
            DeployError::NotFound(m) => ApiError::new(StatusCode::NOT_FOUND, m),
            DeployError::Busy(m) => {
                ApiError { retry_after: Some(1), ..ApiError::new(StatusCode::TOO_MANY_REQUESTS, m) }
            }
            e @ DeployError::NotAComponent(_) => ApiError::new(StatusCode::UNSUPPORTED_MEDIA_TYPE, e.to_string()),
            DeployError::WrongWorld(m) => ApiError::new(StatusCode::UNPROCESSABLE_ENTITY, m),
            DeployError::Unprocessable(m) => ApiError::new(StatusCode::UNPROCESSABLE_ENTITY, m),
            DeployError::Store(StoreError::NoSet(id)) => ApiError::new(StatusCode::NOT_FOUND, format!("no set {id}")),
            DeployError::Store(StoreError::Full { .. }) => {
                tracing::error!("{e}");
                ApiError::new(
                    StatusCode::INSUFFICIENT_STORAGE,
                    "the robot's disk is full: nothing of this request was kept; \
                     free some space (delete recordings or old sets) and try again",
                )
            }
            other => ApiError::internal(other.to_string()),
        }
    }
}

impl From<StoreError> for ApiError {
    fn from(e: StoreError) -> ApiError {
        ApiError::from(DeployError::Store(e))
    }
}
