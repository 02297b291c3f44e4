//! Which illumination stages a cloud must run this frame. Every stage's output is cached under a
//! key of its inputs, and a stage runs only when its key changes (docs/illumination.md; the
//! `--stats` counters show it). Planning is a pure function of the cached keys and this frame's
//! keys, tested on the CPU.

pub mod budget;
pub mod casters;
pub mod ground;
pub mod overlap;
pub mod params;
pub mod pools;
pub mod volume_shape;
pub mod volumes;

use bevy::prelude::*;

use crate::render::{
    core::key_of,
    core::types::{CloudParams, LightParams},
};
use crate::settings::{CloudQualitySettings, ScatterStencil, SweepDirections};

/// The key of every stage's inputs. A stage's key includes the keys of the stages it reads, so a
/// change flows downstream: new particles re-voxelize, which re-shades every light, which
/// re-gathers, which re-scatters.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct StageKeys {
    /// Voxelize: the particles' upload and the grids' resolutions.
    pub density: u64,
    /// Shade, per light slot: the density, the light's local direction and the extinction.
    pub lights: Vec<u64>,
    /// Cast, per light slot: the light's own volume (its shade key) and the volumes of the clouds
    /// that cast their shadow on this one along it, with where they lie relative to it; the shade
    /// key itself when no cloud does (docs/illumination.md §2).
    pub casts: Vec<u64>,
    /// Gather: every light's shadowed volume and irradiance. [`StageKeys::UNLIT`] when neither a
    /// light nor the sky reaches the cloud.
    pub gather: u64,
    /// Scatter: the gathered source, the sky, the medium and the scattering knobs.
    pub scatter: u64,
    /// The scattering operator alone: the density, the medium (with the media of the clouds that
    /// overlap it) and the scattering knobs, without the source. When only the source changed (a light moved), the scattering may restart from
    /// the solution the volumes hold.
    pub medium: u64,
}

impl StageKeys {
    /// The gather key of a cloud that neither a light nor the sky reaches.
    pub const UNLIT: u64 = 1;

    /// This frame's keys of a cloud with the uniform `params`, its lights' uniforms `lights` (in
    /// slot order), the key of what other clouds cast on it along each light (`casters[i]`: 0, or
    /// missing, when none does; [`cast`](crate::render::plan::casters)), the key of the media of the clouds that
    /// overlap it (`media`: 0 when none does; [`overlap`]), what enters its grid
    /// from outside (the sky's radiance, and the key of the ground under it: 0 for none;
    /// [`ground`]), its particles' upload `generation` and its `settings`.
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        params: &CloudParams,
        lights: &[LightParams],
        casters: &[u64],
        media: u64,
        (sky, ground): (Vec3, u64),
        generation: u64,
        settings: &CloudQualitySettings,
    ) -> Self {
        if lights.is_empty() && sky.max_element() <= 0.0 {
            return Self {
                gather: Self::UNLIT,
                ..default()
            };
        }
        let bits = |v: Vec3| v.to_array().map(f32::to_bits);
        let density = key_of((generation, params.n, params.light_n));
        let shade = |light: &LightParams| {
            key_of((
                density,
                bits(light.w),
                light.sigma_scale.to_bits(),
                light.offset,
                params.light_n,
            ))
        };
        let keys: Vec<u64> = lights.iter().map(shade).collect();
        let casts: Vec<u64> = keys
            .iter()
            .enumerate()
            .map(|(i, &own)| match casters.get(i).copied().unwrap_or(0) {
                0 => own,
                cast => key_of((own, cast)),
            })
            .collect();
        let gather_inputs: Vec<_> = casts
            .iter()
            .zip(lights)
            .map(|(key, light)| (*key, bits(light.irradiance)))
            .collect();
        // The beams are seen through the δ-M depth scale (docs/illumination.md §3).
        let gather = key_of((&gather_inputs, density, params.depth_scale.to_bits()));
        let medium = key_of((
            density,
            params.k_local.to_bits(),
            params.albedo.to_bits(),
            [
                params.depth_scale,
                params.scatter_albedo,
                params.scatter_anisotropy,
            ]
            .map(f32::to_bits),
            settings.scatter_stencil,
            settings.scatter_directions,
            settings.scatter_iterations,
            settings.warm_scatter_iterations,
            settings.coarse_cycles(),
            media,
        ));
        Self {
            density,
            lights: keys,
            casts,
            gather,
            scatter: key_of((gather, medium, bits(sky), ground)),
            medium,
        }
    }
}

