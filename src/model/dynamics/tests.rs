use super::*;
use crate::model::frame::quat_from_paper;
use crate::model::superquadric::jacobian;

/// A posed, non-trivial superquadric with a small displacement at every node.
pub(crate) fn test_state(tess: &Tessellation) -> ModelState {
    let mut s = ModelState::new(
        tess,
        DVec3::new(0.3, -0.2, 0.5),
        DQuat::from_axis_angle(DVec3::new(0.2, 1.0, -0.4).normalize(), 0.7),
        SuperquadricParams {
            a: 1.3,
            a1: 0.8,
            a2: 1.0,
            a3: 0.6,
            e1: 0.8,
            e2: 1.2,
        },
    );
    for (i, d) in s.displacement.iter_mut().enumerate() {
        *d = 0.01
            * DVec3::new(
                (i as f64 * 0.7).sin(),
                (i as f64 * 1.3).cos(),
                (i as f64 * 0.4).sin(),
            );
    }
    s
}

/// [`test_state`] tapered and bent.
fn deformed_state(tess: &Tessellation) -> ModelState {
    ModelState {
        deformation: GlobalDeformation {
            taper: [0.3, -0.2],
            bend: [0.4, 0.25],
        },
        ..test_state(tess)
    }
}

fn test_forces(tess: &Tessellation) -> NodalForces {
    let mut f = NodalForces::new(tess.node_count());
    for (i, at) in [
        (0.3, 0.4),
        (-0.9, 2.5),
        (1.2, -2.0),
        (1.5, 0.1),
        (-1.5, 1.0),
    ]
    .iter()
    .enumerate()
    {
        let p = tess.locate(at.0, at.1);
        f.add(&p, DVec3::new(1.0 - i as f64, 0.5 * i as f64, 0.3), 0.0);
    }
    f
}

/// Potential of constant point forces: V(q) = −Σ_p f_p · x_p(q). Its negative gradient is f_q.
fn potential(tess: &Tessellation, state: &ModelState, forces: &NodalForces) -> f64 {
    let mut x = Vec::new();
    state.node_positions(tess, &mut x);
    -forces
        .force
        .iter()
        .zip(&x)
        .map(|(f, x)| f.dot(*x))
        .sum::<f64>()
}

/// `all_finite` finds a NaN or an infinity in any coordinate of any vector, and passes
/// finite ones (and none).
#[test]
fn all_finite_finds_every_non_finite_coordinate() {
    assert!(all_finite(&[]));
    let finite: Vec<DVec3> = (0..37)
        .map(|i| DVec3::new(i as f64, -1e300, f64::MIN_POSITIVE))
        .collect();
    assert!(all_finite(&finite));
    for bad in [f64::NAN, f64::INFINITY, f64::NEG_INFINITY] {
        for i in [0, 1, 17, 36] {
            for c in 0..3 {
                let mut v = finite.clone();
                v[i][c] = bad;
                assert!(!all_finite(&v), "{bad} at vector {i}, coordinate {c}");
            }
        }
    }
}

#[test]
fn prepare_gives_the_node_walks_positions_to_the_bit() {
    // Plain, deformed, and with displacements missing at the end (the ring walk's slice
    // and per-node paths), against `node_positions`.
    for k in [3, 8, 31] {
        let tess = Tessellation::new(k);
        let mut short = test_state(&tess);
        short.displacement.truncate(tess.node_count() - k - 1);
        for state in [test_state(&tess), deformed_state(&tess), short] {
            let mut expected = Vec::new();
            state.node_positions(&tess, &mut expected);
            let mut ws = Workspace::default();
            assert_eq!(ws.prepare(&tess, &state), &expected[..], "k = {k}");
            let rt = rotation_matrix(state.rotation).transpose();
            for (p, x) in ws.points.iter().zip(&expected) {
                assert!((*p - rt * (*x - state.translation)).length() < 1e-12);
            }
        }
    }
}

