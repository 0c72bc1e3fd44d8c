//! Property-based tests of the plugin's dynamics: random sequences of mouse drags (near and a
//! million units away), user springs, parameter edits, joints, second-order dynamics on and off
//! and resets keep every state finite, within its bounds and with a unit quaternion. And the
//! number of threads does not change an answer: the same app run with one compute thread and
//! with every core gives bit-identical states.

use bevy::prelude::*;
use bevy::tasks::ComputeTaskPool;
use bevy_deformable_sq::model::deform::{MAX_BEND, MAX_TAPER};
use bevy_deformable_sq::model::fem::Tessellation;
use bevy_deformable_sq::model::joint::JointEnd;
use bevy_deformable_sq::model::superquadric::{
    LEAST_EPSILON, MAX_EPSILON, MIN_ASPECT, SuperquadricParams,
};
use bevy_deformable_sq::plugin::model_node_positions;
use bevy_deformable_sq::prelude::*;
use bevy_deformable_sq::synthetic::superquadric_cloud;
use glam::{DQuat, DVec3};
use proptest::prelude::*;
use proptest::test_runner::{Config, RngSeed};
use std::hash::{Hash, Hasher};

/// A headless app stepping the simulation once per `update`.
fn app(pools: TaskPoolOptions) -> App {
    let mut app = App::new();
    app.add_plugins((
        MinimalPlugins.set(TaskPoolPlugin {
            task_pool_options: pools,
        }),
        DeformableSqPlugin::in_schedule(Update),
    ));
    app
}

/// What a user or a program does to the models between steps.
#[derive(Clone, Debug)]
enum Op {
    /// Press on model `m` near its node `node`, then drag the cursor `distance` away along `dir`
    /// for `steps` steps, as the mouse spring does; release.
    Drag {
        m: usize,
        node: usize,
        dir: [f64; 3],
        distance: f64,
        steps: u32,
    },
    /// A spring written by the user's own code, not clamped: anchor `distance` away.
    Spring {
        m: usize,
        u: f64,
        v: f64,
        distance: f64,
        stiffness: f64,
    },
    /// An edit of the settings, as the inspector's sliders and switches make them.
    Settings { m: usize, s: ModelSettings },
    /// An edit of the global shape within the inspector's ranges.
    Shape { m: usize, g: GlobalShape },
    /// A joint between two models.
    Joint {
        a: usize,
        b: usize,
        ends: [f64; 4],
        stiffness: f64,
    },
    /// Second-order dynamics on (with these parameters) or off.
    Inertia { m: usize, on: Option<[f64; 3]> },
    /// Back to the spawn state.
    Reset { m: usize },
    /// Just step.
    Run { steps: u32 },
}

fn log_uniform(lo: f64, hi: f64) -> impl Strategy<Value = f64> {
    (lo.ln()..hi.ln()).prop_map(f64::exp)
}

/// Settings across the ranges of the sandbox inspector's sliders and switches.
fn settings() -> impl Strategy<Value = ModelSettings> {
    (
        (
            log_uniform(1e-8, 0.1),
            log_uniform(1e-4, 2.0),
            log_uniform(1e-3, 0.2),
        ),
        (
            log_uniform(1e-2, 10.0),
            log_uniform(1e-2, 10.0),
            1u32..=1000,
        ),
        prop::array::uniform9(any::<bool>()),
    )
        .prop_map(|((w0, w1, dt), (gg, gl, every), f)| ModelSettings {
            w0,
            w1,
            dt,
            gamma_global: gg,
            gamma_local: gl,
            reassign_every: every,
            global_only: f[0],
            hold_local_steps: if f[1] { 20 } else { 0 },
            fix_epsilon: f[2],
            fix_shape: f[3],
            planar: f[4],
            taper: f[5],
            bend: f[6],
            implicit_local: f[7],
            fix_pose: f[8],
        })
}

