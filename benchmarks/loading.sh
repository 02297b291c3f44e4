#!/usr/bin/env bash
# How long the `render` tool takes to load CSV particle files (docs/benchmark/loading.md):
#   benchmarks/loading.sh RENDER_BINARY [RENDER_BINARY ...]
# Writes a 38,000-line CSV cloud (the paper's particle count, 5 lights), 100,000 coincident
# particles and 2,000,000 coincident particles into a temporary folder, then runs each binary
# on each scene twice, alternating, and prints the tool's own "loaded in" line. Each run is
# stopped once the scene has loaded: this measures loading, not rendering.
set -euo pipefail
[ $# -ge 1 ] || { echo "usage: $0 RENDER_BINARY [RENDER_BINARY ...]" >&2; exit 2; }
dir=$(mktemp -d)
python3 - "$dir" <<'PY'
import random, struct, sys
d = sys.argv[1]
random.seed(1)
def f32(x): return struct.unpack('f', struct.pack('f', x))[0]
def shortest(x):
    v = f32(x)
    for p in range(1, 12):
        s = '%.*g' % (p, v)
        if f32(float(s)) == v: return s
    return repr(v)
def cloud():
    while True:
        x, y, z = (random.uniform(-1, 1) for _ in range(3))
        if x * x + y * y + z * z < 1: break
    return 2.5 * x, 1.2 * y + 0.7, 2.5 * z, random.uniform(0.05, 0.15), 1.0
def write(name, n, particle):
    with open(f'{d}/{name}.csv', 'w') as f:
        f.write('x,y,z,radius,density\n')
        for _ in range(n):
            f.write(','.join(shortest(v) for v in particle()) + '\n')
    with open(f'{d}/{name}.ron', 'w') as f:
        f.write('''(camera: (position: (0.0, 0.7, 7.0), look_at: (0.0, 0.7, 0.0), vertical_fov_degrees: 40.0,
  width: 64, height: 48),
 lights: [(direction: (-0.7, -0.5, -0.5), irradiance: (1.5, 1.45, 1.35)),
   (direction: (1.0, -0.2, -0.1), irradiance: (0.3, 0.5, 1.6)),
   (direction: (-1.0, -0.2, 0.3), irradiance: (1.6, 0.5, 0.3)),
   (direction: (0.2, -1.0, 0.1), irradiance: (0.6, 1.0, 0.6)),
   (direction: (0.1, 0.3, -1.0), irradiance: (0.8, 0.7, 1.0))],
 clouds: [(medium: (extinction: 3.0, albedo: 0.95), particles: Csv("%s.csv"))],
 settings: (volume_resolution: 32))''' % name)
write('paper_38k', 38000, cloud)
write('coincident_100k', 100000, lambda: (0.0, 0.0, 0.0, 0.05, 1.0))
write('coincident_2m', 2000000, lambda: (0.0, 0.0, 0.0, 0.05, 1.0))
PY
for round in 1 2; do
    for binary in "$@"; do
        for scene in paper_38k coincident_100k coincident_2m; do
            # A loader that has not finished within 5 minutes is reported as such.
            line=$(timeout 300 stdbuf -oL -eL "$binary" "$dir/$scene.ron" --out "$dir/out.png" 2>&1 \
                | grep -m1 "loaded in" || echo "not loaded within 300 s")
            echo "round $round, $binary, $scene: $line"
        done
    done
done
rm -rf "$dir"
