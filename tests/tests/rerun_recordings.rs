//! Rerun recordings (`--rerun FILE.rrd`, issue 23 item 5; the client's optional feature
//! `rerun`), read back with the rerun crate's decoder: `relfusion stream` against a real
//! relfusiond and `relfusion run` locally. Built only with this crate's feature `rerun`
//! (`make test-rerun`): the rerun SDK and arrow are about a third of a cold test build.

mod viewers;

use std::collections::{BTreeMap, BTreeSet};
use std::io::BufReader;
use std::path::{Path, PathBuf};

use relfusion_tests::{Relfusiond, synth_sequence, temp_dir};
use rerun::external::re_log_encoding::Decoder;
use rerun::log::{Chunk, LogMsg, RowId};
use viewers::{
    check_mcap, check_service_recording, foxglove_check, relfusion, stream_and_fetch, tum_lines,
};

/// What a recording holds, by entity path.
#[derive(Debug, Default)]
struct Contents {
    images: BTreeMap<String, usize>,
    transforms: BTreeMap<String, usize>,
    points: BTreeMap<String, usize>,
    line_strips: BTreeSet<String>,
    pinholes: BTreeSet<String>,
    /// Mesh block entity → its (row, triangles; `None` = Clear) in logging order.
    mesh: BTreeMap<String, Vec<(RowId, Option<usize>)>>,
}

impl Contents {
    /// Triangles of the blocks whose last entry is a mesh (not a Clear).
    fn mesh_triangles(&self) -> usize {
        self.mesh
            .values()
            .filter_map(|rows| {
                rows.iter()
                    .max_by_key(|(row, _)| *row)
                    .and_then(|(_, t)| *t)
            })
            .sum()
    }

    fn clears(&self) -> usize {
        self.mesh
            .values()
            .flatten()
            .filter(|(_, t)| t.is_none())
            .count()
    }
}

fn rows_with(chunk: &Chunk, component: &rerun::ComponentDescriptor) -> Vec<RowId> {
    chunk
        .iter_component_indices("frame".into(), component.component)
        .map(|(_, row)| row)
        .collect()
}

