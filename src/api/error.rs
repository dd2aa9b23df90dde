//! API errors as RFC 9457 problem details (`application/problem+json`).
//!
//! Every error response of the service has this shape:
//!
//! ```json
//! {"type": "urn:qemd:problem:invalid-parameter", "title": "Unprocessable Content",
//!  "status": 422, "detail": "params.knn: must be between 3 and 1024 …", "field": "params.knn"}
//! ```
//!
//! Client errors say what is wrong. Internal errors are logged (inside the request's span, which
//! carries its `x-request-id`) and answered with a generic detail: no paths, no SQL, no chains.

use axum::http::{HeaderMap, HeaderName, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};

use crate::jobs::JobsError;

/// An error answered to a client. Its `Display` is the problem's `detail` (an internal error's
/// says only where to look: the message itself is logged, never sent).
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum ApiError {
    /// 400: a malformed request.
    #[error("{0}")]
    BadRequest(String),
    /// 401: no or a wrong bearer token.
    #[error("a valid `Authorization: Bearer <token>` is required")]
    Unauthorized,
    /// 404: no such resource (for this tenant).
    #[error("{0}")]
    NotFound(String),
    /// 404: no such route.
    #[error("no such route")]
    NoRoute,
    /// 405: the route does not take this method.
    #[error("this route does not take this method")]
    MethodNotAllowed,
    /// 409: the resource's state forbids the request.
    #[error("{detail}")]
    Conflict {
        /// What is in the way.
        detail: String,
        /// The server's offset of a resumable upload (sent as `Upload-Offset`).
        offset: Option<u64>,
    },
    /// 413: a body or upload is too large.
    #[error("larger than the limit of {limit} bytes")]
    TooLarge {
        /// The limit in bytes.
        limit: u64,
    },
    /// 415: unknown content type or format.
    #[error("{0}")]
    UnsupportedMediaType(String),
    /// 416: the range lies outside the file.
    #[error("the range lies outside the {size} bytes of the file")]
    RangeNotSatisfiable {
        /// File size (sent as `Content-Range: bytes */size`).
        size: u64,
    },
    /// 422: a well-formed request with invalid content.
    #[error("{}", field_first(field.as_deref(), detail))]
    Unprocessable {
        /// The offending field, when there is one.
        field: Option<String>,
        /// What is wrong.
        detail: String,
    },
    /// 429: come back later.
    #[error("{detail}")]
    TooManyRequests {
        /// What is full.
        detail: String,
        /// Seconds (sent as `Retry-After`).
        retry_after: u64,
    },
    /// 503: shutting down or not ready.
    #[error("{0}")]
    Unavailable(String),
    /// 504: the run hit its wall-clock limit and was stopped (the detail names the limit).
    #[error("{0}")]
    TimeLimit(String),
    /// 500: logged, never shown.
    #[error("internal error; the server log has the details under this response's x-request-id")]
    Internal(String),
}

/// `detail`, prefixed with `field: ` unless it already starts with the field's name.
fn field_first(field: Option<&str>, detail: &str) -> String {
    match field {
        Some(f) if !detail.starts_with(f) => format!("{f}: {detail}"),
        _ => detail.to_string(),
    }
}

/// The JSON body of a problem response.
#[derive(Debug, serde::Serialize)]
struct Problem<'a> {
    #[serde(rename = "type")]
    kind: String,
    title: &'a str,
    status: u16,
    detail: String,
    #[serde(skip_serializing_if = "Option::is_none")]
    field: Option<&'a str>,
}

impl ApiError {
    /// A 422 naming `field`.
    pub fn invalid(field: impl Into<String>, detail: impl Into<String>) -> ApiError {
        ApiError::Unprocessable {
            field: Some(field.into()),
            detail: detail.into(),
        }
    }

