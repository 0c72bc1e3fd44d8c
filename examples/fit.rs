//! Command-line fitter: fits a deformable superquadric to a point cloud.
//!
//! ```text
//! cargo run --release --example fit -- (POINTS | --image IMAGE | --scene FILE | --paper egg|mug|pestle|doll)
//!     [--nodes N | --k K] [--w0 F] [--w1 F|auto] [--beta F] [--max-steps N] [--out-mesh FILE.obj]
//!     [--out-params FILE.json] [--quiet]
//!     points only: [--global-only] [--paper-forces] [--plane] [--outliers F] [--refine] [--switch]
//!                  [--similar] [--robust] [--migrate] [--reassign N] [--parts N] [--app] [--taper]
//!                  [--bend] [--implicit-local GAMMA]
//!     images only: [--sigma PX] [--band F] [--region F] [--paper-band] [--free-depth]
//!                  [--part x0,y0,x1,y1,x2,y2,x3,y3]... [--parts N] [--out-overlay FILE.png]
//!     scenes only: [--out-scene FILE.dsq.ron]
//! ```
//!
//! POINTS is an OBJ (vertices are the points) or PLY file; `--paper egg` / `--paper mug` runs the
//! paper's range experiment on its rebuilt data with the paper's settings, `--paper pestle` /
//! `--paper doll` its image experiments on the shipped stand-in images (options given after it
//! override them). IMAGE is a PNG or JPEG; each `--part` places one part from four pixel points
//! (both ends of the major axis, then both ends of the minor axis); without `--part` the `--parts`
//! largest blobs of the thresholded image are fitted (default 1). `--out-overlay` draws the fitted
//! outlines over the image. `--scene` runs every part of a scene file (see
//! `bevy_deformable_sq::scene`) to rest with the scene's settings (`--max-steps` caps each part),
//! printing one line per part; `--out-scene` writes the scene back with the fitted states.
//! Image fits print one JSON line per part, then one for the image
//! (`outline_*`: mean P/P_ref along the projected outlines; `iou_*`: silhouettes vs foreground). `--app` runs the same fit through `DeformableSqPlugin` in a headless Bevy app
//! (every initial hypothesis an entity, simulated in parallel); the result is the same. Progress goes to stderr; the last line
//! on stdout is a one-line JSON summary. `--robust` is `--outliers 0.2 --plane --refine --switch
//! --similar` (`FitOptions::robust`): the most accurate pure superquadric on partial or outlier-ridden clouds.
//! A POINTS file is fitted by default with `--outliers 0.2 --plane --w1 auto`, and with `--robust`
//! when `--global-only` (without `--app`); `--paper-forces` starts from the paper's springs and
//! stiffness instead (equal weights, nearest-node springs, w0 = 1e-3, w1 = 0.1), to which the
//! other flags add. `--outliers`, `--w0` and `--w1` given explicitly are kept.
//! `--taper` and `--bend` free the global tapering and bending of `model::deform` (beyond the paper)
//! for curved, tapered objects; the summary then carries `taper` and `bend`.
//! `--implicit-local GAMMA` takes the membrane's update as one backward-Euler step solved by
//! conjugate gradients with local damping γ_d = GAMMA (`DynamicsParams::implicit_local`, beyond
//! the paper; e.g. 0.01): fewer joint steps, each dearer (BENCHMARKS.md, log entry 23).
//! Bad input exits with code 2 and a one-line message.

