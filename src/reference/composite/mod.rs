//! CPU reference of the final billboard render (`docs/illumination.md`, "Draw"; docs/physics.md, "The
//! particle approximation").
//!
//! Every particle is a camera-facing disc whose opacity along a pixel ray is `1 - exp(-tau)`, `tau`
//! the optical depth of the ray's chord through the particle's sphere. Its colour is the
//! scattered light along that chord, cut into `K` equal segments. Two compositings
//! ([`Compositing`]):
//!
//! - view transmittance: each segment's light is seen through the whole cloud's optical depth
//!   towards the camera (a [`ViewVolume`]), shares the segment's extinction with the other
//!   particles there in proportion to its own, and `S` is taken log-linear between the segment's
//!   ends; the particles' light adds up and what is behind is multiplied by every particle's
//!   transmittance, in any order;
//! - sorted: each segment contributes `albedo S` at its midpoint times its own opacity and the
//!   transmittance of the segments in front of it; particles are blended back to front.
//!
//! Clouds are composited in the order given (the caller orders them back to front, as Bevy's
//! transparent phase does per entity), except that consecutive view-transmittance clouds make
//! one layer: each particle's light is seen through the view volumes of all of them, so clouds
//! that interpenetrate composite correctly in any order.
//!
//! With distance fog ([`composite_fogged`]), each segment is fogged at its own distance, its
//! share of the view as its coverage (docs/physics.md, "Fog"); objects are fogged, the
//! background is not (as in Bevy).

use bevy::math::{DQuat, DVec3};
use rayon::prelude::*;

use crate::fog::Fog;
use crate::particle::{Medium, Particle};
use crate::reference::camera::PinholeCamera;
use crate::reference::geometry::nearest_object;
use crate::reference::illumination::DensityGrid;
use crate::reference::view_volume::ViewVolume;
use crate::scene::{Scene, SceneObject};
use crate::settings::{BillboardShading, CloudQualitySettings, Compositing};

/// A cloud's `Transform`: world point = `translation + rotation * (scale * local)`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CloudPlacement {
    /// World translation of the local origin, metres.
    pub translation: DVec3,
    /// Unit rotation `R`.
    pub rotation: DQuat,
    /// Uniform scale `s > 0`.
    pub scale: f64,
}

impl CloudPlacement {
    /// No rotation, unit scale, at `translation`.
    pub fn at(translation: DVec3) -> Self {
        Self {
            translation,
            rotation: DQuat::IDENTITY,
            scale: 1.0,
        }
    }

    /// World position of a local point.
    pub fn world_point(&self, local: DVec3) -> DVec3 {
        self.translation + self.rotation * (local * self.scale)
    }

    /// Local position of a world point.
    pub fn local_point(&self, world: DVec3) -> DVec3 {
        self.rotation.inverse() * (world - self.translation) / self.scale
    }

    /// Local direction of a world unit direction (unit).
    pub fn local_direction(&self, world: DVec3) -> DVec3 {
        self.rotation.inverse() * world
    }
}

/// What a cloud scatters towards the camera at a cloud-local point, given the view ray's unit
/// direction in cloud-local space: `albedo * S(x, w)`, radiance in the units of `E` (e.g.
/// [`CloudIllumination::scattered_at`](crate::reference::illumination::CloudIllumination::scattered_at)).
pub type ScatteredLight<'a> = &'a (dyn Fn(DVec3, DVec3) -> DVec3 + Sync);

/// One cloud as the compositor draws it.
#[derive(Clone, Copy)]
pub struct BillboardCloud<'a> {
    /// Particles in cloud-local space.
    pub particles: &'a [Particle],
    /// The cloud's transform.
    pub world_from_local: CloudPlacement,
    /// The medium; only `extinction` (world, 1/m) is used here, the albedo is in `scattered`.
    pub medium: Medium,
    /// The light scattered at each shading point.
    pub scattered: ScatteredLight<'a>,
    /// Segments `K >= 1` of each chord (`chord_segments`).
    pub segments: u32,
    /// How the particles are composited.
    pub compositing: BillboardCompositing<'a>,
    /// Where the scattered light is evaluated (`billboard_shading`).
    pub shading: BillboardShading,
}

