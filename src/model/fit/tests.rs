use super::*;
use crate::model::superquadric::{SuperquadricParams, inside_outside, shape_at};
use glam::DQuat;

#[test]
fn a_refinement_is_given_up_when_it_runs_off_or_grows_too_long() {
    // Coming closer lowers the least distance; a little farther keeps it.
    assert_eq!(refine_check(0.8, 1.0), Some(0.8));
    assert_eq!(refine_check(1.005, 1.0), Some(1.0));
    // More than 1 % farther than the least, or half again as long: given up.
    assert_eq!(refine_check(1.02, 1.0), None);
    assert!(refine_overgrown(3.01, 2.0));
    assert!(!refine_overgrown(2.99, 2.0));
}

#[test]
fn the_squareness_extension_moves_only_an_exponent_at_the_bound_and_only_closer() {
    use crate::synthetic::superquadric_cloud;
    let tess = Tessellation::new(31);
    let (c, q) = (DVec3::new(0.1, -0.2, 0.3), DQuat::from_rotation_x(0.4));
    // A flat-capped cylinder (ε1 = 0.02, round section), sampled exactly.
    let cylinder = SuperquadricParams {
        a: 1.5,
        a1: 0.6,
        a2: 0.6,
        e1: 0.02,
        ..Default::default()
    };
    let points = superquadric_cloud(&cylinder, c, q, 2000, 0.0, 5);
    let weights = vec![1.0; points.len()];
    let state_with =
        |e1: f64, e2: f64| ModelState::new(&tess, c, q, SuperquadricParams { e1, e2, ..cylinder });
    let distance = |state: &ModelState| {
        let mut x = Vec::new();
        state.node_positions(&tess, &mut x);
        weighted_mean_distance(&tess, &x, &points, &weights)
    };
    // At the bound: ε1 goes below it, to the trial closest to the points, and the surface
    // comes closer; ε2 (round) stays.
    let at_bound = state_with(MIN_EPSILON, 1.0);
    let shape = extend_squareness(&tess, &at_bound, &points, &weights).expect("moved");
    assert!(shape.e1 < MIN_EPSILON && EXTENDED_EPSILONS.contains(&shape.e1));
    assert_eq!(
        (shape.e2, shape.a1, shape.a),
        (1.0, cylinder.a1, cylinder.a)
    );
    let extended = state_with(shape.e1, 1.0);
    for e in EXTENDED_EPSILONS {
        assert!(distance(&extended) <= distance(&state_with(e, 1.0)));
    }
    assert!(distance(&extended) < 0.5 * distance(&at_bound));
    // Above the bound nothing moves, nor at the bound when no trial is closer: a sphere's
    // ε2 at the bound is nearer to 1 than 0.1 already, and squarer is farther.
    assert!(extend_squareness(&tess, &state_with(0.3, 1.0), &points, &weights).is_none());
    let sphere = superquadric_cloud(&SuperquadricParams::default(), c, q, 500, 0.0, 6);
    let round = ModelState::new(
        &tess,
        c,
        q,
        SuperquadricParams {
            e2: MIN_EPSILON,
            ..Default::default()
        },
    );
    assert!(extend_squareness(&tess, &round, &sphere, &vec![1.0; 500]).is_none());
}

/// The growth rule is asked after every step: a refinement whose model runs off in length
/// is given up at the first step that takes it past [`REFINE_MAX_GROWTH`], long before the
/// distance check of [`REFINE_CHECK_EVERY`] steps.
#[test]
fn a_refinement_is_given_up_at_the_first_step_that_makes_it_too_long() {
    use crate::synthetic::superquadric_cloud;
    let tess = Tessellation::new(15);
    let opts = FitOptions::default();
    // Points on an ellipsoid 6 times as long as wide; the model starts as a third of it.
    let long = SuperquadricParams {
        a: 3.0,
        a1: 1.0 / 6.0,
        a2: 1.0 / 6.0,
        ..Default::default()
    };
    let points = superquadric_cloud(&long, DVec3::ZERO, DQuat::IDENTITY, 500, 0.0, 7);
    let start = InitialPose {
        translation: DVec3::ZERO,
        rotation: DQuat::IDENTITY,
        shape: SuperquadricParams { a: 1.0, ..long },
    };
    let longest = |r: &Relaxation| r.state.shape.semi_axes().max_element();
    let refine_for = |budget: u32| {
        let mut relax = Relaxation::new(&tess, &opts, &points, &start);
        relax.refine_least = Some(f64::INFINITY);
        relax.refine_start = longest(&relax);
        let at_rest = relax
            .run(Stage::Refine, budget, &mut |_| {})
            .expect("refine");
        (relax, at_rest)
    };
    let (given_up, at_rest) = refine_for(REFINE_MAX_STEPS);
    assert!(given_up.gave_up && !at_rest);
    let steps = given_up.steps;
    assert!(steps > 1 && steps < REFINE_CHECK_EVERY, "{steps}");
    assert!(longest(&given_up) > REFINE_MAX_GROWTH * given_up.refine_start);
    // One step fewer: not yet too long, and going on.
    let (before, _) = refine_for(steps - 1);
    assert!(!before.gave_up && before.steps == steps - 1);
    assert!(longest(&before) <= REFINE_MAX_GROWTH * before.refine_start);
}

