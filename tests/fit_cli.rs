//! The command-line fitter (`dsq fit`), run as a user runs it: every bad input gives a
//! one-line error naming the file and exit code 2; a good input gives a JSON summary line and the
//! requested mesh and parameter files.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

/// The `dsq` binary that cargo builds for the integration tests.
fn dsq() -> Command {
    Command::new(env!("CARGO_BIN_EXE_dsq"))
}

/// An example binary that `cargo test` builds next to the test binaries.
fn example_binary(name: &str) -> PathBuf {
    let exe = std::env::current_exe().expect("test binary path");
    let dir = exe.parent().and_then(Path::parent).expect("target dir");
    let bin = dir
        .join("examples")
        .join(format!("{name}{}", std::env::consts::EXE_SUFFIX));
    assert!(
        bin.exists(),
        "{} not built; cargo test builds examples",
        bin.display()
    );
    bin
}

/// What example `name` printed, run without arguments (fails the test when the run failed).
fn example_stdout(name: &str) -> String {
    let out = Command::new(example_binary(name))
        .output()
        .unwrap_or_else(|e| panic!("run {name}: {e}"));
    let text = String::from_utf8_lossy(&out.stdout).into_owned();
    assert!(
        out.status.success(),
        "{name}: {text}{}",
        String::from_utf8_lossy(&out.stderr)
    );
    text
}

#[path = "support/clouds.rs"]
mod clouds;

fn scratch() -> PathBuf {
    let d = std::env::temp_dir().join(format!("bdsq-cli-{}", std::process::id()));
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// `dsq fit ARGS`.
fn run(args: &[&str]) -> Output {
    dsq().arg("fit").args(args).output().expect("run dsq fit")
}

/// The JSON lines a successful run printed (fails the test, with stderr, when the run failed).
fn json_lines(out: &Output) -> Vec<serde_json::Value> {
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8_lossy(&out.stdout)
        .lines()
        .map(|l| serde_json::from_str(l).unwrap_or_else(|e| panic!("{e}: {l}")))
        .collect()
}

/// Asserts that the `|`-separated cells `cells` of a table row each hold `n` finite, non-negative
/// numbers separated by `/` (a trailing `°` allowed).
fn assert_numeric_cells(row: &str, cells: std::ops::Range<usize>, n: usize) {
    let all: Vec<&str> = row.split('|').map(str::trim).collect();
    for cell in &all[cells] {
        let v: Vec<f64> = cell
            .split('/')
            .map(|x| {
                x.trim()
                    .trim_end_matches('°')
                    .parse()
                    .unwrap_or_else(|e| panic!("{e}: {row}"))
            })
            .collect();
        assert!(
            v.len() == n && v.iter().all(|x| x.is_finite() && *x >= 0.0),
            "{row}"
        );
    }
}

fn assert_bad_input(args: &[&str], file_hint: &str, what: &str) {
    let out = run(args);
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "args {args:?}: stderr {err}");
    let lines: Vec<&str> = err.lines().collect();
    assert_eq!(lines.len(), 1, "not one line: {err}");
    assert!(
        lines[0].contains(file_hint),
        "error does not name {file_hint}: {err}"
    );
    assert!(
        lines[0].to_lowercase().contains(what),
        "error does not say {what}: {err}"
    );
    assert!(!err.contains("panicked"), "{err}");
}

