//! Benchmarks of the kernels and of whole fits (issue: speed). Run with
//! `cargo bench --bench kernels`; figures and targets are in BENCHMARKS.md.

use bevy_deformable_sq::io::{load_luminance, load_points};
use bevy_deformable_sq::model::dynamics::{
    DynamicsParams, ModelState, NodalForces, Workspace, step_prepared,
};
use bevy_deformable_sq::model::fem::Tessellation;
use bevy_deformable_sq::model::fit::{FitOptions, fit, fit_residuals, residuals};
use bevy_deformable_sq::model::forces::image::{ImageFrame, ImagePotential, ImageScratch};
use bevy_deformable_sq::model::forces::range::{
    InfluenceMode, QueryOrder, RangeForces, nearest_indices,
};
use bevy_deformable_sq::model::image_fit::PartAxes;
use bevy_deformable_sq::model::inertia::{
    InertiaParams, InertiaWorkspace, Velocity, step as inertia_step,
};
use bevy_deformable_sq::model::superquadric::SuperquadricParams;
use bevy_deformable_sq::synthetic::superquadric_cloud;
use bevy_deformable_sq::synthetic::{ImageExperiment, doll_experiment};
use criterion::{BenchmarkId, Criterion, criterion_group, criterion_main};
use glam::{DQuat, DVec3};
use std::alloc::{GlobalAlloc, Layout, System};
use std::hint::black_box;
use std::path::Path;
use std::sync::Arc;
use std::sync::atomic::{AtomicUsize, Ordering};
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
    let explicit = [(71, 5000), (31, 1000), (100, 10_000), (316, 100_000)].map(|c| (c, false));
    // The implicit membrane (`DynamicsParams::implicit_local`) with a fitter's γ_d = 0.01.
    let implicit = [(71, 5000), (31, 1000)].map(|c| (c, true));
    for ((k, m), implicit_local) in explicit.into_iter().chain(implicit) {
        let (tess, state, range) = attached(k, m);
        let params = DynamicsParams {
            dt: 0.01,
            implicit_local,
            gamma_local: if implicit_local { 0.01 } else { 1.0 },
            ..Default::default()
        };
        let name = if implicit_local {
            "implicit_local"
        } else {
            "nodes_points"
        };
        let (mut forces, mut ws) = (NodalForces::new(tess.node_count()), Workspace::default());
        let mut s = state.clone();
        g.bench_with_input(
            BenchmarkId::new(name, format!("{}n_{m}p", tess.node_count())),
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
        let name = format!("{m}p_{}n", tess.node_count());
        // As a fit reassigns: its points, fixed, searched in the order `RangeForces` keeps.
        let order = QueryOrder::new(&points);
        g.bench_with_input(BenchmarkId::new("points_vs_nodes", &name), &(), |b, _| {
            b.iter(|| black_box(order.nearest_indices(&x)))
        });
        // The same search in the points' given (random) order, and the one-time ordering.
        g.bench_with_input(BenchmarkId::new("unordered", &name), &(), |b, _| {
            b.iter(|| black_box(nearest_indices(&x, &points)))
        });
        g.bench_with_input(
            BenchmarkId::new("query_order", format!("{m}p")),
            &(),
            |b, _| b.iter(|| black_box(QueryOrder::new(&points))),
        );
    }
    g.finish();
}