    /// The HTTP status.
    pub fn status(&self) -> StatusCode {
        match self {
            ApiError::BadRequest(_) => StatusCode::BAD_REQUEST,
            ApiError::Unauthorized => StatusCode::UNAUTHORIZED,
            ApiError::NotFound(_) | ApiError::NoRoute => StatusCode::NOT_FOUND,
            ApiError::MethodNotAllowed => StatusCode::METHOD_NOT_ALLOWED,
            ApiError::Conflict { .. } => StatusCode::CONFLICT,
            ApiError::TooLarge { .. } => StatusCode::PAYLOAD_TOO_LARGE,
            ApiError::UnsupportedMediaType(_) => StatusCode::UNSUPPORTED_MEDIA_TYPE,
            ApiError::RangeNotSatisfiable { .. } => StatusCode::RANGE_NOT_SATISFIABLE,
            ApiError::Unprocessable { .. } => StatusCode::UNPROCESSABLE_ENTITY,
            ApiError::TooManyRequests { .. } => StatusCode::TOO_MANY_REQUESTS,
            ApiError::Unavailable(_) => StatusCode::SERVICE_UNAVAILABLE,
            ApiError::TimeLimit(_) => StatusCode::GATEWAY_TIMEOUT,
            ApiError::Internal(_) => StatusCode::INTERNAL_SERVER_ERROR,
        }
    }

    /// The problem type's slug (`urn:qemd:problem:<slug>`).
    fn slug(&self) -> &'static str {
        match self {
            ApiError::BadRequest(_) => "bad-request",
            ApiError::Unauthorized => "unauthorized",
            ApiError::NotFound(_) => "not-found",
            ApiError::NoRoute => "no-route",
            ApiError::MethodNotAllowed => "method-not-allowed",
            ApiError::Conflict { .. } => "conflict",
            ApiError::TooLarge { .. } => "too-large",
            ApiError::UnsupportedMediaType(_) => "unsupported-media-type",
            ApiError::RangeNotSatisfiable { .. } => "range-not-satisfiable",
            ApiError::Unprocessable { field: Some(_), .. } => "invalid-parameter",
            ApiError::Unprocessable { field: None, .. } => "invalid-content",
            ApiError::TooManyRequests { .. } => "too-many-requests",
            ApiError::Unavailable(_) => "unavailable",
            ApiError::TimeLimit(_) => "time-limit",
            ApiError::Internal(_) => "internal",
        }
    }
}

impl From<JobsError> for ApiError {
    fn from(e: JobsError) -> Self {
        match e {
            JobsError::NoSuch(what) => ApiError::NotFound(format!("no such {what}")),
            JobsError::Invalid { field, detail } => ApiError::Unprocessable {
                field: Some(field),
                detail,
            },
            JobsError::Rejected(d) => ApiError::Unprocessable {
                field: None,
                detail: d,
            },
            JobsError::Run(e) if e.is_input_fault() => ApiError::Unprocessable {
                field: None,
                detail: e.to_string(),
            },
            JobsError::Run(e) => ApiError::Internal(e.to_string()),
            JobsError::UnsupportedFormat(d) => ApiError::UnsupportedMediaType(d),
            JobsError::OverLimit { limit } => ApiError::TooLarge { limit },
            JobsError::WrongState { detail, offset } => ApiError::Conflict { detail, offset },
            JobsError::QueueFull => ApiError::TooManyRequests {
                detail: "the job queue is full; retry later".into(),
                retry_after: 5,
            },
            JobsError::Busy => ApiError::TooManyRequests {
                detail: "too many synchronous requests at once; retry shortly".into(),
                retry_after: 1,
            },
            JobsError::BodyRead(d) => ApiError::BadRequest(d),
            JobsError::ShuttingDown => ApiError::Unavailable("the server is shutting down".into()),
            e @ JobsError::TimeLimit { .. } => ApiError::TimeLimit(format!(
                "{e}; the run was stopped. Larger scans belong in a job (POST /v1/jobs)"
            )),
            e @ (JobsError::Db(_)
            | JobsError::Io { .. }
            | JobsError::Slurm(_)
            | JobsError::Internal(_)) => ApiError::Internal(e.to_string()),
        }
    }
}

