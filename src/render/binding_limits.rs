//! The draw's and the view passes' pipelines bind no more storage buffers per shader stage than
//! the adapter check in `Plugin::finish` asks for (the illumination passes' test is in
//! `pipelines.rs`). The computed draw binds more, and falls back to the rasteriser on an adapter
//! that allows fewer (`splat.rs`).

use bevy::render::render_resource::{BindGroupLayoutDescriptor, ShaderStages};

use crate::render::{
    core::adapter::REQUIRED_STORAGE_BUFFERS,
    core::gpu::storage_buffers_in,
    draw::BillboardPipeline,
    draw::target::{billboard_view_layout, composite_layout},
    view::sort::sort_layout,
    view::view_volume::view_volume_layouts,
};

/// Asserts that the pipeline of `groups` fits the adapter check in every stage it runs.
fn assert_fits(groups: &[&BindGroupLayoutDescriptor]) {
    for stage in [
        ShaderStages::VERTEX,
        ShaderStages::FRAGMENT,
        ShaderStages::COMPUTE,
    ] {
        let storage = storage_buffers_in(groups, stage);
        let labels: Vec<&str> = groups.iter().map(|g| &*g.label).collect();
        assert!(
            storage <= REQUIRED_STORAGE_BUFFERS,
            "{labels:?} bind {storage} storage buffers in {stage:?}"
        );
    }
}

#[test]
fn every_billboard_pipeline_fits_the_storage_buffers_the_adapter_check_asks_for() {
    let billboards = BillboardPipeline::new(Default::default());
    let view_groups = [
        billboards.view_layout.clone(),
        billboard_view_layout(false),
        billboard_view_layout(true),
    ];
    for view in &view_groups {
        for cloud in [
            &billboards.sorted_layout,
            &billboards.view_transmittance_layout,
        ] {
            assert_fits(&[view, cloud]);
        }
    }
}

#[test]
fn the_sort_view_volume_and_composite_pipelines_fit_the_adapter_check() {
    assert_fits(&[&sort_layout()]);
    for layout in &view_volume_layouts() {
        assert_fits(&[layout]);
    }
    assert_fits(&[&composite_layout(false)]);
    assert_fits(&[&composite_layout(true)]);
}
