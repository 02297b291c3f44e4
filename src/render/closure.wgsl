// Closing the scattering series (docs/illumination.md §4): the orders past M are summed as
// tail = a S_M + b S_(M-1) per channel, and added to the multiple-scattering volume (with
// moments, a F_M + b F_(M-1) to its flux; the quadrupole takes no tail). The coefficients come
// from the orders' density-weighted sums s_k = sum rho |S_k|: two geometric modes fitted to
// s_(M-3) .. s_M for the full series from its fourth order on, else one mode, the ratio of the
// last two. Every cloud of a volume pool in one dispatch: z workgroup i closes slot `work[i]`.
#import bevy_particle_clouds::types::{Slot, flat_invocation, flux_element}

@group(0) @binding(0) var<storage, read> slots: array<Slot>;
@group(0) @binding(1) var<storage, read> densities: array<f32>;
// The volumes of S_M and S_(M-1); S_(M-2) and S_(M-3) went through the same two before them.
@group(0) @binding(2) var<storage, read> last: array<vec4<f32>>;
@group(0) @binding(3) var<storage, read> before: array<vec4<f32>>;
@group(0) @binding(4) var<storage, read_write> multiple: array<vec4<f32>>;
// Per slot, from `slot.closure`, six vec4 (pools.rs, CLOSURE_ENTRIES): the sums s_(M-3) .. s_M
// (xyz), then the coefficients a and b.
@group(0) @binding(5) var<storage, read_write> closures: array<vec4<f32>>;
// A slot per z workgroup.
@group(0) @binding(6) var<storage, read> work: array<u32>;

const MAX_ORDER_RATIO: f32 = 0.995;
// The least relative rise of the sums' ratio resolved into two modes (RESOLVED_RATIO_STEP).
const RESOLVED_RATIO_STEP: f32 = 1e-4;
const THREADS: u32 = 256u;
const LAST: u32 = 0u;
const BEFORE: u32 = 1u;

var<workgroup> partial: array<vec3<f32>, THREADS>;

fn order_at(volume: u32, i: u32) -> vec3<f32> {
    if volume == LAST {
        return last[i].xyz;
    }
    return before[i].xyz;
}

// The density-weighted sum of |S| over a slot's grid in `volume` (LAST or BEFORE), for every
// thread of the workgroup. Each thread takes 4 voxels per iteration (a 256^3 grid stays within
// software rasterisers' 65535 loop iterations).
fn order_sum(i: u32, slot: Slot, volume: u32) -> vec3<f32> {
    // The previous sum's readers are done with `partial`.
    workgroupBarrier();
    let voxels = slot.cloud.n * slot.cloud.n * slot.cloud.n;
    var sum = vec3(0.0);
    for (var first = 4u * i; first < voxels; first += 4u * THREADS) {
        // Unrolled by hand: a nested loop would count against the same limit.
        let v = min(vec4(first) + vec4(0u, 1u, 2u, 3u), vec4(voxels - 1u));
        let inside = vec4<f32>(vec4(first) + vec4(0u, 1u, 2u, 3u) < vec4(voxels));
        let d = slot.density;
        let rho = vec4(densities[d + v.x], densities[d + v.y], densities[d + v.z], densities[d + v.w]) * inside;
        let s = slot.volume;
        sum += rho.x * abs(order_at(volume, s + v.x)) + rho.y * abs(order_at(volume, s + v.y))
            + rho.z * abs(order_at(volume, s + v.z)) + rho.w * abs(order_at(volume, s + v.w));
    }
    partial[i] = sum;
    workgroupBarrier();
    for (var stride = THREADS / 2u; stride > 0u; stride /= 2u) {
        if i < stride {
            partial[i] += partial[i + stride];
        }
        workgroupBarrier();
    }
    return partial[0];
}

// One mode: lambda = s_M / s_(M-1) clamped to [0, MAX_ORDER_RATIO], a = lambda / (1 - lambda).
fn geometric(last_sum: f32, before_sum: f32) -> f32 {
    let lambda = select(0.0, clamp(last_sum / before_sum, 0.0, MAX_ORDER_RATIO), before_sum > 0.0);
    return lambda / (1.0 - lambda);
}

// Two modes (SeriesTail::two_ratios): (a, b, 1), or (geometric a, 0, 0) where the sums' ratios
// do not rise by a resolved step, or the recurrence s_(k+2) = p s_(k+1) + q s_k they fit has
// no roots in [0, MAX_ORDER_RATIO].
fn two_ratios(s: array<f32, 4>) -> vec3<f32> {
    let fallback = vec3(geometric(s[3], s[2]), 0.0, 0.0);
    if !(s[0] > 0.0 && s[1] > 0.0 && s[2] > 0.0) {
        return fallback;
    }
    let x = vec3(s[1] / s[0], s[2] / s[1], s[3] / s[2]);
    if !(x.x < x.y && x.y < x.z && x.y - x.x > RESOLVED_RATIO_STEP * x.y) {
        return fallback;
    }
    let p = x.y * (x.x - x.z) / (x.x - x.y);
    let q = x.x * x.y * (x.z - x.y) / (x.x - x.y);
    let discriminant = p * p + 4.0 * q;
    if discriminant < 0.0 {
        return fallback;
    }
    let l1 = (p + sqrt(discriminant)) / 2.0;
    let l2 = (p - sqrt(discriminant)) / 2.0;
    if !(l2 >= 0.0 && l1 <= MAX_ORDER_RATIO) {
        return fallback;
    }
    let d = (1.0 - l1) * (1.0 - l2);
    return vec3(1.0 / d - 1.0, -l1 * l2 / d, 1.0);
}

