#!/usr/bin/env bash
# Twinswarm beside both speed peers, the minimal pybullet swarm (../shared/bench/peer_pybullet.py)
# and Crazyflow (../shared/bench/peer_crazyflow.py, JAX + MuJoCo), in one run on the same N, each
# pinned to the same single core, and a table of drone-seconds simulated per second and ratios.
#
#   scripts/bench-peers.sh [--write-docs] [N ...]     (default N: 100 1000 10000)
#
#   SIM_SECONDS=30   simulated seconds of every run (Twinswarm from tick 0, both peers)
#   PEER_MAX_N=1000  pybullet runs only up to this N (it is slow at 10,000); larger N say "skipped"
#   CRAZYFLOW_MAX_N=1000  the same for Crazyflow (at 10,000 it had not finished after 19 minutes)
#   ROUNDS=1         runs every N's measurements this many times, round after round; the table
#                    gives the median drone-s/s and the median of the rounds' ratios (each ratio
#                    from runs minutes apart at most), with their range: the host's speed moves
#                    by up to 2× within an hour, Crazyflow's most
#   STEP_MANY=1      also the 8 worlds of 10 copters: Twinswarm's `step_many` through
#                    `scripts/bench-python.sh --only vector` (which builds the release binary and
#                    the wheel into .venv-bench first), beside Crazyflow at N = 10, W = 8; 0 skips it
#   BENCH_CORE=0     the core every measurement is pinned to (taskset -c)
#   --write-docs     also replace the section between `<!-- bench-peers:begin -->` and
#                    `<!-- bench-peers:end -->` in docs/performance.md ("Beside both peers")
#
# For each N, back to back, every run on one thread of core BENCH_CORE:
# - Twinswarm `dense` (`benches/swarm_rt.rs --scene dense`): the experiment, a 1.5 m grid taking
#   off from the floor, 10 pillars among the copters, Wall-Avoid at 1 m on the full model (4 sonar
#   cones with cross-talk, IR, IMU, estimators, battery, downwash), measured from tick 0, crashes
#   piling up;
# - Twinswarm `cruise`: the 2 m grid in the air, each copter heading its own way at 0.3 m/s;
# - pybullet: `peer_pybullet.py bench --scheme ctrl50_zoh --k 10 --rays 1` (a 1.5 m grid in the
#   air at 1 m, 10 boxes, 50 ms control, 10 Bullet substeps, 4 sonar rays + 1 IR ray per drone in
#   one rayTestBatch);
# - Crazyflow: `peer_crazyflow.py N 1 SIM_SECONDS 200` (N drones in one world hovering on
#   attitude commands at 200 Hz, no contacts, no sensors), XLA on one thread: a command every
#   50 ms (ctrl20hz) and one compiled scan of all steps (fused).
# Twinswarm and pybullet report drone-s/s on the CPU time of the stepping thread (N * rtf_cpu,
# robust on a shared machine); Crazyflow and `step_many` on the wall clock.
# pybullet (.venv-bench) and crazyflow (.venv-crazyflow, Python >= 3.11) come from PyPI,
# installed on first use. Set CARGO_TARGET_DIR to reuse a build directory.
set -euo pipefail
cd "$(dirname "$0")/.."

write_docs=0
ns=()
for a in "$@"; do
    case "$a" in
        --write-docs) write_docs=1 ;;
        ''|*[!0-9]*) echo "usage: $0 [--write-docs] [N ...]" >&2; exit 2 ;;
        *) ns+=("$a") ;;
    esac
