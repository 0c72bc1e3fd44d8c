//! Deterministic synthetic data: the paper's range experiments (section VI-B), whose NRCC range
//! maps are not public, rebuilt from their description, and clouds sampled from superquadrics
//! with known parameters.
//!
//! * [`egg`]: 499 points from the upper half of an egg, as a range camera looking down −z sees it
//!   (an orthographic grid of rays, first hit).
//! * [`mug`]: 651 points from the upper part of an upright mug whose wall has pits.
//! * [`superquadric_cloud`]: points on a superquadric with known pose and parameters.
//! * [`ground_truth_cloud`]: a random superquadric seen as EMS's paper tests its fitter — a
//!   partial view, noise and outliers — with [`ParameterErrors`] to score a fit against it.
//! * [`photo`]: a generated photo of superquadrics on a desk (shading, texture, clutter,
//!   shadow, blur, noise) with each object's mask and a user's four clicks.
//! * [`union_cloud`]: a whole object of known parts, a body with limbs, whole or seen from one
//!   side.

use crate::model::deform::GlobalDeformation;
use crate::model::fit::{FitOptions, Initialization, Solver};
use crate::model::init::{InitialPose, moments};
use crate::model::superquadric::{SuperquadricParams, shape_at};
use glam::{DQuat, DVec3};
use std::f64::consts::{FRAC_PI_2, PI};

mod creature;
mod depth_video;
mod image_experiments;
mod photo;
mod sweeps;
mod union;

pub use creature::{Creature, CreaturePart, creature};
pub use depth_video::{
    DEPTH_SCALE, DepthVideo, DepthVideoRecipe, PoseError, VGA, depth_video, tracking_recipe,
};
pub use image_experiments::{ImageExperiment, doll_experiment, pestle_experiment};
pub use photo::{PHOTO_HEIGHT, PHOTO_WIDTH, Photo, PhotoObject, photo};
pub use sweeps::{SweepSet, set_cloud, sweep_cloud};
pub use union::{UnionCloud, union_cloud};

/// A small deterministic generator (SplitMix64), so data and tests are the same on every machine.
#[derive(Clone, Debug)]
pub struct Rng(u64);

impl Rng {
    /// A generator from a seed.
    pub fn new(seed: u64) -> Self {
        Self(seed)
    }
    /// The next 64 random bits.
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }
    /// Uniform in [0, 1).
    pub fn uniform(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }
    /// Uniform in [lo, hi).
    pub fn range(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * self.uniform()
    }
    /// Standard normal (Box–Muller).
    pub fn normal(&mut self) -> f64 {
        let u1 = self.uniform().max(1e-300);
        let u2 = self.uniform();
        (-2.0 * u1.ln()).sqrt() * (2.0 * PI * u2).cos()
    }
    /// Picks `n` of `items` without replacement, keeping their order.
    pub fn choose<T: Clone>(&mut self, items: &[T], n: usize) -> Vec<T> {
        let mut idx: Vec<usize> = (0..items.len()).collect();
        for i in 0..n.min(idx.len()) {
            let j = i + (self.next_u64() % (idx.len() - i) as u64) as usize;
            idx.swap(i, j);
        }
        let mut chosen: Vec<usize> = idx.into_iter().take(n).collect();
        chosen.sort_unstable();
        chosen.into_iter().map(|i| items[i].clone()).collect()
    }
}

/// Semi-length of the synthetic egg along its long (x) axis.
pub const EGG_HALF_LENGTH: f64 = 0.75;
/// Equatorial radius of the synthetic egg.
pub const EGG_RADIUS: f64 = 0.55;

/// Radius of the egg's cross-section at x (an egg: fatter towards +x), 0 outside |x| ≤ half length.
pub fn egg_radius(x: f64) -> f64 {
    let c = (x / EGG_HALF_LENGTH).clamp(-1.0, 1.0);
    EGG_RADIUS * (1.0 - c * c).max(0.0).sqrt() * (1.0 + 0.18 * c)
}

