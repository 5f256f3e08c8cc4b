"""Attach to a running Twinswarm over Zenoh and fly one copter 0.5 m up.

    python attach_copter.py [PREFIX] [COPTER] [ENDPOINT]
"""
import json, sys
import zenoh

defaults = ["twinswarm/lab", "finken1", "tcp/127.0.0.1:7447"]
prefix, copter, endpoint = sys.argv[1:4] + defaults[len(sys.argv[1:4]):]
conf = zenoh.Config()
conf.insert_json5("mode", '"peer"')
conf.insert_json5("scouting/multicast/enabled", "false")  # loopback only, no multicast
conf.insert_json5("connect/endpoints", json.dumps([endpoint]))

with zenoh.open(conf) as session:
    token = session.liveliness().declare_token(f"{prefix}/alive/copters/{copter}")  # "I am attached"
    states = session.declare_subscriber(f"{prefix}/copters/{copter}/state")
    z0 = json.loads(states.recv().payload.to_bytes())["pos_m"][2]
    session.put(f"{prefix}/copters/{copter}/cmd", json.dumps({"height": z0 + 0.5}))
    for sample in states:
        state = json.loads(sample.payload.to_bytes())
        if abs(state["pos_m"][2] - (z0 + 0.5)) < 0.03:
            print(f"{copter} climbed from {z0:.2f} m to {state['pos_m'][2]:.2f} m at t = {state['time_s']:.2f} s")
            break
    token.undeclare()
