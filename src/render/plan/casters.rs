//! Clouds shadow each other (docs/illumination.md §2, "Clouds shadow each other"). Optical depths
//! add along a line, so the optical depth towards a light through every cloud is the sum of each
//! cloud's own, each sampled on its own light box. Shade writes a cloud's own optical depth twice:
//! into `own_depth`, which other clouds read, and into `optical_depth`, which gather and the
//! billboards read. The cast pass then rebuilds `optical_depth` of a cloud that others shadow as
//! its own plus, at each voxel centre, every caster's own volume looked up there.
//!
//! This file decides who casts on whom (a pure function of the clouds' bounding spheres, tested
//! on the CPU), keys what a cloud is cast (so a still sky casts nothing twice), and holds the GPU
//! types of `cast.wgsl`.

use bevy::{math::Affine3A, prelude::*, render::render_resource::ShaderType};
use bytemuck::{Pod, Zeroable};

use crate::render::{core::key_of, core::types::LightParams, extract::particles::CloudBounds};

/// A cloud's bounding sphere in the world: it holds the cloud's density cube, and so every light
/// box of it. With the half-extents of the cube's world-axis-aligned box beside it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CloudSphere {
    /// World centre, metres.
    pub centre: Vec3,
    /// World radius, metres.
    pub radius: f32,
    /// Half-extents of the box around the density cube along the world axes, metres.
    pub half_extents: Vec3,
}

impl CloudSphere {
    /// The sphere around the density cube `bounds` (cloud-local) of a cloud placed by
    /// `world_from_local`, whose largest scale factor is `scale`.
    pub fn new(bounds: CloudBounds, world_from_local: &Affine3A, scale: f32) -> Self {
        let m = world_from_local.matrix3;
        let abs = Mat3::from_cols(
            m.x_axis.abs().into(),
            m.y_axis.abs().into(),
            m.z_axis.abs().into(),
        );
        Self {
            centre: world_from_local.transform_point3(bounds.centre),
            radius: 0.5 * 3f32.sqrt() * bounds.side * scale,
            half_extents: abs * Vec3::splat(0.5 * bounds.side),
        }
    }
}

/// Whether `caster` may shadow some point of `receiver` under a light travelling along the unit
/// direction `d`: their columns along the light overlap, and the caster does not lie wholly past
/// the receiver. Conservative: a caster that passes holds nothing along a receiver's column or
/// lies past it adds exactly 0 in the cast (`cast_depth` in `cast.wgsl`).
pub fn casts_on(d: Vec3, receiver: CloudSphere, caster: CloudSphere) -> bool {
    let offset = caster.centre - receiver.centre;
    let along = offset.dot(d);
    let across = (offset - along * d).length();
    let reach = receiver.radius + caster.radius;
    across < reach && along < reach
}

/// A cloud as other clouds see it (the cast, and [`overlap`](crate::render::plan::overlap)): where it is, its
/// medium, and what its volumes hold.
#[derive(Clone, Debug)]
pub struct WorldCloud {
    /// Its render entity.
    pub entity: Entity,
    /// Its bounding sphere.
    pub sphere: CloudSphere,
    /// World from cloud-local.
    pub world_from_local: Affine3A,
    /// Extinction per world metre at density 1.
    pub extinction: f32,
    /// Single-scattering albedo.
    pub albedo: f32,
    /// Henyey–Greenstein anisotropy `g` (its medium as the sweep takes it depends on it).
    pub anisotropy: f32,
    /// The density key its grids hold ([`StageKeys::density`](crate::render::plan::StageKeys)).
    pub density: u64,
    /// The shade key of each of its light volumes ([`StageKeys::lights`](crate::render::plan::StageKeys)).
    pub shade_keys: Vec<u64>,
    /// It shadows other clouds (no `NotShadowCaster`).
    pub casts_shadows: bool,
}

impl WorldCloud {
    /// Bits of this cloud's local space seen from `receiver`'s: how it lies relative to it.
    pub fn relative_bits(&self, receiver: &WorldCloud) -> [u32; 12] {
        let relative = self.world_from_local.inverse() * receiver.world_from_local;
        relative.to_cols_array().map(f32::to_bits)
    }
}

