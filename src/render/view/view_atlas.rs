//! Every view volume of one view in shared buffers (docs/illumination.md §5, "Overlapping
//! clouds"): their optical depths, their `ViewVolumeParams`, and each volume's neighbours, the
//! volumes of the clouds that may lie in front of some point of its cloud, which its billboards
//! see through. The clouds that overlap on screen form groups, which `draw.rs` draws as one.

use bevy::{
    platform::collections::HashMap,
    prelude::*,
    render::{
        render_resource::{Buffer, ShaderType},
        renderer::{RenderDevice, RenderQueue},
        view::RetainedViewEntity,
    },
};

use crate::render::{
    core::gpu::{storage, storage_bytes},
    core::key_of,
};

/// Mirror of `ViewVolumeParams` in `types.wgsl`.
#[derive(ShaderType, Clone, Copy, Debug, Default, PartialEq)]
pub struct ViewVolumeParams {
    /// Cloud-local from view space.
    pub local_from_view: Mat4,
    /// Tangent rectangle `(u0, u1, v0, v1)` of the rays: `u = x / depth`, `v = y / depth`.
    pub rect: Vec4,
    /// View depths of the first and last slice, metres.
    pub depth: Vec2,
    /// Extinction `K` per world metre at density 1.
    pub extinction: f32,
    /// Rays per side and slices `n` (the fine grid's resolution).
    pub n: u32,
    /// First element of this volume in its view's [`ViewVolumeAtlas::optical_depth`].
    pub offset: u32,
    /// First entry of this volume's neighbours in [`ViewVolumeAtlas::neighbours`].
    pub first_neighbour: u32,
    /// Its neighbours: the view volumes (its own among them) whose clouds may lie in front of
    /// some point of this cloud. Its billboards see through all of them.
    pub neighbour_count: u32,
    /// The first `front_count` neighbours lie wholly in front of this volume: their optical
    /// depth along each of its columns is summed once into its front map.
    pub front_count: u32,
    /// First vec4 of the cloud's multiple scattering seen from the camera in
    /// [`ViewVolumeAtlas::seen_multiple`] (an anisotropic cloud's).
    pub seen_offset: u32,
    /// Voxels per side of that volume (the scattering grid's `N`); 0 when the cloud has none
    /// (isotropic: its billboards read the mean `S_m`).
    pub seen_n: u32,
}

/// Elements a view volume of `n` rays per side and `n` slices takes in its atlas: its `n³`
/// optical depths, then its front map, `n²` sums of the optical depth of the neighbours wholly in
/// front of it along each column's ray (`view_volume.wgsl`, `sum_front`).
pub fn view_volume_len(n: u32) -> u64 {
    let n = n as u64;
    n * n * n + n * n
}

/// The key of an unlit cloud's volume.
pub(crate) const UNLIT: u64 = u64::MAX;

/// Every transmittance volume of one view in shared buffers, so that a cloud's billboards can
/// see through the clouds that overlap it (docs/illumination.md §5, "Overlapping clouds").
pub struct ViewVolumeAtlas {
    /// `f32` optical depths from the camera, each volume's `n³` from its `offset`, then its front
    /// map ([`view_volume_len`]).
    pub optical_depth: Buffer,
    /// Every volume's `ViewVolumeParams`, indexed by the neighbour lists.
    pub volumes: Buffer,
    /// The volumes' neighbour lists, concatenated: indices into `volumes`.
    pub neighbours: Buffer,
    /// vec4 multiple scattering of each anisotropic cloud seen from the camera, `N³` from its
    /// `seen_offset` (docs/illumination.md §5).
    pub seen_multiple: Buffer,
    /// Where each cloud's optical depths lie in `optical_depth` (in f32).
    depth_regions: Regions,
    /// Where each anisotropic cloud's multiple scattering lies in `seen_multiple` (in vec4).
    seen_regions: Regions,
    /// What `volumes` and `neighbours` hold.
    written: u64,
    /// Per cloud, its group: clouds that overlap on screen, directly or through others. A group
    /// is drawn as one (docs/illumination.md §5).
    pub groups: HashMap<Entity, u32>,
    /// `[volume, n]` of each volume with neighbours wholly in front of it, whose front map
    /// `sum_front` fills.
    pub(crate) fronts: Vec<[u32; 2]>,
    /// The front maps must be summed again: the volumes or their lists changed since.
    pub(crate) fronts_stale: bool,
}

