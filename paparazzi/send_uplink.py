#!/usr/bin/env python3
"""Send the virtual sonar uplink SONAR_UPLINK to an NPS aircraft's datalink (pprzlink 2.0 over
UDP, as `link -udp` sends uplink: to 127.0.0.1:4243 by default), as the FINken mixed-reality
bridge did (`dl SONAR_UPLINK <ac_id> 255 <front> <left> <back> <right>`, cm, every 50 ms).

    . target/paparazzi/env.sh
    python3 paparazzi/send_uplink.py --ac-id 21 --front 0.5 [--right R] [--back B] [--left L] \\
        [--rate 20] [--seconds 5] [--host 127.0.0.1] [--port 4243]

Distances in m; a direction left out is sent as 765 cm (nothing). The message's field order
is front, LEFT, back, RIGHT (the FINken's). Encodes with Paparazzi's own pprzlink Python
library and $PAPARAZZI_HOME/var/messages.xml (which build_nps.sh extends with SONAR_UPLINK,
datalink id 153), or --messages FILE. Prints one line per second sent. A test aid.
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

NONE_CM = 765


def cm(v):
    return NONE_CM if v is None else max(0, min(NONE_CM, int(round(v * 100.0))))


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ac-id", type=int, required=True)
    for d in ("front", "right", "back", "left"):
        ap.add_argument(f"--{d}", type=float, help="virtual distance, m (left out: nothing)")
    ap.add_argument("--rate", type=float, default=20.0, help="messages per wall second")
    ap.add_argument("--seconds", type=float, default=5.0, help="wall seconds to send for")
    ap.add_argument("--host", default="127.0.0.1")
    ap.add_argument("--port", type=int, default=4243)
    ap.add_argument("--sender", type=int, default=0, help="pprzlink sender id (0: the ground)")
    ap.add_argument("--messages", help="messages.xml (default $PAPARAZZI_HOME/var/messages.xml)")
    a = ap.parse_args()

    from pprzlink import messages_xml_map
    messages_xml_map.parse_messages(a.messages or os.path.join(home, "var/messages.xml"))
    from pprzlink.message import PprzMessage
    from pprzlink.pprz_transport import PprzTransport

    msg = PprzMessage("datalink", "SONAR_UPLINK")
    values = {"ac_id": a.ac_id, "unused": 255, "front": cm(a.front), "left": cm(a.left),
              "back": cm(a.back), "right": cm(a.right)}
    for k, v in values.items():
        msg[k] = v
    frame = bytes(PprzTransport("datalink").pack_pprz_msg(a.sender, msg, receiver=a.ac_id))
    print(f"send_uplink: SONAR_UPLINK id {msg.msg_id} class {msg.class_id} {values} -> "
          f"{a.host}:{a.port}, {len(frame)} B frame {frame.hex()}", flush=True)
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    period = 1.0 / a.rate
    t0 = time.monotonic()
    n = 0
    next_t = t0
    last_print = t0
    while time.monotonic() - t0 < a.seconds:
        s.sendto(frame, (a.host, a.port))
        n += 1
        now = time.monotonic()
        if now - last_print >= 1.0:
            print(f"send_uplink: {n} sent", flush=True)
            last_print = now
        next_t += period
        time.sleep(max(0.0, next_t - time.monotonic()))
    print(f"send_uplink: done, {n} messages in {time.monotonic() - t0:.2f} s", flush=True)


if __name__ == "__main__":
    main()
