//! Image forces (section V, eqs. 20, 21, 23): a 3D model pulled towards the intensity edges of a
//! 2D monocular image.
//!
//! **Potential.** P = ‖∇(G_σ ∗ I)‖ (eq. 20): the luminance I (in [0, 1]) is smoothed by a
//! separable Gaussian of width σ pixels, differentiated by central differences, and P is the
//! magnitude of that gradient at every pixel. ∇P is taken at every pixel by central differences
//! of P, and between pixels by the bilinear interpolant of the four surrounding pixels — the
//! quadrilateral element of Fig. 10 with a = b = 1, as section V builds it. All of it is computed
//! once per image and σ ([`ImagePotential::new`]), never per step.
//!
//! **Placement.** The image lies in the world's x–y plane (z = 0), rescaled so its longer side
//! has length `extent` (1: the paper's unit square) and centred on `center` ([`ImageFrame`]);
//! x runs right along the columns, y up against the rows. Derivatives are per unit of that
//! plane, so P is in intensity per unit length and ∇P in intensity per unit length².
//!
//! **Forces.** Π is the orthographic projection onto the plane. Every node whose |x3| is below
//! the band (0.2 by default) gets f = β A_i (∂P/∂x, ∂P/∂y, 0) (eq. 23), where A_i is the node's
//! lumped material area, so β is a force density per unit material area and the pull does not
//! depend on the tessellation. Nodes projecting outside the image get no force.
//!
//! **Damping weight.** The global damping of [`crate::model::dynamics`] is C = γ Σ κ_i L_iᵀ L_i.
//! An image force is the gradient of a potential, not a spring, so κ_i is the potential's
//! curvature scale: κ_i = β A_i P_ref / σ_w², where P_ref is the 99th percentile of P and σ_w the
//! smoothing width in plane units. A blurred step edge of contrast Δ has P = Δ g_σ(x), whose
//! curvature at the ridge is exactly P_max / σ², so the global step is then a damped Newton step
//! on the potential near an edge, and the motion depends on neither β nor the node count.

use crate::model::dynamics::NodalForces;
use crate::model::fem::Tessellation;
use glam::{DVec2, DVec3};
use std::sync::Arc;

mod blur;
mod region;
#[cfg(test)]
mod tests;
mod tone;

pub use blur::MIN_SIGMA;
pub(crate) use blur::smooth;
pub use region::RegionModel;
use tone::foreground_mask;
pub(crate) use tone::two_toned;
pub use tone::{TWO_TONE, luminance_of, otsu_threshold};

/// Default half-width of the band |x3| < band of nodes that feel the image (the paper's 0.2).
pub const DEFAULT_BAND: f64 = 0.2;
/// Default Gaussian width σ in pixels.
pub const DEFAULT_SIGMA: f64 = 2.0;
/// Default force strength β on the potential of [0, 1] intensities in unit-plane coordinates.
pub const DEFAULT_IMAGE_BETA: f64 = 1e-3;

/// Damping weight of a node in a flat part of the image, relative to one on a strong edge.
pub const FLAT_WEIGHT: f64 = 0.1;

/// Where the image sits in the world's x–y plane.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ImageFrame {
    /// World (x, y) of the image's centre.
    pub center: DVec2,
    /// World length of the image's longer side (1: the unit square of the paper).
    pub extent: f64,
}

impl Default for ImageFrame {
    /// The paper's placement: longer side 1, centred on the origin.
    fn default() -> Self {
        Self {
            center: DVec2::ZERO,
            extent: 1.0,
        }
    }
}

