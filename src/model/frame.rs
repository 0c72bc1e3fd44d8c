//! The rigid model frame: x = c + R p (eq. 2) with R from a unit quaternion (eq. 16), and the
//! rotational Jacobian B = −R p̃ G (eqs. 17–19).
//!
//! The paper's quaternion is [s, v] with scalar s first; glam's [`DQuat`] stores (x, y, z, w) with
//! the scalar last. [`quat_to_paper`] and [`quat_from_paper`] convert, so q_θ = (s, v1, v2, v3).

use glam::{DMat3, DQuat, DVec3, DVec4};

/// q_θ in the paper's order (s, v1, v2, v3).
pub fn quat_to_paper(q: DQuat) -> [f64; 4] {
    [q.w, q.x, q.y, q.z]
}

/// A glam quaternion from q_θ in the paper's order (s, v1, v2, v3).
pub fn quat_from_paper(q: [f64; 4]) -> DQuat {
    DQuat::from_xyzw(q[1], q[2], q[3], q[0])
}

/// The rotation matrix R of eq. (16) for a unit quaternion [s, v].
pub fn rotation_matrix(q: DQuat) -> DMat3 {
    let (s, v1, v2, v3) = (q.w, q.x, q.y, q.z);
    DMat3::from_cols(
        DVec3::new(
            1.0 - 2.0 * (v2 * v2 + v3 * v3),
            2.0 * (v1 * v2 + s * v3),
            2.0 * (v1 * v3 - s * v2),
        ),
        DVec3::new(
            2.0 * (v1 * v2 - s * v3),
            1.0 - 2.0 * (v1 * v1 + v3 * v3),
            2.0 * (v2 * v3 + s * v1),
        ),
        DVec3::new(
            2.0 * (v1 * v3 + s * v2),
            2.0 * (v2 * v3 - s * v1),
            1.0 - 2.0 * (v1 * v1 + v2 * v2),
        ),
    )
}

/// The dual (cross-product) matrix p̃ of eq. (18): p̃ w = p × w.
pub fn skew(p: DVec3) -> DMat3 {
    DMat3::from_cols(
        DVec3::new(0.0, p.z, -p.y),
        DVec3::new(-p.z, 0.0, p.x),
        DVec3::new(p.y, -p.x, 0.0),
    )
}

/// The 3×4 matrix G of eq. (19), as four columns, mapping q̇_θ to the body angular velocity
/// ω = G q̇_θ = 2 (s v̇ − ṡ v − v × v̇). Its columns are orthogonal to q_θ: G q_θ = 0.
pub fn g_matrix(q: DQuat) -> [DVec3; 4] {
    let (s, v1, v2, v3) = (q.w, q.x, q.y, q.z);
    [
        2.0 * DVec3::new(-v1, -v2, -v3),
        2.0 * DVec3::new(s, -v3, v2),
        2.0 * DVec3::new(v3, s, -v1),
        2.0 * DVec3::new(-v2, v1, s),
    ]
}

/// B = −R p̃ G (eq. 17): the four columns ∂x/∂q_θ for the model-frame point p. For a unit
/// quaternion these are exactly the derivatives of c + R(q/|q|) p.
pub fn b_matrix(r: &DMat3, q: DQuat, p: DVec3) -> [DVec3; 4] {
    let g = g_matrix(q);
    // −R p̃ G_j = −R (p × G_j) = R (G_j × p)
    g.map(|gj| *r * gj.cross(p))
}

/// The generalized torque f_θ = Bᵀ f (eq. 33) of a world force f acting at model-frame point p.
pub fn generalized_torque(r: &DMat3, q: DQuat, p: DVec3, f: DVec3) -> DVec4 {
    let b = b_matrix(r, q, p);
    DVec4::new(b[0].dot(f), b[1].dot(f), b[2].dot(f), b[3].dot(f))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn test_quat() -> DQuat {
        DQuat::from_axis_angle(DVec3::new(0.3, -0.5, 0.8).normalize(), 1.1)
    }

    #[test]
    fn rotation_matrix_is_eq_16_and_matches_glam() {
        let q = test_quat();
        let r = rotation_matrix(q);
        let g = DMat3::from_quat(q);
        assert!((r - g).to_cols_array().iter().all(|x| x.abs() < 1e-14));
        assert!((r.determinant() - 1.0).abs() < 1e-14);
    }

    #[test]
    fn skew_is_cross_product() {
        let p = DVec3::new(1.0, -2.0, 0.5);
        let w = DVec3::new(0.3, 0.7, -1.1);
        assert!((skew(p) * w - p.cross(w)).length() < 1e-15);
    }

    #[test]
    fn g_annihilates_the_quaternion() {
        let q = test_quat();
        let gq = g_matrix(q)
            .iter()
            .zip(quat_to_paper(q))
            .fold(DVec3::ZERO, |acc, (col, qi)| acc + *col * qi);
        assert!(gq.length() < 1e-14);
    }

    #[test]
    fn b_matches_central_differences_of_normalized_rotation() {
        let q = test_quat();
        let p = DVec3::new(0.7, -1.3, 0.4);
        let r = rotation_matrix(q);
        let b = b_matrix(&r, q, p);
        let h = 1e-6;
        let x_of = |qa: [f64; 4]| rotation_matrix(quat_from_paper(qa).normalize()) * p;
        for j in 0..4 {
            let mut plus = quat_to_paper(q);
            let mut minus = quat_to_paper(q);
            plus[j] += h;
            minus[j] -= h;
            let fd = (x_of(plus) - x_of(minus)) / (2.0 * h);
            assert!(
                (fd - b[j]).length() < 1e-8,
                "column {j}: {:?} vs {:?}",
                b[j],
                fd
            );
        }
    }

    #[test]
    fn generalized_torque_is_virtual_work_of_rotation() {
        // f_θ · δq_θ equals f · δx for a small rotation δq_θ.
        let q = test_quat();
        let r = rotation_matrix(q);
        let p = DVec3::new(0.2, 0.9, -0.6);
        let f = DVec3::new(1.0, -0.4, 2.0);
        let ft = generalized_torque(&r, q, p, f);
        let h = 1e-6;
        let dq = [0.1, -0.3, 0.2, 0.5];
        let plus: Vec<f64> = quat_to_paper(q)
            .iter()
            .zip(dq)
            .map(|(a, b)| a + h * b)
            .collect();
        let minus: Vec<f64> = quat_to_paper(q)
            .iter()
            .zip(dq)
            .map(|(a, b)| a - h * b)
            .collect();
        let x = |qa: &[f64]| {
            rotation_matrix(quat_from_paper([qa[0], qa[1], qa[2], qa[3]]).normalize()) * p
        };
        let work_fd = f.dot(x(&plus) - x(&minus)) / (2.0 * h);
        let work = ft.dot(DVec4::from_array(dq));
        assert!((work - work_fd).abs() < 1e-8, "{work} vs {work_fd}");
    }
}
