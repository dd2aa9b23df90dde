//! `/v1/uploads`: one-request and resumable (tus 1.0 core + creation + termination) uploads.
//!
//! * `POST /v1/uploads` with a body: the body streams to disk (never held in memory), is hashed
//!   (SHA-256), its format sniffed (or taken from `?format=`, `?filename=` or the content type),
//!   and validated by opening it; 201 with the upload's id, size, sha256, format and point count.
//! * `POST /v1/uploads` with `Upload-Length: N` and no body: creates a resumable upload
//!   (201, `Location`, `Upload-Offset: 0`). The format hint may also come in tus
//!   `Upload-Metadata` (`filename`, `format`, base64 values).
//! * `PATCH /v1/uploads/{id}` with `Content-Type: application/offset+octet-stream` and
//!   `Upload-Offset` equal to the server's offset appends the body (204 with the new
//!   `Upload-Offset`); a wrong offset answers 409 with the server's. The last byte triggers
//!   hashing and validation. A finished upload that fails validation (415 when its format cannot
//!   be told, 422 when it is not a valid file) is kept with all its bytes: a PATCH with
//!   `?format=` (or `?filename=`), `Upload-Offset` at the full length and an empty body
//!   validates it again.
//! * `HEAD`/`GET /v1/uploads/{id}`: `Upload-Offset`, `Upload-Length` (and the JSON view).
//! * `DELETE /v1/uploads/{id}`: removes it (409 while a queued or running job reads it).