/// Why a potential could not be built.
#[derive(Clone, Debug, PartialEq)]
pub enum ImageError {
    /// Fewer than 2 pixels along a side: no central difference or interpolant exists.
    TooSmall {
        /// Width in pixels.
        width: usize,
        /// Height in pixels.
        height: usize,
    },
    /// The luminance buffer does not hold width × height values.
    WrongSize {
        /// Values given.
        got: usize,
        /// width × height.
        expected: usize,
    },
    /// A luminance value is not finite.
    NonFinite {
        /// Row-major index of the pixel.
        index: usize,
    },
    /// σ lies outside [[`MIN_SIGMA`], a third of the image's longer side].
    BadSigma {
        /// The σ given.
        sigma: f64,
        /// The largest σ the image takes.
        max: f64,
    },
    /// The frame's extent is not positive or its centre not finite.
    BadFrame,
}

impl std::fmt::Display for ImageError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            ImageError::TooSmall { width, height } => write!(
                f,
                "image is {width}×{height} pixels; the potential needs at least 2×2"
            ),
            ImageError::WrongSize { got, expected } => {
                write!(f, "luminance has {got} values, expected {expected}")
            }
            ImageError::NonFinite { index } => {
                write!(f, "luminance of pixel {index} is not finite")
            }
            ImageError::BadSigma { sigma, max } => write!(
                f,
                "sigma = {sigma:?} is out of range [{MIN_SIGMA}, {max}] pixels (a third of the image's longer side)"
            ),
            ImageError::BadFrame => write!(
                f,
                "image placement: extent must be positive and the centre finite"
            ),
        }
    }
}

impl std::error::Error for ImageError {}

/// The image potential P and its gradient ∇P at every pixel, with the image's placement.
#[derive(Clone, Debug, PartialEq)]
pub struct ImagePotential {
    width: usize,
    height: usize,
    sigma: f64,
    frame: ImageFrame,
    /// Plane units per pixel.
    pitch: f64,
    luminance: Vec<f64>,
    p: Vec<f64>,
    grad: Vec<DVec2>,
    p_ref: f64,
    foreground: Vec<bool>,
    /// ∇(G_σ ∗ I) at every pixel, per unit length (y up): the direction in which the smoothed
    /// image brightens.
    brightening: Vec<DVec2>,
    /// The foreground's and the background's mean luminance, when the image is two-tone.
    two_tone: Option<RegionModel>,
    /// The image's colour (RGB in [0, 1]) when it has any: what a part's figure is told by.
    colour: Option<Vec<[f32; 3]>>,
}

/// Central difference of a pixel field at (col, row) along x (right) and y (up), per pixel;
/// one-sided at the image border.
fn pixel_gradient<T>(f: &[T], width: usize, height: usize, col: usize, row: usize) -> [T; 2]
where
    T: Copy + std::ops::Sub<Output = T> + std::ops::Div<f64, Output = T>,
{
    let at = |c: usize, r: usize| f[r * width + c];
    let (c0, c1) = (col.saturating_sub(1), (col + 1).min(width - 1));
    let (r0, r1) = (row.saturating_sub(1), (row + 1).min(height - 1));
    let dx = (at(c1, row) - at(c0, row)) / (c1 - c0) as f64;
    // Rows grow downwards; y grows upwards.
    let dy = (at(col, r0) - at(col, r1)) / (r1 - r0) as f64;
    [dx, dy]
}

