//! Adding a data file to an open scene, as a file dropped on the window does: a scan becomes a
//! part fitted to it, an image becomes a backdrop. The scene asset is replaced by the scene as it
//! is now plus the file, so [`spawn_scenes`](super::spawn_scenes) respawns every part in its
//! current state and [`save_scene`](super::save_scene) writes the file's source with the rest.

use super::{DeformableScene, DeformableSceneRoot, scene_dir, scene_from_world};
use crate::io::{decode_luminance, decode_points};
use crate::model::fit::{FitOptions, MIN_POINTS};
use crate::model::forces::image::DEFAULT_SIGMA;
use crate::model::parts::{DEFAULT_MAX_PARTS, PartCount, Whole, fit_parts};
use crate::scene::{
    CameraDef, DataSource, Forces, PartDef, PartPlacement, Placement, SceneData, SceneDef,
};
use bevy::math::DVec3;
use bevy::prelude::*;
use bevy::tasks::{AsyncComputeTaskPool, Task, block_on, poll_once};
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

/// Where [`add_file`] puts what it adds, in world space.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FilePlacement {
    /// Where a point cloud's centroid goes; an image's centre is its x and y.
    pub at: DVec3,
    /// The RMS distance from their centroid that a cloud's points are scaled to.
    pub radius: f64,
    /// The world length of an image's longer side.
    pub extent: f64,
}

/// What [`add_file`] added.
#[derive(Clone, Debug, PartialEq)]
pub enum AddedFile {
    /// Parts fitted to the file's points: the object split into parts
    /// ([`crate::model::parts::fit_parts`]), one new scene part each (one part: placed `Auto`;
    /// several: at their pure fits, sharing the points, joined where they touch), with local
    /// DOFs.
    Part {
        /// The data source's name, and the part's (with several, the first part's).
        name: String,
        /// How many points the file has.
        points: usize,
        /// How many parts the object was split into.
        parts: usize,
    },
    /// An image source drawn as the backdrop in the world x–y plane; the scene's camera now faces
    /// it.
    Image {
        /// The source's name.
        name: String,
        /// Its size in pixels.
        size: (usize, usize),
    },
}

/// Adds the file at `file` to the scene of `root`:
/// - an OBJ or PLY file becomes a point source, placed by [`Placement::framing`] at
///   `placement.at` with RMS radius `placement.radius`, and the object's parts on it with range
///   forces and local DOFs ([`AddedFile::Part`]), which the scene's
///   [`FitDriver`](crate::plugin::FitDriver) fits to convergence;
/// - a PNG or JPEG file becomes an image source centred at `placement.at`'s x and y, its longer
///   side `placement.extent` long, with the scene's camera looking straight at it.
///
/// The scene asset is replaced by [`scene_from_world`] (every part as it is now, local
/// displacements included) plus the file, so the scene respawns and `save_scene` writes it all.
/// A file outside `assets_dir` is copied into `assets_dir/imported/` first, so the scene, saved,
/// reopens through the asset server. A file that cannot be read or decoded, or has fewer than
/// [`MIN_POINTS`] points, is an error naming it, and the scene is left as it was.
///
/// The split of a scan into parts takes seconds and runs here, on the calling thread; an app
/// adds a file without holding up its frames with [`add_file_in_background`].
pub fn add_file(
    world: &mut World,
    root: Entity,
    file: &Path,
    placement: FilePlacement,
    assets_dir: &Path,
) -> Result<AddedFile, String> {
    read_file(world, root, file, placement, assets_dir)?
        .split()?
        .add_to(world, root)
}

/// Starts adding the file at `file` to the scene of `root` as [`add_file`] does, and returns at
/// once: the file is read here (its errors are returned), and the scan's split into parts runs
/// on the [`AsyncComputeTaskPool`]. The entity returned carries an [`AddingFile`] while it runs;
/// when the split is done the scene gains the file, the entity is despawned, and a
/// [`FileAdded`] message says what came of it.
pub fn add_file_in_background(
    world: &mut World,
    root: Entity,
    file: &Path,
    placement: FilePlacement,
    assets_dir: &Path,
) -> Result<Entity, String> {
    let read = read_file(world, root, file, placement, assets_dir)?;
    let task = AsyncComputeTaskPool::get().spawn(async move { read.split() });
    Ok(world
        .spawn(AddingFile {
            root,
            file: file.to_path_buf(),
            started: Instant::now(),
            task,
        })
        .id())
}

