//! The paper's fit ([`Solver::Dynamics`]): the explicit dynamics of eq. (15) under range
//! springs, stage by stage.
//!
//! The loop is the paper's (section VI-B): attach every data point to its point of influence,
//! then repeat {gather spring forces → Euler step}, reattaching every `reassign_every` steps
//! (200 in the paper), until each stage comes to rest ([`super::relax`]). A model at rest is
//! reattached at once rather than waiting for the next multiple of N, which reaches the same
//! equilibrium in fewer steps.
//!
//! **Coverage first.** Data-to-model springs cannot pull a part of the model that no data point
//! chose, so the fit starts with the weak model-to-data coverage springs of `forces::range` on,
//! global DOFs only, until the model is at rest ([`Stage::Cover`]); then it switches them off, so
//! the equilibrium is the paper's (data-to-model springs only). `coverage = 0` skips this stage.
//!
//! **Global first.** With `global_first` (default), the local DOFs are held until the global ones
//! have come to rest, so the superquadric parameters capture all they can — what a recogniser
//! indexes — and the local displacements only the detail it misses. The paper lets both move from
//! the start; set `global_first = false` for that.
//!
//! With moments initialisation the global stages run from each of the three axis hypotheses of
//! the moments frame side by side, and the one whose surface lies closest to the data goes on.
//! The options may add the cross-section switch ([`FitOptions::switch_cross_section`]) and the
//! similarity switch ([`FitOptions::similarity_switch`]) before the joint stage; with
//! [`FitOptions::k_from_data`] the joint stage goes on to a finer tessellation chosen from the
//! data ([`super::mesh::joint_k`]).
//!
//! [`Solver::Dynamics`]: super::Solver::Dynamics

use super::context::{Context, FitProgress, Outcome, Sink, Stage};
use super::hypotheses::{cross_section_dual, similarity_candidates};
use super::mesh::joint_k;
use super::options::FitError;
use super::relax::{
    Relaxation, global_stages, has_joint_stage, implicit_joint_options, similarity_share, surrounds,
};
use super::residuals::{mean_distance, weighted_mean_distance};
use crate::model::fem::Tessellation;
use crate::model::init::InitialPose;
use crate::model::parallel::run_parallel;
use glam::DVec3;

/// The model the global stages chose, and the steps the runs it beat took.
struct Chosen<'a> {
    relax: Relaxation<'a>,
    converged: bool,
    start: InitialPose,
    /// Steps of every other run.
    other_steps: u32,
}

/// The fit by the paper's dynamics from the `starts` (unit frame): see the module docs.
pub(super) fn fit(
    ctx: &Context,
    starts: &[InitialPose],
    sink: &mut Sink,
) -> Result<Outcome, FitError> {
    let opts = &ctx.opts;
    let tess = Tessellation::new(opts.k);
    let whole = surrounds(&tess, opts, &ctx.unit, starts);
    let mut chosen = race(ctx, &tess, starts, whole, sink.progress)?;
    if opts.switch_cross_section {
        switch_cross_section(ctx, &tess, whole, &mut chosen, sink.progress)?;
    }
    if opts.similarity_switch {
        switch_similar(ctx, &tess, whole, &mut chosen, sink.progress)?;
    }
    (sink.watch)(&tess, &chosen.relax.state);
    let finer_opts = implicit_joint_options(opts);
    let fine;
    let Chosen {
        mut relax,
        mut converged,
        start,
        other_steps,
    } = chosen;
    let mut on = &tess;
    if has_joint_stage(opts) {
        let k = if opts.k_from_data {
            joint_k(&tess, &relax.x, relax.range.points(), opts.k)
        } else {
            opts.k
        };
        let budget = opts.max_steps.saturating_sub(other_steps);
        converged = relax.run(Stage::Joint, budget, sink.progress)?;
        if k != tess.k {
            // The membrane at rest on `tess` is the finer one's start (from zero displacements
            // it came to rest 1.02–1.5× farther from the shipped scans), and the global DOFs
            // at rest are held while it comes to rest again by implicit steps (with them free,
            // the same fit at 2–4× the time).
            fine = Tessellation::new(k);
            relax = relax.retessellate(&fine);
            (relax.opts, relax.params) = (&finer_opts, finer_opts.dynamics);
            converged = relax.run(Stage::Joint, budget, sink.progress)?;
            on = &fine;
        }
    }
    Ok(Outcome {
        state: relax.state,
        tess: on.clone(),
        start,
        steps: relax.steps + other_steps,
        global_steps: relax.global_steps,
        reassignments: relax.reassignments,
        substepped_steps: relax.substepped,
        converged,
    })
}

