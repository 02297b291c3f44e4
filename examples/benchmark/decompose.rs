//! `decompose`: the real-time transport split into its parts, each compared with the same part
//! of the path tracer, which splits its paths by scattering order (issue #9's error
//! decomposition). Computed with the f64 CPU references of the real-time passes
//! (docs/illumination.md), which the GPU matches within 2e-4 of the maximum (tests/illumination.rs,
//! tests/draw.rs), so no adapter is needed.
//!
//! - single scattering (order 1): billboards shading `albedo S_1`, against paths cut after one
//!   scattering event;
//! - each order `n >= 2`: billboards shading `albedo S_{n-1}` of the grid, against paths whose
//!   light scattered exactly `n` times; the orders past `M + 1` against the closure;
//! - the multiple-scattering part (orders >= 2) as a whole;
//! - the billboards alone: order 1 drawn from the exact single scattering (the path tracer's
//!   transmittance towards each light at every shading point), so only the billboard
//!   approximation (chord segments, particles composited whole in sorted order) is left;
//! - the image itself, beside the parts' sum: the billboards take `S` log-linear along each
//!   chord piece, which is not additive, so parts drawn on their own sum to a little less light
//!   than the image where `S` varies along the pieces.
//!
//! An anisotropic medium's orders are those of its δ-Eddington transform, whose beam keeps light
//! that scattered at small angles, and its orders' angular moments are not kept apart: its
//! image is split into order 1 (the light volumes' exact beam, without the transform) and
//! everything else.

use std::{fmt::Write, path::Path};

use bevy_particle_clouds::{
    CloudQualitySettings,
    image_io::LinearImage,
    reference::{
        composite::{ScatteredLight, composite_scene_cloud},
        illumination::{
            CloudIllumination, DensityGrid, illuminate_scene_cloud, single_scattering_towards,
        },
        metrics::relative_rmse,
        path_tracer::{Lighting, ParticleMedia, PathTracerSettings, noise_level, render_orders},
    },
    scene::Scene,
};

use super::{
    ReferenceSpp, downsample, grid_error, load_scene, parse_settings, sweep_scenes, write_report,
};

/// The options of `benchmark decompose`.
#[derive(clap::Args, Debug)]
pub(crate) struct DecomposeArgs {
    /// Only these scenes (comma-separated names; default: the quick ones).
    #[arg(long, value_delimiter = ',')]
    pub(crate) scenes: Option<Vec<String>>,
    /// Decompose each of these settings (RON, as a scene file's `settings`; against one
    /// path-traced reference per scene) instead of the defaults. Repeatable.
    #[arg(long = "settings", value_name = "RON", value_parser = parse_settings)]
    pub(crate) settings: Vec<CloudQualitySettings>,
    #[command(flatten)]
    pub(crate) reference: ReferenceSpp,
}

/// `benchmark decompose`: every chosen scene's error at the default settings (or at each
/// `--settings`, against one path-traced reference per scene), part by part; writes
/// `DIR/decomposition.md`.
pub(crate) fn decompose_benchmark(args: &DecomposeArgs, out: &Path) -> Result<(), String> {
    let chosen = sweep_scenes(args.scenes.as_deref(), false)?;
    let settings = if args.settings.is_empty() {
        vec![CloudQualitySettings::default()]
    } else {
        args.settings.clone()
    };
    let mut md = String::from(
        "The error split by scattering order (`cargo run --example benchmark -- decompose`), \
         computed with the f64 CPU references of the real-time passes (which the GPU matches \
         within 2e-4 of the maximum) against the path tracer split by order. Energies are sums \
         over the image; λ is an order's energy over the previous one's.\n",
    );
    for bench in chosen {
        let scene = load_scene(bench)?;
        let spp = args.reference.spp.unwrap_or(bench.spp);
        let factor = bench.error_downsample;
        let parts: Vec<RealTime> = settings
            .iter()
            .map(|s| real_time(&scene, s, factor))
            .collect();
        let orders = parts.iter().map(|r| r.orders()).max().unwrap_or(1);
        eprintln!(
            "benchmark: {}: path tracing {orders} orders at {spp} spp per half",
            bench.name
        );
        let truth = Truth::render(&scene, factor, spp, orders);
        for (s, r) in settings.iter().zip(&parts) {
            let section = decompose(bench.name, &scene, s, factor, spp, (r, &truth));
            eprintln!("{section}");
            md.push_str(&section);
        }
    }
    write_report(out, "decomposition.md", &md)
}

