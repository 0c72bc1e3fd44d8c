//! The physics-based modelling sandbox (the paper's Fig. 1 as an app): open a scene, pull models
//! with mouse springs, tune them in an egui inspector, and watch fits converge.
//!
//! `cargo run --release --example sandbox [-- SCENE] [--potential] [--wireframe] [--select PART] [--screenshot FILE [--exit-after-steps N]]`
//!
//! SCENE is a `.dsq.ron` file under `assets/` (default `scenes/sandbox.dsq.ron`); `--potential`
//! and `--wireframe` start with those display toggles on; `--select` opens the inspector on the
//! part of that name. Mouse: drag a
//! model with the left button to pull it by a spring (drawn in red); drag empty space with the
//! left or right button to orbit, with the middle button (or Shift + right) to pan; the wheel
//! zooms. Keys: Space pause / run, S single step, R reset the selected part, F fit the selected
//! part to convergence, Tab next part, N place a new part with four clicks, J join two parts
//! with two clicks, arrows orbit, +/-
//! zoom, Home frame the scene.
use bevy::diagnostic::{DiagnosticsStore, FrameTimeDiagnosticsPlugin};
use bevy::ecs::schedule::ScheduleLabel;
use bevy::input::mouse::{AccumulatedMouseMotion, AccumulatedMouseScroll};
use bevy::pbr::wireframe::{Wireframe, WireframePlugin};
use bevy::picking::mesh_picking::MeshPickingPlugin;
use bevy::prelude::*;
use bevy_deformable_sq::io::write_model_obj;
use bevy_deformable_sq::model::deform::{MAX_BEND, MAX_TAPER};
use bevy_deformable_sq::model::dynamics::ModelState;
use bevy_deformable_sq::model::fit::{FitOptions, Stage, residuals};
use bevy_deformable_sq::model::image_fit::ellipsoid_from_points;
use bevy_deformable_sq::model::joint::JointEnd;
use bevy_deformable_sq::model::superquadric::{LEAST_EPSILON, MAX_EPSILON};
use bevy_deformable_sq::plugin::scene::save_scene;
use bevy_deformable_sq::plugin::{FitDriver, Scratch};
use bevy_deformable_sq::prelude::*;
use bevy_egui::input::EguiWantsInput;
use bevy_egui::{EguiContexts, EguiPlugin, EguiPrimaryContextPass, egui};
use glam::DVec3;
use std::collections::VecDeque;

/// The schedule one simulation step runs in; the sandbox runs it `steps_per_frame` times a frame.
#[derive(ScheduleLabel, Clone, Debug, PartialEq, Eq, Hash)]
struct SimStep;

/// Everything the inspector edits that is not a component.
#[derive(Resource)]
struct Sandbox {
    scene: String,
    scenes: Vec<String>,
    steps_per_frame: u32,
    running: bool,
    single_steps: u32,
    selected: Option<Entity>,
    data_forces: bool,
    show_images: bool,
    show_potential: bool,
    wireframe: bool,
    message: String,
    residual: VecDeque<f32>,
    sim_steps: u64,
    pending: Option<Action>,
    root: Option<Entity>,
    /// Points picked so far while placing a new part (`None`: not placing).
    placing: Option<Vec<Vec3>>,
    /// The ends picked so far while making a joint (`None`: not joining).
    joining: Option<Vec<(Entity, JointEnd)>>,
    /// The part `--demo-drag` drags (`--demo-part NAME`, default the cylinder).
    demo_part: String,
    /// The part to select once it appears (`--select NAME`).
    select: Option<String>,
}

/// Work the inspector asks for that needs the whole world.
#[derive(Clone, Debug)]
enum Action {
    Open(String),
    SaveScene,
    ExportObj,
    Fit(Entity),
}

/// The camera's orbit about a target.
#[derive(Resource)]
struct Orbit {
    target: Vec3,
    yaw: f32,
    pitch: f32,
    distance: f32,
}

