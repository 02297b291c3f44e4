// Voxelize: every particle deposits its mass into its cloud's (fine) density grid
// (docs/illumination.md §1), as a gather that writes each voxel once, with no float atomic. A
// particle wider than 32 voxels deposits on a coarser density level instead; the levels are then
// enlarged into the fine grid, coarsest first.
//
// Each level is cut into bricks of VOXEL_BRICK³ voxels. The particles are binned by the brick
// of their centre (count, scan, scatter: integer atomics, whose results do not depend on the
// order), each brick's list is sorted by particle, and each particle's kernel sum W is reduced
// in a fixed order. Then one workgroup per brick sums, for each of its voxels, every particle
// binned within reach, read in batches through workgroup memory: the same sums in the same order
// on every run, so the density is bit-identical run to run, and coincident particles cost what
// spread ones do.
//
// Every cloud of a volume pool in one dispatch: z workgroup i voxelizes `work[i]`, whose particles
// were copied into `particles` from element `work[i].y` on.
#import bevy_particle_clouds::types::{Particle, DensityLevels, Slot, KERNEL_VOLUME, kernel, voxel_index}

const BRICK: u32 = #{VOXEL_BRICK}u;
const THREADS: u32 = #{BRICK_WORKGROUP}u;
// An item's words in `bricks` start with its levels' reach, then the number of its bricks that
// a particle reaches.
const REACH_WORDS: u32 = 8u;
const MARKED_WORD: u32 = REACH_WORDS;
const HEADER_WORDS: u32 = REACH_WORDS + 1u;
// Particles whose kernel sums one workgroup reduces, one after the other.
const SUMS_PER_GROUP: u32 = 8u;
// A brick's list up to this long is sorted by one invocation; longer, by the workgroup.
const SHORT_LIST: u32 = 32u;

@group(0) @binding(0) var<storage, read> slots: array<Slot>;
// The particles of every cloud voxelized this frame, one after the other.
@group(0) @binding(1) var<storage, read> particles: array<Particle>;
// Every slot's density levels, the fine grid first; a slot's are cleared to zero before the
// passes.
@group(0) @binding(2) var<storage, read_write> density: array<f32>;
// Per particle of `particles`: +W, its kernel's sum over the voxel centres in its support; or
// -S, a sub-voxel particle's trilinear weights' sum over the corners inside its level; or 0 for
// a particle that deposits nothing.
@group(0) @binding(3) var<storage, read_write> totals: array<f32>;
// The levels' sizes and bricks (the same for every slot of a pool); `upsample_from` differs per
// upsample dispatch (a dynamic offset).
@group(0) @binding(4) var<uniform> levels: DensityLevels;
// (slot, first particle, first word in `bricks`, particles) per z workgroup.
@group(0) @binding(5) var<storage, read> work: array<vec4<u32>>;
// Per item, cleared to zero before the passes: REACH_WORDS words, each level's reach in bricks;
// the number of marked bricks (`scan_bricks`); then one word per brick, the levels one after the
// other: its particles (`bin`), then the first of its list (`scan_bricks`), then the end of its
// list, the next brick's first (`scatter`); then one word per brick again, 1 where a particle's
// deposit reaches it (`bin`); then the marked bricks, ascending (`scan_bricks`).
@group(0) @binding(6) var<storage, read_write> bricks: array<atomic<u32>>;
// Per particle of `particles`: item-local particle indices, brick after brick, ascending within
// a brick after `sort_bricks`.
@group(0) @binding(7) var<storage, read_write> binned: array<u32>;
// The gather's indirect dispatches, (x, y, z) each: the host writes x and z (the items), and
// `scan_bricks` raises y until x·y workgroups cover every item's marked bricks. Bound to a
// stand-in in the gather's own bind group, which reads this buffer as its dispatch instead.
@group(0) @binding(8) var<storage, read_write> gather_groups: array<atomic<u32>>;

// The item's cloud's fine grid: its corner (m) and voxel size (m), and the first element of its
// levels in `density`. Read field by field: every invocation of every pass reads them, and the
// slot holds far more.
var<private> grid_origin: vec3<f32>;
var<private> fine_h: f32;
var<private> first_density: u32;
// (slot, first particle, first word in `bricks`, particles): the count copied into `particles`,
// which a slot's uniform may not hold yet in the frame the particles change.
var<private> item: vec4<u32>;

