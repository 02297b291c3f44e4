//! Batching on the GPU: the clouds of one volume shape share a pool, and each illumination pass
//! covers them all in one dispatch. The dispatch count stays flat in clouds; a cloud's volumes are
//! the same whether it is lit alone or beside others; a pool that grows keeps what it held.

use bevy::{prelude::*, render::sync_world::RenderEntity};
use bevy_particle_clouds::headless::{self, FrameRecorder};
use bevy_particle_clouds::render::{pools::VolumePools, volumes::CloudVolumes};
use bevy_particle_clouds::{
    CloudPass, CloudQualitySettings, Medium, Particle,
    generators::SplitMix64,
    reference::{illumination::voxelize, metrics::max_relative_difference},
    settings::SweepDispatch,
};

use crate::{common, plugin::small_cloud};

/// A camera and one light looking at clouds along x, the light across the row (so that no cloud
/// shadows another: `between_clouds.rs` tests that).
fn scene() -> App {
    let mut app = common::headless_app();
    let image = headless::float_target(&mut app, 64, 32);
    let eye = Transform::from_xyz(0.0, 0.0, 24.0).looking_at(Vec3::ZERO, Vec3::Y);
    headless::spawn_linear_camera(&mut app, image, eye, 40.0, Vec3::ZERO);
    headless::spawn_light(&mut app, Vec3::new(0.0, -1.0, -0.4), Vec3::ONE);
    app
}

/// The plugin tests' small cloud at `x`, at `resolution`³, its albedo varied by `variant`.
fn spawn(app: &mut App, x: f32, variant: u32, resolution: u32) -> Entity {
    let cloud = small_cloud(app, 0.3 + 0.08 * variant as f32, Vec3::X * x);
    app.world_mut()
        .entity_mut(cloud)
        // Supersampling 3 (fine grids of 36³ at 12³): the atlas of the last test has room for
        // the respawned cloud's view volume beside the others' at this size, not at 4.
        .insert(CloudQualitySettings {
            light_supersampling: 3,
            ..common::quality(resolution, 3)
        });
    cloud
}

/// The fine density (`m`³ voxels, the finest level) the GPU holds for `cloud`.
pub(crate) fn fine_density(app: &mut App, cloud: Entity, m: usize) -> Vec<f32> {
    let render = app.world().get::<RenderEntity>(cloud).unwrap().id();
    let range = common::with_render_world(app, |world| {
        let volumes = world.get::<CloudVolumes>(render).unwrap();
        let pool = world.resource::<VolumePools>().pool(&volumes.slot);
        pool.fine_density(volumes.slot.index)
    });
    let bytes = headless::read_buffer_range(app, &range).unwrap();
    headless::floats(&bytes)[..m.pow(3)].to_vec()
}

/// Runs and dispatches of the batched passes (voxelize, shade, gather, scatter, view volume)
/// until the scene is steady (counted by `recorder` from where it stands).
fn illuminate(app: &mut App, recorder: &mut FrameRecorder, clouds: u32) -> ([u32; 5], [u32; 5]) {
    let first = recorder.frames.len();
    headless::render_until_steady(app, recorder, clouds, 20).unwrap();
    let frames = &recorder.frames[first..];
    let passes = [
        CloudPass::Voxelize,
        CloudPass::Shade,
        CloudPass::Gather,
        CloudPass::Scatter,
        CloudPass::ViewVolume,
    ];
    let sum = |f: &dyn Fn(&headless::FrameStats, CloudPass) -> u32| {
        passes.map(|p| frames.iter().map(|s| f(s, p)).sum())
    };
    (sum(&|s, p| s.runs(p)), sum(&|s, p| s.dispatches(p)))
}

/// A cloud's light volumes and multiple scattering, read from its slot.
fn volumes_of(app: &mut App, cloud: Entity) -> (Vec<f64>, Vec<f64>) {
    let render = app.world().get::<RenderEntity>(cloud).unwrap().id();
    let (depths, multiple) = common::with_render_world(app, |world| {
        let volumes = world
            .get::<CloudVolumes>(render)
            .expect("the cloud's volumes");
        let pool = world.resource::<VolumePools>().pool(&volumes.slot);
        let slot = volumes.slot.index;
        (pool.optical_depth(slot), pool.multiple(slot))
    });
    let read = |app: &mut App, range| -> Vec<f64> {
        let bytes = headless::read_buffer_range(app, range).unwrap();
        headless::floats(&bytes)
            .into_iter()
            .map(f64::from)
            .collect()
    };
    let volumes = (read(app, &depths), read(app, &multiple));
    assert!(volumes.1.iter().any(|&s| s > 0.0), "no multiple scattering");
    volumes
}

