//! The local stage of a solved image fit: a closed contour on the outline the global stage
//! ([`super::solved`]) fitted, with one radial displacement per node, its tension, and its lift
//! onto the membrane.
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

use super::outline::{Area, Fields, KINDS, MIN_HALF_WIDTH, Outline};
use crate::model::dynamics::ModelState;
use crate::model::fem::Tessellation;
use crate::model::lm::{LmOptions, Problem, solve_em};
use crate::model::superquadric::spow;
use glam::{DQuat, DVec2, DVec3};
use std::f64::consts::TAU;

/// Nodes of the local stage's contour.
pub const SNAKE_NODES: usize = 64;
/// The contour's tension length, in units of the potential's σ.
pub const TENSION_SIGMAS: f64 = 2.0;
/// The contour's unknowns: a radial displacement (pixels) per node.
const M: usize = SNAKE_NODES;

/// The contour at rest.
pub(crate) struct Contour {
    /// Each node's polar angle in the model's x–z plane, rising from 0 below 2π.
    angle: [f64; M],
    /// Each node's distance from the centre on the outline (pixels).
    radius: [f64; M],
    /// Each node's displacement along its ray (pixels).
    pub delta: [f64; M],
    /// Engine steps taken.
    pub steps: usize,
    /// True when the engine came to rest.
    pub converged: bool,
}

/// Where an area pixel lies from the contour: the two nodes about its ray and its share of the
/// way from the first to the second, its distance from the centre, and the outline's there.
#[derive(Clone, Copy)]
struct OnRay {
    nodes: (usize, usize),
    t: f64,
    rho: f64,
    radius: f64,
}

/// The contour's least-squares problem: residuals [`KINDS`] j + k at node j (see
/// [`Fields::at`]), then the tension between node j and j + 1 at [`KINDS`] M + j, then one an
/// area pixel.
struct ContourProblem<'a> {
    fields: &'a Fields<'a>,
    area: Option<(&'a Area, Vec<OnRay>)>,
    centre: DVec2,
    ray: [DVec2; M],
    radius: [f64; M],
    weight: [f64; M],
    tension: [f64; M],
    least: f64,
}

impl ContourProblem<'_> {
    fn node(&self, delta: &[f64; M], j: usize) -> DVec2 {
        self.centre + self.ray[j] * (self.radius[j] + delta[j])
    }

    fn bounds(&self, j: usize) -> (f64, f64) {
        (-(self.radius[j] - self.least).max(0.0), self.radius[j])
    }

    /// Area pixel `i`'s residual and its two nonzero derivatives (over its ray's two nodes).
    fn area_residual(&self, d: &[f64; M], i: usize) -> Option<(f64, [(usize, f64); 2])> {
        let (area, rays) = self.area.as_ref()?;
        let ray = rays[i];
        let (j, k) = ray.nodes;
        let edge = ray.radius + (1.0 - ray.t) * d[j] + ray.t * d[k];
        let (r, dr) = area.residual(i, ray.rho - edge);
        Some((r, [(j, -dr * (1.0 - ray.t)), (k, -dr * ray.t)]))
    }
}

