//! Spectral bisection of a cloud: the cut of its neighbourhood graph with the least normalised
//! cut (Shi & Malik 2000), found by sweeping the graph's Fiedler vector. A part of an object
//! meets the rest at a narrow neck (a leg's hip, a head's neck, an ear's base), and the
//! normalised cut is least across the narrowest neck that leaves two sizeable sides.
//!
//! The graph joins each point to its [`NEIGHBOURS`] nearest (symmetrised, unit weights). The
//! Fiedler vector is the second eigenvector of D^{-1/2} W D^{-1/2}, found by Lanczos iteration
//! with full reorthogonalisation against the trivial eigenvector D^{1/2} 1 and the Krylov basis,
//! from the points' coordinate along their principal axis (deterministic).

use crate::model::forces::nearest::kd_tree;
use crate::model::init::principal_frame;
use glam::DVec3;
use kiddo::SquaredEuclidean;
use std::num::NonZeroUsize;

/// Neighbours each point is joined to.
pub const NEIGHBOURS: usize = 10;

/// Lanczos steps, at most.
const LANCZOS_STEPS: usize = 160;

/// The two sides of the least normalised cut of the neighbourhood graph `graph` of `points`
/// ([`neighbourhood_graph`]; `true`: the second side), or `None` for fewer than three points.
pub fn bisect_graph(points: &[DVec3], graph: &[Vec<usize>]) -> Option<Vec<bool>> {
    let n = points.len();
    if n < 3 {
        return None;
    }
    let degree: Vec<f64> = graph.iter().map(|a| a.len() as f64).collect();
    let fiedler = fiedler_vector(points, graph, &degree);
    // The partition vector is D^{-1/2} f; sweep its order for the least normalised cut.
    let value: Vec<f64> = fiedler
        .iter()
        .zip(&degree)
        .map(|(f, d)| f / d.sqrt())
        .collect();
    let mut order: Vec<usize> = (0..n).collect();
    order.sort_by(|&a, &b| value[a].total_cmp(&value[b]).then(a.cmp(&b)));
    let total: f64 = degree.iter().sum();
    let mut side = vec![false; n];
    let (mut cut, mut volume) = (0.0, 0.0);
    let mut best = (f64::INFINITY, 0);
    for (rank, &v) in order.iter().enumerate().take(n - 1) {
        let into = graph[v].iter().filter(|&&u| side[u]).count() as f64;
        cut += degree[v] - 2.0 * into;
        volume += degree[v];
        side[v] = true;
        let ncut = cut / volume + cut / (total - volume);
        if ncut < best.0 {
            best = (ncut, rank + 1);
        }
    }
    let mut out = vec![false; n];
    for &v in &order[best.1..] {
        out[v] = true;
    }
    Some(out)
}

/// The largest connected set of the nodes of `graph` where `mask` holds (`true` on it), or
/// `None` when no node is masked. Ties go to the set with the lowest node.
pub fn largest_component(graph: &[Vec<usize>], mask: &[bool]) -> Option<Vec<bool>> {
    let mut label = vec![usize::MAX; graph.len()];
    let mut best: Option<(usize, usize)> = None;
    let mut stack = Vec::new();
    let mut count = 0;
    for start in 0..graph.len() {
        if !mask[start] || label[start] != usize::MAX {
            continue;
        }
        let id = count;
        count += 1;
        let mut size = 0;
        label[start] = id;
        stack.push(start);
        while let Some(v) = stack.pop() {
            size += 1;
            for &u in &graph[v] {
                if mask[u] && label[u] == usize::MAX {
                    label[u] = id;
                    stack.push(u);
                }
            }
        }
        if best.is_none_or(|(_, s)| size > s) {
            best = Some((id, size));
        }
    }
    let (id, _) = best?;
    Some(label.iter().map(|&l| l == id).collect())
}

/// Each point's neighbours (symmetrised k-nearest), without duplicates.
pub fn neighbourhood_graph(points: &[DVec3]) -> Option<Vec<Vec<usize>>> {
    let tree = kd_tree(points)?;
    let k = NonZeroUsize::new((NEIGHBOURS + 1).min(points.len()))?;
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
    Some(graph)
}

