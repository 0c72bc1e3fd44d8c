//! The model-to-data half of a symmetric distance, for the Levenberg–Marquardt placing of a
//! superquadric (beyond the paper): the solved counterpart of `forces::range`'s coverage
//! springs.
//!
//! The points' distances to the surface see only the parts of the model that some point lies
//! near: a model fitted by them alone can shrink into the bulk of a cloud and leave its limbs or
//! the far end of a scan unexplained. The coverage term pulls a fixed set of surface points
//! x_j (the nodes of a coarse tessellation, at their material coordinates) towards their
//! nearest data points q_j, with weight `density` × a_j / |Ω| (a_j the node's material area),
//! scaled by the data term's total weight Σ w_i and by the inlier weight of q_j:
//!
//! ```text
//! E = Σ_i w_i d_i² + density · Σw · Σ_j (a_j / |Ω|) w(q_j) |x_j − q_j|²
//! ```
//!
//! which is the springs' energy of the dynamics' placing stage divided by β|Ω|. The nearest
//! points are found again at every evaluation (the k-d tree of the points is built once). On a
//! one-view scan the term would pull the unseen side onto the seen one, so a fit uses it to place
//! the model and then goes on without it, as the dynamics do.

use super::NUM_UNKNOWNS;
use super::engine::Normal;
use crate::model::fem::Tessellation;
use crate::model::init::InitialPose;
use crate::model::nearest::kd_tree;
use crate::model::superquadric::{SignedPowers, Trig, jacobian_from_powers};
use glam::{DMat3, DVec3};
use kiddo::{ImmutableKdTree, SquaredEuclidean};

/// The tessellation whose nodes carry the coverage term: k = 12 (146 nodes), about one node per
/// 15° of latitude and longitude, enough to see a limb and cheap next to the points' term.
pub const COVERAGE_K: usize = 12;

/// The coverage term of a set of points (see the module docs).
pub struct Coverage {
    points: Vec<DVec3>,
    tree: ImmutableKdTree<f64, 3>,
    trig: Vec<Trig>,
    /// a_j / |Ω| of each node.
    share: Vec<f64>,
    density: f64,
}

/// One node's surface point, its nearest data point and ∂x/∂(unknowns).
struct NodeTerm {
    offset: DVec3,
    target: usize,
    jacobian: [DVec3; NUM_UNKNOWNS],
}

impl Coverage {
    /// The coverage term of `points` with `density` (the dynamics' coverage fraction of β);
    /// `None` when the points admit no search tree or the density is not positive.
    pub fn new(points: &[DVec3], density: f64) -> Option<Self> {
        if !(density > 0.0) {
            return None;
        }
        let tess = Tessellation::new(COVERAGE_K);
        Some(Self {
            tree: kd_tree(points)?,
            points: points.to_vec(),
            trig: tess.trig.clone(),
            share: tess.node_area.iter().map(|a| a / tess.area).collect(),
            density,
        })
    }

    /// Node `j`'s surface point on `pose` and, with `jacobian`, its derivatives over the
    /// [`NUM_UNKNOWNS`] unknowns (semi-axes, ε1, ε2, translation, rotation increment).
    fn node(&self, pose: &InitialPose, j: usize, jacobian: bool) -> NodeTerm {
        let q = &pose.shape;
        let t = &self.trig[j];
        let p = SignedPowers::new(q, t);
        let axes = q.semi_axes();
        let unit = DVec3::new(p.cu * p.cv, p.cu * p.sv, p.su);
        let s = axes * unit;
        let r = DMat3::from_quat(pose.rotation);
        let x = pose.translation + r * s;
        let target = self
            .tree
            .query(&x.to_array())
            .nearest_one::<SquaredEuclidean<f64>>()
            .execute()
            .item as usize;
        let mut d = [DVec3::ZERO; NUM_UNKNOWNS];
        if jacobian {
            d[0] = r * DVec3::new(unit.x, 0.0, 0.0);
            d[1] = r * DVec3::new(0.0, unit.y, 0.0);
            d[2] = r * DVec3::new(0.0, 0.0, unit.z);
            let j = jacobian_from_powers(q, t, &p);
            d[3] = r * j[4];
            d[4] = r * j[5];
            (d[5], d[6], d[7]) = (DVec3::X, DVec3::Y, DVec3::Z);
            // x = t + R·exp(ω×)·s: ∂x/∂ω = −R·[s]×, whose column k is R·(e_k × s).
            for k in 0..3 {
                d[8 + k] = r * DVec3::AXES[k].cross(s);
            }
        }
        NodeTerm {
            offset: x - self.points[target],
            target,
            jacobian: d,
        }
    }

