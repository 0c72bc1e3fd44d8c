//! Global tapering and bending on top of the superquadric (beyond the paper: its section VII lists
//! "further global deformations" as work in progress).
//!
//! The deformation T maps the reference shape s (eq. 4) before the local displacement is added,
//! so a node's world position becomes x = c + R (T(s) + d) and the global coordinates gain
//! q_T = (t_x, t_y, b_x, b_y). With A = a·a3 (the semi-axis along the model's z) and ζ = z / A:
//!
//! ```text
//! taper:  q   = ((1 + t_x ζ) x,  (1 + t_y ζ) y)                      (Barr 1984; Solina & Bajcsy 1990)
//! bend:   m   = 1 − b·q / A
//!         p_xy = q + m A ζ² C(|b|² ζ²) b,    p_z = m z S(|b|² ζ²)
//!         C(X) = (1 − cos √X) / X,           S(X) = sin √X / √X
//! ```
//!
//! Tapering scales each cross-section linearly along z: the end at z = A is (1 + t) times as wide
//! as the middle, the end at z = −A (1 − t) times. Bending (our own derivation) turns the z axis into
//! a circular arc of curvature |b| / A in the direction b / |b| of the x–y plane, centred on the
//! model's origin: the middle stays put and each end turns through |b| radians; every point keeps
//! its distance (1 − k w, with w its offset towards the bend) from the centre of curvature. Both
//! coordinates are dimensionless, so they mean the same at any scale, and both are the identity at
//! 0. Writing the bend with b = curvature × direction (rather than a curvature and an angle) and
//! C, S as functions of |b|² makes T analytic in b through b = 0, where an angle would be undefined.
//!
//! [`GlobalDeformation::jacobian`] gives ∂T/∂(x, y, z, A, t_x, t_y, b_x, b_y) by forward-mode
//! differentiation of the formulas above; the tests check it against central differences.

use glam::{DMat3, DVec3};

/// Number of deformation coordinates q_T = (t_x, t_y, b_x, b_y).
pub const NUM_DEFORM: usize = 4;
/// Largest |t_x|, |t_y|: at 1 one end of the model shrinks to a point.
pub const MAX_TAPER: f64 = 1.0;
/// Largest bend angle |b| of each end, in radians (the whole arc then spans 2|b|, below a full turn).
pub const MAX_BEND: f64 = 2.5;
/// Largest value of |b| · (widest cross-section) / A: keeps every point on the near side of the
/// centre of curvature (m > 0), so that bending never turns the surface inside out.
pub const MAX_BEND_WIDTH: f64 = 0.9;

/// The global deformation coordinates q_T: tapering t = (t_x, t_y) and bending b = (b_x, b_y).
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GlobalDeformation {
    /// Tapering (t_x, t_y) of the x and y extents along z, each in [−1, 1].
    #[serde(default)]
    pub taper: [f64; 2],
    /// Bending b = (b_x, b_y): the direction in the x–y plane towards which the z axis bends, with
    /// length the angle (radians) through which each end turns.
    #[serde(default)]
    pub bend: [f64; 2],
}

/// How T and its first derivatives come out of [`GlobalDeformation::jacobian`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DeformJacobian {
    /// T(s).
    pub value: DVec3,
    /// ∂T/∂s (columns ∂T/∂x, ∂T/∂y, ∂T/∂z).
    pub d_point: DMat3,
    /// ∂T/∂A, A = a·a3.
    pub d_height: DVec3,
    /// ∂T/∂(t_x, t_y, b_x, b_y).
    pub d_params: [DVec3; NUM_DEFORM],
}

impl GlobalDeformation {
    /// No deformation.
    pub const IDENTITY: Self = Self {
        taper: [0.0; 2],
        bend: [0.0; 2],
    };

    /// True when T is the identity (every coordinate 0).
    pub fn is_identity(&self) -> bool {
        self.taper == [0.0; 2] && self.bend == [0.0; 2]
    }

    /// True when every coordinate is finite.
    pub fn is_finite(&self) -> bool {
        self.to_array().iter().all(|x| x.is_finite())
    }

    /// The coordinates as q_T = (t_x, t_y, b_x, b_y).
    pub fn to_array(&self) -> [f64; NUM_DEFORM] {
        [self.taper[0], self.taper[1], self.bend[0], self.bend[1]]
    }

    /// Builds the coordinates from q_T = (t_x, t_y, b_x, b_y).
    pub fn from_array(q: [f64; NUM_DEFORM]) -> Self {
        Self {
            taper: [q[0], q[1]],
            bend: [q[2], q[3]],
        }
    }

