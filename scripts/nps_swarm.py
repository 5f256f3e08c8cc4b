#!/usr/bin/env python3
"""Fly N Paparazzi NPS FINken aircraft (the real rotorcraft autopilot, Twinswarm as its flight
model) in one Twinswarm world, and report how they flew and how fast.

    .venv/bin/python scripts/nps_swarm.py --count 4 --plan wall_avoid --duration 60
    .venv/bin/python scripts/nps_swarm.py --count 1 --plan hover --duration 40 --json

Builds (paparazzi/build_nps.sh, ~25 s per aircraft the first time, ~1 s after) one aircraft
per ac_id (`tw_nps<ac_id>`; the id is compiled in), writes a scene with N `autopilot` copters
(1 ms steps, the FINken's sonar schedule) in the paper's 4 m x 3 m arena (larger for more
copters), starts `twinswarm run --no-bus` on a Unix-domain socket in a fresh temporary folder
(removed at the end; `--transport tcp`: a free loopback TCP port), then the N NPS processes with
`--time_factor 1e9` (lockstep: nothing waits on the wall clock), each on a private Ivy bus. Reads the
run's JSON summary and its MCAP log (PyPI mcap, CRCs on) and prints: simulated seconds per
wall second, the time the world waited for the autopilots, crashes, each copter's height over
the last 10 s, the closest approach to a wall and between copters, and the digests.

Needs the Paparazzi tree of shared/paparazzi/build.sh at target/paparazzi (scripts/test.sh
builds it) and a twinswarm binary: --twinswarm PATH, default the release build
target/release/twinswarm (`cargo build --release --bin twinswarm`), else target/debug/twinswarm
with a note on stderr (the debug world is several times slower per step).
"""

import argparse
import json
import math
import resource
import shutil
import signal
import os
import socket
import statistics
import subprocess
import sys
import threading
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PPRZ = Path(os.environ.get("TWINSWARM_PAPARAZZI_BUILD", REPO / "target" / "paparazzi"))
# The FINken's rotor-disc square as the sonars see it: arm 0.1 m at 45°, 5" rotors.
HALF_WIDTH_M = 0.1 / math.sqrt(2) + 0.0635


def default_twinswarm(quiet=False):
    """The release build of twinswarm, else the debug build (with a note: slower), else exit."""
    release, debug = REPO / "target" / "release" / "twinswarm", REPO / "target" / "debug" / "twinswarm"
    if release.exists():
        return str(release)
    if debug.exists():
        if not quiet:
            print(f"nps_swarm.py: no {release.relative_to(REPO)}, using {debug.relative_to(REPO)} "
                  "(slower; `cargo build --release --bin twinswarm`, or pass --twinswarm)", file=sys.stderr)
        return str(debug)
    sys.exit("nps_swarm.py: no twinswarm binary in target/release or target/debug: build one, or pass --twinswarm")


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def build(ac_id, plan, log, udp=None, cruise=None, hold=None, firmware="port"):
    # the port's aircraft keep their names; the firmware's get their own (the ac_id is compiled in)
    name = f"tw_nps{ac_id}" if firmware == "port" else f"tw_fw{firmware.replace('-', '')}_{ac_id}"
    cmd = ["bash", str(REPO / "paparazzi" / "build_nps.sh"), "--name", name, "--ac-id", str(ac_id),
           "--flight-plan", plan, "--pprz", str(PPRZ)]
    if firmware != "port":
        cmd += ["--firmware", firmware]
    if udp:
        cmd += ["--udp-out", str(udp[0]), "--udp-in", str(udp[1])]
    if cruise is not None:
        cmd += ["--cruise", cruise]
    if hold is not None:
        cmd += ["--sighting-hold", str(hold)]
    r = subprocess.run(cmd, capture_output=True, text=True)
    log.write(r.stdout + r.stderr)
    if r.returncode != 0:
        sys.exit(f"building {name} failed:\n{r.stdout[-3000:]}\n{r.stderr[-3000:]}")
    return PPRZ / "paparazzi" / "var" / "aircrafts" / name / "nps" / "simsitl"


def arena_for(n):
    """The paper's arena for up to two copters; more get about 3 m² each."""
    if n <= 2:
        return 4.0, 3.0
    side = math.ceil(math.sqrt(n))
    return 2.0 * side + 1.0, 1.5 * math.ceil(n / side) + 1.5