/// The refining stage's migration ([`RangeForces::migrate`] on the continuous superquadric,
/// `fit::REFINE_RATE`): every point of influence evaluated on x(u) with its tangents, moved the
/// Gauss–Newton way and evaluated at the trial. The model alternates between two shapes a few
/// per cent apart, so that every iteration's two migrations move the points as a fit's steps do
/// (a model at rest would leave them at their feet, the cheap path).
fn migration(c: &mut Criterion) {
    let mut g = c.benchmark_group("migration");
    g.sample_size(20);
    for m in [1000, 6000] {
        let (tess, state, mut range) = attached(31, m);
        range.mode = InfluenceMode::Migrating { rate: 1.0 };
        let mut other = state.clone();
        other.shape.a *= 1.03;
        other.shape.e1 += 0.02;
        other.translation.y += 0.01;
        let (mut xa, mut xb) = (Vec::new(), Vec::new());
        state.node_positions(&tess, &mut xa);
        other.node_positions(&tess, &mut xb);
        let (sa, sb) = (state.surface(), other.surface());
        g.bench_with_input(
            BenchmarkId::new("surface_two_steps", format!("{m}p_{}n", tess.node_count())),
            &(),
            |b, _| {
                b.iter(|| {
                    range.migrate(&tess, &xa, Some(&sa));
                    range.migrate(&tess, &xb, Some(&sb));
                })
            },
        );
    }
    g.finish();
}

/// What measuring a pure superquadric's residuals costs a fit (`fit::fit_residuals`: each point's
/// closest surface point, `model::distance`), against its 963-node mesh.
fn residuals_of_a_fit(c: &mut Criterion) {
    let mut g = c.benchmark_group("fit_residuals");
    g.sample_size(10);
    let tess = Tessellation::new(31);
    let state = ModelState::new(&tess, DVec3::ZERO, DQuat::IDENTITY, target());
    for m in [1000, 6000] {
        let points = superquadric_cloud(&target(), DVec3::ZERO, DQuat::IDENTITY, m, 0.02, 3);
        g.bench_with_input(
            BenchmarkId::new("pure_exact", format!("{m}p")),
            &(),
            |b, _| b.iter(|| black_box(fit_residuals(&tess, &state, &points))),
        );
        let mut x = Vec::new();
        state.node_positions(&tess, &mut x);
        g.bench_with_input(
            BenchmarkId::new("mesh_963n", format!("{m}p")),
            &(),
            |b, _| b.iter(|| black_box(residuals(&tess, &x, &points))),
        );
    }
    g.finish();
}

fn ems_fits(c: &mut Criterion) {
    let mut g = c.benchmark_group("ems_fit");
    g.sample_size(10).measurement_time(Duration::from_secs(10));
    // EMS's clouds stay beside the crate, never in it: the group is skipped without them.
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/data/ems/single_superquadric");
    if !dir.is_dir() {
        eprintln!("ems_fit skipped: {} not found", dir.display());
        return;
    }
    for name in [
        "noisy_pointCloud_example_1",
        "noisy_pointCloud_example_2",
        "noisy_pointCloud_example_3",
        "partial_pointCloud_example_1",
        "partial_pointCloud_example_2",
        "partial_pointCloud_example_3",
    ] {
        let points = load_points(&dir.join(format!("{name}.ply"))).expect("EMS's cloud");
        for (mode, global_only, defaults) in [
            ("global", true, false),
            ("local", false, false),
            ("global_defaults", true, true),
            ("local_defaults", false, true),
        ] {
            // The paper's forces and stiffness (`dsq fit --paper-forces`), or the command-line
            // fitter's defaults for a cloud (`fit`).
            let paper = FitOptions {
                global_only,
                ..Default::default()
            };
            // The noise estimate is part of the timed fit, as it is of the command line's.
            let opts = || match (defaults, global_only) {
                (false, _) => paper,
                (true, true) => paper.for_data(),
                (true, false) => paper.for_data().with_stiffness_from_noise(&points).0,
            };
            g.bench_with_input(BenchmarkId::new(mode, name), &(), |b, _| {
                b.iter(|| black_box(fit(&points, &opts(), |_| {}).expect("fit")))
            });
        }
    }
    g.finish();
}