/// Every view's [`ViewVolumeAtlas`].
#[derive(Resource, Default)]
pub struct ViewVolumeAtlases(pub HashMap<RetainedViewEntity, ViewVolumeAtlas>);

impl ViewVolumeAtlases {
    /// Every view's buffers (the memory census).
    pub(crate) fn buffers(&self) -> impl Iterator<Item = &Buffer> {
        self.0.values().flat_map(|a| {
            [
                &a.optical_depth,
                &a.volumes,
                &a.neighbours,
                &a.seen_multiple,
            ]
        })
    }
}

/// One cloud's volume in one view while the view's atlas is prepared.
pub(crate) struct AtlasEntry {
    pub(crate) entity: Entity,
    pub(crate) params: ViewVolumeParams,
    /// Key of the march's inputs (`UNLIT` for a zero volume).
    pub(crate) key: u64,
    /// Key of where the camera sees the cloud's multiple scattering from (0: it has none).
    pub(crate) seen_key: u64,
    /// The cloud is drawn this frame.
    pub(crate) drawn: bool,
}

impl AtlasEntry {
    /// Whether the volume has optical depths in the atlas: the cloud is lit. It is marched once
    /// its illumination is ready, the frame before it is first drawn.
    pub(crate) fn occupies(&self) -> bool {
        self.key != UNLIT
    }

    /// Whether other clouds' billboards see through it: it is marched and drawn.
    fn seen_through(&self) -> bool {
        self.drawn && self.occupies()
    }
}

/// Regions of a buffer shared by a view's clouds, one per cloud: `(cloud, length, offset)`.
#[derive(Default)]
struct Regions(Vec<(Entity, u64, u64)>);

impl Regions {
    /// Places the `wanted` regions `(cloud, length)` in a buffer of `capacity` elements: a
    /// region keeps its offset while its length holds, and new regions go after the last one
    /// kept; when they do not fit, every region is packed anew, the buffer growing by doubling
    /// if needed, but past `max` elements (the storage binding) only as far as they need.
    /// Returns each cloud's offset, and the capacity the buffer must grow to, if any.
    fn place(
        &mut self,
        wanted: &[(Entity, u64)],
        capacity: u64,
        max: u64,
    ) -> (HashMap<Entity, u64>, Option<u64>) {
        let previous: HashMap<Entity, (u64, u64)> =
            self.0.iter().map(|&(e, len, o)| (e, (len, o))).collect();
        let (mut kept, mut placed) = (Vec::new(), Vec::new());
        for &(entity, len) in wanted {
            match previous.get(&entity) {
                Some(&(l, offset)) if l == len => kept.push((entity, len, offset)),
                _ => placed.push((entity, len)),
            }
        }
        let mut end = kept.iter().map(|&(_, len, o)| o + len).max().unwrap_or(0);
        let needed: u64 = placed.iter().map(|&(_, len)| len).sum();
        let mut grown = None;
        if end + needed > capacity {
            placed = kept
                .drain(..)
                .map(|(e, len, _)| (e, len))
                .chain(placed)
                .collect();
            end = 0;
            let total: u64 = placed.iter().map(|&(_, len)| len).sum();
            if total > capacity {
                grown = Some(
                    total
                        .next_power_of_two()
                        .max(capacity * 2)
                        .min(max)
                        .max(total),
                );
            }
        }
        for (entity, len) in placed {
            kept.push((entity, len, end));
            end += len;
        }
        self.0 = kept;
        (self.0.iter().map(|&(e, _, o)| (e, o)).collect(), grown)
    }
}

/// Lowers the resolution of every occupying volume by one factor until together they hold at
/// most `max_elements` (one storage binding of f32): a view of many clouds with fine grids would
/// pass it (8 clouds at 48³ × 4: 8 × 192³ floats, 226 MB). The march samples the fine density
/// by position, so any resolution of at least 2 works; a coarser one blurs the shadows that
/// particles cast towards the camera. Returns whether any was lowered.
fn fit_view_volumes(entries: &mut [AtlasEntry], max_elements: u64) -> bool {
    let total = |entries: &[AtlasEntry], scale: f64| -> u64 {
        entries
            .iter()
            .filter(|e| e.occupies())
            .map(|e| view_volume_len(scaled(e.params.n, scale)))
            .sum()
    };
    if total(entries, 1.0) <= max_elements {
        return false;
    }
    let mut scale = (max_elements as f64 / total(entries, 1.0) as f64).cbrt();
    while scale > 0.0 && total(entries, scale) > max_elements {
        scale *= 0.99;
    }
    for entry in entries.iter_mut().filter(|e| e.occupies()) {
        entry.params.n = scaled(entry.params.n, scale);
    }
    true
}

