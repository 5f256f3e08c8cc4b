#!/usr/bin/env python3
"""The NPS FINken on the lab's own 2015-12 firmware beside the real FINken: the third data
column of docs/accuracy.md's table ("Held against the real FINken"). The real column is
scripts/real_flights.py, Twinswarm's own copter scripts/model_vs_real.py.

Flies, through scripts/nps_swarm.py, one NPS FINken on the firmware of 16 Dec 2015
(`--firmware 2015-12 --plan wall_avoid`: finken_wall_avoid, set point 0.6 m) in the paper's
4 m x 3 m arena for 60 s, untrimmed and trimmed by flying (`--trim-flights 2`), with
FINKEN_FW_DEBUG=10: every 10 ms the NPS process prints the firmware's own state, i.e. what the
real copter's telemetry logged: `finken_sensor_model.pos.z` (FINKEN_SENSOR_MODEL pos_z, its IR
height), `distance_d_*` (its sonars after its own 5-reading mean) and the AHRS's body roll and
pitch (AHRS_EULER_INT). The print does not change the flight (the same digest with and without).
Reads the run's MCAP log with model_vs_real.py's reader (take-off, crash, the world's truth)
and computes the figures with real_flights.py's own functions and windows:

- take-off: the world's `took_off` (as model_vs_real.py; the real one, IR 8 cm above its floor
  reading, cannot be used: the simulated IR reads nothing below 0.20 m and the firmware then
  holds 1.30 m); the flight's end: the wall hit if it hit one, else the end of the run; the
  real logs' "landing" is that end;
- height from take-off + 5 s to the end - 1 s, and in the settled window (real_flights.
  steady_window: from take-off + 5 s once the smoothed height is within 5 cm of the flight's
  steady height, to the end - 1 s): mean, sd, range of pos_z (real_flights.describe);
- roll, pitch standard deviation of the AHRS estimate in the settled window (the real pooled
  figure's window), and the world's true attitude beside it;
- sonar noise in flight (real_flights.sonar_flight_noise: repeats dropped, residual from a
  5-sample moving median, |r| > 20 cm counted as jumps), per direction, settled window;
- Wall-Avoid's state shares (idle / active / guard, real_flights.wall_avoid_state), and the
  attitude split by them (real_flights.angle_stats; the real "hover" figure is Wall-Avoid idle).

    .venv/bin/python scripts/nps_vs_real.py [--twinswarm PATH] [--trim-flights 0,2] [--arena 4x3] [--json FILE]

Needs what nps_swarm.py needs (the Paparazzi tree at target/paparazzi, a twinswarm binary:
default target/release/twinswarm) and the test venv (mcap, mcap-protobuf-support, numpy). With
the shared data folder (../shared/data or $TWINSWARM_SHARED_DATA) it prints the real 16 Dec
2015 figures beside.
"""

import argparse
import json
import os
import pathlib
import re
import subprocess
import sys
import tempfile

import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
import model_vs_real  # noqa: E402  (the MCAP reader, take-off)
import nps_swarm  # noqa: E402
import real_flights as rf  # noqa: E402  (the real figures' definitions)

ROOT = pathlib.Path(__file__).resolve().parent.parent
# the debug print's sonar order is the firmware's struct's: front, right, back, left
FILT_ORDER = ("distance_d_front", "distance_d_rigth", "distance_d_back", "distance_d_left")
FW_LINE = re.compile(r"\[finken_fw\] t=\S+ sonar_cm=(\S+) filt_cm=(\S+) world_m=\S+ ir=\S+ \(world \S+\) z=(\S+) "
                     r"sp_z=(\S+) ctl=(\S+)")
ATT_LINE = re.compile(r"\[finken_fw_att\] t=(\S+) est_deg=(\S+) true_deg=(\S+)")


class Telemetry:
    """The firmware's state as the NPS process printed it, shaped like real_flights' messages
    (`.t`, `[field]`)."""

    def __init__(self, rows):
        a = np.array(rows, float).reshape(-1, 11)
        self.t = a[:, 0]
        self.cols = {"pos_z": a[:, 1], "sp_z": a[:, 2], "pos_roll": np.radians(a[:, 3]),
                     "pos_pitch": np.radians(a[:, 4]), "true_roll_deg": a[:, 5], "true_pitch_deg": a[:, 6]}
        for k, name in enumerate(FILT_ORDER):
            self.cols[name] = a[:, 7 + k]

    def __getitem__(self, name):
        return self.cols[name]


def read_nps_log(path):
    """Pairs each `[finken_fw]` line with the `[finken_fw_att]` line printed after it."""
    rows, fw = [], None
    for line in pathlib.Path(path).read_text(errors="replace").splitlines():
        m = FW_LINE.search(line)
        if m:
            fw = m
            continue
        m = ATT_LINE.search(line)
        if m and fw is not None:
            est = [float(v) for v in m.group(2).split(",")]
            true = [float(v) for v in m.group(3).split(",")]
            filt = [float(v) for v in fw.group(2).split(",")]
            rows.append([float(m.group(1)), float(fw.group(3)), float(fw.group(4)), est[0], est[1],
                         true[0], true[1], *filt])
            fw = None
    return Telemetry(rows)


