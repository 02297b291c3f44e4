//! What an adapter must offer the plugin, checked in `Plugin::finish` (as Bevy's atmosphere does).

use bevy::{
    prelude::*,
    render::{
        render_resource::DownlevelFlags,
        renderer::{RenderAdapter, RenderDevice},
    },
};

/// Why an adapter cannot run the plugin: the passes need compute shaders, storage buffers in the
/// vertex stage and eight storage buffers per stage (the sweep's; WebGPU's default limit).
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum Unsupported {
    /// No compute shaders (WebGL2, for example).
    #[error("the adapter has no compute shaders")]
    ComputeShaders,
    /// Vertex shaders cannot read storage buffers.
    #[error("the adapter cannot read storage buffers in vertex shaders")]
    VertexStorage,
    /// Too few storage buffers per shader stage.
    #[error("the adapter allows {0} storage buffers per shader stage; 8 are needed")]
    StorageBuffers(u32),
}

/// Storage buffers per shader stage the plugin's pipelines bind at most (tests hold every
/// pipeline to it), but the computed draw's, which falls back to the rasteriser on an adapter
/// that allows fewer (`splat::compute_draw_refusal`); an adapter with fewer cannot run it.
pub(crate) const REQUIRED_STORAGE_BUFFERS: u32 = 8;

/// Why this adapter cannot run the plugin, if it cannot.
pub(crate) fn check_adapter(render_app: &SubApp) -> Result<(), Unsupported> {
    let adapter = render_app.world().resource::<RenderAdapter>();
    let flags = adapter.get_downlevel_capabilities().flags;
    let limits = render_app.world().resource::<RenderDevice>().limits();
    if !flags.contains(DownlevelFlags::COMPUTE_SHADERS) {
        return Err(Unsupported::ComputeShaders);
    }
    if !flags.contains(DownlevelFlags::VERTEX_STORAGE) {
        return Err(Unsupported::VertexStorage);
    }
    if limits.max_storage_buffers_per_shader_stage < REQUIRED_STORAGE_BUFFERS {
        return Err(Unsupported::StorageBuffers(
            limits.max_storage_buffers_per_shader_stage,
        ));
    }
    Ok(())
}
