//! `dsq fit A.ply B.obj …`: many clouds fitted side by side over every core. One JSON line per
//! file on stdout in the order given (a file that cannot be fitted gets `"error"` instead of a
//! fit, and a line on stderr), each fit's mesh and parameters into `--out-dir`, and a progress
//! bar on stderr when it is a terminal (a line per file otherwise, none with `--quiet`).

use crate::args::Args;
use crate::fit::{fit_points, write_params};
use bevy_deformable_sq::io::{load_points_sampled, write_model_obj};
use indicatif::{ProgressBar, ProgressStyle};
use rayon::prelude::*;
use std::collections::{BTreeMap, HashMap};
use std::io::IsTerminal;
use std::path::{Path, PathBuf};
use std::sync::mpsc;

/// One file's outcome: its JSON line, or why it failed.
type Outcome = Result<serde_json::Value, String>;

/// Fits every file in `files` with `args`' options; an error if any file failed (each said why).
pub fn run(files: &[PathBuf], args: &Args) -> Result<(), String> {
    let outputs = match &args.out_dir {
        Some(dir) => Some(output_stems(files, dir)?),
        None => None,
    };
    let bar = progress_bar(files.len(), args.quiet);
    let (tx, rx) = mpsc::channel::<(usize, Outcome)>();
    let mut failed = 0;
    std::thread::scope(|scope| {
        scope.spawn(move || {
            files
                .par_iter()
                .enumerate()
                .for_each_with(tx, |tx, (i, file)| {
                    let out = outputs.as_ref().map(|o| o[i].as_path());
                    // The receiver lives until every sender is dropped.
                    let _ = tx.send((i, fit_file(file, out, args)));
                });
        });
        // Print in the order given, each line as soon as the ones before it are printed.
        let (mut pending, mut next) = (BTreeMap::new(), 0);
        for (done, (i, outcome)) in rx.into_iter().enumerate() {
            let name = files[i].display().to_string();
            match &outcome {
                Ok(line) => log(
                    &bar,
                    args.quiet,
                    &format!(
                        "[{}/{}] {name}: mean {:.3e} of the diagonal, {} ms",
                        done + 1,
                        files.len(),
                        line["mean"].as_f64().unwrap_or(f64::NAN),
                        line["wall_ms"]
                    ),
                ),
                Err(e) => {
                    failed += 1;
                    bar.suspend(|| eprintln!("error: {e}"));
                }
            }
            bar.inc(1);
            pending.insert(i, outcome);
            while let Some(outcome) = pending.remove(&next) {
                let line = outcome.unwrap_or_else(|e| {
                    serde_json::json!({ "file": files[next].display().to_string(), "error": e })
                });
                bar.suspend(|| crate::emit(&line));
                next += 1;
            }
        }
    });
    bar.finish_and_clear();
    if failed > 0 {
        Err(format!(
            "{failed} of {} files could not be fitted (each is named above)",
            files.len()
        ))
    } else {
        Ok(())
    }
}

/// Reads and fits one file, writing `out`.obj and `out`.json when given.
fn fit_file(file: &Path, out: Option<&Path>, args: &Args) -> Outcome {
    let points = load_points_sampled(file, args.mesh_samples).map_err(|e| e.to_string())?;
    let name = file.display().to_string();
    let (line, report) = fit_points(&points, &name, args, false)?;
    if let Some(out) = out {
        write_model_obj(&out.with_extension("obj"), &report.tess, &report.state)
            .map_err(|e| format!("{name}: {e}"))?;
        write_params(&out.with_extension("json"), &report).map_err(|e| format!("{name}: {e}"))?;
    }
    Ok(line)
}

/// `dir`/STEM for every file (the extension is added when writing); `dir` is created. Two files
/// with one stem would overwrite each other's output, so they are refused before any fit.
fn output_stems(files: &[PathBuf], dir: &Path) -> Result<Vec<PathBuf>, String> {
    std::fs::create_dir_all(dir).map_err(|e| format!("{}: cannot create: {e}", dir.display()))?;
    let mut seen: HashMap<&std::ffi::OsStr, &Path> = HashMap::new();
    files
        .iter()
        .map(|f| {
            let stem = f
                .file_stem()
                .ok_or_else(|| format!("{}: not a file name", f.display()))?;
            if let Some(other) = seen.insert(stem, f) {
                return Err(format!(
                    "{} and {} would both write {} into {}: rename one",
                    other.display(),
                    f.display(),
                    Path::new(stem).with_extension("obj").display(),
                    dir.display()
                ));
            }
            Ok(dir.join(stem))
        })
        .collect()
}

/// A bar on a terminal, hidden otherwise (and with `--quiet`).
fn progress_bar(n: usize, quiet: bool) -> ProgressBar {
    if quiet || !std::io::stderr().is_terminal() {
        return ProgressBar::hidden();
    }
    let bar = ProgressBar::new(n as u64);
    if let Ok(style) =
        ProgressStyle::with_template("{bar:40} {pos}/{len} files  {elapsed} (ETA {eta})")
    {
        bar.set_style(style);
    }
    bar
}

/// A line per fitted file on stderr when there is no bar to show progress (and no `--quiet`).
fn log(bar: &ProgressBar, quiet: bool, line: &str) {
    if !quiet && bar.is_hidden() {
        eprintln!("{line}");
    }
}
