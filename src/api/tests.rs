//! Router-level tests: the real router driven with `tower::ServiceExt::oneshot`, no socket.

use std::collections::{BTreeMap, BTreeSet};

use axum::body::Body;
use axum::http::{Method, Request, StatusCode, header};
use tower::ServiceExt;

use super::*;
use crate::jobs::{Jobs, Settings};

async fn state(dir: &std::path::Path, tokens: &[(&str, &str)]) -> AppState {
    let jobs = Jobs::open(Settings {
        data_dir: dir.to_path_buf(),
        ..Settings::default()
    })
    .await
    .unwrap();
    AppState::new(
        jobs,
        ApiSettings {
            tokens: tokens
                .iter()
                .map(|(t, n)| (t.to_string(), n.to_string()))
                .collect(),
            max_sync_size: 1 << 20,
        },
    )
    .unwrap()
}

async fn send(app: &Router, req: Request<Body>) -> (StatusCode, axum::http::HeaderMap, Vec<u8>) {
    let r = app.clone().oneshot(req).await.unwrap();
    let status = r.status();
    let headers = r.headers().clone();
    let body = axum::body::to_bytes(r.into_body(), 1 << 26).await.unwrap();
    (status, headers, body.to_vec())
}

fn problem_type(body: &[u8]) -> String {
    serde_json::from_slice::<serde_json::Value>(body)
        .ok()
        .and_then(|v| v["type"].as_str().map(str::to_string))
        .unwrap_or_default()
}

const METHODS: [&str; 7] = ["GET", "HEAD", "POST", "PUT", "PATCH", "DELETE", "OPTIONS"];

/// The document's paths and methods; `head` is implied wherever `get` is (axum answers HEAD
/// with the GET handler, and so does any HTTP server).
fn documented() -> BTreeMap<String, BTreeSet<String>> {
    let doc = openapi_document().unwrap();
    let mut out = BTreeMap::new();
    for (path, item) in doc["paths"].as_object().unwrap() {
        let mut methods: BTreeSet<String> = item
            .as_object()
            .unwrap()
            .keys()
            .map(|k| k.to_ascii_uppercase())
            .filter(|k| METHODS.contains(&k.as_str()) || k == "TRACE")
            .collect();
        if methods.contains("GET") {
            methods.insert("HEAD".into());
        }
        out.insert(path.clone(), methods);
    }
    out
}

#[tokio::test]
async fn openapi_document_agrees_with_the_router() {
    let dir = tempfile::tempdir().unwrap();
    let app = router(state(dir.path(), &[]).await);
    // What the router answers: probe every route with every method.
    let mut routed = BTreeMap::new();
    for (path, _, _) in routes() {
        let concrete = path.replace("{id}", "00000000-0000-4000-8000-000000000000");
        let mut methods = BTreeSet::new();
        for m in METHODS {
            let req = Request::builder()
                .method(Method::from_bytes(m.as_bytes()).unwrap())
                .uri(&concrete)
                .body(Body::empty())
                .unwrap();
            let (status, _, body) = send(&app, req).await;
            let kind = problem_type(&body);
            let missing =
                status == StatusCode::METHOD_NOT_ALLOWED || kind == "urn:qemd:problem:no-route";
            if !missing {
                methods.insert(m.to_string());
            }
        }
        routed.insert(path.to_string(), methods);
    }
    let documented = documented();
    for (path, methods) in &documented {
        assert_eq!(
            routed.get(path),
            Some(methods),
            "{path}: router vs proto/openapi.yaml"
        );
    }
    for (path, methods) in &routed {
        assert_eq!(
            documented.get(path),
            Some(methods),
            "{path}: router vs proto/openapi.yaml"
        );
    }
    // And the document is served as JSON.
    let (status, headers, body) = send(
        &app,
        Request::get("/openapi.json").body(Body::empty()).unwrap(),
    )
    .await;
    assert_eq!(status, StatusCode::OK);
    assert_eq!(headers[header::CONTENT_TYPE], "application/json");
    let served: serde_json::Value = serde_json::from_slice(&body).unwrap();
    assert_eq!(served, openapi_document().unwrap());
}

