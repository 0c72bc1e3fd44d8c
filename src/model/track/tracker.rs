//! The tracker: one superquadric followed from frame to frame by predict, gate and a MAP fit.

use super::camera::{DepthFrame, Intrinsics};
use super::problem::{FreeRay, Information, Prior, Tracked};
use super::support::{Plane, Support, find_plane};
use super::symmetry::nearest_equivalent;
use crate::model::distance::{NUM_UNKNOWNS, radial_distance};
use crate::model::init::InitialPose;
use crate::model::linalg::cholesky_solve;
use crate::model::lm::{LmOptions, Metric, Mixture, normal_equations, solve_em};
use crate::model::superquadric::MIN_EPSILON;
use glam::{DQuat, DVec3};

/// A frame the tracker takes: a depth image, or points already in the camera frame.
#[derive(Clone, Debug, PartialEq)]
pub enum Frame {
    /// A depth image (its free space is used).
    Depth(DepthFrame),
    /// Camera-frame points without an image (no free space).
    Points(Vec<DVec3>),
}

/// How a track is followed. Lengths are in units of the object's size (the mean semi-axis), so
/// the defaults hold at any scale.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TrackOptions {
    /// The outlier mixture's prior outlier fraction in [0, 1) (the scene around the object).
    pub outlier_ratio: f64,
    /// Use the depth image's free space.
    pub free_space: bool,
    /// Most data points a frame's fit takes (the window's pixels are strided down to it).
    pub max_points: usize,
    /// Most free-space rays a frame's fit takes.
    pub max_free_rays: usize,
    /// The process noise: how far, in sizes, the centre may stray a frame from constant
    /// velocity (one standard deviation).
    pub motion: f64,
    /// How far, in radians, the orientation may stray a frame from constant spin.
    pub turn: f64,
    /// How much, in sizes, a semi-axis may change a frame (a rigid object: little).
    pub shape_drift: f64,
    /// How much an exponent may change a frame.
    pub exponent_drift: f64,
    /// A frame whose inliers number less than this fraction of the track's usual count, or
    /// fewer than [`MIN_TRACK_POINTS`], is lost.
    pub min_seen: f64,
    /// Hold ε1 and ε2 where the first frame put them.
    pub hold_exponents: bool,
    /// Find the plane the object stands on in each depth frame, take its points out of the
    /// data and hold the model above it ([`super::support`]).
    pub support: bool,
}

impl Default for TrackOptions {
    fn default() -> Self {
        Self {
            outlier_ratio: 0.2,
            free_space: true,
            max_points: 3000,
            max_free_rays: 1500,
            motion: 0.1,
            turn: 0.05,
            shape_drift: 0.002,
            exponent_drift: 0.005,
            min_seen: 0.15,
            hold_exponents: false,
            support: true,
        }
    }
}

impl TrackOptions {
    /// Checks the options; the message names the first field out of range.
    pub fn validate(&self) -> Result<(), String> {
        if !(0.0..1.0).contains(&self.outlier_ratio) {
            return Err(format!(
                "outliers = {} is out of range [0, 1)",
                self.outlier_ratio
            ));
        }
        if self.max_points < MIN_TRACK_POINTS || self.max_free_rays == 0 {
            return Err(format!(
                "max_points must be at least {MIN_TRACK_POINTS} and max_free_rays at least 1"
            ));
        }
        for (name, v) in [
            ("motion", self.motion),
            ("turn", self.turn),
            ("shape_drift", self.shape_drift),
            ("exponent_drift", self.exponent_drift),
            ("min_seen", self.min_seen),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(format!("{name} = {v} must be finite and at least 0"));
            }
        }
        Ok(())
    }
}

/// Fewest inlier points a frame needs to count as seen.
pub const MIN_TRACK_POINTS: usize = 30;

/// The least distance from the floor, per metre of depth, at which a point counts as off it
/// (0.4 %: three standard deviations of a structured-light sensor's noise near a metre, with
/// its millimetre quantisation).
pub const FLOOR_TOLERANCE: f64 = 0.004;

/// Free-space samples taken along each ray through the model's bounding sphere.
const FREE_SAMPLES: usize = 8;

