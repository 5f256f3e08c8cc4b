#!/usr/bin/env bash
# Build a FINken NPS aircraft that flies in a Twinswarm world (Paparazzi NPS + the Twinswarm FDM).
#
#   paparazzi/build_nps.sh [--name NAME] [--ac-id N] [--periodic HZ] [--flight-plan hover|wall_avoid]
#                          [--firmware port|2015-12|2015-07] [--pprz DIR]
#
# Installs this folder's files into the Paparazzi tree built by shared/paparazzi/build.sh
# (default: <repo>/target/paparazzi), idempotently (a file is copied only when it differs, so
# make rebuilds only what changed), then runs `make AIRCRAFT=NAME nps.compile` there with a
# private conf file (CONF_XML=conf/userconf/twinswarm/conf.xml): the tree's own conf/conf.xml is
# never touched. New files added to the tree:
#   sw/simulator/nps/nps_fdm_twinswarm.{c,h}, conf/modules/fdm_twinswarm.xml,
#   sw/airborne/modules/twinswarm/twinswarm_finken.{c,h}, conf/modules/twinswarm_finken.xml,
#   conf/airframes/twinswarm/NAME.xml, conf/flight_plans/twinswarm/finken_{hover,wall_avoid}.xml,
#   conf/telemetry/twinswarm/finken.xml,
#   conf/userconf/twinswarm/{conf.xml,aircraft/NAME.xml,messages.xml}
# and the message definitions are extended (README "Messages"): conf/userconf/twinswarm/
# messages.xml = pprzlink's v1.0 messages.xml + conf/messages/twinswarm_messages.xml
# (TWINSWARM_SONAR telemetry 192, SONAR_UPLINK datalink 153, GPS_INJECT moved 153 -> 42) is
# installed as var/messages.xml and the C headers in var/include/pprzlink are regenerated from
# it (pprzlink's own `make pymessages`), only when it differs from var/messages.xml.
# --flight-plan: hover (default; arm, climb, hold 1 m) or wall_avoid (arm, climb to 1 m, then
# the FINken's Wall-Avoid with a cruise tilt, forever).
# Output: $PAPARAZZI_HOME/var/aircrafts/NAME/nps/simsitl
#
# --udp-out PORT / --udp-in PORT (default 4242 / 4243): where its telemetry goes (UDP on
# 127.0.0.1, Paparazzi `link -udp_port`) and where it listens for the datalink (`link
# -udp_uplink_port`). Compiled in, like the ac_id. An aircraft built before under another name
# with the same ac_id is dropped from the private conf (ac_ids must be unique there).
# --cruise FWD,RIGHT (deg, default the airframe's 1.0,0.6): the wall_avoid plan's cruise tilt;
# 0,0 flies the firmware's Wall-Avoid alone (it keeps its place between obstacles).
# --sighting-hold S (default 0, off; not in the firmware): a sonar reading nearer than the goal
# distance stands in for farther ones this long, so a copter that drifts out of a cone is kept.
# --periodic HZ sets the airframe's PERIODIC_FREQUENCY (default 500); NPS then steps at
# 2*HZ (SYS_TIME_FREQUENCY): 1000 steps per simulated second (dt 1 ms, which divides Twinswarm's
# 5 ms physics and 50 ms control steps) at 500 Hz; the FINken's own 512 Hz gives dt = 1/1024 s.
# --firmware port (default: this project's airframe twinswarm_finken.xml, Paparazzi's guidance,
# module twinswarm_finken) or 2015-12: the FINken's own firmware of 16 Dec 2015, its modules
# compiled unchanged from ../shared/paparazzi/finken_firmware/flight_2015-12 (copied verbatim to
# sw/airborne/finken_fw/2015_12 and conf/finken_fw/2015_12), airframe
# conf/airframes/finken_fw_2015_12.xml (fink3.xml, aircraft 5), the firmware's own flight plan
# free_flight.xml (both --flight-plan values; wall_avoid loads finken_wall_avoid in place of
# finken_rc_passthrough), no AHRS/INS bypass; glue in finken_fw/ (docs/paparazzi.md, "The
# FINken's own firmware"). --cruise and --sighting-hold belong to the port.
# --firmware 2015-07: the paper's mixed-reality firmware (../shared/paparazzi/finken_firmware/
# mixed_reality_2015-07: finken_model with the SONAR_UPLINK min() fusion, sonar_array_i2c on i2c2,
# finken_ir_adc), airframe conf/airframes/finken_fw_2015_07.xml (quadrotor_lia_ovgu.xml), its
# flight plan ovgu_sonar.xml for both --flight-plan values (the firmware always centres on its
# sonars; it has no separate Wall-Avoid module).
# --firmware-dir DIR: where the copies are (default <repo>/../shared/paparazzi/finken_firmware).
set -euo pipefail

