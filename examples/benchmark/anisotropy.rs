//! `--anisotropy`: variants of the multiple scattering of a Henyey–Greenstein medium, computed
//! with the f64 CPU reference and compared with the path tracer (experiment).

use std::f64::consts::PI;

use bevy::math::DVec3;
use bevy_particle_clouds::{
    CloudQualitySettings,
    image_io::LinearImage,
    reference::{
        camera::PinholeCamera,
        composite::{BillboardCloud, BillboardCompositing, CloudPlacement, composite},
        illumination::{
            CloudIllumination, DensityGrid, illuminate_scene_cloud, lattice_directions,
            order_ratio, segment_weights, single_scattering_towards,
        },
        metrics::relative_rmse,
    },
    scene::Scene,
};
use rayon::prelude::*;

use super::*;

/// Radiance moments of a voxel: the mean `(1/4π) ∫ L` and the flux `(1/4π) ∫ L ω` (per axis, RGB).
#[derive(Clone, Copy, Default, Debug)]
struct Moments {
    mean: DVec3,
    flux: [DVec3; 3],
    /// (1/4π) ∫ L ω ω^T: xx, yy, zz, xy, xz, yz.
    second: [DVec3; 6],
}

fn outer(w: DVec3) -> [f64; 6] {
    [w.x * w.x, w.y * w.y, w.z * w.z, w.x * w.y, w.x * w.z, w.y * w.z]
}

fn weight(o: [i64; 3], lebedev: bool) -> f64 {
    if !lebedev {
        return 1.0 / 26.0;
    }
    match o.iter().filter(|c| **c != 0).count() {
        1 => 1.0 / 21.0,
        2 => 4.0 / 105.0,
        _ => 9.0 / 280.0,
    }
}

impl Moments {
    fn along(&self, w: DVec3) -> DVec3 {
        self.flux[0] * w.x + self.flux[1] * w.y + self.flux[2] * w.z
    }
    fn add(&mut self, o: &Moments, k: DVec3) {
        self.mean += o.mean * k;
        for a in 0..3 {
            self.flux[a] += o.flux[a] * k;
        }
        for a in 0..6 {
            self.second[a] += o.second[a] * k;
        }
    }
    fn of(i: DVec3, w: DVec3, weight: f64) -> Moments {
        let q = outer(w);
        Moments {
            mean: i * weight,
            flux: [i * (w.x * weight), i * (w.y * weight), i * (w.z * weight)],
            second: std::array::from_fn(|a| i * (q[a] * weight)),
        }
    }
    /// The l = 2 term of the in-scattered radiance towards `w` per unit g².
    fn quadrupole(&self, w: DVec3) -> DVec3 {
        let q = outer(w);
        let wmw = self.second[0] * q[0] + self.second[1] * q[1] + self.second[2] * q[2]
            + (self.second[3] * q[3] + self.second[4] * q[4] + self.second[5] * q[5]) * 2.0;
        (wmw * 3.0 - self.mean) * 2.5
    }
    /// In-scattered radiance towards `w` with a P1 phase function of asymmetry `g`.
    fn scattered(&self, g: f64, w: DVec3) -> DVec3 {
        self.mean + self.along(w) * (3.0 * g)
    }
}

#[derive(Clone, Copy, Debug)]
pub(crate) enum G {
    Zero,
    True,
    Reduced,
}

#[derive(Clone, Copy, Debug)]
pub(crate) struct Variant {
    pub(crate) name: &'static str,
    /// δ-Eddington: the grid sweeps the scaled medium (f = g²) from the scaled beam.
    pub(crate) delta: bool,
    pub(crate) g_sweep: G,
    pub(crate) g_final: G,
    /// Clamp the seen multiple scattering at 0.
    pub(crate) clamp: bool,
    pub(crate) lebedev: bool,
    pub(crate) p2_seen: bool,
    /// The δ-excess E (T_c - T) seen with HG(g²) instead of HG(g).
    pub(crate) excess_g2: bool,
    /// The closure's tail carries no second moment.
    pub(crate) tail_q0: bool,
}

