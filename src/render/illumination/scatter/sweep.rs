//! The discrete-ordinates sweep's directions (docs/illumination.md §4; `sweep.wgsl`): the
//! uniform entry of each direction pair, where each set of them sits in the sweep's dynamic
//! uniform buffer, and how many lattice lines a direction has in a grid.

use bevy::{prelude::*, render::render_resource::ShaderType};

use crate::render::core::gpu::DYNAMIC_UNIFORM_STRIDE;
use crate::settings::SweepDirections;

/// Mirror of `SweepDirection` in `sweep.wgsl`: one direction pair `(o, -o)` of the
/// discrete-ordinates sweep.
#[derive(ShaderType, Clone, Copy, Debug, Default, PartialEq)]
pub struct SweepDirection {
    /// The lattice direction, its first non-zero component positive.
    pub o: IVec3,
    /// 1 for the first dispatch of an iteration (it overwrites `S_{n+1}`), else 0.
    pub first: u32,
    /// 1 when the iteration's order goes into `multiple` (after its sweeps: `accumulate_order`,
    /// or with one dispatch per order `sum_pairs`); 0 for a warm restart's first sweep.
    pub accumulate: u32,
    /// Linear RGB radiance of the sky, for the sweeps of an iteration that brings the boundary
    /// in (docs/illumination.md §4), else 0.
    pub sky: Vec3,
    /// 1 for the sweeps of an iteration that brings the light entering the grid in (the sky's,
    /// and the ground's on lines that climb), else 0.
    pub boundary: u32,
    /// Each direction's weight in the order's mean and flux
    /// ([`crate::lattice::LatticeDirection::mean`]).
    pub mean_weight: f32,
    /// Each direction's weight in the order's quadrupole
    /// ([`crate::lattice::LatticeDirection::quadrupole`]).
    pub quadrupole_weight: f32,
    /// The number of pairs in the direction set (13 or 49).
    pub pairs: u32,
}

/// The direction sets in the order the uniform buffer holds them, in each of its four sets.
pub(crate) const DIRECTION_SETS: [SweepDirections; 2] =
    [SweepDirections::Lattice26, SweepDirections::Lattice98];

/// Direction pairs of every direction set (13 + 49): the entries of each of the four sets of
/// [`sweep_direction_offset`].
const PAIRS_PER_SET: usize = 62;

pub use crate::render::core::workgroups::MAX_SWEEP_PAIRS;

/// Bytes the sweep's direction binding holds: [`MAX_SWEEP_PAIRS`] entries, whichever stencil
/// reads it.
pub const SWEEP_DIRECTIONS_BINDING: u64 = MAX_SWEEP_PAIRS as u64 * DYNAMIC_UNIFORM_STRIDE as u64;

/// The dynamic offset of the `SweepDirection` of direction pair `index` (of
/// `directions.pairs()`), accumulating or not, bringing the sky in or not.
pub fn sweep_direction_offset(
    directions: SweepDirections,
    index: usize,
    accumulate: bool,
    sky: bool,
) -> u32 {
    let set = 2 * (!accumulate as usize) + (!sky as usize);
    let before: usize = DIRECTION_SETS
        .iter()
        .take_while(|&&d| d != directions)
        .map(|d| d.pairs().len())
        .sum();
    (set * PAIRS_PER_SET + before + index) as u32 * DYNAMIC_UNIFORM_STRIDE
}

/// Lattice lines of direction `o` in an `n³` grid, as `sweep.wgsl`'s `sweep` decodes them
/// (one invocation each, some of them empty): the first axis of largest `|o_a| = f` starts at
/// `0..f`, each other moving axis at `-(ceil(n / f) - 1) |o_a|..n`, each still axis at `0..n`.
pub fn sweep_lines(o: IVec3, n: u32) -> u32 {
    let steps = o.abs().to_array().map(|c| c as u32);
    let f = steps.into_iter().max().unwrap_or(1).max(1);
    let first = steps.iter().position(|&c| c == f).unwrap_or(0);
    let reach = n.div_ceil(f) - 1;
    (0..3)
        .map(|a| match steps[a] {
            0 => n,
            _ if a == first => f,
            s => n + reach * s,
        })
        .product()
}