/// A global shape across the inspector's slider ranges.
fn shape() -> impl Strategy<Value = GlobalShape> {
    (
        0.05f64..=3.0,
        prop::array::uniform3(0.05f64..=1.0),
        prop::array::uniform2(LEAST_EPSILON..=MAX_EPSILON),
        prop::array::uniform2(-MAX_TAPER..=MAX_TAPER),
        prop::array::uniform2(-MAX_BEND..=MAX_BEND),
    )
        .prop_map(|(a, [a1, a2, a3], [e1, e2], taper, bend)| GlobalShape {
            a,
            a1,
            a2,
            a3,
            e1,
            e2,
            taper,
            bend,
        })
}

const MODELS: usize = 3;

fn op() -> impl Strategy<Value = Op> {
    let m = 0..MODELS;
    let distance = prop_oneof![0.0f64..2.0, Just(1e3), Just(1e6)];
    prop_oneof![
        3 => (m.clone(), any::<usize>(), prop::array::uniform3(-1.0f64..1.0), distance.clone(), 1u32..40)
            .prop_map(|(m, node, dir, distance, steps)| Op::Drag { m, node, dir, distance, steps }),
        1 => (m.clone(), -1.5f64..1.5, -3.1f64..3.1, distance, log_uniform(1e-3, 1e3))
            .prop_map(|(m, u, v, distance, stiffness)| Op::Spring { m, u, v, distance, stiffness }),
        2 => (m.clone(), settings()).prop_map(|(m, s)| Op::Settings { m, s }),
        2 => (m.clone(), shape()).prop_map(|(m, g)| Op::Shape { m, g }),
        1 => (m.clone(), m.clone(), prop::array::uniform4(-3.0f64..3.0), log_uniform(1e-2, 1e3))
            .prop_map(|(a, b, ends, stiffness)| Op::Joint { a, b, ends, stiffness }),
        1 => (m.clone(), prop::option::of((log_uniform(1e-2, 100.0), log_uniform(1e-2, 10.0), 0.0f64..=10.0)))
            .prop_map(|(m, on)| Op::Inertia { m, on: on.map(|(a, b, c)| [a, b, c]) }),
        1 => m.prop_map(|m| Op::Reset { m }),
        2 => (1u32..60).prop_map(|steps| Op::Run { steps }),
    ]
}

/// Three models: a range-fitting ellipsoid, a rounded box with mass and a plain sphere.
fn spawn_models(app: &mut App) -> Vec<Entity> {
    let truth = SuperquadricParams {
        a: 1.0,
        a1: 0.8,
        a2: 0.5,
        a3: 1.0,
        e1: 0.6,
        e2: 1.0,
    };
    let points = superquadric_cloud(&truth, DVec3::ZERO, DQuat::IDENTITY, 200, 0.01, 3);
    let w = app.world_mut();
    vec![
        w.spawn((
            GlobalShape::default(),
            FemMesh::new(7),
            RangeData::new(points),
        ))
        .id(),
        w.spawn((
            GlobalShape {
                a: 0.6,
                e1: 0.3,
                e2: 0.3,
                ..default()
            },
            RigidState {
                translation: DVec3::new(2.0, 0.0, 0.0),
                rotation: DQuat::from_rotation_y(0.5),
            },
            FemMesh::new(7),
            Inertia::default(),
        ))
        .id(),
        w.spawn((
            GlobalShape::default(),
            RigidState {
                translation: DVec3::new(-2.0, 0.0, 0.0),
                rotation: DQuat::IDENTITY,
            },
            FemMesh::new(5),
        ))
        .id(),
    ]
}