#[test]
fn openapi_params_are_the_cli_params() {
    // Every field of the parameter spec is documented, and nothing else; the sync path's query
    // parameters are the same set.
    let doc = openapi_document().unwrap();
    let documented: BTreeSet<String> = doc["components"]["schemas"]["Params"]["properties"]
        .as_object()
        .unwrap()
        .keys()
        .cloned()
        .collect();
    // The spec's own field names, as serde reads them (not a list kept here).
    let expected: BTreeSet<String> = crate::pipeline::SpecOverlay::fields()
        .iter()
        .map(|f| f.to_string())
        .collect();
    assert_eq!(documented, expected);
    let query: BTreeSet<String> = doc["paths"]["/v1/denoise"]["post"]["parameters"]
        .as_array()
        .unwrap()
        .iter()
        .map(|p| p["name"].as_str().unwrap().to_string())
        .filter(|n| n != "format" && n != "output_format")
        .collect();
    assert_eq!(query, expected);
}

#[test]
fn openapi_formats_are_the_format_enum() {
    // Every name a request may give and every canonical name an answer carries.
    use crate::io::Format;
    let doc = openapi_document().unwrap();
    let documented: BTreeSet<String> = doc["components"]["schemas"]["Format"]["enum"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_str().unwrap().to_string())
        .collect();
    let mut expected: BTreeSet<String> = Format::NAMES.iter().map(|n| n.to_string()).collect();
    expected.extend(
        Format::NAMES
            .iter()
            .filter_map(|n| Format::from_name(n))
            .map(|f| f.name().to_string()),
    );
    assert_eq!(documented, expected);
}

#[tokio::test]
async fn problems_for_routes_methods_and_tokens() {
    let dir = tempfile::tempdir().unwrap();
    let app = router(state(dir.path(), &[("token-alice", "alice")]).await);
    let (status, headers, body) =
        send(&app, Request::get("/nope").body(Body::empty()).unwrap()).await;
    assert_eq!(status, StatusCode::NOT_FOUND);
    assert_eq!(headers[header::CONTENT_TYPE], "application/problem+json");
    assert_eq!(problem_type(&body), "urn:qemd:problem:no-route");
    assert!(headers.contains_key("x-request-id"));

    let (status, _, body) = send(&app, Request::put("/v1/jobs").body(Body::empty()).unwrap()).await;
    assert_eq!(status, StatusCode::METHOD_NOT_ALLOWED);
    assert_eq!(problem_type(&body), "urn:qemd:problem:method-not-allowed");

    // /v1 needs the token; operations endpoints do not.
    let (status, headers, body) =
        send(&app, Request::get("/v1/jobs").body(Body::empty()).unwrap()).await;
    assert_eq!(status, StatusCode::UNAUTHORIZED);
    assert_eq!(problem_type(&body), "urn:qemd:problem:unauthorized");
    assert!(headers.contains_key(header::WWW_AUTHENTICATE));
    let (status, _, _) = send(
        &app,
        Request::get("/v1/jobs")
            .header(header::AUTHORIZATION, "Bearer token-alice")
            .body(Body::empty())
            .unwrap(),
    )
    .await;
    assert_eq!(status, StatusCode::OK);
    let (status, _, _) = send(&app, Request::get("/healthz").body(Body::empty()).unwrap()).await;
    assert_eq!(status, StatusCode::OK);

    // A request id given by the client is kept.
    let (_, headers, _) = send(
        &app,
        Request::get("/healthz")
            .header("x-request-id", "abc-123")
            .body(Body::empty())
            .unwrap(),
    )
    .await;
    assert_eq!(headers["x-request-id"], "abc-123");
}

/// A tiny binary PLY point cloud of `n` points on a wavy surface.
fn ply(n: usize) -> Vec<u8> {
    let mut b = format!(
        "ply\nformat binary_little_endian 1.0\nelement vertex {n}\nproperty float x\n\
         property float y\nproperty float z\nend_header\n"
    )
    .into_bytes();
    for i in 0..n {
        let (u, v) = ((i % 40) as f32 * 0.1, (i / 40) as f32 * 0.1);
        for c in [
            u,
            v,
            (u * 3.0).sin() * 0.1 + ((i * 7919) % 13) as f32 * 1e-3,
        ] {
            b.extend_from_slice(&c.to_le_bytes());
        }
    }
    b
}

