use super::*;
use crate::model::dynamics::ModelState;
use crate::model::superquadric::SuperquadricParams;
use glam::DQuat;
use std::f64::consts::{FRAC_PI_2, PI, TAU};

fn pseudo_random(n: usize, seed: u64) -> Vec<DVec3> {
    let mut s = seed;
    let mut next = || {
        s = s
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (s >> 11) as f64 / (1u64 << 53) as f64 * 2.0 - 1.0
    };
    (0..n)
        .map(|_| DVec3::new(next(), next(), next()) * 1.5)
        .collect()
}

/// The nodes of a squarish, turned and shifted superquadric on a k-tessellation: a search
/// target with flat faces and near-ties.
fn squarish_nodes(k: usize) -> Vec<DVec3> {
    let tess = Tessellation::new(k);
    let state = ModelState::new(
        &tess,
        DVec3::new(0.1, 0.0, -0.2),
        DQuat::from_rotation_y(0.4),
        SuperquadricParams {
            a: 1.0,
            a1: 1.0,
            a2: 0.7,
            a3: 0.5,
            e1: 0.3,
            e2: 0.5,
        },
    );
    let mut x = Vec::new();
    state.node_positions(&tess, &mut x);
    x
}

#[test]
fn kd_tree_assignment_equals_brute_force() {
    for k in [5, 20, 41] {
        let x = squarish_nodes(k);
        let pts = pseudo_random(3000, k as u64);
        let fast = nearest_indices(&x, &pts);
        let brute = nearest_indices_brute(&x, &pts);
        for (i, (a, b)) in fast.iter().zip(&brute).enumerate() {
            // Equal distances (ties between coincident-distance nodes) are the same answer.
            let (da, db) = (
                x[*a as usize].distance_squared(pts[i]),
                x[*b as usize].distance_squared(pts[i]),
            );
            assert!(
                a == b || da == db,
                "point {i}: kd {a} ({da}) vs brute {b} ({db})"
            );
        }
        let same = fast.iter().zip(&brute).filter(|(a, b)| a == b).count();
        assert!(
            same >= pts.len() - 5,
            "only {same} of {} identical",
            pts.len()
        );
    }
}

/// Searching in query order gives each point the answer of a search in the given order,
/// and the order is a permutation that puts nearby points together; odd inputs (no points,
/// one point, all points equal, non-finite coordinates, no nodes) give the same answers too.
#[test]
fn query_order_gives_the_unordered_answers() {
    let x = squarish_nodes(20);
    let pts = pseudo_random(5000, 7);
    let order = QueryOrder::new(&pts);
    assert_eq!(order.len(), pts.len());
    let mut seen = order.order.clone();
    seen.sort_unstable();
    assert!(seen.iter().enumerate().all(|(j, &i)| i as usize == j));
    assert_eq!(order.nearest_indices(&x), nearest_indices(&x, &pts));
    // Consecutive queries are close: the mean step between them (about 0.23) is a small
    // fraction of that between the points in their given, random order (about 2.0, 0.66 of
    // this cube's side of 3); the spacing of 5000 points in it is about 0.17.
    let step =
        |p: &[DVec3]| p.windows(2).map(|w| w[0].distance(w[1])).sum::<f64>() / (p.len() - 1) as f64;
    assert!(
        step(&order.sorted) < 0.2 * step(&pts),
        "{}",
        step(&order.sorted)
    );
    let mut odd = vec![DVec3::splat(f64::NAN), DVec3::new(f64::INFINITY, 0.0, 1.0)];
    odd.extend_from_slice(&pts[..10]);
    for points in [vec![], vec![DVec3::ONE], vec![DVec3::ONE; 4], odd] {
        let order = QueryOrder::new(&points);
        assert_eq!(order.is_empty(), points.is_empty());
        assert_eq!(order.nearest_indices(&x), nearest_indices(&x, &points));
        assert_eq!(order.nearest_indices(&[]), nearest_indices(&[], &points));
    }
}

