//! # bevy_particle_clouds
//!
//! Participating media — clouds, smoke, fog, snow — made of particles, rendered by Bevy on the GPU:
//! lit by any number of directional lights, a sky ([`CloudSkyLight`]) and the ground below
//! ([`CloudGround`]), self-shadowed and shadowing each other, with multiple scattering (through
//! each other's media where clouds overlap); the medium scatters isotropically or forward
//! ([`Medium::anisotropy`]).
//! It follows Remes, Umenhoffer and Szécsi, *GPU based particle rendering system for isotropic
//! participating media*: per cloud the particles' density is voxelized, each light shades a
//! light-aligned volume slice by slice, the lights are gathered into one illumination volume,
//! multiple scattering iterates a 26-neighbour stencil, and the particles are drawn as sorted,
//! camera-facing billboards in the `Transparent3d` phase.
//!
//! ```no_run
//! use bevy::prelude::*;
//! use bevy_particle_clouds::prelude::*;
//!
//! fn setup(mut commands: Commands, mut particles: ResMut<Assets<Particles>>) {
//!     let cumulus = particles.add(generators::cumulus(1.5, 400, 7));
//!     commands.spawn((ParticleCloud::new(cumulus), Transform::from_xyz(0.0, 2.0, 0.0)));
//!     // A blue sky that lights the clouds (black, and free, by default).
//!     commands.insert_resource(CloudSkyLight { color: Color::srgb(0.5, 0.7, 1.0), brightness: 400.0 });
//!     commands.spawn((
//!         DirectionalLight { illuminance: 10_000.0, ..default() },
//!         Transform::from_xyz(1.0, 1.0, 0.5).looking_at(Vec3::ZERO, Vec3::Y),
//!     ));
//!     // Clouds drawn at half the view's size per axis, enlarged by a depth-aware upsample.
//!     commands.spawn((Camera3d::default(), CloudTargetScale(0.5), Transform::from_xyz(0.0, 2.0, 8.0)));
//! }
//!
//! App::new()
//!     .add_plugins((DefaultPlugins, ParticleCloudsPlugin))
//!     .add_systems(Startup, setup)
//!     .run();
//! ```
//!
//! Units and the physical model: `docs/physics.md`; the discretization: `docs/illumination.md`;
//! scene files: `docs/scene-format.md`.
//!
//! # Features
//!
//! The default is what a game needs: the plugin, the components, the [`Particles`] asset and its
//! PLY/CSV loader, and `distance_fog`. Opt in to the rest:
//!
//! | feature | enables |
//! |---|---|
//! | `distance_fog` (default) | clouds fogged by the camera's `DistanceFog` (pulls in `bevy_pbr`) |
//! | `lit_object` | materials that take the clouds' shadows: `lit_object::LitObjectMaterial` (Lambertian) and `cloud_shadowed_material::CloudShadowedMaterial` (a game's `StandardMaterial`); pulls in `bevy_pbr` |
//! | `parallel` | multi-threaded particle generators (rayon); identical results |
//! | `scene` | RON scene files (`scene`) |
//! | `image` | EXR (with metadata) and PNG output (`image_io`) |
//! | `reference` | the f64 CPU reference of every pass and the ground-truth path tracer (`reference`); implies `scene`, `parallel` |
//! | `headless` | rendering without a window (`headless`): spawn a scene, render until finished, capture; implies `scene`, `distance_fog`, `lit_object` |

#![warn(missing_docs)]
pub mod atmosphere;
pub mod beam_phase;
pub mod cloud;
#[cfg(feature = "lit_object")]
pub mod cloud_shadowed_material;
pub mod fog;
pub mod generators;
pub mod ground;
#[cfg(feature = "headless")]
pub mod headless;
#[cfg(feature = "image")]
pub mod image_io;
pub mod lattice;
pub mod linear_image;
#[cfg(feature = "lit_object")]
pub mod lit_object;
pub mod loader;
pub mod lod;
pub mod math;
pub mod particle;
pub mod particle_files;
#[cfg(feature = "reference")]
pub mod reference;
pub mod render;
#[cfg(feature = "scene")]
pub mod scene;
pub mod settings;
pub mod shadow_maps;
pub mod stats;
pub mod views;

use bevy::prelude::*;

