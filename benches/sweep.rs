//! The fitter's defaults swept over generated clouds whose truth is known: partial views, noise
//! 0–5 %, outliers 0–40 % (uniform in a box, or Gaussian about the object), exponents over
//! [0.1, 1.9].
//!
//! ```text
//! cargo bench --bench sweep [-- --clouds N] [--local] [--export DIR] [--ems FILE]
//! ```
//!
//! Each cloud is fitted as `dsq fit CLOUD [--global-only]` fits it (`CloudOptions`, the defaults
//! for a user's cloud) and scored two ways, both as fractions of the inliers' bounding-box
//! diagonal:
//!
//! - **truth**: the mean distance from the noise-free samples of the seen part of the true
//!   surface to the fitted surface: how far the fit lies from the object;
//! - **inliers**: the mean distance of the noisy surface points to the fitted surface.
//!
//! Prints a row per cloud, then the worst and the median of each. `--local` fits with local
//! DOFs (the default fit); without it a pure superquadric (`--global-only`). `--export DIR`
//! writes each cloud as `DIR/sweep_N.ply` and its truth as `DIR/truth.jsonl`; `--ems FILE` reads
//! another fitter's superquadrics of those clouds (JSON lines with `cloud`, `shape` [ε1, ε2],
//! `scale` [3 semi-axes], `translation` and `rot`, 9 numbers row-major) and scores them the same
//! way. `cargo test` runs four clouds and fails when a figure is not finite.

use bevy_deformable_sq::model::fit::{CloudOptions, FitOptions, fit, fit_residuals};
use bevy_deformable_sq::model::fit::{bounding_diagonal, surface_distances};
use bevy_deformable_sq::synthetic::sweep_cloud;
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;

#[path = "common/ems.rs"]
mod ems;
#[path = "common/mode.rs"]
mod mode;
#[path = "common/ply.rs"]
mod ply;

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v.get(v.len() / 2).copied().unwrap_or(f64::NAN)
}

fn mean(v: &[f64]) -> f64 {
    v.iter().sum::<f64>() / v.len().max(1) as f64
}

fn main() -> ExitCode {
    let benched = mode::benched();
    let mut clouds = if benched { 64u64 } else { 4 };
    let (mut local, mut export, mut ems_file) = (false, None::<PathBuf>, None::<PathBuf>);
    let mut args = std::env::args()
        .skip(1)
        .filter(|a| a != "--bench")
        .filter(|_| benched);
    while let Some(a) = args.next() {
        match a.as_str() {
            "--local" => local = true,
            "--clouds" => match args.next().and_then(|n| n.parse().ok()) {
                Some(n) => clouds = n,
                None => {
                    eprintln!("--clouds: expected a count");
                    return ExitCode::from(2);
                }
            },
            "--export" => export = args.next().map(PathBuf::from),
            "--ems" => ems_file = args.next().map(PathBuf::from),
            _ => {
                eprintln!("usage: sweep [--clouds N] [--local] [--export DIR] [--ems FILE]");
                return ExitCode::from(2);
            }
        }
    }
    let theirs = match ems::read_results(ems_file.as_deref()) {
        Ok(r) => r,
        Err(e) => {
            eprintln!("{e}");
            return ExitCode::from(2);
        }
    };
    if let Some(dir) = &export
        && let Err(e) = std::fs::create_dir_all(dir)
    {
        eprintln!("{}: {e}", dir.display());
        return ExitCode::from(2);
    }
    let opts = match (CloudOptions {
        global_only: !local,
        ..CloudOptions::default()
    })
    .resolve(FitOptions::default(), true)
    {
        Ok(p) => p,
        Err(e) => {
            eprintln!("{e}");
            return ExitCode::from(2);
        }
    };
    println!(
        "| cloud | seen | noise | outliers | ε1, ε2 (truth) | ε1, ε2 (fit) | truth | inliers | ms | other: truth | other: inliers |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|---|");
    let (mut truth_d, mut inlier_d, mut ratios) = (Vec::new(), Vec::new(), Vec::new());
    let mut truths = String::new();
    for i in 1..=clouds {
        let (r, c) = sweep_cloud(i);
        let inliers = &c.points[..c.points.len() - c.outliers];
        if let Some(dir) = &export {
            let path = dir.join(format!("sweep_{i}.ply"));
            if let Err(e) = ply::write_ascii(&path, &c.points) {
                eprintln!("{}: {e}", path.display());
                return ExitCode::from(2);
            }
            truths += &ply::truth_line(&format!("sweep_{i}"), &c.truth);
        }
        let start = Instant::now();
        let report = match fit(&c.points, &opts, |_| {}) {
            Ok(report) => report,
            Err(e) => {
                eprintln!("cloud {i}: {e}");
                return ExitCode::FAILURE;
            }
        };
        let ms = start.elapsed().as_secs_f64() * 1e3;
        let diagonal = bounding_diagonal(inliers);
        let scale = |r: bevy_deformable_sq::model::fit::Residuals| r.mean * r.diagonal / diagonal;
        let truth = scale(fit_residuals(&report.tess, &report.state, &c.surface));
        let inlier = scale(fit_residuals(&report.tess, &report.state, inliers));
        let other = theirs
            .iter()
            .find(|f| f.cloud == format!("sweep_{i}"))
            .map(|f| {
                let pose = f.pose();
                (
                    mean(&surface_distances(&pose, &c.surface)) / diagonal,
                    mean(&surface_distances(&pose, inliers)) / diagonal,
                )
            });
        if let Err(e) = mode::check_finite(&format!("cloud {i}"), &[truth, inlier]) {
            eprintln!("{e}");
            return ExitCode::FAILURE;
        }
        let (t, f) = (c.truth.shape, report.state.shape);
        println!(
            "| {i} | {:.0} % | {:.0} % | {:.0} % {:?} | {:.2}, {:.2} | {:.2}, {:.2} | {:.5} | {:.5} | {ms:.0} | {} | {} |",
            r.kept * 100.0,
            r.noise * 100.0,
            r.outliers * 100.0,
            r.outlier_spread,
            t.e1,
            t.e2,
            f.e1,
            f.e2,
            truth,
            inlier,
            other.map_or("–".into(), |o| format!("{:.5}", o.0)),
            other.map_or("–".into(), |o| format!("{:.5}", o.1)),
        );
        truth_d.push(truth);
        inlier_d.push(inlier);
        if let Some((_, o)) = other {
            ratios.push(inlier / o);
        }
    }
    let worst = |v: &[f64]| v.iter().copied().fold(0.0, f64::max);
    println!();
    println!(
        "truth: worst {:.5}, median {:.5}; inliers: worst {:.5}, median {:.5}; clouds over 1 %: {}",
        worst(&truth_d),
        median(truth_d.clone()),
        worst(&inlier_d),
        median(inlier_d.clone()),
        truth_d.iter().filter(|&&d| d > 0.01).count()
    );
    if !ratios.is_empty() {
        println!(
            "inliers ÷ other's: worst {:.3}, median {:.3}, over 1.1: {} of {}",
            worst(&ratios),
            median(ratios.clone()),
            ratios.iter().filter(|&&r| r > 1.1).count(),
            ratios.len()
        );
    }
    if let Some(dir) = &export
        && let Err(e) = std::fs::write(dir.join("truth.jsonl"), truths)
    {
        eprintln!("{}: {e}", dir.join("truth.jsonl").display());
        return ExitCode::from(2);
    }
    ExitCode::SUCCESS
}