fn read_rrd(path: &Path) -> Contents {
    let file = std::fs::File::open(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let mut contents = Contents::default();
    let messages = Decoder::<LogMsg>::decode_eager(BufReader::new(file)).expect("an .rrd file");
    for message in messages {
        let LogMsg::ArrowMsg(_, arrow) = message.expect("decodable message") else {
            continue;
        };
        let chunk = Chunk::from_arrow_msg(&arrow).expect("chunk");
        let entity = chunk.entity_path().to_string();
        let entity = entity.trim_start_matches('/').to_string();
        let count =
            |d: rerun::ComponentDescriptor| rows_with(&chunk, &d).len() + static_rows(&chunk, &d);
        let images = count(rerun::EncodedImage::descriptor_blob());
        if images > 0 {
            *contents.images.entry(entity.clone()).or_default() += images;
        }
        let transforms = count(rerun::Transform3D::descriptor_translation());
        if transforms > 0 {
            *contents.transforms.entry(entity.clone()).or_default() += transforms;
        }
        let points = count(rerun::Points3D::descriptor_positions());
        if points > 0 {
            *contents.points.entry(entity.clone()).or_default() += points;
        }
        if count(rerun::LineStrips3D::descriptor_strips()) > 0 {
            contents.line_strips.insert(entity.clone());
        }
        if count(rerun::Pinhole::descriptor_image_from_camera()) > 0 {
            contents.pinholes.insert(entity.clone());
        }
        let triangles = rerun::Mesh3D::descriptor_triangle_indices();
        let rows = rows_with(&chunk, &triangles);
        let sizes = chunk
            .iter_component::<rerun::components::TriangleIndices>(triangles.component)
            .map(|batch| batch.len());
        for (row, size) in rows.into_iter().zip(sizes) {
            contents
                .mesh
                .entry(entity.clone())
                .or_default()
                .push((row, Some(size)));
        }
        for row in rows_with(&chunk, &rerun::Clear::descriptor_is_recursive()) {
            contents
                .mesh
                .entry(entity.clone())
                .or_default()
                .push((row, None));
        }
    }
    contents
}

/// Rows of a static chunk (no timeline) that carry the component.
fn static_rows(chunk: &Chunk, d: &rerun::ComponentDescriptor) -> usize {
    if chunk.is_static() && chunk.components().contains_component(d.component) {
        chunk.num_rows()
    } else {
        0
    }
}

/// The checks shared by both commands.
fn check(contents: &Contents, frames: usize, poses: usize, keyframes: usize, triangles: usize) {
    assert_eq!(
        contents.images.get("world/camera/image"),
        Some(&frames),
        "{contents:?}"
    );
    assert!(
        contents.pinholes.contains("world/camera/image"),
        "{contents:?}"
    );
    assert_eq!(
        contents.transforms.get("world/camera"),
        Some(&poses),
        "{contents:?}"
    );
    assert!(
        contents.line_strips.contains("world/trajectory"),
        "{contents:?}"
    );
    let keyframe_entities: BTreeSet<&String> = contents
        .transforms
        .keys()
        .filter(|e| e.starts_with("world/keyframes/"))
        .collect();
    assert_eq!(keyframe_entities.len(), keyframes, "{keyframe_entities:?}");
    let with_points = contents
        .points
        .keys()
        .filter(|e| e.ends_with("/points"))
        .count();
    assert!(
        with_points > 0 && with_points <= keyframes,
        "{:?}",
        contents.points
    );
    assert!(
        contents.mesh.len() > 10,
        "mesh blocks: {}",
        contents.mesh.len()
    );
    assert!(contents.mesh.keys().all(|e| e.starts_with("world/mesh/")));
    assert_eq!(contents.mesh_triangles(), triangles, "mesh triangles");
}

#[test]
fn stream_and_run_write_rerun_recordings_that_read_back() {
    const FRAMES: usize = 40;
    let sequence = synth_sequence("rerun", FRAMES, 31);
    let seq = sequence.to_str().expect("utf-8 path");
    let work = temp_dir("rerun");

    // Streamed to a real service.
    let server = Relfusiond::spawn(&work.join("data"), Vec::<PathBuf>::new(), &[]);
    let rrd = work.join("stream.rrd");
    let mcap_path = work.join("stream.mcap");
    let mcap_arg = mcap_path.to_str().expect("path");
    let streamed = stream_and_fetch(
        seq,
        &server,
        &work,
        &["--rerun", rrd.to_str().expect("path"), "--mcap", mcap_arg],
    );
    let (summary, poses, keyframes, triangles) = (
        &streamed.summary,
        streamed.poses,
        streamed.keyframes,
        streamed.triangles,
    );
    let contents = read_rrd(&rrd);
    check(&contents, FRAMES, poses, keyframes, triangles);
    assert_eq!(
        contents.clears() as u64,
        summary["rerun"]["mesh_blocks_cleared"]
            .as_u64()
            .expect("counts"),
    );
    // The MCAP of the same stream holds the same updates.
    let mcap = foxglove_check(&["mcap", mcap_arg]);
    check_mcap(&mcap, FRAMES, poses, keyframes, triangles);
    assert_eq!(mcap["mesh_deletions_total"], contents.clears(), "{mcap}");
    assert_eq!(
        mcap["mesh_entities_total"],
        contents
            .mesh
            .values()
            .flatten()
            .filter(|(_, t)| t.is_some())
            .count(),
        "{mcap}"
    );
    assert_eq!(mcap["counts"]["/mesh"], summary["foxglove"]["mesh_updates"]);
    check_service_recording(&streamed);

    // A local run.
    let out = work.join("run");
    let recorded = work.join("run.rrd");
    let run = relfusion(&[
        "run",
        seq,
        "--out",
        out.to_str().expect("path"),
        "--deterministic",
        "--quiet",
        "--rerun",
        recorded.to_str().expect("path"),
    ]);
    let contents = read_rrd(&recorded);
    check(
        &contents,
        FRAMES,
        tum_lines(&out.join("trajectory.txt")),
        tum_lines(&out.join("keyframes.txt")),
        run[0]["mesh_triangles"].as_u64().expect("mesh triangles") as usize,
    );
}
