//! Scene files as Bevy assets: load a `.dsq.ron` scene (see [`crate::scene`]) with the
//! [`AssetServer`], spawn a [`DeformableSceneRoot`] holding its handle, and every part of the
//! scene appears as a child entity with the plugin's components; despawn the root and the parts
//! go with it. When the asset changes (Bevy's file watcher with this crate's `hot_reload`
//! feature, or `Assets::get_mut`) the parts are spawned anew. A scene that fails to load is
//! logged and recorded in [`SceneInstance::error`]; the app keeps running. [`save_scene`] writes
//! the parts' current state back to a scene file.
//!
//! ```no_run
//! use bevy::prelude::*;
//! use bevy_deformable_sq::prelude::*;
//!
//! fn setup(mut commands: Commands, assets: Res<AssetServer>) {
//!     commands.spawn(DeformableSceneRoot(assets.load("scenes/egg.dsq.ron")));
//!     commands.spawn((Camera3d::default(), DeformableSceneCamera));
//! }
//! # App::new().add_plugins((DefaultPlugins, DeformableSqPlugins::default())).add_systems(Startup, setup);
//! ```

use super::components::{ModelColor, PALETTE};
use super::{
    FemMesh, FitDriver, GlobalShape, ImageData, Inertia, LocalDofs, ModelSettings, PartJoint,
    RangeData, RigidState,
};
use crate::model::dynamics::ModelState;
use crate::model::forces::range::RangeForces;
use crate::scene::{
    CameraDef, Forces, JointDef, PartDef, SCENE_EXTENSION, SceneData, SceneDef, SceneError,
};
use bevy::asset::io::Reader;
use bevy::asset::{AssetLoader, LoadContext, LoadState};
use bevy::math::DVec3;
use bevy::prelude::*;
use std::collections::HashMap;
use std::path::{Path, PathBuf};

mod add;
pub use add::{
    AddedFile, AddingFile, FileAdded, FilePlacement, add_file, add_file_in_background, add_part,
};

/// A loaded scene: its definition and its data (points placed in the world, image potentials).
#[derive(Asset, TypePath, Clone, Debug)]
pub struct DeformableScene {
    /// The scene as written.
    pub def: SceneDef,
    /// Its data, loaded.
    pub data: SceneData,
}

/// Loads `.dsq.ron` scene files and the data files they name (read through the asset server,
/// relative to the scene).
#[derive(Default, TypePath)]
pub struct DeformableSceneLoader;

impl AssetLoader for DeformableSceneLoader {
    type Asset = DeformableScene;
    type Settings = ();
    type Error = SceneError;

    async fn load(
        &self,
        reader: &mut dyn Reader,
        _: &Self::Settings,
        load_context: &mut LoadContext<'_>,
    ) -> Result<Self::Asset, Self::Error> {
        let file = load_context.path().path().to_path_buf();
        let fail = |message: String| SceneError {
            file: file.clone(),
            position: None,
            field: None,
            message,
        };
        let mut bytes = Vec::new();
        reader
            .read_to_end(&mut bytes)
            .await
            .map_err(|e| fail(format!("cannot read: {e}")))?;
        let text = std::str::from_utf8(&bytes).map_err(|e| fail(format!("not UTF-8: {e}")))?;
        let mut def = SceneDef::parse(text, &file)?;
        let mut files: HashMap<String, Result<Vec<u8>, String>> = HashMap::new();
        for (_, rel) in def.data_files() {
            if files.contains_key(rel) {
                continue;
            }
            let read = match load_context.path().resolve_embed_str(rel) {
                Ok(path) => load_context
                    .read_asset_bytes(path)
                    .await
                    .map_err(|e| format!("cannot read {rel:?}: {e}")),
                Err(e) => Err(format!("{rel:?} is not a valid asset path: {e}")),
            };
            files.insert(rel.to_string(), read);
        }
        let data = SceneData::resolve(&def, &file, |rel| {
            files
                .get(rel)
                .cloned()
                .unwrap_or_else(|| Err(format!("{rel:?} was not read")))
        })?;
        def.apply_noise_stiffness(&data);
        Ok(DeformableScene { def, data })
    }

    fn extensions(&self) -> &[&str] {
        &[SCENE_EXTENSION]
    }
}

/// Spawn one to instantiate a scene: its parts become children of this entity. Keep the root at
/// the origin (parts are placed in world space).
#[derive(Component, Clone, Debug, Default)]
#[require(SceneInstance, Transform, Visibility)]
pub struct DeformableSceneRoot(pub Handle<DeformableScene>);

