//! Binary little-endian PLY point clouds with per-vertex colour (MeshLab, CloudCompare and
//! Open3D read them directly).

use std::io::{BufRead, BufReader, Read, Write};
use std::path::Path;

use crate::{Error, Result};

/// One coloured 3-D point, in world coordinates of the map.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ColoredPoint {
    pub position: [f32; 3],
    pub color: [u8; 3],
}

/// The bytes of `points` as `binary_little_endian` PLY with `x y z` (float) and
/// `red green blue` (uchar) vertex properties (files here, HTTP downloads in the server).
pub fn points_ply_bytes(points: &[ColoredPoint]) -> Vec<u8> {
    let header = format!(
        "ply\nformat binary_little_endian 1.0\ncomment relfusion semi-dense map\nelement vertex {}\n\
         property float x\nproperty float y\nproperty float z\n\
         property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n",
        points.len()
    );
    let mut bytes = Vec::with_capacity(header.len() + points.len() * 15);
    bytes.extend_from_slice(header.as_bytes());
    for p in points {
        for v in p.position {
            bytes.extend_from_slice(&v.to_le_bytes());
        }
        bytes.extend_from_slice(&p.color);
    }
    bytes
}

/// Writes `points` as a PLY file ([`points_ply_bytes`]).
pub fn write_points_ply(path: &Path, points: &[ColoredPoint]) -> Result<()> {
    let bytes = points_ply_bytes(points);
    let mut file = std::fs::File::create(path).map_err(|e| Error::io(path, e))?;
    file.write_all(&bytes).map_err(|e| Error::io(path, e))
}

/// Reads back a point cloud written by [`write_points_ply`] (that exact vertex layout).
pub fn read_points_ply(path: &Path) -> Result<Vec<ColoredPoint>> {
    let file = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
    let mut reader = BufReader::new(file);
    let bad = |why: &str| Error::Shape(format!("{}: {why}", path.display()));
    let mut count = None;
    loop {
        let mut line = String::new();
        if reader
            .read_line(&mut line)
            .map_err(|e| Error::io(path, e))?
            == 0
        {
            return Err(bad("header ends before end_header"));
        }
        let line = line.trim();
        if let Some(n) = line.strip_prefix("element vertex ") {
            count = Some(
                n.trim()
                    .parse::<usize>()
                    .map_err(|_| bad("bad vertex count"))?,
            );
        } else if line.starts_with("format ") && line != "format binary_little_endian 1.0" {
            return Err(bad("not binary_little_endian"));
        } else if line == "end_header" {
            break;
        }
    }
    let count = count.ok_or_else(|| bad("no vertex element"))?;
    let mut body = Vec::new();
    reader
        .read_to_end(&mut body)
        .map_err(|e| Error::io(path, e))?;
    if body.len() != count * 15 {
        return Err(bad("vertex data does not match the header"));
    }
    Ok(body
        .chunks_exact(15)
        .map(|c| {
            let f = |i: usize| f32::from_le_bytes([c[i], c[i + 1], c[i + 2], c[i + 3]]);
            ColoredPoint {
                position: [f(0), f(4), f(8)],
                color: [c[12], c[13], c[14]],
            }
        })
        .collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ply_round_trip_and_truncation() {
        let dir = std::env::temp_dir().join(format!("relfusion-ply-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("temp dir");
        let path = dir.join("p.ply");
        let points: Vec<ColoredPoint> = (0..100)
            .map(|i| ColoredPoint {
                position: [i as f32 * 0.5, -(i as f32), 1e-3 * i as f32],
                color: [i as u8, 255 - i as u8, 7],
            })
            .collect();
        write_points_ply(&path, &points).expect("write");
        assert_eq!(read_points_ply(&path).expect("read"), points);
        let bytes = std::fs::read(&path).expect("bytes");
        std::fs::write(&path, &bytes[..bytes.len() - 1]).expect("truncate");
        assert!(read_points_ply(&path).is_err());
    }
}