/// What the illumination system must do for one cloud this frame.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct WorkPlan {
    /// Rebuild the density grid.
    pub voxelize: bool,
    /// Light slots to shade.
    pub shade: Vec<usize>,
    /// Light slots whose volume is rebuilt from its own optical depth and what other clouds cast
    /// on it: those whose casters changed, and every shaded one that has casters.
    pub cast: Vec<usize>,
    /// Gather every light into the scattering source `S_0`.
    pub gather: bool,
    /// Restart the multiple scattering from `S_0`: this many iterations, then the closure.
    pub scatter: Option<u32>,
    /// The stencil of those iterations.
    pub stencil: ScatterStencil,
    /// The sweep's directions (the discrete-ordinates stencil's).
    pub directions: SweepDirections,
    /// No light reaches the cloud: its multiple scattering is zeroed instead of computed.
    pub unlit: bool,
    /// The scattering restarts from the solution the volumes hold (only the source changed):
    /// `scatter` is then `warm_scatter_iterations` (docs/illumination.md §4).
    pub warm: bool,
    /// Coarse-grid cycles after the full series (`scatter_coarse_cycles`; 0 in a warm
    /// restart).
    pub cycles: u32,
}

impl WorkPlan {
    /// Nothing to do.
    pub fn is_empty(&self) -> bool {
        *self == Self::default()
    }
}

/// The stages whose keys changed between `cached` (what the volumes hold) and `now`.
pub fn plan(cached: &StageKeys, now: &StageKeys, settings: &CloudQualitySettings) -> WorkPlan {
    if now.gather == StageKeys::UNLIT {
        // Nothing lights the cloud: it only absorbs. Zero its multiple scattering once.
        return WorkPlan {
            unlit: cached.gather != StageKeys::UNLIT,
            ..default()
        };
    }
    // Only the source changed (a light moved or changed colour), and the volumes hold a
    // scattering solution of this medium to restart from.
    let warm = settings.warm_scatter_iterations > 0
        && settings.scatter_iterations > 0
        && now.scatter != cached.scatter
        && now.medium == cached.medium
        && now.gather != cached.gather
        && cached.gather != StageKeys::UNLIT
        && cached.scatter != 0;
    let iterations = if warm {
        settings.warm_scatter_iterations
    } else {
        settings.scatter_iterations
    };
    let changed = (now.scatter != cached.scatter).then_some(iterations);
    let shade: Vec<usize> = (0..now.lights.len())
        .filter(|&i| cached.lights.get(i) != Some(&now.lights[i]))
        .collect();
    // Shade writes a light's own optical depth into the volume gather reads too: only a volume
    // with casters, or one whose casters changed without a re-shade, needs the cast.
    let cast = (0..now.casts.len())
        .filter(|&i| cached.casts.get(i) != Some(&now.casts[i]))
        .filter(|&i| now.casts[i] != now.lights[i] || !shade.contains(&i))
        .collect();
    WorkPlan {
        voxelize: now.density != cached.density,
        shade,
        cast,
        gather: now.gather != cached.gather,
        scatter: changed,
        stencil: if changed.is_some() {
            settings.scatter_stencil
        } else {
            default()
        },
        directions: if changed.is_some() {
            settings.scatter_directions
        } else {
            default()
        },
        unlit: false,
        warm,
        cycles: if changed.is_some() && !warm {
            settings.coarse_cycles()
        } else {
            0
        },
    }
}

/// Marks the scatter key of a warm restart's solution.
const WARM_RESTART: u64 = 0x5741_524d_5354_4152;