/// The paper's egg data: 499 points on the upper half (z ≥ 0) of an egg lying along x, sampled by
/// a range camera looking down −z on a regular grid, then thinned to 499 at random.
pub fn egg() -> Vec<DVec3> {
    let h = 0.045;
    let mut pts = Vec::new();
    let n = (EGG_HALF_LENGTH / h).ceil() as i32 + 1;
    for i in -n..=n {
        for j in -n..=n {
            let (x, y) = (i as f64 * h, j as f64 * h);
            let r = egg_radius(x);
            if y.abs() < r {
                pts.push(DVec3::new(x, y, (r * r - y * y).sqrt()));
            }
        }
    }
    Rng::new(233).choose(&pts, 499)
}

/// A point of the ridged egg: the [`egg_radius`] egg along x with five ridges round its axis
/// (radius × (1 + 0.08 cos 5φ)), a surface with detail no superquadric has; `s` ∈ [−1, 1] along the
/// axis, `phi` the angle round it.
pub fn ridged_egg_at(s: f64, phi: f64) -> DVec3 {
    let r = egg_radius(s * EGG_HALF_LENGTH) * (1.0 + 0.08 * (5.0 * phi).cos());
    DVec3::new(EGG_HALF_LENGTH * s, r * phi.cos(), r * phi.sin())
}

/// `n` points over the whole ridged egg ([`ridged_egg_at`]; uniform in s and φ, which is
/// area-uniform on a sphere), without noise.
pub fn ridged_egg(n: usize, seed: u64) -> Vec<DVec3> {
    let mut rng = Rng::new(seed);
    (0..n)
        .map(|_| ridged_egg_at(rng.range(-1.0, 1.0), rng.range(-PI, PI)))
        .collect()
}

/// Mug radius.
pub const MUG_RADIUS: f64 = 0.5;
/// Mug half height.
pub const MUG_HALF_HEIGHT: f64 = 0.8;
/// Depth of each pit in the mug's wall.
pub const MUG_PIT_DEPTH: f64 = 0.07;
/// Radius of each pit on the wall.
pub const MUG_PIT_RADIUS: f64 = 0.16;

/// Centres of the mug's pits as (azimuth, height).
pub fn mug_pits() -> Vec<(f64, f64)> {
    let mut rng = Rng::new(251);
    (0..10)
        .map(|i| {
            (
                -PI + (i as f64 + rng.range(0.2, 0.8)) * 2.0 * PI / 10.0,
                rng.range(0.2, 0.6),
            )
        })
        .collect()
}

/// Inward depth of the pitted wall at (azimuth, height): smooth spherical-cap dents.
pub fn mug_pit_depth(azimuth: f64, z: f64) -> f64 {
    mug_pits()
        .iter()
        .map(|&(a, h)| {
            let da = (azimuth - a + PI).rem_euclid(2.0 * PI) - PI;
            let d2 = (da * MUG_RADIUS).powi(2) + (z - h).powi(2);
            let t = 1.0 - d2 / (MUG_PIT_RADIUS * MUG_PIT_RADIUS);
            if t > 0.0 { MUG_PIT_DEPTH * t * t } else { 0.0 }
        })
        .fold(0.0, f64::max)
}

/// The paper's mug data: 651 points on the upper part of an upright mug (axis z): its closed top
/// and its wall down to mid-height, the wall dented by pits ([`mug_pits`]).
pub fn mug() -> Vec<DVec3> {
    let mut rng = Rng::new(251_1683);
    let wall_area = 2.0 * PI * MUG_RADIUS * MUG_HALF_HEIGHT;
    let top_area = PI * MUG_RADIUS * MUG_RADIUS;
    (0..651)
        .map(|_| {
            if rng.uniform() < wall_area / (wall_area + top_area) {
                let az = rng.range(-PI, PI);
                let z = rng.range(0.0, MUG_HALF_HEIGHT);
                let r = MUG_RADIUS - mug_pit_depth(az, z);
                DVec3::new(r * az.cos(), r * az.sin(), z)
            } else {
                let r = MUG_RADIUS * rng.uniform().sqrt();
                let az = rng.range(-PI, PI);
                DVec3::new(r * az.cos(), r * az.sin(), MUG_HALF_HEIGHT)
            }
        })
        .collect()
}

