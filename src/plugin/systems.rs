//! Thin systems over the pure core, one per stage of the paper's loop (see
//! [`DeformableSqSystems`](super::DeformableSqSystems)). Per-model work runs in parallel
//! (`par_iter_mut`).

use super::components::*;
use crate::model::dynamics::{step, step_prepared};
use crate::model::inertia::{self, Velocity};
use crate::model::joint::{JointLoad, MAX_REACH, MULTIPLIER_RATE, inertial_multiplier_rate};
use crate::model::superquadric::SuperquadricParams;
use bevy::math::DVec3;
use bevy::prelude::*;

/// True when the model takes a step this run.
fn stepping(control: &SimControl) -> bool {
    !control.frozen && (!control.paused || control.step_requests > 0)
}

/// The first non-finite component of a model, by name.
pub fn first_non_finite(
    rigid: &RigidState,
    shape: &GlobalShape,
    local: &LocalDofs,
) -> Option<&'static str> {
    if !(rigid.translation.is_finite() && rigid.rotation.is_finite()) {
        Some("RigidState")
    } else if !SuperquadricParams::from(*shape).is_finite() {
        Some("GlobalShape")
    } else if !local.displacement.iter().all(|d| d.is_finite()) {
        Some("LocalDofs")
    } else {
        None
    }
}

/// Stage `Prepare`: shares tessellations, carries the local DOFs onto a changed mesh (sizes them
/// to it when they fit neither), sizes the buffers to the mesh, records
/// the spawn state, carries out resets, and freezes any model whose state was made non-finite
/// from outside (naming the entity and component).
pub fn prepare(
    mut cache: ResMut<FemMeshCache>,
    mut models: Query<(
        Entity,
        &mut FemMesh,
        &mut RigidState,
        &mut GlobalShape,
        &mut LocalDofs,
        &mut SimControl,
        &mut Scratch,
        Option<&mut RangeData>,
        Option<&mut Inertia>,
    )>,
) {
    for (
        entity,
        mut fem,
        mut rigid,
        mut shape,
        mut local,
        mut control,
        mut scratch,
        mut range,
        inertia,
    ) in &mut models
    {
        if fem.get().is_none() {
            let new = cache.get(fem.k);
            // Re-tessellated (`k` changed): the membrane, and the one a reset goes back to, are
            // carried onto the new mesh (`Tessellation::prolong`), and the range springs are
            // reattached on it.
            if let Some(old) = fem.tessellation.replace(new.clone()) {
                let carry = |l: &mut LocalDofs| {
                    if l.displacement.len() == old.node_count() {
                        l.displacement = new.prolong(&old, &l.displacement);
                    }
                };
                carry(&mut local);
                if let Some((_, _, initial)) = scratch.initial.as_mut() {
                    carry(initial);
                }
                if let Some(range) = range.as_mut() {
                    range.forces.detach();
                }
            }
        }
        let Some(tess) = fem.get().cloned() else {
            continue;
        };
        let n = tess.node_count();
        let mut inertia = inertia;
        // A velocity sized for another mesh (the model was re-tessellated): the old nodes' rates
        // mean nothing on the new one, so the model starts again at rest. (An empty one is a
        // velocity set at spawn, kept.)
        if let Some(inertia) = inertia.as_mut()
            && !inertia.velocity.local.is_empty()
            && inertia.velocity.local.len() != n
        {
            inertia.velocity = Velocity::zero(n);
        }
        if local.displacement.len() != n {
            local.displacement = vec![DVec3::ZERO; n];
            scratch.initial = None;
            if let Some(mut range) = range {
                range.forces.detach();
            }
        } else if control.reset_requested {
            if let Some((r, s, l)) = scratch.initial.clone() {
                *rigid = r;
                *shape = s;
                *local = l;
            }
            if let Some(inertia) = inertia.as_mut() {
                inertia.velocity = Velocity::zero(n);
            }
            if let Some(mut range) = range {
                range.forces.detach();
            }
            *control = SimControl {
                paused: control.paused,
                ..default()
            };
        }
        if scratch.initial.is_none() {
            scratch.initial = Some((*rigid, *shape, local.clone()));
        }
        if scratch.forces.force.len() != n {
            scratch.forces.clear(n);
        }
        if !control.frozen
            && let Some(what) = first_non_finite(&rigid, &shape, &local)
        {
            control.frozen = true;
            control.error = Some(format!(
                "{what} is not finite; the model is frozen until reset"
            ));
            error!("deformable superquadric {entity}: {what} is not finite; frozen until reset");
        }
    }
}

