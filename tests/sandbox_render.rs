//! The sandbox in a real renderer: run it under Xvfb with Mesa's CPU Vulkan driver, drag the
//! cylinder with the (scripted) mouse, save a screenshot, and check that the drag pulled the
//! cylinder and that the models are in the picture (their part colours where the parts are, not
//! a blank or black frame). Needs `Xvfb` and a Vulkan driver; CI (`.ci/run`) installs them and
//! sets `BDSQ_RENDER_TEST=1`, which makes their absence a failure rather than a skip.
//!
//! Each test starts its own Xvfb with `-displayfd` (the server picks a free display, so tests in
//! parallel never race for one) and runs the sandbox on it directly. `xvfb-run` is not used: it
//! replaces the program's exit status with its own when its clean-up fails (exit 5), which made
//! the exit-code test flaky.

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};

fn example(name: &str) -> PathBuf {
    let exe = std::env::current_exe().unwrap();
    let dir = exe.parent().and_then(Path::parent).unwrap();
    dir.join("examples")
        .join(format!("{name}{}", std::env::consts::EXE_SUFFIX))
}

/// Chromaticity (r, g, b) / (r + g + b) of a colour.
fn chroma(c: [f32; 3]) -> [f32; 3] {
    let s = (c[0] + c[1] + c[2]).max(1e-6);
    c.map(|x| x / s)
}

/// Whether the renderer is there: a missing one fails the test under `BDSQ_RENDER_TEST=1`, and
/// skips it otherwise.
fn renderer_available() -> bool {
    let required = std::env::var("BDSQ_RENDER_TEST").is_ok_and(|v| v == "1");
    let has_xvfb = Command::new("sh")
        .args(["-c", "command -v Xvfb"])
        .output()
        .is_ok_and(|o| o.status.success());
    if !has_xvfb {
        assert!(!required, "BDSQ_RENDER_TEST=1 but Xvfb is missing");
        eprintln!("skipped: no Xvfb (install xvfb and mesa-vulkan-drivers to run this test)");
    }
    has_xvfb
}

/// Pixels brighter than a near-black background (`lit`), and, inside `region` (x and y ranges),
/// the count of pixels classed as each colour of `palette`: the nearest by chromaticity (the
/// colours are shaded and tone-mapped), when within 0.15 of it.
fn colour_counts(
    img: &image::Rgb32FImage,
    palette: &[[f32; 3]],
    region: (std::ops::Range<u32>, std::ops::Range<u32>),
) -> (usize, Vec<usize>) {
    let mut lit = 0usize;
    let mut counts = vec![0usize; palette.len()];
    for (x, y, p) in img.enumerate_pixels() {
        let c = [p.0[0], p.0[1], p.0[2]];
        let bright = c.iter().sum::<f32>();
        if bright > 0.45 {
            lit += 1;
        }
        if !region.0.contains(&x) || !region.1.contains(&y) || bright < 0.3 {
            continue;
        }
        let ch = chroma(c);
        let dist = |colour: [f32; 3]| -> f32 {
            let want = chroma(colour);
            (0..3)
                .map(|k| (ch[k] - want[k]).powi(2))
                .sum::<f32>()
                .sqrt()
        };
        let nearest = (0..palette.len())
            .min_by(|&a, &b| dist(palette[a]).total_cmp(&dist(palette[b])))
            .unwrap();
        if dist(palette[nearest]) < 0.15 {
            counts[nearest] += 1;
        }
    }
    (lit, counts)
}

/// An Xvfb server of this test's own, stopped when dropped.
struct Display {
    server: Child,
    /// The `DISPLAY` value, e.g. `:3`.
    name: String,
}

