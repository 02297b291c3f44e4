//! The ground under each cloud (docs/illumination.md §4, "The ground"): the frame the CPU writes
//! into the cloud's slot of its pool's ground maps, and the key of what the map depends on. The
//! ground pass (`ground.wgsl`) fills the map's radiance at the start of the scatter stage; the
//! sweep (`scatter.wgsl`) reads it.

use bevy::{math::Affine3A, prelude::*, render::render_resource::ShaderType};

use crate::ground::{CloudGround, GROUND_MAP_SIDE, GroundMapPlacement};
use crate::render::{core::key_of, core::types::CloudParams, extract::ExtractedCloud};

/// Mirror of the frame at the start of `GroundMap` in `types.wgsl`: where the cloud and the
/// ground under it lie, and what the ground reflects.
#[derive(ShaderType, Clone, Copy, Debug, Default, PartialEq)]
pub struct GroundFrame {
    /// Rows of the cloud's world-from-local affine map (translation in w).
    pub world_from_local: [Vec4; 3],
    /// Rows of its inverse.
    pub local_from_world: [Vec4; 3],
    /// The plane's world height; the map's centre (world x, z); its half-width. Metres.
    pub plane: Vec4,
    /// Lambertian reflectance (xyz); w 1 when a ground lights the cloud, else 0 (the sweep then
    /// takes the sky from every side).
    pub reflectance: Vec4,
    /// The sky's radiance (xyz), which the ground reflects.
    pub sky: Vec4,
}

/// Bytes of one slot's `GroundMap`: the frame, then a vec4 of radiance per texel.
pub fn ground_map_bytes() -> u64 {
    GroundFrame::min_size().get() + 16 * (GROUND_MAP_SIDE as u64).pow(2)
}

/// The rows of an affine map, translation in w.
fn rows(affine: Affine3A) -> [Vec4; 3] {
    let m = Mat4::from(affine).transpose();
    [m.x_axis, m.y_axis, m.z_axis]
}

/// The ground frame of `cloud` with the uniform `params` under `ground` (none: a frame that
/// turns the ground off) and the sky `sky`.
pub fn ground_frame(
    cloud: &ExtractedCloud,
    params: &CloudParams,
    ground: Option<&CloudGround>,
    sky: Vec3,
) -> GroundFrame {
    let Some(ground) = ground else {
        return GroundFrame::default();
    };
    let to_world = cloud.world_from_local;
    let side = params.n as f32 * params.h;
    let map = GroundMapPlacement::new(to_world, params.grid_origin, side, ground.height);
    GroundFrame {
        world_from_local: rows(to_world),
        local_from_world: rows(to_world.inverse()),
        plane: Vec4::new(map.height, map.centre.x, map.centre.y, map.half_width),
        reflectance: ground.reflectance.extend(1.0),
        sky: sky.extend(0.0),
    }
}

/// The key of a cloud's ground frame (0 without a ground): the scattering reruns when it changes.
pub fn ground_key(frame: &GroundFrame) -> u64 {
    if frame.reflectance.w == 0.0 {
        return 0;
    }
    let bits = |v: &[Vec4]| -> Vec<[u32; 4]> {
        v.iter().map(|v| v.to_array().map(f32::to_bits)).collect()
    };
    key_of((
        bits(&frame.world_from_local),
        bits(&[frame.plane, frame.reflectance, frame.sky]),
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The rows map points as the affine map does, and the frame's inverse undoes it.
    #[test]
    fn the_frame_rows_are_the_affine_map() {
        let affine = Affine3A::from_scale_rotation_translation(
            Vec3::splat(2.0),
            Quat::from_rotation_y(0.7),
            Vec3::new(1.0, 5.0, -2.0),
        );
        let r = rows(affine);
        let p = Vec3::new(0.3, -0.4, 0.9);
        let mapped = Vec3::new(
            r[0].dot(p.extend(1.0)),
            r[1].dot(p.extend(1.0)),
            r[2].dot(p.extend(1.0)),
        );
        assert!((mapped - affine.transform_point3(p)).length() < 1e-5);
    }

    #[test]
    fn the_frame_is_the_head_of_the_wgsl_map() {
        // 9 vec4: the WGSL `GroundMap`'s radiance starts right after them.
        assert_eq!(GroundFrame::min_size().get(), 9 * 16);
    }
}
