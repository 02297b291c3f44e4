//! A cloud's uniforms and the sizes of its volumes, from its settings, its particles and the
//! lights: the pure part of preparing its volumes ([`volumes`](super::volumes)).

use bevy::prelude::*;

use crate::math::{density_level, density_level_sizes};
use crate::particle::DeltaM;
use crate::render::{
    extract::particles::{CloudBounds, GpuParticles},
    extract::{ExtractedCloud, ExtractedCloudLights},
    plan::StageKeys,
    plan::ground::{ground_frame, ground_key},
    plan::pools::VolumeShape,
};

use crate::render::core::types::{CloudParams, LightParams};

/// Every light's uniform for a cloud of uniform `params`, slot `i` shading the `i`-th light in
/// the cloud's local frame.
pub(crate) fn light_params(
    params: &CloudParams,
    cloud: &ExtractedCloud,
    lights: &ExtractedCloudLights,
) -> Vec<LightParams> {
    let to_local = cloud.rotation().inverse();
    lights
        .lights
        .iter()
        .zip(0..)
        .map(|(l, i)| {
            LightParams::new(
                params,
                (to_local * l.direction).normalize(),
                l.irradiance * cloud.light_transmittance(i as usize),
                i,
            )
        })
        .collect()
}

/// This frame's stage keys of `cloud` (at its settings' resolution), other clouds casting on it
/// what `casts` keys (per light slot; empty: none) and overlapping it with the media `media`
/// keys (0: none).
pub(crate) fn frame_keys(
    cloud: &ExtractedCloud,
    gpu: &GpuParticles,
    bounds: CloudBounds,
    lights: &ExtractedCloudLights,
    casts: &[u64],
    media: u64,
) -> StageKeys {
    let params = cloud_params(cloud, gpu, bounds, lights);
    let ground = ground_frame(cloud, &params, lights.ground.as_ref(), lights.sky);
    StageKeys::new(
        &params,
        &light_params(&params, cloud, lights),
        casts,
        media,
        (lights.sky, ground_key(&ground)),
        gpu.generation,
        &cloud.settings,
    )
}

/// `cloud` illuminated at `n` voxels per side, its fine grid lowered where one such cloud's
/// volumes would not fit the adapter's storage binding (`max_binding` bytes).
pub(crate) fn at_resolution(
    cloud: &ExtractedCloud,
    n: u32,
    lights: &ExtractedCloudLights,
    max_binding: u64,
) -> ExtractedCloud {
    let mut cloud = cloud.clone();
    cloud.settings.volume_resolution = n;
    let (count, moments) = (lights.lights.len() as u32, cloud.has_moments());
    let wanted = cloud.settings.light_resolution();
    // None fits: n, and the allocation refuses the cloud with its own warning.
    let fitting =
        VolumeShape::fitting_light_resolution(&cloud.settings, count, moments, max_binding)
            .unwrap_or(n);
    cloud.light_resolution = fitting;
    if fitting < wanted {
        let message = format!(
            "particle cloud: light volumes of {wanted}³ voxels for {count} lights exceed this \
             adapter's storage buffer limit of {max_binding} bytes; such clouds are shaded on a \
             fine grid of {fitting}³ (a scattering grid of {n}³)",
        );
        // The default's lowering is documented (5 lights at 48³ on a 128 MiB binding): not a
        // warning, which would fire for every user of such an adapter.
        if cloud.settings.light_supersampling_is_default() {
            info_once!("{message}");
        } else {
            warn_once!("{message}");
        }
    }
    cloud
}

/// The shape of the volumes `cloud` is illuminated in under `lights`.
pub(crate) fn volume_shape(cloud: &ExtractedCloud, lights: &ExtractedCloudLights) -> VolumeShape {
    let count = lights.lights.len() as u32;
    VolumeShape::new(&cloud.settings, count, cloud.has_moments())
        .with_light_resolution(cloud.light_resolution)
}

/// The uniform of the fine grid (voxelize and shade): the same cube at `m` voxels per side.
pub(crate) fn fine_params(params: &CloudParams) -> CloudParams {
    CloudParams {
        n: params.light_n,
        h: params.h * params.n as f32 / params.light_n as f32,
        ..*params
    }
}

/// The largest particle's radius in fine voxels, in a fine grid of `m` voxels per side over
/// `bounds`.
fn largest_particle_in_voxels(bounds: CloudBounds, m: u32) -> f64 {
    (bounds.max_radius * m as f32 / bounds.side) as f64
}

/// Density levels that hold particles: the fine grid down to the largest particle's level, or one
/// further when that particle is within 1e-4 of a level's boundary, where the GPU's f32 choice
/// may differ from this one (a level deposited on but not upsampled would lose its mass).
pub(crate) fn levels_in_use(bounds: CloudBounds, m: u32) -> usize {
    let r_over_h = largest_particle_in_voxels(bounds, m);
    density_level(r_over_h * (1.0 + 1e-4), density_level_sizes(m).len()) + 1
}

