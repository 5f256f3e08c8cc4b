#!/usr/bin/env bash
# Build the speed-baseline aircraft: the NPS FINken of paparazzi/conf/airframes/twinswarm_finken.xml
# with upstream Paparazzi's JSBSim flight model (conf/modules/fdm_jsbsim.xml) in place of the
# Twinswarm FDM, hover flight plan.
#
#   paparazzi/upstream_fdm/build_upstream.sh [--name NAME] [--ac-id N] [--periodic HZ]
#        [--udp-out PORT] [--udp-in PORT] [--jsbsim-root DIR] [--pprz DIR]
#
# Defaults: name twinswarm_finken_upstream, ac_id 99, PERIODIC_FREQUENCY 500 (NPS step 1 ms),
# telemetry to UDP 127.0.0.1:4262 and datalink on 4263 (not 4242/4243, so that a run never
# mixes with a Twinswarm-FDM aircraft's telemetry), JSBSim in <repo>/target/jsbsim/install.
#
# JSBSim: no Debian package here (bookworm has none) and the PyPI wheels ship no headers, so
# when DIR/lib/libJSBSim.a is missing this script builds JSBSim 1.1.14's C++ library (static,
# PIC, -O2, the defines of its setup.py) from the PyPI source distribution
# (`pip download --no-binary jsbsim jsbsim==1.1.14`, which carries the C++ source) and copies
# its headers to DIR/include/JSBSim: ~4 min on 2 cores. 1.1.14, the last 1.1 release, because
# this tree's sw/simulator/nps/nps_fdm_jsbsim.cpp is written for the 1.1 API (raw model pointers,
# FGPropertyNode::SetDouble); JSBSim 1.2+/1.3 return std::shared_ptr and dropped SetDouble
# (1.3.3 fails to compile it). The Paparazzi source is used unpatched.
#
# Airframe conf/airframes/twinswarm/NAME.xml = twinswarm_finken.xml with:
#   <module name="fdm" type="jsbsim"> (JSBSIM_ROOT = DIR, no pkg-config),
#   NPS_JSBSIM_MODEL "simple_x_quad_ccw" (upstream's conf/simulator/jsbsim/aircraft, unchanged:
#     0.38 kg X quad, 0.84 lbf per motor at command 1, so hover at command 0.25; NE and SW rotors
#     CCW like Twinswarm's FINken front right / back left),
#   NPS_ACTUATOR_NAMES ne, se, sw, nw = the airframe's motors 0 front right, 1 back right,
#     2 back left, 3 front left,
#   module twinswarm_finken dropped (it reads the Twinswarm FDM's sonars; the hover plan does not
#     use it), and so its settings file. Everything else (gains, NPS_BYPASS_AHRS/INS, startup
#     mode, NOMINAL_HOVER_THROTTLE 0.5 with ADAPT_THROTTLE) is the FINken's.
# Private conf: conf/userconf/twinswarm/aircraft/NAME.xml, concatenated into conf.xml like
# build_nps.sh does; refuses an ac_id already used by another aircraft there.
# Needs the files build_nps.sh installs (hover flight plan, telemetry file, merged messages):
# runs build_nps.sh once (default aircraft) if they are missing.
# Output: $PAPARAZZI_HOME/var/aircrafts/NAME/nps/simsitl
set -euo pipefail

here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
ppz_dir="$(cd "$here/.." && pwd)"
repo="$(cd "$ppz_dir/.." && pwd)"
name=twinswarm_finken_upstream
ac_id=99
periodic=500
udp_out=4262
udp_in=4263
jsbsim_root="$repo/target/jsbsim/install"
jsbsim_version=1.1.14
pprz="$repo/target/paparazzi"

while [ $# -gt 0 ]; do
  case "$1" in
    --name) name="$2"; shift 2 ;;
    --ac-id) ac_id="$2"; shift 2 ;;
    --periodic) periodic="$2"; shift 2 ;;
    --udp-out) udp_out="$2"; shift 2 ;;
    --udp-in) udp_in="$2"; shift 2 ;;
    --jsbsim-root) jsbsim_root="$2"; shift 2 ;;
    --pprz) pprz="$2"; shift 2 ;;
    -h|--help) sed -n '2,36p' "$0"; exit 0 ;;
    *) echo "unknown argument: $1" >&2; exit 2 ;;
  esac
done
case "$name" in (*[!A-Za-z0-9_]*|"") echo "bad aircraft name: $name" >&2; exit 2 ;; esac
case "$ac_id" in (*[!0-9]*|"") echo "bad ac_id: $ac_id" >&2; exit 2 ;; esac
case "$periodic" in (*[!0-9]*|"") echo "bad periodic frequency: $periodic" >&2; exit 2 ;; esac
case "$udp_out$udp_in" in (*[!0-9]*|"") echo "bad UDP port: $udp_out / $udp_in" >&2; exit 2 ;; esac

