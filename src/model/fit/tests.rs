use super::relax::{Relaxation, StageClock, similarity_share};
use super::residuals::PARALLEL_DISTANCES;
use super::*;
use crate::model::init::InitialPose;
use crate::model::superquadric::{SuperquadricParams, inside_outside, shape_at};
use crate::synthetic::ridged_egg;
use glam::DQuat;

/// The squareness a dynamics fit could only reach by its extension step: a box below the
/// dynamics' least exponent, fitted by the solved fit alone (its exponents go down to
/// [`LEAST_EPSILON`]) to generated truth.
#[test]
fn the_solved_fit_recovers_a_box_squarer_than_the_dynamics_could_hold() {
    use crate::model::superquadric::{LEAST_EPSILON, MIN_EPSILON};
    let truth = SuperquadricParams {
        a: 1.5,
        a1: 1.0,
        a2: 0.7,
        a3: 0.5,
        e1: 0.04,
        e2: 0.04,
    };
    let rotation = DQuat::from_rotation_z(0.3) * DQuat::from_rotation_x(-0.2);
    let points = crate::synthetic::superquadric_cloud(
        &truth,
        DVec3::new(0.5, -0.3, 1.0),
        rotation,
        1200,
        0.0,
        31,
    );
    let opts = FitOptions {
        global_only: true,
        ..FitOptions::default()
    }
    .for_data();
    let r = fit(&points, &opts, |_| {}).expect("the box fits");
    let q = r.state.shape;
    assert!(r.state.is_finite() && r.options.solver == Solver::Solved);
    assert!(q.e1 < MIN_EPSILON && q.e2 < MIN_EPSILON, "{q:?}");
    assert!(q.e1 >= LEAST_EPSILON && q.e2 >= LEAST_EPSILON, "{q:?}");
    let mut found = q.semi_axes().to_array();
    let mut expected = truth.semi_axes().to_array();
    found.sort_by(f64::total_cmp);
    expected.sort_by(f64::total_cmp);
    for (f, t) in found.iter().zip(expected) {
        assert!((f / t - 1.0).abs() < 0.01, "{found:?} against {expected:?}");
    }
    // The surface passes through the points: a thousandth of the diagonal.
    assert!(r.residuals.mean < 1e-3, "{:?}", r.residuals);
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

/// The settle rule counts at least one changed spring as settled: a point midway between two
/// nodes may flip between them at every rest of a small cloud, where 0.2 % of the points rounds
/// to none.
#[test]
fn a_stage_ends_at_rest_when_at_most_its_share_of_springs_changed_and_at_least_one() {
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
        5
    }));
    assert_eq!(calls, 1);
    // At rest: two springs of 216 changed is not settled, one is (0.2 % of 216 is 0.43).
    assert!(!clock.after_step(resting, &opts, 216, || 2));
    assert!(clock.after_step(resting, &opts, 216, || 1));
    assert!(clock.after_step(resting, &opts, 216, || 0));
    // Of 5000 points, 0.2 % is ten.
    assert!(clock.after_step(resting, &opts, 5000, || 10));
    assert!(!clock.after_step(resting, &opts, 5000, || 11));
    // Every spring changed (the robust weights still sharpening) is not at rest.
    assert!(!clock.after_step(resting, &opts, 216, || 216));
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

