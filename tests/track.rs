//! Tracking through generated depth videos with a known truth (`model::track`), in the library
//! and through `dsq track` as a user runs it.

use bevy_deformable_sq::io::{load_depth_png, write_depth_png};
use bevy_deformable_sq::model::track::{DepthFrame, Frame, TrackOptions, Tracker, initial_pose};
use bevy_deformable_sq::synthetic::{
    DEPTH_SCALE, DepthVideo, PoseError, depth_video, tracking_recipe,
};
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

/// Generated video 0 of the sweep: a box on a floor with a distractor behind it, 40 frames,
/// wholly in view throughout.
fn video() -> DepthVideo {
    depth_video(&tracking_recipe(0))
}

/// A fresh directory for one test's files.
fn scratch(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("dsq-track-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// Writes the first `n` frames of `video` as PNGs and its camera as Open3D JSON into `dir`.
fn write_video(video: &DepthVideo, n: usize, dir: &Path) -> (Vec<PathBuf>, PathBuf) {
    let frames = (0..n)
        .map(|i| {
            let path = dir.join(format!("depth_{i:03}.png"));
            write_depth_png(&path, &video.depth_frame(i), DEPTH_SCALE).unwrap();
            path
        })
        .collect();
    let c = &video.intrinsics;
    let camera = dir.join("camera.json");
    let json = serde_json::json!({
        "width": c.width, "height": c.height,
        "intrinsic_matrix": [c.fx, 0.0, 0.0, 0.0, c.fy, 0.0, c.cx, c.cy, 1.0],
    });
    std::fs::write(&camera, json.to_string()).unwrap();
    (frames, camera)
}

fn dsq(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_dsq"))
        .args(args)
        .output()
        .expect("run dsq")
}

/// `dsq`'s one-line error (exit code 2), or a failed test.
fn error_of(args: &[&str]) -> String {
    let out = dsq(args);
    let err = String::from_utf8_lossy(&out.stderr).into_owned();
    assert_eq!(out.status.code(), Some(2), "{args:?}: {err}");
    let lines: Vec<&str> = err.lines().filter(|l| l.starts_with("error:")).collect();
    assert_eq!(lines.len(), 1, "{args:?}: {err}");
    lines[0].to_string()
}

#[test]
fn a_box_is_tracked_within_the_targets_from_its_true_first_pose() {
    let video = video();
    let mut tracker = Tracker::new(video.truth[0], TrackOptions::default()).unwrap();
    let mut worst = (0.0f64, 0.0f64, 0.0f64);
    for i in 0..video.frames.len() {
        let out = tracker.step(&Frame::Depth(video.depth_frame(i)));
        assert!(!out.lost, "frame {i} lost");
        let e = PoseError::of(&video.truth[i], &out.pose);
        assert!(video.whole[i]);
        worst.0 = worst.0.max(e.centre);
        worst.1 = worst.1.max(e.angle);
        if i >= 10 {
            worst.2 = worst.2.max(e.axes);
        }
        // The MAP energy falls from the prediction and stays finite.
        let [before, after] = out.energy;
        assert!(
            after.is_finite() && after <= before,
            "frame {i}: {before} → {after}"
        );
    }
    assert!(worst.0 < 2e-3, "centre {:.2} mm", worst.0 * 1e3);
    assert!(
        worst.1 < 0.4f64.to_radians(),
        "angle {:.3}°",
        worst.1.to_degrees()
    );
    assert!(worst.2 < 2e-3, "semi-axes {:.2} mm", worst.2 * 1e3);
}

#[test]
fn a_box_is_found_from_a_pixel_box_and_followed() {
    let video = video();
    let first = video.depth_frame(0);
    let init = initial_pose(&first, video.roi(0)).unwrap();
    let mut tracker = Tracker::new(init, TrackOptions::default()).unwrap();
    for i in 0..video.frames.len() {
        let out = tracker.step(&Frame::Depth(video.depth_frame(i)));
        let e = PoseError::of(&video.truth[i], &out.pose);
        assert!(!out.lost, "frame {i} lost");
        // Within 6 mm and 0.03 rad from the first frame on, the issue's looser target.
        assert!(
            e.centre < 6e-3 && e.angle < 0.03,
            "frame {i}: {:.2} mm {:.4} rad",
            e.centre * 1e3,
            e.angle
        );
    }
}

#[test]
fn a_box_seen_from_one_side_starts_as_a_box_not_a_plate() {
    // Video 18: a box whose pure range fit from the first frame alone is a plate through its
    // visible faces; the image's free space and floor pick the box.
    let video = depth_video(&tracking_recipe(18));
    let start = initial_pose(&video.depth_frame(0), video.roi(0)).unwrap();
    let e = PoseError::of(&video.truth[0], &start);
    assert!(
        e.centre < 10e-3 && e.axes < 10e-3 && e.angle < 0.05,
        "{:.2} mm, semi-axes {:.2} mm, {:.3} rad",
        e.centre * 1e3,
        e.axes * 1e3,
        e.angle
    );
}

#[test]
fn a_track_is_lost_on_empty_frames_and_found_again() {
    let video = video();
    let mut tracker = Tracker::new(video.truth[0], TrackOptions::default()).unwrap();
    let blank = DepthFrame {
        intrinsics: video.intrinsics,
        depth: vec![0.0; video.frames[0].len()],
    };
    let mut last_good = None;
    for i in 0..24 {
        let frame = if (10..15).contains(&i) {
            blank.clone()
        } else {
            video.depth_frame(i)
        };
        let out = tracker.step(&Frame::Depth(frame));
        if (10..15).contains(&i) {
            assert!(out.lost, "frame {i} has no depth and is not lost");
            assert_eq!(
                Some(out.pose),
                last_good,
                "a lost frame keeps the last good pose"
            );
        } else {
            assert!(!out.lost, "frame {i} lost");
            last_good = Some(out.pose);
        }
        if i >= 16 {
            let e = PoseError::of(&video.truth[i], &out.pose);
            assert!(
                e.centre < 6e-3 && e.angle < 0.03,
                "frame {i} after re-acquiring: {:.2} mm {:.4} rad",
                e.centre * 1e3,
                e.angle
            );
        }
    }
}

#[test]
fn dsq_track_follows_png_frames_and_agrees_with_the_library_bit_for_bit() {
    let video = video();
    let dir = scratch("run");
    let n = 8;
    let (frames, camera) = write_video(&video, n, &dir);
    let roi = video.roi(0).map(|x| x.to_string()).join(",");
    let params = dir.join("track.jsonl");
    let meshes = dir.join("meshes");
    let mut args = vec!["track", "--quiet", "--intrinsics", camera.to_str().unwrap()];
    args.extend(["--roi", &roi, "--out-params", params.to_str().unwrap()]);
    args.extend(["--out-dir", meshes.to_str().unwrap()]);
    let names: Vec<&str> = frames.iter().map(|p| p.to_str().unwrap()).collect();
    args.extend(&names);
    let run = |args: &[&str]| {
        let out = dsq(args);
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        String::from_utf8(out.stdout).unwrap()
    };
    let stdout = run(&args);
    let lines: Vec<serde_json::Value> = stdout
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    assert_eq!(lines.len(), n + 1);
    let summary = &lines[n];
    assert_eq!(summary["frames"], n);
    assert_eq!(summary["lost"], 0);
    assert!(summary["fps"].as_f64().unwrap() > 0.0);
    assert_eq!(std::fs::read_to_string(&params).unwrap().lines().count(), n);
    for i in 0..n {
        assert!(meshes.join(format!("frame_{i:05}.obj")).exists());
        assert!(meshes.join(format!("frame_{i:05}.png")).exists());
    }

    // The library on the same files gives the same numbers, bit for bit.
    let camera_read = bevy_deformable_sq::io::load_intrinsics(&camera).unwrap();
    let first = load_depth_png(&frames[0], Some(&camera_read), DEPTH_SCALE).unwrap();
    let init = initial_pose(&first, video.roi(0)).unwrap();
    let mut tracker = Tracker::new(init, TrackOptions::default()).unwrap();
    for (i, path) in frames.iter().enumerate() {
        let frame = load_depth_png(path, Some(&camera_read), DEPTH_SCALE).unwrap();
        let out = tracker.step(&Frame::Depth(frame));
        let line = &lines[i];
        assert_eq!(line["frame"], i);
        assert_eq!(line["lost"], false);
        let t: Vec<f64> = serde_json::from_value(line["translation"].clone()).unwrap();
        assert_eq!(t, out.pose.translation.to_array().to_vec(), "frame {i}");
        assert_eq!(line["a1"].as_f64(), Some(out.pose.shape.a1), "frame {i}");
        let e = PoseError::of(&video.truth[i], &out.pose);
        assert!(e.centre < 6e-3, "frame {i}: {:.2} mm", e.centre * 1e3);
    }

    // A second run gives the same lines but for the times.
    let strip = |text: &str| -> Vec<serde_json::Value> {
        text.lines()
            .take(n)
            .map(|l| {
                let mut v: serde_json::Value = serde_json::from_str(l).unwrap();
                v.as_object_mut().unwrap().remove("ms");
                v
            })
            .collect()
    };
    assert_eq!(strip(&stdout), strip(&run(&args)));

    // Started from the first frame's line (`--init`), it follows the same object.
    let init_file = dir.join("init.json");
    std::fs::write(&init_file, stdout.lines().next().unwrap()).unwrap();
    let mut args = vec!["track", "--quiet", "--intrinsics", camera.to_str().unwrap()];
    args.extend(["--init", init_file.to_str().unwrap()]);
    args.extend(&names[1..]);
    let again = run(&args);
    let last: serde_json::Value = serde_json::from_str(again.lines().nth(n - 2).unwrap()).unwrap();
    let t: Vec<f64> = serde_json::from_value(last["translation"].clone()).unwrap();
    let truth = video.truth[n - 1].translation.to_array();
    let off = (0..3)
        .map(|k| (t[k] - truth[k]).powi(2))
        .sum::<f64>()
        .sqrt();
    assert!(off < 6e-3, "from --init: {:.2} mm", off * 1e3);
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn dsq_track_names_bad_input_in_one_line() {
    let video = video();
    let dir = scratch("errors");
    let (frames, camera) = write_video(&video, 2, &dir);
    let (f0, f1) = (frames[0].to_str().unwrap(), frames[1].to_str().unwrap());
    let cam = camera.to_str().unwrap();
    let roi = video.roi(0).map(|x| x.to_string()).join(",");

    // A smaller frame, an 8-bit image, a blank first frame and a camera of another size.
    let small = dir.join("small.png");
    let c = &video.intrinsics;
    let mut half = c.to_owned();
    half.width /= 2;
    let blank = DepthFrame {
        intrinsics: half,
        depth: vec![0.0; (half.width * half.height) as usize],
    };
    write_depth_png(&small, &blank, DEPTH_SCALE).unwrap();
    let grey8 = dir.join("grey8.png");
    image::GrayImage::new(c.width, c.height)
        .save(&grey8)
        .unwrap();
    let empty = dir.join("empty.png");
    let mut none = blank.clone();
    none.intrinsics = *c;
    none.depth = vec![0.0; (c.width * c.height) as usize];
    write_depth_png(&empty, &none, DEPTH_SCALE).unwrap();
    let other_camera = dir.join("other.json");
    std::fs::write(
        &other_camera,
        r#"{"width": 320, "height": 240, "intrinsic_matrix": [300,0,0,0,300,0,160,120,1]}"#,
    )
    .unwrap();
    let bad_camera = dir.join("bad.json");
    std::fs::write(&bad_camera, r#"{"width": 640, "height": 480}"#).unwrap();
    let missing = dir.join("missing.png");
    let cloud = dir.join("cloud.ply");
    std::fs::write(
        &cloud,
        "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\nend_header\n0 0 1\n",
    )
    .unwrap();
    let (small, grey8, empty) = (
        small.to_str().unwrap(),
        grey8.to_str().unwrap(),
        empty.to_str().unwrap(),
    );

    let cases: Vec<(Vec<&str>, &str)> = vec![
        (
            vec![
                f0,
                "--roi",
                &roi,
                "--intrinsics",
                cam,
                missing.to_str().unwrap(),
            ],
            "missing.png: cannot read",
        ),
        (
            vec![f0, "--roi", &roi, "--intrinsics", cam, small],
            "small.png: is 320×480 pixels",
        ),
        (
            vec![
                f0,
                "--roi",
                &roi,
                "--intrinsics",
                other_camera.to_str().unwrap(),
            ],
            "the intrinsics are 320×240",
        ),
        (
            vec![
                f0,
                "--roi",
                &roi,
                "--intrinsics",
                bad_camera.to_str().unwrap(),
            ],
            "`intrinsic_matrix`",
        ),
        (
            vec![f0, "--roi", &roi, "--intrinsics", cam, grey8],
            "16-bit",
        ),
        (
            vec![f0, f1, "--roi", &roi, "--depth-scale", "0"],
            "--depth-scale 0",
        ),
        (
            vec![f0, f1, "--roi", &roi, "--depth-scale", "NaN"],
            "--depth-scale NaN",
        ),
        (
            vec![f0, f1, "--roi", &roi, "--depth-scale", "-0.001"],
            "--depth-scale -0.001",
        ),
        (
            vec![f0, "--roi", "600,400,700,500", "--intrinsics", cam],
            "outside the 640×480 image",
        ),
        (
            vec![f0, "--roi", "1,2,3", "--intrinsics", cam],
            "--roi 1,2,3",
        ),
        (
            vec![empty, f1, "--roi", &roi, "--intrinsics", cam],
            "empty.png: the first frame has no depth",
        ),
        (vec![f0, f1, "--intrinsics", cam], "give --init"),
        (
            vec![cloud.to_str().unwrap(), "--roi", &roi],
            "needs --intrinsics",
        ),
        (
            vec![f0, "--init", missing.to_str().unwrap()],
            "missing.png: cannot read",
        ),
        (vec![f0, "--init", cam], "no `translation`"),
        (vec![f0, "--roi", &roi, "--outliers", "1.5"], "--outliers"),
    ];
    for (mut args, expect) in cases {
        args.insert(0, "track");
        let e = error_of(&args);
        assert!(e.contains(expect), "{args:?}: {e} (expected {expect:?})");
    }
    std::fs::remove_dir_all(&dir).ok();
}
