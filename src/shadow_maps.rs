//! Cloud shadow maps (docs/illumination.md §10): per directional light, the optical depth of every
//! cloud along the light, over a square of texels across it that covers every cloud. Surfaces
//! read them to take the clouds' shadows: the scene files' lit objects do
//! (`lit_object::LitObjectMaterial`), and so can a game's own materials.
//!
//! Off by default ([`CloudShadowMaps::resolution`] 0): then nothing is computed. On, every cloud
//! that casts shadows is illuminated, seen or not, since its shadow may fall in view. The main
//! world places the maps (this file); the render world fills them with the cast pass
//! (`render::shadow_maps`), the sum at each texel of every cloud's own light volume along the
//! texel's column.
//!
//! Under a sky ([`CloudSkyLight`]) there is one more map, the sky map
//! ([`CloudShadowMaps::sky`]): over a horizontal plane under the clouds, the part of the sky's
//! irradiance the clouds take away (`render::sky_map`).

use bevy::{
    asset::RenderAssetUsages,
    camera::primitives::Aabb,
    light::{DirectionalLight, NotShadowCaster},
    platform::collections::HashMap,
    prelude::*,
    render::{
        extract_resource::ExtractResource, render_resource::ShaderType, storage::ShaderBuffer,
    },
};

use crate::{
    CloudSkyLight,
    cloud::{NotCloudLight, ParticleCloud},
    ground::CloudGround,
    math::light_basis,
};

/// Cloud shadow maps: their resolution, and (written by the plugin) where each lies and the
/// buffer that holds them. A resource; off (`resolution` 0) by default.
#[derive(Resource, ExtractResource, Clone, Debug, Default, Reflect)]
#[reflect(Resource, Default)]
pub struct CloudShadowMaps {
    /// Texels per side of each light's map; 0 (the default) turns the maps off. The maps cover
    /// every cloud, so a texel's width is the span of the clouds across the light over this.
    pub resolution: u32,
    /// Per cloud-lighting light, where its map lies (written by the plugin every frame).
    pub maps: Vec<(Entity, ShadowMapPlacement)>,
    /// Where the sky map lies, under a sky with clouds above the plane (written by the plugin
    /// every frame): a horizontal square at the [`CloudGround`]'s height (world `y = 0` without
    /// one), its texels the fraction `1 - V` of the sky's irradiance on an upward-facing surface
    /// there that the clouds take away; in the buffer after the lights' maps.
    pub sky: Option<ShadowMapPlacement>,
    /// The optical depths of every light's map, `resolution²` f32 per light, then the sky map's
    /// [`sky_map_size`]`²` occlusions (written by the plugin's render world; bind it read-only
    /// as `array<f32>`).
    pub buffer: Handle<ShaderBuffer>,
}

impl CloudShadowMaps {
    /// Shadow maps of `resolution` texels per side.
    pub fn with_resolution(resolution: u32) -> Self {
        Self {
            resolution,
            ..default()
        }
    }

    /// Bytes of the maps' buffer for `lights` maps of `resolution²` texels and a sky map (never
    /// empty: materials bind it whether the maps are on or not).
    pub fn buffer_bytes(lights: usize, resolution: u32) -> usize {
        let sky = sky_map_size(resolution).pow(2) as usize;
        ((lights * (resolution * resolution) as usize + sky) * 4).max(16)
    }

    /// The placement of the map of light `light` (its main-world entity), if it has one.
    pub fn map_of(&self, light: Entity) -> Option<&ShadowMapPlacement> {
        self.maps.iter().find(|(e, _)| *e == light).map(|(_, p)| p)
    }
}

