//! The sky lights the clouds (docs/illumination.md §4): a uniform radiance enters the
//! multiple-scattering grid from every side in the first iteration of the series.

use bevy::prelude::*;
use bevy_particle_clouds::{CloudPass, Medium, reference::metrics::relative_rmse};

use crate::draw::{Setup, assert_images_match, cloud_setup, reference, render};

const SKY: Vec3 = Vec3::new(0.3, 0.45, 0.7);

/// The draw tests' cloud seen against the sky it is lit by, with no directional light.
fn sky_setup(albedo: f32) -> Setup {
    sky_setup_scattering(albedo, 0.0)
}

/// [`sky_setup`] in a medium of Henyey–Greenstein anisotropy `g`.
fn sky_setup_scattering(albedo: f32, anisotropy: f32) -> Setup {
    let camera = Transform::from_xyz(0.3, 0.4, 4.0).looking_at(Vec3::ZERO, Vec3::Y);
    let mut setup = cloud_setup(21, camera);
    setup.lights.clear();
    setup.medium = Medium {
        extinction: 4.0,
        albedo,
        anisotropy,
    };
    setup.background = SKY;
    setup.sky = SKY;
    setup
}

/// Under a sky, with a light and without one, both compositings: the GPU image equals the CPU
/// reference's.
#[test]
fn a_sky_lit_cloud_equals_the_cpu_billboard_reference() {
    for compositing in [
        bevy_particle_clouds::Compositing::ViewTransmittance,
        bevy_particle_clouds::Compositing::Sorted,
    ] {
        for with_sun in [false, true] {
            let mut setup = sky_setup(0.9);
            if with_sun {
                setup.lights = cloud_setup(21, setup.camera).lights;
            }
            setup.settings.compositing = compositing;
            let (_, _, gpu) = render(&setup);
            let what = format!("sky, sun {with_sun}, {compositing:?}");
            assert_images_match(&gpu.image, &reference(&setup), &what);
        }
    }
}

/// The furnace: albedo 1 under a uniform sky and no light. Every path ends in the sky, so the
/// exact answer is the sky in every pixel, cloud or not (the path tracer's furnace test), whatever
/// the phase function. The real-time image keeps the sky within the grid's and the closure's
/// error, isotropic or scattering forward (its moments vanish); an absorbing cloud (albedo 0.5)
/// darkens it.
#[test]
fn an_albedo_one_cloud_under_a_uniform_sky_almost_vanishes() {
    for anisotropy in [0.0, 0.8] {
        furnace(anisotropy);
    }
}

fn furnace(anisotropy: f32) {
    let (_, _, white) = render(&sky_setup_scattering(1.0, anisotropy));
    let sky: Vec<[f32; 4]> = white
        .image
        .pixels
        .iter()
        .map(|_| [SKY.x, SKY.y, SKY.z, 1.0])
        .collect();
    let rgb = |p: &[[f32; 4]]| {
        p.iter()
            .map(|c| [c[0], c[1], c[2], 1.0])
            .collect::<Vec<_>>()
    };
    let error = relative_rmse(&rgb(&white.image.pixels), &sky);
    let (_, _, grey) = render(&sky_setup_scattering(0.5, anisotropy));
    let darkening = relative_rmse(&rgb(&grey.image.pixels), &sky);
    eprintln!(
        "furnace, g = {anisotropy}: albedo 1 differs from the sky by {error:.4}, albedo 0.5 by \
         {darkening:.4}"
    );
    assert!(
        error < 0.02,
        "albedo 1 under the sky: relative RMSE {error}"
    );
    assert!(
        darkening > 10.0 * error,
        "albedo 0.5 hardly darkens: {darkening}"
    );
}

/// The sky costs no pass: illuminating a cloud takes exactly the dispatches under a blue sky that
/// it takes under a black one (the sky is a value in the sweep's uniform).
#[test]
fn the_sky_adds_no_dispatch() {
    let dispatches = |sky: Vec3| {
        let mut setup = sky_setup(0.9);
        setup.lights = cloud_setup(21, setup.camera).lights;
        setup.sky = sky;
        let (_, _, render) = render(&setup);
        [
            CloudPass::Voxelize,
            CloudPass::Shade,
            CloudPass::Gather,
            CloudPass::Scatter,
        ]
        .map(|pass| {
            render
                .frames
                .frames
                .iter()
                .map(|f| f.dispatches(pass))
                .sum::<u32>()
        })
    };
    let (black, blue) = (dispatches(Vec3::ZERO), dispatches(SKY));
    assert!(black.iter().sum::<u32>() > 0);
    assert_eq!(black, blue, "dispatches per pass, black sky against blue");
}
