//! The `Particles` asset on the GPU: uploaded once per change of the asset.

use std::sync::atomic::{AtomicU64, Ordering};

use bevy::{
    ecs::system::{SystemParamItem, lifetimeless::SRes},
    prelude::*,
    render::{
        render_asset::{PrepareAssetError, RenderAsset, RenderAssets},
        render_resource::{Buffer, BufferInitDescriptor, BufferUsages},
        renderer::RenderDevice,
    },
};
use bytemuck::{Pod, Zeroable};

use crate::cloud::Particles;
use crate::render::extract::ExtractedCloud;

/// Extinction times density (1/m) above which a medium is lowered to it on the GPU: every voxel
/// is opaque long before (docs/benchmark/dense.md: black from about 1e6), and the passes' products
/// of it overflow f32 near 1e38, which drew NaN at an extinction of `f32::MAX`.
pub const OPAQUE_EXTINCTION: f32 = 1e30;

/// One particle as the shaders read it (`types.wgsl`, `Particle`).
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable)]
#[repr(C)]
pub struct GpuParticle {
    /// Cloud-local centre (xyz, metres) and radius (w, metres).
    pub position_radius: [f32; 4],
    /// Density in x; yzw unused.
    pub density: [f32; 4],
}

/// The grid the density is voxelized on (docs/illumination.md §1), in cloud-local metres.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CloudBounds {
    /// Centre of the cube, cloud-local metres.
    pub centre: Vec3,
    /// Side of the cube.
    pub side: f32,
    /// The largest radius of a particle that carries density, local metres.
    pub max_radius: f32,
    /// The densest particle's peak density (dimensionless; the medium's `extinction` scales it),
    /// for the warning on media denser than the fine grid resolves.
    pub max_density: f32,
}

/// A particle set uploaded to the GPU.
pub struct GpuParticles {
    /// `array<Particle>`; usable as storage in every pass.
    pub buffer: Buffer,
    /// Number of particles (the buffer holds at least one, for a valid binding).
    pub count: u32,
    /// `None` when no particle carries density (nothing to render).
    pub bounds: Option<CloudBounds>,
    /// Changes whenever the asset is uploaded again: the voxelize and sort caches key on it.
    pub generation: u64,
}

static GENERATION: AtomicU64 = AtomicU64::new(1);

impl RenderAsset for GpuParticles {
    type SourceAsset = Particles;
    type Param = SRes<RenderDevice>;

    fn prepare_asset(
        source: Self::SourceAsset,
        _id: AssetId<Self::SourceAsset>,
        device: &mut SystemParamItem<Self::Param>,
        _previous: Option<&Self>,
    ) -> Result<Self, PrepareAssetError<Self::SourceAsset>> {
        let mut data: Vec<GpuParticle> = source
            .particles
            .iter()
            .map(|p| GpuParticle {
                position_radius: [p.position.x, p.position.y, p.position.z, p.radius],
                density: [p.density, 0.0, 0.0, 0.0],
            })
            .collect();
        let count = data.len() as u32;
        // Storage bindings may not be empty.
        if data.is_empty() {
            data.push(GpuParticle::default());
        }
        let buffer = device.create_buffer_with_data(&BufferInitDescriptor {
            label: Some("particle_clouds_particles"),
            contents: bytemuck::cast_slice(&data),
            // Copied into voxelize's scratch, where every voxelized cloud's particles meet.
            usage: BufferUsages::STORAGE | BufferUsages::COPY_DST | BufferUsages::COPY_SRC,
        });
        let max_radius = source
            .particles
            .iter()
            .filter(|p| p.density > 0.0)
            .fold(0.0f32, |m, p| m.max(p.radius));
        let max_density = source
            .particles
            .iter()
            .fold(0.0f32, |m, p| m.max(p.density));
        let bounds = source.bounds().map(|(lo, hi)| CloudBounds {
            centre: (lo + hi) * 0.5,
            side: (hi - lo).max_element(),
            max_radius,
            max_density,
        });
        Ok(Self {
            buffer,
            count,
            bounds,
            generation: GENERATION.fetch_add(1, Ordering::Relaxed),
        })
    }
}

/// Lowers each cloud's extinction so that at its densest particle, in local metres, it stays
/// within [`OPAQUE_EXTINCTION`]; after its particles are uploaded, before any pass reads it.
pub(crate) fn clamp_opaque_extinctions(
    mut clouds: Query<&mut ExtractedCloud>,
    particles: Res<RenderAssets<GpuParticles>>,
) {
    for mut cloud in &mut clouds {
        let Some(bounds) = particles.get(cloud.particles).and_then(|g| g.bounds) else {
            continue;
        };
        let ceiling = opaque_ceiling(bounds.max_density * cloud.scale());
        if cloud.extinction > ceiling {
            cloud.extinction = ceiling;
        }
    }
}

/// The largest extinction a cloud whose densest particle times its scale is `peak` renders at.
fn opaque_ceiling(peak: f32) -> f32 {
    OPAQUE_EXTINCTION / peak.max(f32::MIN_POSITIVE)
}

#[cfg(test)]
mod tests {
    use super::{OPAQUE_EXTINCTION, opaque_ceiling};

    #[test]
    fn the_opaque_ceiling_bounds_extinction_times_density() {
        assert_eq!(opaque_ceiling(1.0), OPAQUE_EXTINCTION);
        assert_eq!(opaque_ceiling(1e20), 1e10);
        // No density: no ceiling worth the name, and never NaN.
        assert_eq!(opaque_ceiling(0.0), f32::INFINITY);
        // The densest f32 particle: extinction times it is the ceiling, not an overflow.
        let product = opaque_ceiling(f32::MAX) * f32::MAX;
        assert!(
            (product / OPAQUE_EXTINCTION - 1.0).abs() < 1e-5,
            "{product}"
        );
    }
}
