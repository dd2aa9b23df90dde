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

use super::auth::Tenant;
use super::jobs::field_of;
use super::{ApiError, AppState, format_of_media_type, media_type, media_type_of, read_limited};
use crate::io::Format;
use crate::io::sniff::{SNIFF_LEN, sniff};
use crate::jobs::SyncRequest;
use crate::pipeline::SpecOverlay;
use axum::Extension;
use axum::body::Body;
use axum::extract::{RawQuery, State};
use axum::http::{HeaderMap, HeaderName, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};

/// A query string split: input format, output format, the parameter choices.
type Split = (Option<String>, Option<String>, SpecOverlay);

/// Splits a query string into the format choices and the parameter spec's choices, which
/// deserialise straight from the text (numbers, booleans and names parsed by their types, so
/// the accepted names and their types are the spec's own).
fn split_query(query: Option<&str>) -> Result<Split, ApiError> {
    let pairs: Vec<(String, String)> = match query {
        None => Vec::new(),
        Some(q) => serde_urlencoded::from_str(q)
            .map_err(|e| ApiError::BadRequest(format!("query string: {e}")))?,
    };
    let (mut format, mut output, mut rest) = (None, None, Vec::new());
    for (k, v) in pairs {
        let slot = match k.as_str() {
            "format" => &mut format,
            "output_format" => &mut output,
            _ => {
                rest.push((k, v));
                continue;
            }
        };
        if slot.replace(v).is_some() {
            return Err(ApiError::invalid(k, "given twice"));
        }
    }
    let text = serde_urlencoded::to_string(&rest)
        .map_err(|e| ApiError::BadRequest(format!("query string: {e}")))?;
    let pairs = serde_urlencoded::Deserializer::new(form_urlencoded::parse(text.as_bytes()));
    let spec: SpecOverlay = serde_path_to_error::deserialize(pairs).map_err(|e| {
        let msg = e.inner().to_string();
        let field = field_of(&e.path().to_string(), &msg, "");
        // serde names a repeated parameter in the message only.
        let field = match msg.strip_prefix("duplicate field `") {
            Some(rest) => rest.split('`').next().unwrap_or_default().to_string(),
            None => field,
        };
        ApiError::invalid(field, msg)
    })?;
    Ok((format, output, spec))
}

/// `POST /v1/denoise`.
pub async fn denoise(
    State(state): State<AppState>,
    Extension(Tenant(_tenant)): Extension<Tenant>,
    RawQuery(query): RawQuery,
    headers: HeaderMap,
    body: Body,
) -> Result<Response, ApiError> {
    let (format, output_format, spec) = split_query(query.as_deref())?;
    let from_type = format_of_media_type(&headers).ok_or_else(|| {
        ApiError::UnsupportedMediaType(format!(
            "content type `{}` is not a scan; send the file as application/octet-stream",
            media_type(&headers).unwrap_or_default()
        ))
    })?;
    let bytes = read_limited(&headers, body, state.settings.max_sync_size).await?;
    let output_format = match output_format {
        Some(name) => Some(
            Format::from_name(&name)
                .ok_or_else(|| ApiError::invalid("output_format", Format::unknown(&name)))?,
        ),
        None => None,
    };
    let format = match format {
        Some(name) => Format::from_name(&name)
            .ok_or_else(|| ApiError::UnsupportedMediaType(Format::unknown(&name)))?,
        None => match from_type {
            // LAS, LAZ and COPC share the media types: the header says which the body is, and
            // the answer keeps it (issue 51: a LAZ body sent as vnd.las came back as LAS).
            Some(f) if f.is_las() => sniff(&bytes[..bytes.len().min(SNIFF_LEN)])
                .filter(|s| s.is_las())
                .unwrap_or(f),
            Some(f) => f,
            None => sniff(&bytes[..bytes.len().min(SNIFF_LEN)]).ok_or_else(|| {
                ApiError::UnsupportedMediaType(
                    "cannot tell the format from the content; name it with ?format=".into(),
                )
            })?,
        },
    };
    let out = state
        .jobs
        .denoise_now(
            bytes,
            SyncRequest {
                format,
                spec,
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
        HeaderValue::from_static(media_type_of(out.format)),
    );
    let report = &out.report;
    for (name, value) in [
        ("x-qemd-format", out.format.to_string()),
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
            "format=ply&knn=8&solve=plain&output_format=xyz&eps=0.5&guard=false",
        ))
        .unwrap();
        assert_eq!(f.as_deref(), Some("ply"));
        assert_eq!(o.as_deref(), Some("xyz"));
        assert_eq!(m.knn, Some(8));
        assert_eq!(m.eps, Some(0.5));
        assert_eq!(m.solve, Some(crate::denoise::SolveKind::Plain));
        assert_eq!(m.guard, Some(false));
        let field = |q: &str| match split_query(Some(q)) {
            Err(ApiError::Unprocessable { field: Some(f), .. }) => f,
            other => panic!("{q}: {other:?}"),
        };
        assert_eq!(field("knn=many"), "knn");
        assert_eq!(field("knn=3&knn=4"), "knn");
        assert_eq!(field("format=ply&format=las"), "format");
        assert_eq!(field("knnn=3"), "knnn");
        assert_eq!(field("volume=maybe"), "volume");
    }

    #[test]
    fn issue10_the_422_names_every_spec_field() {
        // An unknown parameter's answer lists the accepted names: all of the spec's, outlier
        // options included (a hand-kept list used to leave those out).
        let Err(ApiError::Unprocessable { detail, .. }) = split_query(Some("knnn=3")) else {
            panic!("accepted");
        };
        for f in SpecOverlay::fields() {
            assert!(
                detail.contains(&format!("`{f}`")),
                "{f} missing from: {detail}"
            );
        }
        let (_, _, m) = split_query(Some("outliers=remove&outlier_alpha=1.5")).unwrap();
        assert_eq!(m.outliers, Some(crate::pipeline::OutlierMode::Remove));
        assert_eq!(m.outlier_alpha, Some(1.5));
    }
}
