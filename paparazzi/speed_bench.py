#!/usr/bin/env python3
"""The speed table of docs/paparazzi.md ("Speed"): N NPS aircraft in one Twinswarm world, the
world's CPU per step and simulated seconds per wall second, for several configurations side by
side, the rounds interleaved (config after config, count after count) so that a noisy machine
shares its noise among them.

    .venv/bin/python paparazzi/speed_bench.py --counts 1,4,16,64 --rounds 3 --duration 20 \\
        --config before,target/ap-bench/twinswarm.before,tcp,PATH/TO/OLD/simsitl \\
        --config tcp,target/release/twinswarm,tcp --config unix,target/release/twinswarm,unix

Each run is `scripts/nps_swarm.py --plan wall_avoid --no-log` with every NPS started from one
aircraft binary (`--one-build`, or `--simsitl` for a given one: each told the copter it flies by
TWINSWARM_FDM_AC_ID); a configuration is NAME,TWINSWARM,TRANSPORT[,SIMSITL]. The load average
(/proc/loadavg) is taken before and after each run. Writes every run as a JSON line (--jsonl)
and prints the medians per configuration and count, with the range over the rounds.
"""

import argparse
import importlib.util
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SPEC = importlib.util.spec_from_file_location("nps_swarm", REPO / "scripts" / "nps_swarm.py")
nps_swarm = importlib.util.module_from_spec(SPEC)
SPEC.loader.exec_module(nps_swarm)

FIELDS = ["sim_s_per_wall_s", "us_per_step", "world_cpu_us_per_step", "nps_cpu_us_per_step_each",
          "world_sleeps_per_step"]


def loadavg():
    return float(Path("/proc/loadavg").read_text().split()[0])


def parse_config(spec):
    parts = spec.split(",")
    if len(parts) not in (3, 4) or parts[2] not in ("tcp", "unix"):
        sys.exit(f"--config {spec}: NAME,TWINSWARM,TRANSPORT[,SIMSITL], TRANSPORT tcp or unix")
    for p in parts[1:2] + parts[3:]:
        if not Path(p).is_file():
            sys.exit(f"--config {spec}: no file {p}")
    return {"name": parts[0], "twinswarm": parts[1], "transport": parts[2], "simsitl": parts[3] if len(parts) == 4 else None}


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--counts", default="1,4,16", help="aircraft per world, comma-separated (default 1,4,16)")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--duration", type=float, default=20.0, help="simulated s per run (default 20)")
    ap.add_argument("--duration-for", action="append", default=[], metavar="COUNT:S",
                    help="another duration for that count, e.g. 64:10")
    ap.add_argument("--first-ac", type=int, default=50)
    ap.add_argument("--config", action="append", required=True, help="NAME,TWINSWARM,TRANSPORT[,SIMSITL]")
    ap.add_argument("--jsonl", default="speed_bench.jsonl", help="every run, one JSON line each (appended)")
    a = ap.parse_args()
    configs = [parse_config(c) for c in a.config]
    counts = [int(c) for c in a.counts.split(",")]
    durations = {int(k): float(v) for k, v in (d.split(":") for d in a.duration_for)}
    runs = []
    with open(a.jsonl, "a") as out:
        for rnd in range(a.rounds):
            for n in counts:
                for c in configs:
                    args = ["--count", str(n), "--plan", "wall_avoid", "--duration", str(durations.get(n, a.duration)),
                            "--first-ac", str(a.first_ac), "--no-log", "--quiet", "--twinswarm", c["twinswarm"],
                            "--transport", c["transport"]]
                    args += ["--simsitl", c["simsitl"]] if c["simsitl"] else ["--one-build"]
                    with tempfile.TemporaryDirectory(prefix="speed_bench.") as tmp:
                        l0, t0 = loadavg(), time.time()
                        r = nps_swarm.main(args + ["--out", tmp])
                        l1 = loadavg()
                    row = {"config": c["name"], "count": n, "round": rnd, "load_before": l0, "load_after": l1,
                           "started": time.strftime("%H:%M:%S", time.localtime(t0)), "args": args,
                           **{k: r[k] for k in FIELDS + ["steps", "wall_s", "nps_exit", "autopilots_left", "digests"]}}
                    out.write(json.dumps(row) + "\n")
                    out.flush()
                    runs.append(row)
                    print(f"round {rnd} {c['name']:>8} {n:>3}: {r['sim_s_per_wall_s']:7.2f} sim s/wall s, world CPU "
                          f"{r['world_cpu_us_per_step']:7.1f} us/step, each NPS {r['nps_cpu_us_per_step_each']:5.1f}, "
                          f"world sleeps {r['world_sleeps_per_step']:.2f}/step, load {l0:.2f}-{l1:.2f}", flush=True)
    print("\nmedian (range) over the rounds")
    print(f"{'config':>8} {'N':>3} {'sim s / wall s':>22} {'world CPU us/step':>24} {'NPS CPU us/step each':>22}")
    for n in counts:
        for c in configs:
            rs = [r for r in runs if r["count"] == n and r["config"] == c["name"]]

            def fmt(k, nd):
                v = [r[k] for r in rs]
                return f"{statistics.median(v):.{nd}f} ({min(v):.{nd}f}-{max(v):.{nd}f})"
            print(f"{c['name']:>8} {n:>3} {fmt('sim_s_per_wall_s', 2):>22} {fmt('world_cpu_us_per_step', 1):>24} "
                  f"{fmt('nps_cpu_us_per_step_each', 1):>22}")
        digests = {json.dumps(r["digests"], sort_keys=True) for r in runs if r["count"] == n}
        print(f"{'':>8} {n:>3} digests: {'the same in every run' if len(digests) == 1 else f'{len(digests)} different sets'}")


if __name__ == "__main__":
    main()
