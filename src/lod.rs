//! Level of detail: a cloud's volume resolution follows its size on screen, so that distant clouds
//! cost little (docs/illumination.md §7).
//!
//! The [`CloudLevelOfDetail`] resource turns it on. Each frame, [`CloudLod`] on every cloud records
//! its largest projected diameter over the active cameras and the resolution that asks for. The
//! renderer moves a cloud to a new resolution only when the cloud is re-lit anyway (new particles,
//! or a light that moved), so a level change never pops on a still sky.

use bevy::{camera::primitives::Aabb, prelude::*};

use crate::{
    cloud::ParticleCloud,
    settings::{
        CloudQualitySettings, DefaultCloudQuality, MAX_VOLUME_RESOLUTION, MIN_VOLUME_RESOLUTION,
    },
};

/// How far a cloud's projected size must move past a level's boundary, in levels, before the
/// cloud asks for a coarser level: a cloud at a boundary does not flip between two.
const HYSTERESIS: f32 = 0.25;

/// The level-of-detail knobs (a resource). Off by default.
#[derive(Resource, Clone, Copy, Debug, PartialEq, Reflect)]
#[reflect(Resource, Default, Debug, PartialEq)]
pub struct CloudLevelOfDetail {
    /// Screen pixels per scattering voxel, across a cloud's projected diameter, below which its
    /// resolution is lowered: a cloud `D` pixels across asks for about `D / pixels_per_voxel`
    /// voxels per side (in steps of `√2`), never more than its `volume_resolution` and never
    /// fewer than `min_resolution`. Larger is coarser and cheaper. `0` (the default) turns level
    /// of detail off: every cloud keeps its `volume_resolution`. Negative, NaN or infinite
    /// values also turn it off, with a warning.
    pub pixels_per_voxel: f32,
    /// The fewest voxels per side a cloud is lowered to. Clamped to
    /// `MIN_VOLUME_RESOLUTION..=MAX_VOLUME_RESOLUTION`. Default 16.
    pub min_resolution: u32,
}

impl Default for CloudLevelOfDetail {
    fn default() -> Self {
        Self {
            pixels_per_voxel: 0.0,
            min_resolution: 16,
        }
    }
}

impl CloudLevelOfDetail {
    /// On: `pixels_per_voxel` is finite and positive.
    pub fn enabled(&self) -> bool {
        self.pixels_per_voxel.is_finite() && self.pixels_per_voxel > 0.0
    }

    /// The resolution of `level` for a cloud of at most `max` voxels per side: `max / √2^level`,
    /// rounded to a multiple of 4, and no lower than `min_resolution` (or `max`, if smaller).
    pub fn resolution(&self, max: u32, level: u32) -> u32 {
        let min = self
            .min_resolution
            .clamp(MIN_VOLUME_RESOLUTION, MAX_VOLUME_RESOLUTION)
            .min(max);
        let scaled = max as f32 * 0.5f32.powf(level as f32 * 0.5);
        ((scaled / 4.0).round() as u32 * 4).clamp(min, max)
    }

    /// The coarsest level whose resolution is above `min_resolution`, plus one (where it is
    /// reached): levels past it have the same resolution.
    fn coarsest_level(&self, max: u32) -> u32 {
        (0..64)
            .find(|&l| self.resolution(max, l) <= self.resolution(max, u32::MAX / 2))
            .unwrap_or(0)
    }

    /// The level a cloud `pixels` across asks for, at most `max` voxels per side, coming from
    /// level `current`: finer at once when it grows on screen, coarser only once it is
    /// `HYSTERESIS` levels past the boundary.
    pub fn level(&self, pixels: f32, max: u32, current: Option<u32>) -> u32 {
        let coarsest = self.coarsest_level(max);
        // Continuous level: 0 where the cloud spans `max` voxels at `pixels_per_voxel`.
        let wanted = 2.0 * (max as f32 * self.pixels_per_voxel / pixels).log2();
        let level = |x: f32| (x.floor().max(0.0) as u32).min(coarsest);
        if wanted.is_nan() || wanted <= 0.0 {
            return 0; // as large as its resolution, or a camera inside it
        }
        match current {
            Some(c) if wanted >= c as f32 && wanted < (c + 1) as f32 + HYSTERESIS => {
                c.min(coarsest)
            }
            Some(c) if wanted >= c as f32 => level(wanted - HYSTERESIS),
            _ => level(wanted),
        }
    }
}

/// A cloud's level of detail (written by the plugin while [`CloudLevelOfDetail`] is on).
#[derive(Component, Clone, Copy, Debug, Default, PartialEq, Reflect)]
#[reflect(Component, Default, Debug, PartialEq)]
pub struct CloudLod {
    /// The cloud's largest projected diameter over the active cameras, physical pixels
    /// (infinite when a camera is inside its bounding sphere).
    pub projected_pixels: f32,
    /// The level it asks for: 0 is its `volume_resolution`, each level `√2` coarser.
    pub level: u32,
    /// The volume resolution of that level, voxels per side. The renderer moves the cloud to it
    /// the next time the cloud is re-lit.
    pub resolution: u32,
}

/// The projected diameter, in pixels, of a sphere of `radius` metres at `centre` in a perspective
/// camera at `eye` with vertical field of view `fov` (radians) over `height` pixels. Infinite when
/// the eye is inside the sphere.
pub fn projected_diameter(centre: Vec3, radius: f32, eye: Vec3, fov: f32, height: f32) -> f32 {
    let d2 = centre.distance_squared(eye);
    let r2 = radius * radius;
    if d2 <= r2 {
        return f32::INFINITY;
    }
    // The tangent of the sphere's angular radius, over the tangent of half the field of view.
    let tangent = radius / (d2 - r2).sqrt();
    tangent / (0.5 * fov).tan() * height
}

