//! A still view keeps its image ([`CloudRedraw::WhenChanged`]; docs/illumination.md §6).
//!
//! A computing view's clouds stay in its cloud target between frames, and the target is
//! composited onto the view every frame. The CPU keys what the target's texels are made of, as
//! far as it knows it ([`DrawInputs`]); the one input it cannot know, the opaque depth each texel's
//! particles are tested against, the GPU compares before the splat (`compare_depth` in
//! `billboard.wgsl`). The view draws when either changed.

use std::sync::atomic::{AtomicU64, Ordering};

use bevy::{math::Mat4, prelude::*, render::view::ExtractedView};

use crate::render::{core::gpu::uniform_bytes, core::key_of, draw::fog::CloudFogParams};
use crate::settings::CloudRedraw;

/// What a computing view's splat reads, besides the opaque depth and the buffers that only the
/// passes before the draw write.
pub(crate) struct DrawInputs<'a> {
    /// The view: its transform, projection and viewport.
    pub view: &'a ExtractedView,
    /// The camera's exposure (the billboards' light is scaled by it).
    pub exposure: f32,
    /// The temporal jitter of the view's projection, pixels.
    pub jitter: Option<Vec2>,
    /// The view's fog uniform.
    pub fog: Option<CloudFogParams>,
    /// The key of every splat batch (its clouds' uniforms and the buffers it binds), in order.
    pub batches: Vec<u64>,
    /// The key of the target's own bindings (its texture, the depth texture, its parameters).
    pub target: u64,
    /// `CloudPassCounters::illumination_epoch`: it changes whenever any pass but the draw
    /// records work or writes what the billboards read.
    pub epoch: u64,
}

impl DrawInputs<'_> {
    /// The key of the inputs: equal keys, the same texels (given the same depth). Never 0, which
    /// stands for a target that holds nothing yet.
    pub fn key(&self) -> u64 {
        let matrix = |m: Mat4| m.to_cols_array().map(f32::to_bits);
        let view = self.view;
        key_of((
            (
                matrix(view.world_from_view.to_matrix()),
                matrix(view.clip_from_view),
                view.clip_from_world.map(matrix),
                view.viewport,
            ),
            self.exposure.to_bits(),
            self.jitter.map(|j| j.to_array().map(f32::to_bits)),
            self.fog.as_ref().map(uniform_bytes),
            &self.batches,
            self.target,
            self.epoch,
        ))
        .max(1)
    }
}

/// Whether a view whose target last showed `drawn` must draw again for inputs keyed `key`, then
/// records `key` as shown. A view that rasterises clouds into its target over the splats
/// (`rasterises`) draws every frame: its blend adds onto what the target holds.
pub(crate) fn must_redraw(
    mode: CloudRedraw,
    rasterises: bool,
    drawn: &AtomicU64,
    key: u64,
) -> bool {
    let previous = drawn.swap(key, Ordering::Relaxed);
    mode == CloudRedraw::EveryFrame || rasterises || previous != key
}

#[cfg(test)]
mod tests {
    use bevy::render::{sync_world::MainEntity, view::RetainedViewEntity};

    use super::*;

    fn view() -> ExtractedView {
        ExtractedView {
            retained_view_entity: RetainedViewEntity::new(
                MainEntity::from(Entity::PLACEHOLDER),
                None,
                0,
            ),
            clip_from_view: Mat4::perspective_infinite_reverse_rh(0.7, 1.5, 0.1),
            world_from_view: GlobalTransform::from_xyz(0.0, 1.0, 5.0),
            clip_from_world: None,
            viewport: UVec4::new(0, 0, 640, 480),
            color_grading: default(),
            invert_culling: false,
            target_format: bevy::render::render_resource::TextureFormat::Rgba16Float,
        }
    }

    #[test]
    fn every_input_the_splat_reads_changes_the_key() {
        let v = view();
        let inputs = || DrawInputs {
            view: &v,
            exposure: 1.0,
            jitter: None,
            fog: None,
            batches: vec![7, 9],
            target: 3,
            epoch: 11,
        };
        let base = inputs().key();
        assert_eq!(base, inputs().key(), "the same inputs, the same key");
        let mut moved = view();
        moved.world_from_view = GlobalTransform::from_xyz(0.0, 1.0, 5.001);
        let mut zoomed = view();
        zoomed.clip_from_view = Mat4::perspective_infinite_reverse_rh(0.71, 1.5, 0.1);
        let mut resized = view();
        resized.viewport = UVec4::new(0, 0, 640, 481);
        for other in [&moved, &zoomed, &resized] {
            assert_ne!(
                DrawInputs {
                    view: other,
                    ..inputs()
                }
                .key(),
                base
            );
        }
        let changed = [
            DrawInputs {
                exposure: 0.5,
                ..inputs()
            },
            DrawInputs {
                jitter: Some(Vec2::new(0.25, -0.25)),
                ..inputs()
            },
            DrawInputs {
                fog: Some(CloudFogParams::default()),
                ..inputs()
            },
            DrawInputs {
                batches: vec![7],
                ..inputs()
            },
            DrawInputs {
                batches: vec![7, 10],
                ..inputs()
            },
            DrawInputs {
                target: 4,
                ..inputs()
            },
            DrawInputs {
                epoch: 12,
                ..inputs()
            },
        ];
        for (i, c) in changed.iter().enumerate() {
            assert_ne!(c.key(), base, "change {i} kept the key");
        }
    }

    #[test]
    fn a_view_draws_when_its_key_changes_when_asked_every_frame_and_when_it_rasterises() {
        let drawn = AtomicU64::new(0);
        let when_changed = CloudRedraw::WhenChanged;
        assert!(
            must_redraw(when_changed, false, &drawn, 5),
            "nothing shown yet"
        );
        assert!(!must_redraw(when_changed, false, &drawn, 5), "the same key");
        assert!(must_redraw(when_changed, false, &drawn, 6), "a new key");
        assert!(
            must_redraw(when_changed, true, &drawn, 6),
            "rasterised over the splats"
        );
        assert!(must_redraw(CloudRedraw::EveryFrame, false, &drawn, 6));
        assert!(!must_redraw(when_changed, false, &drawn, 6));
    }
}