fn main() -> AppExit {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let scene = args
        .iter()
        .find(|a| a.ends_with(".dsq.ron"))
        .cloned()
        .unwrap_or_else(|| "scenes/sandbox.dsq.ron".into());
    let mut scenes: Vec<String> = std::fs::read_dir(screenshot::assets_dir().0.join("scenes"))
        .map(|d| {
            d.filter_map(|e| e.ok())
                .map(|e| format!("scenes/{}", e.file_name().to_string_lossy()))
                .filter(|n| n.ends_with(".dsq.ron"))
                .collect()
        })
        .unwrap_or_default();
    scenes.sort();
    let mut app = App::new();
    app.add_plugins((
        screenshot::default_plugins(),
        MeshPickingPlugin,
        WireframePlugin::default(),
        FrameTimeDiagnosticsPlugin::default(),
        EguiPlugin::default(),
        DeformableSqPlugins::in_schedule(SimStep),
        MouseSpringPlugin,
    ))
    .insert_resource(Sandbox {
        scene: scene.clone(),
        scenes,
        steps_per_frame: 2,
        running: true,
        single_steps: 0,
        selected: None,
        data_forces: true,
        show_images: true,
        show_potential: args.iter().any(|a| a == "--potential"),
        wireframe: args.iter().any(|a| a == "--wireframe"),
        message: String::new(),
        residual: VecDeque::new(),
        sim_steps: 0,
        pending: Some(Action::Open(scene)),
        root: None,
        placing: None,
        joining: None,
        demo_part: args
            .iter()
            .position(|a| a == "--demo-part")
            .and_then(|i| args.get(i + 1).cloned())
            .unwrap_or_else(|| "cylinder".into()),
        select: args
            .iter()
            .position(|a| a == "--select")
            .and_then(|i| args.get(i + 1).cloned()),
    })
    .insert_resource(Orbit {
        target: Vec3::new(0.0, 0.5, 0.0),
        yaw: 0.0,
        pitch: 0.35,
        distance: 7.0,
    })
    .init_schedule(SimStep)
    .add_systems(Startup, setup)
    .add_systems(
        Update,
        (
            (actions, keys, orbit_camera, sync_mouse_spring)
                .chain()
                .before(MouseSpringSystems),
            (place_part, run_simulation, track_residual, apply_display)
                .chain()
                .after(MouseSpringSystems),
        ),
    )
    .add_systems(EguiPrimaryContextPass, inspector)
    .add_observer(pick_joint_end);
    if args.iter().any(|a| a == "--demo-drag") {
        app.add_systems(Update, demo_drag.before(MouseSpringSystems));
    }
    screenshot::maybe_add(&mut app);
    app.run()
}

fn setup(mut commands: Commands) {
    commands.spawn((
        Camera3d::default(),
        DeformableSceneCamera,
        Transform::default(),
    ));
    commands.spawn((
        DirectionalLight {
            shadow_maps_enabled: true,
            illuminance: 8000.0,
            ..default()
        },
        Transform::from_xyz(3.0, 8.0, 5.0).looking_at(Vec3::ZERO, Vec3::Y),
    ));
    commands.insert_resource(GlobalAmbientLight {
        brightness: 300.0,
        ..default()
    });
}

/// Opens scenes, saves them and exports meshes (needs the whole world).
fn actions(world: &mut World) {
    let Some(action) = world.resource_mut::<Sandbox>().pending.take() else {
        return;
    };
    let message = match action {
        Action::Open(path) => {
            if let Some(old) = world.resource::<Sandbox>().root {
                world.despawn(old);
            }
            let handle = world.resource::<AssetServer>().load(path.clone());
            let root = world.spawn(DeformableSceneRoot(handle)).id();
            let mut s = world.resource_mut::<Sandbox>();
            s.root = Some(root);
            s.selected = None;
            s.residual.clear();
            s.scene = path.clone();
            format!("opened {path}")
        }
        Action::SaveScene => {
            let s = world.resource::<Sandbox>();
            let out = screenshot::assets_dir().0.join(
                s.scene
                    .replace(".dsq.ron", "_saved.dsq.ron")
                    .replace("_saved_saved", "_saved"),
            );
            match s.root {
                Some(root) => {
                    match save_scene(world, root, &out, &screenshot::assets_dir().0, true) {
                        Ok(()) => format!("saved {}", out.display()),
                        Err(e) => format!("save failed: {e}"),
                    }
                }
                None => "no scene to save".into(),
            }
        }
        Action::ExportObj => export_selected(world),
        Action::Fit(part) => fit_to_convergence(world, part),
    };
    world.resource_mut::<Sandbox>().message = message;
}

/// Writes the selected part as an OBJ mesh and its parameters as JSON next to the working
/// directory.
fn export_selected(world: &mut World) -> String {
    let Some(e) = world.resource::<Sandbox>().selected else {
        return "select a part to export".into();
    };
    let (Some(fem), Some(r), Some(s), Some(l)) = (
        world.get::<FemMesh>(e),
        world.get::<RigidState>(e),
        world.get::<GlobalShape>(e),
        world.get::<LocalDofs>(e),
    ) else {
        return "the part is gone".into();
    };
    let Some(tess) = fem.get() else {
        return "the part has no mesh yet".into();
    };
    let state = ModelState {
        translation: r.translation,
        rotation: r.rotation,
        shape: (*s).into(),
        deformation: s.deformation(),
        displacement: l.displacement.clone(),
    };
    let name = world
        .get::<Name>(e)
        .map(|n| n.as_str().replace(' ', "_"))
        .unwrap_or_else(|| "part".into());
    let (obj, json) = (format!("{name}.obj"), format!("{name}.json"));
    let params = serde_json::json!({
        "translation": state.translation.to_array(),
        "rotation_xyzw": state.rotation.to_array(),
        "shape": state.shape,
        "nodes": tess.node_count(),
    });
    match write_model_obj(obj.as_ref(), tess, &state)
        .map_err(|e| e.to_string())
        .and_then(|()| {
            std::fs::write(&json, params.to_string()).map_err(|e| format!("{json}: {e}"))
        }) {
        Ok(()) => format!("wrote {obj} and {json}"),
        Err(e) => format!("export failed: {e}"),
    }
}

