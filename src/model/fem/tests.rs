use super::*;

/// A smooth but irregular field over the nodes.
fn field(n: usize, seed: f64) -> Vec<DVec3> {
    (0..n)
        .map(|i| {
            let t = i as f64 + seed;
            DVec3::new((t * 0.7).sin(), (t * 1.3).cos(), (t * 0.4 + 1.0).sin())
        })
        .collect()
}

#[test]
fn stiffness_diagonal_is_k_applied_to_unit_vectors() {
    let t = Tessellation::new(9);
    let (w0, w1) = (0.02, 0.7);
    let diag = t.stiffness_diagonal(w0, w1);
    let n = t.node_count();
    for i in [0, 1, 5, 17, n / 2, n - 2, n - 1] {
        let mut e = vec![DVec3::ZERO; n];
        e[i] = DVec3::ONE;
        let mut ke = vec![DVec3::ZERO; n];
        t.apply_stiffness(w0, w1, &e, &mut ke);
        assert!((ke[i].x - diag[i]).abs() <= 1e-12 * diag[i], "node {i}");
        assert!(diag[i] > 0.0);
    }
}

#[test]
fn shifted_solve_satisfies_its_system_and_stops_at_once_from_the_answer() {
    let t = Tessellation::new(12);
    let n = t.node_count();
    let (w0, w1) = (0.01, 0.5);
    // Springs on a third of the nodes, damping nowhere: the membrane alone holds the rest.
    let shift: Vec<f64> = (0..n).map(|i| if i % 3 == 0 { 0.3 } else { 0.0 }).collect();
    let diag = t.stiffness_diagonal(w0, w1);
    let b = field(n, 0.5);
    let mut x = vec![DVec3::ZERO; n];
    let mut cg = CgScratch::default();
    let tol = 1e-12;
    let iterations = t.solve_shifted((w0, w1), &shift, &diag, &b, &mut x, (tol, 5000), &mut cg);
    assert!(
        iterations > 0 && iterations < 5000,
        "{iterations} iterations"
    );
    let mut mx: Vec<DVec3> = x.iter().zip(&shift).map(|(x, s)| *s * *x).collect();
    t.apply_stiffness(w0, w1, &x, &mut mx);
    let residual = mx
        .iter()
        .zip(&b)
        .map(|(m, b)| (*m - *b).abs())
        .sum::<DVec3>();
    let size = b.iter().map(|b| b.abs()).sum::<DVec3>();
    assert!(
        residual.max_element() <= 1e-9 * size.max_element(),
        "{residual}"
    );
    // Warm-started at the answer: nothing to do.
    let again = t.solve_shifted((w0, w1), &shift, &diag, &b, &mut x, (1e-6, 5000), &mut cg);
    assert_eq!(again, 0);
}

#[test]
fn every_edge_has_two_triangles_that_contain_it() {
    let t = Tessellation::new(7);
    let tris = t.triangles();
    assert_eq!(t.edges.len() * 2, tris.len() * 3);
    let mut seen = std::collections::HashSet::new();
    // In the order of the triangles: each edge when its second triangle is reached.
    assert!(t.edges.windows(2).all(|w| w[0][3] <= w[1][3]));
    for &[a, b, t1, t2] in &t.edges {
        assert!(seen.insert((a.min(b), a.max(b))), "edge listed twice");
        assert!(t1 < t2);
        for tri in [tris[t1 as usize], tris[t2 as usize]] {
            assert!(tri.contains(&a) && tri.contains(&b));
        }
    }
}

#[test]
fn grid_signed_powers_equal_the_per_node_ones_bit_for_bit() {
    let shapes = [
        SuperquadricParams::default(),
        SuperquadricParams {
            a: 1.3,
            a1: 0.4,
            a2: 0.9,
            a3: 1.0,
            e1: 0.1,
            e2: 1.93,
        },
    ];
    for k in [3, 8, 31] {
        let t = Tessellation::new(k);
        for q in &shapes {
            let mut grid = Vec::new();
            t.signed_powers(q, &mut grid);
            assert_eq!(grid.len(), t.node_count());
            let bits = |p: &SignedPowers| [p.cu, p.su, p.cv, p.sv].map(f64::to_bits);
            for (i, (g, trig)) in grid.iter().zip(&t.trig).enumerate() {
                assert_eq!(bits(g), bits(&SignedPowers::new(q, trig)), "k {k} node {i}");
            }
        }
    }
}

