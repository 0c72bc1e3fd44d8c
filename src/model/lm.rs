//! The global DOFs' rest state solved for directly (beyond the paper).
//!
//! A pure superquadric fit comes to rest where the range springs' generalized force on the
//! global DOFs vanishes. The explicit dynamics of [`super::fit`] reach that state in hundreds to
//! thousands of small steps; this module reaches it in tens of Levenberg–Marquardt iterations,
//! the way EMS (Liu et al., CVPR 2022) does, then goes on where EMS stops:
//!
//! - the eleven unknowns are the semi-axes a·a_i, the exponents ε1 and ε2, the translation, and a
//!   rotation increment about the current orientation; the Jacobians of every distance are
//!   analytic (tested against central differences), the normal equations are 11 × 11, and an
//!   unknown on its bound is held there while the step would push it past ([`lm_step`]);
//! - outliers are weighed by the posterior of a Gaussian–uniform mixture, refreshed between
//!   Levenberg–Marquardt rounds (an EM alternation, [`fit_em`]);
//! - the distance is the radial one, its projection on the normal, or the exact distance to the
//!   closest surface point ([`Metric`]); the last keeps each point's foot between evaluations,
//!   so that its search starts where it ended ([`super::distance::closest_point_from`]);
//! - the coverage term ([`Coverage`]) can be added, to place a model over the whole cloud;
//! - [`solve`] ([`mod@search`]) runs the whole search: starts, placing, similarity switches and the
//!   polish on every point.
//!
//! [`super::fit::fit`] uses it by default ([`Solver::Solved`]); the paper's dynamics stay
//! available as [`Solver::Dynamics`], and the plugin's per-frame simulation is the dynamics.

pub use super::distance::{Distance, Metric, NUM_UNKNOWNS, radial, radial_distance};
use super::init::InitialPose;
use super::linalg::cholesky_solve;
use super::superquadric::{LEAST_EPSILON, MAX_EPSILON, MIN_ASPECT, SuperquadricParams};
use glam::{DQuat, DVec3};

mod coverage;
mod deformed;
pub mod search;
pub use coverage::{COVERAGE_K, Coverage};
pub use deformed::{
    DeformedFit, DeformedPose, NUM_DEFORMED, SEED_RAYS, deformed_distances, fit_deformed,
};
pub use search::*;
#[cfg(test)]
mod tests;

/// How a fit reaches the rest state of its global DOFs.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub enum Solver {
    /// Solved for: the superquadric by Levenberg–Marquardt ([`solve`]); with local DOFs, then
    /// the membrane by linear solves for fixed attachments
    /// ([`super::fit::implicit_joint_options`]).
    #[default]
    Solved,
    /// The paper's explicit Euler dynamics under range springs (every stage of
    /// [`super::fit::fit`]).
    Dynamics,
}

/// `pose` moved by the unknowns' increment `delta` (in [`Distance`]'s order), its semi-axes held
/// at least [`MIN_ASPECT`] of the longest and its exponents in [[`LEAST_EPSILON`],
/// [`MAX_EPSILON`]].
pub fn apply_increment(pose: &InitialPose, delta: &[f64; NUM_UNKNOWNS]) -> InitialPose {
    bounded_increment(pose, delta, f64::INFINITY, LEAST_EPSILON)
}

/// [`apply_increment`] with every semi-axis also held at most `max_semi_axis` and the exponents
/// at least `min_epsilon`.
pub fn bounded_increment(
    pose: &InitialPose,
    delta: &[f64; NUM_UNKNOWNS],
    max_semi_axis: f64,
    min_epsilon: f64,
) -> InitialPose {
    let axes = (pose.shape.semi_axes() + DVec3::new(delta[0], delta[1], delta[2]))
        .min(DVec3::splat(max_semi_axis));
    let longest = axes.max_element().max(f64::MIN_POSITIVE);
    let axes = axes.max(DVec3::splat(longest * MIN_ASPECT));
    let shape = SuperquadricParams {
        // The semi-axes normalised into a and a_i; the exponents held in their own bounds
        // (`normalized` would hold them at the dynamics' least, above `min_epsilon`).
        e1: (pose.shape.e1 + delta[3]).clamp(min_epsilon, MAX_EPSILON),
        e2: (pose.shape.e2 + delta[4]).clamp(min_epsilon, MAX_EPSILON),
        ..SuperquadricParams {
            a: 1.0,
            a1: axes.x,
            a2: axes.y,
            a3: axes.z,
            e1: 1.0,
            e2: 1.0,
        }
        .normalized()
    };
    let w = DVec3::new(delta[8], delta[9], delta[10]);
    InitialPose {
        translation: pose.translation + DVec3::new(delta[5], delta[6], delta[7]),
        rotation: (pose.rotation * DQuat::from_scaled_axis(w)).normalize(),
        shape,
    }
}