/// EM rounds and steps a round of a frame's fit: it starts at the prediction, a few steps from
/// rest.
const FRAME_ROUNDS: (u32, u32) = (8, 4);

/// What the tracker made of one frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TrackedFrame {
    /// The pose and shape: the frame's fit, or the last good one when lost.
    pub pose: InitialPose,
    /// True when the frame showed too little of the object; `pose` is then the last good one.
    pub lost: bool,
    /// Gated points the fit took.
    pub points: usize,
    /// Their inlier weight sum.
    pub inliers: f64,
    /// Free-space rays the fit took.
    pub free_rays: usize,
    /// The inliers' RMS distance to the surface (√(3σ²)).
    pub rms: f64,
    /// Levenberg–Marquardt steps.
    pub iterations: u32,
    /// The frame's MAP energy under the fit's final inlier weights, at the prediction and at
    /// the fit (0 when lost): the fit's is the lower.
    pub energy: [f64; 2],
}

/// A tracked superquadric's state between frames.
#[derive(Clone, Debug)]
pub struct Tracker {
    opts: TrackOptions,
    pose: InitialPose,
    velocity: DVec3,
    spin: DVec3,
    covariance: Information,
    sigma2: f64,
    usual_inliers: Option<f64>,
    lost_for: u32,
    floor: Option<Plane>,
    frame: u64,
}

/// The object's size: its mean semi-axis.
fn size_of(pose: &InitialPose) -> f64 {
    let a = pose.shape.semi_axes();
    (a.x + a.y + a.z) / 3.0
}

/// `m` inverted by Cholesky, with a relative ridge that keeps a nearly singular one finite.
fn inverse(m: &Information) -> Information {
    let scale = (0..NUM_UNKNOWNS).map(|k| m[k][k].abs()).fold(0.0, f64::max);
    let mut a = *m;
    for (k, row) in a.iter_mut().enumerate() {
        row[k] += 1e-12 * scale.max(f64::MIN_POSITIVE);
    }
    let mut out = [[0.0; NUM_UNKNOWNS]; NUM_UNKNOWNS];
    for c in 0..NUM_UNKNOWNS {
        let mut e = [0.0; NUM_UNKNOWNS];
        e[c] = 1.0;
        let x = cholesky_solve(&a, &e).unwrap_or([0.0; NUM_UNKNOWNS]);
        for r in 0..NUM_UNKNOWNS {
            out[r][c] = x[r];
        }
    }
    out
}

/// A diagonal matrix over the unknowns from the semi-axes', exponents', translation's and
/// rotation's variances.
fn diagonal(axes: f64, exponents: f64, translation: f64, rotation: f64) -> Information {
    let mut m = [[0.0; NUM_UNKNOWNS]; NUM_UNKNOWNS];
    for k in 0..NUM_UNKNOWNS {
        m[k][k] = match k {
            0..=2 => axes,
            3 | 4 => exponents,
            5..=7 => translation,
            _ => rotation,
        };
    }
    m
}

/// The MAP energy of `problem` at `pose` with the points weighted by `weights` (1 each when
/// empty) summing to `total`: Σ wᵢ eᵢ² plus the prior, free-space and support terms.
fn energy_at(problem: &Tracked, pose: &InitialPose, weights: &[f64], total: f64) -> f64 {
    use crate::model::lm::Problem;
    let (e, _) = problem.evaluate(pose, &[]);
    let data: f64 = if weights.is_empty() {
        e.iter().map(|d| d * d).sum()
    } else {
        e.iter().zip(weights).map(|(d, w)| w * d * d).sum()
    };
    data + problem.extra_cost(pose, weights, total)
}