#[test]
fn the_continuous_surface_passes_through_the_nodes_and_lies_on_the_superquadric_between() {
    let tess = Tessellation::new(9);
    // Through the nodes, tapered, bent and displaced.
    let state = deformed_state(&tess);
    let mut x = Vec::new();
    state.node_positions(&tess, &mut x);
    let surface = state.surface();
    for (i, [u, v]) in tess.uv.iter().enumerate() {
        let at = ElementPoint::at_node(i as u32);
        let d = surface.at(*u, *v, &at).distance(x[i]);
        assert!(d < 1e-12, "node {i} at ({u}, {v}) is {d} off the surface");
    }
    // Between the nodes, undeformed and undisplaced: on the superquadric (F = 1) and outside
    // the mesh's chords.
    let state = ModelState::new(&tess, state.translation, state.rotation, state.shape);
    state.node_positions(&tess, &mut x);
    let (surface, r) = (state.surface(), rotation_matrix(state.rotation));
    let mut bulge: f64 = 0.0;
    for i in 0..40 {
        let (u, v) = (
            -1.5 + 3.0 * (i as f64 + 0.37) / 40.0,
            -3.1 + 0.155 * i as f64,
        );
        let at = tess.locate(u, v);
        let p = surface.at(u, v, &at);
        let local = r.transpose() * (p - state.translation);
        let f = crate::model::superquadric::inside_outside(&state.shape, local);
        assert!((f - 1.0).abs() < 1e-9, "F = {f} at ({u}, {v})");
        bulge = bulge.max(p.distance(at.interpolate(|k| x[k])));
    }
    assert!(bulge > 1e-3, "the mesh's chords are the surface: {bulge}");
}

#[test]
fn the_continuous_surfaces_tangents_match_central_differences() {
    let tess = Tessellation::new(9);
    for state in [test_state(&tess), deformed_state(&tess)] {
        let surface = state.surface();
        let x = |u: f64, v: f64| surface.at(u, v, &tess.locate(u, v));
        let h = 1e-6;
        for i in 0..25 {
            // Points inside elements, off the coordinate lines through the axes.
            let (u, v) = (
                -1.4 + 2.8 * (i as f64 + 0.31) / 25.0,
                -3.0 + 0.2437 * i as f64,
            );
            let at = tess.locate(u, v);
            let (p, tangents) = surface.with_tangents(u, v, &at);
            assert!(p.distance(x(u, v)) < 1e-12);
            let (tu, tv) = tangents.expect("regular point");
            let fu = (x(u + h, v) - x(u - h, v)) / (2.0 * h);
            let fv = (x(u, v + h) - x(u, v - h)) / (2.0 * h);
            let scale = 1.0 + fu.length().max(fv.length());
            assert!(
                (tu - fu).length() < 1e-6 * scale,
                "∂x/∂u {tu} vs {fu} at ({u}, {v})"
            );
            assert!(
                (tv - fv).length() < 1e-6 * scale,
                "∂x/∂v {tv} vs {fv} at ({u}, {v})"
            );
        }
        // On the coordinate lines through the axes the tangents are not given.
        let at = tess.locate(0.3, 0.0);
        assert!(surface.with_tangents(0.3, 0.0, &at).1.is_none());
    }
}

#[test]
fn global_generalized_forces_match_central_differences() {
    // Every global DOF, tapering and bending included, for the plain superquadric (at q_T = 0)
    // and a tapered, bent one.
    let tess = Tessellation::new(6);
    let forces = test_forces(&tess);
    for state in [test_state(&tess), deformed_state(&tess)] {
        let fq = generalized_global_forces(&tess, &state, &forces);
        let h = 1e-6;
        for j in 0..NUM_GLOBAL {
            let perturbed = |sign: f64| {
                let mut s = state.clone();
                match j {
                    0..=2 => s.translation[j] += sign * h,
                    3..=6 => {
                        let mut q = quat_to_paper(s.rotation);
                        q[j - 3] += sign * h;
                        s.rotation = quat_from_paper(q).normalize();
                    }
                    7..DEFORM_START => {
                        let mut a = s.shape.to_array();
                        a[j - 7] += sign * h;
                        s.shape = SuperquadricParams::from_array(a);
                    }
                    _ => {
                        let mut t = s.deformation.to_array();
                        t[j - DEFORM_START] += sign * h;
                        s.deformation = GlobalDeformation::from_array(t);
                    }
                }
                potential(&tess, &s, &forces)
            };
            let fd = -(perturbed(1.0) - perturbed(-1.0)) / (2.0 * h);
            assert!(
                (fd - fq[j]).abs() < 1e-6 * (1.0 + fd.abs()),
                "dof {j} at {:?}: f_q {} vs fd {fd}",
                state.deformation,
                fq[j]
            );
        }
    }
}

