//! The superquadric ellipsoid reference shape s(u; q_s) (eq. 4) and its Jacobian J = ∂s/∂q_s (eq. 9).
//!
//! The printed eq. (10) is wrong in its ε columns: it shows ε1·C^(ε1−1), which is neither ∂/∂ε nor
//! dimensionally consistent. Here every column is derived from eq. (4):
//!
//! ```text
//! s  = a (a1 Cu^ε1 Cv^ε2,  a2 Cu^ε1 Sv^ε2,  a3 Su^ε1)
//! ∂s/∂ε1 = a (a1 Cu^ε1 Cv^ε2 ln|cos u|,  a2 Cu^ε1 Sv^ε2 ln|cos u|,  a3 Su^ε1 ln|sin u|)
//! ∂s/∂ε2 = a (a1 Cu^ε1 Cv^ε2 ln|cos v|,  a2 Cu^ε1 Sv^ε2 ln|sin v|,  0)
//! ```
//!
//! because ∂/∂ε [sgn(c)|c|^ε] = sgn(c)|c|^ε ln|c|, which tends to 0 as |c| → 0 for ε > 0.
//! `tests` checks every column against central differences.

use glam::DVec3;

/// Lower bound kept on each aspect ratio a_i (eq. 4 allows 0 ≤ a_i ≤ 1; 0 collapses the shape).
pub const MIN_ASPECT: f64 = 1e-3;
/// Lower bound the dynamics keep on the squareness exponents ε1, ε2 (ε → 0 is a box with infinite
/// curvature). Below it eq. (4) crowds a flat face into a sliver of (u, v) at the pole — for ε1 =
/// 0.05 the inner half of a flat cap lies within 10⁻⁶ rad of u = π/2 — and the data's points of
/// influence cannot migrate onto it. A shape may hold an exponent down to [`LEAST_EPSILON`]: the
/// squareness extension of a pure superquadric fit (`fit::extend_squareness`) sets one there, and
/// the dynamics then keep it ([`SuperquadricParams::normalized_keeping`]).
pub const MIN_EPSILON: f64 = 0.1;
/// Least squareness exponent a shape may hold (scenes accept [`LEAST_EPSILON`, `MAX_EPSILON`]):
/// below [`MIN_EPSILON`] only where it was set, never moved there by the dynamics.
pub const LEAST_EPSILON: f64 = 0.01;
/// Upper bound kept on the squareness exponents ε1, ε2 (ε > 2 gives concave, pinched shapes).
pub const MAX_EPSILON: f64 = 2.0;

/// The global deformation coordinates q_s = (a, a1, a2, a3, ε1, ε2) of eq. (5).
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SuperquadricParams {
    /// Scale a ≥ 0.
    pub a: f64,
    /// Aspect ratio along the model's x axis, 0 < a1 ≤ 1.
    pub a1: f64,
    /// Aspect ratio along the model's y axis, 0 < a2 ≤ 1.
    pub a2: f64,
    /// Aspect ratio along the model's z axis, 0 < a3 ≤ 1.
    pub a3: f64,
    /// Squareness ε1 along the latitude u (the z profile).
    pub e1: f64,
    /// Squareness ε2 along the longitude v (the x–y cross-section).
    pub e2: f64,
}

impl Default for SuperquadricParams {
    /// A unit sphere: a = 1, a_i = 1, ε1 = ε2 = 1.
    fn default() -> Self {
        Self {
            a: 1.0,
            a1: 1.0,
            a2: 1.0,
            a3: 1.0,
            e1: 1.0,
            e2: 1.0,
        }
    }
}

/// Number of global deformation coordinates in q_s.
pub const NUM_SHAPE: usize = 6;

impl SuperquadricParams {
    /// The parameters as the vector q_s of eq. (5).
    pub fn to_array(&self) -> [f64; NUM_SHAPE] {
        [self.a, self.a1, self.a2, self.a3, self.e1, self.e2]
    }

    /// Builds the parameters from the vector q_s of eq. (5).
    pub fn from_array(q: [f64; NUM_SHAPE]) -> Self {
        Self {
            a: q[0],
            a1: q[1],
            a2: q[2],
            a3: q[3],
            e1: q[4],
            e2: q[5],
        }
    }

