//! The paper's dynamics on an image ([`crate::model::fit::Solver::Dynamics`]): each part steps
//! its equations of motion under the image forces, the global DOFs to rest and then global and
//! local together, with its region model refreshed and its growth checked as it goes.

use super::options::{ImageFitOptions, ImagePartFit};
use super::outline::MAX_GROWTH;
use crate::model::dynamics::{
    FreeDofs, ModelState, NodalForces, StepError, Workspace, step_prepared,
};
use crate::model::fem::Tessellation;
use crate::model::fit::max_motion;
use crate::model::forces::image::{ImageForces, ImageScratch};
use crate::model::image_measure::{PartRegion, outline_potential, part_region};
use glam::DVec3;

/// Steps between updates of a part's [`RegionModel`](crate::model::forces::image::RegionModel) and
/// checks of its size.
pub const REGION_REFRESH: usize = 10;

/// Measures a part's region ([`part_region`], from its node world positions `x`) and sets
/// `forces.region_model` from it: the image's own model on a two-tone image
/// ([`ImagePotential::two_tone`](crate::model::forces::image::ImagePotential::two_tone)), else the part's (kept as it was when the measure gives none).
/// [`fit_part`](super::fit_part) calls it every [`REGION_REFRESH`] steps, and so does the plugin's simulation of
/// a model with a region force. Returns the measure.
pub fn refresh_region_model(
    forces: &mut ImageForces,
    tess: &Tessellation,
    x: &[DVec3],
) -> PartRegion {
    let now = part_region(&forces.potential, tess, x);
    forces.region_model = forces
        .potential
        .two_tone()
        .or(now.model)
        .or(forces.region_model);
    now
}

/// Why a part measured `now`, placed as `placed`, must stop; `None` while it may go on.
fn outgrown(placed: &PartRegion, now: &PartRegion) -> Option<String> {
    if 2 * now.on_image < now.area {
        let share = 100.0 * now.on_image as f64 / now.area as f64;
        return Some(format!(
            "left the image ({share:.0}% of its silhouette on it)"
        ));
    }
    (placed.area > 0 && now.area as f64 > MAX_GROWTH * placed.area as f64).then(|| {
        format!(
            "grew past {MAX_GROWTH}× its placed area ({} → {} px)",
            placed.area, now.area
        )
    })
}

/// Steps between the checks of a part's net motion (see [`ImageFitOptions::tolerance`]).
pub const REST_WINDOW: usize = 50;

/// The rest test of one stage: a step that moves no node by more than `rest`, or
/// [`REST_WINDOW`] steps that together move none by more.
pub(super) struct RestCheck {
    rest: f64,
    steps: usize,
    checkpoint: Vec<DVec3>,
}

impl RestCheck {
    pub(super) fn new(rest: f64) -> Self {
        Self {
            rest,
            steps: 0,
            checkpoint: Vec::new(),
        }
    }

    /// True when the step from `before` to `after` ends at rest.
    pub(super) fn after_step(&mut self, before: &[DVec3], after: &[DVec3]) -> bool {
        if max_motion(before, after) < self.rest {
            return true;
        }
        self.steps += 1;
        if !self.steps.is_multiple_of(REST_WINDOW) {
            return false;
        }
        let jitters =
            !self.checkpoint.is_empty() && max_motion(&self.checkpoint, after) < self.rest;
        self.checkpoint.clear();
        self.checkpoint.extend_from_slice(after);
        jitters
    }
}

/// [`fit_part`] by the paper's dynamics.
pub(super) fn step_part(
    tess: &Tessellation,
    forces: &ImageForces,
    initial: ModelState,
    opts: &ImageFitOptions,
) -> Result<ImagePartFit, StepError> {
    let mut state = initial;
    let mut x = Vec::new();
    state.node_positions(tess, &mut x);
    let outline_before = outline_potential(&forces.potential, &[(tess, &x)]);
    let mut forces = forces.clone();
    let placed = refresh_region_model(&mut forces, tess, &x);
    let mut stopped = None;
    let mut ws = Workspace::default();
    let mut nf = NodalForces::new(tess.node_count());
    let mut scratch = ImageScratch::default();
    ws.prepare(tess, &state);
    let stages: &[bool] = match (opts.local, opts.global_first) {
        (false, _) => &[false],
        (true, true) => &[false, true],
        (true, false) => &[true],
    };
    let rest = opts.tolerance * forces.potential.frame().extent;
    let (mut steps, mut global_steps, mut converged) = (0, 0, true);
    'stages: for &local in stages {
        let mut params = opts.dynamics;
        // Planar: the depth semi-axis a·a2 (the model's y axis lies along world z) is not observed.
        params.free = FreeDofs::with(local, opts.planar, opts.fix_epsilon);
        let mut at_rest = false;
        // With the region force the part is an object of the foreground, and the global stage
        // pulls its outline only to edges that face outwards (`ImageForces::oriented`): that
        // keeps a thin part from settling as a sliver on one edge. The local stage keeps the
        // plain pull: a folding membrane's normals would switch its forces on and off.
        forces.oriented = forces.region > 0.0 && !local;
        let mut rest_check = RestCheck::new(rest);
        while steps < opts.max_steps {
            nf.clear(tess.node_count());
            forces.accumulate_with(tess, &x, &mut nf, &mut scratch);
            step_prepared(tess, &mut state, &nf, &params, &mut ws)?;
            steps += 1;
            global_steps += !local as usize;
            // The new state's node positions, computed once for the motion and the next forces.
            let x_new = ws.prepare(tess, &state);
            let at = rest_check.after_step(&x, x_new);
            x.clear();
            x.extend_from_slice(x_new);
            if steps.is_multiple_of(REGION_REFRESH) {
                let now = refresh_region_model(&mut forces, tess, &x);
                stopped = outgrown(&placed, &now);
                if stopped.is_some() {
                    converged = false;
                    break 'stages;
                }
            }
            if at {
                at_rest = true;
                break;
            }
        }
        converged &= at_rest;
    }
    let outline_after = outline_potential(&forces.potential, &[(tess, &x)]);
    Ok(ImagePartFit {
        state,
        steps,
        global_steps,
        converged,
        outline_before,
        outline_after,
        stopped,
    })
}
