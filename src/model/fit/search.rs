//! The search for a superquadric's rest state ([`solve`]): which starts and similarity
//! candidates are fitted, in which order, and which fit is kept.
//!
//! Fitting a superquadric is a problem of many local minima: which data axis is the model's z,
//! a square section or its 45° dual, a box that sandwiches a one-view scan or a disc that lies
//! on it. [`solve`] runs two searches side by side on a subsample and keeps the fit whose
//! surface explains the points best. Every comparison of fits (starts, candidates, the two
//! searches) is by [`Mixture::score`]: the negative log-likelihood of the points under the
//! Gaussian–uniform mixture that weighs them, at each fit's own σ². A plain mean distance would
//! prefer a surface that passes through the outliers to one on the inliers:
//!
//! - **from the starts** (`probe_and_continue`): each start, and each of the `probes` (the
//!   moments of the points that lie on a surface, away from scattered outliers), gets
//!   [`PROBE_ROUNDS`] EM rounds of the radial distance twice, from the given inlier variance
//!   and from the start's own ([`LmOptions::own_sigma2`]: a wide variance weighs outliers as
//!   inliers and pulls a start that lies on the object into them); the best goes on to rest,
//!   and its similarity candidates are treated the same way while one of them fits closer
//!   (EMS's similarity switching; the radial distance's wide basin, with the dual and axis
//!   candidates, finds the sections and the squareness of clean partial clouds);
//! - **from placed starts** (`placed_search`): each start is first placed with its exponents
//!   held and the [`Coverage`] term on (the solved counterpart of the dynamics' placing stage,
//!   which keeps a model from shrinking into the bulk of a cloud and leaving its limbs), then
//!   fitted free; the closest goes on, and the others and its similarity candidates are tried
//!   by EMS's switch rule (`switch`: scored as they stand, refitted in score order, the first
//!   that wins kept).
//!
//! Neither search alone keeps the dynamics' accuracy on every cloud: on 26 clouds (EMS's six, the
//! shipped scans, one-view scans of the shipped meshes from three more directions and EMS's
//! multi-part clouds) the first alone left three fits 7–29 % farther from the points than the
//! dynamics, the second alone two fits 6 % farther; together none is more than 1 % farther
//! (docs/results.md, "The solved fit"). When the first search's fit passes through its inliers
//! (`passes_through`: at the σ floor where every EM fit stops, with at least the prior's share
//! of inliers), no fit can explain the points better, and the second search gives up.
//!
//! Both searches end with the surface distance ([`Metric::Surface`]); the kept fit is then
//! polished on every point (on [`FINE_POINTS`] of a larger cloud) for [`FINE_ROUNDS`] rounds.

use crate::model::init::InitialPose;
use crate::model::lm::{Coverage, LmFit, LmOptions, Metric, Mixture, fit_em, fit_em_with};
use crate::model::parallel::run_parallel;
use glam::DVec3;
use std::sync::atomic::{AtomicBool, Ordering};

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

/// EM rounds each start and similarity candidate of the search from the starts gets before
/// they are compared; only the one that scores least is run on to rest.
pub const PROBE_ROUNDS: u32 = 3;

/// Levenberg–Marquardt steps a candidate of EMS's switch rule (`switch`) gets before it is
/// compared with the current fit (EMS's own probe is 3 function evaluations).
pub const PROBE_STEPS: u32 = 3;

/// A placing (`placed_search`) ends when a round lowers its cost by less than this fraction:
/// it only has to bring the model into its basin, which the free fit after it then descends.
pub const PLACING_TOLERANCE: f64 = 1e-2;

/// The most points the searches fit to: a larger cloud is subsampled for them, and only the kept
/// fit is polished on every point.
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

/// [`Mixture::score`] of the [`crate::model::distance::normal_distance`]s of `points` from
/// `pose`: how the searches rank starts, placed fits and candidates. One gauge a point, and the
/// surface distance to first order, so comparable between fits whatever their weights or metric.
pub fn score(pose: &InitialPose, points: &[DVec3], mixture: &Mixture) -> f64 {
    let d: Vec<f64> = points
        .iter()
        .map(|p| crate::model::distance::normal_distance(pose, *p))
        .collect();
    mixture.score(&d)
}