    /// Semi-axis lengths (a·a1, a·a2, a·a3).
    pub fn semi_axes(&self) -> DVec3 {
        DVec3::new(self.a * self.a1, self.a * self.a2, self.a * self.a3)
    }

    /// True when every parameter is finite.
    pub fn is_finite(&self) -> bool {
        self.to_array().iter().all(|x| x.is_finite())
    }

    /// Removes the redundancy between a and a1..a3 (only the products a·a_i matter) by moving the
    /// largest a_i into a, so that max a_i = 1; then clamps a_i to [`MIN_ASPECT`, 1] and ε to
    /// [[`MIN_EPSILON`], [`MAX_EPSILON`]]. Without this the state drifts along a direction that
    /// changes nothing. The semi-axes a·a_i are unchanged unless a bound bites.
    pub fn normalized(&self) -> Self {
        let axes = self.semi_axes().abs();
        let a = axes.max_element().max(f64::MIN_POSITIVE);
        Self {
            a,
            a1: (axes.x / a).clamp(MIN_ASPECT, 1.0),
            a2: (axes.y / a).clamp(MIN_ASPECT, 1.0),
            a3: (axes.z / a).clamp(MIN_ASPECT, 1.0),
            e1: self.e1.clamp(MIN_EPSILON, MAX_EPSILON),
            e2: self.e2.clamp(MIN_EPSILON, MAX_EPSILON),
        }
    }

    /// [`Self::normalized`] for a step from `previous`: an exponent that `previous` held below
    /// [`MIN_EPSILON`] may stay down to where it was (not below [`LEAST_EPSILON`]), so that a step
    /// neither pushes an exponent below [`MIN_EPSILON`] nor makes a shape set there jump to it.
    pub fn normalized_keeping(&self, previous: &Self) -> Self {
        Self {
            e1: self.e1.clamp(epsilon_floor(previous.e1), MAX_EPSILON),
            e2: self.e2.clamp(epsilon_floor(previous.e2), MAX_EPSILON),
            ..self.normalized()
        }
    }
}

/// The least value a step may give an exponent that was `previous`: [`MIN_EPSILON`], or where it
/// was if that is below (not below [`LEAST_EPSILON`]).
pub fn epsilon_floor(previous: f64) -> f64 {
    previous.clamp(LEAST_EPSILON, MIN_EPSILON)
}

/// Signed power sgn(c)|c|^ε, the building block C_w^ε = spow(cos w, ε), S_w^ε = spow(sin w, ε).
#[inline]
pub fn spow(c: f64, e: f64) -> f64 {
    if c == 0.0 {
        0.0
    } else {
        c.signum() * c.abs().powf(e)
    }
}

/// ln|c| with the convention that it is 0 where c = 0. It only ever multiplies sgn(c)|c|^ε, whose
/// product with ln|c| tends to 0 as c → 0 for ε > 0, so the convention gives the correct limit.
#[inline]
pub fn safe_ln_abs(c: f64) -> f64 {
    if c == 0.0 { 0.0 } else { c.abs().ln() }
}

/// Per-node trigonometric terms of a material point u = (u, v): cos/sin and their log-magnitudes.
/// They depend only on u, so a tessellation computes them once and every step reuses them.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Trig {
    /// cos u
    pub cu: f64,
    /// sin u
    pub su: f64,
    /// cos v
    pub cv: f64,
    /// sin v
    pub sv: f64,
    /// ln|cos u| (0 where cos u = 0)
    pub ln_cu: f64,
    /// ln|sin u| (0 where sin u = 0)
    pub ln_su: f64,
    /// ln|cos v| (0 where cos v = 0)
    pub ln_cv: f64,
    /// ln|sin v| (0 where sin v = 0)
    pub ln_sv: f64,
}

impl Trig {
    /// The terms at material coordinates (u, v), snapping the cosines and sines that are zero in
    /// exact arithmetic (u = ±π/2, v = ±π/2, 0, ±π) to exactly 0 so that poles and axes are exact.
    pub fn new(u: f64, v: f64) -> Self {
        let [cu, su, cv, sv] = snapped_trig(u, v);
        Self {
            cu,
            su,
            cv,
            sv,
            ln_cu: safe_ln_abs(cu),
            ln_su: safe_ln_abs(su),
            ln_cv: safe_ln_abs(cv),
            ln_sv: safe_ln_abs(sv),
        }
    }
}

