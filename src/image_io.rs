//! Image output of the render example and the reference renderers (feature `image`).
//!
//! * [`write_exr`] / [`read_exr`]: linear radiance (docs/physics.md, "Output units") as 32-bit float
//!   RGBA OpenEXR, values preserved bit for bit, with [`ImageMetadata`] in the header (software,
//!   adapter, settings, samples, camera). This is what error metrics are computed on.
//! * [`tonemap_to_srgb8`] / [`write_png`]: an 8-bit sRGB picture for looking at, through a fixed
//!   display transform (see [`tonemap_to_srgb8`]). Never compute errors on PNGs.
//! * [`write_image`]: picks one of the two by the file extension.

use std::path::{Path, PathBuf};

use exr::prelude::{
    AttributeValue, Encoding, Image, Layer, LayerAttributes, ReadChannels, ReadLayers,
    SpecificChannels, Text, Vec2, WritableImage,
};
use image::{ImageFormat, Rgba, RgbaImage};

pub use crate::linear_image::LinearImage;

/// Text attributes stored in an EXR file's header beside the pixels (for example `software`,
/// `adapter`, `settings`, `spp`, `seed`, `render_time_s`, `camera`): what made the image.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct ImageMetadata(pub Vec<(String, String)>);

impl ImageMetadata {
    /// Metadata naming this crate and its version as the `software`.
    pub fn software() -> Self {
        Self(vec![(
            "software".into(),
            concat!("bevy_particle_clouds ", env!("CARGO_PKG_VERSION")).into(),
        )])
    }

    /// Adds (or replaces) one attribute.
    pub fn with(mut self, key: &str, value: impl ToString) -> Self {
        self.0.retain(|(k, _)| k != key);
        self.0.push((key.to_owned(), value.to_string()));
        self
    }

    /// The value of `key`, if present.
    pub fn get(&self, key: &str) -> Option<&str> {
        self.0
            .iter()
            .find(|(k, _)| k == key)
            .map(|(_, v)| v.as_str())
    }
}

fn check_size(img: &LinearImage, path: &Path) -> Result<(), ImageIoError> {
    let expected = img.width as u64 * img.height as u64;
    if img.width == 0 || img.height == 0 || img.pixels.len() as u64 != expected {
        return Err(ImageIoError::Size {
            path: path.to_path_buf(),
            width: img.width,
            height: img.height,
            pixels: img.pixels.len(),
        });
    }
    Ok(())
}

/// Why an image could not be written or read. Every message names the file.
#[derive(Debug, thiserror::Error)]
pub enum ImageIoError {
    #[error("cannot write '{}': {error}", path.display())]
    /// Encoding or writing a PNG failed.
    Png {
        /// The file.
        path: PathBuf,
        /// The `image` crate's error.
        error: image::ImageError,
    },
    #[error("cannot write '{}': {error}", path.display())]
    /// Encoding or writing an EXR failed.
    WriteExr {
        /// The file.
        path: PathBuf,
        /// The `exr` crate's error.
        error: exr::error::Error,
    },
    #[error("cannot read '{}': {error}", path.display())]
    /// Reading or decoding an EXR failed.
    ReadExr {
        /// The file.
        path: PathBuf,
        /// The `exr` crate's error.
        error: exr::error::Error,
    },
    #[error(
        "cannot write '{}': the image is {width}x{height} with {pixels} pixels; \
         width and height must be > 0 and the pixel count width*height",
        path.display()
    )]
    /// The image's size does not match its pixel count (or is zero).
    Size {
        /// The file.
        path: PathBuf,
        /// The image's width, pixels.
        width: u32,
        /// The image's height, pixels.
        height: u32,
        /// The number of pixels it holds.
        pixels: usize,
    },
    #[error("cannot write '{}': unsupported file extension; allowed are .exr (linear float) and .png (tonemapped sRGB)", path.display())]
    /// The path's extension is neither `.exr` nor `.png`.
    Extension {
        /// The file.
        path: PathBuf,
    },
}

