//! The reduced-resolution cloud target (the paper's §4 fill-rate optimisation): the GPU's
//! depth-aware upsample against its CPU reference, and the image drawn at half size against the
//! full-size one where objects cut the cloud.

use bevy::{
    prelude::*,
    render::{
        render_resource::{Texture, TextureFormat, TextureUsages},
        view::{Msaa, ViewDepthTexture},
    },
};
use bevy_particle_clouds::{
    Compositing, ParticleCloud,
    fog::{Falloff, Fog},
    headless::{self, FrameRecorder, f16_to_f32, floats},
    image_io::LinearImage,
    reference::{cloud_target::CloudTargetImage, metrics::relative_rmse},
    render::cloud_target::{ViewCloudTarget, ViewCloudTargetResources},
    scene::{ObjectShape, SceneObject},
};

use crate::{
    common,
    draw::{H, Setup, W, cloud_setup, render, spawn},
};

const FRONT: Vec3 = Vec3::new(0.9, 0.1, 0.1);
const BACK: Vec3 = Vec3::new(0.1, 0.9, 0.1);

/// A smooth cloud with a small box in front of it and a wall behind it: edges of both kinds.
pub(crate) fn occluded_setup(compositing: Compositing, scale: f32) -> Setup {
    let camera = Transform::from_xyz(0.0, 0.0, 5.0).looking_at(Vec3::ZERO, Vec3::Y);
    let mut setup = cloud_setup(3, camera);
    // Big, overlapping particles: a smooth cloud, whose image a half-size target loses little of,
    // so that any error at the objects' edges stands out.
    for particle in &mut setup.particles {
        particle.radius = 0.6;
        particle.density *= 0.3;
    }
    setup.objects = vec![
        SceneObject {
            shape: ObjectShape::Cuboid(Vec3::new(0.4, 0.4, 0.1)),
            translation: Vec3::new(-0.3, 0.0, 2.0),
            color: FRONT,
            reflectance: Vec3::ZERO,
        },
        SceneObject {
            shape: ObjectShape::Cuboid(Vec3::new(1.5, 3.0, 0.1)),
            translation: Vec3::new(0.6, 0.0, -1.2),
            color: BACK,
            reflectance: Vec3::ZERO,
        },
    ];
    setup.settings.compositing = compositing;
    setup.settings.cloud_target_scale = scale;
    setup
}

/// The view's cloud target texture, its parameters and the view's depth texture.
pub(crate) fn view_textures(app: &mut App) -> (ViewCloudTarget, Texture, Texture) {
    common::with_render_world(app, |world| {
        let mut views = world.query::<(
            &ViewCloudTarget,
            &ViewCloudTargetResources,
            &ViewDepthTexture,
        )>();
        let (target, resources, depth) = views.single(world).expect("one view with a cloud target");
        (
            *target,
            resources.texture.texture.clone(),
            depth.texture.clone(),
        )
    })
}

/// The texels of a cloud target read back in `format` (f16 or f32 RGBA).
pub(crate) fn target_texels(bytes: &[u8], format: TextureFormat) -> Vec<[f32; 4]> {
    match format {
        TextureFormat::Rgba16Float => bytes
            .chunks_exact(8)
            .map(|t| {
                std::array::from_fn(|c| f16_to_f32(u16::from_le_bytes([t[2 * c], t[2 * c + 1]])))
            })
            .collect(),
        TextureFormat::Rgba32Float => floats(bytes)
            .chunks_exact(4)
            .map(|t| [t[0], t[1], t[2], t[3]])
            .collect(),
        other => panic!("a cloud target in {other:?}"),
    }
}