/// `n` scaled by `scale`, rounded down, at least 2 (a volume's nodes per side).
fn scaled(n: u32, scale: f64) -> u32 {
    ((n as f64 * scale) as u32).max(2)
}

/// Whether the tangent rectangles `(u0, u1, v0, v1)` of two volumes overlap.
fn rects_overlap(a: Vec4, b: Vec4) -> bool {
    a.x < b.y && b.x < a.y && a.z < b.w && b.z < a.w
}

/// Whether cloud `front` may lie in front of some point of cloud `behind` along a ray both
/// cross: they overlap on screen and `front` begins before `behind` ends.
fn may_hide(front: &ViewVolumeParams, behind: &ViewVolumeParams) -> bool {
    rects_overlap(front.rect, behind.rect) && front.depth.x < behind.depth.y
}

/// Whether cloud `front` lies wholly in front of cloud `behind`: its last slice before the
/// other's first, so all of its optical depth along a ray is in front of every point of `behind`.
fn wholly_in_front(front: &ViewVolumeParams, behind: &ViewVolumeParams) -> bool {
    front.depth.y <= behind.depth.x
}

/// Fills the neighbour range of each entry seen through and returns the lists, the neighbours
/// wholly in front of it first (`front_count` of them); groups the entries by screen overlap
/// (union-find), each entry's group the smallest index in it.
pub(crate) fn link_neighbours(entries: &mut [AtlasEntry]) -> (Vec<u32>, Vec<u32>) {
    let mut lists = Vec::new();
    let mut group: Vec<u32> = (0..entries.len() as u32).collect();
    fn root(group: &mut [u32], mut i: u32) -> u32 {
        while group[i as usize] != i {
            group[i as usize] = group[group[i as usize] as usize];
            i = group[i as usize];
        }
        i
    }
    for i in 0..entries.len() {
        if !entries[i].seen_through() {
            continue;
        }
        let first = lists.len() as u32;
        let mut others = Vec::new();
        for j in 0..entries.len() {
            let (a, b) = (&entries[j], &entries[i]);
            if a.seen_through() && may_hide(&a.params, &b.params) {
                if wholly_in_front(&a.params, &b.params) {
                    lists.push(j as u32);
                } else {
                    others.push(j as u32);
                }
            }
            if a.seen_through() && rects_overlap(a.params.rect, b.params.rect) {
                let (ri, rj) = (root(&mut group, i as u32), root(&mut group, j as u32));
                group[ri.max(rj) as usize] = ri.min(rj);
            }
        }
        entries[i].params.first_neighbour = first;
        entries[i].params.front_count = lists.len() as u32 - first;
        lists.extend(others);
        entries[i].params.neighbour_count = lists.len() as u32 - first;
    }
    let groups = (0..entries.len() as u32)
        .map(|i| root(&mut group, i))
        .collect();
    (lists, groups)
}

impl ViewVolumeAtlas {
    pub(crate) fn new(device: &RenderDevice) -> Self {
        Self {
            optical_depth: storage(device, "particle_clouds_view_optical_depth", 4),
            volumes: storage(
                device,
                "particle_clouds_view_volumes",
                ViewVolumeParams::min_size().get(),
            ),
            neighbours: storage(device, "particle_clouds_view_volume_neighbours", 4),
            seen_multiple: storage(device, "particle_clouds_view_seen_multiple", 16),
            depth_regions: Regions::default(),
            seen_regions: Regions::default(),
            written: 0,
            groups: HashMap::default(),
            fronts: Vec::new(),
            fronts_stale: false,
        }
    }

