//! The estimators: free flights by delta tracking, transmittance by ratio tracking, next-event
//! estimation of the lights (and lit objects' light), and a path's radiance.

use std::ops::ControlFlow;

use bevy::math::DVec3;

use super::{Coefficients, Media, Segment};
use crate::fog::Fog;
use crate::math::{SplitMix64, light_basis};
use crate::reference::geometry::{nearest_object, object_normal};
use crate::scene::{Scene, SceneObject};

/// Expected tentative collisions in a segment above which the tracker walks it by its exact
/// optical depth instead of by null collisions. A medium far denser than its majorant grid's
/// cells would otherwise take billions of steps per cell, and steps below the f64 resolution of
/// the distance never end one (extinction 1e30 hung the tracer). No benchmark scene reaches it
/// (at most 43, `albedo_one`; a benchmark unit test), so their references are unchanged.
pub const DENSE_SEGMENT: f64 = 64.0;

/// `segment` holds more than [`DENSE_SEGMENT`] expected tentative collisions.
fn is_dense(segment: &Segment) -> bool {
    segment.majorant * (segment.t1 - segment.t0) > DENSE_SEGMENT
}

/// The distance `t` in `segment` where its optical depth from `segment.t0` reaches `depth`
/// (below the segment's whole depth), by bisection on the exact, increasing optical depth.
fn invert_optical_depth<M: Media>(
    media: &M,
    origin: DVec3,
    dir: DVec3,
    segment: &Segment,
    depth: f64,
) -> f64 {
    let (mut lo, mut hi) = (segment.t0, segment.t1);
    for _ in 0..80 {
        let mid = 0.5 * (lo + hi);
        if mid <= lo || mid >= hi {
            break;
        }
        if media.segment_optical_depth(origin, dir, segment, mid) < depth {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    hi
}

/// Walks the tentative collisions along `origin + t dir` (`dir` unit) in `[0, t_max]`:
/// exponential steps at each majorant segment's majorant, `collide` called at each with its
/// distance (metres), the coefficients there, the majorant and the generator, until it breaks.
/// Exponential steps are memoryless, so restarting at each segment boundary with the new
/// majorant is exact. A dense segment (see [`DENSE_SEGMENT`]) goes to `dense` instead, which
/// takes it whole.
fn tentative_collisions<M: Media>(
    media: &M,
    origin: DVec3,
    dir: DVec3,
    t_max: f64,
    rng: &mut SplitMix64,
    mut dense: impl FnMut(&Segment, &mut SplitMix64) -> ControlFlow<()>,
    mut collide: impl FnMut(f64, Coefficients, f64, &mut SplitMix64) -> ControlFlow<()>,
) {
    let _ = media.visit_segments(origin, dir, t_max, |seg| {
        if is_dense(&seg) {
            return dense(&seg, rng);
        }
        let mut t = seg.t0;
        loop {
            t += rng.exponential() / seg.majorant;
            if t >= seg.t1 {
                return ControlFlow::Continue(());
            }
            let c = media.coefficients(origin + dir * t, &seg);
            collide(t, c, seg.majorant, rng)?;
        }
    });
}

/// Delta tracking: samples a real collision along `origin + t dir` (`dir` unit) in `[0, t_max]`
/// with density `T(0,t) σ_t(t)`. Returns the distance (metres) and the coefficients there, or
/// `None` (probability `T(0, t_max)`) when the ray leaves `[0, t_max]` unscattered. A dense
/// segment is sampled exactly by inverting its optical depth (free flights are memoryless, so a
/// fresh exponential per segment is exact too).
pub fn sample_free_flight<M: Media>(
    media: &M,
    origin: DVec3,
    dir: DVec3,
    t_max: f64,
    rng: &mut SplitMix64,
) -> Option<(f64, Coefficients)> {
    let hit = std::cell::Cell::new(None);
    let dense = |seg: &Segment, rng: &mut SplitMix64| {
        let depth = rng.exponential();
        if media.segment_optical_depth(origin, dir, seg, seg.t1) <= depth {
            return ControlFlow::Continue(());
        }
        let t = invert_optical_depth(media, origin, dir, seg, depth);
        let c = media.coefficients(origin + dir * t, seg);
        if c.extinction <= 0.0 {
            return ControlFlow::Continue(()); // only where rounding put t off the medium
        }
        hit.set(Some((t, c)));
        ControlFlow::Break(())
    };
    tentative_collisions(
        media,
        origin,
        dir,
        t_max,
        rng,
        dense,
        |t, c, majorant, rng| {
            // Real collision with probability σ_t / majorant, null collision otherwise.
            if rng.next_f64() * majorant < c.extinction {
                hit.set(Some((t, c)));
                return ControlFlow::Break(());
            }
            ControlFlow::Continue(())
        },
    );
    hit.get()
}

/// Below this transmittance weight, ratio tracking plays Russian roulette (survive with 1/2,
/// weight doubled): unbiased, and it stops wasting work on rays that carry almost nothing.
const RATIO_TRACKING_ROULETTE: f64 = 0.1;

/// Ratio tracking: an unbiased estimate of the transmittance `exp(-∫_0^t_max σ_t dt)` of the
/// medium alone (objects are not considered) along `origin + t dir`, `dir` unit, `t_max` in metres
/// (may be `∞`). Dimensionless, in `[0, 1]` up to the roulette's weight doubling.
pub fn transmittance<M: Media>(
    media: &M,
    origin: DVec3,
    dir: DVec3,
    t_max: f64,
    rng: &mut SplitMix64,
) -> f64 {
    let weight = std::cell::Cell::new(1.0);
    // A dense segment's transmittance, exactly.
    let dense = |seg: &Segment, _: &mut SplitMix64| {
        weight.set(weight.get() * (-media.segment_optical_depth(origin, dir, seg, seg.t1)).exp());
        if weight.get() == 0.0 {
            return ControlFlow::Break(());
        }
        ControlFlow::Continue(())
    };
    tentative_collisions(
        media,
        origin,
        dir,
        t_max,
        rng,
        dense,
        |_, c, majorant, rng| {
            let mut w = weight.get();
            // Each tentative collision multiplies by the null-collision probability.
            w *= (1.0 - c.extinction / majorant).max(0.0);
            if w < RATIO_TRACKING_ROULETTE {
                if w == 0.0 || rng.next_f64() < 0.5 {
                    weight.set(0.0);
                    return ControlFlow::Break(());
                }
                w *= 2.0;
            }
            weight.set(w);
            ControlFlow::Continue(())
        },
    );
    weight.get()
}

/// A directional light prepared for shadow rays.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DirectionalLight {
    /// Unit direction from the medium towards the light (minus the travel direction).
    pub to_light: DVec3,
    /// Linear RGB irradiance perpendicular to the light's direction.
    pub irradiance: DVec3,
}

/// Everything but the media that a path sees: lights, background and opaque objects.
#[derive(Clone, Debug, PartialEq)]
pub struct Lighting {
    /// Linear RGB radiance of every ray that escapes.
    pub background: DVec3,
    /// The directional lights.
    pub lights: Vec<DirectionalLight>,
    /// Opaque objects: emitting their colour, and reflecting light where they have a reflectance.
    pub objects: Vec<SceneObject>,
    /// Distance fog along the camera's rays (docs/physics.md, "Fog"), if any.
    pub fog: Option<Fog>,
}

/// How far a ray leaving an object's surface starts off it, metres: clear of the surface it
/// leaves for any scene of sane size.
const SURFACE_OFFSET: f64 = 1e-7;

impl Lighting {
    /// The lighting of a scene; lights with a zero direction (refused by validation) are skipped.
    pub fn from_scene(scene: &Scene) -> Self {
        let lights = scene
            .lights
            .iter()
            .filter(|l| l.direction.length_squared() > 0.0)
            .map(|l| DirectionalLight {
                to_light: -l.direction.as_dvec3().normalize(),
                irradiance: l.irradiance.as_dvec3(),
            })
            .collect();
        Self {
            background: scene.background.as_dvec3(),
            lights,
            objects: scene.objects.clone(),
            fog: scene.fog,
        }
    }

    /// The fog's colour along the camera ray `dir` (its glow about each light).
    fn fog_colour(&self, fog: &Fog, dir: DVec3) -> DVec3 {
        fog.colour_towards(dir, self.lights.iter().map(|l| (l.to_light, l.irradiance)))
    }

    /// `Σ_l E_l T_l(x)`: unscattered irradiance at `x` from all lights, with exact transmittance.
    /// An object anywhere on the shadow ray blocks the light entirely.
    pub fn direct_irradiance<M: Media>(&self, media: &M, x: DVec3) -> DVec3 {
        self.single_scattering(media, x, |_| 1.0)
    }

    /// `Σ_l p(cos θ_l) E_l T_l(x)`: the unscattered light of every light scattered at `x`
    /// towards `-dir` (`dir` the unit direction the path arrived along), per unit `σ_s`.
    pub fn in_scattered<M: Media>(&self, media: &M, x: DVec3, dir: DVec3) -> DVec3 {
        // The light travels along -to_light and leaves along -dir: cos θ = to_light · dir.
        self.single_scattering(media, x, |to_light| media.phase(x, to_light.dot(dir)))
    }

    /// The radiance object `index` shows at its surface point `x` (docs/physics.md, "Lit
    /// objects"): its colour, plus `R / π` times the irradiance reaching it from the lights
    /// (blocked by objects, attenuated by every cloud: exact transmittance) and from the sky
    /// (one direction, cosine-distributed about the normal: `π L_background T` where nothing
    /// blocks it), an unbiased estimate.
    pub fn object_radiance<M: Media>(
        &self,
        media: &M,
        index: usize,
        x: DVec3,
        rng: &mut SplitMix64,
    ) -> DVec3 {
        let object = &self.objects[index];
        let emitted = object.color.as_dvec3();
        let reflectance = object.reflectance.as_dvec3();
        if reflectance == DVec3::ZERO {
            return emitted;
        }
        let n = object_normal(object, x);
        let origin = x + n * SURFACE_OFFSET;
        let arriving = |to: DVec3| {
            let blocked = nearest_object(&self.objects, origin, to).is_some();
            if blocked {
                0.0
            } else {
                (-media.optical_depth(origin, to, f64::INFINITY)).exp()
            }
        };
        let mut irradiance = DVec3::ZERO;
        for light in &self.lights {
            let cos = n.dot(light.to_light);
            if cos > 0.0 {
                irradiance += light.irradiance * (cos * arriving(light.to_light));
            }
        }
        if self.background != DVec3::ZERO {
            irradiance +=
                self.background * (std::f64::consts::PI * arriving(cosine_direction(n, rng)));
        }
        emitted + reflectance * irradiance * std::f64::consts::FRAC_1_PI
    }

    fn single_scattering<M: Media>(
        &self,
        media: &M,
        x: DVec3,
        phase: impl Fn(DVec3) -> f64,
    ) -> DVec3 {
        let mut e = DVec3::ZERO;
        for light in &self.lights {
            if nearest_object(&self.objects, x, light.to_light).is_some() {
                continue;
            }
            let tau = media.optical_depth(x, light.to_light, f64::INFINITY);
            e += light.irradiance * ((-tau).exp() * phase(light.to_light));
        }
        e
    }
}

/// A unit direction about the unit normal `n`, with the density `cos θ / π`.
fn cosine_direction(n: DVec3, rng: &mut SplitMix64) -> DVec3 {
    cosine_direction_of(n, [rng.next_f64(), rng.next_f64()])
}

/// The direction [`cosine_direction`] makes of the uniform numbers `u` in `[0, 1)²`.
pub(super) fn cosine_direction_of(n: DVec3, [u1, u2]: [f64; 2]) -> DVec3 {
    let (r, phi) = (u1.sqrt(), 2.0 * std::f64::consts::PI * u2);
    let [u, v, w] = light_basis(n);
    u * (r * phi.cos()) + v * (r * phi.sin()) + w * (1.0 - u1).max(0.0).sqrt()
}

/// One-sample estimate of the radiance (linear RGB) arriving at `origin` from direction `-dir`
/// (`dir` unit), i.e. docs/physics.md's `L` for the ray `origin + t dir`.
///
/// `max_scatter_events` cuts paths after that many real scattering events (1 gives single
/// scattering exactly; [`MAX_SCATTER_EVENTS`](super::MAX_SCATTER_EVENTS) for the full solution).
pub fn radiance<M: Media>(
    media: &M,
    lighting: &Lighting,
    origin: DVec3,
    dir: DVec3,
    max_scatter_events: u32,
    rng: &mut SplitMix64,
) -> DVec3 {
    let mut total = [DVec3::ZERO];
    radiance_by_order(
        media,
        lighting,
        origin,
        dir,
        max_scatter_events,
        rng,
        &mut total,
    );
    total[0]
}

/// [`radiance`] split by scattering order: `orders[k]` receives the light that reached the camera
/// after exactly `k` scattering events (0: the background or an object seen unscattered), the last
/// entry every order from its own on. The entries sum to [`radiance`]'s estimate.
pub fn radiance_by_order<M: Media>(
    media: &M,
    lighting: &Lighting,
    origin: DVec3,
    dir: DVec3,
    max_scatter_events: u32,
    rng: &mut SplitMix64,
    orders: &mut [DVec3],
) {
    let last = orders.len() - 1;
    let (mut o, mut d) = (origin, dir);
    let mut events = 0;
    // What the fog lets through from the camera ray's end (its first collision or its object).
    let mut fogged = DVec3::ONE;
    loop {
        let object = nearest_object(&lighting.objects, o, d);
        let t_max = object.map_or(f64::INFINITY, |(t, _)| t);
        let collision = sample_free_flight(media, o, d, t_max, rng);
        if events == 0
            && let Some(fog) = &lighting.fog
        {
            // The fog fogs what ends the camera ray, at its distance (the sky is not fogged, as
            // in Bevy). With t the first collision, E[A(t) F] = ∫ T_cloud dA F, the fog of a
            // medium that permeates the cloud (docs/physics.md, "Fog").
            let end = collision.map(|(t, _)| t).or(object.map(|(t, _)| t));
            if let Some(t) = end {
                let at = fog.at(t);
                fogged = at.transmitted;
                orders[0] += at.inscattered * lighting.fog_colour(fog, d);
            }
        }
        let Some((t, c)) = collision else {
            // Unscattered to the end of the ray: the object's radiance or the background.
            orders[(events as usize).min(last)] += fogged
                * match object {
                    Some((t, i)) => lighting.object_radiance(media, i, o + d * t, rng),
                    None => lighting.background,
                };
            return;
        };
        let x = o + d * t;
        // σ_s/σ_t: a real collision was accepted with probability σ_t/majorant > 0, so σ_t > 0.
        let albedo = c.scattering / c.extinction;
        events += 1;
        orders[(events as usize).min(last)] += fogged * lighting.in_scattered(media, x, d) * albedo;
        // Russian roulette on the albedo: survivors keep weight 1.
        if events >= max_scatter_events || rng.next_f64() >= albedo {
            return;
        }
        d = media.scatter_direction(x, d, rng);
        o = x;
    }
}