#[test]
fn bad_inputs_exit_2_with_a_one_line_error() {
    let dir = scratch();
    let write = |name: &str, text: &str| {
        let p = dir.join(name);
        std::fs::write(&p, text).unwrap();
        p.display().to_string()
    };
    let missing = dir.join("missing.obj").display().to_string();
    assert_bad_input(&[&missing], "missing.obj", "cannot read");
    let empty = write("empty.obj", "");
    assert_bad_input(&[&empty], "empty.obj", "empty");
    let text = write("text.obj", "v 1.0 hello 2.0\n");
    assert_bad_input(&[&text], "text.obj", "line 1");
    let nan = write("nan.obj", "v 0 0 0\nv 1 1 1\nv NaN 0 1\n");
    assert_bad_input(&[&nan], "nan.obj", "nan");
    let inf = write(
        "inf.ply",
        "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\nend_header\n0 0 0\n1 inf 1\n",
    );
    assert_bad_input(&[&inf], "inf.ply", "line 9");
    let mut bin = b"ply\nformat binary_little_endian 1.0\nelement vertex 2\nproperty double x\nproperty double y\nproperty double z\nend_header\n".to_vec();
    for v in [0.0f64, 0.0, 0.0, 1.0, f64::INFINITY, 1.0] {
        bin.extend_from_slice(&v.to_le_bytes());
    }
    let bin_path = dir.join("inf_binary.ply");
    std::fs::write(&bin_path, bin).unwrap();
    assert_bad_input(&[bin_path.to_str().unwrap()], "inf_binary.ply", "infinite");
    let few = write("few.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\n");
    assert_bad_input(&[&few], "few.obj", "at least");
    let same = write("same.obj", &"v 1 1 1\n".repeat(20));
    assert_bad_input(&[&same], "same.obj", "coincide");
    let bad_ply = write(
        "bad.ply",
        "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nend_header\n0\n1\n",
    );
    assert_bad_input(&[&bad_ply], "bad.ply", "y");
    let dir_arg = dir.display().to_string();
    assert_bad_input(&[&dir_arg], &dir_arg, "directory");
    let txt = write("points.txt", "1 2 3\n");
    assert_bad_input(&[&txt], "points.txt", "extension");
}

#[test]
fn bad_options_exit_2() {
    let cloud = clouds::partial_file(&clouds::cloud_dir(), 1);
    let cloud = cloud.to_str().unwrap();
    for args in [
        vec![cloud, "--nodes", "100"],
        vec![cloud, "--w1", "-1"],
        vec![cloud, "--bogus"],
        vec![cloud, "--w0", "abc"],
    ] {
        let out = run(&args);
        assert_eq!(out.status.code(), Some(2), "{args:?}");
        assert!(!String::from_utf8_lossy(&out.stderr).contains("panicked"));
    }
}

#[test]
fn w1_auto_takes_the_stiffness_from_the_clouds_noise_and_is_refused_for_scenes() {
    let cloud = concat!(env!("CARGO_MANIFEST_DIR"), "/assets/data/hippo1_scan.obj");
    let lines = json_lines(&run(&[cloud, "--w1", "auto", "--global-only", "--quiet"]));
    let line = &lines[0];
    let (noise, w1) = (
        line["noise"].as_f64().unwrap(),
        line["w1"].as_f64().unwrap(),
    );
    assert!(noise > 0.0 && noise < 0.02, "{line}");
    assert!((0.003..0.1).contains(&w1), "{line}");
    assert!(
        (line["w0"].as_f64().unwrap() - w1 / 100.0).abs() < 1e-15,
        "{line}"
    );
    let scene = concat!(env!("CARGO_MANIFEST_DIR"), "/assets/scenes/egg.dsq.ron");
    assert_bad_input(
        &["--scene", scene, "--w1", "auto"],
        "--w1 auto",
        "point cloud",
    );
}

#[test]
fn fits_a_shipped_cloud_and_writes_mesh_and_params() {
    let dir = scratch();
    let cloud = clouds::partial_file(&clouds::cloud_dir(), 1);
    let cloud = cloud.to_str().unwrap();
    let mesh = dir.join("fit.obj");
    let params = dir.join("fit.json");
    let out = run(&[
        cloud,
        "--k",
        "15",
        "--quiet",
        "--out-mesh",
        mesh.to_str().unwrap(),
        "--out-params",
        params.to_str().unwrap(),
    ]);
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let last = stdout.lines().last().expect("summary line");
    let summary: serde_json::Value = serde_json::from_str(last).expect("JSON summary");
    for key in ["steps", "wall_ms", "points", "nodes", "mean", "rms", "max"] {
        assert!(summary.get(key).is_some(), "summary lacks {key}: {last}");
    }
    assert_eq!(summary["points"], 150);
    assert_eq!(summary["nodes"], 227);
    assert!(summary["mean"].as_f64().unwrap() < 0.01, "{last}");
    let obj = std::fs::read_to_string(&mesh).unwrap();
    assert_eq!(obj.lines().filter(|l| l.starts_with("v ")).count(), 227);
    assert_eq!(
        obj.lines().filter(|l| l.starts_with("f ")).count(),
        2 * 227 - 4
    );
    let p: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&params).unwrap()).unwrap();
    for key in [
        "translation",
        "rotation",
        "a",
        "a1",
        "a2",
        "a3",
        "e1",
        "e2",
        "nodes",
        "residuals",
    ] {
        assert!(p.get(key).is_some(), "params lack {key}");
    }
}

