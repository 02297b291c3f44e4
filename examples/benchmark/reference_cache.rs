//! Path-traced references, cached on disk by a hash of everything that determines them.

use super::*;

/// A path-traced ground truth: the mean of two independent renders.
pub(crate) struct Reference {
    pub(crate) image: Vec<[f32; 4]>,
    pub(crate) width: u32,
    pub(crate) height: u32,
    /// Samples per pixel of `image` (both renders together).
    pub(crate) spp: u32,
    /// Noise level of `image`: docs/physics.md's noise level of one render (relative RMSE of the two
    /// renders / √2) divided by √2, since `image` averages both.
    pub(crate) noise: f64,
    /// The same after a 4×4 box filter of both renders.
    pub(crate) noise_box4: f64,
    /// With lit objects: which pixels see one (their centre's ray hits it first), and the noise
    /// over those pixels.
    pub(crate) ground: Option<(Vec<bool>, f64)>,
    /// The two renders `image` averages (seeds 1 and 2).
    pub(crate) seeds: [Vec<[f32; 4]>; 2],
}

/// The pixels of `scene`'s camera whose centre ray first hits a lit object (one with a
/// reflectance); `None` without lit objects.
pub(crate) fn lit_object_pixels(scene: &Scene) -> Option<Vec<bool>> {
    use bevy_particle_clouds::reference::{camera::PinholeCamera, geometry::nearest_object};
    if scene.objects.iter().all(|o| o.reflectance == Vec3::ZERO) {
        return None;
    }
    let camera = PinholeCamera::from_scene(&scene.camera);
    let (w, h) = (scene.camera.width, scene.camera.height);
    let seen = (0..w * h).map(|i| {
        let ray = camera.pixel_ray(i % w, i / w);
        nearest_object(&scene.objects, camera.position, ray)
            .is_some_and(|(_, o)| scene.objects[o].reflectance != Vec3::ZERO)
    });
    Some(seen.collect())
}

/// `pixels` with every pixel outside `mask` zeroed.
pub(crate) fn masked(pixels: &[[f32; 4]], mask: &[bool]) -> Vec<[f32; 4]> {
    pixels
        .iter()
        .zip(mask)
        .map(|(p, &m)| if m { *p } else { [0.0; 4] })
        .collect()
}

/// FNV-1a, 64 bits: a hash that is the same on every machine and Rust version.
pub(crate) fn fnv1a(bytes: &[u8]) -> u64 {
    bytes.iter().fold(0xcbf2_9ce4_8422_2325, |h, &b| {
        (h ^ b as u64).wrapping_mul(0x0000_0100_0000_01b3)
    })
}

/// The scene as the path tracer sees it (camera, background, lights, clouds, objects, fog),
/// hashed. A scene without fog hashes as before fog existed, so its cached references hold.
pub(crate) fn reference_hash(scene: &Scene, spp: u32) -> u64 {
    let mut text = format!(
        "{:?}|{:?}|{:?}|{:?}|{:?}|spp {spp}",
        scene.camera, scene.background, scene.lights, scene.clouds, scene.objects
    );
    if let Some(fog) = &scene.fog {
        text += &format!("|fog {fog:?}");
    }
    fnv1a(text.as_bytes())
}

