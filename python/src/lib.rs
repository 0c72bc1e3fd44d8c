//! `deformable_sq`: bevy_deformable_sq's fitter for Python. numpy arrays in, fitted parameters,
//! meshes and surface samples out; options are the keywords of `dsq fit`'s flags, resolved by the
//! same code (`CloudOptions`), so a cloud fits here as `dsq fit` fits it. Every fit releases the
//! GIL. Bad input raises `ValueError` with the message `dsq` prints.

mod options;
mod track;

use bevy_deformable_sq::io::{MESH_SAMPLES, load_points_sampled};
use bevy_deformable_sq::model::dynamics::ModelState;
use bevy_deformable_sq::model::fem::Tessellation;
use bevy_deformable_sq::model::fit::{FitReport, FitSummary, fit as fit_cloud};
use bevy_deformable_sq::model::forces::image::{ImageFrame, ImagePotential};
use bevy_deformable_sq::model::frame::rotation_matrix;
use bevy_deformable_sq::model::image_fit::{ImagePartFit, PartAxes, fit_image as fit_image_parts};
use bevy_deformable_sq::model::parts::{Whole, fit_parts as fit_whole};
use bevy_deformable_sq::synthetic::Rng;
use glam::{DVec2, DVec3};
use numpy::ndarray::Array2;
use numpy::{IntoPyArray, PyArray2, PyReadonlyArray2, PyUntypedArrayMethods};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList};
use std::path::PathBuf;
use std::sync::Arc;

/// A `ValueError` with `message`'s first line, as `dsq` prints it.
fn value_error(message: impl std::fmt::Display) -> PyErr {
    let text = message.to_string();
    let line = text.lines().find(|l| !l.trim().is_empty()).unwrap_or("");
    PyValueError::new_err(line.to_string())
}

/// `array` as a C-contiguous float64 array (any dtype numpy can cast).
fn as_f64_array<'py>(array: &Bound<'py, PyAny>) -> PyResult<Bound<'py, PyAny>> {
    let np = array.py().import("numpy")?;
    np.call_method1("ascontiguousarray", (array, "float64"))
        .map_err(|e| value_error(format!("cannot read the array as numbers: {e}")))
}

/// An (N, 3) array of points.
fn points_of(array: &Bound<'_, PyAny>) -> PyResult<Vec<DVec3>> {
    let array = as_f64_array(array)?;
    let view: PyReadonlyArray2<f64> = array.extract().map_err(|_| {
        let shape: Vec<usize> = array
            .getattr("shape")
            .and_then(|s| s.extract())
            .unwrap_or_default();
        value_error(format!(
            "points: expected an (N, 3) array, got shape {shape:?}"
        ))
    })?;
    let shape = view.shape();
    if shape[1] != 3 {
        return Err(value_error(format!(
            "points: expected an (N, 3) array, got shape {shape:?}"
        )));
    }
    let a = view.as_array();
    Ok(a.rows()
        .into_iter()
        .map(|r| DVec3::new(r[0], r[1], r[2]))
        .collect())
}

/// (V, 3) float64 vertices and (F, 3) int64 faces of a model's closed surface.
fn mesh_arrays<'py>(
    py: Python<'py>,
    tess: &Tessellation,
    state: &ModelState,
) -> (Bound<'py, PyArray2<f64>>, Bound<'py, PyArray2<i64>>) {
    let mut x = Vec::new();
    state.node_positions(tess, &mut x);
    let v: Vec<f64> = x.iter().flat_map(|p| p.to_array()).collect();
    let f: Vec<i64> = tess
        .triangles()
        .iter()
        .flat_map(|t| t.map(i64::from))
        .collect();
    let v = Array2::from_shape_vec((x.len(), 3), v).expect("3 coordinates a vertex");
    let f = Array2::from_shape_vec((tess.triangles().len(), 3), f).expect("3 corners a face");
    (v.into_pyarray(py), f.into_pyarray(py))
}

