//! [`MouseSpringPlugin`] (feature `picking`): pull any model with the mouse, the paper's central
//! interaction (section VI).
//!
//! A left press on a model, through Bevy picking (the model's [`Mesh3d`] is pickable with
//! Bevy's mesh picking backend), attaches a [`Spring`] from the grabbed surface point to the
//! cursor. While the button is held the anchor follows the cursor in the plane through the
//! grabbed point that faces the camera; releasing the button removes the spring. The spring's
//! constant is scaled to the membrane's stiffness and its stretch clamped
//! ([`Spring::mouse_stiffness`], [`Spring::pull_towards`]), so no drag can blow the simulation
//! up. Grabbing a model unpauses it and ends a fit it was running ([`FitDriver`]): the user takes
//! over.
//!
//! The press, release and drag-end observers are global; the drag runs in [`Update`] in
//! [`MouseSpringSystems`]. Set [`MouseSpringSettings::enabled`] to false while the app uses the
//! left button for something else (placing parts, picking joint ends).

use crate::plugin::{
    FemMesh, FitDriver, GlobalShape, LocalDofs, ModelSettings, RigidState, SimControl,
    world_positions,
};
use crate::plugin::{Spring, SpringForces};
use bevy::math::DVec3;
use bevy::picking::events::{DragEnd, Pointer, Press, Release};
use bevy::picking::pointer::PointerButton;
use bevy::prelude::*;
use bevy::window::PrimaryWindow;

/// The mouse spring in use: which model it pulls, which entry of its [`SpringForces`] it is, the
/// plane the anchor moves in, and the model's scale a at the grab.
#[derive(Resource, Clone, Copy, Debug, Default, PartialEq)]
pub struct MouseSpring {
    /// The model being pulled; `None` while no button is held on one.
    pub model: Option<Entity>,
    /// The spring's index in the model's [`SpringForces`].
    pub spring: usize,
    /// A point of the drag plane (the grabbed point; the plane faces the camera).
    pub plane_point: Vec3,
    /// The model's scale a when it was grabbed (the stretch clamp's unit).
    pub scale: f64,
}

/// Whether a press on a model grabs it.
#[derive(Resource, Clone, Copy, Debug, PartialEq, Reflect)]
#[reflect(Resource, Debug, PartialEq)]
pub struct MouseSpringSettings {
    /// Presses grab models (default true).
    pub enabled: bool,
}

impl Default for MouseSpringSettings {
    fn default() -> Self {
        Self { enabled: true }
    }
}

/// The set the drag system runs in ([`Update`]); order your own cursor handling against it.
#[derive(SystemSet, Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct MouseSpringSystems;

/// Sent when a press grabs a model with the mouse spring.
#[derive(Message, Clone, Copy, Debug, PartialEq)]
pub struct ModelGrabbed {
    /// The model.
    pub model: Entity,
}

/// Mouse springs on every model: press, drag and release through Bevy picking.
#[derive(Default)]
pub struct MouseSpringPlugin;

impl Plugin for MouseSpringPlugin {
    fn build(&self, app: &mut App) {
        app.init_resource::<MouseSpring>()
            .init_resource::<MouseSpringSettings>()
            .register_type::<MouseSpringSettings>()
            .add_message::<ModelGrabbed>()
            .add_systems(Update, drag_spring.in_set(MouseSpringSystems))
            // Where the simulation runs in `Update`, the spring moves before the step.
            .configure_sets(
                Update,
                MouseSpringSystems.before(crate::plugin::DeformableSqSystems::Prepare),
            )
            .add_observer(grab)
            .add_observer(release)
            .add_observer(drag_end);
    }
}

