//! Lit objects under clouds (docs/illumination.md §10): the cloud shadow map and the sky map
//! against the CPU reference texel by texel, and a Lambertian ground's every pixel against the
//! shading the CPU reference gives it through those maps; the map is filled again only when a
//! cloud moves.

use bevy::render::storage::GpuShaderBuffer;
use bevy::{prelude::*, render::render_asset::RenderAssets};
use bevy_particle_clouds::{
    CloudPass, CloudShadowMaps, LightSample, Particle,
    cloud_shadowed_material::{CloudShadowReceiver, CloudShadowedMaterial},
    headless::{self, FrameRecorder},
    reference::{
        camera::PinholeCamera,
        composite::CloudPlacement,
        geometry::nearest_object,
        illumination::{
            CloudIllumination, PlacedCloud, cloud_shadow_map, illuminate_clouds_under_sky,
            shadow_map_depth_at, sky_occlusion_map,
        },
        metrics::{max_relative_difference, relative_rmse},
    },
    render::shadow_maps::BAND_ROWS,
    scene::{ObjectShape, SceneObject},
    shadow_maps::ShadowMapPlacement,
};

use bevy_particle_clouds::fog::{Falloff, Fog};
use bevy_particle_clouds::linear_image::LinearImage;

use crate::common;
use crate::draw::{FOV, H, Setup, SetupCloud, W, cloud_setup, spawn_into};
use crate::illumination::TOLERANCE;

const REFLECTANCE: Vec3 = Vec3::new(0.5, 0.6, 0.7);
const EMITTED: Vec3 = Vec3::new(0.01, 0.01, 0.02);

/// A cloud high above a Lambertian ground, out of the camera's view, its shadow on the ground in
/// view; a sky.
fn cloud_over_ground() -> Setup {
    let camera = Transform::from_xyz(0.0, 0.6, 4.5).looking_at(Vec3::new(-0.6, 0.0, -0.3), Vec3::Y);
    let mut setup = cloud_setup(41, camera);
    setup.transform = Transform::from_xyz(0.2, 3.5, 0.0);
    setup.lights = vec![LightSample {
        direction: Vec3::new(-0.3, -1.0, -0.2),
        irradiance: Vec3::new(2.0, 1.8, 1.5),
    }];
    setup.sky = Vec3::new(0.1, 0.15, 0.25);
    setup.background = setup.sky;
    setup.objects = vec![SceneObject {
        shape: ObjectShape::Cuboid(Vec3::new(20.0, 1.0, 20.0)),
        translation: Vec3::new(0.0, -0.5, 0.0),
        color: EMITTED,
        reflectance: REFLECTANCE,
    }];
    setup
}

/// The setup spawned with cloud shadow maps of `resolution` texels per side.
fn spawn_with_maps(setup: &Setup, resolution: u32) -> (App, headless::SceneTarget) {
    let mut app = common::headless_app();
    headless::enable_cloud_shadow_maps(&mut app, resolution, setup.lights.len());
    spawn_into(app, setup, &[setup.cloud()])
}

/// The GPU's shadow map of the first light, and its placement.
fn gpu_map(app: &mut App) -> (Vec<f64>, ShadowMapPlacement) {
    let maps = app.world().resource::<CloudShadowMaps>().clone();
    gpu_values(app, maps.maps[0].1)
}

/// How far the GPU's sky map may lie from the CPU's, in fractions of the sky's irradiance: f32
/// sums of 32 transmittances, and a ray that grazes a cloud's box may take one more or one fewer
/// step on the GPU than in f64.
const SKY_TOLERANCE: f64 = 1e-4;

/// The largest difference between two sky maps, in fractions of the sky's irradiance (its
/// texels are those fractions already, so no maximum scales it).
fn sky_map_error(gpu: &[f64], cpu: &[f64]) -> f64 {
    let error = gpu
        .iter()
        .zip(cpu)
        .map(|(g, c)| (g - c).abs())
        .fold(0.0, f64::max);
    eprintln!("sky map: {error:e} of the sky against the CPU reference");
    error
}

/// The GPU's sky map, and its placement.
fn gpu_sky_map(app: &mut App) -> (Vec<f64>, ShadowMapPlacement) {
    let maps = app.world().resource::<CloudShadowMaps>().clone();
    gpu_values(app, maps.sky.expect("a sky map under the sky"))
}

