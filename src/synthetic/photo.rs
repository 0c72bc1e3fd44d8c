//! Generated photos with a known truth, for image fits: superquadrics rendered on a desk, seen
//! orthographically along −z, with the faults of real photos.
//!
//! Every scene ([`photo`]) draws from one seed:
//! - one or two objects, each a box (ε ≤ 0.3), a cylinder (ε1 ≤ 0.3, ε2 = 1) or a superellipsoid
//!   (ε in 0.3–1.5), turned so that up to three faces show;
//! - Lambertian shading under one light (ambient 0.25), so a box's faces differ in brightness;
//!   in a third of the scenes the object's brightest face is scaled to within 3 % of the desk's
//!   luminance, in the desk's own hue;
//! - a checker texture on the object (half the scenes) and a desk that is plain, grained or
//!   cluttered with other shapes (kept 6 px clear of the objects, so the truth stays exact);
//! - a cast shadow (the silhouette moved away from the light and darkened), Gaussian blur up to
//!   σ = 1.2 px and noise up to σ = 0.03;
//! - four clicks as a user places a part (both ends of the truth's major axis, then of its minor,
//!   2σ of its pixels from the centroid), each moved by up to a quarter of the mean semi-axis.

use super::Rng;
use crate::model::forces::image::smooth;
use crate::model::image_measure::mask_axis_ends;
use crate::model::superquadric::{SuperquadricParams, inside_outside};
use glam::{DMat3, DVec2, DVec3};

/// The generated photos' width in pixels.
pub const PHOTO_WIDTH: usize = 240;
/// The generated photos' height in pixels.
pub const PHOTO_HEIGHT: usize = 180;

/// One object of a generated photo.
#[derive(Clone, Debug)]
pub struct PhotoObject {
    /// The object's pixels (row-major, `PHOTO_WIDTH` × `PHOTO_HEIGHT`): where a ray through the
    /// pixel's centre meets it.
    pub mask: Vec<bool>,
    /// The user's four clicks (pixels: column, row): the major axis's ends, then the minor's.
    pub clicks: [DVec2; 4],
    /// What the object is, in a few words ("box", "cylinder", "superellipsoid", with "faint"
    /// when a face is within 3 % of the desk's luminance).
    pub kind: String,
}

/// A generated photo and its truth.
#[derive(Clone, Debug)]
pub struct Photo {
    /// Row-major RGB in [0, 1], row 0 at the top.
    pub rgb: Vec<[f32; 3]>,
    /// The objects on it.
    pub objects: Vec<PhotoObject>,
    /// The scene's faults, in a few words (background, texture, blur, noise).
    pub description: String,
    /// The plain desk's luminance (before grain, clutter and shadow).
    pub desk_luminance: f64,
}

impl Photo {
    /// The luminance (Rec. 709 weights), as a photo file would be read.
    pub fn luminance(&self) -> Vec<f64> {
        self.rgb
            .iter()
            .map(|p| crate::model::forces::image::luminance_of(p.map(f64::from)))
            .collect()
    }
}

/// An object to render: pose, shape, albedo.
struct Solid {
    centre: DVec3,
    /// Columns: the model's axes in the world.
    turn: DMat3,
    shape: SuperquadricParams,
    albedo: [f64; 3],
    checker: Option<f64>,
}

impl Solid {
    /// The first surface point along the ray through pixel-plane point (x, y) looking down −z,
    /// and the world normal there.
    fn hit(&self, x: f64, y: f64) -> Option<(DVec3, DVec3)> {
        let reach = self.shape.semi_axes().length();
        let d = DVec2::new(x - self.centre.x, y - self.centre.y);
        if d.length() > reach {
            return None;
        }
        let inside = |z: f64| {
            let p = self.turn.transpose() * (DVec3::new(x, y, z) - self.centre);
            inside_outside(&self.shape, p) < 1.0
        };
        let (top, step) = (self.centre.z + reach, 0.25);
        let mut z = top;
        while z > self.centre.z - reach {
            if inside(z) {
                let (mut hi, mut lo) = (z + step, z);
                for _ in 0..30 {
                    let mid = 0.5 * (hi + lo);
                    if inside(mid) { lo = mid } else { hi = mid }
                }
                let p = DVec3::new(x, y, lo);
                return Some((p, self.normal(p)));
            }
            z -= step;
        }
        None
    }