/// A curved, tapered tube closed by flat ends — a banana — built directly from its geometry
/// (not from `model::deform`), for the tapering and bending fits.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Banana {
    /// Radius of the circular arc the tube's axis follows.
    pub arc_radius: f64,
    /// The axis turns through ±`half_angle` radians either side of its middle.
    pub half_angle: f64,
    /// Radius of the circular cross-section at the middle.
    pub radius: f64,
    /// The cross-section's radius grows linearly along the arc, to (1 + `taper`) × `radius` at the
    /// +z end and (1 − `taper`) × `radius` at the other.
    pub taper: f64,
}

impl Default for Banana {
    /// Arc radius 3 turning ±0.6 rad (an axis 3.6 long), radius 0.4 tapering by ±40 %.
    fn default() -> Self {
        Self {
            arc_radius: 3.0,
            half_angle: 0.6,
            radius: 0.4,
            taper: 0.4,
        }
    }
}

impl Banana {
    /// A tube of half-length `half` (along its axis) whose axis turns through `turn_deg` degrees
    /// from end to end, of middle radius `radius` and taper `taper`.
    pub fn bent(half: f64, turn_deg: f64, radius: f64, taper: f64) -> Self {
        let half_angle = 0.5 * turn_deg.to_radians();
        Self {
            arc_radius: half / half_angle,
            half_angle,
            radius,
            taper,
        }
    }

    /// A straight tube of half-length `half` (a truncated cone when `taper` ≠ 0; a cone when it is
    /// 1): a banana whose arc turns through 0.01°.
    pub fn cone(half: f64, radius: f64, taper: f64) -> Self {
        Self::bent(half, 0.01, radius, taper)
    }

    /// `n` area-uniform points on the surface, with Gaussian noise of standard deviation `noise`
    /// per coordinate. Model frame: the axis's middle at the origin, the axis along z there,
    /// bending towards +x (the centre of the arc is at (`arc_radius`, 0, 0)).
    pub fn points(&self, n: usize, noise: f64, seed: u64) -> Vec<DVec3> {
        self.oriented_points(n, noise, seed)
            .into_iter()
            .map(|(p, _)| p)
            .collect()
    }

    /// As [`Banana::points`], each with the outward unit normal of the surface where it was drawn
    /// (before the noise): a one-view scan keeps the points whose normal faces the viewer.
    pub fn oriented_points(&self, n: usize, noise: f64, seed: u64) -> Vec<(DVec3, DVec3)> {
        let mut rng = Rng::new(seed);
        let (big_r, phi_max) = (self.arc_radius, self.half_angle);
        let r_at = |phi: f64| self.radius * (1.0 + self.taper * phi / phi_max);
        let axis = |phi: f64| DVec3::new(big_r * (1.0 - phi.cos()), 0.0, big_r * phi.sin());
        // Outward direction (away from the arc's centre) at angle φ, and the axis's tangent.
        let outward = |phi: f64| DVec3::new(-phi.cos(), 0.0, phi.sin());
        let tangent = |phi: f64| DVec3::new(phi.sin(), 0.0, phi.cos());
        // Tube area 2π R ∫ r dφ; each end a disk π r².
        let tube = 2.0 * PI * big_r * 2.0 * phi_max * self.radius;
        let ends = [-phi_max, phi_max].map(|phi| PI * r_at(phi).powi(2));
        let total = tube + ends[0] + ends[1];
        let r_max = r_at(phi_max).max(r_at(-phi_max));
        // The tube's normal leans towards the thin end by the slope of the radius along the axis.
        let slope = self.radius * self.taper / (phi_max * big_r);
        let mut out = Vec::with_capacity(n);
        while out.len() < n {
            let pick = rng.uniform() * total;
            let (p, normal) = if pick < tube {
                // Area element r (R + r cos θ) dφ dθ: rejection from the largest.
                let (phi, theta) = (rng.range(-phi_max, phi_max), rng.range(-PI, PI));
                let r = r_at(phi);
                if rng.uniform() * r_max * (big_r + r_max) > r * (big_r + r * theta.cos()) {
                    continue;
                }
                let radial = theta.cos() * outward(phi) + theta.sin() * DVec3::Y;
                (
                    axis(phi) + r * radial,
                    (radial - slope * tangent(phi)).normalize(),
                )
            } else {
                let phi = if pick < tube + ends[0] {
                    -phi_max
                } else {
                    phi_max
                };
                let (rho, theta) = (r_at(phi) * rng.uniform().sqrt(), rng.range(-PI, PI));
                let p = axis(phi) + rho * (theta.cos() * outward(phi) + theta.sin() * DVec3::Y);
                (p, phi.signum() * tangent(phi))
            };
            let noisy = p + noise * DVec3::new(rng.normal(), rng.normal(), rng.normal());
            out.push((noisy, normal));
        }
        out
    }
}

