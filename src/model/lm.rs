//! The global DOFs' rest state solved for directly (beyond the paper).
//!
//! A pure superquadric fit comes to rest where the range springs' generalized force on the
//! global DOFs vanishes. The explicit dynamics of [`super::fit`] reach that state in hundreds to
//! thousands of small steps; this module reaches it in tens of Levenberg–Marquardt iterations,
//! the way EMS (Liu et al., CVPR 2022) does, then goes on where EMS stops:
//!
//! - the starts and similarity candidates are fitted to a subsample with the **radial distance**
//!   |x|·(1 − 1/G(x)) ([`super::distance::radial`]): one closed-form gauge a point, no
//!   correspondence search, zero exactly on the surface;
//! - the kept fit is then **polished with the surface distance**, each point's distance to its
//!   closest surface point ([`super::distance::surface`]), first on the subsample and then on
//!   every point: the radial distance overweighs points off the ends of long axes, and on some
//!   scans left the fit 18 % farther from the data than the dynamics;
//! - the eleven unknowns are the semi-axes a·a_i, the exponents ε1 and ε2, the translation, and a
//!   rotation increment about the current orientation; both Jacobians are analytic (tested
//!   against central differences), the normal equations are 11 × 11, and an exponent on its bound
//!   is held there while the step would push it past ([`lm_step`]);
//! - outliers are weighed by the posterior of a Gaussian–uniform mixture, refreshed between
//!   Levenberg–Marquardt rounds (an EM alternation, [`LmFit`]).
//!
//! [`super::fit::fit`] uses it when [`Solver::LevenbergMarquardt`] is chosen (for a fit with
//! local DOFs, to place the superquadric); the paper's dynamics stay the default of
//! [`super::fit::FitOptions`] and of the plugin.

pub use super::distance::{Distance, Metric, NUM_UNKNOWNS, radial, radial_distance};
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
    /// For fits without tapering or bending: the superquadric solved for by this module; with
    /// local DOFs, then the membrane brought to rest by implicit steps
    /// ([`super::fit::implicit_joint_options`]).
    LevenbergMarquardt,
}

/// `pose` moved by the unknowns' increment `delta` (in [`Distance`]'s order), its semi-axes held
/// at least [`MIN_ASPECT`] of the longest and its exponents in [[`MIN_EPSILON`], [`MAX_EPSILON`]].
pub fn apply_increment(pose: &InitialPose, delta: &[f64; NUM_UNKNOWNS]) -> InitialPose {
    bounded_increment(pose, delta, f64::INFINITY)
}

