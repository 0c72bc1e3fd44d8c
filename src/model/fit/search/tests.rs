//! Tests of the search for a superquadric's rest state.

use super::*;
use crate::model::lm::tests::{options, pose};
use crate::model::lm::weighted_cost;
use crate::synthetic::superquadric_cloud;
use glam::DVec3;

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
fn the_solve_recovers_the_truth_from_a_far_start_and_a_near_one() {
    let truth = pose();
    let points = superquadric_cloud(&truth.shape, truth.translation, truth.rotation, 300, 0.0, 5);
    let mut far = truth;
    far.translation += DVec3::new(2.0, 0.0, 0.0);
    far.shape.a *= 0.3;
    for starts in [vec![far, truth], vec![far]] {
        let s = solve(
            &points,
            (&starts, &[]),
            0.05,
            &options(0.0),
            |_| Vec::new(),
            2,
            0.1,
        )
        .unwrap();
        assert!(starts.contains(&s.start));
        assert!(
            mean_surface(&s.fit.pose, &points) < 1e-6,
            "{:?}",
            s.fit.pose
        );
        assert!(s.fit.pose.shape.is_finite() && s.fit.cost.is_finite());
    }
    // An empty set of starts has no solution, and no panic.
    assert!(
        solve(
            &points,
            (&[], &[]),
            0.05,
            &options(0.0),
            |_| Vec::new(),
            2,
            0.1
        )
        .is_none()
    );
}

/// Mean |surface distance| of `points` to `pose`.
fn mean_surface(pose: &InitialPose, points: &[DVec3]) -> f64 {
    points
        .iter()
        .map(|p| crate::model::distance::surface_distance(pose, *p).abs())
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
    let polished = solve(
        &points,
        (&[truth], &[]),
        0.01,
        &options(0.0),
        |_| Vec::new(),
        0,
        0.1,
    )
    .unwrap();
    let (before, after) = (
        mean_surface(&radial_only.pose, &points),
        mean_surface(&polished.fit.pose, &points),
    );
    assert!(after < 0.99 * before, "polished {after} vs radial {before}");
    assert!(polished.fit.pose.shape.is_finite() && polished.fit.cost.is_finite());
}

#[test]
fn only_a_fit_through_its_inliers_at_the_floor_ends_the_search() {
    let truth = pose();
    let points = superquadric_cloud(&truth.shape, truth.translation, truth.rotation, 300, 0.0, 8);
    let opts = options(0.2);
    let exact = fit_em(&points, &truth, 0.01, &opts);
    assert!(passes_through(&exact, points.len(), &opts.mixture));
    // The same surface with most points called outliers: not the whole explanation.
    let few = LmFit {
        weights: vec![0.5; points.len()],
        ..exact.clone()
    };
    assert!(!passes_through(&few, points.len(), &opts.mixture));
    // A fit above the floor: another minimum may lie closer.
    let mut off = truth;
    off.shape.a *= 1.02;
    let near = LmFit {
        cost: weighted_cost(Metric::Radial, &off, &points, &[]),
        ..exact
    };
    assert!(!passes_through(&near, points.len(), &opts.mixture));
}
