use super::*;
use crate::reference::illumination::{scatter, single_scattering_at};
use std::f64::consts::PI;

use crate::math::henyey_greenstein;
use crate::reference::illumination::test_support::*;
use bevy::math::Vec3;

#[test]
fn zero_extinction_gives_unattenuated_light_everywhere() {
    let particles = random_cloud(20, 5);
    let medium = Medium {
        extinction: 0.0,
        albedo: 0.8,
        ..Default::default()
    };
    let lights = [
        LocalLight {
            direction: DVec3::new(0.0, -1.0, 0.0),
            irradiance: DVec3::new(2.0, 3.0, 4.0),
        },
        LocalLight {
            direction: DVec3::new(1.0, -1.0, 0.5),
            irradiance: DVec3::new(1.0, 0.0, 0.5),
        },
        LocalLight {
            direction: DVec3::X,
            irradiance: DVec3::ZERO,
        },
        LocalLight {
            direction: DVec3::ZERO,
            irradiance: DVec3::ONE,
        },
    ];
    let settings = CloudQualitySettings {
        volume_resolution: 8,
        light_supersampling: 2,
        ..Default::default()
    };
    let ill = illuminate(&particles, &medium, 2.0, &lights, &settings).unwrap();
    assert_eq!(
        ill.lights.len(),
        2,
        "zero irradiance and zero direction lights are skipped"
    );
    for (vol, _) in &ill.lights {
        assert_eq!(vol.n, 16);
        assert!(vol.optical_depth.iter().all(|&t| t == 0.0));
    }
    let expected = DVec3::new(3.0, 3.0, 4.5) / (4.0 * PI);
    for s in &ill.source.mean {
        assert!((*s - expected).length() < 1e-15);
    }
    // Nothing scatters twice in a medium that does not interact.
    assert!(ill.multiple.total.iter().all(|m| *m == DVec3::ZERO));
    for idx in [0, 77, 511] {
        let x = ill.grid.voxel_centre_linear(idx);
        assert!((ill.scattered_at(x, DVec3::Z) - expected * ill.albedo).length() < 1e-15);
    }
}

#[test]
fn illuminate_is_well_defined_without_lights_or_particles() {
    let settings = CloudQualitySettings {
        volume_resolution: 6,
        ..Default::default()
    };
    let medium = Medium::default();
    assert!(illuminate(&[], &medium, 1.0, &[], &settings).is_none());
    let particles = random_cloud(5, 1);
    let ill = illuminate(&particles, &medium, 1.0, &[], &settings).unwrap();
    assert!(ill.lights.is_empty());
    assert!(ill.multiple.total.iter().all(|a| *a == DVec3::ZERO));
    assert_eq!(ill.scattered_at(DVec3::ZERO, DVec3::Z), DVec3::ZERO);
}

#[test]
fn transmittance_at_centre_of_particle_matches_half_chord() {
    // tau at the centre of one particle lit from an oblique direction ~ K eta r 8/15.
    let p = particle(0.0, 0.0, 0.0, 1.0, 1.0);
    let grid = voxelize(&[p], 64).unwrap();
    let k = 2.0;
    let vol = shade(&grid, &inputs(k, 1.0, 0.0, 64), DVec3::new(0.4, -1.0, 0.3));
    let tau = vol.optical_depth_at(DVec3::ZERO);
    let expected = k * 8.0 / 15.0;
    assert!(
        (tau - expected).abs() < 0.01 * expected,
        "tau {tau} vs {expected}"
    );
}

#[test]
fn scattered_light_is_albedo_times_single_plus_multiple() {
    let particles = random_cloud(10, 9);
    let medium = Medium {
        extinction: 5.0,
        albedo: 0.7,
        ..Default::default()
    };
    let settings = CloudQualitySettings {
        volume_resolution: 8,
        scatter_iterations: 4,
        ..Default::default()
    };
    let light = LocalLight::from_world(
        &LightSample {
            direction: Vec3::new(0.0, -2.0, 0.0),
            irradiance: Vec3::ONE,
        },
        DQuat::from_rotation_z(0.3),
    );
    assert!((light.direction.length() - 1.0).abs() < 1e-12);
    let ill = illuminate(&particles, &medium, 1.5, &[light], &settings).unwrap();
    assert_eq!(ill.k_local, 7.5);
    // At a voxel centre the multiple part is that voxel's value.
    let idx = ill.grid.index(3, 4, 5);
    let x = ill.grid.voxel_centre(3, 4, 5);
    let expected = (single_scattering_at(&ill.lights, x) + ill.multiple.total[idx]) * ill.albedo;
    assert!((ill.scattered_at(x, DVec3::X) - expected).length() < 1e-12 * expected.length());
    assert!(
        ill.multiple
            .total
            .iter()
            .all(|a| a.is_finite() && a.min_element() >= 0.0)
    );
}

