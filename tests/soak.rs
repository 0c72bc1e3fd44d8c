//! A soak test: the sandbox's heaviest load, the doll scene's 11 parts with image forces, loaded
//! through the scene plugin and run headless for 10 000 steps while mouse springs are dragged
//! at random (near and far): no model freezes, no state turns non-finite, and the process's
//! memory stays flat after the first frames. Alone in its test binary, so that its memory is its
//! own.

use bevy::asset::AssetPlugin;
use bevy::prelude::*;
use bevy_deformable_sq::model::fem::Tessellation;
use bevy_deformable_sq::plugin::model_node_positions;
use bevy_deformable_sq::prelude::*;
use glam::DVec3;
use std::path::Path;
use std::sync::Arc;

const STEPS: u32 = 10_000;

/// The process's resident memory in bytes (Linux; `None` elsewhere).
fn resident_bytes() -> Option<u64> {
    let statm = std::fs::read_to_string("/proc/self/statm").ok()?;
    let pages: u64 = statm.split_whitespace().nth(1)?.parse().ok()?;
    Some(pages * 4096)
}

/// A small deterministic generator for the drags (SplitMix64).
struct Dice(u64);

impl Dice {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }

    fn uniform(&mut self) -> f64 {
        (self.next() >> 11) as f64 / (1u64 << 53) as f64
    }
}

/// A drag in progress: model, its scale at the press, target and steps left.
struct Drag {
    model: Entity,
    scale: f64,
    target: DVec3,
    left: u32,
}

/// A part's world node positions, its tessellation and its scale a.
fn part(app: &App, e: Entity) -> (Vec<DVec3>, Option<Arc<Tessellation>>, f64) {
    let w = app.world();
    let x = model_node_positions(w, e).expect("a built mesh");
    let tess = w.get::<FemMesh>(e).and_then(|m| m.get().cloned());
    (x, tess, w.get::<GlobalShape>(e).expect("shape").a)
}

#[test]
fn the_sandbox_load_runs_10000_steps_with_random_drags() {
    let assets = Path::new(env!("CARGO_MANIFEST_DIR")).join("assets");
    let mut app = App::new();
    app.add_plugins((
        MinimalPlugins.set(TaskPoolPlugin {
            task_pool_options: simulation_task_pools(),
        }),
        AssetPlugin {
            file_path: assets.display().to_string(),
            ..default()
        },
        DeformableSqPlugin::in_schedule(Update),
        DeformableSqScenePlugin,
    ));
    let handle = app
        .world()
        .resource::<AssetServer>()
        .load("scenes/doll.dsq.ron");
    let root = app.world_mut().spawn(DeformableSceneRoot(handle)).id();
    let mut parts = Vec::new();
    for _ in 0..5000 {
        app.update();
        let instance = app.world().get::<SceneInstance>(root).expect("instance");
        assert!(instance.error.is_none(), "{:?}", instance.error);
        if instance.spawned.is_some() {
            parts = instance.parts.clone();
            break;
        }
        std::thread::sleep(std::time::Duration::from_millis(2));
    }
    assert_eq!(
        parts.len(),
        11,
        "the doll scene spawned {} parts",
        parts.len()
    );
    for &e in &parts {
        assert!(
            app.world().get::<ImageData>(e).is_some(),
            "a part without image forces"
        );
    }

    let mut dice = Dice(0x50a6);
    let mut drag: Option<Drag> = None;
    let mut steps = 0u32;
    let mut baseline = None;
    let mut peak = 0u64;
    let (mut drags, mut far) = (0, 0);
    while steps < STEPS {
        // Every part has stepped once per update since the scene spawned.
        match &mut drag {
            Some(d) if d.left > 0 => {
                d.left -= 1;
                let e = d.model;
                let (x, tess, _) = part(&app, e);
                if let (Some(tess), Some(mut springs)) =
                    (tess, app.world_mut().get_mut::<SpringForces>(e))
                    && let Some(s) = springs.0.first_mut()
                {
                    s.pull_towards(&tess, &x, d.target, d.scale);
                }
            }
            Some(d) => {
                app.world_mut()
                    .entity_mut(d.model)
                    .insert(SpringForces(vec![]));
                drag = None;
            }
            None if dice.uniform() < 0.05 => {
                // Press on a random part near a random node, and pick where the cursor goes.
                let e = parts[dice.next() as usize % parts.len()];
                let (x, tess, a) = part(&app, e);
                let settings = *app.world().get::<ModelSettings>(e).expect("settings");
                if let Some(tess) = tess
                    && !x.is_empty()
                {
                    let hit = x[dice.next() as usize % x.len()];
                    let dir = DVec3::new(
                        dice.uniform() - 0.5,
                        dice.uniform() - 0.5,
                        0.2 * (dice.uniform() - 0.5),
                    )
                    .normalize_or(DVec3::X);
                    let reach = if dice.uniform() < 0.2 {
                        far += 1;
                        1e6
                    } else {
                        3.0 * a * dice.uniform()
                    };
                    if let Some(spring) =
                        Spring::grab(&tess, &x, hit, Spring::mouse_stiffness(&settings, a))
                    {
                        drags += 1;
                        app.world_mut()
                            .entity_mut(e)
                            .insert(SpringForces(vec![spring]));
                        drag = Some(Drag {
                            model: e,
                            scale: a,
                            target: hit + reach * dir,
                            left: 10 + (dice.next() % 60) as u32,
                        });
                    }
                }
            }
            None => {}
        }
        app.update();
        steps += 1;
        for &e in &parts {
            let w = app.world();
            let c = w.get::<SimControl>(e).expect("control");
            assert!(!c.frozen, "step {steps}: part {e} froze: {:?}", c.error);
            let r = w.get::<RigidState>(e).expect("rigid");
            let g = w.get::<GlobalShape>(e).expect("shape");
            let l = w.get::<LocalDofs>(e).expect("local");
            assert!(
                r.translation.is_finite()
                    && (r.rotation.length() - 1.0).abs() < 1e-9
                    && [g.a, g.a1, g.a2, g.a3, g.e1, g.e2]
                        .iter()
                        .all(|v| v.is_finite())
                    && l.displacement.iter().all(|d| d.is_finite()),
                "step {steps}: part {e} is not finite"
            );
        }
        if let Some(now) = resident_bytes() {
            if steps == 500 {
                baseline = Some(now);
            }
            peak = peak.max(now);
        }
    }
    assert!(drags > 100 && far > 10, "{drags} drags, {far} far");
    for &e in &parts {
        let taken = app.world().get::<SimControl>(e).expect("control").steps;
        assert!(taken >= u64::from(STEPS), "a part took {taken} steps");
    }
    if let (Some(base), Some(end)) = (baseline, resident_bytes()) {
        let mib = |b: u64| b as f64 / (1 << 20) as f64;
        println!(
            "{drags} drags ({far} to 1e6); resident memory: {:.1} MiB at step 500, {:.1} MiB at \
             the end, peak {:.1} MiB",
            mib(base),
            mib(end),
            mib(peak)
        );
        assert!(
            peak <= base + (16 << 20),
            "memory grew from {:.1} MiB at step 500 to a peak of {:.1} MiB",
            mib(base),
            mib(peak)
        );
    }
}
