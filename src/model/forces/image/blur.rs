//! The Gaussian blur of an image's luminance that the potential is built on: its kernel, bounded
//! below by [`MIN_SIGMA`], and the separable convolution.

/// The narrowest Gaussian the potential takes, in pixels: its weight one pixel off is
/// exp(−8) ≈ 3·10⁻⁴, so a narrower one smooths nothing, and at 10⁻³⁰⁰ its 1/σ² overflows.
pub const MIN_SIGMA: f64 = 0.25;

/// Normalised 1D Gaussian of width `sigma` pixels, radius ⌈3σ⌉.
pub(super) fn gaussian_kernel(sigma: f64) -> Vec<f64> {
    let radius = (3.0 * sigma).ceil() as isize;
    let mut k: Vec<f64> = (-radius..=radius)
        .map(|i| (-(i * i) as f64 / (2.0 * sigma * sigma)).exp())
        .collect();
    let sum: f64 = k.iter().sum();
    k.iter_mut().for_each(|v| *v /= sum);
    k
}

/// Convolves the rows (`along_x`) or the columns of a `width` × `height` field with `kernel`,
/// clamping at the edges.
pub(super) fn convolve(
    src: &[f64],
    width: usize,
    height: usize,
    kernel: &[f64],
    along_x: bool,
) -> Vec<f64> {
    let r = (kernel.len() / 2) as isize;
    let mut out = vec![0.0; src.len()];
    for row in 0..height {
        for col in 0..width {
            let mut acc = 0.0;
            for (t, w) in kernel.iter().enumerate() {
                let o = t as isize - r;
                let (c, rr) = if along_x {
                    (
                        (col as isize + o).clamp(0, width as isize - 1) as usize,
                        row,
                    )
                } else {
                    (
                        col,
                        (row as isize + o).clamp(0, height as isize - 1) as usize,
                    )
                };
                acc += w * src[rr * width + c];
            }
            out[row * width + col] = acc;
        }
    }
    out
}

/// `values` (`width` × `height`, row-major) smoothed by a Gaussian of `sigma` pixels, rows then
/// columns, edges clamped.
pub(crate) fn smooth(values: &[f64], width: usize, height: usize, sigma: f64) -> Vec<f64> {
    let kernel = gaussian_kernel(sigma);
    convolve(
        &convolve(values, width, height, &kernel, true),
        width,
        height,
        &kernel,
        false,
    )
}