#[test]
fn local_generalized_forces_match_central_differences_inside_elements() {
    let tess = Tessellation::new(6);
    let state = test_state(&tess);
    let forces = test_forces(&tess);
    let fd_local = generalized_local_forces(&state, &forces);
    let h = 1e-6;
    for node in [0usize, 5, 17, tess.north_pole(), 30] {
        for c in 0..3 {
            let v = |sign: f64| {
                let mut s = state.clone();
                s.displacement[node][c] += sign * h;
                potential(&tess, &s, &forces)
            };
            let fd = -(v(1.0) - v(-1.0)) / (2.0 * h);
            assert!(
                (fd - fd_local[node][c]).abs() < 1e-7,
                "node {node} comp {c}: {} vs {fd}",
                fd_local[node][c]
            );
        }
    }
}

#[test]
fn jacobian_structure_reproduces_the_jacobian() {
    // J_b,c = base_c (α_c,b · φ_c) is the same J as `superquadric::jacobian`.
    let tess = Tessellation::new(9);
    let state = test_state(&tess);
    let alpha = jacobian_coefficients(&state.shape);
    let mut powers = Vec::new();
    tess.signed_powers(&state.shape, &mut powers);
    for (t, pw) in tess.trig.iter().zip(&powers) {
        let jac = jacobian(&state.shape, t);
        let base = [pw.cu * pw.cv, pw.cu * pw.sv, pw.su];
        let phi = log_features(t);
        for b in 0..NUM_SHAPE {
            for c in 0..3 {
                let rebuilt = base[c] * dot3(&alpha[c][b], &phi[c]);
                assert!((rebuilt - jac[b][c]).abs() <= 1e-14 * (1.0 + jac[b][c].abs()));
            }
        }
    }
}

/// Σ κ L_iᵀ L_i + Σ ρ (L_iᵀ n_i)(L_iᵀ n_i)ᵀ and Σ L_iᵀ F_i built from explicit world columns
/// L_i = [I, B_i, R (∂T/∂s J + ∂T/∂A ∂A/∂q_s), R ∂T/∂q_T].
fn explicit_system(
    tess: &Tessellation,
    state: &ModelState,
    forces: &NodalForces,
) -> ([[f64; NUM_GLOBAL]; NUM_GLOBAL], [f64; NUM_GLOBAL]) {
    let mut ws = Workspace::default();
    ws.prepare(tess, state);
    let r = rotation_matrix(state.rotation);
    let q = &state.shape;
    let axes = q.semi_axes();
    let mut gram = [[0.0; NUM_GLOBAL]; NUM_GLOBAL];
    let mut f = [0.0; NUM_GLOBAL];
    for i in 0..tess.node_count() {
        let b = crate::model::frame::b_matrix(&r, state.rotation, ws.points[i]);
        let jac = jacobian(q, &tess.trig[i]);
        let s = crate::model::superquadric::shape(q, &tess.trig[i]);
        let t = state.deformation.jacobian(s, axes.z);
        let d_height = [q.a3, 0.0, 0.0, q.a, 0.0, 0.0];
        let cols: Vec<DVec3> = [DVec3::X, DVec3::Y, DVec3::Z]
            .into_iter()
            .chain(b)
            .chain((0..NUM_SHAPE).map(|k| r * (t.d_point * jac[k] + d_height[k] * t.d_height)))
            .chain(t.d_params.iter().map(|c| r * *c))
            .collect();
        let n = forces.plane_normal[i];
        let force = forces.force[i] + forces.shape_force[i];
        let kappa = forces.stiffness[i] + forces.shape_stiffness[i];
        for a in 0..NUM_GLOBAL {
            f[a] += cols[a].dot(force);
            for bb in 0..NUM_GLOBAL {
                gram[a][bb] += kappa * cols[a].dot(cols[bb])
                    + forces.plane_stiffness[i] * cols[a].dot(n) * cols[bb].dot(n);
            }
        }
    }
    (gram, f)
}