/// The second eigenvector of A = D^{-1/2} W D^{-1/2} (module docs).
fn fiedler_vector(points: &[DVec3], graph: &[Vec<usize>], degree: &[f64]) -> Vec<f64> {
    let n = points.len();
    let sqrt_d: Vec<f64> = degree.iter().map(|d| d.sqrt()).collect();
    let trivial_norm = sqrt_d.iter().map(|x| x * x).sum::<f64>().sqrt();
    let trivial: Vec<f64> = sqrt_d.iter().map(|x| x / trivial_norm).collect();
    let apply = |x: &[f64], out: &mut [f64]| {
        for (i, o) in out.iter_mut().enumerate() {
            *o = graph[i].iter().map(|&j| x[j] / sqrt_d[j]).sum::<f64>() / sqrt_d[i];
        }
    };
    let axis = principal_frame(points).col(0);
    let centroid = points.iter().copied().sum::<DVec3>() / n as f64;
    let mut q: Vec<f64> = points
        .iter()
        .enumerate()
        .map(|(i, p)| (p - centroid).dot(axis) + 1e-3 * ((i * 7919 % 1009) as f64 / 1009.0))
        .collect();
    let mut basis: Vec<Vec<f64>> = Vec::new();
    let (mut alpha, mut beta) = (Vec::new(), Vec::new());
    let mut w = vec![0.0; n];
    let steps = LANCZOS_STEPS.min(n - 1);
    for _ in 0..steps {
        orthogonalise(&mut q, std::iter::once(&trivial).chain(&basis));
        let norm = dot(&q, &q).sqrt();
        if !(norm > 1e-12) {
            break;
        }
        q.iter_mut().for_each(|x| *x /= norm);
        if !basis.is_empty() {
            beta.push(norm);
        }
        apply(&q, &mut w);
        alpha.push(dot(&q, &w));
        basis.push(std::mem::replace(&mut q, w.clone()));
    }
    let m = basis.len();
    let (_, top) = top_eigenpair(&alpha[..m], &beta[..m.saturating_sub(1)]);
    let mut f = vec![0.0; n];
    for (k, b) in basis.iter().enumerate() {
        let c = top[k];
        f.iter_mut().zip(b).for_each(|(x, y)| *x += c * y);
    }
    f
}

fn dot(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

/// Removes from `q` its components along each of `against` (unit vectors), twice over.
fn orthogonalise<'a>(q: &mut [f64], against: impl Iterator<Item = &'a Vec<f64>> + Clone) {
    for _ in 0..2 {
        for v in against.clone() {
            let c = dot(q, v);
            q.iter_mut().zip(v).for_each(|(x, y)| *x -= c * y);
        }
    }
}

/// How many eigenvalues of the symmetric tridiagonal matrix (diagonal `alpha`, off-diagonal
/// `beta`) lie below `x` (Sturm's count).
fn count_below(alpha: &[f64], beta: &[f64], x: f64) -> usize {
    let mut count = 0;
    let mut d = 1.0;
    for i in 0..alpha.len() {
        let b2 = if i == 0 {
            0.0
        } else {
            beta[i - 1] * beta[i - 1]
        };
        d = alpha[i] - x - b2 / d;
        if d == 0.0 {
            d = -1e-300;
        }
        if d < 0.0 {
            count += 1;
        }
    }
    count
}

