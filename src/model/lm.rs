//! The global DOFs' rest state solved for directly (beyond the paper).
//!
//! A pure superquadric fit comes to rest where the range springs' generalized force on the
//! global DOFs vanishes. The explicit dynamics of [`super::fit`] reach that state in hundreds to
//! thousands of small steps; this module reaches it in tens of Levenberg–Marquardt iterations of
//! a closed-form residual, the way EMS (Liu et al., CVPR 2022) does:
//!
//! - the residual of a point is its **radial distance** to the superquadric, |x|·(1 − F(x)^(−ε1/2))
//!   with x the point in the model frame and F the inside–outside function
//!   ([`super::superquadric::inside_outside`]): O(1) a point, no correspondence search, and zero
//!   exactly on the surface;
//! - the eleven unknowns are the semi-axes a·a_i, the exponents ε1 and ε2, the translation, and a
//!   rotation increment about the current orientation; the Jacobian is analytic ([`radial`],
//!   tested against central differences) and the normal equations are 11 × 11;
//! - outliers are weighed by the posterior of a Gaussian–uniform mixture, refreshed between
//!   Levenberg–Marquardt rounds (an EM alternation, [`RadialFit`]).
//!
//! [`super::fit::fit`] uses it for pure superquadric fits when [`Solver::LevenbergMarquardt`] is
//! chosen; the paper's dynamics stay the default of [`super::fit::FitOptions`] and of the plugin.

use super::init::InitialPose;
use super::linalg::cholesky_solve;
use super::superquadric::{MAX_EPSILON, MIN_ASPECT, MIN_EPSILON, SuperquadricParams};
use glam::{DQuat, DVec3};

/// How a fit reaches the rest state of its global DOFs.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Solver {
    /// The paper's explicit Euler dynamics under range springs (every stage of
    /// [`super::fit::fit`]).
    #[default]
    Dynamics,
    /// For pure superquadric fits ([`super::fit::FitOptions::global_only`]) without tapering or
    /// bending: the Levenberg–Marquardt solve of this module. Other fits use the dynamics.
    LevenbergMarquardt,
}

/// Number of unknowns: semi-axes (3), ε1, ε2, translation (3), rotation increment (3).
pub const NUM_UNKNOWNS: usize = 11;

/// A point's radial distance and its gradient with respect to the [`NUM_UNKNOWNS`] unknowns, in
/// the order semi-axes, ε1, ε2, translation, rotation increment ω (the orientation R·exp(ω×),
/// about the model's own axes).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Radial {
    /// |x|·(1 − F(x)^(−ε1/2)): positive outside, negative inside.
    pub distance: f64,
    /// ∂distance/∂unknowns.
    pub gradient: [f64; NUM_UNKNOWNS],
}

/// The radial distance of `p` to the superquadric of `pose` (tapering and bending ignored).
pub fn radial_distance(pose: &InitialPose, p: DVec3) -> f64 {
    radial_in_model(
        pose,
        pose.rotation.inverse() * (p - pose.translation),
        false,
    )
    .distance
}

/// The radial distance of `p` and its gradient ([`Radial`]).
pub fn radial(pose: &InitialPose, p: DVec3) -> Radial {
    let x = pose.rotation.inverse() * (p - pose.translation);
    let mut r = radial_in_model(pose, x, true);
    // x = Rᵀ(p − t): ∂x/∂t = −Rᵀ, and with R·exp(ω×), x ≈ x + x × ω, so ∂d/∂ω = ∇ₓd × x.
    let g = DVec3::new(r.gradient[5], r.gradient[6], r.gradient[7]);
    let dt = -(pose.rotation * g);
    let dw = g.cross(x);
    r.gradient[5..8].copy_from_slice(&dt.to_array());
    r.gradient[8..11].copy_from_slice(&dw.to_array());
    r
}

