//! DeformableSqPlugin in headless apps (`MinimalPlugins`, time driven by
//! `TimeUpdateStrategy::ManualDuration`).

use bevy::prelude::*;
use bevy::time::TimeUpdateStrategy;
use bevy_deformable_sq::model::dynamics::{ModelState, NodalForces, Workspace, step};
use bevy_deformable_sq::model::fem::Tessellation;
use bevy_deformable_sq::model::fit::residuals;
use bevy_deformable_sq::model::joint::JointEnd;
use bevy_deformable_sq::model::superquadric::SuperquadricParams;
use bevy_deformable_sq::prelude::*;
use bevy_deformable_sq::synthetic::superquadric_cloud;
use glam::{DQuat, DVec3};
use std::hash::{Hash, Hasher};
use std::time::Duration;

/// A headless app whose every `update` advances time by one fixed step (1/64 s).
fn app() -> App {
    let mut app = App::new();
    app.add_plugins(MinimalPlugins)
        .add_plugins(DeformableSqPlugin::default());
    app.insert_resource(TimeUpdateStrategy::ManualDuration(Duration::from_secs_f64(
        1.0 / 64.0,
    )));
    app
}

/// Updates until every model has taken at least `steps` steps (bounded).
fn run_steps(app: &mut App, steps: u64) {
    for _ in 0..steps * 4 + 10 {
        app.update();
        let mut q = app.world_mut().query::<&SimControl>();
        if q.iter(app.world())
            .all(|c| c.steps >= steps || c.frozen || c.paused)
        {
            return;
        }
    }
    panic!("models did not take {steps} steps");
}

fn cloud(seed: u64, centre: DVec3) -> Vec<DVec3> {
    let shape = SuperquadricParams {
        a: 1.2,
        a1: 0.8,
        a2: 0.6,
        a3: 1.0,
        e1: 0.7,
        e2: 1.2,
    };
    superquadric_cloud(
        &shape,
        centre,
        DQuat::from_rotation_z(0.3),
        400,
        0.005,
        seed,
    )
}

fn start_shape() -> GlobalShape {
    GlobalShape {
        a: 1.0,
        a1: 1.0,
        a2: 1.0,
        a3: 1.0,
        e1: 1.0,
        e2: 1.0,
        ..Default::default()
    }
}

fn spawn_model(app: &mut App, points: Vec<DVec3>, centre: DVec3, k: usize) -> Entity {
    app.world_mut()
        .spawn((
            start_shape(),
            RigidState {
                translation: centre,
                rotation: DQuat::IDENTITY,
            },
            FemMesh::new(k),
            RangeData::new(points),
        ))
        .id()
}

fn state_of(app: &App, e: Entity) -> (RigidState, GlobalShape, LocalDofs, SimControl) {
    let w = app.world();
    (
        *w.get::<RigidState>(e).unwrap(),
        *w.get::<GlobalShape>(e).unwrap(),
        w.get::<LocalDofs>(e).unwrap().clone(),
        w.get::<SimControl>(e).unwrap().clone(),
    )
}

fn state_hash(app: &App, e: Entity) -> u64 {
    let (r, s, l, _) = state_of(app, e);
    let mut h = std::collections::hash_map::DefaultHasher::new();
    let mut put = |x: f64| x.to_bits().hash(&mut h);
    r.translation
        .to_array()
        .into_iter()
        .chain(r.rotation.to_array())
        .for_each(&mut put);
    [s.a, s.a1, s.a2, s.a3, s.e1, s.e2]
        .into_iter()
        .for_each(&mut put);
    l.displacement
        .iter()
        .flat_map(|d| d.to_array())
        .for_each(&mut put);
    h.finish()
}

