//! The fused mesh as binary glTF 2.0 (`.glb`, Khronos glTF 2.0 specification §4.4): one file
//! that Blender, three.js/Babylon viewers, Windows 3D Viewer and most game engines open.
//!
//! Layout: one buffer (the BIN chunk) holding positions (f32 VEC3), normals (f32 VEC3),
//! colours (normalised u8 VEC3 with a byte stride of 4, because the spec requires every vertex
//! attribute element to start on a 4-byte boundary) and indices (u32), each in its own buffer
//! view; one mesh with one indexed `TRIANGLES` primitive; one node; one scene. The material is
//! non-metallic and rough, and asks for `KHR_materials_unlit` (used, not required): the vertex
//! colours come from camera images and already contain the scene's lighting, so a viewer that
//! supports the extension shows them as captured, and one that does not still shades a matte
//! surface.
//!
//! **Units and axes.** glTF says metres and +Y up; a monocular map has neither. Coordinates are
//! map units (an unknown scale of the scene, fixed by the first keyframes) in the map's frame,
//! the first keyframe's camera frame (x right, y down, z forward), so the scene's up axis is
//! not known and a viewer may show the scene tilted or upside down.

use std::io::Write;
use std::path::Path;

use serde_json::{Value, json};

use super::{encode_to_bytes, encode_to_file, write_atomic};
use crate::fusion::Mesh;
use crate::fusion::weld::{BlockSource, Bounds, WeldCounts, each_triangle, each_vertex, weld};
use crate::{Error, Result};

/// `glTF` in ASCII, little-endian (spec §4.4.2).
const GLB_MAGIC: u32 = 0x4654_6C67;
const GLB_VERSION: u32 = 2;
/// Chunk types `JSON` and `BIN\0`.
const CHUNK_JSON: u32 = 0x4E4F_534A;
const CHUNK_BIN: u32 = 0x004E_4942;

/// glTF enumerations (spec §5): component types, buffer-view targets, primitive mode.
const FLOAT: u32 = 5126;
const UNSIGNED_BYTE: u32 = 5121;
const UNSIGNED_INT: u32 = 5125;
const ARRAY_BUFFER: u32 = 34962;
const ELEMENT_ARRAY_BUFFER: u32 = 34963;
const TRIANGLES: u32 = 4;

/// The bytes of `mesh` as a GLB file (see the module docs for the layout).
///
/// A mesh without triangles becomes a scene with one empty node and no buffer: glTF forbids
/// meshes without primitives and accessors with zero elements, and an empty scene is what
/// every loader accepts. `mesh` must be consistent (one normal and colour per position,
/// indices below the vertex count), as [`Mesh::from_blocks`] builds it.
pub fn mesh_glb_bytes(mesh: &Mesh) -> Vec<u8> {
    debug_assert!(mesh.normals.len() == mesh.positions.len());
    debug_assert!(mesh.colors.len() == mesh.positions.len());
    if mesh.is_empty() {
        return container(&scene(None), None);
    }
    let n = mesh.positions.len();
    let mut bin = Vec::with_capacity(n * 28 + mesh.indices.len() * 4);
    for v in mesh.positions.iter().chain(&mesh.normals).flatten() {
        bin.extend_from_slice(&v.to_le_bytes());
    }
    for c in &mesh.colors {
        bin.extend_from_slice(&color_element(*c));
    }
    for i in &mesh.indices {
        bin.extend_from_slice(&i.to_le_bytes());
    }
    let mut bounds = Bounds::default();
    mesh.positions.iter().for_each(|p| bounds.add(*p));
    let doc = scene(Some((n, mesh.indices.len(), bounds)));
    let mut out = container(&doc, Some(bin.len()));
    out.extend_from_slice(&bin);
    out.resize(out.len().next_multiple_of(4), 0);
    out
}

/// Writes `mesh` as a GLB file ([`mesh_glb_bytes`]), atomically (temporary file + rename).
pub fn write_mesh_glb(path: &Path, mesh: &Mesh) -> Result<()> {
    write_atomic(path, &mesh_glb_bytes(mesh))
}

