//! The first frame's superquadric, from a pixel box around the object.
//!
//! From one view a pure range fit is ambiguous: the back is hidden, and a plate through the
//! visible faces or a box reaching behind them explains the points as well as the object. The
//! depth image says more than its points: the model may not stand in front of what the camera
//! saw (free space), nor sink into the floor. So the start is chosen among candidates by the
//! whole image's evidence: the range fit, and boxes and ellipsoids standing on the floor with
//! the points' footprint, each refined by the tracker's own MAP fit of the frame, and scored on
//! the box's points, free space and floor alike.

use super::camera::DepthFrame;
use super::region::{object_region, step_noise};
use super::support::{Plane, Support, find_plane};
use super::tracker::{FLOOR_TOLERANCE, Frame, MIN_TRACK_POINTS, TrackOptions, Tracker};
use crate::model::distance::radial_distance;
use crate::model::fit::{CloudOptions, FitOptions, fit};
use crate::model::init::InitialPose;
use crate::model::superquadric::SuperquadricParams;
use glam::{DMat3, DQuat, DVec2, DVec3};

/// Samples along each free-space ray of the score.
const RAY_SAMPLES: usize = 16;

/// Most free-space rays the score takes.
const SCORE_RAYS: usize = 2000;

/// Times a candidate is refined by the tracker's MAP fit of the first frame.
const REFINES: usize = 2;

/// The superquadric to start a track from, fitted to the pixels of `frame` inside the box
/// [x0, x1) × [y0, y1): the frame's floor found outside the box and its points taken out
/// ([`find_plane`]), the piece of continuous surface that fills the box's middle kept (what lies
/// behind or beside the object dropped), then the best of the candidates (see the module docs).
/// Errors: a box outside the image or empty, or too few points in it.
pub fn initial_pose(frame: &DepthFrame, [x0, y0, x1, y1]: [u32; 4]) -> Result<InitialPose, String> {
    let c = &frame.intrinsics;
    if x0 >= x1 || y0 >= y1 || x1 > c.width || y1 > c.height {
        return Err(format!(
            "the box {x0},{y0},{x1},{y1} is empty or outside the {}×{} image",
            c.width, c.height
        ));
    }
    let boxed = (x0 as usize, y0 as usize, x1 as usize, y1 as usize);
    let inside = |p: DVec3| {
        c.project(p).is_some_and(|px| {
            px.x >= x0 as f64 && px.x < x1 as f64 && px.y >= y0 as f64 && px.y < y1 as f64
        })
    };
    let in_box = frame.points_in(boxed, 1);
    let mut floor = None;
    if in_box.len() >= MIN_TRACK_POINTS {
        let centre = in_box.iter().map(|(p, _)| *p).sum::<DVec3>() / in_box.len() as f64;
        floor = find_plane(frame, inside, centre, FLOOR_TOLERANCE * centre.z, None, 0);
    }
    // Off the floor, a depth jump wider than a steep surface's step between pixels (a surface
    // at 80° to the ray steps 6 pixel footprints) plus three times the noise of a difference.
    let footprint = 2.0 / (c.fx + c.fy);
    let noise = floor.map_or(0.0, |f| f.noise).max(step_noise(frame, boxed));
    let jump = |z: f64| 6.0 * footprint * z + 3.0 * std::f64::consts::SQRT_2 * noise;
    let above = |p: DVec3| floor.is_none_or(|f| f.height(p) > f.band(FLOOR_TOLERANCE * p.z));
    let points = object_region(frame, boxed, above, jump);
    if points.len() < MIN_TRACK_POINTS {
        return Err(format!(
            "the box {x0},{y0},{x1},{y1} holds {} pixels of an object off the floor; at least {MIN_TRACK_POINTS} are needed",
            points.len()
        ));
    }
    let opts = CloudOptions {
        global_only: true,
        ..CloudOptions::default()
    }
    .resolve(FitOptions::default(), true)
    .map_err(|e| e.to_string())?;
    let report = fit(&points, &opts, |_| {}).map_err(|e| e.to_string())?;
    let range_fit = InitialPose::of(&report.state);
    let mut candidates = vec![range_fit];
    if let Some(f) = &floor {
        candidates.extend(standing(&points, f));
    }
    let track = TrackOptions::default();
    let scene = Frame::Depth(frame.clone());
    let refined: Vec<InitialPose> = candidates
        .into_iter()
        .filter_map(|mut pose| {
            for _ in 0..REFINES {
                let out = Tracker::new(pose, track).ok()?.step(&scene);
                if out.lost {
                    return None;
                }
                pose = out.pose;
            }
            Some(pose)
        })
        .collect();
    let score = Score::new(frame, boxed, &points, floor, &range_fit);
    Ok(refined
        .into_iter()
        .map(|p| (score.of(&p), p))
        .min_by(|a, b| a.0.total_cmp(&b.0))
        .map_or(range_fit, |(_, p)| p))
}

