#!/usr/bin/env python3
"""Scaling benchmark: one swarm on 1, 2, 4, … threads and on 1-8 shards, side by side.

For each swarm size it writes the scene (`twinswarm scene KIND --n N`), flies it with
`twinswarm run SCENE --no-bus --no-log --threads T --json` for every thread count and with
`twinswarm cluster SCENE --shards S --threads T --no-bus --json` for every shard count (the
machine's cores shared among the shards), and reports per run: wall time, real-time factor,
drone-seconds per second, the speed-up over one thread, the largest process's resident memory
(`wait4` of each run), the CPU it spent per simulated second over one thread's (the work a
configuration adds, apart from its waits and this machine's pace) with how busy its cores were,
and whether every copter's digest equals the one-thread run's (the bits must not depend on
threads or shards). From the thread runs it fits Amdahl's law,
speed-up(n) = 1 / (f + (1 - f) / n), by least squares on f: the serial fraction the curve
implies. It writes a Markdown table (with the commit, the date and the machine), a JSON file
and an SVG of the measured speed-up against Amdahl's curve for that f and the ideal line.

    python3 scripts/scaling.py                                  # 10,000 dense, threads up to the cores
    python3 scripts/scaling.py --sizes 10000,100000 --threads 1,2,4,8,16 --shards 1,2,4,8 \\
        --docs --json scaling.json          # the table into docs/performance.md, the plot beside it

Thread counts above the machine's cores are measured if asked (oversubscribed: they say
nothing of scaling) and marked so. Runs are sequential; nothing else should run meanwhile.
"""
import argparse
import datetime
import json
import os
import pathlib
import platform
import subprocess
import sys
import tempfile
import time

REPO = pathlib.Path(__file__).resolve().parents[1]


def machine():
    model = platform.processor() or platform.machine()
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    mem = ""
    try:
        for line in open("/proc/meminfo"):
            if line.startswith("MemTotal"):
                mem = f"{int(line.split()[1]) / 1024 / 1024:.0f} GiB"
                break
    except OSError:
        pass
    return f"{model}, {os.cpu_count()} cores, {mem}".strip(", ")


def commit():
    try:
        rev = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO, capture_output=True, text=True)
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=REPO,
                               capture_output=True, text=True)
        return rev.stdout.strip() + ("+changes" if dirty.stdout.strip() else "")
    except OSError:
        return "unknown"


def measured(cmd):
    """Runs `cmd`, returns (its JSON summary, wall s, its peak RSS in MiB: the largest of it and
    the descendants it waited for, as `wait4` reports for this one run)."""
    start = time.monotonic()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    out, err = proc.stdout.read(), proc.stderr.read()
    _, status, usage = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)
    wall = time.monotonic() - start
    if proc.returncode != 0:
        sys.exit(f"error: {' '.join(map(str, cmd))} exited {proc.returncode}:\n{err[-2000:]}")
    try:
        summary = json.loads(out)
    except json.JSONDecodeError as e:
        sys.exit(f"error: {' '.join(map(str, cmd))}: its --json output is not JSON ({e}): {out[:500]}")
    return summary, wall, usage.ru_maxrss / 1024


def digests(summary):
    return {c["id"] if "id" in c else c["name"]: c["digest"] for c in summary["copters"]}


def cpu_per_sim_s(summary):
    """CPU seconds (every thread; a cluster's shards and launcher together) per simulated second
    (`run --json` and `cluster --json` both report it; None where the platform has no CPU clock).
    A `run` of a build before a27a00a has only `cpu_s`: over `sim_time_s`, as it never resumes here."""
    if "cpu_per_sim_s" in summary:
        return summary["cpu_per_sim_s"]
    if summary.get("cpu_s") is not None and summary.get("sim_time_s"):
        return summary["cpu_s"] / summary["sim_time_s"]
    return None


def with_work(row, summary, used, one_thread_cpu):
    """The row's CPU account: CPU per simulated s, over one thread's (the work the configuration
    adds: 1.00 is none), and how busy the cores it had were (CPU per wall s over their count:
    below 1, threads or shards waited)."""
    cpu = cpu_per_sim_s(summary)
    row["cpu_per_sim_s"] = cpu
    row["work_over_1_thread"] = cpu / one_thread_cpu if cpu and one_thread_cpu else None
    row["cores_busy"] = cpu * row["real_time_factor"] / used if cpu else None
    return row