impl BillboardCloud<'_> {
    /// The scattered light the billboard of the particle centred at world `centre` shows at world
    /// point `x` of a pixel's ray along world `w` from a camera at `eye`: evaluated there, or with
    /// [`BillboardShading::Centre`] at the centre towards the camera.
    fn shade(&self, x: DVec3, w: DVec3, eye: DVec3, centre: DVec3) -> DVec3 {
        let (at, along) = match self.shading {
            BillboardShading::Chord => (x, w),
            BillboardShading::Centre => (centre, (centre - eye).normalize()),
        };
        let local = &self.world_from_local;
        (self.scattered)(local.local_point(at), local.local_direction(along))
    }
}

/// [`Compositing`] with what it needs.
#[derive(Clone, Copy)]
pub enum BillboardCompositing<'a> {
    /// Through the view transmittance marched in this fine density grid (cloud-local, `rho`).
    ViewTransmittance(&'a DensityGrid),
    /// Sorted back to front.
    Sorted,
}

impl<'a> BillboardCompositing<'a> {
    /// The compositing `settings` choose; `fine` is the cloud's fine density grid
    /// ([`CloudIllumination::fine`](crate::reference::illumination::CloudIllumination::fine)).
    pub fn new(compositing: Compositing, fine: &'a DensityGrid) -> Self {
        match compositing {
            Compositing::ViewTransmittance => Self::ViewTransmittance(fine),
            Compositing::Sorted => Self::Sorted,
        }
    }
}

/// A particle prepared for one camera: world centre, world radius `R = s r`, view depth `z_c`.
#[derive(Clone, Copy, Debug)]
struct Billboard {
    centre: DVec3,
    radius: f64,
    density: f64,
    depth: f64,
}

/// One cloud's billboards sorted back to front (descending `z_c`), and its view volume when it is
/// composited through one.
struct SortedCloud<'a> {
    cloud: &'a BillboardCloud<'a>,
    billboards: Vec<Billboard>,
    view: Option<ViewVolume>,
}

fn sort_cloud<'a>(camera: &PinholeCamera, cloud: &'a BillboardCloud<'a>) -> SortedCloud<'a> {
    let placement = &cloud.world_from_local;
    let mut billboards: Vec<Billboard> = cloud
        .particles
        .iter()
        .filter(|p| p.density > 0.0)
        .map(|p| {
            let centre = placement.world_point(p.position.as_dvec3());
            Billboard {
                centre,
                radius: placement.scale * p.radius as f64,
                density: p.density as f64,
                depth: camera.view_depth(centre),
            }
        })
        .collect();
    // Stable, so particles at equal depth keep their input order.
    billboards.sort_by(|a, b| b.depth.total_cmp(&a.depth));
    let view = match cloud.compositing {
        BillboardCompositing::ViewTransmittance(fine) => ViewVolume::march(
            camera,
            fine,
            &cloud.world_from_local,
            cloud.medium.extinction as f64,
        ),
        BillboardCompositing::Sorted => None,
    };
    SortedCloud {
        cloud,
        billboards,
        view,
    }
}

/// Fills each view volume's front map from the other clouds' volumes wholly in front of it, as
/// the GPU does once per view.
fn sum_fronts(sorted: &mut [SortedCloud]) {
    let views: Vec<ViewVolume> = sorted.iter().filter_map(|s| s.view.clone()).collect();
    for view in sorted.iter_mut().filter_map(|s| s.view.as_mut()) {
        let fronts: Vec<&ViewVolume> = views
            .iter()
            .filter(|v| v.wholly_in_front_of(view))
            .collect();
        view.sum_front(fronts.into_iter());
    }
}

/// `F(s) = q² s - 2 q s³ / (3 R²) + s⁵ / (5 R⁴)`, the antiderivative of `(q - s²/R²)²`.
fn chord_antiderivative(q: f64, r: f64, s: f64) -> f64 {
    let (r2, s2) = (r * r, s * s);
    s * (q * q - 2.0 * q * s2 / (3.0 * r2) + s2 * s2 / (5.0 * r2 * r2))
}

/// The visible part of a pixel ray's chord through a particle: `s` runs along the ray from the
/// point closest to the centre (at ray parameter `t_c`), the chord covers `s0..s1`, and
/// `q = 1 - b²/R²`.
struct Chord {
    /// Depth of the billboard: the particle's view depth, or the near plane.
    depth: f64,
    t_c: f64,
    q: f64,
    s0: f64,
    s1: f64,
}

