//! One Euler step of eq. (15): the global increment, the local block (explicit with the checked
//! stability bound, or one backward-Euler solve) and the update of the state.

use super::*;

/// Relative residual at which the implicit local solve stops ([`DynamicsParams::implicit_local`]):
/// each component's |b − M d⁺| at most this times its |b|.
pub const IMPLICIT_LOCAL_TOLERANCE: f64 = 1e-6;

/// Conjugate-gradient iterations the implicit local solve takes at most.
pub const IMPLICIT_LOCAL_MAX_ITERATIONS: u32 = 2000;

/// The local block of eq. (15) as one backward-Euler step ([`DynamicsParams::implicit_local`]),
/// from `displacement` into `ws.new_d` (its warm start), at the pose of `rotation`. With
/// `before`, the nodes have moved from there to `ws.world` since the forces were gathered, and
/// each node's force is moved with them: F_i − κ_i Δx_i. Returns the solver's iterations.
pub(super) fn implicit_local_step(
    tess: &Tessellation,
    displacement: &[DVec3],
    (forces, rotation, before): (&NodalForces, DQuat, Option<&[DVec3]>),
    params: &DynamicsParams,
    ws: &mut Workspace,
) -> u32 {
    let n = tess.node_count();
    let rt = rotation_matrix(rotation).transpose();
    ws.local_force.clear();
    ws.local_force.extend((0..n).map(|i| {
        let moved = before.map_or(DVec3::ZERO, |b| ws.world[i] - b[i]);
        rt * (forces.force[i] - forces.stiffness[i] * moved)
    }));
    let (w0, w1) = (params.w0, params.w1);
    let key = (w0, w1, n);
    if ws.k_diagonal_key != Some(key) {
        ws.k_diagonal = tess.stiffness_diagonal(w0, w1);
        ws.k_diagonal_key = Some(key);
    }
    let damping = params.gamma_local / params.dt;
    ws.shift.clear();
    ws.shift
        .extend((0..n).map(|i| damping * tess.node_area[i] + forces.stiffness[i]));
    for i in 0..n {
        ws.local_force[i] += ws.shift[i] * displacement[i];
    }
    tess.solve_shifted(
        (w0, w1),
        &ws.shift,
        &ws.k_diagonal,
        &ws.local_force,
        &mut ws.new_d,
        (IMPLICIT_LOCAL_TOLERANCE, IMPLICIT_LOCAL_MAX_ITERATIONS),
        &mut ws.cg,
    )
}

/// One explicit Euler step of eq. (15), q ← q + Δt C⁻¹ (f_q − K q), with the damping of the
/// module docs. Renormalises the quaternion, moves the largest a_i into a and clamps a_i, ε to
/// their bounds. On error the state is untouched: a step never writes a non-finite value.
pub fn step(
    tess: &Tessellation,
    state: &mut ModelState,
    forces: &NodalForces,
    params: &DynamicsParams,
    ws: &mut Workspace,
) -> Result<StepReport, StepError> {
    ws.prepare(tess, state);
    step_prepared(tess, state, forces, params, ws)
}

/// [`step`] for a state that [`Workspace::prepare`] was last called on, so a loop that needs the
/// node positions for its forces computes them once per step: `prepare` → forces from
/// [`Workspace::world_positions`] → `step_prepared` → `prepare` the new state → …
/// Given a workspace prepared for another state, the step uses that state's node points. After
/// the step the workspace must be prepared again before its positions are read.
pub fn step_prepared(
    tess: &Tessellation,
    state: &mut ModelState,
    forces: &NodalForces,
    params: &DynamicsParams,
    ws: &mut Workspace,
) -> Result<StepReport, StepError> {
    with_avx2!({ step_prepared_body(tess, state, forces, params, ws) })
}

