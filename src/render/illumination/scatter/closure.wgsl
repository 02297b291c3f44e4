// Closing the scattering series (docs/illumination.md §4): the orders past M sum to
// a S_M + b S_{M-1}, per channel, added to the multiple-scattering volume (with moments, their
// flux and quadrupole alike). The orders' sizes N_k = sum rho |S_k| (the absolute values matter
// for a warm restart's correction, whose orders may be negative) fit two geometric modes to the
// last four orders: N_{k+2} = p N_{k+1} - q N_k, and a = (p - q) / (1 - p + q),
// b = -q / (1 - p + q), blended with one mode's by a weight that falls continuously to 0 where the
// fit stops being two valid, well-conditioned modes (a switch would let the rounding of the sizes
// move the tail). One mode: the ratio lambda = N_M / N_{M-1}, a = lambda / (1 - lambda), b = 0;
// always so in a warm restart. Every cloud of a volume pool in one dispatch: z workgroup i closes
// slot `work[i]`. The constants are `reference::illumination`'s (a unit test keeps them equal).
#import bevy_particle_clouds::types::{Slot, flat_invocation, flux_element, quadrupole_element}

@group(0) @binding(0) var<storage, read> slots: array<Slot>;
@group(0) @binding(1) var<storage, read> densities: array<f32>;
// S_M and S_{M-1}.
@group(0) @binding(2) var<storage, read> last: array<vec4<f32>>;
@group(0) @binding(3) var<storage, read> before: array<vec4<f32>>;
@group(0) @binding(4) var<storage, read_write> multiple: array<vec4<f32>>;
// Per slot, 4 vec4: N_{M-3} (w: 1 once `order_sizes` stored them for this series), N_{M-2}, a, b.
@group(0) @binding(5) var<storage, read_write> closure: array<vec4<f32>>;
// A slot per z workgroup.
@group(0) @binding(6) var<storage, read> work: array<u32>;

const MAX_ORDER_RATIO: f32 = 0.995;
// The two-mode tail's weight: 0 at the first value of each pair, 1 from the second on
// (`two_mode_weight` in src/reference/illumination/scatter.rs). The modes' separation
// (1 - r2) / (1 - r1): nearer, the tail follows the orders' differences.
const MODE_SEPARATION: f32 = 1.5;
const MODE_SEPARATION_FULL: f32 = 2.0;
// y = |det| / N_{M-2}^2 (1 - r1), log-linear: the fit moves the tail by about e / y for a
// relative change e of the sizes.
const CONDITIONING: f32 = 1e-5;
const CONDITIONING_FULL: f32 = 1e-4;
// The slower ratio (down to full weight), and the faster (up).
const ORDER_RATIO_FULL: f32 = 0.99;
const FAST_RATIO_FULL: f32 = 0.02;
const THREADS: u32 = 256u;

var<workgroup> numerators: array<vec3<f32>, THREADS>;
var<workgroup> denominators: array<vec3<f32>, THREADS>;

