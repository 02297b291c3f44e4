//! The ground under the clouds: a horizontal Lambertian plane that lights them from below with the
//! light it reflects (docs/illumination.md §4, "The ground").
//!
//! A cloud's multiple-scattering sweep takes, on every lattice line that climbs into its grid,
//! the ground's radiance where that line, continued backwards, meets the plane: the sun's and the
//! sky's light reflected there, with the cloud's own shadow on it. The radiance is held per cloud
//! in a small map of the plane under it ([`GroundMapPlacement`]), shared by the GPU and the CPU
//! reference.

use bevy::{math::Affine3A, prelude::*};

/// A horizontal Lambertian ground under the clouds (world `y = height`): the light it reflects
/// lights the clouds from below, as the path tracer's lit ground does. Insert it to turn the
/// bounce on; without it (the default) the sky's radiance enters the clouds from below too.
///
/// The ground's radiance is `reflectance / π` times the irradiance of the cloud-lighting lights
/// (through the cloud's own shadow, and that of the clouds its light volumes hold) plus the sky's
/// `π L_sky` ([`CloudSkyLight`](crate::CloudSkyLight), unshadowed). It is only a light source:
/// draw the ground itself with your own mesh (`lit_object::LitObjectMaterial` takes the clouds'
/// shadows).
#[derive(Resource, Clone, Copy, Debug, PartialEq, Reflect)]
#[reflect(Resource, Default, Debug, PartialEq)]
pub struct CloudGround {
    /// World height of the plane, metres (its `y`), within ±[`MAX_GROUND_HEIGHT`]. Default 0.
    pub height: f32,
    /// Lambertian reflectance (albedo), linear RGB, each in `[0, 1]`. Default 0.3, bare soil and
    /// grass.
    pub reflectance: Vec3,
}

impl Default for CloudGround {
    fn default() -> Self {
        Self {
            height: 0.0,
            reflectance: Vec3::splat(0.3),
        }
    }
}

impl CloudGround {
    /// Itself, or why it is refused (the field, its value and what is allowed).
    pub fn validate(&self) -> Result<Self, String> {
        // NaN fails too.
        if self.height.is_nan() || self.height.abs() > MAX_GROUND_HEIGHT {
            return Err(format!(
                "`CloudGround::height` is {} m; it must be within ±{MAX_GROUND_HEIGHT:e} m",
                self.height
            ));
        }
        let r = self.reflectance;
        if !r.is_finite() || r.min_element() < 0.0 || r.max_element() > 1.0 {
            return Err(format!(
                "`CloudGround::reflectance` is {r}; every component must be in [0, 1]"
            ));
        }
        Ok(*self)
    }
}

/// The largest `|CloudGround::height|`, metres: far beyond any world, and far enough from f32's
/// range that the map under a cloud stays finite.
pub const MAX_GROUND_HEIGHT: f32 = 1e9;

/// Texels per side of a cloud's ground map.
pub const GROUND_MAP_SIDE: u32 = 32;

/// The lattice's steepest climb: a line along `(1, 1, 1)` moves `sqrt 2` across per unit up.
const WIDEST_REACH: f32 = std::f32::consts::SQRT_2;

/// Where a cloud's ground map lies: a square of the plane centred under the cloud's grid, wide
/// enough to hold every point the grid's climbing lattice lines come from (those of a rotated
/// grid that come from further away take its edge texels: far ground, out of the cloud's shadow).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GroundMapPlacement {
    /// The plane's world height, metres.
    pub height: f32,
    /// World `(x, z)` of the map's centre, metres.
    pub centre: Vec2,
    /// Half the map's width, metres.
    pub half_width: f32,
}

impl GroundMapPlacement {
    /// The map of a cloud whose grid is the cube of side `side` from `origin` (cloud-local
    /// metres), placed by `world_from_local`, over a ground at world height `height`.
    pub fn new(world_from_local: Affine3A, origin: Vec3, side: f32, height: f32) -> Self {
        let corners = (0..8).map(|c| {
            let corner = Vec3::new((c & 1) as f32, ((c >> 1) & 1) as f32, (c >> 2) as f32);
            world_from_local.transform_point3(origin + corner * side)
        });
        let (low, high) =
            corners.fold((Vec3::MAX, Vec3::MIN), |(lo, hi), p| (lo.min(p), hi.max(p)));
        let reach = WIDEST_REACH * (high.y - height).max(0.0);
        let half = 0.5 * (high - low);
        Self {
            height,
            centre: Vec2::new(low.x + half.x, low.z + half.z),
            half_width: half.x.max(half.z) + reach,
        }
    }

    /// World `(x, z)` of texel `(i, j)`'s centre (`i` along world x, `j` along z).
    pub fn texel_centre(&self, i: u32, j: u32) -> Vec2 {
        let texel = 2.0 * self.half_width / GROUND_MAP_SIDE as f32;
        self.centre - Vec2::splat(self.half_width) + (Vec2::new(i as f32, j as f32) + 0.5) * texel
    }

