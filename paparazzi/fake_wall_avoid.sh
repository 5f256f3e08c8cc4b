#!/usr/bin/env bash
# Bring-up check of Wall-Avoid: fly an NPS FINken built with `build_nps.sh --flight-plan
# wall_avoid` against fake_world.py in a walled arena, no GCS, no RC; optionally check the
# SONAR_UPLINK fusion on its telemetry.
#
#   paparazzi/fake_wall_avoid.sh [--name NAME] [--duration S] [--port P] [--ivy-port Q] [--out DIR]
#                                [--uplink] [-- extra fake_world args]
#
# Default: 60 simulated s as fast as it goes in a 4 m x 3 m arena (--arena 4x3; later fake_world
# args win). Passes iff the copter did not crash, its centre never came closer to a wall than
# fake_world's --radius (0.15 m), and it came near (1 m) a wall at least 4 times.
# --uplink: the world runs at real time (--pace 1, default 30 s) and, while the copter flies
# Wall-Avoid, send_uplink.py sends SONAR_UPLINK at 20 Hz: first for another ac_id (front 0.3 m,
# must be ignored), then for this aircraft (front 0.9 m, right 1.0 m, 4 s: an obstacle fixed to
# the body; much closer ones sandwich the copter against a real wall, which the firmware's
# symmetric Wall-Avoid centres between and, at 0.5 m, overshoots into the wall). telemetry_tap.py
# records TWINSWARM_SONAR (UDP 4242); passes iff the fused/virtual readings follow the uplink:
# virtual = sent while the last uplink is at most 0.5 s old, none when older, fused =
# min(real, virtual), the other aircraft's uplink never accepted.
# Everything on 127.0.0.1, a private Ivy bus (127.255.255.255:Q, default 2171), bounded in time.
# Output in DIR: world.log (summary JSON last line), summary.json, state.csv, nps.log, tap.log.
set -euo pipefail

here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
repo="$(cd "$here/.." && pwd)"
name=twinswarm_finken
duration=""
port=7471
ivy_port=2171
out="$(mktemp -d /tmp/twinswarm_wa.XXXXXX)"
pprz="$repo/target/paparazzi"
uplink=0
extra=()
while [ $# -gt 0 ]; do
  case "$1" in
    --name) name="$2"; shift 2 ;;
    --duration) duration="$2"; shift 2 ;;
    --port) port="$2"; shift 2 ;;
    --ivy-port) ivy_port="$2"; shift 2 ;;
    --out) out="$2"; shift 2 ;;
    --pprz) pprz="$2"; shift 2 ;;
    --uplink) uplink=1; shift ;;
    --) shift; extra=("$@"); break ;;
    *) echo "unknown argument: $1" >&2; exit 2 ;;
  esac
done
[ -n "$duration" ] || { if [ "$uplink" = 1 ]; then duration=30; else duration=60; fi; }
mkdir -p "$out"
# shellcheck disable=SC1091
. "$pprz/env.sh"
sim="$PAPARAZZI_HOME/var/aircrafts/$name/nps/simsitl"
[ -x "$sim" ] || { echo "no $sim: run paparazzi/build_nps.sh --name $name --flight-plan wall_avoid first" >&2; exit 1; }
acf="$PAPARAZZI_HOME/conf/userconf/twinswarm/aircraft/$name.xml"
ac_id="$(sed -n 's/.*ac_id="\([0-9]*\)".*/\1/p' "$acf")"
grep -q 'finken_wall_avoid.xml' "$acf" || echo "warning: $name was not built with --flight-plan wall_avoid" >&2

pace=()
[ "$uplink" = 1 ] && pace=(--pace 1)
python3 "$here/fake_world.py" --port "$port" --duration "$duration" --arena 4x3 "${pace[@]}" \
  --csv "$out/state.csv" --json "$out/summary.json" "${extra[@]}" > "$out/world.log" 2>&1 &
world=$!
for _ in $(seq 50); do grep -q listening "$out/world.log" 2>/dev/null && break; sleep 0.1; done