/// A Henyey–Greenstein medium: single scattering takes the phase function towards the
/// camera (forward: the camera looks into the light) and sees the optical depths through the
/// δ-M depth scale `1 - albedo g³`; the multiple scattering is seen through the phase
/// function's first three moments. `g = 0` is the isotropic medium exactly.
#[test]
fn anisotropic_medium_sees_single_and_multiple_scattering_with_its_phase_function() {
    let particles = random_cloud(12, 4);
    let medium = Medium {
        extinction: 6.0,
        albedo: 0.9,
        anisotropy: 0.7,
    };
    let settings = CloudQualitySettings {
        volume_resolution: 8,
        scatter_iterations: 5,
        scatter_coarse_cycles: 0,
        ..Default::default()
    };
    let light = LocalLight {
        direction: DVec3::new(0.3, -1.0, 0.2).normalize(),
        irradiance: DVec3::new(1.0, 0.9, 0.8),
    };
    let ill = illuminate(&particles, &medium, 1.0, &[light], &settings).unwrap();
    let x = ill.grid.voxel_centre(4, 3, 4);
    let scale = DeltaM::new(ill.albedo, ill.anisotropy).depth_scale;
    assert!((scale - (1.0 - 0.9 * 0.343)).abs() < 1e-6);
    let (vol, e) = &ill.lights[0];
    let tau = vol.optical_depth_at(x);
    let table = ill.beam.as_ref().expect("g > 0 truncates the peak");
    // The beam that never scattered, and its excess spread by the peak scatterings.
    let beam = |cos| {
        let excess = (-tau * scale).exp() - (-tau).exp();
        *e * ((-tau).exp() + excess * table.ratio(cos, tau * (1.0 - scale)))
    };
    let m = &ill.multiple;
    let (mean, flux, quadrupole) = (
        ill.grid.sample_clamped(&m.total, x),
        ill.grid.sample_clamped_array(&m.flux, x),
        ill.grid.sample_clamped_array(&m.quadrupole, x),
    );
    for (ray, cos) in [(-light.direction, 1.0), (light.direction, -1.0)] {
        let (w, g) = (-ray, ill.anisotropy);
        let seen = (mean
            + flux_along(&flux, w) * (3.0 * g)
            + quadrupole_along(&quadrupole, w) * (7.5 * g * g))
            .max(DVec3::ZERO);
        assert_eq!(ill.multiple_towards(x, w), seen);
        let expected = (beam(cos) * henyey_greenstein(ill.anisotropy, cos) + seen) * ill.albedo;
        let got = ill.scattered_at(x, ray);
        assert!(
            (got - expected).length() < 1e-12 * expected.length(),
            "cos {cos}: {got} against {expected}"
        );
    }
    // The multiply scattered light flows on with the light: more of it is seen looking into
    // the light than from where it comes.
    assert!(
        ill.multiple_towards(x, light.direction).x > ill.multiple_towards(x, -light.direction).x
    );
    assert!(
        ill.scattered_at(x, -light.direction).x > 10.0 * ill.scattered_at(x, light.direction).x
    );
    let isotropic = Medium {
        anisotropy: 0.0,
        ..medium
    };
    let iso = illuminate(&particles, &isotropic, 1.0, &[light], &settings).unwrap();
    assert!(iso.source.flux.is_empty() && iso.multiple.flux.is_empty());
    assert!(iso.multiple.quadrupole.is_empty() && iso.beam.is_none());
    let plain = scatter(
        &iso.grid,
        iso.k_local,
        iso.albedo,
        settings.scatter_stencil,
        &iso.source.mean,
        5,
    );
    assert_eq!(iso.multiple, plain);
    for ray in [DVec3::X, -light.direction] {
        let expected = (single_scattering_at(&iso.lights, x)
            + iso.grid.sample_clamped(&iso.multiple.total, x))
            * iso.albedo;
        assert!((iso.scattered_at(x, ray) - expected).length() < 1e-15 * expected.length());
    }
    assert_eq!(
        DeltaM::new(0.9, 0.0),
        DeltaM {
            depth_scale: 1.0,
            albedo: 0.9,
            anisotropy: 0.0,
            second_moment: 0.0
        }
    );
}
