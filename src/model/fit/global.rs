//! The solved fit's global stage (beyond the paper): the superquadric's rest state by
//! Levenberg–Marquardt ([`super::solve`]: the axis hypotheses and similarity
//! candidates searched on a subsample, the kept fit polished on every point), and with tapering
//! or bending free its deformation after it ([`crate::model::lm::fit_deformed`], from each of its
//! axes as z, undeformed and as the points' centreline shows).

use super::context::Context;
use super::hypotheses::{similarity_candidates, turned_axes};
use super::options::FitError;
use super::relax::has_joint_stage;
use super::search::{FINE_POINTS, FINE_ROUNDS, coarse_sample, solve, solve_lean, spread_sample};
use crate::model::centreline::seed_deformation;
use crate::model::deform::GlobalDeformation;
use crate::model::dynamics::ModelState;
use crate::model::fem::Tessellation;
use crate::model::forces::range::SIGMA_FLOOR;
use crate::model::init::InitialPose;
use crate::model::lm::{
    DeformedFit, DeformedPose, LmOptions, Metric, Mixture, deformed_distances, fit_deformed,
};
use crate::model::parallel::run_parallel;
use crate::model::superquadric::LEAST_EPSILON;
use glam::DVec3;

/// Most EM rounds of a Levenberg–Marquardt fit, and Levenberg–Marquardt steps in a round.
pub(crate) const LM_ROUNDS: (u32, u32) = (50, 5);

/// A round of a Levenberg–Marquardt fit that lowers its cost by less than this fraction ends it
/// (0.1 %: the mean distance then moves by about 0.05 % more, below what the figures resolve;
/// on the 26 clouds of docs/results.md 10⁻⁴ changed no fit's mean residual by more than 1 %
/// where both reached the same minimum, at 1.2–1.5 times the steps).
pub(crate) const LM_TOLERANCE: f64 = 1e-3;

/// Similarity switches a Levenberg–Marquardt fit makes at most (EMS's `MaxiSwitch`).
pub(crate) const LM_SWITCHES: u32 = 2;

/// The longest semi-axis a Levenberg–Marquardt fit may reach, in units of the farthest point's
/// distance from the data's centroid ([`LmOptions::max_semi_axis`]), so at most the data's
/// widest extent: the points' distances do not see the side of a one-view scan no point lies
/// on, where an unbounded superquadric can stretch for nothing.
pub(crate) const LM_SEMI_AXIS_REACH: f64 = 2.0;

/// The superquadric the global stage chose (unit frame).
pub(super) struct Global {
    /// Its state on the options' tessellation (with its deformation, when free).
    pub state: ModelState,
    /// The tessellation.
    pub tess: Tessellation,
    /// The start it came from.
    pub start: InitialPose,
    /// The inliers' first variance σ² the search started from: what a carrier fitted after it
    /// starts from too.
    pub sigma2: f64,
    /// The Levenberg–Marquardt settings it ran with.
    pub lm: LmOptions,
    /// Levenberg–Marquardt steps over every start and candidate.
    pub steps: u32,
    /// Steps of the kept fit.
    pub global_steps: u32,
    /// Whether it came to rest.
    pub converged: bool,
    /// Its cost Σ wᵢ dᵢ² at the end (unit frame).
    pub cost: f64,
}