    /// The coordinates brought within their bounds for a superquadric of semi-axes `axes`:
    /// |t_i| ≤ [`MAX_TAPER`], |b| ≤ [`MAX_BEND`], and |b| small enough that the widest tapered
    /// cross-section stays on the near side of the centre of curvature ([`MAX_BEND_WIDTH`]).
    pub fn clamped(&self, axes: DVec3) -> Self {
        let taper = self.taper.map(|t| t.clamp(-MAX_TAPER, MAX_TAPER));
        let widest = ((1.0 + taper[0].abs()) * axes.x).max((1.0 + taper[1].abs()) * axes.y);
        let limit = MAX_BEND.min(MAX_BEND_WIDTH * axes.z / widest.max(f64::MIN_POSITIVE));
        let [bx, by] = self.bend;
        let len = bx.hypot(by);
        // A bend scaled onto the limit can come out an ulp or two above it; clamping it again
        // must change nothing (the plugin clamps what it stores before every step).
        let bend = if len > limit * (1.0 + 4.0 * f64::EPSILON) {
            [bx * limit / len, by * limit / len]
        } else {
            self.bend
        };
        Self { taper, bend }
    }

    /// T(s) for the superquadric point `s` of a model whose semi-axis along z is `height` (A).
    pub fn apply(&self, s: DVec3, height: f64) -> DVec3 {
        let zeta = s.z / height;
        let q = [
            (1.0 + self.taper[0] * zeta) * s.x,
            (1.0 + self.taper[1] * zeta) * s.y,
        ];
        let [bx, by] = self.bend;
        if bx == 0.0 && by == 0.0 {
            return DVec3::new(q[0], q[1], s.z);
        }
        let big_x = (bx * bx + by * by) * zeta * zeta;
        let [(c, _), (sv, _)] = arc(big_x);
        let m = 1.0 - (bx * q[0] + by * q[1]) / height;
        let lift = m * height * zeta * zeta * c;
        DVec3::new(q[0] + lift * bx, q[1] + lift * by, m * s.z * sv)
    }

    /// T(s) and its derivatives with respect to s, A and q_T (see [`DeformJacobian`]).
    pub fn jacobian(&self, s: DVec3, height: f64) -> DeformJacobian {
        // Forward mode over the inputs (x, y, z, A, t_x, t_y, b_x, b_y).
        let var = |i: usize, v: f64| Dual::seed(v, i);
        let (x, y, z, h) = (var(0, s.x), var(1, s.y), var(2, s.z), var(3, height));
        let (tx, ty) = (var(4, self.taper[0]), var(5, self.taper[1]));
        let (bx, by) = (var(6, self.bend[0]), var(7, self.bend[1]));
        let zeta = z.div(h);
        let qx = Dual::constant(1.0).add(tx.mul(zeta)).mul(x);
        let qy = Dual::constant(1.0).add(ty.mul(zeta)).mul(y);
        let big_x = bx.mul(bx).add(by.mul(by)).mul(zeta).mul(zeta);
        let [c, sv] = arc(big_x.v).map(|f| big_x.chain(f));
        let m = Dual::constant(1.0).sub(bx.mul(qx).add(by.mul(qy)).div(h));
        let lift = m.mul(h).mul(zeta).mul(zeta).mul(c);
        let out = [qx.add(lift.mul(bx)), qy.add(lift.mul(by)), m.mul(z).mul(sv)];
        let column = |i: usize| DVec3::new(out[0].d[i], out[1].d[i], out[2].d[i]);
        DeformJacobian {
            value: DVec3::new(out[0].v, out[1].v, out[2].v),
            d_point: DMat3::from_cols(column(0), column(1), column(2)),
            d_height: column(3),
            d_params: [column(4), column(5), column(6), column(7)],
        }
    }
}

/// [C(X), S(X)] with their derivatives, each as (value, d/dX): C(X) = (1 − cos √X) / X and
/// S(X) = sin √X / √X, by their series near 0 (where the closed forms cancel).
fn arc(x: f64) -> [(f64, f64); 2] {
    if x.abs() < 1e-2 {
        let (x2, x3) = (x * x, x * x * x);
        [
            (
                0.5 - x / 24.0 + x2 / 720.0 - x3 / 40320.0 + x2 * x2 / 3628800.0,
                -1.0 / 24.0 + x / 360.0 - x2 / 13440.0 + x3 / 907200.0,
            ),
            (
                1.0 - x / 6.0 + x2 / 120.0 - x3 / 5040.0 + x2 * x2 / 362880.0,
                -1.0 / 6.0 + x / 60.0 - x2 / 1680.0 + x3 / 90720.0,
            ),
        ]
    } else {
        let r = x.sqrt();
        let (s, c) = r.sin_cos();
        [
            ((1.0 - c) / x, s / (2.0 * r * r * r) - (1.0 - c) / (x * x)),
            (s / r, c / (2.0 * x) - s / (2.0 * x * r)),
        ]
    }
}