/// Keyboard shortcuts (ignored while egui has the keyboard).
fn keys(
    input: Res<ButtonInput<KeyCode>>,
    egui: Res<EguiWantsInput>,
    mut sandbox: ResMut<Sandbox>,
    mut orbit: ResMut<Orbit>,
    mut controls: Query<&mut SimControl>,
    instances: Query<&SceneInstance>,
) {
    if egui.wants_any_keyboard_input() {
        return;
    }
    if input.just_pressed(KeyCode::Space) {
        sandbox.running = !sandbox.running;
    }
    if input.just_pressed(KeyCode::KeyS) {
        sandbox.running = false;
        sandbox.single_steps += 1;
    }
    if input.just_pressed(KeyCode::KeyN) {
        sandbox.placing = Some(Vec::new());
        sandbox.message = PLACING_HELP.into();
    }
    if input.just_pressed(KeyCode::KeyJ) {
        sandbox.joining = Some(Vec::new());
        sandbox.message = JOINING_HELP.into();
    }
    if input.just_pressed(KeyCode::Escape) {
        sandbox.placing = None;
        sandbox.joining = None;
    }
    if input.just_pressed(KeyCode::Tab) {
        let parts: Vec<Entity> = instances.iter().flat_map(|i| i.parts.clone()).collect();
        let next = match sandbox
            .selected
            .and_then(|s| parts.iter().position(|p| *p == s))
        {
            Some(i) => parts.get((i + 1) % parts.len()).copied(),
            None => parts.first().copied(),
        };
        sandbox.selected = next;
        sandbox.residual.clear();
    }
    if let Some(sel) = sandbox.selected {
        if input.just_pressed(KeyCode::KeyR)
            && let Ok(mut c) = controls.get_mut(sel)
        {
            c.reset_requested = true;
        }
        if input.just_pressed(KeyCode::KeyF) {
            sandbox.pending = Some(Action::Fit(sel));
        }
    }
    let step = 0.03;
    if input.pressed(KeyCode::ArrowLeft) {
        orbit.yaw -= step;
    }
    if input.pressed(KeyCode::ArrowRight) {
        orbit.yaw += step;
    }
    if input.pressed(KeyCode::ArrowUp) {
        orbit.pitch = (orbit.pitch + step).min(1.5);
    }
    if input.pressed(KeyCode::ArrowDown) {
        orbit.pitch = (orbit.pitch - step).max(-1.5);
    }
    if input.pressed(KeyCode::Equal) || input.pressed(KeyCode::NumpadAdd) {
        orbit.distance = (orbit.distance * 0.97).max(0.2);
    }
    if input.pressed(KeyCode::Minus) || input.pressed(KeyCode::NumpadSubtract) {
        orbit.distance = (orbit.distance / 0.97).min(200.0);
    }
    if input.just_pressed(KeyCode::Home) {
        *orbit = Orbit {
            target: Vec3::new(0.0, 0.5, 0.0),
            yaw: 0.0,
            pitch: 0.35,
            distance: 7.0,
        };
    }
}

/// Gives a range part a [`FitDriver`] that runs the fitter's stages to rest, and unpauses it.
fn fit_to_convergence(world: &mut World, part: Entity) -> String {
    if world.get::<RangeData>(part).is_none() {
        return "only parts with range data are fitted to convergence".into();
    }
    let options = FitOptions::default();
    world.entity_mut(part).insert(FitDriver::new(
        options,
        [Stage::Cover, Stage::Global, Stage::Joint],
        options.max_steps as u64,
    ));
    if let Some(mut c) = world.get_mut::<SimControl>(part) {
        c.paused = false;
    }
    "fitting to convergence".into()
}

