//! The synthetic room: an axis-aligned box room (world z up, floor at z = 0) with furniture
//! blocks standing on the floor, ray-cast on the CPU.
//!
//! The furniture is kept out of a central "free" region ([`FREE_MIN`]..[`FREE_MAX`] grown by
//! [`CLEARANCE`]) in which every trajectory preset moves, so the camera can never be inside an
//! object or closer than ~0.4 m to one.

use nalgebra::{Vector2, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::geometry::{PinholeCamera, SE3};

use super::texture::{self, Texture, random_color, random_posters, random_textured};

/// Room interior: 4 m (x) × 3 m (y) × 2.6 m (z).
pub const ROOM_MIN: [f64; 3] = [-2.0, -1.5, 0.0];
/// See [`ROOM_MIN`].
pub const ROOM_MAX: [f64; 3] = [2.0, 1.5, 2.6];
/// Corners of the box in which camera centres stay (all presets, any sequence length).
pub const FREE_MIN: [f64; 3] = [-1.05, -0.65, 0.9];
/// See [`FREE_MIN`].
pub const FREE_MAX: [f64; 3] = [0.55, 0.65, 1.7];
/// Horizontal distance kept between furniture and the free region, metres.
pub const CLEARANCE: f64 = 0.35;

/// A furniture block: a box of half-extents `half` centred at `center`, turned by `yaw` about z.
#[derive(Clone, Debug)]
pub struct Block {
    pub center: Vector3<f64>,
    pub half: Vector3<f64>,
    pub yaw: f64,
    /// `(sin yaw, cos yaw)`, cached: ray casting would otherwise spend most of its time here.
    pub sin_cos_yaw: (f64, f64),
    pub texture: Texture,
    /// Offset added to face coordinates so that blocks sharing a pattern do not look alike.
    pub uv_offset: Vector2<f64>,
}

/// Everything the renderer needs: room faces, blocks and the light.
#[derive(Clone, Debug)]
pub struct Scene {
    pub room_min: Vector3<f64>,
    pub room_max: Vector3<f64>,
    /// Textures of the room faces, indexed `2·axis + side` (side 0 = min, 1 = max):
    /// walls x = −2, x = +2, y = −1.5, y = +1.5, then floor and ceiling.
    pub faces: Vec<Texture>,
    pub blocks: Vec<Block>,
    /// Point light position (world), near the ceiling.
    pub light: Vector3<f64>,
}

/// A ray–surface intersection.
#[derive(Debug)]
pub struct Hit<'a> {
    /// Ray parameter: with a direction whose camera-frame z is 1, this is the z-depth.
    pub t: f64,
    pub normal: Vector3<f64>,
    pub uv: Vector2<f64>,
    pub texture: &'a Texture,
}

/// Surface coordinates on a face perpendicular to `axis`: the two other coordinates.
fn face_uv(axis: usize, p: &Vector3<f64>) -> Vector2<f64> {
    match axis {
        0 => Vector2::new(p.y, p.z),
        1 => Vector2::new(p.x, p.z),
        _ => Vector2::new(p.x, p.y),
    }
}

impl Scene {
    /// The room of `seed`: textures, furniture layout and light all follow from it.
    pub fn generate(seed: u64) -> Scene {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        rng.set_stream(1);
        let (room_min, room_max) = (Vector3::from(ROOM_MIN), Vector3::from(ROOM_MAX));

        // Walls: the one the camera faces (+x) and the floor are always richly textured; one
        // side wall is mostly uniform with posters (textured islands in a textureless area);
        // the ceiling is uniform apart from two lamp panels.
        let y_span = (room_min.y, room_max.y);
        let x_span = (room_min.x, room_max.x);
        let z_span = (room_min.z, room_max.z);
        let back = random_textured(&mut rng);
        let front_base = random_textured(&mut rng);
        let front = random_posters(&mut rng, front_base, y_span, z_span, 2);
        let plain = Texture::Uniform(random_color(&mut rng, 0.55, 0.8));
        let left = random_posters(&mut rng, plain, x_span, z_span, 3);
        let right = random_textured(&mut rng);
        let floor = match rng.random_range(0..2u32) {
            0 => Texture::Tiles {
                a: random_color(&mut rng, 0.6, 0.85),
                b: random_color(&mut rng, 0.15, 0.4),
                size: rng.random_range(0.3..0.5),
                seed: rng.random(),
            },
            _ => Texture::Noise {
                dark: random_color(&mut rng, 0.1, 0.25),
                light: random_color(&mut rng, 0.55, 0.75),
                frequency: rng.random_range(4.0..8.0),
                octaves: 5,
                seed: rng.random(),
            },
        };
        let ceiling = texture::Texture::Posters {
            background: Box::new(Texture::Uniform([0.85, 0.85, 0.82])),
            posters: vec![
                lamp(-0.9, -0.4, rng.random_range(-0.6..0.0)),
                lamp(0.8, 0.3, rng.random_range(0.0..0.6)),
            ],
        };
        let faces = vec![back, front, left, right, floor, ceiling];
        let blocks = place_blocks(&mut rng, &room_min, &room_max);
        let light = Vector3::new(
            rng.random_range(-0.5..0.5),
            rng.random_range(-0.5..0.5),
            2.3,
        );
        Scene {
            room_min,
            room_max,
            faces,
            blocks,
            light,
        }
    }