/// The doll experiment's image potential and its 11 parts placed from their four points each, as
/// the sandbox's load and the image-force kernel start from.
fn doll_parts() -> (
    ImageExperiment,
    Arc<ImagePotential>,
    Vec<(DVec3, DQuat, SuperquadricParams)>,
) {
    let e = doll_experiment();
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join(e.image);
    let (w, h, lum) = load_luminance(&path).expect("shipped image");
    let potential = Arc::new(
        ImagePotential::new(w, h, lum, e.sigma, ImageFrame::default()).expect("potential"),
    );
    let poses = e
        .parts
        .iter()
        .map(|(_, pts)| {
            PartAxes::from_points(&potential, *pts)
                .expect("placement")
                .pose()
        })
        .collect();
    (e, potential, poses)
}

/// The benchmarks of whole app steps, through the plugin (feature `bevy`).
#[cfg(feature = "bevy")]
mod app {
    use super::*;
    use bevy::prelude::*;
    use bevy::time::TimeUpdateStrategy;
    use bevy_deformable_sq::prelude::*;

    /// A headless app, one `update` = one simulation step of every model (models spread over the
    /// cores by the plugin's parallel systems).
    fn headless_app() -> App {
        let mut app = App::new();
        app.add_plugins((
            MinimalPlugins.set(TaskPoolPlugin {
                task_pool_options: simulation_task_pools(),
            }),
            DeformableSqPlugin::in_schedule(Update),
        ));
        app.insert_resource(TimeUpdateStrategy::ManualDuration(Duration::from_millis(
            16,
        )));
        app
    }

