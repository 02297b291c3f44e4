//! The plugin end to end on the GPU (lavapipe on CI): plain scenes, opaque objects, a cloud's
//! life cycle, invalid clouds.

use bevy::prelude::*;
use bevy_particle_clouds::headless::{self, FrameRecorder, SceneTarget};
use bevy_particle_clouds::{
    CloudPass, CloudQualitySettings, Compositing, Medium, Particle, ParticleCloud, Particles,
    scene::{ObjectShape, SceneObject},
};

use crate::common;

const W: u32 = 64;
const H: u32 = 48;

fn setup(background: Vec3, camera: Transform) -> (App, SceneTarget) {
    let mut app = common::headless_app();
    let image = headless::float_target(&mut app, W, H);
    let camera = headless::spawn_linear_camera(&mut app, image.clone(), camera, 40.0, background);
    (
        app,
        SceneTarget {
            image,
            width: W,
            height: H,
            camera,
            drawable_clouds: 0,
        },
    )
}

fn pixel(image: &bevy_particle_clouds::image_io::LinearImage, x: u32, y: u32) -> [f32; 4] {
    image.pixels[(y * image.width + x) as usize]
}

fn close(a: [f32; 4], b: Vec3, tolerance: f32) -> bool {
    (a[0] - b.x).abs() <= tolerance
        && (a[1] - b.y).abs() <= tolerance
        && (a[2] - b.z).abs() <= tolerance
}

/// A small cloud (20 particles, bounding sphere radius ~1.3 m) at `translation`, 16³.
pub(crate) fn small_cloud(app: &mut App, albedo: f32, translation: Vec3) -> Entity {
    let particles: Vec<Particle> = (0..20)
        .map(|i| {
            let a = i as f32 * 0.7;
            Particle {
                position: Vec3::new(a.cos() * 0.4, (i as f32 * 0.05) - 0.5, a.sin() * 0.4),
                radius: 0.35,
                density: 1.0,
            }
        })
        .collect();
    headless::spawn_cloud(
        app,
        particles,
        Medium {
            extinction: 4.0,
            albedo,
            ..Default::default()
        },
        common::quality(16, 4),
        Transform::from_translation(translation),
    )
}

/// [`small_cloud`] composited with `compositing`.
fn small_cloud_compositing(app: &mut App, albedo: f32, compositing: Compositing) -> Entity {
    let cloud = small_cloud(app, albedo, Vec3::ZERO);
    app.world_mut()
        .entity_mut(cloud)
        .insert(CloudQualitySettings {
            compositing,
            ..common::quality(16, 4)
        });
    cloud
}

#[test]
fn without_clouds_the_plain_scene_renders_and_no_pass_runs() {
    let background = Vec3::new(0.25, 0.5, 1.0);
    let (mut app, target) = setup(
        background,
        Transform::from_xyz(0.0, 0.0, 5.0).looking_at(Vec3::ZERO, Vec3::Y),
    );
    headless::spawn_light(&mut app, Vec3::new(0.0, -1.0, -0.3), Vec3::splat(2.0));
    let mut recorder = FrameRecorder::default();
    for _ in 0..4 {
        recorder.frame(&mut app).unwrap();
    }
    let image = headless::capture(&mut app, &mut recorder, &target.image).unwrap();
    for frame in &recorder.frames {
        assert!(
            frame.passes.iter().all(|(_, runs)| *runs == 0),
            "a pass ran without clouds: {frame:?}"
        );
    }
    for &p in &image.pixels {
        assert!(
            close(p, background, 1e-3),
            "pixel {p:?} differs from the background {background}"
        );
    }
}

#[test]
fn an_opaque_object_renders_exactly_its_color() {
    let background = Vec3::new(0.1, 0.1, 0.1);
    let color = Vec3::new(0.8, 0.2, 0.05);
    let (mut app, target) = setup(
        background,
        Transform::from_xyz(0.0, 0.0, 5.0).looking_at(Vec3::ZERO, Vec3::Y),
    );
    headless::spawn_object(
        &mut app,
        &SceneObject {
            shape: ObjectShape::Cuboid(Vec3::new(1.0, 1.0, 0.2)),
            translation: Vec3::ZERO,
            color,
            reflectance: Vec3::ZERO,
        },
    );
    let mut recorder = FrameRecorder::default();
    for _ in 0..3 {
        recorder.frame(&mut app).unwrap();
    }
    let image = headless::capture(&mut app, &mut recorder, &target.image).unwrap();
    // f16 storage: 11 significant bits.
    assert!(
        close(
            pixel(&image, W / 2, H / 2),
            color,
            color.max_element() / 1024.0
        ),
        "{:?}",
        pixel(&image, W / 2, H / 2)
    );
    assert!(close(pixel(&image, 1, 1), background, 1e-3));
}