#[test]
fn gram_matrix_equals_explicit_lt_l_sum() {
    // The Gram matrix and forces through the superquadric's moments (plain model, q_T held)
    // and column by column (tapered and bent, or q_T free) equal the sums built from explicit
    // columns; the two paths agree on the plain model.
    let tess = Tessellation::new(5);
    let mut forces = test_forces(&tess);
    for i in 0..tess.node_count() {
        forces.stiffness[i] = 0.1 + (i % 3) as f64;
        forces.shape_stiffness[i] = 0.05 * (i % 2) as f64;
        forces.shape_force[i] = DVec3::new(0.1, -0.2 * (i % 3) as f64, 0.05);
        if i % 4 == 1 {
            // Point-to-plane springs on some nodes, with any unit normal.
            forces.plane_stiffness[i] = 0.5 + (i % 5) as f64;
            forces.plane_normal[i] =
                DVec3::new((i as f64).sin(), 0.3, (0.7 * i as f64).cos()).normalize();
        }
    }
    let held = FreeDofs::default();
    let free = FreeDofs {
        taper: true,
        bend: true,
        ..held
    };
    for (state, dofs) in [
        (test_state(&tess), held),
        (test_state(&tess), free),
        (deformed_state(&tess), held),
        (deformed_state(&tess), free),
    ] {
        let mut ws = Workspace::default();
        ws.prepare(&tess, &state);
        let (m, f, _) = global_system(&tess, &state, &ws, &forces, &dofs);
        let (explicit, explicit_f) = explicit_system(&tess, &state, &forces);
        // The moments path leaves the q_T rows empty: they are held.
        let rows = if state.deformation.is_identity() && !dofs.taper {
            DEFORM_START
        } else {
            NUM_GLOBAL
        };
        for a in 0..rows {
            let tol = |x: f64| 1e-9 * (1.0 + x.abs());
            assert!((f[a] - explicit_f[a]).abs() < tol(explicit_f[a]), "f {a}");
            for b in 0..rows {
                assert!(
                    (m[a][b] - explicit[a][b]).abs() < tol(explicit[a][b]),
                    "({a},{b}) at {:?}, free {dofs:?}",
                    state.deformation
                );
            }
        }
    }
}

/// Relaxes a displaced model with no external force for `steps` steps at Δt far beyond the
/// explicit bound, checking that the strain energy never rises, the quaternion stays unit and
/// the global DOFs stay where they are; returns the final energy over the first and the
/// step reports.
fn relax_unforced(implicit_local: bool, steps: usize) -> (f64, Vec<StepReport>) {
    let tess = Tessellation::new(12);
    let mut state = test_state(&tess);
    for (i, d) in state.displacement.iter_mut().enumerate() {
        *d = 0.2
            * DVec3::new(
                (i as f64 * 2.7).sin(),
                (i as f64 * 0.3).cos(),
                (i as f64).sin(),
            );
    }
    let params = DynamicsParams {
        dt: 5.0,
        w0: 0.01,
        w1: 0.5,
        implicit_local,
        ..Default::default()
    };
    let forces = NodalForces::new(tess.node_count());
    let mut ws = Workspace::default();
    let start = tess.strain_energy(params.w0, params.w1, &state.displacement);
    let mut energy = start;
    let before = state.clone();
    let mut reports = Vec::new();
    for _ in 0..steps {
        reports.push(step(&tess, &mut state, &forces, &params, &mut ws).expect("finite"));
        assert!(state.displacement.iter().all(|d| d.is_finite()));
        let e = tess.strain_energy(params.w0, params.w1, &state.displacement);
        assert!(e <= energy * (1.0 + 1e-12), "energy rose: {energy} -> {e}");
        energy = e;
        assert!((state.rotation.length() - 1.0).abs() < 1e-12);
    }
    // No external force: the global DOFs do not move.
    assert_eq!(state.translation, before.translation);
    assert_eq!(state.rotation, before.rotation);
    (energy / start, reports)
}