impl ImagePotential {
    /// Builds P and ∇P from a row-major luminance image (row 0 at the top, values in [0, 1]),
    /// smoothed by a Gaussian of `sigma` pixels, placed in the plane by `frame`.
    pub fn new(
        width: usize,
        height: usize,
        luminance: Vec<f64>,
        sigma: f64,
        frame: ImageFrame,
    ) -> Result<Self, ImageError> {
        if width < 2 || height < 2 {
            return Err(ImageError::TooSmall { width, height });
        }
        if luminance.len() != width * height {
            return Err(ImageError::WrongSize {
                got: luminance.len(),
                expected: width * height,
            });
        }
        if let Some(index) = luminance.iter().position(|v| !v.is_finite()) {
            return Err(ImageError::NonFinite { index });
        }
        // The kernel reaches 3σ: a σ past a third of the image's longer side smooths it all away
        // (and a kernel of 10³⁰⁰ pixels would not fit in memory).
        let max = width.max(height) as f64 / 3.0;
        if !(sigma.is_finite() && (MIN_SIGMA..=max).contains(&sigma)) {
            return Err(ImageError::BadSigma { sigma, max });
        }
        if !(frame.extent.is_finite() && frame.extent > 0.0 && frame.center.is_finite()) {
            return Err(ImageError::BadFrame);
        }
        let pitch = frame.extent / width.max(height) as f64;
        let smooth = smooth(&luminance, width, height, sigma);
        let mut p = vec![0.0; width * height];
        let mut brightening = vec![DVec2::ZERO; width * height];
        for row in 0..height {
            for col in 0..width {
                let [dx, dy] = pixel_gradient(&smooth, width, height, col, row);
                p[row * width + col] = (dx * dx + dy * dy).sqrt() / pitch;
                brightening[row * width + col] = DVec2::new(dx, dy) / pitch;
            }
        }
        let mut grad = vec![DVec2::ZERO; width * height];
        for row in 0..height {
            for col in 0..width {
                let [dx, dy] = pixel_gradient(&p, width, height, col, row);
                grad[row * width + col] = DVec2::new(dx, dy) / pitch;
            }
        }
        let mut sorted = p.clone();
        sorted.sort_by(f64::total_cmp);
        let p_ref = sorted[((sorted.len() - 1) as f64 * 0.99).round() as usize];
        let (foreground, two_tone) = foreground_mask(width, height, &luminance);
        Ok(Self {
            width,
            height,
            sigma,
            frame,
            pitch,
            luminance,
            p,
            grad,
            p_ref,
            foreground,
            brightening,
            two_tone,
            colour: None,
        })
    }

    /// ∇(G_σ ∗ I) at pixel `i` (row-major), per unit length, y up.
    pub(crate) fn brightening_at_pixel(&self, i: usize) -> DVec2 {
        self.brightening[i]
    }

    /// This potential with the image's colour (row-major RGB in [0, 1], the pixels of the
    /// luminance it was built from): a part's figure is then told by colour
    /// ([`crate::model::image_fit`]). A grey image (no pixel's channels differ by more than 1/255)
    /// keeps none. Errors: the wrong number of pixels, or a value not finite.
    pub fn with_colour(mut self, rgb: Vec<[f32; 3]>) -> Result<Self, ImageError> {
        if rgb.len() != self.width * self.height {
            return Err(ImageError::WrongSize {
                got: rgb.len(),
                expected: self.width * self.height,
            });
        }
        if let Some(index) = rgb.iter().position(|p| !p.iter().all(|v| v.is_finite())) {
            return Err(ImageError::NonFinite { index });
        }
        let chroma = |p: &[f32; 3]| {
            p.iter().fold(f32::MIN, |a, &b| a.max(b)) - p.iter().fold(f32::MAX, |a, &b| a.min(b))
        };
        self.colour = rgb.iter().any(|p| chroma(p) > 1.0 / 255.0).then_some(rgb);
        Ok(self)
    }

    /// The image's colour, when it has any (see [`Self::with_colour`]).
    pub fn colour(&self) -> Option<&[[f32; 3]]> {
        self.colour.as_deref()
    }

    /// The image's relief: at every pixel, how fast the smoothed image changes per pixel, the
    /// norm of ∇(G_σ ∗ I) over the colour channels on a colour image, over the luminance
    /// otherwise: the potential P of eq. (20), per pixel rather than per unit length, taken over
    /// colour. Edges are its ridges, whatever the brightness on either side.
    pub(crate) fn relief(&self) -> Vec<f64> {
        let (w, h) = (self.width, self.height);
        let Some(rgb) = &self.colour else {
            return self.p.iter().map(|p| p * self.pitch).collect();
        };
        let mut sq = vec![0.0; w * h];
        for channel in 0..3 {
            let c: Vec<f64> = rgb.iter().map(|p| f64::from(p[channel])).collect();
            let smooth = smooth(&c, w, h, self.sigma);
            for row in 0..h {
                for col in 0..w {
                    let [dx, dy] = pixel_gradient(&smooth, w, h, col, row);
                    sq[row * w + col] += dx * dx + dy * dy;
                }
            }
        }
        sq.into_iter().map(f64::sqrt).collect()
    }