impl Problem<M> for ContourProblem<'_> {
    type Model = [f64; M];
    type Foot = ();

    fn len(&self) -> usize {
        (KINDS + 1) * M + self.area.as_ref().map_or(0, |(a, _)| a.pixels.len())
    }

    fn evaluate(&self, d: &[f64; M], _: &[()]) -> (Vec<f64>, Vec<()>) {
        let e = (0..self.len())
            .map(|i| {
                if i >= (KINDS + 1) * M {
                    self.area_residual(d, i - (KINDS + 1) * M)
                        .map_or(0.0, |(r, _)| r)
                } else if i < KINDS * M {
                    let j = i / KINDS;
                    self.fields
                        .at(i % KINDS, self.node(d, j))
                        .map_or(0.0, |(r, _)| self.weight[j] * r)
                } else {
                    let j = i - KINDS * M;
                    self.tension[j] * (d[(j + 1) % M] - d[j])
                }
            })
            .collect();
        (e, Vec::new())
    }

    fn gradient(&self, d: &[f64; M], i: usize, _: Option<&()>) -> Option<(f64, [f64; M])> {
        let mut g = [0.0; M];
        if i >= (KINDS + 1) * M {
            let (r, parts) = self.area_residual(d, i - (KINDS + 1) * M)?;
            for (j, v) in parts {
                g[j] += v;
            }
            Some((r, g))
        } else if i < KINDS * M {
            let j = i / KINDS;
            let (r, grad) = self.fields.at(i % KINDS, self.node(d, j))?;
            g[j] = self.weight[j] * grad.dot(self.ray[j]);
            Some((self.weight[j] * r, g))
        } else {
            let j = i - KINDS * M;
            let k = (j + 1) % M;
            g[k] = self.tension[j];
            g[j] = -self.tension[j];
            Some((self.tension[j] * (d[k] - d[j]), g))
        }
    }

    fn moved(&self, d: &[f64; M], step: &[f64; M]) -> [f64; M] {
        std::array::from_fn(|j| {
            let (lo, hi) = self.bounds(j);
            (d[j] + step[j]).clamp(lo, hi)
        })
    }

    fn on_bound(&self, d: &[f64; M], j: usize) -> (bool, bool) {
        let (lo, hi) = self.bounds(j);
        (d[j] <= lo, d[j] >= hi)
    }

    fn held(&self, _: usize) -> bool {
        false
    }
}

/// Solves the contour on outline `o` (see the module docs).
pub(crate) fn solve_contour(
    fields: &Fields,
    area: Option<&Area>,
    o: &Outline,
    sigma: f64,
    opts: &LmOptions,
) -> Contour {
    let (problem, angle) = contour_problem(fields, area, o, sigma);
    let fit = solve_em(&problem, &[0.0; M], 0.0, false, opts);
    Contour {
        angle,
        radius: problem.radius,
        delta: fit.model,
        steps: fit.iterations as usize,
        converged: fit.converged,
    }
}

/// The contour's problem on outline `o`, and its nodes' polar angles.
fn contour_problem<'a>(
    fields: &'a Fields,
    area: Option<&'a Area>,
    o: &Outline,
    sigma: f64,
) -> (ContourProblem<'a>, [f64; M]) {
    let etas: [f64; M] = std::array::from_fn(|j| TAU * j as f64 / M as f64);
    let points = etas.map(|e| o.point(e));
    let radius = points.map(|p| p.distance(o.c).max(1e-9));
    let ray = std::array::from_fn(|j| (points[j] - o.c) / radius[j]);
    let gap = |j: usize| points[j].distance(points[(j + 1) % M]).max(1e-9);
    let length = TENSION_SIGMAS * sigma;
    let angle = etas.map(|e| {
        let (s, c) = e.sin_cos();
        let (x, z) = (o.r[0] * spow(c, o.eps), o.r[1] * spow(s, o.eps));
        z.atan2(x).rem_euclid(TAU)
    });
    let (ex, ez) = o.axes();
    let area = area.map(|a| {
        let rays = a
            .pixels
            .iter()
            .map(|&q| {
                let l = q - o.c;
                let (nodes, t) = bracket(&angle, l.dot(ez).atan2(l.dot(ex)));
                OnRay {
                    nodes,
                    t,
                    rho: l.length(),
                    radius: (1.0 - t) * radius[nodes.0] + t * radius[nodes.1],
                }
            })
            .collect();
        (a, rays)
    });
    let problem = ContourProblem {
        fields,
        area,
        centre: o.c,
        ray,
        radius,
        weight: std::array::from_fn(|j| (0.5 * (gap(j) + gap((j + M - 1) % M))).sqrt()),
        tension: std::array::from_fn(|j| length / gap(j).sqrt()),
        // A node stays at least two least semi-axes from the centre (or where the outline has it),
        // so that the contour cannot thin a part below the global stage's bound.
        least: 2.0 * MIN_HALF_WIDTH.max(sigma),
    };
    (problem, angle)
}

impl Contour {
    /// The displacement and the outline's radius at polar angle `phi`, linear between nodes.
    fn at(&self, phi: f64) -> (f64, f64) {
        let ((j, k), t) = bracket(&self.angle, phi);
        (
            self.delta[j] + t * (self.delta[k] - self.delta[j]),
            self.radius[j] + t * (self.radius[k] - self.radius[j]),
        )
    }
}