impl Tracker {
    /// A track that starts at `pose` (camera frame), as uncertain as a first guess: a quarter of
    /// its size in centre and semi-axes, 0.3 rad and 0.3 in the exponents. Errors name an option
    /// out of range or a pose that is not finite.
    pub fn new(pose: InitialPose, opts: TrackOptions) -> Result<Self, String> {
        opts.validate()?;
        let finite =
            pose.translation.is_finite() && pose.rotation.is_finite() && pose.shape.is_finite();
        if !(finite && size_of(&pose) > 0.0) {
            return Err("the initial pose is not finite or has no size".into());
        }
        let size = size_of(&pose);
        let quarter = (0.25 * size).powi(2);
        Ok(Self {
            opts,
            pose,
            velocity: DVec3::ZERO,
            spin: DVec3::ZERO,
            covariance: diagonal(quarter, 0.09, quarter, 0.09),
            sigma2: (0.02 * size).powi(2),
            usual_inliers: None,
            lost_for: 0,
            floor: None,
            frame: 0,
        })
    }

    /// The last good pose.
    pub fn pose(&self) -> InitialPose {
        self.pose
    }

    /// Frames lost in a row.
    pub fn lost_for(&self) -> u32 {
        self.lost_for
    }

    /// The prediction for the next frame: constant velocity and spin from the last good frame
    /// (none while lost), its covariance grown by the process noise.
    fn predict(&self) -> (InitialPose, Information) {
        let mut mean = self.pose;
        if self.lost_for == 0 {
            mean.translation += self.velocity;
            mean.rotation = (mean.rotation * DQuat::from_scaled_axis(self.spin)).normalize();
        }
        let size = size_of(&self.pose);
        let o = &self.opts;
        let q = diagonal(
            (o.shape_drift * size).powi(2),
            o.exponent_drift.powi(2),
            (o.motion * size).powi(2),
            o.turn.powi(2),
        );
        let mut p = self.covariance;
        for a in 0..NUM_UNKNOWNS {
            for b in 0..NUM_UNKNOWNS {
                p[a][b] += q[a][b];
            }
        }
        (mean, p)
    }

    /// Follows the object into `frame`: see the module docs of [`super`].
    pub fn step(&mut self, frame: &Frame) -> TrackedFrame {
        let (mean, covariance) = self.predict();
        let size = size_of(&mean);
        let sd = |k: usize| covariance[k][k].max(0.0).sqrt();
        let spread = (sd(5).powi(2) + sd(6).powi(2) + sd(7).powi(2)).sqrt()
            + size * (sd(8).powi(2) + sd(9).powi(2) + sd(10).powi(2)).sqrt()
            + (sd(0).powi(2) + sd(1).powi(2) + sd(2).powi(2)).sqrt();
        // The gate: three standard deviations of the prediction and of the data's noise, at
        // most the object's size.
        let gate = (3.0 * (spread + (3.0 * self.sigma2).sqrt())).min(size);
        let (points, free, floor) = self.gather(frame, &mean, gate);
        self.frame += 1;
        self.floor = floor;
        let support = floor.map(|plane| Support { plane });
        let lost = |me: &mut Self, covariance: Information, points: usize, inliers: f64| {
            me.lost_for += 1;
            me.velocity = DVec3::ZERO;
            me.spin = DVec3::ZERO;
            me.covariance = covariance;
            TrackedFrame {
                pose: me.pose,
                lost: true,
                points,
                inliers,
                free_rays: 0,
                rms: (3.0 * me.sigma2).sqrt(),
                iterations: 0,
                energy: [0.0; 2],
            }
        };
        if points.len() < MIN_TRACK_POINTS {
            return lost(self, covariance, points.len(), 0.0);
        }
        let lm = self.lm_options(&points, &mean, gate);
        let prior = Prior {
            mean,
            information: inverse(&covariance),
            scale: self.sigma2,
        };
        let problem = Tracked::new(&points, &lm, Some(&prior), &free, support.as_ref());
        let fit = solve_em(&problem, &mean, self.sigma2, false, &lm);
        let inliers = if fit.weights.is_empty() {
            points.len() as f64
        } else {
            fit.weights.iter().sum()
        };
        let energy = [energy_at(&problem, &mean, &fit.weights, inliers), fit.cost];
        let usual = self.usual_inliers.unwrap_or(inliers);
        let finite = fit.model.translation.is_finite()
            && fit.model.rotation.is_finite()
            && fit.model.shape.is_finite();
        if !finite || inliers < MIN_TRACK_POINTS as f64 || inliers < self.opts.min_seen * usual {
            return lost(self, covariance, points.len(), inliers);
        }
        // The posterior information: the prediction's plus the data's JᵀWJ/σ².
        let (_, feet) = crate::model::lm::Problem::evaluate(&problem, &fit.model, &[]);
        let (jtj, _) = normal_equations(&problem, &fit.model, &fit.weights, &feet);
        let mut information = prior.information;
        for a in 0..NUM_UNKNOWNS {
            for b in 0..=a {
                let v = jtj[a][b] / fit.sigma2;
                information[a][b] += v;
                if a != b {
                    information[b][a] += v;
                }
            }
        }
        let pose = nearest_equivalent(&fit.model, mean.rotation);
        let frames = (self.lost_for + 1) as f64;
        self.velocity = (pose.translation - self.pose.translation) / frames;
        let mut turn = (self.pose.rotation.inverse() * pose.rotation).normalize();
        if turn.w < 0.0 {
            turn = -turn;
        }
        self.spin = turn.to_scaled_axis() / frames;
        self.pose = pose;
        self.covariance = inverse(&information);
        self.sigma2 = fit.sigma2;
        // The usual count follows slowly, so that a few poor frames do not lower the bar.
        self.usual_inliers = Some(match self.usual_inliers {
            None => inliers,
            Some(u) => 0.8 * u + 0.2 * inliers,
        });
        self.lost_for = 0;
        TrackedFrame {
            pose,
            lost: false,
            points: points.len(),
            inliers,
            free_rays: free.len(),
            rms: (3.0 * fit.sigma2).sqrt(),
            iterations: fit.iterations,
            energy,
        }
    }

