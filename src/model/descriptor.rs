//! Global parameters as part descriptors (the paper's abstract: the global parameters are "a
//! compact description a recognizer can index").
//!
//! A fitted part is described by its shape alone — the three semi-axes and the two squareness
//! exponents — not by where it sits or how it is turned. The same surface has several
//! descriptions: flipping an axis changes nothing; swapping x and y (with a1 ↔ a2) changes
//! nothing, since x and y enter the inside-outside function symmetrically; and a permutation that
//! moves the z axis describes the same surface with ε1 and ε2 swapped when the two are equal (the
//! fitter's three axis hypotheses are exactly such relabellings). [`ShapeDescriptor::distance`]
//! is the smallest distance over these relabellings, so two fits of one object that chose
//! different axes compare as equal.
//!
//! Coordinates: the logarithms of the semi-axes (so that scale differences count as ratios) and
//! the exponents. [`ShapeDescriptor::scale_free`] divides the semi-axes by their geometric mean,
//! for indexing shape regardless of size.

use super::superquadric::SuperquadricParams;

/// A part's global shape as a point in descriptor space.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ShapeDescriptor {
    /// ln of the semi-axes a·a1, a·a2, a·a3 (the model's x, y, z).
    pub log_axes: [f64; 3],
    /// ε1 (the profile along z) and ε2 (the cross-section in x–y).
    pub epsilon: [f64; 2],
}

/// How much an exponent difference weighs against a log-axis difference in
/// [`ShapeDescriptor::distance`]: a change of 0.5 in ε counts as much as a factor e^0.5 ≈ 1.65 in
/// an axis.
pub const EPSILON_WEIGHT: f64 = 1.0;

impl ShapeDescriptor {
    /// The descriptor of a superquadric's global parameters.
    pub fn new(q: &SuperquadricParams) -> Self {
        let axes = q.semi_axes();
        Self {
            log_axes: [axes.x, axes.y, axes.z].map(|a| a.abs().max(f64::MIN_POSITIVE).ln()),
            epsilon: [q.e1, q.e2],
        }
    }

    /// The same descriptor with the semi-axes divided by their geometric mean (shape without
    /// size).
    pub fn scale_free(mut self) -> Self {
        let mean = self.log_axes.iter().sum::<f64>() / 3.0;
        self.log_axes.iter_mut().for_each(|l| *l -= mean);
        self
    }

    /// The descriptions of the same surface under the superquadric's relabellings: (x, y, z) and
    /// (y, x, z) with the same exponents, and the four permutations that move z with ε1 and ε2
    /// swapped (the same surface when ε1 = ε2).
    pub fn relabellings(&self) -> [ShapeDescriptor; 6] {
        let [x, y, z] = self.log_axes;
        let [e1, e2] = self.epsilon;
        let keep = |log_axes| ShapeDescriptor {
            log_axes,
            epsilon: [e1, e2],
        };
        let swap = |log_axes| ShapeDescriptor {
            log_axes,
            epsilon: [e2, e1],
        };
        [
            keep([x, y, z]),
            keep([y, x, z]),
            swap([y, z, x]),
            swap([z, y, x]),
            swap([z, x, y]),
            swap([x, z, y]),
        ]
    }

    /// Euclidean distance in descriptor space, without relabelling.
    pub fn raw_distance(&self, other: &Self) -> f64 {
        let axes: f64 = (0..3)
            .map(|i| (self.log_axes[i] - other.log_axes[i]).powi(2))
            .sum();
        let eps: f64 = (0..2)
            .map(|i| (self.epsilon[i] - other.epsilon[i]).powi(2))
            .sum();
        (axes + EPSILON_WEIGHT * EPSILON_WEIGHT * eps).sqrt()
    }

    /// The distance between two parts: the smallest [`Self::raw_distance`] over the
    /// [`Self::relabellings`] of `other`. Symmetric, zero for two descriptions of one surface.
    pub fn distance(&self, other: &Self) -> f64 {
        self.best_relabelling(other).1
    }
}

/// For each of [`ShapeDescriptor::relabellings`], which of the original axes becomes each axis of
/// the relabelled description (relabelling k's axis j is the original's axis `RELABELLINGS[k][j]`).
pub const RELABELLINGS: [[usize; 3]; 6] = [
    [0, 1, 2],
    [1, 0, 2],
    [1, 2, 0],
    [2, 1, 0],
    [2, 0, 1],
    [0, 2, 1],
];

impl ShapeDescriptor {
    /// The relabelling of `other` nearest `self` (an index into [`Self::relabellings`] and
    /// [`RELABELLINGS`]) and its distance.
    pub fn best_relabelling(&self, other: &Self) -> (usize, f64) {
        other
            .relabellings()
            .iter()
            .map(|o| self.raw_distance(o))
            .enumerate()
            .min_by(|a, b| a.1.total_cmp(&b.1))
            .unwrap_or((0, f64::INFINITY))
    }
}

