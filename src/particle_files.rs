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

use std::fmt::Write as _;
use std::io::Write as _;
use std::path::{Path, PathBuf};

use bevy::{
    math::Vec3,
    reflect::{Reflect, std_traits::ReflectDefault},
};
use serde::{Deserialize, Serialize};

use crate::particle::Particle;

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

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum PlyFormat {
    Ascii,
    BinaryLittleEndian,
    BinaryBigEndian,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum ScalarType {
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    F32,
    F64,
}

impl ScalarType {
    fn parse(name: &str) -> Option<Self> {
        Some(match name {
            "char" | "int8" => ScalarType::I8,
            "uchar" | "uint8" => ScalarType::U8,
            "short" | "int16" => ScalarType::I16,
            "ushort" | "uint16" => ScalarType::U16,
            "int" | "int32" => ScalarType::I32,
            "uint" | "uint32" => ScalarType::U32,
            "float" | "float32" => ScalarType::F32,
            "double" | "float64" => ScalarType::F64,
            _ => return None,
        })
    }

    fn size(self) -> usize {
        match self {
            ScalarType::I8 | ScalarType::U8 => 1,
            ScalarType::I16 | ScalarType::U16 => 2,
            ScalarType::I32 | ScalarType::U32 | ScalarType::F32 => 4,
            ScalarType::F64 => 8,
        }
    }

    fn is_integer(self) -> bool {
        !matches!(self, ScalarType::F32 | ScalarType::F64)
    }

    /// Decodes one value from exactly `self.size()` bytes.
    fn decode(self, b: &[u8], little: bool) -> f64 {
        macro_rules! get {
            ($t:ty, $n:expr) => {{
                let a: [u8; $n] = b[..$n].try_into().unwrap();
                if little {
                    <$t>::from_le_bytes(a)
                } else {
                    <$t>::from_be_bytes(a)
                }
            }};
        }
        match self {
            ScalarType::I8 => b[0] as i8 as f64,
            ScalarType::U8 => b[0] as f64,
            ScalarType::I16 => get!(i16, 2) as f64,
            ScalarType::U16 => get!(u16, 2) as f64,
            ScalarType::I32 => get!(i32, 4) as f64,
            ScalarType::U32 => get!(u32, 4) as f64,
            ScalarType::F32 => get!(f32, 4) as f64,
            ScalarType::F64 => get!(f64, 8),
        }
    }
}

#[derive(Clone, Debug)]
enum PropertyKind {
    Scalar(ScalarType),
    List { count: ScalarType, item: ScalarType },
}

#[derive(Clone, Debug)]
struct PlyProperty {
    name: String,
    kind: PropertyKind,
}

#[derive(Clone, Debug)]
struct PlyElement {
    name: String,
    count: usize,
    properties: Vec<PlyProperty>,
}

struct PlyHeader {
    format: PlyFormat,
    elements: Vec<PlyElement>,
    /// Byte offset of the first byte after the `end_header` line.
    body_start: usize,
    /// Number of lines in the header (the body's first line is `header_lines + 1`).
    header_lines: usize,
}

fn parse_ply_header(path: &Path, bytes: &[u8]) -> Result<PlyHeader, ParticleFileError> {
    let mut pos = 0usize;
    let mut line_no = 0usize;
    let mut format = None;
    let mut elements: Vec<PlyElement> = Vec::new();
    loop {
        if pos >= bytes.len() {
            return Err(ParticleFileError::format(
                path,
                format!("line {}", line_no + 1),
                "the header ends without an `end_header` line",
            ));
        }
        let end = bytes[pos..]
            .iter()
            .position(|&b| b == b'\n')
            .map_or(bytes.len(), |i| pos + i);
        let raw = &bytes[pos..end];
        pos = (end + 1).min(bytes.len().max(end + 1));
        line_no += 1;
        let at = format!("line {line_no}");
        let line = std::str::from_utf8(raw)
            .map_err(|_| ParticleFileError::format(path, &at, "the header is not valid text"))?;
        let line = line.trim_end_matches('\r');
        let mut words = line.split_whitespace();
        let keyword = words.next().unwrap_or("");
        if line_no == 1 {
            if line.trim() != "ply" {
                return Err(ParticleFileError::complaint(
                    path,
                    &at,
                    Complaint::new("the file must start with the line `ply`", line),
                ));
            }
            continue;
        }
        let rest: Vec<&str> = words.collect();
        let bad_line = |complaint: Complaint| ParticleFileError::complaint(path, &at, complaint);
        match keyword {
            "" | "comment" | "obj_info" => {}
            "format" => format = Some(ply_format(&rest, line).map_err(bad_line)?),
            "element" => elements.push(ply_element(&rest, line).map_err(bad_line)?),
            "property" => {
                let Some(element) = elements.last_mut() else {
                    return Err(bad_line(
                        "`property` before any `element`".to_string().into(),
                    ));
                };
                element
                    .properties
                    .push(ply_property(&rest, line).map_err(bad_line)?);
            }
            "end_header" => {
                let format = format.ok_or_else(|| {
                    ParticleFileError::format(path, &at, "the header has no `format` line")
                })?;
                return Ok(PlyHeader {
                    format,
                    elements,
                    body_start: pos.min(bytes.len()),
                    header_lines: line_no,
                });
            }
            other => {
                return Err(ParticleFileError::complaint(
                    path,
                    &at,
                    Complaint::new(
                        "unknown header keyword; allowed are comment obj_info format element \
                         property end_header",
                        other,
                    ),
                ));
            }
        }
    }
}

/// A `format` line's format (`rest`: its words after the keyword), or why not.
fn ply_format(rest: &[&str], line: &str) -> Result<PlyFormat, Complaint> {
    let format = match rest.first().copied() {
        Some("ascii") => PlyFormat::Ascii,
        Some("binary_little_endian") => PlyFormat::BinaryLittleEndian,
        Some("binary_big_endian") => PlyFormat::BinaryBigEndian,
        other => {
            return Err(Complaint::new(
                "unknown format; allowed are `ascii`, `binary_little_endian` and \
                 `binary_big_endian`",
                other.unwrap_or(""),
            ));
        }
    };
    if rest.get(1).copied() != Some("1.0") || rest.len() != 2 {
        return Err(Complaint::new(
            format!("expected `format {} 1.0`", rest[0]),
            line,
        ));
    }
    Ok(format)
}

/// An `element <name> <count>` line's element, without properties yet, or why not.
fn ply_element(rest: &[&str], line: &str) -> Result<PlyElement, Complaint> {
    let [name, count] = rest else {
        return Err(Complaint::new("expected `element <name> <count>`", line));
    };
    let count = count
        .parse::<usize>()
        .map_err(|_| Complaint::new("an element's count must be an integer >= 0", count))?;
    Ok(PlyElement {
        name: name.to_string(),
        count,
        properties: Vec::new(),
    })
}

/// A `property <type> <name>` or `property list <type> <type> <name>` line's property, or why
/// not.
fn ply_property(rest: &[&str], line: &str) -> Result<PlyProperty, Complaint> {
    let scalar = |t: &str| {
        ScalarType::parse(t).ok_or_else(|| {
            Complaint::new(
                "unknown property type; allowed are char uchar short ushort int uint float double \
                 (or int8 uint8 int16 uint16 int32 uint32 float32 float64)",
                t,
            )
        })
    };
    match rest {
        ["list", count, item, name] => {
            let (count, item) = (scalar(count)?, scalar(item)?);
            if !count.is_integer() {
                return Err(Complaint::new(
                    "a list property has a non-integer count type",
                    name,
                ));
            }
            Ok(PlyProperty {
                name: name.to_string(),
                kind: PropertyKind::List { count, item },
            })
        }
        [ty, name] => Ok(PlyProperty {
            name: name.to_string(),
            kind: PropertyKind::Scalar(scalar(ty)?),
        }),
        _ => Err(Complaint::new(
            "expected `property <type> <name>` or `property list <type> <type> <name>`",
            line,
        )),
    }
}

/// How a message names vertex property `pi`: by the attribute it holds (`` `radius` ``), else by
/// its 1-based place (a name from the file is its text, which messages leave out).
fn property_label(attributes: &ParticleAttributes, columns: &[usize; 5], pi: usize) -> String {
    match columns.iter().position(|&c| c == pi) {
        Some(c) => format!("`{}`", attributes.names()[c]),
        None => format!("{}", pi + 1),
    }
}

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

/// For the vertex element: which property holds each of `x y z radius density`.
fn vertex_columns(
    path: &Path,
    vertex: &PlyElement,
    attributes: &ParticleAttributes,
) -> Result<[usize; 5], ParticleFileError> {
    let names = vertex.properties.iter().map(|p| p.name.as_str());
    let columns = attributes
        .columns(names, "vertex property")
        .map_err(|complaint| ParticleFileError::complaint(path, "header", complaint))?;
    for &c in columns.iter().filter(|&&c| c != usize::MAX) {
        let property = &vertex.properties[c];
        if matches!(property.kind, PropertyKind::List { .. }) {
            return Err(ParticleFileError::format(
                path,
                "header",
                format!(
                    "vertex property `{}` is a list; it must be a number",
                    property.name
                ),
            ));
        }
    }
    Ok(columns)
}

/// Reads the particles of a PLY file (see the module documentation).
pub fn read_ply(path: &Path) -> Result<Vec<Particle>, ParticleFileError> {
    let bytes = std::fs::read(path).map_err(|e| ParticleFileError::io(path, e))?;
    parse_ply(path, &bytes, &ParticleAttributes::default())
}

/// Parses PLY bytes into particles through `attributes`; `path` is only used in error messages.
pub fn parse_ply(
    path: &Path,
    bytes: &[u8],
    attributes: &ParticleAttributes,
) -> Result<Vec<Particle>, ParticleFileError> {
    attributes.check(path)?;
    let header = parse_ply_header(path, bytes)?;
    let Some(vertex_index) = header.elements.iter().position(|e| e.name == "vertex") else {
        return Err(ParticleFileError::format(
            path,
            "header",
            "the file has no `element vertex`",
        ));
    };
    let vertex = &header.elements[vertex_index];
    let columns = vertex_columns(path, vertex, attributes)?;
    let body = &bytes[header.body_start..];
    let vertices = Vertices {
        header: &header,
        index: vertex_index,
        columns,
        attributes,
    };
    match header.format {
        PlyFormat::Ascii => read_ply_ascii_body(path, &vertices, body),
        PlyFormat::BinaryLittleEndian => read_ply_binary_body(path, &vertices, body, true),
        PlyFormat::BinaryBigEndian => read_ply_binary_body(path, &vertices, body, false),
    }
}

/// What the body readers need to know about the vertices.
struct Vertices<'a> {
    header: &'a PlyHeader,
    /// Index of the `vertex` element.
    index: usize,
    /// Which property holds each of `x y z radius density` (`usize::MAX`: a default).
    columns: [usize; 5],
    attributes: &'a ParticleAttributes,
}

