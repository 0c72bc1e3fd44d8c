//! The fitter's defaults swept over generated clouds whose truth is known
//! (`synthetic::set_cloud`), set by set:
//!
//! - `mixed`: partial views, noise 0–5 %, outliers 0–40 % (uniform in a box, or Gaussian about
//!   the object), exponents over [0.1, 1.9];
//! - `outliers`: 40 % outliers in a Gaussian as wide as the object, 60 % seen, noise 2 %;
//! - `partial`: 20 % outliers, 40 % seen, noise 1 %;
//! - `deformed`: tapered and bent truths, fitted with `--taper --bend`.
//!
//! ```text
//! cargo bench --bench sweep [-- --set NAME|all] [--clouds N] [--local] [--export DIR] [--ems FILE]
//! ```
//!
//! Each cloud is fitted as `dsq fit CLOUD [--global-only]` fits it (`CloudOptions`, the defaults
//! for a user's cloud) and scored three ways:
//!
//! - **truth**: the mean distance from the noise-free samples of the seen part of the true
//!   surface to the fitted surface, over the inliers' bounding-box diagonal: how far the fit lies
//!   from the object;
//! - **inliers**: the same for the noisy surface points;
//! - **÷ floor**: the inliers' mean distance to the fit over their mean distance to the true
//!   surface. 1 explains them as well as the truth does; a fit several times above 1 has missed
//!   the object.
//!
//! Prints a row per cloud, then for each set the worst and the median, and how many clouds are
//! within 1.1 of the floor. `--local` fits with local DOFs (the default fit); without it a pure
//! superquadric (`--global-only`). `--clouds N` (default 64) clouds per set. `--export DIR` writes
//! each cloud as `DIR/SET_N.ply` and the truths as `DIR/truth.jsonl`; `--ems FILE` reads another
//! fitter's superquadrics of those clouds (JSON lines with `cloud`, `shape` [ε1, ε2], `scale`
//! [3 semi-axes], `translation` and `rot`, 9 numbers row-major) and scores them the same way.
//! `cargo test` runs two clouds of each set and fails when a figure is not finite.

use bevy_deformable_sq::model::fit::{CloudOptions, FitOptions, fit, fit_residuals};
use bevy_deformable_sq::model::fit::{bounding_diagonal, surface_distances};
use bevy_deformable_sq::model::lm::{DeformedPose, deformed_distances};
use bevy_deformable_sq::synthetic::{GroundTruthCloud, SweepSet, set_cloud};
use glam::DVec3;
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

fn worst(v: &[f64]) -> f64 {
    v.iter().copied().fold(0.0, f64::max)
}

/// What the command line asked for.
struct Args {
    sets: Vec<SweepSet>,
    clouds: u64,
    local: bool,
    export: Option<PathBuf>,
    ems: Option<PathBuf>,
}

const USAGE: &str = "usage: sweep [--set mixed|outliers|partial|deformed|all] [--clouds N] [--local] [--export DIR] [--ems FILE]";

fn parse(benched: bool) -> Result<Args, String> {
    let mut a = Args {
        sets: SweepSet::ALL.to_vec(),
        clouds: if benched { 64 } else { 2 },
        local: false,
        export: None,
        ems: None,
    };
    let mut args = std::env::args()
        .skip(1)
        .filter(|a| a != "--bench")
        .filter(|_| benched);
    while let Some(flag) = args.next() {
        match flag.as_str() {
            "--local" => a.local = true,
            "--set" => {
                let name = args.next().unwrap_or_default();
                a.sets = match (name.as_str(), SweepSet::from_name(&name)) {
                    ("all", _) => SweepSet::ALL.to_vec(),
                    (_, Some(s)) => vec![s],
                    _ => return Err(format!("--set: no set is named {name:?}\n{USAGE}")),
                }
            }
            "--clouds" => {
                a.clouds = args
                    .next()
                    .and_then(|n| n.parse().ok())
                    .ok_or("--clouds: expected a count")?
            }
            "--export" => a.export = Some(args.next().ok_or("--export: expected a folder")?.into()),
            "--ems" => a.ems = Some(args.next().ok_or("--ems: expected a file")?.into()),
            _ => return Err(USAGE.into()),
        }
    }
    Ok(a)
}

/// The mean distance of `points` from the cloud's true surface.
fn from_truth(c: &GroundTruthCloud, points: &[DVec3]) -> f64 {
    if c.deformation.is_identity() {
        mean(&surface_distances(&c.truth, points))
    } else {
        let truth = DeformedPose {
            pose: c.truth,
            deformation: c.deformation,
        };
        mean(&deformed_distances(&truth, points))
    }
}

/// One set's figures.
#[derive(Default)]
struct Tally {
    truth: Vec<f64>,
    floor: Vec<f64>,
    other_truth: Vec<f64>,
    other_floor: Vec<f64>,
    ms: Vec<f64>,
}

impl Tally {
    fn print(&self, set: SweepSet) {
        summary(set.name(), &self.truth, &self.floor);
        println!("    median {:.0} ms", median(self.ms.clone()));
        if !self.other_floor.is_empty() {
            summary(
                &format!("{} (other)", set.name()),
                &self.other_truth,
                &self.other_floor,
            );
        }
    }
}

