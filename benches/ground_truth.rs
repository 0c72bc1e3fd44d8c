//! Parameter errors on clouds with known ground truth, generated as EMS's paper tests its fitter
//! (`synthetic::ground_truth_cloud`: a random superquadric, 60 % of its surface seen, noise of 1 %
//! of the largest semi-axis, 20 % outliers).
//!
//! ```text
//! cargo bench --bench ground_truth [-- --clouds N] [--export DIR] [--ems FILE]
//! ```
//!
//! `cargo test` runs it on two clouds, ignoring any arguments, and fails when a figure is not a
//! finite number.
//!
//! For each cloud, a global-only fit with the paper's springs through the paper's dynamics, one
//! with `FitOptions::robust` through the dynamics (`dsq fit --robust --global-only --solver
//! dynamics`) and the default, solved one (`dsq fit --robust --global-only`) are scored by
//! `synthetic::ParameterErrors`: mean relative error
//! of the semi-axes, mean error of ε1 and ε2, translation error over the largest semi-axis and
//! the rotation error in degrees (all after matching the axes). Prints a Markdown table and the
//! medians. `--export DIR` also writes each cloud as `DIR/cloud_N.ply` (ASCII) and its truth as
//! `DIR/truth.jsonl`, so that other fitters can be run on the same clouds; `--ems FILE` reads EMS's
//! fits of them (made by running EMS on the exported clouds, outside the crate: JSON lines with
//! `cloud`, `shape`, `scale`, `translation` and `rot`) and scores them the same way in the last
//! column.

use bevy_deformable_sq::model::fit::{FitOptions, Solver, bounding_diagonal, fit, point_distances};
use bevy_deformable_sq::model::init::InitialPose;
use bevy_deformable_sq::synthetic::{CloudRecipe, ParameterErrors, ground_truth_cloud};
use std::path::PathBuf;
use std::process::ExitCode;

#[path = "common/ems.rs"]
mod ems;
#[path = "common/mode.rs"]
mod mode;
#[path = "common/ply.rs"]
mod ply;

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    if v.is_empty() {
        f64::NAN
    } else {
        v[v.len() / 2]
    }
}

fn cell(e: &ParameterErrors) -> String {
    format!(
        "{:.3} / {:.3} / {:.3} / {:.1}°",
        e.axes, e.epsilon, e.translation, e.rotation_deg
    )
}

