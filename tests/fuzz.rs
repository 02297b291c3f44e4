//! Fuzzed parsers: every input ends in `Ok` or a typed error, never a panic, and no parser
//! allocates out of proportion to its input.
//!
//! Property-based (proptest): each case takes a valid file of the corpus below (PLY ascii, PLY
//! binary of both byte orders, CSV, a RON scene, a loader's settings) and mutates it: bytes
//! flipped, inserted, deleted, duplicated or truncated, and numbers or keywords swapped for
//! hostile ones (NaN, 1e39, huge counts). A stable toolchain has no coverage-guided fuzzer, so
//! the mutations aim where the parsers branch. `FUZZ_CASES` sets the cases per parser (default
//! 20,000, what CI runs); failures proptest finds are kept in `tests/fuzz.proptest-regressions`
//! and replayed first, and the inputs found by hand are in `tests/fuzz_corpus/`.

use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;
use std::path::Path;

use bevy_particle_clouds::{
    Particles,
    particle_files::{ParticleAttributes, parse_csv, parse_ply},
    scene::{ParticlePaths, Scene, SceneFile, apply_setting},
    settings::CloudQualitySettings,
};
use proptest::prelude::*;
use proptest::test_runner::{Config, TestRunner};

// ---------------------------------------------------------------------------------------------
// Allocation accounting: the peak bytes live on this thread while a parser runs.
// ---------------------------------------------------------------------------------------------

struct Counting;

thread_local! {
    static LIVE: Cell<usize> = const { Cell::new(0) };
    static PEAK: Cell<usize> = const { Cell::new(0) };
}

fn grow(bytes: usize) {
    // `try_with`: the thread's storage may already be gone while it exits.
    let _ = LIVE.try_with(|live| {
        let now = live.get() + bytes;
        live.set(now);
        let _ = PEAK.try_with(|peak| peak.set(peak.get().max(now)));
    });
}

fn shrink(bytes: usize) {
    let _ = LIVE.try_with(|live| live.set(live.get().saturating_sub(bytes)));
}

unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        grow(layout.size());
        unsafe { System.alloc(layout) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        shrink(layout.size());
        unsafe { System.dealloc(ptr, layout) }
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        grow(new_size);
        shrink(layout.size());
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

#[global_allocator]
static ALLOCATOR: Counting = Counting;

/// The most bytes `f` held at once beyond what was live before it.
fn peak_allocation<T>(f: impl FnOnce() -> T) -> (T, usize) {
    let before = LIVE.with(Cell::get);
    PEAK.with(|p| p.set(before));
    let result = f();
    (result, PEAK.with(Cell::get) - before)
}

/// What a parser may hold for an input of `len` bytes: the particles it can hold (a PLY vertex
/// takes 3 bytes at least, a particle 20), the vector's doubling, and a fixed allowance for
/// buffers and messages.
fn allowance(len: usize) -> usize {
    64 * len + (1 << 20)
}

// ---------------------------------------------------------------------------------------------
// The corpus and its mutations
// ---------------------------------------------------------------------------------------------

const PLY_HEADER: &str = "element vertex 3\nproperty float x\nproperty float y\n\
                          property float z\nproperty float radius\nproperty float density\n\
                          element face 1\nproperty list uchar int vertex_indices\nend_header\n";

fn ply_ascii() -> Vec<u8> {
    format!(
        "ply\nformat ascii 1.0\ncomment puffs\n{PLY_HEADER}0 0 0 0.5 1\n1.5 0.25 -2 0.75 0.5\n\
         -1 2 3 1 2\n3 0 1 2\n"
    )
    .into_bytes()
}

fn ply_binary(little: bool) -> Vec<u8> {
    let order = if little { "little" } else { "big" };
    let mut bytes = format!("ply\nformat binary_{order}_endian 1.0\n{PLY_HEADER}").into_bytes();
    for v in [
        0.0f32, 0.0, 0.0, 0.5, 1.0, 1.5, 0.25, -2.0, 0.75, 0.5, -1.0, 2.0, 3.0, 1.0, 2.0,
    ] {
        bytes.extend(if little {
            v.to_le_bytes()
        } else {
            v.to_be_bytes()
        });
    }
    bytes.push(3);
    for i in 0i32..3 {
        bytes.extend(if little {
            i.to_le_bytes()
        } else {
            i.to_be_bytes()
        });
    }
    bytes
}

fn csv() -> Vec<u8> {
    b"id,x,y,z,radius,density,name\n1,0,0,0,0.5,1,\"puff, big\"\n\n2,1.5,0.25,-2,0.75,0.5,b\n"
        .to_vec()
}

fn scene() -> Vec<u8> {
    b"(camera: (position: (0.0, 0.6, 6.0), look_at: (0.0, 0.0, 0.0), vertical_fov_degrees: 38.0, \
      width: 16, height: 12), background: (0.1, 0.2, 0.3), \
      lights: [(direction: (-0.5, -0.8, -0.35), irradiance: (1.0, 0.97, 0.9))], \
      clouds: [(translation: (0.0, 1.0, 0.0), medium: (extinction: 10.0, albedo: 0.99, anisotropy: 0.5), \
      particles: Inline([(position: (0.1, 0.2, 0.3), radius: 0.2, density: 0.8), \
      (position: (-0.3, 0.0, 0.1), radius: 0.25, density: 1.0)]))], \
      objects: [(shape: Cuboid((0.8, 3.0, 0.3)), translation: (0.9, 0.0, 1.8), color: (0.05, 0.05, 0.05))], \
      fog: (color: (0.25, 0.3, 0.38), falloff: Exponential(density: 0.08)), \
      settings: (volume_resolution: 32, scatter_iterations: 4))"
        .to_vec()
}

fn attributes() -> Vec<u8> {
    b"(position: (\"px\", \"py\", \"pz\"), radius: \"pscale\", density: \"density\", \
      default_radius: Some(0.5), default_density: Some(1.0), scale: 0.01)"
        .to_vec()
}

/// Text the parsers give meaning to, spliced in by the mutations.
const TOKENS: &[&str] = &[
    "NaN",
    "nan",
    "inf",
    "-inf",
    "1e39",
    "-1e39",
    "1e-45",
    "-0",
    "0",
    "4294967295",
    "18446744073709551616",
    "99999999999",
    "-1",
    "\n",
    "\r\n",
    ",",
    "\"",
    " ",
    "(",
    ")",
    "[",
    "]",
    "element vertex 4000000000\n",
    "property list uint int x\n",
    "property double x\n",
    "format binary_big_endian 1.0\n",
    "end_header\n",
    "ply\n",
    "Some(",
    "None",
    ":",
    "Ply(\"a.ply\")",
    "Csv(\"../x.csv\")",
    "\u{feff}",
    "\u{0}",
    "\u{ffff}",
    "é",
];

#[derive(Clone, Debug)]
enum Mutation {
    Flip { at: usize, bit: u8 },
    Insert { at: usize, token: usize },
    Delete { at: usize, len: usize },
    Duplicate { at: usize, len: usize },
    Truncate { at: usize },
    Byte { at: usize, byte: u8 },
}

fn mutation() -> impl Strategy<Value = Mutation> {
    let at = any::<usize>();
    prop_oneof![
        (at.clone(), 0u8..8).prop_map(|(at, bit)| Mutation::Flip { at, bit }),
        (at.clone(), 0..TOKENS.len()).prop_map(|(at, token)| Mutation::Insert { at, token }),
        (at.clone(), 1usize..16).prop_map(|(at, len)| Mutation::Delete { at, len }),
        (at.clone(), 1usize..64).prop_map(|(at, len)| Mutation::Duplicate { at, len }),
        at.clone().prop_map(|at| Mutation::Truncate { at }),
        (at, any::<u8>()).prop_map(|(at, byte)| Mutation::Byte { at, byte }),
    ]
}

fn apply(mut bytes: Vec<u8>, mutations: &[Mutation]) -> Vec<u8> {
    for m in mutations {
        let n = bytes.len().max(1);
        match *m {
            Mutation::Flip { at, bit } => {
                if let Some(b) = bytes.get_mut(at % n) {
                    *b ^= 1 << bit;
                }
            }
            Mutation::Insert { at, token } => {
                let at = at % (bytes.len() + 1);
                bytes.splice(at..at, TOKENS[token].bytes());
            }
            Mutation::Delete { at, len } => {
                let at = at % n;
                bytes.drain(at.min(bytes.len())..(at + len).min(bytes.len()));
            }
            Mutation::Duplicate { at, len } => {
                let at = at % n;
                let piece = bytes[at.min(bytes.len())..(at + len).min(bytes.len())].to_vec();
                bytes.splice(at.min(bytes.len())..at.min(bytes.len()), piece);
            }
            Mutation::Truncate { at } => bytes.truncate(at % n),
            Mutation::Byte { at, byte } => {
                if let Some(b) = bytes.get_mut(at % n) {
                    *b = byte;
                }
            }
        }
    }
    bytes
}

/// Mutated inputs of `seeds`: one seed, then 0-8 mutations.
fn mutated(seeds: Vec<Vec<u8>>) -> impl Strategy<Value = Vec<u8>> {
    (
        proptest::sample::select(seeds),
        proptest::collection::vec(mutation(), 0..8),
    )
        .prop_map(|(seed, mutations)| apply(seed, &mutations))
}

// ---------------------------------------------------------------------------------------------
// The parsers under test, as the loader and the scene loader call them
// ---------------------------------------------------------------------------------------------

/// What the `AssetServer` loader does with a file's bytes: parse by extension, then validate.
fn load_particles(name: &str, bytes: &[u8]) -> Result<usize, String> {
    let attributes = ParticleAttributes::default();
    let path = Path::new(name);
    let particles = if name.ends_with(".csv") {
        parse_csv(path, bytes, &attributes)
    } else {
        parse_ply(path, bytes, &attributes)
    }
    .map_err(|e| e.to_string())?;
    let particles = Particles::new(particles);
    particles.validate().map_err(|e| e.to_string())?;
    Ok(particles.particles.len())
}

/// A scene's text, parsed and validated; particle files resolve in an empty folder.
fn load_scene(bytes: &[u8]) -> Result<usize, String> {
    let text = std::str::from_utf8(bytes).map_err(|e| e.to_string())?;
    let file: SceneFile = ron::from_str(text).map_err(|e| e.to_string())?;
    let empty = std::env::temp_dir().join(format!("bpc_fuzz_{}", std::process::id()));
    std::fs::create_dir_all(&empty).map_err(|e| e.to_string())?;
    let scene = Scene::from_scene_file_with(file, &empty, ParticlePaths::InsideSceneFolder)
        .map_err(|e| e.to_string())?;
    scene.validate().map_err(|e| e.to_string())?;
    Ok(scene.clouds.len())
}

/// A loader's settings (an asset `.meta` file's `settings`), deserialized and used.
fn load_attributes(bytes: &[u8]) -> Result<usize, String> {
    let text = std::str::from_utf8(bytes).map_err(|e| e.to_string())?;
    let attributes: ParticleAttributes = ron::from_str(text).map_err(|e| e.to_string())?;
    parse_csv(Path::new("a.csv"), b"px,py,pz\n1,2,3\n", &attributes)
        .map(|p| p.len())
        .map_err(|e| e.to_string())
}

/// Runs `cases` mutated inputs of `seeds` through `parse`: no panic, no message without text,
/// and no allocation beyond the allowance.
fn fuzz(name: &str, seeds: Vec<Vec<u8>>, parse: fn(&[u8]) -> Result<usize, String>) -> u32 {
    for seed in &seeds {
        assert!(parse(seed).is_ok(), "{name}: a corpus seed must parse");
    }
    let cases = cases();
    let mut runner = TestRunner::new(config(cases));
    let (ok, refused) = (Cell::new(0u32), Cell::new(0u32));
    let result = runner.run(&mutated(seeds), |input| {
        let (result, peak) = peak_allocation(|| parse(&input));
        prop_assert!(
            peak <= allowance(input.len()),
            "{name}: {peak} bytes held for an input of {} bytes",
            input.len()
        );
        match result {
            Ok(_) => ok.set(ok.get() + 1),
            Err(message) => {
                prop_assert!(!message.trim().is_empty(), "{name}: an empty message");
                refused.set(refused.get() + 1);
            }
        }
        Ok(())
    });
    if let Err(e) = result {
        panic!("{name}: {e}");
    }
    let (ok, refused) = (ok.get(), refused.get());
    eprintln!("fuzz {name}: {cases} cases, {ok} parsed, {refused} refused");
    // The mutations must reach both outcomes, or the property tested nothing.
    assert!(
        ok > 0 && refused > 0,
        "{name}: {ok} parsed, {refused} refused"
    );
    cases
}

/// `cases` cases, failures kept in `tests/fuzz.proptest-regressions` and replayed first.
fn config(cases: u32) -> Config {
    Config {
        cases,
        failure_persistence: Some(Box::new(
            proptest::test_runner::FileFailurePersistence::WithSource("proptest-regressions"),
        )),
        source_file: Some(file!()),
        ..Config::default()
    }
}

fn cases() -> u32 {
    std::env::var("FUZZ_CASES")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(20_000)
}

#[test]
fn ply_ascii_and_binary_of_both_orders() {
    fuzz(
        "ply",
        vec![ply_ascii(), ply_binary(true), ply_binary(false)],
        |b| load_particles("f.ply", b),
    );
}

#[test]
fn csv_files() {
    fuzz("csv", vec![csv()], |b| load_particles("f.csv", b));
}

#[test]
fn scene_files_and_their_validation() {
    fuzz("scene", vec![scene()], load_scene);
}

#[test]
fn loader_settings() {
    fuzz("attributes", vec![attributes()], load_attributes);
}

/// `--set FIELD=VALUE` assignments: any text is applied or refused with a message.
#[test]
fn setting_assignments() {
    let strategy = "[a-z_]{0,24}(=| = |==)?[-+0-9a-zA-Z.e_]{0,12}";
    let mut runner = TestRunner::new(config(cases()));
    let fields = [
        "volume_resolution",
        "scatter_iterations",
        "light_supersampling",
    ];
    let result = runner.run(
        &(strategy, proptest::sample::select(fields.to_vec())),
        |(text, field)| {
            let mut settings = CloudQualitySettings::default();
            let _ = apply_setting(&mut settings, &text);
            // A known field with a hostile value is refused or applied, never a panic.
            for value in ["NaN", "-1", "1e39", "4294967296", "0", ""] {
                let _ = apply_setting(&mut settings, &format!("{field}={value}"));
            }
            Ok(())
        },
    );
    if let Err(e) = result {
        panic!("{e}");
    }
}

/// The inputs found by hand and by earlier runs (`tests/fuzz_corpus/`): each parses or is refused,
/// within the allowance.
#[test]
fn the_kept_corpus() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fuzz_corpus");
    let mut files: Vec<_> = std::fs::read_dir(&dir)
        .expect("tests/fuzz_corpus")
        .map(|e| e.unwrap().path())
        .collect();
    files.sort();
    assert!(files.len() >= 4, "{files:?}");
    for file in files {
        let bytes = std::fs::read(&file).unwrap();
        let name = file.file_name().unwrap().to_string_lossy().to_string();
        let parse = |b: &[u8]| match file.extension().and_then(|e| e.to_str()) {
            Some("ron") if name.starts_with("attributes") => load_attributes(b),
            Some("ron") => load_scene(b),
            _ => load_particles(&name, b),
        };
        let (result, peak) = peak_allocation(|| parse(&bytes));
        assert!(
            peak <= allowance(bytes.len()),
            "{name}: {peak} bytes held for an input of {} bytes",
            bytes.len()
        );
        let expected_ok = name.contains(".ok.");
        assert_eq!(result.is_ok(), expected_ok, "{name}: {result:?}");
    }
}
