//! Distances from a point to a pure superquadric's surface (beyond the paper), in closed form or
//! by a short 2-D search, with their gradients over the pose and the global shape.
//!
//! Everything here rests on the superquadric's **gauge** G(x) = F(x)^(ε1/2), with F the
//! inside–outside function ([`super::superquadric::inside_outside`]): G is 1 on the surface and
//! homogeneous of degree one (G(λx) = λ·G(x)), so x/G(x) is the surface point on the ray
//! through x. [`gauge`] evaluates it in logarithms, which keeps exponents as small as
//! [`super::superquadric::LEAST_EPSILON`] and points far from the model finite.
//!
//! - The **radial distance** |x|·(1 − 1/G(x)) (EMS's, Liu et al., CVPR 2022) costs one gauge a
//!   point: [`radial_distance`], [`radial`].
//! - The **surface distance** is the Euclidean distance to the closest surface point, found by a
//!   damped Gauss–Newton search over the ray directions from the radial foot ([`closest_point`]):
//!   [`surface_distance`], [`surface`]. It is what a user means by "how far is the data", and
//!   what the residual figures report.
//!
//! Gradients run over [`NUM_UNKNOWNS`] unknowns in the order semi-axes (3), ε1, ε2, translation
//! (3), rotation increment ω (3, the orientation R·exp(ω×), about the model's own axes).

use super::init::InitialPose;
use super::superquadric::SuperquadricParams;
use glam::DVec3;

/// Number of unknowns: semi-axes (3), ε1, ε2, translation (3), rotation increment (3).
pub const NUM_UNKNOWNS: usize = 11;

/// The gauge G(x) = F(x)^(ε1/2) at a model-frame point and its derivatives.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Gauge {
    /// G(x): 1 on the surface, below inside, above outside; 0 only at the centre.
    pub value: f64,
    /// ∇ₓG (homogeneous of degree zero: the same all along a ray).
    pub grad_x: DVec3,
    /// ∂G/∂(A1, A2, A3, ε1, ε2), A_i the semi-axes.
    pub grad_shape: [f64; 5],
}

/// ln(e^a + e^b) without overflow, and the weight e^(a − result) of `a` in it.
fn log_sum_exp(a: f64, b: f64) -> (f64, f64) {
    if a == f64::NEG_INFINITY && b == f64::NEG_INFINITY {
        return (f64::NEG_INFINITY, 0.5);
    }
    let (hi, lo) = if a >= b { (a, b) } else { (b, a) };
    let t = (lo - hi).exp();
    let s = hi + t.ln_1p();
    let w_hi = 1.0 / (1.0 + t);
    (s, if a >= b { w_hi } else { 1.0 - w_hi })
}

/// w·ℓ with the convention 0·(−∞) = 0 (a zero coordinate's weight times its log).
fn weighted_log(w: f64, l: f64) -> f64 {
    if w == 0.0 { 0.0 } else { w * l }
}