#[test]
fn a_refinement_stalls_when_its_weighted_distance_stops_falling() {
    // No previous check: never stalled; 0.1 % closer or more: going on.
    assert!(!refine_stalled(1.0, None));
    assert!(!refine_stalled(0.998, Some(1.0)));
    assert!(refine_stalled(0.9995, Some(1.0)));
    assert!(refine_stalled(1.02, Some(1.0)));
}

/// Near a surface, the search round the nearest nodes finds the distance to the closest of
/// all triangles, bit for bit; with one node, or none, it still answers.
#[test]
fn point_distances_equal_the_closest_of_all_triangles_near_the_surface() {
    let tess = Tessellation::new(9);
    let state = ModelState::new(
        &tess,
        DVec3::new(0.2, -0.1, 0.3),
        DQuat::from_rotation_x(0.7),
        SuperquadricParams {
            a2: 0.6,
            a3: 0.8,
            e1: 0.4,
            e2: 1.5,
            ..Default::default()
        },
    );
    let mut x = Vec::new();
    state.node_positions(&tess, &mut x);
    // Off every node, a little in and out along a fixed skew direction, and off the
    // midpoints of edges.
    let skew = DVec3::new(0.03, -0.02, 0.025);
    let mut points: Vec<DVec3> = x.iter().flat_map(|p| [*p + skew, *p - skew]).collect();
    points.extend(
        tess.triangles()
            .iter()
            .map(|&[a, b, _]| 0.5 * (x[a as usize] + x[b as usize]) + 0.5 * skew),
    );
    let brute: Vec<f64> = points
        .iter()
        .map(|p| {
            tess.triangles()
                .iter()
                .map(|&[a, b, c]| {
                    let (a, b, c) = (x[a as usize], x[b as usize], x[c as usize]);
                    closest_point_on_triangle(*p, a, b, c).distance_squared(*p)
                })
                .fold(f64::INFINITY, f64::min)
                .sqrt()
        })
        .collect();
    assert_eq!(point_distances(&tess, &x, &points), brute);
    assert!(brute.iter().any(|&d| d > 0.01));
    assert!(point_distances(&tess, &x, &[]).is_empty());
    // Over the cores, in several runs of points each with its own triangles seen: the same
    // distances to the bit.
    let n = 4 * points.len();
    let many: Vec<DVec3> = points.iter().cycle().take(n).copied().collect();
    assert!(n > 4 * PARALLEL_DISTANCES);
    let expected: Vec<f64> = brute.iter().cycle().take(n).copied().collect();
    assert_eq!(point_distances_parallel(&tess, &x, &many), expected);
    assert!(point_distances_parallel(&tess, &x, &[]).is_empty());
}

/// A candidate is refined up to the margin times the chosen fit's placing distance and
/// not past it.
#[test]
fn similarity_candidates_refine_within_the_margin() {
    let chosen = 0.02;
    assert!(refine_candidate(0.5 * chosen, chosen));
    assert!(refine_candidate(SIMILARITY_REFINE_MARGIN * chosen, chosen));
    assert!(!refine_candidate(
        1.001 * SIMILARITY_REFINE_MARGIN * chosen,
        chosen
    ));
    assert!(!refine_candidate(f64::NAN, chosen));
}

