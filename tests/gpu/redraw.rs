//! A still view keeps its image (`CloudRedraw::WhenChanged`, the default): frames in which
//! nothing the clouds' image depends on changed draw no cloud, and every change that does draws
//! the same image as a view that draws every frame (`CloudRedraw::EveryFrame`).

use bevy::{camera::Exposure, prelude::*};
use bevy_particle_clouds::{
    CloudPass, CloudRedraw, Compositing,
    fog::{Falloff, Fog},
    headless::{self, FrameRecorder},
    image_io::LinearImage,
};

use crate::{cloud_target::occluded_setup, draw::spawn};

/// The image the view shows now with `CloudRedraw::WhenChanged`, then the one it draws with
/// `EveryFrame`, and the draw runs of the frames that captured the first.
fn kept_and_drawn(
    app: &mut App,
    frames: &mut FrameRecorder,
    image: &Handle<Image>,
) -> (LinearImage, LinearImage, u32) {
    app.insert_resource(CloudRedraw::WhenChanged);
    let before = frames.frames.len();
    let kept = headless::capture(app, frames, image).unwrap();
    let runs = frames.frames[before..]
        .iter()
        .map(|f| f.runs(CloudPass::Draw))
        .sum();
    app.insert_resource(CloudRedraw::EveryFrame);
    let drawn = headless::capture(app, frames, image).unwrap();
    app.insert_resource(CloudRedraw::WhenChanged);
    (kept, drawn, runs)
}

/// Kept and drawn images agree to the f16 rounding of sums added in a varying order.
const SAME: f32 = 2e-3;

#[test]
fn a_still_view_keeps_its_clouds_until_an_object_moves_in_front_of_them() {
    let setup = occluded_setup(Compositing::ViewTransmittance, 1.0);
    let (mut app, target) = spawn(&setup);
    let mut frames = FrameRecorder::default();
    headless::render_until_steady(&mut app, &mut frames, 1, 20).unwrap();
    for _ in 0..2 {
        let frame = frames.frame(&mut app).unwrap();
        assert_eq!(frame.work(), 0, "a still scene runs no pass: {frame:?}");
        assert_eq!(
            frame.runs(CloudPass::Draw),
            0,
            "nothing changed: no cloud drawn"
        );
        // The depth comparison, the splat's one batch and the resolve, whose workgroups leave
        // at once.
        assert_eq!(frame.dispatches(CloudPass::Draw), 3);
    }
    let (kept, drawn, runs) = kept_and_drawn(&mut app, &mut frames, &target.image);
    assert_eq!(runs, 0, "the capture's frames drew no cloud");
    let still = kept.worst_difference(&drawn);
    eprintln!("kept against drawn: worst difference {still:e} of the peak");
    assert!(
        still <= SAME,
        "the kept image differs by {still} of its peak"
    );

    // The box in front of the cloud moves across it: the CPU sees no change of the clouds, the
    // depth comparison does.
    let front = app
        .world_mut()
        .query::<(Entity, &Transform)>()
        .iter(app.world())
        .find(|(_, t)| t.translation == setup.objects[0].translation)
        .map(|(e, _)| e)
        .expect("the front box");
    let mut transform = app.world_mut().get_mut::<Transform>(front).unwrap();
    transform.translation.x += 0.6;
    let (moved, moved_drawn, runs) = kept_and_drawn(&mut app, &mut frames, &target.image);
    assert_eq!(runs, 0, "the CPU saw no change of the clouds");
    let changed = moved.worst_difference(&kept);
    let agree = moved.worst_difference(&moved_drawn);
    eprintln!("the box moved: {changed:e} from before, {agree:e} from the drawn image");
    assert!(changed > 0.1, "the image hardly changed ({changed})");
    assert!(
        agree <= SAME,
        "the redrawn image differs by {agree} of its peak"
    );
}

/// A change made to the camera entity.
type CameraChange = fn(&mut EntityWorldMut);

/// An exponential fog, thick enough to change the cloud's image.
fn fog() -> Fog {
    Fog {
        color: Vec3::new(0.3, 0.4, 0.5),
        alpha: 1.0,
        falloff: Falloff::Exponential { density: 0.2 },
        directional_light_color: Vec3::ZERO,
        directional_light_exponent: 8.0,
    }
}

#[test]
fn a_still_view_draws_again_when_its_fog_exposure_or_camera_changes() {
    let mut setup = occluded_setup(Compositing::ViewTransmittance, 1.0);
    setup.objects.clear();
    let (mut app, target) = spawn(&setup);
    let camera = target.camera;
    let mut frames = FrameRecorder::default();
    headless::render_until_steady(&mut app, &mut frames, 1, 20).unwrap();
    let mut previous = headless::capture(&mut app, &mut frames, &target.image).unwrap();
    let changes: [(&str, CameraChange); 3] = [
        ("fog", |c| {
            c.insert(bevy_particle_clouds::render::fog::distance_fog(&fog()));
        }),
        ("exposure", |c| {
            c.insert(Exposure { ev100: 1.0 });
        }),
        ("camera", |c| {
            c.get_mut::<Transform>().unwrap().translation.x += 0.05;
        }),
    ];
    for (what, change) in changes {
        change(&mut app.world_mut().entity_mut(camera));
        let (kept, drawn, runs) = kept_and_drawn(&mut app, &mut frames, &target.image);
        let changed = kept.worst_difference(&previous);
        let agree = kept.worst_difference(&drawn);
        eprintln!("{what}: {changed:e} from before, {agree:e} from the drawn image, {runs} runs");
        assert!(runs > 0, "{what}: the change drew no cloud");
        assert!(
            changed > 0.01,
            "{what}: the image hardly changed ({changed})"
        );
        assert!(
            agree <= SAME,
            "{what}: the image differs by {agree} of its peak"
        );
        previous = kept;
    }
}
