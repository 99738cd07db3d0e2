//! Procedural surface textures for the synthetic room.
//!
//! Direct (photometric) tracking as in LSD-SLAM (Engel et al., ECCV 2014, §3) only constrains
//! the pose where the image gradient is large, so most surfaces carry strong multi-scale
//! gradients (value noise, bricks, tiles, dots, posters with sharp edges), while a few stay
//! uniform on purpose so that the semi-dense selection and the dense layer see textureless
//! regions too. Textures are functions of metric surface coordinates `(u, v)`, so a surface
//! looks the same from every view (Lambertian, brightness constancy holds).

use rand::Rng;
use rand_chacha::ChaCha8Rng;

/// Linear RGB albedo in [0, 1].
pub type Rgb = [f32; 3];

/// A surface pattern evaluated at metric coordinates.
#[derive(Clone, Debug)]
pub enum Texture {
    /// One colour: no gradient at all apart from shading.
    Uniform(Rgb),
    /// Fractal value noise between two colours: gradients at every scale from
    /// `1/frequency` metres down to `1/(frequency·2^(octaves−1))`.
    Noise {
        dark: Rgb,
        light: Rgb,
        frequency: f64,
        octaves: u32,
        seed: u64,
    },
    /// Running-bond bricks with mortar lines (sharp edges) and per-brick shade variation.
    Bricks {
        brick: Rgb,
        mortar: Rgb,
        width: f64,
        height: f64,
        mortar_width: f64,
        seed: u64,
    },
    /// Two-colour checker tiles with grout lines and a fine noise on top.
    Tiles {
        a: Rgb,
        b: Rgb,
        size: f64,
        seed: u64,
    },
    /// One disk of random colour and radius per `cell × cell` square, on a background colour.
    Dots {
        background: Rgb,
        cell: f64,
        seed: u64,
    },
    /// Rectangular posters (each with its own texture and a dark frame) on a background.
    Posters {
        background: Box<Texture>,
        posters: Vec<Poster>,
    },
}

/// A rectangle `[u0, u1] × [v0, v1]` (metres) on a surface showing `content`.
#[derive(Clone, Debug)]
pub struct Poster {
    pub u0: f64,
    pub v0: f64,
    pub u1: f64,
    pub v1: f64,
    /// Width of the dark frame around the poster, metres.
    pub frame: f64,
    pub content: Box<Texture>,
}

/// splitmix64 finaliser over the lattice point and the seed: a stateless, platform-independent
/// hash, so textures are bit-identical across runs and threads.
fn hash(seed: u64, x: i64, y: i64) -> u64 {
    let mut h = seed
        ^ (x as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15)
        ^ (y as u64)
            .wrapping_mul(0xC2B2_AE3D_27D4_EB4F)
            .rotate_left(31);
    h ^= h >> 30;
    h = h.wrapping_mul(0xBF58_476D_1CE4_E5B9);
    h ^= h >> 27;
    h = h.wrapping_mul(0x94D0_49BB_1331_11EB);
    h ^ (h >> 31)
}

