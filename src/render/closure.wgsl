// Closing the scattering series (docs/illumination.md §4): the orders past M are taken as
// geometric with the per-channel ratio of the last two, lambda = sum rho |S_M| / sum rho |S_{M-1}|
// (the absolute values matter for a warm restart's correction, whose orders may be negative),
// and S_M lambda / (1 - lambda) is added to the multiple-scattering volume (with moments, its
// flux and quadrupole alike). Every cloud of a volume pool in one dispatch: z
// workgroup i closes slot `work[i]`.
#import bevy_particle_clouds::types::{Slot, flat_invocation, flux_element, quadrupole_element}

@group(0) @binding(0) var<storage, read> slots: array<Slot>;
@group(0) @binding(1) var<storage, read> densities: array<f32>;
// S_M and S_{M-1}.
@group(0) @binding(2) var<storage, read> last: array<vec4<f32>>;
@group(0) @binding(3) var<storage, read> before: array<vec4<f32>>;
@group(0) @binding(4) var<storage, read_write> multiple: array<vec4<f32>>;
// lambda per channel (xyz), one per slot.
@group(0) @binding(5) var<storage, read_write> ratio: array<vec4<f32>>;
// A slot per z workgroup.
@group(0) @binding(6) var<storage, read> work: array<u32>;

const MAX_ORDER_RATIO: f32 = 0.995;
const THREADS: u32 = 256u;

var<workgroup> numerators: array<vec3<f32>, THREADS>;
var<workgroup> denominators: array<vec3<f32>, THREADS>;

// One workgroup: the two density-weighted sums, then lambda. Each thread takes 4 voxels per
// iteration (a 256^3 grid stays within software rasterisers' 65535 loop iterations).
@compute @workgroup_size(256)
fn order_ratio(@builtin(local_invocation_index) i: u32, @builtin(workgroup_id) group: vec3<u32>) {
    let slot = slots[work[group.z]];
    let voxels = slot.cloud.n * slot.cloud.n * slot.cloud.n;
    let d = slot.density;
    let s = slot.volume;
    var numerator = vec3(0.0);
    var denominator = vec3(0.0);
    for (var first = 4u * i; first < voxels; first += 4u * THREADS) {
        // Unrolled by hand: a nested loop would count against the same limit.
        let v = min(vec4(first) + vec4(0u, 1u, 2u, 3u), vec4(voxels - 1u));
        let inside = vec4<f32>(vec4(first) + vec4(0u, 1u, 2u, 3u) < vec4(voxels));
        let rho = vec4(densities[d + v.x], densities[d + v.y], densities[d + v.z], densities[d + v.w]) * inside;
        numerator += rho.x * abs(last[s + v.x].xyz) + rho.y * abs(last[s + v.y].xyz)
            + rho.z * abs(last[s + v.z].xyz) + rho.w * abs(last[s + v.w].xyz);
        denominator += rho.x * abs(before[s + v.x].xyz) + rho.y * abs(before[s + v.y].xyz)
            + rho.z * abs(before[s + v.z].xyz) + rho.w * abs(before[s + v.w].xyz);
    }
    numerators[i] = numerator;
    denominators[i] = denominator;
    workgroupBarrier();
    for (var stride = THREADS / 2u; stride > 0u; stride /= 2u) {
        if i < stride {
            numerators[i] += numerators[i + stride];
            denominators[i] += denominators[i + stride];
        }
        workgroupBarrier();
    }
    if i == 0u {
        let den = denominators[0];
        let lambda = clamp(numerators[0] / max(den, vec3(1e-30)), vec3(0.0), vec3(MAX_ORDER_RATIO));
        ratio[slot.ratio] = vec4(select(vec3(0.0), lambda, den > vec3(0.0)), 0.0);
    }
}

@compute @workgroup_size(#{LINEAR_WORKGROUP})
fn extrapolate(@builtin(global_invocation_id) id: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let slot = slots[work[id.z]];
    let v = flat_invocation(id, groups);
    if v >= slot.cloud.n * slot.cloud.n * slot.cloud.n {
        return;
    }
    let tail = vec4(ratio[slot.ratio].xyz, 0.0);
    let k = tail / (1.0 - tail);
    let m = slot.multiple + v;
    // Never negative: the full series' orders are not; a warm restart's truncated correction may
    // overshoot where the light fell.
    multiple[m] = max(multiple[m] + last[slot.volume + v] * k, vec4(0.0));
#ifdef MOMENTS
    let n = slot.cloud.n;
    for (var axis = 0u; axis < 3u; axis++) {
        multiple[flux_element(slot.multiple, n, v, axis)] += last[flux_element(slot.volume, n, v, axis)] * k;
    }
    for (var c = 0u; c < 5u; c++) {
        multiple[quadrupole_element(slot.multiple, n, v, c)] += last[quadrupole_element(slot.volume, n, v, c)] * k;
    }
#endif
}
