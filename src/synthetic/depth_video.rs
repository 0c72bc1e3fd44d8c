//! Generated depth videos with a known truth: a pinhole camera looks down at a floor on which a
//! superquadric moves and turns, with a second object behind it, an occluder that passes in
//! front, and a depth sensor's faults (noise growing as z², lost and mixed pixels at
//! silhouettes, scattered dropouts, 1 mm quantisation). Some videos let the object leave the
//! view. For the tracker's tests and sweeps ([`crate::model::track`]).

use super::Rng;
use crate::model::distance::gauge;
use crate::model::init::InitialPose;
use crate::model::superquadric::{SuperquadricParams, shape_at};
use crate::model::track::{DepthFrame, Intrinsics};
use glam::{DQuat, DVec3};
use rayon::prelude::*;
use std::f64::consts::{FRAC_PI_2, PI};

/// A VGA depth camera (640×480, 525 px focal length, as a Kinect or a RealSense at VGA):
/// Open3D's PrimeSense default, [`crate::io::PRIMESENSE_DEFAULT`].
pub const VGA: Intrinsics = crate::io::PRIMESENSE_DEFAULT;

/// The metres per unit of a generated frame's raw depth (1 mm).
pub const DEPTH_SCALE: f64 = 0.001;

/// How a depth video is made.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DepthVideoRecipe {
    /// Frames.
    pub frames: usize,
    /// The camera.
    pub intrinsics: Intrinsics,
    /// The moving object's shape (metres).
    pub shape: SuperquadricParams,
    /// Its centre's distance ahead of the camera along the floor at the first frame, metres.
    pub distance: f64,
    /// Its sideways offset at the first frame, metres (+x right).
    pub offset: f64,
    /// Its velocity over the floor per frame (sideways, ahead), metres.
    pub velocity: [f64; 2],
    /// Its turn per frame about the floor's normal, radians.
    pub spin: f64,
    /// Its tilt away from upright, radians (0: standing on the floor).
    pub tilt: f64,
    /// Its tumble per frame about a horizontal axis, radians (its centre then rides above the
    /// floor by its largest semi-axis).
    pub tumble: f64,
    /// The sensor's noise σ = `noise`·z² (metres; 0.0015 is a structured-light sensor's).
    pub noise: f64,
    /// A floor under the object.
    pub floor: bool,
    /// A second object behind the first.
    pub distractor: bool,
    /// An occluder that passes in front of the object around the middle of the video.
    pub occluder: bool,
    /// The seed of the noise.
    pub seed: u64,
}

impl Default for DepthVideoRecipe {
    fn default() -> Self {
        Self {
            frames: 40,
            intrinsics: VGA,
            shape: SuperquadricParams {
                a: 1.0,
                a1: 0.05,
                a2: 0.05,
                a3: 0.05,
                e1: 0.2,
                e2: 0.2,
            },
            distance: 0.9,
            offset: 0.0,
            velocity: [0.004, 0.0],
            spin: 0.02,
            tilt: 0.0,
            tumble: 0.0,
            noise: 0.0015,
            floor: true,
            distractor: true,
            occluder: false,
            seed: 1,
        }
    }
}

/// A generated depth video and its truth.
#[derive(Clone, Debug, PartialEq)]
pub struct DepthVideo {
    /// The camera.
    pub intrinsics: Intrinsics,
    /// Each frame's raw depth (row-major, millimetres, 0 = none).
    pub frames: Vec<Vec<u16>>,
    /// Each frame's true pose and shape of the object (camera frame).
    pub truth: Vec<InitialPose>,
    /// The fraction of the object's surface each frame shows.
    pub seen: Vec<f64>,
    /// Whether each frame shows the whole of the object's visible side: inside the image and
    /// not occluded.
    pub whole: Vec<bool>,
}

impl DepthVideo {
    /// Frame `i` as the tracker takes it.
    pub fn depth_frame(&self, i: usize) -> DepthFrame {
        DepthFrame {
            intrinsics: self.intrinsics,
            depth: self.frames[i]
                .iter()
                .map(|&d| (d as f64 * DEPTH_SCALE) as f32)
                .collect(),
        }
    }
}

/// The camera's height above the floor (metres) and its pitch down (radians).
const CAMERA: (f64, f64) = (0.7, 0.45);

/// The floor's up direction in the camera frame (y down, z ahead) and the horizontal direction
/// ahead.
fn floor_axes() -> (DVec3, DVec3) {
    let (s, c) = CAMERA.1.sin_cos();
    (DVec3::new(0.0, -c, -s), DVec3::new(0.0, -s, c))
}

