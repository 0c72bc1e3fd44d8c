//! Small dense linear algebra the model needs: a symmetric positive-definite solve for the 13 global
//! degrees of freedom, and the eigen-decomposition of a symmetric 3×3 matrix for moment-based
//! initialisation.

use glam::{DMat3, DVec3};

/// Solves A x = b for a symmetric positive-definite `N×N` matrix by Cholesky factorisation.
/// Returns `None` when A is not numerically positive definite or an input is not finite.
pub fn cholesky_solve<const N: usize>(a: &[[f64; N]; N], b: &[f64; N]) -> Option<[f64; N]> {
    let mut l = [[0.0; N]; N];
    for i in 0..N {
        for j in 0..=i {
            let mut sum = a[i][j];
            for k in 0..j {
                sum -= l[i][k] * l[j][k];
            }
            if i == j {
                if !(sum > 0.0) || !sum.is_finite() {
                    return None;
                }
                l[i][i] = sum.sqrt();
            } else {
                l[i][j] = sum / l[j][j];
            }
        }
    }
    let mut y = [0.0; N];
    for i in 0..N {
        let mut sum = b[i];
        for k in 0..i {
            sum -= l[i][k] * y[k];
        }
        y[i] = sum / l[i][i];
    }
    let mut x = [0.0; N];
    for i in (0..N).rev() {
        let mut sum = y[i];
        for k in i + 1..N {
            sum -= l[k][i] * x[k];
        }
        x[i] = sum / l[i][i];
    }
    x.iter().all(|v| v.is_finite()).then_some(x)
}

/// Eigen-decomposition of a symmetric 3×3 matrix by cyclic Jacobi rotations. Returns the
/// eigenvalues in ascending order and the matching unit eigenvectors as the columns of a proper
/// rotation (determinant +1).
pub fn symmetric_eigen3(m: &DMat3) -> (DVec3, DMat3) {
    let mut a = m.to_cols_array_2d(); // a[col][row]; symmetric, so a[i][j] = a[j][i]
    let mut v = DMat3::IDENTITY.to_cols_array_2d();
    for _sweep in 0..50 {
        let off = a[0][1].powi(2) + a[0][2].powi(2) + a[1][2].powi(2);
        let scale = a[0][0].powi(2) + a[1][1].powi(2) + a[2][2].powi(2);
        if off <= 1e-30 * scale.max(f64::MIN_POSITIVE) {
            break;
        }
        for (p, q) in [(0, 1), (0, 2), (1, 2)] {
            if a[p][q].abs() < 1e-300 {
                continue;
            }
            let theta = (a[q][q] - a[p][p]) / (2.0 * a[p][q]);
            let t = theta.signum() / (theta.abs() + (theta * theta + 1.0).sqrt());
            let t = if theta == 0.0 { 1.0 } else { t };
            let c = 1.0 / (t * t + 1.0).sqrt();
            let s = t * c;
            // A ← Jᵀ A J with the rotation J in the (p, q) plane.
            for k in 0..3 {
                let (akp, akq) = (a[k][p], a[k][q]);
                a[k][p] = c * akp - s * akq;
                a[k][q] = s * akp + c * akq;
            }
            for k in 0..3 {
                let (apk, aqk) = (a[p][k], a[q][k]);
                a[p][k] = c * apk - s * aqk;
                a[q][k] = s * apk + c * aqk;
            }
            for k in 0..3 {
                let (vkp, vkq) = (v[p][k], v[q][k]);
                v[p][k] = c * vkp - s * vkq;
                v[q][k] = s * vkp + c * vkq;
            }
        }
    }
    let mut pairs: Vec<(f64, DVec3)> = (0..3).map(|i| (a[i][i], DVec3::from_array(v[i]))).collect();
    pairs.sort_by(|x, y| x.0.total_cmp(&y.0));
    let (e0, e1) = (pairs[0].1.normalize(), pairs[1].1.normalize());
    let e2 = e0.cross(e1);
    (
        DVec3::new(pairs[0].0, pairs[1].0, pairs[2].0),
        DMat3::from_cols(e0, e1, e2),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cholesky_solves_spd_system() {
        let a = [[4.0, 1.0, 0.5], [1.0, 3.0, -0.2], [0.5, -0.2, 2.0]];
        let b = [1.0, -2.0, 0.5];
        let x = cholesky_solve(&a, &b).expect("SPD");
        for i in 0..3 {
            let r: f64 = (0..3).map(|j| a[i][j] * x[j]).sum::<f64>() - b[i];
            assert!(r.abs() < 1e-14);
        }
        assert!(cholesky_solve(&[[1.0, 2.0], [2.0, 1.0]], &[1.0, 1.0]).is_none());
        assert!(cholesky_solve(&[[f64::NAN]], &[1.0]).is_none());
    }

    #[test]
    fn eigen3_diagonalises() {
        let r = DMat3::from_quat(glam::DQuat::from_axis_angle(
            DVec3::new(1.0, 2.0, -0.5).normalize(),
            0.8,
        ));
        let d = DMat3::from_diagonal(DVec3::new(3.0, 0.5, 1.7));
        let m = r * d * r.transpose();
        let (vals, vecs) = symmetric_eigen3(&m);
        assert!(
            (vals - DVec3::new(0.5, 1.7, 3.0)).length() < 1e-12,
            "{vals:?}"
        );
        assert!((vecs.determinant() - 1.0).abs() < 1e-12);
        for i in 0..3 {
            let e = vecs.col(i);
            assert!((m * e - vals[i] * e).length() < 1e-12);
        }
    }
}