    /// Width in pixels.
    pub fn width(&self) -> usize {
        self.width
    }

    /// Height in pixels.
    pub fn height(&self) -> usize {
        self.height
    }

    /// The smoothing width σ in pixels.
    pub fn sigma(&self) -> f64 {
        self.sigma
    }

    /// The image's placement in the plane.
    pub fn frame(&self) -> ImageFrame {
        self.frame
    }

    /// Plane units per pixel.
    pub fn pitch(&self) -> f64 {
        self.pitch
    }

    /// The unsmoothed luminance, row-major, row 0 at the top.
    pub fn luminance(&self) -> &[f64] {
        &self.luminance
    }

    /// P at every pixel, row-major.
    pub fn potential(&self) -> &[f64] {
        &self.p
    }

    /// The foreground, row-major: the pixels on the side of Otsu's threshold that covers less of
    /// the image's border (an object in front of a background).
    pub fn foreground(&self) -> &[bool] {
        &self.foreground
    }

    /// How well an edge at a point faces along a part's outward in-plane unit normal `n`: the
    /// cosine between `n` and the direction from the part's inside to its outside across the
    /// edge, clamped to [0, 1]. That direction is the one ∇(G_σ ∗ I) brightens in times
    /// `polarity` ([`RegionModel::polarity`]: +1 for a part darker than its surroundings, −1 for
    /// a brighter one). 1 where the part's outline would lie with the object inside and the
    /// background outside; 0 where the part would lie outside the object (a part flattened onto
    /// one edge has one side of each kind). 0 off the image, where the image is flat, or with
    /// polarity 0.
    pub fn edge_facing(&self, x: DVec2, n: DVec2, polarity: f64) -> f64 {
        self.cell(x)
            .map_or(0.0, |cell| self.edge_facing_in(&cell, n, polarity))
    }

    /// [`Self::edge_facing`] at a point whose pixel cell has been looked up.
    fn edge_facing_in(&self, cell: &Cell, n: DVec2, polarity: f64) -> f64 {
        let g = bilinear(&self.brightening, cell);
        let dir = (polarity * g).normalize_or_zero();
        dir.dot(n).clamp(0.0, 1.0)
    }

    /// The luminance at a plane point, bilinear between pixels; `None` off the image.
    pub fn luminance_at(&self, x: DVec2) -> Option<f64> {
        self.cell(x).map(|cell| bilinear(&self.luminance, &cell))
    }

    /// True when the pixel under a plane point is foreground (false off the image).
    pub fn in_foreground(&self, x: DVec2) -> bool {
        self.locate(x).is_some_and(|p| self.foreground_at(p))
    }

    /// The foreground flag of the pixel nearest an image point.
    fn foreground_at(&self, OnImage(p): OnImage) -> bool {
        let c = nearest_index(p.x).min(self.width - 1);
        let r = nearest_index(p.y).min(self.height - 1);
        self.foreground[r * self.width + c]
    }

    /// The image-wide region model of a two-tone image (Otsu's separability at least
    /// [`TWO_TONE`]): the foreground's mean luminance inside, the background's outside. `None`
    /// for a photo, whose parts each measure their own ([`RegionModel::from_samples`]).
    pub fn two_tone(&self) -> Option<RegionModel> {
        self.two_tone
    }

    /// The 99th percentile of P: the height of a typical strong edge.
    pub fn p_ref(&self) -> f64 {
        self.p_ref
    }