/// What the maps' buffer holds in the map placed as `placement`.
fn gpu_values(app: &mut App, placement: ShadowMapPlacement) -> (Vec<f64>, ShadowMapPlacement) {
    let maps = app.world().resource::<CloudShadowMaps>().clone();
    let buffer = common::with_render_world(app, |world| {
        let buffers = world.resource::<RenderAssets<GpuShaderBuffer>>();
        buffers
            .get(&maps.buffer)
            .expect("the maps' buffer")
            .buffer
            .clone()
    });
    let bytes = headless::read_buffer(app, &buffer).unwrap();
    let texels = (placement.size * placement.size) as usize;
    let values = headless::floats(&bytes)[placement.first as usize..][..texels]
        .iter()
        .map(|&v| v as f64)
        .collect();
    (values, placement)
}

/// The CPU reference of the first light's shadow map of `setup`'s cloud, placed as `map`.
fn cpu_shadow_map(setup: &Setup, map: &ShadowMapPlacement) -> Vec<f64> {
    let (cloud, placement) = cpu_cloud(setup);
    cloud_shadow_map(&[(&cloud, placement)], 0, map)
}

/// The CPU reference of the sky map of `setup`'s cloud, placed as `map`.
fn cpu_sky_map(setup: &Setup, map: &ShadowMapPlacement) -> Vec<f64> {
    let (cloud, placement) = cpu_cloud(setup);
    sky_occlusion_map(&[(&cloud, placement)], map)
}

/// The CPU reference of `setup`'s cloud, and where it lies.
fn cpu_cloud(setup: &Setup) -> (CloudIllumination, CloudPlacement) {
    let placement = CloudPlacement {
        translation: setup.transform.translation.as_dvec3(),
        rotation: setup.transform.rotation.as_dquat(),
        scale: 1.0,
    };
    let placed = [PlacedCloud {
        particles: &setup.particles,
        medium: setup.medium,
        placement,
        settings: setup.settings,
    }];
    let mut cpu = illuminate_clouds_under_sky(&placed, &setup.lights, setup.sky.as_dvec3());
    let cloud = cpu.remove(0).expect("a cloud with density");
    (cloud, placement)
}

/// The setup's camera, as the CPU reference sees it.
fn pinhole(setup: &Setup) -> PinholeCamera {
    let eye = setup.camera.translation.as_dvec3();
    PinholeCamera::looking_at(
        eye,
        eye + setup.camera.forward().as_vec3().as_dvec3(),
        setup.camera.up().as_vec3().as_dvec3(),
        FOV as f64,
        W,
        H,
    )
}

#[test]
fn a_lit_ground_takes_the_clouds_shadow_as_the_cpu_reference_does() {
    lit_ground_matches_the_cpu_reference(None);
}

/// In `DistanceFog`, the lit ground is fogged as Bevy fogs its meshes (`apply_fog`), glow
/// included: `L V(d) + A(d) F`.
#[test]
fn a_lit_ground_in_fog_is_fogged_like_bevys_meshes() {
    lit_ground_matches_the_cpu_reference(Some(Fog {
        color: Vec3::new(0.3, 0.32, 0.35),
        alpha: 1.0,
        falloff: Falloff::Exponential { density: 0.12 },
        directional_light_color: Vec3::new(0.5, 0.4, 0.3),
        directional_light_exponent: 1.5,
    }));
}

