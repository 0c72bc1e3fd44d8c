//! The physics-based modelling sandbox (the paper's Fig. 1 as an app): open a scene, pull models
//! with mouse springs, tune them in the inspector, place new parts and join them.
//!
//! `cargo run --release --example sandbox --features examples [-- SCENE] [--potential] [--wireframe] [--select PART] [--screenshot FILE [--exit-after-steps N]]`
//!
//! SCENE is a `.dsq.ron` file under `assets/` (default `scenes/sandbox.dsq.ron`); `--potential`
//! and `--wireframe` start with those display toggles on; `--select` opens the inspector on the
//! part of that name. `DeformableSqPlugins` does the work (simulation, meshes, scene files, mouse
//! springs, inspector); this example adds the scene list, placing and joining parts, and keys.
use bevy::diagnostic::{DiagnosticsStore, FrameTimeDiagnosticsPlugin};
use bevy::ecs::schedule::ScheduleLabel;
use bevy::pbr::wireframe::{Wireframe, WireframePlugin};
use bevy::picking::events::{Pointer, Press};
use bevy::picking::pointer::PointerButton;
use bevy::prelude::*;
use bevy_deformable_sq::model::image_fit::ellipsoid_from_points;
use bevy_deformable_sq::model::joint::JointEnd;
use bevy_deformable_sq::plugin::scene::{
    AddedFile, AddingFile, FileAdded, FilePlacement, add_file_in_background, add_part, save_scene,
};
use bevy_deformable_sq::plugin::world_positions;
use bevy_deformable_sq::prelude::*;
use bevy_deformable_sq::scene::{Forces, PartDef, PartPlacement};
use bevy_egui::input::EguiWantsInput;
use bevy_egui::{EguiContexts, EguiPrimaryContextPass, egui};
use glam::DVec3;
use std::path::Path;

/// The schedule one simulation step runs in; the sandbox runs it `steps_per_frame` times a frame.
#[derive(ScheduleLabel, Clone, Debug, PartialEq, Eq, Hash)]
struct SimStep;

/// The sandbox's own state (the inspector keeps the selection and the message line).
#[derive(Resource, Default)]
struct Sandbox {
    scene: String,
    scenes: std::collections::BTreeSet<String>,
    root: Option<Entity>,
    steps_per_frame: u32,
    running: bool,
    step_once: bool,
    show_images: bool,
    show_potential: bool,
    wireframe: bool,
    /// Points picked so far while placing a new part (`None`: not placing).
    placing: Option<Vec<Vec3>>,
    /// The ends picked so far while making a joint (`None`: not joining).
    joining: Option<Vec<(Entity, JointEnd)>>,
}

fn main() -> AppExit {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let flag = |name: &str| args.iter().any(|a| a == name);
    let scene = args
        .iter()
        .find(|a| a.ends_with(".dsq.ron"))
        .cloned()
        .unwrap_or_else(|| "scenes/sandbox.dsq.ron".into());
    let dir = screenshot::assets_dir().0.join("scenes");
    let scenes = (std::fs::read_dir(dir).into_iter().flatten().flatten())
        .map(|e| format!("scenes/{}", e.file_name().display()))
        .filter(|n| n.ends_with(".dsq.ron"))
        .collect();
    let mut app = App::new();
    app.add_plugins((
        screenshot::default_plugins(),
        WireframePlugin::default(),
        FrameTimeDiagnosticsPlugin::default(),
        DeformableSqPlugins::in_schedule(SimStep),
        orbit::OrbitCameraPlugin,
    ))
    .insert_resource(Sandbox {
        scenes,
        steps_per_frame: 2,
        running: true,
        show_images: true,
        show_potential: flag("--potential"),
        wireframe: flag("--wireframe"),
        ..default()
    })
    .insert_resource(InspectorState {
        select_name: args
            .iter()
            .position(|a| a == "--select")
            .and_then(|i| args.get(i + 1).cloned()),
        ..default()
    })
    .init_schedule(SimStep)
    .add_systems(Startup, move |w: &mut World| open_scene(w, &scene))
    .add_systems(
        Update,
        (
            keys.before(MouseSpringSystems),
            (drop_files, show_added).chain(),
            (place_part, run_simulation, apply_display).after(MouseSpringSystems),
        ),
    )
    .add_systems(EguiPrimaryContextPass, toolbar)
    .add_observer(pick_joint_end);
    demo_drag::maybe_add(&mut app, &args);
    demo_drop::maybe_add(&mut app, &args);
    screenshot::maybe_add(&mut app);
    app.run()
}

