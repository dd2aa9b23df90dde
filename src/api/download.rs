//! `GET /v1/jobs/{id}/result`: the result file, streamed from disk.
//!
//! * `Content-Length`, `Accept-Ranges: bytes`, a strong `ETag` (the result's SHA-256) and
//!   `Content-Disposition` with a file name.
//! * `If-None-Match` with the ETag (or `*`) answers 304.
//! * One `Range: bytes=a-b` / `a-` / `-n` answers 206 with `Content-Range`; a range starting
//!   beyond the end answers 416 (`Content-Range: bytes */size`). Several ranges, other units and
//!   malformed headers are ignored (200 with the whole file, as RFC 9110 allows), and so is a
//!   `Range` whose `If-Range` does not match the current ETag.
//! * `HEAD` answers the same headers without the body.

use axum::Extension;
use axum::body::Body;
use axum::extract::{Path, State};
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use tokio::io::{AsyncReadExt, AsyncSeekExt};
use tokio_util::io::ReaderStream;

use super::auth::Tenant;
use super::{ApiError, AppState, media_type_of};

/// What a `Range` header asks of a file of a given size.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RangeRequest {
    /// The whole file (no range, or one to ignore).
    Full,
    /// Bytes `start..=end`.
    Part(u64, u64),
    /// Nothing of the file can satisfy it.
    Unsatisfiable,
}

/// Interprets a `Range` header value for a file of `size` bytes.
pub fn parse_range(value: &str, size: u64) -> RangeRequest {
    let Some((unit, spec)) = value.trim().split_once('=') else {
        return RangeRequest::Full;
    };
    if !unit.trim().eq_ignore_ascii_case("bytes") || spec.contains(',') {
        return RangeRequest::Full;
    }
    let Some((a, b)) = spec.trim().split_once('-') else {
        return RangeRequest::Full;
    };
    let (a, b) = (a.trim(), b.trim());
    let num = |s: &str| {
        (!s.is_empty() && s.bytes().all(|c| c.is_ascii_digit()))
            .then(|| s.parse::<u64>().ok())
            .flatten()
    };
    match (a.is_empty(), b.is_empty()) {
        // bytes=-n: the last n bytes.
        (true, false) => match num(b) {
            Some(0) => RangeRequest::Unsatisfiable,
            Some(_) if size == 0 => RangeRequest::Unsatisfiable,
            Some(n) => RangeRequest::Part(size.saturating_sub(n), size - 1),
            None => RangeRequest::Full,
        },
        // bytes=a-
        (false, true) => match num(a) {
            Some(s) if s >= size => RangeRequest::Unsatisfiable,
            Some(s) => RangeRequest::Part(s, size - 1),
            None => RangeRequest::Full,
        },
        (false, false) => match (num(a), num(b)) {
            (Some(s), Some(e)) if s <= e => {
                if s >= size {
                    RangeRequest::Unsatisfiable
                } else {
                    RangeRequest::Part(s, e.min(size - 1))
                }
            }
            _ => RangeRequest::Full,
        },
        (true, true) => RangeRequest::Full,
    }
}

/// True when an `If-None-Match` value matches `etag`.
pub(crate) fn matches_etag(value: &str, etag: &str) -> bool {
    value
        .split(',')
        .map(|t| t.trim().trim_start_matches("W/"))
        .any(|t| t == "*" || t == etag)
}

/// `attachment` named `name` (RFC 6266): an ASCII `filename` for every client and, when the
/// name is not plain ASCII, `filename*` with its UTF-8 bytes percent-encoded (RFC 8187).
fn disposition(name: &str) -> String {
    let ascii: String = name
        .chars()
        .map(|c| match c {
            ' '..='~' if c != '"' && c != '\\' => c,
            _ => '_',
        })
        .collect();
    if ascii == name {
        return format!("attachment; filename=\"{name}\"");
    }
    let encoded: String = name
        .bytes()
        .map(|b| match b {
            b'A'..=b'Z' | b'a'..=b'z' | b'0'..=b'9' | b'.' | b'-' | b'_' => (b as char).to_string(),
            b => format!("%{b:02X}"),
        })
        .collect();
    format!("attachment; filename=\"{ascii}\"; filename*=UTF-8''{encoded}")
}

