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

/// Fewest points a fit accepts: the 11 independent global DOFs need at least 4 points in general
/// position, and the moments a few more to mean anything.
pub const MIN_POINTS: usize = 10;

/// Migration rate of the refining stage ([`Stage::Refine`]): each step moves a point of influence
/// the whole Gauss–Newton way to the foot of its datum (at most one element).
pub const REFINE_RATE: f64 = 1.0;

/// Step budget of the refining stage. A refinement that is not at rest by then, or that leaves
/// the points farther from the surface than the global stage did, is undone: on noisy clouds with
/// outliers, points near a cylinder's rim can let its length run away (each cap point's closest
/// surface point slides onto the side wall), a minimum of the one-sided distance that is no fit.
pub const REFINE_MAX_STEPS: u32 = 3000;

/// The refining stage is checked every this many steps ([`REFINE_GIVE_UP`], [`refine_stalled`]).
pub const REFINE_CHECK_EVERY: u32 = 250;

/// A refinement whose mean point-to-surface distance, checked every [`REFINE_CHECK_EVERY`] steps,
/// exceeds this multiple of the least distance it has had (the global stage's at first) is given
/// up and undone at once instead of at the end of its [`REFINE_MAX_STEPS`]. On scans of objects
/// that are no superquadric, the outlier weights let it drop whole limbs (the bunny's ears) and
/// the one-sided distance it minimises keeps falling while the model runs off; on a cylinder with
/// outliers (EMS's `noisy_pointCloud_example_2`), projected onto the mesh's chords, it first came
/// closer, then its length ran away.
pub const REFINE_GIVE_UP: f64 = 1.01;

/// A refinement is also given up, after any step, when the superquadric's longest semi-axis has
/// grown past this multiple of its length at the start of the stage ([`refine_overgrown`]). The
/// refinement polishes a fit that the global stage has placed and sized; a model that grows by
/// half again is the other way a cylinder's length runs away with its rim points, the mean
/// distance still falling as it goes (on EMS's `noisy_pointCloud_example_3`, two similarity
/// candidates grew 3× in 3000 steps).
pub const REFINE_MAX_GROWTH: f64 = 1.5;

/// The refining stage's check every [`REFINE_CHECK_EVERY`] steps, shared by [`fit`] and the
/// plugin's fit: given the mean `distance` of the points now and the `least` seen before, returns
/// the new least, or `None` to give the refinement up ([`REFINE_GIVE_UP`]).
pub fn refine_check(distance: f64, least: f64) -> Option<f64> {
    (distance <= REFINE_GIVE_UP * least).then(|| least.min(distance))
}

/// Whether a refinement has run off in length: its longest semi-axis `longest` is past
/// [`REFINE_MAX_GROWTH`] times `start`, its length at the start of the stage. One number, so
/// [`fit`] and the plugin's fit ask after every step of the stage that did not end it: a model
/// that runs off in length goes on running off, and was given up only at the next check of
/// [`REFINE_CHECK_EVERY`] (on EMS's `partial_pointCloud_example_1`
/// had one similarity candidate 2.2 times as long 65 steps into its refinement and 62 times at
/// the check 215 steps in).
pub fn refine_overgrown(longest: f64, start: f64) -> bool {
    longest > REFINE_MAX_GROWTH * start
}

/// A refinement whose inlier-weighted mean point-to-surface distance ([`refine_distances`], with
/// the robust weights of the moment), checked every [`REFINE_CHECK_EVERY`] steps, fell by less
/// than this fraction since the previous check is given up ([`refine_stalled`]): it is circling,
/// not converging. On EMS's `partial_pointCloud_example_3` one similarity candidate's refinement
/// went round a cycle of states (the largest node motion steady at 2.6e-3 of the RMS radius a
/// step) to its [`REFINE_MAX_STEPS`] and was undone; it is now undone 920 steps sooner. The
/// weights matter: with 20 % outliers the plain mean distance wanders by more than this while a
/// fit still converges (a rule on it lost one of the 20 ground-truth clouds).
pub const REFINE_MIN_PROGRESS: f64 = 1e-3;

/// A similarity candidate ([`FitOptions::similarity_switch`]) goes on to the refining stage only
/// when its global stage ended no farther from the points than this multiple of the chosen fit's
/// global stage (both by the chosen fit's inlier-weighted mean distance,
/// [`weighted_mean_distance`]): the two stages ran on the same forces, so the comparison is
/// like for like, and a candidate that placed much worse has not been seen to refine past the
/// chosen fit. On the eight shipped clouds and the 20 ground-truth clouds (`cargo run --release
/// --example ground_truth`) the candidates that won did so from ratios of 0.39 to 1.89, and
/// those that lost reached 4.5; at 2.5 the fits and the ground-truth table are what refining
/// every candidate gives, and EMS's `partial_pointCloud_example_1`, `_2` and `_3` skip
/// refinements that took 25 %, 31 % and 40 % of their steps.
pub const SIMILARITY_REFINE_MARGIN: f64 = 2.5;

/// Whether a similarity candidate whose global stage ended `candidate` from the points is
/// refined, when the chosen fit's global stage ended `chosen` from them
/// ([`SIMILARITY_REFINE_MARGIN`]). Shared by [`fit`] and the plugin's fit.
pub fn refine_candidate(candidate: f64, chosen: f64) -> bool {
    candidate <= SIMILARITY_REFINE_MARGIN * chosen
}

/// Whether a refinement has stalled: its inlier-weighted distance `weighted` at a check is more
/// than 1 − [`REFINE_MIN_PROGRESS`] times the one at the `previous` check of the stage (none at
/// the first). Shared by [`fit`] and the plugin's fit.
pub fn refine_stalled(weighted: f64, previous: Option<f64>) -> bool {
    previous.is_some_and(|p| weighted > (1.0 - REFINE_MIN_PROGRESS) * p)
}

/// The refining stage's two measures at a check, from one pass over the point distances: the
/// mean distance of `range`'s points to the surface through `node_x` ([`refine_check`]) and the
/// same weighted by each point's [`RangeForces::relative_weight`] ([`refine_stalled`]).
pub fn refine_distances(tess: &Tessellation, node_x: &[DVec3], range: &RangeForces) -> (f64, f64) {
    let d = point_distances(tess, node_x, range.points());
    let mean = d.iter().sum::<f64>() / d.len().max(1) as f64;
    let (mut total, mut weighted) = (0.0, 0.0);
    for (i, d) in d.iter().enumerate() {
        let w = range.relative_weight(i);
        total += w;
        weighted += w * d;
    }
    (mean, weighted / total.max(f64::MIN_POSITIVE))
}

/// How the first superquadric is placed.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub enum Initialization {
    /// From the data's centroid and central moments ([`initial_pose`]).
    #[default]
    Moments,
    /// An explicit pose and shape in the data's frame and units (the paper's experiments).
    Explicit(InitialPose),
}