#[test]
fn a_static_cloud_is_illuminated_once_then_only_drawn() {
    let background = Vec3::new(0.0, 0.0, 0.0);
    let (mut app, mut target) = setup(
        background,
        Transform::from_xyz(0.0, 0.0, 4.0).looking_at(Vec3::ZERO, Vec3::Y),
    );
    headless::spawn_light(
        &mut app,
        Vec3::new(-1.0, -1.0, -0.5),
        Vec3::new(2.0, 1.8, 1.6),
    );
    small_cloud(&mut app, 0.9, Vec3::ZERO);
    target.drawable_clouds = 1;
    let mut recorder = FrameRecorder::default();
    let frames =
        headless::render_until_steady(&mut app, &mut recorder, target.drawable_clouds, 20).unwrap();
    let first_work: u32 = recorder.frames.iter().map(|f| f.work()).sum();
    assert_eq!(recorder.total(CloudPass::Voxelize), 1, "voxelized once");
    assert_eq!(recorder.total(CloudPass::Shade), 1, "one light shaded once");
    assert_eq!(recorder.total(CloudPass::Gather), 1);
    assert_eq!(recorder.total(CloudPass::Scatter), 4, "4 iterations");
    assert_eq!(
        recorder.total(CloudPass::ViewVolume),
        1,
        "one view's volume marched once"
    );
    assert_eq!(
        recorder.total(CloudPass::Sort),
        0,
        "no sort through the view transmittance (the default)"
    );
    assert!(
        first_work > 0 && frames <= 3,
        "illumination took {frames} frames"
    );
    for _ in 0..3 {
        let frame = recorder.frame(&mut app).unwrap();
        assert_eq!(frame.work(), 0, "a static scene repeats no work: {frame:?}");
        assert_eq!(
            frame.runs(CloudPass::Draw),
            0,
            "a still view keeps its image (`CloudRedraw`)"
        );
    }
    let image = headless::capture(&mut app, &mut recorder, &target.image).unwrap();
    assert!(
        image
            .pixels
            .iter()
            .flatten()
            .all(|v| v.is_finite() && *v >= 0.0)
    );
    let centre = pixel(&image, W / 2, H / 2);
    assert!(
        centre[3] > 0.0 && centre[0] > 1e-3,
        "the cloud is visible and lit: {centre:?}"
    );
    assert!(
        close(pixel(&image, 0, 0), background, 1e-4),
        "outside the cloud the background shows"
    );

    // Moving the light re-shades, gathers and scatters, but never re-voxelizes or reruns a view
    // pass.
    let light = app
        .world_mut()
        .query_filtered::<Entity, With<DirectionalLight>>()
        .single(app.world())
        .unwrap();
    app.world_mut()
        .entity_mut(light)
        .insert(Transform::default().looking_to(Vec3::new(1.0, -1.0, 0.0), Vec3::Y));
    let frame = recorder.frame(&mut app).unwrap().clone();
    assert_eq!(frame.runs(CloudPass::Voxelize), 0);
    assert_eq!(frame.runs(CloudPass::Shade), 1);
    assert_eq!(frame.runs(CloudPass::Gather), 1);
    assert_eq!(frame.runs(CloudPass::ViewVolume), 0);
}

#[test]
fn opted_out_and_dark_lights_cost_nothing_and_unseen_clouds_do_no_work() {
    let (mut app, mut target) = setup(
        Vec3::ZERO,
        Transform::from_xyz(0.0, 0.0, 4.0).looking_at(Vec3::ZERO, Vec3::Y),
    );
    headless::spawn_light(&mut app, Vec3::NEG_Y, Vec3::ONE);
    let opted_out = headless::spawn_light(&mut app, Vec3::X, Vec3::ONE);
    app.world_mut()
        .entity_mut(opted_out)
        .insert(bevy_particle_clouds::NotCloudLight);
    headless::spawn_light(&mut app, Vec3::Z, Vec3::ZERO);
    small_cloud(&mut app, 0.9, Vec3::ZERO);
    small_cloud(&mut app, 0.9, Vec3::new(0.0, 0.0, 40.0)); // behind the camera: culled
    target.drawable_clouds = 1;
    let mut recorder = FrameRecorder::default();
    headless::render_until_steady(&mut app, &mut recorder, target.drawable_clouds, 20).unwrap();
    assert_eq!(
        recorder.total(CloudPass::Voxelize),
        1,
        "only the visible cloud is voxelized"
    );
    assert_eq!(
        recorder.total(CloudPass::Shade),
        1,
        "only the one lit, opted-in light is shaded"
    );
    assert_eq!(recorder.total(CloudPass::ViewVolume), 1);
}