fn lit_ground_matches_the_cpu_reference(fog: Option<Fog>) {
    let mut setup = cloud_over_ground();
    setup.fog = fog;
    let (mut app, target) = spawn_with_maps(&setup, 96);
    let mut recorder = FrameRecorder::default();
    headless::render_until_steady(&mut app, &mut recorder, 1, 20).unwrap();
    let image = headless::capture(&mut app, &mut recorder, &target.image).unwrap();
    let drawn = recorder.frames.last().unwrap().runs(CloudPass::Draw);
    assert_eq!(drawn, 0, "the cloud is out of view");

    // The map, texel by texel.
    let (gpu, map) = gpu_map(&mut app);
    let cpu_map = cpu_shadow_map(&setup, &map);
    let error = max_relative_difference(&gpu, &cpu_map);
    assert!(error <= TOLERANCE, "shadow map: {error:e} of its maximum");
    let (gpu_sky, sky_map) = gpu_sky_map(&mut app);
    let cpu_sky = cpu_sky_map(&setup, &sky_map);
    let error = sky_map_error(&gpu_sky, &cpu_sky);
    let hidden = cpu_sky.iter().copied().fold(0.0, f64::max);
    assert!(error <= SKY_TOLERANCE, "sky map: {error:e} of the sky");
    assert!(hidden > 0.02, "the cloud hides the sky: {hidden}");

    // Every ground pixel: its colour plus R / pi (E cos T + pi L_sky V), T and V through the
    // CPU's maps.
    let eye = setup.camera.translation.as_dvec3();
    let camera = pinhole(&setup);
    let light = &setup.lights[0];
    let to_light = -light.direction.normalize().as_dvec3();
    let (mut expected, mut seen, mut darkest) = (Vec::new(), Vec::new(), 1.0f64);
    for py in 0..H {
        for px in 0..W {
            let ray = camera.pixel_ray(px, py);
            let Some((t, _)) = nearest_object(&setup.objects, eye, ray) else {
                continue;
            };
            let x = eye + ray * t;
            let transmittance = (-shadow_map_depth_at(&map, &cpu_map, x)).exp();
            darkest = darkest.min(transmittance);
            let visible = 1.0 - shadow_map_depth_at(&sky_map, &cpu_sky, x);
            let e = light.irradiance.as_dvec3() * (to_light.y * transmittance)
                + setup.sky.as_dvec3() * (std::f64::consts::PI * visible);
            let mut l = EMITTED.as_dvec3() + REFLECTANCE.as_dvec3() * e / std::f64::consts::PI;
            if let Some(fog) = &setup.fog {
                l = fog.apply(
                    l,
                    1.0,
                    t,
                    fog.colour_towards(ray, [(to_light, light.irradiance.as_dvec3())]),
                );
            }
            expected.push([l.x as f32, l.y as f32, l.z as f32, 1.0]);
            let g = image.pixels[(py * W + px) as usize];
            seen.push([g[0], g[1], g[2], 1.0]);
        }
    }
    assert!(
        expected.len() > (W * H / 3) as usize,
        "the ground fills the view"
    );
    assert!(darkest < 0.3, "the cloud's shadow falls in view: {darkest}");
    let error = relative_rmse(&seen, &expected);
    // f16 output, and f32 positions interpolated across the ground.
    eprintln!("lit ground: relative RMSE {error:e} against the CPU shading");
    assert!(error < 3e-3, "lit ground: relative RMSE {error}");
}

/// Clouds far apart across the light: the map is cast in bands of rows, each with the clouds
/// that cross it, and still matches the CPU reference texel by texel; a cloud's shadow is not
/// lost where it crosses a band's edge.
#[test]
fn a_map_of_clouds_apart_matches_the_cpu_reference() {
    let setup = cloud_over_ground();
    let apart = [
        setup.transform,
        Transform::from_xyz(-7.0, 3.0, 8.0).with_rotation(Quat::from_rotation_y(1.1)),
        Transform::from_xyz(6.0, 4.0, -5.0),
    ];
    let clouds: Vec<SetupCloud> = apart
        .iter()
        .map(|&transform| SetupCloud {
            transform,
            ..setup.cloud()
        })
        .collect();
    let mut app = common::headless_app();
    headless::enable_cloud_shadow_maps(&mut app, 160, setup.lights.len());
    let (mut app, _) = spawn_into(app, &setup, &clouds);
    let mut recorder = FrameRecorder::default();
    headless::render_until_steady(&mut app, &mut recorder, 1, 20).unwrap();
    let (gpu, map) = gpu_map(&mut app);
    assert!(map.size.div_ceil(BAND_ROWS) >= 8, "the map has bands");

    let placements: Vec<CloudPlacement> = apart
        .iter()
        .map(|t| CloudPlacement {
            translation: t.translation.as_dvec3(),
            rotation: t.rotation.as_dquat(),
            scale: 1.0,
        })
        .collect();
    let placed: Vec<PlacedCloud> = placements
        .iter()
        .map(|&placement| PlacedCloud {
            particles: &setup.particles,
            medium: setup.medium,
            placement,
            settings: setup.settings,
        })
        .collect();
    let cpu = illuminate_clouds_under_sky(&placed, &setup.lights, setup.sky.as_dvec3());
    let lit: Vec<_> = cpu
        .iter()
        .zip(&placements)
        .map(|(c, &p)| (c.as_ref().expect("a cloud with density"), p))
        .collect();
    let cpu_map = cloud_shadow_map(&lit, 0, &map);
    let error = max_relative_difference(&gpu, &cpu_map);
    assert!(error <= TOLERANCE, "shadow map: {error:e} of its maximum");
    // The sky map sums the three clouds' optical depths along each direction.
    let (gpu_sky, sky_map) = gpu_sky_map(&mut app);
    let error = sky_map_error(&gpu_sky, &sky_occlusion_map(&lit, &sky_map));
    assert!(error <= SKY_TOLERANCE, "sky map: {error:e} of the sky");
    // Some bands hold no cloud's shadow, others do.
    let band_holds = |b: u32| {
        let rows = (b * BAND_ROWS) as usize..((b + 1) * BAND_ROWS).min(map.size) as usize;
        let n = map.size as usize;
        cpu_map[rows.start * n..rows.end * n]
            .iter()
            .any(|&t| t > 1e-3)
    };
    let holding = (0..map.size.div_ceil(BAND_ROWS))
        .filter(|&b| band_holds(b))
        .count();
    assert!(
        holding > 1 && holding < map.size.div_ceil(BAND_ROWS) as usize,
        "{holding} bands hold a shadow"
    );
}