/// Superquadrics standing on `floor` over the points' footprint: up along the floor's normal,
/// as tall as the points' top, across the footprint's principal axes; a rounded box and an
/// ellipsoid.
fn standing(points: &[DVec3], floor: &Plane) -> Vec<InitialPose> {
    let up = floor.normal;
    let mut heights: Vec<f64> = points.iter().map(|p| floor.height(*p)).collect();
    heights.sort_by(f64::total_cmp);
    let top = heights[(heights.len() * 95 / 100).min(heights.len() - 1)];
    if !(top > 0.0) {
        return Vec::new();
    }
    // The footprint on the floor in a basis (s, t) of the plane.
    let s = up.any_orthonormal_vector();
    let t = up.cross(s);
    let flat: Vec<DVec2> = points
        .iter()
        .map(|p| DVec2::new(p.dot(s), p.dot(t)))
        .collect();
    let mean = flat.iter().copied().sum::<DVec2>() / flat.len() as f64;
    let (mut sxx, mut sxy, mut syy) = (0.0, 0.0, 0.0);
    for q in &flat {
        let d = *q - mean;
        (sxx, sxy, syy) = (sxx + d.x * d.x, sxy + d.x * d.y, syy + d.y * d.y);
    }
    let angle = 0.5 * (2.0 * sxy).atan2(sxx - syy);
    let major = DVec2::new(angle.cos(), angle.sin());
    let minor = major.perp();
    let span = |axis: DVec2| {
        let mut v: Vec<f64> = flat.iter().map(|q| q.dot(axis)).collect();
        v.sort_by(f64::total_cmp);
        let (lo, hi) = (v[v.len() / 50], v[v.len() - 1 - v.len() / 50]);
        (lo, hi)
    };
    let (a, b) = (span(major), span(minor));
    let middle = major * 0.5 * (a.0 + a.1) + minor * 0.5 * (b.0 + b.1);
    let x = (s * major.x + t * major.y).normalize();
    let y = up.cross(x);
    let foot = s * middle.x + t * middle.y + up * floor.offset;
    let half =
        DVec3::new(0.5 * (a.1 - a.0), 0.5 * (b.1 - b.0), 0.5 * top).max(DVec3::splat(1e-3 * top));
    let rotation = DQuat::from_mat3(&DMat3::from_cols(x, y, up)).normalize();
    let largest = half.max_element();
    [0.3, 1.0]
        .into_iter()
        .map(|e| InitialPose {
            translation: foot + up * half.z,
            rotation,
            shape: SuperquadricParams {
                a: largest,
                a1: half.x / largest,
                a2: half.y / largest,
                a3: half.z / largest,
                e1: e,
                e2: e,
            },
        })
        .collect()
}

/// How well a candidate explains the box: its points' distances, the free space it fills and
/// its depth below the floor, each truncated at a tenth of the object's size.
struct Score<'a> {
    points: &'a [DVec3],
    rays: Vec<Vec<DVec3>>,
    floor: Option<Support>,
    truncation: f64,
}

impl<'a> Score<'a> {
    /// The score of the box `boxed` of `frame` with the object's `points`, the `floor`, and
    /// the scale of `reference`.
    fn new(
        frame: &DepthFrame,
        boxed: (usize, usize, usize, usize),
        points: &'a [DVec3],
        floor: Option<Plane>,
        reference: &InitialPose,
    ) -> Self {
        let axes = reference.shape.semi_axes();
        let size = (axes.x + axes.y + axes.z) / 3.0;
        let truncation = 0.1 * size;
        let (u0, v0, u1, v1) = boxed;
        let area = (u1 - u0) * (v1 - v0);
        let stride = ((area as f64 / SCORE_RAYS as f64).sqrt().ceil() as usize).max(1);
        // Each ray from where the object's near side could be to just before the depth seen.
        let reach = 2.0 * axes.max_element();
        let margin = truncation;
        let mut rays = Vec::new();
        for (p, [u, v]) in frame.points_in(boxed, stride) {
            let r = frame.intrinsics.ray(u as f64, v as f64);
            let (near, far) = ((p.z - reach).max(1e-3), p.z - margin);
            if far > near {
                rays.push(
                    (0..RAY_SAMPLES)
                        .map(|k| r * (near + (far - near) * (k as f64 + 0.5) / RAY_SAMPLES as f64))
                        .collect(),
                );
            }
        }
        Self {
            points,
            rays,
            floor: floor.map(|plane| Support { plane }),
            truncation,
        }
    }

    /// The score of `pose` (lower is better).
    fn of(&self, pose: &InitialPose) -> f64 {
        let cap = self.truncation * self.truncation;
        let data: f64 = self
            .points
            .iter()
            .map(|p| radial_distance(pose, *p).powi(2).min(cap))
            .sum();
        let free: f64 = self
            .rays
            .iter()
            .map(|ray| {
                let deepest = ray
                    .iter()
                    .map(|s| radial_distance(pose, *s))
                    .fold(0.0, f64::min);
                (deepest * deepest).min(cap)
            })
            .sum();
        let below = self.floor.map_or(0.0, |f| f.depth_below(pose).0);
        data + free + self.points.len() as f64 * (below * below).min(cap)
    }
}