/// The global stages from every start side by side, each with an equal share of the step cap;
/// the one whose surface lies closest to the points goes on (the earlier on a tie).
fn race<'a>(
    ctx: &'a Context,
    tess: &'a Tessellation,
    starts: &[InitialPose],
    whole: bool,
    progress: &mut dyn FnMut(&FitProgress),
) -> Result<Chosen<'a>, FitError> {
    let opts = &ctx.opts;
    let share = opts.max_steps / starts.len().max(1) as u32;
    let run = |start: &InitialPose, progress: &mut dyn FnMut(&FitProgress)| {
        let mut relax = Relaxation::new(tess, opts, &ctx.unit, start);
        relax.global_coverage = whole;
        let mut converged = true;
        for stage in global_stages(opts) {
            converged &= relax.run(stage, share, &mut |p: &FitProgress| progress(p))?;
        }
        let score = mean_distance(tess, &relax.x, relax.range.points());
        Ok::<_, FitError>((score, relax, converged))
    };
    let mut best: Option<(f64, Relaxation, bool, InitialPose)> = None;
    let mut steps = 0;
    for (result, start) in run_parallel(starts, run, progress).into_iter().zip(starts) {
        let (score, relax, converged) = result?;
        steps += relax.steps;
        if best.as_ref().is_none_or(|b| score < b.0) {
            best = Some((score, relax, converged, *start));
        }
    }
    let (_, relax, converged, start) =
        best.ok_or_else(|| FitError::BadOption("no initial state to start from".into()))?;
    Ok(Chosen {
        other_steps: steps - relax.steps,
        relax,
        converged,
        start,
    })
}

/// The cross-section dual of the chosen model through the global stage; kept when it lies
/// closer to the points.
fn switch_cross_section<'a>(
    ctx: &'a Context,
    tess: &'a Tessellation,
    whole: bool,
    chosen: &mut Chosen<'a>,
    progress: &mut dyn FnMut(&FitProgress),
) -> Result<(), FitError> {
    let Some(dual) = cross_section_dual(&InitialPose::of(&chosen.relax.state)) else {
        return Ok(());
    };
    let spent = chosen.other_steps + chosen.relax.steps;
    let budget = ctx.opts.max_steps.saturating_sub(spent);
    let (other, converged) = global_run(ctx, tess, whole, &dual, budget, progress)?;
    let score = |r: &Relaxation| mean_distance(tess, &r.x, r.range.points());
    if score(&other) < score(&chosen.relax) {
        chosen.other_steps += chosen.relax.steps;
        (chosen.relax, chosen.converged, chosen.start) = (other, converged, dual);
    } else {
        chosen.other_steps += other.steps;
    }
    Ok(())
}

/// The similarity candidates of the chosen model through the global stage side by side, each
/// scored with the chosen fit's inlier probabilities; the closest kept when it beats the chosen
/// one.
fn switch_similar<'a>(
    ctx: &'a Context,
    tess: &'a Tessellation,
    whole: bool,
    chosen: &mut Chosen<'a>,
    progress: &mut dyn FnMut(&FitProgress),
) -> Result<(), FitError> {
    let opts = &ctx.opts;
    let weights = chosen.relax.range.relative_weights();
    let weighted = |x: &[DVec3]| weighted_mean_distance(tess, x, &ctx.unit, &weights);
    let candidates = similarity_candidates(&InitialPose::of(&chosen.relax.state));
    let spent = chosen.other_steps + chosen.relax.steps;
    let share = similarity_share(opts.max_steps, spent, candidates.len());
    let run = |candidate: &InitialPose, progress: &mut dyn FnMut(&FitProgress)| {
        let (other, converged) = global_run(ctx, tess, whole, candidate, share, progress)?;
        let score = weighted(&other.x);
        Ok::<_, FitError>((other, converged, score))
    };
    let runs = run_parallel(&candidates, run, progress);
    let mut best_score = weighted(&chosen.relax.x);
    let mut best: Option<(Relaxation, bool, InitialPose)> = None;
    // In the candidates' order, so that ties and the outcome do not depend on scheduling.
    for (result, candidate) in runs.into_iter().zip(candidates) {
        let (other, converged, score) = result?;
        if score < best_score {
            best_score = score;
            if let Some((old, _, _)) = best.replace((other, converged, candidate)) {
                chosen.other_steps += old.steps;
            }
        } else {
            chosen.other_steps += other.steps;
        }
    }
    if let Some((other, converged, candidate)) = best {
        chosen.other_steps += chosen.relax.steps;
        (chosen.relax, chosen.converged, chosen.start) = (other, converged, candidate);
    }
    Ok(())
}

/// The global stage from `start` (unit frame) within `budget` steps, the coverage springs on
/// when the data surrounds the model (`whole`): the relaxation and whether it came to rest.
fn global_run<'a>(
    ctx: &'a Context,
    tess: &'a Tessellation,
    whole: bool,
    start: &InitialPose,
    budget: u32,
    progress: &mut dyn FnMut(&FitProgress),
) -> Result<(Relaxation<'a>, bool), FitError> {
    let mut relax = Relaxation::new(tess, &ctx.opts, &ctx.unit, start);
    relax.global_coverage = whole;
    let converged = relax.run(Stage::Global, budget, progress)?;
    Ok((relax, converged))
}
