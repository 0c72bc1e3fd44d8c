//! A cloud cut into small connected patches of about equal size, and which patches touch: the
//! pieces a whole object's parts are assembled from ([`super::merge`]).
//!
//! The patches are the geodesic Voronoi cells of seeds spread by farthest-point sampling: every
//! point belongs to the seed nearest it along the cloud's neighbourhood graph (edges as long as
//! the distance between their points). A cell grows only over the surface, so it never reaches
//! across a gap between two limbs that lie close in space, and each cell is connected. The graph
//! of separate pieces of surface (a model made of several shells) is first joined where the
//! pieces come nearest, so that every pair of touching shells can still be judged as one part.

use crate::model::nearest::kd_tree;
use glam::DVec3;
use kiddo::SquaredEuclidean;
use std::cmp::Ordering;
use std::collections::BinaryHeap;
use std::num::NonZeroUsize;

/// Neighbours each point is joined to.
pub const NEIGHBOURS: usize = 10;

/// Each point's neighbours (its [`NEIGHBOURS`] nearest, symmetrised), without duplicates; empty
/// for no points.
pub fn neighbourhood_graph(points: &[DVec3]) -> Vec<Vec<usize>> {
    let (Some(tree), Some(k)) = (
        kd_tree(points),
        NonZeroUsize::new((NEIGHBOURS + 1).min(points.len())),
    ) else {
        return Vec::new();
    };
    let mut graph: Vec<Vec<usize>> = vec![Vec::new(); points.len()];
    for (i, p) in points.iter().enumerate() {
        for r in tree
            .query(&p.to_array())
            .nearest_n::<SquaredEuclidean<f64>>(k)
            .execute()
        {
            let j = r.item as usize;
            if j != i {
                graph[i].push(j);
                graph[j].push(i);
            }
        }
    }
    for a in &mut graph {
        a.sort_unstable();
        a.dedup();
    }
    graph
}

/// `graph` (each point's neighbours, symmetric) joined into one connected graph: each connected
/// component but the largest gets an edge from its point nearest to the rest of the points to
/// that nearest point, smallest components first, until one component is left.
pub fn connect(points: &[DVec3], graph: &mut [Vec<usize>]) {
    loop {
        let (label, count) = components(graph);
        if count <= 1 {
            return;
        }
        let mut size = vec![0usize; count];
        for &l in &label {
            size[l] += 1;
        }
        // The smallest component, joined to the nearest point outside it.
        let Some(c) = (0..count).min_by_key(|&c| (size[c], c)) else {
            return;
        };
        let outside: Vec<usize> = (0..points.len()).filter(|&i| label[i] != c).collect();
        let rest: Vec<DVec3> = outside.iter().map(|&i| points[i]).collect();
        let Some(tree) = kd_tree(&rest) else { return };
        let best = (0..points.len())
            .filter(|&i| label[i] == c)
            .map(|i| {
                let n = tree
                    .query(&points[i].to_array())
                    .nearest_one::<SquaredEuclidean<f64>>()
                    .execute();
                (n.distance, i, outside[n.item as usize])
            })
            .min_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        let Some((_, i, j)) = best else { return };
        graph[i].push(j);
        graph[j].push(i);
    }
}

/// The connected sets of the nodes of `graph` where `mask` holds (each a list of nodes, in
/// order), in the order of their lowest node.
pub fn components_where(graph: &[Vec<usize>], mask: &[bool]) -> Vec<Vec<usize>> {
    let mut seen = vec![false; graph.len()];
    let mut out = Vec::new();
    let mut stack = Vec::new();
    for start in 0..graph.len() {
        if !mask[start] || seen[start] {
            continue;
        }
        seen[start] = true;
        stack.push(start);
        let mut set = Vec::new();
        while let Some(v) = stack.pop() {
            set.push(v);
            for &u in &graph[v] {
                if mask[u] && !seen[u] {
                    seen[u] = true;
                    stack.push(u);
                }
            }
        }
        set.sort_unstable();
        out.push(set);
    }
    out
}

/// Each node's connected component in `graph`, and how many there are.
fn components(graph: &[Vec<usize>]) -> (Vec<usize>, usize) {
    let mut label = vec![usize::MAX; graph.len()];
    let mut count = 0;
    let mut stack = Vec::new();
    for start in 0..graph.len() {
        if label[start] != usize::MAX {
            continue;
        }
        label[start] = count;
        stack.push(start);
        while let Some(v) = stack.pop() {
            for &u in &graph[v] {
                if label[u] == usize::MAX {
                    label[u] = count;
                    stack.push(u);
                }
            }
        }
        count += 1;
    }
    (label, count)
}

/// A point on the Dijkstra frontier: its distance, the point and its seed.
#[derive(PartialEq)]
struct Front(f64, usize, usize);

impl Eq for Front {}

impl Ord for Front {
    fn cmp(&self, other: &Self) -> Ordering {
        // Least distance first (BinaryHeap is a max-heap); ties by point, for determinism.
        other
            .0
            .total_cmp(&self.0)
            .then_with(|| other.1.cmp(&self.1))
    }
}

