//! The plugin's fit to convergence ([`FitDriver`]) runs the core's fit: the same state, bit for
//! bit, whatever the options and whatever the model did before; it honours every option and
//! leaves the model's own settings alone.

use bevy::prelude::*;
use bevy_deformable_sq::model::dynamics::ModelState;
use bevy_deformable_sq::model::fit::{FitOptions, FitReport, Solver, fit};
use bevy_deformable_sq::model::superquadric::SuperquadricParams;
use bevy_deformable_sq::plugin::headless::fit_headless;
use bevy_deformable_sq::prelude::*;
use bevy_deformable_sq::synthetic::superquadric_cloud;
use glam::{DQuat, DVec3};
use std::time::Duration;

/// A headless app stepping the simulation once per update.
fn app() -> App {
    let mut app = App::new();
    app.add_plugins((MinimalPlugins, DeformableSqPlugin::in_schedule(Update)));
    app
}

fn shape() -> SuperquadricParams {
    SuperquadricParams {
        a: 1.4,
        a1: 0.5,
        a2: 0.8,
        a3: 1.0,
        e1: 0.5,
        e2: 1.3,
    }
}

fn cloud(seed: u64) -> Vec<DVec3> {
    superquadric_cloud(
        &shape(),
        DVec3::new(2.0, -1.0, 0.5),
        DQuat::from_rotation_x(0.7),
        300,
        0.01,
        seed,
    )
}

/// A model with `points` as its range data, at the origin as a unit sphere.
fn spawn(app: &mut App, points: Vec<DVec3>) -> Entity {
    app.world_mut()
        .spawn((GlobalShape::default(), RangeData::new(points)))
        .id()
}

/// Updates until the model's driver is done (the fit runs on another thread).
fn until_done(app: &mut App, e: Entity) {
    for _ in 0..200_000 {
        app.update();
        if app
            .world()
            .get::<FitDriver>(e)
            .is_some_and(FitDriver::is_done)
        {
            return;
        }
        std::thread::sleep(Duration::from_micros(100));
    }
    panic!("the fit did not end");
}

/// The model's state as its components hold it.
fn state_of(app: &App, e: Entity) -> ModelState {
    let w = app.world();
    bevy_deformable_sq::plugin::model_state(
        w.get::<RigidState>(e).unwrap(),
        w.get::<GlobalShape>(e).unwrap(),
        w.get::<LocalDofs>(e).unwrap(),
    )
}

/// The report of the driver on `e`.
fn report_of(app: &App, e: Entity) -> FitReport {
    let d = app.world().get::<FitDriver>(e).unwrap();
    assert!(d.error().is_none(), "{:?}", d.error());
    d.report().cloned().expect("a report")
}

#[test]
fn a_model_that_stepped_twenty_thousand_times_fits_as_a_fresh_one() {
    // The old driver compared the model's own step count, counted since spawn, with the fit's
    // budget: a model that had stepped more than the budget ended its fit after one step.
    let points = cloud(3);
    let mut app = app();
    let old = spawn(&mut app, points.clone());
    for _ in 0..20_000 {
        app.update();
    }
    assert!(app.world().get::<SimControl>(old).unwrap().steps >= 20_000);
    let fresh = spawn(&mut app, points.clone());
    let options = FitOptions::default().for_data();
    for e in [old, fresh] {
        app.world_mut()
            .entity_mut(e)
            .insert(FitDriver::new(options));
    }
    until_done(&mut app, old);
    until_done(&mut app, fresh);
    let (a, b) = (report_of(&app, old), report_of(&app, fresh));
    assert!(a.converged && b.converged);
    assert_eq!(state_of(&app, old), state_of(&app, fresh));
    assert_eq!(a.steps, b.steps);
    // And the core's fit, bit for bit.
    let core = fit(&points, &options, |_| {}).unwrap();
    assert_eq!(state_of(&app, old), core.state);
    assert_eq!(app.world().get::<FemMesh>(old).unwrap().k, core.tess.k);
}

