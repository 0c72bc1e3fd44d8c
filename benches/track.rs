//! The tracker swept over generated depth videos whose truth is known
//! (`synthetic::tracking_recipe`): shapes over the exponents, speeds, noise, tilts and tumbles,
//! an occluder on every third, every fifth leaving the view.
//!
//! ```text
//! cargo bench --bench track [-- --videos N] [--video I] [--init roi|truth]
//! cargo bench --bench track -- --video I --write DIR
//! ```
//!
//! `--write DIR` writes video I as `dsq track` reads it (16-bit PNGs, `camera.json`, `roi.txt`)
//! with its truth (`truth.jsonl`), for timing the whole process.
//!
//! Each video is tracked from a box around the object in its first frame (`--init roi`, what a
//! user gives `dsq track --roi`) or from its true first pose (`--init truth`), and scored per
//! frame against the truth: the centre's distance, the orientation's angle modulo the shape's
//! symmetries, the largest semi-axis error. It prints a row per video (`--video I` a row per
//! frame of that video) and the worst case over the sweep of:
//!
//! - frames wholly in view: centre ≤ 2 mm and angle ≤ 0.4°;
//! - frames showing at least a fifth of the surface: centre ≤ 6 mm and angle ≤ 0.03 rad;
//! - after the first 10 frames, semi-axes within 2 mm;
//! - the largest jump of the centre between frames beyond the object's own motion;
//! - orientation flips: good frames whose orientation turned 0.25 rad more than the truth's;
//! - the tracking time per frame (the frame's decoding excluded) against the points it took.
//!
//! `cargo test` runs one short video and fails when a figure is not finite.

use bevy_deformable_sq::io::write_depth_png;
use bevy_deformable_sq::model::track::{
    Frame, TrackOptions, Tracker, free_axis, initial_pose, nearest_axis_angle,
};
use bevy_deformable_sq::synthetic::{
    DEPTH_SCALE, DepthVideoRecipe, PoseError, depth_video, tracking_recipe,
};
use std::process::ExitCode;
use std::time::Instant;

struct Row {
    whole: (usize, usize),
    fifth: (usize, usize),
    worst_whole: (f64, f64),
    worst_fifth: (f64, f64),
    worst_axes: f64,
    worst_jump: f64,
    flips: usize,
    lost: usize,
    seconds: f64,
    points: usize,
    frames: usize,
}

