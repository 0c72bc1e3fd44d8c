//! A tracked frame's fit as one least-squares problem of the engine ([`crate::model::lm`]):
//! the frame's points on the superquadric's surface, the prediction's prior, and the free space
//! the depth image shows.
//!
//! - **Data**: each gated point's exact distance to the surface, weighted by the outlier
//!   mixture (the plain fit's residual).
//! - **Prior** (the information form of a Kalman update, Metaxas & Terzopoulos 1993 made
//!   discrete): s·rᵀΛr with r the unknowns' difference from the prediction (semi-axes,
//!   exponents and translation subtracted; the rotation as log(R̄ᵀR)), Λ the prediction's
//!   information, and s the inliers' variance that turns it into the data's units.
//! - **Free space**: a depth pixel's ray is empty up to the surface it saw. Samples along each
//!   ray, in front of the observed depth by a margin, that fall inside the model are evidence
//!   against it: each ray adds the square of its deepest sample's radial distance (0 when none
//!   is inside). This keeps a model from growing into something seen behind it.
//! - **Support**: the plane the object stands on, when one was found ([`super::support`]): the
//!   lowest point of the model's surface below it, weighted as heavily as all the data.

use super::support::Support;
use crate::model::distance::{NUM_UNKNOWNS, radial, radial_distance};
use crate::model::frame::skew;
use crate::model::init::InitialPose;
use crate::model::lm::{LmOptions, Normal, Plain, Problem};
use crate::model::parallel::map_points;
use glam::{DMat3, DVec3};

/// N unknowns' information matrix.
pub type Information = [[f64; NUM_UNKNOWNS]; NUM_UNKNOWNS];

/// The prediction a frame's fit is held to.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Prior {
    /// The predicted pose and shape.
    pub mean: InitialPose,
    /// Its information Λ (inverse covariance) over the unknowns, in the engine's order.
    pub information: Information,
    /// The data's variance s that scales the prior into the data's units.
    pub scale: f64,
}

/// r = q ⊖ q̄ over the unknowns: differences of the semi-axes, exponents and translation, and
/// log(R̄ᵀR) of the rotations.
pub fn prior_residual(mean: &InitialPose, pose: &InitialPose) -> [f64; NUM_UNKNOWNS] {
    let mut r = [0.0; NUM_UNKNOWNS];
    let da = pose.shape.semi_axes() - mean.shape.semi_axes();
    r[..3].copy_from_slice(&da.to_array());
    r[3] = pose.shape.e1 - mean.shape.e1;
    r[4] = pose.shape.e2 - mean.shape.e2;
    r[5..8].copy_from_slice(&(pose.translation - mean.translation).to_array());
    r[8..11].copy_from_slice(&rotation_log(mean, pose).to_array());
    r
}

/// log(R̄ᵀR) as a rotation vector, the short way round.
fn rotation_log(mean: &InitialPose, pose: &InitialPose) -> DVec3 {
    let mut q = (mean.rotation.inverse() * pose.rotation).normalize();
    if q.w < 0.0 {
        q = -q;
    }
    q.to_scaled_axis()
}

/// The inverse right Jacobian of SO(3) at φ: d log(exp(φ)·exp(ω)) / dω at ω = 0.
fn inverse_right_jacobian(phi: DVec3) -> DMat3 {
    let theta = phi.length();
    let k = skew(phi);
    let c = if theta < 1e-6 {
        1.0 / 12.0
    } else {
        1.0 / (theta * theta) - (1.0 + theta.cos()) / (2.0 * theta * theta.sin())
    };
    DMat3::IDENTITY + k * 0.5 + k * k * c
}

/// The prior's residual r and its Jacobian over the unknowns' increment at `pose`.
fn prior_jacobian(
    mean: &InitialPose,
    pose: &InitialPose,
) -> ([f64; NUM_UNKNOWNS], [[f64; NUM_UNKNOWNS]; NUM_UNKNOWNS]) {
    let r = prior_residual(mean, pose);
    let mut j = [[0.0; NUM_UNKNOWNS]; NUM_UNKNOWNS];
    for k in 0..8 {
        j[k][k] = 1.0;
    }
    let jr = inverse_right_jacobian(DVec3::new(r[8], r[9], r[10]));
    for a in 0..3 {
        for b in 0..3 {
            j[8 + a][8 + b] = jr.col(b)[a];
        }
    }
    (r, j)
}

/// One ray of free space: the samples along it known to be empty.
#[derive(Clone, Debug, PartialEq)]
pub struct FreeRay {
    /// Camera-frame points in front of the observed depth.
    pub samples: Vec<DVec3>,
}

