//! Exact nearest-node search over a uniform grid of cells, for queries near a surface.
//!
//! The model's nodes lie on a closed surface and a fit's data points lie near it, so the nearest
//! node of a point is usually within about one node spacing. [`NodeGrid`] buckets the nodes into
//! cubic cells (a counting sort, O(n)) and answers a query by scanning a block of cells around it:
//! first the cells within half a cell's width of it (one to eight cells), then, if a cell outside
//! that block could hold a nearer node, the cells within the best distance found so far, which
//! must hold the nearest node. Each row of a block along x is one contiguous run of the sorted
//! nodes. A query far from every node (its block would exceed [`MAX_BLOCK_CELLS`] cells) is
//! answered by a k-d tree (kiddo) over the nodes, built on the first such query, and so is, in
//! [`NodeGrid::nearest_each`], a query after one that was more than [`FAR_CELLS`] cells from its
//! nearest node.
//!
//! The answer is the nearest node: [`nearest_indices_brute`]'s, since both compare
//! the same squared distances computed the same way. Between nodes at the same distance the grid
//! takes the lowest index, as the brute force does, and the k-d tree whichever it meets first.

use std::cell::OnceCell;

use glam::DVec3;
use kiddo::{ImmutableKdTree, SquaredEuclidean};

use crate::model::simd::with_avx2;

/// Cell width in node spacings, the spacing estimated as √(A / n) from the area A of the nodes'
/// bounding box and their number n (the cells may be wider: [`MAX_CELLS_PER_NODE`]). Chosen by
/// the `reassignment` benchmarks among 0.5–3.0: wider cells scan more nodes for each query,
/// narrower ones more rows of cells and more second blocks.
const CELL_SPACINGS: f64 = 0.8;

/// At most this many cells per node: bounds the grid's memory when the nodes' bounding box is
/// thin or nearly degenerate (a flat or needle-like model).
const MAX_CELLS_PER_NODE: usize = 8;

/// Blocks of cells scanned for one query before it is handed to the k-d tree.
const MAX_PASSES: usize = 4;

/// [`NodeGrid::nearest_each`] hands a query to the k-d tree when the query before it was
/// farther than this many cells' widths from its nearest node.
pub const FAR_CELLS: f64 = 3.0;

/// A block of more cells than this (7³) is not scanned: the query goes to the k-d tree.
pub const MAX_BLOCK_CELLS: usize = 343;

/// The nodes bucketed into a uniform grid of cubic cells, in struct-of-arrays order by cell.
pub struct NodeGrid<'a> {
    /// The nodes as given, for the k-d tree of the queries that fall back to it.
    nodes: &'a [DVec3],
    /// The grid's corner: the least coordinates of the nodes.
    lo: DVec3,
    /// The cells' width.
    h: f64,
    /// 1 / `h`.
    inv_h: f64,
    /// Cells along x, y and z.
    dims: [usize; 3],
    /// The sorted nodes of cell c = x + dims[0] (y + dims[1] z) are
    /// `cell_start[c]..cell_start[c + 1]`.
    cell_start: Vec<u32>,
    /// The nodes' coordinates, sorted by cell.
    xs: Vec<f64>,
    /// See `xs`.
    ys: Vec<f64>,
    /// See `xs`.
    zs: Vec<f64>,
    /// The index among the given nodes of each sorted node.
    ids: Vec<u32>,
    /// How far short of a cell's face a node may be and still be bucketed beyond it, from the
    /// rounding of its cell coordinate; subtracted from every distance bound.
    slack: f64,
    /// The k-d tree over `nodes`, built on the first query that the grid hands to it.
    tree: OnceCell<Option<ImmutableKdTree<f64, 3>>>,
}