/// One setting's real-time images per order (index 0: order 1; see [`real_time_orders`]).
pub struct RealTime {
    orders: Vec<LinearImage>,
    /// Order 1 drawn by the billboards from the exact single scattering (the path tracer's
    /// transmittance at every shading point): what the billboards alone cost.
    exact_single: LinearImage,
    /// The image itself, shading the whole `albedo (S_1 + S_m)` as the renderer does. The
    /// billboards take `S` log-linear along each chord piece, which does not add over parts, so
    /// the orders' images need not sum to it.
    image: LinearImage,
}

/// The path tracer's images of one scene split by order (index 0: order 1), the last holding
/// every order from its own on, and the two independent halves they average, for each part's
/// noise. Rendered once per scene, for every setting decomposed against it.
pub struct Truth {
    orders: Vec<LinearImage>,
    halves: [Vec<LinearImage>; 2],
}

pub(crate) fn energy(image: &LinearImage) -> f64 {
    image
        .pixels
        .iter()
        .map(|p| (p[0] + p[1] + p[2]) as f64)
        .sum()
}

fn sum(images: &[LinearImage]) -> LinearImage {
    let mut out = images[0].clone();
    for image in &images[1..] {
        for (o, p) in out.pixels.iter_mut().zip(&image.pixels) {
            (0..3).for_each(|c| o[c] += p[c]);
        }
    }
    out
}

/// The real-time image of the light a field of `albedo S` scatters, box-filtered by `factor`.
pub(crate) fn billboards(
    scene: &Scene,
    scattered: ScatteredLight,
    settings: &CloudQualitySettings,
    fine: &DensityGrid,
    factor: u32,
) -> LinearImage {
    let pixels = composite_scene_cloud(scene, 0, scattered, settings, fine);
    downsample(
        &LinearImage {
            width: scene.camera.width,
            height: scene.camera.height,
            pixels,
        },
        factor,
    )
}

/// Order images of the real-time transport: 1 (single), 2..=M+1 (the grid's orders), M+2 (the
/// closure); for an anisotropic medium, 1 (the exact beam) and 2 (everything else).
fn real_time_orders(
    scene: &Scene,
    ill: &CloudIllumination,
    settings: &CloudQualitySettings,
    factor: u32,
) -> Vec<LinearImage> {
    let albedo = ill.albedo;
    let grid = &ill.grid;
    if ill.anisotropy != 0.0 {
        // Albedo 0 in the depth scale: the beam through the whole optical depth.
        let exact =
            |x, ray| single_scattering_towards(&ill.lights, x, (0.0, ill.anisotropy), ray, None);
        let camera = (scene.camera.position - scene.clouds[0].translation).as_dvec3();
        let seen = ill.seen_from(camera, settings.compositing);
        return vec![
            billboards(
                scene,
                &|x, ray| exact(x, ray) * albedo,
                settings,
                &ill.fine,
                factor,
            ),
            billboards(
                scene,
                &|x, ray| seen.scattered_at(x, ray) - exact(x, ray) * albedo,
                settings,
                &ill.fine,
                factor,
            ),
        ];
    }
    let mut images = vec![billboards(
        scene,
        &|x, ray| {
            single_scattering_towards(&ill.lights, x, (albedo, ill.anisotropy), ray, None) * albedo
        },
        settings,
        &ill.fine,
        factor,
    )];
    for order in &ill.multiple.orders {
        images.push(billboards(
            scene,
            &|x, _| grid.sample_clamped(order, x) * albedo,
            settings,
            &ill.fine,
            factor,
        ));
    }
    let mut tail = ill.multiple.total.clone();
    for order in &ill.multiple.orders {
        tail.iter_mut().zip(order).for_each(|(t, s)| *t -= *s);
    }
    images.push(billboards(
        scene,
        &|x, _| grid.sample_clamped(&tail, x) * albedo,
        settings,
        &ill.fine,
        factor,
    ));
    images
}