/// [`Mixture::score`] of the exact distances of `points` from `pose`'s surface: how [`solve`]
/// chooses between its two searches, and how the placed fits are ranked.
fn surface_score(pose: &InitialPose, points: &[DVec3], mixture: &Mixture) -> f64 {
    let d: Vec<f64> = points
        .iter()
        .map(|p| crate::model::distance::surface_distance(pose, *p))
        .collect();
    mixture.score(&d)
}

/// The indices of `poses` in the order of their [`score`], least first; poses whose score is
/// not finite are dropped. Ties keep the given order.
fn in_score_order(poses: &[InitialPose], points: &[DVec3], mixture: &Mixture) -> Vec<usize> {
    let mut scored: Vec<(f64, usize)> = poses
        .iter()
        .enumerate()
        .map(|(i, p)| (score(p, points, mixture), i))
        .filter(|(s, _)| s.is_finite())
        .collect();
    scored.sort_by(|a, b| a.0.total_cmp(&b.0));
    scored.into_iter().map(|(_, i)| i).collect()
}

/// A fit, its [`score`] and the start it came from.
type Scored = (LmFit, f64, InitialPose);

/// [`fit_em`] for [`PROBE_ROUNDS`] from each of `starts` side by side (threads of their own),
/// from `sigma2` and, with `own_too`, from each start's own σ² as well
/// ([`LmOptions::own_sigma2`]), then the one with the least finite [`score`] on to rest: that
/// fit and the steps all of them took.
fn probe_and_continue(
    points: &[DVec3],
    starts: &[InitialPose],
    sigma2: f64,
    opts: &LmOptions,
    own_too: bool,
) -> Option<(Scored, u32)> {
    let probe = LmOptions {
        max_rounds: PROBE_ROUNDS.min(opts.max_rounds),
        ..*opts
    };
    let ways: &[bool] = if own_too { &[false, true] } else { &[false] };
    let tries: Vec<(InitialPose, bool)> = starts
        .iter()
        .flat_map(|s| ways.iter().map(move |&own| (*s, own)))
        .collect();
    let run = |&(start, own): &(InitialPose, bool), _: &mut dyn FnMut(&())| {
        let probe = LmOptions {
            own_sigma2: own || probe.own_sigma2,
            ..probe
        };
        let fit = fit_em(points, &start, sigma2, &probe);
        let s = score(&fit.pose, points, &opts.mixture);
        (fit, s, start)
    };
    let runs = run_parallel(&tries, run, &mut |_: &()| {});
    let mut iterations = runs.iter().map(|(f, _, _)| f.iterations).sum();
    let (mut fit, mut s, start) = runs
        .into_iter()
        .filter(|(_, s, _)| s.is_finite())
        .min_by(|a, b| a.1.total_cmp(&b.1))?;
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
        s = score(&fit.pose, points, &opts.mixture);
    }
    Some(((fit, s, start), iterations))
}

/// EMS's switch rule (Liu et al. 2022): the `candidates` are scored as they stand and refitted
/// in score order, each for [`PROBE_STEPS`] Levenberg–Marquardt steps from `sigma2`, until one
/// scores less than `least`; that one is fitted to rest and returned if it still does, with its
/// index among the candidates. Also returns the steps every candidate took.
fn switch(
    points: &[DVec3],
    candidates: &[InitialPose],
    sigma2: f64,
    least: f64,
    opts: &LmOptions,
) -> (Option<(LmFit, f64, usize)>, u32) {
    let probe = LmOptions {
        max_rounds: 1,
        steps_per_round: PROBE_STEPS,
        ..*opts
    };
    let mut steps = 0;
    for i in in_score_order(candidates, points, &opts.mixture) {
        let trial = fit_em(points, &candidates[i], sigma2, &probe);
        steps += trial.iterations;
        if !(score(&trial.pose, points, &opts.mixture) < least) {
            continue;
        }
        let fit = fit_em(points, &trial.pose, trial.sigma2, opts);
        steps += fit.iterations;
        let s = score(&fit.pose, points, &opts.mixture);
        if s < least {
            return (Some((fit, s, i)), steps);
        }
    }
    (None, steps)
}

