//! Whole objects split into parts (`model::parts`), pinned to generated truth.

use bevy_deformable_sq::model::fit::{FitOptions, bounding_diagonal, point_distances};
use bevy_deformable_sq::model::parts::{DEFAULT_MAX_PARTS, PartCount, Whole, fit_parts};
use bevy_deformable_sq::model::superquadric::SuperquadricParams;
use bevy_deformable_sq::scene::SceneDef;
use bevy_deformable_sq::synthetic::{superquadric_cloud, union_cloud};
use glam::{DQuat, DVec3};
use std::path::Path;

fn pure() -> FitOptions {
    FitOptions {
        global_only: true,
        ..FitOptions::default()
    }
    .for_data()
}

/// The mean distance of `points` to the nearest fitted part, over their diagonal.
fn mean_error(points: &[DVec3], whole: &Whole) -> f64 {
    let mut best = vec![f64::INFINITY; points.len()];
    let mut x = Vec::new();
    for f in &whole.fits {
        f.state.node_positions(&f.tess, &mut x);
        for (b, d) in best.iter_mut().zip(point_distances(&f.tess, &x, points)) {
            *b = b.min(d);
        }
    }
    best.iter().sum::<f64>() / points.len() as f64 / bounding_diagonal(points)
}

/// A rounded block and a pointed spindle 3 apart, 600 points each.
fn two_apart(noise: f64) -> Vec<DVec3> {
    let a = SuperquadricParams {
        a: 1.0,
        a1: 0.5,
        a2: 0.5,
        a3: 1.0,
        e1: 0.5,
        e2: 1.0,
    };
    let b = SuperquadricParams {
        a: 0.6,
        a1: 1.0,
        a2: 0.7,
        a3: 0.7,
        e1: 1.0,
        e2: 0.4,
    };
    let mut points = superquadric_cloud(&a, DVec3::ZERO, DQuat::IDENTITY, 600, noise, 1);
    points.extend(superquadric_cloud(
        &b,
        DVec3::new(3.0, 0.0, 0.0),
        DQuat::IDENTITY,
        600,
        noise,
        2,
    ));
    points
}

#[test]
fn two_separate_superquadrics_become_two_parts_each_on_its_own() {
    let points = two_apart(0.005);
    let whole = fit_parts(&points, PartCount::Auto(DEFAULT_MAX_PARTS), &pure()).expect("fit");
    assert_eq!(whole.fits.len(), 2);
    let (a, b) = (whole.owner[0], whole.owner[600]);
    assert_ne!(a, b);
    assert!(whole.owner[..600].iter().all(|&o| o == a));
    assert!(whole.owner[600..].iter().all(|&o| o == b));
    let e = mean_error(&points, &whole);
    assert!(e < 0.002, "mean distance {e} of the diagonal");
    // Apart: no joint.
    assert!(whole.joints.is_empty(), "{:?}", whole.joints);
}

#[test]
fn one_noisy_superquadric_stays_one_part() {
    // A part that would only cover noise does not pay for its parameters.
    let q = SuperquadricParams {
        a: 1.0,
        a1: 1.0,
        a2: 0.6,
        a3: 0.8,
        e1: 0.7,
        e2: 1.2,
    };
    for noise in [0.0, 0.01, 0.03] {
        let points = superquadric_cloud(&q, DVec3::ONE, DQuat::IDENTITY, 2000, noise, 5);
        let whole = fit_parts(&points, PartCount::Auto(DEFAULT_MAX_PARTS), &pure()).expect("fit");
        assert_eq!(whole.fits.len(), 1, "noise {noise}");
    }
}

#[test]
fn a_body_and_a_limb_are_two_parts_joined_where_they_meet() {
    // Generated truth: union_cloud seed 200 (a body and one limb, whole surface).
    let cloud = union_cloud(200, 2, 3000, 0.0, false);
    let whole = fit_parts(&cloud.points, PartCount::Auto(DEFAULT_MAX_PARTS), &pure()).expect("fit");
    assert_eq!(whole.fits.len(), 2);
    let e = mean_error(&cloud.points, &whole);
    assert!(e < 0.002, "mean distance {e} of the diagonal");
    assert_eq!(whole.joints.len(), 1);
    let joint = whole.joints[0];
    assert_eq!(joint.parts, [0, 1]);
    // The joint lies where the limb enters the body: inside both true parts' reach.
    let limb = &cloud.parts[1];
    let reach = limb.shape.semi_axes().max_element() * 1.5;
    assert!(joint.at.distance(limb.translation) < reach, "{joint:?}");
}

#[test]
fn an_exact_count_is_met_and_the_same_input_gives_the_same_parts() {
    let points = two_apart(0.0);
    let three = fit_parts(&points, PartCount::Exact(3), &pure()).expect("fit");
    assert_eq!(three.fits.len(), 3);
    let again = fit_parts(&points, PartCount::Exact(3), &pure()).expect("fit");
    assert_eq!(three.owner, again.owner);
    for (a, b) in three.fits.iter().zip(&again.fits) {
        assert_eq!(a.state.translation, b.state.translation);
        assert_eq!(a.state.shape, b.state.shape);
    }
    let e = fit_parts(&points[..25], PartCount::Exact(3), &pure()).unwrap_err();
    assert!(e.to_string().contains("parts = 3 is out of range"), "{e}");
    // A cap is an upper bound: a cloud too small for it is fitted, as one part here.
    let few = fit_parts(&points[..25], PartCount::Auto(DEFAULT_MAX_PARTS), &pure()).expect("fit");
    assert_eq!(few.fits.len(), 1);
    let e = fit_parts(&points[..25], PartCount::Auto(0), &pure()).unwrap_err();
    assert!(e.to_string().contains("parts = 0 is out of range"), "{e}");
}

