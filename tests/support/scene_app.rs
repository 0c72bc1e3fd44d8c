//! A headless app that loads scene files from a folder of assets, shared by the scene tests.
#![allow(dead_code)]

use bevy::asset::AssetPlugin;
use bevy::ecs::schedule::ScheduleLabel;
use bevy::prelude::*;
use bevy_deformable_sq::prelude::*;
use std::path::Path;

/// The schedule the simulation runs in, stepped by hand so that `update` only loads and spawns.
#[derive(ScheduleLabel, Clone, Debug, PartialEq, Eq, Hash)]
pub struct Step;

/// An app with the plugin stepped in [`Step`] and the scene plugin, its assets in `assets`.
pub fn scene_app(assets: &Path) -> App {
    let mut app = App::new();
    app.add_plugins((
        MinimalPlugins,
        AssetPlugin {
            file_path: assets.display().to_string(),
            ..default()
        },
        DeformableSqPlugin::in_schedule(Step),
        DeformableSqScenePlugin,
    ));
    app.init_schedule(Step);
    app
}

/// Spawns a root for `path` and updates until its parts are spawned or it failed (bounded).
pub fn load(app: &mut App, path: &str) -> Entity {
    let handle = app.world().resource::<AssetServer>().load(path.to_string());
    let root = app.world_mut().spawn(DeformableSceneRoot(handle)).id();
    for _ in 0..2000 {
        app.update();
        let instance = app.world().get::<SceneInstance>(root).unwrap();
        if instance.spawned.is_some() || instance.error.is_some() {
            return root;
        }
        std::thread::sleep(std::time::Duration::from_millis(2));
    }
    panic!("{path} neither loaded nor failed");
}

/// The parts the scene of `root` spawned.
pub fn parts(app: &App, root: Entity) -> Vec<Entity> {
    app.world()
        .get::<SceneInstance>(root)
        .unwrap()
        .parts
        .clone()
}
