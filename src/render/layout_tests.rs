//! The Rust mirrors of the WGSL uniform and storage structs have the WGSL layout: the same fields
//! in the same order, and the same size (naga computes the WGSL side).

use bevy::render::render_resource::ShaderType;

use crate::render::{
    draw::DrawParams,
    draw::fog::CloudFogParams,
    draw::target::CloudTargetParams,
    extract::particles::GpuParticle,
    illumination::pipelines::SweepDirection,
    illumination::sky_map::{SkyCaster, SkyMapTarget},
    plan::ground::ground_map_bytes,
    plan::pools::Slot,
    plan::volumes::CloudParams,
    plan::volumes::DensityLevels,
    plan::volumes::LightParams,
    view::sort::SortParams,
    view::view_volume::ViewVolumeParams,
};

const WGSL: [&str; 6] = [
    include_str!("core/types.wgsl"),
    include_str!("illumination/sky_map.wgsl"),
    include_str!("draw/fog.wgsl"),
    include_str!("draw/billboard.wgsl"),
    include_str!("view/sort.wgsl"),
    include_str!("illumination/scatter/sweep.wgsl"),
];
const RUST: [&str; 16] = [
    include_str!("plan/volume_shape.rs"),
    include_str!("illumination/scatter/sweep.rs"),
    include_str!("draw/target.rs"),
    include_str!("view/view_atlas.rs"),
    include_str!("core/types.rs"),
    include_str!("draw/fog.rs"),
    include_str!("illumination/sky_map.rs"),
    include_str!("plan/ground.rs"),
    include_str!("plan/volumes.rs"),
    include_str!("plan/pools.rs"),
    include_str!("draw/billboards.rs"),
    include_str!("view/sort.rs"),
    include_str!("view/view_volume.rs"),
    include_str!("illumination/pipelines.rs"),
    include_str!("extract/particles.rs"),
    include_str!("draw/cloud_target.rs"),
];

/// The text of `struct <name> { … }` (from `start`, e.g. `struct ` or `pub struct `) up to the
/// closing brace at the start of a line.
fn block<'a>(sources: &[&'a str], start: &str, name: &str) -> &'a str {
    let head = format!("{start}{name} {{");
    sources
        .iter()
        .find_map(|s| {
            let at = s.find(&head)?;
            let end = at + s[at..].find("\n}")?;
            Some(&s[at..end + 2])
        })
        .unwrap_or_else(|| panic!("no `{head}`"))
}

/// Field names of a struct block, in order (comments skipped).
fn field_names(block: &str, prefix: &str) -> Vec<String> {
    block
        .lines()
        .skip(1)
        .map(str::trim)
        .filter(|l| !l.starts_with("//") && l.contains(':'))
        .filter_map(|l| l.strip_prefix(prefix))
        .map(|l| l.split(':').next().unwrap().trim().to_owned())
        .collect()
}

/// Size (bytes) and member names of a WGSL struct, as naga lays it out.
fn wgsl_layout(name: &str) -> (u32, Vec<String>) {
    // A struct parses alone, or after `CloudParams`, which `Slot` holds.
    let source = match name {
        "Slot" => format!(
            "{}\n{}",
            block(&WGSL, "struct ", "CloudParams"),
            block(&WGSL, "struct ", name)
        ),
        _ => block(&WGSL, "struct ", name).to_owned(),
    };
    let module = naga::front::wgsl::parse_str(&source).expect("the struct parses");
    let (_, ty) = module
        .types
        .iter()
        .find(|(_, t)| t.name.as_deref() == Some(name))
        .unwrap();
    let naga::TypeInner::Struct { members, span } = &ty.inner else {
        panic!("{name} is not a struct");
    };
    let names = members.iter().map(|m| m.name.clone().unwrap()).collect();
    (*span, names)
}

fn check(wgsl: &str, rust: &str, rust_size: u64) {
    let (size, wgsl_fields) = wgsl_layout(wgsl);
    let rust_fields = field_names(block(&RUST, "pub struct ", rust), "pub ");
    assert_eq!(rust_fields, wgsl_fields, "{rust} and WGSL {wgsl}: fields");
    assert_eq!(rust_size, size as u64, "{rust} and WGSL {wgsl}: size");
}

#[test]
fn rust_mirrors_have_the_wgsl_layout() {
    check("CloudParams", "CloudParams", CloudParams::min_size().get());
    check("LightParams", "LightParams", LightParams::min_size().get());
    check("Slot", "Slot", Slot::min_size().get());
    check(
        "DensityLevels",
        "DensityLevels",
        DensityLevels::min_size().get(),
    );
    check("DrawParams", "DrawParams", DrawParams::min_size().get());
    check(
        "CloudFog",
        "CloudFogParams",
        CloudFogParams::min_size().get(),
    );
    check("SortParams", "SortParams", SortParams::min_size().get());
    check(
        "ViewVolumeParams",
        "ViewVolumeParams",
        ViewVolumeParams::min_size().get(),
    );
    check(
        "SweepDirection",
        "SweepDirection",
        SweepDirection::min_size().get(),
    );
    check(
        "CloudTargetParams",
        "CloudTargetParams",
        CloudTargetParams::min_size().get(),
    );
    // A slot's ground map: the frame, then the radiance of GROUND_MAP_SIDE² texels.
    let (size, mut fields) = wgsl_layout("GroundMap");
    assert_eq!(fields.pop().as_deref(), Some("radiance"));
    let frame = field_names(block(&RUST, "pub struct ", "GroundFrame"), "pub ");
    assert_eq!(frame, fields, "GroundFrame and WGSL GroundMap: fields");
    assert_eq!(ground_map_bytes(), size as u64, "GroundMap: size");
    check("SkyCaster", "SkyCaster", SkyCaster::min_size().get());
    check(
        "SkyMapTarget",
        "SkyMapTarget",
        SkyMapTarget::min_size().get(),
    );
    // The particle buffer is plain bytes (bytemuck), laid out as `Particle`.
    let (size, _) = wgsl_layout("Particle");
    assert_eq!(std::mem::size_of::<GpuParticle>() as u32, size);
}