/// `n` points on the superquadric `shape` placed at (`translation`, `rotation`), at material
/// coordinates drawn so that a sphere would be sampled uniformly (u = asin(2r − 1)), with
/// Gaussian noise of standard deviation `noise` (data units) added to each coordinate.
pub fn superquadric_cloud(
    shape: &SuperquadricParams,
    translation: DVec3,
    rotation: DQuat,
    n: usize,
    noise: f64,
    seed: u64,
) -> Vec<DVec3> {
    let mut rng = Rng::new(seed);
    (0..n)
        .map(|_| {
            let u = (2.0 * rng.uniform() - 1.0)
                .asin()
                .clamp(-FRAC_PI_2, FRAC_PI_2);
            let v = rng.range(-PI, PI);
            let p = translation + rotation * shape_at(shape, u, v);
            p + noise * DVec3::new(rng.normal(), rng.normal(), rng.normal())
        })
        .collect()
}

/// How [`ground_truth_cloud`] makes a cloud.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CloudRecipe {
    /// Points on the surface (inliers) after the partial view.
    pub surface_points: usize,
    /// Fraction of the surface kept by the partial view (a cut by a random plane).
    pub kept: f64,
    /// Gaussian noise per coordinate, as a fraction of the largest semi-axis.
    pub noise: f64,
    /// Fraction of all points that are outliers.
    pub outliers: f64,
    /// Where the outliers are drawn.
    pub outlier_spread: OutlierSpread,
    /// The range ε1 and ε2 are drawn from, uniformly.
    pub epsilon: [f64; 2],
    /// Tapering and bending of the truth (none by default).
    pub deformation: GlobalDeformation,
}

/// How [`ground_truth_cloud`] spreads its outliers.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum OutlierSpread {
    /// Uniform in the inliers' bounding box grown by a fifth on every side (EMS's).
    #[default]
    Uniform,
    /// Gaussian about the inliers' centroid, with the standard deviation along each world axis
    /// half the inliers' extent along it: dense inside and near the object, thin far from it.
    Gaussian,
}

impl Default for CloudRecipe {
    /// 1000 surface points, 60 % of the surface, noise 1 % of the largest semi-axis, 20 %
    /// outliers uniform in a box, exponents in [0.2, 1.8] (EMS's hardest synthetic setting has a
    /// partial view, noise and outliers together).
    fn default() -> Self {
        Self {
            surface_points: 1000,
            kept: 0.6,
            noise: 0.01,
            outliers: 0.2,
            outlier_spread: OutlierSpread::Uniform,
            epsilon: [0.2, 1.8],
            deformation: GlobalDeformation::default(),
        }
    }
}

/// A cloud with known ground truth.
#[derive(Clone, Debug, PartialEq)]
pub struct GroundTruthCloud {
    /// The superquadric the points were drawn from (pose and shape, data units).
    pub truth: InitialPose,
    /// The truth's tapering and bending (the recipe's), applied in its frame before the pose.
    pub deformation: GlobalDeformation,
    /// Surface points (noisy) followed by outliers.
    pub points: Vec<DVec3>,
    /// The surface points before noise: samples of the seen part of the true surface.
    pub surface: Vec<DVec3>,
    /// How many of `points` are outliers (the last ones).
    pub outliers: usize,
}

