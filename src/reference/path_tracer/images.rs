//! Images: the settings, and every pixel's radiance averaged over its jittered paths.

use std::sync::{
    Arc,
    atomic::{AtomicUsize, Ordering},
};
use std::time::{Duration, Instant};

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
    /// Told how many rows are finished, as they finish (with a `time_limit`, rows of every
    /// pass of samples, out of all the passes' rows).
    pub progress: Option<Progress>,
    /// Stop once this much time has passed, at the end of the pass of samples then running
    /// (passes of 1, 1, 2, 4, … samples per pixel, so at most about twice the limit): the image
    /// averages the samples finished, the same image as asking for that many. `None`: no limit.
    pub time_limit: Option<Duration>,
}

impl Default for PathTracerSettings {
    fn default() -> Self {
        Self {
            samples_per_pixel: 256,
            seed: 0,
            progress: None,
            time_limit: None,
        }
    }
}

/// Renders a scene: linear RGB radiance per pixel (alpha 1), row-major, row 0 at the top.
pub fn render(scene: &Scene, settings: &PathTracerSettings) -> Vec<[f32; 4]> {
    render_within_limit(scene, settings).0
}

/// [`render`], and the samples per pixel it finished: fewer than asked for where the
/// settings' `time_limit` stopped it.
pub fn render_within_limit(scene: &Scene, settings: &PathTracerSettings) -> (Vec<[f32; 4]>, u32) {
    let media = ParticleMedia::from_scene(scene);
    let lighting = Lighting::from_scene(scene);
    let camera = PinholeCamera::from_scene(&scene.camera);
    let (mut images, samples) = render_passes(&media, &lighting, &camera, settings, 1);
    (images.pop().expect("one image"), samples)
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
    render_passes(media, lighting, camera, settings, orders).0
}

/// The sample ranges of the passes: all at once without a time limit, else 1, 1, 2, 4, …
fn passes(settings: &PathTracerSettings) -> Vec<std::ops::Range<u32>> {
    let spp = settings.samples_per_pixel.max(1);
    if settings.time_limit.is_none() {
        return vec![0..spp];
    }
    let mut ranges = vec![0..1];
    while ranges.last().unwrap().end < spp {
        let start = ranges.last().unwrap().end;
        ranges.push(start..(2 * start).min(spp));
    }
    ranges
}

/// Renders pass after pass until the samples or the time limit run out; the images and the
/// samples per pixel finished. Each sample's generator is seeded from `(seed, pixel, sample)`
/// and added in sample order, so the image depends neither on the threads nor on the passes.
fn render_passes<M: Media>(
    media: &M,
    lighting: &Lighting,
    camera: &PinholeCamera,
    settings: &PathTracerSettings,
    orders: usize,
) -> (Vec<Vec<[f32; 4]>>, u32) {
    let start = Instant::now();
    let orders = orders.max(1);
    let (width, height) = (camera.width as usize, camera.height as usize);
    let mut pixels = vec![vec![DVec3::ZERO; orders]; width * height];
    let passes = passes(settings);
    let rows_done = AtomicUsize::new(0);
    let mut samples = 0;
    for range in &passes {
        if settings
            .time_limit
            .is_some_and(|limit| start.elapsed() >= limit)
        {
            break;
        }
        pixels
            .par_chunks_mut(width.max(1))
            .enumerate()
            .for_each(|(py, row)| {
                for (px, out) in row.iter_mut().enumerate() {
                    let pixel = (py * width + px) as u64;
                    let path = PixelPath { px, py, pixel };
                    add_samples(media, lighting, camera, settings, path, range.clone(), out);
                }
                let done = rows_done.fetch_add(1, Ordering::Relaxed) + 1;
                if let Some(Progress(report)) = &settings.progress {
                    report(done, height * passes.len());
                }
            });
        samples = range.end;
    }
    let images = (0..orders)
        .map(|k| {
            pixels
                .iter()
                .map(|p| {
                    let l = p[k] / samples.max(1) as f64;
                    [l.x as f32, l.y as f32, l.z as f32, 1.0]
                })
                .collect()
        })
        .collect();
    (images, samples)
}

/// A pixel: its column, row and index in the image.
#[derive(Clone, Copy)]
struct PixelPath {
    px: usize,
    py: usize,
    pixel: u64,
}

/// Adds the radiance of the paths of `samples` through jittered points of the pixel into
/// `orders`, split into `orders.len()` scattering orders.
fn add_samples<M: Media>(
    media: &M,
    lighting: &Lighting,
    camera: &PinholeCamera,
    settings: &PathTracerSettings,
    PixelPath { px, py, pixel }: PixelPath,
    samples: std::ops::Range<u32>,
    orders: &mut [DVec3],
) {
    for s in samples {
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
}

/// Noise level of a path-traced image (docs/physics.md): the relative RMSE between two independent
/// renders (different seeds, same sample count) divided by `√2`, which estimates the relative RMSE
/// of one render against the noise-free image. Dimensionless.
pub fn noise_level(a: &[[f32; 4]], b: &[[f32; 4]]) -> f64 {
    relative_rmse(a, b) / std::f64::consts::SQRT_2
}