#[test]
fn bad_images_and_image_options_exit_2_with_a_one_line_error() {
    let dir = scratch();
    let horse = concat!(env!("CARGO_MANIFEST_DIR"), "/assets/data/horse.png");
    let missing = dir.join("missing.png").display().to_string();
    assert_bad_input(&["--image", &missing], "missing.png", "cannot read");
    let corrupt = dir.join("corrupt.png");
    std::fs::write(&corrupt, b"\x89PNG\r\n\x1a\n but not an image").unwrap();
    assert_bad_input(
        &["--image", corrupt.to_str().unwrap()],
        "corrupt.png",
        "cannot decode",
    );
    let tiny = dir.join("tiny.png");
    // A valid 1×1 gray PNG.
    let one: &[u8] = &[
        0x89, 0x50, 0x4e, 0x47, 0x0d, 0x0a, 0x1a, 0x0a, 0x00, 0x00, 0x00, 0x0d, 0x49, 0x48, 0x44,
        0x52, 0x00, 0x00, 0x00, 0x01, 0x00, 0x00, 0x00, 0x01, 0x08, 0x00, 0x00, 0x00, 0x00, 0x3a,
        0x7e, 0x9b, 0x55, 0x00, 0x00, 0x00, 0x0a, 0x49, 0x44, 0x41, 0x54, 0x78, 0x9c, 0x63, 0x60,
        0x00, 0x00, 0x00, 0x02, 0x00, 0x01, 0x48, 0xaf, 0xa4, 0x71, 0x00, 0x00, 0x00, 0x00, 0x49,
        0x45, 0x4e, 0x44, 0xae, 0x42, 0x60, 0x82,
    ];
    std::fs::write(&tiny, one).unwrap();
    assert_bad_input(&["--image", tiny.to_str().unwrap()], "tiny.png", "1×1");
    assert_bad_input(&["--image", horse, "--sigma", "0"], "--sigma", "finite");
    assert_bad_input(&["--image", horse, "--sigma", "-2"], "--sigma", "finite");
    // The dynamics' options are refused by the solved fit (the default), naming the way out.
    assert_bad_input(
        &["--image", horse, "--region", "0.04"],
        "region",
        "solver dynamics",
    );
    assert_bad_input(
        &["--image", horse, "--part", "900,10,950,10,925,0,925,20"],
        "--part 1",
        "outside the image",
    );
    assert_bad_input(
        &["--image", horse, "--part", "1,2,3"],
        "--part",
        "8 finite numbers",
    );
}

#[test]
fn fits_parts_to_an_image_and_writes_the_overlay() {
    let dir = scratch();
    let horse = concat!(env!("CARGO_MANIFEST_DIR"), "/assets/data/horse.png");
    let overlay = dir.join("overlay.png");
    let mesh = dir.join("parts.obj");
    let out = run(&[
        "--image",
        horse,
        "--k",
        "12",
        "--out-overlay",
        overlay.to_str().unwrap(),
        "--out-mesh",
        mesh.to_str().unwrap(),
    ]);
    let lines = json_lines(&out);
    // One automatically placed part (the horse is one blob), then the image summary.
    assert_eq!(lines.len(), 2, "{lines:?}");
    assert_eq!(lines[0]["part"], 1);
    let summary = &lines[1];
    assert!(
        summary["outline_after"].as_f64().unwrap() > summary["outline_before"].as_f64().unwrap(),
        "{summary}"
    );
    // An automatic placement says so, in the line and on stderr.
    assert_eq!(summary["placed"], "blobs");
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("Otsu") && err.contains("--part"), "{err}");
    let (w, h, _) = bevy_deformable_sq::io::load_luminance(&overlay).unwrap();
    assert_eq!((w, h), (400, 328));
    let obj = std::fs::read_to_string(&mesh).unwrap();
    assert_eq!(obj.lines().filter(|l| l.starts_with("v ")).count(), 146);
}