/// Every model's state is finite and within its bounds, with a unit quaternion; every joint's
/// multiplier is finite. A model no unclamped spring pulls (not `wild`) also stays near where
/// the drags can take it, and of a size the edits give: it did not run away or collapse.
fn check_states(
    app: &mut App,
    models: &[Entity],
    wild: &[bool; MODELS],
) -> Result<(), TestCaseError> {
    for (i, &e) in models.iter().enumerate() {
        let w = app.world();
        let r = w.get::<RigidState>(e).expect("rigid");
        let g = w.get::<GlobalShape>(e).expect("shape");
        let l = w.get::<LocalDofs>(e).expect("local");
        let c = w.get::<SimControl>(e).expect("control");
        prop_assert!(r.translation.is_finite(), "{e}: {r:?} ({:?})", c.error);
        prop_assert!(
            (r.rotation.length() - 1.0).abs() < 1e-9,
            "{e}: |q| = {}",
            r.rotation.length()
        );
        prop_assert!(g.a.is_finite() && g.a > 0.0, "{e}: {g:?}");
        for ai in [g.a1, g.a2, g.a3] {
            prop_assert!((MIN_ASPECT..=1.0).contains(&ai), "{e}: {g:?}");
        }
        for ei in [g.e1, g.e2] {
            prop_assert!((LEAST_EPSILON..=MAX_EPSILON).contains(&ei), "{e}: {g:?}");
        }
        prop_assert!(g.taper.iter().all(|t| t.abs() <= MAX_TAPER), "{e}: {g:?}");
        prop_assert!(g.bend.iter().all(|b| b.abs() <= MAX_BEND), "{e}: {g:?}");
        prop_assert!(l.displacement.iter().all(|d| d.is_finite()), "{e}: local");
        if !wild[i] {
            prop_assert!(r.translation.length() < 1e4, "{e} ran away: {r:?}");
            prop_assert!(g.a > 1e-3 && g.a < 1e3, "{e} collapsed or blew up: {g:?}");
        }
        if let Some(i) = w.get::<Inertia>(e) {
            prop_assert!(i.velocity.is_finite(), "{e}: velocity");
        }
        let nodes = model_node_positions(w, e).expect("a built mesh");
        prop_assert!(nodes.iter().all(|x| x.is_finite()), "{e}: nodes");
    }
    let mut joints = app.world_mut().query::<&PartJoint>();
    for j in joints.iter(app.world()) {
        prop_assert!(j.joint.multiplier.is_finite() && j.gap.is_finite(), "{j:?}");
    }
    Ok(())
}

fn node_positions(app: &App, e: Entity) -> Vec<DVec3> {
    model_node_positions(app.world(), e).expect("a built mesh")
}

fn tessellation(app: &App, e: Entity) -> Option<std::sync::Arc<Tessellation>> {
    app.world().get::<FemMesh>(e)?.get().cloned()
}

/// Models that an unclamped user spring pulls, directly or through joints.
fn wild_closure(wild: &[bool; MODELS], joints: &[(usize, usize)]) -> [bool; MODELS] {
    let mut out = *wild;
    for _ in 0..MODELS {
        for &(a, b) in joints {
            let either = out[a] || out[b];
            out[a] = either;
            out[b] = either;
        }
    }
    out
}