/// The gauge of the superquadric with semi-axes `axes` and exponents `e1`, `e2` at the
/// model-frame point `x`. With `x` = 0 the value is 0 and the derivatives are 0.
pub fn gauge(axes: DVec3, e1: f64, e2: f64, x: DVec3) -> Gauge {
    let zero = Gauge {
        value: 0.0,
        grad_x: DVec3::ZERO,
        grad_shape: [0.0; 5],
    };
    if x == DVec3::ZERO {
        return zero;
    }
    let ln_u = (x / axes).abs();
    let ln_u = DVec3::new(ln_u.x.ln(), ln_u.y.ln(), ln_u.z.ln());
    // ln F = lse((ε2/ε1)·lse(a, b), c) with a, b, c the logs of the three powers.
    let (a, b, c) = (2.0 / e2 * ln_u.x, 2.0 / e2 * ln_u.y, 2.0 / e1 * ln_u.z);
    let (ln_h, w_a) = log_sum_exp(a, b);
    let big_a = if ln_h == f64::NEG_INFINITY {
        f64::NEG_INFINITY
    } else {
        e2 / e1 * ln_h
    };
    let (ln_f, w_big_a) = log_sum_exp(big_a, c);
    let value = (0.5 * e1 * ln_f).exp();
    // ∂lnG/∂ln|x_i| are weights that sum to one (Euler's theorem for degree one).
    let w_x = w_big_a * w_a;
    let w_y = w_big_a * (1.0 - w_a);
    let w_z = 1.0 - w_big_a;
    let per = |w: f64, c: f64| if w == 0.0 { 0.0 } else { w / c };
    let grad_x = DVec3::new(per(w_x, x.x), per(w_y, x.y), per(w_z, x.z)) * value;
    let lse_entropy = weighted_log(w_a, a) + weighted_log(1.0 - w_a, b);
    let d_e1 = 0.5 * (ln_f - weighted_log(w_big_a, big_a) - weighted_log(w_z, c));
    let d_e2 = if w_big_a == 0.0 {
        0.0
    } else {
        0.5 * w_big_a * (ln_h - lse_entropy)
    };
    Gauge {
        value,
        grad_x,
        grad_shape: [
            -value * w_x / axes.x,
            -value * w_y / axes.y,
            -value * w_z / axes.z,
            value * d_e1,
            value * d_e2,
        ],
    }
}

/// A distance and its gradient over the [`NUM_UNKNOWNS`] unknowns.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Distance {
    /// Signed distance: positive outside, negative inside.
    pub distance: f64,
    /// ∂distance/∂unknowns.
    pub gradient: [f64; NUM_UNKNOWNS],
}

/// The point `p` in the model frame of `pose`.
fn to_model(pose: &InitialPose, p: DVec3) -> DVec3 {
    pose.rotation.inverse() * (p - pose.translation)
}

/// Fills slots 5–10 of `gradient` (translation, rotation increment) from the distance's
/// gradient `n` over the model-frame point `x`: x = Rᵀ(p − t), so ∂/∂t = −R·n, and with
/// R·exp(ω×), x moves by x × ω, so ∂/∂ω = n × x.
fn rigid_gradient(pose: &InitialPose, x: DVec3, n: DVec3, gradient: &mut [f64; NUM_UNKNOWNS]) {
    gradient[5..8].copy_from_slice(&(-(pose.rotation * n)).to_array());
    gradient[8..11].copy_from_slice(&n.cross(x).to_array());
}

/// The radial distance |x|·(1 − 1/G(x)) of `p` to the superquadric of `pose` (tapering and
/// bending ignored); the centre lies the least semi-axis inside.
pub fn radial_distance(pose: &InitialPose, p: DVec3) -> f64 {
    let x = to_model(pose, p);
    let axes = pose.shape.semi_axes();
    let r = x.length();
    if !(r > 0.0) {
        return -axes.min_element();
    }
    r * (1.0 - 1.0 / gauge(axes, pose.shape.e1, pose.shape.e2, x).value)
}

/// The radial distance of `p` and its gradient.
pub fn radial(pose: &InitialPose, p: DVec3) -> Distance {
    let x = to_model(pose, p);
    let axes = pose.shape.semi_axes();
    let mut gradient = [0.0; NUM_UNKNOWNS];
    let r = x.length();
    if !(r > 0.0) {
        return Distance {
            distance: -axes.min_element(),
            gradient,
        };
    }
    let g = gauge(axes, pose.shape.e1, pose.shape.e2, x);
    // d = r − r/G: ∂d/∂θ = (r/G²)·∂G/∂θ, ∇ₓd = x/r·(1 − 1/G) + (r/G²)·∇ₓG.
    let k = r / (g.value * g.value);
    for (slot, d) in gradient[..5].iter_mut().zip(g.grad_shape) {
        *slot = k * d;
    }
    let n = x / r * (1.0 - 1.0 / g.value) + g.grad_x * k;
    rigid_gradient(pose, x, n, &mut gradient);
    Distance {
        distance: r * (1.0 - 1.0 / g.value),
        gradient,
    }
}