#[test]
fn similarity_candidates_share_the_steps_left_within_the_cap() {
    assert_eq!(similarity_share(20_000, 2_000, 4), 4_500);
    assert_eq!(similarity_share(20_000, 2_001, 4), 4_499);
    // All of them together stay within the cap; none is left when it is spent.
    for (max, spent, n) in [(20_000, 1_977, 3), (900, 899, 5), (300, 400, 2), (10, 0, 0)] {
        let share = similarity_share(max, spent, n);
        assert!(
            spent.min(max) + share * n.max(1) as u32 <= max,
            "{max} {spent} {n}"
        );
    }
    assert_eq!(similarity_share(300, 400, 2), 0);
}

#[test]
fn a_stage_ends_when_its_rests_go_round_a_cycle_of_springs() {
    let opts = FitOptions {
        reassign_every: 200,
        tolerance: 1e-5,
        settle_fraction: 0.002,
        ..FitOptions::default()
    };
    let (moving, resting) = (1e-3, 1e-6);
    let mut clock = StageClock::new(Stage::Global);
    // Moving between reattachments: nothing happens; the 200th step reattaches, not over.
    let mut calls = 0;
    for _ in 0..199 {
        assert!(!clock.after_step(moving, &opts, 216, || unreachable!()));
    }
    assert!(!clock.after_step(moving, &opts, 216, || {
        calls += 1;
        (5, 1)
    }));
    assert_eq!(calls, 1);
    // Rests whose reattachments each give new springs (one point of 216 moved: unsettled).
    for signature in [10, 11, 12, 13, 14] {
        assert!(!clock.after_step(resting, &opts, 216, || (1, signature)));
    }
    // Springs of one of the last four rests again: a cycle, the stage is over.
    assert!(clock.after_step(resting, &opts, 216, || (1, 12)));
    // Older than the memory: not a cycle.
    let mut clock = StageClock::new(Stage::Global);
    for signature in [1, 2, 3, 4, 5] {
        assert!(!clock.after_step(resting, &opts, 216, || (1, signature)));
    }
    assert!(!clock.after_step(resting, &opts, 216, || (1, 1)));
    // Alternating springs, A B A: over at the second A.
    let mut clock = StageClock::new(Stage::Refine);
    assert!(!clock.after_step(resting, &opts, 216, || (1, 7)));
    assert!(!clock.after_step(resting, &opts, 216, || (1, 8)));
    assert!(clock.after_step(resting, &opts, 216, || (1, 7)));
    // Every spring changed (the robust weights still sharpening) is no cycle; a settled
    // reattachment ends the stage whatever its springs.
    let mut clock = StageClock::new(Stage::Global);
    assert!(!clock.after_step(resting, &opts, 216, || (216, 7)));
    assert!(!clock.after_step(resting, &opts, 216, || (216, 7)));
    assert!(clock.after_step(resting, &opts, 216, || (0, 9)));
}

#[test]
fn similarity_candidates_of_a_round_shape_are_the_same_surface() {
    // A sphere (ε1 = ε2 = 1, equal semi-axes): the axis candidates (exponents swapped) and
    // the duals about every axis (ε2 = 1, section scale 1) all describe the sphere itself.
    let pose = InitialPose {
        translation: DVec3::new(0.3, -0.2, 0.1),
        rotation: DQuat::from_rotation_y(0.4) * DQuat::from_rotation_x(-0.3),
        shape: SuperquadricParams::default(),
    };
    let candidates = similarity_candidates(&pose);
    // Two axis candidates and a dual about each axis.
    assert_eq!(candidates.len(), 5);
    // Surface points of `pose` lie on the surface of every one of `others`.
    let same_surface = |pose: &InitialPose, others: &[InitialPose]| {
        for c in others {
            for i in 0..200 {
                let (u, v) = (-1.5 + 3.0 * (i % 20) as f64 / 19.0, 0.031 * i as f64);
                let p = pose.translation + pose.rotation * shape_at(&pose.shape, u, v);
                let f = inside_outside(&c.shape, c.rotation.inverse() * (p - c.translation));
                assert!((f - 1.0).abs() < 1e-9, "{c:?}: F = {f}");
            }
        }
    };
    same_surface(&pose, &candidates);
    // An ellipsoid with three different axes: its axis candidates still are the ellipsoid
    // (each semi-axis stays along its world direction).
    let ellipsoid = InitialPose {
        shape: SuperquadricParams {
            a1: 1.0,
            a2: 0.7,
            a3: 0.5,
            ..pose.shape
        },
        ..pose
    };
    same_surface(&ellipsoid, &similarity_candidates(&ellipsoid)[..2]);
    // A long box: no section is alike enough for a dual except about the long axis.
    let long = InitialPose {
        shape: SuperquadricParams {
            a1: 0.3,
            a2: 0.32,
            a3: 1.0,
            e1: 0.3,
            e2: 0.3,
            ..pose.shape
        },
        ..pose
    };
    let candidates = similarity_candidates(&long);
    assert_eq!(candidates.len(), 3);
    let dual = candidates[2];
    assert!((dual.shape.e2 - 1.7).abs() < 1e-12 && (dual.shape.e1 - 0.3).abs() < 1e-12);
}