/// The radial distance of a model-frame point `x`; with `grad`, the gradient over the semi-axes
/// and exponents in slots 0–4 and ∇ₓ in slots 5–7 (slots 8–10 zero).
fn radial_in_model(pose: &InitialPose, x: DVec3, grad: bool) -> Radial {
    let ax = pose.shape.semi_axes();
    let (e1, e2) = (pose.shape.e1, pose.shape.e2);
    let mut gradient = [0.0; NUM_UNKNOWNS];
    let r = x.length();
    if !(r > 0.0) {
        // The centre: no direction to measure along; it lies the least semi-axis inside.
        return Radial {
            distance: -ax.min_element(),
            gradient,
        };
    }
    let u = (x / ax).abs();
    let ln_u = DVec3::new(u.x.ln(), u.y.ln(), u.z.ln());
    let gx = if u.x > 0.0 {
        (2.0 / e2 * ln_u.x).exp()
    } else {
        0.0
    };
    let gy = if u.y > 0.0 {
        (2.0 / e2 * ln_u.y).exp()
    } else {
        0.0
    };
    let gz = if u.z > 0.0 {
        (2.0 / e1 * ln_u.z).exp()
    } else {
        0.0
    };
    let h = gx + gy;
    let ln_h = h.ln();
    let big_h = if h > 0.0 { (e2 / e1 * ln_h).exp() } else { 0.0 };
    let f = (big_h + gz).max(f64::MIN_POSITIVE);
    let ln_f = f.ln();
    let g = (-0.5 * e1 * ln_f).exp();
    let distance = r * (1.0 - g);
    if !grad {
        return Radial { distance, gradient };
    }
    // F's partial derivatives; H/h·g_x is written so that h = 0 gives 0.
    let hh = if h > 0.0 { big_h / h } else { 0.0 };
    let ratio = |g: f64, c: f64| if c != 0.0 { g / c } else { 0.0 };
    let f_x = DVec3::new(
        2.0 / e1 * hh * ratio(gx, x.x),
        2.0 / e1 * hh * ratio(gy, x.y),
        2.0 / e1 * ratio(gz, x.z),
    );
    let f_a = DVec3::new(
        -2.0 / e1 * hh * gx / ax.x,
        -2.0 / e1 * hh * gy / ax.y,
        -2.0 / e1 * gz / ax.z,
    );
    // g_x = u_x^(2/ε2), so ∂g_x/∂ε2 = −(2/ε2²)·g_x·ln u_x (0 where u_x = 0).
    let g_ln = |g: f64, ln_u: f64| if g > 0.0 { g * ln_u } else { 0.0 };
    let h_e2 = -2.0 / (e2 * e2) * (g_ln(gx, ln_u.x) + g_ln(gy, ln_u.y));
    let f_e2 = if h > 0.0 {
        big_h * (ln_h / e1 + e2 / e1 * h_e2 / h)
    } else {
        0.0
    };
    let f_e1 = if h > 0.0 {
        -big_h * ln_h * e2 / (e1 * e1)
    } else {
        0.0
    } - 2.0 / (e1 * e1) * g_ln(gz, ln_u.z);
    // d = r(1 − G), G = F^(−ε1/2): ∂G/∂θ = −G·ε1/2·F_θ/F, and ∂G/∂ε1 has −G·ln F/2 besides.
    let k = r * g * 0.5 * e1 / f;
    let d_a = f_a * k;
    gradient[0..3].copy_from_slice(&d_a.to_array());
    gradient[3] = k * f_e1 + r * g * 0.5 * ln_f;
    gradient[4] = k * f_e2;
    let d_x = x / r * (1.0 - g) + f_x * k;
    gradient[5..8].copy_from_slice(&d_x.to_array());
    Radial { distance, gradient }
}

