//! The ROS 2 messages relfusion writes and reads, in CDR ([`super::cdr`]): field for field the
//! definitions of [`super::types`].

use super::cdr::{CdrError, CdrReader, CdrWriter};

/// A rigid transform or pose: translation and unit quaternion (x, y, z, w).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Rigid {
    pub t: [f64; 3],
    pub q: [f64; 4],
}

/// One `geometry_msgs/TransformStamped`.
#[derive(Clone, Debug, PartialEq)]
pub struct Transform {
    pub stamp_ns: u64,
    pub parent: String,
    pub child: String,
    pub rigid: Rigid,
}

/// `builtin_interfaces/Time` from nanoseconds (seconds saturate at `i32::MAX`, year 2038).
fn time(w: &mut CdrWriter, ns: u64) {
    let sec = i32::try_from(ns / 1_000_000_000).unwrap_or(i32::MAX);
    w.i32(sec);
    w.u32((ns % 1_000_000_000) as u32);
}

fn header(w: &mut CdrWriter, stamp_ns: u64, frame_id: &str) {
    time(w, stamp_ns);
    w.string(frame_id);
}

fn pose(w: &mut CdrWriter, p: &Rigid) {
    for v in p.t.iter().chain(&p.q) {
        w.f64(*v);
    }
}

/// `geometry_msgs/PoseStamped`.
pub fn pose_stamped(stamp_ns: u64, frame_id: &str, p: &Rigid) -> Vec<u8> {
    let mut w = CdrWriter::with_capacity(96);
    header(&mut w, stamp_ns, frame_id);
    pose(&mut w, p);
    w.finish()
}

/// `nav_msgs/Path`: stamped poses, all in `frame_id`.
pub fn path(stamp_ns: u64, frame_id: &str, poses: &[(u64, Rigid)]) -> Vec<u8> {
    let mut w = CdrWriter::with_capacity(32 + poses.len() * 96);
    header(&mut w, stamp_ns, frame_id);
    w.len(poses.len());
    for (stamp, p) in poses {
        header(&mut w, *stamp, frame_id);
        pose(&mut w, p);
    }
    w.finish()
}

/// `tf2_msgs/TFMessage`.
pub fn tf_message(transforms: &[Transform]) -> Vec<u8> {
    let mut w = CdrWriter::with_capacity(transforms.len() * 128);
    w.len(transforms.len());
    for t in transforms {
        header(&mut w, t.stamp_ns, &t.parent);
        w.string(&t.child);
        pose(&mut w, &t.rigid);
    }
    w.finish()
}

/// `sensor_msgs/PointField.FLOAT32`.
const FLOAT32: u8 = 7;

/// `sensor_msgs/PointCloud2` of unorganised points with fields `x y z` (float32).
pub fn point_cloud2(stamp_ns: u64, frame_id: &str, points: &[[f32; 3]]) -> Vec<u8> {
    let mut w = CdrWriter::with_capacity(128 + points.len() * 12);
    header(&mut w, stamp_ns, frame_id);
    w.u32(1);
    w.len(points.len());
    w.len(3);
    for (i, name) in ["x", "y", "z"].into_iter().enumerate() {
        w.string(name);
        w.u32(4 * i as u32);
        w.u8(FLOAT32);
        w.u32(1);
    }
    w.bool(false);
    w.u32(12);
    w.len(points.len() * 12); // row_step
    let data: Vec<u8> = points
        .iter()
        .flatten()
        .flat_map(|v| v.to_le_bytes())
        .collect();
    w.bytes(&data);
    w.bool(true);
    w.finish()
}

/// `visualization_msgs/Marker.TRIANGLE_LIST`, `.ADD`, `.DELETE`.
const TRIANGLE_LIST: i32 = 11;
const ADD: i32 = 0;
const DELETE: i32 = 2;

/// One marker of a [`marker_array`].
#[derive(Clone, Copy, Debug)]
pub enum Marker<'a> {
    /// A triangle list: three vertices per triangle, colour per vertex.
    Triangles {
        ns: &'a str,
        positions: &'a [[f32; 3]],
        colors: &'a [[u8; 3]],
        indices: &'a [u32],
    },
    Delete {
        ns: &'a str,
    },
}

