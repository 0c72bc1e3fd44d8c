//! What a fit is asked for: [`FitOptions`], how it starts ([`Initialization`]), and the checks
//! of its input ([`validate_points`], [`validate_options`]) with their [`FitError`]s.

use crate::model::dynamics::{DynamicsParams, StepError};
use crate::model::fem::check_k;
use crate::model::forces::range::{DEFAULT_COVERAGE, InfluenceMode};
use crate::model::init::InitialPose;
use crate::model::init::Normalization;
use crate::model::noise::{NoiseEstimate, estimate_noise, stiffness_for_noise};
use glam::DVec3;

/// Fewest points a fit accepts: the 11 independent global DOFs need at least 4 points in general
/// position, and the moments a few more to mean anything.
pub const MIN_POINTS: usize = 10;

/// How a fit reaches the rest state of its global DOFs.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub enum Solver {
    /// Solved for: the superquadric by Levenberg–Marquardt ([`crate::model::fit::solve`]); with local DOFs, then
    /// the membrane by linear solves for fixed attachments
    /// ([`super::implicit_joint_options`]).
    #[default]
    Solved,
    /// The paper's explicit Euler dynamics under range springs (every stage of [`super::fit`]).
    Dynamics,
}

impl Solver {
    /// Its name on the command line and in a fit's JSON: "solved" or "dynamics".
    pub fn name(self) -> &'static str {
        match self {
            Solver::Solved => "solved",
            Solver::Dynamics => "dynamics",
        }
    }
}

/// Whether a fit chooses the membrane's stiffness (w0, w1) from the noise its points show
/// ([`crate::model::noise::stiffness_for_noise`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum NoiseStiffness {
    /// w0 and w1 as the options give them.
    #[default]
    Off,
    /// From the noise when it can be estimated; as given when it cannot (too few points).
    WhenMeasurable,
    /// From the noise; a cloud whose noise cannot be estimated is an error.
    Required,
}

/// How the first superquadric is placed.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub enum Initialization {
    /// From the data's centroid and central moments ([`initial_pose`](crate::model::init::initial_pose)).
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
    /// After the joint stage on `k`, a dense cloud's membrane goes on to a finer tessellation
    /// chosen from the data ([`joint_k`](super::joint_k)), carried over from `k` and brought to rest there with
    /// the global DOFs held ([`implicit_joint_options`](super::implicit_joint_options)): nodes where the data's detail is. Off:
    /// every stage keeps `k`. The report's `tess` is the final one. Honoured by [`fit`](super::fit) and the
    /// plugin's headless fit (`fit_headless`); a fit driver in a live app keeps its model's mesh.
    pub k_from_data: bool,
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
    /// After choosing the hypothesis, also try its cross-section dual (turned 45° about the model
    /// axis with ε2 → 2 − ε2, see [`cross_section_dual`](super::cross_section_dual)) when ε2 is far from 1, and keep whichever
    /// fits closer: a square section and a diamond one are each other's local minimum (EMS's
    /// "similarity switching"; beyond the paper).
    pub switch_cross_section: bool,
    /// Try the fit's similarity candidates ([`similarity_candidates`](super::similarity_candidates): the other two axes as the
    /// model's z with the exponents swapped, and the cross-section dual about each axis whose
    /// two perpendicular semi-axes are alike) and keep one that fits closer (EMS's similarity
    /// switching, Liu et al. 2022; beyond the paper): the solved fit by EMS's rule, at most
    /// `LM_SWITCHES` (2) times; the dynamics run each through the global stage and keep the one
    /// closest to the points, weighted by the chosen fit's inlier probabilities. The solved fit
    /// with local DOFs always tries them.
    pub similarity_switch: bool,
    /// Initial pose and shape.
    pub init: Initialization,
    /// How the fit comes to rest: solved for (the default), or by the paper's dynamics
    /// ([`Solver`]).
    pub solver: Solver,
    /// Whether the membrane's stiffness comes from the points' noise when the fit starts.
    pub noise_stiffness: NoiseStiffness,
}