/// The reference shape s(u; q_s) of eq. (4) at a point with precomputed [`Trig`] terms.
pub fn shape(q: &SuperquadricParams, t: &Trig) -> DVec3 {
    shape_from_powers(q, &SignedPowers::new(q, t))
}

/// The four signed powers C_u^ε1, S_u^ε1, C_v^ε2, S_v^ε2 at one point: the expensive part of
/// both s and J, computed once per node per step and shared by [`shape_from_powers`] and
/// [`jacobian_from_powers`].
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct SignedPowers {
    /// C_u^ε1
    pub cu: f64,
    /// S_u^ε1
    pub su: f64,
    /// C_v^ε2
    pub cv: f64,
    /// S_v^ε2
    pub sv: f64,
}

impl SignedPowers {
    /// The signed powers of `q`'s exponents at a point with terms `t`.
    pub fn new(q: &SuperquadricParams, t: &Trig) -> Self {
        Self {
            cu: spow(t.cu, q.e1),
            su: spow(t.su, q.e1),
            cv: spow(t.cv, q.e2),
            sv: spow(t.sv, q.e2),
        }
    }

    /// The signed powers at material coordinates (u, v), with the cosines and sines of
    /// [`snapped_trig`] but without [`Trig`]'s logarithms: what evaluating s at one point needs.
    pub fn at(q: &SuperquadricParams, u: f64, v: f64) -> Self {
        Self::of_trig(q, snapped_trig(u, v))
    }

    /// The signed powers from [cos u, sin u, cos v, sin v] ([`snapped_trig`]).
    pub fn of_trig(q: &SuperquadricParams, [cu, su, cv, sv]: [f64; 4]) -> Self {
        Self {
            cu: spow(cu, q.e1),
            su: spow(su, q.e1),
            cv: spow(cv, q.e2),
            sv: spow(sv, q.e2),
        }
    }

    /// The signed powers of eq. (4) from a point's [`Trig`] terms as sgn(c) exp(ε ln|c|): four
    /// `exp` in place of four `powf`, for a caller that keeps the terms of a point across steps while the
    /// exponents change (the refining stage's points of influence, `forces::range`). Equal to
    /// [`Self::new`] to a few ulps.
    pub fn from_logs(q: &SuperquadricParams, t: &Trig) -> Self {
        let p = |c: f64, ln: f64, e: f64| {
            if c == 0.0 {
                0.0
            } else {
                c.signum() * (e * ln).exp()
            }
        };
        Self {
            cu: p(t.cu, t.ln_cu, q.e1),
            su: p(t.su, t.ln_su, q.e1),
            cv: p(t.cv, t.ln_cv, q.e2),
            sv: p(t.sv, t.ln_sv, q.e2),
        }
    }
}

/// [cos u, sin u, cos v, sin v], each snapped to exactly 0 where it is zero in exact arithmetic
/// (below 1e-12: u = ±π/2, v = ±π/2, 0, ±π), so that poles and axes are exact.
pub fn snapped_trig(u: f64, v: f64) -> [f64; 4] {
    let snap = |x: f64| if x.abs() < 1e-12 { 0.0 } else { x };
    let ((su, cu), (sv, cv)) = (u.sin_cos(), v.sin_cos());
    [snap(cu), snap(su), snap(cv), snap(sv)]
}

/// s (eq. 4) from precomputed signed powers.
pub fn shape_from_powers(q: &SuperquadricParams, p: &SignedPowers) -> DVec3 {
    q.a * DVec3::new(q.a1 * p.cu * p.cv, q.a2 * p.cu * p.sv, q.a3 * p.su)
}

/// The reference shape s(u, v; q_s) of eq. (4) at material coordinates (u, v).
pub fn shape_at(q: &SuperquadricParams, u: f64, v: f64) -> DVec3 {
    shape_from_powers(q, &SignedPowers::at(q, u, v))
}

