//! PLY files (ascii, binary little- and big-endian): the header, and writing.

use std::fmt::Write as _;
use std::io::Write as _;
use std::path::Path;

use super::ply_body::*;
use super::*;
use crate::particle::Particle;

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum PlyFormat {
    Ascii,
    BinaryLittleEndian,
    BinaryBigEndian,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum ScalarType {
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
    pub(super) fn parse(name: &str) -> Option<Self> {
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

    pub(super) fn size(self) -> usize {
        match self {
            ScalarType::I8 | ScalarType::U8 => 1,
            ScalarType::I16 | ScalarType::U16 => 2,
            ScalarType::I32 | ScalarType::U32 | ScalarType::F32 => 4,
            ScalarType::F64 => 8,
        }
    }

    pub(super) fn is_integer(self) -> bool {
        !matches!(self, ScalarType::F32 | ScalarType::F64)
    }

    /// Decodes one value from exactly `self.size()` bytes.
    pub(super) fn decode(self, b: &[u8], little: bool) -> f64 {
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
pub(super) enum PropertyKind {
    Scalar(ScalarType),
    List { count: ScalarType, item: ScalarType },
}

#[derive(Clone, Debug)]
pub(super) struct PlyProperty {
    pub(super) name: String,
    pub(super) kind: PropertyKind,
}

#[derive(Clone, Debug)]
pub(super) struct PlyElement {
    pub(super) name: String,
    pub(super) count: usize,
    pub(super) properties: Vec<PlyProperty>,
}

pub(super) struct PlyHeader {
    pub(super) format: PlyFormat,
    pub(super) elements: Vec<PlyElement>,
    /// Byte offset of the first byte after the `end_header` line.
    pub(super) body_start: usize,
    /// Number of lines in the header (the body's first line is `header_lines + 1`).
    pub(super) header_lines: usize,
}

pub(super) fn parse_ply_header(path: &Path, bytes: &[u8]) -> Result<PlyHeader, ParticleFileError> {
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
pub(super) fn ply_format(rest: &[&str], line: &str) -> Result<PlyFormat, Complaint> {
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
pub(super) fn ply_element(rest: &[&str], line: &str) -> Result<PlyElement, Complaint> {
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
pub(super) fn ply_property(rest: &[&str], line: &str) -> Result<PlyProperty, Complaint> {
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
pub(super) fn property_label(
    attributes: &ParticleAttributes,
    columns: &[usize; 5],
    pi: usize,
) -> String {
    match columns.iter().position(|&c| c == pi) {
        Some(c) => format!("`{}`", attributes.names()[c]),
        None => format!("{}", pi + 1),
    }
}

/// For the vertex element: which property holds each of `x y z radius density`.
pub(super) fn vertex_columns(
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
