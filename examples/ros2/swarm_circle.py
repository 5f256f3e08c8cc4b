"""Crazyswarm2-style swarm script over ROS 2: every copter of a running `twinswarm run --ros2`
flies a circle, commanded through its `/<copter>/cmd_vel`, then hovers.

It speaks ROS 2 through zenoh-ros2-sdk (an rmw_zenoh-compatible client, `pip install
zenoh-ros2-sdk`), so it runs without a ROS 2 install; an rclpy node with
`RMW_IMPLEMENTATION=rmw_zenoh_cpp` publishing the same Twists does the same (docs/ros2.md).

    twinswarm run --ros2 --realtime --duration 60 &
    python examples/ros2/swarm_circle.py --seconds 20

With `--lockstep` it drives a lockstep run instead (docs/ros2.md#claims-and-lockstep): it answers
every `/clock` tick with each copter's Twist, and the simulator waits for the answers, so the
circle is flown at the simulator's speed, the same bits whatever this script's latency. The run
waits for its claims from tick 0, with the copters on the floor, so it climbs for 2 s first:

    twinswarm run --ros2 --lockstep --wait-claims finken1,finken2 --duration 25 &
    python examples/ros2/swarm_circle.py --lockstep --expect 2 --seconds 20

(`--expect 2`: wait until both copters are in the graph, since the run waits for both claims.)

Its Zenoh session stays on loopback, with multicast scouting off.
"""
import argparse
import json
import os
import queue
import tempfile
import time

TWIST = "geometry_msgs/msg/Twist"
VECTOR3 = "geometry_msgs/msg/Vector3"
# Given explicitly: the SDK would otherwise fetch message definitions from GitHub.
CLOCK, TIME = "rosgraph_msgs/msg/Clock", "builtin_interfaces/msg/Time"
DEFINITIONS = {VECTOR3: "float64 x\nfloat64 y\nfloat64 z\n", TWIST: "Vector3 linear\nVector3 angular\n",
               TIME: "int32 sec\nuint32 nanosec\n", CLOCK: "builtin_interfaces/Time clock\n"}


