//! The global stage of a solved image fit (beyond the paper): each part's projected outline
//! ([`Outline`]) solved by least squares, the way range fits are, so that a fit ends at a
//! stationary point of a bounded energy.
//!
//! **The global stage** solves the six unknowns (centre, θ, r1, r3, ε1) with the one
//! Levenberg–Marquardt engine ([`crate::model::lm`]) on a fixed energy. Parts on one image are
//! solved in sweeps, each with the others as they are, until a sweep moves no part by more than
//! [`REST_PX`]. Bounds keep what the image can show: no semi-axis under [`MIN_HALF_WIDTH`]
//! pixels or σ, none past √[`MAX_GROWTH`] times the placed major one (the area at most
//! [`MAX_GROWTH`] times), ε1 in [0.1, 2], the centre on the image.
//!

use super::evidence::Raster;
use super::figure;
use super::outline::{
    Area, EDGE_REACH, Fields, KINDS, MAX_GROWTH, MIN_HALF_WIDTH, N, Outline, engine_options,
};
use crate::model::dynamics::ModelState;
use crate::model::forces::image::ImagePotential;
use crate::model::lm::{Problem, solve_em};
use crate::model::superquadric::{MAX_EPSILON, MIN_EPSILON};
use glam::DVec2;

/// A sweep over the parts that moves no part's outline by more than this many pixels ends the
/// global stage.
pub const REST_PX: f64 = 0.05;
/// The bounds of the global stage's unknowns.
#[derive(Clone, Copy, Debug)]
struct Bounds {
    r: [f64; 2],
    eps: [f64; 2],
    c_max: DVec2,
}

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
        relief: &[f64],
        initial: &ModelState,
    ) -> Self {
        let (placed, depth, e2) = Outline::of_state(pot, initial);
        let sigma = pot.sigma();
        let least = MIN_HALF_WIDTH.max(sigma);
        let most = MAX_GROWTH.sqrt() * placed.r[0].max(placed.r[1]);
        let figure = figure::part_figure(pot, relief, &placed);
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

    /// The model state whose projected outline is `o`, with the depth and ε2 as placed.
    pub(super) fn state(
        &self,
        o: &Outline,
        pot: &ImagePotential,
        tess: &crate::model::fem::Tessellation,
    ) -> ModelState {
        o.state(pot, self.depth, self.e2, self.z, tess)
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

/// Solves every part's global stage from where it was placed (see the module docs): sweeps
/// over the parts in order, each solved with the others as they are (what another part covers
/// neither rewards nor costs it), until a sweep moves no part by [`REST_PX`]. `hold_eps` holds
/// ε1. Returns each part's outline, the engine's steps, and whether it ended at rest.
pub(super) fn sweep(parts: &[Part], hold_eps: bool) -> Vec<(Outline, usize, bool)> {
    let mut outlines: Vec<Outline> = parts.iter().map(Part::start).collect();
    let mut steps = vec![0; parts.len()];
    let mut rested = vec![false; parts.len()];
    for _ in 0..MAX_SWEEPS {
        let mut still = true;
        for (k, part) in parts.iter().enumerate() {
            let area = part.area(&others(&outlines, k));
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
    (0..parts.len())
        .map(|k| (outlines[k], steps[k], rested[k]))
        .collect()
}

/// Every outline but the `k`-th.
pub(super) fn others(outlines: &[Outline], k: usize) -> Vec<Outline> {
    (0..outlines.len())
        .filter(|&j| j != k)
        .map(|j| outlines[j])
        .collect()
}

#[cfg(test)]
pub(super) mod tests;
