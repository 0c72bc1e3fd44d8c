//! An orbit camera for the windowed examples: drag empty space with the left or right button to
//! orbit, with the middle button (or Shift + right) to pan; the wheel or + / - zooms, the arrows
//! orbit, Home frames the scene again. A scene's camera, placed on spawn, is taken over as the
//! orbit's start. Nothing moves while egui or a mouse spring has the pointer, or while
//! [`Orbit::left_button`] is off (the app uses the left button for something else).
use bevy::input::mouse::{AccumulatedMouseMotion, AccumulatedMouseScroll};
use bevy::prelude::*;
use bevy_deformable_sq::prelude::*;
use bevy_egui::input::EguiWantsInput;

/// The camera's orbit about a target.
#[derive(Resource, Clone, Copy, Debug)]
pub struct Orbit {
    /// The point looked at.
    pub target: Vec3,
    /// About the vertical, in radians.
    pub yaw: f32,
    /// Above the horizontal, in radians.
    pub pitch: f32,
    /// From the target.
    pub distance: f32,
    /// A left drag on empty space orbits.
    pub left_button: bool,
}

impl Default for Orbit {
    fn default() -> Self {
        Self {
            target: Vec3::new(0.0, 0.5, 0.0),
            yaw: 0.0,
            pitch: 0.35,
            distance: 7.0,
            left_button: true,
        }
    }
}

/// Spawns the camera (a [`DeformableSceneCamera`], so a scene's `camera` places it) and a sun,
/// and adds [`Orbit`] and the system that places the camera from it, after the mouse springs.
pub struct OrbitCameraPlugin;

impl Plugin for OrbitCameraPlugin {
    fn build(&self, app: &mut App) {
        app.init_resource::<Orbit>()
            .insert_resource(GlobalAmbientLight {
                brightness: 300.0,
                ..default()
            })
            .add_systems(Startup, spawn_camera_and_sun)
            .add_systems(Update, orbit_camera.after(MouseSpringSystems));
    }
}

fn spawn_camera_and_sun(mut commands: Commands) {
    commands.spawn((Camera3d::default(), DeformableSceneCamera));
    commands.spawn((
        DirectionalLight {
            shadow_maps_enabled: true,
            illuminance: 8000.0,
            ..default()
        },
        Transform::from_xyz(3.0, 8.0, 5.0).looking_at(Vec3::ZERO, Vec3::Y),
    ));
}

fn orbit_camera(
    mut orbit: ResMut<Orbit>,
    buttons: Res<ButtonInput<MouseButton>>,
    keys: Res<ButtonInput<KeyCode>>,
    motion: Res<AccumulatedMouseMotion>,
    scroll: Res<AccumulatedMouseScroll>,
    egui: Res<EguiWantsInput>,
    mouse: Res<MouseSpring>,
    mut camera: Single<&mut Transform, With<Camera3d>>,
    placed: Query<&SceneInstance, Changed<SceneInstance>>,
    mut started: Local<bool>,
) {
    if !placed.is_empty() || !*started {
        *started = true;
        // The scene moved the camera: orbit about what it looks at from there.
        let (forward, eye) = (camera.forward(), camera.translation);
        orbit.distance = (eye - orbit.target).length().max(0.5);
        orbit.target = eye + forward * orbit.distance;
        orbit.pitch = (-forward.y).asin();
        orbit.yaw = (-forward.x).atan2(-forward.z);
    }
    if !egui.wants_any_keyboard_input() {
        let step = 0.03;
        let key = |k| keys.pressed(k) as i32 as f32;
        orbit.yaw += step * (key(KeyCode::ArrowRight) - key(KeyCode::ArrowLeft));
        orbit.pitch = (orbit.pitch + step * (key(KeyCode::ArrowUp) - key(KeyCode::ArrowDown)))
            .clamp(-1.5, 1.5);
        let zoom = key(KeyCode::Minus).max(key(KeyCode::NumpadSubtract))
            - key(KeyCode::Equal).max(key(KeyCode::NumpadAdd));
        orbit.distance = (orbit.distance * 0.97f32.powf(-zoom)).clamp(0.2, 200.0);
        if keys.just_pressed(KeyCode::Home) {
            *orbit = Orbit {
                left_button: orbit.left_button,
                ..default()
            };
        }
    }
    if !egui.wants_any_pointer_input() && mouse.model.is_none() {
        let d = motion.delta;
        let shift = keys.pressed(KeyCode::ShiftLeft) || keys.pressed(KeyCode::ShiftRight);
        let right = buttons.pressed(MouseButton::Right);
        if buttons.pressed(MouseButton::Middle) || (shift && right) {
            let s = orbit.distance * 0.0015;
            orbit.target += (-camera.right() * d.x + camera.up() * d.y) * s;
        } else if (buttons.pressed(MouseButton::Left) && orbit.left_button) || right {
            orbit.yaw -= d.x * 0.005;
            orbit.pitch = (orbit.pitch + d.y * 0.005).clamp(-1.5, 1.5);
        }
        if scroll.delta.y != 0.0 {
            orbit.distance =
                (orbit.distance * (1.0 - 0.1 * scroll.delta.y.signum())).clamp(0.2, 200.0);
        }
    }
    let dir = Vec3::new(
        orbit.yaw.sin() * orbit.pitch.cos(),
        orbit.pitch.sin(),
        orbit.yaw.cos() * orbit.pitch.cos(),
    );
    **camera = Transform::from_translation(orbit.target + dir * orbit.distance)
        .looking_at(orbit.target, Vec3::Y);
}