/// A value with its derivatives along the eight inputs of [`GlobalDeformation::jacobian`].
#[derive(Clone, Copy)]
struct Dual {
    v: f64,
    d: [f64; 8],
}

impl Dual {
    fn constant(v: f64) -> Self {
        Self { v, d: [0.0; 8] }
    }
    fn seed(v: f64, i: usize) -> Self {
        let mut d = [0.0; 8];
        d[i] = 1.0;
        Self { v, d }
    }
    fn add(self, o: Self) -> Self {
        Self {
            v: self.v + o.v,
            d: std::array::from_fn(|i| self.d[i] + o.d[i]),
        }
    }
    fn sub(self, o: Self) -> Self {
        Self {
            v: self.v - o.v,
            d: std::array::from_fn(|i| self.d[i] - o.d[i]),
        }
    }
    fn mul(self, o: Self) -> Self {
        Self {
            v: self.v * o.v,
            d: std::array::from_fn(|i| self.d[i] * o.v + self.v * o.d[i]),
        }
    }
    fn div(self, o: Self) -> Self {
        let inv = 1.0 / o.v;
        Self {
            v: self.v * inv,
            d: std::array::from_fn(|i| (self.d[i] - self.v * inv * o.d[i]) * inv),
        }
    }
    /// f(self) for f's (value, derivative) at `self.v`.
    fn chain(self, (v, dv): (f64, f64)) -> Self {
        Self {
            v,
            d: self.d.map(|x| dv * x),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample_points() -> Vec<DVec3> {
        vec![
            DVec3::new(0.3, -0.2, 0.9),
            DVec3::new(-0.25, 0.1, -1.4),
            DVec3::new(0.1, 0.35, 0.02),
            DVec3::new(0.0, 0.0, 1.5),
            DVec3::new(0.4, 0.0, 0.0),
        ]
    }

    fn deformations() -> Vec<GlobalDeformation> {
        vec![
            GlobalDeformation::IDENTITY,
            GlobalDeformation {
                taper: [0.4, -0.3],
                bend: [0.0, 0.0],
            },
            GlobalDeformation {
                taper: [0.0, 0.0],
                bend: [0.7, -0.4],
            },
            GlobalDeformation {
                taper: [-0.5, 0.6],
                bend: [1e-4, 2e-5],
            },
            GlobalDeformation {
                taper: [0.2, 0.1],
                bend: [-1.3, 0.9],
            },
        ]
    }

    #[test]
    fn jacobian_matches_central_differences() {
        let h = 1e-6;
        let height = 1.5;
        for d in deformations() {
            for s in sample_points() {
                let jac = d.jacobian(s, height);
                assert!((jac.value - d.apply(s, height)).length() < 1e-14);
                for axis in 0..3 {
                    let e = DVec3::AXES[axis] * h;
                    let fd = (d.apply(s + e, height) - d.apply(s - e, height)) / (2.0 * h);
                    let an = jac.d_point.col(axis);
                    assert!(
                        (fd - an).length() < 1e-7,
                        "∂/∂s{axis} {d:?} at {s}: {an} vs {fd}"
                    );
                }
                let fd = (d.apply(s, height + h) - d.apply(s, height - h)) / (2.0 * h);
                assert!((fd - jac.d_height).length() < 1e-7, "∂/∂A {d:?} at {s}");
                for k in 0..NUM_DEFORM {
                    let (mut plus, mut minus) = (d.to_array(), d.to_array());
                    plus[k] += h;
                    minus[k] -= h;
                    let fd = (GlobalDeformation::from_array(plus).apply(s, height)
                        - GlobalDeformation::from_array(minus).apply(s, height))
                        / (2.0 * h);
                    let an = jac.d_params[k];
                    assert!(
                        (fd - an).length() < 1e-7,
                        "∂/∂q_T{k} {d:?} at {s}: {an} vs {fd}"
                    );
                }
            }
        }
    }

    #[test]
    fn arc_functions_are_smooth_across_the_series_switch() {
        for x in [1e-2 * (1.0 - 1e-9), 1e-2 * (1.0 + 1e-9)] {
            let [(c, dc), (s, ds)] = arc(x);
            let r = x.sqrt();
            assert!((c - (1.0 - r.cos()) / x).abs() < 1e-12);
            assert!((s - r.sin() / r).abs() < 1e-14);
            let h = 1e-7;
            let (plus, minus) = (arc(x + h), arc(x - h));
            assert!((dc - (plus[0].0 - minus[0].0) / (2.0 * h)).abs() < 1e-6);
            assert!((ds - (plus[1].0 - minus[1].0) / (2.0 * h)).abs() < 1e-6);
        }
    }

    #[test]
    fn taper_scales_cross_sections_linearly_along_z() {
        let d = GlobalDeformation {
            taper: [0.5, -0.25],
            bend: [0.0; 2],
        };
        let height = 2.0;
        let top = d.apply(DVec3::new(1.0, 1.0, 2.0), height);
        let bottom = d.apply(DVec3::new(1.0, 1.0, -2.0), height);
        let middle = d.apply(DVec3::new(1.0, 1.0, 0.0), height);
        assert_eq!(top, DVec3::new(1.5, 0.75, 2.0));
        assert_eq!(bottom, DVec3::new(0.5, 1.25, -2.0));
        assert_eq!(middle, DVec3::new(1.0, 1.0, 0.0));
    }

    #[test]
    fn bend_maps_the_axis_onto_a_circle_and_keeps_distances_to_its_centre() {
        // Bend towards +x by 0.8 rad at each end of a model with A = 2: curvature 0.4, centre of
        // curvature at (2.5, 0, 0).
        let d = GlobalDeformation {
            taper: [0.0; 2],
            bend: [0.8, 0.0],
        };
        let height = 2.0;
        let centre = DVec3::new(2.5, 0.0, 0.0);
        for i in 0..=10 {
            let z = -2.0 + 0.4 * i as f64;
            let on_axis = d.apply(DVec3::new(0.0, 0.0, z), height);
            assert!(
                ((on_axis - centre).length() - 2.5).abs() < 1e-12,
                "axis point {on_axis}"
            );
            // Arc length along the axis is kept: the angle turned is z times the curvature.
            let angle = (on_axis.z).atan2(centre.x - on_axis.x);
            assert!((angle - 0.4 * z).abs() < 1e-12);
            // A point off the axis towards the bend keeps its distance to the centre, and y.
            let off = d.apply(DVec3::new(0.5, 0.3, z), height);
            let r = DVec3::new(off.x - 2.5, 0.0, off.z).length();
            assert!(
                (r - 2.0).abs() < 1e-12,
                "off-axis point {off} at {r} from the centre"
            );
            assert_eq!(off.y, 0.3);
        }
        // The ends turn through ±0.8 rad.
        let top = d.apply(DVec3::new(0.0, 0.0, 2.0), height);
        assert!(
            (top - DVec3::new(2.5 - 2.5 * 0.8_f64.cos(), 0.0, 2.5 * 0.8_f64.sin())).length()
                < 1e-12
        );
    }

    #[test]
    fn clamped_keeps_taper_and_bend_within_bounds() {
        let axes = DVec3::new(0.5, 0.3, 2.0);
        let d = GlobalDeformation {
            taper: [3.0, -0.2],
            bend: [6.0, 8.0],
        }
        .clamped(axes);
        assert_eq!(d.taper, [1.0, -0.2]);
        let len = d.bend[0].hypot(d.bend[1]);
        // Widest section 2 × 0.5 = 1: |b| ≤ 0.9 × 2 / 1.
        assert!((len - 1.8).abs() < 1e-12);
        assert!((d.bend[0] / d.bend[1] - 0.75).abs() < 1e-12);
        let inside = GlobalDeformation {
            taper: [0.1, 0.1],
            bend: [0.2, 0.1],
        };
        assert_eq!(inside.clamped(axes), inside);
        // Clamping a clamped value changes nothing, to the bit, over many directions and sizes.
        for i in 0..2000 {
            let angle = i as f64 * 0.7;
            let size = 1.0 + (i % 37) as f64 * 0.113;
            let d = GlobalDeformation {
                taper: [0.3, -0.45],
                bend: [size * angle.cos(), size * angle.sin()],
            }
            .clamped(axes);
            assert_eq!(d.clamped(axes), d, "{i}");
        }
    }
}