#[test]
fn plugin_fit_equals_the_pure_core_step_for_step() {
    let points = cloud(1, DVec3::new(0.5, 0.0, 0.2));
    let mut app = app();
    let e = spawn_model(&mut app, points.clone(), DVec3::new(0.4, 0.1, 0.0), 15);
    run_steps(&mut app, 600);
    let (rigid, shape, local, control) = state_of(&app, e);
    let steps = control.steps;

    // The same loop through the pure core.
    let tess = Tessellation::new(15);
    let mut state = ModelState::new(
        &tess,
        DVec3::new(0.4, 0.1, 0.0),
        DQuat::IDENTITY,
        start_shape().into(),
    );
    let mut range = RangeData::new(points.clone()).forces;
    let settings = ModelSettings::default();
    let (mut ws, mut forces, mut x) = (
        Workspace::default(),
        NodalForces::new(tess.node_count()),
        Vec::new(),
    );
    for s in 0..steps {
        state.node_positions(&tess, &mut x);
        if s % settings.reassign_every as u64 == 0 {
            range.reassign(&tess, &x);
        }
        range.migrate(&tess, &x, Some(&state.surface()));
        forces.clear(tess.node_count());
        range.accumulate(&tess, &x, &mut forces);
        step(&tess, &mut state, &forces, &settings.dynamics(), &mut ws).unwrap();
    }
    assert_eq!(state.translation, rigid.translation);
    assert_eq!(state.rotation, rigid.rotation);
    assert_eq!(SuperquadricParams::from(shape), state.shape);
    assert_eq!(state.displacement, local.displacement);

    state.node_positions(&tess, &mut x);
    let res = residuals(&tess, &x, &points);
    eprintln!("plugin fit after {steps} steps: {res:?}");
    assert!(
        res.mean < 0.01,
        "the plugin's model did not fit its data: {res:?}"
    );
}

#[test]
fn reassignment_happens_exactly_every_n_steps() {
    let mut app = app();
    let e = spawn_model(&mut app, cloud(2, DVec3::ZERO), DVec3::ZERO, 9);
    app.world_mut()
        .get_mut::<ModelSettings>(e)
        .unwrap()
        .reassign_every = 7;
    for _ in 0..200 {
        app.update();
        let steps = app.world().get::<SimControl>(e).unwrap().steps;
        let done = app.world().get::<RangeData>(e).unwrap().reassignments;
        // Before steps 0, 7, 14, …: ⌈steps / 7⌉ reattachments after `steps` steps.
        assert_eq!(done, steps.div_ceil(7), "after {steps} steps");
    }
    assert!(app.world().get::<SimControl>(e).unwrap().steps >= 100);
}

#[test]
fn two_runs_are_bit_identical() {
    let run = || {
        let mut app = app();
        let es: Vec<Entity> = (0..4)
            .map(|i| {
                spawn_model(
                    &mut app,
                    cloud(10 + i, DVec3::X * i as f64),
                    DVec3::X * i as f64,
                    11,
                )
            })
            .collect();
        run_steps(&mut app, 250);
        es.iter()
            .map(|&e| {
                (
                    state_hash(&app, e),
                    app.world().get::<SimControl>(e).unwrap().steps,
                )
            })
            .collect::<Vec<_>>()
    };
    assert_eq!(run(), run());
}

#[test]
fn despawning_a_model_mid_run_leaves_the_others_running() {
    let mut app = app();
    let a = spawn_model(&mut app, cloud(3, DVec3::ZERO), DVec3::ZERO, 9);
    let b = spawn_model(&mut app, cloud(4, DVec3::Y * 3.0), DVec3::Y * 3.0, 9);
    run_steps(&mut app, 20);
    app.world_mut().despawn(a);
    let before = app.world().get::<SimControl>(b).unwrap().steps;
    for _ in 0..30 {
        app.update();
    }
    assert!(app.world().get_entity(a).is_err());
    assert!(app.world().get::<SimControl>(b).unwrap().steps > before + 20);
}

#[test]
fn a_model_with_no_data_stays_at_rest() {
    let mut app = app();
    let e = app
        .world_mut()
        .spawn((
            GlobalShape {
                a: 1.3,
                a1: 0.5,
                a2: 0.8,
                a3: 1.0,
                e1: 0.6,
                e2: 1.4,
                // Tapered and bent, as a model may be.
                taper: [0.2, -0.1],
                bend: [0.1, 0.2],
            },
            RigidState::default(),
        ))
        .id();
    run_steps(&mut app, 1);
    let first = state_hash(&app, e);
    run_steps(&mut app, 100);
    assert_eq!(state_hash(&app, e), first);
    let (_, shape, local, control) = state_of(&app, e);
    assert_eq!(shape.a, 1.3);
    assert_eq!(
        local.displacement.len(),
        963,
        "a default model has the paper's 963 nodes"
    );
    assert!(local.displacement.iter().all(|d| *d == DVec3::ZERO));
    assert!(control.steps >= 100);
}