/// `pose` moved by the unknowns' increment `delta` (in [`Radial`]'s order), its semi-axes held
/// at least [`MIN_ASPECT`] of the longest and its exponents in [[`MIN_EPSILON`], [`MAX_EPSILON`]].
pub fn apply_increment(pose: &InitialPose, delta: &[f64; NUM_UNKNOWNS]) -> InitialPose {
    let axes = pose.shape.semi_axes() + DVec3::new(delta[0], delta[1], delta[2]);
    let longest = axes.max_element().max(f64::MIN_POSITIVE);
    let axes = axes.max(DVec3::splat(longest * MIN_ASPECT));
    let shape = SuperquadricParams {
        a: 1.0,
        a1: axes.x,
        a2: axes.y,
        a3: axes.z,
        e1: (pose.shape.e1 + delta[3]).clamp(MIN_EPSILON, MAX_EPSILON),
        e2: (pose.shape.e2 + delta[4]).clamp(MIN_EPSILON, MAX_EPSILON),
    }
    .normalized();
    let w = DVec3::new(delta[8], delta[9], delta[10]);
    InitialPose {
        translation: pose.translation + DVec3::new(delta[5], delta[6], delta[7]),
        rotation: (pose.rotation * DQuat::from_scaled_axis(w)).normalize(),
        shape,
    }
}

/// Σ wᵢ dᵢ² over `points` with weights `weights` (1 each when empty).
pub fn radial_cost(pose: &InitialPose, points: &[DVec3], weights: &[f64]) -> f64 {
    points
        .iter()
        .enumerate()
        .map(|(i, p)| {
            let d = radial_distance(pose, *p);
            weights.get(i).copied().unwrap_or(1.0) * d * d
        })
        .sum()
}

/// Levenberg–Marquardt damping at the start of a solve, relative to the normal matrix' diagonal.
pub const INITIAL_DAMPING: f64 = 1e-3;

/// One Levenberg–Marquardt step on Σ wᵢ dᵢ² from `pose`, whose cost is `cost`, with damping
/// `lambda` (updated: lowered after a step that lowered the cost, raised while one did not).
/// Returns the new pose and cost, or `None` when no damping up to 10¹⁰ lowered the cost (at a
/// minimum to working precision).
pub fn lm_step(
    pose: &InitialPose,
    cost: f64,
    points: &[DVec3],
    weights: &[f64],
    lambda: &mut f64,
) -> Option<(InitialPose, f64)> {
    let mut jtj = [[0.0; NUM_UNKNOWNS]; NUM_UNKNOWNS];
    let mut jtr = [0.0; NUM_UNKNOWNS];
    for (i, p) in points.iter().enumerate() {
        let w = weights.get(i).copied().unwrap_or(1.0);
        if w <= 0.0 {
            continue;
        }
        let r = radial(pose, *p);
        if !r.distance.is_finite() || r.gradient.iter().any(|g| !g.is_finite()) {
            continue;
        }
        for a in 0..NUM_UNKNOWNS {
            let wg = w * r.gradient[a];
            jtr[a] += wg * r.distance;
            for b in 0..=a {
                jtj[a][b] += wg * r.gradient[b];
            }
        }
    }
    for a in 0..NUM_UNKNOWNS {
        for b in 0..a {
            jtj[b][a] = jtj[a][b];
        }
    }
    let scale = (0..NUM_UNKNOWNS).map(|a| jtj[a][a]).fold(0.0, f64::max);
    let neg: [f64; NUM_UNKNOWNS] = jtr.map(|g| -g);
    while *lambda < 1e10 {
        let mut damped = jtj;
        for (a, row) in damped.iter_mut().enumerate() {
            row[a] += *lambda * row[a] + 1e-12 * scale.max(f64::MIN_POSITIVE);
        }
        if let Some(delta) = cholesky_solve(&damped, &neg) {
            let next = apply_increment(pose, &delta);
            let next_cost = radial_cost(&next, points, weights);
            if next_cost < cost {
                *lambda = (*lambda / 3.0).max(1e-12);
                return Some((next, next_cost));
            }
        }
        *lambda *= 4.0;
    }
    None
}

