//! `/v1/jobs/{id}/preview*`: the bounded before/after preview of a successful job that the web
//! page draws ([`crate::jobs::preview`] builds it on first use).
//!
//! * `GET /v1/jobs/{id}/preview`: the description (JSON): kind, point counts, pairing, origin,
//!   bounding box, attributes, displacement quantiles, and links to the two files.
//! * `GET /v1/jobs/{id}/preview/before`, `…/after`: binary little-endian PLY (`application/x-ply`)
//!   with a strong `ETag`; `If-None-Match` answers 304.
//!
//! Scoped to the tenant like every `/v1` route: another tenant's job answers 404. A job that is
//! not successful answers 409.

use axum::Extension;
use axum::body::Body;
use axum::extract::{Path, State};
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use serde_json::json;
use tokio_util::io::ReaderStream;

use super::auth::Tenant;
use super::download::matches_etag;
use super::{ApiError, AppState};

/// `GET /v1/jobs/{id}/preview`.
pub async fn describe(
    State(state): State<AppState>,
    Extension(Tenant(tenant)): Extension<Tenant>,
    Path(id): Path<String>,
) -> Result<Response, ApiError> {
    let p = state.jobs.preview(&tenant, &id).await?;
    let mut v = serde_json::to_value(&p.meta)
        .map_err(|e| ApiError::Internal(format!("preview json: {e}")))?;
    let base = format!("/v1/jobs/{id}/preview");
    v["links"] = json!([
        {"rel": "self", "href": base},
        {"rel": "before", "href": format!("{base}/before"), "type": "application/x-ply"},
        {"rel": "after", "href": format!("{base}/after"), "type": "application/x-ply"},
    ]);
    let mut r = axum::Json(v).into_response();
    r.headers_mut().insert(
        header::CACHE_CONTROL,
        HeaderValue::from_static("private, no-cache"),
    );
    Ok(r)
}

/// `GET /v1/jobs/{id}/preview/before`.
pub async fn before(
    State(state): State<AppState>,
    Extension(Tenant(tenant)): Extension<Tenant>,
    Path(id): Path<String>,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    file(&state, &tenant, &id, false, &headers).await
}

/// `GET /v1/jobs/{id}/preview/after`.
pub async fn after(
    State(state): State<AppState>,
    Extension(Tenant(tenant)): Extension<Tenant>,
    Path(id): Path<String>,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    file(&state, &tenant, &id, true, &headers).await
}

async fn file(
    state: &AppState,
    tenant: &str,
    id: &str,
    after: bool,
    headers: &HeaderMap,
) -> Result<Response, ApiError> {
    let side = if after { "after" } else { "before" };
    let p = state.jobs.preview(tenant, id).await?;
    let path = if after { p.after } else { p.before };
    let file = tokio::fs::File::open(&path)
        .await
        .map_err(|e| ApiError::Internal(format!("open {}: {e}", path.display())))?;
    let meta = file
        .metadata()
        .await
        .map_err(|e| ApiError::Internal(format!("stat {}: {e}", path.display())))?;
    let mtime = meta
        .modified()
        .ok()
        .and_then(|t| t.duration_since(std::time::UNIX_EPOCH).ok())
        .map_or(0, |d| d.as_nanos());
    let etag = format!("\"{id}-{side}-{}-{mtime:x}\"", meta.len());
    let mut out = HeaderMap::new();
    let mut put = |name: header::HeaderName, value: String| {
        if let Ok(v) = HeaderValue::from_str(&value) {
            out.insert(name, v);
        }
    };
    put(header::ETAG, etag.clone());
    put(header::CACHE_CONTROL, "private, no-cache".into());
    let inm = headers
        .get(header::IF_NONE_MATCH)
        .and_then(|v| v.to_str().ok());
    if inm.is_some_and(|v| matches_etag(v, &etag)) {
        return Ok((StatusCode::NOT_MODIFIED, out).into_response());
    }
    put(header::CONTENT_TYPE, "application/x-ply".into());
    put(header::CONTENT_LENGTH, meta.len().to_string());
    put(
        header::CONTENT_DISPOSITION,
        format!("inline; filename=\"{id}-{side}.ply\""),
    );
    let body = Body::from_stream(ReaderStream::with_capacity(file, 1 << 16));
    Ok((StatusCode::OK, out, body).into_response())
}