impl Display {
    /// Starts Xvfb at 1280×720 on a display it picks, and waits until it takes connections.
    fn start() -> Display {
        let mut server = Command::new("Xvfb")
            .args([
                "-displayfd",
                "1",
                "-screen",
                "0",
                "1280x720x24",
                "-nolisten",
                "tcp",
            ])
            .stdout(Stdio::piped())
            .stderr(Stdio::null())
            .spawn()
            .expect("start Xvfb");
        let mut line = String::new();
        let read =
            BufReader::new(server.stdout.take().expect("Xvfb's stdout")).read_line(&mut line);
        let number = line.trim();
        if read.is_err() || number.is_empty() {
            let _ = server.kill();
            panic!("Xvfb did not report a display number ({read:?})");
        }
        let name = format!(":{number}");
        Display { server, name }
    }
}

impl Drop for Display {
    fn drop(&mut self) {
        let _ = self.server.kill();
        let _ = self.server.wait();
    }
}

/// The sandbox on a fresh Xvfb with `args`, started in `dir` with `envs`, killed after `seconds`.
fn sandbox(dir: &Path, seconds: u32, args: &[&str], envs: &[(&str, &str)]) -> std::process::Output {
    let display = Display::start();
    let runtime =
        std::env::temp_dir().join(format!("bdsq-xdg-{}{}", std::process::id(), display.name));
    let _ = std::fs::create_dir_all(&runtime);
    let mut cmd = Command::new("timeout");
    cmd.arg(seconds.to_string())
        .arg(example("sandbox"))
        .args(args)
        .current_dir(dir)
        .env_remove("BEVY_ASSET_ROOT")
        .env_remove("CARGO_MANIFEST_DIR")
        .env("DISPLAY", &display.name)
        .env("XDG_RUNTIME_DIR", &runtime)
        .env("WGPU_BACKEND", "vulkan");
    for (k, v) in envs {
        cmd.env(k, v);
    }
    let out = cmd.output().expect("run the sandbox");
    let _ = std::fs::remove_dir_all(&runtime);
    out
}

/// Started from another folder, not through cargo, the sandbox finds the crate's assets, says
/// where they are, and a scripted run ends by itself.
#[test]
fn the_sandbox_started_from_elsewhere_finds_its_assets_and_exits() {
    if !renderer_available() {
        return;
    }
    let dir = std::env::temp_dir();
    let out = dir.join(format!("bdsq-elsewhere-{}.png", std::process::id()));
    let _ = std::fs::remove_file(&out);
    let path = out.display().to_string();
    let run = sandbox(
        &dir,
        180,
        &[
            "scenes/egg.dsq.ron",
            "--screenshot",
            &path,
            "--exit-after-steps",
            "5",
        ],
        &[],
    );
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert!(
        run.status.success() && out.exists(),
        "{}: {stderr}",
        run.status
    );
    assert!(stderr.contains("the crate's assets/"), "{stderr}");
    let _ = std::fs::remove_file(&out);
}

/// A scripted run of a scene that does not exist exits with code 2 and a message naming it,
/// instead of waiting for models that never come.
#[test]
fn a_scripted_run_of_a_missing_scene_exits_2_naming_the_file() {
    if !renderer_available() {
        return;
    }
    let dir = std::env::temp_dir();
    let path = dir.join("bdsq-nope.png").display().to_string();
    let run = sandbox(
        &dir,
        180,
        &[
            "scenes/nope.dsq.ron",
            "--screenshot",
            &path,
            "--exit-after-steps",
            "20",
        ],
        &[],
    );
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert_eq!(run.status.code(), Some(2), "{stderr}");
    let last = stderr
        .lines()
        .rfind(|l| l.starts_with("error: "))
        .unwrap_or("");
    assert!(last.contains("nope.dsq.ron"), "{stderr}");
}

