//! Fitting a deformable superquadric to range points: points in, the model at rest out.
//!
//! [`fit`] is one pipeline of stages over one context:
//!
//! 1. **the context**: the points and options checked, the points normalised once to their
//!    centroid and RMS radius (so a fit does not depend on where the data sits or on its units:
//!    translate, rotate or scale the input and the result is the same fit, transformed), and
//!    the membrane's stiffness chosen from their noise where the options ask;
//! 2. **the hypotheses** ([`initial_hypotheses`]): the moments frame with each axis as z, or one
//!    explicit pose;
//! 3. **the global stage**, by one of two plans ([`FitOptions::solver`]):
//!    - **solved** (the default, beyond the paper; [`Solver::Solved`]): the superquadric's rest
//!      state, with its tapering and bending when free, by Levenberg–Marquardt
//!      ([`solve`], [`crate::model::lm::fit_deformed`]);
//!    - **the paper's dynamics** ([`Solver::Dynamics`]): the explicit Euler steps of eq. (15)
//!      under range springs, stage by stage ([`Stage`]), as section VI-B runs them;
//! 4. **the membrane**, with local DOFs: solved by linear solves for fixed attachments
//!    ([`implicit_joint_options`]) alternated with reattachment, or the dynamics' joint stage;
//! 5. **the report** ([`FitReport`]): the state mapped back to the data's frame, and its
//!    residuals on every point.
//!
//! [`CloudOptions`] resolves what a user gives (`dsq fit`'s flags, the Python keywords, the
//! plugin's settings) into [`FitOptions`] once.

mod cloud;
mod context;
mod dynamics;
mod global;
mod hypotheses;
mod membrane;
mod mesh;
mod options;
mod relax;
mod report;
mod residuals;
mod search;
#[cfg(test)]
mod tests;

pub use crate::model::init::Normalization;
pub use cloud::{CloudOptions, Stiffness, k_for_nodes};
pub use context::{FitProgress, Stage};
pub use hypotheses::{
    DUAL_AXES_RATIO, DUAL_EPSILON_GAP, cross_section_dual, initial_hypotheses,
    similarity_candidates,
};
pub use mesh::{MAX_JOINT_K, joint_k};
pub use options::{
    FitError, FitOptions, Initialization, MIN_POINTS, NoiseStiffness, ROBUST_OUTLIER_RATIO, Solver,
    validate_options, validate_points,
};
pub use relax::{has_joint_stage, implicit_joint_options, max_motion};
pub use report::{FitReport, FitSummary};
pub use residuals::{
    Residuals, bounding_diagonal, closest_point_on_triangle, fit_residuals, mean_distance,
    point_distances, point_distances_parallel, residuals, surface_distances,
    weighted_mean_distance,
};
pub use search::{
    COARSE_POINTS, FINE_POINTS, FINE_ROUNDS, PLACING_TOLERANCE, PROBE_ROUNDS, PROBE_STEPS,
    Solution, coarse_sample, ellipsoid_carrier, score, solve, solve_lean, spread_sample,
};

use crate::model::dynamics::ModelState;
use crate::model::fem::Tessellation;
use context::{Context, Sink};
use glam::DVec3;

/// Fits a deformable superquadric to `points`, calling `progress` as it goes (every 100 steps of
/// the dynamics; after each stage of the solved fit). See the module docs.
pub fn fit(
    points: &[DVec3],
    opts: &FitOptions,
    progress: impl FnMut(&FitProgress),
) -> Result<FitReport, FitError> {
    fit_watched(points, opts, progress, |_, _| {})
}

/// A pure superquadric fitted to `points` by one lean search (from `opts`' starts, without
/// similarity switches or the placed search; [`solve_lean`]), in the data's
/// frame and units: a quick fit for a caller that weighs many candidate pieces of a cloud
/// ([`crate::model::parts`]). Its tapering, bending and local DOFs are not fitted. Errors as
/// [`fit`]'s.
pub fn fit_lean(
    points: &[DVec3],
    opts: &FitOptions,
) -> Result<crate::model::init::InitialPose, FitError> {
    let ctx = Context::new(points, opts)?;
    let starts = hypotheses::starts(&ctx);
    let unit = global::solve_lean_global(&ctx, &starts)?;
    let mut pose = ctx.norm.pose_from_unit(&unit);
    pose.shape = pose.shape.normalized();
    Ok(pose)
}

/// A fit of `points` whose superquadric is `pose` (data frame), held as given: with local DOFs
/// (the solved plan's), its membrane brought to rest on it; without, the report of `pose`
/// itself, its residuals measured on every point. What a caller uses that chose the
/// superquadric by a search of its own (a whole object's parts, [`crate::model::parts`]).
/// Errors as [`fit`]'s.
pub fn fit_on(
    points: &[DVec3],
    pose: &crate::model::init::InitialPose,
    opts: &FitOptions,
) -> Result<FitReport, FitError> {
    let ctx = Context::new(points, opts)?;
    let unit = ctx.norm.pose_to_unit(pose);
    let global = global::held_global(&ctx, &unit);
    let outcome = if has_joint_stage(&ctx.opts) {
        let mut progress = |_: &FitProgress| {};
        let mut watch = |_: &Tessellation, _: &ModelState| {};
        let mut sink = Sink {
            progress: &mut progress,
            watch: &mut watch,
        };
        // No starts: no ellipsoid carrier either, the membrane rests on the superquadric given.
        membrane::solve_membrane(&ctx, &[], global, &mut sink)?
    } else {
        global.into()
    };
    Ok(FitReport::new(&ctx, outcome))
}

/// [`fit`], also handing `watch` the model as the plan has it (data frame, on its tessellation)
/// when the superquadric has been chosen and before the membrane is brought to rest: what a live
/// app shows while a fit runs. The report's state is the last word.
pub fn fit_watched(
    points: &[DVec3],
    opts: &FitOptions,
    mut progress: impl FnMut(&FitProgress),
    mut watch: impl FnMut(&Tessellation, &ModelState),
) -> Result<FitReport, FitError> {
    let ctx = Context::new(points, opts)?;
    let starts = hypotheses::starts(&ctx);
    let norm = ctx.norm;
    let mut watch = |tess: &Tessellation, unit: &ModelState| watch(tess, &norm.state_to_data(unit));
    let mut sink = Sink {
        progress: &mut progress,
        watch: &mut watch,
    };
    let outcome = match ctx.opts.solver {
        Solver::Dynamics => dynamics::fit(&ctx, &starts, &mut sink)?,
        Solver::Solved => {
            let global = global::solve_global(&ctx, &starts)?;
            (sink.watch)(&global.tess, &global.state);
            let (local, cost) = (has_joint_stage(&ctx.opts), global.cost);
            let outcome = if local {
                membrane::solve_membrane(&ctx, &starts, global, &mut sink)?
            } else {
                global.into()
            };
            (sink.progress)(&FitProgress {
                step: outcome.steps,
                stage: if local { Stage::Joint } else { Stage::Global },
                max_motion: 0.0,
                energy: cost,
                reassignments: outcome.reassignments,
            });
            outcome
        }
    };
    Ok(FitReport::new(&ctx, outcome))
}
