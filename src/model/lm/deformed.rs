//! Levenberg–Marquardt on a tapered and bent superquadric (beyond the paper).
//!
//! The surface is m(v) = T(s(v)) in the model frame, x = c + R m: s(v) = v / G(v) the
//! superquadric's point on the ray v ([`super::super::distance::gauge`]) and T the global
//! deformation of [`crate::model::deform`]. Each point keeps a foot, the ray v of its closest
//! surface point, found by Gauss–Newton steps in a chart of rays about the last foot (as
//! [`super::super::distance::closest_point`] does for the undeformed surface). The residual is
//! the point's offset from its foot along the surface normal n = D⁻ᵀ∇G / |D⁻ᵀ∇G| (D = ∂T/∂s),
//! and with the foot held its gradient over the unknowns is the distance's (the envelope
//! theorem). The unknowns are the 11 of [`NUM_UNKNOWNS`] and the deformation
//! (t_x, t_y, b_x, b_y): [`NUM_DEFORMED`].

use super::engine::{LmOptions, Problem, solve_em};
use super::plain::{bounded_increment, on_bound};
use crate::model::deform::{GlobalDeformation, NUM_DEFORM};
use crate::model::distance::{NUM_UNKNOWNS, gauge};
use crate::model::init::InitialPose;
use crate::model::parallel::map_points;
use glam::{DMat3, DVec3};

/// Unknowns of a deformed fit: [`NUM_UNKNOWNS`] and the deformation's [`NUM_DEFORM`].
pub const NUM_DEFORMED: usize = NUM_UNKNOWNS + NUM_DEFORM;

/// A pose, shape and global deformation.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DeformedPose {
    /// Translation, rotation and superquadric.
    pub pose: InitialPose,
    /// Tapering and bending.
    pub deformation: GlobalDeformation,
}

/// Gauss–Newton steps a foot takes from a cold start (the ray through the point) and from a warm
/// one (its foot on the last iterate).
const FOOT_STEPS: (u32, u32) = (16, 4);

/// A point's foot: its ray and what the residual needs there.
#[derive(Clone, Copy)]
struct Foot {
    ray: DVec3,
    /// The surface point m (model frame).
    m: DVec3,
    /// The unit normal there (model frame).
    n: DVec3,
}

/// The surface point of ray `v`, with ∂m/∂v along the chart's tangents `t`, and the gauge.
fn surface_at(
    axes: DVec3,
    (e1, e2): (f64, f64),
    deformation: &GlobalDeformation,
    v: DVec3,
    t: [DVec3; 2],
) -> (DVec3, [DVec3; 2], crate::model::distance::Gauge, DMat3) {
    let g = gauge(axes, e1, e2, v);
    let inv = 1.0 / g.value;
    let s = v * inv;
    let jt = deformation.jacobian(s, axes.z);
    let ds = t.map(|t| t * inv - v * (g.grad_x.dot(t) * inv * inv));
    (jt.value, ds.map(|d| jt.d_point * d), g, jt.d_point)
}

