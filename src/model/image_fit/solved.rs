//! Image fits solved for their rest state (beyond the paper): the part's projected outline fitted
//! by least squares, the way range fits are, so that a fit ends at a stationary point of a
//! bounded energy.
//!
//! **The outline.** Seen along its y axis (the view), a superquadric's occluding outline is its
//! x–z section, the superellipse |x/a1|^(2/ε1) + |z/a3|^(2/ε1) = 1 (scaled by a); ε2 and the depth
//! are not observed. [`Outline`] is that superellipse in pixel coordinates: centre, the turn θ of
//! its z axis from the image's columns, the semi-axes r1 (model x) and r3 (model z), and ε1.
//!
//! **Two residuals at each outline sample**, each weighted by the square root of the share of
//! the placed outline's length it stands for (the energy is a mean along the outline, which a
//! shrinking outline cannot lower by itself):
//! - the edge residual: the distance to the nearest image edge ([`evidence::edge_distance`]),
//!   saturated at [`EDGE_REACH`] σ as c·tanh(d/c): an edge farther than the potential reaches does
//!   not pull (chamfer matching);
//! - the region residual: the distance outside the part's figure ([`evidence::figure_distance`]:
//!   what the placement lies on, decided by what encloses what), saturated at the placed minor
//!   semi-axis; 0 inside, where a sample may be where the part joins another (a limb's end in
//!   the body).
//!
//! **The area term** ([`Area`]): at pixels within the part's reach, its soft silhouette against
//! the figure's soft membership, each pixel weighing [`AREA_SIGMAS`] σ. Without it an outline
//! could lie flat along one edge at no cost. What other parts cover neither rewards nor charges
//! the part (the union's silhouette is compared), so a limb does not balloon into the body. A
//! figure that fills the part's reach, or on a photo is larger than the part may grow, is dropped
//! ([`FILLED`]): the part is fitted to the edges alone.
//!
//! **The global stage** solves the six unknowns (centre, θ, r1, r3, ε1) with the one
//! Levenberg–Marquardt engine ([`crate::model::lm`]) on a fixed energy. Parts on one image are
//! solved in sweeps, each with the others as they are, until a sweep moves no part by more than
//! [`REST_PX`]. Bounds keep what the image can show: no semi-axis under [`MIN_HALF_WIDTH`]
//! pixels or σ, none past √[`MAX_GROWTH`] times the placed major one (the area at most
//! [`MAX_GROWTH`] times), ε1 in [0.1, 2], the centre on the image.
//!
//! **The local stage** is a closed contour on that outline with one radial displacement δ_j per
//! node ([`SNAKE_NODES`] nodes, even in the outline's parameter), the same residuals at the
//! displaced nodes and the area term, and a tension Σ ℓ²(δ_{j+1} − δ_j)²/Δs_j with
//! ℓ = [`TENSION_SIGMAS`] σ, so that it follows the image's outline at the scale the potential
//! resolves. Its energy is bounded below, and it is solved by the same engine to rest; no node
//! comes nearer the centre than twice the least semi-axis. The displacement is lifted onto the
//! membrane: a node whose projection lies a fraction t of the way from the centre to the outline,
//! along a ray, moves by t δ along that ray (interpolated between contour nodes).
//!
//! [`MAX_GROWTH`]: super::MAX_GROWTH

use super::super::dynamics::ModelState;
use super::super::fem::Tessellation;
use super::super::forces::image::ImagePotential;
use super::super::lm::{LmOptions, Mixture, Problem, solve_em};
use super::super::superquadric::{MAX_EPSILON, MIN_EPSILON, SuperquadricParams, spow};
use super::MAX_GROWTH;
use super::evidence::{self, Raster};
use glam::{DMat3, DQuat, DVec2, DVec3};