/// The Jacobian J = ∂s/∂q_s (eq. 9), as its six columns ∂s/∂(a, a1, a2, a3, ε1, ε2).
/// Derived from eq. (4); the printed eq. (10) is wrong in the ε columns (see the module docs).
pub fn jacobian(q: &SuperquadricParams, t: &Trig) -> [DVec3; NUM_SHAPE] {
    jacobian_from_powers(q, t, &SignedPowers::new(q, t))
}

/// J (eq. 9, derived anew) from precomputed signed powers.
pub fn jacobian_from_powers(
    q: &SuperquadricParams,
    t: &Trig,
    p: &SignedPowers,
) -> [DVec3; NUM_SHAPE] {
    // Unit-scale components: s = a (a1 X, a2 Y, a3 Z).
    let (x, y, z) = (p.cu * p.cv, p.cu * p.sv, p.su);
    let a = q.a;
    [
        DVec3::new(q.a1 * x, q.a2 * y, q.a3 * z),
        DVec3::new(a * x, 0.0, 0.0),
        DVec3::new(0.0, a * y, 0.0),
        DVec3::new(0.0, 0.0, a * z),
        a * DVec3::new(q.a1 * x * t.ln_cu, q.a2 * y * t.ln_cu, q.a3 * z * t.ln_su),
        a * DVec3::new(q.a1 * x * t.ln_cv, q.a2 * y * t.ln_sv, 0.0),
    ]
}

/// The implicit inside–outside function F(p) = ((|x/A1|^(2/ε2) + |y/A2|^(2/ε2))^(ε2/ε1) +
/// |z/A3|^(2/ε1)) of the superquadric with semi-axes A_i = a·a_i; F = 1 on the surface of eq. (4).
pub fn inside_outside(q: &SuperquadricParams, p: DVec3) -> f64 {
    let ax = q.semi_axes();
    let fx = (p.x / ax.x).abs().powf(2.0 / q.e2);
    let fy = (p.y / ax.y).abs().powf(2.0 / q.e2);
    let fz = (p.z / ax.z).abs().powf(2.0 / q.e1);
    (fx + fy).powf(q.e2 / q.e1) + fz
}

#[cfg(test)]
mod tests {
    use super::*;

    fn params() -> SuperquadricParams {
        SuperquadricParams {
            a: 1.7,
            a1: 0.6,
            a2: 0.9,
            a3: 0.45,
            e1: 0.7,
            e2: 1.3,
        }
    }

    #[test]
    fn jacobian_matches_central_differences() {
        let q = params();
        let h = 1e-6;
        for &(u, v) in &[
            (0.3, 0.4),
            (-0.9, 2.5),
            (1.2, -2.0),
            (-0.2, -0.7),
            (0.0, 1.0),
        ] {
            let t = Trig::new(u, v);
            let jac = jacobian(&q, &t);
            for (col, analytic) in jac.iter().enumerate() {
                let mut plus = q.to_array();
                let mut minus = q.to_array();
                plus[col] += h;
                minus[col] -= h;
                let fd = (shape(&SuperquadricParams::from_array(plus), &t)
                    - shape(&SuperquadricParams::from_array(minus), &t))
                    / (2.0 * h);
                assert!(
                    (fd - *analytic).length() < 1e-7,
                    "column {col} at ({u},{v}): analytic {analytic:?} vs fd {fd:?}"
                );
            }
        }
    }

    #[test]
    fn signed_powers_from_logs_equal_the_powers() {
        use std::f64::consts::{FRAC_PI_2, PI};
        let us = [-FRAC_PI_2, -1.2, -0.3, 0.0, 1e-7, 0.8, FRAC_PI_2];
        let vs = [-PI, -2.0, -FRAC_PI_2, 0.0, 0.4, FRAC_PI_2, 2.9, PI];
        for (e1, e2) in [(0.1, 1.9), (0.7, 1.3), (1.0, 1.0), (1.6, 0.2)] {
            let q = SuperquadricParams { e1, e2, ..params() };
            for u in us {
                for v in vs {
                    let t = Trig::new(u, v);
                    let (a, b) = (SignedPowers::new(&q, &t), SignedPowers::from_logs(&q, &t));
                    for (x, y) in [(a.cu, b.cu), (a.su, b.su), (a.cv, b.cv), (a.sv, b.sv)] {
                        // Zeros exactly, signs kept, values to a few ulps (of ε ln|c|).
                        assert_eq!(x == 0.0, y == 0.0, "u {u} v {v}: {x} vs {y}");
                        assert_eq!(x.signum(), y.signum());
                        assert!((x - y).abs() <= 4e-15 * x.abs(), "u {u} v {v}: {x} vs {y}");
                    }
                }
            }
        }
    }