fn read_ply_ascii_body(
    path: &Path,
    vertices: &Vertices,
    body: &[u8],
) -> Result<Vec<Particle>, ParticleFileError> {
    let Vertices {
        header,
        index: vertex_index,
        columns,
        attributes,
    } = *vertices;
    let text = std::str::from_utf8(body).map_err(|e| {
        ParticleFileError::format(path, "body", format!("an ascii PLY body must be text: {e}"))
    })?;
    // Each element instance is one non-blank line.
    let mut lines = text
        .lines()
        .enumerate()
        .map(|(i, l)| (i + header.header_lines + 1, l))
        .filter(|(_, l)| !l.trim().is_empty());
    // Skip the instances of elements before `vertex`.
    for element in &header.elements[..vertex_index] {
        for k in 0..element.count {
            if lines.next().is_none() {
                return Err(ParticleFileError::complaint(
                    path,
                    "end of file",
                    Complaint::new(
                        format!(
                            "an element before `vertex` declares {} items but the file ends after {k}",
                            element.count
                        ),
                        &element.name,
                    ),
                ));
            }
        }
    }
    let vertex = &header.elements[vertex_index];
    let label = |pi: usize| property_label(attributes, &columns, pi);
    // Reserve no more than the text can hold (a vertex line takes at least 2 bytes), whatever the
    // header claims.
    let mut particles = Vec::with_capacity(vertex.count.min(text.len() / 2 + 1));
    for k in 0..vertex.count {
        let Some((line_no, line)) = lines.next() else {
            return Err(ParticleFileError::format(
                path,
                "end of file",
                format!(
                    "element `vertex` declares {} vertices but the file ends after {k}",
                    vertex.count
                ),
            ));
        };
        let at = format!("line {line_no}");
        let mut tokens = line.split_whitespace();
        let mut values = attributes.initial_values();
        for (pi, property) in vertex.properties.iter().enumerate() {
            let mut next = || -> Result<f64, ParticleFileError> {
                let token = tokens.next().ok_or_else(|| {
                    ParticleFileError::format(
                        path,
                        &at,
                        format!("vertex {k}: the line ends before property {}", label(pi)),
                    )
                })?;
                token.parse::<f64>().map_err(|_| {
                    ParticleFileError::complaint(
                        path,
                        &at,
                        Complaint::new(
                            format!("vertex {k}: property {} is not a number", label(pi)),
                            token,
                        ),
                    )
                })
            };
            match property.kind {
                PropertyKind::Scalar(_) => {
                    let v = next()?;
                    if let Some(c) = columns.iter().position(|&c| c == pi) {
                        values[c] = v;
                    }
                }
                PropertyKind::List { .. } => {
                    let n = next()?;
                    if !(n >= 0.0 && n.fract() == 0.0) {
                        return Err(ParticleFileError::format(
                            path,
                            &at,
                            format!(
                                "vertex {k}: the list of property {} has count {n}; it must be \
                                 an integer >= 0",
                                label(pi)
                            ),
                        ));
                    }
                    for _ in 0..n as usize {
                        next()?;
                    }
                }
            }
        }
        if let Some(extra) = tokens.next() {
            return Err(ParticleFileError::complaint(
                path,
                &at,
                Complaint::new(
                    format!(
                        "vertex {k}: unexpected value after the {} declared properties",
                        vertex.properties.len()
                    ),
                    extra,
                ),
            ));
        }
        particles.push(attributes.particle(values));
    }
    Ok(particles)
}

