//! `relfusion bench viewer --server URL`: the viewer's bundle size and its frame rate in
//! Debian's headless Chromium (SwiftShader, no GPU) with an N-triangle mesh split into blocks
//! as `MeshUpdate`s deliver it (the page `/view/bench?triangles=N`, rotating the view so that
//! every frame is drawn).

use std::time::Duration;

use anyhow::Context as _;
use relfusion_client::browser::{Driver, eval, wait_until};
use serde_json::json;

use super::connect::{ConnectArgs, runtime};

#[derive(Debug, clap::Args)]
pub struct ViewerArgs {
    #[command(flatten)]
    pub connect: ConnectArgs,
    /// Triangles of the generated mesh.
    #[arg(long, default_value_t = 200_000)]
    pub triangles: u64,
    /// Seconds the frame rate is measured over (after 1 s of warm-up).
    #[arg(long, default_value_t = 5)]
    pub seconds: u64,
    /// Canvas size in pixels, WIDTHxHEIGHT of the browser window.
    #[arg(long, default_value = "1280x800")]
    pub window: String,
}

pub fn viewer(args: &ViewerArgs) -> anyhow::Result<()> {
    let (width, height) = args
        .window
        .split_once('x')
        .and_then(|(w, h)| Some((w.parse::<u32>().ok()?, h.parse::<u32>().ok()?)))
        .context("--window must be WIDTHxHEIGHT, e.g. 1280x800")?;
    let server = args.connect.server();
    let server = server.trim_end_matches('/');
    let work = scratch_dir()?;
    runtime()?.block_on(async {
        let bundle = reqwest::get(format!("{server}/viewer/viewer.js"))
            .await?
            .error_for_status()?
            .bytes()
            .await?
            .len();
        let mut driver = Driver::start(&work)?;
        let page = driver.browser(width, height).await?;
        page.goto(&format!(
            "{server}/view/bench?triangles={}&seconds={}",
            args.triangles, args.seconds
        ))
        .await?;
        let timeout = Duration::from_secs(args.seconds + 120);
        wait_until(
            &page,
            "!!window.relfusionViewer && window.relfusionViewer.finished",
            timeout,
            "bench",
        )
        .await?;
        let figures = eval(
            &page,
            "{fps: window.relfusionViewer.benchFps, triangles: window.relfusionViewer.benchTriangles, blocks: window.relfusionViewer.benchBlocks, errors: window.relfusionViewer.errors, renderer: (() => { const gl = document.createElement('canvas').getContext('webgl2'); const i = gl && gl.getExtension('WEBGL_debug_renderer_info'); return i ? gl.getParameter(i.UNMASKED_RENDERER_WEBGL) : 'unknown'; })()}",
        )
        .await?;
        page.close().await?;
        println!(
            "{}",
            json!({
                "bundle_bytes": bundle,
                "window": args.window,
                "triangles": figures["triangles"],
                "blocks": figures["blocks"],
                "fps": figures["fps"],
                "webgl_renderer": figures["renderer"],
                "page_errors": figures["errors"],
            })
        );
        anyhow::Ok(())
    })?;
    let _ = std::fs::remove_dir_all(&work);
    Ok(())
}

/// A fresh directory for the browser's profile and the driver's log.
fn scratch_dir() -> anyhow::Result<std::path::PathBuf> {
    let dir = std::env::temp_dir().join(format!("relfusion-bench-viewer-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir)?;
    Ok(dir)
}
