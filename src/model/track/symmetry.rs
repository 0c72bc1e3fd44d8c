//! A superquadric's equivalent labellings: the same surface described by another pose.
//!
//! Turning the model frame by a rotation P that permutes its axes (with signs), and permuting
//! the semi-axes to match, describes the same surface whenever the exponents allow it: always
//! when P keeps the z axis (ε2 shapes x and y alike), and for any P when ε1 = ε2. A box has 24
//! such labellings, a general superquadric 8. A fitter may return any of them; a tracker keeps
//! the one nearest the last frame's, so that the orientation it reports does not flip.

use crate::model::init::InitialPose;
use crate::model::superquadric::SuperquadricParams;
use glam::{DMat3, DQuat, DVec3};

/// The exponents count as equal (ε1 = ε2, so any axis may be z) within this difference.
pub const EQUAL_EXPONENTS: f64 = 0.05;

/// The 24 proper rotations whose columns are signed unit axes, each with the permutation π it
/// makes (new axis j is old axis π[j]).
fn axis_rotations() -> Vec<(DMat3, [usize; 3])> {
    let mut out = Vec::with_capacity(24);
    for perm in [
        [0, 1, 2],
        [1, 2, 0],
        [2, 0, 1],
        [1, 0, 2],
        [0, 2, 1],
        [2, 1, 0],
    ] {
        for signs in 0..8u32 {
            let s = |k: u32| if signs >> k & 1 == 1 { -1.0 } else { 1.0 };
            let col = |j: usize| {
                let mut c = DVec3::ZERO;
                c[perm[j]] = s(j as u32);
                c
            };
            let m = DMat3::from_cols(col(0), col(1), col(2));
            if m.determinant() > 0.0 {
                out.push((m, perm));
            }
        }
    }
    out
}

/// Every labelling of `pose`'s surface (see the module docs), `pose` itself first.
pub fn equivalents(pose: &InitialPose) -> Vec<InitialPose> {
    let q = pose.shape;
    let axes = q.semi_axes();
    let any_axis = (q.e1 - q.e2).abs() <= EQUAL_EXPONENTS;
    axis_rotations()
        .into_iter()
        .filter(|(_, perm)| any_axis || perm[2] == 2)
        .map(|(m, perm)| {
            if m == DMat3::IDENTITY {
                return *pose;
            }
            let shape = SuperquadricParams {
                a: 1.0,
                a1: axes[perm[0]],
                a2: axes[perm[1]],
                a3: axes[perm[2]],
                e1: q.e1,
                e2: q.e2,
            }
            .normalized_keeping(&q);
            InitialPose {
                translation: pose.translation,
                rotation: (pose.rotation * DQuat::from_mat3(&m)).normalize(),
                shape,
            }
        })
        .collect()
}

/// The labelling of `pose` whose orientation is nearest `reference`.
pub fn nearest_equivalent(pose: &InitialPose, reference: DQuat) -> InitialPose {
    equivalents(pose)
        .into_iter()
        .min_by(|a, b| {
            a.rotation
                .angle_between(reference)
                .total_cmp(&b.rotation.angle_between(reference))
        })
        .unwrap_or(*pose)
}

/// Whether a shape turns freely about its z axis (a circular section: a1 = a2 within 5 % and
/// ε2 = 1 within [`EQUAL_EXPONENTS`]): its turn about z is then not part of its orientation.
pub fn axisymmetric(q: &SuperquadricParams) -> bool {
    (q.a1 - q.a2).abs() <= 0.05 * q.a1.max(q.a2) && (q.e2 - 1.0).abs() <= EQUAL_EXPONENTS
}

/// The world direction of the axis `pose`'s shape turns freely about, when one of its
/// labellings is [`axisymmetric`] (for an ellipsoid, whichever pair of semi-axes is equal).
pub fn free_axis(pose: &InitialPose) -> Option<DVec3> {
    equivalents(pose)
        .iter()
        .find(|e| axisymmetric(&e.shape))
        .map(|e| e.rotation * DVec3::Z)
}