/// Places the camera from the orbit; mouse drags on empty space orbit and pan, the wheel zooms.
/// A scene's camera (placed on spawn) is taken over as the orbit's start.
fn orbit_camera(
    mut orbit: ResMut<Orbit>,
    buttons: Res<ButtonInput<MouseButton>>,
    keys: Res<ButtonInput<KeyCode>>,
    motion: Res<AccumulatedMouseMotion>,
    scroll: Res<AccumulatedMouseScroll>,
    egui: Res<EguiWantsInput>,
    mouse: Res<MouseSpring>,
    sandbox: Res<Sandbox>,
    mut camera: Single<&mut Transform, With<Camera3d>>,
    placed: Query<&SceneInstance, Changed<SceneInstance>>,
) {
    if !placed.is_empty() {
        // The scene moved the camera: orbit about what it looks at from there.
        let forward = camera.forward();
        let eye = camera.translation;
        let distance = (eye - orbit.target).length().max(0.5);
        orbit.target = eye + forward * distance;
        orbit.distance = distance;
        orbit.pitch = (-forward.y).asin();
        orbit.yaw = (-forward.x).atan2(-forward.z);
    }
    if !egui.wants_any_pointer_input() && mouse.model.is_none() {
        let d = motion.delta;
        let shift = keys.pressed(KeyCode::ShiftLeft) || keys.pressed(KeyCode::ShiftRight);
        let pan =
            buttons.pressed(MouseButton::Middle) || (shift && buttons.pressed(MouseButton::Right));
        if pan {
            let right = camera.right();
            let up = camera.up();
            let s = orbit.distance * 0.0015;
            orbit.target += (-right * d.x + up * d.y) * s;
        } else if (buttons.pressed(MouseButton::Left) && sandbox.placing.is_none())
            || buttons.pressed(MouseButton::Right)
        {
            orbit.yaw -= d.x * 0.005;
            orbit.pitch = (orbit.pitch + d.y * 0.005).clamp(-1.5, 1.5);
        }
        if scroll.delta.y != 0.0 {
            orbit.distance =
                (orbit.distance * (1.0 - 0.1 * scroll.delta.y.signum())).clamp(0.2, 200.0);
        }
    }
    let dir = Vec3::new(
        orbit.yaw.sin() * orbit.pitch.cos(),
        orbit.pitch.sin(),
        orbit.yaw.cos() * orbit.pitch.cos(),
    );
    **camera = Transform::from_translation(orbit.target + dir * orbit.distance)
        .looking_at(orbit.target, Vec3::Y);
}

/// The mouse springs are off while the left button places a part or picks a joint's end; a
/// grabbed model becomes the selected one.
fn sync_mouse_spring(
    mut sandbox: ResMut<Sandbox>,
    mut settings: ResMut<MouseSpringSettings>,
    mut grabbed: MessageReader<ModelGrabbed>,
) {
    settings.enabled = sandbox.placing.is_none() && sandbox.joining.is_none();
    if let Some(g) = grabbed.read().last() {
        sandbox.selected = Some(g.model);
    }
}

/// Newly spawned parts and images (a scene opened or reloaded) take the display toggles.
fn apply_display(
    sandbox: Res<Sandbox>,
    mut commands: Commands,
    parts: Query<Entity, Added<ScenePart>>,
    mut images: Query<(&mut SceneImage, &mut Visibility), Added<SceneImage>>,
) {
    if sandbox.wireframe {
        for e in &parts {
            commands.entity(e).insert(Wireframe);
        }
    }
    for (mut image, mut visibility) in &mut images {
        image.show_potential = sandbox.show_potential;
        if !sandbox.show_images {
            *visibility = Visibility::Hidden;
        }
    }
}

const JOINING_HELP: &str = "New joint: click a point on one part, then a point on another: \
the joint holds them together (model::joint). Esc cancels.";

/// Making a joint: each click on a model while joining picks the node nearest the hit as one
/// end; the second end, on another model, makes the [`PartJoint`] (a child of the scene, so
/// saving the scene keeps it).
fn pick_joint_end(
    press: On<Pointer<Press>>,
    mut sandbox: ResMut<Sandbox>,
    models: Query<(&FemMesh, &Scratch)>,
    mut commands: Commands,
) {
    if press.button != PointerButton::Primary {
        return;
    }
    let Some(ends) = sandbox.joining.as_mut() else {
        return;
    };
    let entity = press.entity;
    let Ok((fem, scratch)) = models.get(entity) else {
        return;
    };
    let (Some(tess), Some(hit)) = (fem.get(), press.hit.position) else {
        return;
    };
    let Some(end) = JointEnd::nearest(tess, scratch.node_positions(), hit.as_dvec3()) else {
        return;
    };
    if ends.first().is_some_and(|(e, _)| *e == entity) {
        sandbox.message = "New joint: the second end must be on another part.".into();
        return;
    }
    ends.push((entity, end));
    if let [(a, end_a), (b, end_b)] = ends[..] {
        let mut joint = commands.spawn((Name::new("joint"), PartJoint::new(a, end_a, b, end_b)));
        if let Some(root) = sandbox.root {
            joint.insert(ChildOf(root));
        }
        sandbox.joining = None;
        sandbox.message = "Joint made: drag either part and the other follows.".into();
    }
}

const PLACING_HELP: &str = "New part: click both ends of its major axis, then both ends of its \
minor axis, on the ground (y = 0) or on the image plane (z = 0) when the scene has an image. Esc cancels.";

