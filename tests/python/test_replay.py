"""`twinswarm replay`: a logged run goes back onto Zenoh with its timing, in the live message
shapes; bad files and bad speeds are refused with exit code 2. Every wait is bounded."""
import json
import subprocess
import threading
import time

import pytest
import zenoh

from conftest import log_bodies, loopback_endpoint, zenoh_client_config

STATE_KEYS = {
    "name", "kind", "ac_id", "tick", "time_s", "mode", "pos_m", "vel_m_s", "attitude_rad",
    "angvel_rad_s", "quat_xyzw", "rotor_thrust_n", "crashed",
}
SENSOR_KEYS = {
    "name", "tick", "time_s", "sonar_m", "sonar_fused_m", "ir_m", "attitude_rad", "rate_body_rad_s", "accel_body_m_s2",
    "height_est_m", "battery_v", "battery_charge",
}


def session_to(endpoint):
    return zenoh.open(zenoh_client_config(endpoint))


def read_log(path, topic):
    return log_bodies(path, topic)


def wait_for_line(proc, needle, timeout):
    """Reads stdout lines until one contains `needle` (in a thread, so it is bounded)."""
    lines, found = [], threading.Event()

    def pump():
        for line in proc.stdout:
            lines.append(line)
            if needle in line:
                found.set()
        found.set()

    threading.Thread(target=pump, daemon=True).start()
    assert found.wait(timeout), f"no {needle!r} within {timeout} s: {lines}"
    return lines