#[test]
fn a_fit_from_a_global_only_model_keeps_its_settings_and_its_membrane_still() {
    // The old driver wrote `global_only: false` into the model's settings for its joint stage.
    let mut app = app();
    let e = spawn(&mut app, cloud(4));
    let settings = ModelSettings {
        global_only: true,
        ..default()
    };
    app.world_mut().entity_mut(e).insert(settings);
    app.update();
    app.world_mut()
        .entity_mut(e)
        .insert(FitDriver::for_model(&settings));
    until_done(&mut app, e);
    assert_eq!(*app.world().get::<ModelSettings>(e).unwrap(), settings);
    let report = report_of(&app, e);
    assert!(report.converged && report.options.solver == Solver::Solved);
    let state = state_of(&app, e);
    assert!(state.displacement.iter().all(|d| *d == DVec3::ZERO));
    // A pure fit of a superquadric cloud: its axes recovered.
    let mut found = state.shape.semi_axes().to_array();
    let mut truth = shape().semi_axes().to_array();
    found.sort_by(f64::total_cmp);
    truth.sort_by(f64::total_cmp);
    for (f, t) in found.iter().zip(truth) {
        assert!((f / t - 1.0).abs() < 0.03, "{found:?} against {truth:?}");
    }
}

#[test]
fn every_option_set_in_the_plugin_is_the_cores() {
    // The old driver read none of solver, init, k, the switches or β; each case here differs
    // from the default in some of them, and the plugin's fit is the core's bit for bit.
    let points = cloud(5);
    let start = bevy_deformable_sq::model::init::InitialPose {
        translation: DVec3::new(1.5, -0.5, 0.0),
        rotation: DQuat::IDENTITY,
        shape: SuperquadricParams::default(),
    };
    let cases = [
        FitOptions {
            k: 15,
            k_from_data: false,
            solver: Solver::Dynamics,
            beta: 2.0,
            ..FitOptions::default()
        },
        FitOptions {
            init: bevy_deformable_sq::model::fit::Initialization::Explicit(start),
            global_only: true,
            ..FitOptions::default().robust()
        },
        FitOptions {
            k: 13,
            outlier_ratio: 0.1,
            similarity_switch: true,
            ..FitOptions::default()
        },
    ];
    for options in cases {
        let mut app = app();
        let e = spawn(&mut app, points.clone());
        app.world_mut()
            .entity_mut(e)
            .insert(FitDriver::new(options));
        until_done(&mut app, e);
        let core = fit(&points, &options, |_| {}).unwrap();
        let plugin = report_of(&app, e);
        assert_eq!(plugin.options.solver, core.options.solver);
        assert_eq!(plugin.steps, core.steps, "{options:?}");
        assert_eq!(state_of(&app, e), core.state, "{options:?}");
        assert_eq!(app.world().get::<FemMesh>(e).unwrap().k, core.tess.k);
    }
    // The dynamics case ran the dynamics, on the mesh it was given.
    let mut app = app();
    let e = spawn(&mut app, points.clone());
    app.world_mut()
        .entity_mut(e)
        .insert(FitDriver::new(cases[0]));
    until_done(&mut app, e);
    assert_eq!(report_of(&app, e).options.solver, Solver::Dynamics);
    assert_eq!(app.world().get::<FemMesh>(e).unwrap().k, 15);
}

#[test]
fn a_driver_on_a_model_without_range_data_says_so() {
    let mut app = app();
    let e = app
        .world_mut()
        .spawn((
            GlobalShape::default(),
            FitDriver::new(FitOptions::default()),
        ))
        .id();
    until_done(&mut app, e);
    let d = app.world().get::<FitDriver>(e).unwrap();
    assert!(d.report().is_none());
    assert!(
        d.error()
            .unwrap()
            .to_string()
            .contains("no range or image data")
    );
}