/// Per light slot, the clouds of `clouds` that cast their shadow on `receiver` under the light
/// travelling along `directions[l]`, and the key of what they cast: their entities, their own
/// volumes' keys and where they lie relative to the receiver (0 when none casts).
pub fn casters_of(
    receiver: &WorldCloud,
    clouds: &[WorldCloud],
    directions: &[Vec3],
) -> (Vec<Vec<Entity>>, Vec<u64>) {
    directions
        .iter()
        .enumerate()
        .map(|(l, &d)| {
            let mut casters: Vec<&WorldCloud> = clouds
                .iter()
                .filter(|c| c.casts_shadows && c.entity != receiver.entity)
                .filter(|c| c.shade_keys.len() > l)
                .filter(|c| casts_on(d, receiver.sphere, c.sphere))
                .collect();
            // The key must not depend on the order the clouds come in.
            casters.sort_by_key(|c| c.entity);
            if casters.is_empty() {
                return (Vec::new(), 0);
            }
            let placed: Vec<_> = casters
                .iter()
                .map(|c| (c.entity, c.shade_keys[l], c.relative_bits(receiver)))
                .collect();
            (casters.iter().map(|c| c.entity).collect(), key_of(placed))
        })
        .unzip()
}

/// Mirror of `Caster` in `cast.wgsl`: one cloud casting its shadow on another along one light.
#[derive(ShaderType, Clone, Copy, Debug, Default, PartialEq)]
pub struct Caster {
    /// The caster's continuous light-box voxel coordinates (voxel `i`'s centre at `i`) of a
    /// receiver-local point.
    pub coords_from_receiver: Mat4,
    /// First element of the caster's own light volume in its pool's `own_depth`.
    pub first: u32,
    /// Voxels per side of that volume.
    pub n: u32,
    /// Unused: pads the struct to 16 bytes.
    pub _padding: UVec2,
}

/// A cloud's own light volume as casters are made of it: where its voxels lie in the world.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CasterVolume {
    /// The volume's continuous voxel coordinates of a world point.
    coords_from_world: Affine3A,
    first: u32,
    n: u32,
}

impl CasterVolume {
    /// The light volume `light`, at element `first` with `n` voxels per side, of a cloud whose
    /// density cube is centred on `grid_centre`, placed by `world_from_local`.
    pub fn new(
        light: &LightParams,
        grid_centre: Vec3,
        world_from_local: &Affine3A,
        first: u32,
        n: u32,
    ) -> Self {
        // g = ((x - C) . axis + e) / h - 0.5 per axis of the light box (docs/illumination.md §2).
        let h = Vec3::new(light.h_u, light.h_v, light.h_w);
        let axes = [light.u, light.v, light.w];
        let rows = Mat3::from_cols(axes[0] / h.x, axes[1] / h.y, axes[2] / h.z).transpose();
        let offset = (light.half_extents - Vec3::from(axes.map(|a| a.dot(grid_centre)))) / h - 0.5;
        let coords = Affine3A::from_mat3_translation(rows, offset);
        Self {
            coords_from_world: coords * world_from_local.inverse(),
            first,
            n,
        }
    }

    /// The span of the volume's box along the world direction `axis` (unit), metres: where its
    /// columns lie across a light travelling along its own.
    pub fn span_along(&self, axis: Vec3) -> (f32, f32) {
        let world_from_coords = self.coords_from_world.inverse();
        let (lo, hi) = (-0.5, self.n as f32 - 0.5);
        (0..8u32).fold((f32::INFINITY, f32::NEG_INFINITY), |(a, b), c| {
            let pick = |bit: u32| if c & (1 << bit) == 0 { lo } else { hi };
            let corner = world_from_coords.transform_point3(Vec3::new(pick(0), pick(1), pick(2)));
            let t = corner.dot(axis);
            (a.min(t), b.max(t))
        })
    }

