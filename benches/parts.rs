//! Whole objects split into parts (`--parts auto`), measured on two sets nobody tuned on.
//!
//! ```text
//! cargo bench --bench parts -- creatures [--count N] [--local]
//! cargo bench --bench parts -- corpus [--dir DIR] [--mp FILE] [--scans] [--local] [--only A,B]
//! ```
//!
//! - **creatures**: `synthetic::creature` trees of 2–16 superquadrics (thin and thick limbs,
//!   some tapered or bent), 4000 points with 0.2 % noise, each as a closed surface and as a
//!   one-view scan (`--count` of each, default 120). A creature passes when the count found is
//!   within one of the truth; when it is right, each true part's points lie on average within
//!   1 % of the diagonal of the fitted parts. Prints a row per creature, the pass rates and the
//!   worst case.
//! - **corpus**: every `NAME.obj` (or `NAME_scan.obj` with `--scans`) of the corpus that
//!   `../shared/tools/fetch_corpus.py` fetched (default `~/.cache/dsq-corpus`), split as
//!   `dsq fit FILE --parts auto [--global-only]` splits it. Chamfer-L1 as `chamfer.py` measures
//!   it (as a % of the mesh's longest side: 20000 samples of the mesh by area against samples
//!   of the union of the parts), the least exposed part, the share of points explained and the
//!   time; beside Marching-Primitives' figures when `--mp` names `corpus_mps.json`. A scan's
//!   Chamfer is its scan-to-fit half, beside one part's.
//!
//! `cargo test` runs two small creatures and fails when a figure is not finite.

use bevy_deformable_sq::io::{load_points_sampled, sample_surface};
use bevy_deformable_sq::model::fit::{
    CloudOptions, FitOptions, bounding_diagonal, fit, point_distances,
};
use bevy_deformable_sq::model::init::InitialPose;
use bevy_deformable_sq::model::nearest::nearest_indices;
use bevy_deformable_sq::model::parts::{DEFAULT_MAX_PARTS, PartCount, Whole, fit_parts};
use bevy_deformable_sq::synthetic::creature;
use glam::DVec3;
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;

#[path = "common/mode.rs"]
mod mode;

fn options(local: bool) -> FitOptions {
    CloudOptions {
        global_only: !local,
        ..CloudOptions::default()
    }
    .resolve(FitOptions::default(), true)
    .expect("the defaults resolve")
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v.get(v.len() / 2).copied().unwrap_or(f64::NAN)
}

/// The mean distance of `points` to the nearest fitted part.
fn mean_error(points: &[DVec3], whole: &Whole) -> f64 {
    let mut best = vec![f64::INFINITY; points.len()];
    let mut x = Vec::new();
    for f in &whole.fits {
        f.state.node_positions(&f.tess, &mut x);
        for (b, d) in best.iter_mut().zip(point_distances(&f.tess, &x, points)) {
            *b = b.min(d);
        }
    }
    best.iter().sum::<f64>() / points.len().max(1) as f64
}