    /// The outward unit normal at world point `p` (the gradient of F^ε1, by central differences).
    fn normal(&self, p: DVec3) -> DVec3 {
        let f = |q: DVec3| {
            let local = self.turn.transpose() * (q - self.centre);
            inside_outside(&self.shape, local).powf(self.shape.e1 / 2.0)
        };
        let h = 1e-3;
        let g = DVec3::new(
            f(p + DVec3::X * h) - f(p - DVec3::X * h),
            f(p + DVec3::Y * h) - f(p - DVec3::Y * h),
            f(p + DVec3::Z * h) - f(p - DVec3::Z * h),
        );
        g.try_normalize().unwrap_or(DVec3::Z)
    }

    /// The albedo at world point `p`, with the checker in the model's frame.
    fn albedo_at(&self, p: DVec3) -> [f64; 3] {
        let Some(period) = self.checker else {
            return self.albedo;
        };
        let l = self.turn.transpose() * (p - self.centre) / period;
        let odd = (l.x.floor() + l.y.floor() + l.z.floor()) as i64 % 2 != 0;
        let k = if odd { 0.85 } else { 1.0 };
        self.albedo.map(|a| a * k)
    }
}

/// Lambertian brightness with ambient 0.25.
fn shade(n: DVec3, light: DVec3) -> f64 {
    0.25 + 0.75 * n.dot(light).max(0.0)
}