/// [`apply_increment`] with every semi-axis also held at most `max_semi_axis`.
pub fn bounded_increment(
    pose: &InitialPose,
    delta: &[f64; NUM_UNKNOWNS],
    max_semi_axis: f64,
) -> InitialPose {
    let axes = (pose.shape.semi_axes() + DVec3::new(delta[0], delta[1], delta[2]))
        .min(DVec3::splat(max_semi_axis));
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

/// Clouds at least this large have their Levenberg–Marquardt sums taken over every core.
pub const PARALLEL_POINTS: usize = 2048;

/// Σ wᵢ dᵢ² over `points` with weights `weights` (1 each when empty), d the `metric`'s distance.
pub fn weighted_cost(metric: Metric, pose: &InitialPose, points: &[DVec3], weights: &[f64]) -> f64 {
    use rayon::prelude::*;
    let term = |(i, p): (usize, &DVec3)| {
        let d = metric.distance(pose, *p);
        weights.get(i).copied().unwrap_or(1.0) * d * d
    };
    if points.len() >= PARALLEL_POINTS {
        points.par_iter().enumerate().map(term).sum()
    } else {
        points.iter().enumerate().map(term).sum()
    }
}

/// The normal equations' JᵀWJ (lower triangle) and JᵀWr.
type Normal = ([[f64; NUM_UNKNOWNS]; NUM_UNKNOWNS], [f64; NUM_UNKNOWNS]);

/// JᵀWJ and JᵀWr of the `metric`'s distances of `points` from `pose`.
fn normal_equations(
    metric: Metric,
    pose: &InitialPose,
    points: &[DVec3],
    weights: &[f64],
) -> Normal {
    use rayon::prelude::*;
    let zero = || ([[0.0; NUM_UNKNOWNS]; NUM_UNKNOWNS], [0.0; NUM_UNKNOWNS]);
    let add = |mut n: Normal, (i, p): (usize, &DVec3)| {
        let w = weights.get(i).copied().unwrap_or(1.0);
        if w <= 0.0 {
            return n;
        }
        let r = metric.with_gradient(pose, *p);
        if !r.distance.is_finite() || r.gradient.iter().any(|g| !g.is_finite()) {
            return n;
        }
        for a in 0..NUM_UNKNOWNS {
            let wg = w * r.gradient[a];
            n.1[a] += wg * r.distance;
            for b in 0..=a {
                n.0[a][b] += wg * r.gradient[b];
            }
        }
        n
    };
    let sum = |mut x: Normal, y: Normal| {
        for a in 0..NUM_UNKNOWNS {
            x.1[a] += y.1[a];
            for b in 0..NUM_UNKNOWNS {
                x.0[a][b] += y.0[a][b];
            }
        }
        x
    };
    if points.len() >= PARALLEL_POINTS {
        points
            .par_iter()
            .enumerate()
            .fold(zero, add)
            .reduce(zero, sum)
    } else {
        points.iter().enumerate().fold(zero(), add)
    }
}

/// Levenberg–Marquardt damping at the start of a solve, relative to the normal matrix' diagonal.
pub const INITIAL_DAMPING: f64 = 1e-3;

/// One Levenberg–Marquardt step on Σ wᵢ dᵢ² from `pose`, whose cost is `cost`, with damping
/// `lambda` (updated: lowered after a step that lowered the cost, raised while one did not) and
/// the semi-axes held at most `max_semi_axis`.
/// Returns the new pose and cost, or `None` at a minimum to working precision: when the step's
/// predicted decrease falls below `floor` times the cost, or no damping up to 10¹⁰ lowered it.
pub fn lm_step(
    metric: Metric,
    pose: &InitialPose,
    cost: f64,
    points: &[DVec3],
    weights: &[f64],
    lambda: &mut f64,
    floor: f64,
    max_semi_axis: f64,
) -> Option<(InitialPose, f64)> {
    let (mut jtj, jtr) = normal_equations(metric, pose, points, weights);
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
        if let Some(delta) = bounded_solve(pose, damped, neg, max_semi_axis) {
            // The decrease the linear model predicts, 2δ·(−Jᵀr) − δᵀJᵀJδ: below the floor the
            // cost's own rounding (or, for the surface distance, its search's) hides it.
            let quadratic: f64 = (0..NUM_UNKNOWNS)
                .map(|a| delta[a] * (0..NUM_UNKNOWNS).map(|b| jtj[a][b] * delta[b]).sum::<f64>())
                .sum();
            let predicted =
                2.0 * (0..NUM_UNKNOWNS).map(|a| delta[a] * neg[a]).sum::<f64>() - quadratic;
            if !(predicted > floor * cost) {
                return None;
            }
            let next = bounded_increment(pose, &delta, max_semi_axis);
            let next_cost = weighted_cost(metric, &next, points, weights);
            if next_cost < cost {
                *lambda = (*lambda / 3.0).max(1e-12);
                return Some((next, next_cost));
            }
        }
        *lambda *= 4.0;
    }
    None
}

