//! Records the illumination passes (the `RenderGraph` system, once per frame before any camera):
//! voxelize, then per pool shade, cast, gather, the overlap, the ground and the scattering
//! series, then the shadow and sky maps, each batched as [`batches`](super::batches) prepared it.

use bevy::{
    prelude::*,
    render::{
        render_asset::RenderAssets,
        render_resource::{ComputePipeline, PipelineCache},
        renderer::{RenderAdapterInfo, RenderContext},
    },
};

use crate::render::{
    core::gpu::{StagePass, record_stage},
    core::workgroups::{dispatch_columns, dispatch_linear},
    extract::ExtractedCloud,
    extract::particles::GpuParticles,
    illumination::batches::{IlluminationBatches, PoolBatches},
    illumination::pipelines::{IlluminationPipelines, PerOrderSweepPipelines, ReadyPipelines},
    illumination::scatter::scatter_batch_passes,
    illumination::shadow_maps::ShadowMapKeys,
    illumination::sky_map::SkyMapKey,
    illumination::voxelize::{prepare_round, record_round},
    plan::CloudIllumination,
    plan::pools::VolumePools,
    plan::volumes::CloudVolumes,
};
use crate::{
    settings::{ShadingMethod, SweepDispatch, SweepMarch},
    shadow_maps::SKY_MAP_DIRECTIONS,
    stats::{CloudPass, CloudPassCounters},
};

impl IlluminationBatches {
    /// Whether anything shades or casts this frame.
    fn shades(&self) -> bool {
        let casting = |b: &PoolBatches| b.shade.is_some() || !b.cast.is_empty();
        self.pools.iter().any(casting) || !self.maps.batches.is_empty()
    }

    /// Whether anything gathers or marches the sky map this frame.
    fn gathers(&self) -> bool {
        self.pools.iter().any(|b| b.gather.is_some()) || !self.sky.marches.is_empty()
    }

    /// Whether any cloud scatters this frame.
    fn scatters(&self) -> bool {
        self.pools.iter().any(|b| !b.scatter.is_empty())
    }

    /// Shade (§2): one column per invocation, marching slice by slice away from the light (or,
    /// with `ShadingMethod::BruteForce`, one voxel per invocation marching all the way to the
    /// light); every (cloud, light) of a pool in one dispatch. Then, once every cloud's own
    /// optical depth is shaded, other clouds' shadows and the shadow maps (§10), one
    /// invocation per column along the light (`cast.wgsl`): their dispatches count as shade's,
    /// their runs do not. Returns the runs: the lights shaded.
    fn record_shade(
        &self,
        pass: &mut StagePass,
        ready: &ReadyPipelines,
        shade: &ComputePipeline,
        brute_force: bool,
    ) -> u32 {
        pass.set_pipeline(shade);
        let mut runs = 0;
        for b in &self.pools {
            let Some(batch) = &b.shade else { continue };
            for (offset, items) in batch.work.chunks() {
                pass.set_bind_group(0, &batch.group, &[offset]);
                if brute_force {
                    dispatch_linear(pass, b.m.pow(3), items);
                } else {
                    dispatch_columns(pass, b.m, items);
                }
            }
            runs += batch.work.items;
        }
        pass.set_pipeline(ready.cast);
        let pools = self.pools.iter();
        let light_volumes = pools.flat_map(|b| b.cast.iter().map(move |c| (c, b.m.pow(2))));
        let map_texels = self.maps.batches.iter().map(|(c, columns)| (c, *columns));
        for (batch, columns) in light_volumes.chain(map_texels) {
            for (offset, items) in batch.work.chunks() {
                pass.set_bind_group(0, &batch.group, &[offset]);
                dispatch_linear(pass, columns, items);
            }
        }
        runs
    }

