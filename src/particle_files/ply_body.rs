//! The body of a PLY file, ascii or binary, read into particles by the header's columns.

use std::path::Path;

use super::ply::*;
use super::*;
use crate::particle::Particle;

/// What the body readers need to know about the vertices.
pub(super) struct Vertices<'a> {
    pub(super) header: &'a PlyHeader,
    /// Index of the `vertex` element.
    pub(super) index: usize,
    /// Which property holds each of `x y z radius density` (`usize::MAX`: a default).
    pub(super) columns: [usize; 5],
    pub(super) attributes: &'a ParticleAttributes,
}

pub(super) fn read_ply_ascii_body(
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

pub(super) fn read_ply_binary_body(
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