/// A cloud's illumination state (render world component): the keys of what its volumes hold,
/// this frame's plan, and whether a finished illumination exists.
#[derive(Component, Clone, Debug, Default)]
pub struct CloudIllumination {
    /// The keys of the stages whose output the volumes hold.
    pub keys: StageKeys,
    /// This frame's work, consumed by `illuminate_clouds`.
    pub plan: WorkPlan,
    /// The volumes hold a finished illumination: the cloud may be drawn.
    pub ready: bool,
    /// Counts (wrapping) the frames whose work changed its multiple scattering: what a view's
    /// evaluation of it towards the camera was made from (`view_volume.rs`).
    pub scattered: u32,
    /// Frames its pending work has been put off by the re-light budget.
    pub waited: u32,
    /// Per light slot, the clouds (render entities) that cast their shadow on this one this
    /// frame, for the cast pass.
    pub casters: Vec<Vec<Entity>>,
    /// The clouds whose media reach into its scattering grid this frame, for the overlap pass.
    pub neighbours: Vec<Entity>,
}

impl CloudIllumination {
    /// Plans this frame against the cached keys, which become `now`. An unlit cloud keeps its
    /// density and shaded volumes: they are still valid when a light comes back.
    pub fn update(&mut self, now: StageKeys, settings: &CloudQualitySettings) {
        self.plan = plan(&self.keys, &now, settings);
        self.keys = if now.gather == StageKeys::UNLIT {
            StageKeys {
                gather: StageKeys::UNLIT,
                scatter: 0,
                ..std::mem::take(&mut self.keys)
            }
        } else if self.plan.warm {
            // A warm restart's solution is not the full solve's: the next frame with the same
            // source settles it (its scatter key differs), and then nothing runs.
            StageKeys {
                scatter: now.scatter ^ WARM_RESTART,
                ..now
            }
        } else {
            now
        };
    }