    /// Gives each occupying entry its offsets: of its optical depths, and of its multiple
    /// scattering seen from the camera if it has one ([`Regions::place`]). A volume whose offset
    /// or buffer changed is marched (or seen) again, since its key holds both: so a cloud entering
    /// the view costs one march of its own, not of every cloud.
    pub(crate) fn lay_out(&mut self, device: &RenderDevice, entries: &mut [AtlasEntry]) {
        let max_bytes = device.limits().max_storage_buffer_binding_size;
        if fit_view_volumes(entries, max_bytes / 4) {
            info_once!(
                "particle clouds: one view's transmittance volumes exceed the adapter's storage \
                 buffer limit of {max_bytes} bytes; they are marched at a lower resolution in \
                 such views (docs/illumination.md §5)"
            );
        }
        let occupying = || entries.iter().filter(|e| e.occupies());
        let depths: Vec<_> = occupying()
            .map(|e| (e.entity, view_volume_len(e.params.n)))
            .collect();
        let seen: Vec<_> = occupying()
            .filter(|e| e.params.seen_n > 0)
            .map(|e| (e.entity, (e.params.seen_n as u64).pow(3)))
            .collect();
        let (depth_offsets, grown) =
            self.depth_regions
                .place(&depths, self.optical_depth.size() / 4, max_bytes / 4);
        if let Some(elements) = grown {
            self.optical_depth =
                storage(device, "particle_clouds_view_optical_depth", elements * 4);
        }
        let (seen_offsets, grown) =
            self.seen_regions
                .place(&seen, self.seen_multiple.size() / 16, max_bytes / 16);
        if let Some(elements) = grown {
            self.seen_multiple =
                storage(device, "particle_clouds_view_seen_multiple", elements * 16);
        }
        for entry in entries.iter_mut().filter(|e| e.occupies()) {
            entry.params.offset = depth_offsets[&entry.entity] as u32;
            let buffer = self.optical_depth.id();
            entry.key = key_of((entry.key, entry.params.offset, entry.params.n, buffer));
            if let Some(&offset) = seen_offsets.get(&entry.entity) {
                entry.params.seen_offset = offset as u32;
                let buffer = self.seen_multiple.id();
                entry.seen_key = key_of((entry.seen_key, offset, buffer));
            }
        }
    }

