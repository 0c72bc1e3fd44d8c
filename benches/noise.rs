//! How stiff the membrane should be for noisy points: fits a cloud with known, detailed truth (an
//! egg with five ridges round its axis, which no superquadric has) at several noise levels and
//! membrane stiffnesses, and scores each fit by how far the clean surface lies from it.
//!
//! `cargo bench --bench noise [-- --points N]`
//!
//! Columns: the noise added (σ per coordinate over the cloud's RMS radius), the noise that
//! `model::noise::estimate_noise` finds from the points alone, the error of a pure superquadric
//! (global-only) fit, the error with local DOFs for each w1 (w0 = w1 / 100), and the error with the
//! stiffness `model::noise::stiffness_for_noise` picks from the estimate. Error: the mean distance
//! of 4000 clean surface points to the fitted surface, over the RMS radius, in units of 10⁻³.
use bevy_deformable_sq::model::fit::{FitOptions, Normalization, fit, point_distances};
use bevy_deformable_sq::model::noise::{estimate_noise, stiffness_for_noise};
use bevy_deformable_sq::synthetic::{Rng, ridged_egg};
use glam::DVec3;

/// The membrane stiffnesses swept.
const W1: [f64; 7] = [0.001, 0.003, 0.01, 0.03, 0.1, 0.3, 1.0];
/// Noise per coordinate over the RMS radius.
const NOISE: [f64; 6] = [0.0, 0.005, 0.01, 0.02, 0.04, 0.08];

/// Mean distance of `truth` to the surface fitted to `points` with `opts`, over `scale`.
fn truth_error(points: &[DVec3], truth: &[DVec3], opts: &FitOptions, scale: f64) -> f64 {
    let report = fit(points, opts, |_| {}).expect("fit");
    let mut x = Vec::new();
    report.state.node_positions(&report.tess, &mut x);
    let d = point_distances(&report.tess, &x, truth);
    d.iter().sum::<f64>() / d.len() as f64 / scale
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let n: usize = args
        .iter()
        .position(|a| a == "--points")
        .and_then(|i| args.get(i + 1))
        .and_then(|v| v.parse().ok())
        .unwrap_or(2000);
    let truth = ridged_egg(4000, 1);
    let clean = ridged_egg(n, 2);
    let scale = Normalization::of(&clean).scale;
    print!("{:>7} {:>7} {:>7}", "noise", "est.", "global");
    for w1 in W1 {
        print!(" {:>7}", format!("w1={w1}"));
    }
    println!(" {:>7} {:>6}", "auto", "w1");
    for sigma in NOISE {
        let mut rng = Rng::new(3);
        let points: Vec<DVec3> = clean
            .iter()
            .map(|p| *p + sigma * scale * DVec3::new(rng.normal(), rng.normal(), rng.normal()))
            .collect();
        let estimate = estimate_noise(&points).map_or(f64::NAN, |e| e.relative);
        let base = FitOptions::default();
        let global = FitOptions {
            global_only: true,
            ..base
        };
        print!(
            "{:>7.4} {:>7.4} {:>7.2}",
            sigma,
            estimate,
            1e3 * truth_error(&points, &truth, &global, scale)
        );
        let with = |w0: f64, w1: f64| FitOptions {
            dynamics: bevy_deformable_sq::model::dynamics::DynamicsParams {
                w0,
                w1,
                ..base.dynamics
            },
            ..base
        };
        for w1 in W1 {
            let e = truth_error(&points, &truth, &with(w1 / 100.0, w1), scale);
            print!(" {:>7.2}", 1e3 * e);
        }
        let (w0, w1) = stiffness_for_noise(estimate);
        let e = truth_error(&points, &truth, &with(w0, w1), scale);
        println!(" {:>7.2} {:>6.3}", 1e3 * e, w1);
    }
}
