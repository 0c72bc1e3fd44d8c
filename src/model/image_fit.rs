//! Fitting parts to a 2D image (section VI-A): placing them, bringing them to rest on the image
//! (solved, or under the image forces of [`crate::model::forces::image`]), and measuring how well
//! their outlines sit on the image's edges.
//!
//! **Placing a part.** The paper places each part from four points picked with the mouse: the
//! centre and the ends of two axes. [`PartAxes::from_points`] takes both ends of the major axis
//! and both ends of the minor axis (in pixels): the centre is their mean, the semi-axes half
//! their lengths. [`segment`] places parts with no user at all, as the paper proposes: the
//! luminance is thresholded (Otsu), split into 4-connected blobs, and each blob's central
//! moments give a centre and two semi-axes (2√λ of the covariance, exact for a filled ellipse).
//!
//! A part's long axis becomes the superquadric's polar (z) axis, so its latitude rings cut across
//! it; its depth (the world z extent) is taken equal to the minor semi-axis, as for a body of
//! revolution; ε1 = ε2 = 1.
//!
//! **Solved (the default, beyond the paper).** Each part's projected outline, a superellipse
//! (centre, turn, two semi-axes, ε1), is solved by the Levenberg–Marquardt engine of
//! [`crate::model::lm`] against the distance from the image's Canny edges, the distance outside
//! the part's figure (what its clicks lie on, bounded by edges: the watershed of the image's
//! colour relief from the placement's core, [`CORE`], against all beyond it grown [`GROUND`]
//! times; on a silhouette, what encloses what) and the figure's area near it. Parts on one
//! image are solved in sweeps until none moves ([`fit_parts_together`]): what one covers, the
//! others neither gain nor lose. Then a closed contour with one radial displacement per node and
//! its own tension is solved the same way and lifted onto the membrane. Both energies are bounded
//! below, so every part ends at rest; bounds keep it at least [`MIN_HALF_WIDTH`] pixels in
//! semi-axis and at most [`MAX_GROWTH`] times its placed area.
//!
//! **The paper's dynamics** ([`Solver::Dynamics`]). Each part runs on its own (parts do not
//! interact): global DOFs until rest, then global and local together until rest, or `max_steps`
//! in all. Rest is a step that moves no node
//! by more than `tolerance` × the image's extent, or [`REST_WINDOW`] steps that together move none
//! by more (a part that only jitters in place). With a region force, the global stage pulls the
//! outline only to edges that face outwards ([`ImageForces::oriented`]); the local stage keeps the
//! plain pull.
//!
//! **Measures** live in [`crate::model::image_measure`] and are re-exported here.
//!
//! **One file a stage**, each using only those below it: `placement` (four clicks or blobs),
//! `evidence` (the edges and distance fields), `outline` (the superellipse, its residuals and
//! the area term), `figure` (what a part lies on), `solved` (the global stage), `contour` (the
//! local stage), and `dynamics` (the paper's dynamics); this file runs them in order.

mod choices;
mod contour;
mod dynamics;
mod evidence;
mod figure;
mod options;
mod outline;
mod placement;
mod solved;

use crate::model::dynamics::{ModelState, StepError};
use crate::model::fem::Tessellation;
use crate::model::fit::Solver;
use crate::model::forces::image::{ImageForces, ImagePotential};
use std::sync::Arc;

pub use crate::model::image_measure::{
    PartRegion, PartSilhouette, iou, outline_potential, outline_segments, part_region,
    part_silhouette, parts_on, silhouette_iou, silhouette_mask,
};
pub use choices::ImageChoices;
pub use contour::{SNAKE_NODES, TENSION_SIGMAS};
pub use dynamics::{REGION_REFRESH, REST_WINDOW, refresh_region_model};
pub use evidence::{EDGE_HIGH, EDGE_LOW};
pub use figure::{CORE, FILLED, GROUND};
pub use options::{ImageFitOptions, ImagePartFit};
pub use outline::{AREA_SIGMAS, EDGE_REACH, MAX_GROWTH, MIN_HALF_WIDTH};
pub use placement::{
    Blob, PartAxes, PlacementError, ellipsoid_from_points, ellipsoid_pose, segment,
};
pub use solved::REST_PX;