/// A solid the camera sees.
struct Solid {
    pose: InitialPose,
}

impl Solid {
    /// The depth of the first point where the ray z·`ray` meets the solid, if it does.
    fn hit(&self, ray: DVec3) -> Option<f64> {
        let axes = self.pose.shape.semi_axes();
        let c = self.pose.translation;
        let radius = axes.length();
        let (a, b, k) = (ray.dot(ray), ray.dot(c), c.dot(c) - radius * radius);
        let disc = b * b - a * k;
        if !(disc > 0.0) {
            return None;
        }
        let (z0, z1) = (((b - disc.sqrt()) / a).max(1e-6), (b + disc.sqrt()) / a);
        if !(z1 > z0) {
            return None;
        }
        let inv = self.pose.rotation.inverse();
        let q = &self.pose.shape;
        let g = |z: f64| gauge(axes, q.e1, q.e2, inv * (ray * z - c)).value - 1.0;
        const MARCH: usize = 64;
        let mut prev = z0;
        for i in 1..=MARCH {
            let z = z0 + (z1 - z0) * i as f64 / MARCH as f64;
            if g(z) < 0.0 {
                let (mut lo, mut hi) = (prev, z);
                for _ in 0..32 {
                    let mid = 0.5 * (lo + hi);
                    if g(mid) < 0.0 {
                        hi = mid;
                    } else {
                        lo = mid;
                    }
                }
                return Some(hi);
            }
            prev = z;
        }
        None
    }

    /// The outward unit normal at a surface point `p` (camera frame).
    fn normal(&self, p: DVec3) -> DVec3 {
        let q = &self.pose.shape;
        let x = self.pose.rotation.inverse() * (p - self.pose.translation);
        let g = gauge(q.semi_axes(), q.e1, q.e2, x);
        (self.pose.rotation * g.grad_x).normalize_or_zero()
    }

    /// Whether its bounding sphere's image lies wholly inside the image.
    fn within(&self, c: &Intrinsics) -> bool {
        let (u, v, hu, hv) = self.extent(c);
        u - hu >= 0.0 && v - hv >= 0.0 && u + hu <= c.width as f64 && v + hv <= c.height as f64
    }

    /// Its bounding sphere's image: the centre's pixel and the half-extents at its nearest depth.
    fn extent(&self, c: &Intrinsics) -> (f64, f64, f64, f64) {
        let centre = self.pose.translation;
        let radius = self.pose.shape.semi_axes().length();
        let z = (centre.z - radius).max(0.05);
        (
            c.fx * centre.x / centre.z + c.cx,
            c.fy * centre.y / centre.z + c.cy,
            c.fx * radius / z,
            c.fy * radius / z,
        )
    }

    /// The pixel box its bounding sphere covers, clipped to the image (empty when it misses).
    fn window(&self, c: &Intrinsics) -> (usize, usize, usize, usize) {
        if self.pose.translation.z <= 0.0 {
            return (0, 0, 0, 0);
        }
        let (u, v, hu, hv) = self.extent(c);
        let clip = |x: f64, hi: u32| x.clamp(0.0, hi as f64) as usize;
        (
            clip((u - hu).floor(), c.width),
            clip((v - hv).floor(), c.height),
            clip((u + hu).ceil(), c.width),
            clip((v + hv).ceil(), c.height),
        )
    }

    /// Its surface area, from a 96 × 192 grid of its parametrisation.
    fn area(&self) -> f64 {
        let q = &self.pose.shape;
        let (nu, nv) = (96, 192);
        let at = |i: usize, j: usize| {
            let u = -FRAC_PI_2 + PI * i as f64 / nu as f64;
            let v = -PI + 2.0 * PI * j as f64 / nv as f64;
            shape_at(q, u, v)
        };
        let mut area = 0.0;
        for i in 0..nu {
            for j in 0..nv {
                let (p00, p10, p01, p11) = (at(i, j), at(i + 1, j), at(i, j + 1), at(i + 1, j + 1));
                area += 0.5
                    * ((p10 - p00).cross(p01 - p00).length()
                        + (p10 - p11).cross(p01 - p11).length());
            }
        }
        area
    }
}