/// The uniform of a cloud's illumination passes.
pub(crate) fn cloud_params(
    cloud: &ExtractedCloud,
    gpu: &GpuParticles,
    bounds: CloudBounds,
    lights: &ExtractedCloudLights,
) -> CloudParams {
    let n = cloud.settings.volume_resolution;
    let delta = DeltaM::new(cloud.albedo as f64, cloud.anisotropy as f64);
    CloudParams {
        n,
        particle_count: gpu.count,
        light_n: cloud.light_resolution,
        light_count: lights.lights.len() as u32,
        grid_origin: bounds.centre - bounds.side * 0.5,
        h: bounds.side / n as f32,
        grid_centre: bounds.centre,
        k_local: cloud.extinction * cloud.scale(),
        albedo: cloud.albedo,
        forward_scattering: cloud.settings.forward_scattering,
        anisotropy: cloud.anisotropy,
        depth_scale: delta.depth_scale as f32,
        lit: lights.any() as u32,
        foreign: 0,
        scatter_albedo: delta.albedo as f32,
        scatter_anisotropy: delta.anisotropy as f32,
        scatter_second_moment: delta.second_moment as f32,
        moments: cloud.has_moments() as u32,
    }
}

/// Optical depths across one fine voxel, at the densest particle's peak, above which a medium
/// draws measurably wrong: the light volumes hold optical depth at voxel centres, so where one
/// voxel is this thick its lit skin, which scatters almost all of a dense medium's light, is
/// shaded as if it lay deeper. On `benchmark dense`'s ball (llvmpipe, default settings) the mean
/// radiance was 9 % off at 2, 11 % at 3, 20 % dark at 100 and black at 10,000.
pub const DENSE_VOXEL_LIMIT: f32 = 3.0;

/// The optical thickness of one fine voxel at the densest particle's peak, for a cloud of
/// uniform `params` (its extinction in local metres) over `bounds`.
pub(crate) fn fine_voxel_thickness(params: &CloudParams, bounds: CloudBounds) -> f32 {
    params.k_local * bounds.max_density * fine_params(params).h
}

