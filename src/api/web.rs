//! The web page: static files compiled into the binary, served at `/` and under `/web/`.
//!
//! * `GET /` is `web/static/index.html`; `GET /web/<file>` the page's scripts, styles and the
//!   vendored libraries (three.js, its PLY loader and orbit controls, tus-js-client), which
//!   `web/scripts/vendor.mjs` copies from `web/node_modules` as `web/package-lock.json` pins
//!   them and which are committed, so a plain `cargo build` needs nothing but the Rust toolchain.
//! * Nothing is fetched from elsewhere: the page works offline. Responses carry a strong `ETag`
//!   (the file's SHA-256; `If-None-Match` answers 304), `Cache-Control: no-cache`, and a
//!   `Content-Security-Policy` that allows scripts from this origin plus the page's one inline
//!   script, the import map, by its hash.
//! * No authentication: the files hold no data; the page asks for a bearer token and sends it
//!   with each `/v1` request (kept in `sessionStorage`, i.e. for the browser tab only).

use std::collections::HashMap;
use std::sync::OnceLock;

use axum::Router;
use axum::extract::Path;
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use sha2::{Digest, Sha256};

use super::{ApiError, AppState};

/// One embedded file: its path under `/web/`, media type and bytes.
struct Asset {
    path: &'static str,
    media_type: &'static str,
    bytes: &'static [u8],
}

macro_rules! asset {
    ($path:literal, $ty:literal) => {
        Asset {
            path: $path,
            media_type: $ty,
            bytes: include_bytes!(concat!("../../web/static/", $path)),
        }
    };
}

/// Every file of the page.
static ASSETS: &[Asset] = &[
    asset!("index.html", "text/html; charset=utf-8"),
    asset!("style.css", "text/css; charset=utf-8"),
    asset!("app.js", "text/javascript; charset=utf-8"),
    asset!("api.js", "text/javascript; charset=utf-8"),
    asset!("form.js", "text/javascript; charset=utf-8"),
    asset!("viewer.js", "text/javascript; charset=utf-8"),
    asset!("colours.js", "text/javascript; charset=utf-8"),
    asset!(
        "vendor/three/three.module.js",
        "text/javascript; charset=utf-8"
    ),
    asset!(
        "vendor/three/three.core.js",
        "text/javascript; charset=utf-8"
    ),
    asset!(
        "vendor/three/addons/loaders/PLYLoader.js",
        "text/javascript; charset=utf-8"
    ),
    asset!(
        "vendor/three/addons/controls/OrbitControls.js",
        "text/javascript; charset=utf-8"
    ),
    asset!("vendor/tus/tus.min.js", "text/javascript; charset=utf-8"),
    asset!("vendor/VERSIONS.json", "application/json"),
    asset!("vendor/three/LICENSE", "text/plain; charset=utf-8"),
    asset!("vendor/tus/LICENSE", "text/plain; charset=utf-8"),
];

/// Standard base64 with padding (for the CSP hash).
fn base64(bytes: &[u8]) -> String {
    const A: &[u8; 64] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
    let mut out = String::with_capacity(bytes.len().div_ceil(3) * 4);
    for chunk in bytes.chunks(3) {
        let b = [
            chunk[0],
            chunk.get(1).copied().unwrap_or(0),
            chunk.get(2).copied().unwrap_or(0),
        ];
        let n = (u32::from(b[0]) << 16) | (u32::from(b[1]) << 8) | u32::from(b[2]);
        for (k, shift) in [18, 12, 6, 0].into_iter().enumerate() {
            if k <= chunk.len() {
                out.push(char::from(A[((n >> shift) & 63) as usize]));
            } else {
                out.push('=');
            }
        }
    }
    out
}

/// The page's headers, computed once: ETags by path and the CSP.
struct Index {
    etags: HashMap<&'static str, String>,
    csp: String,
}

fn index() -> &'static Index {
    static INDEX: OnceLock<Index> = OnceLock::new();
    INDEX.get_or_init(|| {
        let etags = ASSETS
            .iter()
            .map(|a| {
                let sum = Sha256::digest(a.bytes);
                let hex: String = sum.iter().map(|b| format!("{b:02x}")).collect();
                (a.path, format!("\"{hex}\""))
            })
            .collect();
        // The import map is the one inline script; allow exactly it.
        let html = ASSETS
            .iter()
            .find(|a| a.path == "index.html")
            .map_or("", |a| std::str::from_utf8(a.bytes).unwrap_or(""));
        let open = "<script type=\"importmap\">";
        let map = html
            .split_once(open)
            .and_then(|(_, rest)| rest.split_once("</script>"))
            .map_or("", |(m, _)| m);
        let hash = base64(&Sha256::digest(map.as_bytes()));
        let csp = format!(
            "default-src 'self'; script-src 'self' 'sha256-{hash}'; style-src 'self'; \
             img-src 'self' data: blob:; connect-src 'self'; worker-src 'self' blob:; \
             object-src 'none'; base-uri 'none'; frame-ancestors 'none'; form-action 'none'"
        );
        Index { etags, csp }
    })
}

