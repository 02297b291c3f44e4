//! Accuracy against ground truth, on the CPU: the real-time discretization (its f64 reference,
//! which the GPU passes match within 2e-4 of the maximum: tests/gpu/illumination.rs, tests/gpu/draw.rs)
//! against the path tracer, on a small thick cloud lit from the side.
//!
//! A forward-scattering cloud lit from behind glows at its edges as the path tracer says; lit
//! from the side, its multiply scattered light, seen through its angular moments, matches the
//! path tracer.
//!
//! Raising a quality knob must not make the result worse: for fixed iterations, the in-scattered
//! light at 64³ and 128³ is at least as accurate as at 32³.

use std::f64::consts::PI;

use bevy::{math::DVec3, prelude::*};
use bevy_particle_clouds::{
    CloudQualitySettings, LightSample, Medium, Particle,
    generators::SplitMix64,
    reference::{
        composite::composite_scene_cloud,
        illumination::{CloudIllumination, illuminate_scene_cloud},
        metrics::relative_rmse,
        path_tracer::{
            self, Lighting, MAX_SCATTER_EVENTS, ParticleMedia, PathTracerSettings, noise_level,
            radiance,
        },
    },
    scene::{ResolvedCloud, Scene, SceneCamera},
};
use rayon::prelude::*;

fn scene() -> Scene {
    let mut rng = SplitMix64::new(3);
    let particles = (0..60)
        .map(|_| {
            let p = rng.in_unit_ball();
            Particle {
                position: p * Vec3::new(1.0, 0.7, 0.8),
                radius: 0.25 + 0.2 * rng.next_f32(),
                density: 1.0 - 0.5 * p.length(),
            }
        })
        .collect();
    Scene {
        camera: SceneCamera {
            position: Vec3::new(0.0, 0.0, 5.0),
            look_at: Vec3::ZERO,
            up: Vec3::Y,
            vertical_fov_degrees: 36.0,
            width: 32,
            height: 24,
        },
        background: Vec3::ZERO,
        lights: vec![LightSample {
            direction: Vec3::new(-1.0, -0.3, -0.1),
            irradiance: Vec3::new(3.0, 2.8, 2.5),
        }],
        clouds: vec![ResolvedCloud {
            translation: Vec3::ZERO,
            medium: Medium {
                extinction: 4.0,
                albedo: 0.95,
                ..Default::default()
            },
            particles,
        }],
        objects: Vec::new(),
        fog: None,
        shadow_map_resolution: bevy_particle_clouds::scene::DEFAULT_SHADOW_MAP_RESOLUTION,
        settings: CloudQualitySettings::default(),
    }
}

/// The real-time image of `scene` at `settings`, from the CPU reference of every pass: rendered
/// at twice the size and box-filtered 2×2, as the benchmark does, so that each pixel averages
/// over its footprint like the path tracer's instead of sampling its centre (at 32×24 the
/// difference would otherwise dominate every other error).
fn real_time(scene: &Scene, settings: &CloudQualitySettings) -> Vec<[f32; 4]> {
    real_time_with(scene, settings, |_| {})
}

/// [`real_time`] with the illumination changed by `change` before the billboards draw it.
fn real_time_with(
    scene: &Scene,
    settings: &CloudQualitySettings,
    change: impl FnOnce(&mut CloudIllumination),
) -> Vec<[f32; 4]> {
    let mut illumination =
        illuminate_scene_cloud(scene, 0, settings).expect("a cloud with density");
    change(&mut illumination);
    let mut fine = scene.clone();
    fine.camera.width *= 2;
    fine.camera.height *= 2;
    let cloud = &scene.clouds[0];
    let camera = (scene.camera.position - cloud.translation).as_dvec3();
    let seen = illumination.seen_from(camera, settings.compositing);
    let pixels = composite_scene_cloud(
        &fine,
        0,
        &|x, ray| seen.scattered_at(x, ray),
        settings,
        &illumination.fine,
    );
    let (w, h) = (scene.camera.width as usize, scene.camera.height as usize);
    (0..w * h)
        .map(|i| {
            let (x, y) = (2 * (i % w), 2 * (i / w));
            std::array::from_fn(|c| {
                [(0, 0), (1, 0), (0, 1), (1, 1)]
                    .iter()
                    .map(|(dx, dy)| pixels[(y + dy) * 2 * w + x + dx][c])
                    .sum::<f32>()
                    / 4.0
            })
        })
        .collect()
}