/// A cloud as the level-of-detail system sees it.
type LodCloud = (
    Entity,
    &'static GlobalTransform,
    &'static Aabb,
    Option<&'static CloudQualitySettings>,
    Option<&'static mut CloudLod>,
);

/// Sets every cloud's [`CloudLod`] from the active perspective cameras.
pub(crate) fn update_cloud_lod(
    mut commands: Commands,
    lod: Res<CloudLevelOfDetail>,
    default_quality: Res<DefaultCloudQuality>,
    cameras: Query<(&Camera, &GlobalTransform, &Projection)>,
    mut clouds: Query<LodCloud, With<ParticleCloud>>,
    mut warned: Local<bool>,
) {
    if !lod.enabled() {
        if lod.pixels_per_voxel != 0.0 && !std::mem::replace(&mut *warned, true) {
            warn!(
                "CloudLevelOfDetail: `pixels_per_voxel` is {}; it must be finite and > 0 (0 turns \
                 level of detail off); level of detail is off",
                lod.pixels_per_voxel
            );
        }
        return;
    }
    let views: Vec<(Vec3, f32, f32)> = cameras
        .iter()
        .filter(|(camera, _, _)| camera.is_active)
        .filter_map(|(camera, transform, projection)| {
            let Projection::Perspective(p) = projection else {
                return None;
            };
            let height = camera.physical_viewport_size()?.y as f32;
            Some((transform.translation(), p.fov, height))
        })
        .collect();
    for (entity, transform, aabb, settings, current) in &mut clouds {
        let max = settings.unwrap_or(&default_quality.0).volume_resolution;
        let (scale, _, _) = transform.to_scale_rotation_translation();
        let centre = transform.transform_point(aabb.center.into());
        let radius = aabb.half_extents.length() * scale.abs().max_element();
        let pixels = views
            .iter()
            .map(|&(eye, fov, height)| projected_diameter(centre, radius, eye, fov, height))
            .fold(0.0, f32::max);
        let level = lod.level(pixels, max, current.as_deref().map(|c| c.level));
        let next = CloudLod {
            projected_pixels: pixels,
            level,
            resolution: lod.resolution(max, level),
        };
        match current {
            Some(mut c) => {
                c.set_if_neq(next);
            }
            None => {
                commands.entity(entity).insert(next);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn lod(pixels_per_voxel: f32) -> CloudLevelOfDetail {
        CloudLevelOfDetail {
            pixels_per_voxel,
            ..default()
        }
    }

    #[test]
    fn levels_step_by_root_two_down_to_the_minimum() {
        let l = lod(2.0);
        let steps: Vec<u32> = (0..7).map(|level| l.resolution(48, level)).collect();
        assert_eq!(steps, [48, 32, 24, 16, 16, 16, 16]);
        assert_eq!(l.coarsest_level(48), 3);
        assert_eq!(l.resolution(128, 1), 92);
        // A cloud whose own resolution is below the minimum keeps it.
        assert_eq!(l.resolution(8, 3), 8);
    }

    #[test]
    fn a_cloud_asks_for_about_one_voxel_per_pixels_per_voxel() {
        let l = lod(2.0);
        // 96 pixels across at 2 pixels per voxel: all 48 voxels.
        assert_eq!(l.level(96.0, 48, None), 0);
        assert_eq!(l.level(1000.0, 48, None), 0);
        assert_eq!(l.level(f32::INFINITY, 48, None), 0);
        // Half the size: two levels (√2 each) coarser, 24 voxels.
        assert_eq!(l.level(48.0, 48, None), 2);
        assert_eq!(l.resolution(48, l.level(48.0, 48, None)), 24);
        // Tiny: the coarsest level, clamped to the minimum.
        assert_eq!(l.level(1.0, 48, None), 3);
        assert_eq!(l.level(0.0, 48, None), 3);
    }

    #[test]
    fn coarser_levels_wait_past_the_boundary_finer_ones_do_not() {
        let l = lod(2.0);
        // Level 1 spans 96/√2 .. 96/2 pixels; continuous level 2 is at 48.
        let at = |level: f32| 96.0 * 0.5f32.powf(level / 2.0);
        assert_eq!(
            l.level(at(2.1), 48, Some(1)),
            1,
            "inside the hysteresis band"
        );
        assert_eq!(l.level(at(2.3), 48, Some(1)), 2, "past it");
        assert_eq!(l.level(at(0.9), 48, Some(1)), 0, "finer at once");
        assert_eq!(l.level(at(1.5), 48, Some(1)), 1);
    }

    #[test]
    fn projected_diameter_of_a_sphere() {
        // A sphere of radius 1 at distance 10, 90° field of view over 1000 pixels: tan = 1/√99.
        let d = projected_diameter(
            Vec3::ZERO,
            1.0,
            Vec3::new(0.0, 0.0, 10.0),
            90f32.to_radians(),
            1000.0,
        );
        assert!((d - 1000.0 / 99f32.sqrt()).abs() < 1e-3, "{d}");
        assert_eq!(
            projected_diameter(Vec3::ZERO, 2.0, Vec3::X, 1.0, 100.0),
            f32::INFINITY
        );
    }

    #[test]
    fn off_unless_finite_and_positive() {
        assert!(!CloudLevelOfDetail::default().enabled());
        assert!(!lod(-1.0).enabled() && !lod(f32::NAN).enabled() && !lod(f32::INFINITY).enabled());
        assert!(lod(0.5).enabled());
    }
}
