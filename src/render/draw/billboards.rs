//! The billboard draw in the `Transparent3d` phase (the paper's Algorithm 3): one phase item per
//! cloud and view (per group of view-transmittance clouds that overlap on screen), instanced
//! draws of a four-vertex strip per particle, depth test on (reverse Z), depth writes off.
//! `Compositing::Sorted`: one draw in the sorted order, premultiplied-alpha blending.
//! `Compositing::ViewTransmittance`: two order-independent draws, one multiplying what is behind
//! by each particle's transmittance, one adding each particle's light, first for every cloud of
//! the group, then for every cloud (one draw into a cloud target, `cloud_target.rs`, which holds
//! only clouds).
use bevy::{
    core_pipeline::core_3d::CORE_3D_DEPTH_FORMAT,
    prelude::*,
    render::{
        render_resource::{
            BindGroupLayoutDescriptor, BlendComponent, BlendFactor, BlendOperation, BlendState,
            ColorTargetState, ColorWrites, CompareFunction, DepthBiasState, DepthStencilState,
            FragmentState, MultisampleState, PrimitiveState, PrimitiveTopology,
            RenderPipelineDescriptor, ShaderStages, ShaderType, SpecializedRenderPipeline,
            StencilState, TextureFormat, VertexState,
            binding_types::{storage_buffer_read_only_sized, uniform_buffer, uniform_buffer_sized},
        },
        view::ViewUniform,
    },
};

use crate::render::{
    core::gpu::sequential_layout,
    core::shaders::CloudShaders,
    draw::fog::{CloudFogParams, FogMode},
    extract::ExtractedCloud,
};
use crate::settings::{BillboardShading, Compositing};

/// Mirror of `DrawParams` in `billboard.wgsl`.
#[derive(ShaderType, Clone, Copy, Debug, Default)]
pub struct DrawParams {
    /// World from cloud-local.
    pub world_from_local: Mat4,
    /// Cloud-local from world (the shading points' lookups).
    pub local_from_world: Mat4,
    /// Uniform scale: world metres per local metre.
    pub scale: f32,
    /// Extinction `K` per world metre at density 1.
    pub extinction: f32,
    /// Segments of each chord at which the illumination is evaluated (`chord_segments`).
    pub segments: u32,
    /// 1 when the illumination is evaluated once per particle, at its centre
    /// (`BillboardShading::Centre`).
    pub centre_shading: u32,
}

/// A cloud's billboard uniform.
pub(crate) fn draw_params(cloud: &ExtractedCloud) -> DrawParams {
    let world_from_local = Mat4::from(cloud.world_from_local);
    DrawParams {
        world_from_local,
        local_from_world: world_from_local.inverse(),
        scale: cloud.scale(),
        extinction: cloud.extinction,
        segments: cloud.settings.chord_segments,
        centre_shading: (cloud.settings.billboard_shading == BillboardShading::Centre) as u32,
    }
}

/// The billboard render pipeline's layouts and shader (specialized per view target).
#[derive(Resource)]
pub struct BillboardPipeline {
    /// Group 0: the view uniform and the view's fog.
    pub view_layout: BindGroupLayoutDescriptor,
    /// Group 1 when sorted: draw uniform, cloud uniform, particles, sorted order, lights,
    /// optical depths, multiple scattering.
    pub sorted_layout: BindGroupLayoutDescriptor,
    /// Group 1 through the view transmittance: the same with the view volume's uniform in place
    /// of the order, then the view's atlas: optical depths, volumes, neighbour lists.
    pub view_transmittance_layout: BindGroupLayoutDescriptor,
    shader: Handle<Shader>,
}

impl BillboardPipeline {
    /// `billboard.wgsl`.
    pub fn shader(&self) -> Handle<Shader> {
        self.shader.clone()
    }

    pub(crate) fn cloud_layout(&self, compositing: Compositing) -> &BindGroupLayoutDescriptor {
        match compositing {
            Compositing::Sorted => &self.sorted_layout,
            Compositing::ViewTransmittance => &self.view_transmittance_layout,
        }
    }
}

pub(crate) fn init_billboard_pipeline(mut commands: Commands, shaders: Res<CloudShaders>) {
    commands.insert_resource(BillboardPipeline::new(shaders.billboard.clone()));
}

impl BillboardPipeline {
    /// The layouts, drawing with `shader`.
    pub(crate) fn new(shader: Handle<Shader>) -> Self {
        let view_layout = sequential_layout(
            "particle_clouds_view_layout",
            ShaderStages::VERTEX_FRAGMENT,
            (
                uniform_buffer::<ViewUniform>(true),
                uniform_buffer::<CloudFogParams>(true),
            ),
        );
        let read = || storage_buffer_read_only_sized(false, None);
        let uniform = || uniform_buffer_sized(false, None);
        let sorted_layout = sequential_layout(
            "particle_clouds_billboard_sorted_layout",
            ShaderStages::VERTEX_FRAGMENT,
            (
                uniform(),
                uniform(),
                read(),
                read(),
                read(),
                read(),
                read(),
                read(),
            ),
        );
        let view_transmittance_layout = sequential_layout(
            "particle_clouds_billboard_view_transmittance_layout",
            ShaderStages::VERTEX_FRAGMENT,
            (
                uniform(),
                uniform(),
                read(),
                uniform(),
                read(),
                read(),
                read(),
                read(),
                read(),
                read(),
                read(),
            ),
        );
        BillboardPipeline {
            view_layout,
            sorted_layout,
            view_transmittance_layout,
            shader,
        }
    }
}