/// `n` points on a model's surface, uniform by area, from `seed`.
fn surface_samples<'py>(
    py: Python<'py>,
    tess: &Tessellation,
    state: &ModelState,
    n: usize,
    seed: u64,
) -> Bound<'py, PyArray2<f64>> {
    let mut x = Vec::new();
    state.node_positions(tess, &mut x);
    let tris = tess.triangles();
    let corners = |t: &[u32; 3]| t.map(|i| x[i as usize]);
    // Cumulative areas, to pick a triangle by area.
    let mut cumulative = Vec::with_capacity(tris.len());
    let mut total = 0.0;
    for t in tris {
        let [a, b, c] = corners(t);
        total += 0.5 * (b - a).cross(c - a).length();
        cumulative.push(total);
    }
    let mut rng = Rng::new(seed);
    let mut out = Vec::with_capacity(3 * n);
    for _ in 0..n {
        let pick = rng.uniform() * total;
        let i = cumulative
            .partition_point(|&c| c < pick)
            .min(tris.len() - 1);
        let [a, b, c] = corners(&tris[i]);
        let (mut u, mut v) = (rng.uniform(), rng.uniform());
        if u + v > 1.0 {
            (u, v) = (1.0 - u, 1.0 - v);
        }
        out.extend((a + (b - a) * u + (c - a) * v).to_array());
    }
    Array2::from_shape_vec((n, 3), out)
        .expect("3 coordinates a point")
        .into_pyarray(py)
}

/// A fit of a superquadric (and its membrane) to a point cloud: the fitted global parameters,
/// the residuals, and the surface.
#[pyclass(module = "deformable_sq", frozen)]
struct FitResult {
    report: FitReport,
    summary: FitSummary,
}

#[pymethods]
impl FitResult {
    /// The translation c of the model frame (data units).
    #[getter]
    fn translation(&self) -> [f64; 3] {
        self.summary.translation
    }

    /// The rotation as a unit quaternion [w, x, y, z] (the paper's [s, v1, v2, v3]).
    #[getter]
    fn rotation(&self) -> [f64; 4] {
        self.summary.rotation
    }

    /// The rotation as a 3 × 3 matrix (model frame to data frame).
    #[getter]
    fn rotation_matrix<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray2<f64>> {
        let m = rotation_matrix(self.report.state.rotation);
        let rows: Vec<f64> = (0..3).flat_map(|r| m.row(r).to_array()).collect();
        Array2::from_shape_vec((3, 3), rows)
            .expect("3 × 3")
            .into_pyarray(py)
    }

    /// The scale a (data units).
    #[getter]
    fn a(&self) -> f64 {
        self.summary.shape.a
    }

    /// The aspect ratios a1, a2, a3.
    #[getter]
    fn aspect(&self) -> [f64; 3] {
        let s = &self.summary.shape;
        [s.a1, s.a2, s.a3]
    }

    /// The squareness ε1 (along z) and ε2 (about z).
    #[getter]
    fn epsilon(&self) -> [f64; 2] {
        let s = &self.summary.shape;
        [s.e1, s.e2]
    }

    /// The tapering (t_x, t_y); zero unless freed.
    #[getter]
    fn taper(&self) -> [f64; 2] {
        self.summary.taper
    }

    /// The bending (b_x, b_y); zero unless freed.
    #[getter]
    fn bend(&self) -> [f64; 2] {
        self.summary.bend
    }