// s_(M-3), after the iteration that writes it into the volume S_(M-1) will take.
@compute @workgroup_size(256)
fn sum_order_m3(@builtin(local_invocation_index) i: u32, @builtin(workgroup_id) group: vec3<u32>) {
    let slot = slots[work[group.z]];
    let sum = order_sum(i, slot, BEFORE);
    if i == 0u {
        closures[slot.closure] = vec4(sum, 0.0);
    }
}

// s_(M-2), after the iteration that writes it into the volume S_M will take.
@compute @workgroup_size(256)
fn sum_order_m2(@builtin(local_invocation_index) i: u32, @builtin(workgroup_id) group: vec3<u32>) {
    let slot = slots[work[group.z]];
    let sum = order_sum(i, slot, LAST);
    if i == 0u {
        closures[slot.closure + 1u] = vec4(sum, 0.0);
    }
}

// s_(M-1) and s_M, and the coefficients of one mode.
@compute @workgroup_size(256)
fn close_geometric(@builtin(local_invocation_index) i: u32, @builtin(workgroup_id) group: vec3<u32>) {
    let slot = slots[work[group.z]];
    let before_sum = order_sum(i, slot, BEFORE);
    let last_sum = order_sum(i, slot, LAST);
    if i == 0u {
        let c = slot.closure;
        closures[c + 2u] = vec4(before_sum, 0.0);
        closures[c + 3u] = vec4(last_sum, 0.0);
        let a = vec3(geometric(last_sum.x, before_sum.x), geometric(last_sum.y, before_sum.y), geometric(last_sum.z, before_sum.z));
        closures[c + 4u] = vec4(a, 0.0);
        closures[c + 5u] = vec4(0.0);
    }
}

// s_(M-1) and s_M, and the coefficients of two modes per channel (from s_(M-3) and s_(M-2),
// written by `sum_order_m3` and `sum_order_m2` in this series).
@compute @workgroup_size(256)
fn close_two_ratios(@builtin(local_invocation_index) i: u32, @builtin(workgroup_id) group: vec3<u32>) {
    let slot = slots[work[group.z]];
    let before_sum = order_sum(i, slot, BEFORE);
    let last_sum = order_sum(i, slot, LAST);
    if i == 0u {
        let c = slot.closure;
        closures[c + 2u] = vec4(before_sum, 0.0);
        closures[c + 3u] = vec4(last_sum, 0.0);
        let m3 = closures[c].xyz;
        let m2 = closures[c + 1u].xyz;
        let r = two_ratios(array(m3.x, m2.x, before_sum.x, last_sum.x));
        let g = two_ratios(array(m3.y, m2.y, before_sum.y, last_sum.y));
        let b = two_ratios(array(m3.z, m2.z, before_sum.z, last_sum.z));
        closures[c + 4u] = vec4(r.x, g.x, b.x, 0.0);
        closures[c + 5u] = vec4(r.y, g.y, b.y, 0.0);
    }
}

@compute @workgroup_size(#{LINEAR_WORKGROUP})
fn extrapolate(@builtin(global_invocation_id) id: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let slot = slots[work[id.z]];
    let v = flat_invocation(id, groups);
    if v >= slot.cloud.n * slot.cloud.n * slot.cloud.n {
        return;
    }
    let a = vec4(closures[slot.closure + 4u].xyz, 0.0);
    let b = vec4(closures[slot.closure + 5u].xyz, 0.0);
    var tail = last[slot.volume + v] * a + before[slot.volume + v] * b;
    // Two modes fitted to the sums may leave a voxel whose orders fall faster than either a
    // negative tail; the full series' orders are not negative. One mode keeps S_M's sign (a warm
    // restart's correction is signed).
    tail = select(tail, max(tail, vec4(0.0)), b != vec4(0.0));
    let m = slot.multiple + v;
    // Never negative: the full series' orders are not; a warm restart's truncated correction may
    // overshoot where the light fell.
    multiple[m] = max(multiple[m] + tail, vec4(0.0));
#ifdef MOMENTS
    let n = slot.cloud.n;
    for (var axis = 0u; axis < 3u; axis++) {
        let flux = flux_element(slot.volume, n, v, axis);
        multiple[flux_element(slot.multiple, n, v, axis)] += last[flux] * a + before[flux] * b;
    }
#endif
}
