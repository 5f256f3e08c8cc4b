#!/usr/bin/env bash
# Two shards against two threads, interleaved: ROUNDS rounds of `run --threads 1`,
# `run --threads 2` and `cluster --shards 2 --threads 1` on SCENE for SECONDS simulated; per
# round and as medians, each one's real time and its ratio to one thread (this machine is
# noisy: runs side by side say more than one run of each), and the CPU each used per simulated
# second over one thread's (the work the split adds, whatever the cores' waits; a cluster's
# counts its shards and its launcher, whose Zenoh router carries the ghosts).
# docs/performance.md §11b, §11d.
#
#   scripts/shards-vs-threads.sh SCENE.toml [SECONDS=10] [ROUNDS=5]
set -euo pipefail
bin="${TWINSWARM:-$(dirname "$0")/../target/release/twinswarm}"
scene=${1:?usage: $0 SCENE.toml [SECONDS] [ROUNDS]}
seconds=${2:-10}
rounds=${3:-5}
# Real time and CPU seconds per simulated second of a `run --json` or `cluster --json`.
figures() {
    python3 -c '
import json, sys
d = json.load(sys.stdin)
cpu = d.get("cpu_per_sim_s") or float("nan")
print(d["real_time_factor"], cpu)'
}
for _ in $(seq "$rounds"); do
    one=$("$bin" run "$scene" --threads 1 --duration "$seconds" --no-bus --no-log --json 2>/dev/null | figures)
    two=$("$bin" run "$scene" --threads 2 --duration "$seconds" --no-bus --no-log --json 2>/dev/null | figures)
    shards=$("$bin" cluster "$scene" --shards 2 --threads 1 --duration "$seconds" --no-bus --json 2>/dev/null | figures)
    echo "$one $two $shards"
done | python3 -c '
import statistics as st, sys
rows = [[float(x) for x in line.split()] for line in sys.stdin]
print("real time: 1 thread, 2 threads, 2 shards x 1 thread; over 1 thread;"
      " CPU per simulated s over 1 thread: 2 threads, 2 shards")
for a, ca, b, cb, c, cc in rows:
    print(f"  {a:.3f}  {b:.3f}  {c:.3f};  {b / a:.2f}  {c / a:.2f};  {cb / ca:.2f}  {cc / ca:.2f}")
print("medians of the ratios: 2 threads %.2f, 2 shards x 1 thread %.2f; CPU: 2 threads %.2f, 2 shards %.2f"
      % (st.median(r[2] / r[0] for r in rows), st.median(r[4] / r[0] for r in rows),
         st.median(r[3] / r[1] for r in rows), st.median(r[5] / r[1] for r in rows)))
'
