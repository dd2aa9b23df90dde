//! Bearer-token authentication: a token names a tenant.
//!
//! With no tokens configured every request belongs to the tenant `default`. With tokens, each
//! `/v1` request must carry `Authorization: Bearer <token>`; a missing, malformed or unknown
//! token answers 401 (problem+json with `WWW-Authenticate: Bearer`). Tokens are compared in time
//! independent of where they differ.

use axum::extract::{Request, State};
use axum::http::header;
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};

use super::{ApiError, AppState};

/// The tenant a request acts for (a request extension set by [`authenticate`]).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Tenant(pub String);

/// The tenant of unauthenticated deployments.
pub const DEFAULT_TENANT: &str = "default";

/// Equality whose running time does not depend on where the inputs differ.
fn same(a: &[u8], b: &[u8]) -> bool {
    let mut diff = a.len() ^ b.len();
    for (i, x) in a.iter().enumerate() {
        diff |= usize::from(x ^ b.get(i).copied().unwrap_or(!x));
    }
    diff == 0
}

/// The tenant `authorization` (an `Authorization` header value) authenticates, if any.
pub fn tenant_of(tokens: &[(String, String)], authorization: Option<&str>) -> Option<String> {
    let value = authorization?.trim();
    let (scheme, token) = value.split_once(' ')?;
    if !scheme.eq_ignore_ascii_case("bearer") {
        return None;
    }
    let token = token.trim().as_bytes();
    // Check every entry, so the time taken does not tell which token was close.
    let mut found = None;
    for (t, tenant) in tokens {
        if same(t.as_bytes(), token) && found.is_none() {
            found = Some(tenant.clone());
        }
    }
    found
}

/// Middleware: resolves the tenant or answers 401.
pub async fn authenticate(State(state): State<AppState>, mut req: Request, next: Next) -> Response {
    let tokens = &state.settings.tokens;
    let tenant = if tokens.is_empty() {
        DEFAULT_TENANT.to_string()
    } else {
        let auth = req
            .headers()
            .get(header::AUTHORIZATION)
            .and_then(|v| v.to_str().ok());
        match tenant_of(tokens, auth) {
            Some(t) => t,
            None => return ApiError::Unauthorized.into_response(),
        }
    };
    tracing::Span::current().record("tenant", tracing::field::display(&tenant));
    let _ = req.extensions_mut().insert(Tenant(tenant));
    next.run(req).await
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tokens_name_tenants() {
        let tokens = vec![
            ("secret-aaa".to_string(), "alice".to_string()),
            ("secret-bbb".to_string(), "bob".to_string()),
        ];
        assert_eq!(
            tenant_of(&tokens, Some("Bearer secret-aaa")).as_deref(),
            Some("alice")
        );
        assert_eq!(
            tenant_of(&tokens, Some("bearer secret-bbb")).as_deref(),
            Some("bob")
        );
        for bad in [
            None,
            Some(""),
            Some("Bearer"),
            Some("Bearer secret-aa"),
            Some("Bearer secret-aaaa"),
            Some("Basic secret-aaa"),
            Some("secret-aaa"),
        ] {
            assert_eq!(tenant_of(&tokens, bad), None, "{bad:?}");
        }
        assert!(same(b"abc", b"abc"));
        assert!(!same(b"abc", b"abd"));
        assert!(!same(b"abc", b"ab"));
        assert!(!same(b"", b"a"));
    }
}
