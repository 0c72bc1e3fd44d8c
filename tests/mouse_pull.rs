//! A mouse pull that a person can steer (the sandbox's cylinder): dragged 1.0 sideways from a
//! surface point over 60 steps and released for 120, the model follows the drag and keeps its
//! shape; the membrane's dent relaxes.

use bevy::prelude::*;
use bevy_deformable_sq::plugin::model_node_positions;
use bevy_deformable_sq::prelude::*;
use glam::DVec3;

/// What the pull did: the centroid's motion, the largest semi-axis ratio, the ε changes, the
/// largest local displacement (over a) at the release and at the end, how far the centroid moved
/// over the last 60 steps, and whether everything stayed finite.
#[derive(Debug)]
struct Pull {
    moved: DVec3,
    axes_ratio: f64,
    d_eps: [f64; 2],
    dent_at_release: f64,
    dent: f64,
    drift: f64,
    finite: bool,
}

/// The largest local displacement of model `e`, over its scale a.
fn dent(app: &App, e: Entity) -> f64 {
    let w = app.world();
    let a = w.get::<GlobalShape>(e).unwrap().a;
    let local = w.get::<LocalDofs>(e).unwrap();
    local
        .displacement
        .iter()
        .map(|d| d.length())
        .fold(0.0, f64::max)
        / a
}

/// The gesture: the cylinder's side grabbed at mid-height and dragged 1.0 sideways over
/// 60 steps, then released for 120 steps; `reshape`: the paper's pull instead of a grab.
fn pull(reshape: bool) -> Pull {
    let mut app = App::new();
    app.add_plugins((MinimalPlugins, DeformableSqPlugin::in_schedule(Update)));
    // The sandbox's cylinder (assets/scenes/sandbox.dsq.ron): semi-axes 0.36, 0.36, 0.6.
    let shape = GlobalShape {
        a: 0.6,
        a1: 0.6,
        a2: 0.6,
        a3: 1.0,
        e1: 0.2,
        e2: 1.0,
        ..default()
    };
    let e = app
        .world_mut()
        .spawn((shape, RigidState::default(), FemMesh::new(31)))
        .id();
    app.update();
    let tess = app
        .world()
        .get::<FemMesh>(e)
        .unwrap()
        .get()
        .unwrap()
        .clone();
    let x0 = model_node_positions(app.world(), e).unwrap();
    let centroid = |x: &[DVec3]| x.iter().sum::<DVec3>() / x.len() as f64;
    let c0 = centroid(&x0);
    let settings = *app.world().get::<ModelSettings>(e).unwrap();
    // Grab the side at mid-height and drag it sideways (along y), 1.0 over 60 steps.
    let hit = DVec3::new(0.36, 0.0, 0.0);
    let mut spring =
        Spring::grab(&tess, &x0, hit, Spring::mouse_stiffness(&settings, 0.6)).unwrap();
    spring.reshape = reshape;
    app.world_mut()
        .entity_mut(e)
        .insert(SpringForces(vec![spring]));
    for s in 1..=60 {
        let x = model_node_positions(app.world(), e).unwrap();
        let target = hit + DVec3::new(0.0, s as f64 / 60.0, 0.0);
        let mut entity = app.world_mut().entity_mut(e);
        let mut springs = entity.get_mut::<SpringForces>().unwrap();
        springs.0[0].pull_towards(&tess, &x, target, 0.6);
        app.update();
    }
    app.world_mut().entity_mut(e).remove::<SpringForces>();
    let dent_at_release = dent(&app, e);
    let mut c_before = DVec3::ZERO;
    for s in 0..120 {
        if s == 60 {
            c_before = centroid(&model_node_positions(app.world(), e).unwrap());
        }
        app.update();
    }
    let w = app.world();
    let x = model_node_positions(w, e).unwrap();
    let s = w.get::<GlobalShape>(e).unwrap();
    let before = [0.36, 0.36, 0.6];
    let after = [s.a * s.a1, s.a * s.a2, s.a * s.a3];
    let axes_ratio = (0..3)
        .map(|i| (after[i] / before[i]).max(before[i] / after[i]))
        .fold(0.0, f64::max);
    Pull {
        moved: centroid(&x) - c0,
        axes_ratio,
        d_eps: [(s.e1 - 0.2).abs(), (s.e2 - 1.0).abs()],
        dent_at_release,
        dent: dent(&app, e),
        drift: centroid(&x).distance(c_before),
        finite: x.iter().all(|p| p.is_finite()),
    }
}

#[test]
fn a_sideways_grab_carries_the_cylinder_and_keeps_its_shape() {
    let p = pull(false);
    assert!(p.finite, "{p:?}");
    // The model follows the drag (at least half of it) and keeps its shape.
    assert!(p.moved.y >= 0.5, "{p:?}");
    assert!(p.axes_ratio <= 1.5, "{p:?}");
    assert!(p.d_eps[0] <= 0.2 && p.d_eps[1] <= 0.2, "{p:?}");
    // It dents where it was pulled; released, the dent relaxes and nothing runs on.
    assert!(p.dent_at_release > 0.01, "{p:?}");
    assert!(p.dent < 0.25 * p.dent_at_release, "{p:?}");
    assert!(p.drift < 0.01, "{p:?}");
}

#[test]
fn with_reshape_the_pull_is_the_papers_and_moves_the_global_shape() {
    // The paper's Fig. 1 spring acts on every DOF: the same gesture stretches the cylinder.
    let p = pull(true);
    assert!(p.finite, "{p:?}");
    assert!(p.axes_ratio > 1.5, "{p:?}");
    assert!(p.drift < 0.01, "{p:?}");
}