    /// Whether `p` is inside the room, at least `margin` from every wall and block.
    pub fn is_free(&self, p: &Vector3<f64>, margin: f64) -> bool {
        let inside =
            (0..3).all(|a| p[a] > self.room_min[a] + margin && p[a] < self.room_max[a] - margin);
        inside
            && self.blocks.iter().all(|b| {
                let local = rotate_z(&(p - b.center), b.sin_cos_yaw, -1.0);
                (0..3).any(|a| local[a].abs() > b.half[a] + margin)
            })
    }

    /// The closest surface hit by the ray `origin + t·dir`, t > 0. The room is closed, so
    /// every ray from inside hits something; `None` only for rays from outside.
    pub fn intersect(&self, origin: &Vector3<f64>, dir: &Vector3<f64>) -> Option<Hit<'_>> {
        self.intersect_blocks(origin, dir, u64::MAX)
    }

    /// [`Scene::intersect`] against the room and only the blocks whose bit is set in `mask`
    /// (block k ↔ bit k; see [`Scene::block_pixel_bounds`]).
    pub fn intersect_blocks(
        &self,
        origin: &Vector3<f64>,
        dir: &Vector3<f64>,
        mask: u64,
    ) -> Option<Hit<'_>> {
        // Room: the ray leaves the box through the face of the smallest positive exit time.
        let mut best: Option<(f64, usize, usize)> = None;
        for a in 0..3 {
            let (bound, side) = if dir[a] > 0.0 {
                (self.room_max[a], 1)
            } else if dir[a] < 0.0 {
                (self.room_min[a], 0)
            } else {
                continue;
            };
            let t = (bound - origin[a]) / dir[a];
            if t > 0.0 && best.is_none_or(|(bt, _, _)| t < bt) {
                best = Some((t, a, side));
            }
        }
        let mut hit = best.map(|(t, a, side)| {
            let p = origin + dir * t;
            let mut normal = Vector3::zeros();
            normal[a] = if side == 0 { 1.0 } else { -1.0 };
            Hit {
                t,
                normal,
                uv: face_uv(a, &p),
                texture: &self.faces[2 * a + side],
            }
        });
        for (k, b) in self.blocks.iter().enumerate() {
            if k >= 64 || mask & (1u64 << k) == 0 {
                continue;
            }
            let o = rotate_z(&(origin - b.center), b.sin_cos_yaw, -1.0);
            let d = rotate_z(dir, b.sin_cos_yaw, -1.0);
            // Slab test (Kay & Kajiya 1986): entry time and the axis it happens on.
            let (mut t_near, mut t_far, mut axis) = (f64::NEG_INFINITY, f64::INFINITY, 0);
            for a in 0..3 {
                if d[a] == 0.0 {
                    if o[a].abs() > b.half[a] {
                        t_near = f64::INFINITY;
                    }
                    continue;
                }
                let t0 = (-b.half[a] - o[a]) / d[a];
                let t1 = (b.half[a] - o[a]) / d[a];
                let (lo, hi) = if t0 < t1 { (t0, t1) } else { (t1, t0) };
                if lo > t_near {
                    t_near = lo;
                    axis = a;
                }
                t_far = t_far.min(hi);
            }
            let closer = hit.as_ref().is_none_or(|h| t_near < h.t);
            if t_near > 0.0 && t_near <= t_far && closer {
                let local = o + d * t_near;
                let mut n = Vector3::zeros();
                n[axis] = -d[axis].signum();
                hit = Some(Hit {
                    t: t_near,
                    normal: rotate_z(&n, b.sin_cos_yaw, 1.0),
                    uv: face_uv(axis, &local) + b.uv_offset,
                    texture: &b.texture,
                });
            }
        }
        hit
    }

    /// Per block, the pixel rectangle `[x_min, x_max, y_min, y_max]` (grown by one pixel)
    /// outside which no ray from `camera` at `world_from_camera` can hit it: the bounding box
    /// of its projected corners (a convex box projects inside their hull), nothing when all are
    /// behind the camera, the whole plane when only some are. Lets the renderer skip most slab tests.
    pub fn block_pixel_bounds(
        &self,
        camera: &PinholeCamera,
        world_from_camera: &SE3,
    ) -> Vec<[f64; 4]> {
        let camera_from_world = world_from_camera.inverse();
        self.blocks
            .iter()
            .map(|b| {
                let mut r = [
                    f64::INFINITY,
                    f64::NEG_INFINITY,
                    f64::INFINITY,
                    f64::NEG_INFINITY,
                ];
                let mut behind = 0;
                for corner in 0..8 {
                    let sign = |bit: usize| if corner & (1 << bit) == 0 { -1.0 } else { 1.0 };
                    let local =
                        Vector3::new(sign(0) * b.half.x, sign(1) * b.half.y, sign(2) * b.half.z);
                    let world = rotate_z(&local, b.sin_cos_yaw, 1.0) + b.center;
                    let p = camera_from_world.act(&world);
                    if p.z < 1e-3 {
                        behind += 1;
                        continue;
                    }
                    let uv = camera.project(&p);
                    r = [
                        r[0].min(uv.x - 1.0),
                        r[1].max(uv.x + 1.0),
                        r[2].min(uv.y - 1.0),
                        r[3].max(uv.y + 1.0),
                    ];
                }
                match behind {
                    // Rays only go forward (camera z > 0): an empty rectangle.
                    8 => [
                        f64::INFINITY,
                        f64::NEG_INFINITY,
                        f64::INFINITY,
                        f64::NEG_INFINITY,
                    ],
                    0 => r,
                    _ => [
                        f64::NEG_INFINITY,
                        f64::INFINITY,
                        f64::NEG_INFINITY,
                        f64::INFINITY,
                    ],
                }
            })
            .collect()
    }

    /// Lambertian radiance in [0, 1] per channel at a hit: albedo × (ambient + diffuse term with
    /// a soft inverse-square falloff). View-independent, so brightness constancy — the
    /// assumption of direct tracking — holds exactly up to 8-bit rounding.
    pub fn shade(&self, origin: &Vector3<f64>, dir: &Vector3<f64>, hit: &Hit<'_>) -> [f32; 3] {
        const AMBIENT: f64 = 0.4;
        const DIFFUSE: f64 = 0.8;
        const FALLOFF_M2: f64 = 6.0;
        let p = origin + dir * hit.t;
        let to_light = self.light - p;
        let r2 = to_light.norm_squared();
        let cos = (hit.normal.dot(&to_light) / r2.sqrt()).max(0.0);
        let s = (AMBIENT + DIFFUSE * cos / (1.0 + r2 / FALLOFF_M2)) as f32;
        let a = hit.texture.albedo(hit.uv.x, hit.uv.y);
        [
            (a[0] * s).min(1.0),
            (a[1] * s).min(1.0),
            (a[2] * s).min(1.0),
        ]
    }
}