/// The foot of model-frame point `y` on `p`'s surface, from ray `start` (a unit vector): at most
/// `steps` Newton steps on ½|m − y|² over a chart of rays about `start` (its Hessian by
/// differences of the analytic gradient; Gauss–Newton steps where it is not positive definite),
/// each damped until it brings m closer. Gauss–Newton alone converges only linearly, at the rate
/// of the distance over the radius of curvature.
fn foot(p: &DeformedPose, y: DVec3, start: DVec3, steps: u32) -> Foot {
    let axes = p.pose.shape.semi_axes();
    let e = (p.pose.shape.e1, p.pose.shape.e2);
    let d0 = start.normalize_or(DVec3::Z);
    let t: [DVec3; 2] = d0.any_orthonormal_pair().into();
    // (ray, m, ∂m/∂c, gauge, ∂T/∂s, f, ∇f)
    let at = |c: [f64; 2]| {
        let v = d0 + t[0] * c[0] + t[1] * c[1];
        let (m, j, g, dt) = surface_at(axes, e, &p.deformation, v, t);
        let r = m - y;
        (
            v,
            m,
            j,
            g,
            dt,
            r.length_squared(),
            [j[0].dot(r), j[1].dot(r)],
        )
    };
    let mut c = [0.0; 2];
    let mut cur = at(c);
    let mut damping = 0.0;
    for _ in 0..steps {
        let (_, _, j, _, _, f, grad) = cur;
        let g2 = grad[0] * grad[0] + grad[1] * grad[1];
        // At rest: the offset normal to the surface to 10⁻⁸ rad.
        if !(g2 > 1e-16 * f * (j[0].length_squared() + j[1].length_squared())) {
            break;
        }
        let gn = [
            [j[0].dot(j[0]), j[0].dot(j[1])],
            [j[0].dot(j[1]), j[1].dot(j[1])],
        ];
        let h = 1e-7 * (1.0 + c[0].abs().max(c[1].abs()));
        let (a0, a1) = (at([c[0] + h, c[1]]).6, at([c[0], c[1] + h]).6);
        let off = 0.5 * ((a0[1] - grad[1]) + (a1[0] - grad[0])) / h;
        let newton = [[(a0[0] - grad[0]) / h, off], [off, (a1[1] - grad[1]) / h]];
        let positive =
            newton[0][0] > 0.0 && newton[0][0] * newton[1][1] - newton[0][1] * newton[0][1] > 0.0;
        let m = if positive { newton } else { gn };
        let mut moved = false;
        for _ in 0..10 {
            let (m00, m11) = (m[0][0] + damping * gn[0][0], m[1][1] + damping * gn[1][1]);
            let det = m00 * m11 - m[0][1] * m[0][1];
            if m00 > 0.0 && det > 0.0 {
                let dc = [
                    (-grad[0] * m11 + grad[1] * m[0][1]) / det,
                    (-grad[1] * m00 + grad[0] * m[0][1]) / det,
                ];
                let next_c = [c[0] + dc[0], c[1] + dc[1]];
                let next = at(next_c);
                if next.5 < f {
                    (c, cur, moved) = (next_c, next, true);
                    damping = if damping < 1e-6 { 0.0 } else { damping * 0.25 };
                    break;
                }
            }
            damping = (damping * 10.0).max(1e-3);
        }
        if !moved {
            break;
        }
    }
    let (v, m, _, g, dt, ..) = cur;
    // The normal of T(level set): D⁻ᵀ ∇G.
    let n = dt
        .inverse()
        .transpose()
        .mul_vec3(g.grad_x)
        .normalize_or_zero();
    Foot {
        ray: v.normalize_or(d0),
        m,
        n,
    }
}

/// The point `q`'s signed distance from its foot `f` on `p`, and with `gradient` its gradient
/// over the [`NUM_DEFORMED`] unknowns (the foot's ray held).
fn residual(
    p: &DeformedPose,
    q: DVec3,
    f: &Foot,
    gradient: Option<&mut [f64; NUM_DEFORMED]>,
) -> f64 {
    let r = DMat3::from_quat(p.pose.rotation);
    let y = r.transpose() * (q - p.pose.translation);
    let e = f.n.dot(y - f.m);
    if let Some(grad) = gradient {
        let axes = p.pose.shape.semi_axes();
        let (e1, e2) = (p.pose.shape.e1, p.pose.shape.e2);
        let g = gauge(axes, e1, e2, f.ray);
        let s = f.ray / g.value;
        let jt = p.deformation.jacobian(s, axes.z);
        let k = 1.0 / (g.value * g.value);
        for i in 0..5 {
            // ∂s/∂θ = −v ∂G/∂θ / G², then through T; A_z is also T's height.
            let mut dm = jt.d_point * (-f.ray * (g.grad_shape[i] * k));
            if i == 2 {
                dm += jt.d_height;
            }
            grad[i] = -f.n.dot(dm);
        }
        let tr = -(r * f.n);
        grad[5..8].copy_from_slice(&tr.to_array());
        grad[8..11].copy_from_slice(&f.n.cross(y).to_array());
        for (j, d) in jt.d_params.iter().enumerate() {
            grad[NUM_UNKNOWNS + j] = -f.n.dot(*d);
        }
    }
    e
}