/// The coverage springs' targets come from a tree of the data points built once and kept:
/// at every reassignment, as the nodes move, they are a fresh search's answers; a clone
/// (sharing the tree) is equal and answers alike; without coverage springs no tree is built.
#[test]
fn kept_point_tree_gives_fresh_coverage_targets() {
    let tess = Tessellation::new(20);
    let pts = pseudo_random(700, 11);
    let mut range = RangeForces::new(pts.clone(), 1.0, InfluenceMode::NearestNode);
    let mut x = squarish_nodes(20);
    for round in 0..3 {
        range.reassign(&tess, &x);
        assert!(matches!(range.point_tree, PointTree::Built(Some(_))));
        assert_eq!(
            range.node_targets,
            nearest_indices(&pts, &x),
            "round {round}"
        );
        assert_eq!(range.node_targets, nearest_indices_brute(&pts, &x));
        for p in &mut x {
            *p = *p * 1.1 + DVec3::new(0.05, -0.02, 0.03);
        }
    }
    let mut copy = range.clone();
    assert_eq!(copy, range);
    copy.reassign(&tess, &x);
    range.reassign(&tess, &x);
    assert_eq!(copy.node_targets, range.node_targets);
    // With no coverage springs no tree is built.
    let mut bare = RangeForces::new(pts, 1.0, InfluenceMode::NearestNode);
    bare.coverage = 0.0;
    bare.reassign(&tess, &x);
    assert!(bare.node_targets.is_empty());
    assert!(matches!(bare.point_tree, PointTree::Unbuilt));
}

/// A unit sphere on a k-tessellation, its node positions, and three points 0.3 outside it
/// between nodes.
fn unit_sphere_and_points_outside(k: usize) -> (Tessellation, ModelState, Vec<DVec3>, Vec<DVec3>) {
    let tess = Tessellation::new(k);
    let state = ModelState::new(
        &tess,
        DVec3::ZERO,
        DQuat::IDENTITY,
        SuperquadricParams::default(),
    );
    let mut x = Vec::new();
    state.node_positions(&tess, &mut x);
    let dirs = [
        DVec3::new(0.3, 0.5, 0.2),
        DVec3::new(-0.7, 0.1, 0.4),
        DVec3::new(0.1, -0.2, -0.9),
    ];
    let pts = dirs.iter().map(|d| 1.3 * d.normalize()).collect();
    (tess, state, x, pts)
}

#[test]
fn migration_reaches_the_foot_of_the_perpendicular() {
    // Points just outside a unit sphere, between nodes: the nearest surface point is r/|r|.
    let (tess, _, x, pts) = unit_sphere_and_points_outside(24);
    let mut range = RangeForces::new(pts.clone(), 1.0, InfluenceMode::Migrating { rate: 0.5 });
    range.reassign(&tess, &x);
    let before: Vec<f64> = range
        .influence
        .iter()
        .zip(&pts)
        .map(|(inf, r)| inf.at.interpolate(|k| x[k]).distance(*r))
        .collect();
    for _ in 0..100 {
        range.migrate(&tess, &x, None);
    }
    for ((inf, r), b) in range.influence.iter().zip(&pts).zip(before) {
        let xs = inf.at.interpolate(|k| x[k]);
        let d = xs.distance(*r);
        assert!(d <= b, "migration moved away: {b} -> {d}");
        // The true minimum over the faceted surface, by dense sampling of material coordinates.
        let mut best = f64::INFINITY;
        for i in 0..=600 {
            for j in 0..=1200 {
                let (u, v) = (
                    -FRAC_PI_2 + PI * i as f64 / 600.0,
                    -PI + TAU * j as f64 / 1200.0,
                );
                best = best.min(tess.locate(u, v).interpolate(|k| x[k]).distance(*r));
            }
        }
        assert!(
            d - best < 2e-4,
            "migrated distance {d}, minimum {best}, nearest node {b}"
        );
    }
}

