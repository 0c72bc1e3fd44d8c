//! Global tapering and bending on shapes they should capture: cones, bananas bent 45–120°, bent
//! and tapered horns, in random orientations, whole or seen from one side, with noise. Each cloud
//! is made from the shape's own geometry (`synthetic::Banana`), not from `model::deform`.
//!
//! ```text
//! cargo bench --bench deformed [-- --only NAME] [--poses N]
//! ```
//!
//! `--poses N` fits each cloud in N random poses (and one-view cuts) instead of one.
//!
//! For each cloud, two fits as `dsq fit --global-only` and `dsq fit --global-only --taper --bend`
//! make them (`FitOptions::for_data`). Prints a Markdown table: the deformed fit's mean residual
//! over the plain one's (target ≤ 0.5), the fitted taper |t_x|, |t_y| and bend angle |b| beside the
//! truth (target: within 20 %, or within 0.1 where the truth is 0), and whether both targets are
//! met.
//!
//! `cargo test` runs it on two clouds and fails when a figure is not a finite number.

use bevy_deformable_sq::model::fit::{FitOptions, FitReport, fit};
use bevy_deformable_sq::synthetic::{Banana, Rng};
use glam::{DQuat, DVec3};
use std::process::ExitCode;

#[path = "common/mode.rs"]
mod mode;

/// One cloud of the set.
struct Case {
    name: &'static str,
    shape: Banana,
    /// Keep only the points facing a random viewer.
    one_view: bool,
    /// Noise per coordinate, as a fraction of the tube's middle radius.
    noise: f64,
}

/// The test set: name, half-length, turn end to end (degrees; 0 for a straight cone), middle
/// radius, taper, one view, noise (fraction of the radius).
#[rustfmt::skip]
const CASES: [(&str, f64, f64, f64, f64, bool, f64); 10] = [
    ("cone t 1", 1.5, 0.0, 0.5, 1.0, false, 0.01),
    ("cone t 0.6", 1.5, 0.0, 0.6, 0.6, false, 0.01),
    ("cone t 0.8, one view", 2.0, 0.0, 0.5, 0.8, true, 0.01),
    ("banana 45°", 1.8, 45.0, 0.35, 0.0, false, 0.01),
    ("banana 80°, t 0.3", 1.8, 80.0, 0.4, 0.3, false, 0.01),
    ("banana 120°", 2.0, 120.0, 0.3, 0.0, false, 0.01),
    ("banana 100°, one view", 1.8, 100.0, 0.35, 0.2, true, 0.01),
    ("banana 60°, thick", 1.2, 60.0, 0.45, 0.0, false, 0.02),
    ("horn 90°, t 0.8", 1.8, 90.0, 0.45, 0.8, false, 0.01),
    ("horn 60°, t 0.6, one view", 2.0, 60.0, 0.5, 0.6, true, 0.01),
];

fn cases() -> Vec<Case> {
    CASES
        .iter()
        .map(|&(name, half, turn, radius, taper, one_view, noise)| Case {
            name,
            shape: if turn == 0.0 {
                Banana::cone(half, radius, taper)
            } else {
                Banana::bent(half, turn, radius, taper)
            },
            one_view,
            noise,
        })
        .collect()
}

/// A uniformly random rotation.
fn random_rotation(rng: &mut Rng) -> DQuat {
    let axis = DVec3::new(rng.normal(), rng.normal(), rng.normal()).normalize();
    DQuat::from_axis_angle(axis, rng.range(0.0, std::f64::consts::TAU))
}

/// The case's cloud: 2000 points (before the one-view cut), turned and moved at random.
fn cloud(case: &Case, seed: u64) -> Vec<DVec3> {
    let mut rng = Rng::new(seed ^ 0x5eed);
    let turn = random_rotation(&mut rng);
    let offset = DVec3::new(
        rng.range(-2.0, 2.0),
        rng.range(-2.0, 2.0),
        rng.range(-2.0, 2.0),
    );
    // A viewer off to the side of the axis, so that the scan sees the length of the shape.
    let view = DVec3::new(rng.normal(), rng.normal(), 0.5 * rng.normal()).normalize();
    case.shape
        .oriented_points(2000, case.noise * case.shape.radius, seed)
        .into_iter()
        .filter(|(_, n)| !case.one_view || n.dot(view) > 0.0)
        .map(|(p, _)| turn * p + offset)
        .collect()
}

fn fit_with(points: &[DVec3], deform: bool) -> Option<FitReport> {
    let mut o = FitOptions {
        global_only: true,
        ..FitOptions::default()
    };
    o.dynamics.free.taper = deform;
    o.dynamics.free.bend = deform;
    fit(points, &o.for_data(), |_| {}).ok()
}

/// Whether `fitted` is within 20 % of `truth`, or within 0.1 of a zero truth.
fn close(fitted: f64, truth: f64) -> bool {
    if truth.abs() < 1e-3 {
        fitted.abs() <= 0.1
    } else {
        (fitted - truth).abs() <= 0.2 * truth.abs()
    }
}

fn main() -> ExitCode {
    let quick = !mode::benched();
    let only = std::env::args()
        .skip_while(|a| a != "--only")
        .nth(1)
        .filter(|_| !quick);
    let poses: u64 = std::env::args()
        .skip_while(|a| a != "--poses")
        .nth(1)
        .and_then(|n| n.parse().ok())
        .filter(|_| !quick)
        .unwrap_or(1);
    let mut all = cases();
    if quick {
        all.truncate(2);
    }
    println!(
        "| cloud | points | deformed ÷ plain | taper (fit / truth) | bend rad (fit / truth) | met |"
    );
    println!("|---|---|---|---|---|---|");
    let (mut figures, mut met) = (Vec::new(), 0);
    let mut run = 0;
    let runs = all
        .iter()
        .enumerate()
        .flat_map(|(i, case)| (0..poses).map(move |pose| (i as u64 + 1000 * pose, case)));
    for (seed, case) in runs {
        if only.as_deref().is_some_and(|o| !case.name.contains(o)) {
            continue;
        }
        run += 1;
        let points = cloud(case, 100 + seed);
        let (Some(plain), Some(both)) = (fit_with(&points, false), fit_with(&points, true)) else {
            println!(
                "| {} | {} | the fit failed | | | no |",
                case.name,
                points.len()
            );
            figures.push(f64::NAN);
            continue;
        };
        let ratio = both.residuals.mean / plain.residuals.mean;
        let d = both.state.deformation;
        let bend = d.bend[0].hypot(d.bend[1]);
        let truth_bend = if case.shape.half_angle < 1e-3 {
            0.0
        } else {
            case.shape.half_angle
        };
        let ok = ratio <= 0.5
            && d.taper.iter().all(|t| close(t.abs(), case.shape.taper))
            && close(bend, truth_bend);
        met += ok as usize;
        println!(
            "| {} | {} | {:.3} | {:.2}, {:.2} / {:.2} | {:.2} / {:.2} | {} |",
            case.name,
            points.len(),
            ratio,
            d.taper[0].abs(),
            d.taper[1].abs(),
            case.shape.taper,
            bend,
            truth_bend,
            if ok { "yes" } else { "no" }
        );
        figures.extend([ratio, bend, d.taper[0].abs(), d.taper[1].abs()]);
    }
    println!("\n{met} of {run} clouds meet both targets");
    match mode::check_finite("deformed", &figures) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::FAILURE
        }
    }
}
