//! The Rust mirrors of the uniform structs in `types.wgsl` that several steps share: a cloud's
//! parameters, its density levels and a light's box. The layout tests (`render/layout_tests.rs`)
//! hold each to its WGSL twin.

use bevy::{prelude::*, render::render_resource::ShaderType};

use crate::math::{
    LEVEL_KERNEL_NARROWING, MAX_DENSITY_LEVELS, MAX_RADIUS_IN_LEVEL_VOXELS, density_level_sizes,
    light_basis,
};
use crate::render::core::workgroups::VOXEL_BRICK;

/// Mirror of `CloudParams` in `types.wgsl`.
#[derive(ShaderType, Clone, Copy, Debug, Default, PartialEq)]
pub struct CloudParams {
    /// Voxels per side `N` of the density and scattering volumes.
    pub n: u32,
    /// Particles in the cloud.
    pub particle_count: u32,
    /// Voxels per side `m` of the fine density grid and of each light's optical-depth volume,
    /// over the same cube as the scattering grid: any `m >= n` (the gather weighs the fine
    /// voxels by their overlap with each scattering voxel).
    pub light_n: u32,
    /// Lights in the cloud's light array.
    pub light_count: u32,
    /// Corner of the density cube, cloud-local metres.
    pub grid_origin: Vec3,
    /// Voxel size, cloud-local metres.
    pub h: f32,
    /// Centre of the density cube, cloud-local metres.
    pub grid_centre: Vec3,
    /// Extinction per cloud-local metre at density 1 (`K` times the cloud's scale).
    pub k_local: f32,
    /// Single-scattering albedo.
    pub albedo: f32,
    /// Forward-scattering fraction of the shading pass.
    pub forward_scattering: f32,
    /// Henyey–Greenstein anisotropy `g` of the scattering towards the camera.
    pub anisotropy: f32,
    /// The fraction of the shaded optical depths the light's beam and the multiple scattering
    /// see ([`DeltaM::depth_scale`](crate::particle::DeltaM::depth_scale); 1 for an isotropic medium).
    pub depth_scale: f32,
    /// 1 when a light or the sky reaches the cloud, else 0 (it only absorbs).
    pub lit: u32,
    /// 1 when other clouds' media reach into its scattering grid ([`overlap`](crate::render::plan::overlap)).
    pub foreign: u32,
    /// The albedo the multiple scattering sweeps with ([`DeltaM::albedo`](crate::particle::DeltaM::albedo)).
    pub scatter_albedo: f32,
    /// The asymmetry `g'` of the sweep's P2 source ([`DeltaM::anisotropy`](crate::particle::DeltaM::anisotropy)).
    pub scatter_anisotropy: f32,
    /// The second moment `chi'_2` of the sweep's P2 source ([`DeltaM::second_moment`](crate::particle::DeltaM::second_moment)).
    pub scatter_second_moment: f32,
    /// 1 when the scattering volumes hold angular moments beside their means (an anisotropic
    /// medium; docs/illumination.md §4, §9), else 0.
    pub moments: u32,
}

/// Mirror of `DensityLevels` in `types.wgsl`: the density levels of a fine grid
/// (docs/illumination.md §1), with the level one upsample dispatch enlarges.
#[derive(ShaderType, Clone, Copy, Debug, Default, PartialEq)]
pub struct DensityLevels {
    /// Per level, the fine grid first: voxels per side (x), first element in the density
    /// buffer (y), first brick of voxelize's gather among a cloud's bricks (z), and bricks per
    /// side (w; [`VOXEL_BRICK`] voxels each).
    pub size_offset: [UVec4; MAX_DENSITY_LEVELS],
    /// Levels in use.
    pub count: u32,
    /// The level an upsample dispatch enlarges into the one below it (0 for the deposit).
    pub upsample_from: u32,
    /// [`MAX_RADIUS_IN_LEVEL_VOXELS`].
    pub max_radius: f32,
    /// [`LEVEL_KERNEL_NARROWING`].
    pub kernel_narrowing: f32,
}

impl DensityLevels {
    /// Elements of the buffer that holds every density level of a fine grid of `m` voxels per side.
    pub fn elements(m: u32) -> u64 {
        density_level_sizes(m)
            .iter()
            .map(|&n| (n as u64).pow(3))
            .sum()
    }

    /// Bricks of voxelize's gather over every density level of a fine grid of `m` voxels per
    /// side.
    pub fn bricks(m: u32) -> u64 {
        density_level_sizes(m)
            .iter()
            .map(|&n| (n.div_ceil(VOXEL_BRICK) as u64).pow(3))
            .sum()
    }

    /// The levels of a fine grid of `m` voxels per side, one entry per value of `upsample_from`
    /// (`0..count`); and the elements of the density buffer that holds them all.
    pub(crate) fn entries(m: u32) -> (Vec<DensityLevels>, u64) {
        let sizes = density_level_sizes(m);
        let mut size_offset = [UVec4::ZERO; MAX_DENSITY_LEVELS];
        let mut elements = 0;
        let mut bricks = 0;
        for (entry, &n) in size_offset.iter_mut().zip(&sizes) {
            let side = n.div_ceil(VOXEL_BRICK);
            *entry = UVec4::new(n, elements as u32, bricks, side);
            elements += (n as u64).pow(3);
            bricks += side.pow(3);
        }
        let entries = (0..sizes.len() as u32)
            .map(|upsample_from| DensityLevels {
                size_offset,
                count: sizes.len() as u32,
                upsample_from,
                max_radius: MAX_RADIUS_IN_LEVEL_VOXELS as f32,
                kernel_narrowing: LEVEL_KERNEL_NARROWING as f32,
            })
            .collect();
        (entries, elements)
    }
}

/// Mirror of `LightParams` in `types.wgsl`.
#[derive(ShaderType, Clone, Copy, Debug, Default, PartialEq)]
pub struct LightParams {
    /// First axis across the light, cloud-local.
    pub u: Vec3,
    /// Voxel size along `u`, local metres.
    pub h_u: f32,
    /// Second axis across the light.
    pub v: Vec3,
    /// Voxel size along `v`.
    pub h_v: f32,
    /// The direction the light travels, cloud-local.
    pub w: Vec3,
    /// Voxel size along `w` (the slice thickness).
    pub h_w: f32,
    /// Half-extents of the light box along `u`, `v`, `w`.
    pub half_extents: Vec3,
    /// Extinction per local metre per unit density in the shading pass, `k_local (1 - f albedo)`.
    pub sigma_scale: f32,
    /// Linear RGB irradiance.
    pub irradiance: Vec3,
    /// First element of this light's volume in the cloud's optical-depth buffer.
    pub offset: u32,
}

impl LightParams {
    /// The light box of light `index` travelling along `direction_local` (docs/illumination.md §2).
    pub fn new(cloud: &CloudParams, direction_local: Vec3, irradiance: Vec3, index: u32) -> Self {
        let [u, v, w] = light_basis(direction_local.as_dvec3().normalize()).map(|a| a.as_vec3());
        let side = cloud.h * cloud.n as f32;
        let half_extents = 0.5
            * side
            * Vec3::new(
                u.abs().element_sum(),
                v.abs().element_sum(),
                w.abs().element_sum(),
            );
        let h = 2.0 * half_extents / cloud.light_n as f32;
        Self {
            u,
            h_u: h.x,
            v,
            h_v: h.y,
            w,
            h_w: h.z,
            half_extents,
            sigma_scale: cloud.k_local * (1.0 - cloud.forward_scattering * cloud.albedo),
            irradiance,
            offset: index * cloud.light_n.pow(3),
        }
    }
}