/// Whether `fit` passes through its inliers as closely as a fit can: its weighted cost is at
/// most a hundredth of the σ floor's (its inliers within a tenth of the floor, where every EM
/// fit stops), and it counts at least the prior's share of the `n` points as inliers. No other
/// minimum then explains the points better, and [`solve`] does not search further.
pub(crate) fn passes_through(fit: &LmFit, n: usize, mixture: &Mixture) -> bool {
    let inliers = if fit.weights.is_empty() {
        n as f64
    } else {
        fit.weights.iter().sum()
    };
    inliers >= (1.0 - mixture.outlier_ratio) * n as f64
        && fit.cost <= 0.01 * mixture.sigma2_floor * inliers
}

/// What both searches are given.
struct Search<'a> {
    points: &'a [DVec3],
    starts: &'a [InitialPose],
    /// More starts for the search from the starts alone.
    probes: &'a [InitialPose],
    sigma2: f64,
    opts: &'a LmOptions,
    candidates: &'a (dyn Fn(&InitialPose) -> Vec<InitialPose> + Sync),
    max_switches: u32,
    /// The [`Coverage`] density the placing runs with.
    coverage: f64,
}

/// The search from the starts (see the module docs), ending with the surface distance.
fn search_from_starts(s: &Search) -> Option<(Scored, u32)> {
    let radial = LmOptions {
        metric: Metric::Radial,
        ..*s.opts
    };
    let all: Vec<InitialPose> = s.starts.iter().chain(s.probes).copied().collect();
    let ((mut best, mut least, mut start), mut iterations) =
        probe_and_continue(s.points, &all, s.sigma2, &radial, !s.probes.is_empty())?;
    for _ in 0..s.max_switches {
        let others = (s.candidates)(&best.pose);
        let Some(((fit, score, from), spent)) =
            probe_and_continue(s.points, &others, best.sigma2, &radial, false)
        else {
            break;
        };
        iterations += spent;
        if score >= least {
            break;
        }
        (best, least, start) = (fit, score, from);
    }
    let fit = fit_em(s.points, &best.pose, best.sigma2, s.opts);
    iterations += fit.iterations;
    let least = score(&fit.pose, s.points, &s.opts.mixture);
    Some(((fit, least, start), iterations))
}

/// The search from placed starts (see the module docs), ending with the surface distance;
/// `None` as soon as `stop` is set.
fn placed_search(s: &Search, stop: &AtomicBool) -> Option<(Scored, u32)> {
    let stopped = || stop.load(Ordering::Relaxed);
    let points = s.points;
    let coverage = Coverage::new(points, s.coverage);
    let placing = LmOptions {
        metric: Metric::Normal,
        tolerance: PLACING_TOLERANCE,
        hold_exponents: true,
        ..*s.opts
    };
    let free = LmOptions {
        metric: Metric::Normal,
        ..*s.opts
    };
    let run = |start: &InitialPose, _: &mut dyn FnMut(&())| {
        if stopped() {
            return None;
        }
        let placed = fit_em_with(points, start, s.sigma2, &placing, coverage.as_ref());
        if stopped() {
            return None;
        }
        let fit = fit_em(points, &placed.pose, placed.sigma2, &free);
        let iterations = placed.iterations + fit.iterations;
        let d = surface_score(&fit.pose, points, &s.opts.mixture);
        Some((fit, d, *start, iterations))
    };
    let mut fits: Vec<_> = run_parallel(s.starts, run, &mut |_: &()| {})
        .into_iter()
        .collect::<Option<_>>()?;
    let mut iterations: u32 = fits.iter().map(|f| f.3).sum();
    fits.retain(|f| f.1.is_finite());
    // Ranked by the exact distance: the placed fits are far apart, and their first-order
    // distances are least accurate where they differ.
    fits.sort_by(|a, b| a.1.total_cmp(&b.1));
    let (first, rest) = fits.split_first()?;
    let mut best = fit_em(points, &first.0.pose, first.0.sigma2, s.opts);
    iterations += best.iterations;
    let mut least = score(&best.pose, points, &s.opts.mixture);
    let mut start = first.2;
    // The other placed starts are candidates of the first switch (each with its start).
    let mut pending: Vec<(InitialPose, InitialPose)> =
        rest.iter().map(|f| (f.0.pose, f.2)).collect();
    for _ in 0..s.max_switches.max(u32::from(!pending.is_empty())) {
        if stopped() {
            return None;
        }
        let mut tried = std::mem::take(&mut pending);
        if s.max_switches > 0 {
            tried.extend((s.candidates)(&best.pose).into_iter().map(|c| (c, c)));
        }
        let poses: Vec<InitialPose> = tried.iter().map(|t| t.0).collect();
        let (won, spent) = switch(points, &poses, best.sigma2, least, s.opts);
        iterations += spent;
        let Some((fit, score, i)) = won else {
            break;
        };
        (best, least, start) = (fit, score, tried[i].1);
    }
    Some(((best, least, start), iterations))
}

