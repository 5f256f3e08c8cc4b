"""The live view (`twinswarm run --foxglove ADDR`) seen by an independent client of the Foxglove
WebSocket protocol (PyPI `websockets`), spec:
https://github.com/foxglove/ws-protocol/blob/main/docs/spec.md

Each run listens on a free loopback port. The live messages are checked against the run's own
MCAP log (PyPI `mcap`, CRCs validated): the same bytes at the same timestamp, i.e. the
simulator's state at that tick.
"""

import asyncio
import base64
import json
import struct
import subprocess
import time

import pytest
import websockets
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
from mcap.reader import make_reader

from conftest import free_tcp_port

SUBPROTOCOL = "foxglove.websocket.v1"


def start_run(twinswarm_bin, port, *args):
    return subprocess.Popen(
        [str(twinswarm_bin), "run", "--no-bus", "--realtime", "--json", "--foxglove", f"127.0.0.1:{port}", *map(str, args)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


async def connect(port, deadline_s=20.0, **kw):
    """Connects once the server listens (the run starts it before its first step)."""
    t0 = time.monotonic()
    while True:
        try:
            return await websockets.connect(f"ws://127.0.0.1:{port}", subprotocols=[SUBPROTOCOL], **kw)
        except OSError:
            if time.monotonic() - t0 > deadline_s:
                raise
            await asyncio.sleep(0.05)


async def hello(ws):
    """serverInfo, then the advertisement: {topic: channel}."""
    info = json.loads(await ws.recv())
    assert info["op"] == "serverInfo" and info["name"].startswith("twinswarm"), info
    assert "time" in info["capabilities"]
    adv = json.loads(await ws.recv())
    assert adv["op"] == "advertise", adv
    return info, {c["topic"]: c for c in adv["channels"]}


def message_class(channel):
    """The protobuf class of an advertised channel, from its schema (base64 FileDescriptorSet)."""
    fds = descriptor_pb2.FileDescriptorSet.FromString(base64.b64decode(channel["schema"]))
    pool = descriptor_pool.DescriptorPool()
    for f in fds.file:
        pool.Add(f)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(channel["schemaName"]))


def epoch_ns(log):
    """Tick 0's log time, from the log's `twinswarm` metadata."""
    with open(log, "rb") as f:
        meta = {m.name: dict(m.metadata) for m in make_reader(f).iter_metadata()}
    return int(meta["twinswarm"]["epoch_unix_ns"])


def finish(proc, timeout=60):
    out, err = proc.communicate(timeout=timeout)
    assert proc.returncode == 0, err
    return json.loads(out)


def test_live_client_sees_the_simulator_state(twinswarm_bin, tmp_path):
    port = free_tcp_port()
    log = tmp_path / "live.mcap"
    proc = start_run(twinswarm_bin, port, "--duration", "5", "--log", log)
    topics = ["/scene/arena", "/scene/copters", "/tf", "/copters/state"]

    async def client():
        async with await connect(port) as ws:
            assert ws.subprotocol == SUBPROTOCOL
            _info, channels = await hello(ws)
            for t in topics + ["/copters/sensors", "/events"]:
                assert t in channels, sorted(channels)
            assert channels["/copters/state"]["schemaName"] == "twinswarm.CopterState"
            assert channels["/scene/copters"]["schemaName"] == "foxglove.SceneUpdate"
            assert channels["/tf"]["schemaName"] == "foxglove.FrameTransform"
            for ch in channels.values():
                assert ch["encoding"] == "protobuf" and ch["schemaEncoding"] == "protobuf", ch["topic"]
            subs = {k + 1: channels[t] for k, t in enumerate(topics)}
            await ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                {"id": sid, "channelId": ch["id"]} for sid, ch in subs.items()]}))
            got, times = [], []
            t0 = time.monotonic()
            while time.monotonic() - t0 < 2.0:
                m = await asyncio.wait_for(ws.recv(), 5)
                assert isinstance(m, bytes), m
                # A client of the `time` capability stamps messages with the server's clock
                # (Foxglove Studio takes 0 before the first): the time comes first.
                assert got or times or m[0] == 2, "the first binary frame is the time (op 2)"
                if m[0] == 2:
                    times.append(struct.unpack_from("<Q", m, 1)[0])
                    continue
                assert m[0] == 1, m[:1]
                sid, ts = struct.unpack_from("<IQ", m, 1)
                got.append((subs[sid]["topic"], ts, m[13:]))
            return got, times, channels

    got, times, channels = asyncio.run(client())
    summary = finish(proc)
    live = summary["live"]
    assert live["clients"] == 1 and live["subscriptions"] == 4, live
    assert live["protocol_errors"] == 0 and live["messages_dropped"] == 0, live
    assert times and times == sorted(times), "time messages each step, in order"

    by_topic = {}
    for topic, ts, data in got:
        by_topic.setdefault(topic, []).append((ts, data))
    assert len(by_topic["/scene/arena"]) == 1, "the static scene is latched: sent once on subscribe"
    # Foxglove's messages decode with PyPI foxglove-schemas-protobuf; ours with the schema the
    # server advertised (a base64 FileDescriptorSet), as a Foxglove client does.
    arena = SceneUpdate.FromString(by_topic["/scene/arena"][0][1])
    assert any(e.cubes for e in arena.entities), "walls and boxes"
    CopterState = message_class(channels["/copters/state"])
    assert len(by_topic["/copters/state"]) >= 20 * 4, "four copters for a second or more"

    # Every live message is in the log, same timestamp, same bytes.
    logged = set()
    with open(log, "rb") as f:
        for _s, channel, msg in make_reader(f, validate_crcs=True).iter_messages():
            if channel.topic in topics:
                logged.add((channel.topic, msg.log_time, bytes(msg.data)))
    for topic, ts, data in got:
        assert (topic, ts, data) in logged, f"{topic} at {ts} is not in the log"

    # The transforms are the states' positions at that tick.
    states = {}
    epoch = epoch_ns(log)
    for ts, data in by_topic["/copters/state"]:
        s = CopterState.FromString(data)
        assert ts == epoch + s.tick * 50_000_000, "log time is the tick's"
        states[(ts, s.copter)] = s
    checked = 0
    for ts, data in by_topic["/tf"]:
        tf = FrameTransform.FromString(data)
        assert tf.timestamp.ToNanoseconds() == ts
        s = states.get((ts, tf.child_frame_id))
        if s is None:
            continue
        t = tf.translation
        assert [t.x, t.y, t.z] == pytest.approx(list(s.pos_m), abs=1e-6)
        assert [tf.rotation.x, tf.rotation.y, tf.rotation.z, tf.rotation.w] == pytest.approx(list(s.quat_xyzw), abs=1e-6)
        checked += 1
    assert checked >= 20 * 4
    # The copters' scene: one entity per copter, in its frame, at the message's time.
    for ts, data in by_topic["/scene/copters"]:
        scene = SceneUpdate.FromString(data)
        assert {e.frame_id for e in scene.entities} == {name for _ts, name in states}
        assert all(e.timestamp.ToNanoseconds() == ts and len(e.cylinders) == 4 for e in scene.entities)


