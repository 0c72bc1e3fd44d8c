//! Loads a scene file and simulates its parts live: range parts run the scene's fit to rest,
//! image parts are pulled by their image.
//! `cargo run --release --example scene [-- SCENE] [--screenshot FILE [--exit-after-steps N]]`
//! SCENE is a `.dsq.ron` file under `assets/` (default `scenes/cow.dsq.ron`). A scene that fails
//! to load is logged and the window stays open. The mouse orbits the camera (which the scene places) and pulls models;
//! the inspector window tunes them.
use bevy::prelude::*;
use bevy_deformable_sq::prelude::*;

/// The scene to load, relative to `assets/`.
#[derive(Resource)]
struct ScenePath(String);

fn main() -> AppExit {
    let scene = std::env::args()
        .skip(1)
        .find(|a| a.ends_with(".dsq.ron"))
        .unwrap_or_else(|| "scenes/cow.dsq.ron".into());
    let mut app = App::new();
    app.add_plugins((
        screenshot::default_plugins(),
        DeformableSqPlugins::default(),
        orbit::OrbitCameraPlugin,
    ))
    .insert_resource(ScenePath(scene))
    .add_systems(Startup, setup);
    screenshot::maybe_add(&mut app);
    app.run()
}

fn setup(mut commands: Commands, assets: Res<AssetServer>, scene: Res<ScenePath>) {
    commands.spawn(DeformableSceneRoot(assets.load(scene.0.clone())));
}

#[path = "support/orbit.rs"]
mod orbit;
#[path = "support/screenshot.rs"]
mod screenshot;
