#!/usr/bin/env python3
"""Figures of the *real* FINken copters that a simulator must be held against.

Reads the real Paparazzi flight logs in the shared data folder (`finken_flights/`, see its
SOURCES.md section "finken_flights/") and computes, for every `.data` + `.log` pair
(report_2015-12-16 and each robust_multicopter_flight experiment) and the battery CSVs:

1. flights: motor-on segments (ROTORCRAFT_STATUS ap_motors_on, edges refined to the
   telemetry sample by the motor vibration in FINKEN_SENSOR_MODEL acceleration_z), take-off
   and landing (IR height pos_z above its on-ground reading), duration, aircraft;
2. telemetry inter-arrival per message (FINKEN_SENSOR_MODEL, AHRS_EULER_INT, ROTORCRAFT_FP):
   configured period of the active telemetry mode, observed gaps (median, mean, p95, p99,
   share > 50 ms, 5 ms histogram to 200 ms), link outages, modem baud rate and link load;
3. attitude noise per flight (AHRS_EULER_INT body angles and FINKEN_SENSOR_MODEL angles):
   mean and standard deviation of roll and pitch in the settled part, split by the state of
   finken_wall_avoid read from the sonars (idle = "hover", active, guard);
4. height hold: IR height in the settled part and from take-off + 5 s to landing - 1 s
   (mean, std, min, max), and the set point of the flight plan in the `.log`;
5. battery: hover thrust against voltage (thrust = a + b*V) over each ~9-minute flight;
6. sonar noise: at rest (MC1/MC2_DISTANCES plateaus) and in flight;
7. arena geometry of the 16 Dec 2015 lab from the sonars, the copter's start positions,
   and V-REP's own output for its twin: which logged angle tilts it which way, the mapping
   of V-REP time to log time (V-REP ran ~2 % slow), and where and when it left the arena.

The field order of every message is taken from the `.log` of the same flight.

Run (Python 3.11, numpy):

    python3 scripts/real_flights.py [SHARED_DATA_DIR] [--json FILE]

SHARED_DATA_DIR defaults to $TWINSWARM_SHARED_DATA, else ../shared/data next to the
repository root.  Without numpy: python3 -m venv /tmp/rf && /tmp/rf/bin/pip install numpy.
"""
import argparse
import collections
import json
import math
import os
import pathlib
import re
import sys
import xml.etree.ElementTree as ET

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
G = 9.81
PPRZ_OVERHEAD = 6          # STX, length, sender id, message id, two checksum bytes
BITS_PER_BYTE = 10         # 8N1 on the serial modem
GAP_OUTAGE_S = 1.0         # a gap longer than this is a link outage, not telemetry jitter
VIB_THRESHOLD = 0.25       # m/s^2: rolling std of acceleration_z with the motors running
AIRBORNE_MARGIN = 0.08     # m above the on-ground IR reading
STEADY_AFTER_TAKEOFF = 5.0  # s
STEADY_BEFORE_LANDING = 1.0  # s
SONAR_VALID = (20, 300)    # cm, FINKEN_MIN_DIST / FINKEN_MAX_DIST (finken_model common.xml)
SONAR_FACE_SEPARATION = 0.20  # m between opposite sonar faces (assumption, checked below)
SONARS = ("distance_d_front", "distance_d_rigth", "distance_d_left", "distance_d_back")  # sic
# The V-REP arena of the 2015-12-16 twin: x in [-4, 0], y in [0, 3] (the rectangle drawn
# over simulationPosition20151216140935.log and logExampleArenaBoundaries.log by the
# authors' documentation/plots/scatterPlotPosition.py, ovgu-FINken/Simulation).
VREP_ARENA = (-4.0, 0.0, 0.0, 3.0)
ANGLE_INT_TO_DEG = math.degrees(2.0 ** -12)  # 0.0139882 deg, AHRS_EULER_INT unit
CHECKS_16DEC_FSM = {"median_ms": 28, "mean_ms": 35, "p95_ms": 63, "p99_ms": 91, "over_50ms": 0.14}


# --------------------------------------------------------------------------- parsing

def attr(elem, name):
    """An XML attribute whatever its case (the logs write most of them in upper case)."""
    for key in (name, name.upper(), name.lower()):
        if key in elem.attrib:
            return elem.attrib[key]
    return None


def parse_log(path):
    """Message definitions (by class) and the root element of a Paparazzi server `.log`."""
    root = ET.parse(path).getroot()
    defs = {}
    for cls in root.iter("msg_class"):
        for msg in cls.findall("message"):
            fields = [(attr(f, "name"), attr(f, "type")) for f in msg.findall("field")]
            defs.setdefault(attr(msg, "name"), {"class": attr(cls, "name"), "fields": fields})
    return root, defs


def find_aircraft(root, ac_id):
    for ac in root.iter("aircraft"):
        if attr(ac, "ac_id") == str(ac_id):
            return ac
    return None


def aircraft_config(ac):
    """Name, modem baud, telemetry modes (in order) and height set point of one aircraft."""
    baud = None
    for conf in ac.iter("configure"):
        if attr(conf, "name") == "MODEM_BAUD":
            baud = int(attr(conf, "value").lstrip("B"))
    modes = {}
    for proc in ac.iter("process"):
        for mode in proc.findall("mode"):
            modes[attr(mode, "name")] = {attr(m, "name"): float(attr(m, "period"))
                                         for m in mode.findall("message")}
    setpoints = [float(attr(s, "value")) for s in ac.iter("set")
                 if attr(s, "var") == "finken_system_set_point.z"]
    return {"name": attr(ac, "name"), "baud": baud, "modes": modes,
            "mode_order": list(modes), "z_setpoint": setpoints[0] if setpoints else None}


class Msg:
    """All occurrences of one message: times, sender ids, numeric columns and wire sizes."""

    def __init__(self, rows, fields):
        self.t = np.array([float(r[0]) for r in rows])
        self.ac = [r[1] for r in rows]
        self.cols = {}
        for i, (name, _type) in enumerate(fields):
            self.cols[name] = np.array([to_float(r, 3 + i) for r in rows])
        self.size = np.array([payload_size(r[3:], fields) for r in rows]) if fields else None

    def __getitem__(self, name):
        return self.cols[name]


def to_float(row, i):
    try:
        return float(row[i])
    except (IndexError, ValueError):
        return math.nan


TYPE_SIZE = {"int8": 1, "uint8": 1, "char": 1, "int16": 2, "uint16": 2, "int32": 4,
             "uint32": 4, "float": 4, "int64": 8, "uint64": 8, "double": 8}


def payload_size(values, fields):
    """Bytes of a message payload on the wire (arrays and strings carry a length byte)."""
    size = 0
    for (_, ftype), text in zip(fields, values):
        if ftype.endswith("[]"):
            size += 1 + TYPE_SIZE.get(ftype[:-2], 1) * len(text.split(","))
        elif ftype == "string":
            size += 1 + len(text)
        else:
            size += TYPE_SIZE.get(ftype, 4)
    return size


def load_data(path, defs):
    rows = collections.defaultdict(list)
    with open(path) as f:
        for line in f:
            parts = line.split()
            if len(parts) >= 3:
                rows[parts[2]].append(parts)
    return {name: Msg(rr, defs.get(name, {"fields": []})["fields"]) for name, rr in rows.items()}