pub(crate) const VARIANTS: &[Variant] = &[
    Variant { name: "isotropic (today)", delta: false, g_sweep: G::Zero, g_final: G::Zero, clamp: true, lebedev: false, p2_seen: false, excess_g2: false, tail_q0: false },
    Variant { name: "P1 g, true medium", delta: false, g_sweep: G::True, g_final: G::True, clamp: true, lebedev: false, p2_seen: false, excess_g2: false, tail_q0: false },
    Variant { name: "P1 g sweep only", delta: false, g_sweep: G::True, g_final: G::Zero, clamp: true, lebedev: false, p2_seen: false, excess_g2: false, tail_q0: false },
    Variant { name: "P1 g seen only", delta: false, g_sweep: G::Zero, g_final: G::True, clamp: true, lebedev: false, p2_seen: false, excess_g2: false, tail_q0: false },
    Variant { name: "dE: g' sweep, g seen", delta: true, g_sweep: G::Reduced, g_final: G::True, clamp: true, lebedev: false, p2_seen: false, excess_g2: false, tail_q0: false },
    Variant { name: "dE: g' sweep, g' seen", delta: true, g_sweep: G::Reduced, g_final: G::Reduced, clamp: true, lebedev: false, p2_seen: false, excess_g2: false, tail_q0: false },
    Variant { name: "dE: g' sweep, iso seen", delta: true, g_sweep: G::Reduced, g_final: G::Zero, clamp: true, lebedev: false, p2_seen: false, excess_g2: false, tail_q0: false },
    Variant { name: "dE: iso sweep, g seen", delta: true, g_sweep: G::Zero, g_final: G::True, clamp: true, lebedev: false, p2_seen: false, excess_g2: false, tail_q0: false },
    Variant { name: "isotropic, Lebedev", delta: false, g_sweep: G::Zero, g_final: G::Zero, clamp: true, lebedev: true, p2_seen: false, excess_g2: false, tail_q0: false },
    Variant { name: "dE, Lebedev", delta: true, g_sweep: G::Reduced, g_final: G::True, clamp: true, lebedev: true, p2_seen: false, excess_g2: false, tail_q0: false },
    Variant { name: "dE, P2 seen", delta: true, g_sweep: G::Reduced, g_final: G::True, clamp: true, lebedev: false, p2_seen: true, excess_g2: false, tail_q0: false },
    Variant { name: "dE, excess g2", delta: true, g_sweep: G::Reduced, g_final: G::True, clamp: true, lebedev: false, p2_seen: false, excess_g2: true, tail_q0: false },
    Variant { name: "dE, P2 seen, excess g2", delta: true, g_sweep: G::Reduced, g_final: G::True, clamp: true, lebedev: false, p2_seen: true, excess_g2: true, tail_q0: false },
    Variant { name: "dE, P2 seen, tail Q 0", delta: true, g_sweep: G::Reduced, g_final: G::True, clamp: true, lebedev: false, p2_seen: true, excess_g2: false, tail_q0: true },
    Variant { name: "dE, Lebedev, P2 seen", delta: true, g_sweep: G::Reduced, g_final: G::True, clamp: true, lebedev: true, p2_seen: true, excess_g2: false, tail_q0: false },
];

struct Grid<'a> {
    grid: &'a DensityGrid,
    k: f64,
    albedo: f64,
}

fn sweep_direction(m: &Grid, o: [i64; 3], s: &[Moments], g: f64, sky: DVec3) -> Vec<DVec3> {
    let grid = m.grid;
    let n = grid.n as i64;
    let len = ((o[0] * o[0] + o[1] * o[1] + o[2] * o[2]) as f64).sqrt();
    let step = grid.h * len;
    let travel = -DVec3::new(o[0] as f64, o[1] as f64, o[2] as f64) / len;
    let mut radiance = vec![DVec3::ZERO; grid.len()];
    let order = |a: usize, i: i64| if o[a] > 0 { n - 1 - i } else { i };
    let j_at = |i: usize| s[i].scattered(g, travel) * m.albedo;
    for kk in 0..n {
        for jj in 0..n {
            for ii in 0..n {
                let v = [order(0, ii), order(1, jj), order(2, kk)];
                let idx = grid.index(v[0] as usize, v[1] as usize, v[2] as usize);
                let u = [v[0] + o[0], v[1] + o[1], v[2] + o[2]];
                let upwind = u
                    .iter()
                    .all(|&c| (0..n).contains(&c))
                    .then(|| grid.index(u[0] as usize, u[1] as usize, u[2] as usize));
                let (rho_u, j_u, i_u) =
                    upwind.map_or((0.0, DVec3::ZERO, sky), |j| (grid.rho[j], j_at(j), radiance[j]));
                let j = j_at(idx);
                let tau = m.k * (grid.rho[idx] + rho_u) * 0.5 * step;
                let (constant, linear) = segment_weights(tau);
                radiance[idx] = i_u * (1.0 - constant) + j * constant + (j_u - j) * linear;
            }
        }
    }
    radiance
}

