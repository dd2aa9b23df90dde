//! Operations endpoints (no authentication): liveness, readiness, Prometheus metrics, and the
//! OpenAPI document.
//!
//! * `GET /healthz`: 200 while the process serves requests.
//! * `GET /readyz`: 200 when the job store answers and the server is not shutting down, else 503.
//! * `GET /metrics`: Prometheus text format (see [`crate::jobs::metrics`]).
//! * `GET /openapi.json`: `proto/openapi.yaml` as JSON.

use axum::extract::State;
use axum::http::{HeaderValue, header};
use axum::response::{IntoResponse, Response};
use serde_json::json;

use super::{ApiError, AppState};

/// `GET /healthz`.
pub async fn healthz() -> Response {
    axum::Json(json!({"status": "ok"})).into_response()
}

/// `GET /readyz`.
pub async fn readyz(State(state): State<AppState>) -> Result<Response, ApiError> {
    if state.jobs.ready().await {
        Ok(axum::Json(json!({
            "status": "ready",
            "queue_depth": state.jobs.queue_depth(),
        }))
        .into_response())
    } else {
        Err(ApiError::Unavailable(
            "not ready: shutting down or the job store does not answer".into(),
        ))
    }
}

/// `GET /metrics`.
pub async fn metrics(State(state): State<AppState>) -> Result<Response, ApiError> {
    let text = state.jobs.render_metrics().await?;
    let mut r = text.into_response();
    r.headers_mut().insert(
        header::CONTENT_TYPE,
        HeaderValue::from_static("text/plain; version=0.0.4; charset=utf-8"),
    );
    Ok(r)
}

/// `GET /openapi.json`.
pub async fn openapi(State(state): State<AppState>) -> Response {
    let mut r = state.openapi.as_str().to_string().into_response();
    r.headers_mut().insert(
        header::CONTENT_TYPE,
        HeaderValue::from_static("application/json"),
    );
    r
}
