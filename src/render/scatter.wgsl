// Multiple scattering: one iteration n -> n + 1 (docs/illumination.md §4). Reads S_n, writes
// S_{n+1} and adds it to the multiple-scattering volume (after the sweeps, `accumulate_order`).
// Two stencils: the discrete-ordinates sweep, with two walks of its lattice lines (serial, or a
// scan per line), and the paper's.
// Every cloud of a volume pool in one dispatch: z workgroup i scatters slot `work[i]`.
// An anisotropic medium's volumes hold angular moments beside their means (shader def MOMENTS):
// the sweep's source takes the P1 phase function of the transformed medium, and each order's
// flux (and in `multiple` the quadrupole) is gathered from the radiance of every direction.
#import bevy_particle_clouds::types::{CloudParams, Slot, GroundMap, GROUND_MAP_SIDE, voxel_index, flat_invocation, flux_element, quadrupole_element, quadrupole_basis, affine_point, affine_vector}

// One direction pair (o, -o) of the discrete-ordinates sweep, o's first non-zero component
// positive; `first` is 1 for the first of an iteration's 13 dispatches (it overwrites S_{n+1});
// `accumulate` is 0 for the first sweep of a warm restart, which leaves `multiple` alone (else
// the sweeps add the quadrupole, and `accumulate_order` the rest, after them); `sky`
// is the sky's radiance and `boundary` 1 in the first iteration of a series, where the light
// entering the grid from outside (the sky's, and the ground's on lines that climb) comes in (so
// S_1 = K S_0 + their single scattering); else 0 and nothing enters.
struct SweepDirection {
    o: vec3<i32>,
    first: u32,
    accumulate: u32,
    sky: vec3<f32>,
    boundary: u32,
}

@group(0) @binding(0) var<storage, read> slots: array<Slot>;
@group(0) @binding(1) var<uniform> direction: SweepDirection;
@group(0) @binding(2) var<storage, read> densities: array<f32>;
@group(0) @binding(3) var<storage, read> s_in: array<vec4<f32>>;
@group(0) @binding(4) var<storage, read_write> s_out: array<vec4<f32>>;
@group(0) @binding(5) var<storage, read_write> multiple: array<vec4<f32>>;
// A slot per z workgroup.
@group(0) @binding(6) var<storage, read> work: array<u32>;
// Other clouds' media per voxel (overlap.wgsl), read where `cloud.foreign` is 1.
@group(0) @binding(7) var<storage, read> foreign: array<vec2<f32>>;
// Per slot, the ground under the cloud and its radiance (ground.wgsl).
@group(0) @binding(8) var<storage, read> grounds: array<GroundMap>;

var<private> slot_index: u32;
var<private> slot: Slot;
var<private> cloud: CloudParams;

fn begin(item: u32) {
    slot_index = work[item];
    slot = slots[slot_index];
    cloud = slot.cloud;
}

// Voxel i of this slot's density and volumes.
fn density(i: u32) -> f32 {
    return densities[slot.density + i];
}

// The medium the sweep goes through at voxel i, delta-Eddington transformed (§4): its density
// in units of the cloud's extinction at density 1 (x) and its albedo (y), over every cloud whose
// medium reaches it (§4, "Clouds that overlap"); the cloud's own albedo where none does.
fn medium(i: u32) -> vec2<f32> {
    let rho = cloud.depth_scale * density(i);
    if cloud.foreign == 0u {
        return vec2(rho, cloud.scatter_albedo);
    }
    let other = foreign[slot.foreign + i];
    let total = rho + other.x;
    return vec2(total, select(cloud.scatter_albedo, (cloud.scatter_albedo * rho + other.y) / total, other.x > 0.0));
}

// The in-scattered radiance of order n at voxel i towards the unit direction w, per unit
// scattering coefficient: its mean, plus 3 g' F . w with moments (the P1 phase function).
fn order_in(i: u32, w: vec3<f32>) -> vec3<f32> {
    var s = s_in[slot.volume + i].xyz;
#ifdef MOMENTS
    var along = vec3(0.0);
    for (var axis = 0u; axis < 3u; axis++) {
        along += s_in[flux_element(slot.volume, cloud.n, i, axis)].xyz * w[axis];
    }
    s += 3.0 * cloud.scatter_anisotropy * along;
#endif
    return s;
}

// Below this optical depth the segment weights use their series: 1 - e and (1 - e)/tau - e
// cancel in f32.
const SERIES_BELOW: f32 = 0.02;

