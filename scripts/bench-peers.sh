#!/usr/bin/env bash
# Twinswarm and a minimal pybullet swarm (../shared/bench/peer_pybullet.py), back to back on
# the same N, and the ratios of their real-time factors.
#
#   scripts/bench-peers.sh [N ...]        (default: 100 1000)
#
# Twinswarm: `cargo bench -p twinswarm --bench swarm_rt` (Wall-Avoid, 4 exact sonar cones +
# IR + IMU noise, 50 ms control steps of 10 x 5 ms physics substeps, one thread).
# pybullet: `peer_pybullet.py bench --scheme ctrl50_zoh --k 10 --rays 1` (50 ms control,
# 10 Bullet substeps, 4 sonar rays + 1 IR ray per drone in one rayTestBatch, one thread).
# Both report real-time factors on CPU time of the stepping thread (rtf_cpu, robust on a
# shared machine) and on the wall clock (rtf_wallclock). pybullet comes from PyPI, installed
# into .venv-bench on first use. Set CARGO_TARGET_DIR to reuse a build directory.
set -euo pipefail
cd "$(dirname "$0")/.."
ns=("$@")
[ ${#ns[@]} -gt 0 ] || ns=(100 1000)
peer=../shared/bench/peer_pybullet.py
[ -f "$peer" ] || { echo "error: $peer not found (expected next to the repository)" >&2; exit 1; }

venv=.venv-bench
if [ ! -x "$venv/bin/python" ]; then
    python3 -m venv "$venv"
    "$venv/bin/pip" install --quiet pybullet numpy
fi

out=$(mktemp -d)
trap 'rm -rf "$out"' EXIT
echo "load average before: $(cut -d' ' -f1-3 /proc/loadavg)" >&2
nice -n 10 cargo bench -p twinswarm --bench swarm_rt --no-run >/dev/null 2>&1 ||
    nice -n 10 cargo bench -p twinswarm --bench swarm_rt --no-run
for n in "${ns[@]}"; do
    cargo bench -q -p twinswarm --bench swarm_rt -- --n "$n" --threads 1 | tee -a "$out/twinswarm.jsonl"
    "$venv/bin/python" "$peer" bench --scheme ctrl50_zoh --k 10 --rays 1 --n "$n" 2>/dev/null |
        tee -a "$out/pybullet.jsonl"
done
echo "load average after: $(cut -d' ' -f1-3 /proc/loadavg)" >&2

"$venv/bin/python" - "$out" <<'PY'
import json, sys
out = sys.argv[1]
ts = {r["N"]: r for r in map(json.loads, open(f"{out}/twinswarm.jsonl"))}
pb = {r["N"]: r for r in map(json.loads, open(f"{out}/pybullet.jsonl"))}
print()
print("| N | Twinswarm rtf (cpu / wall) | pybullet rtf (cpu / wall) | ratio (cpu / wall) | target |")
print("|---|---|---|---|---|")
for n in sorted(ts):
    t, p = ts[n], pb.get(n)
    if p is None:
        continue
    rc, rw = t["rtf_cpu"] / p["rtf_cpu"], t["rtf_wallclock"] / p["rtf_wallclock"]
    verdict = "met" if rc >= 5 else "MISSED"
    print(f"| {n} | {t['rtf_cpu']:.1f} / {t['rtf_wallclock']:.1f} | {p['rtf_cpu']:.2f} / {p['rtf_wallclock']:.2f} "
          f"| {rc:.1f}x / {rw:.1f}x | >= 5x: {verdict} |")
PY