fn creatures(count: u64, local: bool) -> Result<(), String> {
    let opts = options(local);
    for view in [false, true] {
        let (mut within, mut exact, mut found_right, mut worst) = (0, 0, 0, (0.0f64, 0u64));
        let mut times = Vec::new();
        for seed in 0..count {
            let parts = 2 + (seed % 15) as usize;
            let c = creature(1000 + seed, parts, 4000, 0.002, view);
            let t = Instant::now();
            let whole = fit_parts(&c.points, PartCount::Auto(DEFAULT_MAX_PARTS), &opts)
                .map_err(|e| e.to_string())?;
            times.push(t.elapsed().as_secs_f64());
            let diagonal = bounding_diagonal(&c.points);
            let errors: Vec<f64> = (0..parts)
                .map(|j| {
                    let mine: Vec<DVec3> = c
                        .points
                        .iter()
                        .zip(&c.owner)
                        .filter(|(_, o)| **o == j)
                        .map(|(p, _)| *p)
                        .collect();
                    mean_error(&mine, &whole) / diagonal
                })
                .collect();
            let err = errors.iter().copied().fold(0.0, f64::max);
            mode::check_finite("creature error", &[err, whole.explained])?;
            let n = whole.fits.len();
            within += usize::from(n.abs_diff(parts) <= 1);
            if n == parts {
                exact += 1;
                found_right += usize::from(err <= 0.01);
            }
            if err > worst.0 {
                worst = (err, seed);
            }
            println!(
                "view {view} seed {seed}: {parts} parts, found {n}, worst part {err:.4} of the diagonal, explained {:.3}, {:.2} s",
                whole.explained,
                times.last().copied().unwrap_or(0.0)
            );
        }
        println!(
            "one view {view}: count within ±1 on {within} of {count}; exact on {exact}, of which {found_right} with every part within 1 %; worst part {:.4} (seed {}); median {:.2} s, slowest {:.2} s",
            worst.0,
            worst.1,
            median(times.clone()),
            times.iter().copied().fold(0.0, f64::max)
        );
    }
    Ok(())
}

/// Chamfer-L1 of `whole` against `reference` points (as chamfer.py measures it): each part's
/// surface sampled by area, the samples inside another part dropped; (ref → fit, fit → ref,
/// each part's exposed share).
fn chamfer(reference: &[DVec3], whole: &Whole) -> (f64, f64, Vec<f64>) {
    let poses: Vec<InitialPose> = whole
        .fits
        .iter()
        .map(|f| InitialPose::of(&f.state))
        .collect();
    let mut samples = Vec::new();
    let mut exposed = Vec::new();
    let mut x = Vec::new();
    for (j, f) in whole.fits.iter().enumerate() {
        f.state.node_positions(&f.tess, &mut x);
        let s = sample_surface(&x, f.tess.triangles(), 20_000 / whole.fits.len().max(1))
            .unwrap_or_default();
        let kept: Vec<DVec3> = s
            .iter()
            .copied()
            .filter(|p| {
                poses
                    .iter()
                    .enumerate()
                    .all(|(k, o)| k == j || !o.contains(*p))
            })
            .collect();
        exposed.push(kept.len() as f64 / s.len().max(1) as f64);
        samples.extend(kept);
    }
    let mean_to = |from: &[DVec3], to: &[DVec3]| {
        if to.is_empty() {
            return f64::INFINITY;
        }
        let near = nearest_indices(to, from);
        from.iter()
            .zip(near)
            .map(|(p, i)| p.distance(to[i as usize]))
            .sum::<f64>()
            / from.len().max(1) as f64
    };
    (
        mean_to(reference, &samples),
        mean_to(&samples, reference),
        exposed,
    )
}

struct CorpusArgs {
    dir: PathBuf,
    mp: Option<PathBuf>,
    scans: bool,
    local: bool,
    only: Option<Vec<String>>,
}

