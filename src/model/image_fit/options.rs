//! What an image fit is asked ([`ImageFitOptions`]) and what it answers per part
//! ([`ImagePartFit`]).

use crate::model::dynamics::{DynamicsParams, ModelState};
use crate::model::fit::Solver;
use crate::model::forces::image::{DEFAULT_BAND, DEFAULT_IMAGE_BETA, ImageForces, ImagePotential};
use std::sync::Arc;

/// Settings of [`fit_image`](super::fit_image).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ImageFitOptions {
    /// Latitude rings and longitudes of each part (k² + 2 nodes).
    pub k: usize,
    /// Dynamics (w0, w1, Δt, damping); `free` is set per stage.
    pub dynamics: DynamicsParams,
    /// Force strength β.
    pub beta: f64,
    /// Band half-width on |x3|.
    pub band: f64,
    /// Pull only the projected outline (see [`ImageForces::outline_only`]); false: the paper's
    /// forces on every node in the band.
    pub outline_only: bool,
    /// Region (balloon) force fraction (see [`ImageForces::region`]); 0: the paper's forces.
    pub region: f64,
    /// Move only in the image plane (see [`FreeDofs::planar`](crate::model::dynamics::FreeDofs::planar)) and hold the depth ratio a2:
    /// what one image cannot observe stays as placed.
    pub planar: bool,
    /// Hold ε1 = ε2 fixed (the paper does for the pestle and the doll); false by default, so that
    /// a box is fitted as a box. With `planar`, ε2 is held anyway (one image does not observe it,
    /// see [`FreeDofs::with`](crate::model::dynamics::FreeDofs::with)).
    pub fix_epsilon: bool,
    /// Run the global DOFs to rest before freeing the local ones.
    pub global_first: bool,
    /// Free the local DOFs at all; false: the global stage only (a pure superquadric per part).
    pub local: bool,
    /// Rest: no node moves more than this × the image extent in a step, or in the last
    /// [`REST_WINDOW`](super::REST_WINDOW) steps together (a part that only jitters in place as its outline nodes
    /// switch).
    pub tolerance: f64,
    /// Step cap per part (the dynamics).
    pub max_steps: usize,
    /// How a part comes to rest: solved for it by least squares ([`Solver::Solved`], the
    /// default; see the module docs), or by the paper's dynamics ([`Solver::Dynamics`]).
    pub solver: Solver,
}

impl Default for ImageFitOptions {
    /// k = 31 (963 nodes), w0 = 1e-3, w1 = 0.1 and band 0.2 (the doll experiment's), ε free.
    fn default() -> Self {
        Self {
            k: 31,
            dynamics: DynamicsParams::default(),
            beta: DEFAULT_IMAGE_BETA,
            band: DEFAULT_BAND,
            outline_only: true,
            region: 0.0,
            planar: true,
            fix_epsilon: false,
            global_first: true,
            local: true,
            tolerance: 1e-5,
            max_steps: 3000,
            solver: Solver::Solved,
        }
    }
}

impl ImageFitOptions {
    /// The image forces these options apply with `potential`.
    pub fn forces(&self, potential: Arc<ImagePotential>) -> ImageForces {
        ImageForces {
            potential,
            beta: self.beta,
            band: self.band,
            outline_only: self.outline_only,
            region: self.region,
            region_model: None,
            oriented: false,
        }
    }

    /// The pestle experiment: k = 71 (5043 nodes), w0 = 1e-6, w1 = 4e-2, ε fixed.
    pub fn pestle() -> Self {
        let mut o = Self {
            k: 71,
            fix_epsilon: true,
            ..Self::default()
        };
        o.dynamics.w0 = 1e-6;
        o.dynamics.w1 = 4e-2;
        o
    }
}

/// One part's fit.
#[derive(Clone, Debug)]
pub struct ImagePartFit {
    /// The state at rest (or at the step cap).
    pub state: ModelState,
    /// Steps taken in all.
    pub steps: usize,
    /// Steps with the local DOFs held.
    pub global_steps: usize,
    /// True when every stage ended at rest.
    pub converged: bool,
    /// [`outline_potential`](super::outline_potential) of this part before and after.
    pub outline_before: f64,
    /// [`outline_potential`](super::outline_potential) after the fit.
    pub outline_after: f64,
    /// Why the part was stopped before rest, in one line: it left the image, or grew past
    /// [`MAX_GROWTH`](super::MAX_GROWTH) times its placed area (see [`fit_part`](super::fit_part)). `None` for a part that ran to
    /// rest or to the step cap.
    pub stopped: Option<String>,
}
