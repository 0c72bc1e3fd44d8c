//! The keywords of `fit` and `fit_image`, read into the core's options: the same names as
//! `dsq fit`'s flags (with `_` for `-`), the same resolution, and a `ValueError` naming the
//! keyword for an unknown one or a value of the wrong type.

use crate::value_error;
use bevy_deformable_sq::model::fit::{CloudOptions, FitOptions, Solver, Stiffness, k_for_nodes};
use bevy_deformable_sq::model::forces::image::DEFAULT_SIGMA;
use bevy_deformable_sq::model::image_fit::{ImageChoices, ImageFitOptions};
use bevy_deformable_sq::model::parts::{DEFAULT_MAX_PARTS, PartCount};
use pyo3::prelude::*;
use pyo3::types::PyDict;

/// The keywords of `fit`.
pub const FIT_KEYWORDS: [&str; 19] = [
    "global_only",
    "solver",
    "paper_forces",
    "robust",
    "plane",
    "switch",
    "similar",
    "migrate",
    "taper",
    "bend",
    "outliers",
    "nodes",
    "k",
    "w0",
    "w1",
    "beta",
    "max_steps",
    "reassign",
    "implicit_local",
];

/// The keywords of `fit_image`.
pub const IMAGE_KEYWORDS: [&str; 14] = [
    "global_only",
    "solver",
    "sigma",
    "band",
    "region",
    "paper_band",
    "free_depth",
    "fix_epsilon",
    "nodes",
    "k",
    "w0",
    "w1",
    "beta",
    "max_steps",
];

/// A keyword's value as `T`, or a `ValueError` naming it and what it takes.
fn value<'py, T: FromPyObjectOwned<'py>>(
    key: &str,
    v: &Bound<'py, PyAny>,
    takes: &str,
) -> PyResult<T> {
    v.extract::<T>().map_err(|_| {
        let got = v
            .get_type()
            .name()
            .map(|n| n.to_string())
            .unwrap_or_default();
        value_error(format!("{key}: expected {takes}, got {got}"))
    })
}

/// The (keyword, value) pairs of `options`, each keyword one of `known`.
fn keywords<'py>(
    options: Option<&Bound<'py, PyDict>>,
    known: &[&str],
) -> PyResult<Vec<(String, Bound<'py, PyAny>)>> {
    let Some(options) = options else {
        return Ok(Vec::new());
    };
    options
        .iter()
        .map(|(k, v)| {
            let key: String = k.extract()?;
            if !known.contains(&key.as_str()) {
                return Err(value_error(format!(
                    "unknown option {key:?}; the options are {}",
                    known.join(", ")
                )));
            }
            Ok((key, v))
        })
        .collect()
}

/// A node count's k, or k as given.
fn tessellation(key: &str, v: &Bound<'_, PyAny>) -> PyResult<usize> {
    let n: usize = value(key, v, "a positive integer")?;
    if key == "nodes" {
        k_for_nodes(n).map_err(|e| value_error(e.replacen("--nodes", "nodes", 1)))
    } else {
        Ok(n)
    }
}

/// The `solver` keyword's value.
fn solver(key: &str, v: &Bound<'_, PyAny>) -> PyResult<Solver> {
    let s: String = value(key, v, "\"solved\" or \"dynamics\"")?;
    match s.as_str() {
        "solved" | "lm" => Ok(Solver::Solved),
        "dynamics" => Ok(Solver::Dynamics),
        _ => Err(value_error(format!(
            "solver: {s:?} is not a solver; give \"solved\" or \"dynamics\""
        ))),
    }
}

/// `fit`'s keywords resolved as `dsq fit` resolves its flags for a POINTS file.
pub fn cloud_options(options: Option<&Bound<'_, PyDict>>) -> PyResult<FitOptions> {
    let mut c = CloudOptions::default();
    for (key, v) in keywords(options, &FIT_KEYWORDS)? {
        let flag = |v: &Bound<'_, PyAny>| value::<bool>(&key, v, "True or False");
        let number = |v: &Bound<'_, PyAny>| value::<f64>(&key, v, "a number");
        let count = |v: &Bound<'_, PyAny>| value::<u32>(&key, v, "a non-negative integer");
        match key.as_str() {
            "global_only" => c.global_only = flag(&v)?,
            "paper_forces" => c.paper_forces = flag(&v)?,
            "robust" => c.robust = flag(&v)?,
            "plane" => c.plane = flag(&v)?,
            "switch" => c.switch = flag(&v)?,
            "similar" => c.similar = flag(&v)?,
            "migrate" => c.migrate = flag(&v)?,
            "taper" => c.taper = flag(&v)?,
            "bend" => c.bend = flag(&v)?,
            "solver" => c.solver = Some(solver(&key, &v)?),
            "outliers" => c.outliers = Some(number(&v)?),
            "nodes" | "k" => c.k = Some(tessellation(&key, &v)?),
            "w0" => c.w0 = Some(number(&v)?),
            "w1" => {
                c.w1 = Some(if v.extract::<String>().is_ok_and(|s| s == "auto") {
                    Stiffness::FromNoise
                } else {
                    Stiffness::Value(value(&key, &v, "a number or \"auto\"")?)
                })
            }
            "beta" => c.beta = Some(number(&v)?),
            "max_steps" => c.max_steps = Some(count(&v)?),
            "reassign" => c.reassign = Some(count(&v)?),
            "implicit_local" => c.implicit_local = Some(number(&v)?),
            _ => unreachable!("checked against FIT_KEYWORDS"),
        }
    }
    c.resolve(FitOptions::default(), true).map_err(value_error)
}