def scene(n, first_ac, duration, seed, boxes, arena=None, gap=None, airframe=None):
    sx, sy = arena or arena_for(n)
    side = math.ceil(math.sqrt(n)) if n > 2 else n
    lines = [
        'name = "nps_swarm"',
        "[sim]",
        f"seed = {seed}",
        "physics_dt_s = 0.001",
        "control_dt_s = 0.001",
        f"duration_s = {duration}",
        "[arena]",
        f"size_m = [{sx}, {sy}]",
        "height_m = 2.5",
        "walls = true",
        "[sensors.sonar]",
        "period_steps = 50",
    ]
    for b in boxes:
        lines += ["[[box]]", *b]
    rows = math.ceil(n / side)
    for k in range(n):
        i, j = k % side, k // side
        x = -sx / 2 + (i + 0.5) * sx / side
        y = -sy / 2 + (j + 0.5) * sy / rows
        yaw = 0.0 if i % 2 == 0 else 180.0
        if gap is not None:
            x, y = (k - (n - 1) / 2) * gap, 0.0
        lines += [
            "[[copter]]",
            f'name = "nps{first_ac + k}"',
            'kind = "autopilot"',
            f"ac_id = {first_ac + k}",
            f"start = {{ pos_m = [{x:.3f}, {y:.3f}], yaw_deg = {yaw} }}",
        ]
        if airframe:
            lines.append(f"airframe = {{ {airframe} }}")
    return "\n".join(lines) + "\n", (sx, sy)


def states(path):
    """Every /copters/state message of the log, decoded, CRCs checked."""
    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory

    out = []
    fields = None
    factory = DecoderFactory()
    with open(path, "rb") as f:
        reader = make_reader(f, validate_crcs=True, decoder_factories=[factory])
        for _s, _c, _m, proto in reader.iter_decoded_messages(topics=["/copters/state"], log_time_order=False):
            # CopterState's fields are scalars and repeated scalars: read them as they are (json_format's
            # MessageToDict formats each float as a string first, and took 3/4 of a 1 kHz log's reading)
            if fields is None:
                fields = [(fd.name, fd.is_repeated) for fd in proto.DESCRIPTOR.fields]
            out.append({name: list(getattr(proto, name)) if rep else getattr(proto, name) for name, rep in fields})
    return out


def flight_figures(path, arena, last_s=10.0):
    rows = states(path)
    by_tick = {}
    for r in rows:
        by_tick.setdefault(int(r["tick"]), []).append(r)
    hx, hy = arena[0] / 2, arena[1] / 2
    wall = math.inf
    pair, apart = math.inf, -math.inf
    max_x = -math.inf
    heights = {}
    t_end = max(float(r["t_s"]) for r in rows)
    for tick, rs in by_tick.items():
        pos = [[float(v) for v in r["pos_m"]] for r in rs]
        for r, p in zip(rs, pos):
            if p[2] > 0.3:
                max_x = max(max_x, p[0])
                wall = min(wall, hx - abs(p[0]) - HALF_WIDTH_M, hy - abs(p[1]) - HALF_WIDTH_M)
            if float(r["t_s"]) > t_end - last_s:
                heights.setdefault(r["copter"], []).append(p[2])
        for a in range(len(pos)):
            for b in range(a + 1, len(pos)):
                if pos[a][2] > 0.3 and pos[b][2] > 0.3:
                    d = math.dist(pos[a], pos[b])
                    pair, apart = min(pair, d - 2 * HALF_WIDTH_M), max(apart, d)
    return {
        "min_wall_clearance_m": None if wall == math.inf else round(wall, 3),
        "min_pair_clearance_m": None if pair == math.inf else round(pair, 3),
        "max_pair_distance_m": None if apart == -math.inf else round(apart, 3),
        "max_x_m": None if max_x == -math.inf else round(max_x, 3),
        "height_last_s": {
            c: {"mean_m": round(statistics.fmean(h), 4), "sd_m": round(statistics.pstdev(h), 4)} for c, h in heights.items()
        },
    }