fn read_ply_binary_body(
    path: &Path,
    vertices: &Vertices,
    body: &[u8],
    little: bool,
) -> Result<Vec<Particle>, ParticleFileError> {
    let Vertices {
        header,
        index: vertex_index,
        columns,
        attributes,
    } = *vertices;
    let body_offset = header.body_start;
    let mut pos = 0usize;
    // Reads one scalar at `pos`, or explains where the file ended.
    let read = |pos: &mut usize,
                ty: ScalarType,
                what: &dyn Fn() -> String|
     -> Result<f64, ParticleFileError> {
        let n = ty.size();
        if *pos + n > body.len() {
            return Err(ParticleFileError::format(
                path,
                format!("{} (byte {})", what(), body_offset + *pos),
                "the file ends early",
            ));
        }
        let v = ty.decode(&body[*pos..*pos + n], little);
        *pos += n;
        Ok(v)
    };
    for element in &header.elements[..vertex_index] {
        let fixed: Option<usize> = element
            .properties
            .iter()
            .map(|p| match p.kind {
                PropertyKind::Scalar(t) => Some(t.size()),
                PropertyKind::List { .. } => None,
            })
            .sum();
        match fixed {
            Some(size) => {
                let total = size.saturating_mul(element.count);
                if pos.saturating_add(total) > body.len() {
                    return Err(ParticleFileError::complaint(
                        path,
                        format!("byte {}", body_offset + pos),
                        Complaint::new(
                            format!(
                                "the file ends before the {} items of an element before `vertex`",
                                element.count
                            ),
                            &element.name,
                        ),
                    ));
                }
                pos += total;
            }
            None => {
                for k in 0..element.count {
                    for p in &element.properties {
                        let what = || format!("item {k} of an element before `vertex`");
                        match p.kind {
                            PropertyKind::Scalar(t) => {
                                read(&mut pos, t, &what)?;
                            }
                            PropertyKind::List { count, item } => {
                                let n = read(&mut pos, count, &what)?;
                                if n < 0.0 {
                                    return Err(ParticleFileError::format(
                                        path,
                                        format!("{} (byte {})", what(), body_offset + pos),
                                        format!("a list has negative count {n}"),
                                    ));
                                }
                                let skip = (n as usize).saturating_mul(item.size());
                                if pos.saturating_add(skip) > body.len() {
                                    return Err(ParticleFileError::format(
                                        path,
                                        format!("{} (byte {})", what(), body_offset + pos),
                                        "the file ends early",
                                    ));
                                }
                                pos += skip;
                            }
                        }
                    }
                }
            }
        }
    }
    let vertex = &header.elements[vertex_index];
    let mut particles = Vec::with_capacity(vertex.count.min(body.len() / 5 + 1));
    for k in 0..vertex.count {
        let what = || format!("vertex {k}");
        let mut values = attributes.initial_values();
        for (pi, property) in vertex.properties.iter().enumerate() {
            match property.kind {
                PropertyKind::Scalar(t) => {
                    let v = read(&mut pos, t, &what)?;
                    if let Some(c) = columns.iter().position(|&c| c == pi) {
                        values[c] = v;
                    }
                }
                PropertyKind::List { count, item } => {
                    let n = read(&mut pos, count, &what)?;
                    let skip = (n.max(0.0) as usize).saturating_mul(item.size());
                    if n < 0.0 || pos.saturating_add(skip) > body.len() {
                        return Err(ParticleFileError::format(
                            path,
                            format!("vertex {k} (byte {})", body_offset + pos),
                            format!(
                                "the list of property {} with count {n} does not fit in the file",
                                property_label(attributes, &columns, pi)
                            ),
                        ));
                    }
                    pos += skip;
                }
            }
        }
        particles.push(attributes.particle(values));
    }
    // Elements after the vertices are ignored.
    Ok(particles)
}