    /// This volume casting on a target whose space is placed by `target_world_from_local` (the
    /// identity for the world).
    pub fn on(&self, target_world_from_local: &Affine3A) -> Caster {
        Caster {
            coords_from_receiver: Mat4::from(self.coords_from_world * *target_world_from_local),
            first: self.first,
            n: self.n,
            _padding: UVec2::ZERO,
        }
    }
}

/// What a cast target's optical depths start from, before its casters are added.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum CastStart {
    /// Nothing (a shadow map).
    Zero = 0,
    /// The target's own optical depth (a light volume; its first dispatch this frame).
    Own = 1,
    /// What the target holds (a later dispatch, for casters in another pool).
    Held = 2,
}

/// A work item of the cast pass (`CastTarget` in `cast.wgsl`): a lattice of points in the
/// target's space (a cloud's local space for its light volume, the world for a shadow map), and
/// its casters that lie in the pool the dispatch binds. Point `(i, j, k)` lies at
/// `origin + i step_x + j step_y + k step_z`; its value is element
/// `first + i + size_x (j + size_y k)`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Pod, Zeroable)]
#[repr(C)]
pub struct CastTarget {
    /// Point `(0, 0, 0)`.
    pub origin: [f32; 3],
    /// Its element in the optical depths written.
    pub first: u32,
    /// From one point to the next along x.
    pub step_x: [f32; 3],
    /// Points along x.
    pub size_x: u32,
    /// From one point to the next along y.
    pub step_y: [f32; 3],
    /// Points along y.
    pub size_y: u32,
    /// From one point to the next along z.
    pub step_z: [f32; 3],
    /// Points along z.
    pub size_z: u32,
    /// Its first caster in the dispatch's caster array.
    pub first_caster: u32,
    /// Its casters in that array.
    pub casters: u32,
    /// A [`CastStart`].
    pub start: u32,
    /// Unused: pads the item to 80 bytes (work lists are bound in 256-byte chunks).
    pub _padding: u32,
}

impl CastTarget {
    /// The voxels of light volume `light` of a cloud whose density cube is centred on
    /// `grid_centre` (cloud-local), starting at element `first`.
    pub fn light_volume(light: &LightParams, grid_centre: Vec3, n: u32, first: u32) -> Self {
        let h = Vec3::new(light.h_u, light.h_v, light.h_w);
        let axes = [light.u, light.v, light.w];
        let corner = -light.half_extents + 0.5 * h;
        let origin = grid_centre + axes[0] * corner.x + axes[1] * corner.y + axes[2] * corner.z;
        let step = |a: usize| (axes[a] * h[a]).to_array();
        Self {
            origin: origin.to_array(),
            first,
            step_x: step(0),
            size_x: n,
            step_y: step(1),
            size_y: n,
            step_z: step(2),
            size_z: n,
            ..default()
        }
    }

    /// Columns along z (the light's travel for a light volume): the cast's invocations.
    pub fn columns(&self) -> u32 {
        self.size_x * self.size_y
    }
}

/// The cast work of one target buffer (a pool's light volumes, or the shadow maps) whose casters
/// lie in one pool: the targets, and their casters.
#[derive(Default)]
pub struct CastWork {
    /// One per target.
    pub targets: Vec<CastTarget>,
    /// The targets' casters, each target's in a run.
    pub casters: Vec<Caster>,
}

/// Adds `target`, cast on by `casters` (each with the pool it lies in), to `work`, one item per
/// pool the casters lie in. The first (in pool order, the order the dispatches run) starts from
/// `start`, the others add to what the first wrote. Without casters, one item in `own_pool`
/// writes `start` alone (a light volume whose casters have gone gets its own optical depth
/// back).
pub fn add_cast<P: Copy + Ord + std::hash::Hash>(
    work: &mut bevy::platform::collections::HashMap<P, CastWork>,
    target: CastTarget,
    start: CastStart,
    casters: impl IntoIterator<Item = (P, Caster)>,
    own_pool: P,
) {
    let mut by_pool = by_pool(casters);
    if by_pool.is_empty() {
        by_pool.push((own_pool, Vec::new()));
    }
    for (i, (pool, casters)) in by_pool.into_iter().enumerate() {
        let w = work.entry(pool).or_default();
        w.targets.push(CastTarget {
            first_caster: w.casters.len() as u32,
            casters: casters.len() as u32,
            start: if i == 0 { start } else { CastStart::Held } as u32,
            ..target
        });
        w.casters.extend(casters);
    }
}

