// Cast: the shadows clouds cast on each other (docs/illumination.md §2, "Clouds shadow each
// other"). Optical depths add along a line, so a light volume of a cloud that others shadow is its
// own optical depth plus, at each voxel centre, every caster's own volume looked up there. One
// invocation per voxel of a light volume; z workgroup i rebuilds the volume of `work[i]` from the
// casters of it that lie in the pool bound as `caster_depth` (one dispatch per pool they lie in).
#import bevy_particle_clouds::types::{LightParams, Slot, flat_invocation, light_voxel_centre, clamped_lookup, clamped_corner, corner_weight}

// Rust mirror: `Caster` in cast.rs.
struct Caster {
    // The caster's light-box voxel coordinates (voxel i's centre at i) of a receiver-local point.
    coords_from_receiver: mat4x4<f32>,
    // First element of its own light volume in `caster_depth`, and voxels per side.
    first: u32,
    n: u32,
    _padding: vec2<u32>,
}

// Rust mirror: `CastItem` in cast.rs.
struct CastItem {
    slot: u32,
    light: u32,
    first_caster: u32,
    casters: u32,
    // 0: own optical depth plus these casters'; 1: these casters added to what the volume holds.
    accumulate: u32,
    _padding_0: u32,
    _padding_1: u32,
    _padding_2: u32,
}

// The receivers' pool.
@group(0) @binding(0) var<storage, read> slots: array<Slot>;
@group(0) @binding(1) var<storage, read> lights: array<LightParams>;
@group(0) @binding(2) var<storage, read> own_depth: array<f32>;
@group(0) @binding(3) var<storage, read_write> optical_depth: array<f32>;
// This dispatch's casters, and the own light volumes of the pool they lie in.
@group(0) @binding(4) var<storage, read> casters: array<Caster>;
@group(0) @binding(5) var<storage, read> caster_depth: array<f32>;
@group(0) @binding(6) var<storage, read> work: array<CastItem>;

// The optical depth `caster` casts on receiver-local point `p`: 0 beside its light box or before
// it (its column holds none of the caster there); inside or past it, the clamped lookup, whose
// last slice (the whole column) carries on past the box.
fn cast_depth(caster: Caster, p: vec3<f32>) -> f32 {
    let g = (caster.coords_from_receiver * vec4(p, 1.0)).xyz;
    let edge = f32(caster.n) - 0.5;
    if g.x < -0.5 || g.x > edge || g.y < -0.5 || g.y > edge || g.z < -0.5 {
        return 0.0;
    }
    let t = clamped_lookup(g, caster.n);
    var tau = 0.0;
    for (var corner = 0u; corner < 8u; corner++) {
        tau += corner_weight(t, corner) * caster_depth[caster.first + clamped_corner(t, corner, caster.n)];
    }
    return tau;
}

@compute @workgroup_size(#{LINEAR_WORKGROUP})
fn cast_shadows(@builtin(global_invocation_id) id: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let item = work[id.z];
    let slot = slots[item.slot];
    let light = lights[slot.lights + item.light];
    let m = slot.fine.n;
    let i = flat_invocation(id, groups);
    if i >= m * m * m {
        return;
    }
    let p = light_voxel_centre(slot.fine, light, vec3(i % m, (i / m) % m, i / (m * m)));
    var tau = 0.0;
    for (var k = 0u; k < item.casters; k++) {
        tau += cast_depth(casters[item.first_caster + k], p);
    }
    let at = slot.optical_depth + light.offset + i;
    let held = select(own_depth[at], optical_depth[at], item.accumulate != 0u);
    optical_depth[at] = held + tau;
}
