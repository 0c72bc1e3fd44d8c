//! What every stage of a fit shares ([`Context`]): the points in the data's frame and in the
//! unit frame they are normalised to once, the options as the fit runs them (the membrane's
//! stiffness chosen from the noise where they ask), and the noise estimate. Also what the stages
//! hand on: their progress ([`FitProgress`], [`Stage`]) and the model they reached
//! ([`Outcome`]).

use super::options::{
    FitError, FitOptions, NoiseStiffness, check_count_and_values, check_extent, validate_options,
};
use crate::model::dynamics::ModelState;
use crate::model::fem::Tessellation;
use crate::model::init::{InitialPose, Normalization};
use crate::model::noise::NoiseEstimate;
use glam::DVec3;

/// Which degrees of freedom the loop is moving, and with which forces.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Stage {
    /// Global DOFs only, with the model-to-data coverage springs on (placing the model).
    Cover,
    /// Global DOFs only (local held), the paper's forces.
    Global,
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

/// Where a fit reports: its progress, and the model (unit frame) once its superquadric is
/// chosen, before the membrane comes to rest.
pub(super) struct Sink<'a> {
    /// Progress, from the calling thread.
    pub progress: &'a mut dyn FnMut(&FitProgress),
    /// The model as the fit has it (unit frame, on its tessellation).
    pub watch: &'a mut dyn FnMut(&Tessellation, &ModelState),
}

/// The points and settings every stage of one fit reads.
pub(super) struct Context {
    /// The map between the data's frame and the unit frame.
    pub norm: Normalization,
    /// The points in the unit frame (centroid at the origin, RMS radius 1).
    pub unit: Vec<DVec3>,
    /// The options as the fit runs them.
    pub opts: FitOptions,
    /// The noise the points show, when the stiffness was chosen from it.
    pub noise: Option<NoiseEstimate>,
}

impl Context {
    /// The context of a fit of `points` with `opts`: the points and options checked, the points
    /// normalised, and the membrane's stiffness chosen from their noise where `opts` ask
    /// ([`FitOptions::noise_stiffness`]).
    pub fn new(points: &[DVec3], opts: &FitOptions) -> Result<Self, FitError> {
        check_count_and_values(points)?;
        let norm = Normalization::of(points);
        check_extent(&norm)?;
        validate_options(opts)?;
        let (opts, noise) = match opts.noise_stiffness {
            NoiseStiffness::Off => (*opts, None),
            asked => match opts.with_stiffness_from_noise(points) {
                (_, None) if asked == NoiseStiffness::Required => {
                    return Err(FitError::BadOption(
                        "too few points to estimate the noise (w1 auto)".into(),
                    ));
                }
                found => found,
            },
        };
        let unit = points.iter().map(|p| norm.unit_point(*p)).collect();
        Ok(Self {
            norm,
            unit,
            opts,
            noise,
        })
    }
}

/// The model a plan brought to rest, in the unit frame, and what it took.
pub(super) struct Outcome {
    /// The fitted state (unit frame).
    pub state: ModelState,
    /// The tessellation it lives on.
    pub tess: Tessellation,
    /// The start it came from (unit frame).
    pub start: InitialPose,
    /// Steps over every start and candidate tried.
    pub steps: u32,
    /// Steps the kept model took with the global DOFs alone.
    pub global_steps: u32,
    /// Reattachments.
    pub reassignments: u32,
    /// Steps whose local update was sub-stepped.
    pub substepped_steps: u32,
    /// At rest rather than at the step cap.
    pub converged: bool,
}
