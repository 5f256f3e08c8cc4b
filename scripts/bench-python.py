#!/usr/bin/env python3
"""The Python package's speed, side by side in one run with the CLI and the pybullet peer.

    scripts/bench-python.sh            (builds the release binary and wheel, then runs this)

Back to back, in one process run, on this machine:
1. `dense` take-off (a 1.5 m grid among 10 pillars, Wall-Avoid at 1 m) at N = 100 and 1,000 on
   one thread: the CLI (`twinswarm run --no-bus --no-log`), the Python batched path (each step:
   `truth()`, `sensors()`, a batched `command("mode", "wall_avoid")` for every copter (it keeps
   the physics)
   and `step()`; its digests must equal the CLI's), alternating, three runs each, the best of
   each counted, and the pybullet peer
   (`peer_pybullet.py bench --scheme ctrl50_zoh --k 10 --rays 1`); real-time factors on the
   wall clock and their ratios;
2. the PettingZoo dict API against the batched path on the same swarm and actions;
3. lockstep over Zenoh on loopback, one Python controller (thread and session) per copter,
   answering each state at once: control steps per second at N = 1, 10, 100;
4. B = 8 worlds of 10 copters stepped by `step_many` on RAYON_NUM_THREADS threads (2 from
   bench-python.sh; scripts/bench-peers.sh asks 1, on one core): env-steps and copter-steps per
   second; the package's VectorEnv (8 one-copter worlds), and the pybullet peer stepping the same
   80 copters;
5. (`--only ros2-lockstep`, not by default) a ROS 2 controller node driving the lockstep:
   `examples/ros2/swarm_circle.py --lockstep` (zenoh-ros2-sdk, one session, a `cmd_vel`
   publisher per copter) answering each `/clock` tick for every copter of `run --ros2
   --lockstep`: ticks per second at N = 1, 10, 100, as the example measures them.

Prints one JSON object per measurement and a summary table (Markdown) at the end.
"""
import argparse
import json
import os
import subprocess
import sys
import tempfile
import threading
import time

import numpy as np

import twinswarm

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PEER = os.path.join(ROOT, "..", "shared", "bench", "peer_pybullet.py")


def emit(rows, **r):
    rows.append(r)
    print(json.dumps(r), flush=True)


def scene(binary, kind, n):
    return subprocess.run([binary, "scene", kind, "--n", str(n)], capture_output=True, text=True, check=True).stdout


def cli_run(binary, text, seconds, *extra):
    with tempfile.NamedTemporaryFile("w", suffix=".toml", delete=False) as f:
        f.write(text)
    try:
        out = subprocess.run([binary, "run", f.name, "--no-bus", "--no-log", "--json", "--threads", "1",
                              "--duration", str(seconds), *extra], capture_output=True, text=True, check=True)
    finally:
        os.unlink(f.name)
    return json.loads(out.stdout)


