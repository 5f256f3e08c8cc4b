#!/usr/bin/env python3
"""What `twinswarm run --ros2` costs a run, measured side by side.

For each N, interleaved ROUNDS times (this machine is noisy), the same generated scene
(`twinswarm scene dense --n N --air`, no log, one thread, at full speed, on the Zenoh bus
listening on a free loopback port):

- bus:      the Zenoh bus alone (every run of this script has it: ROS 2 needs it);
- ros2:     --ros2, no ROS subscriber;
- watched:  --ros2 and a subscriber (eclipse-zenoh, in this process) on every copter's
            `/<c>/pose` and on `/tf`, reading everything, with the subscription tokens in
            the ROS graph, as an rmw_zenoh node has them.

It reports each run's real-time factor (simulated / wall time, from `--json`), the best of the
rounds per variant, the cost against `bus`, and what the watched runs sent. Run with the venv of
scripts/test.sh:

    .venv/bin/python scripts/ros2-cost.py [--n 100 1000] [--seconds 300 30] [--rounds 3]
                                          [--bin target/release/twinswarm]
"""

import argparse
import json
import pathlib
import socket
import subprocess
import sys
import tempfile
import threading
import time
import tomllib

import zenoh
from rosbags.typesys import Stores, get_typestore

ROOT = pathlib.Path(__file__).resolve().parents[1]


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def client(endpoint):
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("listen/endpoints", "[]")
    conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
    return conf


TS = get_typestore(Stores.ROS2_JAZZY)
POSE_HASH = TS.hash_rihs01("geometry_msgs/msg/PoseStamped")
TF_HASH = TS.hash_rihs01("tf2_msgs/msg/TFMessage")


def ros_name(copter):
    s = "".join(c if c.isascii() and c.isalnum() else "_" for c in copter)
    return "c_" + s if not s or s[0].isdigit() else s


def subscription_tokens(session, scene):
    """A ROS node's tokens: the node, and a subscription to every `/<c>/pose` and to `/tf`."""
    zid = str(session.info.zid())
    names = [ros_name(c["name"]) for c in tomllib.loads(scene.read_text()).get("copter", [])]
    keys = [f"@ros2_lv/0/{zid}/0/0/NN/%/%/cost_watcher"]
    topics = [(f"%{n}%pose", "geometry_msgs::msg::dds_::PoseStamped_", POSE_HASH) for n in names]
    topics.append(("%tf", "tf2_msgs::msg::dds_::TFMessage_", TF_HASH))
    keys += [f"@ros2_lv/0/{zid}/0/{k + 1}/MS/%/%/cost_watcher/{t}/{ty}/{h}/2::,5:,:,:,,"
             for k, (t, ty, h) in enumerate(topics)]
    return [session.liveliness().declare_token(k) for k in keys]


def run(binary, scene, seconds, variant):
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    args = [str(binary), "run", str(scene), "--no-log", "--json", "--duration", str(seconds), "--threads", "1",
            "--listen", endpoint, "--prefix", f"cost{port}/swarm"]
    if variant != "bus":
        args.append("--ros2")
    if variant != "watched":
        p = subprocess.run(args, capture_output=True, text=True, timeout=3600)
        if p.returncode != 0:
            sys.exit(f"twinswarm failed ({variant}): {p.stderr}")
        return json.loads(p.stdout), None
    # Subscribe before the run steps: the subscriber connects while the simulator opens its
    # session (it retries until the port listens).
    received = [0]
    lock = threading.Lock()

    def count(_):
        with lock:
            received[0] += 1

    proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    session = None
    t0 = time.monotonic()
    while session is None:
        try:
            session = zenoh.open(client(endpoint))
        except Exception:
            if time.monotonic() - t0 > 30 or proc.poll() is not None:
                raise
            time.sleep(0.01)
    subs = [session.declare_subscriber(k, count) for k in ("0/*/pose/**", "0/tf/**")]
    tokens = subscription_tokens(session, scene)
    out, err = proc.communicate(timeout=3600)
    del subs, tokens
    session.close()
    if proc.returncode != 0:
        sys.exit(f"twinswarm failed ({variant}): {err}")
    return json.loads(out), received[0]


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n", type=int, nargs="+", default=[100, 1000])
    ap.add_argument("--seconds", type=float, nargs="+", default=[300, 30],
                    help="simulated seconds per N (the last one for the rest)")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--bin", default=str(ROOT / "target" / "release" / "twinswarm"))
    a = ap.parse_args()
    with open("/proc/loadavg") as f:
        print(f"load average before: {' '.join(f.read().split()[:3])}", file=sys.stderr)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for k, n in enumerate(a.n):
            seconds = a.seconds[min(k, len(a.seconds) - 1)]
            scene = pathlib.Path(tmp) / f"dense{n}.toml"
            gen = [a.bin, "scene", "dense", "--n", str(n), "--air"]
            scene.write_text(subprocess.run(gen, capture_output=True, text=True, check=True).stdout)
            best, watched = {}, None
            for r in range(a.rounds):
                for variant in ("bus", "ros2", "watched"):
                    summary, received = run(a.bin, scene, seconds, variant)
                    rtf = summary["real_time_factor"]
                    ros = summary["bus"].get("ros2")
                    print(json.dumps({"N": n, "round": r, "variant": variant, "rtf": round(rtf, 2),
                                      "ros2": ros, "received": received}), flush=True)
                    best[variant] = max(best.get(variant, 0), rtf)
                    if variant == "watched":
                        watched = (ros, received)
            rows.append((n, best, watched))
    with open("/proc/loadavg") as f:
        print(f"load average after: {' '.join(f.read().split()[:3])}", file=sys.stderr)
    print()
    print("| N | bus alone (rtf) | --ros2, no subscriber | cost | --ros2, pose and tf subscribed | cost | ROS messages sent / received |")
    print("|---:|---:|---:|---:|---:|---:|---|")
    for n, best, (ros, received) in rows:
        cost = lambda v: f"{(best['bus'] / best[v] - 1) * 100:+.1f} %"
        print(f"| {n} | {best['bus']:.2f}x | {best['ros2']:.2f}x | {cost('ros2')} | {best['watched']:.2f}x "
              f"| {cost('watched')} | {ros['sent']} / {received} |")


if __name__ == "__main__":
    main()