/// Where a billboard sits along pixel ray `w` and which part of its chord is seen, or `None` when
/// the ray misses the particle (`q <= 0`) or the visible chord is empty.
fn chord(camera: &PinholeCamera, w: DVec3, bb: &Billboard) -> Option<Chord> {
    let oc = bb.centre - camera.position;
    let t_c = oc.dot(w);
    let r = bb.radius;
    let q = 1.0 - (oc - w * t_c).length_squared() / (r * r);
    if q <= 0.0 {
        return None;
    }
    let s1 = r * q.sqrt();
    if bb.depth - r >= camera.near {
        // Wholly beyond the near plane: the full chord, billboard at the particle's depth.
        return Some(Chord {
            depth: bb.depth,
            t_c,
            q,
            s0: -s1,
            s1,
        });
    }
    // The sphere reaches the near plane: only the chord beyond it counts, billboard on the plane.
    let s0 = (-s1).max(camera.near / w.dot(camera.forward) - t_c);
    (s0 < s1).then_some(Chord {
        depth: camera.near,
        t_c,
        q,
        s0,
        s1,
    })
}

/// The `K` equal segments `(a, b, tau)` of a particle's visible chord, front to back: their ends
/// along the ray (from the closest point) and their optical depth.
fn segments<'a>(
    bb: &'a Billboard,
    chord: &'a Chord,
    cloud: &BillboardCloud,
) -> impl Iterator<Item = (f64, f64, f64)> + 'a {
    let sigma = cloud.medium.extinction as f64 * bb.density;
    let k = cloud.segments.max(1);
    let ds = (chord.s1 - chord.s0) / k as f64;
    (0..k).map(move |i| {
        let (a, b) = (chord.s0 + ds * i as f64, chord.s0 + ds * (i + 1) as f64);
        let depth = |s| chord_antiderivative(chord.q, bb.radius, s);
        (a, b, (sigma * (depth(b) - depth(a))).max(0.0))
    })
}

/// Premultiplied radiance and alpha of one particle along pixel ray `w`: `K` equal segments of the
/// chord, front to back, each `(1 - exp(-tau_k))` times the transmittance in front of it times the
/// scattered light at its midpoint.
fn particle_radiance(
    camera: &PinholeCamera,
    w: DVec3,
    bb: &Billboard,
    chord: &Chord,
    cloud: &BillboardCloud,
    seen: &Seen,
) -> (DVec3, f64) {
    let (mut colour, mut transmittance) = (DVec3::ZERO, 1.0);
    for (a, b, tau) in segments(bb, chord, cloud) {
        let t = chord.t_c + 0.5 * (a + b);
        let x = camera.position + w * t;
        let coverage = transmittance * -(-tau).exp_m1();
        let light = cloud.shade(x, w, camera.position, bb.centre) * coverage;
        colour += seen.piece(light, coverage, t);
        transmittance -= coverage;
    }
    (colour, 1.0 - transmittance)
}

/// How a pixel ray's light reaches the image: times `exposure`, then fogged (the fog, and its
/// colour along this ray).
struct Seen<'a> {
    exposure: f64,
    fog: Option<(&'a Fog, DVec3)>,
}

impl Seen<'_> {
    /// A piece of premultiplied light covering `coverage` of the view at distance `t`.
    fn piece(&self, light: DVec3, coverage: f64, t: f64) -> DVec3 {
        match self.fog {
            Some((fog, colour)) => fog.apply(light * self.exposure, coverage, t, colour),
            None => light * self.exposure,
        }
    }
}

/// `(1 - exp(-x)) / x`, 1 at 0: the mean of `exp(-x t)` over `t` in `[0, 1]`.
fn mean_attenuation(x: f64) -> f64 {
    if x.abs() < 1e-6 {
        1.0 - 0.5 * x
    } else {
        -(-x).exp_m1() / x
    }
}

/// Mean of `S`, log-linear from `a` to `b` over a segment of optical depth `tau`, weighted by what
/// each point of it shows through the segment (`exp(-tau t)`): `a g(tau + beta) / g(tau)`,
/// `beta = ln(a / b)`, per channel. Exact for `S` exponential and the extinction constant along
/// the segment; a channel zero at either end is taken linear instead.
fn segment_mean(a: DVec3, b: DVec3, tau: f64) -> DVec3 {
    let g = mean_attenuation(tau);
    let channel = |a: f64, b: f64| {
        if a > 0.0 && b > 0.0 {
            let beta = (a / b).ln().clamp(-40.0, 40.0);
            a * mean_attenuation(tau + beta) / g
        } else {
            // Linear: the weights' centroid `(1 / g - 1) / tau` of the far end.
            let far = if tau < 1e-6 {
                0.5
            } else {
                (1.0 / g - 1.0) / tau
            };
            a + (b - a) * far
        }
    };
    DVec3::new(channel(a.x, b.x), channel(a.y, b.y), channel(a.z, b.z))
}

