//! The paper's fit ([`Solver::Dynamics`]): the explicit dynamics of eq. (15) under range
//! springs, stage by stage.
//!
//! The loop is the paper's (section VI-B): attach every data point to its point of influence,
//! then repeat {gather spring forces → Euler step}, reattaching every `reassign_every` steps
//! (200 in the paper). A stage stops at equilibrium: when the largest node motion in one step
//! falls below `tolerance` × the data's scale right after a reattachment that moved at most
//! `settle_fraction` of the points, and at least one ([`StageClock::after_step`]); or after
//! `max_steps`. A model at rest is reattached at once rather than waiting for the next multiple
//! of N, which reaches the same equilibrium in fewer steps.
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
//! data ([`joint_k`]).

use super::*;

/// One model relaxing under range springs: the state of the loop between steps.
#[derive(Clone)]
pub(super) struct Relaxation<'a> {
    pub(super) tess: &'a Tessellation,
    pub(super) opts: &'a FitOptions,
    pub(super) state: ModelState,
    pub(super) range: RangeForces,
    pub(super) params: DynamicsParams,
    pub(super) ws: Workspace,
    pub(super) forces: NodalForces,
    pub(super) x: Vec<DVec3>,
    pub(super) steps: u32,
    pub(super) global_steps: u32,
    pub(super) substepped: u32,
    pub(super) reassignments: u32,
    /// The global stage keeps the coverage springs on (a tapered or bent fit of data that
    /// surrounds it; see [`fit`]).
    pub(super) global_coverage: bool,
}

impl<'a> Relaxation<'a> {
    pub(super) fn new(
        tess: &'a Tessellation,
        opts: &'a FitOptions,
        unit: &[DVec3],
        start: &InitialPose,
    ) -> Self {
        Self::from_state(tess, opts, unit, start_state(tess, opts, unit, start))
    }

    /// A relaxation of `unit` from `state` as it is (its deformation and displacements kept).
    pub(super) fn from_state(
        tess: &'a Tessellation,
        opts: &'a FitOptions,
        unit: &[DVec3],
        state: ModelState,
    ) -> Self {
        let mut range = RangeForces::new(unit.to_vec(), opts.beta, opts.influence);
        range.coverage = 0.0;
        range.robust = (opts.outlier_ratio > 0.0).then(|| Robust::new(opts.outlier_ratio));
        let mut x = Vec::new();
        state.node_positions(tess, &mut x);
        Self {
            tess,
            opts,
            state,
            range,
            params: opts.dynamics,
            ws: Workspace::default(),
            forces: NodalForces::new(tess.node_count()),
            x,
            steps: 0,
            global_steps: 0,
            substepped: 0,
            reassignments: 0,
            global_coverage: false,
        }
    }

    /// This relaxation moved onto `tess`, another tessellation of the same surface: the global
    /// state is kept, the local displacements are carried over ([`Tessellation::prolong`]), and
    /// the springs are reattached when the next stage starts.
    pub(super) fn retessellate<'b>(self, tess: &'b Tessellation) -> Relaxation<'b>
    where
        'a: 'b,
    {
        let mut state = self.state;
        state.displacement = tess.prolong(self.tess, &state.displacement);
        let mut x = Vec::new();
        state.node_positions(tess, &mut x);
        Relaxation {
            tess,
            state,
            ws: Workspace::default(),
            forces: NodalForces::new(tess.node_count()),
            x,
            ..self
        }
    }

    /// Runs `stage` until it is over (true; see [`StageClock::after_step`]), or until `budget`
    /// total steps (false).
    pub(super) fn run(
        &mut self,
        stage: Stage,
        budget: u32,
        progress: &mut dyn FnMut(&FitProgress),
    ) -> Result<bool, FitError> {
        let tess = self.tess;
        let mut clock = StageClock::new(stage);
        self.params.free.local = clock.local_free(self.opts);
        self.range.coverage = clock.coverage(self.opts, self.global_coverage);
        self.range.plane = clock.plane(self.opts);
        self.range.mode = self.opts.influence;
        self.range.reassign(tess, &self.x);
        self.reassignments += 1;
        self.ws.prepare(tess, &self.state);
        while self.steps < budget {
            self.range
                .migrate(tess, &self.x, Some(&self.state.surface()));
            self.forces.clear(tess.node_count());
            self.range.accumulate(tess, &self.x, &mut self.forces);
            let report = step_prepared(
                tess,
                &mut self.state,
                &self.forces,
                &self.params,
                &mut self.ws,
            )
            .map_err(FitError::Step)?;
            self.steps += 1;
            if stage != Stage::Joint {
                self.global_steps += 1;
            }
            if report.substeps > 1 {
                self.substepped += 1;
            }
            let x_new = self.ws.prepare(tess, &self.state);
            let motion = max_motion(&self.x, x_new);
            self.x.clear();
            self.x.extend_from_slice(x_new);
            if self.steps.is_multiple_of(100) {
                let energy = self.range.energy(tess, &self.x)
                    + tess.strain_energy(self.params.w0, self.params.w1, &self.state.displacement);
                progress(&FitProgress {
                    step: self.steps,
                    stage,
                    max_motion: motion,
                    energy,
                    reassignments: self.reassignments,
                });
            }
            let (range, x) = (&mut self.range, &self.x);
            let mut reassigned = false;
            let done = clock.after_step(motion, self.opts, range.points().len(), || {
                reassigned = true;
                range.reassign(tess, x)
            });
            self.reassignments += reassigned as u32;
            if done {
                return Ok(true);
            }
        }
        Ok(false)
    }
}