    /// The Levenberg–Marquardt settings of a frame's fit of `points` about `mean`.
    fn lm_options(&self, points: &[DVec3], mean: &InitialPose, gate: f64) -> LmOptions {
        let (lo, hi) = points.iter().fold(
            (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY)),
            |(lo, hi), p| (lo.min(*p), hi.max(*p)),
        );
        let extent = (hi - lo).max(DVec3::splat(1e-3 * size_of(mean)));
        let size = size_of(mean);
        LmOptions {
            mixture: Mixture {
                outlier_ratio: self.opts.outlier_ratio,
                outlier_density: 1.0 / (extent.x * extent.y * extent.z),
                sigma2_floor: (1e-3 * size).powi(2),
            },
            max_rounds: FRAME_ROUNDS.0,
            steps_per_round: FRAME_ROUNDS.1,
            tolerance: 1e-4,
            metric: Metric::Surface,
            max_semi_axis: 2.0 * (mean.shape.semi_axes().max_element() + gate),
            min_epsilon: MIN_EPSILON,
            hold_exponents: self.opts.hold_exponents,
            own_sigma2: false,
        }
    }

    /// The frame's points within `gate` of the predicted surface `mean` and off the floor, its
    /// free-space rays through the model's bounding sphere, and the floor.
    fn gather(
        &self,
        frame: &Frame,
        mean: &InitialPose,
        gate: f64,
    ) -> (Vec<DVec3>, Vec<FreeRay>, Option<Plane>) {
        let near = |p: &DVec3| radial_distance(mean, *p).abs() < gate;
        match frame {
            Frame::Points(all) => {
                let kept: Vec<DVec3> = all.iter().copied().filter(near).collect();
                let stride = kept.len().div_ceil(self.opts.max_points).max(1);
                (kept.into_iter().step_by(stride).collect(), Vec::new(), None)
            }
            Frame::Depth(depth) => {
                let radius = mean.shape.semi_axes().length() + gate;
                let Some(window) = window(&depth.intrinsics, mean.translation, radius) else {
                    return (Vec::new(), Vec::new(), None);
                };
                // The floor's points lie within 0.4 % of the depth (a structured-light
                // sensor's noise and quantisation there), or within the band its own spread
                // measured in the last frame when that is wider.
                let least = FLOOR_TOLERANCE * mean.translation.z;
                let floor = if self.opts.support {
                    let claims = |p: DVec3| radial_distance(mean, p) < gate;
                    let tolerance = self.floor.map_or(least, |f| f.band(least));
                    let above = mean.translation;
                    find_plane(depth, claims, above, tolerance, self.floor, self.frame)
                } else {
                    None
                };
                // The object keeps every point above the floor's own noise band.
                let off_floor =
                    |p: &DVec3| floor.is_none_or(|f| f.height(*p) > f.band(0.5 * least));
                let area = (window.2 - window.0) * (window.3 - window.1);
                let stride =
                    ((area as f64 / self.opts.max_points as f64).sqrt().ceil() as usize).max(1);
                let pixels = depth.points_in(window, stride);
                let points: Vec<DVec3> = pixels
                    .iter()
                    .map(|(p, _)| *p)
                    .filter(|p| near(p) && off_floor(p))
                    .collect();
                let free = if self.opts.free_space {
                    let stride = ((area as f64 / self.opts.max_free_rays as f64).sqrt().ceil()
                        as usize)
                        .max(1);
                    let margin = 3.0 * (3.0 * self.sigma2).sqrt();
                    free_rays(depth, window, stride, mean, radius, margin, gate)
                } else {
                    Vec::new()
                };
                (points, free, floor)
            }
        }
    }
}