def load_flight(stem):
    """One `.data` + `.log` pair: messages, definitions and the flying aircraft's config."""
    root, defs = parse_log(stem.with_suffix(".log"))
    msgs = load_data(stem.with_suffix(".data"), defs)
    fsm = msgs.get("FINKEN_SENSOR_MODEL")
    ac_id = fsm.ac[0] if fsm else next(iter(msgs.values())).ac[0]
    ac = find_aircraft(root, ac_id)
    return {"stem": stem, "msgs": msgs, "defs": defs, "ac_id": ac_id,
            "config": aircraft_config(ac) if ac is not None else None}


# --------------------------------------------------------------------------- statistics

def r(x, nd=3):
    """Round for printing and JSON (None for missing values)."""
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return None
    return round(float(x), nd)


def describe(x, nd=3):
    x = np.asarray(x, float)
    x = x[np.isfinite(x)]
    if len(x) == 0:
        return {"n": 0}
    return {"n": int(len(x)), "mean": r(x.mean(), nd), "std": r(x.std(ddof=1) if len(x) > 1 else 0, nd),
            "min": r(x.min(), nd), "max": r(x.max(), nd)}


def rolling_std(t, x, half_window):
    """Standard deviation of x over [t - w, t + w] at every sample (time-based window)."""
    lo = np.searchsorted(t, t - half_window)
    hi = np.searchsorted(t, t + half_window, side="right")
    c1 = np.concatenate([[0], np.cumsum(x)])
    c2 = np.concatenate([[0], np.cumsum(x * x)])
    n = np.maximum(hi - lo, 1)
    mean = (c1[hi] - c1[lo]) / n
    return np.sqrt(np.maximum((c2[hi] - c2[lo]) / n - mean ** 2, 0))


def moving_median(x, n):
    pad = n // 2
    xp = np.pad(x, pad, mode="edge")
    return np.array([np.median(xp[i:i + n]) for i in range(len(x))])


def in_windows(t, windows):
    mask = np.zeros(len(t), bool)
    for a, b in windows:
        mask |= (t >= a) & (t <= b)
    return mask


# --------------------------------------------------------------------------- 1 flights

def motor_runs(status):
    """Runs of ROTORCRAFT_STATUS samples with ap_motors_on = 1, with their bracketing samples."""
    on = status["ap_motors_on"] == 1
    t = status.t
    runs, i = [], 0
    while i < len(t):
        if not on[i]:
            i += 1
            continue
        j = i
        while j + 1 < len(t) and on[j + 1]:
            j += 1
        before = t[i - 1] if i > 0 else -math.inf
        after = t[j + 1] if j + 1 < len(t) else math.inf
        runs.append((before, t[i], t[j], after))
        i = j + 1
    return runs


def vibration(fsm):
    rate = 1.0 / max(np.median(np.diff(fsm.t)), 1e-3)
    half = max(0.25, 3.0 / rate)
    return rolling_std(fsm.t, np.nan_to_num(fsm["acceleration_z"]), half)


def refine_edges(fsm, vib, run):
    """Motor start/stop at the telemetry samples where the vibration run that contains the first
    (last) 'on' status begins (ends), walking over consecutive samples (no gap over 0.5 s) and
    never past the bracketing 'off' statuses. Flags an end that falls in a telemetry outage."""
    before, first_on, last_on, after = run
    t, hot = fsm.t, vib > VIB_THRESHOLD
    i = max(int(np.searchsorted(t, first_on, side="right")) - 1, 0)
    start = first_on
    if hot[i] and t[i] > before:
        while i > 0 and hot[i - 1] and t[i] - t[i - 1] < 0.5 and t[i - 1] > before:
            i -= 1
        start = t[i]
    j = min(int(np.searchsorted(t, last_on)), len(t) - 1)
    end, end_in_gap = last_on, False
    if hot[j] and t[j] < after:
        while j + 1 < len(t) and hot[j + 1] and t[j + 1] - t[j] < 0.5 and t[j + 1] < after:
            j += 1
        end = t[j]
    seen = t[(t >= last_on) & (t <= min(after, t[-1]))]
    end_in_gap = after == math.inf or (len(seen) > 1 and np.diff(seen).max() > GAP_OUTAGE_S)
    return float(start), float(end), bool(end_in_gap)


def airborne(fsm, start, end):
    """Take-off: first IR height above the on-ground reading + 8 cm that holds for 0.5 s.
    Landing: first later sample below on-ground + 4 cm for the next 1 s (or up to an outage),
    or a flip (|roll| or |pitch| over 45 deg; the IR sensor then sees the ceiling)."""
    ground = fsm["pos_z"][(fsm.t < start) & (fsm.t > start - 10)]
    if len(ground) == 0:  # log starts with the motors on: the first second is still on ground
        ground = fsm["pos_z"][(fsm.t >= start) & (fsm.t < start + 1)]
    z0 = float(np.median(ground))
    k = (fsm.t >= start) & (fsm.t <= end)
    t, z = fsm.t[k], fsm["pos_z"][k]
    tilt = np.maximum(np.abs(fsm["pos_roll"][k]), np.abs(fsm["pos_pitch"][k]))
    up = z > z0 + AIRBORNE_MARGIN
    down = z < z0 + AIRBORNE_MARGIN / 2
    takeoff = next((i for i in range(len(t)) if up[i] and up[(t >= t[i]) & (t <= t[i] + 0.5)].all()), None)
    if takeoff is None:
        return z0, None, None
    for i in range(takeoff + 1, len(t)):
        ahead = (t > t[i]) & (t <= t[i] + 1.0)
        if tilt[i] > math.radians(45) or (down[i] and down[ahead].all()):
            return z0, float(t[takeoff]), float(t[i - 1])
    return z0, float(t[takeoff]), float(t[-1])


def steady_window(fsm, takeoff, landing):
    """From 5 s after take-off, and once the smoothed height is within 5 cm of the flight's
    steady height (median of the second half), until 1 s before landing."""
    a, b = takeoff + STEADY_AFTER_TAKEOFF, landing - STEADY_BEFORE_LANDING
    k = (fsm.t >= takeoff) & (fsm.t <= landing)
    if b - a < 2 or k.sum() < 10:
        return None
    t, z = fsm.t[k], fsm["pos_z"][k]
    z_ref = np.median(z[t >= (takeoff + landing) / 2])
    zs = moving_median(z, 9)
    ok = (t >= a) & (np.abs(zs - z_ref) < 0.05)
    if not ok.any() or b - t[ok][0] < 2:
        return None
    return float(t[ok][0]), b


def segment_flights(log):
    msgs = log["msgs"]
    fsm, status = msgs.get("FINKEN_SENSOR_MODEL"), msgs.get("ROTORCRAFT_STATUS")
    if fsm is None or status is None:
        return []
    vib = vibration(fsm)
    flights = []
    for run in motor_runs(status):
        start, end, end_in_gap = refine_edges(fsm, vib, run)
        z0, takeoff, landing = airborne(fsm, start, end)
        steady = steady_window(fsm, takeoff, landing) if takeoff else None
        flights.append({"n": len(flights) + 1, "aircraft": log["config"]["name"],
                        "ac_id": log["ac_id"], "motors_on": r(start), "motors_off": r(end),
                        "duration_s": r(end - start, 1), "end_in_telemetry_gap": end_in_gap,
                        "start_before_log": run[0] == -math.inf,
                        "status_on": [r(run[1]), r(run[2])], "ground_ir_m": r(z0),
                        "takeoff": r(takeoff), "landing": r(landing),
                        "airborne_s": r(landing - takeoff, 1) if takeoff else None,
                        "steady": [r(steady[0]), r(steady[1])] if steady else None})
    return flights