    /// Point-to-surface distances as fractions of the bounding-box diagonal: mean, rms, p95, max.
    #[getter]
    fn residuals<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let r = &self.summary.residuals;
        let d = PyDict::new(py);
        for (k, v) in [
            ("mean", r.mean),
            ("rms", r.rms),
            ("p95", r.p95),
            ("max", r.max),
            ("diagonal", r.diagonal),
        ] {
            d.set_item(k, v)?;
        }
        Ok(d)
    }

    /// Whether the fit came to rest before its step cap.
    #[getter]
    fn converged(&self) -> bool {
        self.summary.converged
    }

    /// Steps (or solver iterations) taken.
    #[getter]
    fn steps(&self) -> u32 {
        self.summary.steps
    }

    /// The node count of the membrane's tessellation.
    #[getter]
    fn nodes(&self) -> usize {
        self.summary.nodes
    }

    /// Which solver ran: "solved" or "dynamics".
    #[getter]
    fn solver(&self) -> &'static str {
        self.summary.solver.name()
    }

    /// The noise the points show (fraction of the diagonal) when the stiffness came from it.
    #[getter]
    fn noise(&self) -> Option<f64> {
        self.summary.noise
    }

    /// The fitted closed surface: (vertices (V, 3) float64, faces (F, 3) int64).
    fn mesh<'py>(&self, py: Python<'py>) -> (Bound<'py, PyArray2<f64>>, Bound<'py, PyArray2<i64>>) {
        mesh_arrays(py, &self.report.tess, &self.report.state)
    }

    /// `n` points sampled on the fitted surface, uniform by area (from `seed`).
    #[pyo3(signature = (n, seed = 0))]
    fn surface_points<'py>(
        &self,
        py: Python<'py>,
        n: usize,
        seed: u64,
    ) -> Bound<'py, PyArray2<f64>> {
        surface_samples(py, &self.report.tess, &self.report.state, n, seed)
    }

    /// The parameters as `dsq fit --out-params` writes them.
    fn to_dict<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let json = serde_json::to_string(&self.summary).map_err(value_error)?;
        py.import("json")?.call_method1("loads", (json,))
    }

    fn __repr__(&self) -> String {
        let s = &self.summary.shape;
        format!(
            "FitResult(a={:.4}, aspect=({:.3}, {:.3}, {:.3}), epsilon=({:.3}, {:.3}), mean={:.3e}, converged={})",
            s.a,
            s.a1,
            s.a2,
            s.a3,
            s.e1,
            s.e2,
            self.summary.residuals.mean,
            if self.summary.converged {
                "True"
            } else {
                "False"
            }
        )
    }
}

/// Fits a deformable superquadric to `points`, an (N, 3) array, with `dsq fit`'s defaults for
/// a cloud; the keywords are its flags (see the stub for the list).
#[pyfunction]
#[pyo3(signature = (points, **options))]
fn fit(
    py: Python<'_>,
    points: &Bound<'_, PyAny>,
    options: Option<&Bound<'_, PyDict>>,
) -> PyResult<FitResult> {
    let points = points_of(points)?;
    let options = options::cloud_options(options)?;
    let report = py
        .detach(|| fit_cloud(&points, &options, |_| {}))
        .map_err(value_error)?;
    Ok(FitResult {
        summary: report.summary(),
        report,
    })
}

/// A whole object fitted as parts: each part's fit, the part of every point, and the joints.
#[pyclass(module = "deformable_sq", frozen)]
struct PartsResult {
    whole: Whole,
}

#[pymethods]
impl PartsResult {
    /// Each part's fit, as `fit` returns it.
    #[getter]
    fn parts(&self) -> Vec<FitResult> {
        self.whole
            .fits
            .iter()
            .map(|report| FitResult {
                summary: report.summary(),
                report: report.clone(),
            })
            .collect()
    }

    /// The part of each point (the one whose surface is nearest), an (N,) int64 array.
    #[getter]
    fn owner<'py>(&self, py: Python<'py>) -> Bound<'py, numpy::PyArray1<i64>> {
        let owner: Vec<i64> = self.whole.owner.iter().map(|&o| o as i64).collect();
        owner.into_pyarray(py)
    }

    /// The joints between the parts that touch: (part i, part j, [x, y, z] where they touch).
    #[getter]
    fn joints(&self) -> Vec<(usize, usize, [f64; 3])> {
        self.whole
            .joints
            .iter()
            .map(|j| (j.parts[0], j.parts[1], j.at.to_array()))
            .collect()
    }

    /// The fraction of the points the parts explain: those within the split's reach (where
    /// coding a point as an outlier would be cheaper) of the nearest part.
    #[getter]
    fn explained(&self) -> f64 {
        self.whole.explained
    }

    /// For each part, the fraction of its points (those nearest it) within reach of it.
    #[getter]
    fn part_explained(&self) -> Vec<f64> {
        self.whole.part_explained.clone()
    }

    fn __len__(&self) -> usize {
        self.whole.fits.len()
    }

    fn __repr__(&self) -> String {
        format!(
            "PartsResult({} parts, {} joints)",
            self.whole.fits.len(),
            self.whole.joints.len()
        )
    }
}