/// The Gaussian–uniform mixture that weighs the points: inliers lie a Gaussian distance from the
/// surface, outliers anywhere in the data's bounding box with prior probability `outlier_ratio`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Mixture {
    /// Prior fraction of outliers w_o in [0, 1); 0 weighs every point 1.
    pub outlier_ratio: f64,
    /// The outliers' uniform density 1/V, V the volume of the data's bounding box.
    pub outlier_density: f64,
    /// Least σ² of the inliers' distance per coordinate.
    pub sigma2_floor: f64,
}

impl Mixture {
    /// The posterior inlier probability of a point `distance` from the surface when the inliers'
    /// variance per coordinate is `sigma2`.
    pub fn inlier(&self, distance: f64, sigma2: f64) -> f64 {
        if self.outlier_ratio <= 0.0 {
            return 1.0;
        }
        let gauss = (2.0 * std::f64::consts::PI * sigma2).powf(-1.5);
        let c = self.outlier_ratio * self.outlier_density / (gauss * (1.0 - self.outlier_ratio));
        let e = (-0.5 * distance * distance / sigma2).exp();
        let p = e / (c + e);
        if p.is_finite() { p } else { 0.0 }
    }
}

/// Settings of [`fit_radial`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RadialOptions {
    /// The outlier model.
    pub mixture: Mixture,
    /// Most EM rounds (each refreshes the weights and then takes Levenberg–Marquardt steps).
    pub max_rounds: u32,
    /// Most Levenberg–Marquardt steps a round.
    pub steps_per_round: u32,
    /// A round that lowers the cost by less than this fraction ends the fit.
    pub tolerance: f64,
}

/// Where [`fit_radial`] came to rest.
#[derive(Clone, Debug, PartialEq)]
pub struct RadialFit {
    /// The pose and shape.
    pub pose: InitialPose,
    /// Σ wᵢ dᵢ² at the end.
    pub cost: f64,
    /// The points' inlier weights wᵢ (empty without an outlier model).
    pub weights: Vec<f64>,
    /// The inliers' variance per coordinate σ².
    pub sigma2: f64,
    /// Levenberg–Marquardt steps taken.
    pub iterations: u32,
    /// True when a round's progress fell below the tolerance (not stopped by the round cap).
    pub converged: bool,
}

impl RadialFit {
    /// Mean |dᵢ| of the points nearest the surface: all of them without an outlier model, the
    /// nearest (1 − w_o) of them with one. Comparable between fits of the same points whatever
    /// their weights.
    pub fn score(&self, points: &[DVec3], mixture: &Mixture) -> f64 {
        trimmed_mean_distance(&self.pose, points, mixture.outlier_ratio)
    }
}

/// Mean |dᵢ| over the ⌈(1 − `outlier_ratio`)·n⌉ points nearest the surface of `pose`.
pub fn trimmed_mean_distance(pose: &InitialPose, points: &[DVec3], outlier_ratio: f64) -> f64 {
    let mut d: Vec<f64> = points
        .iter()
        .map(|p| radial_distance(pose, *p).abs())
        .collect();
    let keep = (((1.0 - outlier_ratio.clamp(0.0, 0.99)) * d.len() as f64).ceil() as usize)
        .clamp(1, d.len().max(1));
    if keep < d.len() {
        d.select_nth_unstable_by(keep - 1, f64::total_cmp);
    }
    let kept = &d[..keep.min(d.len())];
    kept.iter().sum::<f64>() / kept.len().max(1) as f64
}