// (1 - e, (1 - e)/tau - e), e = exp(-tau): the weights of a segment's constant and linear source.
fn segment_weights(tau: f32) -> vec2<f32> {
    if tau < SERIES_BELOW {
        let t2 = tau * tau;
        return vec2(tau - t2 / 2.0 + t2 * tau / 6.0, tau / 2.0 - t2 / 3.0 + t2 * tau / 8.0);
    }
    let e = exp(-tau);
    return vec2(1.0 - e, (1.0 - e) / tau - e);
}

// The ground's radiance at world (x, z): bilinear in the cloud's ground map, its edge texels
// extending outwards.
fn ground_radiance(xz: vec2<f32>) -> vec3<f32> {
    let plane = grounds[slot_index].plane;
    let side = f32(GROUND_MAP_SIDE);
    let c = clamp((xz - plane.yz + vec2(plane.w)) / (2.0 * plane.w) * side - 0.5, vec2(0.0), vec2(side - 1.0));
    let base = min(vec2<u32>(floor(c)), vec2(GROUND_MAP_SIDE - 2u));
    let f = c - vec2<f32>(base);
    let at = base.x + GROUND_MAP_SIDE * base.y;
    let row0 = mix(grounds[slot_index].radiance[at].xyz, grounds[slot_index].radiance[at + 1u].xyz, f.x);
    let row1 = mix(grounds[slot_index].radiance[at + GROUND_MAP_SIDE].xyz, grounds[slot_index].radiance[at + GROUND_MAP_SIDE + 1u].xyz, f.x);
    return mix(row0, row1, f.y);
}

// The radiance entering the grid on a lattice line whose first voxel is `v`, travelling along
// the cloud-local unit direction w, `half_step` before that voxel's centre: nothing but in an
// iteration that brings the boundary in; then the sky's, or where a ground lights the cloud and
// the line climbs (in the world), the ground's where the line, continued backwards, meets it.
fn entering(v: vec3<u32>, w: vec3<f32>, half_step: f32) -> vec3<f32> {
    if direction.boundary == 0u {
        return vec3(0.0);
    }
    let ground = grounds[slot_index].reflectance.w != 0.0;
    let to_world = grounds[slot_index].world_from_local;
    let travel = affine_vector(to_world, w);
    if !ground || travel.y <= 0.0 {
        return direction.sky;
    }
    let p = cloud.grid_origin + (vec3<f32>(v) + 0.5) * cloud.h - w * half_step;
    let entry = affine_point(to_world, p);
    let t = max(entry.y - grounds[slot_index].plane.x, 0.0) / travel.y;
    return ground_radiance(entry.xz - travel.xz * t);
}

// The voxel at position t along a lattice line: `start` is the line's point at t = 0 in the
// frame where o has no negative component (`flip` marks the mirrored axes).
fn line_position(start: vec3<i32>, t: i32, flip: vec3<bool>) -> vec3<u32> {
    let n = i32(cloud.n);
    let step = vec3<i32>(abs(direction.o));
    let mirrored = start + t * step;
    return vec3<u32>(select(mirrored, vec3(n - 1) - mirrored, flip));
}

fn line_voxel(start: vec3<i32>, t: i32, flip: vec3<bool>) -> u32 {
    return voxel_index(line_position(start, t, flip), cloud.n);
}

// A voxel's medium (density, albedo) and order-n radiance towards a direction; zero outside
// the line.
struct Sample {
    m: vec2<f32>,
    s: vec3<f32>,
}

const OUTSIDE: Sample = Sample(vec2(0.0), vec3(0.0));

// One segment's transport, as the affine map r -> a r + b (a vec4 (b, a)) of the radiance
// arriving from the upwind neighbour's side: attenuation over the segment, plus the segment's
// own scattering J = albedo S, linear along it.
fn transport(here: Sample, up: Sample, half_step: f32) -> vec4<f32> {
    let tau = cloud.k_local * (here.m.x + up.m.x) * half_step;
    let w = segment_weights(tau);
    let j = here.m.y * here.s;
    return vec4(j * w.x + (up.m.y * up.s - j) * w.y, 1.0 - w.x);
}

const IDENTITY: vec4<f32> = vec4(0.0, 0.0, 0.0, 1.0);

// `first`, then `second`.
fn then(first: vec4<f32>, second: vec4<f32>) -> vec4<f32> {
    return vec4(second.w * first.xyz + second.xyz, second.w * first.w);
}

fn apply(map: vec4<f32>, radiance: vec3<f32>) -> vec3<f32> {
    return map.w * radiance + map.xyz;
}