/// The Levenberg–Marquardt settings of a fit of `ctx`'s points from `first` (a start, unit
/// frame), and the inliers' first σ²: the outliers' density from the points' bounding box in the
/// start's frame, and EMS's first σ² from its volume and the points' reach.
pub(super) fn lm_options(ctx: &Context, first: &InitialPose) -> (LmOptions, f64) {
    let unit = &ctx.unit;
    let frame = first.rotation.inverse();
    let (lo, hi) = unit.iter().fold(
        (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY)),
        |(lo, hi), p| (lo.min(frame * *p), hi.max(frame * *p)),
    );
    let extent = (hi - lo).max(DVec3::splat(1e-9));
    let volume = extent.x * extent.y * extent.z;
    let reach = unit
        .iter()
        .map(|p| p.abs().max_element())
        .fold(0.0, f64::max);
    let farthest = unit.iter().map(|p| p.length()).fold(0.0, f64::max);
    let lm = LmOptions {
        mixture: Mixture {
            outlier_ratio: ctx.opts.outlier_ratio,
            outlier_density: 1.0 / volume,
            sigma2_floor: (SIGMA_FLOOR * extent.length()).powi(2),
        },
        max_rounds: LM_ROUNDS.0,
        steps_per_round: LM_ROUNDS.1,
        tolerance: LM_TOLERANCE,
        metric: Metric::Surface,
        max_semi_axis: LM_SEMI_AXIS_REACH * farthest,
        min_epsilon: LEAST_EPSILON,
        hold_exponents: false,
        own_sigma2: false,
    };
    (lm, volume.cbrt() * reach / 100.0)
}

/// The global stage from the `starts` (unit frame), with the starts of the points that lie on a
/// surface probed too: see the module docs. A fit with local DOFs
/// always tries the similarity candidates: which of them the membrane starts from matters more
/// than their cost, a few Levenberg–Marquardt rounds on a subsample.
pub(super) fn solve_global(ctx: &Context, starts: &[InitialPose]) -> Result<Global, FitError> {
    let probes = super::hypotheses::surface_starts(ctx);
    let opts = &ctx.opts;
    let first = starts
        .first()
        .ok_or_else(|| FitError::BadOption("no initial state to start from".into()))?;
    let (lm, sigma2) = lm_options(ctx, first);
    let switches = if opts.similarity_switch || has_joint_stage(opts) {
        LM_SWITCHES
    } else {
        0
    };
    let solution = solve(
        &ctx.unit,
        (starts, &probes),
        sigma2,
        &lm,
        similarity_candidates,
        switches,
        opts.coverage,
    )
    .ok_or_else(|| FitError::BadOption("no initial state to start from".into()))?;
    let fit = &solution.fit;
    let pose = fit.pose;
    let tess = Tessellation::new(opts.k);
    let mut global = Global {
        state: ModelState::new(&tess, pose.translation, pose.rotation, pose.shape),
        tess,
        start: solution.start,
        sigma2,
        lm,
        steps: solution.iterations,
        global_steps: fit.iterations,
        converged: fit.converged,
        cost: fit.cost,
    };
    let free = opts.dynamics.free;
    if free.taper || free.bend {
        let deformed = solve_deformed(&ctx.unit, &pose, fit.sigma2, &lm, (free.taper, free.bend));
        let (p, state) = (deformed.pose.pose, &mut global.state);
        (state.translation, state.rotation, state.shape) = (p.translation, p.rotation, p.shape);
        state.deformation = deformed.pose.deformation;
        global.steps += deformed.iterations;
        global.global_steps += deformed.iterations;
        global.converged &= deformed.converged;
    }
    Ok(global)
}

/// The global stage held at `pose` (unit frame): the superquadric as given, with the settings a
/// membrane fitted on it reads.
pub(super) fn held_global(ctx: &Context, pose: &InitialPose) -> Global {
    let (lm, sigma2) = lm_options(ctx, pose);
    let tess = Tessellation::new(ctx.opts.k);
    Global {
        state: ModelState::new(&tess, pose.translation, pose.rotation, pose.shape),
        tess,
        start: *pose,
        sigma2,
        lm,
        steps: 0,
        global_steps: 0,
        converged: true,
        cost: 0.0,
    }
}