def autopilot_boots(log):
    """Log times at which the autopilot (re)started: ROTORCRAFT_STATUS time - cpu_time (s),
    grouped within 3 s. A boot after an outage means the copter was powered off."""
    st = log["msgs"].get("ROTORCRAFT_STATUS")
    if st is None:
        return []
    boots = []
    for b in sorted(st.t - st["cpu_time"]):
        if not boots or b - boots[-1][-1] > 3:
            boots.append([b])
        else:
            boots[-1].append(b)
    return [r(np.median(g), 1) for g in boots]


# --------------------------------------------------------------------------- 2 telemetry

def active_mode(log):
    """The telemetry mode: DL_VALUE index 0 (Paparazzi puts telemetry_mode_<process> before
    the settings listed in the .log) and, as a check, the mode whose message set best
    matches the telemetry messages actually received."""
    cfg, msgs = log["config"], log["msgs"]
    by_setting = None
    dl = msgs.get("DL_VALUE")
    if dl is not None:
        vals = set(dl["value"][dl["index"] == 0])
        if len(vals) == 1:
            idx = int(vals.pop())
            by_setting = cfg["mode_order"][idx] if idx < len(cfg["mode_order"]) else None
    seen = {n for n, m in msgs.items() if log["defs"].get(n, {}).get("class") == "telemetry"}
    seen -= {"BLOCK", "PONG", "SETTING", "WP_MOVED_ENU"}  # forwarded uplink / renamed
    jacc = {name: len(seen & set(m)) / len(seen | set(m)) for name, m in cfg["modes"].items()}
    by_messages = max(jacc, key=jacc.get)
    return by_setting or by_messages, by_setting, by_messages, r(jacc[by_messages])


def gap_stats(t, windows=None, period=None):
    """Inter-arrival statistics of one message; gaps over max(1 s, 3 periods) are outages,
    counted apart."""
    t = np.asarray(t)
    limit = max(GAP_OUTAGE_S, 3 * period) if period else GAP_OUTAGE_S
    gaps = np.diff(t)
    if windows is not None:
        keep = in_windows(t[:-1], windows) & in_windows(t[1:], windows)
        gaps = gaps[keep]
    outages = gaps[gaps > limit]
    g = gaps[gaps <= limit] * 1000.0
    if len(g) < 2:
        return {"n_gaps": int(len(g))}
    hist, _ = np.histogram(g, bins=np.arange(0, 205, 5))
    return {"n_gaps": int(len(g)), "median_ms": r(np.median(g), 1), "mean_ms": r(g.mean(), 1),
            "p95_ms": r(np.percentile(g, 95), 1), "p99_ms": r(np.percentile(g, 99), 1),
            "max_ms": r(g.max(), 1), "over_50ms": r((g > 50).mean(), 4),
            "outages": int(len(outages)), "outage_limit_s": r(limit, 2), "outage_total_s": r(outages.sum(), 1),
            "hist_5ms_to_200": hist.tolist(), "hist_over_200": int((g >= 200).sum())}


def link_load(log, mode):
    """Bytes/s on the modem: configured (active mode), observed, and the ground's LINK_REPORT."""
    cfg, msgs, defs = log["config"], log["msgs"], log["defs"]
    capacity = cfg["baud"] / BITS_PER_BYTE
    configured = 0.0
    for name, period in cfg["modes"][mode].items():
        m = msgs.get(name)
        if m is not None and m.size is not None:
            size = float(np.mean(m.size))
        elif name in defs:
            size = sum(TYPE_SIZE.get(ft, 4) for _, ft in defs[name]["fields"])
        else:
            continue
        configured += (size + PPRZ_OVERHEAD) / period
    tele = [m for n, m in msgs.items() if defs.get(n, {}).get("class") == "telemetry"]
    up = link_up_seconds(log)
    observed = sum(float(np.sum(m.size + PPRZ_OVERHEAD)) for m in tele if m.size is not None) / up
    rep = msgs.get("LINK_REPORT")
    reported = rep["rx_bytes_rate"][rep["rx_bytes_rate"] > 0] if rep is not None else np.array([])
    return {"baud": cfg["baud"], "capacity_Bps": r(capacity, 0),
            "configured_Bps": r(configured, 0), "configured_load": r(configured / capacity, 3),
            "observed_Bps": r(observed, 0), "observed_load": r(observed / capacity, 3),
            "link_up_s": r(up, 1),
            "link_report_rx_Bps_median": r(np.median(reported), 0) if len(reported) else None,
            "link_report_load_median": r(np.median(reported) / capacity, 3) if len(reported) else None}


def link_up_seconds(log):
    """Time covered by telemetry, without outages over 1 s."""
    t = np.sort(np.concatenate([m.t for n, m in log["msgs"].items()
                                if log["defs"].get(n, {}).get("class") == "telemetry"]))
    gaps = np.diff(t)
    return float(gaps[gaps <= GAP_OUTAGE_S].sum())


def telemetry_report(log, flights):
    mode, by_setting, by_messages, jacc = active_mode(log)
    periods = log["config"]["modes"][mode]
    windows = [(f["motors_on"], f["motors_off"]) for f in flights]
    out = {"mode": mode, "mode_by_DL_VALUE_index0": by_setting,
           "mode_by_message_set": by_messages, "message_set_jaccard": jacc, "messages": {}}
    for name in ("FINKEN_SENSOR_MODEL", "AHRS_EULER_INT", "ROTORCRAFT_FP"):
        m = log["msgs"].get(name)
        if m is None:
            out["messages"][name] = {"configured_period_s": periods.get(name), "count": 0}
            continue
        out["messages"][name] = {"configured_period_s": periods.get(name), "count": len(m.t),
                                 "all": gap_stats(m.t, None, periods.get(name)),
                                 "motors_on": gap_stats(m.t, windows, periods.get(name))}
    out["link"] = link_load(log, mode)
    return out


# --------------------------------------------------------------------------- 3, 4 attitude, height

def wall_avoid_state(fsm, goal_dist=1.2, guard_dist=0.7, hold=1.0):
    """0 idle, 1 active, 2 guard. finken_wall_avoid corrects a sonar pair when its nearer
    sonar reads < GOAL_DIST (1.2 m) and damps commands toward walls nearer than GUARD_DIST
    (0.7 m; finken_wall_avoid/common.xml); its lead-lag state lingers, so within 1 s of an
    active sample counts as active too."""
    d = np.full(len(fsm.t), np.inf)
    for name in SONARS:
        x = fsm[name]
        d = np.minimum(d, np.where((x >= SONAR_VALID[0]) & (x < SONAR_VALID[1]), x / 100.0, np.inf))
    near = d < goal_dist
    state = np.zeros(len(d), int)
    if near.any():
        state[in_windows(fsm.t, merge([(fsm.t[i] - hold, fsm.t[i] + hold) for i in np.where(near)[0]]))] = 1
    state[d < guard_dist] = 2
    return state