fn add_to(element: u32, share: vec4<f32>, overwrite: bool) {
    if overwrite {
        s_out[element] = share;
    } else {
        s_out[element] += share;
    }
}

// Voxel `voxel`'s share of the radiance arriving there along the unit direction w (`forth`) and
// along -w (`back`): 1/26 of each.
fn share_of(forth: vec3<f32>, back: vec3<f32>) -> vec4<f32> {
    return vec4((forth + back) / 26.0, 0.0);
}

// With moments, the share's flux and quadrupole: the flux to the next order's (added, or written
// over what it held: `overwrite`, in an iteration's first dispatch); the quadrupole, even in w,
// to `multiple` only (the sweep's source is P1): added, or, in a warm restart's first sweep,
// which does not accumulate, written anew (§4). The means, and the flux in `multiple`, are
// accumulated once per iteration (`accumulate_order`).
fn deposit_moments(voxel: u32, forth: vec3<f32>, back: vec3<f32>, w: vec3<f32>, overwrite: bool) {
#ifdef MOMENTS
    let n = cloud.n;
    let flux = vec4((forth - back) / 26.0, 0.0);
    for (var axis = 0u; axis < 3u; axis++) {
        add_to(flux_element(slot.volume, n, voxel, axis), flux * w[axis], overwrite);
    }
    let share = share_of(forth, back);
    var q = quadrupole_basis(w);
    for (var c = 0u; c < 5u; c++) {
        let at = quadrupole_element(slot.multiple, n, voxel, c);
        if overwrite && direction.accumulate == 0u {
            multiple[at] = share * q[c];
        } else {
            multiple[at] += share * q[c];
        }
    }
#endif
}

fn deposit(voxel: u32, forth: vec3<f32>, back: vec3<f32>, w: vec3<f32>, overwrite: bool) {
    add_to(slot.volume + voxel, share_of(forth, back), overwrite);
    deposit_moments(voxel, forth, back, w, overwrite);
}

// A lattice line of the dispatch's direction o, and its voxels t0..t1.
struct Line {
    start: vec3<i32>,
    flip: vec3<bool>,
    t0: i32,
    t1: i32,
}

// Line `index` of direction o: free axes take any coordinate, the other moving axes an offset
// from the first moving axis in -(n - 1)..=(n - 1). Past the last line, or where a line misses
// the grid, t0 = t1.
fn lattice_line(index: u32) -> Line {
    let n = i32(cloud.n);
    let o = direction.o;
    let first_axis = select(select(2, 1, o.y != 0), 0, o.x != 0);
    var rest = index;
    var start = vec3(0);
    for (var a = 0; a < 3; a++) {
        if o[a] == 0 {
            start[a] = i32(rest % cloud.n);
            rest /= cloud.n;
        } else if a != first_axis {
            let span = 2u * cloud.n - 1u;
            start[a] = i32(rest % span) - (n - 1);
            rest /= span;
        }
    }
    var t0 = 0;
    var t1 = n;
    for (var a = 0; a < 3; a++) {
        if o[a] != 0 {
            t0 = max(t0, -start[a]);
            t1 = min(t1, n - start[a]);
        }
    }
    t1 = select(t0, max(t1, t0), rest == 0u);
    return Line(start, o < vec3(0), t0, t1);
}

// Voxel t of the line, seen travelling along w; OUTSIDE past the line's ends.
fn sample(line: Line, t: i32, w: vec3<f32>) -> Sample {
    if t < line.t0 || t >= line.t1 {
        return OUTSIDE;
    }
    let i = line_voxel(line.start, t, line.flip);
    return Sample(medium(i), order_in(i, w));
}

const LANES: u32 = #{LINEAR_WORKGROUP}u;

// Each lane's composed map, scanned in place: `forth_maps` along -o (from the +o side, lanes
// in falling order), `back_maps` along o (lanes in rising order).
var<workgroup> forth_maps: array<vec4<f32>, LANES>;
var<workgroup> back_maps: array<vec4<f32>, LANES>;

// The half step along o and the unit direction from the +o side.
fn pair_geometry() -> vec4<f32> {
    let o = vec3<f32>(direction.o);
    return vec4(-normalize(o), 0.5 * cloud.h * length(o));
}

