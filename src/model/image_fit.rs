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
//! the part's figure (what its placement lies on, decided by what encloses what; by colour on a
//! colour image, [`ImagePotential::with_colour`]) and the figure's area near it. Parts on one
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

use super::dynamics::{
    DynamicsParams, FreeDofs, ModelState, NodalForces, StepError, Workspace, step_prepared,
};
use super::fem::Tessellation;
use super::fit::max_motion;
use super::forces::image::{
    DEFAULT_BAND, DEFAULT_IMAGE_BETA, ImageForces, ImagePotential, ImageScratch,
};
use super::image_measure::PixelMoments;
pub use super::image_measure::{
    PartRegion, PartSilhouette, iou, outline_potential, outline_segments, part_region,
    part_silhouette, parts_on, silhouette_iou, silhouette_mask,
};
use super::superquadric::SuperquadricParams;
use glam::{DMat3, DQuat, DVec2, DVec3};
use std::sync::Arc;

mod choices;
mod contour;
mod evidence;
mod solved;
use super::fit::Solver;
pub use choices::ImageChoices;
pub use evidence::{EDGE_HIGH, EDGE_LOW};
pub use solved::{
    AREA_SIGMAS, EDGE_REACH, FILLED, MIN_HALF_WIDTH, REST_PX, SNAKE_NODES, TENSION_SIGMAS,
};

/// A part's placement in the image plane: centre, major semi-axis (a vector) and minor semi-axis.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PartAxes {
    /// Centre in plane coordinates.
    pub center: DVec2,
    /// Major semi-axis as a plane vector (direction and length).
    pub major: DVec2,
    /// Minor semi-axis length (in the plane, perpendicular to `major`; also the depth).
    pub minor: f64,
}

/// Why a part could not be placed.
#[derive(Clone, Debug, PartialEq)]
pub enum PlacementError {
    /// The part's centre is not on the image.
    OutsideImage {
        /// Centre in pixels.
        center: DVec2,
    },
    /// An axis has zero or non-finite length.
    DegenerateAxis,
}

impl std::fmt::Display for PlacementError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            PlacementError::OutsideImage { center } => write!(
                f,
                "the part's centre ({:.1}, {:.1}) px is outside the image",
                center.x, center.y
            ),
            PlacementError::DegenerateAxis => {
                write!(f, "an axis of the part has zero or non-finite length")
            }
        }
    }
}

impl std::error::Error for PlacementError {}

impl PartAxes {
    /// From four pixel positions: both ends of the major axis, then both ends of the minor axis.
    pub fn from_points(
        potential: &ImagePotential,
        pixels: [DVec2; 4],
    ) -> Result<Self, PlacementError> {
        if !pixels.iter().all(|p| p.is_finite()) {
            return Err(PlacementError::DegenerateAxis);
        }
        let center_px = (pixels[0] + pixels[1] + pixels[2] + pixels[3]) / 4.0;
        let x = pixels.map(|p| potential.to_plane(p));
        let axes = Self {
            center: potential.to_plane(center_px),
            major: (x[1] - x[0]) / 2.0,
            minor: (x[3] - x[2]).length() / 2.0,
        };
        axes.check(potential)
    }

    /// From a blob's pixel moments.
    pub fn from_blob(potential: &ImagePotential, blob: &Blob) -> Result<Self, PlacementError> {
        let [[sxx, sxy], [_, syy]] = blob.covariance;
        // Eigen-decomposition of the 2×2 covariance (pixels, y down).
        let mean = 0.5 * (sxx + syy);
        let d = (0.25 * (sxx - syy).powi(2) + sxy * sxy).sqrt();
        let (l1, l2) = (mean + d, (mean - d).max(0.0));
        let angle = 0.5 * (2.0 * sxy).atan2(sxx - syy);
        let dir_px = DVec2::new(angle.cos(), angle.sin());
        let c = blob.centroid;
        let major_end = potential.to_plane(c + dir_px * 2.0 * l1.sqrt());
        let center = potential.to_plane(c);
        let axes = Self {
            center,
            major: major_end - center,
            minor: 2.0 * l2.sqrt() * potential.pitch(),
        };
        axes.check(potential)
    }

