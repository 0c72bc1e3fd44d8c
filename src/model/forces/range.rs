//! Range-data forces (eq. 22): a spring w (r − x(u_r)) from every data point r to its point of
//! influence u_r on the model's surface. (The paper prints the magnitude β‖r − x‖; the force is the
//! vector.)
//!
//! **Weight.** Each of the m points gets w = β |Ω| / m, where |Ω| is the area of the material
//! domain covered by the elements (≈ 2π²). The springs then act as a force density β per unit
//! material area whatever m is, so the motion does not depend on how many points a scan has.
//!
//! **Points of influence.** [`InfluenceMode::NearestNode`] is the paper's: u_r is the node nearest
//! r, found again every N steps. The paper did that by brute force in O(mn); [`nearest_indices`]
//! buckets the nodes into a uniform grid ([`crate::model::nearest::NodeGrid`], O(n)) and scans the cells
//! around each point, with a k-d tree (kiddo, O(log n) a query) behind it for points far from
//! every node, and gives the same assignment as [`nearest_indices_brute`] (tested);
//! [`RangeForces`] searches its points in a spatial order fixed once ([`QueryOrder`]), which
//! gives the same answers faster.
//! [`InfluenceMode::Migrating`] is the paper's alternative (Fig. 3): each point of influence
//! slides over the surface by the tangential components of its force until they vanish, at the
//! foot of the perpendicular from r; a reassignment then only replaces it when the nearest node
//! is closer. Given the model's continuous surface
//! ([`ModelSurface`], the paper's x(u)), the points slide over it with its own tangents and a
//! whole 2×2 Gauss–Newton move, not over the mesh's triangles, whose chords would bias a fit by
//! up to h²κ/8 ([`RangeForces::migrate`]).
//!
//! **Coverage springs (beyond the paper).** Data-to-model springs leave every part of the model
//! that no data point chose free: fitted from an initial state larger than the data, a part with
//! no data near it (the top of a too-tall tube) stays where it is and the global fit stalls. Each
//! node therefore also gets a weak spring to its nearest data point, of density `coverage` × β per
//! unit material area, acting on the global DOFs only (so it never bends the membrane onto the
//! data). It is the model-to-data half of a symmetric (Chamfer) distance; `coverage = 0` gives the
//! paper's forces exactly. On one-view data the coverage springs also pull the unseen back towards
//! the data, so the fit loop uses them only to place the model and then switches them off.
//!
//! **Outlier-robust weights (beyond the paper).** Every data point pulls with the same strength in
//! the paper, so scattered outliers drag the model off its object. With [`Robust`] set, each
//! point's spring is weighted by its posterior probability p_i of being a surface point, under
//! the mixture EMS uses (Liu et al., CVPR 2022): inliers at a Gaussian distance d_i from their
//! point of influence, N(d; 0, σ² I₃), with prior 1 − w_o, and outliers uniform over the data's
//! bounding box (density 1/V), with prior w_o:
//! p_i = (1 − w_o) N(d_i) / ((1 − w_o) N(d_i) + w_o / V). Each reassignment runs
//! [`EM_ITERATIONS`] rounds of this E-step and the M-step σ² = Σ p_i d_i² / (3 Σ p_i), starting
//! from σ² = mean d²/3 at the first, and floored at ([`SIGMA_FLOOR`] × the bounding-box
//! diagonal)² so that a near-perfect fit does not reject everything. The spring constants become
//! w_i = β |Ω| p_i / Σ p (the total strength stays β |Ω|, scale-free as before), and a coverage
//! spring to a point is weighted by that point's p. Parameters: w_o (`outlier_ratio`; EMS's
//! default is 0.1, 0.2 for its noisy examples); σ is estimated, not set. Measured
//! (`tests/recovery.rs`): 800 surface points plus 200 uniform outliers, global only — mean
//! distance of the inliers to the fit 0.0216 with w_o = 0.2, 0.0221 for the clean cloud, 0.302
//! with the paper's weights.
//!
//! **Point-to-plane springs (beyond the paper).** A data point attached to a node pulls that node
//! onto itself, so a superquadric fitted with nearest-node springs is pinned to the nodes the
//! points chose: between nodes the surface cannot pass through the data, and the global fit is
//! biased by the node spacing. With `plane` set, each spring becomes w ((1 − μ) n nᵀ + μ I)(r − x)
//! with n the surface normal at its point of influence and μ = [`TANGENT_FRACTION`]: it pulls
//! mainly across the surface and lets the surface slide along itself. It acts on the global DOFs
//! only, and adds (1 − μ) w (Lᵀn)(Lᵀn)ᵀ + μ w LᵀL to the global damping block (through
//! `NodalForces::plane_stiffness`), so the global step stays a Gauss–Newton step on this energy.
//! μ > 0 matters: with μ = 0 the model is free to stretch along the data between reattachments
//! (on EMS's noisy clouds it grew without bound); μ = 0.3 fitted all six EMS clouds to rest.
//! Points that migrate on the continuous surface, whose feet slide with it every step, use
//! μ = [`SURFACE_TANGENT_FRACTION`] (0.03), for which the global step is nearly Gauss–Newton on the
//! point-to-surface distance.