    /// Gather (§1, §3): the scattering grid's density, and every light's single scattering into
    /// its source `S_0`; every cloud of a pool in one dispatch. Then the sky map (§10), marched
    /// through the scattering grids' densities: every pool's clouds along each texel's
    /// directions, then each texel's occlusion. Its dispatches count as gather's, not its runs.
    fn record_gather(&self, pass: &mut StagePass, ready: &ReadyPipelines) -> u32 {
        let mut runs = 0;
        for b in &self.pools {
            let Some(batch) = &b.gather else { continue };
            pass.set_pipeline(ready.gather[b.moments as usize]);
            for (offset, items) in batch.work.chunks() {
                pass.set_bind_group(0, &batch.group, &[offset]);
                dispatch_linear(pass, b.n.pow(3), items);
            }
            runs += batch.work.items;
        }
        let sky = &self.sky;
        if let Some(first) = sky.marches.first() {
            pass.set_pipeline(ready.march_sky);
            for group in &sky.marches {
                pass.set_bind_group(0, group, &[]);
                dispatch_linear(pass, sky.texels * SKY_MAP_DIRECTIONS, 1);
            }
            pass.set_pipeline(ready.resolve_sky);
            pass.set_bind_group(0, first, &[]);
            dispatch_linear(pass, sky.texels, 1);
        }
        runs
    }

    /// Multiple scattering (§4): other clouds' media in the grids to scatter in (once every
    /// density is gathered), the ground's radiance under the clouds it lights (once their light
    /// volumes hold every shadow), then each batch's iterations and the series' closure.
    /// Returns the runs: iterations times clouds.
    fn record_scatter(&self, pass: &mut StagePass, ready: &ReadyPipelines) -> u32 {
        pass.set_pipeline(ready.overlap);
        for b in &self.pools {
            for batch in &b.overlap {
                for (offset, items) in batch.work.chunks() {
                    pass.set_bind_group(0, &batch.group, &[offset]);
                    dispatch_linear(pass, b.n.pow(3), items);
                }
            }
        }
        pass.set_pipeline(ready.ground);
        let side = crate::ground::GROUND_MAP_SIDE;
        for batch in self.pools.iter().filter_map(|b| b.ground.as_ref()) {
            for (offset, items) in batch.work.chunks() {
                pass.set_bind_group(0, &batch.group, &[offset]);
                dispatch_linear(pass, side * side, items);
            }
        }
        let mut runs = 0;
        for b in &self.pools {
            for batch in &b.scatter {
                scatter_batch_passes(pass, ready, batch, b.n, b.moments);
                runs += batch.iterations * batch.work.items;
            }
        }
        runs
    }
}

/// What the passes are recorded with: the shading method, the sweep's march and dispatch (and
/// the pipelines of one dispatch per order, once queued), and the adapter they suit.
type IlluminationChoices<'w> = (
    Option<Res<'w, ShadingMethod>>,
    Option<Res<'w, SweepMarch>>,
    Option<Res<'w, SweepDispatch>>,
    Option<Res<'w, PerOrderSweepPipelines>>,
    Res<'w, RenderAdapterInfo>,
);