fn sweep(m: &Grid, s: &[Moments], g: f64, sky: DVec3, lebedev: bool) -> Vec<Moments> {
    lattice_directions()
        .into_par_iter()
        .map(|o| {
            let len = ((o[0] * o[0] + o[1] * o[1] + o[2] * o[2]) as f64).sqrt();
            let travel = -DVec3::new(o[0] as f64, o[1] as f64, o[2] as f64) / len;
            sweep_direction(m, o, s, g, sky)
                .into_iter()
                .map(|i| Moments::of(i, travel, weight(o, lebedev)))
                .collect::<Vec<_>>()
        })
        .reduce(
            || vec![Moments::default(); s.len()],
            |mut a, b| {
                a.iter_mut().zip(&b).for_each(|(x, y)| x.add(y, DVec3::ONE));
                a
            },
        )
}

/// The beam's moments gathered per scattering voxel (density-weighted over fine children).
fn source(ill: &CloudIllumination, depth_scale: f64) -> Vec<Moments> {
    let (grid, fine) = (&ill.grid, &ill.fine);
    let f = fine.n / grid.n;
    (0..grid.len())
        .into_par_iter()
        .map(|idx| {
            let (i, j, k) = (idx % grid.n, (idx / grid.n) % grid.n, idx / (grid.n * grid.n));
            let (mut weighted, mut mass, mut plain) = (Moments::default(), 0.0, Moments::default());
            for child in 0..f * f * f {
                let (a, b, c) = (child % f, (child / f) % f, child / (f * f));
                let (fi, fj, fk) = (i * f + a, j * f + b, k * f + c);
                let p = fine.voxel_centre(fi, fj, fk);
                let mut m = Moments::default();
                for (vol, e) in &ill.lights {
                    let t = *e * (-vol.optical_depth_at(p) * depth_scale).exp() / (4.0 * PI);
                    let d = vol.basis[2];
                    m.add(&Moments::of(t, d, 1.0), DVec3::ONE);
                }
                let rho = fine.rho[fine.index(fi, fj, fk)];
                weighted.add(&m, DVec3::splat(rho));
                mass += rho;
                plain.add(&m, DVec3::ONE);
            }
            let mut out = Moments::default();
            if mass > 0.0 {
                out.add(&weighted, DVec3::splat(1.0 / mass));
            } else {
                out.add(&plain, DVec3::splat(1.0 / (f * f * f) as f64));
            }
            out
        })
        .collect()
}

fn g_of(which: G, g: f64, f: f64) -> f64 {
    match which {
        G::Zero => 0.0,
        G::True => g,
        G::Reduced => (g - f) / (1.0 - f),
    }
}

/// The seen multiple scattering of `variant`: per voxel moments summed over orders and closed.
fn multiple(ill: &CloudIllumination, v: &Variant, iterations: u32, sky: DVec3) -> Vec<Moments> {
    let g = ill.anisotropy;
    let f = if v.delta { g * g } else { 0.0 };
    let albedo = ill.albedo;
    let m = Grid {
        grid: &ill.grid,
        k: ill.k_local * (1.0 - albedo * f),
        albedo: albedo * (1.0 - f) / (1.0 - albedo * f),
    };
    let scale = if v.delta { 1.0 - albedo * f } else { 1.0 };
    let s0 = source(ill, scale);
    let gs = g_of(v.g_sweep, g, f);
    let mut orders: Vec<Vec<Moments>> = Vec::new();
    for k in 0..iterations {
        let prev = orders.last().unwrap_or(&s0);
        orders.push(sweep(&m, prev, gs, if k == 0 { sky } else { DVec3::ZERO }, v.lebedev));
    }
    let means = |o: &[Moments]| o.iter().map(|x| x.mean).collect::<Vec<_>>();
    let last = orders.last().unwrap();
    let before = if orders.len() >= 2 { &orders[orders.len() - 2] } else { &s0 };
    let ratio = order_ratio(&ill.grid, &means(last), &means(before));
    let tail = ratio / (DVec3::ONE - ratio);
    let mut total = vec![Moments::default(); s0.len()];
    for o in &orders {
        total.iter_mut().zip(o).for_each(|(t, x)| t.add(x, DVec3::ONE));
    }
    total.iter_mut().zip(last).for_each(|(t, x)| {
        let mut x = *x;
        if v.tail_q0 {
            x.second = [DVec3::ZERO; 6];
            // Keep the trace: the tail's M is isotropic, mean I / 3.
            for a in 0..3 {
                x.second[a] = x.mean / 3.0;
            }
        }
        t.add(&x, tail)
    });
    total
}

