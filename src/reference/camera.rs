//! The pinhole camera shared by the CPU reference renderers, matching Bevy's perspective camera
//! (vertical field of view, aspect = width / height, rays through pixel centres, +Y up, looking down -Z).

use bevy::math::DVec3;

/// A pinhole camera in world space.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PinholeCamera {
    /// Eye position, metres.
    pub position: DVec3,
    /// Unit viewing direction.
    pub forward: DVec3,
    /// Unit right vector (image +x).
    pub right: DVec3,
    /// Unit up vector (image -y: row 0 is the top).
    pub up: DVec3,
    /// `tan(vertical_fov / 2)`.
    pub tan_half_fov: f64,
    /// Image width, pixels.
    pub width: u32,
    /// Image height, pixels.
    pub height: u32,
    /// Near-plane distance along `forward`, metres (Bevy's default perspective near is 0.1).
    pub near: f64,
}

/// Bevy's default `PerspectiveProjection::near`, metres.
pub const DEFAULT_NEAR: f64 = 0.1;

impl PinholeCamera {
    /// A camera at `position` looking at `look_at` with the `up` hint (like `Transform::looking_at`).
    pub fn looking_at(
        position: DVec3,
        look_at: DVec3,
        up: DVec3,
        vertical_fov_degrees: f64,
        width: u32,
        height: u32,
    ) -> Self {
        let forward = (look_at - position).normalize();
        let right = forward.cross(up).normalize();
        let up = right.cross(forward);
        Self {
            position,
            forward,
            right,
            up,
            tan_half_fov: (vertical_fov_degrees.to_radians() * 0.5).tan(),
            width,
            height,
            near: DEFAULT_NEAR,
        }
    }

    /// The camera of a scene file.
    pub fn from_scene(camera: &crate::scene::SceneCamera) -> Self {
        Self::looking_at(
            camera.position.as_dvec3(),
            camera.look_at.as_dvec3(),
            camera.up.as_dvec3(),
            camera.vertical_fov_degrees as f64,
            camera.width,
            camera.height,
        )
    }

    /// Unit world direction of the ray through image point `(x, y)` in pixels
    /// (`(px + 0.5, py + 0.5)` is the centre of pixel `(px, py)`; `y` grows downwards).
    pub fn ray_direction(&self, x: f64, y: f64) -> DVec3 {
        let aspect = self.width as f64 / self.height as f64;
        let ndc_x = 2.0 * x / self.width as f64 - 1.0;
        let ndc_y = 1.0 - 2.0 * y / self.height as f64;
        (self.forward
            + self.right * (ndc_x * self.tan_half_fov * aspect)
            + self.up * (ndc_y * self.tan_half_fov))
            .normalize()
    }

    /// Unit direction through the centre of pixel `(px, py)`.
    pub fn pixel_ray(&self, px: u32, py: u32) -> DVec3 {
        self.ray_direction(px as f64 + 0.5, py as f64 + 0.5)
    }

    /// View depth (distance along `forward`) of a world point.
    pub fn view_depth(&self, point: DVec3) -> f64 {
        (point - self.position).dot(self.forward)
    }
}