#[test]
fn several_cameras_hdr_and_not_msaa_on_and_off() {
    several_cameras(Compositing::Sorted, CloudPass::Sort);
    several_cameras(Compositing::ViewTransmittance, CloudPass::ViewVolume);
}

fn several_cameras(compositing: Compositing, view_pass: CloudPass) {
    let mut app = common::headless_app();
    common::draw_every_frame(&mut app);
    headless::spawn_light(&mut app, Vec3::new(-1.0, -1.0, -1.0), Vec3::splat(3.0));
    small_cloud_compositing(&mut app, 0.95, compositing);
    // An HDR camera with 4x MSAA and an 8-bit sRGB one without: both must draw the cloud.
    let hdr = headless::float_target(&mut app, W, H);
    let camera = headless::spawn_linear_camera(
        &mut app,
        hdr.clone(),
        Transform::from_xyz(0.0, 0.0, 4.0).looking_at(Vec3::ZERO, Vec3::Y),
        40.0,
        Vec3::ZERO,
    );
    app.world_mut().entity_mut(camera).insert(Msaa::Sample4);
    let mut ldr_image = Image::new_target_texture(
        W,
        H,
        bevy::render::render_resource::TextureFormat::Rgba8UnormSrgb,
        None,
    );
    ldr_image.texture_descriptor.usage |= bevy::render::render_resource::TextureUsages::COPY_SRC;
    let ldr = app
        .world_mut()
        .resource_mut::<Assets<Image>>()
        .add(ldr_image);
    app.world_mut().spawn((
        Camera3d::default(),
        bevy::camera::RenderTarget::Image(ldr.into()),
        Msaa::Off,
        bevy::core_pipeline::tonemapping::Tonemapping::Reinhard,
        Transform::from_xyz(3.0, 1.0, 3.0).looking_at(Vec3::ZERO, Vec3::Y),
    ));
    let mut recorder = FrameRecorder::default();
    let mut last = Default::default();
    for _ in 0..5 {
        last = recorder.frame(&mut app).unwrap().clone();
    }
    assert_eq!(last.runs(CloudPass::Draw), 2, "one draw per camera");
    assert_eq!(
        recorder.total(view_pass),
        2,
        "{compositing:?}: one {view_pass:?} per camera"
    );
    assert_eq!(
        recorder.total(CloudPass::Voxelize),
        1,
        "illumination is shared by the views"
    );
    let target = SceneTarget {
        image: hdr,
        width: W,
        height: H,
        camera,
        drawable_clouds: 1,
    };
    let image = headless::capture(&mut app, &mut recorder, &target.image).unwrap();
    let centre = pixel(&image, W / 2, H / 2);
    assert!(
        centre[0] > 1e-3 && centre[0].is_finite(),
        "{compositing:?}: the MSAA view shows the cloud: {centre:?}"
    );
}

/// Edits the particles of `cloud`'s asset in place (an asset change, as a game makes one).
pub(crate) fn edit_particles(app: &mut App, cloud: Entity, edit: impl FnOnce(&mut Vec<Particle>)) {
    let handle = app
        .world()
        .get::<ParticleCloud>(cloud)
        .unwrap()
        .particles
        .clone();
    edit(
        &mut app
            .world_mut()
            .resource_mut::<Assets<Particles>>()
            .get_mut(&handle)
            .unwrap()
            .particles,
    );
}

/// Renders the small cloud on black at the given camera `ev100`.
fn cloud_at_exposure(ev100: f32) -> bevy_particle_clouds::image_io::LinearImage {
    let (mut app, mut target) = setup(
        Vec3::ZERO,
        Transform::from_xyz(0.0, 0.0, 4.0).looking_at(Vec3::ZERO, Vec3::Y),
    );
    app.world_mut()
        .entity_mut(target.camera)
        .insert(bevy::camera::Exposure { ev100 });
    headless::spawn_light(&mut app, Vec3::new(-1.0, -1.0, -0.5), Vec3::splat(2.0));
    small_cloud(&mut app, 0.9, Vec3::ZERO);
    target.drawable_clouds = 1;
    let mut recorder = FrameRecorder::default();
    headless::render_until_steady(&mut app, &mut recorder, target.drawable_clouds, 20).unwrap();
    headless::capture(&mut app, &mut recorder, &target.image).unwrap()
}