use bevy::math::{DVec2, DVec3};
use bevy_deformable_sq::io::{
    FittedParams, load_luminance, load_points, write_model_obj, write_obj, write_overlay_png,
};
use bevy_deformable_sq::model::dynamics::ModelState;
use bevy_deformable_sq::model::fem::Tessellation;
use bevy_deformable_sq::model::fit::FitReport;
use bevy_deformable_sq::model::fit::{
    FitOptions, Residuals, Stage, bounding_diagonal, fit, point_distances,
};
use bevy_deformable_sq::model::forces::image::{DEFAULT_SIGMA, ImageFrame, ImagePotential};
use bevy_deformable_sq::model::forces::range::InfluenceMode;
use bevy_deformable_sq::model::image_fit::ImagePartFit;
use bevy_deformable_sq::model::image_fit::{
    ImageFitOptions, PartAxes, doll_experiment, fit_image, outline_potential, outline_segments,
    parts_on, pestle_experiment, segment, silhouette_iou,
};
use bevy_deformable_sq::model::parts::fit_parts;
use bevy_deformable_sq::plugin::headless::fit_headless;
use bevy_deformable_sq::scene::{PartRun, SceneData, SceneDef, Split, run_scene};
use bevy_deformable_sq::synthetic;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::Arc;
use std::time::Duration;
use std::time::Instant;

const USAGE: &str = "usage: fit (POINTS | --image IMAGE | --scene FILE | --paper egg|mug|pestle|doll) [--nodes N | --k K] [--w0 F] [--w1 F|auto] [--beta F] \
[--max-steps N] [--out-mesh FILE.obj] [--out-params FILE.json] [--quiet]; points: [--global-only] [--paper-forces] [--plane] [--outliers F] [--refine] [--switch] [--similar] [--robust] [--migrate] [--reassign N] [--parts N] [--app] [--taper] [--bend] [--implicit-local GAMMA]; \
images: [--sigma PX] [--band F] [--region F] [--paper-band] [--free-depth] [--part x0,y0,x1,y1,x2,y2,x3,y3]... [--parts N] [--out-overlay FILE.png]; scenes: [--out-scene FILE.dsq.ron]";