/// The radial distance projected on the surface normal, (G(x) − 1)/|∇ₓG(x)| (Taubin's first-order
/// distance to the level set G = 1): the radial distance times the cosine between the ray
/// and the normal, so it does not overweigh points whose ray meets the surface obliquely (off
/// the ends of long semi-axes) as the radial distance does, and it costs the same one gauge.
pub fn normal_distance(pose: &InitialPose, p: DVec3) -> f64 {
    normal(pose, p).distance
}

/// [`normal_distance`] and a gradient with the cosine held: the radial distance's gradient times
/// the cosine (Gauss–Newton on the projected residual, the cosine refreshed at every
/// evaluation).
pub fn normal(pose: &InitialPose, p: DVec3) -> Distance {
    let x = to_model(pose, p);
    let axes = pose.shape.semi_axes();
    let r = x.length();
    let mut gradient = [0.0; NUM_UNKNOWNS];
    if !(r > 0.0) {
        return Distance {
            distance: -axes.min_element(),
            gradient,
        };
    }
    let g = gauge(axes, pose.shape.e1, pose.shape.e2, x);
    let slope = g.grad_x.length();
    // cos = x̂·∇G/|∇G| = G/(r|∇G|) by Euler's theorem.
    let cos = if slope > 0.0 {
        g.value / (r * slope)
    } else {
        1.0
    };
    let k = cos * r / (g.value * g.value);
    for (slot, d) in gradient[..5].iter_mut().zip(g.grad_shape) {
        *slot = k * d;
    }
    let n = (x / r * (1.0 - 1.0 / g.value) + g.grad_x * (r / (g.value * g.value))) * cos;
    rigid_gradient(pose, x, n, &mut gradient);
    Distance {
        distance: r * (1.0 - 1.0 / g.value) * cos,
        gradient,
    }
}

/// The closest surface point to a model-frame point ([`closest_point`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Foot {
    /// The unit ray direction the surface point lies on (model frame).
    pub direction: DVec3,
    /// The surface point direction / G(direction).
    pub point: DVec3,
    /// The outward unit normal there.
    pub normal: DVec3,
    /// The gauge at `direction` (its value is 1/|point|).
    pub gauge: Gauge,
    /// Signed distance from the point to it: positive outside.
    pub distance: f64,
}

/// Most iterations of [`closest_point`]'s search.
pub const CLOSEST_ITERATIONS: u32 = 16;

/// The surface point s(c) = v/G(v), v = d0 + c₁t1 + c₂t2, of a chart about the ray `d0`, with
/// what a step needs: φ = ½|s − x|² and its gradient over c.
#[derive(Clone, Copy)]
struct ChartPoint {
    c: [f64; 2],
    v: DVec3,
    s: DVec3,
    g: Gauge,
    j: [DVec3; 2],
    f: f64,
    grad: [f64; 2],
}

/// The angle (rad) within which [`closest_point`]'s offset is normal to the surface at rest: the
/// distance is then exact to 10⁻¹⁰ of itself.
const EXACT_ANGLE: f64 = 1e-5;

/// The angle within which a warm-started search ([`closest_point_from`]) is at rest: the distance
/// is then exact to 5·10⁻⁷ of itself, below what a fit's steps resolve, and its gradient (the
/// envelope theorem's, first order in the angle) to 10⁻³.
const WARM_ANGLE: f64 = 1e-3;

/// One chart about a ray: the tangent basis fixed for the whole search.
struct Chart {
    axes: DVec3,
    e1: f64,
    e2: f64,
    x: DVec3,
    d0: DVec3,
    t: [DVec3; 2],
    /// The search is at rest when the offset is normal to within this angle (rad).
    angle: f64,
}

