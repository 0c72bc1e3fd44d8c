//! An image's tones: Otsu's threshold, whether the image is two tones (a silhouette), its
//! foreground, and luminance from colour.

use super::RegionModel;

/// Otsu's separability η (the share of the luminance's variance between the two classes of
/// Otsu's threshold) from which an image is two-tone: a silhouette, whose two classes are figure
/// and ground for every part on it. Drawn silhouettes (the shipped horse) have η ≥ 0.99; the
/// shipped photos 0.56–0.76.
pub const TWO_TONE: f64 = 0.9;

/// Otsu's threshold of luminance values in [0, 1] (256 bins).
pub fn otsu_threshold(luminance: &[f64]) -> f64 {
    let mut hist = [0usize; 256];
    for &v in luminance {
        hist[(v.clamp(0.0, 1.0) * 255.0).round() as usize] += 1;
    }
    let total = luminance.len() as f64;
    let sum_all: f64 = hist
        .iter()
        .enumerate()
        .map(|(i, &h)| i as f64 * h as f64)
        .sum();
    let (mut w0, mut sum0, mut best, mut best_t) = (0.0, 0.0, -1.0, 0usize);
    for (t, &h) in hist.iter().enumerate() {
        w0 += h as f64;
        sum0 += t as f64 * h as f64;
        let w1 = total - w0;
        if w0 == 0.0 || w1 == 0.0 {
            continue;
        }
        let (m0, m1) = (sum0 / w0, (sum_all - sum0) / w1);
        let between = w0 * w1 * (m0 - m1).powi(2);
        if between > best {
            best = between;
            best_t = t;
        }
    }
    (best_t as f64 + 0.5) / 255.0
}

/// True when Otsu's two classes of `values` hold at least [`TWO_TONE`] of their variance: the
/// values are two tones (a silhouette), not the many of a photo.
pub(crate) fn two_toned(values: &[f64]) -> bool {
    two_tone_share(values) >= TWO_TONE
}

/// The share of the variance of `values` that Otsu's two classes hold (0 for no values or no
/// variance).
fn two_tone_share(values: &[f64]) -> f64 {
    let n = values.len() as f64;
    if n == 0.0 {
        return 0.0;
    }
    let t = otsu_threshold(values);
    let (mut sums, mut counts) = ([0.0; 2], [0.0; 2]);
    for &v in values {
        sums[usize::from(v > t)] += v;
        counts[usize::from(v > t)] += 1.0;
    }
    let mean = values.iter().sum::<f64>() / n;
    let total = values.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / n;
    let between = counts[0] * counts[1] / (n * n)
        * (sums[1] / counts[1].max(1.0) - sums[0] / counts[0].max(1.0)).powi(2);
    if total > 0.0 { between / total } else { 0.0 }
}

/// See [`super::ImagePotential::foreground`], and [`super::ImagePotential::two_tone`].
pub(super) fn foreground_mask(w: usize, h: usize, lum: &[f64]) -> (Vec<bool>, Option<RegionModel>) {
    let t = otsu_threshold(lum);
    let (mut bright, mut border) = (0usize, 0usize);
    for row in 0..h {
        for col in 0..w {
            if row == 0 || col == 0 || row + 1 == h || col + 1 == w {
                border += 1;
                bright += (lum[row * w + col] > t) as usize;
            }
        }
    }
    let foreground_bright = 2 * bright < border;
    let mask: Vec<bool> = lum.iter().map(|&v| (v > t) == foreground_bright).collect();
    let (mut sums, mut counts) = ([0.0; 2], [0usize; 2]);
    for (&v, &f) in lum.iter().zip(&mask) {
        sums[usize::from(f)] += v;
        counts[usize::from(f)] += 1;
    }
    let two_tone = (!counts.contains(&0) && two_toned(lum)).then(|| {
        let [ground, figure] = [0, 1].map(|c| sums[c] / counts[c] as f64);
        RegionModel {
            inside: figure,
            outside: ground,
        }
    });
    (mask, two_tone)
}

/// Converts 8-bit or float image data to luminance in [0, 1] (Rec. 709 weights on RGB).
pub fn luminance_of(rgb: [f64; 3]) -> f64 {
    0.2126 * rgb[0] + 0.7152 * rgb[1] + 0.0722 * rgb[2]
}
