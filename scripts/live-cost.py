#!/usr/bin/env python3
"""What the live view (`twinswarm run --foxglove`) costs a run, measured side by side.

For each N, interleaved ROUNDS times (this machine is noisy), the same generated scene
(`twinswarm scene dense|cruise --n N --air`, no log, no bus, one thread, at full speed):

- off:     no --foxglove;
- idle:    --foxglove, no client connected;
- watched: --foxglove and one client (PyPI `websockets`, in this process) subscribed to every
           channel and reading everything it gets.

It reports each run's real-time factor (simulated / wall time, from `--json`), the best of the
rounds per variant, the cost against `off`, and the live counters of the watched runs. Run
with the venv of scripts/test.sh:

    .venv/bin/python scripts/live-cost.py [--n 100 1000] [--seconds 30] [--rounds 3]
                                          [--scene dense|cruise] [--bin target/release/twinswarm]
"""

import argparse
import asyncio
import json
import pathlib
import socket
import subprocess
import sys
import tempfile
import time

import websockets

ROOT = pathlib.Path(__file__).resolve().parents[1]


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


async def watch(port, proc):
    """Subscribes to everything and reads until the run ends; returns messages received."""
    t0 = time.monotonic()
    while True:
        try:
            ws = await websockets.connect(f"ws://127.0.0.1:{port}", subprotocols=["foxglove.websocket.v1"],
                                          max_size=None)
            break
        except OSError:
            if time.monotonic() - t0 > 30 or proc.poll() is not None:
                raise
            await asyncio.sleep(0.01)
    got = 0
    async with ws:
        await ws.recv()  # serverInfo
        adv = json.loads(await ws.recv())
        await ws.send(json.dumps({"op": "subscribe", "subscriptions": [
            {"id": k, "channelId": c["id"]} for k, c in enumerate(adv["channels"])]}))
        try:
            async for _ in ws:
                got += 1
        except websockets.ConnectionClosed:
            pass
    return got


def run(binary, scene, seconds, variant):
    args = [str(binary), "run", str(scene), "--no-bus", "--no-log", "--json", "--duration", str(seconds),
            "--threads", "1"]
    port = free_port()
    if variant != "off":
        args += ["--foxglove", f"127.0.0.1:{port}"]
    if variant == "watched":
        # The run waits for nothing: start it, connect as fast as possible; the first steps
        # before the subscription are a small part of the run.
        proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        received = asyncio.run(watch(port, proc))
        out, err = proc.communicate(timeout=3600)
    else:
        p = subprocess.run(args, capture_output=True, text=True, timeout=3600)
        out, err, received = p.stdout, p.stderr, None
        proc = p
    if proc.returncode != 0:
        sys.exit(f"twinswarm failed ({variant}): {err}")
    summary = json.loads(out)
    return summary["real_time_factor"], summary.get("live"), received


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n", type=int, nargs="+", default=[100, 1000])
    ap.add_argument("--seconds", type=float, default=30)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--scene", choices=["dense", "cruise"], default="dense")
    ap.add_argument("--bin", default=str(ROOT / "target" / "release" / "twinswarm"))
    a = ap.parse_args()
    with open("/proc/loadavg") as f:
        print(f"load average before: {' '.join(f.read().split()[:3])}", file=sys.stderr)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for n in a.n:
            scene = pathlib.Path(tmp) / f"{a.scene}{n}.toml"
            gen = [a.bin, "scene", a.scene, "--n", str(n)] + (["--air"] if a.scene == "dense" else [])
            scene.write_text(subprocess.run(gen, capture_output=True, text=True, check=True).stdout)
            best = {}
            live = None
            for r in range(a.rounds):
                for variant in ("off", "idle", "watched"):
                    rtf, stats, received = run(a.bin, scene, a.seconds, variant)
                    print(json.dumps({"N": n, "round": r, "variant": variant, "rtf": round(rtf, 2),
                                      "received": received, "live": stats}), flush=True)
                    best[variant] = max(best.get(variant, 0), rtf)
                    if variant == "watched":
                        live = (stats, received)
            rows.append((n, best, live))
    with open("/proc/loadavg") as f:
        print(f"load average after: {' '.join(f.read().split()[:3])}", file=sys.stderr)
    print()
    print(f"| scene | N | off (rtf) | idle server | cost | one client, all channels | cost | messages sent / received / dropped | steps skipped |")
    print("|---|---:|---:|---:|---:|---:|---:|---|---:|")
    for n, best, (stats, received) in rows:
        cost = lambda v: f"{(best['off'] / best[v] - 1) * 100:+.1f} %"
        print(f"| {a.scene} (air, {a.seconds:g} s) | {n} | {best['off']:.1f}x | {best['idle']:.1f}x | {cost('idle')} "
              f"| {best['watched']:.1f}x | {cost('watched')} | {stats['messages_sent']} / {received} / "
              f"{stats['messages_dropped']} | {stats['steps_skipped']} |")


if __name__ == "__main__":
    main()
