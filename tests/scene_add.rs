//! Adding a data file to an open scene (`plugin::scene::add_file`, what a file dropped on the
//! sandbox does): a scan becomes a part that is fitted to it, keeps the scene's joints and the
//! user's view, and saves and reopens as it was; an image becomes the backdrop; a file that
//! cannot be taken is an error naming it, and nothing changes.

use bevy::prelude::*;
use bevy_deformable_sq::model::fit::{bounding_diagonal, residuals};
use bevy_deformable_sq::model::image_fit::PartAxes;
use bevy_deformable_sq::plugin::scene::{
    AddedFile, AddingFile, DeformableScene, FileAdded, FilePlacement, SceneImage, add_file,
    add_file_in_background, add_part, save_scene,
};
use bevy_deformable_sq::plugin::world_positions;
use bevy_deformable_sq::prelude::*;
use bevy_deformable_sq::scene::{Forces, PartDef, PartPlacement, SceneDef};
use glam::DVec3;
use std::path::{Path, PathBuf};

#[path = "support/scene_app.rs"]
mod scene_app;
use scene_app::{Step, load, parts, scene_app};

/// A folder of assets of this test's own, holding a copy of the shipped chain scene (four jointed
/// links, no data files) in `scenes/`.
fn assets_with_chain(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("bdsq-add-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(dir.join("scenes")).unwrap();
    let shipped = Path::new(env!("CARGO_MANIFEST_DIR")).join("assets/scenes/chain.dsq.ron");
    std::fs::copy(shipped, dir.join("scenes/chain.dsq.ron")).unwrap();
    dir
}

/// An app on a copy of the chain scene in assets of its own (see [`assets_with_chain`]), with a
/// scene camera: the assets folder, the app, the camera and the scene's root.
fn chain_app(name: &str) -> (PathBuf, App, Entity, Entity) {
    let dir = assets_with_chain(name);
    let mut app = scene_app(&dir);
    let camera = app
        .world_mut()
        .spawn((Camera3d::default(), DeformableSceneCamera))
        .id();
    let root = load(&mut app, "scenes/chain.dsq.ron");
    (dir, app, camera, root)
}

/// Writes `points` to `file` as the vertices of an OBJ.
fn write_points<'a>(file: &Path, points: impl IntoIterator<Item = &'a DVec3>) {
    let text: String = points
        .into_iter()
        .map(|p| format!("v {} {} {}\n", p.x, p.y, p.z))
        .collect();
    std::fs::write(file, text).unwrap();
}

fn shipped_data(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("assets/data")
        .join(name)
}

fn scene_def(app: &App, root: Entity) -> SceneDef {
    let handle = &app.world().get::<DeformableSceneRoot>(root).unwrap().0;
    let scenes = app.world().resource::<Assets<DeformableScene>>();
    scenes.get(handle.id()).unwrap().def.clone()
}

fn named(app: &mut App, name: &str) -> Option<Entity> {
    let mut q = app.world_mut().query::<(Entity, &Name)>();
    q.iter(app.world())
        .find(|(_, n)| n.as_str() == name)
        .map(|(e, _)| e)
}

fn joint_count(app: &mut App) -> usize {
    let mut q = app.world_mut().query::<&PartJoint>();
    q.iter(app.world()).count()
}

const PLACE: FilePlacement = FilePlacement {
    at: DVec3::new(2.0, 0.6, 1.5),
    radius: 0.4,
    extent: 3.0,
};