/// Area-uniform points on the superquadric `shape` (model frame): triangles of a k = 101
/// tessellation drawn by area, then a uniform point in the triangle.
fn area_uniform(shape: &SuperquadricParams, n: usize, rng: &mut Rng) -> Vec<DVec3> {
    let tess = crate::model::fem::Tessellation::new(101);
    let x: Vec<DVec3> = tess
        .uv
        .iter()
        .map(|&[u, v]| shape_at(shape, u, v))
        .collect();
    let tri = |t: &[u32; 3]| (x[t[0] as usize], x[t[1] as usize], x[t[2] as usize]);
    let mut cumulative = Vec::with_capacity(tess.tris.len());
    let mut total = 0.0;
    for t in &tess.tris {
        let (a, b, c) = tri(t);
        total += 0.5 * (b - a).cross(c - a).length();
        cumulative.push(total);
    }
    (0..n)
        .map(|_| {
            let pick = rng.uniform() * total;
            let i = cumulative
                .partition_point(|&c| c < pick)
                .min(tess.tris.len() - 1);
            let (a, b, c) = tri(&tess.tris[i]);
            let (r1, r2) = (rng.uniform().sqrt(), rng.uniform());
            a * (1.0 - r1) + b * (r1 * (1.0 - r2)) + c * (r1 * r2)
        })
        .collect()
}

/// A random unit vector.
fn unit_vector(rng: &mut Rng) -> DVec3 {
    loop {
        let d = DVec3::new(rng.normal(), rng.normal(), rng.normal());
        if d.length_squared() > 1e-12 {
            return d.normalize();
        }
    }
}

/// A cloud from a random superquadric, generated as EMS's paper tests its fitter: semi-axes
/// uniform in [0.5, 3], ε1 and ε2 uniform in `recipe.epsilon` (EMS's [0.2, 1.8] by default), a uniformly random rotation and a
/// translation in [−1, 1]³; surface points drawn uniformly by area (then tapered and bent by
/// `recipe.deformation`), the part on one side of a random plane kept (`recipe.kept` of them), Gaussian noise, then uniform outliers. Deterministic
/// in `seed`.
pub fn ground_truth_cloud(seed: u64, recipe: &CloudRecipe) -> GroundTruthCloud {
    let mut rng = Rng::new(seed);
    let axes = [(); 3].map(|_| rng.range(0.5, 3.0));
    let a = axes[0].max(axes[1]).max(axes[2]);
    let shape = SuperquadricParams {
        a,
        a1: axes[0] / a,
        a2: axes[1] / a,
        a3: axes[2] / a,
        e1: rng.range(recipe.epsilon[0], recipe.epsilon[1]),
        e2: rng.range(recipe.epsilon[0], recipe.epsilon[1]),
    };
    let q = unit_vector(&mut rng);
    let rotation = DQuat::from_axis_angle(q, rng.range(0.0, 2.0 * PI)).normalize();
    let translation = DVec3::new(
        rng.range(-1.0, 1.0),
        rng.range(-1.0, 1.0),
        rng.range(-1.0, 1.0),
    );
    let drawn = (recipe.surface_points as f64 / recipe.kept.clamp(0.05, 1.0)).ceil() as usize;
    let mut surface = area_uniform(&shape, drawn, &mut rng);
    if !recipe.deformation.is_identity() {
        let height = shape.semi_axes().z;
        for p in &mut surface {
            *p = recipe.deformation.apply(*p, height);
        }
    }
    let view = unit_vector(&mut rng);
    surface.sort_by(|p, q| q.dot(view).total_cmp(&p.dot(view)));
    surface.truncate(recipe.surface_points);
    let sigma = recipe.noise * a;
    let surface: Vec<DVec3> = surface
        .iter()
        .map(|p| translation + rotation * *p)
        .collect();
    let mut points: Vec<DVec3> = surface
        .iter()
        .map(|p| *p + sigma * DVec3::new(rng.normal(), rng.normal(), rng.normal()))
        .collect();
    let (lo, hi) = points.iter().fold(
        (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY)),
        |(lo, hi), p| (lo.min(*p), hi.max(*p)),
    );
    let ratio = recipe.outliers.clamp(0.0, 0.9);
    let outliers = (ratio / (1.0 - ratio) * recipe.surface_points as f64).round() as usize;
    let centroid = points.iter().sum::<DVec3>() / points.len().max(1) as f64;
    for _ in 0..outliers {
        let p = match recipe.outlier_spread {
            OutlierSpread::Uniform => {
                let grow = 0.2 * (hi - lo);
                let t = DVec3::new(rng.uniform(), rng.uniform(), rng.uniform());
                lo - grow + t * (hi - lo + 2.0 * grow)
            }
            OutlierSpread::Gaussian => {
                let g = DVec3::new(rng.normal(), rng.normal(), rng.normal());
                centroid + 0.5 * (hi - lo) * g
            }
        };
        points.push(p);
    }
    GroundTruthCloud {
        truth: InitialPose {
            translation,
            rotation,
            shape,
        },
        deformation: recipe.deformation,
        points,
        surface,
        outliers,
    }
}