/// Replaces the open scene by the scene file at `path` (under `assets/`).
fn open_scene(world: &mut World, path: &str) {
    if let Some(old) = world.resource_mut::<Sandbox>().root.take() {
        world.despawn(old);
    }
    let handle = world.resource::<AssetServer>().load(path.to_string());
    let root = world.spawn(DeformableSceneRoot(handle)).id();
    let mut s = world.resource_mut::<Sandbox>();
    s.root = Some(root);
    s.scene = path.to_string();
    world.resource_mut::<InspectorState>().message = format!("opened {path}");
}

/// Saves the open scene, with the parts as they are now, beside it as `NAME_saved.dsq.ron`.
fn save_open_scene(world: &mut World) {
    let assets = screenshot::assets_dir().0;
    let s = world.resource::<Sandbox>();
    let name = s.scene.replace(".dsq.ron", "_saved.dsq.ron");
    let out = assets.join(name.replace("_saved_saved", "_saved"));
    let Some(root) = s.root else {
        return;
    };
    let message = match save_scene(world, root, &out, &assets, true) {
        Ok(()) => format!("saved {}", out.display()),
        Err(e) => format!("save failed: {e}"),
    };
    world.resource_mut::<InspectorState>().message = message;
}

/// Files dropped on the window join the open scene (`add_file_in_background`): a scan as
/// parts fitted to it, in front of what the camera looks at and clear of the other parts; an
/// image as the backdrop, with a new part's four clicks begun. The split into parts runs off the
/// frame ([`show_added`] says how it goes). A file it cannot take says why in the message line,
/// and the scene stays as it was.
fn drop_files(mut drops: MessageReader<FileDragAndDrop>, mut commands: Commands) {
    for drop in drops.read() {
        if let FileDragAndDrop::DroppedFile { path_buf, .. } = drop {
            let file = path_buf.clone();
            commands.queue(move |w: &mut World| add_dropped(w, &file));
        }
    }
}

/// Starts adding one dropped file to the open scene, or says why it cannot.
fn add_dropped(world: &mut World, file: &Path) {
    let Some(root) = world.resource::<Sandbox>().root else {
        return;
    };
    let target = world.resource::<orbit::Orbit>().target.as_dvec3();
    let placement = FilePlacement {
        at: free_spot(world, root, target),
        radius: DROPPED_RADIUS,
        extent: DROPPED_EXTENT,
    };
    let assets = screenshot::assets_dir().0;
    if let Err(e) = add_file_in_background(world, root, file, placement, &assets) {
        world.resource_mut::<InspectorState>().message = format!("not added: {e}");
    }
}

