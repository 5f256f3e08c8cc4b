#!/usr/bin/env python3
"""Run one NPS aircraft free (no external world) for S simulated seconds and time it.

    . target/paparazzi/env.sh
    python3 paparazzi/upstream_fdm/nps_timed_run.py --sim PATH/simsitl --duration 60 \
        [--ac-id 99] [--telemetry-port 4262] [--out DIR] [--json FILE]

NPS has no "stop at t" option, and with `--time_factor 1e9` it runs steps as fast as it can.
So this script is the clock: it binds the aircraft's telemetry port (UDP, compiled into the
aircraft; pprzlink v2 frames, see frames() below), starts NPS
(`--norc --time_factor 1e9 --nodisplay`, private Ivy bus 127.255.255.255:<free UDP port>) in a
process group of its own, and counts the aircraft's ROTORCRAFT_FP messages: the telemetry file
sends one every 0.25 s of autopilot time (125 periodic ticks at 500 Hz: counted in NPS steps,
never the wall clock), so simulated time = 0.25 s x count. ROTORCRAFT_STATUS.cpu_time (whole
seconds of sys_time) is recorded as a cross-check (a lost datagram would show as a
difference). When the count reaches S / 0.25 the wall time is taken and NPS's process group is
ended (SIGTERM, then SIGKILL after 2 s).

Reported: wall time from starting NPS to S simulated seconds (includes NPS/FDM start-up), the
wall time from the first telemetry message (t = 0) to S (the stepping alone), and their ratios
(simulated seconds per wall second), NPS's CPU time (user + sys, getrusage of the child:
less sensitive to other load on the machine; it includes the few ms until the SIGTERM);
and the flight: liftoff, time to 0.8 m, max height,
mean/sd of the height over the last 10 s, max tilt, horizontal drift. "hovered" = the mean
height over the last 10 s within 0.1 m of 1 m and its sd < 0.1 m (fake_hover.sh's criterion).
Bounded: gives up after --max-wall seconds (default 60 + 20 S).
"""
import argparse
import json
import resource
import math
import os
import signal
import socket
import statistics
import struct
import subprocess
import sys
import time

ap = argparse.ArgumentParser()
ap.add_argument("--sim", required=True)
ap.add_argument("--duration", type=float, default=60.0)
ap.add_argument("--ac-id", type=int, default=99)
ap.add_argument("--telemetry-port", type=int, default=4262)
ap.add_argument("--fp-period", type=float, default=0.25, help="ROTORCRAFT_FP period in the telemetry file (s)")
ap.add_argument("--out", default=".")
ap.add_argument("--json", default="")
ap.add_argument("--max-wall", type=float, default=0.0)
a = ap.parse_args()

home = os.environ.get("PAPARAZZI_HOME")
if not home:
    sys.exit("source target/paparazzi/env.sh first (PAPARAZZI_HOME)")
sys.path.insert(0, os.path.join(home, "sw/ext/pprzlink/lib/v2.0/python"))
os.environ.setdefault("PAPARAZZI_SRC", home)
from pprzlink.pprz_transport import PprzTransport  # noqa: E402

max_wall = a.max_wall or (60.0 + 20.0 * a.duration)
os.makedirs(a.out, exist_ok=True)

# telemetry socket first (no SO_REUSEADDR: fail if someone else listens there)
tel = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
tel.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 8 << 20)
try:
    tel.bind(("0.0.0.0", a.telemetry_port))
except OSError as e:
    sys.exit(f"telemetry port {a.telemetry_port} is busy ({e}): another run or a link is listening there")
tel.settimeout(0.2)

# a free UDP port for the private Ivy bus
probe = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
probe.bind(("0.0.0.0", 0))
ivy_port = probe.getsockname()[1]
probe.close()

cmd = [a.sim, "--norc", "--time_factor", "1e9", "--nodisplay", "--ivy_bus", f"127.255.255.255:{ivy_port}"]
log = open(os.path.join(a.out, "nps.log"), "w")
t0 = time.monotonic()
proc = subprocess.Popen(cmd, cwd=a.out, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)

# Fast frame scan (pprzlink v2 "pprz" transport: STX 0x99, LEN = whole frame, sender, receiver,
# class|component<<4, msg_id, payload, ck_a, ck_b): decoding every byte with PprzTransport costs
# ~0.1-0.5 s of Python CPU per 60 s run, which competes with NPS on 2 cores. Only
# ROTORCRAFT_FP and ROTORCRAFT_STATUS are decoded (struct), and the first of each is checked
# against pprzlink's own decoder.
from pprzlink.message import PprzMessage  # noqa: E402
FP_ID = PprzMessage("telemetry", "ROTORCRAFT_FP").msg_id
ST_ID = PprzMessage("telemetry", "ROTORCRAFT_STATUS").msg_id
TEL_CLASS = PprzMessage("telemetry", "ROTORCRAFT_FP").class_id
ST_FIELDS = PprzMessage("telemetry", "ROTORCRAFT_STATUS").fieldnames
assert ST_FIELDS[:12] == ["link_imu_nb_err", "motor_nb_err", "rc_status", "frame_rate", "gps_status", "ap_mode",
                          "ap_in_flight", "ap_motors_on", "arming_status", "ap_h_mode", "ap_v_mode", "cpu_time"], ST_FIELDS
checked = set()


