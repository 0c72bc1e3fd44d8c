//! `track`: one superquadric followed through a depth video, frame by frame, by the core's
//! tracker, with `dsq track`'s lines as dicts.

use crate::value_error;
use bevy_deformable_sq::io::{
    PRIMESENSE_DEFAULT, load_depth_png, load_intrinsics, load_points, parse_intrinsics,
    pose_from_json, track_line,
};
use bevy_deformable_sq::model::init::InitialPose;
use bevy_deformable_sq::model::track::{
    DepthFrame, Frame, Intrinsics, TrackOptions, Tracker, initial_pose,
};
use numpy::{PyReadonlyArray2, PyUntypedArrayMethods};
use pyo3::exceptions::PyStopIteration;
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyString};
use std::path::PathBuf;

/// How the track starts.
#[derive(Clone, Copy)]
enum Start {
    /// From this pose.
    Pose(InitialPose),
    /// From a fit inside this pixel box of the first frame.
    Roi([u32; 4]),
}

/// A track in progress: iterate it for one dict a frame.
#[pyclass(module = "deformable_sq")]
pub struct Track {
    frames: Py<PyAny>,
    camera: Option<Intrinsics>,
    scale: f64,
    start: Start,
    opts: TrackOptions,
    tracker: Option<Tracker>,
    index: usize,
}

#[pymethods]
impl Track {
    fn __iter__(slf: PyRef<'_, Self>) -> PyRef<'_, Self> {
        slf
    }

    fn __next__(&mut self, py: Python<'_>) -> PyResult<Option<Py<PyAny>>> {
        let item = match self.frames.bind(py).call_method0("__next__") {
            Ok(item) => item,
            Err(e) if e.is_instance_of::<PyStopIteration>(py) => return Ok(None),
            Err(e) => return Err(e),
        };
        let i = self.index;
        let (frame, file) = read_frame(&item, self.camera.as_ref(), self.scale)
            .map_err(|e| value_error(format!("frames[{i}]: {e}")))?;
        if self.tracker.is_none() {
            let pose = match self.start {
                Start::Pose(p) => p,
                Start::Roi(roi) => {
                    let depth = match &frame {
                        Frame::Depth(d) => d.clone(),
                        Frame::Points(points) => {
                            let camera = self.camera.ok_or_else(|| {
                                value_error(
                                    "roi on a cloud needs intrinsics to project it".to_string(),
                                )
                            })?;
                            DepthFrame::from_points(camera, points)
                        }
                    };
                    if depth.valid_pixels() == 0 {
                        return Err(value_error(format!(
                            "frames[{i}]: the first frame has no depth to start from"
                        )));
                    }
                    py.detach(|| initial_pose(&depth, roi))
                        .map_err(|e| value_error(format!("roi: {e}")))?
                }
            };
            self.tracker =
                Some(Tracker::new(pose, self.opts).map_err(|e| value_error(format!("init: {e}")))?);
        }
        let Some(tracker) = self.tracker.as_mut() else {
            return Ok(None);
        };
        let out = py.detach(|| tracker.step(&frame));
        let mut line = track_line(i, &out);
        if let Some(file) = file {
            line["file"] = file.into();
        }
        self.index += 1;
        let dict = py
            .import("json")?
            .call_method1("loads", (line.to_string(),))?;
        Ok(Some(dict.unbind()))
    }
}

/// A frame: a path (a 16-bit PNG, or a PLY/OBJ cloud) or an H×W array (uint16 in units of
/// `scale`, any other number type in metres), with the path when it was one.
fn read_frame(
    item: &Bound<'_, PyAny>,
    camera: Option<&Intrinsics>,
    scale: f64,
) -> Result<(Frame, Option<String>), String> {
    if let Some(path) = as_path(item) {
        let name = path.display().to_string();
        let ext = path
            .extension()
            .and_then(|e| e.to_str())
            .map(str::to_ascii_lowercase);
        let frame = match ext.as_deref() {
            Some("png") => load_depth_png(&path, camera, scale)
                .map(Frame::Depth)
                .map_err(|e| e.to_string())?,
            Some("ply" | "obj") => load_points(&path)
                .map(Frame::Points)
                .map_err(|e| e.to_string())?,
            _ => {
                return Err(format!(
                    "{name}: a frame is a 16-bit PNG or a PLY/OBJ cloud"
                ));
            }
        };
        return Ok((frame, Some(name)));
    }
    let camera = camera.copied().unwrap_or(PRIMESENSE_DEFAULT);
    let np = item.py().import("numpy").map_err(|e| e.to_string())?;
    let array = np
        .call_method1("asarray", (item,))
        .map_err(|e| format!("not a path or an array: {e}"))?;
    let dtype: String = array
        .getattr("dtype")
        .and_then(|d| d.getattr("name"))
        .and_then(|n| n.extract())
        .unwrap_or_default();
    let shape: Vec<usize> = array
        .getattr("shape")
        .and_then(|s| s.extract())
        .unwrap_or_default();
    let expected = vec![camera.height as usize, camera.width as usize];
    if shape != expected {
        return Err(format!(
            "an array of shape {shape:?}; the camera's frames are {expected:?} (height, width)"
        ));
    }
    if dtype == "uint16" {
        let a: PyReadonlyArray2<u16> = array
            .extract()
            .map_err(|_| "cannot read the uint16 array".to_string())?;
        let raw: Vec<u16> = a.as_array().iter().copied().collect();
        return DepthFrame::from_raw(camera, &raw, scale).map(|f| (Frame::Depth(f), None));
    }
    let a = np
        .call_method1("ascontiguousarray", (&array, "float64"))
        .map_err(|e| format!("cannot read the array as numbers: {e}"))?;
    let a: PyReadonlyArray2<f64> = a
        .extract()
        .map_err(|_| "cannot read the array as numbers".to_string())?;
    debug_assert_eq!(a.shape(), expected.as_slice());
    let depth: Vec<f32> = a
        .as_array()
        .iter()
        .map(|&z| {
            if z.is_finite() && z > 0.0 {
                z as f32
            } else {
                0.0
            }
        })
        .collect();
    Ok((
        Frame::Depth(DepthFrame {
            intrinsics: camera,
            depth,
        }),
        None,
    ))
}

/// `item` as a path when it is a `str` or an `os.PathLike`.
fn as_path(item: &Bound<'_, PyAny>) -> Option<PathBuf> {
    if item.is_instance_of::<PyString>() || item.hasattr("__fspath__").unwrap_or(false) {
        item.extract::<PathBuf>().ok()
    } else {
        None
    }
}

/// A JSON object given as a dict or a path to a JSON file, as text.
fn json_text(what: &str, value: &Bound<'_, PyAny>) -> PyResult<String> {
    if let Some(path) = as_path(value) {
        return std::fs::read_to_string(&path)
            .map_err(|e| value_error(format!("{what}: {}: cannot read: {e}", path.display())));
    }
    if value.is_instance_of::<PyDict>() {
        let json = value.py().import("json")?;
        return json
            .call_method1("dumps", (value,))?
            .extract()
            .map_err(|e: PyErr| value_error(format!("{what}: {e}")));
    }
    Err(value_error(format!(
        "{what}: give a dict or a path to a JSON file"
    )))
}

/// Follows one object through `frames` (an iterable of 16-bit PNG paths, PLY/OBJ paths, or
/// H×W arrays) as `dsq track` does; yields `dsq track`'s line for each frame as a dict (without
/// its time). See the stub for the keywords.
#[pyfunction]
#[pyo3(signature = (frames, intrinsics=None, *, init=None, roi=None, depth_scale=0.001,
    outliers=TrackOptions::default().outlier_ratio, fix_epsilon=false, free_space=true,
    support=true))]