use crate::model::dynamics::{ModelSurface, NodalForces};
use crate::model::fem::{ElementPoint, Tessellation};
use crate::model::nearest::{kd_tree, query_nearest};
pub use crate::model::nearest::{nearest_indices, nearest_indices_brute};
use crate::model::simd::with_avx2;
use crate::model::superquadric::Trig;
use glam::DVec3;
use kiddo::ImmutableKdTree;
use rayon::prelude::*;
use std::sync::Arc;

mod migrate;
mod tree;
pub use migrate::PARALLEL_MIGRATION;
use migrate::*;
pub use tree::QueryOrder;
use tree::*;
#[cfg(test)]
mod tests;

/// How each data point's point of influence u_r is chosen.
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub enum InfluenceMode {
    /// The node nearest the data point, refreshed at every reassignment (the paper's experiments).
    #[default]
    NearestNode,
    /// The point migrates over the surface along the tangential force (Fig. 3); `rate` is the
    /// fraction of the Gauss–Newton move in u and v taken per step (0 < rate ≤ 1).
    Migrating {
        /// Step fraction per migration step.
        rate: f64,
    },
}

/// A data point's point of influence: material coordinates and the element it lies in.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Influence {
    /// Material latitude u_r.
    pub u: f64,
    /// Material longitude v_r.
    pub v: f64,
    /// The element and shape functions at (u_r, v_r).
    pub at: ElementPoint,
}