impl Chart {
    fn at(&self, c: [f64; 2]) -> ChartPoint {
        let v = self.d0 + self.t[0] * c[0] + self.t[1] * c[1];
        let g = gauge(self.axes, self.e1, self.e2, v);
        let inv = 1.0 / g.value;
        let s = v * inv;
        // ∂s/∂c_k = t_k/G − v·(∇G·t_k)/G² (v is affine in c: no normalisation to differentiate).
        let j = self.t.map(|t| t * inv - v * (g.grad_x.dot(t) * inv * inv));
        let e = s - self.x;
        ChartPoint {
            c,
            v,
            s,
            g,
            j,
            f: e.length_squared(),
            grad: [j[0].dot(e), j[1].dot(e)],
        }
    }

    /// True when the offset x − s is normal to the surface to within `angle` rad (at
    /// [`EXACT_ANGLE`] the distance is exact to 10⁻¹⁰ of itself), or the point lies on the
    /// surface to 10⁻¹² of its radius; `grad` is the gradient of ½|s − x|² over the directions
    /// searched.
    fn within(p: &ChartPoint, grad: [f64; 2], angle: f64) -> bool {
        let g2 = grad[0] * grad[0] + grad[1] * grad[1];
        let j2 = p.j[0].length_squared() + p.j[1].length_squared();
        g2 <= angle * angle * p.f * j2 || p.f <= 1e-24 * p.s.length_squared()
    }

    /// Minimises |s − x|² from c = 0, over both chart directions or, with `line`, over the first
    /// alone: Gauss–Newton steps first, then Newton steps on a finite-difference Hessian (GN
    /// alone crawls where the distance is not small against the radius of curvature), each damped
    /// until it lowers the distance.
    fn descend(&self, line: bool) -> ChartPoint {
        let mut cur = self.at([0.0, 0.0]);
        let mut damping = 0.0;
        // A line search holds the second coordinate: its gradient and coupling are zero.
        let mask = |mut m: [[f64; 2]; 2], mut g: [f64; 2]| {
            if line {
                (m[0][1], m[1][0], m[1][1], g[1]) = (0.0, 0.0, 1.0, 0.0);
            }
            (m, g)
        };
        for it in 0..CLOSEST_ITERATIONS {
            let (gn, grad) = mask(
                [
                    [cur.j[0].dot(cur.j[0]), cur.j[0].dot(cur.j[1])],
                    [cur.j[0].dot(cur.j[1]), cur.j[1].dot(cur.j[1])],
                ],
                cur.grad,
            );
            if !cur.f.is_finite() || Self::within(&cur, grad, self.angle) {
                break;
            }
            let hessian = if it < 2 && !line {
                gn
            } else {
                let h = 1e-7 * (1.0 + cur.c[0].abs().max(cur.c[1].abs()));
                let a = self.at([cur.c[0] + h, cur.c[1]]);
                let b = if line {
                    a
                } else {
                    self.at([cur.c[0], cur.c[1] + h])
                };
                let off = 0.5 * ((a.grad[1] - cur.grad[1]) + (b.grad[0] - cur.grad[0])) / h;
                let m = [
                    [(a.grad[0] - cur.grad[0]) / h, off],
                    [off, (b.grad[1] - cur.grad[1]) / h],
                ];
                mask(m, grad).0
            };
            let mut moved = false;
            for _ in 0..10 {
                let m00 = hessian[0][0] + damping * gn[0][0];
                let m11 = hessian[1][1] + damping * gn[1][1];
                let det = m00 * m11 - hessian[0][1] * hessian[0][1];
                if m00 > 0.0 && det > 0.0 {
                    let d0 = (-grad[0] * m11 + grad[1] * hessian[0][1]) / det;
                    let d1 = (-grad[1] * m00 + grad[0] * hessian[0][1]) / det;
                    let next = self.at([cur.c[0] + d0, cur.c[1] + d1]);
                    if next.f < cur.f {
                        cur = next;
                        damping *= 0.25;
                        if damping < 1e-6 {
                            damping = 0.0;
                        }
                        moved = true;
                        break;
                    }
                }
                damping = (damping * 10.0).max(1e-3);
            }
            if !moved {
                break;
            }
        }
        cur
    }
}