    /// The curvature scale P_ref / σ_w² of the potential's ridges, per unit length² (see the
    /// module docs: the damping weight of an image force per unit β A_i).
    pub fn curvature_scale(&self) -> f64 {
        let sigma_w = self.sigma * self.pitch;
        self.p_ref / (sigma_w * sigma_w)
    }

    /// Plane point of a pixel position (column, row; pixel centres at integers).
    pub fn to_plane(&self, pixel: DVec2) -> DVec2 {
        let half = DVec2::new(self.width as f64, self.height as f64) * 0.5;
        let d = (pixel + DVec2::splat(0.5) - half) * self.pitch;
        self.frame.center + DVec2::new(d.x, -d.y)
    }

    /// Pixel position (column, row; pixel centres at integers) of a plane point.
    pub fn to_pixel(&self, x: DVec2) -> DVec2 {
        let half = DVec2::new(self.width as f64, self.height as f64) * 0.5;
        let d = (x - self.frame.center) / self.pitch;
        DVec2::new(d.x, -d.y) + half - DVec2::splat(0.5)
    }

    /// True when the plane point lies on the image.
    pub fn contains(&self, x: DVec2) -> bool {
        self.contains_pixel(self.to_pixel(x))
    }

    /// True when a pixel position lies on the image.
    fn contains_pixel(&self, p: DVec2) -> bool {
        p.x >= -0.5
            && p.y >= -0.5
            && p.x <= self.width as f64 - 0.5
            && p.y <= self.height as f64 - 0.5
    }

    /// The pixel position of a finite plane point on the image; `None` for any other point. The
    /// lookups of one point share it, so its pixel position is computed once.
    fn locate(&self, x: DVec2) -> Option<OnImage> {
        if !x.is_finite() {
            return None;
        }
        let p = self.to_pixel(x);
        self.contains_pixel(p).then_some(OnImage(p))
    }

    /// The four pixels around a plane point and their bilinear weights N_k (the quadrilateral
    /// element of Fig. 10 with a = b = 1); `None` off the image.
    fn cell(&self, x: DVec2) -> Option<Cell> {
        self.locate(x).map(|p| self.cell_at(p))
    }

    /// [`Self::cell`] of an image point.
    fn cell_at(&self, OnImage(p): OnImage) -> Cell {
        let c = p.x.clamp(0.0, (self.width - 1) as f64);
        let r = p.y.clamp(0.0, (self.height - 1) as f64);
        // c, r ≥ 0 after the clamp, so truncation is the floor (without a call: `floor` is not
        // an instruction on the default x86-64 target).
        let c0 = (c as usize).min(self.width - 2);
        let r0 = (r as usize).min(self.height - 2);
        let (s, t) = (c - c0 as f64, r - r0 as f64);
        let i = r0 * self.width + c0;
        (
            [i, i + 1, i + self.width, i + self.width + 1],
            [(1.0 - s) * (1.0 - t), s * (1.0 - t), (1.0 - s) * t, s * t],
        )
    }

    /// P at a plane point, bilinear between pixels; 0 off the image.
    pub fn potential_at(&self, x: DVec2) -> f64 {
        self.cell(x).map_or(0.0, |cell| bilinear(&self.p, &cell))
    }

    /// ∇P at a plane point: central differences at the four surrounding pixels, bilinear between
    /// them (section V); zero off the image.
    pub fn gradient_at(&self, x: DVec2) -> DVec2 {
        self.cell(x)
            .map_or(DVec2::ZERO, |cell| bilinear(&self.grad, &cell))
    }

    /// [`Self::gradient_at`] and [`Self::potential_at`] together, from one lookup of the pixel
    /// cell: the same values to the bit.
    pub fn gradient_and_potential_at(&self, x: DVec2) -> (DVec2, f64) {
        self.cell(x).map_or((DVec2::ZERO, 0.0), |cell| {
            self.gradient_and_potential_in(&cell)
        })
    }