/// Where the data come from.
enum Source {
    File(PathBuf),
    Paper(&'static str),
    Image(PathBuf),
    Scene(PathBuf),
}

struct Args {
    source: Source,
    options: FitOptions,
    image: ImageArgs,
    out_mesh: Option<PathBuf>,
    out_params: Option<PathBuf>,
    quiet: bool,
    app: bool,
    out_scene: Option<PathBuf>,
    max_steps_override: Option<u32>,
    /// w0 and w1 from the noise the points show (`--w1 auto`, or the default for POINTS).
    stiffness_from_noise: bool,
    /// `--w1 auto` was given: an estimate that cannot be made is an error.
    stiffness_asked: bool,
}

fn parse_args() -> Result<(Args, Option<Vec<DVec3>>), String> {
    let mut args = std::env::args().skip(1);
    let mut points = None;
    let mut paper = None;
    let mut o = FitOptions::default();
    let mut image = ImageArgs::default();
    let mut image_path = None;
    let mut scene_path = None;
    let mut max_steps_override = None;
    let mut out_scene = None;
    let (mut stiffness_from_noise, mut stiffness_asked) = (false, false);
    // What the data-driven defaults of a POINTS fit must leave alone.
    let (mut paper_forces, mut outliers_given, mut stiffness_given) = (false, false, false);
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
                image.options.k = k;
            }
            "--k" => {
                o.k = value(&a, args.next())?;
                if o.k < 3 {
                    return Err(format!("--k {}: k must be at least 3", o.k));
                }
                image.options.k = o.k;
            }
            "--w0" => {
                stiffness_given = true;
                o.dynamics.w0 = finite(&a, value(&a, args.next())?, 0.0)?;
                image.options.dynamics.w0 = o.dynamics.w0;
            }
            "--w1" => match args.next() {
                Some(v) if v == "auto" => {
                    stiffness_from_noise = true;
                    stiffness_asked = true;
                }
                v => {
                    stiffness_given = true;
                    o.dynamics.w1 = finite(&a, value(&a, v)?, 0.0)?;
                    image.options.dynamics.w1 = o.dynamics.w1;
                }
            },
            "--beta" => {
                o.beta = finite(&a, value(&a, args.next())?, f64::MIN_POSITIVE)?;
                image.options.beta = o.beta;
            }
            "--scene" => {
                scene_path = Some(PathBuf::from(args.next().ok_or("--scene needs a file")?))
            }
            "--out-scene" => {
                out_scene = Some(PathBuf::from(
                    args.next().ok_or("--out-scene needs a file")?,
                ))
            }
            "--image" => {
                image_path = Some(PathBuf::from(args.next().ok_or("--image needs a file")?))
            }
            "--sigma" => image.sigma = finite(&a, value(&a, args.next())?, f64::MIN_POSITIVE)?,
            "--band" => {
                image.options.band = finite(&a, value(&a, args.next())?, f64::MIN_POSITIVE)?
            }
            "--paper-band" => image.options.outline_only = false,
            "--free-depth" => image.options.planar = false,
            "--region" => image.options.region = finite(&a, value(&a, args.next())?, 0.0)?,
            "--parts" => image.auto_parts = value(&a, args.next())?,
            "--part" => {
                let v: String = args.next().ok_or("--part needs x0,y0,x1,y1,x2,y2,x3,y3")?;
                let n: Vec<f64> = v
                    .split(',')
                    .map(|t| t.trim().parse::<f64>())
                    .collect::<Result<_, _>>()
                    .map_err(|_| {
                        format!("--part {v:?}: expected 8 numbers x0,y0,x1,y1,x2,y2,x3,y3 (pixels)")
                    })?;
                if n.len() != 8 || !n.iter().all(|x| x.is_finite()) {
                    return Err(format!(
                        "--part {v:?}: expected 8 finite numbers x0,y0,x1,y1,x2,y2,x3,y3 (pixels)"
                    ));
                }
                image
                    .parts
                    .push([0, 2, 4, 6].map(|i| DVec2::new(n[i], n[i + 1])));
            }
            "--out-overlay" => {
                image.overlay = Some(PathBuf::from(
                    args.next().ok_or("--out-overlay needs a file")?,
                ))
            }
            "--reassign" => o.reassign_every = value::<u32>(&a, args.next())?.max(1),
            "--max-steps" => {
                o.max_steps = value(&a, args.next())?;
                max_steps_override = Some(o.max_steps);
                image.options.max_steps = o.max_steps as usize;
            }
            "--paper" => {
                let name = args
                    .next()
                    .ok_or("--paper needs egg, mug, pestle or doll")?;
                let image_experiment = match name.as_str() {
                    "pestle" => Some(pestle_experiment()),
                    "doll" => Some(doll_experiment()),
                    _ => None,
                };
                if let Some(e) = image_experiment {
                    image_path = Some(PathBuf::from(env!("CARGO_MANIFEST_DIR")).join(e.image));
                    image.sigma = e.sigma;
                    image.options = e.options;
                    image.parts = e.parts.iter().map(|p| p.1).collect();
                    continue;
                }
                let (pts, opts) = match name.as_str() {
                    "egg" => synthetic::egg_experiment(),
                    "mug" => synthetic::mug_experiment(),
                    _ => return Err(format!("--paper {name}: expected egg, mug, pestle or doll")),
                };
                paper = Some((if name == "egg" { "egg" } else { "mug" }, pts));
                o = opts;
            }
            "--global-only" => o.global_only = true,
            "--taper" => o.dynamics.free.taper = true,
            "--bend" => o.dynamics.free.bend = true,
            "--plane" => o.point_to_plane = true,
            "--refine" => o.refine = true,
            "--switch" => o.switch_cross_section = true,
            "--similar" => o.similarity_switch = true,
            "--robust" => o = o.robust(),
            "--paper-forces" => paper_forces = true,
            "--outliers" => {
                outliers_given = true;
                let v = args.next().ok_or("--outliers needs a fraction in [0, 1)")?;
                o.outlier_ratio = v
                    .parse()
                    .ok()
                    .filter(|f: &f64| (0.0..1.0).contains(f))
                    .ok_or(format!("--outliers {v}: expected a fraction in [0, 1)"))?;
            }
            "--migrate" => o.influence = InfluenceMode::Migrating { rate: 0.5 },
            "--implicit-local" => {
                o.dynamics.implicit_local = true;
                o.dynamics.gamma_local = value(&a, args.next())?;
                if !(o.dynamics.gamma_local > 0.0) {
                    return Err(format!(
                        "--implicit-local {}: expected a local damping γ_d > 0",
                        o.dynamics.gamma_local
                    ));
                }
            }
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
    let (source, paper_points) = match (points, paper, image_path, scene_path) {
        (Some(p), None, None, None) => (Source::File(p), None),
        (None, Some((name, pts)), None, None) => (Source::Paper(name), Some(pts)),
        (None, None, Some(p), None) => (Source::Image(p), None),
        (None, None, None, Some(p)) => (Source::Scene(p), None),
        (None, None, None, None) => return Err(format!("no POINTS file given\n{USAGE}")),
        _ => {
            return Err(format!(
                "give one of POINTS, --paper, --image or --scene\n{USAGE}"
            ));
        }
    };
    if matches!(source, Source::File(_)) && !paper_forces {
        // The defaults for a user's cloud (README "The command-line fitter"): outlier-robust
        // weights, point-to-plane springs in the global stage and the membrane's stiffness from
        // the noise; a pure superquadric also gets the refining stage and the cross-section
        // switch.
        let given = o;
        o = o.for_data();
        if outliers_given {
            o.outlier_ratio = given.outlier_ratio;
        }
        // (w0 and w1 act on the local DOFs only.)
        stiffness_from_noise |= !stiffness_given && !o.global_only;
    }
    if paper_forces && !matches!(source, Source::File(_)) {
        return Err(
            "--paper-forces acts on POINTS fits (--paper, --image and --scene keep their own settings)"
                .into(),
        );
    }
    if out_scene.is_some() && !matches!(source, Source::Scene(_)) {
        return Err(format!("--out-scene needs --scene\n{USAGE}"));
    }
    if (o.dynamics.free.taper || o.dynamics.free.bend)
        && matches!(source, Source::Image(_) | Source::Scene(_))
    {
        return Err(
            "--taper and --bend act on point fits; a scene part frees them with free: (taper: true, bend: true)"
                .into(),
        );
    }
    if stiffness_from_noise && matches!(source, Source::Image(_) | Source::Scene(_)) {
        return Err(
            "--w1 auto reads the noise of a point cloud; give w1 a number for images and scenes"
                .into(),
        );
    }
    let args = Args {
        source,
        options: o,
        out_mesh,
        out_params,
        quiet,
        app,
        image,
        out_scene,
        max_steps_override,
        stiffness_from_noise,
        stiffness_asked,
    };
    Ok((args, paper_points))
}

