//! Workgroup sizes, the sort's tile and the beam's spread table: defined once here, handed to
//! every shader as shader defs (`#{LINEAR_WORKGROUP}` …), so that a dispatch and the
//! `@workgroup_size` it assumes, or a table and its reader, cannot disagree.

use bevy::shader::ShaderDefVal;

use crate::{
    beam_phase::{BEAM_PHASE_ANGLES, BEAM_PHASE_DEPTHS},
    shadow_maps::SKY_MAP_DIRECTIONS,
};

use crate::render::core::gpu::StagePass;

/// Invocations per workgroup of the one-dimensional kernels (per particle, per lattice line, per
/// tile); the shaders flatten `(x, y)` workgroups with `flat_invocation`.
pub const LINEAR: u32 = 64;
/// Edge of the square workgroups of the kernels that march one column per invocation (shade,
/// voxelize's upsample, view volume).
pub const SLICE: u32 = 8;
/// Voxels per side of a brick of voxelize's gather (`illumination/voxelize.wgsl`): one
/// workgroup of [`BRICK_THREADS`] sums a brick, two voxels per invocation.
pub const VOXEL_BRICK: u32 = 8;
/// Invocations per workgroup of the kernels that work a brick, or a run of bricks, at a time.
pub const BRICK_THREADS: u32 = VOXEL_BRICK.pow(3) / 2;
/// Elements per tile of the radix sort, each walked in order by one invocation.
pub const SORT_TILE: u32 = 256;
/// Texels per side of a tile of the sky map's caster lists (`illumination/sky_map`).
pub const SKY_MAP_TILE: u32 = 8;
/// The most pairs a sweep direction set has (Lattice98's): one dispatch per order binds that
/// many `SweepDirection`s from its set's first (`illumination/scatter/sweep.wgsl`,
/// `SWEEP_PER_ORDER`).
pub const MAX_SWEEP_PAIRS: usize = 49;

/// The shader defs of every pipeline of the crate.
pub fn shader_defs() -> Vec<ShaderDefVal> {
    vec![
        ShaderDefVal::UInt("LINEAR_WORKGROUP".into(), LINEAR),
        ShaderDefVal::UInt("SLICE_WORKGROUP".into(), SLICE),
        ShaderDefVal::UInt("SORT_TILE".into(), SORT_TILE),
        ShaderDefVal::UInt("VOXEL_BRICK".into(), VOXEL_BRICK),
        ShaderDefVal::UInt("BRICK_WORKGROUP".into(), BRICK_THREADS),
        ShaderDefVal::UInt("BEAM_PHASE_ANGLES".into(), BEAM_PHASE_ANGLES),
        ShaderDefVal::UInt("BEAM_PHASE_DEPTHS".into(), BEAM_PHASE_DEPTHS),
        ShaderDefVal::UInt("SKY_MAP_DIRECTIONS".into(), SKY_MAP_DIRECTIONS),
        ShaderDefVal::UInt("SKY_MAP_TILE".into(), SKY_MAP_TILE),
        ShaderDefVal::UInt(
            "DYNAMIC_UNIFORM_STRIDE".into(),
            crate::render::core::gpu::DYNAMIC_UNIFORM_STRIDE,
        ),
        ShaderDefVal::UInt("MAX_SWEEP_PAIRS".into(), MAX_SWEEP_PAIRS as u32),
    ]
}

/// Workgroups for `count` invocations of a [`LINEAR`] kernel, spread over x and y so that no
/// dimension exceeds the 65535 limit.
pub fn linear_groups(count: u32) -> [u32; 3] {
    let groups = count.div_ceil(LINEAR).max(1);
    let x = groups.min(65535);
    [x, groups.div_ceil(x), 1]
}

/// `groups` workgroups spread over x and y so that no dimension exceeds the 65535 limit (the
/// shaders flatten them with `num_workgroups`).
pub fn spread_groups(groups: u32) -> [u32; 2] {
    let x = groups.clamp(1, 65535);
    [x, groups.div_ceil(x).max(1)]
}

/// Dispatches `count` invocations of a [`LINEAR`] kernel, for each of `items` z workgroups.
pub(crate) fn dispatch_linear(pass: &mut StagePass, count: u32, items: u32) {
    let [x, y, _] = linear_groups(count);
    pass.dispatch(x, y, items);
}

/// Dispatches `rows` rows (y) of `count` invocations of a [`LINEAR`] kernel each (x), for each
/// of `items` z workgroups: one row per part of the work that the kernel tells apart by `id.y`.
pub(crate) fn dispatch_rows(pass: &mut StagePass, count: u32, rows: u32, items: u32) {
    pass.dispatch(count.div_ceil(LINEAR).max(1), rows, items);
}

/// Dispatches one invocation per column of an `n × n` slice ([`SLICE`]² workgroups), for each
/// of `items` z workgroups.
pub(crate) fn dispatch_columns(pass: &mut StagePass, n: u32, items: u32) {
    let g = n.div_ceil(SLICE);
    pass.dispatch(g, g, items);
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every `@workgroup_size` of the shaders is one of the defs, never a number.
    #[test]
    fn shaders_take_their_workgroup_sizes_from_the_defs() {
        let sources = [
            include_str!("../illumination/voxelize.wgsl"),
            include_str!("../illumination/shade.wgsl"),
            include_str!("../illumination/gather.wgsl"),
            include_str!("../illumination/scatter/sweep.wgsl"),
            include_str!("../illumination/scatter/closure.wgsl"),
            include_str!("../view/sort.wgsl"),
            include_str!("../view/view_volume.wgsl"),
            include_str!("../illumination/sky_map.wgsl"),
        ];
        let allowed = [
            "@workgroup_size(#{LINEAR_WORKGROUP})",
            "@workgroup_size(#{SLICE_WORKGROUP}, #{SLICE_WORKGROUP}, 1)",
            "@workgroup_size(#{BRICK_WORKGROUP})",
            // Single-workgroup reductions, dispatched as (1, 1, 1): their size is their own.
            "@workgroup_size(256)",
        ];
        let mut sizes = 0;
        for line in sources.iter().flat_map(|s| s.lines()) {
            if let Some(at) = line.find("@workgroup_size") {
                let size = &line[at..=at + line[at..].find(')').unwrap()];
                assert!(allowed.contains(&size), "{line}");
                sizes += 1;
            }
        }
        assert!(sizes >= 14, "found {sizes} entry points");
    }

    #[test]
    fn spread_groups_cover_the_count_within_the_dimension_limit() {
        for groups in [0, 1, 65535, 65536, 300_000, 4_000_000] {
            let [x, y] = spread_groups(groups);
            assert!(x <= 65535 && y <= 65535 && x >= 1 && y >= 1);
            assert!(x * y >= groups && x * (y - 1) < groups.max(1), "{groups}");
        }
    }

    #[test]
    fn linear_groups_cover_the_count_within_the_dimension_limit() {
        for count in [0, 1, 64, 65, 65535 * 64, 65535 * 64 + 1, 10_000_000] {
            let [x, y, z] = linear_groups(count);
            assert!(x <= 65535 && y <= 65535 && z == 1);
            assert!(x * y * LINEAR >= count.max(1), "{count}");
        }
    }
}
