//! The `render` example as a user runs it: scene files in, images and statistics out, invalid
//! scenes refused with one clear message and a non-zero exit.

use std::{
    path::{Path, PathBuf},
    process::{Command, Output},
};

use bevy_particle_clouds::image_io::{read_exr, read_exr_with_metadata};

/// The example's binary, built by `cargo test` beside this test's binary.
fn render_binary() -> PathBuf {
    let exe = std::env::current_exe().expect("test binary path");
    let dir = exe
        .parent()
        .and_then(Path::parent)
        .expect("target profile directory");
    let binary = dir
        .join("examples")
        .join(format!("render{}", std::env::consts::EXE_SUFFIX));
    assert!(
        binary.exists(),
        "{} is missing: run the tests with `cargo test`",
        binary.display()
    );
    binary
}

/// A scratch directory holding the scene-format example as `scene.ron`: the directory and the
/// scene's path.
fn example_scene(name: &str) -> (PathBuf, PathBuf) {
    let dir = scratch_dir(name);
    let scene = dir.join("scene.ron");
    std::fs::write(&scene, scene_format_example()).unwrap();
    (dir, scene)
}

/// Like [`example_scene`], with the example's lights replaced by `count` grey lights of
/// `irradiance` from one direction.
fn example_with_lights(name: &str, count: usize, irradiance: f32) -> (PathBuf, PathBuf) {
    let dir = scratch_dir(name);
    let scene = dir.join("scene.ron");
    let example = scene_format_example();
    let start = example.find("    lights: [").expect("the example's lights");
    let end = start + example[start..].find("    ],\n").expect("their end") + "    ],\n".len();
    let e = irradiance;
    let light = format!("        (direction: (-0.5, -0.8, -0.35), irradiance: ({e}, {e}, {e})),\n");
    let lights = format!("    lights: [\n{}    ],\n", light.repeat(count));
    std::fs::write(
        &scene,
        format!("{}{lights}{}", &example[..start], &example[end..]),
    )
    .unwrap();
    (dir, scene)
}

fn scratch_dir(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!(
        "bevy_particle_clouds_{name}_{}",
        std::process::id()
    ));
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

fn run(args: &[&str]) -> Output {
    Command::new(render_binary())
        .args(args)
        .output()
        .expect("run the render example")
}

/// The example of docs/scene-format.md (its first RON block), read from the document itself.
fn scene_format_example() -> &'static str {
    let doc = include_str!("../docs/scene-format.md");
    let start = doc.find("```ron\n").expect("a RON block") + "```ron\n".len();
    &doc[start..start + doc[start..].find("```").expect("its end")]
}