/// The edge residual's reach, in units of the potential's σ.
pub const EDGE_REACH: f64 = 3.0;
/// The least semi-axis of a part, in pixels: an ellipse this narrow is 5 pixels wide as a bar of
/// the same second moment (2√3 × 1.5).
pub const MIN_HALF_WIDTH: f64 = 3.0;
/// A sweep over the parts that moves no part's outline by more than this many pixels ends the
/// global stage.
pub const REST_PX: f64 = 0.05;
/// Nodes of the local stage's contour.
pub const SNAKE_NODES: usize = 64;
/// The contour's tension length, in units of the potential's σ.
pub const TENSION_SIGMAS: f64 = 2.0;
/// Unknowns of the global stage: centre (2), θ, r1, r3, ε1.
const N: usize = 6;

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
    fn point_jacobian(&self, eta: f64) -> (DVec2, [DVec2; N]) {
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
    fn state(
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

/// The bounds of the global stage's unknowns.
#[derive(Clone, Copy, Debug)]
struct Bounds {
    r: [f64; 2],
    eps: [f64; 2],
    c_max: DVec2,
}

/// Saturated residual c·tanh(v/c) and its derivative over v.
fn saturate(v: f64, cap: f64) -> (f64, f64) {
    let t = (v / cap).tanh();
    (cap * t, 1.0 - t * t)
}

/// What the residuals read: the edge distance, the figure's signed distance, and their reaches.
pub(super) struct Fields<'a> {
    edges: Option<&'a Raster>,
    figure: Option<&'a Raster>,
    edge_cap: f64,
    figure_cap: f64,
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
    fn about(placed: &Outline, figure: &Raster, sigma: f64, size: (usize, usize)) -> Self {
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
    fn cover(&mut self, others: &[Outline]) {
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

/// A figure covering more than this share of the pixels a part can reach is no figure of the
/// part: it fills its reach, so it cannot tell where the part ends (the threshold joined the
/// object to its surroundings). Nor is, on a photo (not two-tone), a figure larger than the
/// part may grow ([`MAX_GROWTH`] times its placed area). The part is then fitted to the edges
/// alone.
pub const FILLED: f64 = 0.9;

/// The most pixels the area term reads.
pub const AREA_PIXELS: usize = 6000;

/// The global stage's least-squares problem: residuals [`KINDS`] j + k at sample j (see
/// [`Fields::at`]), then one a pixel of the area term.
struct GlobalProblem<'a> {
    fields: &'a Fields<'a>,
    area: Option<&'a Area>,
    etas: Vec<f64>,
    weights: Vec<f64>,
    bounds: Bounds,
    hold_eps: bool,
}

/// Samples even in η and their weights at `o`: the square roots of the shares of the outline's
/// length they stand for, times `length`. The energy is so the mean along the outline, not its
/// integral, which a shrinking outline would lower whatever it lies on.
fn samples(o: &Outline, length: f64) -> (Vec<f64>, Vec<f64>) {
    let perimeter = std::f64::consts::PI * (o.r[0] + o.r[1]);
    let m = ((perimeter / 2.0) as usize).clamp(64, 512);
    let etas: Vec<f64> = (0..m)
        .map(|j| std::f64::consts::TAU * j as f64 / m as f64)
        .collect();
    let p: Vec<DVec2> = etas.iter().map(|&e| o.point(e)).collect();
    let ds: Vec<f64> = (0..m)
        .map(|j| 0.5 * p[(j + m - 1) % m].distance(p[(j + 1) % m]))
        .collect();
    let total: f64 = ds.iter().sum::<f64>().max(f64::MIN_POSITIVE);
    let weights = ds.iter().map(|d| (d / total * length).sqrt()).collect();
    (etas, weights)
}

impl Problem<N> for GlobalProblem<'_> {
    type Model = Outline;
    type Foot = ();

    fn len(&self) -> usize {
        KINDS * self.etas.len() + self.area.map_or(0, |a| a.pixels.len())
    }

    fn evaluate(&self, model: &Outline, _: &[()]) -> (Vec<f64>, Vec<()>) {
        let samples = KINDS * self.etas.len();
        let e = (0..self.len())
            .map(|i| {
                if let (Some(area), Some(k)) = (self.area, i.checked_sub(samples)) {
                    return model
                        .radial(area.pixels[k])
                        .map_or(0.0, |(d, _)| area.residual(k, d).0);
                }
                let (j, kind) = (i / KINDS, i % KINDS);
                let p = model.point(self.etas[j]);
                self.fields
                    .at(kind, p)
                    .map_or(0.0, |(r, _)| self.weights[j] * r)
            })
            .collect();
        (e, Vec::new())
    }

    fn gradient(&self, model: &Outline, i: usize, _: Option<&()>) -> Option<(f64, [f64; N])> {
        let samples = KINDS * self.etas.len();
        if let (Some(area), Some(k)) = (self.area, i.checked_sub(samples)) {
            let (d, dd) = model.radial(area.pixels[k])?;
            let (r, dr) = area.residual(k, d);
            return Some((r, dd.map(|g| dr * g)));
        }
        let (j, kind) = (i / KINDS, i % KINDS);
        let (p, jac) = model.point_jacobian(self.etas[j]);
        let (r, g) = self.fields.at(kind, p)?;
        let w = self.weights[j];
        Some((w * r, jac.map(|d| w * g.dot(d))))
    }

    fn moved(&self, m: &Outline, d: &[f64; N]) -> Outline {
        let b = &self.bounds;
        Outline {
            c: (m.c + DVec2::new(d[0], d[1])).clamp(DVec2::ZERO, b.c_max),
            theta: m.theta + d[2],
            r: [
                (m.r[0] + d[3]).clamp(b.r[0], b.r[1]),
                (m.r[1] + d[4]).clamp(b.r[0], b.r[1]),
            ],
            eps: if self.hold_eps {
                m.eps
            } else {
                (m.eps + d[5]).clamp(b.eps[0], b.eps[1])
            },
        }
    }

    fn on_bound(&self, m: &Outline, k: usize) -> (bool, bool) {
        let b = &self.bounds;
        let at = |v: f64, [lo, hi]: [f64; 2]| (v <= lo, v >= hi);
        match k {
            0 => (m.c.x <= 0.0, m.c.x >= b.c_max.x),
            1 => (m.c.y <= 0.0, m.c.y >= b.c_max.y),
            3 => at(m.r[0], b.r),
            4 => at(m.r[1], b.r),
            5 => at(m.eps, b.eps),
            _ => (false, false),
        }
    }

    fn held(&self, k: usize) -> bool {
        k == 5 && self.hold_eps
    }
}

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

/// A part's solved fit: the state, the engine's steps in the global and the local stage, and
/// whether both ended at rest.
pub(crate) struct Solved {
    pub state: ModelState,
    pub global_steps: usize,
    pub local_steps: usize,
    pub converged: bool,
}

/// What one part's solve reads, fixed from its placement.
pub(super) struct Part<'a> {
    placed: Outline,
    depth: f64,
    e2: f64,
    z: f64,
    /// The figure's signed distance and the area term's pixels, when the part has a figure.
    figure: Option<(Raster, Area)>,
    edges: Option<&'a Raster>,
    bounds: Bounds,
    sigma: f64,
}

impl<'a> Part<'a> {
    pub(super) fn new(
        pot: &ImagePotential,
        edges: Option<&'a Raster>,
        initial: &ModelState,
    ) -> Self {
        let (placed, depth, e2) = Outline::of_state(pot, initial);
        let sigma = pot.sigma();
        let least = MIN_HALF_WIDTH.max(sigma);
        let most = MAX_GROWTH.sqrt() * placed.r[0].max(placed.r[1]);
        let grown = Outline {
            r: placed.r.map(|r| r * std::f64::consts::SQRT_2),
            ..placed
        };
        let figure = evidence::figure_distance(
            pot,
            |q| placed.contains(q),
            |q| grown.contains(q) && !placed.contains(q),
        )
        .map(|f| {
            let a = Area::about(&placed, &f, sigma, (pot.width(), pot.height()));
            (f, a)
        })
        .filter(|(f, a)| {
            // A figure that fills the part's whole reach cannot tell where it ends; on a photo,
            // neither can one larger than the part may grow.
            let n = a.membership.len().max(1) as f64;
            let placed_area = std::f64::consts::PI * placed.r[0] * placed.r[1];
            a.membership.iter().sum::<f64>() / n < FILLED
                && (pot.two_tone().is_some()
                    || (f.inside_count() as f64) <= MAX_GROWTH * placed_area)
        });
        Self {
            placed,
            depth,
            e2,
            z: initial.translation.z,
            figure,
            edges,
            bounds: Bounds {
                r: [least, most.max(least)],
                eps: [MIN_EPSILON, MAX_EPSILON],
                c_max: DVec2::new(pot.width() as f64 - 1.0, pot.height() as f64 - 1.0),
            },
            sigma,
        }
    }

    pub(super) fn fields(&self) -> Fields<'_> {
        let minor = self.placed.r[0].min(self.placed.r[1]);
        Fields {
            edges: self.edges,
            figure: self.figure.as_ref().map(|(f, _)| f),
            edge_cap: EDGE_REACH * self.sigma,
            figure_cap: minor.max(EDGE_REACH * self.sigma),
        }
    }

    /// The start within the bounds.
    fn start(&self) -> Outline {
        let b = &self.bounds;
        Outline {
            r: self.placed.r.map(|r| r.clamp(b.r[0], b.r[1])),
            eps: self.placed.eps.clamp(b.eps[0], b.eps[1]),
            ..self.placed
        }
    }

    /// The area term with the other parts' outlines `others` covering what they cover.
    pub(super) fn area(&self, others: &[Outline]) -> Option<Area> {
        let mut area = self.figure.as_ref()?.1.clone();
        area.cover(others);
        Some(area)
    }

    /// The global stage's problem over `fields` and `area`: the samples and their weights are the
    /// placed outline's, so that the energy is one fixed function of the unknowns.
    fn problem<'b>(
        &self,
        fields: &'b Fields<'b>,
        area: Option<&'b Area>,
        hold_eps: bool,
    ) -> GlobalProblem<'b> {
        let length = std::f64::consts::PI * (self.placed.r[0] + self.placed.r[1]);
        let (etas, weights) = samples(&self.placed, length);
        GlobalProblem {
            fields,
            area,
            etas,
            weights,
            bounds: self.bounds,
            hold_eps,
        }
    }

    /// The global stage from `o` (see the module docs): the outline at rest, the engine's steps,
    /// whether it came to rest, and how far (pixels) it moved.
    fn solve_global(
        &self,
        o: Outline,
        area: Option<&Area>,
        hold_eps: bool,
    ) -> (Outline, usize, bool, f64) {
        let fields = self.fields();
        let problem = self.problem(&fields, area, hold_eps);
        let fit = solve_em(&problem, &o, 0.0, false, &engine_options());
        let moved = problem
            .etas
            .iter()
            .map(|&e| fit.model.point(e).distance(o.point(e)))
            .fold(0.0, f64::max);
        (fit.model, fit.iterations as usize, fit.converged, moved)
    }
}

