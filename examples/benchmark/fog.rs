//! Scenes with distance fog: besides the image's error, the error of what the fog changes,
//! `(real-time with fog - real-time without)` against `(reference with fog - reference without)`,
//! relative to that change. Both renderers agree exactly on the fog's own colour over the cloud,
//! which dilutes the plain image error; this measures only the fog's effect. The fog draws no
//! random numbers in the path tracer, so with the same seeds both references trace the same
//! paths and their difference is nearly noise-free.

use super::*;
use bevy::math::DVec3;

/// The fog-free twin of a fogged scene: its reference (same samples and seeds, cached).
pub(crate) struct FogEffect {
    clear: Reference,
}

impl FogEffect {
    /// For a scene with fog, its fog-free twin's reference; `None` without fog. Call it before
    /// the fogged scene's `reference`, whose picture then stays on disk.
    pub(crate) fn new(
        scene: &Scene,
        bench: &BenchScene,
        spp: u32,
        out: &Path,
    ) -> Result<Option<Self>, String> {
        if scene.fog.is_none() {
            return Ok(None);
        }
        let clear = Scene {
            fog: None,
            ..scene.clone()
        };
        Ok(Some(Self {
            clear: reference(&clear, bench, spp, out)?,
        }))
    }

    /// The noise of the references' fog effect (docs/physics.md's noise level, of the mean of
    /// both seeds).
    pub(crate) fn noise(&self, fogged: &Reference) -> f64 {
        let effect = |i: usize| difference(&fogged.seeds[i], &self.clear.seeds[i]);
        noise_level(&effect(0), &effect(1)) / std::f64::consts::SQRT_2
    }

    /// The relative RMSE of the real-time fog effect against the references'; and, as an
    /// estimate, how much of it the cloud's own error explains: with the whole cloud at the
    /// distance `d` of its particles' mean, the fog turns the clear image's error `e` into
    /// `V(d) e`, so the effect inherits `(1 - V(d)) e`.
    pub(crate) fn error(
        &self,
        fogged: &[[f32; 4]],
        clear: &[[f32; 4]],
        reference: &Reference,
        scene: &Scene,
    ) -> (f64, f64) {
        let effect = difference(&reference.image, &self.clear.image);
        let error = relative_rmse(&difference(fogged, clear), &effect);
        let kept = scene
            .fog
            .map_or(DVec3::ONE, |f| f.at(cloud_distance(scene)).transmitted);
        let inherited: Vec<[f32; 4]> = difference(clear, &self.clear.image)
            .iter()
            .zip(&effect)
            .map(|(e, r)| {
                std::array::from_fn(|c| {
                    if c < 3 {
                        r[c] + (1.0 - kept[c] as f32) * e[c]
                    } else {
                        r[c]
                    }
                })
            })
            .collect();
        (error, relative_rmse(&inherited, &effect))
    }
}

/// Distance from the camera to the mean of every particle, metres.
fn cloud_distance(scene: &Scene) -> f64 {
    let (sum, n) = scene
        .clouds
        .iter()
        .flat_map(|c| c.particles.iter().map(|p| p.position + c.translation))
        .fold((Vec3::ZERO, 0), |(s, n), p| (s + p, n + 1));
    (sum / n.max(1) as f32 - scene.camera.position).length() as f64
}

/// `a - b`, pixel by pixel.
fn difference(a: &[[f32; 4]], b: &[[f32; 4]]) -> Vec<[f32; 4]> {
    a.iter()
        .zip(b)
        .map(|(a, b)| std::array::from_fn(|c| a[c] - b[c]))
        .collect()
}
