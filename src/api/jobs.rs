//! `/v1/jobs`: submit, inspect, list and dismiss denoising jobs.
//!
//! The submission body:
//!
//! ```json
//! {"input": "<upload id>", "method": "qem",
//!  "params": {"knn": 16, "iterations": 2, "outliers": "classify", "outlier_alpha": 2.5},
//!  "output_format": "laz"}
//! ```
//!
//! Only `input` is required. `params` takes the CLI's names ([`crate::denoise::Params`]:
//! method, rings, knn, normals, planes, filter, updates, solve, eps, lambda, mu, sigma_r,
//! volume, iterations, and `paper` for `--paper`) plus `outliers` and `outlier_alpha` (also
//! accepted at the top level, like `method`). As on the command line,
//! `bilateral` defaults to three iterations. Any bad field answers 422 naming it
//! (`params.knn`, `output_format`, `input`, …).

use axum::Extension;
use axum::body::Body;
use axum::extract::{Path, RawQuery, State};
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use serde_json::{Map, Value, json};

use super::auth::Tenant;
use super::uploads::parse_query;
use super::{ApiError, AppState, media_type, read_limited, timestamp};
use crate::denoise::{Method, Params};
use crate::jobs::{JobInfo, JobRequest, Status};
use crate::pipeline::OutlierMode;

/// Largest job submission body.
const MAX_JSON: u64 = 64 << 10;

/// The name of the field a serde error is about: the path when it has one, else the field the
/// message quotes (`missing field `x``, `unknown field `x``).
pub(crate) fn field_of(path: &str, message: &str, prefix: &str) -> String {
    let quoted = message
        .split('`')
        .nth(1)
        .filter(|_| message.starts_with("missing field") || message.starts_with("unknown field"));
    let name = match (path, quoted) {
        (".", Some(q)) | ("", Some(q)) => q.to_string(),
        (".", None) | ("", None) => String::new(),
        (p, _) => p.to_string(),
    };
    match (prefix.is_empty(), name.is_empty()) {
        (true, _) => name,
        (false, true) => prefix.to_string(),
        (false, false) => format!("{prefix}.{name}"),
    }
}

/// Deserialises `value` into `T`, answering 422 naming the field (with `prefix`).
pub(crate) fn from_value<T: serde::de::DeserializeOwned>(
    value: Value,
    prefix: &str,
) -> Result<T, ApiError> {
    serde_path_to_error::deserialize(value).map_err(|e| {
        let path = e.path().to_string();
        let msg = e.inner().to_string();
        ApiError::invalid(field_of(&path, &msg, prefix), msg)
    })
}

#[derive(Debug, serde::Deserialize)]
#[serde(deny_unknown_fields)]
struct Submission {
    input: String,
    method: Option<Method>,
    params: Option<Map<String, Value>>,
    outliers: Option<OutlierMode>,
    outlier_alpha: Option<f64>,
    output_format: Option<String>,
}

/// Builds parameters from a `params` object (CLI names) and the top-level `method`: returns the
/// parameters, the outlier mode and threshold.
pub(crate) fn params_from(
    mut map: Map<String, Value>,
    method: Option<Method>,
    outliers: Option<OutlierMode>,
    outlier_alpha: Option<f64>,
    prefix: &str,
) -> Result<(Params, OutlierMode, Option<f64>), ApiError> {
    let dotted = |f: &str| {
        if prefix.is_empty() {
            f.to_string()
        } else {
            format!("{prefix}.{f}")
        }
    };
    let inner_outliers: Option<OutlierMode> = match map.remove("outliers") {
        Some(v) => Some(from_value(v, &dotted("outliers"))?),
        None => None,
    };
    let inner_alpha: Option<f64> = match map.remove("outlier_alpha") {
        Some(v) => Some(from_value(v, &dotted("outlier_alpha"))?),
        None => None,
    };
    let twice = |f: &str| ApiError::invalid(f, "given both at the top level and in params");
    if outliers.is_some() && inner_outliers.is_some() {
        return Err(twice("outliers"));
    }
    if outlier_alpha.is_some() && inner_alpha.is_some() {
        return Err(twice("outlier_alpha"));
    }
    // `paper: true` is the CLI's `--paper`: the paper's Algorithm 1 as the base, the other
    // fields still override it.
    let paper: bool = match map.remove("paper") {
        Some(v) => from_value(v, &dotted("paper"))?,
        None => false,
    };
    let has_iterations = map.contains_key("iterations");
    let has_method = map.contains_key("method");
    if paper {
        let Ok(Value::Object(mut base)) = serde_json::to_value(Params::paper()) else {
            return Err(ApiError::invalid(dotted("paper"), "cannot be applied"));
        };
        base.extend(map);
        map = base;
    }
    let mut params: Params = from_value(Value::Object(map), prefix)?;
    if let Some(m) = method {
        if has_method && params.method != m {
            return Err(ApiError::invalid(
                "method",
                "differs from params.method; give it once",
            ));
        }
        params.method = m;
    }
    if params.method == Method::Bilateral && !has_iterations {
        // As `qemd denoise --method bilateral`: Fleishman et al. iterate, the paper uses three.
        params.iterations = 3;
    }
    Ok((
        params,
        outliers.or(inner_outliers).unwrap_or_default(),
        outlier_alpha.or(inner_alpha),
    ))
}

