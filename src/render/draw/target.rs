//! A view's reduced-resolution cloud target (the paper's §4): its formats, its uniforms, its
//! textures and the bind group layouts of what draws into it and reads it. The billboards, the
//! computed splat and the upsample ([`cloud_target`](super::cloud_target)) all share it.

use bevy::{
    prelude::*,
    render::{
        render_resource::{
            BindGroupLayoutDescriptor, CachedRenderPipelineId, ShaderStages, ShaderType,
            TextureFormat, TextureSampleType, WgpuFeatures,
            binding_types::{
                texture_2d, texture_depth_2d, texture_depth_2d_multisampled, uniform_buffer,
                uniform_buffer_sized,
            },
        },
        view::ViewUniform,
    },
};

use crate::render::{core::gpu::sequential_layout, draw::fog::CloudFogParams};
/// The format of a cloud target that only the computed draw writes: premultiplied linear
/// radiance and opacity, in HDR. The splat rounds each texel to it once.
pub const CLOUD_TARGET_FORMAT: TextureFormat = TextureFormat::Rgba16Float;

/// The format of a cloud target that the rasteriser blends into (`Sorted` clouds, or the
/// rasterised draw below full size), where the adapter can blend it: the blend rounds after every
/// particle, and in f16 that darkened images (on llvmpipe, which rounds towards zero; see
/// docs/performance.md, "The draw's rounding").
pub const BLENDED_CLOUD_TARGET_FORMAT: TextureFormat = TextureFormat::Rgba32Float;

/// The format of a view's cloud target: [`BLENDED_CLOUD_TARGET_FORMAT`] where the rasteriser
/// blends into it and the adapter can blend that format, else [`CLOUD_TARGET_FORMAT`].
pub fn cloud_target_format(rasterised_into: bool, features: WgpuFeatures) -> TextureFormat {
    if rasterised_into && features.contains(WgpuFeatures::FLOAT32_BLENDABLE) {
        BLENDED_CLOUD_TARGET_FORMAT
    } else {
        CLOUD_TARGET_FORMAT
    }
}

/// The relative depth difference (see `relative_depth_difference` in `types.wgsl`) at which a
/// texel's upsampling weight falls to `1/e`. Neighbouring pixels of one surface differ by far
/// less, even at grazing angles; a cloud and the object in front of it by far more.
pub const DEPTH_TOLERANCE: f32 = 0.05;

/// Mirror of `CloudTargetParams` in `types.wgsl`.
#[derive(ShaderType, Clone, Copy, Debug, Default, PartialEq)]
pub struct CloudTargetParams {
    /// The view's viewport in its target: corner, pixels.
    pub viewport_origin: UVec2,
    /// The viewport's size, pixels.
    pub viewport_size: UVec2,
    /// Texels per side of the cloud target.
    pub target_size: UVec2,
    /// Cloud-target texels per view pixel, per axis.
    pub scale: f32,
    /// [`DEPTH_TOLERANCE`].
    pub depth_tolerance: f32,
}

impl CloudTargetParams {
    /// The target of a viewport of `size` pixels at `scale`: at least one texel per side.
    pub fn new(viewport_origin: UVec2, viewport_size: UVec2, scale: f32) -> Self {
        let target_size = (viewport_size.as_vec2() * scale)
            .ceil()
            .as_uvec2()
            .max(UVec2::ONE);
        Self {
            viewport_origin,
            viewport_size,
            target_size,
            scale,
            depth_tolerance: DEPTH_TOLERANCE,
        }
    }

    /// The view pixel whose depth texel `t` stands for (`cloud_target_depth_pixel` in WGSL).
    pub fn depth_pixel(&self, t: UVec2) -> UVec2 {
        let p = ((t.as_vec2() + 0.5) / self.scale).as_uvec2();
        self.viewport_origin + p.min(self.viewport_size - 1)
    }
}

/// A view's cloud target, when its scale is below 1 or it computes its clouds' pixels
/// (`DrawMethod::Compute`): the scale and the target's size. Decided in `PrepareViews`, before
/// the billboards are queued.
#[derive(Component, Clone, Copy, Debug, PartialEq)]
pub struct ViewCloudTarget {
    /// The target's parameters (scale and sizes).
    pub params: CloudTargetParams,
    /// Whether the view's depth is multisampled.
    pub multisampled: bool,
    /// Whether its view-transmittance clouds are splatted by compute (splat.rs) instead of
    /// rasterised.
    pub compute: bool,
    /// The target's format ([`cloud_target_format`]).
    pub format: TextureFormat,
}

/// The clouds a view with a cloud target rasterises into it, back to front, with their
/// pipelines.
#[derive(Component, Default)]
pub struct ViewCloudDraws(pub Vec<(Entity, CachedRenderPipelineId)>);

/// The clouds a computing view splats into its cloud target (before it rasterises the others).
#[derive(Component, Default)]
pub struct ViewCloudSplats(pub Vec<Entity>);

/// Group 0 of the billboard pipeline when drawing into a cloud target.
pub(crate) fn billboard_view_layout(multisampled: bool) -> BindGroupLayoutDescriptor {
    sequential_layout(
        "particle_clouds_cloud_target_view_layout",
        ShaderStages::VERTEX_FRAGMENT,
        (
            uniform_buffer::<ViewUniform>(true),
            uniform_buffer::<CloudTargetParams>(false),
            depth_binding(multisampled),
            uniform_buffer::<CloudFogParams>(true),
        ),
    )
}

/// The composite's group: its parameters, the cloud target, the view's depth.
pub(crate) fn composite_layout(multisampled: bool) -> BindGroupLayoutDescriptor {
    sequential_layout(
        "particle_clouds_cloud_target_composite_layout",
        ShaderStages::FRAGMENT,
        (
            uniform_buffer_sized(false, None),
            texture_2d(TextureSampleType::Float { filterable: false }),
            depth_binding(multisampled),
        ),
    )
}

pub(crate) fn depth_binding(
    multisampled: bool,
) -> bevy::render::render_resource::BindGroupLayoutEntryBuilder {
    if multisampled {
        texture_depth_2d_multisampled()
    } else {
        texture_depth_2d()
    }
}