#[test]
fn twenty_models_fit_at_once() {
    let mut app = app();
    let es: Vec<(Entity, Vec<DVec3>)> = (0..20)
        .map(|i| {
            let centre = DVec3::new((i % 5) as f64 * 4.0, (i / 5) as f64 * 4.0, 0.0);
            let pts = cloud(100 + i, centre);
            (
                spawn_model(&mut app, pts.clone(), centre + DVec3::splat(0.2), 9),
                pts,
            )
        })
        .collect();
    run_steps(&mut app, 300);
    for (e, pts) in es {
        let (rigid, shape, local, control) = state_of(&app, e);
        assert!(!control.frozen);
        let tess = Tessellation::new(9);
        let state = ModelState {
            translation: rigid.translation,
            rotation: rigid.rotation,
            shape: shape.into(),
            deformation: shape.deformation(),
            displacement: local.displacement,
        };
        let mut x = Vec::new();
        state.node_positions(&tess, &mut x);
        let res = residuals(&tess, &x, &pts);
        assert!(res.mean < 0.02, "model {e}: {res:?}");
    }
}

#[test]
fn global_shape_changed_from_outside_is_picked_up() {
    let mut app = app();
    let pts = superquadric_cloud(
        &SuperquadricParams::default(),
        DVec3::ZERO,
        DQuat::IDENTITY,
        500,
        0.0,
        9,
    );
    let e = spawn_model(&mut app, pts, DVec3::ZERO, 11);
    run_steps(&mut app, 400);
    let a_fit = app.world().get::<GlobalShape>(e).unwrap().a;
    assert!((a_fit - 1.0).abs() < 0.05, "fitted a = {a_fit}");
    // An inspector sets a = 1.5; the next step starts from there and moves back towards the data.
    app.world_mut().get_mut::<GlobalShape>(e).unwrap().a = 1.5;
    let steps = app.world().get::<SimControl>(e).unwrap().steps;
    run_steps(&mut app, steps + 1);
    let a = app.world().get::<GlobalShape>(e).unwrap().a;
    assert!(a < 1.5 && a > 1.2, "a = {a} after one step from 1.5");
}

#[test]
fn pause_single_step_and_reset() {
    let mut app = app();
    let e = spawn_model(
        &mut app,
        cloud(5, DVec3::ZERO),
        DVec3::new(0.3, 0.0, 0.0),
        9,
    );
    run_steps(&mut app, 1);
    let spawn = state_of(&app, e);
    run_steps(&mut app, 30);
    app.world_mut().get_mut::<SimControl>(e).unwrap().paused = true;
    app.update();
    let paused_at = state_hash(&app, e);
    let steps = app.world().get::<SimControl>(e).unwrap().steps;
    for _ in 0..10 {
        app.update();
    }
    assert_eq!(state_hash(&app, e), paused_at, "a paused model moved");
    app.world_mut()
        .get_mut::<SimControl>(e)
        .unwrap()
        .step_requests = 1;
    for _ in 0..10 {
        app.update();
    }
    assert_eq!(
        app.world().get::<SimControl>(e).unwrap().steps,
        steps + 1,
        "single step"
    );
    {
        let mut c = app.world_mut().get_mut::<SimControl>(e).unwrap();
        c.reset_requested = true;
        c.paused = false;
    }
    app.update();
    let (r, s, _, c) = state_of(&app, e);
    // After the reset the model stepped at most a couple of times from its spawn state.
    assert!(c.steps <= 3 && !c.reset_requested, "{c:?}");
    assert!((r.translation - spawn.0.translation).length() < 0.2);
    assert!((s.a - spawn.1.a).abs() < 0.2);
}

#[test]
fn a_state_made_non_finite_from_outside_freezes_the_model() {
    let mut app = app();
    let e = spawn_model(&mut app, cloud(6, DVec3::ZERO), DVec3::ZERO, 9);
    run_steps(&mut app, 5);
    app.world_mut()
        .get_mut::<RigidState>(e)
        .unwrap()
        .translation
        .x = f64::NAN;
    for _ in 0..5 {
        app.update();
    }
    let c = app.world().get::<SimControl>(e).unwrap();
    assert!(c.frozen);
    assert!(
        c.error.as_deref().unwrap_or("").contains("RigidState"),
        "{:?}",
        c.error
    );
    // Reset brings it back.
    app.world_mut()
        .get_mut::<SimControl>(e)
        .unwrap()
        .reset_requested = true;
    run_steps(&mut app, 3);
    let (r, _, _, c) = state_of(&app, e);
    assert!(!c.frozen && r.translation.is_finite());
}

/// What the plugin's messages said, collected each update.
#[derive(Resource, Default)]
struct Heard {
    fits: Vec<FitFinished>,
    frozen: Vec<ModelFrozen>,
}

fn listen(
    mut heard: ResMut<Heard>,
    mut fits: MessageReader<FitFinished>,
    mut frozen: MessageReader<ModelFrozen>,
) {
    heard.fits.extend(fits.read().copied());
    heard.frozen.extend(frozen.read().cloned());
}