    /// Forgets every cached stage, so that the next frame redoes all of them (when the work of a
    /// frame could not be recorded, e.g. while pipelines compile).
    pub fn invalidate(&mut self) {
        self.keys = StageKeys::default();
        self.plan = WorkPlan::default();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn params() -> CloudParams {
        CloudParams {
            n: 16,
            light_n: 32,
            k_local: 10.0,
            albedo: 0.9,
            ..default()
        }
    }

    fn light(w: Vec3, irradiance: f32, slot: u32) -> LightParams {
        LightParams {
            w,
            irradiance: Vec3::splat(irradiance),
            sigma_scale: 10.0,
            offset: slot * 32u32.pow(3),
            ..default()
        }
    }

    fn keys(lights: &[LightParams], generation: u64, settings: &CloudQualitySettings) -> StageKeys {
        StageKeys::new(
            &params(),
            lights,
            &[],
            0,
            (Vec3::ZERO, 0),
            generation,
            settings,
        )
    }

    #[test]
    fn each_change_reruns_exactly_its_stage_and_those_downstream() {
        let settings = CloudQualitySettings::default();
        let two = [light(Vec3::X, 1.0, 0), light(Vec3::Y, 2.0, 1)];
        let first = keys(&two, 1, &settings);
        let all = plan(&StageKeys::default(), &first, &settings);
        assert_eq!(
            all,
            WorkPlan {
                voxelize: true,
                shade: vec![0, 1],
                cast: vec![],
                gather: true,
                scatter: Some(settings.scatter_iterations),
                stencil: settings.scatter_stencil,
                directions: settings.scatter_directions,
                unlit: false,
                warm: false,
                cycles: 2,
            }
        );
        // Nothing changed: nothing runs.
        assert!(plan(&first, &keys(&two, 1, &settings), &settings).is_empty());
        // One light turned: only it is shaded again, then gather and scatter.
        let turned = [two[0], light(Vec3::Z, 2.0, 1)];
        let p = plan(&first, &keys(&turned, 1, &settings), &settings);
        assert_eq!(
            (p.voxelize, p.shade.clone(), p.gather),
            (false, vec![1], true)
        );
        assert!(p.scatter.is_some());
        // A brighter light: no shading, gather and scatter only.
        let brighter = [light(Vec3::X, 3.0, 0), two[1]];
        let p = plan(&first, &keys(&brighter, 1, &settings), &settings);
        assert_eq!((p.voxelize, p.shade.len(), p.gather), (false, 0, true));
        // More iterations: scatter only.
        let more = CloudQualitySettings {
            scatter_iterations: 64,
            ..settings
        };
        let p = plan(&first, &keys(&two, 1, &more), &more);
        assert_eq!(
            (p.voxelize, p.shade.len(), p.gather, p.scatter),
            (false, 0, false, Some(64))
        );
        // Another draw target scale (or compositing, chord segments, draw method): no
        // illumination.
        let drawn_smaller = CloudQualitySettings {
            cloud_target_scale: 0.5,
            draw_method: crate::DrawMethod::Compute,
            chord_segments: 2,
            compositing: crate::Compositing::Sorted,
            ..settings
        };
        let p = plan(&first, &keys(&two, 1, &drawn_smaller), &drawn_smaller);
        assert!(p.is_empty());
        // New particles: everything.
        let p = plan(&first, &keys(&two, 2, &settings), &settings);
        assert_eq!(p, all);
    }

    #[test]
    fn a_moved_light_restarts_warm_and_a_still_one_settles_with_a_full_solve() {
        let settings = CloudQualitySettings {
            warm_scatter_iterations: 6,
            ..default()
        };
        let mut state = CloudIllumination::default();
        let lit = |w: Vec3| keys(&[light(w, 1.0, 0)], 1, &settings);
        // The first solve is a full one.
        state.update(lit(Vec3::X), &settings);
        assert_eq!((state.plan.scatter, state.plan.warm), (Some(8), false));
        // The light moves: shade, gather, and a warm restart.
        state.update(lit(Vec3::new(1.0, 0.1, 0.0)), &settings);
        assert_eq!(state.plan.shade, [0]);
        assert_eq!((state.plan.scatter, state.plan.warm), (Some(6), true));
        state.update(lit(Vec3::new(1.0, 0.2, 0.0)), &settings);
        assert_eq!((state.plan.scatter, state.plan.warm), (Some(6), true));
        // It stops: one full solve settles the series, then nothing runs.
        state.update(lit(Vec3::new(1.0, 0.2, 0.0)), &settings);
        assert_eq!(state.plan.shade, Vec::<usize>::new());
        assert_eq!((state.plan.scatter, state.plan.warm), (Some(8), false));
        state.update(lit(Vec3::new(1.0, 0.2, 0.0)), &settings);
        assert!(state.plan.is_empty());
        // A new medium (or density) restarts from zero, whatever the lights.
        let thicker = |w: Vec3| {
            let params = CloudParams {
                k_local: 20.0,
                ..params()
            };
            StageKeys::new(
                &params,
                &[light(w, 1.0, 0)],
                &[],
                0,
                (Vec3::ZERO, 0),
                1,
                &settings,
            )
        };
        state.update(thicker(Vec3::Y), &settings);
        assert_eq!((state.plan.scatter, state.plan.warm), (Some(8), false));
        // Off (0): always the full solve.
        let cold = CloudQualitySettings {
            warm_scatter_iterations: 0,
            ..default()
        };
        let mut state = CloudIllumination::default();
        state.update(keys(&[light(Vec3::X, 1.0, 0)], 1, &cold), &cold);
        state.update(keys(&[light(Vec3::Y, 1.0, 0)], 1, &cold), &cold);
        assert_eq!((state.plan.scatter, state.plan.warm), (Some(8), false));
    }

    #[test]
    fn coarse_grid_cycles_follow_the_full_series_only() {
        let settings = CloudQualitySettings {
            scatter_coarse_cycles: 3,
            ..default()
        };
        let mut state = CloudIllumination::default();
        let lit = |w: Vec3, s: &CloudQualitySettings| keys(&[light(w, 1.0, 0)], 1, s);
        state.update(lit(Vec3::X, &settings), &settings);
        assert_eq!((state.plan.scatter, state.plan.cycles), (Some(8), 3));
        // A warm restart runs none.
        state.update(lit(Vec3::new(1.0, 0.1, 0.0), &settings), &settings);
        assert_eq!((state.plan.warm, state.plan.cycles), (true, 0));
        state.update(lit(Vec3::new(1.0, 0.1, 0.0), &settings), &settings);
        assert_eq!((state.plan.warm, state.plan.cycles), (false, 3));
        // More cycles: the scattering reruns, and only it.
        let more = CloudQualitySettings {
            scatter_coarse_cycles: 5,
            ..settings
        };
        state.update(lit(Vec3::new(1.0, 0.1, 0.0), &more), &more);
        let p = &state.plan;
        assert_eq!(
            (p.gather, p.shade.len(), p.scatter, p.cycles),
            (false, 0, Some(8), 5)
        );
        // The paper's stencil has none.
        let paper = CloudQualitySettings {
            scatter_stencil: ScatterStencil::Paper,
            ..more
        };
        state.update(lit(Vec3::new(1.0, 0.1, 0.0), &paper), &paper);
        assert_eq!((state.plan.scatter, state.plan.cycles), (Some(8), 0));
        // Other sweep directions: the full series again, along them.
        let finer = CloudQualitySettings {
            scatter_directions: SweepDirections::Lattice98,
            ..more
        };
        state.update(lit(Vec3::new(1.0, 0.1, 0.0), &finer), &finer);
        let p = &state.plan;
        assert_eq!(
            (p.gather, p.scatter, p.directions),
            (false, Some(8), SweepDirections::Lattice98)
        );
    }

    #[test]
    fn another_clouds_shadow_recasts_without_reshading() {
        let settings = CloudQualitySettings::default();
        let two = [light(Vec3::X, 1.0, 0), light(Vec3::Y, 2.0, 1)];
        let cast = |casts: &[u64]| {
            StageKeys::new(&params(), &two, casts, 0, (Vec3::ZERO, 0), 1, &settings)
        };
        let mut state = CloudIllumination::default();
        // The first frame: both shaded; light 1 has casters, so it is cast too.
        state.update(cast(&[0, 7]), &settings);
        assert_eq!(
            (state.plan.shade.clone(), state.plan.cast.clone()),
            (vec![0, 1], vec![1])
        );
        state.update(cast(&[0, 7]), &settings);
        assert!(state.plan.is_empty());
        // A caster moved: light 1 is cast again (not shaded), then gather and scatter.
        state.update(cast(&[0, 8]), &settings);
        let p = state.plan.clone();
        assert_eq!(
            (p.voxelize, p.shade, p.cast, p.gather),
            (false, vec![], vec![1], true)
        );
        assert!(p.scatter.is_some());
        // Its casters gone: cast once more, to its own optical depth.
        state.update(cast(&[0, 0]), &settings);
        assert_eq!(
            (state.plan.shade.clone(), state.plan.cast.clone()),
            (vec![], vec![1])
        );
        // No caster: the keys are those of a cloud alone.
        assert_eq!(cast(&[]), cast(&[0, 0]));
    }

    #[test]
    fn an_unlit_cloud_is_zeroed_once() {
        let settings = CloudQualitySettings::default();
        let lit = keys(&[light(Vec3::X, 1.0, 0)], 1, &settings);
        let dark = keys(&[], 1, &settings);
        let p = plan(&lit, &dark, &settings);
        assert_eq!(
            p,
            WorkPlan {
                unlit: true,
                ..default()
            }
        );
        assert!(plan(&dark, &dark, &settings).is_empty());
        // Lit, dark, lit again: the density and the shaded light are kept; gather and scatter rerun.
        let mut state = CloudIllumination::default();
        state.update(lit.clone(), &settings);
        state.update(dark.clone(), &settings);
        assert!(state.plan.unlit);
        state.update(dark, &settings);
        assert!(state.plan.is_empty());
        state.update(lit, &settings);
        let p = &state.plan;
        assert_eq!((p.voxelize, p.shade.len(), p.gather), (false, 0, true));
        assert!(p.scatter.is_some());
    }

    #[test]
    fn invalidating_replans_everything() {
        let settings = CloudQualitySettings::default();
        let mut state = CloudIllumination::default();
        let now = keys(&[light(Vec3::X, 1.0, 0)], 1, &settings);
        state.update(now.clone(), &settings);
        assert!(!state.plan.is_empty());
        state.update(now.clone(), &settings);
        assert!(state.plan.is_empty());
        state.invalidate();
        state.update(now, &settings);
        assert!(state.plan.voxelize && state.plan.gather && state.plan.scatter.is_some());
    }
}
