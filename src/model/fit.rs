//! A headless fitting loop: range points in, a deformable superquadric at equilibrium out.
//!
//! The loop is the paper's (section VI-B): attach every data point to its point of influence,
//! then repeat {gather spring forces → Euler step}, reattaching every `reassign_every` steps
//! (200 in the paper). It stops at equilibrium: when the largest node motion in one step falls
//! below `tolerance` × the data's scale right after a reattachment that moved at most
//! `settle_fraction` of the points (0.2 %: noisy points can flip between nodes for ever); or after
//! `max_steps`. A model at rest is reattached at once rather than waiting for the next multiple of
//! N, which reaches the same equilibrium in fewer steps.
//!
//! **Frame and scale.** The loop works on the data translated to its centroid and divided by its
//! RMS radius, and maps the result back, so a fit does not depend on where the data sits or on its
//! units: translate, rotate or scale the input and the result is the same fit, transformed.
//!
//! **Coverage first.** Data-to-model springs cannot pull a part of the model that no data point
//! chose, so the loop starts with the weak model-to-data coverage springs of `forces::range` on,
//! global DOFs only, until the model is at rest; then it switches them off, so the equilibrium is
//! the paper's (data-to-model springs only). `coverage = 0` skips this stage.
//!
//! **Global first.** With `global_first` (default), the local DOFs are held until the global ones
//! have come to rest, so the superquadric parameters capture all they can — what a recogniser
//! indexes — and the local displacements only the detail it misses. The paper lets both move from
//! the start; set `global_first = false` for that.

use super::centreline::{seed_deformation, seen_whole};
use super::deform::GlobalDeformation;
use super::dynamics::{
    DynamicsParams, ModelState, NodalForces, StepError, Workspace, node_positions, step_prepared,
};
use super::fem::Tessellation;
use super::forces::range::{DEFAULT_COVERAGE, InfluenceMode, RangeForces, Robust};
pub use super::init::Normalization;
use super::init::{InitialPose, initial_pose};
pub use super::lm::Solver;
use super::lm::{LmOptions, Metric, Mixture};
use super::superquadric::{LEAST_EPSILON, MIN_EPSILON, SuperquadricParams};
use crate::model::forces::nearest::kd_tree;
use glam::DVec3;
use kiddo::SquaredEuclidean;
use std::f64::consts::SQRT_2;
use std::num::NonZero;

mod options;
mod plan;
mod residuals;
mod solved;
pub use options::*;
pub use plan::*;
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
    /// Steps taken, over every initial hypothesis tried.
    pub steps: u32,
    /// Steps the chosen hypothesis took in the global-only stages.
    pub global_steps: u32,
    /// Reattachments done.
    pub reassignments: u32,
    /// True when the loop stopped at rest rather than at the step cap.
    pub converged: bool,
    /// Steps whose local update was sub-stepped for stability.
    pub substepped_steps: u32,
    /// Point-to-surface residuals of the fitted model.
    pub residuals: Residuals,
    /// Initial pose the loop started from (data frame): the chosen hypothesis, or its
    /// cross-section dual when that fitted closer.
    pub initial: InitialPose,
    /// How the refining stage went, when the options asked for one ([`FitOptions::refine`]).
    pub refinement: Option<Refinement>,
}

/// The outcome of a refining stage ([`FitOptions::refine`], [`Stage::Refine`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Refinement {
    /// Steps the stage took (counted in [`FitReport::steps`] whether kept or not).
    pub steps: u32,
    /// True when the refined superquadric was kept: at rest within [`REFINE_MAX_STEPS`] and no
    /// farther from the points than the global stage's. Otherwise the fit goes on from the global
    /// stage's state.
    pub kept: bool,
    /// True when the stage was given up early, its mean point-to-surface distance past
    /// [`REFINE_GIVE_UP`] times the least it had had at a check (the global stage's at first).
    pub gave_up: bool,
    /// Mean point-to-surface distance before and after the stage, in units of the data's RMS
    /// radius (the fit's working frame).
    pub before: f64,
    /// See [`Refinement::before`].
    pub after: f64,
}