#[test]
fn the_dispatches_stay_flat_in_clouds_of_one_shape() {
    let mut one = scene();
    spawn(&mut one, 0.0, 0, 12);
    let (runs_one, dispatches_one) = illuminate(&mut one, &mut FrameRecorder::default(), 1);
    // Voxelize's binning (count, scan, scatter, sort), kernel sums and gather (its particles all
    // on the fine grid); one light, 3
    // iterations of 13 sweep directions and the order's accumulation, then the closure's two
    // dispatches, and the default 2 coarse-grid cycles (the media's restriction once, then each
    // two restart sweeps of 15, the residual's restriction and prolongation, and 32 coarse
    // orders closed with two modes); one view volume.
    assert_eq!(runs_one, [1, 1, 1, 3, 1]);
    let cycle = 2 * 15 + 2 + 32 * (13 + 1) + 3;
    assert_eq!(
        dispatches_one,
        [6, 1, 1, 3 * (13 + 1) + 2 + 1 + 2 * cycle, 1]
    );

    let mut six = scene();
    for i in 0..6 {
        spawn(&mut six, 3.0 * i as f32 - 7.5, i, 12);
    }
    let (runs_six, dispatches_six) = illuminate(&mut six, &mut FrameRecorder::default(), 6);
    assert_eq!(runs_six, [6, 6, 6, 18, 6]);
    assert_eq!(dispatches_six, dispatches_one);

    // A second shape is a second pool: one more dispatch per pass, whatever its clouds.
    let mut mixed = scene();
    for i in 0..6 {
        spawn(
            &mut mixed,
            3.0 * i as f32 - 7.5,
            i,
            if i < 4 { 12 } else { 8 },
        );
    }
    let (runs_mixed, dispatches_mixed) = illuminate(&mut mixed, &mut FrameRecorder::default(), 6);
    assert_eq!(runs_mixed, [6, 6, 6, 18, 6]);
    assert_eq!(dispatches_mixed, dispatches_one.map(|d| 2 * d));
}

/// One dispatch per order (`SweepDispatch::PerOrder`) sweeps all 13 direction pairs of an
/// iteration in one dispatch and sums them in a second, the order's accumulation with them, so an
/// iteration takes 2 dispatches instead of 14 and a restart sweep 4 instead of 15, flat in clouds.
#[test]
fn one_dispatch_per_order_takes_two_dispatches_an_iteration() {
    let per_order = |clouds: u32| {
        let mut app = scene();
        app.insert_resource(SweepDispatch::PerOrder);
        for i in 0..clouds {
            spawn(&mut app, 3.0 * i as f32 - 7.5, i, 12);
        }
        illuminate(&mut app, &mut FrameRecorder::default(), clouds)
    };
    let (runs, dispatches) = per_order(1);
    assert_eq!(runs, [1, 1, 1, 3, 1]);
    let cycle = 2 * 4 + 2 + 32 * 2 + 3;
    assert_eq!(dispatches, [6, 1, 1, 3 * 2 + 2 + 1 + 2 * cycle, 1]);
    assert_eq!(per_order(6).1, dispatches);
}

#[test]
fn a_cloud_lit_beside_others_has_the_volumes_it_has_alone() {
    let mut alone = scene();
    let cloud = spawn(&mut alone, 0.0, 2, 12);
    illuminate(&mut alone, &mut FrameRecorder::default(), 1);
    let (depths_alone, multiple_alone) = volumes_of(&mut alone, cloud);

    let mut together = scene();
    let mut clouds = Vec::new();
    for (i, x) in [-8.0, -4.0, 4.0, 8.0].into_iter().enumerate() {
        clouds.push(spawn(&mut together, x, 5 - i as u32, 12));
    }
    let cloud = spawn(&mut together, 0.0, 2, 12);
    illuminate(&mut together, &mut FrameRecorder::default(), 5);
    let (depths, multiple) = volumes_of(&mut together, cloud);
    // Voxelize adds with float atomics, in any order: only rounding may differ.
    assert!(max_relative_difference(&depths, &depths_alone) < 1e-5);
    assert!(max_relative_difference(&multiple, &multiple_alone) < 1e-5);
    // Its neighbours, with other particles, hold other volumes (the slots are not shared).
    let (_, neighbour) = volumes_of(&mut together, clouds[0]);
    assert!(max_relative_difference(&neighbour, &multiple_alone) > 1e-2);
}