/// `p` moved by `delta`, within `opts`' bounds and the deformation's
/// ([`GlobalDeformation::clamped`]).
fn moved(p: &DeformedPose, delta: &[f64; NUM_DEFORMED], opts: &LmOptions) -> DeformedPose {
    let mut rigid = [0.0; NUM_UNKNOWNS];
    rigid.copy_from_slice(&delta[..NUM_UNKNOWNS]);
    let pose = bounded_increment(&p.pose, &rigid, opts.max_semi_axis, opts.min_epsilon);
    let q = p.deformation.to_array();
    let deformation =
        GlobalDeformation::from_array(std::array::from_fn(|j| q[j] + delta[NUM_UNKNOWNS + j]))
            .clamped(pose.shape.semi_axes());
    DeformedPose { pose, deformation }
}

/// Rays a cold foot search starts from: [`SEED_RAYS`] spread evenly over the sphere (a Fibonacci
/// lattice), the nearest of their surface points to the point chosen. The ray through the point
/// itself can start the search on the wrong side of a bent or strongly tapered surface.
pub const SEED_RAYS: usize = 1024;

/// For each model-frame point of `ys`, the ray of the nearest of [`SEED_RAYS`] surface points of
/// `p`.
fn seed_rays(p: &DeformedPose, ys: &[DVec3]) -> Vec<DVec3> {
    let axes = p.pose.shape.semi_axes();
    let golden = std::f64::consts::PI * (3.0 - 5f64.sqrt());
    let rays: Vec<DVec3> = (0..SEED_RAYS)
        .map(|i| {
            let z = 1.0 - (2 * i + 1) as f64 / SEED_RAYS as f64;
            let r = (1.0 - z * z).sqrt();
            let phi = golden * i as f64;
            DVec3::new(r * phi.cos(), r * phi.sin(), z)
        })
        .collect();
    let surface: Vec<DVec3> = rays
        .iter()
        .map(|v| {
            let g = gauge(axes, p.pose.shape.e1, p.pose.shape.e2, *v);
            p.deformation.apply(*v / g.value, axes.z)
        })
        .collect();
    crate::model::nearest::nearest_indices(&surface, ys)
        .into_iter()
        .map(|i| rays[i as usize])
        .collect()
}

/// |distance| of each of `points` from the surface of `p`: each point's foot searched from the
/// nearest of [`SEED_RAYS`] surface points. The residuals of a tapered or bent superquadric.
pub fn deformed_distances(p: &DeformedPose, points: &[DVec3]) -> Vec<f64> {
    feet_and_cost(p, points, &[])
        .1
        .iter()
        .map(|e| e.abs())
        .collect()
}

/// Every point's foot on `p` (warm-started from `feet` when they are there, else from
/// [`seed_rays`]) and its signed distance.
fn feet_and_cost(p: &DeformedPose, points: &[DVec3], feet: &[Foot]) -> (Vec<Foot>, Vec<f64>) {
    let r = DMat3::from_quat(p.pose.rotation).transpose();
    let ys: Vec<DVec3> = points
        .iter()
        .map(|q| r * (*q - p.pose.translation))
        .collect();
    let cold = if feet.len() == points.len() {
        Vec::new()
    } else {
        seed_rays(p, &ys)
    };
    let one = |i: usize| {
        let f = match feet.get(i) {
            Some(f) if cold.is_empty() => foot(p, ys[i], f.ray, FOOT_STEPS.1),
            _ => foot(p, ys[i], cold[i], FOOT_STEPS.0),
        };
        (f, residual(p, points[i], &f, None))
    };
    map_points(points.len(), one).into_iter().unzip()
}

/// The tapered and bent superquadric fitted to `points` (see the module docs), with the
/// deformation coordinates (t_x, t_y, b_x, b_y) that `free` does not free held.
struct Deformed<'a> {
    points: &'a [DVec3],
    opts: &'a LmOptions,
    free: [bool; NUM_DEFORM],
}