impl FreeRay {
    /// The deepest sample inside the model of `pose` and its radial distance (negative), or
    /// `None` when every sample is outside.
    fn deepest(&self, pose: &InitialPose) -> Option<(DVec3, f64)> {
        self.samples
            .iter()
            .map(|&s| (s, radial_distance(pose, s)))
            .filter(|(_, d)| *d < 0.0)
            .min_by(|a, b| a.1.total_cmp(&b.1))
    }
}

/// A tracked frame's problem (see the module docs).
pub(crate) struct Tracked<'a> {
    plain: Plain<'a>,
    prior: Option<&'a Prior>,
    free: &'a [FreeRay],
    support: Option<&'a Support>,
}

impl<'a> Tracked<'a> {
    /// The problem of the gated `points` under `opts`, held to `prior` and kept out of `free`.
    pub(crate) fn new(
        points: &'a [DVec3],
        opts: &LmOptions,
        prior: Option<&'a Prior>,
        free: &'a [FreeRay],
        support: Option<&'a Support>,
    ) -> Self {
        Self {
            plain: Plain::new(points, opts, None),
            prior,
            free,
            support,
        }
    }

    /// The support term's weight: as much as all the points together.
    fn support_weight(&self) -> f64 {
        self.plain.len().max(1) as f64
    }

    /// The support term at `pose`.
    pub(crate) fn support_cost(&self, pose: &InitialPose) -> f64 {
        self.support.map_or(0.0, |s| {
            let below = s.depth_below(pose).0;
            self.support_weight() * below * below
        })
    }

    /// The free-space term at `pose`: Σ over rays of the deepest inside sample's distance².
    pub(crate) fn free_cost(&self, pose: &InitialPose) -> f64 {
        map_points(self.free.len(), |i| {
            self.free[i].deepest(pose).map_or(0.0, |(_, d)| d * d)
        })
        .into_iter()
        .sum()
    }

    /// The prior term at `pose`.
    pub(crate) fn prior_cost(&self, pose: &InitialPose) -> f64 {
        let Some(p) = self.prior else {
            return 0.0;
        };
        let r = prior_residual(&p.mean, pose);
        let mut c = 0.0;
        for a in 0..NUM_UNKNOWNS {
            for b in 0..NUM_UNKNOWNS {
                c += r[a] * p.information[a][b] * r[b];
            }
        }
        p.scale * c
    }
}