/// The pixel box [u0, u1) × [v0, v1) that a sphere of `radius` about the camera-frame `centre`
/// covers, clipped to the image; `None` when it misses the image or lies behind the camera.
fn window(c: &Intrinsics, centre: DVec3, radius: f64) -> Option<(usize, usize, usize, usize)> {
    let z = centre.z - radius;
    if !(centre.z > 0.0) || !radius.is_finite() {
        return None;
    }
    // The sphere's image lies within its bounding box seen at its nearest depth.
    let z = z.max(1e-3 * centre.z.max(1e-9));
    let (u, v) = (
        c.fx * centre.x / centre.z + c.cx,
        c.fy * centre.y / centre.z + c.cy,
    );
    let (hu, hv) = (c.fx * radius / z, c.fy * radius / z);
    let lu = (u - hu).floor().max(0.0);
    let lv = (v - hv).floor().max(0.0);
    let hu = (u + hu).ceil().min(c.width as f64);
    let hv = (v + hv).ceil().min(c.height as f64);
    (lu < hu && lv < hv).then_some((lu as usize, lv as usize, hu as usize, hv as usize))
}

/// The free-space rays of `depth` in `window` (every `stride` pixels): samples along each pixel's
/// ray through the sphere of `radius` about `mean`'s centre, up to `margin` in front of the
/// depth seen, kept when within `gate` of the predicted surface or inside it.
fn free_rays(
    depth: &DepthFrame,
    (u0, v0, u1, v1): (usize, usize, usize, usize),
    stride: usize,
    mean: &InitialPose,
    radius: f64,
    margin: f64,
    gate: f64,
) -> Vec<FreeRay> {
    let c = mean.translation;
    let mut rays = Vec::new();
    for v in (v0..v1).step_by(stride) {
        for u in (u0..u1).step_by(stride) {
            let seen = depth.at(u, v);
            if !(seen > 0.0) {
                continue;
            }
            let r = depth.intrinsics.ray(u as f64, v as f64);
            // |z·r − c|² = radius²: z² r·r − 2z r·c + c·c − radius² = 0.
            let (a, b, k) = (r.dot(r), r.dot(c), c.dot(c) - radius * radius);
            let disc = b * b - a * k;
            if !(disc > 0.0) {
                continue;
            }
            let (z0, z1) = ((b - disc.sqrt()) / a, (b + disc.sqrt()) / a);
            let end = z1.min(seen - margin);
            if !(end > z0) {
                continue;
            }
            let samples: Vec<DVec3> = (0..FREE_SAMPLES)
                .map(|k| r * (z0 + (end - z0) * (k as f64 + 0.5) / FREE_SAMPLES as f64))
                .filter(|s| radial_distance(mean, *s) < gate)
                .collect();
            if !samples.is_empty() {
                rays.push(FreeRay { samples });
            }
        }
    }
    rays
}