/// A bright lamp panel on the ceiling (a uniform poster).
fn lamp(u: f64, v: f64, jitter: f64) -> texture::Poster {
    texture::Poster {
        u0: u + jitter,
        v0: v,
        u1: u + jitter + 0.6,
        v1: v + 0.3,
        frame: 0.03,
        content: Box::new(Texture::Uniform([0.98, 0.97, 0.9])),
    }
}

/// Rotates `v` about the z axis by the angle of `(sin, cos)`, or by its opposite when
/// `direction` is −1.
fn rotate_z(v: &Vector3<f64>, (s, c): (f64, f64), direction: f64) -> Vector3<f64> {
    let s = s * direction;
    Vector3::new(c * v.x - s * v.y, s * v.x + c * v.y, v.z)
}

/// 5–8 blocks of different sizes on the floor, outside the free region grown by
/// [`CLEARANCE`] and not overlapping each other (bounding circles), by rejection sampling.
fn place_blocks(
    rng: &mut ChaCha8Rng,
    room_min: &Vector3<f64>,
    room_max: &Vector3<f64>,
) -> Vec<Block> {
    let target = rng.random_range(5..=8usize);
    let mut blocks: Vec<Block> = Vec::new();
    for _ in 0..2000 {
        if blocks.len() >= target {
            break;
        }
        let half: Vector3<f64> = Vector3::new(
            rng.random_range(0.12..0.45),
            rng.random_range(0.12..0.45),
            rng.random_range(0.15..0.7),
        );
        let radius = half.x.hypot(half.y);
        let x = rng.random_range(room_min.x + radius..room_max.x - radius);
        let y = rng.random_range(room_min.y + radius..room_max.y - radius);
        // Distance from the block's footprint circle to the free rectangle (xy).
        let dx = (FREE_MIN[0] - x).max(x - FREE_MAX[0]).max(0.0);
        let dy = (FREE_MIN[1] - y).max(y - FREE_MAX[1]).max(0.0);
        if dx.hypot(dy) < radius + CLEARANCE {
            continue;
        }
        let clash = blocks.iter().any(|b| {
            (b.center.x - x).hypot(b.center.y - y) < radius + b.half.x.hypot(b.half.y) + 0.05
        });
        if clash {
            continue;
        }
        let texture = if rng.random_range(0..5u32) == 0 {
            Texture::Uniform(random_color(rng, 0.3, 0.8))
        } else {
            random_textured(rng)
        };
        let yaw: f64 = rng.random_range(-0.6..0.6);
        blocks.push(Block {
            center: Vector3::new(x, y, half.z),
            half,
            yaw,
            sin_cos_yaw: yaw.sin_cos(),
            texture,
            uv_offset: Vector2::new(rng.random_range(0.0..10.0), rng.random_range(0.0..10.0)),
        });
    }
    blocks
}
