//! `--demo-drop FILE` (repeatable; for the sandbox's render test): once the scene's parts have
//! taken 10 steps, drops each FILE on the window as the windowing system reports a drop, one every
//! few frames, and prints the message line and the part count before and after each. For each
//! dropped scan it then prints, when the new part's fit has ended, whether it came to rest and
//! the mean distance of the scan's points to its surface, from the model's own components.
use bevy::prelude::*;
use bevy::window::FileDragAndDrop;
use bevy_deformable_sq::model::fit::residuals;
use bevy_deformable_sq::plugin::world_positions;
use bevy_deformable_sq::prelude::*;
use std::path::PathBuf;

/// The files still to drop, the drop awaiting its report, and the parts awaiting theirs.
#[derive(Resource, Default)]
struct DemoDrop {
    files: Vec<PathBuf>,
    pending: Option<(PathBuf, usize, u32)>,
    watch: Vec<String>,
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

fn demo_drop(
    mut demo: ResMut<DemoDrop>,
    mut frame: Local<u32>,
    inspector: Res<InspectorState>,
    window: Single<Entity, With<Window>>,
    parts: Query<&SimControl, With<ScenePart>>,
    mut drops: MessageWriter<FileDragAndDrop>,
) {
    if parts.iter().all(|c| c.steps < 10) {
        return;
    }
    *frame += 1;
    if let Some((file, before, at)) = demo.pending.take() {
        if *frame < at + 3 {
            demo.pending = Some((file, before, at));
            return;
        }
        println!(
            "demo drop: {}: {} (parts {before} -> {})",
            file.display(),
            inspector.message,
            parts.iter().count()
        );
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
        let Some(i) = demo.watch.iter().position(|w| w == name.as_str()) else {
            continue;
        };
        let Some(tess) = fem.get().filter(|_| driver.is_done()) else {
            continue;
        };
        demo.watch.remove(i);
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