/// `visualization_msgs/MarkerArray`, every marker in `frame_id` with id 0 in its own
/// namespace (a mesh block's name), so a newer marker of a block replaces the older.
pub fn marker_array(stamp_ns: u64, frame_id: &str, markers: &[Marker<'_>]) -> Vec<u8> {
    let mut w = CdrWriter::new();
    w.len(markers.len());
    for marker in markers {
        let (ns, action) = match marker {
            Marker::Triangles { ns, .. } => (*ns, ADD),
            Marker::Delete { ns } => (*ns, DELETE),
        };
        header(&mut w, stamp_ns, frame_id);
        w.string(ns);
        w.i32(0);
        w.i32(TRIANGLE_LIST);
        w.i32(action);
        pose(
            &mut w,
            &Rigid {
                t: [0.0; 3],
                q: [0.0, 0.0, 0.0, 1.0],
            },
        );
        for s in [1.0, 1.0, 1.0] {
            w.f64(s);
        }
        for c in [1.0f32; 4] {
            w.f32(c);
        }
        // lifetime 0 (forever), frame_locked false
        w.i32(0);
        w.u32(0);
        w.bool(false);
        match marker {
            Marker::Triangles {
                positions,
                colors,
                indices,
                ..
            } => {
                let valid: Vec<usize> = indices
                    .chunks_exact(3)
                    .filter(|t| t.iter().all(|&i| (i as usize) < positions.len()))
                    .flatten()
                    .map(|&i| i as usize)
                    .collect();
                w.len(valid.len());
                for &i in &valid {
                    for v in positions[i] {
                        w.f64(f64::from(v));
                    }
                }
                w.len(valid.len());
                for &i in &valid {
                    let c = colors.get(i).copied().unwrap_or([200, 200, 200]);
                    for v in c {
                        w.f32(f32::from(v) / 255.0);
                    }
                    w.f32(1.0);
                }
            }
            Marker::Delete { .. } => {
                w.len(0);
                w.len(0);
            }
        }
        w.string(""); // texture_resource
        header(&mut w, 0, ""); // texture: an empty CompressedImage
        w.string("");
        w.len(0);
        w.len(0); // uv_coordinates
        w.string(""); // text
        w.string(""); // mesh_resource
        w.string(""); // mesh_file: empty
        w.len(0);
        w.bool(false); // mesh_use_embedded_materials
    }
    w.finish()
}

/// `sensor_msgs/CompressedImage` (`format`: "jpeg" or "png").
pub fn compressed_image(stamp_ns: u64, frame_id: &str, format: &str, data: &[u8]) -> Vec<u8> {
    let mut w = CdrWriter::with_capacity(data.len() + 64);
    header(&mut w, stamp_ns, frame_id);
    w.string(format);
    w.bytes(data);
    w.finish()
}

/// A `sensor_msgs/Image` as read.
#[derive(Clone, Debug, PartialEq)]
pub struct ImageMsg<'a> {
    pub stamp_ns: u64,
    pub height: u32,
    pub width: u32,
    pub encoding: String,
    pub big_endian: bool,
    pub step: u32,
    pub data: &'a [u8],
}

/// A `sensor_msgs/CompressedImage` as read.
#[derive(Clone, Debug, PartialEq)]
pub struct CompressedImageMsg<'a> {
    pub stamp_ns: u64,
    pub format: String,
    pub data: &'a [u8],
}

/// What relfusion reads of a `sensor_msgs/CameraInfo`.
#[derive(Clone, Debug, PartialEq)]
pub struct CameraInfoMsg {
    pub stamp_ns: u64,
    pub height: u32,
    pub width: u32,
    pub distortion_model: String,
    pub d: Vec<f64>,
    /// Row-major 3×3 intrinsics.
    pub k: [f64; 9],
}

fn read_stamp(r: &mut CdrReader<'_>) -> Result<u64, CdrError> {
    let sec = r.i32()?;
    let nanosec = r.u32()?;
    // Stamps before 1970 are clamped to 0: relfusion's timestamps are non-negative.
    Ok((sec.max(0) as u64) * 1_000_000_000 + u64::from(nanosec.min(999_999_999)))
}

fn read_header(r: &mut CdrReader<'_>) -> Result<u64, CdrError> {
    let stamp = read_stamp(r)?;
    r.string()?;
    Ok(stamp)
}

pub fn read_image(data: &[u8]) -> Result<ImageMsg<'_>, CdrError> {
    let mut r = CdrReader::new(data)?;
    Ok(ImageMsg {
        stamp_ns: read_header(&mut r)?,
        height: r.u32()?,
        width: r.u32()?,
        encoding: r.string()?,
        big_endian: r.u8()? != 0,
        step: r.u32()?,
        data: r.bytes()?,
    })
}

pub fn read_compressed_image(data: &[u8]) -> Result<CompressedImageMsg<'_>, CdrError> {
    let mut r = CdrReader::new(data)?;
    Ok(CompressedImageMsg {
        stamp_ns: read_header(&mut r)?,
        format: r.string()?,
        data: r.bytes()?,
    })
}

