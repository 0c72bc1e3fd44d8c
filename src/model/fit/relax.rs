//! One model relaxing under range springs by the paper's explicit dynamics (eq. 15), stage by
//! stage ([`Relaxation`]), and the clock that ends a stage ([`StageClock`]): at equilibrium, when
//! the largest node motion in one step falls below `tolerance` × the data's scale right after a
//! reattachment that moved at most `settle_fraction` of the points, and at least one; or after
//! its step budget. Also the options of a stage whose local update is one implicit step
//! ([`implicit_joint_options`]), which the solved fit's membrane runs.

use super::context::{FitProgress, Stage};
use super::options::{FitError, FitOptions};
use crate::model::centreline::{seed_deformation, seen_whole};
use crate::model::deform::GlobalDeformation;
use crate::model::dynamics::{
    DynamicsParams, FreeDofs, ModelState, NodalForces, Workspace, step_prepared,
};
use crate::model::fem::Tessellation;
use crate::model::forces::range::{RangeForces, Robust};
use crate::model::init::InitialPose;
use crate::model::superquadric::NUM_SHAPE;
use glam::DVec3;

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

/// The bookkeeping of one stage of the dynamics: how the forces and free DOFs are set, when
/// points are reattached and when the model is at rest.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) struct StageClock {
    /// The stage being run.
    pub stage: Stage,
    /// Steps since the last reattachment.
    pub since_reassign: u32,
}

impl StageClock {
    /// A clock at the start of `stage`.
    pub fn new(stage: Stage) -> Self {
        Self {
            stage,
            since_reassign: 0,
        }
    }

    /// Whether the local DOFs move in this stage.
    pub fn local_free(&self, opts: &FitOptions) -> bool {
        opts.dynamics.free.local && self.stage == Stage::Joint
    }

    /// Whether the range springs are point-to-plane in this stage (the global stage, when
    /// `point_to_plane` is set).
    pub fn plane(&self, opts: &FitOptions) -> bool {
        opts.point_to_plane && self.stage == Stage::Global
    }

    /// Coverage-spring density in this stage: the placing stage has them, and with
    /// `global_coverage` (a tapered or bent fit of data that surrounds the model, beyond the
    /// paper) the global stage too.
    pub fn coverage(&self, opts: &FitOptions, global_coverage: bool) -> f64 {
        if self.stage == Stage::Cover || (global_coverage && self.stage == Stage::Global) {
            opts.coverage
        } else {
            0.0
        }
    }

    /// After a step whose largest node motion was `motion`: reattaches through `reassign` (which
    /// returns how many springs changed) when `reassign_every` steps have passed or the model is
    /// at rest, and returns true when the stage is over: at rest right after a reattachment that
    /// changed at most `settle_fraction` of the `points`, and never fewer than one. (A point
    /// midway between two nodes can flip from one to the other at every rest for ever; below 500
    /// points the default 0.2 % rounds to none, and such a stage ran to its step cap.)
    pub fn after_step(
        &mut self,
        motion: f64,
        opts: &FitOptions,
        points: usize,
        reassign: impl FnOnce() -> usize,
    ) -> bool {
        self.since_reassign += 1;
        let at_rest = motion < opts.tolerance;
        if self.since_reassign < opts.reassign_every && !at_rest {
            return false;
        }
        let changed = reassign();
        self.since_reassign = 0;
        at_rest && changed as f64 <= (opts.settle_fraction * points as f64).max(1.0)
    }
}

/// The step budget of each similarity candidate ([`FitOptions::similarity_switch`]) when `spent`
/// of the fit's `max_steps` are used: an equal share of the rest, as the hypotheses share the
/// whole, so that the candidates can run side by side and the fit stays within its cap.
pub(super) fn similarity_share(max_steps: u32, spent: u32, candidates: usize) -> u32 {
    max_steps.saturating_sub(spent) / candidates.max(1) as u32
}

/// The stages a fit runs before choosing among initial hypotheses: placing (when `coverage` > 0)
/// and the global stage (unless the local DOFs move from the start).
pub(super) fn global_stages(opts: &FitOptions) -> Vec<Stage> {
    let mut stages = Vec::new();
    if opts.coverage > 0.0 {
        stages.push(Stage::Cover);
    }
    if opts.global_first || opts.global_only || !opts.dynamics.free.local {
        stages.push(Stage::Global);
    }
    stages
}

/// Whether a fit goes on to the joint stage after the global ones.
pub fn has_joint_stage(opts: &FitOptions) -> bool {
    !opts.global_only && opts.dynamics.free.local
}

/// The time step of [`implicit_joint_options`] over the options' own. The local block is taken
/// implicitly, so its damping γ_d A/Δt then weighs nothing next to the springs and the membrane,
/// and a step brings the local DOFs to the springs' equilibrium.
pub(crate) const IMPLICIT_JOINT_DT_SCALE: f64 = 1e4;

/// The options of the joint stage of a solved fit: the global DOFs held, the local block of
/// eq. (15) taken as one backward-Euler step ([`DynamicsParams::implicit_local`]) at a time step
/// `IMPLICIT_JOINT_DT_SCALE` times the options' own, so that each step solves
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
/// data `unit` surrounds one of the `starts` (unit frame; [`seen_whole`]).
pub(super) fn surrounds(
    tess: &Tessellation,
    opts: &FitOptions,
    unit: &[DVec3],
    starts: &[InitialPose],
) -> bool {
    let free = opts.dynamics.free;
    if !(free.taper || free.bend) || opts.coverage <= 0.0 {
        return false;
    }
    let mut x = Vec::new();
    starts.iter().any(|start| {
        let state = start_state(tess, opts, unit, start);
        state.node_positions(tess, &mut x);
        seen_whole(tess, &x, unit, state.shape.semi_axes().min_element())
    })
}

/// The state a relaxation of `unit` starts from at `start`: with tapering or bending free, moved
/// and deformed as the data's centreline shows ([`seed_deformation`]).
pub(super) fn start_state(
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
