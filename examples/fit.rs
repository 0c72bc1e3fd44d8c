//! Command-line fitter: fits a deformable superquadric to a point cloud.
//!
//! ```text
//! cargo run --release --example fit -- (POINTS | --paper egg|mug) [--nodes N | --k K] [--w0 F] [--w1 F] [--beta F]
//!     [--global-only] [--migrate] [--reassign N] [--max-steps N] [--quiet] [--app]
//!     [--out-mesh FILE.obj] [--out-params FILE.json]
//! ```
//!
//! POINTS is an OBJ (vertices are the points) or PLY file; `--paper egg` / `--paper mug` runs the
//! paper's range experiment on its rebuilt data with the paper's settings (options given after it
//! override them). `--app` runs the same fit through `DeformableSqPlugin` in a headless Bevy app
//! (every initial hypothesis an entity, simulated in parallel); the result is the same. Progress goes to stderr; the last line
//! on stdout is a one-line JSON summary. Bad input exits with code 2 and a one-line message.

use bevy::math::DVec3;
use bevy_deformable_sq::io::{FittedParams, load_points, write_model_obj};
use bevy_deformable_sq::model::fit::{FitOptions, Stage, fit};
use bevy_deformable_sq::model::forces::range::InfluenceMode;
use bevy_deformable_sq::plugin::headless::fit_headless;
use bevy_deformable_sq::synthetic;
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;

const USAGE: &str = "usage: fit (POINTS | --paper egg|mug) [--nodes N | --k K] [--w0 F] [--w1 F] [--beta F] [--global-only] [--migrate] \
[--reassign N] [--max-steps N] [--quiet] [--app] [--out-mesh FILE.obj] [--out-params FILE.json]";

