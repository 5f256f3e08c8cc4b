"""Attach to a running Twinswarm over Zenoh, take control of one copter and fly it 0.5 m up.

    python attach_copter.py [PREFIX] [COPTER] [ENDPOINT] [CLIENT]

The liveliness token `<prefix>/alive/copters/<copter>/<client>` claims the copter: while it
lives, only commands naming this client apply (docs/security.md); when this process ends, the
copter's lost-client failsafe takes over.
"""
import json, os, sys
import zenoh

defaults = ["twinswarm/lab", "finken1", "tcp/127.0.0.1:7447", f"attach-{os.getpid()}"]
prefix, copter, endpoint, client = sys.argv[1:5] + defaults[len(sys.argv[1:5]):]
conf = zenoh.Config()
conf.insert_json5("mode", '"peer"')
conf.insert_json5("scouting/multicast/enabled", "false")  # no multicast discovery
conf.insert_json5("listen/endpoints", "[]")  # a pure client: listen on no interface
conf.insert_json5("connect/endpoints", json.dumps([endpoint]))  # only the simulator (loopback by default)

with zenoh.open(conf) as session:
    token = session.liveliness().declare_token(f"{prefix}/alive/copters/{copter}/{client}")  # "mine now"
    states = session.declare_subscriber(f"{prefix}/copters/{copter}/state")
    z0 = json.loads(states.recv().payload.to_bytes())["pos_m"][2]
    session.put(f"{prefix}/copters/{copter}/cmd", json.dumps({"height": z0 + 0.5, "client": client}))
    for sample in states:
        state = json.loads(sample.payload.to_bytes())
        if abs(state["pos_m"][2] - (z0 + 0.5)) < 0.03:
            print(f"{copter} climbed from {z0:.2f} m to {state['pos_m'][2]:.2f} m at t = {state['time_s']:.2f} s")
            break
    token.undeclare()