pub use cloud::{
    CloudSkyLight, CloudSystems, InvalidCloud, NotCloudLight, ParticleCloud, Particles,
};
pub use ground::CloudGround;
pub use lod::{CloudLevelOfDetail, CloudLod};
pub use particle::{LightSample, Medium, Particle};
pub use settings::{
    BillboardShading, CloudQualitySettings, CloudRedraw, CloudRelightBudget, CloudTargetScale,
    Compositing, DefaultCloudQuality, DrawMethod, ScatterStencil, SweepDirections,
};
pub use shadow_maps::{CloudLight, CloudLights, CloudShadowMaps};
pub use stats::{CloudGpuMemory, CloudPass, CloudPassCounters, PASSES};

/// Everything a Bevy user needs.
pub mod prelude {
    pub use crate::{
        BillboardShading, CloudGround, CloudLevelOfDetail, CloudLod, CloudQualitySettings,
        CloudRedraw, CloudRelightBudget, CloudShadowMaps, CloudSkyLight, CloudSystems,
        CloudTargetScale, Compositing, DefaultCloudQuality, DrawMethod, Medium, NotCloudLight,
        Particle, ParticleCloud, ParticleCloudsPlugin, Particles, ScatterStencil, SweepDirections,
        generators,
    };
}

/// Renders every [`ParticleCloud`]. Add it after `DefaultPlugins`.
///
/// Without clouds it adds no GPU work: every pass is skipped while no cloud exists.
#[derive(Default)]
pub struct ParticleCloudsPlugin;

impl Plugin for ParticleCloudsPlugin {
    fn build(&self, app: &mut App) {
        app.init_asset::<Particles>()
            .init_asset_loader::<loader::ParticlesLoader>()
            .register_type::<ParticleCloud>()
            .register_asset_reflect::<Particles>()
            .register_type::<NotCloudLight>()
            .register_type::<CloudSkyLight>()
            .init_resource::<CloudSkyLight>()
            .register_type::<CloudGround>()
            .register_type::<CloudQualitySettings>()
            .register_type::<CloudTargetScale>()
            .register_type::<DefaultCloudQuality>()
            .register_type::<CloudLevelOfDetail>()
            .register_type::<CloudLod>()
            .init_resource::<DefaultCloudQuality>()
            .init_resource::<CloudLevelOfDetail>()
            .register_type::<CloudShadowMaps>()
            .init_resource::<CloudShadowMaps>()
            .register_type::<CloudLights>()
            .init_resource::<CloudLights>()
            .init_resource::<CloudPassCounters>()
            .init_resource::<cloud::ParticlesValidity>()
            .add_systems(
                PostUpdate,
                (
                    cloud::update_cloud_aabbs
                        .in_set(CloudSystems::CalculateBounds)
                        .in_set(bevy::camera::visibility::VisibilitySystems::CalculateBounds),
                    cloud::validate_changed_particles
                        .in_set(CloudSystems::ValidateParticles)
                        .after(bevy::asset::AssetEventSystems),
                    (
                        shadow_maps::collect_cloud_lights
                            .after(bevy::transform::TransformSystems::Propagate)
                            .after(
                                bevy::camera::visibility::VisibilitySystems::VisibilityPropagate,
                            ),
                        // After every bounds system, not only the clouds': the rest write
                        // other entities' `Aabb`, but unordered they read as ambiguities.
                        shadow_maps::place_cloud_shadow_maps
                            .after(bevy::camera::visibility::VisibilitySystems::CalculateBounds),
                    )
                        .chain(),
                    // The last word on the clouds' visibility: after the lights, which may
                    // mark entities visible, and after Bevy hides what no view saw (both
                    // after Bevy's visibility check).
                    views::hide_clouds_from_other_projections
                        .after(bevy::light::SimulationLightSystems::CheckLightVisibility)
                        .after(
                            bevy::camera::visibility::VisibilitySystems::MarkNewlyHiddenEntitiesInvisible,
                        ),
                    views::warn_of_clamped_target_scales,
                    lod::update_cloud_lod
                        .in_set(CloudSystems::LevelOfDetail)
                        .after(bevy::camera::visibility::VisibilitySystems::CalculateBounds)
                        .after(bevy::transform::TransformSystems::Propagate)
                        .after(bevy::camera::CameraUpdateSystems),
                ),
            );
        render::build(app);
    }

    fn finish(&self, app: &mut App) {
        render::finish(app);
    }
}