    fn check(self, potential: &ImagePotential) -> Result<Self, PlacementError> {
        if !(self.major.is_finite() && self.minor.is_finite() && self.center.is_finite())
            || self.major.length() <= 0.0
            || self.minor <= 0.0
        {
            return Err(PlacementError::DegenerateAxis);
        }
        if !potential.contains(self.center) {
            return Err(PlacementError::OutsideImage {
                center: potential.to_pixel(self.center),
            });
        }
        Ok(self)
    }

    /// The pose and shape this placement gives: the model's z axis along the major axis, its
    /// x axis along the minor one, its y axis out of the image; ε1 = ε2 = 1.
    pub fn pose(&self) -> (DVec3, DQuat, SuperquadricParams) {
        ellipsoid_pose(
            self.center.extend(0.0),
            self.major.extend(0.0),
            self.minor,
            DVec3::Z,
        )
    }

    /// A model in this placement with zero local displacement.
    pub fn state(&self, tess: &Tessellation) -> ModelState {
        let (c, r, s) = self.pose();
        ModelState::new(tess, c, r, s)
    }
}

/// The ellipsoid a user places as in the paper's Fig. 6(a), in any plane: centred on `center`,
/// its model z axis along `major` (the half-axis vector, in the plane), its x axis along the minor
/// axis of half-length `minor`, its y axis along the plane's unit `normal`; the depth semi-axis is
/// the minor one, ε1 = ε2 = 1.
pub fn ellipsoid_pose(
    center: DVec3,
    major: DVec3,
    minor: f64,
    normal: DVec3,
) -> (DVec3, DQuat, SuperquadricParams) {
    let ez = major.normalize();
    let ex = normal.cross(ez);
    let ey = ez.cross(ex);
    let rotation = DQuat::from_mat3(&DMat3::from_cols(ex, ey, ez)).normalize();
    let major = major.length();
    let minor = minor.min(major);
    let shape = SuperquadricParams {
        a: major,
        a1: minor / major,
        a2: minor / major,
        a3: 1.0,
        e1: 1.0,
        e2: 1.0,
    }
    .normalized();
    (center, rotation, shape)
}

/// The placement of [`ellipsoid_pose`] from four points in a plane: both ends of the major axis,
/// then both ends of the minor axis (projected into the plane through their mean with unit
/// `normal`); `None` when an axis has no length.
pub fn ellipsoid_from_points(
    points: [DVec3; 4],
    normal: DVec3,
) -> Option<(DVec3, DQuat, SuperquadricParams)> {
    let flat = |v: DVec3| v - normal * v.dot(normal);
    let center = (points[0] + points[1] + points[2] + points[3]) / 4.0;
    let major = flat(points[1] - points[0]) / 2.0;
    let minor = flat(points[3] - points[2]).length() / 2.0;
    let ok = major.is_finite() && minor.is_finite() && major.length() > 1e-9 && minor > 1e-9;
    ok.then(|| ellipsoid_pose(center, major, minor, normal.normalize()))
}

/// A 4-connected region of foreground pixels.
#[derive(Clone, Debug, PartialEq)]
pub struct Blob {
    /// Pixel count.
    pub area: usize,
    /// Mean pixel position (column, row).
    pub centroid: DVec2,
    /// Covariance of the pixel positions [[σxx, σxy], [σxy, σyy]] (pixels², rows downwards).
    pub covariance: [[f64; 2]; 2],
}

/// The foreground's 4-connected blobs of at least `min_area` pixels, largest first.
pub fn segment(potential: &ImagePotential, min_area: usize) -> Vec<Blob> {
    let (w, h) = (potential.width(), potential.height());
    let mask = potential.foreground();
    let mut seen = vec![false; w * h];
    let mut blobs = Vec::new();
    let mut stack = Vec::new();
    for start in 0..w * h {
        if !mask[start] || seen[start] {
            continue;
        }
        seen[start] = true;
        stack.push(start);
        let mut moments = PixelMoments::default();
        while let Some(i) = stack.pop() {
            let (c, r) = (i % w, i / w);
            moments.add(DVec2::new(c as f64, r as f64));
            let mut visit = |j: usize| {
                if mask[j] && !seen[j] {
                    seen[j] = true;
                    stack.push(j);
                }
            };
            if c > 0 {
                visit(i - 1);
            }
            if c + 1 < w {
                visit(i + 1);
            }
            if r > 0 {
                visit(i - w);
            }
            if r + 1 < h {
                visit(i + w);
            }
        }
        if moments.count() >= min_area.max(1)
            && let Some((centroid, covariance)) = moments.mean_and_covariance()
        {
            blobs.push(Blob {
                area: moments.count(),
                centroid,
                covariance,
            });
        }
    }
    blobs.sort_by_key(|b| std::cmp::Reverse(b.area));
    blobs
}

