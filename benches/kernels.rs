//! Benchmarks of the kernels and of whole fits (issue: speed). Run with
//! `cargo bench --bench kernels`; figures and targets are in BENCHMARKS.md.

use bevy::math::{DQuat, DVec3};
use bevy::prelude::*;
use bevy::time::TimeUpdateStrategy;
use bevy_deformable_sq::io::load_points;
use bevy_deformable_sq::model::dynamics::{
    DynamicsParams, ModelState, NodalForces, Workspace, step_prepared,
};
use bevy_deformable_sq::model::fem::Tessellation;
use bevy_deformable_sq::model::fit::{FitOptions, fit};
use bevy_deformable_sq::model::forces::range::{InfluenceMode, RangeForces, nearest_indices};
use bevy_deformable_sq::model::superquadric::SuperquadricParams;
use bevy_deformable_sq::prelude::*;
use bevy_deformable_sq::synthetic::superquadric_cloud;
use criterion::{BenchmarkId, Criterion, criterion_group, criterion_main};
use std::hint::black_box;
use std::path::Path;
use std::time::Duration;

fn target() -> SuperquadricParams {
    SuperquadricParams {
        a: 1.2,
        a1: 0.8,
        a2: 0.6,
        a3: 1.0,
        e1: 0.7,
        e2: 1.2,
    }
}

/// A model on k rings with m attached points, ready to step.
fn attached(k: usize, m: usize) -> (Tessellation, ModelState, RangeForces) {
    let tess = Tessellation::new(k);
    let state = ModelState::new(
        &tess,
        DVec3::new(0.05, 0.0, 0.0),
        DQuat::IDENTITY,
        SuperquadricParams::default(),
    );
    let mut range = RangeForces::new(
        superquadric_cloud(&target(), DVec3::ZERO, DQuat::IDENTITY, m, 0.01, 7),
        4.0,
        InfluenceMode::NearestNode,
    );
    let mut x = Vec::new();
    state.node_positions(&tess, &mut x);
    range.reassign(&tess, &x);
    (tess, state, range)
}

/// One simulation step as the fitter takes it: node positions, spring forces, generalized forces
/// and the Euler update.
fn step_once(
    tess: &Tessellation,
    state: &mut ModelState,
    range: &RangeForces,
    forces: &mut NodalForces,
    ws: &mut Workspace,
    params: &DynamicsParams,
) {
    forces.clear(tess.node_count());
    range.accumulate(tess, ws.prepare(tess, state), forces);
    step_prepared(tess, state, forces, params, ws).expect("finite");
}

fn euler_step(c: &mut Criterion) {
    let mut g = c.benchmark_group("euler_step");
    for (k, m) in [(71, 5000), (31, 1000), (100, 10_000), (316, 100_000)] {
        let (tess, state, range) = attached(k, m);
        let params = DynamicsParams {
            dt: 0.01,
            ..Default::default()
        };
        let (mut forces, mut ws) = (NodalForces::new(tess.node_count()), Workspace::default());
        let mut s = state.clone();
        g.bench_with_input(
            BenchmarkId::new("nodes_points", format!("{}n_{m}p", tess.node_count())),
            &(),
            |b, _| {
                b.iter(|| {
                    step_once(&tess, &mut s, &range, &mut forces, &mut ws, &params);
                    // Keep the state near the start so every iteration does the same work.
                    if s.displacement[0].length() > 1.0 {
                        s = state.clone();
                    }
                })
            },
        );
    }
    g.finish();
}

fn reassignment(c: &mut Criterion) {
    let mut g = c.benchmark_group("reassignment");
    g.sample_size(10);
    for (k, m) in [(141, 100_000), (31, 1000), (100, 10_000)] {
        let tess = Tessellation::new(k);
        let state = ModelState::new(&tess, DVec3::ZERO, DQuat::IDENTITY, target());
        let mut x = Vec::new();
        state.node_positions(&tess, &mut x);
        let points = superquadric_cloud(&target(), DVec3::ZERO, DQuat::IDENTITY, m, 0.02, 3);
        g.bench_with_input(
            BenchmarkId::new("points_vs_nodes", format!("{m}p_{}n", tess.node_count())),
            &(),
            |b, _| b.iter(|| black_box(nearest_indices(&x, &points))),
        );
    }
    g.finish();
}

fn ems_fits(c: &mut Criterion) {
    let mut g = c.benchmark_group("ems_fit");
    g.sample_size(10).measurement_time(Duration::from_secs(10));
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("assets/data/ems");
    for name in [
        "noisy_pointCloud_example_1",
        "noisy_pointCloud_example_2",
        "noisy_pointCloud_example_3",
        "partial_pointCloud_example_1",
        "partial_pointCloud_example_2",
        "partial_pointCloud_example_3",
    ] {
        let points = load_points(&dir.join(format!("{name}.ply"))).expect("shipped cloud");
        for global_only in [true, false] {
            let opts = FitOptions {
                global_only,
                ..Default::default()
            };
            let mode = if global_only { "global" } else { "local" };
            g.bench_with_input(BenchmarkId::new(mode, name), &(), |b, _| {
                b.iter(|| black_box(fit(&points, &opts, |_| {}).expect("fit")))
            });
        }
    }
    g.finish();
}

/// Eleven 963-node models in one headless app, one FixedUpdate step each per update (range
/// springs on 500 points each; image forces are not implemented yet).
fn app_step(c: &mut Criterion) {
    let mut app = App::new();
    app.add_plugins((MinimalPlugins, DeformableSqPlugin::in_schedule(Update)));
    app.insert_resource(TimeUpdateStrategy::ManualDuration(Duration::from_millis(
        16,
    )));
    for i in 0..11 {
        let centre = DVec3::new(i as f64 * 3.0, 0.0, 0.0);
        let pts = superquadric_cloud(&target(), centre, DQuat::IDENTITY, 500, 0.01, i);
        app.world_mut().spawn((
            GlobalShape::default(),
            RigidState {
                translation: centre,
                rotation: DQuat::IDENTITY,
            },
            RangeData::new(pts),
        ));
    }
    app.update();
    c.bench_function("app_step/11_models_963_nodes", |b| b.iter(|| app.update()));
}

criterion_group!(benches, euler_step, reassignment, app_step, ems_fits);
criterion_main!(benches);
