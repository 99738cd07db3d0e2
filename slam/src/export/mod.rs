//! Files a person opens: point clouds, and the fused mesh as PLY (MeshLab, CloudCompare) or
//! binary glTF (Blender, web viewers).

pub mod glb;
pub mod mesh_ply;
pub mod ply;

pub use glb::{mesh_glb_bytes, mesh_glb_bytes_from, write_mesh_glb, write_mesh_glb_from};
pub use mesh_ply::{
    mesh_ply_bytes, mesh_ply_bytes_from, read_mesh_ply, write_mesh_ply, write_mesh_ply_from,
};
pub use ply::{ColoredPoint, points_ply_bytes, read_points_ply, write_points_ply};

use std::io::Write;
use std::path::Path;
use std::sync::atomic::{AtomicU64, Ordering};

use crate::{Error, Result};

/// Writes `bytes` to a temporary file beside `path` and renames it over `path`, so a reader
/// (a viewer polling the file, a download) never sees a half-written mesh. The temporary name
/// carries the process id and a counter so concurrent exports to one path cannot interleave.
fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    write_atomic_with(path, |out| {
        out.write_all(bytes).map_err(|e| Error::io(path, e))
    })
}

/// A streaming mesh encoder: writes the surface of a source to `out`, mapping write errors
/// with the function given.
type SurfaceEncoder = fn(
    &mut dyn crate::fusion::weld::BlockSource,
    &mut dyn Write,
    &dyn Fn(std::io::Error) -> Error,
) -> Result<crate::fusion::weld::WeldCounts>;

/// `encode`s `source` into the file `path`, atomically.
fn encode_to_file(
    path: &Path,
    source: &mut dyn crate::fusion::weld::BlockSource,
    encode: SurfaceEncoder,
) -> Result<crate::fusion::weld::WeldCounts> {
    write_atomic_with(path, |out| encode(source, out, &|e| Error::io(path, e)))
}

/// `encode`s `source` into bytes (`name` only names the output in errors, which a `Vec`
/// never raises).
fn encode_to_bytes(
    name: &str,
    source: &mut dyn crate::fusion::weld::BlockSource,
    encode: SurfaceEncoder,
) -> Result<Vec<u8>> {
    let mut bytes = Vec::new();
    encode(source, &mut bytes, &|e| Error::io(Path::new(name), e))?;
    Ok(bytes)
}

/// [`write_atomic`] for a file written piece by piece by `write` (buffered).
fn write_atomic_with<T>(path: &Path, write: impl FnOnce(&mut dyn Write) -> Result<T>) -> Result<T> {
    static COUNTER: AtomicU64 = AtomicU64::new(0);
    let name = path.file_name().ok_or_else(|| {
        Error::io(
            path,
            std::io::Error::new(std::io::ErrorKind::InvalidInput, "not a file path"),
        )
    })?;
    let mut tmp_name = name.to_os_string();
    tmp_name.push(format!(
        ".{}-{}.tmp",
        std::process::id(),
        COUNTER.fetch_add(1, Ordering::Relaxed)
    ));
    let tmp = path.with_file_name(tmp_name);
    let written = std::fs::File::create(&tmp)
        .map_err(|e| Error::io(&tmp, e))
        .and_then(|file| {
            let mut out = std::io::BufWriter::new(file);
            let value = write(&mut out)?;
            out.flush().map_err(|e| Error::io(&tmp, e))?;
            Ok(value)
        })
        .and_then(|value| {
            std::fs::rename(&tmp, path).map_err(|e| Error::io(path, e))?;
            Ok(value)
        });
    if written.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    written
}
