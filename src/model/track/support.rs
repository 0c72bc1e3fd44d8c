//! The plane an object stands on: found in each depth frame, its points taken out of the data,
//! and its solid side kept free of the model.
//!
//! From one view a model may sink through the floor it stands on at no cost: the floor hides
//! whatever lies below it, and the floor's points beside the object's foot lie close to the
//! sides extended downward, so they even pull the model down. A tracker that knows the floor
//! takes its points out of the object's data and holds the model above it: the lowest point of
//! the model's surface may not lie below the plane ([`Support::depth_below`]).

use super::camera::DepthFrame;
use crate::model::init::InitialPose;
use crate::model::superquadric::{SignedPowers, Trig, jacobian_from_powers, shape_from_powers};
use glam::DVec3;

/// A plane n·p = d (n unit, pointing to the side the camera is on).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Plane {
    /// Its unit normal, towards the camera.
    pub normal: DVec3,
    /// Its offset: n·p = d on the plane.
    pub offset: f64,
    /// The spread σ of its points' heights near the object's depth (a robust estimate of the
    /// sensor's noise there, 0 until measured).
    pub noise: f64,
}

impl Plane {
    /// The signed height of `p` above the plane (positive on the camera's side).
    pub fn height(&self, p: DVec3) -> f64 {
        self.normal.dot(p) - self.offset
    }

    /// The band of heights its points take: three times its noise, at least `least`.
    pub fn band(&self, least: f64) -> f64 {
        (3.0 * self.noise).max(least)
    }

    /// The plane through three points, its normal towards the camera (the origin); `None` when
    /// they are collinear.
    fn through(a: DVec3, b: DVec3, c: DVec3) -> Option<Self> {
        let n = (b - a).cross(c - a);
        let len = n.length();
        if !(len > 1e-12) {
            return None;
        }
        let mut n = n / len;
        let mut d = n.dot(a);
        // The camera at the origin has height −d: make it positive.
        if d > 0.0 {
            n = -n;
            d = -d;
        }
        Some(Self {
            normal: n,
            offset: d,
            noise: 0.0,
        })
    }
}

/// RANSAC hypotheses tried a frame.
const HYPOTHESES: usize = 128;

/// Pixels sampled from a frame to find its plane.
const SAMPLES: usize = 4000;

/// The frame's largest plane away from the object: the plane that most of `frame`'s pixels lie
/// within `tolerance` of, not counting those `object` claims, refined by least squares;
/// `previous` (the last frame's) is tried first. `None` unless the plane holds a fifth of the
/// sampled pixels and `above` (a point of the object) lies on the camera's side of it. The
/// hypotheses come from `seed`, so a frame always finds the same plane. Its noise is measured
/// on the points within a quarter of `above`'s depth of it (all its points when too few are).
pub fn find_plane(
    frame: &DepthFrame,
    object: impl Fn(DVec3) -> bool,
    above: DVec3,
    tolerance: f64,
    previous: Option<Plane>,
    seed: u64,
) -> Option<Plane> {
    let c = &frame.intrinsics;
    let pixels = c.width as usize * c.height as usize;
    let stride = ((pixels as f64 / SAMPLES as f64).sqrt().ceil() as usize).max(1);
    let points: Vec<DVec3> = frame
        .points_in((0, 0, c.width as usize, c.height as usize), stride)
        .into_iter()
        .map(|(p, _)| p)
        .filter(|p| !object(*p))
        .collect();
    if points.len() < 3 {
        return None;
    }
    let support = |pl: &Plane| {
        points
            .iter()
            .filter(|p| pl.height(**p).abs() <= tolerance)
            .count()
    };
    let mut state = seed;
    let mut best: Option<(Plane, usize)> = previous.map(|p| (p, support(&p)));
    for _ in 0..HYPOTHESES {
        let mut pick = || points[(splitmix(&mut state) % points.len() as u64) as usize];
        let Some(plane) = Plane::through(pick(), pick(), pick()) else {
            continue;
        };
        let n = support(&plane);
        if best.is_none_or(|(_, m)| n > m) {
            best = Some((plane, n));
        }
    }
    let (plane, count) = best?;
    if count < points.len() / 5 {
        return None;
    }
    let mut plane = refine(&plane, &points, tolerance).unwrap_or(plane);
    plane.noise = noise(&plane, &points, above, tolerance);
    (plane.height(above) > plane.band(tolerance)).then_some(plane)
}

