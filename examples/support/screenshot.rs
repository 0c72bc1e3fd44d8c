//! Shared by the examples: `--screenshot FILE [--exit-after-steps N]` runs until every model has
//! taken N simulation steps (default 300) or come to rest, saves a screenshot of the window and exits — for CI and
//! for README images. Pipelines compile synchronously in this mode so the frame is never blank.

use bevy::app::PluginGroupBuilder;
use bevy::prelude::*;
use bevy::render::RenderPlugin;
use bevy::render::view::screenshot::{Screenshot, ScreenshotCaptured, save_to_disk};
use bevy_deformable_sq::prelude::{SimControl, simulation_task_pools};
use std::path::PathBuf;

#[derive(Resource)]
struct Request {
    path: PathBuf,
    after_steps: u64,
    frames: u32,
    taken: bool,
}

/// `--screenshot FILE` and `--exit-after-steps N` from the command line.
pub fn args() -> Option<(PathBuf, u64)> {
    let args: Vec<String> = std::env::args().collect();
    let value = |flag: &str| {
        args.iter()
            .position(|a| a == flag)
            .and_then(|i| args.get(i + 1))
            .cloned()
    };
    let path = value("--screenshot")?;
    let steps = value("--exit-after-steps")
        .and_then(|s| s.parse().ok())
        .unwrap_or(300);
    Some((PathBuf::from(path), steps))
}

/// `DefaultPlugins` with the compute pool on every core ([`simulation_task_pools`]), and with
/// synchronous pipeline compilation when a screenshot is asked for.
pub fn default_plugins() -> PluginGroupBuilder {
    let plugins = DefaultPlugins.build().set(TaskPoolPlugin {
        task_pool_options: simulation_task_pools(),
    });
    if args().is_some() {
        plugins.set(RenderPlugin {
            synchronous_pipeline_compilation: true,
            ..default()
        })
    } else {
        plugins
    }
}

/// Adds the screenshot system when `--screenshot` was given.
pub fn maybe_add(app: &mut App) {
    if let Some((path, after_steps)) = args() {
        app.insert_resource(Request {
            path,
            after_steps,
            frames: 0,
            taken: false,
        })
        .add_systems(Update, take);
    }
}

fn take(mut commands: Commands, mut req: ResMut<Request>, models: Query<&SimControl>) {
    req.frames += 1;
    // Every model has taken its steps, or stopped (a fit at rest pauses its model).
    let ready = !models.is_empty()
        && models
            .iter()
            .all(|c| c.steps >= req.after_steps || c.paused || c.frozen);
    if req.taken || req.frames < 10 || !ready {
        return;
    }
    req.taken = true;
    commands
        .spawn(Screenshot::primary_window())
        .observe(save_to_disk(req.path.clone()))
        .observe(
            |_: On<ScreenshotCaptured>, mut exit: MessageWriter<AppExit>| {
                exit.write(AppExit::Success);
            },
        );
}
