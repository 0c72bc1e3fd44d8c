//! `dsq fit`: runs a fit and prints its JSON lines (the point fitter's, an image's parts', a
//! scene's parts').

use crate::args::{Args, Source};
use bevy_deformable_sq::io::{
    load_image, load_points_sampled, write_model_obj, write_models_obj, write_obj,
    write_overlay_png,
};
use bevy_deformable_sq::model::dynamics::ModelState;
use bevy_deformable_sq::model::fem::Tessellation;
use bevy_deformable_sq::model::fit::{
    FitError, FitOptions, FitReport, Residuals, Stage, bounding_diagonal, fit, point_distances,
};
use bevy_deformable_sq::model::forces::image::{ImageFrame, ImagePotential};
use bevy_deformable_sq::model::image_fit::{
    ImagePartFit, PartAxes, fit_image, outline_potential, outline_segments, part_silhouette,
    parts_on, segment, silhouette_iou,
};
use bevy_deformable_sq::model::parts::{PartCount, fit_parts};
use bevy_deformable_sq::scene::{PartRun, SceneData, SceneDef, Split, run_scene};
use glam::DVec3;
use std::path::Path;
use std::sync::Arc;
use std::time::{Duration, Instant};

/// `--app`: the fit through the plugin in a headless Bevy app.
#[cfg(feature = "bevy")]
fn fit_through_app(points: &[DVec3], options: &FitOptions) -> Result<FitReport, FitError> {
    bevy_deformable_sq::plugin::headless::fit_headless(points, options)
}

/// `--app` without the `bevy` feature: refused when the options are resolved.
#[cfg(not(feature = "bevy"))]
fn fit_through_app(_: &[DVec3], _: &FitOptions) -> Result<FitReport, FitError> {
    unreachable!("--app is refused without the bevy feature")
}

/// Runs the fit `args` describes (`paper_points`: the data of `--paper egg|mug`) and prints its
/// JSON lines.
pub fn run(args: Args, paper_points: Option<Vec<DVec3>>) -> Result<(), String> {
    let (points, name) = match (&args.source, paper_points) {
        (Source::Image(path), _) => return run_image(path, &args),
        (Source::Scene(path), _) => return run_scene_file(path, &args),
        (Source::Files(files), _) => return crate::batch::run(files, &args),
        (Source::File(path), _) => (
            load_points_sampled(path, args.mesh_samples).map_err(|e| e.to_string())?,
            path.display().to_string(),
        ),
        (Source::Paper(name), Some(pts)) => (pts, format!("paper:{name}")),
        (Source::Paper(name), None) => return Err(format!("no data for --paper {name}")),
    };
    if let Some(count) = args.cloud_parts {
        return run_parts(&points, &name, count, &args);
    }
    let (summary, report) = fit_points(&points, &name, &args, !args.quiet)?;
    if let Some(path) = &args.out_mesh {
        write_model_obj(path, &report.tess, &report.state).map_err(|e| e.to_string())?;
    }
    if let Some(path) = &args.out_params {
        write_params(path, &report)?;
    }
    crate::emit(&summary);
    Ok(())
}

/// Writes a range fit's parameters (`--out-params`) as pretty JSON.
pub fn write_params(path: &Path, report: &FitReport) -> Result<(), String> {
    let json = serde_json::to_string_pretty(&report.summary()).map_err(|e| e.to_string())?;
    std::fs::write(path, json).map_err(|e| format!("{}: cannot write: {e}", path.display()))
}

