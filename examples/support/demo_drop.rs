//! `--demo-drop FILE` (repeatable; for the sandbox's render test): once the scene's parts have
//! taken 10 steps, drops each FILE on the window as the windowing system reports a drop, one
//! after another, and prints the message line and the part count before and after each (once
//! its split, which runs off the frame, is done), with the longest frame while it was split.
//! For each part of a dropped scan it then prints, when the part's fit has ended, whether it
//! came to rest and the mean distance of its points to its surface, from the model's own
//! components.
use bevy::prelude::*;
use bevy::window::FileDragAndDrop;
use bevy_deformable_sq::model::fit::residuals;
use bevy_deformable_sq::plugin::scene::{AddedFile, AddingFile, FileAdded};
use bevy_deformable_sq::plugin::world_positions;
use bevy_deformable_sq::prelude::*;
use std::path::PathBuf;

/// The files still to drop, the drop awaiting its report, and the parts awaiting theirs.
#[derive(Resource, Default)]
struct DemoDrop {
    files: Vec<PathBuf>,
    pending: Option<(PathBuf, usize, u32)>,
    /// The frames the pending drop's split has run over, and the longest of them in seconds.
    split_frames: u32,
    longest: f64,
    /// What came of the pending drop's file, when it has joined the scene.
    added: Option<String>,
    /// Frames since no file was being added.
    idle: u32,
    watch: Vec<String>,
    /// The parts already reported.
    reported: Vec<String>,
}

/// Adds the scripted drops when the command line asks for them.
pub fn maybe_add(app: &mut App, args: &[String]) {
    let files: Vec<PathBuf> = args
        .windows(2)
        .filter(|w| w[0] == "--demo-drop")
        .map(|w| PathBuf::from(&w[1]))
        .collect();
    if files.is_empty() {
        return;
    }
    app.insert_resource(DemoDrop { files, ..default() })
        .add_systems(Update, (demo_drop, report_rest));
}

#[allow(clippy::too_many_arguments)]
fn demo_drop(
    mut demo: ResMut<DemoDrop>,
    mut frame: Local<u32>,
    time: Res<Time<Real>>,
    inspector: Res<InspectorState>,
    window: Single<Entity, With<Window>>,
    parts: Query<&SimControl, With<ScenePart>>,
    adding: Query<&AddingFile>,
    mut added: MessageReader<FileAdded>,
    mut drops: MessageWriter<FileDragAndDrop>,
) {
    for a in added.read() {
        demo.added = Some(match &a.result {
            Ok(AddedFile::Part { parts, .. }) => format!("added as {parts} parts"),
            Ok(AddedFile::Image { .. }) => "added as an image".into(),
            Err(e) => format!("failed: {e}"),
        });
    }
    if parts.iter().all(|c| c.steps < 10) {
        return;
    }
    *frame += 1;
    if let Some((file, before, at)) = demo.pending.take() {
        if !adding.is_empty() {
            demo.longest = demo.longest.max(time.delta_secs_f64());
            demo.split_frames += 1;
        }
        // Three frames after the split is done, for the scene to respawn with the new parts.
        demo.idle = if adding.is_empty() { demo.idle + 1 } else { 0 };
        if *frame < at + 3 || demo.idle < 3 {
            demo.pending = Some((file, before, at));
            return;
        }
        println!(
            "demo drop: {}: {} (parts {before} -> {}; {}; split over {} frames, the longest \
             {:.0} ms)",
            file.display(),
            inspector.message,
            parts.iter().count(),
            demo.added.take().as_deref().unwrap_or("nothing added"),
            demo.split_frames,
            demo.longest * 1e3
        );
        demo.longest = 0.0;
        demo.split_frames = 0;
        demo.idle = 0;
        return;
    }
    if demo.files.is_empty() {
        return;
    }
    let file = demo.files.remove(0);
    if let Some(stem) = file.file_stem() {
        demo.watch.push(stem.to_string_lossy().into_owned());
    }
    drops.write(FileDragAndDrop::DroppedFile {
        window: *window,
        path_buf: file.clone(),
    });
    demo.pending = Some((file, parts.iter().count(), *frame));
}

fn report_rest(
    mut demo: ResMut<DemoDrop>,
    parts: Query<(
        &Name,
        &FitDriver,
        &FemMesh,
        &RigidState,
        &GlobalShape,
        &LocalDofs,
        &RangeData,
    )>,
) {
    for (name, driver, fem, rigid, shape, local, range) in &parts {
        // A scan's parts are named after it: "scan", or "scan 1", "scan 2", ….
        let of = |w: &String| {
            let n = name.as_str();
            n == w
                || n.strip_prefix(w.as_str())
                    .is_some_and(|r| r.starts_with(' '))
        };
        if !demo.watch.iter().any(of) || demo.reported.iter().any(|r| r == name.as_str()) {
            continue;
        }
        let Some(tess) = fem.get().filter(|_| driver.is_done()) else {
            continue;
        };
        demo.reported.push(name.to_string());
        let mut nodes = Vec::new();
        world_positions(tess, rigid, shape, local, &mut nodes);
        let points = range.forces.points();
        let r = residuals(tess, &nodes, points);
        println!(
            "demo drop: part {name} at rest: {}, {} points, mean distance {:.5} of the diagonal, \
             local DOFs: {}",
            driver.converged(),
            points.len(),
            r.mean / r.diagonal,
            local.displacement.iter().any(|d| d.length() > 0.0)
        );
    }
}