here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
repo="$(cd "$here/.." && pwd)"
name=twinswarm_finken
ac_id=7
periodic=500
flight_plan=hover
udp_out=4242
udp_in=4243
cruise=""
hold=""
pprz="$repo/target/paparazzi"
firmware=port
fw_dir="$repo/../shared/paparazzi/finken_firmware"

while [ $# -gt 0 ]; do
  case "$1" in
    --name) name="$2"; shift 2 ;;
    --ac-id) ac_id="$2"; shift 2 ;;
    --periodic) periodic="$2"; shift 2 ;;
    --flight-plan) flight_plan="$2"; shift 2 ;;
    --udp-out) udp_out="$2"; shift 2 ;;
    --udp-in) udp_in="$2"; shift 2 ;;
    --cruise) cruise="$2"; shift 2 ;;
    --sighting-hold) hold="$2"; shift 2 ;;
    --pprz) pprz="$2"; shift 2 ;;
    --firmware) firmware="$2"; shift 2 ;;
    --firmware-dir) fw_dir="$2"; shift 2 ;;
    -h|--help) sed -n '2,49p' "$0"; exit 0 ;;
    *) echo "unknown argument: $1" >&2; exit 2 ;;
  esac
done

case "$name" in (*[!A-Za-z0-9_]*|"") echo "bad aircraft name: $name" >&2; exit 2 ;; esac
case "$ac_id" in (*[!0-9]*|"") echo "bad ac_id: $ac_id" >&2; exit 2 ;; esac
case "$periodic" in (*[!0-9]*|"") echo "bad periodic frequency: $periodic" >&2; exit 2 ;; esac
case "$cruise" in ("") ;; (*[!0-9.,-]*|*,*,*) echo "bad cruise: $cruise (FWD,RIGHT in deg)" >&2; exit 2 ;; (*,*) ;; (*) echo "bad cruise: $cruise (FWD,RIGHT in deg)" >&2; exit 2 ;; esac
case "$hold" in ("") ;; (*[!0-9.]*) echo "bad sighting hold: $hold (s)" >&2; exit 2 ;; esac
case "$udp_out$udp_in" in (*[!0-9]*|"") echo "bad UDP port: $udp_out / $udp_in" >&2; exit 2 ;; esac
case "$flight_plan" in (hover|wall_avoid) ;; (*) echo "bad flight plan: $flight_plan (hover or wall_avoid)" >&2; exit 2 ;; esac
case "$firmware" in
  (port) ;;
  (2015-12|2015-07)
    [ -z "$cruise$hold" ] || { echo "--cruise/--sighting-hold: options of the port's module, not of the firmware $firmware" >&2; exit 2; }
    if [ "$firmware" = 2015-12 ]; then fw_src="$fw_dir/flight_2015-12"; else fw_src="$fw_dir/mixed_reality_2015-07"; fi
    [ -f "$fw_src/sw/airborne/modules/finken_model/finken_model_system.c" ] || { echo "no firmware copy at $fw_src" >&2; exit 1; } ;;
  (*) echo "bad firmware: $firmware (port, 2015-12 or 2015-07)" >&2; exit 2 ;;
esac

if [ ! -f "$pprz/env.sh" ]; then
  echo "no Paparazzi build at $pprz: run shared/paparazzi/build.sh $pprz first" >&2
  exit 1
