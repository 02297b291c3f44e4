//! The view volumes' pass: marches every pending volume (`view_volume.wgsl`), one dispatch per view
//! and volume pool, once the cloud's illumination is ready. What each volume holds, and when it
//! is due, is prepared in `view_volume.rs`.

use bevy::{
    platform::collections::HashMap,
    prelude::*,
    render::{
        render_resource::{BindGroup, BindGroupEntries, PipelineCache},
        renderer::{RenderContext, RenderDevice},
        view::RetainedViewEntity,
    },
};

use crate::render::{
    core::gpu::{WorkList, record_stage},
    core::workgroups,
    plan::CloudIllumination,
    plan::pools::{PoolId, VolumePool, VolumePools},
    plan::volumes::CloudVolumes,
    view::view_atlas::{ViewVolumeAtlas, ViewVolumeAtlases},
    view::view_volume::{CloudViewVolumes, ViewVolume, ViewVolumePipeline},
};
use crate::stats::{CloudPass, CloudPassCounters};

/// The pending volumes of one view whose clouds share a volume pool: marched (or seen) in one
/// dispatch.
#[derive(Default)]
struct MarchBatch {
    /// `(atlas volume, slot)` per volume.
    items: Vec<[u32; 2]>,
    /// Rays per side (the pool's fine grid), or voxels per side (its scattering grid).
    n: u32,
}

/// One dispatch's bind group, work list and columns per side.
type Dispatch = (BindGroup, WorkList, u32);

/// Marches every pending view volume whose cloud's illumination is ready, and evaluates the
/// multiple scattering of anisotropic clouds seen from the camera where the camera or the
/// scattering changed (once per frame, after the illumination, before the cameras draw): one
/// dispatch per view and volume pool each.
#[allow(clippy::too_many_arguments)] // a render system's resources
pub(crate) fn march_view_volumes(
    mut ctx: RenderContext,
    mut clouds: Query<(&CloudIllumination, &CloudVolumes, &mut CloudViewVolumes)>,
    pipeline: Option<Res<ViewVolumePipeline>>,
    pipeline_cache: Res<PipelineCache>,
    mut atlases: ResMut<ViewVolumeAtlases>,
    pools: Res<VolumePools>,
    device: Res<RenderDevice>,
    counters: Res<CloudPassCounters>,
) {
    let Some(pipeline) = pipeline else { return };
    let (Some(march), Some(sum_front), Some(see_multiple)) = (
        pipeline_cache.get_compute_pipeline(pipeline.march),
        pipeline_cache.get_compute_pipeline(pipeline.sum_front),
        pipeline_cache.get_compute_pipeline(pipeline.see_multiple),
    ) else {
        return;
    };
    let DueVolumes {
        marches,
        sights,
        runs,
    } = due_volumes(&mut clouds);
    // A view's front maps are summed again after any of its volumes was marched, or when its
    // volumes or lists changed.
    for (view, _) in marches.keys() {
        if let Some(atlas) = atlases.0.get_mut(view) {
            atlas.fronts_stale = true;
        }
    }
    let fronts = front_batches(&mut atlases, &device, &pipeline_cache, &pipeline);
    if marches.is_empty() && sights.is_empty() && fronts.is_empty() {
        return;
    }
    let layout = pipeline_cache.get_bind_group_layout(&pipeline.layout);
    let marches = dispatches(marches, &atlases, &pools, &device, |atlas, pool, work| {
        device.create_bind_group(
            "particle_clouds_view_volume_bind_group",
            &layout,
            &BindGroupEntries::sequential((
                pool.slots.as_entire_binding(),
                atlas.volumes.as_entire_binding(),
                pool.densities.as_entire_binding(),
                atlas.optical_depth.as_entire_binding(),
                work.binding(),
            )),
        )
    });
    let layout = pipeline_cache.get_bind_group_layout(&pipeline.seen_layout);
    let sights = dispatches(sights, &atlases, &pools, &device, |atlas, pool, work| {
        device.create_bind_group(
            "particle_clouds_view_volume_seen_bind_group",
            &layout,
            &BindGroupEntries::with_indices((
                (0, pool.slots.as_entire_binding()),
                (1, atlas.volumes.as_entire_binding()),
                (4, work.binding()),
                (6, pool.multiple.as_entire_binding()),
                (7, atlas.seen_multiple.as_entire_binding()),
            )),
        )
    });
    let recorder = ctx.diagnostic_recorder();
    record_stage(
        &mut ctx,
        recorder.as_deref(),
        &counters,
        CloudPass::ViewVolume,
        |pass| {
            for (pipeline, dispatches) in [
                (march, &marches),
                (sum_front, &fronts),
                (see_multiple, &sights),
            ] {
                pass.set_pipeline(pipeline);
                for (group, work, n) in dispatches {
                    for (offset, items) in work.chunks() {
                        pass.set_bind_group(0, group, &[offset]);
                        workgroups::dispatch_columns(pass, *n, items);
                    }
                }
            }
            runs
        },
    );
}