/// The message line while dropped files are split into parts (their names and the seconds so
/// far), and what came of each when it has joined the scene.
fn show_added(
    adding: Query<&AddingFile>,
    mut added: MessageReader<FileAdded>,
    mut sandbox: ResMut<Sandbox>,
    mut inspector: ResMut<InspectorState>,
) {
    for FileAdded { result, .. } in added.read() {
        inspector.message = match result {
            Ok(AddedFile::Part {
                name,
                points,
                parts,
            }) => {
                inspector.select_name = Some(name.clone());
                if *parts == 1 {
                    format!("added {name}: {points} points, placed from their moments and fitted")
                } else {
                    format!(
                        "added {name}: {points} points split into {parts} jointed parts, fitted"
                    )
                }
            }
            Ok(AddedFile::Image { name, size }) => {
                sandbox.show_images = true;
                let mut how = InspectorState::default();
                begin(&mut sandbox, &mut how, false);
                format!(
                    "added {name} ({} x {} px) as the backdrop. {}",
                    size.0, size.1, how.message
                )
            }
            Err(e) => format!("not added: {e}"),
        };
    }
    let running: Vec<String> = adding
        .iter()
        .map(|a| {
            let name = a.file().file_name().unwrap_or_default().display();
            format!("{name} ({:.1} s)", a.elapsed().as_secs_f64())
        })
        .collect();
    if !running.is_empty() {
        inspector.message = format!("splitting into parts: {}", running.join(", "));
    }
}

/// The RMS radius a dropped scan is scaled to. The default scene's models have RMS radii of
/// 0.45–0.6; a scan is often long and thin (the cow's longest semi-axis is 2.7 times its RMS
/// radius), and at 0.35 such a scan's long axis stays under 1, within the 1.5 between parts.
const DROPPED_RADIUS: f64 = 0.35;

/// The world length of a dropped image's longer side: the width of the default scene's row of
/// models.
const DROPPED_EXTENT: f64 = 6.0;

/// Where a dropped scan goes: the point of a 1.5-unit grid on the models' height (y = 0.6)
/// nearest to 1.5 in front of `target`, at least 1.4 from every part (the default scene's
/// spacing, less a margin).
fn free_spot(world: &mut World, root: Entity, target: DVec3) -> DVec3 {
    let parts: Vec<DVec3> = world
        .query::<(&RigidState, &ChildOf)>()
        .iter(world)
        .filter(|(_, c)| c.parent() == root)
        .map(|(r, _)| r.translation)
        .collect();
    let want = DVec3::new(target.x, 0.6, target.z + 1.5);
    let grid = (-8..=8).flat_map(|i| (-8..=8).map(move |j| (i, j)));
    grid.map(|(i, j)| want + 1.5 * DVec3::new(i as f64, 0.0, j as f64))
        .filter(|c| parts.iter().all(|p| p.distance(*c) >= 1.4))
        .min_by(|a, b| a.distance(want).total_cmp(&b.distance(want)))
        .unwrap_or(want)
}

/// Starts placing a new part, or making a joint, and shows how.
fn begin(sandbox: &mut Sandbox, inspector: &mut InspectorState, joint: bool) {
    sandbox.placing = (!joint).then(Vec::new);
    sandbox.joining = joint.then(Vec::new);
    inspector.message = if joint {
        "New joint: click a point on one part, then a point on another. Esc cancels."
    } else {
        "New part: click both ends of its major axis, then both ends of its minor axis, on the \
         ground (y = 0), or on the image plane (z = 0) when the scene has an image. Esc cancels."
    }
    .into();
}