impl<'a> NodeGrid<'a> {
    /// Buckets `nodes`. `None` when there are none, or any coordinate is not finite.
    pub fn new(nodes: &'a [DVec3]) -> Option<Self> {
        if nodes.is_empty()
            || nodes.len() >= u32::MAX as usize
            || !nodes.iter().all(|p| p.is_finite())
        {
            return None;
        }
        let (lo, hi) = nodes
            .iter()
            .fold((nodes[0], nodes[0]), |(lo, hi), p| (lo.min(*p), hi.max(*p)));
        let ext = hi - lo;
        if !ext.is_finite() {
            return None; // coordinates so far apart that their differences overflow
        }
        let n = nodes.len();
        let box_area = 2.0 * (ext.x * ext.y + ext.y * ext.z + ext.z * ext.x);
        let max_cells = (MAX_CELLS_PER_NODE * n) as f64;
        // Wide enough that the grid has at most `max_cells` cells along its longest side cubed.
        let floor = ext.max_element() / (max_cells.cbrt() - 1.0).max(1.0);
        let mut h = (CELL_SPACINGS * (box_area / n as f64).sqrt()).max(floor);
        if !(h > 0.0 && h.is_finite()) {
            // All nodes at one point: one cell.
            h = 1.0;
        }
        let dims = ext
            .to_array()
            .map(|e| ((e / h) as usize).saturating_add(1).max(1));
        let cells = dims[0] * dims[1] * dims[2];
        let cell_of = |p: &DVec3| -> usize {
            let c = ((*p - lo) * (1.0 / h)).to_array();
            let i = |a: usize| (c[a] as usize).min(dims[a] - 1);
            i(0) + dims[0] * (i(1) + dims[1] * i(2))
        };
        let mut cell_start = vec![0u32; cells + 1];
        let node_cells: Vec<u32> = nodes.iter().map(|p| cell_of(p) as u32).collect();
        for &c in &node_cells {
            cell_start[c as usize + 1] += 1;
        }
        for c in 0..cells {
            cell_start[c + 1] += cell_start[c];
        }
        let mut next = cell_start.clone();
        let mut ids = vec![0u32; n];
        for (i, &c) in node_cells.iter().enumerate() {
            let slot = &mut next[c as usize];
            ids[*slot as usize] = i as u32;
            *slot += 1;
        }
        let coord = |a: usize| {
            ids.iter()
                .map(|&i| nodes[i as usize][a])
                .collect::<Vec<f64>>()
        };
        let (xs, ys, zs) = (coord(0), coord(1), coord(2));
        let scale = lo.abs().max(hi.abs()).max_element();
        Some(Self {
            nodes,
            lo,
            h,
            inv_h: 1.0 / h,
            dims,
            cell_start,
            xs,
            ys,
            zs,
            ids,
            slack: 1e-9 * h + 1e-12 * scale,
            tree: OnceCell::new(),
        })
    }

    /// For every query, the index of the nearest node ([`NodeGrid::nearest`]), in a build for
    /// AVX2 where the processor has it.
    /// Queries go to the k-d tree directly while the previous query's nearest node was more
    /// than [`FAR_CELLS`] cells away: in a spatial order ([`crate::model::forces::range::QueryOrder`])
    /// consecutive queries are near each other, and a query that far from the nodes would scan
    /// a large block of mostly empty cells.
    pub fn nearest_each(&self, queries: &[DVec3]) -> Vec<u32> {
        let far = (FAR_CELLS * self.h) * (FAR_CELLS * self.h);
        with_avx2!({
            let mut last = 0.0;
            queries
                .iter()
                .map(|q| {
                    let (i, d) = if last > far {
                        self.tree_nearest(*q)
                    } else {
                        self.nearest_and_distance(*q)
                    };
                    last = d;
                    i
                })
                .collect()
        })
    }

    /// The index of the node nearest `q` (ties to the lowest index, unless the k-d tree answers).
    /// A query with a non-finite coordinate gets the k-d tree's answer.
    pub fn nearest(&self, q: DVec3) -> u32 {
        self.nearest_and_distance(q).0
    }