/// The surface point of `shape` (centred, unrotated) closest to the model-frame point `x`.
///
/// The surface is s(d) = d / G(d) over ray directions d. The search starts at the radial foot
/// (d = x/|x|) and minimises |s − x|² over a chart of directions about it (Gauss–Newton, then
/// Newton steps), keeping only steps that bring s closer, until the offset x − s is normal to
/// the surface or after [`CLOSEST_ITERATIONS`]. A search that stalls beside a crease (an
/// exponent near 2 folds the surface along a coordinate plane) goes on along the fold. A point
/// deep inside (G(x) < ½), where the distance has several local minima, is also searched from the ends of the three semi-axes on
/// its side, and the nearest kept. The distance found is never above the radial one. At the
/// centre the search starts at the end of the least semi-axis.
pub fn closest_point(shape: &SuperquadricParams, x: DVec3) -> Foot {
    closest_point_from(shape, x, None)
}

/// [`closest_point`] warm-started from `hint`, the ray direction of an earlier foot of the same
/// point on a nearby shape (a fit's previous iterate): the search starts there, and is kept when
/// it comes to rest no farther than the radial foot and the point is not deep inside (G(x) ≥ ½,
/// where the distance has one minimum near the ray); otherwise the whole search of
/// [`closest_point`] runs as well and the nearer foot is kept. A fit moves little between
/// iterates, so a warm start comes to rest in one or two steps where a cold one takes several.
pub fn closest_point_from(shape: &SuperquadricParams, x: DVec3, hint: Option<DVec3>) -> Foot {
    let axes = shape.semi_axes();
    let (e1, e2) = (shape.e1, shape.e2);
    let r = x.length();
    let chart = |d0: DVec3, t: [DVec3; 2], angle: f64| Chart {
        axes,
        e1,
        e2,
        x,
        d0,
        t,
        angle,
    };
    let search = |d0: DVec3, angle: f64| {
        let c = chart(d0, d0.any_orthonormal_pair().into(), angle);
        let p = c.descend(false);
        if Chart::within(&p, p.grad, angle) {
            return p;
        }
        // Stalled on a crease: with an exponent near 2 the surface folds along a coordinate
        // plane, where the distance has a kink across the fold and a smooth minimum along it.
        let mut best = p;
        for i in 0..3 {
            if p.s[i].abs() > 1e-3 * p.s.length() {
                continue;
            }
            let mut on = p.v;
            on[i] = 0.0;
            let along = DVec3::AXES[i].cross(on).normalize_or_zero();
            if along == DVec3::ZERO {
                continue;
            }
            let line = chart(on, [along, DVec3::AXES[i]], angle).descend(true);
            if line.f < best.f {
                best = line;
            }
        }
        best
    };
    let at_x = gauge(axes, e1, e2, x).value;
    let deep = r == 0.0 || at_x < 0.5;
    let warm = hint
        .filter(|h| h.is_finite() && *h != DVec3::ZERO)
        .and_then(|h| {
            let p = search(h, WARM_ANGLE);
            // The radial foot's squared distance bounds the closest one's.
            let radial = r * (1.0 - 1.0 / at_x);
            (p.f.is_finite() && p.f <= radial * radial * (1.0 + 1e-12)).then_some(p)
        });
    if let Some(p) = warm
        && !deep
        && Chart::within(&p, p.grad, WARM_ANGLE)
    {
        return foot_at(x, p);
    }
    let radial_start = if r > 0.0 {
        x / r
    } else {
        DVec3::AXES[axes.min_position()]
    };
    let mut best = search(radial_start, EXACT_ANGLE);
    if let Some(p) = warm
        && p.f < best.f
    {
        best = p;
    }
    if deep {
        for (i, axis) in DVec3::AXES.iter().enumerate() {
            let side = if x[i] < 0.0 { -1.0 } else { 1.0 };
            let other = search(*axis * side, EXACT_ANGLE);
            if other.f < best.f {
                best = other;
            }
        }
    }
    foot_at(x, best)
}