/// Keyboard shortcuts (ignored while egui has the keyboard); the mouse springs and the orbit's
/// left button are off while the left button places a part or picks a joint's end.
fn keys(
    input: Res<ButtonInput<KeyCode>>,
    egui: Res<EguiWantsInput>,
    mut sandbox: ResMut<Sandbox>,
    mut inspector: ResMut<InspectorState>,
    mut springs: ResMut<MouseSpringSettings>,
    mut orbit: ResMut<orbit::Orbit>,
    mut controls: Query<(
        &mut SimControl,
        &ModelSettings,
        Has<RangeData>,
        Has<ImageData>,
    )>,
    mut commands: Commands,
) {
    if !egui.wants_any_keyboard_input() {
        let pressed = |k| input.just_pressed(k);
        if pressed(KeyCode::Space) {
            sandbox.running = !sandbox.running;
        }
        if pressed(KeyCode::KeyS) {
            (sandbox.running, sandbox.step_once) = (false, true);
        }
        if pressed(KeyCode::KeyN) || pressed(KeyCode::KeyJ) {
            begin(&mut sandbox, &mut inspector, pressed(KeyCode::KeyJ));
        }
        if pressed(KeyCode::Escape) {
            (sandbox.placing, sandbox.joining) = (None, None);
        }
        if let Some(e) = inspector.selected
            && let Ok((mut control, settings, range, image)) = controls.get_mut(e)
        {
            control.reset_requested |= pressed(KeyCode::KeyR);
            if (range || image) && pressed(KeyCode::KeyF) {
                commands.entity(e).insert(FitDriver::for_model(settings));
            }
        }
    }
    let picking = sandbox.placing.is_some() || sandbox.joining.is_some();
    springs.enabled = !picking;
    orbit.left_button = !picking;
}

/// Making a joint: each click on a model while joining picks the node nearest the hit as one
/// end; the second end, on another model, makes the [`PartJoint`] (a child of the scene, so
/// saving the scene keeps it).
fn pick_joint_end(
    press: On<Pointer<Press>>,
    mut sandbox: ResMut<Sandbox>,
    mut inspector: ResMut<InspectorState>,
    models: Query<(&FemMesh, &RigidState, &GlobalShape, &LocalDofs)>,
    mut commands: Commands,
) {
    let (entity, primary) = (press.entity, press.button == PointerButton::Primary);
    let (Some(ends), Ok((fem, rigid, shape, local)), true) =
        (sandbox.joining.as_mut(), models.get(entity), primary)
    else {
        return;
    };
    let (Some(tess), Some(hit)) = (fem.get(), press.hit.position) else {
        return;
    };
    let mut nodes = Vec::new();
    world_positions(tess, rigid, shape, local, &mut nodes);
    let Some(end) = JointEnd::nearest(tess, &nodes, hit.as_dvec3()) else {
        return;
    };
    if ends.first().is_some_and(|(e, _)| *e == entity) {
        inspector.message = "New joint: the second end must be on another part.".into();
        return;
    }
    ends.push((entity, end));
    if let [(a, end_a), (b, end_b)] = ends[..] {
        let mut joint = commands.spawn((Name::new("joint"), PartJoint::new(a, end_a, b, end_b)));
        if let Some(root) = sandbox.root {
            joint.insert(ChildOf(root));
        }
        sandbox.joining = None;
        inspector.message = "Joint made: drag either part and the other follows.".into();
    }
}