#[test]
fn grid_walk_visits_every_node_in_order_with_its_grid_index() {
    for k in [3, 4, 17] {
        let t = Tessellation::new(k);
        let mut next = 0;
        t.for_each_grid_node(|i, ring, lon| {
            assert_eq!(i, next);
            assert_eq!((ring, lon), t.grid_index(i), "k {k} node {i}");
            next += 1;
        });
        assert_eq!(next, t.node_count());
    }
}

#[test]
fn grid_rings_cover_every_node_in_order_with_its_longitude_terms() {
    let q = SuperquadricParams::default();
    for k in [3, 4, 17] {
        let t = Tessellation::new(k);
        let mut grid = GridPowers::default();
        t.grid_powers(&q, &mut grid);
        let mut next = 0;
        for ring in 0..k + 2 {
            let (nodes, trig) = t.grid_ring(ring);
            let powers = grid.ring_longitudes(ring);
            assert_eq!(
                (nodes.start, nodes.len()),
                (next, trig.len()),
                "k {k} ring {ring}"
            );
            assert_eq!(powers.len(), trig.len(), "k {k} ring {ring}");
            for (j, i) in nodes.enumerate() {
                assert_eq!(t.grid_index(i).0, ring, "k {k} node {i}");
                // The node's own longitude terms and signed powers.
                assert_eq!(trig[j].ln_cv.to_bits(), t.trig[i].ln_cv.to_bits());
                assert_eq!(trig[j].ln_sv.to_bits(), t.trig[i].ln_sv.to_bits());
                let at = grid.at(&t, i);
                assert_eq!(powers[j], [at.cv, at.sv], "k {k} node {i}");
            }
            next += trig.len();
        }
        assert_eq!(next, t.node_count());
    }
}

#[test]
fn stencil_stiffness_equals_the_element_by_element_product() {
    for k in [3, 4, 12, 31] {
        let t = Tessellation::new(k);
        let q: Vec<DVec3> = (0..t.node_count())
            .map(|i| {
                let x = i as f64;
                DVec3::new((0.7 * x).sin(), (1.3 * x).cos(), (0.29 * x).sin() - 0.2)
            })
            .collect();
        let (mut fast, mut reference) = (
            vec![DVec3::ZERO; t.node_count()],
            vec![DVec3::ZERO; t.node_count()],
        );
        t.apply_stiffness(0.003, 0.7, &q, &mut fast);
        t.apply_stiffness_by_element(0.003, 0.7, &q, &mut reference);
        for (i, (a, b)) in fast.iter().zip(&reference).enumerate() {
            assert!((*a - *b).length() < 1e-13, "k {k} node {i}: {a} vs {b}");
        }
    }
}

#[test]
fn the_flat_ring_stencil_adds_each_row_to_the_bit_as_a_pass_of_its_own() {
    // The reference: one row at a time, node by node, as whole vectors (j ± 1 wrapping).
    let one_row = |w: [f64; 3], x: &[DVec3], out: &mut [DVec3]| {
        let k = x.len();
        for j in 0..k {
            let (before, after) = (x[(j + k - 1) % k], x[(j + 1) % k]);
            out[j] += w[0] * before + w[1] * x[j] + w[2] * after;
        }
    };
    let w = [
        [0.31, -1.7, 0.29],
        [-0.11, 0.45, -0.13],
        [0.07, -0.52, 0.19],
    ];
    for k in [3, 4, 5, 12, 71] {
        let rows: Vec<Vec<DVec3>> = (0..3).map(|r| field(k, 0.37 * r as f64)).collect();
        let start = field(k, 2.5);
        let (mut fast, mut reference) = (start.clone(), start.clone());
        add_ring_stencils(
            [(w[0], &rows[0][..]), (w[1], &rows[1]), (w[2], &rows[2])],
            &mut fast,
        );
        for r in 0..3 {
            one_row(w[r], &rows[r], &mut reference);
        }
        assert_eq!(fast, reference, "k = {k}, three rows");
        let (mut fast, mut reference) = (start.clone(), start);
        add_ring_stencils([(w[1], &rows[1][..])], &mut fast);
        one_row(w[1], &rows[1], &mut reference);
        assert_eq!(fast, reference, "k = {k}, one row");
    }
}