/// Fits a whole object: `points`, an (N, 3) array, split into parts as `dsq fit --parts`
/// splits a cloud. `parts`: "auto" (as many as the description length asks, at most
/// `max_parts`) or a count; the other keywords are `fit`'s.
#[pyfunction]
#[pyo3(signature = (points, parts = None, max_parts = None, **options))]
fn fit_parts(
    py: Python<'_>,
    points: &Bound<'_, PyAny>,
    parts: Option<&Bound<'_, PyAny>>,
    max_parts: Option<usize>,
    options: Option<&Bound<'_, PyDict>>,
) -> PyResult<PartsResult> {
    let points = points_of(points)?;
    let count = options::part_count(parts, max_parts)?;
    let options = options::cloud_options(options)?;
    let whole = py
        .detach(|| fit_whole(&points, count, &options))
        .map_err(value_error)?;
    Ok(PartsResult { whole })
}

/// The points of an OBJ or PLY file, as an (N, 3) float64 array: its vertices, or, when it has
/// faces, `mesh_samples` points spread uniformly by area over its surface.
#[pyfunction]
#[pyo3(signature = (path, mesh_samples = MESH_SAMPLES))]
fn load_points<'py>(
    py: Python<'py>,
    path: PathBuf,
    mesh_samples: usize,
) -> PyResult<Bound<'py, PyArray2<f64>>> {
    let points = py
        .detach(|| load_points_sampled(&path, mesh_samples))
        .map_err(value_error)?;
    let flat: Vec<f64> = points.iter().flat_map(|p| p.to_array()).collect();
    Ok(Array2::from_shape_vec((points.len(), 3), flat)
        .expect("3 coordinates a point")
        .into_pyarray(py))
}

/// One part of an image fit: its pose and shape in the image plane's frame, and its surface.
#[pyclass(module = "deformable_sq", frozen)]
struct ImagePart {
    fit: ImagePartFit,
    tess: Tessellation,
}

#[pymethods]
impl ImagePart {
    /// The translation c (the image plane's units: the image's longer side spans
    /// [-0.5, 0.5], y up).
    #[getter]
    fn translation(&self) -> [f64; 3] {
        self.fit.state.translation.to_array()
    }

    /// The rotation as a unit quaternion [w, x, y, z].
    #[getter]
    fn rotation(&self) -> [f64; 4] {
        let q = self.fit.state.rotation;
        [q.w, q.x, q.y, q.z]
    }

    /// The scale a.
    #[getter]
    fn a(&self) -> f64 {
        self.fit.state.shape.a
    }

    /// The aspect ratios a1, a2, a3.
    #[getter]
    fn aspect(&self) -> [f64; 3] {
        let s = &self.fit.state.shape;
        [s.a1, s.a2, s.a3]
    }

    /// The squareness ε1, ε2.
    #[getter]
    fn epsilon(&self) -> [f64; 2] {
        let s = &self.fit.state.shape;
        [s.e1, s.e2]
    }

    /// Whether the part came to rest before its step cap.
    #[getter]
    fn converged(&self) -> bool {
        self.fit.converged
    }

    /// Steps taken.
    #[getter]
    fn steps(&self) -> usize {
        self.fit.steps
    }