/// The real-time images of `scene` at `settings`, per order, box-filtered by `factor`.
pub fn real_time(scene: &Scene, settings: &CloudQualitySettings, factor: u32) -> RealTime {
    let cloud = &scene.clouds[0];
    let ill = illuminate_scene_cloud(scene, 0, settings).expect("a cloud with density");
    let media = ParticleMedia::from_scene(scene);
    let lighting = Lighting::from_scene(scene);
    let albedo = ill.albedo;
    let exact_single = billboards(
        scene,
        &|x, ray| lighting.in_scattered(&media, x + cloud.translation.as_dvec3(), ray) * albedo,
        settings,
        &ill.fine,
        factor,
    );
    RealTime {
        orders: real_time_orders(scene, &ill, settings, factor),
        exact_single,
        image: grid_error::image(scene, &ill, settings, factor),
    }
}

impl RealTime {
    /// Order images this setting has (the last holding every order from its own on).
    pub fn orders(&self) -> usize {
        self.orders.len()
    }
}

impl Truth {
    /// Two independent path-traced renders of `scene` at `spp` each, at `1 / factor` of its
    /// size, split into `orders` images.
    pub fn render(scene: &Scene, factor: u32, spp: u32, orders: usize) -> Self {
        let mut small = scene.clone();
        small.camera.width /= factor;
        small.camera.height /= factor;
        let half = |seed| -> Vec<LinearImage> {
            let (bar, progress) =
                crate::path_tracing_progress(&format!("orders, seed {seed}"), small.camera.height);
            let images = render_orders(
                &small,
                &PathTracerSettings {
                    samples_per_pixel: spp,
                    seed,
                    progress: Some(progress),
                    time_limit: None,
                },
                orders + 1, // index 0: the background
            );
            bar.finish_and_clear();
            images
                .into_iter()
                .skip(1)
                .map(|pixels| LinearImage {
                    width: small.camera.width,
                    height: small.camera.height,
                    pixels,
                })
                .collect()
        };
        let halves = [half(1), half(2)];
        let orders = halves[0]
            .iter()
            .zip(&halves[1])
            .map(|(a, b)| {
                let mut mean = a.clone();
                for (m, p) in mean.pixels.iter_mut().zip(&b.pixels) {
                    (0..3).for_each(|c| m[c] = 0.5 * (m[c] + p[c]));
                }
                mean
            })
            .collect();
        Truth { orders, halves }
    }
}

/// `images` (per order) regrouped into `n`: the orders from the `n`-th on summed into the last.
fn regrouped(images: &[LinearImage], n: usize) -> Vec<LinearImage> {
    let mut out = images[..n - 1].to_vec();
    out.push(sum(&images[n - 1..]));
    out
}

/// Relative RMSE of `x` against the mean of the two halves, and the mean's noise.
fn error(x: &LinearImage, truth: &LinearImage, halves: [&LinearImage; 2]) -> (f64, f64) {
    let noise = noise_level(&halves[0].pixels, &halves[1].pixels) / std::f64::consts::SQRT_2;
    (relative_rmse(&x.pixels, &truth.pixels), noise)
}

/// One setting's images against the truth regrouped to its orders.
struct Parts<'a> {
    real_time: &'a [LinearImage],
    exact_single: &'a LinearImage,
    truth: Vec<LinearImage>,
    halves: [Vec<LinearImage>; 2],
}

