// Multiple scattering: one iteration n -> n + 1 (docs/illumination.md §4). Reads S_n, writes
// S_{n+1} and adds it to the multiple-scattering volume (after the sweeps, `accumulate_order`).
// Two stencils, one entry point each: the discrete-ordinates sweep and the paper's.
// Every cloud of a volume pool in one dispatch: z workgroup i scatters slot `work[i]`.
// An anisotropic medium's volumes hold angular moments beside their means (shader def MOMENTS):
// the sweep's source takes the P2 phase function of the transformed medium, and each order's
// flux and quadrupole are gathered from the radiance of every direction.
#import bevy_particle_clouds::types::{CloudParams, Slot, GroundMap, GROUND_MAP_SIDE, voxel_index, flat_invocation, flux_element, quadrupole_element, quadrupole_basis, quadrupole_weights, affine_point, affine_vector}

// One direction pair (o, -o) of the discrete-ordinates sweep, o's first non-zero component
// positive, with each direction's quadrature weights in the order's mean (and flux) and in its
// quadrupole (src/lattice.rs); `first` is 1 for the first of an iteration's dispatches (13 or
// 49, one per pair; it overwrites S_{n+1});
// `accumulate` is 0 for the first sweep of a warm restart (the paper's stencil then leaves
// `multiple` alone; the sweep never writes it: `accumulate_order` adds each order); `sky`
// is the sky's radiance and `boundary` 1 in the first iteration of a series, where the light
// entering the grid from outside (the sky's, and the ground's on lines that climb) comes in (so
// S_1 = K S_0 + their single scattering); else 0 and nothing enters.
// `pairs` is the number of pairs in the set.
struct SweepDirection {
    o: vec3<i32>,
    first: u32,
    accumulate: u32,
    sky: vec3<f32>,
    boundary: u32,
    mean_weight: f32,
    quadrupole_weight: f32,
    pairs: u32,
}

