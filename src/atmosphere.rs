//! Clouds under Bevy's [`Atmosphere`]: the sun reaches each cloud through the atmosphere's
//! transmittance, as it reaches Bevy's meshes (`pbr_lighting.wgsl` multiplies a directional
//! light's colour by the transmittance from the shaded point to the light, and by the part of the
//! sun's disk above the horizon), so that clouds redden and darken with the sun at dusk. Each
//! cloud takes the transmittance at its centre, from the atmosphere whose planet centre is nearest
//! to it, integrated on the CPU at extraction when the cloud, a light or the atmosphere changed. The atmosphere's sky light and aerial perspective are not modelled (docs/guide.md, "What clouds
//! interact with").

use bevy::{
    ecs::system::SystemParam,
    light::{
        Atmosphere, SunDisk,
        atmosphere::{Falloff, ScatteringMedium},
    },
    math::DVec3,
    platform::collections::HashMap,
    prelude::*,
};

use std::sync::Arc;

use crate::{render::core::key_of, shadow_maps::CloudLights};

/// Steps of the midpoint rule along the path to the light. Bevy's transmittance table takes 40
/// (`AtmosphereSettings::transmittance_lut_samples`); 256 put the overhead optical depth of an
/// 8 km scale height within 1e-4 of the exact one (the unit test).
const STEPS: u32 = 256;

/// One planet's atmosphere, in its own space (metres of the atmosphere, centred on the planet):
/// what the transmittance to a light needs.
pub struct AtmosphereTransmittance<'a> {
    /// Planet radius and atmosphere top, atmosphere metres.
    inner_radius: f64,
    outer_radius: f64,
    /// World → atmosphere space: the entity's translation and scale (its rotation is ignored, as
    /// Bevy ignores it: the atmosphere is spherically symmetric).
    centre: Vec3,
    scale: Vec3,
    medium: &'a ScatteringMedium,
}

impl<'a> AtmosphereTransmittance<'a> {
    /// `atmosphere` placed by `transform`, made of `medium`.
    pub fn new(
        atmosphere: &Atmosphere,
        transform: &GlobalTransform,
        medium: &'a ScatteringMedium,
    ) -> Self {
        let (scale, _, centre) = transform.to_scale_rotation_translation();
        Self {
            inner_radius: atmosphere.inner_radius as f64,
            outer_radius: atmosphere.outer_radius as f64,
            centre,
            scale,
            medium,
        }
    }

    /// Linear RGB transmittance from world point `point` to a directional light travelling along
    /// `direction` (world) whose disk spans `sun_angular_size` radians: Bevy's
    /// `transmittance(r, mu) * calculate_visible_sun_ratio(r, mu)`, with the point lifted onto
    /// the ground where it lies below it.
    pub fn towards_light(&self, point: Vec3, direction: Vec3, sun_angular_size: f32) -> Vec3 {
        let p = ((point - self.centre) / self.scale).as_dvec3();
        let r = p.length().max(self.inner_radius + 1e-3);
        let up = p.try_normalize().unwrap_or(DVec3::Y);
        let mu = (-direction.as_dvec3().normalize()).dot(up).clamp(-1.0, 1.0);
        let visible = self.visible_sun_ratio(r, mu, sun_angular_size as f64);
        if visible == 0.0 {
            return Vec3::ZERO;
        }
        let tau = self.optical_depth(r, mu);
        (tau.map(|t| (-t).exp()) * visible).as_vec3()
    }

    /// A key of the atmosphere: its place, its radii and its medium's terms.
    fn key(&self) -> u64 {
        let bits = |v: Vec3| v.to_array().map(f32::to_bits);
        let terms: Vec<_> = (self.medium.terms.iter())
            .map(|t| {
                let falloff = match &t.falloff {
                    Falloff::Linear => [0, 0, 0],
                    Falloff::Exponential { scale } => [1, scale.to_bits() as u64, 0],
                    Falloff::Tent { center, width } => {
                        [2, center.to_bits() as u64, width.to_bits() as u64]
                    }
                    // A curve is immutable behind its `Arc`: its address identifies it.
                    Falloff::Curve(curve) => [3, Arc::as_ptr(curve) as *const () as u64, 0],
                };
                (bits(t.absorption), bits(t.scattering), falloff)
            })
            .collect();
        key_of((
            [self.inner_radius, self.outer_radius].map(f64::to_bits),
            bits(self.centre),
            bits(self.scale),
            terms,
        ))
    }