/// How far the lowest point of `shape` turned by `rotation` lies below its centre along `up`:
/// the largest of −up·(R s) over a fine grid of its surface (exact when a pole or an equator
/// point is lowest, as for an upright model).
fn lowest_below_centre(shape: &SuperquadricParams, rotation: DQuat, up: DVec3) -> f64 {
    let down = rotation.inverse() * -up;
    let (rings, longitudes) = (128, 256);
    let mut lowest: f64 = 0.0;
    for a in 0..=rings {
        let u = -FRAC_PI_2 + PI * a as f64 / rings as f64;
        for b in 0..longitudes {
            let v = -PI + 2.0 * PI * b as f64 / longitudes as f64;
            lowest = lowest.max(down.dot(shape_at(shape, u, v)));
        }
    }
    lowest
}

/// The object's pose at frame `t` of `r`.
fn object_pose(r: &DepthVideoRecipe, t: f64) -> InitialPose {
    let (up, ahead) = floor_axes();
    let side = DVec3::X;
    // Upright: its z axis along the floor's up; turned by the spin about it, tilted and
    // tumbled about the sideways axis.
    let upright = DQuat::from_mat3(&glam::DMat3::from_cols(side, ahead, up));
    let turn = DQuat::from_axis_angle(up, r.spin * t);
    let tip = DQuat::from_axis_angle(side, r.tilt + r.tumble * t);
    let rotation = (turn * tip * upright).normalize();
    let lift = lowest_below_centre(&r.shape, rotation, up);
    let ground = ahead * (r.distance + r.velocity[1] * t) + side * (r.offset + r.velocity[0] * t);
    // The floor lies CAMERA.0 below the camera along up.
    let translation = ground - up * (CAMERA.0 - lift);
    InitialPose {
        translation,
        rotation,
        shape: r.shape,
    }
}

/// The depth video of `recipe` (see the module docs).
pub fn depth_video(recipe: &DepthVideoRecipe) -> DepthVideo {
    let c = recipe.intrinsics;
    let (w, h) = (c.width as usize, c.height as usize);
    let (up, ahead) = floor_axes();
    let total_area = Solid {
        pose: object_pose(recipe, 0.0),
    }
    .area();
    let distractor = Solid {
        pose: InitialPose {
            translation: ahead * (recipe.distance + 0.45) + DVec3::X * (recipe.offset - 0.12)
                - up * (CAMERA.0 - 0.09),
            rotation: DQuat::from_axis_angle(up, 0.5)
                * DQuat::from_mat3(&glam::DMat3::from_cols(DVec3::X, ahead, up)),
            shape: SuperquadricParams {
                a: 1.0,
                a1: 0.12,
                a2: 0.07,
                a3: 0.09,
                e1: 0.3,
                e2: 0.6,
            },
        },
    };
    // Frames are made side by side, each from its own seed.
    let frames: Vec<(Vec<u16>, InitialPose, f64, bool)> = (0..recipe.frames)
        .into_par_iter()
        .map(|f| {
            let mut rng = Rng::new(recipe.seed.wrapping_mul(0x9E37_79B9).wrapping_add(f as u64));
            let t = f as f64;
            let object = Solid {
                pose: object_pose(recipe, t),
            };
            // The occluder, a post, crosses the object's line of sight at the video's middle.
            let half = recipe.frames as f64 / 2.0;
            let post_x = object.pose.translation.x + 0.012 * (t - half);
            let occluder = Solid {
                pose: InitialPose {
                    translation: ahead * (recipe.distance * 0.55) + DVec3::X * post_x
                        - up * (CAMERA.0 - 0.25),
                    rotation: DQuat::from_mat3(&glam::DMat3::from_cols(DVec3::X, ahead, up)),
                    shape: SuperquadricParams {
                        a: 1.0,
                        a1: 0.02,
                        a2: 0.02,
                        a3: 0.25,
                        e1: 0.3,
                        e2: 1.0,
                    },
                },
            };
            let mut depth = vec![0.0f64; w * h];
            // The floor everywhere it is seen, then each solid over its window.
            if recipe.floor {
                for v in 0..h {
                    for u in 0..w {
                        let ray = c.ray(u as f64, v as f64);
                        let d = up.dot(ray);
                        if d < 0.0 {
                            depth[v * w + u] = -CAMERA.0 / d;
                        }
                    }
                }
            }
            let mut solids: Vec<(&Solid, bool)> = vec![(&object, true)];
            if recipe.distractor {
                solids.push((&distractor, false));
            }
            if recipe.occluder {
                solids.push((&occluder, false));
            }
            let mut object_hits: Vec<(usize, f64)> = Vec::new();
            for (solid, is_object) in &solids {
                let (u0, v0, u1, v1) = solid.window(&c);
                for v in v0..v1 {
                    for u in u0..u1 {
                        let ray = c.ray(u as f64, v as f64);
                        if let Some(z) = solid.hit(ray) {
                            let slot = &mut depth[v * w + u];
                            if *is_object {
                                object_hits.push((v * w + u, z));
                            }
                            if *slot == 0.0 || z < *slot {
                                *slot = z;
                            }
                        }
                    }
                }
            }
            // What of the object is seen: its pixels where it is the nearest, each weighing the
            // area of surface it covers.
            let (mut seen_area, mut occluded) = (0.0, 0usize);
            for &(i, z) in &object_hits {
                // Hidden by something other than the floor it stands on (which it touches).
                if depth[i] < z - 1e-3 {
                    occluded += 1;
                    continue;
                }
                if depth[i] < z {
                    continue;
                }
                let ray = c.ray((i % w) as f64, (i / w) as f64);
                let n = object.normal(ray * z);
                let cos = n.dot(-ray.normalize()).abs().max(0.1);
                seen_area += z * z / (c.fx * c.fy) / cos;
            }
            let inside = object.within(&c);
            (
                sensor(&depth, w, h, recipe.noise, &mut rng),
                object.pose,
                seen_area / total_area,
                inside && occluded == 0 && !object_hits.is_empty(),
            )
        })
        .collect();
    let mut video = DepthVideo {
        intrinsics: c,
        frames: Vec::with_capacity(recipe.frames),
        truth: Vec::with_capacity(recipe.frames),
        seen: Vec::with_capacity(recipe.frames),
        whole: Vec::with_capacity(recipe.frames),
    };
    for (frame, truth, seen, whole) in frames {
        video.frames.push(frame);
        video.truth.push(truth);
        video.seen.push(seen);
        video.whole.push(whole);
    }
    video
}

