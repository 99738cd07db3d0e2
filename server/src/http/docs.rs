//! The API docs page (issue 23, item 4): Swagger UI over this server's `/openapi.json`, its
//! assets embedded in the binary (`server/assets/swagger-ui/`, vendored from npm), so the page
//! works with no internet and no CDN. Public, like the document it shows.

use axum::http::header;
use axum::response::{IntoResponse, Response};

const BUNDLE: &[u8] = include_bytes!("../../assets/swagger-ui/swagger-ui-bundle.js");
const CSS: &[u8] = include_bytes!("../../assets/swagger-ui/swagger-ui.css");

/// The page: loads the embedded assets and points Swagger UI at `/openapi.json`. "Authorize"
/// takes the bearer token once for every request tried from the page.
const PAGE: &str = r##"<!DOCTYPE html>
<html lang="en">
<head>
  <meta charset="utf-8">
  <title>relfusiond API</title>
  <link rel="stylesheet" href="/docs/swagger-ui.css">
</head>
<body>
  <div id="swagger-ui"></div>
  <script src="/docs/swagger-ui-bundle.js"></script>
  <script src="/docs/init.js"></script>
</body>
</html>
"##;

/// Starts Swagger UI; a file of its own, not an inline script, so the page's
/// Content-Security-Policy can refuse every inline script.
const INIT: &str = r##"window.ui = SwaggerUIBundle({
  url: "/openapi.json",
  dom_id: "#swagger-ui",
  deepLinking: true,
  persistAuthorization: true,
});
"##;

/// `GET /docs/init.js`.
pub async fn init() -> Response {
    asset("text/javascript; charset=utf-8", INIT.as_bytes())
}

/// `GET /docs`.
pub async fn page() -> Response {
    super::security::html(PAGE, super::security::DOCS_CSP)
}

/// An asset embedded in the binary. Long-lived caching is safe: the assets change only with
/// the binary.
pub(super) fn asset(content_type: &'static str, body: &'static [u8]) -> Response {
    (
        [
            (header::CONTENT_TYPE, content_type),
            (header::CACHE_CONTROL, "public, max-age=86400"),
        ],
        body,
    )
        .into_response()
}

/// `GET /docs/swagger-ui-bundle.js`.
pub async fn bundle() -> Response {
    asset("text/javascript; charset=utf-8", BUNDLE)
}

/// `GET /docs/swagger-ui.css`.
pub async fn css() -> Response {
    asset("text/css; charset=utf-8", CSS)
}