@group(0) @binding(0) var<storage, read> slots: array<Slot>;
#ifdef SWEEP_PER_ORDER
// One dispatch per order (`SweepDispatch::PerOrder`): every pair of the set from the bound one
// on, a dynamic-uniform stride apart. Each pair deposits its share into a volume of its own,
// `s_out` then being the pool's per-pair volumes, pair p's `p * arrayLength(&s_in)` in;
// `sum_pairs` adds them into the next order.
struct DirectionEntry {
    @size(#{DYNAMIC_UNIFORM_STRIDE}) d: SweepDirection,
}
@group(0) @binding(1) var<uniform> directions: array<DirectionEntry, #{MAX_SWEEP_PAIRS}>;
var<private> direction: SweepDirection;
#else
@group(0) @binding(1) var<uniform> direction: SweepDirection;
#endif
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
// Where this invocation's pair's volume starts in `s_out`: 0 but with SWEEP_PER_ORDER.
var<private> pair_base: u32;
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

// The medium the sweep goes through at voxel i, delta-M transformed (§4): its density
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
// scattering coefficient: its mean, plus with moments 3 g' F . w + (15/2) chi'_2 w^T Q w (the P2
// phase function of the transformed medium's moments).
fn order_in(i: u32, w: vec3<f32>) -> vec3<f32> {
    var s = s_in[slot.volume + i].xyz;
#ifdef MOMENTS
    var along = vec3(0.0);
    for (var axis = 0u; axis < 3u; axis++) {
        along += s_in[flux_element(slot.volume, cloud.n, i, axis)].xyz * w[axis];
    }
    var quadratic = vec3(0.0);
    let q = quadrupole_weights(w);
    for (var c = 0u; c < 5u; c++) {
        quadratic += s_in[quadrupole_element(slot.volume, cloud.n, i, c)].xyz * q[c];
    }
    s += 3.0 * cloud.scatter_anisotropy * along + 7.5 * cloud.scatter_second_moment * quadratic;
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

// int_0^tau exp(-t) u (1 - u) dt, u = t / tau: the weight of a segment's parabolic source term.
// Below 0.5 its series (the closed form cancels in f32).
fn curvature_weight(tau: f32) -> f32 {
    if tau < 0.5 {
        var term = tau;
        var sum = 0.0;
        for (var k = 0; k < 7; k++) {
            let kf = f32(k);
            sum += term / ((kf + 2.0) * (kf + 3.0));
            term *= -tau / (kf + 1.0);
        }
        return sum;
    }
    let e = exp(-tau);
    return segment_weights(tau).y - (2.0 - e * (tau * tau + 2.0 * tau + 2.0)) / (tau * tau);
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

// Radiance arriving at a voxel from its upwind neighbour's side: what arrived there, attenuated
// over the segment, plus the segment's own scattering J = albedo S, parabolic along it: linear
// between its ends less c/2 u (1 - u), c its second difference along the line (§4). `m` and
// `m_up` are the two ends' media (density, albedo), `j` and `j_up` their J.
fn transport(upwind: vec3<f32>, m: vec2<f32>, j: vec3<f32>, m_up: vec2<f32>, j_up: vec3<f32>, c: vec3<f32>, half_step: f32) -> vec3<f32> {
    let tau = cloud.k_local * (m.x + m_up.x) * half_step;
    let w = segment_weights(tau);
    return (1.0 - w.x) * upwind + j * w.x + (j_up - j) * w.y - c * (0.5 * curvature_weight(tau));
}

fn add_to(element: u32, share: vec4<f32>, overwrite: bool) {
    if overwrite {
        s_out[pair_base + element] = share;
    } else {
        s_out[pair_base + element] += share;
    }
}

// Voxel `voxel`'s share of the radiance arriving there travelling along w: its mean weight to
// the next order's mean (and with moments its flux), and with moments its quadrupole weight to
// the quadrupole (§4: gathering a P2 radiance's quadrupole integrates degree 4, which the mean's
// weights miss); added to what the volume held (its mean `held`, read ahead by the march), or
// written over it (`overwrite`, in an iteration's first dispatch). `multiple` takes the order
// once the iteration's sweeps are done (`accumulate_order`).
fn deposit(voxel: u32, radiance: vec3<f32>, w: vec3<f32>, overwrite: bool, held: vec4<f32>) {
    let share = vec4(radiance * direction.mean_weight, 0.0);
    s_out[pair_base + slot.volume + voxel] = held + share;
#ifdef MOMENTS
    let n = cloud.n;
    for (var axis = 0u; axis < 3u; axis++) {
        add_to(flux_element(slot.volume, n, voxel, axis), share * w[axis], overwrite);
    }
    let q = quadrupole_basis(w);
    let weighted = vec4(radiance * direction.quadrupole_weight, 0.0);
    for (var c = 0u; c < 5u; c++) {
        add_to(quadrupole_element(slot.volume, n, voxel, c), weighted * q[c], overwrite);
    }
#endif
}

// The mean the next order holds at voxel i so far: 0 where this dispatch writes it over.
fn held_mean(i: u32, overwrite: bool) -> vec4<f32> {
    if overwrite {
        return vec4(0.0);
    }
    return s_out[pair_base + slot.volume + i];
}

// One invocation per lattice line of direction o: marches it against o (radiance arriving from
// the +o side), then along o (from the -o side). The lines partition the grid, so each voxel is
// written by one invocation of this dispatch.
@compute @workgroup_size(#{LINEAR_WORKGROUP})
fn sweep(@builtin(global_invocation_id) id: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    begin(id.z);
#ifdef SWEEP_PER_ORDER
    // Row y of workgroups sweeps pair y, x its lines (those past its count decode to `rest` > 0).
    var rest = id.x;
    direction = directions[id.y].d;
    pair_base = id.y * arrayLength(&s_in);
    // The pair's volume holds the previous order's share: the first march writes over it.
    let overwrite = true;
#else
    var rest = flat_invocation(id, groups);
    let overwrite = direction.first != 0u;
#endif
    let n = i32(cloud.n);
    let o = direction.o;
    let step = abs(o);
    let f = max(step.x, max(step.y, step.z));
    let first_axis = select(select(2, 1, step.y == f), 0, step.x == f);
    // Decode the line (pipelines.rs, `sweep_lines`), where o has no negative component: the
    // first axis of largest step f starts at 0..f, the other moving axes at an offset in
    // -(ceil(n / f) - 1) |o_a|..n, the still axes anywhere.
    let reach = (n + f - 1) / f - 1;
    var start = vec3(0);
    for (var a = 0; a < 3; a++) {
        var span = cloud.n;
        var offset = 0;
        if a == first_axis {
            span = u32(f);
        } else if step[a] != 0 {
            offset = reach * step[a];
            span = cloud.n + u32(offset);
        }
        start[a] = i32(rest % span) - offset;
        rest /= span;
    }
    if rest != 0u {
        return;
    }
    // The positions t along the line inside the grid: 0 <= start + t step < n on every moving axis.
    var t0 = 0;
    var t1 = n;
    for (var a = 0; a < 3; a++) {
        if step[a] != 0 {
            t0 = max(t0, (max(-start[a], 0) + step[a] - 1) / step[a]);
            t1 = min(t1, (n - start[a] + step[a] - 1) / step[a]);
        }
    }
    if t0 >= t1 {
        return;
    }
    let flip = o < vec3(0);
    let half_step = 0.5 * cloud.h * length(vec3<f32>(o));
    // The direction the radiance arriving from the +o side travels in.
    let w = -normalize(vec3<f32>(o));
    // Against o: radiance arriving from the +o side, the boundary's entering the grid.
    march(start, flip, t1 - 1, -1, t1 - t0, w, half_step, overwrite);
    // Along o: radiance arriving from the -o side.
    march(start, flip, t0, 1, t1 - t0, -w, half_step, false);
}

// The source J = albedo S towards w at voxel i, and the voxel's medium.
struct LineNode {
    m: vec2<f32>,
    j: vec3<f32>,
}

fn line_node(i: u32, w: vec3<f32>) -> LineNode {
    let m = medium(i);
    return LineNode(m, m.y * order_in(i, w));
}

// Marches `count` voxels of a line from position `first` by `dt`, the radiance travelling along
// w, and deposits each voxel's share. It carries the last two voxels' sources and the next one's;
// each segment's curvature is the mean of its ends' second differences, those whose neighbours
// are both on the line. The march is a chain of dependent steps (one lattice line per
// invocation), each waiting on memory on a GPU: with SWEEP_READ_AHEAD each step loads the voxel
// two ahead and the next voxel's sum so far, whose latency its own arithmetic and stores then
// hide; without, each step loads what it needs as it needs it (a CPU adapter's SIMD lanes do
// better with less held). The same arithmetic in the same order either way.
fn march(start: vec3<i32>, flip: vec3<bool>, first: i32, dt: i32, count: i32, w: vec3<f32>, half_step: f32, overwrite: bool) {
    var radiance = entering(line_position(start, first, flip), w, half_step);
    var up = LineNode(vec2(0.0), vec3(0.0));
    var d_up = vec3(0.0);
    var has_d_up = false;
    var i = line_voxel(start, first, flip);
    var here = line_node(i, w);
#ifdef SWEEP_READ_AHEAD
    var i_next = 0u;
    var next = LineNode(vec2(0.0), vec3(0.0));
    if count > 1 {
        i_next = line_voxel(start, first + dt, flip);
        next = line_node(i_next, w);
    }
    var held = held_mean(i, overwrite);
#endif
    for (var k = 0; k < count; k++) {
        let has_next = k + 1 < count;
#ifdef SWEEP_READ_AHEAD
        var i_after = 0u;
        var after = LineNode(vec2(0.0), vec3(0.0));
        if k + 2 < count {
            i_after = line_voxel(start, first + (k + 2) * dt, flip);
            after = line_node(i_after, w);
        }
        var held_next = vec4(0.0);
        if has_next {
            held_next = held_mean(i_next, overwrite);
        }
#else
        var i_next = 0u;
        var next = LineNode(vec2(0.0), vec3(0.0));
        if has_next {
            i_next = line_voxel(start, first + (k + 1) * dt, flip);
            next = line_node(i_next, w);
        }
        let held = held_mean(i, overwrite);
#endif
        let has_d = k > 0 && has_next;
        let d = up.j - 2.0 * here.j + next.j;
        let ends = vec2(f32(has_d), f32(has_d_up));
        let c = (d * ends.x + d_up * ends.y) / max(ends.x + ends.y, 1.0);
        radiance = transport(radiance, here.m, here.j, up.m, up.j, c, half_step);
        deposit(i, radiance, w, overwrite, held);
        d_up = d;
        has_d_up = has_d;
        up = here;
        here = next;
        i = i_next;
#ifdef SWEEP_READ_AHEAD
        next = after;
        i_next = i_after;
        held = held_next;
#endif
    }
}

// After an accumulating iteration's sweeps: `multiple` += S_(n+1), and with moments its flux and
// quadrupole.
@compute @workgroup_size(#{LINEAR_WORKGROUP})
fn accumulate_order(@builtin(global_invocation_id) id: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let v = slot_voxel(id, groups);
    if v == PAST_THE_GRID {
        return;
    }
    for (var e = 0u; e < VOXEL_ELEMENTS; e++) {
        multiple[voxel_element(slot.multiple, v, e)] += s_out[voxel_element(slot.volume, v, e)];
    }
}

// The vec4 a voxel holds in each scattering volume: its mean, and with moments its flux (3) and
// quadrupole (5).
#ifdef MOMENTS
const VOXEL_ELEMENTS: u32 = 9u;
#else
const VOXEL_ELEMENTS: u32 = 1u;
#endif

// Element e (< VOXEL_ELEMENTS) of voxel v in the volume whose slot starts at `base`.
fn voxel_element(base: u32, v: u32, e: u32) -> u32 {
    if e == 0u {
        return base + v;
    }
    if e < 4u {
        return flux_element(base, cloud.n, v, e - 1u);
    }
    return quadrupole_element(base, cloud.n, v, e - 4u);
}

#ifdef SWEEP_PER_ORDER
// After a dispatch of every pair (SWEEP_PER_ORDER), bound with the pairs' volumes as `s_in`:
// the next order is their sum, in the pairs' order, and an accumulating iteration adds it to
// `multiple` (what `accumulate_order` does after one dispatch per pair). With moments, their
// flux and quadrupole alike.
@compute @workgroup_size(#{LINEAR_WORKGROUP})
fn sum_pairs(@builtin(global_invocation_id) id: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let v = slot_voxel(id, groups);
    if v == PAST_THE_GRID {
        return;
    }
    direction = directions[0].d;
    let stride = arrayLength(&s_out);
    for (var e = 0u; e < VOXEL_ELEMENTS; e++) {
        let order = voxel_element(slot.volume, v, e);
        var total = vec4(0.0);
        for (var p = 0u; p < direction.pairs; p++) {
            total += s_in[p * stride + order];
        }
        s_out[order] = total;
        if direction.accumulate != 0u {
            multiple[voxel_element(slot.multiple, v, e)] += total;
        }
    }
}
#endif

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
// moments, their flux and quadrupole alike.
@compute @workgroup_size(#{LINEAR_WORKGROUP})
fn warm_start(@builtin(global_invocation_id) id: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let v = slot_voxel(id, groups);
    if v == PAST_THE_GRID {
        return;
    }
    for (var e = 0u; e < VOXEL_ELEMENTS; e++) {
        let at = voxel_element(slot.volume, v, e);
        s_out[at] = s_in[at] + multiple[voxel_element(slot.multiple, v, e)];
    }
}

// Then s_out holds K (S_0 + X): the correction W_0 = K (S_0 + X) - X becomes the series' first
// order, and `multiple` becomes X + W_0. With moments, their flux and quadrupole alike.
@compute @workgroup_size(#{LINEAR_WORKGROUP})
fn warm_correction(@builtin(global_invocation_id) id: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let v = slot_voxel(id, groups);
    if v == PAST_THE_GRID {
        return;
    }
    for (var e = 0u; e < VOXEL_ELEMENTS; e++) {
        correct(voxel_element(slot.volume, v, e), voxel_element(slot.multiple, v, e));
    }
}

fn correct(order: u32, solution: u32) {
    let scattered = s_out[order];
    s_out[order] = scattered - multiple[solution];
    multiple[solution] = scattered;
}
