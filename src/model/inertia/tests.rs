use super::*;

/// `dynamics`' test state, elongated along z (so that it may bend), optionally tapered and
/// bent.
fn state(tess: &Tessellation, deformed: bool) -> ModelState {
    let s = crate::model::dynamics::tests::test_state(tess);
    let deformation = if deformed {
        GlobalDeformation {
            taper: [0.2, -0.1],
            bend: [0.3, 0.15],
        }
    } else {
        GlobalDeformation::IDENTITY
    };
    ModelState {
        shape: SuperquadricParams {
            a1: 0.6,
            a2: 0.5,
            a3: 1.0,
            ..s.shape
        },
        deformation,
        ..s
    }
}

fn moving(tess: &Tessellation) -> Velocity {
    Velocity {
        linear: DVec3::new(0.1, -0.3, 0.2),
        angular: DVec3::new(0.4, 0.2, -0.5),
        axes: DVec3::new(0.05, -0.03, 0.04),
        epsilon: [0.05, -0.04],
        deformation: [0.03, -0.02, 0.05, 0.01],
        local: (0..tess.node_count())
            .map(|i| 0.05 * DVec3::new((i as f64 * 0.3).cos(), (i as f64 * 0.9).sin(), 0.2))
            .collect(),
    }
}

fn all_free() -> DynamicsParams {
    let mut p = DynamicsParams::default();
    p.free.taper = true;
    p.free.bend = true;
    p
}

#[test]
fn velocity_product_term_is_the_second_derivative_of_each_node_along_the_motion() {
    // At constant v (Ω fixed in world, rates constant), ẍ_i = a_i: compare with the second
    // central difference of x_i along q(t) = q ⊕ t v.
    let tess = Tessellation::new(6);
    for deformed in [false, true] {
        let s0 = state(&tess, deformed);
        let v = moving(&tess);
        let at = |t: f64| {
            let mut s = s0.clone();
            let mut w = v.clone();
            advance(&mut s, &mut w, t);
            let mut x = Vec::new();
            s.node_positions(&tess, &mut x);
            x
        };
        let h = 1e-4;
        let (xp, x0, xm) = (at(h), at(0.0), at(-h));
        let rot = rotation_matrix(s0.rotation);
        node_kinematics(&tess, &s0, &v, &mut GridPowers::default(), |i, k| {
            let fd = (xp[i] - 2.0 * x0[i] + xm[i]) / (h * h);
            let a = velocity_product(&rot, &v, i, k);
            assert!(
                (fd - a).length() < 1e-5 * (1.0 + a.length()),
                "node {i}: {a} vs {fd}"
            );
            // And the first derivative is ẋ_i = L_i v.
            let xdot = v.linear + v.angular.cross(k.r) + rot * shape_velocity(&v, i, k);
            let fd1 = (xp[i] - xm[i]) / (2.0 * h);
            assert!((fd1 - xdot).length() < 1e-6, "node {i}: {xdot} vs {fd1}");
        });
    }
}

/// Worst relative drifts of energy, momentum and angular momentum over one unit of time of
/// undamped, force-free motion with step `dt`.
fn drifts(dt: f64) -> (f64, f64, f64, ModelState) {
    let tess = Tessellation::new(8);
    let params = DynamicsParams { dt, ..all_free() };
    let inertia = InertiaParams {
        damping: 0.0,
        ..InertiaParams::default()
    };
    let mut s = state(&tess, true);
    let mut v = moving(&tess);
    let mut ws = InertiaWorkspace::default();
    let forces = NodalForces::new(tess.node_count());
    let energy = |s: &ModelState, v: &Velocity| {
        kinetic_energy(&tess, s, v, &inertia)
            + tess.strain_energy(params.w0, params.w1, &s.displacement)
    };
    let e0 = energy(&s, &v);
    let (p0, l0) = momentum(&tess, &s, &v, &inertia);
    let mass: f64 = tess.node_area.iter().sum::<f64>() * inertia.mass_density;
    let (mut worst_e, mut worst_p, mut worst_l) = (0.0_f64, 0.0_f64, 0.0_f64);
    for _ in 0..(1.0 / dt).round() as usize {
        step(&tess, &mut s, &mut v, &forces, &params, &inertia, &mut ws).expect("finite");
        let (p, l) = momentum(&tess, &s, &v, &inertia);
        worst_e = worst_e.max((energy(&s, &v) - e0).abs() / e0);
        worst_p = worst_p.max((p - p0).length() / (mass * v.linear.length().max(0.1)));
        worst_l = worst_l.max((l - l0).length() / l0.length());
    }
    (worst_e, worst_p, worst_l, s)
}

#[test]
fn undamped_free_motion_conserves_energy_momentum_and_angular_momentum() {
    // No forces, no damping: a spinning, translating, breathing, tapering, bending model with
    // a deformed, moving membrane, for one unit of time. The drifts are the step's O(h):
    // within 0.1 % at h = 2e-3, and about halved at h = 1e-3 (a wrong inertial term would
    // leave an O(1) drift that does not shrink with h).
    let (e1, p1, l1, end) = drifts(2e-3);
    let (e2, p2, l2, _) = drifts(1e-3);
    for (coarse, fine, what) in [
        (e1, e2, "energy"),
        (p1, p2, "momentum"),
        (l1, l2, "angular momentum"),
    ] {
        assert!(coarse < 2e-3, "{what} drift {coarse}");
        assert!(
            fine < 0.7 * coarse,
            "{what} drift {coarse} -> {fine}: not O(h)"
        );
    }
    // The motion did happen: the model turned.
    let tess = Tessellation::new(8);
    assert!(end.rotation.angle_between(state(&tess, true).rotation) > 0.3);
}