/// The cloud of [`ply`] as PCL writes it by default: `binary_compressed` (LZF over the
/// column-major fields).
fn compressed_pcd(n: usize) -> Vec<u8> {
    let body = ply(n);
    let start = body.len() - n * 12;
    let mut columns = Vec::with_capacity(n * 12);
    for c in 0..3 {
        for i in 0..n {
            let at = start + i * 12 + c * 4;
            columns.extend_from_slice(&body[at..at + 4]);
        }
    }
    let packed = lzf::compress(&columns).unwrap();
    let mut b = format!(
        "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\n\
         TYPE F F F\nCOUNT 1 1 1\nWIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\n\
         DATA binary_compressed\n"
    )
    .into_bytes();
    b.extend_from_slice(&(packed.len() as u32).to_le_bytes());
    b.extend_from_slice(&(columns.len() as u32).to_le_bytes());
    b.extend_from_slice(&packed);
    b
}

#[tokio::test]
async fn issue10_the_service_tells_compressed_pcd_by_content() {
    // PCL's default encoding used to get 415 "cannot tell the format from the content".
    let dir = tempfile::tempdir().unwrap();
    let app = router(state(dir.path(), &[]).await);
    let data = compressed_pcd(1200);
    let (status, headers, body) = send(
        &app,
        Request::post("/v1/denoise?knn=8")
            .body(Body::from(data.clone()))
            .unwrap(),
    )
    .await;
    assert_eq!(status, StatusCode::OK, "{}", String::from_utf8_lossy(&body));
    assert_eq!(headers["x-qemd-format"], "pcd");
    assert_eq!(headers["x-qemd-points-in"], "1200");
    assert!(body.starts_with(b"# .PCD"));
    let (status, _, body) = send(
        &app,
        Request::post("/v1/uploads").body(Body::from(data)).unwrap(),
    )
    .await;
    assert_eq!(
        status,
        StatusCode::CREATED,
        "{}",
        String::from_utf8_lossy(&body)
    );
    let v: serde_json::Value = serde_json::from_slice(&body).unwrap();
    assert_eq!(v["format"], "pcd");
    assert_eq!(v["points"], 1200);
}

#[tokio::test]
async fn uploads_whole_and_resumable_agree() {
    let dir = tempfile::tempdir().unwrap();
    let app = router(state(dir.path(), &[]).await);
    let data = ply(1200);
    let (status, headers, body) = send(
        &app,
        Request::post("/v1/uploads")
            .header(header::CONTENT_TYPE, "application/octet-stream")
            .body(Body::from(data.clone()))
            .unwrap(),
    )
    .await;
    assert_eq!(
        status,
        StatusCode::CREATED,
        "{}",
        String::from_utf8_lossy(&body)
    );
    let whole: serde_json::Value = serde_json::from_slice(&body).unwrap();
    assert_eq!(whole["format"], "ply");
    assert_eq!(whole["points"], 1200);
    assert_eq!(whole["size"], data.len());
    let id = whole["id"].as_str().unwrap();
    assert_eq!(headers[header::LOCATION], format!("/v1/uploads/{id}"));

    // Resumable: create, then three PATCHes, one with a wrong offset.
    let (status, headers, _) = send(
        &app,
        Request::post("/v1/uploads")
            .header("upload-length", data.len())
            .body(Body::empty())
            .unwrap(),
    )
    .await;
    assert_eq!(status, StatusCode::CREATED);
    assert_eq!(headers["upload-offset"], "0");
    let loc = headers[header::LOCATION].to_str().unwrap().to_string();
    let patch = |offset: usize, chunk: Vec<u8>| {
        Request::patch(&loc)
            .header(header::CONTENT_TYPE, "application/offset+octet-stream")
            .header("upload-offset", offset)
            .body(Body::from(chunk))
            .unwrap()
    };
    let third = data.len() / 3;
    let (status, headers, _) = send(&app, patch(0, data[..third].to_vec())).await;
    assert_eq!(status, StatusCode::NO_CONTENT);
    assert_eq!(headers["upload-offset"], third.to_string());
    let (status, headers, _) = send(&app, patch(0, data[..third].to_vec())).await;
    assert_eq!(status, StatusCode::CONFLICT);
    assert_eq!(headers["upload-offset"], third.to_string());
    let (status, headers, _) = send(&app, Request::head(&loc).body(Body::empty()).unwrap()).await;
    assert_eq!(status, StatusCode::OK);
    assert_eq!(headers["upload-offset"], third.to_string());
    assert_eq!(headers["upload-length"], data.len().to_string());
    let (status, _, _) = send(&app, patch(third, data[third..2 * third].to_vec())).await;
    assert_eq!(status, StatusCode::NO_CONTENT);
    let (status, _, _) = send(&app, patch(2 * third, data[2 * third..].to_vec())).await;
    assert_eq!(status, StatusCode::NO_CONTENT);
    let (status, _, body) = send(&app, Request::get(&loc).body(Body::empty()).unwrap()).await;
    assert_eq!(status, StatusCode::OK);
    let resumed: serde_json::Value = serde_json::from_slice(&body).unwrap();
    assert_eq!(resumed["complete"], true);
    assert_eq!(resumed["sha256"], whole["sha256"]);
    assert_eq!(resumed["format"], "ply");
    // A PATCH after completion conflicts; a wrong content type is refused.
    let (status, _, _) = send(&app, patch(data.len(), vec![1])).await;
    assert_eq!(status, StatusCode::CONFLICT);
    let (status, _, _) = send(
        &app,
        Request::patch(&loc)
            .header("upload-offset", 0)
            .body(Body::from(vec![1u8]))
            .unwrap(),
    )
    .await;
    assert_eq!(status, StatusCode::UNSUPPORTED_MEDIA_TYPE);
}