/// Stage `Reassign`: every `reassign_every` steps (and before the first step), reattaches each
/// range point to its point of influence (nearest node, k-d tree).
pub fn reassign(
    mut models: Query<(
        ModelStateRef,
        &ModelSettings,
        &SimControl,
        &mut Scratch,
        &mut RangeData,
    )>,
) {
    models
        .par_iter_mut()
        .for_each(|(model, settings, control, mut scratch, mut range)| {
            let Some(tess) = model.fem.get() else { return };
            if !stepping(control) {
                return;
            }
            let due = control
                .steps
                .is_multiple_of(settings.reassign_every.max(1) as u64)
                || range.forces.influence().len() != range.forces.points().len();
            if !due {
                return;
            }
            let scratch = &mut *scratch;
            scratch.current_positions(|s| &mut s.node_x, &model, tess);
            range.forces.reassign(tess, &scratch.node_x);
            range.reassignments += 1;
        });
}

/// Stage `GatherForces`: range springs (eq. 22) with their migration, image forces (eq. 23), and
/// user springs, spread to the nodes.
pub fn gather_forces(
    mut models: Query<(
        ModelStateRef,
        &SimControl,
        &mut Scratch,
        Option<&mut RangeData>,
        Option<&mut ImageData>,
        Option<&SpringForces>,
    )>,
) {
    use crate::model::image_fit::{REGION_REFRESH, refresh_region_model};
    models
        .par_iter_mut()
        .for_each(|(model, control, mut scratch, range, image, springs)| {
            let Some(tess) = model.fem.get() else { return };
            if !stepping(control) {
                return;
            }
            let scratch = &mut *scratch;
            scratch.current_positions(|s| &mut s.node_x, &model, tess);
            scratch.forces.clear(tess.node_count());
            if let Some(mut range) = range {
                let surface = model.surface();
                range.forces.migrate(tess, &scratch.node_x, Some(&surface));
                range
                    .forces
                    .accumulate(tess, &scratch.node_x, &mut scratch.forces);
            }
            if let Some(mut image) = image {
                // The region force's model of the part, measured as the part moves.
                let forces = &image.forces;
                if forces.region > 0.0
                    && (forces.region_model.is_none()
                        || control.steps.is_multiple_of(REGION_REFRESH as u64))
                {
                    refresh_region_model(&mut image.forces, tess, &scratch.node_x);
                }
                image.forces.accumulate_with(
                    tess,
                    &scratch.node_x,
                    &mut scratch.forces,
                    &mut scratch.image,
                );
            }
            for spring in springs.map(|s| s.0.as_slice()).unwrap_or(&[]) {
                let at = tess.locate(spring.u, spring.v);
                let x = at.interpolate(|k| scratch.node_x[k]);
                scratch.forces.add(
                    &at,
                    spring.stiffness * (spring.anchor - x),
                    spring.stiffness,
                );
            }
        });
}

/// Stage `GatherForces`, after the models' own forces: each [`PartJoint`] adds its constraint
/// force to its two models when either steps this run (the forces act on the global coordinates
/// only).
pub fn joint_forces(
    mut joints: Query<&mut PartJoint>,
    mut models: Query<(
        &FemMesh,
        &SimControl,
        &mut Scratch,
        &ModelSettings,
        &GlobalShape,
        Option<&Inertia>,
    )>,
) {
    for mut pj in &mut joints {
        let pj = &mut *pj;
        if pj.a == pj.b {
            continue;
        }
        let Ok(
            [
                (fem_a, control_a, mut a, settings_a, shape_a, inertia_a),
                (fem_b, control_b, mut b, settings_b, shape_b, inertia_b),
            ],
        ) = models.get_many_mut([pj.a, pj.b])
        else {
            continue;
        };
        // With mass on either side, the multiplier's rate that keeps it stable (the slower).
        let rate = [(inertia_a, settings_a), (inertia_b, settings_b)]
            .iter()
            .filter_map(|(i, s)| i.map(|i| inertial_multiplier_rate(i.params.damping, s.dt)))
            .fold(MULTIPLIER_RATE, f64::min);
        let (Some(tess_a), Some(tess_b)) = (fem_a.get(), fem_b.get()) else {
            continue;
        };
        let (a, b) = (&mut *a, &mut *b);
        // A paused model holds still, its nodes where its last step left them: it anchors the
        // other.
        if !(stepping(control_a) || stepping(control_b))
            || a.node_x.len() != tess_a.node_count()
            || b.node_x.len() != tess_b.node_count()
        {
            continue;
        }
        let reach = MAX_REACH * shape_a.a.min(shape_b.a);
        pj.gap = pj.joint.apply(
            rate,
            reach,
            (
                tess_a,
                &a.node_x,
                &mut a.forces,
                JointLoad::for_model(inertia_a.is_some()),
            ),
            (
                tess_b,
                &b.node_x,
                &mut b.forces,
                JointLoad::for_model(inertia_b.is_some()),
            ),
        );
    }
}

