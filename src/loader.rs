//! Loads [`Particles`] from `.ply` and `.csv` files through Bevy's `AssetServer`:
//! `asset_server.load::<Particles>("clouds/cumulus.ply")`. Failures arrive as
//! `AssetLoadFailedEvent<Particles>` with a message naming the file, the line and the problem.
//! A file replaced while the game runs (with Bevy's `file_watcher` feature) is reloaded; a
//! malformed replacement fails the same way and its clouds keep their last good particles.

use bevy::{
    asset::{AssetLoader, LoadContext, io::Reader},
    prelude::*,
};

use crate::{
    cloud::Particles,
    particle_files::{ParticleAttributes, ParticleFileError, parse_csv, parse_ply},
};

/// The asset loader of particle files (PLY with vertex properties `x y z radius density`,
/// ascii or binary; CSV with header `x,y,z,radius,density`). Every particle is validated. Its
/// settings, [`ParticleAttributes`], map other attribute names, give defaults and a scale:
///
/// ```no_run
/// # use bevy::prelude::*;
/// # use bevy_particle_clouds::{Particles, particle_files::ParticleAttributes};
/// # fn load(asset_server: Res<AssetServer>) {
/// let smoke: Handle<Particles> = asset_server
///     .load_builder()
///     .with_settings(|a: &mut ParticleAttributes| {
///         a.radius = "pscale".into();
///         a.default_density = Some(1.0);
///     })
///     .load("smoke.csv");
/// # }
/// ```
#[derive(Default, TypePath)]
pub struct ParticlesLoader;

/// Why a particle file could not be loaded.
#[derive(Debug, thiserror::Error)]
pub enum ParticlesLoadError {
    /// The asset reader failed.
    #[error("cannot read particle file: {0}")]
    Io(#[from] std::io::Error),
    /// The file does not follow the PLY or CSV format; the message names the file and the line
    /// (for binary PLY, the vertex and byte offset).
    #[error(transparent)]
    Format(#[from] ParticleFileError),
    /// The file parsed but a particle is invalid (NaN position, radius <= 0, negative density).
    #[error("particle file '{path}': {error}")]
    Invalid {
        /// The asset path of the file.
        path: String,
        /// Which particle and field.
        error: crate::particle::InvalidMedium,
    },
}

impl AssetLoader for ParticlesLoader {
    type Asset = Particles;
    type Settings = ParticleAttributes;
    type Error = ParticlesLoadError;

    async fn load(
        &self,
        reader: &mut dyn Reader,
        attributes: &ParticleAttributes,
        load_context: &mut LoadContext<'_>,
    ) -> Result<Particles, ParticlesLoadError> {
        let mut bytes = Vec::new();
        reader.read_to_end(&mut bytes).await?;
        let path = load_context.path().path().to_path_buf();
        let is_csv = path
            .extension()
            .is_some_and(|e| e.eq_ignore_ascii_case("csv"));
        let particles = if is_csv {
            parse_csv(&path, &bytes, attributes)?
        } else {
            parse_ply(&path, &bytes, attributes)?
        };
        let particles = Particles::new(particles);
        particles
            .validate()
            .map_err(|error| ParticlesLoadError::Invalid {
                path: path.display().to_string(),
                error,
            })?;
        Ok(particles)
    }

    fn extensions(&self) -> &[&str] {
        &["ply", "csv"]
    }
}