fn serve(path: &str, headers: &HeaderMap) -> Response {
    let Some(asset) = ASSETS.iter().find(|a| a.path == path) else {
        return ApiError::NoRoute.into_response();
    };
    let idx = index();
    let etag = idx.etags.get(asset.path).cloned().unwrap_or_default();
    let mut out = HeaderMap::new();
    let mut put = |name: header::HeaderName, value: &str| {
        if let Ok(v) = HeaderValue::from_str(value) {
            out.insert(name, v);
        }
    };
    put(header::ETAG, &etag);
    put(header::CACHE_CONTROL, "no-cache");
    put(header::X_CONTENT_TYPE_OPTIONS, "nosniff");
    put(header::REFERRER_POLICY, "no-referrer");
    if asset.path == "index.html" {
        put(header::CONTENT_SECURITY_POLICY, &idx.csp);
    }
    let fresh = headers
        .get(header::IF_NONE_MATCH)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|v| super::download::matches_etag(v, &etag));
    if fresh {
        return (StatusCode::NOT_MODIFIED, out).into_response();
    }
    put(header::CONTENT_TYPE, asset.media_type);
    (StatusCode::OK, out, asset.bytes).into_response()
}

/// `GET /`: the page.
pub async fn page(headers: HeaderMap) -> Response {
    serve("index.html", &headers)
}

/// `GET /web/{*path}`: the page's files.
pub async fn file(Path(path): Path<String>, headers: HeaderMap) -> Response {
    serve(&path, &headers)
}

/// The routes of the page's files (`/` is in [`super::routes`], documented in the OpenAPI file;
/// the files under `/web/` are not API).
pub fn router() -> Router<AppState> {
    Router::new().route("/web/{*path}", get(file))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The page's form shows the defaults of `proto/openapi.yaml`'s `Params`; they must be the
    /// defaults the code applies.
    #[test]
    fn issue13_form_defaults_are_the_code_defaults() {
        let doc = super::super::openapi_document().unwrap();
        let props = doc["components"]["schemas"]["Params"]["properties"]
            .as_object()
            .unwrap();
        let mut code = serde_json::to_value(crate::denoise::Params::default()).unwrap();
        code["outliers"] = serde_json::to_value(crate::pipeline::OutlierMode::default()).unwrap();
        code["outlier_alpha"] = serde_json::json!(crate::jobs::Settings::default().outlier_alpha);
        code["paper"] = serde_json::json!(false);
        // Not serialised when off (stored specs keep their shape).
        code["write_normals"] = serde_json::json!(false);
        code["sensor_origin"] =
            serde_json::json!(crate::denoise::SensorOrigin::default().to_string());
        let mut checked = 0;
        for (name, prop) in props {
            let Some(doc_default) = prop.get("default") else {
                // Fields without one are unset in the code too (chosen from the data, or `knn`,
                // whose presence picks point mode); the form leaves them empty.
                assert!(code[name].is_null(), "{name}: code default {}", code[name]);
                continue;
            };
            let same = match (doc_default.as_f64(), code[name].as_f64()) {
                (Some(a), Some(b)) => (a - b).abs() < 1e-12,
                _ => doc_default == &code[name],
            };
            assert!(same, "{name}: openapi {doc_default} vs code {}", code[name]);
            checked += 1;
        }
        assert!(checked >= 12, "{checked}");
    }

    #[test]
    fn base64_matches_rfc4648() {
        for (raw, enc) in [
            ("", ""),
            ("f", "Zg=="),
            ("fo", "Zm8="),
            ("foo", "Zm9v"),
            ("foob", "Zm9vYg=="),
            ("foobar", "Zm9vYmFy"),
        ] {
            assert_eq!(base64(raw.as_bytes()), enc);
        }
    }

    #[test]
    fn every_asset_is_there_and_the_import_map_names_only_embedded_files() {
        let html = std::str::from_utf8(ASSETS[0].bytes).unwrap();
        assert!(html.contains("<script type=\"importmap\">"));
        assert!(index().csp.contains("'sha256-"));
        for a in ASSETS {
            assert!(!a.bytes.is_empty(), "{}", a.path);
        }
        // Every /web/ URL the page names is embedded.
        for part in html.split("/web/").skip(1) {
            let url: String = part
                .chars()
                .take_while(|c| !matches!(c, '"' | '\'' | ' ' | '>'))
                .collect();
            if url.ends_with('/') {
                assert!(ASSETS.iter().any(|a| a.path.starts_with(&url)), "{url}");
            } else {
                assert!(ASSETS.iter().any(|a| a.path == url), "{url}");
            }
        }
    }
}