#[test]
fn a_scan_added_to_a_scene_is_fitted_and_saves_and_reopens_as_it_was() {
    let (dir, mut app, camera, root) = chain_app("scan");
    assert_eq!(joint_count(&mut app), 3);
    // The user has moved the view since the scene placed the camera.
    let user_view = Transform::from_xyz(-4.0, 3.0, 2.0).looking_at(Vec3::ZERO, Vec3::Y);
    *app.world_mut().get_mut::<Transform>(camera).unwrap() = user_view;

    // One superquadric's surface, seen from one side: one part. (A whole object's scan splits
    // into several: the last test.)
    let q = bevy_deformable_sq::model::superquadric::SuperquadricParams {
        a: 1.0,
        a1: 1.0,
        a2: 0.7,
        a3: 0.5,
        e1: 0.8,
        e2: 1.0,
    };
    let all = bevy_deformable_sq::synthetic::superquadric_cloud(
        &q,
        DVec3::ZERO,
        glam::DQuat::IDENTITY,
        3000,
        0.002,
        7,
    );
    let view = DVec3::new(0.3, 0.4, 0.866).normalize();
    let scan = std::env::temp_dir().join(format!("bdsq-blob-{}/blob_scan.obj", std::process::id()));
    std::fs::create_dir_all(scan.parent().unwrap()).unwrap();
    write_points(&scan, all.iter().filter(|p| p.dot(view) > 0.0));
    let added = add_file(app.world_mut(), root, &scan, PLACE, &dir).unwrap();
    let AddedFile::Part {
        name,
        points,
        parts: 1,
    } = added
    else {
        panic!("a scan made {added:?}");
    };
    assert_eq!(name, "blob_scan");
    // The scan lies outside the assets, so it was imported there (a scene names assets only).
    let imported = dir.join("imported/blob_scan.obj");
    assert_eq!(
        std::fs::read(&imported).unwrap(),
        std::fs::read(&scan).unwrap()
    );

    for _ in 0..50 {
        app.update();
    }
    assert_eq!(
        parts(&app, root).len(),
        5,
        "the chain's four links and the scan"
    );
    assert_eq!(
        joint_count(&mut app),
        3,
        "the joints were made anew, not doubled"
    );
    assert_eq!(*app.world().get::<Transform>(camera).unwrap(), user_view);

    // Placed from the points' moments: centroid at `at`, RMS radius `radius`.
    let e = named(&mut app, &name).expect("the scan's part");
    let pts = app
        .world()
        .get::<RangeData>(e)
        .unwrap()
        .forces
        .points()
        .to_vec();
    assert_eq!(pts.len(), points);
    let centroid = pts.iter().copied().sum::<DVec3>() / pts.len() as f64;
    let rms = (pts
        .iter()
        .map(|p| p.distance_squared(centroid))
        .sum::<f64>()
        / pts.len() as f64)
        .sqrt();
    assert!(centroid.distance(PLACE.at) < 1e-9, "{centroid}");
    assert!((rms - PLACE.radius).abs() < 1e-9, "{rms}");

    // Fitted to convergence with its local DOFs, onto the scan.
    for _ in 0..20_000 {
        let done = app.world().get::<FitDriver>(e).is_some_and(|d| d.is_done());
        if done {
            break;
        }
        app.world_mut().run_schedule(Step);
        std::thread::sleep(std::time::Duration::from_millis(1));
    }
    let driver = app.world().get::<FitDriver>(e).unwrap();
    assert!(driver.converged(), "{:?}", driver.error());
    let w = app.world();
    let (rigid, shape, local) = (
        *w.get::<RigidState>(e).unwrap(),
        *w.get::<GlobalShape>(e).unwrap(),
        w.get::<LocalDofs>(e).unwrap().clone(),
    );
    let tess = w.get::<FemMesh>(e).unwrap().get().unwrap().clone();
    let mut nodes = Vec::new();
    world_positions(&tess, &rigid, &shape, &local, &mut nodes);
    let r = residuals(&tess, &nodes, &pts);
    assert!(
        r.mean < 0.01 * bounding_diagonal(&pts),
        "mean distance {} of a diagonal of {}",
        r.mean,
        r.diagonal
    );
    assert!(local.displacement.iter().any(|d| d.length() > 0.0));

    // Saved and opened again: the same part, in the same state, on the same data.
    save_scene(
        app.world(),
        root,
        &dir.join("scenes/saved.dsq.ron"),
        &dir,
        true,
    )
    .unwrap();
    let mut again = scene_app(&dir);
    let root2 = load(&mut again, "scenes/saved.dsq.ron");
    assert_eq!(parts(&again, root2).len(), 5);
    assert_eq!(joint_count(&mut again), 3);
    let e2 = named(&mut again, &name).unwrap();
    let w2 = again.world();
    assert_eq!(*w2.get::<RigidState>(e2).unwrap(), rigid);
    assert_eq!(*w2.get::<GlobalShape>(e2).unwrap(), shape);
    assert_eq!(*w2.get::<LocalDofs>(e2).unwrap(), local);
    assert_eq!(w2.get::<RangeData>(e2).unwrap().forces.points(), &pts[..]);
    let _ = std::fs::remove_dir_all(&dir);
    let _ = std::fs::remove_dir_all(scan.parent().unwrap());
}