/// A depth sensor's reading of the true `depth`: pixels at a jump of more than 2 cm to a
/// neighbour are lost (half of them) or mixed with the neighbour (a fifth: flying pixels), 1 %
/// of the rest are lost, noise σ = k·z² is added, and depth is rounded to millimetres.
fn sensor(depth: &[f64], w: usize, h: usize, k: f64, rng: &mut Rng) -> Vec<u16> {
    let mut out = vec![0u16; w * h];
    for v in 0..h {
        for u in 0..w {
            let z = depth[v * w + u];
            if !(z > 0.0) {
                continue;
            }
            let mut jump: Option<f64> = None;
            for (du, dv) in [(-1i64, 0i64), (1, 0), (0, -1), (0, 1)] {
                let (x, y) = (u as i64 + du, v as i64 + dv);
                if x < 0 || y < 0 || x >= w as i64 || y >= h as i64 {
                    continue;
                }
                let n = depth[y as usize * w + x as usize];
                if (n - z).abs() > 0.02 || n == 0.0 {
                    jump = Some(n);
                }
            }
            let roll = rng.uniform();
            let mut z = z;
            if let Some(n) = jump {
                if roll < 0.5 {
                    continue;
                }
                if roll < 0.7 && n > 0.0 {
                    z = z + (n - z) * rng.uniform();
                }
            } else if roll < 0.01 {
                continue;
            }
            let noisy = z + k * z * z * rng.normal();
            out[v * w + u] = (noisy / DEPTH_SCALE).round().clamp(0.0, u16::MAX as f64) as u16;
        }
    }
    out
}

/// Recipe `i` of the generated tracking sweep: shapes over the exponents (boxes, cylinders,
/// ellipsoids, diamonds and pinched ones) and sizes (semi-axes 3–10 cm), speeds up to 1.2 cm and
/// 0.05 rad a frame, noise from none to three times a structured-light sensor's, tilted and
/// tumbling objects, the occluder on every third, and every fifth leaving the view.
pub fn tracking_recipe(i: usize) -> DepthVideoRecipe {
    let mut rng = Rng::new(0x7AC4 + i as u64 * 7919);
    let exponents = [
        (0.2, 0.2),
        (0.2, 1.0),
        (1.0, 1.0),
        (0.6, 1.6),
        (1.4, 0.4),
        (0.4, 0.8),
    ];
    let (e1, e2) = exponents[i % exponents.len()];
    let shape = SuperquadricParams {
        a: 1.0,
        a1: rng.range(0.03, 0.08),
        a2: rng.range(0.03, 0.08),
        a3: rng.range(0.04, 0.10),
        e1,
        e2,
    };
    let leaves = i % 5 == 4;
    let speed = rng.range(0.0, 0.012);
    let heading = rng.range(0.0, 2.0 * PI);
    let mut velocity = [speed * heading.cos(), 0.5 * speed * heading.sin()];
    if leaves {
        // Out through the right edge over the second half.
        velocity = [0.02, 0.0];
    }
    let tumbling = i % 7 == 3;
    DepthVideoRecipe {
        frames: 40,
        intrinsics: VGA,
        shape,
        distance: rng.range(0.7, 1.3),
        offset: if leaves { 0.0 } else { rng.range(-0.1, 0.1) },
        velocity,
        spin: rng.range(-0.05, 0.05),
        tilt: if i % 4 == 1 { rng.range(0.2, 0.6) } else { 0.0 },
        tumble: if tumbling { rng.range(0.01, 0.03) } else { 0.0 },
        noise: [0.0, 0.0015, 0.003, 0.0045][i % 4],
        floor: true,
        distractor: true,
        occluder: i % 3 == 2,
        seed: i as u64 + 1,
    }
}

