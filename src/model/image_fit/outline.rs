//! What a solved image fit (beyond the paper) fits and measures: a part's projected outline,
//! the residuals along it and the area term. The global stage ([`super::solved`]) and the
//! contour ([`super::contour`]) both solve over these.
//!
//! **The outline.** Seen along its y axis (the view), a superquadric's occluding outline is its
//! x–z section, the superellipse |x/a1|^(2/ε1) + |z/a3|^(2/ε1) = 1 (scaled by a); ε2 and the depth
//! are not observed. [`Outline`] is that superellipse in pixel coordinates: centre, the turn θ of
//! its z axis from the image's columns, the semi-axes r1 (model x) and r3 (model z), and ε1.
//!
//! **Two residuals at each outline sample**, each weighted by the square root of the share of
//! the placed outline's length it stands for (the energy is a mean along the outline, which a
//! shrinking outline cannot lower by itself):
//! - the edge residual: the distance to the nearest image edge ([`super::evidence`]),
//!   saturated at [`EDGE_REACH`] σ as c·tanh(d/c): an edge farther than the potential reaches does
//!   not pull (chamfer matching);
//! - the region residual: the distance outside the part's figure ([`super::figure`]:
//!   what the placement lies on, bounded by edges), saturated at the placed minor
//!   semi-axis; 0 inside, where a sample may be where the part joins another (a limb's end in
//!   the body).
//!
//! **The area term** ([`Area`]): at pixels within the part's reach, its soft silhouette against
//! the figure's soft membership, each pixel weighing [`AREA_SIGMAS`] σ. Without it an outline
//! could lie flat along one edge at no cost. What other parts cover neither rewards nor charges
//! the part (the union's silhouette is compared), so a limb does not balloon into the body. A
//! figure that fills the part's reach, or on a photo is larger than the part may grow, is dropped
//! ([`super::FILLED`]): the part is fitted to the edges alone.
//!

use super::evidence::Raster;
use crate::model::dynamics::ModelState;
use crate::model::fem::Tessellation;
use crate::model::forces::image::ImagePotential;
use crate::model::lm::{LmOptions, Mixture};
use crate::model::superquadric::{MIN_EPSILON, SuperquadricParams, spow};
use glam::{DMat3, DQuat, DVec2, DVec3};

/// The edge residual's reach, in units of the potential's σ.
pub const EDGE_REACH: f64 = 3.0;
/// The least semi-axis of a part, in pixels: an ellipse this narrow is 5 pixels wide as a bar of
/// the same second moment (2√3 × 1.5).
pub const MIN_HALF_WIDTH: f64 = 3.0;
/// Unknowns of the global stage: centre (2), θ, r1, r3, ε1.
pub(super) const N: usize = 6;

/// A part whose projected silhouette grows past this many times its placed area is stopped: the
/// image gave it nothing to stop at (a balloon in a region that looks like its inside).
pub const MAX_GROWTH: f64 = 4.0;

/// A superellipse in pixel coordinates (column, row): the projected outline of a part.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct Outline {
    /// Centre.
    pub c: DVec2,
    /// The model z axis' turn from the columns' direction (towards the rows').
    pub theta: f64,
    /// Semi-axes along the model x and z axes.
    pub r: [f64; 2],
    /// The squareness ε1.
    pub eps: f64,
}

impl Outline {
    /// The model x and z axes in pixel coordinates.
    pub(super) fn axes(&self) -> (DVec2, DVec2) {
        let (s, c) = self.theta.sin_cos();
        (DVec2::new(s, -c), DVec2::new(c, s))
    }

    /// The point at parameter η.
    pub(crate) fn point(&self, eta: f64) -> DVec2 {
        let (ex, ez) = self.axes();
        let (s, c) = eta.sin_cos();
        self.c + self.r[0] * spow(c, self.eps) * ex + self.r[1] * spow(s, self.eps) * ez
    }

    /// The point at η and its derivatives over (cx, cy, θ, r1, r3, ε1).
    pub(super) fn point_jacobian(&self, eta: f64) -> (DVec2, [DVec2; N]) {
        let (ex, ez) = self.axes();
        let (s, c) = eta.sin_cos();
        let (xh, zh) = (spow(c, self.eps), spow(s, self.eps));
        let ln = |v: f64| if v == 0.0 { 0.0 } else { v.abs().ln() };
        let [r1, r3] = self.r;
        let p = self.c + r1 * xh * ex + r3 * zh * ez;
        (
            p,
            [
                DVec2::X,
                DVec2::Y,
                r1 * xh * ez - r3 * zh * ex,
                xh * ex,
                zh * ez,
                r1 * xh * ln(c) * ex + r3 * zh * ln(s) * ez,
            ],
        )
    }