fn track(recipe: &DepthVideoRecipe, from_truth: bool, verbose: bool) -> Result<Row, String> {
    let video = depth_video(recipe);
    let first = video.depth_frame(0);
    let init = if from_truth {
        video.truth[0]
    } else {
        initial_pose(&first, video.roi(0))?
    };
    let mut tracker = Tracker::new(init, TrackOptions::default())?;
    let mut row = Row {
        whole: (0, 0),
        fifth: (0, 0),
        worst_whole: (0.0, 0.0),
        worst_fifth: (0.0, 0.0),
        worst_axes: 0.0,
        worst_jump: 0.0,
        flips: 0,
        lost: 0,
        seconds: 0.0,
        points: 0,
        frames: 0,
    };
    let mut last: Option<glam::DVec3> = None;
    let mut last_turn: Option<(glam::DQuat, glam::DQuat)> = None;
    for i in 0..video.frames.len() {
        let frame = Frame::Depth(video.depth_frame(i));
        let start = Instant::now();
        let out = tracker.step(&frame);
        row.seconds += start.elapsed().as_secs_f64();
        row.points += out.points;
        row.frames += 1;
        let e = PoseError::of(&video.truth[i], &out.pose);
        if out.lost {
            row.lost += 1;
        }
        if video.whole[i] {
            row.whole.1 += 1;
            if e.centre <= 0.002 && e.angle <= 0.4f64.to_radians() {
                row.whole.0 += 1;
            }
            row.worst_whole.0 = row.worst_whole.0.max(e.centre);
            row.worst_whole.1 = row.worst_whole.1.max(e.angle);
        }
        if video.seen[i] >= 0.2 {
            row.fifth.1 += 1;
            if e.centre <= 0.006 && e.angle <= 0.03 {
                row.fifth.0 += 1;
            }
            row.worst_fifth.0 = row.worst_fifth.0.max(e.centre);
            row.worst_fifth.1 = row.worst_fifth.1.max(e.angle);
            if i >= 10 {
                row.worst_axes = row.worst_axes.max(e.axes);
            }
        }
        // A flip: the reported orientation turns between good frames by more than the truth
        // did plus 0.25 rad (another labelling is at least a quarter turn away); where the
        // truth turns freely about an axis, only the fit's axis nearest it counts.
        if !out.lost {
            let (fit, truth) = (out.pose.rotation, video.truth[i].rotation);
            let free = free_axis(&video.truth[i]);
            let turn = |a: glam::DQuat, b: glam::DQuat| match free {
                Some(axis) => {
                    let k = [glam::DVec3::X, glam::DVec3::Y, glam::DVec3::Z]
                        .into_iter()
                        .max_by(|x, y| {
                            (a * *x)
                                .dot(axis)
                                .abs()
                                .total_cmp(&(a * *y).dot(axis).abs())
                        })
                        .unwrap_or(glam::DVec3::Z);
                    nearest_axis_angle(a * k, b)
                }
                None => a.angle_between(b),
            };
            if let Some((f0, t0)) = last_turn
                && turn(f0, fit) > turn(t0, truth) + 0.25
            {
                row.flips += 1;
            }
            last_turn = Some((fit, truth));
        }
        if let Some(prev) = last {
            let moved = (video.truth[i].translation - video.truth[i - 1].translation).length();
            let jump = (out.pose.translation - prev).length() - moved;
            row.worst_jump = row.worst_jump.max(jump);
        }
        last = Some(out.pose.translation);
        if verbose {
            println!(
                "  frame {i:2}  seen {:.2} whole {}  centre {:.2} mm  angle {:.3}°  axes {:.2} mm  lost {}  points {}  free {}  rms {:.2} mm  steps {}",
                video.seen[i],
                video.whole[i] as u8,
                e.centre * 1e3,
                e.angle.to_degrees(),
                e.axes * 1e3,
                out.lost as u8,
                out.points,
                out.free_rays,
                out.rms * 1e3,
                out.iterations
            );
        }
    }
    Ok(row)
}

/// `--write DIR`: video `i` as `dsq track` reads it: DIR/depth_NNN.png, DIR/camera.json
/// (Open3D's intrinsics), DIR/roi.txt (the first frame's box) and DIR/truth.jsonl (a pose line
/// per frame, as `dsq track` prints them).
fn write_video(i: usize, dir: &std::path::Path) -> Result<(), String> {
    use bevy_deformable_sq::model::frame::quat_to_paper;
    std::fs::create_dir_all(dir).map_err(|e| format!("{}: {e}", dir.display()))?;
    let video = depth_video(&tracking_recipe(i));
    let mut truth = String::new();
    for (f, pose) in video.truth.iter().enumerate() {
        let path = dir.join(format!("depth_{f:03}.png"));
        write_depth_png(&path, &video.depth_frame(f), DEPTH_SCALE).map_err(|e| e.to_string())?;
        let s = &pose.shape;
        let line = serde_json::json!({
            "frame": f, "translation": pose.translation.to_array(),
            "rotation": quat_to_paper(pose.rotation), "a": s.a, "a1": s.a1, "a2": s.a2,
            "a3": s.a3, "e1": s.e1, "e2": s.e2, "seen": video.seen[f], "whole": video.whole[f],
        });
        truth.push_str(&format!("{line}\n"));
    }
    let c = &video.intrinsics;
    let camera = serde_json::json!({
        "width": c.width, "height": c.height,
        "intrinsic_matrix": [c.fx, 0.0, 0.0, 0.0, c.fy, 0.0, c.cx, c.cy, 1.0],
    });
    let roi = video.roi(0).map(|x| x.to_string()).join(",");
    let write = |name: &str, text: String| {
        std::fs::write(dir.join(name), text).map_err(|e| format!("{name}: {e}"))
    };
    write("camera.json", camera.to_string())?;
    write("roi.txt", roi)?;
    write("truth.jsonl", truth)
}