def merge(windows):
    out = []
    for a, b in sorted(windows):
        if out and a <= out[-1][1]:
            out[-1] = (out[-1][0], max(out[-1][1], b))
        else:
            out.append((a, b))
    return out


def angle_stats(t, roll, pitch, window, wa_t, wa):
    k = (t >= window[0]) & (t <= window[1])
    state = wa[np.clip(np.searchsorted(wa_t, t, side="right") - 1, 0, len(wa) - 1)]
    out = {}
    for label, sel in (("all", k), ("wall_avoid_idle", k & (state == 0)),
                       ("wall_avoid_active", k & (state == 1)), ("wall_avoid_guard", k & (state == 2))):
        out[label] = {"n": int(sel.sum()),
                      "roll_deg": describe(roll[sel], 2), "pitch_deg": describe(pitch[sel], 2)}
    return out


def attitude_and_height(log, flight):
    msgs, fsm = log["msgs"], log["msgs"]["FINKEN_SENSOR_MODEL"]
    win = flight["steady"]
    wa = wall_avoid_state(fsm)
    out = {"steady": win}
    before = (fsm.t < flight["motors_on"]) & (fsm.t > flight["motors_on"] - 10)
    out["on_ground_deg"] = {"roll": r(np.degrees(np.median(fsm["pos_roll"][before])), 2) if before.any() else None,
                            "pitch": r(np.degrees(np.median(fsm["pos_pitch"][before])), 2) if before.any() else None}
    k = (fsm.t >= win[0]) & (fsm.t <= win[1])
    out["wall_avoid_share_idle_active_guard"] = [r(np.mean(wa[k] == v), 3) for v in (0, 1, 2)]
    out["fsm"] = angle_stats(fsm.t, np.degrees(fsm["pos_roll"]), np.degrees(fsm["pos_pitch"]), win, fsm.t, wa)
    ahrs = msgs.get("AHRS_EULER_INT")
    if ahrs is not None:
        out["ahrs_body"] = angle_stats(ahrs.t, ahrs["body_phi"] * ANGLE_INT_TO_DEG,
                                       ahrs["body_theta"] * ANGLE_INT_TO_DEG, win, fsm.t, wa)
    z = fsm["pos_z"][k]
    a, b = flight["takeoff"] + STEADY_AFTER_TAKEOFF, flight["landing"] - STEADY_BEFORE_LANDING
    z_air = fsm["pos_z"][(fsm.t >= a) & (fsm.t <= b)]
    out["height_airborne"] = dict(describe(z_air, 3), window=[r(a), r(b)])
    sp = msgs.get("FINKEN_SYSTEM_SET_POINT")
    out["height"] = dict(describe(z, 3), setpoint_flight_plan=log["config"]["z_setpoint"],
                         setpoint_telemetry=sorted(set(sp["distance_z"].tolist())) if sp else None,
                         error_mean=r(z.mean() - log["config"]["z_setpoint"], 3))
    return out


# --------------------------------------------------------------------------- 5 battery

def read_csv(path, sep):
    with open(path) as f:
        header = f.readline().rstrip("\n").split(sep)
        rows = [line.rstrip("\n").split(sep) for line in f if line.strip()]
    return header, rows


def longest_run(mask, t, max_dip=2.0):
    """Longest stretch of mask, bridging dips shorter than max_dip seconds."""
    idx = np.where(mask)[0]
    if len(idx) == 0:
        return None
    runs, a = [], idx[0]
    for p, q in zip(idx[:-1], idx[1:]):
        if t[q] - t[p] > max_dip:
            runs.append((a, p))
            a = q
    runs.append((a, idx[-1]))
    return max(runs, key=lambda ab: t[ab[1]] - t[ab[0]])


def thrust_compensation(firmware_dir, ac_id):
    """The firmware's battery compensation for aircraft `ac_id` (`finken_model_actuators.c`,
    `compensate_battery_drop`): FINKEN_ACTUATORS_MODEL.thrust = FINKEN_ACTUATORS_SET_POINT.thrust
    + (THRUST_LOW - THRUST_DEFAULT) * (84 - vsupply) / (84 - 65), vsupply in decivolts, the
    result clamped to [0.2, 1.0]; the two constants from the aircraft's `<ac_id>_param.xml`.
    Returns (low, default) or None where the firmware copy is absent."""
    f = firmware_dir / "conf" / "modules" / "finken_model" / f"{ac_id}_param.xml"
    if not f.is_file():
        return None
    text = f.read_text()
    get = lambda name: float(re.search(rf'name="{name}"\s+value="([^"]+)"', text).group(1))
    return get("THRUST_LOW"), get("THRUST_DEFAULT")


def battery_fit(t, v, thr, a, b):
    k = (t >= t[a] + 10) & (t <= t[b] - 5)
    fit = np.polyfit(v[k], thr[k], 1)
    resid = thr[k] - np.polyval(fit, v[k])
    first, last = k & (t < t[a] + 20), k & (t > t[b] - 15)
    # thrust ∝ V^-p: the slope of log thrust against log V.
    p = -np.polyfit(np.log(v[k]), np.log(thr[k]), 1)[0]
    return {"thrust_a": r(fit[1], 4), "thrust_b_per_V": r(fit[0], 4),
            "r": r(np.corrcoef(v[k], thr[k])[0, 1], 3), "resid_std": r(resid.std(), 4),
            "thrust_start": r(np.median(thr[first]), 3), "thrust_end": r(np.median(thr[last]), 3),
            "rise_pct": r(100 * (np.median(thr[last]) / np.median(thr[first]) - 1), 0),
            "power_of_V": r(p, 2)}


def battery_report(path, firmware_dir):
    """Both thrust columns of a battery flight: the one the file carries and the other one
    worked out by the firmware's own compensation (`thrust_compensation`), each fitted
    thrust = a + b·V and as a power of V. A plotter export carries one of the two."""
    header, rows = read_csv(path, "\t")
    col = {h: i for i, h in enumerate(header)}
    thrust_col = next(h for h in header if h.endswith(":thrust"))
    t = np.array([float(x[col["Time"]]) for x in rows])
    thr = np.array([float(x[col[thrust_col]]) for x in rows])
    dv = np.array([float(x[col["ROTORCRAFT_STATUS:vsupply"]]) for x in rows])
    v = dv / 10.0
    z = np.array([float(x[col["FINKEN_SENSOR_MODEL:pos_z"]]) for x in rows])
    a, b = longest_run(z > 0.35, t)
    k = (t >= t[a] + 10) & (t <= t[b] - 5)
    first, last = k & (t < t[a] + 20), k & (t > t[b] - 15)
    ac_id = int(re.search(r"_ac(\d+)", path.name).group(1)) if re.search(r"_ac(\d+)", path.name) else 5
    out = {"file": path.name, "thrust_column": thrust_col, "rate_hz": r(1 / np.median(np.diff(t)), 1),
           "takeoff": r(t[a], 1), "landing": r(t[b], 1), "duration_s": r(t[b] - t[a], 1),
           "fit_window": [r(t[a] + 10, 1), r(t[b] - 5, 1)],
           "V_start_loaded": r(np.median(v[first]), 2), "V_end_loaded": r(np.median(v[last]), 2),
           "V_rest_before": r(np.median(v[(t < t[a]) & (t > t[a] - 20)]), 2),
           "V_rest_after": r(np.median(v[t > t[b] + 2]), 2) if (t > t[b] + 2).any() else None,
           "height_m": describe(z[k], 3)}
    comp = thrust_compensation(firmware_dir, ac_id)
    columns = {thrust_col.split(":")[0]: thr}
    if comp is not None:
        low, default = comp
        shift = (low - default) * (84 - dv) / (84 - 65)
        if thrust_col.startswith("FINKEN_ACTUATORS_SET_POINT"):
            columns["FINKEN_ACTUATORS_MODEL"] = np.clip(thr + shift, 0.2, 1.0)
        else:
            # Only where the compensated value was not clamped can the set point be recovered.
            # (The set point is what the flight plans fly: `throttle=finken_actuators_set_point.thrust`.)
            columns["FINKEN_ACTUATORS_SET_POINT"] = np.where((thr > 0.2) & (thr < 1.0), thr - shift, np.nan)
        out["compensation"] = {"ac_id": ac_id, "THRUST_LOW": low, "THRUST_DEFAULT": default,
                               "model_minus_set_point_at_12V": r((low - default) * (84 - 120) / 19, 4)}
    for name, values in columns.items():
        ok = ~np.isnan(values)
        fit = battery_fit(t[ok], v[ok], values[ok], *np.searchsorted(t[ok], [t[a], t[b]]).clip(0, ok.sum() - 1))
        out[name] = dict(fit, logged=name == thrust_col.split(":")[0])
    return out