fn run() -> Result<(), String> {
    let (args, paper_points) = parse_args()?;
    match &args.source {
        Source::Image(path) => return run_image(path, &args),
        Source::Scene(path) => return run_scene_file(path, &args),
        _ => {}
    }
    let (points, name) = match (&args.source, paper_points) {
        (Source::File(path), _) => (
            load_points(path).map_err(|e| e.to_string())?,
            path.display().to_string(),
        ),
        (Source::Paper(name), Some(pts)) => (pts, format!("paper:{name}")),
        (Source::Paper(name), None) => return Err(format!("no data for --paper {name}")),
        (Source::Image(_) | Source::Scene(_), _) => unreachable!("returned above"),
    };
    // The wall time includes the noise estimate.
    let start = Instant::now();
    // `--w1 auto`: the stiffness from the noise of the whole cloud.
    let (options, noise) = if args.stiffness_from_noise {
        let (o, noise) = args.options.with_stiffness_from_noise(&points);
        // Asked for, the estimate must be made; as a default, too few points keep the paper's
        // stiffness (and the fit itself says what is wrong with the cloud, if anything).
        if noise.is_none() && args.stiffness_asked {
            return Err(format!("{name}: too few points to estimate the noise"));
        }
        (o, noise)
    } else {
        (args.options, None)
    };
    let args = Args { options, ..args };
    if args.image.auto_parts > 1 {
        return run_parts(&points, &name, &args);
    }
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
                Stage::Refine => "refining",
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
    let through = if args.app { "plugin" } else { "core" };
    let mut summary = range_summary(
        &name,
        &report,
        points.len(),
        wall,
        through,
        args.options.global_only,
    );
    if let Some(noise) = noise {
        summary["noise"] = noise.relative.into();
        summary["w0"] = args.options.dynamics.w0.into();
        summary["w1"] = args.options.dynamics.w1.into();
    }
    println!("{summary}");
    Ok(())
}