fi
# One build at a time in a Paparazzi tree: every build writes the private conf.xml,
# var/messages.xml and the installed modules (tests build aircraft from two pytest workers).
command -v flock >/dev/null || { echo "flock (util-linux) not found: needed to serialise builds in $pprz" >&2; exit 1; }
exec 9>"$pprz/.build_nps.lock"
flock 9
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
install_file "$here/conf/flight_plans/twinswarm_finken_wall_avoid.xml" "$home/conf/flight_plans/twinswarm/finken_wall_avoid.xml"
install_file "$here/sw/twinswarm_finken.c" "$home/sw/airborne/modules/twinswarm/twinswarm_finken.c"
install_file "$here/sw/twinswarm_finken.h" "$home/sw/airborne/modules/twinswarm/twinswarm_finken.h"
install_file "$here/conf/modules/twinswarm_finken.xml" "$home/conf/modules/twinswarm_finken.xml"
install_file "$here/conf/telemetry/twinswarm_finken.xml" "$home/conf/telemetry/twinswarm/finken.xml"

# the message definitions: pprzlink's pristine v1.0 file + ours, regenerated only on a change
uc="$home/conf/userconf/twinswarm"
mkdir -p "$uc"
python3 "$here/merge_messages.py" "$home/sw/ext/pprzlink/message_definitions/v1.0/messages.xml" \
  "$here/conf/messages/twinswarm_messages.xml" "$uc/messages.xml.tmp.$$"
mv "$uc/messages.xml.tmp.$$" "$uc/messages.xml"
if ! cmp -s "$uc/messages.xml" "$home/var/messages.xml" \
   || [ ! -f "$home/var/include/pprzlink/telemetry/TWINSWARM_SONAR.h" ] \
   || [ ! -f "$home/var/include/pprzlink/datalink/SONAR_UPLINK.h" ]; then
  echo "installing the message definitions $uc/messages.xml as var/messages.xml, regenerating var/include/pprzlink"
  make -C "$home/sw/ext/pprzlink" Q=@ MESSAGES_XML="$uc/messages.xml" MESSAGES_INSTALL="$home/var" \
    VALIDATE_XML=FALSE PPRZLINK_LIB_VERSION=2.0 pymessages
  conf_changed=1
