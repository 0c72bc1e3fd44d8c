//! [`DeformableSqDebugPlugin`] (feature `debug_render`): gizmos for what pulls on each model —
//! its range data points, the spring from each point to its point of influence on the surface,
//! user springs, and the joints between models. Separate from the simulation, like avian's debug rendering.

use crate::plugin::{FemMesh, PartJoint, RangeData, Scratch, SpringForces};
use bevy::prelude::*;

/// What the debug gizmos draw.
#[derive(Resource, Reflect, Clone, Copy, Debug, PartialEq)]
#[reflect(Resource, Debug, PartialEq)]
pub struct DebugRenderConfig {
    /// Draw each range data point as a small cross.
    pub points: bool,
    /// Draw the spring from each data point to its point of influence.
    pub data_springs: bool,
    /// Draw user springs (mouse springs).
    pub user_springs: bool,
    /// Draw each joint: a small sphere at each end and the gap between them.
    pub joints: bool,
    /// Half size of a data point's cross, in world units.
    pub point_size: f32,
}

impl Default for DebugRenderConfig {
    fn default() -> Self {
        Self {
            points: true,
            data_springs: true,
            user_springs: true,
            joints: true,
            point_size: 0.01,
        }
    }
}

/// The gizmo group the debug gizmos draw in: switch them off, or change their line width, through
/// Bevy's `GizmoConfigStore` without touching other gizmos.
#[derive(Default, Reflect, GizmoConfigGroup)]
pub struct DeformableSqGizmos;

/// Draws range data, data springs, user springs and joints with gizmos ([`DeformableSqGizmos`]),
/// in [`PostUpdate`]. It needs Bevy's `GizmoPlugin` (in `DefaultPlugins`), added before or after
/// it (registered at once when it is there, else when the app's plugins are finished); without
/// one (a headless app) it draws nothing.
pub struct DeformableSqDebugPlugin;

impl Plugin for DeformableSqDebugPlugin {
    fn build(&self, app: &mut App) {
        app.init_resource::<DebugRenderConfig>()
            .register_type::<DebugRenderConfig>();
        register_gizmos(app);
    }

    fn finish(&self, app: &mut App) {
        register_gizmos(app);
    }
}

/// The gizmo group and the drawing system, once, where Bevy's gizmos exist.
fn register_gizmos(app: &mut App) {
    if app.is_plugin_added::<bevy::gizmos::GizmoPlugin>()
        && !app
            .world()
            .contains_resource::<bevy::gizmos::gizmos::GizmoStorage<DeformableSqGizmos, ()>>()
    {
        app.init_gizmo_group::<DeformableSqGizmos>()
            .add_systems(PostUpdate, draw_debug);
    }
}

/// The gizmo system.
pub(crate) fn draw_debug(
    mut gizmos: Gizmos<DeformableSqGizmos>,
    config: Res<DebugRenderConfig>,
    models: Query<(
        &FemMesh,
        &Scratch,
        Option<&RangeData>,
        Option<&SpringForces>,
    )>,
    joints: Query<&PartJoint>,
) {
    let point_colour = Color::srgb(0.95, 0.95, 0.2);
    let spring_colour = Color::srgba(0.9, 0.9, 0.9, 0.5);
    let user_colour = Color::srgb(1.0, 0.2, 0.2);
    for (fem, scratch, range, springs) in &models {
        let x = scratch.node_positions();
        let Some(tess) = fem.get() else { continue };
        if x.len() != tess.node_count() {
            continue;
        }
        if let Some(range) = range {
            for (i, r) in range.forces.points().iter().enumerate() {
                let r = r.as_vec3();
                if config.points {
                    gizmos.cross(
                        Isometry3d::from_translation(r),
                        config.point_size,
                        point_colour,
                    );
                }
                if config.data_springs
                    && let Some(inf) = range.forces.influence().get(i)
                {
                    gizmos.line(r, inf.at.interpolate(|k| x[k]).as_vec3(), spring_colour);
                }
            }
        }
        if config.user_springs {
            for s in springs.map(|s| s.0.as_slice()).unwrap_or(&[]) {
                let at = tess.locate(s.u, s.v).interpolate(|k| x[k]);
                gizmos.line(at.as_vec3(), s.anchor.as_vec3(), user_colour);
            }
        }
    }
    if config.joints {
        let joint_colour = Color::srgb(0.2, 0.9, 0.9);
        for j in &joints {
            let end = |e: Entity, at: crate::model::joint::JointEnd| {
                let (fem, scratch, ..) = models.get(e).ok()?;
                let tess = fem.get()?;
                let x = scratch.node_positions();
                (x.len() == tess.node_count()).then(|| at.position(tess, x).as_vec3())
            };
            let (Some(a), Some(b)) = (end(j.a, j.joint.a), end(j.b, j.joint.b)) else {
                continue;
            };
            let radius = 4.0 * config.point_size;
            gizmos.sphere(Isometry3d::from_translation(a), radius, joint_colour);
            gizmos.sphere(Isometry3d::from_translation(b), radius, joint_colour);
            gizmos.line(a, b, joint_colour);
        }
    }
}