#[test]
fn a_bad_scene_exits_2_naming_the_file_and_field() {
    let dir = scratch();
    let bad = dir.join("bad.dsq.ron");
    std::fs::write(
        &bad,
        r#"(data: {"egg": Generated(Egg)}, parts: [(placement: Pose(translation: (0.0, 0.0, 0.0), shape: (a: 1.0, a1: 1.0, a2: 1.0, a3: 1.0, e1: 1.0, e2: 1.0)), w0: -2.0, forces: Range(data: "egg"))])"#,
    )
    .unwrap();
    assert_bad_input(
        &["--scene", &bad.display().to_string()],
        "bad.dsq.ron",
        "parts[0].w0",
    );
    let missing = dir.join("missing.dsq.ron");
    assert_bad_input(
        &["--scene", &missing.display().to_string()],
        "missing.dsq.ron",
        "cannot read",
    );
}

#[test]
fn the_scene_runner_fits_every_part_and_writes_mesh_params_and_scene() {
    let dir = scratch();
    let scene = Path::new(env!("CARGO_MANIFEST_DIR")).join("assets/scenes/cow.dsq.ron");
    let (mesh, params, saved) = (
        dir.join("cow.obj"),
        dir.join("cow.json"),
        dir.join("out/cow_fitted.dsq.ron"),
    );
    std::fs::create_dir_all(saved.parent().unwrap()).unwrap();
    let out = run(&[
        "--scene",
        &scene.display().to_string(),
        "--max-steps",
        "300",
        "--out-mesh",
        &mesh.display().to_string(),
        "--out-params",
        &params.display().to_string(),
        "--out-scene",
        &saved.display().to_string(),
    ]);
    let lines = json_lines(&out);
    let names: Vec<&str> = lines.iter().map(|l| l["name"].as_str().unwrap()).collect();
    assert_eq!(
        names,
        [
            "body",
            "head",
            "back leg 1",
            "back leg 2",
            "fore leg 1",
            "fore leg 2"
        ]
    );
    for (i, l) in lines.iter().enumerate() {
        assert_eq!(l["part"], i + 1);
        assert!(l["steps"].as_u64().unwrap() <= 300, "{l}");
        assert_eq!(l["solver"], "solved", "{l}");
        assert!(l["rms"].as_f64().unwrap() < 0.1, "{l}");
        assert_eq!(l["nodes"], 443);
    }
    let obj = std::fs::read_to_string(&mesh).unwrap();
    assert_eq!(obj.lines().filter(|l| l.starts_with("v ")).count(), 6 * 443);
    let json: Vec<serde_json::Value> =
        serde_json::from_str(&std::fs::read_to_string(&params).unwrap()).unwrap();
    assert_eq!(json.len(), 6);
    // The written scene finds its data from its new directory and starts where the fit ended.
    let (def, data) =
        bevy_deformable_sq::scene::SceneDef::load_file(&saved).unwrap_or_else(|e| panic!("{e}"));
    let (orig, _) = bevy_deformable_sq::scene::SceneDef::load_file(&scene).unwrap();
    assert_eq!(
        data.points["cow"].len(),
        bevy_deformable_sq::io::MESH_SAMPLES
    );
    for i in 0..6 {
        assert!(def.parts[i].local.is_some());
        assert_ne!(def.parts[i].placement, orig.parts[i].placement);
        assert_eq!(def.parts[i].forces, orig.parts[i].forces);
    }
}

#[test]
fn the_index_example_finds_each_complete_objects_own_library_part() {
    // examples/index.rs: descriptors of fitted parts, the nearest library part for each query.
    let out = Command::new(example_binary("index"))
        .output()
        .expect("run index");
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{text}");
    // A cow leg finds a cow leg (the four are the same kind of part: back from fore is not a
    // shape's to tell); a rescanned object finds itself.
    for (query, own) in [
        ("cow back leg 2", "cow back leg 1|cow fore leg 1"),
        ("cow fore leg 2", "cow back leg 1|cow fore leg 1"),
        ("egg, rescanned", "egg"),
        ("mug, rescanned", "mug"),
    ] {
        let line = text
            .lines()
            .find(|l| l.starts_with(query))
            .unwrap_or_else(|| panic!("no line for {query}: {text}"));
        let nearest = line.split('→').nth(1).unwrap_or("").trim_start();
        let found = own
            .split('|')
            .any(|o| nearest.starts_with(&format!("{o} ")));
        assert!(found, "{line}");
    }
}

