//! The GPU helpers every pass shares: buffers, their encodings, and a recorded stage (a compute
//! pass inside a GPU time span, counted in `CloudPassCounters`). Dispatch sizes are in
//! [`workgroups`](crate::render::core::workgroups).

use bevy::{
    prelude::*,
    render::{
        diagnostic::{DiagnosticsRecorder, RecordDiagnostics},
        render_resource::{
            BindGroup, BindGroupLayoutDescriptor, BindGroupLayoutEntries, BindingType, Buffer,
            BufferBinding, BufferBindingType, BufferDescriptor, BufferInitDescriptor, BufferUsages,
            ComputePass, ComputePassDescriptor, ComputePipeline,
            IntoBindGroupLayoutEntryBuilderArray, IntoIndexedBindGroupLayoutEntryBuilderArray,
            ShaderStages, ShaderType, encase,
        },
        renderer::{RenderContext, RenderDevice},
    },
};

use crate::stats::{CloudPass, CloudPassCounters};

/// A storage buffer of at least 16 bytes (bindings may not be empty) that can be cleared, copied and read back.
pub(crate) fn storage(device: &RenderDevice, label: &'static str, size: u64) -> Buffer {
    device.create_buffer(&BufferDescriptor {
        label: Some(label),
        size: size.max(16),
        usage: BufferUsages::STORAGE | BufferUsages::COPY_DST | BufferUsages::COPY_SRC,
        mapped_at_creation: false,
    })
}

/// A bind group layout whose bindings are numbered in order, all seen by the same stages.
pub(crate) fn sequential_layout<const N: usize>(
    label: &'static str,
    visibility: ShaderStages,
    entries: impl IntoBindGroupLayoutEntryBuilderArray<N>,
) -> BindGroupLayoutDescriptor {
    BindGroupLayoutDescriptor::new(
        label,
        &BindGroupLayoutEntries::sequential(visibility, entries),
    )
}

/// A bind group layout of numbered bindings (a subset of a shader's), all seen by the same stages.
pub(crate) fn indexed_layout<const N: usize>(
    label: &'static str,
    visibility: ShaderStages,
    entries: impl IntoIndexedBindGroupLayoutEntryBuilderArray<N>,
) -> BindGroupLayoutDescriptor {
    BindGroupLayoutDescriptor::new(
        label,
        &BindGroupLayoutEntries::with_indices(visibility, entries),
    )
}

/// Storage buffers a pipeline whose groups are `groups` binds in `stage`: what an adapter's
/// `max_storage_buffers_per_shader_stage` limits.
pub(crate) fn storage_buffers_in(
    groups: &[&BindGroupLayoutDescriptor],
    stage: ShaderStages,
) -> u32 {
    groups
        .iter()
        .flat_map(|group| &group.entries)
        .filter(|entry| {
            entry.visibility.contains(stage)
                && matches!(
                    entry.ty,
                    BindingType::Buffer {
                        ty: BufferBindingType::Storage { .. },
                        ..
                    }
                )
        })
        .count() as u32
}

/// Work items per dispatch of a batched pass: the most z workgroups (65535) rounded down so that
/// each chunk starts on a 256-byte dynamic offset for items of 4 or 8 bytes.
pub const WORK_CHUNK: u32 = 65472;

/// The work list of one batched pass: a slot, a (slot, light) pair or a (view volume, slot) pair
/// per z workgroup, bound a chunk at a time with a dynamic offset.
pub struct WorkList {
    buffer: Buffer,
    /// Items in the list.
    pub items: u32,
    item_bytes: u32,
}

impl WorkList {
    /// A list of `items` (each a `u32`, or a `[u32; 2]`).
    pub fn new<T: bytemuck::Pod>(device: &RenderDevice, items: &[T]) -> Self {
        let item_bytes = size_of::<T>() as u32;
        let count = items.len() as u32;
        let mut bytes: Vec<u8> = bytemuck::cast_slice(items).to_vec();
        // Every chunk's binding is as long as the first; the last is padded to it.
        let last = count.saturating_sub(1) / WORK_CHUNK * WORK_CHUNK;
        bytes.resize(((last + count.min(WORK_CHUNK)) * item_bytes) as usize, 0);
        let buffer = device.create_buffer_with_data(&BufferInitDescriptor {
            label: Some("particle_clouds_work"),
            contents: &bytes,
            usage: BufferUsages::STORAGE,
        });
        Self {
            buffer,
            items: count,
            item_bytes,
        }
    }

    /// The binding of one chunk (the dynamic offset picks which).
    pub fn binding(&self) -> BufferBinding<'_> {
        BufferBinding {
            buffer: &self.buffer,
            offset: 0,
            size: std::num::NonZeroU64::new((self.items.min(WORK_CHUNK) * self.item_bytes) as u64),
        }
    }

    /// Each chunk's dynamic offset and its number of items.
    pub fn chunks(&self) -> impl Iterator<Item = (u32, u32)> + '_ {
        (0..self.items).step_by(WORK_CHUNK as usize).map(|first| {
            (
                first * self.item_bytes,
                (self.items - first).min(WORK_CHUNK),
            )
        })
    }
}

/// A uniform buffer of `size` bytes, written with `RenderQueue::write_buffer`.
pub(crate) fn uniform(device: &RenderDevice, label: &'static str, size: u64) -> Buffer {
    device.create_buffer(&BufferDescriptor {
        label: Some(label),
        size,
        usage: BufferUsages::UNIFORM | BufferUsages::COPY_DST,
        mapped_at_creation: false,
    })
}