# --------------------------------------------------------------------------- 6 sonar noise

def stable_runs(t, x, tol=5.0, min_len=4.0):
    """Plateaus of one sonar: greedy runs in which every valid reading stays within `tol` cm of
    the run's running median, a single deviating sample being kept as an outlier (two in a row
    end the run), without telemetry gaps over 1 s; runs of at least `min_len` s are kept."""
    runs, i, n = [], 0, len(x)
    while i < n:
        j, members, outliers, misses = i, [i], [], 0
        while j + 1 < n and t[j + 1] - t[j] < 1.0:
            med = np.median(x[members])
            if abs(x[j + 1] - med) <= tol:
                members.append(j + 1)
                misses = 0
            else:
                misses += 1
                if misses == 2:
                    outliers = outliers[:-1]
                    j -= 1
                    break
                outliers.append(j + 1)
            j += 1
        if t[members[-1]] - t[members[0]] >= min_len:
            runs.append((members, outliers))
        i = max(j + 1, i + 1)
    return runs


def sonar_rest_noise(fsm, trim=1.0):
    """Within-plateau scatter of each sonar while the copter is held still (motors off); the
    first and last second of each plateau (the hand settling) are left out."""
    out = {}
    for name in SONARS:
        t, x = fsm.t, fsm[name]
        valid = (x >= SONAR_VALID[0]) & (x < SONAR_VALID[1])
        runs = stable_runs(t[valid], x[valid])
        num = den = n_out = n_all = 0
        stds, dur = [], 0.0
        for members, outliers in runs:
            tt, v = t[valid][members], x[valid][members]
            keep = (tt >= tt[0] + trim) & (tt <= tt[-1] - trim)
            tt, v = tt[keep], v[keep]
            if len(v) < 5:
                continue
            stds.append(v.std(ddof=1))
            num, den = num + (len(v) - 1) * v.var(ddof=1), den + len(v) - 1
            n_out, n_all = n_out + len(outliers), n_all + len(members) + len(outliers)
            dur += tt[-1] - tt[0]
        out[name] = {"plateaus": len(stds), "plateau_s": r(dur, 1),
                     "pooled_std_cm": r(math.sqrt(num / den), 2) if den else None,
                     "median_plateau_std_cm": r(np.median(stds), 2) if stds else None,
                     "outlier_share": r(n_out / n_all, 4) if n_all else None}
    return out


def sonar_flight_noise(fsm, window):
    """In-flight scatter per sonar. Telemetry (~35 Hz) repeats a value until the sonar updates,
    so repeats are dropped first; then the std of the first difference / sqrt(2) (robust: MAD)
    and the residual from a 5-sample moving median (std after dropping |r| > 20 cm, and MAD)."""
    k = (fsm.t >= window[0]) & (fsm.t <= window[1])
    out = {}
    for name in SONARS:
        x = fsm[name][k]
        x = x[(x >= SONAR_VALID[0]) & (x < SONAR_VALID[1])]
        if len(x) < 20:
            continue
        repeat = np.mean(np.diff(x) == 0)
        u = x[np.concatenate([[True], np.diff(x) != 0])]
        d = np.diff(u)
        res = u - moving_median(u, 5)
        big = np.abs(res) > 20
        out[name] = {"n": int(len(x)), "updates": int(len(u)), "repeat_share": r(repeat, 3),
                     "diff_std_over_sqrt2_cm": r(d.std() / math.sqrt(2), 2),
                     "diff_mad_over_sqrt2_cm": r(1.4826 * np.median(np.abs(d)) / math.sqrt(2), 2),
                     "movmed5_resid_std_cm": r(res[~big].std(), 2),
                     "movmed5_resid_mad_cm": r(1.4826 * np.median(np.abs(res)), 2),
                     "jumps_over_20cm_share": r(big.mean(), 3)}
    return out


# --------------------------------------------------------------------------- 7 arena

def arena_sums(log, flights):
    fsm = log["msgs"]["FINKEN_SENSOR_MODEL"]
    k = in_windows(fsm.t, [tuple(f["steady"]) for f in flights if f["steady"]])
    for name in SONARS:
        k &= (fsm[name] >= SONAR_VALID[0]) & (fsm[name] < SONAR_VALID[1])
    fb = fsm["distance_d_front"][k] + fsm["distance_d_back"][k]
    lr = fsm["distance_d_left"][k] + fsm["distance_d_rigth"][k]
    yaw = np.degrees(fsm["pos_yaw"][k]) % 360
    return fb, lr, yaw


def plateau_estimate(x, bin_cm=2):
    """Mode of the distribution (2 cm bins) and the median of the samples within 10 cm of it."""
    hist, edges = np.histogram(x, bins=np.arange(x.min(), x.max() + bin_cm, bin_cm))
    mode = edges[np.argmax(hist)] + bin_cm / 2
    near = x[np.abs(x - mode) <= 10]
    return float(mode), float(np.median(near)), float(len(near) / len(x))


def arena_report(log, flights):
    fb, lr, yaw = arena_sums(log, flights)
    out = {"n": int(len(fb))}
    for label, x in (("front_plus_back_cm", fb), ("left_plus_right_cm", lr)):
        mode, med, share = plateau_estimate(x)
        out[label] = {"percentiles_5_25_50_75_95": [r(v, 1) for v in np.percentile(x, [5, 25, 50, 75, 95])],
                      "mode": r(mode, 1), "plateau_median": r(med, 1), "plateau_share": r(share, 3)}
    fbm, lrm = out["front_plus_back_cm"]["plateau_median"], out["left_plus_right_cm"]["plateau_median"]
    out["size_m_with_face_separation"] = {"separation_m": SONAR_FACE_SEPARATION,
                                          "front_back_axis": r(fbm / 100 + SONAR_FACE_SEPARATION, 2),
                                          "left_right_axis": r(lrm / 100 + SONAR_FACE_SEPARATION, 2)}
    out["separation_if_4x3_m"] = {"front_back": r(4.0 - fbm / 100, 2), "left_right": r(3.0 - lrm / 100, 2)}
    bins = {}
    for a in range(0, 360, 10):
        s = (yaw >= a) & (yaw < a + 10)
        if s.sum() >= 50:
            bins[a] = {"n": int(s.sum()), "fb_median": r(np.median(fb[s]), 1), "lr_median": r(np.median(lr[s]), 1)}
    out["by_yaw_deg"] = bins
    out["yaw_percentiles_5_50_95_deg"] = [r(v, 1) for v in np.percentile(yaw, [5, 50, 95])]
    return out


