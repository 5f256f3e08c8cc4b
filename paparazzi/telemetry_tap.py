#!/usr/bin/env python3
"""Print an NPS aircraft's telemetry (pprzlink v2 over UDP, as NPS sends it to `link`) as text.

    . target/paparazzi/env.sh
    python3 paparazzi/telemetry_tap.py [--port 4242] [--only ROTORCRAFT_FP,ROTORCRAFT_STATUS] [--seconds 30]

Uses Paparazzi's own pprzlink Python library and messages.xml ($PAPARAZZI_HOME). Binds the
downlink port itself, so do not run it beside a `link -udp` on the same port. A debugging aid.
"""
import argparse
import os
import socket
import sys
import time

home = os.environ.get("PAPARAZZI_HOME")
if not home:
    sys.exit("source target/paparazzi/env.sh first (PAPARAZZI_HOME)")
sys.path.insert(0, os.path.join(home, "sw/ext/pprzlink/lib/v2.0/python"))
os.environ.setdefault("PAPARAZZI_SRC", home)
from pprzlink.pprz_transport import PprzTransport  # noqa: E402

ap = argparse.ArgumentParser()
ap.add_argument("--port", type=int, default=4242)
ap.add_argument("--only", default="", help="comma-separated message names")
ap.add_argument("--seconds", type=float, default=1e9, help="wall seconds to listen")
a = ap.parse_args()
only = set(filter(None, a.only.split(",")))

s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
s.bind(("0.0.0.0", a.port))
s.settimeout(0.5)
tp = PprzTransport("telemetry")
t_end = time.time() + a.seconds
while time.time() < t_end:
    try:
        data, _ = s.recvfrom(4096)
    except socket.timeout:
        continue
    for b in data:
        if tp.parse_byte(bytes([b])):
            (sender, receiver, component, msg) = tp.unpack()
            if msg is None or (only and msg.name not in only):
                continue
            print(f"{sender} {msg.name} " + " ".join(f"{k}={v}" for k, v in zip(msg.fieldnames, msg.fieldvalues)),
                  flush=True)