/// Records every planned illumination stage of every cloud.
#[allow(clippy::too_many_arguments)]
pub(crate) fn illuminate_clouds(
    mut ctx: RenderContext,
    mut clouds: Query<(&ExtractedCloud, &CloudVolumes, &mut CloudIllumination)>,
    batches: Option<Res<IlluminationBatches>>,
    pools: Res<VolumePools>,
    particles: Res<RenderAssets<GpuParticles>>,
    pipelines: Option<Res<IlluminationPipelines>>,
    pipeline_cache: Res<PipelineCache>,
    counters: Res<CloudPassCounters>,
    (shading, march, dispatch, per_order, adapter): IlluminationChoices,
    (mut map_keys, mut sky_key): (ResMut<ShadowMapKeys>, ResMut<SkyMapKey>),
) {
    let Some(pipelines) = pipelines else { return };
    let maps_pending = batches.as_ref().is_some_and(|b| {
        !b.maps.clears.is_empty() || !b.maps.batches.is_empty() || b.sky.is_pending()
    });
    if clouds.iter().all(|(_, _, s)| s.plan.is_empty()) && !maps_pending {
        return;
    }
    let brute_force = shading.is_some_and(|s| *s == ShadingMethod::BruteForce);
    let shade_stage = if brute_force {
        &pipelines.shade_brute_force
    } else {
        &pipelines.shade
    };
    let cpu = adapter.device_type == wgpu::DeviceType::Cpu;
    let read_ahead = march.map_or(SweepMarch::default(), |m| *m).reads_ahead(cpu);
    // One dispatch per order waits for its pipelines as for the others.
    let wants_per_order = dispatch.is_some_and(|d| *d == SweepDispatch::PerOrder);
    let per_order = per_order.as_deref().filter(|_| wants_per_order);
    let ready = (!wants_per_order || per_order.is_some())
        .then(|| pipelines.ready(&pipeline_cache, read_ahead, per_order))
        .flatten();
    let (Some(ready), Some(shade), Some(batches)) =
        (ready, shade_stage.get(&pipeline_cache), batches)
    else {
        // Not compiled yet: forget the plan so that the next frame does all of it.
        clouds.iter_mut().for_each(|(_, _, mut s)| s.invalidate());
        *map_keys = ShadowMapKeys::default();
        *sky_key = SkyMapKey::default();
        return;
    };
    let recorder = ctx.diagnostic_recorder();
    let mut clouds: Vec<_> = clouds
        .iter_mut()
        .filter(|(_, _, s)| !s.plan.is_empty())
        .filter(|(cloud, _, _)| particles.get(cloud.particles).is_some())
        .map(|(_, v, s)| (v, s))
        .collect();

    // Voxelize (docs/illumination.md §1): clear, copy the particles together, bin them into
    // bricks, and gather each brick's density on its level; then the coarse levels are
    // enlarged into the fine grid, coarsest first.
    for round in &batches.voxelize {
        prepare_round(&mut ctx, round);
        record_stage(
            &mut ctx,
            recorder.as_deref(),
            &counters,
            CloudPass::Voxelize,
            |pass| record_round(pass, ready.voxelize, round),
        );
    }

    // Shade (§2), then the casts of other clouds' shadows and the shadow maps.
    let (maps, sky) = (&batches.maps, &batches.sky);
    if let Some(buffer) = &maps.buffer {
        for &(offset, size) in maps.clears.iter().chain(&sky.clear) {
            ctx.command_encoder()
                .clear_buffer(buffer, offset, Some(size));
        }
    }
    if batches.shades() {
        record_stage(
            &mut ctx,
            recorder.as_deref(),
            &counters,
            CloudPass::Shade,
            |pass| batches.record_shade(pass, &ready, shade, brute_force),
        );
    }
    // Gather (§1, §3), then the sky map.
    if batches.gathers() {
        record_stage(
            &mut ctx,
            recorder.as_deref(),
            &counters,
            CloudPass::Gather,
            |pass| batches.record_gather(pass, &ready),
        );
    }
    // Multiple scattering (§4): a warm restart starts from what `multiple` holds; the full
    // series from zero.
    for (v, s) in &clouds {
        if (s.plan.scatter.is_some() && !s.plan.warm) || s.plan.unlit {
            let multiple = pools.pool(&v.slot).multiple(v.slot.index);
            ctx.command_encoder().clear_buffer(
                &multiple.buffer,
                multiple.offset,
                Some(multiple.size),
            );
        }
    }
    if batches.scatters() {
        record_stage(
            &mut ctx,
            recorder.as_deref(),
            &counters,
            CloudPass::Scatter,
            |pass| batches.record_scatter(pass, &ready),
        );
    }

    for (_, s) in &mut clouds {
        let scattered = s.plan.scatter.is_some() || s.plan.unlit;
        s.ready |= scattered;
        s.scattered = s.scattered.wrapping_add(scattered as u32);
        s.plan = default();
    }
}
