//! Fitting through the plugin in a headless app (`MinimalPlugins`): the command-line fitter's
//! `--app` mode. It runs the same fit as [`crate::model::fit::fit`], step for step, with every
//! initial hypothesis as its own entity, simulated in parallel; the result is the same. The
//! refining stage and the cross-section switch ([`FitOptions::refine`],
//! [`FitOptions::switch_cross_section`]) choose between runs after the fact and run in the core
//! fitter only; asking for them here is an error.

use super::{
    DeformableSqPlugin, FemMesh, FitDriver, GlobalShape, LocalDofs, ModelSettings, RangeData,
    RigidState, SimControl,
};
use crate::model::dynamics::ModelState;
use crate::model::fit::{
    FitError, FitOptions, FitReport, Normalization, Stage, global_stages, has_joint_stage,
    initial_hypotheses, mean_distance, residuals, validate_options, validate_points,
};
use crate::model::forces::range::RangeForces;
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
    if opts.refine || opts.switch_cross_section {
        return Err(FitError::BadOption(
            "FitOptions::refine and switch_cross_section run in model::fit::fit only, not \
             through the plugin"
                .into(),
        ));
    }
    let norm = Normalization::of(points);
    let unit: Vec<DVec3> = points.iter().map(|p| norm.unit_point(*p)).collect();
    let candidates = initial_hypotheses(points, opts);
    let mut app = App::new();
    app.add_plugins((MinimalPlugins, DeformableSqPlugin::in_schedule(Update)));
    let share = opts.max_steps as u64 / candidates.len() as u64;
    let entities: Vec<Entity> = candidates
        .iter()
        .map(|initial| {
            let start = norm.pose_to_unit(initial);
            let mut range = RangeForces::new(unit.clone(), opts.beta, opts.influence);
            range.coverage = 0.0;
            app.world_mut()
                .spawn((
                    GlobalShape::from(start.shape.normalized()),
                    RigidState {
                        translation: start.translation,
                        rotation: start.rotation,
                    },
                    FemMesh::new(opts.k),
                    ModelSettings::from_fit(opts),
                    RangeData {
                        forces: range,
                        reassignments: 0,
                    },
                    FitDriver::new(*opts, global_stages(opts), share),
                ))
                .id()
        })
        .collect();
    let max_updates = opts.max_steps as u64 + 10;
    run_until_done(&mut app, max_updates)?;

    // The hypothesis whose surface lies closest to the data goes on (first wins ties, as in `fit`).
    let tess = app
        .world()
        .get::<FemMesh>(entities[0])
        .and_then(|f| f.get().cloned())
        .ok_or(FitError::Degenerate)?;
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
    let (_, chosen) = best.ok_or(FitError::Degenerate)?;
    let steps_of = |app: &App, e: Entity| app.world().get::<SimControl>(e).map_or(0, |c| c.steps);
    let other_steps: u64 = entities
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
    let e = entities[chosen];
    if has_joint_stage(opts) {
        let budget = opts.max_steps as u64 - other_steps;
        app.world_mut()
            .get_mut::<FitDriver>(e)
            .ok_or(FitError::Degenerate)?
            .continue_with([Stage::Joint], budget);
        app.world_mut()
            .get_mut::<SimControl>(e)
            .ok_or(FitError::Degenerate)?
            .paused = false;
        run_until_done(&mut app, max_updates)?;
    }
    let world = app.world();
    let driver = world.get::<FitDriver>(e).ok_or(FitError::Degenerate)?;
    let state = norm.state_to_data(&state_of(world, e).ok_or(FitError::Degenerate)?);
    let mut world_x = Vec::new();
    state.node_positions(&tess, &mut world_x);
    Ok(FitReport {
        residuals: residuals(&tess, &world_x, points),
        steps: (steps_of(&app, e) + other_steps) as u32,
        global_steps: driver.global_steps as u32,
        reassignments: driver.reassignments as u32,
        converged: driver.converged,
        substepped_steps: driver.substepped_steps as u32,
        initial: candidates[chosen],
        refinement: None,
        state,
        tess: (*tess).clone(),
    })
}
