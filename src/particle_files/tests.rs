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
    let e = err("ply\nformat ascii 1.0\nelement face 1\nproperty list uchar int v\nend_header\n");
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
