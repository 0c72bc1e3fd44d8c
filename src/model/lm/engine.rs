//! The one Levenberg–Marquardt engine (beyond the paper): EM rounds of damped Gauss–Newton steps
//! on Σ wᵢ eᵢ² over any residual ([`Problem`]), with outlier weights from a [`Mixture`], bounds
//! kept by an active set, and an extra term (the coverage) when the problem has one. The plain
//! superquadric ([`super::plain`]) and the tapered and bent one ([`super::deformed`]) are its
//! problems.
//!
//! A round refreshes the inlier weights wᵢ from the residuals and σ², takes up to
//! [`LmOptions::steps_per_round`] steps and re-estimates σ² from the weighted cost; rounds end
//! when one lowers the cost by less than [`LmOptions::tolerance`] of it, when the points lie on
//! the surface to a tenth of the σ floor, or after [`LmOptions::max_rounds`].

use super::Mixture;
use crate::model::linalg::cholesky_solve;
use crate::model::parallel::sum_points;

/// Settings of a Levenberg–Marquardt fit.
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
    /// The distance the fit minimises (the plain superquadric's; a deformed fit has its own).
    pub metric: crate::model::distance::Metric,
    /// The longest a semi-axis may grow (`f64::INFINITY`: no bound). The distances measure the
    /// points' way to the surface only, so on a one-view scan a superquadric can stretch far
    /// beyond the data on the side no point sees at almost no cost; such a model fits the points
    /// no better, and leaves a fit with local DOFs few nodes where the data is.
    pub max_semi_axis: f64,
    /// The least ε1 and ε2 (at most [`crate::model::superquadric::MAX_EPSILON`]).
    pub min_epsilon: f64,
    /// Hold ε1 and ε2 where they are (fit the pose and the semi-axes alone).
    pub hold_exponents: bool,
    /// Start at the start's own inliers' variance ([`Mixture::fitted_sigma2`], EM on σ² alone
    /// from the given one) rather than at the given one. A start that lies on the object among
    /// outliers keeps to it, where the given variance would weigh the outliers as inliers and
    /// pull it into them; a start that fits some of the points and is to grow over the rest
    /// (a merge of pieces) needs the given, wider one.
    pub own_sigma2: bool,
}

/// A normal matrix JᵀWJ (lower triangle while it is summed) and JᵀWr over N unknowns.
pub(crate) type Normal<const N: usize> = ([[f64; N]; N], [f64; N]);

/// A least-squares problem the engine solves: signed residuals eᵢ of a model's surface, their
/// gradients over N unknowns, and the model moved by an increment within its bounds.
pub(crate) trait Problem<const N: usize>: Sync {
    /// What the unknowns move.
    type Model: Copy + Sync;
    /// What a point keeps between evaluations to warm-start its next one (its foot on the
    /// surface).
    type Foot: Copy + Send + Sync;
    /// The number of points.
    fn len(&self) -> usize;
    /// Every point's signed residual at `model` and its foot, warm-started from `hints` (the
    /// feet at a nearby model; empty: a cold start). The feet may be empty when the residual
    /// keeps none.
    fn evaluate(&self, model: &Self::Model, hints: &[Self::Foot]) -> (Vec<f64>, Vec<Self::Foot>);
    /// Point `i`'s residual and its gradient over the unknowns at `model`, from its foot
    /// `foot`; `None` when it has none.
    fn gradient(
        &self,
        model: &Self::Model,
        i: usize,
        foot: Option<&Self::Foot>,
    ) -> Option<(f64, [f64; N])>;
    /// `model` moved by `delta`, within the model's bounds.
    fn moved(&self, model: &Self::Model, delta: &[f64; N]) -> Self::Model;
    /// Whether unknown `k` sits on its lower and on its upper bound at `model`: the step holds
    /// it there while it would push past.
    fn on_bound(&self, model: &Self::Model, k: usize) -> (bool, bool);
    /// Whether unknown `k` is held where it is.
    fn held(&self, k: usize) -> bool;
    /// An extra term of the cost at `model` when the points' weights are `weights` (1 each when
    /// empty) with sum `total`; 0 for none.
    fn extra_cost(&self, _model: &Self::Model, _weights: &[f64], _total: f64) -> f64 {
        0.0
    }
    /// Adds the extra term's JᵀWJ (lower triangle) and JᵀWr at `model` to `n`.
    fn add_extra_normal(
        &self,
        _model: &Self::Model,
        _weights: &[f64],
        _total: f64,
        _n: &mut Normal<N>,
    ) {
    }
}

