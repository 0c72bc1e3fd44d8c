//! Fitting through the plugin in a headless app (`MinimalPlugins`): the command-line fitter's
//! `--app` mode. It runs the same fit as [`crate::model::fit::fit`], step for step, with every
//! initial hypothesis as its own entity, simulated in parallel; the result is the same. The
//! cross-section switch ([`FitOptions::switch_cross_section`]) runs the dual as one more entity,
//! the refining stage ([`FitOptions::refine`]) runs on the chosen one, which goes back to its
//! state before the stage when the refinement is not kept, and the similarity switch
//! ([`FitOptions::similarity_switch`]) runs each candidate as one more entity, and a pure
//! superquadric ends with the squareness extension (`fit::extend_squareness`), and a joint stage
//! on a tessellation chosen from the data ([`FitOptions::k_from_data`]) goes on from the
//! membrane at rest on the model's own mesh to the finer one — as `fit` does.

use super::{
    DeformableSqPlugin, FemMesh, FemMeshCache, FitDriver, GlobalShape, LocalDofs, ModelSettings,
    RangeData, RigidState, SimControl,
};
use crate::model::dynamics::ModelState;
use crate::model::fem::Tessellation;
use crate::model::fit::{
    FitError, FitOptions, FitReport, Normalization, REFINE_CHECK_EVERY, REFINE_MAX_STEPS,
    Refinement, Stage, cross_section_dual, extend_squareness, fit_residuals, global_stages,
    has_joint_stage, implicit_joint_options, initial_hypotheses, joint_k, mean_distance,
    refine_candidate, refine_check, refine_distances, refine_overgrown, refine_stalled,
    similarity_candidates, similarity_share, start_state, surrounds, validate_options,
    validate_points, weighted_mean_distance,
};
use crate::model::forces::range::RangeForces;
use crate::model::init::InitialPose;
use bevy::math::DVec3;
use bevy::prelude::*;

fn state_of(world: &World, e: Entity) -> Option<ModelState> {
    let (r, s, l) = (
        world.get::<RigidState>(e)?,
        world.get::<GlobalShape>(e)?,
        world.get::<LocalDofs>(e)?,
    );
    Some(ModelState {
        translation: r.translation,
        rotation: r.rotation,
        shape: (*s).into(),
        deformation: s.deformation(),
        displacement: l.displacement.clone(),
    })
}

/// Updates the app until every driver is done or has frozen (bounded by `max_updates`).
fn run_until_done(app: &mut App, max_updates: u64) -> Result<(), FitError> {
    for _ in 0..max_updates {
        app.update();
        let mut q = app.world_mut().query::<(&FitDriver, &SimControl)>();
        let mut all_done = true;
        for (driver, control) in q.iter(app.world()) {
            if control.frozen {
                return Err(FitError::Step(
                    crate::model::dynamics::StepError::NonFinite("state (model frozen)"),
                ));
            }
            all_done &= driver.done;
        }
        if all_done {
            return Ok(());
        }
    }
    Err(FitError::BadOption(
        "the headless app did not finish within its update budget".into(),
    ))
}