fn main() -> ExitCode {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let quick = !args.iter().any(|a| a == "--bench");
    let value = |name: &str| {
        args.iter()
            .position(|a| a == name)
            .and_then(|i| args.get(i + 1))
            .cloned()
    };
    let videos: usize = value("--videos")
        .and_then(|v| v.parse().ok())
        .unwrap_or(if quick { 1 } else { 30 });
    let only: Option<usize> = value("--video").and_then(|v| v.parse().ok());
    let from_truth = value("--init").as_deref() == Some("truth");
    if let Some(dir) = value("--write") {
        return match write_video(only.unwrap_or(0), std::path::Path::new(&dir)) {
            Ok(()) => ExitCode::SUCCESS,
            Err(e) => {
                eprintln!("error: {e}");
                ExitCode::from(2)
            }
        };
    }
    let list: Vec<usize> = only.map_or((0..videos).collect(), |i| vec![i]);
    let mut all = Vec::new();
    println!(
        "video  whole ok  fifth ok  worst whole (mm, °)  worst fifth (mm, rad)  axes mm  jump mm  flips  lost  ms/frame  points"
    );
    for i in list {
        let mut recipe = tracking_recipe(i);
        if quick {
            recipe.frames = 6;
        }
        let row = match track(&recipe, from_truth, only.is_some()) {
            Ok(r) => r,
            Err(e) => {
                eprintln!("error: video {i}: {e}");
                return ExitCode::from(2);
            }
        };
        println!(
            "{i:5}  {:3}/{:<3}  {:3}/{:<3}  {:6.2} {:6.3}        {:6.2} {:6.4}          {:6.2}  {:6.2}  {:5}  {:4}  {:8.2}  {:6}",
            row.whole.0,
            row.whole.1,
            row.fifth.0,
            row.fifth.1,
            row.worst_whole.0 * 1e3,
            row.worst_whole.1.to_degrees(),
            row.worst_fifth.0 * 1e3,
            row.worst_fifth.1,
            row.worst_axes * 1e3,
            row.worst_jump * 1e3,
            row.flips,
            row.lost,
            row.seconds / row.frames as f64 * 1e3,
            row.points / row.frames.max(1)
        );
        let figures = [
            row.worst_whole.0,
            row.worst_whole.1,
            row.worst_fifth.0,
            row.worst_fifth.1,
            row.worst_axes,
            row.seconds,
        ];
        if figures.iter().any(|f| !f.is_finite()) {
            eprintln!("error: video {i} has a figure that is not finite");
            return ExitCode::FAILURE;
        }
        all.push(row);
    }
    let sum = |f: &dyn Fn(&Row) -> usize| all.iter().map(f).sum::<usize>();
    let max = |f: &dyn Fn(&Row) -> f64| all.iter().map(f).fold(0.0, f64::max);
    println!(
        "all    {}/{} wholly-in-view frames within 2 mm and 0.4°; {}/{} frames with a fifth seen within 6 mm and 0.03 rad",
        sum(&|r| r.whole.0),
        sum(&|r| r.whole.1),
        sum(&|r| r.fifth.0),
        sum(&|r| r.fifth.1)
    );
    println!(
        "worst  whole {:.2} mm {:.3}°; fifth {:.2} mm {:.4} rad; axes after 10 frames {:.2} mm; jump {:.2} mm; flips {}; lost {}; {:.2} ms a frame for {} points",
        max(&|r| r.worst_whole.0) * 1e3,
        max(&|r| r.worst_whole.1).to_degrees(),
        max(&|r| r.worst_fifth.0) * 1e3,
        max(&|r| r.worst_fifth.1),
        max(&|r| r.worst_axes) * 1e3,
        max(&|r| r.worst_jump) * 1e3,
        sum(&|r| r.flips),
        sum(&|r| r.lost),
        all.iter().map(|r| r.seconds).sum::<f64>() / sum(&|r| r.frames).max(1) as f64 * 1e3,
        sum(&|r| r.points) / sum(&|r| r.frames).max(1)
    );
    ExitCode::SUCCESS
}
