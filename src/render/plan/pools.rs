//! Volume pools: the illumination volumes of every cloud of one shape (voxels per side, light
//! voxels per side, lights) packed into shared buffers, one slot per cloud. Each illumination pass
//! then covers every cloud of a pool in one dispatch, whose z workgroups walk a list of slots
//! (docs/illumination.md §9): the dispatch count grows with the shapes in use, not with the
//! clouds. A slot's region of each buffer starts on a [`SLOT_ALIGNMENT`] boundary, so the
//! per-cloud passes (the draw) bind it on its own, as if it were the cloud's own buffer.

use std::sync::{Arc, Mutex};

use bevy::{
    platform::collections::HashMap,
    prelude::*,
    render::{
        render_resource::{Buffer, BufferBinding, CommandEncoderDescriptor, ShaderType},
        renderer::{RenderDevice, RenderQueue},
    },
};

use crate::render::{
    core::gpu::{dynamic_uniform, storage},
    core::types::{CloudParams, DensityLevels, LightParams},
    plan::ground::ground_map_bytes,
};

// A pool's shape and its slot's layout moved to `volume_shape.rs`; their public paths stay.
use crate::render::plan::volume_shape::{CLOSURE_BYTES, CoarseBytes};
pub use crate::render::plan::volume_shape::{SLOT_ALIGNMENT, Slot, VolumeShape};

/// A part of a buffer, as a binding.
#[derive(Clone, Debug)]
pub struct BufferRange {
    /// The buffer.
    pub buffer: Buffer,
    /// First byte.
    pub offset: u64,
    /// Bytes.
    pub size: u64,
}

impl BufferRange {
    /// The range as a bind group entry's resource.
    pub fn binding(&self) -> BufferBinding<'_> {
        BufferBinding {
            buffer: &self.buffer,
            offset: self.offset,
            size: std::num::NonZeroU64::new(self.size),
        }
    }
}

/// A cloud's place in a pool; dropping it frees the slot.
#[derive(Debug)]
pub struct PoolSlot {
    /// Which pool.
    pub pool: PoolId,
    /// The slot's index in it.
    pub index: u32,
    free: Arc<Mutex<Vec<u32>>>,
}

impl Drop for PoolSlot {
    fn drop(&mut self) {
        if let Ok(mut free) = self.free.lock() {
            free.push(self.index);
        }
    }
}

/// A pool: its shape and its number among the pools of that shape.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct PoolId {
    /// The shape of its clouds' volumes.
    pub shape: VolumeShape,
    /// Pools of one shape are numbered from 0 as each fills up.
    pub number: u32,
}

/// The shared buffers of the clouds of one shape.
pub struct VolumePool {
    shape: VolumeShape,
    /// Slots the buffers hold.
    capacity: u32,
    /// The most slots it may grow to.
    max_slots: u32,
    /// Slots handed out at least once; those below it and not free are in use.
    used: u32,
    free: Arc<Mutex<Vec<u32>>>,
    /// `Slot` per slot.
    pub slots: Buffer,
    /// `LightParams` per slot and light, each slot's on a [`SLOT_ALIGNMENT`] boundary.
    pub lights: Buffer,
    /// f32 fine density levels and scattering-grid density per slot.
    pub densities: Buffer,
    /// f32 optical depth of every light volume per slot: its own and other clouds' shadows
    /// (gather and the billboards read it).
    pub optical_depth: Buffer,
    /// The same, the cloud's own optical depth only (other clouds' casts read it; same layout).
    pub own_depth: Buffer,
    /// vec4 multiple-scattering source `S_0` per slot (its means, then with moments its flux and
    /// its quadrupole).
    pub source: Buffer,
    /// vec4 ping-pong scattering orders per slot (laid out like `source`).
    pub orders: [Buffer; 2],
    /// vec4 multiple scattering `S_m` per slot (its means, then with moments its flux and its
    /// quadrupole).
    pub multiple: Buffer,
    /// The series' closure per slot, 4 vec4 (`closure.wgsl`): two order sizes and the tail's
    /// two coefficients.
    pub order_ratios: Buffer,
    /// vec2 per voxel of the scattering grid: other clouds' media there (extinction, scattering;
    /// [`overlap`](crate::render::plan::overlap)).
    pub foreign: Buffer,
    /// `GroundMap` per slot: the ground under the cloud and its radiance
    /// ([`ground`](crate::render::plan::ground)).
    pub ground: Buffer,
    /// The `DensityLevels` uniform of the shape's fine grid, one entry per `upsample_from`,
    /// `DYNAMIC_UNIFORM_STRIDE` bytes apart (voxelize).
    pub density_levels: Buffer,
    /// Each slot's coarse grid, where the shape has them.
    pub coarse: Option<CoarseGrids>,
}