/// The step `m·δ = rhs`, with the exponents that sit on a bound of [[`MIN_EPSILON`],
/// [`MAX_EPSILON`]], and the semi-axes that sit on `max_semi_axis`, held where they are when the
/// step would push them past it (an active set): clamping such a step afterwards would bend it
/// off the descent direction and leave the other unknowns creeping.
fn bounded_solve(
    pose: &InitialPose,
    mut m: [[f64; NUM_UNKNOWNS]; NUM_UNKNOWNS],
    mut rhs: [f64; NUM_UNKNOWNS],
    max_semi_axis: f64,
) -> Option<[f64; NUM_UNKNOWNS]> {
    let axes = pose.shape.semi_axes();
    // (unknown, at its lower bound, at its upper bound)
    let bounded = [
        (0, false, axes.x >= max_semi_axis),
        (1, false, axes.y >= max_semi_axis),
        (2, false, axes.z >= max_semi_axis),
        (
            3,
            pose.shape.e1 <= MIN_EPSILON,
            pose.shape.e1 >= MAX_EPSILON,
        ),
        (
            4,
            pose.shape.e2 <= MIN_EPSILON,
            pose.shape.e2 >= MAX_EPSILON,
        ),
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
}

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
    /// The distance the starts and similarity candidates are fitted with; [`solve`] polishes the
    /// kept fit with [`Metric::Surface`] whatever this is.
    pub metric: Metric,
    /// The longest a semi-axis may grow (`f64::INFINITY`: no bound). The distances measure the
    /// points' way to the surface only, so on a one-view scan a superquadric can stretch far
    /// beyond the data on the side no point sees at almost no cost; such a model fits the points
    /// no better, and leaves a fit with local DOFs few nodes where the data is.
    pub max_semi_axis: f64,
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

impl LmFit {
    /// Mean radial distance |dᵢ| of the points nearest the surface: all of them without an
    /// outlier model, the nearest (1 − w_o) of them with one. Comparable between fits of the same
    /// points whatever their weights or metric. (Ranking the starts by the surface distance
    /// instead chose worse fits on two of eleven test clouds.)
    pub fn score(&self, points: &[DVec3], mixture: &Mixture) -> f64 {
        trimmed_mean_distance(&self.pose, points, mixture.outlier_ratio)
    }
}

/// Mean radial distance over the ⌈(1 − `outlier_ratio`)·n⌉ points nearest the surface of
/// `pose`.
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

/// EM rounds from `start`: each refreshes the inlier weights from the distances of
/// [`LmOptions::metric`] and σ²,
/// then takes up to [`LmOptions::steps_per_round`] Levenberg–Marquardt steps and
/// re-estimates σ² from the weighted cost; rounds end when one lowers the cost by less than
/// [`LmOptions::tolerance`] of it, or after [`LmOptions::max_rounds`].
pub fn fit_em(points: &[DVec3], start: &InitialPose, sigma2: f64, opts: &LmOptions) -> LmFit {
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
    // Predicted gains below this share of the cost are noise: the radial distance is exact to
    // rounding, the surface distance to its search's tolerance.
    let floor = match opts.metric {
        Metric::Radial => 1e-12,
        Metric::Surface => 1e-3 * opts.tolerance,
    };
    for _ in 0..opts.max_rounds {
        let mut cost = if robust {
            // The weights and the cost they give, from one pass over the distances.
            use rayon::prelude::*;
            let weigh = |p: &DVec3| {
                let d = opts.metric.distance(&fit.pose, *p);
                let w = mixture.inlier(d, fit.sigma2);
                (w, w * d * d)
            };
            let pairs: Vec<(f64, f64)> = if points.len() >= PARALLEL_POINTS {
                points.par_iter().map(weigh).collect()
            } else {
                points.iter().map(weigh).collect()
            };
            fit.weights = pairs.iter().map(|(w, _)| *w).collect();
            pairs.iter().map(|(_, c)| c).sum()
        } else {
            weighted_cost(opts.metric, &fit.pose, points, &fit.weights)
        };
        for _ in 0..opts.steps_per_round {
            let Some((pose, c)) = lm_step(
                opts.metric,
                &fit.pose,
                cost,
                points,
                &fit.weights,
                &mut lambda,
                floor,
                opts.max_semi_axis,
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
    pub fit: LmFit,
    /// The start it came from.
    pub start: InitialPose,
    /// Levenberg–Marquardt steps over every start and candidate tried.
    pub iterations: u32,
}

/// EM rounds each start and similarity candidate of [`solve`] gets before they are compared;
/// only the one that scores least is run on to rest (EMS's rule, in place of running every one to
/// rest).
pub const PROBE_ROUNDS: u32 = 3;

/// [`fit_em`] for [`PROBE_ROUNDS`] from each of `starts` side by side (threads of their own),
/// then the one with the least finite [`LmFit::score`] on to rest: that fit, its score and start,
/// and the steps all of them took.
fn best_fit(
    points: &[DVec3],
    starts: &[InitialPose],
    sigma2: f64,
    opts: &LmOptions,
) -> Option<(LmFit, f64, InitialPose, u32)> {
    let probe = LmOptions {
        max_rounds: PROBE_ROUNDS.min(opts.max_rounds),
        ..*opts
    };
    let run = |start: &InitialPose, _: &mut dyn FnMut(&super::fit::FitProgress)| {
        let fit = fit_em(points, start, sigma2, &probe);
        let score = fit.score(points, &opts.mixture);
        (fit, score)
    };
    let runs = super::fit::run_parallel(starts, run, &mut |_| {});
    let mut iterations = runs.iter().map(|(f, _)| f.iterations).sum();
    let ((mut fit, mut score), start) = runs
        .into_iter()
        .zip(starts)
        .filter(|((_, s), _)| s.is_finite())
        .min_by(|((_, a), _), ((_, b), _)| a.total_cmp(b))?;
    if !fit.converged && opts.max_rounds > probe.max_rounds {
        let rest = LmOptions {
            max_rounds: opts.max_rounds - probe.max_rounds,
            ..*opts
        };
        fit = LmFit {
            iterations: 0,
            ..fit_em(points, &fit.pose, fit.sigma2, &rest)
        };
        iterations += fit.iterations;
        score = fit.score(points, &opts.mixture);
    }
    Some((fit, score, *start, iterations))
}

/// The most points the starts and the similarity candidates of [`solve`] are fitted to: a larger
/// cloud is subsampled for them, and only the kept fit is refined on every point.
pub const COARSE_POINTS: usize = 512;

/// Every `n / COARSE_POINTS`-th point of `points` (all of them when there are at most twice
/// [`COARSE_POINTS`]).
pub fn coarse_sample(points: &[DVec3]) -> Vec<DVec3> {
    spread_sample(points, COARSE_POINTS)
}

/// The most points [`solve`]'s last stage is fitted to: a larger cloud is subsampled for it too
/// (its fit then costs the same whatever the cloud's size; only the residuals visit every
/// point). None of the test clouds and scans reaches it.
pub const FINE_POINTS: usize = 32_768;

/// `count` points spread evenly through `points` in their order (all of them when there are at
/// most twice `count`).
pub fn spread_sample(points: &[DVec3], count: usize) -> Vec<DVec3> {
    if points.len() <= 2 * count {
        return points.to_vec();
    }
    let stride = points.len() as f64 / count as f64;
    (0..count)
        .map(|i| points[((i as f64 * stride) as usize).min(points.len() - 1)])
        .collect()
}

/// Most EM rounds of [`solve`]'s last stage, on every point of a subsampled cloud: the subsample's
/// fit is close, and the rounds after two changed the mean distance of the test scans by under
/// 0.1 % (hippo scan: 1.760e-2 with two, 1.761e-2 with 17) at 2.3 times the cost.
pub const FINE_ROUNDS: u32 = 2;

/// Fits from each of `starts` and keeps the one with the least [`LmFit::score`]; then tries
/// the kept fit's similarity candidates (`candidates`, from its pose) from that fit's σ², and
/// moves to a candidate that scores less, until none does (at most `max_switches` moves). The
/// starts run side by side on threads of their own. Starts and candidates are fitted to
/// [`coarse_sample`]`(points)`. The kept fit is then polished with the surface distance
/// ([`Metric::Surface`]) when the options' metric is another, to rest on the subsample and then
/// for at most [`FINE_ROUNDS`] rounds on every point (on [`FINE_POINTS`] of them spread through a
/// larger cloud; [`LmFit::weights`] are then those points').
pub fn solve(
    all_points: &[DVec3],
    starts: &[InitialPose],
    sigma2: f64,
    opts: &LmOptions,
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
    let surface = LmOptions {
        metric: Metric::Surface,
        ..*opts
    };
    if opts.metric != Metric::Surface {
        best = fit_em(points, &best.pose, best.sigma2, &surface);
        iterations += best.iterations;
    }
    if points.len() < all_points.len() {
        let fine = LmOptions {
            max_rounds: FINE_ROUNDS,
            ..surface
        };
        let fine_points = spread_sample(all_points, FINE_POINTS);
        best = fit_em(&fine_points, &best.pose, best.sigma2, &fine);
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
        crate::model::distance::tests::pose(0.6, 1.4)
    }

    fn options(outlier_ratio: f64) -> LmOptions {
        LmOptions {
            mixture: Mixture {
                outlier_ratio,
                outlier_density: 1.0 / 27.0,
                sigma2_floor: 1e-10,
            },
            max_rounds: 30,
            steps_per_round: 10,
            tolerance: 1e-6,
            metric: Metric::Radial,
            max_semi_axis: f64::INFINITY,
        }
    }

    #[test]
    fn a_spread_sample_keeps_small_clouds_whole_and_spreads_through_large_ones() {
        let points: Vec<DVec3> = (0..1000).map(|i| DVec3::splat(i as f64)).collect();
        assert_eq!(spread_sample(&points, 500), points);
        let few = spread_sample(&points, 100);
        assert_eq!(few.len(), 100);
        assert_eq!(few[0], points[0]);
        assert_eq!(few[99], points[990]);
        assert!(few.windows(2).all(|w| w[1].x - w[0].x == 10.0));
    }

    #[test]
    fn the_semi_axes_stop_at_their_bound_and_the_cost_still_falls() {
        let truth = pose();
        let points = superquadric_cloud(
            &truth.shape,
            truth.translation,
            truth.rotation,
            400,
            0.0,
            11,
        );
        let longest = truth.shape.semi_axes().max_element();
        let bound = 0.8 * longest;
        let mut start = truth;
        start.shape.a *= 0.7;
        let opts = LmOptions {
            max_semi_axis: bound,
            ..options(0.0)
        };
        let free = fit_em(&points, &start, 1e-2, &options(0.0));
        let held = fit_em(&points, &start, 1e-2, &opts);
        let start_cost = weighted_cost(Metric::Radial, &start, &points, &[]);
        // Unbounded, the longest semi-axis comes back to the truth; bounded, it stops at the
        // bound while the others go on fitting.
        assert!((free.pose.shape.semi_axes().max_element() - longest).abs() < 1e-6);
        let axes = held.pose.shape.semi_axes();
        assert!(axes.max_element() <= bound * (1.0 + 1e-12), "{axes}");
        assert!((axes.max_element() - bound).abs() < 1e-9, "{axes}");
        assert!(held.cost.is_finite() && held.cost < start_cost);
        assert!(held.cost > free.cost);
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
        let mut cost = weighted_cost(Metric::Radial, &start, &points, &[]);
        let mut pose = start;
        let mut lambda = INITIAL_DAMPING;
        for _ in 0..60 {
            let Some((next, c)) = lm_step(
                Metric::Radial,
                &pose,
                cost,
                &points,
                &[],
                &mut lambda,
                1e-12,
                f64::INFINITY,
            ) else {
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
        let fit = fit_em(&points, &start, 0.05, &options(0.2));
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

    /// Mean |surface distance| of `points` to `pose`.
    fn mean_surface(pose: &InitialPose, points: &[DVec3]) -> f64 {
        points
            .iter()
            .map(|p| super::super::distance::surface_distance(pose, *p).abs())
            .sum::<f64>()
            / points.len() as f64
    }

    #[test]
    fn the_surface_polish_brings_a_noisy_elongated_fit_closer() {
        // A long, squarish superquadric under noise: the radial distance's optimum is off the
        // surface distance's, and the polish moves there.
        let mut truth = pose();
        truth.shape.a3 = 0.25;
        truth.shape.e1 = 0.3;
        let points = superquadric_cloud(
            &truth.shape,
            truth.translation,
            truth.rotation,
            1500,
            0.04,
            9,
        );
        let radial_only = fit_em(&points, &truth, 0.01, &options(0.0));
        let polished = solve(&points, &[truth], 0.01, &options(0.0), |_| Vec::new(), 0).unwrap();
        let (before, after) = (
            mean_surface(&radial_only.pose, &points),
            mean_surface(&polished.fit.pose, &points),
        );
        assert!(after < 0.99 * before, "polished {after} vs radial {before}");
        assert!(polished.fit.pose.shape.is_finite() && polished.fit.cost.is_finite());
    }

    #[test]
    fn an_exponent_on_its_bound_stays_there_while_the_rest_converge() {
        // A box: ε below the least allowed exponent, so the fit rests with both on the bound.
        let mut truth = pose();
        truth.shape.e1 = 0.05;
        truth.shape.e2 = 0.05;
        let points =
            superquadric_cloud(&truth.shape, truth.translation, truth.rotation, 600, 0.0, 4);
        let mut start = truth;
        start.shape.e1 = 0.4;
        start.shape.e2 = 0.4;
        start.shape.a *= 1.05;
        let fit = fit_em(&points, &start, 0.01, &options(0.0));
        assert_eq!(
            (fit.pose.shape.e1, fit.pose.shape.e2),
            (MIN_EPSILON, MIN_EPSILON)
        );
        assert!(fit.converged && fit.cost.is_finite(), "{fit:?}");
        // The bound's rounder corners make the fit a little larger than the box.
        let axes = fit.pose.shape.semi_axes();
        assert!(
            ((axes - truth.shape.semi_axes()).abs() / truth.shape.semi_axes()).max_element() < 0.04,
            "{axes} vs {}",
            truth.shape.semi_axes()
        );
    }
}
