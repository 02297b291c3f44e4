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

use crate::settings::CloudQualitySettings;

use crate::render::{
    core::gpu::{dynamic_uniform, storage},
    core::types::{CloudParams, DensityLevels, LightParams},
    plan::ground::ground_map_bytes,
};

/// The byte boundary every slot's region starts on: WebGPU's largest
/// `min_storage_buffer_offset_alignment`.
pub const SLOT_ALIGNMENT: u64 = 256;

/// Bytes of a slot's series closure (`closure.wgsl`): 4 vec4.
const CLOSURE_BYTES: u64 = 64;

/// Clouds whose volumes can share a pool.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct VolumeShape {
    /// Voxels per side `N` of the scattering grid.
    pub n: u32,
    /// Voxels per side `m` of the fine grid and of each light volume.
    pub m: u32,
    /// Lights, each with a light volume.
    pub lights: u32,
    /// The scattering volumes hold angular moments beside their means (an anisotropic medium):
    /// the source and the orders their flux (3 vec4 per voxel), `multiple` its flux and
    /// quadrupole (8 vec4 per voxel).
    pub moments: bool,
    /// Each slot has a coarse grid of half the side for the scattering's coarse-grid cycles
    /// (docs/illumination.md §4): [`CoarseGrids`].
    pub coarse: bool,
}

/// Mirror of `Slot` in `types.wgsl`: one cloud's uniforms and the first element of each of its
/// volumes in its pool's buffers.
#[derive(ShaderType, Clone, Copy, Debug, Default, PartialEq)]
pub struct Slot {
    /// The scattering grid's uniform.
    pub cloud: CloudParams,
    /// The fine grid's uniform (shade).
    pub fine: CloudParams,
    /// First f32 of the fine density (its finest level) in `densities`.
    pub fine_density: u32,
    /// First f32 of the scattering grid's density in `densities`.
    pub density: u32,
    /// First f32 of the light volumes in `optical_depth`.
    pub optical_depth: u32,
    /// First vec4 of the volume in `source` and `orders`.
    pub volume: u32,
    /// First vec4 of the volume in `multiple`.
    pub multiple: u32,
    /// First vec2 of the other clouds' media in `foreign`.
    pub foreign: u32,
    /// First of the cloud's lights in the pool's light array.
    pub lights: u32,
    /// Its element of the closure's `order_ratios`.
    pub ratio: u32,
    /// 1 for a coarse grid's slot ([`CoarseGrids`]): its series sums a signed correction, which
    /// the closure does not clamp at 0; else 0.
    pub coarse: u32,
}

/// Bytes of one slot in each kind of pool buffer.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
struct SlotBytes {
    /// The fine density with its levels, then (aligned) the scattering grid's density.
    densities: u64,
    /// Where in a slot of `densities` the scattering grid's density starts.
    density_at: u64,
    /// The fine density levels' bytes (what voxelize and the view volume bind).
    fine_density: u64,
    /// Every light's `m³` optical depth.
    optical_depth: u64,
    /// One `n³` vec4 volume (`source`, each order), with its flux and quadrupole if the shape has
    /// moments.
    volume: u64,
    /// The `n³` vec4 `multiple`, with its flux and quadrupole if the shape has moments.
    multiple: u64,
    /// The `n³` vec2 other clouds' media.
    foreign: u64,
    /// Every light's `LightParams` (at least one: a binding of a runtime-sized array may not be
    /// shorter).
    lights: u64,
}

fn aligned(bytes: u64) -> u64 {
    aligned_to(bytes, SLOT_ALIGNMENT)
}

/// `bytes` (at least 1) rounded up to a multiple of `unit`.
fn aligned_to(bytes: u64, unit: u64) -> u64 {
    bytes.max(1).div_ceil(unit) * unit
}

/// The stride of the slots' `LightParams`: on [`SLOT_ALIGNMENT`] boundaries, and a whole number
/// of `LightParams`, so that the element the passes index and the range the billboards bind
/// start at the same byte.
fn light_stride(lights: u32) -> u64 {
    let size = LightParams::min_size().get();
    let gcd = |mut a: u64, mut b: u64| {
        while b != 0 {
            (a, b) = (b, a % b);
        }
        a
    };
    let unit = SLOT_ALIGNMENT / gcd(SLOT_ALIGNMENT, size) * size;
    aligned_to(size * lights.max(1) as u64, unit)
}