/// Most sweeps over the parts (the doll's 11 settle in 8).
const MAX_SWEEPS: usize = 20;

/// Solves every part from `initial` (see the module docs): sweeps over the parts in order, each
/// part's global stage solved with the others as they are (what another part covers neither
/// rewards nor costs it), until a sweep moves no part by [`REST_PX`]; then with `local` each
/// part's contour. `hold_eps` holds ε1.
pub(crate) fn solve_parts(
    pot: &ImagePotential,
    edges: Option<&Raster>,
    tess: &Tessellation,
    initial: &[ModelState],
    local: bool,
    hold_eps: bool,
) -> Vec<Solved> {
    let parts: Vec<Part> = initial.iter().map(|s| Part::new(pot, edges, s)).collect();
    let mut outlines: Vec<Outline> = parts.iter().map(Part::start).collect();
    let mut steps = vec![0; parts.len()];
    let mut rested = vec![false; parts.len()];
    for _ in 0..MAX_SWEEPS {
        let mut still = true;
        for (k, part) in parts.iter().enumerate() {
            let others: Vec<Outline> = (0..parts.len())
                .filter(|&j| j != k)
                .map(|j| outlines[j])
                .collect();
            let area = part.area(&others);
            let (o, n, at_rest, moved) = part.solve_global(outlines[k], area.as_ref(), hold_eps);
            outlines[k] = o;
            steps[k] += n;
            rested[k] = at_rest;
            still &= moved < REST_PX;
        }
        if still {
            break;
        }
        rested.iter_mut().for_each(|r| *r = false);
    }
    let opts = engine_options();
    parts
        .iter()
        .enumerate()
        .map(|(k, part)| {
            let o = outlines[k];
            let mut state = o.state(pot, part.depth, part.e2, part.z, tess);
            let (mut local_steps, mut converged) = (0, rested[k]);
            if local {
                let others: Vec<Outline> = (0..parts.len())
                    .filter(|&j| j != k)
                    .map(|j| outlines[j])
                    .collect();
                let area = part.area(&others);
                let snake = super::contour::solve_contour(
                    &part.fields(),
                    area.as_ref(),
                    &o,
                    part.sigma,
                    &opts,
                );
                local_steps = snake.steps;
                converged &= snake.converged;
                super::contour::lift(&snake, pot.pitch(), tess, &mut state);
            }
            Solved {
                state,
                global_steps: steps[k],
                local_steps,
                converged,
            }
        })
        .collect()
}

#[cfg(test)]
pub(super) mod tests;
