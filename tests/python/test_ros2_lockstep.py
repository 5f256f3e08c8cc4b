"""ROS 2 controllers and the claim rule (`twinswarm run --ros2`, docs/ros2.md#lockstep): a ROS node
with a publisher on `/<c>/cmd_vel` claims copter `c`, as a Zenoh client's liveliness token does,
and under `--lockstep` each step waits for its answer to the last `/clock`.

The ROS node here is made the way rmw_zenoh_cpp makes one, on eclipse-zenoh: its node token,
subscriptions (with their tokens) to `/clock` and each copter's pose, and one `cmd_vel`
publisher per copter, whose GID is the XXH3-128 of its token (computed by PyPI's `xxhash`, not
by the simulator's code) and rides in each sample's attachment.
"""
import json
import math
import random
import signal
import struct
import subprocess
import threading
import time

import numpy as np
import xxhash
import zenoh

from conftest import free_tcp_port, zenoh_client_config
from test_ros2 import TS, data_key, entity_token, finish

DURATION_S = 4.0
COPTERS = ("finken1", "finken2")
TWIST = "geometry_msgs/msg/Twist"
POSE = "geometry_msgs/msg/PoseStamped"
CLOCK = "rosgraph_msgs/msg/Clock"
PI32, TAU32 = np.float32(math.pi), np.float32(2 * math.pi)


def rmw_gid(token: str) -> bytes:
    """rmw_zenoh_cpp's GID of an entity: XXH3-128 of its token key, low 64 bits first, each
    little-endian (the reverse of xxHash's canonical big-endian digest)."""
    return xxhash.xxh3_128_digest(token.encode())[::-1]