/// Fits one cloud (`name` for the messages) with `args`' options; `progress`: a line on stderr
/// every half second. Gives the JSON summary line and the report.
pub fn fit_points(
    points: &[DVec3],
    name: &str,
    args: &Args,
    progress: bool,
) -> Result<(serde_json::Value, FitReport), String> {
    // The wall time includes the noise estimate.
    let start = Instant::now();
    let options = &args.options;
    let mut last_print = Instant::now();
    let report = if args.app {
        fit_through_app(points, options)
    } else {
        fit(points, options, |p| {
            if progress && (last_print.elapsed().as_millis() >= 500 || p.step.is_multiple_of(1000))
            {
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
    let through = if args.app { "plugin" } else { "core" };
    let summary = range_summary(name, &report, points.len(), wall, through);
    Ok((summary, report))
}

/// `POINTS --parts auto|N`: the cloud split into parts (`model::parts`), one JSON line per part
/// (the point fitter's, with `part` and its point count) and one for the whole; `--out-mesh`
/// writes every part into one OBJ, `--out-params` every part's parameters.
fn run_parts(points: &[DVec3], name: &str, count: PartCount, args: &Args) -> Result<(), String> {
    if args.app {
        return Err("--app fits one part; drop it or --parts".into());
    }
    let start = Instant::now();
    let whole = fit_parts(points, count, &args.options).map_err(|e| format!("{name}: {e}"))?;
    let wall = start.elapsed();
    let mut summaries = Vec::new();
    for (j, part) in whole.fits.iter().enumerate() {
        let n = whole.owner.iter().filter(|&&o| o == j).count();
        let mut line = range_summary(name, part, n, wall, "core");
        line["part"] = serde_json::json!(j);
        line["explained"] = serde_json::json!(whole.part_explained[j]);
        crate::emit(&line);
        summaries.push(part.summary());
    }
    if let Some(path) = &args.out_mesh {
        let models: Vec<_> = whole.fits.iter().map(|f| (&f.tess, &f.state)).collect();
        write_models_obj(path, &models).map_err(|e| e.to_string())?;
    }
    if let Some(path) = &args.out_params {
        let json = serde_json::to_string_pretty(&summaries).map_err(|e| e.to_string())?;
        std::fs::write(path, json).map_err(|e| format!("{}: cannot write: {e}", path.display()))?;
    }
    if let Some(path) = &args.out_scene {
        let Source::File(points_file) = &args.source else {
            return Err("--out-scene with --parts needs a POINTS file".into());
        };
        SceneDef::of_whole(points_file, path, &whole)
            .save(path)
            .map_err(|e| e.to_string())?;
    }
    let joints: Vec<[usize; 2]> = whole.joints.iter().map(|j| j.parts).collect();
    crate::emit(serde_json::json!({
        "file": name,
        "parts": whole.fits.len(),
        "joints": joints,
        "points": points.len(),
        "explained": whole.explained,
        "wall_ms": (wall.as_secs_f64() * 1e4).round() / 10.0,
    }));
    Ok(())
}

/// Fits parts to an image: placed by `--part` four-point sets, or else the `--parts` largest
/// blobs of the thresholded image. One JSON line per part, then one for the whole image.
fn run_image(path: &std::path::Path, args: &Args) -> Result<(), String> {
    let ia = &args.image;
    let (w, h, lum, rgb) = load_image(path).map_err(|e| e.to_string())?;
    let potential = Arc::new(
        ImagePotential::new(w, h, lum, ia.sigma, ImageFrame::default())
            .and_then(|p| p.with_colour(rgb))
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
        if !args.quiet {
            eprintln!(
                "{}: parts placed on the largest blobs of an Otsu threshold of the image; on a \
                 photo with a textured background they can land on it: place them with --part",
                path.display()
            );
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
        if let Some(why) = &f.stopped {
            eprintln!("{}: part {} stopped: {why}", path.display(), i + 1);
        }
        let mut line = image_part_line(&path.display().to_string(), i + 1, f, tess.node_count());
        let sil = part_silhouette(&potential, &tess, &after[i]);
        line["area_px"] = sil.area.into();
        line["width_px"] = ((sil.width * 10.0).round() / 10.0).into();
        line["on_foreground"] = ((sil.on_foreground * 1e3).round() / 1e3).into();
        crate::emit(&line);
        all_params.push(line);
    }
    if let Some(out) = &args.out_params {
        let json = serde_json::to_string_pretty(&all_params).map_err(|e| e.to_string())?;
        std::fs::write(out, json).map_err(|e| format!("{}: cannot write: {e}", out.display()))?;
    }
    let summary = serde_json::json!({
        "file": path.display().to_string(), "parts": fits.len(),
        "placed": if ia.parts.is_empty() { "blobs" } else { "points" },
        "wall_ms": (wall.as_secs_f64() * 1e4).round() / 10.0,
        "converged": fits.iter().all(|f| f.converged),
        "outline_before": outline_potential(&potential, &parts_on(&tess, &before)),
        "outline_after": outline_potential(&potential, &parts_on(&tess, &after)),
        "iou_before": silhouette_iou(&potential, &parts_on(&tess, &before)),
        "iou_after": silhouette_iou(&potential, &parts_on(&tess, &after)),
    });
    crate::emit(&summary);
    Ok(())
}

/// The one-line summary of a range fit (the point fitter's, and a range part's in a scene): the
/// fit's summary ([`FitReport::summary`]) with its residuals at the top level, and the run's
/// file, points, wall time and path.
fn range_summary(
    name: &str,
    report: &FitReport,
    points: usize,
    wall: Duration,
    through: &str,
) -> serde_json::Value {
    let mut line = report.summary().flat_json();
    line["file"] = name.into();
    line["points"] = points.into();
    line["wall_ms"] = ((wall.as_secs_f64() * 1e4).round() / 10.0).into();
    line["steps_per_s"] = (report.steps as f64 / wall.as_secs_f64().max(1e-9))
        .round()
        .into();
    line["through"] = through.into();
    line
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
        "stopped": f.stopped,
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
                range_summary(&file, report, n, wall, "core")
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
        crate::emit(&line);
        lines.push(line);
        let mut x = Vec::new();
        run.state().node_positions(&tess, &mut x);
        let base = vertices.len() as u32;
        vertices.extend_from_slice(&x);
        triangles.extend(tess.triangles().iter().map(|t| t.map(|i| i + base)));
    }
    for line in split_summaries(&def, &data, &runs, &file) {
        crate::emit(&line);
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
