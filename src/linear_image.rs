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
}