// `SweepWalk::Serial`: one invocation per lattice line of direction o marches it against o
// (radiance from the +o side), then along o. Few long threads: fast where invocations are CPU
// threads; a GPU waits on memory at every step. The lines partition the grid, so each voxel is
// written by one invocation of a dispatch.
@compute @workgroup_size(#{LINEAR_WORKGROUP})
fn sweep_serial(@builtin(global_invocation_id) id: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    begin(id.z);
    let line = lattice_line(flat_invocation(id, groups));
    let geometry = pair_geometry();
    let w = geometry.xyz;
    let half_step = geometry.w;
    if line.t0 >= line.t1 {
        return;
    }
    var radiance = entering(line_position(line.start, line.t1 - 1, line.flip), w, half_step);
    var up = OUTSIDE;
    for (var t = line.t1 - 1; t >= line.t0; t--) {
        let here = sample(line, t, w);
        radiance = apply(transport(here, up, half_step), radiance);
        deposit(line_voxel(line.start, t, line.flip), radiance, vec3(0.0), w, direction.first != 0u);
        up = here;
    }
    radiance = entering(line_position(line.start, line.t0, line.flip), -w, half_step);
    up = OUTSIDE;
    for (var t = line.t0; t < line.t1; t++) {
        let here = sample(line, t, -w);
        radiance = apply(transport(here, up, half_step), radiance);
        deposit(line_voxel(line.start, t, line.flip), vec3(0.0), radiance, w, false);
        up = here;
    }
}

// `SweepWalk::Scan`: one workgroup per lattice line of direction o, both directions of the pair.
// Transport along a line is the recurrence r_t = a_t r_(t-1) + b_t, whose affine maps compose
// associatively: each lane composes its chunk of the line, the workgroup scans the chunks' maps
// (Hillis-Steele), and each lane replays its chunk from the radiance arriving at it: n² to
// (2n - 1)² workgroups of short chains instead of as many threads of n steps each.
@compute @workgroup_size(#{LINEAR_WORKGROUP})
fn sweep_scan(
    @builtin(workgroup_id) group: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) lane: u32,
) {
    begin(group.z);
    let line = lattice_line(group.x + group.y * groups.x);
    let geometry = pair_geometry();
    let w = geometry.xyz;
    let half_step = geometry.w;
    let chunk = (line.t1 - line.t0 + i32(LANES) - 1) / i32(LANES);
    let c0 = min(line.t0 + i32(lane) * chunk, line.t1);
    let c1 = min(c0 + chunk, line.t1);
    var forth = IDENTITY;
    var up = sample(line, c1, w);
    for (var t = c1 - 1; t >= c0; t--) {
        let here = sample(line, t, w);
        forth = then(forth, transport(here, up, half_step));
        up = here;
    }
    var back = IDENTITY;
    up = sample(line, c0 - 1, -w);
    for (var t = c0; t < c1; t++) {
        let here = sample(line, t, -w);
        back = then(back, transport(here, up, half_step));
        up = here;
    }
    forth_maps[lane] = forth;
    back_maps[lane] = back;
    for (var d = 1u; d < LANES; d *= 2u) {
        workgroupBarrier();
        if lane + d < LANES {
            forth = then(forth_maps[lane + d], forth);
        }
        if lane >= d {
            back = then(back_maps[lane - d], back);
        }
        workgroupBarrier();
        forth_maps[lane] = forth;
        back_maps[lane] = back;
    }
    workgroupBarrier();
    if c0 >= c1 {
        return;
    }
    // The lane's chunk, from the radiance entering the grid through the maps of the chunks before.
    var arriving = select(IDENTITY, back_maps[max(lane, 1u) - 1u], lane > 0u);
    var radiance = apply(arriving, entering(line_position(line.start, line.t0, line.flip), -w, half_step));
    var backs: array<vec3<f32>, #{SWEEP_CHUNK}>;
    up = sample(line, c0 - 1, -w);
    for (var t = c0; t < c1; t++) {
        let here = sample(line, t, -w);
        radiance = apply(transport(here, up, half_step), radiance);
        backs[t - c0] = radiance;
        up = here;
    }
    arriving = select(IDENTITY, forth_maps[min(lane + 1u, LANES - 1u)], lane + 1u < LANES);
    radiance = apply(arriving, entering(line_position(line.start, line.t1 - 1, line.flip), w, half_step));
    var forths: array<vec3<f32>, #{SWEEP_CHUNK}>;
    up = sample(line, c1, w);
    for (var t = c1 - 1; t >= c0; t--) {
        let here = sample(line, t, w);
        radiance = apply(transport(here, up, half_step), radiance);
        forths[t - c0] = radiance;
        up = here;
    }
    // The chunk's means: every load before any store, so that they wait on memory once.
    let overwrite = direction.first != 0u;
    var held: array<vec4<f32>, #{SWEEP_CHUNK}>;
    if !overwrite {
        for (var t = c0; t < c1; t++) {
            held[t - c0] = s_out[slot.volume + line_voxel(line.start, t, line.flip)];
        }
    }
    for (var t = c0; t < c1; t++) {
        let j = t - c0;
        let voxel = line_voxel(line.start, t, line.flip);
        s_out[slot.volume + voxel] = held[j] + share_of(forths[j], backs[j]);
        deposit_moments(voxel, forths[j], backs[j], w, overwrite);
    }
}

// After an accumulating iteration's sweeps: `multiple` += S_(n+1), and with moments its flux.
@compute @workgroup_size(#{LINEAR_WORKGROUP})
fn accumulate_order(@builtin(global_invocation_id) id: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let v = slot_voxel(id, groups);
    if v == PAST_THE_GRID {
        return;
    }
    multiple[slot.multiple + v] += s_out[slot.volume + v];
#ifdef MOMENTS
    for (var axis = 0u; axis < 3u; axis++) {
        multiple[flux_element(slot.multiple, cloud.n, v, axis)] += s_out[flux_element(slot.volume, cloud.n, v, axis)];
    }
#endif
}

// The paper's Algorithm 2: every neighbour inside the grid weighted by the voxel's own opacity.
@compute @workgroup_size(#{LINEAR_WORKGROUP})
fn scatter_paper(@builtin(global_invocation_id) invocation: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    begin(invocation.z);
    let n = cloud.n;
    let flat = flat_invocation(invocation, groups);
    if flat >= n * n * n {
        return;
    }
    let id = vec3(flat % n, (flat / n) % n, flat / (n * n));
    var sum = vec3(0.0);
    for (var z = -1; z <= 1; z++) {
        for (var y = -1; y <= 1; y++) {
            for (var x = -1; x <= 1; x++) {
                let v = vec3<i32>(id) + vec3(x, y, z);
                if all(vec3(x, y, z) == vec3(0)) || any(v < vec3(0)) || any(v >= vec3(i32(n))) {
                    continue;
                }
                sum += s_in[slot.volume + voxel_index(vec3<u32>(v), n)].xyz;
            }
        }
    }
    let opacity = 1.0 - exp(-cloud.k_local * density(flat) * cloud.h);
    let s = sum * (cloud.albedo / 26.0 * opacity);
    s_out[slot.volume + flat] = vec4(s, 0.0);
    if direction.accumulate != 0u {
        multiple[slot.multiple + flat] += vec4(s, 0.0);
    }
}

const PAST_THE_GRID: u32 = 0xffffffffu;

// The voxel of a one-voxel-per-invocation kernel, or PAST_THE_GRID.
fn slot_voxel(id: vec3<u32>, groups: vec3<u32>) -> u32 {
    begin(id.z);
    let v = flat_invocation(id, groups);
    if v >= cloud.n * cloud.n * cloud.n {
        return PAST_THE_GRID;
    }
    return v;
}

// A warm restart (docs/illumination.md §4) from the solution X that `multiple` holds: its first
// sweep scatters S_0 + X (written here into s_out, from S_0 in s_in) without accumulating. With
// moments, their flux alike.
@compute @workgroup_size(#{LINEAR_WORKGROUP})
fn warm_start(@builtin(global_invocation_id) id: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let v = slot_voxel(id, groups);
    if v == PAST_THE_GRID {
        return;
    }
    s_out[slot.volume + v] = s_in[slot.volume + v] + multiple[slot.multiple + v];
#ifdef MOMENTS
    for (var axis = 0u; axis < 3u; axis++) {
        let at = flux_element(slot.volume, cloud.n, v, axis);
        s_out[at] = s_in[at] + multiple[flux_element(slot.multiple, cloud.n, v, axis)];
    }
#endif
}

// Then s_out holds K (S_0 + X): the correction W_0 = K (S_0 + X) - X becomes the series' first
// order, and `multiple` becomes X + W_0 (its quadrupole, that of K (S_0 + X), the first sweep
// wrote).
@compute @workgroup_size(#{LINEAR_WORKGROUP})
fn warm_correction(@builtin(global_invocation_id) id: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let v = slot_voxel(id, groups);
    if v == PAST_THE_GRID {
        return;
    }
    correct(slot.volume + v, slot.multiple + v);
#ifdef MOMENTS
    for (var axis = 0u; axis < 3u; axis++) {
        correct(flux_element(slot.volume, cloud.n, v, axis), flux_element(slot.multiple, cloud.n, v, axis));
    }
#endif
}

fn correct(order: u32, solution: u32) {
    let scattered = s_out[order];
    s_out[order] = scattered - multiple[solution];
    multiple[solution] = scattered;
}