/// Range data attached to one model: the points, their springs and points of influence.
#[derive(Clone, Debug, PartialEq)]
pub struct RangeForces {
    /// Data points r in world space (read with [`Self::points`]; fixed for the forces' life, so
    /// that their query order is computed once).
    points: Vec<DVec3>,
    /// The points in a spatially coherent order, for the nearest-node searches of every
    /// reassignment.
    query_order: QueryOrder,
    /// A k-d tree of the points, for the coverage springs' searches.
    point_tree: PointTree,
    /// Spring stiffness β per unit material area (each point gets β |Ω| / m).
    pub beta: f64,
    /// How points of influence are chosen.
    pub mode: InfluenceMode,
    /// Current point of influence of each data point (empty until the first [`Self::reassign`];
    /// read with [`Self::influence`]).
    influence: Vec<Influence>,
    /// Density of the model-to-data coverage springs, as a fraction of β (see the module docs).
    pub coverage: f64,
    /// Nearest data point of each node, refreshed with the points of influence.
    pub node_targets: Vec<u32>,
    /// Outlier-robust weights (beyond the paper; see the module docs), or `None` for the paper's
    /// equal weights.
    pub robust: Option<Robust>,
    /// Point-to-plane springs on the global DOFs (beyond the paper; see the module docs): each
    /// spring pulls only along the surface normal at its point of influence, and acts on the
    /// global DOFs only. `false` (the default) gives the paper's springs.
    pub plane: bool,
    /// Spread [`Self::migrate`] over the cores (rayon, in runs of [`PARALLEL_MIGRATION`] points;
    /// the same points of influence to the bit). For a fit that runs alone: the fitter sets it
    /// on the chosen fit from its refining stage on, while the other cores have nothing to do. `false`
    /// (the default) migrates on the calling thread.
    pub parallel: bool,
    /// How far each point of influence lies off the mesh's triangles, on the model's continuous
    /// surface ([`ModelSurface`]): x(u_r) − Σ N_k x_k as the last [`Self::migrate`] given that
    /// surface found it. Added to the mesh's point until the next migration (the offset changes
    /// only as slowly as the global shape), so that the springs, their energy and the weights see
    /// the same point. Empty when points of influence lie on the triangles. A reassignment onto a
    /// node sets its entry to zero.
    pub surface_offset: Vec<DVec3>,
    /// The [`Trig`] terms of each point of influence's (u, v) as the last [`Self::migrate`] on the
    /// continuous surface left it, so that the next one evaluates the surface there without a
    /// sine, a cosine or a logarithm. An entry whose (u, v) is no longer its point's is computed
    /// afresh.
    surface_terms: Vec<SurfaceTerms>,
    /// Each point's node while every point of influence sits on a node, as it does after a
    /// nearest-node reassignment: a copy of `influence[i].at.nodes[0]`, 4 bytes a point where an
    /// [`Influence`] is 128, so that [`Self::accumulate`] reads only what nearest-node springs
    /// need. Empty otherwise, and emptied whenever `influence` changes another way.
    on_node: Vec<u32>,
}

/// A point of influence's material coordinates and their [`Trig`] terms.
#[derive(Clone, Copy, Debug, PartialEq)]
struct SurfaceTerms {
    u: f64,
    v: f64,
    trig: Trig,
}

impl SurfaceTerms {
    /// The terms at (u, v).
    fn new(u: f64, v: f64) -> Self {
        Self {
            u,
            v,
            trig: Trig::new(u, v),
        }
    }
}

/// The tangential stiffness of a point-to-plane spring as a fraction μ of its normal stiffness:
/// the spring is w ((1 − μ) n nᵀ + μ I) d. A pure point-to-plane spring (μ = 0) leaves the
/// surface free to slide along itself, and with points attached to nodes a model then stretches
/// away along the data between reattachments; μ keeps the energy bounded.
pub const TANGENT_FRACTION: f64 = 0.3;

/// μ for the data springs of points that migrate on the continuous surface
/// ([`RangeForces::surface_offset`]): their feet slide with the surface every step, so nothing
/// stretches between reattachments, and the tangential stiffness only slows the global
/// Gauss–Newton step down to point-to-point ICP's pace. Measured (`fit --global-only`): the
/// hippo's refinement 2377 → 482 steps, the whole fit 10051 → 3709; EMS's six clouds as close or
/// closer (`partial_3` 0.00028 → 0.00022 of the diagonal) and the ground-truth medians unchanged.
/// With μ = 0 the near-box `partial_3` never came to rest.
pub const SURFACE_TANGENT_FRACTION: f64 = 0.03;

/// The point-to-plane spring force per unit stiffness for offset `d`, unit normal `n` and
/// tangential fraction `mu`: ((1 − μ) n nᵀ + μ I) d.
fn plane_spring(d: DVec3, n: DVec3, mu: f64) -> DVec3 {
    (1.0 - mu) * n.dot(d) * n + mu * d
}

