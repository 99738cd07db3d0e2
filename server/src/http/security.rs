//! Security headers on every response, and the Content-Security-Policy of the HTML pages.
//!
//! Every response says `nosniff` (a download is never run as a script or page),
//! `Referrer-Policy: no-referrer` (a page's address, which may carry a token, never leaves
//! with a request) and `X-Frame-Options: DENY` (no page is framed: no clickjacking). HTML
//! pages set their own policy with [`html`]; any other HTML response gets [`STRICT_CSP`].

use axum::extract::Request;
use axum::http::{HeaderValue, header};
use axum::middleware::Next;
use axum::response::{Html, IntoResponse, Response};

/// The policy of HTML without scripts (error pages and the like).
pub const STRICT_CSP: &str = "default-src 'none'; style-src 'self'; img-src 'self'; \
    base-uri 'none'; form-action 'none'; frame-ancestors 'none'";

/// The API docs: Swagger UI's own script and styles (it sets inline styles), the OpenAPI
/// document and requests tried from the page, nothing from elsewhere.
pub const DOCS_CSP: &str = "default-src 'none'; script-src 'self'; \
    style-src 'self' 'unsafe-inline'; img-src 'self' data:; connect-src 'self'; \
    font-src 'self'; base-uri 'none'; form-action 'none'; frame-ancestors 'none'";

/// The viewer: its bundle only (no inline script). protobufjs compiles its decoders with
/// `Function` at run time, hence `'unsafe-eval'`; no other origin can be reached or loaded.
pub const VIEWER_CSP: &str = "default-src 'none'; script-src 'self' 'unsafe-eval'; \
    style-src 'self' 'unsafe-inline'; img-src 'self' data: blob:; connect-src 'self'; \
    worker-src 'self' blob:; base-uri 'none'; form-action 'none'; frame-ancestors 'none'";

/// An HTML page with its policy.
pub fn html(page: &'static str, csp: &'static str) -> Response {
    let mut response = Html(page).into_response();
    response.headers_mut().insert(
        header::CONTENT_SECURITY_POLICY,
        HeaderValue::from_static(csp),
    );
    response
}

/// The middleware (see the module docs).
pub async fn headers(request: Request, next: Next) -> Response {
    let mut response = next.run(request).await;
    let headers = response.headers_mut();
    for (name, value) in [
        (header::X_CONTENT_TYPE_OPTIONS, "nosniff"),
        (header::REFERRER_POLICY, "no-referrer"),
        (header::X_FRAME_OPTIONS, "DENY"),
    ] {
        headers.insert(name, HeaderValue::from_static(value));
    }
    let is_html = headers
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|v| v.starts_with("text/html"));
    if is_html && !headers.contains_key(header::CONTENT_SECURITY_POLICY) {
        headers.insert(
            header::CONTENT_SECURITY_POLICY,
            HeaderValue::from_static(STRICT_CSP),
        );
    }
    response
}