def mean_attitude(path, settle_s=3.0):
    """Each copter's mean roll and pitch (deg, NED: Paparazzi's) from lift-off + settle_s to the end
    of the log, the world's truth; None for a copter that never lifted off."""
    by = {}
    for r in states(path):
        by.setdefault(r["copter"], []).append(r)
    out = {}
    for c, rs in by.items():
        up = next((float(r["t_s"]) for r in rs if float(r["pos_m"][2]) > 0.1), None)
        w = [r for r in rs if up is not None and float(r["t_s"]) >= up + settle_s and not r.get("crashed")]
        # the world's rpy: x north, y west, z up; NED roll = roll, NED pitch = -pitch
        out[c] = (statistics.fmean(math.degrees(float(r["rpy_rad"][0])) for r in w),
                  statistics.fmean(-math.degrees(float(r["rpy_rad"][1])) for r in w)) if w else None
    return out


def trim_flights(a, n, out):
    """The lab's trim, by flying (docs/paparazzi.md, "The FINken's own firmware"): hover each copter
    of the scene (same seed, so the same rotors) in a 40 m x 40 m arena, 30 s, and move its IMU
    calibration (body-to-IMU roll and pitch) by the mean attitude it held; n rounds. Returns the
    trims, one "PHI,THETA" per copter."""
    trims = [(0.0, 0.0)] * a.count
    if a.imu_trim:
        trims = parse_trims(a.imu_trim, a.count)
    trim_ac = a.first_ac + 100 if a.first_ac + 100 + a.count <= 255 else a.first_ac - 100
    for k in range(n):
        spec = ";".join(f"{p:.3f},{t:.3f}" for p, t in trims)
        r = main(["--firmware", a.firmware, "--count", str(a.count), "--plan", "hover", "--duration", "30",
                  "--first-ac", str(trim_ac), "--arena", "40x40", "--seed", str(a.seed), "--twinswarm", a.twinswarm,
                  "--out", str(out / f"trim{k + 1}"), f"--imu-trim={spec}", "--quiet"]
                 + ([f"--airframe={a.airframe}"] if a.airframe else []))
        means = mean_attitude(Path(r["out"]) / "run.mcap")
        new = []
        for i, (p, t) in enumerate(trims):
            m = means.get(f"nps{trim_ac + i}")
            new.append((p, t) if m is None else (p - m[0], t - m[1]))
        trims = new
    return ";".join(f"{p:.3f},{t:.3f}" for p, t in trims)


def parse_trims(spec, count):
    parts = [tuple(float(v) for v in x.split(",")) for x in spec.split(";")]
    if any(len(p) != 2 for p in parts) or len(parts) not in (1, count):
        sys.exit(f"--imu-trim {spec}: PHI,THETA (deg) for all copters, or one per copter separated by ';'")
    return parts * count if len(parts) == 1 else parts