#[test]
fn the_camera_exposure_scales_clouds_like_lit_surfaces() {
    let unit = cloud_at_exposure(headless::UNIT_EXPOSURE_EV100);
    // One stop more: Bevy's exposure factor halves, and so must the cloud's radiance.
    let half = cloud_at_exposure(headless::UNIT_EXPOSURE_EV100 + 1.0);
    let mut compared = 0;
    for (a, b) in unit.pixels.iter().zip(&half.pixels) {
        if a[0] > 0.02 {
            assert!(
                (b[0] - 0.5 * a[0]).abs() <= 2e-3 * a[0] + 1e-4,
                "{} vs half of {}",
                b[0],
                a[0]
            );
            compared += 1;
        }
    }
    assert!(compared > 50, "the cloud covers pixels");
}

#[test]
fn changing_the_particles_revoxelizes_and_reruns_the_view_pass() {
    for (compositing, view_pass, slid) in [
        (Compositing::ViewTransmittance, CloudPass::ViewVolume, 1),
        (Compositing::Sorted, CloudPass::Sort, 0),
    ] {
        let (mut app, mut target) = setup(
            Vec3::ZERO,
            Transform::from_xyz(0.0, 0.0, 4.0).looking_at(Vec3::ZERO, Vec3::Y),
        );
        headless::spawn_light(&mut app, Vec3::NEG_Y, Vec3::ONE);
        let cloud = small_cloud_compositing(&mut app, 0.9, compositing);
        target.drawable_clouds = 1;
        let mut recorder = FrameRecorder::default();
        headless::render_until_steady(&mut app, &mut recorder, target.drawable_clouds, 20).unwrap();
        edit_particles(&mut app, cloud, |p| p[0].position.x += 0.1);
        let mut runs = [0; 2];
        for _ in 0..3 {
            let frame = recorder.frame(&mut app).unwrap();
            runs[0] += frame.runs(CloudPass::Voxelize);
            runs[1] += frame.runs(view_pass);
        }
        assert_eq!(
            runs,
            [1, 1],
            "{compositing:?}: one re-voxelization and one {view_pass:?} after the asset changed"
        );
        // Turning the cloud reruns the view pass but never re-voxelizes (the grid is cloud-local).
        app.world_mut()
            .entity_mut(cloud)
            .insert(Transform::from_rotation(Quat::from_rotation_y(0.5)));
        let frame = recorder.frame(&mut app).unwrap().clone();
        assert_eq!(
            (frame.runs(CloudPass::Voxelize), frame.runs(view_pass)),
            (0, 1)
        );
        // Sliding it sideways keeps every view depth's order (no sort) but moves the cloud
        // across the view (a new view volume).
        app.world_mut().entity_mut(cloud).insert(
            Transform::from_rotation(Quat::from_rotation_y(0.5)).with_translation(Vec3::X * 0.2),
        );
        let frame = recorder.frame(&mut app).unwrap().clone();
        assert_eq!(
            (frame.runs(CloudPass::Voxelize), frame.runs(view_pass)),
            (0, slid),
            "{compositing:?}"
        );
    }
}

#[test]
fn render_layers_hide_clouds_from_cameras_on_other_layers() {
    use bevy::camera::visibility::RenderLayers;
    let (mut app, _) = setup(
        Vec3::ZERO,
        Transform::from_xyz(0.0, 0.0, 4.0).looking_at(Vec3::ZERO, Vec3::Y),
    );
    headless::spawn_light(&mut app, Vec3::NEG_Y, Vec3::ONE);
    // Beside the seen cloud, not above it: a cloud that shadows a seen one is illuminated.
    let hidden = small_cloud(&mut app, 0.9, Vec3::new(-2.5, 0.0, 0.0));
    app.world_mut()
        .entity_mut(hidden)
        .insert(RenderLayers::layer(1));
    small_cloud(&mut app, 0.9, Vec3::new(0.5, 0.0, 0.0));
    common::draw_every_frame(&mut app);
    let mut recorder = FrameRecorder::default();
    let mut draws = 0;
    for _ in 0..4 {
        draws = recorder.frame(&mut app).unwrap().runs(CloudPass::Draw);
    }
    assert_eq!(
        draws, 1,
        "the camera on layer 0 draws only the layer-0 cloud"
    );
    assert_eq!(
        recorder.total(CloudPass::Voxelize),
        1,
        "the unseen cloud does no work"
    );
}