/// Placing a new part as the paper's user does (Fig. 6(a)): four clicks on the ground plane, or
/// on the image plane when the scene has an image, give both ends of the major axis and of the
/// minor axis. On the ground the part (an ellipsoid, no data) is spawned under the scene root; on
/// an image it joins the scene ([`add_part`]) placed by the clicks in the image's pixels and
/// pulled by the image, so it fits the outline it was placed on and saves with the scene.
fn place_part(
    mut sandbox: ResMut<Sandbox>,
    mut inspector: ResMut<InspectorState>,
    buttons: Res<ButtonInput<MouseButton>>,
    egui: Res<EguiWantsInput>,
    window: Single<&Window>,
    camera: Single<(&Camera, &GlobalTransform)>,
    images: Query<&SceneImage>,
    mut instances: Query<&mut SceneInstance>,
    mut gizmos: Gizmos,
    mut commands: Commands,
) {
    let normal = if images.is_empty() { Vec3::Y } else { Vec3::Z };
    let root = sandbox.root;
    let Some(points) = sandbox.placing.as_mut() else {
        return;
    };
    for (i, p) in points.iter().enumerate() {
        let colour = [Color::srgb(1.0, 0.3, 0.3), Color::srgb(0.3, 0.6, 1.0)][i / 2];
        gizmos.sphere(Isometry3d::from_translation(*p), 0.04, colour);
    }
    if !buttons.just_pressed(MouseButton::Left) || egui.wants_any_pointer_input() {
        return;
    }
    let (camera, cam_tf) = *camera;
    let at = |c| camera.viewport_to_world(cam_tf, c).ok();
    let ray = window.cursor_position().and_then(at);
    let plane = InfinitePlane3d::new(normal);
    let Some((ray, t)) = ray.and_then(|r| Some((r, r.intersect_plane(Vec3::ZERO, plane)?))) else {
        return;
    };
    points.push(ray.get_point(t));
    if points.len() < 4 {
        return;
    }
    let p: [DVec3; 4] = std::array::from_fn(|i| points[i].as_dvec3());
    sandbox.placing = None;
    let Some((translation, rotation, shape)) = ellipsoid_from_points(p, normal.as_dvec3()) else {
        inspector.message = "both axes need a length: the part was not placed".into();
        return;
    };
    let Some(mut instance) = root.and_then(|r| instances.get_mut(r).ok()) else {
        return;
    };
    let name = format!("part {}", instance.parts.len() + 1);
    // On an image, the part is the scene's, pulled by the image (the paper's Fig. 6(a)).
    if let Some(image) = images.iter().next() {
        let px = p.map(|x| image.potential.to_pixel(x.truncate()).to_array());
        let mut part = PartDef::new(name.clone());
        part.placement = PartPlacement::Axes {
            major: [px[0], px[1]],
            minor: [px[2], px[3]],
        };
        part.forces = Forces::image(image.name.clone());
        part.k = 31;
        let root = root.expect("the instance is the root's");
        commands.queue(move |w: &mut World| {
            let assets = screenshot::assets_dir().0;
            let message = match add_part(w, root, part, &assets) {
                Ok(()) => format!("placed {name} on the image; it is pulled to its edges"),
                Err(e) => format!("not placed: {e}"),
            };
            w.resource_mut::<InspectorState>().message = message;
            w.resource_mut::<InspectorState>().select_name = Some(name);
        });
        return;
    }
    let e = commands
        .spawn((
            Name::new(name.clone()),
            GlobalShape::from(shape),
            RigidState {
                translation,
                rotation,
            },
            FemMesh::new(31),
            ChildOf(root.expect("the instance is the root's")),
        ))
        .id();
    instance.parts.push(e);
    inspector.selected = Some(e);
    inspector.message = format!("placed {name}");
}

/// Runs `steps_per_frame` simulation steps while running, or the one step asked for.
fn run_simulation(world: &mut World) {
    let mut s = world.resource_mut::<Sandbox>();
    let steps = match s.running {
        true => s.steps_per_frame,
        false => std::mem::take(&mut s.step_once) as u32,
    };
    for _ in 0..steps {
        world.run_schedule(SimStep);
    }
}

/// Parts and images take the display toggles when one changes and when a scene spawns them.
fn apply_display(
    sandbox: Res<Sandbox>,
    mut applied: Local<Option<[bool; 3]>>,
    new_parts: Query<(), Added<ScenePart>>,
    parts: Query<Entity, With<ScenePart>>,
    mut images: Query<(&mut SceneImage, &mut Visibility)>,
    mut commands: Commands,
) {
    let now = [
        sandbox.wireframe,
        sandbox.show_images,
        sandbox.show_potential,
    ];
    // (Reading `is_added` through `iter_mut` marks nothing changed.)
    let new = !new_parts.is_empty() || images.iter_mut().any(|(image, _)| image.is_added());
    if *applied == Some(now) && !new {
        return;
    }
    *applied = Some(now);
    for e in &parts {
        match now[0] {
            true => commands.entity(e).insert(Wireframe),
            false => commands.entity(e).remove::<Wireframe>(),
        };
    }
    for (mut image, mut visibility) in &mut images {
        image.show_potential = now[2];
        *visibility = [Visibility::Hidden, Visibility::Inherited][now[1] as usize];
    }
}