/// Writes particles as a binary little-endian PLY with float properties `x y z radius density`.
pub fn write_ply_binary(path: &Path, particles: &[Particle]) -> Result<(), ParticleFileError> {
    let mut out = Vec::with_capacity(200 + particles.len() * 20);
    write!(
        out,
        "ply\nformat binary_little_endian 1.0\ncomment bevy_particle_clouds particles\nelement vertex {}\n\
         property float x\nproperty float y\nproperty float z\nproperty float radius\nproperty float density\n\
         end_header\n",
        particles.len()
    )
    .unwrap();
    for p in particles {
        for v in [
            p.position.x,
            p.position.y,
            p.position.z,
            p.radius,
            p.density,
        ] {
            out.extend_from_slice(&v.to_le_bytes());
        }
    }
    std::fs::write(path, out).map_err(|e| ParticleFileError::io(path, e))
}

/// Writes particles as an ascii PLY with float properties `x y z radius density`
/// (values round-trip exactly: Rust prints the shortest decimal that parses back to the same f32).
pub fn write_ply_ascii(path: &Path, particles: &[Particle]) -> Result<(), ParticleFileError> {
    let mut out = String::with_capacity(200 + particles.len() * 40);
    write!(
        out,
        "ply\nformat ascii 1.0\ncomment bevy_particle_clouds particles\nelement vertex {}\n\
         property float x\nproperty float y\nproperty float z\nproperty float radius\nproperty float density\n\
         end_header\n",
        particles.len()
    )
    .unwrap();
    for p in particles {
        writeln!(
            out,
            "{} {} {} {} {}",
            p.position.x, p.position.y, p.position.z, p.radius, p.density
        )
        .unwrap();
    }
    std::fs::write(path, out).map_err(|e| ParticleFileError::io(path, e))
}