    /// [`Self::gradient_and_potential_at`] of a located point (zero off the image).
    fn gradient_and_potential_in(&self, cell: &Cell) -> (DVec2, f64) {
        (bilinear(&self.grad, cell), bilinear(&self.p, cell))
    }
}

/// The four pixels around a point and their bilinear weights ([`ImagePotential::cell`]).
type Cell = ([usize; 4], [f64; 4]);

/// The pixel position of a plane point that lies on the image ([`ImagePotential::locate`]).
#[derive(Clone, Copy, Debug)]
struct OnImage(DVec2);

/// `p.round().max(0.0) as usize` (the nearest pixel index, halves away from zero, nothing below
/// 0) for every `p`, without `round`, which is a function call, not an instruction, on the
/// default x86-64 target.
fn nearest_index(p: f64) -> usize {
    // Every f64 from 2⁵² up is an integer.
    const INTEGRAL: f64 = 4_503_599_627_370_496.0;
    if p.is_nan() || p <= 0.0 {
        0
    } else if p >= INTEGRAL {
        p as usize
    } else {
        // Below 2⁵² the truncation and the fraction p − ⌊p⌋ are exact.
        let whole = p as usize;
        whole + usize::from(p - whole as f64 >= 0.5)
    }
}

/// Σ_k N_k v_k over the four pixels of a [`ImagePotential::cell`] lookup.
fn bilinear<T>(values: &[T], (idx, w): &Cell) -> T
where
    T: Copy + std::iter::Sum,
    f64: std::ops::Mul<T, Output = T>,
{
    (0..4).map(|k| w[k] * values[idx[k]]).sum()
}

/// Signed doubled area of a triangle projected on the x–y plane (> 0: it faces +z).
pub fn projected_facing(x: &[DVec3], t: &[u32; 3]) -> f64 {
    let (a, b, c) = (
        x[t[0] as usize].truncate(),
        x[t[1] as usize].truncate(),
        x[t[2] as usize].truncate(),
    );
    (b - a).perp_dot(c - a)
}

/// Calls `f(a, b)` for every edge of the projected outline (the occluding contour seen along z):
/// the edges whose two triangles face opposite ways.
pub fn for_each_outline_edge(tess: &Tessellation, x: &[DVec3], f: impl FnMut(u32, u32)) {
    for_each_outline_edge_with(tess, x, &mut Vec::new(), f);
}

/// [`for_each_outline_edge`] with a buffer for the triangles' facings that the caller keeps, so
/// that a search allocates nothing once the buffer has grown.
pub fn for_each_outline_edge_with(
    tess: &Tessellation,
    x: &[DVec3],
    facing: &mut Vec<bool>,
    mut f: impl FnMut(u32, u32),
) {
    // Each triangle's facing once, not once for each of its three edges.
    facing.clear();
    facing.extend(
        tess.triangles()
            .iter()
            .map(|t| projected_facing(x, t) > 0.0),
    );
    for &[a, b, t1, t2] in &tess.edges {
        if facing[t1 as usize] != facing[t2 as usize] {
            f(a, b);
        }
    }
}

/// The buffers [`ImageForces::accumulate_with`] reuses from step to step: which nodes act, each
/// triangle's projected facing, and the nodes' normals when they are computed in one pass. A
/// model that keeps one allocates nothing per step.
#[derive(Clone, Debug, Default)]
pub struct ImageScratch {
    acting: Vec<bool>,
    facing: Vec<bool>,
    normals: Vec<DVec3>,
}

/// True when the region force's normals are cheaper from one pass over every triangle
/// ([`Tessellation::vertex_normals`]) than node by node ([`Tessellation::vertex_normal`]) for
/// `acting` of `nodes` nodes. Node by node, each of a node's triangles (six, except at the poles)
/// is crossed for that node alone; the pass crosses each of the 2k² triangles once and normalises every node, so it
/// costs about what a third of the nodes cost one by one. Both give the same normals to the bit.
fn normals_in_one_pass(acting: usize, nodes: usize) -> bool {
    3 * acting > nodes
}