/// How far a fitted superquadric is from the ground truth, after matching the two by the
/// relabelling of axes that describes the fitted surface most like the truth
/// ([`ShapeDescriptor::best_relabelling`](crate::model::descriptor::ShapeDescriptor::best_relabelling)).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ParameterErrors {
    /// Mean |a_fit / a_true − 1| over the three semi-axes.
    pub axes: f64,
    /// Mean |ε_fit − ε_true| over ε1 and ε2.
    pub epsilon: f64,
    /// |t_fit − t_true| over the truth's largest semi-axis.
    pub translation: f64,
    /// Angle between the frames in degrees, the smallest over the axis sign flips (the
    /// superquadric's mirror symmetries).
    pub rotation_deg: f64,
}

impl ParameterErrors {
    /// The errors of the fitted pose and shape `fit` against `truth`.
    pub fn of(truth: &InitialPose, fit: &InitialPose) -> Self {
        use crate::model::descriptor::{RELABELLINGS, ShapeDescriptor};
        let (t, f) = (
            ShapeDescriptor::new(&truth.shape),
            ShapeDescriptor::new(&fit.shape),
        );
        let (k, _) = t.best_relabelling(&f);
        let relabelled = f.relabellings()[k];
        let axes = (0..3)
            .map(|i| (relabelled.log_axes[i] - t.log_axes[i]).exp() - 1.0)
            .map(f64::abs)
            .sum::<f64>()
            / 3.0;
        let epsilon = (0..2)
            .map(|i| (relabelled.epsilon[i] - t.epsilon[i]).abs())
            .sum::<f64>()
            / 2.0;
        let truth_m = glam::DMat3::from_quat(truth.rotation);
        let fit_m = glam::DMat3::from_quat(fit.rotation);
        let order = RELABELLINGS[k];
        let mut rotation_deg = f64::INFINITY;
        for signs in 0..8 {
            let s = |j: usize| if signs & (1 << j) != 0 { -1.0 } else { 1.0 };
            let frame = glam::DMat3::from_cols(
                fit_m.col(order[0]) * s(0),
                fit_m.col(order[1]) * s(1),
                fit_m.col(order[2]) * s(2),
            );
            let m = truth_m.transpose() * frame;
            if m.determinant() < 0.0 {
                continue;
            }
            let cos = ((m.x_axis.x + m.y_axis.y + m.z_axis.z - 1.0) / 2.0).clamp(-1.0, 1.0);
            rotation_deg = rotation_deg.min(cos.acos().to_degrees());
        }
        Self {
            axes,
            epsilon,
            translation: truth.translation.distance(fit.translation)
                / truth.shape.semi_axes().abs().max_element(),
            rotation_deg,
        }
    }
}

/// A paper experiment: its data and the fit options the paper gives, run by the paper's
/// dynamics ([`Solver::Dynamics`]).
fn paper_experiment(
    points: Vec<DVec3>,
    k: usize,
    w0: f64,
    w1: f64,
    shape: SuperquadricParams,
) -> (Vec<DVec3>, FitOptions) {
    let mut o = FitOptions {
        k,
        solver: Solver::Dynamics,
        ..Default::default()
    };
    o.dynamics.w0 = w0;
    o.dynamics.w1 = w1;
    o.init = Initialization::Explicit(InitialPose {
        translation: moments(&points).centroid,
        rotation: DQuat::IDENTITY,
        shape,
    });
    (points, o)
}