/// The two nodes whose polar angles (`angle`, rising from 0 below 2π) bracket `phi`, and its
/// share of the way from the first to the second.
fn bracket(angle: &[f64; M], phi: f64) -> ((usize, usize), f64) {
    let phi = phi.rem_euclid(TAU);
    let j = angle.partition_point(|&a| a <= phi).max(1) - 1;
    let k = (j + 1) % M;
    let span = (angle[k] - angle[j]).rem_euclid(TAU).max(1e-12);
    let t = ((phi - angle[j]).rem_euclid(TAU) / span).clamp(0.0, 1.0);
    ((j, k), t)
}

/// Lifts `contour` onto the membrane of `state` (`pitch` plane units a pixel): a node projected
/// a fraction t of the way out to the outline moves t δ along its ray.
pub(crate) fn lift(contour: &Contour, pitch: f64, tess: &Tessellation, state: &mut ModelState) {
    let mut model = ModelState {
        translation: DVec3::ZERO,
        rotation: DQuat::IDENTITY,
        displacement: vec![DVec3::ZERO; tess.node_count()],
        ..state.clone()
    };
    let mut x = Vec::new();
    model.node_positions(tess, &mut x);
    model.displacement.clear();
    for s in &x {
        let phi = s.z.atan2(s.x);
        let (delta, radius) = contour.at(phi);
        let rho = DVec2::new(s.x, s.z).length() / pitch;
        let t = (rho / radius).min(1.0);
        let (sp, cp) = phi.sin_cos();
        model
            .displacement
            .push(DVec3::new(cp, 0.0, sp) * (t * delta * pitch));
    }
    state.displacement = model.displacement;
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::image_fit::solved::tests::{blob, part_on};

    #[test]
    fn the_contours_gradient_is_the_central_difference_and_its_energy_falls() {
        let (pot, truth) = blob();
        let edges = crate::model::image_fit::evidence::edge_distance(&pot);
        let part = part_on(&pot, edges.as_ref());
        let fields = part.fields();
        let area = part.area(&[]);
        // The contour on an outline a little inside the truth: it has somewhere to go.
        let o = Outline {
            r: truth.r.map(|r| r - 3.0),
            ..truth
        };
        let (problem, _) = contour_problem(&fields, area.as_ref(), &o, pot.sigma());
        let d: [f64; M] = std::array::from_fn(|j| 0.7 * ((j as f64) * 0.4).sin());
        let (e0, _) = problem.evaluate(&d, &[]);
        let h = 1e-6;
        // Every kind of residual: edge, region, tension, area.
        let mut checked = 0;
        for i in (0..problem.len()).step_by(7) {
            let Some((r, g)) = problem.gradient(&d, i, None) else {
                continue;
            };
            assert!((r - e0[i]).abs() < 1e-12, "residual {i}");
            for k in [i / KINDS % M, (i / KINDS + 1) % M, 3] {
                let mut plus = d;
                let mut minus = d;
                plus[k] += h;
                minus[k] -= h;
                let fd = (problem.evaluate(&plus, &[]).0[i] - problem.evaluate(&minus, &[]).0[i])
                    / (2.0 * h);
                assert!(
                    (fd - g[k]).abs() < 1e-5 * (1.0 + g[k].abs()),
                    "residual {i} node {k}: {fd} vs {}",
                    g[k]
                );
            }
            checked += usize::from(g.iter().any(|g| g.abs() > 1e-3));
        }
        assert!(checked > 20, "{checked} residuals with a slope");
        let cost = |d: &[f64; M]| {
            problem
                .evaluate(d, &[])
                .0
                .iter()
                .map(|e| e * e)
                .sum::<f64>()
        };
        let fit = solve_contour(
            &fields,
            area.as_ref(),
            &o,
            pot.sigma(),
            &crate::model::image_fit::outline::engine_options(),
        );
        assert!(fit.converged && fit.delta.iter().all(|x| x.is_finite()));
        assert!(
            cost(&fit.delta) < 0.5 * cost(&[0.0; M]),
            "{} → {}",
            cost(&[0.0; M]),
            cost(&fit.delta)
        );
        // The contour moves out onto the truth, about 3 px.
        let mean = fit.delta.iter().sum::<f64>() / M as f64;
        assert!((mean - 3.0).abs() < 1.0, "mean displacement {mean}");
    }
}