    /// [`NodeGrid::nearest`], and its squared distance.
    #[inline(always)]
    fn nearest_and_distance(&self, q: DVec3) -> (u32, f64) {
        if !q.is_finite() {
            return self.tree_nearest(q);
        }
        let mut best = (f64::INFINITY, u32::MAX);
        let mut rho = 0.5 * self.h;
        let mut scanned: Option<[[usize; 2]; 3]> = None;
        for _ in 0..MAX_PASSES {
            let mut block = self.block(q, rho);
            if scanned == Some(block) {
                // Nothing new within rho (a tie at its edge): one more cell around.
                for (a, b) in block.iter_mut().enumerate() {
                    *b = [b[0].saturating_sub(1), (b[1] + 1).min(self.dims[a] - 1)];
                }
            }
            let cells: usize = block.iter().map(|[f, l]| l - f + 1).product();
            if cells > MAX_BLOCK_CELLS {
                break;
            }
            self.scan_block(q, &block, &mut best);
            scanned = Some(block);
            // The nearest distance to any cell outside the block.
            let qa = q.to_array();
            let mut bound = f64::INFINITY;
            for (a, [first, last]) in block.into_iter().enumerate() {
                if first > 0 {
                    bound = bound.min(qa[a] - (self.lo[a] + first as f64 * self.h));
                }
                if last + 1 < self.dims[a] {
                    bound = bound.min(self.lo[a] + (last + 1) as f64 * self.h - qa[a]);
                }
            }
            if bound == f64::INFINITY {
                return (best.1, best.0); // the block covers the grid
            }
            let bound = bound - self.slack;
            if bound > 0.0 && best.0 < bound * bound {
                return (best.1, best.0);
            }
            // The nearest node is within the best distance so far: a block covering that ball.
            rho = if best.0.is_finite() {
                best.0.sqrt() * (1.0 + 1e-9) + 2.0 * self.slack
            } else {
                2.0 * rho
            };
        }
        self.tree_nearest(q)
    }

    /// The cells (first and last along each axis) that cover the cube of half-width `rho`
    /// about `q`, clamped to the grid.
    #[inline(always)]
    fn block(&self, q: DVec3, rho: f64) -> [[usize; 2]; 3] {
        let qa = q.to_array();
        std::array::from_fn(|a| {
            let cell = |x: f64| {
                // Truncation is the floor here (clamped at 0 first), and needs no libm call.
                ((x - self.lo[a]) * self.inv_h).clamp(0.0, (self.dims[a] - 1) as f64) as usize
            };
            [cell(qa[a] - rho), cell(qa[a] + rho)]
        })
    }

    /// Scans the nodes of the cells of `block` into `best` (squared distance, index), ties to
    /// the lower index: a contiguous run of sorted nodes for each row of cells along x.
    #[inline(always)]
    fn scan_block(&self, q: DVec3, block: &[[usize; 2]; 3], best: &mut (f64, u32)) {
        let [d0, d1, _] = self.dims;
        let [[x0, x1], [y0, y1], [z0, z1]] = *block;
        for z in z0..=z1 {
            for y in y0..=y1 {
                let row = d0 * (y + d1 * z);
                self.scan_cells(q, row + x0, row + x1, best);
            }
        }
    }

    /// Scans the nodes of cells `first..=last` (consecutive along x) into `best`.
    #[inline(always)]
    fn scan_cells(&self, q: DVec3, first: usize, last: usize, best: &mut (f64, u32)) {
        let nodes = self.cell_start[first] as usize..self.cell_start[last + 1] as usize;
        let (xs, ys, zs, ids) = (
            &self.xs[nodes.clone()],
            &self.ys[nodes.clone()],
            &self.zs[nodes.clone()],
            &self.ids[nodes],
        );
        for (((x, y), z), &i) in xs.iter().zip(ys).zip(zs).zip(ids) {
            // As `DVec3::distance_squared`: (n − q) · (n − q), summed x, y, z.
            let (dx, dy, dz) = (x - q.x, y - q.y, z - q.z);
            let d = dx * dx + dy * dy + dz * dz;
            if d < best.0 || (d == best.0 && i < best.1) {
                *best = (d, i);
            }
        }
    }

    /// The k-d tree's answer for `q` and its squared distance (the brute force's where kiddo
    /// cannot build a tree).
    fn tree_nearest(&self, q: DVec3) -> (u32, f64) {
        let tree = self.tree.get_or_init(|| kd_tree(self.nodes));
        let i = match tree {
            Some(tree) => {
                tree.query(&q.to_array())
                    .nearest_one::<SquaredEuclidean<f64>>()
                    .execute()
                    .item
            }
            None => nearest_indices_brute(self.nodes, &[q])[0],
        };
        (i, self.nodes[i as usize].distance_squared(q))
    }
}

