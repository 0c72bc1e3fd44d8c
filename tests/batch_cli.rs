//! `dsq fit A B C …`: many clouds side by side. A JSON line per file in the order given, every
//! good file fitted as it would be alone (bit for bit), a bad one named and skipped with exit
//! code 2, and each fit's mesh and parameters in `--out-dir`.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn dsq_fit(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_dsq"))
        .arg("fit")
        .args(args)
        .output()
        .expect("run dsq fit")
}

fn scratch(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("bdsq-batch-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

#[path = "support/clouds.rs"]
mod clouds;

/// Generated cloud `i` of `kind` ("noisy" or "partial"), as a file.
fn generated(kind: &str, i: u64) -> String {
    let dir = clouds::cloud_dir();
    let path = match kind {
        "noisy" => clouds::noisy_file(&dir, i),
        _ => clouds::partial_file(&dir, i),
    };
    path.display().to_string()
}

fn lines(out: &Output) -> Vec<serde_json::Value> {
    String::from_utf8_lossy(&out.stdout)
        .lines()
        .map(|l| serde_json::from_str(l).unwrap_or_else(|e| panic!("{e}: {l}")))
        .collect()
}

#[test]
fn many_files_give_a_line_each_in_order_and_the_single_fits_outputs() {
    let dir = scratch("ok");
    let bad = dir.join("broken.ply");
    std::fs::write(&bad, "not a ply file\n").unwrap();
    let files = [
        generated("partial", 3),
        bad.display().to_string(),
        generated("noisy", 2),
        generated("partial", 1),
    ];
    let out_dir = dir.join("fits");
    let mut args: Vec<&str> = files.iter().map(String::as_str).collect();
    args.extend([
        "--global-only",
        "--quiet",
        "--out-dir",
        out_dir.to_str().unwrap(),
    ]);
    let out = dsq_fit(&args);
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{err}");
    assert!(!err.contains("panicked"), "{err}");
    // The bad file is named on one line, and the run's end says how many failed.
    let err_lines: Vec<&str> = err.lines().collect();
    assert_eq!(err_lines.len(), 2, "{err}");
    assert!(err_lines[0].starts_with("error: ") && err_lines[0].contains("broken.ply"));
    assert!(err_lines[1].contains("1 of 4 files"), "{err}");
    // One line per file, in the order given; the bad one says why.
    let got = lines(&out);
    assert_eq!(got.len(), 4);
    for (line, file) in got.iter().zip(&files) {
        assert_eq!(line["file"], file.as_str());
    }
    assert!(got[1]["error"].as_str().unwrap().contains("broken.ply"));
    for i in [0, 2, 3] {
        assert!(got[i]["mean"].as_f64().unwrap().is_finite());
    }
    // Each good file's mesh and parameters are what a fit of it alone writes.
    for file in [&files[0], &files[2], &files[3]] {
        let stem = Path::new(file).file_stem().unwrap().to_str().unwrap();
        let (mesh, params) = (
            dir.join(format!("{stem}.obj")),
            dir.join(format!("{stem}.json")),
        );
        let alone = dsq_fit(&[
            file,
            "--global-only",
            "--quiet",
            "--out-mesh",
            mesh.to_str().unwrap(),
            "--out-params",
            params.to_str().unwrap(),
        ]);
        assert!(alone.status.success());
        for (a, b) in [(mesh, "obj"), (params, "json")] {
            let batch = out_dir.join(format!("{stem}.{b}"));
            assert_eq!(
                std::fs::read(&a).unwrap(),
                std::fs::read(&batch).unwrap(),
                "{}",
                batch.display()
            );
        }
    }
    assert!(!out_dir.join("broken.obj").exists());
}

#[test]
fn batch_options_that_cannot_apply_are_refused_in_one_line() {
    let dir = scratch("refused");
    let (a, b) = (generated("noisy", 1), generated("noisy", 2));
    // Two files of one name in different folders would overwrite each other's output.
    let twin = dir.join("noisy_1.ply");
    std::fs::copy(&a, &twin).unwrap();
    let out_dir = dir.join("fits").display().to_string();
    let twin = twin.display().to_string();
    for (args, says) in [
        (vec![&a[..], &b, "--out-mesh", "m.obj"], "--out-dir"),
        (vec![&a[..], &b, "--parts", "2"], "--parts"),
        (vec![&a[..], &twin, "--out-dir", &out_dir], "rename one"),
        (vec!["--paper", "egg", "--out-dir", &out_dir], "--out-dir"),
    ] {
        let out = dsq_fit(&args);
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{args:?}: {err}");
        assert_eq!(err.lines().count(), 1, "{args:?}: {err}");
        assert!(err.contains(says), "{args:?}: {err}");
        assert!(out.stdout.is_empty(), "{args:?}: nothing is fitted");
    }
}

#[test]
fn a_reader_that_goes_away_ends_the_run_quietly() {
    // `dsq fit *.ply | head -1`: stdout closes before the lines are written.
    let files: Vec<String> = (1..=3).map(|i| generated("noisy", i)).collect();
    let mut child = Command::new(env!("CARGO_BIN_EXE_dsq"))
        .arg("fit")
        .args(&files)
        .args(["--global-only", "--quiet"])
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .expect("run dsq fit");
    drop(child.stdout.take());
    let out = child.wait_with_output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!err.contains("panicked"), "{err}");
    assert_eq!(out.status.code(), Some(0), "{err}");
}
