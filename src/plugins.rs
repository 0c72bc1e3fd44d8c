//! [`DeformableSqPlugins`]: every plugin of the crate in one group.

use crate::plugin::DeformableSqPlugin;
use crate::plugin::scene::DeformableSqScenePlugin;
use crate::render::DeformableSqRenderPlugin;
use bevy::app::{PluginGroup, PluginGroupBuilder};
use bevy::ecs::schedule::{InternedScheduleLabel, ScheduleLabel};
use bevy::prelude::FixedUpdate;

/// Every plugin of the crate: the simulation ([`DeformableSqPlugin`]), the dynamic meshes
/// ([`DeformableSqRenderPlugin`]), scene files as assets
/// ([`DeformableSqScenePlugin`]), with the `debug_render` feature the gizmos
/// (`debug_render::DeformableSqDebugPlugin`), with `picking` the mouse springs
/// (`picking::MouseSpringPlugin`) and with `egui` the inspector window
/// (`inspector::DeformableSqInspectorPlugin`). Each can be disabled or replaced
/// (`DeformableSqPlugins::default().build().disable::<DeformableSqRenderPlugin>()`), and they may
/// be added before or after Bevy's own plugins.
#[derive(Clone, Copy, Debug)]
pub struct DeformableSqPlugins {
    /// The schedule the simulation runs in (default `FixedUpdate`).
    pub schedule: InternedScheduleLabel,
}

impl Default for DeformableSqPlugins {
    fn default() -> Self {
        Self {
            schedule: FixedUpdate.intern(),
        }
    }
}

impl DeformableSqPlugins {
    /// The plugins with the simulation in another schedule (e.g. `Update`: one step per frame).
    pub fn in_schedule(schedule: impl ScheduleLabel) -> Self {
        Self {
            schedule: schedule.intern(),
        }
    }
}

impl PluginGroup for DeformableSqPlugins {
    fn build(self) -> PluginGroupBuilder {
        let group = PluginGroupBuilder::start::<Self>()
            .add(DeformableSqPlugin {
                schedule: self.schedule,
            })
            .add(DeformableSqRenderPlugin)
            .add(DeformableSqScenePlugin);
        #[cfg(feature = "debug_render")]
        let group = group.add(crate::debug_render::DeformableSqDebugPlugin);
        #[cfg(feature = "picking")]
        let group = group.add(crate::picking::MouseSpringPlugin);
        #[cfg(feature = "egui")]
        let group = group.add(crate::inspector::DeformableSqInspectorPlugin);
        group
    }
}
