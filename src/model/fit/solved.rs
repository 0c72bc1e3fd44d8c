//! The solved fit (beyond the paper; [`Solver::Solved`], the default).
//!
//! The fit's answer is the equilibrium of C q̇ + K q = f_q; the explicit dynamics reach it in
//! thousands of small steps. Here it is solved for:
//!
//! 1. the superquadric by Levenberg–Marquardt ([`crate::model::lm::solve`]: the axis hypotheses
//!    and similarity candidates searched on a subsample, the kept fit polished on every point);
//!    with tapering or bending free, then its deformation with it
//!    ([`crate::model::lm::fit_deformed`], from each of its axes as z, undeformed and as the
//!    points' centreline shows). A pure superquadric ends there;
//! 2. with local DOFs, the membrane with the global DOFs held ([`implicit_joint_options`]): each
//!    step solves (κ + K) d = f + κ d by conjugate gradients for the current attachments and
//!    then reattaches the points, so it ends in tens of steps, on the model's tessellation and
//!    then on a finer one chosen once from the data ([`joint_k`]). The membrane is solved on two
//!    carriers side by side, the fitted superquadric and an ellipsoid placed over the whole cloud
//!    ([`crate::model::lm::ellipsoid_carrier`]; not with tapering or bending free, whose
//!    deformed fit is the carrier), and the one that lies nearer the points is kept: which
//!    carrier a membrane reaches the points from decides where it comes to rest, and neither is
//!    the better on every cloud (docs/results.md, "The solved fit").
//!
//! The membrane sees at most [`FINE_POINTS`] of the points, spread through a larger cloud; the
//! residuals are measured on every point.

use super::*;
use crate::model::dynamics::FreeDofs;
use crate::model::lm::{FINE_POINTS, spread_sample};
use crate::model::superquadric::{LEAST_EPSILON, NUM_SHAPE};

/// True when `opts` ask for the solved fit.
pub fn solves(opts: &FitOptions) -> bool {
    opts.solver == Solver::Solved
}

/// Most EM rounds of a Levenberg–Marquardt fit, and Levenberg–Marquardt steps in a round.
pub const LM_ROUNDS: (u32, u32) = (50, 5);

/// A round of a Levenberg–Marquardt fit that lowers its cost by less than this fraction ends it
/// (0.1 %: the mean distance then moves by about 0.05 % more, below what the figures resolve;
/// on the 26 clouds of docs/results.md 10⁻⁴ changed no fit's mean residual by more than 1 %
/// where both reached the same minimum, at 1.2–1.5 times the steps).
pub const LM_TOLERANCE: f64 = 1e-3;

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

/// [`fit`] by the solved plan (see the module docs) from the `starts` (data frame), the points
/// given in data units and in `norm`'s unit frame. A fit with local DOFs always tries the
/// similarity candidates: which of them the membrane starts from matters more than their cost, a
/// few Levenberg–Marquardt rounds on a subsample.
pub(super) fn fit_solved(
    points: &[DVec3],
    opts: &FitOptions,
    (norm, unit): (&Normalization, &[DVec3]),
    starts: &[InitialPose],
    (progress, watch): Reporting,
) -> Result<FitReport, FitError> {
    let mut tess = Tessellation::new(opts.k);
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
        metric: Metric::Surface,
        max_semi_axis: LM_SEMI_AXIS_REACH * farthest,
        min_epsilon: LEAST_EPSILON,
        hold_exponents: false,
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
    let (mut converged, mut reassignments, substepped) = (fit.converged, 0, 0);
    let free = opts.dynamics.free;
    if free.taper || free.bend {
        let deformed = solve_deformed(unit, &pose, fit.sigma2, &lm, (free.taper, free.bend));
        let p = deformed.pose.pose;
        (state.translation, state.rotation, state.shape) = (p.translation, p.rotation, p.shape);
        state.deformation = deformed.pose.deformation;
        steps += deformed.iterations;
        global_steps += deformed.iterations;
        converged &= deformed.converged;
    }
    watch(&tess, &state);
    if local {
        // The membrane has a thousand-odd nodes: a spread of FINE_POINTS of a larger cloud
        // attaches to them as well as all of it, and keeps each reattachment's search short.
        let unit = &spread_sample(unit, FINE_POINTS)[..];
        let mut carriers = vec![state.clone()];
        // With tapering or bending free the deformed fit is the carrier: its deformation is
        // what was asked for, and a membrane on an ellipsoid would make it up instead.
        if !(free.taper || free.bend)
            && let Some(f) = crate::model::lm::ellipsoid_carrier(unit, &starts, sigma2, &lm)
        {
            let p = f.pose;
            carriers.push(ModelState::new(&tess, p.translation, p.rotation, p.shape));
        }
        let run = |carrier: &ModelState, progress: &mut dyn FnMut(&FitProgress)| {
            membrane(&tess, opts, unit, carrier, steps, progress)
        };
        let mut best: Option<Membrane> = None;
        for m in run_parallel(&carriers, run, &mut |p: &FitProgress| progress(p)) {
            let m = m?;
            if best.as_ref().is_none_or(|b| m.distance < b.distance) {
                best = Some(m);
            }
        }
        let m = best.ok_or(FitError::Degenerate)?;
        steps += m.steps;
        reassignments += m.reassignments;
        converged = m.converged;
        (tess, state) = (m.tess, m.state);
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
        solver: Solver::Solved,
    })
}