done
[ ${#ns[@]} -gt 0 ] || ns=(100 1000 10000)
sim_s=${SIM_SECONDS:-30}
peer_max_n=${PEER_MAX_N:-1000}
crazyflow_max_n=${CRAZYFLOW_MAX_N:-1000}
step_many=${STEP_MANY:-1}
rounds=${ROUNDS:-1}
core=${BENCH_CORE:-0}
pin=(taskset -c "$core")
pybullet_peer=../shared/bench/peer_pybullet.py
crazyflow_peer=../shared/bench/peer_crazyflow.py
for f in "$pybullet_peer" "$crazyflow_peer"; do
    [ -f "$f" ] || { echo "error: $f not found (expected next to the repository)" >&2; exit 1; }
done

venv=.venv-bench
if [ ! -x "$venv/bin/python" ]; then
    python3 -m venv "$venv"
    "$venv/bin/pip" install --quiet --disable-pip-version-check pybullet numpy
fi
cf_venv=.venv-crazyflow
if [ ! -x "$cf_venv/bin/python" ]; then
    python3 -c 'import sys; sys.exit(sys.version_info < (3, 11))' ||
        { echo "error: crazyflow needs Python >= 3.11, python3 is $(python3 --version)" >&2; exit 1; }
    python3 -m venv "$cf_venv"
    "$cf_venv/bin/pip" install --quiet --disable-pip-version-check crazyflow
fi
# XLA (jax) on one thread, as peer_crazyflow.py's docstring asks.
cf_env=(env XLA_FLAGS="--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1")

out=$(mktemp -d)
trap 'rm -rf "$out"' EXIT

# Build swarm_rt (niced, on any core), then run a copy of the binary: a rebuild in the same tree
# during the run changes nothing, and no cargo lock is waited on between measurements.
bin=$(nice -n 10 cargo bench -p twinswarm --bench swarm_rt --no-run --message-format=json-render-diagnostics |
    python3 -c 'import json, sys
exe = [m["executable"] for m in map(json.loads, sys.stdin)
       if m.get("reason") == "compiler-artifact" and m.get("executable") and m["target"]["name"] == "swarm_rt"]
print(exe[-1])')
cp "$bin" "$out/swarm_rt"

# run NAME CMD...: append the last line of CMD's output (a JSON object) to $out/NAME.jsonl; a
# failure is reported and the run goes on.
run() {
    local name=$1
    shift
    if "$@" >"$out/last.out" 2>"$out/last.err"; then
        tail -n 1 "$out/last.out" | tee -a "$out/$name.jsonl"
    else
        echo "warning: $name failed: $*" >&2
        tail -n 5 "$out/last.err" >&2
    fi
}

load_before=$(cut -d' ' -f1-3 /proc/loadavg)
echo "load average before: $load_before" >&2
for round in $(seq "$rounds"); do
    [ "$rounds" = 1 ] || echo "round $round of $rounds" >&2
    for n in "${ns[@]}"; do
        for scene in dense cruise; do
            run twinswarm "${pin[@]}" "$out/swarm_rt" --scene "$scene" --n "$n" --threads 1 --sim-seconds "$sim_s"
        done
        if [ "$n" -le "$peer_max_n" ]; then
            run pybullet "${pin[@]}" "$venv/bin/python" "$pybullet_peer" bench --scheme ctrl50_zoh --k 10 --rays 1 \
                --n "$n" --sim-seconds "$sim_s"
        fi
        if [ "$n" -le "$crazyflow_max_n" ]; then
            run crazyflow "${pin[@]}" "${cf_env[@]}" "$cf_venv/bin/python" "$crazyflow_peer" "$n" 1 "$sim_s" 200
        fi
    done
done
# 8 worlds of 10 copters.
run crazyflow "${pin[@]}" "${cf_env[@]}" "$cf_venv/bin/python" "$crazyflow_peer" 10 8 "$sim_s" 200
if [ "$step_many" = 1 ]; then
    # Builds first (unpinned), then measures on core $core, step_many on one rayon thread.
    if RAYON_NUM_THREADS=1 PIN_CORE=$core scripts/bench-python.sh --only vector >"$out/vector.out"; then
        grep '"bench": "vector"' "$out/vector.out" | tee -a "$out/vector.jsonl"
    else
        echo "warning: scripts/bench-python.sh --only vector failed" >&2
    fi
fi
load_after=$(cut -d' ' -f1-3 /proc/loadavg)
echo "load average after: $load_after" >&2

meta='from importlib.metadata import version as v; import sys; print(", ".join(f"{p} {v(p)}" for p in sys.argv[1:]))'
versions="$("$venv/bin/python" -c "$meta" pybullet), $("$cf_venv/bin/python" -c "$meta" crazyflow jax mujoco)"
commit=$(git rev-parse --short HEAD)
# Uncommitted changes to what builds the simulator (not to scripts or docs) are said.
git diff --quiet HEAD -- crates benches Cargo.toml Cargo.lock || commit="$commit + uncommitted changes"
ROUNDS=$rounds CRAZYFLOW_MAX_N=$crazyflow_max_n python3 - "$out" "$sim_s" "$peer_max_n" "$step_many" "$load_before" "$load_after" "$commit" "$(date -u +%F)" \
    "$write_docs" "${ns[*]}" "$versions" <<'PY'
import json, os, re, statistics, sys

out, sim_s, peer_max_n, step_many, load0, load1, commit, date, write_docs, ns, versions = sys.argv[1:]
peer_max_n, ns = int(peer_max_n), [int(n) for n in ns.split()]
cf_max_n = int(os.environ["CRAZYFLOW_MAX_N"])
rounds = int(os.environ["ROUNDS"])


def rows(name):
    path = f"{out}/{name}.jsonl"
    return [json.loads(l) for l in open(path)] if os.path.exists(path) else []


def by(rs, key):
    # Each key's runs in round order.
    out = {}
    for r in rs:
        out.setdefault(key(r), []).append(r)
    return out


ts = by(rows("twinswarm"), lambda r: (r["scenario"], r["N"]))
pb = by(rows("pybullet"), lambda r: r["N"])
cf = by(rows("crazyflow"), lambda r: (r["n"], r["worlds"]))
vec = rows("vector")


def med(vs):
    vs = [v for v in vs if v is not None]
    return statistics.median(vs) if vs else None


def paired(a, b):
    # The median of the rounds' ratios a/b (the runs of one round are minutes apart at most),
    # and their range.
    rs = [x / y for x, y in zip(a, b) if x is not None and y]
    return (statistics.median(rs), min(rs), max(rs)) if rs else None


def num(v):
    return f"{v:,.0f}" if v >= 100 else f"{v:.3g}"


def ratio(a, b):
    return a / b if a is not None and b else None


def fmt_ratio(r):
    if r is None:
        return "—"
    if isinstance(r, tuple):
        m, lo, hi = r
        return f"{m:.2f}×" if rounds == 1 else f"{m:.2f}× ({lo:.2f}–{hi:.2f})"
    return f"{r:.2f}×"


def median_of(r):
    return r[0] if isinstance(r, tuple) else r


def verdict(r, ok, what):
    return f"{what}: {'not measured' if r is None else 'met' if ok(median_of(r)) else 'MISSED'}"


lines = [
    "| scene | N | Twinswarm drone-s/s (cpu / wall) | crashed | pybullet drone-s/s | Crazyflow drone-s/s (ctrl 20 Hz / fused) "
    "| Twinswarm / pybullet | Twinswarm / Crazyflow ctrl 20 Hz | targets |",
    "|---|---:|---:|---:|---:|---:|---:|---:|---|",
]
for scene, label in (("dense_takeoff", "dense take-off"), ("cruise", "cruise")):
    for n in ns:
        t, p, c = ts.get((scene, n), []), pb.get(n, []), cf.get((n, 1), [])
        t_cpus = [n * r["rtf_cpu"] if r["rtf_cpu"] is not None else None for r in t]
        t_cpu = med(t_cpus)
        ts_cell = f"{num(t_cpu)} / {num(med([n * r['rtf_wallclock'] for r in t]))}" if t_cpu else "failed"
        p_dsss = [n * r["rtf_cpu"] for r in p]
        p_dss = med(p_dsss)
        p_cell = num(p_dss) if p else f"skipped (N > PEER_MAX_N = {peer_max_n})" if n > peer_max_n else "failed"
        c_ctrl = [r["ctrl20hz_drone_s_per_s"] for r in c]
        c_cell = (f"{num(med(c_ctrl))} / {num(med([r['fused_drone_s_per_s'] for r in c]))}" if c
                  else f"skipped (N > CRAZYFLOW_MAX_N = {cf_max_n})" if n > cf_max_n else "failed")
        rp, rc = paired(t_cpus, p_dsss), paired(t_cpus, c_ctrl)
        targets = []
        if scene == "dense_takeoff" and n in (100, 1000):
            targets.append(verdict(rp, lambda r: r >= 6, "≥ 6× pybullet"))
        if scene == "dense_takeoff" and n == 100:
            targets.append(verdict(rc, lambda r: r > 1.0, "> 1.0× Crazyflow"))
        if scene == "dense_takeoff" and n == 1000:
            targets.append(verdict(rc, lambda r: r >= 0.7, "≥ 0.7× Crazyflow"))
        crashed = f"{t[-1]['crashed']:,}" if t else ""
        lines.append(f"| {label} | {n:,} | {ts_cell} | {crashed} | {p_cell} | {c_cell} "
                     f"| {fmt_ratio(rp)} | {fmt_ratio(rc)} | {'; '.join(targets) or '—'} |")
c = (cf.get((10, 8)) or [None])[-1]
c_cell = f"{num(c['ctrl20hz_drone_s_per_s'])} / {num(c['fused_drone_s_per_s'])}" if c else "failed"
if vec:
    v = vec[-1]
    t_dss, p_dss = 0.05 * v["copter_steps_per_s"], 0.05 * v["peer_80_copter_steps_per_s"]
    rc = ratio(t_dss, c["ctrl20hz_drone_s_per_s"] if c else None)
    lines.append(f"| 8 worlds × 10 copters (hover; Twinswarm `step_many` on 1 thread, wall; pybullet: one world of 80) "
                 f"| 80 | — / {num(t_dss)} | | {num(p_dss)} | {c_cell} | {fmt_ratio(ratio(t_dss, p_dss))} | {fmt_ratio(rc)} | — |")
else:
    why = "not run, STEP_MANY=0" if step_many != "1" else "failed"
    lines.append(f"| 8 worlds × 10 copters (Twinswarm `step_many` {why}) | 80 | — | | — | {c_cell} | — | — | — |")

rounds_note = "" if rounds == 1 else f"ROUNDS={rounds}: medians, and each ratio the median of the rounds' with their range; "
stamp = (f"`scripts/bench-peers.sh {' '.join(map(str, ns))}` at {commit}, {date}, {rounds_note}{sim_s} simulated seconds per run, "
         f"every run on one thread pinned to one core; {versions}; load average {load0} before, {load1} after.")
notes = [
    "Drone-s/s: drone-seconds simulated per second, N × real-time factor. Twinswarm's first figure and "
    "pybullet's are on the CPU time of the stepping thread; Twinswarm's second, Crazyflow's and `step_many`'s on "
    "the wall clock (on a loaded machine the wall clock understates a peer, so the ratio to Crazyflow is "
    "flattering then: compare the load averages). Targets are judged on the dense take-off.",
]
table = "\n".join(lines)
print()
print(stamp)
print()
print(table)

if write_docs == "1":
    path = "docs/performance.md"
    text = open(path).read()
    begin, end = "<!-- bench-peers:begin -->", "<!-- bench-peers:end -->"
    if begin not in text or end not in text:
        sys.exit(f"error: {path} has no {begin} ... {end} section")
    body = "\n\n".join([stamp, table, *notes])
    text = re.sub(re.escape(begin) + ".*?" + re.escape(end), lambda _: f"{begin}\n{body}\n{end}", text, flags=re.S)
    open(path, "w").write(text)
    print(f"\nwrote {path}", file=sys.stderr)
PY