#[test]
fn a_freeze_and_a_fit_to_convergence_are_each_reported_once() {
    let mut app = app();
    app.init_resource::<Heard>().add_systems(Update, listen);
    let frozen = spawn_model(&mut app, cloud(6, DVec3::ZERO), DVec3::ZERO, 9);
    let fitted = spawn_model(&mut app, cloud(7, DVec3::X * 4.0), DVec3::X * 4.1, 9);
    run_steps(&mut app, 3);
    app.world_mut()
        .get_mut::<RigidState>(frozen)
        .unwrap()
        .translation
        .y = f64::INFINITY;
    let options = bevy_deformable_sq::model::fit::FitOptions::default();
    app.world_mut()
        .entity_mut(fitted)
        .insert(FitDriver::to_convergence(options));
    // The fit runs on the async compute pool: update until it is reported.
    for _ in 0..100_000 {
        app.update();
        if !app.world().resource::<Heard>().fits.is_empty() {
            break;
        }
        std::thread::sleep(Duration::from_micros(200));
    }
    // A few more updates: neither event is sent again while nothing changes.
    for _ in 0..20 {
        app.update();
    }
    let heard = app.world().resource::<Heard>();
    assert_eq!(heard.frozen.len(), 1, "{:?}", heard.frozen);
    assert_eq!(heard.frozen[0].model, frozen);
    assert!(
        heard.frozen[0].error.contains("RigidState"),
        "{:?}",
        heard.frozen
    );
    assert_eq!(heard.fits.len(), 1, "{:?}", heard.fits);
    let fit = heard.fits[0];
    let control = app.world().get::<SimControl>(fitted).unwrap();
    assert!(
        fit.model == fitted && fit.at_rest && control.paused,
        "{fit:?} {control:?}"
    );
    let report = app.world().get::<FitDriver>(fitted).unwrap().report();
    assert_eq!(Some(fit.steps), report.map(|r| r.steps as u64));
    let (r, ..) = state_of(&app, fitted);
    assert!((r.translation - DVec3::X * 4.0).length() < 0.1, "{r:?}");
    // A reset clears the freeze; freezing again is reported again.
    app.world_mut()
        .get_mut::<SimControl>(frozen)
        .unwrap()
        .reset_requested = true;
    run_steps(&mut app, 2);
    app.world_mut()
        .get_mut::<LocalDofs>(frozen)
        .unwrap()
        .displacement[0]
        .x = f64::NAN;
    for _ in 0..5 {
        app.update();
    }
    let heard = app.world().resource::<Heard>();
    assert_eq!(heard.frozen.len(), 2, "{:?}", heard.frozen);
    assert!(
        heard.frozen[1].error.contains("LocalDofs"),
        "{:?}",
        heard.frozen
    );
}

#[cfg(feature = "serialize")]
#[test]
fn components_round_trip_through_serde() {
    let shape = GlobalShape {
        a: 1.25,
        a1: 0.3,
        a2: 1.0,
        a3: 0.7,
        e1: 0.45,
        e2: 1.7,
        taper: [0.25, -0.5],
        bend: [0.1, 0.0],
    };
    let rigid = RigidState {
        translation: DVec3::new(1.0, -2.5, 1e-9),
        rotation: DQuat::from_rotation_y(0.3),
    };
    let local = LocalDofs {
        displacement: vec![DVec3::new(0.1, 0.2, -0.3); 11],
    };
    let settings = ModelSettings {
        w0: 1e-6,
        reassign_every: 50,
        ..Default::default()
    };
    let json = serde_json::to_string(&(shape, rigid, &local, settings)).unwrap();
    let back: (GlobalShape, RigidState, LocalDofs, ModelSettings) =
        serde_json::from_str(&json).unwrap();
    assert_eq!(back, (shape, rigid, local, settings));
}

/// A mouse spring dragged a million units away: the anchor is held within MAX_STRETCH · a of the
/// grabbed point, so the pulled model follows steadily: no node moves more than a bounded
/// distance in a step, nothing goes non-finite, and the membrane deforms without tearing into a
/// spike (the spring constant is scaled to the membrane's stiffness).
#[test]
fn a_mouse_spring_dragged_far_away_pulls_the_model_without_blowing_up() {
    drag_far_away(false);
}

#[test]
fn a_model_with_mass_dragged_far_away_stays_finite_too() {
    // Issue 9: the second-order dynamics keep the simulation finite under any drag as well.
    drag_far_away(true);
}