/// What a [`DeformableSceneRoot`] has spawned.
#[derive(Component, Clone, Debug, Default)]
pub struct SceneInstance {
    /// The part entities, in the scene's order.
    pub parts: Vec<Entity>,
    /// One entity per image data source ([`SceneImage`]), drawn as a backdrop by the render
    /// plugin.
    pub images: Vec<Entity>,
    /// The scene the parts were spawned from (cleared to respawn).
    pub spawned: Option<AssetId<DeformableScene>>,
    /// Why the scene failed to load, if it did.
    pub error: Option<String>,
    /// The scene camera last applied: a respawn moves the camera only when the scene's camera
    /// changed, so a view the user has moved to stays.
    camera: Option<CameraDef>,
}

/// A part spawned from a scene: its index in the scene's `parts`.
#[derive(Component, Clone, Copy, Debug, PartialEq, Eq)]
pub struct ScenePart {
    /// Index into [`SceneDef::parts`].
    pub index: usize,
}

/// An image data source of a scene, placed where the scene puts it (a child of the root). With the
/// render plugins it is drawn as a textured quad in the world x–y plane, at z = 0 where the parts'
/// projected outlines are fitted, so each fitted outline lies on its image edge.
#[derive(Component, Clone, Debug)]
#[require(Transform, Visibility)]
pub struct SceneImage {
    /// The source's name in the scene.
    pub name: String,
    /// The image and its potential.
    pub potential: std::sync::Arc<crate::model::forces::image::ImagePotential>,
    /// Draw the potential P (eq. 20, as grey up to P_ref) instead of the image.
    pub show_potential: bool,
}

/// Put it on a camera to have it placed where a scene's `camera` says when the scene spawns.
#[derive(Component, Clone, Copy, Debug, Default)]
pub struct DeformableSceneCamera;

/// The settings a scene's part simulates with.
pub fn part_settings(part: &PartDef) -> ModelSettings {
    let d = part.dynamics();
    ModelSettings {
        w0: d.w0,
        w1: d.w1,
        dt: d.dt,
        gamma_global: d.gamma_global,
        gamma_local: d.gamma_local,
        reassign_every: part.reassign_every,
        global_only: part.free.global_only,
        hold_local_steps: 0,
        fix_epsilon: part.fix_epsilon(),
        fix_shape: part.free.fix_shape,
        fix_pose: false,
        planar: part.planar(),
        taper: part.free.taper,
        bend: part.free.bend,
        implicit_local: d.implicit_local,
    }
}

/// Spawns part `index` of `scene` as a child of `root`: the model's components, its data
/// (range parts also get a [`FitDriver`] that fits them as `dsq fit --scene` does and leaves the
/// model paused at rest) and a [`Name`].
fn spawn_part(
    commands: &mut Commands,
    root: Entity,
    scene: &DeformableScene,
    index: usize,
) -> Option<Entity> {
    let part = scene.def.parts.get(index)?;
    let state: ModelState = scene.data.initial_state(&scene.def, index)?;
    let local = if part.local.is_some() {
        state.displacement.clone()
    } else {
        Vec::new()
    };
    let mut e = commands.spawn((
        Name::new(part.name.clone()),
        ScenePart { index },
        GlobalShape::new(state.shape, state.deformation),
        RigidState {
            translation: state.translation,
            rotation: state.rotation,
        },
        LocalDofs {
            displacement: local,
        },
        FemMesh::new(part.k),
        part_settings(part),
        // The part's colour follows its place in the scene, whatever components it carries.
        ModelColor(PALETTE[index % PALETTE.len()]),
        ChildOf(root),
    ));
    if let Some(params) = part.inertia {
        e.insert(Inertia::new(params));
    }
    match &part.forces {
        Forces::Free => {}
        Forces::Range {
            beta,
            coverage,
            influence,
            ..
        } => {
            let points = scene
                .data
                .range_points(&scene.def, index)
                .unwrap_or_default();
            let options = part.fit_options(&state);
            let mut forces = RangeForces::new(points, *beta, *influence);
            forces.coverage = *coverage;
            e.insert((
                RangeData {
                    forces,
                    reassignments: 0,
                },
                FitDriver::new(options),
            ));
        }
        Forces::Image { .. } => {
            if let Some(forces) = scene.data.image_forces(part) {
                e.insert(ImageData { forces });
            }
        }
    }
    Some(e.id())
}