/// The `Tus-Resumable` header sent with every upload response.
pub const TUS_RESUMABLE: (&str, &str) = ("tus-resumable", "1.0.0");

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        let status = self.status();
        if let ApiError::Internal(msg) = &self {
            // Logged inside the request span: the line carries the request id.
            tracing::error!(error = %msg, "internal error");
        }
        let field = match &self {
            ApiError::Unprocessable { field, .. } => field.as_deref(),
            _ => None,
        };
        let body = Problem {
            kind: format!("urn:qemd:problem:{}", self.slug()),
            title: status.canonical_reason().unwrap_or("Error"),
            status: status.as_u16(),
            detail: self.to_string(),
            field,
        };
        let json = serde_json::to_vec(&body).unwrap_or_else(|_| b"{}".to_vec());
        let mut headers = HeaderMap::new();
        headers.insert(
            header::CONTENT_TYPE,
            HeaderValue::from_static("application/problem+json"),
        );
        match &self {
            ApiError::Unauthorized => {
                headers.insert(
                    header::WWW_AUTHENTICATE,
                    HeaderValue::from_static("Bearer realm=\"qemd\""),
                );
            }
            ApiError::TooManyRequests { retry_after, .. } => {
                headers.insert(header::RETRY_AFTER, HeaderValue::from(*retry_after));
            }
            ApiError::RangeNotSatisfiable { size } => {
                if let Ok(v) = HeaderValue::from_str(&format!("bytes */{size}")) {
                    headers.insert(header::CONTENT_RANGE, v);
                }
            }
            ApiError::Conflict {
                offset: Some(o), ..
            } => {
                headers.insert(
                    HeaderName::from_static("upload-offset"),
                    HeaderValue::from(*o),
                );
                headers.insert(
                    HeaderName::from_static(TUS_RESUMABLE.0),
                    HeaderValue::from_static(TUS_RESUMABLE.1),
                );
            }
            _ => {}
        }
        (status, headers, json).into_response()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn problem_shape_and_headers() {
        let r = ApiError::invalid("params.knn", "must be between 3 and 1024").into_response();
        assert_eq!(r.status(), StatusCode::UNPROCESSABLE_ENTITY);
        assert_eq!(
            r.headers()[header::CONTENT_TYPE],
            "application/problem+json"
        );
        let body = axum::body::to_bytes(r.into_body(), 1 << 16).await.unwrap();
        let v: serde_json::Value = serde_json::from_slice(&body).unwrap();
        assert_eq!(v["status"], 422);
        assert_eq!(v["field"], "params.knn");
        assert_eq!(v["type"], "urn:qemd:problem:invalid-parameter");
        assert!(v["detail"].as_str().unwrap().starts_with("params.knn:"));

        let r = ApiError::Internal("/secret/path: disk on fire".into()).into_response();
        assert_eq!(r.status(), StatusCode::INTERNAL_SERVER_ERROR);
        let body = axum::body::to_bytes(r.into_body(), 1 << 16).await.unwrap();
        let text = String::from_utf8(body.to_vec()).unwrap();
        assert!(!text.contains("secret") && !text.contains("fire"), "{text}");

        let r = ApiError::from(JobsError::QueueFull).into_response();
        assert_eq!(r.status(), StatusCode::TOO_MANY_REQUESTS);
        assert_eq!(r.headers()[header::RETRY_AFTER], "5");
        let r = ApiError::RangeNotSatisfiable { size: 10 }.into_response();
        assert_eq!(r.headers()[header::CONTENT_RANGE], "bytes */10");
        let r = ApiError::Unauthorized.into_response();
        assert!(r.headers().contains_key(header::WWW_AUTHENTICATE));
    }
}
