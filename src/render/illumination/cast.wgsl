// Cast: the shadows clouds cast (docs/illumination.md §2, "Clouds shadow each other"). Optical
// depths add along a line, so a light volume of a cloud that others shadow is its own optical
// depth plus, at each voxel centre, every caster's own volume looked up there; and a cloud shadow
// map (§10) is the sum of every cloud's at each texel's column. One invocation per column of a
// target's lattice (a light volume's columns along the light, a map's texels); z workgroup i does
// target `work[i]` with its casters that lie in the pool bound as `caster_depth` (one dispatch
// per pool they lie in).
#import bevy_particle_clouds::types::{flat_invocation, clamped_lookup, clamped_corner, corner_weight}

// Rust mirror: `Caster` in cast.rs.
struct Caster {
    // The caster's light-box voxel coordinates (voxel i's centre at i) of a point in the
    // target's space.
    coords_from_receiver: mat4x4<f32>,
    // First element of its own light volume in `caster_depth`, and voxels per side.
    first: u32,
    n: u32,
    _padding: vec2<u32>,
}

// Rust mirror: `CastTarget` in cast.rs: a lattice of points in the target's space (a cloud's
// local space, or the world), point (i, j, k) at origin + i step_x + j step_y + k step_z, its
// value at element first + i + size_x (j + size_y k).
struct CastTarget {
    origin: vec3<f32>,
    first: u32,
    step_x: vec3<f32>,
    size_x: u32,
    step_y: vec3<f32>,
    size_y: u32,
    step_z: vec3<f32>,
    size_z: u32,
    first_caster: u32,
    casters: u32,
    // What the casters add to: 0 nothing, 1 the target's own optical depth, 2 what it holds.
    start: u32,
    _padding: u32,
}

// The targets' own optical depths (a pool's `own_depth`; unread for a shadow map), and the
// optical depths written.
@group(0) @binding(0) var<storage, read> own_depth: array<f32>;
@group(0) @binding(1) var<storage, read_write> optical_depth: array<f32>;
// This dispatch's casters, and the own light volumes of the pool they lie in.
@group(0) @binding(2) var<storage, read> casters: array<Caster>;
@group(0) @binding(3) var<storage, read> caster_depth: array<f32>;
@group(0) @binding(4) var<storage, read> work: array<CastTarget>;

const START_ZERO: u32 = 0u;
const START_OWN: u32 = 1u;

// The caster's light-box voxel coordinates of point `p` of the target's space.
fn caster_coords(caster: Caster, p: vec3<f32>) -> vec3<f32> {
    return (caster.coords_from_receiver * vec4(p, 1.0)).xyz;
}

// The optical depth `caster` casts on the point of its light-box coordinates `g`: 0 beside its
// light box or before it (its column holds none of the caster there); inside or past it, the
// clamped lookup, whose last slice (the whole column) carries on past the box.
fn cast_depth(caster: Caster, g: vec3<f32>) -> f32 {
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

// Whether the whole column from light-box coordinates `g` on lies past the caster's last slice:
// the lattice's z steps travel with the light, so every point of it takes the same whole column.
fn wholly_past(caster: Caster, g: vec3<f32>) -> bool {
    return g.z >= f32(caster.n - 1u);
}

// One invocation per column (x, y) of a target's lattice, walking its points along z, which
// travel with the light (a light volume's slices; a shadow map has one): a caster the column
// lies wholly past adds the same depth to each point, so it is looked up once per column
// instead of once per point (the clouds in front of a cloud along the light, most of its
// casters). The others are looked up at every point.
@compute @workgroup_size(#{LINEAR_WORKGROUP})
fn cast_shadows(@builtin(global_invocation_id) id: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let lattice = work[id.z];
    let i = flat_invocation(id, groups);
    let columns = lattice.size_x * lattice.size_y;
    if i >= columns {
        return;
    }
    let top = lattice.origin + f32(i % lattice.size_x) * lattice.step_x + f32(i / lattice.size_x) * lattice.step_y;
    var past = 0.0;
    for (var k = 0u; k < lattice.casters; k++) {
        let caster = casters[lattice.first_caster + k];
        let g = caster_coords(caster, top);
        if wholly_past(caster, g) {
            past += cast_depth(caster, g);
        }
    }
    for (var z = 0u; z < lattice.size_z; z++) {
        let at = lattice.first + i + columns * z;
        var held = 0.0;
        if lattice.start == START_OWN {
            held = own_depth[at];
        } else if lattice.start != START_ZERO {
            held = optical_depth[at];
        }
        optical_depth[at] = held + past;
    }
    for (var k = 0u; k < lattice.casters; k++) {
        let caster = casters[lattice.first_caster + k];
        if wholly_past(caster, caster_coords(caster, top)) {
            continue;
        }
        for (var z = 0u; z < lattice.size_z; z++) {
            let tau = cast_depth(caster, caster_coords(caster, top + f32(z) * lattice.step_z));
            if tau > 0.0 {
                let at = lattice.first + i + columns * z;
                optical_depth[at] += tau;
            }
        }
    }
}