#[test]
fn an_orthographic_camera_shows_no_clouds_and_a_perspective_one_beside_it_does() {
    let background = Vec3::new(0.25, 0.5, 1.0);
    let eye = Transform::from_xyz(0.0, 0.0, 5.0).looking_at(Vec3::ZERO, Vec3::Y);
    // Pixels of `image` other than the background, asserting that every one is finite.
    let cloud_pixels = |image: &bevy_particle_clouds::image_io::LinearImage| {
        let finite = |p: &[f32; 4]| p.iter().all(|c| c.is_finite());
        assert!(image.pixels.iter().all(finite), "a pixel is not finite");
        let cloud = |p: &&[f32; 4]| !close(**p, background, 1e-3);
        image.pixels.iter().filter(cloud).count()
    };
    let run = |with_perspective: bool| {
        let (mut app, orthographic) = setup(background, eye);
        common::draw_every_frame(&mut app);
        // 4 m across the view's height: the cloud (about 2.6 m wide) fills its middle.
        let projection = Projection::Orthographic(OrthographicProjection {
            scaling_mode: bevy::camera::ScalingMode::FixedVertical {
                viewport_height: 4.0,
            },
            ..OrthographicProjection::default_3d()
        });
        app.world_mut()
            .entity_mut(orthographic.camera)
            .insert(projection);
        let perspective = with_perspective.then(|| {
            let image = headless::float_target(&mut app, W, H);
            headless::spawn_linear_camera(&mut app, image.clone(), eye, 40.0, background);
            image
        });
        headless::spawn_light(&mut app, Vec3::new(0.0, -1.0, -0.3), Vec3::splat(2.0));
        small_cloud(&mut app, 0.9, Vec3::ZERO);
        let mut recorder = FrameRecorder::default();
        let mut draws = 0;
        for _ in 0..4 {
            draws = recorder.frame(&mut app).unwrap().runs(CloudPass::Draw);
        }
        let shown = headless::capture(&mut app, &mut recorder, &orthographic.image).unwrap();
        let beside = perspective.map(|image| {
            cloud_pixels(&headless::capture(&mut app, &mut recorder, &image).unwrap())
        });
        let voxelized = recorder.total(CloudPass::Voxelize);
        (draws, cloud_pixels(&shown), beside, voxelized)
    };
    let (draws, changed, _, voxelized) = run(false);
    assert_eq!(draws, 0, "the orthographic camera draws no cloud");
    assert_eq!(changed, 0, "{changed} pixels differ from the background");
    assert_eq!(voxelized, 0, "a cloud no camera can draw does no work");
    let (draws, changed, beside, voxelized) = run(true);
    assert_eq!(draws, 1, "the perspective camera draws the cloud");
    assert_eq!(
        changed, 0,
        "beside it, the orthographic view stays background"
    );
    let beside = beside.unwrap();
    assert!(
        beside > 100,
        "the perspective view shows the cloud on {beside} pixels"
    );
    assert_eq!(
        voxelized, 1,
        "the cloud is illuminated for the perspective view"
    );
}

#[test]
fn particles_made_invalid_later_are_refused_on_change() {
    let (mut app, mut target) = setup(
        Vec3::ZERO,
        Transform::from_xyz(0.0, 0.0, 4.0).looking_at(Vec3::ZERO, Vec3::Y),
    );
    headless::spawn_light(&mut app, Vec3::NEG_Y, Vec3::ONE);
    let cloud = small_cloud(&mut app, 0.9, Vec3::ZERO);
    target.drawable_clouds = 1;
    common::draw_every_frame(&mut app);
    let mut recorder = FrameRecorder::default();
    headless::render_until_steady(&mut app, &mut recorder, target.drawable_clouds, 20).unwrap();
    edit_particles(&mut app, cloud, |p| p[3].radius = -1.0);
    for _ in 0..2 {
        assert_eq!(
            recorder.frame(&mut app).unwrap().runs(CloudPass::Draw),
            0,
            "the now invalid cloud is not drawn"
        );
    }
    edit_particles(&mut app, cloud, |p| p[3].radius = 0.3);
    let mut draws = 0;
    for _ in 0..3 {
        draws = recorder.frame(&mut app).unwrap().runs(CloudPass::Draw);
    }
    assert_eq!(draws, 1, "valid again, drawn again");
}
