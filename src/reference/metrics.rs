//! Image error metrics of docs/physics.md ("Error metrics").
//!
//! Images are linear RGB radiance, RGBA `f32` per pixel, row-major; the alpha channel is ignored.
//! All sums are taken in `f64` so large images do not lose precision.

/// Relative RMSE of `x` against the reference `r`: `sqrt( Σ (x - r)² / Σ r² )` over all pixels and
/// the three colour channels (docs/physics.md's headline figure). Dimensionless.
///
/// Returns `0` when both images are identical (even all black) and `inf` when the reference is
/// black but `x` is not.
///
/// # Panics
/// If the images differ in size.
pub fn relative_rmse(x: &[[f32; 4]], r: &[[f32; 4]]) -> f64 {
    let num = channel_sum(x, r, |a, b| (a - b) * (a - b));
    if num == 0.0 {
        0.0
    } else {
        (num / channel_sum(x, r, |_, b| b * b)).sqrt()
    }
}

/// `Σ f(x, r)` over all pixels and the three colour channels, in `f64`.
///
/// # Panics
/// If the images differ in size.
fn channel_sum(x: &[[f32; 4]], r: &[[f32; 4]], f: impl Fn(f64, f64) -> f64) -> f64 {
    assert_eq!(x.len(), r.len(), "images differ in size");
    let mut sum = 0.0f64;
    for (a, b) in x.iter().zip(r) {
        for c in 0..3 {
            sum += f(a[c] as f64, b[c] as f64);
        }
    }
    sum
}

/// `Σ f(x, r)` over all pixels and colour channels divided by their count; 0 for empty images.
fn channel_mean(x: &[[f32; 4]], r: &[[f32; 4]], f: impl Fn(f64, f64) -> f64) -> f64 {
    let sum = channel_sum(x, r, f);
    if x.is_empty() {
        0.0
    } else {
        sum / (3 * x.len()) as f64
    }
}

/// relMSE: `mean( (x - r)² / (r² + 0.01) )` over all pixels and the three colour channels.
/// The `0.01` keeps dark reference pixels from dominating. Dimensionless.
///
/// # Panics
/// If the images differ in size.
pub fn rel_mse(x: &[[f32; 4]], r: &[[f32; 4]]) -> f64 {
    channel_mean(x, r, |a, b| (a - b) * (a - b) / (b * b + 0.01))
}

/// Mean absolute error `mean |x - r|` over all pixels and the three colour channels, in the
/// images' radiance units.
///
/// # Panics
/// If the images differ in size.
pub fn mean_absolute_error(x: &[[f32; 4]], r: &[[f32; 4]]) -> f64 {
    channel_mean(x, r, |a, b| (a - b).abs())
}

/// The largest difference between two volumes (any flat arrays), relative to the largest value
/// of the reference `r`: `max |x - r| / max |r|`. How the GPU volumes are compared with their
/// CPU reference. Dimensionless.
///
/// Returns `0` when both are identical (even all zero) and `inf` when `r` is all zero but `x` is
/// not.
///
/// # Panics
/// If the volumes differ in size.
pub fn max_relative_difference(x: &[f64], r: &[f64]) -> f64 {
    assert_eq!(x.len(), r.len(), "volumes differ in size");
    let scale = r.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    let largest = x
        .iter()
        .zip(r)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0, f64::max);
    if largest == 0.0 { 0.0 } else { largest / scale }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn max_relative_difference_is_relative_to_the_largest_reference_value() {
        assert_eq!(
            max_relative_difference(&[1.0, 2.5, -4.0], &[1.0, 2.0, -4.0]),
            0.125
        );
        assert_eq!(max_relative_difference(&[0.0; 3], &[0.0; 3]), 0.0);
        assert_eq!(
            max_relative_difference(&[0.0, 1.0], &[0.0; 2]),
            f64::INFINITY
        );
    }

    #[test]
    fn identical_images_have_zero_error() {
        let a = vec![[0.5, 0.25, 1.0, 1.0]; 6];
        assert_eq!(relative_rmse(&a, &a), 0.0);
        assert_eq!(rel_mse(&a, &a), 0.0);
        assert_eq!(mean_absolute_error(&a, &a), 0.0);
        let black = vec![[0.0; 4]; 6];
        assert_eq!(relative_rmse(&black, &black), 0.0);
    }

    #[test]
    fn known_values() {
        // Reference all 1, image all 1.1: every channel is off by 0.1.
        let r = vec![[1.0, 1.0, 1.0, 1.0]; 4];
        let x = vec![[1.1, 1.1, 1.1, 1.0]; 4];
        assert!((relative_rmse(&x, &r) - 0.1).abs() < 1e-6);
        assert!((rel_mse(&x, &r) - 0.01 / 1.01).abs() < 1e-6);
        assert!((mean_absolute_error(&x, &r) - 0.1).abs() < 1e-6);
        // Alpha is ignored.
        let y = vec![[1.0, 1.0, 1.0, 0.0]; 4];
        assert_eq!(relative_rmse(&y, &r), 0.0);
    }
}