#[test]
fn free_model_relaxes_with_falling_energy_and_unit_quaternion() {
    // The explicit update must sub-step, not explode.
    let (ratio, reports) = relax_unforced(false, 200);
    assert!(reports.iter().all(|r| r.substeps > 1));
    assert!(ratio < 1e-3, "{ratio}");
}

#[test]
fn implicit_local_step_is_stable_far_beyond_the_explicit_bound() {
    // One solve a step, and ten steps where the explicit update needs hundreds of sub-steps.
    let (ratio, reports) = relax_unforced(true, 10);
    assert!(
        reports
            .iter()
            .all(|r| r.substeps == 1 && r.local_iterations > 0)
    );
    assert!(ratio < 1e-3, "{ratio}");
}

#[test]
fn implicit_local_step_with_little_damping_reaches_the_springs_equilibrium() {
    // Global DOFs held, κ = 1 springs from every node to a displaced copy of the model:
    // with γ_d → 0 one implicit step is the static equilibrium (I + K) d = Rᵀ(t − c) − s.
    let tess = Tessellation::new(10);
    let state0 = test_state(&tess);
    let mut target_state = state0.clone();
    for (i, d) in target_state.displacement.iter_mut().enumerate() {
        *d += 0.05 * DVec3::new((i as f64).cos(), (i as f64 * 0.5).sin(), 0.3);
    }
    let mut target = Vec::new();
    target_state.node_positions(&tess, &mut target);
    let (forces, _) = springs_to(&tess, &state0, &target);
    let params = DynamicsParams {
        implicit_local: true,
        gamma_local: 1e-12,
        w0: 0.01,
        w1: 0.5,
        free: FreeDofs {
            translation: false,
            rotation: false,
            shape: [false; NUM_SHAPE],
            ..Default::default()
        },
        ..Default::default()
    };
    let mut state = state0.clone();
    step(
        &tess,
        &mut state,
        &forces,
        &params,
        &mut Workspace::default(),
    )
    .expect("finite");
    let d = &state.displacement;
    let mut lhs = d.clone();
    tess.apply_stiffness(params.w0, params.w1, d, &mut lhs);
    // Rᵀ(t − c) − s = d_target, the target's own displacement (same pose and shape).
    let worst = lhs
        .iter()
        .zip(&target_state.displacement)
        .map(|(l, t)| (*l - *t).length())
        .fold(0.0, f64::max);
    assert!(worst < 1e-5, "equilibrium residual {worst}");
    assert!(state.displacement != state0.displacement);
}

#[test]
fn implicit_local_joint_steps_bring_node_springs_to_rest_with_falling_energy() {
    // Global and local DOFs free, springs to a moved, reshaped and displaced copy: the global
    // Gauss–Newton step and the implicit membrane after it (Gauss–Seidel) must not overshoot.
    let tess = Tessellation::new(10);
    let mut target_state = test_state(&tess);
    target_state.translation += DVec3::new(0.05, -0.03, 0.02);
    target_state.shape.a1 *= 1.1;
    for (i, d) in target_state.displacement.iter_mut().enumerate() {
        *d += 0.03 * DVec3::new((i as f64 * 0.9).cos(), (i as f64 * 0.5).sin(), 0.1);
    }
    let mut target = Vec::new();
    target_state.node_positions(&tess, &mut target);
    let params = DynamicsParams {
        implicit_local: true,
        gamma_local: 0.01,
        gamma_global: 0.05,
        w0: 0.01,
        w1: 0.1,
        ..Default::default()
    };
    let mut state = test_state(&tess);
    let mut ws = Workspace::default();
    let total = |state: &ModelState| {
        springs_to(&tess, state, &target).1
            + tess.strain_energy(params.w0, params.w1, &state.displacement)
    };
    let start = total(&state);
    let mut energy = start;
    for _ in 0..40 {
        let (forces, _) = springs_to(&tess, &state, &target);
        step(&tess, &mut state, &forces, &params, &mut ws).expect("finite");
        assert!(state.is_finite());
        let e = total(&state);
        assert!(e <= energy * (1.0 + 1e-9), "energy rose: {energy} -> {e}");
        energy = e;
    }
    assert!(energy < 0.05 * start, "{energy} of {start}");
}

