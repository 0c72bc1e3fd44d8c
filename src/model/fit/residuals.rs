//! How far a fit lies from its data: point-to-surface distances through the tessellation or the
//! continuous superquadric, and their summaries ([`Residuals`]).

use crate::model::dynamics::ModelState;
use crate::model::fem::Tessellation;
use crate::model::init::{InitialPose, Normalization};
use crate::model::lm::{DeformedPose, deformed_distances};
use crate::model::nearest::kd_tree;
use glam::DVec3;
use kiddo::SquaredEuclidean;
use std::num::NonZero;

/// Distances of the data points to the fitted surface, as fractions of the data's bounding-box
/// diagonal.
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize)]
pub struct Residuals {
    /// Mean distance.
    pub mean: f64,
    /// Root-mean-square distance.
    pub rms: f64,
    /// 95th percentile.
    pub p95: f64,
    /// Largest distance.
    pub max: f64,
    /// The bounding-box diagonal the figures are relative to (data units).
    pub diagonal: f64,
}

/// The mean distance of `points` to the surface through `node_x`, point i weighted by
/// `weights[i]` (the similarity switch's score, [`FitOptions::similarity_switch`](super::FitOptions::similarity_switch)).
pub fn weighted_mean_distance(
    tess: &Tessellation,
    node_x: &[DVec3],
    points: &[DVec3],
    weights: &[f64],
) -> f64 {
    weighted_mean(&point_distances(tess, node_x, points), weights)
}

/// The mean of the distances `d`, `d[i]` weighted by `weights[i]`.
fn weighted_mean(d: &[f64], weights: &[f64]) -> f64 {
    let total: f64 = weights.iter().sum();
    d.iter().zip(weights).map(|(d, w)| d * w).sum::<f64>() / total.max(f64::MIN_POSITIVE)
}

/// The score by which hypotheses are compared: the mean distance of the points to the surface
/// through `node_x`.
pub fn mean_distance(tess: &Tessellation, node_x: &[DVec3], points: &[DVec3]) -> f64 {
    let d = point_distances(tess, node_x, points);
    d.iter().sum::<f64>() / d.len().max(1) as f64
}

/// Closest point to `p` on triangle (a, b, c) (Ericson, Real-Time Collision Detection §5.1.5).
pub fn closest_point_on_triangle(p: DVec3, a: DVec3, b: DVec3, c: DVec3) -> DVec3 {
    let (ab, ac, ap) = (b - a, c - a, p - a);
    let (d1, d2) = (ab.dot(ap), ac.dot(ap));
    if d1 <= 0.0 && d2 <= 0.0 {
        return a;
    }
    let bp = p - b;
    let (d3, d4) = (ab.dot(bp), ac.dot(bp));
    if d3 >= 0.0 && d4 <= d3 {
        return b;
    }
    let vc = d1 * d4 - d3 * d2;
    if vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0 {
        return a + ab * (d1 / (d1 - d3));
    }
    let cp = p - c;
    let (d5, d6) = (ab.dot(cp), ac.dot(cp));
    if d6 >= 0.0 && d5 <= d6 {
        return c;
    }
    let vb = d5 * d2 - d1 * d6;
    if vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0 {
        return a + ac * (d2 / (d2 - d6));
    }
    let va = d3 * d6 - d5 * d4;
    if va <= 0.0 && (d4 - d3) >= 0.0 && (d5 - d6) >= 0.0 {
        return b + (c - b) * ((d4 - d3) / ((d4 - d3) + (d5 - d6)));
    }
    let denom = 1.0 / (va + vb + vc);
    a + ab * (vb * denom) + ac * (vc * denom)
}

/// Number of nearest nodes whose incident triangles are searched for each point's closest
/// surface point in [`residuals`].
pub(crate) const RESIDUAL_CANDIDATE_NODES: usize = 12;

/// Distance from every point to the triangulated surface through `node_x` (the render
/// triangulation of `tess`). The closest point is searched on the triangles around the
/// `RESIDUAL_CANDIDATE_NODES` nearest nodes (k-d tree), which contain it on any surface whose
/// triangles are not much longer than the node spacing.
pub fn point_distances(tess: &Tessellation, node_x: &[DVec3], points: &[DVec3]) -> Vec<f64> {
    distances(tess, node_x, points, false)
}

/// Points a run of [`point_distances_parallel`] takes: each run measures on a list of triangles
/// seen of its own, as long as the mesh's triangle list.
pub(crate) const PARALLEL_DISTANCES: usize = 256;

/// [`point_distances`] over rayon's threads, in runs of `PARALLEL_DISTANCES` points: each point
/// is measured as it is there, so the distances are the same to the bit. For the parts of a fit
/// that run alone, such as the residuals ([`fit_residuals`]); the hypotheses and candidates,
/// which already run side by side, use [`point_distances`].
pub fn point_distances_parallel(
    tess: &Tessellation,
    node_x: &[DVec3],
    points: &[DVec3],
) -> Vec<f64> {
    distances(tess, node_x, points, true)
}