/// Fits a superquadric to `all_points` from `starts` (see the module docs; the search from the
/// starts probes `probes` too: starts that need no placing, such as the moments of the points
/// that lie on a surface, away from the outliers): the two searches
/// side by side on [`coarse_sample`]`(all_points)` with `opts` (each phase sets its own
/// metric: the options' is not used), from inlier variance `sigma2`, each trying the `candidates` of its
/// fits (similarity candidates) at most `max_switches` times, placing with the [`Coverage`] term
/// of density `coverage` (the fit's [`super::FitOptions::coverage`]); the fit that explains the
/// subsample better by [`Mixture::score`] of its surface distances (the first search's on a tie), then polished for at most
/// [`FINE_ROUNDS`] rounds on every point (on [`FINE_POINTS`] of them spread through a larger
/// cloud; [`LmFit::weights`] are then those points', and [`LmFit::converged`] says whether the
/// search came to rest). `None` when no start gives a finite fit.
pub fn solve(
    all_points: &[DVec3],
    (starts, probes): (&[InitialPose], &[InitialPose]),
    sigma2: f64,
    opts: &LmOptions,
    candidates: impl Fn(&InitialPose) -> Vec<InitialPose> + Sync,
    max_switches: u32,
    coverage: f64,
) -> Option<Solution> {
    let sample = coarse_sample(all_points);
    let opts = &LmOptions {
        metric: Metric::Surface,
        ..*opts
    };
    let search = Search {
        points: &sample,
        starts,
        probes,
        sigma2,
        opts,
        candidates: &candidates,
        max_switches,
        coverage,
    };
    // The two searches side by side; the second gives up when the first passes through its
    // inliers.
    let done = AtomicBool::new(false);
    let kinds = [true, false];
    let run = |&from_starts: &bool, _: &mut dyn FnMut(&())| {
        if from_starts {
            let found = search_from_starts(&search);
            if found
                .as_ref()
                .is_some_and(|((f, _, _), _)| passes_through(f, sample.len(), &opts.mixture))
            {
                done.store(true, Ordering::Relaxed);
            }
            found
        } else {
            placed_search(&search, &done)
        }
    };
    let mut found = run_parallel(&kinds, run, &mut |_: &()| {}).into_iter();
    let (first, second) = (found.next().flatten(), found.next().flatten());
    // Whether the second search ran to its end or gave up depends on the scheduling: once the
    // first passes through its inliers, the second is dropped either way, steps and all.
    let second = second.filter(|_| !done.load(Ordering::Relaxed));
    let mut iterations = 0;
    let mut best: Option<(f64, LmFit, InitialPose)> = None;
    for ((fit, _, start), spent) in [first, second].into_iter().flatten() {
        iterations += spent;
        let d = surface_score(&fit.pose, &sample, &opts.mixture);
        if d.is_finite() && best.as_ref().is_none_or(|b| d < b.0) {
            best = Some((d, fit, start));
        }
    }
    let (_, mut fit, start) = best?;
    if sample.len() < all_points.len() {
        let fine = LmOptions {
            max_rounds: FINE_ROUNDS,
            ..*opts
        };
        let fine_points = spread_sample(all_points, FINE_POINTS);
        let converged = fit.converged;
        fit = fit_em(&fine_points, &fit.pose, fit.sigma2, &fine);
        iterations += fit.iterations;
        // The polish is a fixed number of rounds: the fit is at rest when the search was.
        fit.converged |= converged;
    }
    Some(Solution {
        fit,
        start,
        iterations,
    })
}

