//! Tracking a deformable superquadric through a depth video (beyond the 1991 paper; its
//! authors' next one, Metaxas & Terzopoulos, PAMI 1993, made the model's dynamics the system
//! model of a Kalman filter).
//!
//! Each frame, the [`Tracker`]:
//!
//! 1. **predicts** the state from the last good one: the centre and orientation at constant
//!    velocity and spin, the shape where it was, the covariance grown by the process noise
//!    ([`TrackOptions::motion`], [`TrackOptions::turn`], [`TrackOptions::shape_drift`]);
//! 2. **gates** the frame: the pixels inside the predicted model's bounding sphere, back-projected,
//!    and kept within three standard deviations of the predicted surface;
//! 3. **solves a MAP fit** from the prediction: the gated points' distances under the outlier
//!    mixture, plus the prediction's prior in information form, plus the free space the depth
//!    image shows ([`problem`]), by the range fit's Levenberg–Marquardt engine;
//! 4. **updates** the information by the data's JᵀWJ/σ², keeps the labelling of the surface
//!    nearest the prediction's ([`symmetry`]), and the velocity from the motion.
//!
//! A frame whose inliers fall below [`TrackOptions::min_seen`] of the track's usual count is
//! **lost**: the state stays at the last good frame, its covariance keeps growing, so the gate
//! widens until the object is found again.

pub mod camera;
pub mod problem;
mod region;
pub mod support;
pub mod symmetry;
mod tracker;

pub use camera::{DepthFrame, Intrinsics};
pub use symmetry::{equivalents, nearest_equivalent, orientation_error};
pub use tracker::{FLOOR_TOLERANCE, Frame, MIN_TRACK_POINTS, TrackOptions, TrackedFrame, Tracker};

use crate::model::fit::{CloudOptions, FitOptions, fit};
use crate::model::init::InitialPose;

/// The superquadric to start a track from, fitted to the pixels of `frame` inside the box
/// [x0, x1) × [y0, y1): the frame's floor found outside the box and its points taken out
/// ([`support::find_plane`]), the piece of continuous surface that fills the box's middle kept
/// (what lies behind or beside the object dropped), then a pure superquadric by the range fit's
/// robust defaults. Errors: a box outside the image or empty, or too few points in it.
pub fn initial_pose(frame: &DepthFrame, [x0, y0, x1, y1]: [u32; 4]) -> Result<InitialPose, String> {
    let c = &frame.intrinsics;
    if x0 >= x1 || y0 >= y1 || x1 > c.width || y1 > c.height {
        return Err(format!(
            "the box {x0},{y0},{x1},{y1} is empty or outside the {}×{} image",
            c.width, c.height
        ));
    }
    let boxed = (x0 as usize, y0 as usize, x1 as usize, y1 as usize);
    let inside = |p: glam::DVec3| {
        c.project(p).is_some_and(|px| {
            px.x >= x0 as f64 && px.x < x1 as f64 && px.y >= y0 as f64 && px.y < y1 as f64
        })
    };
    let in_box: Vec<_> = frame.points_in(boxed, 1);
    let mut floor = None;
    if in_box.len() >= MIN_TRACK_POINTS {
        let centre = in_box.iter().map(|(p, _)| *p).sum::<glam::DVec3>() / in_box.len() as f64;
        floor = support::find_plane(frame, inside, centre, FLOOR_TOLERANCE * centre.z, None, 0);
    }
    // Off the floor, a depth jump wider than a steep surface's step between pixels (a surface
    // at 80° to the ray steps 6 pixel footprints) plus three times the noise of a difference.
    let footprint = 2.0 / (c.fx + c.fy);
    let noise = floor
        .map_or(0.0, |f| f.noise)
        .max(region::step_noise(frame, boxed));
    let jump = |z: f64| 6.0 * footprint * z + 3.0 * std::f64::consts::SQRT_2 * noise;
    let above = |p: glam::DVec3| floor.is_none_or(|f| f.height(p) > f.band(FLOOR_TOLERANCE * p.z));
    let points = region::object_region(frame, boxed, above, jump);
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
    Ok(InitialPose::of(&report.state))
}