use axum::Extension;
use axum::body::Body;
use axum::extract::{Path, RawQuery, State};
use axum::http::{HeaderMap, HeaderName, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use serde_json::json;

use super::auth::Tenant;
use super::error::TUS_RESUMABLE;
use super::{ApiError, AppState, format_of_media_type, media_type, timestamp};
use crate::jobs::{FormatHint, Upload};

#[derive(Debug, Default, serde::Deserialize)]
#[serde(deny_unknown_fields)]
struct UploadQuery {
    format: Option<String>,
    filename: Option<String>,
}

/// Parses a query string into `T`; an unknown, repeated or ill-typed parameter answers 422
/// naming it, as the parameters of `/v1/denoise` and the fields of a job body do.
pub(crate) fn parse_query<T: serde::de::DeserializeOwned + Default>(
    q: Option<String>,
) -> Result<T, ApiError> {
    let Some(q) = q else {
        return Ok(T::default());
    };
    let pairs = serde_urlencoded::Deserializer::new(form_urlencoded::parse(q.as_bytes()));
    serde_path_to_error::deserialize(pairs).map_err(|e| {
        let msg = e.inner().to_string();
        let field = super::jobs::field_of(&e.path().to_string(), &msg, "");
        // serde names a repeated parameter in the message only.
        let field = match msg.strip_prefix("duplicate field `") {
            Some(rest) => rest.split('`').next().unwrap_or_default().to_string(),
            None => field,
        };
        ApiError::invalid(field, msg)
    })
}

fn header_u64(headers: &HeaderMap, name: &str) -> Result<Option<u64>, ApiError> {
    match headers.get(name) {
        None => Ok(None),
        Some(v) => v
            .to_str()
            .ok()
            .and_then(|s| s.trim().parse::<u64>().ok())
            .map(Some)
            .ok_or_else(|| ApiError::BadRequest(format!("{name} must be a non-negative integer"))),
    }
}

/// Decodes standard base64 (padding optional); `None` when malformed.
fn base64(s: &str) -> Option<Vec<u8>> {
    let mut out = Vec::new();
    let (mut acc, mut bits) = (0u32, 0u32);
    for c in s.trim().bytes().filter(|&c| c != b'=') {
        let v = match c {
            b'A'..=b'Z' => c - b'A',
            b'a'..=b'z' => c - b'a' + 26,
            b'0'..=b'9' => c - b'0' + 52,
            b'+' => 62,
            b'/' => 63,
            _ => return None,
        };
        acc = (acc << 6) | u32::from(v);
        bits += 6;
        if bits >= 8 {
            bits -= 8;
            out.push(((acc >> bits) & 0xff) as u8);
        }
    }
    Some(out)
}

/// The `filename` and `format` entries of a tus `Upload-Metadata` header.
fn metadata(headers: &HeaderMap) -> Result<FormatHint, ApiError> {
    let mut hint = FormatHint::default();
    let Some(v) = headers.get("upload-metadata") else {
        return Ok(hint);
    };
    let bad = || ApiError::BadRequest("Upload-Metadata must be `key base64, …`".into());
    let text = v.to_str().map_err(|_| bad())?;
    for pair in text.split(',').map(str::trim).filter(|p| !p.is_empty()) {
        let mut it = pair.split_whitespace();
        let key = it.next().ok_or_else(bad)?;
        let value = it
            .next()
            .map(base64)
            .unwrap_or(Some(Vec::new()))
            .ok_or_else(bad)?;
        let value = String::from_utf8(value).map_err(|_| bad())?;
        match key {
            "filename" => hint.filename = Some(value),
            "format" => hint.format = Some(value),
            _ => {}
        }
    }
    Ok(hint)
}

fn location(id: &str) -> String {
    format!("/v1/uploads/{id}")
}

/// The JSON view of an upload.
pub(crate) fn view(u: &Upload) -> serde_json::Value {
    json!({
        "id": u.id,
        "complete": u.complete,
        "size": u.size,
        "length": u.length,
        "offset": u.size,
        "sha256": u.sha256,
        "format": u.format,
        "filename": u.filename,
        "points": u.points,
        "faces": u.faces,
        "created": timestamp(u.created_ms),
        "links": [{"rel": "self", "href": location(&u.id)}],
    })
}

fn tus_headers(u: &Upload) -> Vec<(HeaderName, HeaderValue)> {
    let mut h = vec![
        (
            HeaderName::from_static(TUS_RESUMABLE.0),
            HeaderValue::from_static(TUS_RESUMABLE.1),
        ),
        (
            HeaderName::from_static("upload-offset"),
            HeaderValue::from(u.size),
        ),
        (header::CACHE_CONTROL, HeaderValue::from_static("no-store")),
    ];
    if let Some(l) = u.length {
        h.push((
            HeaderName::from_static("upload-length"),
            HeaderValue::from(l),
        ));
    }
    h
}

fn with_headers(
    status: StatusCode,
    h: Vec<(HeaderName, HeaderValue)>,
    body: Option<serde_json::Value>,
) -> Response {
    let mut r = match body {
        Some(b) => (status, axum::Json(b)).into_response(),
        None => status.into_response(),
    };
    for (k, v) in h {
        r.headers_mut().insert(k, v);
    }
    r
}

/// `POST /v1/uploads`.
pub async fn create(
    State(state): State<AppState>,
    Extension(Tenant(tenant)): Extension<Tenant>,
    RawQuery(query): RawQuery,
    headers: HeaderMap,
    body: Body,
) -> Result<Response, ApiError> {
    let q: UploadQuery = parse_query(query)?;
    let from_type = format_of_media_type(&headers).ok_or_else(|| {
        ApiError::UnsupportedMediaType(format!(
            "content type `{}` is not a scan; send the file as application/octet-stream",
            media_type(&headers).unwrap_or_default()
        ))
    })?;
    let mut hint = metadata(&headers)?;
    if q.format.is_some() {
        hint.format = q.format;
    }
    if q.filename.is_some() {
        hint.filename = q.filename;
    }
    if hint.format.is_none() {
        hint.format = from_type.map(|f| f.name().to_string());
    }
    crate::jobs::check_hint(&hint)?;
    let content_length = header_u64(&headers, "content-length")?;
    let upload = match header_u64(&headers, "upload-length")? {
        Some(length) => {
            if content_length.unwrap_or(0) != 0 {
                return Err(ApiError::BadRequest(
                    "a resumable upload is created with an empty body; send the bytes with PATCH"
                        .into(),
                ));
            }
            state.jobs.create_resumable(&tenant, length, hint).await?
        }
        None => {
            state
                .jobs
                .receive(&tenant, content_length, hint, body.into_data_stream())
                .await?
        }
    };
    let mut h = tus_headers(&upload);
    if let Ok(v) = HeaderValue::from_str(&location(&upload.id)) {
        h.push((header::LOCATION, v));
    }
    Ok(with_headers(StatusCode::CREATED, h, Some(view(&upload))))
}

/// `OPTIONS /v1/uploads`: tus discovery.
pub async fn options(State(state): State<AppState>) -> Response {
    let h = vec![
        (
            HeaderName::from_static(TUS_RESUMABLE.0),
            HeaderValue::from_static(TUS_RESUMABLE.1),
        ),
        (
            HeaderName::from_static("tus-version"),
            HeaderValue::from_static("1.0.0"),
        ),
        (
            HeaderName::from_static("tus-extension"),
            HeaderValue::from_static("creation,termination"),
        ),
        (
            HeaderName::from_static("tus-max-size"),
            HeaderValue::from(state.jobs.settings().max_upload_size),
        ),
    ];
    with_headers(StatusCode::NO_CONTENT, h, None)
}

/// `GET` and `HEAD /v1/uploads/{id}`.
pub async fn status(
    State(state): State<AppState>,
    Extension(Tenant(tenant)): Extension<Tenant>,
    Path(id): Path<String>,
) -> Result<Response, ApiError> {
    let u = state.jobs.upload(&tenant, &id).await?;
    Ok(with_headers(
        StatusCode::OK,
        tus_headers(&u),
        Some(view(&u)),
    ))
}

/// `GET /v1/uploads?limit=&offset=`: the tenant's uploads, newest first, with their file names
/// (a reloaded page lists them again).
pub async fn list(
    State(state): State<AppState>,
    Extension(Tenant(tenant)): Extension<Tenant>,
    RawQuery(query): RawQuery,
) -> Result<Response, ApiError> {
    let q: super::PageQuery = parse_query(query)?;
    let (limit, offset) = super::page_of(q.limit, q.offset)?;
    let (rows, total) = state.jobs.list_uploads(&tenant, limit, offset).await?;
    let uploads = rows.iter().map(view).collect();
    Ok(super::page_response(
        ("/v1/uploads", ""),
        "uploads",
        uploads,
        (limit, offset),
        total,
    ))
}

/// `PATCH /v1/uploads/{id}`: appends a chunk.
pub async fn patch(
    State(state): State<AppState>,
    Extension(Tenant(tenant)): Extension<Tenant>,
    Path(id): Path<String>,
    RawQuery(query): RawQuery,
    headers: HeaderMap,
    body: Body,
) -> Result<Response, ApiError> {
    if media_type(&headers).as_deref() != Some("application/offset+octet-stream") {
        return Err(ApiError::UnsupportedMediaType(
            "PATCH needs Content-Type: application/offset+octet-stream".into(),
        ));
    }
    let offset = header_u64(&headers, "upload-offset")?
        .ok_or_else(|| ApiError::BadRequest("PATCH needs an Upload-Offset header".into()))?;
    let q: UploadQuery = parse_query(query)?;
    let named = q.format.is_some() || q.filename.is_some();
    let hint = named.then_some(FormatHint {
        format: q.format,
        filename: q.filename,
    });
    let u = state
        .jobs
        .append(&tenant, &id, offset, hint, body.into_data_stream())
        .await?;
    Ok(with_headers(StatusCode::NO_CONTENT, tus_headers(&u), None))
}

/// `DELETE /v1/uploads/{id}`.
pub async fn delete(
    State(state): State<AppState>,
    Extension(Tenant(tenant)): Extension<Tenant>,
    Path(id): Path<String>,
) -> Result<Response, ApiError> {
    state.jobs.delete_upload(&tenant, &id).await?;
    Ok(with_headers(
        StatusCode::NO_CONTENT,
        vec![(
            HeaderName::from_static(TUS_RESUMABLE.0),
            HeaderValue::from_static(TUS_RESUMABLE.1),
        )],
        None,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn base64_and_metadata() {
        assert_eq!(base64("c2Nhbi5wbHk=").unwrap(), b"scan.ply");
        assert_eq!(base64("bGFz").unwrap(), b"las");
        assert!(base64("no!").is_none());
        let mut h = HeaderMap::new();
        h.insert(
            "upload-metadata",
            HeaderValue::from_static("filename c2Nhbi5wbHk=,format bGFz, is_confidential"),
        );
        let m = metadata(&h).unwrap();
        assert_eq!(m.filename.as_deref(), Some("scan.ply"));
        assert_eq!(m.format.as_deref(), Some("las"));
    }
}