/// `items` grouped by the pool each lies in, the pools in order: the order their dispatches
/// run, the first writing a target and the others adding to it (the cast, and the overlap of
/// [`overlap`](crate::render::plan::overlap)).
pub fn by_pool<P: Copy + Ord, T>(items: impl IntoIterator<Item = (P, T)>) -> Vec<(P, Vec<T>)> {
    let mut grouped: Vec<(P, Vec<T>)> = Vec::new();
    for (pool, item) in items {
        match grouped.iter_mut().find(|(p, _)| *p == pool) {
            Some((_, list)) => list.push(item),
            None => grouped.push((pool, vec![item])),
        }
    }
    grouped.sort_by_key(|(pool, _)| *pool);
    grouped
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    pub(crate) fn sphere(x: f32, y: f32, radius: f32) -> CloudSphere {
        CloudSphere {
            centre: Vec3::new(x, y, 0.0),
            radius,
            half_extents: Vec3::splat(radius / 3f32.sqrt()),
        }
    }

    #[test]
    fn a_cloud_casts_on_those_beyond_it_along_the_light() {
        let down = Vec3::NEG_Y;
        let receiver = sphere(0.0, 0.0, 1.0);
        // Above it, under a sun overhead: it casts; below it, or beside it, not.
        assert!(casts_on(down, receiver, sphere(0.3, 5.0, 1.0)));
        assert!(!casts_on(down, receiver, sphere(0.3, -5.0, 1.0)));
        assert!(!casts_on(down, receiver, sphere(2.5, 5.0, 1.0)));
        // Interpenetrating clouds cast on each other both ways.
        let other = sphere(0.5, 0.5, 1.0);
        assert!(casts_on(down, receiver, other) && casts_on(down, other, receiver));
        // A low sun from +x: the cloud at +x casts.
        let low = Vec3::new(-1.0, -0.1, 0.0).normalize();
        assert!(casts_on(low, receiver, sphere(6.0, 0.5, 1.0)));
        assert!(!casts_on(low, receiver, sphere(-6.0, 0.5, 1.0)));
    }

    pub(crate) fn cloud(index: u32, x: f32) -> WorldCloud {
        WorldCloud {
            entity: Entity::from_raw_u32(index).unwrap(),
            sphere: sphere(x, 0.0, 1.0),
            world_from_local: Affine3A::from_translation(Vec3::X * x),
            extinction: 2.0,
            albedo: 0.9,
            anisotropy: 0.0,
            density: index as u64,
            shade_keys: vec![10 + index as u64, 20 + index as u64],
            casts_shadows: true,
        }
    }

    #[test]
    fn the_cast_key_changes_with_the_casters_and_not_with_a_shared_motion() {
        let lights = [Vec3::NEG_X, Vec3::X];
        let clouds = [cloud(1, 0.0), cloud(2, 3.0)];
        let (casters, keys) = casters_of(&clouds[0], &clouds, &lights);
        // Light 0 travels towards -x: cloud 2, at +x, casts on cloud 1; light 1 the other way.
        assert_eq!(casters, [vec![clouds[1].entity], vec![]]);
        assert_ne!(keys[0], 0);
        assert_eq!(keys[1], 0);
        // Both moved together: the same key. One moved, or re-shaded: another.
        let shift = |c: &WorldCloud, by: f32| WorldCloud {
            world_from_local: Affine3A::from_translation(Vec3::Y * by) * c.world_from_local,
            ..c.clone()
        };
        let together = [shift(&clouds[0], 1.0), shift(&clouds[1], 1.0)];
        assert_eq!(casters_of(&together[0], &together, &lights).1, keys);
        let apart = [clouds[0].clone(), shift(&clouds[1], 0.5)];
        assert_ne!(casters_of(&apart[0], &apart, &lights).1[0], keys[0]);
        let reshaded = [
            clouds[0].clone(),
            WorldCloud {
                shade_keys: vec![99, 20],
                ..clouds[1].clone()
            },
        ];
        assert_ne!(casters_of(&reshaded[0], &reshaded, &lights).1[0], keys[0]);
    }

    /// A light box travelling down, its axes x, z, -y, voxels 0.5, 0.25, 1 across.
    fn light_box() -> LightParams {
        LightParams {
            u: Vec3::X,
            h_u: 0.5,
            v: Vec3::Z,
            h_v: 0.25,
            w: Vec3::NEG_Y,
            h_w: 1.0,
            half_extents: Vec3::new(2.0, 1.0, 4.0),
            ..default()
        }
    }

    #[test]
    fn a_light_volumes_cast_target_walks_its_voxel_centres() {
        let light = light_box();
        let centre = Vec3::new(1.0, 2.0, 3.0);
        let t = CastTarget::light_volume(&light, centre, 8, 100);
        // Voxel (a, b, c) at C + xi_u u + xi_v v + xi_w w, xi = -e + (idx + 0.5) h.
        let (a, b, c) = (3.0, 5.0, 7.0);
        let xi = -light.half_extents + (Vec3::new(a, b, c) + 0.5) * Vec3::new(0.5, 0.25, 1.0);
        let expected = centre + xi.x * light.u + xi.y * light.v + xi.z * light.w;
        let point = Vec3::from(t.origin)
            + a * Vec3::from(t.step_x)
            + b * Vec3::from(t.step_y)
            + c * Vec3::from(t.step_z);
        assert!((point - expected).length() < 1e-5, "{point} vs {expected}");
        assert_eq!((t.first, t.columns(), t.size_z), (100, 64, 8));
    }

    #[test]
    fn a_target_is_cast_on_once_per_pool_its_casters_lie_in() {
        let mut work = bevy::platform::collections::HashMap::default();
        let target = CastTarget::default();
        let caster = |n| Caster { n, ..default() };
        let casters = [(2, caster(1)), (1, caster(2)), (2, caster(3))];
        add_cast(&mut work, target, CastStart::Own, casters, 7);
        // Pool 1 runs first and starts from the target's own depth; pool 2 adds its two.
        let one = &work[&1];
        assert_eq!(
            (one.targets[0].start, one.targets[0].casters),
            (CastStart::Own as u32, 1)
        );
        let two = &work[&2];
        assert_eq!(
            (two.targets[0].start, two.targets[0].casters),
            (CastStart::Held as u32, 2)
        );
        assert_eq!(two.casters.iter().map(|c| c.n).collect::<Vec<_>>(), [1, 3]);
        // No caster: one item in its own pool, its own depth alone.
        add_cast(&mut work, target, CastStart::Own, [], 7);
        assert_eq!(
            (work[&7].targets[0].casters, work[&7].targets[0].start),
            (0, 1)
        );
    }

    #[test]
    fn a_caster_maps_receiver_points_to_its_light_box_voxels() {
        let light = light_box();
        let centre = Vec3::new(1.0, 2.0, 3.0);
        let caster = Affine3A::from_translation(Vec3::new(10.0, 0.0, 0.0));
        let receiver = Affine3A::from_translation(Vec3::new(12.0, 1.0, 0.0));
        let c = CasterVolume::new(&light, centre, &caster, 0, 8).on(&receiver);
        // Receiver-local p is caster-local p + (2, 1, 0).
        let p = Vec3::new(-0.5, 0.5, 2.0);
        let local = p + Vec3::new(2.0, 1.0, 0.0);
        let d = local - centre;
        let expected =
            (Vec3::new(d.x, d.z, -d.y) + light.half_extents) / Vec3::new(0.5, 0.25, 1.0) - 0.5;
        let g = c.coords_from_receiver.transform_point3(p);
        assert!((g - expected).length() < 1e-5, "{g} vs {expected}");
    }
}