/// The mean of two independent path-traced renders of `scene` at `spp` each, and its noise level.
fn reference(scene: &Scene, spp: u32) -> (Vec<[f32; 4]>, f64) {
    let trace = |seed| {
        path_tracer::render(
            scene,
            &PathTracerSettings {
                samples_per_pixel: spp,
                seed,
                progress: None,
                time_limit: None,
            },
        )
    };
    let (a, b) = (trace(1), trace(2));
    let noise = noise_level(&a, &b) / std::f64::consts::SQRT_2;
    let mean = a
        .iter()
        .zip(&b)
        .map(|(x, y)| std::array::from_fn(|c| 0.5 * (x[c] + y[c])))
        .collect();
    (mean, noise)
}

/// The in-scattered light `S(x)` (docs/physics.md) at `points`, by the path tracer: the direct light
/// with exact transmittance, plus the radiance arriving from `samples` uniform directions (all
/// orders). Returns the values and their noise (relative standard error over all points).
fn in_scattered_light(scene: &Scene, points: &[DVec3], samples: u32) -> (Vec<DVec3>, f64) {
    let media = ParticleMedia::from_scene(scene);
    let lighting = Lighting::from_scene(scene);
    let values: Vec<(DVec3, DVec3)> = points
        .par_iter()
        .enumerate()
        .map(|(i, &x)| {
            let (mut sum, mut squares) = (DVec3::ZERO, DVec3::ZERO);
            for s in 0..samples {
                let mut rng = SplitMix64::for_sample(7, i as u64, s as u64);
                let dir = rng.unit_sphere();
                let l = radiance(&media, &lighting, x, dir, MAX_SCATTER_EVENTS, &mut rng);
                sum += l;
                squares += l * l;
            }
            let mean = sum / samples as f64;
            let variance = (squares / samples as f64 - mean * mean) / samples as f64;
            let direct = lighting.direct_irradiance(&media, x) / (4.0 * PI);
            (direct + mean, variance)
        })
        .collect();
    let norm: f64 = values.iter().map(|(s, _)| s.length_squared()).sum();
    let noise = (values.iter().map(|(_, v)| v.element_sum()).sum::<f64>() / norm).sqrt();
    (values.into_iter().map(|(s, _)| s).collect(), noise)
}

/// `error` at the default settings with `volume_resolution` 32, 64 and 128: `(resolution, error)`.
fn by_resolution(error: impl Fn(&CloudQualitySettings) -> f64) -> Vec<(u32, f64)> {
    [32, 64, 128]
        .into_iter()
        .map(|volume_resolution| {
            let settings = CloudQualitySettings {
                volume_resolution,
                ..default()
            };
            (volume_resolution, error(&settings))
        })
        .collect()
}

#[test]
fn in_scattered_light_converges_with_resolution() {
    // What `volume_resolution` controls: S = S_1 + S_m at the particles' centres, against the
    // path tracer's in-scattered light there (no billboards involved).
    let scene = scene();
    let cloud = &scene.clouds[0];
    let points: Vec<DVec3> = cloud
        .particles
        .iter()
        .map(|p| p.position.as_dvec3())
        .collect();
    let (truth, noise) = in_scattered_light(&scene, &points, 16_000);
    let norm: f64 = truth.iter().map(|s| s.length_squared()).sum();
    let errors = by_resolution(|settings| {
        let ill = illuminate_scene_cloud(&scene, 0, settings).expect("a cloud with density");
        let squared: f64 = points
            .iter()
            .zip(&truth)
            .map(|(&x, s)| (ill.scattered_at(x, DVec3::Z) / ill.albedo - *s).length_squared())
            .sum();
        (squared / norm).sqrt()
    });
    eprintln!("path-traced S: noise {noise:.4}; relative RMSE of S by resolution: {errors:?}");
    assert!(
        noise < 0.01,
        "the reference is too noisy to compare: {noise}"
    );
    let at_32 = errors[0].1;
    assert!(at_32 < 0.04, "32³ errs by {at_32}");
    for &(n, error) in &errors[1..] {
        assert!(
            error <= at_32,
            "{n}³ errs by {error}, more than 32³ ({at_32}); reference noise {noise}"
        );
    }
}