/// A pure superquadric fitted to `ctx`'s points from `starts` (unit frame) by the lean search
/// ([`super::solve_lean`]): the superquadric alone, without its deformation.
pub(super) fn solve_lean_global(
    ctx: &Context,
    starts: &[InitialPose],
) -> Result<InitialPose, FitError> {
    let first = starts
        .first()
        .ok_or_else(|| FitError::BadOption("no initial state to start from".into()))?;
    let (lm, sigma2) = lm_options(ctx, first);
    solve_lean(&ctx.unit, starts, sigma2, &lm)
        .map(|s| s.fit.pose)
        .ok_or_else(|| FitError::BadOption("no initial state to start from".into()))
}

/// The tapering and bending of a solved fit (`free`: taper, bend) from its superquadric `pose`
/// (unit frame): [`fit_deformed`] from the superquadric with each of its axes as z, undeformed
/// and as the points' centreline shows ([`seed_deformation`]), side by side on a subsample; the
/// one the outlier mixture scores best kept and polished on every point (on [`FINE_POINTS`] of a larger cloud).
fn solve_deformed(
    unit: &[DVec3],
    pose: &InitialPose,
    sigma2: f64,
    lm: &LmOptions,
    (taper, bend): (bool, bool),
) -> DeformedFit {
    let free = [taper, taper, bend, bend];
    let sample = coarse_sample(unit);
    // Tapering and bending act along the model's z: each of the fit's axes in turn as z (the
    // superquadric alone may have put the object's axis on any), undeformed and as its
    // centreline shows.
    let mut starts = Vec::new();
    for turns in 0..3 {
        let turned = turned_axes(pose, turns, false);
        starts.push(DeformedPose {
            pose: turned,
            deformation: GlobalDeformation::IDENTITY,
        });
        // The centreline's start is a new shape: its exponents start round, not at the pure
        // fit's (which may have made a double cone of a cone).
        if let Some((mut p, deformation)) = seed_deformation(&sample, &turned, taper, bend) {
            (p.shape.e1, p.shape.e2) = (1.0, 1.0);
            starts.push(DeformedPose {
                pose: p,
                deformation,
            });
        }
    }
    // The starts are the fitted superquadric's: each begins at its own inliers' variance.
    let lm = &LmOptions {
        own_sigma2: true,
        ..*lm
    };
    let run = |start: &DeformedPose, _: &mut dyn FnMut(&())| {
        fit_deformed(&sample, start, sigma2, lm, free)
    };
    let fits = run_parallel(&starts, run, &mut |_: &()| {});
    let iterations: u32 = fits.iter().map(|f| f.iterations).sum();
    // Ranked as the plain search ranks its fits, by how well the mixture explains the points: a
    // plain mean distance would prefer a surface that passes through the outliers.
    let score = |f: &DeformedFit| lm.mixture.score(&deformed_distances(&f.pose, &sample));
    let mut best = fits
        .into_iter()
        .map(|f| (score(&f), f))
        .filter(|(s, f)| s.is_finite() && f.mean_distance.is_finite())
        .min_by(|a, b| a.0.total_cmp(&b.0))
        .map(|(_, f)| f)
        .unwrap_or(DeformedFit {
            pose: starts[0],
            mean_distance: f64::INFINITY,
            iterations: 0,
            converged: false,
        });
    if sample.len() < unit.len() {
        let fine = LmOptions {
            max_rounds: FINE_ROUNDS,
            ..*lm
        };
        let converged = best.converged;
        best = fit_deformed(
            &spread_sample(unit, FINE_POINTS),
            &best.pose,
            sigma2,
            &fine,
            free,
        );
        best.converged |= converged;
    }
    best.iterations += iterations;
    best
}

impl From<Global> for super::context::Outcome {
    /// A pure superquadric's outcome: the global stage's model as it stands.
    fn from(g: Global) -> Self {
        Self {
            state: g.state,
            tess: g.tess,
            start: g.start,
            steps: g.steps,
            global_steps: g.global_steps,
            reassignments: 0,
            substepped_steps: 0,
            converged: g.converged,
        }
    }
}
