//! CPU reference of the cloud target's depth-aware upsample (`src/render/draw/cloud_target.wgsl`;
//! docs/illumination.md §6), written from the description, in f32 like the shader: the GPU's
//! composite is tested pixel by pixel against it.

use bevy::math::{UVec2, Vec2};

/// A cloud target as read back from the GPU, and the view it belongs to.
pub struct CloudTargetImage<'a> {
    /// Texels, row-major: premultiplied radiance and opacity.
    pub texels: &'a [[f32; 4]],
    /// Texels per side.
    pub size: UVec2,
    /// Texels per view pixel, per axis.
    pub scale: f32,
    /// The view's viewport: corner and size, pixels.
    pub viewport: (UVec2, UVec2),
    /// Relative depth difference at which a texel's weight falls to `1/e`.
    pub depth_tolerance: f32,
}

/// `|a - b| / max(a, b)` of two reverse-Z depths (0 when both are the sky).
pub fn relative_depth_difference(a: f32, b: f32) -> f32 {
    let far = a.max(b);
    if far <= 0.0 { 0.0 } else { (a - b).abs() / far }
}

impl CloudTargetImage<'_> {
    /// The view pixel under texel `t`'s centre, whose depth the texel was drawn against.
    pub fn depth_pixel(&self, t: UVec2) -> UVec2 {
        let (origin, size) = self.viewport;
        let p = ((t.as_vec2() + 0.5) / self.scale).as_uvec2();
        origin + p.min(size - 1)
    }

    /// The cloud target enlarged at view pixel `pixel`, whose scene depth `depth` returns: the
    /// four texels around the pixel's centre, weighted bilinearly times
    /// `exp(-(difference / tolerance)^2)` of their relative depth difference; when every weight
    /// vanishes, the texel nearest in reverse-Z depth (inverse depth).
    pub fn upsample(&self, pixel: UVec2, depth: impl Fn(UVec2) -> f32) -> [f32; 4] {
        let own = depth(pixel);
        let centre = pixel.as_vec2() + Vec2::splat(0.5);
        let u = (centre - self.viewport.0.as_vec2()) * self.scale - Vec2::splat(0.5);
        let base = u.floor();
        let f = u - base;
        let mut sum = [0.0f32; 4];
        let mut weight = 0.0f32;
        let mut nearest = ([0.0f32; 4], 2.0f32);
        for (dx, dy) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
            let t = (base.as_ivec2() + bevy::math::IVec2::new(dx, dy))
                .clamp(bevy::math::IVec2::ZERO, self.size.as_ivec2() - 1)
                .as_uvec2();
            let bx = if dx == 1 { f.x } else { 1.0 - f.x };
            let by = if dy == 1 { f.y } else { 1.0 - f.y };
            let texel_depth = depth(self.depth_pixel(t));
            let similarity = relative_depth_difference(own, texel_depth) / self.depth_tolerance;
            let w = bx * by * (-similarity * similarity).exp();
            let texel = self.texels[(t.y * self.size.x + t.x) as usize];
            for c in 0..4 {
                sum[c] += w * texel[c];
            }
            weight += w;
            if (own - texel_depth).abs() < nearest.1 {
                nearest = (texel, (own - texel_depth).abs());
            }
        }
        if weight < 1e-4 {
            nearest.0
        } else {
            sum.map(|s| s / weight)
        }
    }

    /// What the composite shows at `pixel` over `behind`: the upsampled radiance plus what is
    /// behind times the upsampled transmittance.
    pub fn over(&self, pixel: UVec2, depth: impl Fn(UVec2) -> f32, behind: [f32; 4]) -> [f32; 4] {
        let c = self.upsample(pixel, depth);
        std::array::from_fn(|i| c[i] + (1.0 - c[3]) * behind[i])
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn image(
        texels: &[[f32; 4]],
        size: UVec2,
        scale: f32,
        viewport: UVec2,
    ) -> CloudTargetImage<'_> {
        CloudTargetImage {
            texels,
            size,
            scale,
            viewport: (UVec2::ZERO, viewport),
            depth_tolerance: 0.05,
        }
    }

    #[test]
    fn on_one_surface_the_upsample_is_bilinear() {
        // 2×1 texels over 4×2 pixels, all at one depth.
        let texels = [[0.0, 0.0, 0.0, 0.0], [1.0, 2.0, 3.0, 0.5]];
        let img = image(&texels, UVec2::new(2, 1), 0.5, UVec2::new(4, 2));
        // Pixel 1's centre (1.5) is texel coordinate 0.25: a quarter of the way to texel 1.
        let c = img.upsample(UVec2::new(1, 0), |_| 0.3);
        assert!(
            (c[0] - 0.25).abs() < 1e-6 && (c[3] - 0.125).abs() < 1e-6,
            "{c:?}"
        );
        // Past the last texel's centre: clamped to it.
        assert_eq!(img.upsample(UVec2::new(3, 1), |_| 0.3), texels[1]);
    }

    #[test]
    fn a_pixel_takes_its_cloud_from_texels_on_its_own_surface() {
        // Texel 0 stands for a near object (depth 0.5), texel 1 for the sky (0) with a cloud.
        let texels = [[0.0; 4], [1.0, 1.0, 1.0, 1.0]];
        let img = image(&texels, UVec2::new(2, 1), 0.5, UVec2::new(4, 1));
        let depth = |p: UVec2| if p.x < 2 { 0.5 } else { 0.0 };
        assert_eq!(img.depth_pixel(UVec2::new(0, 0)), UVec2::new(1, 0));
        assert_eq!(img.depth_pixel(UVec2::new(1, 0)), UVec2::new(3, 0));
        // Pixel 1 (object) lies between the texels' centres: no cloud bleeds onto it.
        assert_eq!(img.upsample(UVec2::new(1, 0), depth), [0.0; 4]);
        // Pixel 2 (sky) too: the whole cloud, no halo of the object's empty texel.
        assert_eq!(img.upsample(UVec2::new(2, 0), depth), [1.0; 4]);
        // The sky behind shows only through the cloud's transmittance.
        let over = img.over(UVec2::new(2, 0), depth, [0.2, 0.4, 0.6, 1.0]);
        assert_eq!(over, [1.0, 1.0, 1.0, 1.0]);
    }

    #[test]
    fn sky_between_two_objects_takes_the_texel_of_the_farther() {
        let texels = [[0.0; 4], [1.0; 4]];
        let img = image(&texels, UVec2::new(2, 1), 0.5, UVec2::new(4, 1));
        // A near box (0.03) left, a wall (0.016) right, sky (0) at pixel 2: the sky sees the
        // cloud in front of the wall, not the box's empty texel.
        let depth = |p: UVec2| match p.x {
            0 | 1 => 0.03,
            2 => 0.0,
            _ => 0.016,
        };
        assert_eq!(img.upsample(UVec2::new(2, 0), depth), [1.0; 4]);
    }

    #[test]
    fn a_sliver_no_texel_stands_for_takes_the_nearest_in_depth() {
        let texels = [[1.0; 4], [0.5; 4]];
        let img = image(&texels, UVec2::new(2, 1), 0.5, UVec2::new(4, 1));
        // Pixel 2 is at 0.9; texel 0 stands for 0.1, texel 1 for 0.6: texel 1 is nearer.
        let depth = |p: UVec2| match p.x {
            1 => 0.1,
            2 => 0.9,
            _ => 0.6,
        };
        assert_eq!(img.upsample(UVec2::new(2, 0), depth), [0.5; 4]);
    }
}