#[test]
fn the_scene_format_example_renders_to_exr_png_and_stats() {
    let (dir, scene) = example_scene("example");
    let (exr, png, stats) = (
        dir.join("out.exr"),
        dir.join("out.png"),
        dir.join("stats.json"),
    );
    let out = run(&[
        scene.to_str().unwrap(),
        "--out",
        exr.to_str().unwrap(),
        "--stats",
        stats.to_str().unwrap(),
        "--frames",
        "3",
    ]);
    assert!(
        out.status.success(),
        "render failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        stderr.contains("render: wrote"),
        "progress on stderr: {stderr}"
    );

    let image = read_exr(&exr).unwrap();
    assert_eq!((image.width, image.height), (160, 120));
    assert!(
        image
            .pixels
            .iter()
            .flatten()
            .all(|v| v.is_finite() && *v >= 0.0)
    );
    // The occluder's pixels show its radiance; the cloud is lit somewhere.
    assert!(
        image
            .pixels
            .iter()
            .any(|p| (p[0] - 0.05).abs() < 1e-3 && (p[2] - 0.05).abs() < 1e-3)
    );
    assert!(image.pixels.iter().any(|p| p[0] > 0.02), "the cloud is lit");

    let stats: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&stats).unwrap()).unwrap();
    assert!(stats["adapter"].as_str().is_some_and(|a| !a.is_empty()));
    let frames = stats["frames"].as_array().unwrap();
    assert!(frames.len() >= 3);
    let runs = |frame: &serde_json::Value, pass: &str| frame["passes"][pass].as_u64().unwrap();
    assert_eq!(
        frames.iter().map(|f| runs(f, "voxelize")).sum::<u64>(),
        1,
        "voxelized once"
    );
    let last = frames.last().unwrap();
    for pass in ["voxelize", "shade", "gather", "scatter", "sort"] {
        assert_eq!(
            runs(last, pass),
            0,
            "the last frame of a static scene runs no {pass}"
        );
    }
    let drawn: u64 = frames.iter().map(|f| runs(f, "draw")).sum();
    assert!(drawn >= 1, "the cloud was drawn");
    assert_eq!(
        runs(last, "draw"),
        0,
        "a still view keeps its image (`CloudRedraw`)"
    );
    for frame in frames {
        for (pass, ms) in frame["gpu_ms"].as_object().unwrap() {
            // A kept frame's draw still compares the depth and composites: a time, no run.
            let ran = runs(frame, pass) > 0 || pass == "draw";
            assert!(
                ms.is_null() || (ms.as_f64().unwrap() >= 0.0 && ran),
                "{pass}: {ms}"
            );
        }
    }

    let out = run(&[scene.to_str().unwrap(), "--out", png.to_str().unwrap()]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let png = image::open(&png).unwrap().to_rgba8();
    assert_eq!(png.dimensions(), (160, 120));
}

const INLINE_PARTICLES: &str = "Inline([
                (position: (0.1, 0.2, 0.3), radius: 0.2, density: 0.8),
                (position: (-0.3, 0.0, 0.1), radius: 0.25, density: 1.0),
            ])";

#[test]
fn invalid_scenes_are_refused_with_the_field_and_value() {
    let dir = scratch_dir("invalid");
    let cases = [
        (
            "albedo: 0.99",
            "albedo: 1.5",
            "clouds[0].medium.albedo is 1.5",
        ),
        (
            "radius: 0.2",
            "radius: -0.2",
            "clouds[0].particles[0].radius is -0.2",
        ),
        (
            "direction: (-0.5, -0.8, -0.35)",
            "direction: (0.0, 0.0, 0.0)",
            "lights[0].direction is (0, 0, 0)",
        ),
        ("width: 160", "width: 0", "camera.width is 0"),
        ("width: 160", "width: 160, colour: 1", "colour"),
        (
            "volume_resolution: 128",
            "volume_resolution: 100000",
            "settings.volume_resolution is 100000",
        ),
        (
            INLINE_PARTICLES,
            "Ply(\"missing.ply\")",
            "clouds[0].particles: cannot read 'missing.ply'",
        ),
    ];
    for (i, (from, to, expected)) in cases.iter().enumerate() {
        assert!(scene_format_example().contains(from), "case {i}");
        let text = scene_format_example().replacen(from, to, 1);
        let scene = dir.join(format!("bad{i}.ron"));
        std::fs::write(&scene, text).unwrap();
        let out_path = dir.join(format!("bad{i}.exr"));
        let out = run(&[scene.to_str().unwrap(), "--out", out_path.to_str().unwrap()]);
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "case {i} must fail: {stderr}");
        assert!(
            stderr.contains(expected),
            "case {i}: expected {expected:?} in {stderr}"
        );
        assert!(!stderr.contains("panicked"), "case {i} panicked: {stderr}");
        assert!(!out_path.exists(), "case {i} wrote an image");
    }
    let out = run(&["/nonexistent/scene.ron", "--out", "x.exr"]);
    assert_eq!(out.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&out.stderr).contains("/nonexistent/scene.ron"));
}

