"""Crazyswarm2-style swarm script over ROS 2: every copter of a running `twinswarm run --ros2`
flies a circle, commanded through its `/<copter>/cmd_vel`, then hovers.

It speaks ROS 2 through zenoh-ros2-sdk (an rmw_zenoh-compatible client, `pip install
zenoh-ros2-sdk`), so it runs without a ROS 2 install; an rclpy node with
`RMW_IMPLEMENTATION=rmw_zenoh_cpp` publishing the same Twists does the same (docs/ros2.md).

    twinswarm run --ros2 --realtime --duration 60 &
    python examples/ros2/swarm_circle.py --seconds 20

Its Zenoh session stays on loopback, with multicast scouting off.
"""
import argparse
import json
import os
import tempfile
import time

TWIST = "geometry_msgs/msg/Twist"
VECTOR3 = "geometry_msgs/msg/Vector3"
# Given explicitly: the SDK would otherwise fetch message definitions from GitHub.
DEFINITIONS = {VECTOR3: "float64 x\nfloat64 y\nfloat64 z\n", TWIST: "Vector3 linear\nVector3 angular\n"}


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--port", type=int, default=7447, help="the simulator's Zenoh port on 127.0.0.1")
    ap.add_argument("--domain", type=int, default=0, help="ROS domain id (twinswarm run --ros-domain)")
    ap.add_argument("--seconds", type=float, default=20.0, help="how long to fly the circle")
    ap.add_argument("--speed", type=float, default=0.3, help="forward speed, m/s")
    ap.add_argument("--radius", type=float, default=0.8, help="circle radius, m")
    args = ap.parse_args()

    config = tempfile.NamedTemporaryFile("w", suffix=".json5", delete=False)
    json.dump({"mode": "peer", "scouting": {"multicast": {"enabled": False}},
               "listen": {"endpoints": ["tcp/127.0.0.1:0"]}}, config)
    config.close()
    os.environ["ZENOH_SESSION_CONFIG_URI"] = config.name

    from rosbags.typesys import Stores, get_typestore, get_types_from_msg
    from zenoh_ros2_sdk import ROS2Publisher, ZenohSession, get_topic_names_and_types

    twist_hash = get_typestore(Stores.ROS2_JAZZY).hash_rihs01(TWIST)
    session = ZenohSession.get_instance("127.0.0.1", args.port)
    session.store.register(get_types_from_msg(DEFINITIONS[VECTOR3], VECTOR3))
    Vector3 = session.store.types[VECTOR3]

    topics = get_topic_names_and_types(domain_id=args.domain, router_port=args.port, timeout=2.0)
    copters = sorted(t.split("/")[1] for t, types in topics if t.endswith("/cmd_vel") and TWIST in types)
    if not copters:
        raise SystemExit(f"no /<copter>/cmd_vel on domain {args.domain} at 127.0.0.1:{args.port}: "
                         "is `twinswarm run --ros2` running?")
    print(f"{len(copters)} copters: {', '.join(copters)}")
    pubs = {c: ROS2Publisher(topic=f"/{c}/cmd_vel", msg_type=TWIST, msg_definition=DEFINITIONS[TWIST],
                             node_name="swarm_circle", domain_id=args.domain, router_port=args.port,
                             type_hash=twist_hash)
            for c in copters}
    yaw_rate = args.speed / args.radius
    end = time.monotonic() + args.seconds
    while time.monotonic() < end:
        for p in pubs.values():
            p.publish(linear=Vector3(x=args.speed, y=0.0, z=0.0), angular=Vector3(x=0.0, y=0.0, z=yaw_rate))
        time.sleep(0.1)
    for p in pubs.values():
        p.publish(linear=Vector3(x=0.0, y=0.0, z=0.0), angular=Vector3(x=0.0, y=0.0, z=0.0))
    print("done: hovering")
    time.sleep(0.5)
    os.unlink(config.name)
    os._exit(0)


if __name__ == "__main__":
    main()