fn corpus(a: &CorpusArgs) -> Result<(), String> {
    let manifest = std::fs::read_to_string(a.dir.join("manifest.json"))
        .map_err(|e| format!("{}: {e} (run fetch_corpus.py)", a.dir.display()))?;
    let manifest: serde_json::Value = serde_json::from_str(&manifest).map_err(|e| e.to_string())?;
    let mp: serde_json::Value = match &a.mp {
        Some(p) => serde_json::from_str(&std::fs::read_to_string(p).map_err(|e| e.to_string())?)
            .map_err(|e| e.to_string())?,
        None => serde_json::Value::Null,
    };
    let opts = options(a.local);
    let names: Vec<String> = manifest["meshes"]
        .as_array()
        .map(|m| {
            m.iter()
                .filter_map(|m| m["name"].as_str().map(String::from))
                .collect()
        })
        .unwrap_or_default();
    println!(
        "| mesh | parts | Chamfer-L1 % | least exposed | explained | s | MP parts | MP Chamfer % |"
    );
    println!("|---|---|---|---|---|---|---|---|");
    for name in names {
        if a.only.as_ref().is_some_and(|o| !o.contains(&name)) {
            continue;
        }
        let mesh = a.dir.join(format!("{name}.obj"));
        let file = if a.scans {
            a.dir.join(format!("{name}_scan.obj"))
        } else {
            mesh.clone()
        };
        let t = Instant::now();
        let points = load_points_sampled(&file, 10_000).map_err(|e| e.to_string())?;
        let whole = fit_parts(&points, PartCount::Auto(DEFAULT_MAX_PARTS), &opts)
            .map_err(|e| format!("{name}: {e}"))?;
        let seconds = t.elapsed().as_secs_f64();
        let reference = if a.scans {
            points.clone()
        } else {
            load_points_sampled(&mesh, 20_000).map_err(|e| e.to_string())?
        };
        let (lo, hi) = reference.iter().fold(
            (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY)),
            |(lo, hi), p| (lo.min(*p), hi.max(*p)),
        );
        let side = (hi - lo).max_element();
        let (to_fit, to_ref, exposed) = chamfer(&reference, &whole);
        let figure = if a.scans {
            // The scan-to-fit half, beside one part's.
            let one = fit(&points, &opts, |_| {}).map_err(|e| e.to_string())?;
            let single = Whole::of(&points, vec![one], whole.scale);
            let (one_to_fit, _, _) = chamfer(&reference, &single);
            format!(
                "{:.2} (one part {:.2})",
                100.0 * to_fit / side,
                100.0 * one_to_fit / side
            )
        } else {
            format!("{:.2}", 50.0 * (to_fit + to_ref) / side)
        };
        let least = exposed.iter().copied().fold(1.0, f64::min);
        let m = mp["meshes"]
            .as_array()
            .and_then(|m| m.iter().find(|m| m["name"] == name.as_str()));
        println!(
            "| {name} | {} | {figure} | {least:.2} | {:.3} | {seconds:.2} | {} | {} |",
            whole.fits.len(),
            whole.explained,
            m.map_or("—".into(), |m| m["parts"].to_string()),
            m.map_or("—".into(), |m| m["chamfer_pct"].to_string()),
        );
    }
    Ok(())
}

fn main() -> ExitCode {
    let benched = mode::benched();
    let args: Vec<String> = std::env::args()
        .skip(1)
        .filter(|a| a != "--bench")
        .collect();
    let result = if !benched {
        // `cargo test`: two small creatures, a figure each.
        creatures(2, false)
    } else {
        let mut count = 120;
        let mut c = CorpusArgs {
            dir: PathBuf::from(std::env::var("HOME").unwrap_or_default()).join(".cache/dsq-corpus"),
            mp: None,
            scans: false,
            local: false,
            only: None,
        };
        let mut it = args.iter().skip(1);
        let mut bad = None;
        while let Some(a) = it.next() {
            match a.as_str() {
                "--count" => count = it.next().and_then(|n| n.parse().ok()).unwrap_or(count),
                "--dir" => c.dir = it.next().map(PathBuf::from).unwrap_or(c.dir),
                "--mp" => c.mp = it.next().map(PathBuf::from),
                "--scans" => c.scans = true,
                "--local" => c.local = true,
                "--only" => c.only = it.next().map(|s| s.split(',').map(String::from).collect()),
                other => bad = Some(other.to_string()),
            }
        }
        match (bad, args.first().map(String::as_str)) {
            (Some(b), _) => Err(format!("unknown argument {b:?}")),
            (None, Some("creatures")) => creatures(count, c.local),
            (None, Some("corpus")) => corpus(&c),
            _ => Err("give `creatures` or `corpus`".into()),
        }
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::FAILURE
        }
    }
}