/// The lean search: the search from the starts alone ([`PROBE_ROUNDS`] EM rounds of the radial
/// distance from each, the best on to rest), without similarity switches or the placed search,
/// on [`coarse_sample`]`(all_points)`; then on to rest on the distance along the normal (the
/// radial distance is biased on elongated shapes). What a caller that weighs many
/// candidate fits uses (the pieces a whole object is assembled from, [`crate::model::parts`]);
/// [`solve`] is the whole search. `None` when no start gives a finite fit.
pub fn solve_lean(
    all_points: &[DVec3],
    starts: &[InitialPose],
    sigma2: f64,
    opts: &LmOptions,
) -> Option<Solution> {
    let sample = coarse_sample(all_points);
    let radial = LmOptions {
        metric: Metric::Radial,
        ..*opts
    };
    let ((fit, _, start), mut iterations) =
        probe_and_continue(&sample, starts, sigma2, &radial, false)?;
    let polish = LmOptions {
        metric: Metric::Normal,
        ..*opts
    };
    let fit = fit_em(&sample, &fit.pose, fit.sigma2, &polish);
    iterations += fit.iterations;
    Some(Solution {
        fit,
        start,
        iterations,
    })
}

/// The carrier a fit with local DOFs may start its membrane from instead of the fitted
/// superquadric: an ellipsoid (exponents held at the starts', 1 for moments starts) placed from
/// each of `starts` with the [`Coverage`] term of density `coverage` and then fitted without it, the one nearest the
/// points of [`coarse_sample`]`(all_points)` by [`Mixture::score`]. A superquadric fitted
/// alone can take exponents near their bounds (a box, an octahedron) whose tessellation crowds
/// its nodes onto edges and corners, and a membrane on it reaches the points badly; a rounder
/// carrier spreads them evenly. `None` when no start gives a finite fit.
pub fn ellipsoid_carrier(
    all_points: &[DVec3],
    starts: &[InitialPose],
    sigma2: f64,
    opts: &LmOptions,
    coverage: f64,
) -> Option<LmFit> {
    let sample = coarse_sample(all_points);
    let points = &sample[..];
    let coverage = Coverage::new(points, coverage);
    let placing = LmOptions {
        metric: Metric::Normal,
        tolerance: PLACING_TOLERANCE,
        hold_exponents: true,
        ..*opts
    };
    let fitting = LmOptions {
        metric: Metric::Normal,
        hold_exponents: true,
        ..*opts
    };
    let run = |start: &InitialPose, _: &mut dyn FnMut(&())| {
        let placed = fit_em_with(points, start, sigma2, &placing, coverage.as_ref());
        let fit = fit_em(points, &placed.pose, placed.sigma2, &fitting);
        let d = surface_score(
            &fit.pose,
            points,
            &Mixture {
                outlier_ratio: 0.0,
                ..opts.mixture
            },
        );
        (fit, d)
    };
    run_parallel(starts, run, &mut |_: &()| {})
        .into_iter()
        .filter(|f| f.1.is_finite())
        .min_by(|a, b| a.1.total_cmp(&b.1))
        .map(|f| f.0)
}

#[cfg(test)]
mod tests;