/// A pool's coarse grids (docs/illumination.md §4, "Coarse-grid cycles"): per slot, a grid of
/// half the side on which the scattering's corrections are solved, its volumes laid out like
/// those of a pool of that side, slot for slot. The sweep and the closure bind these in place of
/// the pool's own buffers.
pub struct CoarseGrids {
    /// The coarse grid's `Slot` per slot (its `cloud.n` half the pool's).
    pub slots: Buffer,
    /// Per slot, f32 density then vec2 other clouds' media: the mean of the 8 fine voxels' each
    /// coarse one holds (the sweep binds it as both).
    pub densities: Buffer,
    /// vec4 residual per slot, averaged from the fine grid by density: the coarse series' start.
    pub source: Buffer,
    /// vec4 ping-pong orders per slot.
    pub orders: [Buffer; 2],
    /// vec4 correction per slot: the coarse series' sum past its start.
    pub multiple: Buffer,
    /// The coarse series' closure per slot (`closure.wgsl`).
    pub order_ratios: Buffer,
}

impl CoarseGrids {
    /// For `capacity` slots of a pool of `shape` (the fine grids').
    fn new(device: &RenderDevice, shape: VolumeShape, capacity: u32) -> Self {
        let CoarseBytes { media, volume, .. } = shape.coarse_bytes();
        let c = capacity as u64;
        Self {
            slots: storage(
                device,
                "particle_clouds_coarse_slots",
                Slot::min_size().get() * c,
            ),
            densities: storage(device, "particle_clouds_coarse_media", media * c),
            source: storage(device, "particle_clouds_coarse_source", volume * c),
            orders: [
                storage(device, "particle_clouds_coarse_order_a", volume * c),
                storage(device, "particle_clouds_coarse_order_b", volume * c),
            ],
            multiple: storage(device, "particle_clouds_coarse_multiple", volume * c),
            order_ratios: storage(device, "particle_clouds_coarse_ratios", CLOSURE_BYTES * c),
        }
    }

    fn buffers(&self) -> [&Buffer; 7] {
        [
            &self.slots,
            &self.densities,
            &self.source,
            &self.orders[0],
            &self.orders[1],
            &self.multiple,
            &self.order_ratios,
        ]
    }
}

impl VolumePool {
    fn new(device: &RenderDevice, shape: VolumeShape, capacity: u32, max_slots: u32) -> Self {
        let b = shape.bytes();
        let c = capacity as u64;
        Self {
            shape,
            capacity,
            max_slots,
            used: 0,
            free: Arc::default(),
            slots: storage(device, "particle_clouds_slots", Slot::min_size().get() * c),
            lights: storage(device, "particle_clouds_pool_lights", b.lights * c),
            densities: storage(device, "particle_clouds_densities", b.densities * c),
            optical_depth: storage(device, "particle_clouds_optical_depth", b.optical_depth * c),
            own_depth: storage(device, "particle_clouds_own_depth", b.optical_depth * c),
            source: storage(device, "particle_clouds_source", b.volume * c),
            orders: [
                storage(device, "particle_clouds_order_a", b.volume * c),
                storage(device, "particle_clouds_order_b", b.volume * c),
            ],
            multiple: storage(device, "particle_clouds_multiple", b.multiple * c),
            order_ratios: storage(device, "particle_clouds_order_ratios", CLOSURE_BYTES * c),
            foreign: storage(device, "particle_clouds_foreign", b.foreign * c),
            ground: storage(device, "particle_clouds_ground", ground_map_bytes() * c),
            density_levels: dynamic_uniform(
                device,
                "particle_clouds_density_levels",
                DensityLevels::entries(shape.m).0,
            ),
            coarse: shape
                .coarse
                .then(|| CoarseGrids::new(device, shape, capacity)),
        }
    }

    fn buffers(&self) -> impl Iterator<Item = &Buffer> {
        let coarse = self.coarse.iter().flat_map(CoarseGrids::buffers);
        [
            &self.slots,
            &self.lights,
            &self.densities,
            &self.optical_depth,
            &self.own_depth,
            &self.source,
            &self.orders[0],
            &self.orders[1],
            &self.multiple,
            &self.order_ratios,
            &self.foreign,
            &self.ground,
        ]
        .into_iter()
        .chain(coarse)
    }