#[test]
fn a_still_sky_fills_the_map_once_and_a_moving_cloud_again() {
    let setup = cloud_over_ground();
    let (mut app, _) = spawn_with_maps(&setup, 64);
    let mut recorder = FrameRecorder::default();
    headless::render_until_steady(&mut app, &mut recorder, 1, 20).unwrap();
    let dispatches = |recorder: &FrameRecorder, from: usize, pass: CloudPass| -> u32 {
        recorder.frames[from..]
            .iter()
            .map(|f| f.dispatches(pass))
            .sum()
    };
    // Still: nothing.
    let first = recorder.frames.len();
    for _ in 0..3 {
        recorder.frame(&mut app).unwrap();
    }
    assert_eq!(dispatches(&recorder, first, CloudPass::Shade), 0);
    assert_eq!(dispatches(&recorder, first, CloudPass::Gather), 0);
    // The cloud drifts: no cloud is re-lit, but the maps are filled again: one cast dispatch,
    // and, after gather's, the sky map's march (one pool) and resolve.
    let mut clouds = app
        .world_mut()
        .query_filtered::<&mut Transform, With<bevy_particle_clouds::ParticleCloud>>();
    for mut t in clouds.iter_mut(app.world_mut()) {
        t.translation.x += 0.3;
    }
    let first = recorder.frames.len();
    for _ in 0..3 {
        recorder.frame(&mut app).unwrap();
    }
    let runs: u32 = recorder.frames[first..]
        .iter()
        .map(|f| f.runs(CloudPass::Shade))
        .sum();
    assert_eq!(
        (runs, dispatches(&recorder, first, CloudPass::Shade)),
        (0, 1)
    );
    assert_eq!(dispatches(&recorder, first, CloudPass::Gather), 2);
}

/// Which material the ground of [`standard_ground_image`] wears.
#[derive(Clone, Copy, PartialEq)]
enum Ground {
    /// Bevy's `StandardMaterial`.
    Standard,
    /// The same, extended to take the clouds' shadows.
    CloudShadowed,
}