// ---------------------------------------------------------------------------------------------
// CSV
// ---------------------------------------------------------------------------------------------

/// Reads the particles of a CSV file (see the module documentation).
pub fn read_csv(path: &Path) -> Result<Vec<Particle>, ParticleFileError> {
    let bytes = std::fs::read(path).map_err(|e| ParticleFileError::io(path, e))?;
    parse_csv(path, &bytes, &ParticleAttributes::default())
}

/// Parses CSV bytes into particles through `attributes`; `path` is only used in error messages.
pub fn parse_csv(
    path: &Path,
    bytes: &[u8],
    attributes: &ParticleAttributes,
) -> Result<Vec<Particle>, ParticleFileError> {
    attributes.check(path)?;
    let bytes = bytes.strip_prefix("\u{feff}".as_bytes()).unwrap_or(bytes);
    let mut reader = csv::ReaderBuilder::new()
        .has_headers(false)
        .flexible(true)
        .trim(csv::Trim::All)
        .from_reader(bytes);
    // The 1-based line where a record starts, counted only for a message: counting it for every
    // record would scan the file once per line. The csv crate's own line count skips blank lines,
    // and its byte offset may point at the blank lines before the record.
    let line_of = |byte: u64| {
        let mut start = (byte as usize).min(bytes.len());
        while bytes.get(start).is_some_and(|b| matches!(b, b'\n' | b'\r')) {
            start += 1;
        }
        1 + bytes[..start].iter().filter(|&&b| b == b'\n').count()
    };
    // Records with the byte where they start, blank (or whitespace-only) lines skipped.
    let mut records = reader.records().filter_map(|record| match record {
        Ok(r) if r.iter().all(str::is_empty) => None,
        Ok(r) => Some(Ok((r.position().map_or(0, csv::Position::byte), r))),
        Err(e) => Some(Err(e)),
    });
    let csv_error = |e: csv::Error| {
        let at = e
            .position()
            .map_or("file".to_owned(), |p| format!("line {}", line_of(p.byte())));
        ParticleFileError::format(path, at, e.to_string())
    };
    let Some(header) = records.next().transpose().map_err(csv_error)? else {
        return Err(ParticleFileError::format(
            path,
            "line 1",
            format!(
                "the file is empty; it needs a header naming the columns `{}`",
                attributes.names().join(",")
            ),
        ));
    };
    let (header_byte, header) = header;
    let columns = attributes
        .columns(header.iter(), "column")
        .map_err(|complaint| {
            ParticleFileError::complaint(path, format!("line {}", line_of(header_byte)), complaint)
        })?;
    let names = attributes.names();
    let mut particles = Vec::new();
    for record in records {
        let (byte, record) = record.map_err(csv_error)?;
        let at = || format!("line {}", line_of(byte));
        if record.len() != header.len() {
            return Err(ParticleFileError::format(
                path,
                at(),
                format!(
                    "expected {} comma-separated values (the header's columns), found {}",
                    header.len(),
                    record.len()
                ),
            ));
        }
        let mut values = attributes.initial_values();
        for (c, &i) in columns
            .iter()
            .enumerate()
            .filter(|(_, i)| **i != usize::MAX)
        {
            values[c] = record[i].parse::<f64>().map_err(|_| {
                let complaint =
                    Complaint::new(format!("column `{}` is not a number", names[c]), &record[i]);
                ParticleFileError::complaint(path, at(), complaint)
            })?;
        }
        particles.push(attributes.particle(values));
    }
    Ok(particles)
}