impl Problem<NUM_DEFORMED> for Deformed<'_> {
    type Model = DeformedPose;
    type Foot = Foot;

    fn len(&self) -> usize {
        self.points.len()
    }

    fn evaluate(&self, p: &DeformedPose, hints: &[Foot]) -> (Vec<f64>, Vec<Foot>) {
        let (feet, e) = feet_and_cost(p, self.points, hints);
        (e, feet)
    }

    fn gradient(
        &self,
        p: &DeformedPose,
        i: usize,
        foot: Option<&Foot>,
    ) -> Option<(f64, [f64; NUM_DEFORMED])> {
        let mut g = [0.0; NUM_DEFORMED];
        let r = residual(p, self.points[i], foot?, Some(&mut g));
        Some((r, g))
    }

    fn moved(&self, p: &DeformedPose, delta: &[f64; NUM_DEFORMED]) -> DeformedPose {
        moved(p, delta, self.opts)
    }

    fn on_bound(&self, p: &DeformedPose, k: usize) -> (bool, bool) {
        on_bound(&p.pose, k, self.opts.max_semi_axis, self.opts.min_epsilon)
    }

    fn held(&self, k: usize) -> bool {
        (self.opts.hold_exponents && (k == 3 || k == 4))
            || (k >= NUM_UNKNOWNS && !self.free[k - NUM_UNKNOWNS])
    }
}

/// Where [`fit_deformed`] came to rest.
#[derive(Clone, Debug, PartialEq)]
pub struct DeformedFit {
    /// The pose, shape and deformation.
    pub pose: DeformedPose,
    /// Mean |distance| of the points from the surface.
    pub mean_distance: f64,
    /// Levenberg–Marquardt steps taken.
    pub iterations: u32,
    /// True when a round's progress fell below the tolerance.
    pub converged: bool,
}