/// Light one particle adds along pixel ray `w` when seen through the view transmittance
/// `view_depth` (the optical depth from the camera to a world point), and its own alpha: segment
/// `k` of the chord adds `mean S * tau_k / tau_all * exp(-tau_view(a_k)) * (1 - exp(-tau_all))`,
/// where `tau_all`, the segment's optical depth with every particle, is the view volumes' (at
/// least the particle's own `tau_k`).
fn particle_light_through_view(
    camera: &PinholeCamera,
    w: DVec3,
    bb: &Billboard,
    chord: &Chord,
    cloud: &BillboardCloud,
    view_depth: &dyn Fn(DVec3) -> f64,
    seen: &Seen,
) -> (DVec3, f64) {
    let at = |s: f64| camera.position + w * (chord.t_c + s);
    let scattered = |s: f64| cloud.shade(at(s), w, camera.position, bb.centre);
    let (mut light, mut own) = (DVec3::ZERO, 0.0);
    let (mut view_before, mut s_before) = (view_depth(at(chord.s0)), scattered(chord.s0));
    for (a, b, tau) in segments(bb, chord, cloud) {
        let view_after = view_depth(at(b));
        let s_after = scattered(b);
        let all = (view_after - view_before).max(tau);
        let coverage = tau * (-view_before).exp() * mean_attenuation(all);
        let t = chord.t_c + 0.5 * (a + b);
        light += seen.piece(segment_mean(s_before, s_after, all) * coverage, coverage, t);
        own += tau;
        (view_before, s_before) = (view_after, s_after);
    }
    (light, -(-own).exp_m1())
}

/// Radiance of one pixel ray `w`; `clouds` holds only the billboards that may touch its row.
fn shade_ray<'c>(
    camera: &PinholeCamera,
    w: DVec3,
    background: DVec3,
    objects: &[SceneObject],
    clouds: &'c [(&'c SortedCloud<'c>, Vec<&'c Billboard>)],
    seen: &Seen,
) -> DVec3 {
    let (mut colour, opaque_depth) = match nearest_object(objects, camera.position, w) {
        // An object is fogged at its distance as Bevy fogs meshes; its colour is radiance.
        Some((t, i)) => {
            let c = objects[i].color.as_dvec3();
            let fogged = seen.fog.map_or(c, |(fog, f)| fog.apply(c, 1.0, t, f));
            (fogged, t * w.dot(camera.forward))
        }
        None => (background, f64::INFINITY),
    };
    let visible = |sorted: &'c SortedCloud, billboards: &'c [&'c Billboard]| {
        billboards.iter().filter_map(move |bb| {
            let chord = chord(camera, w, bb)?;
            // Behind the opaque surface: the depth test fails.
            (opaque_depth >= chord.depth).then_some((*bb, chord, sorted.cloud))
        })
    };
    // Consecutive clouds composited through their view volumes make one layer: each particle's
    // light is seen through all their volumes, so their order does not matter.
    for run in clouds.chunk_by(|a, b| a.0.view.is_some() && b.0.view.is_some()) {
        let views: Vec<&ViewVolume> = run.iter().filter_map(|(s, _)| s.view.as_ref()).collect();
        if views.is_empty() {
            for (sorted, billboards) in run {
                for (bb, chord, cloud) in visible(sorted, billboards) {
                    let (radiance, alpha) = particle_radiance(camera, w, bb, &chord, cloud, seen);
                    colour = radiance + colour * (1.0 - alpha);
                }
            }
            continue;
        }
        let (mut light, mut transmittance) = (DVec3::ZERO, 1.0);
        for (sorted, billboards) in run {
            // The clouds wholly in front of this one through its front map, the others looked up.
            let Some(own) = sorted.view.as_ref() else {
                continue;
            };
            let view_depth = |x: DVec3| {
                let others = views.iter().filter(|v| !v.wholly_in_front_of(own));
                own.front_at(x) + others.map(|v| v.optical_depth_at(x)).sum::<f64>()
            };
            for (bb, chord, cloud) in visible(sorted, billboards) {
                let (l, alpha) =
                    particle_light_through_view(camera, w, bb, &chord, cloud, &view_depth, seen);
                light += l;
                transmittance *= 1.0 - alpha;
            }
        }
        colour = colour * transmittance + light;
    }
    colour
}