impl Problem<NUM_UNKNOWNS> for Tracked<'_> {
    type Model = InitialPose;
    type Foot = DVec3;

    fn len(&self) -> usize {
        self.plain.len()
    }

    fn evaluate(&self, pose: &InitialPose, hints: &[DVec3]) -> (Vec<f64>, Vec<DVec3>) {
        self.plain.evaluate(pose, hints)
    }

    fn gradient(
        &self,
        pose: &InitialPose,
        i: usize,
        foot: Option<&DVec3>,
    ) -> Option<(f64, [f64; NUM_UNKNOWNS])> {
        self.plain.gradient(pose, i, foot)
    }

    fn moved(&self, pose: &InitialPose, delta: &[f64; NUM_UNKNOWNS]) -> InitialPose {
        self.plain.moved(pose, delta)
    }

    fn on_bound(&self, pose: &InitialPose, k: usize) -> (bool, bool) {
        self.plain.on_bound(pose, k)
    }

    fn held(&self, k: usize) -> bool {
        self.plain.held(k)
    }

    fn extra_cost(&self, pose: &InitialPose, _weights: &[f64], _total: f64) -> f64 {
        self.prior_cost(pose) + self.free_cost(pose) + self.support_cost(pose)
    }

    fn add_extra_normal(
        &self,
        pose: &InitialPose,
        _weights: &[f64],
        _total: f64,
        n: &mut Normal<NUM_UNKNOWNS>,
    ) {
        if let Some(p) = self.prior {
            let (r, j) = prior_jacobian(&p.mean, pose);
            // ΛJ and Λr, then JᵀΛJ and JᵀΛr, all times s.
            let mut lj = [[0.0; NUM_UNKNOWNS]; NUM_UNKNOWNS];
            let mut lr = [0.0; NUM_UNKNOWNS];
            for a in 0..NUM_UNKNOWNS {
                for b in 0..NUM_UNKNOWNS {
                    lr[a] += p.information[a][b] * r[b];
                    for c in 0..NUM_UNKNOWNS {
                        lj[a][c] += p.information[a][b] * j[b][c];
                    }
                }
            }
            for a in 0..NUM_UNKNOWNS {
                for c in 0..NUM_UNKNOWNS {
                    n.1[a] += p.scale * j[c][a] * lr[c];
                }
                for b in 0..=a {
                    let v: f64 = (0..NUM_UNKNOWNS).map(|c| j[c][a] * lj[c][b]).sum();
                    n.0[a][b] += p.scale * v;
                }
            }
        }
        if let Some((r, g)) = self.support.and_then(|s| s.residual(pose)) {
            let w = self.support_weight();
            for a in 0..NUM_UNKNOWNS {
                n.1[a] += w * g[a] * r;
                for b in 0..=a {
                    n.0[a][b] += w * g[a] * g[b];
                }
            }
        }
        for ray in self.free {
            let Some((s, _)) = ray.deepest(pose) else {
                continue;
            };
            let d = radial(pose, s);
            for a in 0..NUM_UNKNOWNS {
                n.1[a] += d.gradient[a] * d.distance;
                for b in 0..=a {
                    n.0[a][b] += d.gradient[a] * d.gradient[b];
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::lm::apply_increment;
    use crate::model::superquadric::SuperquadricParams;
    use glam::DQuat;

    fn pose(turn: f64) -> InitialPose {
        InitialPose {
            translation: DVec3::new(0.05, -0.02, 1.1),
            rotation: DQuat::from_euler(glam::EulerRot::XYZ, 0.4, turn, -0.9),
            shape: SuperquadricParams {
                a: 1.0,
                a1: 0.05,
                a2: 0.07,
                a3: 0.09,
                e1: 0.6,
                e2: 1.2,
            }
            .normalized(),
        }
    }

    #[test]
    fn the_prior_jacobian_matches_central_differences() {
        let mean = pose(0.2);
        let mut at = pose(1.3);
        at.translation += DVec3::new(0.01, 0.02, -0.03);
        let (_, j) = prior_jacobian(&mean, &at);
        let h = 1e-6;
        for k in 0..NUM_UNKNOWNS {
            let mut d = [0.0; NUM_UNKNOWNS];
            d[k] = h;
            let plus = prior_residual(&mean, &apply_increment(&at, &d));
            d[k] = -h;
            let minus = prior_residual(&mean, &apply_increment(&at, &d));
            for a in 0..NUM_UNKNOWNS {
                let numeric = (plus[a] - minus[a]) / (2.0 * h);
                assert!(
                    (numeric - j[a][k]).abs() < 1e-6,
                    "∂r{a}/∂δ{k}: {numeric} against {}",
                    j[a][k]
                );
            }
        }
    }

    #[test]
    fn the_extra_normal_is_the_extra_cost_gradient() {
        // The extra terms' JᵀWr is half the gradient of their cost: check it by central
        // differences, with a prior and with free samples inside the model.
        let mean = pose(0.2);
        let at = pose(0.35);
        let mut information = [[0.0; NUM_UNKNOWNS]; NUM_UNKNOWNS];
        for a in 0..NUM_UNKNOWNS {
            information[a][a] = 100.0 + a as f64;
            if a > 0 {
                information[a][a - 1] = 5.0;
                information[a - 1][a] = 5.0;
            }
        }
        let prior = Prior {
            mean,
            information,
            scale: 1e-4,
        };
        let free = vec![
            FreeRay {
                samples: vec![at.translation + DVec3::new(0.01, 0.0, 0.0)],
            },
            FreeRay {
                samples: vec![
                    at.translation + DVec3::new(0.0, 0.03, -0.01),
                    at.translation + DVec3::new(0.0, 0.5, 0.0),
                ],
            },
        ];
        let opts = crate::model::lm::tests::options(0.0);
        let problem = Tracked::new(&[], &opts, Some(&prior), &free, None);
        let mut n = ([[0.0; NUM_UNKNOWNS]; NUM_UNKNOWNS], [0.0; NUM_UNKNOWNS]);
        problem.add_extra_normal(&at, &[], 0.0, &mut n);
        let h = 1e-7;
        for k in 0..NUM_UNKNOWNS {
            let mut d = [0.0; NUM_UNKNOWNS];
            d[k] = h;
            let plus = problem.extra_cost(&apply_increment(&at, &d), &[], 0.0);
            d[k] = -h;
            let minus = problem.extra_cost(&apply_increment(&at, &d), &[], 0.0);
            let numeric = (plus - minus) / (4.0 * h);
            let scale = n.1[k].abs().max(1e-6);
            assert!(
                (numeric - n.1[k]).abs() < 1e-4 * scale + 1e-9,
                "unknown {k}: {numeric} against {}",
                n.1[k]
            );
        }
        assert!(problem.free_cost(&at) > 0.0);
    }
}