#[test]
fn the_sandbox_renders_its_models() {
    if !renderer_available() {
        return;
    }
    let out = std::env::temp_dir().join(format!("bdsq-sandbox-{}.png", std::process::id()));
    let _ = std::fs::remove_file(&out);
    let shot = out.display().to_string();
    let status = sandbox(
        &std::env::temp_dir(),
        600,
        &[
            "scenes/sandbox.dsq.ron",
            "--demo-drag",
            "--screenshot",
            &shot,
            "--exit-after-steps",
            "160",
        ],
        &[("BEVY_ASSET_ROOT", env!("CARGO_MANIFEST_DIR"))],
    );
    assert!(
        status.status.success() && out.exists(),
        "the sandbox did not save a screenshot: {}\n{}",
        status.status,
        String::from_utf8_lossy(&status.stderr)
            .lines()
            .filter(|l| l.contains("ERROR") || l.contains("panicked"))
            .collect::<Vec<_>>()
            .join("\n")
    );
    // The scripted drag went through picking, the grab and the spring: the cylinder followed the
    // cursor to the right.
    let stdout = String::from_utf8_lossy(&status.stdout);
    let line = stdout
        .lines()
        .find(|l| l.starts_with("demo drag:"))
        .unwrap_or_else(|| panic!("no demo drag report in {stdout}"));
    assert!(line.contains("cylinder grabbed: true"), "{line}");
    // A grab carries the cylinder and keeps its shape: semi-axes within 1.5×, ε within 0.2.
    let figure = |key: &str, end: &str| -> f64 {
        line.split(key)
            .nth(1)
            .and_then(|t| t.split(end).next())
            .and_then(|t| t.trim().parse().ok())
            .unwrap_or_else(|| panic!("no {key:?} in {line}"))
    };
    assert!(figure("semi-axes within", "x,") <= 1.5, "{line}");
    assert!(figure("epsilon within", ",") <= 0.2, "{line}");
    let dx: f64 = line
        .rsplit("(x ")
        .next()
        .and_then(|t| t.trim_end_matches(')').parse().ok())
        .unwrap_or_else(|| panic!("{line}"));
    assert!(
        dx > 0.1,
        "the pulled cylinder did not follow the cursor: {line}"
    );
    let img = image::open(&out).expect("a PNG").to_rgb32f();
    assert_eq!((img.width(), img.height()), (1280, 720));
    // The parts in a row across the middle of the frame, each in its palette colour (shaded and
    // tone-mapped, so each pixel is classed by the nearest chromaticity, grey included).
    let palette = [
        ("ellipsoid", [0.90, 0.45, 0.20]),
        ("rounded box", [0.25, 0.55, 0.90]),
        ("cylinder", [0.35, 0.75, 0.35]),
        ("octahedron", [0.85, 0.30, 0.55]),
        ("bunny", [0.95, 0.80, 0.25]),
        ("grey", [0.5, 0.5, 0.5]),
    ];
    let colours = palette.map(|(_, c)| c);
    let (lit, counts) = colour_counts(&img, &colours, (320..1280, 150..600));
    let total = (img.width() * img.height()) as usize;
    assert!(
        lit > total / 50,
        "the frame is (nearly) black: {lit} lit pixels"
    );
    assert!(
        lit < total * 9 / 10,
        "the frame is (nearly) blank: {lit} lit pixels"
    );
    // The ellipsoid sits partly under the inspector; the other four must show.
    for ((name, _), n) in palette[1..5].iter().zip(&counts[1..5]) {
        assert!(
            *n > 1500,
            "the {name} is not visible: {n} pixels of its colour ({counts:?})"
        );
    }
    let _ = std::fs::remove_file(&out);
}