/// For every query point, the index of the nearest point of `nodes` (usually the model's nodes),
/// by a grid of `nodes` ([`NodeGrid::nearest_each`]). Where no grid can be built (a non-finite
/// node, or none) a k-d tree over `nodes` answers, and [`nearest_indices_brute`] where that
/// cannot be built either.
pub fn nearest_indices(nodes: &[DVec3], points: &[DVec3]) -> Vec<u32> {
    if let Some(grid) = NodeGrid::new(nodes) {
        return grid.nearest_each(points);
    }
    match kd_tree(nodes) {
        Some(tree) => query_nearest(&tree, points),
        None => nearest_indices_brute(nodes, points),
    }
}

/// A k-d tree over `points` (entry i is `points[i]`), or `None` where kiddo cannot build one.
pub(crate) fn kd_tree(points: &[DVec3]) -> Option<ImmutableKdTree<f64, 3>> {
    let entries: Vec<[f64; 3]> = points.iter().map(|p| p.to_array()).collect();
    ImmutableKdTree::<f64, 3>::new_from_slice(&entries).ok()
}

/// For every query point, the index of the nearest entry of `tree`.
pub(crate) fn query_nearest(tree: &ImmutableKdTree<f64, 3>, points: &[DVec3]) -> Vec<u32> {
    points
        .iter()
        .map(|p| {
            tree.query(&p.to_array())
                .nearest_one::<SquaredEuclidean<f64>>()
                .execute()
                .item
        })
        .collect()
}

