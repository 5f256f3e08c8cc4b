#!/usr/bin/env python3
"""Twin accuracy on the real path: two processes in real time, over Ivy or over Zenoh.

`twinswarm run` (mixed_lab, FINken_01's twin, a log) and a `twinswarm copter` stand-in for
aircraft 5 (Wall-Avoid at 0.3 m/s, the measured telemetry link plus a loss, `--track`) fly together for
MINUTES. Afterwards:
- the stand-in's trajectory is its `--track` CSV (its simulated time, paced in real time);
- the twin's is `/copters/state` in the simulator's MCAP log (read with the PyPI `mcap` reader,
  CRCs checked), by tick;
- the two clocks differ by a constant offset (each process starts its own), found from the
  `FINKEN_SENSOR_MODEL` texts the simulator logged: each carries the stand-in's position at
  the time it was sent, so the offset is the one that best matches them to the track.
The error is the horizontal distance between the twin at simulator time t and the stand-in
at t + offset, from 10 s on (after take-off). Prints median, p95 and max, and whether the twin
ever left the arena.

    .venv/bin/python scripts/twin-accuracy.py --transport ivy --minutes 3 [--bin target/release/twinswarm]
"""
import argparse
import bisect
import csv
import json
import os
import pathlib
import socket
import subprocess
import sys
import tempfile
import time

from mcap.reader import make_reader

ROOT = pathlib.Path(__file__).resolve().parents[1]
SCENE = ROOT / "assets/scenes/mixed_lab.toml"
PAIRING = ROOT / "assets/pairing/mixed_lab.xml"
HALF_X, HALF_Y = 2.0, 1.5


def free_port(kind):
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def read_track(path):
    t, x, y = [], [], []
    with open(path) as f:
        for row in csv.DictReader(f):
            t.append(float(row["t_s"]))
            x.append(float(row["x_m"]))
            y.append(float(row["y_m"]))
    return t, x, y


def interp(ts, vs, t):
    i = bisect.bisect_left(ts, t)
    if i <= 0 or i >= len(ts):
        return None
    a = (t - ts[i - 1]) / (ts[i] - ts[i - 1])
    return vs[i - 1] + a * (vs[i] - vs[i - 1])


def read_log(path, dt_s=0.05):
    """The twin's positions by tick, and the (time, x, y) of the stand-in's FINKEN_SENSOR_MODEL
    texts, from the log (protobuf through PyPI mcap-protobuf-support, CRCs checked)."""
    from google.protobuf import json_format
    from mcap_protobuf.decoder import DecoderFactory

    twin, fsm, decoders, factory = {}, [], {}, DecoderFactory()
    with open(path, "rb") as f:
        for schema, channel, msg in make_reader(f, validate_crcs=True).iter_messages(
                topics=["/copters/state", "/pprz/5/FINKEN_SENSOR_MODEL/decoded"]):
            if schema.id not in decoders:
                decoders[schema.id] = factory.decoder_for(channel.message_encoding, schema)
            body = json_format.MessageToDict(decoders[schema.id](msg.data), preserving_proto_field_name=True)
            if channel.topic == "/copters/state":
                if body.get("copter") == "finken_01":
                    twin[int(body["tick"])] = body["pos_m"]
            else:
                fields = body["fields"]
                fsm.append((int(body["tick"]) * dt_s, fields["pos_x"], fields["pos_y"]))
    return twin, fsm