[ -f "$pprz/env.sh" ] || { echo "no Paparazzi build at $pprz: run shared/paparazzi/build.sh $pprz first" >&2; exit 1; }
# shellcheck disable=SC1091
. "$pprz/env.sh"
home="$PAPARAZZI_HOME"

# ---- JSBSim (C++ library + headers) ----
if [ ! -f "$jsbsim_root/lib/libJSBSim.a" ] || [ ! -f "$jsbsim_root/include/JSBSim/FGFDMExec.h" ]; then
  jdir="$(dirname "$jsbsim_root")"
  mkdir -p "$jdir"
  tarball="$jdir/JSBSim-$jsbsim_version.tar.gz"
  if [ ! -f "$tarball" ]; then
    echo "fetching the JSBSim $jsbsim_version source distribution from PyPI (pip download)"
    tmpd="$(mktemp -d)"
    pip download --quiet --no-deps --no-binary jsbsim -d "$tmpd" "jsbsim==$jsbsim_version"
    mv "$tmpd"/[Jj][Ss][Bb][Ss]im-"$jsbsim_version".tar.gz "$tarball"
    rm -rf "$tmpd"
  fi
  src="$jdir/JSBSim-$jsbsim_version"
  obj="$jdir/obj"
  rm -rf "$src" "$obj"
  tar xzf "$tarball" -C "$jdir"
  mkdir -p "$obj"
  # the sdist has no CMakeLists.txt: compile the library sources its setup.py lists (the
  # "build from the sources" branch, minus the Cython module) with the same defines
  python3 - "$src/setup.py" "$obj/Makefile" "$src" <<'PY'
import re, sys
setup, mk, src = sys.argv[1:]
t = open(setup).read()
lists = re.findall(r"'sources': convert_CMake_list_to_Python_list\('([^']*)'\)", t)
files = [f for f in lists[-1].split(';') if f and not f.endswith('.pyx')]
defs = re.findall(r"compile_flags = \['-D'\+flag for flag in convert_CMake_list_to_Python_list\('([^']*)'\)\]", t)[-1]
dflags = ' '.join("'-D%s'" % d for d in defs.split(';') if d)  # single-quoted for the shell
objs = []
rules = []
for f in files:
    o = re.sub(r'[/.]', '_', f) + '.o'
    objs.append(o)
    cc = '$(CC) $(CFLAGS)' if f.endswith('.c') else '$(CXX) $(CXXFLAGS)'
    rules.append(f"{o}: {src}/{f}\n\t{cc} -c -o $@ $<\n")
with open(mk, 'w') as m:
    m.write(f"FLAGS = -O2 -fPIC -I{src}/src -I{src}/src/simgear/xml {dflags}\n")
    m.write("CFLAGS = $(FLAGS)\nCXXFLAGS = -std=c++11 $(FLAGS)\n")
    m.write("libJSBSim.a: " + ' '.join(objs) + "\n\tar rcs $@ $^\n")
    m.write('\n'.join(rules))
PY
  echo "building JSBSim $jsbsim_version (static library, $(grep -c '^\S*\.o:' "$obj/Makefile") files) into $jsbsim_root"
  make -C "$obj" -j "$(nproc)" libJSBSim.a > "$jdir/build.log" 2>&1 || { tail -20 "$jdir/build.log" >&2; exit 1; }
  mkdir -p "$jsbsim_root/lib" "$jsbsim_root/include/JSBSim"
  cp "$obj/libJSBSim.a" "$jsbsim_root/lib/"
  (cd "$src/src" && find . \( -name '*.h' -o -name '*.hxx' \) -exec cp --parents {} "$jsbsim_root/include/JSBSim/" \;)
fi

# ---- what build_nps.sh installs and this aircraft uses ----
uc="$home/conf/userconf/twinswarm"
if [ ! -f "$home/conf/flight_plans/twinswarm/finken_hover.xml" ] \
   || [ ! -f "$home/conf/telemetry/twinswarm/finken.xml" ] \
   || [ ! -f "$home/var/include/pprzlink/telemetry/TWINSWARM_SONAR.h" ]; then
  echo "running build_nps.sh once for the flight plan, telemetry file and messages"
  "$ppz_dir/build_nps.sh" --pprz "$pprz"
fi

conf_changed=0
install_text() {  # install_text DST < text: replace DST only if different
  local dst="$1" tmp
  tmp="$(mktemp)"; cat > "$tmp"
  mkdir -p "$(dirname "$dst")"
  if ! cmp -s "$tmp" "$dst"; then
    mv "$tmp" "$dst"; chmod 644 "$dst"
    echo "installed ${dst#"$home"/}"; conf_changed=1
  else
    rm -f "$tmp"
  fi
}