    /// Why the part was stopped (it grew without bound or left the image), or None.
    #[getter]
    fn stopped(&self) -> Option<String> {
        self.fit.stopped.clone()
    }

    /// The mean image potential along the outline before and after the fit (1 on a typical
    /// strong edge).
    #[getter]
    fn outline(&self) -> (f64, f64) {
        (self.fit.outline_before, self.fit.outline_after)
    }

    /// The part's closed surface: (vertices (V, 3) float64, faces (F, 3) int64).
    fn mesh<'py>(&self, py: Python<'py>) -> (Bound<'py, PyArray2<f64>>, Bound<'py, PyArray2<i64>>) {
        mesh_arrays(py, &self.tess, &self.fit.state)
    }

    fn __repr__(&self) -> String {
        let s = &self.fit.state.shape;
        format!(
            "ImagePart(a={:.4}, aspect=({:.3}, {:.3}, {:.3}), epsilon=({:.3}, {:.3}), converged={})",
            s.a,
            s.a1,
            s.a2,
            s.a3,
            s.e1,
            s.e2,
            if self.fit.converged { "True" } else { "False" }
        )
    }
}

/// Fits parts to an image: `image` is an (H, W) luminance array or an (H, W, 3) RGB one, in
/// [0, 1] or 0–255 for integers; each of `parts` is eight pixel coordinates, both ends of the
/// part's major axis then of its minor axis. The keywords are `dsq fit --image`'s flags.
#[pyfunction]
#[pyo3(signature = (image, parts, **options))]
fn fit_image(
    py: Python<'_>,
    image: &Bound<'_, PyAny>,
    parts: &Bound<'_, PyList>,
    options: Option<&Bound<'_, PyDict>>,
) -> PyResult<Vec<ImagePart>> {
    let (width, height, lum, rgb) = options::luminance(image)?;
    let (opts, sigma) = options::image_options(options)?;
    let potential = ImagePotential::new(width, height, lum, sigma, ImageFrame::default())
        .and_then(|p| match rgb {
            Some(rgb) => p.with_colour(rgb),
            None => Ok(p),
        })
        .map_err(|e| value_error(format!("image: {e}")))?;
    let potential = Arc::new(potential);
    let placed: Vec<PartAxes> = parts
        .iter()
        .enumerate()
        .map(|(i, p)| {
            let n: Vec<f64> = p.extract().map_err(|_| {
                value_error(format!(
                    "parts[{i}]: expected 8 numbers x0, y0, x1, y1, x2, y2, x3, y3"
                ))
            })?;
            if n.len() != 8 {
                return Err(value_error(format!(
                    "parts[{i}]: expected 8 numbers x0, y0, x1, y1, x2, y2, x3, y3, got {}",
                    n.len()
                )));
            }
            let pixels = [0, 2, 4, 6].map(|j| DVec2::new(n[j], n[j + 1]));
            PartAxes::from_points(&potential, pixels)
                .map_err(|e| value_error(format!("parts[{i}]: {e}")))
        })
        .collect::<PyResult<_>>()?;
    if placed.is_empty() {
        return Err(value_error("parts: give at least one part"));
    }
    let fits = py
        .detach(|| fit_image_parts(potential, &placed, &opts))
        .map_err(value_error)?;
    let tess = Tessellation::new(opts.k);
    Ok(fits
        .into_iter()
        .map(|fit| ImagePart {
            fit,
            tess: tess.clone(),
        })
        .collect())
}

/// The module.
#[pymodule]
fn deformable_sq(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(fit, m)?)?;
    m.add_function(wrap_pyfunction!(fit_image, m)?)?;
    m.add_function(wrap_pyfunction!(fit_parts, m)?)?;
    m.add_class::<PartsResult>()?;
    m.add_function(wrap_pyfunction!(load_points, m)?)?;
    m.add_class::<FitResult>()?;
    m.add_class::<ImagePart>()?;
    m.add_function(wrap_pyfunction!(track::track, m)?)?;
    m.add_class::<track::Track>()?;
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    Ok(())
}