/// Encodes a `ShaderType` value as uniform-buffer bytes.
pub fn uniform_bytes<T: ShaderType + encase::internal::WriteInto>(value: &T) -> Vec<u8> {
    let mut buffer = encase::UniformBuffer::new(Vec::new());
    buffer
        .write(value)
        .expect("uniform encoding cannot fail for plain structs");
    buffer.into_inner()
}

/// Byte stride of the entries of a dynamic-offset uniform buffer (the largest dynamic-offset
/// alignment WebGPU allows adapters to require).
pub const DYNAMIC_UNIFORM_STRIDE: u32 = 256;

/// A uniform buffer of `values`, [`DYNAMIC_UNIFORM_STRIDE`] bytes apart: entry `i` is bound at
/// dynamic offset `i * DYNAMIC_UNIFORM_STRIDE`.
pub(crate) fn dynamic_uniform<T: ShaderType + encase::internal::WriteInto>(
    device: &RenderDevice,
    label: &'static str,
    values: impl IntoIterator<Item = T>,
) -> Buffer {
    let mut bytes = Vec::new();
    for (i, value) in values.into_iter().enumerate() {
        bytes.resize(i * DYNAMIC_UNIFORM_STRIDE as usize, 0);
        bytes.extend_from_slice(&uniform_bytes(&value));
    }
    device.create_buffer_with_data(&BufferInitDescriptor {
        label: Some(label),
        contents: &bytes,
        usage: BufferUsages::UNIFORM | BufferUsages::COPY_DST,
    })
}

/// Encodes a slice of `ShaderType` values as a storage-buffer array.
pub fn storage_bytes<T: ShaderType + encase::internal::WriteInto + encase::ShaderSize>(
    values: &[T],
) -> Vec<u8> {
    let mut buffer = encase::StorageBuffer::new(Vec::new());
    buffer
        .write(&values)
        .expect("storage encoding cannot fail for plain structs");
    buffer.into_inner()
}

/// A read-only storage buffer holding `values` (at least one: bindings may not be empty).
pub(crate) fn storage_init<T: ShaderType + encase::internal::WriteInto + encase::ShaderSize>(
    device: &RenderDevice,
    label: &'static str,
    values: &[T],
) -> Buffer {
    device.create_buffer_with_data(&BufferInitDescriptor {
        label: Some(label),
        contents: &storage_bytes(values),
        usage: BufferUsages::STORAGE,
    })
}

/// A stage's compute pass, counting its dispatches.
pub struct StagePass<'p, 'a> {
    pass: &'p mut ComputePass<'a>,
    dispatches: u32,
}

impl<'p, 'a> StagePass<'p, 'a> {
    /// Wraps `pass`, with no dispatch counted yet.
    pub fn new(pass: &'p mut ComputePass<'a>) -> Self {
        Self {
            pass,
            dispatches: 0,
        }
    }

    /// Dispatches recorded so far.
    pub fn dispatches(&self) -> u32 {
        self.dispatches
    }

    /// Sets the pipeline of the next dispatches.
    pub fn set_pipeline(&mut self, pipeline: &ComputePipeline) {
        self.pass.set_pipeline(pipeline);
    }

    /// Sets bind group `index`, with its dynamic offsets.
    pub fn set_bind_group(&mut self, index: u32, group: &BindGroup, offsets: &[u32]) {
        self.pass.set_bind_group(index, group, offsets);
    }

    /// Dispatches `x × y × z` workgroups, and counts it.
    pub fn dispatch(&mut self, x: u32, y: u32, z: u32) {
        self.pass.dispatch_workgroups(x, y, z);
        self.dispatches += 1;
    }

    /// Dispatches the workgroups that the three words of `args` at byte `offset` say (written
    /// by an earlier dispatch), and counts it.
    pub fn dispatch_indirect(&mut self, args: &Buffer, offset: u64) {
        self.pass.dispatch_workgroups_indirect(args, offset);
        self.dispatches += 1;
    }
}

/// Records one stage: a GPU time span around one compute pass, and the pass's counters (the
/// runs `body` returns, and its dispatches).
pub(crate) fn record_stage(
    ctx: &mut RenderContext,
    recorder: Option<&DiagnosticsRecorder>,
    counters: &CloudPassCounters,
    stage: CloudPass,
    body: impl FnOnce(&mut StagePass) -> u32,
) {
    let span = recorder.time_span(ctx.command_encoder(), stage.span_name());
    let mut pass = ctx
        .command_encoder()
        .begin_compute_pass(&ComputePassDescriptor {
            label: Some(stage.span_name()),
            ..default()
        });
    let mut counted = StagePass::new(&mut pass);
    let runs = body(&mut counted);
    let dispatches = counted.dispatches();
    drop(pass);
    span.end(ctx.command_encoder());
    counters.add(stage, runs);
    counters.add_dispatches(stage, dispatches);
}

/// One batched pass over a pool: its bind group and work list.
pub(crate) struct Batch {
    pub(crate) group: BindGroup,
    pub(crate) work: WorkList,
}

impl Batch {
    /// The batch of `items`, with the bind group `bind` makes for their work list; `None`
    /// without items.
    pub(crate) fn new<T: bytemuck::Pod>(
        device: &RenderDevice,
        items: &[T],
        bind: impl FnOnce(&WorkList) -> BindGroup,
    ) -> Option<Self> {
        if items.is_empty() {
            return None;
        }
        let work = WorkList::new(device, items);
        Some(Self {
            group: bind(&work),
            work,
        })
    }
}