/// Clouds at least this large have their Levenberg–Marquardt sums taken over every core.
pub const PARALLEL_POINTS: usize = 2048;

/// The points a parallel sum takes as one term: fixed, so that the partial sums, and so the
/// total, come out bit for bit the same whatever the scheduling.
const SUM_CHUNK: usize = 1024;

/// Σ over the indices of `n` points: `add` accumulates point i into a partial sum started by
/// `zero`, and `merge` adds one partial sum into another. Over every core when there are at
/// least [`PARALLEL_POINTS`], in fixed chunks merged in order (deterministic).
fn sum_points<T: Send>(
    n: usize,
    zero: impl Fn() -> T + Sync,
    add: impl Fn(&mut T, usize) + Sync,
    merge: impl Fn(&mut T, &T),
) -> T {
    use rayon::prelude::*;
    let range = |range: std::ops::Range<usize>| {
        let mut acc = zero();
        for i in range {
            add(&mut acc, i);
        }
        acc
    };
    if n >= PARALLEL_POINTS {
        let chunk = |c: usize| range(c * SUM_CHUNK..((c + 1) * SUM_CHUNK).min(n));
        let parts: Vec<T> = (0..n.div_ceil(SUM_CHUNK))
            .into_par_iter()
            .map(chunk)
            .collect();
        let mut total = zero();
        for part in &parts {
            merge(&mut total, part);
        }
        total
    } else {
        range(0..n)
    }
}

/// Σ wᵢ dᵢ² over `points` with weights `weights` (1 each when empty), d the `metric`'s distance.
pub fn weighted_cost(metric: Metric, pose: &InitialPose, points: &[DVec3], weights: &[f64]) -> f64 {
    let mut feet = Vec::new();
    cost_from(metric, pose, points, weights, &[], &mut feet)
}

/// [`weighted_cost`] with each point's surface search warm-started from `hints` (its foot at a
/// nearby pose; empty: none), writing each point's foot direction into `feet` (left empty for
/// the radial distance, which has none).
fn cost_from(
    metric: Metric,
    pose: &InitialPose,
    points: &[DVec3],
    weights: &[f64],
    hints: &[DVec3],
    feet: &mut Vec<DVec3>,
) -> f64 {
    feet.clear();
    if metric != Metric::Surface {
        let add = |c: &mut f64, i: usize| {
            let d = metric.distance(pose, points[i]);
            *c += weights.get(i).copied().unwrap_or(1.0) * d * d;
        };
        return sum_points(points.len(), || 0.0, add, |a, b| *a += b);
    }
    feet.resize(points.len(), DVec3::ZERO);
    // Each chunk writes its own feet: the same fixed chunks as `sum_points`.
    let chunk = |(c, out): (usize, &mut [DVec3])| {
        let first = c * SUM_CHUNK;
        let mut sum = 0.0;
        for (j, foot) in out.iter_mut().enumerate() {
            let i = first + j;
            let (d, f) = metric.distance_from(pose, points[i], hints.get(i).copied());
            *foot = f;
            sum += weights.get(i).copied().unwrap_or(1.0) * d * d;
        }
        sum
    };
    if points.len() >= PARALLEL_POINTS {
        use rayon::prelude::*;
        let parts: Vec<f64> = feet
            .par_chunks_mut(SUM_CHUNK)
            .enumerate()
            .map(chunk)
            .collect();
        parts.into_iter().sum()
    } else {
        chunk((0, &mut feet[..]))
    }
}

/// The `metric`'s signed distance of each of `points` from `pose`, the surface searches
/// warm-started from `feet` and `feet` moved to the new feet (over every core for large clouds).
fn signed_distances(
    metric: Metric,
    pose: &InitialPose,
    points: &[DVec3],
    feet: &mut Vec<DVec3>,
) -> Vec<f64> {
    use rayon::prelude::*;
    let hints = std::mem::take(feet);
    let one = |(i, p): (usize, &DVec3)| metric.distance_from(pose, *p, hints.get(i).copied());
    let pairs: Vec<(f64, DVec3)> = if points.len() >= PARALLEL_POINTS {
        points.par_iter().enumerate().map(one).collect()
    } else {
        points.iter().enumerate().map(one).collect()
    };
    if metric == Metric::Surface {
        *feet = pairs.iter().map(|(_, f)| *f).collect();
    }
    pairs.into_iter().map(|(d, _)| d).collect()
}