/// Writes a 32-bit float RGBA OpenEXR file holding exactly the image's values (lossless ZIP
/// compression) and the crate's name and version as its `software` attribute.
pub fn write_exr(img: &LinearImage, path: &Path) -> Result<(), ImageIoError> {
    write_exr_with_metadata(img, path, &ImageMetadata::software())
}

/// [`write_exr`] with `metadata` as text attributes of the file's header.
pub fn write_exr_with_metadata(
    img: &LinearImage,
    path: &Path,
    metadata: &ImageMetadata,
) -> Result<(), ImageIoError> {
    check_size(img, path)?;
    let width = img.width as usize;
    let channels = SpecificChannels::rgba(|Vec2(x, y): Vec2<usize>| {
        let [r, g, b, a] = img.pixels[y * width + x];
        (r, g, b, a)
    });
    let size = (width, img.height as usize);
    // `software` is a standard EXR attribute; the others are custom text attributes.
    let attributes = LayerAttributes {
        software_name: metadata.get("software").map(Text::from),
        ..LayerAttributes::default()
    };
    let layer = Layer::new(size, attributes, Encoding::FAST_LOSSLESS, channels);
    let mut image = Image::from_layer(layer);
    for (key, value) in metadata.0.iter().filter(|(key, _)| key != "software") {
        image.attributes.other.insert(
            Text::from(key.as_str()),
            AttributeValue::Text(Text::from(value.as_str())),
        );
    }
    image
        .write()
        .to_file(path)
        .map_err(|error| ImageIoError::WriteExr {
            path: path.to_path_buf(),
            error,
        })
}

/// Reads the first RGBA layer of an OpenEXR file (missing alpha reads as 1) and its text
/// attributes.
pub fn read_exr_with_metadata(path: &Path) -> Result<(LinearImage, ImageMetadata), ImageIoError> {
    let image = exr::prelude::read()
        .no_deep_data()
        .largest_resolution_level()
        .rgba_channels(
            |size, _| LinearImage::new(size.width() as u32, size.height() as u32),
            |img: &mut LinearImage, Vec2(x, y), (r, g, b, a): (f32, f32, f32, f32)| {
                *img.pixel_mut(x as u32, y as u32) = [r, g, b, a];
            },
        )
        .first_valid_layer()
        .all_attributes()
        .from_file(path)
        .map_err(|error| ImageIoError::ReadExr {
            path: path.to_path_buf(),
            error,
        })?;
    let software = image.layer_data.attributes.software_name.as_ref();
    // A single-part file has one header: custom attributes may come back on the image or the layer.
    let other = image.attributes.other.iter();
    let custom = other
        .chain(&image.layer_data.attributes.other)
        .filter_map(|(key, value)| match value {
            AttributeValue::Text(text) => Some((key.to_string(), text.to_string())),
            _ => None,
        });
    let metadata = software
        .map(|name| ("software".to_owned(), name.to_string()))
        .into_iter()
        .chain(custom)
        .collect();
    Ok((
        image.layer_data.channel_data.pixels,
        ImageMetadata(metadata),
    ))
}

/// Reads the first RGBA layer of an OpenEXR file (missing alpha reads as 1).
pub fn read_exr(path: &Path) -> Result<LinearImage, ImageIoError> {
    read_exr_with_metadata(path).map(|(image, _)| image)
}

/// The display curve of [`tonemap_to_srgb8`] for one linear channel value, result in `[0, 1]`
/// before the sRGB encoding: Krzysztof Narkowicz's "ACES filmic tone mapping curve" fit (2015),
/// `f(x) = x (2.51 x + 0.03) / (x (2.43 x + 0.59) + 0.14)`, clamped to `[0, 1]`, applied to each
/// channel with exposure 1 (no pre-scale). NaN and negative values map to 0, +inf to 1.
/// `f(0.18) ≈ 0.267`, `f(1) ≈ 0.804`; it reaches 1 at `x ≈ 7.24`.
pub fn aces_fitted(x: f32) -> f32 {
    if x.is_nan() || x <= 0.0 {
        return 0.0;
    }
    let x = x.min(1.0e4) as f64; // beyond ~7.24 the curve is clamped to 1 anyway
    let y = x * (2.51 * x + 0.03) / (x * (2.43 * x + 0.59) + 0.14);
    y.clamp(0.0, 1.0) as f32
}