#[test]
fn an_image_model_fits_to_convergence_as_the_core_solves_it_bit_for_bit() {
    use bevy_deformable_sq::model::fem::Tessellation;
    use bevy_deformable_sq::model::forces::image::{ImageForces, ImageFrame, ImagePotential};
    use bevy_deformable_sq::model::image_fit::{ImageFitOptions, PartAxes, fit_part};
    use glam::DVec2;
    // A dark ellipse (semi-axes 40 and 18 px) on a light ground, and a part placed off it.
    let (w, h) = (160, 120);
    let lum = (0..w * h)
        .map(|i| {
            let q = (DVec2::new((i % w) as f64, (i / w) as f64) - DVec2::new(80.0, 60.0))
                / DVec2::new(40.0, 18.0);
            if q.length_squared() <= 1.0 { 0.2 } else { 0.8 }
        })
        .collect();
    let potential =
        std::sync::Arc::new(ImagePotential::new(w, h, lum, 2.0, ImageFrame::default()).unwrap());
    let k = 12;
    let tess = Tessellation::new(k);
    let axes = PartAxes::from_points(
        &potential,
        [(50.0, 64.0), (106.0, 60.0), (78.0, 48.0), (78.0, 74.0)].map(|(x, y)| DVec2::new(x, y)),
    )
    .unwrap();
    let start = axes.state(&tess);
    let mut app = app();
    let e = app
        .world_mut()
        .spawn((
            GlobalShape::new(start.shape, start.deformation),
            RigidState {
                translation: start.translation,
                rotation: start.rotation,
            },
            FemMesh::new(k),
            ImageData::new(potential.clone()),
            FitDriver::new(FitOptions::default()),
        ))
        .id();
    until_done(&mut app, e);
    let d = app.world().get::<FitDriver>(e).unwrap();
    assert!(d.error().is_none(), "{:?}", d.error());
    let fitted = d.image_fit().expect("an image fit").clone();
    assert!(d.converged() && d.report().is_none());
    let core = fit_part(
        &tess,
        &ImageForces::new(potential.clone()),
        start,
        &ImageFitOptions {
            k,
            ..ImageFitOptions::default()
        },
    )
    .unwrap();
    assert_eq!(fitted.state, core.state);
    assert_eq!(state_of(&app, e), core.state);
    assert!(app.world().get::<SimControl>(e).unwrap().paused);
}

#[test]
fn the_fitter_through_a_headless_app_gives_the_core_fit_bit_for_bit() {
    let points = cloud(77);
    // A cone fitted with tapering and bending free, and a dense one-view cloud
    // with local DOFs (a finer tessellation chosen from the data).
    let cone_shape = bevy_deformable_sq::synthetic::Banana::cone(1.5, 0.5, 1.0);
    let turn = DQuat::from_axis_angle(DVec3::new(-0.4, 0.8, 0.3).normalize(), 2.1);
    let cone: Vec<DVec3> = cone_shape
        .points(600, 0.01 * cone_shape.radius, 11)
        .into_iter()
        .map(|p| turn * p + DVec3::new(1.0, 0.5, -2.0))
        .collect();
    let mut deformed = FitOptions {
        k: 11,
        global_only: true,
        ..Default::default()
    };
    deformed.dynamics.free.taper = true;
    deformed.dynamics.free.bend = true;
    let half: Vec<DVec3> = superquadric_cloud(
        &shape(),
        DVec3::ZERO,
        DQuat::from_rotation_y(0.3),
        1200,
        0.005,
        79,
    )
    .into_iter()
    .filter(|p| p.z > 0.0)
    .collect();
    let dynamics = FitOptions {
        solver: Solver::Dynamics,
        k: 11,
        ..Default::default()
    };
    let cases = [
        (&points, FitOptions::default().for_data()),
        (
            &points,
            FitOptions {
                global_only: true,
                ..Default::default()
            }
            .robust(),
        ),
        (&points, dynamics),
        (&points, dynamics.robust()),
        (&cone, deformed.for_data()),
        (
            &cone,
            FitOptions {
                solver: Solver::Dynamics,
                ..deformed
            },
        ),
        (
            &half,
            FitOptions {
                k: 11,
                ..FitOptions::default()
            }
            .for_data(),
        ),
    ];
    let mut retessellated = false;
    for (points, opts) in cases {
        let core = fit(points, &opts, |_| {}).expect("core fit");
        let app = fit_headless(points, &opts).expect("headless fit");
        assert_eq!(app.initial, core.initial);
        assert_eq!(app.steps, core.steps, "{opts:?}");
        assert_eq!(app.converged, core.converged);
        assert_eq!(app.state, core.state, "{opts:?}: states differ");
        assert_eq!(app.residuals, core.residuals);
        assert_eq!(app.tess.k, core.tess.k);
        assert_eq!(app.options.solver, core.options.solver);
        retessellated |= core.tess.k > opts.k;
    }
    assert!(retessellated, "no case went on to a finer tessellation");
}