/// Whether a fit that frees tapering or bending keeps the model-to-data coverage springs on in
/// its global stages (beyond the paper). Tapering and bending let a model run on past the ends of
/// its data, which the data-to-model springs do not see: a cone's tip grown round, a banana longer
/// and more bent than it is. The coverage springs hold the model to the data's extent, but on a
/// one-view scan they would pull the unseen side onto the seen one; so they stay on only when the
/// data surrounds the start of one of the hypotheses ([`seen_whole`]).
pub(crate) fn surrounds(
    tess: &Tessellation,
    opts: &FitOptions,
    unit: &[DVec3],
    norm: &Normalization,
    candidates: &[InitialPose],
) -> bool {
    let free = opts.dynamics.free;
    if !(free.taper || free.bend) || opts.coverage <= 0.0 {
        return false;
    }
    let mut x = Vec::new();
    candidates.iter().any(|candidate| {
        let state = start_state(tess, opts, unit, &norm.pose_to_unit(candidate));
        state.node_positions(tess, &mut x);
        seen_whole(tess, &x, unit, state.shape.semi_axes().min_element())
    })
}

/// The state a relaxation of `unit` starts from at `start`: with tapering or bending free, moved
/// and deformed as the data's centreline shows ([`seed_deformation`]).
pub(crate) fn start_state(
    tess: &Tessellation,
    opts: &FitOptions,
    unit: &[DVec3],
    start: &InitialPose,
) -> ModelState {
    let free = opts.dynamics.free;
    let (start, deformation) = seed_deformation(unit, start, free.taper, free.bend)
        .unwrap_or((*start, GlobalDeformation::IDENTITY));
    let mut state = ModelState::new(
        tess,
        start.translation,
        start.rotation,
        start.shape.normalized(),
    );
    state.deformation = deformation;
    state
}