/// Placing a new part as the paper's user does (Fig. 6(a)): four clicks on the ground plane, or
/// on the image plane when the scene has an image, give both ends of the major axis and of the
/// minor axis; the part (an ellipsoid, no data) is spawned under the scene root.
fn place_part(
    mut sandbox: ResMut<Sandbox>,
    buttons: Res<ButtonInput<MouseButton>>,
    egui: Res<EguiWantsInput>,
    window: Single<&Window>,
    camera: Single<(&Camera, &GlobalTransform)>,
    images: Query<(), With<SceneImage>>,
    mut instances: Query<&mut SceneInstance>,
    mut gizmos: Gizmos,
    mut commands: Commands,
) {
    let normal = if images.is_empty() { Vec3::Y } else { Vec3::Z };
    let Some(points) = sandbox.placing.as_mut() else {
        return;
    };
    for (i, p) in points.iter().enumerate() {
        let colour = if i < 2 {
            Color::srgb(1.0, 0.3, 0.3)
        } else {
            Color::srgb(0.3, 0.6, 1.0)
        };
        gizmos.sphere(Isometry3d::from_translation(*p), 0.04, colour);
    }
    if !buttons.just_pressed(MouseButton::Left) || egui.wants_any_pointer_input() {
        return;
    }
    let (camera, cam_tf) = *camera;
    let Some(cursor) = window.cursor_position() else {
        return;
    };
    let Ok(ray) = camera.viewport_to_world(cam_tf, cursor) else {
        return;
    };
    let Some(t) = ray.intersect_plane(Vec3::ZERO, InfinitePlane3d::new(normal)) else {
        return;
    };
    points.push(ray.get_point(t));
    if points.len() < 4 {
        return;
    }
    let p: [DVec3; 4] = std::array::from_fn(|i| points[i].as_dvec3());
    sandbox.placing = None;
    let Some((translation, rotation, shape)) = ellipsoid_from_points(p, normal.as_dvec3()) else {
        sandbox.message = "both axes need a length: the part was not placed".into();
        return;
    };
    let Some(root) = sandbox.root else { return };
    let Ok(mut instance) = instances.get_mut(root) else {
        return;
    };
    let name = format!("part {}", instance.parts.len() + 1);
    let e = commands
        .spawn((
            Name::new(name.clone()),
            GlobalShape::from(shape),
            RigidState {
                translation,
                rotation,
            },
            FemMesh::new(31),
            ChildOf(root),
        ))
        .id();
    instance.parts.push(e);
    sandbox.selected = Some(e);
    sandbox.message = format!("placed {name}");
}

/// `--demo-drag` (for the render test): once the scene runs, moves the real cursor onto the
/// cylinder, presses the left button as the windowing system would report it, drags 160 pixels to
/// the right over 40 frames and holds, then prints how far the cylinder moved. Picking, the grab,
/// the drag and the spring all run as they do for a user.
fn demo_drag(
    mut frame: Local<u32>,
    mut start: Local<Option<(Vec2, DVec3)>>,
    sandbox: Res<Sandbox>,
    mouse: Res<MouseSpring>,
    mut window: Single<(Entity, &mut Window)>,
    camera: Single<(&Camera, &GlobalTransform)>,
    parts: Query<(&Name, &RigidState)>,
    mut buttons: MessageWriter<bevy::input::mouse::MouseButtonInput>,
    mut events: MessageWriter<bevy::window::WindowEvent>,
) {
    let Some((name, rigid)) = parts.iter().find(|(n, _)| n.as_str() == sandbox.demo_part) else {
        return;
    };
    if sandbox.sim_steps < 20 {
        return;
    }
    let (camera, cam_tf) = *camera;
    let (window_entity, window) = &mut *window;
    let Some((p0, c0)) = *start else {
        let Ok(p) = camera.world_to_viewport(cam_tf, rigid.translation.as_vec3()) else {
            return;
        };
        window.set_cursor_position(Some(p));
        *start = Some((p, rigid.translation));
        return;
    };
    *frame += 1;
    match *frame {
        1..=2 => {}
        3 => {
            let press = bevy::input::mouse::MouseButtonInput {
                button: MouseButton::Left,
                state: bevy::input::ButtonState::Pressed,
                window: *window_entity,
            };
            buttons.write(press);
            events.write(bevy::window::WindowEvent::MouseButtonInput(press));
        }
        4..=43 => window.set_cursor_position(Some(p0 + Vec2::new(4.0 * (*frame - 3) as f32, 0.0))),
        44 => println!(
            "demo drag: {} grabbed: {}, moved by {:.3} (x {:.3})",
            name,
            mouse.model.is_some(),
            (rigid.translation - c0).length(),
            rigid.translation.x - c0.x
        ),
        _ => {}
    }
}

/// Runs `steps_per_frame` simulation steps while running, or the requested single steps.
fn run_simulation(world: &mut World) {
    let (running, n, single) = {
        let s = world.resource::<Sandbox>();
        (s.running, s.steps_per_frame, s.single_steps)
    };
    let steps = if running { n } else { single.min(1) };
    for _ in 0..steps {
        world.run_schedule(SimStep);
    }
    let mut s = world.resource_mut::<Sandbox>();
    s.sim_steps += steps as u64;
    if !running {
        s.single_steps = s.single_steps.saturating_sub(steps);
    }
}

