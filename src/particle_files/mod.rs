//! Particle files referenced by scene files (`docs/scene-format.md`): PLY and CSV.
//!
//! * **PLY** — `format ascii 1.0`, `format binary_little_endian 1.0` (and, as a courtesy,
//!   `binary_big_endian`). The `vertex` element must have the scalar properties `x y z radius
//!   density` in any order, of any PLY numeric type; every other property (scalar or list) and
//!   every other element, before or after `vertex`, is skipped.
//! * **CSV** — a header naming the columns `x,y,z,radius,density` in any order (whitespace
//!   around names ignored; other columns are skipped), then one particle per line; blank lines are
//!   ignored. Read and written with the `csv` crate (quoted fields work).
//!
//! Other attribute names (Houdini's `pscale` for the radius, say), defaults for a missing radius or
//! density, and a scale come from [`ParticleAttributes`], the loader's settings.
//!
//! Readers do not validate values (a negative radius is read as written); `scene` (feature `scene`)
//! validates every particle and names it in its error. Errors here name the file and, for text,
//! the 1-based line number (for binary PLY, the vertex index and byte offset).
//!
//! This file holds the errors and the attributes; `ply.rs` the PLY header and writer,
//! `ply_body.rs` the PLY bodies, `csv.rs` the CSV reader and writer.

use std::path::{Path, PathBuf};

use bevy::{
    math::Vec3,
    reflect::{Reflect, std_traits::ReflectDefault},
};
use serde::{Deserialize, Serialize};

use crate::particle::Particle;

mod csv;
mod ply;
mod ply_body;
#[cfg(test)]
mod tests;

pub use csv::{parse_csv, read_csv, write_csv};
pub use ply::{parse_ply, read_ply, write_ply_ascii, write_ply_binary};

/// Why a particle file could not be read or written.
#[derive(Debug, thiserror::Error)]
pub enum ParticleFileError {
    /// The file could not be opened, read or written.
    #[error("cannot access '{}': {source}", path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// The operating system's error.
        #[source]
        source: std::io::Error,
    },
    /// The file's contents do not follow the format. `location` is e.g. `line 12` or
    /// `vertex 3 (byte 245)`.
    #[error("{}: {location}: {message}{}", path.display(), found_suffix(found))]
    Format {
        /// The file.
        path: PathBuf,
        /// Where: `line N` (1-based), `vertex K (byte B)` or `end of file`.
        location: String,
        /// What is wrong and what is allowed. Never holds the file's own text: that is `found`.
        message: String,
        /// The file's own text the message is about (a token, a name or a header line), at
        /// most 60 characters; [`ParticleFileError::detail_without_content`] leaves it out.
        found: Option<String>,
    },
}

/// `; found `text`` after a message, or nothing.
fn found_suffix(found: &Option<String>) -> String {
    found
        .as_ref()
        .map_or(String::new(), |f| format!("; found `{f}`"))
}

/// What is wrong, and the file's own text it is about (shortened for the message).
struct Complaint {
    message: String,
    found: Option<String>,
}

impl Complaint {
    fn new(message: impl Into<String>, found: &str) -> Self {
        Self {
            message: message.into(),
            found: Some(short(found)),
        }
    }
}

impl From<String> for Complaint {
    fn from(message: String) -> Self {
        Self {
            message,
            found: None,
        }
    }
}

impl ParticleFileError {
    /// The error without the file's path (for messages that name the file already).
    pub fn detail(&self) -> String {
        match self {
            ParticleFileError::Format { found, .. } => {
                self.detail_without_content() + &found_suffix(found)
            }
            ParticleFileError::Io { .. } => self.detail_without_content(),
        }
    }

    /// [`detail`](Self::detail) without any of the file's own text: for files named by someone
    /// the reader need not trust (a scene file's particle files), whose text must not reach a
    /// log.
    pub fn detail_without_content(&self) -> String {
        match self {
            ParticleFileError::Io { source, .. } => source.to_string(),
            ParticleFileError::Format {
                location, message, ..
            } => format!("{location}: {message}"),
        }
    }

    fn format(path: &Path, location: impl Into<String>, message: impl Into<String>) -> Self {
        Self::complaint(path, location, message.into().into())
    }

    fn complaint(path: &Path, location: impl Into<String>, complaint: Complaint) -> Self {
        ParticleFileError::Format {
            path: path.to_path_buf(),
            location: location.into(),
            message: complaint.message,
            found: complaint.found,
        }
    }

    fn io(path: &Path, source: std::io::Error) -> Self {
        ParticleFileError::Io {
            path: path.to_path_buf(),
            source,
        }
    }
}