def figures(out, ac):
    """The table's figures for one run of nps_swarm.py (its --out folder), aircraft ac."""
    fw = read_nps_log(out / f"nps{ac}.log")
    m = model_vs_real.messages(out / "run.mcap", ["/copters/state", "/copters/sensors"])
    states = m["/copters/state"]
    t0 = model_vs_real.took_off(states)
    crash = next((s for s in states if s.crashed), None)
    end = crash.t_s if crash else float(fw.t[-1])
    res = {"take_off_s": t0, "end_s": round(end, 3),
           "wall_hit_s": round(crash.t_s, 3) if crash else None,
           "crash_cause": crash.crash_cause if crash else None}
    if t0 is None:
        res["note"] = "never took off"
        return res
    res["airborne_s"] = round(end - t0, 2)
    air = (t0 + rf.STEADY_AFTER_TAKEOFF, end - rf.STEADY_BEFORE_LANDING)
    res["window_take_off_plus_5_s"] = [round(air[0], 3), round(air[1], 3)]
    if air[1] - air[0] < 2:
        res["note"] = (f"the flight ended {end - t0:.2f} s after take-off: no window from take-off + 5 s "
                       "to the end - 1 s; the figures below are from take-off to the end (not the real "
                       "logs' window)")
        steady = None
        whole = (t0, end)
    else:
        steady = rf.steady_window(fw, t0, end)
        whole = None
    res["steady_window"] = [round(steady[0], 3), round(steady[1], 3)] if steady else None
    k = rf.in_windows(fw.t, [air]) if whole is None else rf.in_windows(fw.t, [whole])
    res["height_take_off_plus_5_s" if whole is None else "height_take_off_to_end"] = rf.describe(fw["pos_z"][k])
    win = steady or whole or air
    ks = rf.in_windows(fw.t, [win])
    res["attitude_window"] = "steady" if steady else ("take-off to end" if whole else "take-off + 5 s")
    if steady:
        res["height_settled"] = rf.describe(fw["pos_z"][ks])
    res["ahrs_roll_deg"] = rf.describe(np.degrees(fw["pos_roll"][ks]), 2)
    res["ahrs_pitch_deg"] = rf.describe(np.degrees(fw["pos_pitch"][ks]), 2)
    res["true_roll_deg"] = rf.describe(fw["true_roll_deg"][ks], 2)
    res["true_pitch_deg"] = rf.describe(fw["true_pitch_deg"][ks], 2)
    wa = rf.wall_avoid_state(fw)
    res["wall_avoid_share_idle_active_guard"] = [rf.r(np.mean(wa[ks] == v), 3) for v in (0, 1, 2)]
    # split by Wall-Avoid's state, as the real figures are (idle: the real "hover" row)
    res["ahrs_by_wall_avoid_state"] = rf.angle_stats(fw.t, np.degrees(fw["pos_roll"]), np.degrees(fw["pos_pitch"]),
                                                     win, fw.t, wa)
    res["sonar_in_flight"] = rf.sonar_flight_noise(fw, win)
    # The world's side, as a check: its IR (what the firmware's ADC was given) and its raw sonar
    # readings (model_vs_real.sonar_noise: raw, and as a 5-reading mean would log them).
    sens = [s for s in m["/copters/sensors"] if win[0] <= s.t_s <= win[1]]
    res["world_ir_m"] = rf.describe([s.ir_m for s in sens if s.HasField("ir_m")])
    res["world_sonar_noise"] = model_vs_real.sonar_noise(sens)
    return res


def real_reference():
    """The real 16 Dec 2015 figures of the table, if the shared data folder is there."""
    try:
        rep = rf.run(rf.resolve_data_dir(None))
    except SystemExit:
        return None
    pooled = rep["pooled_2015_12_16"]
    per = rep["logs"]["report_2015-12-16/15_12_16__13_55_00"]["per_flight"].values()
    sonar = {n: rf.r(np.median([f["sonar_in_flight"][n]["movmed5_resid_std_cm"] for f in per]), 2)
             for n in rf.SONARS}
    return {"ahrs_roll_deg_sd": pooled["ahrs_roll_deg"]["std"], "ahrs_pitch_deg_sd": pooled["ahrs_pitch_deg"]["std"],
            "height_take_off_plus_5_s": pooled["height_airborne"], "height_settled": pooled["height_settled"],
            "sonar_movmed5_resid_std_cm_median_of_flights": sonar}


def fmt_height(d):
    return f"mean {d['mean']:.3f} m, sd {d['std'] * 100:.1f} cm, {d['min']:.3f}-{d['max']:.3f} m (n {d['n']})"


