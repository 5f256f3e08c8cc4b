#!/usr/bin/env bash
# Bring-up check: fly the NPS FINken (built by build_nps.sh) against fake_world.py, no GCS, no RC.
#
#   paparazzi/fake_hover.sh [--name NAME] [--duration S] [--port P] [--out DIR] [-- extra fake_world args]
#
# Starts fake_world.py on 127.0.0.1:P, then NPS with --norc and a huge --time_factor (the main
# loop then never waits on the wall clock: the world's answers pace it), on a private Ivy bus
# (127.255.255.255:2099, so that no running GCS/server sees it). The flight plan arms, climbs
# and holds 1 m by itself. The world closes the connection after S simulated seconds, which
# ends NPS. Output in DIR: fake_world.log (summary JSON on its last line), summary.json,
# hover.csv (state every 10 ms), nps.log. Exit status 0 iff, over the last 10 s, the copter held 1 m within 10 cm (mean and sd).
set -euo pipefail

here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
repo="$(cd "$here/.." && pwd)"
name=twinswarm_finken
duration=60
port=7460
out="$(mktemp -d /tmp/twinswarm_nps.XXXXXX)"
pprz="$repo/target/paparazzi"
extra=()
while [ $# -gt 0 ]; do
  case "$1" in
    --name) name="$2"; shift 2 ;;
    --duration) duration="$2"; shift 2 ;;
    --port) port="$2"; shift 2 ;;
    --out) out="$2"; shift 2 ;;
    --pprz) pprz="$2"; shift 2 ;;
    --) shift; extra=("$@"); break ;;
    *) echo "unknown argument: $1" >&2; exit 2 ;;
  esac
done
mkdir -p "$out"
# shellcheck disable=SC1091
. "$pprz/env.sh"
sim="$PAPARAZZI_HOME/var/aircrafts/$name/nps/simsitl"
[ -x "$sim" ] || { echo "no $sim: run paparazzi/build_nps.sh --name $name first" >&2; exit 1; }

python3 "$here/fake_world.py" --port "$port" --duration "$duration" \
  --csv "$out/hover.csv" --json "$out/summary.json" "${extra[@]}" > "$out/fake_world.log" 2>&1 &
world=$!
# wait until it listens (at most 5 s)
for _ in $(seq 50); do grep -q listening "$out/fake_world.log" 2>/dev/null && break; sleep 0.1; done

start=$(date +%s%N)
(cd "$out" && TWINSWARM_FDM="127.0.0.1:$port" timeout $((60 + ${duration%.*} * 10)) \
  "$sim" --norc --ivy_bus 127.255.255.255:2099 --time_factor 1e9 > "$out/nps.log" 2>&1) || true
end=$(date +%s%N)
wait "$world" || true
echo "NPS + fake world: $(( (end - start) / 1000000 )) ms wall for $duration s simulated"
tail -n 1 "$out/fake_world.log"
echo "output in $out"
python3 - "$out/summary.json" <<'EOF'
import json, sys
s = json.load(open(sys.argv[1]))
ok = (not s["crashed"]) and s.get("hold_mean_error_m") is not None \
     and abs(s["hold_mean_error_m"]) < 0.1 and s["hold_sd_m"] < 0.1
print("held 1 m" if ok else "did NOT hold 1 m")
sys.exit(0 if ok else 1)
EOF