/// How a particle file's attributes become particles: which CSV column or PLY vertex property holds
/// each value, values for attributes the file lacks, and a scale. These are the settings of the
/// `AssetServer` loader (`load_with_settings`, or a `.meta` file); the default reads the names
/// `x y z radius density` in metres.
///
/// ```
/// # use bevy_particle_clouds::particle_files::ParticleAttributes;
/// // Houdini's point attributes, in centimetres, without a density attribute.
/// let houdini = ParticleAttributes {
///     radius: "pscale".into(),
///     default_density: Some(1.0),
///     scale: 0.01,
///     ..Default::default()
/// };
/// # assert_eq!(houdini.names()[3], "pscale");
/// ```
#[derive(Clone, Debug, PartialEq, Reflect, Serialize, Deserialize)]
#[reflect(Default, Debug, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct ParticleAttributes {
    /// Names of the attributes holding the centre's x, y and z (file units). Default `x`, `y`, `z`.
    pub position: [String; 3],
    /// Name of the attribute holding the radius (file units), e.g. Houdini's `pscale`.
    /// Default `radius`.
    pub radius: String,
    /// Name of the attribute holding the dimensionless density. Default `density`.
    pub density: String,
    /// The radius (file units) of every particle when the file has no radius attribute; `None`
    /// (the default) requires the attribute.
    pub default_radius: Option<f32>,
    /// The density of every particle when the file has no density attribute; `None` (the
    /// default) requires the attribute.
    pub default_density: Option<f32>,
    /// Metres per file unit: multiplies positions and radii (0.01 for a file in centimetres).
    /// Finite and `> 0`. Default 1.
    pub scale: f32,
}

impl Default for ParticleAttributes {
    fn default() -> Self {
        Self {
            position: ["x".into(), "y".into(), "z".into()],
            radius: "radius".into(),
            density: "density".into(),
            default_radius: None,
            default_density: None,
            scale: 1.0,
        }
    }
}

impl ParticleAttributes {
    /// The attribute names of `x y z radius density`, in that order.
    pub fn names(&self) -> [&str; 5] {
        let [x, y, z] = &self.position;
        [x, y, z, &self.radius, &self.density]
    }

    /// The value each of `x y z radius density` takes when the file lacks it (`None`: required).
    fn defaults(&self) -> [Option<f64>; 5] {
        let d = |v: Option<f32>| v.map(f64::from);
        [
            None,
            None,
            None,
            d(self.default_radius),
            d(self.default_density),
        ]
    }

    /// The values a particle starts from before its columns are read: the defaults, else 0.
    fn initial_values(&self) -> [f64; 5] {
        self.defaults().map(|d| d.unwrap_or(0.0))
    }

    /// The particle of the values of `x y z radius density`, scaled to metres.
    fn particle(&self, v: [f64; 5]) -> Particle {
        let s = self.scale as f64;
        Particle {
            position: Vec3::new((v[0] * s) as f32, (v[1] * s) as f32, (v[2] * s) as f32),
            radius: (v[3] * s) as f32,
            density: v[4] as f32,
        }
    }

    /// Refuses a scale that is not finite and positive.
    fn check(&self, path: &Path) -> Result<(), ParticleFileError> {
        if self.scale.is_finite() && self.scale > 0.0 {
            return Ok(());
        }
        Err(ParticleFileError::format(
            path,
            "settings",
            format!(
                "ParticleAttributes::scale is {}; it must be finite and > 0",
                self.scale
            ),
        ))
    }

    /// Which of `names` (a CSV header or the vertex properties) holds each of
    /// `x y z radius density` (`usize::MAX` where a default stands in). Names that map to nothing
    /// are ignored. `what` names the file's attributes in messages (`column`, `vertex property`).
    fn columns<'a>(
        &self,
        names: impl IntoIterator<Item = &'a str>,
        what: &str,
    ) -> Result<[usize; 5], Complaint> {
        let wanted = self.names();
        let mut columns = [usize::MAX; 5];
        for (i, name) in names.into_iter().enumerate() {
            for c in (0..5).filter(|&c| wanted[c] == name) {
                if columns[c] != usize::MAX {
                    return Err(Complaint::new(
                        format!("a {what} holding `{}` appears twice", wanted[c]),
                        name,
                    ));
                }
                columns[c] = i;
            }
        }
        let missing: Vec<&str> = (0..5)
            .filter(|&c| columns[c] == usize::MAX && self.defaults()[c].is_none())
            .map(|c| wanted[c])
            .collect();
        if missing.is_empty() {
            return Ok(columns);
        }
        Err(format!(
            "missing {what}{} `{}`; the particles need `{}` (other names or defaults for the radius \
             and density are set with the loader's `ParticleAttributes`)",
            if missing.len() == 1 { "" } else { "s" },
            missing.join("`, `"),
            wanted.join(" ")
        )
        .into())
    }
}

// ---------------------------------------------------------------------------------------------
// PLY
// ---------------------------------------------------------------------------------------------

/// Shortens a line for an error message.
fn short(s: &str) -> String {
    const MAX: usize = 60;
    if s.chars().count() <= MAX {
        s.to_string()
    } else {
        let mut out: String = s.chars().take(MAX).collect();
        out.push('…');
        out
    }
}