#[derive(Clone, Copy, PartialEq)]
enum Part {
    All,
    /// Exact single scattering (unscaled beam).
    Single,
    /// Everything but that.
    Rest,
}

fn image(scene: &Scene, ill: &CloudIllumination, v: &Variant, settings: &CloudQualitySettings) -> LinearImage {
    image_part(scene, ill, v, settings, Part::All)
}

fn image_part(scene: &Scene, ill: &CloudIllumination, v: &Variant, settings: &CloudQualitySettings, part: Part) -> LinearImage {
    let total = multiple(ill, v, settings.scatter_iterations, scene.background.as_dvec3());
    let g = ill.anisotropy;
    let f = if v.delta { g * g } else { 0.0 };
    let gf = g_of(v.g_final, g, f);
    let mean: Vec<DVec3> = total.iter().map(|m| m.mean).collect();
    let flux: [Vec<DVec3>; 3] = std::array::from_fn(|a| total.iter().map(|m| m.flux[a]).collect());
    let second: [Vec<DVec3>; 6] = std::array::from_fn(|a| total.iter().map(|m| m.second[a]).collect());
    let albedo = ill.albedo;
    let scattered = |x: DVec3, ray: DVec3| {
        let single = if v.excess_g2 {
            single_scattering_towards(&ill.lights, x, (0.0, g), ray)
                + single_scattering_towards(&ill.lights, x, (albedo, g * g), ray)
                    * 0.0
                + ill.lights.iter().fold(DVec3::ZERO, |acc, (vol, e)| {
                    let tau = vol.optical_depth_at(x);
                    let c = 1.0 - albedo * g * g;
                    let cos = -vol.basis[2].dot(ray);
                    acc + *e * (((-c * tau).exp() - (-tau).exp())
                        * bevy_particle_clouds::math::henyey_greenstein(g * g, cos))
                })
        } else {
            single_scattering_towards(&ill.lights, x, (albedo, g), ray)
        };
        let w = -ray;
        let s = ill.grid.sample_clamped(&mean, x)
            + (ill.grid.sample_clamped(&flux[0], x) * w.x
                + ill.grid.sample_clamped(&flux[1], x) * w.y
                + ill.grid.sample_clamped(&flux[2], x) * w.z)
                * (3.0 * gf);
        let s = if v.p2_seen {
            let at = Moments {
                mean: ill.grid.sample_clamped(&mean, x),
                flux: [DVec3::ZERO; 3],
                second: std::array::from_fn(|a| ill.grid.sample_clamped(&second[a], x)),
            };
            s + at.quadrupole(w) * (gf * gf)
        } else {
            s
        };
        let s = if v.clamp { s.max(DVec3::ZERO) } else { s };
        let exact = single_scattering_towards(&ill.lights, x, (0.0, g), ray);
        match part {
            Part::All => (single + s) * albedo,
            Part::Single => exact * albedo,
            Part::Rest => (single + s - exact) * albedo,
        }
    };
    let cloud = &scene.clouds[0];
    let billboards = BillboardCloud {
        particles: &cloud.particles,
        world_from_local: CloudPlacement::at(cloud.translation.as_dvec3()),
        medium: cloud.medium,
        scattered: &scattered,
        segments: settings.chord_segments,
        compositing: BillboardCompositing::new(settings.compositing, &ill.fine),
    };
    let camera = PinholeCamera::from_scene(&scene.camera);
    let background = if part == Part::All { scene.background.as_dvec3() } else { DVec3::ZERO };
    let pixels = composite(&camera, background, &[], &[billboards], 1.0);
    LinearImage { width: scene.camera.width, height: scene.camera.height, pixels }
}