def amdahl_fraction(points):
    """Least-squares serial fraction f in [0, 1] from (threads, speed-up) points."""
    pts = [(n, s) for n, s in points if n > 1]
    if not pts:
        return None
    best = min((sum((s - 1 / (f + (1 - f) / n)) ** 2 for n, s in pts), f)
               for f in (k / 10000 for k in range(10001)))
    return best[1]


def fly(args, n, scene, duration):
    cores = os.cpu_count() or 1
    rows = []
    reference = None
    one_thread_rtf = one_thread_cpu = None
    for t in args.threads:
        cmd = [args.bin, "run", scene, "--no-bus", "--no-log", "--threads", str(t), "--duration", str(duration),
               "--json"]
        s, wall, rss = measured(cmd)
        d = digests(s)
        reference = reference or d
        rtf = s["real_time_factor"]
        one_thread_rtf = one_thread_rtf or (rtf if t == 1 else None)
        one_thread_cpu = one_thread_cpu or (cpu_per_sim_s(s) if t == 1 else None)
        rows.append(with_work({
            "copters": n, "kind": "run", "how": f"{t} thread{'s' if t > 1 else ''}", "threads": t, "shards": 1,
            "oversubscribed": t > cores, "loop_wall_s": s["wall_time_s"], "process_wall_s": wall,
            "real_time_factor": rtf, "drone_s_per_s": n * rtf,
            "speed_up": (rtf / one_thread_rtf) if one_thread_rtf else None,
            "rss_mib": rss, "differ": sum(1 for k, v in d.items() if reference.get(k) != v),
            "crashed": len(s["crashes"]) if isinstance(s["crashes"], list) else s["crashes"],
        }, s, min(t, cores), one_thread_cpu))
        print(f"  {n} copters, {t} thread(s): {wall:.1f} s, {rtf:.2f}× real time, "
              f"{rows[-1]['differ']} digests differ", file=sys.stderr)
    for k in args.shards:
        t = max(1, cores // k)
        cmd = [args.bin, "cluster", scene, "--shards", str(k), "--threads", str(t), "--no-bus",
               "--duration", str(duration), "--json"]
        s, wall, rss = measured(cmd)
        d = digests(s)
        # The slowest shard's step loop (the barrier makes them one pace); start-up apart.
        rtf = s["real_time_factor"]
        rows.append(with_work({
            "copters": n, "kind": "cluster",
            "how": f"{k} shard{'s' if k > 1 else ''} × {t} thread{'s' if t > 1 else ''}",
            "threads": t, "shards": k, "oversubscribed": k * t > cores, "loop_wall_s": duration / rtf,
            "process_wall_s": wall, "real_time_factor": rtf, "drone_s_per_s": n * rtf,
            "speed_up": (rtf / one_thread_rtf) if one_thread_rtf else None,
            "rss_mib": rss, "differ": sum(1 for c, v in d.items() if reference and reference.get(c) != v),
            "crashed": s.get("crashed"),
        }, s, min(k * t, cores), one_thread_cpu))
        print(f"  {n} copters, {k} shard(s) × {t} thread(s): {wall:.1f} s, "
              f"{rtf:.2f}× real time, {rows[-1]['differ']} digests differ", file=sys.stderr)
    return rows


def markdown(args, rows, fractions, header):
    lines = [header, "",
             "| copters | how | real time | drone-s/s | speed-up over 1 thread | CPU per simulated s over 1 thread's "
             "| cores busy | largest process | digests unlike 1 thread |",
             "|---:|---|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        sp = f"{r['speed_up']:.2f}" if r["speed_up"] else "–"
        over = " (oversubscribed)" if r["oversubscribed"] else ""
        work = f"{r['work_over_1_thread']:.2f}" if r.get("work_over_1_thread") else "–"
        busy = f"{r['cores_busy'] * 100:.0f} %" if r.get("cores_busy") else "–"
        lines.append(f"| {r['copters']:,} | {r['how']}{over} | {r['real_time_factor']:.2f}× | "
                     f"{r['drone_s_per_s']:,.0f} | {sp} | {work} | {busy} | {r['rss_mib']:.0f} MiB | {r['differ']} |")
    lines.append("")
    for n, f in fractions.items():
        if f is not None:
            lines.append(f"- {n:,} copters: Amdahl's serial fraction from the thread runs **{f * 100:.1f} %** "
                         f"(speed-up limit {1 / f:.1f}×)" if f > 0 else f"- {n:,} copters: serial fraction 0 %")
    return "\n".join(lines) + "\n"


def svg(rows, fractions, path):
    w, h, m = 520, 360, 50
    nmax = max([r["threads"] for r in rows if r["kind"] == "run"] + [2])
    smax = max([r["speed_up"] or 1 for r in rows] + [nmax])
    x = lambda n: m + (w - 2 * m) * (n - 1) / max(nmax - 1, 1)
    y = lambda s: h - m - (h - 2 * m) * (s - 0) / smax
    out = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{w}" height="{h}" font-family="sans-serif" font-size="11">',
           f'<rect width="{w}" height="{h}" fill="white"/>',
           f'<line x1="{m}" y1="{h - m}" x2="{w - m}" y2="{h - m}" stroke="black"/>',
           f'<line x1="{m}" y1="{m}" x2="{m}" y2="{h - m}" stroke="black"/>',
           f'<text x="{w / 2}" y="{h - 12}" text-anchor="middle">threads</text>',
           f'<text x="14" y="{h / 2}" transform="rotate(-90 14 {h / 2})" text-anchor="middle">speed-up over 1 thread</text>',
           f'<line x1="{x(1)}" y1="{y(1)}" x2="{x(nmax)}" y2="{y(nmax)}" stroke="#aaa" stroke-dasharray="4 3"/>']
    for n in range(1, nmax + 1):
        if n & (n - 1) == 0:
            out.append(f'<text x="{x(n)}" y="{h - m + 14}" text-anchor="middle">{n}</text>')
    colours = ["#1f77b4", "#d62728", "#2ca02c", "#9467bd"]
    for i, (n, f) in enumerate(sorted(fractions.items())):
        c = colours[i % len(colours)]
        pts = sorted((r["threads"], r["speed_up"]) for r in rows if r["copters"] == n and r["kind"] == "run"
                     and r["speed_up"])
        if f is not None:
            curve = " ".join(f"{x(k / 10):.1f},{y(1 / (f + (1 - f) / (k / 10))):.1f}" for k in range(10, nmax * 10 + 1))
            out.append(f'<polyline points="{curve}" fill="none" stroke="{c}" stroke-opacity="0.5"/>')
        for t, s in pts:
            out.append(f'<circle cx="{x(t):.1f}" cy="{y(s):.1f}" r="4" fill="{c}"/>')
        label = f"{n:,} copters" + (f", Amdahl f = {f * 100:.1f} %" if f is not None else "")
        out.append(f'<text x="{m + 10}" y="{m + 14 * (i + 1)}" fill="{c}">{label}</text>')
    out.append(f'<text x="{w - m}" y="{m + 14}" text-anchor="end" fill="#888">dashed: ideal</text>')
    out.append("</svg>")
    pathlib.Path(path).write_text("\n".join(out) + "\n")


BEGIN = "<!-- scaling.py: begin -->"
END = "<!-- scaling.py: end -->"


def docs_parts(path):
    """What lies before BEGIN and after END in `path` (checked before the runs, so that a file
    without them fails at once, not after an hour of measuring)."""
    doc = path.read_text() if path.is_file() else sys.exit(f"error: --docs: no file {path}")
    if doc.count(BEGIN) != 1 or doc.count(END) != 1 or doc.index(BEGIN) > doc.index(END):
        sys.exit(f"error: --docs: {path} must hold one `{BEGIN}` line and, after it, one `{END}` line")
    head, rest = doc.split(BEGIN, 1)
    return head, rest.split(END, 1)[1]


def into_docs(path, text):
    """Replaces what lies between the BEGIN and END lines of `path` with `text`."""
    head, tail = docs_parts(path)
    path.write_text(f"{head}{BEGIN}\n{text}{END}{tail}")


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    cores = os.cpu_count() or 1
    ap.add_argument("--bin", default=str(REPO / "target" / "release" / "twinswarm"))
    ap.add_argument("--scene", default="dense", choices=["dense", "cruise", "hover", "boxes"])
    ap.add_argument("--sizes", default="10000", help="comma-separated swarm sizes")
    ap.add_argument("--threads", default=",".join(str(1 << k) for k in range(8) if 1 << k <= cores),
                    help="comma-separated thread counts (default: powers of two up to the cores)")
    ap.add_argument("--shards", default=",".join(str(k) for k in (1, 2, 4, 8) if k <= cores),
                    help="comma-separated shard counts (the cores shared among them; empty: none)")
    ap.add_argument("--duration", default="10", help="simulated s, one value or one per size")
    ap.add_argument("--seed", default="1")
    ap.add_argument("--md", type=pathlib.Path, help="write the Markdown table here")
    ap.add_argument("--svg", type=pathlib.Path, help="write the speed-up plot here")
    ap.add_argument("--json", type=pathlib.Path, help="write every row as JSON here")
    ap.add_argument("--docs", nargs="?", type=pathlib.Path, const=REPO / "docs" / "performance.md",
                    help="write the table into this Markdown file (default docs/performance.md) between its "
                         f"`{BEGIN}` and `{END}` lines, and the plot as scaling.svg beside it")
    args = ap.parse_args()
    if not pathlib.Path(args.bin).is_file():
        sys.exit(f"error: no twinswarm binary at {args.bin}: build it with `cargo build --release` or pass --bin")
    try:
        sizes = [int(v) for v in args.sizes.split(",") if v]
        args.threads = [int(v) for v in args.threads.split(",") if v]
        args.shards = [int(v) for v in args.shards.split(",") if v]
        durations = [float(v) for v in args.duration.split(",") if v]
    except ValueError as e:
        sys.exit(f"error: --sizes, --threads, --shards and --duration take comma-separated numbers: {e}")
    if 1 not in args.threads:
        args.threads = [1] + args.threads
    if len(durations) not in (1, len(sizes)) or any(v <= 0 for v in sizes + args.threads + args.shards + durations):
        sys.exit("error: sizes, threads, shards and durations must be positive; --duration one value or one per size")
    if args.docs:
        docs_parts(args.docs)
    rows, fractions = [], {}
    with tempfile.TemporaryDirectory() as tmp:
        for i, n in enumerate(sizes):
            duration = durations[i] if len(durations) > 1 else durations[0]
            scene = pathlib.Path(tmp) / f"{args.scene}-{n}.toml"
            made = subprocess.run([args.bin, "scene", args.scene, "--n", str(n), "--seed", args.seed],
                                  capture_output=True, text=True)
            if made.returncode != 0:
                sys.exit(f"error: twinswarm scene: {made.stderr}")
            scene.write_text(made.stdout)
            print(f"{n} copters, `{args.scene}`, {duration:g} s:", file=sys.stderr)
            got = fly(args, n, str(scene), duration)
            rows += got
            fractions[n] = amdahl_fraction([(r["threads"], r["speed_up"]) for r in got
                                            if r["kind"] == "run" and r["speed_up"] and not r["oversubscribed"]])
    when = datetime.date.today().isoformat()
    header = (f"`python3 scripts/scaling.py --sizes {args.sizes} --scene {args.scene} --duration {args.duration}` "
              f"at {commit()}, {when}, on {machine()} (real time: simulated s per wall s of the step loop, "
              f"a cluster's slowest shard's, start-up apart; CPU: every thread of the run's processes during "
              f"the step loop, a cluster's shards' and its launcher's (the router) while they ran; cores "
              f"busy: that CPU per wall s over the cores the run had; the largest process's peak memory; "
              f"a cluster's shards share the cores)")
    text = markdown(args, rows, fractions, header)
    print(text)
    if args.md:
        args.md.write_text(text)
    if args.svg:
        svg(rows, fractions, args.svg)
    if args.docs:
        into_docs(args.docs, text)
        svg(rows, fractions, args.docs.parent / "scaling.svg")
    if args.json:
        args.json.write_text(json.dumps({"machine": machine(), "commit": commit(), "date": when, "rows": rows,
                                         "serial_fraction": fractions}, indent=1))
    if any(r["differ"] for r in rows):
        sys.exit("error: some runs ended with other digests than one thread's (see the last column)")


if __name__ == "__main__":
    main()