/// Where one light's shadow map lies (mirror of `ShadowMapPlacement` in WGSL): a square of
/// `size²` texels across the light, its texel `(i, j)` the column through the world point
/// `(corner.x + (i + 1/2) texel) u + (corner.y + (j + 1/2) texel) v + t d`, its value the optical
/// depth of every cloud along that column, at element `first + i + size j` of the maps' buffer.
#[derive(ShaderType, Clone, Copy, Debug, Default, PartialEq, Reflect)]
#[reflect(Clone, Debug, Default, PartialEq)]
pub struct ShadowMapPlacement {
    /// The map's first axis across the light (unit).
    pub u: Vec3,
    /// A texel's side, metres.
    pub texel: f32,
    /// Its second axis across the light (unit).
    pub v: Vec3,
    /// Where the first cloud begins along the light (`x . d`), metres: a point before it is in
    /// no cloud's shadow.
    pub w_begin: f32,
    /// The direction the light travels (unit).
    pub d: Vec3,
    /// Where the last cloud ends along the light (`x . d`), metres: the columns are summed to
    /// there.
    pub w_end: f32,
    /// `(x . u, x . v)` of the map's corner, metres.
    pub corner: Vec2,
    /// Texels per side.
    pub size: u32,
    /// The map's first element in the maps' buffer.
    pub first: u32,
}

impl ShadowMapPlacement {
    /// The map of `size²` texels, starting at element `first`, of a light travelling along the
    /// unit direction `d`, covering clouds within the world spheres `clouds` (centre, radius);
    /// `None` without clouds.
    pub fn covering(d: Vec3, clouds: &[(Vec3, f32)], size: u32, first: u32) -> Option<Self> {
        let [u, v, _] = light_basis(d.as_dvec3()).map(|a| a.as_vec3());
        let (mut lo, mut hi) = (Vec3::INFINITY, Vec3::NEG_INFINITY);
        for &(c, r) in clouds {
            let p = Vec3::new(c.dot(u), c.dot(v), c.dot(d));
            lo = lo.min(p - r);
            hi = hi.max(p + r);
        }
        if clouds.is_empty() || !lo.is_finite() || !hi.is_finite() {
            return None;
        }
        let span = (hi.x - lo.x).max(hi.y - lo.y).max(f32::MIN_POSITIVE);
        let centre = (lo.truncate() + hi.truncate()) * 0.5;
        Some(Self {
            u,
            texel: span / size as f32,
            v,
            w_begin: lo.z,
            d,
            w_end: hi.z,
            corner: centre - span * 0.5,
            size,
            first,
        })
    }

    /// The world point of texel `(i, j)`'s column where the columns end (past every cloud).
    pub fn texel_point(&self, i: u32, j: u32) -> Vec3 {
        let a = self.corner + (Vec2::new(i as f32, j as f32) + 0.5) * self.texel;
        a.x * self.u + a.y * self.v + self.w_end * self.d
    }

    /// The sky map of `size²` texels, starting at element `first`, on the horizontal plane at
    /// world height `height`, under clouds within the world spheres `clouds` (centre, radius):
    /// its axes world `x` and `z`, its "light" travelling down (`d = -y`), so `w_begin` is minus
    /// the clouds' top and `w_end` minus `height`, and its texels' points lie on the plane. It
    /// covers the clouds' footprint widened by [`SKY_MAP_REACH`] times their top's height above
    /// the plane, where the sky they hide still matters. `None` without clouds above the plane.
    pub fn sky(clouds: &[(Vec3, f32)], height: f32, size: u32, first: u32) -> Option<Self> {
        let (mut lo, mut hi) = (Vec2::INFINITY, Vec2::NEG_INFINITY);
        let mut top = f32::NEG_INFINITY;
        for &(c, r) in clouds {
            lo = lo.min(c.xz() - r);
            hi = hi.max(c.xz() + r);
            top = top.max(c.y + r);
        }
        if !top.is_finite() || top <= height || !lo.is_finite() || !hi.is_finite() {
            return None;
        }
        let reach = SKY_MAP_REACH * (top - height);
        let span = (hi - lo).max_element() + 2.0 * reach;
        Some(Self {
            u: Vec3::X,
            texel: span / size as f32,
            v: Vec3::Z,
            w_begin: -top,
            d: Vec3::NEG_Y,
            w_end: -height,
            corner: (lo + hi) * 0.5 - span * 0.5,
            size,
            first,
        })
    }
}

/// Directions per texel of the sky map: the `k`-th of them is [`sky_direction`]`(k)`.
pub const SKY_MAP_DIRECTIONS: u32 = 128;

/// How far beyond the clouds' footprint the sky map reaches, per metre of their top's height
/// above its plane: 2, so it holds every point that sees a cloud less than 63° from the zenith
/// (beyond, at most a fifth of the sky's irradiance comes from below 27° of elevation).
pub const SKY_MAP_REACH: f32 = 2.0;