pub(crate) fn anisotropy_benchmark(args: &Args, chosen: &[&BenchScene]) -> Result<(), String> {
    let settings = args.settings.first().copied().unwrap_or_default();
    for bench in chosen {
        let scene = load_scene(bench)?;
        let spp = args.spp.unwrap_or(bench.spp);
        let reference = reference(&scene, bench, spp, &args.out)?;
        let ill = illuminate_scene_cloud(&scene, 0, &settings).ok_or("no density")?;
        let truth = LinearImage { width: reference.width, height: reference.height, pixels: reference.image.clone() };
        let boxed_truth = downsample(&truth, 4);
        if std::env::var_os("ANISOTROPY_SPLIT").is_some() {
            split(&scene, bench, &ill, &settings, spp);
        }
        let only = std::env::var("ANISOTROPY_ONLY").ok();
        for v in VARIANTS.iter().filter(|v| only.as_ref().is_none_or(|o| o.split(';').any(|n| n == v.name))) {
            let img = downsample(&image(&scene, &ill, v, &settings), bench.error_downsample);
            let sky = scene.background;
            let e = relative_rmse(
                &cloud_pixels(&img.pixels, &truth.pixels, sky),
                &cloud_pixels(&truth.pixels, &truth.pixels, sky),
            );
            let e4 = relative_rmse(
                &cloud_pixels(&downsample(&img, 4).pixels, &boxed_truth.pixels, sky),
                &cloud_pixels(&boxed_truth.pixels, &boxed_truth.pixels, sky),
            );
            let energy = |p: &[[f32; 4]]| p.iter().map(|x| (x[0] + x[1] + x[2]) as f64).sum::<f64>();
            println!(
                "{:<24} {:<28} rel RMSE {:.4} (denoised {:.4}), 4x4 box {:.4} (denoised {:.4}), energy {:.3}",
                bench.name,
                v.name,
                e,
                denoised(e, reference.noise),
                e4,
                denoised(e4, reference.noise_box4),
                energy(&img.pixels) / energy(&truth.pixels)
            );
            let _ = write_png(
                &side_by_side(&img, &truth),
                &args.out.join(format!("{}-{}.png", bench.name, v.name.replace([' ', ':', ',', '\'', '(', ')'], "_"))),
            );
        }
    }
    Ok(())
}

fn split(scene: &Scene, bench: &BenchScene, ill: &CloudIllumination, settings: &CloudQualitySettings, spp: u32) {
    use bevy_particle_clouds::reference::path_tracer::{PathTracerSettings, render_orders};
    let factor = bench.error_downsample;
    let mut small = scene.clone();
    small.camera.width /= factor;
    small.camera.height /= factor;
    let halves: Vec<Vec<Vec<[f32; 4]>>> = [1u64, 2]
        .iter()
        .map(|&seed| render_orders(&small, &PathTracerSettings { samples_per_pixel: spp, seed, progress: None }, 3))
        .collect();
    let energy = |p: &[[f32; 4]]| p.iter().map(|x| (x[0] + x[1] + x[2]) as f64).sum::<f64>();
    for k in 1..3 {
        let truth: Vec<[f32; 4]> = halves[0][k].iter().zip(&halves[1][k]).map(|(a, b)| std::array::from_fn(|c| 0.5 * (a[c] + b[c]))).collect();
        let noise = noise_level(&halves[0][k], &halves[1][k]) / std::f64::consts::SQRT_2;
        let part = if k == 1 { Part::Single } else { Part::Rest };
        for v in [&VARIANTS[0], &VARIANTS[4], &VARIANTS[10]] {
            let img = downsample(&image_part(scene, ill, v, settings, part), factor);
            let e = relative_rmse(&img.pixels, &truth);
            println!(
                "{:<24} {:<28} order {} rel RMSE {:.4} (noise {:.4}, denoised {:.4}), energy {:.3}",
                bench.name, v.name, if k == 1 { "1" } else { ">=2" }, e, noise, denoised(e, noise), energy(&img.pixels) / energy(&truth)
            );
            let t = LinearImage { width: img.width, height: img.height, pixels: truth.clone() };
            let _ = write_png(&side_by_side(&img, &t), &std::path::PathBuf::from(format!("/tmp/bench/split-{}-{}-{}.png", bench.name, k, v.name.replace([' ', ':', ',', '\'', '(', ')'], "_"))));
        }
    }
}