/// The normal equations' JᵀWJ (lower triangle) and JᵀWr.
type Normal = ([[f64; NUM_UNKNOWNS]; NUM_UNKNOWNS], [f64; NUM_UNKNOWNS]);

/// JᵀWJ and JᵀWr of the `metric`'s distances of `points` from `pose`, the surface searches
/// warm-started from `hints`.
fn normal_equations(
    metric: Metric,
    pose: &InitialPose,
    points: &[DVec3],
    weights: &[f64],
    hints: &[DVec3],
) -> Normal {
    let zero = || ([[0.0; NUM_UNKNOWNS]; NUM_UNKNOWNS], [0.0; NUM_UNKNOWNS]);
    let add = |n: &mut Normal, i: usize| {
        let w = weights.get(i).copied().unwrap_or(1.0);
        if w <= 0.0 {
            return;
        }
        let r = metric.with_gradient_from(pose, points[i], hints.get(i).copied());
        if !r.distance.is_finite() || r.gradient.iter().any(|g| !g.is_finite()) {
            return;
        }
        for a in 0..NUM_UNKNOWNS {
            let wg = w * r.gradient[a];
            n.1[a] += wg * r.distance;
            for b in 0..=a {
                n.0[a][b] += wg * r.gradient[b];
            }
        }
    };
    let merge = |x: &mut Normal, y: &Normal| {
        for a in 0..NUM_UNKNOWNS {
            x.1[a] += y.1[a];
            for b in 0..NUM_UNKNOWNS {
                x.0[a][b] += y.0[a][b];
            }
        }
    };
    sum_points(points.len(), zero, add, merge)
}

/// Levenberg–Marquardt damping at the start of a solve, relative to the normal matrix' diagonal.
pub const INITIAL_DAMPING: f64 = 1e-3;

/// One Levenberg–Marquardt step on Σ wᵢ dᵢ² (plus the `coverage` term, when given) from `pose`,
/// whose cost is `cost`, with damping `lambda` (lowered after a step that lowered the cost,
/// raised while one did not), within the bounds of `opts` and with its exponents held when it
/// says so. Returns the new pose and cost, or `None` at a minimum to the precision that
/// matters: when the step's predicted decrease falls below a tenth of the tolerance times the
/// cost (a step the round would count as no progress), or no damping up to 10¹⁰ lowered it.
/// `feet` are the points' surface feet at `pose` (empty: none yet; the surface distance's warm
/// starts), moved to the new pose's when the step is taken; `trial_feet` is scratch.
pub fn lm_step(
    pose: &InitialPose,
    cost: f64,
    (points, weights): (&[DVec3], &[f64]),
    lambda: &mut f64,
    opts: &LmOptions,
    (feet, trial_feet): (&mut Vec<DVec3>, &mut Vec<DVec3>),
    coverage: Option<&Coverage>,
) -> Option<(InitialPose, f64)> {
    let metric = opts.metric;
    let mut normal = normal_equations(metric, pose, points, weights, feet);
    let total = if weights.is_empty() {
        points.len() as f64
    } else {
        weights.iter().sum()
    };
    if let Some(c) = coverage {
        c.add_normal(pose, weights, total, &mut normal);
    }
    let (mut jtj, mut jtr) = normal;
    if opts.hold_exponents {
        for k in [3, 4] {
            for row in jtj.iter_mut() {
                row[k] = 0.0;
            }
            jtj[k] = [0.0; NUM_UNKNOWNS];
            jtj[k][k] = 1.0;
            jtr[k] = 0.0;
        }
    }
    for a in 0..NUM_UNKNOWNS {
        for b in 0..a {
            jtj[b][a] = jtj[a][b];
        }
    }
    let scale = (0..NUM_UNKNOWNS).map(|a| jtj[a][a]).fold(0.0, f64::max);
    let neg: [f64; NUM_UNKNOWNS] = jtr.map(|g| -g);
    let floor = 0.1 * opts.tolerance;
    while *lambda < 1e10 {
        let mut damped = jtj;
        for (a, row) in damped.iter_mut().enumerate() {
            row[a] += *lambda * row[a] + 1e-12 * scale.max(f64::MIN_POSITIVE);
        }
        if let Some(delta) = bounded_solve(pose, damped, neg, opts) {
            // The decrease the linear model predicts, 2δ·(−Jᵀr) − δᵀJᵀJδ.
            let quadratic: f64 = (0..NUM_UNKNOWNS)
                .map(|a| delta[a] * (0..NUM_UNKNOWNS).map(|b| jtj[a][b] * delta[b]).sum::<f64>())
                .sum();
            let predicted =
                2.0 * (0..NUM_UNKNOWNS).map(|a| delta[a] * neg[a]).sum::<f64>() - quadratic;
            if !(predicted > floor * cost) {
                return None;
            }
            let next = bounded_increment(pose, &delta, opts.max_semi_axis, opts.min_epsilon);
            let next_cost = cost_from(metric, &next, points, weights, feet, trial_feet)
                + coverage.map_or(0.0, |c| c.cost(&next, weights, total));
            if next_cost < cost {
                *lambda = (*lambda / 3.0).max(1e-12);
                std::mem::swap(feet, trial_feet);
                return Some((next, next_cost));
            }
        }
        *lambda *= 4.0;
    }
    None
}