    /// The weight of node `j`'s spring to point `target` when the points' weights are `weights`
    /// (1 each when empty) with sum `total`.
    fn weight(&self, j: usize, target: usize, weights: &[f64], total: f64) -> f64 {
        self.density * total * self.share[j] * weights.get(target).copied().unwrap_or(1.0)
    }

    /// The term's cost on `pose` (see the module docs).
    pub fn cost(&self, pose: &InitialPose, weights: &[f64], total: f64) -> f64 {
        (0..self.trig.len())
            .map(|j| {
                let n = self.node(pose, j, false);
                self.weight(j, n.target, weights, total) * n.offset.length_squared()
            })
            .sum()
    }

    /// Adds the term's JᵀWJ (lower triangle) and JᵀWr on `pose` to `n`.
    pub(super) fn add_normal(
        &self,
        pose: &InitialPose,
        weights: &[f64],
        total: f64,
        n: &mut Normal<NUM_UNKNOWNS>,
    ) {
        for j in 0..self.trig.len() {
            let t = self.node(pose, j, true);
            let w = self.weight(j, t.target, weights, total);
            if !(w > 0.0) {
                continue;
            }
            for a in 0..NUM_UNKNOWNS {
                let wa = w * t.jacobian[a];
                n.1[a] += wa.dot(t.offset);
                for b in 0..=a {
                    n.0[a][b] += wa.dot(t.jacobian[b]);
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::lm::apply_increment;

    #[test]
    fn the_coverage_gradient_matches_central_differences() {
        let pose = crate::model::distance::tests::pose(0.6, 1.4);
        let points: Vec<DVec3> = (0..60)
            .map(|i| {
                let t = i as f64;
                DVec3::new(
                    (t * 0.37).sin(),
                    (t * 0.71).cos() * 1.3,
                    (t * 1.13).sin() * 0.8,
                )
            })
            .collect();
        let c = Coverage::new(&points, 0.1).expect("a tree");
        let weights: Vec<f64> = (0..points.len())
            .map(|i| 0.5 + (i % 3) as f64 * 0.25)
            .collect();
        let total: f64 = weights.iter().sum();
        let mut n: Normal<NUM_UNKNOWNS> =
            ([[0.0; NUM_UNKNOWNS]; NUM_UNKNOWNS], [0.0; NUM_UNKNOWNS]);
        c.add_normal(&pose, &weights, total, &mut n);
        let h = 1e-7;
        for k in 0..NUM_UNKNOWNS {
            let mut delta = [0.0; NUM_UNKNOWNS];
            delta[k] = h;
            let up = c.cost(&apply_increment(&pose, &delta), &weights, total);
            delta[k] = -h;
            let down = c.cost(&apply_increment(&pose, &delta), &weights, total);
            // ∂E/∂θ = 2 Jᵀ W r (the nearest points held: no node changes target over ±h here).
            let numeric = (up - down) / (2.0 * h);
            let analytic = 2.0 * n.1[k];
            assert!(
                (numeric - analytic).abs() <= 1e-5 * (1.0 + numeric.abs()),
                "unknown {k}: analytic {analytic}, numeric {numeric}"
            );
        }
        assert!(c.cost(&pose, &weights, total).is_finite());
    }
}