#[test]
fn each_nodes_triangles_are_the_triangles_with_that_corner_in_ascending_order() {
    for k in [3, 4, 9] {
        let t = Tessellation::new(k);
        let nt = &t.node_tris;
        assert_eq!(nt.first.len(), t.node_count() + 1);
        for n in 0..t.node_count() {
            let expected: Vec<u32> = (0..t.tris.len() as u32)
                .filter(|&i| t.tris[i as usize].contains(&(n as u32)))
                .collect();
            assert_eq!(nt.of_node(n), &expected[..], "k = {k}, node {n}");
        }
        assert!(nt.of_node(t.node_count()).is_empty());
    }
    // Corners past the node count are left out.
    let nt = NodeTriangles::of(&[[0, 1, 2], [1, 2, 3]], 3);
    assert_eq!(nt.of_node(1), &[0, 1]);
    assert_eq!(nt.of_node(2), &[0, 1]);
    assert_eq!(nt.incident.len(), 5);
}

#[test]
fn one_nodes_normal_is_that_nodes_entry_of_all_the_normals_to_the_bit() {
    let t = Tessellation::new(17);
    // A lumpy, off-centre surface, so that no two triangles' normals are alike.
    let x: Vec<DVec3> = t
        .trig
        .iter()
        .enumerate()
        .map(|(i, g)| {
            let r = 1.0 + 0.3 * (i as f64 * 0.37).sin();
            DVec3::new(0.2, -0.1, 0.4) + r * DVec3::new(g.cu * g.cv, 0.6 * g.cu * g.sv, g.su)
        })
        .collect();
    let mut all = Vec::new();
    t.vertex_normals(&x, &mut all);
    for (i, n) in all.iter().enumerate() {
        assert_eq!(t.vertex_normal(&x, i), *n, "node {i}");
    }
}

#[test]
fn vertex_normals_of_a_sphere_point_outward_along_the_radius() {
    let t = Tessellation::new(24);
    let x: Vec<DVec3> = t
        .trig
        .iter()
        .map(|g| 2.0 * DVec3::new(g.cu * g.cv, g.cu * g.sv, g.su))
        .collect();
    let mut n = Vec::new();
    t.vertex_normals(&x, &mut n);
    for (i, (p, n)) in x.iter().zip(&n).enumerate() {
        assert!(n.dot(p.normalize()) > 0.995, "node {i}: {n} at {p}");
    }
}

#[test]
fn node_counts_match_the_paper() {
    for (k, n) in [(31, 963), (41, 1683), (51, 2603), (71, 5043)] {
        let t = Tessellation::new(k);
        assert_eq!(t.node_count(), n);
        assert_eq!(
            t.quads.len() + t.north.len() + t.south.len(),
            (k - 1) * k + 2 * k
        );
    }
}

#[test]
fn radau_triangle_rule_integrates_cubics_exactly() {
    // ∫∫_T ξ^a η^b = a! b! / (a + b + 2)!
    let fact = |n: u32| (1..=n).product::<u32>().max(1) as f64;
    for a in 0..=3u32 {
        for b in 0..=(3 - a) {
            let exact = fact(a) * fact(b) / fact(a + b + 2);
            let quad: f64 = radau_triangle_rule()
                .iter()
                .map(|&(x, e, w)| w * x.powi(a as i32) * e.powi(b as i32))
                .sum();
            assert!(
                (quad - exact).abs() < 1e-14,
                "ξ^{a} η^{b}: {quad} vs {exact}"
            );
        }
    }
}