#[test]
fn migration_onto_the_continuous_surface_reaches_its_foot_past_the_chords() {
    // Points 0.3 outside a unit sphere, between nodes: the foot is r/|r|, 0.3 away, and the
    // mesh's chords lie farther.
    let (tess, state, x, pts) = unit_sphere_and_points_outside(10);
    let mut exact = RangeForces::new(pts.clone(), 1.0, InfluenceMode::Migrating { rate: 1.0 });
    exact.coverage = 0.0;
    exact.reassign(&tess, &x);
    let mut faceted = exact.clone();
    for _ in 0..50 {
        exact.migrate(&tess, &x, Some(&state.surface()));
        faceted.migrate(&tess, &x, None);
    }
    assert_eq!(exact.surface_offset.len(), pts.len());
    assert!(faceted.surface_offset.is_empty());
    for (i, r) in pts.iter().enumerate() {
        let on_surface = exact.influence_x(i, &x);
        assert!((on_surface.length() - 1.0).abs() < 1e-12);
        let d = on_surface.distance(*r);
        let chord = faceted.influence_x(i, &x).distance(*r);
        assert!((d - 0.3).abs() < 1e-6, "foot {d} away, not 0.3");
        assert!(
            chord > d + 1e-3,
            "the chords are no farther: {chord} vs {d}"
        );
    }
    // The springs' energy sees the same points.
    let e = 0.5 * exact.point_weight(&tess) * 3.0 * 0.09;
    assert!((exact.energy(&tess, &x) - e).abs() < 1e-6 * e);
}

/// A k-tessellated superquadric at the origin with aspect ratios a1, a2 and exponents ε1, ε2
/// (`[a1, a2, e1, e2]`), its state and its node positions.
fn superquadric_nodes(
    k: usize,
    [a1, a2, e1, e2]: [f64; 4],
) -> (Tessellation, ModelState, Vec<DVec3>) {
    let shape = SuperquadricParams {
        a1,
        a2,
        e1,
        e2,
        ..Default::default()
    };
    let tess = Tessellation::new(k);
    let state = ModelState::new(&tess, DVec3::ZERO, DQuat::IDENTITY, shape);
    let mut x = Vec::new();
    state.node_positions(&tess, &mut x);
    (tess, state, x)
}

#[test]
fn the_kept_surface_terms_change_no_migration() {
    // Migrations that keep each point's terms from the last one, and migrations that
    // compute them afresh every time, on a superquadric whose exponents change between
    // them: the same points of influence to the bit, and every kept entry is its point's.
    let (tess, mut state, mut x) = superquadric_nodes(12, [0.9, 0.7, 0.4, 1.5]);
    let mut kept = RangeForces::new(
        pseudo_random(200, 5),
        1.0,
        InfluenceMode::Migrating { rate: 1.0 },
    );
    kept.reassign(&tess, &x);
    let mut fresh = kept.clone();
    for step in 0..12 {
        state.shape.e1 = 0.4 + 0.02 * step as f64;
        state.shape.e2 = 1.5 - 0.03 * step as f64;
        state.node_positions(&tess, &mut x);
        if step == 6 {
            kept.reassign(&tess, &x);
            fresh.reassign(&tess, &x);
        }
        fresh.surface_terms.clear();
        kept.migrate(&tess, &x, Some(&state.surface()));
        fresh.migrate(&tess, &x, Some(&state.surface()));
        assert_eq!(kept.influence, fresh.influence, "step {step}");
        assert_eq!(kept.surface_offset, fresh.surface_offset, "step {step}");
    }
    for (inf, terms) in kept.influence.iter().zip(&kept.surface_terms) {
        if (terms.u, terms.v) == (inf.u, inf.v) {
            assert_eq!(terms.trig, Trig::new(inf.u, inf.v));
        }
    }
    assert!(
        kept.influence
            .iter()
            .zip(&kept.surface_terms)
            .any(|(inf, t)| (t.u, t.v) == (inf.u, inf.v)),
        "no point kept its terms"
    );
}