/// What one billboard draw does to the colour target.
#[derive(Clone, Copy, PartialEq, Eq, Hash, Debug)]
pub enum BillboardBlend {
    /// `Compositing::Sorted`: premultiplied colour and alpha over what is behind.
    Sorted,
    /// `Compositing::ViewTransmittance`, first draw: what is behind times `1 - alpha`.
    Attenuate,
    /// `Compositing::ViewTransmittance`, second draw: plus each particle's light.
    Emit,
    /// `Compositing::ViewTransmittance` into a cloud target, which holds only clouds: one draw
    /// that adds each particle's light and accumulates its opacity in alpha
    /// (`a <- alpha + a (1 - alpha)`, so `1 - a` is the product of the transmittances).
    Accumulate,
}

impl BillboardBlend {
    fn compositing(self) -> Compositing {
        match self {
            Self::Sorted => Compositing::Sorted,
            Self::Attenuate | Self::Emit | Self::Accumulate => Compositing::ViewTransmittance,
        }
    }

    fn entry_point(self) -> &'static str {
        match self {
            Self::Sorted => "fragment",
            Self::Attenuate => "attenuate",
            Self::Emit => "emit",
            Self::Accumulate => "accumulate",
        }
    }

    fn state(self) -> BlendState {
        let component = |src_factor, dst_factor| BlendComponent {
            src_factor,
            dst_factor,
            operation: BlendOperation::Add,
        };
        match self {
            Self::Sorted => BlendState::PREMULTIPLIED_ALPHA_BLENDING,
            Self::Attenuate => BlendState {
                color: component(BlendFactor::Zero, BlendFactor::OneMinusSrcAlpha),
                alpha: component(BlendFactor::One, BlendFactor::OneMinusSrcAlpha),
            },
            Self::Emit => BlendState {
                color: component(BlendFactor::One, BlendFactor::One),
                alpha: component(BlendFactor::Zero, BlendFactor::One),
            },
            Self::Accumulate => BlendState {
                color: component(BlendFactor::One, BlendFactor::One),
                alpha: component(BlendFactor::One, BlendFactor::OneMinusSrcAlpha),
            },
        }
    }
}

/// Where the billboards are drawn.
#[derive(Clone, Copy, PartialEq, Eq, Hash, Debug)]
pub enum BillboardTarget {
    /// Into the view's own colour target, depth-tested by its depth attachment.
    View {
        /// The view's colour target format (HDR or not).
        format: TextureFormat,
        /// MSAA sample count of the view.
        samples: u32,
    },
    /// Into the view's reduced-resolution cloud target (`cloud_target.rs`), depth-tested in the
    /// fragment shader against the view's depth.
    CloudTarget {
        /// Whether the view's depth is multisampled.
        multisampled_depth: bool,
        /// The target's format (`ViewCloudTarget::format`).
        format: TextureFormat,
    },
}

/// What a billboard pipeline depends on: where it draws, the draw's blend and the view's fog.
#[derive(Clone, Copy, PartialEq, Eq, Hash, Debug)]
pub struct BillboardPipelineKey {
    /// The target drawn into.
    pub target: BillboardTarget,
    /// Which of the compositing's draws.
    pub blend: BillboardBlend,
    /// The view's distance fog, if any.
    pub fog: Option<FogMode>,
}

impl SpecializedRenderPipeline for BillboardPipeline {
    type Key = BillboardPipelineKey;

    fn specialize(&self, key: Self::Key) -> RenderPipelineDescriptor {
        let compositing = key.blend.compositing();
        // The shared `types` module uses the workgroup defs too.
        let mut shader_defs = crate::render::core::workgroups::shader_defs();
        if compositing == Compositing::ViewTransmittance {
            shader_defs.push("VIEW_TRANSMITTANCE".into());
        }
        if let Some(fog) = key.fog {
            shader_defs.extend(fog.shader_defs().map(Into::into));
        }
        // The attenuating draw writes alpha only: its vertices need no centre shading.
        if key.blend == BillboardBlend::Attenuate {
            shader_defs.push("ALPHA_ONLY".into());
        }
        let (view_layout, format, samples, depth_stencil) = match key.target {
            BillboardTarget::View { format, samples } => (
                self.view_layout.clone(),
                format,
                samples,
                Some(DepthStencilState {
                    format: CORE_3D_DEPTH_FORMAT,
                    // Read-only depth: opaque geometry hides particles, particles hide nothing.
                    depth_write_enabled: Some(false),
                    depth_compare: Some(CompareFunction::GreaterEqual),
                    stencil: StencilState::default(),
                    bias: DepthBiasState::default(),
                }),
            ),
            BillboardTarget::CloudTarget {
                multisampled_depth,
                format,
            } => {
                shader_defs.push("CLOUD_TARGET".into());
                if multisampled_depth {
                    shader_defs.push("MULTISAMPLED".into());
                }
                (
                    crate::render::draw::target::billboard_view_layout(multisampled_depth),
                    format,
                    1,
                    None,
                )
            }
        };
        RenderPipelineDescriptor {
            label: Some("particle_clouds_billboards".into()),
            layout: vec![view_layout, self.cloud_layout(compositing).clone()],
            vertex: VertexState {
                shader: self.shader.clone(),
                entry_point: Some("vertex".into()),
                shader_defs: shader_defs.clone(),
                buffers: vec![],
            },
            fragment: Some(FragmentState {
                shader: self.shader.clone(),
                entry_point: Some(key.blend.entry_point().into()),
                shader_defs,
                targets: vec![Some(ColorTargetState {
                    format,
                    blend: Some(key.blend.state()),
                    write_mask: ColorWrites::ALL,
                })],
            }),
            primitive: PrimitiveState {
                topology: PrimitiveTopology::TriangleStrip,
                cull_mode: None,
                ..default()
            },
            depth_stencil,
            multisample: MultisampleState {
                count: samples,
                mask: !0,
                alpha_to_coverage_enabled: false,
            },
            ..default()
        }
    }
}