/// A mouse spring on a model (first or second order) pulled towards a cursor a million units
/// away for 600 steps: no step moves a node more than 2, the membrane does not tear, and the
/// grabbed point follows steadily.
fn drag_far_away(with_mass: bool) {
    use bevy_deformable_sq::plugin::model_node_positions;
    let mut app = app();
    let e = app
        .world_mut()
        .spawn((
            GlobalShape {
                a: 0.8,
                ..default()
            },
            RigidState::default(),
            FemMesh::new(15),
        ))
        .id();
    if with_mass {
        app.world_mut().entity_mut(e).insert(Inertia::default());
    }
    run_steps(&mut app, 1);
    let (tess, x0) = {
        let w = app.world();
        let tess = w.get::<FemMesh>(e).unwrap().get().unwrap().clone();
        (tess, model_node_positions(w, e).unwrap())
    };
    let hit = DVec3::new(0.8, 0.0, 0.0);
    let settings = *app.world().get::<ModelSettings>(e).unwrap();
    let spring = Spring::grab(&tess, &x0, hit, Spring::mouse_stiffness(&settings, 0.8)).unwrap();
    assert!(
        (spring.anchor - hit).length() < 0.2,
        "grabbed far from the press"
    );
    app.world_mut()
        .entity_mut(e)
        .insert(SpringForces(vec![spring]));
    let target = DVec3::new(1e6, 0.0, 0.0);
    let mut before = x0;
    let mut grabbed_x = Vec::new();
    for _ in 0..600 {
        {
            let x = model_node_positions(app.world(), e).unwrap();
            let mut entity = app.world_mut().entity_mut(e);
            let mut springs = entity.get_mut::<SpringForces>().unwrap();
            springs.0[0].pull_towards(&tess, &x, target, 0.8);
            let at = tess
                .locate(springs.0[0].u, springs.0[0].v)
                .interpolate(|k| x[k]);
            assert!((springs.0[0].anchor - at).length() <= Spring::MAX_STRETCH * 0.8 + 1e-9);
            grabbed_x.push(at.x);
        }
        app.update();
        let w = app.world();
        let c = w.get::<SimControl>(e).unwrap();
        assert!(!c.frozen, "{:?}", c.error);
        let after = model_node_positions(w, e).unwrap();
        let motion = before
            .iter()
            .zip(&after)
            .map(|(p, q)| p.distance(*q))
            .fold(0.0, f64::max);
        assert!(
            motion.is_finite() && motion < 2.0,
            "a step moved a node by {motion}"
        );
        before = after;
    }
    let local = app.world().get::<LocalDofs>(e).unwrap();
    let spike = local
        .displacement
        .iter()
        .map(|d| d.length())
        .fold(0.0, f64::max);
    assert!(spike > 1e-3, "the spring did not deform the membrane");
    assert!(spike < 2.0, "the membrane tore into a spike of {spike}");
    // The grabbed point follows the cursor, steadily.
    assert!(grabbed_x.last().unwrap() > &10.0, "{:?}", grabbed_x.last());
    assert!(grabbed_x.windows(2).filter(|w| w[1] < w[0] - 1e-9).count() < 10);
}