/// The largest distance any node moved between two sets of node positions: the rest measure of
/// [`StageClock::after_step`].
pub fn max_motion(before: &[DVec3], after: &[DVec3]) -> f64 {
    before
        .iter()
        .zip(after)
        .map(|(a, b)| a.distance_squared(*b))
        .fold(0.0, f64::max)
        .sqrt()
}

/// One model relaxing under range springs: the state of the loop between steps.
#[derive(Clone)]
struct Relaxation<'a> {
    tess: &'a Tessellation,
    opts: &'a FitOptions,
    state: ModelState,
    range: RangeForces,
    params: DynamicsParams,
    ws: Workspace,
    forces: NodalForces,
    x: Vec<DVec3>,
    steps: u32,
    global_steps: u32,
    substepped: u32,
    reassignments: u32,
    /// The least mean point-to-surface distance seen so far, when the stage is to be given up (not
    /// at rest) as soon as a check every [`REFINE_CHECK_EVERY`] steps finds the distance more than
    /// [`REFINE_GIVE_UP`] times it: set for the refining stage.
    refine_least: Option<f64>,
    /// The inlier-weighted distance at the refining stage's previous check ([`refine_stalled`]).
    refine_previous: Option<f64>,
    /// The longest semi-axis at the start of the refining stage ([`REFINE_MAX_GROWTH`]).
    refine_start: f64,
    /// Set when a run stopped at that check.
    gave_up: bool,
    /// The closest state a refining stage's checks have seen, with its mean distance, kept for a
    /// tapered or bent fit (see [`Relaxation::refine`]).
    refine_best: Option<(f64, ModelState)>,
    /// The global stage keeps the coverage springs on (a tapered or bent fit of data that
    /// surrounds it; see [`fit`]).
    global_coverage: bool,
}

