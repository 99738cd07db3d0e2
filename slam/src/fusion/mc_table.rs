//! The marching-cubes case table, generated from first principles instead of pasted from the
//! literature (published tables differ in how they resolve ambiguous faces, and a table copied
//! with one wrong entry is a hole in every mesh that hits that case).
//!
//! Cell geometry: corner `i` sits at offset `(i & 1, (i >> 1) & 1, (i >> 2) & 1)`; the case
//! index has bit `i` set when corner `i` is *inside* (tsdf < 0). Edge `e` runs along axis
//! `e / 4` from its lower corner (the corner whose bit `axis` is clear and whose two other bits,
//! in increasing axis order, are `e % 4`) to the corner with that bit set ([`edge_corners`]).
//!
//! Construction of one case:
//! 1. On each of the six cube faces, walk the four face edges counter-clockwise seen from
//!    outside the cube and record the sign changes: an *entry* goes from an outside corner to
//!    an inside one, an *exit* the other way. Entries and exits alternate.
//! 2. Connect every entry to the next crossing counter-clockwise (necessarily an exit). With
//!    two crossings that is the only choice; with four (an ambiguous face: the inside corners
//!    are diagonal) it cuts each inside corner off on its own ("inside corners separated").
//!    The rule depends only on the face's four corner signs, and the cell on the other side of
//!    the face walks it in the opposite direction with entries and exits swapped, so it draws
//!    the same segments reversed: neighbouring cells agree and the surface is watertight.
//! 3. Why this direction: the inside region of the cell has the surface and the inside parts
//!    of the faces as its boundary. Orienting the surface with normals from inside to outside,
//!    its boundary curve on each face is the reverse of the (outward-normal, counter-clockwise)
//!    boundary of the face's inside part; that reverse runs from an entry to the following
//!    exit, inside on the right seen from outside. Each crossed cube edge is an entry on one of
//!    its two faces and an exit on the other, so the segments chain into closed loops, and a
//!    loop runs counter-clockwise seen from the positive (outside) side.
//! 4. Each loop, started at its smallest edge id, is triangulated as a fan from that edge,
//!    which keeps the loop's direction: triangles are counter-clockwise seen from outside.
//!
//! The table is built once ([`TABLE`]); the GPU receives it as a storage buffer
//! ([`CaseTable::gpu_words`]), so the WGSL kernel holds no copy of its own.

use std::sync::LazyLock;

use super::mesh::EdgeKey;

/// Cube edges of a cell.
pub const EDGE_COUNT: usize = 12;

/// Most triangles any case produces (checked by the builder; a test shows it is reached).
pub const MAX_TRIS: usize = 5;

/// `u32` words per case in [`CaseTable::gpu_words`]: the triangle count, then `3 · MAX_TRIS`
/// edge ids (unused ones 0).
pub const CASE_STRIDE: usize = 1 + 3 * MAX_TRIS;

/// Offset of corner `c` (0..8) from the cell's lower corner.
pub const fn corner_offset(c: u8) -> [i32; 3] {
    [(c & 1) as i32, ((c >> 1) & 1) as i32, ((c >> 2) & 1) as i32]
}

/// Axis (0 = x, 1 = y, 2 = z) of edge `e`.
pub const fn edge_axis(e: u8) -> u8 {
    e / 4
}

/// Lower and upper corner of edge `e`: the lower corner is `e % 4` with a zero bit inserted at
/// position `axis` (the WGSL kernel computes the same formula).
pub const fn edge_corners(e: u8) -> (u8, u8) {
    let axis = edge_axis(e);
    let k = e % 4;
    let below = (1u8 << axis) - 1;
    let lo = (k & below) | ((k & !below) << 1);
    (lo, lo | 1 << axis)
}

/// The edge joining corners `a` and `b`, if they differ along exactly one axis.
pub const fn edge_between(a: u8, b: u8) -> Option<u8> {
    let d = a ^ b;
    if a >= 8 || b >= 8 || d.count_ones() != 1 {
        return None;
    }
    let axis = d.trailing_zeros() as u8;
    let lo = if a < b { a } else { b };
    let below = (1u8 << axis) - 1;
    Some(axis * 4 + ((lo & below) | ((lo >> (axis + 1)) << axis)))
}

/// The grid edge that edge `e` of the cell whose lower corner is global voxel `cell_voxel`
/// lies on (its lower endpoint and axis).
pub fn edge_key(cell_voxel: [i32; 3], e: u8) -> EdgeKey {
    let o = corner_offset(edge_corners(e).0);
    EdgeKey {
        voxel: [
            cell_voxel[0] + o[0],
            cell_voxel[1] + o[1],
            cell_voxel[2] + o[2],
        ],
        axis: edge_axis(e),
    }
}