def decide(index: int, tick: int, pos) -> tuple:
    """The controller, a pure function of the copter's pose: towards one of two points,
    switching every 2 s, and towards 1 m up. Returns (forward, left, climb) in m/s."""
    x, y, z = (float(np.float32(v)) for v in pos)
    goal = (0.9, 0.2) if (tick // 40 + index) % 2 == 0 else (-0.9, 0.4)
    clip = lambda v, m: max(-m, min(m, v))  # noqa: E731
    return clip(0.8 * (goal[0] - x), 0.6), clip(0.8 * (goal[1] - y), 0.6), clip(0.8 * (1.0 - z), 0.3)


class RosPilot:
    """One ROS node (`/pilot`) on its own session: subscribes to `/clock` and each copter's pose,
    publishes each copter's `cmd_vel`. Subscriptions are declared before the publishers, as a
    client should (the claim then never comes before the node can hear the clock)."""

    def __init__(self, endpoint, copters, node="pilot"):
        self.session = zenoh.open(zenoh_client_config(endpoint))
        zid = str(self.session.info.zid())
        self.cond = threading.Condition()
        self.clocks, self.poses = [], {}
        lv = self.session.liveliness()
        self.tokens = [lv.declare_token(f"@ros2_lv/0/{zid}/0/0/NN/%/%/{node}")]
        self.subs = [self.session.declare_subscriber(data_key("/clock", CLOCK), self._on_clock)]
        self.tokens.append(lv.declare_token(entity_token(zid, "MS", "/clock", CLOCK, eid=1, node=node,
                                                         qos="2::,1:,:,:,,")))
        for k, c in enumerate(copters):
            self.subs.append(self.session.declare_subscriber(data_key(f"/{c}/pose", POSE), self._on_pose(c)))
            self.tokens.append(lv.declare_token(entity_token(zid, "MS", f"/{c}/pose", POSE, eid=10 + k, node=node,
                                                             qos="2::,5:,:,:,,")))
        self.pubs = {}
        for k, c in enumerate(copters):
            token = entity_token(zid, "MP", f"/{c}/cmd_vel", TWIST, eid=20 + k, node=node)
            self.pubs[c] = [self.session.declare_publisher(data_key(f"/{c}/cmd_vel", TWIST)), rmw_gid(token), 0]
            self.tokens.append(lv.declare_token(token))
        self.client = f"ros2:/{node}@{zid}/0"
        V3 = TS.types["geometry_msgs/msg/Vector3"]
        self._twist = lambda lin: bytes(TS.serialize_cdr(
            TS.types[TWIST](linear=V3(x=lin[0], y=lin[1], z=lin[2]), angular=V3(x=0.0, y=0.0, z=0.0)), TWIST))

    def _on_clock(self, s):
        m = TS.deserialize_cdr(bytes(s.payload.to_bytes()), CLOCK)
        with self.cond:
            self.clocks.append(m.clock.sec * 10**9 + m.clock.nanosec)
            self.cond.notify_all()

    def _on_pose(self, copter):
        def cb(s):
            m = TS.deserialize_cdr(bytes(s.payload.to_bytes()), POSE)
            p = m.pose.position
            with self.cond:
                self.poses[(copter, m.header.stamp.sec * 10**9 + m.header.stamp.nanosec)] = (p.x, p.y, p.z)
                self.cond.notify_all()
        return cb

    def wait(self, what, timeout=30.0):
        with self.cond:
            assert self.cond.wait_for(what, timeout), "nothing came from the simulator"
            return what()

    def send(self, copter, lin):
        pub = self.pubs[copter]
        pub[2] += 1
        pub[0].put(self._twist(lin), attachment=struct.pack("<qq", pub[2], time.time_ns()) + bytes([16]) + pub[1])

    def close(self):
        for t in self.tokens:
            t.undeclare()
        self.session.close()


def fly_ros(pilot, last_tick, jitter_s, seed):
    """Answers each `/clock` tick up to `last_tick` with every copter's Twist, after a random
    delay per copter."""
    rng = random.Random(seed)
    seen = 0
    while True:
        pilot.wait(lambda: len(pilot.clocks) > seen)
        stamp = pilot.clocks[seen]
        seen += 1
        tick = round(stamp / 50e6)
        poses = pilot.wait(lambda: [pilot.poses.get((c, stamp)) for c in COPTERS]
                           if all((c, stamp) in pilot.poses for c in COPTERS) else None)
        for i, c in enumerate(COPTERS):
            time.sleep(rng.uniform(0.0, jitter_s))
            pilot.send(c, decide(i, tick, poses[i]))
        if tick >= last_tick:
            return


def run_sim(twinswarm_bin, endpoint, prefix, *extra):
    return subprocess.Popen(
        [str(twinswarm_bin), "run", "--lockstep", "--wait-claims", ",".join(COPTERS), "--lockstep-timeout", "10",
         "--duration", str(DURATION_S), "--json", "--no-log", "--listen", endpoint, "--prefix", prefix, *extra],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE)


def ros_lockstep_run(twinswarm_bin, jitter_s, seed):
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    proc = run_sim(twinswarm_bin, endpoint, f"roslock-{seed}/lab", "--ros2")
    try:
        time.sleep(0.5)
        pilot = RosPilot(endpoint, COPTERS)
        try:
            # The run's last step answers tick steps - 1; the state after it needs no answer.
            fly_ros(pilot, round(DURATION_S / 0.05) - 1, jitter_s, seed)
            summary = finish(proc)
        finally:
            pilot.close()
    finally:
        if proc.poll() is None:
            proc.kill()
    return summary, pilot.client


def wrap_pi(a):
    """The simulator's `wrap_pi` in f32: (a + π) mod 2π − π."""
    r = np.fmod(np.float32(a) + PI32, TAU32)
    return (r + TAU32 if r < 0 else r) - PI32


def recv(sub, timeout=30.0):
    """The next sample, or a failure that says nothing came."""
    end = time.monotonic() + timeout
    while (sample := sub.try_recv()) is None:
        assert time.monotonic() < end, "no state from the simulator"
        time.sleep(0.0005)
    return sample


def zenoh_mirror_run(twinswarm_bin):
    """The same decisions as JSON commands over the Zenoh lockstep: what the simulator makes of
    a Twist (docs/ros2.md), done here in f32 from the state message's height and yaw."""
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    prefix = "roslock-mirror/lab"
    proc = run_sim(twinswarm_bin, endpoint, prefix)
    last_tick = round(DURATION_S / 0.05)
    try:
        time.sleep(0.5)
        with zenoh.open(zenoh_client_config(endpoint)) as session:
            subs = [session.declare_subscriber(f"{prefix}/copters/{c}/state") for c in COPTERS]
            pubs = [session.declare_publisher(f"{prefix}/copters/{c}/cmd") for c in COPTERS]
            tokens = [session.liveliness().declare_token(f"{prefix}/alive/copters/{c}/mirror") for c in COPTERS]
            for tick in range(last_tick):
                for i, (sub, pub) in enumerate(zip(subs, pubs)):
                    state = json.loads(recv(sub).payload.to_bytes())
                    assert state["tick"] == tick, (state["tick"], tick)
                    fwd, left, climb = decide(i, tick, state["pos_m"])
                    height = np.float32(state["pos_m"][2]) + np.float32(climb)
                    yaw = wrap_pi(state["attitude_rad"][2])
                    pub.put(json.dumps({"mode": "velocity", "velocity": [fwd, left], "height": float(height),
                                        "yaw": float(yaw), "tick": tick, "client": "mirror"}))
            summary = finish(proc)
            del tokens
    finally:
        if proc.poll() is None:
            proc.kill()
    return summary


def test_a_ros_node_drives_the_lockstep_answering_clock_ticks(twinswarm_bin):
    a, client = ros_lockstep_run(twinswarm_bin, jitter_s=0.020, seed=1)
    b, _ = ros_lockstep_run(twinswarm_bin, jitter_s=0.020, seed=2)
    steps = round(DURATION_S / 0.05)
    for s in (a, b):
        ls = s["lockstep"]
        assert s["control_steps"] == steps
        assert ls["timeouts"] == {} and ls["late"] == 0 and ls["refused"] == 0, ls
        assert ls["answers"] == len(COPTERS) * steps, ls
        assert ls["wait_s"] > 0.2, "the pilot's sleeps held the steps"
        assert s["bus"]["commands_not_controller"] == 0, s["bus"]
    digests = [c["digest"] for c in a["copters"]]
    assert digests == [c["digest"] for c in b["copters"]], "latency changed the run"
    mirror = zenoh_mirror_run(twinswarm_bin)
    assert mirror["lockstep"]["answers"] == len(COPTERS) * steps, mirror["lockstep"]
    assert [c["digest"] for c in mirror["copters"]] == digests, "the ROS run differs from its Zenoh mirror"
    final = np.array([c["final_pos_m"][:2] for c in a["copters"]])
    assert np.abs(final - np.array([[-0.8, 0.0], [0.8, 0.0]])).max() > 0.3, "they flew"


def test_a_ros_publisher_claims_its_copter_and_others_are_refused(twinswarm_bin):
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    proc = subprocess.Popen(
        [str(twinswarm_bin), "run", "--ros2", "--realtime", "--duration", "120", "--json", "--no-log",
         "--listen", endpoint, "--prefix", "rosclaim/lab"], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        time.sleep(0.5)
        owner = RosPilot(endpoint, ["finken1"], node="owner")
        other = RosPilot(endpoint, ["finken1"], node="other")
        time.sleep(1.5)
        for _ in range(10):
            owner.send("finken1", (0.2, 0.0, 0.0))
            other.send("finken1", (-0.2, 0.0, 0.0))
            time.sleep(0.05)
        time.sleep(0.5)
        owner.close()
        time.sleep(1.0)
        for _ in range(5):
            other.send("finken1", (-0.2, 0.0, 0.0))
            time.sleep(0.05)
        time.sleep(0.5)
        other.close()
        proc.send_signal(signal.SIGINT)  # ends the run after the current step, summary and all
        out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, err.decode()[-3000:]
    bus = json.loads(out)["bus"]
    # The first node claimed finken1: the other's ten were refused; once the owner left, the
    # other's claim, queued behind it, took over and its five were taken.
    assert bus["commands_not_controller"] == 10, bus
    assert bus["commands_accepted"] == 15, bus
    err = err.decode()
    assert f'is controlled by client "{owner.client}", not "{other.client}"' in err, err[-3000:]
    handover = [err.find(f'finken1: now controlled by "{c}"') for c in (owner.client, other.client)]
    assert 0 <= handover[0] < handover[1], err[-3000:]