/// `POINTS --parts N`: N parts on one cloud (`model::parts`), one JSON line per part (the point
/// fitter's, with `part` and its point count) and one for the whole.
fn run_parts(points: &[DVec3], name: &str, args: &Args) -> Result<(), String> {
    if args.app {
        return Err("--app fits one part; drop it or --parts".into());
    }
    let k = args.image.auto_parts;
    let start = Instant::now();
    let report = fit_parts(points, k, 8, &args.options).map_err(|e| format!("{name}: {e}"))?;
    let wall = start.elapsed();
    for (j, part) in report.fits.iter().enumerate() {
        let n = report.owner.iter().filter(|&&o| o == j).count();
        let mut line = range_summary(name, part, n, wall, "core", args.options.global_only);
        line["part"] = serde_json::json!(j);
        println!("{line}");
    }
    println!(
        "{}",
        serde_json::json!({
            "file": name,
            "parts": k,
            "points": points.len(),
            "rounds": report.rounds,
            "stable": report.stable,
            "wall_ms": (wall.as_secs_f64() * 1e4).round() / 10.0,
        })
    );
    Ok(())
}

/// Image-fit settings from the command line.
struct ImageArgs {
    options: ImageFitOptions,
    sigma: f64,
    parts: Vec<[DVec2; 4]>,
    auto_parts: usize,
    overlay: Option<PathBuf>,
}

impl Default for ImageArgs {
    fn default() -> Self {
        Self {
            options: ImageFitOptions::default(),
            sigma: DEFAULT_SIGMA,
            parts: Vec::new(),
            auto_parts: 1,
            overlay: None,
        }
    }
}

/// Fits parts to an image: placed by `--part` four-point sets, or else the `--parts` largest
/// blobs of the thresholded image. One JSON line per part, then one for the whole image.
fn run_image(path: &std::path::Path, args: &Args) -> Result<(), String> {
    let ia = &args.image;
    let (w, h, lum) = load_luminance(path).map_err(|e| e.to_string())?;
    let potential = Arc::new(
        ImagePotential::new(w, h, lum, ia.sigma, ImageFrame::default())
            .map_err(|e| format!("{}: {e}", path.display()))?,
    );
    let placed: Vec<PartAxes> = if ia.parts.is_empty() {
        let blobs = segment(&potential, (w * h / 1000).max(20));
        if blobs.is_empty() {
            return Err(format!(
                "{}: no foreground blob found to place a part",
                path.display()
            ));
        }
        blobs
            .iter()
            .take(ia.auto_parts.max(1))
            .map(|b| PartAxes::from_blob(&potential, b))
            .collect::<Result<_, _>>()
            .map_err(|e| format!("{}: {e}", path.display()))?
    } else {
        ia.parts
            .iter()
            .enumerate()
            .map(|(i, p)| {
                PartAxes::from_points(&potential, *p).map_err(|e| format!("--part {}: {e}", i + 1))
            })
            .collect::<Result<_, _>>()?
    };
    let start = Instant::now();
    let fits = fit_image(potential.clone(), &placed, &ia.options)
        .map_err(|e| format!("{}: {e}", path.display()))?;
    let wall = start.elapsed();
    let tess = Tessellation::new(ia.options.k);
    let positions = |state: &ModelState| {
        let mut x = Vec::new();
        state.node_positions(&tess, &mut x);
        x
    };
    let before: Vec<Vec<DVec3>> = placed.iter().map(|p| positions(&p.state(&tess))).collect();
    let after: Vec<Vec<DVec3>> = fits.iter().map(|f| positions(&f.state)).collect();
    if let Some(out) = &args.out_mesh {
        let mut vertices = Vec::new();
        let mut triangles = Vec::new();
        for x in &after {
            let base = vertices.len() as u32;
            vertices.extend_from_slice(x);
            triangles.extend(tess.triangles().iter().map(|t| t.map(|i| i + base)));
        }
        let note = format!(
            "{} deformable superquadrics fitted to {}",
            after.len(),
            path.display()
        );
        write_obj(out, &vertices, &triangles, &note).map_err(|e| e.to_string())?;
    }
    if let Some(out) = &ia.overlay {
        let outlines: Vec<_> = after.iter().map(|x| outline_segments(&tess, x)).collect();
        write_overlay_png(out, &potential, &outlines).map_err(|e| e.to_string())?;
    }
    let mut all_params = Vec::new();
    for (i, f) in fits.iter().enumerate() {
        let line = image_part_line(&path.display().to_string(), i + 1, f, tess.node_count());
        println!("{line}");
        all_params.push(line);
    }
    if let Some(out) = &args.out_params {
        let json = serde_json::to_string_pretty(&all_params).map_err(|e| e.to_string())?;
        std::fs::write(out, json).map_err(|e| format!("{}: cannot write: {e}", out.display()))?;
    }
    let summary = serde_json::json!({
        "file": path.display().to_string(), "parts": fits.len(),
        "wall_ms": (wall.as_secs_f64() * 1e4).round() / 10.0,
        "converged": fits.iter().all(|f| f.converged),
        "outline_before": outline_potential(&potential, &parts_on(&tess, &before)),
        "outline_after": outline_potential(&potential, &parts_on(&tess, &after)),
        "iou_before": silhouette_iou(&potential, &parts_on(&tess, &before)),
        "iou_after": silhouette_iou(&potential, &parts_on(&tess, &after)),
    });
    println!("{summary}");
    Ok(())
}