/// [`fit`] by the paper's dynamics: see the module docs. `unit` are the points in `norm`'s
/// frame and `candidates` the initial hypotheses (data frame).
pub(super) fn fit_dynamics(
    points: &[DVec3],
    opts: &FitOptions,
    (norm, unit): (&Normalization, &[DVec3]),
    candidates: &[InitialPose],
    (progress, watch): Reporting,
) -> Result<FitReport, FitError> {
    let tess = Tessellation::new(opts.k);
    let whole = surrounds(&tess, opts, unit, norm, candidates);
    // The joint stage's tessellation, when it is not `tess` ([`FitOptions::k_from_data`]).
    let mut fine = None;
    // The options of a joint stage on that finer tessellation.
    let finer_opts = implicit_joint_options(opts);
    // Each hypothesis gets an equal share of the step cap.
    let share = opts.max_steps / candidates.len().max(1) as u32;
    let run = |initial: &InitialPose, progress: &mut dyn FnMut(&FitProgress)| {
        let mut relax = Relaxation::new(&tess, opts, unit, &norm.pose_to_unit(initial));
        relax.global_coverage = whole;
        let mut converged = true;
        for stage in global_stages(opts) {
            converged &= relax.run(stage, share, &mut |p: &FitProgress| progress(p))?;
        }
        let score = mean_distance(&tess, &relax.x, relax.range.points());
        Ok::<_, FitError>((score, relax, converged))
    };
    let results = run_parallel(candidates, run, progress);
    let mut best: Option<(f64, Relaxation, bool, InitialPose)> = None;
    let mut steps_used = 0;
    for (result, initial) in results.into_iter().zip(candidates) {
        let (score, relax, converged) = result?;
        steps_used += relax.steps;
        // Ties keep the earlier hypothesis, whichever thread finished first.
        if best.as_ref().is_none_or(|b| score < b.0) {
            best = Some((score, relax, converged, *initial));
        }
    }
    let Some((score, mut relax, mut converged, mut initial)) = best else {
        return Err(FitError::BadOption("no initial state to start from".into()));
    };
    if opts.switch_cross_section
        && let Some(dual) = cross_section_dual(&InitialPose::of(&relax.state))
    {
        let mut other = Relaxation::new(&tess, opts, unit, &dual);
        other.global_coverage = whole;
        let budget = opts.max_steps.saturating_sub(steps_used);
        let other_converged = other.run(Stage::Global, budget, progress)?;
        steps_used += other.steps;
        let other_score = mean_distance(&tess, &other.x, other.range.points());
        if other_score < score {
            (relax, converged) = (other, other_converged);
            initial = norm.pose_to_data(&tess, &dual);
        }
    }
    // Steps taken by runs other than `relax` (the other hypotheses and candidates).
    let mut other_steps = steps_used - relax.steps;
    if opts.similarity_switch {
        // Every candidate is scored with the chosen fit's inlier probabilities.
        let weights = relax.range.relative_weights();
        let weighted = |x: &[DVec3]| weighted_mean_distance(&tess, x, unit, &weights);
        let candidates = similarity_candidates(&InitialPose::of(&relax.state));
        let share = similarity_share(opts.max_steps, other_steps + relax.steps, candidates.len());
        // The candidates are independent runs: they run side by side like the hypotheses.
        let run = |candidate: &InitialPose, progress: &mut dyn FnMut(&FitProgress)| {
            let mut other = Relaxation::new(&tess, opts, unit, candidate);
            other.global_coverage = whole;
            let converged = other.run(Stage::Global, share, &mut |p: &FitProgress| progress(p))?;
            let score = weighted(&other.x);
            Ok::<_, FitError>((other, converged, score))
        };
        let runs = run_parallel(&candidates, run, progress);
        let mut best_score = weighted(&relax.x);
        let mut best: Option<(Relaxation, bool, InitialPose)> = None;
        // In the candidates' order, so that ties and the outcome do not depend on scheduling.
        for (result, candidate) in runs.into_iter().zip(candidates) {
            let (other, other_converged, other_score) = result?;
            if other_score < best_score {
                best_score = other_score;
                if let Some((old, _, _)) = best.replace((other, other_converged, candidate)) {
                    other_steps += old.steps;
                }
            } else {
                other_steps += other.steps;
            }
        }
        if let Some((other, other_converged, candidate)) = best {
            other_steps += relax.steps;
            (relax, converged) = (other, other_converged);
            initial = norm.pose_to_data(&tess, &candidate);
        }
    }
    watch(&tess, &relax.state);
    if has_joint_stage(opts) {
        let k = if opts.k_from_data {
            joint_k(&tess, &relax.x, relax.range.points(), opts.k)
        } else {
            opts.k
        };
        let budget = opts.max_steps.saturating_sub(other_steps);
        converged = relax.run(Stage::Joint, budget, progress)?;
        if k != tess.k {
            // The membrane at rest on `tess` is the finer one's start (from zero displacements
            // it came to rest 1.02–1.5× farther from the shipped scans), and the global DOFs
            // at rest are held while it comes to rest again by implicit steps (with them free,
            // the same fit at 2–4× the time).
            relax = relax.retessellate(fine.insert(Tessellation::new(k)));
            (relax.opts, relax.params) = (&finer_opts, finer_opts.dynamics);
            converged = relax.run(Stage::Joint, budget, progress)?;
        }
    }
    let state = norm.state_to_data(&relax.state);
    let (steps, global_steps) = (relax.steps + other_steps, relax.global_steps);
    let (reassignments, substepped_steps) = (relax.reassignments, relax.substepped);
    let tess = fine.unwrap_or(tess);
    let residuals = fit_residuals(&tess, &state, points);
    Ok(FitReport {
        state,
        steps,
        global_steps,
        reassignments,
        converged,
        substepped_steps,
        residuals,
        initial,
        tess,
        solver: Solver::Dynamics,
    })
}