    /// Doubles the capacity (within `max_slots`), copying every slot's contents on the GPU.
    fn grow(&mut self, device: &RenderDevice, queue: &RenderQueue) {
        let capacity = (self.capacity * 2).min(self.max_slots);
        let mut grown = Self::new(device, self.shape, capacity, self.max_slots);
        let mut encoder = device.create_command_encoder(&CommandEncoderDescriptor {
            label: Some("particle_clouds_grow_pool"),
        });
        for (old, new) in self.buffers().zip(grown.buffers()) {
            encoder.copy_buffer_to_buffer(old, 0, new, 0, old.size());
        }
        queue.submit([encoder.finish()]);
        grown.used = self.used;
        grown.free = self.free.clone();
        *self = grown;
    }

    /// A free slot, growing the buffers if needed; `None` when the pool is full.
    fn allocate(
        &mut self,
        device: &RenderDevice,
        queue: &RenderQueue,
        id: PoolId,
    ) -> Option<PoolSlot> {
        let freed = self.free.lock().ok()?.pop();
        let index = match freed {
            Some(index) => index,
            None => {
                if self.used == self.capacity && self.capacity < self.max_slots {
                    self.grow(device, queue);
                }
                if self.used == self.capacity {
                    return None;
                }
                self.used += 1;
                self.used - 1
            }
        };
        Some(PoolSlot {
            pool: id,
            index,
            free: self.free.clone(),
        })
    }

    /// The shape of its clouds' volumes.
    pub fn shape(&self) -> VolumeShape {
        self.shape
    }

    /// No slot is in use.
    fn is_empty(&self) -> bool {
        self.free
            .lock()
            .is_ok_and(|f| f.len() == self.used as usize)
    }

    /// The `Slot` uniform of slot `index` of a cloud with the uniforms `cloud` and `fine`.
    pub fn slot(&self, index: u32, cloud: CloudParams, fine: CloudParams) -> Slot {
        let b = self.shape.bytes();
        let i = index as u64;
        let element = |bytes: u64, size: u64| (bytes / size) as u32;
        Slot {
            cloud,
            fine,
            fine_density: element(i * b.densities, 4),
            density: element(i * b.densities + b.density_at, 4),
            optical_depth: element(i * b.optical_depth, 4),
            volume: element(i * b.volume, 16),
            multiple: element(i * b.multiple, 16),
            foreign: element(i * b.foreign, 8),
            lights: element(i * b.lights, LightParams::min_size().get()),
            ratio: index,
            coarse: 0,
        }
    }

    /// The `Slot` of slot `index`'s coarse grid ([`CoarseGrids`]), for a cloud whose scattering
    /// grid has the uniform `cloud`: half the side, twice the voxel, and the same media,
    /// restricted (`coarse_grid.wgsl`, `restrict_media`).
    pub fn coarse_slot(&self, index: u32, cloud: CloudParams) -> Slot {
        let b = self.shape.coarse_bytes();
        let i = index as u64;
        let element = |bytes: u64, size: u64| (bytes / size) as u32;
        let cloud = CloudParams {
            n: cloud.n / 2,
            h: cloud.h * 2.0,
            ..cloud
        };
        Slot {
            cloud,
            fine: cloud,
            fine_density: 0,
            density: element(i * b.media, 4),
            optical_depth: 0,
            volume: element(i * b.volume, 16),
            multiple: element(i * b.volume, 16),
            foreign: element(i * b.media + b.foreign_at, 8),
            lights: 0,
            ratio: index,
            coarse: 1,
        }
    }

    fn range(buffer: &Buffer, index: u32, stride: u64, offset: u64, size: u64) -> BufferRange {
        BufferRange {
            buffer: buffer.clone(),
            offset: index as u64 * stride + offset,
            size,
        }
    }

    /// Slot `index`'s fine density levels (voxelize writes them, shade and the view volume read them).
    pub fn fine_density(&self, index: u32) -> BufferRange {
        let b = self.shape.bytes();
        Self::range(&self.densities, index, b.densities, 0, b.fine_density)
    }

    /// Slot `index`'s scattering-grid density.
    pub fn density(&self, index: u32) -> BufferRange {
        let b = self.shape.bytes();
        let size = (self.shape.n as u64).pow(3) * 4;
        Self::range(&self.densities, index, b.densities, b.density_at, size)
    }

    /// Slot `index`'s light volumes.
    pub fn optical_depth(&self, index: u32) -> BufferRange {
        let b = self.shape.bytes();
        let size = (self.shape.m as u64).pow(3) * 4 * self.shape.lights.max(1) as u64;
        Self::range(&self.optical_depth, index, b.optical_depth, 0, size)
    }

    /// Slot `index`'s source `S_0`, its moments included.
    pub fn source(&self, index: u32) -> BufferRange {
        let b = self.shape.bytes();
        let size = (self.shape.n as u64).pow(3) * 16 * self.shape.vec4_per_voxel().0;
        Self::range(&self.source, index, b.volume, 0, size)
    }