/// `GET` and `HEAD /v1/jobs/{id}/result`.
pub async fn result(
    State(state): State<AppState>,
    Extension(Tenant(tenant)): Extension<Tenant>,
    Path(id): Path<String>,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    let r = state.jobs.result(&tenant, &id).await?;
    let etag = format!("\"{}\"", r.sha256);
    let text = |name| {
        headers
            .get(name)
            .and_then(|v: &HeaderValue| v.to_str().ok())
    };
    let mut common = HeaderMap::new();
    let mut put = |name: header::HeaderName, value: String| {
        if let Ok(v) = HeaderValue::from_str(&value) {
            common.insert(name, v);
        }
    };
    put(header::ETAG, etag.clone());
    put(header::ACCEPT_RANGES, "bytes".into());
    put(header::CACHE_CONTROL, "private, no-cache".into());
    if text(header::IF_NONE_MATCH).is_some_and(|v| matches_etag(v, &etag)) {
        return Ok((StatusCode::NOT_MODIFIED, common).into_response());
    }
    put(header::CONTENT_TYPE, media_type_of(r.format).into());
    put(header::CONTENT_DISPOSITION, disposition(&r.filename));
    let range_applies = text(header::IF_RANGE).is_none_or(|v| v.trim() == etag);
    let range = match text(header::RANGE) {
        Some(v) if range_applies => parse_range(v, r.size),
        _ => RangeRequest::Full,
    };
    let (status, start, len) = match range {
        RangeRequest::Full => (StatusCode::OK, 0, r.size),
        RangeRequest::Part(s, e) => {
            put(header::CONTENT_RANGE, format!("bytes {s}-{e}/{}", r.size));
            (StatusCode::PARTIAL_CONTENT, s, e - s + 1)
        }
        RangeRequest::Unsatisfiable => return Err(ApiError::RangeNotSatisfiable { size: r.size }),
    };
    put(header::CONTENT_LENGTH, len.to_string());
    let mut file = tokio::fs::File::open(&r.path)
        .await
        .map_err(|e| ApiError::Internal(format!("open result {}: {e}", r.path.display())))?;
    if start > 0 {
        file.seek(std::io::SeekFrom::Start(start))
            .await
            .map_err(|e| ApiError::Internal(format!("seek result: {e}")))?;
    }
    let body = Body::from_stream(ReaderStream::with_capacity(file.take(len), 1 << 16));
    Ok((status, common, body).into_response())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ranges() {
        use RangeRequest::*;
        assert_eq!(parse_range("bytes=0-9", 100), Part(0, 9));
        assert_eq!(parse_range("bytes=90-200", 100), Part(90, 99));
        assert_eq!(parse_range("bytes=95-", 100), Part(95, 99));
        assert_eq!(parse_range("bytes=-10", 100), Part(90, 99));
        assert_eq!(parse_range("bytes=-500", 100), Part(0, 99));
        assert_eq!(parse_range("bytes=100-", 100), Unsatisfiable);
        assert_eq!(parse_range("bytes=200-300", 100), Unsatisfiable);
        assert_eq!(parse_range("bytes=-0", 100), Unsatisfiable);
        assert_eq!(parse_range("bytes=0-1,5-6", 100), Full);
        assert_eq!(parse_range("items=0-1", 100), Full);
        assert_eq!(parse_range("bytes=5-1", 100), Full);
        assert_eq!(parse_range("bytes=x-1", 100), Full);
        assert_eq!(parse_range("bytes=-", 100), Full);
        assert_eq!(parse_range("bytes=+1-2", 100), Full);
        assert!(matches_etag("\"a\", \"b\"", "\"b\""));
        assert!(matches_etag("*", "\"b\""));
        assert!(matches_etag("W/\"b\"", "\"b\""));
        assert!(!matches_etag("\"a\"", "\"b\""));
    }
}
