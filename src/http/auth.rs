//! Bearer API tokens. Tokens are kept only as SHA-256 hashes and compared in constant time; with no token
//! configured, authentication is off (and the configuration only allows loopback binds).

use std::sync::Arc;

use axum::extract::{Request, State};
use axum::http::header;
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use sha2::{Digest, Sha256};
use subtle::ConstantTimeEq;

use super::problem::api_error;
use crate::config::Settings;
use crate::error_code::ErrorCode;

/// The accepted token hashes.
#[derive(Clone, Default)]
pub struct Tokens {
    hashes: Arc<Vec<[u8; 32]>>,
}

fn unhex(s: &str) -> Option<[u8; 32]> {
    let mut out = [0u8; 32];
    if s.len() != 64 {
        return None;
    }
    for (i, slot) in out.iter_mut().enumerate() {
        *slot = u8::from_str_radix(s.get(2 * i..2 * i + 2)?, 16).ok()?;
    }
    Some(out)
}

impl Tokens {
    /// Hash the configured tokens (clear ones are hashed here and not kept).
    pub fn from_settings(s: &Settings) -> Self {
        let mut hashes: Vec<[u8; 32]> = s
            .api_tokens
            .iter()
            .map(|t| Sha256::digest(t.as_bytes()).into())
            .collect();
        hashes.extend(s.api_token_sha256.iter().filter_map(|h| unhex(h)));
        Self {
            hashes: Arc::new(hashes),
        }
    }

    pub fn enabled(&self) -> bool {
        !self.hashes.is_empty()
    }

    /// True when `token` hashes to one of the accepted hashes; every hash is compared, in constant time.
    pub fn accepts(&self, token: &str) -> bool {
        let h: [u8; 32] = Sha256::digest(token.as_bytes()).into();
        let mut ok = subtle::Choice::from(0u8);
        for known in self.hashes.iter() {
            ok |= known.ct_eq(&h);
        }
        ok.into()
    }
}

/// Routes that stay open without a token: probes and the contract.
fn is_public(path: &str) -> bool {
    matches!(path, "/healthz" | "/readyz" | "/openapi.yaml")
}

/// The token of an `Authorization` value with the `Bearer` scheme; the scheme is case-insensitive (RFC 9110
/// §11.1) and separated from the token by spaces.
fn bearer_token(value: &str) -> Option<&str> {
    let (scheme, token) = value.trim_start().split_once(' ')?;
    let token = token.trim();
    (scheme.eq_ignore_ascii_case("bearer") && !token.is_empty()).then_some(token)
}

/// Middleware: refuse requests without a valid `Authorization: Bearer <token>`.
pub async fn require_token(State(tokens): State<Tokens>, req: Request, next: Next) -> Response {
    if !tokens.enabled() || is_public(req.uri().path()) {
        return next.run(req).await;
    }
    let token = req
        .headers()
        .get(header::AUTHORIZATION)
        .and_then(|v| v.to_str().ok())
        .and_then(bearer_token);
    match token {
        Some(t) if tokens.accepts(t) => next.run(req).await,
        _ => {
            let mut r = api_error(
                ErrorCode::Unauthorized,
                "send Authorization: Bearer <token>",
            )
            .into_response();
            r.headers_mut().insert(
                header::WWW_AUTHENTICATE,
                axum::http::HeaderValue::from_static("Bearer"),
            );
            r
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_configured_tokens_are_accepted_and_hashes_work_like_tokens() {
        let s = Settings {
            api_tokens: vec!["first-secret-token-123".into()],
            api_token_sha256: vec![
                // sha256("second-secret-token-456")
                crate::storage::npy::hex(&Sha256::digest(b"second-secret-token-456")),
            ],
            ..Settings::default()
        };
        let t = Tokens::from_settings(&s);
        assert!(t.enabled());
        assert!(t.accepts("first-secret-token-123"));
        assert!(t.accepts("second-secret-token-456"));
        assert!(!t.accepts("first-secret-token-12"));
        assert!(!t.accepts(""));
        assert!(!Tokens::default().enabled());
    }

    #[test]
    fn the_bearer_scheme_is_case_insensitive_and_the_token_is_not() {
        for v in [
            "Bearer abc",
            "bearer abc",
            "BEARER abc",
            "bEaReR   abc ",
            " Bearer abc",
        ] {
            assert_eq!(bearer_token(v), Some("abc"), "{v:?}");
        }
        assert_eq!(bearer_token("Bearer ABC"), Some("ABC"));
        for v in [
            "Basic abc",
            "Bearerabc",
            "Bearer",
            "Bearer   ",
            "",
            "Token abc",
        ] {
            assert_eq!(bearer_token(v), None, "{v:?}");
        }
    }
}
