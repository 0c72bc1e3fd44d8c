//! `dsq track`: one superquadric followed through a depth video (`model::track`).

use bevy_deformable_sq::io::{
    load_depth_png, load_intrinsics, load_points, pose_from_json, track_line, write_model_obj,
    write_track_png,
};
use bevy_deformable_sq::model::dynamics::ModelState;
use bevy_deformable_sq::model::fem::Tessellation;
use bevy_deformable_sq::model::init::InitialPose;
use bevy_deformable_sq::model::track::{
    DepthFrame, Frame, Intrinsics, TrackOptions, TrackedFrame, Tracker, initial_pose,
};
use clap::Args as ClapArgs;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// `dsq track`'s command line.
#[derive(ClapArgs, Debug)]
#[command(after_help = "\
Each frame starts from the last one's prediction and is fitted as a MAP estimate: the frame's \
points near the predicted surface, the prediction as a prior, the image's free space, and the \
floor the object stands on. stdout gets one JSON line per frame (the pose and shape, `frame`, \
`file`, `lost`, `ms`) and a summary line (`frames`, `fps`, `lost`). Bad input exits with code 2 \
and a one-line message.")]
pub struct TrackArgs {
    /// The frames, in order: 16-bit PNG depth images (0 = no depth), or PLY/OBJ clouds already
    /// in the camera frame (x right, y down, z forward).
    #[arg(required = true, value_name = "FRAMES")]
    frames: Vec<PathBuf>,
    /// The camera: the JSON Open3D writes for a PinholeCameraIntrinsic. Default: Open3D's
    /// PrimeSense default (640×480, f = 525).
    #[arg(long, value_name = "CAM.json")]
    intrinsics: Option<PathBuf>,
    /// Metres per depth unit of the PNG frames.
    #[arg(
        long,
        default_value_t = 0.001,
        value_name = "S",
        allow_hyphen_values = true
    )]
    depth_scale: f64,
    /// Start from this superquadric: a `dsq fit --out-params` file, or a line of a track.
    #[arg(long, value_name = "PARAMS.json", conflicts_with = "roi")]
    init: Option<PathBuf>,
    /// Start from a fit to the pixels of the first frame inside this box (x0,y0,x1,y1; x1 and y1
    /// excluded).
    #[arg(long, value_name = "x0,y0,x1,y1", allow_hyphen_values = true)]
    roi: Option<String>,
    /// Also write the per-frame lines to this file (JSON lines).
    #[arg(long, value_name = "FILE")]
    out_params: Option<PathBuf>,
    /// Write each frame's model as DIR/frame_NNNNN.obj, and for a depth frame a picture of the
    /// frame with the model over it, DIR/frame_NNNNN.png.
    #[arg(long, value_name = "DIR")]
    out_dir: Option<PathBuf>,
    /// The outlier mixture's prior outlier fraction in [0, 1): the scene around the object.
    #[arg(long, default_value_t = TrackOptions::default().outlier_ratio, value_name = "F")]
    outliers: f64,
    /// Hold ε1 and ε2 where the first frame put them.
    #[arg(long)]
    fix_epsilon: bool,
    /// Do not use the depth image's free space.
    #[arg(long)]
    no_free_space: bool,
    /// Do not look for a floor under the object.
    #[arg(long)]
    no_support: bool,
    /// No progress on stderr.
    #[arg(long)]
    quiet: bool,
}

/// Triangulation of the written meshes (k rings).
const MESH_K: usize = 24;

/// Runs `dsq track`.
pub fn run(args: TrackArgs) -> Result<(), String> {
    let start = Instant::now();
    if !(args.depth_scale.is_finite() && args.depth_scale > 0.0) {
        return Err(format!(
            "--depth-scale {} must be a positive number of metres per unit",
            args.depth_scale
        ));
    }
    let opts = TrackOptions {
        outlier_ratio: args.outliers,
        hold_exponents: args.fix_epsilon,
        free_space: !args.no_free_space,
        support: !args.no_support,
        ..TrackOptions::default()
    };
    opts.validate().map_err(|e| format!("--outliers: {e}"))?;
    let roi = args.roi.as_deref().map(parse_roi).transpose()?;
    let camera = args
        .intrinsics
        .as_deref()
        .map(load_intrinsics)
        .transpose()
        .map_err(|e| e.to_string())?;
    // The start: a pose, or the box to find one in within the first frame.
    let first: Result<InitialPose, [u32; 4]> = match (&args.init, roi) {
        (Some(path), _) => Ok(read_init(path)?),
        (None, Some(roi)) => Err(roi),
        (None, None) => return Err("give --init PARAMS.json or --roi x0,y0,x1,y1".into()),
    };
    if let Some(dir) = &args.out_dir {
        std::fs::create_dir_all(dir)
            .map_err(|e| format!("{}: cannot create: {e}", dir.display()))?;
    }
    let mut out_params = match &args.out_params {
        Some(path) => Some(std::io::BufWriter::new(
            std::fs::File::create(path)
                .map_err(|e| format!("{}: cannot write: {e}", path.display()))?,
        )),
        None => None,
    };
    let tess = args.out_dir.as_ref().map(|_| Tessellation::new(MESH_K));

    let mut tracker: Option<Tracker> = None;
    let mut lost = 0usize;
    for (i, path) in args.frames.iter().enumerate() {
        let frame_start = Instant::now();
        let frame = read_frame(path, camera.as_ref(), args.depth_scale)?;
        let tracker = match &mut tracker {
            Some(t) => t,
            None => {
                let pose = match first {
                    Ok(pose) => pose,
                    Err(roi) => first_pose(path, &frame, camera.as_ref(), roi)?,
                };
                tracker.insert(Tracker::new(pose, opts).map_err(|e| format!("--init: {e}"))?)
            }
        };
        let out = tracker.step(&frame);
        lost += out.lost as usize;
        let ms = frame_start.elapsed().as_secs_f64() * 1e3;
        let line = frame_line(i, path, &out, ms);
        if let Some(w) = &mut out_params {
            writeln!(w, "{line}").map_err(|e| format!("--out-params: cannot write: {e}"))?;
        }
        if let (Some(dir), Some(tess)) = (&args.out_dir, &tess) {
            let p = &out.pose;
            let state = ModelState::new(tess, p.translation, p.rotation, p.shape);
            write_model_obj(&dir.join(format!("frame_{i:05}.obj")), tess, &state)
                .map_err(|e| e.to_string())?;
            if let Frame::Depth(depth) = &frame {
                write_track_png(&dir.join(format!("frame_{i:05}.png")), depth, p)
                    .map_err(|e| e.to_string())?;
            }
        }
        if !args.quiet {
            eprintln!(
                "frame {i:>5}  {}  points {:>5}  inliers {:>7.0}  rms {:.2} mm  {ms:.1} ms",
                if out.lost { "lost " } else { "     " },
                out.points,
                out.inliers,
                out.rms * 1e3
            );
        }
        crate::emit(line);
    }
    if let Some(mut w) = out_params {
        w.flush()
            .map_err(|e| format!("--out-params: cannot write: {e}"))?;
    }
    let seconds = start.elapsed().as_secs_f64();
    let frames = args.frames.len();
    crate::emit(serde_json::json!({
        "frames": frames,
        "lost": lost,
        "seconds": (seconds * 1e4).round() / 1e4,
        "fps": (frames as f64 / seconds.max(1e-9) * 10.0).round() / 10.0,
    }));
    Ok(())
}