// The sizes of the orders the two bindings hold, summed by one workgroup into element 0 of
// `numerators` (`last`) and `denominators` (`before`). Each thread takes 4 voxels per iteration
// (a 256^3 grid stays within software rasterisers' 65535 loop iterations).
fn order_sizes_of(slot: Slot, i: u32) {
    let voxels = slot.cloud.n * slot.cloud.n * slot.cloud.n;
    let d = slot.density;
    let s = slot.volume;
    // Compensated (Kahan) sums: the two-mode fit takes differences of the sizes' ratios.
    var numerator = vec3(0.0);
    var denominator = vec3(0.0);
    var numerator_lost = vec3(0.0);
    var denominator_lost = vec3(0.0);
    for (var first = 4u * i; first < voxels; first += 4u * THREADS) {
        // Unrolled by hand: a nested loop would count against the same limit.
        let v = min(vec4(first) + vec4(0u, 1u, 2u, 3u), vec4(voxels - 1u));
        let inside = vec4<f32>(vec4(first) + vec4(0u, 1u, 2u, 3u) < vec4(voxels));
        let rho = vec4(densities[d + v.x], densities[d + v.y], densities[d + v.z], densities[d + v.w]) * inside;
        let n = rho.x * abs(last[s + v.x].xyz) + rho.y * abs(last[s + v.y].xyz)
            + rho.z * abs(last[s + v.z].xyz) + rho.w * abs(last[s + v.w].xyz) - numerator_lost;
        let n_sum = numerator + n;
        numerator_lost = (n_sum - numerator) - n;
        numerator = n_sum;
        let b = rho.x * abs(before[s + v.x].xyz) + rho.y * abs(before[s + v.y].xyz)
            + rho.z * abs(before[s + v.z].xyz) + rho.w * abs(before[s + v.w].xyz) - denominator_lost;
        let b_sum = denominator + b;
        denominator_lost = (b_sum - denominator) - b;
        denominator = b_sum;
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
}

// Dispatched after the series' order M - 2, while the bindings hold S_{M-2} and S_{M-3}: their
// sizes, kept for `order_ratio`.
@compute @workgroup_size(256)
fn order_sizes(@builtin(local_invocation_index) i: u32, @builtin(workgroup_id) group: vec3<u32>) {
    let slot = slots[work[group.z]];
    order_sizes_of(slot, i);
    if i == 0u {
        closure[4u * slot.ratio] = vec4(denominators[0], 1.0);
        closure[4u * slot.ratio + 1u] = vec4(numerators[0], 0.0);
    }
}

fn ramp(x: f32, zero: f32, one: f32) -> f32 {
    return clamp((x - zero) / (one - zero), 0.0, 1.0);
}

// The tail's coefficients (a, b) of one channel from the sizes N_{M-3}..N_M, blended by the
// two-mode weight with one mode's `a_one`.
fn two_modes(n: vec4<f32>, a_one: f32) -> vec2<f32> {
    let det = n.y * n.y - n.z * n.x;
    let p = (n.y * n.z - n.w * n.x) / det;
    let q = (n.z * n.z - n.y * n.w) / det;
    let disc = p * p - 4.0 * q;
    if !(disc >= 0.0) {
        return vec2(a_one, 0.0);
    }
    let r1 = 0.5 * (p + sqrt(disc));
    let r2 = 0.5 * (p - sqrt(disc));
    let conditioning = abs(det) / (n.y * n.y) * (1.0 - r1);
    if !(conditioning > CONDITIONING) || !(r1 < 1.0) {
        return vec2(a_one, 0.0);
    }
    let weight = ramp(log(conditioning), log(CONDITIONING), log(CONDITIONING_FULL))
        * ramp((1.0 - r2) / (1.0 - r1), MODE_SEPARATION, MODE_SEPARATION_FULL)
        * ramp(r1, MAX_ORDER_RATIO, ORDER_RATIO_FULL)
        * ramp(r2, 0.0, FAST_RATIO_FULL);
    if weight <= 0.0 {
        return vec2(a_one, 0.0);
    }
    let d = 1.0 - p + q;
    return vec2(weight * (p - q) / d + (1.0 - weight) * a_one, weight * -q / d);
}

// One workgroup: the last two orders' sizes, then the tail's coefficients.
@compute @workgroup_size(256)
fn order_ratio(@builtin(local_invocation_index) i: u32, @builtin(workgroup_id) group: vec3<u32>) {
    let slot = slots[work[group.z]];
    order_sizes_of(slot, i);
    if i != 0u {
        return;
    }
    let at = 4u * slot.ratio;
    let num = numerators[0];
    let den = denominators[0];
    let lambda = select(vec3(0.0), clamp(num / max(den, vec3(1e-30)), vec3(0.0), vec3(MAX_ORDER_RATIO)), den > vec3(0.0));
    var a = lambda / (1.0 - lambda);
    var b = vec3(0.0);
    if closure[at].w == 1.0 {
        let early = closure[at].xyz;
        let middle = closure[at + 1u].xyz;
        for (var c = 0u; c < 3u; c++) {
            let fit = two_modes(vec4(early[c], middle[c], den[c], num[c]), a[c]);
            a[c] = fit.x;
            b[c] = fit.y;
        }
    }
    // The stored sizes belong to this series only: a warm restart closes with one mode.
    closure[at] = vec4(0.0);
    closure[at + 2u] = vec4(a, 0.0);
    closure[at + 3u] = vec4(b, 0.0);
}

@compute @workgroup_size(#{LINEAR_WORKGROUP})
fn extrapolate(@builtin(global_invocation_id) id: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let slot = slots[work[id.z]];
    let v = flat_invocation(id, groups);
    if v >= slot.cloud.n * slot.cloud.n * slot.cloud.n {
        return;
    }
    let a = closure[4u * slot.ratio + 2u];
    let b = closure[4u * slot.ratio + 3u];
    let m = slot.multiple + v;
    // Never negative: the full series' orders are not; a warm restart's truncated correction may
    // overshoot where the light fell.
    // Where a channel has two modes, its tail lies between those of one mode with ratio 0 and
    // MAX_ORDER_RATIO (the energy bound holds whatever the fit), where one mode's lies already.
    let s_m = last[slot.volume + v];
    var tail = s_m * a + before[slot.volume + v] * b;
    let bound = s_m * (MAX_ORDER_RATIO / (1.0 - MAX_ORDER_RATIO));
    let bounded = clamp(tail, min(bound, vec4(0.0)), max(bound, vec4(0.0)));
    tail = select(tail, bounded, b != vec4(0.0));
    // A coarse grid's sum is a correction, of either sign.
    let sum = multiple[m] + tail;
    multiple[m] = select(max(sum, vec4(0.0)), sum, slot.coarse == 1u);
#ifdef MOMENTS
    let n = slot.cloud.n;
    for (var axis = 0u; axis < 3u; axis++) {
        let at = flux_element(slot.volume, n, v, axis);
        multiple[flux_element(slot.multiple, n, v, axis)] += last[at] * a + before[at] * b;
    }
    for (var c = 0u; c < 5u; c++) {
        let at = quadrupole_element(slot.volume, n, v, c);
        multiple[quadrupole_element(slot.multiple, n, v, c)] += last[at] * a + before[at] * b;
    }
#endif
}