/// A file being added to a scene in the background ([`add_file_in_background`]): while its
/// scan is split into parts.
#[derive(Component)]
pub struct AddingFile {
    root: Entity,
    file: PathBuf,
    started: Instant,
    task: Task<Result<SplitFile, String>>,
}

impl AddingFile {
    /// The file being added.
    pub fn file(&self) -> &Path {
        &self.file
    }

    /// The scene root it is added to.
    pub fn root(&self) -> Entity {
        self.root
    }

    /// How long it has been running.
    pub fn elapsed(&self) -> Duration {
        self.started.elapsed()
    }
}

/// Sent once when a file added by [`add_file_in_background`] has joined its scene, or failed
/// to.
#[derive(Message, Clone, Debug, PartialEq)]
pub struct FileAdded {
    /// The scene root.
    pub root: Entity,
    /// The file.
    pub file: PathBuf,
    /// What was added ([`add_file`]'s result).
    pub result: Result<AddedFile, String>,
}

/// `PreUpdate`: adds to their scenes the files whose split has finished, and sends
/// [`FileAdded`] for each (by a command, as the scene changes).
pub(super) fn finish_added_files(
    mut running: Query<(Entity, &mut AddingFile)>,
    mut commands: Commands,
) {
    for (e, mut adding) in &mut running {
        let Some(split) = block_on(poll_once(&mut adding.task)) else {
            continue;
        };
        let (root, file) = (adding.root, adding.file.clone());
        commands.entity(e).despawn();
        commands.queue(move |world: &mut World| {
            let result = split.and_then(|s| s.add_to(world, root));
            world.write_message(FileAdded { root, file, result });
        });
    }
}

/// A file read, decoded and placed for a scene, its object not yet split ([`read_file`]).
struct ReadFile {
    shown: String,
    stem: String,
    dir: PathBuf,
    what: Read,
}

/// What a [`ReadFile`] holds.
enum Read {
    /// A scan: its source, how many points the file has, and the points placed in the world.
    Points {
        source: DataSource,
        count: usize,
        placed: Vec<DVec3>,
    },
    /// An image: its source, its size in pixels, and the camera that looks straight at it.
    Image {
        source: DataSource,
        size: (usize, usize),
        camera: CameraDef,
    },
}

/// A file ready to join a scene: a scan split into parts, or an image ([`ReadFile::split`]).
struct SplitFile {
    read: ReadFile,
    whole: Option<Whole>,
}

/// Reads `file` for the scene of `root` ([`add_file`]'s first half): decodes it, places it, and
/// copies it among the assets when it lies outside them.
fn read_file(
    world: &World,
    root: Entity,
    file: &Path,
    placement: FilePlacement,
    assets_dir: &Path,
) -> Result<ReadFile, String> {
    let shown = file.display().to_string();
    let kind = Kind::of(file).ok_or_else(|| {
        format!("{shown}: not a point cloud (.obj, .ply) or an image (.png, .jpg, .jpeg)")
    })?;
    let bytes = std::fs::read(file).map_err(|e| format!("{shown}: cannot read: {e}"))?;
    if world.get::<DeformableSceneRoot>(root).is_none() {
        return Err("not a scene root".into());
    }
    let dir = scene_dir(world, root, assets_dir).ok_or("the scene has no file path")?;
    let stem = file
        .file_stem()
        .and_then(|s| s.to_str())
        .unwrap_or("data")
        .to_string();
    let what = match kind {
        Kind::Points => {
            let raw = decode_points(file, &bytes).map_err(|e| e.to_string())?;
            if raw.len() < MIN_POINTS {
                return Err(format!(
                    "{shown}: {} points, and a fit needs at least {MIN_POINTS}",
                    raw.len()
                ));
            }
            let framing = Placement::framing(&raw, placement.at, placement.radius)
                .ok_or_else(|| format!("{shown}: the points all coincide or are not finite"))?;
            let path = source_path(file, &dir, assets_dir)?;
            Read::Points {
                source: DataSource::Points {
                    path,
                    placement: framing,
                },
                count: raw.len(),
                placed: raw.iter().map(|p| framing.place(*p)).collect(),
            }
        }
        Kind::Image => {
            let (w, h, _) = decode_luminance(file, &bytes).map_err(|e| e.to_string())?;
            let path = source_path(file, &dir, assets_dir)?;
            let center = [placement.at.x, placement.at.y];
            Read::Image {
                source: DataSource::Image {
                    path,
                    sigma: DEFAULT_SIGMA,
                    center,
                    extent: placement.extent,
                },
                size: (w, h),
                // Straight on, as the image scenes look: the longer side fills about 70 % of a
                // 45° view.
                camera: CameraDef {
                    eye: [center[0], center[1], 1.6 * placement.extent],
                    target: [center[0], center[1], 0.0],
                    up: [0.0, 1.0, 0.0],
                },
            }
        }
    };
    Ok(ReadFile {
        shown,
        stem,
        dir,
        what,
    })
}

