//! The search structures of the range forces: the k-d tree of the data points, kept between
//! reassignments, and the cache-friendly order the points are queried in.

use super::*;

/// The k-d tree of a [`RangeForces`]' own data points, for the coverage springs' search of each
/// node's nearest point: built at the first reassignment that needs it and kept, since the
/// points never change (it used to be built again at every reassignment). Its answers are
/// [`nearest_indices`]' over the same points (the same indices but where two points tie).
/// Shared between clones; a cache of the points, so it takes no part in equality.
#[derive(Clone, Default)]
pub(super) enum PointTree {
    /// Not built yet.
    #[default]
    Unbuilt,
    /// Built; `None` where kiddo could not build one (the brute force answers then).
    Built(Option<Arc<ImmutableKdTree<f64, 3>>>),
}

impl PartialEq for PointTree {
    /// Always equal: the tree is a function of the points, which the owner compares.
    fn eq(&self, _: &Self) -> bool {
        true
    }
}

impl std::fmt::Debug for PointTree {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            PointTree::Unbuilt => f.write_str("PointTree::Unbuilt"),
            PointTree::Built(tree) => write!(f, "PointTree::Built({})", tree.is_some()),
        }
    }
}

impl PointTree {
    /// For every query in `queries`, the index of the nearest of `points` (which must be the
    /// points this tree was, or is now, built over): [`nearest_indices`]`(points, queries)`.
    pub(super) fn nearest_indices(&mut self, points: &[DVec3], queries: &[DVec3]) -> Vec<u32> {
        if matches!(self, PointTree::Unbuilt) {
            *self = PointTree::Built(kd_tree(points).map(Arc::new));
        }
        match self {
            PointTree::Built(Some(tree)) => query_nearest(tree, queries),
            _ => nearest_indices_brute(points, queries),
        }
    }
}

/// Query points kept in a spatially coherent order (Morton order of a 1024³ grid over their
/// bounding box) for repeated nearest-node searches against changing nodes: consecutive queries
/// then read the same cells of the grid (or branches of the k-d tree) in cache. The answers are
/// [`nearest_indices`]' nearest nodes (the same indices but where two nodes tie, since the order
/// decides which queries the tree answers; tested); only the time changes. A fit's data points
/// never change while its nodes move, so [`RangeForces`] orders its points once and searches in
/// that order at every reassignment.
/// Measured (`cargo bench --bench kernels -- reassignment`): 100 000
/// points against 19 883 nodes searched in 0.74–0.98 of the time they take in random order
/// (medians of interleaved runs 0.86–0.87), for a one-time ordering that costs about a sixth of
/// one search; at 1000 points against 963 nodes no difference.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct QueryOrder {
    /// `order[j]`: the index among the given points of the j-th point in query order.
    pub(super) order: Vec<u32>,
    /// The points in query order: `sorted[j] = points[order[j]]`, read front to back.
    pub(super) sorted: Vec<DVec3>,
}

impl QueryOrder {
    /// Orders `points`. Non-finite coordinates are allowed: such points take the first or the
    /// last cell of the grid and are searched like any other.
    pub fn new(points: &[DVec3]) -> Self {
        let finite = points.iter().filter(|p| p.is_finite());
        let (lo, hi) = finite.fold(
            (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY)),
            |(lo, hi), p| (lo.min(*p), hi.max(*p)),
        );
        let span = (hi - lo).max_element();
        let scale = if span > 0.0 && span.is_finite() {
            1023.0 / span
        } else {
            0.0
        };
        let mut keyed: Vec<(u32, u32)> = points
            .iter()
            .enumerate()
            .map(|(i, p)| {
                // `as` saturates, and sends NaN to 0.
                let cell = ((*p - lo) * scale).to_array().map(|c| c as u32);
                let key = morton_spread(cell[0])
                    | morton_spread(cell[1]) << 1
                    | morton_spread(cell[2]) << 2;
                (key, i as u32)
            })
            .collect();
        keyed.sort_unstable();
        let order: Vec<u32> = keyed.into_iter().map(|(_, i)| i).collect();
        let sorted = order.iter().map(|&i| points[i as usize]).collect();
        Self { order, sorted }
    }

    /// How many points are ordered.
    pub fn len(&self) -> usize {
        self.order.len()
    }

    /// True when no points are ordered.
    pub fn is_empty(&self) -> bool {
        self.order.is_empty()
    }

    /// For every ordered point, in the order the points were given, the index of the nearest
    /// of `nodes`: [`nearest_indices`]`(nodes, points)`, searched in query order.
    pub fn nearest_indices(&self, nodes: &[DVec3]) -> Vec<u32> {
        let mut out = vec![0; self.order.len()];
        for (&i, n) in self.order.iter().zip(nearest_indices(nodes, &self.sorted)) {
            out[i as usize] = n;
        }
        out
    }
}

/// The low 10 bits of `x` spread to every third bit (bit b to bit 3b), for a Morton key.
pub(super) fn morton_spread(x: u32) -> u32 {
    let mut x = x.min(1023);
    x = (x | (x << 16)) & 0x0300_00ff;
    x = (x | (x << 8)) & 0x0300_f00f;
    x = (x | (x << 4)) & 0x030c_30c3;
    (x | (x << 2)) & 0x0924_9249
}