#[test]
fn the_composite_equals_the_cpu_upsample_of_the_target_it_drew() {
    for compositing in [Compositing::ViewTransmittance, Compositing::Sorted] {
        let setup = occluded_setup(compositing, 0.5);
        let (mut app, target) = spawn(&setup);
        // The test reads the view's depth back.
        let mut camera = app.world_mut().entity_mut(target.camera);
        let mut camera = camera.get_mut::<Camera3d>().unwrap();
        camera.depth_texture_usages.0 |= TextureUsages::COPY_SRC.bits();
        let mut frames = FrameRecorder::default();
        headless::render_until_steady(&mut app, &mut frames, 1, 20).unwrap();
        let shown = headless::capture(&mut app, &mut frames, &target.image).unwrap();
        let (target_view, texture, depth) = view_textures(&mut app);
        let params = target_view.params;
        // Sorted clouds are rasterised into the target: in f32 where the adapter blends it.
        let format = texture.format();
        assert_eq!(format, target_view.format);
        assert_eq!(params.target_size, UVec2::new(W / 2, H / 2));
        let texels = target_texels(&headless::read_texture(&mut app, &texture).unwrap(), format);
        let depth = floats(&headless::read_texture(&mut app, &depth).unwrap());
        // What is behind the cloud: the same view with the cloud hidden.
        let cloud = app
            .world_mut()
            .query_filtered::<Entity, With<ParticleCloud>>()
            .single(app.world())
            .unwrap();
        app.world_mut().entity_mut(cloud).insert(Visibility::Hidden);
        let behind = headless::capture(&mut app, &mut frames, &target.image).unwrap();

        let image = CloudTargetImage {
            texels: &texels,
            size: params.target_size,
            scale: params.scale,
            viewport: (params.viewport_origin, params.viewport_size),
            depth_tolerance: params.depth_tolerance,
        };
        let depth_at = |p: UVec2| depth[(p.y * W + p.x) as usize];
        let mut worst = 0.0f32;
        let mut worst_at = String::new();
        let mut covered = 0;
        for y in 0..H {
            for x in 0..W {
                let i = (y * W + x) as usize;
                let expected = image.over(UVec2::new(x, y), depth_at, behind.pixels[i]);
                let got = shown.pixels[i];
                for c in 0..3 {
                    // f16 target and output: 2^-11 relative per rounding; and the blender may
                    // round the composite's alpha to f16 towards zero (NVIDIA does), which moves
                    // what shows through by one ulp of alpha (2^-11 below 1) of what is behind.
                    let alpha_ulp = 2f32.powi(-11) * behind.pixels[i][c].abs();
                    let difference = ((got[c] - expected[c]).abs() - alpha_ulp).max(0.0)
                        / expected[c].abs().max(0.05);
                    if difference > worst {
                        worst = difference;
                        worst_at = format!(
                            "({x}, {y}) channel {c}: got {}, expected {}, behind {}, cloud {:?}",
                            got[c],
                            expected[c],
                            behind.pixels[i][c],
                            image.upsample(UVec2::new(x, y), depth_at)
                        );
                    }
                }
                covered += usize::from(image.upsample(UVec2::new(x, y), depth_at)[3] > 0.1);
            }
        }
        eprintln!(
            "{compositing:?}: worst relative difference {worst:e} at {worst_at}, {covered} cloudy pixels"
        );
        assert!(
            covered > 100,
            "{compositing:?}: the cloud covers {covered} pixels"
        );
        // About six f16 roundings, beyond alpha's.
        assert!(
            worst < 3e-3,
            "{compositing:?}: the composite differs from its CPU reference by {worst}"
        );
    }
}

/// The image at half size against the one at full size. Nothing bleeds onto the object in front
/// of the cloud: it keeps its exact colour. No halo surrounds it: next to its edges the half-size
/// image errs no more than it does elsewhere in the cloud (where it errs by its resolution alone).
#[test]
fn at_half_size_objects_in_front_stay_clean_and_their_edges_have_no_halo() {
    for compositing in [Compositing::ViewTransmittance, Compositing::Sorted] {
        let (_, _, full) = render(&occluded_setup(compositing, 1.0));
        let (_, _, half) = render(&occluded_setup(compositing, 0.5));
        let mut bare = occluded_setup(compositing, 1.0);
        bare.medium.extinction = 0.0;
        let bare = render_without_cloud(&bare);
        let at = |x: i32, y: i32| (y * W as i32 + x) as usize;
        let on_front = |p: [f32; 4]| (p[0] - FRONT.x).abs() < 1e-3 && (p[1] - FRONT.y).abs() < 1e-3;
        let front = |x: i32, y: i32| {
            (0..W as i32).contains(&x)
                && (0..H as i32).contains(&y)
                && on_front(bare.pixels[at(x, y)])
        };
        let (mut ring, mut rest) = (Vec::new(), Vec::new());
        let mut front_pixels = 0;
        for y in 0..H as i32 {
            for x in 0..W as i32 {
                let (f, h, b) = (
                    full.image.pixels[at(x, y)],
                    half.image.pixels[at(x, y)],
                    bare.pixels[at(x, y)],
                );
                if front(x, y) {
                    front_pixels += 1;
                    assert!(
                        on_front(h),
                        "{compositing:?}: cloud bled onto the front object at {x},{y}: {h:?}"
                    );
                    continue;
                }
                let cloudy = (0..3).any(|c| (f[c] - b[c]).abs() > 0.02);
                if !cloudy {
                    continue;
                }
                let error = (0..3).map(|c| (h[c] - f[c]).abs()).sum::<f32>() / 3.0;
                let near_edge = (-2..=2).any(|dy| (-2..=2).any(|dx| front(x + dx, y + dy)));
                if near_edge {
                    ring.push(error)
                } else {
                    rest.push(error)
                }
            }
        }
        let mean = |v: &[f32]| v.iter().sum::<f32>() / v.len() as f32;
        let (ring_error, rest_error) = (mean(&ring), mean(&rest));
        eprintln!(
            "{compositing:?}: half size errs {ring_error:.4} by the front object's edge ({} px), {rest_error:.4} elsewhere in the cloud ({} px)",
            ring.len(),
            rest.len()
        );
        assert!(
            front_pixels > 10 && ring.len() > 10,
            "the front object cuts the cloud"
        );
        // Measured: 0.6 of the error elsewhere; 1.2 with a plain bilinear upsample, 1.15 when sky
        // slivers between two objects took the nearer object's empty texel.
        assert!(
            ring_error < rest_error,
            "{compositing:?}: a halo: {ring_error} by the edge, {rest_error} elsewhere"
        );
    }
}

