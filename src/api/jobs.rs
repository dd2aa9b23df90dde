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
//! Only `input` is required. `params` is the parameter spec ([`SpecOverlay`]: the CLI's names
//! in snake case, `paper` for `--paper`, `outliers` and `outlier_alpha`); `method`, `outliers`
//! and `outlier_alpha` are also accepted at the top level. Defaults and validation are the
//! spec's, as on the command line. Any bad field answers 422 naming it (`params.knn`,
//! `output_format`, `input`, …).

use axum::Extension;
use axum::body::Body;
use axum::extract::{Path, RawQuery, State};
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use serde_json::{Map, Value, json};

use super::auth::Tenant;
use super::uploads::parse_query;
use super::{ApiError, AppState, media_type, read_limited, timestamp};
use crate::denoise::Method;
use crate::io::Format;
use crate::jobs::{JobInfo, JobRequest, Status};
use crate::pipeline::{OutlierMode, SpecOverlay};

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
    output_format: Option<Format>,
}

/// The parameter choices of a request: the `params` object (the spec's names, [`SpecOverlay`])
/// under the choices given at the top level (`method`, `outliers`, `outlier_alpha`); a field
/// both give with different values is refused. Field errors name `prefix.field`.
pub(crate) fn overlay_from(
    params: Map<String, Value>,
    top: SpecOverlay,
    prefix: &str,
) -> Result<SpecOverlay, ApiError> {
    let inner: SpecOverlay = from_value(Value::Object(params), prefix)?;
    top.merge(inner).map_err(|f| {
        ApiError::invalid(
            f,
            format!("differs between the top level and {prefix}; give it once"),
        )
    })
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
            json!({
                "href": rhref,
                "size": size,
                "sha256": sha,
                "format": r.spec.output_format,
                "filename": r.spec.result_filename(&r.id),
            })
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
        "input_filename": r.spec.input_filename,
        "params": r.spec.denoise.params,
        "outliers": r.spec.denoise.outliers,
        "outlier_alpha": r.spec.denoise.outlier_alpha,
        "output_format": r.spec.output_format,
        "tiled": r.spec.tile_points.is_some(),
        "executor": r.spec.executor.name(),
        "slurm": r.slurm.as_ref().map(|s| json!({
            "jobs": s.jobs,
            "earlier": s.earlier,
            "resubmits": s.resubmits,
        })),
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

/// `bytes` as a JSON value, refusing an object that names a key twice (issue 51: the last one
/// won silently; RFC 8259 leaves duplicates to the parser, and a request that says two things
/// is refused as a flag given twice is).
fn strict_json(bytes: &[u8]) -> Result<Value, serde_json::Error> {
    use serde::de::{DeserializeSeed, Deserializer, Error as _, MapAccess, SeqAccess, Visitor};

    struct Strict;

    impl<'de> DeserializeSeed<'de> for Strict {
        type Value = Value;
        fn deserialize<D: Deserializer<'de>>(self, d: D) -> Result<Value, D::Error> {
            d.deserialize_any(self)
        }
    }

    impl<'de> Visitor<'de> for Strict {
        type Value = Value;
        fn expecting(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
            f.write_str("a JSON value")
        }
        fn visit_bool<E>(self, v: bool) -> Result<Value, E> {
            Ok(Value::Bool(v))
        }
        fn visit_i64<E>(self, v: i64) -> Result<Value, E> {
            Ok(Value::from(v))
        }
        fn visit_u64<E>(self, v: u64) -> Result<Value, E> {
            Ok(Value::from(v))
        }
        fn visit_f64<E>(self, v: f64) -> Result<Value, E> {
            Ok(Value::from(v))
        }
        fn visit_str<E>(self, v: &str) -> Result<Value, E> {
            Ok(Value::String(v.to_string()))
        }
        fn visit_string<E>(self, v: String) -> Result<Value, E> {
            Ok(Value::String(v))
        }
        fn visit_unit<E>(self) -> Result<Value, E> {
            Ok(Value::Null)
        }
        fn visit_seq<A: SeqAccess<'de>>(self, mut a: A) -> Result<Value, A::Error> {
            let mut v = Vec::new();
            while let Some(x) = a.next_element_seed(Strict)? {
                v.push(x);
            }
            Ok(Value::Array(v))
        }
        fn visit_map<A: MapAccess<'de>>(self, mut a: A) -> Result<Value, A::Error> {
            let mut m = serde_json::Map::new();
            while let Some(k) = a.next_key::<String>()? {
                if m.contains_key(&k) {
                    return Err(A::Error::custom(format!("the key `{k}` appears twice")));
                }
                let v = a.next_value_seed(Strict)?;
                m.insert(k, v);
            }
            Ok(Value::Object(m))
        }
    }

    let mut d = serde_json::Deserializer::from_slice(bytes);
    let v = Strict.deserialize(&mut d)?;
    d.end()?;
    Ok(v)
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
    let value = strict_json(&bytes)
        .map_err(|e| ApiError::BadRequest(format!("the body is not valid JSON: {e}")))?;
    if !value.is_object() {
        return Err(ApiError::BadRequest(
            "the body must be a JSON object".into(),
        ));
    }
    let s: Submission = from_value(value, "")?;
    let top = SpecOverlay {
        method: s.method,
        outliers: s.outliers,
        outlier_alpha: s.outlier_alpha,
        ..SpecOverlay::default()
    };
    let spec = overlay_from(s.params.unwrap_or_default(), top, "params")?;
    let row = state
        .jobs
        .submit(
            &tenant,
            JobRequest {
                input: s.input,
                spec,
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
    let (limit, offset) = super::page_of(q.limit, q.offset)?;
    let (rows, total) = state.jobs.list(&tenant, status, limit, offset).await?;
    let filter = status.map_or(String::new(), |s| format!("&status={}", s.as_str()));
    let jobs = rows.iter().map(view).collect();
    Ok(super::page_response(
        ("/v1/jobs", &filter),
        "jobs",
        jobs,
        (limit, offset),
        total,
    ))
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
        let none = SpecOverlay::default;
        let o = overlay_from(
            map(json!({"knn": 8, "outliers": "classify", "outlier_alpha": 3.0})),
            none(),
            "params",
        )
        .unwrap();
        assert_eq!(o.knn, Some(8));
        assert_eq!(o.outliers, Some(OutlierMode::Classify));
        assert_eq!(o.outlier_alpha, Some(3.0));
        let top = SpecOverlay {
            method: Some(Method::Bilateral),
            ..none()
        };
        let o = overlay_from(Map::new(), top.clone(), "params").unwrap();
        assert_eq!(o.method, Some(Method::Bilateral));
        assert!(matches!(
            overlay_from(map(json!({"method": "qem"})), top, "params"),
            Err(ApiError::Unprocessable { field: Some(f), .. }) if f == "method"
        ));
        let err = |v: Value| match overlay_from(map(v), none(), "params") {
            Err(ApiError::Unprocessable { field, .. }) => field.unwrap(),
            other => panic!("{other:?}"),
        };
        assert_eq!(err(json!({"knn": "many"})), "params.knn");
        assert_eq!(err(json!({"knnn": 3})), "params.knnn");
        assert_eq!(err(json!({"solve": "magic"})), "params.solve");
        assert_eq!(err(json!({"outliers": "maybe"})), "params.outliers");
    }
}