/// EM rounds from `start`: each refreshes the inlier weights from the radial distances and σ²,
/// then takes up to [`RadialOptions::steps_per_round`] Levenberg–Marquardt steps and
/// re-estimates σ² from the weighted cost; rounds end when one lowers the cost by less than
/// [`RadialOptions::tolerance`] of it, or after [`RadialOptions::max_rounds`].
pub fn fit_radial(
    points: &[DVec3],
    start: &InitialPose,
    sigma2: f64,
    opts: &RadialOptions,
) -> RadialFit {
    let mixture = opts.mixture;
    let robust = mixture.outlier_ratio > 0.0;
    let mut fit = RadialFit {
        pose: *start,
        cost: f64::INFINITY,
        weights: Vec::new(),
        sigma2: sigma2.max(mixture.sigma2_floor),
        iterations: 0,
        converged: false,
    };
    let mut lambda = INITIAL_DAMPING;
    let mut previous = f64::INFINITY;
    for _ in 0..opts.max_rounds {
        let mut cost = if robust {
            // The weights and the cost they give, from one pass over the distances.
            let mut cost = 0.0;
            fit.weights = points
                .iter()
                .map(|p| {
                    let d = radial_distance(&fit.pose, *p);
                    let w = mixture.inlier(d, fit.sigma2);
                    cost += w * d * d;
                    w
                })
                .collect();
            cost
        } else {
            radial_cost(&fit.pose, points, &fit.weights)
        };
        for _ in 0..opts.steps_per_round {
            let Some((pose, c)) = lm_step(&fit.pose, cost, points, &fit.weights, &mut lambda)
            else {
                break;
            };
            fit.iterations += 1;
            let small = cost - c <= opts.tolerance * 0.1 * c;
            (fit.pose, cost) = (pose, c);
            if small {
                break;
            }
        }
        fit.cost = cost;
        let total: f64 = if robust {
            fit.weights.iter().sum()
        } else {
            points.len() as f64
        };
        if robust && total > 0.0 {
            fit.sigma2 = (cost / (3.0 * total)).max(mixture.sigma2_floor);
        }
        // At rest: progress below the tolerance, or the points on the surface to a tenth of the
        // σ floor (a clean cloud's cost falls towards rounding for ever).
        let at_floor = cost <= 0.01 * mixture.sigma2_floor * total;
        if previous - cost < opts.tolerance * cost || at_floor {
            fit.converged = true;
            break;
        }
        previous = cost;
    }
    fit
}

/// The outcome of [`solve`].
#[derive(Clone, Debug, PartialEq)]
pub struct Solution {
    /// The kept fit.
    pub fit: RadialFit,
    /// The start it came from.
    pub start: InitialPose,
    /// Levenberg–Marquardt steps over every start and candidate tried.
    pub iterations: u32,
}

/// [`fit_radial`] from each of `starts` side by side (threads of their own): the fit with the
/// least finite [`RadialFit::score`], its score and start, and the steps all of them took.
fn best_fit(
    points: &[DVec3],
    starts: &[InitialPose],
    sigma2: f64,
    opts: &RadialOptions,
) -> Option<(RadialFit, f64, InitialPose, u32)> {
    let run = |start: &InitialPose, _: &mut dyn FnMut(&super::fit::FitProgress)| {
        let fit = fit_radial(points, start, sigma2, opts);
        let score = fit.score(points, &opts.mixture);
        (fit, score)
    };
    let runs = super::fit::run_parallel(starts, run, &mut |_| {});
    let iterations = runs.iter().map(|(f, _)| f.iterations).sum();
    runs.into_iter()
        .zip(starts)
        .filter(|((_, s), _)| s.is_finite())
        .min_by(|((_, a), _), ((_, b), _)| a.total_cmp(b))
        .map(|((f, s), start)| (f, s, *start, iterations))
}

/// The most points the starts and the similarity candidates of [`solve`] are fitted to: a larger
/// cloud is subsampled for them, and only the kept fit is refined on every point.
pub const COARSE_POINTS: usize = 512;

