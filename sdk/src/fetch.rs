//! Downloads a session's results into a folder: the same file names `relfusion run` uses, so
//! `relfusion eval` and other tools read either.

use std::path::{Path, PathBuf};

use serde::Serialize;

use crate::api::{Client, is_not_found};
use crate::error::ClientError;

/// Results every session has (the request fails without them).
const REQUIRED: [(&str, &str); 3] = [
    ("trajectory", "trajectory.txt"),
    ("keyframes", "keyframes.txt"),
    ("pointcloud.ply", "pointcloud.ply"),
];
/// Results a session may not have yet (no mesh before the fusion stage has run, no recording
/// before it ends).
const OPTIONAL: [(&str, &str); 3] = [
    ("mesh.ply", "mesh.ply"),
    ("mesh.glb", "mesh.glb"),
    ("recording.mcap", "recording.mcap"),
];

/// What [`fetch`] wrote.
#[derive(Clone, Debug, Default, Serialize)]
pub struct Fetched {
    /// Files written, with their sizes in bytes.
    pub files: Vec<(PathBuf, u64)>,
    /// Optional results the server does not have (yet), with its reason.
    pub missing: Vec<(String, String)>,
}

/// Writes `trajectory.txt`, `keyframes.txt`, `pointcloud.ply` and, when the server has them,
/// `mesh.ply`, `mesh.glb` and `recording.mcap` of session `id` into `out_dir` (created). Each file is written
/// to a temporary name and renamed, so a folder never holds half a download.
pub async fn fetch(client: &Client, id: &str, out_dir: &Path) -> Result<Fetched, ClientError> {
    std::fs::create_dir_all(out_dir).map_err(|e| ClientError::io(out_dir, e))?;
    let mut fetched = Fetched::default();
    for (route, file) in REQUIRED {
        let bytes = client.download(id, route).await?;
        fetched
            .files
            .push(write_atomic(&out_dir.join(file), &bytes)?);
    }
    for (route, file) in OPTIONAL {
        match client.download(id, route).await {
            Ok(bytes) => fetched
                .files
                .push(write_atomic(&out_dir.join(file), &bytes)?),
            Err(e) if is_not_found(&e) => {
                let reason = match &e {
                    ClientError::Api { message, .. } => message.clone(),
                    other => other.to_string(),
                };
                fetched.missing.push((file.to_string(), reason));
            }
            Err(e) => return Err(e),
        }
    }
    Ok(fetched)
}

fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(PathBuf, u64), ClientError> {
    let tmp = path.with_extension("part");
    std::fs::write(&tmp, bytes).map_err(|e| ClientError::io(&tmp, e))?;
    std::fs::rename(&tmp, path).map_err(|e| ClientError::io(path, e))?;
    Ok((path.to_path_buf(), bytes.len() as u64))
}
