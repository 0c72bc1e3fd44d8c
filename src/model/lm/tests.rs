//! Tests of the Levenberg–Marquardt core.

use super::*;
use crate::model::init::InitialPose;
use crate::model::superquadric::MIN_EPSILON;
use crate::synthetic::superquadric_cloud;
use glam::{DQuat, DVec3};

/// The superquadric the tests fit.
pub(crate) fn pose() -> InitialPose {
    crate::model::distance::tests::pose(0.6, 1.4)
}

/// Settings of the tests' fits with outlier prior `outlier_ratio`.
pub(crate) fn options(outlier_ratio: f64) -> LmOptions {
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
        min_epsilon: MIN_EPSILON,
        hold_exponents: false,
        own_sigma2: false,
    }
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
    let points = superquadric_cloud(&truth.shape, truth.translation, truth.rotation, 400, 0.0, 7);
    let mut start = truth;
    start.translation += DVec3::new(0.1, 0.05, -0.08);
    start.rotation = (start.rotation * DQuat::from_rotation_z(0.15)).normalize();
    start.shape.a *= 1.15;
    start.shape.e1 = 1.0;
    start.shape.e2 = 1.0;
    let mut cost = weighted_cost(Metric::Radial, &start, &points, &[]);
    let mut pose = start;
    let mut lambda = engine::INITIAL_DAMPING;
    let opts = options(0.0);
    let problem = plain::Plain::new(&points, &opts, None);
    let total = points.len() as f64;
    for _ in 0..60 {
        let Some(s) = engine::step(
            &problem,
            &pose,
            (cost, &[]),
            (&[], total),
            &mut lambda,
            &opts,
        ) else {
            break;
        };
        let (next, c) = (s.model, s.data + s.extra);
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
fn an_exponent_on_its_bound_stays_there_while_the_rest_converge() {
    // A box: ε below the least allowed exponent, so the fit rests with both on the bound.
    let mut truth = pose();
    truth.shape.e1 = 0.05;
    truth.shape.e2 = 0.05;
    let points = superquadric_cloud(&truth.shape, truth.translation, truth.rotation, 600, 0.0, 4);
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

#[test]
fn the_mixture_score_prefers_the_surface_of_the_inliers_where_the_plain_mean_does_not() {
    let mixture = Mixture {
        outlier_ratio: 0.2,
        outlier_density: 1.0 / 8.0,
        sigma2_floor: 1e-10,
    };
    let mut rng = crate::synthetic::Rng::new(4);
    // 600 inliers with noise 0.01 about surface A and 400 outliers 0.6 away from it; surface B
    // passes between them, every point 0.2 from it.
    let mut on_a: Vec<f64> = (0..600).map(|_| 0.01 * rng.normal()).collect();
    on_a.extend((0..400).map(|_| 0.6 + 0.05 * rng.normal()));
    let on_b: Vec<f64> = (0..1000)
        .map(|i| if i % 2 == 0 { 0.2 } else { -0.2 })
        .collect();
    let plain = |d: &[f64]| d.iter().map(|x| x.abs()).sum::<f64>() / d.len() as f64;
    assert!(plain(&on_b) < plain(&on_a));
    let (a, b) = (mixture.score(&on_a), mixture.score(&on_b));
    assert!(a.is_finite() && b.is_finite());
    assert!(a < b, "surface A scores {a}, surface B {b}");
    // Without an outlier model the score is the Gaussian's: the least mean square wins.
    let gaussian = Mixture {
        outlier_ratio: 0.0,
        ..mixture
    };
    assert!(gaussian.score(&on_b) < gaussian.score(&on_a));
}

#[test]
fn a_start_on_the_object_stays_there_among_heavy_outliers() {
    // 40 % outliers about the object: fitted from the truth, the fit keeps to it when the
    // inliers' variance starts at the start's own and not at one that takes in the outliers.
    use crate::synthetic::{SweepSet, set_cloud};
    for i in [21, 25, 31] {
        let (_, c) = set_cloud(SweepSet::Outliers, i);
        let inliers = &c.points[..c.points.len() - c.outliers];
        let opts = LmOptions {
            metric: Metric::Surface,
            own_sigma2: true,
            ..options(0.2)
        };
        let (lo, hi) = c.points.iter().fold(
            (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY)),
            |(lo, hi), p| (lo.min(*p), hi.max(*p)),
        );
        let extent = hi - lo;
        let opts = LmOptions {
            mixture: Mixture {
                outlier_density: 1.0 / (extent.x * extent.y * extent.z),
                ..opts.mixture
            },
            ..opts
        };
        // A wide first σ² (a tenth of the object's size), as a search starts with.
        let fit = fit_em(&c.points, &c.truth, 0.01 * c.truth.shape.a.powi(2), &opts);
        let mean = |pose: &InitialPose| {
            inliers
                .iter()
                .map(|p| super::super::distance::surface_distance(pose, *p).abs())
                .sum::<f64>()
                / inliers.len() as f64
        };
        let ratio = mean(&fit.pose) / mean(&c.truth);
        assert!(ratio < 1.1, "cloud {i}: inliers at {ratio} times the floor");
    }
}

#[test]
fn the_fitted_variance_is_the_inliers_among_outliers() {
    let mut rng = crate::synthetic::Rng::new(5);
    let sigma = 0.01;
    let mut d: Vec<f64> = (0..800).map(|_| sigma * rng.normal()).collect();
    d.extend((0..400).map(|_| rng.range(-1.0, 1.0)));
    let m = Mixture {
        outlier_ratio: 0.2,
        outlier_density: 1.0,
        sigma2_floor: 1e-12,
    };
    // From the whole spread, EM on σ² alone comes down to the inliers' (per coordinate: a
    // distance's variance is σ², its square's mean over 3 coordinates σ²/3 for a 1-D residual).
    let s = m.fitted_sigma2(
        &d,
        d.iter().map(|d| d * d).sum::<f64>() / (3.0 * d.len() as f64),
    );
    let expected = sigma * sigma / 3.0;
    assert!((s / expected - 1.0).abs() < 0.25, "σ² {s} for {expected}");
    // Without an outlier model it is the start itself.
    let none = Mixture {
        outlier_ratio: 0.0,
        ..m
    };
    assert_eq!(none.fitted_sigma2(&d, 0.5), 0.5);
}