impl Default for FitOptions {
    /// The solved fit ([`Solver::Solved`]); k = 31 (963 nodes), w0 = 1e-3, w1 = 0.1, β = 4,
    /// moments initialisation; for the dynamics γ_g = Δt = 0.05 (each global step a whole
    /// Gauss–Newton step on the springs, bounded by the step's trust region: it reaches rest in
    /// 3–4 steps per reattachment where the interactive default, half a step, takes 15–20),
    /// nearest-node springs reattached every 200 steps, global first.
    fn default() -> Self {
        Self {
            k: 31,
            k_from_data: false,
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
            switch_cross_section: false,
            similarity_switch: false,
            init: Initialization::Moments,
            solver: Solver::Solved,
            noise_stiffness: NoiseStiffness::Off,
        }
    }
}

impl FitOptions {
    /// These options with everything that makes a fit robust to outliers and accurate on partial
    /// clouds (all beyond the paper): outlier-robust weights with a prior outlier fraction of 0.2
    /// (EMS's), point-to-plane springs in the global stage, the cross-section switch and the
    /// similarity switch. `dsq fit`'s `--robust`.
    pub fn robust(self) -> Self {
        Self {
            outlier_ratio: ROBUST_OUTLIER_RATIO,
            point_to_plane: true,
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
    /// stage, and — for a pure superquadric ([`FitOptions::global_only`]) — both switches, i.e.
    /// [`FitOptions::robust`]. With local DOFs the membrane's tessellation is chosen from the
    /// data ([`FitOptions::k_from_data`]). Pair it with
    /// [`FitOptions::with_stiffness_from_noise`] for fits with local DOFs.
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
            k_from_data: !self.global_only,
            outlier_ratio: if self.outlier_ratio > 0.0 {
                self.outlier_ratio
            } else {
                ROBUST_OUTLIER_RATIO
            },
            ..base
        }
    }

    /// These options with the membrane stiffness (w0, w1) chosen from the noise `points` show
    /// ([`crate::model::noise::estimate_noise`], [`crate::model::noise::stiffness_for_noise`]), and the estimate;
    /// unchanged options and `None` when the noise cannot be estimated (too few points).
    pub fn with_stiffness_from_noise(self, points: &[DVec3]) -> (Self, Option<NoiseEstimate>) {
        let Some(noise) = estimate_noise(points) else {
            return (self, None);
        };
        let (w0, w1) = stiffness_for_noise(noise.relative);
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

/// Checks the points a fit is given.
pub fn validate_points(points: &[DVec3]) -> Result<(), FitError> {
    check_count_and_values(points)?;
    check_extent(&Normalization::of(points))
}

/// Checks that `points` are finite and at least [`MIN_POINTS`].
pub(super) fn check_count_and_values(points: &[DVec3]) -> Result<(), FitError> {
    if let Some(index) = points.iter().position(|p| !p.is_finite()) {
        return Err(FitError::NonFinitePoint { index });
    }
    if points.len() < MIN_POINTS {
        return Err(FitError::TooFewPoints {
            found: points.len(),
        });
    }
    Ok(())
}

/// Checks that the points normalised by `n` do not all coincide: coincident to rounding, the
/// spread is below 10⁻¹² of the distance from the origin (a cloud of any scale about the origin
/// is fine).
pub(super) fn check_extent(n: &Normalization) -> Result<(), FitError> {
    if !(n.scale > 1e-12 * n.centroid.abs().max_element()) || !(n.scale > 0.0) {
        return Err(FitError::Degenerate);
    }
    Ok(())
}

/// Checks a fit's options.
pub fn validate_options(o: &FitOptions) -> Result<(), FitError> {
    let d = &o.dynamics;
    let bad = |name: &str, v: f64| FitError::BadOption(format!("{name} = {v:?} is out of range"));
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
    check_k("k", o.k).map_err(FitError::BadOption)?;
    for (name, n) in [
        ("max_steps", o.max_steps),
        ("reassign_every", o.reassign_every),
    ] {
        if n == 0 {
            return Err(FitError::BadOption(format!(
                "{name} = 0 is out of range: it must be at least 1"
            )));
        }
    }
    Ok(())
}