fn begin(z: u32) {
    item = work[z];
    grid_origin = slots[item.x].fine.grid_origin;
    fine_h = slots[item.x].fine.h;
    first_density = slots[item.x].fine_density;
}

// One density level: voxels per side, its first element in `density`, its voxel size, its first
// brick among the item's bricks, and bricks per side.
struct Level {
    n: u32,
    offset: u32,
    h: f32,
    first_brick: u32,
    bricks: u32,
}

fn level_at(l: u32) -> Level {
    let size = levels.size_offset[l];
    return Level(size.x, first_density + size.y, fine_h * f32(1u << l), size.z, size.w);
}

// Bricks of an item, over every level.
fn brick_count() -> u32 {
    let last = levels.size_offset[levels.count - 1u];
    return last.z + last.w * last.w * last.w;
}

// The item's first word of its bricks' marks, and of its list of marked bricks.
fn marks_word() -> u32 {
    return item.z + HEADER_WORDS + brick_count();
}

fn marked_list_word() -> u32 {
    return item.z + HEADER_WORDS + 2u * brick_count();
}

// The finest level on which a particle of radius `r` spans at most `max_radius` voxels, else the
// coarsest (`density_level` in src/math.rs).
fn particle_level(r: f32) -> u32 {
    var l = 0u;
    while l + 1u < levels.count && r > levels.max_radius * level_at(l).h {
        l++;
    }
    return l;
}

// A particle's footprint on its level: its centre in voxel coordinates, its radius in voxels (for
// its mass), the radius of the kernel it deposits with (narrower on a coarse level, by what the
// upsampling spreads: `level_kernel_radius` in src/math.rs), and the range of voxels inside that
// kernel's support.
struct Footprint {
    l: u32,
    level: Level,
    g: vec3<f32>,
    r_voxels: f32,
    kernel_voxels: f32,
    lo: vec3<i32>,
    hi: vec3<i32>,
}

fn footprint(particle: Particle) -> Footprint {
    let r = particle.position_radius.w;
    let l = particle_level(r);
    let level = level_at(l);
    let g = (particle.position_radius.xyz - grid_origin) / level.h - 0.5;
    let narrowing = levels.kernel_narrowing * (level.h * level.h - fine_h * fine_h);
    let kernel_voxels = select(sqrt(max(r * r - narrowing, 0.0)), r, l == 0u) / level.h;
    let lo = max(vec3<i32>(ceil(g - kernel_voxels)), vec3(0));
    let hi = min(vec3<i32>(floor(g + kernel_voxels)), vec3(i32(level.n) - 1));
    return Footprint(l, level, g, r / level.h, kernel_voxels, lo, hi);
}

// The kernel's weight at offset `d` (voxels) from the centre, of a kernel of 1 / radius² `inv_k2`.
fn kernel_weight(d: vec3<f32>, inv_k2: f32) -> f32 {
    return kernel(dot(d, d) * inv_k2);
}

// A sub-voxel particle's trilinear weight at offset `d` (voxels): its mass goes to the 8 voxel
// centres around it.
fn splat_weight(d: vec3<f32>) -> f32 {
    let w = max(vec3(1.0) - abs(d), vec3(0.0));
    return w.x * w.y * w.z;
}

fn inv_k2_of(f: Footprint) -> f32 {
    return 1.0 / (f.kernel_voxels * f.kernel_voxels);
}

// A particle's word in `bricks`: the brick of its centre on its level.
fn brick_word(f: Footprint) -> u32 {
    let side = f.level.bricks;
    let b = vec3<u32>(clamp(vec3<i32>(floor(f.g / f32(BRICK))), vec3(0), vec3(i32(side) - 1)));
    return item.z + HEADER_WORDS + f.level.first_brick + b.x + side * (b.y + side * b.z);
}

