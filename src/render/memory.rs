//! The GPU memory the crate holds: each frame a census sums the buffers and textures of its
//! render-world resources and components (each buffer once, however many hold it) and publishes
//! it through [`CloudPassCounters`], so that the main world (a test, a game's debug overlay)
//! can watch it return to its baseline once the clouds are gone. Per-frame transients (work
//! lists, bind groups) are left out.

use bevy::{
    platform::collections::HashSet,
    prelude::*,
    render::{
        render_asset::RenderAssets,
        render_resource::{Buffer, BufferId},
    },
};

use crate::render::{
    draw::CloudDrawBindGroups, draw::cloud_target::ViewCloudTargetResources,
    draw::splat_batch::ViewSplatBatches, extract::ExtractedCloud, extract::particles::GpuParticles,
    illumination::batches::SweepPairVolumes, illumination::voxelize::VoxelizeScratch,
    plan::pools::VolumePools, plan::volumes::CloudVolumes, view::sort::CloudSorts,
    view::view_atlas::ViewVolumeAtlases, view::view_volume::CloudViewVolumes,
};
use crate::stats::{CloudGpuMemory, CloudPassCounters};

/// Bytes of distinct buffers, by id.
#[derive(Default)]
struct Census {
    seen: HashSet<BufferId>,
}

impl Census {
    /// The bytes of those of `buffers` not counted before.
    fn count<'a>(&mut self, buffers: impl IntoIterator<Item = &'a Buffer>) -> u64 {
        buffers
            .into_iter()
            .filter(|b| self.seen.insert(b.id()))
            .map(|b| b.size())
            .sum()
    }
}

/// What a cloud holds in the render world.
type CloudHoldings = (
    Option<&'static CloudVolumes>,
    Option<&'static CloudSorts>,
    Option<&'static CloudViewVolumes>,
    Option<&'static CloudDrawBindGroups>,
);

/// What a view holds in the render world.
type ViewHoldings = (
    Option<&'static ViewCloudTargetResources>,
    Option<&'static ViewSplatBatches>,
);

/// Counts what the crate holds and publishes it ([`CloudPassCounters::gpu_memory`]).
#[allow(clippy::too_many_arguments)] // one parameter per holder
pub(crate) fn census_gpu_memory(
    pools: Res<VolumePools>,
    scratch: Res<VoxelizeScratch>,
    pairs: Res<SweepPairVolumes>,
    atlases: Res<ViewVolumeAtlases>,
    particles: Res<RenderAssets<GpuParticles>>,
    clouds: Query<CloudHoldings>,
    views: Query<ViewHoldings>,
    counters: Res<CloudPassCounters>,
) {
    let mut census = Census::default();
    let volume_pools = census.count(pools.buffers().chain(pairs.buffers()));
    let voxelize_scratch = census.count(scratch.buffers());
    let particles = census.count(particles.iter().map(|(_, p)| &p.buffer));
    let mut per_cloud = 0;
    for (volumes, sorts, view_volumes, draw) in &clouds {
        per_cloud += census.count(volumes.map(|v| &v.params_buffer));
        per_cloud += census.count(
            sorts
                .iter()
                .flat_map(|s| s.0.values())
                .flat_map(|s| s.buffers.buffers()),
        );
        per_cloud += census.count(
            view_volumes
                .iter()
                .flat_map(|v| v.0.values())
                .map(|v| &v.params),
        );
        per_cloud += census.count(draw.into_iter().flat_map(CloudDrawBindGroups::buffers));
    }
    let mut per_view = census.count(atlases.buffers());
    for (target, batches) in &views {
        if let Some(target) = target {
            let texture = &target.texture.texture;
            let texel = texture.format().block_copy_size(None).unwrap_or(0) as u64;
            let size = texture.size();
            per_view += texel * size.width as u64 * size.height as u64;
            per_view += census.count(target.splat.iter().flat_map(|s| s.buffers()));
        }
        per_view += census.count(
            batches
                .iter()
                .flat_map(|b| b.0.values())
                .flat_map(|b| b.buffers()),
        );
    }
    counters.set_gpu_memory(CloudGpuMemory {
        volume_pools,
        voxelize_scratch,
        particles,
        per_cloud,
        per_view,
    });
}

/// Frees the voxelization's scratch once no cloud is left: it is kept between frames for
/// clouds whose particles change every frame, and would otherwise stay at its last size.
pub(crate) fn release_idle_scratch(
    clouds: Query<(), With<ExtractedCloud>>,
    mut scratch: ResMut<VoxelizeScratch>,
) {
    if clouds.is_empty() {
        scratch.release();
    }
}