/// The one-line summary of a range fit (the point fitter's, and a range part's in a scene).
fn range_summary(
    name: &str,
    report: &FitReport,
    points: usize,
    wall: Duration,
    through: &str,
    global_only: bool,
) -> serde_json::Value {
    let (r, shape) = (report.residuals, report.state.shape);
    serde_json::json!({
        "file": name,
        "steps": report.steps,
        "global_steps": report.global_steps,
        "wall_ms": (wall.as_secs_f64() * 1e4).round() / 10.0,
        "steps_per_s": (report.steps as f64 / wall.as_secs_f64().max(1e-9)).round(),
        "points": points,
        "nodes": report.tess.node_count(),
        "global_only": global_only,
        "through": through,
        "converged": report.converged,
        "mean": r.mean,
        "rms": r.rms,
        "p95": r.p95,
        "max": r.max,
        "a": shape.a, "a1": shape.a1, "a2": shape.a2, "a3": shape.a3,
        "e1": shape.e1, "e2": shape.e2,
        "taper": report.state.deformation.taper, "bend": report.state.deformation.bend,
        "refine": report.refinement.map(|r| serde_json::json!({
            "steps": r.steps, "kept": r.kept, "gave_up": r.gave_up,
        })),
    })
}

/// The one-line summary of one part of an image fit.
fn image_part_line(file: &str, part: usize, f: &ImagePartFit, nodes: usize) -> serde_json::Value {
    let s = &f.state;
    serde_json::json!({
        "file": file, "part": part, "steps": f.steps,
        "global_steps": f.global_steps, "converged": f.converged, "nodes": nodes,
        "outline_before": f.outline_before, "outline_after": f.outline_after,
        "translation": s.translation.to_array(), "a": s.shape.a, "a1": s.shape.a1,
        "a2": s.shape.a2, "a3": s.shape.a3, "e1": s.shape.e1, "e2": s.shape.e2,
    })
}