/// The engine's EM rounds (the module `engine`) on the deformed surface from `start`, from an
/// inlier variance of at least `sigma2` and the start's own spread; `free` says which
/// deformation coordinates move (t_x, t_y, b_x, b_y); the others are held at the start's.
pub fn fit_deformed(
    points: &[DVec3],
    start: &DeformedPose,
    sigma2: f64,
    opts: &LmOptions,
    free: [bool; NUM_DEFORM],
) -> DeformedFit {
    let problem = Deformed { points, opts, free };
    let fit = solve_em(&problem, start, sigma2, true, opts);
    let e = &fit.residuals;
    DeformedFit {
        pose: fit.model,
        mean_distance: e.iter().map(|x| x.abs()).sum::<f64>() / e.len().max(1) as f64,
        iterations: fit.iterations,
        converged: fit.converged,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::lm::{Metric, Mixture};
    use crate::model::superquadric::SuperquadricParams;

    fn deformed() -> DeformedPose {
        DeformedPose {
            pose: InitialPose {
                translation: DVec3::new(0.2, -0.1, 0.3),
                rotation: glam::DQuat::from_euler(glam::EulerRot::XYZ, 0.3, -0.5, 0.8),
                shape: SuperquadricParams {
                    a: 1.5,
                    a1: 0.35,
                    a2: 0.3,
                    a3: 1.0,
                    e1: 0.6,
                    e2: 1.2,
                },
            },
            deformation: GlobalDeformation {
                taper: [0.3, -0.2],
                bend: [0.25, 0.1],
            },
        }
    }

    const POINTS: [DVec3; 4] = [
        DVec3::new(0.7, 0.2, 0.9),
        DVec3::new(-0.3, 0.6, -0.4),
        DVec3::new(0.1, -0.5, 1.4),
        DVec3::new(0.5, 0.0, -1.0),
    ];

    #[test]
    fn the_deformed_distance_gradient_matches_central_differences() {
        let p = deformed();
        let opts = LmOptions {
            mixture: Mixture {
                outlier_ratio: 0.0,
                outlier_density: 1.0,
                sigma2_floor: 1e-12,
            },
            max_rounds: 1,
            steps_per_round: 1,
            tolerance: 1e-6,
            metric: Metric::Surface,
            max_semi_axis: f64::INFINITY,
            min_epsilon: crate::model::superquadric::LEAST_EPSILON,
            hold_exponents: false,
            own_sigma2: false,
        };
        // The distance at the foot found afresh at each pose.
        let distance = |p: &DeformedPose, q: DVec3| {
            let y = DMat3::from_quat(p.pose.rotation).transpose() * (q - p.pose.translation);
            let f = foot(p, y, y, 50);
            residual(p, q, &f, None)
        };
        let h = 1e-6;
        for q in POINTS {
            let y = DMat3::from_quat(p.pose.rotation).transpose() * (q - p.pose.translation);
            let f = foot(&p, y, y, 50);
            let mut g = [0.0; NUM_DEFORMED];
            let d = residual(&p, q, &f, Some(&mut g));
            assert!(d.is_finite());
            // At the foot the offset is along the normal: |y − m| = |d|.
            assert!(
                ((y - f.m).length() - d.abs()).abs() < 1e-9 * d.abs(),
                "{q}: {} vs {d}",
                (y - f.m).length()
            );
            for k in 0..NUM_DEFORMED {
                let mut delta = [0.0; NUM_DEFORMED];
                delta[k] = h;
                let up = distance(&moved(&p, &delta, &opts), q);
                delta[k] = -h;
                let down = distance(&moved(&p, &delta, &opts), q);
                let numeric = (up - down) / (2.0 * h);
                assert!(
                    (numeric - g[k]).abs() <= 1e-5 * (1.0 + numeric.abs()),
                    "point {q}, unknown {k}: analytic {} numeric {numeric}",
                    g[k]
                );
            }
        }
    }

    #[test]
    fn a_deformed_fit_recovers_its_taper_and_bend_and_its_cost_falls() {
        let truth = deformed();
        // Points on the true surface: rays through the sphere, mapped by T and the pose.
        let mut rng = crate::synthetic::Rng::new(3);
        let axes = truth.pose.shape.semi_axes();
        let points: Vec<DVec3> = (0..600)
            .map(|_| {
                let v = DVec3::new(rng.normal(), rng.normal(), rng.normal());
                let g = gauge(axes, truth.pose.shape.e1, truth.pose.shape.e2, v);
                let m = truth.deformation.apply(v / g.value, axes.z);
                truth.pose.translation + truth.pose.rotation * m
            })
            .collect();
        let mut start = truth;
        start.deformation = GlobalDeformation::IDENTITY;
        start.pose.shape.e1 = 1.0;
        start.pose.translation += DVec3::new(0.05, -0.03, 0.02);
        let opts = LmOptions {
            mixture: Mixture {
                outlier_ratio: 0.0,
                outlier_density: 1.0,
                sigma2_floor: 1e-12,
            },
            max_rounds: 50,
            steps_per_round: 5,
            tolerance: 1e-6,
            metric: Metric::Surface,
            max_semi_axis: f64::INFINITY,
            min_epsilon: crate::model::superquadric::LEAST_EPSILON,
            hold_exponents: false,
            own_sigma2: false,
        };
        let before = feet_and_cost(&start, &points, &[]).1;
        let fit = fit_deformed(&points, &start, 1e-2, &opts, [true; NUM_DEFORM]);
        let before = before.iter().map(|x| x.abs()).sum::<f64>() / points.len() as f64;
        assert!(
            fit.mean_distance < 1e-6,
            "{} from {before}",
            fit.mean_distance
        );
        let (found, want) = (
            fit.pose.deformation.to_array(),
            truth.deformation.to_array(),
        );
        for (f, w) in found.iter().zip(want) {
            assert!((f - w).abs() < 1e-4, "{found:?} against {want:?}");
        }
        // Held coordinates stay where they start.
        let held = fit_deformed(&points, &start, 1e-2, &opts, [true, true, false, false]);
        assert_eq!(held.pose.deformation.bend, [0.0, 0.0]);
        assert!(held.mean_distance > fit.mean_distance && held.mean_distance < before);
    }
}
