//! The per-view passes (the paper's Algorithm 1, line 7, and what compositing needs per camera):
//! the GPU sort of each view's particles (`sort`, `Compositing::Sorted`), the optical depth from
//! the camera (`view_volume`, `Compositing::ViewTransmittance`), and the shared buffers a view's
//! volumes live in (`view_atlas`).

pub mod sort;
pub mod view_atlas;
pub mod view_volume;
pub mod view_volume_node;

use bevy::{
    platform::collections::HashMap,
    prelude::*,
    render::view::{ExtractedView, RenderVisibleEntities},
};

use crate::cloud::ParticleCloud;

/// Every view each visible cloud is seen in (the per-view passes: sort, view volume).
pub(crate) fn views_by_cloud<'a>(
    views: impl IntoIterator<Item = (&'a ExtractedView, &'a RenderVisibleEntities)>,
) -> HashMap<Entity, Vec<&'a ExtractedView>> {
    let mut by_cloud: HashMap<Entity, Vec<&ExtractedView>> = HashMap::default();
    for (view, visible) in views {
        if let Some(class) = visible.get::<ParticleCloud>() {
            for (entity, _) in &class.entities_cpu_culling {
                by_cloud.entry(*entity).or_default().push(view);
            }
        }
    }
    by_cloud
}
