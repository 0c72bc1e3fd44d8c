//! Shared by the examples: where `assets/` is ([`assets_dir`]), and `--screenshot FILE
//! [--exit-after-steps N]`, which runs until every model has taken N simulation steps (default
//! 300) or come to rest and every dropped file has joined the scene, saves a screenshot of the window and exits — for CI and for the docs'
//! images. Pipelines compile synchronously in this mode so the frame is never blank. A scripted
//! run ends by itself: a scene that fails to load, or no model to simulate after
//! [`FRAMES_WITHOUT_MODELS`] frames, exits with code 2 and a one-line message.

use bevy::app::PluginGroupBuilder;
use bevy::prelude::*;
use bevy::render::RenderPlugin;
use bevy::render::view::screenshot::{Screenshot, ScreenshotCaptured, save_to_disk};
use bevy_deformable_sq::plugin::scene::{AddingFile, FileAdded};
use bevy_deformable_sq::prelude::{FitDriver, SceneInstance, SimControl, simulation_task_pools};
use std::path::{Path, PathBuf};

/// A scripted run with no model to simulate after this many frames gives up.
pub const FRAMES_WITHOUT_MODELS: u32 = 600;

/// Where the examples' `assets/` folder is, and why: Bevy's `BEVY_ASSET_ROOT` when set (its
/// `assets/`), else this crate's own `assets/` (its path known at build time) when it is there,
/// else `assets/` next to the executable. So an example binary started from anywhere, not only
/// through cargo, finds the shipped scenes.
pub fn assets_dir() -> (PathBuf, &'static str) {
    if let Some(root) = std::env::var_os("BEVY_ASSET_ROOT") {
        return (PathBuf::from(root).join("assets"), "BEVY_ASSET_ROOT");
    }
    let own = Path::new(env!("CARGO_MANIFEST_DIR")).join("assets");
    if own.is_dir() {
        return (own, "the crate's assets/, known at build time");
    }
    let exe = std::env::current_exe().ok();
    let dir = exe
        .as_deref()
        .and_then(Path::parent)
        .unwrap_or(Path::new("."));
    (dir.join("assets"), "next to the executable")
}

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

/// `DefaultPlugins` with the compute pool on every core ([`simulation_task_pools`]), with mesh
/// picking (for the mouse springs) and egui (for the inspector), and with synchronous pipeline
/// compilation when a screenshot is asked for.
pub fn default_plugins() -> PluginGroupBuilder {
    let plugins = DefaultPlugins
        .build()
        .add(bevy::picking::mesh_picking::MeshPickingPlugin)
        .add(bevy_egui::EguiPlugin::default())
        .set(TaskPoolPlugin {
            task_pool_options: simulation_task_pools(),
        })
        .set(AssetPlugin {
            file_path: assets_dir().0.display().to_string(),
            ..default()
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

/// Logs where the assets are read from, and adds the screenshot system when `--screenshot` was
/// given.
pub fn maybe_add(app: &mut App) {
    app.add_systems(Startup, || {
        let (dir, why) = assets_dir();
        info!("assets: {} ({why})", dir.display());
    });
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

fn take(
    mut commands: Commands,
    mut req: ResMut<Request>,
    models: Query<(&SimControl, Option<&FitDriver>)>,
    scenes: Query<&SceneInstance>,
    adding: Query<(), With<AddingFile>>,
    mut added: MessageReader<FileAdded>,
    mut exit: MessageWriter<AppExit>,
) {
    req.frames += 1;
    // A file that has just joined the scene respawns its parts in the next frames: wait for
    // them as for the scene's first parts.
    if added.read().count() > 0 {
        req.frames = 1;
    }
    if req.taken {
        return;
    }
    if let Some(e) = scenes.iter().find_map(|s| s.error.as_deref()) {
        eprintln!("error: {}", e.lines().next().unwrap_or(e));
        exit.write(AppExit::from_code(2));
        req.taken = true;
        return;
    }
    if models.is_empty() && req.frames > FRAMES_WITHOUT_MODELS {
        eprintln!("error: no model to simulate after {FRAMES_WITHOUT_MODELS} frames");
        exit.write(AppExit::from_code(2));
        req.taken = true;
        return;
    }
    // Every model has taken its steps, or stopped; a model with a fit once the fit has ended (a
    // fit pauses its model while it runs).
    let ready = !models.is_empty()
        && adding.is_empty()
        && models.iter().all(|(c, fit)| {
            fit.is_none_or(FitDriver::is_done)
                && (c.steps >= req.after_steps || c.paused || c.frozen)
        });
    if req.taken || req.frames < 10 || !ready {
        return;
    }
    req.taken = true;
    info!("every model ready after {} frames: screenshot", req.frames);
    commands
        .spawn(Screenshot::primary_window())
        .observe(save_to_disk(req.path.clone()))
        .observe(
            |_: On<ScreenshotCaptured>, mut exit: MessageWriter<AppExit>| {
                exit.write(AppExit::Success);
            },
        );
}
