//! The HTTP API (axum): asynchronous denoising jobs with OGC API – Processes semantics, resumable
//! uploads, ranged downloads, a synchronous path for small scans, and operations endpoints.
//!
//! # Brief overview
//!
//! * [`router`] builds the whole [`Router`] from an [`AppState`] (the job service plus API
//!   settings), so tests can drive it with `tower::ServiceExt::oneshot` and no socket.
//!   The routes are listed in one place, [`routes`], which the OpenAPI test compares with
//!   `proto/openapi.yaml` (served as `/openapi.json`).
//! * `/v1/*` requires `Authorization: Bearer <token>` when tokens are configured; the token names
//!   the tenant ([`auth`]). Other tenants' resources answer 404.
//! * Errors are RFC 9457 problem details ([`error::ApiError`]).
//! * Every request gets an `x-request-id` (generated, or the client's) that the response carries
//!   and every log line of the request includes.
//! * [`server::Server`] binds, serves and shuts down gracefully (SIGTERM / Ctrl-C: stop accepting,
//!   cancel running jobs at their next tile so they resume at the next start, exit).
//!
//! | route | handler module |
//! |---|---|
//! | `POST /v1/uploads`, `OPTIONS /v1/uploads`, `GET`/`HEAD`/`PATCH`/`DELETE /v1/uploads/{id}` | [`uploads`] |
//! | `POST`/`GET /v1/jobs`, `GET`/`DELETE /v1/jobs/{id}` | [`jobs`] |
//! | `GET /v1/jobs/{id}/result` (Range, ETag) | [`download`] |
//! | `POST /v1/denoise` | [`sync`] |
//! | `GET /v1/jobs/{id}/preview`, `…/preview/before`, `…/preview/after` | [`preview`] |
//! | `/healthz`, `/readyz`, `/metrics`, `/openapi.json` | [`ops`] |
//! | `GET /` (the web page), `GET /web/{file}` (its files) | [`web`] |

pub mod auth;
pub mod conn;
pub mod download;
pub mod error;
pub mod jobs;
pub mod ops;
pub mod preview;
pub mod server;
pub mod sync;
pub mod uploads;
pub mod web;

use std::sync::Arc;

use axum::Router;
use axum::http::{HeaderMap, Request, header};
use axum::routing::{MethodRouter, get, post};
use tower::ServiceBuilder;
use tower_http::request_id::{MakeRequestUuid, PropagateRequestIdLayer, SetRequestIdLayer};
use tower_http::trace::{DefaultOnResponse, TraceLayer};
use tracing::Level;

pub use error::ApiError;

use crate::io::Format;
use crate::jobs::Jobs;

/// The OpenAPI document (the wire contract), embedded.
pub const OPENAPI_YAML: &str = include_str!("../../proto/openapi.yaml");

/// API settings beside the job service's.
#[derive(Debug, Clone, Default)]
pub struct ApiSettings {
    /// `(token, tenant)` pairs; empty for no authentication.
    pub tokens: Vec<(String, String)>,
    /// Largest synchronous request body in bytes.
    pub max_sync_size: u64,
}

/// Everything a handler needs (cheap to clone).
#[derive(Clone, Debug)]
pub struct AppState {
    /// The job service.
    pub jobs: Jobs,
    /// API settings.
    pub settings: Arc<ApiSettings>,
    /// `proto/openapi.yaml` converted to JSON once.
    openapi: Arc<String>,
}

impl AppState {
    /// Builds the state.
    ///
    /// # Errors
    /// The embedded OpenAPI document does not parse (a build defect caught by the tests).
    pub fn new(jobs: Jobs, settings: ApiSettings) -> Result<AppState, ApiError> {
        let doc = openapi_document()?;
        let openapi =
            serde_json::to_string(&doc).map_err(|e| ApiError::Internal(format!("openapi: {e}")))?;
        Ok(AppState {
            jobs,
            settings: Arc::new(settings),
            openapi: Arc::new(openapi),
        })
    }
}

/// `proto/openapi.yaml` as JSON.
///
/// # Errors
/// The document does not parse.
pub fn openapi_document() -> Result<serde_json::Value, ApiError> {
    serde_norway::from_str(OPENAPI_YAML).map_err(|e| ApiError::Internal(format!("openapi: {e}")))
}