/// The angle between `axis` and the nearest of `rotation`'s three axes, either way along it.
pub fn nearest_axis_angle(axis: DVec3, rotation: DQuat) -> f64 {
    [DVec3::X, DVec3::Y, DVec3::Z]
        .into_iter()
        .map(|k| {
            let a = axis.angle_between(rotation * k);
            a.min(std::f64::consts::PI - a)
        })
        .fold(f64::INFINITY, f64::min)
}

/// The angle between `fit`'s orientation and the nearest of `truth`'s labellings. Where the
/// truth turns freely about an axis ([`free_axis`]), only that axis counts, against the fit's
/// axis nearest it. Whether the fit's semi-axes match that labelling's is the semi-axes' error,
/// not this one.
pub fn orientation_error(truth: &InitialPose, fit: &InitialPose) -> f64 {
    if let Some(axis) = free_axis(truth) {
        return nearest_axis_angle(axis, fit.rotation);
    }
    equivalents(truth)
        .iter()
        .map(|e| e.rotation.angle_between(fit.rotation))
        .fold(f64::INFINITY, f64::min)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::distance::radial_distance;

    fn pose(e1: f64, e2: f64) -> InitialPose {
        InitialPose {
            translation: DVec3::new(0.1, -0.2, 1.0),
            rotation: DQuat::from_euler(glam::EulerRot::XYZ, 0.3, -0.5, 1.1),
            shape: SuperquadricParams {
                a: 1.0,
                a1: 0.3,
                a2: 0.4,
                a3: 0.5,
                e1,
                e2,
            }
            .normalized(),
        }
    }

    #[test]
    fn every_labelling_describes_the_same_surface() {
        for (e1, e2, count) in [(0.4, 1.3, 8), (0.3, 0.3, 24)] {
            let p = pose(e1, e2);
            let eq = equivalents(&p);
            assert_eq!(eq.len(), count);
            assert_eq!(eq[0], p);
            let probes = [
                DVec3::new(0.5, 0.1, 1.2),
                DVec3::new(-0.2, 0.3, 0.7),
                DVec3::new(0.0, -0.4, 1.4),
            ];
            for e in &eq {
                for x in probes {
                    let (a, b) = (radial_distance(&p, x), radial_distance(e, x));
                    assert!((a - b).abs() < 1e-9, "{a} {b}");
                }
            }
        }
    }

    #[test]
    fn the_nearest_labelling_follows_the_reference() {
        let p = pose(0.3, 0.3);
        for e in equivalents(&p) {
            // Angles from acos near 1 resolve to about √ε ≈ 1e-8.
            let back = nearest_equivalent(&e, p.rotation);
            assert!(back.rotation.angle_between(p.rotation) < 1e-6);
            assert!((back.shape.semi_axes() - p.shape.semi_axes()).length() < 1e-9);
            assert!(orientation_error(&p, &e) < 1e-6);
        }
        let mut turned = p;
        turned.rotation = p.rotation * DQuat::from_rotation_x(0.02);
        assert!((orientation_error(&p, &turned) - 0.02).abs() < 1e-9);
        // An ellipsoid with two equal semi-axes turns freely about the third, whichever it is:
        // a turn about it is no error, a tilt of it is.
        let mut spheroid = pose(1.0, 1.0);
        spheroid.shape.a2 = spheroid.shape.a3;
        let axis = free_axis(&spheroid).expect("a spheroid turns freely");
        assert!(nearest_axis_angle(axis, spheroid.rotation * DQuat::from_rotation_x(0.0)) < 1e-6);
        let mut spun = spheroid;
        spun.rotation =
            spheroid.rotation * DQuat::from_axis_angle(spheroid.rotation.inverse() * axis, 0.7);
        assert!(orientation_error(&spheroid, &spun) < 1e-6);
        let mut tilted = spheroid;
        tilted.rotation = spheroid.rotation
            * DQuat::from_axis_angle(
                (spheroid.rotation.inverse() * axis).any_orthonormal_vector(),
                0.1,
            );
        assert!((orientation_error(&spheroid, &tilted) - 0.1).abs() < 1e-6);
    }
}