#[test]
fn an_image_added_to_a_scene_becomes_the_backdrop_facing_the_camera() {
    let (dir, mut app, camera, root) = chain_app("image");
    let coins = shipped_data("coins.png");
    let added = add_file(app.world_mut(), root, &coins, PLACE, &dir).unwrap();
    assert_eq!(
        added,
        AddedFile::Image {
            name: "coins".into(),
            size: (384, 303)
        }
    );
    for _ in 0..5 {
        app.update();
    }
    let mut images = app.world_mut().query::<&SceneImage>();
    let images: Vec<_> = images.iter(app.world()).collect();
    assert_eq!(images.len(), 1);
    assert_eq!(images[0].name, "coins");
    assert_eq!(parts(&app, root).len(), 4);
    // The camera looks straight down -z at the image's centre.
    let t = app.world().get::<Transform>(camera).unwrap();
    assert!(t.translation.abs_diff_eq(Vec3::new(2.0, 0.6, 4.8), 1e-5));
    assert!(t.forward().abs_diff_eq(Vec3::NEG_Z, 1e-5));
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_file_that_cannot_be_added_names_itself_and_changes_nothing() {
    let dir = assets_with_chain("bad");
    let mut app = scene_app(&dir);
    let root = load(&mut app, "scenes/chain.dsq.ron");
    let before = scene_def(&app, root);
    let scratch = std::env::temp_dir().join(format!("bdsq-add-{}-files", std::process::id()));
    std::fs::create_dir_all(&scratch).unwrap();
    let write = |name: &str, text: &str| {
        let p = scratch.join(name);
        std::fs::write(&p, text).unwrap();
        p
    };
    let cases = [
        (write("garbage.ply", "garbage\n"), "magic number"),
        (
            write("three.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\n"),
            "at least",
        ),
        (write("same.obj", &"v 1 2 3\n".repeat(20)), "coincide"),
        (write("notes.txt", "hello"), "not a point cloud"),
        (write("broken.png", "not a png"), "cannot decode"),
        (scratch.join("missing.ply"), "cannot read"),
    ];
    for (file, why) in &cases {
        let e = add_file(app.world_mut(), root, file, PLACE, &dir).unwrap_err();
        let name = file.file_name().unwrap().to_string_lossy();
        assert!(e.contains(&*name) && e.contains(why), "{e}");
        assert!(!e.contains('\n'), "one line: {e}");
    }
    for _ in 0..5 {
        app.update();
    }
    assert_eq!(scene_def(&app, root), before);
    assert_eq!(parts(&app, root).len(), 4);
    assert!(!dir.join("imported").exists(), "nothing was imported");
    let _ = std::fs::remove_dir_all(&dir);
    let _ = std::fs::remove_dir_all(&scratch);
}

/// Four clicks on an added image make a part of the scene pulled by that image, placed as the
/// clicks say; clicks that give an axis no length are refused and change nothing.
#[test]
fn a_part_placed_on_an_added_image_is_pulled_by_it() {
    let dir = assets_with_chain("placed");
    let mut app = scene_app(&dir);
    let root = load(&mut app, "scenes/chain.dsq.ron");
    add_file(
        app.world_mut(),
        root,
        &shipped_data("coins.png"),
        PLACE,
        &dir,
    )
    .unwrap();
    for _ in 0..5 {
        app.update();
    }
    // The first coin of the top row: centre (37, 54) px, radius about 21 px.
    let (major, minor) = ([[16.0, 54.0], [58.0, 54.0]], [[37.0, 33.0], [37.0, 75.0]]);
    let coin = |name: &str, major, minor| {
        let mut part = PartDef::new(name);
        part.placement = PartPlacement::Axes { major, minor };
        part.forces = Forces::image("coins");
        part.k = 15;
        part
    };
    let flat = coin("flat", [[37.0, 54.0]; 2], minor);
    let before = scene_def(&app, root);
    let e = add_part(app.world_mut(), root, flat, &dir).unwrap_err();
    assert!(e.contains("flat") && e.contains("cannot be placed"), "{e}");
    assert_eq!(scene_def(&app, root), before);

    add_part(app.world_mut(), root, coin("coin", major, minor), &dir).unwrap();
    for _ in 0..5 {
        app.update();
    }
    assert_eq!(parts(&app, root).len(), 5);
    let e = named(&mut app, "coin").expect("the placed part");
    assert!(
        app.world().get::<ImageData>(e).is_some(),
        "pulled by the image"
    );
    let mut images = app.world_mut().query::<&SceneImage>();
    let potential = images.single(app.world()).unwrap().potential.clone();
    let px = [major[0], major[1], minor[0], minor[1]].map(glam::DVec2::from_array);
    let (translation, ..) = PartAxes::from_points(&potential, px).unwrap().pose();
    let rigid = *app.world().get::<RigidState>(e).unwrap();
    assert!(rigid.translation.distance(translation) < 1e-12);
    // Pulled: it moves under the image's forces and stays finite.
    for _ in 0..20 {
        app.world_mut().run_schedule(Step);
    }
    let moved = *app.world().get::<RigidState>(e).unwrap();
    assert!(moved.translation.is_finite() && moved != rigid);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_dropped_object_of_two_parts_becomes_two_jointed_parts_sharing_its_points() {
    // Generated truth: a body and one limb (synthetic::union_cloud seed 200), written as an OBJ.
    let (dir, mut app, _camera, root) = chain_app("whole");
    let cloud = bevy_deformable_sq::synthetic::union_cloud(200, 2, 3000, 0.0, false);
    let file = dir.join("body_and_limb.obj");
    write_points(&file, &cloud.points);
    let added = add_file(app.world_mut(), root, &file, PLACE, &dir).unwrap();
    assert_eq!(
        added,
        AddedFile::Part {
            name: "body_and_limb 1".into(),
            points: cloud.points.len(),
            parts: 2,
        }
    );
    for _ in 0..50 {
        app.update();
    }
    assert_eq!(parts(&app, root).len(), 6, "the chain's four links and two");
    assert_eq!(
        joint_count(&mut app),
        4,
        "the chain's three and the new one"
    );
    let def = scene_def(&app, root);
    for name in ["body_and_limb 1", "body_and_limb 2"] {
        let part = def.parts.iter().find(|p| p.name == name).expect(name);
        assert!(
            matches!(&part.forces, Forces::Range { data, shared: true, .. } if data == "body_and_limb"),
            "{:?}",
            part.forces
        );
        assert!(matches!(part.placement, PartPlacement::Pose { .. }));
    }
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_file_added_in_the_background_joins_the_scene_when_its_split_is_done() {
    let (dir, mut app, _camera, root) = chain_app("background");
    let cloud = bevy_deformable_sq::synthetic::union_cloud(200, 2, 3000, 0.0, false);
    let file = dir.join("body_and_limb.obj");
    write_points(&file, &cloud.points);
    // A file that cannot be read is refused at once, and nothing starts.
    let missing = dir.join("missing.obj");
    let e = add_file_in_background(app.world_mut(), root, &missing, PLACE, &dir).unwrap_err();
    assert!(
        e.contains("missing.obj") && e.contains("cannot read"),
        "{e}"
    );

    let task = add_file_in_background(app.world_mut(), root, &file, PLACE, &dir).unwrap();
    // The call returns before the split: the scene is as it was, the task is there.
    assert!(app.world().get::<AddingFile>(task).is_some());
    assert_eq!(parts(&app, root).len(), 4);
    let mut added = Vec::new();
    let mut frames = 0;
    while added.is_empty() {
        app.update();
        frames += 1;
        let messages = app.world().resource::<Messages<FileAdded>>();
        added.extend(messages.iter_current_update_messages().cloned());
        assert!(frames < 100_000, "the split never ended");
        std::thread::sleep(std::time::Duration::from_millis(1));
    }
    assert_eq!(
        added,
        vec![FileAdded {
            root,
            file: file.clone(),
            result: Ok(AddedFile::Part {
                name: "body_and_limb 1".into(),
                points: cloud.points.len(),
                parts: 2,
            }),
        }]
    );
    assert!(app.world().get_entity(task).is_err(), "the task is gone");
    for _ in 0..50 {
        app.update();
    }
    assert_eq!(parts(&app, root).len(), 6, "the chain's four links and two");
    assert_eq!(joint_count(&mut app), 4);
    let _ = std::fs::remove_dir_all(&dir);
}