/// The largest eigenvalue of the symmetric tridiagonal matrix (diagonal `alpha`, off-diagonal
/// `beta`) and its unit eigenvector: the value by bisection on Sturm's count, the vector by
/// inverse iteration.
fn top_eigenpair(alpha: &[f64], beta: &[f64]) -> (f64, Vec<f64>) {
    let m = alpha.len();
    if m == 0 {
        return (0.0, Vec::new());
    }
    let radius = |i: usize| {
        (if i > 0 { beta[i - 1].abs() } else { 0.0 })
            + (if i + 1 < m { beta[i].abs() } else { 0.0 })
    };
    let (mut lo, mut hi) = (0..m).fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), i| {
        (lo.min(alpha[i] - radius(i)), hi.max(alpha[i] + radius(i)))
    });
    for _ in 0..200 {
        let mid = 0.5 * (lo + hi);
        if mid <= lo || mid >= hi {
            break;
        }
        if count_below(alpha, beta, mid) == m {
            hi = mid;
        } else {
            lo = mid;
        }
    }
    let lambda = hi + 1e-10 * (1.0 + hi.abs());
    // Inverse iteration: (T − λ) y = x by the Thomas algorithm, three times.
    let mut x = vec![1.0 / (m as f64).sqrt(); m];
    for _ in 0..3 {
        let mut c = vec![0.0; m];
        let mut d = vec![0.0; m];
        for i in 0..m {
            let sub = if i > 0 { beta[i - 1] } else { 0.0 };
            let mut denom = alpha[i] - lambda - sub * if i > 0 { c[i - 1] } else { 0.0 };
            if denom.abs() < 1e-300 {
                denom = -1e-300;
            }
            c[i] = if i + 1 < m { beta[i] / denom } else { 0.0 };
            d[i] = (x[i] - sub * if i > 0 { d[i - 1] } else { 0.0 }) / denom;
        }
        for i in (0..m).rev() {
            x[i] = d[i] - if i + 1 < m { c[i] * x[i + 1] } else { 0.0 };
        }
        let norm = dot(&x, &x).sqrt();
        if !(norm > 0.0 && norm.is_finite()) {
            break;
        }
        x.iter_mut().for_each(|v| *v /= norm);
    }
    (hi, x)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn two_blobs_joined_by_a_thin_neck_are_cut_at_the_neck() {
        // Two dense grids joined by a narrow strip: the cut falls on the strip.
        let mut points = Vec::new();
        for i in 0..20 {
            for j in 0..20 {
                points.push(DVec3::new(i as f64 * 0.1, j as f64 * 0.1, 0.0));
                points.push(DVec3::new(4.0 + i as f64 * 0.1, j as f64 * 0.1, 0.0));
            }
        }
        for i in 0..20 {
            points.push(DVec3::new(2.0 + i as f64 * 0.1, 1.0, 0.0));
        }
        let graph = neighbourhood_graph(&points).expect("graph");
        let side = bisect_graph(&points, &graph).expect("bisect");
        let left = points.iter().zip(&side).filter(|(p, _)| p.x < 1.95);
        let right = points.iter().zip(&side).filter(|(p, _)| p.x > 4.0);
        let l: Vec<bool> = left.map(|(_, s)| *s).collect();
        let r: Vec<bool> = right.map(|(_, s)| *s).collect();
        assert!(l.iter().all(|&s| s == l[0]), "left blob split");
        assert!(r.iter().all(|&s| s == r[0]), "right blob split");
        assert_ne!(l[0], r[0]);
    }

    #[test]
    fn the_top_eigenpair_of_a_tridiagonal_matrix_is_found() {
        // diag 2, off-diagonal 1, size 5: eigenvalues 2 + 2 cos(kπ/6), the top 2 + √3, its
        // vector sin(iπ/6) (i = 1..5), normalised.
        let (value, vector) = top_eigenpair(&[2.0; 5], &[1.0; 4]);
        assert!((value - (2.0 + 3f64.sqrt())).abs() < 1e-9, "{value}");
        let truth: Vec<f64> = (1..=5)
            .map(|i| (i as f64 * std::f64::consts::PI / 6.0).sin())
            .collect();
        let norm = dot(&truth, &truth).sqrt();
        let sign = vector[0].signum();
        for (v, t) in vector.iter().zip(&truth) {
            assert!((sign * v - t / norm).abs() < 1e-8, "{vector:?}");
        }
        assert_eq!(count_below(&[2.0; 5], &[1.0; 4], 2.5), 3);
    }
}