/// Fits `points` through [`DeformableSqPlugin`] in a headless app; see the module docs.
pub fn fit_headless(points: &[DVec3], opts: &FitOptions) -> Result<FitReport, FitError> {
    validate_points(points)?;
    validate_options(opts)?;
    let norm = Normalization::of(points);
    let unit: Vec<DVec3> = points.iter().map(|p| norm.unit_point(*p)).collect();
    let candidates = initial_hypotheses(points, opts);
    let mut app = App::new();
    app.add_plugins((MinimalPlugins, DeformableSqPlugin::in_schedule(Update)));
    // The models' tessellation, shared through the plugin's cache.
    let model_tess = app.world_mut().resource_mut::<FemMeshCache>().get(opts.k);
    // As in `fit`: a tapered or bent fit seeds its start from the data's centreline, and keeps
    // the coverage springs on in its global stages when the data surrounds the model.
    let whole = surrounds(&model_tess, opts, &unit, &norm, &candidates);
    let spawn = Spawner {
        opts,
        unit: &unit,
        tess: &model_tess,
        whole,
    };
    let share = opts.max_steps as u64 / candidates.len() as u64;
    let entities: Vec<Entity> = candidates
        .iter()
        .map(|initial| {
            let driver = FitDriver::new(*opts, global_stages(opts), share);
            spawn.model(&mut app, &norm.pose_to_unit(initial), driver)
        })
        .collect();
    let max_updates = opts.max_steps as u64 + 10;
    run_until_done(&mut app, max_updates)?;

    // The hypothesis whose surface lies closest to the data goes on (first wins ties, as in `fit`).
    let mut tess = model_tess.clone();
    let mut best: Option<(f64, usize)> = None;
    let mut x = Vec::new();
    for (i, &e) in entities.iter().enumerate() {
        let state = state_of(app.world(), e).ok_or(FitError::Degenerate)?;
        state.node_positions(&tess, &mut x);
        let score = mean_distance(&tess, &x, &unit);
        if best.is_none_or(|b| score < b.0) {
            best = Some((score, i));
        }
    }
    let (mut score, chosen) = best.ok_or(FitError::Degenerate)?;
    let mut other_steps: u64 = entities
        .iter()
        .enumerate()
        .filter(|(i, _)| *i != chosen)
        .map(|(_, &e)| steps_of(&app, e))
        .sum();
    for (i, &e) in entities.iter().enumerate() {
        if i != chosen {
            app.world_mut().despawn(e);
        }
    }
    let mut e = entities[chosen];
    let mut initial = candidates[chosen];
    if opts.switch_cross_section {
        let state = state_of(app.world(), e).ok_or(FitError::Degenerate)?;
        if let Some(dual) = cross_section_dual(&InitialPose::of(&state)) {
            let budget = (opts.max_steps as u64).saturating_sub(other_steps + steps_of(&app, e));
            let driver = FitDriver::new(*opts, [Stage::Global], budget);
            let other = spawn.model(&mut app, &dual, driver);
            run_until_done(&mut app, max_updates)?;
            let other_score = distance_of(&app, other, &tess, &unit)?;
            if other_score < score {
                other_steps += steps_of(&app, e);
                app.world_mut().despawn(e);
                (e, score) = (other, other_score);
                initial = norm.pose_to_data(&tess, &dual);
            } else {
                other_steps += steps_of(&app, other);
                app.world_mut().despawn(other);
            }
        }
    }
    let mut refinement = None;
    // As in `fit`: the chosen model at the end of its global stage, for the similarity candidates.
    let mut placed = None;
    if opts.refine {
        if opts.similarity_switch {
            placed = Some(state_of(app.world(), e).ok_or(FitError::Degenerate)?);
        }
        let cap = (opts.max_steps as u64).saturating_sub(other_steps);
        let (stage, undone_steps) = refine(&mut app, e, cap, score, &tess, &unit, opts)?;
        other_steps += undone_steps;
        refinement = Some(stage);
    }
    if opts.similarity_switch {
        // As in `fit`: each candidate through the global stage and, within the margin, the
        // refining stage, scored with the chosen fit's inlier probabilities.
        let weights = weights_of(&app, e)?;
        let weighted_at = |state: &ModelState| {
            let mut x = Vec::new();
            state.node_positions(&tess, &mut x);
            weighted_mean_distance(&tess, &x, &unit, &weights)
        };
        let weighted = |app: &App, e: Entity| -> Result<f64, FitError> {
            Ok(weighted_at(
                &state_of(app.world(), e).ok_or(FitError::Degenerate)?,
            ))
        };
        let placed = placed.as_ref().map(weighted_at);
        let mut best_score = weighted(&app, e)?;
        let mut best: Option<(Entity, InitialPose)> = None;
        let current = InitialPose::of(&state_of(app.world(), e).ok_or(FitError::Degenerate)?);
        let candidates = similarity_candidates(&current);
        // Each candidate's budget is `fit`'s: an equal share of the steps left.
        let spent = other_steps + steps_of(&app, e);
        let cap = similarity_share(
            opts.max_steps,
            u32::try_from(spent).unwrap_or(u32::MAX),
            candidates.len(),
        ) as u64;
        for candidate in candidates {
            let driver = FitDriver::new(*opts, [Stage::Global], cap);
            let other = spawn.model(&mut app, &candidate, driver);
            run_until_done(&mut app, max_updates)?;
            // As in `fit`: scored after the global stage, and again only after a kept refinement.
            let mut other_score = weighted(&app, other)?;
            if opts.refine && placed.is_none_or(|chosen| refine_candidate(other_score, chosen)) {
                let before = distance_of(&app, other, &tess, &unit)?;
                let (stage, undone) = refine(&mut app, other, cap, before, &tess, &unit, opts)?;
                other_steps += undone;
                if stage.kept {
                    other_score = weighted(&app, other)?;
                }
            }
            if other_score < best_score {
                best_score = other_score;
                if let Some((old, _)) = best.replace((other, candidate)) {
                    other_steps += steps_of(&app, old);
                    app.world_mut().despawn(old);
                }
            } else {
                other_steps += steps_of(&app, other);
                app.world_mut().despawn(other);
            }
        }
        if let Some((other, candidate)) = best {
            other_steps += steps_of(&app, e);
            app.world_mut().despawn(e);
            e = other;
            initial = norm.pose_to_data(&tess, &candidate);
        }
    }
    if !has_joint_stage(opts) && opts.refine {
        // As in `fit`: a pure superquadric ends with the squareness extension.
        let state = state_of(app.world(), e).ok_or(FitError::Degenerate)?;
        let weights = weights_of(&app, e)?;
        if let Some(shape) = extend_squareness(&tess, &state, &unit, &weights) {
            let mut global = app
                .world_mut()
                .get_mut::<GlobalShape>(e)
                .ok_or(FitError::Degenerate)?;
            (global.e1, global.e2) = (shape.e1, shape.e2);
        }
    }
    if has_joint_stage(opts) {
        let k = if opts.k_from_data {
            let state = state_of(app.world(), e).ok_or(FitError::Degenerate)?;
            state.node_positions(&tess, &mut x);
            joint_k(&tess, &x, &unit, opts.k)
        } else {
            opts.k
        };
        let budget = (opts.max_steps as u64).saturating_sub(other_steps);
        run_joint_stage(&mut app, e, budget, max_updates)?;
        if k != tess.k {
            // As in `fit`: the membrane at rest is carried onto the finer mesh (the plugin does
            // that when `FemMesh::k` changes) and runs on there, the global DOFs held, by
            // implicit steps.
            let finer = implicit_joint_options(opts);
            let mut model = app.world_mut().entity_mut(e);
            model.get_mut::<FemMesh>().ok_or(FitError::Degenerate)?.k = k;
            *model
                .get_mut::<ModelSettings>()
                .ok_or(FitError::Degenerate)? = ModelSettings::from_fit(&finer);
            model
                .get_mut::<FitDriver>()
                .ok_or(FitError::Degenerate)?
                .options = finer;
            run_joint_stage(&mut app, e, budget, max_updates)?;
            tess = app
                .world()
                .get::<FemMesh>(e)
                .and_then(|f| f.get().cloned())
                .ok_or(FitError::Degenerate)?;
        }
    }
    let world = app.world();
    let driver = world.get::<FitDriver>(e).ok_or(FitError::Degenerate)?;
    let state = norm.state_to_data(&state_of(world, e).ok_or(FitError::Degenerate)?);
    Ok(FitReport {
        residuals: fit_residuals(&tess, &state, points),
        steps: (steps_of(&app, e) + other_steps) as u32,
        global_steps: driver.global_steps as u32,
        reassignments: driver.reassignments as u32,
        converged: driver.converged,
        substepped_steps: driver.substepped_steps as u32,
        initial,
        refinement,
        state,
        tess: (*tess).clone(),
    })
}