/// The JSON view of a job.
pub(crate) fn view(info: &JobInfo) -> Value {
    let r = &info.row;
    let href = format!("/v1/jobs/{}", r.id);
    let mut links = vec![json!({"rel": "self", "href": href})];
    let result = match (r.status, r.result_size, &r.result_sha256) {
        (Status::Successful, Some(size), Some(sha)) => {
            let rhref = format!("{href}/result");
            links.push(json!({"rel": "results", "href": rhref}));
            json!({"href": rhref, "size": size, "sha256": sha, "format": r.spec.output_format})
        }
        _ => Value::Null,
    };
    let now = super::now_ms();
    let queued_s = r
        .started_ms
        .unwrap_or(if r.status == Status::Accepted {
            now
        } else {
            r.finished_ms.unwrap_or(now)
        })
        .saturating_sub(r.created_ms) as f64
        / 1e3;
    let run_s = r.started_ms.map(|s| {
        let end = match r.status {
            Status::Running => now,
            _ => r.finished_ms.unwrap_or(now),
        };
        end.saturating_sub(s).max(0) as f64 / 1e3
    });
    json!({
        "id": r.id,
        "type": "process",
        "processID": "denoise",
        "status": r.status.as_str(),
        "input": r.upload,
        "params": r.spec.params,
        "outliers": r.spec.outliers,
        "outlier_alpha": r.spec.outlier_alpha,
        "output_format": r.spec.output_format,
        "tiled": r.spec.tile_points.is_some(),
        "created": timestamp(r.created_ms),
        "started": r.started_ms.map(timestamp),
        "finished": r.finished_ms.map(timestamp),
        "progress": info.progress,
        "timings": {"queued_s": queued_s.max(0.0), "run_s": run_s},
        "report": r.report,
        "message": r.error,
        "result": result,
        "links": links,
    })
}

/// `POST /v1/jobs`.
pub async fn create(
    State(state): State<AppState>,
    Extension(Tenant(tenant)): Extension<Tenant>,
    headers: HeaderMap,
    body: Body,
) -> Result<Response, ApiError> {
    if media_type(&headers).as_deref() != Some("application/json") {
        return Err(ApiError::UnsupportedMediaType(
            "a job is submitted as application/json".into(),
        ));
    }
    let bytes = read_limited(&headers, body, MAX_JSON).await?;
    let value: Value = serde_json::from_slice(&bytes)
        .map_err(|e| ApiError::BadRequest(format!("the body is not JSON: {e}")))?;
    if !value.is_object() {
        return Err(ApiError::BadRequest(
            "the body must be a JSON object".into(),
        ));
    }
    let s: Submission = from_value(value, "")?;
    let (params, outliers, outlier_alpha) = params_from(
        s.params.unwrap_or_default(),
        s.method,
        s.outliers,
        s.outlier_alpha,
        "params",
    )?;
    let row = state
        .jobs
        .submit(
            &tenant,
            JobRequest {
                input: s.input,
                params,
                outliers,
                outlier_alpha,
                output_format: s.output_format,
            },
        )
        .await?;
    let info = state.jobs.job(&tenant, &row.id).await?;
    let mut r = (StatusCode::CREATED, axum::Json(view(&info))).into_response();
    if let Ok(v) = HeaderValue::from_str(&format!("/v1/jobs/{}", row.id)) {
        r.headers_mut().insert(header::LOCATION, v);
    }
    Ok(r)
}