def test_bad_clients_get_errors_and_are_counted(twinswarm_bin):
    port = free_tcp_port()
    proc = start_run(twinswarm_bin, port, "--duration", "6", "--no-log")

    async def status(ws):
        while True:
            m = await asyncio.wait_for(ws.recv(), 5)
            if isinstance(m, str) and json.loads(m)["op"] == "status":
                return json.loads(m)

    async def client():
        async with await connect(port) as ws:
            _info, channels = await hello(ws)
            await ws.send(json.dumps({"op": "teleport", "to": "mars"}))
            s = await status(ws)
            assert s["level"] == 2 and "unknown op" in s["message"], s
            await ws.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": 1, "channelId": 9999}]}))
            s = await status(ws)
            assert "channel 9999 does not exist" in s["message"], s
            await ws.send(b"\x01\xff\xfe garbage")
            s = await status(ws)
            assert "binary" in s["message"], s
            await ws.send("{not json")
            s = await status(ws)
            assert "not JSON" in s["message"], s
            await ws.send(json.dumps({"op": "unsubscribe", "subscriptionIds": [42]}))
            s = await status(ws)
            assert "42" in s["message"], s
            # A flood of errors closes the connection (policy violation); bounded: 200 frames.
            for _ in range(200):
                try:
                    await ws.send(json.dumps({"op": "nope"}))
                except websockets.ConnectionClosed:
                    break
            with pytest.raises(websockets.ConnectionClosed) as closed:
                while True:
                    await asyncio.wait_for(ws.recv(), 5)
            assert closed.value.rcvd is not None and closed.value.rcvd.code == 1008, closed.value
        # Without the subprotocol the handshake is refused.
        with pytest.raises(websockets.InvalidStatus):
            await websockets.connect(f"ws://127.0.0.1:{port}")
        # The server is still serving.
        async with await connect(port) as ws:
            await hello(ws)

    asyncio.run(client())
    live = finish(proc)["live"]
    assert live["protocol_errors"] >= 100, live
    assert live["clients_closed"] == 1 and live["handshakes_refused"] == 1 and live["clients"] == 2, live


