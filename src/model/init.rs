//! Automatic initialisation from the data's centroid and central moments, as the paper's
//! conclusion proposes ("initial values may be estimated by rough segmentation and calculation of
//! central moments of the data"), so nobody has to place the first superquadric by hand.
//!
//! The principal axes of the second central moments give the orientation: the model's z axis
//! (the one whose profile ε1 shapes) along the axis of largest spread, x along the middle one,
//! y = z × x. Each axis's sign is chosen so that the third central moment along it is ≥ 0, which
//! makes the frame follow the data under rotation (equivariance). The centre and the semi-axes
//! come from the robust extent (1st–99th percentile) of the data along each axis, so a one-view
//! scan, whose centroid lies off-centre, still gets a box around what was seen.

use super::dynamics::ModelState;
use super::fem::Tessellation;
use super::linalg::symmetric_eigen3;
use super::superquadric::SuperquadricParams;
use glam::{DMat3, DQuat, DVec3};

/// A rigid pose and global shape: everything but the local displacements.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct InitialPose {
    /// q_c
    pub translation: DVec3,
    /// q_θ
    pub rotation: DQuat,
    /// q_s
    pub shape: SuperquadricParams,
}

impl InitialPose {
    /// The pose and global shape of a model state (its local displacements dropped).
    pub fn of(state: &super::dynamics::ModelState) -> Self {
        Self {
            translation: state.translation,
            rotation: state.rotation,
            shape: state.shape,
        }
    }

    /// Whether `p` (world) lies strictly inside the superquadric: its inside–outside function
    /// ([`super::superquadric::inside_outside`]) below 1 in the model frame.
    pub fn contains(&self, p: DVec3) -> bool {
        let local = self.rotation.inverse() * (p - self.translation);
        super::superquadric::inside_outside(&self.shape, local) < 1.0
    }
}

/// The centroid and second central moments of a point set.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Moments {
    /// Mean of the points.
    pub centroid: DVec3,
    /// Covariance Σ (p − μ)(p − μ)ᵀ / m.
    pub covariance: DMat3,
}

/// Centroid and covariance of `points` (which must be non-empty).
pub fn moments(points: &[DVec3]) -> Moments {
    let m = points.len().max(1) as f64;
    let centroid = points.iter().copied().sum::<DVec3>() / m;
    let mut cov = DMat3::ZERO;
    for p in points {
        let d = *p - centroid;
        cov += DMat3::from_cols(d * d.x, d * d.y, d * d.z);
    }
    Moments {
        centroid,
        covariance: cov * (1.0 / m),
    }
}

/// The principal frame: columns (x, y, z) with z along the largest spread, a proper rotation whose
/// axis signs follow the third moments (see the module docs).
pub fn principal_frame(points: &[DVec3]) -> DMat3 {
    let mo = moments(points);
    let (_, vecs) = symmetric_eigen3(&mo.covariance);
    let skew_sign = |axis: DVec3| {
        let third: f64 = points
            .iter()
            .map(|p| (*p - mo.centroid).dot(axis).powi(3))
            .sum();
        if third < 0.0 { -axis } else { axis }
    };
    let z = skew_sign(vecs.col(2));
    let x = skew_sign(vecs.col(1));
    DMat3::from_cols(x, z.cross(x), z)
}

/// The `q` quantile of `sorted` (ascending, non-empty), interpolated between neighbours.
pub(crate) fn quantile(sorted: &[f64], q: f64) -> f64 {
    let pos = q * (sorted.len() - 1) as f64;
    let (lo, hi) = (pos.floor() as usize, pos.ceil() as usize);
    sorted[lo] + (sorted[hi] - sorted[lo]) * (pos - lo as f64)
}

/// The initial superquadric (ε1 = ε2 = 1, an ellipsoid) boxing the data in its principal frame.
pub fn initial_pose(points: &[DVec3]) -> InitialPose {
    let frame = principal_frame(points);
    let centroid = moments(points).centroid;
    let mut centre_local = DVec3::ZERO;
    let mut semi = DVec3::ZERO;
    for axis in 0..3 {
        let mut proj: Vec<f64> = points
            .iter()
            .map(|p| (*p - centroid).dot(frame.col(axis)))
            .collect();
        proj.sort_by(f64::total_cmp);
        let (lo, hi) = (quantile(&proj, 0.01), quantile(&proj, 0.99));
        centre_local[axis] = 0.5 * (lo + hi);
        semi[axis] = 0.5 * (hi - lo);
    }
    let largest = semi.max_element().max(f64::MIN_POSITIVE);
    let semi = semi.max(DVec3::splat(0.05 * largest));
    let a = semi.max_element();
    InitialPose {
        translation: centroid + frame * centre_local,
        rotation: DQuat::from_mat3(&frame).normalize(),
        shape: SuperquadricParams {
            a,
            a1: semi.x / a,
            a2: semi.y / a,
            a3: semi.z / a,
            e1: 1.0,
            e2: 1.0,
        },
    }
}

/// The normalisation that maps data to a centred unit-RMS frame and back.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Normalization {
    /// Data centroid.
    pub centroid: DVec3,
    /// Data RMS radius about the centroid.
    pub scale: f64,
}