/// The paper's third experiment: [`egg`] data, 2603 nodes (k = 51), w0 = 1e-6, w1 = 0.1, and the
/// initial sphere at the data's centre of gravity, a = 1.2, a1 = a2 = a3 = 0.5, ε1 = ε2 = 1.
pub fn egg_experiment() -> (Vec<DVec3>, FitOptions) {
    let sphere = SuperquadricParams {
        a: 1.2,
        a1: 0.5,
        a2: 0.5,
        a3: 0.5,
        e1: 1.0,
        e2: 1.0,
    };
    paper_experiment(egg(), 51, 1e-6, 0.1, sphere)
}

/// The paper's fourth experiment: [`mug`] data, 1683 nodes (k = 41), w0 = 0.01, w1 = 0.1, and the
/// "tubular" initial state a = 1.5, a1 = a2 = 0.3, a3 = 0.8, ε1 = 0.7, ε2 = 1.0, upright at the
/// data's centroid.
pub fn mug_experiment() -> (Vec<DVec3>, FitOptions) {
    let tube = SuperquadricParams {
        a: 1.5,
        a1: 0.3,
        a2: 0.3,
        a3: 0.8,
        e1: 0.7,
        e2: 1.0,
    };
    paper_experiment(mug(), 41, 0.01, 0.1, tube)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn egg_and_mug_have_the_papers_point_counts() {
        let e = egg();
        assert_eq!(e.len(), 499);
        assert!(e.iter().all(|p| p.z >= 0.0));
        let m = mug();
        assert_eq!(m.len(), 651);
        assert!(
            m.iter()
                .all(|p| p.z >= 0.0 && p.z <= MUG_HALF_HEIGHT + 1e-12)
        );
        // Some wall points lie in pits.
        assert!(
            m.iter()
                .filter(|p| p.z < MUG_HALF_HEIGHT && MUG_RADIUS - p.truncate().length() > 0.02)
                .count()
                > 20
        );
    }

    #[test]
    fn ground_truth_clouds_follow_their_recipe_and_score_zero_against_themselves() {
        let recipe = CloudRecipe::default();
        let c = ground_truth_cloud(3, &recipe);
        assert_eq!(c.points.len(), 1250);
        assert_eq!(c.outliers, 250);
        // Noise-free inliers lie on the truth's surface: F = 1 there.
        let clean = ground_truth_cloud(
            3,
            &CloudRecipe {
                noise: 0.0,
                outliers: 0.0,
                ..recipe
            },
        );
        let t = &clean.truth;
        for p in &clean.points {
            let local = t.rotation.inverse() * (*p - t.translation);
            let f = crate::model::superquadric::inside_outside(&t.shape, local);
            assert!((f - 1.0).abs() < 0.02, "F = {f}");
        }
        let zero = ParameterErrors::of(t, t);
        assert!(zero.axes < 1e-12 && zero.epsilon < 1e-12 && zero.translation < 1e-12);
        assert!(zero.rotation_deg < 1e-4, "{}", zero.rotation_deg);
        // A relabelled description of the same surface (x and y swapped, frame turned 90°
        // about z) scores zero too; a different shape does not.
        let swapped = InitialPose {
            rotation: t.rotation * DQuat::from_rotation_z(FRAC_PI_2),
            shape: SuperquadricParams {
                a1: t.shape.a2,
                a2: t.shape.a1,
                ..t.shape
            },
            ..*t
        };
        let e = ParameterErrors::of(t, &swapped);
        assert!(
            e.axes < 1e-12 && e.epsilon < 1e-12 && e.rotation_deg < 1e-4,
            "{e:?}"
        );
        let other = ground_truth_cloud(4, &recipe).truth;
        let e = ParameterErrors::of(t, &other);
        assert!(e.axes > 0.05 && e.rotation_deg > 1.0, "{e:?}");
    }

    #[test]
    fn generator_is_deterministic() {
        assert_eq!(egg(), egg());
        assert_eq!(Rng::new(7).next_u64(), Rng::new(7).next_u64());
    }
}
