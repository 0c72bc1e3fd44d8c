//! The smallest app: one deformable superquadric fitting a point cloud, live.
//! `cargo run --release --example minimal [-- --screenshot FILE]`
use bevy::prelude::*;
use bevy_deformable_sq::model::init::initial_pose;
use bevy_deformable_sq::model::superquadric::SuperquadricParams;
use bevy_deformable_sq::prelude::*;
use bevy_deformable_sq::synthetic::superquadric_cloud;
use glam::{DQuat, DVec3};

fn main() -> AppExit {
    let mut app = App::new();
    app.add_plugins((
        screenshot::default_plugins(),
        DeformableSqPlugins::default(),
    ))
    .add_systems(Startup, setup);
    screenshot::maybe_add(&mut app);
    app.run()
}

fn setup(mut commands: Commands) {
    // A squarish cloud to fit; the model starts as the ellipsoid of the cloud's moments.
    let target = SuperquadricParams {
        a: 1.5,
        a1: 1.0,
        a2: 0.6,
        a3: 0.8,
        e1: 0.4,
        e2: 0.7,
    };
    let points = superquadric_cloud(
        &target,
        DVec3::ZERO,
        DQuat::from_rotation_y(0.5),
        800,
        0.0,
        1,
    );
    let start = initial_pose(&points);
    commands.spawn((
        GlobalShape::from(start.shape),
        RigidState {
            translation: start.translation,
            rotation: start.rotation,
        },
        RangeData::new(points).with_coverage(0.1),
        ModelSettings {
            hold_local_steps: 300,
            ..default()
        },
    ));
    commands.spawn((
        Camera3d::default(),
        Transform::from_xyz(3.0, 2.5, 4.5).looking_at(Vec3::ZERO, Vec3::Y),
    ));
    commands.spawn((
        DirectionalLight {
            shadow_maps_enabled: true,
            ..default()
        },
        Transform::from_xyz(4.0, 8.0, 3.0).looking_at(Vec3::ZERO, Vec3::Y),
    ));
}

#[path = "support/screenshot.rs"]
mod screenshot;
