#!/usr/bin/env bash
# Twinswarm and a minimal pybullet swarm (../shared/bench/peer_pybullet.py), side by side in one
# run on the same N, and the ratios of their real-time factors.
#
#   scripts/bench-peers.sh [N ...]        (default: 100 1000)
#   SIM_SECONDS=60 scripts/bench-peers.sh  (Twinswarm's simulated time; default 60 s)
#
# For each N, back to back:
# - Twinswarm `dense` (`cargo bench -p twinswarm --bench swarm_rt -- --scene dense`): the
#   experiment: a 1.5 m grid taking off from the floor, 10 pillars among the copters,
#   Wall-Avoid at 1 m on the full model (4 sonar cones with cross-talk, IR, IMU, estimators,
#   battery, downwash), measured from the floor for SIM_SECONDS, crashes piling up;
# - Twinswarm `cruise`: the 2 m grid in the air, each copter heading its own way at 0.3 m/s;
# - pybullet: `peer_pybullet.py bench --scheme ctrl50_zoh --k 10 --rays 1` (a 1.5 m grid in the
#   air at 1 m, 10 boxes, 50 ms control, 10 Bullet substeps, 4 sonar rays + 1 IR ray per drone
#   in one rayTestBatch, one thread).
# All on one thread. Both report real-time factors on the CPU time of the stepping thread
# (rtf_cpu, robust on a shared machine) and on the wall clock. pybullet comes from PyPI,
# installed into .venv-bench on first use. Set CARGO_TARGET_DIR to reuse a build directory.
set -euo pipefail
cd "$(dirname "$0")/.."
ns=("$@")
[ ${#ns[@]} -gt 0 ] || ns=(100 1000)
sim_s=${SIM_SECONDS:-60}
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
    for scene in dense cruise; do
        cargo bench -q -p twinswarm --bench swarm_rt -- --scene "$scene" --n "$n" --threads 1 --sim-seconds "$sim_s" |
            tee -a "$out/twinswarm.jsonl"
    done
    "$venv/bin/python" "$peer" bench --scheme ctrl50_zoh --k 10 --rays 1 --n "$n" 2>/dev/null |
        tee -a "$out/pybullet.jsonl"
done
echo "load average after: $(cut -d' ' -f1-3 /proc/loadavg)" >&2

"$venv/bin/python" - "$out" <<'PY'
import json, sys
out = sys.argv[1]
ts = [json.loads(l) for l in open(f"{out}/twinswarm.jsonl")]
pb = {r["N"]: r for r in map(json.loads, open(f"{out}/pybullet.jsonl"))}
print()
print("| scene | N | Twinswarm rtf (cpu / wall) | crashed | pybullet rtf (cpu / wall) | ratio (cpu / wall) | >= 5x | >= 10x real time |")
print("|---|---|---|---|---|---|---|---|")
for t in sorted(ts, key=lambda r: (r["scenario"], r["N"])):
    p = pb.get(t["N"])
    if p is None:
        continue
    rc, rw = t["rtf_cpu"] / p["rtf_cpu"], t["rtf_wallclock"] / p["rtf_wallclock"]
    ten = "met" if t["rtf_cpu"] >= 10 else "MISSED"
    print(f"| {t['scenario']} ({t['sim_s']:.0f} s) | {t['N']} | {t['rtf_cpu']:.1f} / {t['rtf_wallclock']:.1f} | {t['crashed']} "
          f"| {p['rtf_cpu']:.2f} / {p['rtf_wallclock']:.2f} | {rc:.1f}x / {rw:.1f}x | {'met' if rc >= 5 else 'MISSED'} | {ten} |")
PY