/// A cone (generated by its own geometry, not by `model::deform`), turned and moved: the solved
/// fit's tapering recovers its taper and comes far closer than the pure superquadric.
#[test]
fn the_solved_fit_recovers_a_turned_cones_taper() {
    let shape = crate::synthetic::Banana::cone(1.5, 0.6, 0.6);
    let turn = DQuat::from_axis_angle(DVec3::new(0.3, -0.8, 0.5).normalize(), 1.1);
    let points: Vec<DVec3> = shape
        .points(2000, 0.01 * shape.radius, 5)
        .into_iter()
        .map(|p| turn * p + DVec3::new(2.0, -1.0, 0.5))
        .collect();
    let mut o = FitOptions {
        global_only: true,
        ..FitOptions::default()
    }
    .for_data();
    let plain = fit(&points, &o, |_| {}).unwrap();
    o.dynamics.free.taper = true;
    o.dynamics.free.bend = true;
    let r = fit(&points, &o, |_| {}).unwrap();
    assert!(r.converged && r.state.is_finite() && r.options.solver == Solver::Solved);
    // Measured: 0.0304 → 0.0020 of the diagonal (unturned).
    assert!(
        r.residuals.mean < 0.2 * plain.residuals.mean,
        "{:?} against {:?}",
        r.residuals,
        plain.residuals
    );
    let t = r.state.deformation.taper;
    assert!(
        t.iter().all(|t| (t.abs() - 0.6).abs() < 0.12),
        "{:?}",
        r.state.deformation
    );
    let b = r.state.deformation.bend;
    assert!(b[0].hypot(b[1]) < 0.1, "{:?}", r.state.deformation);
}

/// The ridged egg (no superquadric has its five ridges) with the fitter's defaults for a
/// user's cloud, through `solver`.
fn ridged_egg_fit(solver: Solver) -> FitReport {
    let points = ridged_egg(1500, 3);
    let (opts, _) = FitOptions {
        solver,
        ..FitOptions::default().for_data()
    }
    .with_stiffness_from_noise(&points);
    fit(&points, &opts, |_| {}).expect("the ridged egg fits")
}

#[test]
fn a_solved_fit_with_local_dofs_matches_the_dynamics_in_far_fewer_steps() {
    let solved = ridged_egg_fit(Solver::Solved);
    let relaxed = ridged_egg_fit(Solver::Dynamics);
    assert!(solved.converged && solved.state.is_finite());
    let (a, b) = (solved.residuals.mean, relaxed.residuals.mean);
    // Holding the global DOFs costs a little: 1.137e-3 against 1.052e-3 here.
    assert!(a <= 1.1 * b, "solved {a}, dynamics {b}");
    assert!(
        3 * solved.steps < relaxed.steps,
        "solved {} steps, dynamics {}",
        solved.steps,
        relaxed.steps
    );
    // The local DOFs did the work of the ridges: far closer than the superquadric alone.
    let pure_options = FitOptions {
        solver: Solver::Solved,
        global_only: true,
        ..FitOptions::default()
    };
    let pure = fit(&ridged_egg(1500, 3), &pure_options.for_data(), |_| {}).expect("pure");
    let c = pure.residuals.mean;
    assert!(a < 0.5 * c, "with local DOFs {a}, pure {c}");
}

#[test]
fn a_cloud_past_twice_fine_points_fits_with_local_dofs_on_a_spread_of_them() {
    use crate::synthetic::superquadric_cloud;
    let shape = SuperquadricParams {
        a: 2.0,
        a1: 1.0,
        a2: 0.6,
        a3: 0.35,
        e1: 0.7,
        e2: 1.2,
    };
    let n = 2 * super::FINE_POINTS + 5000;
    let points = superquadric_cloud(
        &shape,
        DVec3::new(3.0, -1.0, 2.0),
        glam::DQuat::IDENTITY,
        n,
        0.0,
        17,
    );
    let opts = FitOptions {
        solver: Solver::Solved,
        ..FitOptions::default().for_data()
    };
    let r = fit(&points, &opts, |_| {}).expect("the cloud fits");
    assert!(r.converged && r.state.is_finite());
    // The membrane's chords over a superquadric the solve recovered: about 1e-3 of the
    // diagonal, measured on every point.
    assert!(r.residuals.mean < 3e-3, "{:?}", r.residuals);
    let axes = r.state.shape.semi_axes();
    let mut found = axes.to_array();
    found.sort_by(f64::total_cmp);
    let mut truth = shape.semi_axes().to_array();
    truth.sort_by(f64::total_cmp);
    for (f, t) in found.iter().zip(truth) {
        assert!((f / t - 1.0).abs() < 0.02, "{axes} against {truth:?}");
    }
}