#[test]
fn a_shared_scan_scene_prints_its_parts_and_the_split() {
    let scene = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/assets/scenes/cow_scan.dsq.ron"
    );
    let lines = json_lines(&run(&["--scene", scene, "--quiet"]));
    assert_eq!(lines.len(), 7, "six parts and the split: {lines:?}");
    let split = &lines[6];
    assert_eq!(split["data"], "cow");
    assert_eq!(split["parts"].as_u64(), Some(6));
    let owned: u64 = lines[..6]
        .iter()
        .map(|l| l["points"].as_u64().unwrap())
        .sum();
    assert_eq!(
        Some(owned),
        split["points"].as_u64(),
        "every point in one part"
    );
    let mean = split["mean"].as_f64().unwrap();
    assert!(mean > 0.0 && mean < 0.005, "{split}");
}

#[test]
fn points_with_parts_fit_several_parts_and_give_every_point_to_one() {
    // The cow mesh's vertices in 3 parts: a line per part, then one for the whole.
    let cow = concat!(env!("CARGO_MANIFEST_DIR"), "/assets/data/cow.obj");
    let lines = json_lines(&run(&[cow, "--parts", "3"]));
    assert_eq!(lines.len(), 4, "{lines:?}");
    let owned: u64 = lines[..3]
        .iter()
        .map(|l| l["points"].as_u64().unwrap())
        .sum();
    assert_eq!(
        owned,
        lines[3]["points"].as_u64().unwrap(),
        "every point in one part"
    );
    for (j, l) in lines[..3].iter().enumerate() {
        assert_eq!(l["part"].as_u64(), Some(j as u64));
        assert!(l["mean"].as_f64().unwrap() < 0.05, "{l}");
    }
}

#[test]
fn help_exits_0_and_a_bare_dsq_prints_its_usage_with_exit_2() {
    for args in [
        &["--help"][..],
        &["fit", "--help"],
        &["help", "fit"],
        &["--version"],
    ] {
        let out = dsq().args(args).output().expect("run dsq");
        assert_eq!(out.status.code(), Some(0), "{args:?}");
        let text = String::from_utf8_lossy(&out.stdout);
        assert!(text.contains("dsq"), "{args:?}: {text}");
    }
    let fit_help = String::from_utf8_lossy(&dsq().args(["fit", "--help"]).output().unwrap().stdout)
        .into_owned();
    for option in ["--paper", "--global-only", "--part", "--out-scene", "--w1"] {
        assert!(fit_help.contains(option), "{option} missing: {fit_help}");
    }
    let bare = dsq().output().expect("run dsq");
    assert_eq!(bare.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&bare.stderr).contains("Usage: dsq"));
}

#[cfg(not(feature = "bevy"))]
#[test]
fn app_needs_the_bevy_feature_and_says_so() {
    assert_bad_input(&["--paper", "egg", "--app"], "--app", "`bevy` feature");
}

/// `dsq fit F --app FLAGS` writes the mesh `dsq fit F FLAGS` writes, bit for bit: the plugin's
/// fit to convergence runs the core's fit, for every shipped cloud and every kind of fit.
#[cfg(feature = "bevy")]
#[test]
fn every_shipped_cloud_fits_through_the_app_to_the_cores_mesh() {
    let data = concat!(env!("CARGO_MANIFEST_DIR"), "/assets/data");
    let mut files: Vec<String> = [
        "bunny_scan.obj",
        "cow_scan.obj",
        "ant_scan.obj",
        "hippo1_scan.obj",
        "cow.obj",
    ]
    .iter()
    .map(|f| format!("{data}/{f}"))
    .collect();
    let generated = clouds::cloud_dir();
    for i in 1..=3 {
        for file in [
            clouds::noisy_file(&generated, i),
            clouds::partial_file(&generated, i),
        ] {
            files.push(file.display().to_string());
        }
    }
    let flag_sets: [&[&str]; 6] = [
        &[],
        &["--global-only"],
        &["--solver", "dynamics", "--global-only"],
        &["--global-only", "--taper", "--bend"],
        &["--robust", "--global-only"],
        &["--nodes", "2603"],
    ];
    let dir = scratch();
    for (c, cloud) in files.iter().enumerate() {
        for (f, flags) in flag_sets.iter().enumerate() {
            let mesh = |through: &[&str]| {
                let path = dir.join(format!("app_{c}_{f}_{}.obj", through.len()));
                let mut args = vec![
                    cloud.as_str(),
                    "--quiet",
                    "--out-mesh",
                    path.to_str().unwrap(),
                ];
                args.extend_from_slice(flags);
                args.extend_from_slice(through);
                let out = run(&args);
                assert!(
                    out.status.success(),
                    "{args:?}: {}",
                    String::from_utf8_lossy(&out.stderr)
                );
                std::fs::read(&path).unwrap()
            };
            assert!(
                mesh(&[]) == mesh(&["--app"]),
                "{cloud} {flags:?}: the app's mesh differs from the core's"
            );
        }
    }
}

