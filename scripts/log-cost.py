#!/usr/bin/env python3
"""What logging costs a run, and how big its files are, side by side with an older binary.

For each scene and N, interleaved ROUNDS times (this machine is noisy), the same generated
scene file (`twinswarm scene …`, written once by the new binary) is flown by each binary, with
`--no-log` and with `--log`, no bus, one stepping thread, at full speed. Each binary writes
its own format at its own settings: the new one protobuf at its fixed zstd level, an older one
(`--old`) whatever it wrote (JSON, with zstd levels it lowered while behind).

It reports, per binary: the best real-time factor with and without the log (`--json`'s
`real_time_factor`: the step loop, which the writer holds back once 4 steps wait for it), the
cost of logging (median over rounds of the off/on ratio of a round, minus 1), and the file's
size per simulated second. Then the size ratio old/new, at equal content and rate.

    .venv/bin/python scripts/log-cost.py --n 100 1000 --seconds 20 --rounds 3 \\
        --scenes "dense --air" hover --old /tmp/twinswarm-json [--log-rate HZ] \\
        [--variant "l2=--log-zstd-level 2"] [--variant "every=--log-unchanged 0"]

`--old` is a binary built from an older commit, e.g. `git worktree add /tmp/old c8098a1 &&
cargo build --release --manifest-path /tmp/old/Cargo.toml`. Without it only the new binary runs.
"""

import argparse
import json
import pathlib
import statistics
import subprocess
import sys
import tempfile

ROOT = pathlib.Path(__file__).resolve().parents[1]


def fly(binary, scene, seconds, log, extra):
    args = [str(binary), "run", str(scene), "--no-bus", "--json", "--duration", str(seconds)]
    args += ["--log", str(log)] if log else ["--no-log"]
    r = subprocess.run(args + extra, capture_output=True, text=True, timeout=3600)
    if r.returncode != 0:
        sys.exit(f"{' '.join(args)} failed: {r.stderr}")
    summary = json.loads(r.stdout)
    size = log.stat().st_size if log else 0
    if log:
        log.unlink()
    return summary["real_time_factor"], size


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n", type=int, nargs="+", default=[100, 1000])
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--scenes", nargs="+", default=["dense --air", "hover"],
                    help="`twinswarm scene` arguments, e.g. \"dense --air\", cruise, hover")
    ap.add_argument("--bin", default=str(ROOT / "target/release/twinswarm"))
    ap.add_argument("--old", help="an older binary to compare with (same scene files)")
    ap.add_argument("--log-rate", type=float, help="the new binary's --log-rate (the old one logs every step)")
    ap.add_argument("--variant", action="append", default=[], metavar="NAME=ARGS",
                    help="also fly the new binary with these `run` arguments, e.g. "
                         "\"l2=--log-zstd-level 2\" (repeatable; each gets its own columns)")
    a = ap.parse_args()
    binaries = {"new": pathlib.Path(a.bin)}
    extra = {"new": ["--log-rate", str(a.log_rate)] if a.log_rate else []}
    for v in a.variant:
        name, _, args = v.partition("=")
        binaries[name] = pathlib.Path(a.bin)
        extra[name] = extra["new"] + args.split()
    if a.old:
        binaries["old"] = pathlib.Path(a.old)
        extra["old"] = []
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = pathlib.Path(tmp)
        for scene_args in a.scenes:
            for n in a.n:
                scene = tmp / "scene.toml"
                r = subprocess.run([str(binaries["new"]), "scene", *scene_args.split(), "--n", str(n)],
                                   capture_output=True, text=True, check=True)
                scene.write_text(r.stdout)
                runs = {(b, log): [] for b in binaries for log in (False, True)}
                for _ in range(a.rounds):
                    for b, binary in binaries.items():
                        for log in (False, True):
                            runs[(b, log)].append(fly(binary, scene, a.seconds, tmp / "run.mcap" if log else None,
                                                      extra[b]))
                row = {"scene": scene_args, "n": n, "seconds": a.seconds}
                for b in binaries:
                    off = [rtf for rtf, _ in runs[(b, False)]]
                    on = [rtf for rtf, _ in runs[(b, True)]]
                    cost = statistics.median(o / w - 1.0 for o, w in zip(off, on))
                    mib_s = statistics.median(size for _, size in runs[(b, True)]) / 2**20 / a.seconds
                    row[b] = {"rtf_off": max(off), "rtf_on": max(on), "cost_pct": 100 * cost,
                              "cost_pct_rounds": [round(100 * (o / w - 1), 1) for o, w in zip(off, on)],
                              "mib_per_sim_s": mib_s}
                if "old" in row:
                    for b in binaries:
                        if b != "old":
                            row[b]["size_ratio_old_over_this"] = row["old"]["mib_per_sim_s"] / row[b]["mib_per_sim_s"]
                rows.append(row)
                print(json.dumps(row), flush=True)
    print()
    print("| scene | N | binary | off (×RT) | log on (×RT) | cost | MiB per sim. s | size old/this |")
    print("|---|---:|---|---:|---:|---:|---:|---:|")
    for row in rows:
        for b in binaries:
            r = row[b]
            ratio = f"{r['size_ratio_old_over_this']:.1f}×" if "size_ratio_old_over_this" in r else ""
            print(f"| {row['scene']} | {row['n']:,} | {b} | {r['rtf_off']:.1f} | {r['rtf_on']:.1f} | "
                  f"{r['cost_pct']:+.1f} % | {r['mib_per_sim_s']:.2f} | {ratio} |")


if __name__ == "__main__":
    main()