def test_a_stalled_client_loses_messages_and_the_run_does_not_wait(twinswarm_bin, tmp_path):
    """100 copters for 6 s, a client subscribed to everything that stops reading: its queue
    fills, messages are dropped and counted, and the realtime run keeps its deadlines."""
    port = free_tcp_port()
    scene = tmp_path / "dense100.toml"
    gen = subprocess.run([str(twinswarm_bin), "scene", "dense", "--n", "100", "--air"], capture_output=True, text=True)
    assert gen.returncode == 0, gen.stderr
    scene.write_text(gen.stdout)
    proc = start_run(twinswarm_bin, port, scene, "--duration", "6", "--no-log")

    async def client():
        # A small read queue: the library stops reading the socket once it holds 4 frames.
        async with await connect(port, max_queue=4) as ws:
            _info, channels = await hello(ws)
            await ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                {"id": k, "channelId": ch["id"]} for k, ch in enumerate(channels.values())]}))
            await asyncio.sleep(5.5)

    asyncio.run(client())
    summary = finish(proc)
    live = summary["live"]
    assert live["messages_dropped"] > 0 and live["messages_sent"] > 0, live
    assert summary["realtime_overruns"] == 0, "the realtime run kept its deadlines"


def test_replay_serves_a_log_at_its_pace(twinswarm_bin, tmp_path):
    """`replay FILE --no-bus --foxglove`: every channel of the file with its schema, the
    messages' bytes and timestamps as logged, at the log's pace scaled by --speed."""
    log = tmp_path / "short.mcap"
    r = subprocess.run([str(twinswarm_bin), "run", "--no-bus", "--duration", "4", "--log", str(log)],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    logged, channels_in_file = {}, {}
    with open(log, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        for schema, channel, msg in reader.iter_messages():
            channels_in_file[channel.topic] = schema.name
            logged.setdefault(channel.topic, []).append((msg.log_time, bytes(msg.data)))
    port = free_tcp_port()
    proc = subprocess.Popen(
        [str(twinswarm_bin), "replay", str(log), "--no-bus", "--foxglove", f"127.0.0.1:{port}", "--speed", "2",
         "--wait-for-subscriber", "20"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)

    async def client():
        async with await connect(port) as ws:
            info, channels = await hello(ws)
            assert info["name"] == "twinswarm replay"
            assert {t: c["schemaName"] for t, c in channels.items()} == channels_in_file
            await ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                {"id": 7, "channelId": channels["/copters/state"]["id"]}]}))
            got, t_first, t_last = [], None, None
            while True:
                try:
                    m = await asyncio.wait_for(ws.recv(), 10)
                except websockets.ConnectionClosed:
                    break
                if isinstance(m, bytes) and m[0] == 1:
                    sid, ts = struct.unpack_from("<IQ", m, 1)
                    assert sid == 7
                    got.append((ts, m[13:]))
                    t_last = time.monotonic()
                    t_first = t_first or t_last
            return got, t_last - t_first

    got, span_s = asyncio.run(client())
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, err
    assert got == logged["/copters/state"], "every state, in order, as logged"
    log_span_s = (got[-1][0] - got[0][0]) / 1e9
    assert span_s == pytest.approx(log_span_s / 2, abs=0.5), "served at twice the log's pace"
    assert "live view:" in out and "protocol errors" in out, out