#[test]
fn taper_and_bend_reach_the_summary_and_are_refused_for_images_and_scenes() {
    // The banana scene frees its part's taper and bend: the fit recovers the tube's (each end
    // turned by 0.6 rad, the section growing by 40 %).
    let scene = concat!(env!("CARGO_MANIFEST_DIR"), "/assets/scenes/banana.dsq.ron");
    let lines = json_lines(&run(&["--scene", scene, "--quiet"]));
    let line = &lines[0];
    let (taper, bend) = (pair_of(line, "taper"), pair_of(line, "bend"));
    assert!(taper.iter().all(|t| (t.abs() - 0.4).abs() < 0.1), "{line}");
    assert!((bend[0].hypot(bend[1]) - 0.6).abs() < 0.1, "{line}");
    // A plain fit reports none.
    let plain = json_lines(&run(&["--paper", "mug", "--global-only", "--quiet"]));
    assert_eq!(pair_of(&plain[0], "taper"), [0.0, 0.0]);
    assert_eq!(pair_of(&plain[0], "bend"), [0.0, 0.0]);
    assert_bad_input(&["--scene", scene, "--taper"], "--taper", "point fits");
    let image = concat!(env!("CARGO_MANIFEST_DIR"), "/assets/data/rocket.png");
    assert_bad_input(&["--image", image, "--bend"], "--bend", "point fits");
}

fn pair_of(line: &serde_json::Value, key: &str) -> [f64; 2] {
    let v = line[key]
        .as_array()
        .unwrap_or_else(|| panic!("no {key}: {line}"));
    [v[0].as_f64().unwrap(), v[1].as_f64().unwrap()]
}

#[test]
fn the_deform_example_prints_four_fits_per_object() {
    let text = example_stdout("deform");
    let rows: Vec<&str> = text
        .lines()
        .filter(|l| l.starts_with("| banana") || l.starts_with("| cow"))
        .collect();
    assert_eq!(rows.len(), 8, "{text}");
    for row in rows {
        // steps, wall ms, mean, p95.
        assert_numeric_cells(row, 4..8, 1);
    }
}

#[test]
fn a_users_cloud_gets_robust_forces_and_a_stiffness_from_its_noise_unless_the_papers_are_asked_for()
{
    let cloud = clouds::partial_file(&clouds::cloud_dir(), 1);
    let cloud = cloud.to_str().unwrap();
    // With local DOFs: w0 and w1 from the noise, solved.
    let local = &json_lines(&run(&[cloud, "--k", "15", "--quiet"]))[0];
    let w1 = local["w1"].as_f64().expect("w1 chosen from the noise");
    assert!(local["noise"].as_f64().is_some() && w1 != 0.1, "{local}");
    assert_eq!(local["solver"], "solved", "{local}");
    // A pure superquadric: solved, on the continuous surface through the clean points.
    let pure = &json_lines(&run(&[cloud, "--global-only", "--quiet"]))[0];
    assert_eq!(pure["solver"], "solved", "{pure}");
    // The paper's forces through the paper's dynamics: no noise estimate, a farther pure
    // superquadric (pinned to its nodes).
    let paper = &json_lines(&run(&[
        cloud,
        "--global-only",
        "--paper-forces",
        "--solver",
        "dynamics",
        "--quiet",
    ]))[0];
    assert!(paper.get("w1").is_none(), "{paper}");
    assert_eq!(paper["solver"], "dynamics", "{paper}");
    let mean = |l: &serde_json::Value| l["mean"].as_f64().unwrap();
    assert!(mean(pure) < 0.5 * mean(paper), "{pure} vs {paper}");
    // Explicit stiffness is kept; the flag is refused where it has no meaning.
    let given = &json_lines(&run(&[cloud, "--k", "15", "--w1", "0.2", "--quiet"]))[0];
    assert!(given.get("w1").is_none(), "{given}");
    let scene = concat!(env!("CARGO_MANIFEST_DIR"), "/assets/scenes/egg.dsq.ron");
    assert_bad_input(
        &["--scene", scene, "--paper-forces"],
        "--paper-forces",
        "points",
    );
}