#[test]
fn a_force_accelerates_the_centre_of_mass_by_f_over_m() {
    // A model at rest, one point force on one node: Σ m_i ẍ_i = F at once, and after t the
    // centre of mass has moved ½ (F / m) t² (the model also turns and deforms).
    let tess = Tessellation::new(8);
    let params = DynamicsParams {
        dt: 1e-3,
        ..all_free()
    };
    let inertia = InertiaParams {
        damping: 0.0,
        ..InertiaParams::default()
    };
    let mut s = state(&tess, true);
    let mut v = Velocity::zero(tess.node_count());
    let mut ws = InertiaWorkspace::default();
    let mut forces = NodalForces::new(tess.node_count());
    let force = DVec3::new(0.7, -0.2, 0.4);
    forces.force[17] = force;
    let masses: Vec<f64> = tess
        .node_area
        .iter()
        .map(|a| a * inertia.mass_density)
        .collect();
    let mass: f64 = masses.iter().sum();
    let (g, d) = accelerations(&tess, &s, &v, &forces, &params, &inertia, None).unwrap();
    let mut total = DVec3::ZERO;
    let rot = rotation_matrix(s.rotation);
    let at_rest = Velocity::zero(tess.node_count());
    node_kinematics(&tess, &s, &at_rest, &mut GridPowers::default(), |i, k| {
        let mut acc = DVec3::new(g[0], g[1], g[2]) + DVec3::new(g[3], g[4], g[5]).cross(k.r);
        acc += rot
            * (k.p_cols
                .iter()
                .zip(&g[6..])
                .map(|(c, x)| *x * *c)
                .sum::<DVec3>()
                + d[i]);
        total += masses[i] * acc;
    });
    assert!(
        (total - force).length() < 1e-9,
        "Σ m ẍ = {total}, F = {force}"
    );
    let centre = |s: &ModelState| {
        let mut x = Vec::new();
        s.node_positions(&tess, &mut x);
        x.iter().zip(&masses).map(|(x, m)| *m * *x).sum::<DVec3>() / mass
    };
    let c0 = centre(&s);
    let steps = 300;
    for _ in 0..steps {
        step(&tess, &mut s, &mut v, &forces, &params, &inertia, &mut ws).unwrap();
    }
    let t = steps as f64 * params.dt;
    let expected = 0.5 * force / mass * t * t;
    let moved = centre(&s) - c0;
    assert!(
        (moved - expected).length() < 0.01 * expected.length(),
        "moved {moved}, expected {expected}"
    );
}

#[test]
fn damping_makes_energy_fall_and_a_pulled_model_settle() {
    // A spring pulls one node of a model whose superquadric shape is held (a rigid body with
    // a membrane; with K_ss = 0 a free shape would drift along the shape changes that keep
    // the node in place) towards a point; with damping the model swings and comes to rest
    // with the node at the spring's anchor, energy falling throughout. (With the default
    // soft membrane, w1 = 0.1, the last of the stretch the pull leaves in the membrane creeps
    // out over minutes of simulated time; a stiffer one, w1 = 1, settles within 30.)
    let tess = Tessellation::new(8);
    let mut params = DynamicsParams {
        dt: 0.01,
        w0: 0.01,
        w1: 1.0,
        ..DynamicsParams::default()
    };
    params.free.shape = [false; 6];
    let inertia = InertiaParams::default();
    let mut s = ModelState {
        displacement: vec![DVec3::ZERO; tess.node_count()],
        ..state(&tess, false)
    };
    let mut v = Velocity::zero(tess.node_count());
    let mut ws = InertiaWorkspace::default();
    let anchor = DVec3::new(2.0, 1.0, 0.0);
    let node = 20;
    let total = |s: &ModelState, v: &Velocity| {
        let mut x = Vec::new();
        s.node_positions(&tess, &mut x);
        let spring = 0.5 * 4.0 * (anchor - x[node]).length_squared();
        (
            kinetic_energy(&tess, s, v, &inertia)
                + tess.strain_energy(params.w0, params.w1, &s.displacement)
                + spring,
            x[node],
        )
    };
    let (mut last, start) = total(&s, &v);
    let first = last;
    let d0 = (start - anchor).length();
    // Closest approach so far, and how far the node swung back out after it.
    let (mut closest, mut swing_back) = (d0, 0.0_f64);
    for k in 0..3000 {
        let mut x = Vec::new();
        s.node_positions(&tess, &mut x);
        let mut forces = NodalForces::new(tess.node_count());
        forces.force[node] = 4.0 * (anchor - x[node]);
        forces.stiffness[node] = 4.0;
        step(&tess, &mut s, &mut v, &forces, &params, &inertia, &mut ws).expect("finite");
        let (e, at) = total(&s, &v);
        // Energy falls from second to second (within a swing it wobbles by the step's O(ω h):
        // the node's spring is stiff against its light mass).
        if k % 100 == 99 {
            assert!(e < last, "step {k}: energy rose {last} -> {e}");
            last = e;
        }
        let d = (at - anchor).length();
        closest = closest.min(d);
        swing_back = swing_back.max(d - closest);
    }
    // Underdamped: after coming near, the node swings out again by a tenth of the start.
    assert!(
        swing_back > 0.1 * d0,
        "no overshoot: swung back {swing_back} of {d0}"
    );
    let mut x = Vec::new();
    s.node_positions(&tess, &mut x);
    let ke = kinetic_energy(&tess, &s, &v, &inertia);
    let off = (x[node] - anchor).length();
    assert!(off < 0.01 * d0, "came to {off} of the anchor");
    assert!(
        last < 1e-3 * first && ke < 1e-4 * first,
        "energy {last}, kinetic {ke} of {first}"
    );
}