/// Everything a fit can be told.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FitOptions {
    /// Tessellation: k rings × k longitudes + 2 poles.
    pub k: usize,
    /// Stiffness, damping, time step and free DOFs.
    pub dynamics: DynamicsParams,
    /// Range-spring strength per unit material area.
    pub beta: f64,
    /// How points of influence are chosen.
    pub influence: InfluenceMode,
    /// Density of the model-to-data coverage springs as a fraction of β (0: the paper's forces).
    pub coverage: f64,
    /// Reattach points every N steps (the paper: 200).
    pub reassign_every: u32,
    /// Step cap.
    pub max_steps: u32,
    /// Rest threshold: largest node motion in a step, in units of the data's RMS radius.
    pub tolerance: f64,
    /// A reattachment that moves at most this fraction of the points counts as changing nothing
    /// (noisy points can flip between two nearly equidistant nodes for ever).
    pub settle_fraction: f64,
    /// Hold the local DOFs until the global ones are at rest.
    pub global_first: bool,
    /// Freeze the local DOFs for good: a pure superquadric fit.
    pub global_only: bool,
    /// Point-to-plane springs in the global stage (beyond the paper; see `forces::range`): the
    /// superquadric's surface may pass between its nodes instead of being pinned to the nodes the
    /// points chose, which makes global-only fits of clean data several times more accurate.
    /// Off by default (the paper's springs); the placing and joint stages always use those.
    pub point_to_plane: bool,
    /// Prior fraction of outliers for the outlier-robust spring weights (`forces::range::Robust`);
    /// 0 gives the paper's equal weights.
    pub outlier_ratio: f64,
    /// After the global stage, refine the superquadric with points of influence that migrate to
    /// their closest surface points ([`Stage::Refine`]): the global parameters then fit the
    /// surface through the points rather than the nearest nodes, which on clean data makes a
    /// pure superquadric fit one to two orders of magnitude closer (beyond the paper). A pure
    /// superquadric fit ([`FitOptions::global_only`]) then ends with the squareness extension
    /// ([`extend_squareness`]), which may set an exponent the dynamics left at [`MIN_EPSILON`]
    /// below it.
    pub refine: bool,
    /// After choosing the hypothesis, also try its cross-section dual (turned 45° about the model
    /// axis with ε2 → 2 − ε2, see [`cross_section_dual`]) when ε2 is far from 1, and keep whichever
    /// fits closer: a square section and a diamond one are each other's local minimum (EMS's
    /// "similarity switching"; beyond the paper).
    pub switch_cross_section: bool,
    /// After the refining stage, try the fit's similarity candidates ([`similarity_candidates`]:
    /// the other two axes as the model's z with the exponents swapped, and the cross-section dual
    /// about each axis whose two perpendicular semi-axes are alike), each through the global
    /// stage and, unless it placed much worse than the fit ([`SIMILARITY_REFINE_MARGIN`]), the
    /// refining stage, and keep the one closest to the points — weighted by the chosen fit's
    /// inlier probabilities — if it is closer than the fit (EMS's similarity switching, Liu et
    /// al. 2022; beyond the paper).
    pub similarity_switch: bool,
    /// Initial pose and shape.
    pub init: Initialization,
    /// How the global DOFs come to rest: the paper's dynamics, or for a pure superquadric the
    /// Levenberg–Marquardt solve of [`super::lm`] ([`Solver`]).
    pub solver: Solver,
}

impl Default for FitOptions {
    /// k = 31 (963 nodes), w0 = 1e-3, w1 = 0.1, γ_g = Δt = 0.05 (each global step a whole
    /// Gauss–Newton step on the springs, bounded by the step's trust region: it reaches rest in
    /// 3–4 steps per reattachment where the interactive default, half a step, takes 15–20), β = 4,
    /// nearest-node springs reattached every 200 steps, global first, moments initialisation.
    fn default() -> Self {
        Self {
            k: 31,
            dynamics: DynamicsParams {
                gamma_global: 0.05,
                ..DynamicsParams::default()
            },
            beta: 4.0,
            influence: InfluenceMode::NearestNode,
            coverage: DEFAULT_COVERAGE,
            reassign_every: 200,
            max_steps: 20_000,
            tolerance: 1e-5,
            settle_fraction: 0.002,
            global_first: true,
            global_only: false,
            point_to_plane: false,
            outlier_ratio: 0.0,
            refine: false,
            switch_cross_section: false,
            similarity_switch: false,
            init: Initialization::Moments,
            solver: Solver::Dynamics,
        }
    }
}

impl FitOptions {
    /// These options with everything that makes a fit robust to outliers and accurate on partial
    /// clouds (all beyond the paper): outlier-robust weights with a prior outlier fraction of 0.2
    /// (EMS's), point-to-plane springs in the global stage, the refining stage, the cross-section
    /// switch and the similarity switch. `dsq fit`'s `--robust`.
    pub fn robust(self) -> Self {
        Self {
            outlier_ratio: ROBUST_OUTLIER_RATIO,
            point_to_plane: true,
            refine: true,
            switch_cross_section: true,
            similarity_switch: true,
            ..self
        }
    }
}

impl FitOptions {
    /// These options as the command-line fitter sets them for a user's cloud (all beyond the
    /// paper; docs/cli.md): outlier-robust weights with the prior outlier
    /// fraction [`ROBUST_OUTLIER_RATIO`] unless one is set, point-to-plane springs in the global
    /// stage, and — for a pure superquadric ([`FitOptions::global_only`]) — the refining stage and
    /// both switches, i.e. [`FitOptions::robust`]. With local DOFs the refining stage and the
    /// switches are left as they are: they change the fitted surface by nothing measurable there
    /// (20 generated clouds with 20 % outliers: the same median inlier residual, 35 % more steps
    /// for the refining stage and the cross-section switch). Pair it with [`FitOptions::with_stiffness_from_noise`] for fits with local DOFs.
    pub fn for_data(self) -> Self {
        let base = if self.global_only {
            self.robust()
        } else {
            Self {
                point_to_plane: true,
                ..self
            }
        };
        Self {
            outlier_ratio: if self.outlier_ratio > 0.0 {
                self.outlier_ratio
            } else {
                ROBUST_OUTLIER_RATIO
            },
            ..base
        }
    }

    /// These options with the membrane stiffness (w0, w1) chosen from the noise `points` show
    /// ([`super::noise::estimate_noise`], [`super::noise::stiffness_for_noise`]), and the estimate;
    /// unchanged options and `None` when the noise cannot be estimated (too few points).
    pub fn with_stiffness_from_noise(
        self,
        points: &[DVec3],
    ) -> (Self, Option<super::noise::NoiseEstimate>) {
        let Some(noise) = super::noise::estimate_noise(points) else {
            return (self, None);
        };
        let (w0, w1) = super::noise::stiffness_for_noise(noise.relative);
        let dynamics = DynamicsParams {
            w0,
            w1,
            ..self.dynamics
        };
        (Self { dynamics, ..self }, Some(noise))
    }
}

/// The prior outlier fraction of [`FitOptions::robust`].
pub const ROBUST_OUTLIER_RATIO: f64 = 0.2;

/// Why a fit could not run.
#[derive(Clone, Debug, PartialEq)]
pub enum FitError {
    /// Fewer than [`MIN_POINTS`] points.
    TooFewPoints {
        /// How many there were.
        found: usize,
    },
    /// A coordinate is NaN or infinite.
    NonFinitePoint {
        /// Index of the offending point.
        index: usize,
    },
    /// All points coincide (no extent to fit).
    Degenerate,
    /// An option is out of range; names it.
    BadOption(String),
    /// The simulation refused a step.
    Step(StepError),
}

impl std::fmt::Display for FitError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            FitError::TooFewPoints { found } => {
                write!(f, "{found} points; a fit needs at least {MIN_POINTS}")
            }
            FitError::NonFinitePoint { index } => {
                write!(f, "point {index} has a NaN or infinite coordinate")
            }
            FitError::Degenerate => write!(f, "all points coincide; there is no shape to fit"),
            FitError::BadOption(what) => write!(f, "{what}"),
            FitError::Step(e) => write!(f, "simulation failed: {e}"),
        }
    }
}

impl std::error::Error for FitError {}

/// Which degrees of freedom the loop is moving, and with which forces.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Stage {
    /// Global DOFs only, with the model-to-data coverage springs on (placing the model).
    Cover,
    /// Global DOFs only (local held), the paper's forces.
    Global,
    /// Global DOFs only, after the hypothesis is chosen, with each point's point of influence
    /// migrating to its closest point on the surface (the paper's Fig. 3) and point-to-plane
    /// springs: the superquadric fitted to the points themselves instead of to the nodes they
    /// chose (beyond the paper's experiments; [`FitOptions::refine`]). [`fit`] and
    /// `plugin::headless::fit_headless` undo it when it does not pay; the plugin's `FitDriver` alone
    /// runs it to rest or to its budget.
    Refine,
    /// Global and local DOFs together.
    Joint,
}

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