def peer(n, seconds):
    out = subprocess.run([sys.executable, PEER, "bench", "--scheme", "ctrl50_zoh", "--k", "10", "--rays", "1",
                          "--n", str(n), "--sim-seconds", str(seconds)], capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def python_path(text, steps):
    sim = twinswarm.Sim(scene=text, threads=1)
    t0 = time.perf_counter()
    for _ in range(steps):
        truth, sensors = sim.truth(), sim.sensors()
        sim.command("mode", "wall_avoid")
        sim.step()
    wall = time.perf_counter() - t0
    assert truth.shape[0] == sensors.shape[0] == sim.n
    return sim, wall


def bench_dense(binary, rows, ns, seconds):
    for n in ns:
        text = scene(binary, "dense", n)
        steps = round(seconds / 0.05)
        # The CLI and the Python path alternate, three runs each; the best of each counts (on a
        # shared machine a run is only ever slowed down).
        cli_rtfs, py_rtfs = [], []
        for _ in range(3):
            cli = cli_run(binary, text, seconds)
            sim, wall = python_path(text, steps)
            same = sim.digest() == [c["digest"] for c in cli["copters"]]
            assert same, "the Python batched path parted from the CLI"
            cli_rtfs.append(cli["real_time_factor"])
            py_rtfs.append(steps * 0.05 / wall)
        pb = peer(n, min(seconds, 20.0))
        py_rtf, cli_rtf = max(py_rtfs), max(cli_rtfs)
        emit(rows, bench="dense", N=n, sim_s=seconds, cli_rtf=round(cli_rtf, 2),
             python_rtf=round(py_rtf, 2), python_vs_cli=round(py_rtf / cli_rtf, 3),
             cli_rtfs=[round(r, 2) for r in cli_rtfs], python_rtfs=[round(r, 2) for r in py_rtfs],
             peer_rtf=pb["rtf_wallclock"], python_vs_peer=round(py_rtf / pb["rtf_wallclock"], 2),
             crashed=int(sim.crashed().sum()), digests_equal=same)


def bench_pettingzoo(binary, rows, ns, steps):
    for n in ns:
        text = scene(binary, "hover", n)
        env = twinswarm.parallel_env(scene=text, task="hover", seed=1, max_steps=steps + 10)
        obs, _ = env.reset(seed=1)
        rng = np.random.default_rng(0)
        acts = rng.uniform(-0.2, 0.2, size=(steps, n, 4)).astype(np.float32)
        t0 = time.perf_counter()
        for k in range(steps):
            actions = {a: acts[k, i] for i, a in enumerate(env.agents)}
            obs, rew, term, trunc, info = env.step(actions)
        t_env = time.perf_counter() - t0
        # The same swarm, the same actions, through the batched Sim alone.
        sim = twinswarm.Sim(scene=text, seed=1)
        t0 = time.perf_counter()
        for k in range(steps):
            sim.command("velocity", np.column_stack([acts[k, :, 0], acts[k, :, 1], np.full(n, 1.0),
                                                     np.zeros(n)]))
            sim.step()
            sim.truth(), sim.sensors()
        t_raw = time.perf_counter() - t0
        emit(rows, bench="pettingzoo", N=n, steps=steps, env_steps_per_s=round(steps / t_env, 1),
             batched_steps_per_s=round(steps / t_raw, 1), overhead=round(t_env / t_raw - 1.0, 3))


def free_port():
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def bench_lockstep(binary, rows, ns, seconds):
    import zenoh

    for n in ns:
        text = scene(binary, "hover", n)
        with tempfile.NamedTemporaryFile("w", suffix=".toml", delete=False) as f:
            f.write(text)
        names = [l.split('"')[1] for l in text.splitlines() if l.startswith("name = ") and "copter" not in l][1:]
        names = twinswarm.Sim(scene=text).names
        port = free_port()
        endpoint = f"tcp/127.0.0.1:{port}"
        prefix = f"bench-{port}/w"
        last = round(seconds / 0.05)
        proc = subprocess.Popen([binary, "run", f.name, "--lockstep", "--wait-claims", ",".join(names),
                                 "--duration", str(seconds), "--no-log", "--json", "--listen", endpoint,
                                 "--prefix", prefix, "--lockstep-timeout", "10"],
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        times = {}
        lock = threading.Lock()

        def controller(i, name):
            conf = zenoh.Config()
            conf.insert_json5("mode", '"peer"')
            conf.insert_json5("scouting/multicast/enabled", "false")
            conf.insert_json5("listen/endpoints", "[]")
            conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
            with zenoh.open(conf) as s:
                sub = s.declare_subscriber(f"{prefix}/copters/{name}/state")
                pub = s.declare_publisher(f"{prefix}/copters/{name}/cmd")
                tok = s.liveliness().declare_token(f"{prefix}/alive/copters/{name}/c{i}")
                while True:
                    sample = sub.recv()
                    tick = json.loads(sample.payload.to_bytes())["tick"]
                    if tick in (1, last):
                        with lock:
                            times.setdefault(tick, time.perf_counter())
                    pub.put(json.dumps({"tick": tick, "client": f"c{i}"}))
                    if tick >= last:
                        break
                tok.undeclare()

        time.sleep(0.3)
        threads = [threading.Thread(target=controller, args=(i, nm), daemon=True) for i, nm in enumerate(names)]
        for t in threads:
            t.start()
        out, err = proc.communicate(timeout=600)
        os.unlink(f.name)
        assert proc.returncode == 0, err
        ls = json.loads(out)["lockstep"]
        steps_per_s = (last - 1) / (times[last] - times[1])
        emit(rows, bench="lockstep", N=n, steps=last, steps_per_s=round(steps_per_s, 1),
             rtf=round(steps_per_s * 0.05, 2), timeouts=sum(ls["timeouts"].values()), answers=ls["answers"])


def bench_ros2_lockstep(binary, rows, ns, seconds):
    for n in ns:
        text = scene(binary, "hover", n)
        with tempfile.NamedTemporaryFile("w", suffix=".toml", delete=False) as f:
            f.write(text)
        names = twinswarm.Sim(scene=text).names
        port = free_port()
        # The example climbs for 2 s, then circles for `seconds`; the run ends a second later.
        proc = subprocess.Popen([binary, "run", f.name, "--ros2", "--lockstep", "--wait-claims", ",".join(names),
                                 "--duration", str(seconds + 3.0), "--no-log", "--json",
                                 "--listen", f"tcp/127.0.0.1:{port}", "--lockstep-timeout", "10"],
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        time.sleep(0.3)
        example = os.path.join(ROOT, "examples", "ros2", "swarm_circle.py")
        ctl = subprocess.run([sys.executable, example, "--lockstep", "--seconds", str(seconds), "--port", str(port),
                              "--expect", str(n)],
                             capture_output=True, text=True, timeout=600)
        out, err = proc.communicate(timeout=600)
        os.unlink(f.name)
        assert ctl.returncode == 0 and proc.returncode == 0, (ctl.stderr[-2000:], err[-2000:])
        line = next(l for l in ctl.stdout.splitlines() if l.startswith("lockstep:"))
        ticks, wall = int(line.split()[1]), float(line.split()[5])
        ls = json.loads(out)["lockstep"]
        emit(rows, bench="ros2-lockstep", N=n, ticks=ticks, ticks_per_s=round(ticks / wall, 1),
             rtf=round(ticks / wall * 0.05, 2), timeouts=sum(ls["timeouts"].values()), answers=ls["answers"])


def bench_vector(binary, rows, steps):
    text = scene(binary, "hover", 10)
    sims = [twinswarm.Sim(scene=text, seed=s) for s in range(8)]
    t0 = time.perf_counter()
    for _ in range(steps):
        twinswarm.step_many(sims)
        for s in sims:
            s.truth(), s.sensors()
    wall = time.perf_counter() - t0
    env = twinswarm.vector_env(num_envs=8, max_steps=steps + 10)
    env.reset(seed=0)
    acts = np.zeros((8, 4), dtype=np.float32)
    t0 = time.perf_counter()
    for _ in range(steps):
        env.step(acts)
    wall_env = time.perf_counter() - t0
    pb = peer(80, 10.0)
    emit(rows, bench="vector", B=8, copters_per_world=10, threads=int(os.environ.get("RAYON_NUM_THREADS", "0")),
         env_steps_per_s=round(8 * steps / wall, 1), copter_steps_per_s=round(80 * steps / wall, 1),
         vectorenv_1copter_env_steps_per_s=round(8 * steps / wall_env, 1),
         peer_80_copter_steps_per_s=round(80 * pb["ctrl_steps_per_s"], 1),
         vs_peer=round((80 * steps / wall) / (80 * pb["ctrl_steps_per_s"]), 2))


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--binary", default=os.path.join(ROOT, "target", "release", "twinswarm"))
    ap.add_argument("--n", type=int, nargs="+", default=[100, 1000])
    ap.add_argument("--seconds", type=float, default=60.0, help="simulated seconds of the dense runs")
    ap.add_argument("--only", nargs="+", default=["dense", "pettingzoo", "lockstep", "vector"])
    a = ap.parse_args()
    rows = []
    print(json.dumps({"load_before": open("/proc/loadavg").read().split()[:3]}), flush=True)
    if "dense" in a.only:
        bench_dense(a.binary, rows, a.n, a.seconds)
    if "pettingzoo" in a.only:
        bench_pettingzoo(a.binary, rows, a.n, 200)
    if "lockstep" in a.only:
        bench_lockstep(a.binary, rows, [1, 10, 100], 10.0)
    if "vector" in a.only:
        bench_vector(a.binary, rows, 400)
    if "ros2-lockstep" in a.only:
        bench_ros2_lockstep(a.binary, rows, [1, 10, 100], 10.0)
    print(json.dumps({"load_after": open("/proc/loadavg").read().split()[:3]}), flush=True)
    print("\n| bench | N | figures |\n|---|---|---|")
    for r in rows:
        rest = ", ".join(f"{k} {v}" for k, v in r.items() if k not in ("bench", "N"))
        print(f"| {r['bench']} | {r.get('N', '')} | {rest} |")


if __name__ == "__main__":
    main()