/// The [`Foot`] of the model-frame point `x` at the chart point `best`.
fn foot_at(x: DVec3, best: ChartPoint) -> Foot {
    let length = best.v.length();
    let d = best.v / length;
    let normal = best.g.grad_x.normalize_or_zero();
    // G is of degree one and ∇ₓG of degree zero: the gauge at d from the gauge at v.
    let mut at_d = best.g;
    at_d.value /= length;
    at_d.grad_shape = at_d.grad_shape.map(|g| g / length);
    let distance = best.f.sqrt();
    Foot {
        direction: d,
        point: best.s,
        normal,
        gauge: at_d,
        distance: if (x - best.s).dot(normal) < 0.0 {
            -distance
        } else {
            distance
        },
    }
}

/// The signed distance of `p` to the closest point of the superquadric of `pose` (tapering and
/// bending ignored).
pub fn surface_distance(pose: &InitialPose, p: DVec3) -> f64 {
    closest_point(&pose.shape, to_model(pose, p)).distance
}

/// The surface distance of `p` and its gradient. At the closest point the distance moves with
/// the surface along its normal n (the envelope theorem): ∂D/∂θ = −n·∂s/∂θ with the ray
/// direction held, and s = d/G(d) gives ∂s/∂θ = −d·(∂G/∂θ)/G².
pub fn surface(pose: &InitialPose, p: DVec3) -> Distance {
    surface_from(pose, p, None).0
}

/// [`surface`] with the search warm-started from `hint` ([`closest_point_from`]), and the foot's
/// ray direction, the hint for the next call.
pub fn surface_from(pose: &InitialPose, p: DVec3, hint: Option<DVec3>) -> (Distance, DVec3) {
    let x = to_model(pose, p);
    let foot = closest_point_from(&pose.shape, x, hint);
    let mut gradient = [0.0; NUM_UNKNOWNS];
    let g = foot.gauge;
    let k = foot.normal.dot(foot.direction) / (g.value * g.value);
    for (slot, d) in gradient[..5].iter_mut().zip(g.grad_shape) {
        *slot = k * d;
    }
    rigid_gradient(pose, x, foot.normal, &mut gradient);
    let distance = Distance {
        distance: foot.distance,
        gradient,
    };
    (distance, foot.direction)
}

/// Which distance a fit's residuals measure.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Metric {
    /// [`radial_distance`]: one gauge a point.
    Radial,
    /// [`surface_distance`]: a few gauges a point, exact.
    Surface,
    /// [`normal_distance`]: one gauge a point, the surface distance to first order.
    Normal,
}

impl Metric {
    /// The signed distance of `p` to the superquadric of `pose`.
    pub fn distance(self, pose: &InitialPose, p: DVec3) -> f64 {
        match self {
            Self::Radial => radial_distance(pose, p),
            Self::Surface => surface_distance(pose, p),
            Self::Normal => normal_distance(pose, p),
        }
    }

    /// The signed distance of `p` and its gradient.
    pub fn with_gradient(self, pose: &InitialPose, p: DVec3) -> Distance {
        match self {
            Self::Radial => radial(pose, p),
            Self::Surface => surface(pose, p),
            Self::Normal => normal(pose, p),
        }
    }

    /// [`Metric::distance`] with the surface distance's search warm-started from `hint`
    /// ([`closest_point_from`]), and the foot's ray direction (the radial distance needs no
    /// search: its hint and direction are ignored and zero).
    pub fn distance_from(self, pose: &InitialPose, p: DVec3, hint: Option<DVec3>) -> (f64, DVec3) {
        match self {
            Self::Radial => (radial_distance(pose, p), DVec3::ZERO),
            Self::Normal => (normal_distance(pose, p), DVec3::ZERO),
            Self::Surface => {
                let foot = closest_point_from(&pose.shape, to_model(pose, p), hint);
                (foot.distance, foot.direction)
            }
        }
    }

