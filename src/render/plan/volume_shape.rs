//! The shape of a volume pool (the clouds whose volumes can share one) and the layout of one
//! slot in it: each volume's bytes, aligned so that a slot binds on its own
//! ([`pools`](super::pools)).

use bevy::render::render_resource::ShaderType;

use crate::settings::CloudQualitySettings;

use crate::render::core::types::{CloudParams, DensityLevels, LightParams};

/// The byte boundary every slot's region starts on: WebGPU's largest
/// `min_storage_buffer_offset_alignment`.
pub const SLOT_ALIGNMENT: u64 = 256;

/// Bytes of a slot's series closure (`closure.wgsl`): 4 vec4.
pub(crate) const CLOSURE_BYTES: u64 = 64;

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
    /// (docs/illumination.md §4): [`CoarseGrids`](super::pools::CoarseGrids).
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
    /// 1 for a coarse grid's slot ([`CoarseGrids`](super::pools::CoarseGrids)): its series sums a signed correction, which
    /// the closure does not clamp at 0; else 0.
    pub coarse: u32,
}

/// Bytes of one slot in each kind of pool buffer.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct SlotBytes {
    /// The fine density with its levels, then (aligned) the scattering grid's density.
    pub(crate) densities: u64,
    /// Where in a slot of `densities` the scattering grid's density starts.
    pub(crate) density_at: u64,
    /// The fine density levels' bytes (what voxelize and the view volume bind).
    pub(crate) fine_density: u64,
    /// Every light's `m³` optical depth.
    pub(crate) optical_depth: u64,
    /// One `n³` vec4 volume (`source`, each order), with its flux and quadrupole if the shape has
    /// moments.
    pub(crate) volume: u64,
    /// The `n³` vec4 `multiple`, with its flux and quadrupole if the shape has moments.
    pub(crate) multiple: u64,
    /// The `n³` vec2 other clouds' media.
    pub(crate) foreign: u64,
    /// Every light's `LightParams` (at least one: a binding of a runtime-sized array may not be
    /// shorter).
    pub(crate) lights: u64,
}

pub(crate) fn aligned(bytes: u64) -> u64 {
    aligned_to(bytes, SLOT_ALIGNMENT)
}

/// `bytes` (at least 1) rounded up to a multiple of `unit`.
pub(crate) fn aligned_to(bytes: u64, unit: u64) -> u64 {
    bytes.max(1).div_ceil(unit) * unit
}

/// The stride of the slots' `LightParams`: on [`SLOT_ALIGNMENT`] boundaries, and a whole number
/// of `LightParams`, so that the element the passes index and the range the billboards bind
/// start at the same byte.
pub(crate) fn light_stride(lights: u32) -> u64 {
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

    /// Bytes of one slot's coarse grid ([`CoarseGrids`](super::pools::CoarseGrids)) in its media buffer (its density,
    /// then other clouds' media from the second value on) and in each of its volume buffers
    /// (half the side).
    pub(crate) fn coarse_bytes(&self) -> CoarseBytes {
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

    pub(crate) fn bytes(&self) -> SlotBytes {
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
    pub(crate) fn vec4_per_voxel(&self) -> (u64, u64) {
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

/// Bytes of one slot's coarse grid ([`VolumeShape::coarse_bytes`]).
pub(crate) struct CoarseBytes {
    /// In the media buffer: the density, then other clouds' media.
    pub(crate) media: u64,
    /// Where other clouds' media start within it.
    pub(crate) foreign_at: u64,
    /// In each volume buffer.
    pub(crate) volume: u64,
}
