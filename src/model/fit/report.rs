//! What a fit returns ([`FitReport`]) and the one way it is written out ([`FitSummary`]): the
//! JSON of `dsq fit --out-params`, of `dsq fit`'s line (with the residuals at the top level) and
//! of the Python package's `FitResult.to_dict()`.

use super::context::{Context, Outcome};
use super::options::{FitOptions, Solver};
use super::residuals::{Residuals, unit_residuals};
use crate::model::dynamics::ModelState;
use crate::model::fem::Tessellation;
use crate::model::frame::quat_to_paper;
use crate::model::init::InitialPose;
use crate::model::noise::NoiseEstimate;
use crate::model::superquadric::SuperquadricParams;

/// The outcome of a fit.
#[derive(Clone, Debug)]
pub struct FitReport {
    /// The fitted state in the data's frame and units.
    pub state: ModelState,
    /// The tessellation the state lives on.
    pub tess: Tessellation,
    /// Steps taken, over every initial hypothesis tried: Euler steps of the dynamics, or the
    /// solved fit's Levenberg–Marquardt steps and linear solves of the membrane.
    pub steps: u32,
    /// Steps the chosen hypothesis took with the global DOFs alone.
    pub global_steps: u32,
    /// Reattachments done.
    pub reassignments: u32,
    /// True when the loop stopped at rest rather than at the step cap.
    pub converged: bool,
    /// Steps whose local update was sub-stepped for stability.
    pub substepped_steps: u32,
    /// Point-to-surface residuals of the fitted model.
    pub residuals: Residuals,
    /// Initial pose the fit started from (data frame): the chosen hypothesis, or the similarity
    /// candidate the fit moved to.
    pub initial: InitialPose,
    /// The options the fit ran with: those given, with the membrane's stiffness chosen from the
    /// noise where they asked ([`FitOptions::noise_stiffness`]); `options.solver` is the solver
    /// that ran.
    pub options: FitOptions,
    /// The noise the points show, when the stiffness was chosen from it.
    pub noise: Option<NoiseEstimate>,
}

impl FitReport {
    /// The report of the fit of `ctx` that ended in `outcome`: the state mapped back to the
    /// data's frame and units, and its residuals measured on every point.
    pub(super) fn new(ctx: &Context, outcome: Outcome) -> Self {
        let norm = &ctx.norm;
        // Measured in the unit frame, so that no squared distance overflows at any scale; the
        // figures are relative to the diagonal, so only it is scaled back.
        let mut residuals = unit_residuals(&outcome.tess, &outcome.state, &ctx.unit);
        residuals.diagonal *= norm.scale;
        Self {
            state: norm.state_to_data(&outcome.state),
            initial: norm.pose_to_data(&outcome.tess, &outcome.start),
            tess: outcome.tess,
            steps: outcome.steps,
            global_steps: outcome.global_steps,
            reassignments: outcome.reassignments,
            converged: outcome.converged,
            substepped_steps: outcome.substepped_steps,
            residuals,
            options: ctx.opts,
            noise: ctx.noise,
        }
    }

    /// The fit's parameters and figures, as they are written out.
    pub fn summary(&self) -> FitSummary {
        let s = &self.state;
        let n = s.displacement.len().max(1) as f64;
        let local = s
            .displacement
            .iter()
            .map(|d| d.length_squared())
            .sum::<f64>();
        let d = &self.options.dynamics;
        FitSummary {
            translation: s.translation.to_array(),
            rotation: quat_to_paper(s.rotation),
            shape: s.shape,
            taper: s.deformation.taper,
            bend: s.deformation.bend,
            nodes: self.tess.node_count(),
            k: self.tess.k,
            local_rms: (local / n).sqrt(),
            steps: self.steps,
            global_steps: self.global_steps,
            converged: self.converged,
            solver: self.options.solver,
            global_only: self.options.global_only,
            residuals: self.residuals,
            noise: self.noise.map(|e| e.relative),
            w0: self.noise.map(|_| d.w0),
            w1: self.noise.map(|_| d.w1),
        }
    }
}

/// The parameters and figures of a fit ([`FitReport::summary`]), serialisable to JSON.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct FitSummary {
    /// Translation c (data units).
    pub translation: [f64; 3],
    /// Rotation quaternion in the paper's order [s, v1, v2, v3].
    pub rotation: [f64; 4],
    /// The global shape (a in data units), flattened into the JSON object.
    #[serde(flatten)]
    pub shape: SuperquadricParams,
    /// Tapering (t_x, t_y) of [`crate::model::deform`] (0 unless freed).
    pub taper: [f64; 2],
    /// Bending (b_x, b_y) of [`crate::model::deform`] (0 unless freed).
    pub bend: [f64; 2],
    /// Node count k² + 2.
    pub nodes: usize,
    /// Rings and longitudes k.
    pub k: usize,
    /// RMS length of the local displacements (data units).
    pub local_rms: f64,
    /// Steps taken.
    pub steps: u32,
    /// Steps the kept model took with its global DOFs alone.
    pub global_steps: u32,
    /// Whether the fit came to rest before the step cap.
    pub converged: bool,
    /// The solver that ran: "solved" or "dynamics".
    #[serde(serialize_with = "solver_name")]
    pub solver: Solver,
    /// Whether the local DOFs stayed frozen (a pure superquadric).
    pub global_only: bool,
    /// Point-to-surface residuals, as fractions of the bounding-box diagonal.
    pub residuals: Residuals,
    /// The noise the points show (fraction of the diagonal), when the stiffness came from it.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub noise: Option<f64>,
    /// The membrane stiffness w0 chosen from the noise.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub w0: Option<f64>,
    /// The membrane stiffness w1 chosen from the noise.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub w1: Option<f64>,
}

impl FitSummary {
    /// The summary as one JSON object with the residuals' figures at its top level (`mean`,
    /// `rms`, `p95`, `max`, `diagonal`): `dsq fit`'s line.
    pub fn flat_json(&self) -> serde_json::Value {
        let mut v = serde_json::to_value(self).unwrap_or(serde_json::Value::Null);
        if let Some(map) = v.as_object_mut()
            && let Some(serde_json::Value::Object(r)) = map.remove("residuals")
        {
            map.extend(r);
        }
        v
    }
}

/// A solver by its name in the JSON ([`Solver::name`]).
fn solver_name<S: serde::Serializer>(solver: &Solver, s: S) -> Result<S::Ok, S::Error> {
    s.serialize_str(solver.name())
}