    /// [`Metric::with_gradient`] warm-started from `hint` (see [`Metric::distance_from`]).
    pub fn with_gradient_from(self, pose: &InitialPose, p: DVec3, hint: Option<DVec3>) -> Distance {
        match self {
            Self::Radial => radial(pose, p),
            Self::Normal => normal(pose, p),
            Self::Surface => surface_from(pose, p, hint).0,
        }
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::model::lm::apply_increment;
    use crate::model::superquadric::{inside_outside, shape_at};
    use crate::synthetic::superquadric_cloud;
    use glam::DQuat;

    /// A rotated, translated superquadric with exponents `e1`, `e2` (the tests' fixture).
    pub(crate) fn pose(e1: f64, e2: f64) -> InitialPose {
        InitialPose {
            translation: DVec3::new(0.2, -0.1, 0.3),
            rotation: DQuat::from_euler(glam::EulerRot::XYZ, 0.3, -0.5, 0.8),
            shape: SuperquadricParams {
                a: 1.2,
                a1: 0.7,
                a2: 1.0,
                a3: 0.5,
                e1,
                e2,
            },
        }
    }

    const POINTS: [DVec3; 5] = [
        DVec3::new(1.1, 0.4, -0.2),
        DVec3::new(-0.3, 0.9, 0.6),
        DVec3::new(0.25, -0.2, 0.35),
        DVec3::new(0.2, -0.1, 1.5),
        DVec3::new(-1.4, -0.8, 0.1),
    ];

    #[test]
    fn the_gauge_is_f_to_the_half_e1_and_its_gradients_match_central_differences() {
        let shape = pose(0.6, 1.4).shape;
        let axes = shape.semi_axes();
        let h = 1e-6;
        for x in POINTS {
            let g = gauge(axes, shape.e1, shape.e2, x);
            let f = inside_outside(&shape, x);
            assert!((g.value - f.powf(shape.e1 / 2.0)).abs() < 1e-12 * g.value);
            // Degree one: G(2x) = 2G(x).
            let g2 = gauge(axes, shape.e1, shape.e2, 2.0 * x).value;
            assert!((g2 - 2.0 * g.value).abs() < 1e-12 * g2);
            for i in 0..3 {
                let e = DVec3::AXES[i] * h;
                let num = (gauge(axes, shape.e1, shape.e2, x + e).value
                    - gauge(axes, shape.e1, shape.e2, x - e).value)
                    / (2.0 * h);
                assert!(
                    (num - g.grad_x[i]).abs() < 1e-6,
                    "x{i} {num} {}",
                    g.grad_x[i]
                );
                let (da, db) = (axes + e, axes - e);
                let num = (gauge(da, shape.e1, shape.e2, x).value
                    - gauge(db, shape.e1, shape.e2, x).value)
                    / (2.0 * h);
                assert!((num - g.grad_shape[i]).abs() < 1e-6, "A{i}");
            }
            let num = (gauge(axes, shape.e1 + h, shape.e2, x).value
                - gauge(axes, shape.e1 - h, shape.e2, x).value)
                / (2.0 * h);
            assert!((num - g.grad_shape[3]).abs() < 1e-6, "e1 {num}");
            let num = (gauge(axes, shape.e1, shape.e2 + h, x).value
                - gauge(axes, shape.e1, shape.e2 - h, x).value)
                / (2.0 * h);
            assert!((num - g.grad_shape[4]).abs() < 1e-6, "e2 {num}");
        }
    }

    #[test]
    fn the_gauge_stays_finite_at_extreme_exponents_and_distances() {
        let axes = DVec3::new(1.0, 0.5, 2.0);
        for (e1, e2) in [(0.01, 0.01), (0.01, 2.0), (2.0, 0.01)] {
            for x in [
                DVec3::new(1e150, 1e-150, 3.0),
                DVec3::new(0.0, 0.0, 1e-300),
                DVec3::new(0.3, 0.0, 0.0),
            ] {
                let g = gauge(axes, e1, e2, x);
                assert!(g.value.is_finite() && g.value > 0.0, "{e1} {e2} {x}");
                assert!(g.grad_x.is_finite() && g.grad_shape.iter().all(|d| d.is_finite()));
            }
        }
    }

    /// A distance as a function of the unknowns about `pose`.
    fn moved(metric: Metric, pose: &InitialPose, p: DVec3, k: usize, h: f64) -> f64 {
        let mut delta = [0.0; NUM_UNKNOWNS];
        delta[k] = h;
        metric.distance(&apply_increment(pose, &delta), p)
    }

    #[test]
    fn both_gradients_match_central_differences() {
        for metric in [Metric::Radial, Metric::Surface] {
            for (e1, e2) in [(0.6, 1.4), (1.0, 1.0), (0.3, 0.5)] {
                let pose = pose(e1, e2);
                // The surface distance is exact to ~10⁻¹⁰: a step that keeps that noise small.
                let h = if metric == Metric::Radial { 1e-6 } else { 1e-4 };
                for p in POINTS {
                    let r = metric.with_gradient(&pose, p);
                    assert!((r.distance - metric.distance(&pose, p)).abs() < 1e-12);
                    for k in 0..NUM_UNKNOWNS {
                        let numeric = (moved(metric, &pose, p, k, h)
                            - moved(metric, &pose, p, k, -h))
                            / (2.0 * h);
                        assert!(
                            (numeric - r.gradient[k]).abs() <= 1e-5 * (1.0 + numeric.abs()),
                            "{metric:?} ε ({e1}, {e2}) point {p}, unknown {k}: analytic {} \
                             numeric {numeric}",
                            r.gradient[k]
                        );
                    }
                }
            }
        }
    }

    #[test]
    fn distances_are_zero_on_the_surface_and_signed_off_it() {
        let pose = pose(0.6, 1.4);
        for metric in [Metric::Radial, Metric::Surface] {
            for p in superquadric_cloud(&pose.shape, pose.translation, pose.rotation, 50, 0.0, 1) {
                assert!(metric.distance(&pose, p).abs() < 1e-9, "{p}");
                let out = pose.translation + (p - pose.translation) * 1.1;
                let inside = pose.translation + (p - pose.translation) * 0.9;
                assert!(metric.distance(&pose, out) > 0.0);
                assert!(metric.distance(&pose, inside) < 0.0);
            }
        }
    }

    #[test]
    fn the_closest_point_is_the_nearest_of_a_dense_sampling() {
        for (e1, e2) in [
            (0.6, 1.4),
            (0.1, 0.1),
            (1.9, 0.3),
            (1.0, 1.0),
            (2.0, 2.0),
            (0.1, 2.0),
        ] {
            let shape = pose(e1, e2).shape;
            let n = 400;
            let samples: Vec<DVec3> = (0..=n)
                .flat_map(|i| {
                    let u =
                        -std::f64::consts::FRAC_PI_2 + std::f64::consts::PI * i as f64 / n as f64;
                    (0..2 * n).map(move |j| (u, std::f64::consts::PI * j as f64 / n as f64))
                })
                .map(|(u, v)| shape_at(&shape, u, v))
                .collect();
            for x in POINTS
                .iter()
                .chain(&[DVec3::new(2.0, 2.0, 2.0), DVec3::new(0.05, 0.02, 0.0)])
            {
                let foot = closest_point(&shape, *x);
                assert!((gauge(shape.semi_axes(), e1, e2, foot.point).value - 1.0).abs() < 1e-9);
                let sampled = samples
                    .iter()
                    .map(|s| (*s - *x).length())
                    .fold(f64::INFINITY, f64::min);
                // On the surface (checked above), so never nearer than the true closest point;
                // never farther than the dense sampling (to its spacing), nor than radial.
                assert!(
                    foot.distance.abs() <= sampled + 2e-3,
                    "ε ({e1}, {e2}) {x}: {} vs sampled {sampled}",
                    foot.distance
                );
                let radial =
                    (x.length() * (1.0 - 1.0 / gauge(shape.semi_axes(), e1, e2, *x).value)).abs();
                assert!(foot.distance.abs() <= radial + 1e-12);
            }
        }
    }
}