/// Writes the surface of `source` as a GLB file, the same bytes as [`write_mesh_glb`] of its
/// welded mesh, a block at a time: one pass counts and bounds the vertices (the JSON chunk
/// comes first), then one pass per buffer view (positions, normals, colours, indices), each
/// welding as it goes ([`crate::fusion::weld`]). Atomic like [`write_mesh_glb`].
pub fn write_mesh_glb_from(path: &Path, source: &mut dyn BlockSource) -> Result<WeldCounts> {
    encode_to_file(path, source, encode)
}

/// The bytes [`write_mesh_glb_from`] writes.
pub fn mesh_glb_bytes_from(source: &mut dyn BlockSource) -> Result<Vec<u8>> {
    encode_to_bytes("mesh.glb", source, encode)
}

fn encode(
    source: &mut dyn BlockSource,
    out: &mut dyn Write,
    io: &dyn Fn(std::io::Error) -> Error,
) -> Result<WeldCounts> {
    let mut bounds = Bounds::default();
    let counts = weld(source, &mut bounds)?;
    if counts.triangles == 0 {
        out.write_all(&container(&scene(None), None)).map_err(io)?;
        return Ok(counts);
    }
    let (n, indices) = (counts.vertices as usize, counts.triangles as usize * 3);
    let doc = scene(Some((n, indices, bounds)));
    out.write_all(&container(&doc, Some(n * 28 + indices * 4)))
        .map_err(io)?;
    for view in 0..3 {
        each_vertex(source, |p, normal, c| {
            let mut element = [0u8; 12];
            let bytes: &[u8] = match view {
                0 | 1 => {
                    let v = if view == 0 { p } else { normal };
                    for (k, x) in v.iter().enumerate() {
                        element[4 * k..4 * k + 4].copy_from_slice(&x.to_le_bytes());
                    }
                    &element
                }
                _ => {
                    element[..4].copy_from_slice(&color_element(c));
                    &element[..4]
                }
            };
            out.write_all(bytes).map_err(io)
        })?;
    }
    each_triangle(source, |t| {
        let mut element = [0u8; 12];
        for (k, i) in t.iter().enumerate() {
            element[4 * k..4 * k + 4].copy_from_slice(&i.to_le_bytes());
        }
        out.write_all(&element).map_err(io)
    })?;
    Ok(counts)
}

/// A colour as its `COLOR_0` element: normalised u8 VEC3 padded to 4 bytes.
fn color_element(c: [u8; 3]) -> [u8; 4] {
    [c[0], c[1], c[2], 0]
}

/// The glTF document: the scene, and with `(vertices, indices, bounds)` the mesh whose BIN
/// chunk holds positions, normals, colours and indices in that order.
fn scene(mesh: Option<(usize, usize, Bounds)>) -> Value {
    let mut doc = json!({
        "asset": { "version": "2.0", "generator": "relfusion" },
        "scene": 0,
        "scenes": [{ "nodes": [0] }],
        "nodes": [{ "name": "relfusion mesh" }],
    });
    let Some((n, indices, bounds)) = mesh else {
        return doc;
    };
    let views = vec![
        buffer_view(0, 12 * n, None, ARRAY_BUFFER),
        buffer_view(12 * n, 24 * n, None, ARRAY_BUFFER),
        buffer_view(24 * n, 28 * n, Some(4), ARRAY_BUFFER),
        buffer_view(28 * n, 28 * n + 4 * indices, None, ELEMENT_ARRAY_BUFFER),
    ];
    doc["bufferViews"] = Value::Array(views);
    doc["buffers"] = json!([{ "byteLength": 28 * n + 4 * indices }]);
    doc["accessors"] = json!([
        { "bufferView": 0, "componentType": FLOAT, "count": n, "type": "VEC3",
          "min": bounds.min, "max": bounds.max },
        { "bufferView": 1, "componentType": FLOAT, "count": n, "type": "VEC3" },
        { "bufferView": 2, "componentType": UNSIGNED_BYTE, "normalized": true, "count": n,
          "type": "VEC3" },
        { "bufferView": 3, "componentType": UNSIGNED_INT, "count": indices,
          "type": "SCALAR" },
    ]);
    doc["materials"] = json!([{
        "name": "vertex colour",
        "pbrMetallicRoughness": { "metallicFactor": 0.0, "roughnessFactor": 1.0 },
        "extensions": { "KHR_materials_unlit": {} },
    }]);
    doc["extensionsUsed"] = json!(["KHR_materials_unlit"]);
    doc["meshes"] = json!([{
        "name": "relfusion mesh",
        "primitives": [{
            "attributes": { "POSITION": 0, "NORMAL": 1, "COLOR_0": 2 },
            "indices": 3,
            "material": 0,
            "mode": TRIANGLES,
        }],
    }]);
    doc["nodes"][0]["mesh"] = json!(0);
    doc
}