#[test]
fn a_growing_pool_keeps_what_its_clouds_hold() {
    let mut app = scene();
    let mut recorder = FrameRecorder::default();
    let first = spawn(&mut app, -6.0, 1, 12);
    illuminate(&mut app, &mut recorder, 1);
    let before = volumes_of(&mut app, first);
    // Three more clouds of its shape: the pool grows from one slot to two, then four.
    for i in 0..3 {
        spawn(&mut app, 3.0 * i as f32 - 2.0, 3 + i, 12);
    }
    let (runs, _) = illuminate(&mut app, &mut recorder, 4);
    // The view's atlas grows too, so the first cloud's view volume is marched again.
    assert_eq!(runs, [3, 3, 3, 9, 4], "only the new clouds are lit");
    let after = volumes_of(&mut app, first);
    assert_eq!(after, before);

    // A despawned cloud frees its slot, and the next cloud of its shape takes it.
    let slot_of = |app: &mut App, cloud: Entity| {
        let render = app.world().get::<RenderEntity>(cloud).unwrap().id();
        common::with_render_world(app, |world| {
            world.get::<CloudVolumes>(render).unwrap().slot.index
        })
    };
    let freed = slot_of(&mut app, first);
    app.world_mut().despawn(first);
    illuminate(&mut app, &mut recorder, 3);
    let next = spawn(&mut app, -6.0, 7, 12);
    let (runs, _) = illuminate(&mut app, &mut recorder, 4);
    assert_eq!(slot_of(&mut app, next), freed);
    // Where the atlas has room, the other clouds' view volumes keep their places.
    assert_eq!(
        runs,
        [1, 1, 1, 3, 1],
        "only the new cloud is lit and marched"
    );
}

/// Clouds of one pool whose particles lie on different density levels are voxelized by the same
/// dispatches (each coarse level enlarged only in the clouds that use it), and each gets its own
/// density: the CPU reference's, voxel by voxel.
#[test]
fn clouds_on_different_density_levels_are_voxelized_together() {
    let mut app = scene();
    // A fine grid of 144³ (36³ at supersampling 4): levels of 144, 72, 36, 18, 9 and 5 voxels
    // per side.
    let settings = CloudQualitySettings {
        light_supersampling: 4,
        ..common::quality(36, 2)
    };
    let medium = Medium {
        extinction: 2.0,
        albedo: 0.9,
        ..default()
    };
    // Small particles in a ball, and at its centre one of radius `largest`: about 5, 44 and 72
    // fine voxels (its cube is at least 1.3 and 2.2 m wide), on levels 0, 1 and 2 (a level
    // takes radii up to 32 of its voxels).
    let mut rng = SplitMix64::new(5);
    let mut particles = |largest: f32| -> Vec<Particle> {
        (0..40)
            .map(|i| Particle {
                position: if i == 0 {
                    Vec3::ZERO
                } else {
                    rng.in_unit_ball() * 0.5
                },
                radius: match i {
                    0 => largest,
                    // Beside a particle on level 2 (36 rows, its level's whole side), one on
                    // the fine grid, 29.5 of its voxels in radius, whose support spans 61 rows.
                    1 if largest > 1.0 => 0.45,
                    _ => 0.06 + 0.1 * rng.next_f32(),
                },
                density: 0.2 + rng.next_f32(),
            })
            .collect()
    };
    let sets = [particles(0.05), particles(0.4), particles(1.1)];
    let clouds: Vec<Entity> = sets
        .iter()
        .zip([-5.0, 0.0, 5.0])
        .map(|(p, x)| {
            let at = Transform::from_xyz(x, 0.0, 0.0);
            headless::spawn_cloud(&mut app, p.clone(), medium, settings, at)
        })
        .collect();
    let mut recorder = FrameRecorder::default();
    headless::render_until_steady(&mut app, &mut recorder, 3, 20).unwrap();
    let count = |f: fn(&headless::FrameStats, CloudPass) -> u32| -> u32 {
        recorder
            .frames
            .iter()
            .map(|s| f(s, CloudPass::Voxelize))
            .sum()
    };
    let levels = |app: &mut App, cloud: Entity| {
        let render = app.world().get::<RenderEntity>(cloud).unwrap().id();
        common::with_render_world(app, |world| {
            let v = world.get::<CloudVolumes>(render).unwrap();
            (v.levels_in_use, v.slot.pool)
        })
    };
    let (in_use, pools): (Vec<usize>, Vec<_>) = clouds.iter().map(|&c| levels(&mut app, c)).unzip();
    assert_eq!(in_use, [1, 2, 3]);
    assert!(pools.iter().all(|p| *p == pools[0]), "one pool");
    // Three clouds voxelized once each; the binning (count, scan, scatter, sort), the kernels'
    // sums, the gather, and levels 2 and 1 enlarged: eight dispatches, as for the one cloud
    // with three levels.
    assert_eq!(
        (count(|s, p| s.runs(p)), count(|s, p| s.dispatches(p))),
        (3, 8)
    );

    let m = settings.light_resolution() as usize;
    for (cloud, particles) in clouds.into_iter().zip(&sets) {
        let gpu: Vec<f64> = fine_density(&mut app, cloud, m)
            .into_iter()
            .map(f64::from)
            .collect();
        let cpu = voxelize(particles, m).expect("density");
        let difference = max_relative_difference(&gpu, &cpu.rho);
        assert!(difference < 2e-4, "{difference}");
    }
}
