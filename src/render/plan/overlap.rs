//! Clouds that overlap (docs/illumination.md §4, "Clouds that overlap"). The in-scattered light
//! `S` is a property of a place, not of a cloud: where two clouds interpenetrate, light scatters
//! in the media of both. So each cloud's multiple scattering sweeps through the media of every
//! cloud that reaches into its cube: before the sweeps, the overlap pass samples each neighbour's
//! scattering-grid density at the cloud's voxel centres into `foreign` (the neighbours' extinction
//! and scattering, in units of the cloud's own extinction), and the sweep takes each voxel's
//! summed extinction and its albedo from it.
//!
//! This file decides which clouds overlap (their bounding spheres), keys what a cloud takes from
//! its neighbours, and holds the GPU types of `overlap.wgsl`.

use bevy::{math::Affine3A, prelude::*, render::render_resource::ShaderType};
use bytemuck::{Pod, Zeroable};

use crate::render::{
    core::key_of,
    plan::casters::{CloudSphere, WorldCloud},
};

/// Whether two clouds' density cubes (and so possibly their media) may overlap: their bounding
/// spheres and their world-axis-aligned boxes do.
pub fn overlaps(a: CloudSphere, b: CloudSphere) -> bool {
    let offset = b.centre - a.centre;
    offset.length() < a.radius + b.radius
        && offset.abs().cmplt(a.half_extents + b.half_extents).all()
}

/// The clouds of `clouds` whose media may reach into `receiver`'s cube, and the key of what they
/// give it: their entities, the density their grids hold, their media and where they lie
/// relative to the receiver (0 when none does).
pub fn neighbours_of(receiver: &WorldCloud, clouds: &[WorldCloud]) -> (Vec<Entity>, u64) {
    let mut neighbours: Vec<&WorldCloud> = clouds
        .iter()
        .filter(|c| c.entity != receiver.entity && c.extinction > 0.0)
        .filter(|c| overlaps(receiver.sphere, c.sphere))
        .collect();
    if neighbours.is_empty() {
        return (Vec::new(), 0);
    }
    // The key must not depend on the order the clouds come in.
    neighbours.sort_by_key(|c| c.entity);
    let media: Vec<_> = neighbours
        .iter()
        .map(|c| {
            let medium = [c.extinction, c.albedo, c.anisotropy].map(f32::to_bits);
            (c.entity, c.density, medium, c.relative_bits(receiver))
        })
        .collect();
    let key = key_of((receiver.extinction.to_bits(), media));
    (neighbours.iter().map(|c| c.entity).collect(), key)
}

/// Mirror of `Neighbour` in `overlap.wgsl`: one cloud whose medium reaches into another's cube.
#[derive(ShaderType, Clone, Copy, Debug, Default, PartialEq)]
pub struct Neighbour {
    /// The neighbour's continuous scattering-grid coordinates (voxel `i`'s centre at `i`) of a
    /// receiver-local point.
    pub coords_from_receiver: Mat4,
    /// First element of the neighbour's scattering-grid density in its pool's `densities`.
    pub first: u32,
    /// Voxels per side of that grid.
    pub n: u32,
    /// The neighbour's extinction over the receiver's (world, at density 1), as the sweep takes
    /// it: times the neighbour's δ-M depth scale (docs/illumination.md §4).
    pub extinction: f32,
    /// The neighbour's δ-M transformed albedo.
    pub albedo: f32,
}

impl Neighbour {
    /// The neighbour whose scattering grid has its corner at `grid_origin` (local), voxels of
    /// side `h` and `n` per side, its density at element `first`, placed by
    /// `neighbour_world_from_local`, for a receiver placed by `receiver_world_from_local`.
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        grid_origin: Vec3,
        h: f32,
        n: u32,
        first: u32,
        neighbour_world_from_local: &Affine3A,
        receiver_world_from_local: &Affine3A,
        extinction: f32,
        albedo: f32,
    ) -> Self {
        // g = (x - O) / h - 0.5 (docs/illumination.md §1).
        let coords = Affine3A::from_scale(Vec3::splat(1.0 / h))
            * Affine3A::from_translation(-grid_origin - 0.5 * h);
        let relative = neighbour_world_from_local.inverse() * *receiver_world_from_local;
        Self {
            coords_from_receiver: Mat4::from(coords * relative),
            first,
            n,
            extinction,
            albedo,
        }
    }
}

/// A work item of the overlap pass (`OverlapItem` in `overlap.wgsl`): one slot, and its
/// neighbours that lie in the pool the dispatch binds.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Pod, Zeroable)]
#[repr(C)]
pub struct OverlapItem {
    /// The receiver's slot in its pool.
    pub slot: u32,
    /// Its first neighbour in the dispatch's neighbour array.
    pub first_neighbour: u32,
    /// Its neighbours in that array.
    pub neighbours: u32,
    /// 0: `foreign` becomes these neighbours' media (the first dispatch for this slot this
    /// frame); 1: they are added to it (a later one, for neighbours in another pool).
    pub accumulate: u32,
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::render::plan::casters::tests::cloud;

    #[test]
    fn clouds_whose_cubes_meet_are_neighbours_keyed_by_what_they_give() {
        // Cubes of half-side 1/sqrt(3): 1.0 apart they overlap, 1.5 or 2.5 apart not.
        let clouds = [cloud(1, 0.0), cloud(2, 1.0), cloud(3, -1.5)];
        let (neighbours, key) = neighbours_of(&clouds[0], &clouds);
        assert_eq!(neighbours, [clouds[1].entity]);
        assert_ne!(key, 0);
        assert_eq!(neighbours_of(&clouds[2], &clouds), (vec![], 0));
        // A new density, a new albedo or another place: another key.
        let changed = |f: &dyn Fn(&mut WorldCloud)| {
            let mut other = clouds.clone();
            f(&mut other[1]);
            neighbours_of(&other[0], &other).1
        };
        assert_ne!(changed(&|c| c.density = 99), key);
        assert_ne!(changed(&|c| c.albedo = 0.5), key);
        assert_ne!(
            changed(&|c| c.world_from_local = Affine3A::from_translation(Vec3::X * 0.8)),
            key
        );
        // Its light volumes do not matter here.
        assert_eq!(changed(&|c| c.shade_keys = vec![7, 8]), key);
    }

    #[test]
    fn a_neighbour_maps_receiver_points_to_its_grid_voxels() {
        let origin = Vec3::new(-1.0, -2.0, 0.5);
        let neighbour = Affine3A::from_translation(Vec3::new(3.0, 0.0, 0.0));
        let receiver = Affine3A::from_translation(Vec3::new(2.0, 1.0, 0.0));
        let n = Neighbour::new(origin, 0.25, 16, 0, &neighbour, &receiver, 2.0, 0.9);
        // Receiver-local p is neighbour-local p + (-1, 1, 0).
        let p = Vec3::new(0.5, -0.5, 1.0);
        let expected = (p + Vec3::new(-1.0, 1.0, 0.0) - origin) / 0.25 - 0.5;
        let g = n.coords_from_receiver.transform_point3(p);
        assert!((g - expected).length() < 1e-5, "{g} vs {expected}");
    }
}