impl ReadFile {
    /// Splits a scan into parts ([`fit_parts`], pure); the slow half of [`add_file`], and the
    /// only one that needs no world.
    fn split(self) -> Result<SplitFile, String> {
        let whole = match &self.what {
            Read::Points { placed, .. } => {
                let opts = FitOptions {
                    global_only: true,
                    ..FitOptions::default()
                }
                .for_data();
                let whole = fit_parts(placed, PartCount::Auto(DEFAULT_MAX_PARTS), &opts)
                    .map_err(|e| format!("{}: {e}", self.shown))?;
                Some(whole)
            }
            Read::Image { .. } => None,
        };
        Ok(SplitFile { read: self, whole })
    }
}

impl SplitFile {
    /// Adds the file to the scene of `root` as it is now ([`add_file`]'s last step).
    fn add_to(self, world: &mut World, root: Entity) -> Result<AddedFile, String> {
        let ReadFile {
            stem, dir, what, ..
        } = self.read;
        let mut def = scene_from_world(world, root, true)?;
        let name = unused_name(&def, &stem);
        let added = match (what, self.whole) {
            (Read::Points { source, count, .. }, Some(whole)) => {
                def.data.insert(name.clone(), source);
                let (first, parts) = add_parts(&mut def, &name, &whole);
                AddedFile::Part {
                    name: first,
                    points: count,
                    parts,
                }
            }
            (
                Read::Image {
                    source,
                    size,
                    camera,
                },
                _,
            ) => {
                def.data.insert(name.clone(), source);
                def.camera = Some(camera);
                AddedFile::Image { name, size }
            }
            (Read::Points { .. }, None) => return Err("the scan was not split".into()),
        };
        replace_scene(world, root, def, &dir)?;
        Ok(added)
    }
}

/// Adds the parts of `whole` (split from the scene's source `source`) to `def`: one part placed
/// `Auto`, or several placed at their fits, sharing the source, joined where they touch
/// ([`SceneDef::add_whole`]), with local DOFs. Gives the first part's name and the count.
fn add_parts(def: &mut SceneDef, source: &str, whole: &Whole) -> (String, usize) {
    if whole.fits.len() == 1 {
        let mut part = PartDef::new(source);
        part.placement = PartPlacement::Auto;
        part.forces = Forces::range(source);
        def.parts.push(part);
        return (source.to_string(), 1);
    }
    // The split's parts are pure superquadrics; here they get their membranes from the fit.
    let first = def.add_whole(source, whole);
    for part in &mut def.parts[first..] {
        part.free.global_only = false;
    }
    (format!("{source} 1"), whole.fits.len())
}

/// Adds `part` to the scene of `root` (its data sources must be the scene's already): a part
/// placed by four clicks on a scene's image, say, with `Axes` in the image's pixels and
/// [`Forces::image`]. As with [`add_file`], the scene asset is replaced by [`scene_from_world`]
/// plus the part, so every part respawns as it is now and `save_scene` writes the new one. A part
/// the scene rejects, or one that cannot be placed (a zero-length axis), is an error, and the
/// scene is left as it was.
pub fn add_part(
    world: &mut World,
    root: Entity,
    part: PartDef,
    assets_dir: &Path,
) -> Result<(), String> {
    let mut def = scene_from_world(world, root, true)?;
    let dir = scene_dir(world, root, assets_dir).ok_or("the scene has no file path")?;
    def.parts.push(part);
    replace_scene(world, root, def, &dir)
}