/// Outlier-robust weights of the data springs (beyond the paper; see the module docs): the
/// posterior probability that each point is a surface point rather than an outlier, under a
/// mixture of a Gaussian in the distance to the model and a uniform density over the data's
/// bounding box, as in EMS (Liu et al., CVPR 2022).
#[derive(Clone, Debug, PartialEq)]
pub struct Robust {
    /// Prior fraction of outliers w_o in [0, 1).
    pub outlier_ratio: f64,
    /// Posterior inlier probability p_i of each point (filled at the first reassignment).
    pub inlier: Vec<f64>,
    /// Σ p_i.
    pub inlier_sum: f64,
    /// Variance σ² of the inliers' distance to the model per coordinate (0: not estimated yet).
    pub sigma2: f64,
}

impl Robust {
    /// Robust weights with prior outlier fraction `outlier_ratio`.
    pub fn new(outlier_ratio: f64) -> Self {
        Self {
            outlier_ratio,
            inlier: Vec::new(),
            inlier_sum: 0.0,
            sigma2: 0.0,
        }
    }
}

/// EM iterations of the robust weights per reassignment.
pub const EM_ITERATIONS: usize = 3;

/// Smallest σ of the robust weights as a fraction of the data's bounding-box diagonal: a fit that
/// matches its data exactly would otherwise shrink σ to zero and call every point an outlier
/// (at 1e-5 EMS's clean near-box `partial_pointCloud_example_3` loses its refinement that way).
/// Every point within a few σ of the surface pulls with full weight, so the floor is also the
/// scale below which the weights cannot tell a surface point from a stray one: at 1e-3 it held σ
/// above the inliers' own spread on `noisy_pointCloud_example_1` (its EM σ is 4.5–9.7·10⁻⁴ of
/// the diagonal) and let `partial_3`'s few stray points bend the fit (median distance 6.3·10⁻⁵
/// of the diagonal; 6·10⁻⁶ at 3·10⁻⁴, EMS 5·10⁻⁶). Measured with `fit FILE --global-only` on
/// the eight shipped clouds and `cargo bench --bench ground_truth` (its table does not
/// change).
pub const SIGMA_FLOOR: f64 = 3e-4;

/// Default coverage-spring density as a fraction of β.
pub const DEFAULT_COVERAGE: f64 = 0.1;

/// A reassignment that changes the robust weights' σ² ([`Robust`]) by more than this fraction
/// counts every spring as changed, so that a fit is not at rest while its weights still sharpen:
/// stopped earlier, a fit keeps the weight of outliers that a tighter σ would drop (on generated
/// clouds with 20 % outliers the refining stage stopped after 193 steps with σ still falling,
/// 0.1 of the RMS radius short of where it settles).
pub const WEIGHTS_SETTLED: f64 = 0.01;

/// A migration onto the continuous surface ([`RangeForces::migrate`]) leaves a point where it is
/// when its move along the surface would be shorter than this fraction of its distance to its
/// datum: the point is at its foot to within a relative 10⁻⁶ of that distance (the neglected move
/// enters it squared), and trying the move would cost a second evaluation of the surface.
pub const MIGRATION_AT_FOOT: f64 = 1e-3;

impl RangeForces {
    /// Range data with no points of influence yet.
    pub fn new(points: Vec<DVec3>, beta: f64, mode: InfluenceMode) -> Self {
        Self {
            query_order: QueryOrder::new(&points),
            point_tree: PointTree::Unbuilt,
            points,
            beta,
            mode,
            influence: Vec::new(),
            coverage: DEFAULT_COVERAGE,
            node_targets: Vec::new(),
            robust: None,
            plane: false,
            parallel: false,
            surface_offset: Vec::new(),
            on_node: Vec::new(),
            surface_terms: Vec::new(),
        }
    }

    /// The data points r in world space, in the order they were given.
    pub fn points(&self) -> &[DVec3] {
        &self.points
    }