/// σ of the heights of `plane`'s points near `above`'s depth: 1.4826 × their median absolute
/// height, over the points within three times `tolerance` of it.
fn noise(plane: &Plane, points: &[DVec3], above: DVec3, tolerance: f64) -> f64 {
    let heights = |near: f64| -> Vec<f64> {
        points
            .iter()
            .filter(|p| (p.z - above.z).abs() <= near)
            .map(|p| plane.height(*p).abs())
            .filter(|h| *h <= 3.0 * tolerance)
            .collect()
    };
    let mut h = heights(0.25 * above.z);
    if h.len() < 30 {
        h = heights(f64::INFINITY);
    }
    if h.is_empty() {
        return 0.0;
    }
    let mid = h.len() / 2;
    let (_, m, _) = h.select_nth_unstable_by(mid, f64::total_cmp);
    1.4826 * *m
}

/// The next number of a SplitMix64 sequence.
fn splitmix(state: &mut u64) -> u64 {
    *state = state.wrapping_add(0x9E37_79B9_7F4A_7C15);
    let mut z = *state;
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// The least-squares plane of the points within `tolerance` of `plane`.
fn refine(plane: &Plane, points: &[DVec3], tolerance: f64) -> Option<Plane> {
    let near: Vec<DVec3> = points
        .iter()
        .copied()
        .filter(|p| plane.height(*p).abs() <= tolerance)
        .collect();
    if near.len() < 3 {
        return None;
    }
    let m = crate::model::init::moments(&near);
    let (values, vectors) = crate::model::linalg::symmetric_eigen3(&m.covariance);
    let k = (0..3).min_by(|&a, &b| values[a].total_cmp(&values[b]))?;
    let mut n = vectors.col(k).normalize();
    if n.dot(plane.normal) < 0.0 {
        n = -n;
    }
    Some(Plane {
        normal: n,
        offset: n.dot(m.centroid),
        noise: 0.0,
    })
}

/// The support term's grid of surface directions (rings × longitudes).
const GRID: (usize, usize) = (12, 24);

/// The plane as the tracked problem uses it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Support {
    /// The plane.
    pub plane: Plane,
}

impl Support {
    /// How far the lowest of the model's surface points over a grid of its parametrisation
    /// lies below the plane (0 when none does), with that point's material coordinates.
    pub fn depth_below(&self, pose: &InitialPose) -> (f64, Option<Trig>) {
        let mut lowest: (f64, Option<Trig>) = (0.0, None);
        for i in 0..=GRID.0 {
            let u = -std::f64::consts::FRAC_PI_2 + std::f64::consts::PI * i as f64 / GRID.0 as f64;
            for j in 0..GRID.1 {
                let v =
                    -std::f64::consts::PI + 2.0 * std::f64::consts::PI * j as f64 / GRID.1 as f64;
                let t = Trig::new(u, v);
                let s = shape_from_powers(&pose.shape, &SignedPowers::new(&pose.shape, &t));
                let h = self.plane.height(pose.translation + pose.rotation * s);
                if h < lowest.0 {
                    lowest = (h, Some(t));
                }
            }
        }
        (-lowest.0, lowest.1)
    }

