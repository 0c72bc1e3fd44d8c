//! The paper's range experiments (section VI-B) on data rebuilt from their description
//! (`bevy_deformable_sq::synthetic`), with the paper's node counts, stiffnesses and initial states.

use bevy_deformable_sq::model::fit::{FitOptions, FitReport, fit};
use bevy_deformable_sq::synthetic;
use glam::DVec3;

fn run(points: &[DVec3], opts: FitOptions) -> FitReport {
    fit(points, &opts, |_| {}).expect("fit runs")
}

fn egg_options(global_only: bool) -> (Vec<DVec3>, FitOptions) {
    let (points, o) = synthetic::egg_experiment();
    (points, FitOptions { global_only, ..o })
}

fn mug_options(global_only: bool) -> (Vec<DVec3>, FitOptions) {
    let (points, o) = synthetic::mug_experiment();
    (points, FitOptions { global_only, ..o })
}

#[test]
fn egg_fit_reaches_a_small_residual() {
    let (points, opts) = egg_options(false);
    let r = run(&points, opts);
    eprintln!(
        "egg: {:?} steps {} converged {}",
        r.residuals, r.steps, r.converged
    );
    assert!(
        r.converged,
        "egg fit did not come to rest in {} steps",
        r.steps
    );
    assert!(r.state.displacement.len() == 2603);
    assert!(
        r.residuals.mean < 0.005,
        "egg mean residual {} of the diagonal",
        r.residuals.mean
    );
    assert!(
        r.residuals.max < 0.03,
        "egg max residual {}",
        r.residuals.max
    );
    assert!((r.state.rotation.length() - 1.0).abs() < 1e-12);
}

#[test]
fn mug_pits_are_reconstructed_by_the_local_dofs() {
    let (points, opts) = mug_options(true);
    let global = run(&points, opts);
    let (points, opts) = mug_options(false);
    let local = run(&points, opts);
    eprintln!(
        "mug global-only: {:?} steps {}",
        global.residuals, global.steps
    );
    eprintln!(
        "mug with local:  {:?} steps {}",
        local.residuals, local.steps
    );
    assert!(global.converged && local.converged);
    assert!(
        local.residuals.mean < 0.5 * global.residuals.mean,
        "local {} vs global-only {}",
        local.residuals.mean,
        global.residuals.mean
    );
    // The pits: points in a pit sit well inside the global superquadric but on the local surface.
    let pit_points: Vec<DVec3> = points
        .iter()
        .copied()
        .filter(|p| {
            p.z < synthetic::MUG_HALF_HEIGHT && synthetic::mug_pit_depth(p.y.atan2(p.x), p.z) > 0.04
        })
        .collect();
    assert!(pit_points.len() > 10);
    let mean_dist = |r: &FitReport| {
        let mut x = Vec::new();
        r.state.node_positions(&r.tess, &mut x);
        let d = bevy_deformable_sq::model::fit::point_distances(&r.tess, &x, &pit_points);
        d.iter().sum::<f64>() / d.len() as f64
    };
    let (dg, dl) = (mean_dist(&global), mean_dist(&local));
    eprintln!(
        "pit points: global-only {dg:.4}, local {dl:.4} (pit depth {})",
        synthetic::MUG_PIT_DEPTH
    );
    assert!(dl < 0.5 * dg, "pits not reconstructed: {dl} vs {dg}");
}