# ---- the airframe ----
install_text "$home/conf/airframes/twinswarm/$name.xml" < <(
  python3 - "$ppz_dir/conf/airframes/twinswarm_finken.xml" "$name" "$periodic" "$udp_out" "$udp_in" "$jsbsim_root" <<'EOF'
import sys
src, name, periodic, udp_out, udp_in, jroot = sys.argv[1:]
t = open(src).read()
def sub(old, new):
    global t
    if t.count(old) != 1:
        sys.exit(f"build_upstream: expected once in twinswarm_finken.xml: {old!r}")
    t = t.replace(old, new)
sub('<airframe name="twinswarm_finken">', f'<airframe name="{name}">')
sub('@PERIODIC_FREQUENCY@', periodic)
sub('<module name="fdm" type="twinswarm"/>',
    '<!-- upstream Paparazzi flight model (speed baseline, paparazzi/upstream_fdm) -->\n'
    '      <module name="fdm" type="jsbsim">\n'
    f'        <configure name="JSBSIM_ROOT" value="{jroot}"/>\n'
    '        <configure name="FIND_JSBSIM_VIA_PKG_CONFIG" value="no"/>\n'
    '      </module>')
sub('<module name="telemetry" type="transparent"/>',
    f'<module name="telemetry" type="transparent"><configure name="MODEM_PORT_OUT" value="{udp_out}"/>'
    f'<configure name="MODEM_PORT_IN" value="{udp_in}"/></module>')
# the hover plan does not use it, and it needs the Twinswarm FDM's sonar state
lines = [l for l in t.split('\n') if '<module name="twinswarm_finken"/>' not in l]
if len(lines) == len(t.split('\n')):
    sys.exit("build_upstream: module twinswarm_finken not found")
t = '\n'.join(lines)
sub('<section name="SIMULATOR" prefix="NPS_">',
    '<section name="SIMULATOR" prefix="NPS_">\n'
    '    <!-- upstream JSBSim model, unchanged; motors 0..3 = front right, back right, back left, front left -->\n'
    '    <define name="JSBSIM_MODEL" value="simple_x_quad_ccw" type="string"/>\n'
    '    <define name="ACTUATOR_NAMES" value="ne_motor, se_motor, sw_motor, nw_motor" type="string[]"/>')
sys.stdout.write(t)
EOF
)

# ---- the private conf entry ----
for other in "$uc"/aircraft/*.xml; do
  [ -e "$other" ] && [ "$other" != "$uc/aircraft/$name.xml" ] && grep -q "ac_id=\"$ac_id\"" "$other" && {
    echo "ac_id $ac_id is already used by $(basename "$other" .xml) in $uc: pick another with --ac-id" >&2
    exit 1
  }
done
install_text "$uc/aircraft/$name.xml" <<EOF
  <aircraft
   name="$name"
   ac_id="$ac_id"
   airframe="airframes/twinswarm/$name.xml"
   radio="radios/spektrum.xml"
   telemetry="telemetry/twinswarm/finken.xml"
   flight_plan="flight_plans/twinswarm/finken_hover.xml"
   settings="settings/rotorcraft_basic.xml settings/nps.xml"
   settings_modules="modules/ahrs_float_cmpl_quat.xml modules/guidance_pid_rotorcraft.xml modules/guidance_rotorcraft.xml modules/nav_rotorcraft.xml modules/stabilization_int_quat.xml modules/stabilization_rate.xml"
   gui_color="#0080ff"
  />
EOF
# conf.xml: every aircraft file, as build_nps.sh writes it (written only if it changed)
tmpc="$(mktemp)"
{ echo "<conf>"; cat "$uc"/aircraft/*.xml; echo "</conf>"; } > "$tmpc"
if ! cmp -s "$tmpc" "$uc/conf.xml"; then mv "$tmpc" "$uc/conf.xml"; echo "installed conf/userconf/twinswarm/conf.xml"; else rm -f "$tmpc"; fi

# Paparazzi's generator misses some configuration changes (see paparazzi/README.md): start clean
if [ "$conf_changed" = 1 ] && [ -d "$home/var/aircrafts/$name" ]; then
  echo "configuration changed: removing var/aircrafts/$name for a clean build"
  rm -rf "${home:?}/var/aircrafts/$name"
fi

echo "building $name (ac_id $ac_id, JSBSim simple_x_quad_ccw, hover plan, PERIODIC_FREQUENCY $periodic Hz) in $home"
start=$(date +%s%N)
make -C "$home" AIRCRAFT="$name" CONF_XML="$uc/conf.xml" nps.compile
end=$(date +%s%N)
ms=$(( (end - start) / 1000000 ))
printf 'built %s in %d.%03d s: %s\n' "$name" $((ms / 1000)) $((ms % 1000)) "$home/var/aircrafts/$name/nps/simsitl"