/// The sRGB opto-electronic transfer function (IEC 61966-2-1) of a value in `[0, 1]`.
pub fn srgb_oetf(c: f32) -> f32 {
    let c = c.clamp(0.0, 1.0) as f64;
    let v = if c <= 0.003_130_8 {
        12.92 * c
    } else {
        1.055 * c.powf(1.0 / 2.4) - 0.055
    };
    v as f32
}

fn to_u8(v: f32) -> u8 {
    (v.clamp(0.0, 1.0) * 255.0).round() as u8
}

/// The display transform used for every PNG: per channel [`aces_fitted`] (exposure 1), then the sRGB
/// OETF ([`srgb_oetf`]), rounded to 8 bits. NaN and negative radiance count as 0. Alpha is not
/// tonemapped: it is clamped to `[0, 1]` (NaN → 0) and stored linearly; pass alpha 1 for an
/// opaque picture.
pub fn tonemap_to_srgb8(img: &LinearImage) -> RgbaImage {
    let mut out = RgbaImage::new(img.width, img.height);
    for (dst, src) in out.pixels_mut().zip(&img.pixels) {
        let c = |v: f32| to_u8(srgb_oetf(aces_fitted(v)));
        let a = if src[3].is_nan() { 0 } else { to_u8(src[3]) };
        *dst = Rgba([c(src[0]), c(src[1]), c(src[2]), a]);
    }
    out
}

/// Writes the image through [`tonemap_to_srgb8`] as an 8-bit sRGB RGBA PNG.
pub fn write_png(img: &LinearImage, path: &Path) -> Result<(), ImageIoError> {
    check_size(img, path)?;
    tonemap_to_srgb8(img)
        .save_with_format(path, ImageFormat::Png)
        .map_err(|error| ImageIoError::Png {
            path: path.to_path_buf(),
            error,
        })
}

/// Refuses an output path whose extension is neither `.exr` nor `.png`, before any rendering.
pub fn check_output_path(path: &Path) -> Result<(), ImageIoError> {
    match path
        .extension()
        .and_then(|e| e.to_str())
        .map(str::to_ascii_lowercase)
        .as_deref()
    {
        Some("exr" | "png") => Ok(()),
        _ => Err(ImageIoError::Extension {
            path: path.to_path_buf(),
        }),
    }
}