/// Where [`solve_em`] came to rest.
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct EmFit<M> {
    /// The model.
    pub model: M,
    /// Σ wᵢ eᵢ² plus the extra term at the end.
    pub cost: f64,
    /// The points' inlier weights wᵢ (empty without an outlier model).
    pub weights: Vec<f64>,
    /// The inliers' variance per coordinate σ².
    pub sigma2: f64,
    /// The points' signed residuals at the end.
    pub residuals: Vec<f64>,
    /// Levenberg–Marquardt steps taken.
    pub iterations: u32,
    /// True when a round's progress fell below the tolerance (not stopped by the round cap).
    pub converged: bool,
}

/// Levenberg–Marquardt damping at the start of a solve, relative to the normal matrix' diagonal.
pub(crate) const INITIAL_DAMPING: f64 = 1e-3;

/// Σ wᵢ eᵢ² (w 1 each when empty).
fn weighted(e: &[f64], w: &[f64]) -> f64 {
    e.iter()
        .enumerate()
        .map(|(i, e)| w.get(i).copied().unwrap_or(1.0) * e * e)
        .sum()
}

/// EM rounds of `problem` from `start` (see the module docs), from an inlier variance of at
/// least `sigma2` and the mixture's floor, and with `spread` at least the start's own spread
/// (Σ eᵢ² / 3n): a start far from the points would otherwise call most of them outliers and
/// come to rest where it is. With [`LmOptions::own_sigma2`], from the start's own variance
/// found from there.
pub(crate) fn solve_em<const N: usize, P: Problem<N>>(
    problem: &P,
    start: &P::Model,
    sigma2: f64,
    spread: bool,
    opts: &LmOptions,
) -> EmFit<P::Model> {
    let mixture = opts.mixture;
    let robust = mixture.outlier_ratio > 0.0;
    let (mut e, mut feet) = problem.evaluate(start, &[]);
    let own = if spread {
        weighted(&e, &[]) / (3.0 * e.len().max(1) as f64)
    } else {
        0.0
    };
    let mut fit = EmFit {
        model: *start,
        cost: f64::INFINITY,
        weights: Vec::new(),
        sigma2: if opts.own_sigma2 {
            mixture.fitted_sigma2(&e, sigma2.max(own))
        } else {
            sigma2.max(own).max(mixture.sigma2_floor)
        },
        residuals: Vec::new(),
        iterations: 0,
        converged: false,
    };
    let mut lambda = INITIAL_DAMPING;
    let mut previous = f64::INFINITY;
    for _ in 0..opts.max_rounds {
        if robust {
            fit.weights = e.iter().map(|&d| mixture.inlier(d, fit.sigma2)).collect();
        }
        let total: f64 = if robust {
            fit.weights.iter().sum()
        } else {
            problem.len() as f64
        };
        let mut data = weighted(&e, &fit.weights);
        let mut extra = problem.extra_cost(&fit.model, &fit.weights, total);
        for _ in 0..opts.steps_per_round {
            let Some(s) = step(
                problem,
                &fit.model,
                (data + extra, &feet),
                (&fit.weights, total),
                &mut lambda,
                opts,
            ) else {
                break;
            };
            fit.iterations += 1;
            let (before, after) = (data + extra, s.data + s.extra);
            let small = before - after <= opts.tolerance * 0.1 * after;
            (fit.model, data, extra, e, feet) = (s.model, s.data, s.extra, s.residuals, s.feet);
            if small {
                break;
            }
        }
        let cost = data + extra;
        fit.cost = cost;
        if robust && total > 0.0 {
            fit.sigma2 = (data / (3.0 * total)).max(mixture.sigma2_floor);
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
    fit.residuals = e;
    fit
}

/// A step [`step`] took.
pub(crate) struct Step<M, F> {
    /// The model after it.
    pub model: M,
    /// Σ wᵢ eᵢ² there.
    pub data: f64,
    /// The extra term there.
    pub extra: f64,
    /// The residuals there.
    pub residuals: Vec<f64>,
    /// The feet there.
    pub feet: Vec<F>,
}

/// One Levenberg–Marquardt step of `problem` from `model`, whose cost is `cost` with the points'
/// feet `feet`, the points weighted by `weights` (sum `total`), with damping `lambda` (lowered
/// after a step that lowered the cost, raised while one did not). `None` at a minimum to the
/// precision that matters: when the step's predicted decrease falls below a tenth of the
/// tolerance times the cost (a step a round would count as no progress), or no damping up to
/// 10¹⁰ lowers it.
pub(crate) fn step<const N: usize, P: Problem<N>>(
    problem: &P,
    model: &P::Model,
    (cost, feet): (f64, &[P::Foot]),
    (weights, total): (&[f64], f64),
    lambda: &mut f64,
    opts: &LmOptions,
) -> Option<Step<P::Model, P::Foot>> {
    let mut normal = normal_equations(problem, model, weights, feet);
    problem.add_extra_normal(model, weights, total, &mut normal);
    let (mut jtj, mut jtr) = normal;
    for a in 0..N {
        for b in 0..a {
            jtj[b][a] = jtj[a][b];
        }
    }
    for k in (0..N).filter(|&k| problem.held(k)) {
        hold(&mut jtj, &mut jtr, k);
    }
    let scale = (0..N).map(|a| jtj[a][a]).fold(0.0, f64::max);
    let neg: [f64; N] = jtr.map(|g| -g);
    let floor = 0.1 * opts.tolerance;
    while *lambda < 1e10 {
        let mut damped = jtj;
        for (a, row) in damped.iter_mut().enumerate() {
            row[a] += *lambda * row[a] + 1e-12 * scale.max(f64::MIN_POSITIVE);
        }
        if let Some(delta) = bounded_solve(problem, model, damped, neg) {
            // The decrease the linear model predicts, 2δ·(−Jᵀr) − δᵀJᵀJδ.
            let quadratic: f64 = (0..N)
                .map(|a| delta[a] * (0..N).map(|b| jtj[a][b] * delta[b]).sum::<f64>())
                .sum();
            let predicted = 2.0 * (0..N).map(|a| delta[a] * neg[a]).sum::<f64>() - quadratic;
            if !(predicted > floor * cost) {
                return None;
            }
            let next = problem.moved(model, &delta);
            let (residuals, next_feet) = problem.evaluate(&next, feet);
            let data = weighted(&residuals, weights);
            let extra = problem.extra_cost(&next, weights, total);
            if data + extra < cost {
                *lambda = (*lambda / 3.0).max(1e-12);
                return Some(Step {
                    model: next,
                    data,
                    extra,
                    residuals,
                    feet: next_feet,
                });
            }
        }
        *lambda *= 4.0;
    }
    None
}

/// Holds unknown `k` of the system (m, rhs): its row and column cleared, its δ then exactly 0.
fn hold<const N: usize>(m: &mut [[f64; N]; N], rhs: &mut [f64; N], k: usize) {
    for row in m.iter_mut() {
        row[k] = 0.0;
    }
    m[k] = [0.0; N];
    m[k][k] = 1.0;
    rhs[k] = 0.0;
}

/// JᵀWJ (lower triangle) and JᵀWr of the problem's residuals at `model`, each from its foot.
pub(crate) fn normal_equations<const N: usize, P: Problem<N>>(
    problem: &P,
    model: &P::Model,
    weights: &[f64],
    feet: &[P::Foot],
) -> Normal<N> {
    let zero = || ([[0.0; N]; N], [0.0; N]);
    let add = |n: &mut Normal<N>, i: usize| {
        let w = weights.get(i).copied().unwrap_or(1.0);
        if !(w > 0.0) {
            return;
        }
        let Some((r, g)) = problem.gradient(model, i, feet.get(i)) else {
            return;
        };
        if !r.is_finite() || g.iter().any(|g| !g.is_finite()) {
            return;
        }
        for a in 0..N {
            let wg = w * g[a];
            n.1[a] += wg * r;
            for b in 0..=a {
                n.0[a][b] += wg * g[b];
            }
        }
    };
    let merge = |x: &mut Normal<N>, y: &Normal<N>| {
        for a in 0..N {
            x.1[a] += y.1[a];
            for b in 0..N {
                x.0[a][b] += y.0[a][b];
            }
        }
    };
    sum_points(problem.len(), zero, add, merge)
}

/// The step `m·δ = rhs` with every unknown that sits on a bound ([`Problem::on_bound`]) held
/// there when the step would push it past (an active set): clamping such a step afterwards
/// would bend it off the descent direction and leave the other unknowns creeping.
fn bounded_solve<const N: usize, P: Problem<N>>(
    problem: &P,
    model: &P::Model,
    mut m: [[f64; N]; N],
    mut rhs: [f64; N],
) -> Option<[f64; N]> {
    let bounds: [(bool, bool); N] = std::array::from_fn(|k| problem.on_bound(model, k));
    // Each pass holds at least one more unknown (its δ is then exactly 0), so this ends.
    loop {
        let delta = cholesky_solve(&m, &rhs)?;
        let mut held = false;
        for (k, &(low, high)) in bounds.iter().enumerate() {
            if (low && delta[k] < 0.0) || (high && delta[k] > 0.0) {
                hold(&mut m, &mut rhs, k);
                held = true;
            }
        }
        if !held {
            return Some(delta);
        }
    }
}