#[test]
fn a_model_with_inertia_keeps_moving_swings_on_a_spring_and_resets_to_rest() {
    // Second-order dynamics through the plugin: a model given a velocity and no force coasts
    // (a first-order model would stay put); pulled by a spring it swings past the anchor and
    // settles there; reset brings it back at rest.
    let mut app = app();
    let settings = ModelSettings {
        dt: 0.01,
        global_only: true,
        ..Default::default()
    };
    let mut inertia = Inertia::default();
    inertia.velocity.linear = DVec3::new(1.0, 0.0, 0.0);
    let coasting = app
        .world_mut()
        .spawn((
            start_shape(),
            RigidState::default(),
            settings,
            inertia,
            FemMesh::new(9),
        ))
        .id();
    let still = app
        .world_mut()
        .spawn((
            start_shape(),
            RigidState::default(),
            settings,
            FemMesh::new(9),
        ))
        .id();
    run_steps(&mut app, 100);
    let steps = app.world().get::<SimControl>(coasting).unwrap().steps as f64;
    let x = app.world().get::<RigidState>(coasting).unwrap().translation;
    // Undamped it would move 1 × t; the default damping (β = 0.5) slows it as e^(−βt).
    let t = steps * 0.01;
    let expected = (1.0 - (-0.5 * t).exp()) / 0.5;
    assert!(
        (x.x - expected).abs() < 0.02 * expected,
        "coasted {x}, expected {expected}"
    );
    assert_eq!(
        app.world().get::<RigidState>(still).unwrap().translation,
        DVec3::ZERO
    );

    // A spring on the north pole towards (0, 0, 3): the pole swings past it and settles.
    let anchor = DVec3::new(0.0, 0.0, 3.0);
    let pulled = app
        .world_mut()
        .spawn((
            start_shape(),
            RigidState::default(),
            ModelSettings {
                dt: 0.02,
                ..settings
            },
            Inertia::default(),
            FemMesh::new(9),
            SpringForces(vec![Spring {
                u: std::f64::consts::FRAC_PI_2,
                v: 0.0,
                anchor,
                stiffness: 4.0,
                reshape: true,
            }]),
        ))
        .id();
    let (mut closest, mut swing_back) = (f64::INFINITY, 0.0_f64);
    for _ in 0..1500 {
        app.update();
        let d = (pole_of(&app, pulled) - anchor).length();
        closest = closest.min(d);
        swing_back = swing_back.max(d - closest);
    }
    assert!(swing_back > 0.1, "never overshot: {swing_back}");
    // The spring also stretches the shape (K_ss = 0): the pole is where it settles.
    let off = (pole_of(&app, pulled) - anchor).length();
    assert!(off < 0.02, "came to rest {off} off");
    assert!(!app.world().get::<SimControl>(pulled).unwrap().frozen);

    app.world_mut()
        .get_mut::<SimControl>(coasting)
        .unwrap()
        .reset_requested = true;
    app.update();
    app.update();
    let v = &app.world().get::<Inertia>(coasting).unwrap().velocity;
    assert!(v.linear.length() < 1e-12, "after reset {v:?}");
    // A new mesh starts the model at rest too: the old nodes' rates mean nothing on it.
    app.world_mut()
        .get_mut::<Inertia>(coasting)
        .unwrap()
        .velocity
        .linear = DVec3::X;
    app.world_mut().get_mut::<FemMesh>(coasting).unwrap().k = 7;
    app.update();
    app.update();
    let v = &app.world().get::<Inertia>(coasting).unwrap().velocity;
    assert_eq!(v.local.len(), 7 * 7 + 2);
    assert!(v.linear.length() < 1e-12, "after re-tessellation {v:?}");
}

#[test]
fn a_new_mesh_carries_the_membrane_and_the_state_a_reset_returns_to() {
    // A membrane displaced by d everywhere, paused: after k changes it is d on every node of the
    // new mesh (the interpolation of a constant), and a reset goes back to d on that mesh too.
    let mut app = app();
    let d = DVec3::new(0.02, -0.01, 0.03);
    let e = app
        .world_mut()
        .spawn((
            start_shape(),
            RigidState::default(),
            FemMesh::new(9),
            LocalDofs {
                displacement: vec![d; 9 * 9 + 2],
            },
            SimControl {
                paused: true,
                ..default()
            },
        ))
        .id();
    // (The first update runs no fixed step.)
    let updates = |app: &mut App| (0..3).for_each(|_| app.update());
    updates(&mut app);
    assert!(app.world().get::<FemMesh>(e).unwrap().get().is_some());
    app.world_mut()
        .get_mut::<LocalDofs>(e)
        .unwrap()
        .displacement[0] = DVec3::ONE;
    app.world_mut().get_mut::<FemMesh>(e).unwrap().k = 14;
    updates(&mut app);
    let carried = &app.world().get::<LocalDofs>(e).unwrap().displacement;
    assert_eq!(carried.len(), 14 * 14 + 2);
    // Node 0 is a pole on both meshes: it keeps its own displacement.
    assert_eq!(carried[0], DVec3::ONE);
    let moved = carried
        .iter()
        .filter(|&&c| (c - d).length() > 1e-12)
        .count();
    assert!(
        moved > 0 && moved < carried.len() / 4,
        "{moved} nodes off d"
    );
    app.world_mut()
        .get_mut::<SimControl>(e)
        .unwrap()
        .reset_requested = true;
    updates(&mut app);
    let reset = &app.world().get::<LocalDofs>(e).unwrap().displacement;
    assert_eq!(reset.len(), 14 * 14 + 2);
    assert!(reset.iter().all(|&r| (r - d).length() < 1e-12), "{reset:?}");
}

/// The north pole of a global-only model: c + R (0, 0, a·a3).
fn pole_of(app: &App, e: Entity) -> DVec3 {
    let (rigid, shape, _, _) = state_of(app, e);
    rigid.translation + rigid.rotation * DVec3::new(0.0, 0.0, shape.a * shape.a3)
}