pub fn read_camera_info(data: &[u8]) -> Result<CameraInfoMsg, CdrError> {
    let mut r = CdrReader::new(data)?;
    let stamp_ns = read_header(&mut r)?;
    let height = r.u32()?;
    let width = r.u32()?;
    let distortion_model = r.string()?;
    let n = r.len(8)?;
    let d = (0..n).map(|_| r.f64()).collect::<Result<Vec<_>, _>>()?;
    let k = r.f64s::<9>()?;
    Ok(CameraInfoMsg {
        stamp_ns,
        height,
        width,
        distortion_model,
        d,
        k,
    })
}

/// Writers of a camera's messages: recordings with images, and tools that play a ROS 2
/// camera.
pub mod camera {
    use super::*;

    /// `sensor_msgs/Image` (`rgb8`, tightly packed).
    pub fn image_rgb8(
        stamp_ns: u64,
        frame_id: &str,
        width: u32,
        height: u32,
        rgb: &[u8],
    ) -> Vec<u8> {
        let mut w = CdrWriter::with_capacity(rgb.len() + 64);
        header(&mut w, stamp_ns, frame_id);
        w.u32(height);
        w.u32(width);
        w.string("rgb8");
        w.u8(0);
        w.u32(width * 3);
        w.bytes(rgb);
        w.finish()
    }

    /// `sensor_msgs/CameraInfo` with a `plumb_bob` model (`d` = k1 k2 p1 p2 k3).
    pub fn camera_info(
        stamp_ns: u64,
        frame_id: &str,
        width: u32,
        height: u32,
        [fx, fy, cx, cy]: [f64; 4],
        d: [f64; 5],
    ) -> Vec<u8> {
        let mut w = CdrWriter::with_capacity(400);
        header(&mut w, stamp_ns, frame_id);
        w.u32(height);
        w.u32(width);
        w.string("plumb_bob");
        w.len(5);
        d.iter().for_each(|v| w.f64(*v));
        for v in [fx, 0.0, cx, 0.0, fy, cy, 0.0, 0.0, 1.0] {
            w.f64(v);
        }
        for v in [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0] {
            w.f64(v);
        }
        for v in [fx, 0.0, cx, 0.0, 0.0, fy, cy, 0.0, 0.0, 0.0, 1.0, 0.0] {
            w.f64(v);
        }
        w.u32(0);
        w.u32(0);
        for _ in 0..4 {
            w.u32(0);
        }
        w.bool(false);
        w.finish()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn camera_messages_read_back() {
        let info = camera::camera_info(
            1_500_000_000,
            "cam",
            640,
            480,
            [500.0, 501.0, 320.0, 240.0],
            [0.1, -0.2, 0.0, 0.0, 0.05],
        );
        let read = read_camera_info(&info).expect("CameraInfo");
        assert_eq!((read.width, read.height), (640, 480));
        assert_eq!(read.k[0], 500.0);
        assert_eq!(read.k[4], 501.0);
        assert_eq!(read.d, vec![0.1, -0.2, 0.0, 0.0, 0.05]);
        assert_eq!(read.stamp_ns, 1_500_000_000);
        let rgb = vec![7u8; 4 * 2 * 3];
        let image = camera::image_rgb8(3, "cam", 4, 2, &rgb);
        let read = read_image(&image).expect("Image");
        assert_eq!((read.width, read.height, read.step), (4, 2, 12));
        assert_eq!(read.encoding, "rgb8");
        assert_eq!(read.data, &rgb[..]);
        assert!(read_image(&image[..image.len() - 1]).is_err());
    }

    #[test]
    fn clouds_and_markers_have_their_sizes() {
        let cloud = point_cloud2(0, "world", &[[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]);
        // Header (8 + 4 + 6 "world\0", padded to 20), then the fixed fields.
        assert!(cloud.len() > 24 + 2 * 12);
        let positions = [[0.0f32; 3], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]];
        let colors = [[255u8, 0, 0]; 3];
        let one = marker_array(
            0,
            "world",
            &[Marker::Triangles {
                ns: "block_0_0_0",
                positions: &positions,
                colors: &colors,
                // The second triangle points outside the block and is left out.
                indices: &[0, 1, 2, 0, 1, 9],
            }],
        );
        let none = marker_array(
            0,
            "world",
            &[Marker::Triangles {
                ns: "block_0_0_0",
                positions: &positions,
                colors: &colors,
                indices: &[],
            }],
        );
        assert_eq!(one.len() - none.len(), 3 * 24 + 3 * 16);
    }
}
