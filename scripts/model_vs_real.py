#!/usr/bin/env python3
"""Twinswarm's model beside the real FINken: the simulator's side of the table in
docs/accuracy.md ("Held against the real FINken"). The real side is scripts/real_flights.py.

Flies, with the `twinswarm` binary given (default target/release/twinswarm, else
target/debug/twinswarm):

- **lab**: the 16 Dec 2015 flight's set-up: one FINken in Wall-Avoid holding 0.6 m in the lab's
  4 m x 3 m arena, starting where the real copter started (0.06, -0.44), 120 s, its pack charged
  as that day's was (`ROTORCRAFT_STATUS.vsupply` 11.5-11.8 V in flight 1; charge 0.8 gives
  11.7 V under load);
- **hover**: the same copter in an 8 m x 8 m arena, where every wall is beyond Wall-Avoid's
  1.2 m, so it hovers, 120 s;
- **battery**: the hover copter for 9 minutes, as the battery flights of Feb 2016 flew (its
  pack's voltage).

With `--scene FILE` it flies that scene instead (e.g. the embedded lab scene,
assets/scenes/finken_lab.toml) and gives each copter's IR height from its take-off + 5 s.

It reads each run's MCAP log (PyPI mcap with CRCs on, the file's own protobuf schemas):
roll and pitch of the AHRS estimate (standard deviation, mean), the IR height around the set
point, the battery's voltage, and the sonars' noise (the residual from a 5-sample moving median, as for the real logs, and the
first difference / sqrt 2), all from 5 s after take-off on.

    .venv/bin/python scripts/model_vs_real.py [--bin PATH] [--json FILE] [--airframe NAME] [--only RUNS]
    .venv/bin/python scripts/model_vs_real.py --scene assets/scenes/finken_lab.toml

Needs the test venv (mcap, mcap-protobuf-support, numpy): `scripts/test.sh` makes it.
"""

import argparse
import json
import pathlib
import statistics
import subprocess
import sys
import tempfile

import numpy as np
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory

ROOT = pathlib.Path(__file__).resolve().parent.parent
SETTLE_S = 5.0

# Arena, start, duration, the pack's initial charge.
SCENES = {
    "lab": ([4.0, 3.0], [0.06, -0.44], 120.0, 0.8),
    "hover": ([8.0, 8.0], [0.0, 0.0], 120.0, 1.0),
    "battery": ([8.0, 8.0], [0.0, 0.0], 540.0, 1.0),
}


EXTRA = ""
AIRFRAME = "finken3_2015_12"


def scene_toml(name, size, start, duration, charge):
    # The preset with the set-up's pack (a scene's airframe table starts from finken3).
    firmware = "finken_height = {}\n" if AIRFRAME == "finken3_2015_12" else ""
    if AIRFRAME not in ("finken3", "finken3_2015_12"):
        sys.exit(f"model_vs_real.py: --airframe must be finken3 or finken3_2015_12, got {AIRFRAME!r}")
    return f"""name = "{name}"
[sim]
seed = 2015
duration_s = {duration}
[arena]
size_m = [{size[0]}, {size[1]}]
height_m = 2.5
[airframes.under_test]
{firmware}battery = {{ initial_charge = {charge} }}
[[copter]]
name = "finken"
kind = "virtual"
ac_id = 5
airframe = "under_test"
start = {{ pos_m = [{start[0]}, {start[1]}], yaw_deg = 0.0 }}
mode = "wall_avoid"
command = {{ height_m = 0.6 }}
""" + EXTRA


def fly(binary, name, tmp):
    size, start, duration, charge = SCENES[name]
    scene = tmp / f"{name}.toml"
    scene.write_text(scene_toml(name, size, start, duration, charge))
    log = tmp / f"{name}.mcap"
    subprocess.run([str(binary), "run", str(scene), "--no-bus", "--log", str(log)], check=True,
                   stdout=subprocess.DEVNULL)
    return log


def messages(path, topics):
    factory, decoders, out = DecoderFactory(), {}, {t: [] for t in topics}
    with open(path, "rb") as f:
        for schema, channel, message in make_reader(f, validate_crcs=True).iter_messages(topics=topics):
            if schema.id not in decoders:
                decoders[schema.id] = factory.decoder_for(channel.message_encoding, schema)
            out[channel.topic].append(decoders[schema.id](message.data))
    return out


def took_off(states):
    for s in states:
        if s.took_off:
            return s.t_s
    return None