/// `GET /v1/jobs/{id}`.
pub async fn status(
    State(state): State<AppState>,
    Extension(Tenant(tenant)): Extension<Tenant>,
    Path(id): Path<String>,
) -> Result<Response, ApiError> {
    let info = state.jobs.job(&tenant, &id).await?;
    Ok(axum::Json(view(&info)).into_response())
}

/// `DELETE /v1/jobs/{id}`: cancels (if running) and dismisses; the files are removed.
pub async fn dismiss(
    State(state): State<AppState>,
    Extension(Tenant(tenant)): Extension<Tenant>,
    Path(id): Path<String>,
) -> Result<Response, ApiError> {
    let info = state.jobs.dismiss(&tenant, &id).await?;
    Ok(axum::Json(view(&info)).into_response())
}

#[derive(Debug, Default, serde::Deserialize)]
#[serde(deny_unknown_fields)]
struct ListQuery {
    status: Option<String>,
    limit: Option<u64>,
    offset: Option<u64>,
}

/// Default and largest page size of `GET /v1/jobs`.
const PAGE: (u64, u64) = (50, 1000);

/// `GET /v1/jobs?status=&limit=&offset=`.
pub async fn list(
    State(state): State<AppState>,
    Extension(Tenant(tenant)): Extension<Tenant>,
    RawQuery(query): RawQuery,
) -> Result<Response, ApiError> {
    let q: ListQuery = parse_query(query)?;
    let status = match q.status.as_deref() {
        None => None,
        Some(s) => Some(Status::parse(s).ok_or_else(|| {
            ApiError::invalid(
                "status",
                format!("`{s}` is not one of accepted, running, successful, failed, dismissed"),
            )
        })?),
    };
    let limit = q.limit.unwrap_or(PAGE.0);
    if !(1..=PAGE.1).contains(&limit) {
        return Err(ApiError::invalid("limit", "must be between 1 and 1000"));
    }
    let offset = q.offset.unwrap_or(0);
    let (rows, total) = state.jobs.list(&tenant, status, limit, offset).await?;
    let page = |off: u64| {
        let mut href = format!("/v1/jobs?limit={limit}&offset={off}");
        if let Some(s) = status {
            href.push_str(&format!("&status={}", s.as_str()));
        }
        href
    };
    let mut links = vec![json!({"rel": "self", "href": page(offset)})];
    if offset + (rows.len() as u64) < total {
        links.push(json!({"rel": "next", "href": page(offset + rows.len() as u64)}));
    }
    if offset > 0 {
        links.push(json!({"rel": "prev", "href": page(offset.saturating_sub(limit))}));
    }
    Ok(axum::Json(json!({
        "jobs": rows.iter().map(view).collect::<Vec<_>>(),
        "total": total,
        "limit": limit,
        "offset": offset,
        "links": links,
    }))
    .into_response())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fields_are_named() {
        assert_eq!(field_of(".", "missing field `input`", ""), "input");
        assert_eq!(
            field_of(".", "unknown field `knnn`, expected one of", "params"),
            "params.knnn"
        );
        assert_eq!(field_of("knn", "invalid type", "params"), "params.knn");
        assert_eq!(field_of(".", "invalid type", "params"), "params");
    }

    #[test]
    fn params_with_cli_names() {
        let map = |v: Value| v.as_object().unwrap().clone();
        let (p, o, a) = params_from(
            map(json!({"knn": 8, "outliers": "classify", "outlier_alpha": 3.0})),
            None,
            None,
            None,
            "params",
        )
        .unwrap();
        assert_eq!(p.knn, Some(8));
        assert_eq!(o, OutlierMode::Classify);
        assert_eq!(a, Some(3.0));
        let (p, _, _) =
            params_from(Map::new(), Some(Method::Bilateral), None, None, "params").unwrap();
        assert_eq!(p.iterations, 3);
        let err = |v: Value| match params_from(map(v), None, None, None, "params") {
            Err(ApiError::Unprocessable { field, .. }) => field.unwrap(),
            other => panic!("{other:?}"),
        };
        assert_eq!(err(json!({"knn": "many"})), "params.knn");
        assert_eq!(err(json!({"knnn": 3})), "params.knnn");
        assert_eq!(err(json!({"solve": "magic"})), "params.solve");
        assert_eq!(err(json!({"outliers": "maybe"})), "params.outliers");
    }
}
