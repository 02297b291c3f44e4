//! The per-view back-to-front sort of each cloud's particles on the GPU (the paper's named future
//! work): a 32-bit LSD radix sort of view-depth keys (`sort.wgsl`). It runs only when the
//! view, the cloud's transform or its particles changed.

use bevy::{
    platform::collections::HashMap,
    prelude::*,
    render::{
        render_asset::RenderAssets,
        render_resource::{
            BindGroup, BindGroupEntries, BindGroupLayout, BindGroupLayoutDescriptor, Buffer,
            BufferDescriptor, BufferUsages, CachedComputePipelineId, ComputePipeline,
            ComputePipelineDescriptor, PipelineCache, ShaderStages, ShaderType,
            binding_types::{
                storage_buffer_read_only_sized, storage_buffer_sized, uniform_buffer_sized,
            },
        },
        renderer::{RenderContext, RenderDevice, RenderQueue},
        view::{ExtractedView, RenderVisibleEntities, RetainedViewEntity},
    },
};

use crate::render::{
    core::gpu::{StagePass, record_stage, sequential_layout, storage, uniform_bytes},
    core::key_of,
    core::shaders::CloudShaders,
    core::workgroups::{self, SORT_TILE, dispatch_linear},
    extract::ExtractedCloud,
    extract::particles::GpuParticles,
    view::views_by_cloud,
};
use crate::{
    settings::Compositing,
    stats::{CloudPass, CloudPassCounters},
};

/// Mirror of `SortParams` in `sort.wgsl`.
#[derive(ShaderType, Clone, Copy, Debug, Default)]
pub struct SortParams {
    /// Row of view-from-local giving view-space z.
    pub depth_row: Vec4,
    /// Elements to sort.
    pub count: u32,
    /// Tiles of `SORT_TILE` elements.
    pub tiles: u32,
    /// Bit offset of this pass's 8-bit digit.
    pub shift: u32,
    /// Uniform-buffer padding.
    pub _padding: u32,
}

/// The sort's compute pipelines.
#[derive(Resource)]
pub struct SortPipelines {
    /// The layout shared by every sort pipeline.
    pub layout: BindGroupLayoutDescriptor,
    /// View-depth keys and identity values.
    pub depth_keys: CachedComputePipelineId,
    /// Per-tile digit histograms.
    pub count_digits: CachedComputePipelineId,
    /// Global exclusive scan of the histograms.
    pub scan_digits: CachedComputePipelineId,
    /// Stable scatter by digit.
    pub scatter_digits: CachedComputePipelineId,
}

/// The compiled sort pipelines, in dispatch order.
pub struct ReadySortPipelines<'a> {
    /// See [`SortPipelines::depth_keys`].
    pub depth_keys: &'a ComputePipeline,
    /// See [`SortPipelines::count_digits`].
    pub count_digits: &'a ComputePipeline,
    /// See [`SortPipelines::scan_digits`].
    pub scan_digits: &'a ComputePipeline,
    /// See [`SortPipelines::scatter_digits`].
    pub scatter_digits: &'a ComputePipeline,
}

impl SortPipelines {
    /// The compiled pipelines, once all are ready.
    pub fn ready<'a>(&self, cache: &'a PipelineCache) -> Option<ReadySortPipelines<'a>> {
        Some(ReadySortPipelines {
            depth_keys: cache.get_compute_pipeline(self.depth_keys)?,
            count_digits: cache.get_compute_pipeline(self.count_digits)?,
            scan_digits: cache.get_compute_pipeline(self.scan_digits)?,
            scatter_digits: cache.get_compute_pipeline(self.scatter_digits)?,
        })
    }
}

/// The sort passes' one layout: the digit pass's uniform, the particles, the keys and values in
/// and out, the histogram.
pub(crate) fn sort_layout() -> BindGroupLayoutDescriptor {
    let write = || storage_buffer_sized(false, None);
    sequential_layout(
        "particle_clouds_sort_layout",
        ShaderStages::COMPUTE,
        (
            uniform_buffer_sized(false, None),
            storage_buffer_read_only_sized(false, None),
            write(),
            write(),
            write(),
            write(),
            write(),
        ),
    )
}

pub(crate) fn init_sort_pipelines(
    mut commands: Commands,
    shaders: Res<CloudShaders>,
    cache: Res<PipelineCache>,
) {
    let layout = sort_layout();
    let queue = |entry_point: &'static str| {
        cache.queue_compute_pipeline(ComputePipelineDescriptor {
            label: Some(format!("particle_clouds_sort_{entry_point}").into()),
            layout: vec![layout.clone()],
            shader: shaders.sort.clone(),
            shader_defs: workgroups::shader_defs(),
            entry_point: Some(entry_point.into()),
            ..default()
        })
    };
    commands.insert_resource(SortPipelines {
        depth_keys: queue("depth_keys"),
        count_digits: queue("count_digits"),
        scan_digits: queue("scan_digits"),
        scatter_digits: queue("scatter_digits"),
        layout,
    });
}

