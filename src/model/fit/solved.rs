//! Fits that solve for their rest state (beyond the paper): [`Solver::LevenbergMarquardt`].
//!
//! The fit's answer is the equilibrium of C q̇ + K q = f_q; the explicit dynamics reach it in
//! thousands of small steps. Here the superquadric is solved for by Levenberg–Marquardt
//! ([`crate::model::lm::solve`]: the axis hypotheses and similarity candidates compared after a
//! few rounds, on a subsample). A pure superquadric ends there. A fit with local DOFs then
//!
//! 1. runs the dynamics' global stages ([`global_stages`]) from the solved pose: their
//!    model-to-data coverage springs wrap the superquadric round the data, so that the membrane
//!    has its nodes where the data is (from the solved pose alone, the local DOFs of a one-view
//!    scan came to rest up to 2.4 times farther from the points);
//! 2. holds the global DOFs there and brings the local DOFs to rest by implicit steps
//!    ([`implicit_joint_options`]): each step solves (κ + K) d = f + κ d by conjugate gradients
//!    for the current attachments, then reattaches the points, so the stage ends in tens of
//!    steps.
//!
//! Both stages see at most [`FINE_POINTS`] of the points, spread through a larger cloud; the
//! residuals are measured on every point.

use super::*;
use crate::model::dynamics::FreeDofs;
use crate::model::lm::{FINE_POINTS, spread_sample};
use crate::model::superquadric::NUM_SHAPE;

/// True when `opts` ask for the Levenberg–Marquardt solve and the fit is one it can do: no
/// tapering or bending.
pub fn uses_lm(opts: &FitOptions) -> bool {
    let free = &opts.dynamics.free;
    opts.solver == Solver::LevenbergMarquardt && !free.taper && !free.bend
}

/// Most EM rounds of a Levenberg–Marquardt fit, and Levenberg–Marquardt steps in a round.
pub const LM_ROUNDS: (u32, u32) = (50, 5);

/// A round of a Levenberg–Marquardt fit that lowers its cost by less than this fraction ends it.
pub const LM_TOLERANCE: f64 = 1e-4;

/// Similarity switches a Levenberg–Marquardt fit makes at most (EMS's `MaxiSwitch`).
pub const LM_SWITCHES: u32 = 2;

/// The longest semi-axis a Levenberg–Marquardt fit may reach, in units of the farthest point's
/// distance from the data's centroid ([`crate::model::lm::LmOptions::max_semi_axis`]), so at
/// most the data's widest extent. Unbounded, the bunny scan's superquadric stretched to 5.5 times
/// that extent on the side no point sees.
pub const LM_SEMI_AXIS_REACH: f64 = 2.0;

/// The time step of [`implicit_joint_options`] over the options' own. The local block is taken
/// implicitly, so its damping γ_d A/Δt then weighs nothing next to the springs and the membrane,
/// and a step brings the local DOFs to the springs' equilibrium.
pub const IMPLICIT_JOINT_DT_SCALE: f64 = 1e4;

/// The options of the joint stage of a solved fit: the global DOFs held, the local block of
/// eq. (15) taken as one backward-Euler step ([`DynamicsParams::implicit_local`]) at a time step
/// [`IMPLICIT_JOINT_DT_SCALE`] times the options' own, so that each step solves
/// (κ + K) d = f + κ d for the current attachments, and the points reattached after every step.
/// The stage is over when a step moves no node by more than the tolerance and the reattachment
/// after it changes (almost) nothing: the equilibrium K d = f_d of those attachments.
pub fn implicit_joint_options(opts: &FitOptions) -> FitOptions {
    let d = opts.dynamics;
    FitOptions {
        dynamics: DynamicsParams {
            dt: d.dt * IMPLICIT_JOINT_DT_SCALE,
            implicit_local: true,
            free: FreeDofs {
                translation: false,
                rotation: false,
                shape: [false; NUM_SHAPE],
                taper: false,
                bend: false,
                ..d.free
            },
            ..d
        },
        reassign_every: 1,
        ..*opts
    }
}