/// One fitter's line of a set: its truth errors' worst and median, and its inliers ÷ floor.
fn summary(name: &str, truth: &[f64], floor: &[f64]) {
    println!(
        "{name}: truth worst {:.5}, median {:.5}; ÷ floor worst {:.2}, median {:.3}, ≤ 1.1 on {} of {}, > 1.5 on {}",
        worst(truth),
        median(truth.to_vec()),
        worst(floor),
        median(floor.to_vec()),
        floor.iter().filter(|&&r| r <= 1.1).count(),
        floor.len(),
        floor.iter().filter(|&&r| r > 1.5).count(),
    );
}

fn main() -> ExitCode {
    let a = match parse(mode::benched()) {
        Ok(a) => a,
        Err(e) => {
            eprintln!("{e}");
            return ExitCode::from(2);
        }
    };
    let theirs = match ems::read_results(a.ems.as_deref()) {
        Ok(r) => r,
        Err(e) => {
            eprintln!("{e}");
            return ExitCode::from(2);
        }
    };
    if let Some(dir) = &a.export
        && let Err(e) = std::fs::create_dir_all(dir)
    {
        eprintln!("{}: {e}", dir.display());
        return ExitCode::from(2);
    }
    println!(
        "| cloud | points | seen | noise | outliers | ε1, ε2 (truth) | ε1, ε2 (fit) | truth | inliers | ÷ floor | ms | other: truth | other: ÷ floor |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|---|---|---|");
    let mut truths = String::new();
    let mut tallies = Vec::new();
    for &set in &a.sets {
        let deformed = set == SweepSet::Deformed;
        let opts = match (CloudOptions {
            global_only: !a.local,
            taper: deformed,
            bend: deformed,
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
        let mut tally = Tally::default();
        for i in 1..=a.clouds {
            let name = format!("{}_{i}", set.name());
            let (r, c) = set_cloud(set, i);
            let inliers = &c.points[..c.points.len() - c.outliers];
            if let Some(dir) = &a.export {
                let path = dir.join(format!("{name}.ply"));
                if let Err(e) = ply::write_ascii(&path, &c.points) {
                    eprintln!("{}: {e}", path.display());
                    return ExitCode::from(2);
                }
                truths += &ply::truth_line(&name, &c.truth);
            }
            let start = Instant::now();
            let report = match fit(&c.points, &opts, |_| {}) {
                Ok(report) => report,
                Err(e) => {
                    eprintln!("{name}: {e}");
                    return ExitCode::FAILURE;
                }
            };
            let ms = start.elapsed().as_secs_f64() * 1e3;
            let diagonal = bounding_diagonal(inliers);
            let floor = from_truth(&c, inliers);
            let scale = |r: bevy_deformable_sq::model::fit::Residuals| r.mean * r.diagonal;
            let truth = scale(fit_residuals(&report.tess, &report.state, &c.surface)) / diagonal;
            let inlier = scale(fit_residuals(&report.tess, &report.state, inliers));
            let other = theirs.iter().find(|f| f.cloud == name).map(|f| {
                let pose = f.pose();
                (
                    mean(&surface_distances(&pose, &c.surface)) / diagonal,
                    mean(&surface_distances(&pose, inliers)) / floor,
                )
            });
            let other = other.filter(|_| r.noise > 0.0);
            // A noise-free cloud has no floor to be measured against.
            let ratio = (r.noise > 0.0).then_some(inlier / floor);
            if let Err(e) = mode::check_finite(&name, &[truth, ratio.unwrap_or(0.0)]) {
                eprintln!("{e}");
                return ExitCode::FAILURE;
            }
            let (t, f) = (c.truth.shape, report.state.shape);
            println!(
                "| {name} | {} | {:.0} % | {:.0} % | {:.0} % {:?} | {:.2}, {:.2} | {:.2}, {:.2} | {truth:.5} | {:.5} | {} | {ms:.0} | {} | {} |",
                r.surface_points,
                r.kept * 100.0,
                r.noise * 100.0,
                r.outliers * 100.0,
                r.outlier_spread,
                t.e1,
                t.e2,
                f.e1,
                f.e2,
                inlier / diagonal,
                ratio.map_or("–".into(), |r| format!("{r:.2}")),
                other.map_or("–".into(), |o| format!("{:.5}", o.0)),
                other.map_or("–".into(), |o| format!("{:.2}", o.1)),
            );
            tally.truth.push(truth);
            tally.floor.extend(ratio);
            tally.ms.push(ms);
            if let Some((t, f)) = other {
                tally.other_truth.push(t);
                tally.other_floor.push(f);
            }
        }
        tallies.push((set, tally));
    }
    println!();
    for (set, tally) in &tallies {
        tally.print(*set);
    }
    if let Some(dir) = &a.export
        && let Err(e) = std::fs::write(dir.join("truth.jsonl"), truths)
    {
        eprintln!("{}: {e}", dir.join("truth.jsonl").display());
        return ExitCode::from(2);
    }
    ExitCode::SUCCESS
}
