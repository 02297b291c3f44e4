//! Images: the settings, and every pixel's radiance averaged over its jittered paths.

use std::sync::{
    Arc,
    atomic::{AtomicUsize, Ordering},
};

use bevy::math::DVec3;
use rayon::prelude::*;

use super::{Lighting, MAX_SCATTER_EVENTS, Media, ParticleMedia, radiance_by_order};
use crate::math::SplitMix64;
use crate::reference::camera::PinholeCamera;
use crate::reference::metrics::relative_rmse;
use crate::scene::Scene;

/// Called as rows of the image are finished, with `(rows done, rows in all)`, from any thread.
#[derive(Clone)]
pub struct Progress(pub Arc<dyn Fn(usize, usize) + Send + Sync>);

impl Progress {
    /// A callback from a closure.
    pub fn new(report: impl Fn(usize, usize) + Send + Sync + 'static) -> Self {
        Self(Arc::new(report))
    }
}

impl std::fmt::Debug for Progress {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("Progress(..)")
    }
}

/// Settings of [`render`].
#[derive(Clone, Debug)]
pub struct PathTracerSettings {
    /// Paths per pixel, each through a uniformly jittered point of the pixel (0 is taken as 1).
    pub samples_per_pixel: u32,
    /// Seed of all random numbers; the image is a deterministic function of the scene and this
    /// seed, whatever the number of threads.
    pub seed: u64,
    /// Told how many rows are finished, as they finish.
    pub progress: Option<Progress>,
}

impl Default for PathTracerSettings {
    fn default() -> Self {
        Self {
            samples_per_pixel: 256,
            seed: 0,
            progress: None,
        }
    }
}

/// Renders a scene: linear RGB radiance per pixel (alpha 1), row-major, row 0 at the top.
pub fn render(scene: &Scene, settings: &PathTracerSettings) -> Vec<[f32; 4]> {
    let media = ParticleMedia::from_scene(scene);
    let lighting = Lighting::from_scene(scene);
    let camera = PinholeCamera::from_scene(&scene.camera);
    render_media(&media, &lighting, &camera, settings)
}

/// [`render`] split by scattering order: image `k` holds the light scattered exactly `k` times
/// (image 0 the background and objects seen directly), the last image every order from its own
/// on; `orders >= 1` images, which sum to [`render`]'s image.
pub fn render_orders(
    scene: &Scene,
    settings: &PathTracerSettings,
    orders: usize,
) -> Vec<Vec<[f32; 4]>> {
    let media = ParticleMedia::from_scene(scene);
    let lighting = Lighting::from_scene(scene);
    let camera = PinholeCamera::from_scene(&scene.camera);
    render_media_orders(&media, &lighting, &camera, settings, orders)
}

/// [`render`] for any media: rows in parallel, each sample with its own generator seeded from
/// `(seed, pixel, sample)`, so the image does not depend on the number of threads.
pub fn render_media<M: Media>(
    media: &M,
    lighting: &Lighting,
    camera: &PinholeCamera,
    settings: &PathTracerSettings,
) -> Vec<[f32; 4]> {
    render_media_orders(media, lighting, camera, settings, 1)
        .pop()
        .expect("one image")
}

/// [`render_orders`] for any media.
pub fn render_media_orders<M: Media>(
    media: &M,
    lighting: &Lighting,
    camera: &PinholeCamera,
    settings: &PathTracerSettings,
    orders: usize,
) -> Vec<Vec<[f32; 4]>> {
    let orders = orders.max(1);
    let (width, height) = (camera.width as usize, camera.height as usize);
    let mut pixels = vec![vec![DVec3::ZERO; orders]; width * height];
    if width > 0 && height > 0 {
        let rows_done = AtomicUsize::new(0);
        pixels
            .par_chunks_mut(width)
            .enumerate()
            .for_each(|(py, row)| {
                for (px, out) in row.iter_mut().enumerate() {
                    let pixel = (py * width + px) as u64;
                    pixel_radiance(media, lighting, camera, settings, pixel, px, py, out);
                }
                let done = rows_done.fetch_add(1, Ordering::Relaxed) + 1;
                if let Some(Progress(report)) = &settings.progress {
                    report(done, height);
                }
            });
    }
    (0..orders)
        .map(|k| {
            pixels
                .iter()
                .map(|p| [p[k].x as f32, p[k].y as f32, p[k].z as f32, 1.0])
                .collect()
        })
        .collect()
}

/// Mean radiance of `samples_per_pixel` paths through jittered points of pixel `(px, py)`, split
/// into `orders.len()` scattering orders.
#[allow(clippy::too_many_arguments)]
fn pixel_radiance<M: Media>(
    media: &M,
    lighting: &Lighting,
    camera: &PinholeCamera,
    settings: &PathTracerSettings,
    pixel: u64,
    px: usize,
    py: usize,
    orders: &mut [DVec3],
) {
    let spp = settings.samples_per_pixel.max(1);
    for s in 0..spp {
        let mut rng = SplitMix64::for_sample(settings.seed, pixel, s as u64);
        let x = px as f64 + rng.next_f64();
        let y = py as f64 + rng.next_f64();
        let dir = camera.ray_direction(x, y);
        radiance_by_order(
            media,
            lighting,
            camera.position,
            dir,
            MAX_SCATTER_EVENTS,
            &mut rng,
            orders,
        );
    }
    orders.iter_mut().for_each(|o| *o /= spp as f64);
}

/// Noise level of a path-traced image (docs/physics.md): the relative RMSE between two independent
/// renders (different seeds, same sample count) divided by `√2`, which estimates the relative RMSE
/// of one render against the noise-free image. Dimensionless.
pub fn noise_level(a: &[[f32; 4]], b: &[[f32; 4]]) -> f64 {
    relative_rmse(a, b) / std::f64::consts::SQRT_2
}