#[test]
fn the_cross_section_dual_turns_a_square_into_a_diamond_through_the_same_points() {
    let pose = |e2| InitialPose {
        translation: DVec3::new(0.3, -0.2, 0.1),
        rotation: DQuat::from_rotation_y(0.4),
        shape: SuperquadricParams {
            a: 1.0,
            a1: 1.0,
            a2: 1.0,
            a3: 0.6,
            e1: 0.8,
            e2,
        },
    };
    assert_eq!(cross_section_dual(&pose(1.3)), None);
    // A nearly square section's dual is a nearly diamond one through the same points: the
    // square's surface points lie near the dual's surface, and not near the dual unturned.
    let square = pose(0.15);
    let dual = cross_section_dual(&square).unwrap();
    assert!((dual.shape.e2 - 1.85).abs() < 1e-12);
    let unturned = InitialPose {
        rotation: square.rotation,
        ..dual
    };
    let misfit = |other: &InitialPose| {
        let mut worst: f64 = 0.0;
        for i in 0..200 {
            let (u, v) = (-1.2 + 2.4 * (i % 20) as f64 / 19.0, 0.031 * i as f64);
            let p = square.translation + square.rotation * shape_at(&square.shape, u, v);
            let local = other.rotation.inverse() * (p - other.translation);
            let f = inside_outside(&other.shape, local);
            worst = worst.max((f.powf(other.shape.e1 / 2.0) - 1.0).abs());
        }
        worst
    };
    assert!(misfit(&dual) < 0.15, "{}", misfit(&dual));
    assert!(
        misfit(&unturned) > 2.0 * misfit(&dual),
        "{}",
        misfit(&unturned)
    );
}

#[test]
fn joint_k_is_finer_for_a_dense_cloud_on_a_small_share_of_the_surface() {
    let tess = Tessellation::new(31);
    let mut x = Vec::new();
    let sphere = SuperquadricParams::default();
    ModelState::new(&tess, DVec3::ZERO, DQuat::IDENTITY, sphere).node_positions(&tess, &mut x);
    // Points on the sphere's cap z > 1/2 (a quarter of its area), `n` of them on a spiral.
    let cap = |n: usize| -> Vec<DVec3> {
        (0..n)
            .map(|i| {
                let z = 0.5 + 0.5 * (i as f64 + 0.5) / n as f64;
                let phi = i as f64 * 2.399_963;
                let r = (1.0 - z * z).sqrt();
                DVec3::new(r * phi.cos(), r * phi.sin(), z)
            })
            .collect()
    };
    // The cap is a quarter of the area but, nearer the pole, 11 of the 31 rings and the pole:
    // about 342 of the 963 nodes covered, a share of 0.355. 6000 points ask for
    // 6000 / 2 / 0.355 ≈ 8450 nodes (k = 92), 12 000 for more than the cap.
    let k = joint_k(&tess, &x, &cap(6000), 31);
    assert!((88..=96).contains(&k), "k = {k}");
    assert_eq!(joint_k(&tess, &x, &cap(12_000), 31), MAX_JOINT_K);
    // 200 points on that cap cover at most 200 nodes: never coarser than the global stages'.
    assert_eq!(joint_k(&tess, &x, &cap(200), 31), 31);
    assert_eq!(joint_k(&tess, &x, &cap(200), 40), 40);
    // 800 points ask for about 1130 nodes (k = 34), under 1.5 × 963: not worth a second stage.
    assert_eq!(joint_k(&tess, &x, &cap(800), 31), 31);
    assert!(joint_k(&tess, &x, &cap(1500), 31) > 38);
    // No nodes to measure against: the given k.
    assert_eq!(joint_k(&tess, &[], &cap(200), 31), 31);
}