/// Migration spread over the cores moves every point of influence exactly as migration on
/// one thread does, on the continuous surface (with its kept terms and offsets) and on the
/// mesh, over steps in which the superquadric changes and the points are reassigned. The
/// points are several runs of [`PARALLEL_MIGRATION`], so that rayon splits them.
#[test]
fn parallel_migration_moves_every_point_as_one_thread_does() {
    let (tess, mut state, mut x) = superquadric_nodes(16, [0.8, 1.1, 0.5, 1.3]);
    let points = pseudo_random(8 * PARALLEL_MIGRATION + 37, 11);
    let mut serial = RangeForces::new(points, 1.0, InfluenceMode::Migrating { rate: 1.0 });
    serial.reassign(&tess, &x);
    let mut parallel = serial.clone();
    parallel.parallel = true;
    let mut faceted = (serial.clone(), parallel.clone());
    for step in 0..10 {
        state.shape.e1 = 0.5 + 0.03 * step as f64;
        state.shape.a2 = 1.1 - 0.02 * step as f64;
        state.node_positions(&tess, &mut x);
        if step == 5 {
            for forces in [&mut serial, &mut parallel, &mut faceted.0, &mut faceted.1] {
                forces.reassign(&tess, &x);
            }
        }
        serial.migrate(&tess, &x, Some(&state.surface()));
        parallel.migrate(&tess, &x, Some(&state.surface()));
        assert_eq!(serial.influence, parallel.influence, "step {step}");
        assert_eq!(
            serial.surface_offset, parallel.surface_offset,
            "step {step}"
        );
        assert_eq!(serial.surface_terms, parallel.surface_terms, "step {step}");
        faceted.0.migrate(&tess, &x, None);
        faceted.1.migrate(&tess, &x, None);
        assert_eq!(faceted.0.influence, faceted.1.influence, "step {step}");
        assert!(faceted.1.surface_offset.is_empty());
    }
    // The points did migrate off their nodes, on both surfaces.
    for forces in [&parallel, &faceted.1] {
        let off_nodes = forces
            .influence
            .iter()
            .filter(|inf| inf.at.weights[0] != 1.0)
            .count();
        assert!(
            off_nodes > forces.points().len() / 2,
            "{off_nodes} off nodes"
        );
    }
}

/// Nearest-node springs read their nodes from the compact copy (`on_node`), and give the
/// forces and stiffnesses the general path gives from the points of influence, to the bit,
/// with and without robust weights; migrating points and [`RangeForces::detach`] leave no
/// copy behind, and a detached range adds no spring until it is reassigned.
#[test]
fn springs_on_nodes_match_the_general_path_to_the_bit() {
    let (tess, _, x) = superquadric_nodes(12, [1.0, 0.8, 0.7, 1.3]);
    let general = |range: &RangeForces| {
        let mut slow = range.clone();
        slow.on_node.clear();
        let mut out = NodalForces::new(tess.node_count());
        slow.accumulate(&tess, &x, &mut out);
        out
    };
    for robust in [None, Some(Robust::new(0.1))] {
        let mut range = RangeForces::new(pseudo_random(700, 3), 2.0, InfluenceMode::NearestNode);
        range.robust = robust;
        range.coverage = 0.0;
        range.reassign(&tess, &x);
        assert_eq!(range.on_node.len(), 700);
        let mut fast = NodalForces::new(tess.node_count());
        range.accumulate(&tess, &x, &mut fast);
        assert!(fast == general(&range), "the on-node path differs");
        assert!(fast.stiffness.iter().any(|&k| k > 0.0));

        range.detach();
        assert!(range.influence().is_empty() && range.on_node.is_empty());
        let mut none = NodalForces::new(tess.node_count());
        range.accumulate(&tess, &x, &mut none);
        assert!(
            none == NodalForces::new(tess.node_count()),
            "a detached range pulls"
        );
        range.reassign(&tess, &x);
        let mut again = NodalForces::new(tess.node_count());
        range.accumulate(&tess, &x, &mut again);
        assert_eq!(range.on_node.len(), 700);
        assert!(
            again == general(&range),
            "the reattached on-node path differs"
        );
        // Without robust weights (whose σ² a reassignment moves on) the same springs again.
        assert!(
            range.robust.is_some() || again == fast,
            "reattached springs differ"
        );
    }
    let mut migrating = RangeForces::new(
        pseudo_random(300, 4),
        2.0,
        InfluenceMode::Migrating { rate: 0.5 },
    );
    migrating.reassign(&tess, &x);
    migrating.migrate(&tess, &x, None);
    assert!(migrating.on_node.is_empty());
    assert!(
        migrating
            .influence()
            .iter()
            .any(|inf| inf.at.weights[0] != 1.0)
    );
}