/// A view of bytes `start..end` of buffer 0.
fn buffer_view(start: usize, end: usize, stride: Option<usize>, target: u32) -> Value {
    let mut v = json!({
        "buffer": 0,
        "byteOffset": start,
        "byteLength": end - start,
        "target": target,
    });
    if let Some(s) = stride {
        v["byteStride"] = json!(s);
    }
    v
}

/// The GLB container up to the BIN chunk's data: 12-byte header, the JSON chunk padded with
/// spaces and, for a BIN chunk of `bin` bytes, its 8-byte header; the caller writes the data
/// and pads it with zeros to a multiple of 4 bytes (spec §4.4.3).
fn container(doc: &Value, bin: Option<usize>) -> Vec<u8> {
    let mut json = serde_json::to_vec(doc).expect("a JSON value always serialises");
    json.resize(json.len().next_multiple_of(4), b' ');
    let bin = bin.map(|b| b.next_multiple_of(4));
    let total = 12 + 8 + json.len() + bin.map_or(0, |b| 8 + b);
    let mut out = Vec::with_capacity(12 + 8 + json.len() + 8);
    for word in [
        GLB_MAGIC,
        GLB_VERSION,
        total as u32,
        json.len() as u32,
        CHUNK_JSON,
    ] {
        out.extend_from_slice(&word.to_le_bytes());
    }
    out.extend_from_slice(&json);
    if let Some(b) = bin {
        for word in [b as u32, CHUNK_BIN] {
            out.extend_from_slice(&word.to_le_bytes());
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::export::mesh_ply::tests::test_mesh;
    use gltf::Semantic;
    use gltf::accessor::{DataType, Dimensions};
    use gltf::buffer::Source;
    use gltf::mesh::Mode;

    fn word(bytes: &[u8], at: usize) -> u32 {
        u32::from_le_bytes(bytes[at..at + 4].try_into().expect("4 bytes"))
    }

    /// The container rules of spec §4.4 checked byte by byte: header, chunk order, lengths
    /// and padding. Returns the JSON text.
    fn check_container(bytes: &[u8], has_bin: bool) -> String {
        assert_eq!(word(bytes, 0), GLB_MAGIC);
        assert_eq!(word(bytes, 4), 2);
        assert_eq!(word(bytes, 8) as usize, bytes.len());
        let json_len = word(bytes, 12) as usize;
        assert_eq!(word(bytes, 16), CHUNK_JSON);
        assert_eq!(json_len % 4, 0);
        let json = std::str::from_utf8(&bytes[20..20 + json_len]).expect("UTF-8 JSON");
        serde_json::from_str::<Value>(json).expect("JSON chunk parses, padding included");
        let rest = &bytes[20 + json_len..];
        if has_bin {
            let bin_len = word(rest, 0) as usize;
            assert_eq!(word(rest, 4), CHUNK_BIN);
            assert_eq!(bin_len % 4, 0);
            assert_eq!(rest.len(), 8 + bin_len);
        } else {
            assert!(rest.is_empty());
        }
        json.to_string()
    }

    #[test]
    fn glb_round_trips_through_the_gltf_crate() {
        let mesh = test_mesh();
        let bytes = mesh_glb_bytes(&mesh);
        let json = check_container(&bytes, true);
        assert!(json.contains("\"generator\":\"relfusion\""));

        let gltf = gltf::Gltf::from_slice(&bytes).expect("gltf validates the file");
        let blob = gltf.blob.as_deref().expect("BIN chunk");
        let scene = gltf.default_scene().expect("default scene");
        let node = scene.nodes().next().expect("one node");
        let gmesh = node.mesh().expect("node has the mesh");
        assert_eq!(gltf.meshes().count(), 1);
        let prims: Vec<_> = gmesh.primitives().collect();
        assert_eq!(prims.len(), 1);
        let prim = &prims[0];
        assert_eq!(prim.mode(), Mode::Triangles);

        for (semantic, accessor) in prim.attributes() {
            let view = accessor.view().expect("accessor has a view");
            assert_eq!(accessor.count(), mesh.vertex_count());
            assert_eq!(
                (view.offset() + accessor.offset()) % 4,
                0,
                "{semantic:?} aligned"
            );
            if semantic == Semantic::Colors(0) {
                assert_eq!(accessor.data_type(), DataType::U8);
                assert_eq!(accessor.dimensions(), Dimensions::Vec3);
                assert!(accessor.normalized());
                assert_eq!(view.stride(), Some(4));
            }
            if semantic == Semantic::Positions {
                let lo: Vec<f32> = (0..3)
                    .map(|k| mesh.positions.iter().map(|p| p[k]).fold(f32::MAX, f32::min))
                    .collect();
                let hi: Vec<f32> = (0..3)
                    .map(|k| mesh.positions.iter().map(|p| p[k]).fold(f32::MIN, f32::max))
                    .collect();
                let as_f32 = |v: Option<gltf::json::Value>| -> Vec<f32> {
                    serde_json::from_value(v.expect("min/max present")).expect("numbers")
                };
                assert_eq!(as_f32(accessor.min()), lo);
                assert_eq!(as_f32(accessor.max()), hi);
            }
        }

        let reader = prim.reader(|b| matches!(b.source(), Source::Bin).then_some(blob));
        let positions: Vec<[f32; 3]> = reader.read_positions().expect("POSITION").collect();
        let normals: Vec<[f32; 3]> = reader.read_normals().expect("NORMAL").collect();
        let colors: Vec<[u8; 3]> = reader
            .read_colors(0)
            .expect("COLOR_0")
            .into_rgb_u8()
            .collect();
        let indices: Vec<u32> = reader.read_indices().expect("indices").into_u32().collect();
        assert_eq!(positions, mesh.positions);
        assert_eq!(normals, mesh.normals);
        assert_eq!(colors, mesh.colors);
        assert_eq!(indices, mesh.indices);
    }

    #[test]
    fn empty_mesh_glb_is_an_empty_scene() {
        let vertices_only = Mesh {
            indices: Vec::new(),
            ..test_mesh()
        };
        for mesh in [Mesh::default(), vertices_only] {
            let bytes = mesh_glb_bytes(&mesh);
            check_container(&bytes, false);
            let gltf = gltf::Gltf::from_slice(&bytes).expect("gltf validates the file");
            assert!(gltf.blob.is_none());
            assert_eq!(gltf.meshes().count(), 0);
            let scene = gltf.default_scene().expect("default scene");
            assert_eq!(scene.nodes().count(), 1);
        }
    }

    #[test]
    fn glb_file_is_written_atomically() {
        let dir = std::env::temp_dir().join(format!("relfusion-glb-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("temp dir");
        let path = dir.join("mesh.glb");
        std::fs::write(&path, b"old").expect("old file");
        write_mesh_glb(&path, &test_mesh()).expect("write");
        assert_eq!(
            std::fs::read(&path).expect("read"),
            mesh_glb_bytes(&test_mesh())
        );
        assert_eq!(std::fs::read_dir(&dir).expect("list").count(), 1);
        std::fs::remove_dir_all(&dir).expect("clean up");
    }
}
