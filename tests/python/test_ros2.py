"""ROS 2 over Zenoh (`twinswarm run --ros2`), checked by independent peers with no ROS install:
eclipse-zenoh for the session and the graph, rosbags' Jazzy type store for CDR and RIHS01, and
zenoh-ros2-sdk, a third-party rmw_zenoh-compatible client. Formats: ros2/rmw_zenoh
docs/design.md (Jazzy, rmw_zenoh_cpp >= 0.2.4)."""
import json
import math
import os
import struct
import subprocess
import sys
import textwrap
import time
import uuid

import numpy as np
import pytest
import xxhash
import zenoh
from rosbags.typesys import Stores, get_typestore

from conftest import free_tcp_port, zenoh_client_config

TS = get_typestore(Stores.ROS2_JAZZY)
QOS_COUNTS = [1, 1, 2, 2, 2, 3]  # comma-separated pieces of each ':'-separated QoS policy


def start(twinswarm_bin, endpoint, duration, *args, scene=None):
    return subprocess.Popen(
        [str(twinswarm_bin), "run", *([str(scene)] if scene else []), "--realtime", "--json", "--no-log", "--ros2",
         "--listen", endpoint, "--duration", str(duration), *args],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE)


def finish(proc, timeout=60):
    out, err = proc.communicate(timeout=timeout)
    assert proc.returncode == 0, err.decode()[-3000:]
    return json.loads(out)


def ros_type(dds):
    """`pkg::msg::dds_::Name_` -> `pkg/msg/Name`."""
    pkg, kind, _, name = dds.split("::")
    assert name.endswith("_"), dds
    return f"{pkg}/{kind}/{name[:-1]}"


def graph(session, timeout=10.0, want=1):
    """The domain-0 liveliness tokens, once at least `want` are there."""
    end = time.monotonic() + timeout
    while True:
        keys = [str(r.ok.key_expr) for r in session.liveliness().get("@ros2_lv/0/**", timeout=2.0) if r.ok]
        if len(keys) >= want or time.monotonic() > end:
            return keys
        time.sleep(0.2)


def parse_token(key):
    """A liveliness token as design.md lays it out: (kind, node, topic, type, hash, qos)."""
    parts = key.split("/")
    assert parts[0] == "@ros2_lv" and parts[1] == "0", key
    assert all(parts), f"empty part in {key}"
    assert all(c in "0123456789abcdef" for c in parts[2]) and len(parts[2]) <= 32, key
    int(parts[3]), int(parts[4])
    kind = parts[5]
    assert (parts[6], parts[7], parts[8]) == ("%", "%", "twinswarm"), key  # enclave /, namespace /, name
    if kind == "NN":
        assert len(parts) == 9 and parts[3] == parts[4], key
        return kind, None, None, None, None
    assert kind in ("MP", "MS") and len(parts) == 13, key
    topic = parts[9].replace("%", "/")
    qos = parts[12].split(":")
    assert [len(q.split(",")) for q in qos] == QOS_COUNTS, key
    return kind, topic, ros_type(parts[10]), parts[11], parts[12]


def data_key(topic, typ):
    dds = "{}::{}::dds_::{}_".format(*typ.split("/"))
    return f"0/{topic.lstrip('/')}/{dds}/{TS.hash_rihs01(typ)}"


class Samples:
    """Every sample on some keys: (key, payload, attachment), in arrival order; with `topics`
    ({topic: type}, keys in the same order), a ROS subscription: each also has its token in the
    graph, as rmw_zenoh declares it (the simulator sends only what the graph asks for)."""

    def __init__(self, session, keys, topics=None):
        self.got = {k: [] for k in keys}
        self.subs = [session.declare_subscriber(k, self._on(k)) for k in keys]
        zid = str(session.info.zid())
        self.tokens = [session.liveliness().declare_token(entity_token(zid, "MS", t, ty, eid=k + 1, node="pytest_sub",
                                                                      qos="2::,5:,:,:,,"))
                       for k, (t, ty) in enumerate((topics or {}).items())]

    def _on(self, key):
        def cb(s):
            att = s.attachment.to_bytes() if s.attachment is not None else None
            self.got[key].append((bytes(s.payload.to_bytes()), att))
        return cb


def stamp_s(stamp):
    return stamp.sec + stamp.nanosec * 1e-9


def f32(x):
    return struct.unpack("<f", struct.pack("<f", x))[0]