// Bricks from a particle's centre brick to the farthest brick its deposit reaches (a splat
// reaches one voxel; the centre brick is clamped into the level, hence the extra voxel).
fn reach_of(f: Footprint) -> u32 {
    let voxels = max(f.kernel_voxels, 1.0) + 1.0;
    return u32(min(ceil(voxels / f32(BRICK)), f32(f.level.bricks)));
}

// The item's particle that invocation `id` handles, if any, as an index into `particles`.
fn particle_of(id: vec3<u32>) -> i32 {
    begin(id.z);
    if id.x >= item.w || particles[item.y + id.x].density.x <= 0.0 {
        return -1;
    }
    return i32(item.y + id.x);
}

// Binning, pass 1: every particle counts itself in its centre's brick, widens its level's
// reach, and marks the bricks it deposits on.
@compute @workgroup_size(#{LINEAR_WORKGROUP})
fn bin(@builtin(global_invocation_id) id: vec3<u32>) {
    let i = particle_of(id);
    if i < 0 {
        return;
    }
    let f = footprint(particles[i]);
    atomicAdd(&bricks[brick_word(f)], 1u);
    atomicMax(&bricks[item.z + f.l], reach_of(f));
    // Mark the bricks its deposit (kernel or splat) can reach, so that the others skip it.
    let n = vec3(i32(f.level.n) - 1);
    let base = vec3<i32>(floor(f.g));
    let lo = vec3<u32>(clamp(min(f.lo, base), vec3(0), n)) / BRICK;
    let hi = vec3<u32>(clamp(max(f.hi, base + 1), vec3(0), n)) / BRICK;
    let side = f.level.bricks;
    let marks = marks_word() + f.level.first_brick;
    for (var z = lo.z; z <= hi.z; z++) {
        for (var y = lo.y; y <= hi.y; y++) {
            for (var x = lo.x; x <= hi.x; x++) {
                atomicStore(&bricks[marks + x + side * (y + side * z)], 1u);
            }
        }
    }
}

var<workgroup> partial: array<u32, THREADS>;
var<workgroup> scan_total: u32;

// The sum of `value` over the workgroup's invocations before `t` (an exclusive scan); the sum
// over all of them is left in `scan_total`.
fn exclusive_scan(t: u32, value: u32) -> u32 {
    partial[t] = value;
    workgroupBarrier();
    for (var d = 1u; d < THREADS; d <<= 1u) {
        let before = select(0u, partial[max(t, d) - d], t >= d);
        workgroupBarrier();
        partial[t] += before;
        workgroupBarrier();
    }
    if t == THREADS - 1u {
        scan_total = partial[t];
    }
    let inclusive = partial[t];
    workgroupBarrier();
    return inclusive - value;
}

// Binning, pass 2, one workgroup per item, each invocation over a run of bricks: the bricks'
// counts become their lists' first elements, and the marked bricks a list, in order, that the
// gather's workgroups walk (so that bricks no particle reaches cost nothing).
@compute @workgroup_size(#{BRICK_WORKGROUP})
fn scan_bricks(@builtin(local_invocation_index) t: u32, @builtin(workgroup_id) group: vec3<u32>) {
    begin(group.z);
    let count = brick_count();
    let run = (count + THREADS - 1u) / THREADS;
    let first = min(t * run, count);
    let end = min(t * run + run, count);
    let counts = item.z + HEADER_WORDS;
    var sum = 0u;
    for (var b = first; b < end; b++) {
        sum += atomicLoad(&bricks[counts + b]);
    }
    var start = exclusive_scan(t, sum);
    for (var b = first; b < end; b++) {
        let c = atomicLoad(&bricks[counts + b]);
        atomicStore(&bricks[counts + b], start);
        start += c;
    }
    let marks = marks_word();
    var marked = 0u;
    for (var b = first; b < end; b++) {
        marked += atomicLoad(&bricks[marks + b]);
    }
    var at = marked_list_word() + exclusive_scan(t, marked);
    for (var b = first; b < end; b++) {
        if atomicLoad(&bricks[marks + b]) != 0u {
            atomicStore(&bricks[at], b);
            at++;
        }
    }
    if t == 0u {
        atomicStore(&bricks[item.z + MARKED_WORD], scan_total);
        for (var d = 0u; d + 2u < arrayLength(&gather_groups); d += 3u) {
            let x = max(atomicLoad(&gather_groups[d]), 1u);
            atomicMax(&gather_groups[d + 1u], (scan_total + x - 1u) / x);
        }
    }
}

// Binning, pass 3: every particle writes its index into its brick's list (in an order the
// hardware chooses, put right by `sort_bricks`).
@compute @workgroup_size(#{LINEAR_WORKGROUP})
fn scatter(@builtin(global_invocation_id) id: vec3<u32>) {
    let i = particle_of(id);
    if i < 0 {
        return;
    }
    let at = atomicAdd(&bricks[brick_word(footprint(particles[i]))], 1u);
    binned[item.y + at] = id.x;
}

// The item-local range of brick `b`'s list (after `scatter`).
fn brick_list(b: u32) -> vec2<u32> {
    let word = item.z + HEADER_WORDS + b;
    let start = select(0u, atomicLoad(&bricks[max(word, 1u) - 1u]), b > 0u);
    return vec2(start, atomicLoad(&bricks[word]));
}

fn insertion_sort(first: u32, count: u32) {
    for (var a = 1u; a < count; a++) {
        let x = binned[first + a];
        var b = a;
        while b > 0u && binned[first + b - 1u] > x {
            binned[first + b] = binned[first + b - 1u];
            b--;
        }
        binned[first + b] = x;
    }
}

// Sorts `binned[first .. first + count]` ascending with the whole workgroup (a bitonic network
// whose merges compare mirrored pairs, so that the missing elements past `count` act as
// +infinity and never move).
fn bitonic_sort(t: u32, first: u32, count: u32) {
    let padded = 1u << (32u - countLeadingZeros(count - 1u));
    for (var k = 2u; k <= padded; k <<= 1u) {
        for (var j = k >> 1u; j > 0u; j >>= 1u) {
            for (var first_pair = 0u; first_pair < padded / 2u; first_pair += THREADS) {
                let p = first_pair + t;
                let block = p / j;
                let offset = p % j;
                let a = block * 2u * j + offset;
                let b = select(a + j, block * 2u * j + 2u * j - 1u - offset, j == k >> 1u);
                if b < count {
                    let x = binned[first + a];
                    let y = binned[first + b];
                    if x > y {
                        binned[first + a] = y;
                        binned[first + b] = x;
                    }
                }
            }
            storageBarrier();
        }
    }
}

var<workgroup> long_lists: array<u32, THREADS>;
var<workgroup> long_count: atomic<u32>;
var<workgroup> shared_long: u32;
var<workgroup> shared_range: vec2<u32>;

// Binning, pass 4: every brick's list sorted by particle, so the gather sums in a fixed order.
// One invocation per brick sorts a short list; the workgroup sorts the long ones together.
@compute @workgroup_size(#{BRICK_WORKGROUP})
fn sort_bricks(@builtin(local_invocation_index) t: u32, @builtin(workgroup_id) group: vec3<u32>) {
    begin(group.z);
    // Cleared here: not every driver zeroes workgroup memory (lavapipe crashed on a stale count).
    if t == 0u {
        atomicStore(&long_count, 0u);
    }
    workgroupBarrier();
    let b = group.x * THREADS + t;
    if b < brick_count() {
        let list = brick_list(b);
        let count = list.y - list.x;
        if count > SHORT_LIST {
            long_lists[atomicAdd(&long_count, 1u)] = b;
        } else if count > 1u {
            insertion_sort(item.y + list.x, count);
        }
    }
    workgroupBarrier();
    if t == 0u {
        shared_long = atomicLoad(&long_count);
    }
    let long = workgroupUniformLoad(&shared_long);
    for (var i = 0u; i < long; i++) {
        if t == 0u {
            shared_range = brick_list(long_lists[i]);
        }
        let list = workgroupUniformLoad(&shared_range);
        bitonic_sort(t, item.y + list.x, list.y - list.x);
    }
}

var<workgroup> sums: array<f32, #{LINEAR_WORKGROUP}>;

// The sum a particle's deposit is normalised by (see `totals`), from `w`, its kernel's sum.
fn total_of(f: Footprint, w: f32) -> f32 {
    if f.r_voxels >= 1.0 && w > 0.0 {
        return w;
    }
    var inside = 0.0;
    let base = vec3<i32>(floor(f.g));
    for (var corner = 0u; corner < 8u; corner++) {
        let v = base + vec3<i32>(vec3(corner & 1u, (corner >> 1u) & 1u, corner >> 2u));
        if all(v >= vec3(0)) && all(v < vec3(i32(f.level.n))) {
            inside += splat_weight(vec3<f32>(v) - f.g);
        }
    }
    return -inside;
}

// Every particle's kernel sum W (the normalisation that makes the deposit mass-exact): the
// workgroup's invocations each sum rows of the support, then add their sums in a fixed tree.
// `SUMS_PER_GROUP` particles per workgroup, the workgroups flattened over x and y.
@compute @workgroup_size(#{LINEAR_WORKGROUP})
fn kernel_sums(
    @builtin(local_invocation_index) t: u32,
    @builtin(workgroup_id) group: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
) {
    begin(group.z);
    let first = (group.x + group.y * groups.x) * SUMS_PER_GROUP;
    for (var k = 0u; k < SUMS_PER_GROUP; k++) {
        let p = first + k;
        var sum = 0.0;
        var f: Footprint;
        let present = p < item.w && particles[item.y + p].density.x > 0.0;
        if present {
            f = footprint(particles[item.y + p]);
            let size = max(f.hi - f.lo + 1, vec3(0));
            let inv_k2 = inv_k2_of(f);
            if f.r_voxels >= 1.0 {
                for (var row = t; row < u32(size.y * size.z); row += #{LINEAR_WORKGROUP}u) {
                    let yz = f.lo.yz + vec2(i32(row) % size.y, i32(row) / size.y);
                    for (var x = f.lo.x; x <= f.hi.x; x++) {
                        sum += kernel_weight(vec3<f32>(vec3(x, yz)) - f.g, inv_k2);
                    }
                }
            }
        }
        sums[t] = sum;
        workgroupBarrier();
        for (var half = #{LINEAR_WORKGROUP}u / 2u; half > 0u; half >>= 1u) {
            if t < half {
                sums[t] += sums[t + half];
            }
            workgroupBarrier();
        }
        if t == 0u && p < item.w {
            totals[item.y + p] = select(0.0, total_of(f, sums[0]), present);
        }
        workgroupBarrier();
    }
}

// A particle as the gather reads it: its centre in voxels of its level, 1 / its kernel's radius²
// (negative: splatted trilinearly), and the density it adds per unit of weight.
struct Candidate {
    g: vec3<f32>,
    inv_k2: f32,
    scale: f32,
}

// The item's particle `p` as the gather of the brick of voxels `lo ..= hi` reads it; its density
// per unit of weight is 0 where its support misses the brick (a step the brick skips).
fn candidate(p: u32, lo: vec3<f32>, hi: vec3<f32>) -> Candidate {
    let particle = particles[item.y + p];
    let f = footprint(particle);
    let total = totals[item.y + p];
    // Mass / the level's voxel volume, in density units; (r/h)^3 avoids overflow for huge
    // particles.
    let per_voxel = KERNEL_VOLUME * particle.density.x * f.r_voxels * f.r_voxels * f.r_voxels;
    let splat = total < 0.0;
    // A kernel's support is a ball, a splat's a box of ±1 voxel: each misses the brick where the
    // brick's nearest point to the centre weighs nothing (by the weights' own arithmetic, which
    // only grows farther out, so no weight is dropped).
    let out = f.g - clamp(f.g, lo, hi);
    let inv_k2 = inv_k2_of(f);
    let misses = select(dot(out, out) * inv_k2 >= 1.0, any(abs(out) >= vec3(1.0)), splat);
    let scale = select(per_voxel / abs(total), 0.0, total == 0.0 || misses);
    return Candidate(f.g, select(inv_k2, -1.0, splat), scale);
}

fn weight(c: Candidate, v: vec3<u32>) -> f32 {
    let d = vec3<f32>(v) - c.g;
    if c.inv_k2 < 0.0 {
        return splat_weight(d);
    }
    return kernel_weight(d, c.inv_k2);
}

// A candidate's density at two voxels (none where its support misses the brick).
fn add(near: Candidate, voxel: vec3<u32>, other: vec3<u32>) -> vec2<f32> {
    if near.scale == 0.0 {
        return vec2(0.0);
    }
    return near.scale * vec2(weight(near, voxel), weight(near, other));
}

var<workgroup> batch: array<Candidate, THREADS>;
// Per row of neighbour bricks (a run of consecutive bricks, so one run of `binned`): its first
// element, and the candidates of the rows before it.
var<workgroup> row_first: array<u32, THREADS>;
var<workgroup> row_before: array<u32, THREADS>;
var<workgroup> shared_count: u32;
// The workgroup's brick and its level's reach, or none.
var<workgroup> shared_brick: vec2<u32>;

// The candidate `c`'s particle among the rows' runs (`rows` of them).
fn candidate_particle(c: u32, rows: u32) -> u32 {
    var lo = 0u;
    var hi = rows - 1u;
    while lo < hi {
        let mid = (lo + hi + 1u) / 2u;
        if row_before[mid] <= c {
            lo = mid;
        } else {
            hi = mid - 1u;
        }
    }
    return binned[item.y + row_first[lo] + c - row_before[lo]];
}

// The brick `index` of an item: its level, its brick coordinates there, the level's bricks and
// voxels per side. Read from the uniform alone, so that the gather's loops stay uniform.
struct Brick {
    l: u32,
    at: vec3<u32>,
    side: u32,
    n: u32,
}

fn brick_at(index: u32) -> Brick {
    var l = 0u;
    while l + 1u < levels.count && index >= levels.size_offset[l + 1u].z {
        l++;
    }
    let size = levels.size_offset[l];
    let b = index - size.z;
    return Brick(l, vec3(b % size.w, (b / size.w) % size.w, b / (size.w * size.w)), size.w, size.x);
}

// The gather, one workgroup per marked brick (an indirect dispatch, flattened over x and y):
// each invocation sums two voxels' density over every particle binned within its level's
// reach, batch by batch through workgroup memory, and writes them once. Bricks no particle
// reaches are not in the list: their voxels stay as cleared.
@compute @workgroup_size(#{BRICK_WORKGROUP})
fn gather(
    @builtin(local_invocation_index) t: u32,
    @builtin(workgroup_id) group: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
) {
    begin(group.z);
    let in_list = group.x + group.y * groups.x;
    if t == 0u {
        shared_brick = vec2(0u);
        if in_list < atomicLoad(&bricks[item.z + MARKED_WORD]) {
            let b = atomicLoad(&bricks[marked_list_word() + in_list]);
            shared_brick = vec2(b, atomicLoad(&bricks[item.z + brick_at(b).l]));
        }
    }
    let chosen = workgroupUniformLoad(&shared_brick);
    let reach = chosen.y;
    // Past this item's marked bricks (the dispatch covers the item with the most).
    if reach == 0u {
        return;
    }
    let brick = brick_at(chosen.x);
    let lo = vec3<u32>(max(vec3<i32>(brick.at) - i32(reach), vec3(0)));
    let hi = min(brick.at + reach, vec3(brick.side - 1u));
    let size = hi - lo + 1u;
    let voxel = brick.at * BRICK + vec3(t % BRICK, (t / BRICK) % BRICK, t / (BRICK * BRICK));
    let other = voxel + vec3(0u, 0u, THREADS / (BRICK * BRICK));
    let corner = vec3<f32>(brick.at * BRICK);
    var sum = vec2(0.0);
    for (var first_row = 0u; first_row < size.y * size.z; first_row += THREADS) {
        let rows = min(size.y * size.z - first_row, THREADS);
        if t < rows {
            let row = first_row + t;
            let y = lo.y + row % size.y;
            let z = lo.z + row / size.y;
            let first = levels.size_offset[brick.l].z + lo.x + brick.side * (y + brick.side * z);
            let run = vec2(brick_list(first).x, brick_list(first + size.x - 1u).y);
            row_first[t] = run.x;
            row_before[t] = run.y - run.x;
        }
        workgroupBarrier();
        if t == 0u {
            var before = 0u;
            for (var r = 0u; r < rows; r++) {
                let count = row_before[r];
                row_before[r] = before;
                before += count;
            }
            shared_count = before;
        }
        let count = workgroupUniformLoad(&shared_count);
        for (var first = 0u; first < count; first += THREADS) {
            if first + t < count {
                batch[t] = candidate(candidate_particle(first + t, rows), corner, corner + f32(BRICK - 1u));
            }
            workgroupBarrier();
            // Four candidates an iteration: software rasterisers cut an invocation off after
            // 65535 iterations, and a brick may read hundreds of thousands of candidates.
            let end = min(count - first, THREADS);
            var c = 0u;
            for (; c + 4u <= end; c += 4u) {
                sum += add(batch[c], voxel, other) + add(batch[c + 1u], voxel, other)
                    + add(batch[c + 2u], voxel, other) + add(batch[c + 3u], voxel, other);
            }
            for (; c < end; c++) {
                sum += add(batch[c], voxel, other);
            }
            workgroupBarrier();
        }
    }
    let offset = level_at(brick.l).offset;
    if all(voxel < vec3(brick.n)) {
        density[offset + voxel_index(voxel, brick.n)] = sum.x;
    }
    if all(other < vec3(brick.n)) {
        density[offset + voxel_index(other, brick.n)] = sum.y;
    }
}

// The density weights of fine voxel `i` on the coarse voxels (i >> 1) - 1 + t, t = 0, 1, 2, one
// axis of a level of `fine_n` voxels under one of `coarse_n`. Coarse voxel J gives 1/8, 3/8, 3/8
// and 1/8 of its mass to fine voxels 2J - 1 ..= 2J + 2; a share that would leave the level goes to
// its edge voxel, so no mass is lost. Density weights are twice the shares (a fine voxel is half
// as wide); inside, they are trilinear interpolation's.
fn prolongation(i: u32, fine_n: u32, coarse_n: u32) -> vec3<f32> {
    var w = vec3(0.0);
    for (var t = 0; t < 3; t++) {
        let j = i32(i >> 1u) - 1 + t;
        if j < 0 || j >= i32(coarse_n) {
            continue;
        }
        for (var d = -1; d <= 2; d++) {
            if clamp(2 * j + d, 0, i32(fine_n) - 1) == i32(i) {
                w[t] += select(0.75, 0.25, d == -1 || d == 2);
            }
        }
    }
    return w;
}

// Once per coarse level, coarsest first: level `upsample_from` enlarged by `prolongation` on every
// axis is added to the level below. One invocation per column of the level below, whose voxels
// only it writes; z workgroup i enlarges `work[i]`'s levels.
@compute @workgroup_size(#{SLICE_WORKGROUP}, #{SLICE_WORKGROUP}, 1)
fn upsample(@builtin(global_invocation_id) id: vec3<u32>) {
    begin(id.z);
    let coarse = level_at(levels.upsample_from);
    let fine = level_at(levels.upsample_from - 1u);
    if any(id.xy >= vec2(fine.n)) {
        return;
    }
    let wx = prolongation(id.x, fine.n, coarse.n);
    let wy = prolongation(id.y, fine.n, coarse.n);
    for (var z = 0u; z < fine.n; z++) {
        let v = vec3(id.xy, z);
        let wz = prolongation(z, fine.n, coarse.n);
        let base = vec3<i32>(v >> vec3(1u)) - 1;
        var sum = 0.0;
        for (var c = 0; c < 3; c++) {
            for (var b = 0; b < 3; b++) {
                for (var a = 0; a < 3; a++) {
                    let weight = wx[a] * wy[b] * wz[c];
                    if weight > 0.0 {
                        let j = vec3<u32>(base + vec3(a, b, c));
                        sum += weight * density[coarse.offset + voxel_index(j, coarse.n)];
                    }
                }
            }
        }
        density[fine.offset + voxel_index(v, fine.n)] += sum;
    }
}
