//! Fitting a deformable superquadric to range points: points in, the model at rest out.
//!
//! [`fit`] runs one of two plans ([`FitOptions::solver`]):
//!
//! - **Solved** (the default, beyond the paper; [`Solver::Solved`], module `solved`): the
//!   superquadric's rest state (with its tapering and bending, when free) is solved for by
//!   Levenberg–Marquardt ([`crate::model::lm::solve`], [`crate::model::lm::fit_deformed`]), and
//!   with local DOFs the membrane's by linear solves for fixed attachments
//!   ([`implicit_joint_options`]), alternated with reattachment until the attachments settle;
//! - **the paper's dynamics** ([`Solver::Dynamics`], module `relax`): the explicit Euler steps of
//!   eq. (15) under range springs, stage by stage ([`Stage`]), as section VI-B runs them.
//!
//! **Frame and scale.** Both work on the data translated to its centroid and divided by its RMS
//! radius, and map the result back, so a fit does not depend on where the data sits or on its
//! units: translate, rotate or scale the input and the result is the same fit, transformed.

use super::centreline::{seed_deformation, seen_whole};
use super::deform::GlobalDeformation;
use super::dynamics::{
    DynamicsParams, ModelState, NodalForces, StepError, Workspace, step_prepared,
};
use super::fem::Tessellation;
use super::forces::range::{DEFAULT_COVERAGE, InfluenceMode, RangeForces, Robust};
pub use super::init::Normalization;
use super::init::{InitialPose, initial_pose};
pub use super::lm::Solver;
use super::lm::{LmOptions, Metric, Mixture};
use super::superquadric::SuperquadricParams;
use crate::model::forces::nearest::kd_tree;
use crate::model::parallel::run_parallel;
use glam::DVec3;
use kiddo::SquaredEuclidean;
use std::f64::consts::SQRT_2;
use std::num::NonZero;

mod cloud;
mod options;
mod plan;
mod relax;
mod residuals;
mod solved;
pub use cloud::*;
pub use options::*;
pub use plan::*;
use relax::*;
pub use residuals::*;
pub use solved::*;
#[cfg(test)]
mod tests;

/// Fewest points a fit accepts: the 11 independent global DOFs need at least 4 points in general
/// position, and the moments a few more to mean anything.
pub const MIN_POINTS: usize = 10;

/// A snapshot for progress reports.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FitProgress {
    /// Steps taken so far.
    pub step: u32,
    /// Current stage.
    pub stage: Stage,
    /// Largest node motion of the last step (units of the data's RMS radius).
    pub max_motion: f64,
    /// Spring plus strain energy (normalised units).
    pub energy: f64,
    /// Reattachments so far.
    pub reassignments: u32,
}

/// Distances of the data points to the fitted surface, as fractions of the data's bounding-box
/// diagonal.
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize)]
pub struct Residuals {
    /// Mean distance.
    pub mean: f64,
    /// Root-mean-square distance.
    pub rms: f64,
    /// 95th percentile.
    pub p95: f64,
    /// Largest distance.
    pub max: f64,
    /// The bounding-box diagonal the figures are relative to (data units).
    pub diagonal: f64,
}

/// The outcome of a fit.
#[derive(Clone, Debug)]
pub struct FitReport {
    /// The fitted state in the data's frame and units.
    pub state: ModelState,
    /// The tessellation the state lives on.
    pub tess: Tessellation,
    /// Steps taken, over every initial hypothesis tried: Euler steps of the dynamics, or the
    /// solved fit's Levenberg–Marquardt steps and linear solves of the membrane.
    pub steps: u32,
    /// Steps the chosen hypothesis took with the global DOFs alone.
    pub global_steps: u32,
    /// Reattachments done.
    pub reassignments: u32,
    /// True when the loop stopped at rest rather than at the step cap.
    pub converged: bool,
    /// Steps whose local update was sub-stepped for stability.
    pub substepped_steps: u32,
    /// Point-to-surface residuals of the fitted model.
    pub residuals: Residuals,
    /// Initial pose the fit started from (data frame): the chosen hypothesis, or the similarity
    /// candidate the fit moved to.
    pub initial: InitialPose,
    /// The solver that ran ([`FitOptions::solver`]).
    pub solver: Solver,
}

/// The largest distance any node moved between two sets of node positions: the measure a fit's
/// rest test compares with its motion tolerance.
pub fn max_motion(before: &[DVec3], after: &[DVec3]) -> f64 {
    before
        .iter()
        .zip(after)
        .map(|(a, b)| a.distance_squared(*b))
        .fold(0.0, f64::max)
        .sqrt()
}

/// Fits a deformable superquadric to `points`, calling `progress` as it goes (every 100 steps of
/// the dynamics; after each stage of the solved fit). See the module docs for the two plans;
/// with moments initialisation both start from the three axis hypotheses of the moments frame.
pub fn fit(
    points: &[DVec3],
    opts: &FitOptions,
    progress: impl FnMut(&FitProgress),
) -> Result<FitReport, FitError> {
    fit_watched(points, opts, progress, |_, _| {})
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
    validate_points(points)?;
    validate_options(opts)?;
    let norm = Normalization::of(points);
    let unit: Vec<DVec3> = points.iter().map(|p| norm.unit_point(*p)).collect();
    let candidates = initial_hypotheses(points, opts);
    let mut watch = |tess: &Tessellation, unit_state: &ModelState| {
        watch(tess, &norm.state_to_data(unit_state));
    };
    let frame = (&norm, &unit[..]);
    if solves(opts) {
        fit_solved(
            points,
            opts,
            frame,
            &candidates,
            (&mut progress, &mut watch),
        )
    } else {
        fit_dynamics(
            points,
            opts,
            frame,
            &candidates,
            (&mut progress, &mut watch),
        )
    }
}

/// Where a plan reports: its progress, and the model (unit frame) at the end of a stage.
type Reporting<'a> = (
    &'a mut dyn FnMut(&FitProgress),
    &'a mut dyn FnMut(&Tessellation, &ModelState),
);
