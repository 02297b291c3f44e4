//! Test policy, shared by the GPU tests: fail (never skip) without an adapter, and fail on any
//! GPU validation error. Everything else comes from the library's `headless` module.

#![allow(dead_code)]

use bevy::{
    prelude::*,
    render::{RenderApp, error_handler::RenderErrorHandler, settings::Backends},
};
use bevy_particle_clouds::{CloudQualitySettings, headless};
use std::sync::OnceLock;

/// What to do when no adapter exists: say how to get one (tests fail, never skip).
pub const NO_ADAPTER: &str = "no Vulkan adapter found: install Mesa's software driver with \
`apt-get update && apt-get install -y mesa-vulkan-drivers` (lavapipe), or a GPU driver";

/// Panics with [`NO_ADAPTER`] unless wgpu finds a Vulkan adapter.
///
/// The instance that looked is kept for the whole process, so that the Vulkan driver stays
/// loaded while each test's app creates and drops its own. Loaded and unloaded once per test,
/// NVIDIA's Linux driver (580.159) failed to load from the thirteenth test on ("cannot allocate
/// memory in static TLS block"): its loads seem to take static TLS that unloading keeps.
pub fn assert_adapter() {
    static ADAPTER: OnceLock<(wgpu::Instance, bool)> = OnceLock::new();
    let (_, found) = ADAPTER.get_or_init(|| {
        let mut desc = wgpu::InstanceDescriptor::new_without_display_handle();
        desc.backends = Backends::VULKAN;
        desc.flags = wgpu::InstanceFlags::default().with_env();
        let instance = wgpu::Instance::new(desc);
        let options = wgpu::RequestAdapterOptions {
            power_preference: wgpu::PowerPreference::HighPerformance,
            force_fallback_adapter: false,
            compatible_surface: None,
        };
        let found = bevy::tasks::block_on(instance.request_adapter(&options)).is_ok();
        (instance, found)
    });
    assert!(found, "{NO_ADAPTER}");
}

/// A headless app whose render errors panic, so a broken pass fails the test instead of
/// rendering garbage. The dev build enables winit for the windowed examples; its event loop
/// needs a display and can be created once per process, so tests leave it out.
pub fn headless_app() -> App {
    headless_app_with(headless::plugins())
}

/// [`headless_app`] of `plugins` (normally `headless::plugins()`, adjusted), less winit.
pub fn headless_app_with(plugins: bevy::app::PluginGroupBuilder) -> App {
    assert_adapter();
    let mut app = headless::app_with(plugins.disable::<bevy::winit::WinitPlugin>());
    app.insert_resource(RenderErrorHandler(|error, _, _| {
        panic!("render error {:?}: {}", error.ty, error.description)
    }));
    app
}

/// Makes every view draw its clouds every frame (`CloudRedraw::EveryFrame`), for tests that count
/// the clouds a view draws in a frame: a still view keeps its image and draws none.
pub fn draw_every_frame(app: &mut App) {
    app.insert_resource(bevy_particle_clouds::CloudRedraw::EveryFrame);
}

/// Quality settings with the given resolution and iterations, defaults otherwise.
pub fn quality(volume_resolution: u32, scatter_iterations: u32) -> CloudQualitySettings {
    CloudQualitySettings {
        volume_resolution,
        scatter_iterations,
        ..default()
    }
}

/// Runs a closure on the render world.
pub fn with_render_world<R>(app: &mut App, f: impl FnOnce(&mut World) -> R) -> R {
    f(app.sub_app_mut(RenderApp).world_mut())
}