def cmd_vel_topics(session, domain):
    """The copters whose `/<copter>/cmd_vel` (a Twist) a node subscribes to, from the graph's
    tokens. Queried here with a reply channel as large as the graph: the SDK's own listing
    (`get_topic_names_and_types`) waits forever once the graph has more tokens than
    eclipse-zenoh's default reply channel holds (a few hundred: 25 copters' worth)."""
    import zenoh

    replies = session.liveliness.get(f"@ros2_lv/{domain}/**", zenoh.handlers.FifoChannel(1 << 20), timeout=2.0)
    copters = set()
    for reply in replies:
        parts = str(reply.ok.key_expr).split("/") if reply.ok else []
        if len(parts) == 13 and parts[5] == "MS" and parts[10] == "geometry_msgs::msg::dds_::Twist_":
            topic = parts[9].split("%")
            if len(topic) == 3 and topic[2] == "cmd_vel":
                copters.add(topic[1])
    return sorted(copters)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--port", type=int, default=7447, help="the simulator's Zenoh port on 127.0.0.1")
    ap.add_argument("--domain", type=int, default=0, help="ROS domain id (twinswarm run --ros-domain)")
    ap.add_argument("--seconds", type=float, default=20.0, help="how long to fly the circle")
    ap.add_argument("--speed", type=float, default=0.3, help="forward speed, m/s")
    ap.add_argument("--radius", type=float, default=0.8, help="circle radius, m")
    ap.add_argument("--expect", type=int, default=1, help="wait until this many copters are in the graph")
    ap.add_argument("--lockstep", action="store_true",
                    help="answer every /clock tick (twinswarm run --lockstep); --seconds are simulated")
    args = ap.parse_args()

    config = tempfile.NamedTemporaryFile("w", suffix=".json5", delete=False)
    json.dump({"mode": "peer", "scouting": {"multicast": {"enabled": False}},
               "listen": {"endpoints": ["tcp/127.0.0.1:0"]}}, config)
    config.close()
    os.environ["ZENOH_SESSION_CONFIG_URI"] = config.name

    from rosbags.typesys import Stores, get_typestore, get_types_from_msg
    from zenoh_ros2_sdk import ROS2Publisher, ROS2Subscriber, ZenohSession

    store = get_typestore(Stores.ROS2_JAZZY)
    session = ZenohSession.get_instance("127.0.0.1", args.port)
    for name in (VECTOR3, TIME):
        session.store.register(get_types_from_msg(DEFINITIONS[name], name))
    Vector3 = session.store.types[VECTOR3]

    # The simulator declares its graph on idle cores: with many copters, topics appear over seconds.
    deadline = time.monotonic() + 60.0
    while True:
        copters = cmd_vel_topics(session, args.domain)
        if len(copters) >= args.expect or time.monotonic() > deadline:
            break
    if len(copters) < args.expect:
        raise SystemExit(f"{len(copters)} copters' cmd_vel in the graph after 60 s, not --expect {args.expect}")
    if not copters:
        raise SystemExit(f"no /<copter>/cmd_vel on domain {args.domain} at 127.0.0.1:{args.port}: "
                         "is `twinswarm run --ros2` running?")
    print(f"{len(copters)} copters: {', '.join(copters)}")
    ticks = queue.Queue()
    if args.lockstep:
        # Subscribed before the publishers claim the copters: the first /clock it must answer
        # then reaches it.
        clock = ROS2Subscriber(topic="/clock", msg_type=CLOCK, msg_definition=DEFINITIONS[CLOCK],
                               callback=lambda m: ticks.put(m.clock.sec + m.clock.nanosec * 1e-9),
                               node_name="swarm_circle", domain_id=args.domain, router_port=args.port,
                               type_hash=store.hash_rihs01(CLOCK))
    pubs = {c: ROS2Publisher(topic=f"/{c}/cmd_vel", msg_type=TWIST, msg_definition=DEFINITIONS[TWIST],
                             node_name="swarm_circle", domain_id=args.domain, router_port=args.port,
                             type_hash=store.hash_rihs01(TWIST))
            for c in copters}
    yaw_rate = args.speed / args.radius
    circle = dict(linear=Vector3(x=args.speed, y=0.0, z=0.0), angular=Vector3(x=0.0, y=0.0, z=yaw_rate))
    climb = dict(linear=Vector3(x=0.0, y=0.0, z=0.5), angular=Vector3(x=0.0, y=0.0, z=0.0))
    if args.lockstep:
        # One Twist per copter per tick: 2 s of climbing, then --seconds of circling, in
        # simulated time from the first tick.
        first, answered = None, 0
        while True:
            try:
                t = ticks.get(timeout=10.0)
            except queue.Empty:
                raise SystemExit("no /clock for 10 s: is `twinswarm run --ros2 --lockstep` running?")
            if first is None:
                first, began = t, time.perf_counter()
            if t - first >= 2.0 + args.seconds:
                break
            for p in pubs.values():
                p.publish(**(climb if t - first < 2.0 else circle))
            answered += 1
        wall = time.perf_counter() - began
        print(f"lockstep: {answered} ticks answered in {wall:.4f} s: {answered / wall:.0f} ticks/s, "
              f"{(t - first) / wall:.1f}x real time")
        del clock
    else:
        end = time.monotonic() + args.seconds
        while time.monotonic() < end:
            for p in pubs.values():
                p.publish(**circle)
            time.sleep(0.1)
    for p in pubs.values():
        p.publish(linear=Vector3(x=0.0, y=0.0, z=0.0), angular=Vector3(x=0.0, y=0.0, z=0.0))
    print("done: hovering")
    time.sleep(0.5)
    os.unlink(config.name)
    os._exit(0)


if __name__ == "__main__":
    main()