    /// The signed radial distance of pixel `q` from the outline (positive outside: |q − c| times
    /// 1 − F^(−ε/2), F the superellipse's inside–outside function) and its derivatives over
    /// (cx, cy, θ, r1, r3, ε1); `None` at the centre.
    pub(crate) fn radial(&self, q: DVec2) -> Option<(f64, [f64; N])> {
        let (ex, ez) = self.axes();
        let l = q - self.c;
        let rho = l.length();
        if !(rho > 1e-9) {
            return None;
        }
        let (x, z) = (l.dot(ex), l.dot(ez));
        let [r1, r3] = self.r;
        let e = self.eps;
        let p = 2.0 / e;
        let term = |v: f64, r: f64| {
            let a = (v / r).abs().powf(p);
            let ln = if v == 0.0 { 0.0 } else { (v / r).abs().ln() };
            let dv = if v == 0.0 { 0.0 } else { p * a / v };
            (a, dv, -p * a / r, -p / e * a * ln)
        };
        let (a, da_x, da_r1, da_e) = term(x, r1);
        let (b, db_z, db_r3, db_e) = term(z, r3);
        let f = a + b;
        if !(f > 0.0) {
            return None;
        }
        let s = f.powf(-e / 2.0);
        // ∂F over the unknowns, through x and z where they move them.
        let dx = [-ex.x, -ex.y, z, 0.0, 0.0, 0.0];
        let dz = [-ez.x, -ez.y, -x, 0.0, 0.0, 0.0];
        let mut df: [f64; N] = std::array::from_fn(|k| da_x * dx[k] + db_z * dz[k]);
        df[3] += da_r1;
        df[4] += db_r3;
        df[5] += da_e + db_e;
        let drho = [-l.x / rho, -l.y / rho, 0.0, 0.0, 0.0, 0.0];
        let grad = std::array::from_fn(|k| {
            let mut dln_s = -e / 2.0 * df[k] / f;
            if k == 5 {
                dln_s -= 0.5 * f.ln();
            }
            drho[k] * (1.0 - s) - rho * s * dln_s
        });
        Some((rho * (1.0 - s), grad))
    }

    /// True when pixel `q` lies inside.
    pub(crate) fn contains(&self, q: DVec2) -> bool {
        let (ex, ez) = self.axes();
        let d = q - self.c;
        let f = |v: f64, r: f64| (v / r).abs().powf(2.0 / self.eps);
        f(d.dot(ex), self.r[0]) + f(d.dot(ez), self.r[1]) <= 1.0
    }

    /// The outline a model state projects to, with its depth semi-axis and ε2.
    pub(crate) fn of_state(pot: &ImagePotential, s: &ModelState) -> (Self, f64, f64) {
        let ez = s.rotation * DVec3::Z;
        let ez_px = DVec2::new(ez.x, -ez.y);
        let theta = ez_px.y.atan2(ez_px.x);
        let axes = s.shape.semi_axes();
        let pitch = pot.pitch();
        let outline = Self {
            c: pot.to_pixel(s.translation.truncate()),
            theta,
            r: [axes.x / pitch, axes.z / pitch],
            eps: s.shape.e1,
        };
        (outline, axes.y, s.shape.e2)
    }

    /// The model state with this outline, `depth` semi-axis and `e2`, at depth `z`.
    pub(super) fn state(
        &self,
        pot: &ImagePotential,
        depth: f64,
        e2: f64,
        z: f64,
        tess: &Tessellation,
    ) -> ModelState {
        let (s, c) = self.theta.sin_cos();
        let ex = DVec3::new(s, c, 0.0);
        let ez = DVec3::new(c, -s, 0.0);
        let rotation = DQuat::from_mat3(&DMat3::from_cols(ex, DVec3::Z, ez)).normalize();
        let pitch = pot.pitch();
        let shape = SuperquadricParams {
            a: 1.0,
            a1: self.r[0] * pitch,
            a2: depth,
            a3: self.r[1] * pitch,
            e1: self.eps,
            e2,
        }
        .normalized();
        ModelState::new(tess, pot.to_plane(self.c).extend(z), rotation, shape)
    }
}

/// Saturated residual c·tanh(v/c) and its derivative over v.
fn saturate(v: f64, cap: f64) -> (f64, f64) {
    let t = (v / cap).tanh();
    (cap * t, 1.0 - t * t)
}

/// What the residuals read: the edge distance, the figure's signed distance, and their reaches.
pub(super) struct Fields<'a> {
    pub(super) edges: Option<&'a Raster>,
    pub(super) figure: Option<&'a Raster>,
    pub(super) edge_cap: f64,
    pub(super) figure_cap: f64,
}

/// Residuals at each outline sample: the edge distance and the figure's signed distance.
pub(super) const KINDS: usize = 2;

impl Fields<'_> {
    /// Residual `kind` of a sample at `p` and its gradient over `p`; `None` without its field.
    /// Kinds: 0 the edge distance, 1 the distance outside the figure (0 inside: a sample deep
    /// in the figure may be where the part joins another), each saturated.
    pub(super) fn at(&self, kind: usize, p: DVec2) -> Option<(f64, DVec2)> {
        let (field, cap) = if kind == 0 {
            (self.edges?, self.edge_cap)
        } else {
            (self.figure?, self.figure_cap)
        };
        let (v, g) = field.sample(p);
        if kind == 1 && v <= 0.0 {
            return Some((0.0, DVec2::ZERO));
        }
        let (r, dr) = saturate(v, cap);
        Some((r, g * dr))
    }
}