impl DepthVideo {
    /// The pixel box [x0, y0, x1, y1) around the object's true outline in frame `i`, clipped to
    /// the image: what a user drags around it.
    pub fn roi(&self, i: usize) -> [u32; 4] {
        let truth = &self.truth[i];
        let c = &self.intrinsics;
        let (mut lo, mut hi) = (glam::DVec2::splat(f64::INFINITY), glam::DVec2::ZERO);
        for a in 0..=32 {
            for b in 0..64 {
                let u = -FRAC_PI_2 + PI * a as f64 / 32.0;
                let v = -PI + 2.0 * PI * b as f64 / 64.0;
                let p = truth.translation + truth.rotation * shape_at(&truth.shape, u, v);
                if let Some(px) = c.project(p) {
                    lo = lo.min(px);
                    hi = hi.max(px);
                }
            }
        }
        let clip = |x: f64, top: u32| x.clamp(0.0, top as f64) as u32;
        [
            clip(lo.x.floor(), c.width),
            clip(lo.y.floor(), c.height),
            clip(hi.x.ceil() + 1.0, c.width),
            clip(hi.y.ceil() + 1.0, c.height),
        ]
    }
}

/// How far a tracked pose lies from the truth.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PoseError {
    /// The centres' distance, metres.
    pub centre: f64,
    /// The orientations' angle modulo the truth's labellings
    /// ([`crate::model::track::orientation_error`]), radians.
    pub angle: f64,
    /// The largest semi-axis difference, against the truth's labelling nearest the fit's
    /// orientation, metres.
    pub axes: f64,
}

impl PoseError {
    /// The error of `fit` against `truth`.
    pub fn of(truth: &InitialPose, fit: &InitialPose) -> Self {
        let nearest = crate::model::track::nearest_equivalent(truth, fit.rotation);
        Self {
            centre: (truth.translation - fit.translation).length(),
            angle: crate::model::track::orientation_error(truth, fit),
            axes: (nearest.shape.semi_axes() - fit.shape.semi_axes())
                .abs()
                .max_element(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every video's object stands on the floor: its lowest surface point lies on the floor
    /// plane, never through it, upright or tilted.
    #[test]
    fn objects_stand_on_the_floor() {
        let (up, _) = floor_axes();
        for i in 0..12 {
            let recipe = tracking_recipe(i);
            for t in [0.0, 7.0, 20.0] {
                let pose = object_pose(&recipe, t);
                // The camera is at the origin, CAMERA.0 above the floor.
                let mut lowest = f64::INFINITY;
                for a in 0..=200 {
                    let u = -FRAC_PI_2 + PI * a as f64 / 200.0;
                    for b in 0..400 {
                        let v = -PI + 2.0 * PI * b as f64 / 400.0;
                        let p = pose.translation + pose.rotation * shape_at(&pose.shape, u, v);
                        lowest = lowest.min(up.dot(p) + CAMERA.0);
                    }
                }
                assert!(
                    lowest > -5e-4 && lowest < 5e-4,
                    "video {i} frame {t}: lowest point {lowest} m from the floor"
                );
            }
        }
    }

    /// An upright object's z axis is the floor's up, and its rotation is proper.
    #[test]
    fn upright_objects_point_up() {
        let (up, _) = floor_axes();
        let recipe = tracking_recipe(0);
        assert_eq!(recipe.tilt, 0.0);
        let pose = object_pose(&recipe, 0.0);
        assert!((pose.rotation * DVec3::Z - up).length() < 1e-9);
        assert!((pose.rotation.length() - 1.0).abs() < 1e-12);
    }
}