/// [`fit`] by [`crate::model::lm::solve`] from the `starts` (unit frame of `norm`, data units
/// given), then the module's stages for the local DOFs, or for a pure superquadric the
/// squareness extension when the options ask for the refining stage. A fit with local DOFs always
/// tries the similarity candidates: which of them the membrane starts from matters more than
/// their cost, a few Levenberg–Marquardt rounds on a subsample.
pub(super) fn fit_lm(
    points: &[DVec3],
    opts: &FitOptions,
    norm: &Normalization,
    unit: &[DVec3],
    starts: &[InitialPose],
    mut tess: Tessellation,
    progress: &mut impl FnMut(&FitProgress),
) -> Result<FitReport, FitError> {
    let starts: Vec<InitialPose> = starts.iter().map(|s| norm.pose_to_unit(s)).collect();
    // The outliers' box and EMS's first σ², in the first start's frame.
    let frame = starts[0].rotation.inverse();
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
    let sigma2 = volume.cbrt() * reach / 100.0;
    let diagonal = extent.length();
    let farthest = unit.iter().map(|p| p.length()).fold(0.0, f64::max);
    let lm = LmOptions {
        mixture: Mixture {
            outlier_ratio: opts.outlier_ratio,
            outlier_density: 1.0 / volume,
            sigma2_floor: (crate::model::forces::range::SIGMA_FLOOR * diagonal).powi(2),
        },
        max_rounds: LM_ROUNDS.0,
        steps_per_round: LM_ROUNDS.1,
        tolerance: LM_TOLERANCE,
        metric: Metric::Radial,
        max_semi_axis: LM_SEMI_AXIS_REACH * farthest,
    };
    let local = has_joint_stage(opts);
    let switches = if opts.similarity_switch || local {
        LM_SWITCHES
    } else {
        0
    };
    let solution =
        crate::model::lm::solve(unit, &starts, sigma2, &lm, similarity_candidates, switches)
            .ok_or_else(|| FitError::BadOption("no initial state to start from".into()))?;
    let fit = &solution.fit;
    let pose = fit.pose;
    let mut state = ModelState::new(&tess, pose.translation, pose.rotation, pose.shape);
    let (mut steps, mut global_steps) = (solution.iterations, fit.iterations);
    let (mut converged, mut reassignments, mut substepped) = (fit.converged, 0, 0);
    if local {
        // The membrane has a thousand-odd nodes: a spread of FINE_POINTS of a larger cloud
        // attaches to them as well as all of it, and keeps each reattachment's search short.
        let unit = &spread_sample(unit, FINE_POINTS)[..];
        let mut placed = Relaxation::new(&tess, opts, unit, &pose);
        for stage in global_stages(opts) {
            let budget = opts.max_steps.saturating_sub(steps);
            placed.run(stage, budget, &mut |p: &FitProgress| progress(p))?;
        }
        let k = if opts.k_from_data {
            joint_k(&tess, &placed.x, placed.range.points(), opts.k)
        } else {
            opts.k
        };
        let pose = InitialPose::of(&placed.state);
        steps += placed.steps;
        global_steps += placed.steps;
        (reassignments, substepped) = (placed.reassignments, placed.substepped);
        drop(placed);
        let joint = implicit_joint_options(opts);
        let mut relax = Relaxation::new(&tess, &joint, unit, &pose);
        let budget = opts.max_steps.saturating_sub(steps);
        converged = relax.run(Stage::Joint, budget, &mut |p: &FitProgress| progress(p))?;
        // The membrane at rest on `tess` is the finer one's start ([`FitOptions::k_from_data`]);
        // the step count runs on through both.
        let (joint_steps, joint_reassignments, joint_state) = if k != tess.k {
            let fine = Tessellation::new(k);
            let mut on_fine = relax.retessellate(&fine);
            converged = on_fine.run(Stage::Joint, budget, &mut |p: &FitProgress| progress(p))?;
            let out = (on_fine.steps, on_fine.reassignments, on_fine.state);
            tess = fine;
            out
        } else {
            (relax.steps, relax.reassignments, relax.state)
        };
        steps += joint_steps;
        reassignments += joint_reassignments;
        state = joint_state;
    } else if opts.refine {
        let weights = if fit.weights.is_empty() {
            vec![1.0; unit.len()]
        } else if fit.weights.len() == unit.len() {
            fit.weights.clone()
        } else {
            // The last stage saw a subsample: every point's weight, at the fit.
            let weigh = |p: &DVec3| {
                let d = Metric::Surface.distance(&pose, *p);
                lm.mixture.inlier(d, fit.sigma2)
            };
            unit.iter().map(weigh).collect()
        };
        if let Some(shape) = extend_squareness(&tess, &state, unit, &weights) {
            state.shape = shape;
        }
    }
    progress(&FitProgress {
        step: steps,
        stage: if local { Stage::Joint } else { Stage::Global },
        max_motion: 0.0,
        energy: fit.cost,
        reassignments,
    });
    let state = norm.state_to_data(&state);
    let residuals = fit_residuals(&tess, &state, points);
    Ok(FitReport {
        state,
        steps,
        global_steps,
        reassignments,
        converged,
        substepped_steps: substepped,
        residuals,
        initial: norm.pose_to_data(&tess, &solution.start),
        tess,
        refinement: None,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::synthetic::ridged_egg;

    /// The ridged egg (no superquadric has its five ridges) with the fitter's defaults for a
    /// user's cloud, through `solver`.
    fn ridged_egg_fit(solver: Solver) -> FitReport {
        let points = ridged_egg(1500, 3);
        let (opts, _) = FitOptions {
            solver,
            ..FitOptions::default().for_data()
        }
        .with_stiffness_from_noise(&points);
        fit(&points, &opts, |_| {}).expect("the ridged egg fits")
    }

    #[test]
    fn a_solved_fit_with_local_dofs_matches_the_dynamics_in_far_fewer_steps() {
        let solved = ridged_egg_fit(Solver::LevenbergMarquardt);
        let relaxed = ridged_egg_fit(Solver::Dynamics);
        assert!(solved.converged && solved.state.is_finite());
        let (a, b) = (solved.residuals.mean, relaxed.residuals.mean);
        // Holding the global DOFs costs a little: 1.137e-3 against 1.052e-3 here.
        assert!(a <= 1.1 * b, "solved {a}, dynamics {b}");
        assert!(
            3 * solved.steps < relaxed.steps,
            "solved {} steps, dynamics {}",
            solved.steps,
            relaxed.steps
        );
        // The local DOFs did the work of the ridges: far closer than the superquadric alone.
        let pure_options = FitOptions {
            solver: Solver::LevenbergMarquardt,
            global_only: true,
            ..FitOptions::default()
        };
        let pure = fit(&ridged_egg(1500, 3), &pure_options.for_data(), |_| {}).expect("pure");
        let c = pure.residuals.mean;
        assert!(a < 0.5 * c, "with local DOFs {a}, pure {c}");
    }

    #[test]
    fn a_cloud_past_twice_fine_points_fits_with_local_dofs_on_a_spread_of_them() {
        use crate::synthetic::superquadric_cloud;
        let shape = SuperquadricParams {
            a: 2.0,
            a1: 1.0,
            a2: 0.6,
            a3: 0.35,
            e1: 0.7,
            e2: 1.2,
        };
        let n = 2 * FINE_POINTS + 5000;
        let points = superquadric_cloud(
            &shape,
            DVec3::new(3.0, -1.0, 2.0),
            glam::DQuat::IDENTITY,
            n,
            0.0,
            17,
        );
        let opts = FitOptions {
            solver: Solver::LevenbergMarquardt,
            ..FitOptions::default().for_data()
        };
        let r = fit(&points, &opts, |_| {}).expect("the cloud fits");
        assert!(r.converged && r.state.is_finite());
        // The membrane's chords over a superquadric the solve recovered: about 1e-3 of the
        // diagonal, measured on every point.
        assert!(r.residuals.mean < 3e-3, "{:?}", r.residuals);
        let axes = r.state.shape.semi_axes();
        let mut found = axes.to_array();
        found.sort_by(f64::total_cmp);
        let mut truth = shape.semi_axes().to_array();
        truth.sort_by(f64::total_cmp);
        for (f, t) in found.iter().zip(truth) {
            assert!((f / t - 1.0).abs() < 0.02, "{axes} against {truth:?}");
        }
    }

    #[test]
    fn the_implicit_joint_stage_lowers_the_energy_and_holds_the_global_dofs() {
        let points = ridged_egg(800, 5);
        let norm = Normalization::of(&points);
        let unit: Vec<DVec3> = points.iter().map(|p| norm.unit_point(*p)).collect();
        let base = FitOptions::default().for_data();
        let opts = implicit_joint_options(&base);
        let tess = Tessellation::new(base.k);
        let start = norm.pose_to_unit(&initial_hypotheses(&points, &base)[0]);
        let mut relax = Relaxation::new(&tess, &opts, &unit, &start);
        let energy = |r: &Relaxation| {
            let mut x = Vec::new();
            r.state.node_positions(&tess, &mut x);
            let mut range = r.range.clone();
            range.reassign(&tess, &x);
            range.energy(&tess, &x)
                + tess.strain_energy(opts.dynamics.w0, opts.dynamics.w1, &r.state.displacement)
        };
        let before = energy(&relax);
        let global = (
            relax.state.translation,
            relax.state.rotation,
            relax.state.shape,
        );
        let at_rest = relax
            .run(Stage::Joint, 200, &mut |_| {})
            .expect("the stage runs");
        let after = energy(&relax);
        assert!(at_rest, "rest within 200 steps");
        assert!(relax.steps < 60, "{} steps", relax.steps);
        assert!(relax.state.is_finite());
        assert!(after < 0.5 * before, "energy {before} → {after}");
        assert_eq!(
            global,
            (
                relax.state.translation,
                relax.state.rotation,
                relax.state.shape
            )
        );
    }
}