def quat_of_rpy(r, p, y):
    cr, sr, cp, sp, cy, sy = (math.cos(r / 2), math.sin(r / 2), math.cos(p / 2), math.sin(p / 2),
                              math.cos(y / 2), math.sin(y / 2))
    return (sr * cp * cy - cr * sp * sy, cr * sp * cy + sr * cp * sy, cr * cp * sy - sr * sp * cy,
            cr * cp * cy + sr * sp * sy)


def test_the_swarm_is_a_ros2_node_its_graph_and_messages_as_rmw_zenoh_and_rosbags_read_them(twinswarm_bin):
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    proc = start(twinswarm_bin, endpoint, 12, "--prefix", "ros2test/lab")
    session = zenoh.open(zenoh_client_config(endpoint))
    try:
        per_copter = ["pose", "odom", "imu", "sonar/front", "sonar/right", "sonar/back", "sonar/left", "ir",
                      "battery"]
        expected_pub = {"/clock", "/tf", "/tf_static", "/arena"} | {f"/{c}/{t}" for c in ("finken1", "finken2")
                                                                    for t in per_copter}
        keys = graph(session, want=1 + len(expected_pub) + 4)
        tokens = [parse_token(k) for k in keys]
        assert sum(t[0] == "NN" for t in tokens) == 1, keys
        pubs = {t[1]: t for t in tokens if t[0] == "MP"}
        subs = {t[1]: t for t in tokens if t[0] == "MS"}
        assert set(pubs) == expected_pub, sorted(pubs)
        assert set(subs) == {"/finken1/cmd_vel", "/finken1/goal_pose", "/finken2/cmd_vel", "/finken2/goal_pose"}
        for kind, topic, typ, hsh, qos in list(pubs.values()) + list(subs.values()):
            assert hsh == TS.hash_rihs01(typ), (topic, typ)
        assert pubs["/arena"][4] == ":1:,1:,:,:,,", "reliable, transient local, keep last 1"
        assert pubs["/finken1/pose"][4].startswith("2:"), "sensor data is best effort"

        topics = {"/finken1/pose": "geometry_msgs/msg/PoseStamped", "/finken1/imu": "sensor_msgs/msg/Imu",
                  "/clock": "rosgraph_msgs/msg/Clock", "/tf": "tf2_msgs/msg/TFMessage",
                  **{f"/finken1/sonar/{s}": "sensor_msgs/msg/Range" for s in ("front", "right", "back", "left")}}
        ros = Samples(session, [data_key(t, ty) for t, ty in topics.items()], topics)
        state = Samples(session, ["ros2test/lab/copters/finken1/state", "ros2test/lab/copters/finken1/sensors"])
        time.sleep(3.0)
        del ros.subs, ros.tokens, state.subs
    finally:
        session.close()
    summary = finish(proc)
    assert summary["bus"]["ros2"]["sent"] > 0

    # Attachments: 33 bytes, sequence numbers increasing by one per publisher, a 16-byte GID:
    # rmw_zenoh_cpp's, the XXH3-128 of the publisher's token (low 64 bits first, little-endian).
    token_of = {data_key(topic, typ): key for key, (kind, topic, typ, _, _) in zip(keys, tokens) if kind == "MP"}
    for key, samples in ros.got.items():
        assert len(samples) >= 2, f"few samples on {key}"
        gid = xxhash.xxh3_128_digest(token_of[key].encode())[::-1]
        seqs = []
        for _, att in samples:
            assert att is not None and len(att) == 33 and att[16] == 16, key
            assert att[17:] == gid, (key, att[17:].hex(), gid.hex())
            seq, ts_ns = struct.unpack_from("<qq", att)
            assert ts_ns > 1.6e18, "wall-clock ns"
            seqs.append(seq)
        assert seqs == list(range(seqs[0], seqs[0] + len(seqs))), (key, seqs[:10])

    states = {round(json.loads(p)["time_s"], 6): json.loads(p) for p, _ in state.got["ros2test/lab/copters/finken1/state"]}
    sensors = {round(json.loads(p)["time_s"], 6): json.loads(p) for p, _ in state.got["ros2test/lab/copters/finken1/sensors"]}
    decoded = {t: [TS.deserialize_cdr(p, ty) for p, _ in ros.got[data_key(t, ty)]] for t, ty in topics.items()}

    matched = 0
    for m in decoded["/finken1/pose"]:
        s = states.get(round(stamp_s(m.header.stamp), 6))
        if s is None:
            continue
        matched += 1
        assert m.header.frame_id == "world"
        p, q = m.pose.position, m.pose.orientation
        assert [p.x, p.y, p.z] == [f32(v) for v in s["pos_m"]]
        assert [q.x, q.y, q.z, q.w] == [f32(v) for v in s["quat_xyzw"]]
    assert matched >= 5, f"{matched} poses matched a state of the same time"

    matched = 0
    for m in decoded["/finken1/imu"]:
        s = sensors.get(round(stamp_s(m.header.stamp), 6))
        if s is None:
            continue
        matched += 1
        assert m.header.frame_id == "finken1/base_link"
        a = m.angular_velocity
        assert [a.x, a.y, a.z] == [f32(v) for v in s["rate_body_rad_s"]]
        la = m.linear_acceleration
        assert [la.x, la.y, la.z] == [f32(v) for v in s["accel_body_m_s2"]]
        q = quat_of_rpy(*s["attitude_rad"])
        o = m.orientation
        assert np.allclose([o.x, o.y, o.z, o.w], q, atol=1e-6), ([o.x, o.y, o.z, o.w], q)
    assert matched >= 5

    # Ranges: each sonar on its own turn (the firmware's round robin), the reading of its tick.
    ranges = 0
    for side in ("front", "right", "back", "left"):
        for m in decoded[f"/finken1/sonar/{side}"]:
            s = sensors.get(round(stamp_s(m.header.stamp), 6))
            assert m.header.frame_id == f"finken1/sonar_{side}"
            assert m.radiation_type == 0 and m.min_range == pytest.approx(0.2) and m.field_of_view > 0
            if s is None:
                continue
            ranges += 1
            want = f32(s["sonar_m"][side])
            assert m.range == (math.inf if want >= m.max_range else want), (side, m.range, want)
    assert ranges >= 4
    stamps = {side: sorted(stamp_s(m.header.stamp) for m in decoded[f"/finken1/sonar/{side}"])
              for side in ("front", "right", "back", "left")}
    for side, ts in stamps.items():
        gaps = np.diff(ts)
        assert np.allclose(gaps, 0.2, atol=1e-6), (side, gaps[:5])  # 5 Hz each

    clocks = [stamp_s(m.clock) for m in decoded["/clock"]]
    assert clocks == sorted(clocks) and np.allclose(np.diff(clocks), 0.05, atol=1e-6)
    tf_matched = 0
    for m in decoded["/tf"]:
        by_child = {t.child_frame_id: t for t in m.transforms}
        assert set(by_child) == {"finken1/base_link", "finken2/base_link"}
        t = by_child["finken1/base_link"]
        assert t.header.frame_id == "world"
        s = states.get(round(stamp_s(t.header.stamp), 6))
        if s is not None:
            tf_matched += 1
            tr = t.transform.translation
            assert [tr.x, tr.y, tr.z] == [f32(v) for v in s["pos_m"]]
    assert tf_matched >= 5


