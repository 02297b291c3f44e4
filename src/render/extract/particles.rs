//! The `Particles` asset on the GPU: uploaded once per change of the asset.

use std::sync::atomic::{AtomicU64, Ordering};

use bevy::{
    ecs::system::{SystemParamItem, lifetimeless::SRes},
    prelude::*,
    render::{
        render_asset::{PrepareAssetError, RenderAsset},
        render_resource::{Buffer, BufferInitDescriptor, BufferUsages},
        renderer::RenderDevice,
    },
};
use bytemuck::{Pod, Zeroable};

use crate::cloud::Particles;

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
