"""A swarm sharded over processes, seen from outside (docs/sharding.md):

1. One bus for clients: two shard processes on loopback (peer to peer), an eclipse-zenoh
   client sees every copter's state on the usual keys, and its commands reach a copter on
   whichever shard holds it, before and after the copter crosses the border.
2. The logs: each shard's MCAP, merged by `twinswarm log merge`, is the one-process log of
   the swarm: every copter's state once per step, byte for byte the same, read back by the
   independent `mcap` reader with CRC validation.
"""
import json
import subprocess
import time

import zenoh

from conftest import free_tcp_port, log_messages, zenoh_client_config


def flock(twinswarm_bin, tmp_path):
    """`twinswarm scene flock` with free-running sonars and the PD Wall-Avoid, the flock these
    tests were written for: crashes within seconds (with the firmware's round robin no two of
    its copters meet), and a copter that goes where it is sent (the firmware's Wall-Avoid holds
    a pilot's input back near anything its filtered sonars see, cross-talk echoes included)."""
    path = tmp_path / "flock.toml"
    text = subprocess.run(
        [str(twinswarm_bin), "scene", "flock", "--n", "144", "--seed", "3"],
        check=True, capture_output=True, text=True,
    ).stdout
    for old, new in [('schedule = "round_robin"', 'schedule = "together"'),
                     ("cycle_s = 0.2\n", "cycle_s = 0.049\n"), ("cycle_spread = 0.00005", "cycle_spread = 0.002"),
                     ('controller = "firmware"', 'controller = "pd"')]:
        assert text.count(old) == 1, old
        text = text.replace(old, new)
    path.write_text(text)
    return path


def wait(what, cond, timeout, extra=None):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if cond():
            return
        time.sleep(0.05)
    raise AssertionError(f"timed out: {what}: {extra() if extra else ''}")


def test_one_bus_for_clients_and_commands_follow_a_migrating_copter(twinswarm_bin, tmp_path):
    scene = flock(twinswarm_bin, tmp_path)
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    prefix = f"shards-{endpoint.rsplit(':', 1)[1]}/flock"
    common = [str(twinswarm_bin), "run", str(scene), "--realtime", "--json", "--no-log",
              "--duration", "20", "--prefix", prefix]
    s0 = subprocess.Popen(common + ["--shard", "0/2", "--listen", endpoint],
                          stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    time.sleep(0.5)
    s1 = subprocess.Popen(common + ["--shard", "1/2", "--connect", endpoint],
                          stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        latest = {}

        def on_state(sample):
            msg = json.loads(sample.payload.to_bytes())
            latest[msg["name"]] = msg

        with zenoh.open(zenoh_client_config(endpoint)) as session:
            sub = session.declare_subscriber(f"{prefix}/copters/*/state", on_state)
            wait("every copter's state, from one shard or the other", lambda: len(latest) == 144, 20)
            # c67 starts 4 m left of the border (x = 0) in shard 0's strip: sent right at 1 m/s.
            assert latest["c67"]["pos_m"][0] < -3.0, latest["c67"]
            key = f"{prefix}/copters/c67/cmd"
            session.put(key, json.dumps({"velocity": [1.0, 0.0]}))
            wait("c67 crossing into shard 1's strip", lambda: latest["c67"]["pos_m"][0] > 1.0, 10)
            # Now shard 1 steps it: this command must reach shard 1.
            # (Down from its 1 m: the FINken holds height on its IR, whose table ends at 1.3 m.)
            session.put(key, json.dumps({"velocity": [0.0, 0.0], "height": 0.6}))
            wait("c67 descending (height 0.6 m) on its new shard", lambda: latest["c67"]["pos_m"][2] < 0.75, 8, lambda: latest["c67"])
            sub.undeclare()
        out0, err0 = s0.communicate(timeout=60)
        out1, err1 = s1.communicate(timeout=60)
    finally:
        for p in (s0, s1):
            if p.poll() is None:
                p.kill()
    assert s0.returncode == 0, err0
    assert s1.returncode == 0, err1
    r0, r1 = json.loads(out0), json.loads(out1)
    names0 = {c["name"] for c in r0["copters"]}
    names1 = {c["name"] for c in r1["copters"]}
    assert not names0 & names1, "no copter is on two shards"
    assert len(names0 | names1) == 144
    assert "c67" in names1, "c67 ended on shard 1"
    c67 = next(c for c in r1["copters"] if c["name"] == "c67")
    assert c67["final_pos_m"][2] < 0.75, c67
    for r in (r0, r1):
        assert r["shard"]["shards"] == 2 and r["shard"]["error"] is None
        assert r["shard"]["link"]["exchanges"] == r["control_steps"]
    assert r1["shard"]["taken_over"] >= 1


def test_merged_shard_logs_are_the_one_process_log(twinswarm_bin, tmp_path):
    scene = flock(twinswarm_bin, tmp_path)
    one = tmp_path / "one.mcap"
    subprocess.run([str(twinswarm_bin), "run", str(scene), "--no-bus", "--duration", "10", "--json",
                    "--log", str(one)], check=True, capture_output=True)
    logs = tmp_path / "shards"
    cluster = subprocess.run([str(twinswarm_bin), "cluster", str(scene), "--shards", "3", "--duration", "10",
                              "--no-bus", "--json", "--log-dir", str(logs)], capture_output=True, text=True)
    assert cluster.returncode == 0, cluster.stderr
    inputs = sorted(logs.glob("shard-*-of-3.mcap"))
    assert len(inputs) == 3
    merged = tmp_path / "merged.mcap"
    subprocess.run([str(twinswarm_bin), "log", "merge", "-o", str(merged), *map(str, inputs)],
                   check=True, capture_output=True)

    def states(path):
        by_step = {}
        for _channel, message, body in log_messages(path, ["/copters/state"]):
            key = (body["tick"], body["id"])
            assert key not in by_step, f"{path.name}: {key} twice"
            by_step[key] = (message.data, {k: v for k, v in body.items() if k not in ("tick", "t_s")})
        return by_step

    a, b = states(one), states(merged)
    # Every step of every copter, except that a wreck at rest is held (`--log-unchanged`).
    assert len({tick for tick, _id in a}) == 200 and len({i for _tick, i in a}) == 144
    assert len(a) < 144 * 200, "wrecks at rest held"
    assert a.keys() <= b.keys()
    differ = [k for k in a if a[k][0] != b[k][0]]
    assert not differ, f"{len(differ)} states differ, first {differ[:5]}"
    # A shard writes a copter again on the step it takes it over, where the one-process log
    # holds it: the same values, that step's tick.
    for tick, i in sorted(b.keys() - a.keys()):
        before = max(t for t, j in a if j == i and t < tick)
        assert b[(tick, i)][1] == a[(before, i)][1], f"copter {i} at tick {tick}: not the held state"

    def events(path):
        return sorted((e["tick"], e["copter"], e["kind"]) for e in
                      (body for _c, _m, body in log_messages(path, ["/events"])) if e["kind"] in ("took_off", "crashed"))

    assert events(one) == events(merged)
    assert any(kind == "crashed" for _t, _c, kind in events(one)), "crashes to agree on"