/// Energy of a displacement field by brute-force numerical integration of its interpolant
/// (fine midpoint rule, finite-difference gradients) — independent of the element matrices.
fn brute_energy(
    w0: f64,
    w1: f64,
    q: &[f64],
    region: impl Fn(f64, f64) -> Option<(f64, f64)>,
    a: f64,
    b: f64,
    field: impl Fn(f64, f64, &[f64]) -> f64,
) -> f64 {
    let n = 400;
    let mut e = 0.0;
    let (du, dv) = (a / n as f64, b / n as f64);
    for iu in 0..n {
        for iv in 0..n {
            let (x, y) = ((iu as f64 + 0.5) / n as f64, (iv as f64 + 0.5) / n as f64);
            if let Some((uu, vv)) = region(x, y) {
                let h = 1e-6;
                let d = field(uu, vv, q);
                let gu = (field(uu + h, vv, q) - field(uu - h, vv, q)) / (2.0 * h);
                let gv = (field(uu, vv + h, q) - field(uu, vv - h, q)) / (2.0 * h);
                e += (w1 * (gu * gu + gv * gv) + w0 * d * d) * du * dv;
            }
        }
    }
    0.5 * e
}

#[test]
fn quad_stiffness_matches_brute_force_energy_and_gradient() {
    let (a, b) = (0.3, 0.5);
    let (w0, w1) = (0.7, 1.3);
    let m = quad_element(a, b);
    let k = m.stiffness(w0, w1);
    let q = [0.2, -0.5, 0.9, 0.4];
    // Field of the bilinear interpolant on [0,a]×[0,b] with nodes (0,0),(a,0),(a,b),(0,b).
    let field = |u: f64, v: f64, q: &[f64]| {
        let (x, y) = (u / a, v / b);
        q[0] * (1.0 - x) * (1.0 - y) + q[1] * x * (1.0 - y) + q[2] * x * y + q[3] * (1.0 - x) * y
    };
    let brute = brute_energy(w0, w1, &q, |x, y| Some((x * a, y * b)), a, b, field);
    let fe = 0.5
        * (0..4)
            .map(|i| (0..4).map(|j| q[i] * k[i][j] * q[j]).sum::<f64>())
            .sum::<f64>();
    assert!((fe - brute).abs() < 1e-5 * brute, "{fe} vs {brute}");
    // K q is the gradient of the energy: central differences.
    for i in 0..4 {
        let h = 1e-6;
        let (mut qp, mut qm) = (q, q);
        qp[i] += h;
        qm[i] -= h;
        let e = |q: &[f64; 4]| {
            0.5 * (0..4)
                .map(|i| (0..4).map(|j| q[i] * k[i][j] * q[j]).sum::<f64>())
                .sum::<f64>()
        };
        let fd = (e(&qp) - e(&qm)) / (2.0 * h);
        let kq: f64 = (0..4).map(|j| k[i][j] * q[j]).sum();
        assert!((fd - kq).abs() < 1e-8);
    }
}

#[test]
fn triangle_stiffness_matches_brute_force_energy() {
    let (a, b) = (0.4, 0.25);
    let (w0, w1) = (0.9, 0.6);
    let q = [0.3, -0.8, 0.5];
    for cap in [Cap::North, Cap::South] {
        let k = triangle_element(cap, a, b).stiffness(w0, w1);
        let fe = 0.5
            * (0..3)
                .map(|i| (0..3).map(|j| q[i] * k[i][j] * q[j]).sum::<f64>())
                .sum::<f64>();
        type Field = fn(f64, f64, &[f64]) -> f64;
        type Region = fn(f64, f64) -> Option<(f64, f64)>;
        let (field, region): (Field, Region) = match cap {
            Cap::North => (
                |u, v, q| {
                    let (x, e) = (u / 0.4, v / 0.25);
                    q[0] * (1.0 - x - e) + q[1] * x + q[2] * e
                },
                |x, y| (x + y <= 1.0).then_some((x * 0.4, y * 0.25)),
            ),
            Cap::South => (
                |u, v, q| {
                    let (x, e) = (u / 0.4, v / 0.25);
                    q[0] * (1.0 - x) + q[1] * (x - e) + q[2] * e
                },
                |x, y| (y <= x).then_some((x * 0.4, y * 0.25)),
            ),
        };
        let brute = brute_energy(w0, w1, &q, region, a, b, field);
        assert!(
            (fe - brute).abs() < 5e-3 * brute,
            "{cap:?}: {fe} vs {brute}"
        );
    }
}