/// Runs every part of a scene file to rest without a window: one JSON line per part (a range
/// part's as the point fitter's, an image part's as an image fit's), with the scene and the part's
/// name; `--out-mesh` writes every part into one OBJ, `--out-params` a JSON array of the lines,
/// `--out-scene` the scene with every part's fitted pose, shape and local displacements.
fn run_scene_file(path: &Path, args: &Args) -> Result<(), String> {
    let (mut def, data) = SceneDef::load_file(path).map_err(|e| e.to_string())?;
    let max_steps = args.max_steps_override;
    let start = Instant::now();
    let runs = run_scene(&def, &data, max_steps);
    let wall = start.elapsed();
    let file = path.display().to_string();
    let (mut lines, mut vertices, mut triangles) = (Vec::new(), Vec::new(), Vec::new());
    for (i, (run, part)) in runs.iter().zip(&def.parts).enumerate() {
        let run = run.as_ref().map_err(|e| format!("{file}: {e}"))?;
        let tess = Tessellation::new(part.k);
        let mut line = match run {
            PartRun::Range(report) => {
                let n = data.range_points(&def, i).map_or(0, |p| p.len());
                range_summary(&file, report, n, wall, "core", part.free.global_only)
            }
            PartRun::Image(f) => image_part_line(&file, i + 1, f, tess.node_count()),
            PartRun::Free(_) => serde_json::json!({ "file": file, "steps": 0, "converged": true }),
        };
        line["part"] = (i + 1).into();
        line["name"] = part.name.clone().into();
        if let Some(noise) = data.noise.get(&i) {
            line["noise"] = noise.relative.into();
            line["w0"] = part.w0.into();
            line["w1"] = part.w1.into();
        }
        println!("{line}");
        lines.push(line);
        let mut x = Vec::new();
        run.state().node_positions(&tess, &mut x);
        let base = vertices.len() as u32;
        vertices.extend_from_slice(&x);
        triangles.extend(tess.triangles().iter().map(|t| t.map(|i| i + base)));
    }
    for line in split_summaries(&def, &data, &runs, &file) {
        println!("{line}");
        lines.push(line);
    }
    if let Some(out) = &args.out_mesh {
        let note = format!("{} parts of scene {file}", def.parts.len());
        write_obj(out, &vertices, &triangles, &note).map_err(|e| e.to_string())?;
    }
    if let Some(out) = &args.out_params {
        let json = serde_json::to_string_pretty(&lines).map_err(|e| e.to_string())?;
        std::fs::write(out, json).map_err(|e| format!("{}: cannot write: {e}", out.display()))?;
    }
    if let Some(out) = &args.out_scene {
        for (i, run) in runs.iter().enumerate() {
            if let Ok(run) = run {
                def.set_state(i, run.state(), true);
            }
        }
        let from = path.parent().unwrap_or(Path::new(""));
        def.rebase(from, out.parent().unwrap_or(Path::new("")));
        def.save(out).map_err(|e| e.to_string())?;
    }
    Ok(())
}

/// One JSON line per source its parts share: how the split went and the distance of every point
/// to the surface of the part it pulls on, over the whole cloud's bounding-box diagonal.
fn split_summaries(
    def: &SceneDef,
    data: &SceneData,
    runs: &[Result<PartRun, String>],
    file: &str,
) -> Vec<serde_json::Value> {
    let mut sources: Vec<(&String, &Split)> = data.splits.iter().collect();
    sources.sort_by_key(|(name, _)| *name);
    sources
        .into_iter()
        .map(|(name, split)| {
            let mut parts: Vec<usize> = split.owner.to_vec();
            parts.sort_unstable();
            parts.dedup();
            let mut d = Vec::new();
            for &i in &parts {
                let (Some(Ok(run)), Some(pts)) = (runs.get(i), data.range_points(def, i)) else {
                    continue;
                };
                let tess = Tessellation::new(def.parts[i].k);
                let mut x = Vec::new();
                run.state().node_positions(&tess, &mut x);
                d.extend(point_distances(&tess, &x, &pts));
            }
            let all = data.points.get(name).map_or(&[][..], |p| p.as_slice());
            let r = Residuals::of(d, bounding_diagonal(all));
            serde_json::json!({
                "file": file, "data": name, "parts": parts.len(), "points": all.len(),
                "rounds": split.rounds, "stable": split.stable, "moved": split.moved,
                "mean": r.mean, "p95": r.p95, "max": r.max,
            })
        })
        .collect()
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