def entity_token(zid, kind, topic, typ, eid=1, node="pytest_teleop", qos="::,10:,:,:,,"):
    """The token of a publisher (MP) or subscription (MS) of node 0 of session `zid`."""
    dds = "{}::{}::dds_::{}_".format(*typ.split("/"))
    return (f"@ros2_lv/0/{zid}/0/{eid}/{kind}/%/%/{node}/{topic.replace('/', '%')}/{dds}/{TS.hash_rihs01(typ)}"
            f"/{qos}")


def publisher_token(zid, topic, typ, node="pytest_teleop"):
    return entity_token(zid, "MP", topic, typ, node=node)


def test_a_twist_on_cmd_vel_flies_the_copter_where_it_says(twinswarm_bin, tmp_path):
    scene = tmp_path / "open_hall.toml"
    scene.write_text(textwrap.dedent("""\
        name = "hall"
        [arena]
        size_m = [12.0, 12.0]
        height_m = 3.0
        [[copter]]
        name = "finken1"
        start = { pos_m = [-3.0, 0.0], z_m = 0.8, yaw_deg = 0.0 }
        mode = "velocity"
        command = { height_m = 0.8, velocity_m_s = [0.0, 0.0] }
        """))
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    proc = start(twinswarm_bin, endpoint, 14, "--prefix", "ros2cmd/hall", scene=scene)
    session = zenoh.open(zenoh_client_config(endpoint))
    try:
        zid = str(session.info.zid())
        node = session.liveliness().declare_token(f"@ros2_lv/0/{zid}/0/0/NN/%/%/pytest_teleop")
        typ = "geometry_msgs/msg/Twist"
        token = session.liveliness().declare_token(publisher_token(zid, "/finken1/cmd_vel", typ))
        pub = session.declare_publisher(data_key("/finken1/cmd_vel", typ))
        states = Samples(session, ["ros2cmd/hall/copters/finken1/state"])
        graph(session, want=10)
        time.sleep(2.0)
        Twist, Vector3 = TS.types[typ], TS.types["geometry_msgs/msg/Vector3"]
        gid = uuid.uuid4().bytes
        start_pos = json.loads(states.got["ros2cmd/hall/copters/finken1/state"][-1][0])["pos_m"]
        # Forward 0.4 m/s, climbing 0.1 m/s, for 4 s, at 10 Hz.
        msg = Twist(linear=Vector3(x=0.4, y=0.0, z=0.1), angular=Vector3(x=0.0, y=0.0, z=0.0))
        payload = bytes(TS.serialize_cdr(msg, typ))
        for seq in range(1, 41):
            att = struct.pack("<qq", seq, time.time_ns()) + bytes([16]) + gid
            pub.put(payload, attachment=att)
            time.sleep(0.1)
        end_pos = json.loads(states.got["ros2cmd/hall/copters/finken1/state"][-1][0])["pos_m"]
        del states.subs, pub, token, node
    finally:
        session.close()
    summary = finish(proc)
    dx, dy, dz = (end_pos[k] - start_pos[k] for k in range(3))
    assert dx > 0.8, f"moved {dx:.2f} m forward"
    assert abs(dy) < 0.5 * dx, f"and {dy:.2f} m sideways"
    assert dz > 0.15, f"climbed {dz:.2f} m"
    assert summary["bus"]["commands_accepted"] >= 38, summary["bus"]