impl<'a> Relaxation<'a> {
    fn new(
        tess: &'a Tessellation,
        opts: &'a FitOptions,
        unit: &[DVec3],
        start: &InitialPose,
    ) -> Self {
        let state = start_state(tess, opts, unit, start);
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
            refine_least: None,
            refine_previous: None,
            refine_start: 0.0,
            gave_up: false,
            refine_best: None,
            global_coverage: false,
        }
    }

    /// This relaxation moved onto `tess`, another tessellation of the same surface: the global
    /// state is kept, the local displacements are carried over ([`Tessellation::prolong`]), and
    /// the springs are reattached when the next stage starts.
    fn retessellate<'b>(self, tess: &'b Tessellation) -> Relaxation<'b>
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
    fn run(
        &mut self,
        stage: Stage,
        budget: u32,
        progress: &mut impl FnMut(&FitProgress),
    ) -> Result<bool, FitError> {
        let tess = self.tess;
        let mut clock = StageClock::new(stage);
        self.params.free.local = clock.local_free(self.opts);
        self.range.coverage = clock.coverage(self.opts, self.global_coverage);
        self.range.plane = clock.plane(self.opts);
        self.range.mode = clock.influence(self.opts);
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
                (range.reassign(tess, x), range.signature())
            });
            self.reassignments += reassigned as u32;
            if done {
                return Ok(true);
            }
            if let Some(least) = self.refine_least {
                let longest = self.state.shape.semi_axes().max_element();
                if refine_overgrown(longest, self.refine_start) {
                    self.gave_up = true;
                    return Ok(false);
                }
                if !self.steps.is_multiple_of(REFINE_CHECK_EVERY) {
                    continue;
                }
                let (distance, weighted) = refine_distances(tess, &self.x, &self.range);
                let free = self.opts.dynamics.free;
                if (free.taper || free.bend)
                    && self.refine_best.as_ref().is_none_or(|b| distance < b.0)
                {
                    self.refine_best = Some((distance, self.state.clone()));
                }
                self.refine_least = refine_check(distance, least);
                if refine_stalled(weighted, self.refine_previous) {
                    self.refine_least = None;
                }
                self.refine_previous = Some(weighted);
                if self.refine_least.is_none() {
                    self.gave_up = true;
                    return Ok(false);
                }
            }
        }
        Ok(false)
    }

    /// The refining stage from a global stage whose points lay `score` from the surface, within
    /// `cap` steps of this relaxation in all: given up past [`REFINE_GIVE_UP`] times the least
    /// distance seen, and undone (this relaxation back to its state before it) unless it came to
    /// rest no farther than `score`, or — with tapering or bending free — one of its checks saw
    /// a state closer than `score` (then the closest is kept).
    fn refine(
        &mut self,
        score: f64,
        cap: u32,
        progress: &mut impl FnMut(&FitProgress),
    ) -> Result<Refinement, FitError> {
        let before = self.clone();
        let budget = (self.steps + REFINE_MAX_STEPS).min(cap);
        self.refine_least = Some(score);
        self.refine_start = self.state.shape.semi_axes().max_element();
        let at_rest = self.run(Stage::Refine, budget, progress)?;
        let gave_up = self.gave_up;
        (self.refine_least, self.refine_previous, self.gave_up) = (None, None, false);
        let mut after = mean_distance(self.tess, &self.x, self.range.points());
        let mut kept = at_rest && after <= score;
        let steps = self.steps - before.steps;
        // A tapered or bent fit keeps the closest state its checks saw when that is closer than
        // the global stage's: its refinement can come most of the way down and then wobble by a
        // per cent as the deformation creeps on (a cone: 0.043 to 0.0080, then 0.0081), which
        // the rules above, made for runaway pure fits, would undo whole.
        if let Some((distance, state)) = self.refine_best.take()
            && !kept
            && distance <= score
        {
            self.state = state;
            self.state.node_positions(self.tess, &mut self.x);
            (after, kept) = (distance, true);
        }
        if !kept {
            *self = before;
        }
        Ok(Refinement {
            steps,
            kept,
            gave_up,
            before: score,
            after,
        })
    }
}

/// The most threads a fit starts for its axis hypotheses and similarity candidates: one for each
/// up to this many (beyond that each thread takes the next one).
pub const MAX_FIT_THREADS: usize = 8;