/// The warning for a cloud of `extinction` (1/m) whose uniform becomes `new` (from `old`):
/// once, when its medium becomes denser than its fine grid resolves.
pub(crate) fn dense_medium_warning(
    extinction: f32,
    old: &CloudParams,
    new: &CloudParams,
    bounds: CloudBounds,
) -> Option<String> {
    let thickness = fine_voxel_thickness(new, bounds);
    let was_dense = fine_voxel_thickness(old, bounds) > DENSE_VOXEL_LIMIT;
    (thickness > DENSE_VOXEL_LIMIT && !was_dense).then(|| {
        format!(
            "`extinction` {} 1/m at a peak density of {} is {thickness:.1} optical depths \
             across one fine voxel, more than the {DENSE_VOXEL_LIMIT} its light volumes \
             resolve: its radiance is 10 % off or more, and far denser media draw black (the \
             fine voxel is the cloud's side over `volume_resolution` × `light_supersampling`)",
            extinction, bounds.max_density,
        )
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::render::core::types::DensityLevels;
    use crate::render::extract::CloudLight;
    use crate::settings::CloudQualitySettings;

    fn bounds(max_radius: f32) -> CloudBounds {
        CloudBounds {
            centre: Vec3::ZERO,
            side: 2.0,
            max_radius,
            max_density: 1.0,
        }
    }

    fn params(k_local: f32) -> CloudParams {
        CloudParams {
            n: 64,
            light_n: 128,
            h: 2.0 / 64.0,
            k_local,
            ..default()
        }
    }

    #[test]
    fn a_medium_denser_than_its_fine_grid_resolves_is_warned_of_once() {
        let bounds = CloudBounds {
            max_density: 2.0,
            ..bounds(0.1)
        };
        // τ = k · 2 · (2 / 128): at the limit for k = 4 · limit.
        let at_limit = DENSE_VOXEL_LIMIT * 32.0;
        let thickness = fine_voxel_thickness(&params(at_limit), bounds);
        assert!((thickness - DENSE_VOXEL_LIMIT).abs() < 1e-4 * DENSE_VOXEL_LIMIT);
        let extinction = at_limit * 1.01;
        let clear = params(at_limit * 0.99);
        let dense = params(at_limit * 1.01);
        let message = dense_medium_warning(extinction, &clear, &dense, bounds).expect("a warning");
        assert!(message.contains(&format!("`extinction` {} 1/m", at_limit * 1.01)));
        assert!(message.contains("peak density of 2 "));
        // Once: not again while it stays dense, nor for a medium the grid resolves.
        assert_eq!(
            dense_medium_warning(extinction, &dense, &dense, bounds),
            None
        );
        assert_eq!(
            dense_medium_warning(extinction, &clear, &clear, bounds),
            None
        );
        assert_eq!(
            dense_medium_warning(extinction, &dense, &clear, bounds),
            None
        );
    }

    #[test]
    fn only_levels_holding_particles_are_upsampled() {
        let m = 144;
        let h = 2.0 / m as f32;
        assert_eq!(levels_in_use(bounds(31.9 * h), m), 1);
        // At the boundary the GPU may round either way: the next level is upsampled too.
        assert_eq!(levels_in_use(bounds(32.0 * h), m), 2);
        assert_eq!(levels_in_use(bounds(32.5 * h), m), 2);
        assert_eq!(levels_in_use(bounds(72.0 * h), m), 3);
        assert_eq!(levels_in_use(bounds(144.0 * h), m), 4);
    }

    #[test]
    fn density_levels_pack_after_the_fine_grid() {
        let (entries, elements) = DensityLevels::entries(144);
        assert_eq!(entries.len(), 6);
        assert_eq!(
            elements,
            [144u64, 72, 36, 18, 9, 5]
                .iter()
                .map(|n| n.pow(3))
                .sum::<u64>()
        );
        let e = &entries[3];
        assert_eq!((e.count, e.upsample_from), (6, 3));
        // Voxelize's bricks (8³ voxels) follow the same order: 18³ of the fine grid, then 9³.
        assert_eq!(e.size_offset[0], UVec4::new(144, 0, 0, 18));
        assert_eq!(
            e.size_offset[1],
            UVec4::new(72, 144u32.pow(3), 18u32.pow(3), 9)
        );
        assert_eq!(e.size_offset[5].w, 1);
        assert_eq!(e.size_offset[6], UVec4::ZERO);
        assert_eq!(
            DensityLevels::bricks(144),
            [18u64, 9, 5, 3, 2, 1].iter().map(|n| n.pow(3)).sum::<u64>()
        );
    }

    /// Five lights' volumes at 64³ × 4 (5 × 256³ floats, 336 MB) pass a 128 MiB binding
    /// (lavapipe's, and WebGPU's default): the fine grid drops to the largest whose five volumes
    /// fit, 188³ (5 × 188³ × 4 bytes = 132.9 MB; 189³ would be 135.0 MB), not to a whole
    /// multiple of 64 (128³). One light keeps 256³ (67 MB), and so do five under a larger
    /// binding. At the default 48³ (192³), five lights get 188³ too, four keep 192³.
    #[test]
    fn the_fine_grid_is_lowered_until_the_volumes_fit_the_binding() {
        let lights = |count| ExtractedCloudLights {
            lights: vec![
                CloudLight {
                    entity: Entity::PLACEHOLDER,
                    direction: Vec3::NEG_Y,
                    irradiance: Vec3::ONE,
                };
                count
            ],
            ..default()
        };
        let cloud = ExtractedCloud::for_test(default());
        let fitted = |lights: &ExtractedCloudLights, n, max_binding| {
            at_resolution(&cloud, n, lights, max_binding).light_resolution
        };
        let mib_128 = 128 << 20;
        assert_eq!(cloud.settings.light_supersampling, 4);
        assert_eq!(fitted(&lights(5), 64, mib_128), 188);
        assert_eq!(fitted(&lights(1), 64, mib_128), 256);
        assert_eq!(fitted(&lights(5), 64, 1 << 30), 256);
        assert_eq!(fitted(&lights(5), 48, mib_128), 188);
        assert_eq!(fitted(&lights(4), 48, mib_128), 192);
        // More lights share the binding: ten get 149³ (132.3 MB), twenty 118³ (131.4 MB).
        assert_eq!(fitted(&lights(10), 48, mib_128), 149);
        assert_eq!(fitted(&lights(20), 48, mib_128), 118);
        // At 128³ three lights' volumes bound the grid: 3 × 223³ × 4 = 133.1 MB.
        assert_eq!(fitted(&lights(3), 128, mib_128), 223);
        // One light's fine density (its levels, about 8/7 of m³ floats, and the 128³ scattering
        // grid's) bounds it: about 300³, more than 64³ × 4 (the factor 2 it got before).
        let one = fitted(&lights(1), 128, mib_128);
        assert!((290..=310).contains(&one), "{one}");
        let at_128 = ExtractedCloud::for_test(CloudQualitySettings {
            volume_resolution: 128,
            ..default()
        });
        let shape_128 = |m| volume_shape(&at_128, &lights(1)).with_light_resolution(m);
        assert!(shape_128(one).max_slots(mib_128) >= 1);
        assert_eq!(shape_128(one + 1).max_slots(mib_128), 0);
        // Nothing fits: the scattering grid's side, and the allocation refuses the cloud with its
        // own warning.
        assert_eq!(fitted(&lights(1), 64, 1 << 20), 64);
        let lowered = at_resolution(&cloud, 64, &lights(5), mib_128);
        let lowered_shape = volume_shape(&lowered, &lights(5));
        assert_eq!((lowered_shape.n, lowered_shape.m), (64, 188));
        assert!(lowered_shape.max_slots(mib_128) >= 1);
    }
}
