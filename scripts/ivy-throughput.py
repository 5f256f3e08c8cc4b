#!/usr/bin/env python3
"""Ivy throughput with 100 peer regexes: Twinswarm's agent against ivy-python, in one run.

A receiver (ivy-python 4.0) binds 100 regexes `^(\\S+) MSG<i> (.*)$`; then each sender sends
N texts that match one of them, and the receiver measures messages per second from the first
to the last arrival. Senders: `twinswarm ivy send --repeat N` (Rust, sender-side matching over
the receiver's 100 regexes) and an ivy-python agent doing the same. Loopback bus, free port.

    .venv/bin/python scripts/ivy-throughput.py [--n 20000] [--bin target/release/twinswarm]
"""
import argparse
import socket
import subprocess
import threading
import time

from ivy.ivy import IvyApplicationConnected, IvyServer


def free_udp_port():
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Receiver:
    def __init__(self, bus):
        self.lock = threading.Lock()
        self.times = []
        self.joined = {}
        self.srv = IvyServer("Receiver", app_callback=self.on_app, usesDaemons=True)
        for i in range(100):
            self.srv.bind_msg(self.on_msg, r"^(\S+) MSG%d (.*)$" % i)
        self.srv.start(bus)

    def on_app(self, agent, ev):
        if ev == IvyApplicationConnected:
            self.joined.setdefault(agent.agent_name, threading.Event()).set()

    def on_msg(self, agent, *groups):
        with self.lock:
            self.times.append(time.perf_counter())

    def measure(self, n, timeout_s=120):
        t0 = time.monotonic()
        while time.monotonic() - t0 < timeout_s:
            with self.lock:
                if len(self.times) >= n:
                    break
            time.sleep(0.05)
        time.sleep(0.5)
        with self.lock:
            t, self.times = self.times, []
        rate = (len(t) - 1) / (t[-1] - t[0]) if len(t) > 1 else 0.0
        return len(t), rate


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=20000)
    ap.add_argument("--bin", default="target/release/twinswarm")
    a = ap.parse_args()
    bus = f"127.255.255.255:{free_udp_port()}"
    rx = Receiver(bus)
    text = "5 MSG57 1.000000 -2.500000 3 4 5 6 7 8"

    out = subprocess.run([a.bin, "ivy", "-b", bus, "--name", "RustSender", "send", "--wait", "1.5",
                          "--repeat", str(a.n), text], capture_output=True, text=True, timeout=300)
    print("twinswarm sender:", out.stdout.strip().replace("\n", "; "))
    got_rust, rate_rust = rx.measure(a.n)

    py = IvyServer("PySender", usesDaemons=True)
    py.start(bus)
    time.sleep(1.5)
    t0 = time.perf_counter()
    for _ in range(a.n):
        py.send_msg(text)
    send_s = time.perf_counter() - t0
    got_py, rate_py = rx.measure(a.n)
    py.stop()
    rx.srv.stop()
    print(f"| sender | received | rate at the receiver (msgs/s) |")
    print(f"|---|---:|---:|")
    print(f"| twinswarm (Rust) | {got_rust}/{a.n} | {rate_rust:,.0f} |")
    print(f"| ivy-python 4.0 | {got_py}/{a.n} | {rate_py:,.0f} (its send loop: {a.n / send_s:,.0f}/s) |")
    print(f"ratio twinswarm / ivy-python: {rate_rust / rate_py:.2f}" if rate_py else "ivy-python received nothing")


if __name__ == "__main__":
    main()