/// Checks the points a fit is given.
pub fn validate_points(points: &[DVec3]) -> Result<(), FitError> {
    if let Some(index) = points.iter().position(|p| !p.is_finite()) {
        return Err(FitError::NonFinitePoint { index });
    }
    if points.len() < MIN_POINTS {
        return Err(FitError::TooFewPoints {
            found: points.len(),
        });
    }
    // Coincident to rounding: the spread is below 10⁻¹² of the distance from the origin (a
    // cloud of any scale about the origin is fine).
    let n = Normalization::of(points);
    if !(n.scale > 1e-12 * n.centroid.abs().max_element()) || !(n.scale > 0.0) {
        return Err(FitError::Degenerate);
    }
    Ok(())
}

/// Checks a fit's options.
pub fn validate_options(o: &FitOptions) -> Result<(), FitError> {
    let d = &o.dynamics;
    let bad = |name: &str, v: f64| FitError::BadOption(format!("{name} = {v} is out of range"));
    for (name, v, ok) in [
        ("w0", d.w0, d.w0 >= 0.0),
        ("w1", d.w1, d.w1 >= 0.0),
        ("dt", d.dt, d.dt > 0.0),
        ("gamma_global", d.gamma_global, d.gamma_global > 0.0),
        ("gamma_local", d.gamma_local, d.gamma_local > 0.0),
        ("beta", o.beta, o.beta > 0.0),
        ("tolerance", o.tolerance, o.tolerance > 0.0),
        ("coverage", o.coverage, o.coverage >= 0.0),
        (
            "outlier_ratio",
            o.outlier_ratio,
            (0.0..1.0).contains(&o.outlier_ratio),
        ),
        (
            "settle_fraction",
            o.settle_fraction,
            (0.0..1.0).contains(&o.settle_fraction),
        ),
    ] {
        if !(ok && v.is_finite()) {
            return Err(bad(name, v));
        }
    }
    if o.k < super::fem::MIN_K {
        return Err(FitError::BadOption(format!(
            "k = {} is below the minimum {}",
            o.k,
            super::fem::MIN_K
        )));
    }
    if o.reassign_every == 0 {
        return Err(FitError::BadOption(
            "reassign_every = 0; it must be at least 1".into(),
        ));
    }
    Ok(())
}

/// The bookkeeping of one stage of a fit: how the forces and free DOFs are set, when points are
/// reattached and when the model is at rest. [`fit`] and the plugin's fit driver share it, so a fit
/// takes the same steps either way.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct StageClock {
    /// The stage being run.
    pub stage: Stage,
    /// Steps since the last reattachment.
    pub since_reassign: u32,
    /// Signatures ([`RangeForces::signature`]) of the springs that the last
    /// [`REST_CYCLE_MEMORY`] unsettled reattachments at rest gave, newest at
    /// `rests % REST_CYCLE_MEMORY`.
    pub rest_signatures: [u64; REST_CYCLE_MEMORY],
    /// How many unsettled reattachments at rest this stage has had.
    pub rests: u32,
}

/// How many of its last rests a stage remembers to tell a cycle of rests
/// ([`StageClock::after_step`]).
pub const REST_CYCLE_MEMORY: usize = 4;

impl StageClock {
    /// A clock at the start of `stage`.
    pub fn new(stage: Stage) -> Self {
        Self {
            stage,
            since_reassign: 0,
            rest_signatures: [0; REST_CYCLE_MEMORY],
            rests: 0,
        }
    }

    /// Whether the local DOFs move in this stage.
    pub fn local_free(&self, opts: &FitOptions) -> bool {
        opts.dynamics.free.local && self.stage == Stage::Joint
    }

    /// Whether the range springs are point-to-plane in this stage (the global stages, when
    /// `point_to_plane` is set).
    pub fn plane(&self, opts: &FitOptions) -> bool {
        (opts.point_to_plane && self.stage == Stage::Global) || self.stage == Stage::Refine
    }

    /// How points of influence are chosen in this stage: migrating in the refining stage, the
    /// options' mode otherwise.
    pub fn influence(&self, opts: &FitOptions) -> InfluenceMode {
        if self.stage == Stage::Refine {
            InfluenceMode::Migrating { rate: REFINE_RATE }
        } else {
            opts.influence
        }
    }

    /// Coverage-spring density in this stage (only the placing stage has them).
    pub fn coverage(&self, opts: &FitOptions) -> f64 {
        if self.stage == Stage::Cover {
            opts.coverage
        } else {
            0.0
        }
    }

    /// After a step whose largest node motion was `motion`: reattaches through `reassign` (which
    /// returns how many springs changed and the springs' [`RangeForces::signature`]) when
    /// `reassign_every` steps have passed or the model is at rest, and returns true when the stage
    /// is over: at rest right after a reattachment that changed at most `settle_fraction` of the
    /// `points`, or at rest right after one that gave springs this stage has already had at one of
    /// its last [`REST_CYCLE_MEMORY`] rests. That is a cycle of rests: with nearest-node springs a
    /// point midway between two nodes can flip from one to the other at each rest for ever (on
    /// EMS's `partial_pointCloud_example_3` with `--outliers 0.05`, one point of 216 — more than
    /// the 0.2 % it may — every 3 steps, until the fit's 20 000-step cap). A reattachment that
    /// changed every spring (the robust weights still sharpening) starts no cycle.
    pub fn after_step(
        &mut self,
        motion: f64,
        opts: &FitOptions,
        points: usize,
        reassign: impl FnOnce() -> (usize, u64),
    ) -> bool {
        self.since_reassign += 1;
        let at_rest = motion < opts.tolerance;
        if self.since_reassign < opts.reassign_every && !at_rest {
            return false;
        }
        let (changed, signature) = reassign();
        self.since_reassign = 0;
        if !at_rest {
            return false;
        }
        if changed as f64 <= opts.settle_fraction * points as f64 {
            return true;
        }
        if changed >= points {
            return false;
        }
        let seen = self.rest_signatures[..(self.rests as usize).min(REST_CYCLE_MEMORY)]
            .contains(&signature);
        self.rest_signatures[self.rests as usize % REST_CYCLE_MEMORY] = signature;
        self.rests += 1;
        seen
    }
}

/// The step budget of each similarity candidate ([`FitOptions::similarity_switch`]) when `spent`
/// of the fit's `max_steps` are used: an equal share of the rest, as the hypotheses share the
/// whole, so that the candidates can run side by side and the fit stays within its cap.
pub fn similarity_share(max_steps: u32, spent: u32, candidates: usize) -> u32 {
    max_steps.saturating_sub(spent) / candidates.max(1) as u32
}

/// The mean distance of `points` to the surface through `node_x`, point i weighted by
/// `weights[i]` (the similarity switch's score, [`FitOptions::similarity_switch`]).
pub fn weighted_mean_distance(
    tess: &Tessellation,
    node_x: &[DVec3],
    points: &[DVec3],
    weights: &[f64],
) -> f64 {
    weighted_mean(&point_distances(tess, node_x, points), weights)
}

/// The mean of the distances `d`, `d[i]` weighted by `weights[i]`.
fn weighted_mean(d: &[f64], weights: &[f64]) -> f64 {
    let total: f64 = weights.iter().sum();
    d.iter().zip(weights).map(|(d, w)| d * w).sum::<f64>() / total.max(f64::MIN_POSITIVE)
}

/// The exponents [`extend_squareness`] tries below [`MIN_EPSILON`], largest first.
pub const EXTENDED_EPSILONS: [f64; 4] = [0.05, 0.03, 0.02, LEAST_EPSILON];