/// Runs model `e`'s joint stage through its driver, within `budget` steps of the model in all.
fn run_joint_stage(
    app: &mut App,
    e: Entity,
    budget: u64,
    max_updates: u64,
) -> Result<(), FitError> {
    app.world_mut()
        .get_mut::<FitDriver>(e)
        .ok_or(FitError::Degenerate)?
        .continue_with([Stage::Joint], budget);
    app.world_mut()
        .get_mut::<SimControl>(e)
        .ok_or(FitError::Degenerate)?
        .paused = false;
    run_until_done(app, max_updates)
}

/// The inlier weights of model `e`'s points ([`RangeForces::relative_weights`]).
fn weights_of(app: &App, e: Entity) -> Result<Vec<f64>, FitError> {
    let range = app
        .world()
        .get::<RangeData>(e)
        .ok_or(FitError::Degenerate)?;
    Ok(range.forces.relative_weights())
}

fn steps_of(app: &App, e: Entity) -> u64 {
    app.world().get::<SimControl>(e).map_or(0, |c| c.steps)
}

/// What every model of one headless fit is spawned with: the options, the `unit` points, a
/// tessellation for the seeded start, and whether the global stages keep the coverage springs.
struct Spawner<'a> {
    opts: &'a FitOptions,
    unit: &'a [DVec3],
    tess: &'a Tessellation,
    whole: bool,
}