/// Runs `ops`, checking every state after every step. A model may freeze (refuse a step with a
/// clear error, its state untouched) only under a spring the user's code set unclamped, on it or
/// on a model jointed to it: a mouse drag, an edit or a joint never freezes one.
fn run(ops: &[Op]) -> Result<(), TestCaseError> {
    let mut app = app(TaskPoolOptions::default());
    let models = spawn_models(&mut app);
    app.update();
    check_states(&mut app, &models, &[false; MODELS])?;
    let mut wild = [false; MODELS];
    let mut joints: Vec<(usize, usize)> = Vec::new();
    let step = |app: &mut App, n: u32, wild: &[bool; MODELS]| -> Result<(), TestCaseError> {
        for _ in 0..n {
            app.update();
            check_states(app, &models, wild)?;
        }
        for (i, &e) in models.iter().enumerate() {
            let c = app.world().get::<SimControl>(e).expect("control");
            prop_assert!(!c.frozen || wild[i], "model {i} froze: {:?}", c.error);
        }
        Ok(())
    };
    for op in ops {
        match op.clone() {
            Op::Drag {
                m,
                node,
                dir,
                distance,
                steps,
            } => {
                let e = models[m];
                let (Some(tess), x) = (tessellation(&app, e), node_positions(&app, e)) else {
                    continue;
                };
                if x.len() != tess.node_count() {
                    continue;
                }
                let settings = *app.world().get::<ModelSettings>(e).expect("settings");
                let a = app.world().get::<GlobalShape>(e).expect("shape").a;
                let hit = x[node % x.len()];
                let Some(spring) =
                    Spring::grab(&tess, &x, hit, Spring::mouse_stiffness(&settings, a))
                else {
                    continue;
                };
                let dir = DVec3::from_array(dir).try_normalize().unwrap_or(DVec3::X);
                let target = hit + distance * dir;
                app.world_mut()
                    .entity_mut(e)
                    .insert(SpringForces(vec![spring]));
                // The stretch is bounded by the scale at the press, as `MouseSpringPlugin` does.
                for _ in 0..steps {
                    let x = node_positions(&app, e);
                    if let Some(mut springs) = app.world_mut().get_mut::<SpringForces>(e)
                        && let Some(s) = springs.0.first_mut()
                    {
                        s.pull_towards(&tess, &x, target, a);
                    }
                    step(&mut app, 1, &wild_closure(&wild, &joints))?;
                }
                app.world_mut().entity_mut(e).insert(SpringForces(vec![]));
            }
            Op::Spring {
                m,
                u,
                v,
                distance,
                stiffness,
            } => {
                wild[m] = true;
                let e = models[m];
                let c = app.world().get::<RigidState>(e).expect("rigid").translation;
                app.world_mut()
                    .entity_mut(e)
                    .insert(SpringForces(vec![Spring {
                        u,
                        v,
                        anchor: c + DVec3::new(distance, 0.5 * distance, 0.0),
                        stiffness,
                        reshape: true,
                    }]));
            }
            Op::Settings { m, s } => {
                app.world_mut().entity_mut(models[m]).insert(s);
            }
            Op::Shape { m, g } => {
                app.world_mut().entity_mut(models[m]).insert(g);
            }
            Op::Joint {
                a,
                b,
                ends,
                stiffness,
            } => {
                if a == b {
                    continue;
                }
                let mut joint = PartJoint::new(
                    models[a],
                    JointEnd {
                        u: ends[0].clamp(-1.5, 1.5),
                        v: ends[1],
                    },
                    models[b],
                    JointEnd {
                        u: ends[2].clamp(-1.5, 1.5),
                        v: ends[3],
                    },
                );
                joint.joint.stiffness = stiffness;
                app.world_mut().spawn(joint);
                joints.push((a, b));
            }
            Op::Inertia { m, on } => {
                let mut e = app.world_mut().entity_mut(models[m]);
                match on {
                    Some([mass_density, local_inertia, damping]) => {
                        e.insert(Inertia::new(
                            bevy_deformable_sq::model::inertia::InertiaParams {
                                mass_density,
                                local_inertia,
                                damping,
                            },
                        ));
                    }
                    None => {
                        e.remove::<Inertia>();
                    }
                }
            }
            Op::Reset { m } => {
                let e = models[m];
                app.world_mut()
                    .get_mut::<SimControl>(e)
                    .expect("control")
                    .reset_requested = true;
                app.world_mut().entity_mut(e).insert(SpringForces(vec![]));
                wild[m] = false;
            }
            Op::Run { steps } => step(&mut app, steps, &wild_closure(&wild, &joints))?,
        }
        step(&mut app, 1, &wild_closure(&wild, &joints))?;
    }
    Ok(())
}

proptest! {
    #![proptest_config(Config {
        cases: 256,
        rng_seed: RngSeed::Fixed(0x5eed_0004),
        failure_persistence: None,
        max_shrink_iters: 128,
        ..Config::default()
    })]

    #[test]
    fn random_drags_edits_and_joints_keep_every_state_finite_and_in_bounds(
        ops in prop::collection::vec(op(), 1..14)
    ) {
        run(&ops)?;
    }
}

/// The child process's mark: run the workload with the threads it is given and print its hash.
const CHILD: &str = "BDSQ_THREADS_CHILD";