#[tokio::test]
async fn sync_denoise_and_its_refusals() {
    let dir = tempfile::tempdir().unwrap();
    let app = router(state(dir.path(), &[]).await);
    let data = ply(1200);
    let (status, headers, body) = send(
        &app,
        Request::post("/v1/denoise?knn=8")
            .body(Body::from(data.clone()))
            .unwrap(),
    )
    .await;
    assert_eq!(status, StatusCode::OK, "{}", String::from_utf8_lossy(&body));
    assert_eq!(headers["x-qemd-points-in"], "1200");
    assert_eq!(body.len(), data.len());
    assert_ne!(body, data);

    let (status, _, body) = send(
        &app,
        Request::post("/v1/denoise?knn=1")
            .body(Body::from(data.clone()))
            .unwrap(),
    )
    .await;
    assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY);
    let v: serde_json::Value = serde_json::from_slice(&body).unwrap();
    assert_eq!(v["field"], "knn");

    let (status, _, _) = send(
        &app,
        Request::post("/v1/denoise")
            .body(Body::from(vec![0u8; (1 << 20) + 1]))
            .unwrap(),
    )
    .await;
    assert_eq!(status, StatusCode::PAYLOAD_TOO_LARGE);
    let (status, _, _) = send(
        &app,
        Request::post("/v1/denoise")
            .header(header::CONTENT_TYPE, "application/json")
            .body(Body::from("{}"))
            .unwrap(),
    )
    .await;
    assert_eq!(status, StatusCode::UNSUPPORTED_MEDIA_TYPE);
    let (status, _, _) = send(
        &app,
        Request::post("/v1/denoise?format=ply")
            .body(Body::from("ply\nformat nonsense\n"))
            .unwrap(),
    )
    .await;
    assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY);
}

#[tokio::test]
async fn issue9_sync_write_normals_adds_the_fields_and_refuses_kitti() {
    let dir = tempfile::tempdir().unwrap();
    let app = router(state(dir.path(), &[]).await);
    let data = ply(1200);
    let (status, _, body) = send(
        &app,
        Request::post("/v1/denoise?write_normals=true")
            .body(Body::from(data.clone()))
            .unwrap(),
    )
    .await;
    assert_eq!(status, StatusCode::OK, "{}", String::from_utf8_lossy(&body));
    let text = String::from_utf8_lossy(&body[..400]);
    assert!(
        text.contains(
            "property float nx\nproperty float ny\nproperty float nz\nproperty float curvature\n\
             property uchar structure\n"
        ),
        "{text}"
    );
    // 12 bytes of position and 17 of normals per point.
    assert_eq!(
        body.len() - body.windows(11).position(|w| w == b"end_header\n").unwrap() - 11,
        1200 * 29
    );
    let (status, _, body) = send(
        &app,
        Request::post("/v1/denoise?write_normals=true&output_format=kitti")
            .body(Body::from(data))
            .unwrap(),
    )
    .await;
    assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY);
    let v: serde_json::Value = serde_json::from_slice(&body).unwrap();
    assert_eq!(v["field"], "write_normals", "{v}");
}