def moving_median_residual(x, k=5):
    x = np.asarray(x)
    if len(x) < k:
        return np.array([])
    med = np.array([np.median(x[i:i + k]) for i in range(len(x) - k + 1)])
    return x[k // 2:len(x) - k // 2] - med


def sonar_noise(sensors):
    """Per sonar: residual std from a 5-sample moving median and first difference / sqrt 2, cm,
    over its distinct readings (the log holds a reading until the next; repeats are dropped, as
    for the real logs)."""
    out = []
    for k in range(4):
        fresh = []
        for s in sensors:
            if len(s.sonar_m) == 4 and np.isfinite(s.sonar_m[k]) and (not fresh or s.sonar_m[k] != fresh[-1]):
                fresh.append(s.sonar_m[k])
        r = moving_median_residual(fresh)
        r = r[np.abs(r) < 0.2]
        d = np.diff(fresh)
        # As the firmware logs them: the mean of the last 5 readings.
        logged = np.convolve(fresh, np.ones(5) / 5, mode="valid") if len(fresh) >= 5 else np.array([])
        rl = moving_median_residual(logged)
        rl = rl[np.abs(rl) < 0.2]
        out.append({"residual_cm": round(float(np.std(r)) * 100, 2) if len(r) else None,
                    "diff_cm": round(float(np.std(d)) / np.sqrt(2) * 100, 2) if len(d) else None,
                    "logged_residual_cm": round(float(np.std(rl)) * 100, 2) if len(rl) else None,
                    "readings": len(fresh)})
    return out


def attitude_and_height(log):
    m = messages(log, ["/copters/state", "/copters/sensors", "/copters/control"])
    t0 = took_off(m["/copters/state"])
    settled = [s for s in m["/copters/sensors"] if t0 is not None and s.t_s >= t0 + SETTLE_S]
    roll = np.degrees([s.attitude_rad[0] for s in settled])
    pitch = np.degrees([s.attitude_rad[1] for s in settled])
    ir = np.array([s.ir_m for s in settled if s.HasField("ir_m")])
    return m, t0, {
        "take_off_s": t0,
        "roll_deg": {"mean": round(float(roll.mean()), 2), "std": round(float(roll.std()), 2)},
        "pitch_deg": {"mean": round(float(pitch.mean()), 2), "std": round(float(pitch.std()), 2)},
        "ir_height_m": {"set_point": 0.6, "mean": round(float(ir.mean()), 3), "std": round(float(ir.std()), 3),
                        "min": round(float(ir.min()), 3), "max": round(float(ir.max()), 3)},
        "sonar_noise": sonar_noise(settled),
    }


def scene_heights(binary, scene, tmp):
    """Each copter's IR height from its take-off + 5 s to the end (or its crash), as for the
    real flights: mean, standard deviation, range, and the 5 s means' range."""
    log = tmp / "scene.mcap"
    subprocess.run([str(binary), "run", str(scene), "--no-bus", "--log", str(log)], check=True,
                   stdout=subprocess.DEVNULL)
    m = messages(log, ["/copters/state", "/copters/sensors"])
    out = {}
    for name in sorted({s.copter for s in m["/copters/state"]}):
        states = [s for s in m["/copters/state"] if s.copter == name]
        t0 = took_off(states)
        if t0 is None:
            out[name] = {"take_off_s": None}
            continue
        sensors = [s for s in m["/copters/sensors"] if s.copter == name and s.t_s >= t0 + SETTLE_S]
        t_ir = np.array([(s.t_s, s.ir_m) for s in sensors if s.HasField("ir_m")])
        ir = t_ir[:, 1]
        bins = [ir[(t_ir[:, 0] >= lo) & (t_ir[:, 0] < lo + 5)] for lo in np.arange(t_ir[0, 0], t_ir[-1, 0], 5)]
        means = [b.mean() for b in bins if len(b)]
        out[name] = {"take_off_s": round(t0, 2), "mean": round(float(ir.mean()), 3), "std": round(float(ir.std()), 3),
                     "min": round(float(ir.min()), 3), "max": round(float(ir.max()), 3),
                     "five_s_means": [round(float(min(means)), 3), round(float(max(means)), 3)]}
    return out


def battery(log):
    """The pack's voltage from take-off to the end (the height loop's thrust adaptation absorbs
    the sag; `cargo test -p sim-core --test fidelity` gives the thrust at the same command)."""
    m = messages(log, ["/copters/state", "/copters/sensors"])
    t0 = took_off(m["/copters/state"])
    s = [x for x in m["/copters/sensors"] if x.t_s >= t0 + 10]
    first = [x.battery_v for x in s[:200]]
    last = [x.battery_v for x in s[-200:]]
    return {"v_start": round(statistics.mean(first), 2), "v_end": round(statistics.mean(last), 2),
            "charge_end": round(s[-1].battery_charge, 3), "minutes": round((s[-1].t_s - s[0].t_s) / 60, 1)}


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--bin", type=pathlib.Path)
    ap.add_argument("--json", type=pathlib.Path)
    ap.add_argument("--scene-extra", default="", help="TOML tables added to every scene (to try a setting)")
    ap.add_argument("--airframe", default="finken3_2015_12",
                    help="the copter's airframe: finken3_2015_12 (the lab firmware's height loop, the default) or "
                         "finken3 (Twinswarm's newton loop)")
    ap.add_argument("--only", default="lab,hover,battery", help="comma-separated runs (default all three)")
    ap.add_argument("--scene", type=pathlib.Path, help="fly this scene file instead; per-copter IR heights")
    args = ap.parse_args()
    global EXTRA, AIRFRAME
    EXTRA = args.scene_extra.replace("\\n", "\n")
    AIRFRAME = args.airframe
    only = set(args.only.split(","))
    binary = args.bin or next((p for p in [ROOT / "target/release/twinswarm", ROOT / "target/debug/twinswarm"]
                               if p.exists()), None)
    if binary is None or not binary.exists():
        sys.exit("model_vs_real.py: no twinswarm binary (build it, or pass --bin)")
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True,
                            text=True).stdout.strip()
    out = {"commit": commit, "binary": str(binary), "airframe": AIRFRAME}
    with tempfile.TemporaryDirectory() as d:
        tmp = pathlib.Path(d)
        if args.scene:
            out = {"commit": commit, "binary": str(binary), "scene": str(args.scene),
                   "heights": scene_heights(binary, args.scene, tmp)}
            only = set()
        for name in ("lab", "hover"):
            if name in only:
                _m, _t0, figs = attitude_and_height(fly(binary, name, tmp))
                out[name] = figs
        if "battery" in only:
            out["battery"] = battery(fly(binary, "battery", tmp))
    print(json.dumps(out, indent=2))
    if args.json:
        args.json.write_text(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