def percentile(v, p):
    v = sorted(v)
    return v[min(len(v) - 1, int(round(p * (len(v) - 1))))]


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--transport", choices=["ivy", "zenoh"], required=True)
    ap.add_argument("--minutes", type=float, default=3.0)
    ap.add_argument("--bin", default=str(ROOT / "target/release/twinswarm"))
    ap.add_argument("--jitter-ms", default=None,
                    help="a uniform telemetry link with this jitter instead of the measured one")
    ap.add_argument("--loss", default="0.05")
    a = ap.parse_args()
    secs = a.minutes * 60
    tmp = pathlib.Path(tempfile.mkdtemp(prefix="twin-accuracy-"))
    log, track = tmp / "run.mcap", tmp / "track.csv"
    if a.transport == "ivy":
        bus = f"127.255.255.255:{free_port(socket.SOCK_DGRAM)}"
        sim_net, copter_net = ["--no-bus", "--ivy", bus], ["--ivy", bus]
    else:
        ep = f"tcp/127.0.0.1:{free_port(socket.SOCK_STREAM)}"
        prefix = f"accuracy-{os.getpid()}/mixed_lab"
        sim_net, copter_net = ["--listen", ep, "--prefix", prefix], ["--connect", ep, "--prefix", prefix]
    sim = subprocess.Popen([a.bin, "run", str(SCENE), "--pairing", str(PAIRING), "--realtime",
                            "--duration", str(secs + 5), "--twin-attitude", "measured", "--json",
                            "--log", str(log), *sim_net], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    time.sleep(1.0)
    copter = subprocess.run([a.bin, "copter", str(SCENE), "--pairing", str(PAIRING), "--ac-id", "5",
                             "--velocity", "0.3,0", "--duration", str(secs),
                             *(["--jitter-ms", a.jitter_ms] if a.jitter_ms else []),
                             "--loss", a.loss, "--json", "--track", str(track), *copter_net],
                            capture_output=True, text=True, timeout=secs + 120)
    out, err = sim.communicate(timeout=120)
    if sim.returncode != 0 or copter.returncode != 0:
        sys.exit(f"run failed: sim {sim.returncode} {err[-2000:]}\ncopter {copter.returncode} {copter.stderr[-2000:]}")
    tt, tx, ty = read_track(track)
    twin, fsm = read_log(log)
    # The clock offset: the one that best fits the logged FINKEN_SENSOR_MODEL positions to the
    # track (coarse grid, then fine).
    def cost(off):
        e = [((interp(tt, tx, t + off) or 0) - x) ** 2 + ((interp(tt, ty, t + off) or 0) - y) ** 2
             for t, x, y in fsm[50::5] if interp(tt, tx, t + off) is not None]
        return sum(e) / max(1, len(e))
    best = min((cost(o / 10), o / 10) for o in range(-100, 101))[1]
    best = min((cost(best + o / 1000), best + o / 1000) for o in range(-100, 101))[1]
    errors, outside = [], 0
    for tick, (x, y, _z) in sorted(twin.items()):
        t = tick * 0.05
        if t < 10:
            continue
        sx, sy = interp(tt, tx, t + best), interp(tt, ty, t + best)
        if sx is None:
            continue
        errors.append(((x - sx) ** 2 + (y - sy) ** 2) ** 0.5)
        outside += int(abs(x) > HALF_X or abs(y) > HALF_Y)
    summary = json.loads(out)
    lat = summary["twins"]["finken_01"]["input_latency_ms"]
    link = f"uniform {a.jitter_ms} ms jitter" if a.jitter_ms else "the measured link"
    print(f"transport {a.transport}, {a.minutes} min, {link}, loss {a.loss}: "
          f"{len(errors)} samples, clock offset {best:.3f} s")
    print(f"  twin vs stand-in horizontal error: median {100 * percentile(errors, 0.5):.1f} cm, "
          f"p95 {100 * percentile(errors, 0.95):.1f} cm, max {100 * max(errors):.1f} cm; "
          f"twin outside the arena in {outside} steps")
    print(f"  telemetry to twin input: p50 {lat['p50']:.1f} ms, p99 {lat['p99']:.1f} ms (n {lat['n']}); "
          f"crashes {len(summary['crashes'])}")
    print(f"  stand-in: {json.loads(copter.stdout)['telemetry_sent']} telemetry sent, "
          f"{json.loads(copter.stdout)['virtual_sonar_received']} virtual sonar received")


if __name__ == "__main__":
    main()