/// Texels per side of the sky map beside light maps of `resolution` texels: an eighth, at least
/// 8. What the clouds hide of the sky varies over about their height above the plane, more
/// smoothly than their shadow.
pub fn sky_map_size(resolution: u32) -> u32 {
    (resolution / 8).max(8)
}

/// Direction `k` of the sky map's [`SKY_MAP_DIRECTIONS`] (world, unit, upwards): cosine-weighted
/// over the upper hemisphere, on a Fibonacci spiral (`r = sqrt((k + 1/2) / K)` from the zenith's
/// axis, the golden angle between neighbours), so their mean of a function is the
/// cosine-weighted mean `1 / π ∫ f cos θ dω` that Lambertian irradiance takes.
pub fn sky_direction(k: u32) -> Vec3 {
    sky_direction_among(k, SKY_MAP_DIRECTIONS)
}

/// Direction `k` of `count` on the same spiral as [`sky_direction`]'s.
pub fn sky_direction_among(k: u32, count: u32) -> Vec3 {
    let r = ((k as f32 + 0.5) / count as f32).sqrt();
    // The golden angle, π (3 - √5).
    let phi = k as f32 * std::f32::consts::PI * (3.0 - 5f32.sqrt());
    Vec3::new(r * phi.cos(), (1.0 - r * r).max(0.0).sqrt(), r * phi.sin())
}

/// The direction and irradiance of a directional light that lights clouds, if it lights them:
/// `E = color (linear) × illuminance` along the light's forward; none for a hidden, dark or broken
/// light ([`cloud_light_problem`]).
pub fn cloud_light(
    light: &DirectionalLight,
    transform: &GlobalTransform,
    visible: bool,
) -> Option<(Vec3, Vec3)> {
    if !visible || cloud_light_problem(light, transform).is_some() {
        return None;
    }
    valid_cloud_light(light, transform)
}

/// [`cloud_light`] of a visible light that [`cloud_light_problem`] accepts.
fn valid_cloud_light(
    light: &DirectionalLight,
    transform: &GlobalTransform,
) -> Option<(Vec3, Vec3)> {
    let irradiance = light.color.to_linear().to_vec3() * light.illuminance;
    let direction = light_forward(transform).try_normalize()?;
    (irradiance.max_element() > 0.0).then_some((direction.into(), irradiance))
}

/// The light's forward (`-Z`) in the world, not normalised. Not `GlobalTransform::forward`, which
/// panics in debug builds on a degenerate transform.
fn light_forward(transform: &GlobalTransform) -> bevy::math::Vec3A {
    transform.affine().matrix3 * bevy::math::Vec3A::NEG_Z
}

/// Why a directional light cannot light clouds, naming the field, its value and what is allowed;
/// none for a valid light (a dark one included). Such a light is skipped, as a dark one is: a
/// negative or non-finite irradiance would put negative or NaN light in every cloud.
pub fn cloud_light_problem(
    light: &DirectionalLight,
    transform: &GlobalTransform,
) -> Option<String> {
    let allowed = "finite and at least 0";
    if !(light.illuminance.is_finite() && light.illuminance >= 0.0) {
        return Some(format!(
            "DirectionalLight::illuminance is {} lux: it must be {allowed}",
            light.illuminance
        ));
    }
    let color = light.color.to_linear().to_vec3();
    if !(color.is_finite() && color.min_element() >= 0.0) {
        return Some(format!(
            "DirectionalLight::color is linear RGB {color}: each channel must be {allowed}"
        ));
    }
    // Finite but huge values can still overflow f32 when multiplied.
    if !(color * light.illuminance).is_finite() {
        return Some(format!(
            "DirectionalLight::color {color} × illuminance {} lux overflows f32: the irradiance \
             must be finite",
            light.illuminance
        ));
    }
    let forward = light_forward(transform);
    if forward.try_normalize().is_none() {
        return Some(format!(
            "the light's GlobalTransform maps its forward (-Z) to {forward}: it must be finite \
             and non-zero"
        ));
    }
    None
}

/// A cloud as the shadow maps see it.
type MappedCloud = (&'static GlobalTransform, &'static Aabb);