/// Springs κ = 1 from every node to where the same node of `target` is, and their energy.
fn springs_to(tess: &Tessellation, state: &ModelState, target: &[DVec3]) -> (NodalForces, f64) {
    let mut x = Vec::new();
    state.node_positions(tess, &mut x);
    let mut f = NodalForces::new(tess.node_count());
    let mut energy = 0.0;
    for i in 0..x.len() {
        f.force[i] = target[i] - x[i];
        f.stiffness[i] = 1.0;
        energy += 0.5 * (target[i] - x[i]).length_squared();
    }
    (f, energy)
}

#[test]
fn free_taper_and_bend_recover_a_deformed_target_with_falling_energy() {
    // Node springs to a tapered, bent copy of the model: the global step (Gauss–Newton on
    // the springs) must bring q_T from 0 to the target's, the energy falling every step.
    let tess = Tessellation::new(10);
    // Elongated along z, so that the target's bend is well inside its bound.
    let start = ModelState {
        shape: SuperquadricParams {
            a: 1.5,
            a1: 0.5,
            a2: 0.4,
            a3: 1.0,
            e1: 0.8,
            e2: 1.2,
        },
        displacement: vec![DVec3::ZERO; tess.node_count()],
        ..test_state(&tess)
    };
    let truth = ModelState {
        deformation: GlobalDeformation {
            taper: [0.35, -0.25],
            bend: [0.5, 0.3],
        },
        ..start.clone()
    };
    let mut target = Vec::new();
    truth.node_positions(&tess, &mut target);
    let mut params = DynamicsParams::default();
    params.free.local = false;
    params.free.taper = true;
    params.free.bend = true;
    let mut state = start.clone();
    let mut ws = Workspace::default();
    let (_, mut energy) = springs_to(&tess, &state, &target);
    let first = energy;
    for _ in 0..300 {
        let (forces, e) = springs_to(&tess, &state, &target);
        // (Once at rounding level, the energy only wanders there.)
        assert!(
            e <= energy * (1.0 + 1e-9) + 1e-24 * first,
            "energy rose: {energy} -> {e}"
        );
        energy = e;
        step(&tess, &mut state, &forces, &params, &mut ws).expect("finite");
    }
    assert!(energy < 1e-10 * first, "energy {first} -> {energy}");
    for (got, want) in state
        .deformation
        .to_array()
        .iter()
        .zip(truth.deformation.to_array())
    {
        assert!((got - want).abs() < 1e-5, "{:?}", state.deformation);
    }
    // Held, the same springs leave q_T at 0.
    params.free.taper = false;
    params.free.bend = false;
    let mut held = start.clone();
    for _ in 0..20 {
        let (forces, _) = springs_to(&tess, &held, &target);
        step(&tess, &mut held, &forces, &params, &mut ws).expect("finite");
    }
    assert!(held.deformation.is_identity());
}

/// Unit-stiffness forces on every node, `force(along)` from its coordinate along the model's
/// z axis.
fn axial_pull(
    tess: &Tessellation,
    state: &ModelState,
    force: impl Fn(f64) -> DVec3,
) -> NodalForces {
    let mut x = Vec::new();
    state.node_positions(tess, &mut x);
    let mut forces = NodalForces::new(tess.node_count());
    let axis = rotation_matrix(state.rotation) * DVec3::Z;
    for i in 0..x.len() {
        forces.force[i] = force((x[i] - state.translation).dot(axis));
        forces.stiffness[i] = 1.0;
    }
    forces
}