/// [`point_distances`] on one thread or, with `parallel`, over rayon's.
pub(super) fn distances(
    tess: &Tessellation,
    node_x: &[DVec3],
    points: &[DVec3],
    parallel: bool,
) -> Vec<f64> {
    use rayon::prelude::*;
    let tris = tess.triangles();
    let tree = kd_tree(node_x);
    let k = NonZero::new(RESIDUAL_CANDIDATE_NODES.min(node_x.len()).max(1))
        .unwrap_or(NonZero::<usize>::MIN);
    let all_nodes: Vec<u32> = if tree.is_none() {
        (0..node_x.len() as u32).collect()
    } else {
        Vec::new()
    };
    // A triangle round several candidate nodes is measured once per point: `seen[t]` holds the
    // last point (plus one) that measured it.
    let distance = |seen: &mut Vec<u32>, (i, p): (usize, &DVec3)| {
        let stamp = i as u32 + 1;
        let mut best = f64::INFINITY;
        let mut measure = |n: u32| {
            let n = n as usize;
            for &t in tess.node_tris.of_node(n) {
                if seen[t as usize] == stamp {
                    continue;
                }
                seen[t as usize] = stamp;
                let [a, b, c] = tris[t as usize];
                let q = closest_point_on_triangle(
                    *p,
                    node_x[a as usize],
                    node_x[b as usize],
                    node_x[c as usize],
                );
                best = best.min(q.distance_squared(*p));
            }
        };
        match &tree {
            Some(tree) => tree
                .query(&p.to_array())
                .nearest_n::<SquaredEuclidean<f64>>(k)
                .execute()
                .iter()
                .for_each(|r| measure(r.item)),
            None => all_nodes.iter().for_each(|&n| measure(n)),
        }
        best.sqrt()
    };
    let unseen = || vec![0u32; tris.len()];
    if parallel {
        points
            .par_iter()
            .enumerate()
            .with_min_len(PARALLEL_DISTANCES)
            .map_init(unseen, distance)
            .collect()
    } else {
        let mut seen = unseen();
        points
            .iter()
            .enumerate()
            .map(|ip| distance(&mut seen, ip))
            .collect()
    }
}

/// The residuals a fit reports for `state` (fitted on `tess`): a model with local displacements is
/// measured on its own mesh, which is what it renders; a pure superquadric (all displacements
/// zero) on its continuous surface, which the solved fit fits and which the 963-node mesh's
/// chords would misstate by more than a clean fit's distances: [`surface_distances`], or for a
/// tapered or bent one [`deformed_distances`].
pub fn fit_residuals(tess: &Tessellation, state: &ModelState, points: &[DVec3]) -> Residuals {
    // Measured in the points' unit frame, so that no squared distance overflows at any scale;
    // the figures are relative to the diagonal, so only it is scaled back.
    let norm = Normalization::of(points);
    if !(norm.scale > 0.0) {
        return Residuals::of(Vec::new(), 0.0);
    }
    let unit: Vec<DVec3> = points.iter().map(|p| norm.unit_point(*p)).collect();
    let mut r = unit_residuals(tess, &norm.state_to_unit(state), &unit);
    r.diagonal *= norm.scale;
    r
}

/// [`fit_residuals`] in the unit frame.
pub(super) fn unit_residuals(
    tess: &Tessellation,
    state: &ModelState,
    points: &[DVec3],
) -> Residuals {
    let pure = state.displacement.iter().all(|d| *d == DVec3::ZERO);
    if pure {
        let pose = InitialPose::of(state);
        let d = if state.deformation.is_identity() {
            surface_distances(&pose, points)
        } else {
            let deformed = DeformedPose {
                pose,
                deformation: state.deformation,
            };
            deformed_distances(&deformed, points)
        };
        return Residuals::of(d, bounding_diagonal(points));
    }
    let mut x = Vec::new();
    state.node_positions(tess, &mut x);
    residuals(tess, &x, points)
}

/// |distance| of each of `points` to the closest point of the pure superquadric `pose`
/// ([`crate::model::distance::surface_distance`]), over every core for large clouds.
pub fn surface_distances(pose: &InitialPose, points: &[DVec3]) -> Vec<f64> {
    use rayon::prelude::*;
    let one = |p: &DVec3| crate::model::distance::surface_distance(pose, *p).abs();
    if points.len() >= 4 * PARALLEL_DISTANCES {
        points
            .par_iter()
            .with_min_len(PARALLEL_DISTANCES)
            .map(one)
            .collect()
    } else {
        points.iter().map(one).collect()
    }
}

/// Point-to-surface residual statistics relative to the points' bounding-box diagonal, the
/// distances measured over every core ([`point_distances_parallel`]).
pub fn residuals(tess: &Tessellation, node_x: &[DVec3], points: &[DVec3]) -> Residuals {
    Residuals::of(
        point_distances_parallel(tess, node_x, points),
        bounding_diagonal(points),
    )
}

/// The length of the diagonal of the points' axis-aligned bounding box (0 for no points).
pub fn bounding_diagonal(points: &[DVec3]) -> f64 {
    if points.is_empty() {
        return 0.0;
    }
    let (lo, hi) = points
        .iter()
        .fold((DVec3::INFINITY, DVec3::NEG_INFINITY), |(lo, hi), p| {
            (lo.min(*p), hi.max(*p))
        });
    // hi − lo may pass f64's largest: halve before subtracting, divide before squaring.
    let e = hi * 0.5 - lo * 0.5;
    let m = e.abs().max_element();
    if m > 0.0 {
        2.0 * m * (e / m).length()
    } else {
        0.0
    }
}

impl Residuals {
    /// The statistics of point-to-surface distances `d` (data units) relative to `diagonal`;
    /// all zero when there are no distances or the diagonal is not positive.
    pub fn of(mut d: Vec<f64>, diagonal: f64) -> Self {
        if d.is_empty() || !(diagonal > 0.0) {
            return Residuals {
                diagonal,
                ..Default::default()
            };
        }
        d.sort_by(f64::total_cmp);
        let m = d.len() as f64;
        let p95 = d[((0.95 * (m - 1.0)).round() as usize).min(d.len() - 1)];
        Residuals {
            mean: d.iter().sum::<f64>() / m / diagonal,
            rms: (d.iter().map(|x| x * x).sum::<f64>() / m).sqrt() / diagonal,
            p95: p95 / diagonal,
            max: d[d.len() - 1] / diagonal,
            diagonal,
        }
    }
}
