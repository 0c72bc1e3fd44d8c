//! [`DepthTrack`]: a model that follows an object through a depth video, frame by frame, by the
//! core's tracker ([`crate::model::track`]), the same code as `dsq track`.

use super::components::{GlobalShape, RigidState, SimControl};
use crate::model::init::InitialPose;
use crate::model::track::{Frame, TrackOptions, TrackedFrame, Tracker};
use bevy::prelude::*;

/// A depth video driving its model: insert it on a model and each run of the plugin's schedule
/// while [`DepthTrack::playing`] (or once per [`DepthTrack::step_requests`]) tracks the next
/// frame and writes the pose and shape into the model's [`RigidState`] and [`GlobalShape`]. The
/// model is paused as soon as the track is inserted: the video, not the simulation, moves it.
/// The poses are `dsq track`'s for the same frames and start, bit for bit.
#[derive(Component)]
#[component(on_insert = pause_for_the_track)]
pub struct DepthTrack {
    frames: Vec<Frame>,
    tracker: Tracker,
    next: usize,
    last: Option<TrackedFrame>,
    /// Track a frame every run of the schedule.
    pub playing: bool,
    /// Track this many frames even while not playing (single-stepping).
    pub step_requests: u32,
}

impl DepthTrack {
    /// A track of `frames` from `start` (camera frame; [`crate::model::track::initial_pose`]
    /// finds one in a pixel box), playing. Errors name an option out of range or a start that is
    /// not finite.
    pub fn new(frames: Vec<Frame>, start: InitialPose, opts: TrackOptions) -> Result<Self, String> {
        Ok(Self {
            frames,
            tracker: Tracker::new(start, opts)?,
            next: 0,
            last: None,
            playing: true,
            step_requests: 0,
        })
    }

    /// The index of the next frame to track (the count tracked so far).
    pub fn next_frame(&self) -> usize {
        self.next
    }

    /// The frames.
    pub fn frames(&self) -> &[Frame] {
        &self.frames
    }

    /// What the last tracked frame gave.
    pub fn last(&self) -> Option<&TrackedFrame> {
        self.last.as_ref()
    }

    /// Whether every frame has been tracked.
    pub fn finished(&self) -> bool {
        self.next >= self.frames.len()
    }
}

/// Pauses the model's simulation when a track is inserted.
fn pause_for_the_track(
    mut world: bevy::ecs::world::DeferredWorld,
    context: bevy::ecs::lifecycle::HookContext,
) {
    if let Some(mut control) = world.get_mut::<SimControl>(context.entity) {
        control.paused = true;
    }
}

/// Tracks the next frame of every playing or stepped [`DepthTrack`] and writes its pose.
pub(crate) fn advance_tracks(
    mut models: Query<(
        &mut DepthTrack,
        &mut SimControl,
        &mut RigidState,
        &mut GlobalShape,
    )>,
) {
    models
        .par_iter_mut()
        .for_each(|(mut track, mut control, mut rigid, mut shape)| {
            if track.finished() || !(track.playing || track.step_requests > 0) {
                return;
            }
            control.paused = true;
            track.step_requests = track.step_requests.saturating_sub(1);
            let track = &mut *track;
            let out = track.tracker.step(&track.frames[track.next]);
            track.next += 1;
            track.last = Some(out);
            rigid.translation = out.pose.translation;
            rigid.rotation = out.pose.rotation;
            *shape = GlobalShape::from(out.pose.shape);
        });
}