    /// μ of the data springs' point-to-plane form: [`SURFACE_TANGENT_FRACTION`] while the points
    /// migrate on the continuous surface, [`TANGENT_FRACTION`] otherwise.
    fn tangent_fraction(&self) -> f64 {
        if self.surface_offset.is_empty() {
            TANGENT_FRACTION
        } else {
            SURFACE_TANGENT_FRACTION
        }
    }

    /// The current point of influence of each data point, in the points' order (empty until the
    /// first [`Self::reassign`] and after [`Self::detach`]).
    pub fn influence(&self) -> &[Influence] {
        &self.influence
    }

    /// Forgets every point of influence, so that the next [`Self::reassign`] attaches every
    /// point afresh (for a model whose nodes were replaced, or a reset); until then
    /// [`Self::accumulate`] adds no data point's spring (the coverage springs of the last
    /// reassignment stay).
    pub fn detach(&mut self) {
        self.influence.clear();
        self.on_node.clear();
    }

    /// Where point `i`'s point of influence is, for nodes at `node_x`: interpolated on the mesh,
    /// plus its [`Self::surface_offset`] after a migration onto the continuous surface.
    #[inline]
    fn influence_x(&self, i: usize, node_x: &[DVec3]) -> DVec3 {
        let x = self.influence[i].at.interpolate(|k| node_x[k]);
        self.surface_offset.get(i).map_or(x, |d| x + *d)
    }

    /// The weight of point `i` relative to the paper's equal weights: m p_i / Σ p with the
    /// inlier probabilities p of [`Robust`], so that the springs' total strength stays β |Ω|; 1
    /// without robust weights or before the first reassignment.
    pub fn relative_weight(&self, i: usize) -> f64 {
        self.inlier_scale().map_or(1.0, |(p, scale)| p[i] * scale)
    }

    /// [`Self::relative_weight`] of every point, in the points' order.
    pub fn relative_weights(&self) -> Vec<f64> {
        (0..self.points.len())
            .map(|i| self.relative_weight(i))
            .collect()
    }

    /// The inlier probabilities and m / Σ p, when robust weights are in force.
    fn inlier_scale(&self) -> Option<(&[f64], f64)> {
        match &self.robust {
            Some(r) if r.inlier.len() == self.points.len() && r.inlier_sum > 0.0 => {
                Some((&r.inlier, self.points.len() as f64 / r.inlier_sum))
            }
            _ => None,
        }
    }

    /// The inlier probability of point `i` (1 without robust weights).
    fn inlier(&self, i: usize) -> f64 {
        match &self.robust {
            Some(r) if r.inlier.len() == self.points.len() => r.inlier[i],
            _ => 1.0,
        }
    }

    /// The spring constant w = β |Ω| / m of each point.
    pub fn point_weight(&self, tess: &Tessellation) -> f64 {
        let area = tess.area;
        if self.points.is_empty() {
            0.0
        } else {
            self.beta * area / self.points.len() as f64
        }
    }

