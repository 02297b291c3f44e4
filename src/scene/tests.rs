use super::*;
use crate::particle_files::{write_csv, write_ply_ascii, write_ply_binary};
use crate::settings::ScatterStencil;

/// The example of docs/scene-format.md (its first RON block), read from the document itself,
/// so that the example users copy is the one tested.
fn example() -> &'static str {
    let doc = include_str!("../../docs/scene-format.md");
    let start = doc.find("```ron\n").expect("a RON block") + "```ron\n".len();
    &doc[start..start + doc[start..].find("```").expect("its end")]
}

/// The example with every optional field left out.
const MINIMAL: &str = r#"(
    camera: (position: (0.0, 0.6, 6.0), look_at: (0.0, 0.0, 0.0), vertical_fov_degrees: 38.0, width: 160, height: 120),
    lights: [(direction: (-0.5, -0.8, -0.35), irradiance: (1.0, 0.97, 0.9))],
    clouds: [(medium: (extinction: 10, albedo: 1), particles: Inline([]))],
)"#;

fn here() -> &'static Path {
    Path::new(".")
}

fn tmp_dir(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("bpc_scene_{}_{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

fn example_file() -> SceneFile {
    ron::from_str(example()).unwrap()
}

/// The clouds' ground is the top face of the widest lit cuboid: unlit objects and spheres
/// are not grounds.
#[test]
fn the_widest_lit_cuboid_is_the_clouds_ground() {
    let mut scene = Scene::from_ron_str(MINIMAL, here()).unwrap();
    assert_eq!(scene.cloud_ground(), None);
    let object = |shape, y: f32, reflectance: Vec3| SceneObject {
        shape,
        translation: Vec3::new(3.0, y, -1.0),
        color: Vec3::ZERO,
        reflectance,
    };
    let lit = Vec3::new(0.3, 0.35, 0.25);
    scene.objects = vec![
        object(
            ObjectShape::Cuboid(Vec3::new(100.0, 1.0, 100.0)),
            5.0,
            Vec3::ZERO,
        ),
        object(ObjectShape::Sphere(50.0), 0.0, lit),
        object(
            ObjectShape::Cuboid(Vec3::new(2.0, 4.0, 2.0)),
            0.0,
            Vec3::ONE,
        ),
        object(ObjectShape::Cuboid(Vec3::new(30.0, 1.0, 30.0)), -0.5, lit),
    ];
    let ground = scene.cloud_ground().expect("a ground");
    assert_eq!((ground.height, ground.reflectance), (0.0, lit));
}

#[test]
fn fog_is_read_with_its_defaults_and_checked() {
    use crate::fog::Falloff;
    let with_fog = |fog: &str| {
        MINIMAL.replacen(
            "    clouds: [",
            &format!("    fog: {fog},\n    clouds: ["),
            1,
        )
    };
    let scene = Scene::from_ron_str(
        &with_fog("(color: (0.2, 0.3, 0.4), falloff: Exponential(density: 0.1))"),
        here(),
    )
    .unwrap();
    let fog = scene.fog.unwrap();
    assert_eq!(fog.falloff, Falloff::Exponential { density: 0.1 });
    assert_eq!((fog.alpha, fog.directional_light_exponent), (1.0, 8.0));
    assert_eq!(fog.directional_light_color, Vec3::ZERO);
    let minimal = Scene::from_ron_str(MINIMAL, here()).unwrap();
    assert_eq!(minimal.fog, None);
    assert_eq!(minimal.shadow_map_resolution, DEFAULT_SHADOW_MAP_RESOLUTION);
    let with_maps = |n: u32| {
        MINIMAL.replacen(
            "    clouds: [",
            &format!("    shadow_map_resolution: {n},\n    clouds: ["),
            1,
        )
    };
    assert_eq!(
        Scene::from_ron_str(&with_maps(96), here())
            .unwrap()
            .shadow_map_resolution,
        96
    );
    assert_eq!(
        Scene::from_ron_str(&with_maps(8), here())
            .unwrap_err()
            .to_string(),
        "shadow_map_resolution is 8; allowed: 16..=2048"
    );
    let e = Scene::from_ron_str(
        &with_fog("(color: (0.2, 0.3, 0.4), falloff: Linear(start: 10, end: 2))"),
        here(),
    )
    .unwrap_err()
    .to_string();
    assert_eq!(
        e,
        "fog.falloff is Linear(start: 10, end: 2); start and end must be finite, start < end"
    );
    let e = Scene::from_ron_str(
        &with_fog("(color: (0.2, 0.3, 0.4), falloff: Exponential(density: 0.1), density: 2)"),
        here(),
    )
    .unwrap_err()
    .to_string();
    assert!(e.contains("density"), "{e}");
}

#[test]
fn settings_are_set_from_assignments_and_checked() {
    let mut settings = CloudQualitySettings::default();
    apply_setting(&mut settings, "volume_resolution=64").unwrap();
    apply_setting(&mut settings, "compositing = Sorted").unwrap();
    apply_setting(&mut settings, "draw_method=Compute").unwrap();
    assert_eq!(settings.volume_resolution, 64);
    assert_eq!(settings.compositing, crate::Compositing::Sorted);
    assert_eq!(settings.draw_method, crate::DrawMethod::Compute);
    let e = apply_setting(&mut settings, "draw_method=Tiled").unwrap_err();
    assert!(matches!(e, SceneError::Parse { .. }), "{e}");
    assert!(e.to_string().contains("Raster"), "{e}");
    let e = apply_setting(&mut settings, "chord_segments=99").unwrap_err();
    assert_eq!(
        e.to_string(),
        "settings.chord_segments is 99; allowed is 1..=16"
    );
    let e = apply_setting(&mut settings, "resolution=64")
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("--set resolution=64") && e.contains("resolution"),
        "{e}"
    );
    let e = apply_setting(&mut settings, "volume_resolution")
        .unwrap_err()
        .to_string();
    assert!(e.contains("field=value"), "{e}");
    let e = apply_setting(&mut settings, "volume_resolution=abc").unwrap_err();
    assert!(matches!(e, SceneError::Parse { .. }), "{e}");
}

#[test]
fn example_parses_with_its_values() {
    let s = Scene::from_ron_str(example(), here()).unwrap();
    assert_eq!(s.camera.position, Vec3::new(0.0, 0.6, 6.0));
    assert_eq!(s.camera.look_at, Vec3::ZERO);
    assert_eq!(s.camera.up, Vec3::Y);
    assert_eq!(s.camera.vertical_fov_degrees, 38.0);
    assert_eq!((s.camera.width, s.camera.height), (160, 120));
    assert_eq!(s.background, Vec3::ZERO);
    assert_eq!(
        s.lights,
        vec![LightSample {
            direction: Vec3::new(-0.5, -0.8, -0.35),
            irradiance: Vec3::new(1.0, 0.97, 0.9)
        }]
    );
    assert_eq!(
        s.clouds,
        vec![ResolvedCloud {
            translation: Vec3::ZERO,
            medium: Medium {
                extinction: 10.0,
                albedo: 0.99,
                ..Default::default()
            },
            particles: vec![
                Particle {
                    position: Vec3::new(0.1, 0.2, 0.3),
                    radius: 0.2,
                    density: 0.8
                },
                Particle {
                    position: Vec3::new(-0.3, 0.0, 0.1),
                    radius: 0.25,
                    density: 1.0
                },
            ],
        }]
    );
    assert_eq!(
        s.objects,
        vec![SceneObject {
            shape: ObjectShape::Cuboid(Vec3::new(0.8, 3.0, 0.3)),
            translation: Vec3::new(0.9, 0.0, 1.8),
            color: Vec3::splat(0.05),
            reflectance: Vec3::ZERO,
        }]
    );
    assert_eq!(
        s.settings,
        CloudQualitySettings {
            volume_resolution: 128,
            scatter_iterations: 16,
            ..Default::default()
        }
    );
    assert_eq!(s.settings.scatter_stencil, ScatterStencil::default());
    s.validate().unwrap();
}

#[test]
fn optional_fields_take_their_defaults() {
    let s = Scene::from_ron_str(MINIMAL, here()).unwrap();
    assert_eq!(s.camera.up, Vec3::Y);
    assert_eq!(s.background, Vec3::ZERO);
    assert!(s.objects.is_empty());
    assert_eq!(s.settings, CloudQualitySettings::default());
    assert_eq!(s.clouds[0].translation, Vec3::ZERO);
    // integer literals are accepted for float fields; an empty cloud is allowed
    assert_eq!(
        s.clouds[0].medium,
        Medium {
            extinction: 10.0,
            albedo: 1.0,
            anisotropy: 0.0,
        }
    );
    assert!(s.clouds[0].particles.is_empty());
    let text = MINIMAL.replace("albedo: 1)", "albedo: 1, anisotropy: 0.7)");
    let s = Scene::from_ron_str(&text, here()).unwrap();
    assert_eq!(s.clouds[0].medium.anisotropy, 0.7);
    // a sphere object and the non-default stencil parse too
    let text = MINIMAL.replace(
            "\n)",
            "objects: [(shape: Sphere(0.5), color: (1, 2, 3))], settings: (scatter_stencil: Paper, forward_scattering: 0.5, compositing: ViewTransmittance))",
        );
    let s = Scene::from_ron_str(&text, here()).unwrap();
    assert_eq!(
        s.objects,
        vec![SceneObject {
            shape: ObjectShape::Sphere(0.5),
            translation: Vec3::ZERO,
            color: Vec3::new(1.0, 2.0, 3.0),
            reflectance: Vec3::ZERO,
        }]
    );
    assert_eq!(s.settings.scatter_stencil, ScatterStencil::Paper);
    assert_eq!(s.settings.forward_scattering, 0.5);
    assert_eq!(
        s.settings.compositing,
        crate::settings::Compositing::ViewTransmittance
    );
    assert_eq!(
        s.settings.volume_resolution,
        CloudQualitySettings::default().volume_resolution
    );
}

type Mutation = fn(&mut SceneFile);

fn cloud0(f: &mut SceneFile) -> &mut SceneCloud {
    &mut f.clouds[0]
}

fn inline(f: &mut SceneFile, cloud: usize) -> &mut Vec<Particle> {
    match &mut f.clouds[cloud].particles {
        ParticleSource::Inline(p) => p,
        _ => unreachable!(),
    }
}

/// Every validation rule: (mutation of the example, the exact expected message).
const RULES: &[(Mutation, &str)] = &[
    (
        |f| f.camera.position.x = f32::NAN,
        "camera.position is (NaN, 0.6, 6); every coordinate must be finite",
    ),
    (
        |f| f.camera.look_at.z = f32::INFINITY,
        "camera.look_at is (0, 0, inf); every coordinate must be finite",
    ),
    (
        |f| f.camera.up.y = f32::NEG_INFINITY,
        "camera.up is (0, -inf, 0); every coordinate must be finite",
    ),
    (
        |f| f.camera.look_at = f.camera.position,
        "camera.look_at is (0, 0.6, 6); it must differ from camera.position (0, 0.6, 6)",
    ),
    (
        |f| f.camera.up = Vec3::ZERO,
        "camera.up is (0, 0, 0); it must not be zero",
    ),
    (
        |f| f.camera.up = Vec3::new(0.0, -0.3, -3.0),
        "camera.up is (0, -0.3, -3); it must not be parallel to the viewing direction look_at - position = (0, -0.6, -6)",
    ),
    (
        |f| f.camera.vertical_fov_degrees = 190.0,
        "camera.vertical_fov_degrees is 190; it must lie in (0, 180)",
    ),
    (
        |f| f.camera.vertical_fov_degrees = 180.0,
        "camera.vertical_fov_degrees is 180; it must lie in (0, 180)",
    ),
    (
        |f| f.camera.vertical_fov_degrees = 0.0,
        "camera.vertical_fov_degrees is 0; it must lie in (0, 180)",
    ),
    (
        |f| f.camera.vertical_fov_degrees = f32::NAN,
        "camera.vertical_fov_degrees is NaN; it must lie in (0, 180)",
    ),
    (
        |f| f.camera.width = 0,
        "camera.width is 0; it must be > 0 and <= 16384",
    ),
    (
        |f| f.camera.height = 16385,
        "camera.height is 16385; it must be > 0 and <= 16384",
    ),
    (
        |f| f.background = Vec3::new(-1.0, 0.0, 0.0),
        "background is (-1, 0, 0); every component must be finite and >= 0",
    ),
    (
        |f| f.background.z = f32::NAN,
        "background is (0, 0, NaN); every component must be finite and >= 0",
    ),
    (
        |f| f.lights[0].direction = Vec3::ZERO,
        "lights[0].direction is (0, 0, 0); it must not be zero",
    ),
    (
        |f| f.lights[0].direction.x = f32::NAN,
        "lights[0].direction is (NaN, -0.8, -0.35); every coordinate must be finite",
    ),
    (
        |f| f.lights[0].irradiance.y = -0.5,
        "lights[0].irradiance is (1, -0.5, 0.9); every component must be finite and >= 0",
    ),
    (
        |f| {
            f.lights.push(LightSample {
                direction: Vec3::ZERO,
                irradiance: Vec3::ONE,
            })
        },
        "lights[1].direction is (0, 0, 0); it must not be zero",
    ),
    (
        |f| cloud0(f).translation.y = f32::INFINITY,
        "clouds[0].translation is (0, inf, 0); every coordinate must be finite",
    ),
    (
        |f| cloud0(f).medium.albedo = 1.5,
        "clouds[0].medium.albedo is 1.5; it must lie in [0, 1]",
    ),
    (
        |f| cloud0(f).medium.albedo = -0.1,
        "clouds[0].medium.albedo is -0.1; it must lie in [0, 1]",
    ),
    (
        |f| cloud0(f).medium.albedo = f32::NAN,
        "clouds[0].medium.albedo is NaN; it must lie in [0, 1]",
    ),
    (
        |f| cloud0(f).medium.anisotropy = 1.0,
        "clouds[0].medium.anisotropy is 1; it must lie in (-1, 1)",
    ),
    (
        |f| cloud0(f).medium.anisotropy = f32::NAN,
        "clouds[0].medium.anisotropy is NaN; it must lie in (-1, 1)",
    ),
    (
        |f| cloud0(f).medium.extinction = -1.0,
        "clouds[0].medium.extinction is -1; it must be finite and >= 0",
    ),
    (
        |f| cloud0(f).medium.extinction = f32::INFINITY,
        "clouds[0].medium.extinction is inf; it must be finite and >= 0",
    ),
    (
        |f| inline(f, 0)[1].radius = -0.2,
        "clouds[0].particles[1].radius is -0.2; it must be > 0 and at most 1e15 m",
    ),
    (
        |f| inline(f, 0)[0].radius = 0.0,
        "clouds[0].particles[0].radius is 0; it must be > 0 and at most 1e15 m",
    ),
    (
        |f| inline(f, 0)[1].radius = f32::NAN,
        "clouds[0].particles[1].radius is NaN; it must be > 0 and at most 1e15 m",
    ),
    (
        |f| inline(f, 0)[1].density = -1.0,
        "clouds[0].particles[1].density is -1; it must be finite and >= 0",
    ),
    (
        |f| inline(f, 0)[0].density = f32::INFINITY,
        "clouds[0].particles[0].density is inf; it must be finite and >= 0",
    ),
    (
        |f| inline(f, 0)[1].position.z = f32::NAN,
        "clouds[0].particles[1].position is (-0.3, 0, NaN); every coordinate must be finite and within ±1e15 m",
    ),
    (
        |f| inline(f, 0)[0].position.x = 3e38,
        "clouds[0].particles[0].position is (300000000000000000000000000000000000000, 0.2, 0.3); every coordinate must be finite and within ±1e15 m",
    ),
    (
        |f| inline(f, 0)[1].radius = 2e15,
        "clouds[0].particles[1].radius is 2000000000000000; it must be > 0 and at most 1e15 m",
    ),
    (
        |f| {
            let mut c = f.clouds[0].clone();
            c.medium.albedo = 2.0;
            f.clouds.push(c);
        },
        "clouds[1].medium.albedo is 2; it must lie in [0, 1]",
    ),
    (
        |f| {
            let mut c = f.clouds[0].clone();
            c.particles = ParticleSource::Inline(vec![Particle::default(); 4]);
            f.clouds.push(c);
            inline(f, 1)[3].radius = 1.0;
        },
        "clouds[1].particles[0].radius is 0; it must be > 0 and at most 1e15 m",
    ),
    (
        |f| f.objects[0].shape = ObjectShape::Cuboid(Vec3::new(0.8, 0.0, 0.3)),
        "objects[0].shape is Cuboid((0.8, 0, 0.3)); every extent must be finite and > 0",
    ),
    (
        |f| f.objects[0].shape = ObjectShape::Cuboid(Vec3::new(0.8, f32::INFINITY, 0.3)),
        "objects[0].shape is Cuboid((0.8, inf, 0.3)); every extent must be finite and > 0",
    ),
    (
        |f| f.objects[0].shape = ObjectShape::Sphere(-1.0),
        "objects[0].shape is Sphere(-1); the radius must be finite and > 0",
    ),
    (
        |f| f.objects[0].shape = ObjectShape::Sphere(f32::NAN),
        "objects[0].shape is Sphere(NaN); the radius must be finite and > 0",
    ),
    (
        |f| f.objects[0].translation.x = f32::NAN,
        "objects[0].translation is (NaN, 0, 1.8); every coordinate must be finite",
    ),
    (
        |f| f.objects[0].color.x = -0.05,
        "objects[0].color is (-0.05, 0.05, 0.05); every component must be finite and >= 0",
    ),
    (
        |f| f.objects[0].reflectance = Vec3::new(0.5, 1.2, 0.5),
        "objects[0].reflectance is (0.5, 1.2, 0.5); every component must lie in [0, 1]",
    ),
    (
        |f| f.objects[0].reflectance.z = f32::NAN,
        "objects[0].reflectance is (0, 0, NaN); every component must lie in [0, 1]",
    ),
    (
        |f| f.settings.volume_resolution = 300,
        "settings.volume_resolution is 300; allowed is 4..=256",
    ),
    (
        |f| f.settings.volume_resolution = 3,
        "settings.volume_resolution is 3; allowed is 4..=256",
    ),
    (
        |f| f.settings.scatter_iterations = 5000,
        "settings.scatter_iterations is 5000; allowed is 0..=4096",
    ),
    (
        |f| f.settings.warm_scatter_iterations = 1,
        "settings.warm_scatter_iterations is 1; allowed is 0 (off) or 2..=4096",
    ),
    (
        |f| f.settings.scatter_coarse_cycles = 65,
        "settings.scatter_coarse_cycles is 65; allowed is 0..=64",
    ),
    (
        |f| f.settings.forward_scattering = 2.0,
        "settings.forward_scattering is 2; it must lie in [0, 1]",
    ),
    (
        |f| f.settings.forward_scattering = f32::NAN,
        "settings.forward_scattering is NaN; it must lie in [0, 1]",
    ),
    (
        |f| f.settings.cloud_target_scale = 0.1,
        "settings.cloud_target_scale is 0.1; it must lie in [0.125, 1]",
    ),
    (
        |f| f.settings.cloud_target_scale = f32::NAN,
        "settings.cloud_target_scale is NaN; it must lie in [0.125, 1]",
    ),
];

#[test]
fn every_rule_refuses_with_path_value_and_allowed_range() {
    for (i, (mutate, expected)) in RULES.iter().enumerate() {
        let mut file = example_file();
        mutate(&mut file);
        let message = match Scene::from_scene_file(file.clone(), here()) {
            Ok(_) => panic!("rule {i} ({expected}) was not enforced"),
            Err(e) => e.to_string(),
        };
        assert_eq!(message, *expected, "rule {i}");
        // `Scene::validate` applies the same rules to a scene built in code.
        let mut scene = Scene::from_ron_str(example(), here()).unwrap();
        let mut file2 = example_file();
        mutate(&mut file2);
        scene.camera = file2.camera;
        scene.background = file2.background;
        scene.lights = file2.lights;
        scene.objects = file2.objects;
        scene.settings = file2.settings;
        scene.clouds = file2
            .clouds
            .into_iter()
            .map(|c| ResolvedCloud {
                translation: c.translation,
                medium: c.medium,
                particles: match c.particles {
                    ParticleSource::Inline(p) => p,
                    _ => unreachable!(),
                },
            })
            .collect();
        assert_eq!(
            scene.validate().unwrap_err().to_string(),
            *expected,
            "validate, rule {i}"
        );
    }
}

#[test]
fn non_finite_values_written_in_ron_are_refused() {
    let text = example().replace("albedo: 0.99", "albedo: NaN");
    let e = Scene::from_ron_str(&text, here()).unwrap_err().to_string();
    assert_eq!(e, "clouds[0].medium.albedo is NaN; it must lie in [0, 1]");
    let text = example().replace("radius: 0.25", "radius: -inf");
    let e = Scene::from_ron_str(&text, here()).unwrap_err().to_string();
    assert_eq!(
        e,
        "clouds[0].particles[1].radius is -inf; it must be > 0 and at most 1e15 m"
    );
}

#[test]
fn unknown_fields_are_refused_at_every_level() {
    let cases = [
        (
            "    settings:",
            "    bogus_top: 1,\n    settings:",
            "bogus_top",
        ),
        ("        width: 160,", "        width: 160, fov: 3,", "fov"),
        (
            "irradiance: (1.0, 0.97, 0.9)",
            "irradiance: (1.0, 0.97, 0.9), intensity: 2.0",
            "intensity",
        ),
        (
            "            translation: (0.0, 0.0, 0.0),",
            "            translation: (0.0, 0.0, 0.0), rotation: 1,",
            "rotation",
        ),
        ("albedo: 0.99", "albedo: 0.99, phase_g: 0.5", "phase_g"),
        (
            "radius: 0.2, density: 0.8",
            "radius: 0.2, density: 0.8, colour: 1",
            "colour",
        ),
        (
            "color: (0.05, 0.05, 0.05)",
            "color: (0.05, 0.05, 0.05), colour: 1",
            "colour",
        ),
        (
            "scatter_iterations: 16",
            "scatter_iterations: 16, volume_res: 3",
            "volume_res",
        ),
    ];
    for (from, to, field) in cases {
        assert!(example().contains(from), "{from}");
        let text = example().replacen(from, to, 1);
        let e = Scene::from_ron_str(&text, here()).unwrap_err();
        assert!(matches!(e, SceneError::Parse { .. }), "{e:?}");
        let message = e.to_string();
        assert!(
            message.contains(&format!("Unexpected field named `{field}`")),
            "{message}"
        );
        // origin:line:col
        assert!(message.starts_with("scene:"), "{message}");
        let SceneError::Parse { error, .. } = e else {
            unreachable!()
        };
        assert!(error.span.start.line > 1, "{message}");
    }
}

#[test]
fn unknown_variants_missing_fields_and_syntax_errors_are_parse_errors() {
    let e = Scene::from_ron_str(&example().replace("Inline(", "Obj("), here())
        .unwrap_err()
        .to_string();
    assert!(e.contains("`Obj`") && e.contains("`Inline`"), "{e}");
    let e = Scene::from_ron_str(&example().replace("Cuboid(", "Box("), here())
        .unwrap_err()
        .to_string();
    assert!(e.contains("`Box`"), "{e}");
    let e = Scene::from_ron_str(&example().replace("        height: 120,\n", ""), here())
        .unwrap_err()
        .to_string();
    assert!(e.contains("`height`"), "{e}");
    let e =
        Scene::from_ron_str(&example().replace("width: 160", "width: -160"), here()).unwrap_err();
    let SceneError::Parse { error, .. } = &e else {
        panic!("{e:?}")
    };
    assert_eq!(error.span.start.line, 7, "{e}");
    let e = Scene::from_ron_str(
        &example().replace("look_at: (0.0, 0.0, 0.0),", "look_at: (0.0, 0.0 0.0),"),
        here(),
    )
    .unwrap_err()
    .to_string();
    assert!(e.starts_with("scene:4:"), "{e}");
}

fn sample_particles() -> Vec<Particle> {
    vec![
        Particle {
            position: Vec3::new(0.1, 0.2, 0.3),
            radius: 0.2,
            density: 0.8,
        },
        Particle {
            position: Vec3::new(-0.3, 0.0, 0.1),
            radius: 0.25,
            density: 1.0,
        },
        Particle {
            position: Vec3::new(0.7, -0.25, 1.0 / 3.0),
            radius: 0.125,
            density: 0.0,
        },
    ]
}

fn scene_with_sources(sources: &str) -> String {
    example().replacen(
            "            translation: (0.0, 0.0, 0.0),  // optional, default origin\n",
            "",
            1,
        )
        .replace(
            "particles: Inline([\n                (position: (0.1, 0.2, 0.3), radius: 0.2, density: 0.8),\n                (position: (-0.3, 0.0, 0.1), radius: 0.25, density: 1.0),\n            ]),",
            sources,
        )
}

#[test]
fn particle_files_load_relative_to_the_scene_file() {
    let dir = tmp_dir("files");
    std::fs::create_dir_all(dir.join("data")).unwrap();
    write_ply_binary(&dir.join("data/bin.ply"), &sample_particles()).unwrap();
    write_ply_ascii(&dir.join("ascii.ply"), &sample_particles()[1..]).unwrap();
    write_csv(&dir.join("data/c.csv"), &sample_particles()[..2]).unwrap();
    let text = scene_with_sources("particles: Ply(\"data/bin.ply\"),")
            .replace(
                "    ],\n    objects",
                "    (medium: (extinction: 1, albedo: 0.5), particles: Ply(\"ascii.ply\")),\n    \
                 (medium: (extinction: 1, albedo: 0.5), particles: Csv(\"data/c.csv\")),\n    ],\n    objects",
            );
    let scene_path = dir.join("scene.ron");
    std::fs::write(&scene_path, &text).unwrap();
    let s = Scene::load(&scene_path).unwrap();
    assert_eq!(s.clouds.len(), 3);
    assert_eq!(s.clouds[0].particles, sample_particles());
    assert_eq!(s.clouds[1].particles, sample_particles()[1..].to_vec());
    assert_eq!(s.clouds[2].particles, sample_particles()[..2].to_vec());
    // from_ron_str resolves against its base_dir
    let s2 = Scene::from_ron_str(&text, &dir).unwrap();
    assert_eq!(s, s2);
}

#[test]
fn missing_particle_file_names_field_written_and_resolved_path() {
    let dir = tmp_dir("missing");
    let text = scene_with_sources("particles: Ply(\"missing.ply\"),");
    let e = Scene::from_ron_str(&text, &dir).unwrap_err();
    let message = e.to_string();
    let resolved = std::path::absolute(dir.join("missing.ply")).unwrap();
    assert!(
        message.starts_with(&format!(
            "clouds[0].particles: cannot read 'missing.ply' (resolved to {}): ",
            resolved.display()
        )),
        "{message}"
    );
    assert!(
        matches!(&e, SceneError::ParticleFile { error, .. } if matches!(**error, ParticleFileError::Io { .. }))
    );
    let e = Scene::from_ron_str(&scene_with_sources("particles: Csv(\"\"),"), &dir)
        .unwrap_err()
        .to_string();
    assert_eq!(
        e,
        "clouds[0].particles is \"\"; the file name must not be empty"
    );
}

#[test]
fn particle_file_errors_name_line_numbers() {
    let dir = tmp_dir("bad_files");
    std::fs::write(
        dir.join("bad.csv"),
        "x,y,z,radius,density\n0,0,0,1,1\n\n0,0,0,one,1\n",
    )
    .unwrap();
    let e = Scene::from_ron_str(&scene_with_sources("particles: Csv(\"bad.csv\"),"), &dir)
        .unwrap_err()
        .to_string();
    assert!(
        e.starts_with("clouds[0].particles: cannot read 'bad.csv'"),
        "{e}"
    );
    assert!(
        e.ends_with("line 4: column `radius` is not a number"),
        "{e}"
    );
    std::fs::write(
            dir.join("bad.ply"),
            "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\n\
             property float radius\nproperty float density\nend_header\n0 0 0 1 1\n0 0 0 1 x\n",
        )
        .unwrap();
    let e = Scene::from_ron_str(&scene_with_sources("particles: Ply(\"bad.ply\"),"), &dir)
        .unwrap_err()
        .to_string();
    assert!(e.contains("line 11") && e.contains("`density`"), "{e}");
}

#[test]
fn invalid_particle_in_a_file_names_the_path_and_the_file() {
    let dir = tmp_dir("invalid_in_file");
    let mut p = sample_particles();
    p[2].density = -3.0;
    write_csv(&dir.join("p.csv"), &p).unwrap();
    let e = Scene::from_ron_str(&scene_with_sources("particles: Csv(\"p.csv\"),"), &dir)
        .unwrap_err()
        .to_string();
    assert!(e.starts_with("clouds[0].particles[2].density is -3; it must be finite and >= 0 (particle file 'p.csv'"), "{e}");
}

#[test]
fn scene_file_errors_name_the_path() {
    let dir = tmp_dir("scene_file");
    let path = dir.join("nope.ron");
    let e = Scene::load(&path).unwrap_err().to_string();
    assert!(
        e.starts_with(&format!("cannot read scene file '{}': ", path.display())),
        "{e}"
    );
    std::fs::write(&path, example().replace("width: 160", "widht: 160")).unwrap();
    let e = Scene::load(&path).unwrap_err().to_string();
    assert!(
        e.starts_with(&format!("{}:7:", path.display())) && e.contains("`widht`"),
        "{e}"
    );
}
