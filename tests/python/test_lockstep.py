"""Lockstep with external controllers (`twinswarm run --lockstep`, docs/lockstep.md), with
eclipse-zenoh clients as the controllers: one session and one thread per copter.

Each controller claims its copter, answers every state of tick t with a velocity command
carrying `"tick": t` after sleeping a random 0-20 ms, and the simulator steps once every
answer is in. Two such runs give identical digests, and they equal an in-process Python run
(`twinswarm.Sim`) of the same controller logic: the lockstep makes latency irrelevant.
"""
import json
import random
import subprocess
import threading
import time

import numpy as np
import zenoh

import twinswarm
from conftest import free_tcp_port, zenoh_client_config

DURATION_S = 4.0
COPTERS = ("finken1", "finken2")


def decide(name_index: int, tick: int, x: float, y: float) -> list:
    """The controller: fly to one of two points, switching every 2 s, at 1 m. Positions are
    float32 on both paths (the state message's JSON holds the f64 of each f32, exactly)."""
    x, y = float(np.float32(x)), float(np.float32(y))
    goal = (0.9, 0.2) if (tick // 40 + name_index) % 2 == 0 else (-0.9, 0.4)
    clip = lambda v: max(-0.6, min(0.6, v))  # noqa: E731
    return [clip(0.8 * (goal[0] - x)), clip(0.8 * (goal[1] - y)), 1.0, 0.0]


def controller(endpoint, prefix, index, name, last_tick, errors, jitter_s):
    """Claims `name`, then answers each state until `last_tick`."""
    rng = random.Random(1000 + index)
    client = f"pilot{index}"
    try:
        with zenoh.open(zenoh_client_config(endpoint)) as session:
            sub = session.declare_subscriber(f"{prefix}/copters/{name}/state")
            pub = session.declare_publisher(f"{prefix}/copters/{name}/cmd")
            token = session.liveliness().declare_token(f"{prefix}/alive/copters/{name}/{client}")
            deadline = time.monotonic() + 120
            while time.monotonic() < deadline:
                sample = sub.try_recv()
                if sample is None:
                    time.sleep(0.0005)
                    continue
                state = json.loads(sample.payload.to_bytes())
                tick = state["tick"]
                x, y = state["pos_m"][0], state["pos_m"][1]
                fwd, left, height, yaw = decide(index, tick, x, y)
                time.sleep(rng.uniform(0.0, jitter_s))
                cmd = {"mode": "velocity", "velocity": [fwd, left], "height": height, "yaw": yaw, "tick": tick,
                       "client": client}
                pub.put(json.dumps(cmd))
                if tick >= last_tick:
                    break
            token.undeclare()
    except Exception as e:  # noqa: BLE001 - reported by the test
        errors.append(f"{name}: {e!r}")


def lockstep_run(twinswarm_bin, jitter_s):
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    prefix = f"lockstep-{endpoint.rsplit(':', 1)[1]}/lab"
    proc = subprocess.Popen(
        [str(twinswarm_bin), "run", "--lockstep", "--wait-claims", ",".join(COPTERS), "--lockstep-timeout", "10",
         "--duration", str(DURATION_S), "--json", "--no-log", "--listen", endpoint, "--prefix", prefix],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    errors = []
    last_tick = round(DURATION_S / 0.05)
    try:
        time.sleep(0.5)
        threads = [threading.Thread(target=controller, args=(endpoint, prefix, i, n, last_tick, errors, jitter_s))
                   for i, n in enumerate(COPTERS)]
        for t in threads:
            t.start()
        out, err = proc.communicate(timeout=180)
        for t in threads:
            t.join(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert not errors, errors
    assert proc.returncode == 0, err
    summary = json.loads(out)
    return summary


def test_lockstep_runs_are_identical_whatever_the_latency_and_equal_the_python_run(twinswarm_bin):
    a = lockstep_run(twinswarm_bin, jitter_s=0.020)
    b = lockstep_run(twinswarm_bin, jitter_s=0.020)
    for s in (a, b):
        ls = s["lockstep"]
        assert s["control_steps"] == round(DURATION_S / 0.05)
        assert ls["timeouts"] == {} and ls["late"] == 0 and ls["refused"] == 0, ls
        assert ls["answers"] == len(COPTERS) * s["control_steps"], ls
        assert ls["wait_s"] > 0.2, "the controllers' sleeps held the steps"
    digests = [c["digest"] for c in a["copters"]]
    assert digests == [c["digest"] for c in b["copters"]]

    sim = twinswarm.Sim()
    for _ in range(round(DURATION_S / 0.05)):
        t = sim.truth()
        rows = [decide(i, sim.tick, t[i, 0], t[i, 1]) for i in range(sim.n)]
        sim.command("velocity", rows)
        sim.step()
    assert sim.digest() == digests
    assert np.abs(sim.truth()[:, :2] - np.array([[-0.8, 0.0], [0.8, 0.0]])).max() > 0.3, "they flew"


def test_a_silent_controller_times_out_and_its_copter_keeps_its_command(twinswarm_bin):
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    prefix = f"lockstep-{endpoint.rsplit(':', 1)[1]}/lab"
    proc = subprocess.Popen(
        [str(twinswarm_bin), "run", "--lockstep", "--wait-claims", "finken1", "--lockstep-timeout", "0.05",
         "--duration", "1", "--json", "--no-log", "--listen", endpoint, "--prefix", prefix],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        time.sleep(0.5)
        with zenoh.open(zenoh_client_config(endpoint)) as session:
            token = session.liveliness().declare_token(f"{prefix}/alive/copters/finken1/mute")
            out, err = proc.communicate(timeout=60)
            token.undeclare()
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, err
    ls = json.loads(out)["lockstep"]
    assert ls["timeouts"] == {"mute": 20} and ls["answers"] == 0 and ls["steps_held"] == 20, ls


def test_lockstep_refuses_what_it_cannot_do(twinswarm_bin):
    for args, message in [
        (["--lockstep", "--no-bus"], "--lockstep needs the Zenoh bus"),
        (["--wait-claims", "finken1"], "--wait-claims needs --lockstep"),
        (["--lockstep", "--wait-claims", "nobody"], 'no copter named "nobody"'),
        (["--lockstep", "--lockstep-timeout", "0"], "--lockstep-timeout must be in"),
    ]:
        out = subprocess.run([str(twinswarm_bin), "run", "--no-log", *args], capture_output=True, text=True,
                             timeout=30)
        assert out.returncode == 2 and message in out.stderr, (args, out.stderr)
