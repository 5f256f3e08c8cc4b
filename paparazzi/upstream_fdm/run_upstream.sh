#!/usr/bin/env bash
# Fly the upstream-FDM baseline aircraft (built by build_upstream.sh: the FINken with JSBSim's
# simple_x_quad_ccw) free and as fast as it goes, and time it.
#
#   paparazzi/upstream_fdm/run_upstream.sh [--duration S] [--runs N] [--name NAME] [--ac-id N]
#        [--telemetry-port PORT] [--out DIR] [--pprz DIR]
#   paparazzi/upstream_fdm/run_upstream.sh --fake-world [--duration S] [--runs N] ...
#
# Each run: NPS with --norc --time_factor 1e9 --nodisplay on a private Ivy bus
# 127.255.255.255:<free UDP port>, stopped (its own process group, by id) once its telemetry
# (UDP PORT, default 4262, compiled into the aircraft by build_upstream.sh) shows S simulated
# seconds: ROTORCRAFT_FP comes every 0.25 s of autopilot time, so the count of those messages
# is the simulated clock (see nps_timed_run.py). Prints per run one JSON line (wall times,
# simulated s per wall s, the hover figures) and a summary line; output in DIR/run_K/
# (nps.log, height.csv, result.json). Exit status 0 iff every run reached S and hovered at 1 m.
# --fake-world: the reference measured the same way: the Twinswarm-FDM hover aircraft of
# build_nps.sh (default name twinswarm_finken, ac_id 7, telemetry port 4242) against
# paparazzi/fake_world.py (started per run on a free TCP port of 127.0.0.1, with a duration past
# S so that the telemetry clock, not the world, ends the run; ended by its id afterwards).
set -euo pipefail

here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
repo="$(cd "$here/../.." && pwd)"
name=twinswarm_finken_upstream
ac_id=99
duration=60
runs=1
port=4262
out=""
fake_world=0
pprz="$repo/target/paparazzi"
while [ $# -gt 0 ]; do
  case "$1" in
    --duration) duration="$2"; shift 2 ;;
    --runs) runs="$2"; shift 2 ;;
    --name) name="$2"; shift 2 ;;
    --ac-id) ac_id="$2"; shift 2 ;;
    --telemetry-port) port="$2"; shift 2 ;;
    --out) out="$2"; shift 2 ;;
    --pprz) pprz="$2"; shift 2 ;;
    --fake-world) fake_world=1; shift ;;
    -h|--help) sed -n '2,19p' "$0"; exit 0 ;;
    *) echo "unknown argument: $1" >&2; exit 2 ;;
  esac
done
if [ "$fake_world" = 1 ]; then  # defaults of the reference (explicit options given before win)
  [ "$name" = twinswarm_finken_upstream ] && name=twinswarm_finken
  [ "$ac_id" = 99 ] && ac_id=7
  [ "$port" = 4262 ] && port=4242
fi
case "$runs" in (*[!0-9]*|""|0) echo "bad --runs: $runs" >&2; exit 2 ;; esac
[ -n "$out" ] || out="$(mktemp -d /tmp/twinswarm_upstream.XXXXXX)"
mkdir -p "$out"
# shellcheck disable=SC1091
. "$pprz/env.sh"
sim="$PAPARAZZI_HOME/var/aircrafts/$name/nps/simsitl"
[ -x "$sim" ] || { echo "no $sim: run paparazzi/upstream_fdm/build_upstream.sh first" >&2; exit 1; }

status=0
for k in $(seq "$runs"); do
  mkdir -p "$out/run_$k"
  world=""
  if [ "$fake_world" = 1 ]; then
    wport=$(python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])')
    python3 "$here/../fake_world.py" --port "$wport" --duration "$(python3 -c "print($duration + 30)")" \
      > "$out/run_$k/fake_world.log" 2>&1 &
    world=$!
    for _ in $(seq 50); do grep -q listening "$out/run_$k/fake_world.log" 2>/dev/null && break; sleep 0.1; done
    export TWINSWARM_FDM="127.0.0.1:$wport"
  fi
  python3 "$here/nps_timed_run.py" --sim "$sim" --duration "$duration" --ac-id "$ac_id" \
    --telemetry-port "$port" --out "$out/run_$k" --json "$out/run_$k/result.json" || status=1
  if [ -n "$world" ]; then
    sleep 0.5
    kill "$world" 2>/dev/null || true
    wait "$world" 2>/dev/null || true
  fi
done
python3 - "$out" "$runs" <<'PY'
import json, sys, statistics
out, runs = sys.argv[1], int(sys.argv[2])
rs = [json.load(open(f"{out}/run_{k}/result.json")) for k in range(1, runs + 1)]
tot = [r["sim_per_wall_total"] for r in rs if "sim_per_wall_total" in r]
stp = [r["sim_per_wall_stepping"] for r in rs if "sim_per_wall_stepping" in r]
cpu = [r["sim_per_nps_cpu_s"] for r in rs if r.get("sim_per_nps_cpu_s")]
hov = sum(1 for r in rs if r.get("hovered"))
print(f"{len(tot)}/{runs} runs reached {rs[0]['duration_s']} s, {hov}/{runs} hovered at 1 m; "
      f"simulated s per wall s: incl. start-up {', '.join(map(str, tot))}"
      + (f" (median {statistics.median(tot)})" if tot else "")
      + f"; stepping only {', '.join(map(str, stp))}; per NPS CPU s {', '.join(map(str, cpu))}")
PY
echo "output in $out"
exit $status
