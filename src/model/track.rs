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
mod start;
pub mod support;
pub mod symmetry;
mod tracker;

pub use camera::{DepthFrame, Intrinsics};
pub use start::initial_pose;
pub use symmetry::{
    axisymmetric, equivalents, free_axis, nearest_axis_angle, nearest_equivalent, orientation_error,
};
pub use tracker::{FLOOR_TOLERANCE, Frame, MIN_TRACK_POINTS, TrackOptions, TrackedFrame, Tracker};