impl PartialOrd for Front {
    fn partial_cmp(&self, other: &Self) -> Option<Ordering> {
        Some(self.cmp(other))
    }
}

/// The patch of each point (module docs): `count` seeds by farthest-point sampling from the
/// point farthest from the centroid, then each point given to the seed nearest along `graph`
/// (connected: [`connect`]). Patch numbers are the seeds' order; a point the graph does not
/// reach from any seed gets the patch of the nearest seed in space.
pub fn patches(points: &[DVec3], graph: &[Vec<usize>], count: usize) -> Vec<usize> {
    let n = points.len();
    if n == 0 {
        return Vec::new();
    }
    let count = count.clamp(1, n);
    let centroid = points.iter().copied().sum::<DVec3>() / n as f64;
    let mut far = vec![f64::INFINITY; n];
    let mut seeds = Vec::with_capacity(count);
    let mut next = (0..n)
        .max_by(|&a, &b| {
            points[a]
                .distance_squared(centroid)
                .total_cmp(&points[b].distance_squared(centroid))
                .then(b.cmp(&a))
        })
        .unwrap_or(0);
    while seeds.len() < count {
        seeds.push(next);
        let s = points[next];
        for (f, p) in far.iter_mut().zip(points) {
            *f = f.min(p.distance_squared(s));
        }
        next = (0..n)
            .max_by(|&a, &b| far[a].total_cmp(&far[b]).then(b.cmp(&a)))
            .unwrap_or(0);
        if far[next] == 0.0 {
            break;
        }
    }
    let mut label = vec![usize::MAX; n];
    let mut dist = vec![f64::INFINITY; n];
    let mut heap = BinaryHeap::new();
    for (k, &s) in seeds.iter().enumerate() {
        dist[s] = 0.0;
        heap.push(Front(0.0, s, k));
    }
    while let Some(Front(d, v, k)) = heap.pop() {
        if label[v] != usize::MAX {
            continue;
        }
        label[v] = k;
        for &u in &graph[v] {
            let du = d + points[u].distance(points[v]);
            if label[u] == usize::MAX && du < dist[u] {
                dist[u] = du;
                heap.push(Front(du, u, k));
            }
        }
    }
    for i in 0..n {
        if label[i] == usize::MAX {
            label[i] = (0..seeds.len())
                .min_by(|&a, &b| {
                    points[seeds[a]]
                        .distance_squared(points[i])
                        .total_cmp(&points[seeds[b]].distance_squared(points[i]))
                })
                .unwrap_or(0);
        }
    }
    label
}

/// Which of `count` patches touch: for each patch, its neighbours and how many graph edges join
/// them, in patch order.
pub fn adjacency(graph: &[Vec<usize>], label: &[usize], count: usize) -> Vec<Vec<(usize, usize)>> {
    let mut joins = vec![std::collections::BTreeMap::<usize, usize>::new(); count];
    for (i, near) in graph.iter().enumerate() {
        for &j in near {
            let (a, b) = (label[i], label[j]);
            if a != b {
                *joins[a].entry(b).or_insert(0) += 1;
            }
        }
    }
    joins.into_iter().map(|m| m.into_iter().collect()).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Two parallel lines of points 0.05 apart along each, 0.6 apart across.
    fn two_lines() -> Vec<DVec3> {
        let mut p: Vec<DVec3> = (0..100)
            .map(|i| DVec3::new(i as f64 * 0.05, 0.0, 0.0))
            .collect();
        p.extend((0..100).map(|i| DVec3::new(i as f64 * 0.05, 0.6, 0.0)));
        p
    }

    #[test]
    fn patches_grow_along_the_surface_not_across_a_gap() {
        let points = two_lines();
        let mut graph = neighbourhood_graph(&points);
        // The 10 nearest of a point lie on its own line: two components, joined once.
        assert_eq!(components(&graph).1, 2);
        connect(&points, &mut graph);
        assert_eq!(components(&graph).1, 1);
        let label = patches(&points, &graph, 8);
        assert_eq!(label.len(), 200);
        let used: std::collections::BTreeSet<usize> = label.iter().copied().collect();
        assert_eq!(used.len(), 8);
        // No patch holds points of both lines but where the lines were joined.
        let mixed = (0..8)
            .filter(|&k| {
                let on = |y: f64| (0..200).any(|i| label[i] == k && points[i].y == y);
                on(0.0) && on(0.6)
            })
            .count();
        assert!(mixed <= 1, "{mixed} patches cross the gap");
        // Patches are about equal: none more than three times the mean.
        for k in 0..8 {
            let size = label.iter().filter(|&&l| l == k).count();
            assert!((5..=75).contains(&size), "patch {k}: {size}");
        }
        let adj = adjacency(&graph, &label, 8);
        // A chain along each line: every patch touches one to three others.
        assert!(adj.iter().all(|a| (1..=3).contains(&a.len())), "{adj:?}");
        for (k, a) in adj.iter().enumerate() {
            for &(j, edges) in a {
                assert!(edges > 0 && adj[j].iter().any(|&(i, e)| i == k && e == edges));
            }
        }
    }
}