def frames(data):
    i, n = 0, len(data)
    while i + 6 <= n:
        if data[i] != 0x99:
            i += 1
            continue
        ln = data[i + 1]
        if ln < 6 or i + ln > n:
            i += 1
            continue
        ck_a = ck_b = 0
        for b in data[i + 1:i + ln - 2]:
            ck_a = (ck_a + b) & 0xFF
            ck_b = (ck_b + ck_a) & 0xFF
        if ck_a != data[i + ln - 2] or ck_b != data[i + ln - 1]:
            i += 1
            continue
        yield data[i + 2:i + ln - 2]  # sender, receiver, class|comp, msg_id, payload
        i += ln


def check(buf, name, fast):
    if name in checked:
        return
    checked.add(name)
    tp = PprzTransport("telemetry")
    _s, _r, _c, msg = tp.unpack_pprz_msg(bytearray(buf))
    v = dict(zip(msg.fieldnames, msg.fieldvalues))
    for k, x in fast.items():
        if int(v[k]) != x:
            sys.exit(f"fast decoder disagrees with pprzlink on {name}.{k}: {x} != {v[k]}")


n_fp = 0
t_first = None
t_done = None
cpu_time = 0
fp = []  # (sim_t, up, east, north, phi, theta)
status_last = {}
target = int(round(a.duration / a.fp_period))
reason = ""
try:
    while True:
        now = time.monotonic()
        if now - t0 > max_wall:
            reason = f"gave up after {max_wall:.0f} s wall"
            break
        if proc.poll() is not None:
            reason = f"NPS exited early (status {proc.returncode})"
            break
        try:
            data, _ = tel.recvfrom(65536)
        except socket.timeout:
            continue
        now = time.monotonic()
        for buf in frames(data):
            if buf[0] != a.ac_id or (buf[2] & 0x0F) != TEL_CLASS:
                continue
            if t_first is None:
                t_first = now
            if buf[3] == FP_ID:
                east, north, up = struct.unpack_from("<3i", buf, 4)
                phi, theta = struct.unpack_from("<2i", buf, 4 + 24)
                check(buf, "ROTORCRAFT_FP", {"east": east, "north": north, "up": up, "phi": phi, "theta": theta})
                fp.append((n_fp * a.fp_period, up / 256.0, east / 256.0, north / 256.0,
                           phi * 0.0139882, theta * 0.0139882))
                n_fp += 1
                if n_fp > target and t_done is None:
                    t_done = now
            elif buf[3] == ST_ID:
                b = struct.unpack_from("<I10BH", buf, 4)
                st = dict(zip(ST_FIELDS[:12], b))
                check(buf, "ROTORCRAFT_STATUS", st)
                cpu_time = max(cpu_time, st["cpu_time"])
                status_last = {k: st[k] for k in ("ap_mode", "ap_motors_on", "ap_in_flight")}
        if t_done is not None:
            break
finally:
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGTERM)
        try:
            proc.wait(2)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    log.close()
    tel.close()
# CPU time of NPS (our only child; it ran a few ms past t_done until the SIGTERM)
ru = resource.getrusage(resource.RUSAGE_CHILDREN)
nps_cpu = ru.ru_utime + ru.ru_stime

res = {"sim": a.sim, "duration_s": a.duration, "ivy_bus": f"127.255.255.255:{ivy_port}",
       "rotorcraft_fp_received": n_fp, "status_cpu_time_s": cpu_time, "last_status": status_last}
if t_done is None:
    res["error"] = reason or "did not reach the duration"
else:
    wall_total = t_done - t0
    wall_step = t_done - t_first
    res.update({
        "wall_total_s": round(wall_total, 3),
        "wall_startup_s": round(t_first - t0, 3),
        "wall_stepping_s": round(wall_step, 3),
        "sim_per_wall_total": round(a.duration / wall_total, 2),
        "sim_per_wall_stepping": round(a.duration / wall_step, 2),
        "nps_cpu_s": round(nps_cpu, 3),
        "sim_per_nps_cpu_s": round(a.duration / nps_cpu, 2) if nps_cpu > 0 else None,
    })
if fp:
    ups = [(t, u) for t, u, *_ in fp]
    last = [u for t, u in ups if t >= a.duration - 10.0]
    lift = next((t for t, u in ups if u > 0.05), None)
    reach = next((t for t, u in ups if u > 0.8), None)
    e0, n0 = fp[0][2], fp[0][3]
    res["flight"] = {
        "liftoff_s": lift, "reach_0.8m_s": reach,
        "max_height_m": round(max(u for _, u in ups), 3),
        "last10s_mean_m": round(statistics.fmean(last), 4) if last else None,
        "last10s_sd_m": round(statistics.pstdev(last), 4) if len(last) > 1 else None,
        "max_tilt_after_liftoff_deg": round(max((max(abs(p), abs(q)) for t, u, _e, _n, p, q in fp
                                                  if lift is not None and t >= lift), default=0.0), 2),
        "max_horizontal_drift_m": round(max(math.hypot(e - e0, n - n0) for _t, _u, e, n, _p, _q in fp), 3),
    }
    res["hovered"] = bool(last) and abs(statistics.fmean(last) - 1.0) < 0.1 and statistics.pstdev(last) < 0.1
    with open(os.path.join(a.out, "height.csv"), "w") as f:
        f.write("sim_t_s,up_m,east_m,north_m,phi_deg,theta_deg\n")
        for row in fp:
            f.write(",".join(f"{x:.4f}" for x in row) + "\n")
else:
    res["hovered"] = False
print(json.dumps(res))
if a.json:
    with open(a.json, "w") as f:
        json.dump(res, f, indent=1)
sys.exit(0 if t_done is not None and res["hovered"] else 1)
