//! Churn in a running app: for thousands of frames, clouds are spawned, despawned, given new
//! particles, re-parented and re-set, lights come and go, and the view is resized. Nothing
//! panics, every frame renders, and the GPU memory the crate holds (its own census,
//! `CloudPassCounters::gpu_memory`) returns to its baseline whenever the clouds are gone.

use bevy::{prelude::*, render::render_resource::Extent3d};
use bevy_particle_clouds::{
    CloudPass, CloudPassCounters, CloudQualitySettings, Medium, Particle, generators,
    headless::{self, FrameRecorder},
    math::SplitMix64,
};

use crate::{common, plugin::edit_particles};

/// Cycles of churn, each ending with every cloud despawned.
const CYCLES: usize = 8;
/// Frames of churn per cycle.
const FRAMES: usize = 250;
/// Frames after the last despawn for the pools, particles and view resources to go.
const SETTLE: usize = 4;

struct Churn {
    rng: SplitMix64,
    clouds: Vec<Entity>,
    lights: Vec<Entity>,
    parent: Entity,
    image: Handle<Image>,
}

impl Churn {
    fn below(&mut self, n: usize) -> usize {
        (self.rng.next_u64() % n as u64) as usize
    }

    fn uniform(&mut self, lo: f32, hi: f32) -> f32 {
        lo + (hi - lo) * self.rng.next_f64() as f32
    }

    fn particles(&mut self) -> Vec<Particle> {
        let count = 5 + self.below(40);
        generators::sphere(0.6, 0.2, count, self.rng.next_u64()).particles
    }

    fn settings(&mut self) -> CloudQualitySettings {
        CloudQualitySettings {
            volume_resolution: [8, 12, 16][self.below(3)],
            light_supersampling: 1 + self.below(2) as u32,
            scatter_iterations: 1 + self.below(3) as u32,
            scatter_coarse_cycles: self.below(2) as u32,
            ..default()
        }
    }

    fn spawn_cloud(&mut self, app: &mut App) {
        let particles = self.particles();
        let medium = Medium {
            extinction: self.uniform(1.0, 30.0),
            albedo: self.uniform(0.5, 1.0),
            anisotropy: [0.0, 0.0, 0.6][self.below(3)],
        };
        let settings = self.settings();
        let at = Vec3::new(self.uniform(-1.5, 1.5), self.uniform(-0.8, 0.8), 0.0);
        let cloud = headless::spawn_cloud(
            app,
            particles,
            medium,
            settings,
            Transform::from_translation(at),
        );
        self.clouds.push(cloud);
    }

    /// One frame's change, drawn at random.
    fn change(&mut self, app: &mut App) {
        let pick = self.below(self.clouds.len().max(1));
        let cloud = self.clouds.get(pick).copied();
        match (self.below(9), cloud) {
            (0 | 1, _) if self.clouds.len() < 6 => self.spawn_cloud(app),
            (2, Some(cloud)) => {
                app.world_mut().despawn(cloud);
                self.clouds.retain(|&c| c != cloud);
            }
            (3, Some(cloud)) => {
                let particles = self.particles();
                edit_particles(app, cloud, |p| *p = particles);
            }
            (4, Some(cloud)) => {
                let settings = self.settings();
                app.world_mut().entity_mut(cloud).insert(settings);
            }
            (5, Some(cloud)) => {
                let mut entity = app.world_mut().entity_mut(cloud);
                if entity.contains::<ChildOf>() {
                    entity.remove::<ChildOf>();
                } else {
                    entity.insert(ChildOf(self.parent));
                }
            }
            (6, _) if self.lights.len() < 3 => {
                let direction = Vec3::new(self.uniform(-1.0, 1.0), -1.0, self.uniform(-1.0, 1.0));
                let light = headless::spawn_light(app, direction, Vec3::splat(1.5));
                self.lights.push(light);
            }
            (7, _) if !self.lights.is_empty() => {
                let pick = self.below(self.lights.len());
                let light = self.lights.remove(pick);
                app.world_mut().despawn(light);
            }
            (8, _) => {
                let size = Extent3d {
                    width: 16 + 8 * self.below(4) as u32,
                    height: 12 + 6 * self.below(4) as u32,
                    depth_or_array_layers: 1,
                };
                let mut images = app.world_mut().resource_mut::<Assets<Image>>();
                images.get_mut(&self.image).unwrap().resize(size);
            }
            _ => {
                let mut parent = app.world_mut().get_mut::<Transform>(self.parent).unwrap();
                parent.rotate_y(0.05);
            }
        }
    }
}

fn memory(app: &App) -> bevy_particle_clouds::CloudGpuMemory {
    app.world().resource::<CloudPassCounters>().gpu_memory()
}

#[test]
fn thousands_of_frames_of_churn_leave_no_gpu_memory_behind() {
    let mut app = common::headless_app();
    common::draw_every_frame(&mut app);
    let image = headless::float_target(&mut app, 32, 24);
    headless::spawn_linear_camera(
        &mut app,
        image.clone(),
        Transform::from_xyz(0.0, 0.0, 6.0).looking_at(Vec3::ZERO, Vec3::Y),
        50.0,
        Vec3::new(0.1, 0.2, 0.3),
    );
    let parent = app
        .world_mut()
        .spawn((Transform::from_xyz(0.3, 0.0, 0.0), Visibility::default()))
        .id();
    let light = headless::spawn_light(&mut app, Vec3::new(-0.4, -1.0, -0.3), Vec3::ONE);
    let mut recorder = FrameRecorder::default();
    for _ in 0..SETTLE {
        recorder.frame(&mut app).unwrap();
    }
    let baseline = memory(&app);
    let mut churn = Churn {
        rng: SplitMix64::new(7),
        clouds: Vec::new(),
        lights: vec![light],
        parent,
        image,
    };
    let mut peaks = Vec::new();
    for cycle in 0..CYCLES {
        let (mut peak, mut drawn) = (0, 0);
        for _ in 0..FRAMES {
            churn.change(&mut app);
            let frame = recorder.frame(&mut app).expect("every frame renders");
            drawn += frame.runs(CloudPass::Draw);
            peak = peak.max(memory(&app).total());
        }
        for cloud in std::mem::take(&mut churn.clouds) {
            app.world_mut().despawn(cloud);
        }
        for _ in 0..SETTLE {
            recorder.frame(&mut app).expect("every frame renders");
        }
        let after = memory(&app);
        eprintln!(
            "cycle {cycle}: {drawn} clouds drawn, peak {peak} bytes, after despawning {after:?}"
        );
        assert!(drawn > 0, "cycle {cycle} drew no cloud");
        assert_eq!(after, baseline, "cycle {cycle} left memory behind");
        peaks.push(peak);
    }
    // Nothing grows from cycle to cycle: the later cycles peak no higher than the first half's
    // highest peak allows for the clouds they happened to hold.
    let first = peaks[..CYCLES / 2].iter().max().copied().unwrap();
    let last = peaks[CYCLES / 2..].iter().max().copied().unwrap();
    eprintln!("baseline {baseline:?}; peaks {peaks:?}");
    assert!(last <= 2 * first, "peaks grew: {peaks:?}");
}
