//! Trilinear lookups on voxel grids, shared by every stage.

use std::ops::{Add, Mul};

use bevy::math::DVec3;

/// The two voxels (index, weight) that one axis of a trilinear lookup touches. `None` is a voxel
/// outside the volume.
type AxisFootprint = [(Option<usize>, f64); 2];

/// Footprint of continuous voxel coordinate `g` (voxel `i` has its centre at `g = i`) with a zero
/// border: voxels outside `0..n` are reported as `None` and the caller treats them as 0.
pub(super) fn axis_zero_border(g: f64, n: usize) -> AxisFootprint {
    let i0 = g.floor();
    let f = g - i0;
    let inside = |i: f64| (i >= 0.0 && i < n as f64).then_some(i as usize);
    [(inside(i0), 1.0 - f), (inside(i0 + 1.0), f)]
}

/// Footprint of `g` clamped to the edge voxels (a texture's clamp-to-edge addressing).
pub(super) fn axis_clamped(g: f64, n: usize) -> AxisFootprint {
    let g = g.clamp(0.0, (n - 1) as f64);
    let i0 = g.floor();
    let f = g - i0;
    let i0 = i0 as usize;
    [(Some(i0), 1.0 - f), (Some((i0 + 1).min(n - 1)), f)]
}

/// Trilinear combination over the 8 corners of `axes` (x, y, z footprints) of a volume of side `n`
/// stored with linear index `i + n * (j + n * k)`. Corners outside (`None`) or of zero weight are
/// skipped, so out-of-range indices are never touched.
pub(super) fn trilinear<T>(axes: [AxisFootprint; 3], n: usize, values: &[T]) -> T
where
    T: Copy + Default + Add<Output = T> + Mul<f64, Output = T>,
{
    trilinear_of(axes, n, |i| values[i])
}

/// [`trilinear`] of the values `value(i)` of the voxels `i`.
pub(super) fn trilinear_of<T>(axes: [AxisFootprint; 3], n: usize, value: impl Fn(usize) -> T) -> T
where
    T: Default + Add<Output = T> + Mul<f64, Output = T>,
{
    let mut acc = T::default();
    for &(k, wk) in &axes[2] {
        for &(j, wj) in &axes[1] {
            for &(i, wi) in &axes[0] {
                let (Some(i), Some(j), Some(k)) = (i, j, k) else {
                    continue;
                };
                let w = wi * wj * wk;
                if w != 0.0 {
                    acc = acc + value(i + n * (j + n * k)) * w;
                }
            }
        }
    }
    acc
}

/// Per-voxel arrays as [`trilinear_of`] combines them.
pub(super) struct Entries<const K: usize>(pub(super) [DVec3; K]);

impl<const K: usize> Default for Entries<K> {
    fn default() -> Self {
        Self([DVec3::ZERO; K])
    }
}

impl<const K: usize> Add for Entries<K> {
    type Output = Self;
    fn add(self, other: Self) -> Self {
        Self(std::array::from_fn(|i| self.0[i] + other.0[i]))
    }
}

impl<const K: usize> Mul<f64> for Entries<K> {
    type Output = Self;
    fn mul(self, w: f64) -> Self {
        Self(self.0.map(|v| v * w))
    }
}

/// Splits a linear index `i + n * (j + n * k)` into `(i, j, k)`.
#[inline]
pub(super) fn unravel(idx: usize, n: usize) -> (usize, usize, usize) {
    (idx % n, (idx / n) % n, idx / (n * n))
}