#[test]
fn the_scene_of_a_whole_object_reads_back_with_its_parts_and_joints() {
    let cloud = union_cloud(200, 2, 1500, 0.0, false);
    let opts = FitOptions::default().for_data();
    let whole = fit_parts(&cloud.points, PartCount::Auto(4), &opts).expect("fit");
    let scene = SceneDef::of_whole(
        Path::new("/data/cloud.obj"),
        Path::new("/data/scenes/x.dsq.ron"),
        &whole,
    );
    let text = scene.to_ron().expect("ron");
    let back = SceneDef::parse(&text, Path::new("x.dsq.ron")).expect("parse");
    assert_eq!(back, scene);
    assert_eq!(back.parts.len(), whole.fits.len());
    assert_eq!(back.joints.len(), whole.joints.len());
    assert!(text.contains("\"../cloud.obj\""), "{text}");
    // Each part keeps its membrane.
    for (part, fit) in back.parts.iter().zip(&whole.fits) {
        assert_eq!(
            part.local.as_ref().map(Vec::len),
            Some(fit.state.displacement.len())
        );
    }
}

/// The count and each part's surface recovered on generated unions (`synthetic::union_cloud`):
/// a body with 1–5 limbs, 3000 points over the whole surface (the count exact), and with 2–3
/// limbs seen from one side (the count within one). Each true part's points lie within 0.5 % of
/// the diagonal of the fitted parts, on average.
#[test]
fn generated_bodies_with_limbs_are_split_into_their_parts() {
    let cases = [
        (2, false),
        (3, false),
        (4, false),
        (5, false),
        (6, false),
        (3, true),
        (4, true),
    ];
    for (parts, view) in cases {
        let cloud = union_cloud(100 * parts as u64, parts, 3000, 0.0, view);
        let whole =
            fit_parts(&cloud.points, PartCount::Auto(DEFAULT_MAX_PARTS), &pure()).expect("fit");
        let found = whole.fits.len();
        let off = if view { 1 } else { 0 };
        assert!(
            found.abs_diff(parts) <= off,
            "{parts} parts, one view {view}: {found}"
        );
        for j in 0..parts {
            let mine: Vec<DVec3> = cloud
                .points
                .iter()
                .zip(&cloud.owner)
                .filter(|(_, o)| **o == j)
                .map(|(p, _)| *p)
                .collect();
            let e = mean_error(&mine, &whole) * bounding_diagonal(&mine)
                / bounding_diagonal(&cloud.points);
            assert!(e < 0.005, "{parts} parts, one view {view}: part {j} at {e}");
        }
    }
}

/// The generated unions the default is measured on (docs/results.md): `cargo test --release
/// --no-default-features --test parts -- --ignored --nocapture`.
#[test]
#[ignore]
fn sweep_generated_unions() {
    for view in [false, true] {
        for parts in 2..=6 {
            for seed in 0..3u64 {
                let cloud = union_cloud(100 * parts as u64 + seed, parts, 3000, 0.0, view);
                let t = std::time::Instant::now();
                let whole = fit_parts(&cloud.points, PartCount::Auto(DEFAULT_MAX_PARTS), &pure())
                    .expect("fit");
                let counts: Vec<usize> = (0..parts)
                    .map(|j| cloud.owner.iter().filter(|&&o| o == j).count())
                    .collect();
                println!(
                    "one view {view}, {parts} parts {counts:?}, seed {seed}: found {}, mean distance {:.4} of the diagonal, {:.2} s",
                    whole.fits.len(),
                    mean_error(&cloud.points, &whole),
                    t.elapsed().as_secs_f64()
                );
            }
        }
    }
}

/// What the parts explain is reported: one part fitted to a sphere and a small one far from it
/// leaves the small one unexplained, and the report says so; split, every point is explained.
#[test]
fn the_share_of_points_explained_is_reported_per_part_and_whole() {
    let sphere = SuperquadricParams::default();
    let small = SuperquadricParams { a: 0.3, ..sphere };
    let mut points = superquadric_cloud(&sphere, DVec3::ZERO, DQuat::IDENTITY, 1500, 0.0, 1);
    points.extend(superquadric_cloud(
        &small,
        DVec3::new(5.0, 0.0, 0.0),
        DQuat::IDENTITY,
        300,
        0.0,
        2,
    ));
    let one = fit_parts(&points, PartCount::Exact(1), &pure()).expect("fit");
    // The small sphere is a sixth of the points.
    assert!(one.explained < 0.9, "one part explains {}", one.explained);
    assert_eq!(one.part_explained.len(), 1);
    assert!((one.part_explained[0] - one.explained).abs() < 1e-12);
    let two = fit_parts(&points, PartCount::Auto(DEFAULT_MAX_PARTS), &pure()).expect("fit");
    assert_eq!(two.fits.len(), 2);
    assert_eq!(two.explained, 1.0);
    assert_eq!(two.part_explained, vec![1.0, 1.0]);
}