/// Every route: path and method router, `/v1` ones flagged for authentication.
pub fn routes() -> Vec<(&'static str, bool, MethodRouter<AppState>)> {
    vec![
        ("/", false, get(web::page)),
        ("/healthz", false, get(ops::healthz)),
        ("/readyz", false, get(ops::readyz)),
        ("/metrics", false, get(ops::metrics)),
        ("/openapi.json", false, get(ops::openapi)),
        (
            "/v1/uploads",
            true,
            post(uploads::create)
                .get(uploads::list)
                .options(uploads::options),
        ),
        (
            "/v1/uploads/{id}",
            true,
            get(uploads::status)
                .patch(uploads::patch)
                .delete(uploads::delete),
        ),
        ("/v1/jobs", true, post(jobs::create).get(jobs::list)),
        (
            "/v1/jobs/{id}",
            true,
            get(jobs::status).delete(jobs::dismiss),
        ),
        ("/v1/jobs/{id}/result", true, get(download::result)),
        ("/v1/jobs/{id}/preview", true, get(preview::describe)),
        ("/v1/jobs/{id}/preview/before", true, get(preview::before)),
        ("/v1/jobs/{id}/preview/after", true, get(preview::after)),
        ("/v1/denoise", true, post(sync::denoise)),
    ]
}

/// The service's router over `state`.
pub fn router(state: AppState) -> Router {
    let mut open = Router::new();
    let mut v1 = Router::new();
    for (path, authed, mr) in routes() {
        if authed {
            v1 = v1.route(path, mr);
        } else {
            open = open.route(path, mr);
        }
    }
    let v1 = v1.route_layer(axum::middleware::from_fn_with_state(
        state.clone(),
        auth::authenticate,
    ));
    open.merge(v1)
        .merge(web::router())
        .fallback(|| async { ApiError::NoRoute })
        .method_not_allowed_fallback(|| async { ApiError::MethodNotAllowed })
        .layer(
            ServiceBuilder::new()
                .layer(SetRequestIdLayer::x_request_id(MakeRequestUuid))
                .layer(
                    TraceLayer::new_for_http()
                        .make_span_with(|req: &Request<_>| {
                            let id = req
                                .headers()
                                .get("x-request-id")
                                .and_then(|v| v.to_str().ok())
                                .unwrap_or("-");
                            tracing::info_span!(
                                "request",
                                request_id = %id,
                                method = %req.method(),
                                path = %req.uri().path(),
                                tenant = tracing::field::Empty,
                            )
                        })
                        .on_response(DefaultOnResponse::new().level(Level::INFO)),
                )
                .layer(PropagateRequestIdLayer::x_request_id()),
        )
        .with_state(state)
}

/// The request's media type without parameters, lower-cased (`None` when absent).
pub(crate) fn media_type(headers: &HeaderMap) -> Option<String> {
    headers
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .map(|v| {
            v.split(';')
                .next()
                .unwrap_or_default()
                .trim()
                .to_ascii_lowercase()
        })
}

/// The format a scan's content type names: `Some(None)` for generic binary or text (sniff the
/// content), `Some(Some(ext))` for a format's own type, `None` for anything else (refused).
pub(crate) fn format_of_media_type(headers: &HeaderMap) -> Option<Option<Format>> {
    match media_type(headers).as_deref() {
        None | Some("application/octet-stream") | Some("text/plain") => Some(None),
        Some("application/vnd.las") => Some(Some(Format::Las)),
        Some("application/vnd.laszip") => Some(Some(Format::Laz)),
        Some("application/x-ply") | Some("model/x-ply") => Some(Some(Format::Ply)),
        Some("application/x-pcd") => Some(Some(Format::Pcd)),
        Some("model/obj") => Some(Some(Format::Obj)),
        _ => None,
    }
}