#[cfg(test)]
mod tests {
    use axum::http::Request;
    use tower::ServiceExt;

    use super::super::{ApiSettings, router};
    use super::*;
    use crate::jobs::{Jobs, Settings};

    /// A noisy wavy sheet of `n` points with an intensity, as binary PLY.
    fn sheet(n: usize) -> Vec<u8> {
        let mut b = format!(
            "ply\nformat binary_little_endian 1.0\nelement vertex {n}\nproperty double x\n\
             property double y\nproperty double z\nproperty ushort intensity\nend_header\n"
        )
        .into_bytes();
        for i in 0..n {
            let (u, v) = ((i % 60) as f64 * 0.1, (i / 60) as f64 * 0.1);
            let noise = ((i * 7919) % 17) as f64 * 2e-3 - 0.016;
            for c in [
                500_000.0 + u,
                6_000_000.0 + v,
                (u * 2.0).sin() * 0.2 + noise,
            ] {
                b.extend_from_slice(&c.to_le_bytes());
            }
            b.extend_from_slice(&((i % 1000) as u16).to_le_bytes());
        }
        b
    }

    /// Vertex records of one of our preview PLYs: header lines and the bytes after it.
    fn parse(ply: &[u8]) -> (Vec<String>, Vec<u8>) {
        let end = ply.windows(11).position(|w| w == b"end_header\n").unwrap();
        let header = String::from_utf8(ply[..end].to_vec()).unwrap();
        (
            header.lines().map(str::to_string).collect(),
            ply[end + 11..].to_vec(),
        )
    }

    fn f32_at(b: &[u8], at: usize) -> f32 {
        f32::from_le_bytes(b[at..at + 4].try_into().unwrap())
    }

    async fn send(app: &axum::Router, req: Request<Body>) -> (StatusCode, HeaderMap, Vec<u8>) {
        let r = app.clone().oneshot(req).await.unwrap();
        let (status, headers) = (r.status(), r.headers().clone());
        let body = axum::body::to_bytes(r.into_body(), 1 << 26).await.unwrap();
        (status, headers, body.to_vec())
    }

    fn get(uri: &str, token: &str) -> Request<Body> {
        Request::get(uri)
            .header(header::AUTHORIZATION, format!("Bearer {token}"))
            .body(Body::empty())
            .unwrap()
    }

