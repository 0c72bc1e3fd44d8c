//! The solved fit's membrane (beyond the paper): the local DOFs brought to rest with the global
//! DOFs held ([`implicit_joint_options`]). Each step solves (κ + K) d = f + κ d by conjugate
//! gradients for the current attachments and then reattaches the points, so it ends in tens of
//! steps, on the model's tessellation and then on a finer one chosen once from the data
//! ([`joint_k`]).
//!
//! The membrane is solved on two carriers side by side, the fitted superquadric and an ellipsoid
//! placed over the whole cloud ([`ellipsoid_carrier`]; not with tapering or bending free, whose
//! deformed fit is the carrier), and the one that lies nearer the points is kept: which carrier
//! a membrane reaches the points from decides where it comes to rest, and neither is the better
//! on every cloud (docs/results.md, "The solved fit"). The membrane sees at most [`FINE_POINTS`]
//! of the points, spread through a larger cloud.

use super::context::{Context, FitProgress, Outcome, Sink, Stage};
use super::global::Global;
use super::mesh::joint_k;
use super::options::FitError;
use super::relax::{Relaxation, implicit_joint_options};
use super::residuals::mean_distance;
use super::search::{FINE_POINTS, ellipsoid_carrier, spread_sample};
use crate::model::dynamics::ModelState;
use crate::model::fem::Tessellation;
use crate::model::init::InitialPose;
use crate::model::parallel::run_parallel;
use glam::DVec3;

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

/// The membrane of `global`'s superquadric (see the module docs), the ellipsoid carrier placed
/// from the `starts` (unit frame).
pub(super) fn solve_membrane(
    ctx: &Context,
    starts: &[InitialPose],
    global: Global,
    sink: &mut Sink,
) -> Result<Outcome, FitError> {
    // The membrane has a thousand-odd nodes: a spread of FINE_POINTS of a larger cloud attaches
    // to them as well as all of it, and keeps each reattachment's search short.
    let unit = &spread_sample(&ctx.unit, FINE_POINTS)[..];
    let free = ctx.opts.dynamics.free;
    let tess = &global.tess;
    let mut carriers = vec![global.state.clone()];
    // With tapering or bending free the deformed fit is the carrier: its deformation is what was
    // asked for, and a membrane on an ellipsoid would make it up instead.
    if !(free.taper || free.bend)
        && let Some(f) =
            ellipsoid_carrier(unit, starts, global.sigma2, &global.lm, ctx.opts.coverage)
    {
        let p = f.pose;
        carriers.push(ModelState::new(tess, p.translation, p.rotation, p.shape));
    }
    let run = |carrier: &ModelState, progress: &mut dyn FnMut(&FitProgress)| {
        membrane(tess, ctx, unit, carrier, global.steps, progress)
    };
    let mut best: Option<Membrane> = None;
    for m in run_parallel(&carriers, run, &mut |p: &FitProgress| (sink.progress)(p)) {
        let m = m?;
        if best.as_ref().is_none_or(|b| m.distance < b.distance) {
            best = Some(m);
        }
    }
    let m = best.ok_or(FitError::Degenerate)?;
    Ok(Outcome {
        state: m.state,
        tess: m.tess,
        start: global.start,
        steps: global.steps + m.steps,
        global_steps: global.global_steps,
        reassignments: m.reassignments,
        substepped_steps: 0,
        converged: m.converged,
    })
}

/// The local DOFs brought to rest on the superquadric `carrier` (unit frame, with its
/// deformation), its global DOFs held: by [`implicit_joint_options`]' linear solves for fixed
/// attachments, on `tess` and then, with [`crate::model::fit::FitOptions::k_from_data`], on the
/// finer tessellation [`joint_k`] chooses from the carrier's nodes (each a few tens of solves).
/// `spent` steps of the options' cap are used.
fn membrane(
    tess: &Tessellation,
    ctx: &Context,
    unit: &[DVec3],
    carrier: &ModelState,
    spent: u32,
    progress: &mut dyn FnMut(&FitProgress),
) -> Result<Membrane, FitError> {
    let opts = &ctx.opts;
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