def position_from_sonars(fsm, k):
    """Copter centre relative to the arena centre from the medians over samples k, assuming
    the copter square to the walls: X toward the wall the front sonar faces = (back - front)/2,
    Y toward the wall the right sonar faces = (left - right)/2 (independent of arena size and
    of the sonar face separation)."""
    d = {n: float(np.median(fsm[n][k])) for n in SONARS}
    return {"front": d["distance_d_front"], "back": d["distance_d_back"], "left": d["distance_d_left"],
            "right": d["distance_d_rigth"], "yaw_deg": r(np.degrees(np.median(fsm["pos_yaw"][k])) % 360, 1),
            "X_m": r((d["distance_d_back"] - d["distance_d_front"]) / 200, 2),
            "Y_m": r((d["distance_d_left"] - d["distance_d_rigth"]) / 200, 2)}


def start_positions(log, flights):
    """Per flight: from the first 0.5 s above ground + 0.15 m, and on the ground (3 s before
    the motors start)."""
    fsm = log["msgs"]["FINKEN_SENSOR_MODEL"]
    out = []
    for f in flights:
        if not f["takeoff"]:
            continue
        up = (fsm.t >= f["takeoff"]) & (fsm.t <= f["landing"]) & (fsm["pos_z"] > f["ground_ir_m"] + 0.15)
        if not up.any():
            continue
        t0 = fsm.t[up][0]
        ground = (fsm.t < f["motors_on"]) & (fsm.t > f["motors_on"] - 3)
        out.append(dict(position_from_sonars(fsm, up & (fsm.t <= t0 + 0.5)), flight=f["n"], t=r(t0, 2),
                        on_ground=position_from_sonars(fsm, ground) if ground.sum() > 3 else None))
    return out


def pooled(log, flights):
    """All flights of one log together: IR height and AHRS body angles in the settled windows,
    and IR height from take-off + 5 s to landing - 1 s."""
    fsm, ahrs = log["msgs"]["FINKEN_SENSOR_MODEL"], log["msgs"].get("AHRS_EULER_INT")
    settled = [tuple(f["steady"]) for f in flights if f["steady"]]
    air = [(f["takeoff"] + STEADY_AFTER_TAKEOFF, f["landing"] - STEADY_BEFORE_LANDING)
           for f in flights if f["steady"]]
    out = {"flights": [f["n"] for f in flights if f["steady"]],
           "height_settled": describe(fsm["pos_z"][in_windows(fsm.t, settled)]),
           "height_airborne": describe(fsm["pos_z"][in_windows(fsm.t, air)])}
    if ahrs is not None:
        k = in_windows(ahrs.t, settled)
        out["ahrs_roll_deg"] = describe(ahrs["body_phi"][k] * ANGLE_INT_TO_DEG, 2)
        out["ahrs_pitch_deg"] = describe(ahrs["body_theta"][k] * ANGLE_INT_TO_DEG, 2)
    return out


def ground_sums(starts):
    """Front+back and left+right while standing still on the floor before each flight."""
    g = [s["on_ground"] for s in starts if s["on_ground"]]
    fb = np.array([x["front"] + x["back"] for x in g])
    lr = np.array([x["left"] + x["right"] for x in g])
    return {"front_plus_back_cm": fb.tolist(), "left_plus_right_cm": lr.tolist(),
            "yaw_deg": [x["yaw_deg"] for x in g]}


# --------------------------------------------------------------------------- 7 V-REP twin

def read_vrep(path):
    """Rows 'ms: a b c' or 'ms a b c', decimal commas allowed -> array [t_s, a, b, c]."""
    rows = []
    with open(path) as f:
        for line in f:
            line = line.replace(":", " ").replace(",", ".").split()
            if len(line) == 4:
                rows.append([float(v) for v in line])
    a = np.array(rows)
    a[:, 0] /= 1000.0
    return a


def smooth(x, n=5):
    return np.convolve(x, np.ones(n) / n, mode="same")


def twin_tilt_convention(pos, ori):
    """Which logged angle tilts the twin toward which V-REP axis: regress the twin's own
    horizontal acceleration on g*tan(angle) (5-sample smoothing, 3-40 s)."""
    t, dt = pos[:, 0], np.median(np.diff(pos[:, 0]))
    acc = [np.gradient(np.gradient(smooth(pos[:, i]), dt), dt) for i in (1, 2)]
    k = (t > 3) & (t < 40)
    out = {}
    for ai, axis in enumerate(("x", "y")):
        for ci in (1, 2):
            pred = G * np.tan(np.radians(smooth(ori[:, ci])))
            gain = np.polyfit(pred[k], acc[ai][k], 1)[0]
            out[f"a{axis}_vs_c{ci}"] = {"corr": r(np.corrcoef(pred[k], acc[ai][k])[0, 1], 3), "gain": r(gain, 3)}
    return out


def offset_scan(ori, ahrs, lo=815.0, hi=835.0, window=(5.0, 45.0)):
    """Log time of V-REP t = 0: per channel, the offset maximising corr(c1, -phi),
    corr(c2, -theta), corr(c3, psi - psi0); and the one maximising their sum."""
    ts = ori[:, 0]
    k = (ts >= window[0]) & (ts <= window[1])
    phi = ahrs["body_phi"] * ANGLE_INT_TO_DEG
    theta = ahrs["body_theta"] * ANGLE_INT_TO_DEG
    psi = np.degrees(np.unwrap(np.radians(ahrs["body_psi"] * ANGLE_INT_TO_DEG)))
    offsets = np.arange(lo, hi, 0.01)
    scores = np.zeros((len(offsets), 3))
    for i, t0 in enumerate(offsets):
        for j, (sign, real) in enumerate(((-1, phi), (-1, theta), (1, psi))):
            x = np.interp(ts[k] + t0, ahrs.t, real)
            scores[i, j] = sign * np.corrcoef(ori[k, j + 1], x)[0, 1]
    best = {name: {"offset_s": r(offsets[np.argmax(scores[:, j])], 2), "corr": r(scores[:, j].max(), 3)}
            for j, name in enumerate(("c1_vs_minus_phi", "c2_vs_minus_theta", "c3_vs_psi"))}
    i = np.argmax(scores.sum(axis=1))
    best["combined"] = {"offset_s": r(offsets[i], 2), "corrs": [r(v, 3) for v in scores[i]]}
    return best, scores