/// A hash mapped to [0, 1).
fn unit(h: u64) -> f64 {
    (h >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
}

/// ⌊x⌋ without a libm call (the default x86-64 target has no SSE4.1 `roundsd`, and `floor`
/// was a tenth of the render time). Exact for |x| < 2⁶³.
#[inline]
fn floor(x: f64) -> f64 {
    let t = x as i64 as f64;
    if t > x { t - 1.0 } else { t }
}

/// Whether the integer-valued `x` is even.
#[inline]
fn even(x: f64) -> bool {
    (x as i64) & 1 == 0
}

/// Value noise in [0, 1] with quintic fade (C² across lattice cells).
fn value_noise(seed: u64, u: f64, v: f64) -> f64 {
    let (fu, fv) = (floor(u), floor(v));
    let (iu, iv) = (fu as i64, fv as i64);
    let fade = |t: f64| t * t * t * (t * (t * 6.0 - 15.0) + 10.0);
    let (su, sv) = (fade(u - fu), fade(v - fv));
    let n00 = unit(hash(seed, iu, iv));
    let n10 = unit(hash(seed, iu + 1, iv));
    let n01 = unit(hash(seed, iu, iv + 1));
    let n11 = unit(hash(seed, iu + 1, iv + 1));
    let top = n00 + (n10 - n00) * su;
    let bottom = n01 + (n11 - n01) * su;
    top + (bottom - top) * sv
}

/// Fractal sum of `octaves` value-noise layers, amplitude halving per octave, in [0, 1].
fn fbm(seed: u64, u: f64, v: f64, frequency: f64, octaves: u32) -> f64 {
    let (mut sum, mut norm, mut amp, mut f) = (0.0, 0.0, 1.0, frequency);
    for o in 0..octaves {
        // Offset each octave so lattice lines of different octaves do not coincide.
        let shift = 0.37 * f64::from(o);
        sum += amp
            * value_noise(
                seed.wrapping_add(u64::from(o)),
                u * f + shift,
                v * f - shift,
            );
        norm += amp;
        amp *= 0.6;
        f *= 2.03;
    }
    sum / norm
}

fn mix(a: Rgb, b: Rgb, t: f64) -> Rgb {
    let t = t.clamp(0.0, 1.0) as f32;
    [
        a[0] + (b[0] - a[0]) * t,
        a[1] + (b[1] - a[1]) * t,
        a[2] + (b[2] - a[2]) * t,
    ]
}

fn scale(c: Rgb, s: f64) -> Rgb {
    let s = s as f32;
    [
        (c[0] * s).min(1.0),
        (c[1] * s).min(1.0),
        (c[2] * s).min(1.0),
    ]
}

impl Texture {
    /// Albedo at surface coordinates `(u, v)` in metres.
    pub fn albedo(&self, u: f64, v: f64) -> Rgb {
        match self {
            Texture::Uniform(c) => *c,
            Texture::Noise {
                dark,
                light,
                frequency,
                octaves,
                seed,
            } => {
                // Half linear (stretched: the fbm concentrates around 0.5), half a steep
                // sigmoid of the same value, which turns iso-contours into sharp-edged blotches
                // ("camouflage"): strong gradients at every scale, not only smooth shading.
                let n = fbm(*seed, u, v, *frequency, *octaves) - 0.5;
                let steep = 1.0 / (1.0 + (-n * 40.0).exp());
                mix(*dark, *light, 0.5 * (n * 2.2 + 0.5) + 0.5 * steep)
            }
            Texture::Bricks {
                brick,
                mortar,
                width,
                height,
                mortar_width,
                seed,
            } => {
                let row = floor(v / height);
                let shifted = u / width + if even(row) { 0.0 } else { 0.5 };
                let col = floor(shifted);
                let (du, dv) = ((shifted - col) * width, (v / height - row) * height);
                if du < *mortar_width || dv < *mortar_width {
                    return *mortar;
                }
                let shade = 0.7 + 0.5 * unit(hash(*seed, col as i64, row as i64));
                let grain = 0.75 + 0.5 * fbm(*seed ^ 0x55, u, v, 40.0, 2);
                scale(*brick, shade * grain)
            }
            Texture::Tiles { a, b, size, seed } => {
                let (cu, cv) = (floor(u / size), floor(v / size));
                let (fu, fv) = (u / size - cu, v / size - cv);
                let grout = 0.02;
                if fu < grout || fv < grout {
                    return [0.12, 0.12, 0.13];
                }
                let base = if even(cu + cv) { *a } else { *b };
                let jitter = 0.8 + 0.35 * unit(hash(*seed, cu as i64, cv as i64));
                let grain = 0.65 + 0.7 * fbm(*seed ^ 0xAA, u, v, 25.0, 3);
                scale(base, jitter * grain)
            }
            Texture::Dots {
                background,
                cell,
                seed,
            } => {
                let (cu, cv) = (floor(u / cell), floor(v / cell));
                let h = hash(*seed, cu as i64, cv as i64);
                // Disk fully inside its cell, so only one cell has to be checked.
                let r = (0.15 + 0.3 * unit(h)) * cell;
                let cx = (cu + 0.5) * cell + (unit(h.rotate_left(13)) - 0.5) * (cell - 2.0 * r);
                let cy = (cv + 0.5) * cell + (unit(h.rotate_left(29)) - 0.5) * (cell - 2.0 * r);
                if (u - cx).powi(2) + (v - cy).powi(2) < r * r {
                    let g = |k: u32| {
                        0.05 + 0.9 * unit(hash(*seed ^ u64::from(k), cu as i64, cv as i64)) as f32
                    };
                    [g(1), g(2), g(3)]
                } else {
                    scale(*background, 0.75 + 0.5 * fbm(*seed ^ 0x33, u, v, 20.0, 3))
                }
            }
            Texture::Posters {
                background,
                posters,
            } => {
                for p in posters {
                    if u >= p.u0 && u <= p.u1 && v >= p.v0 && v <= p.v1 {
                        let inner = u - p.u0 > p.frame
                            && p.u1 - u > p.frame
                            && v - p.v0 > p.frame
                            && p.v1 - v > p.frame;
                        return if inner {
                            p.content.albedo(u, v)
                        } else {
                            [0.08, 0.07, 0.06]
                        };
                    }
                }
                background.albedo(u, v)
            }
        }
    }
}

/// A random colour with brightness in `[lo, hi]` and a moderate tint.
pub fn random_color(rng: &mut ChaCha8Rng, lo: f32, hi: f32) -> Rgb {
    let b = rng.random_range(lo..hi);
    let mut c = [0.0; 3];
    for ch in &mut c {
        *ch = (b + rng.random_range(-0.12..0.12f32)).clamp(0.02, 0.95);
    }
    c
}

/// A random strongly textured pattern (noise, bricks, tiles or dots) with feature sizes
/// suited to a surface seen from 1–4 m.
pub fn random_textured(rng: &mut ChaCha8Rng) -> Texture {
    let seed = rng.random::<u64>();
    match rng.random_range(0..4u32) {
        0 => Texture::Noise {
            dark: random_color(rng, 0.05, 0.3),
            light: random_color(rng, 0.6, 0.9),
            frequency: rng.random_range(4.0..9.0),
            octaves: 5,
            seed,
        },
        1 => Texture::Bricks {
            brick: random_color(rng, 0.4, 0.7),
            mortar: random_color(rng, 0.75, 0.9),
            width: rng.random_range(0.18..0.3),
            height: rng.random_range(0.06..0.1),
            mortar_width: 0.012,
            seed,
        },
        2 => Texture::Tiles {
            a: random_color(rng, 0.6, 0.85),
            b: random_color(rng, 0.2, 0.45),
            size: rng.random_range(0.12..0.3),
            seed,
        },
        _ => Texture::Dots {
            background: random_color(rng, 0.5, 0.8),
            cell: rng.random_range(0.08..0.2),
            seed,
        },
    }
}

/// Random posters on a `[u_min, u_max] × [v_min, v_max]` wall, each with its own strong
/// texture, over `background`; posters do not overlap (rejection sampling, deterministic).
pub fn random_posters(
    rng: &mut ChaCha8Rng,
    background: Texture,
    (u_min, u_max): (f64, f64),
    (v_min, v_max): (f64, f64),
    count: usize,
) -> Texture {
    let mut posters: Vec<Poster> = Vec::new();
    for _ in 0..200 {
        if posters.len() >= count {
            break;
        }
        let (w, h) = (rng.random_range(0.4..1.1), rng.random_range(0.35..0.9));
        let u0 = rng.random_range(u_min + 0.1..(u_max - w - 0.1).max(u_min + 0.11));
        let v0 = rng.random_range(v_min + 0.3..(v_max - h - 0.15).max(v_min + 0.31));
        let (u1, v1) = (u0 + w, v0 + h);
        let overlaps = posters
            .iter()
            .any(|p| u0 < p.u1 + 0.1 && p.u0 < u1 + 0.1 && v0 < p.v1 + 0.1 && p.v0 < v1 + 0.1);
        if !overlaps && u1 < u_max && v1 < v_max {
            let content = Box::new(random_textured(rng));
            posters.push(Poster {
                u0,
                v0,
                u1,
                v1,
                frame: 0.02,
                content,
            });
        }
    }
    Texture::Posters {
        background: Box::new(background),
        posters,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn dataset_synth_noise_is_bounded_and_varies() {
        let (mut lo, mut hi) = (f64::MAX, f64::MIN);
        for i in 0..2000 {
            let n = fbm(7, f64::from(i) * 0.013, f64::from(i % 37) * 0.07, 3.0, 4);
            assert!((0.0..=1.0).contains(&n));
            lo = lo.min(n);
            hi = hi.max(n);
        }
        assert!(hi - lo > 0.4, "noise range {lo}..{hi}");
        assert_eq!(value_noise(3, 1.25, -2.5), value_noise(3, 1.25, -2.5));
        assert_ne!(value_noise(3, 1.25, -2.5), value_noise(4, 1.25, -2.5));
    }
}