#[test]
fn a_joint_keeps_a_pulled_part_attached_to_another() {
    // Two balls touching at x = 0, jointed there; a spring pulls the right ball's far side
    // further right. Without the joint the right ball leaves the left one behind; with it the
    // joint's ends stay together (the right ball, whose shape has no stiffness, partly stretches
    // instead of dragging the left one: K_ss = 0, the paper's choice).
    let end_a = JointEnd { u: 0.0, v: 0.0 };
    let end_b = JointEnd {
        u: 0.0,
        v: std::f64::consts::PI,
    };
    let run = |jointed: bool| {
        let mut app = app();
        let settings = ModelSettings {
            global_only: true,
            ..Default::default()
        };
        let spawn = |app: &mut App, x: f64| {
            app.world_mut()
                .spawn((
                    GlobalShape {
                        a: 0.5,
                        ..start_shape()
                    },
                    RigidState {
                        translation: DVec3::new(x, 0.0, 0.0),
                        rotation: DQuat::IDENTITY,
                    },
                    settings,
                    FemMesh::new(9),
                ))
                .id()
        };
        let (left, right) = (spawn(&mut app, -0.5), spawn(&mut app, 0.5));
        app.world_mut()
            .entity_mut(right)
            .insert(SpringForces(vec![Spring {
                u: 0.0,
                v: 0.0,
                anchor: DVec3::new(3.0, 0.0, 0.0),
                stiffness: 1.0,
                reshape: true,
            }]));
        if jointed {
            app.world_mut()
                .spawn(PartJoint::new(left, end_a, right, end_b));
        }
        run_steps(&mut app, 300);
        let tess = Tessellation::new(9);
        let end = |e, end: JointEnd| {
            let (rigid, shape, local, _) = state_of(&app, e);
            let mut x = Vec::new();
            bevy_deformable_sq::plugin::world_positions(&tess, &rigid, &shape, &local, &mut x);
            end.position(&tess, &x)
        };
        let moved = state_of(&app, right).0.translation.x - 0.5;
        ((end(right, end_b) - end(left, end_a)).length(), moved)
    };
    let (apart, moved) = run(false);
    assert!(
        moved > 0.3 && apart > 0.3,
        "unjointed: ends {apart} apart, moved {moved}"
    );
    let (together, moved) = run(true);
    assert!(moved > 0.3, "the pulled ball moved {moved}");
    assert!(together < 1e-3, "the joint opened by {together}");
}

/// Every schedule the plugins add systems to, built with ambiguity detection as an error: no two
/// of the crate's systems touch the same data in an undefined order.
#[test]
fn the_plugins_systems_have_no_ambiguities() {
    use bevy::ecs::schedule::{LogLevel, ScheduleBuildSettings, ScheduleLabel};
    let mut app = App::new();
    app.add_plugins((
        MinimalPlugins,
        bevy::asset::AssetPlugin::default(),
        DeformableSqPlugins::in_schedule(Update),
    ));
    for label in [Update.intern(), PreUpdate.intern(), PostUpdate.intern()] {
        app.edit_schedule(label, |s| {
            s.set_build_settings(ScheduleBuildSettings {
                ambiguity_detection: LogLevel::Error,
                ..default()
            });
        });
    }
    let points = superquadric_cloud(
        &SuperquadricParams::default(),
        DVec3::ZERO,
        DQuat::IDENTITY,
        300,
        0.0,
        3,
    );
    app.world_mut().spawn((
        GlobalShape::default(),
        RigidState::default(),
        RangeData::new(points),
    ));
    // A schedule with an ambiguity fails to build, and `update` panics.
    for _ in 0..3 {
        app.update();
    }
    let mut q = app.world_mut().query::<&SimControl>();
    assert!(q.iter(app.world()).all(|c| c.steps == 3 && !c.frozen));
}