    /// Writes every volume's params and the neighbour lists when they changed, growing their
    /// buffers as needed. Returns whether it wrote.
    pub(crate) fn write(
        &mut self,
        device: &RenderDevice,
        queue: &RenderQueue,
        entries: &[AtlasEntry],
        lists: &[u32],
    ) -> bool {
        let params: Vec<ViewVolumeParams> = entries.iter().map(|e| e.params).collect();
        let (params, lists) = (storage_bytes(&params), storage_bytes(lists));
        let key = key_of((&params, &lists));
        if key == self.written {
            // Same params: the same volumes have fronts.
            return false;
        }
        self.written = key;
        self.fronts = entries
            .iter()
            .enumerate()
            .filter(|(_, e)| e.params.front_count > 0)
            .map(|(i, e)| [i as u32, e.params.n])
            .collect();
        self.fronts_stale = true;
        let fit = |buffer: &mut Buffer, label, bytes: &[u8]| {
            if bytes.len() as u64 > buffer.size() {
                *buffer = storage(device, label, (bytes.len() as u64).next_power_of_two());
            }
            if !bytes.is_empty() {
                queue.write_buffer(buffer, 0, bytes);
            }
        };
        fit(&mut self.volumes, "particle_clouds_view_volumes", &params);
        fit(
            &mut self.neighbours,
            "particle_clouds_view_volume_neighbours",
            &lists,
        );
        true
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn entry(index: u32, rect: Vec4, depth: Vec2, drawn: bool) -> AtlasEntry {
        AtlasEntry {
            entity: Entity::from_raw_u32(index).unwrap(),
            params: ViewVolumeParams {
                rect,
                depth,
                n: 4,
                ..default()
            },
            key: index as u64,
            seen_key: 0,
            drawn,
        }
    }

    #[test]
    fn a_cloud_sees_through_the_clouds_that_may_lie_in_front_of_it() {
        let left = Vec4::new(-0.5, 0.0, -0.2, 0.2);
        let middle = Vec4::new(-0.1, 0.3, -0.2, 0.2);
        let right = Vec4::new(0.6, 0.9, -0.2, 0.2);
        let mut entries = [
            // 0 and 1 overlap on screen and in depth; 2 is wholly behind 1 on screen.
            entry(0, left, Vec2::new(4.0, 6.0), true),
            entry(1, middle, Vec2::new(5.0, 7.0), true),
            entry(2, middle, Vec2::new(8.0, 9.0), true),
            // Alone on screen.
            entry(3, right, Vec2::new(4.0, 6.0), true),
            // Overlaps 0 but is not drawn this frame: nobody sees through it.
            entry(4, left, Vec2::new(1.0, 2.0), false),
        ];
        let (lists, groups) = link_neighbours(&mut entries);
        let neighbours = |i: usize| {
            let p = &entries[i].params;
            let range =
                p.first_neighbour as usize..(p.first_neighbour + p.neighbour_count) as usize;
            lists[range].to_vec()
        };
        assert_eq!(neighbours(0), [0, 1]);
        assert_eq!(neighbours(1), [0, 1]);
        // 0 and 1 both begin before 2 ends; 2 begins after 1 ends, so 1 does not see through it.
        assert_eq!(neighbours(2), [0, 1, 2]);
        // 0 and 1 end before 2 begins: they come first, summed into 2's front map.
        assert_eq!(entries[2].params.front_count, 2);
        assert_eq!(entries[0].params.front_count, 0);
        assert_eq!(neighbours(3), [3]);
        assert_eq!(neighbours(4), [] as [u32; 0]);
        // 0, 1 and 2 overlap on screen, directly or through 1: one group, drawn as one.
        assert_eq!(groups, [0, 0, 0, 3, 4]);
    }

    #[test]
    fn a_region_keeps_its_place_while_it_fits_and_all_are_packed_when_not() {
        let cloud = |i| Entity::from_raw_u32(i).unwrap();
        let mut regions = Regions::default();
        let (offsets, grown) = regions.place(&[(cloud(0), 4), (cloud(1), 8)], 16, 1 << 20);
        assert_eq!(
            (offsets[&cloud(0)], offsets[&cloud(1)], grown),
            (0, 4, None)
        );
        // 0 leaves, 2 comes after the last one kept, 1 stays where it was.
        let (offsets, grown) = regions.place(&[(cloud(1), 8), (cloud(2), 4)], 16, 1 << 20);
        assert_eq!(
            (offsets[&cloud(1)], offsets[&cloud(2)], grown),
            (4, 12, None)
        );
        // 1 changes size: it no longer fits after 2, so both are packed anew from 0.
        let (offsets, grown) = regions.place(&[(cloud(1), 6), (cloud(2), 4)], 16, 1 << 20);
        assert_eq!(
            (offsets[&cloud(2)], offsets[&cloud(1)], grown),
            (0, 4, None)
        );
        // More than the buffer holds: packed, and the buffer doubles (at least).
        let (offsets, grown) = regions.place(&[(cloud(1), 6), (cloud(3), 20)], 16, 1 << 20);
        assert_eq!(
            (offsets[&cloud(1)], offsets[&cloud(3)], grown),
            (0, 6, Some(32))
        );
        // Never past the binding's `max`, unless the regions themselves need more.
        let (_, grown) = regions.place(&[(cloud(1), 6), (cloud(3), 30)], 32, 40);
        assert_eq!(grown, Some(40));
        let (_, grown) = regions.place(&[(cloud(1), 26), (cloud(3), 30)], 40, 40);
        assert_eq!(grown, Some(56));
    }

    /// Eight clouds at 48³ × 4 (fine grids of 192) pass lavapipe's 128 MiB binding in one view:
    /// their volumes are marched at one lower resolution that fits; under the limit, untouched.
    #[test]
    fn a_view_whose_volumes_pass_the_binding_marches_them_coarser() {
        let max_elements = (128 << 20) / 4;
        let mut entries: Vec<AtlasEntry> = (0..8)
            .map(|i| {
                let mut e = entry(i, Vec4::ZERO, Vec2::ZERO, true);
                e.params.n = 192;
                e
            })
            .collect();
        // Not marched yet: takes no room.
        entries[7].key = UNLIT;
        let fits = |entries: &[AtlasEntry]| -> u64 {
            entries
                .iter()
                .filter(|e| e.occupies())
                .map(|e| view_volume_len(e.params.n))
                .sum()
        };
        assert!(fits(&entries) > max_elements);
        assert!(fit_view_volumes(&mut entries, max_elements));
        assert!(fits(&entries) <= max_elements);
        let n = entries[0].params.n;
        // 7 × (n³ + n²) floats within 33.5 M: n = 168 at most; the steps of 1 % stay close.
        assert!((160..=168).contains(&n), "{n}");
        assert!(entries[..7].iter().all(|e| e.params.n == n));
        assert_eq!(entries[7].params.n, 192);
        // Four fit as they are.
        let mut four: Vec<AtlasEntry> = entries.drain(..4).collect();
        four.iter_mut().for_each(|e| e.params.n = 192);
        assert!(!fit_view_volumes(&mut four, max_elements));
        assert!(four.iter().all(|e| e.params.n == 192));
    }
}