/// One frame's line: the library's ([`track_line`]) with the file and the time.
fn frame_line(i: usize, path: &Path, out: &TrackedFrame, ms: f64) -> serde_json::Value {
    let mut line = track_line(i, out);
    line["file"] = path.display().to_string().into();
    line["ms"] = ((ms * 1e3).round() / 1e3).into();
    line
}

/// `--roi x0,y0,x1,y1`.
fn parse_roi(text: &str) -> Result<[u32; 4], String> {
    let v: Vec<u32> = text
        .split(',')
        .map(|s| s.trim().parse::<u32>())
        .collect::<Result<_, _>>()
        .map_err(|_| format!("--roi {text}: give four whole pixel numbers x0,y0,x1,y1"))?;
    <[u32; 4]>::try_from(v).map_err(|_| format!("--roi {text}: give four numbers x0,y0,x1,y1"))
}

/// A frame by its extension: a PNG depth image, or a PLY/OBJ cloud.
fn read_frame(path: &Path, camera: Option<&Intrinsics>, scale: f64) -> Result<Frame, String> {
    let ext = path
        .extension()
        .and_then(|e| e.to_str())
        .map(str::to_ascii_lowercase);
    match ext.as_deref() {
        Some("png") => load_depth_png(path, camera, scale)
            .map(Frame::Depth)
            .map_err(|e| e.to_string()),
        Some("ply" | "obj") => load_points(path)
            .map(Frame::Points)
            .map_err(|e| e.to_string()),
        _ => Err(format!(
            "{}: a frame is a 16-bit PNG depth image or a PLY/OBJ cloud",
            path.display()
        )),
    }
}

/// The first frame's superquadric, fitted inside the `--roi` box.
fn first_pose(
    path: &Path,
    frame: &Frame,
    camera: Option<&Intrinsics>,
    roi: [u32; 4],
) -> Result<InitialPose, String> {
    let depth = match frame {
        Frame::Depth(d) => d.clone(),
        Frame::Points(points) => {
            let camera = camera.ok_or_else(|| {
                format!(
                    "{}: --roi on a cloud needs --intrinsics to project it",
                    path.display()
                )
            })?;
            DepthFrame::from_points(*camera, points)
        }
    };
    if depth.valid_pixels() == 0 {
        return Err(format!(
            "{}: the first frame has no depth to start from",
            path.display()
        ));
    }
    initial_pose(&depth, roi).map_err(|e| format!("{}: --roi: {e}", path.display()))
}

/// Reads `--init`: a JSON object with `translation`, `rotation` ([s, v1, v2, v3]) and the shape
/// `a`, `a1`, `a2`, `a3`, `e1`, `e2` (a `dsq fit --out-params` file or a track's line).
fn read_init(path: &Path) -> Result<InitialPose, String> {
    let at = |m: String| format!("{}: {m}", path.display());
    let text = std::fs::read_to_string(path).map_err(|e| at(format!("cannot read: {e}")))?;
    let v: serde_json::Value =
        serde_json::from_str(&text).map_err(|e| at(format!("not JSON: {e}")))?;
    let pose = pose_from_json(&v).map_err(at)?;
    for name in ["taper", "bend"] {
        if let Some(d) = v.get(name).and_then(serde_json::Value::as_array)
            && d.iter().any(|x| x.as_f64().is_some_and(|x| x != 0.0))
        {
            eprintln!(
                "warning: {}: the track follows a pure superquadric; `{name}` is dropped",
                path.display()
            );
        }
    }
    Ok(pose)
}