def replay_received(twinswarm_bin, log, endpoint, key_expr, args, timeout=30):
    """Runs `twinswarm replay LOG --listen ENDPOINT ARGS --wait-for-subscriber 15`, subscribes to
    `key_expr` once it waits, and collects what arrives until it exits (bounded by `timeout`).
    Returns (exit code, stdout, stderr, [(arrival time, key, payload text)])."""
    replay = subprocess.Popen(
        [str(twinswarm_bin), "replay", str(log), "--listen", endpoint, *args, "--wait-for-subscriber", "15"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    received = []
    lock = threading.Lock()
    try:
        lines = wait_for_line(replay, "waiting up to", 20)
        with session_to(endpoint) as session:
            def on_sample(sample):
                with lock:
                    received.append((time.monotonic(), str(sample.key_expr), sample.payload.to_string()))

            sub = session.declare_subscriber(key_expr, on_sample)
            out, err = replay.communicate(timeout=timeout)
            time.sleep(0.3)
            sub.undeclare()
    finally:
        if replay.poll() is None:
            replay.kill()
            replay.communicate(timeout=10)
    with lock:
        return replay.returncode, "".join(lines) + out, err, list(received)


def test_replay_republishes_with_original_timing(twinswarm_bin, free_port, tmp_path):
    log = tmp_path / "run.mcap"
    subprocess.run(
        [str(twinswarm_bin), "run", "--no-bus", "--duration", "3", "--log", str(log)],
        check=True, capture_output=True, timeout=60,
    )
    logged_states = read_log(log, "/copters/state")
    copters = sorted({s["copter"] for s in logged_states})
    steps = len({s["tick"] for s in logged_states})
    assert len(logged_states) == steps * len(copters) and steps == 60

    endpoint = f"tcp/127.0.0.1:{free_port}"
    speed = 2.0
    code, out, err, received = replay_received(twinswarm_bin, log, endpoint, "twinswarm/lab/**", ["--speed", str(speed)])
    print(out)
    assert code == 0, err
    assert f"{len(logged_states)} state" in out and f"{steps} clock" in out

    got = [(t, k, json.loads(p)) for t, k, p in received]
    states = [(t, p) for t, k, p in got if k.endswith("/state")]
    clocks = [(t, p) for t, k, p in got if k == "twinswarm/lab/clock"]
    sensors = [(t, p) for t, k, p in got if k.endswith("/sensors")]
    # Every step, every copter, none missed, in the live shape.
    assert len(states) == len(logged_states), (len(states), len(logged_states))
    assert len(clocks) == steps
    assert sensors and all(set(p) == SENSOR_KEYS for _t, p in sensors)
    for t, p in states:
        assert set(p) == STATE_KEYS, p
    for name in copters:
        ticks = [p["tick"] for _t, p in states if p["name"] == name]
        assert ticks == sorted(ticks) and len(set(ticks)) == len(ticks) == steps, (name, ticks[:5])
        logged = [s for s in logged_states if s["copter"] == name]
        # The log holds f32 (protobuf `float`), decoded here as doubles; the Zenoh JSON holds
        # the f64 of each f32. The same numbers both ways, exactly.
        replayed = [p["pos_m"] for _t, p in states if p["name"] == name]
        assert replayed == [list(s["pos_m"]) for s in logged]
    assert [p["tick"] for _t, p in clocks] == sorted({s["tick"] for s in logged_states})

    # Timing: clock inter-arrival ≈ 50 ms / speed, whole replay ≈ 3 s / speed.
    arrivals = [t for t, _p in clocks]
    gaps = [b - a for a, b in zip(arrivals, arrivals[1:])]
    mean_gap = sum(gaps) / len(gaps)
    span = arrivals[-1] - arrivals[0]
    expected_span = (clocks[-1][1]["time_s"] - clocks[0][1]["time_s"]) / speed
    print(f"clock mean gap {mean_gap * 1e3:.1f} ms (expect {50 / speed:.1f}), span {span:.3f} s (expect {expected_span:.3f})")
    assert abs(mean_gap - 0.05 / speed) <= 0.2 * 0.05 / speed
    assert abs(span - expected_span) <= 0.3 * expected_span
    assert abs(span - 3.0 / speed) <= 0.3 * 3.0 / speed


def test_replay_republishes_bus_traffic_under_a_new_prefix(twinswarm_bin, free_port, tmp_path):
    """A run that received a command: replay puts the command back on its key (under --prefix)."""
    log = tmp_path / "bus.mcap"
    sim_ep = f"tcp/127.0.0.1:{free_port}"
    sim = subprocess.Popen(
        [str(twinswarm_bin), "run", "--realtime", "--duration", "2", "--log", str(log), "--listen", sim_ep],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    try:
        time.sleep(0.8)
        with session_to(sim_ep) as session:
            time.sleep(0.3)
            session.put("twinswarm/lab/copters/finken1/cmd", '{"height": 0.6}')
            time.sleep(0.3)
        sim.communicate(timeout=30)
    finally:
        if sim.poll() is None:
            sim.kill()
            sim.communicate(timeout=10)
    assert sim.returncode == 0
    bus = read_log(log, "/bus")
    assert any(m["key"] == "twinswarm/lab/copters/finken1/cmd" for m in bus), bus

    replay_ep = loopback_endpoint()
    code, out, err, received = replay_received(twinswarm_bin, log, replay_ep, "again/**",
                                               ["--speed", "4", "--prefix", "again/lab"])
    assert code == 0, err
    assert f"{len(bus)} bus" in out, out
    got = [(k, p) for _t, k, p in received]
    assert ("again/lab/copters/finken1/cmd", '{"height": 0.6}') in got
    assert any(k == "again/lab/clock" for k, _ in got)


def test_replay_sends_held_copters_every_step_like_the_live_simulator(twinswarm_bin, free_port, tmp_path):
    """A crash-heavy log holds wrecks at rest (written once a second): replay sends every
    copter's state and the clock on every step anyway, with the values of the log that writes
    every copter every step."""
    scene = tmp_path / "dense.toml"
    scene.write_text(subprocess.run([str(twinswarm_bin), "scene", "dense", "--n", "64", "--spacing", "1.0"],
                                    check=True, capture_output=True, text=True).stdout)
    held, full = tmp_path / "held.mcap", tmp_path / "full.mcap"
    for path, extra in ((held, []), (full, ["--log-unchanged", "0"])):
        subprocess.run([str(twinswarm_bin), "run", str(scene), "--no-bus", "--duration", "8", "--log", str(path),
                        *extra], check=True, capture_output=True, timeout=120)
    expected = {(s["copter"], s["tick"]): s["pos_m"] for s in read_log(full, "/copters/state")}
    logged = read_log(held, "/copters/state")
    assert len(logged) < len(expected) == 64 * 160, "wrecks held in the log"

    endpoint = f"tcp/127.0.0.1:{free_port}"
    code, out, err, received = replay_received(twinswarm_bin, held, endpoint, "held/dense/**",
                                               ["--speed", "8", "--prefix", "held/dense"], timeout=60)
    assert code == 0, err
    assert f"{len(expected)} state" in out and "160 clock" in out, out
    got = [(k, json.loads(p)) for _t, k, p in received]
    states = [p for k, p in got if k.endswith("/state")]
    clocks = [p["tick"] for k, p in got if k == "held/dense/clock"]
    assert clocks == list(range(1, 161))
    assert len(states) == len(expected)
    replayed = {(p["name"], p["tick"]): p["pos_m"] for p in states}
    assert replayed.keys() == expected.keys(), "every copter on every step"
    differ = [k for k in expected if replayed[k] != pytest.approx(expected[k], rel=1e-7, abs=1e-12)]
    assert not differ, f"{len(differ)} states differ from the full log, first {differ[:5]}"


def test_replay_refuses_bad_files_and_speeds(twinswarm_bin, tmp_path):
    good = tmp_path / "good.mcap"
    subprocess.run(
        [str(twinswarm_bin), "run", "--no-bus", "--duration", "0.5", "--log", str(good)],
        check=True, capture_output=True, timeout=60,
    )
    empty = tmp_path / "empty.mcap"
    empty.write_bytes(b"")
    text = tmp_path / "text.mcap"
    text.write_text("not an mcap file\n")
    truncated = tmp_path / "truncated.mcap"
    truncated.write_bytes(good.read_bytes()[:3000])
    cases = [
        ([str(empty)], "empty"),
        ([str(text)], "not an MCAP file"),
        ([str(truncated)], "truncated"),
        ([str(tmp_path / "missing.mcap")], "cannot read"),
        ([str(good), "--speed", "0"], "--speed"),
        ([str(good), "--speed", "-1"], "--speed"),
        ([str(good), "--speed", "nan"], "--speed"),
        ([str(good), "--speed", "inf"], "--speed"),
    ]
    for args, needle in cases:
        r = subprocess.run([str(twinswarm_bin), "replay", *args], capture_output=True, text=True, timeout=30)
        assert r.returncode == 2, (args, r.returncode, r.stderr)
        assert needle in r.stderr and "panicked" not in r.stderr, (args, r.stderr)