def print_run(label, r, arena):
    print(f"\n=== NPS FINken, 2015-12 firmware, Wall-Avoid, {arena.replace('x', ' m x ')} m, {label}")
    print(f"  take-off {r['take_off_s']} s; " + (f"hit a wall at {r['wall_hit_s']} s ({r['crash_cause']}), "
          f"{r.get('airborne_s')} s after take-off" if r["wall_hit_s"] else f"no wall hit, flew to {r['end_s']} s"))
    if "note" in r:
        print("  note:", r["note"])
    if r.get("take_off_s") is None:
        return
    if "height_take_off_plus_5_s" in r:
        where, h = f"take-off + 5 s {r['window_take_off_plus_5_s']}", r["height_take_off_plus_5_s"]
    else:
        where, h = "take-off to end", r["height_take_off_to_end"]
    print(f"  height around the 0.6 m set point, {where}: {fmt_height(h)}")
    if r.get("height_settled"):
        print(f"  height, settled {r['steady_window']}: {fmt_height(r['height_settled'])}")
    print(f"  roll, pitch standard deviation in Wall-Avoid ({r['attitude_window']}): AHRS roll "
          f"{r['ahrs_roll_deg']['std']}°, pitch {r['ahrs_pitch_deg']['std']}° (means {r['ahrs_roll_deg']['mean']}°, "
          f"{r['ahrs_pitch_deg']['mean']}°); true roll {r['true_roll_deg']['std']}°, pitch {r['true_pitch_deg']['std']}°")
    print(f"  Wall-Avoid idle / active / guard: {r['wall_avoid_share_idle_active_guard']}")
    for state, a in r["ahrs_by_wall_avoid_state"].items():
        if a["n"] and state != "all":
            print(f"    {state}: AHRS roll sd {a['roll_deg']['std']}°, pitch sd {a['pitch_deg']['std']}° (n {a['n']})")
    print("  sonar noise in flight (residual from a 5-sample moving median, of the readings as logged):")
    for name, s in r["sonar_in_flight"].items():
        print(f"    {name}: {s['movmed5_resid_std_cm']} cm, jumps > 20 cm {s['jumps_over_20cm_share']}, "
              f"updates {s['updates']}")
    print(f"  world's IR in the same window: {fmt_height(r['world_ir_m'])}")
    print("  world's raw sonar (residual, as a 5-mean logs it, cm): "
          + ", ".join(f"{s['residual_cm']}/{s['logged_residual_cm']}" for s in r["world_sonar_noise"])
          + " (front, right, back, left)")


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--twinswarm", help="the twinswarm binary (default: nps_swarm.py's, target/release/twinswarm)")
    ap.add_argument("--trim-flights", default="0,2", help="the runs: trim flights before each (default 0,2)")
    ap.add_argument("--first-ac", type=int, default=61)
    ap.add_argument("--seed", type=int, default=2016)
    ap.add_argument("--duration", type=float, default=60.0)
    ap.add_argument("--arena", default="4x3", help="floor XxY, m (default the paper's 4x3)")
    ap.add_argument("--out", type=pathlib.Path, help="keep each run here (default a temporary folder)")
    ap.add_argument("--json", type=pathlib.Path)
    args = ap.parse_args()
    os.environ["FINKEN_FW_DEBUG"] = "10"
    args.twinswarm = args.twinswarm or nps_swarm.default_twinswarm()
    base = args.out or pathlib.Path(tempfile.mkdtemp(prefix="nps_vs_real."))
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True,
                            text=True).stdout.strip()
    report = {"commit": commit, "arena": args.arena, "runs": {}}
    for n in [int(v) for v in args.trim_flights.split(",")]:
        label = "untrimmed" if n == 0 else f"trim_flights_{n}"
        argv = ["--firmware", "2015-12", "--plan", "wall_avoid", "--count", "1", "--arena", args.arena,
                "--duration", str(args.duration), "--first-ac", str(args.first_ac), "--seed", str(args.seed),
                "--out", str(base / label), "--quiet", "--trim-flights", str(n)]
        argv += ["--twinswarm", args.twinswarm]
        run = nps_swarm.main(argv)
        r = figures(base / label, args.first_ac)
        r.update({"digest": run["digests"], "imu_trim": run["imu_trim"], "min_wall_clearance_m":
                  run["min_wall_clearance_m"], "sim_s_per_wall_s": run["sim_s_per_wall_s"], "out": run["out"]})
        report["runs"][label] = r
        print_run(label, r, args.arena)
        print(f"  digest {run['digests']}, IMU trim {run['imu_trim']}, {run['sim_s_per_wall_s']} x real time, "
              f"min wall clearance {run['min_wall_clearance_m']} m")
    real = real_reference()
    report["real_16_dec_2015"] = real
    if real:
        print("\n=== the real FINken, 16 Dec 2015 (real_flights.py, pooled over its 6 settled flights)")
        print(f"  roll, pitch sd {real['ahrs_roll_deg_sd']}°, {real['ahrs_pitch_deg_sd']}°; height from take-off + 5 s: "
              f"{fmt_height(real['height_take_off_plus_5_s'])}; settled: {fmt_height(real['height_settled'])}")
        print("  sonar noise in flight (median of the flights), cm:", real["sonar_movmed5_resid_std_cm_median_of_flights"])
    if args.json:
        args.json.write_text(json.dumps(report, indent=2, default=str))


if __name__ == "__main__":
    main()