/// A scan dropped on the window (through the windowing system's drop message) is split into
/// jointed parts off the frame, each fitted with its local DOFs and drawn in its colour; a file
/// that cannot be read, dropped first, says why in the message line and adds nothing.
#[test]
fn a_scan_dropped_on_the_sandbox_is_fitted_and_a_bad_file_changes_nothing() {
    if !renderer_available() {
        return;
    }
    let tmp = std::env::temp_dir();
    let out = tmp.join(format!("bdsq-drop-{}.png", std::process::id()));
    let bad = tmp.join(format!("bdsq-drop-{}-bad.ply", std::process::id()));
    std::fs::write(&bad, "garbage\n").unwrap();
    let _ = std::fs::remove_file(&out);
    let cow = Path::new(env!("CARGO_MANIFEST_DIR")).join("assets/data/cow_scan.obj");
    let (shot, bad_s, cow_s) = (
        out.display().to_string(),
        bad.display().to_string(),
        cow.display().to_string(),
    );
    let run = sandbox(
        &tmp,
        600,
        &[
            "scenes/sandbox.dsq.ron",
            "--demo-drop",
            &bad_s,
            "--demo-drop",
            &cow_s,
            "--screenshot",
            &shot,
            "--exit-after-steps",
            "300",
        ],
        &[("BEVY_ASSET_ROOT", env!("CARGO_MANIFEST_DIR"))],
    );
    let stdout = String::from_utf8_lossy(&run.stdout);
    assert!(
        run.status.success() && out.exists(),
        "{}: {stdout}",
        run.status
    );
    let line = |start: &str| {
        stdout
            .lines()
            .find(|l| l.starts_with(start))
            .unwrap_or_else(|| panic!("no {start:?} in {stdout}"))
            .to_string()
    };
    let bad_line = line(&format!("demo drop: {bad_s}:"));
    assert!(
        bad_line.contains("not added:") && bad_line.contains("magic number"),
        "{bad_line}"
    );
    assert!(bad_line.contains("(parts 5 -> 5;"), "{bad_line}");
    // The cow's scan is split into jointed parts off the frame: the window kept drawing frames
    // while it was split (a split inside a frame would be over before the next).
    let cow_line = line(&format!("demo drop: {cow_s}:"));
    let number_after = |text: &str, key: &str| -> usize {
        text.split(key)
            .nth(1)
            .and_then(|t| t.split(|c: char| !c.is_ascii_digit()).next())
            .and_then(|t| t.parse().ok())
            .unwrap_or_else(|| panic!("no number after {key:?} in {text}"))
    };
    let parts = number_after(&cow_line, "added as ");
    assert!(parts >= 2, "{cow_line}");
    assert!(
        cow_line.contains(&format!("(parts 5 -> {};", 5 + parts)),
        "{cow_line}"
    );
    assert!(number_after(&cow_line, "split over ") >= 2, "{cow_line}");
    // Every part of it is fitted with its local DOFs and comes to rest, and the parts follow
    // their shares of the points: a point lies on average within 1 % of its part's extent from
    // it. (Some parts of a few dozen points lie farther: docs/results.md.)
    let rests: Vec<&str> = stdout
        .lines()
        .filter(|l| l.starts_with("demo drop: part cow_scan "))
        .collect();
    assert_eq!(rests.len(), parts, "{stdout}");
    let (mut shared, mut weighted) = (0, 0.0);
    for rest in &rests {
        assert!(rest.ends_with("local DOFs: true"), "{rest}");
        let n = number_after(rest, "at rest: true, ");
        let mean: f64 = rest
            .split("mean distance ")
            .nth(1)
            .and_then(|t| t.split(' ').next())
            .and_then(|t| t.parse().ok())
            .unwrap_or_else(|| panic!("{rest}"));
        shared += n;
        weighted += n as f64 * mean;
    }
    assert_eq!(shared, 2999, "{stdout}");
    assert!(weighted / 2999.0 < 0.01, "{}", rests.join("\n"));
    // The new parts (from the sixth on, the first two in the palette's sixth and seventh
    // colours, which the scene's five models do not use) are in the picture.
    let img = image::open(&out).expect("a PNG").to_rgb32f();
    let palette = [
        [0.90, 0.45, 0.20],
        [0.25, 0.55, 0.90],
        [0.35, 0.75, 0.35],
        [0.85, 0.30, 0.55],
        [0.95, 0.80, 0.25],
        [0.55, 0.40, 0.85],
        [0.30, 0.80, 0.80],
        [0.5, 0.5, 0.5],
    ];
    let (_, counts) = colour_counts(&img, &palette, (320..1280, 0..720));
    assert!(
        counts[5] + counts[6] > 3000,
        "the dropped scan's parts: {counts:?}"
    );
    let _ = std::fs::remove_file(&out);
    let _ = std::fs::remove_file(&bad);
}