/// The directional lights of the main world, for [`collect_cloud_lights`].
pub(crate) type CloudLightQuery<'w, 's> = Query<
    'w,
    's,
    (
        Entity,
        &'static DirectionalLight,
        &'static GlobalTransform,
        &'static InheritedVisibility,
    ),
    Without<NotCloudLight>,
>;

/// A directional light that lights clouds: `E = color (linear) × illuminance`.
#[derive(Clone, Copy, Debug, PartialEq, Reflect)]
pub struct CloudLight {
    /// The light's main-world entity.
    pub entity: Entity,
    /// World direction the light travels (unit).
    pub direction: Vec3,
    /// Linear RGB irradiance: the light's linear colour × its `illuminance` (lux).
    pub irradiance: Vec3,
}

/// This frame's directional lights that light clouds ([`cloud_light`]; hidden, dark, opted-out and
/// broken lights are not among them), in query order. Written by the plugin once a frame in
/// `PostUpdate`, after transforms and visibility; the shadow maps, the lit objects and the render
/// world read it.
#[derive(Resource, Clone, Debug, Default, PartialEq, Reflect)]
#[reflect(Resource)]
pub struct CloudLights(pub Vec<CloudLight>);

/// Collects [`CloudLights`] once transforms and visibility are up to date, and warns once per
/// light, and again if its problem changes, of a visible light that [`cloud_light_problem`]
/// refuses: such a light is skipped as a dark one would be.
pub(crate) fn collect_cloud_lights(
    query: CloudLightQuery,
    mut lights: ResMut<CloudLights>,
    mut refused: Local<HashMap<Entity, String>>,
) {
    let mut collected = Vec::new();
    let mut broken = HashMap::default();
    for (entity, light, transform, visible) in &query {
        if !visible.get() {
            continue;
        }
        if let Some(problem) = cloud_light_problem(light, transform) {
            if refused.get(&entity) != Some(&problem) {
                warn!("directional light {entity}: {problem}; it does not light the clouds");
            }
            broken.insert(entity, problem);
        } else if let Some((direction, irradiance)) = valid_cloud_light(light, transform) {
            collected.push(CloudLight {
                entity,
                direction,
                irradiance,
            });
        }
    }
    *refused = broken;
    lights.set_if_neq(CloudLights(collected));
}

