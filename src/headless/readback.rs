//! Reading the GPU's results back: a captured frame as linear floats, buffers and textures.

use super::*;

/// Captures the next rendered frame of the `Rgba16Float` render target `image` (for a scene,
/// [`SceneTarget::image`]) as linear RGBA floats.
pub fn capture(
    app: &mut App,
    recorder: &mut FrameRecorder,
    image: &Handle<Image>,
) -> Result<LinearImage, HeadlessError> {
    let shot: Arc<Mutex<Option<Image>>> = Arc::default();
    let sink = shot.clone();
    app.world_mut()
        .spawn(Screenshot::image(image.clone()))
        .observe(move |captured: On<ScreenshotCaptured>| {
            *sink.lock().unwrap() = Some(captured.image.clone())
        });
    recorder.frame(app)?;
    const FRAMES: usize = 10;
    for _ in 0..FRAMES {
        if let Some(image) = shot.lock().unwrap().take() {
            return decode_rgba16f(&image);
        }
        recorder.drain(app)?;
    }
    Err(HeadlessError::NoScreenshot { frames: FRAMES })
}

/// Converts an `Rgba16Float` image into linear floats.
pub fn decode_rgba16f(image: &Image) -> Result<LinearImage, HeadlessError> {
    let format = image.texture_descriptor.format;
    let (TextureFormat::Rgba16Float, Some(data)) = (format, image.data.as_ref()) else {
        return Err(HeadlessError::Format { format });
    };
    let pixels = data
        .chunks_exact(8)
        .map(|px| {
            std::array::from_fn(|c| f16_to_f32(u16::from_le_bytes([px[2 * c], px[2 * c + 1]])))
        })
        .collect();
    Ok(LinearImage {
        width: image.width(),
        height: image.height(),
        pixels,
    })
}

/// IEEE 754 half to single precision.
pub fn f16_to_f32(bits: u16) -> f32 {
    let sign = if bits & 0x8000 != 0 { -1.0 } else { 1.0 };
    let exponent = ((bits >> 10) & 0x1f) as i32;
    let mantissa = (bits & 0x3ff) as f32;
    sign * match exponent {
        0 => mantissa * 2f32.powi(-24),
        31 if mantissa == 0.0 => f32::INFINITY,
        31 => f32::NAN,
        e => (1.0 + mantissa / 1024.0) * 2f32.powi(e - 15),
    }
}

/// Copies a GPU buffer back to the CPU (blocking): for comparing what a pass wrote with the CPU
/// reference.
pub fn read_buffer(
    app: &mut App,
    buffer: &bevy::render::render_resource::Buffer,
) -> Result<Vec<u8>, HeadlessError> {
    read_back(app, buffer.size(), |encoder, staging| {
        encoder.copy_buffer_to_buffer(buffer, 0, staging, 0, buffer.size());
    })
}

/// The bytes of a part of a GPU buffer (a cloud's slot in a volume pool, for example).
pub fn read_buffer_range(
    app: &mut App,
    range: &crate::render::plan::pools::BufferRange,
) -> Result<Vec<u8>, HeadlessError> {
    read_back(app, range.size, |encoder, staging| {
        encoder.copy_buffer_to_buffer(&range.buffer, range.offset, staging, 0, range.size);
    })
}

/// Records `copy` of `size` bytes into a mappable staging buffer, submits it, waits and returns
/// the bytes.
fn read_back(
    app: &mut App,
    size: u64,
    copy: impl FnOnce(
        &mut bevy::render::render_resource::CommandEncoder,
        &bevy::render::render_resource::Buffer,
    ),
) -> Result<Vec<u8>, HeadlessError> {
    use bevy::render::{
        render_resource::{BufferDescriptor, BufferUsages, CommandEncoderDescriptor, MapMode},
        renderer::RenderQueue,
    };
    let world = app.sub_app(RenderApp).world();
    let device = world.resource::<RenderDevice>();
    let staging = device.create_buffer(&BufferDescriptor {
        label: Some("headless_readback"),
        size,
        usage: BufferUsages::MAP_READ | BufferUsages::COPY_DST,
        mapped_at_creation: false,
    });
    let mut encoder = device.create_command_encoder(&CommandEncoderDescriptor::default());
    copy(&mut encoder, &staging);
    world.resource::<RenderQueue>().submit([encoder.finish()]);
    let slice = staging.slice(..);
    let mapped: Arc<Mutex<Option<String>>> = Arc::default();
    let sink = mapped.clone();
    slice.map_async(MapMode::Read, move |result| {
        *sink.lock().unwrap() = result.err().map(|e| e.to_string());
    });
    device
        .poll(PollType::wait_indefinitely())
        .map_err(|e| HeadlessError::Poll(e.to_string()))?;
    if let Some(error) = mapped.lock().unwrap().take() {
        return Err(HeadlessError::Poll(error));
    }
    let data = slice.get_mapped_range().to_vec();
    staging.unmap();
    Ok(data)
}

/// Copies a 2D texture (its first mip level; the depth aspect of a depth texture) back to the
/// CPU (blocking), rows tightly packed: for comparing what a render pass wrote with the CPU
/// reference. The texture needs `COPY_SRC` usage.
pub fn read_texture(
    app: &mut App,
    texture: &bevy::render::render_resource::Texture,
) -> Result<Vec<u8>, HeadlessError> {
    use bevy::render::render_resource::{
        TexelCopyBufferInfo, TexelCopyBufferLayout, TextureAspect,
    };
    let aspect = if texture.format().is_depth_stencil_format() {
        TextureAspect::DepthOnly
    } else {
        TextureAspect::All
    };
    let texel = texture
        .format()
        .block_copy_size(Some(aspect))
        .ok_or(HeadlessError::Format {
            format: texture.format(),
        })?;
    let (width, height) = (texture.width(), texture.height());
    let row = width * texel;
    // Buffer copies need rows aligned to 256 bytes.
    let padded = row.next_multiple_of(256);
    let bytes = read_back(app, u64::from(padded * height), |encoder, staging| {
        let mut source = texture.as_image_copy();
        source.aspect = aspect;
        encoder.copy_texture_to_buffer(
            source,
            TexelCopyBufferInfo {
                buffer: staging,
                layout: TexelCopyBufferLayout {
                    offset: 0,
                    bytes_per_row: Some(padded),
                    rows_per_image: Some(height),
                },
            },
            texture.size(),
        );
    })?;
    Ok(bytes
        .chunks_exact(padded as usize)
        .flat_map(|r| &r[..row as usize])
        .copied()
        .collect())
}

/// Little-endian f32s of a byte buffer.
pub fn floats(bytes: &[u8]) -> Vec<f32> {
    bytes
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .collect()
}