    /// Extinction per atmosphere metre at radius `r`: every term's absorption and scattering
    /// times its falloff at `p = 1 - (r - inner) / (outer - inner)` (1 on the ground, 0 at the
    /// top), as Bevy's density table holds it.
    fn extinction(&self, r: f64) -> DVec3 {
        let altitude = (r - self.inner_radius) / (self.outer_radius - self.inner_radius);
        let p = (1.0 - altitude).clamp(0.0, 1.0) as f32;
        self.medium
            .terms
            .iter()
            .map(|term| {
                // A custom curve may leave [0, 1]; outside it, or NaN, it holds no medium.
                let falloff = term.falloff.sample(p);
                let falloff = if falloff.is_finite() {
                    falloff.max(0.0)
                } else {
                    0.0
                };
                ((term.absorption + term.scattering) * falloff).as_dvec3()
            })
            .sum()
    }

    /// Optical depth from radius `r` along the direction at cosine `mu` from the zenith to the
    /// top of the atmosphere, or to the ground where the ray meets it (Bevy's
    /// `max_atmosphere_distance`); midpoint rule.
    fn optical_depth(&self, r: f64, mu: f64) -> DVec3 {
        let length = self.path_length(r, mu);
        let dt = length / STEPS as f64;
        (0..STEPS)
            .map(|i| {
                let t = (i as f64 + 0.5) * dt;
                let r_t = (t * t + 2.0 * r * mu * t + r * r).sqrt();
                self.extinction(r_t) * dt
            })
            .sum()
    }

    /// Distance from radius `r` along cosine `mu` to the atmosphere's top, or to the ground when
    /// the ray meets it first.
    fn path_length(&self, r: f64, mu: f64) -> f64 {
        let discriminant = |radius: f64| r * r * (mu * mu - 1.0) + radius * radius;
        let ground = discriminant(self.inner_radius);
        if mu < 0.0 && ground >= 0.0 {
            return (-r * mu - ground.sqrt()).max(0.0);
        }
        (-r * mu + discriminant(self.outer_radius).max(0.0).sqrt()).max(0.0)
    }

    /// The part of the sun's disk above the horizon seen from radius `r`, the sun's centre at
    /// cosine `mu` from the zenith (Bevy's `calculate_visible_sun_ratio`: linear in the centre's
    /// angle across the disk).
    fn visible_sun_ratio(&self, r: f64, mu: f64, angular_size: f64) -> f64 {
        let horizon = (-(1.0 - (self.inner_radius / r).powi(2)).max(0.0).sqrt()).acos();
        let zenith = mu.acos();
        let half = 0.5 * angular_size;
        if zenith + half <= horizon {
            return 1.0;
        }
        if zenith - half >= horizon {
            return 0.0;
        }
        (0.5 + 0.5 * (horizon - zenith) / half).clamp(0.0, 1.0)
    }
}

/// What the clouds' extraction reads to light them through the atmosphere: the lights that light
/// clouds, Bevy's atmospheres and their media, and the lights' `SunDisk`s.
#[derive(SystemParam)]
pub struct AtmosphereLight<'w, 's> {
    lights: Res<'w, CloudLights>,
    atmospheres: Query<'w, 's, (&'static Atmosphere, &'static GlobalTransform)>,
    media: Option<Res<'w, Assets<ScatteringMedium>>>,
    suns: Query<'w, 's, &'static SunDisk>,
}

/// Each cloud's transmittances as last integrated, with the key of what they depend on: a cloud
/// that stays put under a still sun and atmosphere is not integrated again.
#[derive(Default)]
pub struct TransmittanceCache {
    held: HashMap<Entity, (u64, Vec<Vec3>)>,
    /// The last atmosphere refused, and why (warned of once).
    refused: Option<String>,
}

impl TransmittanceCache {
    /// Forgets the clouds `keep` refuses (despawned ones).
    pub fn retain(&mut self, mut keep: impl FnMut(Entity) -> bool) {
        self.held.retain(|&cloud, _| keep(cloud));
    }
}