def channel_gains(ori, ahrs, clock, window=(11.0, 47.0)):
    """c_i = gain * real + offset with log time = a + b * t_vrep (yaw: change since V-REP
    t = 0), over the real copter's airborne part."""
    ts = ori[:, 0]
    k = (ts >= window[0]) & (ts <= window[1])
    tl = clock["log_t_at_vrep_0"] + clock["rate_log_per_vrep_s"] * ts
    psi = np.degrees(np.unwrap(ahrs["body_psi"] * ANGLE_INT_TO_DEG * math.pi / 180))
    chans = (("c1_from_phi", 1, ahrs["body_phi"] * ANGLE_INT_TO_DEG),
             ("c2_from_theta", 2, ahrs["body_theta"] * ANGLE_INT_TO_DEG),
             ("c3_from_psi_change", 3, psi - np.interp(tl[0], ahrs.t, psi)))
    out = {}
    for name, ci, real in chans:
        x = np.interp(tl[k], ahrs.t, real)
        gain, off = np.polyfit(x, ori[k, ci], 1)
        out[name] = {"gain": r(gain, 3), "offset_deg": r(off, 2), "corr": r(np.corrcoef(x, ori[k, ci])[0, 1], 3),
                     "resid_std_deg": r(np.std(ori[k, ci] - (gain * x + off)), 2)}
    return out


def clock_fit(ori, ahrs, centres=np.arange(14, 46, 2), half=4.0):
    """V-REP's simulated time does not run exactly at wall-clock rate: the offset is found in
    8 s windows (sum of the roll and pitch correlations, as in offset_scan) and fitted as
    log = a + b * t_vrep over the windows whose summed correlation exceeds 1."""
    ts, offsets = ori[:, 0], np.arange(824.0, 827.0, 0.01)
    pts = []
    for c in centres:
        k = (ts >= c - half) & (ts <= c + half)
        score = [-sum(np.corrcoef(ori[k, j], np.interp(ts[k] + t0, ahrs.t, ahrs[f]))[0, 1]
                      for j, f in ((1, "body_phi"), (2, "body_theta"))) for t0 in offsets]
        i = int(np.argmax(score))
        pts.append((float(c), float(offsets[i]), float(score[i])))
    pts = np.array(pts)
    good = pts[:, 2] > 1.0
    b, a = np.polyfit(pts[good, 0], pts[good, 1], 1)
    resid = pts[good, 1] - (a + b * pts[good, 0])
    return {"log_t_at_vrep_0": r(a, 2), "rate_log_per_vrep_s": r(1 + b, 4), "windows_used": int(good.sum()),
            "resid_std_s": r(resid.std(), 3), "resid_max_s": r(np.abs(resid).max(), 3),
            "local_centre_offset_corrsum": [[r(c, 0), r(t0, 2), r(sc, 2)] for c, t0, sc in pts]}


def tumble_offset(ori, ahrs, limit=30.0):
    """Offset from the crash at the end of the 16 Dec twin flight: first |roll| or |pitch|
    over 30 deg in V-REP's output and in AHRS_EULER_INT (after V-REP t = 30 s)."""
    tv = ori[:, 0]
    iv = np.where((tv > 30) & (np.maximum(np.abs(ori[:, 1]), np.abs(ori[:, 2])) > limit))[0]
    tilt = np.maximum(np.abs(ahrs["body_phi"]), np.abs(ahrs["body_theta"])) * ANGLE_INT_TO_DEG
    ir = np.where((ahrs.t > 850) & (tilt > limit))[0]
    if not len(iv) or not len(ir):
        return None
    return {"vrep_t": r(tv[iv[0]], 3), "log_t": r(ahrs.t[ir[0]], 3), "offset_s": r(ahrs.t[ir[0]] - tv[iv[0]], 2)}


def first_exit(pos, rect=VREP_ARENA):
    x0, x1, y0, y1 = rect
    out = (pos[:, 1] < x0) | (pos[:, 1] > x1) | (pos[:, 2] < y0) | (pos[:, 2] > y1)
    if not out.any():
        return None
    i = int(np.argmax(out))
    x, y = pos[i, 1], pos[i, 2]
    wall = ("x=%g" % x0 if x < x0 else "x=%g" % x1 if x > x1 else "y=%g" % y0 if y < y0 else "y=%g" % y1)
    return {"t_s": r(pos[i, 0], 2), "x": r(x, 3), "y": r(y, 3), "wall": wall,
            "outside_share": r(out[i:].mean(), 3)}


def to_arena(x, y, rect=VREP_ARENA):
    """V-REP x, y -> arena frame centred on the arena: X along x (4 m), Y along y (3 m)."""
    return x - (rect[0] + rect[1]) / 2, y - (rect[2] + rect[3]) / 2


def vrep_report(rep_dir, log, starts, flights):
    pos = read_vrep(rep_dir / "simulationPosition20151216140935.log")
    ori = read_vrep(rep_dir / "simulationOrientation20151216140935.log")
    bounds = read_vrep(rep_dir / "logExampleArenaBoundaries.log")
    ahrs = log["msgs"]["AHRS_EULER_INT"]
    best = offset_scan(ori, ahrs)[0]
    best["tumble_event"] = tumble_offset(ori, ahrs)
    clock = clock_fit(ori, ahrs)
    to_log = lambda tv: clock["log_t_at_vrep_0"] + clock["rate_log_per_vrep_s"] * tv
    to_vrep = lambda tl: (tl - clock["log_t_at_vrep_0"]) / clock["rate_log_per_vrep_s"]
    twin_flight = next(f for f in flights if f["motors_on"] <= to_log(pos[-1, 0]) and f["motors_off"] >= to_log(0))
    real = next(s for s in starts if s["flight"] == twin_flight["n"])
    out = {"rows": len(pos), "duration_s": r(pos[-1, 0], 2),
           "step_ms_median": r(1000 * np.median(np.diff(pos[:, 0])), 1),
           "orientation_deg_range": [r(ori[:, 1:].min(), 1), r(ori[:, 1:].max(), 1)],
           "arena_rect_vrep": VREP_ARENA, "start_vrep": [r(v, 3) for v in pos[0, 1:]],
           "start_arena_XY": [r(v, 3) for v in to_arena(pos[0, 1], pos[0, 2])], "real_start": real,
           "tilt_convention": twin_tilt_convention(pos, ori), "offsets": best, "clock_fit": clock,
           "vrep_span_in_log_time": [r(to_log(0), 2), r(to_log(pos[-1, 0]), 2)],
           "real_flight_in_vrep_time": {k: r(to_vrep(twin_flight[k]), 2)
                                        for k in ("motors_on", "takeoff", "landing", "motors_off")},
           "channel_gains": channel_gains(ori, ahrs, clock),
           "twin_height_m": describe(pos[(pos[:, 0] > 3) & (pos[:, 0] < 45), 3], 3),
           "end_vrep": [r(v, 3) for v in pos[-1, 1:]],
           "end_arena_XY": [r(v, 2) for v in to_arena(pos[-1, 1], pos[-1, 2])],
           "twin_first_exit": first_exit(pos), "boundaries_log_first_exit": first_exit(bounds),
           "boundaries_log_start": [r(v, 3) for v in bounds[0, 1:]], "boundaries_log_s": r(bounds[-1, 0], 2)}
    ex = out["twin_first_exit"]
    if ex:
        ex["log_time_s"] = r(to_log(ex["t_s"]), 2)
        ex["arena_XY"] = [r(v, 2) for v in to_arena(ex["x"], ex["y"])]
        out["real_copter_at_exit"] = real_position_at(log, to_log(ex["t_s"]))
    return out


