#!/usr/bin/env bash
# Two shards against two threads, interleaved: ROUNDS rounds of `run --threads 1`,
# `run --threads 2` and `cluster --shards 2 --threads 1` on SCENE for SECONDS simulated; per
# round and as medians, each one's real time and its ratio to one thread (this machine is
# noisy: runs side by side say more than one run of each). docs/performance.md §11b.
#
#   scripts/shards-vs-threads.sh SCENE.toml [SECONDS=10] [ROUNDS=5]
set -euo pipefail
bin="${TWINSWARM:-$(dirname "$0")/../target/release/twinswarm}"
scene=${1:?usage: $0 SCENE.toml [SECONDS] [ROUNDS]}
seconds=${2:-10}
rounds=${3:-5}
rtf() { python3 -c "import json, sys; print(json.load(sys.stdin)['real_time_factor'])"; }
for _ in $(seq "$rounds"); do
    one=$("$bin" run "$scene" --threads 1 --duration "$seconds" --no-bus --no-log --json 2>/dev/null | rtf)
    two=$("$bin" run "$scene" --threads 2 --duration "$seconds" --no-bus --no-log --json 2>/dev/null | rtf)
    shards=$("$bin" cluster "$scene" --shards 2 --threads 1 --duration "$seconds" --no-bus --json 2>/dev/null | rtf)
    echo "$one $two $shards"
done | python3 -c '
import statistics as st, sys
rows = [[float(x) for x in line.split()] for line in sys.stdin]
print("real time: 1 thread, 2 threads, 2 shards x 1 thread; over 1 thread")
for a, b, c in rows:
    print(f"  {a:.3f}  {b:.3f}  {c:.3f};  {b / a:.2f}  {c / a:.2f}")
print("medians of the ratios: 2 threads %.2f, 2 shards x 1 thread %.2f"
      % (st.median(b / a for a, b, _ in rows), st.median(c / a for a, _, c in rows)))
'