#[test]
fn the_reference_path_tracer_renders_a_scene_file() {
    let dir = scratch_dir("reference");
    let scene = dir.join("scene.ron");
    let small = scene_format_example()
        .replacen("width: 160", "width: 40", 1)
        .replacen("height: 120", "height: 30", 1);
    std::fs::write(&scene, small).unwrap();
    let exr = dir.join("ref.exr");
    let out = run(&[
        scene.to_str().unwrap(),
        "--reference",
        "--spp",
        "4",
        "--seed",
        "3",
        "--out",
        exr.to_str().unwrap(),
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(
        String::from_utf8_lossy(&out.stderr).contains("path tracer"),
        "progress on stderr"
    );
    let image = read_exr(&exr).unwrap();
    assert_eq!((image.width, image.height), (40, 30));
    assert!(
        image
            .pixels
            .iter()
            .flatten()
            .all(|v| v.is_finite() && *v >= 0.0)
    );
    // The occluder covers pixels with exactly its radiance; the cloud scatters light somewhere.
    assert!(image.pixels.iter().any(|p| (p[0] - 0.05).abs() < 1e-6));
    assert!(image.pixels.iter().any(|p| p[0] > 0.02));
}

#[test]
fn the_command_line_is_checked_and_documented() {
    let help = run(&["--help"]);
    assert_eq!(help.status.code(), Some(0));
    let text = String::from_utf8_lossy(&help.stdout);
    for flag in [
        "--out",
        "--stats",
        "--frames",
        "--reference",
        "--spp",
        "--seed",
        "--size",
        "--set",
    ] {
        assert!(text.contains(flag), "--help lists {flag}: {text}");
    }
    let refused = [
        (vec!["--bogus"], "--bogus"),
        (vec!["--spp", "4", "--out", "x.exr"], "--reference"),
        (vec!["--seed", "4", "--out", "x.exr"], "--reference"),
        (vec!["--size", "0x10", "--out", "x.exr"], "--size is 0x10"),
        (
            vec!["--set", "chord_segments=99", "--out", "x.png"],
            "settings.chord_segments is 99",
        ),
        (vec!["--set", "bogus=1", "--out", "x.png"], "bogus"),
    ];
    for (args, expected) in refused {
        let out = run(&args);
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{args:?} must fail: {stderr}");
        assert!(
            stderr.contains(expected),
            "{args:?}: expected {expected:?} in {stderr}"
        );
    }
}

/// Light volumes past any adapter's storage binding (200 lights of 255³ floats: 13 GB) at a
/// `light_supersampling` the scene sets (3; the default's is lowered to fit, as in a game) are
/// refused before anything renders, naming the field, its value and the largest that fits.
#[test]
fn volumes_past_the_adapters_storage_binding_are_refused_with_what_fits() {
    let (dir, scene) = example_with_lights("too_many_lights", 200, 0.01);
    let out = run(&[
        scene.to_str().unwrap(),
        "--out",
        dir.join("x.png").to_str().unwrap(),
        "--set",
        "volume_resolution=85",
        "--set",
        "light_supersampling=3",
    ]);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{stderr}");
    for expected in [
        "settings.volume_resolution is 85 (light volumes of 255³ for 200 lights)",
        "allows at most",
        "its storage buffers hold",
    ] {
        assert!(
            stderr.contains(expected),
            "expected {expected:?} in {stderr}"
        );
    }
    assert!(!dir.join("x.png").exists(), "nothing is written");
}

/// The default `light_supersampling` is "4, or the largest fine grid the adapter binds": five
/// lights at 48³ × 4 (5 × 192³ floats, 142 MB) pass lavapipe's 128 MiB storage binding, so the
/// scene renders on a fine grid of 188³ (5 × 188³ floats, 132.9 MB), and stderr says so; an
/// adapter with a larger binding renders it at 192³.
#[test]
fn the_default_supersampling_is_lowered_to_what_the_adapter_binds() {
    let (dir, scene) = example_with_lights("five_lights", 5, 0.2);
    let exr = dir.join("x.exr");
    let out = run(&[
        scene.to_str().unwrap(),
        "--out",
        exr.to_str().unwrap(),
        "--size",
        "40x30",
        "--set",
        "volume_resolution=48",
    ]);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{stderr}");
    let (image, metadata) = read_exr_with_metadata(&exr).unwrap();
    assert!(image.pixels.iter().any(|p| p[0] > 0.02), "the cloud is lit");
    let adapter = metadata
        .get("adapter")
        .expect("the adapter in the metadata");
    if adapter.contains("llvmpipe") {
        assert!(
            stderr.contains(
                "light volumes of 192³ for 5 lights exceed this adapter's storage buffers \
                 (134217728 bytes); the default light_supersampling's fine grid is lowered to \
                 188³"
            ),
            "{stderr}"
        );
    }
}

#[test]
fn size_and_settings_overrides_reach_the_image_and_its_metadata() {
    let (dir, scene) = example_scene("overrides");
    let exr = dir.join("small.exr");
    let out = run(&[
        scene.to_str().unwrap(),
        "--out",
        exr.to_str().unwrap(),
        "--size",
        "48x32",
        "--set",
        "volume_resolution=16",
        "--set",
        "compositing=Sorted",
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let (image, metadata) = read_exr_with_metadata(&exr).unwrap();
    assert_eq!((image.width, image.height), (48, 32));
    let settings = metadata.get("settings").expect("settings in the metadata");
    assert!(
        settings.contains("volume_resolution: 16") && settings.contains("Sorted"),
        "{settings}"
    );
    assert!(metadata.get("adapter").is_some_and(|a| !a.is_empty()));
    assert!(
        metadata
            .get("software")
            .is_some_and(|s| s.starts_with("bevy_particle_clouds"))
    );
    assert!(
        metadata
            .get("camera")
            .is_some_and(|c| c.contains("width: 48"))
    );
    assert!(metadata.get("render_time_s").is_some());
}

/// `--set draw_method=Raster` (a scene file's `settings.draw_method`) renders the default's
/// image: the clouds' billboards rasterised in the `Transparent3d` phase instead of their pixels
/// summed by a compute shader, over the same objects.
#[test]
fn a_rasterised_scene_renders_the_computed_image() {
    let (dir, scene) = example_scene("compute");
    let render = |name: &str, extra: &[&str]| {
        let exr = dir.join(name);
        let mut args = vec![
            scene.to_str().unwrap(),
            "--out",
            exr.to_str().unwrap(),
            "--size",
            "80x60",
            "--set",
            "volume_resolution=32",
        ];
        args.extend_from_slice(extra);
        let out = run(&args);
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        read_exr_with_metadata(&exr).unwrap()
    };
    let (computed, metadata) = render("computed.exr", &[]);
    let settings = metadata.get("settings").expect("settings in the metadata");
    assert!(settings.contains("Compute"), "{settings}");
    let (raster, metadata) = render("raster.exr", &["--set", "draw_method=Raster"]);
    let settings = metadata.get("settings").expect("settings in the metadata");
    assert!(settings.contains("Raster"), "{settings}");
    let peak = raster
        .pixels
        .iter()
        .flat_map(|p| &p[..3])
        .fold(0f32, |m, v| m.max(*v));
    let worst = raster
        .pixels
        .iter()
        .zip(&computed.pixels)
        .flat_map(|(r, c)| (0..3).map(move |i| (r[i] - c[i]).abs()))
        .fold(0f32, f32::max);
    assert!(peak > 0.02, "the cloud is lit: peak {peak}");
    // f16 targets: the rasteriser rounds after each particle, the sums once.
    assert!(
        worst < 5e-3 * peak,
        "computed and rasterised images differ by {worst} (peak {peak})"
    );
}