/// Spawns the parts of every root whose scene has loaded (or changed since), and records load
/// failures (logged once; the app keeps running).
pub fn spawn_scenes(
    mut commands: Commands,
    scenes: Res<Assets<DeformableScene>>,
    server: Res<AssetServer>,
    mut changes: MessageReader<AssetEvent<DeformableScene>>,
    mut roots: Query<(Entity, &DeformableSceneRoot, &mut SceneInstance)>,
    mut cameras: Query<&mut Transform, With<DeformableSceneCamera>>,
    joints: Query<(Entity, &ChildOf), With<PartJoint>>,
) {
    let modified: Vec<AssetId<DeformableScene>> = changes
        .read()
        .filter_map(|e| match e {
            AssetEvent::Modified { id } => Some(*id),
            _ => None,
        })
        .collect();
    for (root, DeformableSceneRoot(handle), mut instance) in &mut roots {
        let id = handle.id();
        if instance.spawned == Some(id) && !modified.contains(&id) {
            continue;
        }
        let Some(scene) = scenes.get(id) else {
            if let Some(LoadState::Failed(e)) = server.get_load_state(id)
                && instance.error.is_none()
            {
                error!("deformable scene {:?}: {e}", handle.path());
                instance.error = Some(e.to_string());
            }
            continue;
        };
        let instance = &mut *instance;
        for e in instance.parts.drain(..).chain(instance.images.drain(..)) {
            commands.entity(e).try_despawn();
        }
        // The root's joints go with the parts they join; the scene's joints are made anew.
        for (e, _) in joints.iter().filter(|(_, c)| c.parent() == root) {
            commands.entity(e).try_despawn();
        }
        let mut images: Vec<_> = scene.data.images.iter().collect();
        images.sort_by(|a, b| a.0.cmp(b.0));
        instance.images = images
            .into_iter()
            .map(|(name, potential)| {
                commands
                    .spawn((
                        Name::new(format!("image {name}")),
                        SceneImage {
                            name: name.clone(),
                            potential: potential.clone(),
                            show_potential: false,
                        },
                        ChildOf(root),
                    ))
                    .id()
            })
            .collect();
        let spawned: Vec<Option<Entity>> = (0..scene.def.parts.len())
            .map(|i| spawn_part(&mut commands, root, scene, i))
            .collect();
        for def in &scene.def.joints {
            if let (Some(&Some(a)), Some(&Some(b))) =
                (spawned.get(def.parts[0]), spawned.get(def.parts[1]))
            {
                let mut joint = PartJoint::new(a, def.ends[0], b, def.ends[1]);
                joint.joint.stiffness = def.stiffness;
                commands.spawn((Name::new("joint"), joint, ChildOf(root)));
            }
        }
        instance.parts = spawned.into_iter().flatten().collect();
        instance.spawned = Some(id);
        instance.error = None;
        if scene.def.camera == instance.camera {
            continue;
        }
        instance.camera = scene.def.camera;
        if let Some(c) = &scene.def.camera {
            let eye = DVec3::from_array(c.eye).as_vec3();
            let target = DVec3::from_array(c.target).as_vec3();
            let up = DVec3::from_array(c.up).as_vec3();
            for mut t in &mut cameras {
                *t = Transform::from_translation(eye).looking_at(target, up);
            }
        }
    }
}

