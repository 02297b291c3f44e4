//! CSV particle files (with the `csv` crate): reading, with a line number only when an error
//! names one, and writing.

use std::path::Path;

use super::*;
use crate::particle::Particle;

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
    let mut reader = ::csv::ReaderBuilder::new()
        .has_headers(false)
        .flexible(true)
        .trim(::csv::Trim::All)
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
        Ok(r) => Some(Ok((r.position().map_or(0, ::csv::Position::byte), r))),
        Err(e) => Some(Err(e)),
    });
    let csv_error = |e: ::csv::Error| {
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
    let csv_error = |e: ::csv::Error| ParticleFileError::io(path, e.into());
    let mut writer = ::csv::Writer::from_path(path).map_err(csv_error)?;
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