/// Keeps the billboards whose sphere can meet some ray of row `py`: all of that row's rays lie in
/// one plane through the eye, so a sphere farther than `R` from the plane is missed by all of them.
fn row_candidates<'c>(
    camera: &PinholeCamera,
    py: u32,
    clouds: &'c [SortedCloud<'c>],
) -> Vec<(&'c SortedCloud<'c>, Vec<&'c Billboard>)> {
    let ndc_y = 1.0 - 2.0 * (py as f64 + 0.5) / camera.height as f64;
    let in_plane = camera.forward + camera.up * (ndc_y * camera.tan_half_fov);
    let normal = camera.right.cross(in_plane).normalize();
    clouds
        .iter()
        .map(|cloud| {
            let near_row = cloud
                .billboards
                .iter()
                .filter(|bb| (bb.centre - camera.position).dot(normal).abs() < bb.radius)
                .collect();
            (cloud, near_row)
        })
        .collect()
}

/// Renders the billboard image (contract "Draw"): `width * height` linear RGBA pixels, row-major, row 0
/// at the top, alpha 1. Each pixel starts from the nearest opaque object's radiance (or
/// `background`); each cloud in the given order then composites its particles back to front
/// (descending view depth), each colour multiplied by `exposure`. A particle's billboard is hidden
/// where the opaque view depth is smaller than the billboard's depth.
pub fn composite(
    camera: &PinholeCamera,
    background: DVec3,
    objects: &[SceneObject],
    clouds: &[BillboardCloud],
    exposure: f64,
) -> Vec<[f32; 4]> {
    composite_fogged(camera, background, objects, clouds, exposure, None)
}

/// The fog of a view: Bevy's `DistanceFog` and the directional lights that make it glow
/// (`(unit direction towards the light, irradiance)`).
#[derive(Clone, Copy, Debug)]
pub struct ViewFog<'a> {
    /// The fog.
    pub fog: &'a Fog,
    /// The lights it glows about.
    pub lights: &'a [(DVec3, DVec3)],
}

/// [`composite`] through distance fog, if any: objects and every segment of every chord fogged
/// at their own distance (docs/physics.md, "Fog"); the background is not fogged.
pub fn composite_fogged(
    camera: &PinholeCamera,
    background: DVec3,
    objects: &[SceneObject],
    clouds: &[BillboardCloud],
    exposure: f64,
    fog: Option<ViewFog>,
) -> Vec<[f32; 4]> {
    let mut sorted: Vec<SortedCloud> = clouds.iter().map(|c| sort_cloud(camera, c)).collect();
    sum_fronts(&mut sorted);
    let width = camera.width as usize;
    let mut image = vec![[0.0f32; 4]; width * camera.height as usize];
    image
        .par_chunks_mut(width)
        .enumerate()
        .for_each(|(py, row)| {
            let candidates = row_candidates(camera, py as u32, &sorted);
            for (px, pixel) in row.iter_mut().enumerate() {
                let w = camera.pixel_ray(px as u32, py as u32);
                let seen = Seen {
                    exposure,
                    fog: fog.map(|f| (f.fog, f.fog.colour_towards(w, f.lights.iter().copied()))),
                };
                let c = shade_ray(camera, w, background, objects, &candidates, &seen);
                *pixel = [c.x as f32, c.y as f32, c.z as f32, 1.0];
            }
        });
    image
}

/// The billboard image of cloud `index` of `scene` (scene clouds are translated only) over a black
/// background with no objects, shading `scattered` with the `chord_segments` and `compositing`
/// of `settings` (`fine`: the cloud's fine density grid): the real-time image of that cloud alone,
/// at the scene's camera.
pub fn composite_scene_cloud(
    scene: &Scene,
    index: usize,
    scattered: ScatteredLight,
    settings: &CloudQualitySettings,
    fine: &DensityGrid,
) -> Vec<[f32; 4]> {
    let cloud = &scene.clouds[index];
    let billboards = BillboardCloud {
        particles: &cloud.particles,
        world_from_local: CloudPlacement::at(cloud.translation.as_dvec3()),
        medium: cloud.medium,
        scattered,
        segments: settings.chord_segments,
        compositing: BillboardCompositing::new(settings.compositing, fine),
        shading: settings.billboard_shading,
    };
    composite(
        &PinholeCamera::from_scene(&scene.camera),
        DVec3::ZERO,
        &[],
        &[billboards],
        1.0,
    )
}

#[cfg(test)]
mod tests;