/// `StandardMaterial` ground under the cloud of [`cloud_over_ground`], lit by its light (or not,
/// `lit` false) and by Bevy's ambient light; the image, and the shadow map's and sky map's
/// placements.
fn standard_ground_image(
    ground: Ground,
    lit: bool,
) -> (LinearImage, ShadowMapPlacement, Option<ShadowMapPlacement>) {
    let mut setup = cloud_over_ground();
    // The lit object's ground, drawn with a `StandardMaterial` instead.
    let SceneObject {
        shape: ObjectShape::Cuboid(extents),
        translation,
        ..
    } = setup.objects.remove(0)
    else {
        unreachable!("the ground is a cuboid")
    };
    if !lit {
        setup.lights[0].irradiance = Vec3::ZERO;
    }
    let (mut app, target) = spawn_with_maps(&setup, 96);
    app.insert_resource(GlobalAmbientLight {
        color: Color::WHITE,
        brightness: 0.4,
        ..default()
    });
    // Rough, with a specular lobe: both lobes must take the shadow.
    let base = StandardMaterial {
        base_color: Color::linear_rgb(REFLECTANCE.x, REFLECTANCE.y, REFLECTANCE.z),
        perceptual_roughness: 0.6,
        reflectance: 0.5,
        ..default()
    };
    let mesh = Mesh3d(
        app.world_mut()
            .resource_mut::<Assets<Mesh>>()
            .add(Cuboid::from_size(extents)),
    );
    let at = Transform::from_translation(translation);
    let world = app.world_mut();
    match ground {
        Ground::Standard => {
            let material = world.resource_mut::<Assets<StandardMaterial>>().add(base);
            world.spawn((mesh, MeshMaterial3d(material), at));
        }
        Ground::CloudShadowed => {
            let material = CloudShadowedMaterial {
                base,
                extension: CloudShadowReceiver::default(),
            };
            let material = world
                .resource_mut::<Assets<CloudShadowedMaterial>>()
                .add(material);
            world.spawn((mesh, MeshMaterial3d(material), at));
        }
    }
    let mut recorder = FrameRecorder::default();
    headless::render_until_steady(&mut app, &mut recorder, 1, 20).unwrap();
    let image = headless::capture(&mut app, &mut recorder, &target.image).unwrap();
    let maps = app.world().resource::<CloudShadowMaps>();
    let map = maps.maps.first().map(|(_, p)| *p).unwrap_or_default();
    (image, map, maps.sky)
}

/// A game's `StandardMaterial` extended with `CloudShadowReceiver` shows `V` times Bevy's ambient
/// light plus `T` times its direct light, `T` the clouds' transmittance towards the light through
/// the CPU's shadow map and `V` what the CPU's sky map leaves of the sky:
/// `shadowed = V ambient + T (plain - ambient)` at every ground pixel.
#[test]
fn a_standard_material_takes_the_clouds_shadow() {
    let setup = cloud_over_ground();
    let (plain, ..) = standard_ground_image(Ground::Standard, true);
    let (shadowed, map, sky_map) = standard_ground_image(Ground::CloudShadowed, true);
    let (ambient, ..) = standard_ground_image(Ground::Standard, false);
    let cpu_map = cpu_shadow_map(&setup, &map);
    let sky_map = sky_map.expect("a sky map under the sky");
    let cpu_sky = cpu_sky_map(&setup, &sky_map);

    let eye = setup.camera.translation.as_dvec3();
    let camera = pinhole(&setup);
    let (mut expected, mut seen, mut darkest) = (Vec::new(), Vec::new(), 1.0f64);
    let (mut ambient_sum, mut direct_sum) = (0.0, 0.0);
    for py in 0..H {
        for px in 0..W {
            let ray = camera.pixel_ray(px, py);
            let Some((t, _)) = nearest_object(&setup.objects, eye, ray) else {
                continue;
            };
            let x = eye + ray * t;
            let transmittance = (-shadow_map_depth_at(&map, &cpu_map, x)).exp() as f32;
            let visible = 1.0 - shadow_map_depth_at(&sky_map, &cpu_sky, x) as f32;
            darkest = darkest.min(transmittance as f64);
            let i = (py * W + px) as usize;
            let (a, p) = (ambient.pixels[i], plain.pixels[i]);
            let e: [f32; 3] =
                std::array::from_fn(|c| visible * a[c] + transmittance * (p[c] - a[c]));
            ambient_sum += a[1] as f64;
            direct_sum += (p[1] - a[1]) as f64;
            expected.push([e[0], e[1], e[2], 1.0]);
            let s = shadowed.pixels[i];
            seen.push([s[0], s[1], s[2], 1.0]);
        }
    }
    assert!(
        expected.len() > (W * H / 3) as usize,
        "the ground fills the view"
    );
    assert!(darkest < 0.3, "the cloud's shadow falls in view: {darkest}");
    // Both lights matter: an error in either would show.
    let share = ambient_sum / (ambient_sum + direct_sum);
    assert!((0.1..0.7).contains(&share), "ambient share {share}");
    let error = relative_rmse(&seen, &expected);
    eprintln!("StandardMaterial ground: relative RMSE {error:e} against V ambient + T direct");
    assert!(
        error < 1e-3,
        "StandardMaterial ground: relative RMSE {error}"
    );
}