/// The image forces on one model: a shared potential, the strength β and the band.
#[derive(Clone, Debug, PartialEq)]
pub struct ImageForces {
    /// The potential, shared by every part fitted to the same image.
    pub potential: Arc<ImagePotential>,
    /// Force strength β (eq. 23), per unit material area.
    pub beta: f64,
    /// Nodes with |x3 − 0| below this feel the image (the paper's 0.2).
    pub band: f64,
    /// Only nodes on the projected outline (the occluding contour) feel the image. The paper
    /// pulls every node in the band; but an image edge is where the contour projects, and a
    /// part thinner than the band then has all its nodes pulled, so the surest way to put
    /// nodes on an edge is to flatten the part onto it (a1 → 0). `false` gives the paper's forces.
    pub outline_only: bool,
    /// Region (balloon) force, beyond the paper: every acting node is also pushed along its
    /// outward in-plane normal by `region` × β P_ref / σ_w (a fraction of a strong edge's pull)
    /// times the [`RegionModel::membership`] of the luminance under it: out where the image
    /// looks like the part's inside, in where it looks like its surroundings, and in off the
    /// image. It settles on the boundary between the two and keeps a part that straddles a
    /// single edge from flattening onto it (Cohen's balloon, 1991, with its sign from Chan and
    /// Vese's region term). 0, or no [`Self::region_model`], gives the paper's forces.
    pub region: f64,
    /// The part's own intensity model, which signs the region force and orients the edges;
    /// [`crate::model::image_fit::fit_part`] measures it from the part's placement and keeps it
    /// up to date as the part moves.
    pub region_model: Option<RegionModel>,
    /// With a region model: the outline feels only edges that face its outward normal, with
    /// the part's inside within and its surroundings without ([`ImagePotential::edge_facing`]).
    /// Without it, both sides of a thin part can settle on one edge (a sliver).
    pub oriented: bool,
}

impl ImageForces {
    /// Forces of `potential` with the default β and band, on the outline only.
    pub fn new(potential: Arc<ImagePotential>) -> Self {
        Self {
            potential,
            beta: DEFAULT_IMAGE_BETA,
            band: DEFAULT_BAND,
            outline_only: true,
            region: 0.0,
            region_model: None,
            oriented: false,
        }
    }

    /// True when node position `x` is within the band and projects onto the image.
    fn acts_on(&self, x: DVec3) -> bool {
        x.z.abs() < self.band && self.potential.contains(x.truncate())
    }

    /// The nodes that feel the image: in the band, on the image, and (with `outline_only`) on the
    /// projected outline.
    pub fn acting_nodes(&self, tess: &Tessellation, node_x: &[DVec3], out: &mut Vec<bool>) {
        self.acting_nodes_with(tess, node_x, out, &mut Vec::new());
    }

    /// [`Self::acting_nodes`] with the outline search's buffer of facings.
    fn acting_nodes_with(
        &self,
        tess: &Tessellation,
        node_x: &[DVec3],
        out: &mut Vec<bool>,
        facing: &mut Vec<bool>,
    ) {
        out.clear();
        if self.outline_only {
            out.resize(node_x.len(), false);
            for_each_outline_edge_with(tess, node_x, facing, |a, b| {
                out[a as usize] = true;
                out[b as usize] = true;
            });
            // Only the outline's nodes are looked up in the image.
            for (flag, &x) in out.iter_mut().zip(node_x).filter(|(flag, _)| **flag) {
                *flag = self.acts_on(x);
            }
        } else {
            out.extend(node_x.iter().map(|&x| self.acts_on(x)));
        }
    }