/// Writes `.exr` (linear, [`write_exr`]) or `.png` (tonemapped, [`write_png`]) by the path's
/// extension, case-insensitively; any other extension is an error naming the path.
pub fn write_image(img: &LinearImage, path: &Path) -> Result<(), ImageIoError> {
    let ext = path
        .extension()
        .and_then(|e| e.to_str())
        .map(str::to_ascii_lowercase);
    match ext.as_deref() {
        Some("exr") => write_exr(img, path),
        Some("png") => write_png(img, path),
        _ => Err(ImageIoError::Extension {
            path: path.to_path_buf(),
        }),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tmp_dir(name: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("bpc_image_io_{}_{name}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        dir
    }

    fn sample() -> LinearImage {
        LinearImage {
            width: 3,
            height: 2,
            pixels: vec![
                [0.0, 1e-6, 0.5, 1.0],
                [3.25, 1e4, 0.1, 0.0],
                [1.0 / 3.0, 65504.0, 1e-30, 0.25],
                [7.0e5, 0.0, 2.5e-3, 1.0],
                [0.18, 0.18, 0.18, 0.5],
                [1.0, 2.0, 3.0, 1.0],
            ],
        }
    }

    #[test]
    fn exr_round_trip_is_bit_exact() {
        let dir = tmp_dir("exr");
        let path = dir.join("a.exr");
        let img = sample();
        write_exr(&img, &path).unwrap();
        let back = read_exr(&path).unwrap();
        assert_eq!((back.width, back.height), (3, 2));
        for (a, b) in img.pixels.iter().zip(&back.pixels) {
            for c in 0..4 {
                assert_eq!(a[c].to_bits(), b[c].to_bits(), "{a:?} vs {b:?}");
            }
        }
        // row 0 is the top row: the pixel order survives
        assert_eq!(back.pixel(0, 1), img.pixels[3]);
    }

    #[test]
    fn exr_metadata_round_trips() {
        let dir = tmp_dir("meta");
        let path = dir.join("m.exr");
        let metadata = ImageMetadata::software()
            .with("adapter", "llvmpipe")
            .with("spp", 64);
        write_exr_with_metadata(&sample(), &path, &metadata).unwrap();
        let (back, read) = read_exr_with_metadata(&path).unwrap();
        assert_eq!(back, sample());
        assert_eq!(read.get("adapter"), Some("llvmpipe"));
        assert_eq!(read.get("spp"), Some("64"));
        assert_eq!(
            read.get("software"),
            Some(concat!("bevy_particle_clouds ", env!("CARGO_PKG_VERSION")))
        );
    }

    #[test]
    fn tonemap_known_values() {
        let img = LinearImage {
            width: 4,
            height: 2,
            pixels: vec![
                [0.0, 1e6, 0.18, 1.0],
                [f32::NAN, -1.0, f32::INFINITY, f32::NAN],
                [1.0, 0.5, 2.0, 0.5],
                [0.01, 0.001, 100.0, 2.0],
                [f32::NEG_INFINITY, 7.5, 1e-9, -0.5],
                [0.0; 4],
                [1.0; 4],
                [0.0, 0.0, 0.0, 1.0],
            ],
        };
        let out = tonemap_to_srgb8(&img);
        // expected by the formulas in f64 (ACES fitted, then sRGB, round):
        // 0.18 -> 141.13, 1 -> 231.60, 0.5 -> 205.87, 2 -> 245.21, 0.01 -> 12.27, 0.001 -> 0.76
        assert_eq!(out.get_pixel(0, 0).0, [0, 255, 141, 255]);
        assert_eq!(out.get_pixel(1, 0).0, [0, 0, 255, 0]);
        assert_eq!(out.get_pixel(2, 0).0, [232, 206, 245, 128]);
        assert_eq!(out.get_pixel(3, 0).0, [12, 1, 255, 255]);
        assert_eq!(out.get_pixel(0, 1).0, [0, 255, 0, 0]);
        assert_eq!(out.get_pixel(3, 1).0, [0, 0, 0, 255]);

        // and write_png stores exactly these bytes
        let dir = tmp_dir("png");
        let path = dir.join("t.png");
        write_png(&img, &path).unwrap();
        let read = image::open(&path).unwrap().into_rgba8();
        assert_eq!(read, out);
    }

    #[test]
    fn write_image_dispatches_on_extension() {
        let dir = tmp_dir("dispatch");
        let img = sample();
        write_image(&img, &dir.join("a.EXR")).unwrap();
        assert_eq!(read_exr(&dir.join("a.EXR")).unwrap(), img);
        write_image(&img, &dir.join("b.Png")).unwrap();
        assert_eq!(
            image::open(dir.join("b.Png")).unwrap().into_rgba8(),
            tonemap_to_srgb8(&img)
        );
        for name in ["c.jpg", "noext", "d.exr.txt"] {
            let path = dir.join(name);
            let e = write_image(&img, &path).unwrap_err().to_string();
            assert!(e.contains(&path.display().to_string()), "{e}");
            assert!(e.contains(".exr") && e.contains(".png"), "{e}");
            assert!(!path.exists());
        }
    }

    #[test]
    fn size_mismatch_and_missing_file_errors() {
        let dir = tmp_dir("errors");
        let mut img = sample();
        img.pixels.pop();
        let e = write_exr(&img, &dir.join("x.exr")).unwrap_err().to_string();
        assert!(
            e.contains("x.exr") && e.contains("3x2 with 5 pixels"),
            "{e}"
        );
        let e = write_png(&LinearImage::new(0, 4), &dir.join("y.png"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("0x4"), "{e}");
        let e = read_exr(&dir.join("missing.exr")).unwrap_err().to_string();
        assert!(
            e.contains("cannot read") && e.contains("missing.exr"),
            "{e}"
        );
    }
}