/// Runs `job` on every item, each on a thread of its own (up to [`MAX_FIT_THREADS`]; beyond that
/// each thread takes the next item), the calling thread among them and the only one that reports
/// `progress`. Results come back in the items' order, so the outcome does not depend on the
/// scheduling.
///
/// A thread an item rather than one a core: the items are a fit's three axis hypotheses or its
/// three to five similarity candidates, of about equal length, and on two cores a worker a core
/// runs three of them as two after one (the second core idle for the third), where the operating
/// system's time slicing runs them side by side and finishes in about one and a half.
pub(crate) fn run_parallel<I: Sync, R: Send>(
    items: &[I],
    job: impl Fn(&I, &mut dyn FnMut(&FitProgress)) -> R + Sync,
    progress: &mut dyn FnMut(&FitProgress),
) -> Vec<R> {
    use std::sync::Mutex;
    use std::sync::atomic::{AtomicUsize, Ordering};
    let workers = items.len().min(MAX_FIT_THREADS);
    let next = AtomicUsize::new(0);
    let results: Mutex<Vec<(usize, R)>> = Mutex::new(Vec::with_capacity(items.len()));
    let work = |progress: &mut dyn FnMut(&FitProgress)| {
        loop {
            let i = next.fetch_add(1, Ordering::Relaxed);
            let Some(item) = items.get(i) else { break };
            let r = job(item, progress);
            results
                .lock()
                .unwrap_or_else(|e| e.into_inner())
                .push((i, r));
        }
    };
    std::thread::scope(|scope| {
        for _ in 1..workers {
            scope.spawn(|| work(&mut |_: &FitProgress| {}));
        }
        work(progress);
    });
    let mut results = results.into_inner().unwrap_or_else(|e| e.into_inner());
    results.sort_by_key(|(i, _)| *i);
    results.into_iter().map(|(_, r)| r).collect()
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

/// Fits a deformable superquadric to `points`, calling `progress` every 100 steps.
///
/// Stages: coverage (placing, global DOFs), global (the paper's springs, global DOFs), joint
/// (global and local DOFs), each run to rest; see the module docs. With moments initialisation
/// the first two stages run from each of the three axis hypotheses of the moments frame and the
/// one whose surface lies closest to the data goes on. Between choosing and the joint stage, the
/// options may add the cross-section switch ([`FitOptions::switch_cross_section`]), the
/// refining stage ([`FitOptions::refine`]) and, after it, the similarity switch
/// ([`FitOptions::similarity_switch`]). With [`FitOptions::k_from_data`] the joint stage goes on
/// to a finer tessellation chosen from the data ([`joint_k`]).
pub fn fit(
    points: &[DVec3],
    opts: &FitOptions,
    mut progress: impl FnMut(&FitProgress),
) -> Result<FitReport, FitError> {
    validate_points(points)?;
    validate_options(opts)?;
    let norm = Normalization::of(points);
    let unit: Vec<DVec3> = points.iter().map(|p| norm.unit_point(*p)).collect();
    let candidates = initial_hypotheses(points, opts);
    let tess = Tessellation::new(opts.k);
    if uses_lm(opts) {
        return fit_lm(points, opts, &norm, &unit, &candidates, tess, &mut progress);
    }
    let whole = surrounds(&tess, opts, &unit, &norm, &candidates);
    // The joint stage's tessellation, when it is not `tess` ([`FitOptions::k_from_data`]).
    let mut fine = None;
    // The options of a joint stage on that finer tessellation.
    let finer_opts = implicit_joint_options(opts);
    // Each hypothesis gets an equal share of the step cap (as in the plugin's fit driver).
    let share = opts.max_steps / candidates.len().max(1) as u32;
    let run = |initial: &InitialPose, progress: &mut dyn FnMut(&FitProgress)| {
        let mut relax = Relaxation::new(&tess, opts, &unit, &norm.pose_to_unit(initial));
        relax.global_coverage = whole;
        let mut converged = true;
        for stage in global_stages(opts) {
            converged &= relax.run(stage, share, &mut |p: &FitProgress| progress(p))?;
        }
        let score = mean_distance(&tess, &relax.x, relax.range.points());
        Ok::<_, FitError>((score, relax, converged))
    };
    let results = run_parallel(&candidates, run, &mut progress);
    let mut best: Option<(f64, Relaxation, bool, InitialPose)> = None;
    let mut steps_used = 0;
    for (result, initial) in results.into_iter().zip(&candidates) {
        let (score, relax, converged) = result?;
        steps_used += relax.steps;
        // Ties keep the earlier hypothesis, whichever thread finished first.
        if best.as_ref().is_none_or(|b| score < b.0) {
            best = Some((score, relax, converged, *initial));
        }
    }
    let Some((mut score, mut relax, mut converged, mut initial)) = best else {
        return Err(FitError::BadOption("no initial state to start from".into()));
    };
    if opts.switch_cross_section
        && let Some(dual) = cross_section_dual(&InitialPose::of(&relax.state))
    {
        let mut other = Relaxation::new(&tess, opts, &unit, &dual);
        other.global_coverage = whole;
        let budget = opts.max_steps.saturating_sub(steps_used);
        let other_converged = other.run(Stage::Global, budget, &mut progress)?;
        steps_used += other.steps;
        let other_score = mean_distance(&tess, &other.x, other.range.points());
        if other_score < score {
            (score, relax, converged) = (other_score, other, other_converged);
            initial = norm.pose_to_data(&tess, &dual);
        }
    }
    // Steps taken by runs other than `relax` (the other hypotheses, an undone refinement).
    let mut other_steps = steps_used - relax.steps;
    let mut refinement = None;
    // The chosen fit's nodes at the end of its global stage, for the similarity candidates.
    let mut placed = None;
    if opts.refine {
        if opts.similarity_switch {
            placed = Some(relax.x.clone());
        }
        let cap = opts.max_steps.saturating_sub(other_steps);
        // From here on the chosen fit runs alone, so its migration may use every core.
        relax.range.parallel = true;
        let stage = relax.refine(score, cap, &mut progress)?;
        if !stage.kept {
            other_steps += stage.steps;
        }
        refinement = Some(stage);
    }
    if opts.similarity_switch {
        // Every candidate is scored with the chosen fit's inlier probabilities.
        let weights = relax.range.relative_weights();
        let weighted = |x: &[DVec3]| weighted_mean_distance(&tess, x, &unit, &weights);
        let candidates = similarity_candidates(&InitialPose::of(&relax.state));
        let share = similarity_share(opts.max_steps, other_steps + relax.steps, candidates.len());
        let placed = placed.as_deref().map(weighted);
        // The candidates are independent runs: they run side by side like the hypotheses.
        let run = |candidate: &InitialPose, progress: &mut dyn FnMut(&FitProgress)| {
            let mut other = Relaxation::new(&tess, opts, &unit, candidate);
            other.global_coverage = whole;
            let converged = other.run(Stage::Global, share, &mut |p: &FitProgress| progress(p))?;
            let mut undone = 0;
            // The candidate's score, on its worker: after the global stage, and again only if a
            // kept refinement moved it.
            let mut score = weighted(&other.x);
            if opts.refine && placed.is_none_or(|chosen| refine_candidate(score, chosen)) {
                let before = mean_distance(&tess, &other.x, other.range.points());
                let stage = other.refine(before, share, &mut |p: &FitProgress| progress(p))?;
                if stage.kept {
                    score = weighted(&other.x);
                } else {
                    undone = stage.steps;
                }
            }
            Ok::<_, FitError>((other, converged, undone, score))
        };
        let runs = run_parallel(&candidates, run, &mut progress);
        let mut best_score = weighted(&relax.x);
        let mut best: Option<(Relaxation, bool, InitialPose)> = None;
        // In the candidates' order, so that ties and the outcome do not depend on scheduling.
        for (result, candidate) in runs.into_iter().zip(candidates) {
            let (other, other_converged, undone, other_score) = result?;
            other_steps += undone;
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
    if has_joint_stage(opts) {
        let k = if opts.k_from_data {
            joint_k(&tess, &relax.x, relax.range.points(), opts.k)
        } else {
            opts.k
        };
        let budget = opts.max_steps.saturating_sub(other_steps);
        converged = relax.run(Stage::Joint, budget, &mut progress)?;
        if k != tess.k {
            // The membrane at rest on `tess` is the finer one's start (from zero displacements
            // it came to rest 1.02–1.5× farther from the shipped scans), and the global DOFs
            // at rest are held while it comes to rest again by implicit steps (with them free,
            // the same fit at 2–4× the time).
            relax = relax.retessellate(fine.insert(Tessellation::new(k)));
            (relax.opts, relax.params) = (&finer_opts, finer_opts.dynamics);
            converged = relax.run(Stage::Joint, budget, &mut progress)?;
        }
    } else if opts.refine {
        let weights = relax.range.relative_weights();
        if let Some(shape) = extend_squareness(&tess, &relax.state, &unit, &weights) {
            relax.state.shape = shape;
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
        refinement,
    })
}
