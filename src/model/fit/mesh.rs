//! The membrane's tessellation chosen from the data ([`joint_k`]): nodes where the points'
//! detail is.

use crate::model::fem::Tessellation;
use crate::model::nearest::NodeGrid;
use glam::DVec3;

/// The finest tessellation [`joint_k`] chooses: k = 101 (10 203 nodes).
pub const MAX_JOINT_K: usize = 101;

/// Data points per covered node that [`joint_k`] aims at. On the five one-view scans of
/// docs/results.md (3000–6100 points, 16–35 % of the model's surface covered) 2 gives k = 75–96;
/// 3 gave 4–30 % larger mean residuals, 1 (k up to 136) from 10 % larger to 29 % smaller at 1.5×
/// the time.
pub(crate) const POINTS_PER_COVERED_NODE: f64 = 2.0;

/// [`joint_k`] keeps the given tessellation unless the data asks for at least this many times its
/// nodes: a second joint stage on a barely finer mesh costs steps and gains nothing measurable.
pub(crate) const MIN_JOINT_REFINEMENT: f64 = 1.5;

/// The joint stage's tessellation (k) chosen from the data's density and extent, given the
/// model's nodes `x` on `tess` after the global stages and the data `points`: a node is covered
/// when it is some point's nearest, so with c of the n nodes covered the data spans about c/n of
/// the surface, and k grows until that share of the nodes is one per
/// `POINTS_PER_COVERED_NODE` points. A dense scan of a small part of the surface gets nodes
/// where its detail is; a sparse cloud keeps `min_k`, and so does one that asks for fewer than
/// `MIN_JOINT_REFINEMENT` times its nodes. At most [`MAX_JOINT_K`].
pub fn joint_k(tess: &Tessellation, x: &[DVec3], points: &[DVec3], min_k: usize) -> usize {
    let Some(grid) = NodeGrid::new(x) else {
        return min_k;
    };
    let mut covered = vec![false; x.len()];
    for i in grid.nearest_each(points) {
        covered[i as usize] = true;
    }
    let count = covered.iter().filter(|&&c| c).count().max(1);
    let share = count as f64 / tess.node_count() as f64;
    let nodes = points.len() as f64 / (POINTS_PER_COVERED_NODE * share);
    if nodes < MIN_JOINT_REFINEMENT * (min_k * min_k + 2) as f64 {
        return min_k;
    }
    let k = (nodes - 2.0).max(0.0).sqrt().round() as usize;
    k.clamp(min_k, MAX_JOINT_K.max(min_k))
}