/// Checks `def`, loads its data (paths relative to `dir`), checks that its last part can be
/// placed, and makes it the scene asset of `root`, which then respawns.
fn replace_scene(
    world: &mut World,
    root: Entity,
    mut def: SceneDef,
    dir: &Path,
) -> Result<(), String> {
    let handle = &world
        .get::<DeformableSceneRoot>(root)
        .ok_or("not a scene root")?
        .0;
    let id = handle.id();
    let scene_file = handle
        .path()
        .and_then(|p| p.path().file_name())
        .map_or_else(|| dir.join("scene"), |n| dir.join(n));
    def.validate(&scene_file).map_err(|e| e.to_string())?;
    let data = SceneData::resolve(&def, &scene_file, |rel| {
        std::fs::read(dir.join(rel)).map_err(|e| format!("cannot read {rel:?}: {e}"))
    })
    .map_err(|e| e.to_string())?;
    if let Some(last) = def.parts.last()
        && data.initial_state(&def, def.parts.len() - 1).is_none()
    {
        let name = &last.name;
        return Err(format!("part {name:?} cannot be placed where it was asked"));
    }
    def.apply_noise_stiffness(&data);
    world
        .resource_mut::<Assets<DeformableScene>>()
        .insert(id, DeformableScene { def, data })
        .map_err(|e| format!("the scene asset is gone: {e}"))
}

/// The kinds of file [`add_file`] takes, by extension.
enum Kind {
    Points,
    Image,
}

impl Kind {
    fn of(file: &Path) -> Option<Kind> {
        let ext = file.extension()?.to_str()?.to_ascii_lowercase();
        match ext.as_str() {
            "obj" | "ply" => Some(Kind::Points),
            "png" | "jpg" | "jpeg" => Some(Kind::Image),
            _ => None,
        }
    }
}

/// `stem`, or `stem 2`, `stem 3`, …: the first name no data source or part has.
fn unused_name(def: &SceneDef, stem: &str) -> String {
    let taken = |n: &str| def.data.contains_key(n) || def.parts.iter().any(|p| p.name == n);
    let (mut name, mut i) = (stem.to_string(), 1);
    while taken(&name) {
        i += 1;
        name = format!("{stem} {i}");
    }
    name
}

/// The path a scene in `dir` names `file` by: relative, when the file lies under `assets_dir`;
/// otherwise the file is copied into `assets_dir/imported/` (under a name not yet taken there by
/// another file) and named there.
fn source_path(file: &Path, dir: &Path, assets_dir: &Path) -> Result<String, String> {
    let canon = |p: &Path| std::fs::canonicalize(p).unwrap_or_else(|_| p.to_path_buf());
    let (file_c, assets_c) = (canon(file), canon(assets_dir));
    let inside = if file_c.starts_with(&assets_c) {
        file_c
    } else {
        import(file, &assets_c.join("imported"))?
    };
    let rel = crate::scene::relative_path(&inside, &canon(dir));
    Ok(rel.to_string_lossy().replace('\\', "/"))
}

/// Copies `file` into `into` (made if missing), keeping its name unless another file has it; an
/// identical copy already there is reused.
fn import(file: &Path, into: &Path) -> Result<PathBuf, String> {
    let fail = |e: std::io::Error| {
        format!(
            "cannot copy {} into {}: {e}",
            file.display(),
            into.display()
        )
    };
    std::fs::create_dir_all(into).map_err(fail)?;
    let name = file
        .file_name()
        .ok_or("the file has no name")?
        .to_string_lossy();
    let (stem, ext) = name.rsplit_once('.').unwrap_or((&name, ""));
    let bytes = std::fs::read(file).map_err(fail)?;
    let mut i = 1;
    loop {
        let candidate = match i {
            1 => into.join(&*name),
            _ => into.join(format!("{stem}_{i}.{ext}")),
        };
        match std::fs::read(&candidate) {
            Ok(existing) if existing == bytes => return Ok(candidate),
            Ok(_) => i += 1,
            Err(_) => {
                std::fs::write(&candidate, &bytes).map_err(fail)?;
                return Ok(candidate);
            }
        }
    }
}
