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
//! * [`model`] — the paper's mathematics, pure and tested (no ECS types).
//! * [`io`] — reading point clouds (OBJ, PLY) and writing meshes and parameters.
//! * [`plugin`] — [`DeformableSqPlugin`]: models as components, simulated by one chained system set.
//! * [`render`] — each model drawn as a dynamic mesh; `debug_render` (feature) draws data and springs.
//! * [`scene`] — scene files (RON): parts, their data and settings; loaded, run and saved.
//! * [`synthetic`] — deterministic test shapes: the paper's egg and mug, sampled superquadrics.

#[cfg(feature = "debug_render")]
pub mod debug_render;
pub mod io;
pub mod model;
pub mod plugin;
pub mod render;
pub mod scene;
pub mod synthetic;

pub use plugin::{DeformableSqPlugin, DeformableSqSystems};

/// The types a Bevy app needs: `use bevy_deformable_sq::prelude::*;`.
pub mod prelude {
    #[cfg(feature = "debug_render")]
    pub use crate::debug_render::{DebugRenderConfig, DeformableSqDebugPlugin};
    pub use crate::plugin::scene::{
        DeformableScene, DeformableSceneCamera, DeformableSceneRoot, SceneImage, SceneInstance,
        ScenePart,
    };
    pub use crate::plugin::{
        DeformableSqPlugin, DeformableSqSystems, FemMesh, GlobalShape, ImageData, Inertia,
        LocalDofs, ModelSettings, PartJoint, RangeData, RigidState, SimControl, Spring,
        SpringForces, simulation_task_pools,
    };
    pub use crate::render::{ModelColor, ModelMesh};
}