fi
telemetry_sed="s|<module name=\"telemetry\" type=\"transparent\"/>|<module name=\"telemetry\" type=\"transparent\"><configure name=\"MODEM_PORT_OUT\" value=\"$udp_out\"/><configure name=\"MODEM_PORT_IN\" value=\"$udp_in\"/></module>|"
if [ "$firmware" = port ]; then
# (process substitution, not a pipe: install_text must run in this shell to set conf_changed)
install_text "$home/conf/airframes/twinswarm/$name.xml" < <(
  sed "s/@PERIODIC_FREQUENCY@/$periodic/; s/<airframe name=\"twinswarm_finken\">/<airframe name=\"$name\">/
       ${cruise:+s|<define name=\"WA_CRUISE_FWD\" value=\"[^\"]*\"/>|<define name=\"WA_CRUISE_FWD\" value=\"${cruise%,*}\"/>|; s|<define name=\"WA_CRUISE_RIGHT\" value=\"[^\"]*\"/>|<define name=\"WA_CRUISE_RIGHT\" value=\"${cruise#*,}\"/>|;}
       ${hold:+s|<define name=\"WA_SIGHTING_HOLD\" value=\"[^\"]*\"/>|<define name=\"WA_SIGHTING_HOLD\" value=\"$hold\"/>|;}
       $telemetry_sed" \
    "$here/conf/airframes/twinswarm_finken.xml")
fp="flight_plans/twinswarm/finken_$flight_plan.xml"
settings_modules="modules/ahrs_float_cmpl_quat.xml modules/guidance_pid_rotorcraft.xml modules/guidance_rotorcraft.xml modules/nav_rotorcraft.xml modules/stabilization_int_quat.xml modules/stabilization_rate.xml modules/twinswarm_finken.xml"
else
# The firmware: its files verbatim (sw/airborne/modules/... and conf/...), the project's glue.
fw_tag="${firmware/-/_}"
while IFS= read -r -d '' f; do
  rel="${f#"$fw_src"/}"
  case "$rel" in
    (sw/airborne/*) install_file "$f" "$home/sw/airborne/finken_fw/$fw_tag/${rel#sw/airborne/}" ;;
    (conf/*) install_file "$f" "$home/conf/finken_fw/$fw_tag/$rel" ;;
  esac
done < <(find "$fw_src" -type f -print0 | sort -z)
while IFS= read -r -d '' f; do
  install_file "$f" "$home/sw/airborne/finken_fw/shim/${f#"$here/finken_fw/shim/"}"
done < <(find "$here/finken_fw/shim" -type f -print0 | sort -z)
for f in finken_fw_nps.c finken_fw_nps.h finken_fw_api.h sonar_array_i2c_hw.c; do
  install_file "$here/finken_fw/sw/$f" "$home/sw/airborne/modules/finken_fw/$f"
done
for m in finken_fw_$fw_tag finken_fw_${fw_tag}_rc_passthrough finken_fw_${fw_tag}_wall_avoid; do
  if [ -f "$here/conf/modules/$m.xml" ]; then install_file "$here/conf/modules/$m.xml" "$home/conf/modules/$m.xml"; fi
done
wa_sed=""
[ "$flight_plan" = wall_avoid ] && wa_sed="s|<module name=\"finken_fw_${fw_tag}_rc_passthrough\"/>|<module name=\"finken_fw_${fw_tag}_wall_avoid\"/>|"
install_text "$home/conf/airframes/twinswarm/$name.xml" < <(
  sed "s/@PERIODIC_FREQUENCY@/$periodic/; s/<airframe name=\"finken_fw_$fw_tag\">/<airframe name=\"$name\">/
       $wa_sed
       $telemetry_sed" \
    "$here/conf/airframes/finken_fw_$fw_tag.xml")
if [ "$firmware" = 2015-12 ]; then
  fp="finken_fw/$fw_tag/conf/flight_plans/ovgu/free_flight.xml"
else
  # the paper's firmware has no separate Wall-Avoid: finken_model always centres on the sonars
  fp="finken_fw/$fw_tag/conf/flight_plans/ovgu_sonar.xml"
fi
ahrs_settings=modules/ahrs_float_cmpl_quat.xml
[ "$firmware" = 2015-07 ] && ahrs_settings=modules/ahrs_int_cmpl_quat.xml
settings_modules="$ahrs_settings modules/guidance_pid_rotorcraft.xml modules/guidance_rotorcraft.xml modules/nav_rotorcraft.xml modules/stabilization_int_quat.xml modules/stabilization_rate.xml"
fi

# the private conf: one entry per aircraft built with this script, one per ac_id
for other in "$uc"/aircraft/*.xml; do
  [ -e "$other" ] && [ "$other" != "$uc/aircraft/$name.xml" ] && grep -q "ac_id=\"$ac_id\"" "$other" && {
    echo "dropping $(basename "$other" .xml) from the private conf: it had ac_id $ac_id"
    rm -f "$other"
  }
done
install_text "$uc/aircraft/$name.xml" <<EOF
  <aircraft
   name="$name"
   ac_id="$ac_id"
   airframe="airframes/twinswarm/$name.xml"
   radio="radios/spektrum.xml"
   telemetry="telemetry/twinswarm/finken.xml"
   flight_plan="$fp"
   settings="settings/rotorcraft_basic.xml settings/nps.xml"
   settings_modules="$settings_modules"
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

echo "building $name (firmware $firmware, ac_id $ac_id, flight plan $flight_plan, PERIODIC_FREQUENCY $periodic Hz, NPS step 1/$((2 * periodic)) s) in $home"
start=$(date +%s%N)
make -C "$home" AIRCRAFT="$name" CONF_XML="$uc/conf.xml" nps.compile
end=$(date +%s%N)
ms=$(( (end - start) / 1000000 ))
printf 'built %s in %d.%03d s: %s\n' "$name" $((ms / 1000)) $((ms % 1000)) "$home/var/aircrafts/$name/nps/simsitl"