#[test]
fn stiffness_is_symmetric_psd_and_constant_field_has_zero_membrane_energy() {
    let t = Tessellation::new(9);
    let n = t.node_count();
    // Assemble K (one component) column by column through apply_stiffness.
    let (w0, w1) = (0.0, 0.4);
    let mut k = vec![vec![0.0; n]; n];
    for j in 0..n {
        let mut e = vec![DVec3::ZERO; n];
        e[j] = DVec3::X;
        let mut out = vec![DVec3::ZERO; n];
        t.apply_stiffness(w0, w1, &e, &mut out);
        for i in 0..n {
            k[i][j] = out[i].x;
        }
    }
    for i in 0..n {
        for j in 0..n {
            assert!((k[i][j] - k[j][i]).abs() < 1e-12);
        }
    }
    // PSD: energy of many pseudo-random vectors is ≥ 0.
    let mut seed = 12345u64;
    for _ in 0..50 {
        let q: Vec<DVec3> = (0..n)
            .map(|_| {
                seed = seed
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                DVec3::splat((seed >> 11) as f64 / (1u64 << 53) as f64 - 0.5)
            })
            .collect();
        assert!(t.strain_energy(w0, w1, &q) >= -1e-12);
        assert!(t.strain_energy(0.3, w1, &q) > 0.0);
    }
    let constant = vec![DVec3::new(0.3, -1.0, 2.0); n];
    assert!(t.strain_energy(0.0, w1, &constant).abs() < 1e-12);
    assert!(t.strain_energy(0.1, w1, &constant) > 0.0);
}

#[test]
fn locate_interpolates_node_coordinates_and_wraps() {
    let t = Tessellation::new(7);
    for (i, &[u, v]) in t.uv.iter().enumerate().skip(1).take(t.node_count() - 2) {
        let p = t.locate(u, v);
        let w: f64 = p.weights.iter().sum();
        assert!((w - 1.0).abs() < 1e-12);
        let at = p
            .nodes
            .iter()
            .zip(p.weights)
            .find(|(_, w)| *w > 0.999)
            .map(|(n, _)| *n as usize);
        assert_eq!(at, Some(i), "node {i} at ({u},{v})");
    }
    // Past the north pole: u = π/2 + δ is u = π/2 − δ half a turn round.
    let (u, v) = Tessellation::wrap(FRAC_PI_2 + 0.1, 0.2);
    assert!((u - (FRAC_PI_2 - 0.1)).abs() < 1e-12 && (v - (0.2 - PI)).abs() < 1e-12);
    let p = t.locate(FRAC_PI_2, 1.0);
    assert_eq!(p.nodes[0] as usize, t.north_pole());
    assert!((p.weights[0] - 1.0).abs() < 1e-12);
}

/// The wrap's shortcut is `rem_euclid` to the bit: inside [0, 2π), at its ends (±0, 2π and
/// the float below it), outside in both directions, and for non-finite input.
#[test]
fn period_is_rem_euclid_bit_for_bit() {
    let below = f64::from_bits(TAU.to_bits() - 1);
    let mut xs = vec![
        0.0, -0.0, TAU, below, -TAU, -below, 1e-300, -1e-300, 1e300, -1e300,
    ];
    xs.extend((-400..400).map(|i| i as f64 * 0.0371 + 0.5));
    for x in xs {
        assert_eq!(
            period(x).to_bits(),
            x.rem_euclid(TAU).to_bits(),
            "x = {x:e}"
        );
    }
    for x in [f64::NAN, f64::INFINITY, f64::NEG_INFINITY] {
        assert!(period(x).is_nan() && x.rem_euclid(TAU).is_nan());
    }
}

