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

use bevy::{
    asset::RenderAssetUsages,
    camera::primitives::Aabb,
    light::{DirectionalLight, NotShadowCaster},
    prelude::*,
    render::{render_resource::ShaderType, storage::ShaderBuffer},
};

use crate::{
    cloud::{NotCloudLight, ParticleCloud},
    math::light_basis,
};

/// Cloud shadow maps: their resolution, and (written by the plugin) where each lies and the
/// buffer that holds them. A resource; off (`resolution` 0) by default.
#[derive(Resource, Clone, Debug, Default, Reflect)]
#[reflect(Resource, Default)]
pub struct CloudShadowMaps {
    /// Texels per side of each light's map; 0 (the default) turns the maps off. The maps cover
    /// every cloud, so a texel's width is the span of the clouds across the light over this.
    pub resolution: u32,
    /// Per cloud-lighting light, where its map lies (written by the plugin every frame).
    #[reflect(ignore)]
    pub maps: Vec<(Entity, ShadowMapPlacement)>,
    /// The optical depths of every map, `resolution²` f32 per light (written by the plugin's
    /// render world; bind it read-only as `array<f32>`).
    #[reflect(ignore)]
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

    /// Bytes of the maps' buffer for `lights` maps of `resolution²` texels (never empty:
    /// materials bind it whether the maps are on or not).
    pub fn buffer_bytes(lights: usize, resolution: u32) -> usize {
        (lights * (resolution * resolution) as usize * 4).max(16)
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
#[derive(ShaderType, Clone, Copy, Debug, Default, PartialEq)]
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
}

/// The direction and irradiance of a directional light that lights clouds, if it lights them:
/// `E = color (linear) × illuminance` along the light's forward; none for a hidden, dark or broken
/// light.
pub fn cloud_light(
    light: &DirectionalLight,
    transform: &GlobalTransform,
    visible: bool,
) -> Option<(Vec3, Vec3)> {
    let irradiance = light.color.to_linear().to_vec3() * light.illuminance;
    let direction = transform.forward().as_vec3();
    let lit = visible
        && irradiance.is_finite()
        && irradiance.max_element() > 0.0
        && direction.is_finite();
    lit.then_some((direction, irradiance))
}

/// A cloud as the shadow maps see it.
type MappedCloud = (&'static GlobalTransform, &'static Aabb);

/// The directional lights of the main world, for [`cloud_lights`].
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

/// Every light of `lights` that lights clouds ([`cloud_light`]): its entity, direction and
/// irradiance.
pub(crate) fn cloud_lights<'a>(
    lights: &'a CloudLightQuery,
) -> impl Iterator<Item = (Entity, Vec3, Vec3)> + 'a {
    lights
        .iter()
        .filter_map(|(entity, light, transform, visible)| {
            let (direction, irradiance) = cloud_light(light, transform, visible.get())?;
            Some((entity, direction, irradiance))
        })
}

/// Places every cloud-lighting light's map over the clouds, and keeps the maps' buffer sized.
pub(crate) fn place_cloud_shadow_maps(
    mut maps: ResMut<CloudShadowMaps>,
    clouds: Query<MappedCloud, (With<ParticleCloud>, Without<NotShadowCaster>)>,
    lights: CloudLightQuery,
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
    let placed: Vec<(Entity, ShadowMapPlacement)> = cloud_lights(&lights)
        .enumerate()
        .filter_map(|(i, (entity, d, _))| {
            let first = i as u32 * size * size;
            Some((
                entity,
                ShadowMapPlacement::covering(d, &spheres, size, first)?,
            ))
        })
        .filter(|_| size > 0)
        .collect();
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
}
