//! # bevy_deformable_sq
//!
//! Terzopoulos & Metaxas's *deformable superquadrics* (IEEE PAMI 1991) for the Bevy engine.
//!
//! A deformable superquadric is a closed surface x = c + R (s + d): a superellipsoid s with a few
//! **global** parameters (translation c, rotation R, scale a, aspect ratios a1..a3, squareness
//! ε1, ε2) plus a **local** displacement d at every node of a finite-element membrane. Forces from
//! data act through first-order Lagrangian equations of motion, C q̇ + K q = f_q, integrated by
//! explicit Euler until the model comes to rest fitted to the data.
//!
//! ## Getting started
//!
//! Add `DeformableSqPlugins` (or the simulation alone, `DeformableSqPlugin`) to an app and spawn
//! `(GlobalShape { .. }, RigidState { .. })` with `RangeData` (points), `ImageData` (an image) or
//! `SpringForces` (springs to world anchors); the other components are required components with
//! defaults. `use bevy_deformable_sq::prelude::*`
//! brings in what an app needs. Without Bevy, [`model::fit::fit`] fits a point cloud in one call,
//! and the `dsq` binary does the same from the command line.
//!
//! ## The plugins
//!
//! `DeformableSqPlugins` is a plugin group; each member can be disabled or replaced:
//!
//! | plugin | what it does |
//! |---|---|
//! | `DeformableSqPlugin` | the simulation: the systems of `DeformableSqSystems` over the components below |
//! | `render::DeformableSqRenderPlugin` | a dynamic `Mesh3d` per model, its vertices written in place each frame |
//! | `plugin::scene::DeformableSqScenePlugin` | scene files (`*.dsq.ron`) as assets: parts, their data and settings |
//! | `debug_render::DeformableSqDebugPlugin` | gizmos for data points, their springs and user springs |
//! | `picking::MouseSpringPlugin` | press, drag and release a spring on any model |
//! | `inspector::DeformableSqInspectorPlugin` | a window per model: sliders, switches, fit to convergence, export |
//!
//! ## The components
//!
//! A model is `GlobalShape` (a, a1..a3, ε1, ε2) and `RigidState` (translation, rotation: the
//! global DOFs), `LocalDofs` (a displacement per node) and `FemMesh` (the tessellation they live
//! on), with `ModelSettings` (stiffness, damping, time step, which DOFs are free). Its data is
//! `RangeData` (points), `ImageData` (an image's potential) or `SpringForces` (springs to world
//! anchors, the mouse's among them). `FitDriver` runs the core's whole fit of a model's range data
//! in the background, writes it into the model and sends `FitFinished`; `PartJoint` joins two parts; `Inertia` adds mass (second-order dynamics).
//!
//! ## Features
//!
//! | feature | default | what it adds |
//! |---|---|---|
//! | `bevy` | yes | `plugin` and `render`: the plugin, its components and systems, the meshes |
//! | `serialize` | yes | serde derives on the components |
//! | `debug_render` | yes | `debug_render::DeformableSqDebugPlugin`: gizmos for data and springs |
//! | `picking` | no | `picking::MouseSpringPlugin`: pull models with the mouse |
//! | `egui` | no | `inspector::DeformableSqInspectorPlugin` and `inspector::model_inspector_ui`: the model inspector panel |
//! | `hot_reload` | no | scene files reload when they change on disk |
//! | `examples` | no | a window, a font, picking and egui, for the windowed examples |
//!
//! With `--no-default-features` the crate is the pure core, on glam (the version Bevy uses):
//!
//! * [`model`] — the paper's mathematics, pure and tested (no ECS types).
//! * [`io`] — reading point clouds (OBJ, PLY) and images, writing meshes and parameters.
//! * [`scene`] — scene files (RON): parts, their data and settings; loaded, run and saved.
//! * [`synthetic`] — deterministic test shapes: the paper's egg and mug, sampled superquadrics.
//!
//! ## The schedule
//!
//! The plugin runs in `FixedUpdate` by default, one step per run, in the chained set
//! `DeformableSqSystems`: `Prepare → Reassign → GatherForces → Integrate → Converge →
//! WriteBack` (see the `plugin` module).

#[cfg(feature = "debug_render")]
pub mod debug_render;
#[cfg(feature = "egui")]
pub mod inspector;
pub mod io;
pub mod model;
#[cfg(feature = "picking")]
pub mod picking;
#[cfg(feature = "bevy")]
pub mod plugin;
#[cfg(feature = "bevy")]
pub mod render;
pub mod scene;
pub mod synthetic;

#[cfg(feature = "bevy")]
pub use plugin::{DeformableSqPlugin, DeformableSqSystems};

#[cfg(feature = "bevy")]
mod plugins;
#[cfg(feature = "bevy")]
pub use plugins::DeformableSqPlugins;

/// The types a Bevy app needs: `use bevy_deformable_sq::prelude::*;`.
#[cfg(feature = "bevy")]
pub mod prelude {
    pub use crate::DeformableSqPlugins;
    #[cfg(feature = "debug_render")]
    pub use crate::debug_render::{DebugRenderConfig, DeformableSqDebugPlugin, DeformableSqGizmos};
    #[cfg(feature = "egui")]
    pub use crate::inspector::{
        DeformableSqInspectorPlugin, InspectedModel, InspectorState, InspectorSystems,
        ResidualHistory, model_inspector_ui,
    };
    #[cfg(feature = "picking")]
    pub use crate::picking::{
        ModelGrabbed, MouseSpring, MouseSpringPlugin, MouseSpringSettings, MouseSpringSystems,
    };
    pub use crate::plugin::scene::DeformableSqScenePlugin;
    pub use crate::plugin::scene::{
        DeformableScene, DeformableSceneCamera, DeformableSceneRoot, SceneImage, SceneInstance,
        ScenePart,
    };
    pub use crate::plugin::{
        DeformableSqPlugin, DeformableSqSystems, DepthTrack, FemMesh, FitDriver, FitFinished,
        GlobalShape, ImageData, Inertia, LocalDofs, ModelFrozen, ModelSettings, PartJoint,
        RangeData, RigidState, SimControl, Spring, SpringForces, simulation_task_pools,
    };
    pub use crate::render::{DeformableSqRenderPlugin, ModelColor, ModelMesh};
}