/// The AVX2 build of the step's passes over the nodes (`model::simd`) gives the default
/// build's forces, node positions and state to the bit, over several steps: with the explicit
/// local update sub-stepped, for nearest-node springs with coverage springs and for
/// point-to-plane springs with robust weights, and with the implicit membrane's conjugate
/// gradients. (On a processor without AVX2 both runs take the default build.)
#[test]
fn the_avx2_build_of_a_step_gives_the_default_builds_values_to_the_bit() {
    use crate::model::dynamics::{DynamicsParams, Workspace, step_prepared, tests::test_state};
    use crate::model::simd::without_avx2;
    let tess = Tessellation::new(23);
    let n = tess.node_count();
    let start = test_state(&tess);
    let mut x = Vec::new();
    start.node_positions(&tess, &mut x);
    let cases = [
        (false, None, false),
        (true, Some(Robust::new(0.1)), false),
        (false, None, true),
    ];
    for (plane, robust, implicit_local) in cases {
        let params = DynamicsParams {
            dt: 0.2,
            implicit_local,
            ..Default::default()
        };
        let mut range = RangeForces::new(pseudo_random(900, 5), 2.0, InfluenceMode::NearestNode);
        range.plane = plane;
        range.robust = robust;
        range.reassign(&tess, &x);
        let run = || {
            let (mut state, mut ws) = (start.clone(), Workspace::default());
            let mut forces = NodalForces::new(n);
            let mut reports = Vec::new();
            for _ in 0..3 {
                forces.clear(n);
                range.accumulate(&tess, ws.prepare(&tess, &state), &mut forces);
                reports.push(step_prepared(&tess, &mut state, &forces, &params, &mut ws));
            }
            (state, forces, ws.world_positions().to_vec(), reports)
        };
        let wide = run();
        let default = without_avx2(run);
        assert!(wide.3.iter().all(|r| r.as_ref().is_ok_and(|r| {
            if implicit_local {
                r.local_iterations > 0
            } else {
                r.substeps > 1
            }
        })));
        assert!(wide.0 != start && wide.0.displacement != start.displacement);
        assert!(
            wide.1 == default.1,
            "the spring forces differ (plane {plane})"
        );
        assert!(
            wide.2 == default.2,
            "the node positions differ (plane {plane})"
        );
        assert!(wide.0 == default.0, "the states differ (plane {plane})");
        assert!(
            wide.3 == default.3,
            "the step reports differ (plane {plane})"
        );
    }
}

#[test]
fn weights_make_force_density_independent_of_point_count() {
    let tess = Tessellation::new(10);
    let a = RangeForces::new(pseudo_random(100, 1), 2.0, InfluenceMode::NearestNode);
    let b = RangeForces::new(pseudo_random(400, 1), 2.0, InfluenceMode::NearestNode);
    let area: f64 = tess.node_area.iter().sum();
    assert!((a.point_weight(&tess) * 100.0 - 2.0 * area).abs() < 1e-12);
    assert!((b.point_weight(&tess) * 400.0 - 2.0 * area).abs() < 1e-12);
}