/// The paper's O(mn) brute-force nearest-node search (the reference for [`nearest_indices`]).
pub fn nearest_indices_brute(nodes: &[DVec3], points: &[DVec3]) -> Vec<u32> {
    points
        .iter()
        .map(|p| {
            let mut best = (f64::INFINITY, 0u32);
            for (i, n) in nodes.iter().enumerate() {
                let d = n.distance_squared(*p);
                if d < best.0 {
                    best = (d, i as u32);
                }
            }
            best.1
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Points in a box, reproducibly (a linear congruential generator).
    fn scattered(n: usize, seed: u64, lo: f64, hi: f64) -> Vec<DVec3> {
        let mut s = seed
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        let mut next = || {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            lo + (hi - lo) * ((s >> 11) as f64 / (1u64 << 53) as f64)
        };
        (0..n).map(|_| DVec3::new(next(), next(), next())).collect()
    }

    /// Nodes on an ellipsoid's lat-long grid (poles crowded, as a tessellation's are).
    fn ellipsoid_nodes(k: usize) -> Vec<DVec3> {
        let mut x = vec![DVec3::new(0.0, 0.0, 0.9), DVec3::new(0.0, 0.0, -0.9)];
        for i in 1..=k {
            let u = std::f64::consts::PI * (i as f64 / (k + 1) as f64 - 0.5);
            for j in 0..k {
                let v = std::f64::consts::TAU * j as f64 / k as f64;
                x.push(DVec3::new(
                    1.2 * u.cos() * v.cos(),
                    0.7 * u.cos() * v.sin(),
                    0.9 * u.sin(),
                ));
            }
        }
        x
    }

    /// The grid's answers, one query at a time; [`NodeGrid::nearest_each`] (which hands the
    /// queries after a far one to the k-d tree) must give the same.
    fn grid_answers(nodes: &[DVec3], queries: &[DVec3]) -> Vec<u32> {
        let grid = NodeGrid::new(nodes).expect("grid");
        let each: Vec<u32> = queries.iter().map(|q| grid.nearest(*q)).collect();
        let brute = nearest_indices_brute(nodes, queries);
        let tied = |a: &[u32]| {
            a.iter().zip(&brute).zip(queries).all(|((i, j), q)| {
                nodes[*i as usize].distance_squared(*q) == nodes[*j as usize].distance_squared(*q)
            })
        };
        assert!(
            tied(&grid.nearest_each(queries)),
            "nearest_each is not the nearest"
        );
        assert!(tied(&each));
        each
    }

    /// Near the surface, far from it, outside the nodes' box and at the nodes themselves, the
    /// grid gives the brute force's answers, index for index.
    #[test]
    fn grid_answers_are_the_brute_forces() {
        for k in [3, 17, 60] {
            let nodes = ellipsoid_nodes(k);
            let near: Vec<DVec3> = scattered(4000, k as u64, -1.0, 1.0)
                .iter()
                .zip(nodes.iter().cycle())
                .map(|(e, n)| *n + 0.05 * *e)
                .collect();
            let far = scattered(500, 99, -6.0, 6.0);
            for queries in [near, far, nodes.clone()] {
                assert_eq!(
                    grid_answers(&nodes, &queries),
                    nearest_indices_brute(&nodes, &queries)
                );
            }
        }
    }

    /// Ties go to the lowest index, as in the brute force, for queries the grid settles:
    /// repeated nodes, a query equidistant from several; nodes all in one plane, on one line or
    /// at one point give the brute force's answers too.
    #[test]
    fn ties_and_degenerate_nodes_give_the_brute_forces_answers() {
        let mut nodes = ellipsoid_nodes(9);
        nodes.extend(ellipsoid_nodes(9)); // every node twice
        let near: Vec<DVec3> = scattered(800, 5, -0.1, 0.1)
            .iter()
            .zip(nodes.iter().cycle())
            .map(|(e, n)| *n + *e)
            .collect();
        let answers = grid_answers(&nodes, &near);
        assert_eq!(answers, nearest_indices_brute(&nodes, &near));
        assert!(
            answers.iter().all(|&i| i < 83),
            "a repeated node's second copy answered"
        );
        let queries = scattered(800, 5, -1.5, 1.5);
        let cube: Vec<DVec3> = (0..8)
            .map(|i| DVec3::new((i & 1) as f64, (i >> 1 & 1) as f64, (i >> 2) as f64))
            .collect();
        let centre = [DVec3::splat(0.5)];
        assert_eq!(grid_answers(&cube, &centre), vec![0]);
        let flat: Vec<DVec3> = scattered(300, 8, -1.0, 1.0)
            .iter()
            .map(|p| DVec3::new(p.x, p.y, 0.25))
            .collect();
        let one_point = vec![DVec3::new(3.0, -2.0, 1.0); 5];
        let line: Vec<DVec3> = (0..50)
            .map(|i| DVec3::new(i as f64 * 0.1, 0.0, 0.0))
            .collect();
        for nodes in [flat, one_point, line] {
            assert_eq!(
                grid_answers(&nodes, &queries),
                nearest_indices_brute(&nodes, &queries)
            );
        }
    }

    /// Far from the origin (coordinates of 10⁶ with a spacing of 10⁻²) the answers hold;
    /// non-finite nodes, or nodes too far apart, give no grid.
    #[test]
    fn far_translated_nodes_and_non_finite_input() {
        let shift = DVec3::new(1e6, -2e6, 5e5);
        let nodes: Vec<DVec3> = ellipsoid_nodes(40).iter().map(|p| *p + shift).collect();
        let queries: Vec<DVec3> = scattered(2000, 3, -1.3, 1.3)
            .iter()
            .map(|p| *p + shift)
            .collect();
        assert_eq!(
            grid_answers(&nodes, &queries),
            nearest_indices_brute(&nodes, &queries)
        );
        assert!(NodeGrid::new(&[]).is_none());
        // An extent that overflows: no grid, and the search falls back to the tree.
        let wide = [DVec3::splat(-1e308), DVec3::splat(1e308)];
        assert!(NodeGrid::new(&wide).is_none());
        assert_eq!(nearest_indices(&wide, &[DVec3::splat(1e308)]), vec![1]);
        assert!(NodeGrid::new(&[DVec3::ZERO, DVec3::new(f64::NAN, 0.0, 0.0)]).is_none());
        let grid = NodeGrid::new(&nodes).unwrap();
        assert!((grid.nearest(DVec3::splat(f64::NAN)) as usize) < nodes.len());
    }
}