impl Spawner<'_> {
    /// Spawns a model at `start` (the fit's unit frame) pulled by the points, in `fit`'s start
    /// state there ([`start_state`]: with tapering or bending free, seeded from the centreline).
    fn model(&self, app: &mut App, start: &InitialPose, mut driver: FitDriver) -> Entity {
        let opts = self.opts;
        let state = start_state(self.tess, opts, self.unit, start);
        let mut range = RangeForces::new(self.unit.to_vec(), opts.beta, opts.influence);
        range.coverage = 0.0;
        driver.global_coverage = self.whole;
        app.world_mut()
            .spawn((
                GlobalShape::new(state.shape, state.deformation),
                RigidState {
                    translation: state.translation,
                    rotation: state.rotation,
                },
                FemMesh::new(opts.k),
                ModelSettings::from_fit(opts),
                RangeData {
                    forces: range,
                    reassignments: 0,
                },
                driver,
            ))
            .id()
    }
}

/// The mean distance of the `unit` points to the surface of model `e`.
fn distance_of(app: &App, e: Entity, tess: &Tessellation, unit: &[DVec3]) -> Result<f64, FitError> {
    let state = state_of(app.world(), e).ok_or(FitError::Degenerate)?;
    let mut x = Vec::new();
    state.node_positions(tess, &mut x);
    Ok(mean_distance(tess, &x, unit))
}

