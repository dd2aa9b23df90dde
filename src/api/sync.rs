//! `POST /v1/denoise`: synchronous denoising of a small scan, for robotics back ends.
//!
//! The body is the whole file (at most `max_sync_size`); its format comes from `?format=`, else
//! the content type (`application/vnd.las`, …), else the content itself. Parameters are query
//! parameters with the CLI's names (`?knn=16&iterations=2&outliers=classify`), plus
//! `output_format`. The answer is the denoised file, with `x-qemd-points-in`,
//! `x-qemd-points-out`, `x-qemd-moved` and `x-qemd-wall-ms` headers.
//!
//! Nothing is written to the job store; the CPU work runs on the synchronous path's rayon pool.
//! Beyond `sync_concurrency` requests in flight the answer is 429 with `Retry-After`.

use axum::Extension;
use axum::body::Body;
use axum::extract::{RawQuery, State};
use axum::http::{HeaderMap, HeaderName, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use serde_json::{Map, Value};

use super::auth::Tenant;
use super::jobs::params_from;
use super::{ApiError, AppState, format_of_media_type, media_type, media_type_of, read_limited};
use crate::io::sniff::{SNIFF_LEN, sniff};
use crate::jobs::{SyncRequest, canonical_format};

/// Parameters whose values are numbers (query strings carry text).
const NUMERIC: [&str; 11] = [
    "rings",
    "knn",
    "filter",
    "updates",
    "eps",
    "lambda",
    "mu",
    "sigma_r",
    "iterations",
    "outlier_alpha",
    "max_move",
];

/// Parameters whose values are booleans (`true` or `false`).
const BOOLEAN: [&str; 3] = ["paper", "volume", "guard"];

/// A query string split: input format, output format, denoising parameters (JSON object).
type Split = (Option<String>, Option<String>, Map<String, Value>);

/// Splits a query string into the format choices and a JSON object of denoising parameters.
fn split_query(query: Option<&str>) -> Result<Split, ApiError> {
    let pairs: Vec<(String, String)> = match query {
        None => Vec::new(),
        Some(q) => serde_urlencoded::from_str(q)
            .map_err(|e| ApiError::BadRequest(format!("query string: {e}")))?,
    };
    let (mut format, mut output, mut map) = (None, None, Map::new());
    for (k, v) in pairs {
        let value = if NUMERIC.contains(&k.as_str()) {
            match serde_json::from_str::<serde_json::Number>(&v) {
                Ok(n) => Value::Number(n),
                Err(_) => {
                    return Err(ApiError::invalid(
                        k.as_str(),
                        format!("`{v}` is not a number"),
                    ));
                }
            }
        } else if BOOLEAN.contains(&k.as_str()) {
            match v.as_str() {
                "true" => Value::Bool(true),
                "false" => Value::Bool(false),
                _ => {
                    return Err(ApiError::invalid(
                        k.as_str(),
                        format!("`{v}` is not `true` or `false`"),
                    ));
                }
            }
        } else {
            Value::String(v)
        };
        let dup = match k.as_str() {
            "format" => format.replace(value.as_str().unwrap_or_default().to_string()),
            "output_format" => output.replace(value.as_str().unwrap_or_default().to_string()),
            _ => map.insert(k.clone(), value).map(|_| String::new()),
        };
        if dup.is_some() {
            return Err(ApiError::invalid(k, "given twice"));
        }
    }
    Ok((format, output, map))
}

/// `POST /v1/denoise`.
pub async fn denoise(
    State(state): State<AppState>,
    Extension(Tenant(_tenant)): Extension<Tenant>,
    RawQuery(query): RawQuery,
    headers: HeaderMap,
    body: Body,
) -> Result<Response, ApiError> {
    let (format, output_format, map) = split_query(query.as_deref())?;
    let (params, outliers, outlier_alpha) = params_from(map, None, None, None, "")?;
    let from_type = format_of_media_type(&headers).ok_or_else(|| {
        ApiError::UnsupportedMediaType(format!(
            "content type `{}` is not a scan; send the file as application/octet-stream",
            media_type(&headers).unwrap_or_default()
        ))
    })?;
    let bytes = read_limited(&headers, body, state.settings.max_sync_size).await?;
    let format = match format.or(from_type.map(str::to_string)) {
        Some(f) => canonical_format(&f).ok_or_else(|| {
            ApiError::UnsupportedMediaType(format!(
                "unknown format `{f}` (expected ply, obj, off, xyz, txt, pts, bin, pcd, las or laz)"
            ))
        })?,
        None => sniff(&bytes[..bytes.len().min(SNIFF_LEN)])
            .map(str::to_string)
            .ok_or_else(|| {
                ApiError::UnsupportedMediaType(
                    "cannot tell the format from the content; name it with ?format=".into(),
                )
            })?,
    };
    let out = state
        .jobs
        .denoise_now(
            bytes,
            SyncRequest {
                format,
                params,
                outliers,
                outlier_alpha,
                output_format,
            },
        )
        .await
        .map_err(|e| match ApiError::from(e) {
            // Query parameters carry the bare names (`knn`, not `params.knn`).
            ApiError::Unprocessable {
                field: Some(f),
                detail,
            } => ApiError::Unprocessable {
                field: Some(f.strip_prefix("params.").unwrap_or(&f).to_string()),
                detail,
            },
            other => other,
        })?;
    let mut r = (StatusCode::OK, out.bytes).into_response();
    let h = r.headers_mut();
    h.insert(
        header::CONTENT_TYPE,
        HeaderValue::from_static(media_type_of(&out.format)),
    );
    let report = &out.report;
    for (name, value) in [
        ("x-qemd-format", out.format.clone()),
        ("x-qemd-points-in", report.points_in.to_string()),
        ("x-qemd-points-out", report.points_out.to_string()),
        ("x-qemd-moved", report.stats.moved.to_string()),
        ("x-qemd-wall-ms", format!("{:.1}", report.wall_s * 1e3)),
    ] {
        if let Ok(v) = HeaderValue::from_str(&value) {
            h.insert(HeaderName::from_static(name), v);
        }
    }
    Ok(r)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn query_parameters() {
        let (f, o, m) = split_query(Some(
            "format=ply&knn=8&solve=plain&output_format=xyz&eps=0.5",
        ))
        .unwrap();
        assert_eq!(f.as_deref(), Some("ply"));
        assert_eq!(o.as_deref(), Some("xyz"));
        assert_eq!(m["knn"], 8);
        assert_eq!(m["eps"], 0.5);
        assert_eq!(m["solve"], "plain");
        assert!(matches!(
            split_query(Some("knn=many")),
            Err(ApiError::Unprocessable { field: Some(f), .. }) if f == "knn"
        ));
        assert!(split_query(Some("knn=3&knn=4")).is_err());
        let (_, _, m) = split_query(Some("knnn=3")).unwrap();
        assert!(matches!(
            params_from(m, None, None, None, ""),
            Err(ApiError::Unprocessable { field: Some(f), .. }) if f == "knnn"
        ));
    }
}
