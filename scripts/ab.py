#!/usr/bin/env python3
"""Interleaved A/B of twinswarm builds on one scene: this host's speed drifts within minutes,
so builds are compared in alternating rounds and by medians (docs/performance.md §11e, §11f).

  python3 scripts/ab.py run     ROUNDS SECONDS SCENE BIN_A BIN_B [BIN...]   # one process, 1 thread
  python3 scripts/ab.py cluster ROUNDS SECONDS SCENE BIN_A BIN_B [BIN...]   # 2 shards x 1 thread

Copy each build somewhere first (cp target/release/twinswarm /tmp/ts_A). Per run: real time,
CPU per simulated second (`cpu_per_sim_s` of `run --json`, and of `cluster --json` with the
launcher's router), and for `cluster` the barrier's parts (ms a step, mean of the shards) and the
batches that came in shared memory. The digests of all builds must agree (an A/B that changes
the bits says so).
"""
import json
import statistics as st
import subprocess
import sys


def once(mode, binary, scene, seconds):
    common = ["--no-bus", "--duration", seconds, "--json"]
    if mode == "run":
        cmd = [binary, "run", scene, "--no-log", "--threads", "1", *common]
    else:
        cmd = [binary, "cluster", scene, "--shards", "2", "--threads", "1", *common]
    d = json.loads(subprocess.run(cmd, capture_output=True, text=True, check=True).stdout)
    digest = hash(tuple(sorted((c["id"], c["digest"]) for c in d["copters"])))
    if mode == "run":
        # Builds older than `run --json`'s cpu_per_sim_s: cpu_s over the seconds flown.
        cpu = d["cpu_per_sim_s"] if "cpu_per_sim_s" in d else d["cpu_s"] / float(seconds)
        return dict(rt=d["real_time_factor"], cpu=cpu), digest
    links = [p["shard"]["link"] for p in d["per_shard"]]
    per_step = lambda k: st.mean(l[k] / max(l["exchanges"], 1) * 1e3 for l in links)
    row = dict(rt=d["real_time_factor"], cpu=d["cpu_per_sim_s"], router_cpu_s=d["launcher_cpu_s"],
               barrier_ms=st.mean(l["barrier_ms_per_step"] for l in links), send_ms=per_step("send_s"),
               decode_ms=per_step("decode_s"), take_ms=per_step("take_s"),
               transit_ms=st.mean(l.get("transit_ms_per_batch", float("nan")) for l in links),
               in_shm=sum(l.get("batches_in_shm", 0) for l in links) / max(sum(l.get("batches_received", 0) for l in links), 1))
    return row, digest


def main(argv):
    if len(argv) < 6 or argv[0] not in ("run", "cluster"):
        sys.exit(__doc__)
    mode, rounds, seconds, scene, bins = argv[0], int(argv[1]), argv[2], argv[3], argv[4:]
    rows, digests = {b: [] for b in bins}, set()
    for r in range(rounds):
        for b in bins if r % 2 == 0 else bins[::-1]:
            row, digest = once(mode, b, scene, seconds)
            rows[b].append(row)
            digests.add(digest)
            print(b, {k: round(v, 3) for k, v in row.items()}, flush=True)
    print("medians:")
    for b in bins:
        print(" ", b, {k: round(st.median(r[k] for r in rows[b]), 3) for k in rows[b][0]})
    if len(digests) > 1:
        print(f"the builds' digests differ: {sorted(digests)}")
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