#[test]
fn images_are_within_the_goal_and_no_worse_at_finer_resolutions() {
    // The whole image, billboards included, against the path tracer, at the default settings
    // but for the resolution: within the goal at each, and 64³ and 128³ at least as accurate as
    // 32³ (issue #9: an approximation must not get worse as its quality knob rises).
    let scene = scene();
    let (reference, noise) = reference(&scene, 4096);
    assert!(
        noise < 0.015,
        "the reference is too noisy to compare: {noise}"
    );
    let errors = by_resolution(|settings| {
        let error = relative_rmse(&real_time(&scene, settings), &reference);
        let denoised = (error * error - noise * noise).max(0.0).sqrt();
        eprintln!(
            "{}³: relative RMSE {error:.4}, {denoised:.4} without the reference's noise {noise:.4}",
            settings.volume_resolution
        );
        denoised
    });
    let at_32 = errors[0].1;
    for &(n, error) in &errors {
        assert!(error < 0.05, "{n}³ errs by {error}");
        assert!(
            error <= at_32,
            "{n}³ errs by {error}, more than 32³ ({at_32}); reference noise {noise}"
        );
    }
}

/// The silver lining: the same cloud with the sun behind it (travelling almost towards the
/// camera) in a forward-scattering medium (Henyey–Greenstein g = 0.7). The path tracer, which
/// samples the phase function exactly, shows the glow (the cloud at least twice as bright as
/// isotropic); the real-time image follows it in brightness and shape, within the benchmark's
/// goal of 0.05 (0.022 here; 0.034 under the δ-Eddington transform, 0.065 while its beam's
/// excess was seen collimated, docs/illumination.md §4, §5).
#[test]
fn a_cloud_lit_from_behind_glows_as_the_path_tracer_says() {
    let mut scene = scene();
    scene.lights[0].direction = Vec3::new(0.25, -0.3, 1.0);
    let mut forward = scene.clone();
    forward.clouds[0].medium.anisotropy = 0.7;
    let energy = |image: &[[f32; 4]]| {
        image
            .iter()
            .map(|p| (p[0] + p[1] + p[2]) as f64)
            .sum::<f64>()
    };
    let (isotropic, _) = reference(&scene, 1024);
    let (truth, noise) = reference(&forward, 4096);
    let glow = energy(&truth) / energy(&isotropic);
    let settings = CloudQualitySettings::default();
    let image = real_time(&forward, &settings);
    let error = relative_rmse(&image, &truth);
    let denoised = (error * error - noise * noise).max(0.0).sqrt();
    let ratio = energy(&image) / energy(&truth);
    eprintln!(
        "silver lining: path tracer {glow:.2}x isotropic; real-time / truth {ratio:.3}, relative \
         RMSE {error:.4} ({denoised:.4} without the reference's noise {noise:.4})"
    );
    assert!(glow > 2.0, "the path tracer shows no silver lining: {glow}");
    assert!(
        noise < 0.015,
        "the reference is too noisy to compare: {noise}"
    );
    assert!((ratio - 1.0).abs() < 0.15, "real-time / truth {ratio}");
    assert!(denoised < 0.05, "relative RMSE {denoised}");
}

/// A forward-scattering cloud (g = 0.7) lit from the side and from the front: its multiply
/// scattered light flows on with the light, and the camera sees it through the phase function's
/// first three moments (docs/illumination.md §4, §5). Against the path tracer, at most a third of
/// the error of the isotropic multiple scattering it replaced (0.33 and 0.86 here), and within
/// 0.06 (0.052 from the side, 0.045 from the front; this cloud is thinner than the benchmark's
/// cumulus, optical depth about 5 through its core). From the side it was 0.090 while the
/// sweep's source was P1 (see the next test), and 0.030 under the δ-Eddington transform with
/// the P2 source, whose extra quadrupole hid the lattice's loss of it (docs/illumination.md §4,
/// "Why Lebedev for `Q`"); from the front 0.049.
#[test]
fn a_forward_scattering_cloud_lit_from_the_side_or_the_front_follows_the_path_tracer() {
    use bevy_particle_clouds::reference::illumination::{gather, scatter};
    for direction in [Vec3::new(-1.0, -0.3, -0.1), Vec3::new(-0.8, -0.35, -0.6)] {
        let mut forward = scene();
        forward.lights[0].direction = direction;
        forward.clouds[0].medium.anisotropy = 0.7;
        let (truth, noise) = reference(&forward, 8192);
        let settings = CloudQualitySettings::default();
        let denoised = |image: &[[f32; 4]]| {
            let error = relative_rmse(image, &truth);
            (error * error - noise * noise).max(0.0).sqrt()
        };
        let error = denoised(&real_time(&forward, &settings));
        let isotropic = denoised(&real_time_with(&forward, &settings, |ill| {
            let s0 = gather(&ill.grid, &ill.fine, &ill.lights);
            let (grid, k, albedo) = (&ill.grid, ill.k_local, ill.albedo);
            let iterations = settings.scatter_iterations;
            ill.multiple = scatter(grid, k, albedo, settings.scatter_stencil, &s0, iterations);
        }));
        eprintln!(
            "forward, light {direction}: relative RMSE {error:.4}, {isotropic:.4} with isotropic \
             multiple scattering (reference noise {noise:.4})"
        );
        assert!(
            noise < 0.023,
            "the reference is too noisy to compare: {noise}"
        );
        assert!(error < 0.06, "relative RMSE {error}");
        assert!(
            3.0 * error < isotropic,
            "isotropic multiple scattering errs by {isotropic}"
        );
    }
}