    /// The residual h (the lowest grid point's height, negative below the plane; 0 when none
    /// is) and its gradient over the unknowns.
    pub fn residual(&self, pose: &InitialPose) -> Option<(f64, [f64; 11])> {
        let (below, trig) = self.depth_below(pose);
        let t = trig?;
        let q = &pose.shape;
        let powers = SignedPowers::new(q, &t);
        let s = shape_from_powers(q, &powers);
        let jac = jacobian_from_powers(q, &t, &powers);
        let n_model = pose.rotation.inverse() * self.plane.normal;
        let mut g = [0.0; 11];
        // s = (A1 X, A2 Y, A3 Z): ∂s/∂A_i = s_i/A_i along axis i.
        let axes = q.semi_axes();
        for k in 0..3 {
            g[k] = n_model[k] * s[k] / axes[k];
        }
        g[3] = n_model.dot(jac[4]);
        g[4] = n_model.dot(jac[5]);
        g[5..8].copy_from_slice(&self.plane.normal.to_array());
        // p = t + R·exp(ω×)·s: ∂p/∂ω = −R [s]×, so ∂h/∂ω = n_model · (ω × s)' = s × n_model.
        g[8..11].copy_from_slice(&s.cross(n_model).to_array());
        Some((-below, g))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::distance::radial_distance;
    use crate::model::lm::apply_increment;
    use crate::model::superquadric::SuperquadricParams;
    use crate::model::track::Intrinsics;
    use glam::DQuat;

    fn pose() -> InitialPose {
        InitialPose {
            translation: DVec3::new(0.0, 0.05, 1.0),
            rotation: DQuat::from_euler(glam::EulerRot::XYZ, 0.3, 0.2, -0.4),
            shape: SuperquadricParams {
                a: 1.0,
                a1: 0.05,
                a2: 0.06,
                a3: 0.08,
                e1: 0.5,
                e2: 0.8,
            }
            .normalized(),
        }
    }

    fn floor() -> Support {
        Support {
            plane: Plane {
                normal: DVec3::new(0.0, -1.0, 0.0),
                offset: -0.1,
                noise: 0.0,
            },
        }
    }

    #[test]
    fn the_support_gradient_matches_central_differences() {
        let (s, at) = (floor(), pose());
        let (r, g) = s.residual(&at).expect("the model reaches below the plane");
        assert!(r < 0.0);
        let h = 1e-7;
        for k in 0..11 {
            let mut d = [0.0; 11];
            d[k] = h;
            let plus = s.plane.height({
                let p = apply_increment(&at, &d);
                let t = s.depth_below(&at).1.unwrap();
                p.translation
                    + p.rotation * shape_from_powers(&p.shape, &SignedPowers::new(&p.shape, &t))
            });
            d[k] = -h;
            let minus = s.plane.height({
                let p = apply_increment(&at, &d);
                let t = s.depth_below(&at).1.unwrap();
                p.translation
                    + p.rotation * shape_from_powers(&p.shape, &SignedPowers::new(&p.shape, &t))
            });
            let numeric = (plus - minus) / (2.0 * h);
            assert!(
                (numeric - g[k]).abs() < 1e-6,
                "unknown {k}: {numeric} against {}",
                g[k]
            );
        }
    }

    #[test]
    fn the_floor_is_found_and_the_object_is_not() {
        let c = Intrinsics {
            width: 160,
            height: 120,
            fx: 130.0,
            fy: 130.0,
            cx: 79.5,
            cy: 59.5,
        };
        // A floor 0.3 below the camera, tilted, and a box on it.
        let n = DVec3::new(0.0, -1.0, -0.4).normalize();
        let mut points = Vec::new();
        for v in 0..120 {
            for u in 0..160 {
                let r = c.ray(u as f64, v as f64);
                let d = n.dot(r);
                if d < 0.0 {
                    points.push(r * (-0.3 / d));
                }
            }
        }
        let frame = DepthFrame::from_points(c, &points);
        let mut object = pose();
        object.translation = points[points.len() * 3 / 4] + n * 0.09;
        let claims = |p: DVec3| radial_distance(&object, p) < 0.01;
        let plane =
            find_plane(&frame, claims, object.translation, 0.005, None, 7).expect("a floor");
        assert!(plane.normal.dot(n) > 0.999, "{:?}", plane.normal);
        assert!((plane.offset + 0.3).abs() < 1e-3, "{}", plane.offset);
    }
}