/// The step `m·δ = rhs`, with the exponents that sit on a bound of [`LmOptions::min_epsilon`]
/// and [`MAX_EPSILON`], and the semi-axes that sit on [`LmOptions::max_semi_axis`], held where
/// they are when the step would push them past it (an active set): clamping such a step
/// afterwards would bend it off the descent direction and leave the other unknowns creeping.
fn bounded_solve(
    pose: &InitialPose,
    mut m: [[f64; NUM_UNKNOWNS]; NUM_UNKNOWNS],
    mut rhs: [f64; NUM_UNKNOWNS],
    opts: &LmOptions,
) -> Option<[f64; NUM_UNKNOWNS]> {
    let axes = pose.shape.semi_axes();
    let (top, low) = (opts.max_semi_axis, opts.min_epsilon);
    let q = &pose.shape;
    // (unknown, at its lower bound, at its upper bound)
    let bounded = [
        (0, false, axes.x >= top),
        (1, false, axes.y >= top),
        (2, false, axes.z >= top),
        (3, q.e1 <= low, q.e1 >= MAX_EPSILON),
        (4, q.e2 <= low, q.e2 >= MAX_EPSILON),
    ];
    // Each pass holds at least one more unknown (its δ is then exactly 0), so this ends.
    loop {
        let delta = cholesky_solve(&m, &rhs)?;
        let mut held = false;
        for (k, low, high) in bounded {
            if (low && delta[k] < 0.0) || (high && delta[k] > 0.0) {
                for row in m.iter_mut() {
                    row[k] = 0.0;
                }
                m[k] = [0.0; NUM_UNKNOWNS];
                m[k][k] = 1.0;
                rhs[k] = 0.0;
                held = true;
            }
        }
        if !held {
            return Some(delta);
        }
    }
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

    /// How well points at signed `distances` from a surface fit it under this mixture: the
    /// negative log-likelihood per point, at the inliers' variance σ² that maximises it (EM on σ²
    /// alone, from every point an inlier). Less is better; comparable between surfaces, where a
    /// plain mean distance would let a surface that passes through the outliers win.
    pub fn score(&self, distances: &[f64]) -> f64 {
        let n = distances.len().max(1) as f64;
        let floor = self.sigma2_floor.max(f64::MIN_POSITIVE);
        let mut sigma2 = (distances.iter().map(|d| d * d).sum::<f64>() / (3.0 * n)).max(floor);
        if self.outlier_ratio > 0.0 {
            for _ in 0..SCORE_EM_ROUNDS {
                let (mut wd, mut w) = (0.0, 0.0);
                for &d in distances {
                    let p = self.inlier(d, sigma2);
                    wd += p * d * d;
                    w += p;
                }
                let next = if w > 0.0 {
                    (wd / (3.0 * w)).max(floor)
                } else {
                    floor
                };
                let done = (next - sigma2).abs() <= 1e-6 * sigma2;
                sigma2 = next;
                if done {
                    break;
                }
            }
        }
        let (w, density) = (self.outlier_ratio, self.outlier_density);
        let norm = (2.0 * std::f64::consts::PI * sigma2).powf(-1.5);
        let nll: f64 = distances
            .iter()
            .map(|&d| {
                let gauss = (1.0 - w) * norm * (-0.5 * d * d / sigma2).exp();
                -(gauss + w * density).max(f64::MIN_POSITIVE).ln()
            })
            .sum();
        nll / n
    }
}