/// A fogged view drawn at half size (the cloud target's one `accumulate` draw) takes the fog as
/// the full-size draw does: the half-size image stays close to the full-size one, while the
/// same clouds unfogged differ far more. No objects, and the background is not fogged: only the
/// clouds' fog shows.
#[test]
fn a_fogged_cloud_drawn_at_half_size_takes_the_fog() {
    let fog = Fog {
        color: Vec3::new(0.3, 0.35, 0.4),
        alpha: 1.0,
        falloff: Falloff::Exponential { density: 0.2 },
        directional_light_color: Vec3::new(0.4, 0.3, 0.2),
        directional_light_exponent: 2.0,
    };
    let image = |scale: f32, fog: Option<Fog>| {
        let mut setup = occluded_setup(Compositing::ViewTransmittance, scale);
        setup.objects.clear();
        setup.fog = fog;
        render(&setup).2.image.pixels
    };
    let full = image(1.0, Some(fog));
    let half = image(0.5, Some(fog));
    let half_unfogged = image(0.5, None);
    let (error, unfogged) = (
        relative_rmse(&half, &full),
        relative_rmse(&half_unfogged, &full),
    );
    eprintln!("half size against full size, fogged: {error:.4}; unfogged: {unfogged:.4}");
    assert!(
        error < 0.05,
        "the fogged half-size image differs by {error}"
    );
    assert!(
        unfogged > 4.0 * error,
        "the fog changes the half-size image too little: {unfogged} against {error}"
    );
}

/// The setup's objects and background alone (its cloud has no extinction, so draws nothing).
fn render_without_cloud(setup: &Setup) -> LinearImage {
    let (mut app, target) = spawn(setup);
    let mut frames = FrameRecorder::default();
    for _ in 0..3 {
        frames.frame(&mut app).unwrap();
    }
    headless::capture(&mut app, &mut frames, &target.image).unwrap()
}

/// With MSAA the view's depth is multisampled: the billboards and the composite read its first
/// sample. The image matches the one without MSAA but at the objects' antialiased edges.
#[test]
fn a_multisampled_view_draws_the_same_clouds() {
    let setup = occluded_setup(Compositing::ViewTransmittance, 0.5);
    let images = [Msaa::Off, Msaa::Sample4].map(|msaa| {
        let (mut app, target) = spawn(&setup);
        app.world_mut().entity_mut(target.camera).insert(msaa);
        let mut frames = FrameRecorder::default();
        headless::render_until_steady(&mut app, &mut frames, 1, 20).unwrap();
        let image = headless::capture(&mut app, &mut frames, &target.image).unwrap();
        let multisampled = common::with_render_world(&mut app, |world| {
            let mut views = world.query::<&ViewCloudTarget>();
            views.single(world).expect("a cloud target").multisampled
        });
        assert_eq!(multisampled, msaa != Msaa::Off);
        image
    });
    // Away from the objects' edges (within the 2 pixels a texel spans, and one for MSAA's
    // blending): there the depth sample of a texel's pixel moves to its first sample.
    let mut bare = setup;
    bare.medium.extinction = 0.0;
    let bare = render_without_cloud(&bare);
    let at =
        |x: i32, y: i32| (y.clamp(0, H as i32 - 1) * W as i32 + x.clamp(0, W as i32 - 1)) as usize;
    let edge = |x: i32, y: i32| {
        let here = bare.pixels[at(x, y)];
        [(1, 0), (0, 1)].iter().any(|(dx, dy)| {
            let there = bare.pixels[at(x + dx, y + dy)];
            (0..3).any(|c| (there[c] - here[c]).abs() > 1e-3)
        })
    };
    let (mut compared, mut worst) = (0, 0.0f32);
    for y in 0..H as i32 {
        for x in 0..W as i32 {
            if (-3..=3).any(|dy| (-3..=3).any(|dx| edge(x + dx, y + dy))) {
                continue;
            }
            compared += 1;
            for c in 0..3 {
                let d = (images[1].pixels[at(x, y)][c] - images[0].pixels[at(x, y)][c]).abs();
                worst = worst.max(d);
            }
        }
    }
    eprintln!("MSAA against none: worst {worst:e} over {compared} pixels");
    assert!(compared > 500, "{compared} pixels compared");
    assert!(worst < 2e-3, "MSAA changes the clouds by {worst}");
}