/// The markdown section of one scene at one setting.
pub fn decompose(
    name: &str,
    scene: &Scene,
    settings: &CloudQualitySettings,
    factor: u32,
    spp: u32,
    (real_time, truth): (&RealTime, &Truth),
) -> String {
    let n = real_time.orders.len();
    let p = Parts {
        real_time: &real_time.orders,
        exact_single: &real_time.exact_single,
        truth: regrouped(&truth.orders, n),
        halves: [0, 1].map(|h| regrouped(&truth.halves[h], n)),
    };
    let mut s = format!(
        "\n### {name}\n\nReference: 2 × {spp} spp at {}×{}. Settings: `{settings:?}`.\n\n",
        scene.camera.width / factor,
        scene.camera.height / factor
    );
    let multiple = |images: &[LinearImage]| sum(&images[1..]);
    let (parts, whole) = (sum(p.real_time), sum(&p.truth));
    let whole_halves = [sum(&p.halves[0]), sum(&p.halves[1])];
    let rows = [
        ("single scattering (order 1)", {
            error(
                &p.real_time[0],
                &p.truth[0],
                [&p.halves[0][0], &p.halves[1][0]],
            )
        }),
        ("order 1, billboards shading the exact S_1", {
            error(
                p.exact_single,
                &p.truth[0],
                [&p.halves[0][0], &p.halves[1][0]],
            )
        }),
        ("multiple scattering (orders ≥ 2)", {
            let (a, b) = (multiple(&p.halves[0]), multiple(&p.halves[1]));
            error(&multiple(p.real_time), &multiple(&p.truth), [&a, &b])
        }),
        ("everything (the parts' sum)", {
            error(&parts, &whole, [&whole_halves[0], &whole_halves[1]])
        }),
        ("the image itself", {
            error(
                &real_time.image,
                &whole,
                [&whole_halves[0], &whole_halves[1]],
            )
        }),
    ];
    s.push_str("| part | relative RMSE | reference noise | denoised | energy real-time / truth |\n|---|---:|---:|---:|---:|\n");
    let energies = [
        energy(&p.real_time[0]) / energy(&p.truth[0]),
        energy(p.exact_single) / energy(&p.truth[0]),
        energy(&multiple(p.real_time)) / energy(&multiple(&p.truth)),
        energy(&parts) / energy(&whole),
        energy(&real_time.image) / energy(&whole),
    ];
    for ((label, (e, noise)), ratio) in rows.iter().zip(energies) {
        let _ = writeln!(
            s,
            "| {label} | {e:.4} | {noise:.4} | {:.4} | {ratio:.3} |",
            (e * e - noise * noise).max(0.0).sqrt()
        );
    }
    let _ = writeln!(
        s,
        "\nThe parts sum to {:.4} of the image's light: each part is drawn on its own, and the \
         billboards take `S` log-linear along each chord piece, which does not add over parts.",
        energy(&parts) / energy(&real_time.image)
    );
    s.push_str("\n| order | energy real-time | energy truth | real-time / truth | λ real-time | λ truth |\n|---|---:|---:|---:|---:|---:|\n");
    let last = p.real_time.len() - 1;
    for (n, (rt, truth)) in p.real_time.iter().zip(&p.truth).enumerate() {
        let (e_rt, e_tr) = (energy(rt), energy(truth));
        let lambda = |images: &[LinearImage]| {
            (n > 0 && n < last).then(|| energy(&images[n]) / energy(&images[n - 1]))
        };
        let fmt = |v: Option<f64>| v.map_or("".into(), |v| format!("{v:.3}"));
        let anisotropic = scene.clouds[0].medium.anisotropy != 0.0;
        let label = if n == last && anisotropic {
            format!("≥ {} (δ-Eddington beam and grid)", n + 1)
        } else if n == last {
            format!("≥ {} (closure)", n + 1)
        } else {
            format!("{}", n + 1)
        };
        let _ = writeln!(
            s,
            "| {label} | {e_rt:.4e} | {e_tr:.4e} | {:.3} | {} | {} |",
            e_rt / e_tr,
            fmt(lambda(p.real_time)),
            fmt(lambda(&p.truth)),
        );
    }
    s
}