/// `fit_parts`'s `parts` and `max_parts`: "auto" (the default) or a count of at least 1; a cap
/// of at least 1, only with "auto".
pub fn part_count(
    parts: Option<&Bound<'_, PyAny>>,
    max_parts: Option<usize>,
) -> PyResult<PartCount> {
    if max_parts == Some(0) {
        return Err(value_error(
            "max_parts = 0 is out of range: it must be at least 1",
        ));
    }
    let n: usize = match parts {
        Some(v) if !v.extract::<String>().is_ok_and(|s| s == "auto") => {
            value("parts", v, "\"auto\" or a whole number")?
        }
        _ => return Ok(PartCount::Auto(max_parts.unwrap_or(DEFAULT_MAX_PARTS))),
    };
    if n == 0 {
        return Err(value_error(
            "parts = 0 is out of range: it must be at least 1",
        ));
    }
    if max_parts.is_some() {
        return Err(value_error(
            "max_parts caps parts=\"auto\"; give parts=\"auto\"",
        ));
    }
    Ok(PartCount::Exact(n))
}

/// `fit_image`'s keywords resolved as `dsq fit --image` resolves its flags, and the
/// potential's σ.
pub fn image_options(options: Option<&Bound<'_, PyDict>>) -> PyResult<(ImageFitOptions, f64)> {
    let mut c = ImageChoices::default();
    for (key, v) in keywords(options, &IMAGE_KEYWORDS)? {
        let flag = |v: &Bound<'_, PyAny>| value::<bool>(&key, v, "True or False");
        let number = |v: &Bound<'_, PyAny>| value::<f64>(&key, v, "a number");
        match key.as_str() {
            "global_only" => c.global_only = flag(&v)?,
            "paper_band" => c.paper_band = flag(&v)?,
            "free_depth" => c.free_depth = flag(&v)?,
            "fix_epsilon" => c.fix_epsilon = flag(&v)?,
            "sigma" => c.sigma = Some(number(&v)?),
            "band" => c.band = Some(number(&v)?),
            "region" => c.region = Some(number(&v)?),
            "nodes" | "k" => c.k = Some(tessellation(&key, &v)?),
            "w0" => c.w0 = Some(number(&v)?),
            "w1" => c.w1 = Some(number(&v)?),
            "beta" => c.beta = Some(number(&v)?),
            "max_steps" => c.max_steps = Some(value(&key, &v, "a non-negative integer")?),
            "solver" => c.solver = Some(solver(&key, &v)?),
            _ => unreachable!("checked against IMAGE_KEYWORDS"),
        }
    }
    c.resolve(ImageFitOptions::default(), DEFAULT_SIGMA)
        .map_err(value_error)
}

/// An image array's width, height and row-major luminance in [0, 1]: (H, W) grey or (H, W, 3|4)
/// colour (Rec. 709 weights; its RGB kept), floats as they are and integers over 255.
pub fn luminance(image: &Bound<'_, PyAny>) -> PyResult<Pixels> {
    let np = image.py().import("numpy")?;
    let array = np.call_method1("asarray", (image,))?;
    let integer: bool = np
        .call_method1(
            "issubdtype",
            (array.getattr("dtype")?, np.getattr("integer")?),
        )?
        .extract()?;
    let array = crate::as_f64_array(&array)?;
    let shape: Vec<usize> = array.getattr("shape")?.extract()?;
    let scale = if integer { 1.0 / 255.0 } else { 1.0 };
    let flat: Vec<f64> = array.call_method0("ravel")?.extract()?;
    let (lum, rgb) = match shape[..] {
        [_, _] => (flat.iter().map(|v| v * scale).collect(), None),
        [_, _, 3 | 4] => (
            flat.chunks(shape[2])
                .map(|c| scale * (0.2126 * c[0] + 0.7152 * c[1] + 0.0722 * c[2]))
                .collect(),
            Some(
                flat.chunks(shape[2])
                    .map(|c| [c[0], c[1], c[2]].map(|v| (scale * v) as f32))
                    .collect(),
            ),
        ),
        _ => {
            return Err(value_error(format!(
                "image: expected an (H, W) or (H, W, 3) array, got shape {shape:?}"
            )));
        }
    };
    Ok((shape[1], shape[0], lum, rgb))
}

/// An image array's width, height, luminance and, for a colour array, its RGB.
pub type Pixels = (usize, usize, Vec<f64>, Option<Vec<[f32; 3]>>);