/// The tapering and bending of a solved fit (`free`: taper, bend) from its superquadric `pose`
/// (unit frame): [`crate::model::lm::fit_deformed`] from the superquadric with each of its axes as
/// z, undeformed and as the points' centreline shows ([`seed_deformation`]), side by side on a
/// subsample; the nearest to it kept and polished on every point (on [`FINE_POINTS`] of a larger
/// cloud).
fn solve_deformed(
    unit: &[DVec3],
    pose: &InitialPose,
    sigma2: f64,
    lm: &LmOptions,
    (taper, bend): (bool, bool),
) -> crate::model::lm::DeformedFit {
    use crate::model::lm::{DeformedPose, coarse_sample, fit_deformed};
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
    let run = |start: &DeformedPose, _: &mut dyn FnMut(&FitProgress)| {
        fit_deformed(&sample, start, sigma2, lm, free)
    };
    let fits = run_parallel(&starts, run, &mut |_| {});
    let iterations: u32 = fits.iter().map(|f| f.iterations).sum();
    let mut best = fits
        .into_iter()
        .filter(|f| f.mean_distance.is_finite())
        .min_by(|a, b| a.mean_distance.total_cmp(&b.mean_distance))
        .unwrap_or(crate::model::lm::DeformedFit {
            pose: starts[0],
            mean_distance: f64::INFINITY,
            iterations: 0,
            converged: false,
        });
    if sample.len() < unit.len() {
        let fine = LmOptions {
            max_rounds: crate::model::lm::FINE_ROUNDS,
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

/// A membrane at rest on a carrier superquadric ([`membrane`]).
struct Membrane {
    tess: Tessellation,
    state: ModelState,
    /// Mean distance of the points from its mesh (unit frame).
    distance: f64,
    steps: u32,
    reassignments: u32,
    converged: bool,
}

/// The local DOFs brought to rest on the superquadric `carrier` (unit frame, with its
/// deformation), its global DOFs
/// held: by [`implicit_joint_options`]' linear solves for fixed attachments, on `tess` and then,
/// with [`FitOptions::k_from_data`], on the finer tessellation [`joint_k`] chooses from the
/// carrier's nodes (each a few tens of solves). `spent` steps of the options' cap are used.
fn membrane(
    tess: &Tessellation,
    opts: &FitOptions,
    unit: &[DVec3],
    carrier: &ModelState,
    spent: u32,
    progress: &mut dyn FnMut(&FitProgress),
) -> Result<Membrane, FitError> {
    let mut x = Vec::new();
    carrier.node_positions(tess, &mut x);
    let k = if opts.k_from_data {
        joint_k(tess, &x, unit, opts.k)
    } else {
        opts.k
    };
    let joint = implicit_joint_options(opts);
    let budget = opts.max_steps.saturating_sub(spent);
    let fine = Tessellation::new(k);
    let mut relax = Relaxation::from_state(tess, &joint, unit, carrier.clone());
    let mut converged = relax.run(Stage::Joint, budget, &mut |p: &FitProgress| progress(p))?;
    let (steps, reassignments, state, x) = if k != tess.k {
        let mut on_fine = relax.retessellate(&fine);
        converged = on_fine.run(Stage::Joint, budget, &mut |p: &FitProgress| progress(p))?;
        (
            on_fine.steps,
            on_fine.reassignments,
            on_fine.state,
            on_fine.x,
        )
    } else {
        (relax.steps, relax.reassignments, relax.state, relax.x)
    };
    let tess = if k != tess.k { fine } else { tess.clone() };
    let distance = mean_distance(&tess, &x, unit);
    Ok(Membrane {
        tess,
        state,
        distance,
        steps,
        reassignments,
        converged,
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
        let solved = ridged_egg_fit(Solver::Solved);
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
            solver: Solver::Solved,
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
            solver: Solver::Solved,
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