#[test]
fn the_solved_fit_is_the_default_and_fits_a_clean_cloud_in_far_fewer_steps() {
    let cloud = clouds::partial_file(&clouds::cloud_dir(), 1);
    let cloud = cloud.to_str().unwrap();
    let line = |args: &[&str]| {
        let out = run(&[&[cloud, "--quiet"], args].concat());
        json_lines(&out).pop().expect("a summary line")
    };
    let steps_and_mean =
        |l: &serde_json::Value| (l["steps"].as_u64().unwrap(), l["mean"].as_f64().unwrap());
    let default = line(&["--global-only"]);
    assert_eq!(default["solver"], "solved", "{default}");
    // `lm`, the solver's old name, is the same fit.
    assert_eq!(
        steps_and_mean(&default),
        steps_and_mean(&line(&["--global-only", "--solver", "lm"]))
    );
    let (solved_steps, solved_mean) = steps_and_mean(&default);
    let dynamics = line(&["--global-only", "--solver", "dynamics"]);
    assert_eq!(dynamics["solver"], "dynamics", "{dynamics}");
    let (steps, mean) = steps_and_mean(&dynamics);
    // The cloud is a sampled superquadric: the solved fit passes through its points (to a
    // tenth of the σ floor: measured 1.2e-5 of the diagonal), the dynamics' nearest-node
    // springs pin the surface to its nodes (measured 0.0028).
    assert!(
        solved_mean < 1e-4 && mean < 0.01 && mean > 10.0 * solved_mean,
        "solved {solved_mean}, dynamics {mean}"
    );
    assert!(
        2 * solved_steps < steps,
        "solved {solved_steps} steps, dynamics {steps}"
    );
    // With local DOFs: the solved superquadric, then the membrane by linear solves.
    let (solved_steps, _) = steps_and_mean(&line(&[]));
    let (steps, _) = steps_and_mean(&line(&["--solver", "dynamics"]));
    assert!(
        2 * solved_steps < steps,
        "solved {solved_steps} steps, dynamics {steps}"
    );
    // Tapering and bending are solved for too.
    let tapered = line(&["--global-only", "--taper", "--bend"]);
    assert_eq!(tapered["solver"], "solved", "{tapered}");
    assert_bad_input(&["--paper", "egg", "--solver", "lm"], "--solver", "points");
    assert_bad_input(&[cloud, "--refine"], "--refine", "unexpected");
}

#[test]
fn a_dense_scan_goes_on_to_a_finer_tessellation_unless_one_is_given() {
    let cloud = concat!(env!("CARGO_MANIFEST_DIR"), "/assets/data/hippo1_scan.obj");
    let nodes = |extra: &[&str]| {
        let mut args = vec![cloud, "--quiet"];
        args.extend_from_slice(extra);
        let line = json_lines(&run(&args)).remove(0);
        (
            line["nodes"].as_u64().unwrap(),
            line["mean"].as_f64().unwrap(),
        )
    };
    let (chosen, chosen_mean) = nodes(&[]);
    let (given, given_mean) = nodes(&["--k", "31"]);
    assert_eq!(given, 963);
    assert_eq!(nodes(&["--nodes", "963"]).0, 963);
    // K = 93 on this machine: 8651 nodes.
    assert!((3000..=10_203).contains(&chosen), "{chosen} nodes");
    assert!(chosen_mean < given_mean, "{chosen_mean} vs {given_mean}");
    // A pure superquadric has no membrane to refine.
    assert_eq!(nodes(&["--global-only"]).0, 963);
}
