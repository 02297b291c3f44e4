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
            centre: Vec3::ZERO,
            side: 2.0,
            max_radius: 0.1,
            max_density: 2.0,
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
}
