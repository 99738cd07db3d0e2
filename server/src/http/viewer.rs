//! The live viewer (issue 23, item 1): `GET /` lists the caller's sessions, `GET /view/{id}`
//! shows one live — trajectory, keyframes, the camera, the fused mesh patched block by block
//! from `MeshUpdate`s, a status panel. The page is built from `server/viewer/` (three.js and
//! protobufjs from npm, bundled by `scripts/build-viewer.sh`) into `server/assets/viewer/` (its
//! stylesheet is served from the source, `server/viewer/viewer.css`),
//! embedded here: it works with no internet and no CDN. The pages are public; everything they
//! show comes from the token-checked API (the token is entered once in the page, or passed as
//! `?access_token=` in a link, which the page takes once and removes from the address bar).

use axum::response::Response;

use super::docs::asset;

const SCRIPT: &[u8] = include_bytes!("../../assets/viewer/viewer.js");
const STYLE: &[u8] = include_bytes!("../../viewer/viewer.css");
const LICENSES: &[u8] = include_bytes!("../../assets/viewer/licenses.txt");

/// One shell for both pages: the script reads the path to know which it is.
const PAGE: &str = r#"<!DOCTYPE html>
<html lang="en">
<head>
  <meta charset="utf-8">
  <meta name="viewport" content="width=device-width, initial-scale=1">
  <title>relfusion viewer</title>
  <link rel="stylesheet" href="/viewer/viewer.css">
</head>
<body>
  <div id="app"></div>
  <script type="module" src="/viewer/viewer.js"></script>
</body>
</html>
"#;

/// `GET /` and `GET /view/{id}`.
pub async fn page() -> Response {
    super::security::html(PAGE, super::security::VIEWER_CSP)
}

/// `GET /viewer/viewer.js`: the bundle (three.js, protobufjs and the viewer's code).
pub async fn script() -> Response {
    asset("text/javascript; charset=utf-8", SCRIPT)
}

/// `GET /viewer/viewer.css`.
pub async fn style() -> Response {
    asset("text/css; charset=utf-8", STYLE)
}

/// `GET /viewer/licenses.txt`: the licence notices of the bundled libraries.
pub async fn licenses() -> Response {
    asset("text/plain; charset=utf-8", LICENSES)
}