/// The view volumes due this frame, batched per view and pool.
struct DueVolumes {
    /// Those to march (their cloud's density or the view changed).
    marches: HashMap<(RetainedViewEntity, PoolId), MarchBatch>,
    /// Those whose multiple scattering must be seen from the camera again.
    sights: HashMap<(RetainedViewEntity, PoolId), MarchBatch>,
    /// The volumes that run, for the pass counters.
    runs: u32,
}

/// Collects the volumes of illuminated clouds that are pending or must be seen again, and marks
/// them done.
fn due_volumes(
    clouds: &mut Query<(&CloudIllumination, &CloudVolumes, &mut CloudViewVolumes)>,
) -> DueVolumes {
    let mut due_now = DueVolumes {
        marches: HashMap::default(),
        sights: HashMap::default(),
        runs: 0,
    };
    for (illumination, volumes, mut all) in clouds {
        let scattered = illumination.scattered;
        let due = |v: &ViewVolume| v.pending || v.must_see(scattered);
        if !illumination.ready || !all.0.values().any(due) {
            continue;
        }
        let slot = volumes.slot.index;
        for (view, volume) in all.0.iter_mut().filter(|(_, v)| due(v)) {
            let at = (*view, volumes.slot.pool);
            if volume.pending {
                let batch = due_now.marches.entry(at).or_default();
                batch.items.push([volume.entry, slot]);
                batch.n = volumes.fine_params.n.max(2);
            }
            if volume.must_see(scattered) {
                let batch = due_now.sights.entry(at).or_default();
                batch.items.push([volume.entry, slot]);
                batch.n = volumes.params.n;
                volume.seen_pending = false;
                volume.seen_from = Some(scattered);
            }
            volume.pending = false;
            volume.ready = true;
            due_now.runs += 1;
        }
    }
    due_now
}

fn dispatches(
    batches: HashMap<(RetainedViewEntity, PoolId), MarchBatch>,
    atlases: &ViewVolumeAtlases,
    pools: &VolumePools,
    device: &RenderDevice,
    group: impl Fn(&ViewVolumeAtlas, &VolumePool, &WorkList) -> BindGroup,
) -> Vec<Dispatch> {
    batches
        .into_iter()
        .filter_map(|((view, pool), batch)| {
            let (atlas, pool) = (atlases.0.get(&view)?, pools.0.get(&pool)?);
            let work = WorkList::new(device, &batch.items);
            Some((group(atlas, pool, &work), work, batch.n))
        })
        .collect()
}

/// One dispatch of `sum_front` per stale view and volume size, over its volumes that have
/// neighbours wholly in front of them; every view's front maps are then current.
fn front_batches(
    atlases: &mut ViewVolumeAtlases,
    device: &RenderDevice,
    pipeline_cache: &PipelineCache,
    pipeline: &ViewVolumePipeline,
) -> Vec<Dispatch> {
    let layout = pipeline_cache.get_bind_group_layout(&pipeline.front_layout);
    let mut batches = Vec::new();
    for atlas in atlases.0.values_mut().filter(|a| a.fronts_stale) {
        atlas.fronts_stale = false;
        let mut by_size: HashMap<u32, Vec<[u32; 2]>> = HashMap::default();
        for &[volume, n] in &atlas.fronts {
            by_size.entry(n).or_default().push([volume, 0]);
        }
        for (n, items) in by_size {
            let work = WorkList::new(device, &items);
            let group = device.create_bind_group(
                "particle_clouds_view_volume_front_bind_group",
                &layout,
                &BindGroupEntries::with_indices((
                    (1, atlas.volumes.as_entire_binding()),
                    (3, atlas.optical_depth.as_entire_binding()),
                    (4, work.binding()),
                    (5, atlas.neighbours.as_entire_binding()),
                )),
            );
            batches.push((group, work, n));
        }
    }
    batches
}