def last_fdm_line(path):
    # Another thread's output may share the line (NPS's "udp_thread: select failed!" has no
    # newline): from the tag on.
    tag = "[twinswarm fdm]"
    lines = [l[l.index(tag):] for l in path.read_text(errors="replace").splitlines() if tag in l]
    return lines[-1] if lines else ""


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--count", type=int, default=1)
    ap.add_argument("--plan", choices=["hover", "wall_avoid"], default="wall_avoid")
    ap.add_argument("--firmware", choices=["port", "2015-12", "2015-07"], default="port",
                    help="port: the project's airframe and module twinswarm_finken (default); 2015-12: the FINken's "
                    "own firmware of 16 Dec 2015 and its flight plan (hover: finken_rc_passthrough, wall_avoid: "
                    "finken_wall_avoid; set point 0.6 m); 2015-07: the paper's mixed-reality firmware and its flight "
                    "plan ovgu_sonar.xml (either plan: it centres on its sonars; set point 0.5 m); no AHRS/INS bypass "
                    "(build_nps.sh --firmware)")
    ap.add_argument("--duration", type=float, default=60.0)
    ap.add_argument("--first-ac", type=int, default=40, help="ac_id of the first aircraft (default 40)")
    ap.add_argument("--seed", type=int, default=2016)
    ap.add_argument("--gap", type=float, help="start the copters in a row along x, this far apart, m (facing each other in pairs)")
    ap.add_argument("--cruise", help="FWD,RIGHT cruise tilt of the wall_avoid plan, deg (default the airframe's 1.0,0.6); "
                    "(an aircraft is rebuilt when its options change: give such runs their own --first-ac)")
    ap.add_argument("--sighting-hold", type=float, help="the module's WA_SIGHTING_HOLD, s: a sonar reading nearer than "
                    "the goal distance stands in for farther ones this long (default the airframe's 0, off)")
    ap.add_argument("--arena", help="floor size XxY, m (default: 4x3 for up to two copters, larger for more)")
    ap.add_argument("--box", action="append", default=[], metavar="TOML",
                    help='a [[box]] table body, e.g. \'pos_m = [1.0, 0.0]; size_m = [0.4, 0.4, 2.0]; virtual_only = true\'')
    ap.add_argument("--airframe", metavar="TOML", help="overrides of the copters' airframe (an inline table's body, "
                    "docs/scenes.md), e.g. 'rotor_tolerance_sigma = 0'")
    ap.add_argument("--imu-trim", metavar="PHI,THETA[;...]", help="firmware runs: the copters' IMU calibration, "
                    "body-to-IMU roll and pitch, deg (one for all, or one per copter separated by ';'), as the lab's "
                    "calib/$AC_ID_imu_calib.xml gave it (FINKEN_FW_IMU_TRIM); default none")
    ap.add_argument("--trim-flights", type=int, default=0, metavar="N", help="firmware runs: trim each copter first, as "
                    "the lab did by flying: N hover flights (30 s, 40 m x 40 m, same seed), each moving the IMU "
                    "calibration by the mean roll and pitch the copter held (default 0: untrimmed)")
    ap.add_argument("--quiet", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--udp-out", type=int, help="one aircraft: its telemetry's UDP port (link -udp_port)")
    ap.add_argument("--udp-in", type=int, help="one aircraft: its datalink UDP port (link -udp_uplink_port)")
    ap.add_argument("--twinswarm", help="the twinswarm binary (default target/release/twinswarm, else "
                    "target/debug/twinswarm)")
    ap.add_argument("--out", help="keep the scene, logs and summaries here")
    ap.add_argument("--no-log", action="store_true", help="no MCAP log (speed runs): no flight figures")
    ap.add_argument("--transport", choices=["unix", "tcp"], default="unix",
                    help="between the world and each NPS: unix (default), a Unix-domain socket in a fresh temporary "
                    "folder, removed at the end; tcp: a free loopback port (as before 2026-11-28)")
    ap.add_argument("--one-build", action="store_true",
                    help="speed benches: build the first aircraft only and start every NPS from it, each told the "
                    "copter it flies by TWINSWARM_FDM_AC_ID (the ac_id is compiled in: N builds otherwise); their "
                    "telemetry and datalink all keep the first aircraft's id, so not with link (--udp-out)")
    ap.add_argument("--simsitl", metavar="PATH", help="speed benches: start every NPS from this aircraft binary, built "
                    "before (e.g. with another version of the glue), as --one-build does; nothing is built")
    ap.add_argument("--run-arg", action="append", default=[], help="an extra argument for twinswarm run")
    ap.add_argument("--stranger", type=int, metavar="AC", help="also start aircraft AC, which no copter of the scene flies: "
                    "the world must refuse it, and it must exit non-zero saying why")
    ap.add_argument("--stop", metavar="AC:AFTER_S", help="SIGSTOP aircraft AC's NPS AFTER_S wall seconds after it connects, "
                    "for --stop-for seconds (default 12, past the world's 10 s step timeout), then SIGCONT")
    ap.add_argument("--stop-for", type=float, default=12.0)
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args(argv)
    if a.twinswarm is None:
        a.twinswarm = default_twinswarm(quiet=a.quiet)
    if not (PPRZ / "env.sh").exists():
        sys.exit(f"no Paparazzi tree at {PPRZ}: run shared/paparazzi/build.sh {PPRZ} (scripts/test.sh does)")
    out = Path(a.out or tempfile.mkdtemp(prefix="nps_swarm."))
    out.mkdir(parents=True, exist_ok=True)
    acs = [a.first_ac + k for k in range(a.count)]
    if (a.imu_trim or a.trim_flights) and a.firmware == "port":
        sys.exit("--imu-trim/--trim-flights: the firmware's aircraft only (the port's AHRS is NPS's bypass)")
    trims = None
    if a.trim_flights > 0:
        a.imu_trim = trim_flights(a, a.trim_flights, out)
    if a.imu_trim:
        trims = parse_trims(a.imu_trim, a.count)
    t0 = time.monotonic()
    with open(out / "build.log", "w") as log:
        udp = (a.udp_out, a.udp_in) if a.udp_out else None
        if udp and a.count != 1:
            sys.exit("--udp-out/--udp-in: one aircraft only (the ports are compiled in)")
        if a.simsitl:
            a.one_build = True
        if a.one_build and udp:
            sys.exit("--one-build: not with --udp-out/--udp-in (its telemetry and datalink are the first aircraft's)")
        if a.simsitl:
            if not os.access(a.simsitl, os.X_OK):
                sys.exit(f"--simsitl {a.simsitl}: not an executable file")
            sims = [Path(a.simsitl).resolve()] * len(acs)
        elif a.one_build:
            sims = [build(acs[0], a.plan, log, udp, a.cruise, a.sighting_hold, a.firmware)] * len(acs)
        else:
            sims = [build(ac, a.plan, log, udp, a.cruise, a.sighting_hold, a.firmware) for ac in acs]
        if a.stranger is not None:
            if a.stranger in acs:
                sys.exit(f"--stranger {a.stranger}: that aircraft flies a copter of the scene")
            sims.append(build(a.stranger, a.plan, log, None, a.cruise, a.sighting_hold, a.firmware))
            acs_started = acs + [a.stranger]
        else:
            acs_started = acs
    build_s = time.monotonic() - t0
    sock_dir = None
    if a.transport == "unix":
        # Its own folder (0700) for this run's socket, short enough for a socket path (107 bytes).
        base = tempfile.gettempdir()
        sock_dir = tempfile.mkdtemp(prefix="tw-fdm.", dir=base if len(base) < 60 else "/tmp")
        fdm = f"unix:{sock_dir}/fdm.sock"
    else:
        fdm = f"127.0.0.1:{free_port()}"
    try:
        return fly(a, out, acs, acs_started, sims, trims, build_s, fdm)
    finally:
        if sock_dir:
            shutil.rmtree(sock_dir, ignore_errors=True)


def fly(a, out, acs, acs_started, sims, trims, build_s, fdm):
    """Starts the world listening on `fdm` and the NPS processes, waits, and reports."""
    boxes = [[s.strip() for s in b.split(";")] for b in a.box]
    size = tuple(float(v) for v in a.arena.split("x")) if a.arena else None
    text, arena = scene(a.count, a.first_ac, a.duration, a.seed, boxes, size, a.gap, a.airframe)
    (out / "scene.toml").write_text(text)
    run = [str(Path(a.twinswarm).resolve()), "run", str(out / "scene.toml"), "--no-bus", "--json", "--autopilot-listen", fdm]
    run += ["--no-log"] if a.no_log else ["--log", str(out / "run.mcap")]
    run += a.run_arg
    env = dict(os.environ)
    # CPU of the children reaped so far (the builds; earlier runs in this process), to subtract.
    ru0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    with open(out / "run.err", "w") as err, open(out / "run.json", "w") as js:
        world = subprocess.Popen(run, stdout=js, stderr=err, cwd=out)
        for _ in range(200):
            time.sleep(0.05)
            if "waiting for" in (out / "run.err").read_text() or world.poll() is not None:
                break
        npss = []
        for k, (ac, sim) in enumerate(zip(acs_started, sims)):
            e = dict(env, TWINSWARM_FDM=fdm)
            if a.one_build:
                e["TWINSWARM_FDM_AC_ID"] = str(ac)
            if trims and k < len(trims):
                e["FINKEN_FW_IMU_TRIM"] = f"{trims[k][0]:.3f},{trims[k][1]:.3f}"
            f = open(out / f"nps{ac}.log", "w")
            # env.sh: Paparazzi's libraries (libivy) and PAPARAZZI_HOME.
            # Each NPS on an Ivy bus of its own: they have nothing to say to each other there, and
            # ivy-c is not thread-safe: with many NPS agents on one bus, an NPS's Ivy thread
            # matching another's messages (libpcre) while its main loop sends crashed it
            # (SIGSEGV in libpcre, 1 of 64, 2026-11-28).
            cmd = f'. "{PPRZ}/env.sh" && exec "{sim}" --norc --time_factor 1e9 --ivy_bus 127.255.255.255:{free_port()}'
            npss.append(subprocess.Popen(["bash", "-c", cmd], stdout=f, stderr=subprocess.STDOUT, env=e, cwd=out))
        if a.stop:
            stop_ac, after = a.stop.split(":")
            victim = npss[acs_started.index(int(stop_ac))]

            victim_log = out / f"nps{stop_ac}.log"

            def stop_and_continue():
                # From its connection on (a slow machine may take longer to start it).
                for _ in range(600):
                    if "connected to the world" in victim_log.read_text(errors="replace"):
                        break
                    time.sleep(0.05)
                time.sleep(float(after))
                victim.send_signal(signal.SIGSTOP)
                time.sleep(a.stop_for)
                victim.send_signal(signal.SIGCONT)

            threading.Thread(target=stop_and_continue, daemon=True).start()
        world.wait(timeout=600 + a.duration * a.count)
        # CPU time of the children waited for since ru0: the world alone here, the autopilots after.
        ru = resource.getrusage(resource.RUSAGE_CHILDREN)
        world_cpu = ru.ru_utime + ru.ru_stime - (ru0.ru_utime + ru0.ru_stime)
        world_sleeps = ru.ru_nvcsw - ru0.ru_nvcsw
        world_preempted = ru.ru_nivcsw - ru0.ru_nivcsw
        ru0 = ru
        nps_exit = {}
        for ac, p in zip(acs_started, npss):
            try:
                nps_exit[ac] = p.wait(timeout=10 + (a.stop_for if a.stop else 0))
            except subprocess.TimeoutExpired:
                p.kill()
                nps_exit[ac] = "killed after the run"
    ru = resource.getrusage(resource.RUSAGE_CHILDREN)
    nps_cpu = ru.ru_utime + ru.ru_stime - (ru0.ru_utime + ru0.ru_stime)
    if world.returncode != 0:
        sys.exit(f"twinswarm run failed ({world.returncode}):\n{(out / 'run.err').read_text()[-3000:]}")
    summary = json.loads((out / "run.json").read_text())
    steps = summary["control_steps"]
    wall = summary["wall_time_s"]
    report = {
        "count": a.count,
        "plan": a.plan,
        "firmware": a.firmware,
        "sim_s": summary["sim_time_s"],
        "wall_s": round(wall, 3),
        "sim_s_per_wall_s": round(summary["sim_time_s"] / wall, 3),
        "steps": steps,
        "us_per_step": round(wall / steps * 1e6, 1),
        "waited_for_autopilots_s": round(summary["autopilot_wait_s"], 3),
        "world_s": round(wall - summary["autopilot_wait_s"], 3),
        # CPU per step: the world's (stepping, sending, receiving), each autopilot's (NPS: its
        # autopilot, sensors, flight-model client).
        "world_cpu_us_per_step": round(world_cpu / steps * 1e6, 1),
        "nps_cpu_us_per_step_each": round(nps_cpu / steps / a.count * 1e6, 1),
        # How often the world slept on an autopilot (voluntary context switches) per step.
        "world_sleeps_per_step": round(world_sleeps / steps, 2),
        # How often another process took the CPU from it (involuntary context switches) per step.
        "world_preempted_per_step": round(world_preempted / steps, 2),
        "transport": a.transport,
        "build_s": round(build_s, 1),
        "crashes": summary["crashes"],
        "autopilots_left": [ap_["ac_id"] for ap_ in summary["autopilots"] if ap_["left"]],
        "nps_exit": {ac: c for ac, c in nps_exit.items() if c != 0},
        # What each NPS's flight-model client said last ("the world refused ...", "closed ...").
        "nps_said": {ac: last_fdm_line(out / f"nps{ac}.log") for ac in acs_started},
        "autopilots_refused": summary.get("autopilots_refused", []),
        # Each aircraft's uplink in the lockstep (crates/bridge/src/autopilot.rs): "counted" or why
        # not, and how many the world sent it through link; its NPS's side is in nps_said.
        "uplinks": {ap_["ac_id"]: {"uplink": ap_.get("uplink"), "counted": ap_.get("uplinks_counted")}
                    for ap_ in summary["autopilots"]},
        "digests": {c["name"]: c["digest"] for c in summary["copters"]},
        "imu_trim": a.imu_trim,
        "out": str(out),
    }
    if not a.no_log:
        report.update(flight_figures(out / "run.mcap", arena))
    if a.quiet:
        pass
    elif a.json:
        print(json.dumps(report, indent=2))
    else:
        for k, v in report.items():
            print(f"{k}: {v}")
    return report


if __name__ == "__main__":
    main()