    #[tokio::test]
    async fn issue13_preview_pairs_points_and_is_tenant_scoped() {
        let dir = tempfile::tempdir().unwrap();
        let jobs = Jobs::open(Settings {
            data_dir: dir.path().to_path_buf(),
            ..Settings::default()
        })
        .await
        .unwrap();
        let settings = ApiSettings {
            tokens: vec![("ta".into(), "alice".into()), ("tb".into(), "bob".into())],
            max_sync_size: 1 << 20,
        };
        let app = router(AppState::new(jobs.clone(), settings).unwrap());
        let (status, _, body) = send(
            &app,
            Request::post("/v1/uploads?filename=sheet.ply")
                .header(header::AUTHORIZATION, "Bearer ta")
                .header(header::CONTENT_TYPE, "application/octet-stream")
                .body(Body::from(sheet(3000)))
                .unwrap(),
        )
        .await;
        assert_eq!(
            status,
            StatusCode::CREATED,
            "{}",
            String::from_utf8_lossy(&body)
        );
        let up: serde_json::Value = serde_json::from_slice(&body).unwrap();
        let (status, _, body) = send(
            &app,
            Request::post("/v1/jobs")
                .header(header::AUTHORIZATION, "Bearer ta")
                .header(header::CONTENT_TYPE, "application/json")
                .body(Body::from(json!({"input": up["id"]}).to_string()))
                .unwrap(),
        )
        .await;
        assert_eq!(status, StatusCode::CREATED);
        let id = serde_json::from_slice::<serde_json::Value>(&body).unwrap()["id"]
            .as_str()
            .unwrap()
            .to_string();
        let base = format!("/v1/jobs/{id}/preview");
        // Not before the job is done: 409 (or it already finished).
        let mut done = false;
        for _ in 0..600 {
            let (_, _, body) = send(&app, get(&format!("/v1/jobs/{id}"), "ta")).await;
            let v: serde_json::Value = serde_json::from_slice(&body).unwrap();
            match v["status"].as_str().unwrap() {
                "successful" => {
                    done = true;
                    break;
                }
                "failed" => panic!("{v}"),
                _ => {
                    let (status, _, _) = send(&app, get(&base, "ta")).await;
                    assert!(status == StatusCode::CONFLICT || status == StatusCode::OK);
                }
            }
            tokio::time::sleep(std::time::Duration::from_millis(50)).await;
        }
        assert!(done);

        let (status, _, body) = send(&app, get(&base, "ta")).await;
        assert_eq!(status, StatusCode::OK, "{}", String::from_utf8_lossy(&body));
        let meta: serde_json::Value = serde_json::from_slice(&body).unwrap();
        assert_eq!(meta["paired"], true);
        assert_eq!(meta["kind"], "points");
        assert_eq!(meta["points_before"], 3000);
        assert_eq!(meta["intensity"], true);
        assert!(meta["displacement"]["max"].as_f64().unwrap() > 0.0);
        // The origin keeps UTM-sized coordinates out of the f32 positions.
        assert!((meta["origin"][1].as_f64().unwrap() - 6_000_000.0).abs() < 10.0);

        let (status, h, before) = send(&app, get(&format!("{base}/before"), "ta")).await;
        assert_eq!(status, StatusCode::OK);
        assert_eq!(h[header::CONTENT_TYPE], "application/x-ply");
        let etag = h[header::ETAG].to_str().unwrap().to_string();
        let mut req = get(&format!("{base}/before"), "ta");
        req.headers_mut()
            .insert(header::IF_NONE_MATCH, HeaderValue::from_str(&etag).unwrap());
        assert_eq!(send(&app, req).await.0, StatusCode::NOT_MODIFIED);
        let (_, _, after) = send(&app, get(&format!("{base}/after"), "ta")).await;
        let (hb, rb) = parse(&before);
        let (ha, ra) = parse(&after);
        assert!(
            hb.contains(&"property float displacement".to_string()),
            "{hb:?}"
        );
        assert!(ha.contains(&"element vertex 3000".to_string()));
        // x y z displacement intensity: 20 bytes a point; the displacement is the distance.
        assert_eq!(rb.len(), 3000 * 20);
        let mut moved = 0;
        for k in 0..3000 {
            let p = |r: &[u8]| {
                glam::Vec3::new(
                    f32_at(r, k * 20),
                    f32_at(r, k * 20 + 4),
                    f32_at(r, k * 20 + 8),
                )
            };
            let d = p(&rb).distance(p(&ra));
            let stated = f32_at(&rb, k * 20 + 12);
            assert!((d - stated).abs() < 1e-4, "point {k}: {d} vs {stated}");
            assert_eq!(stated, f32_at(&ra, k * 20 + 12));
            moved += usize::from(stated > 0.0);
        }
        assert!(moved > 1000, "{moved}");

        // Tenancy: bob sees neither the description nor the files.
        for path in [
            base.clone(),
            format!("{base}/before"),
            format!("{base}/after"),
        ] {
            let (status, _, _) = send(&app, get(&path, "tb")).await;
            assert_eq!(status, StatusCode::NOT_FOUND, "{path}");
        }
        let (status, _, _) = send(&app, Request::get(&base).body(Body::empty()).unwrap()).await;
        assert_eq!(status, StatusCode::UNAUTHORIZED);

        // A bounded sample keeps the same points on both sides.
        let row = jobs.job("alice", &id).await.unwrap().row;
        let report = row.report.clone().unwrap();
        let res = jobs.result("alice", &id).await.unwrap();
        let input = dir
            .path()
            .join("uploads")
            .join(format!("{}.ply", row.upload));
        let small = dir.path().join("small");
        let meta = crate::jobs::preview::build(
            &small,
            (&input, "ply"),
            (&res.path, res.format.name()),
            &report,
            500,
        )
        .unwrap();
        assert_eq!((meta.points_before, meta.points_after), (500, 500));
        // Deterministic: built again, the same bytes.
        let again = dir.path().join("again");
        crate::jobs::preview::build(
            &again,
            (&input, "ply"),
            (&res.path, res.format.name()),
            &report,
            500,
        )
        .unwrap();
        for f in ["before.ply", "after.ply", "preview.json"] {
            assert_eq!(
                std::fs::read(small.join(f)).unwrap(),
                std::fs::read(again.join(f)).unwrap(),
                "{f}"
            );
        }
        let (_, rb) = parse(&std::fs::read(small.join("before.ply")).unwrap());
        let (_, ra) = parse(&std::fs::read(small.join("after.ply")).unwrap());
        // Before point k is source point chosen[k]: compare with the full preview's.
        let chosen = crate::jobs::preview::select(3000, 500);
        let (_, full) = parse(&before);
        for (k, &i) in chosen.iter().enumerate() {
            let i = i as usize;
            let o = meta.origin;
            let x_small = f64::from(f32_at(&rb, k * 20)) + o[0];
            let disp_small = f32_at(&rb, k * 20 + 12);
            let disp_full = f32_at(&full, i * 20 + 12);
            assert_eq!(disp_small, disp_full, "point {k} = source {i}");
            assert!(x_small > 499_999.0);
            assert_eq!(disp_small, f32_at(&ra, k * 20 + 12));
        }
        // `outliers: remove` drops points: the sides are sampled on their own, unpaired.
        let (_, _, body) = send(
            &app,
            Request::post("/v1/jobs")
                .header(header::AUTHORIZATION, "Bearer ta")
                .header(header::CONTENT_TYPE, "application/json")
                .body(Body::from(
                    json!({"input": up["id"], "params": {"outliers": "remove", "outlier_alpha": 0.5}})
                        .to_string(),
                ))
                .unwrap(),
        )
        .await;
        let removing = serde_json::from_slice::<serde_json::Value>(&body).unwrap()["id"]
            .as_str()
            .unwrap()
            .to_string();
        let mut meta = serde_json::Value::Null;
        for _ in 0..600 {
            let (status, _, body) =
                send(&app, get(&format!("/v1/jobs/{removing}/preview"), "ta")).await;
            if status == StatusCode::OK {
                meta = serde_json::from_slice(&body).unwrap();
                break;
            }
            assert_eq!(status, StatusCode::CONFLICT);
            tokio::time::sleep(std::time::Duration::from_millis(50)).await;
        }
        assert_eq!(meta["paired"], false, "{meta}");
        assert_eq!(meta["displacement"], serde_json::Value::Null);
        assert_eq!(meta["points_before"], 3000);
        assert!(meta["points_after"].as_u64().unwrap() < 3000, "{meta}");
        let (_, _, after) = send(
            &app,
            get(&format!("/v1/jobs/{removing}/preview/after"), "ta"),
        )
        .await;
        let (ha, _) = parse(&after);
        assert!(!ha.iter().any(|l| l.contains("displacement")), "{ha:?}");

        // Dismissing the job removes its preview.
        let (status, _, _) = send(
            &app,
            Request::delete(format!("/v1/jobs/{id}"))
                .header(header::AUTHORIZATION, "Bearer ta")
                .body(Body::empty())
                .unwrap(),
        )
        .await;
        assert_eq!(status, StatusCode::OK);
        assert_eq!(send(&app, get(&base, "ta")).await.0, StatusCode::NOT_FOUND);
    }
}
