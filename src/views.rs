//! Which cameras draw clouds: those with Bevy's perspective projection.
//!
//! The view passes take a camera's rays through its projection's tangents (`x / z`, `y / z`)
//! and its near plane (docs/illumination.md §5), as Bevy's infinite reverse-Z perspective
//! defines them. Under any other projection (orthographic, or a custom one of another form) they
//! would draw a wrong image, so such a camera shows no clouds, with a warning naming it.

use bevy::{camera::visibility::VisibleEntities, platform::collections::HashSet, prelude::*};
use std::any::TypeId;

use crate::{CloudTargetScale, ParticleCloud, settings::MIN_CLOUD_TARGET_SCALE};

/// Whether `clip_from_view` is Bevy's infinite reverse-Z perspective (`PerspectiveProjection`,
/// off-centre or not): clip `w = -z`, clip `z` the near plane's distance alone.
pub fn draws_clouds(clip_from_view: &Mat4) -> bool {
    let (z, w) = (clip_from_view.z_axis, clip_from_view.w_axis);
    clip_from_view.x_axis.w == 0.0
        && clip_from_view.y_axis.w == 0.0
        && z.z == 0.0
        && z.w == -1.0
        && w.x == 0.0
        && w.y == 0.0
        && w.z > 0.0
        && w.w == 0.0
}

/// Why a camera's [`CloudTargetScale`] is not used as given, naming its value, what is allowed and
/// what is drawn instead; none for an allowed value.
pub fn target_scale_problem(scale: CloudTargetScale) -> Option<String> {
    let effective = scale.effective();
    (effective != scale.0).then(|| {
        format!(
            "CloudTargetScale is {}: it must be within {MIN_CLOUD_TARGET_SCALE}..=1, so its clouds \
             are drawn at {effective}",
            scale.0
        )
    })
}

/// Warns when a camera gets a [`CloudTargetScale`] that is clamped (or NaN), each time it is set.
pub(crate) fn warn_of_clamped_target_scales(
    scales: Query<(Entity, &CloudTargetScale), Changed<CloudTargetScale>>,
) {
    for (camera, scale) in &scales {
        if let Some(problem) = target_scale_problem(*scale) {
            warn!("camera {camera}: {problem}");
        }
    }
}

/// A word for the projection a refused camera has, for the warning.
fn projection_name(projection: Option<&Projection>) -> &'static str {
    match projection {
        Some(Projection::Orthographic(_)) => "orthographic",
        Some(Projection::Perspective(_)) => "perspective, but not Bevy's infinite reverse-Z form",
        Some(Projection::Custom(_)) => "custom",
        None => "not a Bevy `Projection`",
    }
}

/// Takes the clouds out of the visible entities of every camera that cannot draw them (after
/// Bevy's visibility check, so nothing downstream sees them there), warning once per camera. A
/// cloud that no other camera sees is then hidden, so that it is not illuminated for nothing.
pub(crate) fn hide_clouds_from_other_projections(
    mut cameras: Query<(Entity, &Camera, Option<&Projection>, &mut VisibleEntities)>,
    mut clouds: Query<&mut ViewVisibility, With<ParticleCloud>>,
    mut warned: Local<HashSet<Entity>>,
) {
    let class = TypeId::of::<ParticleCloud>();
    let mut taken = HashSet::new();
    for (entity, camera, projection, mut visible) in &mut cameras {
        if visible.is_empty(class) || draws_clouds(&camera.clip_from_view()) {
            continue;
        }
        taken.extend(visible.iter(class).copied());
        visible.clear(class);
        if warned.insert(entity) {
            warn!(
                "camera {entity}: its projection is {}; particle clouds are drawn by perspective \
                 cameras only (`Projection::Perspective`), so this camera shows none",
                projection_name(projection)
            );
        }
    }
    // Only where a camera was refused: the clouds the perspective ones still see stay visible.
    if taken.is_empty() {
        return;
    }
    for (.., visible) in &cameras {
        visible.iter(class).for_each(|cloud| {
            taken.remove(cloud);
        });
    }
    for cloud in taken {
        if let Ok(mut visibility) = clouds.get_mut(cloud)
            && visibility.get()
        {
            *visibility = ViewVisibility::HIDDEN;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use bevy::camera::CameraProjection;

    /// Allowed scales pass; outside or NaN, the warning names the value and what is drawn.
    #[test]
    fn a_clamped_target_scale_is_named_with_what_is_drawn() {
        for ok in [1.0, 0.5, MIN_CLOUD_TARGET_SCALE] {
            assert_eq!(target_scale_problem(CloudTargetScale(ok)), None, "{ok}");
        }
        let cases = [
            (
                2.0,
                "is 2: it must be within 0.125..=1, so its clouds are drawn at 1",
            ),
            (
                0.01,
                "is 0.01: it must be within 0.125..=1, so its clouds are drawn at 0.125",
            ),
            (
                f32::NAN,
                "is NaN: it must be within 0.125..=1, so its clouds are drawn at 1",
            ),
            (-1.0, "drawn at 0.125"),
        ];
        for (value, expected) in cases {
            let problem = target_scale_problem(CloudTargetScale(value)).unwrap();
            assert!(problem.contains(expected), "{problem:?} lacks {expected:?}");
        }
    }

    #[test]
    fn perspective_projections_draw_clouds_and_others_do_not() {
        let mut perspective = PerspectiveProjection::default();
        perspective.update(1280.0, 720.0);
        assert!(draws_clouds(&perspective.get_clip_from_view()));
        // A sub-view (off-centre) is still a perspective.
        let off_centre = perspective.get_clip_from_view_for_sub(&bevy::camera::SubCameraView {
            full_size: UVec2::new(2560, 1440),
            offset: Vec2::new(1280.0, 0.0),
            size: UVec2::new(1280, 720),
        });
        assert!(off_centre.z_axis.x != 0.0);
        assert!(draws_clouds(&off_centre));

        let mut orthographic = OrthographicProjection::default_3d();
        orthographic.update(1280.0, 720.0);
        assert!(!draws_clouds(&orthographic.get_clip_from_view()));
        // A finite-far perspective: clip z depends on z.
        let finite = Mat4::perspective_rh(0.8, 16.0 / 9.0, 0.1, 100.0);
        assert!(!draws_clouds(&finite));
        assert!(!draws_clouds(&Mat4::IDENTITY));
    }
}