SDK_CLIENT = r'''
import json, os, sys, time
from rosbags.typesys import get_types_from_msg
from zenoh_ros2_sdk import ROS2Subscriber, ZenohSession, get_topic_names_and_types
port = int(sys.argv[1])
sm = ZenohSession.get_instance("127.0.0.1", port)
for name, d in {
    "builtin_interfaces/msg/Time": "int32 sec\nuint32 nanosec\n",
    "std_msgs/msg/Header": "builtin_interfaces/Time stamp\nstring frame_id\n",
    "geometry_msgs/msg/Point": "float64 x\nfloat64 y\nfloat64 z\n",
    "geometry_msgs/msg/Quaternion": "float64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1\n",
    "geometry_msgs/msg/Pose": "Point position\nQuaternion orientation\n",
}.items():
    sm.store.register(get_types_from_msg(d, name))
topics = dict((t, types) for t, types in get_topic_names_and_types(domain_id=0, router_ip="127.0.0.1",
                                                                   router_port=port, timeout=2.0))
got = []
sub = ROS2Subscriber(topic="/finken1/pose", msg_type="geometry_msgs/msg/PoseStamped",
                     msg_definition="std_msgs/Header header\nPose pose\n", type_hash=sys.argv[2],
                     callback=lambda m: got.append((m.header.frame_id, m.pose.position.z)),
                     node_name="sdk_listener", domain_id=0, router_ip="127.0.0.1", router_port=port)
time.sleep(2.0)
print(json.dumps({"topics": topics, "poses": got[:50], "count": len(got)}))
os._exit(0)
'''


def test_zenoh_ros2_sdk_finds_the_topics_and_receives_poses(twinswarm_bin, tmp_path):
    port = free_tcp_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    # The SDK's own session: loopback only, multicast scouting off (its default config listens on
    # every interface and connects to localhost:7447).
    config = tmp_path / "sdk.json5"
    config.write_text(json.dumps({"mode": "peer", "scouting": {"multicast": {"enabled": False}},
                                  "listen": {"endpoints": ["tcp/127.0.0.1:0"]},
                                  "connect": {"endpoints": [endpoint]}}))
    proc = start(twinswarm_bin, endpoint, 10)
    try:
        time.sleep(2.0)
        env = {**os.environ, "ZENOH_SESSION_CONFIG_URI": str(config)}
        out = subprocess.run([sys.executable, "-c", SDK_CLIENT, str(port),
                              TS.hash_rihs01("geometry_msgs/msg/PoseStamped")],
                             capture_output=True, env=env, timeout=60)
        assert out.returncode == 0, out.stderr.decode()[-3000:]
        result = json.loads(out.stdout.decode().strip().splitlines()[-1])
    finally:
        finish(proc)
    topics = result["topics"]
    assert topics.get("/finken1/pose") == ["geometry_msgs/msg/PoseStamped"], topics
    assert topics.get("/finken2/imu") == ["sensor_msgs/msg/Imu"], topics
    assert topics.get("/finken1/cmd_vel") == ["geometry_msgs/msg/Twist"], topics
    assert result["count"] >= 10, result
    assert all(frame == "world" and 0.0 < z < 3.0 for frame, z in result["poses"]), result["poses"][:5]