/// [`step_prepared`]'s body, inlined into both of its builds.
#[inline(always)]
pub(super) fn step_prepared_body(
    tess: &Tessellation,
    state: &mut ModelState,
    forces: &NodalForces,
    params: &DynamicsParams,
    ws: &mut Workspace,
) -> Result<StepReport, StepError> {
    let n = tess.node_count();
    assert!(
        forces.force.len() == n && forces.shape_force.len() == n,
        "NodalForces sized for another tessellation"
    );
    let mut report = StepReport {
        substeps: 0,
        dt_critical: f64::INFINITY,
        clamped: false,
        trust_limited: false,
        local_iterations: 0,
    };
    assert!(
        ws.points.len() == n,
        "Workspace not prepared for this tessellation"
    );
    let mut delta = global_increment(tess, state, ws, forces, params)?;
    report.trust_limited = limit_global(&mut delta, state);

    // Local block, explicit Euler with the checked stability bound.
    ws.new_d.clear();
    ws.new_d.extend_from_slice(&state.displacement);
    let implicit = params.free.local && params.implicit_local;
    if implicit {
        // Solved after the global update, at the new pose (below).
        report.substeps = 1;
    } else if params.free.local {
        let (w0, w1, gamma) = (params.w0, params.w1, params.gamma_local);
        let lambda_max = ws.max_rate(tess, w0, w1) / gamma;
        report.dt_critical = if lambda_max > 0.0 {
            2.0 / lambda_max
        } else {
            f64::INFINITY
        };
        let safe = 0.9 * report.dt_critical;
        let mut substeps = if params.dt <= safe {
            1
        } else {
            (params.dt / safe).ceil() as u32
        };
        let mut h = params.dt / substeps as f64;
        if substeps > MAX_SUBSTEPS {
            substeps = MAX_SUBSTEPS;
            h = safe;
            report.clamped = true;
        }
        report.substeps = substeps;
        // Data springs linearised about the start of the step, F(d) = F(d⁰) − κ (d − d⁰), and
        // taken implicitly (they are diagonal): d += h (f − κ (d − d⁰) − K d) / (γ A + h κ).
        let rt = rotation_matrix(state.rotation).transpose();
        ws.local_force.clear();
        ws.local_force.extend(forces.force.iter().map(|f| rt * *f));
        // As one pass over two slices, so that the divisions vectorise.
        ws.substep_scale.clear();
        ws.substep_scale.extend(
            tess.node_area
                .iter()
                .zip(&forces.stiffness)
                .map(|(a, kappa)| h / (gamma * a + h * kappa)),
        );
        for _ in 0..substeps {
            ws.kd.clear();
            ws.kd.resize(n, DVec3::ZERO);
            tess.apply_stiffness(w0, w1, &ws.new_d, &mut ws.kd);
            let nodes = ws
                .new_d
                .iter_mut()
                .zip(&state.displacement)
                .zip(forces.stiffness.iter().zip(&ws.substep_scale))
                .zip(ws.local_force.iter().zip(&ws.kd));
            for (((d, d0), (kappa, scale)), (f, kd)) in nodes {
                let spring = *kappa * (*d - *d0);
                *d += *scale * (*f - spring - *kd);
            }
        }
    }

    if implicit && delta.iter().all(|&x| x == 0.0) {
        report.local_iterations = implicit_local_step(
            tess,
            &state.displacement,
            (forces, state.rotation, None),
            params,
            ws,
        );
    }
    if delta.iter().all(|&x| x == 0.0) {
        // No global force: the global DOFs stay exactly where they are (no renormalisation drift).
        let displacement = std::mem::take(&mut ws.new_d);
        if !all_finite(&displacement) {
            ws.new_d = displacement;
            return Err(StepError::NonFinite(
                "local displacement after the Euler step",
            ));
        }
        ws.new_d = std::mem::replace(&mut state.displacement, displacement);
        return Ok(report);
    }
    let q = quat_to_paper(state.rotation);
    let rotation = quat_from_paper(std::array::from_fn(|j| q[j] + delta[3 + j]));
    if !(rotation.length() > 0.0) {
        return Err(StepError::NonFinite("rotation quaternion"));
    }
    let shape_q = state.shape.to_array();
    let shape = SuperquadricParams::from_array(std::array::from_fn(|j| shape_q[j] + delta[7 + j]))
        .normalized_keeping(&state.shape);
    let deform_q = state.deformation.to_array();
    let deformation = GlobalDeformation::from_array(std::array::from_fn(|j| {
        deform_q[j] + delta[DEFORM_START + j]
    }))
    .clamped(shape.semi_axes());
    let mut new = ModelState {
        translation: state.translation + DVec3::new(delta[0], delta[1], delta[2]),
        rotation: rotation.normalize(),
        shape,
        deformation,
        displacement: std::mem::take(&mut ws.new_d),
    };
    if implicit {
        // Gauss–Seidel: the membrane solved at the new pose, the springs' forces moved there.
        // The positions before go into `kd`, which only the explicit update uses.
        let mut before = std::mem::take(&mut ws.kd);
        before.clear();
        before.extend_from_slice(&ws.world);
        ws.prepare(tess, &new);
        ws.new_d = std::mem::take(&mut new.displacement);
        report.local_iterations = implicit_local_step(
            tess,
            &state.displacement,
            (forces, new.rotation, Some(&before)),
            params,
            ws,
        );
        ws.kd = before;
        new.displacement = std::mem::take(&mut ws.new_d);
    }
    if !new.is_finite() {
        ws.new_d = new.displacement;
        return Err(StepError::NonFinite("state after the Euler step"));
    }
    ws.new_d = std::mem::take(&mut state.displacement);
    *state = new;
    Ok(report)
}