/// The toolbar at the bottom right: the scene, new parts and joints, running, the display.
fn toolbar(
    mut contexts: EguiContexts,
    mut sandbox: ResMut<Sandbox>,
    mut inspector: ResMut<InspectorState>,
    diagnostics: Res<DiagnosticsStore>,
    mut commands: Commands,
) -> Result {
    let ctx = contexts.ctx_mut()?;
    let s = &mut *sandbox;
    let frame_ms = diagnostics
        .get(&FrameTimeDiagnosticsPlugin::FRAME_TIME)
        .and_then(|d| d.smoothed())
        .unwrap_or(0.0);
    let window = egui::Window::new("Sandbox")
        .title_bar(false)
        .min_width(880.0);
    let window = window.anchor(egui::Align2::RIGHT_BOTTOM, [-10.0, -10.0]);
    window.resizable(false).show(ctx, |ui| {
        ui.horizontal_wrapped(|ui| {
            egui::ComboBox::from_id_salt("scene")
                .selected_text(s.scene.clone())
                .show_ui(ui, |ui| {
                    for scene in &s.scenes {
                        if ui.selectable_label(*scene == s.scene, scene).clicked() {
                            let scene = scene.clone();
                            commands.queue(move |w: &mut World| open_scene(w, &scene));
                        }
                    }
                });
            if ui.button("Save scene").clicked() {
                commands.queue(save_open_scene);
            }
            if ui.button("New part (4 clicks)").clicked() {
                begin(s, &mut inspector, false);
            }
            if ui.button("New joint (2 clicks)").clicked() {
                begin(s, &mut inspector, true);
            }
            if ui.button(if s.running { "Pause" } else { "Run" }).clicked() {
                s.running = !s.running;
            }
            if ui.button("Step").clicked() {
                (s.running, s.step_once) = (false, true);
            }
            ui.add(egui::Slider::new(&mut s.steps_per_frame, 1..=20).text("steps/frame"));
            ui.checkbox(&mut s.wireframe, "wireframe");
            ui.checkbox(&mut s.show_images, "image");
            ui.checkbox(&mut s.show_potential, "potential P");
            ui.label(format!("frame {frame_ms:.1} ms"))
                .on_hover_text(CHEAT_SHEET);
        });
        // What the overlays are (DeformableSqDebugPlugin's colours).
        ui.horizontal_wrapped(|ui| {
            let legend = [
                ("• data points", egui::Color32::from_rgb(242, 242, 51)),
                ("— data springs", egui::Color32::from_rgb(200, 200, 200)),
                ("— mouse spring", egui::Color32::from_rgb(255, 51, 51)),
                ("— joints", egui::Color32::from_rgb(51, 230, 230)),
            ];
            for (text, colour) in legend {
                ui.label(egui::RichText::new(text).color(colour));
            }
            ui.label("· drag a model to move it, Shift + drag to reshape it; hover the frame time for all keys");
        });
    });
    Ok(())
}

/// The mouse and keys, also in docs/sandbox.md; shown over the toolbar's frame time.
const CHEAT_SHEET: &str = "Left drag on a model: grab it (moves and dents it, its shape held)
Shift + left drag on a model: the paper's pull (its global shape gives way too)
Left / right drag on empty space: orbit; middle drag or Shift + right drag: pan
Wheel or + / -: zoom; arrows: orbit; Home: reset view
Space: pause / run; S: single step; R: reset the selected part; F: fit it to convergence
N: new part from four clicks (major axis ends, minor axis ends); J: new joint; Esc: cancel";

#[path = "support/demo_drag.rs"]
mod demo_drag;
#[path = "support/demo_drop.rs"]
mod demo_drop;
#[path = "support/orbit.rs"]
mod orbit;
#[path = "support/screenshot.rs"]
mod screenshot;