/// Corners of face `f` (= `2 · axis + side`, side 1 at the upper coordinate) in
/// counter-clockwise order seen from outside the cube. With `u, v` the next two axes
/// cyclically, `u × v = axis`, so `(0,0) (1,0) (1,1) (0,1)` in `(u, v)` is counter-clockwise
/// around `+axis`; the lower face (outward normal `−axis`) takes it reversed.
pub fn face_corners(f: usize) -> [u8; 4] {
    let axis = f / 2;
    let side = (f % 2) as u8;
    let (u, v) = ((axis + 1) % 3, (axis + 2) % 3);
    let at = |du: u8, dv: u8| side << axis | du << u | dv << v;
    let ccw = [at(0, 0), at(1, 0), at(1, 1), at(0, 1)];
    if side == 1 {
        ccw
    } else {
        [ccw[3], ccw[2], ccw[1], ccw[0]]
    }
}

/// Triangles (as edge-id triples) of every case.
#[derive(Debug)]
pub struct CaseTable {
    counts: [u8; 256],
    triangles: [[[u8; 3]; MAX_TRIS]; 256],
}

/// The table, built on first use.
pub static TABLE: LazyLock<CaseTable> = LazyLock::new(CaseTable::build);

impl CaseTable {
    fn build() -> Self {
        let mut counts = [0u8; 256];
        let mut triangles = [[[0u8; 3]; MAX_TRIS]; 256];
        for case in 0..=255u8 {
            let tris = case_triangles(case);
            assert!(
                tris.len() <= MAX_TRIS,
                "case {case}: {} triangles",
                tris.len()
            );
            counts[case as usize] = tris.len() as u8;
            triangles[case as usize][..tris.len()].copy_from_slice(&tris);
        }
        Self { counts, triangles }
    }

    /// The triangles of `case`, each three edge ids, counter-clockwise seen from outside.
    pub fn triangles(&self, case: u8) -> &[[u8; 3]] {
        &self.triangles[case as usize][..self.counts[case as usize] as usize]
    }

    /// The table as the kernel reads it: [`CASE_STRIDE`] words per case.
    pub fn gpu_words(&self) -> Vec<u32> {
        let mut words = Vec::with_capacity(256 * CASE_STRIDE);
        for case in 0..256 {
            words.push(u32::from(self.counts[case]));
            words.extend(self.triangles[case].iter().flatten().map(|&e| u32::from(e)));
        }
        words
    }
}

