//! DeformableSqInspectorPlugin in a headless app: the selection, the residual history, the
//! message line, and the panel drawn into a bare egui context.

use bevy::prelude::*;
use bevy::time::TimeUpdateStrategy;
use bevy_deformable_sq::model::fit::FitOptions;
use bevy_deformable_sq::model::superquadric::SuperquadricParams;
use bevy_deformable_sq::prelude::*;
use bevy_deformable_sq::synthetic::superquadric_cloud;
use bevy_egui::egui;
use glam::{DQuat, DVec3};
use std::time::Duration;

fn app() -> App {
    let mut app = App::new();
    app.add_plugins((
        MinimalPlugins,
        DeformableSqPlugin::default(),
        DeformableSqInspectorPlugin,
    ))
    .insert_resource(TimeUpdateStrategy::ManualDuration(Duration::from_secs_f64(
        1.0 / 64.0,
    )))
    .insert_resource(InspectorState {
        select_name: Some("box".into()),
        ..default()
    });
    app
}

fn spawn(app: &mut App, name: &str, at: DVec3) -> Entity {
    let target = SuperquadricParams {
        a: 1.0,
        a1: 0.9,
        a2: 0.6,
        a3: 0.8,
        e1: 0.4,
        e2: 0.5,
    };
    let points = superquadric_cloud(&target, at, DQuat::IDENTITY, 400, 0.0, 5);
    app.world_mut()
        .spawn((
            Name::new(name.to_string()),
            GlobalShape {
                a: 0.8,
                ..default()
            },
            RigidState {
                translation: at + DVec3::splat(0.1),
                rotation: DQuat::IDENTITY,
            },
            FemMesh::new(9),
            RangeData::new(points),
        ))
        .id()
}

#[test]
fn the_named_model_is_selected_and_its_fit_is_plotted_and_reported() {
    let mut app = app();
    let other = spawn(&mut app, "ball", DVec3::X * 3.0);
    let model = spawn(&mut app, "box", DVec3::ZERO);
    app.update();
    app.update();
    let state = app.world().resource::<InspectorState>();
    assert_eq!(state.selected, Some(model));
    assert!(app.world().get::<ResidualHistory>(model).is_some());
    assert!(app.world().get::<ResidualHistory>(other).is_none());
    // Sample every frame, and take the first sample before the fit starts, so that the first
    // value is the start's residual whatever the pool's timing.
    app.world_mut()
        .get_mut::<ResidualHistory>(model)
        .unwrap()
        .every = 1;
    app.update();
    assert_eq!(
        app.world()
            .get::<ResidualHistory>(model)
            .unwrap()
            .values
            .len(),
        1
    );
    app.world_mut()
        .entity_mut(model)
        .insert(FitDriver::to_convergence(FitOptions::default()));
    // The fit runs on the async compute pool; then enough frames for ten samples.
    for _ in 0..200_000 {
        app.update();
        if app.world().get::<FitDriver>(model).unwrap().is_done() {
            break;
        }
        std::thread::sleep(Duration::from_micros(100));
    }
    for _ in 0..10_000 {
        app.update();
        if app
            .world()
            .get::<ResidualHistory>(model)
            .unwrap()
            .values
            .len()
            >= 10
        {
            break;
        }
    }
    let message = &app.world().resource::<InspectorState>().message;
    assert!(message.starts_with("fit at rest after"), "{message}");
    let history = &app.world().get::<ResidualHistory>(model).unwrap().values;
    assert!(history.len() >= 10, "{history:?}");
    let (first, last) = (history[0], *history.back().unwrap());
    // The start is 0.1 off in every axis with the wrong size; the fit lands on the data.
    assert!(last < first * 0.1, "{first} → {last}");
    // The selected model despawned: the selection is dropped.
    app.world_mut().despawn(model);
    app.update();
    assert_eq!(app.world().resource::<InspectorState>().selected, None);
}

/// The texts the panel of `model` draws, and what it said, in one pass of a bare egui context.
fn panel_texts(app: &mut App, model: Entity) -> (Vec<String>, Option<String>) {
    use bevy::ecs::system::RunSystemOnce;
    let ctx = egui::Context::default();
    let system = move |mut models: Query<InspectedModel>, mut commands: Commands| {
        let mut item = models.get_mut(model).expect("the model");
        let mut said = None;
        let mut output = ctx.run_ui(egui::RawInput::default(), |ui| {
            said = model_inspector_ui(ui, &mut item, std::path::Path::new("."), &mut commands);
        });
        fn collect(shape: &egui::Shape, texts: &mut Vec<String>) {
            match shape {
                egui::Shape::Text(t) => texts.push(t.galley.text().to_string()),
                egui::Shape::Vec(shapes) => shapes.iter().for_each(|s| collect(s, texts)),
                _ => {}
            }
        }
        output.textures_delta.clear();
        let mut texts = Vec::new();
        for clipped in &output.shapes {
            collect(&clipped.shape, &mut texts);
        }
        (texts, said)
    };
    app.world_mut().run_system_once(system).expect("the panel")
}

#[test]
fn the_panel_draws_every_control_and_fits_only_models_with_data() {
    let mut app = app();
    let model = spawn(&mut app, "box", DVec3::ZERO);
    let free = app
        .world_mut()
        .spawn((
            Name::new("free"),
            GlobalShape::default(),
            RigidState::default(),
        ))
        .id();
    for _ in 0..12 {
        app.update();
    }
    let (texts, said) = panel_texts(&mut app, model);
    assert_eq!(said, None);
    for want in [
        "box",
        "a",
        "a1",
        "ε1",
        "taper x",
        "bend y",
        "w0",
        "Δt",
        "global only",
        "fix ε",
        "inertia (second order)",
        "paused",
        "Step",
        "Reset",
        "Fit to convergence",
        "Export OBJ",
        "RMS distance to the data (fraction of the diagonal)",
    ] {
        assert!(texts.iter().any(|t| t == want), "no {want:?} in {texts:?}");
    }
    let (texts, _) = panel_texts(&mut app, free);
    assert!(texts.iter().any(|t| t == "free"), "{texts:?}");
    assert!(
        !texts.iter().any(|t| t == "Fit to convergence"),
        "{texts:?}"
    );
    assert!(!texts.iter().any(|t| t.starts_with("RMS")), "{texts:?}");
}
