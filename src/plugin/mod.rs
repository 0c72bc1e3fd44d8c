//! [`DeformableSqPlugin`]: deformable superquadrics as Bevy entities.
//!
//! Add the plugin, spawn `(GlobalShape { .. }, RigidState { .. })`, optionally with
//! [`RangeData`] or [`SpringForces`], and the model simulates in the plugin's schedule (default
//! [`FixedUpdate`]) through one chained system set, [`DeformableSqSystems`], whose stages are the
//! paper's loop. With the render plugins present each model is also a [`Mesh3d`] whose vertices
//! follow the surface (see [`crate::render`]); with `MinimalPlugins` it simulates headless.
//! With an `AssetPlugin`, scene files spawn models and their data (see [`scene`]). A
//! [`DepthTrack`] makes a model follow an object through a depth video.

pub mod components;
mod fit_driver;
pub mod headless;
mod messages;
pub mod scene;
pub(crate) mod systems;
mod track;

pub use components::*;
pub use fit_driver::FitDriver;
pub use messages::{FitFinished, ModelFrozen};
pub use track::DepthTrack;

use bevy::ecs::schedule::{InternedScheduleLabel, ScheduleLabel};
use bevy::prelude::*;

/// The stages of one simulation step, chained in this order in the plugin's schedule.
#[derive(SystemSet, Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum DeformableSqSystems {
    /// Share tessellations, size buffers, record spawn states, carry out resets, and freeze models
    /// made non-finite from outside.
    Prepare,
    /// Reattach range points to their nearest nodes every `reassign_every` steps (section VI-B).
    Reassign,
    /// Turn data and user springs into nodal forces (eq. 22), then add the joints' constraint
    /// forces ([`PartJoint`]).
    GatherForces,
    /// One explicit Euler step of C q̇ + K q = f_q (eq. 15).
    Integrate,
    /// Models with a [`FitDriver`]: their fits started, followed and written back; models with
    /// a [`DepthTrack`]: their next frame tracked.
    Converge,
    /// Copy the model frame into `Transform`, send [`FitFinished`] and [`ModelFrozen`] (and, in
    /// debug builds, check every state is finite).
    WriteBack,
}

/// Task pools that give Bevy's compute pool, where the plugin's systems and their
/// `par_iter_mut` over the models run, every core of the machine. Bevy's default
/// ([`TaskPoolOptions::default`]) first gives a quarter of the cores (at least one each) to the
/// I/O and async-compute pools and the compute pool what is left: one thread on a 2-core machine,
/// so the models of a scene are stepped one after the other while the other core idles, and half
/// of the cores on eight. The I/O and async-compute pools keep their threads here, which sleep
/// while no asset loads. The pools are process-wide, made by the first app that builds a
/// `TaskPoolPlugin`. Measured (`cargo bench --bench kernels -- app_step`): one frame of the sandbox's load, 11
/// models with image forces, ×0.64–0.70 on 2 cores.
///
/// ```
/// use bevy::prelude::*;
/// use bevy::tasks::{ComputeTaskPool, available_parallelism};
/// use bevy_deformable_sq::prelude::*;
///
/// let mut app = App::new();
/// app.add_plugins((
///     MinimalPlugins.set(TaskPoolPlugin {
///         task_pool_options: simulation_task_pools(),
///     }),
///     DeformableSqPlugin::default(),
/// ));
/// assert_eq!(ComputeTaskPool::get().thread_num(), available_parallelism());
/// ```
pub fn simulation_task_pools() -> TaskPoolOptions {
    let mut options = TaskPoolOptions::default();
    options.compute.min_threads = bevy::tasks::available_parallelism();
    options
}

/// Simulates deformable superquadrics. `schedule` is where the steps run: one step per run.
pub struct DeformableSqPlugin {
    /// The schedule the [`DeformableSqSystems`] run in (default [`FixedUpdate`]).
    pub schedule: InternedScheduleLabel,
}

impl Default for DeformableSqPlugin {
    fn default() -> Self {
        Self {
            schedule: FixedUpdate.intern(),
        }
    }
}

impl DeformableSqPlugin {
    /// The plugin running in another schedule (e.g. `Update` for one step per frame).
    pub fn in_schedule(schedule: impl ScheduleLabel) -> Self {
        Self {
            schedule: schedule.intern(),
        }
    }
}

impl Plugin for DeformableSqPlugin {
    fn build(&self, app: &mut App) {
        use DeformableSqSystems::*;
        if let Some(pool) = bevy::tasks::ComputeTaskPool::try_get() {
            let cores = bevy::tasks::available_parallelism();
            if pool.thread_num() < cores {
                info!(
                    "Bevy's compute pool, where the models step in parallel, has {} of {cores} \
                     threads; `TaskPoolPlugin {{ task_pool_options: simulation_task_pools() }}` \
                     gives it every core",
                    pool.thread_num()
                );
            }
        }
        app.init_resource::<FemMeshCache>()
            .register_type::<GlobalShape>()
            .register_type::<RigidState>()
            .register_type::<LocalDofs>()
            .register_type::<FemMesh>()
            .register_type::<ModelSettings>()
            .register_type::<SimControl>()
            .register_type::<SpringForces>()
            .add_message::<FitFinished>()
            .add_message::<ModelFrozen>()
            .configure_sets(
                self.schedule,
                (
                    Prepare,
                    Reassign,
                    GatherForces,
                    Integrate,
                    Converge,
                    WriteBack,
                )
                    .chain(),
            )
            .add_systems(
                self.schedule,
                (
                    systems::prepare.in_set(Prepare),
                    systems::reassign.in_set(Reassign),
                    (systems::gather_forces, systems::joint_forces)
                        .chain()
                        .in_set(GatherForces),
                    systems::integrate.in_set(Integrate),
                    (fit_driver::drive_fits, track::advance_tracks)
                        .chain()
                        .in_set(Converge),
                    (systems::write_transforms, messages::send_messages).in_set(WriteBack),
                ),
            );
        #[cfg(debug_assertions)]
        app.add_systems(self.schedule, systems::assert_finite.in_set(WriteBack));
        // The models' `Transform`s are written before Bevy propagates them, whichever schedule
        // the plugin runs in (a no-op constraint where that schedule propagates nothing).
        app.configure_sets(
            self.schedule,
            WriteBack.before(bevy::transform::TransformSystems::Propagate),
        );
    }
}