/// The buffers of one sort of up to `capacity` elements. After [`record_sort`] the sorted
/// values (particle indices, back to front) are in [`SortBuffers::sorted_values`].
pub struct SortBuffers {
    /// Elements the buffers hold.
    pub capacity: u32,
    keys: [Buffer; 2],
    values: [Buffer; 2],
    histogram: Buffer,
    /// One uniform per 8-bit digit pass (shift 0, 8, 16, 24).
    params: [Buffer; 4],
}

impl SortBuffers {
    /// Every buffer (the memory census).
    pub(crate) fn buffers(&self) -> impl Iterator<Item = &Buffer> {
        self.keys
            .iter()
            .chain(&self.values)
            .chain([&self.histogram])
            .chain(&self.params)
    }

    /// Buffers for up to `capacity` elements.
    pub fn new(device: &RenderDevice, capacity: u32) -> Self {
        let bytes = capacity as u64 * 4;
        let tiles = capacity.div_ceil(SORT_TILE) as u64;
        let params = std::array::from_fn(|_| {
            device.create_buffer(&BufferDescriptor {
                label: Some("particle_clouds_sort_params"),
                size: SortParams::min_size().get(),
                usage: BufferUsages::UNIFORM | BufferUsages::COPY_DST,
                mapped_at_creation: false,
            })
        });
        Self {
            capacity,
            keys: [
                storage(device, "particle_clouds_sort_keys_a", bytes),
                storage(device, "particle_clouds_sort_keys_b", bytes),
            ],
            values: [
                storage(device, "particle_clouds_sort_values_a", bytes),
                storage(device, "particle_clouds_sort_values_b", bytes),
            ],
            histogram: storage(device, "particle_clouds_sort_histogram", tiles * 256 * 4),
            params,
        }
    }

    /// Sets the element count and the depth row used by `depth_keys`.
    pub fn write_params(&self, queue: &RenderQueue, count: u32, depth_row: Vec4) {
        for (pass, buffer) in self.params.iter().enumerate() {
            let params = SortParams {
                depth_row,
                count,
                tiles: count.div_ceil(SORT_TILE),
                shift: 8 * pass as u32,
                _padding: 0,
            };
            queue.write_buffer(buffer, 0, &uniform_bytes(&params));
        }
    }

    /// Keys to sort (read by the digit passes); tests write their own here.
    pub fn keys(&self) -> &Buffer {
        &self.keys[0]
    }

    /// Values travelling with the keys; `depth_keys` fills them with `0..count`.
    pub fn values(&self) -> &Buffer {
        &self.values[0]
    }

    /// The sorted values after the four passes (back in the first buffer).
    pub fn sorted_values(&self) -> &Buffer {
        &self.values[0]
    }

    /// The sorted keys after the four passes.
    pub fn sorted_keys(&self) -> &Buffer {
        &self.keys[0]
    }

    /// Bind groups of the four digit passes; pass `k` reads buffer set `k % 2` and writes the other.
    pub fn bind_groups(
        &self,
        device: &RenderDevice,
        layout: &BindGroupLayout,
        particles: &Buffer,
    ) -> [BindGroup; 4] {
        std::array::from_fn(|pass| {
            let (src, dst) = (pass % 2, 1 - pass % 2);
            device.create_bind_group(
                "particle_clouds_sort_bind_group",
                layout,
                &BindGroupEntries::sequential((
                    self.params[pass].as_entire_binding(),
                    particles.as_entire_binding(),
                    self.keys[src].as_entire_binding(),
                    self.values[src].as_entire_binding(),
                    self.keys[dst].as_entire_binding(),
                    self.values[dst].as_entire_binding(),
                    self.histogram.as_entire_binding(),
                )),
            )
        })
    }
}

/// Records a sort of `count` elements: optionally the depth keys, then four radix passes.
pub fn record_sort(
    pass: &mut StagePass,
    pipelines: &ReadySortPipelines,
    groups: &[BindGroup; 4],
    count: u32,
    depth_keys: bool,
) {
    if depth_keys {
        pass.set_pipeline(pipelines.depth_keys);
        pass.set_bind_group(0, &groups[0], &[]);
        dispatch_linear(pass, count, 1);
    }
    let tiles = count.div_ceil(SORT_TILE);
    for group in groups {
        pass.set_bind_group(0, group, &[]);
        pass.set_pipeline(pipelines.count_digits);
        dispatch_linear(pass, tiles, 1);
        pass.set_pipeline(pipelines.scan_digits);
        pass.dispatch(1, 1, 1);
        pass.set_pipeline(pipelines.scatter_digits);
        dispatch_linear(pass, tiles, 1);
    }
}