#[test]
fn taper_and_bend_stay_within_bounds_under_any_pull() {
    // Huge opposite pulls on the two ends, sideways: the state stays finite and q_T within
    // its bounds (no point crosses the centre of curvature).
    let tess = Tessellation::new(8);
    let mut state = ModelState {
        displacement: vec![DVec3::ZERO; tess.node_count()],
        ..test_state(&tess)
    };
    let mut params = DynamicsParams::default();
    params.free.taper = true;
    params.free.bend = true;
    let mut ws = Workspace::default();
    for k in 0..200 {
        let side = rotation_matrix(state.rotation) * DVec3::X;
        let forces = axial_pull(&tess, &state, |along| {
            1e4 * along.signum() * side * if k % 50 < 25 { 1.0 } else { -3.0 }
        });
        step(&tess, &mut state, &forces, &params, &mut ws).expect("finite");
        assert!(state.is_finite());
        assert_eq!(
            state.deformation,
            state.deformation.clamped(state.shape.semi_axes())
        );
    }
    assert!(!state.deformation.is_identity());
}

#[test]
fn an_exponent_set_below_the_bound_neither_jumps_to_it_nor_sinks_further() {
    // A box-like shape with ε1 = 0.03 (as the squareness extension leaves one), squeezed and
    // then stretched along z: ε1 may rise, fall back to 0.03, never below it, and does not
    // jump to MIN_EPSILON at the first step.
    use crate::model::superquadric::MIN_EPSILON;
    let tess = Tessellation::new(8);
    let mut state = test_state(&tess);
    state.shape.e1 = 0.03;
    let params = DynamicsParams::default();
    let mut ws = Workspace::default();
    let mut seen = Vec::new();
    for k in 0..60 {
        let axis = rotation_matrix(state.rotation) * DVec3::Z;
        let forces = axial_pull(&tess, &state, |along| {
            along * axis * if k < 30 { -5.0 } else { 5.0 }
        });
        step(&tess, &mut state, &forces, &params, &mut ws).expect("finite");
        assert!(
            state.is_finite() && state.shape.e1 >= 0.03,
            "{:?}",
            state.shape
        );
        seen.push(state.shape.e1);
    }
    assert!(seen[0] < MIN_EPSILON, "{seen:?}");
    assert!(seen.iter().any(|&e| e != 0.03), "ε1 never moved: {seen:?}");
}

#[test]
fn non_finite_force_leaves_state_untouched() {
    let tess = Tessellation::new(5);
    let mut state = test_state(&tess);
    let before = state.clone();
    let mut forces = NodalForces::new(tess.node_count());
    forces.force[3] = DVec3::new(f64::NAN, 0.0, 0.0);
    forces.stiffness[3] = 1.0;
    let err = step(
        &tess,
        &mut state,
        &forces,
        &DynamicsParams::default(),
        &mut Workspace::default(),
    );
    assert!(err.is_err());
    assert_eq!(state, before);
}

#[test]
fn planar_motion_holds_depth_and_turns_only_about_z() {
    let tess = Tessellation::new(8);
    let mut state = test_state(&tess);
    let mut forces = test_forces(&tess);
    for k in forces.stiffness.iter_mut() {
        *k = 1.0;
    }
    let mut params = DynamicsParams::default();
    params.free.planar = true;
    let before = state.clone();
    let mut ws = Workspace::default();
    for _ in 0..5 {
        step(&tess, &mut state, &forces, &params, &mut ws).unwrap();
    }
    assert_eq!(state.translation.z, before.translation.z);
    assert!((state.translation - before.translation).truncate().length() > 1e-6);
    // The relative turn is about world z: it maps ẑ to itself.
    let turn = state.rotation * before.rotation.inverse();
    assert!((turn * DVec3::Z - DVec3::Z).length() < 1e-9, "{turn:?}");
    assert!(turn.to_axis_angle().1.abs() > 1e-6);
    // Without the constraint the same forces turn the model out of the plane.
    let mut free = before.clone();
    params.free.planar = false;
    step(&tess, &mut free, &forces, &params, &mut ws).unwrap();
    let turn = free.rotation * before.rotation.inverse();
    assert!((turn * DVec3::Z - DVec3::Z).length() > 1e-6);
}