#[allow(clippy::too_many_arguments)]
pub fn track(
    frames: &Bound<'_, PyAny>,
    intrinsics: Option<&Bound<'_, PyAny>>,
    init: Option<&Bound<'_, PyAny>>,
    roi: Option<Vec<u32>>,
    depth_scale: f64,
    outliers: f64,
    fix_epsilon: bool,
    free_space: bool,
    support: bool,
) -> PyResult<Track> {
    if !(depth_scale.is_finite() && depth_scale > 0.0) {
        return Err(value_error(format!(
            "depth_scale {depth_scale} must be a positive number of metres per unit"
        )));
    }
    let opts = TrackOptions {
        outlier_ratio: outliers,
        hold_exponents: fix_epsilon,
        free_space,
        support,
        ..TrackOptions::default()
    };
    opts.validate()
        .map_err(|e| value_error(format!("outliers: {e}")))?;
    let camera = match intrinsics {
        None => None,
        Some(c) => Some(match as_path(c) {
            Some(path) => load_intrinsics(&path).map_err(value_error)?,
            None => parse_intrinsics(&json_text("intrinsics", c)?)
                .map_err(|e| value_error(format!("intrinsics: {e}")))?,
        }),
    };
    let start = match (init, roi) {
        (Some(_), Some(_)) => return Err(value_error("give init or roi, not both")),
        (Some(init), None) => {
            let text = json_text("init", init)?;
            let v: serde_json::Value = serde_json::from_str(&text)
                .map_err(|e| value_error(format!("init: not JSON: {e}")))?;
            Start::Pose(pose_from_json(&v).map_err(|e| value_error(format!("init: {e}")))?)
        }
        (None, Some(r)) => Start::Roi(
            <[u32; 4]>::try_from(r)
                .map_err(|_| value_error("roi: give four whole pixel numbers x0, y0, x1, y1"))?,
        ),
        (None, None) => return Err(value_error("give init=... or roi=(x0, y0, x1, y1)")),
    };
    let frames = frames
        .try_iter()
        .map_err(|_| value_error("frames: give an iterable of paths or arrays"))?;
    Ok(Track {
        frames: frames.into_any().unbind(),
        camera,
        scale: depth_scale,
        start,
        opts,
        tracker: None,
        index: 0,
    })
}