/// The refining stage on model `e`, as `fit` runs it, within `cap` steps of the model in all:
/// given up when the model grows too long ([`refine_overgrown`], after every step) or, checked
/// every [`REFINE_CHECK_EVERY`] of the model's steps, past
/// [`crate::model::fit::REFINE_GIVE_UP`] times the least distance seen, `score` at first
/// ([`refine_check`]), or stalled ([`refine_stalled`]); kept when at rest and no farther than
/// `score`, else the model goes back to its state before the stage. Returns the outcome and the steps that were undone.
fn refine(
    app: &mut App,
    e: Entity,
    cap: u64,
    score: f64,
    tess: &Tessellation,
    unit: &[DVec3],
    opts: &FitOptions,
) -> Result<(Refinement, u64), FitError> {
    let world = app.world();
    let snapshot = (
        world.get::<RigidState>(e).cloned(),
        world.get::<GlobalShape>(e).cloned(),
        world.get::<LocalDofs>(e).cloned(),
        world.get::<RangeData>(e).cloned(),
        world.get::<FitDriver>(e).cloned(),
        world.get::<SimControl>(e).cloned(),
    );
    let (Some(rigid), Some(shape), Some(local), Some(range), Some(driver), Some(control)) =
        snapshot
    else {
        return Err(FitError::Degenerate);
    };
    let start = control.steps;
    let start_extent = crate::model::superquadric::SuperquadricParams::from(shape)
        .semi_axes()
        .max_element();
    let budget = (start + REFINE_MAX_STEPS as u64).min(cap);
    {
        let mut entity = app.world_mut().entity_mut(e);
        entity
            .get_mut::<FitDriver>()
            .ok_or(FitError::Degenerate)?
            .continue_with([Stage::Refine], budget);
        entity
            .get_mut::<SimControl>()
            .ok_or(FitError::Degenerate)?
            .paused = false;
    }
    let (mut least, mut gave_up, mut seen) = (score, false, start);
    let mut previous = None;
    // As in `fit`: a tapered or bent fit keeps the closest state its checks saw.
    let deforms = opts.dynamics.free.taper || opts.dynamics.free.bend;
    let mut best: Option<(f64, RigidState, GlobalShape, LocalDofs)> = None;
    for _ in 0..=budget.saturating_sub(start) + 10 {
        app.update();
        let world = app.world();
        let control = world.get::<SimControl>(e).ok_or(FitError::Degenerate)?;
        let driver = world.get::<FitDriver>(e).ok_or(FitError::Degenerate)?;
        if control.frozen {
            return Err(FitError::Step(
                crate::model::dynamics::StepError::NonFinite("state (model frozen)"),
            ));
        }
        if control.steps == seen {
            if driver.done {
                break;
            }
            continue;
        }
        seen = control.steps;
        // `fit` checks after every step that did not end the stage at rest.
        let at_rest = driver.done && driver.converged;
        if !at_rest {
            let shape = world.get::<GlobalShape>(e).ok_or(FitError::Degenerate)?;
            let longest = crate::model::superquadric::SuperquadricParams::from(*shape)
                .semi_axes()
                .max_element();
            if refine_overgrown(longest, start_extent) {
                gave_up = true;
                break;
            }
        }
        if !at_rest && seen.is_multiple_of(REFINE_CHECK_EVERY as u64) {
            let state = state_of(app.world(), e).ok_or(FitError::Degenerate)?;
            let range = app
                .world()
                .get::<RangeData>(e)
                .ok_or(FitError::Degenerate)?;
            let mut x = Vec::new();
            state.node_positions(tess, &mut x);
            let (distance, weighted) = refine_distances(tess, &x, &range.forces);
            if deforms && best.as_ref().is_none_or(|b| distance < b.0) {
                let world = app.world();
                let components = (
                    world.get::<RigidState>(e).cloned(),
                    world.get::<GlobalShape>(e).cloned(),
                    world.get::<LocalDofs>(e).cloned(),
                );
                if let (Some(r), Some(g), Some(l)) = components {
                    best = Some((distance, r, g, l));
                }
            }
            let stalled = refine_stalled(weighted, previous);
            previous = Some(weighted);
            match refine_check(distance, least) {
                Some(l) if !stalled => least = l,
                _ => {
                    gave_up = true;
                    break;
                }
            }
        }
        if driver.done {
            break;
        }
    }
    let world = app.world();
    let at_rest = !gave_up && world.get::<FitDriver>(e).is_some_and(|d| d.converged);
    let mut after = distance_of(app, e, tess, unit)?;
    let steps = steps_of(app, e) - start;
    let mut kept = at_rest && after <= score;
    if let Some((distance, r, g, l)) = best
        && !kept
        && distance <= score
    {
        // The closest state, and the model stopped there as `fit`'s relaxation stops (a stage
        // given up is still running).
        let mut entity = app.world_mut().entity_mut(e);
        entity.insert((r, g, l));
        if let Some(mut driver) = entity.get_mut::<FitDriver>() {
            driver.stages.clear();
            (driver.clock, driver.done) = (None, true);
        }
        if let Some(mut control) = entity.get_mut::<SimControl>() {
            control.paused = true;
        }
        (after, kept) = (distance, true);
    }
    if !kept {
        app.world_mut()
            .entity_mut(e)
            .insert((rigid, shape, local, range, driver, control));
    }
    let outcome = Refinement {
        steps: steps as u32,
        kept,
        gave_up,
        before: score,
        after,
    };
    Ok((outcome, if kept { 0 } else { steps }))
}