#[tokio::test]
async fn issue15_every_secured_operation_documents_and_answers_401() {
    // schemathesis found 401 undocumented on most /v1 operations: each operation without
    // `security: []` must document 401, and the router must answer it without a token.
    let dir = tempfile::tempdir().unwrap();
    let app = router(state(dir.path(), &[("token-alice", "alice")]).await);
    let doc = openapi_document().unwrap();
    let mut checked = 0;
    for (path, item) in doc["paths"].as_object().unwrap() {
        for (method, op) in item.as_object().unwrap() {
            if !METHODS.contains(&method.to_ascii_uppercase().as_str()) {
                continue;
            }
            let open = op["security"].as_array().is_some_and(|s| s.is_empty());
            let uri = path.replace("{id}", "e3e70682-c209-1cac-a29f-6fbed82c07cd");
            let req = Request::builder()
                .method(method.to_ascii_uppercase().as_str())
                .uri(&uri)
                .body(Body::empty())
                .unwrap();
            let (status, _, _) = send(&app, req).await;
            if open {
                assert_ne!(status, StatusCode::UNAUTHORIZED, "{method} {path}");
                continue;
            }
            assert!(
                op["responses"]["401"].is_object(),
                "{method} {path}: 401 undocumented"
            );
            assert_eq!(status, StatusCode::UNAUTHORIZED, "{method} {path}");
            checked += 1;
        }
    }
    assert!(checked >= 15, "{checked} secured operations");
}

#[tokio::test]
async fn issue15_delete_during_a_patch_is_409_and_a_patch_after_delete_is_404() {
    // schemathesis found a 500: a PATCH whose upload a DELETE removed after the PATCH had read
    // its row. DELETE now waits for no PATCH (409 while one writes) and a PATCH that finds the
    // file gone answers 404.
    let dir = tempfile::tempdir().unwrap();
    let app = router(state(dir.path(), &[]).await);
    let (status, headers, _) = send(
        &app,
        Request::post("/v1/uploads")
            .header("upload-length", 1000)
            .body(Body::empty())
            .unwrap(),
    )
    .await;
    assert_eq!(status, StatusCode::CREATED);
    let loc = headers[header::LOCATION].to_str().unwrap().to_string();
    // A PATCH whose body is still arriving holds the upload.
    let (tx, rx) = tokio::sync::mpsc::channel::<Result<Vec<u8>, std::io::Error>>(1);
    let stream = futures_util::stream::unfold(rx, |mut rx| async move {
        rx.recv().await.map(|item| (item, rx))
    });
    let slow = Request::patch(&loc)
        .header(header::CONTENT_TYPE, "application/offset+octet-stream")
        .header("upload-offset", 0)
        .body(Body::from_stream(stream))
        .unwrap();
    let app2 = app.clone();
    let patching = tokio::spawn(async move { send(&app2, slow).await.0 });
    // The channel holds one chunk: the second send returns once the PATCH took the first, i.e.
    // once it is past its lock and writing.
    tx.send(Ok(vec![b'x'; 5])).await.unwrap();
    tx.send(Ok(vec![b'x'; 5])).await.unwrap();
    let delete = || Request::delete(&loc).body(Body::empty()).unwrap();
    let (status, _, body) = send(&app, delete()).await;
    assert_eq!(
        status,
        StatusCode::CONFLICT,
        "DELETE during a PATCH: {}",
        String::from_utf8_lossy(&body)
    );
    drop(tx);
    assert_eq!(patching.await.unwrap(), StatusCode::NO_CONTENT);
    assert_eq!(send(&app, delete()).await.0, StatusCode::NO_CONTENT);
    let after = Request::patch(&loc)
        .header(header::CONTENT_TYPE, "application/offset+octet-stream")
        .header("upload-offset", 10)
        .body(Body::from(vec![b'y'; 5]))
        .unwrap();
    assert_eq!(send(&app, after).await.0, StatusCode::NOT_FOUND);

    // The row read, then the file gone (a DELETE in between): 404, not 500.
    let (_, headers, _) = send(
        &app,
        Request::post("/v1/uploads")
            .header("upload-length", 1000)
            .body(Body::empty())
            .unwrap(),
    )
    .await;
    let loc = headers[header::LOCATION].to_str().unwrap().to_string();
    let id = loc.rsplit('/').next().unwrap();
    std::fs::remove_file(dir.path().join("uploads").join(format!("{id}.part"))).unwrap();
    let r = Request::patch(&loc)
        .header(header::CONTENT_TYPE, "application/offset+octet-stream")
        .header("upload-offset", 0)
        .body(Body::from(vec![b'y'; 5]))
        .unwrap();
    assert_eq!(send(&app, r).await.0, StatusCode::NOT_FOUND);
}