    #[test]
    fn printed_eq_10_epsilon_column_is_wrong() {
        // The paper prints ∂s/∂ε1 = a a1 ε1 Cu^(ε1-1) Cv^ε2 for the x component; it disagrees with
        // the finite difference, which the derived column matches (tested above).
        let q = params();
        let (u, v) = (0.3_f64, 0.4_f64);
        let t = Trig::new(u, v);
        let printed = q.a * q.a1 * q.e1 * spow(t.cu, q.e1 - 1.0) * spow(t.cv, q.e2);
        let derived = jacobian(&q, &t)[4].x;
        assert!(
            (printed - derived).abs() > 0.1,
            "printed {printed} derived {derived}"
        );
    }

    #[test]
    fn epsilon_derivative_vanishes_on_axes() {
        let q = params();
        // At the north pole cos u = 0: the x and y components and their ε1 derivative vanish.
        let t = Trig::new(std::f64::consts::FRAC_PI_2, 0.3);
        let j = jacobian(&q, &t);
        assert_eq!(j[4].x, 0.0);
        assert_eq!(j[4].y, 0.0);
        assert!(j.iter().all(|c| c.is_finite()));
        assert!((shape(&q, &t) - DVec3::new(0.0, 0.0, q.a * q.a3)).length() < 1e-15);
    }

    #[test]
    fn surface_points_satisfy_inside_outside_function() {
        let q = params();
        for i in 0..20 {
            let u = -1.5 + 3.0 * i as f64 / 19.0;
            for j in 0..20 {
                let v = -3.1 + 6.2 * j as f64 / 19.0;
                let f = inside_outside(&q, shape_at(&q, u, v));
                assert!((f - 1.0).abs() < 1e-9, "F = {f} at ({u},{v})");
            }
        }
    }

    #[test]
    fn normalized_moves_largest_aspect_into_scale() {
        let q = SuperquadricParams {
            a: 2.0,
            a1: 0.5,
            a2: 1.5,
            a3: 0.25,
            e1: 5.0,
            e2: 0.0,
        };
        let n = q.normalized();
        assert!((n.semi_axes() - q.semi_axes()).length() < 1e-12);
        assert_eq!(n.a2, 1.0);
        assert_eq!(n.e1, MAX_EPSILON);
        assert_eq!(n.e2, MIN_EPSILON);
    }

    #[test]
    fn a_step_keeps_an_exponent_set_below_the_dynamics_bound_and_pushes_none_there() {
        let previous = SuperquadricParams {
            e1: 0.02,
            e2: 0.5,
            ..Default::default()
        };
        // ε1 set at 0.02 may stay or fall back to 0.02, and rise; ε2 stops at MIN_EPSILON.
        let stepped = |e1: f64, e2: f64| {
            SuperquadricParams { e1, e2, ..previous }.normalized_keeping(&previous)
        };
        assert_eq!(stepped(0.02, 0.05).e1, 0.02);
        assert_eq!(stepped(0.001, 0.05).e1, 0.02);
        assert_eq!(stepped(0.06, 0.05).e1, 0.06);
        assert_eq!(stepped(0.06, 0.05).e2, MIN_EPSILON);
        assert_eq!(stepped(0.06, 2.5).e2, MAX_EPSILON);
        // From a shape at or above the bound it is `normalized`.
        let q = SuperquadricParams {
            a: 2.0,
            a1: 0.5,
            e1: 0.03,
            e2: 3.0,
            ..Default::default()
        };
        assert_eq!(
            q.normalized_keeping(&SuperquadricParams::default()),
            q.normalized()
        );
        // Never below LEAST_EPSILON, whatever the previous shape held.
        let below = SuperquadricParams {
            e1: 0.001,
            ..Default::default()
        };
        assert_eq!(below.normalized_keeping(&below).e1, LEAST_EPSILON);
    }
}
