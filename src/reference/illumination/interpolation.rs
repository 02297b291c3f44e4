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

/// The voxels of a fine grid of `m` per side that overlap voxel `v` of a grid of `n` per side
/// over the same interval, each with its overlap in fine voxels (1 when whole; they sum to
/// `m / n`). In units of `1 / n` fine voxel, voxel `v` spans `[v m, (v + 1) m)` and fine voxel `j`
/// spans `[j n, (j + 1) n)`, so integers decide every overlap exactly; with `m = f n` these are
/// the `f` children, whole (contract section 1).
pub(super) fn axis_overlaps(v: usize, n: usize, m: usize) -> impl Iterator<Item = (usize, f64)> {
    let (lo, hi) = (v * m, (v + 1) * m);
    (lo / n..hi.div_ceil(n)).map(move |j| {
        let overlap = (hi.min((j + 1) * n) - lo.max(j * n)) as f64;
        (j, overlap / n as f64)
    })
}

/// [`axis_overlaps`] along three axes: the fine voxels `(i, j, k)` that overlap voxel `voxel`,
/// with the product of their overlaps.
pub(super) fn overlaps(
    voxel: (usize, usize, usize),
    n: usize,
    m: usize,
) -> impl Iterator<Item = ((usize, usize, usize), f64)> {
    let (a, b, c) = voxel;
    axis_overlaps(c, n, m).flat_map(move |(k, wk)| {
        axis_overlaps(b, n, m).flat_map(move |(j, wj)| {
            axis_overlaps(a, n, m).map(move |(i, wi)| ((i, j, k), wi * wj * wk))
        })
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Three voxels over eight fine ones: each covers 8/3 of them, the ones it shares in part.
    #[test]
    fn fine_voxels_are_weighed_by_their_overlap() {
        let third = 1.0 / 3.0;
        let close = |a: Vec<(usize, f64)>, b: &[(usize, f64)]| {
            a.len() == b.len()
                && a.iter()
                    .zip(b)
                    .all(|(x, y)| x.0 == y.0 && (x.1 - y.1).abs() < 1e-15)
        };
        assert!(close(
            axis_overlaps(0, 3, 8).collect(),
            &[(0, 1.0), (1, 1.0), (2, 2.0 * third)]
        ));
        let middle = [(2, third), (3, 1.0), (4, 1.0), (5, third)];
        assert!(close(axis_overlaps(1, 3, 8).collect(), &middle));
        assert!(close(
            axis_overlaps(2, 3, 8).collect(),
            &[(5, 2.0 * third), (6, 1.0), (7, 1.0)]
        ));
        // A whole factor: the children, whole.
        assert!(close(
            axis_overlaps(2, 4, 12).collect(),
            &[(6, 1.0), (7, 1.0), (8, 1.0)]
        ));
        for (n, m) in [(48, 188), (64, 301), (7, 7), (5, 23)] {
            for v in 0..n {
                let sum: f64 = overlaps((v, n - 1 - v, v / 2), n, m).map(|(_, w)| w).sum();
                let expected = (m as f64 / n as f64).powi(3);
                assert!((sum - expected).abs() < 1e-12 * expected, "{n} {m} {v}");
            }
        }
    }
}