    /// Refreshes the points of influence from the current node positions `node_x`. Nearest-node
    /// mode moves every point to its nearest node; migrating mode does so only where the nearest
    /// node is closer than the current point of influence. Returns how many springs changed: the
    /// points that moved, or all of them when the robust weights' σ² moved by more than
    /// [`WEIGHTS_SETTLED`].
    pub fn reassign(&mut self, tess: &Tessellation, node_x: &[DVec3]) -> usize {
        self.node_targets = if self.coverage > 0.0 {
            self.point_tree.nearest_indices(&self.points, node_x)
        } else {
            Vec::new()
        };
        let nearest = self.query_order.nearest_indices(node_x);
        let fresh = self.influence.len() != self.points.len();
        let mut changed = 0;
        if fresh {
            self.influence.clear();
            self.surface_offset.clear();
        }
        for (i, &n) in nearest.iter().enumerate() {
            let [u, v] = tess.uv[n as usize];
            let candidate = Influence {
                u,
                v,
                at: ElementPoint::at_node(n),
            };
            if fresh {
                self.influence.push(candidate);
                changed += 1;
                continue;
            }
            let replace = match self.mode {
                InfluenceMode::NearestNode => {
                    let current = &self.influence[i].at;
                    current.nodes[0] != n || current.weights[0] != 1.0
                }
                InfluenceMode::Migrating { .. } => {
                    let here = self.influence_x(i, node_x).distance_squared(self.points[i]);
                    node_x[n as usize].distance_squared(self.points[i]) < here
                }
            };
            if replace {
                self.influence[i] = candidate;
                if let Some(d) = self.surface_offset.get_mut(i) {
                    *d = DVec3::ZERO;
                }
                changed += 1;
            }
        }
        self.on_node.clear();
        if self.influence.iter().all(|inf| inf.at.weights[0] == 1.0) {
            self.on_node
                .extend(self.influence.iter().map(|inf| inf.at.nodes[0]));
        }
        let sigma2 = self.robust.as_ref().map(|r| r.sigma2);
        self.update_robust(node_x);
        if let (Some(before), Some(rb)) = (sigma2, &self.robust)
            && (rb.sigma2 - before).abs() > WEIGHTS_SETTLED * rb.sigma2
        {
            // Every robust weight moved with σ: every spring changed.
            return self.points.len();
        }
        changed
    }