#[test]
fn the_implicit_joint_stage_lowers_the_energy_and_holds_the_global_dofs() {
    let points = ridged_egg(800, 5);
    let norm = Normalization::of(&points);
    let unit: Vec<DVec3> = points.iter().map(|p| norm.unit_point(*p)).collect();
    let base = FitOptions::default().for_data();
    let opts = implicit_joint_options(&base);
    let tess = Tessellation::new(base.k);
    let start = norm.pose_to_unit(&initial_hypotheses(&points, &base)[0]);
    let mut relax = Relaxation::new(&tess, &opts, &unit, &start);
    let energy = |r: &Relaxation| {
        let mut x = Vec::new();
        r.state.node_positions(&tess, &mut x);
        let mut range = r.range.clone();
        range.reassign(&tess, &x);
        range.energy(&tess, &x)
            + tess.strain_energy(opts.dynamics.w0, opts.dynamics.w1, &r.state.displacement)
    };
    let before = energy(&relax);
    let global = (
        relax.state.translation,
        relax.state.rotation,
        relax.state.shape,
    );
    let at_rest = relax
        .run(Stage::Joint, 200, &mut |_| {})
        .expect("the stage runs");
    let after = energy(&relax);
    assert!(at_rest, "rest within 200 steps");
    assert!(relax.steps < 60, "{} steps", relax.steps);
    assert!(relax.state.is_finite());
    assert!(after < 0.5 * before, "energy {before} → {after}");
    assert_eq!(
        global,
        (
            relax.state.translation,
            relax.state.rotation,
            relax.state.shape
        )
    );
}

/// The lean search ends on a generated superquadric's surface, turned and moved, from its
/// moments; its pose in the data's frame.
#[test]
fn the_lean_search_recovers_a_generated_superquadric() {
    let truth = SuperquadricParams {
        a: 2.0,
        a1: 1.0,
        a2: 0.6,
        a3: 0.35,
        e1: 0.6,
        e2: 0.9,
    };
    let rotation = DQuat::from_rotation_y(0.7) * DQuat::from_rotation_z(-0.4);
    let centre = DVec3::new(3.0, -1.0, 0.5);
    let points = crate::synthetic::superquadric_cloud(&truth, centre, rotation, 800, 0.0, 5);
    let opts = FitOptions {
        global_only: true,
        ..FitOptions::default()
    }
    .for_data();
    let pose = fit_lean(&points, &opts).expect("fits");
    assert!(pose.translation.distance(centre) < 0.01, "{pose:?}");
    let worst = points
        .iter()
        .map(|p| crate::model::distance::surface_distance(&pose, *p).abs())
        .fold(0.0, f64::max);
    assert!(worst < 0.01 * bounding_diagonal(&points), "{worst}");
}

/// `fit_on` keeps the superquadric it is given: pure, its report is that pose's; with local
/// DOFs, the membrane comes to rest on it (finite, and closer to the points than the pose).
#[test]
fn a_fit_on_a_held_superquadric_keeps_it_and_rests_its_membrane() {
    let points = ridged_egg(1500, 3);
    let pure = FitOptions {
        global_only: true,
        ..FitOptions::default()
    }
    .for_data();
    let pose = fit_lean(&points, &pure).expect("fits");
    let held = fit_on(&points, &pose, &pure).expect("report");
    let back = InitialPose::of(&held.state);
    assert!(back.translation.distance(pose.translation) < 1e-9);
    assert!((back.shape.e1 - pose.shape.e1).abs() < 1e-12);
    assert!(held.state.displacement.iter().all(|d| *d == DVec3::ZERO));
    let local = fit_on(&points, &pose, &FitOptions::default().for_data()).expect("membrane");
    assert!(local.state.is_finite());
    assert_eq!(
        InitialPose::of(&local.state).translation,
        held.state.translation
    );
    assert!(
        local.residuals.mean < 0.5 * held.residuals.mean,
        "membrane {}, superquadric {}",
        local.residuals.mean,
        held.residuals.mean
    );
}