/// Where the points come from.
enum Source {
    File(PathBuf),
    Paper(&'static str),
}

struct Args {
    source: Source,
    options: FitOptions,
    out_mesh: Option<PathBuf>,
    out_params: Option<PathBuf>,
    quiet: bool,
    app: bool,
}

fn parse_args() -> Result<(Args, Option<Vec<DVec3>>), String> {
    let mut args = std::env::args().skip(1);
    let mut points = None;
    let mut paper = None;
    let mut o = FitOptions::default();
    let (mut out_mesh, mut out_params, mut quiet, mut app) = (None, None, false, false);
    fn value<T: std::str::FromStr>(flag: &str, v: Option<String>) -> Result<T, String> {
        let v = v.ok_or_else(|| format!("{flag} needs a value"))?;
        v.parse()
            .map_err(|_| format!("{flag}: cannot read {v:?} as a number"))
    }
    fn finite(flag: &str, v: f64, min: f64) -> Result<f64, String> {
        if v.is_finite() && v >= min {
            Ok(v)
        } else {
            Err(format!("{flag}: {v} must be a finite number ≥ {min}"))
        }
    }
    while let Some(a) = args.next() {
        match a.as_str() {
            "--nodes" => {
                let n: usize = value(&a, args.next())?;
                let k = (n.saturating_sub(2) as f64).sqrt().round() as usize;
                if k < 3 || k * k + 2 != n {
                    return Err(format!(
                        "--nodes {n}: a node count is k² + 2 with k ≥ 3 (e.g. 963, 1683, 2603, 5043); nearest is {}",
                        k.max(3) * k.max(3) + 2
                    ));
                }
                o.k = k;
            }
            "--k" => {
                o.k = value(&a, args.next())?;
                if o.k < 3 {
                    return Err(format!("--k {}: k must be at least 3", o.k));
                }
            }
            "--w0" => o.dynamics.w0 = finite(&a, value(&a, args.next())?, 0.0)?,
            "--w1" => o.dynamics.w1 = finite(&a, value(&a, args.next())?, 0.0)?,
            "--beta" => o.beta = finite(&a, value(&a, args.next())?, f64::MIN_POSITIVE)?,
            "--reassign" => o.reassign_every = value::<u32>(&a, args.next())?.max(1),
            "--max-steps" => o.max_steps = value(&a, args.next())?,
            "--paper" => {
                let name = args.next().ok_or("--paper needs egg or mug")?;
                let (pts, opts) = match name.as_str() {
                    "egg" => synthetic::egg_experiment(),
                    "mug" => synthetic::mug_experiment(),
                    _ => return Err(format!("--paper {name}: expected egg or mug")),
                };
                paper = Some((if name == "egg" { "egg" } else { "mug" }, pts));
                o = opts;
            }
            "--global-only" => o.global_only = true,
            "--migrate" => o.influence = InfluenceMode::Migrating { rate: 0.5 },
            "--quiet" => quiet = true,
            "--app" => app = true,
            "--out-mesh" => {
                out_mesh = Some(PathBuf::from(args.next().ok_or("--out-mesh needs a file")?))
            }
            "--out-params" => {
                out_params = Some(PathBuf::from(
                    args.next().ok_or("--out-params needs a file")?,
                ))
            }
            "-h" | "--help" => return Err(USAGE.into()),
            flag if flag.starts_with("--") => {
                return Err(format!("unknown option {flag}\n{USAGE}"));
            }
            p => {
                if points.replace(PathBuf::from(p)).is_some() {
                    return Err(format!("more than one POINTS file given\n{USAGE}"));
                }
            }
        }
    }
    let (source, paper_points) = match (points, paper) {
        (Some(p), None) => (Source::File(p), None),
        (None, Some((name, pts))) => (Source::Paper(name), Some(pts)),
        (Some(_), Some(_)) => return Err(format!("give POINTS or --paper, not both\n{USAGE}")),
        (None, None) => return Err(format!("no POINTS file given\n{USAGE}")),
    };
    let args = Args {
        source,
        options: o,
        out_mesh,
        out_params,
        quiet,
        app,
    };
    Ok((args, paper_points))
}

fn run() -> Result<(), String> {
    let (args, paper_points) = parse_args()?;
    let (points, name) = match (&args.source, paper_points) {
        (Source::File(path), _) => (
            load_points(path).map_err(|e| e.to_string())?,
            path.display().to_string(),
        ),
        (Source::Paper(name), Some(pts)) => (pts, format!("paper:{name}")),
        (Source::Paper(name), None) => return Err(format!("no data for --paper {name}")),
    };
    let start = Instant::now();
    let quiet = args.quiet;
    let mut last_print = Instant::now();
    let report = if args.app {
        fit_headless(&points, &args.options)
    } else {
        fit(&points, &args.options, |p| {
        if !quiet && (last_print.elapsed().as_millis() >= 500 || p.step.is_multiple_of(1000)) {
            last_print = Instant::now();
            let stage = match p.stage {
                Stage::Cover => "placing",
                Stage::Global => "global",
                Stage::Joint => "global+local",
            };
            let rate = p.step as f64 / start.elapsed().as_secs_f64().max(1e-9);
            eprintln!(
                "step {:>6}  {stage:<12}  motion {:.2e}  energy {:.4e}  reattached {:>3}x  {:.0} steps/s",
                p.step, p.max_motion, p.energy, p.reassignments, rate
            );
        }
        })
    }
    .map_err(|e| format!("{name}: {e}"))?;
    let wall = start.elapsed();
    if let Some(path) = &args.out_mesh {
        write_model_obj(path, &report.tess, &report.state).map_err(|e| e.to_string())?;
    }
    let params = FittedParams::from_report(&report);
    if let Some(path) = &args.out_params {
        let json = serde_json::to_string_pretty(&params).map_err(|e| e.to_string())?;
        std::fs::write(path, json).map_err(|e| format!("{}: cannot write: {e}", path.display()))?;
    }
    let r = report.residuals;
    let summary = serde_json::json!({
        "file": name,
        "steps": report.steps,
        "global_steps": report.global_steps,
        "wall_ms": (wall.as_secs_f64() * 1e4).round() / 10.0,
        "steps_per_s": (report.steps as f64 / wall.as_secs_f64().max(1e-9)).round(),
        "points": points.len(),
        "nodes": report.tess.node_count(),
        "global_only": args.options.global_only,
        "through": if args.app { "plugin" } else { "core" },
        "converged": report.converged,
        "mean": r.mean,
        "rms": r.rms,
        "p95": r.p95,
        "max": r.max,
        "a": params.shape.a, "a1": params.shape.a1, "a2": params.shape.a2, "a3": params.shape.a3,
        "e1": params.shape.e1, "e2": params.shape.e2,
    });
    println!("{summary}");
    Ok(())
}

fn main() -> ExitCode {
    match run() {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {}", e.lines().next().unwrap_or(""));
            for line in e.lines().skip(1) {
                eprintln!("{line}");
            }
            ExitCode::from(2)
        }
    }
}
