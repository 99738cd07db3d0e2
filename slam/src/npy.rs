//! Minimal NumPy `.npy` (format 1.0, little-endian `<f4`, C order) reader and writer.
//!
//! Depth maps and benchmark inputs are exchanged as `.npy` so that other implementations
//! (PyTorch, NumPy) can read and produce the same arrays without any conversion step.

use std::path::Path;

use crate::image::ImageF32;
use crate::{Error, Result};

const MAGIC: &[u8] = b"\x93NUMPY";

/// Writes a 2-D float32 array of shape `(height, width)`.
pub fn write_f32(path: &Path, image: &ImageF32) -> Result<()> {
    let mut header = format!(
        "{{'descr': '<f4', 'fortran_order': False, 'shape': ({}, {}), }}",
        image.height, image.width
    );
    // Header length (magic + version + len field + header + '\n') is padded to 64 bytes.
    let unpadded = MAGIC.len() + 2 + 2 + header.len() + 1;
    header.push_str(&" ".repeat((64 - unpadded % 64) % 64));
    header.push('\n');
    let mut bytes = Vec::with_capacity(unpadded + 64 + image.data.len() * 4);
    bytes.extend_from_slice(MAGIC);
    bytes.extend_from_slice(&[1, 0]);
    bytes.extend_from_slice(&(header.len() as u16).to_le_bytes());
    bytes.extend_from_slice(header.as_bytes());
    for v in &image.data {
        bytes.extend_from_slice(&v.to_le_bytes());
    }
    std::fs::write(path, bytes).map_err(|e| Error::io(path, e))
}

/// Reads a 2-D little-endian float32 array written in C order.
pub fn read_f32(path: &Path) -> Result<ImageF32> {
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    let bad = |why: &str| {
        Error::Shape(format!(
            "{}: not a 2-D float32 .npy ({why})",
            path.display()
        ))
    };
    if bytes.len() < 10 || &bytes[..6] != MAGIC {
        return Err(bad("missing magic"));
    }
    let (header_len, start) = match bytes[6] {
        1 => (u16::from_le_bytes([bytes[8], bytes[9]]) as usize, 10),
        2 | 3 if bytes.len() >= 12 => (
            u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]) as usize,
            12,
        ),
        _ => return Err(bad("unsupported version")),
    };
    let header = bytes
        .get(start..start + header_len)
        .and_then(|h| std::str::from_utf8(h).ok())
        .ok_or_else(|| bad("truncated header"))?;
    if !header.contains("'<f4'") {
        return Err(bad("dtype is not <f4"));
    }
    if header.contains("'fortran_order': True") {
        return Err(bad("Fortran order"));
    }
    let shape = header
        .split("'shape':")
        .nth(1)
        .and_then(|s| s.split(')').next())
        .map(|s| s.trim().trim_start_matches('('))
        .ok_or_else(|| bad("no shape"))?;
    let dims: Vec<usize> = shape
        .split(',')
        .map(str::trim)
        .filter(|s| !s.is_empty())
        .map(|s| s.parse().map_err(|_| bad("bad shape")))
        .collect::<Result<_>>()?;
    let [height, width] = dims[..] else {
        return Err(bad("not 2-D"));
    };
    let payload = &bytes[start + header_len..];
    if payload.len() != width * height * 4 {
        return Err(bad("payload size does not match shape"));
    }
    let data = payload
        .chunks_exact(4)
        .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect();
    ImageF32::from_vec(width, height, data).map_err(Into::into)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_keeps_shape_and_values() {
        let dir = std::env::temp_dir().join(format!("relfusion-npy-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("temp dir");
        let path = dir.join("a.npy");
        let img =
            ImageF32::from_vec(3, 2, vec![0.0, 1.5, -2.0, 3.25, f32::MAX, 1e-7]).expect("shape");
        write_f32(&path, &img).expect("write");
        let bytes = std::fs::read(&path).expect("read back");
        assert_eq!(
            (bytes.len() - 6 * 4) % 64,
            0,
            "header must be 64-byte aligned"
        );
        assert_eq!(read_f32(&path).expect("read"), img);
    }

    #[test]
    fn truncated_file_is_an_error() {
        let dir = std::env::temp_dir().join(format!("relfusion-npy-t-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("temp dir");
        let path = dir.join("b.npy");
        write_f32(&path, &ImageF32::filled(4, 4, 1.0)).expect("write");
        let bytes = std::fs::read(&path).expect("read back");
        std::fs::write(&path, &bytes[..bytes.len() - 3]).expect("truncate");
        assert!(read_f32(&path).is_err());
    }
}