/// Settings of [`fit_image`].
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
    /// Move only in the image plane (see [`FreeDofs::planar`]) and hold the depth ratio a2:
    /// what one image cannot observe stays as placed.
    pub planar: bool,
    /// Hold ε1 = ε2 fixed (the paper does for the pestle and the doll); false by default, so that
    /// a box is fitted as a box. With `planar`, ε2 is held anyway (one image does not observe it,
    /// see [`FreeDofs::with`]).
    pub fix_epsilon: bool,
    /// Run the global DOFs to rest before freeing the local ones.
    pub global_first: bool,
    /// Free the local DOFs at all; false: the global stage only (a pure superquadric per part).
    pub local: bool,
    /// Rest: no node moves more than this × the image extent in a step, or in the last
    /// [`REST_WINDOW`] steps together (a part that only jitters in place as its outline nodes
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

/// One of the paper's image experiments (section VI-A) rebuilt on a shipped stand-in image.
#[derive(Clone, Debug, PartialEq)]
pub struct ImageExperiment {
    /// The image, relative to the crate's root directory.
    pub image: &'static str,
    /// Gaussian width σ in pixels.
    pub sigma: f64,
    /// Each part's four points in pixels (see [`PartAxes::from_points`]), named.
    pub parts: Vec<(&'static str, [DVec2; 4])>,
    /// The fit's settings.
    pub options: ImageFitOptions,
}

fn px(p: [f64; 8]) -> [DVec2; 4] {
    [0, 2, 4, 6].map(|i| DVec2::new(p[i], p[i + 1]))
}

/// The pestle experiment on `assets/data/rocket.png` (640×427): one part, 5043 nodes (k = 71),
/// w0 = 1e-6, w1 = 4e-2, ε1 = ε2 = 1 fixed, placed from four points on the rocket's body. β =
/// 2e-5 (the paper's 4e-6 was for 0–255 intensities and pixel units; with [0, 1] intensities and
/// unit-plane lengths a larger β crumples this 5043-node membrane on the rocket's markings).
pub fn pestle_experiment() -> ImageExperiment {
    let mut options = ImageFitOptions::pestle();
    options.beta = 2e-5;
    ImageExperiment {
        image: "assets/data/rocket.png",
        sigma: 2.0,
        parts: vec![("body", px([322., 130., 322., 400., 308., 265., 336., 265.]))],
        options,
    }
}

/// The doll experiment's 11 parts: name, then both ends of the major axis and both ends of the
/// minor axis in pixels of `horse.png`.
const DOLL_PARTS: [(&str, [i16; 8]); 11] = [
    ("body", [65, 130, 300, 140, 180, 88, 180, 192]),
    ("head", [335, 40, 385, 95, 348, 78, 372, 57]),
    ("neck", [285, 125, 335, 45, 290, 70, 330, 100]),
    ("tail", [50, 100, 30, 245, 25, 170, 55, 170]),
    ("haunch", [60, 160, 130, 200, 100, 150, 90, 215]),
    ("forearm 1", [255, 180, 250, 250, 240, 215, 265, 215]),
    ("forearm 2", [282, 180, 272, 250, 262, 215, 287, 215]),
    ("fore shin 1", [250, 250, 255, 305, 245, 278, 260, 278]),
    ("fore shin 2", [272, 250, 282, 305, 268, 278, 285, 278]),
    ("hind shin 1", [62, 220, 58, 300, 52, 260, 68, 260]),
    ("hind shin 2", [110, 215, 122, 295, 108, 255, 124, 255]),
];

/// The doll experiment on `assets/data/horse.png` (400×328): 11 parts of 963 nodes (k = 31),
/// w0 = 1e-3, w1 = 0.1, ε fixed, each placed crudely from four points as in the paper's
/// Fig. 6(a). With a region force of 0.04 (see [`ImageForces::region`]): the horse's limbs are
/// single-edged where they join the body, and edge forces alone flatten those parts onto it.
/// The region force also orients the global stage's edges ([`ImageForces::oriented`]), which
/// keeps the legs from settling as slivers (none does from 0.02 to 0.05); at 0.04 every part
/// also leaves its placement for the edges within 400 steps.
pub fn doll_experiment() -> ImageExperiment {
    ImageExperiment {
        image: "assets/data/horse.png",
        sigma: 2.0,
        parts: DOLL_PARTS
            .iter()
            .map(|(n, p)| (*n, px(p.map(f64::from))))
            .collect(),
        options: ImageFitOptions {
            region: 0.04,
            fix_epsilon: true,
            ..ImageFitOptions::default()
        },
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
    /// [`outline_potential`] of this part before and after.
    pub outline_before: f64,
    /// [`outline_potential`] after the fit.
    pub outline_after: f64,
    /// Why the part was stopped before rest, in one line: it left the image, or grew past
    /// [`MAX_GROWTH`] times its placed area (see [`fit_part`]). `None` for a part that ran to
    /// rest or to the step cap.
    pub stopped: Option<String>,
}

/// Steps between updates of a part's [`RegionModel`](super::forces::image::RegionModel) and
/// checks of its size.
pub const REGION_REFRESH: usize = 10;

/// A part whose projected silhouette grows past this many times its placed area is stopped: the
/// image gave it nothing to stop at (a balloon in a region that looks like its inside).
pub const MAX_GROWTH: f64 = 4.0;

/// Measures a part's region ([`part_region`], from its node world positions `x`) and sets
/// `forces.region_model` from it: the image's own model on a two-tone image
/// ([`ImagePotential::two_tone`]), else the part's (kept as it was when the measure gives none).
/// [`fit_part`] calls it every [`REGION_REFRESH`] steps, and so does the plugin's simulation of
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
struct RestCheck {
    rest: f64,
    steps: usize,
    checkpoint: Vec<DVec3>,
}

impl RestCheck {
    fn new(rest: f64) -> Self {
        Self {
            rest,
            steps: 0,
            checkpoint: Vec::new(),
        }
    }

    /// True when the step from `before` to `after` ends at rest.
    fn after_step(&mut self, before: &[DVec3], after: &[DVec3]) -> bool {
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
    step_part(tess, forces, initial, opts)
}

/// Solves parts on one image together from their states `initial` (see
/// [`ImageFitOptions::solver`]): what one part covers, the others neither gain nor lose. The
/// solved fit of [`fit_image`], for parts placed by their states (a scene's).
pub fn fit_parts_together(
    tess: &Tessellation,
    potential: &ImagePotential,
    initial: &[ModelState],
    opts: &ImageFitOptions,
) -> Vec<ImagePartFit> {
    let edges = evidence::edge_distance(potential);
    let solved = solved::solve_parts(
        potential,
        edges.as_ref(),
        tess,
        initial,
        opts.local,
        opts.fix_epsilon,
    );
    let outline = |s: &ModelState| {
        let mut x = Vec::new();
        s.node_positions(tess, &mut x);
        outline_potential(potential, &[(tess, &x)])
    };
    solved
        .into_iter()
        .zip(initial)
        .map(|(s, start)| ImagePartFit {
            outline_before: outline(start),
            outline_after: outline(&s.state),
            state: s.state,
            steps: s.global_steps + s.local_steps,
            global_steps: s.global_steps,
            converged: s.converged,
            stopped: None,
        })
        .collect()
}

/// [`fit_part`] by the paper's dynamics.
fn step_part(
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
        |axes, _| step_part(&tess, &forces, axes.state(&tess), opts),
        &mut |_: &()| {},
    )
    .into_iter()
    .collect()
}

#[cfg(test)]
mod tests;