/// Places every cloud-lighting light's map over the clouds, and the sky map under a sky, and keeps
/// the maps' buffer sized.
pub(crate) fn place_cloud_shadow_maps(
    mut maps: ResMut<CloudShadowMaps>,
    clouds: Query<MappedCloud, (With<ParticleCloud>, Without<NotShadowCaster>)>,
    lights: Res<CloudLights>,
    (sky, ground): (Res<CloudSkyLight>, Option<Res<CloudGround>>),
    mut buffers: ResMut<Assets<ShaderBuffer>>,
) {
    let spheres: Vec<(Vec3, f32)> = clouds
        .iter()
        .map(|(transform, aabb)| {
            let (scale, _, _) = transform.to_scale_rotation_translation();
            let centre = transform.transform_point(Vec3::from(aabb.center));
            (
                centre,
                Vec3::from(aabb.half_extents).length() * scale.max_element(),
            )
        })
        .collect();
    let size = maps.resolution;
    let placed: Vec<(Entity, ShadowMapPlacement)> = (lights.0.iter().enumerate())
        .filter_map(|(i, light)| {
            let first = i as u32 * size * size;
            Some((
                light.entity,
                ShadowMapPlacement::covering(light.direction, &spheres, size, first)?,
            ))
        })
        .filter(|_| size > 0)
        .collect();
    let lit_sky = sky.radiance().is_ok_and(|r| r.max_element() > 0.0);
    let sky_first = placed.len() as u32 * size * size;
    // A refused ground (its height not finite or out of range) counts as none, as for the clouds.
    let height = ground
        .and_then(|g| g.validate().ok())
        .map_or(0.0, |g| g.height);
    let sky = (lit_sky && size > 0)
        .then(|| ShadowMapPlacement::sky(&spheres, height, sky_map_size(size), sky_first))
        .flatten();
    if maps.sky != sky {
        maps.sky = sky;
    }
    let bytes = CloudShadowMaps::buffer_bytes(placed.len(), size);
    let fits = buffers
        .get(&maps.buffer)
        .is_some_and(|b| b.buffer_description.size == bytes as u64);
    if !fits {
        let buffer = ShaderBuffer::with_size(bytes, RenderAssetUsages::default());
        maps.buffer = buffers.add(buffer);
    }
    if maps.maps != placed {
        maps.maps = placed;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Negative, NaN and infinite irradiances are refused with the field and its value; a dark
    /// light is valid but lights nothing, and so is a hidden one.
    #[test]
    fn a_broken_light_is_refused_by_name_and_a_dark_one_lights_nothing() {
        let sun = |color: Color, illuminance: f32| DirectionalLight {
            color,
            illuminance,
            ..default()
        };
        let down = GlobalTransform::from(Transform::default().looking_to(Vec3::NEG_Y, Vec3::X));
        let good = sun(Color::WHITE, 2.0);
        assert_eq!(cloud_light_problem(&good, &down), None);
        let (direction, irradiance) = cloud_light(&good, &down, true).unwrap();
        assert!((direction - Vec3::NEG_Y).length() < 1e-6);
        assert_eq!(irradiance, Vec3::splat(2.0));
        assert_eq!(cloud_light(&good, &down, false), None);
        let dark = sun(Color::WHITE, 0.0);
        assert_eq!(cloud_light_problem(&dark, &down), None);
        assert_eq!(cloud_light(&dark, &down, true), None);

        let refused = [
            (sun(Color::WHITE, -3.0), "illuminance is -3 lux"),
            (sun(Color::WHITE, f32::NAN), "illuminance is NaN lux"),
            (sun(Color::WHITE, f32::INFINITY), "illuminance is inf lux"),
            (
                sun(Color::linear_rgb(1.0, -0.5, 1.0), 2.0),
                "color is linear RGB [1, -0.5, 1]",
            ),
            (
                sun(Color::linear_rgb(f32::NAN, 1.0, 1.0), 2.0),
                "color is linear RGB [NaN, 1, 1]",
            ),
            (
                sun(Color::linear_rgb(3e38, 1.0, 1.0), 10.0),
                "overflows f32",
            ),
        ];
        for (light, expected) in refused {
            let problem = cloud_light_problem(&light, &down).expect(expected);
            assert!(problem.contains(expected), "{problem:?} lacks {expected:?}");
            assert_eq!(cloud_light(&light, &down, true), None, "{expected}");
        }
        for scale in [Vec3::NAN, Vec3::ZERO] {
            let broken = GlobalTransform::from(Transform::from_scale(scale));
            let problem = cloud_light_problem(&good, &broken).unwrap();
            assert!(
                problem.contains("GlobalTransform maps its forward (-Z) to"),
                "{problem}"
            );
            assert_eq!(cloud_light(&good, &broken, true), None);
        }
    }

    /// The collected lights are the visible, valid, lit ones that are not opted out, in query
    /// order; a light that changes is collected anew.
    #[test]
    fn the_lights_of_the_clouds_are_collected_once_a_frame() {
        use bevy::ecs::system::RunSystemOnce;
        let mut world = World::new();
        world.init_resource::<CloudLights>();
        let sun = |illuminance: f32| DirectionalLight {
            illuminance,
            ..default()
        };
        let down = GlobalTransform::from(Transform::default().looking_to(Vec3::NEG_Y, Vec3::X));
        let visible = InheritedVisibility::VISIBLE;
        let lit = world.spawn((sun(2.0), down, visible)).id();
        world.spawn((sun(2.0), down, InheritedVisibility::HIDDEN));
        world.spawn((sun(0.0), down, visible));
        world.spawn((sun(f32::NAN), down, visible));
        world.spawn((sun(5.0), down, visible, NotCloudLight));
        let side = GlobalTransform::from(Transform::default().looking_to(Vec3::X, Vec3::Y));
        let second = world.spawn((sun(3.0), side, visible)).id();
        world.run_system_once(collect_cloud_lights).unwrap();
        let lights = world.resource::<CloudLights>().0.clone();
        assert_eq!(
            lights.iter().map(|l| l.entity).collect::<Vec<_>>(),
            [lit, second]
        );
        assert!((lights[0].direction - Vec3::NEG_Y).length() < 1e-6);
        assert!((lights[1].direction - Vec3::X).length() < 1e-6);
        assert_eq!(lights[1].irradiance, Vec3::splat(3.0));

        world.entity_mut(second).insert(sun(0.0));
        world.run_system_once(collect_cloud_lights).unwrap();
        let lights = &world.resource::<CloudLights>().0;
        assert_eq!(lights.iter().map(|l| l.entity).collect::<Vec<_>>(), [lit]);
    }

    #[test]
    fn a_map_covers_every_cloud_across_its_light() {
        let down = Vec3::NEG_Y;
        let clouds = [
            (Vec3::new(0.0, 5.0, 0.0), 1.0),
            (Vec3::new(6.0, 9.0, 2.0), 2.0),
        ];
        let map = ShadowMapPlacement::covering(down, &clouds, 64, 128).unwrap();
        // Across the light the clouds span 9 m one way (x: -1..8) and 5 m the other (z: -1..4).
        assert!((map.texel * 64.0 - 9.0).abs() < 1e-4);
        // Along it, from the top of the higher one to the bottom of the lower.
        assert!((map.w_begin - -11.0).abs() < 1e-4 && (map.w_end - -4.0).abs() < 1e-4);
        // Every cloud's centre column falls on the map, past every cloud.
        for (c, _) in clouds {
            let a = (c.dot(map.u) - map.corner.x) / map.texel;
            let b = (c.dot(map.v) - map.corner.y) / map.texel;
            assert!(
                (0.0..64.0).contains(&a) && (0.0..64.0).contains(&b),
                "{a}, {b}"
            );
        }
        let p = map.texel_point(0, 0);
        assert!((p.dot(down) - map.w_end).abs() < 1e-4);
        assert_eq!(ShadowMapPlacement::covering(down, &[], 64, 0), None);
    }

    /// The sky map lies on its plane under the clouds, reaching twice their top's height beyond
    /// their footprint; no clouds above the plane, no map.
    #[test]
    fn the_sky_map_covers_what_the_clouds_hide() {
        let clouds = [
            (Vec3::new(0.0, 5.0, 0.0), 1.0),
            (Vec3::new(6.0, 9.0, 2.0), 2.0),
        ];
        let map = ShadowMapPlacement::sky(&clouds, 1.0, 32, 100).unwrap();
        // Top 11 m, 10 m above the plane: 20 m of reach each side of x -1..8.
        assert!((map.texel * 32.0 - (9.0 + 40.0)).abs() < 1e-3);
        assert_eq!((map.w_begin, map.w_end, map.first), (-11.0, -1.0, 100));
        assert!((map.texel_point(5, 7).y - 1.0).abs() < 1e-6);
        assert!((map.corner.x - (-21.0)).abs() < 1e-3);
        assert_eq!(ShadowMapPlacement::sky(&clouds, 12.0, 32, 0), None);
        assert_eq!(ShadowMapPlacement::sky(&[], 0.0, 32, 0), None);
    }

    /// The directions are unit, upwards, and cosine-weighted: their mean cosine is 2/3, and their
    /// mean of the squared cosine 1/2, as `1 / π ∫ f cos θ dω` gives.
    #[test]
    fn the_sky_directions_are_cosine_weighted() {
        let dirs: Vec<Vec3> = (0..SKY_MAP_DIRECTIONS).map(sky_direction).collect();
        assert!(
            dirs.iter()
                .all(|d| (d.length() - 1.0).abs() < 1e-6 && d.y > 0.0)
        );
        let mean =
            |f: &dyn Fn(Vec3) -> f32| dirs.iter().map(|&d| f(d)).sum::<f32>() / dirs.len() as f32;
        assert!(
            (mean(&|d| d.y) - 2.0 / 3.0).abs() < 2e-3,
            "{}",
            mean(&|d| d.y)
        );
        assert!((mean(&|d| d.y * d.y) - 0.5).abs() < 1e-6);
        assert!(mean(&|d| d.x).abs() < 0.02 && mean(&|d| d.z).abs() < 0.02);
    }
}