    /// The E-step of the robust weights: each point's inlier probability from its distance to its
    /// point of influence, then σ² from the weighted distances, [`EM_ITERATIONS`] times.
    fn update_robust(&mut self, node_x: &[DVec3]) {
        let m = self.points.len();
        if self.robust.is_none() || m == 0 {
            return;
        }
        let d2: Vec<f64> = (0..m)
            .map(|i| self.influence_x(i, node_x).distance_squared(self.points[i]))
            .collect();
        let Some(rb) = self.robust.as_mut() else {
            return;
        };
        let (lo, hi) = self.points.iter().fold(
            (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY)),
            |(lo, hi), p| (lo.min(*p), hi.max(*p)),
        );
        let extent = hi - lo;
        let diagonal = extent.length().max(f64::MIN_POSITIVE);
        // The outliers' uniform density over the data's bounding box (each side at least 1 % of
        // the diagonal, so that flat data have a volume).
        let volume = extent.max(DVec3::splat(0.01 * diagonal)).element_product();
        let p0 = 1.0 / volume;
        let floor = (SIGMA_FLOOR * diagonal).powi(2);
        if !(rb.sigma2 > 0.0) {
            rb.sigma2 = (d2.iter().sum::<f64>() / (3.0 * m as f64)).max(floor);
        }
        rb.inlier.resize(m, 1.0);
        let w_o = rb.outlier_ratio.clamp(0.0, 1.0 - 1e-9);
        for _ in 0..EM_ITERATIONS {
            let s2 = rb.sigma2;
            let norm = (2.0 * std::f64::consts::PI * s2).powf(-1.5);
            let (mut sp, mut spd) = (0.0, 0.0);
            for (p, &d) in rb.inlier.iter_mut().zip(&d2) {
                let g = (1.0 - w_o) * norm * (-d / (2.0 * s2)).exp();
                *p = if g + w_o * p0 > 0.0 {
                    g / (g + w_o * p0)
                } else {
                    0.0
                };
                sp += *p;
                spd += *p * d;
            }
            rb.inlier_sum = sp;
            if sp > 0.0 {
                rb.sigma2 = (spd / (3.0 * sp)).max(floor);
            }
        }
    }

    /// Adds every spring w (r − x(u_r)) to `out`, spread to the element's nodes by N_i (eq. 22),
    /// with stiffness w, and the coverage springs to `out.shape_force`. With `plane`, every spring
    /// keeps only its component along the surface normal n (from [`Tessellation::vertex_normals`],
    /// written to `out.plane_normal`) and goes to `out.shape_force` with stiffness
    /// `out.plane_stiffness`: the global DOFs only. Does nothing before the first
    /// [`Self::reassign`].
    pub fn accumulate(&self, tess: &Tessellation, node_x: &[DVec3], out: &mut NodalForces) {
        with_avx2!({ self.accumulate_body(tess, node_x, out) })
    }

    /// [`Self::accumulate`]'s body, inlined into both of its builds.
    #[inline(always)]
    fn accumulate_body(&self, tess: &Tessellation, node_x: &[DVec3], out: &mut NodalForces) {
        let w = self.point_weight(tess);
        // Each spring's constant: w, or w m p_i / Σ p with robust weights (looked up once here).
        let robust = self.inlier_scale();
        let w_of = |i: usize| robust.map_or(w, |(p, scale)| w * p[i] * scale);
        if self.plane {
            tess.vertex_normals(node_x, &mut out.plane_normal);
            let mu = self.tangent_fraction();
            for (i, (r, inf)) in self.points.iter().zip(&self.influence).enumerate() {
                let w = w_of(i);
                let at = &inf.at;
                let x = self.influence_x(i, node_x);
                let n = at.interpolate(|k| out.plane_normal[k]).normalize_or_zero();
                let f = w * plane_spring(*r - x, n, mu);
                for k in 0..4 {
                    let nk = at.weights[k];
                    if nk != 0.0 {
                        let node = at.nodes[k] as usize;
                        out.shape_force[node] += nk * f;
                        out.plane_stiffness[node] += (1.0 - mu) * nk * w;
                        out.shape_stiffness[node] += mu * nk * w;
                    }
                }
            }
        } else if self.on_node.len() == self.points.len() && self.surface_offset.is_empty() {
            // Every spring on a node (the paper's nearest-node springs): what `out.add` does for
            // a point on a node, in the same order, from the compact copy of the nodes.
            for (i, (r, &n)) in self.points.iter().zip(&self.on_node).enumerate() {
                let (w, n) = (w_of(i), n as usize);
                out.force[n] += w * (*r - node_x[n]);
                out.stiffness[n] += w;
            }
        } else {
            for (i, (r, inf)) in self.points.iter().zip(&self.influence).enumerate() {
                let w = w_of(i);
                let x = self.influence_x(i, node_x);
                out.add(&inf.at, w * (*r - x), w);
            }
        }
        for (i, &t) in self.node_targets.iter().enumerate() {
            let wi = self.coverage * self.beta * tess.node_area[i] * self.inlier(t as usize);
            let d = self.points[t as usize] - node_x[i];
            if self.plane {
                let n = out.plane_normal[i];
                out.shape_force[i] += wi * plane_spring(d, n, TANGENT_FRACTION);
                out.plane_stiffness[i] += (1.0 - TANGENT_FRACTION) * wi;
                out.shape_stiffness[i] += TANGENT_FRACTION * wi;
            } else {
                out.shape_force[i] += wi * d;
                out.shape_stiffness[i] += wi;
            }
        }
    }

    /// The springs' potential energy ½ w Σ |r − x(u_r)|² plus that of the coverage springs; with
    /// `plane`, ½ w Σ dᵀ ((1 − μ) n nᵀ + μ I) d for d = r − x(u_r).
    pub fn energy(&self, tess: &Tessellation, node_x: &[DVec3]) -> f64 {
        let w = self.point_weight(tess);
        let mut normals = Vec::new();
        if self.plane {
            tess.vertex_normals(node_x, &mut normals);
        }
        let normal_at = |at: &ElementPoint| at.interpolate(|k| normals[k]).normalize_or_zero();
        let mu = self.tangent_fraction();
        let sq = |d: DVec3, n: DVec3, mu: f64| {
            if self.plane {
                d.dot(plane_spring(d, n, mu))
            } else {
                d.length_squared()
            }
        };
        let data: f64 = self
            .points
            .iter()
            .zip(&self.influence)
            .enumerate()
            .map(|(i, (r, inf))| {
                let n = if self.plane {
                    normal_at(&inf.at)
                } else {
                    DVec3::ZERO
                };
                self.relative_weight(i) * sq(*r - self.influence_x(i, node_x), n, mu)
            })
            .sum();
        let cover: f64 = self
            .node_targets
            .iter()
            .enumerate()
            .map(|(i, &t)| {
                let n = normals.get(i).copied().unwrap_or_default();
                self.coverage
                    * self.beta
                    * tess.node_area[i]
                    * self.inlier(t as usize)
                    * sq(self.points[t as usize] - node_x[i], n, TANGENT_FRACTION)
            })
            .sum();
        0.5 * (w * data + cover)
    }

    /// One migration step (Fig. 3): project each point's force onto the surface tangents
    /// ∂x/∂u, ∂x/∂v at its point of influence and move (u_r, v_r) by `rate` times the move that
    /// would cancel each projection, at most one element per step, halving the move while it would
    /// take the point farther from its datum. Only in migrating mode.
    ///
    /// With `surface`, the points of influence lie on the model's continuous surface
    /// ([`ModelSurface`], the paper's x(u)), with its own tangents, and
    /// [`Self::surface_offset`] keeps them there; without it, on the mesh's triangles, whose
    /// chords of a curved model lie inside it by up to h² κ / 8 (element size h, curvature κ): a
    /// bias of the fit on a par with the data's own distances once those are well below the
    /// element size. A point whose move would be shorter than [`MIGRATION_AT_FOOT`] of its
    /// distance stays where it is.
    pub fn migrate(
        &mut self,
        tess: &Tessellation,
        node_x: &[DVec3],
        surface: Option<&ModelSurface>,
    ) {
        let InfluenceMode::Migrating { rate } = self.mode else {
            self.surface_offset.clear();
            self.surface_terms.clear();
            return;
        };
        self.on_node.clear();
        let m = self.points.len();
        // Each point moves on its own, so the points may go over the cores; every point's
        // result is the same on any thread. Without `parallel` the loop stays on the calling
        // thread: a rayon loop called from outside rayon's pool would run on the pool's threads
        // and make the similarity candidates, each on a thread of its own, queue there.
        let parallel = self.parallel;
        let (points, influence) = (&self.points, &mut self.influence);
        match surface {
            Some(s) => {
                self.surface_offset.resize(m, DVec3::ZERO);
                self.surface_terms
                    .resize(m, SurfaceTerms::new(f64::NAN, f64::NAN));
                let (terms, offsets) = (&mut self.surface_terms, &mut self.surface_offset);
                let one = |(((r, inf), kept), offset): (
                    ((&DVec3, &mut Influence), &mut SurfaceTerms),
                    &mut DVec3,
                )| {
                    let foot = migrate_point(*r, inf, Some((s, kept)), tess, node_x, rate);
                    *offset = foot - inf.at.interpolate(|k| node_x[k]);
                };
                if parallel {
                    points
                        .par_iter()
                        .zip(influence.par_iter_mut())
                        .zip(terms.par_iter_mut())
                        .zip(offsets.par_iter_mut())
                        .with_min_len(PARALLEL_MIGRATION)
                        .for_each(one);
                } else {
                    points
                        .iter()
                        .zip(influence.iter_mut())
                        .zip(terms.iter_mut())
                        .zip(offsets.iter_mut())
                        .for_each(one);
                }
            }
            None => {
                self.surface_offset.clear();
                self.surface_terms.clear();
                let one = |(r, inf): (&DVec3, &mut Influence)| {
                    migrate_point(*r, inf, None, tess, node_x, rate);
                };
                if parallel {
                    points
                        .par_iter()
                        .zip(influence.par_iter_mut())
                        .with_min_len(PARALLEL_MIGRATION)
                        .for_each(one);
                } else {
                    points.iter().zip(influence.iter_mut()).for_each(one);
                }
            }
        }
    }
}