/// Most EM rounds [`Mixture::score`] takes to find its σ².
const SCORE_EM_ROUNDS: u32 = 50;

/// Settings of [`fit_em`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LmOptions {
    /// The outlier model.
    pub mixture: Mixture,
    /// Most EM rounds (each refreshes the weights and then takes Levenberg–Marquardt steps).
    pub max_rounds: u32,
    /// Most Levenberg–Marquardt steps a round.
    pub steps_per_round: u32,
    /// A round that lowers the cost by less than this fraction ends the fit.
    pub tolerance: f64,
    /// The distance the fit minimises.
    pub metric: Metric,
    /// The longest a semi-axis may grow (`f64::INFINITY`: no bound). The distances measure the
    /// points' way to the surface only, so on a one-view scan a superquadric can stretch far
    /// beyond the data on the side no point sees at almost no cost; such a model fits the points
    /// no better, and leaves a fit with local DOFs few nodes where the data is.
    pub max_semi_axis: f64,
    /// The least ε1 and ε2 (at most [`MAX_EPSILON`]).
    pub min_epsilon: f64,
    /// Hold ε1 and ε2 where they are (fit the pose and the semi-axes alone).
    pub hold_exponents: bool,
}

/// Where [`fit_em`] came to rest.
#[derive(Clone, Debug, PartialEq)]
pub struct LmFit {
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

/// EM rounds from `start`: each refreshes the inlier weights from the distances of
/// [`LmOptions::metric`] and σ², then takes up to [`LmOptions::steps_per_round`]
/// Levenberg–Marquardt steps and re-estimates σ² from the weighted cost; rounds end when one
/// lowers the cost by less than [`LmOptions::tolerance`] of it, or after
/// [`LmOptions::max_rounds`].
pub fn fit_em(points: &[DVec3], start: &InitialPose, sigma2: f64, opts: &LmOptions) -> LmFit {
    fit_em_with(points, start, sigma2, opts, None)
}

/// [`fit_em`] with the [`Coverage`] term added to the cost, when given (its σ² stays the points'
/// own: the weighted points' cost over 3 Σw).
pub fn fit_em_with(
    points: &[DVec3],
    start: &InitialPose,
    sigma2: f64,
    opts: &LmOptions,
    coverage: Option<&Coverage>,
) -> LmFit {
    let mixture = opts.mixture;
    let robust = mixture.outlier_ratio > 0.0;
    let mut fit = LmFit {
        pose: *start,
        cost: f64::INFINITY,
        weights: Vec::new(),
        sigma2: sigma2.max(mixture.sigma2_floor),
        iterations: 0,
        converged: false,
    };
    let mut lambda = INITIAL_DAMPING;
    let mut previous = f64::INFINITY;
    // The surface distance's feet at the current pose, and scratch for a trial pose's.
    let (mut feet, mut trial_feet) = (Vec::new(), Vec::new());
    for _ in 0..opts.max_rounds {
        let mut cost: f64 = if robust {
            // The weights and the cost they give, from one pass over the distances.
            let d = signed_distances(opts.metric, &fit.pose, points, &mut feet);
            fit.weights = d.iter().map(|&d| mixture.inlier(d, fit.sigma2)).collect();
            fit.weights.iter().zip(&d).map(|(w, d)| w * d * d).sum()
        } else {
            cost_from(opts.metric, &fit.pose, points, &fit.weights, &[], &mut feet)
        };
        let total: f64 = if robust {
            fit.weights.iter().sum()
        } else {
            points.len() as f64
        };
        let covered = |pose: &InitialPose, weights: &[f64]| {
            coverage.map_or(0.0, |c| c.cost(pose, weights, total))
        };
        cost += covered(&fit.pose, &fit.weights);
        for _ in 0..opts.steps_per_round {
            let Some((pose, c)) = lm_step(
                &fit.pose,
                cost,
                (points, &fit.weights),
                &mut lambda,
                opts,
                (&mut feet, &mut trial_feet),
                coverage,
            ) else {
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
        if robust && total > 0.0 {
            let own = cost - covered(&fit.pose, &fit.weights);
            fit.sigma2 = (own / (3.0 * total)).max(mixture.sigma2_floor);
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
