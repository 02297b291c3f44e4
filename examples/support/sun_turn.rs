//! `--sun-turn-gif`: the example rendered headlessly while its key lights turn once around the
//! sky, every step re-lit until finished, written as a looping animated GIF (the README's
//! picture).

use std::{f32::consts::TAU, fs::File, io::BufWriter, path::Path, time::Instant};

use bevy::prelude::*;
use bevy_particle_clouds::{headless, image_io};
use image::{
    Delay, Frame,
    codecs::gif::{GifEncoder, Repeat},
};

use super::{Example, FrameRecorder, KeyLight, Options, render_finished, render_to_image};

/// How long each picture shows, milliseconds.
const STEP_MS: u32 = 120;

/// Renders `options.sun_turn_frames` pictures, the key lights' azimuth advanced by one step
/// before each, and writes them to `path` as a GIF.
pub fn run(mut app: App, example: &Example, options: &Options, path: &Path) -> Result<(), String> {
    let start = Instant::now();
    let size = options.size.unwrap_or(UVec2::new(640, 360));
    let target = render_to_image(&mut app, size);
    let steps = options.sun_turn_frames;
    eprintln!(
        "{}: {steps} pictures of a turning sun, headlessly on {}",
        example.title,
        headless::adapter_name(&mut app)
    );
    // Every picture waits until the re-lit clouds are finished, whatever the example's default.
    let settled = Example {
        steady: true,
        ..*example
    };
    let mut recorder = FrameRecorder::default();
    let mut pictures = Vec::with_capacity(steps as usize);
    for step in 0..steps {
        if step > 0 {
            turn_key_lights(app.world_mut(), TAU / steps as f32);
        }
        // The first picture waits for the whole scene; later ones for the re-lighting.
        let frames = if step == 0 { 2 } else { 1 };
        render_finished(&mut app, &settled, &mut recorder, frames)?;
        let picture =
            headless::capture(&mut app, &mut recorder, &target).map_err(|e| e.to_string())?;
        if picture.pixels.iter().flatten().any(|v| !v.is_finite()) {
            return Err(format!("picture {step} has non-finite pixels"));
        }
        let mut picture = image_io::tonemap_to_srgb8(&picture);
        // The camera's clear colour is opaque; a GIF has no partial transparency anyway.
        picture.pixels_mut().for_each(|p| p.0[3] = 255);
        pictures.push(picture);
        eprintln!(
            "{}: picture {}/{steps} at {:.1} s",
            example.title,
            step + 1,
            start.elapsed().as_secs_f64()
        );
    }
    write_gif(path, pictures)?;
    eprintln!(
        "{}: wrote {} ({}x{}, {steps} pictures) in {:.1} s",
        example.title,
        path.display(),
        size.x,
        size.y,
        start.elapsed().as_secs_f64()
    );
    Ok(())
}

/// Turns every key light's azimuth by `angle` radians.
fn turn_key_lights(world: &mut World, angle: f32) {
    let mut lights = world.query::<(&mut KeyLight, &mut Transform)>();
    for (mut light, mut transform) in lights.iter_mut(world) {
        light.azimuth += angle;
        *transform = light.transform();
    }
}

fn write_gif(path: &Path, pictures: Vec<image::RgbaImage>) -> Result<(), String> {
    let error = |e: &dyn std::fmt::Display| format!("cannot write {}: {e}", path.display());
    let file = File::create(path).map_err(|e| error(&e))?;
    // Speed 10 of 1..=30: a good palette per picture without minutes of quantising.
    let mut encoder = GifEncoder::new_with_speed(BufWriter::new(file), 10);
    encoder
        .set_repeat(Repeat::Infinite)
        .map_err(|e| error(&e))?;
    let delay = Delay::from_numer_denom_ms(STEP_MS, 1);
    let frames = pictures
        .into_iter()
        .map(|p| Frame::from_parts(p, 0, 0, delay));
    encoder.encode_frames(frames).map_err(|e| error(&e))
}