    /// Slot `index`'s `multiple` (the billboards bind it), its moments included.
    pub fn multiple(&self, index: u32) -> BufferRange {
        let b = self.shape.bytes();
        let size = (self.shape.n as u64).pow(3) * 16 * self.shape.vec4_per_voxel().1;
        Self::range(&self.multiple, index, b.multiple, 0, size)
    }

    /// Slot `index`'s `LightParams` (the billboards bind them).
    pub fn lights(&self, index: u32) -> BufferRange {
        let b = self.shape.bytes();
        let size = LightParams::min_size().get() * self.shape.lights.max(1) as u64;
        Self::range(&self.lights, index, b.lights, 0, size)
    }

    /// Slot `index`'s `GroundMap`.
    pub fn ground(&self, index: u32) -> BufferRange {
        let size = ground_map_bytes();
        Self::range(&self.ground, index, size, 0, size)
    }

    /// Slot `index`'s closure: the tail's coefficients of `S_M` and `S_{M-1}` (2 vec4).
    pub fn order_ratio(&self, index: u32) -> BufferRange {
        Self::range(&self.order_ratios, index, CLOSURE_BYTES, 32, 32)
    }
}

/// Every pool, by id (render world resource).
#[derive(Resource, Default)]
pub struct VolumePools(pub HashMap<PoolId, VolumePool>);

impl VolumePools {
    /// A slot for a cloud of `shape`: in the first pool of that shape with room, else in a new
    /// one. `None` when one cloud alone exceeds the adapter's `max_binding`.
    pub fn allocate(
        &mut self,
        device: &RenderDevice,
        queue: &RenderQueue,
        shape: VolumeShape,
        max_binding: u64,
    ) -> Option<PoolSlot> {
        let max_slots = shape.max_slots(max_binding);
        if max_slots == 0 {
            return None;
        }
        for number in 0.. {
            let id = PoolId { shape, number };
            let pool = self
                .0
                .entry(id)
                .or_insert_with(|| VolumePool::new(device, shape, 1, max_slots));
            if let Some(slot) = pool.allocate(device, queue, id) {
                return Some(slot);
            }
        }
        None
    }

    /// The pool of `slot`.
    pub fn pool(&self, slot: &PoolSlot) -> &VolumePool {
        &self.0[&slot.pool]
    }

    /// Every buffer of every pool (the memory census).
    pub(crate) fn buffers(&self) -> impl Iterator<Item = &Buffer> {
        self.0
            .values()
            .flat_map(|pool| pool.buffers().chain([&pool.density_levels]))
    }

    /// Drops the pools nobody uses.
    pub fn release_empty(&mut self) {
        self.0.retain(|_, pool| !pool.is_empty());
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn slots_start_on_the_alignment_and_hold_their_volumes() {
        let shape = VolumeShape {
            n: 5,
            m: 10,
            lights: 3,
            moments: false,
            coarse: false,
        };
        let b = shape.bytes();
        for bytes in [
            b.densities,
            b.density_at,
            b.optical_depth,
            b.volume,
            b.multiple,
            b.foreign,
            b.lights,
        ] {
            assert_eq!(bytes % SLOT_ALIGNMENT, 0, "{b:?}");
        }
        assert!(b.fine_density >= 1000 * 4 && b.density_at >= b.fine_density);
        assert!(b.densities - b.density_at >= 125 * 4);
        assert!(b.optical_depth >= 3 * 1000 * 4);
        assert!(b.volume >= 125 * 16 && b.multiple == b.volume);
        assert!(b.foreign >= 125 * 8);
        // With moments: the flux after the means, and the quadrupole after it.
        let moments = VolumeShape {
            moments: true,
            coarse: false,
            ..shape
        }
        .bytes();
        assert!(moments.volume >= 125 * 16 * 9 && moments.multiple == moments.volume);
        assert_eq!(
            (moments.foreign, moments.optical_depth),
            (b.foreign, b.optical_depth)
        );
        assert!(b.lights >= 3 * LightParams::min_size().get());
        // The passes index the lights by element, the billboards bind them by byte: the same place.
        assert_eq!(b.lights % LightParams::min_size().get(), 0, "{b:?}");
    }

    #[test]
    fn a_pool_holds_what_fits_in_one_binding() {
        let shape = VolumeShape {
            n: 16,
            m: 32,
            lights: 1,
            moments: false,
            coarse: false,
        };
        // The fine density levels of 32³ and the 16³ density: 37,448 + 4,096 f32.
        let largest = shape.bytes().densities;
        assert_eq!(shape.max_slots(10 * largest + 1), 10);
        assert_eq!(shape.max_slots(largest - 1), 0);
        assert_eq!(shape.max_slots(u64::MAX), 65535);
    }
}