impl AtmosphereLight<'_, '_> {
    /// Per light of [`CloudLights`], the transmittance from `cloud`'s centre `point` to it through
    /// the atmosphere nearest to the point; empty where there is none. Integrated again only when
    /// the point, a light or the atmosphere changed since `cache` took it.
    pub fn transmittances(
        &self,
        cloud: Entity,
        point: Vec3,
        cache: &mut TransmittanceCache,
    ) -> Vec<Vec3> {
        let air = match self.media.as_deref() {
            Some(media) => nearest_atmosphere(self.atmospheres.iter(), media, point),
            None => Ok(None),
        };
        let air = match air {
            Ok(air) => air,
            Err(problem) => {
                if cache.refused.as_ref() != Some(&problem) {
                    warn!("{problem}; the clouds are lit as if there were no atmosphere");
                    cache.refused = Some(problem);
                }
                None
            }
        };
        let Some(air) = air else {
            cache.held.remove(&cloud);
            return Vec::new();
        };
        // Bevy's meshes take a light without a `SunDisk` as having Earth's.
        let suns: Vec<(Vec3, f32)> = (self.lights.0.iter())
            .map(|l| {
                let disk = self.suns.get(l.entity).unwrap_or(&SunDisk::EARTH);
                (l.direction, disk.angular_size)
            })
            .collect();
        let bits = |v: Vec3| v.to_array().map(f32::to_bits);
        let key = key_of((
            air.key(),
            bits(point),
            suns.iter()
                .map(|&(d, a)| (bits(d), a.to_bits()))
                .collect::<Vec<_>>(),
        ));
        if let Some((held, transmittances)) = cache.held.get(&cloud)
            && *held == key
        {
            return transmittances.clone();
        }
        let transmittances: Vec<Vec3> = suns
            .iter()
            .map(|&(direction, disk)| air.towards_light(point, direction, disk))
            .collect();
        cache.held.insert(cloud, (key, transmittances.clone()));
        transmittances
    }
}

/// The atmosphere of `atmospheres` whose planet centre is nearest to `point` (as Bevy picks a
/// camera's), with its medium: `Ok(None)` where there is none or its medium is not loaded, and
/// why it cannot light the clouds where a field of it is out of range.
pub fn nearest_atmosphere<'a>(
    atmospheres: impl Iterator<Item = (&'a Atmosphere, &'a GlobalTransform)>,
    media: &'a Assets<ScatteringMedium>,
    point: Vec3,
) -> Result<Option<AtmosphereTransmittance<'a>>, String> {
    let nearest = atmospheres.min_by(|(_, a), (_, b)| {
        let da = point.distance_squared(a.translation());
        let db = point.distance_squared(b.translation());
        da.total_cmp(&db)
    });
    let Some((atmosphere, transform)) = nearest else {
        return Ok(None);
    };
    let Some(medium) = media.get(&atmosphere.medium) else {
        return Ok(None);
    };
    validate(atmosphere, transform, medium)?;
    Ok(Some(AtmosphereTransmittance::new(
        atmosphere, transform, medium,
    )))
}