/// Steps 1–4 of the module doc for one case.
fn case_triangles(case: u8) -> Vec<[u8; 3]> {
    let inside = |c: u8| (case >> c) & 1 == 1;
    // Surface boundary segments: entry edge → exit edge.
    let mut next: [Option<u8>; EDGE_COUNT] = [None; EDGE_COUNT];
    for f in 0..6 {
        let corners = face_corners(f);
        let mut crossings: Vec<(u8, bool)> = Vec::with_capacity(4);
        for k in 0..4 {
            let (a, b) = (corners[k], corners[(k + 1) % 4]);
            if inside(a) != inside(b) {
                let e = edge_between(a, b).expect("face corners are adjacent");
                crossings.push((e, inside(b)));
            }
        }
        for (i, &(e, entry)) in crossings.iter().enumerate() {
            if entry {
                let (exit, is_entry) = crossings[(i + 1) % crossings.len()];
                assert!(!is_entry, "case {case}: entries and exits alternate");
                assert!(
                    next[e as usize].replace(exit).is_none(),
                    "case {case}: edge {e} is an entry on two faces"
                );
            }
        }
    }
    let mut visited = [false; EDGE_COUNT];
    let mut triangles = Vec::new();
    for start in 0..EDGE_COUNT as u8 {
        if visited[start as usize] || next[start as usize].is_none() {
            continue;
        }
        let mut lp = Vec::new();
        let mut e = start;
        loop {
            visited[e as usize] = true;
            lp.push(e);
            e = next[e as usize].expect("every crossed edge is an entry on one face");
            if e == start {
                break;
            }
        }
        for i in 1..lp.len() - 1 {
            triangles.push([lp[0], lp[i], lp[i + 1]]);
        }
    }
    triangles
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::{HashMap, HashSet};

    fn pos(c: u8) -> [f64; 3] {
        corner_offset(c).map(f64::from)
    }

    fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
        [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
    }

    fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
        [
            a[1] * b[2] - a[2] * b[1],
            a[2] * b[0] - a[0] * b[2],
            a[0] * b[1] - a[1] * b[0],
        ]
    }

    fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
        a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
    }

    fn midpoint(e: u8) -> [f64; 3] {
        let (a, b) = edge_corners(e);
        let (pa, pb) = (pos(a), pos(b));
        [0, 1, 2].map(|k| 0.5 * (pa[k] + pb[k]))
    }

    /// Outward normal of face `f`.
    fn face_normal(f: usize) -> [f64; 3] {
        let mut n = [0.0; 3];
        n[f / 2] = if f % 2 == 1 { 1.0 } else { -1.0 };
        n
    }

    /// The face both edges lie on, if any (two distinct edges share at most one face).
    fn common_face(e1: u8, e2: u8) -> Option<usize> {
        let on = |e: u8, f: usize| {
            let (a, b) = edge_corners(e);
            let c = face_corners(f);
            c.contains(&a) && c.contains(&b)
        };
        (0..6).find(|&f| on(e1, f) && on(e2, f))
    }

    /// Directed triangle edges of a case that have no reverse twin: the patch boundary.
    fn boundary(tris: &[[u8; 3]]) -> Vec<(u8, u8)> {
        let directed: Vec<(u8, u8)> = tris
            .iter()
            .flat_map(|t| [(t[0], t[1]), (t[1], t[2]), (t[2], t[0])])
            .collect();
        let set: HashSet<(u8, u8)> = directed.iter().copied().collect();
        directed
            .into_iter()
            .filter(|&(a, b)| !set.contains(&(b, a)))
            .collect()
    }

    fn ambiguous(case: u8, f: usize) -> bool {
        let c = face_corners(f);
        let s = c.map(|k| (case >> k) & 1);
        s[0] == s[2] && s[1] == s[3] && s[0] != s[1]
    }

    #[test]
    fn edges_and_faces_are_consistent() {
        for e in 0..12u8 {
            let (a, b) = edge_corners(e);
            assert_eq!((a ^ b).count_ones(), 1);
            assert_eq!(a ^ b, 1 << edge_axis(e));
            assert!(a < b);
            assert_eq!(edge_between(a, b), Some(e));
            assert_eq!(edge_between(b, a), Some(e));
        }
        assert_eq!(edge_between(0, 3), None);
        for f in 0..6 {
            let c = face_corners(f);
            let n = cross(sub(pos(c[1]), pos(c[0])), sub(pos(c[2]), pos(c[1])));
            assert!(
                dot(n, face_normal(f)) > 0.0,
                "face {f} is counter-clockwise"
            );
            let centre = [0.5; 3];
            assert!(dot(sub(pos(c[0]), centre), face_normal(f)) > 0.0);
        }
        assert_eq!(
            edge_key([3, -4, 5], 11),
            EdgeKey {
                voxel: [4, -3, 5],
                axis: 2
            }
        );
    }

    #[test]
    fn empty_cases_and_table_bound() {
        assert!(TABLE.triangles(0).is_empty());
        assert!(TABLE.triangles(255).is_empty());
        let most = (0..=255u8).map(|c| TABLE.triangles(c).len()).max();
        assert_eq!(most, Some(MAX_TRIS), "MAX_TRIS is tight");
        let words = TABLE.gpu_words();
        assert_eq!(words.len(), 256 * CASE_STRIDE);
        for case in 0..=255u8 {
            let w = &words[case as usize * CASE_STRIDE..][..CASE_STRIDE];
            let tris = TABLE.triangles(case);
            assert_eq!(w[0] as usize, tris.len());
            for (i, t) in tris.iter().enumerate() {
                assert_eq!(&w[1 + 3 * i..4 + 3 * i], &t.map(u32::from));
            }
        }
    }

    /// Every case is a set of closed, consistently oriented 2-manifold patches whose boundary
    /// lies on the cube faces, with a vertex on exactly the crossed edges, and the boundary on
    /// each face has the inside corners on its right seen from outside.
    #[test]
    fn every_case_is_an_oriented_manifold_patch_bounded_by_the_faces() {
        for case in 0..=255u8 {
            let inside = |c: u8| (case >> c) & 1 == 1;
            let tris = TABLE.triangles(case);
            let crossed: HashSet<u8> = (0..12u8)
                .filter(|&e| {
                    let (a, b) = edge_corners(e);
                    inside(a) != inside(b)
                })
                .collect();
            let used: HashSet<u8> = tris.iter().flatten().copied().collect();
            assert_eq!(used, crossed, "case {case}: vertices on the crossed edges");
            let mut directed = HashMap::new();
            for t in tris {
                assert!(t[0] != t[1] && t[1] != t[2] && t[0] != t[2], "case {case}");
                for (a, b) in [(t[0], t[1]), (t[1], t[2]), (t[2], t[0])] {
                    *directed.entry((a, b)).or_insert(0) += 1;
                }
            }
            assert!(
                directed.values().all(|&n| n == 1),
                "case {case}: a directed edge twice (non-manifold or flipped)"
            );
            let bnd = boundary(tris);
            // Every crossed edge starts exactly one and ends exactly one boundary segment:
            // the boundary is a union of closed loops and every vertex's fan is one disk.
            for &e in &crossed {
                assert_eq!(bnd.iter().filter(|s| s.0 == e).count(), 1, "case {case}");
                assert_eq!(bnd.iter().filter(|s| s.1 == e).count(), 1, "case {case}");
            }
            for &(u, v) in &bnd {
                let f = common_face(u, v)
                    .unwrap_or_else(|| panic!("case {case}: segment {u}->{v} not on a face"));
                // With vertices at the midpoints, each endpoint of u's edge lies strictly on
                // one side of the segment; the inside one must be on the right.
                let dir = sub(midpoint(v), midpoint(u));
                let right = cross(dir, face_normal(f));
                let (a, b) = edge_corners(u);
                for c in [a, b] {
                    let side = dot(sub(pos(c), midpoint(u)), right);
                    assert!(side != 0.0);
                    assert_eq!(
                        side > 0.0,
                        inside(c),
                        "case {case} segment {u}->{v} corner {c}"
                    );
                }
            }
        }
    }

    /// Complementing the signs keeps the vertices and reverses the boundary on every face
    /// except the ambiguous ones: there the rule separates the inside corners, which are the
    /// other diagonal pair after complementing, so the segments pair the crossings the other
    /// way (both cells sharing such a face still agree, since the rule only reads that face).
    #[test]
    fn complementary_cases_reverse_except_on_ambiguous_faces() {
        let mut with_ambiguous = 0;
        for case in 0..=255u8 {
            let flip = 255 - case;
            let (t1, t2) = (TABLE.triangles(case), TABLE.triangles(flip));
            let v1: HashSet<u8> = t1.iter().flatten().copied().collect();
            let v2: HashSet<u8> = t2.iter().flatten().copied().collect();
            assert_eq!(v1, v2, "case {case}");
            let (b1, b2) = (boundary(t1), boundary(t2));
            for f in 0..6 {
                let on_face = |b: &[(u8, u8)]| -> HashSet<(u8, u8)> {
                    b.iter()
                        .copied()
                        .filter(|&(u, v)| common_face(u, v) == Some(f))
                        .collect()
                };
                let (s1, s2) = (on_face(&b1), on_face(&b2));
                let reversed: HashSet<(u8, u8)> = s2.iter().map(|&(u, v)| (v, u)).collect();
                if ambiguous(case, f) {
                    with_ambiguous += 1;
                    assert_eq!(s1.len(), 2);
                    assert!(
                        s1.is_disjoint(&reversed) && s1.is_disjoint(&s2),
                        "case {case}"
                    );
                } else {
                    assert_eq!(s1, reversed, "case {case} face {f}");
                }
            }
            if !(0..6).any(|f| ambiguous(case, f)) {
                // Same loops reversed; the fans may start elsewhere, so compare boundaries.
                assert_eq!(
                    b1.iter().map(|&(u, v)| (v, u)).collect::<HashSet<_>>(),
                    b2.iter().copied().collect::<HashSet<_>>(),
                    "case {case}"
                );
                assert_eq!(t1.len(), t2.len(), "case {case}");
            }
        }
        assert!(with_ambiguous > 0);
    }

    /// For a linear field the surface in a cell is a plane section of the cube (a convex
    /// polygon), so every fan triangle must face along the gradient, i.e. to positive values.
    #[test]
    fn triangles_of_plane_sections_face_the_positive_side() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        let mut seen = HashSet::new();
        for _ in 0..20_000 {
            let g = [0; 3].map(|_: i32| rng.random_range(-1.0..1.0f64));
            let off = rng.random_range(-1.5..1.5f64);
            let f = |c: u8| dot(g, pos(c)) + off;
            if (0..8u8).any(|c| f(c).abs() < 1e-6) {
                continue;
            }
            let case = (0..8u8).fold(0u8, |m, c| m | u8::from(f(c) < 0.0) << c);
            seen.insert(case);
            let vertex = |e: u8| {
                let (a, b) = edge_corners(e);
                let t = f(a) / (f(a) - f(b));
                let (pa, pb) = (pos(a), pos(b));
                [0, 1, 2].map(|k| pa[k] + t * (pb[k] - pa[k]))
            };
            for tri in TABLE.triangles(case) {
                let [p0, p1, p2] = tri.map(vertex);
                let n = cross(sub(p1, p0), sub(p2, p0));
                assert!(
                    dot(n, g) >= -1e-12,
                    "case {case}: triangle {tri:?} faces inside"
                );
            }
        }
        assert!(seen.len() > 100, "plane cases seen: {}", seen.len());
    }
}
