//! The superquadric's eleven unknowns as a problem of the engine (the module `engine`): the
//! semi-axes a·a_i, the exponents ε1 and ε2, the translation and a rotation increment about the
//! current orientation, against the radial, normal or exact surface distance ([`Metric`]), with
//! the [`Coverage`] term when one is given. The exact distance keeps each point's foot between
//! evaluations, so that its search starts where it ended
//! ([`crate::model::distance::closest_point_from`]).

use super::Coverage;
use super::engine::{EmFit, LmOptions, Normal, Problem, solve_em};
use crate::model::distance::{Metric, NUM_UNKNOWNS};
use crate::model::init::InitialPose;
use crate::model::parallel::map_points;
use crate::model::superquadric::{LEAST_EPSILON, MAX_EPSILON, MIN_ASPECT, SuperquadricParams};
use glam::{DQuat, DVec3};

/// `pose` moved by the unknowns' increment `delta` (in [`crate::model::distance::Distance`]'s
/// order), its semi-axes held at least [`MIN_ASPECT`] of the longest and its exponents in
/// [[`LEAST_EPSILON`], [`MAX_EPSILON`]].
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

/// Whether unknown `k` of `pose` (the plain superquadric's order, [`NUM_UNKNOWNS`]) sits on its
/// lower and on its upper bound: a semi-axis at `max_semi_axis`, an exponent at `min_epsilon` or
/// [`MAX_EPSILON`]; the pose's other unknowns have none.
pub(super) fn on_bound(
    pose: &InitialPose,
    k: usize,
    max_semi_axis: f64,
    min_epsilon: f64,
) -> (bool, bool) {
    let q = &pose.shape;
    match k {
        0..=2 => (false, q.semi_axes()[k] >= max_semi_axis),
        3 => (q.e1 <= min_epsilon, q.e1 >= MAX_EPSILON),
        4 => (q.e2 <= min_epsilon, q.e2 >= MAX_EPSILON),
        _ => (false, false),
    }
}

/// The plain superquadric fitted to `points` by `metric`'s distance (see the module docs).
pub(crate) struct Plain<'a> {
    points: &'a [DVec3],
    metric: Metric,
    coverage: Option<&'a Coverage>,
    max_semi_axis: f64,
    min_epsilon: f64,
    hold_exponents: bool,
}

impl<'a> Plain<'a> {
    /// The problem of `points` under `opts` (its metric, bounds and held exponents), with the
    /// `coverage` term when given.
    pub(crate) fn new(
        points: &'a [DVec3],
        opts: &LmOptions,
        coverage: Option<&'a Coverage>,
    ) -> Self {
        Self {
            points,
            metric: opts.metric,
            coverage,
            max_semi_axis: opts.max_semi_axis,
            min_epsilon: opts.min_epsilon,
            hold_exponents: opts.hold_exponents,
        }
    }
}

impl Problem<NUM_UNKNOWNS> for Plain<'_> {
    type Model = InitialPose;
    /// The ray direction of the point's foot (the exact distance's; none for the others).
    type Foot = DVec3;

    fn len(&self) -> usize {
        self.points.len()
    }

    fn evaluate(&self, pose: &InitialPose, hints: &[DVec3]) -> (Vec<f64>, Vec<DVec3>) {
        let (metric, points) = (self.metric, self.points);
        if metric != Metric::Surface {
            let d = map_points(points.len(), |i| metric.distance(pose, points[i]));
            return (d, Vec::new());
        }
        map_points(points.len(), |i| {
            metric.distance_from(pose, points[i], hints.get(i).copied())
        })
        .into_iter()
        .unzip()
    }

    fn gradient(
        &self,
        pose: &InitialPose,
        i: usize,
        foot: Option<&DVec3>,
    ) -> Option<(f64, [f64; NUM_UNKNOWNS])> {
        let r = self
            .metric
            .with_gradient_from(pose, self.points[i], foot.copied());
        Some((r.distance, r.gradient))
    }

    fn moved(&self, pose: &InitialPose, delta: &[f64; NUM_UNKNOWNS]) -> InitialPose {
        bounded_increment(pose, delta, self.max_semi_axis, self.min_epsilon)
    }

    fn on_bound(&self, pose: &InitialPose, k: usize) -> (bool, bool) {
        on_bound(pose, k, self.max_semi_axis, self.min_epsilon)
    }

    fn held(&self, k: usize) -> bool {
        self.hold_exponents && (k == 3 || k == 4)
    }

    fn extra_cost(&self, pose: &InitialPose, weights: &[f64], total: f64) -> f64 {
        self.coverage.map_or(0.0, |c| c.cost(pose, weights, total))
    }

    fn add_extra_normal(
        &self,
        pose: &InitialPose,
        weights: &[f64],
        total: f64,
        n: &mut Normal<NUM_UNKNOWNS>,
    ) {
        if let Some(c) = self.coverage {
            c.add_normal(pose, weights, total, n);
        }
    }
}

/// Σ wᵢ dᵢ² over `points` with weights `weights` (1 each when empty), d the `metric`'s distance.
pub fn weighted_cost(metric: Metric, pose: &InitialPose, points: &[DVec3], weights: &[f64]) -> f64 {
    let (d, _) = Plain {
        points,
        metric,
        coverage: None,
        max_semi_axis: f64::INFINITY,
        min_epsilon: LEAST_EPSILON,
        hold_exponents: false,
    }
    .evaluate(pose, &[]);
    d.iter()
        .enumerate()
        .map(|(i, d)| weights.get(i).copied().unwrap_or(1.0) * d * d)
        .sum()
}

/// Where [`fit_em`] came to rest.
#[derive(Clone, Debug, PartialEq)]
pub struct LmFit {
    /// The pose and shape.
    pub pose: InitialPose,
    /// Σ wᵢ dᵢ² at the end (with the coverage term, when there is one).
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

impl From<EmFit<InitialPose>> for LmFit {
    fn from(f: EmFit<InitialPose>) -> Self {
        Self {
            pose: f.model,
            cost: f.cost,
            weights: f.weights,
            sigma2: f.sigma2,
            iterations: f.iterations,
            converged: f.converged,
        }
    }
}

/// The superquadric fitted to `points` from `start` by the engine's EM rounds
/// (the module `engine`) on [`LmOptions::metric`]'s distance, from inlier variance `sigma2`.
pub fn fit_em(points: &[DVec3], start: &InitialPose, sigma2: f64, opts: &LmOptions) -> LmFit {
    fit_em_with(points, start, sigma2, opts, None)
}

/// [`fit_em`] with the [`Coverage`] term added to the cost, when given (σ² stays the points'
/// own: their weighted cost over 3 Σw).
pub fn fit_em_with(
    points: &[DVec3],
    start: &InitialPose,
    sigma2: f64,
    opts: &LmOptions,
    coverage: Option<&Coverage>,
) -> LmFit {
    solve_em(
        &Plain::new(points, opts, coverage),
        start,
        sigma2,
        false,
        opts,
    )
    .into()
}