/// Twelve models fitting range data (some with mass, two jointed, one pulled by a spring) for
/// 240 steps with reattachment every 60: the hash of every state bit, and the compute threads.
fn workload(pools: TaskPoolOptions) -> (u64, usize) {
    let mut app = app(pools);
    let mut models = Vec::new();
    for i in 0..12 {
        let truth = SuperquadricParams {
            a: 1.0 + 0.05 * i as f64,
            a1: 0.7,
            a2: 0.5 + 0.03 * i as f64,
            a3: 1.0,
            e1: 0.5 + 0.1 * i as f64,
            e2: 1.0,
        };
        let centre = DVec3::new(3.0 * i as f64, 0.0, 0.0);
        let points = superquadric_cloud(&truth, centre, DQuat::from_rotation_z(0.2), 3000, 0.01, i);
        let mut e = app.world_mut().spawn((
            GlobalShape::default(),
            RigidState {
                translation: centre,
                rotation: DQuat::IDENTITY,
            },
            FemMesh::new(15),
            RangeData::new(points),
            ModelSettings {
                reassign_every: 60,
                ..default()
            },
        ));
        if i % 3 == 0 {
            e.insert(Inertia::default());
        }
        if i == 5 {
            e.insert(SpringForces(vec![Spring {
                u: 0.3,
                v: 1.0,
                anchor: centre + DVec3::new(0.0, 4.0, 0.0),
                stiffness: 0.5,
                reshape: true,
            }]));
        }
        models.push(e.id());
    }
    let (a, b) = (models[1], models[2]);
    app.world_mut().spawn(PartJoint::new(
        a,
        JointEnd { u: 0.0, v: 0.0 },
        b,
        JointEnd {
            u: 0.0,
            v: std::f64::consts::PI,
        },
    ));
    for _ in 0..240 {
        app.update();
    }
    let mut h = std::collections::hash_map::DefaultHasher::new();
    let w = app.world();
    for &e in &models {
        let (r, g, l) = (
            w.get::<RigidState>(e).expect("rigid"),
            w.get::<GlobalShape>(e).expect("shape"),
            w.get::<LocalDofs>(e).expect("local"),
        );
        assert_eq!(w.get::<SimControl>(e).expect("control").steps, 240);
        // Debug prints each f64 in its shortest round-trip form: equal text, equal bits.
        format!("{r:?} {g:?} {l:?}").hash(&mut h);
    }
    (h.finish(), ComputeTaskPool::get().thread_num())
}

#[test]
fn threads_do_not_change_answers() {
    if let Ok(threads) = std::env::var(CHILD) {
        let pools = if threads == "1" {
            TaskPoolOptions::with_num_threads(1)
        } else {
            simulation_task_pools()
        };
        let (hash, threads) = workload(pools);
        println!("workload hash {hash:016x} threads {threads}");
        return;
    }
    // Bevy's task pools and rayon's are made once per process: each count gets its own.
    let run = |threads: &str| -> (String, usize) {
        let mut cmd = std::process::Command::new(std::env::current_exe().expect("test binary"));
        cmd.args(["--exact", "threads_do_not_change_answers", "--nocapture"])
            .env(CHILD, threads);
        if threads == "1" {
            cmd.env("RAYON_NUM_THREADS", "1");
        } else {
            cmd.env_remove("RAYON_NUM_THREADS");
        }
        let out = cmd.output().expect("run the test binary");
        let stdout = String::from_utf8_lossy(&out.stdout);
        assert!(out.status.success(), "{threads} threads: {stdout}");
        let line = stdout
            .lines()
            .find_map(|l| l.strip_prefix("workload hash "))
            .unwrap_or_else(|| panic!("no hash from the {threads}-thread run: {stdout}"));
        let (hash, n) = line.split_once(" threads ").expect("hash line");
        (hash.to_string(), n.trim().parse().expect("thread count"))
    };
    let (one, n1) = run("1");
    let (all, n) = run("all");
    assert_eq!(n1, 1, "the single-thread run had {n1} compute threads");
    assert_eq!(n, bevy::tasks::available_parallelism());
    assert_eq!(one, all, "1 thread and {n} threads gave different states");
}