/// Extreme clouds over a lit ground under a sky: particles of 1e-4 m and of 1e4 m (a cloud far
/// wider than the ground and the view, reaching below the plane), and an extinction of 1e4. The
/// sky map holds fractions in [0, 1], the ground no NaN, nothing below 0 or above what the sun
/// and the sky could give it.
#[test]
fn extreme_clouds_leave_the_sky_map_and_the_ground_bounded() {
    let particle = |radius: f32, density: f32| Particle {
        position: Vec3::ZERO,
        radius,
        density,
    };
    // Each with the least of the sky it must hide somewhere.
    let cases = [
        ("radius 1e-4", vec![particle(1e-4, 1.0); 3], 5.0, 0.0),
        ("radius 1e4", vec![particle(1e4, 1.0)], 1e-3, 0.0),
        ("extinction 1e4", cloud_over_ground().particles, 1e4, 0.02),
    ];
    for (what, particles, extinction, hides) in cases {
        let mut setup = cloud_over_ground();
        setup.particles = particles;
        setup.medium.extinction = extinction;
        let (mut app, target) = spawn_with_maps(&setup, 64);
        let mut recorder = FrameRecorder::default();
        for _ in 0..4 {
            recorder.frame(&mut app).unwrap();
        }
        let image = headless::capture(&mut app, &mut recorder, &target.image).unwrap();
        let (sky, _) = gpu_sky_map(&mut app);
        assert!(
            sky.iter().all(|o| (0.0..=1.0).contains(o)),
            "{what}: the sky map holds {:?}",
            sky.iter().find(|o| !(0.0..=1.0).contains(*o))
        );
        let most = sky.iter().copied().fold(0.0, f64::max);
        assert!(
            most >= hides,
            "{what}: the clouds hide at most {most} of the sky"
        );
        // The sun's and the sky's whole light on the ground, or a cloud's every order.
        let light = setup.lights[0].irradiance.max_element();
        let ground =
            EMITTED.max_element() + (light + std::f32::consts::PI * setup.sky.max_element());
        let cloud = setup.medium.albedo * light / (4.0 * std::f32::consts::PI)
            * (setup.settings.scatter_iterations + 1) as f32;
        let bound = ground.max(cloud).max(setup.background.max_element()) * 1.01;
        for (i, p) in image.pixels.iter().enumerate() {
            assert!(
                p[..3]
                    .iter()
                    .all(|v| v.is_finite() && (0.0..=bound).contains(v)),
                "{what}: pixel {i} = {p:?} outside [0, {bound}]"
            );
        }
    }
}

/// A ground the plugin refuses (its height NaN) counts as none for the sky map too: the map lies
/// on world `y = 0`, finite, and the lit ground has no NaN.
#[test]
fn a_refused_ground_leaves_the_sky_map_on_the_world_plane() {
    let setup = cloud_over_ground();
    let (mut app, target) = spawn_with_maps(&setup, 64);
    app.insert_resource(bevy_particle_clouds::CloudGround {
        height: f32::NAN,
        reflectance: Vec3::splat(0.3),
    });
    let mut recorder = FrameRecorder::default();
    for _ in 0..4 {
        recorder.frame(&mut app).unwrap();
    }
    let sky = app.world().resource::<CloudShadowMaps>().sky;
    let sky = sky.expect("a sky map under the sky");
    assert!(sky.texel.is_finite() && sky.corner.is_finite(), "{sky:?}");
    assert_eq!(sky.w_end, 0.0, "on world y = 0");
    let image = headless::capture(&mut app, &mut recorder, &target.image).unwrap();
    assert!(image.pixels.iter().flatten().all(|v| v.is_finite()));
}

/// The plugins register the particles' and the materials' reflection, so inspectors and scenes
/// can edit them.
#[test]
fn the_assets_are_registered_for_reflection() {
    use bevy::asset::ReflectAsset;
    use bevy_particle_clouds::{Particles, lit_object::LitObjectMaterial};
    use std::any::TypeId;
    let (app, _) = spawn_with_maps(&cloud_over_ground(), 16);
    let registry = app.world().resource::<AppTypeRegistry>().read();
    for (name, id) in [
        ("Particles", TypeId::of::<Particles>()),
        ("LitObjectMaterial", TypeId::of::<LitObjectMaterial>()),
        (
            "CloudShadowedMaterial",
            TypeId::of::<CloudShadowedMaterial>(),
        ),
    ] {
        assert!(
            registry.get_type_data::<ReflectAsset>(id).is_some(),
            "{name} is not registered as a reflected asset"
        );
    }
    assert!(registry.get(TypeId::of::<CloudShadowMaps>()).is_some());
}