/// Every 10 frames, the selected range part's RMS point-to-surface distance (a fraction of the
/// data's bounding-box diagonal), for the inspector's plot.
fn track_residual(
    mut sandbox: ResMut<Sandbox>,
    models: Query<(&FemMesh, &Scratch, &RangeData)>,
    mut frame: Local<u32>,
) {
    *frame += 1;
    if !frame.is_multiple_of(10) {
        return;
    }
    let Some((fem, scratch, range)) = sandbox.selected.and_then(|e| models.get(e).ok()) else {
        return;
    };
    let Some(tess) = fem.get() else { return };
    if scratch.node_positions().len() != tess.node_count() {
        return;
    }
    let r = residuals(tess, scratch.node_positions(), range.forces.points());
    sandbox.residual.push_back(r.rms as f32);
    if sandbox.residual.len() > 300 {
        sandbox.residual.pop_front();
    }
}

/// The inspector window.
fn inspector(
    mut contexts: EguiContexts,
    mut sandbox: ResMut<Sandbox>,
    mut debug: ResMut<DebugRenderConfig>,
    diagnostics: Res<DiagnosticsStore>,
    instances: Query<&SceneInstance>,
    names: Query<&Name>,
    mut parts: Query<(
        &mut GlobalShape,
        &mut ModelSettings,
        &mut SimControl,
        Option<&mut RangeData>,
        Option<&mut ImageData>,
        Option<&FitDriver>,
        Option<&mut Inertia>,
    )>,
    mut images: Query<&mut Visibility, With<SceneImage>>,
    mut scene_images: Query<&mut SceneImage>,
    mut commands: Commands,
    mut saved_beta: Local<std::collections::HashMap<Entity, f64>>,
    joints: Query<(Entity, &PartJoint)>,
) -> Result {
    let ctx = contexts.ctx_mut()?;
    let sandbox = &mut *sandbox;
    egui::Window::new("Deformable superquadrics")
        .default_pos([10.0, 10.0])
        .default_width(300.0)
        // The selected part's controls run past a small window's bottom: scroll to them.
        .vscroll(true)
        .default_height(690.0)
        .show(ctx, |ui| {
            let frame_ms = diagnostics
                .get(&FrameTimeDiagnosticsPlugin::FRAME_TIME)
                .and_then(|d| d.smoothed())
                .unwrap_or(0.0);
            let steps_per_s = if frame_ms > 0.0 {
                1000.0 / frame_ms * sandbox.steps_per_frame as f64
            } else {
                0.0
            };
            ui.label(format!(
                "frame {frame_ms:.1} ms · {} simulation steps ({steps_per_s:.0}/s while running)",
                sandbox.sim_steps
            ));
            ui.horizontal(|ui| {
                egui::ComboBox::from_id_salt("scene")
                    .selected_text(sandbox.scene.clone())
                    .show_ui(ui, |ui| {
                        for s in sandbox.scenes.clone() {
                            if ui.selectable_label(s == sandbox.scene, &s).clicked() {
                                sandbox.pending = Some(Action::Open(s));
                            }
                        }
                    });
                if ui.button("Save scene").clicked() {
                    sandbox.pending = Some(Action::SaveScene);
                }
            });
            ui.horizontal(|ui| {
                if ui.button("New part (4 clicks)").clicked() {
                    sandbox.placing = Some(Vec::new());
                    sandbox.message = PLACING_HELP.into();
                }
                if ui.button("New joint (2 clicks)").clicked() {
                    sandbox.joining = Some(Vec::new());
                    sandbox.message = JOINING_HELP.into();
                }
            });
            for i in &instances {
                if let Some(e) = &i.error {
                    ui.colored_label(egui::Color32::LIGHT_RED, e);
                }
            }
            if !sandbox.message.is_empty() {
                ui.label(&sandbox.message);
            }
            ui.separator();
            ui.horizontal(|ui| {
                let label = if sandbox.running { "Pause" } else { "Run" };
                if ui.button(label).clicked() {
                    sandbox.running = !sandbox.running;
                }
                if ui.button("Step").clicked() {
                    sandbox.running = false;
                    sandbox.single_steps += 1;
                }
            });
            ui.add(edit_slider(&mut sandbox.steps_per_frame, 1..=20).text("steps per frame"));
            ui.checkbox(&mut debug.points, "data points");
            ui.checkbox(&mut debug.data_springs, "data springs");
            ui.checkbox(&mut debug.user_springs, "mouse springs");
            if ui
                .checkbox(
                    &mut sandbox.show_potential,
                    "potential P instead of the image",
                )
                .changed()
            {
                for mut image in &mut scene_images {
                    image.show_potential = sandbox.show_potential;
                }
            }
            if ui.checkbox(&mut sandbox.wireframe, "wireframe").changed() {
                for e in instances.iter().flat_map(|i| i.parts.clone()) {
                    if sandbox.wireframe {
                        commands.entity(e).insert(Wireframe);
                    } else {
                        commands.entity(e).remove::<Wireframe>();
                    }
                }
            }
            if ui.checkbox(&mut sandbox.show_images, "image").changed() {
                for mut v in &mut images {
                    *v = if sandbox.show_images {
                        Visibility::Inherited
                    } else {
                        Visibility::Hidden
                    };
                }
            }
            if ui
                .checkbox(&mut sandbox.data_forces, "data forces")
                .changed()
            {
                for e in instances.iter().flat_map(|i| i.parts.clone()) {
                    if let Ok((_, _, _, range, image, ..)) = parts.get_mut(e) {
                        let beta = match (range, image) {
                            (Some(r), _) => &mut r.into_inner().forces.beta,
                            (_, Some(im)) => &mut im.into_inner().forces.beta,
                            _ => continue,
                        };
                        if sandbox.data_forces {
                            *beta = saved_beta.remove(&e).unwrap_or(*beta);
                        } else {
                            saved_beta.insert(e, *beta);
                            *beta = 0.0;
                        }
                    }
                }
            }
            ui.separator();
            ui.label("Parts");
            for i in &instances {
                for &e in &i.parts {
                    let name = names.get(e).map(|n| n.to_string()).unwrap_or_default();
                    if sandbox.selected.is_none() && sandbox.select.as_ref() == Some(&name) {
                        sandbox.selected = Some(e);
                    }
                    if ui
                        .selectable_label(sandbox.selected == Some(e), name)
                        .clicked()
                    {
                        sandbox.selected = Some(e);
                        sandbox.residual.clear();
                    }
                }
            }
            if !joints.is_empty() {
                ui.separator();
                ui.label("Joints (gap, force carried)");
                for (e, j) in &joints {
                    let name = |m: Entity| names.get(m).map(|n| n.to_string()).unwrap_or_default();
                    ui.horizontal(|ui| {
                        ui.label(format!(
                            "{} ↔ {}: {:.1e}, {:.2}",
                            name(j.a),
                            name(j.b),
                            j.gap.length(),
                            j.joint.multiplier.length()
                        ));
                        if ui.small_button("remove").clicked() {
                            commands.entity(e).despawn();
                        }
                    });
                }
            }
            let Some(sel) = sandbox.selected else { return };
            let Ok((mut shape, mut settings, mut control, range, _, driver, inertia)) =
                parts.get_mut(sel)
            else {
                return;
            };
            ui.separator();
            let g = &mut *shape;
            ui.add(edit_slider(&mut g.a, 0.05..=3.0).text("a"));
            ui.add(edit_slider(&mut g.a1, 0.05..=1.0).text("a1"));
            ui.add(edit_slider(&mut g.a2, 0.05..=1.0).text("a2"));
            ui.add(edit_slider(&mut g.a3, 0.05..=1.0).text("a3"));
            // Down to the least ε a shape may hold; the step keeps one set below 0.1 there.
            let e_range = LEAST_EPSILON..=MAX_EPSILON;
            ui.add(edit_slider(&mut g.e1, e_range.clone()).text("ε1"));
            ui.add(edit_slider(&mut g.e2, e_range).text("ε2"));
            // Tapering and bending (beyond the paper; model::deform). The step keeps them within
            // their bounds for the shape.
            ui.add(edit_slider(&mut g.taper[0], -MAX_TAPER..=MAX_TAPER).text("taper x"));
            ui.add(edit_slider(&mut g.taper[1], -MAX_TAPER..=MAX_TAPER).text("taper y"));
            ui.add(edit_slider(&mut g.bend[0], -MAX_BEND..=MAX_BEND).text("bend x"));
            ui.add(edit_slider(&mut g.bend[1], -MAX_BEND..=MAX_BEND).text("bend y"));
            let s = &mut *settings;
            ui.add(
                edit_slider(&mut s.w0, 0.0..=0.1)
                    .logarithmic(true)
                    .text("w0"),
            );
            ui.add(
                edit_slider(&mut s.w1, 0.0..=2.0)
                    .logarithmic(true)
                    .text("w1"),
            );
            ui.add(
                edit_slider(&mut s.gamma_global, 0.01..=10.0)
                    .logarithmic(true)
                    .text("γ global"),
            );
            ui.add(
                edit_slider(&mut s.gamma_local, 0.01..=10.0)
                    .logarithmic(true)
                    .text("γ local"),
            );
            ui.add(
                edit_slider(&mut s.dt, 0.001..=0.2)
                    .logarithmic(true)
                    .text("Δt"),
            );
            ui.add(edit_slider(&mut s.reassign_every, 1..=1000).text("reassign every"));
            ui.horizontal(|ui| {
                ui.checkbox(&mut s.global_only, "global only");
                // The membrane as one conjugate-gradient solve a step (DynamicsParams::
                // implicit_local): stable at any Δt, so Δt can go up without sub-steps.
                ui.checkbox(&mut s.implicit_local, "implicit membrane")
                    .on_hover_text(
                        "one backward-Euler solve of the local DOFs a step: stable at any Δt \
                         (first-order dynamics; ignored with inertia)",
                    );
            });
            ui.horizontal(|ui| {
                ui.checkbox(&mut s.fix_epsilon, "fix ε");
                ui.checkbox(&mut s.fix_shape, "fix shape (rigid)");
            });
            ui.horizontal(|ui| {
                ui.checkbox(&mut s.taper, "free taper");
                ui.checkbox(&mut s.bend, "free bend");
            });
            // Second-order dynamics (model::inertia): with mass the model swings and settles.
            let mut second_order = inertia.is_some();
            if ui
                .checkbox(&mut second_order, "inertia (second order)")
                .changed()
            {
                if second_order {
                    commands.entity(sel).insert(Inertia::default());
                } else {
                    commands.entity(sel).remove::<Inertia>();
                }
            }
            if let Some(mut inertia) = inertia {
                let p = &mut inertia.params;
                ui.add(
                    edit_slider(&mut p.mass_density, 0.01..=100.0)
                        .logarithmic(true)
                        .text("mass density μ"),
                );
                ui.add(edit_slider(&mut p.damping, 0.0..=10.0).text("damping β"));
            }
            ui.horizontal(|ui| {
                if ui.button("Reset").clicked() {
                    control.reset_requested = true;
                }
                ui.checkbox(&mut control.paused, "paused");
                if ui.button("Export OBJ").clicked() {
                    sandbox.pending = Some(Action::ExportObj);
                }
                if range.is_some() && ui.button("Fit").clicked() {
                    sandbox.pending = Some(Action::Fit(sel));
                }
            });
            if let Some(err) = &control.error {
                ui.colored_label(egui::Color32::LIGHT_RED, err);
            }
            if let Some(d) = driver {
                let state = if d.done {
                    if d.converged {
                        "fit at rest"
                    } else {
                        "fit stopped at its step cap"
                    }
                } else {
                    "fitting…"
                };
                ui.label(format!("{state} ({} steps)", control.steps));
            }
            if range.is_some() {
                ui.label("RMS distance to the data (fraction of the diagonal)");
                plot(ui, &sandbox.residual);
            }
        });
    egui::Window::new("Keys and mouse")
        .default_open(false)
        .anchor(egui::Align2::RIGHT_TOP, [-10.0, 10.0])
        .show(ctx, |ui| {
            for line in CHEAT_SHEET {
                ui.label(*line);
            }
        });
    Ok(())
}