/// The photo of seed `seed` (see the module docs).
pub fn photo(seed: u64) -> Photo {
    let mut rng = Rng::new(seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ 0x70_686f_746f);
    let (w, h) = (PHOTO_WIDTH, PHOTO_HEIGHT);
    let light = DVec3::new(rng.range(-0.7, 0.7), rng.range(-0.7, 0.7), 1.0).normalize();
    let desk_hue = [
        rng.range(0.8, 1.0),
        rng.range(0.75, 0.95),
        rng.range(0.6, 0.9),
    ];
    let desk_level = rng.range(0.35, 0.85);
    let desk =
        desk_hue.map(|c| c * desk_level / crate::model::forces::image::luminance_of(desk_hue));
    let desk_lum = crate::model::forces::image::luminance_of(desk);
    let count = 1 + (seed % 2) as usize;
    let faint = seed.is_multiple_of(3);
    let textured = (seed / 2).is_multiple_of(2);
    let mut solids = Vec::new();
    let mut kinds = Vec::new();
    for k in 0..count {
        let slot_width = w as f64 / count as f64;
        let kind = rng.next_u64() % 3;
        let (e1, e2, name) = match kind {
            0 => (rng.range(0.1, 0.3), rng.range(0.1, 0.3), "box"),
            1 => (rng.range(0.1, 0.3), 1.0, "cylinder"),
            _ => (rng.range(0.3, 1.5), rng.range(0.3, 1.5), "superellipsoid"),
        };
        let limit = (0.5 * slot_width).min(0.5 * h as f64) - 10.0;
        let mut axes = DVec3::new(
            rng.range(14.0, 34.0),
            rng.range(14.0, 34.0),
            rng.range(14.0, 40.0),
        );
        let reach = axes.length();
        if reach > limit {
            axes *= limit / reach;
        }
        let a = axes.max_element();
        let shape = SuperquadricParams {
            a,
            a1: axes.x / a,
            a2: axes.y / a,
            a3: axes.z / a,
            e1,
            e2,
        };
        let turn = DMat3::from_rotation_z(rng.range(0.0, std::f64::consts::TAU))
            * DMat3::from_rotation_x(rng.range(0.35, 0.9))
            * DMat3::from_rotation_z(rng.range(0.0, std::f64::consts::TAU));
        let centre = DVec3::new(
            slot_width * (k as f64 + 0.5) + rng.range(-4.0, 4.0),
            -(h as f64) / 2.0 + rng.range(-4.0, 4.0),
            0.0,
        );
        let hue = if faint {
            desk_hue
        } else {
            [
                rng.range(0.2, 1.0),
                rng.range(0.2, 1.0),
                rng.range(0.2, 1.0),
            ]
        };
        let mut solid = Solid {
            centre,
            turn,
            shape,
            albedo: hue,
            checker: textured.then(|| rng.range(6.0, 14.0)),
        };
        let level = if faint {
            // The brightest face (or the brightest shading) within 3 % of the desk.
            let brightest = brightest_shade(&solid, light);
            desk_lum * (1.0 + rng.range(-0.03, 0.03)) / brightest
        } else {
            rng.range(0.15, 0.9)
        };
        solid.albedo = hue.map(|c| c * level / crate::model::forces::image::luminance_of(hue));
        kinds.push(format!("{}{name}", if faint { "faint " } else { "" }));
        solids.push(solid);
    }
    // Render the objects: truth masks, shaded colours.
    let mut colour = vec![desk; w * h];
    let mut masks = vec![vec![false; w * h]; count];
    let mut any = vec![false; w * h];
    for i in 0..w * h {
        let (x, y) = ((i % w) as f64, -((i / w) as f64));
        for (k, s) in solids.iter().enumerate() {
            if let Some((p, n)) = s.hit(x, y) {
                let b = shade(n, light);
                colour[i] = s.albedo_at(p).map(|a| (a * b).min(1.0));
                masks[k][i] = true;
                any[i] = true;
            }
        }
    }
    // The desk: plain, grained or cluttered, then the cast shadows.
    let background = rng.next_u64() % 3;
    let clear = dilate(w, h, &any, 6);
    match background {
        1 => {
            let (f, phase) = (rng.range(0.05, 0.15), rng.range(0.0, 6.0));
            for i in (0..w * h).filter(|&i| !any[i]) {
                let (x, y) = ((i % w) as f64, (i / w) as f64);
                let g = 1.0 + 0.08 * (f * (x + 0.3 * y) + phase + 2.0 * (0.05 * y).sin()).sin();
                colour[i] = desk.map(|c| c * g);
            }
        }
        2 => {
            for _ in 0..12 {
                let c = DVec2::new(rng.range(0.0, w as f64), rng.range(0.0, h as f64));
                let r = DVec2::new(rng.range(4.0, 20.0), rng.range(4.0, 20.0));
                let paint = [rng.uniform(), rng.uniform(), rng.uniform()];
                let round = rng.uniform() < 0.5;
                for i in (0..w * h).filter(|&i| !clear[i]) {
                    let d = (DVec2::new((i % w) as f64, (i / w) as f64) - c) / r;
                    let inside = if round {
                        d.length_squared() <= 1.0
                    } else {
                        d.x.abs() <= 1.0 && d.y.abs() <= 1.0
                    };
                    if inside {
                        colour[i] = paint;
                    }
                }
            }
        }
        _ => {}
    }
    let shadow_shift = DVec2::new(-light.x, light.y) / light.z * rng.range(6.0, 14.0);
    for i in (0..w * h).filter(|&i| !any[i]) {
        let (c, r) = (
            (i % w) as f64 - shadow_shift.x,
            (i / w) as f64 - shadow_shift.y,
        );
        if c >= 0.0
            && r >= 0.0
            && (c as usize) < w
            && (r as usize) < h
            && any[r as usize * w + c as usize]
        {
            colour[i] = colour[i].map(|v| v * 0.6);
        }
    }
    // Blur and noise.
    let blur = [0.0, 0.7, 1.2][rng.next_u64() as usize % 3];
    let noise = [0.0, 0.01, 0.03][rng.next_u64() as usize % 3];
    let mut rgb: Vec<[f32; 3]> = gaussian_blur(w, h, &colour, blur)
        .into_iter()
        .map(|p| p.map(|v| (v + noise * rng.normal()).clamp(0.0, 1.0) as f32))
        .collect();
    rgb.shrink_to_fit();
    let objects = masks
        .into_iter()
        .zip(kinds)
        .map(|(mask, kind)| {
            // A solid is at least 14 px across, so its mask is never empty.
            let ends = mask_axis_ends(w, &mask).unwrap_or([DVec2::ZERO; 4]);
            let mean_semi_axis =
                ((ends[1] - ends[0]).length() + (ends[3] - ends[2]).length()) / 4.0;
            let clicks = ends.map(|p| {
                let off = rng.range(0.0, 0.25) * mean_semi_axis;
                let turn = rng.range(0.0, std::f64::consts::TAU);
                (p + off * DVec2::new(turn.cos(), turn.sin())).round()
            });
            PhotoObject { mask, clicks, kind }
        })
        .collect();
    let description = format!(
        "{} desk, {}, blur {blur}, noise {noise}",
        ["plain", "grained", "cluttered"][background as usize],
        if textured {
            "checkered"
        } else {
            "plain objects"
        },
    );
    Photo {
        rgb,
        objects,
        description,
        desk_luminance: desk_lum,
    }
}

