//! The renderer's and the references' common image type: linear radiance, unclamped.

/// A linear image: RGB radiance (units of the lights' irradiance, exposure 1) and alpha,
/// row-major, row 0 at the top.
#[derive(Clone, Debug, PartialEq)]
pub struct LinearImage {
    /// Pixels per row.
    pub width: u32,
    /// Rows.
    pub height: u32,
    /// `width * height` pixels `[r, g, b, a]`, pixel `(x, y)` at `y * width + x`.
    pub pixels: Vec<[f32; 4]>,
}

impl LinearImage {
    /// A `width` × `height` image with every pixel `[0, 0, 0, 0]`.
    pub fn new(width: u32, height: u32) -> Self {
        Self {
            width,
            height,
            pixels: vec![[0.0; 4]; width as usize * height as usize],
        }
    }

    /// The pixel at column `x`, row `y` (row 0 at the top).
    pub fn pixel(&self, x: u32, y: u32) -> [f32; 4] {
        self.pixels[y as usize * self.width as usize + x as usize]
    }

    /// Mutable access to the pixel at column `x`, row `y`.
    pub fn pixel_mut(&mut self, x: u32, y: u32) -> &mut [f32; 4] {
        &mut self.pixels[y as usize * self.width as usize + x as usize]
    }

    /// The largest difference of any channel (alpha included) between this image and
    /// `reference`, over the reference's brightest RGB value.
    pub fn worst_difference(&self, reference: &LinearImage) -> f32 {
        let peak = (reference.pixels.iter().flat_map(|p| &p[..3])).fold(0f32, |m, v| m.max(*v));
        let worst = (self.pixels.iter().zip(&reference.pixels))
            .flat_map(|(p, q)| (0..4).map(move |c| (p[c] - q[c]).abs()))
            .fold(0f32, f32::max);
        worst / peak.max(1e-6)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_worst_difference_is_over_the_reference_peak() {
        let mut reference = LinearImage::new(2, 1);
        reference.pixels = vec![[2.0, 0.5, 0.0, 1.0], [0.0, 0.0, 0.0, 0.0]];
        let mut image = reference.clone();
        assert_eq!(image.worst_difference(&reference), 0.0);
        image.pixels[1] = [0.0, 0.0, 0.0, 0.5];
        assert_eq!(image.worst_difference(&reference), 0.25);
    }
}