tap=""
if [ "$uplink" = 1 ]; then
  python3 -u "$here/telemetry_tap.py" --only TWINSWARM_SONAR --seconds $(( ${duration%.*} + 15 )) > "$out/tap.log" 2>&1 &
  tap=$!
  # the sender: wall clock = simulated time (--pace 1); Wall-Avoid starts at about 12 s
  (
    sleep 14
    python3 "$here/send_uplink.py" --ac-id $((ac_id + 1)) --front 0.3 --seconds 2
    sleep 1
    python3 "$here/send_uplink.py" --ac-id "$ac_id" --front 0.9 --right 1.0 --seconds 4
  ) > "$out/uplink.log" 2>&1 &
  sender=$!
fi

start=$(date +%s%N)
(cd "$out" && TWINSWARM_FDM="127.0.0.1:$port" timeout $((60 + ${duration%.*} * 10)) \
  "$sim" --norc --ivy_bus "127.255.255.255:$ivy_port" --time_factor 1e9 > "$out/nps.log" 2>&1) || true
end=$(date +%s%N)
wait "$world" || true
if [ -n "$tap" ]; then
  wait "$sender" || true
  kill "$tap" 2>/dev/null || true
  wait "$tap" 2>/dev/null || true
fi
echo "NPS + fake world: $(( (end - start) / 1000000 )) ms wall for $duration s simulated"
tail -n 1 "$out/world.log"
echo "output in $out"
python3 - "$out" "$ac_id" "$uplink" <<'EOF'
import json, sys
out, ac_id, uplink = sys.argv[1], sys.argv[2], sys.argv[3] == "1"
s = json.load(open(f"{out}/summary.json"))
ok = True
d = s.get("min_wall_distance_m")
if s["crashed"] or d is None or s["touched_wall"] or s["wall_approaches"] < (2 if uplink else 4):
    ok = False
print(f"walls: min distance {d} m at {s.get('min_wall_distance_at_s')} s, {s.get('wall_approaches')} approaches, "
      f"crashed {s['crashed']}, touched {s.get('touched_wall')}")
if uplink:
    rows = []
    for line in open(f"{out}/tap.log"):
        p = line.split()
        if len(p) > 2 and p[0] == ac_id and p[1] == "TWINSWARM_SONAR":
            rows.append({k: float(v) for k, v in (f.split("=") for f in p[2:])})
    fresh = [r for r in rows if 0 <= r["virt_age"] <= 0.45]
    stale = [r for r in rows if r["virt_age"] > 0.55]
    never = [r for r in rows if r["virt_age"] < 0]
    bad = []
    for r in rows:
        for k in ("front", "right", "back", "left"):
            real, virt, fused = r["real_" + k], r["virt_" + k], r["fused_" + k]
            cands = [v for v in (real, virt) if v >= 0]
            want = min(cands) if cands else -1.0
            if abs(fused - want) > 1e-4:
                bad.append(("fused != min(real, virtual)", k, r))
    for r in fresh:
        if abs(r["virt_front"] - 0.9) > 1e-4 or abs(r["virt_right"] - 1.0) > 1e-4 or r["virt_back"] != -1 or r["virt_left"] != -1:
            bad.append(("fresh uplink not applied", r))
    for r in stale + never:
        if any(r["virt_" + k] != -1 for k in ("front", "right", "back", "left")):
            bad.append(("stale/absent uplink applied", r))
    if any(abs(r["virt_front"] - 0.3) < 1e-4 for r in rows):
        bad.append(("another aircraft's uplink applied",))
    changed = [r for r in fresh if r["fused_front"] < r["real_front"] - 0.05 or r["real_front"] < 0]
    print(f"uplink: {len(rows)} TWINSWARM_SONAR, {len(never)} before any uplink, {len(fresh)} with a fresh one "
          f"({len(changed)} of them with fused_front lowered by it), {len(stale)} after it went stale; "
          f"uplinks accepted {int(max((r['uplinks'] for r in rows), default=0))}; {len(bad)} inconsistencies")
    if fresh:
        r = fresh[len(fresh) // 2]
        print("  e.g. during: real_front %.3f virt_front %.3f fused_front %.3f wa_pitch %.2f deg" %
              (r["real_front"], r["virt_front"], r["fused_front"], r["wa_pitch"]))
    for b in bad[:5]:
        print("  ", b)
    if not fresh or not stale or not never or not changed or bad:
        ok = False
print("PASS" if ok else "FAIL")
sys.exit(0 if ok else 1)
EOF