/// The cheat sheet, also in README.md.
const CHEAT_SHEET: &[&str] = &[
    "Left drag on a model: pull it with a spring",
    "Left / right drag on empty space: orbit",
    "Middle drag or Shift + right drag: pan",
    "Wheel or + / -: zoom; arrows: orbit; Home: reset view",
    "Space: pause / run; S: single step",
    "Tab: next part; R: reset part; F: fit part to convergence",
    "N: new part from four clicks (major axis ends, minor axis ends); Esc: cancel",
];

/// A line plot of `values` with its last value.
fn plot(ui: &mut egui::Ui, values: &VecDeque<f32>) {
    let (rect, _) = ui.allocate_exact_size(egui::vec2(280.0, 80.0), egui::Sense::hover());
    let painter = ui.painter_at(rect);
    painter.rect_filled(rect, 2.0, egui::Color32::from_gray(30));
    let Some(max) = values.iter().copied().reduce(f32::max).filter(|m| *m > 0.0) else {
        return;
    };
    let n = values.len().max(2) as f32 - 1.0;
    let points: Vec<egui::Pos2> = values
        .iter()
        .enumerate()
        .map(|(i, v)| {
            egui::pos2(
                rect.left() + rect.width() * i as f32 / n,
                rect.bottom() - rect.height() * (v / max) * 0.95,
            )
        })
        .collect();
    painter.add(egui::Shape::line(
        points,
        egui::Stroke::new(1.5, egui::Color32::LIGHT_GREEN),
    ));
    if let Some(last) = values.back() {
        painter.text(
            rect.right_top() + egui::vec2(-4.0, 4.0),
            egui::Align2::RIGHT_TOP,
            format!("{last:.4} (max {max:.4})"),
            egui::FontId::proportional(11.0),
            egui::Color32::WHITE,
        );
    }
}

#[path = "support/screenshot.rs"]
mod screenshot;

/// A slider that clamps what the user enters to `range` but leaves values outside it alone (egui
/// clamps every shown value by default, which would silently change a model the inspector shows).
fn edit_slider<Num: egui::emath::Numeric>(
    value: &mut Num,
    range: std::ops::RangeInclusive<Num>,
) -> egui::Slider<'_> {
    egui::Slider::new(value, range).clamping(egui::SliderClamping::Edits)
}