    /// The continuous texel coordinate of world `(x, z)` (texel `i`'s centre at `i`), clamped to
    /// the map: the edge texels extend outwards.
    pub fn texel_coords(&self, xz: Vec2) -> Vec2 {
        let side = GROUND_MAP_SIDE as f32;
        let c = (xz - self.centre + Vec2::splat(self.half_width)) / (2.0 * self.half_width) * side;
        (c - 0.5).clamp(Vec2::ZERO, Vec2::splat(side - 1.0))
    }
}

/// Bilinear interpolation of a ground map's `values` (texel `i + side j`) at world `(x, z)`.
pub fn sample_ground_map<T>(placement: &GroundMapPlacement, values: &[T], xz: Vec2) -> T
where
    T: Copy + std::ops::Mul<f64, Output = T> + std::ops::Add<Output = T>,
{
    let side = GROUND_MAP_SIDE as usize;
    let c = placement.texel_coords(xz);
    let base = c.floor().min(Vec2::splat(side as f32 - 2.0));
    let f = (c - base).as_dvec2();
    let (i, j) = (base.x as usize, base.y as usize);
    let at = |di: usize, dj: usize| values[i + di + side * (j + dj)];
    (at(0, 0) * (1.0 - f.x) + at(1, 0) * f.x) * (1.0 - f.y)
        + (at(0, 1) * (1.0 - f.x) + at(1, 1) * f.x) * f.y
}

/// Where a lattice line that climbs along the world direction `travel` (`travel.y > 0`) through
/// the world point `entry` comes from: the plane's point below it, continued backwards (`entry`'s
/// own `(x, z)` where `entry` is below the plane).
pub fn ground_point_behind(entry: Vec3, travel: Vec3, height: f32) -> Vec2 {
    let t = (entry.y - height).max(0.0) / travel.y;
    Vec2::new(entry.x - travel.x * t, entry.z - travel.z * t)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn validation_names_the_field_and_what_is_allowed() {
        assert!(CloudGround::default().validate().is_ok());
        let high = CloudGround {
            height: f32::NAN,
            ..default()
        };
        assert!(
            high.validate()
                .unwrap_err()
                .contains("`CloudGround::height` is NaN m")
        );
        let deep = CloudGround {
            height: -3e38,
            ..default()
        };
        let problem = deep.validate().unwrap_err();
        assert!(
            problem.contains("height` is -3") && problem.contains("±1e9 m"),
            "{problem}"
        );
        let bright = CloudGround {
            reflectance: Vec3::new(0.2, 1.5, 0.2),
            ..default()
        };
        let problem = bright.validate().unwrap_err();
        assert!(problem.contains("reflectance` is [0.2, 1.5, 0.2]") && problem.contains("[0, 1]"));
    }

    /// The map is centred under the grid and reaches as far as the steepest climbing line from
    /// the grid's top comes from; texel centres and coordinates invert each other.
    #[test]
    fn the_map_holds_where_every_climbing_line_comes_from() {
        let world = Affine3A::from_translation(Vec3::new(10.0, 5.0, -3.0));
        let map = GroundMapPlacement::new(world, Vec3::splat(-1.0), 2.0, 1.0);
        assert_eq!(map.centre, Vec2::new(10.0, -3.0));
        // Top at y = 6: 5 m above the plane, sqrt 2 across per metre up, plus the half side.
        assert!((map.half_width - (1.0 + 5.0 * WIDEST_REACH)).abs() < 1e-5);
        let centre = map.texel_centre(3, 17);
        assert!((map.texel_coords(centre) - Vec2::new(3.0, 17.0)).length() < 1e-4);
        // Beyond the map: the edge texel.
        assert_eq!(map.texel_coords(Vec2::new(1e6, -1e6)), Vec2::new(31.0, 0.0));
        // A (1, 1, 1) line through the grid's top corner comes from within the map, as does one
        // of a grid turned 45 degrees about y, which moves sqrt 2 along x per metre up.
        let top = Vec3::new(9.0, 6.0, -4.0);
        for travel in [Vec3::ONE, Vec3::new(WIDEST_REACH, 1.0, 0.0)] {
            let from = ground_point_behind(top, travel, 1.0) - map.centre;
            assert!(from.abs().max_element() <= map.half_width + 1e-4, "{from}");
        }
    }

    #[test]
    fn a_linear_map_samples_exactly() {
        let map = GroundMapPlacement {
            height: 0.0,
            centre: Vec2::ZERO,
            half_width: 16.0,
        };
        let side = GROUND_MAP_SIDE;
        let values: Vec<f64> = (0..side * side)
            .map(|t| {
                let c = map.texel_centre(t % side, t / side);
                (2.0 * c.x - c.y) as f64
            })
            .collect();
        let at = Vec2::new(3.3, -7.8);
        assert!((sample_ground_map(&map, &values, at) - (2.0 * 3.3 + 7.8)).abs() < 1e-4);
    }
}