/// The direction pairs of every direction set in each of the four sets of
/// [`sweep_direction_offset`], with the sky radiance `sky` in the sets that bring it in.
pub(crate) fn sweep_direction_entries(sky: Vec3) -> impl Iterator<Item = SweepDirection> {
    (0..4).flat_map(move |set| {
        DIRECTION_SETS.into_iter().flat_map(move |directions| {
            directions
                .pairs()
                .iter()
                .enumerate()
                .map(move |(i, d)| SweepDirection {
                    o: IVec3::from_array(d.o),
                    first: (i == 0) as u32,
                    // The inverse of `sweep_direction_offset`'s set.
                    accumulate: (set < 2) as u32,
                    sky: if set % 2 == 0 { sky } else { Vec3::ZERO },
                    boundary: (set % 2 == 0) as u32,
                    mean_weight: d.mean as f32,
                    quadrupole_weight: d.quadrupole as f32,
                    pairs: directions.pairs().len() as u32,
                })
        })
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Decoded as `sweep.wgsl` does, the invocations of each direction pair hold every voxel
    /// of the grid on exactly one line (empty lines aside), for both direction sets.
    #[test]
    fn sweep_lines_cover_the_grid_once_per_direction() {
        let n = 5;
        for set in DIRECTION_SETS {
            let pairs = set.pairs();
            for d in pairs {
                let o = IVec3::from_array(d.o);
                assert!(!pairs.iter().any(|e| IVec3::from_array(e.o) == -o), "{o}");
                let mut hits = vec![0u32; (n * n * n) as usize];
                for line in 0..sweep_lines(o, n) {
                    for v in decoded_line(o, n, line) {
                        hits[(v.x + n as i32 * (v.y + n as i32 * v.z)) as usize] += 1;
                    }
                }
                assert!(hits.iter().all(|&h| h == 1), "{o}: {hits:?}");
            }
        }
        // The 26 directions' count: n^(3-k) (2n-1)^(k-1) for k moving axes.
        let lines = |o| sweep_lines(o, n);
        assert_eq!([lines(IVec3::X), lines(IVec3::ONE)], [25, 81]);
    }

    /// The voxels of invocation `line` of direction `o`'s sweep, decoded as `scatter.wgsl`'s
    /// `sweep` does (in the frame where `o` has no negative component).
    fn decoded_line(o: IVec3, n: u32, mut line: u32) -> Vec<IVec3> {
        let step = o.abs();
        let f = step.max_element();
        let first = (0..3).find(|&a| step[a] == f).unwrap();
        let reach = n.div_ceil(f as u32) as i32 - 1;
        let mut start = IVec3::ZERO;
        for a in 0..3 {
            let span = match step[a] {
                0 => n,
                _ if a == first => f as u32,
                s => n + (reach * s) as u32,
            };
            let offset = if step[a] == 0 || a == first {
                0
            } else {
                reach * step[a]
            };
            start[a] = (line % span) as i32 - offset;
            line /= span;
        }
        (0..n as i32)
            .map(|t| start + t * step)
            .filter(|v| v.cmpge(IVec3::ZERO).all() && v.cmplt(IVec3::splat(n as i32)).all())
            .collect()
    }

    /// One dispatch per order binds MAX_SWEEP_PAIRS entries from any set's first pair: the
    /// largest set has that many, and the buffer holds them past the last set's.
    #[test]
    fn one_dispatch_per_order_binds_every_pair_of_the_largest_set() {
        let most = DIRECTION_SETS.iter().map(|s| s.pairs().len()).max();
        assert_eq!(most, Some(MAX_SWEEP_PAIRS));
        let entries = sweep_direction_entries(Vec3::ZERO).count() + MAX_SWEEP_PAIRS - 1;
        for set in DIRECTION_SETS {
            let last = sweep_direction_offset(set, 0, false, false) as u64;
            let end = last + SWEEP_DIRECTIONS_BINDING;
            assert!(
                end <= (entries as u64) * DYNAMIC_UNIFORM_STRIDE as u64,
                "{set:?}"
            );
            let entry = &sweep_direction_entries(Vec3::ZERO).collect::<Vec<_>>()
                [(last / DYNAMIC_UNIFORM_STRIDE as u64) as usize];
            assert_eq!(entry.pairs as usize, set.pairs().len());
        }
    }

    /// Every offset the passes ask for finds the entry it means: its direction, whether it
    /// accumulates, and the sky only where it brings it in.
    #[test]
    fn every_sweep_direction_offset_finds_its_entry() {
        let sky = Vec3::new(0.1, 0.2, 0.3);
        let entries: Vec<SweepDirection> = sweep_direction_entries(sky).collect();
        assert_eq!(entries.len(), 4 * PAIRS_PER_SET);
        for (i, d) in DIRECTION_SETS
            .iter()
            .flat_map(|s| s.pairs().iter().enumerate().map(move |(i, d)| (i, (*s, d))))
        {
            let (set, d) = d;
            for accumulate in [true, false] {
                for brings_sky in [true, false] {
                    let offset = sweep_direction_offset(set, i, accumulate, brings_sky);
                    let entry = entries[(offset / DYNAMIC_UNIFORM_STRIDE) as usize];
                    assert_eq!(entry.o, IVec3::from_array(d.o));
                    assert_eq!(entry.mean_weight, d.mean as f32);
                    assert_eq!(entry.first, (i == 0) as u32);
                    assert_eq!(entry.accumulate, accumulate as u32);
                    assert_eq!(entry.sky, if brings_sky { sky } else { Vec3::ZERO });
                    assert_eq!(entry.boundary, brings_sky as u32);
                }
            }
        }
    }
}