/// Collects a body of at most `limit` bytes (the announced `Content-Length` is checked first).
/// An oversized body is drained (up to [`crate::jobs::DRAIN_MAX`]) before the 413, so the client
/// reads the answer rather than a reset.
pub(crate) async fn read_limited(
    headers: &HeaderMap,
    body: axum::body::Body,
    limit: u64,
) -> Result<axum::body::Bytes, ApiError> {
    use futures_util::StreamExt;
    let mut stream = body.into_data_stream();
    let announced = headers
        .get(header::CONTENT_LENGTH)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.trim().parse::<u64>().ok());
    if let Some(n) = announced.filter(|&n| n > limit) {
        if n - limit <= crate::jobs::DRAIN_MAX {
            crate::jobs::discard(&mut stream, n).await;
        }
        return Err(ApiError::TooLarge { limit });
    }
    let mut buf = Vec::with_capacity(usize::try_from(announced.unwrap_or(0)).unwrap_or(0));
    while let Some(chunk) = stream.next().await {
        let chunk = chunk.map_err(|e| ApiError::BadRequest(format!("reading the body: {e}")))?;
        if (buf.len() + chunk.len()) as u64 > limit {
            crate::jobs::discard(&mut stream, crate::jobs::DRAIN_MAX).await;
            return Err(ApiError::TooLarge { limit });
        }
        buf.extend_from_slice(&chunk);
    }
    Ok(buf.into())
}

/// The media type a result is served with.
pub(crate) fn media_type_of(format: Format) -> &'static str {
    match format {
        Format::Las => "application/vnd.las",
        Format::Laz | Format::Copc => "application/vnd.laszip",
        Format::Obj => "model/obj",
        Format::Xyz | Format::Pts | Format::Off => "text/plain",
        _ => "application/octet-stream",
    }
}

/// Default and largest page size of the lists (`GET /v1/jobs`, `GET /v1/uploads`).
const PAGE: (u64, u64) = (50, 1000);

/// The query of a list without filters (`GET /v1/uploads`).
#[derive(Debug, Default, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct PageQuery {
    pub limit: Option<u64>,
    pub offset: Option<u64>,
}

/// A list's `limit` (default 50, at most 1000) and `offset` (default 0).
///
/// # Errors
/// [`ApiError::Unprocessable`] naming `limit`.
pub(crate) fn page_of(limit: Option<u64>, offset: Option<u64>) -> Result<(u64, u64), ApiError> {
    let limit = limit.unwrap_or(PAGE.0);
    if !(1..=PAGE.1).contains(&limit) {
        return Err(ApiError::invalid("limit", "must be between 1 and 1000"));
    }
    Ok((limit, offset.unwrap_or(0)))
}

/// A page of a list as JSON: the `items` under `key`, `total`, `limit`, `offset`, and the
/// `self`, `next` and `prev` links at `base` (`filter`: more query parameters, each starting `&`).
pub(crate) fn page_response(
    (base, filter): (&str, &str),
    key: &str,
    items: Vec<serde_json::Value>,
    (limit, offset): (u64, u64),
    total: u64,
) -> axum::response::Response {
    use axum::response::IntoResponse;
    let shown = items.len() as u64;
    let page = |off: u64| format!("{base}?limit={limit}&offset={off}{filter}");
    let mut links = vec![serde_json::json!({"rel": "self", "href": page(offset)})];
    if offset + shown < total {
        links.push(serde_json::json!({"rel": "next", "href": page(offset + shown)}));
    }
    if offset > 0 {
        links.push(serde_json::json!({"rel": "prev", "href": page(offset.saturating_sub(limit))}));
    }
    axum::Json(serde_json::json!({
        key: items,
        "total": total,
        "limit": limit,
        "offset": offset,
        "links": links,
    }))
    .into_response()
}

/// Milliseconds since the Unix epoch, now.
pub(crate) fn now_ms() -> i64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| i64::try_from(d.as_millis()).unwrap_or(i64::MAX))
}

/// Milliseconds since the epoch as RFC 3339.
pub(crate) fn timestamp(ms: i64) -> String {
    let t =
        std::time::UNIX_EPOCH + std::time::Duration::from_millis(u64::try_from(ms).unwrap_or(0));
    humantime::format_rfc3339_millis(t).to_string()
}

#[cfg(test)]
mod tests;