pub(crate) fn reference(
    scene: &Scene,
    bench: &BenchScene,
    spp: u32,
    out: &Path,
) -> Result<Reference, String> {
    let mut small = scene.clone();
    small.camera.width = scene.camera.width / bench.error_downsample;
    small.camera.height = scene.camera.height / bench.error_downsample;
    let hash = reference_hash(&small, spp);
    let mut images = Vec::new();
    for seed in [1u64, 2] {
        let path = out.join(format!("reference-{hash:016x}-s{seed}.exr"));
        let image = match read_exr(&path) {
            Ok(image)
                if image.width == small.camera.width && image.height == small.camera.height =>
            {
                eprintln!(
                    "benchmark: {}: cached reference {}",
                    bench.name,
                    path.display()
                );
                image
            }
            _ => {
                let start = Instant::now();
                eprintln!(
                    "benchmark: {}: path tracing the reference, {}x{} at {} spp, seed {seed} ({} threads)",
                    bench.name,
                    small.camera.width,
                    small.camera.height,
                    spp,
                    rayon::current_num_threads()
                );
                let (bar, progress) = crate::path_tracing_progress(
                    &format!("{} seed {seed}", bench.name),
                    small.camera.height,
                );
                let pixels = path_tracer::render(
                    &small,
                    &PathTracerSettings {
                        samples_per_pixel: spp,
                        seed,
                        progress: Some(progress),
                        time_limit: None,
                    },
                );
                bar.finish_and_clear();
                let image = LinearImage {
                    width: small.camera.width,
                    height: small.camera.height,
                    pixels,
                };
                let metadata = ImageMetadata::software()
                    .with("renderer", "path tracer")
                    .with("scene", bench.name)
                    .with("spp", spp)
                    .with("seed", seed)
                    .with(
                        "render_time_s",
                        format!("{:.3}", start.elapsed().as_secs_f64()),
                    )
                    .with("camera", format!("{:?}", small.camera));
                write_exr_with_metadata(&image, &path, &metadata).map_err(|e| e.to_string())?;
                eprintln!(
                    "benchmark: {}: traced in {:.1} s",
                    bench.name,
                    start.elapsed().as_secs_f64()
                );
                image
            }
        };
        images.push(image);
    }
    let image: Vec<[f32; 4]> = images[0]
        .pixels
        .iter()
        .zip(&images[1].pixels)
        .map(|(a, b)| std::array::from_fn(|c| 0.5 * (a[c] + b[c])))
        .collect();
    let boxed = [downsample(&images[0], 4), downsample(&images[1], 4)];
    let mean_boxed = downsample(
        &LinearImage {
            width: small.camera.width,
            height: small.camera.height,
            pixels: image.clone(),
        },
        4,
    );
    let sky = scene.background;
    let noise = noise_level(
        &cloud_pixels(&images[0].pixels, &image, sky),
        &cloud_pixels(&images[1].pixels, &image, sky),
    ) / std::f64::consts::SQRT_2;
    let noise_box4 = noise_level(
        &cloud_pixels(&boxed[0].pixels, &mean_boxed.pixels, sky),
        &cloud_pixels(&boxed[1].pixels, &mean_boxed.pixels, sky),
    ) / std::f64::consts::SQRT_2;
    let _ = write_png(
        &LinearImage {
            width: small.camera.width,
            height: small.camera.height,
            pixels: image_clone(&images),
        },
        &out.join(format!("{}-reference.png", bench.name)),
    );
    let ground = lit_object_pixels(&small).map(|mask| {
        let halves = [0, 1].map(|i| masked(&images[i].pixels, &mask));
        let noise = noise_level(&halves[0], &halves[1]) / std::f64::consts::SQRT_2;
        (mask, noise)
    });
    Ok(Reference {
        image,
        width: small.camera.width,
        height: small.camera.height,
        spp: 2 * spp,
        noise,
        noise_box4,
        ground,
        seeds: [images[0].pixels.clone(), images[1].pixels.clone()],
    })
}

/// Under a non-black sky, `pixels` with every pixel zeroed where the `reference` shows the bare
/// sky (within 0.1 %): relative errors and noise are then taken over the pixels where the cloud
/// changes the sky, which the bare background would otherwise dilute. Unchanged under a black
/// sky.
pub(crate) fn cloud_pixels(
    pixels: &[[f32; 4]],
    reference: &[[f32; 4]],
    sky: Vec3,
) -> Vec<[f32; 4]> {
    let luminance = |p: &[f32; 4]| p[0] + p[1] + p[2];
    let bare = sky.element_sum();
    if bare <= 0.0 {
        return pixels.to_vec();
    }
    pixels
        .iter()
        .zip(reference)
        .map(|(p, r)| {
            if (luminance(r) - bare).abs() > 1e-3 * bare {
                *p
            } else {
                [0.0; 4]
            }
        })
        .collect()
}

pub(crate) fn image_clone(images: &[LinearImage]) -> Vec<[f32; 4]> {
    images[0]
        .pixels
        .iter()
        .zip(&images[1].pixels)
        .map(|(a, b)| std::array::from_fn(|c| if c == 3 { 1.0 } else { 0.5 * (a[c] + b[c]) }))
        .collect()
}

/// Real-time | path tracer | difference, side by side. The difference is `4 (real-time -
/// reference)`: red where the real-time image is brighter, blue where it is darker.
pub(crate) fn side_by_side(real_time: &LinearImage, reference: &LinearImage) -> LinearImage {
    let (w, h) = (reference.width, reference.height);
    let mut out = LinearImage::new(3 * w, h);
    for y in 0..h {
        for x in 0..w {
            let (a, b) = (real_time.pixel(x, y), reference.pixel(x, y));
            let d = (0..3).map(|c| a[c] - b[c]).sum::<f32>() / 3.0 * 4.0;
            *out.pixel_mut(x, y) = [a[0], a[1], a[2], 1.0];
            *out.pixel_mut(w + x, y) = [b[0], b[1], b[2], 1.0];
            *out.pixel_mut(2 * w + x, y) = [d.max(0.0), 0.0, (-d).max(0.0), 1.0];
        }
    }
    out
}

/// Box-filters an image by an integer factor.
pub(crate) fn downsample(image: &LinearImage, factor: u32) -> LinearImage {
    if factor == 1 {
        return image.clone();
    }
    let (w, h) = (image.width / factor, image.height / factor);
    let mut out = LinearImage::new(w, h);
    let weight = 1.0 / (factor * factor) as f32;
    for y in 0..h {
        for x in 0..w {
            let mut sum = [0.0f32; 4];
            for dy in 0..factor {
                for dx in 0..factor {
                    let p = image.pixel(x * factor + dx, y * factor + dy);
                    (0..4).for_each(|c| sum[c] += p[c] * weight);
                }
            }
            *out.pixel_mut(x, y) = sum;
        }
    }
    out
}