/// The brightest Lambertian shading over the solid's normals facing the viewer.
fn brightest_shade(s: &Solid, light: DVec3) -> f64 {
    let reach = s.shape.semi_axes().length();
    let mut best: f64 = 0.25;
    let n = 24;
    for a in 0..n {
        for b in 0..n {
            let x = s.centre.x + reach * (2.0 * a as f64 / n as f64 - 1.0);
            let y = s.centre.y + reach * (2.0 * b as f64 / n as f64 - 1.0);
            if let Some((_, normal)) = s.hit(x, y) {
                best = best.max(shade(normal, light));
            }
        }
    }
    best
}

/// Pixels within `r` (Chebyshev) of a set pixel.
fn dilate(w: usize, h: usize, set: &[bool], r: usize) -> Vec<bool> {
    let mut out = vec![false; w * h];
    for i in (0..w * h).filter(|&i| set[i]) {
        let (c, row) = (i % w, i / w);
        for rr in row.saturating_sub(r)..(row + r + 1).min(h) {
            for cc in c.saturating_sub(r)..(c + r + 1).min(w) {
                out[rr * w + cc] = true;
            }
        }
    }
    out
}

/// A Gaussian blur of standard deviation `sigma` pixels (none at 0) of each colour channel, the
/// one the image potential smooths with.
fn gaussian_blur(w: usize, h: usize, img: &[[f64; 3]], sigma: f64) -> Vec<[f64; 3]> {
    if sigma <= 0.0 {
        return img.to_vec();
    }
    let mut out = img.to_vec();
    for channel in 0..3 {
        let c: Vec<f64> = img.iter().map(|p| p[channel]).collect();
        for (o, v) in out.iter_mut().zip(smooth(&c, w, h, sigma)) {
            o[channel] = v;
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_photo_is_the_same_for_a_seed_and_its_objects_lie_on_it() {
        for seed in 0..6 {
            let (a, b) = (photo(seed), photo(seed));
            assert_eq!(a.rgb, b.rgb);
            assert_eq!(a.objects.len(), 1 + (seed % 2) as usize);
            for o in &a.objects {
                let area = o.mask.iter().filter(|&&m| m).count();
                assert!(area > 300, "seed {seed}: {} has {area} px", o.kind);
                for c in o.clicks {
                    assert!(c.x >= 0.0 && c.y >= 0.0, "seed {seed}: click {c}");
                    assert!(c.x < PHOTO_WIDTH as f64 && c.y < PHOTO_HEIGHT as f64);
                }
            }
            assert!(a.rgb.iter().flatten().all(|v| (0.0..=1.0).contains(v)));
        }
    }

    #[test]
    fn a_faint_object_has_a_face_as_bright_as_the_desk() {
        // Seeds that are multiples of 3 are faint: an object's brightest face is within 3 % of
        // the desk (5 % allowed for the texture's dark squares being elsewhere and the noise).
        let p = photo(3);
        let lum = p.luminance();
        let o = &p.objects[0];
        assert!(o.kind.starts_with("faint"), "{}", o.kind);
        let desk = p.desk_luminance;
        let close = (0..lum.len())
            .filter(|&i| o.mask[i])
            .filter(|&i| (lum[i] - desk).abs() < 0.05 * desk)
            .count();
        assert!(close > 20, "{close} object pixels near the desk's {desk}");
    }
}