/// A press on a model through Bevy picking attaches a mouse spring, a drag-free release removes
/// it, and no press grabs while the mouse springs are switched off.
#[cfg(feature = "picking")]
#[test]
fn a_press_grabs_a_model_with_a_mouse_spring_and_a_release_lets_go() {
    use bevy::camera::NormalizedRenderTarget;
    use bevy::picking::backend::HitData;
    use bevy::picking::events::{Pointer, Press, Release};
    use bevy::picking::pointer::{Location, PointerButton, PointerId};
    let mut app = app();
    app.add_plugins(MouseSpringPlugin);
    let model = app
        .world_mut()
        .spawn((GlobalShape::default(), RigidState::default()))
        .id();
    run_steps(&mut app, 1);
    let location = Location {
        target: NormalizedRenderTarget::None {
            width: 64,
            height: 64,
        },
        position: Vec2::ZERO,
    };
    // The unit sphere's point on +x.
    let hit = HitData::new(Entity::PLACEHOLDER, 1.0, Some(Vec3::X), None);
    let press = |button| {
        Pointer::new(
            PointerId::Mouse,
            location.clone(),
            Press {
                button,
                hit: hit.clone(),
                count: 1,
            },
            model,
        )
    };
    let springs = |app: &App| {
        app.world()
            .get::<SpringForces>(model)
            .map_or(0, |s| s.0.len())
    };
    // Only the primary button grabs.
    app.world_mut().trigger(press(PointerButton::Secondary));
    assert_eq!(app.world().resource::<MouseSpring>().model, None);
    app.world_mut().trigger(press(PointerButton::Primary));
    app.world_mut().flush();
    let mouse = *app.world().resource::<MouseSpring>();
    assert_eq!(mouse.model, Some(model));
    assert_eq!(springs(&app), 1);
    let spring = app.world().get::<SpringForces>(model).unwrap().0[0];
    assert!(spring.stiffness > 0.0 && spring.anchor.distance(DVec3::X) < 0.2);
    let messages = app.world().resource::<Messages<ModelGrabbed>>();
    assert_eq!(messages.len(), 1);
    app.world_mut().trigger(Pointer::new(
        PointerId::Mouse,
        location.clone(),
        Release {
            button: PointerButton::Primary,
            hit: hit.clone(),
        },
        model,
    ));
    assert_eq!(app.world().resource::<MouseSpring>().model, None);
    assert_eq!(springs(&app), 0);
    // Switched off, a press does nothing.
    app.world_mut()
        .resource_mut::<MouseSpringSettings>()
        .enabled = false;
    app.world_mut().trigger(press(PointerButton::Primary));
    app.world_mut().flush();
    assert_eq!(app.world().resource::<MouseSpring>().model, None);
    assert_eq!(springs(&app), 0);
}

#[test]
fn a_depth_track_moves_its_model_as_the_library_tracker_does_bit_for_bit() {
    use bevy_deformable_sq::model::track::{Frame, TrackOptions, Tracker};
    use bevy_deformable_sq::synthetic::{depth_video, tracking_recipe};
    let mut recipe = tracking_recipe(0);
    recipe.frames = 6;
    let video = depth_video(&recipe);
    let frames: Vec<Frame> = (0..6).map(|i| Frame::Depth(video.depth_frame(i))).collect();
    let start = video.truth[0];
    let mut app = app();
    let track = DepthTrack::new(frames.clone(), start, TrackOptions::default()).unwrap();
    let model = app
        .world_mut()
        .spawn((
            GlobalShape::from(start.shape),
            RigidState {
                translation: start.translation,
                rotation: start.rotation,
            },
            track,
        ))
        .id();
    // Pausing and stepping: no frame while paused, one per request.
    app.world_mut()
        .get_mut::<DepthTrack>(model)
        .unwrap()
        .playing = false;
    for _ in 0..8 {
        app.update();
    }
    assert_eq!(
        app.world().get::<DepthTrack>(model).unwrap().next_frame(),
        0
    );
    app.world_mut()
        .get_mut::<DepthTrack>(model)
        .unwrap()
        .step_requests = 1;
    for _ in 0..8 {
        app.update();
    }
    assert_eq!(
        app.world().get::<DepthTrack>(model).unwrap().next_frame(),
        1
    );
    app.world_mut()
        .get_mut::<DepthTrack>(model)
        .unwrap()
        .playing = true;
    for _ in 0..64 {
        app.update();
        if app.world().get::<DepthTrack>(model).unwrap().finished() {
            break;
        }
    }
    assert!(app.world().get::<DepthTrack>(model).unwrap().finished());
    assert!(app.world().get::<SimControl>(model).unwrap().paused);
    let mut tracker = Tracker::new(start, TrackOptions::default()).unwrap();
    let last = frames.iter().map(|f| tracker.step(f)).last().unwrap();
    let rigid = app.world().get::<RigidState>(model).unwrap();
    assert_eq!(rigid.translation, last.pose.translation);
    assert_eq!(rigid.rotation, last.pose.rotation);
    let shape = app.world().get::<GlobalShape>(model).unwrap();
    assert_eq!(SuperquadricParams::from(*shape), last.pose.shape);
    assert!((rigid.translation - video.truth[5].translation).length() < 2e-3);
}