#[test]
fn locate_gradients_match_central_differences() {
    let t = Tessellation::new(8);
    let field = |n: usize| DVec3::new(n as f64 * 0.37 % 1.0, (n * n) as f64 * 0.11 % 1.0, 1.0);
    for &(u, v) in &[(0.3, 0.4), (-1.45, 2.0), (1.5, -1.0), (0.0, -3.0)] {
        let p = t.locate(u, v);
        let grad_u: DVec3 = (0..4).map(|i| p.du[i] * field(p.nodes[i] as usize)).sum();
        let grad_v: DVec3 = (0..4).map(|i| p.dv[i] * field(p.nodes[i] as usize)).sum();
        let h = 1e-7;
        let fd_u = (t.locate(u + h, v).interpolate(field) - t.locate(u - h, v).interpolate(field))
            / (2.0 * h);
        let fd_v = (t.locate(u, v + h).interpolate(field) - t.locate(u, v - h).interpolate(field))
            / (2.0 * h);
        assert!(
            (grad_u - fd_u).length() < 1e-5,
            "{grad_u:?} vs {fd_u:?} at ({u},{v})"
        );
        assert!(
            (grad_v - fd_v).length() < 1e-5,
            "{grad_v:?} vs {fd_v:?} at ({u},{v})"
        );
    }
}

#[test]
fn nodal_areas_sum_to_covered_area() {
    let t = Tessellation::new(11);
    let total: f64 = t.node_area.iter().sum();
    let expected =
        (t.k - 1) as f64 * t.k as f64 * t.h_u * t.h_v + 2.0 * t.k as f64 * 0.5 * t.h_u * t.h_v;
    assert!((total - expected).abs() < 1e-12);
    assert_eq!(t.area, total);
    assert!(t.node_area.iter().all(|&a| a > 0.0));
}

#[test]
fn prolong_keeps_a_field_where_the_nodes_coincide_and_interpolates_between() {
    // k = 3 → 15: every coarse ring is every fourth fine ring ((15 + 1) / (3 + 1)), every coarse
    // longitude every fifth fine one (15 / 3), and both share the poles.
    let (coarse, fine) = (Tessellation::new(3), Tessellation::new(15));
    let field: Vec<DVec3> = (0..coarse.node_count())
        .map(|i| DVec3::new(i as f64, (i * i) as f64 * 0.5, -(i as f64).sin()))
        .collect();
    let same = coarse.prolong(&coarse, &field);
    assert_eq!(same, field, "onto itself a field is unchanged");
    let onto = fine.prolong(&coarse, &field);
    assert_eq!(onto.len(), fine.node_count());
    let mut coincident = 0;
    for (i, &[u, v]) in fine.uv.iter().enumerate() {
        if let Some(j) = coarse
            .uv
            .iter()
            .position(|c| (c[0] - u).abs() + (c[1] - v).abs() < 1e-12)
        {
            assert!(
                onto[i].distance(field[j]) < 1e-9,
                "node {i}: {} vs {}",
                onto[i],
                field[j]
            );
            coincident += 1;
        }
        // In between, a convex combination of the coarse values.
        let (lo, hi) = field
            .iter()
            .fold((field[0], field[0]), |(lo, hi), f| (lo.min(*f), hi.max(*f)));
        assert!(onto[i].cmpge(lo - 1e-9).all() && onto[i].cmple(hi + 1e-9).all());
    }
    assert_eq!(coincident, coarse.node_count());
    let constant = vec![DVec3::new(0.25, -1.0, 2.0); coarse.node_count()];
    for d in fine.prolong(&coarse, &constant) {
        assert!(d.distance(constant[0]) < 1e-12);
    }
}

#[test]
fn a_tessellation_is_bounded_by_the_memory_it_takes_and_a_k_past_it_is_named() {
    assert_eq!(MAX_K, 836);
    for k in [MIN_K, 31, MAX_K] {
        assert_eq!(check_k("k", k), Ok(()));
    }
    for (k, says) in [
        (2, "k = 2 is out of range [3, 836]: k = 3 is the coarsest"),
        (
            837,
            "k = 837 is out of range [3, 836]: 700571 nodes would take about 1.1 GB",
        ),
        (100_000, "10000000002 nodes would take about 15 TB"),
        (usize::MAX, "bytes, k = 836 about 1.1 GB"),
    ] {
        let e = check_k("k", k).unwrap_err();
        assert!(e.contains(says) && !e.contains('\n'), "{e}");
    }
    // Built directly, a k past the bound is held to it rather than allocated.
    assert_eq!(Tessellation::new(usize::MAX).k, MAX_K);
}