/// One view's sorted order of one cloud's particles.
pub struct ViewSort {
    /// The sort's buffers; the order is in [`SortBuffers::sorted_values`].
    pub buffers: SortBuffers,
    /// Key of (view transform, cloud transform, particles) the order was computed for.
    key: u64,
    /// The order must be recomputed this frame.
    pub pending: bool,
    /// The order is valid and may be drawn.
    pub ready: bool,
    /// The sort's bind groups, made in `PrepareBindGroups` while the sort is pending.
    groups: Option<[BindGroup; 4]>,
}

/// Every view's sort of one cloud (render world component on the cloud).
#[derive(Component, Default)]
pub struct CloudSorts(pub HashMap<RetainedViewEntity, ViewSort>);

/// Decides, per view and visible cloud, whether the particles need a new sort.
pub(crate) fn prepare_cloud_sorts(
    mut commands: Commands,
    views: Query<(&ExtractedView, &RenderVisibleEntities)>,
    mut clouds: Query<(&ExtractedCloud, Option<&mut CloudSorts>)>,
    particles: Res<RenderAssets<GpuParticles>>,
    device: Res<RenderDevice>,
    queue: Res<RenderQueue>,
) {
    for (entity, views) in views_by_cloud(views.iter()) {
        let Ok((cloud, sorts)) = clouds.get_mut(entity) else {
            continue;
        };
        let Some(gpu) = particles.get(cloud.particles) else {
            continue;
        };
        if cloud.settings.compositing != Compositing::Sorted {
            continue;
        }
        let mut fresh = CloudSorts::default();
        let is_fresh = sorts.is_none();
        let sorts = match sorts {
            Some(s) => s.into_inner(),
            None => &mut fresh,
        };
        let retained: Vec<_> = views.iter().map(|v| v.retained_view_entity).collect();
        sorts.0.retain(|k, _| retained.contains(k));
        for view in views {
            let view_from_local =
                view.world_from_view.to_matrix().inverse() * Mat4::from(cloud.world_from_local);
            let depth_row = view_from_local.row(2);
            let key = key_of((depth_row.to_array().map(f32::to_bits), gpu.generation));
            let sort = sorts
                .0
                .entry(view.retained_view_entity)
                .or_insert_with(|| ViewSort {
                    buffers: SortBuffers::new(&device, gpu.count),
                    key: 0,
                    pending: false,
                    ready: false,
                    groups: None,
                });
            if sort.buffers.capacity != gpu.count {
                sort.buffers = SortBuffers::new(&device, gpu.count);
                sort.key = 0;
                sort.ready = false;
            }
            if key != sort.key {
                sort.key = key;
                sort.pending = true;
                sort.buffers.write_params(&queue, gpu.count, depth_row);
            }
        }
        if is_fresh {
            commands.entity(entity).insert(fresh);
        }
    }
}

/// Makes the bind groups of every pending sort.
pub(crate) fn prepare_sort_bind_groups(
    mut clouds: Query<(&ExtractedCloud, &mut CloudSorts)>,
    particles: Res<RenderAssets<GpuParticles>>,
    pipelines: Option<Res<SortPipelines>>,
    pipeline_cache: Res<PipelineCache>,
    device: Res<RenderDevice>,
) {
    let Some(pipelines) = pipelines else { return };
    let layout = pipeline_cache.get_bind_group_layout(&pipelines.layout);
    for (cloud, mut sorts) in &mut clouds {
        let Some(gpu) = particles.get(cloud.particles) else {
            continue;
        };
        for sort in sorts.0.values_mut().filter(|s| s.pending) {
            sort.groups = Some(sort.buffers.bind_groups(&device, &layout, &gpu.buffer));
        }
    }
}

/// Records every pending sort (once per frame, before the cameras draw).
pub(crate) fn sort_cloud_particles(
    mut ctx: RenderContext,
    mut clouds: Query<(&ExtractedCloud, &mut CloudSorts)>,
    particles: Res<RenderAssets<GpuParticles>>,
    pipelines: Option<Res<SortPipelines>>,
    pipeline_cache: Res<PipelineCache>,
    counters: Res<CloudPassCounters>,
) {
    let Some(pipelines) = pipelines else { return };
    if !clouds.iter().any(|(_, s)| s.0.values().any(|v| v.pending)) {
        return;
    }
    let Some(ready) = pipelines.ready(&pipeline_cache) else {
        return;
    };
    let recorder = ctx.diagnostic_recorder();
    record_stage(
        &mut ctx,
        recorder.as_deref(),
        &counters,
        CloudPass::Sort,
        |pass| {
            let mut runs = 0;
            for (cloud, mut sorts) in &mut clouds {
                let Some(gpu) = particles.get(cloud.particles) else {
                    continue;
                };
                for sort in sorts.0.values_mut().filter(|s| s.pending) {
                    let Some(groups) = sort.groups.take() else {
                        continue;
                    };
                    record_sort(pass, &ready, &groups, gpu.count, true);
                    sort.pending = false;
                    sort.ready = true;
                    runs += 1;
                }
            }
            runs
        },
    );
}