impl Normalization {
    /// The normalisation of `points`. Nothing is squared or summed before it is divided by the
    /// largest coordinate, so any finite cloud (coordinates up to f64's largest, or subnormal)
    /// gets a finite centroid and scale; the scale is 0 only when every point is the same.
    pub fn of(points: &[DVec3]) -> Self {
        let n = points.len().max(1) as f64;
        let reach = |ps: &mut dyn Iterator<Item = DVec3>| {
            ps.map(|p| p.abs().max_element()).fold(0.0, f64::max)
        };
        let m = reach(&mut points.iter().copied());
        if !(m > 0.0 && m.is_finite()) {
            return Self {
                centroid: DVec3::ZERO,
                scale: 0.0,
            };
        }
        let centroid = points.iter().map(|p| *p / m).sum::<DVec3>() / n * m;
        let r = reach(&mut points.iter().map(|p| *p - centroid));
        let scale = if r > 0.0 && r.is_finite() {
            r * (points
                .iter()
                .map(|p| ((*p - centroid) / r).length_squared())
                .sum::<f64>()
                / n)
                .sqrt()
        } else {
            0.0
        };
        Self { centroid, scale }
    }

    /// Maps a pose from the unit frame to data units (the inverse of [`Self::pose_to_unit`]).
    pub fn pose_from_unit(&self, pose: &InitialPose) -> InitialPose {
        let mut shape = pose.shape;
        shape.a *= self.scale;
        InitialPose {
            translation: self.centroid + pose.translation * self.scale,
            rotation: pose.rotation,
            shape,
        }
    }

    /// Maps a state from data units to the unit frame (the inverse of [`Self::state_to_data`]).
    pub fn state_to_unit(&self, s: &ModelState) -> ModelState {
        let pose = self.pose_to_unit(&InitialPose::of(s));
        ModelState {
            translation: pose.translation,
            rotation: pose.rotation,
            shape: pose.shape,
            deformation: s.deformation,
            displacement: s.displacement.iter().map(|d| *d / self.scale).collect(),
        }
    }
    /// Maps a point from data units to the unit frame.
    pub fn unit_point(&self, p: DVec3) -> DVec3 {
        (p - self.centroid) / self.scale
    }
    /// Maps a pose from data units to the unit frame.
    pub fn pose_to_unit(&self, pose: &InitialPose) -> InitialPose {
        let mut shape = pose.shape;
        shape.a /= self.scale;
        InitialPose {
            translation: self.unit_point(pose.translation),
            rotation: pose.rotation,
            shape,
        }
    }
    /// Maps a start pose from the unit frame back to data units (as a state started there would
    /// report it: the shape normalised).
    pub fn pose_to_data(&self, tess: &Tessellation, pose: &InitialPose) -> InitialPose {
        let start = ModelState::new(tess, pose.translation, pose.rotation, pose.shape);
        InitialPose::of(&self.state_to_data(&start))
    }

    /// Maps a state from the unit frame back to data units.
    pub fn state_to_data(&self, s: &ModelState) -> ModelState {
        let pose = self.pose_from_unit(&InitialPose::of(s));
        ModelState {
            translation: pose.translation,
            rotation: pose.rotation,
            shape: pose.shape,
            // Tapering and bending are dimensionless: the same at any scale.
            deformation: s.deformation,
            displacement: s.displacement.iter().map(|d| *d * self.scale).collect(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::superquadric::shape_at;

    fn egg_cloud() -> Vec<DVec3> {
        let q = SuperquadricParams {
            a: 2.0,
            a1: 0.5,
            a2: 0.3,
            a3: 1.0,
            e1: 1.0,
            e2: 1.0,
        };
        let mut pts = Vec::new();
        for i in 0..30 {
            for j in 0..40 {
                let u = -1.5 + 3.0 * i as f64 / 29.0;
                let v = -3.1 + 6.2 * j as f64 / 39.0;
                let p = shape_at(&q, u, v);
                // Thicken one end so the third moments fix the signs.
                pts.push(p + DVec3::new(0.0, 0.0, 0.2 * (p.z.max(0.0)).powi(2)));
            }
        }
        pts
    }

    #[test]
    fn recovers_axes_and_extent() {
        let pts = egg_cloud();
        let init = initial_pose(&pts);
        let r = DMat3::from_quat(init.rotation);
        assert!(
            r.col(2).dot(DVec3::Z).abs() > 0.999,
            "z axis {:?}",
            r.col(2)
        );
        assert!(
            r.col(0).dot(DVec3::X).abs() > 0.999,
            "x axis {:?}",
            r.col(0)
        );
        let semi = init.shape.semi_axes();
        assert!(
            (semi.x - 1.0).abs() < 0.05 && (semi.y - 0.6).abs() < 0.05,
            "{semi:?}"
        );
    }

    #[test]
    fn frame_is_equivariant_under_rotation() {
        let pts = egg_cloud();
        let rot = DQuat::from_euler(glam::EulerRot::XYZ, 0.4, -1.1, 2.0);
        let moved: Vec<DVec3> = pts
            .iter()
            .map(|p| rot * *p + DVec3::new(3.0, -1.0, 7.0))
            .collect();
        let (a, b) = (initial_pose(&pts), initial_pose(&moved));
        let expected = rot * a.rotation;
        assert!(
            expected.dot(b.rotation).abs() > 1.0 - 1e-10,
            "{expected:?} vs {:?}",
            b.rotation
        );
        assert!((rot * a.translation + DVec3::new(3.0, -1.0, 7.0) - b.translation).length() < 1e-9);
        assert!((a.shape.a - b.shape.a).abs() < 1e-9);
    }
}