def real_position_at(log, t):
    fsm = log["msgs"]["FINKEN_SENSOR_MODEL"]
    k = np.abs(fsm.t - t) <= 0.25
    d = {n: float(np.median(fsm[n][k])) for n in SONARS}
    return {"t": r(t, 2), "X_m": r((d["distance_d_back"] - d["distance_d_front"]) / 200, 2),
            "Y_m": r((d["distance_d_left"] - d["distance_d_rigth"]) / 200, 2),
            "z_m": r(np.median(fsm["pos_z"][k]), 3), "yaw_deg": r(np.degrees(np.median(fsm["pos_yaw"][k])) % 360, 1)}


# --------------------------------------------------------------------------- driver

def flight_logs(ff):
    stems = [ff / "report_2015-12-16" / "15_12_16__13_55_00"]
    for p in sorted((ff / "robust_multicopter_flight").rglob("*.data")):
        stems.append(p.with_suffix(""))
    return stems


def analyse_log(stem, ff):
    name = str(stem.relative_to(ff))
    if not stem.with_suffix(".log").exists():
        return name, {"skipped": "no .log beside the .data: field order unknown"}, None
    log = load_flight(stem)
    flights = segment_flights(log)
    out = {"aircraft": log["config"]["name"], "ac_id": log["ac_id"], "flights": flights,
           "autopilot_boots": autopilot_boots(log),
           "telemetry": telemetry_report(log, flights), "per_flight": {}}
    fsm = log["msgs"]["FINKEN_SENSOR_MODEL"]
    for f in flights:
        if f["steady"]:
            out["per_flight"][f["n"]] = dict(attitude_and_height(log, f),
                                             sonar_in_flight=sonar_flight_noise(fsm, f["steady"]))
    if "DISTANCES" in name and "OnFlight" not in name:
        out["sonar_at_rest"] = sonar_rest_noise(fsm)
    return name, out, log


def resolve_data_dir(arg):
    if arg:
        return pathlib.Path(arg)
    if "TWINSWARM_SHARED_DATA" in os.environ:
        return pathlib.Path(os.environ["TWINSWARM_SHARED_DATA"])
    return ROOT.parent / "shared" / "data"


def run(data_dir):
    ff = data_dir / "finken_flights"
    if not ff.is_dir():
        sys.exit(f"real_flights.py: no finken_flights/ under {data_dir} "
                 "(pass the shared data folder as the first argument or set TWINSWARM_SHARED_DATA)")
    report = {"data_dir": str(data_dir), "logs": {}, "battery": []}
    rep_log = None
    for stem in flight_logs(ff):
        res = analyse_log(stem, ff)
        report["logs"][res[0]] = res[1]
        if stem.name == "15_12_16__13_55_00":
            rep_log = res[2]
    firmware = data_dir.parent / "paparazzi" / "finken_firmware" / "flight_2015-12"
    for p in sorted((ff / "battery").glob("*.csv")):
        report["battery"].append(battery_report(p, firmware))
    rep = report["logs"]["report_2015-12-16/15_12_16__13_55_00"]
    starts = start_positions(rep_log, rep["flights"])
    report["pooled_2015_12_16"] = pooled(rep_log, rep["flights"])
    report["arena_2015_12_16"] = dict(arena_report(rep_log, rep["flights"]), on_ground=ground_sums(starts),
                                      start_positions=starts)
    report["vrep_twin"] = vrep_report(ff / "report_2015-12-16", rep_log, starts, rep["flights"])
    report["check_16dec_fsm"] = check_expected(rep)
    return report


def check_expected(rep):
    got = rep["telemetry"]["messages"]["FINKEN_SENSOR_MODEL"]["all"]
    return {k: {"expected": v, "got": got.get(k)} for k, v in CHECKS_16DEC_FSM.items()}


# --------------------------------------------------------------------------- printing

def fmt(d):
    return ", ".join(f"{k}={v}" for k, v in d.items() if not isinstance(v, (dict, list)))


def print_report(rep):
    for name, log in rep["logs"].items():
        print(f"\n=== {name}")
        if "skipped" in log:
            print("  skipped:", log["skipped"])
            continue
        print(f"  aircraft {log['aircraft']} (ac_id {log['ac_id']}); autopilot boots at {log['autopilot_boots']}")
        for f in log["flights"]:
            print("  flight", fmt(f), "steady", f["steady"])
        tel = log["telemetry"]
        print(f"  telemetry mode {tel['mode']} (DL_VALUE idx0: {tel['mode_by_DL_VALUE_index0']}, "
              f"message set: {tel['mode_by_message_set']}, jaccard {tel['message_set_jaccard']})")
        for m, s in tel["messages"].items():
            print(f"   {m}: period {s['configured_period_s']} s, n {s['count']}")
            for part in ("all", "motors_on"):
                if part in s:
                    print(f"     {part}: " + fmt(s[part]))
            if "hist_5ms_to_200" in s.get("all", {}):
                print("     5 ms histogram (all):", s["all"]["hist_5ms_to_200"], "+", s["all"]["hist_over_200"])
        print("  link:", fmt(tel["link"]))
        for n, pf in log["per_flight"].items():
            print_flight(n, pf)
        if "sonar_at_rest" in log:
            print("  sonar at rest:", json.dumps(log["sonar_at_rest"]))
    print("\n=== battery")
    for b in rep["battery"]:
        print("  " + fmt(b))
        for name in ("FINKEN_ACTUATORS_MODEL", "FINKEN_ACTUATORS_SET_POINT"):
            if name in b:
                print(f"    {name}{' (logged)' if b[name]['logged'] else ' (by the firmware compensation)'}: "
                      + fmt(b[name]))
    print("\n=== 2015-12-16 pooled over flights:", json.dumps(rep["pooled_2015_12_16"]))
    print("\n=== arena 2015-12-16")
    print(json.dumps(rep["arena_2015_12_16"], indent=1))
    print("\n=== V-REP twin")
    print(json.dumps(rep["vrep_twin"], indent=1))
    print("\n=== check 16 Dec FINKEN_SENSOR_MODEL inter-arrival:", json.dumps(rep["check_16dec_fsm"]))


def print_flight(n, pf):
    h = pf["height"]
    ha = pf["height_airborne"]
    print(f"  flight {n} steady {pf['steady']}: height mean {h.get('mean')} std {h.get('std')} "
          f"min {h.get('min')} max {h.get('max')} set point {h['setpoint_flight_plan']}; "
          f"airborne {ha['window']}: mean {ha.get('mean')} std {ha.get('std')} "
          f"min {ha.get('min')} max {ha.get('max')}; "
          f"WA idle/active/guard {pf['wall_avoid_share_idle_active_guard']}; on-ground attitude {pf['on_ground_deg']}")
    for src in ("ahrs_body", "fsm"):
        if src in pf:
            for part, s in pf[src].items():
                print(f"    {src} {part}: n {s['n']} roll {fmt(s['roll_deg'])} | pitch {fmt(s['pitch_deg'])}")
    for sname, s in pf["sonar_in_flight"].items():
        print(f"    sonar {sname}: " + fmt(s))


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("data_dir", nargs="?", help="shared data folder (holds finken_flights/)")
    ap.add_argument("--json", help="also write all figures to this JSON file")
    args = ap.parse_args()
    report = run(resolve_data_dir(args.data_dir))
    print_report(report)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(report, f, indent=1, default=lambda o: o.item() if hasattr(o, "item") else str(o))


if __name__ == "__main__":
    main()