    /// Adds f_i = β A_i (∂P/∂x, ∂P/∂y, 0) (eq. 23) and the damping weight κ_i of the module docs
    /// to every acting node.
    pub fn accumulate(&self, tess: &Tessellation, node_x: &[DVec3], out: &mut NodalForces) {
        self.accumulate_with(tess, node_x, out, &mut ImageScratch::default());
    }

    /// [`Self::accumulate`] with buffers the caller keeps from step to step, the same forces to
    /// the bit. When few nodes act (on the outline of a rounded part, a few percent of them) the
    /// region force's normals are computed at the acting nodes alone
    /// ([`Tessellation::vertex_normal`]); when many do, in one pass over the triangles.
    pub fn accumulate_with(
        &self,
        tess: &Tessellation,
        node_x: &[DVec3],
        out: &mut NodalForces,
        scratch: &mut ImageScratch,
    ) {
        let kappa = self.beta * self.potential.curvature_scale();
        let ImageScratch {
            acting,
            facing,
            normals,
        } = scratch;
        self.acting_nodes_with(tess, node_x, acting, facing);
        let push = self
            .region_model
            .filter(|_| self.region > 0.0)
            .map(|model| {
                let sigma_w = self.potential.sigma() * self.potential.pitch();
                (
                    self.region * self.beta * self.potential.p_ref() / sigma_w,
                    model,
                )
            });
        let polarity = self
            .region_model
            .filter(|_| self.oriented)
            .map(|m| m.polarity());
        let needs_normals = push.is_some() || polarity.is_some();
        let one_pass = needs_normals
            && normals_in_one_pass(acting.iter().filter(|&&a| a).count(), node_x.len());
        if one_pass {
            tess.vertex_normals(node_x, normals);
        }
        for (i, &x) in node_x.iter().enumerate() {
            if !acting[i] {
                continue;
            }
            let a = tess.node_area[i];
            let at = self.potential.locate(x.truncate());
            let n = if !needs_normals {
                DVec2::ZERO
            } else if one_pass {
                normals[i].truncate().normalize_or_zero()
            } else {
                tess.vertex_normal(node_x, i).truncate().normalize_or_zero()
            };
            // One lookup of the pixel cell for every value sampled there.
            let cell = at.map(|p| self.potential.cell_at(p));
            if let Some((push, model)) = push
                && n != DVec2::ZERO
            {
                let sign = cell.as_ref().map_or(-1.0, |cell| {
                    model.membership(bilinear(&self.potential.luminance, cell))
                });
                out.force[i] += (sign * push * a * n).extend(0.0);
            }
            // An oriented outline feels only the edges that face its outward normal.
            let facing = match (&cell, polarity) {
                (_, None) => 1.0,
                (Some(cell), Some(polarity)) => self.potential.edge_facing_in(cell, n, polarity),
                (None, Some(_)) => 0.0,
            };
            let (g, p) = cell.as_ref().map_or((DVec2::ZERO, 0.0), |cell| {
                self.potential.gradient_and_potential_in(cell)
            });
            let near_edge = (p / self.potential.p_ref()).clamp(0.0, 1.0);
            out.force[i] += facing * self.beta * a * DVec3::new(g.x, g.y, 0.0);
            out.stiffness[i] += kappa * a * (FLAT_WEIGHT + (1.0 - FLAT_WEIGHT) * near_edge);
        }
    }

    /// The potential energy E = −β Σ A_i P(Π x_i) over the acting nodes, whose negative gradient
    /// the forces approximate (with the set of acting nodes held fixed).
    pub fn energy(&self, tess: &Tessellation, node_x: &[DVec3]) -> f64 {
        let mut acting = Vec::new();
        self.acting_nodes(tess, node_x, &mut acting);
        -node_x
            .iter()
            .enumerate()
            .filter(|(i, _)| acting[*i])
            .map(|(i, x)| self.beta * tess.node_area[i] * self.potential.potential_at(x.truncate()))
            .sum::<f64>()
    }
}