/// Stage `Integrate`: one explicit Euler step (eq. 15) per model, or one step of the
/// second-order dynamics (eq. 12) for a model with [`Inertia`]. A refused step (non-finite)
/// freezes the model and logs the error; nothing non-finite is written.
pub fn integrate(
    mut models: Query<(
        Entity,
        Ref<FemMesh>,
        &mut RigidState,
        &mut GlobalShape,
        &mut LocalDofs,
        &ModelSettings,
        &mut SimControl,
        &mut Scratch,
        Option<&mut Inertia>,
        Option<&SpringForces>,
    )>,
) {
    models.par_iter_mut().for_each(
        |(
            entity,
            fem,
            mut rigid,
            mut shape,
            mut local,
            settings,
            mut control,
            mut scratch,
            inertia,
            springs,
        )| {
            let ticks = state_ticks(&fem, &rigid, &shape, &local);
            let Some(tess) = fem.get() else { return };
            if !stepping(&control) {
                return;
            }
            // Read before `take_state`, which writes the local DOFs (and so their tick).
            let prepared = scratch.workspace_current(entity, ticks, tess.node_count());
            let mut state = take_state(&rigid, &shape, &mut local);
            let scratch = &mut *scratch;
            scratch.prepared = None;
            let mut params = settings.dynamics_at(control.steps);
            // A grab moves, turns and dents the model; its global shape is held meanwhile.
            if springs.is_some_and(|s| s.0.iter().any(|s| !s.reshape)) {
                params.free = params.free.beyond_the_paper(true, false, false);
            }
            let explicit = inertia.is_none();
            let stepped = match inertia {
                Some(mut inertia) => {
                    let inertia = &mut *inertia;
                    inertia::step(
                        tess,
                        &mut state,
                        &mut inertia.velocity,
                        &scratch.forces,
                        &params,
                        &inertia.params,
                        &mut scratch.inertia_workspace,
                    )
                }
                // The workspace already holds this state's node positions.
                None if prepared => step_prepared(
                    tess,
                    &mut state,
                    &scratch.forces,
                    &params,
                    &mut scratch.workspace,
                ),
                None => step(
                    tess,
                    &mut state,
                    &scratch.forces,
                    &params,
                    &mut scratch.workspace,
                ),
            };
            // The node positions of the state written below, for the systems after this one and
            // the next step, when they are the components' (the stored deformation already
            // within the bounds `take_state` would bring it to).
            let reusable = explicit
                && stepped.is_ok()
                && state.deformation == state.deformation.clamped(state.shape.semi_axes());
            if reusable {
                scratch.workspace.prepare(tess, &state);
            }
            match stepped {
                Ok(report) => {
                    control.steps += 1;
                    control.last_substeps = report.substeps;
                }
                Err(e) => {
                    control.frozen = true;
                    control.error = Some(e.to_string());
                    error!("deformable superquadric {entity}: {e}; frozen until reset");
                }
            }
            if control.paused {
                control.step_requests = control.step_requests.saturating_sub(1);
            }
            put_state(state, &mut rigid, &mut shape, &mut local);
            if reusable {
                scratch.prepared = Some((entity, state_ticks(&fem, &rigid, &shape, &local)));
            }
        },
    );
}

/// Stage `WriteBack`: the model frame into the entity's [`Transform`] (the mesh's vertices are
/// the model-frame points p_i, rewritten by the render systems).
pub fn write_transforms(mut models: Query<(&RigidState, &mut Transform), Changed<RigidState>>) {
    for (rigid, mut transform) in &mut models {
        transform.translation = rigid.translation.as_vec3();
        transform.rotation = rigid.rotation.as_quat();
    }
}

/// Debug builds: after every step, checks that each model's state is finite, naming the entity
/// and component that went bad (a step never writes one; this catches a broken invariant).
#[cfg(debug_assertions)]
pub fn assert_finite(models: Query<(Entity, &RigidState, &GlobalShape, &LocalDofs, &SimControl)>) {
    for (entity, rigid, shape, local, control) in &models {
        if !control.frozen
            && let Some(what) = first_non_finite(rigid, shape, local)
        {
            panic!("deformable superquadric {entity}: {what} became non-finite during a step");
        }
    }
}