/// Every `n / COARSE_POINTS`-th point of `points` (all of them when there are at most twice
/// [`COARSE_POINTS`]).
pub fn coarse_sample(points: &[DVec3]) -> Vec<DVec3> {
    if points.len() <= 2 * COARSE_POINTS {
        return points.to_vec();
    }
    let stride = points.len() as f64 / COARSE_POINTS as f64;
    (0..COARSE_POINTS)
        .map(|i| points[((i as f64 * stride) as usize).min(points.len() - 1)])
        .collect()
}

/// Fits from each of `starts` and keeps the one with the least [`RadialFit::score`]; then tries
/// the kept fit's similarity candidates (`candidates`, from its pose) from that fit's σ², and
/// moves to a candidate that scores less, until none does (at most `max_switches` moves). The
/// starts run side by side on threads of their own. Starts and candidates are fitted to
/// [`coarse_sample`]`(points)`; the kept fit then goes on over every point.
pub fn solve(
    all_points: &[DVec3],
    starts: &[InitialPose],
    sigma2: f64,
    opts: &RadialOptions,
    candidates: impl Fn(&InitialPose) -> Vec<InitialPose>,
    max_switches: u32,
) -> Option<Solution> {
    let sample = coarse_sample(all_points);
    let points = &sample[..];
    let (mut best, mut score, mut start, mut iterations) = best_fit(points, starts, sigma2, opts)?;
    for _ in 0..max_switches {
        let others = candidates(&best.pose);
        let Some((fit, s, other, spent)) = best_fit(points, &others, best.sigma2, opts) else {
            break;
        };
        iterations += spent;
        if s >= score {
            break;
        }
        (best, score, start) = (fit, s, other);
    }
    if points.len() < all_points.len() {
        best = fit_radial(all_points, &best.pose, best.sigma2, opts);
        iterations += best.iterations;
    }
    Some(Solution {
        fit: best,
        start,
        iterations,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::synthetic::superquadric_cloud;

    fn pose() -> InitialPose {
        InitialPose {
            translation: DVec3::new(0.2, -0.1, 0.3),
            rotation: DQuat::from_euler(glam::EulerRot::XYZ, 0.3, -0.5, 0.8),
            shape: SuperquadricParams {
                a: 1.2,
                a1: 0.7,
                a2: 1.0,
                a3: 0.5,
                e1: 0.6,
                e2: 1.4,
            },
        }
    }

    /// The distance as a function of the unknowns about `pose`.
    fn distance_at(pose: &InitialPose, p: DVec3, delta: &[f64; NUM_UNKNOWNS]) -> f64 {
        let mut moved = apply_increment(pose, delta);
        // apply_increment normalises; the same surface, so the distance is unchanged by that.
        moved.shape = moved.shape.normalized();
        radial_distance(&moved, p)
    }

    #[test]
    fn the_gradient_matches_central_differences() {
        let pose = pose();
        let h = 1e-6;
        let points = [
            DVec3::new(1.1, 0.4, -0.2),
            DVec3::new(-0.3, 0.9, 0.6),
            DVec3::new(0.25, -0.2, 0.35),
            DVec3::new(0.2, -0.1, 1.5),
            DVec3::new(-1.4, -0.8, 0.1),
        ];
        for p in points {
            let r = radial(&pose, p);
            for k in 0..NUM_UNKNOWNS {
                let mut plus = [0.0; NUM_UNKNOWNS];
                let mut minus = [0.0; NUM_UNKNOWNS];
                plus[k] = h;
                minus[k] = -h;
                let numeric =
                    (distance_at(&pose, p, &plus) - distance_at(&pose, p, &minus)) / (2.0 * h);
                assert!(
                    (numeric - r.gradient[k]).abs() <= 1e-6 * (1.0 + numeric.abs()),
                    "point {p}, unknown {k}: analytic {} numeric {numeric}",
                    r.gradient[k]
                );
            }
        }
    }

    #[test]
    fn the_distance_is_zero_on_the_surface_and_signed_off_it() {
        let pose = pose();
        for p in superquadric_cloud(&pose.shape, pose.translation, pose.rotation, 50, 0.0, 1) {
            assert!(radial_distance(&pose, p).abs() < 1e-9, "{p}");
            let out = pose.translation + (p - pose.translation) * 1.1;
            let inside = pose.translation + (p - pose.translation) * 0.9;
            assert!(radial_distance(&pose, out) > 0.0);
            assert!(radial_distance(&pose, inside) < 0.0);
        }
    }

    fn options(outlier_ratio: f64) -> RadialOptions {
        RadialOptions {
            mixture: Mixture {
                outlier_ratio,
                outlier_density: 1.0 / 27.0,
                sigma2_floor: 1e-10,
            },
            max_rounds: 30,
            steps_per_round: 10,
            tolerance: 1e-6,
        }
    }

    #[test]
    fn steps_lower_the_cost_and_stay_finite_until_the_fit_recovers_the_shape() {
        let truth = pose();
        let points =
            superquadric_cloud(&truth.shape, truth.translation, truth.rotation, 400, 0.0, 7);
        let mut start = truth;
        start.translation += DVec3::new(0.1, 0.05, -0.08);
        start.rotation = (start.rotation * DQuat::from_rotation_z(0.15)).normalize();
        start.shape.a *= 1.15;
        start.shape.e1 = 1.0;
        start.shape.e2 = 1.0;
        let mut cost = radial_cost(&start, &points, &[]);
        let mut pose = start;
        let mut lambda = INITIAL_DAMPING;
        for _ in 0..60 {
            let Some((next, c)) = lm_step(&pose, cost, &points, &[], &mut lambda) else {
                break;
            };
            assert!(c < cost && c.is_finite(), "{c} after {cost}");
            assert!(next.translation.is_finite() && next.shape.is_finite());
            (pose, cost) = (next, c);
        }
        assert!(cost < 1e-12, "cost {cost}");
        let axes = pose.shape.semi_axes();
        assert!(
            (axes - truth.shape.semi_axes()).abs().max_element() < 1e-5,
            "{axes}"
        );
        assert!((pose.shape.e1 - 0.6).abs() < 1e-5 && (pose.shape.e2 - 1.4).abs() < 1e-5);
    }

    #[test]
    fn outliers_get_low_weights_and_do_not_move_the_fit() {
        let truth = pose();
        let mut points =
            superquadric_cloud(&truth.shape, truth.translation, truth.rotation, 300, 0.0, 3);
        let n = points.len();
        // A fifth more points scattered through the box.
        for i in 0..n / 4 {
            let t = i as f64;
            points.push(DVec3::new(
                (t * 0.37).sin() * 1.5,
                (t * 0.71).cos() * 1.5,
                (t * 1.13).sin() * 1.5,
            ));
        }
        let mut start = truth;
        start.shape.a *= 1.1;
        let fit = fit_radial(&points, &start, 0.05, &options(0.2));
        assert!(fit.cost.is_finite());
        let inliers: f64 = fit.weights[..n].iter().sum::<f64>() / n as f64;
        assert!(
            inliers > 0.95,
            "mean inlier weight of the surface points {inliers}"
        );
        let axes = fit.pose.shape.semi_axes();
        assert!(
            (axes - truth.shape.semi_axes()).abs().max_element() < 1e-3,
            "{axes}"
        );
    }

    #[test]
    fn the_solve_keeps_the_start_that_fits() {
        let truth = pose();
        let points =
            superquadric_cloud(&truth.shape, truth.translation, truth.rotation, 300, 0.0, 5);
        let mut far = truth;
        far.translation += DVec3::new(2.0, 0.0, 0.0);
        far.shape.a *= 0.3;
        let starts = [far, truth];
        let s = solve(&points, &starts, 0.05, &options(0.0), |_| Vec::new(), 2).unwrap();
        assert_eq!(s.start, truth);
        assert!(s.fit.score(&points, &options(0.0).mixture) < 1e-6);
    }
}
