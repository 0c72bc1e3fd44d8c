//! The element matrices (Appendix B): bilinear quadrilaterals with 2×2 Gauss–Legendre quadrature
//! (eqs. 48–52) and the caps' right linear triangles with Radau quadrature (eqs. 53–68).

/// Element matrices of one element type: the gradient part ∫∇N_i·∇N_j du and the value part
/// ∫N_i N_j du, so that K^j = w1·grad + w0·mass for any scalar stiffness pair (w0, w1).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ElementMatrices<const N: usize> {
    /// ∫ ∇N_i · ∇N_j du dv over the element (the w1 part).
    pub grad: [[f64; N]; N],
    /// ∫ N_i N_j du dv over the element (the w0 part).
    pub mass: [[f64; N]; N],
}

impl<const N: usize> ElementMatrices<N> {
    /// The element stiffness w1·grad + w0·mass (eq. 47, one displacement component).
    pub fn stiffness(&self, w0: f64, w1: f64) -> [[f64; N]; N] {
        let mut k = [[0.0; N]; N];
        for (i, row) in k.iter_mut().enumerate() {
            for (j, kij) in row.iter_mut().enumerate() {
                *kij = w1 * self.grad[i][j] + w0 * self.mass[i][j];
            }
        }
        k
    }
}

/// 2-point Gauss–Legendre abscissae on [−1, 1] (weights 1): exact for cubics in each direction,
/// hence for every bilinear × bilinear product in the quadrilateral element.
pub const GAUSS_LEGENDRE_2: [f64; 2] = [-0.577_350_269_189_625_8, 0.577_350_269_189_625_8];

/// 3-point Gauss–Legendre rule on [0, 1] as (abscissa, weight).
pub fn gauss_legendre_3_unit() -> [(f64, f64); 3] {
    let r = (0.6_f64).sqrt();
    [
        (0.5 * (1.0 - r), 5.0 / 18.0),
        (0.5, 8.0 / 18.0),
        (0.5 * (1.0 + r), 5.0 / 18.0),
    ]
}

/// 3-point left Gauss–Radau rule on [0, 1] as (abscissa, weight): it includes the end point 0 and
/// is exact for polynomials of degree ≤ 4.
pub fn gauss_radau_3_unit() -> [(f64, f64); 3] {
    let s6 = 6.0_f64.sqrt();
    [
        (0.0, 1.0 / 9.0),
        (0.5 * (1.0 + (1.0 - s6) / 5.0), (16.0 + s6) / 36.0),
        (0.5 * (1.0 + (1.0 + s6) / 5.0), (16.0 - s6) / 36.0),
    ]
}

/// Quadrature points (ξ, η, weight) on the reference triangle {ξ, η ≥ 0, ξ + η ≤ 1}, made by
/// collapsing the unit square (ξ = s(1 − t), η = t, Jacobian 1 − t) with Gauss–Legendre in s and
/// Gauss–Radau in t, whose end point t = 0 sits on the edge opposite the collapsed vertex. Exact for
/// polynomials of total degree ≤ 3, which covers N_i N_j of the linear triangle.
pub fn radau_triangle_rule() -> [(f64, f64, f64); 9] {
    let mut out = [(0.0, 0.0, 0.0); 9];
    let mut n = 0;
    for (t, wt) in gauss_radau_3_unit() {
        for (s, ws) in gauss_legendre_3_unit() {
            out[n] = (s * (1.0 - t), t, ws * wt * (1.0 - t));
            n += 1;
        }
    }
    out
}

/// Element matrices of the bilinear quadrilateral of size a × b in (u, v) (eqs. 48–52), nodes in
/// the order (ξ_i, η_i) = (−1, −1), (1, −1), (1, 1), (−1, 1), with ξ along u and η along v.
pub fn quad_element(a: f64, b: f64) -> ElementMatrices<4> {
    const XI: [f64; 4] = [-1.0, 1.0, 1.0, -1.0];
    const ETA: [f64; 4] = [-1.0, -1.0, 1.0, 1.0];
    let mut m = ElementMatrices {
        grad: [[0.0; 4]; 4],
        mass: [[0.0; 4]; 4],
    };
    let jac = a * b / 4.0; // eq. (52)
    for &xi in &GAUSS_LEGENDRE_2 {
        for &eta in &GAUSS_LEGENDRE_2 {
            let n: [f64; 4] =
                std::array::from_fn(|i| 0.25 * (1.0 + xi * XI[i]) * (1.0 + eta * ETA[i]));
            // eqs. (50), (51)
            let nu: [f64; 4] = std::array::from_fn(|i| XI[i] * (1.0 + eta * ETA[i]) / (2.0 * a));
            let nv: [f64; 4] = std::array::from_fn(|i| (1.0 + xi * XI[i]) * ETA[i] / (2.0 * b));
            for i in 0..4 {
                for j in 0..4 {
                    m.grad[i][j] += jac * (nu[i] * nu[j] + nv[i] * nv[j]);
                    m.mass[i][j] += jac * n[i] * n[j];
                }
            }
        }
    }
    m
}

/// Which polar cap a linear triangle belongs to.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Cap {
    /// u = +π/2: shape functions (53–55), N1 = 1 − ξ − η, N2 = ξ, N3 = η; node 2 is the pole.
    North,
    /// u = −π/2: shape functions (61–63), N1 = 1 − ξ, N2 = ξ − η, N3 = η; node 1 is the pole.
    South,
}

/// Element matrices of a polar linear triangle of size a (along u) × b (along v) (eqs. 53–68),
/// integrated with the Radau rule of [`radau_triangle_rule`].
pub fn triangle_element(cap: Cap, a: f64, b: f64) -> ElementMatrices<3> {
    // Shape functions and their constant (u, v) gradients, eqs. (58–59) and (66–67).
    type ShapeFn = fn(f64, f64) -> [f64; 3];
    let (shape, du, dv): (ShapeFn, [f64; 3], [f64; 3]) = match cap {
        Cap::North => (
            |x, e| [1.0 - x - e, x, e],
            [-1.0 / a, 1.0 / a, 0.0],
            [-1.0 / b, 0.0, 1.0 / b],
        ),
        Cap::South => (
            |x, e| [1.0 - x, x - e, e],
            [-1.0 / a, 1.0 / a, 0.0],
            [0.0, -1.0 / b, 1.0 / b],
        ),
    };
    let mut m = ElementMatrices {
        grad: [[0.0; 3]; 3],
        mass: [[0.0; 3]; 3],
    };
    for (p, q, w) in radau_triangle_rule() {
        // The north element is the reference triangle itself (eq. 60). The south element
        // (eq. 68, misprinted) is {0 ≤ η ≤ ξ ≤ 1}, the image of the reference triangle under
        // (ξ, η) = (1 − p, q) with unit |Jacobian|; both have area ab/2.
        let (xi, eta) = match cap {
            Cap::North => (p, q),
            Cap::South => (1.0 - p, q),
        };
        let n = shape(xi, eta);
        let jac = a * b * w;
        for i in 0..3 {
            for j in 0..3 {
                m.grad[i][j] += jac * (du[i] * du[j] + dv[i] * dv[j]);
                m.mass[i][j] += jac * n[i] * n[j];
            }
        }
    }
    m
}