/// Writes particles as CSV with the header `x,y,z,radius,density` (values round-trip exactly).
pub fn write_csv(path: &Path, particles: &[Particle]) -> Result<(), ParticleFileError> {
    let csv_error = |e: csv::Error| ParticleFileError::io(path, e.into());
    let mut writer = csv::Writer::from_path(path).map_err(csv_error)?;
    let header = ParticleAttributes::default();
    writer.write_record(header.names()).map_err(csv_error)?;
    for p in particles {
        // Rust's float formatting is the shortest that round-trips.
        let [x, y, z] = p.position.to_array();
        writer
            .write_record([x, y, z, p.radius, p.density].map(|v| v.to_string()))
            .map_err(csv_error)?;
    }
    writer.flush().map_err(|e| ParticleFileError::io(path, e))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tmp_dir(name: &str) -> PathBuf {
        let dir =
            std::env::temp_dir().join(format!("bpc_particle_files_{}_{name}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        dir
    }

    fn sample() -> Vec<Particle> {
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
                position: Vec3::new(1e-7, -123.456, 3.0e5),
                radius: 1.0 / 3.0,
                density: 0.0,
            },
        ]
    }

    #[test]
    fn ply_binary_round_trip() {
        let dir = tmp_dir("ply_bin");
        let path = dir.join("p.ply");
        write_ply_binary(&path, &sample()).unwrap();
        assert_eq!(read_ply(&path).unwrap(), sample());
        write_ply_binary(&path, &[]).unwrap();
        assert_eq!(read_ply(&path).unwrap(), vec![]);
    }

    #[test]
    fn ply_ascii_round_trip() {
        let dir = tmp_dir("ply_ascii");
        let path = dir.join("p.ply");
        write_ply_ascii(&path, &sample()).unwrap();
        assert_eq!(read_ply(&path).unwrap(), sample());
    }

    #[test]
    fn csv_round_trip() {
        let dir = tmp_dir("csv");
        let path = dir.join("p.csv");
        write_csv(&path, &sample()).unwrap();
        assert_eq!(read_csv(&path).unwrap(), sample());
    }

    #[test]
    fn ply_ascii_any_order_types_extra_properties_and_elements() {
        let text = "ply\r\nformat ascii 1.0\r\ncomment hi\r\nelement camera 1\r\nproperty float fov\r\n\
                    element vertex 2\r\nproperty double density\r\nproperty uchar red\r\nproperty int x\r\n\
                    property list uchar int idx\r\nproperty float y\r\nproperty float z\r\nproperty float radius\r\n\
                    element face 1\r\nproperty list uchar int vertex_indices\r\nend_header\r\n\
                    45\r\n0.5 255 1 3 7 8 9 2 3 0.25\r\n\r\n1 0 -2 0 0.5 0.5 1\r\n3 0 1 1\r\n";
        let p = parse_ply(
            Path::new("t.ply"),
            text.as_bytes(),
            &ParticleAttributes::default(),
        )
        .unwrap();
        assert_eq!(
            p,
            vec![
                Particle {
                    position: Vec3::new(1.0, 2.0, 3.0),
                    radius: 0.25,
                    density: 0.5
                },
                Particle {
                    position: Vec3::new(-2.0, 0.5, 0.5),
                    radius: 1.0,
                    density: 1.0
                },
            ]
        );
    }

    #[test]
    fn ply_binary_mixed_types_and_preceding_elements() {
        let mut b = Vec::new();
        b.extend_from_slice(
            b"ply\nformat binary_little_endian 1.0\nelement meta 2\nproperty list uchar ushort ids\nproperty short s\n\
              element vertex 2\nproperty uchar r\nproperty double x\nproperty float y\nproperty int z\n\
              property list uint uchar tags\nproperty float radius\nproperty ushort density\n\
              element face 1\nproperty list uchar int vertex_indices\nend_header\n",
        );
        // meta: [count 1: 7] s=-1 ; [count 0] s=2
        b.extend_from_slice(&[1, 7, 0]);
        b.extend_from_slice(&(-1i16).to_le_bytes());
        b.push(0);
        b.extend_from_slice(&2i16.to_le_bytes());
        for (i, (x, y, z, r, d)) in [
            (0.5f64, -1.5f32, 4i32, 0.125f32, 3u16),
            (2.0, 0.0, -7, 2.0, 0),
        ]
        .iter()
        .enumerate()
        {
            b.push(200);
            b.extend_from_slice(&x.to_le_bytes());
            b.extend_from_slice(&y.to_le_bytes());
            b.extend_from_slice(&z.to_le_bytes());
            b.extend_from_slice(&(i as u32).to_le_bytes());
            b.extend(std::iter::repeat_n(9u8, i));
            b.extend_from_slice(&r.to_le_bytes());
            b.extend_from_slice(&d.to_le_bytes());
        }
        b.extend_from_slice(&[3, 0, 0, 0, 0]); // truncated face: ignored
        let p = parse_ply(Path::new("t.ply"), &b, &ParticleAttributes::default()).unwrap();
        assert_eq!(
            p,
            vec![
                Particle {
                    position: Vec3::new(0.5, -1.5, 4.0),
                    radius: 0.125,
                    density: 3.0
                },
                Particle {
                    position: Vec3::new(2.0, 0.0, -7.0),
                    radius: 2.0,
                    density: 0.0
                },
            ]
        );
    }

    fn err(text: &str) -> String {
        parse_ply(
            Path::new("c.ply"),
            text.as_bytes(),
            &ParticleAttributes::default(),
        )
        .unwrap_err()
        .to_string()
    }

    #[test]
    fn ply_errors_name_file_and_line() {
        let head = "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\n\
                    property float radius\nproperty float density\nend_header\n";
        let e = err(&format!("{head}0 0 0 1 1\n0 0 zz 1 1\n"));
        assert!(
            e.contains("c.ply: line 11") && e.contains("`z`") && e.contains("zz"),
            "{e}"
        );
        let e = err(&format!("{head}0 0 0 1 1\n0 0 1\n"));
        assert!(e.contains("line 11") && e.contains("`radius`"), "{e}");
        let e = err(&format!("{head}0 0 0 1 1 5\n"));
        assert!(
            e.contains("line 10") && e.contains("unexpected value") && e.contains("found `5`"),
            "{e}"
        );
        let e = err(&format!("{head}0 0 0 1 1\n"));
        assert!(
            e.contains("declares 2 vertices") && e.contains("after 1"),
            "{e}"
        );
        let e = err(
            "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nend_header\n1 2\n",
        );
        assert!(e.contains("`z`, `radius`, `density`"), "{e}");
        let e = err("ply\nformat ascii 2.0\n");
        assert!(
            e.contains("line 2") && e.contains("format ascii 1.0"),
            "{e}"
        );
        let e = err("ply\nformat ascii 1.0\nelement vertex 1\nproperty float128 x\n");
        assert!(e.contains("line 4") && e.contains("float128"), "{e}");
        let e = err("plyx\n");
        assert!(e.contains("line 1") && e.contains("`ply`"), "{e}");
        // Each header line names what it expected and what it found.
        for (header, line, expected) in [
            ("format ascii_le 1.0", 2, "unknown format; allowed are"),
            ("format ascii_le 1.0", 2, "found `ascii_le`"),
            (
                "element vertex -1",
                2,
                "count must be an integer >= 0; found `-1`",
            ),
            ("element vertex", 2, "expected `element <name> <count>`"),
            ("property float x", 2, "`property` before any `element`"),
            (
                "element v 1\nproperty list float int v",
                3,
                "non-integer count type",
            ),
            (
                "element v 1\nproperty float",
                3,
                "expected `property <type> <name>`",
            ),
        ] {
            let e = err(&format!("ply\n{header}\nend_header\n"));
            assert!(
                e.contains(&format!("line {line}")) && e.contains(expected),
                "{e}"
            );
        }
        let e = err("ply\nformat ascii 1.0\nelement vertex 1\n");
        assert!(e.contains("end_header"), "{e}");
        let e =
            err("ply\nformat ascii 1.0\nelement face 1\nproperty list uchar int v\nend_header\n");
        assert!(e.contains("no `element vertex`"), "{e}");
        let e = err(
            "ply\nformat binary_little_endian 1.0\nelement vertex 2\nproperty float x\nproperty float y\n\
                     property float z\nproperty float radius\nproperty float density\nend_header\n\0\0\0\0",
        );
        assert!(e.contains("vertex 0") && e.contains("ends early"), "{e}");
    }

    #[test]
    fn csv_any_column_order_whitespace_blank_lines() {
        let text = "\n density , radius,x,y , z\n\n1, 0.5, 1, 2, 3\n  \n0,2,-1,-2,-3\n";
        let p = parse_csv(
            Path::new("t.csv"),
            text.as_bytes(),
            &ParticleAttributes::default(),
        )
        .unwrap();
        assert_eq!(
            p,
            vec![
                Particle {
                    position: Vec3::new(1.0, 2.0, 3.0),
                    radius: 0.5,
                    density: 1.0
                },
                Particle {
                    position: Vec3::new(-1.0, -2.0, -3.0),
                    radius: 2.0,
                    density: 0.0
                },
            ]
        );
        assert_eq!(
            parse_csv(
                Path::new("t.csv"),
                "x,y,z,radius,density\n".as_bytes(),
                &ParticleAttributes::default()
            )
            .unwrap(),
            vec![]
        );
    }

    #[test]
    fn csv_errors_name_file_line_and_column() {
        let e = |t: &str| {
            parse_csv(
                Path::new("c.csv"),
                t.as_bytes(),
                &ParticleAttributes::default(),
            )
            .unwrap_err()
            .to_string()
        };
        let m = e("x,y,z,radius,density\n1,2,3,4,5\n\n1,2,3,abc,5\n");
        assert!(
            m.contains("c.csv: line 4") && m.contains("column `radius`") && m.contains("abc"),
            "{m}"
        );
        let m = e("x,y,z,radius,density\n1,2,3,4\n");
        assert!(
            m.contains("line 2") && m.contains("expected 5") && m.contains("found 4"),
            "{m}"
        );
        let m = e("x,y,z,radius,dens\n");
        assert!(
            m.contains("line 1") && m.contains("missing column `density`"),
            "{m}"
        );
        let m = e("x,y,z,radius\n");
        assert!(
            m.contains("line 1") && m.contains("missing column `density`"),
            "{m}"
        );
        let m = e("x,y,z,radius,density,x\n");
        assert!(m.contains("holding `x` appears twice"), "{m}");
        let m = e("");
        assert!(m.contains("empty"), "{m}");
    }

    /// A file that is not particles (a password file, say) is refused without a word of its text
    /// in the content-free detail, while the full message quotes what it found.
    #[test]
    fn content_free_details_hold_none_of_the_file() {
        let secret = "root:x:0:0:secret:/root:/bin/bash\nsecret2,secret3\n";
        let csv_header = "x,y,z,radius,density\n0,0,secret,1,1\n";
        let ply_token = "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\n\
                         property float z\nproperty float radius\nproperty float density\n\
                         end_header\n0 0 0 1 secret\n";
        let ply_names = "ply\nformat ascii 1.0\nelement secret 1\nproperty secret secret\n";
        let attributes = ParticleAttributes::default();
        // (the error, whether its full message quotes the file)
        let errors = [
            (
                parse_ply(Path::new("p.ply"), secret.as_bytes(), &attributes),
                true,
            ),
            (
                parse_csv(Path::new("p.csv"), secret.as_bytes(), &attributes),
                false,
            ),
            (
                parse_csv(Path::new("p.csv"), csv_header.as_bytes(), &attributes),
                true,
            ),
            (
                parse_ply(Path::new("p.ply"), ply_token.as_bytes(), &attributes),
                true,
            ),
            (
                parse_ply(Path::new("p.ply"), ply_names.as_bytes(), &attributes),
                true,
            ),
        ];
        for (error, quotes) in errors {
            let error = error.unwrap_err();
            let (full, free) = (error.to_string(), error.detail_without_content());
            assert_eq!(full.contains("secret"), quotes, "{full}");
            assert!(!free.contains("secret"), "{free}");
            assert!(free.contains("line"), "the location stays: {free}");
        }
    }

    #[test]
    fn missing_file_names_the_path() {
        let path = tmp_dir("missing").join("nope.ply");
        let e = read_ply(&path).unwrap_err().to_string();
        assert!(e.contains(&path.display().to_string()), "{e}");
        let e = read_csv(&path.with_extension("csv"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("nope.csv"), "{e}");
    }

    #[test]
    fn csv_skips_extra_columns_and_reads_quoted_fields() {
        let text = "id,x,y,z,radius,density,name\n7,1,2,3,0.5,1,\"puff, big\"\n";
        let p = parse_csv(
            Path::new("e.csv"),
            text.as_bytes(),
            &ParticleAttributes::default(),
        );
        assert_eq!(
            p.unwrap(),
            vec![Particle {
                position: Vec3::new(1.0, 2.0, 3.0),
                radius: 0.5,
                density: 1.0
            }]
        );
    }

    #[test]
    fn attributes_map_names_fill_defaults_and_scale() {
        let houdini = ParticleAttributes {
            radius: "pscale".into(),
            default_density: Some(0.5),
            scale: 0.01,
            ..Default::default()
        };
        let expected = [Particle {
            position: Vec3::new(0.01, 0.02, 0.03),
            radius: 0.2,
            density: 0.5,
        }];
        let csv = "x,y,z,pscale\n1,2,3,20\n";
        let close = |got: Vec<Particle>| {
            got.len() == 1
                && (got[0].position - expected[0].position).length() < 1e-6
                && (got[0].radius - expected[0].radius).abs() < 1e-6
                && got[0].density == expected[0].density
        };
        assert!(close(
            parse_csv(Path::new("h.csv"), csv.as_bytes(), &houdini).unwrap()
        ));
        let ply = "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\n\
                   property float z\nproperty float pscale\nend_header\n1 2 3 20\n";
        assert!(close(
            parse_ply(Path::new("h.ply"), ply.as_bytes(), &houdini).unwrap()
        ));
        // Without the default, the density is required, and the message says how to map it.
        let strict = ParticleAttributes {
            default_density: None,
            ..houdini.clone()
        };
        let e = parse_csv(Path::new("h.csv"), csv.as_bytes(), &strict)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("missing column `density`") && e.contains("ParticleAttributes"),
            "{e}"
        );
        let e = parse_ply(Path::new("h.ply"), ply.as_bytes(), &strict)
            .unwrap_err()
            .to_string();
        assert!(e.contains("missing vertex property `density`"), "{e}");
        let bad = ParticleAttributes {
            scale: 0.0,
            ..houdini
        };
        let e = parse_csv(Path::new("h.csv"), csv.as_bytes(), &bad)
            .unwrap_err()
            .to_string();
        assert!(e.contains("scale is 0") && e.contains("> 0"), "{e}");
    }
}