fn main() -> ExitCode {
    let benched = mode::benched();
    let mut clouds = if benched { 20u64 } else { 2 };
    let mut export: Option<PathBuf> = None;
    let mut ems_file: Option<PathBuf> = None;
    // Under `cargo test` the arguments are the test runner's (a filter), not ours.
    let mut args = std::env::args()
        .skip(1)
        .filter(|a| a != "--bench")
        .filter(|_| benched);
    while let Some(a) = args.next() {
        match (a.as_str(), args.next()) {
            ("--clouds", Some(n)) => match n.parse() {
                Ok(n) => clouds = n,
                Err(_) => {
                    eprintln!("--clouds {n}: expected a count");
                    return ExitCode::from(2);
                }
            },
            ("--export", Some(dir)) => export = Some(PathBuf::from(dir)),
            ("--ems", Some(file)) => ems_file = Some(PathBuf::from(file)),
            _ => {
                eprintln!("usage: ground_truth [--clouds N] [--export DIR] [--ems FILE]");
                return ExitCode::from(2);
            }
        }
    }
    if let Some(dir) = &export
        && let Err(e) = std::fs::create_dir_all(dir)
    {
        eprintln!("{}: {e}", dir.display());
        return ExitCode::from(2);
    }
    let ems_fits = match ems::read_results(ems_file.as_deref()) {
        Ok(r) => r,
        Err(e) => {
            eprintln!("{e}");
            return ExitCode::from(2);
        }
    };
    println!(
        "| cloud | ε1, ε2 (truth) | ours, global only: axes / ε / translation / rotation | ours, `--robust`, dynamics | ours, `--robust`, solved (the default) | EMS |"
    );
    println!("|---|---|---|---|---|---|");
    let (mut plain, mut robust, mut solved, mut theirs) =
        (Vec::new(), Vec::new(), Vec::new(), Vec::new());
    let (mut local_rows, mut local) = (Vec::new(), Vec::new());
    let mut truths = String::new();
    for seed in 1..=clouds {
        let c = ground_truth_cloud(seed, &CloudRecipe::default());
        let t = &c.truth;
        if let Some(dir) = &export {
            let path = dir.join(format!("cloud_{seed}.ply"));
            if let Err(e) = ply::write_ascii(&path, &c.points) {
                eprintln!("{}: {e}", path.display());
                return ExitCode::from(2);
            }
            truths += &ply::truth_line(&format!("cloud_{seed}"), t);
        }
        let inliers = &c.points[..c.points.len() - c.outliers];
        let diagonal = bounding_diagonal(inliers);
        // Parameter errors and the inliers' mean distance to the fitted surface over their
        // bounding-box diagonal.
        let score = |opts: FitOptions| {
            fit(&c.points, &opts, |_| {}).map(|r| {
                let mut x = Vec::new();
                r.state.node_positions(&r.tess, &mut x);
                let d = point_distances(&r.tess, &x, inliers);
                let mean = d.iter().sum::<f64>() / d.len().max(1) as f64 / diagonal;
                (
                    ParameterErrors::of(t, &InitialPose::of(&r.state)),
                    mean,
                    r.steps,
                )
            })
        };
        // The paper's springs, through the paper's dynamics.
        let global = FitOptions {
            global_only: true,
            solver: Solver::Dynamics,
            ..Default::default()
        };
        let paper_local = FitOptions {
            solver: Solver::Dynamics,
            ..Default::default()
        };
        let (defaults, _) = FitOptions::default()
            .for_data()
            .with_stiffness_from_noise(&c.points);
        let solved_robust = FitOptions {
            solver: Solver::Solved,
            ..global.robust()
        };
        let runs = [
            global,
            global.robust(),
            solved_robust,
            paper_local,
            defaults,
        ]
        .map(score);
        let [
            (p, _, _),
            (r, _, _),
            (l, pure, _),
            (_, paper_local, paper_steps),
            (_, ours_local, ours_steps),
        ] = match runs.into_iter().collect::<Result<Vec<_>, _>>() {
            Ok(v) => [v[0], v[1], v[2], v[3], v[4]],
            Err(e) => {
                eprintln!("cloud {seed}: {e}");
                return ExitCode::from(2);
            }
        };
        let figures: Vec<f64> = [p, r, l]
            .into_iter()
            .flat_map(|e| [e.axes, e.epsilon, e.translation, e.rotation_deg])
            .chain([pure, paper_local, ours_local])
            .collect();
        if let Err(e) = mode::check_finite(&format!("cloud {seed}"), &figures) {
            eprintln!("{e}");
            return ExitCode::FAILURE;
        }
        local_rows.push(format!(
            "| {seed} | {pure:.4} | {paper_local:.4} ({paper_steps}) | {ours_local:.4} ({ours_steps}) | {:.1} |",
            pure / ours_local
        ));
        local.push([pure, paper_local, ours_local]);
        let name = format!("cloud_{seed}");
        let ems = ems_fits
            .iter()
            .find(|f| f.cloud == name)
            .map(|f| ParameterErrors::of(t, &f.pose()));
        println!(
            "| {seed} | {:.2}, {:.2} | {} | {} | {} | {} |",
            t.shape.e1,
            t.shape.e2,
            cell(&p),
            cell(&r),
            cell(&l),
            ems.as_ref().map_or("–".into(), cell)
        );
        plain.push(p);
        robust.push(r);
        solved.push(l);
        theirs.extend(ems);
    }
    let medians = |v: &[ParameterErrors]| ParameterErrors {
        axes: median(v.iter().map(|e| e.axes).collect()),
        epsilon: median(v.iter().map(|e| e.epsilon).collect()),
        translation: median(v.iter().map(|e| e.translation).collect()),
        rotation_deg: median(v.iter().map(|e| e.rotation_deg).collect()),
    };
    println!(
        "| median | | {} | {} | {} | {} |",
        cell(&medians(&plain)),
        cell(&medians(&robust)),
        cell(&medians(&solved)),
        cell(&medians(&theirs))
    );
    println!();
    println!(
        "| cloud | pure superquadric (`--robust --global-only`) | with local DOFs, the paper's forces and stiffness (steps) | with local DOFs, the fitter's defaults (steps) | pure ÷ defaults |"
    );
    println!("|---|---|---|---|---|");
    for row in &local_rows {
        println!("{row}");
    }
    let column = |i: usize| median(local.iter().map(|r: &[f64; 3]| r[i]).collect());
    println!(
        "| median | {:.4} | {:.4} | {:.4} | {:.1} |",
        column(0),
        column(1),
        column(2),
        median(local.iter().map(|r| r[0] / r[2]).collect())
    );
    if let Some(dir) = &export
        && let Err(e) = std::fs::write(dir.join("truth.jsonl"), truths)
    {
        eprintln!("{}: {e}", dir.join("truth.jsonl").display());
        return ExitCode::from(2);
    }
    ExitCode::SUCCESS
}