impl VolumeShape {
    /// The shape of a cloud's volumes at `settings`, under `lights` lights, with angular
    /// `moments` (an anisotropic medium).
    pub fn new(settings: &CloudQualitySettings, lights: u32, moments: bool) -> Self {
        Self {
            n: settings.volume_resolution,
            m: settings.light_resolution(),
            lights,
            moments,
            coarse: settings.has_coarse_grid(),
        }
    }

    /// Bytes of one slot's coarse grid ([`CoarseGrids`]) in its media buffer (its density,
    /// then other clouds' media from the second value on) and in each of its volume buffers
    /// (half the side).
    fn coarse_bytes(&self) -> CoarseBytes {
        let voxels = (self.n as u64 / 2).pow(3);
        let foreign_at = aligned(voxels * 4);
        CoarseBytes {
            media: foreign_at + aligned(voxels * 8),
            foreign_at,
            volume: aligned(voxels * 16 * self.vec4_per_voxel().0),
        }
    }

    /// This shape with a fine grid of `m` voxels per side.
    pub fn with_light_resolution(self, m: u32) -> Self {
        Self { m, ..self }
    }

    /// The largest fine grid, from `settings`' own ([`CloudQualitySettings::light_resolution`])
    /// down to `volume_resolution`, at which one such cloud's volumes fit a storage binding of
    /// `max_binding` bytes; `None` when none does. Any side will do: the gather averages the fine
    /// voxels by their overlap with each scattering voxel (docs/illumination.md §1), so a
    /// binding trims the grid by a few voxels rather than dividing it.
    pub fn fitting_light_resolution(
        settings: &CloudQualitySettings,
        lights: u32,
        moments: bool,
        max_binding: u64,
    ) -> Option<u32> {
        let shape = Self::new(settings, lights, moments);
        let fits = |m: u32| shape.with_light_resolution(m).max_slots(max_binding) > 0;
        let (mut fitting, wanted) = (settings.volume_resolution, settings.light_resolution());
        if fits(wanted) {
            return Some(wanted);
        }
        if !fits(fitting) {
            return None;
        }
        // The slots' bytes grow with m: bisect between a side that fits and one that does not.
        let mut too_large = wanted;
        while too_large - fitting > 1 {
            let m = (fitting + too_large) / 2;
            *if fits(m) {
                &mut fitting
            } else {
                &mut too_large
            } = m;
        }
        Some(fitting)
    }

    fn bytes(&self) -> SlotBytes {
        let voxels = (self.n as u64).pow(3);
        let fine_density = DensityLevels::elements(self.m) * 4;
        let density_at = aligned(fine_density);
        let (volume, multiple) = self.vec4_per_voxel();
        SlotBytes {
            densities: density_at + aligned(voxels * 4),
            density_at,
            fine_density,
            optical_depth: aligned((self.m as u64).pow(3) * 4 * self.lights.max(1) as u64),
            volume: aligned(voxels * 16 * volume),
            multiple: aligned(voxels * 16 * multiple),
            foreign: aligned(voxels * 8),
            lights: light_stride(self.lights),
        }
    }

    /// The vec4 per voxel of a scattering volume (`source`, an order) and of `multiple`: the
    /// mean, and with moments the flux (3) and the quadrupole (5).
    fn vec4_per_voxel(&self) -> (u64, u64) {
        if self.moments { (9, 9) } else { (1, 1) }
    }

    /// The most slots a pool of this shape may hold under the adapter's `max_binding` (bytes of
    /// one storage binding), at most 65535 (the dispatches' z workgroups).
    pub fn max_slots(&self, max_binding: u64) -> u32 {
        let b = self.bytes();
        let largest = b.densities.max(b.optical_depth).max(b.multiple);
        (max_binding / largest).min(65535) as u32
    }
}

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

/// Bytes of one slot's coarse grid ([`VolumeShape::coarse_bytes`]).
struct CoarseBytes {
    /// In the media buffer: the density, then other clouds' media.
    media: u64,
    /// Where other clouds' media start within it.
    foreign_at: u64,
    /// In each volume buffer.
    volume: u64,
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