/// The scene of `root` with every part's current state: pose, global shape and settings from
/// its components, and its local displacements when `include_local`. Models that are children of
/// the root but were not spawned from the scene are added as parts with no data.
pub fn scene_from_world(
    world: &World,
    root: Entity,
    include_local: bool,
) -> Result<SceneDef, String> {
    let handle = &world
        .get::<DeformableSceneRoot>(root)
        .ok_or_else(|| format!("{root} is not a deformable scene root"))?
        .0;
    let scene = world
        .resource::<Assets<DeformableScene>>()
        .get(handle.id())
        .ok_or("the scene has not loaded")?;
    let mut def = scene.def.clone();
    let children: Vec<Entity> = world
        .get::<Children>(root)
        .map(|c| c.iter().collect())
        .unwrap_or_default();
    let mut index_of = HashMap::new();
    for &e in &children {
        let (Some(rigid), Some(shape), Some(local), Some(fem), Some(s)) = (
            world.get::<RigidState>(e),
            world.get::<GlobalShape>(e),
            world.get::<LocalDofs>(e),
            world.get::<FemMesh>(e),
            world.get::<ModelSettings>(e),
        ) else {
            continue;
        };
        // A model added under the root (e.g. placed by a user) becomes a new part with no data.
        let index = match world.get::<ScenePart>(e) {
            Some(p) => p.index,
            None => {
                let name = world
                    .get::<Name>(e)
                    .map(|n| n.to_string())
                    .unwrap_or_default();
                def.parts.push(PartDef::new(name));
                def.parts.len() - 1
            }
        };
        index_of.insert(e, index);
        let Some(part) = def.parts.get_mut(index) else {
            continue;
        };
        part.k = fem.k;
        part.w0 = s.w0;
        part.w1 = s.w1;
        part.dt = s.dt;
        part.damping.global = Some(s.gamma_global);
        part.damping.local = s.gamma_local;
        part.reassign_every = s.reassign_every;
        part.free.global_only = s.global_only;
        if s.fix_epsilon != part.fix_epsilon() {
            part.free.fix_epsilon = Some(s.fix_epsilon);
        }
        if s.planar != part.planar() {
            part.free.planar = Some(s.planar);
        }
        part.free.fix_shape = s.fix_shape;
        part.free.taper = s.taper;
        part.free.bend = s.bend;
        part.inertia = world.get::<Inertia>(e).map(|i| i.params);
        let state = super::model_state(rigid, shape, local);
        let sized = local.displacement.len() == fem.k * fem.k + 2;
        def.set_state(index, &state, include_local && sized);
    }
    // The joints as they are now: those between two of the scene's models.
    def.joints = children
        .iter()
        .filter_map(|&e| world.get::<PartJoint>(e))
        .filter_map(|j| {
            Some(JointDef {
                parts: [*index_of.get(&j.a)?, *index_of.get(&j.b)?],
                ends: [j.joint.a, j.joint.b],
                stiffness: j.joint.stiffness,
            })
        })
        .collect();
    Ok(def)
}

/// The directory a loaded scene's file lies in on disk, given the asset folder (by default
/// `assets/` of the app's base path: [`default_assets_dir`]).
pub fn scene_dir(world: &World, root: Entity, assets_dir: &Path) -> Option<PathBuf> {
    let handle = &world.get::<DeformableSceneRoot>(root)?.0;
    let path = handle.path()?.path().parent()?.to_path_buf();
    Some(assets_dir.join(path))
}

/// Bevy's default asset folder: `assets/` under the app's base path.
pub fn default_assets_dir() -> PathBuf {
    bevy::asset::io::file::FileAssetReader::get_base_path().join("assets")
}

/// Writes the scene of `root` with every part's current state (see [`scene_from_world`]) to
/// `out`, its data paths rewritten to point from `out`'s directory at the same files.
pub fn save_scene(
    world: &World,
    root: Entity,
    out: &Path,
    assets_dir: &Path,
    include_local: bool,
) -> Result<(), String> {
    let mut def = scene_from_world(world, root, include_local)?;
    let from = scene_dir(world, root, assets_dir).ok_or("the scene has no file path")?;
    def.rebase(&from, out.parent().unwrap_or(Path::new("")));
    def.save(out).map_err(|e| e.to_string())
}

/// Scene files as assets: the `.dsq.ron` loader, and the spawning of a [`DeformableSceneRoot`]'s
/// parts in [`PreUpdate`], after the files added in the background ([`add_file_in_background`])
/// whose split is done have joined their scenes. It needs Bevy's `AssetPlugin` (in `DefaultPlugins`), added before or
/// after it: with the `AssetPlugin` already there it registers at once, otherwise when the app's
/// plugins are finished (`App::run` does that; a test that calls `App::update` itself calls
/// `App::finish` first). Part of [`crate::DeformableSqPlugins`].
#[derive(Default)]
pub struct DeformableSqScenePlugin;

impl Plugin for DeformableSqScenePlugin {
    fn build(&self, app: &mut App) {
        if app.is_plugin_added::<bevy::asset::AssetPlugin>() {
            register_scene_assets(app);
        }
    }

    fn finish(&self, app: &mut App) {
        if app.is_plugin_added::<bevy::asset::AssetPlugin>() {
            register_scene_assets(app);
        } else {
            warn!(
                "DeformableSqScenePlugin: no AssetPlugin in this app, so scene files cannot load \
                 (add DefaultPlugins or AssetPlugin)"
            );
        }
    }
}

/// The scene asset, its loader and the spawning system, once.
fn register_scene_assets(app: &mut App) {
    if app.world().contains_resource::<Assets<DeformableScene>>() {
        return;
    }
    app.init_asset::<DeformableScene>()
        .init_asset_loader::<DeformableSceneLoader>()
        .add_message::<FileAdded>()
        .add_systems(PreUpdate, (add::finish_added_files, spawn_scenes).chain());
}