/// What the billboards of a forward-scattering cloud (g = 0.7) lit from the side shade towards
/// the camera, past single scattering (the beam's excess seen through its spread, and the grid's
/// multiple scattering through the phase function's first three moments), against the path
/// tracer's in-scattered light at points inside the cloud, density-weighted: within 3 % (0.1 %
/// dark). With a P1 source in the sweep it was 9 % bright: the grid held none of the remainder
/// phase function's second moment (docs/illumination.md §4), so the light's quadrupole seen at
/// 90° from the sun was 18 % short of the truth's; with the δ-M transform and the quadrupole
/// gathered with equal weights it was 3.0 % bright (the quadrupole 4.5 % short).
#[test]
fn a_side_lit_forward_scattering_cloud_scatters_towards_the_camera_as_the_path_tracer_says() {
    use bevy_particle_clouds::reference::illumination::single_scattering_towards;
    let g = 0.7;
    let mut scene = scene();
    scene.clouds[0].medium.anisotropy = g as f32;
    let settings = CloudQualitySettings::default();
    let ill = illuminate_scene_cloud(&scene, 0, &settings).expect("a cloud with density");
    let media = ParticleMedia::from_scene(&scene);
    let lighting = Lighting::from_scene(&scene);
    // Towards the camera, 90° from the sun; the points: a lattice over the cloud's middle.
    let w = DVec3::Z;
    let points: Vec<DVec3> = (0..11 * 5 * 9)
        .map(|i| DVec3::new((i % 11) as f64, ((i / 11) % 5) as f64, (i / 55) as f64))
        .map(|c| DVec3::new(-1.0, -0.6, -0.8) + c * DVec3::new(0.2, 0.3, 0.2))
        .filter(|&x| ill.grid.sample(x) > 0.1)
        .collect();
    let samples = 8192;
    // The path tracer: the radiance arriving from directions drawn from the phase function
    // towards w, so their mean is the in-scattered light (the sun's own beam never arrives).
    let truth: Vec<(f64, f64)> = points
        .par_iter()
        .enumerate()
        .map(|(i, &x)| {
            let (mut sum, mut squares) = (0.0, 0.0);
            for s in 0..samples {
                let mut rng = SplitMix64::for_sample(11, i as u64, s as u64);
                let from = -rng.henyey_greenstein(g, w);
                let l = radiance(&media, &lighting, x, from, MAX_SCATTER_EVENTS, &mut rng)
                    .element_sum();
                sum += l;
                squares += l * l;
            }
            let mean = sum / samples as f64;
            (
                mean,
                (squares / samples as f64 - mean * mean) / samples as f64,
            )
        })
        .collect();
    let medium = (ill.albedo, g);
    let shaded = |x: DVec3| {
        let excess = single_scattering_towards(&ill.lights, x, medium, -w, ill.beam.as_ref())
            - single_scattering_towards(&ill.lights, x, (0.0, g), -w, None);
        (ill.multiple_towards(x, w) + excess).element_sum()
    };
    let (mut real_time, mut path_traced, mut variance) = (0.0, 0.0, 0.0);
    for (&x, (t, v)) in points.iter().zip(&truth) {
        let rho = ill.grid.sample(x);
        real_time += rho * shaded(x);
        path_traced += rho * t;
        variance += rho * rho * v;
    }
    let ratio = real_time / path_traced;
    let noise = variance.sqrt() / path_traced;
    eprintln!(
        "towards the camera, {} points: real-time / path tracer {ratio:.4} (noise {noise:.4})",
        points.len()
    );
    assert!(points.len() > 100, "{} points", points.len());
    assert!(
        noise < 0.01,
        "the path tracer is too noisy to compare: {noise}"
    );
    assert!(
        (ratio - 1.0).abs() < 0.03,
        "real-time / path tracer {ratio}"
    );
}