/// Left press on a model: a spring from the grabbed surface point (its nearest node's material
/// coordinates) to the cursor. A grab holds the model's global shape while it acts; with Shift
/// held at the press, the spring reshapes the superquadric too ([`Spring::reshape`]).
fn grab(
    press: On<Pointer<Press>>,
    keys: Option<Res<ButtonInput<KeyCode>>>,
    settings: Res<MouseSpringSettings>,
    mut mouse: ResMut<MouseSpring>,
    mut models: Query<(
        &FemMesh,
        (&RigidState, &GlobalShape, &LocalDofs),
        &ModelSettings,
        &mut SimControl,
        Option<&mut SpringForces>,
    )>,
    mut grabbed: MessageWriter<ModelGrabbed>,
    mut commands: Commands,
) {
    if press.button != PointerButton::Primary || mouse.model.is_some() || !settings.enabled {
        return;
    }
    let entity = press.entity;
    let Ok((fem, (rigid, shape, local), model_settings, mut control, springs)) =
        models.get_mut(entity)
    else {
        return;
    };
    let (Some(tess), Some(hit)) = (fem.get(), press.hit.position) else {
        return;
    };
    let mut nodes = Vec::new();
    world_positions(tess, rigid, shape, local, &mut nodes);
    let size = shape.a.max(1e-3);
    let stiffness = Spring::mouse_stiffness(model_settings, size);
    let Some(mut spring) = Spring::grab(tess, &nodes, hit.as_dvec3(), stiffness) else {
        return;
    };
    spring.reshape = keys.is_some_and(|k| k.any_pressed([KeyCode::ShiftLeft, KeyCode::ShiftRight]));
    let index = match springs {
        Some(mut s) => {
            s.0.push(spring);
            s.0.len() - 1
        }
        None => {
            commands.entity(entity).insert(SpringForces(vec![spring]));
            0
        }
    };
    // A finished fit paused its model: pulling it wakes it, and the user takes over.
    control.paused = false;
    commands.entity(entity).remove::<FitDriver>();
    *mouse = MouseSpring {
        model: Some(entity),
        spring: index,
        plane_point: hit,
        scale: size,
    };
    grabbed.write(ModelGrabbed { model: entity });
}

/// Moves the spring's anchor with the cursor, in the plane through the grabbed point facing the
/// camera (clamped by [`Spring::pull_towards`]).
fn drag_spring(
    mouse: Res<MouseSpring>,
    window: Single<&Window, With<PrimaryWindow>>,
    camera: Single<(&Camera, &GlobalTransform), With<Camera3d>>,
    mut models: Query<(
        &FemMesh,
        (&RigidState, &GlobalShape, &LocalDofs),
        &mut SpringForces,
    )>,
    mut nodes: Local<Vec<DVec3>>,
) {
    let Some(model) = mouse.model else { return };
    let Some(cursor) = window.cursor_position() else {
        return;
    };
    let (camera, cam_tf) = *camera;
    let Ok(ray) = camera.viewport_to_world(cam_tf, cursor) else {
        return;
    };
    let Some(t) = ray.intersect_plane(mouse.plane_point, InfinitePlane3d::new(cam_tf.forward()))
    else {
        return;
    };
    let target = ray.get_point(t).as_dvec3();
    let Ok((fem, (rigid, shape, local), mut springs)) = models.get_mut(model) else {
        return;
    };
    let Some(tess) = fem.get() else { return };
    if let Some(spring) = springs.0.get_mut(mouse.spring) {
        world_positions(tess, rigid, shape, local, &mut nodes);
        spring.pull_towards(tess, &nodes, target, mouse.scale);
    }
}

/// Releasing the button over a model removes the mouse spring.
fn release(
    up: On<Pointer<Release>>,
    mouse: ResMut<MouseSpring>,
    springs: Query<&mut SpringForces>,
) {
    if up.button == PointerButton::Primary {
        end_grab(mouse, springs);
    }
}

/// Releasing the button anywhere after a drag removes the mouse spring.
fn drag_end(
    end: On<Pointer<DragEnd>>,
    mouse: ResMut<MouseSpring>,
    springs: Query<&mut SpringForces>,
) {
    if end.button == PointerButton::Primary {
        end_grab(mouse, springs);
    }
}

fn end_grab(mut mouse: ResMut<MouseSpring>, mut springs: Query<&mut SpringForces>) {
    if let Some(model) = mouse.model.take()
        && let Ok(mut s) = springs.get_mut(model)
        && mouse.spring < s.0.len()
    {
        s.0.remove(mouse.spring);
    }
}