/// Why an atmosphere cannot light the clouds, naming the field, its value and what is allowed.
fn validate(
    atmosphere: &Atmosphere,
    transform: &GlobalTransform,
    medium: &ScatteringMedium,
) -> Result<(), String> {
    let (inner, outer) = (atmosphere.inner_radius, atmosphere.outer_radius);
    if !(inner.is_finite() && inner > 0.0) {
        return Err(format!(
            "`Atmosphere::inner_radius` is {inner}; it must be finite and > 0"
        ));
    }
    if !(outer.is_finite() && outer > inner) {
        return Err(format!(
            "`Atmosphere::outer_radius` is {outer}; it must be finite and > `inner_radius` ({inner})"
        ));
    }
    let (scale, _, centre) = transform.to_scale_rotation_translation();
    if !(scale.is_finite() && scale.min_element() > 0.0 && centre.is_finite()) {
        return Err(format!(
            "the atmosphere's `GlobalTransform` has scale {scale} and translation {centre}; they \
             must be finite and the scale > 0"
        ));
    }
    for (i, term) in medium.terms.iter().enumerate() {
        for (name, v) in [
            ("absorption", term.absorption),
            ("scattering", term.scattering),
        ] {
            if !(v.is_finite() && v.min_element() >= 0.0) {
                return Err(format!(
                    "`ScatteringMedium::terms[{i}].{name}` is {v}; every component must be \
                     finite and >= 0"
                ));
            }
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use bevy::light::atmosphere::{PhaseFunction, ScatteringTerm};

    use super::*;
    use crate::shadow_maps::CloudLight;

    const INNER: f32 = 6_360_000.0;
    const OUTER: f32 = 6_460_000.0;

    /// A medium of one term of extinction `sigma` per metre, falling off exponentially with
    /// Bevy's normalised curve of scale `s`.
    fn one_term(sigma: Vec3, s: f32) -> ScatteringMedium {
        let term = ScatteringTerm {
            absorption: sigma * 0.25,
            scattering: sigma * 0.75,
            falloff: Falloff::Exponential { scale: s },
            phase: PhaseFunction::Isotropic,
        };
        ScatteringMedium::new(256, 256, [term])
    }

    fn atmosphere() -> Atmosphere {
        Atmosphere {
            inner_radius: INNER,
            outer_radius: OUTER,
            ground_albedo: Vec3::splat(0.3),
            medium: Handle::default(),
        }
    }

    /// The planet centred `INNER` below the origin, as Bevy places it by default.
    fn planet() -> GlobalTransform {
        GlobalTransform::from_translation(-Vec3::Y * INNER)
    }

    #[test]
    fn a_sun_overhead_sees_the_column_above_the_point() {
        // Bevy's falloff f(p) = (e^((1 - p) s') - e^s') / (1 - e^s'), s' = -1 / s, with
        // p = 1 - altitude / H: the column from the ground integrates to
        // H / (1 - e^s') (1 / s' (e^s' - 1) - e^s'), the exact optical depth overhead.
        let sigma = Vec3::new(5.8e-6, 13.6e-6, 33.1e-6);
        let s = 8.0 / 100.0;
        let medium = one_term(sigma, s);
        let air = AtmosphereTransmittance::new(&atmosphere(), &planet(), &medium);
        let sp = -1.0 / s as f64;
        let h = (OUTER - INNER) as f64;
        let column = h / (1.0 - sp.exp()) * ((sp.exp() - 1.0) / sp - sp.exp());
        let got = air.towards_light(Vec3::ZERO, Vec3::NEG_Y, 0.0);
        for (c, &g) in got.to_array().iter().enumerate() {
            let want = (-(sigma[c] as f64) * column).exp();
            assert!(
                (g as f64 - want).abs() < 1e-4 * want,
                "channel {c}: {g} against the exact {want}"
            );
        }
        // Redder towards the horizon: less blue gets through a longer, lower path.
        let low = air.towards_light(Vec3::ZERO, Vec3::new(-0.99, -0.14, 0.0), 0.0);
        assert!(low.z < got.z * 0.5 && low.x / low.z > got.x / got.z);
    }

    #[test]
    fn a_sun_below_the_horizon_gives_no_light_and_one_on_it_half() {
        // A clear atmosphere: what reaches the point is the part of the disk above the horizon.
        let medium = one_term(Vec3::ZERO, 0.1);
        let air = AtmosphereTransmittance::new(&atmosphere(), &planet(), &medium);
        // 1 km up, the horizon dips by acos(R / (R + 1 km)), about 0.0177 rad.
        let point = Vec3::Y * 1000.0;
        let dip = (INNER as f64 / (INNER as f64 + 1000.0)).acos();
        let sun = |elevation: f64| -Vec3::new(elevation.cos() as f32, elevation.sin() as f32, 0.0);
        let disk = 0.0093;
        assert_eq!(air.towards_light(point, sun(-dip - 0.01), disk), Vec3::ZERO);
        let on = air.towards_light(point, sun(-dip), disk);
        assert!((on - Vec3::splat(0.5)).abs().max_element() < 0.01, "{on}");
        assert_eq!(air.towards_light(point, sun(-dip + 0.01), disk), Vec3::ONE);
    }

    #[test]
    fn a_clear_atmosphere_lets_all_the_light_through_and_the_nearest_is_chosen() {
        let clear = one_term(Vec3::ZERO, 0.1);
        let mut media = Assets::<ScatteringMedium>::default();
        let handle = media.add(clear);
        let mut near = atmosphere();
        near.medium = handle.clone();
        let far_transform = GlobalTransform::from_translation(Vec3::X * 1e9);
        let far = Atmosphere {
            medium: Handle::default(),
            ..atmosphere()
        };
        let pairs = [(&far, &far_transform), (&near, &planet())];
        let air = nearest_atmosphere(pairs.into_iter(), &media, Vec3::ZERO)
            .unwrap()
            .expect("the near one");
        assert_eq!(air.towards_light(Vec3::ZERO, Vec3::NEG_Y, 0.0), Vec3::ONE);
        // The far one's medium is not loaded: no atmosphere.
        let pairs = [(&far, &far_transform)];
        assert!(
            nearest_atmosphere(pairs.into_iter(), &media, Vec3::ZERO)
                .unwrap()
                .is_none()
        );
    }

    #[test]
    fn a_cloud_is_integrated_again_only_when_it_or_the_sun_moves() {
        use bevy::ecs::system::SystemState;
        let mut world = World::new();
        let mut media = Assets::<ScatteringMedium>::default();
        let medium = media.add(ScatteringMedium::earth(64, 64));
        world.insert_resource(media);
        world.spawn((Atmosphere::earth(medium), planet()));
        let sun = world.spawn(SunDisk::EARTH).id();
        let light = |direction: Vec3| CloudLight {
            entity: sun,
            direction,
            irradiance: Vec3::ONE,
        };
        world.insert_resource(CloudLights(vec![light(
            Vec3::new(-1.0, -0.2, 0.0).normalize(),
        )]));
        let cloud = world.spawn_empty().id();
        let mut cache = TransmittanceCache::default();
        let mut state = SystemState::<AtmosphereLight>::new(&mut world);
        let first = state
            .get(&world)
            .unwrap()
            .transmittances(cloud, Vec3::Y * 500.0, &mut cache);
        assert_eq!(first.len(), 1);
        assert!(first[0].z < first[0].x && first[0].x < 1.0, "{}", first[0]);
        // A marker in the cache: returned while nothing changed, so nothing was integrated.
        cache.held.get_mut(&cloud).unwrap().1[0] = Vec3::splat(-1.0);
        let again = state
            .get(&world)
            .unwrap()
            .transmittances(cloud, Vec3::Y * 500.0, &mut cache);
        assert_eq!(again, [Vec3::splat(-1.0)]);
        let moved = state
            .get(&world)
            .unwrap()
            .transmittances(cloud, Vec3::Y * 800.0, &mut cache);
        assert!(
            moved[0].x > first[0].x,
            "higher, less air: {} {}",
            moved[0],
            first[0]
        );
        world.insert_resource(CloudLights(vec![light(Vec3::NEG_Y)]));
        let noon = state
            .get(&world)
            .unwrap()
            .transmittances(cloud, Vec3::Y * 800.0, &mut cache);
        assert!(noon[0].z > moved[0].z, "{} {}", noon[0], moved[0]);
    }

    #[test]
    fn a_broken_atmosphere_is_refused_naming_its_field() {
        let mut media = Assets::<ScatteringMedium>::default();
        let mut broken = one_term(Vec3::ONE * 1e-5, 0.1);
        broken.terms[0].scattering.y = f32::NAN;
        let broken = media.add(broken);
        let clear = media.add(one_term(Vec3::ZERO, 0.1));
        let refusal = |atmosphere: Atmosphere, transform: GlobalTransform| {
            let pairs = [(&atmosphere, &transform)];
            match nearest_atmosphere(pairs.into_iter(), &media, Vec3::ZERO) {
                Err(problem) => problem,
                Ok(_) => panic!("accepted"),
            }
        };
        let with = |medium: &Handle<ScatteringMedium>| Atmosphere {
            medium: medium.clone(),
            ..atmosphere()
        };
        let problem = refusal(with(&broken), planet());
        assert!(problem.starts_with("`ScatteringMedium::terms[0].scattering` is ["));
        assert!(problem.contains("NaN") && problem.ends_with("must be finite and >= 0"));
        let inverted = Atmosphere {
            outer_radius: INNER - 1.0,
            ..with(&clear)
        };
        assert!(refusal(inverted, planet()).starts_with("`Atmosphere::outer_radius` is 6359999;"));
        let flat = GlobalTransform::from_scale(Vec3::new(1.0, 0.0, 1.0));
        assert!(refusal(with(&clear), flat).contains("scale [1, 0, 1]"));
    }
}