/// Runs one part from `initial` to rest under `forces`.
///
/// The part's region model ([`ImageForces::region_model`]) is the image's own on a two-tone
/// image ([`ImagePotential::two_tone`]). On a photo it is measured from the part's placement and
/// again every [`REGION_REFRESH`] steps ([`part_region`]), so the region force compares the
/// image with the part's own inside and surroundings. A part whose silhouette leaves the image
/// (less than half of it on the image) or grows past [`MAX_GROWTH`] times its placed area is
/// stopped there, and [`ImagePartFit::stopped`] says why.
pub fn fit_part(
    tess: &Tessellation,
    forces: &ImageForces,
    initial: ModelState,
    opts: &ImageFitOptions,
) -> Result<ImagePartFit, StepError> {
    if opts.solver == Solver::Solved {
        let fits = fit_parts_together(tess, &forces.potential, &[initial], opts);
        return Ok(fits.into_iter().next().expect("one part in, one out"));
    }
    dynamics::step_part(tess, forces, initial, opts)
}

/// Solves parts on one image together from their states `initial` (see
/// [`ImageFitOptions::solver`]): what one part covers, the others neither gain nor lose. The
/// solved fit of [`fit_image`], for parts placed by their states (a scene's).
///
/// The pipeline: the image's edges; each part's figure (what its clicks lie on, bounded by
/// edges); the global stage, swept over the parts until none moves; then, with `opts.local`,
/// each part's contour lifted onto its membrane (see the module docs).
pub fn fit_parts_together(
    tess: &Tessellation,
    potential: &ImagePotential,
    initial: &[ModelState],
    opts: &ImageFitOptions,
) -> Vec<ImagePartFit> {
    let edges = evidence::edge_distance(potential);
    let relief = potential.relief();
    let parts: Vec<solved::Part> = initial
        .iter()
        .map(|s| solved::Part::new(potential, edges.as_ref(), &relief, s))
        .collect();
    let global = solved::sweep(&parts, opts.fix_epsilon);
    let outlines: Vec<outline::Outline> = global.iter().map(|g| g.0).collect();
    let outline_measure = |s: &ModelState| {
        let mut x = Vec::new();
        s.node_positions(tess, &mut x);
        outline_potential(potential, &[(tess, &x)])
    };
    parts
        .iter()
        .zip(global)
        .zip(initial)
        .enumerate()
        .map(|(k, ((part, (o, global_steps, rested)), start))| {
            let mut state = part.state(&o, potential, tess);
            let (mut local_steps, mut converged) = (0, rested);
            if opts.local {
                let area = part.area(&solved::others(&outlines, k));
                let snake = contour::solve_contour(
                    &part.fields(),
                    area.as_ref(),
                    &o,
                    potential.sigma(),
                    &outline::engine_options(),
                );
                local_steps = snake.steps;
                converged &= snake.converged;
                contour::lift(&snake, potential.pitch(), tess, &mut state);
            }
            ImagePartFit {
                outline_before: outline_measure(start),
                outline_after: outline_measure(&state),
                state,
                steps: global_steps + local_steps,
                global_steps,
                converged,
                stopped: None,
            }
        })
        .collect()
}

/// Fits every part in `initial` to the image (each on its own, the parts side by side).
pub fn fit_image(
    potential: Arc<ImagePotential>,
    initial: &[PartAxes],
    opts: &ImageFitOptions,
) -> Result<Vec<ImagePartFit>, StepError> {
    let tess = Tessellation::new(opts.k);
    if opts.solver == Solver::Solved {
        let states: Vec<ModelState> = initial.iter().map(|a| a.state(&tess)).collect();
        return Ok(fit_parts_together(&tess, &potential, &states, opts));
    }
    let forces = opts.forces(potential);
    // The parts side by side (as range parts are): a thread a part.
    crate::model::parallel::run_parallel(
        initial,
        |axes, _| dynamics::step_part(&tess, &forces, axes.state(&tess), opts),
        &mut |_: &()| {},
    )
    .into_iter()
    .collect()
}

#[cfg(test)]
mod tests;