/// The index of the entry of `library` nearest `query` by [`ShapeDescriptor::distance`], with
/// that distance; `None` for an empty library.
pub fn nearest_part(library: &[ShapeDescriptor], query: &ShapeDescriptor) -> Option<(usize, f64)> {
    library
        .iter()
        .map(|d| query.distance(d))
        .enumerate()
        .min_by(|a, b| a.1.total_cmp(&b.1))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::superquadric::inside_outside;
    use glam::DVec3;

    fn q(a1: f64, a2: f64, a3: f64, e1: f64, e2: f64) -> SuperquadricParams {
        SuperquadricParams {
            a: 1.0,
            a1,
            a2,
            a3,
            e1,
            e2,
        }
    }

    #[test]
    fn relabellings_describe_the_same_surface_where_the_model_says_so() {
        // x ↔ y: always the same surface; z moved: the same when ε1 = ε2.
        let box_like = q(0.9, 0.5, 0.3, 0.4, 0.4);
        let tube = q(0.9, 0.5, 0.3, 0.4, 1.0);
        for (shape, all_same) in [(box_like, true), (tube, false)] {
            let d = ShapeDescriptor::new(&shape);
            for (k, r) in d.relabellings().iter().enumerate() {
                let axes = r.log_axes.map(f64::exp);
                let other = q(axes[0], axes[1], axes[2], r.epsilon[0], r.epsilon[1]);
                // Points of the original surface, mapped by the same relabelling.
                let perm = relabel_order(k);
                let mut worst: f64 = 0.0;
                for i in 0..50 {
                    let (u, v) = (-1.4 + 2.8 * i as f64 / 49.0, 0.37 * i as f64);
                    let p = crate::model::superquadric::shape_at(&shape, u, v);
                    let pa = p.to_array();
                    let mapped = DVec3::new(pa[perm[0]], pa[perm[1]], pa[perm[2]]);
                    worst = worst.max((inside_outside(&other, mapped) - 1.0).abs());
                }
                if k < 2 || all_same {
                    assert!(worst < 1e-9, "relabelling {k}: off the surface by {worst}");
                } else {
                    assert!(worst > 1e-3, "relabelling {k} of a tube should differ");
                }
            }
        }
    }

    /// The axis order of relabelling `k` of [`ShapeDescriptor::relabellings`].
    fn relabel_order(k: usize) -> [usize; 3] {
        RELABELLINGS[k]
    }

    #[test]
    fn distance_is_zero_for_relabellings_symmetric_and_grows_with_shape_change() {
        let a = ShapeDescriptor::new(&q(0.8, 0.4, 1.0, 0.6, 1.3));
        for r in a.relabellings() {
            assert!(a.distance(&r) < 1e-12 && r.distance(&a) < 1e-12);
        }
        let b = ShapeDescriptor::new(&q(0.7, 0.45, 1.0, 0.9, 1.1));
        assert!((a.distance(&b) - b.distance(&a)).abs() < 1e-12);
        let c = ShapeDescriptor::new(&q(0.2, 0.2, 1.0, 0.2, 0.3));
        assert!(a.distance(&b) < a.distance(&c));
        // Size: a twice-as-large copy is far as is, identical scale-free.
        let big = ShapeDescriptor::new(&SuperquadricParams {
            a: 2.0,
            ..q(0.8, 0.4, 1.0, 0.6, 1.3)
        });
        assert!(a.distance(&big) > 1.0);
        assert!(a.scale_free().distance(&big.scale_free()) < 1e-12);
    }

    #[test]
    fn the_nearest_part_of_a_library_is_found() {
        let library: Vec<ShapeDescriptor> = [
            q(1.0, 1.0, 1.0, 1.0, 1.0),
            q(0.3, 0.3, 1.0, 0.2, 1.0),
            q(1.0, 0.8, 0.3, 0.3, 0.3),
        ]
        .iter()
        .map(ShapeDescriptor::new)
        .collect();
        // A slab fitted with x and y exchanged: the third entry.
        let query = ShapeDescriptor::new(&q(0.75, 0.95, 0.32, 0.3, 0.35));
        assert_eq!(nearest_part(&library, &query).map(|n| n.0), Some(2));
        // A cylinder fitted with its axis along x: the second entry under a relabelling.
        let cylinder_x = ShapeDescriptor::new(&q(1.0, 0.3, 0.3, 1.0, 0.2));
        let (i, d) = nearest_part(&library, &cylinder_x).unwrap();
        assert_eq!(i, 1, "distance {d}");
        assert!(nearest_part(&[], &query).is_none());
    }
}