/// The squareness extension of a pure superquadric fit (beyond the paper). The dynamics hold ε1
/// and ε2 at [`MIN_EPSILON`] or above, because below it eq. (4) crowds a flat face into a sliver
/// of (u, v) at the pole that the points of influence cannot migrate onto; a fit that ends with an
/// exponent at that bound is asking for a squarer shape. Each such exponent (ε1, then ε2 with ε1's
/// outcome) is tried at each of [`EXTENDED_EPSILONS`], every other parameter held, and set to the
/// trial whose surface lies closest to `points` weighted by `weights` (the similarity switch's
/// score, [`weighted_mean_distance`], measured over every core) if it is closer than the fit's.
/// The shape when an exponent moved, `None` otherwise.
///
/// EMS's noisy cylinder (`noisy_pointCloud_example_2`), whose robust fit came to rest at ε1 =
/// 0.1, is the case: the extension takes ε1 to 0.01 and the mean distance of the points to the
/// surface from 0.01485 to 0.01468 of the diagonal, EMS's own fit (ε1 = 0.01) lying 0.01473
/// from them (docs/results.md, "Side by side with EMS").
pub fn extend_squareness(
    tess: &Tessellation,
    state: &ModelState,
    points: &[DVec3],
    weights: &[f64],
) -> Option<SuperquadricParams> {
    let mut x = Vec::new();
    let mut distance = |shape: &SuperquadricParams| {
        node_positions(
            tess,
            state.translation,
            state.rotation,
            shape,
            &state.deformation,
            &state.displacement,
            &mut x,
        );
        // The extension runs alone at the end of a fit: its distances use every core.
        weighted_mean(&point_distances_parallel(tess, &x, points), weights)
    };
    let mut best = state.shape;
    let mut least = None;
    for k in 0..2 {
        let with = |q: SuperquadricParams, e: f64| {
            if k == 0 {
                SuperquadricParams { e1: e, ..q }
            } else {
                SuperquadricParams { e2: e, ..q }
            }
        };
        if [best.e1, best.e2][k] != MIN_EPSILON {
            continue;
        }
        let mut here = *least.get_or_insert_with(|| distance(&best));
        let mut moved = None;
        for e in EXTENDED_EPSILONS {
            let trial = with(best, e);
            let d = distance(&trial);
            if d < here {
                (here, moved) = (d, Some(trial));
            }
        }
        if let Some(shape) = moved {
            (best, least) = (shape, Some(here));
        }
    }
    (best != state.shape).then_some(best)
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

/// The stages a fit runs before choosing among initial hypotheses: placing (when `coverage` > 0)
/// and the global stage (unless the local DOFs move from the start).
pub fn global_stages(opts: &FitOptions) -> Vec<Stage> {
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

/// How far ε2 must be from 1 (an elliptic cross-section, its own dual) before
/// [`cross_section_dual`] offers a dual.
pub const DUAL_EPSILON_GAP: f64 = 0.5;

/// The cross-section dual of a fitted pose: the model turned 45° about its z axis, ε2 → 2 − ε2,
/// and both section semi-axes set to their mean times √2 (a square section's dual diamond reaches
/// its corners) or ÷ √2 (a diamond's dual square is inscribed). `None` when ε2 is within
/// [`DUAL_EPSILON_GAP`] of 1, where the section is nearly elliptic and turning it changes little.
pub fn cross_section_dual(pose: &InitialPose) -> Option<InitialPose> {
    let q = pose.shape;
    if (q.e2 - 1.0).abs() <= DUAL_EPSILON_GAP {
        return None;
    }
    Some(dual_about_z(
        pose,
        if q.e2 < 1.0 { SQRT_2 } else { 1.0 / SQRT_2 },
    ))
}

/// The pose with its axes permuted cyclically `turns` times ((x, y, z) → (y, z, x) for one), so
/// that another axis is the model's z, with the same semi-axes along the same world directions.
/// With `swap`, ε1 and ε2 trade places (EMS's axis-mismatch candidate: exact for ε1 = ε2 = 1,
/// and the nearest superquadric of the new frame when both exponents are alike).
fn turned_axes(pose: &InitialPose, turns: usize, swap: bool) -> InitialPose {
    let m = glam::DMat3::from_quat(pose.rotation);
    let semi = pose.shape.semi_axes().to_array();
    let (cx, cy, cz) = (turns % 3, (turns + 1) % 3, (turns + 2) % 3);
    let frame = glam::DMat3::from_cols(m.col(cx), m.col(cy), m.col(cz));
    let a = semi[cx].max(semi[cy]).max(semi[cz]).max(f64::MIN_POSITIVE);
    let q = pose.shape;
    let (e1, e2) = if swap { (q.e2, q.e1) } else { (q.e1, q.e2) };
    InitialPose {
        translation: pose.translation,
        rotation: glam::DQuat::from_mat3(&frame).normalize(),
        shape: SuperquadricParams {
            a,
            a1: semi[cx] / a,
            a2: semi[cy] / a,
            a3: semi[cz] / a,
            e1,
            e2,
        },
    }
}

/// Bounds on the ratio of two semi-axes for [`similarity_candidates`] to offer the cross-section
/// dual about the third axis (EMS's: a square-ish section only).
pub const DUAL_AXES_RATIO: (f64, f64) = (0.6, 1.4);

/// The similarity candidates of a fitted pose (EMS's similarity switching, Liu et al. 2022): the
/// two other axes as the model's z axis with ε1 and ε2 swapped, then for each axis whose two
/// perpendicular semi-axes are within [`DUAL_AXES_RATIO`] of each other, that axis as z and the
/// cross-section dual about it (turned 45°, ε2 → 2 − ε2, the section rescaled as in
/// [`cross_section_dual`]). Each is a different local minimum near the same surface.
pub fn similarity_candidates(pose: &InitialPose) -> Vec<InitialPose> {
    let mut candidates = vec![turned_axes(pose, 1, true), turned_axes(pose, 2, true)];
    for turns in 0..3 {
        let along = turned_axes(pose, turns, turns != 0);
        let s = along.shape.semi_axes();
        let ratio = s.x / s.y;
        if ratio > DUAL_AXES_RATIO.0 && ratio < DUAL_AXES_RATIO.1 {
            // The section's scale goes linearly in ε2 from √2 (a square's dual diamond reaches its
            // corners) through 1 (a circle is its own dual) to 1/√2 (a diamond's dual square is
            // inscribed), as EMS scales its candidates.
            let e2 = along.shape.e2;
            let scale = if e2 <= 1.0 {
                (1.0 - SQRT_2) * e2 + SQRT_2
            } else {
                (0.5 * SQRT_2 - 1.0) * e2 + 2.0 - 0.5 * SQRT_2
            };
            candidates.push(dual_about_z(&along, scale));
        }
    }
    candidates
}

/// The pose turned 45° about its z axis with ε2 → 2 − ε2 and both section semi-axes set to their
/// mean times `scale`.
fn dual_about_z(pose: &InitialPose, scale: f64) -> InitialPose {
    let q = pose.shape;
    let section = 0.5 * (q.a1 + q.a2) * scale;
    let rotation =
        (pose.rotation * glam::DQuat::from_rotation_z(std::f64::consts::FRAC_PI_4)).normalize();
    let shape = SuperquadricParams {
        a1: section,
        a2: section,
        e2: 2.0 - q.e2,
        ..q
    };
    InitialPose {
        translation: pose.translation,
        rotation,
        shape: shape.normalized(),
    }
}

/// The initial states a fit tries: the three axis hypotheses of the moments frame, or the one
/// explicit pose.
pub fn initial_hypotheses(points: &[DVec3], opts: &FitOptions) -> Vec<InitialPose> {
    match opts.init {
        Initialization::Moments => {
            // The moments are taken in the unit frame: squared coordinates of a cloud at 1e300
            // would overflow.
            let norm = Normalization::of(points);
            if !(norm.scale > 0.0) {
                return axis_hypotheses(&initial_pose(points)).to_vec();
            }
            let unit: Vec<DVec3> = points.iter().map(|p| norm.unit_point(*p)).collect();
            axis_hypotheses(&initial_pose(&unit))
                .iter()
                .map(|h| norm.pose_from_unit(h))
                .collect()
        }
        Initialization::Explicit(pose) => vec![pose],
    }
}

/// The score by which hypotheses are compared: the mean distance of the points to the surface
/// through `node_x`.
pub fn mean_distance(tess: &Tessellation, node_x: &[DVec3], points: &[DVec3]) -> f64 {
    let d = point_distances(tess, node_x, points);
    d.iter().sum::<f64>() / d.len().max(1) as f64
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
}

impl<'a> Relaxation<'a> {
    fn new(
        tess: &'a Tessellation,
        opts: &'a FitOptions,
        unit: &[DVec3],
        start: &InitialPose,
    ) -> Self {
        let state = ModelState::new(
            tess,
            start.translation,
            start.rotation,
            start.shape.normalized(),
        );
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
        self.range.coverage = clock.coverage(self.opts);
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
    /// rest no farther than `score`.
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
        let after = mean_distance(self.tess, &self.x, self.range.points());
        let kept = at_rest && after <= score;
        let steps = self.steps - before.steps;
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

/// The moments frame with each principal axis in turn as the model's z axis: the superquadric's
/// z is special (ε1 shapes its profile), and which data axis it belongs on is not always the one
/// of largest spread (a squat mug's axis is its smallest).
fn axis_hypotheses(pose: &InitialPose) -> [InitialPose; 3] {
    // Cyclic permutation keeps the frame right-handed: (x, y, z) → (y, z, x) → (z, x, y).
    std::array::from_fn(|i| turned_axes(pose, i, false))
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

/// Fits a deformable superquadric to `points`, calling `progress` every 100 steps.
///
/// Stages: coverage (placing, global DOFs), global (the paper's springs, global DOFs), joint
/// (global and local DOFs), each run to rest; see the module docs. With moments initialisation
/// the first two stages run from each of the three axis hypotheses of the moments frame and the
/// one whose surface lies closest to the data goes on. Between choosing and the joint stage, the
/// options may add the cross-section switch ([`FitOptions::switch_cross_section`]), the
/// refining stage ([`FitOptions::refine`]) and, after it, the similarity switch
/// ([`FitOptions::similarity_switch`]).
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
    // Each hypothesis gets an equal share of the step cap (as in the plugin's fit driver).
    let share = opts.max_steps / candidates.len().max(1) as u32;
    let run = |initial: &InitialPose, progress: &mut dyn FnMut(&FitProgress)| {
        let mut relax = Relaxation::new(&tess, opts, &unit, &norm.pose_to_unit(initial));
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
        let budget = opts.max_steps.saturating_sub(other_steps);
        converged = relax.run(Stage::Joint, budget, &mut progress)?;
    } else if opts.refine {
        let weights = relax.range.relative_weights();
        if let Some(shape) = extend_squareness(&tess, &relax.state, &unit, &weights) {
            relax.state.shape = shape;
        }
    }
    let state = norm.state_to_data(&relax.state);
    let residuals = fit_residuals(&tess, &state, points);
    Ok(FitReport {
        state,
        steps: relax.steps + other_steps,
        global_steps: relax.global_steps,
        reassignments: relax.reassignments,
        converged,
        substepped_steps: relax.substepped,
        residuals,
        initial,
        tess,
        refinement,
    })
}

/// True when `opts` ask for the Levenberg–Marquardt solve and the fit is one it can do: a pure
/// superquadric without tapering or bending.
pub fn uses_lm(opts: &FitOptions) -> bool {
    let free = &opts.dynamics.free;
    opts.solver == Solver::LevenbergMarquardt && opts.global_only && !free.taper && !free.bend
}

/// Most EM rounds of a Levenberg–Marquardt fit, and Levenberg–Marquardt steps in a round.
pub const LM_ROUNDS: (u32, u32) = (50, 5);

/// A round of a Levenberg–Marquardt fit that lowers its cost by less than this fraction ends it.
pub const LM_TOLERANCE: f64 = 1e-4;

/// Similarity switches a Levenberg–Marquardt fit makes at most (EMS's `MaxiSwitch`).
pub const LM_SWITCHES: u32 = 2;

/// [`fit`] by [`super::lm::solve`] from the `starts` (unit frame of `norm`, data units given),
/// with the similarity candidates when the options ask for them and the squareness extension
/// when they ask for the refining stage.
fn fit_lm(
    points: &[DVec3],
    opts: &FitOptions,
    norm: &Normalization,
    unit: &[DVec3],
    starts: &[InitialPose],
    tess: Tessellation,
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
    let lm = LmOptions {
        mixture: Mixture {
            outlier_ratio: opts.outlier_ratio,
            outlier_density: 1.0 / volume,
            sigma2_floor: (super::forces::range::SIGMA_FLOOR * diagonal).powi(2),
        },
        max_rounds: LM_ROUNDS.0,
        steps_per_round: LM_ROUNDS.1,
        tolerance: LM_TOLERANCE,
        metric: Metric::Radial,
    };
    let switches = if opts.similarity_switch {
        LM_SWITCHES
    } else {
        0
    };
    let solution = super::lm::solve(unit, &starts, sigma2, &lm, similarity_candidates, switches)
        .ok_or_else(|| FitError::BadOption("no initial state to start from".into()))?;
    let fit = &solution.fit;
    let pose = fit.pose;
    let mut state = ModelState::new(&tess, pose.translation, pose.rotation, pose.shape);
    if opts.refine {
        let weights = if fit.weights.is_empty() {
            vec![1.0; unit.len()]
        } else {
            fit.weights.clone()
        };
        if let Some(shape) = extend_squareness(&tess, &state, unit, &weights) {
            state.shape = shape;
        }
    }
    progress(&FitProgress {
        step: solution.iterations,
        stage: Stage::Global,
        max_motion: 0.0,
        energy: fit.cost,
        reassignments: 0,
    });
    let state = norm.state_to_data(&state);
    let residuals = fit_residuals(&tess, &state, points);
    Ok(FitReport {
        state,
        steps: solution.iterations,
        global_steps: fit.iterations,
        reassignments: 0,
        converged: fit.converged,
        substepped_steps: 0,
        residuals,
        initial: norm.pose_to_data(&tess, &solution.start),
        tess,
        refinement: None,
    })
}

/// Closest point to `p` on triangle (a, b, c) (Ericson, Real-Time Collision Detection §5.1.5).
pub fn closest_point_on_triangle(p: DVec3, a: DVec3, b: DVec3, c: DVec3) -> DVec3 {
    let (ab, ac, ap) = (b - a, c - a, p - a);
    let (d1, d2) = (ab.dot(ap), ac.dot(ap));
    if d1 <= 0.0 && d2 <= 0.0 {
        return a;
    }
    let bp = p - b;
    let (d3, d4) = (ab.dot(bp), ac.dot(bp));
    if d3 >= 0.0 && d4 <= d3 {
        return b;
    }
    let vc = d1 * d4 - d3 * d2;
    if vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0 {
        return a + ab * (d1 / (d1 - d3));
    }
    let cp = p - c;
    let (d5, d6) = (ab.dot(cp), ac.dot(cp));
    if d6 >= 0.0 && d5 <= d6 {
        return c;
    }
    let vb = d5 * d2 - d1 * d6;
    if vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0 {
        return a + ac * (d2 / (d2 - d6));
    }
    let va = d3 * d6 - d5 * d4;
    if va <= 0.0 && (d4 - d3) >= 0.0 && (d5 - d6) >= 0.0 {
        return b + (c - b) * ((d4 - d3) / ((d4 - d3) + (d5 - d6)));
    }
    let denom = 1.0 / (va + vb + vc);
    a + ab * (vb * denom) + ac * (vc * denom)
}

/// Number of nearest nodes whose incident triangles are searched for each point's closest
/// surface point in [`residuals`].
pub const RESIDUAL_CANDIDATE_NODES: usize = 12;

/// Distance from every point to the triangulated surface through `node_x` (the render
/// triangulation of `tess`). The closest point is searched on the triangles around the
/// [`RESIDUAL_CANDIDATE_NODES`] nearest nodes (k-d tree), which contain it on any surface whose
/// triangles are not much longer than the node spacing.
pub fn point_distances(tess: &Tessellation, node_x: &[DVec3], points: &[DVec3]) -> Vec<f64> {
    distances(tess, node_x, points, false)
}

/// Points a run of [`point_distances_parallel`] takes: each run measures on a list of triangles
/// seen of its own, as long as the mesh's triangle list.
pub const PARALLEL_DISTANCES: usize = 256;

/// [`point_distances`] over rayon's threads, in runs of [`PARALLEL_DISTANCES`] points: each point
/// is measured as it is there, so the distances are the same to the bit. For the parts of a fit
/// that run alone, the squareness extension ([`extend_squareness`]) and the residuals
/// ([`fit_residuals`]); the hypotheses and candidates, which already run side by side, use
/// [`point_distances`].
pub fn point_distances_parallel(
    tess: &Tessellation,
    node_x: &[DVec3],
    points: &[DVec3],
) -> Vec<f64> {
    distances(tess, node_x, points, true)
}

/// [`point_distances`] on one thread or, with `parallel`, over rayon's.
fn distances(tess: &Tessellation, node_x: &[DVec3], points: &[DVec3], parallel: bool) -> Vec<f64> {
    use rayon::prelude::*;
    let tris = tess.triangles();
    let tree = kd_tree(node_x);
    let k = NonZero::new(RESIDUAL_CANDIDATE_NODES.min(node_x.len()).max(1))
        .unwrap_or(NonZero::<usize>::MIN);
    let all_nodes: Vec<u32> = if tree.is_none() {
        (0..node_x.len() as u32).collect()
    } else {
        Vec::new()
    };
    // A triangle round several candidate nodes is measured once per point: `seen[t]` holds the
    // last point (plus one) that measured it.
    let distance = |seen: &mut Vec<u32>, (i, p): (usize, &DVec3)| {
        let stamp = i as u32 + 1;
        let mut best = f64::INFINITY;
        let mut measure = |n: u32| {
            let n = n as usize;
            for &t in tess.node_tris.of_node(n) {
                if seen[t as usize] == stamp {
                    continue;
                }
                seen[t as usize] = stamp;
                let [a, b, c] = tris[t as usize];
                let q = closest_point_on_triangle(
                    *p,
                    node_x[a as usize],
                    node_x[b as usize],
                    node_x[c as usize],
                );
                best = best.min(q.distance_squared(*p));
            }
        };
        match &tree {
            Some(tree) => tree
                .query(&p.to_array())
                .nearest_n::<SquaredEuclidean<f64>>(k)
                .execute()
                .iter()
                .for_each(|r| measure(r.item)),
            None => all_nodes.iter().for_each(|&n| measure(n)),
        }
        best.sqrt()
    };
    let unseen = || vec![0u32; tris.len()];
    if parallel {
        points
            .par_iter()
            .enumerate()
            .with_min_len(PARALLEL_DISTANCES)
            .map_init(unseen, distance)
            .collect()
    } else {
        let mut seen = unseen();
        points
            .iter()
            .enumerate()
            .map(|ip| distance(&mut seen, ip))
            .collect()
    }
}

/// The tessellation (k = 151, 22 803 nodes) on which [`fit_residuals`] measures a pure
/// superquadric: its chords lie within 2·10⁻⁵ of the radius of curvature of the surface, below
/// the residuals of a noise-free fit.
pub const SURFACE_RESIDUAL_K: usize = 151;

/// The residuals a fit reports for `state` (fitted on `tess`): a model with local displacements is
/// measured on its own mesh, which is what it renders; a pure superquadric (all displacements
/// zero) on its continuous surface, which the refining stage fits
/// ([`ModelSurface`](super::dynamics::ModelSurface)) and which the 963-node mesh's chords would
/// misstate by more than a clean fit's distances: exactly ([`surface_distances`]) when it is
/// neither tapered nor bent, else on a [`SURFACE_RESIDUAL_K`] tessellation.
pub fn fit_residuals(tess: &Tessellation, state: &ModelState, points: &[DVec3]) -> Residuals {
    // Measured in the points' unit frame, so that no squared distance overflows at any scale;
    // the figures are relative to the diagonal, so only it is scaled back.
    let norm = Normalization::of(points);
    if !(norm.scale > 0.0) {
        return Residuals::of(Vec::new(), 0.0);
    }
    let unit: Vec<DVec3> = points.iter().map(|p| norm.unit_point(*p)).collect();
    let mut r = unit_residuals(tess, &norm.state_to_unit(state), &unit);
    r.diagonal *= norm.scale;
    r
}

/// [`fit_residuals`] in the unit frame.
fn unit_residuals(tess: &Tessellation, state: &ModelState, points: &[DVec3]) -> Residuals {
    let pure = state.displacement.iter().all(|d| *d == DVec3::ZERO);
    if pure && state.deformation.is_identity() {
        let pose = InitialPose::of(state);
        let d = surface_distances(&pose, points);
        return Residuals::of(d, bounding_diagonal(points));
    }
    let fine;
    let tess = if pure && tess.k < SURFACE_RESIDUAL_K {
        fine = Tessellation::new(SURFACE_RESIDUAL_K);
        &fine
    } else {
        tess
    };
    // Displacements missing at the end count as zero: the pure superquadric on the fine mesh.
    let displacement = if pure {
        &[][..]
    } else {
        &state.displacement[..]
    };
    let mut x = Vec::new();
    node_positions(
        tess,
        state.translation,
        state.rotation,
        &state.shape,
        &state.deformation,
        displacement,
        &mut x,
    );
    residuals(tess, &x, points)
}

/// |distance| of each of `points` to the closest point of the pure superquadric `pose`
/// ([`super::distance::surface_distance`]), over every core for large clouds.
pub fn surface_distances(pose: &InitialPose, points: &[DVec3]) -> Vec<f64> {
    use rayon::prelude::*;
    let one = |p: &DVec3| super::distance::surface_distance(pose, *p).abs();
    if points.len() >= 4 * PARALLEL_DISTANCES {
        points
            .par_iter()
            .with_min_len(PARALLEL_DISTANCES)
            .map(one)
            .collect()
    } else {
        points.iter().map(one).collect()
    }
}

/// Point-to-surface residual statistics relative to the points' bounding-box diagonal, the
/// distances measured over every core ([`point_distances_parallel`]).
pub fn residuals(tess: &Tessellation, node_x: &[DVec3], points: &[DVec3]) -> Residuals {
    Residuals::of(
        point_distances_parallel(tess, node_x, points),
        bounding_diagonal(points),
    )
}

/// The length of the diagonal of the points' axis-aligned bounding box (0 for no points).
pub fn bounding_diagonal(points: &[DVec3]) -> f64 {
    if points.is_empty() {
        return 0.0;
    }
    let (lo, hi) = points
        .iter()
        .fold((DVec3::INFINITY, DVec3::NEG_INFINITY), |(lo, hi), p| {
            (lo.min(*p), hi.max(*p))
        });
    // hi − lo may pass f64's largest: halve before subtracting, divide before squaring.
    let e = hi * 0.5 - lo * 0.5;
    let m = e.abs().max_element();
    if m > 0.0 {
        2.0 * m * (e / m).length()
    } else {
        0.0
    }
}

impl Residuals {
    /// The statistics of point-to-surface distances `d` (data units) relative to `diagonal`;
    /// all zero when there are no distances or the diagonal is not positive.
    pub fn of(mut d: Vec<f64>, diagonal: f64) -> Self {
        if d.is_empty() || !(diagonal > 0.0) {
            return Residuals {
                diagonal,
                ..Default::default()
            };
        }
        d.sort_by(f64::total_cmp);
        let m = d.len() as f64;
        let p95 = d[((0.95 * (m - 1.0)).round() as usize).min(d.len() - 1)];
        Residuals {
            mean: d.iter().sum::<f64>() / m / diagonal,
            rms: (d.iter().map(|x| x * x).sum::<f64>() / m).sqrt() / diagonal,
            p95: p95 / diagonal,
            max: d[d.len() - 1] / diagonal,
            diagonal,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::superquadric::{SuperquadricParams, inside_outside, shape_at};
    use glam::DQuat;

    #[test]
    fn a_refinement_is_given_up_when_it_runs_off_or_grows_too_long() {
        // Coming closer lowers the least distance; a little farther keeps it.
        assert_eq!(refine_check(0.8, 1.0), Some(0.8));
        assert_eq!(refine_check(1.005, 1.0), Some(1.0));
        // More than 1 % farther than the least, or half again as long: given up.
        assert_eq!(refine_check(1.02, 1.0), None);
        assert!(refine_overgrown(3.01, 2.0));
        assert!(!refine_overgrown(2.99, 2.0));
    }

    #[test]
    fn the_squareness_extension_moves_only_an_exponent_at_the_bound_and_only_closer() {
        use crate::synthetic::superquadric_cloud;
        let tess = Tessellation::new(31);
        let (c, q) = (DVec3::new(0.1, -0.2, 0.3), DQuat::from_rotation_x(0.4));
        // A flat-capped cylinder (ε1 = 0.02, round section), sampled exactly.
        let cylinder = SuperquadricParams {
            a: 1.5,
            a1: 0.6,
            a2: 0.6,
            e1: 0.02,
            ..Default::default()
        };
        let points = superquadric_cloud(&cylinder, c, q, 2000, 0.0, 5);
        let weights = vec![1.0; points.len()];
        let state_with = |e1: f64, e2: f64| {
            ModelState::new(&tess, c, q, SuperquadricParams { e1, e2, ..cylinder })
        };
        let distance = |state: &ModelState| {
            let mut x = Vec::new();
            state.node_positions(&tess, &mut x);
            weighted_mean_distance(&tess, &x, &points, &weights)
        };
        // At the bound: ε1 goes below it, to the trial closest to the points, and the surface
        // comes closer; ε2 (round) stays.
        let at_bound = state_with(MIN_EPSILON, 1.0);
        let shape = extend_squareness(&tess, &at_bound, &points, &weights).expect("moved");
        assert!(shape.e1 < MIN_EPSILON && EXTENDED_EPSILONS.contains(&shape.e1));
        assert_eq!(
            (shape.e2, shape.a1, shape.a),
            (1.0, cylinder.a1, cylinder.a)
        );
        let extended = state_with(shape.e1, 1.0);
        for e in EXTENDED_EPSILONS {
            assert!(distance(&extended) <= distance(&state_with(e, 1.0)));
        }
        assert!(distance(&extended) < 0.5 * distance(&at_bound));
        // Above the bound nothing moves, nor at the bound when no trial is closer: a sphere's
        // ε2 at the bound is nearer to 1 than 0.1 already, and squarer is farther.
        assert!(extend_squareness(&tess, &state_with(0.3, 1.0), &points, &weights).is_none());
        let sphere = superquadric_cloud(&SuperquadricParams::default(), c, q, 500, 0.0, 6);
        let round = ModelState::new(
            &tess,
            c,
            q,
            SuperquadricParams {
                e2: MIN_EPSILON,
                ..Default::default()
            },
        );
        assert!(extend_squareness(&tess, &round, &sphere, &vec![1.0; 500]).is_none());
    }

    /// The growth rule is asked after every step: a refinement whose model runs off in length
    /// is given up at the first step that takes it past [`REFINE_MAX_GROWTH`], long before the
    /// distance check of [`REFINE_CHECK_EVERY`] steps.
    #[test]
    fn a_refinement_is_given_up_at_the_first_step_that_makes_it_too_long() {
        use crate::synthetic::superquadric_cloud;
        let tess = Tessellation::new(15);
        let opts = FitOptions::default();
        // Points on an ellipsoid 6 times as long as wide; the model starts as a third of it.
        let long = SuperquadricParams {
            a: 3.0,
            a1: 1.0 / 6.0,
            a2: 1.0 / 6.0,
            ..Default::default()
        };
        let points = superquadric_cloud(&long, DVec3::ZERO, DQuat::IDENTITY, 500, 0.0, 7);
        let start = InitialPose {
            translation: DVec3::ZERO,
            rotation: DQuat::IDENTITY,
            shape: SuperquadricParams { a: 1.0, ..long },
        };
        let longest = |r: &Relaxation| r.state.shape.semi_axes().max_element();
        let refine_for = |budget: u32| {
            let mut relax = Relaxation::new(&tess, &opts, &points, &start);
            relax.refine_least = Some(f64::INFINITY);
            relax.refine_start = longest(&relax);
            let at_rest = relax
                .run(Stage::Refine, budget, &mut |_| {})
                .expect("refine");
            (relax, at_rest)
        };
        let (given_up, at_rest) = refine_for(REFINE_MAX_STEPS);
        assert!(given_up.gave_up && !at_rest);
        let steps = given_up.steps;
        assert!(steps > 1 && steps < REFINE_CHECK_EVERY, "{steps}");
        assert!(longest(&given_up) > REFINE_MAX_GROWTH * given_up.refine_start);
        // One step fewer: not yet too long, and going on.
        let (before, _) = refine_for(steps - 1);
        assert!(!before.gave_up && before.steps == steps - 1);
        assert!(longest(&before) <= REFINE_MAX_GROWTH * before.refine_start);
    }

    #[test]
    fn a_refinement_stalls_when_its_weighted_distance_stops_falling() {
        // No previous check: never stalled; 0.1 % closer or more: going on.
        assert!(!refine_stalled(1.0, None));
        assert!(!refine_stalled(0.998, Some(1.0)));
        assert!(refine_stalled(0.9995, Some(1.0)));
        assert!(refine_stalled(1.02, Some(1.0)));
    }

    /// Near a surface, the search round the nearest nodes finds the distance to the closest of
    /// all triangles, bit for bit; with one node, or none, it still answers.
    #[test]
    fn point_distances_equal_the_closest_of_all_triangles_near_the_surface() {
        let tess = Tessellation::new(9);
        let state = ModelState::new(
            &tess,
            DVec3::new(0.2, -0.1, 0.3),
            DQuat::from_rotation_x(0.7),
            SuperquadricParams {
                a2: 0.6,
                a3: 0.8,
                e1: 0.4,
                e2: 1.5,
                ..Default::default()
            },
        );
        let mut x = Vec::new();
        state.node_positions(&tess, &mut x);
        // Off every node, a little in and out along a fixed skew direction, and off the
        // midpoints of edges.
        let skew = DVec3::new(0.03, -0.02, 0.025);
        let mut points: Vec<DVec3> = x.iter().flat_map(|p| [*p + skew, *p - skew]).collect();
        points.extend(
            tess.triangles()
                .iter()
                .map(|&[a, b, _]| 0.5 * (x[a as usize] + x[b as usize]) + 0.5 * skew),
        );
        let brute: Vec<f64> = points
            .iter()
            .map(|p| {
                tess.triangles()
                    .iter()
                    .map(|&[a, b, c]| {
                        let (a, b, c) = (x[a as usize], x[b as usize], x[c as usize]);
                        closest_point_on_triangle(*p, a, b, c).distance_squared(*p)
                    })
                    .fold(f64::INFINITY, f64::min)
                    .sqrt()
            })
            .collect();
        assert_eq!(point_distances(&tess, &x, &points), brute);
        assert!(brute.iter().any(|&d| d > 0.01));
        assert!(point_distances(&tess, &x, &[]).is_empty());
        // Over the cores, in several runs of points each with its own triangles seen: the same
        // distances to the bit.
        let n = 4 * points.len();
        let many: Vec<DVec3> = points.iter().cycle().take(n).copied().collect();
        assert!(n > 4 * PARALLEL_DISTANCES);
        let expected: Vec<f64> = brute.iter().cycle().take(n).copied().collect();
        assert_eq!(point_distances_parallel(&tess, &x, &many), expected);
        assert!(point_distances_parallel(&tess, &x, &[]).is_empty());
    }

    /// A candidate is refined up to the margin times the chosen fit's placing distance and
    /// not past it.
    #[test]
    fn similarity_candidates_refine_within_the_margin() {
        let chosen = 0.02;
        assert!(refine_candidate(0.5 * chosen, chosen));
        assert!(refine_candidate(SIMILARITY_REFINE_MARGIN * chosen, chosen));
        assert!(!refine_candidate(
            1.001 * SIMILARITY_REFINE_MARGIN * chosen,
            chosen
        ));
        assert!(!refine_candidate(f64::NAN, chosen));
    }

    #[test]
    fn similarity_candidates_share_the_steps_left_within_the_cap() {
        assert_eq!(similarity_share(20_000, 2_000, 4), 4_500);
        assert_eq!(similarity_share(20_000, 2_001, 4), 4_499);
        // All of them together stay within the cap; none is left when it is spent.
        for (max, spent, n) in [(20_000, 1_977, 3), (900, 899, 5), (300, 400, 2), (10, 0, 0)] {
            let share = similarity_share(max, spent, n);
            assert!(
                spent.min(max) + share * n.max(1) as u32 <= max,
                "{max} {spent} {n}"
            );
        }
        assert_eq!(similarity_share(300, 400, 2), 0);
    }

    #[test]
    fn a_stage_ends_when_its_rests_go_round_a_cycle_of_springs() {
        let opts = FitOptions {
            reassign_every: 200,
            tolerance: 1e-5,
            settle_fraction: 0.002,
            ..FitOptions::default()
        };
        let (moving, resting) = (1e-3, 1e-6);
        let mut clock = StageClock::new(Stage::Global);
        // Moving between reattachments: nothing happens; the 200th step reattaches, not over.
        let mut calls = 0;
        for _ in 0..199 {
            assert!(!clock.after_step(moving, &opts, 216, || unreachable!()));
        }
        assert!(!clock.after_step(moving, &opts, 216, || {
            calls += 1;
            (5, 1)
        }));
        assert_eq!(calls, 1);
        // Rests whose reattachments each give new springs (one point of 216 moved: unsettled).
        for signature in [10, 11, 12, 13, 14] {
            assert!(!clock.after_step(resting, &opts, 216, || (1, signature)));
        }
        // Springs of one of the last four rests again: a cycle, the stage is over.
        assert!(clock.after_step(resting, &opts, 216, || (1, 12)));
        // Older than the memory: not a cycle.
        let mut clock = StageClock::new(Stage::Global);
        for signature in [1, 2, 3, 4, 5] {
            assert!(!clock.after_step(resting, &opts, 216, || (1, signature)));
        }
        assert!(!clock.after_step(resting, &opts, 216, || (1, 1)));
        // Alternating springs, A B A: over at the second A.
        let mut clock = StageClock::new(Stage::Refine);
        assert!(!clock.after_step(resting, &opts, 216, || (1, 7)));
        assert!(!clock.after_step(resting, &opts, 216, || (1, 8)));
        assert!(clock.after_step(resting, &opts, 216, || (1, 7)));
        // Every spring changed (the robust weights still sharpening) is no cycle; a settled
        // reattachment ends the stage whatever its springs.
        let mut clock = StageClock::new(Stage::Global);
        assert!(!clock.after_step(resting, &opts, 216, || (216, 7)));
        assert!(!clock.after_step(resting, &opts, 216, || (216, 7)));
        assert!(clock.after_step(resting, &opts, 216, || (0, 9)));
    }

    #[test]
    fn similarity_candidates_of_a_round_shape_are_the_same_surface() {
        // A sphere (ε1 = ε2 = 1, equal semi-axes): the axis candidates (exponents swapped) and
        // the duals about every axis (ε2 = 1, section scale 1) all describe the sphere itself.
        let pose = InitialPose {
            translation: DVec3::new(0.3, -0.2, 0.1),
            rotation: DQuat::from_rotation_y(0.4) * DQuat::from_rotation_x(-0.3),
            shape: SuperquadricParams::default(),
        };
        let candidates = similarity_candidates(&pose);
        // Two axis candidates and a dual about each axis.
        assert_eq!(candidates.len(), 5);
        // Surface points of `pose` lie on the surface of every one of `others`.
        let same_surface = |pose: &InitialPose, others: &[InitialPose]| {
            for c in others {
                for i in 0..200 {
                    let (u, v) = (-1.5 + 3.0 * (i % 20) as f64 / 19.0, 0.031 * i as f64);
                    let p = pose.translation + pose.rotation * shape_at(&pose.shape, u, v);
                    let f = inside_outside(&c.shape, c.rotation.inverse() * (p - c.translation));
                    assert!((f - 1.0).abs() < 1e-9, "{c:?}: F = {f}");
                }
            }
        };
        same_surface(&pose, &candidates);
        // An ellipsoid with three different axes: its axis candidates still are the ellipsoid
        // (each semi-axis stays along its world direction).
        let ellipsoid = InitialPose {
            shape: SuperquadricParams {
                a1: 1.0,
                a2: 0.7,
                a3: 0.5,
                ..pose.shape
            },
            ..pose
        };
        same_surface(&ellipsoid, &similarity_candidates(&ellipsoid)[..2]);
        // A long box: no section is alike enough for a dual except about the long axis.
        let long = InitialPose {
            shape: SuperquadricParams {
                a1: 0.3,
                a2: 0.32,
                a3: 1.0,
                e1: 0.3,
                e2: 0.3,
                ..pose.shape
            },
            ..pose
        };
        let candidates = similarity_candidates(&long);
        assert_eq!(candidates.len(), 3);
        let dual = candidates[2];
        assert!((dual.shape.e2 - 1.7).abs() < 1e-12 && (dual.shape.e1 - 0.3).abs() < 1e-12);
    }

    #[test]
    fn the_cross_section_dual_turns_a_square_into_a_diamond_through_the_same_points() {
        let pose = |e2| InitialPose {
            translation: DVec3::new(0.3, -0.2, 0.1),
            rotation: DQuat::from_rotation_y(0.4),
            shape: SuperquadricParams {
                a: 1.0,
                a1: 1.0,
                a2: 1.0,
                a3: 0.6,
                e1: 0.8,
                e2,
            },
        };
        assert_eq!(cross_section_dual(&pose(1.3)), None);
        // A nearly square section's dual is a nearly diamond one through the same points: the
        // square's surface points lie near the dual's surface, and not near the dual unturned.
        let square = pose(0.15);
        let dual = cross_section_dual(&square).unwrap();
        assert!((dual.shape.e2 - 1.85).abs() < 1e-12);
        let unturned = InitialPose {
            rotation: square.rotation,
            ..dual
        };
        let misfit = |other: &InitialPose| {
            let mut worst: f64 = 0.0;
            for i in 0..200 {
                let (u, v) = (-1.2 + 2.4 * (i % 20) as f64 / 19.0, 0.031 * i as f64);
                let p = square.translation + square.rotation * shape_at(&square.shape, u, v);
                let local = other.rotation.inverse() * (p - other.translation);
                let f = inside_outside(&other.shape, local);
                worst = worst.max((f.powf(other.shape.e1 / 2.0) - 1.0).abs());
            }
            worst
        };
        assert!(misfit(&dual) < 0.15, "{}", misfit(&dual));
        assert!(
            misfit(&unturned) > 2.0 * misfit(&dual),
            "{}",
            misfit(&unturned)
        );
    }
}