/// The area term: pixels about the placed outline, each with the figure's soft membership m, and
/// the residual w (H − m) where H = ½(1 − tanh(d/h)) is the part's own soft silhouette at the
/// pixel's signed distance d from its outline.
#[derive(Clone)]
pub(super) struct Area {
    pub(super) pixels: Vec<DVec2>,
    pub(super) membership: Vec<f64>,
    pub(super) weight: f64,
    pub(super) soft: f64,
    /// How much of each pixel the other parts cover, O in [0, 1].
    pub(super) other: Vec<f64>,
}

impl Area {
    /// The area term's pixels: those within [`MAX_GROWTH`]'s square root times the placed
    /// outline, every `stride`-th row and column so that there are at most [`AREA_PIXELS`]; each
    /// weighs its stride² pixels times [`AREA_SIGMAS`] σ.
    pub(super) fn about(
        placed: &Outline,
        figure: &Raster,
        sigma: f64,
        size: (usize, usize),
    ) -> Self {
        let grown = Outline {
            r: placed.r.map(|r| r * MAX_GROWTH.sqrt()),
            ..*placed
        };
        let reach = grown.r[0].max(grown.r[1]);
        let (lo, hi) = (
            (grown.c - DVec2::splat(reach)).max(DVec2::ZERO),
            (grown.c + DVec2::splat(reach))
                .min(DVec2::new(size.0 as f64 - 1.0, size.1 as f64 - 1.0)),
        );
        let box_area = ((hi - lo).max(DVec2::ZERO) + DVec2::ONE).element_product();
        let stride = (box_area / AREA_PIXELS as f64).sqrt().ceil().max(1.0);
        let mut pixels = Vec::new();
        let mut y = lo.y.ceil();
        while y <= hi.y {
            let mut x = lo.x.ceil();
            while x <= hi.x {
                let q = DVec2::new(x, y);
                if grown.contains(q) {
                    pixels.push(q);
                }
                x += stride;
            }
            y += stride;
        }
        let membership = pixels
            .iter()
            .map(|&q| 0.5 * (1.0 - (figure.sample(q).0 / sigma).tanh()))
            .collect();
        Self {
            other: vec![0.0; pixels.len()],
            pixels,
            membership,
            weight: stride * (AREA_SIGMAS * sigma).sqrt(),
            soft: sigma,
        }
    }

    /// Sets what the outlines `others` cover of each pixel: O = 1 − Π (1 − H_k).
    pub(super) fn cover(&mut self, others: &[Outline]) {
        for (q, o) in self.pixels.iter().zip(&mut self.other) {
            let bare: f64 = others
                .iter()
                .map(|k| {
                    k.radial(*q)
                        .map_or(0.0, |(d, _)| 0.5 * (1.0 - (d / self.soft).tanh()))
                })
                .map(|h| 1.0 - h)
                .product();
            *o = 1.0 - bare;
        }
    }

    /// Pixel `i`'s residual from its signed distance `d`, and the residual's derivative over `d`:
    /// the union's silhouette 1 − (1 − H)(1 − O) against the membership m, so that where another
    /// part covers the pixel this part's silhouette neither gains nor loses.
    pub(super) fn residual(&self, i: usize, d: f64) -> (f64, f64) {
        let t = (d / self.soft).tanh();
        let (h, o) = (0.5 * (1.0 - t), self.other[i]);
        (
            self.weight * ((1.0 - o) * h + o - self.membership[i]),
            -self.weight * (1.0 - o) * 0.5 * (1.0 - t * t) / self.soft,
        )
    }
}

/// The area term's weight per pixel, in units of the potential's σ (pixels): the area term and
/// the outline's residuals balance where the outline is this many σ off its figure. Swept over
/// 1, 2, 4 and 8 on the doll, the coins and the coffee photo (docs/results.md): 4 has the best
/// least IoU over them.
pub const AREA_SIGMAS: f64 = 4.0;

/// The most pixels the area term reads.
pub const AREA_PIXELS: usize = 6000;

/// Settings the engine runs each stage with: no outlier model (the residuals saturate instead).
pub(super) fn engine_options() -> LmOptions {
    LmOptions {
        mixture: Mixture {
            outlier_ratio: 0.0,
            outlier_density: 0.0,
            sigma2_floor: 0.0,
        },
        max_rounds: 4,
        steps_per_round: 100,
        tolerance: 1e-7,
        metric: crate::model::lm::Metric::Radial,
        max_semi_axis: f64::INFINITY,
        min_epsilon: MIN_EPSILON,
        hold_exponents: false,
        own_sigma2: false,
    }
}
