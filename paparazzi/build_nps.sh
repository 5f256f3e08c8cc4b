#!/usr/bin/env bash
# Build a FINken NPS aircraft that flies in a Twinswarm world (Paparazzi NPS + the Twinswarm FDM).
#
#   paparazzi/build_nps.sh [--name NAME] [--ac-id N] [--periodic HZ] [--pprz DIR]
#
# Installs this folder's files into the Paparazzi tree built by shared/paparazzi/build.sh
# (default: <repo>/target/paparazzi), idempotently (a file is copied only when it differs, so
# make rebuilds only what changed), then runs `make AIRCRAFT=NAME nps.compile` there with a
# private conf file (CONF_XML=conf/userconf/twinswarm/conf.xml): the tree's own conf/conf.xml is
# never touched. Only new files are added to the tree:
#   sw/simulator/nps/nps_fdm_twinswarm.{c,h}, conf/modules/fdm_twinswarm.xml,
#   conf/airframes/twinswarm/NAME.xml, conf/flight_plans/twinswarm/finken_hover.xml,
#   conf/userconf/twinswarm/{conf.xml,aircraft/NAME.xml}
# Output: $PAPARAZZI_HOME/var/aircrafts/NAME/nps/simsitl
#
# --periodic HZ sets the airframe's PERIODIC_FREQUENCY (default 500); NPS then steps at
# 2*HZ (SYS_TIME_FREQUENCY): 1000 steps per simulated second (dt 1 ms, which divides Twinswarm's
# 5 ms physics and 50 ms control steps) at 500 Hz; the FINken's own 512 Hz gives dt = 1/1024 s.
set -euo pipefail

here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
repo="$(cd "$here/.." && pwd)"
name=twinswarm_finken
ac_id=7
periodic=500
pprz="$repo/target/paparazzi"

while [ $# -gt 0 ]; do
  case "$1" in
    --name) name="$2"; shift 2 ;;
    --ac-id) ac_id="$2"; shift 2 ;;
    --periodic) periodic="$2"; shift 2 ;;
    --pprz) pprz="$2"; shift 2 ;;
    -h|--help) sed -n '2,20p' "$0"; exit 0 ;;
    *) echo "unknown argument: $1" >&2; exit 2 ;;
  esac
done

case "$name" in (*[!A-Za-z0-9_]*|"") echo "bad aircraft name: $name" >&2; exit 2 ;; esac
case "$ac_id" in (*[!0-9]*|"") echo "bad ac_id: $ac_id" >&2; exit 2 ;; esac
case "$periodic" in (*[!0-9]*|"") echo "bad periodic frequency: $periodic" >&2; exit 2 ;; esac

if [ ! -f "$pprz/env.sh" ]; then
  echo "no Paparazzi build at $pprz: run shared/paparazzi/build.sh $pprz first" >&2
  exit 1
fi
# shellcheck disable=SC1091
. "$pprz/env.sh"
home="$PAPARAZZI_HOME"
[ -x "$home/sw/tools/generators/gen_aircraft.out" ] || { echo "Paparazzi generators not built in $home" >&2; exit 1; }

# install SRC DST: copy only if different (keeps timestamps, so repeated runs rebuild nothing)
conf_changed=0
install_file() {
  local src="$1" dst="$2"
  mkdir -p "$(dirname "$dst")"
  if ! cmp -s "$src" "$dst"; then
    cp "$src" "$dst.tmp.$$"
    mv "$dst.tmp.$$" "$dst"
    echo "installed ${dst#"$home"/}"
    case "$dst" in (*.xml) conf_changed=1 ;; esac
  fi
}
# install_text DST < text
install_text() {
  local dst="$1" tmp
  tmp="$(mktemp)"
  cat > "$tmp"
  install_file "$tmp" "$dst"
  rm -f "$tmp"
}

install_file "$here/sw/nps_fdm_twinswarm.c" "$home/sw/simulator/nps/nps_fdm_twinswarm.c"
install_file "$here/sw/nps_fdm_twinswarm.h" "$home/sw/simulator/nps/nps_fdm_twinswarm.h"
install_file "$here/conf/modules/fdm_twinswarm.xml" "$home/conf/modules/fdm_twinswarm.xml"
install_file "$here/conf/flight_plans/twinswarm_finken_hover.xml" "$home/conf/flight_plans/twinswarm/finken_hover.xml"
# (process substitution, not a pipe: install_text must run in this shell to set conf_changed)
install_text "$home/conf/airframes/twinswarm/$name.xml" < <(
  sed "s/@PERIODIC_FREQUENCY@/$periodic/; s/<airframe name=\"twinswarm_finken\">/<airframe name=\"$name\">/" \
    "$here/conf/airframes/twinswarm_finken.xml")

# the private conf: one entry per aircraft built with this script
uc="$home/conf/userconf/twinswarm"
install_text "$uc/aircraft/$name.xml" <<EOF
  <aircraft
   name="$name"
   ac_id="$ac_id"
   airframe="airframes/twinswarm/$name.xml"
   radio="radios/spektrum.xml"
   telemetry="telemetry/default_rotorcraft.xml"
   flight_plan="flight_plans/twinswarm/finken_hover.xml"
   settings="settings/rotorcraft_basic.xml settings/nps.xml"
   settings_modules="modules/ahrs_float_cmpl_quat.xml modules/guidance_pid_rotorcraft.xml modules/guidance_rotorcraft.xml modules/nav_rotorcraft.xml modules/stabilization_int_quat.xml modules/stabilization_rate.xml"
   gui_color="#ff8000"
  />
EOF
install_text "$uc/conf.xml" < <(echo "<conf>"; cat "$uc"/aircraft/*.xml; echo "</conf>")

# Paparazzi's generator decides per header whether to rewrite it and misses some airframe
# changes (a changed module list left generated/modules.h "unchanged", so a new module's init
# was never called): after any configuration change, start the aircraft from scratch.
if [ "$conf_changed" = 1 ] && [ -d "$home/var/aircrafts/$name" ]; then
  echo "configuration changed: removing var/aircrafts/$name for a clean build"
  rm -rf "${home:?}/var/aircrafts/$name"
fi

echo "building $name (ac_id $ac_id, PERIODIC_FREQUENCY $periodic Hz, NPS step 1/$((2 * periodic)) s) in $home"
start=$(date +%s%N)
make -C "$home" AIRCRAFT="$name" CONF_XML="$uc/conf.xml" nps.compile
end=$(date +%s%N)
ms=$(( (end - start) / 1000000 ))
printf 'built %s in %d.%03d s: %s\n' "$name" $((ms / 1000)) $((ms % 1000)) "$home/var/aircrafts/$name/nps/simsitl"