    /// Eleven 963-node models in one headless app with range springs on 500 points each.
    pub fn app_step(c: &mut Criterion) {
        let mut app = headless_app();
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

    /// The sandbox's load as the speed issue states it: the doll experiment's 11 parts (963 nodes
    /// each) on the horse image with the experiment's image forces, one simulation step each.
    pub fn app_step_image(c: &mut Criterion) {
        let (e, potential, poses) = doll_parts();
        let mut app = headless_app();
        let settings = ModelSettings {
            planar: true,
            fix_epsilon: true,
            ..default()
        };
        for (translation, rotation, shape) in poses {
            app.world_mut().spawn((
                GlobalShape::from(shape),
                RigidState {
                    translation,
                    rotation,
                },
                FemMesh::new(e.options.k),
                settings,
                ImageData::new(potential.clone()).with_options(&e.options),
            ));
        }
        app.update();
        c.bench_function("app_step/11_models_963_nodes_image", |b| {
            b.iter(|| app.update())
        });
    }
}

/// The image forces of the sandbox's load on one core: the doll experiment's forces (edge pull on
/// the outline and the region force) on its 11 placed parts, each part's nodal forces cleared and
/// gathered with buffers kept from step to step, as the plugin gathers them.
fn image_forces(c: &mut Criterion) {
    let (e, potential, poses) = doll_parts();
    let forces = e.options.forces(potential);
    let tess = Tessellation::new(e.options.k);
    let parts: Vec<Vec<DVec3>> = poses
        .into_iter()
        .map(|(translation, rotation, shape)| {
            let mut x = Vec::new();
            ModelState::new(&tess, translation, rotation, shape).node_positions(&tess, &mut x);
            x
        })
        .collect();
    let mut out = NodalForces::new(tess.node_count());
    let mut scratch = ImageScratch::default();
    c.bench_function("image_forces/doll_11_parts_963n", |b| {
        b.iter(|| {
            for x in &parts {
                out.clear(tess.node_count());
                forces.accumulate_with(&tess, x, &mut out, &mut scratch);
            }
            black_box(&out);
        })
    });
}

/// Counts the heap bytes in use, so that `memory_per_node` measures rather than estimates.
struct CountingAlloc;

static IN_USE: AtomicUsize = AtomicUsize::new(0);

unsafe impl GlobalAlloc for CountingAlloc {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        IN_USE.fetch_add(layout.size(), Ordering::Relaxed);
        unsafe { System.alloc(layout) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        IN_USE.fetch_sub(layout.size(), Ordering::Relaxed);
        unsafe { System.dealloc(ptr, layout) }
    }
}

#[global_allocator]
static ALLOC: CountingAlloc = CountingAlloc;

/// Memory per node: heap bytes held by a model ready to step (tessellation, state, nodal forces,
/// workspace after one step), over its node count; the range data on top, per data point.
fn memory_per_node(_: &mut Criterion) {
    for (k, m) in [(31, 1000), (71, 5000), (316, 100_000)] {
        let before = IN_USE.load(Ordering::Relaxed);
        let tess = Tessellation::new(k);
        let mut state = ModelState::new(&tess, DVec3::ZERO, DQuat::IDENTITY, target());
        let (mut forces, mut ws) = (NodalForces::new(tess.node_count()), Workspace::default());
        let params = DynamicsParams::default();
        forces.clear(tess.node_count());
        ws.prepare(&tess, &state);
        step_prepared(&tess, &mut state, &forces, &params, &mut ws).expect("finite");
        let model = IN_USE.load(Ordering::Relaxed) - before;
        let mut range = RangeForces::new(
            superquadric_cloud(&target(), DVec3::ZERO, DQuat::IDENTITY, m, 0.01, 7),
            4.0,
            InfluenceMode::NearestNode,
        );
        range.reassign(&tess, ws.world_positions());
        let data = IN_USE.load(Ordering::Relaxed) - before - model;
        println!(
            "memory_per_node/{}n_{m}p: {:.0} bytes per node (model), {:.0} bytes per data point",
            tess.node_count(),
            model as f64 / tess.node_count() as f64,
            data as f64 / m as f64,
        );
        black_box((tess, state, forces, ws, range));
    }
}

/// Issue 9's additions against the paper's step, on the same models: the first-order step with
/// tapering and bending free (the global system summed column by column), and a second-order
/// step (`model::inertia`) with the default mass and damping.
fn beyond_the_paper_step(c: &mut Criterion) {
    let mut g = c.benchmark_group("beyond_the_paper_step");
    for (k, m) in [(71, 5000), (31, 1000)] {
        let (tess, state, range) = attached(k, m);
        let mut params = DynamicsParams {
            dt: 0.01,
            ..Default::default()
        };
        params.free.taper = true;
        params.free.bend = true;
        let label = format!("{}n_{m}p", tess.node_count());
        let (mut forces, mut ws) = (NodalForces::new(tess.node_count()), Workspace::default());
        let mut s = state.clone();
        g.bench_with_input(BenchmarkId::new("taper_bend", &label), &(), |b, _| {
            b.iter(|| {
                step_once(&tess, &mut s, &range, &mut forces, &mut ws, &params);
                if s.displacement[0].length() > 1.0 {
                    s = state.clone();
                }
            })
        });
        let inertia = InertiaParams::default();
        let mut s = state.clone();
        let mut v = Velocity::zero(tess.node_count());
        let mut iws = InertiaWorkspace::default();
        g.bench_with_input(BenchmarkId::new("second_order", &label), &(), |b, _| {
            b.iter(|| {
                forces.clear(tess.node_count());
                range.accumulate(&tess, ws.prepare(&tess, &s), &mut forces);
                inertia_step(&tess, &mut s, &mut v, &forces, &params, &inertia, &mut iws)
                    .expect("finite");
                if s.displacement[0].length() > 1.0 {
                    s = state.clone();
                    v = Velocity::zero(tess.node_count());
                }
            })
        });
    }
    g.finish();
}

criterion_group!(
    benches,
    euler_step,
    beyond_the_paper_step,
    reassignment,
    migration,
    image_forces,
    memory_per_node,
    residuals_of_a_fit,
    ems_fits
);
#[cfg(feature = "bevy")]
criterion_group!(app_benches, app::app_step, app::app_step_image);
#[cfg(feature = "bevy")]
criterion_main!(benches, app_benches);
#[cfg(not(feature = "bevy"))]
criterion_main!(benches);
