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

/// The two sides of the least normalised cut of `points`' neighbourhood graph (`true`: the
/// second side), or `None` for fewer than three points.
pub fn bisect(points: &[DVec3]) -> Option<Vec<bool>> {
    let n = points.len();
    if n < 3 {
        return None;
    }
    let graph = neighbourhood_graph(points)?;
    let degree: Vec<f64> = graph.iter().map(|a| a.len() as f64).collect();
    let fiedler = fiedler_vector(points, &graph, &degree);
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

/// Each point's neighbours (symmetrised k-nearest), without duplicates.
fn neighbourhood_graph(points: &[DVec3]) -> Option<Vec<Vec<usize>>> {
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
    let mut t = vec![vec![0.0; m]; m];
    for i in 0..m {
        t[i][i] = alpha[i];
        if i + 1 < m {
            t[i][i + 1] = beta[i];
            t[i + 1][i] = beta[i];
        }
    }
    let (values, vectors) = jacobi_eigen(t);
    let top = (0..m)
        .max_by(|&a, &b| values[a].total_cmp(&values[b]))
        .unwrap_or(0);
    let mut f = vec![0.0; n];
    for (k, b) in basis.iter().enumerate() {
        let c = vectors[k][top];
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

/// The eigenvalues and eigenvectors (columns: `vectors[i][k]` is component i of vector k) of the
/// symmetric matrix `a`, by cyclic Jacobi rotations.
fn jacobi_eigen(mut a: Vec<Vec<f64>>) -> (Vec<f64>, Vec<Vec<f64>>) {
    let m = a.len();
    let mut v = vec![vec![0.0; m]; m];
    for (i, row) in v.iter_mut().enumerate() {
        row[i] = 1.0;
    }
    for _ in 0..50 {
        let off: f64 = (0..m)
            .flat_map(|i| (0..m).filter(move |&j| j != i).map(move |j| (i, j)))
            .map(|(i, j)| a[i][j] * a[i][j])
            .sum();
        if off < 1e-22 {
            break;
        }
        for p in 0..m {
            for q in p + 1..m {
                if a[p][q].abs() < 1e-300 {
                    continue;
                }
                let theta = (a[q][q] - a[p][p]) / (2.0 * a[p][q]);
                let t = theta.signum() / (theta.abs() + (theta * theta + 1.0).sqrt());
                let t = if theta == 0.0 { 1.0 } else { t };
                let c = 1.0 / (t * t + 1.0).sqrt();
                let s = t * c;
                for k in 0..m {
                    let (akp, akq) = (a[k][p], a[k][q]);
                    a[k][p] = c * akp - s * akq;
                    a[k][q] = s * akp + c * akq;
                }
                for k in 0..m {
                    let (apk, aqk) = (a[p][k], a[q][k]);
                    a[p][k] = c * apk - s * aqk;
                    a[q][k] = s * apk + c * aqk;
                }
                for row in v.iter_mut() {
                    let (vp, vq) = (row[p], row[q]);
                    row[p] = c * vp - s * vq;
                    row[q] = s * vp + c * vq;
                }
            }
        }
    }
    ((0..m).map(|i| a[i][i]).collect(), v)
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
        let side = bisect(&points).expect("bisect");
        let left = points.iter().zip(&side).filter(|(p, _)| p.x < 1.95);
        let right = points.iter().zip(&side).filter(|(p, _)| p.x > 4.0);
        let l: Vec<bool> = left.map(|(_, s)| *s).collect();
        let r: Vec<bool> = right.map(|(_, s)| *s).collect();
        assert!(l.iter().all(|&s| s == l[0]), "left blob split");
        assert!(r.iter().all(|&s| s == r[0]), "right blob split");
        assert_ne!(l[0], r[0]);
    }

    #[test]
    fn jacobi_diagonalises_a_symmetric_matrix() {
        let a = vec![
            vec![2.0, 1.0, 0.0],
            vec![1.0, 2.0, 1.0],
            vec![0.0, 1.0, 2.0],
        ];
        let (values, vectors) = jacobi_eigen(a.clone());
        for k in 0..3 {
            for i in 0..3 {
                let av: f64 = (0..3).map(|j| a[i][j] * vectors[j][k]).sum();
                assert!((av - values[k] * vectors[i][k]).abs() < 1e-10);
            }
        }
        let mut sorted = values.clone();
        sorted.sort_by(f64::total_cmp);
        let r2 = 2f64.sqrt();
        for (s, e) in sorted.iter().zip([2.0 - r2, 2.0, 2.0 + r2]) {
            assert!((s - e).abs() < 1e-10, "{sorted:?}");
        }
    }
}
